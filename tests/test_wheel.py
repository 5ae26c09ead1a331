"""The package as a user installs it: an sdist and a wheel built from the sources (``python -m build``,
the wheel compiled from the sdist), the wheel installed into a fresh venv in a temporary folder, and
``cell`` run there, away from the checkout: a short sim scan, ``cell init`` and ``cell serve``.

The venv borrows the third-party dependencies of the interpreter running the tests (a ``.pth`` line to its
site-packages, whose own ``.pth`` files, the checkout's editable install among them, are not read), so that
the test does not download Open3D; ``pip check`` then verifies that they satisfy the wheel's requirements.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import time
import zipfile
from pathlib import Path

import httpx
import pytest

from cell.deploy import DEPLOY_FILES
from tests.service_process import REPO, free_port

SOURCES = ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md", "cell", "drivers", "calibration")
BUILD_TIMEOUT_S = 600


@pytest.fixture(scope="module")
def dist(tmp_path_factory) -> Path:
    """The sdist and wheel of a copy of the sources (no compiled or cached file of the checkout)."""
    src = tmp_path_factory.mktemp("src")
    for name in SOURCES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("*.so", "*.c", "__pycache__"))
        else:
            shutil.copy2(path, src / name)
    out = tmp_path_factory.mktemp("dist")
    subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(out), str(src)],
                   check=True, capture_output=True, timeout=BUILD_TIMEOUT_S)
    return out


@pytest.fixture(scope="module")
def venv(dist, tmp_path_factory) -> Path:
    """A fresh venv with the wheel installed; returns its ``bin``."""
    root = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root)], check=True)
    purelib = Path(subprocess.check_output([str(root / "bin" / "python"), "-c",
                                            "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                           text=True).strip())
    (purelib / "borrowed-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    wheel = next(dist.glob("cell-*.whl"))
    pip = [str(root / "bin" / "python"), "-m", "pip"]
    subprocess.run([*pip, "install", "--quiet", "--no-deps", str(wheel)], check=True, capture_output=True)
    subprocess.run([*pip, "check"], check=True, capture_output=True)
    return root / "bin"


def test_the_sdist_holds_the_sources_and_the_wheel_the_kernels_and_data(dist):
    with tarfile.open(next(dist.glob("cell-*.tar.gz"))) as archive:
        sdist = {n.split("/", 1)[1] for n in archive.getnames() if "/" in n}
    assert {"cell/perception/_kernels.pyx", "cell/planning/vs/_objective.pyx", "setup.py",
            "cell/templates/ur5e-vl53l8cx.yaml"} <= sdist
    assert not any(n.startswith("tests/") or n.endswith(".so") for n in sdist)
    wheel = zipfile.ZipFile(next(dist.glob("cell-*.whl"))).namelist()
    for pattern in ("cell/perception/_kernels.cpython", "cell/planning/vs/_objective.cpython",
                    "cell/planning/lrnbv/_raygains.cpython", "drivers/sim/objects/bunny.ply",
                    "drivers/sim/objects/CREDITS", "cell/web/static/index.html",
                    "cell/templates/sim-ur5e-tof.yaml", "cell/deploy/systemd/cell.service",
                    "cell/deploy/udev/99-vl53l8cx.rules", "calibration/README.md",
                    "cell/line/Opc.Ua.PackML.NodeSet2.xml",
                    "cell/service/store/migrations/versions/0001_initial.py"):
        assert any(n.startswith(pattern) for n in wheel), pattern


def test_the_installed_cell_scans_inits_and_serves_without_the_checkout(venv, tmp_path):
    cell = str(venv / "cell")
    where = subprocess.check_output([str(venv / "python"), "-c", "import cell.perception._kernels as k; "
                                     "print(k.__file__)"], cwd=tmp_path, text=True)
    assert where.startswith(str(venv.parent)), where
    scan = subprocess.run([cell, "scan", "--object", "cube", "--max-time", "4", "--out", "job"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert scan.returncode == 0, scan.stderr
    result = json.loads((tmp_path / "job" / "result.json").read_text())
    assert result["status"] == "completed" and result["n_captures"] >= 1
    init = subprocess.run([cell, "init", "site", "--template", "ur5e-vl53l8cx"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60)
    assert init.returncode == 0 and "arm.host" in init.stdout, init.stderr
    # what the cell file's marks and docs/deploy.md name, from the installed package
    assert "(cell calibrate guide)" in init.stdout
    guide = subprocess.run([cell, "calibrate", "guide"], cwd=tmp_path, capture_output=True, text=True,
                           timeout=60)
    assert guide.returncode == 0 and guide.stdout.startswith("# Calibration"), guide.stderr
    files = subprocess.run([cell, "deploy", "files", "deploy"], cwd=tmp_path, capture_output=True, text=True,
                           timeout=60)
    assert files.returncode == 0, files.stderr
    for name in DEPLOY_FILES:
        assert (tmp_path / "deploy" / name).read_bytes() == (REPO / "deploy" / name).read_bytes()

    port = free_port()
    serve = subprocess.Popen([cell, "serve", "--port", str(port)], cwd=tmp_path, stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while True:
            assert serve.poll() is None, serve.communicate()[1]
            assert time.monotonic() < deadline, "cell serve did not answer"
            try:
                health = httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1)
                break
            except httpx.HTTPError:
                time.sleep(0.2)
        assert health.status_code == 200
        page = httpx.get(f"http://127.0.0.1:{port}/", timeout=5)
        assert page.status_code == 200 and "<html" in page.text.lower()
    finally:
        serve.terminate()
        serve.wait(timeout=30)
    assert (tmp_path / "data" / "cell.db").is_file()
