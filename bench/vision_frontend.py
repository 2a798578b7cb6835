"""Vision front end on a rendered indoor run: bearing error, association precision, ATE, speed.

A robot drives `indoor_sim`'s 3x3 rooms (doors, revisits); every frame is
rendered as a 2048x512 panorama (service.offline.datasets.render). Two maps are run on
the same frames with the same estimator settings:

- images: the front end's features and association (service.pipeline.images.ImageFrontEnd);
- oracle: the same features, labelled with their true identity (the poster
  corner they lie on, within `--truth-px` pixels; others dropped).

Truth of a feature: the visible poster corner whose projection is nearest,
within `--truth-px`; its identity is the corner's 2-D wall point (corners of a
poster edge one above the other are one point for a 2-D map). A landmark's
identity is the most common truth among all observations carrying its label.

Figures: median bearing error of observations matched to live landmarks (vs the
true bearing of the landmark's corner from the true pose), association
precision (observations matched to live landmarks whose truth is the
landmark's identity / those with a truth), ATE RMSE of both maps, and front-end
milliseconds per panorama (features; association separately).

    python -m bench.vision_frontend --frames 1000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import time
from collections import Counter, defaultdict
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from frontend.association import AssociationConfig
from frontend.cameras import PanoramaCamera
from frontend.features import FeatureConfig, FeatureExtractor, Features
from frontend.pipeline import FrontEnd
from graph.angles import wrap_angles
from graph.config import SlamConfig
from graph.slam import BearingSlam
from graph.types import BearingObservation
from service.offline.datasets.indoor_sim import SimRun, make_world, simulate
from service.offline.datasets.render import (
    TexturedWorld,
    make_textured_world,
    render_panorama,
    visible_corners,
)
from service.offline.evaluation import Trajectory, ate_rmse
from service.pipeline.camera_config import (
    CAMERA_GRAPH_FRAME_DISTANCE_M,
    CAMERA_LANDMARK_FACTORS,
    CAMERA_NOISE_DEFAULTS,
)
from service.pipeline.images import ImageFrontEnd

log = logging.getLogger("bench.vision_frontend")
RESULTS = Path(__file__).resolve().parent / "results"


def corner_identities(corners_xyz: np.ndarray) -> np.ndarray:
    """(C,) identity of each corner: corners sharing a 2-D wall point (1 cm) share one."""
    key = np.round(corners_xyz[:, :2] * 100.0).astype(np.int64)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    return inverse.reshape(-1).astype(np.int64)


def feature_truth(
    feats: Features,
    camera: PanoramaCamera,
    ids: np.ndarray,
    bearings: np.ndarray,
    elevations: np.ndarray,
    max_px: float,
) -> np.ndarray:
    """(N,) corner index each feature lies on (nearest projection within max_px), -1 if none."""
    out = np.full(len(feats), -1, dtype=np.int64)
    if len(ids) == 0 or len(feats) == 0:
        return out
    cu = camera.column_of_bearing(bearings)
    cv = camera.row_of_elevation(elevations)
    w = camera.width
    du = np.mod(feats.u[:, None] - cu[None, :] + w / 2, w) - w / 2
    d = np.hypot(du, feats.v[:, None] - cv[None, :])
    j = np.argmin(d, axis=1)
    near = d[np.arange(len(j)), j] <= max_px
    out[near] = ids[j[near]]
    return out


def diagnose_wrong(
    wrong: list[dict[str, Any]],
    tw: Any,
    identity: np.ndarray,
    label_id: dict[str, int],
    label_truth: dict[str, list[int]],
) -> dict[str, Any]:
    """Sort the wrong landmark matches into cases.

    Each entry of `wrong`: frame, label, feature identity `fid`, landmark identity
    `lid`, feature bearing, fit, predicted-pose error. Cases: `same_face` (the two
    corners are on the same wall face: a neighbouring corner of the same poster or
    of one nearby), `other_face` (a look-alike elsewhere), `wrap` (the feature within
    5 deg of the image's seam), `lid_hidden` (the landmark's own corner not visible
    in that frame), `impure_landmark` (under 90 % of the label's observations are its
    identity).
    """
    first: dict[int, int] = {}
    for c, i in enumerate(identity.tolist()):
        first.setdefault(int(i), c)
    counts: Counter[str] = Counter()
    sep: list[float] = []
    for w in wrong:
        cf, cl = first[w["fid"]], first[w["lid"]]
        d = float(np.hypot(*(tw.corners_xyz[cf, :2] - tw.corners_xyz[cl, :2])))
        w["corner_distance_m"] = d
        sep.append(d)
        same = int(tw.corner_face[cf]) // 2 == int(tw.corner_face[cl]) // 2
        counts["same_wall" if same else "other_wall"] += 1
        counts["near_1m" if d < 1.0 else "far"] += 1
        if abs(w["bearing"]) > math.pi - math.radians(5.0):
            counts["wrap"] += 1
        if not w["lid_visible"]:
            counts["lid_hidden"] += 1
        truths = [t for t in label_truth[w["label"]] if t >= 0]
        purity = sum(1 for t in truths if t == label_id[w["label"]]) / max(1, len(truths))
        w["label_purity"] = purity
        if purity < 0.9:
            counts["impure_landmark"] += 1
        if w["pose_error_m"] > 0.1 or w["pose_error_deg"] > 2.0:
            counts["predicted_pose_off"] += 1
    return {
        "wrong": len(wrong),
        "cases": dict(counts),
        "corner_distance_m_median": float(np.median(sep)) if sep else None,
        "fit_median": float(np.median([w["fit"] for w in wrong])) if wrong else None,
        "entries": wrong[:400],
    }


def speed_test(camera: PanoramaCamera, images: list[np.ndarray]) -> dict[str, Any]:
    """Features per panorama, alone (no estimator running): wall and CPU ms, 1 and 2 threads."""
    out: dict[str, Any] = {"images": len(images)}
    for threads in (1, 2):
        extractor = FeatureExtractor(camera, FeatureConfig(threads=threads))
        wall: list[float] = []
        cpu: list[float] = []
        for _ in range(3):
            for image in images:
                w0, c0 = time.perf_counter(), time.process_time()
                extractor.extract(image)
                wall.append(1e3 * (time.perf_counter() - w0))
                cpu.append(1e3 * (time.process_time() - c0))
        extractor.close()
        out[f"threads_{threads}"] = {
            "wall_ms_median": float(np.median(wall)),
            "wall_ms_min": float(np.min(wall)),
            "cpu_ms_median": float(np.median(cpu)),
        }
    out["load_average"] = list(os.getloadavg())
    return out


def _scene(args: argparse.Namespace) -> tuple[TexturedWorld, SimRun, PanoramaCamera]:
    """The rendered world, the robot's run through it and the camera (from the seed)."""
    rng = np.random.default_rng(args.seed)
    world = make_world(rooms=(3, 3), landmarks=9, rng=rng)
    tw = make_textured_world(world, rng=rng)
    sim = simulate(world, frames=args.frames, rng=rng, door_probability=0.5)
    return tw, sim, PanoramaCamera(args.width, args.width // 4)


def speed_only(args: argparse.Namespace) -> dict[str, Any]:
    """The features speed test alone, on 40 panoramas spread over the run."""
    tw, sim, camera = _scene(args)
    poses = sim.ground_truth.poses()
    step = max(1, args.frames // 40)
    images = [render_panorama(tw, poses[k], camera)[0] for k in range(0, args.frames, step)]
    return {"load_average_start": list(os.getloadavg()), **speed_test(camera, images)}


def _graph_frame_options(args: argparse.Namespace) -> dict[str, Any]:
    """The graph-frame settings given on the command line (others: the estimator's)."""
    out: dict[str, Any] = {}
    if args.graph_frame_max_gap is not None:
        out["graph_frame_max_gap"] = args.graph_frame_max_gap
    if args.graph_frame_angle_deg is not None:
        out["graph_frame_angle_rad"] = math.radians(args.graph_frame_angle_deg)
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    tw, sim, camera = _scene(args)
    identity = corner_identities(tw.corners_xyz)
    config = SlamConfig(
        landmark_cap=args.landmark_cap,
        policy=args.policy,
        pose_window=args.pose_window,
        max_landmark_factors=args.max_landmark_factors or None,
        removal_margin=args.removal_margin,
        graph_frame_distance_m=args.graph_frame_distance or None,
        bearing_loss=args.bearing_loss,
        huber_k=args.huber_k,
        **_graph_frame_options(args),
    )

    association = AssociationConfig()
    if args.coincident_deg is not None:
        association = replace(association, coincident_rad=math.radians(args.coincident_deg))
    if args.elevation_gate is not None:
        association = replace(association, landmark_elevation_gate=args.elevation_gate)
    pipeline = ImageFrontEnd(
        BearingSlam(config, rng=np.random.default_rng(args.seed)),
        FrontEnd(camera, association=association),
    )
    oracle = BearingSlam(config, rng=np.random.default_rng(args.seed))
    truth_poses = sim.ground_truth.poses()

    feature_ms: list[float] = []
    assoc_ms: list[float] = []
    render_ms: list[float] = []
    kept_images: list[np.ndarray] = []
    label_truth: dict[str, list[int]] = defaultdict(list)
    matched: list[tuple[str, int, float, int]] = []  # label, truth corner, bearing, frame
    context: dict[tuple[int, str], dict[str, Any]] = {}  # (frame, label) -> diagnosis
    n_obs = n_track_obs = 0
    dump: list[dict[str, Any]] | None = [] if args.dump else None
    for k, frame in enumerate(sim.frames):
        t0 = time.perf_counter()
        image, _ = render_panorama(tw, truth_poses[k], camera)
        render_ms.append(1e3 * (time.perf_counter() - t0))
        if k % max(1, args.frames // 40) == 0:
            kept_images.append(image)
        t0 = time.perf_counter()
        feats = pipeline.front_end.features(image)
        features_ms = 1e3 * (time.perf_counter() - t0)
        ids, b, e = visible_corners(tw, truth_poses[k], camera)
        truth = feature_truth(feats, camera, ids, b, e, args.truth_px)
        predicted = pipeline.predict(frame)[0]
        result = pipeline.submit(frame, feats)
        feature_ms.append(features_ms)
        assoc_ms.append(result.timing_ms["association"])
        assoc = result.association
        for ob, fi, kind in zip(
            assoc.observations, assoc.feature_index.tolist(), assoc.kind, strict=True
        ):
            c = int(truth[fi])
            label_truth[ob.label].append(int(identity[c]) if c >= 0 else -1)
            n_obs += 1
            if kind == "landmark":
                matched.append((ob.label, c, ob.bearing_rad, k))
                dp = predicted - truth_poses[k]
                context[(k, ob.label)] = {
                    "fit": assoc.landmark_fit.get(ob.label, float("nan")),
                    "pose_error_m": float(np.hypot(dp[0], dp[1])),
                    "pose_error_deg": abs(math.degrees(float(wrap_angles(dp[2])))),
                    "visible": {int(identity[i]) for i in ids.tolist()},
                }
            else:
                n_track_obs += 1
        # Oracle: the same features, labelled by their true identity, one per identity.
        seen: set[int] = set()
        obs: list[BearingObservation] = []
        for fi in np.argsort(feats.response)[::-1].tolist():
            c = int(truth[fi])
            if c < 0 or int(identity[c]) in seen:
                continue
            seen.add(int(identity[c]))
            obs.append(
                BearingObservation(
                    float(feats.bearing_rad[fi]), f"c{identity[c]}", float(feats.sigma_rad[fi])
                )
            )
        if not args.no_oracle:
            oracle.process(replace(frame, observations=tuple(obs)), with_covariance=False)
        if dump is not None:
            dump.append(
                {
                    "images": [
                        (ob.label, ob.bearing_rad, ob.sigma_rad, int(truth[fi]), kind)
                        for ob, fi, kind in zip(
                            assoc.observations,
                            assoc.feature_index.tolist(),
                            assoc.kind,
                            strict=True,
                        )
                    ],
                    "oracle": [(ob.label, ob.bearing_rad, ob.sigma_rad) for ob in obs],
                }
            )
        if (k + 1) % 100 == 0:
            log.info(
                "frame %d: live %d (oracle %d), %.1f ms features",
                k + 1,
                len(pipeline.slam.landmarks),
                len(oracle.landmarks),
                float(np.median(feature_ms[-100:])),
            )

    # Identity of each label: the most common truth among its observations.
    label_id = {}
    for label, truths in label_truth.items():
        known = [t for t in truths if t >= 0]
        if known:
            label_id[label] = Counter(known).most_common(1)[0][0]
    correct = wrong = unknown = 0
    errors: list[float] = []
    wrong_list: list[dict[str, Any]] = []
    for label, c, bearing, k in matched:
        if c < 0 or label not in label_id:
            unknown += 1
            continue
        ctx = context[(k, label)]
        if int(identity[c]) != label_id[label]:
            wrong_list.append(
                {
                    "frame": k,
                    "label": label,
                    "fid": int(identity[c]),
                    "lid": label_id[label],
                    "bearing": bearing,
                    "fit": ctx["fit"],
                    "pose_error_m": ctx["pose_error_m"],
                    "pose_error_deg": ctx["pose_error_deg"],
                    "lid_visible": label_id[label] in ctx["visible"],
                }
            )
        if int(identity[c]) == label_id[label]:
            correct += 1
            x, y, th = truth_poses[k]
            cx, cy = tw.corners_xyz[c, :2]
            true_b = math.atan2(cy - y, cx - x) - th
            errors.append(abs(float(wrap_angles(bearing - true_b))))
        else:
            wrong += 1
    all_correct = sum(
        1 for lb, ts in label_truth.items() for t in ts if t >= 0 and t == label_id.get(lb)
    )
    all_known = sum(1 for ts in label_truth.values() for t in ts if t >= 0)

    def trajectory(slam: BearingSlam) -> Trajectory:
        rows = slam.trajectory("r1")["r1"]
        return Trajectory.from_poses(rows[:, 1], rows[:, 2:5])

    if dump is not None:
        import pickle

        with open(args.dump, "wb") as fh:
            pickle.dump(
                {
                    "frames": sim.frames,
                    "obs": dump,
                    "identity": identity,
                    "slam_config": dataclasses.asdict(config),
                },
                fh,
            )
    speed = speed_test(camera, kept_images) if not args.no_speed else {}
    ate_images = ate_rmse(trajectory(pipeline.slam), sim.ground_truth)
    ate_oracle = ate_rmse(trajectory(oracle), sim.ground_truth) if not args.no_oracle else None
    # Landmarks none of whose observations lie on a poster corner (texture, edges, occluding
    # contours): their share of the landmark matches.
    no_truth_labels = {lb for lb, ts in label_truth.items() if all(t < 0 for t in ts)}
    wrong_doc = diagnose_wrong(wrong_list, tw, identity, label_id, label_truth)
    from service.offline.evaluation import dead_reckoning

    ate_dr = ate_rmse(dead_reckoning(sim.frames), sim.ground_truth)
    return {
        "frames": args.frames,
        "panorama": [camera.width, camera.height],
        "seed": args.seed,
        "coincident_deg": math.degrees(association.coincident_rad),
        "landmark_elevation_gate": association.landmark_elevation_gate,
        "slam_config": {
            "landmark_cap": args.landmark_cap,
            "policy": args.policy,
            "pose_window": args.pose_window,
            "max_landmark_factors": args.max_landmark_factors or None,
            "removal_margin": args.removal_margin,
            "graph_frame_distance_m": args.graph_frame_distance or None,
            "bearing_loss": args.bearing_loss,
            "huber_k": args.huber_k,
            **_graph_frame_options(args),
        },
        "truth_px": args.truth_px,
        "matched_observations": len(matched),
        "matched_with_truth": correct + wrong,
        "matched_without_truth": unknown,
        "precision_matched": correct / max(1, correct + wrong),
        "precision_all_labelled": all_correct / max(1, all_known),
        "observations": n_obs,
        "track_observations": n_track_obs,
        "median_bearing_error_deg": math.degrees(float(np.median(errors))) if errors else None,
        "p90_bearing_error_deg": math.degrees(float(np.percentile(errors, 90))) if errors else None,
        "landmark_matches_without_any_truth": sum(1 for m in matched if m[0] in no_truth_labels),
        "wrong_matches": wrong_doc,
        "load_average_end": list(os.getloadavg()),
        "ate_images_m": ate_images,
        "ate_oracle_m": ate_oracle,
        "ate_dead_reckoning_m": ate_dr,
        "ate_ratio": ate_images / ate_oracle if ate_oracle else None,
        "features_ms_median": float(np.median(feature_ms)),
        "features_ms_p90": float(np.percentile(feature_ms, 90)),
        "association_ms_median": float(np.median(assoc_ms)),
        "render_ms_median": float(np.median(render_ms)),
        "speed": speed,
        "live_landmarks_end": len(pipeline.slam.landmarks),
        "oracle_live_landmarks_end": len(oracle.landmarks),
        # A landmark marginalised and seen again is created anew (both maps).
        "landmarks_created": pipeline.slam.removal_count + len(pipeline.slam.landmarks),
        "oracle_landmarks_created": oracle.removal_count + len(oracle.landmarks),
        "feature_ms": [round(t, 3) for t in feature_ms],
        "errors_deg": [round(math.degrees(e), 4) for e in errors],
        "trajectories": {
            "truth": truth_poses[:, :2].round(4).tolist(),
            "images": trajectory(pipeline.slam).poses()[:, :2].round(4).tolist(),
            "oracle": trajectory(oracle).poses()[:, :2].round(4).tolist()
            if not args.no_oracle
            else [],
        },
        "note": "2-core machine shared with two other engineers' jobs: timings are noisy",
    }


def plot(doc: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    tr = doc["trajectories"]
    for name, style in (("truth", "k-"), ("oracle", "b-"), ("images", "r-")):
        xy = np.asarray(tr[name])
        if len(xy) == 0:
            continue
        axes[0].plot(xy[:, 0], xy[:, 1], style, lw=0.8, label=name)
    axes[0].set_aspect("equal")
    axes[0].set_title(f"ATE images {doc['ate_images_m']:.3f} m, oracle {doc['ate_oracle_m']} m")
    axes[0].legend()
    axes[1].hist(doc["errors_deg"], bins=60, range=(0, 1.0))
    axes[1].set_title(
        f"bearing error of matched features, median {doc['median_bearing_error_deg']:.3f}°"
    )
    axes[1].set_xlabel("deg")
    axes[2].plot(doc["feature_ms"], lw=0.5)
    axes[2].set_title(f"front end ms/panorama, median {doc['features_ms_median']:.1f}")
    axes[2].set_xlabel("frame")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=2048)
    p.add_argument("--landmark-cap", type=int, default=None)
    p.add_argument("--policy", default="oldest")
    p.add_argument("--pose-window", type=int, default=100)
    p.add_argument(
        "--max-landmark-factors",
        type=int,
        default=CAMERA_LANDMARK_FACTORS,
        help="bearing factors on live landmarks per frame, both maps (0: one per observation)",
    )
    p.add_argument(
        "--removal-margin",
        type=int,
        default=0,
        help="over the cap, remove down to cap - this in one update (both maps)",
    )
    p.add_argument(
        "--graph-frame-distance",
        type=float,
        default=CAMERA_GRAPH_FRAME_DISTANCE_M,
        help="metres between graph frames, the others tracked (both maps; 0: every frame)",
    )
    p.add_argument(
        "--bearing-loss",
        default=CAMERA_NOISE_DEFAULTS["bearing_loss"],
        choices=("huber", "geman_mcclure"),
        help="robust loss of bearing factors (both maps)",
    )
    p.add_argument(
        "--huber-k",
        type=float,
        default=CAMERA_NOISE_DEFAULTS["huber_k"],
        help="the loss's threshold / scale in sigmas (both maps)",
    )
    p.add_argument("--graph-frame-max-gap", type=int, default=None)
    p.add_argument("--graph-frame-angle-deg", type=float, default=None)
    p.add_argument("--truth-px", type=float, default=2.0)
    p.add_argument("--out", default="vision_frontend")
    p.add_argument("--no-oracle", action="store_true", help="skip the oracle map (diagnosis)")
    p.add_argument(
        "--coincident-deg",
        type=float,
        default=None,
        help="association: a feature this close in bearing to a landmark match is the same "
        "2-D point and starts no track (default: AssociationConfig's; 0: off)",
    )
    p.add_argument(
        "--elevation-gate",
        type=float,
        default=None,
        help="association: landmark elevation gate in tolerances (AssociationConfig's)",
    )
    p.add_argument("--no-speed", action="store_true", help="skip the features speed test")
    p.add_argument("--speed-only", action="store_true", help="only the features speed test")
    p.add_argument("--dump", help="pickle each frame's observations (and truth) to this file")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.speed_only:
        speed = speed_only(args)
        RESULTS.mkdir(exist_ok=True)
        (RESULTS / f"{args.out}_speed.json").write_text(json.dumps(speed, indent=1))
        print(json.dumps(speed, indent=1))
        return
    doc = run(args)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.out}.json").write_text(json.dumps(doc))
    plot(doc, RESULTS / f"{args.out}.png")
    summary = {k: v for k, v in doc.items() if not isinstance(v, list | dict)}
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
