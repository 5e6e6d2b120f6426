"""Processing orchestrator: runs a recipe's stages over a scan folder into a run folder.

Each stage's result is cached in the run folder, keyed by the stage's plugin,
version, parameters and the keys of its inputs: changing segmentation
parameters recomputes segmentation and what follows, never calibration.
Input files are fingerprinted by (path, size, modification time) — cheap on
hundreds of 18 MP images — and the scan's ``views.jsonl`` by content.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import resource
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from plantscan_core import __version__
from plantscan_core.data import (
    Calibration,
    LabelledMesh,
    Mesh,
    Silhouette,
    Silhouettes,
    Traits,
    ViewRecord,
    Volume,
    plain,
)
from plantscan_core.errors import DataError, PlantScanError, StageError
from plantscan_core.plugins import PluginManager
from plantscan_core.recipe import PROCESSING_SECTIONS, Recipe
from plantscan_core.scanfolder import ScanFolder, atomic_write_bytes, atomic_write_text, now_iso
from plantscan_core.stages import RunResult, Stage, StageContext

CACHE_DIR = "cache"
MASKS_DIR = "masks"


# --------------------------------------------------------------------------- fingerprints
def _sha(obj: Any) -> str:
    return hashlib.sha256(json.dumps(plain(obj), sort_keys=True, default=str).encode()).hexdigest()


def file_fingerprint(path: Path) -> str:
    """Cheap identity of an input file: name, size and modification time (ns)."""
    st = Path(path).stat()
    return f"{Path(path).name}:{st.st_size}:{st.st_mtime_ns}"


def views_fingerprint(scan: ScanFolder, views: list[ViewRecord]) -> str:
    return _sha([[v.to_dict(), file_fingerprint(scan.path_of(v))] for v in views])


# --------------------------------------------------------------------------- masks
def write_mask(path: Path, mask: np.ndarray) -> None:
    """Store a bool mask as a 1-bit PNG (reads back as 0/255 gray), atomically.

    Bi-level PNG: 5x faster to encode than 8-bit (8 vs 41 ms at 4.5 MP,
    measured) and a third of the size; any PNG reader opens it.
    """
    import cv2

    ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255,
                           [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise DataError(f"{path}: could not encode mask")
    atomic_write_bytes(path, buf.tobytes())


def read_mask(path: Path) -> np.ndarray:
    """Read a 0/255 (or 0/1) mask PNG as ``(H, W) bool``; ``DataError`` naming the file."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DataError(f"{path}: mask missing or unreadable")
    return img > 0


# segment.reduce "auto" keeps the long side of the images the segmenter sees at least this
# long: on the 18 MP virtual paper-72 scan 1296 px masks (1/4) merged two leaf pairs at 512^3
# where 2592 px ones (1/2) found all 12 (docs/decisions.md).
AUTO_REDUCE_MIN_LONG_SIDE_PX = 2400


def resolve_reduce(reduce: int | str, image_paths: Sequence[Path]) -> int:
    """``segment.reduce`` as a number; "auto" from the size in the first readable header.

    A file whose header cannot be read is skipped here: decoding it in the
    segment stage names it (and the stage) properly.  No readable header: 1.
    """
    if reduce != "auto":
        return int(reduce)
    from PIL import Image, UnidentifiedImageError

    for path in image_paths:
        try:
            with Image.open(path) as im:  # reads the header only
                long_side = max(im.size)
        except (OSError, UnidentifiedImageError):
            continue
        for r in (8, 4, 2):
            if long_side / r >= AUTO_REDUCE_MIN_LONG_SIDE_PX:
                return r
        return 1
    return 1


def calibration_for_masks(calibration: Calibration, silhouettes: Silhouettes,
                          reduce: int) -> Calibration:
    """The calibration whose camera models match masks taken at 1/``reduce`` size.

    Masks decoded at a reduced size (``segment.reduce``) keep the lens but not
    its pixel units: each camera model is scaled by ``1/reduce`` (pixel centres
    kept, ``CameraModel.scaled``) and its image size set to the masks' own,
    which decoders round up (5184 -> 2592, 427 -> 214 at 1/2).
    """
    if reduce == 1:
        return calibration
    sizes = {s.view.camera: s.shape for s in silhouettes}
    models = dict(calibration.models)
    for name, (h, w) in sizes.items():
        if name not in models:
            continue  # the reconstructor names the view whose camera is missing
        m = models[name]
        if m.width and m.height and (-(-m.width // reduce), -(-m.height // reduce)) != (w, h):
            raise DataError(
                f"camera {name!r}: masks are {w}x{h} px, but 1/{reduce} of the calibrated "
                f"{m.width}x{m.height} px images would be "
                f"{-(-m.width // reduce)}x{-(-m.height // reduce)}")
        models[name] = dataclasses.replace(m.scaled(1.0 / reduce), width=w, height=h)
    return dataclasses.replace(calibration, models=models)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (Linux reports kB, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


# --------------------------------------------------------------------------- the run
class Run:
    """One processing run (internal): stage execution, caching and run.json."""

    def __init__(
        self,
        scan: ScanFolder,
        recipe: Recipe,
        run_dir: Path,
        manager: PluginManager,
        raw_recipe: dict | None,
        overrides: list[str],
        progress: bool,
        workers: int | None,
    ) -> None:
        self.scan = scan
        self.recipe = recipe
        self.run_dir = Path(run_dir)
        self.manager = manager
        self.progress = progress
        self.reduce = 1  # segment.reduce as a number, set by the segment stage
        self.workers = workers or min(4, os.cpu_count() or 1)
        self.context = StageContext(recipe=recipe, scan=scan, run_dir=self.run_dir)
        self.result = RunResult(run_dir=self.run_dir, recipe=recipe, scan=scan)
        self.info: dict[str, Any] = {
            "format": "plantscan-run/1",
            "plantscan_version": __version__,
            "created": now_iso(),
            "scan": str(scan.root.resolve()),
            "plant_id": scan.info.get("plant_id", recipe.plant.id),
            "recipe": raw_recipe if raw_recipe is not None else recipe.model_dump(mode="json"),
            "overrides": list(overrides),
            "stages": {},
            "timings_s": {},
            "input_hashes": {},
        }
        self.result.info = self.info

    # ------------------------------------------------------------------ cache
    def _cache_path(self, stage: str) -> Path:
        return self.run_dir / CACHE_DIR / f"{stage}.json"

    def _cached(self, stage: str, key: str, outputs: list[Path]) -> dict | None:
        """The stage's cache entry when its last result is for ``key`` and on disk, else None."""
        p = self._cache_path(stage)
        if not p.exists() or not all(o.exists() for o in outputs):
            return None
        try:
            entry = json.loads(p.read_text())
        except (OSError, ValueError):
            return None
        return entry if isinstance(entry, dict) and entry.get("key") == key else None

    def _store_key(self, stage: str, key: str, notes: dict | None = None) -> None:
        entry = {"key": key, "at": now_iso(), **({"info": notes} if notes else {})}
        atomic_write_text(self._cache_path(stage), json.dumps(entry))

    # ------------------------------------------------------------------ stage runner
    def run_stage(
        self,
        section: str,
        inputs_key: str,
        outputs: list[Path],
        compute: Callable[[Stage], Any],
        load: Callable[[], Any],
        spec=None,
        stage: str | None = None,
    ) -> tuple[Any, str]:
        """Run (or load from cache) one stage; returns (result, cache key)."""
        stage = stage or PROCESSING_SECTIONS[section]
        spec = spec if spec is not None else getattr(self.recipe, section)
        plugin = self.manager.build(stage, spec.plugin, spec.params, self.context)
        key = _sha({"stage": stage, "plugin": spec.plugin, "version": plugin.version(),
                    "params": plugin.params.model_dump(mode="json"), "inputs": inputs_key})
        self.info["stages"][section] = {"plugin": spec.plugin, "version": plugin.version(),
                                        "params": plugin.params.model_dump(mode="json"),
                                        "key": key}
        entry = self._cached(section, key, outputs)
        cached = entry is not None
        self.manager.before_stage(stage, plugin, self.context)
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            if cached:
                value = load()
                notes = entry.get("info") or {}
            else:
                self._cache_path(section).unlink(missing_ok=True)
                value = compute(plugin)
                # what the plugin says of its work (counts, warnings): kept with the cache key
                # so that a cached stage reports it again
                notes = plain(getattr(plugin, "info", None) or {})
                self._store_key(section, key, notes)
        except BaseException as exc:
            self.manager.on_stage_error(stage, plugin, self.context, exc)
            self._write_info()
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            raise StageError(section, spec.plugin, str(exc) or type(exc).__name__) from exc
        seconds = time.perf_counter() - t0
        self.info["stages"][section]["cached"] = cached
        if notes:
            self.info["stages"][section]["info"] = notes
        self.info["timings_s"][section] = round(seconds, 4)
        self.info.setdefault("cpu_s", {})[section] = round(time.process_time() - c0, 4)
        self.info.setdefault("peak_rss_mb", {})[section] = round(peak_rss_mb(), 1)
        self.result.timings[section] = seconds
        self.manager.after_stage(stage, plugin, self.context, seconds, cached)
        self._write_info()
        return value, key

    def _write_info(self) -> None:
        atomic_write_text(self.run_dir / "run.json", json.dumps(plain(self.info), indent=2))

    # ------------------------------------------------------------------ stages
    def calibrate(self, calibration_path: Path | None) -> str:
        out = self.run_dir / "calibration.yaml"
        if calibration_path is not None:
            calibration = Calibration.load(calibration_path)
            calibration.save(out)
            key = _sha({"file": Path(calibration_path).read_bytes().hex()})
            self.info["stages"]["calibrate"] = {"plugin": "--calibration",
                                                "file": str(calibration_path), "key": key}
            self.result.calibration = calibration
            return key
        views = self.scan.views_by_role("calibration")
        inputs = views_fingerprint(self.scan, views)
        self.info["input_hashes"]["calibration_views"] = inputs

        def compute(plugin):
            c = plugin.calibrate(self.scan)
            c.save(out)
            return c

        self.result.calibration, key = self.run_stage(
            "calibrate", inputs, [out], compute, lambda: Calibration.load(out))
        return key

    def segment(self) -> str:
        views = self.scan.views_by_role("plant")
        if not views:
            raise DataError(f"{self.scan.root}: the scan has no plant views")
        backgrounds = {(v.camera, v.tilt_index): v for v in
                       reversed(self.scan.views_by_role("background"))}
        used_bg = sorted({(v.camera, v.tilt_index) for v in views} & set(backgrounds))
        inputs = _sha([views_fingerprint(self.scan, views),
                       views_fingerprint(self.scan, [backgrounds[k] for k in used_bg])])
        self.info["input_hashes"]["plant_views"] = inputs
        reduce = self.reduce = resolve_reduce(self.recipe.segment.reduce,
                                              [self.scan.path_of(v) for v in views[:8]])
        self.info["segment_reduce"] = reduce
        inputs = _sha([inputs, {"reduce": reduce}])
        mask_dir = self.run_dir / MASKS_DIR
        paths = [mask_dir / f"{v.index:05d}.png" for v in views]

        def compute(plugin):
            bg_images: dict[tuple[str, int], np.ndarray | None] = {}
            lock = threading.Lock()

            def background_for(v: ViewRecord) -> np.ndarray | None:
                k = (v.camera, v.tilt_index)
                with lock:
                    if k not in bg_images:
                        bg_images[k] = (self.scan.read_image(backgrounds[k], reduce=reduce)
                                        if k in backgrounds else None)
                    return bg_images[k]

            def one(i: int) -> Silhouette:
                v = views[i]
                image = self.scan.read_image(v, reduce=reduce)
                bg = background_for(v)
                if bg is not None and bg.shape != image.shape:
                    raise DataError(
                        f"{self.scan.path_of(v)}: image is {image.shape[1]}x{image.shape[0]} but "
                        f"its background plate {backgrounds[(v.camera, v.tilt_index)].file} is "
                        f"{bg.shape[1]}x{bg.shape[0]}")
                try:
                    mask = np.asarray(plugin.segment(image, bg, v), dtype=bool)
                except PlantScanError:
                    raise
                except Exception as exc:
                    raise DataError(f"view {v.index} ({v.file}): {exc}") from exc
                if mask.shape != image.shape[:2]:
                    raise DataError(f"view {v.index} ({v.file}): segmenter returned a mask of "
                                    f"shape {mask.shape}, image is {image.shape[:2]}")
                write_mask(paths[i], mask)
                return Silhouette(v, mask)

            mask_dir.mkdir(parents=True, exist_ok=True)
            return Silhouettes(self._map(one, len(views), "segmenting"))

        def load():
            return Silhouettes([Silhouette(v, read_mask(p)) for v, p in zip(views, paths)])

        self.result.silhouettes, key = self.run_stage("segment", inputs, paths, compute, load)
        return key

    def _map(self, fn: Callable[[int], Any], n: int, label: str) -> list[Any]:
        """Run ``fn(i)`` for i < n on a thread pool (OpenCV releases the GIL), in order."""
        results: list[Any] = [None] * n
        bar = None
        if self.progress:
            from rich.progress import Progress

            bar = Progress(transient=True)
            task = bar.add_task(label, total=n)
            bar.start()
        try:
            with ThreadPoolExecutor(max_workers=self.workers) as pool:
                futures = {pool.submit(fn, i): i for i in range(n)}
                for fut in futures:
                    results[futures[fut]] = fut.result()
                    if bar is not None:
                        bar.advance(task)
        finally:
            if bar is not None:
                bar.stop()
        return results

    def reconstruct(self, inputs: str) -> str:
        out = self.run_dir / "volume.npz"

        def compute(plugin):
            calibration = calibration_for_masks(self.result.calibration,
                                                self.result.silhouettes, self.reduce)
            v = plugin.reconstruct(self.result.silhouettes, calibration)
            v.save(out)
            self.info["reconstruct_stats"] = plain(v.stats)
            return v

        self.result.volume, key = self.run_stage("reconstruct", inputs, [out], compute,
                                                 lambda: Volume.load(out))
        return key

    def mesh(self, inputs: str) -> str:
        out, ply = self.run_dir / "mesh.npz", self.run_dir / "mesh.ply"

        def compute(plugin):
            m = plugin.mesh(self.result.volume)
            m.save(out)
            write_ply(ply, m)
            return m

        self.result.mesh, key = self.run_stage("mesh", inputs, [out], compute,
                                               lambda: Mesh.load(out))
        return key

    def segment_mesh(self, inputs: str) -> str:
        out, ply = self.run_dir / "labelled.npz", self.run_dir / "labelled.ply"

        def compute(plugin):
            lm = plugin.segment(self.result.mesh)
            lm.save(out)
            write_ply(ply, lm.mesh, lm.face_labels)
            return lm

        self.result.labelled, key = self.run_stage("segment_mesh", inputs, [out], compute,
                                                   lambda: LabelledMesh.load(out))
        return key

    def measure(self, inputs: str) -> str:
        out, plant = self.run_dir / "traits.csv", self.run_dir / "plant_traits.json"

        def compute(plugin):
            t = plugin.measure(self.result.labelled)
            t.save(out, plant)
            return t

        self.result.traits, key = self.run_stage("measure", inputs, [out], compute,
                                                 lambda: Traits.load(out, plant))
        self.info["traits"] = {"leaf_count": len(self.result.traits.leaves),
                               "plant": plain(self.result.traits.plant)}
        return key

    def export(self) -> None:
        files: list[str] = []
        for i, spec in enumerate(self.recipe.export):
            def compute(plugin):
                return plugin.export(self.result)

            # Exporters are cheap and their inputs are the whole run: never cached.
            self._cache_path(f"export.{i}").unlink(missing_ok=True)
            written, _ = self.run_stage(f"export.{i}", now_iso(), [], compute, lambda: [],
                                        spec=spec, stage="exporter")
            files += [str(p) for p in written or []]
        self.info["exports"] = files


def process(
    scan_dir: Path,
    recipe: Recipe,
    run_dir: Path,
    manager: PluginManager,
    *,
    raw_recipe: dict | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    calibration_path: Path | None = None,
    progress: bool = False,
    workers: int | None = None,
) -> RunResult:
    """Run the recipe's processing stages over ``scan_dir`` into ``run_dir``.

    Stages run in order (calibrate, segment, reconstruct, mesh, segment_mesh,
    measure, export); a stage runs when the recipe names it and its inputs exist
    (``run.json: skipped`` lists the others).
    ``calibration_path`` replaces the calibrate stage with a saved calibration.

    Returns
    -------
    RunResult : everything produced (fields of stages that did not run are None).
    """
    scan = ScanFolder.open(scan_dir)
    run_dir = Path(run_dir)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PlantScanError(f"{run_dir}: cannot create the run folder ({exc.strerror})") from exc
    run = Run(scan, recipe, run_dir, manager, raw_recipe, list(overrides), progress, workers)
    t0, c0 = time.perf_counter(), time.process_time()
    keys: dict[str, str] = {}
    # What each stage needs from earlier ones; a stage runs when the recipe names it and
    # its inputs exist (calibration and silhouettes are independent of each other).
    needs = {"calibrate": [], "segment": [], "reconstruct": ["calibrate", "segment"],
             "mesh": ["reconstruct"], "segment_mesh": ["mesh"], "measure": ["segment_mesh"]}
    for section, inputs in needs.items():
        named = getattr(recipe, section) is not None or (
            section == "calibrate" and calibration_path is not None)
        if not named or any(i not in keys for i in inputs):
            run.info.setdefault("skipped", []).append(section)
            continue
        if section == "calibrate":
            keys[section] = run.calibrate(calibration_path)
        elif section == "segment":
            keys[section] = run.segment()
        elif section == "reconstruct":
            keys[section] = run.reconstruct(_sha([keys["calibrate"], keys["segment"]]))
        elif section == "mesh":
            keys[section] = run.mesh(keys["reconstruct"])
        elif section == "segment_mesh":
            keys[section] = run.segment_mesh(keys["mesh"])
        elif section == "measure":
            keys[section] = run.measure(keys["segment_mesh"])
    run.export()
    run.info["timings_s"]["total"] = round(time.perf_counter() - t0, 4)
    run.info.setdefault("cpu_s", {})["total"] = round(time.process_time() - c0, 4)
    run.info.setdefault("peak_rss_mb", {})["total"] = round(peak_rss_mb(), 1)
    run._write_info()
    return run.result


# --------------------------------------------------------------------------- PLY
def write_ply(path: Path, mesh: Mesh, face_labels: np.ndarray | None = None) -> None:
    """Binary little-endian PLY; with ``face_labels`` a per-face ``int leaf_id`` property."""
    v = mesh.vertices.astype("<f4")
    f = mesh.faces.astype("<i4")
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment plantscan mesh, units mm, turntable frame",
        f"element vertex {len(v)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(f)}",
        "property list uchar int vertex_indices",
    ]
    if face_labels is not None:
        header.append("property int leaf_id")
    header.append("end_header")
    dt = [("n", "u1"), ("idx", "<i4", (3,))]
    if face_labels is not None:
        dt.append(("leaf_id", "<i4"))
    faces = np.empty(len(f), dtype=dt)
    faces["n"] = 3
    faces["idx"] = f
    if face_labels is not None:
        faces["leaf_id"] = np.asarray(face_labels, dtype="<i4")
    data = ("\n".join(header) + "\n").encode() + v.tobytes() + faces.tobytes()
    atomic_write_bytes(Path(path), data)
