// The covslam dashboard: one map at a time, loaded over REST, then followed live
// through the map's event stream (SSE), resumed from the last event id after a drop.
//
// Data flow: open the stream first (it only sends events newer than its start),
// then load the REST state, then apply the buffered events newer than that state.
// Frame events extend trajectories and time plots at once; landmark and coverage
// state (covariances change with every frame) is re-read at a bounded rate.

import { MapView, ROBOT_COLOURS, clusterColour, ellipse2 } from "./mapview.js";
import { linePlot } from "./plots.js";

const API = new URL("../v1/", window.location.href);
const REMOVALS_LIMIT = 2000; // removals fetched (the latest) for the removal log
const TABLE_ROWS = 300; // removal-log rows rendered (the latest)
const SERIES_MAX = 6000; // time-plot points kept (older ones thinned)
const STATS_POINTS = 500; // time-plot points per robot asked of /trajectory
const ELLIPSES_PER_ROBOT = 25; // 2σ pose ellipses per robot (at least 10 frames apart)
const REFRESH_MIN_MS = 1200; // landmarks/coverage/pose re-read at most this often
const TRAJECTORY_REFRESH_MS = 15000; // smoothed trajectories re-read at most this often

const $ = (id) => document.getElementById(id);
const app = $("app");
const view = new MapView($("map"));

let state = null;
let placesAvailable = null; // null: not yet known; from the OpenAPI schema

function freshState(mapId) {
  return {
    mapId, generation: (state?.generation ?? 0) + 1, source: null, lastEventId: null,
    loading: true, reconnecting: false, buffer: [], retryMs: 1000, retryTimer: 0, refreshTimer: 0, refreshing: false,
    refreshAgain: false, lastRefresh: 0, refreshCost: 0, lastTrajectoryLoad: 0, statsEvery: 1, ellipseFrames: 10,
    landmarks: [], clusters: [], grid: null, removals: [], removalCount: 0, archived: [],
    trajectories: {}, ellipses: [], lastEllipse: {}, series: [], lastFrame: 0, uncapped: 0,
    knownLabels: new Set(),
    robots: [], localisation: {}, places: [], transitions: [], summary: null,
  };
}

function robotColour(robot) {
  let i = state ? state.robots.indexOf(robot) : -1;
  if (i < 0 && state) {
    state.robots.push(robot);
    i = state.robots.length - 1;
  }
  return ROBOT_COLOURS[Math.max(i, 0) % ROBOT_COLOURS.length];
}

// ------------------------------------------------------------------ HTTP
class HttpError extends Error {
  constructor(status, detail) {
    super(`${status}: ${detail}`);
    this.status = status;
  }
}

// ------------------------------------------------------------------ API key
// With auth on, every request carries the key the user entered once (sessionStorage:
// this tab only, gone when it closes). EventSource cannot set headers: the event
// stream takes the key as its access_token query parameter.
const KEY_ITEM = "covslam.apiKey";
const apiKey = () => sessionStorage.getItem(KEY_ITEM);

function authHeaders() {
  const key = apiKey();
  return key ? { Authorization: `Bearer ${key}` } : {};
}

function askForKey(message) {
  const form = $("key-form");
  form.hidden = false;
  app.dataset.state = "key";
  $("summary").textContent = message;
  $("key-input").focus();
}

$("key-form").addEventListener("submit", (e) => {
  e.preventDefault();
  sessionStorage.setItem(KEY_ITEM, $("key-input").value.trim());
  $("key-input").value = "";
  $("key-form").hidden = true;
  start();
});

async function getJSON(path) {
  const r = await fetch(new URL(path, API), {
    headers: { Accept: "application/json", ...authHeaders() },
  });
  if (!r.ok) {
    let detail = r.statusText;
    try {
      detail = (await r.json()).detail ?? detail;
    } catch {
      /* not problem+json */
    }
    throw new HttpError(r.status, detail);
  }
  return r.json();
}

/** Whether this server implements GET places (a 501 stub documents its 501). */
async function placesImplemented() {
  if (placesAvailable !== null) return placesAvailable;
  try {
    const r = await fetch(new URL("../openapi.json", API));
    const schema = await r.json();
    const responses = schema.paths?.["/v1/maps/{map_id}/places"]?.get?.responses ?? {};
    placesAvailable = Object.keys(responses).length > 0 && !("501" in responses);
  } catch {
    placesAvailable = false;
  }
  return placesAvailable;
}

/** Places and transitions from GET places, tolerant of field names. */
function parsePlaces(body) {
  const list = Array.isArray(body) ? body : body?.places ?? [];
  const places = list.map((p) => {
    const pose = p.reference_pose ?? p.pose ?? p.reference ?? p;
    return {
      id: p.id ?? p.place ?? p.index,
      x: Number(pose.x), y: Number(pose.y),
      theta: pose.theta != null ? Number(pose.theta) : NaN,
      landmarks: Array.isArray(p.landmarks) ? p.landmarks.length : p.landmark_count ?? null,
      robot: p.robot ?? null, frame: p.frame ?? null,
    };
  }).filter((p) => Number.isFinite(p.x) && Number.isFinite(p.y));
  const raw = Array.isArray(body) ? [] : body?.transitions ?? [];
  const transitions = raw.map((t) => (Array.isArray(t)
    ? { from: t[0], to: t[1], count: null }
    : { from: t.from ?? t.source ?? t.a, to: t.to ?? t.target ?? t.b, count: t.count ?? t.n ?? null }));
  return { places, transitions };
}

// ------------------------------------------------------------------ maps
/** Every map (admin key, or auth off); a map's own key may not list them: then the
 * one map named by ?map= in the page's address. */
async function listMaps(wanted) {
  try {
    return await getJSON("maps");
  } catch (err) {
    if (err.status !== 403 || !wanted) throw err;
    const map = await getJSON(`maps/${encodeURIComponent(wanted)}`);
    return [map];
  }
}

async function loadMapList() {
  const select = $("map-select");
  const wanted = new URLSearchParams(window.location.search).get("map");
  const maps = await listMaps(wanted);
  maps.sort((a, b) => b.created - a.created);
  const current = state?.mapId ?? wanted;
  select.replaceChildren(...maps.map((m) => {
    const o = document.createElement("option");
    o.value = m.id;
    o.textContent = `${m.name} (${m.id})`;
    return o;
  }));
  if (!maps.length) {
    const o = document.createElement("option");
    o.textContent = "no maps yet";
    select.append(o);
    app.dataset.state = "empty";
    return null;
  }
  const pick = maps.some((m) => m.id === current) ? current : maps[0].id;
  select.value = pick;
  return pick;
}

$("map-select").addEventListener("change", (e) => {
  const id = e.target.value;
  const url = new URL(window.location.href);
  url.searchParams.set("map", id);
  window.history.replaceState(null, "", url);
  openMap(id);
});

// ------------------------------------------------------------------ live stream
function setConn(s, text) {
  const b = $("conn");
  b.dataset.state = s;
  b.textContent = text;
}

function connect(since) {
  const st = state;
  const url = new URL(`maps/${encodeURIComponent(st.mapId)}/events`, API);
  if (since != null) url.searchParams.set("since", since);
  if (apiKey()) url.searchParams.set("access_token", apiKey());
  const source = new EventSource(url);
  st.source = source;
  setConn("connecting", "connecting");
  const opened = new Promise((resolve) => {
    source.addEventListener("open", () => {
      if (st !== state) return;
      st.retryMs = 1000;
      setConn("live", "live");
      if (st.reconnecting && !st.loading) refresh({ trajectory: true }); // events catch up; re-read too
      st.reconnecting = false;
      resolve();
    });
    setTimeout(resolve, 4000);
  });
  for (const kind of ["frame", "landmark_added", "landmark_marginalised", "landmark_restored"]) {
    source.addEventListener(kind, (e) => {
      if (st !== state) return;
      st.lastEventId = Number(e.lastEventId);
      const ev = { kind, data: JSON.parse(e.data) };
      if (st.loading) st.buffer.push(ev);
      else handle(ev);
    });
  }
  source.addEventListener("error", () => {
    if (st !== state) return;
    st.reconnecting = true;
    if (source.readyState === EventSource.CLOSED) reconnectLater();
    else setConn("connecting", "reconnecting"); // the browser retries with Last-Event-ID
  });
  return opened;
}

function reconnectLater() {
  const st = state;
  st.source?.close();
  st.reconnecting = true;
  setConn("error", "offline, retrying");
  clearTimeout(st.retryTimer);
  st.retryTimer = setTimeout(() => {
    if (st === state) connect(st.lastEventId); // null: only new events (and a full re-read)
  }, st.retryMs);
  st.retryMs = Math.min(st.retryMs * 2, 15000);
}

// ------------------------------------------------------------------ events
function handle({ kind, data }) {
  if (kind === "frame") onFrame(data);
  else if (kind === "landmark_added") countLabel(data.label, data.frame_id);
  else if (kind === "landmark_marginalised") onRemoval(data);
  else if (kind === "landmark_restored") state.archived = state.archived.filter((g) => g.landmark_id !== data.id);
  scheduleRefresh();
  render();
}

function onFrame(r) {
  const st = state;
  if (r.frame_id <= st.lastFrame) return; // already in the REST state
  st.lastFrame = r.frame_id;
  robotColour(r.robot);
  const rows = (st.trajectories[r.robot] ??= []);
  const last = rows[rows.length - 1];
  if (!last || r.seq > last.seq) {
    rows.push({ seq: r.seq, stamp: r.stamp, x: r.pose.x, y: r.pose.y, theta: r.pose.theta });
  }
  const point = {
    frame: r.frame_id, robot: r.robot, live: r.landmarks.live, uncapped: st.uncapped,
    ms: r.timing_ms?.total,
  };
  if (r.covariance) {
    const e = ellipse2(xy(r.covariance));
    point.l1 = e.l1;
    point.l2 = e.l2;
    maybeEllipse(r.robot, rows.length - 1, r.frame_id, r.pose, r.covariance);
  }
  st.series.push(point);
  if (st.series.length > SERIES_MAX) {
    const keep = st.series.length - SERIES_MAX / 2;
    st.series = st.series.filter((_, i) => i % 2 === 0 || i >= keep);
  }
  st.localisation[r.robot] = {
    seq: r.seq, pose: r.pose, covariance: r.covariance, localisation: r.localisation,
  };
}

/**
 * The count without the cap between two trajectory loads: a label not seen before is a
 * new landmark (labels of the live landmarks and the fetched removals are known; the
 * next load replaces the estimate by the server's figure).
 */
function countLabel(label, frameId) {
  const st = state;
  if (label == null || st.knownLabels.has(String(label))) return;
  st.knownLabels.add(String(label));
  st.uncapped += 1;
  const last = st.series[st.series.length - 1];
  if (last && last.frame === frameId) last.uncapped = st.uncapped;
}

function onRemoval(doc) {
  const st = state;
  countLabel(doc.label, doc.frame_id); // initialised and removed by the same frame
  st.landmarks = st.landmarks.filter((l) => l.id !== doc.landmark_id);
  if (!st.removals.some((g) => g.landmark_id === doc.landmark_id && g.frame === doc.frame)) {
    st.removals.push(doc);
    st.removalCount += 1;
  }
  // the archive holds it now (until the next re-read brings its archived document)
  st.archived = st.archived.filter((g) => g.landmark_id !== doc.landmark_id);
  st.archived.push({ ...doc, removals: null });
}

/** A ghost: an archived landmark (GET landmarks?state=archived) as the map draws it. */
function ghost(a) {
  return {
    landmark_id: a.id, label: a.label, x: a.x, y: a.y, frame: a.removed_frame,
    policy: a.policy, reason: a.reason, removals: a.removals,
  };
}

const xy = (cov) => [[cov[0][0], cov[0][1]], [cov[1][0], cov[1][1]]];

function maybeEllipse(robot, index, frame, pose, cov) {
  const st = state;
  const prev = st.lastEllipse[robot];
  if (prev !== undefined && index - prev < st.ellipseFrames) return;
  st.lastEllipse[robot] = index;
  st.ellipses.push({ robot, x: pose.x, y: pose.y, covariance: xy(cov), index, frame });
}

// ------------------------------------------------------------------ REST state
async function loadTrajectory(st) {
  const body = await getJSON(`maps/${st.mapId}/trajectory?stats_every=${st.statsEvery}`);
  if (st !== state) return;
  const robots = body.robots;
  const series = [];
  const ellipses = [];
  const lastEllipse = {};
  let lastFrame = 0;
  let uncapped = 0;
  for (const [robot, rows] of Object.entries(robots)) {
    robotColour(robot);
    const mine = st.trajectories[robot] ?? [];
    const end = rows.length ? rows[rows.length - 1].seq : -1;
    rows.push(...mine.filter((p) => p.seq > end)); // frames that arrived while loading
    rows.forEach((p, i) => {
      if (p.frame_id == null) return;
      const e = p.covariance ? ellipse2(xy(p.covariance)) : null;
      series.push({ frame: p.frame_id, robot, live: p.live, uncapped: p.uncapped, ms: p.ms, l1: e?.l1, l2: e?.l2 });
      if (p.frame_id > lastFrame) {
        lastFrame = p.frame_id;
        uncapped = p.uncapped;
      }
      const prev = lastEllipse[robot];
      if (p.covariance && (prev === undefined || i - prev >= st.ellipseFrames)) {
        lastEllipse[robot] = i;
        ellipses.push({ robot, x: p.x, y: p.y, covariance: xy(p.covariance), index: i, frame: p.frame_id });
      }
    });
  }
  st.trajectories = robots;
  st.lastTrajectoryLoad = performance.now();
  // The stored figures up to lastFrame, then what the stream brought after it.
  series.sort((a, b) => a.frame - b.frame);
  st.series = series.concat(st.series.filter((p) => p.frame > lastFrame));
  st.ellipses = ellipses.concat(st.ellipses.filter((e) => e.frame > lastFrame));
  st.lastEllipse = lastEllipse;
  for (const e of st.ellipses) st.lastEllipse[e.robot] = Math.max(st.lastEllipse[e.robot] ?? -1, e.index);
  if (lastFrame > st.lastFrame) {
    st.lastFrame = lastFrame;
    st.uncapped = uncapped;
  }
}

async function loadState(st, { trajectory }) {
  const id = st.mapId;
  const jobs = [
    getJSON(`maps/${id}`),
    getJSON(`maps/${id}/landmarks`),
    getJSON(`maps/${id}/coverage?removals=${REMOVALS_LIMIT}`),
    getJSON(`maps/${id}/landmarks?state=archived`),
    getJSON(`maps/${id}/pose`),
    placesImplemented().then((ok) => (ok ? getJSON(`maps/${id}/places`).catch(() => null) : null)),
  ];
  const [summary, landmarks, coverage, archived, pose, places] = await Promise.all(jobs);
  if (st !== state) return;
  st.summary = summary;
  if (trajectory) {
    const perRobot = summary.counts.frames / Math.max(1, summary.counts.robots);
    st.statsEvery = Math.max(1, Math.ceil(perRobot / STATS_POINTS));
    st.ellipseFrames = Math.max(10, Math.ceil(perRobot / ELLIPSES_PER_ROBOT));
    await loadTrajectory(st);
  }
  st.landmarks = landmarks;
  st.clusters = coverage.clusters;
  st.grid = coverage.grid;
  st.removals = coverage.removals;
  st.removalCount = coverage.removal_count;
  st.archived = archived.map(ghost);
  for (const l of landmarks) st.knownLabels.add(String(l.label));
  for (const r of coverage.removals) st.knownLabels.add(String(r.label));
  for (const [robot, p] of Object.entries(pose.robots)) {
    robotColour(robot);
    const known = st.localisation[robot];
    if (!known || known.seq <= p.seq) st.localisation[robot] = p;
  }
  if (places) Object.assign(st, parsePlaces(places));
  $("layer-places").dataset.state = places ? "ok" : "unavailable";
}

function scheduleRefresh() {
  const st = state;
  if (st.refreshTimer) return;
  // At most every REFRESH_MIN_MS, and never more than a fifth of the time (a busy worker).
  const gap = Math.max(REFRESH_MIN_MS, 4 * st.refreshCost);
  const wait = Math.max(0, st.lastRefresh + gap - performance.now());
  st.refreshTimer = setTimeout(() => {
    st.refreshTimer = 0;
    if (st === state) refresh({ trajectory: performance.now() - st.lastTrajectoryLoad > TRAJECTORY_REFRESH_MS });
  }, Math.max(wait, 150));
}

async function refresh({ trajectory = false } = {}) {
  const st = state;
  if (st.refreshing) {
    st.refreshAgain = true;
    return;
  }
  st.refreshing = true;
  const t0 = performance.now();
  try {
    await loadState(st, { trajectory });
    render();
  } catch (err) {
    showError(err);
    if (err.status === 404 && st === state) {
      st.source?.close(); // the map was deleted: pick another
      state = null;
      start();
      return;
    }
  } finally {
    st.refreshing = false;
    st.lastRefresh = performance.now();
    st.refreshCost = st.lastRefresh - t0;
    if (st.refreshAgain && st === state) {
      st.refreshAgain = false;
      scheduleRefresh();
    }
  }
}

async function openMap(id) {
  if (state) {
    state.source?.close();
    clearTimeout(state.retryTimer);
    clearTimeout(state.refreshTimer);
  }
  state = freshState(id);
  const st = state;
  app.dataset.map = id;
  app.dataset.state = "loading";
  view.autoFit = true;
  try {
    await connect(null); // only events newer than this moment
    await loadState(st, { trajectory: true });
    if (st !== state) return;
    st.lastRefresh = performance.now();
    st.loading = false;
    for (const ev of st.buffer.splice(0)) handle(ev);
    drawNow(true);
    app.dataset.state = "live";
  } catch (err) {
    showError(err);
  }
}

function showError(err) {
  app.dataset.state = "error";
  $("summary").textContent = `error: ${err.message}`;
}

// ------------------------------------------------------------------ rendering
const RENDER_MIN_MS = 250; // a full redraw at most this often while events stream in
let renderTimer = 0;
let lastRender = 0;
let lastPlots = 0;

function render() {
  if (renderTimer) return;
  const wait = Math.max(0, lastRender + RENDER_MIN_MS - performance.now());
  renderTimer = setTimeout(() => {
    renderTimer = 0;
    requestAnimationFrame(() => drawNow());
  }, wait);
}

function drawNow(plots = false) {
  const st = state;
  if (!st) return;
  lastRender = performance.now();
  Object.assign(view.data, {
    landmarks: st.landmarks, grid: st.grid, trajectories: st.trajectories, poseEllipses: st.ellipses,
    places: st.places, transitions: st.transitions, robotColour,
    ghosts: st.archived.filter((g) => Number.isFinite(g.x) && Number.isFinite(g.y)),
  });
  view.flush();
  $("layer-ghosts").dataset.total = String(st.archived.length);
  app.dataset.frame = String(st.lastFrame);
  drawSummary(st);
  drawLegend(st);
  drawLocalisation(st);
  drawRemovals(st);
  if (plots || performance.now() - lastPlots > 400) {
    lastPlots = performance.now();
    drawPlots(st);
  } else {
    setTimeout(render, 450);
  }
}

function drawSummary(st) {
  const s = st.summary;
  if (!s) return;
  const t = s.timing_ms;
  $("summary").textContent = [
    `${st.lastFrame} frames`,
    `${st.landmarks.length} live landmarks (cap ${s.config.landmark_cap ?? "none"}, ${s.config.policy ?? "coverage"})`,
    `${st.removalCount} removed`,
    `${Object.keys(st.trajectories).length} robot(s)`,
    t ? `p50 ${t.p50.toFixed(1)} ms/frame` : "",
  ].filter(Boolean).join(" · ");
}

function swatch(kind, colour) {
  const shapes = {
    dot: `<circle cx="7" cy="7" r="4" fill="${colour}" stroke="#fff"/>`,
    ring: `<circle cx="7" cy="7" r="5" fill="none" stroke="${colour}" stroke-dasharray="2 2"/>`,
    ellipse: `<ellipse cx="7" cy="7" rx="6" ry="3.5" fill="none" stroke="${colour}"/>`,
    line: `<line x1="1" y1="7" x2="13" y2="7" stroke="${colour}" stroke-width="2"/>`,
    dash: `<line x1="1" y1="7" x2="13" y2="7" stroke="${colour}" stroke-width="2" stroke-dasharray="4 2"/>`,
    square: `<rect x="2" y="2" width="10" height="10" fill="${colour}"/>`,
    hatch: `<rect x="2" y="2" width="10" height="10" fill="url(#hole-hatch)" stroke="${colour}"/>`,
    place: `<rect x="3" y="3" width="8" height="8" fill="${colour}" fill-opacity="0.3" stroke="${colour}"/>`,
  };
  return `<svg width="14" height="14" aria-hidden="true">${shapes[kind]}</svg>`;
}

function drawLegend(st) {
  const clusters = new Set(st.landmarks.map((l) => l.cluster));
  const items = [
    [swatch("dot", "#1d232b"), `landmarks ${st.landmarks.length} (2σ ellipses)`],
    [[...clusters].slice(0, 6).map((c) => swatch("dot", clusterColour(c))).join(""),
      `E(X) by cluster: ${clusters.size} clusters`],
    [swatch("ring", "#8a939c"), `archived ${st.archived.length} (removed; seen again, one comes back) — hover for the reason`],
    ...Object.keys(st.trajectories).sort(byName).map((r) => [swatch("line", robotColour(r)),
      `${r} ${st.trajectories[r].length} poses`]),
    [swatch("ellipse", "#56606b"), "2σ pose ellipses"],
    [swatch("square", "rgba(26,127,55,0.35)"), "coverage"],
    [swatch("hatch", "#b42318"), `holes ${st.grid ? st.grid.holes.length : 0}`],
    [swatch("place", "#6f42c1") + swatch("dash", "#6f42c1"), $("layer-places").dataset.state === "ok"
      ? `places ${st.places.length} (reference poses), transitions ${st.transitions.length}`
      : "places: not available"],
  ];
  $("legend").innerHTML = items.map(([s, t]) => `<li>${s}${escapeHtml(t)}</li>`).join("");
}

/** Robot names in natural order: r2 before r10. */
const byName = (a, b) => a.localeCompare(b, undefined, { numeric: true });

function escapeHtml(s) {
  return String(s).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);
}

/** A table cell; `label` (the column's name) is shown beside it when rows stack (phone). */
function cell(text, cls = "", label = "") {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  if (label) td.dataset.label = label;
  return td;
}

const num = (v, digits = 3) => (v == null || !Number.isFinite(v) ? "–" : Number(v).toPrecision(digits));

function drawLocalisation(st) {
  const body = $("localisation").querySelector("tbody");
  const rows = Object.entries(st.localisation).sort(([a], [b]) => byName(a, b)).map(([robot, p]) => {
    const tr = document.createElement("tr");
    tr.dataset.robot = robot;
    const loc = p.localisation ?? {};
    const e = p.covariance ? ellipse2(xy(p.covariance)) : null;
    tr.append(
      cell(robot),
      cell(loc.status ?? "–", `status status-${loc.status}`),
      cell(loc.place ?? "–"),
      cell(loc.confidence != null ? loc.confidence.toFixed(2) : "–", "num"),
      // null while an initialising robot's filter has weighed no observation
      cell(p.pose ? `${p.pose.x.toFixed(2)}, ${p.pose.y.toFixed(2)}` : "–", "num"),
      cell(p.pose ? ((p.pose.theta * 180) / Math.PI).toFixed(0) : "–", "num"),
      cell(e ? `${e.rx.toFixed(2)}×${e.ry.toFixed(2)}` : "–", "num"),
    );
    tr.firstChild.style.color = robotColour(robot);
    return tr;
  });
  body.replaceChildren(...rows);
  $("localisation").dataset.count = String(rows.length);
}

function drawRemovals(st) {
  const body = $("removals").querySelector("tbody");
  const latest = st.removals.slice(-TABLE_ROWS).reverse();
  body.replaceChildren(...latest.map((r) => {
    const d = r.details ?? {};
    const tr = document.createElement("tr");
    tr.dataset.landmark = r.landmark_id;
    tr.append(
      cell(r.frame_id ?? r.frame, "num", "frame"),
      cell(r.landmark_id, "num", "landmark"),
      cell(r.label, "", "label"),
      cell(d.cluster ?? "–", "num", "cluster"),
      cell(num(d.cluster_spread), "num", "D"),
      cell(num(d.information), "num", "I"),
      cell(r.reason, "reason"),
    );
    return tr;
  }));
  $("removals").dataset.count = String(latest.length);
  $("removals").dataset.total = String(st.removalCount);
  $("removal-note").textContent = st.removalCount > latest.length
    ? `latest ${latest.length} of ${st.removalCount}` : `${st.removalCount} removals`;
}

function drawPlots(st) {
  const byRobot = {};
  for (const p of st.series) (byRobot[p.robot] ??= []).push(p);
  const uncertainty = [];
  for (const [robot, pts] of Object.entries(byRobot).sort(([a], [b]) => byName(a, b))) {
    const c = robotColour(robot);
    uncertainty.push({ name: robot, colour: c, points: pts.map((p) => [p.frame, p.l1]) });
    uncertainty.push({ colour: c, dash: "3 2", points: pts.map((p) => [p.frame, p.l2]) });
  }
  linePlot($("plot-uncertainty"), uncertainty, { logY: true, xLabel: "frame", yLabel: "m², dashed: smaller λ" });
  linePlot($("plot-landmarks"), [
    { name: "live", colour: "#0b5cad", points: st.series.map((p) => [p.frame, p.live]) },
    { name: "without the cap", colour: "#c2410c", dash: "5 3", points: st.series.map((p) => [p.frame, p.uncapped]) },
  ], { xLabel: "frame", yLabel: "landmarks" });
  linePlot($("plot-timing"), [
    { name: "estimator", colour: "#15803d", points: st.series.map((p) => [p.frame, p.ms]) },
  ], { logY: true, xLabel: "frame", yLabel: "ms" });
}

// ------------------------------------------------------------------ start
$("zoom-in").addEventListener("click", () => view.zoomAt(1.5, view.svg.clientWidth / 2, view.svg.clientHeight / 2));
$("zoom-out").addEventListener("click", () => view.zoomAt(1 / 1.5, view.svg.clientWidth / 2, view.svg.clientHeight / 2));
$("zoom-fit").addEventListener("click", () => {
  view.autoFit = true;
  view.redraw();
});
window.addEventListener("resize", () => render());

/** For tests and the console: the state, a forced drop of the stream, a synchronous draw. */
window.covslamDashboard = {
  get state() {
    return state;
  },
  dropConnection() {
    reconnectLater();
  },
  draw() {
    drawNow(true);
  },
  reloadMaps() {
    return loadMapList();
  },
};

async function start() {
  try {
    const id = await loadMapList();
    if (id) await openMap(id);
    else setTimeout(start, 5000);
  } catch (err) {
    if (err.status === 401) {
      askForKey(apiKey() ? "that key is not valid: enter an API key" : "enter an API key");
      return;
    }
    if (err.status === 403 && !new URLSearchParams(window.location.search).get("map")) {
      askForKey("this key reaches one map: open /dashboard/?map=<id>, or enter the admin key");
      return;
    }
    showError(err);
    setTimeout(start, 5000);
  }
}

setInterval(() => {
  if (state) loadMapList().catch(() => {});
}, 30000);

start();
