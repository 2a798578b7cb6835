"""Dependencies point one way: the running service (the API app, a worker, a map
session) never loads the offline tools, and the map pipeline knows nothing of the
runtime around it."""

from __future__ import annotations

import json
import subprocess
import sys


def _loaded(*modules: str) -> list[str]:
    """Names of the covslam modules a fresh interpreter has loaded after importing
    `modules`."""
    code = (
        "import importlib, json, sys\n"
        f"for name in {list(modules)!r}:\n"
        "    importlib.import_module(name)\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('api', 'service', 'graph', 'frontend'))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return list(json.loads(out.stdout))


def test_the_runtime_never_loads_the_offline_tools() -> None:
    loaded = _loaded("api.app", "service.worker", "service.session")
    assert "service.session" in loaded and "service.pipeline" in loaded
    assert [m for m in loaded if m.startswith("service.offline")] == []
    assert "api.cli" not in loaded


def test_the_pipeline_imports_no_runtime() -> None:
    loaded = _loaded("service.pipeline", "service.pipeline.snapshot")
    runtime = [
        m
        for m in loaded
        if m.startswith(("api", "service.")) and not m.startswith("service.pipeline")
    ]
    assert runtime == []
