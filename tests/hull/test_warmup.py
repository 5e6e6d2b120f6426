"""``plantscan warm-up`` compiles every kernel signature a real scan and run use.

The warm-up is what keeps the first ``plantscan demo`` from waiting a minute for
numba (``make setup`` runs it).  Wall time is not asserted; what is asserted is
the thing that makes the wait go away: after the warm-up, a virtual scan, the
hull stages with their default parameters and the leaf stages' fork filtration call
no kernel with argument types the warm-up did not compile.  Run in a fresh
interpreter, so that no signature comes from an earlier test.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("numba")
pytest.importorskip("plantscan_sim.api")
pytestmark = pytest.mark.slow

SCRIPT = r"""
import json, sys
from pathlib import Path
from numba.core.registry import CPUDispatcher
from plantscan_hull import kernels
from plantscan_leaves import geometry as leaf_geometry
from plantscan_leaves import kernels as leaf_kernels
from plantscan_sim import render

def signatures():
    out = {}
    for mod in (kernels, leaf_kernels, leaf_geometry, render):
        for name in dir(mod):
            d = getattr(mod, name)
            if isinstance(d, CPUDispatcher):
                out[f"{mod.__name__}.{name}"] = {str(s) for s in d.signatures}
    return out

from plantscan_core.plugins import get_manager
warm = get_manager().warm_up()
before = signatures()
from plantscan_hull.evaluate import truth_silhouettes
from plantscan_hull.stages import MarchingCubesMesher, OctreeHull
from plantscan_sim.api import make_scan
scan = make_scan(Path(sys.argv[1]) / "scan", "plastic-dicot", image_size=(240, 160),
                 images_per_revolution=8, roles=("plant",))
sils, cal = truth_silhouettes(scan)
MarchingCubesMesher().mesh(OctreeHull().reconstruct(sils, cal))
# the leaf stages' fork filtration with what segment passes (scipy's int32 CSR arrays)
import numpy as np
leaf_kernels.fork_branches(np.arange(3)[::-1], np.arange(3.0), np.array([0, 1, 3, 4], np.int32),
                           np.array([1, 0, 2, 1], np.int32), np.zeros((3, 3)), np.ones(3),
                           1.0, 1.0)
# both leaf stages as the shipped dicot and grass recipes run them, on another mock plant
import yaml
from plantscan_leaves import phantoms
from plantscan_leaves.measure import LeafGeometryParams, measure_plant
from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves
plant = phantoms.mock_plant(n_leaves=3, petiole_mm=10.0).mesh(voxel_mm=0.8)
for family in ("dicot", "grass"):
    recipe = yaml.safe_load(open(Path(sys.argv[2]) / f"{family}.yaml"))
    labelled, _ = segment_leaves(plant, CurvatureRegionsParams(**recipe["segment_mesh"]["params"]))
    measure_plant(labelled, LeafGeometryParams(**recipe["measure"]["params"]))
after = signatures()
print(json.dumps({
    "warm": warm,
    "used": sorted(k for k, v in after.items() if v),
    "new": {k: sorted(after[k] - before.get(k, set())) for k in after
            if after[k] - before.get(k, set())},
}))
"""


def test_warm_up_compiles_what_a_scan_and_the_hull_stages_use(tmp_path):
    recipes = Path(__file__).resolve().parents[2] / "recipes"
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path), str(recipes)],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    plugins = {name for name, _ in result["warm"]}
    assert {"hull", "leaves", "sim"} <= plugins, result["warm"]
    assert not any(said.startswith("failed") for _, said in result["warm"]), result["warm"]
    # The hull's work-stealing kernel and the renderer's raster kernels ran at all ...
    assert "plantscan_hull.kernels._steal" in result["used"]
    assert "plantscan_sim.render._raster_triangles" in result["used"]
    assert "plantscan_leaves.kernels._fork_branches_jit" in result["used"]
    assert "plantscan_leaves.kernels._grow_jit" in result["used"]
    assert "plantscan_leaves.geometry._moments_kernel" in result["used"]
    # ... and none of them, nor any other, needed a signature the warm-up had not compiled.
    assert result["new"] == {}
