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
