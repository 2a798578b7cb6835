"""A map's configuration as clients give it, and its translation to `SlamConfig`.

Units: metres, radians. Every field carries its unit in its description, which
is what the OpenAPI schema shows.
"""

from __future__ import annotations

import math
from dataclasses import fields
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from graph.config import SlamConfig
from graph.policies import POLICY_NAMES

Mode = Literal["mapping", "localisation"]

_DEFAULTS = SlamConfig()


class NoiseConfig(BaseModel):
    """Noise models of the estimator (one-sigma values)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    bearing_sigma_rad: float = Field(
        _DEFAULTS.bearing_sigma_rad,
        gt=0,
        description="default bearing noise when an observation gives no sigma, radians",
    )
    huber_k: float | None = Field(
        _DEFAULTS.huber_k,
        gt=0,
        description="Huber threshold of bearing factors in sigmas; null = plain Gaussian",
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
    initial_pose_sigma: tuple[float, float, float] = Field(
        _DEFAULTS.initial_pose_sigma,
        description="sigma of the prior from a robot's initial_pose: x m, y m, theta rad",
    )

    @field_validator("odometry_sigma_floor", "odometry_sigma_per_metre", "initial_pose_sigma")
    @classmethod
    def _non_negative(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        if any(v < 0 or not math.isfinite(v) for v in value):
            raise ValueError("sigmas must be finite and >= 0")
        return value


class MapConfig(BaseModel):
    """How a map estimates. Omitted fields take the service's defaults."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

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
        description="poses kept per robot before the oldest is marginalised; null = keep all",
    )
    camera: Literal["panorama", "omni"] | None = Field(
        None,
        description="camera of image frames (arrives with the image frontend); "
        "null for maps fed with bearing observations",
    )
    noise: NoiseConfig = Field(default_factory=NoiseConfig)
    seed: int = Field(0, ge=0, description="seed of the map's random choices (policy, k-means)")

    @field_validator("policy")
    @classmethod
    def _known_policy(cls, value: str) -> str:
        if value not in POLICY_NAMES:
            raise ValueError(f"unknown policy {value!r}; one of {', '.join(POLICY_NAMES)}")
        return value

    def with_default_cap(self, default_cap: int | None) -> MapConfig:
        """This config with the service's default cap if the client gave none."""
        if "landmark_cap" in self.model_fields_set:
            return self
        return self.model_copy(update={"landmark_cap": default_cap})


def slam_config(config: dict[str, Any], mode: str) -> SlamConfig:
    """The estimator's parameters for a stored map config and mode.

    Raises ValueError when the estimator refuses the combination.
    """
    cfg = MapConfig.model_validate(config)
    return SlamConfig(
        landmark_cap=cfg.landmark_cap,
        policy=cfg.policy,
        pose_window=cfg.pose_window,
        bearing_sigma_rad=cfg.noise.bearing_sigma_rad,
        huber_k=cfg.noise.huber_k,
        odometry_sigma_floor=cfg.noise.odometry_sigma_floor,
        odometry_sigma_per_metre=cfg.noise.odometry_sigma_per_metre,
        odometry_sigma_per_radian=cfg.noise.odometry_sigma_per_radian,
        initial_pose_sigma=cfg.noise.initial_pose_sigma,
        allow_new_landmarks=mode == "mapping",
    )


def slam_config_dict(config: SlamConfig) -> dict[str, Any]:
    """Every estimator parameter by name (JSON-serialisable)."""
    return {f.name: getattr(config, f.name) for f in fields(config)}
