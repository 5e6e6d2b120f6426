"""Processing orchestrator: caching keyed by inputs + params, run.json, errors, decode counts."""

from __future__ import annotations

import json
import threading
import types

import numpy as np
import pytest

from plantscan_core import iostats
from plantscan_core.data import Volume
from plantscan_core.errors import StageError
from plantscan_core.hookspecs import hookimpl
from plantscan_core.pipeline import process, resolve_reduce
from plantscan_core.recipe import validate_recipe
from plantscan_core.runfolder import read_mask
from plantscan_core.stages import Reconstructor, StageParams
from plantscan_core.testing import TINY_CALLS as CALLS
from plantscan_core.testing import (
    TINY_SPHERE_CENTRE_MM,
    TINY_SPHERE_RADIUS_MM,
    TinyDarkSegmenter,
    TinyExactCalibrator,
    stages_plugin,
    tiny_camera,
    tiny_processing_plugin,
    tiny_recipe,
)

SEEN: dict[str, object] = {}


class CountingReconstructor(Reconstructor):
    name = "tiny-count"

    class Params(StageParams):
        fail: bool = False

    def reconstruct(self, silhouettes, calibration):
        SEEN["calibration"] = calibration
        if self.params.fail:
            raise ValueError("bounding box clips the plant")
        area = float(np.mean([s.mask.mean() for s in silhouettes]))
        # what a stage says of its work (counts, warnings) goes to run.json
        self.report.count("views", len(silhouettes))
        self.report.warn("few-views", f"{len(silhouettes)} views", view=silhouettes[0].view.index)
        return Volume(np.full((2, 2, 2), area, np.float32), np.zeros(3), 1.0)


@pytest.fixture
def manager(tiny_rig_manager):
    tiny_rig_manager.register(tiny_processing_plugin, name="tiny-processing")
    tiny_rig_manager.register(stages_plugin(CountingReconstructor), name="tiny-reconstructor")
    CALLS.clear()
    return tiny_rig_manager


def _recipe(manager, **seg_params):
    raw = tiny_recipe()
    raw["calibrate"] = {"plugin": "tiny-exact"}
    raw["segment"] = {"plugin": "tiny-dark", "params": seg_params}
    raw["reconstruct"] = {"plugin": "tiny-count"}
    return validate_recipe(raw, manager.registry), raw


def test_masks_are_right_and_cache_follows_parameters(tiny_scan, manager, tmp_path):
    recipe, raw = _recipe(manager)
    run = tmp_path / "run"
    result = process(tiny_scan.root, recipe, run, manager, raw_recipe=raw)
    plant_views = tiny_scan.views_by_role("plant")
    assert CALLS == {"calibrate": 1, "segment": len(plant_views)}
    # The dark sphere's mask matches its exact projection (a disc) within the rim pixels.
    sil = result.silhouettes[0]
    assert read_mask(run / "masks" / f"{sil.view.index:05d}.png").tolist() == sil.mask.tolist()
    cam = tiny_camera(sil.view.camera, 0.0, sil.view.commanded_angle_deg, (96, 64))
    r = cam.model.f * TINY_SPHERE_RADIUS_MM / cam.depth(np.array([TINY_SPHERE_CENTRE_MM]))[0]
    # Within one ring of rim pixels (2 pi r) of the disc's exact area: pixels are all-or-nothing.
    assert abs(sil.mask.sum() - np.pi * r * r) <= 2 * np.pi * r
    info = json.loads((run / "run.json").read_text())
    assert info["stages"]["segment"]["plugin"] == "tiny-dark"
    assert info["stages"]["segment"]["params"] == {"threshold": 100}
    assert set(info["timings_s"]) >= {"calibrate", "segment", "reconstruct", "total"}
    assert {"calibrate", "segment"} <= set(info["input_hashes"])  # the scan files they read
    said = {"counts": {"views": len(plant_views)}, "figures": {},
            "warnings": [{"code": "few-views", "message": f"{len(plant_views)} views",
                          "view": plant_views[0].index}]}
    assert info["stages"]["reconstruct"]["info"] == said
    assert result.reports["reconstruct"].warnings[0].view == plant_views[0].index
    # the run's own word on segmentation: the views and the decode reduction
    assert info["stages"]["segment"]["info"]["counts"] == {"views": len(plant_views)}
    assert info["stages"]["segment"]["info"]["figures"] == {"reduce": 1}

    # Same recipe again: everything comes from the cache, and the stage's report with it.
    again = process(tiny_scan.root, recipe, run, manager, raw_recipe=raw)
    assert CALLS == {"calibrate": 1, "segment": len(plant_views)}
    info = json.loads((run / "run.json").read_text())
    assert all(info["stages"][s]["cached"] for s in ("calibrate", "segment", "reconstruct"))
    assert info["stages"]["reconstruct"]["info"] == said
    assert again.reports["reconstruct"] == result.reports["reconstruct"]

    # New segmentation parameter: segmentation and what follows recompute, calibration does not.
    recipe2, raw2 = _recipe(manager, threshold=60)
    process(tiny_scan.root, recipe2, run, manager, raw_recipe=raw2)
    assert CALLS == {"calibrate": 1, "segment": 2 * len(plant_views)}
    info = json.loads((run / "run.json").read_text())
    assert info["stages"]["calibrate"]["cached"] is True
    assert info["stages"]["segment"]["cached"] is False
    assert info["stages"]["reconstruct"]["cached"] is False


def test_changed_input_image_invalidates_the_cache(tiny_scan, manager, tmp_path):
    import os

    recipe, raw = _recipe(manager)
    process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    v = tiny_scan.views_by_role("plant")[0]
    path = tiny_scan.path_of(v)
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10_000_000))
    process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    assert CALLS["calibrate"] == 1
    assert CALLS["segment"] == 2 * len(tiny_scan.views_by_role("plant"))


def test_a_calibrator_reading_the_plant_photos_is_redone_when_they_change(
        tiny_scan, manager, tmp_path):
    """A calibrator that declares ``input_roles`` (the sfm calibrator reads the plant
    photos) has them in its cache key: new plant photos redo it; the default
    fingerprints only the calibration views (the test above: calibrated once)."""
    import os

    from plantscan_core.testing import TinyExactCalibrator

    class PlantPhotoCalibrator(TinyExactCalibrator):
        name = "tiny-from-plants"

        def input_roles(self, scan):
            return ["plant"]

    manager.register(stages_plugin(PlantPhotoCalibrator), name="tiny-from-plants")
    recipe, raw = _recipe(manager)
    raw["calibrate"] = {"plugin": "tiny-from-plants"}
    recipe = validate_recipe(raw, manager.registry)
    process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    assert CALLS["calibrate"] == 1  # nothing changed: cached
    path = tiny_scan.path_of(tiny_scan.views_by_role("plant")[0])
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10_000_000))
    process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    assert CALLS["calibrate"] == 2


def test_a_stage_is_redone_when_a_file_it_reads_changes_content(tiny_scan, manager, tmp_path):
    """A stage that declares ``input_files`` (a model file, an imported calibration) has
    their content in its cache key: the same name with new content (a model retrained
    under its old name) redoes it; a new modification time alone does not."""
    import os

    from plantscan_core.testing import TinyExactCalibrator

    model = tmp_path / "model.bin"
    model.write_bytes(b"first training")

    class ModelCalibrator(TinyExactCalibrator):
        name = "tiny-with-model"

        def input_files(self, scan):
            return [model]

    manager.register(stages_plugin(ModelCalibrator), name="tiny-with-model")
    recipe, raw = _recipe(manager)
    raw["calibrate"] = {"plugin": "tiny-with-model"}
    recipe = validate_recipe(raw, manager.registry)
    process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    st = model.stat()
    os.utime(model, ns=(st.st_atime_ns, st.st_mtime_ns + 10_000_000))
    process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    assert CALLS["calibrate"] == 1  # same content: cached
    model.write_bytes(b"second training")
    process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    assert CALLS["calibrate"] == 2


def test_each_image_is_decoded_once_per_run(tiny_scan, manager, tmp_path):
    recipe, raw = _recipe(manager)
    iostats.reset()
    process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    assert iostats.decodes, "nothing decoded"
    assert max(iostats.decodes.values()) == 1, iostats.decodes.most_common(3)
    plant_and_bg = [v for v in tiny_scan.views if v.role in ("plant", "background")]
    assert len(iostats.decodes) == len(plant_and_bg)


def test_reduced_decoding_gives_half_size_masks_and_a_matching_calibration(
        tiny_scan, manager, tmp_path):
    recipe, raw = _recipe(manager)
    full = process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    raw["segment"]["reduce"] = 2
    recipe2 = validate_recipe(raw, manager.registry)
    iostats.reset()
    half = process(tiny_scan.root, recipe2, tmp_path / "run", manager, raw_recipe=raw)
    info = json.loads((tmp_path / "run/run.json").read_text())
    # The reduction is part of the segmentation's cache key; calibration is reused.
    assert info["stages"]["segment"]["cached"] is False
    assert info["stages"]["calibrate"]["cached"] is True
    assert max(iostats.decodes.values()) == 1
    s_full, s_half = full.silhouettes[0], half.silhouettes[0]
    assert s_half.shape == (32, 48)
    # Same disc at half the size: area / 4 within a ring of rim pixels of the small disc.
    r_half = np.sqrt(s_full.mask.sum() / np.pi) / 2
    assert abs(s_half.mask.sum() - s_full.mask.sum() / 4) <= 2 * np.pi * r_half
    # The reconstructor sees cameras for the half-size masks: the sphere centre projects
    # onto the half-size disc's centroid (within half a pixel: rim pixels are all-or-nothing).
    cal = SEEN["calibration"]
    cam = cal.camera_for_view(s_half.view)
    assert (cam.model.width, cam.model.height) == (48, 32)
    uv = cam.project(np.array([TINY_SPHERE_CENTRE_MM]))[0]
    rows, cols = np.nonzero(s_half.mask)
    assert np.hypot(cols.mean() - uv[0], rows.mean() - uv[1]) < 0.5


@pytest.mark.parametrize("size, expected", [
    ((5184, 3456), 2), ((3456, 5184), 2), ((4800, 3200), 2), ((4799, 3199), 1),
    ((3000, 2000), 1), ((640, 427), 1), ((9700, 6500), 4), ((19200, 100), 8)])
def test_auto_reduce_keeps_the_long_side_at_least_2400_px(tmp_path, size, expected):
    from PIL import Image

    path = tmp_path / "img.jpg"
    Image.new("L", size).save(path)  # header is what counts; a black JPEG is small
    assert resolve_reduce("auto", [path]) == expected
    assert resolve_reduce(2, [path]) == 2  # a number is used as given


def test_auto_reduce_skips_an_unreadable_header(tmp_path):
    # The segment stage decodes the broken file and names it; the size comes from the next.
    from PIL import Image

    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"not a jpeg")
    good = tmp_path / "good.jpg"
    Image.new("L", (5184, 3456)).save(good)
    assert resolve_reduce("auto", [broken, good]) == 2
    assert resolve_reduce("auto", [broken]) == 1


def test_stage_failure_is_wrapped_and_earlier_results_are_kept(tiny_scan, manager, tmp_path):
    raw = tiny_recipe()
    raw.update(calibrate={"plugin": "tiny-exact"}, segment={"plugin": "tiny-dark"},
               reconstruct={"plugin": "tiny-count", "params": {"fail": True}})
    recipe = validate_recipe(raw, manager.registry)
    with pytest.raises(StageError, match=r"reconstruct \(tiny-count\): bounding box clips") as e:
        process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    assert isinstance(e.value.__cause__, ValueError)
    assert (tmp_path / "run/calibration.yaml").exists()
    assert len(list((tmp_path / "run/masks").glob("*.png"))) == len(
        tiny_scan.views_by_role("plant"))
    assert json.loads((tmp_path / "run/run.json").read_text())["stages"]["segment"]["cached"] \
        is False


def test_observer_hooks_see_every_stage(tiny_scan, manager, tmp_path):
    seen = []
    obs = types.SimpleNamespace()

    @hookimpl
    def plantscan_after_stage(stage, plugin, context, seconds, cached):
        seen.append((stage, plugin.name, cached))

    obs.plantscan_after_stage = plantscan_after_stage
    manager.register(obs, name="observer")
    try:
        recipe, raw = _recipe(manager)
        process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    finally:
        manager.unregister(obs)
    # calibrate and segment may end in either order (they run side by side); reconstruct
    # needs both
    assert sorted(seen[:2]) == [("calibrator", "tiny-exact", False),
                                ("segmenter", "tiny-dark", False)]
    assert seen[2:] == [("reconstructor", "tiny-count", False)]


class RendezvousCalibrator(TinyExactCalibrator):
    """Waits until segmentation has started (or fails): proves the two run side by side."""

    name = "tiny-rendezvous"

    class Params(StageParams):
        fail: bool = False

    def calibrate(self, scan):
        # A generous bound: segmentation of the tiny scan starts within milliseconds when
        # the steps overlap; run one after the other, segmentation never starts first.
        assert SEGMENT_STARTED.wait(30), "segment did not start while calibrate ran"
        if self.params.fail:
            raise ValueError("no board found")
        return super().calibrate(scan)


SEGMENT_STARTED = threading.Event()


class BrokenSegmenter(TinyDarkSegmenter):
    name = "tiny-broken"

    def segment(self, image, background, view=None):
        raise ValueError("segment broke")


@pytest.fixture
def rendezvous(manager):
    obs = types.SimpleNamespace()

    @hookimpl
    def plantscan_before_stage(stage, plugin, context):
        if stage == "segmenter":
            SEGMENT_STARTED.set()

    obs.plantscan_before_stage = plantscan_before_stage
    SEGMENT_STARTED.clear()
    manager.register(obs, name="rendezvous")
    manager.register(stages_plugin(RendezvousCalibrator, BrokenSegmenter),
                     name="tiny-rendezvous")
    yield manager
    manager.unregister(obs)


@pytest.mark.parametrize("fail", [None, "calibrate", "segment"])
def test_calibrate_runs_beside_segment(tiny_scan, rendezvous, tmp_path, fail):
    """Calibrate (reads only the scan) runs while segment runs; a failure of either is raised
    once both have ended, and the other's result is kept and reused by the next run."""
    raw = tiny_recipe()
    raw.update(calibrate={"plugin": "tiny-rendezvous", "params": {"fail": fail == "calibrate"}},
               segment={"plugin": "tiny-broken" if fail == "segment" else "tiny-dark"},
               reconstruct={"plugin": "tiny-count"})
    recipe = validate_recipe(raw, rendezvous.registry)
    run = tmp_path / "run"
    if fail is None:
        result = process(tiny_scan.root, recipe, run, rendezvous, raw_recipe=raw)
        assert result.volume is not None
        assert CALLS == {"calibrate": 1, "segment": len(tiny_scan.views_by_role("plant"))}
        info = json.loads((run / "run.json").read_text())
        assert info["side_by_side"] == [["calibrate", "segment"]]
        return
    with pytest.raises(StageError, match="no board found" if fail == "calibrate"
                       else "segment broke"):
        process(tiny_scan.root, recipe, run, rendezvous, raw_recipe=raw)
    info = json.loads((run / "run.json").read_text())
    if fail == "calibrate":  # the masks were made and kept
        assert len(list((run / "masks").glob("*.png"))) == len(tiny_scan.views_by_role("plant"))
        assert "cached" in info["stages"]["segment"]
    else:  # the calibration was made and kept
        assert (run / "calibration.yaml").exists()
        assert info["stages"]["calibrate"]["cached"] is False


@pytest.mark.parametrize("bad_images", ["error", "skip"])
def test_truncated_plant_image_is_named_or_skipped(tiny_scan, manager, tmp_path, capsys,
                                                   bad_images):
    """A truncated image stops the run naming it, or (segment.bad_images: skip) is left out
    with a warning and a count in the segment report, on a cached run too."""
    recipe, raw = _recipe(manager)
    raw["segment"]["bad_images"] = bad_images
    recipe = validate_recipe(raw, manager.registry)
    victim = tiny_scan.views_by_role("plant")[2]
    image = tiny_scan.root / victim.file
    image.write_bytes(image.read_bytes()[:200])
    if bad_images == "error":
        with pytest.raises(StageError, match=rf"{victim.file}: cannot decode image"):
            process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
        return
    n = len(tiny_scan.views_by_role("plant"))
    for cached in (False, True):
        result = process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
        assert result.info["stages"]["segment"]["cached"] is cached
        assert len(result.silhouettes) == n - 1
        assert victim.index not in [s.view.index for s in result.silhouettes]
        said = result.info["stages"]["segment"]["info"]
        assert said["counts"]["views"] == n - 1 and said["counts"]["views_skipped"] == 1
        assert [(w["code"], w["view"]) for w in said["warnings"]] == [("bad-image", victim.index)]
        assert said["warnings"][0]["message"].startswith(
            f"view {victim.index} ({victim.file}) skipped: ")
        if not cached:
            assert f"view {victim.index} ({victim.file}) skipped" in capsys.readouterr().err


def test_plant_image_of_another_size_than_its_cameras_others(tiny_scan, manager, tmp_path):
    import cv2

    recipe, raw = _recipe(manager)
    victim = tiny_scan.views_by_role("plant")[3]
    image = tiny_scan.root / victim.file
    cv2.imwrite(str(image), cv2.resize(cv2.imread(str(image)), (80, 60)))
    with pytest.raises(StageError, match=rf"px but view \d+ of the same camera "
                                         rf"'{victim.camera}' is") as info:
        process(tiny_scan.root, recipe, tmp_path / "run", manager, raw_recipe=raw)
    # Views decode in parallel: the odd one is named first or second, beside a good one.
    assert "80x60 px" in str(info.value) and "96x64 px" in str(info.value)
    assert f"view {victim.index} " in str(info.value)
