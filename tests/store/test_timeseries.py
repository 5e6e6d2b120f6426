"""Leaves matched between scans of a growing plant, and plant-level growth series."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from plantscan_store.timeseries import match_leaves, plant_rotation, plant_series


def _growing_plant(days: int = 5, seed: int = 0) -> tuple[pd.DataFrame, list[float]]:
    """A spiral plant (137.5 deg phyllotaxis, one new leaf a day at the top), put back on the
    turntable at a random angle every day; leaves listed in random order, as a measurer
    numbers them.  Column ``truth`` is the leaf's real identity (rank of appearance)."""
    rng = np.random.default_rng(seed)
    rows, rotations = [], []
    for day in range(days):
        rotation = 0.0 if day == 0 else float(rng.uniform(-180, 180))
        rotations.append(rotation)
        n = 6 + day
        for leaf in rng.permutation(n):
            age = day - (leaf - 6) if leaf >= 6 else day + 6 - leaf
            az = np.radians(137.5 * leaf + rotation + rng.normal(0, 3))
            r = 30 + 12 * age
            z = 20 + 8 * leaf + 2 * age + rng.normal(0, 2)
            rows.append({"study_id": "S", "plant_id": "P1",
                         "scan_time": pd.Timestamp("2026-05-04") + pd.Timedelta(days=day),
                         "leaf_id": len(rows), "area_mm2": 50.0 * age + 20,
                         "centroid_x_mm": r * np.cos(az), "centroid_y_mm": r * np.sin(az),
                         "centroid_z_mm": z, "truth": leaf + 1})
    return pd.DataFrame(rows), rotations


@pytest.mark.parametrize("seed", range(5))
def test_leaves_keep_their_track_while_the_plant_grows_and_turns(seed):
    df, rotations = _growing_plant(seed=seed)
    tracked = match_leaves(df)
    # every leaf's track is its rank of appearance: lowest of day 0 first, then each new leaf
    assert (tracked["track"] == tracked["truth"]).all()
    found = tracked.groupby("scan_time")["rotation_deg"].first().to_numpy()[1:]
    # each day's rotation since day 0.  A day's estimate lines the leaves up with where the
    # tracks were last seen, which carries the earlier days' errors (3-deg noise on each of
    # 6-10 leaves, a 1-deg grid): a random walk of 1-2 deg a day over 4 days.
    assert np.abs((found - np.array(rotations[1:]) + 180) % 360 - 180).max() < 8.0


def test_a_missing_leaf_does_not_shift_the_others():
    df, _ = _growing_plant(seed=1)
    gone = df[~((df.scan_time == df.scan_time.max()) & (df.truth == 3))]  # hidden on day 4
    tracked = match_leaves(gone)
    assert (tracked["track"] == tracked["truth"]).all()


def test_rotation_of_an_empty_scan_is_zero():
    empty = np.array([])
    assert plant_rotation(empty, empty, np.array([10.0]), np.array([1.0])) == 0.0


def test_plant_series_relative_growth_rate():
    t = pd.Timestamp("2026-05-04")
    plants = pd.DataFrame({"study_id": "S", "plant_id": ["A"] * 3 + ["B"] * 2,
                           "scan_time": [t, t + pd.Timedelta(days=1), t + pd.Timedelta(days=3),
                                         t, t + pd.Timedelta(days=2)],
                           "total_leaf_area_mm2": [100.0, 200.0, 800.0, 50.0, 50.0]})
    s = plant_series(plants)
    a = s[s.plant_id == "A"]
    assert list(a.day) == [0.0, 1.0, 3.0]
    assert a.relative_growth_rate.iloc[1] == pytest.approx(np.log(2))
    assert a.relative_growth_rate.iloc[2] == pytest.approx(np.log(4) / 2)
    assert s[s.plant_id == "B"].relative_growth_rate.iloc[1] == 0.0
