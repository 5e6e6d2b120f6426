"""`plantscan scan` on the virtual scanner, killed with SIGKILL 10 times and interrupted with
Ctrl-C once, then resumed."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from plantscan_core.acquire import plan
from plantscan_core.plugins import load_plugins
from plantscan_core.recipe import validate_recipe
from plantscan_core.scanfolder import ScanFolder

ROOT = Path(__file__).resolve().parents[2]
PLANTSCAN = Path(sys.executable).with_name("plantscan")


def _lines(path: Path) -> int:
    try:
        return path.read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


@pytest.mark.slow
def test_cli_scan_survives_ten_sigkills(tmp_path):
    shipped = ROOT / "recipes" / "plastic-dicot.yaml"
    if not shipped.exists() or not PLANTSCAN.exists():
        pytest.skip("needs the virtual scanner's recipe and the plantscan command")
    raw = yaml.safe_load(shipped.read_text())
    # Scan only (processing sections need other plugins), tiny images, 8 stops per turn.
    raw = {"name": "kill-test", "plant": raw["plant"], "scan": raw["scan"]}
    raw["scan"].update(image_size=[64, 48], images_per_revolution=8)
    recipe_file = tmp_path / "recipe.yaml"
    recipe_file.write_text(yaml.safe_dump(raw))
    manager = load_plugins()
    if "sim" not in manager.registry.names("camera"):
        pytest.skip("the virtual scanner (plantscan_sim) is not installed")
    recipe = validate_recipe(raw, manager.registry)
    out = tmp_path / "scan"
    cmd = [str(PLANTSCAN), "scan", "--recipe", str(recipe_file), "--out", str(out)]
    rng = random.Random(3)
    seen: dict[str, tuple[int, int]] = {}
    kills = 0
    for i in range(10):
        proc = subprocess.Popen(cmd + (["--resume"] if (out / "scan.yaml").exists() else []),
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        start = _lines(out / "views.jsonl")
        # Kill at a random moment once this run has captured something (start-up and scene
        # set-up take a variable time) - between renders, during a write or a rename.
        while proc.poll() is None and _lines(out / "views.jsonl") <= start:
            time.sleep(0.01)
        time.sleep(rng.uniform(0.0, 0.25))
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            kills += 1
        _, err = proc.communicate()
        assert proc.returncode in (0, -signal.SIGKILL), err.decode()[-2000:]
        scan = ScanFolder.open(out)
        for v in scan.views:
            st = scan.path_of(v).stat()
            assert seen.setdefault(v.file, (st.st_ino, st.st_mtime_ns)) == (
                st.st_ino, st.st_mtime_ns), f"{v.file} rewritten after kill {i}"
    assert kills == 10, "the scan finished before all kills landed"
    # Ctrl-C: the command says so and exits 130, the folder stays consistent.
    proc = subprocess.Popen(cmd + ["--resume"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    start = _lines(out / "views.jsonl")
    while proc.poll() is None and _lines(out / "views.jsonl") <= start:
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    if _lines(out / "views.jsonl") < len(plan(recipe)):  # the scan was not already over
        assert proc.returncode == 130, err.decode()[-2000:]
        assert b"interrupted; everything finished so far is kept" in err
    res = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    scan = ScanFolder.open(out)
    keys = [v.key for v in scan.views]
    assert len(keys) == len(set(keys)) and set(keys) == {v.key for v in plan(recipe)}
    for v in scan.views:
        img = scan.read_image(v)  # decodes: no torn image
        assert img.shape == (48, 64, 3)
        st = scan.path_of(v).stat()
        assert seen.get(v.file, (st.st_ino, st.st_mtime_ns)) == (st.st_ino, st.st_mtime_ns)
    assert not [p for p in (out / "images").rglob(".*") if p.is_file()]
