"""Settings from COVSLAM_* variables, nested with __; unsafe values refused."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from api.cli import main as cli_main
from service.settings import OpenBindError, Settings, get_settings, is_loopback


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


# --------------------------------------------------------------------------- auth and bind


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("127.0.0.1", True),
        ("127.8.9.1", True),
        ("::1", True),
        ("[::1]", True),
        ("localhost", True),
        ("0.0.0.0", False),
        ("::", False),
        ("10.1.2.3", False),
        ("example.org", False),
    ],
)
def test_loopback_rule(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback
    open_settings = Settings(host=host)
    assert not open_settings.auth_enabled
    if loopback:
        open_settings.check_bind()  # auth off, allowed
    else:
        with pytest.raises(OpenBindError, match="COVSLAM_AUTH__ADMIN_KEY"):
            open_settings.check_bind()
    keyed = Settings(host=host, auth={"admin_key": "k" * 32})  # type: ignore[arg-type]
    assert keyed.auth_enabled
    keyed.check_bind()  # a key turns auth on, on any bind


def test_admin_key_from_the_environment_is_never_dumped(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COVSLAM_AUTH__ADMIN_KEY", "a-long-enough-admin-key")
    s = Settings()
    assert s.auth.admin_key is not None
    assert s.auth.admin_key.get_secret_value() == "a-long-enough-admin-key"
    assert "a-long-enough-admin-key" not in repr(s)
    dumped = s.model_dump(mode="json")  # what a worker process gets
    assert dumped["auth"]["admin_key"] is None
    assert "a-long-enough-admin-key" not in str(dumped)


def test_short_admin_key_refused() -> None:
    with pytest.raises(ValidationError, match="at least 16"):
        Settings(auth={"admin_key": "short"})  # type: ignore[arg-type]


def _serve_refusal(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert cli_main(["serve", *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("covslam serve: ")
    return err


def test_serve_refuses_workers_0_like_the_variable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    err = _serve_refusal(["--workers", "0", "--data-dir", str(tmp_path)], capsys)
    assert "workers.count" in err and "0" in err
    monkeypatch.setenv("COVSLAM_WORKERS__COUNT", "0")
    assert "workers.count" in _serve_refusal(["--data-dir", str(tmp_path)], capsys)


def test_serve_refuses_an_open_bind_without_admin_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("COVSLAM_AUTH__ADMIN_KEY", raising=False)
    err = _serve_refusal(["--host", "0.0.0.0", "--data-dir", str(tmp_path)], capsys)
    assert "0.0.0.0" in err and "COVSLAM_AUTH__ADMIN_KEY" in err


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


def test_serve_refuses_a_store_url_like_the_variable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _serve_refusal(["--store-url", "mysql://db/maps", "--data-dir", str(tmp_path)], capsys)
    assert "store.url" in err and "mysql://db/maps" in err


@pytest.mark.parametrize(("setting", "expected"), [(1, {1}), (2, {2})])
def test_a_worker_limits_its_blas_threads(setting: int, expected: set[int]) -> None:
    """workers.blas_threads reaches every BLAS library loaded in a worker process (in a
    child here: the limit is process-wide). Two settings, so that neither can pass by
    being the library's default."""
    code = (
        "import json, sys\n"
        "from threadpoolctl import threadpool_info\n"
        "from service import worker\n"
        "from service.settings import Settings\n"
        f"s = Settings(workers={{'nice': 0, 'blas_threads': {setting}}})\n"
        "worker.init_worker(s.model_dump(mode='json'), 0, own_signals=False)\n"
        "json.dump([i['num_threads'] for i in threadpool_info()"
        " if i['user_api'] == 'blas'], sys.stdout)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    threads = json.loads(out.stdout)
    assert threads, "numpy's BLAS is loaded in a worker"
    assert set(threads) == expected
