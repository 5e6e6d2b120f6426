"""The wheel: ``python -m build`` makes it, and a fresh venv with it runs ``plantscan demo``.

What a lab installing plantscan from a wheel (no checkout) gets: every plugin
package and the shipped recipes inside the wheel, plugins found through the
installed metadata, recipes by name from any folder, the Python API, and a demo
that runs, without the hardware libraries.

The fresh venv gets exactly what ``pip install plantscan-*.whl`` would install:
the wheel (through pip, ``--no-deps``), and the closure of the wheel's own
``Requires-Dist`` (no extras) over the distributions of this environment,
linked file by file from it, as pip would unpack them from its cache (copying
2 GB of open3d & co. again would cost minutes, downloading them a network).  So
a dependency the code imports but the wheel does not declare fails the demo,
``pip check`` sees every requirement met, and gphoto2, phidget22 and pyserial
(the extras) are not there.  plantscan itself comes from the wheel only, which
the test checks by where its modules are imported from.
"""

from __future__ import annotations

import email
import importlib.metadata as md
import json
import os
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow
HARDWARE = {"gphoto2", "phidget22", "pyserial"}  # the extras' libraries


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


def _requires(wheel: Path) -> list[str]:
    """The wheel's ``Requires-Dist`` lines."""
    with zipfile.ZipFile(wheel) as z:
        (name,) = [n for n in z.namelist() if n.endswith(".dist-info/METADATA")]
        return email.message_from_bytes(z.read(name)).get_all("Requires-Dist") or []


def _closure(requirements: list[str]) -> dict[str, md.Distribution]:
    """Canonical name -> installed distribution, for ``requirements`` and what they need
    (markers evaluated here, extras followed where asked), as pip would resolve them."""
    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    found: dict[str, md.Distribution] = {}
    todo = [(Requirement(r), "") for r in requirements]
    while todo:
        req, extra = todo.pop()
        if req.marker is not None and not req.marker.evaluate({"extra": extra}):
            continue
        name = canonicalize_name(req.name)
        dist = found.get(name)
        if dist is None:
            dist = found[name] = md.distribution(req.name)
            todo += [(Requirement(r), "") for r in dist.requires or []]
        for ex in req.extras:
            todo += [(Requirement(r), ex) for r in dist.requires or []]
    return found


def _link_into(site: Path, dists: dict[str, md.Distribution]) -> None:
    """Each distribution's files (its RECORD: packages, .dist-info, .pth) linked into
    ``site``; scripts and data outside site-packages are left out."""
    for dist in dists.values():
        for f in dist.files or []:
            if ".." in f.parts:
                continue
            src, dst = Path(dist.locate_file(f)), site / f
            if src.is_file() and not dst.exists():
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.symlink(src, dst)


def test_default_install_pulls_no_hardware_library(wheel):
    declared = _requires(wheel)
    default = [r for r in declared if "extra ==" not in r]
    assert not HARDWARE & set(_closure(default))
    extras = {r.split("extra ==")[1].strip(" '\"") for r in declared if "extra ==" in r}
    assert {"gphoto2", "phidget", "serial", "all"} <= extras


def test_fresh_venv_runs_the_demo_from_the_wheel(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    py = env_dir / "bin" / "python"
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()"
                                "['purelib'])"], capture_output=True, text=True).stdout.strip())
    deps = _closure([r for r in _requires(wheel) if "extra ==" not in r])
    _link_into(site, deps)
    pip = subprocess.run([str(py), "-m", "pip", "install", "--no-deps", "--no-index", "-q",
                          str(wheel)], capture_output=True, text=True, timeout=300)
    assert pip.returncode == 0, pip.stderr[-3000:]
    met = subprocess.run([str(py), "-m", "pip", "check"], capture_output=True, text=True)
    assert met.returncode == 0, met.stdout  # every requirement of the wheel is met
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
    hardware = run(str(py), "-c", "import importlib.util as u; print([m for m in "
                   "('gphoto2', 'Phidget22', 'serial') if u.find_spec(m)])")
    assert hardware.stdout.strip() == "[]", hardware.stdout + hardware.stderr
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
