"""Acquisition orchestrator behind ``plantscan scan``: the same code for real and virtual rigs.

For each role of the protocol (calibration target, background plates, plant),
for each tilt, for each turntable angle: move, then trigger every camera.
Each image is appended to ``views.jsonl`` as soon as it is on disk, so an
interrupted scan is resumed with ``resume=True`` and finishes with exactly the
protocol's images, none rewritten.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from plantscan_core.data import ViewRecord
from plantscan_core.errors import HardwareError, PlantScanError, ScanFolderError
from plantscan_core.plugins import PluginManager
from plantscan_core.recipe import Recipe
from plantscan_core.scanfolder import ScanFolder, now_iso
from plantscan_core.stages import CaptureRequest, StageContext


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


def all_tilts(recipe: Recipe) -> list[float]:
    """Every tilt of the protocol: the scan's tilts first, then role-only tilts.

    A view's ``tilt_index`` is its tilt's position in this list.
    """
    tilts = list(recipe.scan.tilts_deg)
    for role in recipe.scan.enabled_roles():
        for t in recipe.scan.role_tilts(role):
            if t not in tilts:
                tilts.append(t)
    return tilts


def plan(recipe: Recipe) -> list[PlannedView]:
    """Every view of the protocol in capture order."""
    tilts = all_tilts(recipe)
    out: list[PlannedView] = []
    for role in recipe.scan.enabled_roles():
        for tilt in recipe.scan.role_tilts(role):
            for ai, angle in enumerate(recipe.scan.role_angles(role)):
                for cam in recipe.scan.cameras:
                    out.append(PlannedView(role, cam.name, tilts.index(tilt), tilt, ai, angle))
    return out


def image_relpath(v: PlannedView, ext: str) -> str:
    return f"images/{v.role}/{v.camera}_t{v.tilt_index:02d}_a{v.angle_index:03d}.{ext}"


def _scan_info(recipe: Recipe, raw_recipe: dict) -> dict:
    return {
        "plant_id": recipe.plant.id,
        "species": recipe.plant.species,
        "recipe_name": recipe.name,
        "recipe": raw_recipe,
        "rig": {
            "cameras": [c.name for c in recipe.scan.cameras],
            "tilts_deg": all_tilts(recipe),
            "image_size": list(recipe.scan.image_size),
            "protocol": recipe.scan.protocol,
        },
    }


def acquire(
    recipe: Recipe,
    out: Path,
    manager: PluginManager,
    *,
    raw_recipe: dict | None = None,
    resume: bool = False,
    stop_after: int | None = None,
    on_role_start: Callable[[str], None] | None = None,
    progress: bool = False,
) -> ScanFolder:
    """Run the recipe's scan protocol and write the scan folder ``out``.

    Parameters
    ----------
    recipe : Recipe, already validated in full (nothing has moved yet).
    out : Path, the scan folder.
    resume : continue a scan already in ``out`` (its recipe must match).
    stop_after : stop after this many *new* images (tests of interruption).
    on_role_start : called with the role name before its first image
        (real rigs: ask the user to mount the target or remove the plant).
    """
    raw_recipe = raw_recipe if raw_recipe is not None else recipe.model_dump(mode="json")
    out = Path(out)
    if resume:
        scan = ScanFolder.open(out)
        old = scan.info.get("recipe") or {}
        if _protocol_of(old) != _protocol_of(raw_recipe):
            raise ScanFolderError(
                f"{out}: cannot resume, the scan was started with a different protocol or rig "
                "(compare scan.yaml's recipe.scan with this recipe)"
            )
    else:
        scan = ScanFolder.create(out, _scan_info(recipe, raw_recipe))

    context = StageContext(recipe=recipe, scan=scan)
    # Build everything first, so a bad parameter fails before any motor moves.
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
        scene.setup(scan)

    done = scan.done_keys()
    todo = [v for v in plan(recipe) if v.key not in done]
    devices = [*cameras.values(), turntable] + ([tilt_arm] if tilt_arm is not None else [])
    opened = []
    new_images = 0
    ext = recipe.scan.image_format
    try:
        for d in devices:
            d.open()
            opened.append(d)
        if todo:
            turntable.home()
            if tilt_arm is not None:
                tilt_arm.home()
        current_role = current_tilt = current_angle = None
        measured = None
        bar = _progress(progress, len(todo))
        for v in todo:
            if stop_after is not None and new_images >= stop_after:
                break
            if v.role != current_role:
                if on_role_start is not None:
                    on_role_start(v.role)
                current_role, current_angle = v.role, None
            if v.tilt_deg != current_tilt:
                if tilt_arm is not None:
                    tilt_arm.move_to(v.tilt_deg)
                elif v.tilt_deg != 0.0:
                    raise HardwareError(f"tilt {v.tilt_deg} deg asked but the recipe has no "
                                        "scan.tilt_arm")
                current_tilt, current_angle = v.tilt_deg, None
            if v.angle_deg != current_angle:
                measured = turntable.move_to(v.angle_deg)
                current_angle = v.angle_deg
            view = ViewRecord(
                index=len(scan.views), role=v.role, camera=v.camera, tilt_index=v.tilt_index,
                tilt_deg=v.tilt_deg, angle_index=v.angle_index, commanded_angle_deg=v.angle_deg,
                measured_angle_deg=measured, file=image_relpath(v, ext), captured_at=now_iso(),
            )

            def _write(tmp: Path, v=v, view=view) -> None:
                req = CaptureRequest(
                    out_path=tmp, role=v.role, camera=v.camera, tilt_index=v.tilt_index,
                    tilt_deg=v.tilt_deg, angle_index=v.angle_index,
                    commanded_angle_deg=v.angle_deg, measured_angle_deg=view.measured_angle_deg,
                    image_size=tuple(recipe.scan.image_size), image_format=ext,
                )
                try:
                    cameras[v.camera].capture(req)
                except PlantScanError:
                    raise
                except Exception as exc:
                    raise HardwareError(
                        f"camera {v.camera!r} failed on {v.role} view tilt {v.tilt_index} angle "
                        f"{v.angle_deg:g}: {exc}; the {len(scan.views)} images already "
                        "captured are kept (continue with --resume)"
                    ) from exc

            scan.append_view(view, _write)
            new_images += 1
            if bar is not None:
                bar[0].advance(bar[1])
        if bar is not None:
            bar[0].stop()
    finally:
        for d in reversed(opened):
            try:
                d.close()
            except Exception:  # noqa: BLE001 - closing must not hide the original error
                pass
    return scan


def _protocol_of(raw: dict) -> dict:
    scan = dict(raw.get("scan") or {})
    return scan


def _progress(enabled: bool, total: int):
    if not enabled or total == 0:
        return None
    from rich.progress import Progress

    p = Progress(transient=True)
    task = p.add_task("capturing", total=total)
    p.start()
    return (p, task)
