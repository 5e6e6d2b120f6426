"""The stages of this plugin: ``octree-hull``, ``dense-hull`` and ``marching-cubes``."""

from __future__ import annotations

import json
import logging
import math
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from plantscan_core.data import Calibration, CarvingViews, Mesh, Silhouettes, Volume
from plantscan_core.errors import DataError
from plantscan_core.preflight import WorkEstimate, WorkPlan, check
from plantscan_core.stages import Mesher, Reconstructor, StageParams
from plantscan_hull.bbox import BoundingBoxError, auto_box
from plantscan_hull.carve import Grid, carve_dense, carve_octree
from plantscan_hull.fields import faces_inside, restore
from plantscan_hull.meshing import (
    drop_small_components,
    marching_cubes,
    postprocess,
    topology_report,
)
from plantscan_hull.pot import (
    TaperedCylinder,
    bound_cap,
    fit_cap,
    fit_pot,
    remove_cylinders,
    views_cone,
)
from plantscan_hull.views import prepare_views

log = logging.getLogger(__name__)

POT_FILE = "pot_fit.json"


# k = "auto": mask errors (mixed edge pixels, shade speckle) hit each view independently, so
# the views that wrongly carve a rim point grow with the number of views, and a fixed k lets
# them notch the leaf outlines of large scans; measured on the 18 MP virtual scans
# (docs/reconstruction.md): 360 views best at k 8-10, 72 views at k 3.
K_AUTO_FRACTION = 0.025
K_AUTO_MIN = 3


def resolve_k(k: int | str, n_views: int) -> int:
    """The k a hull of ``n_views`` silhouettes carves with (``k`` an int, or "auto")."""
    if k == "auto":
        return max(K_AUTO_MIN, round(K_AUTO_FRACTION * n_views))
    return int(k)


# The hull's memory, measured (tests/hull/test_hull_memory.py checks the model at 256^3 and
# 512^3 against the peak RSS of a real carve).  Since issue #28 the field is held in blocks
# near the surface (docs/reconstruction.md), so what the carve adds follows the surface, not
# the grid: the mixed blocks, the octree's view lists of the cells near the surface and the
# fine voxels' values, modelled per voxel of the grid's three faces (nx ny + ny nz + nz nx).
# Measured (predicted / added): the test's sphere on 18 views 54 / 55 MB at 256^3, 210 / 205 MB
# at 512^3; 360 views of 3000x2000 px (benchmarks/hull.py, tables excluded): the shared
# synthetic plant 128 / 132 MB at 512^3 and 512 / 455 MB at 1024^3, the benchmark dicot
# 179 / 274 MB at 512^3 (35 % low, not understood) and 715 / 731 MB at 1024^3.  Then the
# int16 distance tables, 2 bytes per pixel of each view's plant box; and, the first time a
# process carves, ~130 MB for loading the compiled kernels.
HULL_BYTES_PER_FACE_VOXEL = 265
HULL_BYTES_PER_TABLE_PX = 2
KERNEL_LOAD_BYTES = 130_000_000
# Time: the carve at 512^3 with 360 views of 1500x1000 px takes ~17 s wall and 1024^3 ~167 s on
# this 2-core machine (docs/benchmarks/hull.md): about linear in voxels at a given view set.
HULL_SECONDS_AT_512 = 17.0


def hull_peak_bytes(grid_shape: tuple[int, int, int], table_pixels: int,
                    kernels_loaded: bool = False) -> int:
    """Estimated peak memory of a carve above what the process held before it, bytes.

    Parameters
    ----------
    grid_shape : (3,) voxels of the grid.
    table_pixels : pixels of the views' distance tables (plant box + margin, summed).
    kernels_loaded : the compiled kernels are already in the process (a second carve).
    """
    nx, ny, nz = (int(n) for n in grid_shape)
    faces = nx * ny + ny * nz + nz * nx
    return (HULL_BYTES_PER_FACE_VOXEL * faces + HULL_BYTES_PER_TABLE_PX * int(table_pixels)
            + (0 if kernels_loaded else KERNEL_LOAD_BYTES))


class HullParams(StageParams):
    """Parameters shared by the hull reconstructors."""

    resolution: int = Field(256, ge=8, le=1024,
                            description="voxels along the longest side of the bounding box")
    k: Annotated[int, Field(ge=0)] | Literal["auto"] = Field(
        "auto", description="a voxel is removed only if outside in more than k views; 'auto': "
        f"{K_AUTO_FRACTION:g} of the views, at least {K_AUTO_MIN} (docs/reconstruction.md)")
    bbox_margin_mm: float = Field(5.0, ge=0, description="margin added around the found box")
    bbox: list[float] | None = Field(
        None, description="fixed box [xmin, ymin, zmin, xmax, ymax, zmax] mm (turntable frame); "
                          "default: found from the silhouettes")
    keep_thin: bool = Field(True, description="keep parts thinner than a voxel (thin leaves)")
    thin_value: float = Field(0.15, gt=0, le=0.5,
                              description="field value of a rescued thin voxel (voxels)")
    floor_z_mm: float | None = Field(
        0.0, description="nothing is below this height (the turntable plate, turntable frame); "
        "null for rigs without one (imports)")
    min_seen_fraction: float = Field(
        0.5, ge=0, le=1, description="a voxel seen (projecting on the image) by fewer than "
        "this fraction of the views, or by at most k, is removed: nothing supports it")
    backend: Literal["auto", "numpy", "numba"] = Field(
        "auto", description="hot loops: numba when installed (auto), or the numpy reference")

    @field_validator("bbox")
    @classmethod
    def _six_numbers(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (len(v) != 6 or any(v[i] >= v[i + 3] for i in range(3))):
            raise ValueError("bbox must be [xmin, ymin, zmin, xmax, ymax, zmax] with min < max")
        return v


class _HullBase(Reconstructor):
    Params = HullParams

    def _carve(self, views, grid: Grid):  # pragma: no cover - abstract
        raise NotImplementedError

    @classmethod
    def estimate(cls, params: HullParams, plan: WorkPlan) -> WorkEstimate:
        """Memory and time before the stage starts: the grid a cube unless ``bbox`` is given
        (the found box is only smaller), the tables whole images unless the masks are known."""
        if params.bbox is not None:
            shape = Grid.from_box(params.bbox[:3], params.bbox[3:], params.resolution).shape
        else:
            shape = (params.resolution,) * 3
        pixels = plan.plant_pixels
        if pixels is None:
            pixels = plan.plant_views * plan.image_size[0] * plan.image_size[1]
        return _hull_estimate(cls.name, shape, pixels, plan.plant_views)

    def reconstruct(self, silhouettes: Silhouettes, calibration: Calibration) -> Volume:
        """Carve the k-tolerant visual hull of ``silhouettes``.

        Returns
        -------
        Volume
            ``field``: (k+1)-th smallest signed distance to the silhouette
            cones, in voxels, clamped to [-1, 1] (> 0 inside).  Work counts,
            timings, the box and the k used go to ``self.report``.
        """
        p = self.params
        if len(silhouettes) == 0:
            raise DataError("reconstruct: no plant silhouette to carve from")
        self.k = k = resolve_k(p.k, len(silhouettes))
        if len(silhouettes) <= k:
            raise DataError(
                f"reconstruct: {len(silhouettes)} silhouettes cannot carve anything with "
                f"k={k} (a voxel must be outside in more than k views); lower "
                "reconstruct.params.k")
        t0 = time.perf_counter()
        views = prepare_views(list(silhouettes), calibration)
        t_prep = time.perf_counter() - t0
        self.min_seen = max(k + 1, math.ceil(p.min_seen_fraction * len(views)))
        info: dict = {"min_views_seen": self.min_seen}
        if p.bbox is None:
            lo, hi, box_info = auto_box(views, k, p.bbox_margin_mm,
                                        coarse=min(128, p.resolution), backend=p.backend,
                                        min_seen=self.min_seen, floor_z=p.floor_z_mm)
            info.update(box_info)
        else:
            lo, hi = np.array(p.bbox[:3]), np.array(p.bbox[3:])
        t_box = time.perf_counter() - t0 - t_prep
        grid = Grid.from_box(lo, hi, p.resolution)
        # The grid is known now: refuse before the big allocation when it cannot fit.
        table_px = sum(int(v.sd.size) for v in views)
        check([_hull_estimate(self.name, grid.shape, table_px, len(views))])
        phi, stats = self._carve(views, grid)
        n_views = len(views)
        del views  # the tables (1.3 GB for 360 views at 2592x1728) are not needed any more
        faces = faces_inside(phi)
        if p.floor_z_mm is not None and grid.lo[2] <= p.floor_z_mm + 1e-6:
            faces = [f for f in faces if f != "z-"]  # resting on the plate is not clipping
        if faces:
            where = "reconstruct.params.bbox" if p.bbox is not None else "the automatic box"
            raise BoundingBoxError(
                f"the plant touches the faces {', '.join(faces)} of {where} "
                f"({grid.lo.round(1).tolist()} .. {grid.hi.round(1).tolist()} mm): the box "
                "clips the plant; enlarge it")
        self.report.note(stats.as_dict())
        self.report.note({"views": n_views, "prep_seconds": t_prep, "bbox_seconds": t_box,
                          "grid_shape": list(grid.shape), "voxel_size_mm": grid.voxel_size,
                          "bbox_mm": [grid.lo.tolist(), grid.hi.tolist()], "k": k, **info})
        return Volume(phi, grid.origin, grid.voxel_size)


def _hull_estimate(name: str, shape: tuple[int, ...], table_pixels: int,
                   n_views: int) -> WorkEstimate:
    voxels = int(np.prod(shape, dtype=np.int64))
    return WorkEstimate(
        stage=f"reconstruct ({name})",
        what=f"a {'x'.join(str(n) for n in shape)} grid and {n_views} views",
        peak_bytes=hull_peak_bytes(tuple(shape), table_pixels),  # type: ignore[arg-type]
        seconds=HULL_SECONDS_AT_512 * voxels / 512**3,
        parameter="reconstruct.params.resolution")


class OctreeHull(_HullBase):
    """Coarse-to-fine (octree) visual hull with k-outside tolerance."""

    name = "octree-hull"

    class Params(HullParams):
        top_cell: int = Field(32, ge=2, le=256,
                              description="side (voxels, power of two) of the coarsest cells")

        @field_validator("top_cell")
        @classmethod
        def _power_of_two(cls, v: int) -> int:
            if v & (v - 1):
                raise ValueError("top_cell must be a power of two")
            return v

    def _carve(self, views, grid):
        p = self.params
        return carve_octree(views, grid, self.k, p.top_cell, p.keep_thin, p.thin_value,
                            backend=p.backend, min_seen=self.min_seen, blocks=True)


class DenseHull(_HullBase):
    """Plain full-grid visual hull: the reference the octree is tested against."""

    name = "dense-hull"
    Params = HullParams

    def _carve(self, views, grid):
        p = self.params
        return carve_dense(views, grid, self.k, p.keep_thin, p.thin_value, backend=p.backend,
                           min_seen=self.min_seen)


class MarchingCubesMesher(Mesher):
    """Pot/carrier removal, then a watertight manifold surface by marching cubes."""

    name = "marching-cubes"

    class Params(StageParams):
        pot: Literal["auto", "none"] | list[TaperedCylinder] = Field(
            "auto", description="'auto' (fit from the hull), 'none', or the tapered cylinders "
                                "(pot, carrier) to remove, mm")
        pot_cap: bool = Field(
            True, description="also remove the hull's cone over the pot's opening that no "
                              "view carves (every camera sees it against the soil or the pot; "
                              "docs/reconstruction.md)")
        cap_fit: Literal["bounded", "hull"] = Field(
            "hull", description="the cap fitted from the hull's slices: 'bounded' no taller and "
                                "no wider at the rim than the cone the views cannot carve "
                                "(recorded as cap_views_bound), 'hull' as fitted; without the "
                                "views (a volume meshed on its own) as fitted")
        pot_margin_mm: float = Field(
            1.5, ge=0, description="removed beyond the pot surface, plus one voxel (the hull's "
                                   "rim is known to a voxel)")
        min_component_voxels: int = Field(
            8, ge=0, description="inside components smaller than this are dropped (mask specks)")
        thin_rims: bool | Literal["measure"] = Field(
            False, description="put the rim of one-voxel-thick parts (leaf slabs) where the "
                               "outside field says, not where linear interpolation from the "
                               "thickness-capped inside value does (docs/reconstruction.md); "
                               "'measure': segment the mesh as interpolated and measure the "
                               "leaves with their rims put out (same faces)")
        smooth_iterations: int = Field(0, ge=0, description="pymeshlab Taubin smoothing steps")
        target_faces: int | None = Field(None, ge=100,
                                         description="pymeshlab quadric decimation target")

        @model_validator(mode="after")
        def _rims_need_the_faces(self):
            if self.thin_rims == "measure" and (self.smooth_iterations or self.target_faces):
                raise ValueError(
                    "thin_rims: measure keeps the rims beside the faces as meshed; smoothing "
                    "(smooth_iterations) or decimation (target_faces) moves or replaces them: "
                    "use one or the other")
            return self

    def mesh(self, volume: Volume, views: CarvingViews | None = None) -> Mesh:
        """Remove pot and carrier from ``volume``, then extract the closed surface."""
        p = self.params
        if p.pot == "auto":
            cylinders = fit_pot(volume)
            if not cylinders:
                self.report.warn(
                    "no-pot", "pot: auto found no pot at the bottom of the hull (no run of "
                    "disc-like slices); if the plant stands in a pot, the pot is in the mesh, "
                    "in the plant's height and perhaps as a leaf: give the pot's tapered "
                    "cylinders (pot: [{z_bottom_mm, z_top_mm, r_bottom_mm, r_top_mm}]), or "
                    "pot: none if there is none")
        elif p.pot == "none":
            cylinders = []
        else:
            cylinders = list(p.pot)
        cap = bound = fitted = None
        if p.pot_cap and cylinders:
            fitted = cap = fit_cap(volume, max(cylinders, key=lambda c: c.z_top_mm))
            if views is not None:  # recorded either way, applied when asked
                bound = views_cone(views, cylinders, float(volume.voxel_size))
            if bound is not None and cap is not None and p.cap_fit == "bounded":
                cap = bound_cap(cap, bound)
        margin = p.pot_margin_mm + float(volume.voxel_size)
        # Pot and specks are removed in the volume's own field and put back afterwards (the
        # volume is the caller's): a copy of the grid is 411 MB of fresh pages at 512^3.
        own = volume.blocks if volume.blocks is not None else volume.field
        undo = [] if (volume.blocks is not None or (
            isinstance(own, np.ndarray) and own.dtype == np.float32
            and own.flags.writeable and own.flags.c_contiguous)) else None
        try:
            field, removed = remove_cylinders(volume, cylinders, margin, undo=undo)
            cap_removed = 0
            if cap is not None:
                # in place: ``field`` is the recorded own field (undo) or already a copy
                field, cap_removed = remove_cylinders(
                    Volume(field, volume.origin, volume.voxel_size), [cap], margin,
                    undo=undo if undo is not None else [],
                    keep_axis_mm=cap.r_top_mm + float(volume.voxel_size))
            field, dropped = drop_small_components(
                field, p.min_component_voxels, in_place=undo is not None or field is not own,
                undo=undo)
            mesh = marching_cubes(field, volume.origin, volume.voxel_size,
                                  thin_rims=p.thin_rims)
        finally:
            if undo:
                restore(own, undo)
        mesh = postprocess(mesh, p.smooth_iterations, p.target_faces)
        if cylinders:  # the plant's height is from the pot's rim, not its lowest drooping leaf
            mesh.base_z_mm = float(max(c.z_top_mm for c in cylinders))
        report = {"pot": [c.model_dump() for c in cylinders], "pot_mode": p.pot
                  if isinstance(p.pot, str) else "given", "pot_margin_mm": margin,
                  "pot_voxels_removed": removed,
                  "cap": None if cap is None else cap.model_dump(),
                  "cap_fitted": None if fitted is None else fitted.model_dump(),
                  "cap_views_bound": None if bound is None else bound.model_dump(),
                  "cap_fit": p.cap_fit if views is not None else "hull (no views)",
                  "cap_voxels_removed": cap_removed,
                  "components_dropped": dropped, "topology": topology_report(mesh)}
        self.report.note(report)
        run_dir = self.context.run_dir
        if run_dir is not None:
            from plantscan_core.scanfolder import atomic_write_text

            atomic_write_text(run_dir / POT_FILE, json.dumps(report, indent=2))
        if mesh.is_empty:
            raise DataError("mesh: nothing left to mesh after pot removal (is the hull only "
                            "the pot? check mesh.params.pot)")
        return mesh
