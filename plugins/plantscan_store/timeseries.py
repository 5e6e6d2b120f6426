"""Scans of one plant over days: plant traits over time, and leaves matched between scans.

Plant-level series need nothing but the plant id and the scan time
(``plant_series``).  Leaves carry no id that survives between scans (the
measurer numbers them anew each time), so ``match_leaves`` links them:

1. Each leaf is placed by its centroid in cylinder coordinates about the
   turntable axis: azimuth (deg), height and distance from the axis (mm).
   The plant stands on the axis and its leaves keep their azimuth as they
   grow; their centroids move out and up, slowly, between daily scans.  The
   leaflets of one compound leaf share an azimuth and rise together: only
   their distance from the axis tells them apart.
2. A pot is rarely put back at the same angle: the whole plant's rotation
   since the first scan is found first, the angle (1 deg steps) whose best
   assignment (step 3, on azimuth and height only: every leaf moves out as it
   grows, which would favour turning each leaf onto its older neighbour)
   costs least.
3. Leaves of the new scan are assigned to the tracks of the earlier scans
   (each track's last position) by the Hungarian method on the cost
   ``|Δazimuth| / AZIMUTH_SCALE_DEG + |Δheight| / HEIGHT_SCALE_MM
   + |Δradius| / RADIUS_SCALE_MM``; a pair costing more than ``MAX_COST`` is
   no match.
4. A leaf left over starts a new track.  Tracks are numbered by *rank of
   appearance*: the leaves of the first scan from the lowest up (older
   leaves sit lower), then each new leaf in the order it appeared.

``benchmarks/experiment.py`` evaluates it on the virtual scanner's growing
plants (truth leaf ids are kept across ages) and docs/experiments.md has the
figures.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

# Daily moves of the virtual families' truth leaf centroids (dicot, branched, rosette,
# grass, seedling; 99th percentiles): azimuth 2.5-10 deg, height 3-24 mm, radius 2-18 mm.
AZIMUTH_SCALE_DEG = 15.0  # a leaf's azimuth moves a few degrees a day as it grows and bends
HEIGHT_SCALE_MM = 15.0  # its centroid rises with the internode below it
RADIUS_SCALE_MM = 15.0  # and moves out as the blade (or the rachis under it) lengthens
MAX_COST = 3.0  # 45 deg of azimuth, or 45 mm of height or radius, or a mix: another leaf
PLANT_KEYS = ("study_id", "plant_id")


def _cylinder(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(azimuth deg, height mm, radius mm) of the leaves' centroids about the turntable axis."""
    x, y = df["centroid_x_mm"].to_numpy(float), df["centroid_y_mm"].to_numpy(float)
    return np.degrees(np.arctan2(y, x)), df["centroid_z_mm"].to_numpy(float), np.hypot(x, y)


def _wrap(deg: np.ndarray) -> np.ndarray:
    return (np.asarray(deg) + 180.0) % 360.0 - 180.0


def _cost(az: np.ndarray, z: np.ndarray, rho: np.ndarray, track_az: np.ndarray,
          track_z: np.ndarray, track_rho: np.ndarray) -> np.ndarray:
    return (np.abs(_wrap(az[:, None] - track_az[None, :])) / AZIMUTH_SCALE_DEG
            + np.abs(z[:, None] - track_z[None, :]) / HEIGHT_SCALE_MM
            + np.abs(rho[:, None] - track_rho[None, :]) / RADIUS_SCALE_MM)


def plant_rotation(az: np.ndarray, z: np.ndarray, track_az: np.ndarray,
                   track_z: np.ndarray) -> float:
    """Rotation (deg) that turns a scan's leaves back onto the tracks, azimuth and height.

    A spiral plant looks almost the same turned by its divergence angle (each
    leaf onto its neighbour's azimuth), so the azimuths alone are ambiguous;
    the heights are not.  The rotation minimises the cost of the best
    assignment (clipped at ``MAX_COST``): 5 deg steps, then 1 deg about the best.
    """
    from scipy.optimize import linear_sum_assignment

    if len(az) == 0 or len(track_az) == 0:
        return 0.0
    # not the radius: every leaf moves out as it grows, so a turn by the divergence angle
    # (each leaf onto its older neighbour, now as far out as that one was) would look cheap
    flat, flat_tracks = np.zeros(len(az)), np.zeros(len(track_az))

    def total(rotation: float) -> float:
        c = np.minimum(_cost(_wrap(az - rotation), z, flat, track_az, track_z, flat_tracks),
                       MAX_COST)
        r, k = linear_sum_assignment(c)
        return float(c[r, k].sum())

    coarse = min(np.arange(-180.0, 180.0, 5.0), key=total)
    return float(_wrap(min(np.arange(coarse - 5.0, coarse + 5.5, 1.0), key=total)))


def match_leaves(leaves: pd.DataFrame) -> pd.DataFrame:
    """``leaves`` (``Store.leaf_traits`` rows) with a ``track`` column per plant.

    ``track`` is the leaf's rank of appearance in its plant's series (1 = the
    lowest leaf of the first scan); the same track in two scans is the same
    leaf.  Leaves without a centroid get no track (``<NA>``).  Adds
    ``rotation_deg``: the plant's rotation since its first scan.
    """
    import pandas as pd
    from scipy.optimize import linear_sum_assignment

    out = leaves.copy()
    out["track"] = pd.array([pd.NA] * len(out), dtype="Int64")
    out["rotation_deg"] = np.nan
    if out.empty:
        return out
    for _, plant in out.groupby(list(PLANT_KEYS), sort=False):
        tracks_az: list[float] = []
        tracks_z: list[float] = []
        tracks_rho: list[float] = []
        for _, scan in plant.groupby("scan_time", sort=True):
            scan = scan[scan["centroid_z_mm"].notna()]
            if scan.empty:
                continue
            az, z, rho = _cylinder(scan)
            assigned = np.full(len(scan), -1)
            if tracks_az:
                prev = np.asarray(tracks_az), np.asarray(tracks_z), np.asarray(tracks_rho)
                rotation = plant_rotation(az, z, prev[0], prev[1])
                out.loc[scan.index, "rotation_deg"] = rotation
                az_back = _wrap(az - rotation)
                cost = _cost(az_back, z, rho, *prev)
                # gated: a pair beyond MAX_COST costs the same however far, so a leaf that
                # is gone and one that is new are not paired off to lower the total
                rows, cols = linear_sum_assignment(np.minimum(cost, MAX_COST))
                for r, c in zip(rows, cols):
                    if cost[r, c] <= MAX_COST:
                        assigned[r] = c
                        tracks_az[c], tracks_z[c] = float(az_back[r]), float(z[r])
                        tracks_rho[c] = float(rho[r])
                # later positions in the frame of the first scan
                az = az_back
            # new leaves: ranked from the lowest up
            for r in sorted(np.flatnonzero(assigned < 0), key=lambda i: (z[i], az[i])):
                tracks_az.append(float(az[r]))
                tracks_z.append(float(z[r]))
                tracks_rho.append(float(rho[r]))
                assigned[r] = len(tracks_az) - 1
            out.loc[scan.index, "track"] = assigned + 1
    return out


def plant_series(plants: pd.DataFrame, trait: str = "total_leaf_area_mm2") -> pd.DataFrame:
    """One row per plant and scan, in time order: metadata, ``scan_time``, ``trait``.

    Adds ``day`` (days since the plant's first scan) and ``relative_growth_rate``
    (per day: ln of the trait's ratio to the previous scan, over the days
    between; NaN for the first scan).
    """
    if plants.empty:
        return plants
    df = plants.sort_values([*PLANT_KEYS, "scan_time"]).copy()
    first = df.groupby(list(PLANT_KEYS))["scan_time"].transform("min")
    df["day"] = (df["scan_time"] - first).dt.total_seconds() / 86400.0
    value = df[trait].astype(float)
    prev = value.groupby([df[k] for k in PLANT_KEYS]).shift(1)
    dt_days = df.groupby(list(PLANT_KEYS))["day"].diff()
    with np.errstate(divide="ignore", invalid="ignore"):
        df["relative_growth_rate"] = np.log(value / prev) / dt_days
    return df


def leaf_series(leaves: pd.DataFrame) -> pd.DataFrame:
    """``match_leaves`` sorted by plant, track and scan time: one leaf's traits over time."""
    if leaves.empty:
        return leaves
    return match_leaves(leaves).sort_values([*PLANT_KEYS, "track", "scan_time"])
