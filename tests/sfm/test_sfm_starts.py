"""The joint solve's focal-length starts solved side by side (``threads`` at a time).

The scene is ``test_sfm_checks``'s (the virtual paper-72 rig's exact correspondences,
thinned, 0.1 px of noise), with a start at ten times the orbit's focal length added so
that the starts do not all end at one rig.
"""

from __future__ import annotations

import numpy as np
from test_sfm_checks import _scene
from test_sfm_exact import SIZE

FAR = 10.0  # the added start's focal lengths, times the orbits' own


def _solve(views, tracks, threads: int):
    from plantscan_sfm.calibrate import SfmSettings, solve_tracks

    st = SfmSettings(plate_diameter_mm=400.0, markers=None, refine_dots=False, threads=threads)
    return solve_tracks(views, tracks, {"cam0": SIZE, "cam1": SIZE}, st)


def test_starts_solved_side_by_side_give_the_calibration_of_one_at_a_time(monkeypatch):
    """Every start is solved to the end and the lowest truncated cost is kept, whatever
    the number of threads: the same costs and the same calibration to the last digit."""
    from plantscan_sfm import calibrate

    own = calibrate.focal_starts

    def starts(state, held):
        return own(state, held) + [{c: FAR * f for c, f in own(state, held)[0].items()}]

    monkeypatch.setattr(calibrate, "focal_starts", starts)
    _, views, tracks, _ = _scene()
    one = _solve(views, tracks, threads=1)
    two = _solve(views, tracks, threads=2)

    assert len(one.quality["solver"]["focal_starts"]) == 4
    assert one.quality["solver"]["focal_starts"] == two.quality["solver"]["focal_starts"]
    for c, m in one.models.items():
        assert two.models[c].f == m.f and two.models[c].cv == m.cv
    for g, p in one.poses.items():
        assert np.array_equal(two.poses[g].centre, p.centre)
        assert np.array_equal(two.poses[g].R, p.R)
