"""Automatic pot fit on analytic hull fields: the pot goes, the plant (stem included) stays."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from plantscan_hull.pot import fit_cap, fit_pot, remove_cylinders

from plantscan_core.data import Volume

VOXEL = 1.0  # mm: the 512^3 hull of an 18 MP scan (where a stem is a run of discs)
CARRIER = (0.0, 32.0, 60.0, 60.0)  # z bottom, z top, r bottom, r top (mm); overlaps the pot
POT = (30.0, 150.0, 52.0, 68.0)
STEM_R = 4.7  # mm: the virtual dicot's stem, 4.7 voxels (> MIN_POT_RADIUS_VOXELS)
LEAF_Z = 220.0  # the lowest leaf: a flat slab


def _cylinder(rho, z, z0, z1, r0, r1):
    """Inside distance (mm, > 0 inside) of a vertical tapered cylinder; broadcasts."""
    r = r0 + (z - z0) / (z1 - z0) * (r1 - r0)
    return np.minimum(r - rho, np.minimum(z - z0, z1 - z))


@pytest.fixture(scope="module")
def potted_plant() -> Volume:
    xs = np.arange(-80.0, 80.0 + VOXEL, VOXEL)
    zs = np.arange(-5.0, 300.0, VOXEL)
    rho = np.hypot(xs[:, None], xs[None, :])[:, :, None]
    x = xs[:, None, None]
    z = zs[None, None, :]
    inside = functools.reduce(np.maximum, [
        _cylinder(rho, z, *CARRIER),
        _cylinder(rho, z, *POT),
        _cylinder(rho, z, POT[1] - 10.0, 290.0, STEM_R, STEM_R),  # from the soil up
        # a leaf leaving the stem sideways: 2 mm thick, 70 mm long, 30 mm wide
        functools.reduce(np.minimum, [1.0 - np.abs(z - LEAF_Z), x - 0.0, 70.0 - x,
                                      15.0 - np.abs(xs[None, :, None])]),
    ])
    field = np.clip(inside / VOXEL, -1.0, 1.0).astype(np.float32)
    return Volume(field, np.array([xs[0], xs[0], zs[0]]), VOXEL)


def test_fit_keeps_the_stem_above_the_rim(potted_plant):
    cyl = fit_pot(potted_plant)
    # Carrier and pot are found (2 pieces), the stem between the rim and the lowest leaf is
    # not a third: a stem of 4.7 voxels is a run of discs too, 0.07 of the pot's radius.
    assert len(cyl) == 2, cyl
    carrier, pot = cyl
    # Rim and radii to within a voxel and a half (slices are judged whole voxels).
    assert pot.z_top_mm == pytest.approx(POT[1], abs=1.5 * VOXEL)
    assert pot.r_top_mm == pytest.approx(POT[3], abs=1.5 * VOXEL)
    assert carrier.r_bottom_mm == pytest.approx(CARRIER[2], abs=1.5 * VOXEL)

    field, removed = remove_cylinders(potted_plant, cyl, margin_mm=2.0 * VOXEL)
    zs = potted_plant.origin[2] + np.arange(field.shape[2]) * VOXEL
    centre = field.shape[0] // 2
    stem_column = field[centre, centre, :] > 0
    above_rim = (zs > POT[1] + 3 * VOXEL) & (zs < LEAF_Z - 2 * VOXEL)
    # Every slice of the stem from just above the rim (rim + margin + a voxel) to the leaf stays.
    assert stem_column[above_rim].all()
    # And the pot is gone: nothing inside below the rim less the margin.
    below_rim = zs < POT[1] - 2 * VOXEL
    assert not (field[:, :, below_rim] > 0).any()
    assert removed > 0


def test_fit_finds_the_pot_over_the_short_cone_low_views_leave():
    # Views near the horizon (an adaptive scan's tilts below 0) carve the cone under the pot
    # to a polygonal stub: here a square pyramid 8 mm tall under the pot, its slices filling
    # 0.64 of their disc (< DISC_FILL) over 8 slices.  The pot is still found.
    xs = np.arange(-80.0, 80.0 + VOXEL, VOXEL)
    zs = np.arange(15.0, 200.0, VOXEL)
    rho = np.hypot(xs[:, None], xs[None, :])[:, :, None]
    diamond = (np.abs(xs[:, None]) + np.abs(xs[None, :]))[:, :, None]
    z = zs[None, None, :]
    cone = np.minimum((z - (POT[0] - 8.0)) / 8.0 * POT[2] - diamond, POT[0] - z + 0.5)
    inside = np.maximum(_cylinder(rho, z, *POT), cone)
    volume = Volume(np.clip(inside / VOXEL, -1.0, 1.0).astype(np.float32),
                    np.array([xs[0], xs[0], zs[0]]), VOXEL)
    cyl = fit_pot(volume)
    assert len(cyl) == 1, cyl
    assert cyl[0].z_top_mm == pytest.approx(POT[1], abs=1.5 * VOXEL)
    assert cyl[0].r_top_mm == pytest.approx(POT[3], abs=1.5 * VOXEL)


def test_fit_finds_the_pot_over_a_cone_with_disc_slices_of_its_own():
    # Under the pot the cone's lowest slices may fill enough of their disc to count as discs,
    # with a slice above them that does not (adaptive scan of validation dicot 1000: discs,
    # then 0.71, then the pot).  The pot starts at the first disc slice with 2 more above it.
    xs = np.arange(-80.0, 80.0 + VOXEL, VOXEL)
    zs = np.arange(15.0, 200.0, VOXEL)
    rho = np.hypot(xs[:, None], xs[None, :])[:, :, None]
    z = zs[None, None, :]
    inside = _cylinder(rho, z, *POT)
    k_pot = int(np.searchsorted(zs, POT[0]))
    # two round slices (discs), then a cross of two bars (fill ~0.37 < DISC_FILL), then the pot
    cross = (np.minimum(np.abs(xs[:, None]), np.abs(xs[None, :])) <= 8.0) \
        & (rho[:, :, 0] <= POT[2])
    field = np.clip(inside / VOXEL, -1.0, 1.0).astype(np.float32)
    field[:, :, k_pot] = np.where(cross, 1.0, -1.0)
    for k in (k_pot - 2, k_pot - 1):
        field[:, :, k] = np.where(rho[:, :, 0] <= 0.5 * POT[2], 1.0, -1.0)
    volume = Volume(field, np.array([xs[0], xs[0], zs[0]]), VOXEL)
    cyl = fit_pot(volume)
    assert len(cyl) == 1, cyl
    assert cyl[0].z_top_mm == pytest.approx(POT[1], abs=1.5 * VOXEL)
    assert cyl[0].r_top_mm == pytest.approx(POT[3], abs=1.5 * VOXEL)
    assert cyl[0].z_bottom_mm <= zs[k_pot - 2]  # the cone's slices go with the pot


def test_the_cap_of_an_analytic_cone_over_the_rim_is_fitted(potted_plant):
    # The potted plant with a cone 14 mm tall standing on the whole rim (what the virtual
    # dicot's rig leaves: 13.3 mm, docs/reconstruction.md): the cap is the cone, the stem
    # through it does not stop the walk (4.7 mm < a quarter of the rim's radius).
    xs = np.arange(-80.0, 80.0 + VOXEL, VOXEL)
    zs = potted_plant.origin[2] + np.arange(potted_plant.shape[2]) * VOXEL
    rho = np.hypot(xs[:, None], xs[None, :])[:, :, None]
    height = 14.0
    cone = np.minimum(POT[3] * (1.0 - (zs[None, None, :] - POT[1]) / height) - rho,
                      zs[None, None, :] - POT[1] + 0.5)
    field = np.maximum(potted_plant.field, np.clip(cone / VOXEL, -1, 1).astype(np.float32))
    volume = Volume(field, potted_plant.origin, VOXEL)
    pot = fit_pot(volume)[-1]
    assert pot.z_top_mm == pytest.approx(POT[1], abs=1.5 * VOXEL)  # the cone is not the pot
    cap = fit_cap(volume, pot)
    assert cap is not None
    # Apex, and the radius at the fitted rim (half a voxel over the cone's base), within 1.5
    # voxels: each slice's disc is read to whole rings of a voxel.
    assert cap.z_top_mm == pytest.approx(POT[1] + height, abs=1.5 * VOXEL)
    r_cone = POT[3] * (1.0 - (cap.z_bottom_mm - POT[1]) / height)
    assert cap.r_bottom_mm == pytest.approx(r_cone, abs=1.5 * VOXEL)
    # Its top radius is the stem's (kept through the cap by the mesher), to the same 1.5 voxels.
    assert cap.r_top_mm == pytest.approx(STEM_R, abs=1.5 * VOXEL)
    # Without the cone there is no cap: the stem alone is a run of narrow discs.
    assert fit_cap(potted_plant, fit_pot(potted_plant)[-1]) is None


def test_fit_finds_the_pot_over_a_tall_cone_broken_by_a_slice_that_is_not_a_disc():
    # At fine voxels (0.6-0.7 mm: small plants at 512^3) the cone under the pot is ~20
    # slices tall, its radius growing ~3.7 voxels a slice.  Its lowest slices are discs,
    # one a little higher is not (development dicots 32, 46, 49: fill 0.74), so the first
    # run of discs is all cone: no piece of 3 slices without a radius jump.  The pot above
    # is still found, and takes the cone with it.
    xs = np.arange(-80.0, 80.0 + VOXEL, VOXEL)
    zs = np.arange(0.0, 200.0, VOXEL)
    rho = np.hypot(xs[:, None], xs[None, :])[:, :, None]
    z = zs[None, None, :]
    cone_height = 14.0  # mm: 52 mm of radius at 3.7 mm a slice
    z_cone = POT[0] - cone_height
    cone = np.minimum((z - z_cone) / cone_height * POT[2] - rho, POT[0] - z + 0.5)
    field = np.clip(np.maximum(_cylinder(rho, z, *POT), cone) / VOXEL, -1.0, 1.0)
    field = field.astype(np.float32)
    k_dip = int(np.searchsorted(zs, z_cone)) + 5
    cross = (np.minimum(np.abs(xs[:, None]), np.abs(xs[None, :])) <= 3.0) & (rho[:, :, 0] <= 20.0)
    field[:, :, k_dip] = np.where(cross, 1.0, -1.0)
    volume = Volume(field, np.array([xs[0], xs[0], zs[0]]), VOXEL)
    cyl = fit_pot(volume)
    assert len(cyl) == 1, cyl
    assert cyl[0].z_top_mm == pytest.approx(POT[1], abs=1.5 * VOXEL)
    assert cyl[0].r_top_mm == pytest.approx(POT[3], abs=1.5 * VOXEL)
    assert cyl[0].z_bottom_mm <= z_cone + VOXEL  # the cone's slices go with the pot
    # and removing it leaves nothing below the rim (less the margin)
    field, _ = remove_cylinders(volume, cyl, margin_mm=2.0 * VOXEL)
    assert not (field[:, :, zs < POT[1] - 2 * VOXEL] > 0).any()
