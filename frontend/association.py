"""Data association: which feature of this frame is which landmark, or which track.

`Associator` is a small stateful object that lives next to one map's estimator.
Per frame:

1. `associate(features, robot=..., predicted_pose=..., pose_cov=..., landmarks=...)`
   matches features to live landmarks: for each landmark the bearing predicted
   from the pose estimate gates the features (gate from the pose's and the
   landmark's covariance and the feature's sigma), then the descriptor distance
   (the smallest over the landmark's stored views) with a ratio test against the
   second-best feature in the gate, and against the second-best landmark for the
   feature. A landmark gets at most one feature and a feature at most one
   landmark. Remaining features are matched frame to frame to the robot's
   candidate tracks: the gate is the arc of bearings the track's last ray can
   project to from the predicted pose (any depth in `track_depth_m`), plus the
   elevation. Each observation carries the landmark's or the track's label; a
   track is reported once it has been seen `track_min_length` times, or from its first
   sighting when the robot had no tracks (`report_when_trackless`).
2. `commit(association, pose=..., live_labels=...)` after the estimator processed
   the frame: stores new views of matched landmarks, extends, starts and ends
   tracks, promotes tracks whose label became a landmark, and moves the views of
   landmarks that are no longer live (marginalised) to its archive.

The archive of views: a landmark the estimator removed keeps its descriptor views
here, under its label, for the place localiser (a robot that does not know where it
is matches its features to live and archived landmarks alike: `match_without_pose`,
and `associate` when given archived positions). The graph's own association is
given live landmarks only, so an archived label never comes back into the graph.
It grows with distinct landmarks, as the estimator's archive does.

Labels of new tracks are ``f"{label_prefix}{n:06d}"`` with n counting up; a label
is never reused.

Convention: poses are (x, y, theta) in the map frame (m, m, rad CCW from +x);
`pose_cov` is the (3, 3) covariance of (x, y, theta) with x, y in the map frame;
landmark positions (2,) in metres with (2, 2) covariances in the map frame;
bearings as in graph.types (rad, CCW from forward, wrapped to (-pi, pi]).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontend.features import Features
from frontend.global_match import match_without_pose
from graph.angles import wrap_angles
from graph.types import BearingObservation

__all__ = ["Association", "AssociationConfig", "Associator", "LandmarkEstimate"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

LandmarkEstimate = tuple[ArrayLike, ArrayLike | None]
"""(xy (2,), covariance (2, 2) or None) of one live landmark, map frame, metres."""

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.int32)


@dataclass(frozen=True, slots=True)
class AssociationConfig:
    """Association parameters; angles in radians."""

    gate_sigmas: float = 2.5
    """Bearing gate half-width in predicted standard deviations."""
    min_gate_rad: float = math.radians(0.5)
    max_gate_rad: float = math.radians(5.0)
    default_landmark_sigma_m: float = 0.1
    """Landmark position sigma used when no covariance is given (a prior: see
    `learn_landmark_sigma`)."""
    no_tracks_from_contested: bool = True
    """Features inside a live landmark's gate and within max_distance of its views, that
    no landmark took, start no track (duplicate landmarks of one corner filled the cap:
    1816 landmarks for 394 corners on a 1000-frame rendered run)."""
    learn_landmark_sigma: bool = True
    """Without covariances, gate each landmark with a position sigma learnt from its own
    matches: the RMS of their lateral errors (bearing residual after the pose correction
    x range), with the default sigma as a prior worth `landmark_sigma_prior_n` matches.
    A well-matched landmark's gate shrinks from ~5 deg to ~1-2 deg, so a look-alike corner
    of the same wall a few degrees off no longer falls inside it."""
    landmark_sigma_prior_n: float = 1.0
    min_landmark_sigma_m: float = 0.005
    elevation_gate_rad: float = math.radians(1.0)
    """Elevation tolerance (plus gate_sigmas feature sigmas) of a predicted elevation."""
    max_distance: float = 45.0
    """Largest descriptor distance of a match (Hamming bits for ORB; L2 for SIFT: x5)."""
    ratio: float = 0.7
    min_matches_for_pose: int = 5
    """Landmark matches needed to correct the pose and match again (consistency check)."""
    """Best distance must be below ratio x the second best (features and landmarks)."""
    views_per_landmark: int = 5
    view_fit_sigmas: float = 2.0
    """A match adds a view (or a height sample) only if it fits within this many sigmas."""
    new_view_angle_rad: float = math.radians(10.0)
    """A matched landmark stores a new view when seen this far from all its views."""
    track_depth_m: tuple[float, float] = (0.3, 30.0)
    track_margin_rad: float = math.radians(1.0)
    """Extra gate for the relative motion error between two frames."""
    track_max_missed: int = 2
    """A track not matched for more frames than this ends."""
    track_min_length: int = 2
    """Sightings before a track is reported to the estimator (1: from its first)."""
    report_when_trackless: bool = True
    """A robot with no candidate tracks (its first frame; its tracks were just dropped at
    a re-anchoring; or it lost them all) reports every new track at its first sighting.
    The first two are the best known poses of the run (the initial pose's prior, or the
    anchor): without their rays the map hangs off the next frame's, one odometry step
    away. On rendered runs (1000 frames, cap 200) the oracle's ATE rose from 0.0050 to
    0.0184 m with its first frame's observations dropped, and that one frame was all of
    the difference between the oracle and the oracle on the front end's selection."""
    max_track_observations: int = 400
    """Most track observations reported per frame (longest tracks first). At 60 the limit
    bound on 91 % of the frames of a 1000-frame rendered run: the longest tracks kept the
    slots, and a corner was first reported a median of 10 frames after the oracle's first
    sighting. Without the limit: precision 99.60 -> 99.79 %, ATE 0.0222 -> 0.0213 m."""
    label_prefix: str = "t"
    coincident_rad: float = math.radians(0.3)
    """A feature this close in bearing to one a landmark took is the same 2-D point (the
    top and bottom corner of a vertical edge): it continues no track and starts none, so
    it does not become a second landmark on the point, taking a second place under the
    cap. Without it a third of the landmark observations of a 1000-frame rendered run
    (cap 200, `oldest`) were a second landmark's of a point already observed in the
    frame, and a landmark lived a median of 79 frames (114 with it). With the elevation
    gate below, the image map's ATE went from 0.71-2.15x the oracle's to 0.82-1.41x over
    five worlds (docs/measurements.md, "Vision front end"). 0: off."""
    landmark_elevation_gate: float = 1.0
    """A landmark with a learnt height takes features within this many elevation
    tolerances (`elevation_gate_rad` + gate_sigmas feature sigmas) of the elevation it
    predicts. At 2 (before 2026-12-03), look-alikes on other walls took over landmarks
    whose corner was out of sight: on a rendered world precision 98.81 % -> 99.33 % at 1.
    Both fields go last: older pickled snapshots lack them, and ImageFrontEnd.set_associator
    gives a restored associator the service's own config."""


@dataclass
class _Landmark:
    descriptors: list[NDArray[Any]] = field(default_factory=list)
    view_angles: list[float] = field(default_factory=list)
    """World direction from the landmark to the robot at each stored view, rad."""
    height_m: float | None = None
    """Running mean of the feature's height above the camera, metres."""
    height_n: int = 0
    lateral_m2: float = 0.0
    """Sum of squared lateral errors (m^2) of the close matches (`learn_landmark_sigma`)."""
    lateral_n: float = 0.0


@dataclass
class _Track:
    label: str
    descriptor: NDArray[Any]
    origin: FloatArray
    """(3,) pose of the last sighting."""
    bearing: float
    elevation: float
    length: int = 1
    missed: int = 0
    views: list[tuple[NDArray[Any], FloatArray, float]] = field(default_factory=list)
    """(descriptor, pose (3,), bearing) of sightings kept for the landmark it may become."""


@dataclass(frozen=True)
class Association:
    """One frame's association result.

    observations: what to give the estimator. feature_index: (len(observations),)
    feature of each. kind: 'landmark' or 'track' per observation. The rest is
    what `commit` needs.
    """

    robot: str
    features: Features
    observations: tuple[BearingObservation, ...]
    feature_index: IntArray
    kind: tuple[str, ...]
    landmark_matches: dict[str, int]
    track_matches: dict[str, int]
    unmatched: IntArray
    landmark_fit: dict[str, float] = field(default_factory=dict)
    """|bearing residual| / its sigma (pose and feature only) of each landmark match."""
    landmark_lateral_m: dict[str, float] = field(default_factory=dict)
    """|bearing residual| x range of each landmark match (m; corrected pose)."""


def _distances(a: NDArray[Any], b: NDArray[Any], binary: bool) -> FloatArray:
    """(P,) descriptor distances of row pairs a[p], b[p]: Hamming bits or L2."""
    if binary:
        return _POPCOUNT[np.bitwise_xor(a, b)].sum(axis=1).astype(np.float64)
    diff = a.astype(np.float32) - b.astype(np.float32)
    return np.sqrt((diff * diff).sum(axis=1)).astype(np.float64)


def _robust_pose_step(
    jac: FloatArray, resid: FloatArray, var: FloatArray, prior_cov: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Pose correction (3,) and its covariance (3, 3) from matched bearings.

    Minimises sum rho(resid - jac @ delta) with Cauchy weights (IRLS) plus the
    prior delta ~ N(0, prior_cov). `jac`: (M, 3) bearing Jacobians w.r.t. the pose;
    `resid`: (M,) bearing residuals; `var`: (M,) their variances.
    """
    prior_info = np.asarray(np.linalg.pinv(prior_cov + 1e-12 * np.eye(3)), dtype=np.float64)
    delta: FloatArray = np.zeros(3)
    info: FloatArray = prior_info
    for _ in range(6):
        e = (resid - jac @ delta) / np.sqrt(var)
        w = 1.0 / (1.0 + (e / 2.0) ** 2)  # Cauchy, scale 2 sigma
        weighted = jac * (w / var)[:, None]
        info = prior_info + weighted.T @ jac
        delta = np.asarray(np.linalg.solve(info, weighted.T @ resid), dtype=np.float64)
    return delta, np.asarray(np.linalg.inv(info), dtype=np.float64)


def _pairs_within(
    predicted: FloatArray, bearings: FloatArray, half_width: float
) -> tuple[IntArray, IntArray]:
    """(landmark row, feature) pairs whose wrapped bearing difference may be within
    `half_width` (a superset by 1e-9 rad; the caller tests exactly), sorted by row then
    feature as np.nonzero of the full (L, N) test would give them."""
    order = np.argsort(bearings, kind="stable")
    sb = bearings[order]
    # Copies shifted by -2 pi and +2 pi handle the seam (bearings in (-pi, pi]).
    ext = np.concatenate([sb - 2.0 * np.pi, sb, sb + 2.0 * np.pi])
    ext_index = np.concatenate([order, order, order])
    margin = half_width + 1e-9
    lo = np.searchsorted(ext, predicted - margin, side="left")
    hi = np.searchsorted(ext, predicted + margin, side="right")
    counts = hi - lo
    rows = np.repeat(np.arange(len(predicted)), counts)
    starts = np.repeat(lo - np.cumsum(counts) + counts, counts)
    cols = ext_index[starts + np.arange(len(rows))]
    # One feature per row only once (a half-width near pi could reach a copy twice).
    keyed = np.unique(rows.astype(np.int64) * max(len(bearings), 1) + cols)
    return keyed // max(len(bearings), 1), keyed % max(len(bearings), 1)


def _best_two(
    keys: IntArray, dist: FloatArray
) -> tuple[IntArray, FloatArray, FloatArray, IntArray]:
    """Per distinct key: (key, best distance, second best, index of the best pair)."""
    order = np.lexsort((dist, keys))
    k, d = keys[order], dist[order]
    first = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    count = np.diff(np.r_[first, len(k)])
    second = np.where(count > 1, d[np.minimum(first + 1, len(d) - 1)], np.inf)
    return k[first], d[first], second, order[first]


def _pick(
    rows: IntArray, cols: IntArray, dist: FloatArray, max_distance: float, ratio: float
) -> list[tuple[int, int]]:
    """Unique (row, col) matches among gated pairs (one entry per row-col pair).

    A pair is kept when it is the best of its row and of its column (mutual), its
    distance is at most `max_distance`, and below `ratio` x the second best of its
    row and of its column. Mutual bests are unique on both sides.
    """
    if len(dist) == 0:
        return []
    _, r_best, r_second, r_pair = _best_two(rows, dist)
    c_keys, c_best, c_second, c_pair = _best_two(cols, dist)
    col_pos = {int(c): i for i, c in enumerate(c_keys.tolist())}
    out = []
    for best, second, pair in zip(r_best.tolist(), r_second.tolist(), r_pair.tolist(), strict=True):
        if best > max_distance or best >= ratio * second:
            continue
        j = col_pos[int(cols[pair])]
        if int(c_pair[j]) != pair or c_best[j] >= ratio * c_second[j]:
            continue
        out.append((int(rows[pair]), int(cols[pair])))
    return out


def _near(bearings: FloatArray, ref: FloatArray, eps: float) -> NDArray[np.bool_]:
    """(N,) whether each bearing is within `eps` of some reference bearing (wrapped)."""
    if len(ref) == 0 or len(bearings) == 0:
        return np.zeros(len(bearings), dtype=bool)
    rows, cols = _pairs_within(ref, bearings, eps)
    close = np.abs(wrap_angles(bearings[cols] - ref[rows])) < eps
    out = np.zeros(len(bearings), dtype=bool)
    out[cols[close]] = True
    return out


class Associator:
    """Landmark descriptors and per-robot candidate tracks of one map."""

    def __init__(self, config: AssociationConfig | None = None) -> None:
        self.config = config or AssociationConfig()
        self._landmarks: dict[str, _Landmark] = {}
        self._archived: dict[str, _Landmark] = {}
        """Views of landmarks no longer live (module docstring)."""
        self._tracks: dict[str, list[_Track]] = {}
        self._next_track = 0
        self._last_fit: dict[str, float] = {}
        self._last_lateral: dict[str, float] = {}
        self._last_contested: IntArray = np.zeros(0, dtype=np.int64)

    def __setstate__(self, state: dict[str, Any]) -> None:
        # A snapshot pickled before the archive of views existed has none.
        state.setdefault("_archived", {})
        self.__dict__.update(state)

    @property
    def known_landmarks(self) -> int:
        return len(self._landmarks)

    @property
    def archived_landmarks(self) -> int:
        """Labels whose views the archive holds (landmarks no longer live)."""
        return len(self._archived)

    def _record(self, label: str) -> _Landmark | None:
        """A live landmark's views, else an archived one's (None: no views)."""
        lm = self._landmarks.get(label)
        return self._archived.get(label) if lm is None else lm

    def track_count(self, robot: str) -> int:
        return len(self._tracks.get(robot, []))

    def has_views(self) -> bool:
        """Some landmark, live or archived, has a stored descriptor (a pose-free match can
        find it)."""
        return any(lm.descriptors for lm in (*self._landmarks.values(), *self._archived.values()))

    def views_of(self, labels: Sequence[str]) -> list[NDArray[Any]]:
        """``(V, D)`` stored descriptor views of each label, live or archived (``(0, 0)``
        for a label the associator holds no view of)."""
        out: list[NDArray[Any]] = []
        for label in labels:
            lm = self._record(label)
            out.append(np.stack(lm.descriptors) if lm and lm.descriptors else np.zeros((0, 0)))
        return out

    def forget_tracks(self, robot: str) -> None:
        """Drop `robot`'s candidate tracks (its chain was re-anchored: the rays of the
        tracks were taken from poses it no longer believes)."""
        self._tracks.pop(robot, None)

    def match_without_pose(
        self, features: Features, labels: Sequence[str], *, limit: int | None = None
    ) -> tuple[tuple[BearingObservation, ...], FloatArray]:
        """Observations of `features` labelled with the landmarks (among `labels`) their
        descriptors match without a pose prior (frontend.global_match), and ``(K,)`` the
        match qualities in [0, 1]; best first, at most `limit`."""
        cfg = self.config
        limit_d = cfg.max_distance if features.binary else 5.0 * cfg.max_distance
        found = match_without_pose(
            features, self.views_of(labels), max_distance=limit_d, ratio=cfg.ratio, limit=limit
        )
        obs = tuple(
            self._observation(features, int(c), labels[int(r)])
            for c, r in zip(found.feature_index, found.landmark_index, strict=True)
        )
        return obs, found.quality

    # ------------------------------------------------------------------ associate
    def associate(
        self,
        features: Features,
        *,
        robot: str,
        predicted_pose: ArrayLike,
        pose_cov: ArrayLike | None,
        landmarks: Mapping[str, LandmarkEstimate],
    ) -> Association:
        """Label the features of one frame (nothing is changed until `commit`).
        `landmarks` may name archived landmarks (at their archived positions): they are
        matched by their archived views."""
        pose = np.asarray(predicted_pose, dtype=np.float64)
        cov = np.zeros((3, 3)) if pose_cov is None else np.asarray(pose_cov, dtype=np.float64)
        n = len(features)
        free = np.ones(n, dtype=bool)
        self._last_fit = {}
        self._last_contested = np.zeros(0, dtype=np.int64)
        lm_matches = self._match_landmarks(features, pose, cov, landmarks)
        for c in lm_matches.values():
            free[c] = False
        # A feature that some live landmark could have been (inside its gate, close in
        # descriptor) but that no landmark took (ratio test, mutual best) starts no new
        # track: its track would become a second landmark on the same corner.
        seeds = free.copy()
        if self.config.no_tracks_from_contested:
            seeds[self._last_contested] = False
        eps = self.config.coincident_rad
        if eps > 0 and lm_matches:
            taken = features.bearing_rad[np.array(list(lm_matches.values()), dtype=np.int64)]
            shadowed = _near(features.bearing_rad, taken, eps)
            free &= ~shadowed
            seeds &= ~shadowed
        tr_matches = self._match_tracks(features, robot, pose, free)
        for c in tr_matches.values():
            free[c] = False

        obs: list[BearingObservation] = []
        index: list[int] = []
        kind: list[str] = []
        for label, c in sorted(lm_matches.items(), key=lambda t: t[1]):
            obs.append(self._observation(features, c, label))
            index.append(c)
            kind.append("landmark")
        tracks = {t.label: t for t in self._tracks.get(robot, [])}
        report = [
            (label, c)
            for label, c in tr_matches.items()
            if tracks[label].length + 1 >= self.config.track_min_length
        ]
        report.sort(key=lambda t: (-tracks[t[0]].length, t[1]))
        unmatched = np.flatnonzero(free & seeds).astype(np.int64)
        if self.config.track_min_length <= 1 or (self.config.report_when_trackless and not tracks):
            labels = self._next_track_labels(len(unmatched))
            report.extend(zip(labels, unmatched.tolist(), strict=True))
        for label, c in report[: self.config.max_track_observations]:
            obs.append(self._observation(features, c, label))
            index.append(c)
            kind.append("track")
        return Association(
            robot=robot,
            features=features,
            observations=tuple(obs),
            feature_index=np.array(index, dtype=np.int64),
            kind=tuple(kind),
            landmark_matches=lm_matches,
            track_matches=tr_matches,
            unmatched=unmatched,
            landmark_fit=dict(self._last_fit),
            landmark_lateral_m=dict(self._last_lateral),
        )

    def _next_track_labels(self, n: int) -> tuple[str, ...]:
        """The labels the next `n` new tracks get (nothing is taken until `commit`)."""
        prefix = self.config.label_prefix
        return tuple(f"{prefix}{self._next_track + i:06d}" for i in range(n))

    @staticmethod
    def _observation(features: Features, c: int, label: str) -> BearingObservation:
        return BearingObservation(
            bearing_rad=float(features.bearing_rad[c]),
            label=label,
            sigma_rad=float(features.sigma_rad[c]),
        )

    def _match_landmarks(
        self,
        features: Features,
        pose: FloatArray,
        cov: FloatArray,
        landmarks: Mapping[str, LandmarkEstimate],
    ) -> dict[str, int]:
        """Gate and match; then correct the pose from the matches and match again.

        The second pass is the consistency check: a match that only fits under the
        wide first gate (a look-alike a few degrees off) does not survive once
        the other landmarks have pinned the pose down.
        """
        cfg = self.config
        found = [(lb, self._record(lb)) for lb in landmarks]
        known = [(lb, lm) for lb, lm in found if lm is not None]
        if not known or len(features) == 0:
            return {}
        labels = [lb for lb, _ in known]
        records = [lm for _, lm in known]
        xy = np.array([landmarks[lb][0] for lb in labels], dtype=np.float64).reshape(-1, 2)
        lcov = self._prior_covs(records)
        for i, lb in enumerate(labels):
            given = landmarks[lb][1]
            if given is not None:
                lcov[i] = np.asarray(given, dtype=np.float64)
        heights = np.array(
            [np.nan if lm.height_m is None else lm.height_m for lm in records], dtype=np.float64
        )
        views = self._view_stack(records)
        picked, resid, jp, var_l = self._gate_and_pick(
            features, views, xy, lcov, heights, pose, cov
        )
        post = cov
        if len(picked) >= cfg.min_matches_for_pose:
            rows = np.array([r for r, _ in picked])
            cols = np.array([c for _, c in picked])
            res = np.array([resid[pair] for pair in picked])
            s2 = var_l[rows] + features.sigma_rad[cols] ** 2
            delta, post = _robust_pose_step(jp[rows], res, s2, cov)
            pose = pose + delta
            picked, resid, jp, var_l = self._gate_and_pick(
                features, views, xy, lcov, heights, pose, post
            )
        # Normalised residual of each match without the landmark's own uncertainty:
        # only close fits may add a view to a landmark (a look-alike must not).
        self._last_fit = {}
        self._last_lateral = {}
        for r, c in picked:
            sd = math.sqrt(float(jp[r] @ post @ jp[r]) + float(features.sigma_rad[c]) ** 2)
            self._last_fit[labels[r]] = abs(resid[r, c]) / sd
            rng_m = math.hypot(xy[r, 0] - pose[0], xy[r, 1] - pose[1])
            self._last_lateral[labels[r]] = abs(resid[r, c]) * rng_m
        return {labels[r]: c for r, c in picked}

    def _prior_covs(self, records: list[_Landmark]) -> FloatArray:
        """(L, 2, 2) position covariances of landmarks the caller gave none for: the
        default sigma, or (learn_landmark_sigma) the one their close matches suggest."""
        cfg = self.config
        var0 = cfg.default_landmark_sigma_m**2
        var = np.full(len(records), var0)
        if cfg.learn_landmark_sigma:
            m2 = np.array([lm.lateral_m2 for lm in records], dtype=np.float64)
            n = np.array([lm.lateral_n for lm in records], dtype=np.float64)
            n0 = cfg.landmark_sigma_prior_n
            learnt = np.maximum((n0 * var0 + m2) / (n0 + n), cfg.min_landmark_sigma_m**2)
            var = np.where(n > 0, learnt, var)
        return var[:, None, None] * np.eye(2)[None, :, :]

    def _gate_and_pick(
        self,
        features: Features,
        views: tuple[NDArray[Any], IntArray],
        xy: FloatArray,
        lcov: FloatArray,
        heights: FloatArray,
        pose: FloatArray,
        cov: FloatArray,
    ) -> tuple[list[tuple[int, int]], dict[tuple[int, int], float], FloatArray, FloatArray]:
        """Matches (landmark row, feature) plus the bearing residual of each gated pair,
        (L, 3) pose Jacobians and (L,) landmark-only bearing variances."""
        cfg = self.config
        dx, dy = xy[:, 0] - pose[0], xy[:, 1] - pose[1]
        r2 = np.maximum(dx * dx + dy * dy, 1e-6)
        predicted = wrap_angles(np.arctan2(dy, dx) - pose[2])
        # d(bearing)/d(landmark xy) = (-dy, dx) / r^2; d/d(pose) = (dy/r^2, -dx/r^2, -1).
        jl = np.column_stack([-dy, dx]) / r2[:, None]
        jp = np.column_stack([dy / r2, -dx / r2, -np.ones(len(xy))])
        var_l = np.einsum("li,lij,lj->l", jl, lcov, jl)
        var = np.einsum("li,ij,lj->l", jp, cov, jp) + var_l
        # Only pairs within the widest gate can pass: find them by bisection on the sorted
        # bearings (with the seam's wrap) instead of testing every landmark x feature.
        li, fi = _pairs_within(predicted, features.bearing_rad, cfg.max_gate_rad)
        resid = wrap_angles(features.bearing_rad[fi] - predicted[li])
        sd = np.sqrt(var[li] + features.sigma_rad[fi] ** 2)
        gate = np.clip(cfg.gate_sigmas * sd, cfg.min_gate_rad, cfg.max_gate_rad)
        inside = np.abs(resid) <= gate
        known = np.isfinite(heights)
        if known.any():
            elev = np.arctan2(np.where(known, heights, 0.0), np.sqrt(r2))
            de = np.abs(features.elevation_rad[fi] - elev[li])
            tol = cfg.elevation_gate_rad + cfg.gate_sigmas * features.sigma_rad[fi]
            inside &= ~known[li] | (de <= cfg.landmark_elevation_gate * tol)
        li, fi, resid = li[inside], fi[inside], resid[inside]
        residuals = dict(
            zip(zip(li.tolist(), fi.tolist(), strict=True), resid.tolist(), strict=True)
        )
        if len(li) == 0:
            self._last_contested = np.zeros(0, dtype=np.int64)
            return [], residuals, jp, var_l
        # Distance to each stored view; keep the smallest per pair.
        stack, counts = views
        pair_views = stack[li]  # (P, K, D)
        k = pair_views.shape[1]
        d = _distances(
            pair_views.reshape(len(li) * k, -1),
            np.repeat(features.descriptors[fi], k, axis=0),
            features.binary,
        ).reshape(len(li), k)
        d[np.arange(k)[None, :] >= counts[li][:, None]] = np.inf
        dist = d.min(axis=1)
        limit = cfg.max_distance if features.binary else 5.0 * cfg.max_distance
        self._last_contested = fi[dist <= limit]
        return _pick(li, fi, dist, limit, cfg.ratio), residuals, jp, var_l

    def _view_stack(self, records: list[_Landmark]) -> tuple[NDArray[Any], IntArray]:
        """(L, K, D) stored views of the landmarks (zero-padded) and (L,) their counts."""
        k = self.config.views_per_landmark
        descs = [lm.descriptors[:k] for lm in records]
        counts = np.array([len(d) for d in descs], dtype=np.int64)
        flat = [d for ds in descs for d in ds]
        if not flat:
            return np.zeros((len(records), k, 32), dtype=np.uint8), counts
        stacked = np.stack(flat)
        views = np.zeros((len(records), k, stacked.shape[-1]), dtype=stacked.dtype)
        rows = np.repeat(np.arange(len(records)), counts)
        slots = np.arange(len(flat)) - np.repeat(np.cumsum(counts) - counts, counts)
        views[rows, slots] = stacked
        return views, counts

    def _match_tracks(
        self, features: Features, robot: str, pose: FloatArray, free: NDArray[np.bool_]
    ) -> dict[str, int]:
        cfg = self.config
        tracks = self._tracks.get(robot, [])
        cand = np.flatnonzero(free)
        if not tracks or len(cand) == 0:
            return {}
        origin = np.array([t.origin for t in tracks])
        world = origin[:, 2] + np.array([t.bearing for t in tracks])
        lo_d, hi_d = cfg.track_depth_m
        depths = np.concatenate([np.geomspace(lo_d, hi_d, 16), [1e4]])
        px = origin[:, 0:1] + depths[None, :] * np.cos(world)[:, None]
        py = origin[:, 1:2] + depths[None, :] * np.sin(world)[:, None]
        b = np.arctan2(py - pose[1], px - pose[0]) - pose[2]  # (T, D)
        ref = b[:, -1:]
        rel = wrap_angles(b - ref)
        lo, hi = rel.min(axis=1), rel.max(axis=1)
        fb = features.bearing_rad[cand]
        offset = wrap_angles(fb[None, :] - ref)  # (T, C)
        sig = features.sigma_rad[cand][None, :]
        margin = cfg.track_margin_rad + cfg.gate_sigmas * sig
        inside = (offset >= lo[:, None] - margin) & (offset <= hi[:, None] + margin)
        ti, ci = np.nonzero(inside)
        if len(ti) == 0:
            return {}
        # Elevation: triangulate the feature's ray with the track's ray (depth along the
        # track's ray, clipped to track_depth_m), carry the implied height to the
        # current distance, and compare. Without parallax the elevation stays put.
        elev = np.array([t.elevation for t in tracks])[ti]
        o = origin[ti]
        wa = world[ti]
        wb = pose[2] + fb[ci]
        ua = np.column_stack([np.cos(wa), np.sin(wa)])
        ub = np.column_stack([np.cos(wb), np.sin(wb)])
        base = pose[None, :2] - o[:, :2]
        cross = ua[:, 0] * ub[:, 1] - ua[:, 1] * ub[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = (base[:, 0] * ub[:, 1] - base[:, 1] * ub[:, 0]) / cross
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, hi_d)
        depth = np.clip(depth, lo_d, hi_d)
        point = o[:, :2] + depth[:, None] * ua
        d_now = np.maximum(np.hypot(point[:, 0] - pose[0], point[:, 1] - pose[1]), 1e-3)
        predicted_e = np.arctan2(depth * np.tan(elev), d_now)
        sig_e = features.sigma_rad[cand[ci]]
        ok = np.abs(features.elevation_rad[cand[ci]] - predicted_e) <= (
            cfg.elevation_gate_rad + cfg.gate_sigmas * sig_e
        )
        ti, ci = ti[ok], ci[ok]
        if len(ti) == 0:
            return {}
        descs = np.stack([tracks[i].descriptor for i in ti])
        dist = _distances(descs, features.descriptors[cand[ci]], features.binary)
        limit = cfg.max_distance if features.binary else 5.0 * cfg.max_distance
        picked = _pick(ti, cand[ci], dist, limit, cfg.ratio)
        return {tracks[r].label: c for r, c in picked}

    # ------------------------------------------------------------------ commit
    def commit(
        self,
        association: Association,
        *,
        pose: ArrayLike,
        live_labels: Collection[str],
        landmark_xy: Mapping[str, ArrayLike] | None = None,
        removed_labels: Collection[str] = (),
    ) -> None:
        """Update descriptors and tracks after the estimator processed the frame.

        `pose`: the frame's pose estimate (3,). `live_labels`: the labels of every
        live landmark after the frame. `landmark_xy`: positions of (some) live
        landmarks, used to learn their height for the elevation gate.
        `removed_labels`: the landmarks the estimator removed this frame; one removed
        before its track was promoted (the frame that made it a landmark) has its
        track's views archived (the track goes on as before).
        """
        cfg = self.config
        feats = association.features
        here = np.asarray(pose, dtype=np.float64)
        live = set(live_labels)
        positions = landmark_xy or {}

        for label, c in association.landmark_matches.items():
            lm = self._landmarks.get(label)
            if lm is None or association.landmark_fit.get(label, 0.0) > cfg.view_fit_sigmas:
                continue
            if label in positions:
                self._learn_height(lm, here, np.asarray(positions[label]), feats, c)
            lateral = association.landmark_lateral_m.get(label)
            if lateral is not None:
                if lm.lateral_n >= 50:  # a window of ~50 matches: the landmark settles
                    lm.lateral_m2 *= 49.0 / 50.0
                    lm.lateral_n = 49.0
                lm.lateral_m2 += lateral * lateral
                lm.lateral_n += 1.0
            xy = positions.get(label)
            angle = float(feats.bearing_rad[c] + here[2] + math.pi)
            if xy is not None:
                p = np.asarray(xy, dtype=np.float64)
                angle = math.atan2(here[1] - p[1], here[0] - p[0])
            gaps = np.abs(wrap_angles(np.array(lm.view_angles) - angle))
            if len(lm.descriptors) == 0 or gaps.min() >= cfg.new_view_angle_rad:
                lm.descriptors.append(feats.descriptors[c].copy())
                lm.view_angles.append(angle)
                if len(lm.descriptors) > cfg.views_per_landmark:
                    # Keep the first view, drop the oldest of the others.
                    del lm.descriptors[1]
                    del lm.view_angles[1]

        tracks = self._tracks.setdefault(association.robot, [])
        kept: list[_Track] = []
        for t in tracks:
            match = association.track_matches.get(t.label)
            if match is None:
                t.missed += 1
            else:
                c = match
                t.descriptor = feats.descriptors[c].copy()
                t.origin = here.copy()
                t.bearing = float(feats.bearing_rad[c])
                t.elevation = float(feats.elevation_rad[c])
                t.length += 1
                t.missed = 0
                self._add_track_view(t, feats, c, here)
            if t.label in live:
                self._promote(t, here, positions.get(t.label))
                continue
            if t.label in removed_labels and self._record(t.label) is None:
                self._archived[t.label] = self._landmark_of(t, here, None)
            if t.missed <= cfg.track_max_missed:
                kept.append(t)
        # The labels `associate` reported for new tracks, the next ones in order (if another
        # association of this map was committed in between, these are later ones: unique).
        fresh = self._next_track_labels(len(association.unmatched))
        for c, label in zip(association.unmatched.tolist(), fresh, strict=True):
            t = _Track(
                label=label,
                descriptor=feats.descriptors[c].copy(),
                origin=here.copy(),
                bearing=float(feats.bearing_rad[c]),
                elevation=float(feats.elevation_rad[c]),
            )
            self._next_track += 1
            self._add_track_view(t, feats, c, here)
            kept.append(t)
        self._tracks[association.robot] = kept
        for label in [lb for lb in self._landmarks if lb not in live]:
            self._archived[label] = self._landmarks.pop(label)
        for label in [lb for lb in self._archived if lb in live]:  # restored by label
            self._landmarks.setdefault(label, self._archived.pop(label))

    def _add_track_view(self, t: _Track, feats: Features, c: int, here: FloatArray) -> None:
        world = float(here[2] + feats.bearing_rad[c])
        if t.views:
            gaps = np.abs(wrap_angles(np.array([p[2] + b for _, p, b in t.views]) - world))
            if gaps.min() < self.config.new_view_angle_rad:
                return
        t.views.append((feats.descriptors[c].copy(), here.copy(), float(feats.bearing_rad[c])))
        if len(t.views) > self.config.views_per_landmark:
            del t.views[1]

    def _promote(self, t: _Track, here: FloatArray, xy: ArrayLike | None) -> None:
        """A track's label became a live landmark: it keeps the track's views."""
        self._landmarks[t.label] = self._landmark_of(t, here, xy)

    @staticmethod
    def _landmark_of(t: _Track, here: FloatArray, xy: ArrayLike | None) -> _Landmark:
        """The landmark record of a track's views (its height from `xy`, if given)."""
        lm = _Landmark()
        views = t.views or [(t.descriptor, here, t.bearing)]
        for desc, p, b in views:
            lm.descriptors.append(desc)
            lm.view_angles.append(float(p[2] + b + math.pi))
        if xy is not None:
            p = np.asarray(xy, dtype=np.float64)
            d = math.hypot(p[0] - t.origin[0], p[1] - t.origin[1])
            lm.height_m = d * math.tan(t.elevation)
            lm.height_n = 1
        return lm

    @staticmethod
    def _learn_height(
        lm: _Landmark, here: FloatArray, xy: FloatArray, feats: Features, c: int
    ) -> None:
        d = math.hypot(xy[0] - here[0], xy[1] - here[1])
        h = d * math.tan(float(feats.elevation_rad[c]))
        lm.height_n = min(lm.height_n + 1, 20)
        lm.height_m = h if lm.height_m is None else lm.height_m + (h - lm.height_m) / lm.height_n
