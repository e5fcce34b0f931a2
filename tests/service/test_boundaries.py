"""Package edges: the service never imports the worker (the worker imports the service, and hands its Celery
app to ``service.compose``); the API sends its tasks through the Celery app it is given."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

from svc_helpers import REPO, auth, make_settings

from service.core.dispatch import SCAN_SURVEY_TASK, SURVEY_QUEUE

FORBIDDEN = "worker"


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(source: str, module: str, is_package: bool = False) -> list[str]:
    """Every module an import statement anywhere in ``source`` (functions, classes, conditionals included) names,
    relative imports resolved against ``module``; ``from a import b`` yields both ``a`` and ``a.b``."""
    package = module.split(".") if is_package else module.split(".")[:-1]
    found: list[str] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package[:len(package) - (node.level - 1)] if node.level - 1 <= len(package) else []
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if base:
                found.append(base)
            found += [f"{base}.{a.name}" if base else a.name for a in node.names]
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            if name in ("import_module", "__import__"):
                found.append(node.args[0].value)
    return found


def names_worker(name: str) -> bool:
    return name == FORBIDDEN or name.startswith(FORBIDDEN + ".")


def test_the_import_walker_sees_every_kind_of_import() -> None:
    src = ("import os\n"
           "from . import jobs\n"
           "def f():\n"
           "    from worker.app import create_celery\n"
           "class C:\n"
           "    def g(self):\n"
           "        import worker.tasks as t\n"
           "if True:\n"
           "    from .. import worker\n"
           "def h():\n"
           "    importlib.import_module('worker.runner')\n")
    found = imported_modules(src, "service.app")
    assert "service.jobs" in found and "os" in found
    assert sorted(n for n in found if names_worker(n)) == ["worker", "worker.app", "worker.app.create_celery",
                                                           "worker.runner", "worker.tasks"]
    # relative imports resolve against the package: service/api/deps.py's ``from .errors`` is service.api.errors
    assert "service.api.errors" in imported_modules("from .errors import api_error", "service.api.deps")
    assert "service.surveys.exif" in imported_modules("from .exif import x", "service.surveys", is_package=True)
    assert "service.workers" not in [n for n in imported_modules("import service.workers", "service.x")
                                     if names_worker(n)]


def test_service_imports_nothing_from_worker() -> None:
    root = REPO
    modules = sorted((root / "service").rglob("*.py"))
    assert len(modules) > 20, modules
    offenders = []
    for path in modules:
        name = module_name(path, root)
        for imported in imported_modules(path.read_text(encoding="utf-8"), name, path.name == "__init__.py"):
            if names_worker(imported):
                offenders.append(f"{path.relative_to(root)}: {imported}")
    assert not offenders, offenders


def test_importing_and_building_the_api_loads_no_worker_module(tmp_path: Path) -> None:
    """The same at run time: every module under service/ imported, the app built, no ``worker`` module loaded."""
    code = ("import importlib, pkgutil, sys\n"
            "import service\n"
            "for m in pkgutil.walk_packages(service.__path__, 'service.'):\n"
            "    importlib.import_module(m.name)\n"
            "import service.app\n"
            "service.app.create_app()\n"
            "bad = sorted(m for m in sys.modules if m == 'worker' or m.startswith('worker.'))\n"
            "assert not bad, bad\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("DUALPHYS_")}
    env.update(DUALPHYS_API_KEYS=json.dumps({"a-long-enough-api-key": "alice"}), DUALPHYS_DATA_DIR=str(tmp_path),
               PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 0, r.stderr[-2000:]


class RecordingCelery:
    """A Celery app stand-in: records ``send_task`` calls."""

    class Result:
        def __init__(self, task_id: str) -> None:
            self.id = task_id

    def __init__(self) -> None:
        self.sent: list[tuple[str, list, str]] = []

    def send_task(self, name: str, args=None, **options):
        self.sent.append((name, list(args or []), options.get("queue")))
        return self.Result(f"task-{len(self.sent)}")


def test_the_api_sends_through_the_celery_app_it_is_given(tmp_path: Path, unit_prefix: str) -> None:
    from fastapi.testclient import TestClient

    from service.app import create_app

    (tmp_path / "surveys-root" / "reef").mkdir(parents=True)
    celery = RecordingCelery()
    with TestClient(create_app(make_settings(tmp_path, unit_prefix), celery_app=celery)) as client:
        r = client.post("/v1/surveys", json={"path": str(tmp_path / "surveys-root" / "reef"), "interval_s": 60},
                        headers=auth("alice"))
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        r = client.post(f"/v1/surveys/{sid}/scan", headers=auth("alice"))
        assert r.status_code == 202, r.text
        assert r.json()["task_id"] == "task-1"
    assert celery.sent == [(SCAN_SURVEY_TASK, [sid], SURVEY_QUEUE)]
