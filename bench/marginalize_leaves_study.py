"""Why iSAM2 ``marginalizeLeaves`` fails, measured on random bearing-only sequences.

Run from the repository root::

    python -m bench.marginalize_leaves_study --seeds 30

Every seed builds one random sequence (a pose chain with ``BetweenFactorPose2``,
``BearingFactor2D`` rays to ``Point2`` landmarks, a weak prior on each new
landmark) and replays it once per variant. Every few steps the oldest landmark
that has been out of view for a while is marginalised:

``a_plain``
    ``marginalizeLeavesWithIndices([l])`` on the tree as iSAM2 left it.
``b_constrained_landmark_only``
    first an empty ``update`` with ``constrainedKeys`` = {l: 0, every other key: 1}
    and ``extraReelimKeys`` = [l]; then marginalise l.
``c_constrained_with_neighbours``
    as (b) but ``extraReelimKeys`` = l and every key sharing a factor with l.
``d_two_landmarks``
    as (c) for the two oldest such landmarks, marginalised in one call.
``e_two_landmarks_plain``
    two landmarks in one call without any preparation (extra, for contrast).
``schur_one`` / ``schur_two``
    the project's route (``graph.isam.IncrementalGraph.update(marginalise=...)``),
    one or two landmarks per update, for comparison.

Each call is classified as clean, an exception (counted by message, with key
names replaced by ``<key>``), or a *silent failure*: the call returned but the
deleted factor indices differ from the landmark's own factors, the number of
live factors dropped differs, the landmark is still in the estimate, or (which
neither indices nor counts reveal) it is still a frontal of a clique in
``ISAM2.dot``. Only
calls made on a consistent iSAM2 are counted; after the first exception or
silent failure a sequence makes no more marginalisation calls but keeps adding
poses, so that failures of later calls (``update``/``calculateEstimate``) can be
attributed to what came before.

Before every ``marginalizeLeaves`` call the script reads the Bayes tree
(``ISAM2.dot``) and replays, symbolically, the bookkeeping of
``ISAM2::marginalizeLeaves`` (gtsam/nonlinear/ISAM2.cpp): which cliques it
removes, which factors it deletes, and under which key each marginal factor is
parked in its ``marginalFactors`` map. The prediction "a marginal factor that
survives to ``variableIndex_.augment`` still mentions a key being marginalised"
is exactly the condition under which ``removeVariables`` ->
``VariableIndex::removeUnusedVariables`` throws "Asking to remove variables from
the variable index that are not unused"; the JSON reports how often the
prediction agrees with what the wheel did, and which branch parked the
offending factor.

Each seed runs in a child process (``--worker``) so that a crash of the
inconsistent iSAM2 after a failure (seen: SIGSEGV in the next ``update``) cannot
take the study down; the worker streams tally snapshots, so a crash is counted
where it happened (in the call, or as a later-call failure after what state).
Results: ``bench/results/marginalize_leaves_study.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from graph.config import SlamConfig
from graph.isam import IncrementalGraph, make_isam

VARIANTS = (
    "a_plain",
    "b_constrained_landmark_only",
    "c_constrained_with_neighbours",
    "d_two_landmarks",
    "e_two_landmarks_plain",
    "schur_one",
    "schur_two",
)
RESULTS = Path(__file__).resolve().parent / "results" / "marginalize_leaves_study.json"
NOT_UNUSED = "Asking to remove variables from the variable index that are not unused"

# Sequence shape (kept small: the whole study must run in well under two minutes).
N_POSES = 60
N_LANDMARKS = 30
WORLD_HALF_WIDTH_M = 12.0
SENSOR_RANGE_M = 6.0
MAX_RAYS_PER_POSE = 8
FIRST_MARGINALISATION = 10
MARGINALISE_EVERY = 3
OUT_OF_VIEW_STEPS = 3
BEARING_SIGMA = math.radians(1.0)
ODOMETRY_SIGMAS = np.array([0.05, 0.05, math.radians(1.0)])


def key_name(key: int) -> str:
    return str(gtsam.DefaultKeyFormatter(key))


# --------------------------------------------------------------------------- sequence
@dataclass
class Step:
    odometry: gtsam.Pose2
    rays: list[tuple[int, float]]  # (landmark id, measured bearing)


@dataclass
class Sequence_:
    landmarks: np.ndarray
    landmark_guess: np.ndarray
    steps: list[Step]


def make_sequence(seed: int) -> Sequence_:
    rng = np.random.default_rng(seed)
    landmarks = rng.uniform(-WORLD_HALF_WIDTH_M, WORLD_HALF_WIDTH_M, size=(N_LANDMARKS, 2))
    guess = landmarks + rng.normal(0.0, 0.3, size=landmarks.shape)
    pose = gtsam.Pose2(0.0, 0.0, 0.0)
    steps: list[Step] = []
    for t in range(N_POSES):
        if t == 0:
            odometry = gtsam.Pose2()
            truth = pose
        else:
            turn = rng.normal(0.0, 0.3)
            if math.hypot(pose.x(), pose.y()) > 0.7 * WORLD_HALF_WIDTH_M:  # steer home
                home = math.atan2(-pose.y(), -pose.x()) - pose.theta()
                turn += 0.5 * math.atan2(math.sin(home), math.cos(home))
            move = gtsam.Pose2(1.0, 0.0, turn)
            truth = pose.compose(move)
            noise = rng.normal(0.0, 1.0, 3) * ODOMETRY_SIGMAS
            odometry = move.compose(gtsam.Pose2(*noise))
        pose = truth
        distance = np.linalg.norm(landmarks - np.array([pose.x(), pose.y()]), axis=1)
        seen = [int(i) for i in np.argsort(distance) if distance[i] < SENSOR_RANGE_M]
        rays = [
            (j, pose.bearing(landmarks[j]).theta() + rng.normal(0.0, BEARING_SIGMA))
            for j in seen[:MAX_RAYS_PER_POSE]
        ]
        steps.append(Step(odometry, rays))
    return Sequence_(landmarks, guess, steps)


class Replay:
    """Turns a sequence into per-step factors, skipping landmarks already marginalised."""

    def __init__(self, seq: Sequence_) -> None:
        self.seq = seq
        self.dead_reckoned = gtsam.Pose2()
        self.in_graph: set[int] = set()
        self.gone: set[int] = set()
        self.last_seen: dict[int, int] = {}
        self.odo_noise = gtsam.noiseModel.Diagonal.Sigmas(ODOMETRY_SIGMAS)
        self.bearing_noise = gtsam.noiseModel.Isotropic.Sigma(1, BEARING_SIGMA)
        self.landmark_prior = gtsam.noiseModel.Isotropic.Sigma(2, 5.0)

    def factors(self, t: int) -> tuple[list[gtsam.NonlinearFactor], gtsam.Values]:
        step = self.seq.steps[t]
        factors: list[gtsam.NonlinearFactor] = []
        values = gtsam.Values()
        if t == 0:
            prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.01]))
            factors.append(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(), prior))
        else:
            self.dead_reckoned = self.dead_reckoned.compose(step.odometry)
            factors.append(gtsam.BetweenFactorPose2(X(t - 1), X(t), step.odometry, self.odo_noise))
        values.insert(X(t), self.dead_reckoned)
        for j, bearing in step.rays:
            if j in self.gone:
                continue
            if j not in self.in_graph:
                self.in_graph.add(j)
                values.insert(L(j), self.seq.landmark_guess[j])
                factors.append(
                    gtsam.PriorFactorPoint2(L(j), self.seq.landmark_guess[j], self.landmark_prior)
                )
            factors.append(
                gtsam.BearingFactor2D(X(t), L(j), gtsam.Rot2(bearing), self.bearing_noise)
            )
            self.last_seen[j] = t
        return factors, values

    def candidates(self, t: int, count: int) -> list[int]:
        """The `count` landmarks out of view longest (oldest last sighting first)."""
        if t < FIRST_MARGINALISATION or t % MARGINALISE_EVERY:
            return []
        old = sorted(
            (seen, j)
            for j, seen in self.last_seen.items()
            if j in self.in_graph and j not in self.gone and seen <= t - OUT_OF_VIEW_STEPS
        )
        if len(old) < count:
            return []
        chosen = [j for _, j in old[:count]]
        self.gone.update(chosen)
        return chosen


# --------------------------------------------------------------------------- Bayes tree
@dataclass
class Clique:
    frontals: list[int]
    separator: list[int]
    parent: str | None = None
    children: list[str] = field(default_factory=list)
    removed: bool = False


def parse_tree(isam: gtsam.ISAM2) -> tuple[dict[str, Clique], dict[int, str]]:
    """Cliques (frontals in elimination order, separator) and key -> clique, from ISAM2.dot."""
    text = isam.dot(lambda k: str(int(k)))
    cliques: dict[str, Clique] = {}
    for cid, label in re.findall(r'^(\d+)\[label="([^"]*)"\];', text, re.MULTILINE):
        front, _, sep = label.partition(":")
        cliques[cid] = Clique(
            [int(s) for s in front.replace(",", " ").split()],
            [int(s) for s in sep.replace(",", " ").split()],
        )
    for parent, child in re.findall(r"^(\d+)->(\d+)$", text, re.MULTILINE):
        cliques[parent].children.append(child)
        cliques[child].parent = parent
    node = {k: cid for cid, c in cliques.items() for k in c.frontals}
    return cliques, node


def factor_tables(isam: gtsam.ISAM2) -> tuple[dict[int, set[int]], dict[int, frozenset[int]]]:
    """key -> factor indices, and factor index -> keys, over the live factors."""
    graph = isam.getFactorsUnsafe()
    index: dict[int, set[int]] = {}
    keys_of: dict[int, frozenset[int]] = {}
    for i in range(graph.size()):
        factor = graph.at(i)
        if factor is None:
            continue
        keys_of[i] = frozenset(int(k) for k in factor.keys())
        for k in keys_of[i]:
            index.setdefault(k, set()).add(i)
    return index, keys_of


def structurally_non_leaf(
    cliques: dict[str, Clique], node: dict[int, str], keys: Sequence[int]
) -> bool:
    """True if a variable outside `keys` is eliminated before some key and depends on it."""
    wanted = set(keys)

    def subtree_frontals(cid: str) -> set[int]:
        out: set[int] = set()
        stack = [cid]
        while stack:
            c = cliques[stack.pop()]
            out.update(c.frontals)
            stack.extend(c.children)
        return out

    for k in keys:
        clique = cliques[node[k]]
        before = clique.frontals[: clique.frontals.index(k)]
        if any(f not in wanted for f in before):
            return True
        for child in clique.children:
            if k in cliques[child].separator and subtree_frontals(child) - wanted:
                return True
    return False


@dataclass
class Prediction:
    deleted: set[int]
    collateral: set[int]  # frontals of removed cliques that were not asked for
    left_in_tree: set[int]  # asked-for keys not split off their clique (nToRemove too small)
    offending: list[dict[str, Any]]  # surviving marginal factors mentioning an asked-for key

    @property
    def not_unused(self) -> bool:
        return bool(self.offending)


def simulate_marginalize_leaves(
    cliques: dict[str, Clique],
    node: dict[int, str],
    index: dict[int, set[int]],
    keys_of: dict[int, frozenset[int]],
    leaf_keys: Iterable[int],
) -> Prediction:
    """Symbolic replay of ISAM2::marginalizeLeaves (gtsam 4.3, ISAM2.cpp), release build.

    Tracks keys only: a clique's ``cachedFactor`` is a factor on its separator; a
    re-elimination of some frontals yields one factor on every other key of the
    gathered graph. ``marginalFactors`` is keyed by a clique's *current* first key,
    exactly as in the C++ (``cg->front()``), including after a clique was split.
    """
    leaf = set(leaf_keys)
    marginal: dict[int, list[tuple[frozenset[int], str]]] = {}
    removed_leaf: set[int] = set()
    deleted: set[int] = set()
    collateral: set[int] = set()
    left_in_tree: set[int] = set()
    climbed_to: dict[int, int] = {}

    def remove_subtree(root: str) -> list[str]:
        parent = cliques[root].parent
        if parent is not None:
            cliques[parent].children.remove(root)
        out: list[str] = []
        stack = [root]
        while stack:
            cid = stack.pop()
            out.append(cid)
            stack.extend(cliques[cid].children)
        for cid in out:
            c = cliques[cid]
            c.removed = True
            marginal.pop(c.frontals[0], None)  # marginalFactors.erase(cg->front())
            removed_leaf.update(c.frontals)
            for f in c.frontals:
                deleted.update(index.get(f, ()))
                if f not in leaf:  # the "not a leaf" throw is #if !defined(NDEBUG)
                    collateral.add(f)
        return out

    for j in sorted(leaf):  # KeySet iterates in key order
        if j in removed_leaf:
            continue
        cid = node[j]
        while True:
            parent = cliques[cid].parent
            if parent is not None and cliques[parent].frontals[0] in leaf:
                cid = parent
            else:
                break
        clique = cliques[cid]
        climbed_to[j] = clique.frontals[0]
        if all(f in leaf for f in clique.frontals):
            if clique.parent is not None:
                under = cliques[clique.parent].frontals[0]
                marginal.setdefault(under, []).append(
                    (frozenset(clique.separator), "whole clique: cachedFactor parked on parent")
                )
            remove_subtree(cid)
            continue
        graph_keys: set[int] = set()
        subtrees = [ch for ch in clique.children if any(p in leaf for p in cliques[ch].separator)]
        for ch in subtrees:
            graph_keys.update(cliques[ch].separator)
        removed_children: list[str] = []
        for ch in subtrees:
            removed_children.extend(remove_subtree(ch))
        step1: set[int] = set()
        for f in clique.frontals:
            if f in leaf:
                step1.update(index.get(f, ()))
        for rc in removed_children:
            for f in cliques[rc].frontals:
                step1.difference_update(index.get(f, ()))
        for fi in step1:
            graph_keys.update(keys_of[fi])
        eliminate = sorted(set(clique.frontals) & leaf)
        remaining = frozenset(graph_keys - set(eliminate))
        if remaining:
            marginal.setdefault(clique.frontals[0], []).append(
                (remaining, "split clique: re-eliminated marginal parked on old front")
            )
        all_keys = clique.frontals + clique.separator
        n_remove = 0
        while n_remove < len(all_keys) and all_keys[n_remove] in leaf:
            n_remove += 1
        left_in_tree.update(set(eliminate) - set(all_keys[:n_remove]))
        clique.frontals = clique.frontals[n_remove:]
        for f in eliminate:
            deleted.update(index.get(f, ()))
        removed_leaf.update(eliminate)

    # A key whose clique was skipped (the climb above jumped to an ancestor whose
    # front is another marginalised key, and that ancestor was only split) is never
    # eliminated: its own factors stay in variableIndex_.
    offending: list[dict[str, Any]] = [
        {
            "branch": "climbed to a split ancestor: key's own clique never eliminated",
            "mentions": [key_name(k)],
            "still_referenced_by": sorted(
                "-".join(sorted(key_name(x) for x in keys_of[i])) for i in index.get(k, ())
            )[:3],
            "climbed_to_front": key_name(climbed_to[k]),
        }
        for k in sorted(leaf - removed_leaf)
    ]
    offending += [
        {
            "parked_under": key_name(under),
            "parked_under_is_marginalised": under in leaf,
            "branch": branch,
            "mentions": sorted(key_name(k) for k in keys & leaf),
        }
        for under, parked in marginal.items()
        for keys, branch in parked
        if keys & leaf
    ]
    return Prediction(deleted, collateral, left_in_tree, offending)


# --------------------------------------------------------------------------- running
def normalise(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    text = re.sub(r"'[a-z]\d+'", "'<key>'", text)
    text = re.sub(r"\b[a-z]\d+\b", "<key>", text)
    return f"{type(exc).__name__}: {text[:140]}"


def key_list(keys: Iterable[int]) -> gtsam.KeyList:
    out = gtsam.KeyList()
    for k in keys:
        out.push_back(k)
    return out


def prepare(isam: gtsam.ISAM2, keys: Sequence[int], with_neighbours: bool) -> None:
    """Empty update that re-eliminates `keys` first (constrained group 0, every other key 1)."""
    index, keys_of = factor_tables(isam)
    groups = gtsam.KeyGroupMap()
    for k in isam.getLinearizationPoint().keys():
        groups.insert2(k, 0 if k in keys else 1)
    reelim = set(keys)
    if with_neighbours:
        for k in keys:
            for fi in index.get(k, ()):
                reelim.update(keys_of[fi])
    params = gtsam.ISAM2UpdateParams()
    params.constrainedKeys = groups
    params.extraReelimKeys = key_list(sorted(reelim))
    isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), params)


@dataclass
class Tally:
    calls: int = 0
    clean: int = 0
    exceptions: Counter[str] = field(default_factory=Counter)
    silent: Counter[str] = field(default_factory=Counter)
    silent_calls: int = 0
    later: dict[str, Counter[str]] = field(
        default_factory=lambda: {
            "after_clean": Counter(),
            "after_silent": Counter(),
            "after_exception": Counter(),
        }
    )
    crashes: int = 0
    non_leaf_calls: int = 0
    outcome_by_leafness: Counter[str] = field(default_factory=Counter)
    prediction: Counter[str] = field(default_factory=Counter)
    not_unused_branch: Counter[str] = field(default_factory=Counter)
    silent_mechanism: Counter[str] = field(default_factory=Counter)
    examples: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {
            "marginalise_calls": self.calls,
            "clean": self.clean,
            "exceptions": dict(self.exceptions),
            "silent_failures": self.silent_calls,
            "silent_failure_reasons": dict(self.silent),
            "later_call_failures": {k: dict(v) for k, v in self.later.items()},
            "crashes": self.crashes,
            "structurally_non_leaf_calls": self.non_leaf_calls,
            "outcome_by_leafness": dict(self.outcome_by_leafness),
            "prediction_vs_actual": dict(self.prediction),
            "not_unused_cause": dict(self.not_unused_branch),
            "silent_failure_mechanism_predicted": dict(self.silent_mechanism),
            "examples": self.examples,
            "seconds": round(self.seconds, 2),
        }

    def merge(self, other: dict[str, Any]) -> None:
        self.calls += other["marginalise_calls"]
        self.clean += other["clean"]
        self.exceptions.update(other["exceptions"])
        self.silent_calls += other["silent_failures"]
        self.silent.update(other["silent_failure_reasons"])
        for k, v in other["later_call_failures"].items():
            self.later[k].update(v)
        self.crashes += other["crashes"]
        self.non_leaf_calls += other["structurally_non_leaf_calls"]
        self.outcome_by_leafness.update(other["outcome_by_leafness"])
        self.prediction.update(other["prediction_vs_actual"])
        self.not_unused_branch.update(other["not_unused_cause"])
        self.silent_mechanism.update(other["silent_failure_mechanism_predicted"])
        self.examples.extend(other["examples"][: max(0, 4 - len(self.examples))])
        self.seconds += other["seconds"]


def live_factor_count(isam: gtsam.ISAM2) -> int:
    graph = isam.getFactorsUnsafe()
    return sum(1 for i in range(graph.size()) if graph.at(i) is not None)


def marginalise_leaves(isam: gtsam.ISAM2, keys: list[int], variant: str, tally: Tally) -> str:
    """One marginalisation call; returns 'clean', 'silent' or 'exception'."""
    if variant not in ("a_plain", "e_two_landmarks_plain"):
        prepare(isam, keys, with_neighbours=variant != "b_constrained_landmark_only")
    index, keys_of = factor_tables(isam)
    expected = set().union(*(index[k] for k in keys))
    cliques, node = parse_tree(isam)
    non_leaf = structurally_non_leaf(cliques, node, keys)
    prediction = simulate_marginalize_leaves(cliques, node, index, keys_of, keys)
    before = live_factor_count(isam)
    tally.calls += 1
    tally.non_leaf_calls += non_leaf
    leafness = "non_leaf" if non_leaf else "leaf"
    try:
        marginal_indices, deleted = isam.marginalizeLeavesWithIndices(key_list(keys))
    except Exception as exc:
        message = normalise(exc)
        tally.exceptions[message] += 1
        tally.outcome_by_leafness[f"{leafness}:exception"] += 1
        actual_not_unused = NOT_UNUSED in str(exc)
        tally.prediction[
            f"predicted_not_unused={prediction.not_unused},actual_not_unused={actual_not_unused}"
        ] += 1
        if actual_not_unused:
            for item in prediction.offending:
                tally.not_unused_branch[item["branch"]] += 1
            if len(tally.examples) < 4:
                tally.examples.append(
                    {
                        "keys": [key_name(k) for k in keys],
                        "offending_marginal_factors": prediction.offending,
                        "collateral_non_leaf_keys": sorted(map(key_name, prediction.collateral)),
                    }
                )
        return "exception"
    dropped = before - live_factor_count(isam) + len(marginal_indices)
    reasons = []
    if set(deleted) != expected:
        reasons.append("deleted indices != landmark's factors")
    if dropped != len(expected):
        reasons.append("factors dropped != landmark's factor count")
    if any(isam.valueExists(k) for k in keys):
        reasons.append("landmark still in estimate")
    _, node_after = parse_tree(isam)
    if any(k in node_after for k in keys):
        # Not visible through indices or factor counts: the key was erased from
        # theta/delta/nodes_ but still sits in a clique's conditional.
        reasons.append("landmark still in a Bayes-tree conditional")
    agree_deleted = set(deleted) == prediction.deleted
    tally.prediction[f"predicted_not_unused={prediction.not_unused},actual_not_unused=False"] += 1
    tally.prediction[f"predicted_deleted_set_matches={agree_deleted}"] += 1
    if not reasons:
        tally.clean += 1
        tally.outcome_by_leafness[f"{leafness}:clean"] += 1
        return "clean"
    tally.silent_calls += 1
    tally.silent.update(reasons)
    tally.outcome_by_leafness[f"{leafness}:silent"] += 1
    tally.prediction[
        f"silent_predicted_by_collateral_or_left_in_tree="
        f"{bool(prediction.collateral or prediction.left_in_tree)}"
    ] += 1
    if prediction.collateral:
        tally.silent_mechanism["cliques of non-marginalised keys removed (collateral)"] += 1
    if prediction.left_in_tree:
        tally.silent_mechanism["marginalised key not first in its clique, left in tree"] += 1
    return "silent"


def snapshot(variant: str, phase: str, tally: Tally) -> None:
    """Stream the tally so a crash of this process can be attributed (see run_seed)."""
    print(json.dumps({"variant": variant, "phase": phase, "tally": tally.to_json()}), flush=True)


def run_isam_variant(seq: Sequence_, variant: str) -> Tally:
    tally = Tally()
    replay = Replay(seq)
    isam = make_isam(SlamConfig())
    state = "clean"
    per_call = 2 if variant in ("d_two_landmarks", "e_two_landmarks_plain") else 1
    for t in range(len(seq.steps)):
        factors, values = replay.factors(t)
        graph = gtsam.NonlinearFactorGraph()
        for f in factors:
            graph.add(f)
        try:
            isam.update(graph, values)
            isam.calculateEstimate()
        except Exception as exc:
            tally.later[f"after_{state}"][normalise(exc)] += 1
            return tally
        if state != "clean":
            continue
        chosen = replay.candidates(t, per_call)
        if not chosen:
            continue
        snapshot(variant, "marginalise", tally)
        outcome = marginalise_leaves(isam, [L(j) for j in chosen], variant, tally)
        if outcome != "clean":
            state = outcome
        snapshot(variant, f"after_{state}", tally)
        try:
            isam.calculateEstimate()
        except Exception as exc:
            tally.later[f"after_{state}"][normalise(exc)] += 1
            return tally
    return tally


def run_schur_variant(seq: Sequence_, variant: str) -> Tally:
    tally = Tally()
    replay = Replay(seq)
    graph = IncrementalGraph(SlamConfig())
    per_call = 2 if variant == "schur_two" else 1
    state = "clean"
    for t in range(len(seq.steps)):
        factors, values = replay.factors(t)
        chosen = [L(j) for j in replay.candidates(t, per_call)] if state == "clean" else []
        expected = {i for k in chosen for i in graph.factors_of(k)}
        before = graph.num_factors
        try:
            graph.update(factors, values, marginalise=chosen)
            graph.estimate()
        except Exception as exc:
            if chosen:
                tally.calls += 1
                tally.exceptions[normalise(exc)] += 1
                state = "exception"
            else:
                tally.later[f"after_{state}"][normalise(exc)] += 1
            return tally
        if not chosen:
            continue
        tally.calls += 1
        internal = live_factor_count(graph._isam)
        n_marginals = graph.num_factors - before + len(expected) - len(factors)
        reasons = []
        if any(k in graph or graph.linearization_point().exists(k) for k in chosen):
            reasons.append("landmark still in estimate")
        if internal != graph.num_factors:
            reasons.append("iSAM2 live factors != bookkeeping")
        if any(graph.factors_of(k) for k in chosen) or n_marginals < 0:
            reasons.append("factors dropped != landmark's factor count")
        if reasons:
            tally.silent_calls += 1
            tally.silent.update(reasons)
            state = "silent"
        else:
            tally.clean += 1
    return tally


def run_worker(seed: int, variants: Sequence[str]) -> None:
    seq = make_sequence(seed)
    for variant in variants:
        start = time.perf_counter()
        if variant.startswith("schur"):
            tally = run_schur_variant(seq, variant)
        else:
            tally = run_isam_variant(seq, variant)
        tally.seconds = time.perf_counter() - start
        snapshot(variant, "done", tally)


def run_seed(seed: int, variants: Sequence[str]) -> list[tuple[str, dict[str, Any]]]:
    """All variants of one seed in child processes; a crashed variant is counted and skipped."""
    done: list[tuple[str, dict[str, Any]]] = []
    remaining = list(variants)
    repo = Path(__file__).resolve().parent.parent
    while remaining:
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "bench.marginalize_leaves_study",
                "--worker",
                str(seed),
                "--variants",
                ",".join(remaining),
            ],
            cwd=repo,
            capture_output=True,
            text=True,
            check=False,
        )
        last: dict[str, Any] | None = None
        for line in proc.stdout.splitlines():
            if not line.startswith("{"):
                continue
            record = json.loads(line)
            if record["phase"] == "done":
                done.append((record["variant"], record["tally"]))
                remaining.remove(record["variant"])
                last = None
            else:
                last = record
        if proc.returncode == 0 or not remaining:
            continue
        variant = remaining.pop(0)
        crash = f"crash (exit {proc.returncode})"
        tally = Tally()
        if last is not None and last["variant"] == variant:
            tally.merge(last["tally"])
            if last["phase"] == "marginalise":
                tally.calls += 1
                tally.exceptions[crash] += 1
            else:
                tally.later[last["phase"]][crash] += 1
        tally.crashes += 1
        done.append((variant, tally.to_json()))
    return done


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seeds", type=int, default=30)
    parser.add_argument("--jobs", type=int, default=2, help="child processes at once")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    unknown = set(variants) - set(VARIANTS)
    if unknown:
        parser.error(f"unknown variants {sorted(unknown)}")
    if args.worker is not None:
        run_worker(args.worker, variants)
        return

    start = time.perf_counter()
    totals = {v: Tally() for v in variants}
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for results in pool.map(lambda s: run_seed(s, variants), range(args.seeds)):
            for variant, record in results:
                totals[variant].merge(record)
    report = {
        "study": "iSAM2.marginalizeLeaves failure modes on random bearing-only sequences",
        "seeds": args.seeds,
        "sequence": {
            "poses": N_POSES,
            "landmarks": N_LANDMARKS,
            "sensor_range_m": SENSOR_RANGE_M,
            "marginalise_from_step": FIRST_MARGINALISATION,
            "marginalise_every_steps": MARGINALISE_EVERY,
            "out_of_view_steps": OUT_OF_VIEW_STEPS,
            "isam_params": "graph.isam.make_isam(SlamConfig())",
        },
        "variants": {v: t.to_json() for v, t in totals.items()},
        "elapsed_s": round(time.perf_counter() - start, 1),
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(report, indent=2, sort_keys=True) + "\n")
    for variant, tally in totals.items():
        summary = tally.to_json()
        print(
            f"{variant:32s} calls={summary['marginalise_calls']:4d} clean={summary['clean']:4d} "
            f"silent={summary['silent_failures']:3d} crashes={summary['crashes']}"
        )
        for message, count in summary["exceptions"].items():
            print(f"    exception x{count}: {message}")
        for where, counter in summary["later_call_failures"].items():
            for message, count in counter.items():
                print(f"    later ({where}) x{count}: {message}")
    print(f"wrote {args.output} in {report['elapsed_s']} s")


if __name__ == "__main__":
    main()
