"""A map's configuration as clients give it, and its translation to `SlamConfig`: the
map pipeline's configuration (the camera's part: service.pipeline.camera_config; the
groups of estimator parameters: service.pipeline.config_groups).

Units: metres, radians. Every field carries its unit in its description, which
is what the OpenAPI schema shows.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from graph.config import (
    Optimizer,
    SlamConfig,
)
from graph.policies import POLICY_NAMES
from service.pipeline.camera_config import (
    CAMERA_GRAPH_FRAME_DISTANCE_M,
    CAMERA_LANDMARK_CAP,
    CAMERA_LANDMARK_FACTORS,
    CAMERA_NOISE_DEFAULTS,
    CameraConfig,
    StrictModel,
)
from service.pipeline.config_groups import (
    ArchiveConfig,
    GatingConfig,
    KeyframeConfig,
    NoiseConfig,
    SolverConfig,
    TriangulationConfig,
)

if TYPE_CHECKING:
    from frontend.cameras import CameraModel

Mode = Literal["mapping", "localisation"]

_DEFAULTS = SlamConfig()


DEFAULT_LANDMARK_CAP = 50
"""The service's default landmark cap of a map created without one (its setting
`default_landmark_cap`; an in-process replay without --landmark-cap too)."""
RANDOM_WALK_NOISE_DEFAULTS: dict[str, Any] = {
    "odometry_sigma_per_sqrt_metre": _DEFAULTS.odometry_sigma_per_sqrt_metre,
    "odometry_sigma_per_sqrt_radian": _DEFAULTS.odometry_sigma_per_sqrt_radian,
}
"""The odometry random walks a map created without them gets (MapConfig.for_new_map).
A stored config without them is a map built before they existed: its log replays
without them, as it was processed."""
WINDOW_FIELDS = (
    "pose_window",
    "window_observations",
    "uncapped_window_observations",
    "max_pose_window",
)


def window_settings(given: Mapping[str, int | None]) -> dict[str, int | None]:
    """The window fields of a map from those its config gives: the estimator's defaults,
    except that a config giving `pose_window` alone gets exactly that window (no growth;
    so does every map stored before the growth existed), and one giving
    `window_observations` without `uncapped_window_observations` gets that bound
    whether capped or not (every map stored before the uncapped default existed)."""
    defaults: dict[str, int | None] = {k: getattr(_DEFAULTS, k) for k in WINDOW_FIELDS}
    if set(given) == {"pose_window"}:
        defaults["window_observations"] = None
        defaults["uncapped_window_observations"] = None
    if "window_observations" in given:
        defaults["uncapped_window_observations"] = None
    return {k: given[k] if k in given else defaults[k] for k in WINDOW_FIELDS}


class MapConfig(StrictModel):
    """How a map estimates. Omitted fields take the service's defaults.

    Every estimator parameter (graph.config.SlamConfig) has one place here, listed in
    SLAM_FIELD_PATHS, under the same name: the landmark budget, windows, graph frames
    and the iSAM2 step at the top level (where they have always been), the rest in
    groups (noise, triangulation, gating, keyframes, solver, archive). One SlamConfig field has
    none: allow_new_landmarks follows the map's `mode` (localisation freezes the map),
    which a client sets beside the config. A stored config that lacks a group (every map
    created before it existed) gets its defaults, which are the estimator's.
    """

    landmark_cap: int | None = Field(
        None,
        ge=1,
        description="most live landmarks kept; the policy marginalises the rest. "
        "null = uncapped; omitted = the service's default cap",
    )
    policy: str = Field(
        "coverage",
        description=f"landmark-selection policy, one of {', '.join(POLICY_NAMES)}",
    )
    pose_window: int | None = Field(
        _DEFAULTS.pose_window,
        ge=2,
        description="poses kept per robot before the oldest is marginalised; null = keep all. "
        "Given alone (without window_observations / max_pose_window), the window is exactly "
        "this long",
    )
    window_observations: int | None = Field(
        _DEFAULTS.window_observations,
        ge=1,
        description="a window of sparse observations grows beyond pose_window, up to "
        "max_pose_window poses, while its poses hold fewer bearing factors than this; "
        "null = pose_window alone, or uncapped_window_observations on an uncapped map",
    )
    uncapped_window_observations: int | None = Field(
        _DEFAULTS.uncapped_window_observations,
        ge=1,
        description="window_observations of a map without a landmark cap when "
        "window_observations is null (a capped map's window does not grow unless asked); "
        "null = pose_window alone",
    )
    max_pose_window: int = Field(
        _DEFAULTS.max_pose_window,
        ge=2,
        description="most poses of a grown window (pose_window if that is more)",
    )
    window_marginals: int | None = Field(
        None,
        ge=1,
        description="a window grows beyond pose_window only while fewer than this many "
        "marginal factors (left by removed landmarks and poses) touch its poses, and "
        "sheds a pose a frame while more do; null = no such bound. A map created without "
        f"it gets {_DEFAULTS.window_marginals}; a stored config without it, none",
    )
    camera: CameraConfig | None = Field(
        None,
        description="camera of the map's image frames (multipart meta + image); "
        "null for maps fed with bearing observations only. The string 'panorama' "
        "means a default 2048x512 panorama",
    )
    noise: NoiseConfig = Field(default_factory=NoiseConfig)
    triangulation: TriangulationConfig = Field(
        default_factory=TriangulationConfig,
        description="when an observation track becomes a landmark: rays, parallax, depth "
        "range (metres), residual, position sigma (metres)",
    )
    gating: GatingConfig = Field(
        default_factory=GatingConfig,
        description="the innovation gate against wrong matches (radians, frames)",
    )
    keyframes: KeyframeConfig = Field(
        default_factory=KeyframeConfig,
        description="which poses leaving the window stay as keyframes (metres, radians)",
    )
    solver: SolverConfig = Field(
        default_factory=SolverConfig,
        description="iSAM2 relinearisation and how old poses' marginals are kept",
    )
    archive: ArchiveConfig = Field(
        default_factory=ArchiveConfig,
        description="when an archived (removed) landmark seen again comes back under its id",
    )
    optimizer: Optimizer = Field(
        _DEFAULTS.optimizer,
        description="iSAM2 step: 'gauss_newton' (partial updates; the default) or 'dogleg' "
        "(Powell's trust region: every update evaluates every factor's error, ~2x a "
        "frame's cost on a dense map, and it let a landmark seen along one ray flip "
        "along it on MRCLAM-6)",
    )
    max_landmark_factors: int | None = Field(
        None,
        ge=1,
        description="most bearing factors on live landmarks per frame (those whose last "
        "factor is oldest first; the rest still count as observed); null = one per "
        f"observation. Omitted: {CAMERA_LANDMARK_FACTORS} for a map with a camera (a "
        "panorama matches ~100 landmarks a frame), null otherwise",
    )
    removal_margin: int = Field(
        _DEFAULTS.removal_margin,
        ge=0,
        description="once the live count exceeds landmark_cap, landmarks are removed down "
        "to landmark_cap - removal_margin in one marginalisation (fewer removal updates "
        "for maps that meet new landmarks every frame); 0 = down to the cap",
    )
    spare_observed: bool = Field(
        _DEFAULTS.spare_observed,
        description="the policy chooses among the live landmarks the frame did not observe "
        "(all of them only if it must remove more): no landmark is removed while in view, "
        "which stops churn through the archive when frames see many landmarks",
    )
    drop_window_observations: bool = Field(
        False,
        description="a pose leaving the window without becoming a keyframe loses its "
        "landmark observations instead of having them marginalised (cheaper with many "
        "landmarks per frame, throws information away)",
    )
    graph_frame_distance_m: float | None = Field(
        None,
        gt=0,
        description="a frame enters the factor graph only once its robot moved this far "
        "(metres) from its last frame that did (or turned graph_frame_angle_rad, or "
        "graph_frame_max_gap frames went by, or it sees fewer than "
        "graph_frame_min_landmarks live landmarks); the frames in between are tracked "
        "against the map's landmarks and follow the graph's corrections. null = every "
        f"frame. Omitted at creation: {CAMERA_GRAPH_FRAME_DISTANCE_M} for a map with a "
        "camera, null otherwise (maps stored without it keep null)",
    )
    graph_frame_angle_rad: float = Field(
        _DEFAULTS.graph_frame_angle_rad,
        gt=0,
        description="with graph_frame_distance_m: a frame that turned this far (radians) "
        "from its robot's last graph frame enters the graph",
    )
    graph_frame_max_gap: int = Field(
        _DEFAULTS.graph_frame_max_gap,
        ge=1,
        description="with graph_frame_distance_m: most frames of a robot from one graph "
        "frame to the next",
    )
    graph_frame_min_landmarks: int = Field(
        _DEFAULTS.graph_frame_min_landmarks,
        ge=0,
        description="with graph_frame_distance_m: a frame seeing fewer live landmarks than "
        "this enters the graph (a tracked pose needs them)",
    )
    seed: int = Field(0, ge=0, description="seed of the map's random choices (policy, k-means)")

    @model_validator(mode="after")
    def _camera_factor_bound(self) -> MapConfig:
        if "max_landmark_factors" not in self.model_fields_set and self.camera is not None:
            self.max_landmark_factors = CAMERA_LANDMARK_FACTORS
        given = {k: getattr(self, k) for k in WINDOW_FIELDS if k in self.model_fields_set}
        for k, v in window_settings(given).items():
            setattr(self, k, v)
        return self

    @field_validator("camera", mode="before")
    @classmethod
    def _camera_shorthand(cls, value: Any) -> Any:
        if value == "panorama":
            return {"model": "panorama"}
        if isinstance(value, str):
            raise ValueError(
                f"camera {value!r}: give an object, e.g. {{'model': 'panorama', "
                "'width': 2048, 'height': 512}} (an omni camera needs its ring geometry)"
            )
        return value

    @field_validator("policy")
    @classmethod
    def _known_policy(cls, value: str) -> str:
        if value not in POLICY_NAMES:
            raise ValueError(f"unknown policy {value!r}; one of {', '.join(POLICY_NAMES)}")
        return value

    def for_new_map(
        self, default_cap: int | None, camera_default_cap: int | None = CAMERA_LANDMARK_CAP
    ) -> MapConfig:
        """The config a map is created with: the service's default cap if the client gave
        none (`camera_default_cap` for a camera map; None: uncapped); the odometry random
        walks of RANDOM_WALK_NOISE_DEFAULTS and the estimator's window_marginals where
        the client gave none; for a camera map,
        graph_frame_distance_m and the noise's bearing loss and
        scale (CAMERA_NOISE_DEFAULTS) where the client gave none of them. Only at
        creation: a stored config or an export without these fields is a map built with
        every frame in the graph, Huber's loss and no marginal bound on its window, and
        its frame log replays that way."""
        given = self.noise.model_fields_set
        noise = self.noise.model_copy(
            update={k: v for k, v in RANDOM_WALK_NOISE_DEFAULTS.items() if k not in given}
        )
        update: dict[str, Any] = {"noise": noise, **self._new_estimator_defaults()}
        if "window_marginals" not in self.model_fields_set:
            update["window_marginals"] = _DEFAULTS.window_marginals
        if self.camera is None:
            return self.with_default_cap(default_cap).model_copy(update=update)
        config = self.with_default_cap(camera_default_cap)
        if "graph_frame_distance_m" not in self.model_fields_set:
            update["graph_frame_distance_m"] = CAMERA_GRAPH_FRAME_DISTANCE_M
        if not {"bearing_loss", "huber_k"} & given:
            # Loss and scale go together: a client who gave a huber_k meant Huber's.
            update["noise"] = noise.model_copy(update=CAMERA_NOISE_DEFAULTS)
        return config.model_copy(update=update)

    def _new_estimator_defaults(self) -> dict[str, Any]:
        """The solver group with the estimator's current defaults where the client gave
        none: the upkeep after the frame and its relinearisation budget (a stored config
        without them keeps what it was built with: everything in the frame)."""
        solver = self.solver
        upkeep = solver.upkeep if "upkeep" in solver.model_fields_set else _DEFAULTS.upkeep
        solver_update: dict[str, Any] = {"upkeep": upkeep}
        if "relinearise_budget" not in solver.model_fields_set and upkeep != "in_frame":
            solver_update["relinearise_budget"] = _DEFAULTS.relinearise_budget
        return {"solver": solver.model_copy(update=solver_update)}

    def with_default_cap(self, default_cap: int | None) -> MapConfig:
        """This config with the service's default cap if the client gave none."""
        if "landmark_cap" in self.model_fields_set:
            return self
        return self.model_copy(update={"landmark_cap": default_cap})


_TOP_LEVEL_FIELDS = (
    "landmark_cap",
    "policy",
    *WINDOW_FIELDS,
    "window_marginals",
    "optimizer",
    "max_landmark_factors",
    "removal_margin",
    "spare_observed",
    "drop_window_observations",
    "graph_frame_distance_m",
    "graph_frame_angle_rad",
    "graph_frame_max_gap",
    "graph_frame_min_landmarks",
)
_GROUPS: dict[str, type[BaseModel]] = {
    "noise": NoiseConfig,
    "triangulation": TriangulationConfig,
    "gating": GatingConfig,
    "archive": ArchiveConfig,
    "keyframes": KeyframeConfig,
    "solver": SolverConfig,
}
SLAM_FIELD_PATHS: dict[str, tuple[str, ...]] = {
    **{name: (name,) for name in _TOP_LEVEL_FIELDS},
    **{name: (group, name) for group, model in _GROUPS.items() for name in model.model_fields},
}
"""Where each estimator parameter sits in a map config: SlamConfig field -> path of
keys (a REST body's `config.<path>`). Every SlamConfig field but allow_new_landmarks
(the map's mode) has one; a test keeps it so."""


def slam_config(config: dict[str, Any], mode: str) -> SlamConfig:
    """The estimator's parameters for a stored map config and mode.

    Raises ValueError when the estimator refuses the combination.
    """
    cfg = MapConfig.model_validate(config)
    params: dict[str, Any] = {}
    for name, path in SLAM_FIELD_PATHS.items():
        value: Any = cfg
        for key in path:
            value = getattr(value, key)
        params[name] = value
    return SlamConfig(**params, allow_new_landmarks=mode == "mapping")


def camera_model(config: dict[str, Any]) -> CameraModel | None:
    """The camera of a stored map config (None: the map takes no image frames).

    Raises ValueError when the camera's parameters are inconsistent.
    """
    from frontend.cameras import camera_from_config  # OpenCV: workers only, not the API

    camera = MapConfig.model_validate(config).camera
    return None if camera is None else camera_from_config(camera.model_dump())


def slam_config_dict(config: SlamConfig) -> dict[str, Any]:
    """Every estimator parameter by name (JSON-serialisable)."""
    return {f.name: getattr(config, f.name) for f in fields(config)}
