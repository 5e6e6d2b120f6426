"""The tip the hull lost, learned: a regression from a leaf's width profile to its lost length.

``leaf-geometry``'s rule (``measure._lost_tip``) continues the straight taper fitted to
the last stations to zero width.  The station extents near a hull's tip are noisy (the
rounded end, a rim zig-zag, a twist), and a blade's taper is not straight: on the grass
family's development plants the rule's estimate and the truth's lost length correlate at
0.4.  The tip model (``measure``'s ``tip_model``; ``scripts/train_tip_model.py`` trains
one on development plants whose blades' bases the measurement placed within a few mm
of the truth's, the lost length being the truth's length less the seen one) reads the
same profile and predicts the lost length as a share of the seen length.  Every
feature is a ratio (scale-free): the same leaf in centimetres gets the same estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# stations of the tip's end read one by one (the profile's last TAIL stations / width)
TAIL = 6
FEATURE_NAMES = (
    "rule_share",       # the rule's lost length / the seen length
    "zero_share",       # where the fitted taper reaches zero width, beyond the end / seen
    "lost_vs_width",    # the lost width (tip_taper_units) / the leaf's width
    "length_vs_width",  # seen length / width
    "taper_slope",      # the fitted taper's fall of width per length, x seen / width
    "taper_residual",   # the fit's rms residual / width
    "taper_share",      # share of the stations in the taper (from 0.9 of the width)
    "stations",         # stations along the midrib
    "tip_fifth",        # mean extent of the last fifth of the stations / width
    "base_fifth",       # ... of the first fifth
    "widest_at",        # where the widest station is, 0 base - 1 tip
    "end_vs_lost",      # the last station's extent / the lost width
    "end2_vs_lost",     # the one before
    *(f"tail_{k}" for k in range(TAIL)),  # the last TAIL stations' extents / width
)
# the learned share is clipped here: a lost tip is never negative, and never more than
# half the seen blade (the rule's own bound is 0.3)
MAX_SHARE = 0.5
MODEL_SCRIPT = "scripts/train_tip_model.py"


def tip_features(extent: np.ndarray, seen_mm: float, lost_width_mm: float,
                 rule_mm: float) -> np.ndarray | None:
    """``FEATURE_NAMES`` of one leaf: its station extents (mm, base to tip), seen length,
    lost width and the rule's estimate (mm).  None for a leaf with no width."""
    from plantscan_leaves.measure import TAPER_FIT_STATIONS, taper_stations

    e = np.asarray(extent, float)
    if not np.any(e > 0) or seen_mm <= 0 or lost_width_mm <= 0:
        return None
    n = len(e)
    w, last, taper = taper_stations(e, lost_width_mm)
    slope = zero = resid = 0.0
    if len(taper) >= TAPER_FIT_STATIONS:
        x = (taper + 0.5) / n * seen_mm
        a, b = np.polyfit(x, e[taper], 1)
        slope = -a * seen_mm / w
        resid = float(np.sqrt(np.mean((e[taper] - (a * x + b)) ** 2)) / w)
        if a < 0:
            zero = float(np.clip(-b / a - seen_mm, 0.0, MAX_SHARE * seen_mm)) / seen_mm
    tail = np.zeros(TAIL)
    k = min(TAIL, n)
    tail[TAIL - k:] = e[n - k:] / w
    fifth = max(1, n // 5)
    return np.array([rule_mm / seen_mm, zero, lost_width_mm / w, seen_mm / w, slope, resid,
                     (n - last) / n, n, e[-fifth:].mean() / w, e[:fifth].mean() / w,
                     float(np.argmax(e)) / n, e[-1] / lost_width_mm,
                     (e[-2] if n > 1 else 0.0) / lost_width_mm, *tail])


@dataclass(frozen=True)
class TipModel:
    """A shipped tip model: the booster and what it was trained on."""

    booster: object
    config: dict

    def lost_mm(self, features: np.ndarray, seen_mm: float) -> float:
        """The lost tip's length (mm) of one leaf with ``features`` and ``seen_mm``."""
        share = float(self.booster.predict(features.reshape(1, -1), num_threads=1)[0])
        return float(np.clip(share, 0.0, MAX_SHARE)) * seen_mm


@lru_cache(maxsize=4)
def load_model(path: str) -> TipModel:
    """The tip model a recipe names (a file shipped in ``plantscan_leaves/models``, or a
    path), loaded once per process."""
    from plantscan_leaves.pieces import read_model

    booster, body = read_model(path, path, FEATURE_NAMES, "tip model", "plantscan_leaves.tips",
                               MODEL_SCRIPT)
    return TipModel(booster, body.get("config", {}))
