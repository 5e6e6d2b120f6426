"""Metric scale and height of a structure-from-motion turntable frame.

Photos alone fix the rig up to its size and the height of the world origin.
Both come from what the recipe knows:

* ``plate``: the turntable plate's diameter.  Its top is the horizontal plane
  holding the most points (a printed plate is covered in them); its radius is
  where the points of its rim (just below the top) concentrate, or else the
  outer edge of the top's points.  The world origin goes to the plate's top.
* ``markers``: the side of the printed ArUco markers (``marker_mm``), from the
  length of their vertical edges (a straight line even on a curved rim); the
  height as for ``plate`` when a plate top is found.
* ``camera-distance``: the distance of the reference camera's centre from the
  axis (a gantry's travel, a tape measure); the height stays that of the
  reference camera (``z = 0``) unless a plate top is found.
"""

from __future__ import annotations

import numpy as np

from plantscan_sfm.features import SfmError


def plate_plane(points: np.ndarray, extent: float) -> tuple[float, dict]:
    """Height of the plate's top (the most populated horizontal slab) and its points."""
    z = points[:, 2]
    bin_w = extent / 300.0
    lo, hi = np.percentile(z, 0.5), np.percentile(z, 99.5)
    edges = np.arange(lo - bin_w, hi + 2 * bin_w, bin_w)
    hist, edges = np.histogram(z, edges)
    k = int(np.argmax(hist))
    near = np.abs(z - 0.5 * (edges[k] + edges[k + 1])) < 2 * bin_w
    z0 = float(np.median(z[near]))
    near = np.abs(z - z0) < 1.5 * bin_w
    return z0, {"plate_points": int(near.sum()), "slab_units": float(bin_w)}


def plate_radius(points: np.ndarray, z0: float, extent: float) -> tuple[float, dict]:
    """Radius of the plate (units of ``points``) from its rim, else from its top's edge."""
    r = np.hypot(points[:, 0], points[:, 1])
    tol = extent / 200.0
    top = np.abs(points[:, 2] - z0) < tol
    if top.sum() < 30:
        raise SfmError(f"only {int(top.sum())} points lie on the plate's top plane; the plate "
                       "cannot give the scale (print a pattern on it, or give "
                       "calibrate.params.camera_distance_mm)")
    r_top = float(np.percentile(r[top], 99.5))
    # Rim: points below the top, within 10 % of the top's outer radius.
    rim = (points[:, 2] < z0 - 2 * tol) & (points[:, 2] > z0 - 0.3 * r_top) \
        & (np.abs(r - r_top) < 0.1 * r_top)
    info = {"top_points": int(top.sum()), "top_outer_radius_units": r_top,
            "rim_points": int(rim.sum())}
    if rim.sum() >= 30:
        rr = r[rim]
        med = float(np.median(rr))
        mad = float(np.median(np.abs(rr - med)))
        if mad < 0.01 * med:
            info.update({"source": "rim", "rim_radius_units": med, "rim_mad_units": mad})
            return med, info
    info["source"] = "top edge"
    return r_top, info


def metric_frame(points: np.ndarray, ref_distance: float, how: str,
                 plate_diameter_mm: float | None, camera_distance_mm: float | None,
                 marker_edges: np.ndarray | None = None, marker_mm: float | None = None,
                 ) -> tuple[float, float, dict]:
    """Scale factor (mm per unit) and the height (units) that becomes ``z = 0``.

    ``points`` (N, 3) are well-triangulated points in the solved frame,
    ``ref_distance`` the reference camera's distance from the axis in it;
    ``marker_edges`` the lengths of printed markers' sides in it (``scale: markers``).
    """
    good = np.isfinite(points).all(axis=1)
    pts = points[good]
    if len(pts) < 30:
        # the real PhenoArch photos (12, 30 degrees apart, nothing printed): 0-6 points,
        # 11 % of the verified matches of one point (docs/benchmarks/sfm_phenoarch.md)
        raise SfmError(
            f"only {len(pts)} points were reconstructed consistently with one turntable model; "
            "too few for the scale: the photos share too few true feature matches -- take "
            "them at smaller turntable steps (at most 10 degrees apart) and print the plate "
            "and markers (docs/sfm.md, 'What to print')")
    extent = float(np.percentile(np.hypot(pts[:, 0], pts[:, 1]), 99))
    info: dict = {"method": how}
    if how == "plate":
        if plate_diameter_mm is None:
            raise SfmError("calibrate.params.plate_diameter_mm is needed for scale: plate")
        z0, pinfo = plate_plane(pts, extent)
        radius, rinfo = plate_radius(pts, z0, extent)
        info.update(pinfo | rinfo)
        s = 0.5 * plate_diameter_mm / radius
        info["mm_per_unit"] = s
        return s, z0, info
    if how == "markers":
        if marker_mm is None:
            raise SfmError("calibrate.params.marker_mm is needed for scale: markers")
        edges = np.asarray(marker_edges if marker_edges is not None else [], float)
        if len(edges) < MIN_MARKER_EDGES:
            raise SfmError(f"only {len(edges)} marker sides were reconstructed (need "
                           f"{MIN_MARKER_EDGES}); the markers cannot give the scale: print "
                           "the marker rows (docs/sfm.md) or use scale: plate")
        med = float(np.median(edges))
        s = marker_mm / med
        info.update({"marker_sides": int(len(edges)), "mm_per_unit": s,
                     "marker_side_spread": float(np.median(np.abs(edges - med)) / med)})
        try:
            z0, pinfo = plate_plane(pts, extent)
            info.update(pinfo)
        except (ValueError, IndexError):
            z0 = 0.0
        return s, z0, info
    if how == "camera-distance":
        if camera_distance_mm is None:
            raise SfmError("calibrate.params.camera_distance_mm is needed for "
                           "scale: camera-distance")
        s = camera_distance_mm / ref_distance
        info["mm_per_unit"] = s
        return s, 0.0, info
    raise ValueError(f"unknown scale source {how!r}; valid: plate, markers, camera-distance")


# Fewer reconstructed marker sides than this give no dependable scale.
MIN_MARKER_EDGES = 8
