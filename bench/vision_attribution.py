"""Where the image map's trajectory error comes from: the estimator alone on recorded observations.

`python -m bench.vision_frontend --dump RUN.pkl` records, per frame, the labelled
observations the front end gave the estimator (with each one's true poster corner,
-1 if none) and the oracle's observations. This replays them through a fresh
`BearingSlam` (same settings) in variants, so each suspect can be switched off
while everything else stays the same (the association itself is not re-run):

- ``images``: as recorded;
- ``no_wrong``: without the observations whose true corner is not their label's
  identity (the most common truth among the label's observations);
- ``no_untrue``: without the observations that lie on no poster corner;
- ``clean``: both removed;
- ``sigma_x``: ``images`` with every bearing sigma scaled by x;
- ``truth_corner``: the front end's observations that lie on a poster corner,
  labelled with that corner (perfect association of the front end's own selection;
  the two ends of a poster edge stay two landmarks, as the front end makes them);
- ``truth_identity``: the same labelled with the corner's 2-D identity (the two ends
  of an edge are one landmark, as for the oracle);
- ``oracle``: the oracle's observations;
- ``oracle_shared``: the oracle's observations of the identities the front end also
  reported (on a corner) in that frame: the oracle's choice of feature per identity,
  the front end's choice of identities.

Each result also counts the landmarks the estimator created (a landmark marginalised
and seen again is created anew) and their mean number of bearing observations.

    python -m bench.vision_attribution RUN.pkl --variants images,no_wrong,oracle
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import pickle
import time
from collections import Counter, defaultdict
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from graph.config import SlamConfig
from graph.slam import BearingSlam
from graph.types import BearingObservation
from service.offline.datasets.indoor_sim import make_world, simulate
from service.offline.evaluation import Trajectory, ate_rmse

log = logging.getLogger("bench.vision_attribution")
RESULTS = Path(__file__).resolve().parent / "results"


def label_identities(obs: list[dict[str, Any]], identity: np.ndarray) -> dict[str, int]:
    """The most common true identity among each label's observations (as vision_frontend)."""
    truths: dict[str, list[int]] = defaultdict(list)
    for frame in obs:
        for label, _, _, c, _ in frame["images"]:
            if c >= 0:
                truths[label].append(int(identity[c]))
    return {lb: Counter(ts).most_common(1)[0][0] for lb, ts in truths.items()}


def variant_observations(
    name: str, frame: dict[str, Any], identity: np.ndarray, label_id: dict[str, int]
) -> tuple[BearingObservation, ...]:
    if name == "oracle":
        return tuple(BearingObservation(b, lb, s) for lb, b, s in frame["oracle"])
    if name == "oracle_shared":
        reported = {f"c{identity[c]}" for _, _, _, c, _ in frame["images"] if c >= 0}
        return tuple(BearingObservation(b, lb, s) for lb, b, s in frame["oracle"] if lb in reported)
    if name in ("truth_corner", "truth_identity"):
        seen: set[str] = set()
        relabelled = []
        for _, bearing, sigma, c, _ in frame["images"]:
            if c < 0:
                continue
            label = f"k{c}" if name == "truth_corner" else f"c{identity[c]}"
            if label not in seen:
                seen.add(label)
                relabelled.append(BearingObservation(bearing, label, sigma))
        return tuple(relabelled)
    scale = float(name.split("_", 1)[1]) if name.startswith("sigma_") else 1.0
    out = []
    for label, bearing, sigma, c, _ in frame["images"]:
        wrong = c >= 0 and label in label_id and int(identity[c]) != label_id[label]
        if name in ("no_wrong", "clean") and wrong:
            continue
        if name in ("no_untrue", "clean") and c < 0:
            continue
        out.append(BearingObservation(bearing, label, sigma * scale))
    return tuple(out)


def run_variant(
    name: str, doc: dict[str, Any], config: SlamConfig, seed: int, truth: Trajectory
) -> dict[str, Any]:
    identity = doc["identity"]
    label_id = label_identities(doc["obs"], identity)
    slam = BearingSlam(config, rng=np.random.default_rng(seed))
    t0 = time.perf_counter()
    n = landmark_obs = 0
    for frame, rec in zip(doc["frames"], doc["obs"], strict=False):
        obs = variant_observations(name, rec, identity, label_id)
        n += len(obs)
        outcome = slam.process(replace(frame, observations=obs), with_covariance=False)
        landmark_obs += len(outcome.observed)
    created = slam.removal_count + len(slam.landmarks)
    rows = slam.trajectory("r1")["r1"]
    est = Trajectory.from_poses(rows[:, 1], rows[:, 2:5])
    return {
        "variant": name,
        "ate_m": ate_rmse(est, truth),
        "observations": n,
        "landmark_observations": landmark_obs,
        "landmarks_created": created,
        "landmark_observations_per_landmark": landmark_obs / max(1, created),
        "seconds": time.perf_counter() - t0,
        "load_average": list(os.getloadavg()),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dump")
    p.add_argument("--variants", default="images,no_wrong,no_untrue,clean,oracle")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--landmark-cap", type=int, default=200)
    p.add_argument("--policy", default="oldest")
    p.add_argument("--pose-window", type=int, default=100)
    p.add_argument("--out", default=None, help="write bench/results/<out>.json")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    with open(args.dump, "rb") as fh:
        doc = pickle.load(fh)
    # The ground truth of the same run (vision_frontend's world and simulation, same seed).
    rng = np.random.default_rng(args.seed)
    world = make_world(rooms=(3, 3), landmarks=9, rng=rng)
    from service.offline.datasets.render import make_textured_world

    make_textured_world(world, rng=rng)
    sim = simulate(world, frames=len(doc["frames"]), rng=rng, door_probability=0.5)
    if "slam_config" in doc:  # the recorded run's own estimator settings
        config = SlamConfig(**doc["slam_config"])
        log.info("the dump's SlamConfig (--landmark-cap, --policy, --pose-window unused)")
    else:
        config = SlamConfig(
            landmark_cap=args.landmark_cap, policy=args.policy, pose_window=args.pose_window
        )
    results = []
    for name in args.variants.split(","):
        res = run_variant(name, doc, config, args.seed, sim.ground_truth)
        log.info("%s", res)
        results.append(res)
    print(json.dumps(results, indent=1))
    if args.out:
        (RESULTS / f"{args.out}.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
