"""Acquisition orchestrator behind ``plantscan scan``: the same code for real and virtual rigs.

For each role of the protocol (calibration target, background plates, plant),
for each tilt, for each turntable angle (a *stop*): move, then trigger every
camera at once.  Each image is appended to ``views.jsonl`` as soon as it is on
disk, so an interrupted scan is resumed with ``resume=True`` and finishes with
exactly the protocol's images, none rewritten.

Timeline of one stop ``k`` (cameras A and B)::

    main thread   | move k ........ | commit k-1 | trigger A+B (wait) | move k+1 ...
    camera A      | download k-1 ...|            | expose k           | download k ...
    camera B      | download k-1 .....|          | expose k           | download k ...

The move to stop ``k`` overlaps the downloads of stop ``k-1``; the rig only
moves once every shutter of the stop has closed.  A camera that splits its
work into ``trigger(request) -> finish`` (expose now, return a callable that
downloads) gets this overlap; a camera with only ``capture(request)`` does all
its work during the trigger phase and still runs concurrently with the others.
Each camera's calls run on its own worker thread, one call at a time, so a
backend never sees two calls at once.

Crash safety
------------
* a camera writes to a hidden temporary name (``.NAME.capture.EXT``); the scan
  folder fsyncs and renames it into place, then appends and fsyncs its line;
* ``KeyboardInterrupt`` (Ctrl-C, and SIGTERM while a scan runs) stops the axes
  (``stop()`` when the axis has one), keeps the images already exposed,
  removes temporaries, closes every device and re-raises;
* a device that fails for good ends the scan with :class:`AcquisitionError`
  (a ``HardwareError``) naming the device and view; every image captured
  before it, and those of the same stop from the other cameras, are kept;
* temporaries left by a killed process are removed when the scan is resumed.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import errno
import logging
import os
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from plantscan_core.data import ViewRecord
from plantscan_core.errors import HardwareError, PlantScanError, ScanFolderError
from plantscan_core.lock import FolderLock
from plantscan_core.plugins import PluginManager
from plantscan_core.progress import Display, StepProgress, display_for, run_logging
from plantscan_core.recipe import Recipe
from plantscan_core.scanfolder import IMAGES_DIR, ScanFolder, now_iso
from plantscan_core.stages import CameraBackend, CaptureRequest, MotionAxis, StageContext
from plantscan_core.trajectory import Stop, order_stops

CAPTURE_TMP_MARK = ".capture"
"""Infix of the temporary name a camera writes to (``.NAME.capture.EXT``)."""


class AcquisitionError(HardwareError):
    """A device failed for good during a scan; what was captured before is intact.

    Attributes
    ----------
    device : str
        ``camera NAME``, ``turntable`` or ``tilt_arm``.
    captured : int
        Number of images listed in ``views.jsonl`` when the scan stopped.
    """

    def __init__(self, message: str, *, device: str, captured: int) -> None:
        self.device = device
        self.captured = captured
        super().__init__(message)


@dataclass(frozen=True)
class PlannedView:
    role: str
    camera: str
    tilt_index: int
    tilt_deg: float
    angle_index: int
    angle_deg: float

    @property
    def key(self) -> tuple[str, str, int, int]:
        return (self.role, self.camera, self.tilt_index, self.angle_index)


def all_tilts(recipe: Recipe, planned: Sequence[Sequence[Stop]] = ()) -> list[float]:
    """Every tilt of the protocol: the scan's tilts first, then role-only tilts, then the
    adaptive planner's candidate tilts and those of ``planned`` stops.

    A view's ``tilt_index`` is its tilt's position in this list.
    """
    tilts = list(recipe.scan.tilts_deg)
    more = [t for role in recipe.scan.enabled_roles() for t in recipe.scan.role_tilts(role)]
    more += recipe.scan.adaptive_tilts() + [s.tilt_deg for r in planned for s in r]
    for t in more:
        if t not in tilts:
            tilts.append(t)
    return tilts


def plan(recipe: Recipe, registry=None, planned: Sequence[Sequence[Stop]] = ()
         ) -> list[PlannedView]:
    """Every view of the protocol in capture order (cameras innermost).

    Calibration and background views go tilt by tilt, turntable angle
    ascending.  The plant views of a ``scan.trajectory`` are visited in the
    quickest order by the rig's timing model (``trajectory.order_stops``), as is
    each round of ``planned`` stops (``ScanFolder.planned_rounds``) after them,
    from where the rig stands.  ``registry`` gives the plugins' timing
    parameters (default: every installed plugin); it changes only the order.
    """
    tilts = all_tilts(recipe, planned)
    scan = recipe.scan
    out: list[PlannedView] = []
    motion = None
    for role in scan.enabled_roles():
        role_stops = scan.role_stops(role)
        if role == "plant" and (scan.trajectory is not None or planned):
            from plantscan_core.timing import rig_motion

            motion = rig_motion(recipe, registry)
            at = (0.0, 0.0)
            if scan.trajectory is not None:
                role_stops, _ = order_stops(role_stops, motion)
            ordered = list(role_stops)
            for stops_of_round in planned:
                at = ordered[-1].position if ordered else at
                ordered += order_stops(list(stops_of_round), motion, at)[0]
            role_stops = ordered
        for stop in role_stops:
            ti = tilts.index(stop.tilt_deg)
            for cam in scan.cameras:
                out.append(PlannedView(role, cam.name, ti, stop.tilt_deg, stop.index,
                                       stop.pan_deg))
    return out


def image_relpath(v: PlannedView, ext: str) -> str:
    return f"images/{v.role}/{v.camera}_t{v.tilt_index:02d}_a{v.angle_index:03d}.{ext}"


def stops(views: list[PlannedView]) -> Iterator[list[PlannedView]]:
    """Group consecutive views taken at the same rig position (one group = one stop)."""
    group: list[PlannedView] = []
    for v in views:
        if group and (v.role, v.tilt_index, v.angle_index) != (
            group[0].role, group[0].tilt_index, group[0].angle_index
        ):
            yield group
            group = []
        group.append(v)
    if group:
        yield group


def _scan_info(recipe: Recipe, raw_recipe: dict) -> dict:
    return {
        "plant_id": recipe.plant.id,
        "species": recipe.plant.species,
        # the plant's and the experiment's metadata as scanned (docs/experiments.md)
        "plant": recipe.plant.model_dump(mode="json"),
        "experiment": recipe.experiment.model_dump(mode="json"),
        "recipe_name": recipe.name,
        "recipe": raw_recipe,
        "rig": {
            "cameras": [c.name for c in recipe.scan.cameras],
            "tilts_deg": all_tilts(recipe),
            "image_size": list(recipe.scan.image_size),
            "protocol": recipe.scan.protocol,
        },
    }


def remove_stale_temporaries(scan: ScanFolder) -> list[Path]:
    """Delete half-written images left by a killed scan (hidden ``.capture``/``.partial`` files).

    They are never listed in ``views.jsonl``; their views are captured again.
    """
    removed = []
    images = scan.root / IMAGES_DIR
    if not images.is_dir():
        return removed
    for p in images.rglob(".*"):
        if p.is_file() and (CAPTURE_TMP_MARK in p.name or ".partial" in p.name):
            p.unlink(missing_ok=True)
            removed.append(p)
    return removed


# --------------------------------------------------------------------------- devices
def _camera_trigger(camera: CameraBackend, request: CaptureRequest) -> Callable[[], Any]:
    """Expose now; return the callable that finishes (downloads) the image.

    Cameras may implement ``trigger(request) -> finish`` to let downloads overlap
    the next move; otherwise ``capture`` does everything here.
    """
    trigger = getattr(camera, "trigger", None)
    if callable(trigger):
        finish = trigger(request)
        if callable(finish):
            return finish
        return _nothing
    camera.capture(request)
    return _nothing


def _nothing() -> None:
    return None


@dataclass
class _Pending:
    """One image of a stop: its trigger, then its download, then its commit."""

    view: ViewRecord
    tmp: Path
    worker: cf.ThreadPoolExecutor
    trigger: cf.Future
    download: cf.Future | None = None

    def wait(self) -> None:
        """Block until the image is complete in ``tmp``; raise the device's error."""
        if self.download is None:
            finish = self.trigger.result()
            self.download = self.worker.submit(finish)
        self.download.result()


class _Rig:
    """The built devices of one acquisition and the per-camera worker threads."""

    def __init__(self, cameras: dict[str, CameraBackend], turntable: MotionAxis,
                 tilt_arm: MotionAxis | None) -> None:
        self.cameras = cameras
        self.turntable = turntable
        self.tilt_arm = tilt_arm
        self.workers = {
            name: cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"camera-{name}")
            for name in cameras
        }
        self.opened: list[Any] = []

    def axes(self) -> list[tuple[str, MotionAxis]]:
        out = [("turntable", self.turntable)]
        if self.tilt_arm is not None:
            out.append(("tilt_arm", self.tilt_arm))
        return out

    def open(self) -> None:
        for name, cam in self.cameras.items():
            self._open_one(f"camera {name!r}", cam)
        for name, axis in self.axes():
            self._open_one(name, axis)

    def _open_one(self, what: str, device: Any) -> None:
        try:
            device.open()
        except PlantScanError:
            raise
        except Exception as exc:
            raise HardwareError(f"{what}: cannot open the device: {exc}") from exc
        self.opened.append(device)

    def stop_axes(self) -> None:
        """Emergency stop: every axis with a ``stop()`` stops now (errors ignored)."""
        for _, axis in self.axes():
            stop = getattr(axis, "stop", None)
            if callable(stop):
                try:
                    stop()
                except Exception:  # noqa: BLE001 - stopping must try every axis
                    pass

    def close(self, wait: bool = True) -> None:
        for ex in self.workers.values():
            ex.shutdown(wait=wait, cancel_futures=True)
        for d in reversed(self.opened):
            try:
                d.close()
            except Exception:  # noqa: BLE001 - closing must not hide the original error
                pass
        self.opened.clear()


# --------------------------------------------------------------------------- orchestrator
def acquire(
    recipe: Recipe,
    out: Path,
    manager: PluginManager,
    *,
    raw_recipe: dict | None = None,
    resume: bool = False,
    stop_after: int | None = None,
    on_role_start: Callable[[str], None] | None = None,
    progress: bool | Display = False,
) -> ScanFolder:
    """Run the recipe's scan protocol and write the scan folder ``out``.

    Parameters
    ----------
    recipe : Recipe, already validated in full (nothing has moved yet).
    out : Path, the scan folder.
    manager : PluginManager that builds the cameras, axes and scene.
    raw_recipe : the recipe as read (stored in ``scan.yaml``); defaults to ``recipe`` dumped.
    resume : continue a scan already in ``out`` (its protocol and rig must match);
        finished images are never rewritten.  The planned stops the folder records
        (``planned_views.jsonl``, an adaptive scan's) are part of its protocol.
    stop_after : capture at most this many *new* images, then return (tests of interruption).
    on_role_start : called with the role name before its first image, once every
        earlier image is committed (real rigs: ask the user to mount the target
        or remove the plant).
    progress : a ``Display`` (``plantscan_core.progress``; the CLI's shows every role's
        images with the time left, from the timing model before the first image), True
        for one chosen by stderr, False for warnings only.  The scan's log goes to
        ``out/run.log``.

    Raises
    ------
    AcquisitionError
        A camera or axis failed for good; the images captured so far are kept
        and listed (continue with ``resume=True``).
    KeyboardInterrupt
        Ctrl-C or SIGTERM: axes stopped, exposed images kept, devices closed.
    """
    lock = FolderLock(Path(out), "scan folder", ScanFolderError)
    try:
        return _acquire(recipe, Path(out), manager, lock, raw_recipe, resume, stop_after,
                        on_role_start, progress)
    finally:
        lock.release()


@dataclass
class _Prepared:
    """What ``_prepare`` readies: the scan folder, the built devices, what is left to take."""

    scan: ScanFolder
    cameras: dict[str, CameraBackend]
    turntable: MotionAxis
    tilt_arm: MotionAxis | None
    clock: Callable[[], str]
    todo: list[PlannedView]
    estimates: dict[str, float]


def _acquire(recipe: Recipe, out: Path, manager: PluginManager, lock: FolderLock,
             raw_recipe: dict | None, resume: bool, stop_after: int | None,
             on_role_start: Callable[[str], None] | None,
             progress: bool | Display) -> ScanFolder:
    """``acquire``, with ``lock`` taken before the folder is opened or created."""
    display = display_for(progress)
    # Building the devices, the virtual scene's plant and the timing estimate take seconds
    # (a camera found on USB; a plant grown, its truth written): a step of their own.
    with display.step("scan set-up"):
        ready = _prepare(recipe, out, manager, lock, raw_recipe, resume, stop_after)
    log = logging.getLogger("plantscan.scan")
    with _Signals() as signals, run_logging(ready.scan.root, display):
        log.info("scan %s (recipe %s%s): %d images to capture, estimated %.0f s",
                 ready.scan.root, recipe.name, ", resumed" if resume else "", len(ready.todo),
                 sum(ready.estimates.values()))
        t0 = time.perf_counter()
        run = _Run(recipe, ready.scan, _Rig(ready.cameras, ready.turntable, ready.tilt_arm),
                   on_role_start, signals, ready.clock)
        run.display, run.estimates = display, ready.estimates
        run.execute(ready.todo)
        log.info("done in %.1f s: %d images in the scan folder", time.perf_counter() - t0,
                 len(ready.scan.views))
    return ready.scan


def _prepare(recipe: Recipe, out: Path, manager: PluginManager, lock: FolderLock,
             raw_recipe: dict | None, resume: bool, stop_after: int | None) -> _Prepared:
    """Open or create the scan folder and build the rig; nothing moves yet."""
    raw_recipe = raw_recipe if raw_recipe is not None else recipe.model_dump(mode="json")
    scan = None
    if resume:
        _take(lock)
        scan = ScanFolder.open(out)
        old = scan.info.get("recipe") or {}
        if _protocol_of(old) != _protocol_of(raw_recipe):
            raise ScanFolderError(
                f"{out}: cannot resume, the scan was started with a different protocol or rig "
                "(compare scan.yaml's recipe.scan with this recipe)"
            )
        remove_stale_temporaries(scan)

    context = StageContext(recipe=recipe, scan=scan)
    # Build everything first, so a bad parameter fails before any motor moves and before
    # a new scan folder is created.
    scene = None
    if recipe.scan.scene is not None:
        scene = manager.build("scene", recipe.scan.scene.plugin, recipe.scan.scene.params, context)
    cameras = {
        c.name: manager.build("camera", c.plugin, c.params, context) for c in recipe.scan.cameras
    }
    turntable = manager.build("axis", recipe.scan.turntable.plugin, recipe.scan.turntable.params,
                              context)
    tilt_arm = None
    if recipe.scan.tilt_arm is not None:
        tilt_arm = manager.build("axis", recipe.scan.tilt_arm.plugin, recipe.scan.tilt_arm.params,
                                 context)
    for cam_name, cam in cameras.items():
        cam.camera_name = cam_name  # lets a backend know which rig camera it is
    if scene is not None:
        scene.check(recipe)  # an impossible virtual rig is refused before the folder exists

    def clock() -> str:
        return (scene.now() if scene is not None else None) or now_iso()

    if scan is None:
        _take(lock)
        scan = ScanFolder.create(out, {**_scan_info(recipe, raw_recipe), "created": clock()})
        context.scan = scan

    if scene is not None:
        scene.setup(scan)

    done = scan.done_keys()
    planned = [[s.stop for s in r.stops] for r in scan.planned_rounds()]
    todo = [v for v in plan(recipe, manager.registry, planned) if v.key not in done]
    if stop_after is not None:
        todo = todo[: max(0, stop_after)]
    return _Prepared(scan, cameras, turntable, tilt_arm, clock, todo,
                     _role_estimates(recipe, manager, todo))


def _take(lock: FolderLock) -> None:
    """Take the scan folder's lock; say so when an earlier scan there was killed."""
    lock.acquire()
    if lock.stale_message():
        print(f"plantscan: warning: {lock.stale_message()}", file=sys.stderr)


def _role_estimates(recipe: Recipe, manager: PluginManager,
                    todo: list[PlannedView]) -> dict[str, float]:
    """Seconds each role of ``todo`` should take (the timing model, ``plantscan scan
    --dry-run``), scaled to the images still to take; a role the model cannot time is absent."""
    from plantscan_core.timing import estimate_scan_time

    try:
        est = estimate_scan_time(recipe, manager.registry)
    except Exception:  # noqa: BLE001 - an estimate must never stop a scan
        return {}
    left = Counter(v.role for v in todo)
    return {r.role: r.total_s * left[r.role] / r.images for r in est.roles
            if r.images and r.total_s > 0 and left[r.role]}


class _Run:
    """State of one ``acquire`` call: where the rig is, what is exposed but not committed."""

    def __init__(self, recipe: Recipe, scan: ScanFolder, rig: _Rig,
                 on_role_start: Callable[[str], None] | None, signals: _Signals,
                 clock: Callable[[], str] = now_iso) -> None:
        self.signals = signals
        self.clock = clock
        self.recipe = recipe
        self.scan = scan
        self.rig = rig
        self.on_role_start = on_role_start
        self.ext = recipe.scan.image_format
        self.pending: list[_Pending] = []
        self.tilt: float | None = None
        self.angle: float | None = None
        self.measured: float | None = None
        self.display = display_for(False)
        self.estimates: dict[str, float] = {}
        self.step: StepProgress | None = None  # the role being captured: its images counted

    def execute(self, todo: list[PlannedView]) -> None:
        rig = self.rig
        interrupted = False
        per_role = Counter(v.role for v in todo)
        steps = contextlib.ExitStack()
        try:
            rig.open()
            if todo:
                self._axis_call("turntable", rig.turntable.home)
                if rig.tilt_arm is not None:
                    self._axis_call("tilt_arm", rig.tilt_arm.home)
            role = None
            for group in stops(todo):
                if group[0].role != role:
                    self.commit()  # the user is asked to change the set-up: nothing in flight
                    steps.close()
                    role = group[0].role
                    if self.on_role_start is not None:
                        self.on_role_start(role)
                    logging.getLogger("plantscan.scan").info(
                        "%s: %d images", role, per_role[role])
                    self.step = steps.enter_context(self.display.step(
                        f"scan {role}", per_role[role], "images", self.estimates.get(role)))
                    self.angle = None
                self.move(group[0])
                self.commit()  # downloads of the previous stop ran during the move
                self.expose(group)
            self.commit()
            steps.close()
        except BaseException as exc:
            steps.__exit__(type(exc), exc, exc.__traceback__)  # the role's line: "failed"
            interrupted = isinstance(exc, KeyboardInterrupt)
            if interrupted:
                rig.stop_axes()
            try:
                self._commit_quietly()
            except KeyboardInterrupt:  # a second Ctrl-C: stop waiting for downloads
                interrupted = True
            raise
        finally:
            steps.close()
            self.step = None
            rig.close(wait=not interrupted)
            for p in self.pending:
                p.tmp.unlink(missing_ok=True)

    # -- motion ------------------------------------------------------------------------
    def _axis_call(self, which: str, fn: Callable, *args):
        try:
            return fn(*args)
        except AcquisitionError:
            raise
        except Exception as exc:
            self._commit_quietly()  # the images exposed before the failure are kept and counted
            msg = str(exc) if isinstance(exc, PlantScanError) else (
                f"failed ({type(exc).__name__}: {exc})")
            raise AcquisitionError(
                f"{which}: {msg}; {self._kept()}", device=which, captured=len(self.scan.views)
            ) from exc

    def move(self, v: PlannedView) -> None:
        rig = self.rig
        if v.tilt_deg != self.tilt:
            if rig.tilt_arm is not None:
                self._axis_call("tilt_arm", rig.tilt_arm.move_to, v.tilt_deg)
            elif v.tilt_deg != 0.0:
                raise HardwareError(f"tilt {v.tilt_deg} deg asked but the recipe has no "
                                    "scan.tilt_arm")
            self.tilt, self.angle = v.tilt_deg, None
        if v.angle_deg != self.angle:
            self.measured = self._axis_call("turntable", rig.turntable.move_to, v.angle_deg)
            self.angle = v.angle_deg

    # -- cameras -----------------------------------------------------------------------
    def expose(self, group: list[PlannedView]) -> None:
        """Trigger every camera of the stop at once; queue their downloads."""
        size = tuple(self.recipe.scan.image_size)
        start = len(self.pending)
        for v in group:
            rel = image_relpath(v, self.ext)
            final = self.scan.root / rel
            final.parent.mkdir(parents=True, exist_ok=True)
            tmp = final.with_name(f".{final.stem}{CAPTURE_TMP_MARK}{final.suffix}")
            view = ViewRecord(
                index=-1, role=v.role, camera=v.camera, tilt_index=v.tilt_index,
                tilt_deg=v.tilt_deg, angle_index=v.angle_index, commanded_angle_deg=v.angle_deg,
                measured_angle_deg=self.measured, file=rel, captured_at=self.clock(),
            )
            req = CaptureRequest(
                out_path=tmp, role=v.role, camera=v.camera, tilt_index=v.tilt_index,
                tilt_deg=v.tilt_deg, angle_index=v.angle_index, commanded_angle_deg=v.angle_deg,
                measured_angle_deg=self.measured, image_size=size, image_format=self.ext,
            )
            worker = self.rig.workers[v.camera]
            cam = self.rig.cameras[v.camera]
            self.pending.append(_Pending(view, tmp, worker,
                                         worker.submit(_camera_trigger, cam, req)))
        failed = False
        for p in self.pending[start:]:
            try:
                finish = p.trigger.result()  # the shutter has closed: the rig may move after this
            except Exception:  # noqa: BLE001 - reported by commit, in capture order
                failed = True
                continue
            p.download = p.worker.submit(finish)
        if failed:
            self.commit()  # keeps the other cameras' images of this stop, then raises

    def commit(self) -> None:
        """Wait for the pending downloads and list them in order; raise the first failure."""
        pending, self.pending = self.pending, []
        first: tuple[_Pending, BaseException] | None = None
        for i, p in enumerate(pending):
            listed = False
            try:
                try:
                    p.wait()
                    if not p.tmp.exists():
                        raise HardwareError(f"{p.tmp}: the camera reported success but wrote "
                                            "no file")
                except Exception as exc:  # noqa: BLE001 - the others are still committed
                    p.tmp.unlink(missing_ok=True)
                    if first is None:
                        first = (p, exc)
                    continue
                view = dataclasses.replace(p.view, index=len(self.scan.views))
                try:
                    with self.signals.critical_section():
                        listed = False
                        self.scan.append_view(view, lambda tmp, src=p.tmp: os.replace(src, tmp))
                        listed = True
                except OSError as exc:
                    p.tmp.unlink(missing_ok=True)
                    raise AcquisitionError(
                        f"cannot store {view.file} in {self.scan.root}: {exc.strerror or exc}"
                        + (" (the disk is full)" if exc.errno == errno.ENOSPC else "")
                        + f"; {self._kept()}",
                        device="scan folder", captured=len(self.scan.views),
                    ) from exc
                if self.step is not None:
                    self.step.advance()
            except BaseException:
                # Still to be committed or cleaned up (this one too, unless it was listed
                # before a deferred Ctrl-C surfaced).
                self.pending = pending[i + 1:] if listed else pending[i:]
                raise
        if first is not None:
            p, exc = first
            self._raise_camera_error(p.view, exc)

    def _commit_quietly(self) -> None:
        """On the way out of an error: keep whatever is complete, swallow further errors."""
        while self.pending:
            try:
                self.commit()
            except Exception:  # noqa: BLE001 - the original error is the one reported
                continue

    def _raise_camera_error(self, view: ViewRecord, exc: BaseException) -> None:
        where = (f"{view.role} view tilt {view.tilt_index} angle {view.commanded_angle_deg:g} "
                 f"({view.file})")
        if isinstance(exc, PlantScanError):
            msg = str(exc)
        elif isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            msg = f"the disk of {self.scan.root} is full ({exc})"
        else:
            msg = f"{type(exc).__name__}: {exc}"
        raise AcquisitionError(
            f"camera {view.camera!r} failed on {where}: {msg}; {self._kept()}",
            device=f"camera {view.camera}", captured=len(self.scan.views),
        ) from exc

    def _kept(self) -> str:
        return (f"the {len(self.scan.views)} images already captured in {self.scan.root} are "
                "kept (fix the device, then continue with --resume)")


class _Signals:
    """Ctrl-C (SIGINT) and SIGTERM while a scan runs in the main thread.

    Both raise ``KeyboardInterrupt`` (motors stop, see ``_Run.execute``), except
    inside a critical section (listing one finished image: rename, line append),
    where the interrupt is held until the section ends, so the folder on disk
    and the scan's view list never disagree.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.critical = 0
        self.deferred: int | None = None
        self.old: dict[int, Any] = {}

    def __enter__(self) -> _Signals:
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                try:
                    self.old[sig] = signal.signal(sig, self._handle)
                except ValueError:  # not the main interpreter
                    pass
        return self

    def __exit__(self, *exc) -> bool:
        for sig, old in self.old.items():
            signal.signal(sig, old)
        self.old.clear()
        return False

    def _handle(self, signum, frame) -> None:
        if self.critical:
            self.deferred = signum
            return
        raise KeyboardInterrupt(f"signal {signum}")

    @contextlib.contextmanager
    def critical_section(self):
        self.critical += 1
        try:
            yield
        finally:
            self.critical -= 1
            if self.critical == 0 and self.deferred is not None:
                signum, self.deferred = self.deferred, None
                raise KeyboardInterrupt(f"signal {signum}")


RESUME_IGNORED_PARAMS = frozenset({
    "port", "serial", "device", "url", "baudrate", "hub_port", "retries", "retry_backoff_s",
    "timeout_s", "reconnect_attempts",
})
"""Device parameters that may change between an interrupted scan and its resume
(a camera re-plugged on another USB port, more patience with a flaky device)."""


def _protocol_of(raw: dict) -> dict:
    """The part of a raw recipe a resumed scan must share with the original."""
    scan = dict(raw.get("scan") or {})
    for key in ("cameras", "turntable", "tilt_arm"):
        specs = scan.get(key)
        if specs is None:
            continue
        many = isinstance(specs, list)
        cleaned = []
        for spec in specs if many else [specs]:
            spec = dict(spec or {})
            spec["params"] = {k: v for k, v in (spec.get("params") or {}).items()
                              if k not in RESUME_IGNORED_PARAMS}
            cleaned.append(spec)
        scan[key] = cleaned if many else cleaned[0]
    return scan


