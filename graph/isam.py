"""iSAM2 with factor bookkeeping and exact marginalisation by Schur complement.

Marginalising a set of variables M (landmarks or old poses):

1. take every factor that touches M, linearise it at iSAM2's linearisation
   point theta;
2. eliminate M from that small Gaussian graph
   (``eliminatePartialMultifrontal(Ordering(M))``); what remains is the marginal
   (Schur complement) on M's neighbours;
3. wrap it in a ``LinearContainerFactor`` at theta and hand it to iSAM2 in the
   same update that removes M's factors. M's variables are then unused and
   iSAM2 drops them itself.

Why not ``ISAM2.marginalizeLeaves``: it edits the Bayes tree in place and
trusts its caller. Its "not a leaf" check sits under ``#if !defined(NDEBUG)``
and is absent from the wheel, so a non-leaf key silently takes other cliques
and their factors with it, or stays in a conditional. With several keys per
call it also throws "Asking to remove variables from the variable index that
are not unused", even for true leaves: when one marginalised key heads a clique
shared with a kept key, the loop that climbs from another marginalised key's
clique stops there and never eliminates the lower key, whose own factors are
still indexed when ``removeVariables`` runs (``VariableIndex::
removeUnusedVariables`` throws; that check is never compiled out).

The Schur route reaches neither failure: it never edits the tree's structure.
It removes factors and adds a marginal from which M has been eliminated;
``ISAM2.update`` drops a key only after ``computeUnusedKeys`` found its index
entry empty, and rebuilds the affected cliques by re-elimination, which needs
no leaf. ``bench/marginalize_leaves_study.py`` measures both routes (0 failures
in 747 Schur marginalisations; the leaf route's failures by variant).
"""

from __future__ import annotations

import logging
import math
import sys
from collections.abc import Callable, Iterable, Sequence
from itertools import chain

import gtsam
import numpy as np
from numpy.typing import NDArray

from graph.config import SlamConfig
from graph.errors import EstimationError
from graph.factors import is_landmark_key, landmark_key_mask
from graph.relative import RelativeMarginalFactor, choose_reference, relative_marginal
from graph.sparsify import tree_factors

log = logging.getLogger(__name__)


_NEVER = 2**31 - 1
"""An iSAM2 relinearisation interval no map reaches."""


def _relinearize_interval(config: SlamConfig) -> int:
    """iSAM2's relinearizeSkip for `config`: with upkeep "after_frame" the upkeep
    relinearises (IncrementalGraph.relinearise), never an update."""
    return _NEVER if config.upkeep == "after_frame" else config.relinearize_skip


def make_isam(config: SlamConfig, *, factorization: str = "CHOLESKY") -> gtsam.ISAM2:
    """iSAM2 for `config`; `factorization` "CHOLESKY" (iSAM2's default, the faster) or
    "QR" (see IncrementalGraph.update)."""
    params = gtsam.ISAM2Params()
    params.setFactorization(factorization)
    if config.optimizer == "dogleg":
        params.setOptimizationParams(gtsam.ISAM2DoglegParams())
    else:
        params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams())
    params.setRelinearizeThreshold(config.relinearize_threshold)
    params.relinearizeSkip = _relinearize_interval(config)
    params.findUnusedFactorSlots = True
    return gtsam.ISAM2(params)


_EMPTY_SET_BYTES = sys.getsizeof(set())


def _sparse(indices: set[int]) -> bool:
    """Whether a set's hash table has more than 16 slots per element (and over 1 KiB).

    A Python set never shrinks its table when elements are discarded. A landmark's set
    of factor indices grows with the bearings of every keyframe that saw it (hundreds
    on the dense lifelong world) and kept that table once those factors had left: after
    that run's busiest stretch the index's sets took ~1.2 MiB, ~0.3 MiB as fresh
    copies. A set that grew by insertion has at most 8 slots per element, so only a set
    that lost most of its elements is rebuilt (to 2-4 slots per element). Where a set's
    elements sit in its table matters nowhere: its readers sort or intersect."""
    size = sys.getsizeof(indices)
    return size > 1024 and size > 256 * len(indices) + _EMPTY_SET_BYTES


def _copy_value(target: gtsam.Values, key: int, source: gtsam.Values) -> None:
    """Insert `source`'s value of `key` (a Point2 landmark or a Pose2) into `target`."""
    if is_landmark_key(key):
        target.insert(key, source.atPoint2(key))
    else:
        target.insert(key, source.atPose2(key))


class IncrementalGraph:
    """An iSAM2 instance plus the index of which factor touches which key."""

    def __init__(self, config: SlamConfig) -> None:
        self._config = config
        self._isam = make_isam(config)
        self._theta: gtsam.Values = self._isam.getLinearizationPoint()
        """iSAM2's own linearisation point, held by a Python wrapper for iSAM2's lifetime.
        pybind11 passes a C++ ``Values`` to a Python factor's callback (the relative
        marginals) by reusing the object's registered wrapper if it has one, and by
        copying every variable otherwise: with ~400 variables, those copies were ~20 % of
        a MRCLAM-6 run's time. Held, every callback on the linearisation point (all
        linearisations, dogleg's error at the current point) gets it without a copy."""
        self._relative = config.relative_marginals
        self._factors: dict[int, gtsam.NonlinearFactor] = {}
        self._key_factors: dict[int, set[int]] = {}
        self._estimate: gtsam.Values | None = None
        self._estimate_poses: tuple[NDArray[np.uint64], NDArray[np.float64]] | None = None
        """The estimate's Pose2 keys (sorted) and their x, y, theta (`poses_xytheta`)."""
        self._pose_cache: dict[int, gtsam.Pose2] = {}
        self._point_cache: dict[int, NDArray[np.float64]] = {}
        """Estimates of single variables asked for since the last update. A frame needs a
        handful of them, and the whole estimate is a copy of every variable. The first
        read after an update costs more either way: it makes iSAM2 compute its delta
        (dogleg's step evaluates the whole graph's error)."""
        self._cov_cache: dict[int, NDArray[np.float64]] = {}
        """Marginal covariances of poses asked for since the last update."""
        self._marginals: set[int] = set()
        """Indices of the marginal factors (relative or linear; not those that are
        between factors, which are evaluated in C++)."""
        self.marginal_keys: list[tuple[int, ...]] = []
        """Keys of every marginal factor added since the caller last cleared this."""
        self.sparsifications = 0
        """Marginal factors replaced by their Chow-Liu tree (see `update`'s `sparsify`)."""
        self.sparsifications_refused = 0
        """Marginal factors kept exact because their tree would lose a direction."""
        self.sparsification_kl: list[float] | None = None
        """Set to a list, KL(exact || tree) in nats of every later sparsification is
        appended to it (an evaluation's measure; every tree computes it)."""
        self.held_back_updates = 0
        """Updates that held variables back from relinearisation (relinearise_budget)."""
        self.holding = False
        """The last update held variables back (relinearise_budget)."""
        self.relinearising = False
        """Updates relinearise though iSAM2's interval says not to (BearingSlam sets it
        during an upkeep with SlamConfig.upkeep "after_frame": the upkeep's updates then
        relinearise as a frame's do, the frame's own update does not)."""
        self.root_keys: tuple[int, ...] = ()
        """Variables the updates keep at the Bayes tree's root (BearingSlam sets them
        during an upkeep: the keys the next frame's factors will touch). iSAM2 orders the
        variables an update re-eliminates with those of its new factors last, at the root;
        an upkeep's new factors are marginals on old keyframes and landmarks, so without
        this the robot's latest pose sinks below them and the next frame's odometry
        factor re-eliminates everything above it."""

    # ------------------------------------------------------------------ queries
    def __contains__(self, key: int) -> bool:
        return key in self._key_factors

    @property
    def num_factors(self) -> int:
        return len(self._factors)

    @property
    def num_variables(self) -> int:
        return len(self._key_factors)

    def factors_of(self, key: int) -> list[int]:
        return sorted(self._key_factors.get(key, ()))

    def is_bearing(self, index: int) -> bool:
        return isinstance(self._factors[index], gtsam.BearingFactor2D)

    def marginals_touching(self, keys: Iterable[int]) -> int:
        """How many marginal factors (evaluated in Python or held linear) touch `keys`."""
        touching = chain.from_iterable(self._key_factors.get(k, ()) for k in keys)
        return len(self._marginals.intersection(touching))

    def factor_keys(self, index: int) -> tuple[int, ...]:
        return tuple(self._factors[index].keys())

    def neighbourhoods(self, key: int) -> list[tuple[int, ...]]:
        """The keys of every factor that touches `key`."""
        return [tuple(self._factors[i].keys()) for i in self.factors_of(key)]

    def marginal_spans(self, keys: Sequence[int]) -> list[frozenset[int]]:
        """The key sets of the marginal factors that marginalising `keys` would add: one
        per group of `keys` linked through shared factors (the multifrontal elimination
        of a group leaves one factor on every other key its factors touch). Bookkeeping
        only: nothing is linearised."""
        marginalised = set(keys)
        group = {k: k for k in marginalised}

        def root(k: int) -> int:
            while group[k] != k:
                group[k] = group[group[k]]
                k = group[k]
            return k

        touched: dict[int, list[int]] = {}
        for k in marginalised:
            for keys_of in self.neighbourhoods(k):
                touched.setdefault(k, []).extend(keys_of)
                for other in keys_of:
                    if other in marginalised:
                        group[root(other)] = root(k)
        spans: dict[int, set[int]] = {}
        for k, factor_keys in touched.items():
            spans.setdefault(root(k), set()).update(x for x in factor_keys if x not in marginalised)
        return [frozenset(s) for s in spans.values() if s]

    def estimate(self) -> gtsam.Values:
        """The current estimate of every variable (cached until the next update)."""
        if self._estimate is None:
            self._estimate = self._isam.calculateEstimate()
        return self._estimate

    def poses_xytheta(self, keys: NDArray[np.uint64]) -> NDArray[np.float64]:
        """(N, 3) x, y, theta of the current estimate of Pose2 variables `keys`, the values
        ``estimate().atPose2(key)`` gives, read from the whole estimate at once (one
        ``extractPose2``, not a wrapper object and three calls per pose)."""
        if self._estimate_poses is None:
            # The graph's variables are poses and landmarks; extractPose2 gives the poses
            # in key order, as Values holds them.
            estimate = self.estimate()
            every = np.fromiter(estimate.keys(), dtype=np.uint64)
            xytheta = np.asarray(gtsam.utilities.extractPose2(estimate), dtype=np.float64)
            self._estimate_poses = (every[~landmark_key_mask(every)], xytheta.reshape(-1, 3))
        poses, xytheta = self._estimate_poses
        idx = np.searchsorted(poses, keys)
        missing = idx >= len(poses)
        if missing.any() or (poses[idx[~missing]] != keys[~missing]).any():
            raise RuntimeError("poses_xytheta: a key the estimate has no pose for")
        return xytheta[idx]

    def pose(self, key: int) -> gtsam.Pose2:
        """The current estimate of one pose: its linearisation point retracted by its
        delta, as calculateEstimate() gives it, without computing every variable."""
        pose = self._pose_cache.get(key)
        if pose is None:
            pose = self._pose_cache[key] = self._isam.calculateEstimatePose2(key)
        return pose

    def point(self, key: int) -> NDArray[np.float64]:
        xy = self._point_cache.get(key)
        if xy is None:
            xy = np.asarray(self._isam.calculateEstimatePoint2(key), dtype=np.float64)
            xy.setflags(write=False)  # shared with the cache: a caller may not edit it
            self._point_cache[key] = xy
        return xy

    def points(self, keys: Sequence[int]) -> NDArray[np.float64]:
        """(N, 2) current estimates of Point2 variables."""
        if not keys:
            return np.zeros((0, 2))
        return np.array([self.point(k) for k in keys], dtype=np.float64)

    def poses_xyt(self, keys: Sequence[int]) -> NDArray[np.float64]:
        """(N, 3) current estimates (x, y, theta) of Pose2 variables."""
        if not keys:
            return np.zeros((0, 3))
        poses = [self.pose(k) for k in keys]
        return np.array([(p.x(), p.y(), p.theta()) for p in poses], dtype=np.float64)

    def pose_covariance(self, key: int) -> NDArray[np.float64]:
        """(3, 3) marginal covariance of a pose (x, y, theta in its own frame); cached
        until the next update (tracked frames ask for their base pose's, read-only)."""
        cov = self._cov_cache.get(key)
        if cov is None:
            cov = np.asarray(self._isam.marginalCovariance(key), dtype=np.float64)
            cov.setflags(write=False)
            self._cov_cache[key] = cov
        return cov

    def landmark_covariances(self, keys: Sequence[int]) -> NDArray[np.float64]:
        """(N, 2, 2) marginal covariances of landmarks from one joint marginal."""
        if not keys:
            return np.zeros((0, 2, 2))
        joint = self._joint_marginal(keys)
        return np.stack([np.asarray(joint.at(k, k)) for k in keys])

    def landmark_joint_covariance(self, keys: Sequence[int]) -> NDArray[np.float64]:
        """(2N, 2N) joint marginal covariance of landmarks, in the order of `keys`."""
        joint = self._joint_marginal(keys)
        return np.block([[np.asarray(joint.at(a, b)) for b in keys] for a in keys])

    def _joint_marginal(self, keys: Sequence[int]) -> gtsam.JointMarginal:
        return self._isam.jointMarginalCovariance(gtsam.KeyVector(list(keys)))

    def nonlinear_graph(self) -> gtsam.NonlinearFactorGraph:
        """The current factors as one graph (for batch checks and snapshots)."""
        graph = gtsam.NonlinearFactorGraph()
        for index in sorted(self._factors):
            graph.add(self._factors[index])
        return graph

    def linearization_point(self) -> gtsam.Values:
        return self._theta

    # ------------------------------------------------------------------ update
    def relinearise(self) -> None:
        """Relinearise, in a step of its own, every variable whose delta exceeds the
        relinearisation threshold (with SlamConfig.upkeep "after_frame", updates do
        not; with relinearise_budget, those the updates held back too)."""
        try:
            self._isam.update(
                gtsam.NonlinearFactorGraph(),
                gtsam.Values(),
                constrainedKeys=self._root_groups(()),
                force_relinearize=True,
            )
            self.holding = False
        except RuntimeError as exc:  # gtsam's IndeterminantLinearSystem etc.
            raise EstimationError(str(exc)) from exc
        finally:
            self._forget_estimate()

    def _root_groups(self, leaving: Iterable[int]) -> gtsam.KeyGroupMap | None:
        """root_keys still in the graph after an update that removes `leaving`, as
        iSAM2's constrained ordering (group 1: eliminated last); None when there are none
        (iSAM2 then puts the new factors' variables last)."""
        if not self.root_keys:
            return None
        gone = set(leaving)
        keys = [k for k in self.root_keys if k in self._key_factors and k not in gone]
        if not keys:
            return None
        groups = gtsam.KeyGroupMap()
        for key in keys:
            groups.insert2(key, 1)
        return groups

    def _relinearises(self) -> bool:
        """Whether the next update relinearises (iSAM2 checks every update when
        relinearize_skip is 1; BearingSlam forces it in an "after_frame" upkeep)."""
        return self.relinearising or _relinearize_interval(self._config) == 1

    def _held_back(self) -> gtsam.KeyList | None:
        """The variables past the relinearisation threshold that the next update must not
        relinearise (SlamConfig.relinearise_budget), or None: the farthest-moved first,
        until the relative marginals on them would exceed the
        budget; a variable that adds none of them is never held back, nor the first."""
        budget = self._config.relinearise_budget
        if budget is None or self._config.upkeep == "in_frame" or not self._marginals:
            return None
        keys = np.fromiter(self._theta.keys(), dtype=np.uint64)
        if keys.size == 0:
            return None
        moved = np.abs(self._isam.getDelta().vector())
        dims = np.where(landmark_key_mask(keys), 2, 3)
        starts = np.concatenate([[0], np.cumsum(dims)[:-1]])
        largest = np.maximum.reduceat(moved, starts)
        over = np.flatnonzero(largest >= self._config.relinearize_threshold)
        if over.size == 0:
            return None
        taken: set[int] = set()
        held = gtsam.KeyList()
        for i in over[np.argsort(-largest[over], kind="stable")]:
            key = int(keys[i])
            more = self._marginals.intersection(self._key_factors.get(key, ())) - taken
            if taken and len(taken) + len(more) > budget:
                held.push_back(key)
            else:
                taken |= more
        if not held.size():
            return None
        self.held_back_updates += 1
        self.holding = True
        return held

    def _forget_estimate(self) -> None:
        self._estimate = None
        self._estimate_poses = None
        self._pose_cache = {}
        self._point_cache = {}
        self._cov_cache = {}

    def update(
        self,
        factors: Iterable[gtsam.NonlinearFactor] = (),
        values: gtsam.Values | None = None,
        *,
        marginalise: Sequence[int] = (),
        drop: Sequence[int] = (),
        then_marginalise: Sequence[int] = (),
        sparsify: Callable[[Sequence[int]], bool] | None = None,
    ) -> None:
        """Add factors (and new variables' initial values) and marginalise keys, in one step.

        `drop`: indices of factors removed without keeping their information (the
        marginalisation of `marginalise` does not see them). `then_marginalise`: keys
        marginalised next, from the factors left by the first Schur complement (its
        marginals included), in the same iSAM2 update: the marginal is the one two
        updates would leave, but iSAM2 never holds the first marginals. Poses
        marginalised on their own get relative marginals, which a joint elimination with
        a landmark would not (see _schur_complement). `sparsify`: a marginal factor over
        keys for which it is true is replaced by its Chow-Liu tree (graph.sparsify)."""
        new = gtsam.NonlinearFactorGraph()
        added: list[gtsam.NonlinearFactor] = list(factors)
        taken: set[int] = set(drop)
        marginals: list[gtsam.NonlinearFactor] = []
        for stage, thinning in ((marginalise, False), (then_marginalise, True)):
            if not stage:
                continue
            # The earlier stage's marginals on this stage's keys are taken in, not added.
            keys = set(stage)
            into = [m for m in marginals if keys.intersection(m.keys())]
            marginals = [m for m in marginals if not keys.intersection(m.keys())]
            indices, more = self._schur_complement(
                stage, exclude=taken, extra=into, summed=thinning, sparsify=sparsify
            )
            taken.update(indices)
            marginals.extend(more)
        remove: list[int] = sorted(taken)
        added.extend(marginals)
        self.marginal_keys.extend(tuple(m.keys()) for m in marginals)
        for factor in added:
            new.add(factor)
        try:
            result = self._isam.update(
                new,
                values or gtsam.Values(),
                remove,
                constrainedKeys=self._root_groups((*marginalise, *then_marginalise)),
                force_relinearize=self.relinearising,
                noRelinKeys=self._held_back() if self._relinearises() else None,
            )
        except RuntimeError as exc:  # gtsam raises IndeterminantLinearSystem etc. as RuntimeError
            qr = self._isam.params().getFactorization() == "QR"
            if "Indeterminate linear system" not in str(exc) or qr:
                raise EstimationError(str(exc)) from exc
            result, added = self._rebuild_with_qr(added, values, remove, exc)
            remove = []
        # Even a pure marginalisation moves the estimate a little: iSAM2 re-eliminates
        # the cliques it touched, and its partial (wildfire) updates had left their
        # delta behind the MAP. A stale cache here made a restored map (rebuilt with a
        # full step) diverge from the original by centimetres.
        self._forget_estimate()
        shrunk: set[int] = set()
        for index in remove:
            self._marginals.discard(index)
            for key in self._factors.pop(index).keys():
                keyed = self._key_factors[key]
                keyed.discard(index)
                if keyed:
                    shrunk.add(key)
                else:
                    del self._key_factors[key]
        for index, factor in zip(result.getNewFactorsIndices(), added, strict=True):
            self._factors[index] = factor
            if isinstance(factor, RelativeMarginalFactor | gtsam.LinearContainerFactor):
                self._marginals.add(index)
            for key in factor.keys():
                self._key_factors.setdefault(key, set()).add(index)
        for key in shrunk.intersection(self._key_factors):
            if _sparse(self._key_factors[key]):
                self._key_factors[key] = set(self._key_factors[key])

    def _rebuild_with_qr(
        self,
        added: list[gtsam.NonlinearFactor],
        values: gtsam.Values | None,
        remove: Sequence[int],
        cause: RuntimeError,
    ) -> tuple[gtsam.ISAM2Result, list[gtsam.NonlinearFactor]]:
        """The update that Cholesky refused, as one batch step of a fresh QR iSAM2 over
        every factor; the map keeps the QR iSAM2 from then on (until a restore).

        iSAM2's Cholesky can meet a non-positive pivot in a clique of a well-posed but
        ill-conditioned graph: MRCLAM-6 robot 2 at cap 8 (policy random) refused frame
        1549 ("Indeterminate linear system") although the graph's Hessian had its
        smallest eigenvalue at 0.14 (largest 1.4e8) and Levenberg-Marquardt solved it;
        QR, which never forms the normal equations, takes it. QR costs ~25 % more per
        frame on the lifelong simulation, so it is the fallback, not the default.
        Returns the update's result and the factors it added, in order; every factor is
        new to the fresh iSAM2, so the bookkeeping is rebuilt from them."""
        removed = set(remove)
        kept = [f for i, f in sorted(self._factors.items()) if i not in removed]
        factors = [*kept, *added]
        used = {k for f in factors for k in f.keys()}
        init = gtsam.Values()
        new_values = values if values is not None else gtsam.Values()
        for key in sorted(used):
            # The failed update may have inserted (and relinearised) variables already.
            _copy_value(init, key, self._theta if self._theta.exists(key) else new_values)
        graph = gtsam.NonlinearFactorGraph()
        for factor in factors:
            graph.add(factor)
        isam = make_isam(self._config, factorization="QR")
        try:
            result = isam.update(graph, init)
        except RuntimeError as exc:
            raise EstimationError(f"{cause} (and with QR: {exc})") from exc
        log.warning(
            "iSAM2's Cholesky refused an update (%s); rebuilt with QR over %d factors",
            " ".join(str(cause).split()[:11]),
            len(factors),
        )
        self._isam = isam
        self._theta = isam.getLinearizationPoint()
        self._factors = {}
        self._key_factors = {}
        return result, factors

    def _eliminate(
        self, linear: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering, summed: bool
    ) -> tuple[gtsam.GaussianBayesTree, gtsam.GaussianFactorGraph]:
        """Eliminate `ordering` from `linear`: (conditionals, the marginal factors).

        QR by default: it leaves Jacobian factors (square roots), which a landmark's
        linear marginal needs as they are (iSAM2's QR fallback) and relative marginals
        use without factoring. But QR stacks every factor of a clique into one dense
        Jacobian, rows by columns: a keyframe thinning of 53 keyframes out of 436
        factors over 186 keys took 15 MiB that way, the largest transient of the 20 000-
        frame lifelong run (bench.memory_transients). `summed` (keyframe thinning, poses
        with relative marginals): GTSAM's default, EliminatePreferCholesky, which sums
        the factors' information into one square matrix, columns by columns; its
        marginals are Hessian factors that relative_marginal takes a square root of.
        Not for every pose: a window exit each frame, factored that way, made the
        lifelong run ~5x slower (mostly the square roots of rank-deficient marginals)."""
        if summed and self._relative:
            return linear.eliminatePartialMultifrontal(ordering)
        try:
            return linear.eliminatePartialMultifrontal(ordering, gtsam.EliminateQR)
        except RuntimeError:  # a Hessian factor that QR cannot take (e.g. rank-deficient)
            return linear.eliminatePartialMultifrontal(ordering)

    def _schur_complement(
        self,
        keys: Sequence[int],
        exclude: set[int] | None = None,
        extra: Sequence[gtsam.NonlinearFactor] = (),
        summed: bool = False,
        sparsify: Callable[[Sequence[int]], bool] | None = None,
    ) -> tuple[list[int], list[gtsam.NonlinearFactor]]:
        """Factor indices touching `keys`, and the marginal factors that replace them
        (and the `extra` factors, not in the graph yet, that are taken in too).
        `summed`: eliminate poses by Cholesky (see `_eliminate`); `sparsify`: see
        `update`."""
        missing = [k for k in keys if k not in self._key_factors]
        if missing:
            raise KeyError(f"cannot marginalise {[gtsam.DefaultKeyFormatter(k) for k in missing]}")
        indices = sorted({i for k in keys for i in self._key_factors[k]} - (exclude or set()))
        theta = self._theta
        local = gtsam.NonlinearFactorGraph()
        for index in indices:
            local.add(self._factors[index])
        for carried in extra:
            local.add(carried)
        linear = local.linearize(theta)
        ordering = gtsam.Ordering(list(keys))
        poses_only = not any(is_landmark_key(k) for k in keys)
        # Multifrontal: keys that share a dense factor (keyframes linked by landmark
        # marginals) go in one clique and one elimination, where sequential elimination
        # did a QR of the whole dense block per key (21 keyframes: 681 ms -> 109 ms).
        conditionals, remaining = self._eliminate(linear, ordering, summed and poses_only)
        # The linearised inputs (a copy of every dense factor taken in) go before the
        # marginals are copied into their containers: one dense copy fewer at the peak.
        del linear, local, conditionals
        marginals: list[gtsam.NonlinearFactor] = []
        for i in range(remaining.size()):
            factor = remaining.at(i)
            if factor is None or len(factor.keys()) == 0:
                continue
            tree = (
                self._tree_of(factor, keys)
                if sparsify is not None and sparsify(list(factor.keys()))
                else None
            )
            marginals.extend(tree if tree is not None else [self._wrap(factor, keys)])
        return indices, marginals

    def _wrap(
        self, factor: gtsam.GaussianFactor, marginalised: Sequence[int]
    ) -> gtsam.NonlinearFactor:
        """A linear marginal at theta (what eliminating `marginalised` left) as a nonlinear
        factor: relative to one of its poses (graph.relative) where the map keeps such
        marginals (relative_marginals; a landmark's too with relative_landmark_marginals),
        else a LinearContainerFactor."""
        relative = self._config.relative_landmark_marginals or not any(
            is_landmark_key(k) for k in marginalised
        )
        reference = choose_reference(list(factor.keys()), marginalised) if relative else None
        if self._relative and reference is not None:
            return relative_marginal(factor, self._theta, reference)
        point = gtsam.Values()
        for key in factor.keys():
            _copy_value(point, key, self._theta)
        return gtsam.LinearContainerFactor(factor, point)

    def _tree_of(
        self, factor: gtsam.GaussianFactor, marginalised: Sequence[int]
    ) -> list[gtsam.NonlinearFactor] | None:
        """The Chow-Liu tree of a linear marginal (graph.sparsify), one factor per edge
        (and the root's marginal), each kept as the marginal itself would be (`_wrap`), so
        that they are relinearised and keep their absolute part where they have one;
        None when the tree would lose a direction the marginal observes (infinite KL)."""
        linear, tree = tree_factors(factor)
        if not math.isfinite(tree.kl):
            # The tree loses a direction the marginal observes (three rays of a landmark
            # constrain three viewpoints, no pair of them does) and can leave a pose
            # unconstrained: iSAM2 then refuses the system even with QR (MRCLAM-6
            # robot 5 at cap 8, policy coverage_paper, seed 2). The marginal stays exact
            # (BearingSlam thins its keyframes instead).
            self.sparsifications_refused += 1
            return None
        self.sparsifications += 1
        if self.sparsification_kl is not None:
            self.sparsification_kl.append(tree.kl)
        return [self._wrap(f, marginalised) for f in linear]

    def sparsify_marginals(
        self, key_sets: Iterable[Sequence[int]], sparsify: Callable[[Sequence[int]], bool]
    ) -> list[tuple[int, ...]]:
        """Replace every factor in the graph over one of `key_sets` for which `sparsify`
        is true (a marginal whose keys became more keyframes) by its Chow-Liu tree, at
        its linearisation at theta, in one update. Returns the key sets of the factors
        kept as they were because their tree would lose a direction (see `_tree_of`)."""
        drop: set[int] = set()
        refused: list[tuple[int, ...]] = []
        trees: list[gtsam.NonlinearFactor] = []
        for keys in key_sets:
            if not keys or not sparsify(keys):
                continue
            shared = set.intersection(*(self._key_factors.get(k, set()) for k in keys))
            for index in sorted(shared - drop):
                factor = self._factors[index]
                if len(factor.keys()) != len(keys):
                    continue
                tree = self._tree_of(factor.linearize(self._theta), keys)
                if tree is None:
                    refused.append(tuple(keys))
                    continue
                drop.add(index)
                trees.extend(tree)
        if drop:
            self.update(trees, drop=sorted(drop))
        return refused
