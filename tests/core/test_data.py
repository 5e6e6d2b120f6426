"""Camera model and calibration contracts, against analytic answers."""

from __future__ import annotations

import numpy as np
import pytest

from plantscan_core.data import (
    Calibration,
    Camera,
    CameraModel,
    LeafTraits,
    Mesh,
    Pose,
    Silhouette,
    TiltAxis,
    Traits,
    ViewRecord,
    rotation_about_axis,
    rotation_x,
    rotation_z,
)

MODEL = CameraModel(f=1500.0, cu=640.2, cv=479.7, d1=-0.08, d2=0.02, width=1280, height=960)


def test_project_unproject_round_trip_through_distortion():
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [1280, 960], size=(500, 2))
    rays = MODEL.unproject(uv)
    back = MODEL.project_camera_points(rays * 700.0)
    # 1e-6 px: the fixed-point inversion converges far below any image-noise level.
    assert np.max(np.abs(back - uv)) < 1e-6


def test_distortion_matches_opencv():
    import cv2

    pts = np.array([[100.0, 50.0, 900.0], [-200.0, 120.0, 800.0]])
    ours = MODEL.project_camera_points(pts)
    cv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), MODEL.K, MODEL.dist_coeffs)
    assert np.allclose(ours, cv.reshape(-1, 2), atol=1e-9)


def test_aspect_ratio_matches_opencv_and_survives_yaml_and_scaling():
    import cv2

    model = CameraModel(f=1500.0, cu=640.2, cv=479.7, d1=-0.08, d2=0.02, width=1280, height=960,
                        aspect=1.0006)
    pts = np.array([[100.0, 50.0, 900.0], [-200.0, 120.0, 800.0]])
    cv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), model.K, model.dist_coeffs)
    assert np.allclose(model.project_camera_points(pts), cv.reshape(-1, 2), atol=1e-9)
    uv = np.array([[10.0, 20.0], [1200.0, 900.0]])
    # 1e-6 px: as the square-pixel round trip above.
    assert np.max(np.abs(model.project_camera_points(model.unproject(uv) * 500) - uv)) < 1e-6
    assert CameraModel.from_dict(model.to_dict()) == model
    assert model.scaled(0.5).aspect == model.aspect
    # A model saved before the aspect existed loads with square pixels.
    old = {k: v for k, v in MODEL.to_dict().items() if k != "aspect"}
    assert CameraModel.from_dict(old).aspect == 1.0


def test_pose_look_at_and_centre():
    pose = Pose.look_at((500.0, 0.0, 100.0), (0.0, 0.0, 100.0))
    assert np.allclose(pose.centre, [500, 0, 100])
    assert np.allclose(pose.apply(np.array([[0.0, 0.0, 100.0]])), [[0, 0, 500]])
    cam = Camera(MODEL, pose)
    # A point above the target images above the principal point (smaller v).
    assert cam.project(np.array([[0.0, 0.0, 150.0]]))[0, 1] < MODEL.cv


def test_turntable_rotation_convention():
    pose = Pose.look_at((500.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    cal = Calibration({"c": MODEL}, {("c", 0): pose})
    p = np.array([[0.0, 50.0, 0.0]])
    # Turning the plate +90 deg brings the point at +Y to -X: straight towards... away from
    # the camera at +X, i.e. it ends on the optical axis.
    cam90 = cal.camera_at("c", 0, 90.0)
    assert np.allclose(cam90.project(p)[0], [MODEL.cu, MODEL.cv], atol=1e-9)
    assert np.isclose(cam90.depth(p)[0], 550.0)


def test_calibration_yaml_round_trip(tmp_path):
    cal = Calibration(
        {"a": MODEL}, {("a", 0): Pose(rotation_x(30) @ rotation_z(10), [1.0, 2.0, 3.0])},
        tilts_deg={0: 0.0, 1: 20.0}, angle_scale=1.0002,
        tilt_axis=TiltAxis(np.array([0.0, 0.0, 120.0]), np.array([0.0, 1.0, 0.0])),
        quality={"rms_px": np.float64(0.12)}, view_angles_deg={0: 0.02, 7: 70.01})
    cal.save(tmp_path / "c.yaml")
    text = (tmp_path / "c.yaml").read_text()
    assert "!!" not in text  # plain YAML, no Python/numpy tags
    back = Calibration.load(tmp_path / "c.yaml")
    assert back.view_angles_deg == {0: 0.02, 7: 70.01}  # the sfm calibrator's solved angles
    p = np.array([[10.0, -20.0, 150.0]])
    for angle in (0.0, 37.0):
        assert np.allclose(back.camera_at("a", 0, angle).project(p),
                           cal.camera_at("a", 0, angle).project(p))
    assert np.allclose(back.camera_at_tilt("a", 20.0, 5.0).project(p),
                       cal.camera_at_tilt("a", 20.0, 5.0).project(p))


def test_tilt_axis_moves_camera_about_the_axis():
    pose = Pose.look_at((500.0, 0.0, 120.0), (0.0, 0.0, 120.0))
    axis = TiltAxis(np.array([0.0, 0.0, 120.0]), np.array([0.0, 1.0, 0.0]))
    cal = Calibration({"c": MODEL}, {("c", 0): pose}, {0: 0.0}, tilt_axis=axis)
    cam = cal.camera_at_tilt("c", 30.0, 0.0)
    expected = rotation_about_axis([0, 1, 0], 30.0) @ np.array([500.0, 0.0, 0.0]) + [0, 0, 120]
    assert np.allclose(cam.pose.centre, expected)
    # The axis point stays on the optical axis of every tilt.
    assert np.allclose(cam.project(np.array([[0.0, 0.0, 120.0]]))[0], [MODEL.cu, MODEL.cv])


def test_traits_csv_round_trip_and_bad_trait_name():
    t = Traits([LeafTraits(0, 152.6, 74.5, 8535.6, 350.89, 0.031, 0.3, "phantom;outline",
                           "check")], {"leaf_count": 1})
    back = Traits.from_csv(t.to_csv())
    assert back.leaves[0].trait("area") == pytest.approx(8535.6)
    assert back.leaves[0].thick_share == pytest.approx(0.031)
    assert back.leaves[0].confidence == pytest.approx(0.3)
    assert (back.leaves[0].confidence_reasons, back.leaves[0].quality_flag) == (
        "phantom;outline", "check")
    header = "leaf_id,length_mm,width_mm,area_mm2,perimeter_mm"
    assert t.to_csv().splitlines()[0] == (
        header + ",thick_share,confidence,confidence_reasons,quality_flag")
    # a table written before the quality columns (or by another tool) still reads
    old = Traits.from_csv(header + "\n0,152.6,74.5,8535.6,350.89\n")
    assert old.leaves[0].perimeter_mm == pytest.approx(350.89)
    assert np.isnan(old.leaves[0].thick_share) and np.isnan(old.leaves[0].confidence)
    assert old.leaves[0].quality_flag == ""
    with pytest.raises(ValueError, match="valid: length, width, area, perimeter"):
        t.leaves[0].trait("volume")


def test_silhouette_is_held_as_its_crop_and_gives_the_full_mask_back():
    view = ViewRecord(3, "plant", "cam0", 0, 0.0, 3, 30.0, None, "images/3.jpg")
    rng = np.random.default_rng(1)
    mask = np.zeros((400, 600), bool)
    mask[120:180, 250:330] = rng.random((60, 80)) < 0.5
    mask[120, 250] = mask[179, 329] = True  # the box's corners are plant
    sil = Silhouette(view, mask)
    assert sil.crop.shape == (60, 80) and (sil.u0, sil.v0) == (250, 120)
    assert sil.shape == (400, 600)
    assert np.array_equal(sil.mask, mask) and sil.area == mask.sum()
    mask[0, 0] = True  # the silhouette holds its own copy
    assert not sil.mask[0, 0]
    empty = Silhouette(view, np.zeros((4, 5), bool))
    assert empty.shape == (4, 5) and not empty.mask.any() and empty.mask.shape == (4, 5)


def test_the_traits_table_is_leaf_traits_fields():
    # traits.csv's header, the trait names, units and report titles come from LeafTraits's
    # fields: a new trait is one field (and the measurer's function that fills it).
    import dataclasses

    from plantscan_core.data import LEAF_COLUMNS, LEAF_TRAIT_COLUMNS, PLANT_COLUMN, TRAIT_NAMES

    assert list(LEAF_TRAIT_COLUMNS) == [f.name for f in dataclasses.fields(LeafTraits)]
    assert TRAIT_NAMES == ("length", "width", "area", "perimeter")
    assert [c.header for c in LEAF_COLUMNS] == [
        "length (mm)", "width (mm)", "area (mm²)", "perimeter (mm)", "thick area (%)",
        "confidence", "confidence reasons", "quality flag"]
    assert [c.unit for c in LEAF_COLUMNS] == ["mm", "mm", "mm2", "mm", "1", "1", "", ""]
    assert [c.name for c in LEAF_COLUMNS if c.required] == list(LEAF_TRAIT_COLUMNS[1:5])
    assert PLANT_COLUMN["total_leaf_area_mm2"].header == "total leaf area (mm²)"
    assert PLANT_COLUMN["leaf_count"].header == "leaf count"


def test_a_new_leaf_trait_is_one_field():
    # One field with its metadata gives the column, its unit and its report title (a
    # subclass stands in for the edit of LeafTraits).
    import dataclasses
    import math

    from plantscan_core import data

    @dataclasses.dataclass
    class WithAngle(data.LeafTraits):
        inclination_deg: float = data._column("deg", "blade angle to the horizontal",
                                              default=math.nan, trait="inclination")

    columns = data.leaf_columns(WithAngle)
    assert columns[:-1] == data.LEAF_COLUMNS
    assert columns[-1] == data.TraitColumn("inclination_deg", "deg",
                                           "blade angle to the horizontal", trait="inclination")
    assert columns[-1].header == "inclination (deg)"


def test_a_traits_table_without_a_trait_names_its_file_and_column(tmp_path):
    from plantscan_core.errors import DataError

    bad = tmp_path / "traits.csv"
    bad.write_text("leaf_id,length_mm,width_mm,area_mm2\n4,1,2,3\n")
    with pytest.raises(DataError, match=r"traits.csv: no column perimeter_mm \(it has leaf_id"):
        Traits.load(bad)


def test_formats_md_lists_the_trait_table():
    # docs/formats.md's table is what a scientist reads; it must not drift from the code.
    from pathlib import Path

    from plantscan_core.data import LEAF_COLUMNS, PLANT_TRAITS

    text = (Path(__file__).resolve().parents[2] / "docs" / "formats.md").read_text()
    section = text.split("### The trait table", 1)[1].split("\n### ", 1)[0]
    rows = [[cell.strip().strip("`") for cell in line.strip("|").split("|")[:3]]
            for line in section.splitlines() if line.startswith("| `")]
    assert rows == [[c.name, c.level, c.unit or "text"] for c in (*LEAF_COLUMNS, *PLANT_TRAITS)]


# --------------------------------------------------------------------------- block fields
def _clamped_field(shape, seed=0):
    """A hull-like clamped field: mostly exact -1, a solid of +1, values in between."""
    rng = np.random.default_rng(seed)
    field = np.full(shape, -1.0, np.float32)
    field[3:20, 4:30, 2:9] = 1.0
    band = rng.random(shape) < 0.05
    field[band] = rng.uniform(-1, 1, band.sum()).astype(np.float32)
    return field


@pytest.mark.parametrize("block", [4, 8, 32])
def test_block_field_gives_the_dense_field_back(block):
    from plantscan_core.data import BlockField

    field = _clamped_field((37, 33, 11))
    blocks = BlockField.from_dense(field, block)
    assert np.array_equal(blocks.dense(), field)
    # any box, reaching beyond the grid on every side: -1 there
    box = blocks.read((-3, 5, -2), (40, 31, 14))
    want = np.full((43, 26, 16), -1.0, np.float32)
    want[3:40, :, 2:13] = field[:, 5:31, :]
    assert np.array_equal(box, want)
    idx = np.array([[0, 0, 0], [36, 32, 10], [10, 10, 5], [5, 20, 3]])
    assert np.array_equal(blocks.values_at(idx), field[tuple(idx.T)])
    maxima = np.maximum.reduceat(np.maximum.reduceat(np.maximum.reduceat(
        field, np.arange(0, 37, block), 0), np.arange(0, 33, block), 1), np.arange(0, 11, block), 2)
    assert np.array_equal(blocks.block_max(), maxima)


def test_block_field_stores_only_the_mixed_blocks():
    from plantscan_core.data import BlockField

    field = np.full((64, 64, 64), -1.0, np.float32)
    field[:32, :32, :32] = 1.0  # one block wholly inside
    field[40, 40, 40] = 0.3  # one mixed block
    blocks = BlockField.from_dense(field, 32)
    assert len(blocks.values) == 1
    assert blocks.index[0, 0, 0] == BlockField.INSIDE and blocks.index[1, 0, 0] == -1
    blocks.materialise(np.array([[0, 0, 0], [1, 1, 1]]))  # an implicit block given a row
    assert len(blocks.values) == 2 and np.array_equal(blocks.dense(), field)


def test_volume_in_blocks_saves_loads_and_reads_densely(tmp_path):
    from plantscan_core.data import BlockField, Volume

    field = _clamped_field((37, 33, 11), seed=3)
    vol = Volume(BlockField.from_dense(field, 8), np.array([1.0, 2.0, 3.0]), 0.5)
    assert vol.shape == (37, 33, 11) and vol.blocks is not None
    assert np.array_equal(vol.field, field) and np.array_equal(vol.occupancy, field > 0)
    vol.save(tmp_path / "v.npz")
    back = Volume.load(tmp_path / "v.npz")
    assert back.blocks is not None and np.array_equal(back.field, field)
    assert back.voxel_size == 0.5 and np.array_equal(back.origin, [1.0, 2.0, 3.0])
    dense = Volume(field, np.zeros(3), 1.0)
    dense.save(tmp_path / "d.npz")
    assert Volume.load(tmp_path / "d.npz").blocks is None
    assert Volume.load(tmp_path / "d.npz").field is not None


def test_label_centroids_are_each_labels_area_weighted_mean():
    # against a plain per-label loop over every face (labels < 0 ignored)
    rng = np.random.default_rng(0)
    mesh = Mesh(rng.normal(size=(60, 3)), rng.integers(0, 60, size=(200, 3)))
    labels = rng.integers(-1, 4, size=200)
    got = mesh.label_centroids(labels)
    area = mesh.face_areas()
    centre = mesh.vertices[mesh.faces].mean(axis=1)
    assert sorted(got) == [0, 1, 2, 3]
    for k, c in got.items():
        sel = labels == k
        np.testing.assert_allclose(c, (area[sel, None] * centre[sel]).sum(0) / area[sel].sum())
    assert mesh.label_centroids(np.full(200, -1)) == {}
