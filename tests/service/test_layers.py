"""Dependencies point one way: the running service (the API app, a worker, a map
session) never loads the offline tools, and the map pipeline knows nothing of the
runtime around it."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path


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


def _imported_names(path: Path) -> set[str]:
    """Every module name an `import` or `from ... import` in `path` names."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module is not None and node.level == 0:
            names.add(node.module)
    return names


def test_no_test_imports_the_benchmarks() -> None:
    """`bench` is not shipped: what tests need lives in the product or under tests/."""
    tests = Path(__file__).resolve().parents[1]
    modules = sorted(tests.rglob("*.py"))
    assert len(modules) > 50
    offenders = {
        str(p.relative_to(tests)): sorted(
            n for n in _imported_names(p) if n.split(".")[0] == "bench"
        )
        for p in modules
    }
    assert {p: names for p, names in offenders.items() if names} == {}


def test_the_import_check_sees_a_bench_import(tmp_path: Path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text(
        "import os\nfrom bench.clusters import PrivatePostgres\nimport bench.lifelong\n"
    )
    assert {"bench.clusters", "bench.lifelong", "os"} == _imported_names(probe)
