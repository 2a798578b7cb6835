"""The dashboard against a real `covslam serve`: its files over HTTP, the frame figures
it reads from /trajectory, and the page itself in headless Chromium (Playwright).

The browser is Debian's `chromium` (`.ci/run` installs it); Playwright never downloads
one. Without it the browser test is skipped and says why. Screenshots are written to
`tmp/artefacts/` (gitignored) for a human to look at.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from tests.e2e.conftest import REPO, Server, create_map, frame_dicts, post_all, sim_frames

ARTEFACTS = REPO / "tmp" / "artefacts"
FRAMES = frame_dicts(sim_frames(80, seed=3))


def test_dashboard_files_are_served(client: httpx.Client) -> None:
    r = client.get("/dashboard", follow_redirects=False)
    assert r.status_code in (307, 308) and r.headers["location"].endswith("/dashboard/")
    page = client.get("/dashboard/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert '<svg id="map"' in page.text and "./dashboard.js" in page.text
    for name in ("dashboard.js", "mapview.js", "plots.js"):
        js = client.get(f"/dashboard/{name}")
        assert js.status_code == 200, name
        assert "javascript" in js.headers["content-type"], js.headers["content-type"]
    assert client.get("/dashboard/dashboard.css").headers["content-type"].startswith("text/css")
    assert client.get("/dashboard/nothing.js").status_code == 404


def test_trajectory_stats_over_http_match_the_frame_results(client: httpx.Client) -> None:
    map_id = create_map(client, "stats", config={"landmark_cap": 6})
    results = post_all(client, map_id, FRAMES[:30])
    plain = client.get(f"/v1/maps/{map_id}/trajectory").json()["robots"]["r1"]
    assert set(plain[0]) == {"seq", "stamp", "x", "y", "theta"}  # unchanged without the flag
    rows = client.get(f"/v1/maps/{map_id}/trajectory", params={"stats_every": 4}).json()
    rows = rows["robots"]["r1"]
    picked = [i for i, p in enumerate(rows) if "frame_id" in p]
    assert picked == [*range(0, 30, 4), 29]
    coverage = client.get(f"/v1/maps/{map_id}/coverage", params={"removals": 1000}).json()
    label = {r["landmark_id"]: r["label"] for r in coverage["removals"]}
    label.update(
        {lm["id"]: lm["label"] for lm in client.get(f"/v1/maps/{map_id}/landmarks").json()}
    )
    ids: set[int] = set()
    for i, (point, result) in enumerate(zip(rows, results, strict=True)):
        ids.update(result["landmarks"]["added"], result["landmarks"]["marginalised"])
        if i not in picked:
            continue
        assert point["frame_id"] == result["frame_id"]
        assert point["covariance"] == result["covariance"]
        assert point["ms"] == result["timing_ms"]["total"]
        assert point["uncapped"] == len({label[lid] for lid in ids})
    bad = client.get(f"/v1/maps/{map_id}/trajectory", params={"stats_every": -1})
    assert bad.status_code == 422
    schema = client.get("/openapi.json").json()
    params = schema["paths"]["/v1/maps/{map_id}/trajectory"]["get"]["parameters"]
    assert any(p["name"] == "stats_every" for p in params)


# --------------------------------------------------------------------------- browser


def _layers(page: Any) -> dict[str, dict[str, str]]:
    """Every element with an id and data attributes: {id: dataset}."""
    return page.evaluate(
        "() => Object.fromEntries([...document.querySelectorAll('[id]')]"
        ".filter(e => Object.keys(e.dataset).length).map(e => [e.id, {...e.dataset}]))"
    )


def _rest(client: httpx.Client, map_id: str) -> dict[str, Any]:
    landmarks = client.get(f"/v1/maps/{map_id}/landmarks").json()
    coverage = client.get(f"/v1/maps/{map_id}/coverage", params={"removals": 2000}).json()
    trajectory = client.get(f"/v1/maps/{map_id}/trajectory").json()["robots"]
    return {
        "landmarks": len(landmarks),
        "clusters": len({lm["cluster"] for lm in landmarks}),
        "nonempty_clusters": sum(1 for c in coverage["clusters"] if c["members"]),
        "ghosts": len(client.get(f"/v1/maps/{map_id}/landmarks?state=archived").json()),
        "removals": coverage["removal_count"],
        "points": sum(len(rows) for rows in trajectory.values()),
        "cells": coverage["grid"]["explored_cells"],
        "holes": len(coverage["grid"]["holes"]),
        "pose": client.get(f"/v1/maps/{map_id}/pose").json()["robots"],
        "places": client.get(f"/v1/maps/{map_id}/places"),
    }


def _wait_for(page: Any, layer: str, key: str, value: int, timeout_s: float = 20) -> None:
    page.wait_for_function(
        "([id, key, want]) => document.getElementById(id)?.dataset[key] === String(want)",
        arg=[layer, key, value],
        timeout=timeout_s * 1e3,
    )


def _check_map_conventions(page: Any, landmarks: list[dict[str, Any]]) -> None:
    """Metres in the map frame: +y is up on screen, +x right; ellipses are 2σ."""
    dots = {
        int(d["id"]): (float(d["cx"]), float(d["cy"]))
        for d in page.evaluate(
            "() => [...document.querySelectorAll('#layer-landmarks circle')]"
            ".map(c => ({id: c.dataset.id, cx: c.getAttribute('cx'), cy: c.getAttribute('cy')}))"
        )
    }
    lo_y, hi_y = min(landmarks, key=lambda lm: lm["y"]), max(landmarks, key=lambda lm: lm["y"])
    lo_x, hi_x = min(landmarks, key=lambda lm: lm["x"]), max(landmarks, key=lambda lm: lm["x"])
    assert dots[hi_y["id"]][1] < dots[lo_y["id"]][1]  # north is up
    assert dots[hi_x["id"]][0] > dots[lo_x["id"]][0]  # east is right
    for lm in landmarks:
        rx, ry = page.evaluate(
            "id => { const e = document.querySelector(`#layer-landmark-ellipses "
            "ellipse[data-id='${id}']`); return [Number(e.getAttribute('rx')), "
            "Number(e.getAttribute('ry'))] }",
            lm["id"],
        )
        eig = np.linalg.eigvalsh(np.asarray(lm["covariance"]))  # ascending, m²
        assert rx == pytest.approx(2 * np.sqrt(eig[1]), rel=1e-6)
        assert ry == pytest.approx(2 * np.sqrt(max(eig[0], 0.0)), rel=1e-6, abs=1e-12)


def test_dashboard_in_chromium_shows_the_map_and_follows_it_live(
    browser: Any, server: Server, client: httpx.Client
) -> None:
    t0 = time.monotonic()
    map_id = create_map(client, "dashboard", config={"landmark_cap": 6})
    post_all(client, map_id, FRAMES[:60])

    page = browser.new_page(viewport={"width": 1280, "height": 800})
    problems: list[str] = []
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.goto(f"{server.url}/dashboard?map={map_id}")
    _wait_for(page, "app", "state", "live")
    _wait_for(page, "app", "frame", 60)
    rest = _rest(client, map_id)
    assert rest["ghosts"] > 0 and rest["landmarks"] == 6  # the cap bit: there are ghosts

    shown = _layers(page)
    assert int(shown["layer-landmarks"]["count"]) == rest["landmarks"]
    assert page.locator("#layer-landmarks circle.landmark").count() == rest["landmarks"]
    assert page.locator("#layer-landmark-ellipses ellipse").count() == rest["landmarks"]
    assert int(shown["layer-observed"]["count"]) == rest["landmarks"]
    assert int(shown["layer-observed"]["clusters"]) == rest["clusters"]
    assert rest["clusters"] == rest["nonempty_clusters"]
    assert int(shown["layer-ghosts"]["count"]) == rest["ghosts"]
    assert page.locator("#layer-ghosts circle.ghost title").count() == rest["ghosts"]
    assert "marginalised landmark" in page.locator("#layer-ghosts title").first.text_content()
    assert int(shown["layer-trajectories"]["points"]) == rest["points"] == 60
    assert int(shown["layer-pose-ellipses"]["count"]) >= 2
    assert int(shown["layer-coverage"]["cells"]) == rest["cells"] > 0
    assert int(shown["layer-coverage"]["holes"]) == rest["holes"]
    assert int(shown["removals"]["count"]) == rest["removals"]
    # 60 frames, each with a covariance: two eigenvalues each, and one time
    assert int(shown["plot-uncertainty"]["points"]) == 2 * 60
    assert int(shown["plot-timing"]["points"]) == 60
    status = rest["pose"]["r1"]["localisation"]["status"]
    assert page.locator("#localisation tr[data-robot='r1'] .status").inner_text() == status
    _check_map_conventions(page, client.get(f"/v1/maps/{map_id}/landmarks").json())
    if rest["places"].status_code == 501:  # not implemented on this server: an empty layer
        assert shown["layer-places"] == {"count": "0", "transitions": "0", "state": "unavailable"}
    else:
        body = rest["places"].json()
        assert int(shown["layer-places"]["count"]) == len(body.get("places", body))

    # A frame posted now appears without a reload, and the rest follows within a refresh.
    page.evaluate("window.__same_page = true")
    post_all(client, map_id, FRAMES[60:70])
    _wait_for(page, "app", "frame", 70)
    assert int(_layers(page)["layer-trajectories"]["points"]) == 70
    after = _rest(client, map_id)
    _wait_for(page, "layer-ghosts", "count", after["ghosts"])
    _wait_for(page, "layer-landmarks", "count", after["landmarks"])
    _wait_for(page, "layer-observed", "clusters", after["clusters"])

    # The stream drops; frames posted meanwhile arrive after the reconnect.
    page.evaluate("window.covslamDashboard.dropConnection()")
    post_all(client, map_id, FRAMES[70:80])
    _wait_for(page, "app", "frame", 80)
    _wait_for(page, "conn", "state", "live")
    _wait_for(page, "layer-trajectories", "points", 80)
    assert page.evaluate("window.__same_page") is True

    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    page.evaluate("window.covslamDashboard.draw()")
    page.screenshot(path=str(ARTEFACTS / "dashboard-1280x800.png"))
    page.set_viewport_size({"width": 390, "height": 844})  # a phone
    page.evaluate("window.covslamDashboard.draw()")
    assert page.evaluate("document.documentElement.scrollWidth") <= 390
    assert page.locator("#map").bounding_box()["width"] <= 390
    page.screenshot(path=str(ARTEFACTS / "dashboard-phone.png"), full_page=True)
    page.close()
    assert problems == []
    assert time.monotonic() - t0 < 60


def _world_scale(page: Any) -> float:
    """Pixels per metre of the map view (the #world transform is matrix(s,0,0,-s,tx,ty))."""
    transform = page.get_attribute("#world", "transform")
    return float(transform.split("(")[1].split(",")[0])


def _dot(page: Any, layer: str, landmark: int) -> tuple[float, float]:
    c = page.locator(f"#{layer} circle[data-id='{landmark}']")
    return float(c.get_attribute("cx")), float(c.get_attribute("cy"))


def _texts_outside(page: Any) -> list[str]:
    """Axis and plot labels that run past the edge of their SVG (cut off on screen)."""
    return page.evaluate(
        """() => [...document.querySelectorAll('svg.plot, svg#map')].flatMap(svg => {
          const w = svg.clientWidth, h = svg.clientHeight;
          const texts = svg.id === 'map' ? svg.querySelectorAll('#axes text')
                                         : svg.querySelectorAll('text');
          return [...texts].filter(t => {
            const b = t.getBBox();
            return b.x < -0.5 || b.y < -0.5 || b.x + b.width > w + 0.5 || b.y + b.height > h + 0.5;
          }).map(t => `${svg.id}: ${t.textContent}`);
        })"""
    )


def _low_contrast(page: Any) -> list[str]:
    """Text whose colour has less than WCAG AA contrast (4.5:1) with the background it
    sits on (HTML text and SVG labels; the nearest ancestor with a background)."""
    return page.evaluate(
        """() => {
          const rgb = (c) => (c.match(/[\\d.]+/g) || []).map(Number);
          const lum = ([r, g, b]) => {
            const f = (v) => (v / 255 <= 0.03928 ? v / 255 / 12.92
                                                   : ((v / 255 + 0.055) / 1.055) ** 2.4);
            return 0.2126 * f(r) + 0.7152 * f(g) + 0.0722 * f(b);
          };
          const background = (el) => {
            for (let e = el; e; e = e.parentElement) {
              const c = rgb(getComputedStyle(e).backgroundColor);
              if (c.length >= 3 && (c.length < 4 || c[3] > 0.5)) return c;
            }
            return [255, 255, 255];
          };
          const bad = [];
          const texts = [...document.querySelectorAll('#app *')].filter((e) =>
            [...e.childNodes].some((n) => n.nodeType === 3 && n.textContent.trim())
            && e.getClientRects().length && e.closest('title') === null && e.tagName !== 'title');
          for (const e of texts) {
            const st = getComputedStyle(e);
            const fg = rgb(e instanceof SVGElement ? st.fill : st.color);
            if (fg.length < 3) continue;
            const [a, b] = [lum(fg), lum(background(e))].sort((x, y) => y - x);
            const ratio = (a + 0.05) / (b + 0.05);
            if (ratio < 4.5) bad.push(`${e.tagName}.${e.className.baseVal ?? e.className}` +
              ` "${e.textContent.trim().slice(0, 30)}": ${ratio.toFixed(2)}`);
          }
          return bad;
        }"""
    )


def _renamed(frames: list[dict[str, Any]], robot: str) -> list[dict[str, Any]]:
    return [{**f, "robot": robot} for f in frames]


def test_dashboard_two_robots_pan_zoom_and_phone_layout(
    browser: Any, server: Server, client: httpx.Client
) -> None:
    """Two robots (named so that a plain sort would misorder them: r2 < r10), pan and
    zoom that keep metres on the axes and survive live updates, places drawn from
    GET places, and a phone-width page whose tables fit without sideways scrolling."""
    map_id = create_map(client, "two robots", config={"landmark_cap": 6})
    r10, r2 = _renamed(FRAMES[:40], "r10"), _renamed(FRAMES[:41], "r2")
    results = post_all(client, map_id, [f for pair in zip(r10, r2[:40], strict=True) for f in pair])
    reported = {r["robot"]: r["localisation"] for r in results}  # each robot's last

    page = browser.new_page(viewport={"width": 1280, "height": 800})
    problems: list[str] = []
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.goto(f"{server.url}/dashboard/?map={map_id}")
    _wait_for(page, "app", "state", "live")
    _wait_for(page, "app", "frame", 80)
    rest = _rest(client, map_id)
    shown = _layers(page)

    # the status table and the legends list robots in natural order
    assert page.eval_on_selector_all(
        "#localisation tbody tr", "rows => rows.map(r => r.dataset.robot)"
    ) == ["r2", "r10"]
    assert int(shown["layer-trajectories"]["robots"]) == 2
    # status, place and confidence as the robot's last frame result said, over REST too
    assert {r: p["localisation"] for r, p in rest["pose"].items()} == reported
    assert any(loc["place"] is not None for loc in reported.values())
    for robot, loc in reported.items():
        row = page.locator(f"#localisation tr[data-robot='{robot}'] td")
        place = "–" if loc["place"] is None else str(loc["place"])
        assert row.nth(1).inner_text() == loc["status"] and row.nth(2).inner_text() == place
    assert int(shown["plot-uncertainty"]["series"]) == 4  # two eigenvalues per robot
    assert page.eval_on_selector_all(
        "#plot-uncertainty path[data-name^='r']", "ps => ps.map(p => p.dataset.name)"
    ) == ["r2", "r10"]

    # places from GET places: markers, headings of reference poses, labels while few
    places = rest["places"].json()
    assert shown["layer-places"]["state"] == "ok"
    assert int(shown["layer-places"]["count"]) == len(places["places"])
    assert int(shown["layer-places"]["transitions"]) == len(places["transitions"])
    if 0 < len(places["places"]) <= 12:
        assert int(shown["layer-places"]["labels"]) == len(places["places"])
    assert int(shown["layer-transitions"]["count"]) == len(places["transitions"])
    robot_colours = {
        page.get_attribute(f"#layer-trajectories polyline[data-robot='{r}']", "stroke")
        for r in ("r2", "r10")
    }
    assert len(robot_colours) == 2 and "#6f42c1" not in robot_colours  # violet = places

    # holes: hatched (readable without colour vision), as many as REST says
    assert int(shown["layer-coverage"]["holes"]) == rest["holes"]
    if rest["holes"]:
        fill = page.eval_on_selector("#layer-coverage rect.hole", "r => getComputedStyle(r).fill")
        assert "hole-hatch" in fill

    assert _texts_outside(page) == []
    assert _low_contrast(page) == []

    # metres on the axes
    axis_text = page.eval_on_selector_all("#axes text", "ts => ts.map(t => t.textContent)")
    assert "x [m]" in axis_text and "y [m]" in axis_text

    # zoom with the wheel about the cursor: the landmark under it stays put
    landmarks = client.get(f"/v1/maps/{map_id}/landmarks").json()
    a, b = landmarks[0]["id"], landmarks[-1]["id"]
    s0 = _world_scale(page)
    box = page.locator("#map").bounding_box()
    ax, ay = _dot(page, "layer-landmarks", a)
    bx, by = _dot(page, "layer-landmarks", b)
    page.mouse.move(box["x"] + ax, box["y"] + ay)
    page.mouse.wheel(0, -400)
    page.wait_for_function(
        "s => !document.getElementById('world')"
        ".getAttribute('transform').startsWith(`matrix(${s},`)",
        arg=s0,
    )
    s1 = _world_scale(page)
    assert s1 > 1.5 * s0
    ax1, ay1 = _dot(page, "layer-landmarks", a)
    assert (ax1, ay1) == pytest.approx((ax, ay), abs=1.5)
    bx1, by1 = _dot(page, "layer-landmarks", b)
    assert (bx1 - ax1, by1 - ay1) == pytest.approx(
        ((bx - ax) * s1 / s0, (by - ay) * s1 / s0), abs=1.5
    )

    # pan by dragging: everything moves with the pointer
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] / 2 + 60, box["y"] + box["height"] / 2 + 40, steps=5)
    page.mouse.up()
    page.wait_for_function(
        "([id, x]) => Math.abs(Number(document.querySelector("
        "`#layer-landmarks circle[data-id='${id}']`).getAttribute('cx')) - x) > 30",
        arg=[a, ax1],
    )
    ax2, ay2 = _dot(page, "layer-landmarks", a)
    assert (ax2 - ax1, ay2 - ay1) == pytest.approx((60, 40), abs=1.5)
    assert _world_scale(page) == pytest.approx(s1)

    # a live frame does not undo the user's view
    transform = page.get_attribute("#world", "transform")
    post_all(client, map_id, [r2[40]])
    _wait_for(page, "app", "frame", 81)
    page.evaluate("window.covslamDashboard.draw()")
    assert page.get_attribute("#world", "transform") == transform
    page.click("#zoom-fit")
    page.wait_for_function(
        "t => document.getElementById('world').getAttribute('transform') !== t", arg=transform
    )
    assert _world_scale(page) == pytest.approx(s0, rel=0.05)

    # phone width: nothing wider than the screen; removal rows stack with their labels
    page.set_viewport_size({"width": 390, "height": 844})
    page.evaluate("window.covslamDashboard.draw()")
    assert page.evaluate("document.documentElement.scrollWidth") <= 390
    assert _texts_outside(page) == []
    for table in ("#localisation", "#removals"):
        fits = page.eval_on_selector(table, "t => t.scrollWidth <= t.parentElement.clientWidth + 1")
        assert fits, table
    if rest["removals"]:
        assert (
            page.eval_on_selector("#removals thead", "h => getComputedStyle(h).display") == "none"
        )
        labels = page.eval_on_selector_all(
            "#removals tbody tr:first-child td[data-label]", "ts => ts.map(t => t.dataset.label)"
        )
        assert labels == ["frame", "landmark", "label", "cluster", "D", "I"]
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTEFACTS / "dashboard-two-robots-phone.png"), full_page=True)
    page.close()
    assert problems == []


def test_dashboard_catches_up_after_the_server_restarts(browser: Any, tmp_path: Path) -> None:
    """A real drop of the stream: the service is killed (-9) and started again on the
    same port; frames posted after the restart reach the open page without a reload,
    and the map selector switches to a map created meanwhile."""
    srv = Server(tmp_path / "data", workers=1)
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            map_id = create_map(c, "restart", config={"landmark_cap": 6})
            post_all(c, map_id, FRAMES[:30])
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        problems: list[str] = []
        page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
        page.goto(f"{srv.url}/dashboard/?map={map_id}")
        _wait_for(page, "app", "frame", 30)
        page.evaluate("window.__same_page = true")

        srv.kill9()
        page.wait_for_function(  # the badge no longer says live
            "() => document.getElementById('conn').dataset.state !== 'live'", timeout=30e3
        )
        srv.start()
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            post_all(c, map_id, FRAMES[30:45])
            other = create_map(c, "made while the page was open", config={"landmark_cap": 4})
            post_all(c, other, FRAMES[:12])
            rest = _rest(c, map_id)
        _wait_for(page, "app", "frame", 45, timeout_s=40)
        _wait_for(page, "conn", "state", "live")
        _wait_for(page, "layer-trajectories", "points", 45)
        _wait_for(page, "layer-ghosts", "count", rest["ghosts"])
        _wait_for(page, "layer-landmarks", "count", rest["landmarks"])
        assert page.evaluate("window.__same_page") is True

        # the selector lists the new map (re-read every 30 s, or on demand) and opens it
        page.evaluate("window.covslamDashboard.reloadMaps()")
        page.wait_for_function(
            "id => [...document.querySelectorAll('#map-select option')].some(o => o.value === id)",
            arg=other,
        )
        page.select_option("#map-select", other)
        _wait_for(page, "app", "map", other)
        _wait_for(page, "app", "frame", 12)
        _wait_for(page, "layer-trajectories", "points", 12)
        assert f"map={other}" in page.url
        page.close()
        # Console errors are expected here (refused connections while the server was
        # down); uncaught exceptions are not.
        assert problems == []
    finally:
        srv.stop()


def _transform(page: Any) -> tuple[float, float, float]:
    """(s, tx, ty) of the #world transform matrix(s,0,0,-s,tx,ty): screen = s*x + tx."""
    t = page.get_attribute("#world", "transform")
    a = [float(v) for v in t[t.index("(") + 1 : -1].split(",")]
    return a[0], a[4], a[5]


def test_dashboard_pinch_zoom_and_touch_pan_on_a_phone(
    browser: Any, server: Server, client: httpx.Client
) -> None:
    """A touch screen at phone width: two fingers zoom about their midpoint, one finger
    pans the map (not the page)."""
    map_id = create_map(client, "touch", config={"landmark_cap": 6})
    post_all(client, map_id, FRAMES[:30])
    context = browser.new_context(
        viewport={"width": 390, "height": 844}, has_touch=True, is_mobile=True
    )
    page = context.new_page()
    problems: list[str] = []
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.goto(f"{server.url}/dashboard/?map={map_id}")
    _wait_for(page, "app", "frame", 30)
    cdp = context.new_cdp_session(page)

    def touch(kind: str, points: list[tuple[float, float]]) -> None:
        cdp.send(
            "Input.dispatchTouchEvent",
            {
                "type": kind,
                "touchPoints": [{"x": x, "y": y, "id": i} for i, (x, y) in enumerate(points)],
            },
        )

    box = page.locator("#map").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.evaluate("window.covslamDashboard.draw()")  # the layout settled before measuring
    box = page.locator("#map").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    s0, tx0, ty0 = _transform(page)
    # the SVG's own coordinates start inside its border
    ox, oy = page.eval_on_selector(
        "#map",
        "m => [m.getBoundingClientRect().left + m.clientLeft, "
        "m.getBoundingClientRect().top + m.clientTop]",
    )
    world = ((cx - ox - tx0) / s0, (cy - oy - ty0) / -s0)  # under the fingers' midpoint
    touch("touchStart", [(cx - 20, cy), (cx + 20, cy)])
    for d in range(25, 101, 5):
        touch("touchMove", [(cx - d, cy), (cx + d, cy)])
    touch("touchEnd", [])
    page.wait_for_function(
        "s => !document.getElementById('world').getAttribute('transform')"
        ".startsWith(`matrix(${s},`)",
        arg=s0,
    )
    s1, tx1, ty1 = _transform(page)
    assert s1 > 2.5 * s0  # fingers 40 px -> 200 px apart
    after = page.locator("#map").bounding_box()
    assert (after["x"], after["y"]) == pytest.approx((box["x"], box["y"]), abs=0.5)  # no scroll
    assert (world[0] * s1 + tx1, -world[1] * s1 + ty1) == pytest.approx((cx - ox, cy - oy), abs=1)

    scroll = page.evaluate("window.scrollY")
    touch("touchStart", [(cx, cy)])
    for d in range(0, 61, 10):
        touch("touchMove", [(cx + d, cy + d)])
    touch("touchEnd", [])
    page.wait_for_function(
        "tx => Math.abs(Number(document.getElementById('world').getAttribute('transform')"
        ".split(',')[4]) - tx) > 30",
        arg=tx1,
    )
    s2, tx2, ty2 = _transform(page)
    assert (s2, tx2 - tx1, ty2 - ty1) == pytest.approx((s1, 60, 60), abs=1.5)
    assert page.evaluate("window.scrollY") == scroll  # the map took the gesture
    context.close()
    assert problems == []
