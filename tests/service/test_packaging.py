"""What can be tested of the serving image without a Docker engine.

* The serving code path (app, every route, l1/l2, the client, `gradsep serve --help`) imports nothing outside
  the core + ``serve`` dependencies: run in a subprocess where torch, mitsuba and the other roles' packages
  cannot be imported.
* The Dockerfile installs exactly ``.[serve]`` on a slim Python 3.11, runs as a non-root user, and its
  HEALTHCHECK command really succeeds against a live service (and fails against a dead one).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tomllib

import pytest

from gradsep.cli import main
from gradsep.service.main import create_app
from tests.service.conftest import REPO, free_port, settings, uvicorn_server

# Packages of the render/train/evaluate roles: a serving host does not have them.
NOT_ON_A_SERVING_HOST = ("torch", "mitsuba", "drjit", "onnx", "onnxscript", "tqdm", "matplotlib", "flip_evaluator",
                         "pyoidn", "rich")

SERVING_SMOKE = """
import importlib.util, sys, tempfile
for name in {blocked!r}:
    sys.modules[name] = None  # any import of it now raises ImportError
from fastapi.testclient import TestClient
from gradsep.cli import build_parser
from gradsep.service.main import create_app
from gradsep.service.settings import Settings
import gradsep.service.client
from tests.service.frames import frame_bytes
if importlib.util.find_spec("gradsep.model.infer") is not None:
    import model.infer  # the network path must be servable too
build_parser().parse_args(["serve", "--port", "1"])
with tempfile.TemporaryDirectory() as models:  # an existing but empty models folder
    with TestClient(create_app(Settings(models_dir=models, token=None))) as client:
        import time
        for _ in range(600):
            if client.get("/readyz").status_code == 200:
                break
            time.sleep(0.05)
        for method in ("l1", "l2"):
            r = client.post("/v1/reconstruct", params={{"method": method}}, content=frame_bytes(),
                            headers={{"Content-Type": "image/x-exr"}})
            assert r.status_code == 200, r.text
        assert client.get("/metrics").status_code == 200 and client.get("/v1/models").status_code == 200
leaked = sorted(m for m in sys.modules if m.split(".")[0] in {blocked!r} and sys.modules[m] is not None)
assert not leaked, leaked
print("serving path OK")
"""


def test_serving_path_needs_no_torch_mitsuba_or_other_roles_packages():
    code = SERVING_SMOKE.format(blocked=NOT_ON_A_SERVING_HOST)
    run = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300,
                         env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stdout + run.stderr
    assert "serving path OK" in run.stdout


@pytest.mark.slow
def test_the_wheel_installs_one_top_level_name(tmp_path):
    """The distribution claims only ``gradsep``: model/, service/, ... install as gradsep.model, gradsep.service
    (setup.py), never as generic top-level packages that would collide with a farm tool's own ``model.py``."""
    import zipfile

    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                            "-w", str(tmp_path), str(REPO)], capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr
    (wheel,) = tmp_path.glob("gradsep-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names} == {"gradsep", wheel.name.split("-")[0] + "-" +
                                                 wheel.name.split("-")[1] + ".dist-info"}
    for package in ("model", "service", "renderer", "training", "evaluation"):
        assert f"gradsep/{package}/__init__.py" in names, package
    assert "gradsep/service/routers/__init__.py" in names


def test_serve_extra_has_what_the_service_imports_and_nothing_heavy():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    names = {re.split(r"[\[<>=!~ ;]", dep, maxsplit=1)[0].lower()
             for dep in project["dependencies"] + project["optional-dependencies"]["serve"]}
    assert {"fastapi", "uvicorn", "python-multipart", "pydantic-settings", "prometheus-client", "httpx",
            "numpy", "scipy", "openexr"} <= names
    assert {"onnxruntime", "onnxruntime-openvino"} <= names  # one or the other, by platform marker
    assert not names & {"torch", "mitsuba", "drjit"}


def dockerfile() -> str:
    return (REPO / "Dockerfile").read_text()


def test_dockerfile_installs_only_the_serve_extra_as_non_root():
    text = dockerfile()
    assert re.findall(r"^FROM (\S+)", text, re.MULTILINE) == ["python:3.11-slim", "python:3.11-slim"]
    installs = re.findall(r"pip install (.+)$", text, re.MULTILINE)
    assert installs == ['".[serve]"']
    users = re.findall(r"^USER (\S+)", text, re.MULTILINE)
    assert users and users[-1] not in ("root", "0")
    assert re.search(r"^COPY models/ /app/models/", text, re.MULTILINE)
    assert re.search(r'^CMD \["gradsep", "serve"', text, re.MULTILINE)


def healthcheck_argv(port: int) -> list[str]:
    match = re.search(r"^HEALTHCHECK .*?CMD (\[.*?\])$", dockerfile(), re.MULTILINE | re.DOTALL)
    assert match, "no HEALTHCHECK with an exec-form CMD"
    argv = json.loads(match.group(1))
    assert argv[0] == "python" and "/healthz" in argv[-1]  # no curl in a slim image
    return [sys.executable, *[a.replace("127.0.0.1:8000", f"127.0.0.1:{port}") for a in argv[1:]]]


def test_dockerfile_healthcheck_passes_on_a_live_service_and_fails_on_a_dead_one():
    with uvicorn_server(create_app(settings(token="secret"))) as url:  # health needs no token
        port = int(url.rsplit(":", 1)[1])
        alive = subprocess.run(healthcheck_argv(port), capture_output=True, timeout=30)
    assert alive.returncode == 0, alive.stderr
    dead = subprocess.run(healthcheck_argv(free_port()), capture_output=True, timeout=30)
    assert dead.returncode != 0


@pytest.mark.parametrize("env, argv, needle", [
    ({"GRADSEP_CONCURRENCY": "0"}, [], "GRADSEP_CONCURRENCY"),
    ({"GRADSEP_NONFINITE": "ignore"}, [], "GRADSEP_NONFINITE"),
    ({"GRADSEP_LAYER_THREADS": "0"}, [], "GRADSEP_LAYER_THREADS"),
    ({"GRADSEP_EXR_THREADS": "-2"}, [], "GRADSEP_EXR_THREADS"),
    ({"GRADSEP_MALLOC_ARENAS": "-1"}, [], "GRADSEP_MALLOC_ARENAS"),
    ({"GRADSEP_MALLOC_ARENAS": "many"}, [], "GRADSEP_MALLOC_ARENAS"),
    ({}, ["--port", "70000"], "--port"),
    ({}, ["--workers", "0"], "--workers"),
])
def test_serve_refuses_bad_settings_with_one_line_and_exit_2(monkeypatch, capsys, env, argv, needle):
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    assert main(["serve", *argv]) == 2  # before uvicorn starts: nothing listens
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gradsep serve: error:") and needle in err[0]
