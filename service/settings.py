"""Service configuration: pydantic-settings, ``COVSLAM_*`` variables, nested with ``__``.

Examples: ``COVSLAM_PORT=9000``, ``COVSLAM_DATA_DIR=/var/lib/covslam``,
``COVSLAM_STORE__SYNCHRONOUS=FULL``, ``COVSLAM_WORKERS__COUNT=4``,
``COVSLAM_FRAMES__MAX_LABEL_CHARS=128``,
``COVSLAM_STORE__URL=postgresql://covslam@db/covslam``, ``COVSLAM_ENGINE=ray``,
``COVSLAM_RAY__ADDRESS=auto``.
Nothing is read at import time: call `get_settings()` (cached; tests clear it).
"""

from __future__ import annotations

import ipaddress
import os
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field, SecretStr, ValidationInfo, field_serializer, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.frame_model import FrameLimits
from service.pipeline.camera_config import CAMERA_LANDMARK_CAP
from service.pipeline.config import DEFAULT_LANDMARK_CAP
from service.store import Store, is_postgres_url, open_store


class StoreSettings(BaseModel):
    """The store: embedded SQLite (default) or PostgreSQL."""

    url: str | None = Field(
        None,
        description="where the maps are stored: a directory (SQLite) or a "
        "postgresql://user:password@host:port/database URL (psycopg 3), which takes "
        "precedence over data_dir; default: SQLite in data_dir",
    )

    @field_validator("url")
    @classmethod
    def _directory_or_postgres(cls, value: str | None) -> str | None:
        if value is not None and "://" in value and not is_postgres_url(value):
            raise ValueError("store.url must be a directory or a postgresql:// URL")
        return value or None

    synchronous: Literal["NORMAL", "FULL"] = Field(
        "NORMAL",
        description="SQLite synchronous mode in WAL: NORMAL survives a killed process, "
        "FULL also a power loss (one fsync per commit)",
    )
    snapshot_every: int = Field(
        200, ge=1, description="frames between two snapshots of a map's estimator state"
    )
    snapshots_kept: int = Field(2, ge=1, description="snapshots kept per map (older deleted)")
    prune_images: bool = Field(
        True,
        description="delete a camera map's stored images once every kept snapshot covers "
        "their frames (the images of the log's tail stay, so any kept snapshot + tail "
        "reproduces the map; a replay of the whole log takes such frames' observations "
        "instead). False keeps every image (~155 kB per 2048x512 PNG frame)",
    )
    events_kept: int = Field(
        20_000, ge=100, description="most recent events kept per map for SSE catch-up"
    )


class WorkerSettings(BaseModel):
    """The pool of worker processes that own the maps."""

    count: int = Field(
        default_factory=lambda: max(1, os.cpu_count() or 1),
        ge=1,
        le=64,
        description="worker processes; each map is run by one at a time, placed and moved "
        "by load (default: CPU count)",
    )
    request_timeout_s: float = Field(
        60.0, gt=0, description="longest wait for a worker's answer before a 503"
    )
    retry_after_s: int = Field(1, ge=1, description="Retry-After seconds sent with a 503")
    read_ahead: int = Field(
        4,
        ge=0,
        le=64,
        description="requests a worker takes from its pipe ahead of the current one, so "
        "that their images' features are extracted meanwhile (0 = off)",
    )
    nice: int = Field(
        5,
        ge=0,
        le=19,
        description="niceness added to worker processes, so the API process (probes, "
        "routing) wins the CPU when workers compute",
    )
    balance_interval_s: float = Field(
        2.0,
        ge=0,
        description="seconds between two looks at the workers' loads; a map moves from "
        "the busiest worker to the least busy one when that evens them out (0 = never)",
    )
    shutdown_timeout_s: float = Field(
        60.0,
        gt=0,
        description="longest wait at shutdown for a worker to snapshot its maps and end",
    )
    blas_threads: int = Field(
        1,
        ge=0,
        le=256,
        description="threads of the BLAS library (numpy's dense algebra) in each worker "
        "process; 0 = the library's default (every core). Workers already run one per "
        "core: more threads each only contend",
    )


class RaySettings(BaseModel):
    """The Ray cluster the `ray` engine joins."""

    address: str = Field(
        "auto",
        description="ray.init address: 'auto' (the cluster `ray start` runs on this "
        "machine), 'host:port' of the head's GCS, or 'local' (a private cluster)",
    )
    namespace: str = Field(
        "covslam", description="Ray namespace of the map actors (one per deployment)"
    )
    actor_cpus: float = Field(
        0.0,
        ge=0,
        le=64,
        description="CPUs a map actor reserves in Ray's scheduler (0: actors are placed "
        "by spreading over the nodes, not by reserved CPUs)",
    )


class ApiSettings(BaseModel):
    """Limits of the HTTP front."""

    event_batch_s: float = Field(
        0.2,
        ge=0,
        le=10,
        description="an event stream writes at most once per this many seconds, "
        "everything since its last write at once (many streams cost the API process "
        "writes, not frames; 0 = a write per wake)",
    )

    view_refresh_s: float = Field(
        1.0,
        ge=0,
        le=60,
        description="a read that finds a busy map's published landmarks or trajectory "
        "rows behind the map asks its worker for new ones at most once per this many "
        "seconds (each costs the worker a joint marginal of the live landmarks, ~5 ms for "
        "50; an idle worker answers such a read itself; 0 = at every such read)",
    )
    max_body_bytes: int = Field(
        1 << 20, ge=1024, description="largest request body except imports, bytes (413 above)"
    )
    max_import_bytes: int = Field(
        256 << 20, ge=1024, description="largest body of POST /v1/maps/import, bytes"
    )
    max_image_bytes: int = Field(
        16 << 20,
        ge=1024,
        description="largest image part of a multipart image frame, bytes (413 above); "
        "the whole multipart body may be 1 MiB more",
    )


ADMIN_KEY_MIN_CHARS = 16
"""Shortest admin key accepted (a guessable key is no key)."""


class AuthSettings(BaseModel):
    """API keys (`Authorization: Bearer <key>`). Setting the admin key turns auth on."""

    admin_key: SecretStr | None = Field(
        None,
        description="the admin key: creates, lists and imports maps, manages every map's "
        f"keys, reads /metrics (at least {ADMIN_KEY_MIN_CHARS} characters). Unset: auth "
        "is off, which only a loopback bind allows",
    )

    @field_validator("admin_key")
    @classmethod
    def _long_enough(cls, value: SecretStr | None) -> SecretStr | None:
        if value is not None and len(value.get_secret_value()) < ADMIN_KEY_MIN_CHARS:
            raise ValueError(
                f"must be at least {ADMIN_KEY_MIN_CHARS} characters (e.g. "
                "python3 -c 'import secrets; print(secrets.token_urlsafe(32))')"
            )
        return value

    @field_serializer("admin_key")
    def _never_dumped(self, value: SecretStr | None) -> None:
        """Dumps (e.g. the settings a worker process gets) never carry the key."""
        return None


class OpenBindError(ValueError):
    """A non-loopback bind without an admin key."""


def is_loopback(host: str) -> bool:
    """True for an address only this machine reaches (127.0.0.0/8, ::1, localhost)."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class Settings(BaseSettings):
    """Everything `covslam serve` can be told."""

    model_config = SettingsConfigDict(
        env_prefix="COVSLAM_", env_nested_delimiter="__", extra="ignore"
    )

    host: str = Field("127.0.0.1", description="address uvicorn binds")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0 = any free port)")
    data_dir: Path = Field(
        Path("./covslam-data"), description="directory of the SQLite store (created if missing)"
    )
    default_landmark_cap: int | None = Field(
        DEFAULT_LANDMARK_CAP,
        description="landmark cap of a new map whose config gives none; null = uncapped",
    )
    default_camera_landmark_cap: int | None = Field(
        CAMERA_LANDMARK_CAP,
        description="landmark cap of a new camera map whose config gives none; null = uncapped",
    )
    log_level: Literal["debug", "info", "warning", "error"] = Field(
        "info", description="log level of the service and uvicorn"
    )
    engine: Literal["local", "ray"] = Field(
        "local",
        description="where maps run: 'local' worker processes of this API process, or "
        "'ray': each map a named, detached Ray actor (pip install 'covslam[ray]')",
    )
    ray: RaySettings = Field(default_factory=RaySettings)
    store: StoreSettings = Field(default_factory=StoreSettings)
    workers: WorkerSettings = Field(default_factory=WorkerSettings)
    api: ApiSettings = Field(default_factory=ApiSettings)
    frames: FrameLimits = Field(
        default_factory=FrameLimits, description="bounds on what one posted frame may hold"
    )
    auth: AuthSettings = Field(default_factory=AuthSettings)
    max_maps: int = Field(
        1000,
        ge=1,
        description="most maps the service holds; creating or importing one more is a 507",
    )

    @property
    def auth_enabled(self) -> bool:
        """Requests need a key: an admin key is set (on any bind)."""
        return self.auth.admin_key is not None

    def check_bind(self) -> None:
        """Raises OpenBindError when the service would answer a network without keys."""
        if not self.auth_enabled and not is_loopback(self.host):
            raise OpenBindError(
                f"refusing to serve on {self.host} without authentication: set "
                "COVSLAM_AUTH__ADMIN_KEY, or bind a loopback address (127.0.0.1)"
            )

    def open_store(self) -> Store:
        """The store `store.url` names (else SQLite in `data_dir`)."""
        return open_store(
            self.store.url, data_dir=self.data_dir, synchronous=self.store.synchronous
        )

    @property
    def store_location(self) -> str:
        """Where the maps are stored, for logs (no password)."""
        if is_postgres_url(self.store.url):
            from service.store_pg import redact

            return redact(self.store.url or "")
        return str(self.store.url or self.data_dir)

    @field_validator("default_landmark_cap", "default_camera_landmark_cap")
    @classmethod
    def _cap_positive(cls, value: int | None, info: ValidationInfo) -> int | None:
        if value is not None and value < 1:
            raise ValueError(f"{info.field_name} must be >= 1 or null")
        return value


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process's settings, read from the environment once (tests: cache_clear())."""
    return Settings()
