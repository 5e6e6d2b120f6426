"""Next-best-view planning on a visual hull: which stops would carve its phantom volume.

A visual hull keeps every point that projects inside every silhouette.  Where
the views never look through a gap (the cup between young leaves, the space
between two stacked plates, the wedges above and below a flat leaf seen only
from above) the hull keeps *phantom* volume that no silhouette can remove.
The planner finds it and chooses the stops whose views would carve it:

1. **Certain and unsure voxels.**  Along the ray of one silhouette pixel the
   object is somewhere inside the hull; where the ray's whole path through the
   hull is short (at most ``certain_run_mm``), the object fills it, so the
   voxels on that path are *certain*.  A voxel is certain when some base view
   sees it on a short path (a leaf seen face-on, a stem from the side), and
   *unsure* otherwise: it lies on long paths in every view, thick parts no view
   saw through.  A surface test (voxels near a silhouette boundary) does not do:
   every point of a hull's surface lies on some view's cone, phantom surfaces
   included, and a shell of surface voxels projects exactly like the solid.
   The pot (``plantscan_hull.pot.fit_pot``) is certain and never a target.
2. **Predicted silhouettes.**  In a candidate view the true silhouette is
   predicted as the projection of the certain voxels, grown by ``margin_px``
   and with its enclosed holes filled (a ring of certain leaf rims around an
   unsure middle predicts a solid, not a window: certain voxels miss the
   middles of leaves seen only face-on, and a filled ring is the safe guess).
   An unsure voxel that projects outside it, inside the image, is predicted
   carved by that view.  Only the certain voxels' shell (``shell``: those with
   a 6-neighbour that is not certain) is projected: the same silhouettes, pixel
   for pixel (tested), at a fifth of the points on a potted dicot.
3. **Lazy greedy.**  The hull removes a voxel outside in more than ``k`` views,
   so an unsure voxel already outside in ``c`` base views needs ``k + 1 - c``
   more.  The objective credits each unsure voxel ``min(need, n) / need`` of
   its volume after ``n`` chosen views see it outside: a sum of concave
   functions of counts, monotone and submodular, so the greedy choice (one
   stop at a time, largest marginal gain) is within 1 - 1/e of the best set
   and lazy evaluation is exact (a stop's gain only shrinks as others are
   chosen: re-evaluate the top of the heap only).  A stop that would break the
   capture-time budget (``PlanRequest.seconds_of``) is passed over.

Every candidate stop's prediction is computed once (both cameras), in
parallel; the greedy loop is then arithmetic on index arrays.
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from plantscan_core.data import Calibration, Camera, Silhouettes, Volume
from plantscan_core.parallel import thread_map
from plantscan_core.trajectory import PlannedStop, PlanRequest, Stop, ViewPlan


@dataclass
class PlanningGrid:
    """The hull pooled to the planning resolution.

    Attributes
    ----------
    index : (N, 3) int64 array
        Grid indices of the inside voxels.
    origin : (3,) float64 array, mm, turntable frame
        Centre of voxel (0, 0, 0).
    voxel_size : float, mm
    """

    index: np.ndarray
    origin: np.ndarray
    voxel_size: float

    @property
    def centres(self) -> np.ndarray:
        """(N, 3) float64 array, mm: centres of the inside voxels."""
        return self.origin + self.index * self.voxel_size

    @property
    def voxel_mm3(self) -> float:
        return self.voxel_size ** 3


def coarser(points_index: np.ndarray, origin: np.ndarray, voxel_mm: float, factor: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxels pooled ``factor`` x: (centres (M, 3) mm, voxels each pools (M,), inverse (N,))."""
    cells, inverse, counts = np.unique(points_index // factor, axis=0, return_inverse=True,
                                       return_counts=True)
    centres = origin + (cells * factor + 0.5 * (factor - 1)) * voxel_mm
    return centres, counts, inverse.ravel()


def pooled(volume: Volume, resolution: int) -> PlanningGrid:
    """Inside voxels of ``volume`` on a grid at most ``resolution`` voxels along its longest side.

    A planning voxel is inside when any voxel it pools is (thin leaves survive).
    """
    occ = volume.field > 0
    f = max(1, math.ceil(max(occ.shape) / resolution))
    if f > 1:
        pad = [(0, (-n) % f) for n in occ.shape]
        occ = np.pad(occ, pad)
        nx, ny, nz = (n // f for n in occ.shape)
        occ = occ.reshape(nx, f, ny, f, nz, f).any(axis=(1, 3, 5))
    s = float(volume.voxel_size) * f
    # the pooled voxel's centre: the middle of the f^3 block it pools
    origin = np.asarray(volume.origin, float) + 0.5 * (f - 1) * float(volume.voxel_size)
    return PlanningGrid(np.argwhere(occ), origin, s)


def shell(index: np.ndarray, solid: np.ndarray) -> np.ndarray:
    """(N,) bool: the ``solid`` voxels (of grid indices ``index`` (N, 3)) with a 6-neighbour
    that is not solid: what a projection of the solid needs (step 2).

    The pot's cylinder is most of the certain voxels (~90 % on a dicot at 128 voxels) and
    only its skin shows in a view; the hole filling of ``predicted_silhouette`` covers
    the inside of the projected skin.
    """
    from scipy.ndimage import binary_erosion

    out = np.zeros(len(index), bool)
    if not solid.any():
        return out
    lo = index[solid].min(axis=0)
    at = index[solid] - lo
    grid = np.zeros(at.max(axis=0) + 1, bool)
    grid[tuple(at.T)] = True
    inner = binary_erosion(grid, border_value=0)  # 6-connected: the cross structure
    out[np.flatnonzero(solid)] = ~inner[tuple(at.T)]
    return out


def in_pot(centres: np.ndarray, cylinders, margin_mm: float) -> np.ndarray:
    """(N,) bool: inside one of the fitted pot / carrier cylinders grown by ``margin_mm``."""
    out = np.zeros(len(centres), bool)
    for c in cylinders:
        rho = np.hypot(centres[:, 0] - c.centre_xy_mm[0], centres[:, 1] - c.centre_xy_mm[1])
        out |= c.inside_distance(rho, centres[:, 2], margin_mm) > 0
    return out


class _Projector:
    """World points -> pixels and depth for one camera, in few array passes (the hot loop:
    every candidate view projects every unsure voxel)."""

    def __init__(self, camera: Camera) -> None:
        m = camera.model
        self.camera = camera
        self.r = np.asarray(camera.pose.R, float)
        self.t = np.asarray(camera.pose.t, float)
        self.f, self.fy, self.cu, self.cv = m.f, m.fy, m.cu, m.cv
        self.d1, self.d2 = m.d1, m.d2
        self.width, self.height = m.width, m.height

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, depth): pixel coordinates and depth (mm, NaN pixels behind the camera)."""
        pc = points @ self.r.T
        pc += self.t
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(z > 0, 1.0 / z, np.nan)
        x, y = pc[:, 0] * inv, pc[:, 1] * inv
        r2 = x * x + y * y
        fac = 1.0 + r2 * (self.d1 + self.d2 * r2)
        return self.f * x * fac + self.cu, self.fy * y * fac + self.cv, z


@dataclass
class _Raster:
    """A camera's image at planning resolution: one planning pixel is ``scale`` image pixels."""

    proj: _Projector
    scale: float
    width: int
    height: int

    @classmethod
    def of(cls, camera: Camera, voxel_mm: float, reference: np.ndarray,
           voxels_per_px: float = 1.0) -> _Raster:
        """A raster whose pixel spans ``voxels_per_px`` voxels at the median depth of
        ``reference`` points."""
        proj = _Projector(camera)
        sample = reference[:: max(1, len(reference) // 4096)]
        depth = float(np.nanmedian(proj.project(sample)[2])) if len(sample) else 1000.0
        px_per_voxel = voxel_mm * camera.model.f / max(depth, 1e-6)
        scale = max(1.0, px_per_voxel * voxels_per_px)
        m = camera.model
        return cls(proj, scale, int(math.ceil(m.width / scale)), int(math.ceil(m.height / scale)))

    def pixels(self, points: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(column, row, on_image, depth) of ``points`` at planning resolution."""
        u, v, z = self.proj.project(points)
        ok = (u >= 0) & (u < self.proj.width) & (v >= 0) & (v < self.proj.height)  # NaN: False
        col = np.clip(np.where(ok, u, 0) / self.scale, 0, self.width - 1).astype(np.int64)
        row = np.clip(np.where(ok, v, 0) / self.scale, 0, self.height - 1).astype(np.int64)
        return col, row, ok, z


# The planning pixel of the ray test spans this many voxels (a tube 2 voxels wide: never
# empty between voxel centres along an oblique ray).
RAY_PIXEL_VOXELS = 2.0


def short_rays(camera: Camera, centres: np.ndarray, voxel_mm: float,
               max_length_mm: float) -> np.ndarray:
    """(N,) bool: voxels on a pixel ray whose whole path through the hull spans at most
    ``max_length_mm``.

    The pixel is inside the silhouette (the voxel is in the hull), so the object
    lies somewhere on that path: when the path is short, the voxel is (nearly)
    object.  The span is from the nearest to the farthest hull voxel in the
    pixel's tube (``RAY_PIXEL_VOXELS`` voxels wide), gaps included: a ray that
    grazes the hull (along a cone patch, where the tube is only partly inside)
    spans the whole patch, and two thin leaves far apart on one ray are not
    certain from that ray.
    """
    raster = _Raster.of(camera, voxel_mm, centres, RAY_PIXEL_VOXELS)
    col, row, ok, depth = raster.pixels(centres)
    idx = np.flatnonzero(ok)
    out = np.zeros(len(centres), bool)
    if not len(idx):
        return out
    key = row[idx] * raster.width + col[idx]
    d = depth[idx]
    near = np.full(raster.width * raster.height, np.inf)
    far = np.full(raster.width * raster.height, -np.inf)
    np.minimum.at(near, key, d)
    np.maximum.at(far, key, d)
    out[idx] = (far - near)[key] + voxel_mm <= max_length_mm
    return out


def outside_mask(camera: Camera, sil, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(outside, seen): ``points`` projecting off ``sil``'s mask, and onto the image at all."""
    uf, vf, _ = _Projector(camera).project(points)
    h, w = sil.shape
    seen = (uf >= -0.5) & (uf < w - 0.5) & (vf >= -0.5) & (vf < h - 0.5)  # NaN: False
    u = np.where(seen, np.floor(uf + 0.5), 0).astype(np.int64)
    v = np.where(seen, np.floor(vf + 0.5), 0).astype(np.int64)
    ch, cw = sil.crop.shape if sil.crop.ndim == 2 else (0, 0)
    cu, cv_ = u - sil.u0, v - sil.v0
    in_box = seen & (cu >= 0) & (cu < cw) & (cv_ >= 0) & (cv_ < ch)
    inside = np.zeros(len(points), bool)
    inside[in_box] = sil.crop[cv_[in_box], cu[in_box]]
    return seen & ~inside, seen


def predicted_silhouette(raster: _Raster, solid: np.ndarray, margin_px: int) -> np.ndarray:
    """(h, w) uint8 planning image: 1 where the projection of ``solid`` points, grown by
    ``margin_px`` planning pixels and with enclosed holes filled, covers."""
    col, row, ok, _ = raster.pixels(solid)
    img = np.zeros((raster.height + 2, raster.width + 2), np.uint8)
    img[row[ok] + 1, col[ok] + 1] = 1
    if margin_px > 0:
        img = cv2.dilate(img, np.ones((3, 3), np.uint8), iterations=margin_px)
    # holes: background the border's background does not reach
    reach = img.copy()
    mask = np.zeros((img.shape[0] + 2, img.shape[1] + 2), np.uint8)
    cv2.floodFill(reach, mask, (0, 0), 2)
    filled = (reach != 2).astype(np.uint8)
    return filled[1:-1, 1:-1]


@dataclass
class Prediction:
    """What one candidate stop is predicted to carve: target indices and counts."""

    stop: Stop
    voxels: np.ndarray   # (M,) int64 indices into the targets
    counts: np.ndarray   # (M,) int32: cameras of the stop that see it outside (1 or 2...)
    cameras: list[str]


@dataclass
class Targets:
    """The unsure voxels the planner tries to carve (pooled when there are many).

    Attributes
    ----------
    centres : (M, 3) float64 array, mm
    weight_mm3 : (M,) float64 array, mm³ — unsure volume each stands for
    need : (M,) float64 array — more views that must see it outside before the hull drops it
    """

    centres: np.ndarray
    weight_mm3: np.ndarray
    need: np.ndarray


class Planner:
    """One planning round (see the module docstring)."""

    def __init__(self, certain_run_mm: float, margin_px: int, resolution: int,
                 max_targets: int) -> None:
        self.certain_run_mm = certain_run_mm
        self.margin_px = margin_px
        self.resolution = resolution
        self.max_targets = max_targets
        self.evaluations = 0

    def analyse(self, volume: Volume, silhouettes: Silhouettes, calibration: Calibration,
                k: int, pot_cylinders) -> tuple[PlanningGrid, np.ndarray, Targets, dict]:
        """(grid, certain (N,) bool, targets, figures): step 1 of the module docstring."""
        grid = pooled(volume, self.resolution)
        x, s = grid.centres, grid.voxel_size
        pot = in_pot(x, pot_cylinders, s)
        cams = [calibration.camera_for_view(sil.view) for sil in silhouettes]
        certain = pot.copy()
        for cam in cams:
            certain |= short_rays(cam, x, s, self.certain_run_mm)
        unsure = np.flatnonzero(~certain)
        factor = 1
        while len(unsure) and factor < 8 and \
                len(np.unique(grid.index[unsure] // factor, axis=0)) > self.max_targets:
            factor *= 2
        centres, counts, _ = coarser(grid.index[unsure], grid.origin, s, factor)
        outside = np.zeros(len(centres), np.int32)
        for cam, sil in zip(cams, silhouettes, strict=True):
            outside += outside_mask(cam, sil, centres)[0]
        need = np.maximum(1, k + 1 - outside).astype(np.float64)
        targets = Targets(centres, counts * grid.voxel_mm3, need)
        figures = {"planning_voxel_mm": s, "hull_voxels": int(len(x)), "k": k,
                   "certain_voxels": int(certain.sum()), "pot_voxels": int(pot.sum()),
                   "unsure_voxels": int(len(unsure)), "targets": int(len(centres)),
                   "target_pooling": factor}
        return grid, certain, targets, figures

    def predictions(self, solid: np.ndarray, targets: Targets, voxel_mm: float,
                    calibration: Calibration, request: PlanRequest) -> list[Prediction]:
        """What each candidate stop is predicted to carve (step 2), on both cores."""
        def predict(stop: Stop) -> Prediction:
            hits: list[np.ndarray] = []
            names = []
            for name in request.cameras:
                cam = calibration.camera_at_stop(name, stop.tilt_deg, stop.pan_deg)
                raster = _Raster.of(cam, voxel_mm, targets.centres)
                sil = predicted_silhouette(raster, solid, self.margin_px)
                col, row, ok, _ = raster.pixels(targets.centres)
                out = ok & (sil[row, col] == 0)
                if out.any():
                    hits.append(np.flatnonzero(out))
                    names.append(name)
            if not hits:
                return Prediction(stop, np.zeros(0, np.int64), np.zeros(0, np.int32), [])
            voxels, counts = np.unique(np.concatenate(hits), return_counts=True)
            return Prediction(stop, voxels, counts.astype(np.int32), names)

        return thread_map(predict, request.candidates)

    def plan(self, volume: Volume, silhouettes: Silhouettes, calibration: Calibration,
             request: PlanRequest, k: int, pot_cylinders) -> ViewPlan:
        t0, c0 = time.perf_counter(), time.process_time()
        grid, certain, targets, figures = self.analyse(volume, silhouettes, calibration, k,
                                                       pot_cylinders)
        figures["analysis_s"] = round(time.perf_counter() - t0, 3)
        plan = ViewPlan(hull_volume_mm3=len(certain) * grid.voxel_mm3,
                        unsure_volume_mm3=float(targets.weight_mm3.sum()), figures=figures)
        if len(targets.centres) and request.candidates and request.max_stops > 0:
            t1 = time.perf_counter()
            skin = shell(grid.index, certain)
            figures["projected_voxels"] = int(skin.sum())
            predictions = self.predictions(grid.centres[skin], targets, grid.voxel_size,
                                           calibration, request)
            figures["predict_s"] = round(time.perf_counter() - t1, 3)
            figures["candidates"] = len(predictions)
            chosen, gains, seen = self.choose(predictions, targets, request)
            plan.predicted_carve_mm3 = float(targets.weight_mm3[seen >= targets.need].sum())
            for p, g in zip(chosen, gains, strict=True):
                plan.stops.append(PlannedStop(p.stop.pan_deg, p.stop.tilt_deg, g,
                                              _reason(p, targets.centres, g)))
            plan.capture_s = request.seconds_of([p.stop for p in chosen]) if chosen else 0.0
            figures["greedy_evaluations"] = self.evaluations
        plan.seconds = time.perf_counter() - t0
        figures["cpu_s"] = round(time.process_time() - c0, 3)
        return plan

    def choose(self, predictions: list[Prediction], targets: Targets, request: PlanRequest
                ) -> tuple[list[Prediction], list[float], np.ndarray]:
        """Lazy greedy over the predictions (step 3); (chosen, their gains mm³, views seen)."""
        need, weight = targets.need, targets.weight_mm3
        seen = np.zeros(len(need), np.float64)

        def gain(p: Prediction) -> float:
            cur, nd = seen[p.voxels], need[p.voxels]
            return float(np.sum((np.minimum(nd, cur + p.counts) - np.minimum(nd, cur)) / nd
                                * weight[p.voxels]))

        heap = [(-gain(p), i) for i, p in enumerate(predictions) if len(p.voxels)]
        self.evaluations = len(predictions)
        heapq.heapify(heap)
        chosen: list[Prediction] = []
        gains: list[float] = []
        while heap and len(chosen) < request.max_stops:
            _, i = heapq.heappop(heap)
            p = predictions[i]
            g = gain(p)
            self.evaluations += 1
            if heap and g < -heap[0][0] - 1e-9:
                heapq.heappush(heap, (-g, i))  # stale bound: someone else may be better now
                continue
            if g <= 0.0:
                break
            if request.max_seconds is not None and \
                    request.seconds_of([c.stop for c in chosen] + [p.stop]) > request.max_seconds:
                continue  # this stop does not fit the time left; others may
            chosen.append(p)
            gains.append(g)
            seen[p.voxels] += p.counts
        return chosen, gains, seen


def _reason(p: Prediction, targets: np.ndarray, gain_mm3: float) -> str:
    pts = targets[p.voxels]
    c = pts.mean(axis=0)
    return (f"carves ~{gain_mm3:.0f} mm3 of unsure hull volume around "
            f"({c[0]:.0f}, {c[1]:.0f}, {c[2]:.0f}) mm (z {pts[:, 2].min():.0f}-"
            f"{pts[:, 2].max():.0f} mm) that {', '.join(p.cameras)} would see outside the "
            "predicted silhouette")
