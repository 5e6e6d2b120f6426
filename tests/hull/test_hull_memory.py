"""The pre-flight memory estimate of the hull against the measured peak of a real carve.

Each carve runs in a fresh process (peak RSS is a process's high-water mark):
the kernels are loaded by a small carve first, then the high-water mark is reset
(``/proc/self/clear_refs``: on a fresh clone the first carve compiles the kernels,
and numba's compiler peaks at about 1.7 GB, which is not the carve's memory), and
the peak resident memory added by the measured carve is compared with
``hull_peak_bytes``.  Tolerance
30 % (issue #23): the estimate decides whether a run is refused, so it must be
close, but allocator slack and page granularity vary between machines.

Since issue #28 the field is held in blocks near the surface, so the model
follows the grid's faces, not its voxels (``plantscan_hull.stages``).  Measured
here (predicted / added): 54 / 55 MB at 256^3, 210 / 205 MB at 512^3; the dense
field's model (5 bytes a voxel) would have said 86 MB and 673 MB.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from plantscan_hull.stages import hull_peak_bytes

CARVE = r"""
import json, sys
sys.path.insert(0, sys.argv[2])
from hull_phantoms import Sphere, render, ring_calibration, views
from plantscan_hull.stages import OctreeHull
from plantscan_hull.views import prepare_views

cal = ring_calibration(f=800.0, size=(640, 480), elevations=(0.0, 30.0))
sils = render(cal, views(18, (0.0, 30.0)), [Sphere((0.0, 0.0, 0.0), 30.0)])
box = [-40.0, -40.0, -40.0, 40.0, 40.0, 40.0]
table_px = sum(int(v.sd.size) for v in prepare_views(list(sils), cal))
# 64: every level of the octree runs, so every kernel is compiled (or loaded) before measuring
OctreeHull(OctreeHull.Params(resolution=64, bbox=box, floor_z_mm=None, k=1)).reconstruct(sils, cal)


def status_kb(key):
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith(key))


with open("/proc/self/clear_refs", "w") as f:  # "5": reset the peak RSS to the current RSS
    f.write("5")
before = status_kb("VmRSS:") * 1024
volume = OctreeHull(OctreeHull.Params(resolution=int(sys.argv[1]), bbox=box, floor_z_mm=None,
                                      k=1)).reconstruct(sils, cal)
peak = status_kb("VmHWM:") * 1024
print(json.dumps({"shape": list(volume.shape), "table_px": table_px, "added": peak - before}))
"""


@pytest.mark.slow
@pytest.mark.parametrize("resolution", [256, 512])
def test_hull_memory_estimate_within_30_percent_of_the_measured_peak(resolution):
    here = Path(__file__).parent
    out = subprocess.run([sys.executable, "-c", CARVE, str(resolution), str(here)],
                         capture_output=True, text=True, check=True, timeout=600)
    m = json.loads(out.stdout.strip().splitlines()[-1])
    assert m["shape"] == [resolution] * 3
    predicted = hull_peak_bytes(tuple(m["shape"]), m["table_px"], kernels_loaded=True)
    print(f"{resolution}^3: predicted {predicted / 1e6:.0f} MB, measured {m['added'] / 1e6:.0f} MB")
    assert abs(predicted - m["added"]) <= 0.3 * m["added"]
