"""The groups of estimator parameters in a map config: `noise`, `triangulation`,
`gating`, `keyframes`, `solver` and `archive`, one strict model each, their defaults
the estimator's (graph.config.SlamConfig). service.pipeline.config puts them together
in `MapConfig` and translates it to a `SlamConfig`.

Units: metres, radians. Every field carries its unit in its description, which
is what the OpenAPI schema shows.
"""

from __future__ import annotations

import math

from pydantic import Field, field_validator, model_validator

from graph.config import (
    BearingLoss,
    KeyframePlacement,
    MarginalSparsification,
    SlamConfig,
    Upkeep,
)
from service.pipeline.camera_config import StrictModel

_DEFAULTS = SlamConfig()


class NoiseConfig(StrictModel):
    """Noise models of the estimator (one-sigma values)."""

    bearing_sigma_rad: float = Field(
        _DEFAULTS.bearing_sigma_rad,
        gt=0,
        description="default bearing noise when an observation gives no sigma, radians",
    )
    huber_k: float | None = Field(
        _DEFAULTS.huber_k,
        gt=0,
        description="threshold (huber) or scale (geman_mcclure) of the bearing loss in "
        "sigmas; null = plain Gaussian",
    )
    bearing_loss: BearingLoss = Field(
        _DEFAULTS.bearing_loss,
        description="robust loss of bearing factors: 'huber', or 'geman_mcclure' (a wrong "
        "match's pull fades as it disagrees more; a camera map's default)",
    )
    odometry_sigma_floor: tuple[float, float, float] = Field(
        _DEFAULTS.odometry_sigma_floor,
        description="odometry sigma of a motionless step: x metres, y metres, theta radians",
    )
    odometry_sigma_per_metre: tuple[float, float, float] = Field(
        _DEFAULTS.odometry_sigma_per_metre,
        description="odometry sigma growth per metre travelled: x m/m, y m/m, theta rad/m",
    )
    odometry_sigma_per_radian: float = Field(
        _DEFAULTS.odometry_sigma_per_radian,
        ge=0,
        description="heading sigma growth per radian turned, rad/rad",
    )
    odometry_sigma_per_sqrt_metre: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0),
        description="random-walk growth of the odometry sigma with the distance travelled, "
        "in quadrature, whatever the frame rate: x m/sqrt(m), y m/sqrt(m), theta "
        "rad/sqrt(m). A map created without a noise model gets "
        f"{_DEFAULTS.odometry_sigma_per_sqrt_metre!r} (sound for wheeled robots); a stored "
        "config without it, none",
    )
    odometry_sigma_per_sqrt_radian: float = Field(
        0.0,
        ge=0,
        allow_inf_nan=False,
        description="random-walk growth of the heading sigma with the angle turned, in "
        "quadrature: rad/sqrt(rad). A map created without a noise model gets "
        f"{_DEFAULTS.odometry_sigma_per_sqrt_radian:.4f}; a stored config without it, none",
    )
    odometry_sigma_per_sqrt_second: tuple[float, float, float] = Field(
        _DEFAULTS.odometry_sigma_per_sqrt_second,
        description="odometry sigma growth with the step's duration, added in quadrature: "
        "x m/sqrt(s), y m/sqrt(s), theta rad/sqrt(s) (e.g. a gyro-less heading drift)",
    )
    initial_pose_sigma: tuple[float, float, float] = Field(
        _DEFAULTS.initial_pose_sigma,
        description="sigma of the prior from a robot's initial_pose: x m, y m, theta rad",
    )

    @field_validator(
        "odometry_sigma_floor",
        "odometry_sigma_per_metre",
        "odometry_sigma_per_sqrt_metre",
        "odometry_sigma_per_sqrt_second",
        "initial_pose_sigma",
    )
    @classmethod
    def _non_negative(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        if any(v < 0 or not math.isfinite(v) for v in value):
            raise ValueError("sigmas must be finite and >= 0")
        return value


class TriangulationConfig(StrictModel):
    """When an unmatched observation track (a candidate) becomes a landmark: enough rays,
    enough parallax, a consistent and well-determined intersection within a depth range.
    The defaults suit rooms and halls (landmarks within 15 m); an outdoor map whose
    landmarks stand tens of metres away needs a larger max_depth_m and
    max_position_sigma_m (see docs/configuration.md)."""

    min_rays: int = Field(
        _DEFAULTS.min_rays,
        ge=2,
        le=10_000,
        description="rays a candidate needs before it is triangulated, count",
    )
    max_rays: int = Field(
        _DEFAULTS.max_rays,
        ge=2,
        le=10_000,
        description="most rays a candidate keeps (oldest dropped first), count; with the "
        "robot's step this bounds the baseline a far landmark is triangulated from",
    )
    min_parallax_rad: float = Field(
        _DEFAULTS.min_parallax_rad,
        gt=0,
        lt=math.pi,
        description="smallest spread of a candidate's ray directions that counts as "
        "enough parallax, radians",
    )
    min_depth_m: float = Field(
        _DEFAULTS.min_depth_m,
        ge=0,
        description="nearest a triangulated landmark may lie from each pose that saw it, metres",
    )
    max_depth_m: float = Field(
        _DEFAULTS.max_depth_m,
        gt=0,
        description="farthest a triangulated landmark may lie from each pose that saw it, "
        "metres; raise it for outdoor maps (landmarks tens of metres away)",
    )
    max_residual_sigmas: float = Field(
        _DEFAULTS.max_residual_sigmas,
        gt=0,
        description="largest bearing residual of a triangulation, in bearing sigmas "
        "(dimensionless)",
    )
    max_position_sigma_m: float = Field(
        _DEFAULTS.max_position_sigma_m,
        gt=0,
        description="largest one-sigma position error (major axis) of a triangulated "
        "landmark, metres; a far landmark's depth is uncertain, so outdoor maps need more",
    )
    candidate_ttl_frames: int = Field(
        _DEFAULTS.candidate_ttl_frames,
        ge=1,
        description="a candidate not observed for this many frames (of any robot) expires, frames",
    )
    landmark_prior_sigma_m: float | None = Field(
        _DEFAULTS.landmark_prior_sigma_m,
        gt=0,
        description="one-sigma of the weak prior on each new landmark at its triangulated "
        "position, metres; null = none",
    )
    candidate_first_rays: int = Field(
        _DEFAULTS.candidate_first_rays,
        ge=0,
        le=10_000,
        description="the first rays of a candidate kept until it initialises (whatever "
        "max_rays drops) and given bearing factors then: they tie a landmark first seen "
        "near the initial pose to that pose's frame, count (below max_rays)",
    )

    @model_validator(mode="after")
    def _ordered(self) -> TriangulationConfig:
        if self.max_rays < self.min_rays:
            raise ValueError("need min_rays <= max_rays")
        if not self.candidate_first_rays < self.max_rays:
            raise ValueError("need candidate_first_rays < max_rays")
        if not self.min_depth_m < self.max_depth_m:
            raise ValueError("need min_depth_m < max_depth_m")
        return self


class GatingConfig(StrictModel):
    """The innovation gate: an observation of an established landmark far from its
    predicted bearing, in a frame where another observation confirms the pose, gets no
    factor (a wrong match or a reflection a robust loss cannot shrug off)."""

    max_innovation_rad: float | None = Field(
        _DEFAULTS.max_innovation_rad,
        gt=0,
        le=math.pi,
        description="largest difference between an observed and the predicted bearing, "
        "radians; null = no gate",
    )
    gate_min_age_frames: int = Field(
        _DEFAULTS.gate_min_age_frames,
        ge=0,
        description="the gate applies to landmarks at least this old, frames",
    )
    gate_confirm_rad: float = Field(
        _DEFAULTS.gate_confirm_rad,
        gt=0,
        le=math.pi,
        description="the gate applies only in a frame where another observation lies within "
        "this of its prediction, radians",
    )


class KeyframeConfig(StrictModel):
    """Which poses leaving the pose window stay in the graph as keyframes."""

    keyframe_placement: KeyframePlacement = Field(
        _DEFAULTS.keyframe_placement,
        description="which keyframes make a pose leaving the window not a keyframe: "
        "'spacing', its robot's last one, when within keyframe_distance_m and "
        "keyframe_angle_rad (keyframes grow with the distance travelled); 'area', any "
        "keyframe of the map within keyframe_distance_m (they grow with the area explored)",
    )
    keyframe_distance_m: float = Field(
        _DEFAULTS.keyframe_distance_m,
        ge=0,
        description="a keyframe within this distance of a pose leaving the window (and, "
        "with 'spacing', within keyframe_angle_rad of its heading) is near it, metres",
    )
    keyframe_angle_rad: float = Field(
        _DEFAULTS.keyframe_angle_rad,
        gt=0,
        description="with 'spacing', a keyframe that turned this far from a pose leaving "
        "the window is not near it, radians",
    )
    max_keyframes: int = Field(
        _DEFAULTS.max_keyframes,
        ge=0,
        description="keyframes kept per robot beyond the window (oldest marginalised "
        "first), count; 0 = none",
    )
    max_linked_keyframes: int = Field(
        _DEFAULTS.max_linked_keyframes,
        ge=1,
        description="most keyframes in one marginal factor (older ones in it are "
        "marginalised too, down to 3/4 of this), count",
    )
    keyframe_for_candidate_rays: bool = Field(
        _DEFAULTS.keyframe_for_candidate_rays,
        description="a pose leaving the window stays as a keyframe while it holds a "
        "candidate's first ray (keeps the widest baseline for its triangulation)",
    )
    marginal_sparsification: MarginalSparsification = Field(
        _DEFAULTS.marginal_sparsification,
        description="how a marginal factor linking more than max_linked_keyframes "
        "keyframes is kept sparse: 'thin_keyframes' marginalises its oldest keyframes, "
        "'chow_liu' replaces it by its Chow-Liu tree (every keyframe kept; the frames' "
        "tail is shorter on dense maps, the map less accurate on sparse ones)",
    )


class SolverConfig(StrictModel):
    """iSAM2's relinearisation and how old poses' marginals are kept. (The iSAM2 step
    itself is the map config's top-level `optimizer`.)"""

    relinearize_threshold: float = Field(
        _DEFAULTS.relinearize_threshold,
        ge=0,
        description="iSAM2 relinearises a variable whose linear delta exceeds this, metres "
        "or radians per component; 0 = every variable",
    )
    relinearize_skip: int = Field(
        _DEFAULTS.relinearize_skip,
        ge=1,
        le=2**31 - 1,
        description="iSAM2 checks for relinearisation every this many updates (GTSAM holds "
        "it in a 32-bit int), count",
    )
    relinearise_budget: int | None = Field(
        None,
        ge=1,
        le=1_000_000,
        description="with an upkeep after the frame: the most relative marginal factors "
        "one iSAM2 update relinearises, count; the variables beyond (the least moved) "
        "keep their linearisation point until the upkeep relinearises them, once the "
        "frame's result is sent. null: no limit. A map created without it gets "
        f"{_DEFAULTS.relinearise_budget} (none if its upkeep is 'in_frame'); a stored "
        "config without it, none",
    )
    upkeep: Upkeep = Field(
        "in_frame",
        description="when the work that keeps the map bounded runs: 'in_frame', before the "
        "frame's result; 'budget_after_frame', the landmark budget's removals, a second "
        "window exit and keyframe thinning once the result is sent, before the map's next "
        "request; 'after_frame', iSAM2's relinearisation too (relinearize_skip then counts "
        "upkeeps). With either, a frame's result lists the removals made after the frame "
        f"before it. A map created without it gets {_DEFAULTS.upkeep!r}; a stored config "
        "without it, 'in_frame'",
    )
    window_exit_after_frame: bool = Field(
        _DEFAULTS.window_exit_after_frame,
        description="with an upkeep after the frame: the pose leaving a robot's window "
        "with a frame leaves in the upkeep, once the frame's result is sent (the window "
        "holds one more pose until then), and the upkeep keeps what the next frame "
        "touches at the root of iSAM2's tree; the frame's answer is faster",
    )
    relative_marginals: bool = Field(
        _DEFAULTS.relative_marginals,
        description="marginals of old poses are kept relative to the next pose rather "
        "than as linear factors in absolute coordinates",
    )
    relative_landmark_marginals: bool = Field(
        _DEFAULTS.relative_landmark_marginals,
        description="a removed landmark's marginal is kept relative to its oldest pose too "
        "rather than as a linear factor frozen where the landmark was removed",
    )


class ArchiveConfig(StrictModel):
    """Removed landmarks are archived; seen again by label they come back under their own
    id (graph.archive), unless removed so recently that they would churn."""

    restore_archived: bool = Field(
        _DEFAULTS.restore_archived,
        description="an archived landmark seen again comes back under its own id at its "
        "archived estimate (false: it is triangulated anew under a new id)",
    )
    restore_after_frames: int = Field(
        _DEFAULTS.restore_after_frames,
        ge=0,
        description="a landmark removed fewer than this many frames ago comes back only "
        "after restore_min_rays observations, frames",
    )
    restore_min_rays: int = Field(
        _DEFAULTS.restore_min_rays,
        ge=1,
        description="observations a recently removed landmark needs to come back, count",
    )
    restore_backoff: bool = Field(
        _DEFAULTS.restore_backoff,
        description="each removal of a landmark doubles its hysteresis (removed k times: "
        "restore_after_frames and restore_min_rays times 2^(k-1)), so that a landmark in "
        "view of dense frames does not churn in and out of the graph",
    )
    restore_prior_sigma_m: float = Field(
        _DEFAULTS.restore_prior_sigma_m,
        gt=0,
        description="one-sigma of the weak prior a restored landmark gets at its archived "
        "estimate (its information is in the marginal already), metres",
    )
