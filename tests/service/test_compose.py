"""docker-compose.yml validates (no Docker engine here): against the Compose specification's JSON schema as
vendored by check-jsonschema (``--builtin-schema vendor.compose-spec``), plus the structure issue 6 asks for
and module paths that exist in this repository."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest
from svc_helpers import REPO

COMPOSE = REPO / "docker-compose.yml"


def _load() -> dict:
    ruamel = pytest.importorskip("ruamel.yaml", reason="ruamel.yaml (installed with check-jsonschema) parses YAML")
    return ruamel.YAML(typ="safe", pure=True).load(COMPOSE.read_text())


def test_compose_file_matches_the_compose_spec_schema() -> None:
    pytest.importorskip("check_jsonschema", reason="check-jsonschema carries the Compose spec's JSON schema")
    r = subprocess.run([sys.executable, "-m", "check_jsonschema", "--builtin-schema", "vendor.compose-spec",
                        str(COMPOSE)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_compose_structure() -> None:
    doc = _load()
    svc = doc["services"]
    assert {"api", "worker", "beat", "redis", "gpu-worker"} <= set(svc)
    redis = svc["redis"]
    assert "--appendonly" in redis["command"] and redis["command"][redis["command"].index("--appendonly") + 1] == "yes"
    assert any(v.endswith(":/data") for v in redis["volumes"])
    for name, s in svc.items():
        assert "healthcheck" in s and s["healthcheck"]["test"], name
    app_services = ["api", "worker", "beat", "gpu-worker"]
    for name in app_services:
        s = svc[name]
        assert "jobs-data:/data" in s["volumes"], name  # one shared data volume
        assert s["depends_on"]["redis"]["condition"] == "service_healthy", name
        assert s["environment"]["DUALPHYS_REDIS_URL"].startswith("redis://redis:"), name
        assert (REPO / s["build"]["dockerfile"]).is_file(), name
    assert set(doc["volumes"]) >= {"jobs-data", "redis-data"}
    gpu = svc["gpu-worker"]
    assert gpu["profiles"] == ["gpu"] and gpu["build"]["dockerfile"] == "docker/Dockerfile.cuda"
    assert gpu["command"][gpu["command"].index("-Q") + 1] == "gpu" and gpu["environment"]["DUALPHYS_DEVICE"] == "cuda"
    assert gpu["deploy"]["resources"]["reservations"]["devices"][0]["capabilities"] == ["gpu"]
    worker_queues = svc["worker"]["command"][svc["worker"]["command"].index("-Q") + 1].split(",")
    assert set(worker_queues) == {"cpu", "surveys"}
    assert "--schedule" in svc["beat"]["command"]


def test_compose_hosts_profile() -> None:
    """Profile ``hosts``: the object store and workers that share no volume with the API (issue 44)."""
    doc = _load()
    svc = doc["services"]
    objects, worker = svc["objects"], svc["host-worker"]
    assert objects["profiles"] == worker["profiles"] == ["hosts"]
    assert "-s3" in objects["command"] and "-s3.port=8333" in objects["command"]
    assert objects["configs"][0]["target"] == "/etc/seaweedfs/s3.json"
    assert "accessKey" in doc["configs"][objects["configs"][0]["source"]]["content"]
    assert "objects-data:/data" in objects["volumes"] and "objects-data" in doc["volumes"]
    env = worker["environment"]
    assert env["DUALPHYS_DATA_DIR"] == "/scratch" and worker["volumes"] == ["/scratch"]  # its own folder only
    assert not any("jobs-data" in v for v in worker["volumes"])
    assert env["DUALPHYS_OBJECT_STORE_URL"].endswith("http://objects:8333}")
    assert worker["depends_on"]["objects"]["condition"] == "service_healthy"
    assert worker["command"][:3] == ["celery", "-A", "worker.app"] and int(worker["deploy"]["replicas"]) >= 2
    # the API and the other services read the same store settings (empty: the data volume is the store)
    for name in ("api", "worker", "beat"):
        assert svc[name]["environment"]["DUALPHYS_OBJECT_STORE_URL"] == "${DUALPHYS_OBJECT_STORE_URL:-}", name


def test_compose_commands_name_real_modules() -> None:
    doc = _load()
    svc = doc["services"]
    api_cmd = svc["api"]["command"]
    module, attr = api_cmd[api_cmd.index("--factory") + 1].split(":")
    assert callable(getattr(importlib.import_module(module), attr))
    for name in ("worker", "beat", "gpu-worker"):
        cmd = svc[name]["command"]
        assert hasattr(importlib.import_module(cmd[cmd.index("-A") + 1]), "app"), name
    assert svc["beat"]["healthcheck"]["test"][-1] == "worker.healthcheck"
    importlib.import_module("worker.healthcheck")
    for dockerfile in ("docker/Dockerfile", "docker/Dockerfile.cuda"):
        text = (REPO / dockerfile).read_text()
        for line in text.splitlines():
            if line.startswith("COPY "):
                for src in line.split()[1:-1]:
                    assert (REPO / src).exists(), (dockerfile, src)
