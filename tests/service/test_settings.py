"""Settings from COVSLAM_* variables, nested with __; unsafe values refused."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from service.settings import Settings, get_settings


def test_nested_environment_variables(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COVSLAM_PORT", "9123")
    monkeypatch.setenv("COVSLAM_DATA_DIR", "/tmp/somewhere")
    monkeypatch.setenv("COVSLAM_STORE__SYNCHRONOUS", "FULL")
    monkeypatch.setenv("COVSLAM_WORKERS__COUNT", "3")
    monkeypatch.setenv("COVSLAM_DEFAULT_LANDMARK_CAP", "20")
    monkeypatch.setenv("COVSLAM_DEFAULT_CAMERA_LANDMARK_CAP", "150")
    get_settings.cache_clear()
    try:
        s = get_settings()
        assert s.port == 9123 and s.data_dir == Path("/tmp/somewhere")
        assert s.store.synchronous == "FULL" and s.workers.count == 3
        assert s.default_landmark_cap == 20
        assert s.default_camera_landmark_cap == 150
    finally:
        get_settings.cache_clear()


def test_defaults() -> None:
    s = Settings()
    assert s.store.synchronous == "NORMAL"
    assert s.data_dir == Path("./covslam-data")
    assert s.workers.count >= 1 and s.api.max_body_bytes >= 1024


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("COVSLAM_STORE__SYNCHRONOUS", "OFF"),
        ("COVSLAM_WORKERS__COUNT", "0"),
        ("COVSLAM_DEFAULT_CAMERA_LANDMARK_CAP", "0"),
        ("COVSLAM_DEFAULT_LANDMARK_CAP", "0"),
        ("COVSLAM_PORT", "70000"),
    ],
)
def test_unsafe_values_are_refused(monkeypatch: pytest.MonkeyPatch, name: str, value: str) -> None:
    monkeypatch.setenv(name, value)
    with pytest.raises(ValidationError):
        Settings()


def test_engine_ray_address_and_store_url_from_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("COVSLAM_ENGINE", "ray")
    monkeypatch.setenv("COVSLAM_RAY__ADDRESS", "10.0.0.5:6379")
    monkeypatch.setenv("COVSLAM_STORE__URL", "postgresql://covslam:s3cret@db:5432/maps")
    s = Settings()
    assert s.engine == "ray" and s.ray.address == "10.0.0.5:6379"
    assert s.store.url == "postgresql://covslam:s3cret@db:5432/maps"
    assert s.store_location == "postgresql://covslam:***@db:5432/maps"


def test_a_store_url_is_a_directory_or_postgresql(tmp_path: Path) -> None:
    s = Settings(data_dir=tmp_path / "ignored", store={"url": str(tmp_path / "maps")})
    store = s.open_store()
    store.catalog().close()
    assert (tmp_path / "maps" / "catalog.sqlite").exists()
    assert not (tmp_path / "ignored").exists()
    for bad in ("mysql://db/maps", "sqlite:///tmp/x"):
        with pytest.raises(ValidationError, match="directory or a postgresql"):
            Settings(store={"url": bad})
    with pytest.raises(ValidationError):
        Settings(engine="threads")
