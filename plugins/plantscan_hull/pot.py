"""Pot and carrier removal: tapered cylinders subtracted from the hull's field.

Given cylinders (from the recipe) or cylinders fitted from the hull: a pot or
carrier is a solid of revolution about a vertical axis, so its hull slices
are nearly full discs, while slices through stem and leaves are sparse.  The
fit walks up from the lowest occupied slice while slices are disc-like,
splits that run where the radius jumps (pot on a carrier), fits a straight
taper ``r(z)`` to each piece, then extends the top piece upwards while its
disc stays filled (leaves hanging over the rim spoil the disc test of the
slice, not the fill of the fitted disc).  Removal is a field operation,
``field = min(field, -inside_distance)``, before meshing, so the mesh stays
watertight and the stem is cut flat at the rim.

Over the pot's opening the hull holds a cone no camera carves (the cap,
:func:`fit_cap`): a camera looking down at depression ``e`` sees a point
``h`` above the opening against the soil or the pot (both in the masks) while
``h / tan(e)`` is less than its distance to the far rim, so every view keeps
the cone of height ``r_rim tan(e_min)`` over the opening.  It is found from the
hull's own slices (full discs on the pot's axis shrinking upwards, the stem at
their centre) and removed with the pot: anything inside it, stem or leaf, is
nothing the silhouettes say (every view sees it inside the pot's image).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field
from scipy import ndimage

from plantscan_core.bounds import CheckedModel
from plantscan_core.data import CarvingViews, Volume
from plantscan_hull.fields import read_box, write_box, z_profile

# A slice is disc-like when its area fills this fraction of the disc through its
# farthest voxel (a polygonal hull of a circle from >= 8 views fills > 0.9).
DISC_FILL = 0.75
# The fitted disc (shrunk by a voxel) must be this full for the rim search to go on.
RIM_FILL = 0.9
# Radius jump (voxels) between slices that splits pot from carrier.
RADIUS_JUMP_VOXELS = 1.5
# Non-disc slices tolerated at the bottom of the hull (the cone under the pot): at least this
# many, and at least BOTTOM_SKIP_MM of height.  Views from near the horizon (adaptive scans,
# tilts below 0) carve the cone under the pot to a stub 8 mm tall whose slices fill < 0.75
# of their disc (1 mm voxels: 8 slices; 4 found no pot and left it in the mesh).
BOTTOM_SKIP_SLICES = 4
BOTTOM_SKIP_MM = 12.0
# Slices copied out of the field at a time while walking up the pot.
SLICE_CHUNK = 32
# A pot narrower than this (voxels) is not told apart from a stem.
MIN_POT_RADIUS_VOXELS = 3.0
# A disc-like run narrower than this fraction of the piece below it is the stem rising
# from the soil, not a pot on a carrier: at 1 mm voxels a 4.7 mm stem is a run of discs
# (it was cut away from the soil to the lowest leaf on an 18 MP 5-tilt scan).  Pots on
# carriers stay within ~0.5-2x of each other; stems are < 0.25 of their pot's radius.
STEM_RADIUS_FRACTION = 0.25
# The cap's edge in a slice: the first ring (a voxel wide, about the pot's axis) less than
# half occupied; the hull's outline crosses its ring about half way.
CAP_RING_FILL = 0.5
# A cap starts at the rim as a disc at least this fraction of the rim's radius wide (a
# narrower first slice is the stem and leaves, not a cone over the whole opening) ...
CAP_BASE_FRACTION = 0.5
# ... and is followed up while its disc is wider than a stem (STEM_RADIUS_FRACTION of the
# rim's radius); at least CAP_MIN_SLICES slices, shrinking, make a cone.
CAP_MIN_SLICES = 3


class TaperedCylinder(CheckedModel):
    """A vertical tapered cylinder (pot, carrier), mm, turntable frame."""

    z_bottom_mm: float
    z_top_mm: float
    r_bottom_mm: float = Field(gt=0)
    r_top_mm: float = Field(gt=0)
    centre_xy_mm: tuple[float, float] = (0.0, 0.0)

    def radius_at(self, z: np.ndarray) -> np.ndarray:
        t = (np.asarray(z, dtype=float) - self.z_bottom_mm) / max(
            self.z_top_mm - self.z_bottom_mm, 1e-9)
        return self.r_bottom_mm + t * (self.r_top_mm - self.r_bottom_mm)

    def inside_distance(self, rho: np.ndarray, z: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Approximate signed distance (mm) into the cylinder grown by ``margin``; > 0 inside.

        ``rho`` (distance to the axis, mm) and ``z`` (mm) broadcast against each
        other, so a grid's radial plane and its column of heights are enough.
        """
        z = np.asarray(z)
        radial = self.radius_at(np.clip(z, self.z_bottom_mm, self.z_top_mm)) + margin - rho
        axial = np.minimum(z - (self.z_bottom_mm - margin), (self.z_top_mm + margin) - z)
        return np.minimum(radial, axial)


@dataclass
class SliceStats:
    area: float               # voxels, holes filled
    centre: np.ndarray        # (2,) mm
    r_eq: float               # mm, radius of the disc of the same area
    fill: float               # area / disc through the farthest voxel


def filled_slice(occupied_slice: np.ndarray) -> np.ndarray:
    """A z-slice of the hull with its enclosed holes filled ((NX, NY) bool).

    Speckled silhouettes (a shaded pot read as shadow in a few views) carve
    scattered holes inside the pot; the pot's cross-section is still the
    outline.  Only the slice's occupied bounding box is labelled.
    """
    rows = np.flatnonzero(occupied_slice.any(axis=1))
    if rows.size == 0:
        return occupied_slice
    cols = np.flatnonzero(occupied_slice.any(axis=0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    out = occupied_slice.copy()
    out[box] = ndimage.binary_fill_holes(occupied_slice[box])
    return out


def slice_stats(filled: np.ndarray, origin: np.ndarray, s: float) -> SliceStats:
    """Area, centroid and disc-likeness of one (hole-filled) slice; ``origin`` (3,) mm."""
    i, j = np.nonzero(filled)
    if i.size == 0:
        return SliceStats(0.0, np.zeros(2), 0.0, 0.0)
    x = origin[0] + i * s
    y = origin[1] + j * s
    centre = np.array([x.mean(), y.mean()])
    rmax = float(np.max(np.hypot(x - centre[0], y - centre[1])))
    area = float(i.size)
    return SliceStats(area, centre, float(np.sqrt(area * s * s / np.pi)),
                      area * s * s / (np.pi * (rmax + s / 2) ** 2))


def _disc_fill(filled: np.ndarray, origin: np.ndarray, s: float,
               centre: np.ndarray, radius: float) -> float:
    nx, ny = filled.shape
    xs = origin[0] + np.arange(nx) * s
    ys = origin[1] + np.arange(ny) * s
    disc = np.hypot(xs[:, None] - centre[0], ys[None, :] - centre[1]) <= radius
    n = disc.sum()
    return float((filled & disc).sum() / n) if n else 0.0


def _pot_pieces(r_eq: np.ndarray, s: float) -> list[np.ndarray]:
    """Pieces (index arrays into a run of disc slices) of pot and carrier, bottom up.

    The run is split where the radius jumps (``RADIUS_JUMP_VOXELS``: a pot on a carrier,
    and every slice of the steep cone under the pot); pieces of 3 slices or more are kept,
    up to the rim, where a piece narrower than ``STEM_RADIUS_FRACTION`` of the one below
    is the stem rising from the soil.
    """
    jumps = np.flatnonzero(np.abs(np.diff(r_eq)) > RADIUS_JUMP_VOXELS * s) + 1
    pieces: list[np.ndarray] = []
    for p in np.split(np.arange(len(r_eq)), jumps):
        if pieces and np.median(r_eq[p]) < STEM_RADIUS_FRACTION * r_eq[pieces[-1][-1]]:
            break  # the pot's rim: the stem rises from here; above it is plant
        if len(p) >= 3:
            pieces.append(p)
    return pieces


def fit_pot(volume: Volume) -> list[TaperedCylinder]:
    """Tapered cylinders (carrier, pot) fitted from the bottom of the hull; [] if none.

    Each slice is judged with its enclosed holes filled (:func:`filled_slice`),
    and only the slices from the bottom up to the pot's rim are examined.

    Parameters
    ----------
    volume : Volume
        The hull (field > 0 inside), turntable frame.
    """
    field = volume.blocks if volume.blocks is not None else volume.field
    s = float(volume.voxel_size)
    origin = np.asarray(volume.origin, dtype=float)
    nx, ny, nz = field.shape
    # max over x, y: no (NX, NY, NZ) bool temporary (106 MB of fresh pages at 512^3).
    occupied_slices = np.flatnonzero(z_profile(field) > 0)
    if occupied_slices.size == 0:
        return []
    k0 = int(occupied_slices[0])
    z = origin[2] + np.arange(nz) * s
    filled: dict[int, np.ndarray] = {}
    stats: dict[int, SliceStats] = {}
    chunks: dict[int, np.ndarray] = {}

    def slice_filled(k: int) -> np.ndarray:
        # z is the fastest axis of the field: slices are copied out 32 at a time
        # (a strided slice per z costs ~5 ms at 512^3).
        if k not in filled:
            c = (k - k0) // SLICE_CHUNK
            if c not in chunks:
                a = k0 + c * SLICE_CHUNK
                b = min(nz, a + SLICE_CHUNK)
                chunks[c] = np.ascontiguousarray(np.moveaxis(
                    read_box(field, (0, 0, a), (nx, ny, b)) > 0, 2, 0))
            filled[k] = filled_slice(chunks[c][(k - k0) % SLICE_CHUNK])
        return filled[k]

    def disc(k: int) -> bool:
        if k not in stats:
            stats[k] = slice_stats(slice_filled(k), origin, s)
        st = stats[k]
        return st.area > 0 and st.fill >= DISC_FILL and st.r_eq >= MIN_POT_RADIUS_VOXELS * s

    # Under the pot the hull is a cone (no camera looks up): skip a few slices to the first disc.
    # The pot starts at the first disc slice of the window from which 3 or more disc slices
    # follow: a cone may hold a disc slice or two of its own below a non-disc one (adaptive
    # scan of validation dicot 1000, 0.77 mm voxels: slices 1-2 discs, 3 fills 0.71, 4 on the
    # pot; taking slice 1 found no pot and left it in the mesh) -- and a run of discs that is
    # all cone (its radius jumping at every slice: no piece) is passed over too (development
    # dicots 32, 46, 49 at 0.60-0.73 mm voxels: 3-5 cone discs, a slice filling 0.74, then 20
    # more cone slices and the pot; the pot was left in 3 of 20 plants).
    skip = max(BOTTOM_SKIP_SLICES, math.ceil(BOTTOM_SKIP_MM / s))
    run, pieces = np.arange(0), []
    ks = k0
    while ks < min(k0 + skip + 1, nz):
        k = ks
        while k < nz and disc(k):
            k += 1
        if k - ks >= 3:
            run = np.arange(ks, k)
            r_eq = np.array([stats[int(kk)].r_eq for kk in run])
            pieces = _pot_pieces(r_eq, s)
            if pieces:
                break
            ks = k  # a later start in the same run ends at k with the same (no) pieces
        ks += 1
    if not pieces:
        return []
    cylinders = []
    for n, piece in enumerate(pieces):
        slope, intercept = np.polyfit(z[run[piece]], r_eq[piece], 1)
        centre = np.mean([stats[int(run[i])].centre for i in piece], axis=0)
        top = int(run[piece[-1]])
        if n == len(pieces) - 1:
            # Rim search: the fitted disc stays full up to the rim even under leaves.
            kk = top + 1
            while kk < nz:
                r = slope * z[kk] + intercept - s
                if r <= 0 or _disc_fill(slice_filled(kk), origin, s, centre, r) < RIM_FILL:
                    break
                kk += 1
            top = kk - 1
        # The lowest piece also takes the cone under the pot (down to the lowest slice).
        z_bottom = z[k0 if n == 0 else int(run[piece[0]])] - s / 2
        z_top = z[top] + s / 2
        cylinders.append(TaperedCylinder(
            z_bottom_mm=float(z_bottom), z_top_mm=float(z_top),
            r_bottom_mm=float(max(slope * z_bottom + intercept, s)),
            r_top_mm=float(max(slope * z_top + intercept, s)),
            centre_xy_mm=(float(centre[0]), float(centre[1]))))
    return cylinders


def _full_radius(field, origin: np.ndarray, s: float, k: int, centre: np.ndarray,
                 r_max: float) -> float:
    """Radius (mm) of the solid disc about ``centre`` in z-slice ``k``: up to the first ring
    (a voxel wide) less than ``CAP_RING_FILL`` occupied, holes filled; 0 if the centre is
    empty.  Only the slice's box of half-side ``r_max`` is read."""
    nx, ny = field.shape[:2]
    i_lo = max(0, int(np.floor((centre[0] - r_max - origin[0]) / s)))
    i_hi = min(nx, int(np.ceil((centre[0] + r_max - origin[0]) / s)) + 1)
    j_lo = max(0, int(np.floor((centre[1] - r_max - origin[1]) / s)))
    j_hi = min(ny, int(np.ceil((centre[1] + r_max - origin[1]) / s)) + 1)
    if i_hi <= i_lo or j_hi <= j_lo:
        return 0.0
    occ = filled_slice(read_box(field, (i_lo, j_lo, k), (i_hi, j_hi, k + 1))[:, :, 0] > 0)
    xs = origin[0] + np.arange(i_lo, i_hi) * s - centre[0]
    ys = origin[1] + np.arange(j_lo, j_hi) * s - centre[1]
    ring = np.floor(np.hypot(xs[:, None], ys[None, :]) / s).astype(np.int64).ravel()
    n_ring = np.bincount(ring)
    full = np.bincount(ring, weights=occ.ravel(), minlength=n_ring.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        fill = full / n_ring
    n = int(r_max / s)
    low = np.flatnonzero(~(fill[:n] >= CAP_RING_FILL))  # an empty ring (n 0) counts as low
    first_low = int(low[0]) if low.size else n
    return first_low * s


def fit_cap(volume: Volume, pot: TaperedCylinder) -> TaperedCylinder | None:
    """The cone of hull over ``pot``'s opening that no view carves; None if there is none.

    Walking up from the rim, each slice's solid disc about the pot's axis
    (:func:`_full_radius`) is followed while it is wider than a stem; when it
    starts at the rim at least ``CAP_BASE_FRACTION`` of the rim's radius wide
    and shrinks over at least ``CAP_MIN_SLICES`` slices, a straight taper
    fitted to it is the cap, from the rim up to where the taper closes (its
    apex: the stem inside the cone is not told apart from it).  A rig with a
    camera level with the rim carves no cone, and none is found.

    Parameters
    ----------
    volume : Volume
        The hull (field > 0 inside), turntable frame.
    pot : TaperedCylinder
        The top piece of :func:`fit_pot` (its rim and axis).

    Returns
    -------
    TaperedCylinder or None
        The cap, mm, turntable frame: ``r_bottom_mm`` at the rim, ``r_top_mm`` the
        stem's radius where the cone ends (a voxel when no stem is seen there);
        the mesher keeps the stem's column through it (``keep_axis_mm``).
    """
    field = volume.blocks if volume.blocks is not None else volume.field
    s = float(volume.voxel_size)
    origin = np.asarray(volume.origin, dtype=float)
    nz = field.shape[2]
    centre = np.asarray(pot.centre_xy_mm, dtype=float)
    r_rim = pot.r_top_mm
    k = int(np.floor((pot.z_top_mm - origin[2]) / s + 0.5))  # the first slice above the rim
    zs, radii = [], []
    stem = s  # the stem's radius where the cone ends (a voxel if none is seen)
    while 0 <= k < nz:
        r = _full_radius(field, origin, s, k, centre, r_rim + 2 * s)
        if r <= STEM_RADIUS_FRACTION * r_rim:
            # the stem rises from the cone: its radius where the disc stops shrinking (the
            # first such slice may still be the cone's tip)
            above = [_full_radius(field, origin, s, kk, centre, r_rim + 2 * s)
                     for kk in range(k + 1, min(k + 1 + CAP_MIN_SLICES, nz))]
            stem = max(min([r, *above]), s)
            break
        if radii and r > radii[-1] + s:
            break  # a leaf widening the disc again: above the cone
        zs.append(origin[2] + k * s)
        radii.append(r)
        k += 1
    if len(radii) < CAP_MIN_SLICES or radii[0] < CAP_BASE_FRACTION * r_rim:
        return None
    slope, intercept = np.polyfit(zs, radii, 1)
    if slope >= 0:
        return None  # not shrinking: no cone
    # The walk ends at a stem's width, most of the way up: the apex is not much further
    # (a third of the walked height on a straight cone); a flat taper ends where it was seen.
    walked = zs[-1] - zs[0] + s
    z_top = min(max(-intercept / slope, zs[-1] + s / 2), zs[-1] + walked / 2)
    return TaperedCylinder(
        z_bottom_mm=float(pot.z_top_mm), z_top_mm=float(z_top),
        r_bottom_mm=float(min(slope * pot.z_top_mm + intercept, r_rim)),
        r_top_mm=float(stem), centre_xy_mm=(float(centre[0]), float(centre[1])))


def _hidden_views(points: np.ndarray, centres: np.ndarray,
                  targets: list[TaperedCylinder]) -> np.ndarray:
    """How many views see each point against a target's top (the pot's opening, a carrier).

    A view sees ``P`` against a cylinder when the ray from its centre through ``P``
    crosses the cylinder's top plane (ahead of the camera) within its widest radius:
    past the point, descending, or in front of it from below (through the pot).

    Parameters
    ----------
    points : (N, 3) float64 array, mm, turntable frame
    centres : (V, 3) float64 array, mm, turntable frame
    targets : the cylinders the masks hold (pot, carrier)

    Returns
    -------
    (N,) int array, views
    """
    d = points[:, None, :] - centres[None, :, :]            # (N, V, 3): the ray at t = 1
    hidden = np.zeros(d.shape[:2], dtype=bool)
    for c in targets:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c.z_top_mm - centres[None, :, 2]) / d[:, :, 2]
        qx = centres[None, :, 0] + t * d[:, :, 0] - c.centre_xy_mm[0]
        qy = centres[None, :, 1] + t * d[:, :, 1] - c.centre_xy_mm[1]
        radius = max(c.r_top_mm, c.r_bottom_mm)
        hidden |= (t > 0) & np.isfinite(t) & (qx * qx + qy * qy <= radius * radius)
    return hidden.sum(axis=1)


def views_cone(views: CarvingViews, cylinders: list[TaperedCylinder],
               step_mm: float) -> TaperedCylinder | None:
    """The straight cone over the pot's opening that the views cannot carve; None if none.

    A point over the opening stays in the hull while at most ``views.k`` views see
    it outside the masks, and every view that sees it against the pot or a carrier
    (:func:`_hidden_views`) sees it inside them.  That region is found from the
    cameras: its apex on the pot's axis and, at heights through it, its edge on
    rays every 5 deg about the axis, each by bisection to ``step_mm`` / 64 (the
    region is convex for ``k`` 0: one view's is the oblique cone from its centre
    through the rim).  The cone returned is the tallest straight cone from the
    whole rim to an apex on the axis inside it: a bound on the cap (:func:`fit_cap`)
    that no leaf above it can push up.

    Parameters
    ----------
    views : CarvingViews
        The cameras that carved the hull, and its k.
    cylinders : the fitted pot (the top one) and carrier
    step_mm : float, mm
        The voxel size.

    Returns
    -------
    TaperedCylinder or None
        From the rim (``r_bottom_mm`` the rim's radius) to the apex (``r_top_mm``
        ``step_mm``); None when the cone is less than ``step_mm`` tall (a camera
        level with the rim).
    """
    if not cylinders or len(views.centres_mm) == 0:
        return None
    pot = max(cylinders, key=lambda c: c.z_top_mm)
    centres = np.asarray(views.centres_mm, dtype=float)
    cx, cy = pot.centre_xy_mm
    z0, r_rim = pot.z_top_mm, pot.r_top_mm
    steps = max(1, math.ceil(math.log2(max(r_rim, centres[:, 2].max() - z0) * 64 / step_mm)))

    def inside(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        pts = np.column_stack([x, y, z])
        return len(centres) - _hidden_views(pts, centres, cylinders) <= views.k

    # the apex on the axis, between the rim and the highest camera (nothing hides above it)
    lo, hi = z0, float(centres[:, 2].max())
    for _ in range(steps):
        mid = (lo + hi) / 2
        if inside(np.array([cx]), np.array([cy]), np.array([mid]))[0]:
            lo = mid
        else:
            hi = mid
    height = lo - z0
    if height < step_mm:
        return None
    # the region's edge at heights through it: the straight cone from the rim must stay
    # inside, r_rim (1 - h / H) <= edge(h), so H <= h r_rim / (r_rim - edge(h))
    az = np.deg2rad(np.arange(0.0, 360.0, 5.0))
    c, sn = np.cos(az), np.sin(az)
    for h in height * np.linspace(0.05, 0.95, 19):
        r_lo, r_hi = np.zeros(az.size), np.full(az.size, r_rim)
        for _ in range(steps):
            mid = (r_lo + r_hi) / 2
            ok = inside(cx + mid * c, cy + mid * sn, np.full(az.size, z0 + h))
            r_lo, r_hi = np.where(ok, mid, r_lo), np.where(ok, r_hi, mid)
        edge = float(r_lo.min())
        if edge < r_rim:
            height = min(height, h * r_rim / (r_rim - edge))
    return TaperedCylinder(z_bottom_mm=float(z0), z_top_mm=float(z0 + height),
                           r_bottom_mm=float(r_rim), r_top_mm=float(step_mm),
                           centre_xy_mm=(float(cx), float(cy)))


def bound_cap(cap: TaperedCylinder, bound: TaperedCylinder) -> TaperedCylinder:
    """``cap`` no taller and no wider at the rim than ``bound`` (:func:`views_cone`)."""
    return cap.model_copy(update={"z_top_mm": min(cap.z_top_mm, bound.z_top_mm),
                                  "r_bottom_mm": min(cap.r_bottom_mm, bound.r_bottom_mm)})


def remove_cylinders(volume: Volume, cylinders: list[TaperedCylinder],
                     margin_mm: float, undo: list | None = None,
                     keep_axis_mm: float = 0.0) -> tuple[np.ndarray, int]:
    """Field with ``cylinders`` (grown by ``margin_mm``) subtracted; and voxels removed.

    ``keep_axis_mm`` > 0 keeps a column of that radius about each cylinder's axis
    (the stem through the cap over the pot: the plant's height is the mesh's extent).

    ``margin_mm`` is the full margin; callers add a voxel to it because the
    hull's rim is only known to a voxel.  With ``undo`` (a list) the volume's
    own field is changed in place and each changed sub-box's former values are
    recorded in ``undo`` (``fields.restore`` puts them back): no copy of the
    grid (411 MB of fresh pages at 512^3, 0.3-1.2 s of page faults).  A volume
    held in blocks is edited block by block (always in place, ``undo`` or not).

    Returns
    -------
    field : (NX, NY, NZ) float32 array, voxels (a new array, or the volume's own
        when ``cylinders`` is empty or ``undo`` is given), or the volume's
        ``BlockField``
    removed : int, voxels that were inside and are now outside
    """
    own = volume.blocks if volume.blocks is not None else volume.field
    if not cylinders:
        return own, 0  # nothing to subtract: no copy of a possibly large grid
    if undo is None and volume.blocks is None:
        field = np.array(own, dtype=np.float32, copy=True)
    else:
        field = own
    s = float(volume.voxel_size)
    origin = np.asarray(volume.origin, dtype=float)
    removed = 0
    for cyl in cylinders:
        k_lo = max(0, int(np.floor((cyl.z_bottom_mm - margin_mm - origin[2]) / s)) - 1)
        k_hi = min(field.shape[2], int(np.ceil((cyl.z_top_mm + margin_mm - origin[2]) / s)) + 2)
        if k_hi <= k_lo:
            continue
        r_max = max(cyl.r_bottom_mm, cyl.r_top_mm) + margin_mm
        (cx, cy), n = cyl.centre_xy_mm, field.shape
        i_lo = max(0, int(np.floor((cx - r_max - origin[0]) / s)) - 1)
        i_hi = min(n[0], int(np.ceil((cx + r_max - origin[0]) / s)) + 2)
        j_lo = max(0, int(np.floor((cy - r_max - origin[1]) / s)) - 1)
        j_hi = min(n[1], int(np.ceil((cy + r_max - origin[1]) / s)) + 2)
        if i_hi <= i_lo or j_hi <= j_lo:
            continue
        # The distance separates into a radial term over (i, j) and an axial one over k:
        # broadcast, in float32, instead of 3D index grids of float64 points.
        xs = (origin[0] + np.arange(i_lo, i_hi) * s - cx).astype(np.float32)
        ys = (origin[1] + np.arange(j_lo, j_hi) * s - cy).astype(np.float32)
        rho = np.hypot(xs[:, None], ys[None, :])[:, :, None]
        zs = (origin[2] + np.arange(k_lo, k_hi) * s).astype(np.float32)
        d_in = cyl.inside_distance(rho, zs, margin_mm).astype(np.float32) / np.float32(s)
        if keep_axis_mm > 0:
            d_in = np.minimum(d_in, (rho - np.float32(keep_axis_mm)) / np.float32(s))
        lo = (i_lo, j_lo, k_lo)
        sub = read_box(field, lo, (i_hi, j_hi, k_hi))
        cut = np.minimum(sub, -np.clip(d_in, -1.0, 1.0))
        removed += int(np.count_nonzero((sub > 0) & (cut <= 0)))
        write_box(field, lo, cut, undo)
    return field, removed
