"""The wheel: ``python -m build`` makes it, and a fresh venv with it runs ``plantscan demo``.

What a lab installing plantscan from a wheel (no checkout) gets: every plugin
package and the shipped recipes inside the wheel, plugins found through the
installed metadata, recipes by name from any folder, the Python API, and a demo
that runs.  The fresh venv takes the third-party dependencies from this
environment through a ``.pth`` line (installing open3d & co. again would cost
minutes and a network); plantscan itself comes from the wheel only, which the
test checks by where its modules are imported from.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow


def _tracked(*folders: str) -> list[str]:
    out = subprocess.run(["git", "-C", str(REPO), "ls-files", *folders], capture_output=True,
                         text=True)
    return out.stdout.split() if out.returncode == 0 else []


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    pytest.importorskip("build")
    if not (REPO / "pyproject.toml").exists():
        pytest.skip("not a source checkout")
    out = tmp_path_factory.mktemp("dist")
    src = tmp_path_factory.mktemp("src") / "plantscan"
    # Built from a copy of the tracked files, as from a clean clone (no .venv, caches, runs).
    files = _tracked() or pytest.skip("not a git checkout")
    for rel in files:
        if (REPO / rel).is_file():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / rel, src / rel)
    done = subprocess.run([sys.executable, "-m", "build", "--wheel", "--outdir", str(out),
                           str(src)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    # "cleanly": no setuptools deprecation or packaging warning in the build's output
    text = done.stdout + done.stderr
    assert "Deprecat" not in text and "SetuptoolsWarning" not in text, text[-3000:]
    (whl,) = out.glob("plantscan-*.whl")
    return whl


def test_wheel_holds_every_package_file_and_the_recipes(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    wanted = [f for f in _tracked("plantscan", "plantscan_core", "plugins")
              if not f.endswith((".md", ".txt"))]
    assert wanted
    # plugins/plantscan_x/y.py is plantscan_x/y.py in the wheel (packages.find where "plugins")
    missing = [f for f in wanted if f.removeprefix("plugins/") not in names]
    assert missing == []
    recipes = {Path(f).name for f in _tracked("recipes") if f.endswith(".yaml")}
    shipped = {Path(n).name for n in names if "/data/share/plantscan/recipes/" in n}
    assert recipes and shipped == recipes
    assert not any(n.startswith(("tests/", "benchmarks/", "docs/")) for n in names)


def test_fresh_venv_runs_the_demo_from_the_wheel(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    py = env_dir / "bin" / "python"
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()"
                                "['purelib'])"], capture_output=True, text=True).stdout.strip())
    # this environment's third-party packages, after the venv's own (plantscan: the wheel's)
    (site / "zz_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    pip = subprocess.run([str(py), "-m", "pip", "install", "--no-deps", "--no-index", "-q",
                          str(wheel)], capture_output=True, text=True, timeout=300)
    assert pip.returncode == 0, pip.stderr[-3000:]
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHONPATH", "VIRTUAL_ENV"))}
    env["PATH"] = f"{env_dir / 'bin'}{os.pathsep}{env['PATH']}"

    def run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
        return subprocess.run(list(args), cwd=work, env=env, capture_output=True, text=True,
                              timeout=timeout)

    where = run(str(py), "-c", "import plantscan, plantscan_core, plantscan_hull; "
                "print(plantscan.__file__, plantscan_core.__file__, plantscan_hull.__file__)")
    assert where.returncode == 0, where.stderr
    assert all(p.startswith(str(site)) for p in where.stdout.split()), where.stdout
    plugins = run("plantscan", "plugins", "--json")
    assert plugins.returncode == 0, plugins.stdout + plugins.stderr
    listing = json.loads(plugins.stdout)
    assert listing["failed"] == []
    assert {"octree-hull", "lab-shadow", "html-report", "sim"} <= {
        s["name"] for s in listing["stages"]}
    check = run("plantscan", "recipe", "check", "plastic-dicot")
    assert check.returncode == 0 and "OK" in check.stdout, check.stderr
    # A small demo: few small images, the hull on its numpy path (this venv's numba cache
    # is empty; compiling the hull kernels is what `plantscan warm-up` is for, tested in
    # tests/hull/test_warmup.py).
    demo = run("plantscan", "demo", "--out", "demo",
               "--set", "scan.image_size=[320,213]", "--set", "scan.images_per_revolution=8",
               "--set", "scan.roles.calibration.images_per_revolution=12",
               "--set", "reconstruct.params.backend=numpy",
               "--set", "reconstruct.params.resolution=64", timeout=900)
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr[-3000:]
    assert (work / "demo" / "run" / "report.html").exists()
    assert (work / "demo" / "run" / "traits.csv").exists()
    assert "demo: report" in demo.stdout
