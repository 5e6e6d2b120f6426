"""Exporters on a synthetic run with known geometry, poses and traits."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from plantscan_report import plugin
from plantscan_report.colours import face_colours, label_colours, leaf_colour
from plantscan_report.html_report import HtmlReportExporter
from plantscan_report.truth import match_leaves, read_truth_traits
from report_fixtures import HOSTILE_ID, HOSTILE_RECIPE

from plantscan_core.data import Traits
from plantscan_core.plugins import new_manager
from plantscan_core.stages import RunResult, StageContext


def build(name: str, run: RunResult, params: dict | None = None):
    manager = new_manager()
    manager.register(plugin, name="report")
    return manager.build("exporter", name, params, StageContext(run.recipe, run.scan, run.run_dir))


def test_every_exporter_registers_under_its_recipe_name():
    manager = new_manager()
    manager.register(plugin, name="report")
    assert manager.registry.names("exporter") == ["colmap", "csv", "glb", "html-report", "obj",
                                                  "ply"]


def _face_colours_of(vertices_rgb: np.ndarray, faces: np.ndarray) -> np.ndarray:
    rgb = vertices_rgb[faces]  # (F, 3 vertices, 3)
    # Every face's three vertices must carry one colour (no blending between leaves).
    assert np.abs(rgb - rgb[:, :1]).max() < 1e-6
    return rgb[:, 0]


@pytest.mark.parametrize("name", ["ply", "obj"])
def test_open3d_mesh_files_keep_geometry_and_leaf_colours(synthetic_run, name):
    import open3d as o3d

    (path,) = build(name, synthetic_run).export(synthetic_run)
    assert path == synthetic_run.run_dir / f"plant.{name}"
    m = o3d.io.read_triangle_mesh(str(path))
    faces, vertices = np.asarray(m.triangles), np.asarray(m.vertices)
    labelled = synthetic_run.labelled
    assert len(faces) == len(labelled.mesh.faces)
    # Same faces in the same order, so face areas match (1e-4 mm²: OBJ stores ~6 digits).
    tri = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    np.testing.assert_allclose(areas, labelled.mesh.face_areas(), atol=1e-3)
    got = _face_colours_of(np.asarray(m.vertex_colors), faces)
    # 8-bit colour quantisation in the files: 1/255 tolerance.
    np.testing.assert_allclose(got, face_colours(labelled), atol=1.0 / 255 + 1e-9)
    leaf0 = labelled.face_labels == labelled.leaf_labels[0]
    np.testing.assert_allclose(got[leaf0], np.tile(leaf_colour(0), (leaf0.sum(), 1)),
                               atol=1.0 / 255 + 1e-9)


def _parse_glb(data: bytes) -> tuple[dict, bytes]:
    magic, version, length = struct.unpack("<4sII", data[:12])
    assert (magic, version, length) == (b"glTF", 2, len(data))
    jlen, jtype = struct.unpack("<I4s", data[12:20])
    assert jtype == b"JSON" and jlen % 4 == 0
    doc = json.loads(data[20:20 + jlen])
    blen, btype = struct.unpack("<I4s", data[20 + jlen:28 + jlen])
    assert btype == b"BIN\0"
    return doc, data[28 + jlen:28 + jlen + blen]


def _accessor(doc: dict, binary: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {5126: "<f4", 5125: "<u4", 5121: "u1"}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    raw = binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]]
    return np.frombuffer(raw, dtype=dtype).reshape(acc["count"], width)


def test_glb_is_valid_gltf_with_one_named_node_per_organ_and_metre_y_up_root(synthetic_run):
    (path,) = build("glb", synthetic_run).export(synthetic_run)
    doc, binary = _parse_glb(path.read_bytes())
    labelled = synthetic_run.labelled
    colours = label_colours(labelled)
    root = doc["nodes"][0]
    children = [doc["nodes"][i] for i in root["children"]]
    assert [c["name"] for c in children] == ["leaf 0", "leaf 1", "stem"]
    total_area = 0.0
    for child, label in zip(children, (0, 1, 2), strict=True):
        prim = doc["meshes"][child["mesh"]]["primitives"][0]
        faces = _accessor(doc, binary, prim["indices"]).reshape(-1, 3)
        positions = _accessor(doc, binary, prim["attributes"]["POSITION"]).astype(float)
        rgba = _accessor(doc, binary, prim["attributes"]["COLOR_0"])
        acc = doc["accessors"][prim["attributes"]["POSITION"]]
        np.testing.assert_allclose(acc["min"], positions.min(0))  # glTF requires exact min/max
        np.testing.assert_allclose(acc["max"], positions.max(0))
        assert len(faces) == int(np.sum(labelled.face_labels == label))
        tri = positions[faces]
        total_area += 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0],
                                                    tri[:, 2] - tri[:, 0]), axis=1).sum()
        # 8-bit colour quantisation: 1/255 tolerance
        np.testing.assert_allclose(rgba[:, :3] / 255.0, np.tile(colours[label], (len(rgba), 1)),
                                   atol=1.0 / 255 + 1e-9)
    # float32 positions of a ~200 mm plant: ~1e-5 mm precision, so 1e-2 mm² on the surface.
    assert total_area == pytest.approx(labelled.mesh.area(), abs=1e-2)
    # The root maps the stem's top (z = 200 mm, turntable Z up) to 0.2 m along glTF's +Y.
    m = np.array(root["matrix"]).reshape(4, 4).T  # column-major in glTF
    np.testing.assert_allclose(m @ [0, 0, 200, 1], [0, 0.2, 0, 1], atol=1e-12)
    assert np.linalg.det(m[:3, :3]) / 1e-9 == pytest.approx(1.0)  # rotation times 1e-3 scale


def _read_ply_faces(data: bytes) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Header lines, vertices and faces of a binary PLY, parsed from its header alone."""
    head, _, body = data.partition(b"end_header\n")
    lines = head.decode().splitlines()
    types = {"float": "<f4", "uchar": "u1", "int": "<i4"}
    elements, current = [], None
    for line in lines:
        words = line.split()
        if words[0] == "element":
            current = (words[1], int(words[2]), [])
            elements.append(current)
        elif words[0] == "property" and words[1] == "list":
            current[2].append(("n", types[words[2]]))
            current[2].append((words[4], types[words[3]], (3,)))  # triangles
        elif words[0] == "property":
            current[2].append((words[2], types[words[1]]))
    (_, nv, vdt), (_, nf, fdt) = elements
    vertices = np.frombuffer(body, dtype=vdt, count=nv)
    faces = np.frombuffer(body, dtype=fdt, count=nf, offset=vertices.nbytes)
    return lines, vertices, faces


def test_ply_carries_colours_and_labels_in_one_file(synthetic_run):
    (path,) = build("ply", synthetic_run).export(synthetic_run)
    lines, vertices, faces = _read_ply_faces(path.read_bytes())
    labelled = synthetic_run.labelled
    assert len(faces) == len(labelled.mesh.faces)
    # leaf faces carry the traits table's leaf id, the stem -1; organ 1 leaf, 2 stem
    is_leaf = np.isin(labelled.face_labels, labelled.leaf_labels)
    np.testing.assert_array_equal(faces["leaf_id"], np.where(is_leaf, labelled.face_labels, -1))
    np.testing.assert_array_equal(faces["organ"], np.where(is_leaf, 1, 2))
    rgb = np.stack([vertices["red"], vertices["green"], vertices["blue"]], axis=1) / 255.0
    got = _face_colours_of(rgb, faces["vertex_indices"])
    np.testing.assert_allclose(got, face_colours(labelled), atol=1.0 / 255 + 1e-9)
    assert any("organ: 0 unassigned, 1 leaf, 2 stem, 3 pot, 4 debris" in ln for ln in lines)


def test_glb_is_read_by_another_implementation(synthetic_run):
    """Assimp (through Open3D) reads our GLB: same face count and leaf colours."""
    import open3d as o3d

    (path,) = build("glb", synthetic_run).export(synthetic_run)
    m = o3d.io.read_triangle_mesh(str(path))
    assert len(m.triangles) == len(synthetic_run.labelled.mesh.faces)
    got = _face_colours_of(np.asarray(m.vertex_colors), np.asarray(m.triangles))
    np.testing.assert_allclose(got, face_colours(synthetic_run.labelled), atol=1.0 / 255 + 1e-9)


def test_mesh_exporters_fall_back_to_the_plain_mesh_and_skip_without_one(synthetic_run):
    plain = RunResult(synthetic_run.run_dir, synthetic_run.recipe, synthetic_run.scan,
                      mesh=synthetic_run.mesh)
    (path,) = build("ply", plain).export(plain)
    assert path.exists()
    nothing = RunResult(synthetic_run.run_dir / "empty", synthetic_run.recipe, synthetic_run.scan)
    for name in ("ply", "obj", "glb", "csv", "colmap"):
        assert build(name, nothing).export(nothing) == []


def test_csv_and_parquet_hold_the_traits(synthetic_run):
    pa = pytest.importorskip("pyarrow.parquet", reason="pyarrow not installed: no Parquet")
    paths = build("csv", synthetic_run).export(synthetic_run)
    names = sorted(p.name for p in paths)
    assert names == ["plant_traits.json", "traits.csv", "traits.parquet"]
    back = Traits.load(synthetic_run.run_dir / "traits.csv",
                       synthetic_run.run_dir / "plant_traits.json")
    for a, b in zip(back.leaves, synthetic_run.traits.leaves, strict=True):
        # CSV keeps 4 decimals: 5e-5 mm rounding.
        assert a.leaf_id == b.leaf_id and abs(a.area_mm2 - b.area_mm2) <= 5e-5
    assert back.plant["leaf_count"] == 2
    table = pa.read_table(synthetic_run.run_dir / "traits.parquet").to_pydict()
    assert table["plant_id"] == [HOSTILE_ID] * 2
    assert table["recipe"] == [HOSTILE_RECIPE] * 2
    np.testing.assert_allclose(table["area_mm2"], [x.area_mm2 for x in synthetic_run.traits.leaves])
    np.testing.assert_allclose(table["plant_height_mm"], [200.0, 200.0])
    # counts are integers in the file, not floats
    assert table["plant_leaf_count"] == [2, 2]
    schema = pa.read_schema(synthetic_run.run_dir / "traits.parquet")
    assert str(schema.field("plant_leaf_count").type) == "int64"
    assert str(schema.field("leaf_id").type) == "int64"


def _qvec_to_rotmat(q):
    """COLMAP's own formula (scripts/python/read_write_model.py), written out independently."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * z * x + 2 * w * y],
        [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
        [2 * z * x - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y]])


def test_colmap_model_reprojects_like_our_cameras(synthetic_run):
    """Project the plant with COLMAP's RADIAL model from the exported text files; the pixels
    must be ours + 0.5 (COLMAP's pixel-centre convention), to 1e-6 px (text keeps 17 digits)."""
    paths = build("colmap", synthetic_run).export(synthetic_run)
    assert [p.name for p in paths] == ["cameras.txt", "images.txt", "points3D.txt"]
    cams = {}
    for line in paths[0].read_text().splitlines():
        if line and not line.startswith("#"):
            cid, model, w, h, *params = line.split()
            assert model == "RADIAL" and (int(w), int(h)) == (320, 240)
            cams[int(cid)] = [float(p) for p in params]
    lines = [ln for ln in paths[1].read_text().splitlines() if not ln.startswith("#")]
    image_lines = lines[0::2]
    views = {v.index: v for v in synthetic_run.scan.views_by_role("plant")}
    assert len(image_lines) == len(views) == 8
    points = synthetic_run.labelled.mesh.vertices
    for line in image_lines:
        image_id, *vals = line.split()
        q, t = np.array(vals[:4], float), np.array(vals[4:7], float)
        cam_id, name = int(vals[7]), vals[8]
        view = views[int(image_id) - 1]
        assert name == view.file
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[0] >= 0
        f, cx, cy, k1, k2 = cams[cam_id]
        xc = points @ _qvec_to_rotmat(q).T + t
        u, v = xc[:, 0] / xc[:, 2], xc[:, 1] / xc[:, 2]
        r2 = u * u + v * v
        radial = 1 + k1 * r2 + k2 * r2 * r2
        colmap_px = np.column_stack([f * u * radial + cx, f * v * radial + cy])
        ours = synthetic_run.calibration.camera_for_view(view).project(points)
        np.testing.assert_allclose(colmap_px - 0.5, ours, atol=1e-6)


def test_truth_leaves_are_paired_by_position_not_by_id(synthetic_run):
    truth = read_truth_traits(synthetic_run.scan.ground_truth_dir)
    match = match_leaves(synthetic_run.traits, truth, synthetic_run.labelled,
                         synthetic_run.scan.ground_truth_dir)
    # The fixture's truth swapped the ids: our leaf 0 is truth leaf 1.
    assert sorted((m.leaf_id, t.leaf_id) for m, t in match.pairs) == [(0, 1), (1, 0)]
    assert match.unmatched_measured == match.unmatched_truth == 0


def test_report_is_self_contained_escaped_and_has_every_section(synthetic_run):
    (path,) = build("html-report", synthetic_run).export(synthetic_run)
    text = path.read_text()
    assert path.name == "report.html"
    for section in ("plant3d", "traits", "truth", "calibration", "silhouettes", "timings"):
        assert f'<section id="{section}">' in text
    # Offline: plotly.js inline once; outside it, no script source and no URL at all.
    from plotly.offline import get_plotlyjs

    assert text.count(get_plotlyjs()) == 1
    rest = text.replace(get_plotlyjs(), "")
    assert "<script src" not in rest and "http://" not in rest and "https://" not in rest
    assert text.count("data:image/jpeg;base64,") == 6  # default thumbnails
    # User text only escaped: the hostile id/recipe never appear raw.
    assert '<script>alert("x")' not in text and "<img src=x" not in text
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; plant-7" in text
    assert "&lt;b&gt;not bold&lt;/b&gt;" in text  # calibrator text too
    # the measurer's quality column and its warnings, escaped
    plain = text.replace(' class=""', "")
    assert "<th>thick area (%)</th>" in plain and "<td>20.0</td>" in plain
    assert "<li>leaf 0: 20 % &lt;thick&gt; (phantom volume)</li>" in text
    # ε of length: leaf 0 (40 mm semi-axis) measured 5 % long, leaf 1 exact -> 2.5 %.
    assert "<td>length</td><td>2.5%</td>" in text.replace(' class=""', "").replace(' class="l"', "")


def test_report_of_a_partial_run_shows_what_exists(synthetic_run):
    """Only traits (e.g. a run whose earlier stages were cached elsewhere): no 3D, no images."""
    partial = RunResult(synthetic_run.run_dir, synthetic_run.recipe, synthetic_run.scan,
                        traits=synthetic_run.traits)
    (path,) = HtmlReportExporter().export(partial)
    text = path.read_text()
    assert '<section id="traits">' in text and '<section id="truth">' in text
    for absent in ("plant3d", "calibration", "silhouettes", "timings"):
        assert f'<section id="{absent}">' not in text
    # Without the labelled mesh the pairing falls back to leaf ids (swapped here on purpose).
    assert "same leaf id" in text


def test_report_survives_a_missing_image(synthetic_run):
    view = synthetic_run.silhouettes[0].view
    synthetic_run.scan.path_of(view).unlink()
    (path,) = HtmlReportExporter().export(synthetic_run)
    text = path.read_text()
    assert "is missing" in text and text.count("data:image/jpeg;base64,") == 5


def test_view_decimation_keeps_the_shape():
    """The 3D view of a dense mesh is decimated to its face budget, its area kept within 2 %
    (vertex clustering of a smooth sphere loses little surface)."""
    import open3d as o3d
    from plantscan_report.html_report import _decimate

    from plantscan_core.data import Mesh

    sphere = Mesh.from_open3d(o3d.geometry.TriangleMesh.create_sphere(50.0, resolution=60))
    small, groups = _decimate(sphere, 1000)
    assert len(sphere.faces) > 5000 and len(small.faces) <= 1000 and len(groups) == len(small.faces)
    assert small.area() == pytest.approx(sphere.area(), rel=0.02)


@pytest.mark.parametrize("cell", [3.0, 7.3])
def test_vertex_clustering_is_open3ds(cell):
    """One group: the same vertices and faces as Open3D's simplify_vertex_clustering."""
    import open3d as o3d
    from plantscan_report.html_report import cluster_vertices

    sphere = o3d.geometry.TriangleMesh.create_sphere(50.0, resolution=60)
    v, f, _ = cluster_vertices(np.asarray(sphere.vertices), np.asarray(sphere.triangles),
                               np.zeros(len(sphere.triangles), int), cell)
    ref = sphere.simplify_vertex_clustering(voxel_size=cell)
    rv, rf = np.asarray(ref.vertices), np.asarray(ref.triangles)

    def face_set(vertices, faces):  # faces as sets of rounded corner positions
        return sorted(tuple(sorted(map(tuple, np.round(vertices[t], 6)))) for t in faces)

    assert len(v) == len(rv) and len(f) == len(rf)
    assert face_set(v, f) == face_set(rv, rf)


def test_vertex_clustering_keeps_groups_apart():
    """Two groups (leaf halves of a sphere) sharing their seam: no clustered vertex is used
    by both, and each keeps its area within 3 % (a coarse grid on a smooth surface)."""
    import open3d as o3d
    from plantscan_report.html_report import cluster_vertices

    from plantscan_core.data import Mesh

    sphere = Mesh.from_open3d(o3d.geometry.TriangleMesh.create_sphere(50.0, resolution=60))
    groups = (sphere.vertices[sphere.faces].mean(axis=1)[:, 0] > 0).astype(int) + 4
    v, f, g = cluster_vertices(sphere.vertices, sphere.faces, groups, 4.0)
    assert set(g.tolist()) == {4, 5} and len(f) < len(sphere.faces) / 2
    assert not set(f[g == 4].ravel().tolist()) & set(f[g == 5].ravel().tolist())
    for label in (4, 5):
        before = Mesh(sphere.vertices, sphere.faces[groups == label]).area()
        assert Mesh(v, f[g == label]).area() == pytest.approx(before, rel=0.03)


def test_plotly_bundle_cannot_close_the_script_element():
    from plotly.offline import get_plotlyjs

    assert "</script" not in get_plotlyjs().lower()


def test_unknown_params_are_rejected(synthetic_run):
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        build("html-report", synthetic_run, {"thumbnail": 3})
    with pytest.raises(ValidationError):
        build("html-report", synthetic_run, {"thumbnail_reduce": 3})


def test_exported_files_stay_in_the_run_folder(synthetic_run):
    for name in ("ply", "obj", "glb", "csv", "colmap", "html-report"):
        for p in build(name, synthetic_run).export(synthetic_run):
            assert Path(p).resolve().is_relative_to(synthetic_run.run_dir.resolve())


def test_parquet_rows_carry_the_scan_time_and_the_plants_metadata(synthetic_run):
    pa = pytest.importorskip("pyarrow.parquet", reason="pyarrow not installed: no Parquet")
    synthetic_run.info = {
        "scan_record": {"acquired_at": "2026-05-06T08:30:00+00:00"},
        "metadata": {"plant": {"id": "P17", "genotype": "Col-0", "treatment": "drought",
                               "replicate": 2, "sowing_date": "2026-05-01",
                               "factors": {"watering": "30%"}},
                     "experiment": {"study_id": "drought-2026"}}}
    build("csv", synthetic_run).export(synthetic_run)
    table = pa.read_table(synthetic_run.run_dir / "traits.parquet").to_pydict()
    n = len(synthetic_run.traits.leaves)
    assert table["plant_id"] == ["P17"] * n  # the resolved id (sample sheet) wins
    assert table["scan_time"] == ["2026-05-06T08:30:00+00:00"] * n
    assert (table["study_id"], table["genotype"], table["replicate"]) == \
        (["drought-2026"] * n, ["Col-0"] * n, [2] * n)
    assert table["factor.watering"] == ["30%"] * n
