"""The virtual world: studio, turntable, pot, plant, calibration board, lights, truth.

What each role shows (what a real lab's set-up holds when that role is shot):

* ``calibration``: backdrop, turntable plate, pot carrier, and the calibration
  board on a post standing on the carrier; no pot, no plant.
* ``background``: backdrop, turntable plate and pot carrier (fixtures of the
  turntable that stay in place when the potted plant is lifted off); no pot, no
  plant.  The plate and carrier are plain and round, so one background plate per
  camera and tilt fits every turntable angle (unless ``plate_texture`` prints a
  pattern on the plate, which turns with it).
* ``plant``: the background plus the pot (dark, tapered, with soil) and the plant.
  The truth masks are pot + plant (the foreground a background subtraction
  should find; the pot is removed later from the hull, see ``pot.yaml``).
"""

from __future__ import annotations

import datetime
import json
import math
import os
import shutil
import threading
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import Field

from plantscan_core.data import Camera, Pose, ViewRecord, plain, rotation_z
from plantscan_core.errors import DataError, RecipeError, ScanFolderError
from plantscan_core.preflight import WorkEstimate, WorkPlan
from plantscan_core.scanfolder import ScanFolder, atomic_write_bytes, atomic_write_text
from plantscan_core.stages import CaptureRequest, Scene, StageParams
from plantscan_sim.families import ORGANS, Ground
from plantscan_sim.geometry import TriMesh, box, frustum, grid_faces, revolve, tube
from plantscan_sim.plants import PRESETS, Plant, build_plant
from plantscan_sim.render import (
    CLASS_BOARD,
    CLASS_PLANT,
    CLASS_POT,
    BoardTexture,
    Lighting,
    Material,
    Renderer,
)
from plantscan_sim.rig import Rig, SimCameraParams
from plantscan_sim.texture import BackdropMarkers, plate_textures

SHARED_KEY = "sim_scene"
TRUTH_VIEWS_DIR = "views"  # ground_truth/views/<role>/<image stem>.json|.mask.png (staging)


class RigError(RecipeError):
    """The virtual rig cannot take the scan the recipe asks for (found before rendering)."""


class SimSceneParams(StageParams):
    """Parameters of the virtual world (``scan.scene.params``)."""

    preset: Literal["dicot", "rosette", "branched", "grass", "seedling", "plastic-dicot",
                    "wheat", "sorghum", "mesh"] = Field(
        "plastic-dicot", description="a plant family (seeded, varied, growing with age) or a "
        "fixed preset (docs/virtual-scanner.md)")
    seed: int = 0
    age: float | None = Field(None, ge=0.0, description="days after emergence (families only); "
                              "None: the mature plant")
    mesh_path: str | None = Field(None, description="PLY/OBJ plant mesh (preset 'mesh')")
    mesh_labels_path: str | None = Field(None, description="one leaf id per face (-1 stem)")
    mesh_scale: float = Field(1.0, gt=0, description="mesh units -> mm")
    leaf_thickness_mm: float = Field(0.5, gt=0.0, le=5.0)
    supersampling: int = Field(3, ge=1, le=8, description="samples per pixel side (plant, bg)")
    calibration_supersampling: int = Field(6, ge=1, le=8,
                                           description="samples per pixel side (board views)")
    noise_sigma: float = Field(2.0, ge=0.0, le=50.0, description="sensor noise, 8-bit DN")
    target_height_mm: float = Field(220.0, description="aim point / tilt axis height")
    arm_azimuth_deg: float = Field(-90.0, description="azimuth of the camera arm at turntable "
                                   "angle 0; -90 puts the cameras on the -Y side, the gauge of "
                                   "the 'turntable' calibrator")
    light_position_mm: tuple[float, float, float] = Field(
        (1100.0, 800.0, 1700.0), description="key light, in the arm's frame (x towards the "
        "cameras, z up); turned with arm_azimuth_deg")
    key_light: float = Field(0.8, ge=0.0)
    ambient: float = Field(0.3, ge=0.0)
    gamma: float = Field(2.2, ge=1.0, le=3.0, description="camera tone curve exponent")
    board: Literal["chessboard", "charuco"] = "chessboard"
    board_squares: tuple[int, int] = (10, 7)
    board_square_mm: float = Field(25.0, gt=0.0)
    board_tilt_deg: float = Field(40.0, ge=0.0, le=80.0,
                                  description="board leans back from vertical by this much")
    board_height_mm: float | None = Field(None, description="board centre height (default: "
                                          "target_height_mm)")
    charuco_dictionary: str = "DICT_5X5_100"
    pot_z_bottom_mm: float = 30.0
    pot_z_top_mm: float = 150.0
    pot_r_bottom_mm: float = 52.0
    pot_r_top_mm: float = 68.0
    soil_depth_mm: float = Field(8.0, ge=0.0)
    carrier_radius_mm: float = 60.0
    plate_radius_mm: float = 200.0
    plate_texture: Literal["plain", "random-dots", "aruco-dots"] = Field(
        "plain", description="pattern printed on the plate's top and rim and on the pot carrier: "
        "'random-dots' gives structure from motion (calibrate: sfm) features that turn with "
        "the plant; 'aruco-dots' adds a row of ArUco markers (DICT_4X4_50) round the plate's "
        "rim and the carrier, which cameras far apart in elevation both identify")
    plate_texture_pitch_mm: float = Field(10.0, gt=0.5, description="cell side of the dots")
    backdrop_texture: Literal["plain", "aruco"] = Field(
        "plain", description="'aruco' prints a grid of 100 mm ArUco markers (DICT_4X4_250, "
        "ids from 50) on the backdrop's wall and floor: fixed in the lab, seen by every "
        "camera, for structure from motion (calibrate: sfm)")
    sway_deg: float = Field(0.0, ge=0.0, le=10.0, description="plant sway: per turntable stop "
                            "the plant (not the pot) tilts about its stem base by a random "
                            "angle of this standard deviation (seeded, in cameras.jsonl)")
    check_rig: bool = Field(True, description="refuse impossible rigs before rendering")
    clock_start: datetime.datetime | None = Field(
        None, description="the virtual scanner's clock (ISO 8601; UTC unless it says): the "
        "scan and its images are time-stamped from this time on (advancing with the real "
        "clock) instead of now, so virtual scans of a growing plant fall on the days of a "
        "virtual experiment")


# The studio sweep, arm frame (+X towards the cameras): floor height and wall position.
BACKDROP_FLOOR_Z_MM = -60.0
BACKDROP_WALL_X_MM = -750.0

# material indices
M_BACKDROP, M_PLATE, M_CARRIER, M_POT, M_SOIL, M_PANEL, M_BOARD, M_POST, M_STEM = range(9)
M_LEAF0 = 9


RENDER_BYTES_PER_PX = 24  # a lower bound: the float32 RGB image (12 B/px) and one copy


class SimScene(Scene):
    """The virtual scanner's world (``scan.scene: {plugin: sim}``)."""

    name = "sim"
    Params = SimSceneParams

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self.true_angle_deg: float | None = None
        self.true_tilt_deg: float | None = None
        self._lock = threading.Lock()
        self.renderer: Renderer | None = None
        self.rig: Rig | None = None
        self.plant: Plant | None = None
        self._clock_t0: float | None = None

    @classmethod
    def estimate(cls, params, plan: WorkPlan) -> WorkEstimate | None:
        """At least one float32 RGB render of a view and one copy of it (24 B/px)."""
        if plan.capture_size is None:
            return None
        w, h = plan.capture_size
        return WorkEstimate(stage="scan.scene (sim)", what=f"rendering one {w}x{h} px image",
                            peak_bytes=RENDER_BYTES_PER_PX * w * h, seconds=None,
                            parameter="scan.image_size")

    # ------------------------------------------------------------------ set-up
    def check(self, recipe=None) -> None:
        """Build the world and refuse an impossible rig, writing nothing (``RigError``).

        Needs no scan folder, so an orchestrator may call it before creating one;
        ``setup`` calls it too (the world is built once).
        """
        recipe = recipe if recipe is not None else self.context.recipe
        if recipe is None:
            raise RecipeError([("scan.scene", "the sim scene needs the recipe in its context")])
        if self.renderer is not None:
            return
        p = self.params
        cams = self._camera_params(recipe)
        self._check_axes(recipe)
        from plantscan_core.acquire import all_tilts, plan

        self.rig = Rig(cams, tuple(recipe.scan.image_size), all_tilts(recipe),
                       p.target_height_mm, p.arm_azimuth_deg)
        if p.age is not None and p.preset in PRESETS:
            raise RecipeError([("scan.scene.params.age", f"the preset {p.preset!r} does not "
                                "grow; age applies to the families dicot, rosette, branched, "
                                "grass, seedling")], "virtual scanner")
        self.plant = scene_plant(p)
        self.jpeg_quality = recipe.scan.jpeg_quality
        self.camera_order = [c.name for c in recipe.scan.cameras]
        if p.check_rig:
            self.check_rig(plan(recipe))
        self._build_world()

    def now(self) -> str | None:
        start = self.params.clock_start
        if start is None:
            return None
        if start.tzinfo is None:
            start = start.replace(tzinfo=datetime.UTC)
        if self._clock_t0 is None:
            self._clock_t0 = time.monotonic()
        t = start + datetime.timedelta(seconds=time.monotonic() - self._clock_t0)
        return t.astimezone(datetime.UTC).isoformat(timespec="seconds")

    def setup(self, scan: ScanFolder) -> None:
        self.check(self.context.recipe)
        self.write_truth(scan)
        self.context.shared[SHARED_KEY] = self

    @property
    def soil_z(self) -> float:
        return soil_height(self.params)

    def ground(self) -> Ground:
        """Soil and pot rim the plant's blades must clear (mm, turntable frame)."""
        return scene_ground(self.params)

    def _camera_params(self, recipe) -> dict[str, SimCameraParams]:
        errors, cams = [], {}
        for i, c in enumerate(recipe.scan.cameras):
            if c.plugin != "sim":
                errors.append((f"scan.cameras.{i}.plugin",
                               f"the sim scene renders only sim cameras, not {c.plugin!r}"))
                continue
            cams[c.name] = SimCameraParams.model_validate(c.params)
        if errors:
            raise RigError(errors)
        return cams

    def _check_axes(self, recipe) -> None:
        errors = []
        tt = recipe.scan.turntable
        if tt.plugin == "sim" and tt.params.get("axis", "turntable") != "turntable":
            errors.append(("scan.turntable.params.axis", "must be 'turntable'"))
        ta = recipe.scan.tilt_arm
        if ta is not None and ta.plugin == "sim" and ta.params.get("axis") != "tilt":
            errors.append(("scan.tilt_arm.params.axis", "must be 'tilt' for the tilt arm"))
        if errors:
            raise RigError(errors)

    # ------------------------------------------------------------------ geometry
    def _board_frame(self):
        p = self.params
        b = math.radians(p.board_tilt_deg)
        a = math.radians(p.arm_azimuth_deg)
        out = np.array([math.cos(a), math.sin(a), 0.0])
        side = np.array([-math.sin(a), math.cos(a), 0.0])
        n = math.cos(b) * out + math.sin(b) * np.array([0.0, 0.0, 1.0])
        up = -math.sin(b) * out + math.cos(b) * np.array([0.0, 0.0, 1.0])
        centre = np.array([0.0, 0.0, p.board_height_mm or p.target_height_mm])
        ex, ey = side, -up  # ex x ey = -n: the pattern reads correctly from the front
        return centre, n, ex, ey

    def board_corners(self) -> np.ndarray:
        """(N, 3) world coordinates (mm) of the board's inner chessboard corners.

        Row-major over the board's rows (``ey``), then columns (``ex``), which is
        the order of ChArUco corner ids.
        """
        p = self.params
        centre, _, ex, ey = self._board_frame()
        nx, ny = p.board_squares
        s = p.board_square_mm
        origin = centre - 0.5 * nx * s * ex - 0.5 * ny * s * ey
        jj, ii = np.meshgrid(np.arange(1, ny), np.arange(1, nx), indexing="ij")
        return origin + (ii.ravel() * s)[:, None] * ex + (jj.ravel() * s)[:, None] * ey

    def _board(self) -> tuple[list[TriMesh], BoardTexture]:
        p = self.params
        centre, n, ex, ey = self._board_frame()
        nx, ny = p.board_squares
        s = p.board_square_mm
        thick = 4.0
        panel = box(centre - 0.5 * thick * n, ex, ey, n,
                    (0.5 * (nx + 2) * s, 0.5 * (ny + 2) * s, 0.5 * thick), M_PANEL)
        tri = panel.vertices[panel.faces]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        fn /= np.linalg.norm(fn, axis=1, keepdims=True)
        panel.face_attr[fn @ n > 0.99] = M_BOARD
        post_top = centre + 0.3 * (ny + 2) * s * ey - (thick + 6.0) * n  # behind the panel
        post = tube(np.array([[post_top[0], post_top[1], p.pot_z_bottom_mm - 5.0], post_top]),
                    6.0, n=12, attr=M_POST)
        origin = centre - 0.5 * nx * s * ex - 0.5 * ny * s * ey
        tex = BoardTexture(origin, ex, ey, (nx, ny), s)
        if p.board == "charuco":
            tex.image, tex.px_per_mm = self._charuco_image()
        return [panel, post], tex

    def charuco_board(self):
        """The OpenCV ``CharucoBoard`` printed on the board (board == 'charuco')."""
        import cv2

        p = self.params
        if not hasattr(cv2.aruco, p.charuco_dictionary):
            raise RecipeError([("scan.scene.params.charuco_dictionary",
                                f"unknown ArUco dictionary {p.charuco_dictionary!r}")])
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, p.charuco_dictionary))
        s = p.board_square_mm
        return cv2.aruco.CharucoBoard(tuple(p.board_squares), s, 0.75 * s, d)

    def _charuco_image(self) -> tuple[np.ndarray, float]:
        p = self.params
        ppm = 8.0
        nx, ny = p.board_squares
        w, h = round(nx * p.board_square_mm * ppm), round(ny * p.board_square_mm * ppm)
        img = self.charuco_board().generateImage((w, h), marginSize=0, borderBits=1)
        tex = np.where(img > 127, 0.82, 0.03).astype(np.float32)
        return tex, w / (nx * p.board_square_mm)

    def pot_mesh(self) -> TriMesh:
        """Pot wall (outer taper, rim, inner wall) and soil disc, closed."""
        p = self.params
        wall = 3.0
        r_in_top = p.pot_r_top_mm - wall
        frac = (self.soil_z - p.pot_z_bottom_mm) / (p.pot_z_top_mm - p.pot_z_bottom_mm)
        r_in_soil = p.pot_r_bottom_mm + frac * (p.pot_r_top_mm - p.pot_r_bottom_mm) - wall
        wall_mesh = revolve(np.array([
            [0.0, p.pot_z_bottom_mm], [p.pot_r_bottom_mm, p.pot_z_bottom_mm],
            [p.pot_r_top_mm, p.pot_z_top_mm], [r_in_top, p.pot_z_top_mm],
            [r_in_soil, self.soil_z]]), 128, M_POT)
        soil = revolve(np.array([[r_in_soil, self.soil_z], [0.0, self.soil_z]]), 128, M_SOIL)
        return TriMesh.concat([wall_mesh, soil])

    def _backdrop(self) -> TriMesh:
        """Studio sweep in the lab frame: floor, curve, wall behind the plant."""
        floor_z, wall_x, rc = BACKDROP_FLOOR_Z_MM, BACKDROP_WALL_X_MM, 300.0
        arc = np.linspace(0.0, np.pi / 2, 16)
        prof = [(1600.0, floor_z), (wall_x + rc, floor_z)]
        prof += [(wall_x + rc - rc * math.sin(t), floor_z + rc - rc * math.cos(t)) for t in arc[1:]]
        prof += [(wall_x, 2500.0)]
        prof = np.array(prof)
        ys = np.linspace(-2600.0, 2600.0, 2)
        v = np.array([[x, y, z] for x, z in prof for y in ys])
        a = math.radians(self.params.arm_azimuth_deg)
        return TriMesh(v @ rotation_z(math.degrees(a)).T, grid_faces(len(prof), 2),
                       np.full(2 * (len(prof) - 1) * 1, M_BACKDROP, np.int64))

    def _build_world(self) -> None:
        p = self.params
        plate = frustum(-60.0, 0.0, p.plate_radius_mm, p.plate_radius_mm, 160, M_PLATE)
        carrier = frustum(0.0, p.pot_z_bottom_mm, p.carrier_radius_mm, p.carrier_radius_mm, 128,
                          M_CARRIER)
        plant = self.plant
        leaf_ids = sorted(plant.leaf_colours)
        leaf_mat = {lid: M_LEAF0 + k for k, lid in enumerate(leaf_ids)}
        attr = np.array([leaf_mat.get(int(a), M_STEM) for a in plant.mesh.face_attr], np.int64)
        plant_mesh = TriMesh(plant.mesh.vertices, plant.mesh.faces, attr)
        board_parts, tex = self._board()
        world = {
            "background": TriMesh.concat([plate, carrier]),
            "calibration": TriMesh.concat([plate, carrier, *board_parts]),
            "plant": TriMesh.concat([plate, carrier, self.pot_mesh(), plant_mesh]),
        }
        moving = {}
        if p.sway_deg > 0:  # the plant is its own ray-casting scene, displaced per view
            world["plant"] = TriMesh.concat([plate, carrier, self.pot_mesh()])
            moving["plant"] = plant_mesh
        materials = [
            Material((0.62, 0.66, 0.72)),            # backdrop: light blue-grey sweep
            Material((0.20, 0.20, 0.21)),            # turntable plate
            Material((0.45, 0.45, 0.46)),            # pot carrier
            Material((0.035, 0.035, 0.04), CLASS_POT),  # pot wall (dark plastic)
            Material((0.10, 0.07, 0.045), CLASS_POT),   # soil
            Material((0.80, 0.80, 0.78)),            # board panel edges/back
            Material((0.82, 0.82, 0.82), CLASS_BOARD),  # board front (textured)
            Material((0.30, 0.30, 0.30)),            # board post
            Material(plant.stem_colour, CLASS_PLANT),
        ] + [Material(plant.leaf_colours[lid], CLASS_PLANT) for lid in leaf_ids]
        light_lab = rotation_z(p.arm_azimuth_deg) @ np.array(p.light_position_mm, float)
        light = Lighting(light_lab, p.key_light, p.ambient,
                         gamma=p.gamma)
        printed = plate_textures(p.plate_texture, p.plate_radius_mm, p.carrier_radius_mm,
                                 p.pot_z_bottom_mm, p.plate_texture_pitch_mm, p.seed)
        textures = dict(zip((M_PLATE, M_CARRIER), printed))
        if p.backdrop_texture == "aruco":
            textures[M_BACKDROP] = BackdropMarkers(p.arm_azimuth_deg, BACKDROP_WALL_X_MM,
                                                   BACKDROP_FLOOR_Z_MM, p.plate_radius_mm)
        self.renderer = Renderer(world, self._backdrop(), materials, light, tex, M_BOARD,
                                 moving, textures=textures)

    # ------------------------------------------------------------------ axes
    def axis_moved(self, axis: str, true_deg: float) -> None:
        """Called by the sim axes with the TRUE position after each move."""
        with self._lock:
            if axis == "tilt":
                self.true_tilt_deg = float(true_deg)
            else:
                self.true_angle_deg = float(true_deg)

    def true_camera(self, camera: str, tilt_deg: float, angle_deg: float) -> Camera:
        return self.rig.camera(camera, tilt_deg, angle_deg)

    # ------------------------------------------------------------------ rendering
    def view_seed(self, role: str, camera: str, tilt_index: int, angle_index: int) -> list[int]:
        """Noise seed of one view: depends only on the scene seed and the view's key."""
        return [self.params.seed, ("calibration", "background", "plant").index(role),
                self.camera_order.index(camera), tilt_index, angle_index]

    def render_request(self, request: CaptureRequest, camera: str):
        """Render what ``camera`` sees now; returns (BGR image, coverage or None, truth dict)."""
        if self.renderer is None:
            raise DataError("the sim scene was not set up (scan.scene.plugin must be 'sim')")
        with self._lock:
            angle = request.commanded_angle_deg if self.true_angle_deg is None \
                else self.true_angle_deg
            tilt = request.tilt_deg if self.true_tilt_deg is None else self.true_tilt_deg
        cam = self.true_camera(camera, tilt, angle)
        if tuple(request.image_size) != (cam.model.width, cam.model.height):
            raise DataError(f"camera {camera!r}: asked for {request.image_size} px but the rig "
                            f"was set up for {(cam.model.width, cam.model.height)}")
        p = self.params
        ss = p.calibration_supersampling if request.role == "calibration" else p.supersampling
        rng = np.random.default_rng(self.view_seed(request.role, camera, request.tilt_index,
                                                   request.angle_index))
        sway = self.plant_sway(request.tilt_index, request.angle_index) \
            if request.role == "plant" and p.sway_deg > 0 else None
        image, cov = self.renderer.render(request.role, cam, angle, ss, p.noise_sigma, rng,
                                          want_coverage=request.role == "plant", sway=sway)
        truth = {"camera": cam.to_dict(), "true_angle_deg": angle, "true_tilt_deg": tilt,
                 "commanded_angle_deg": request.commanded_angle_deg,
                 "commanded_tilt_deg": request.tilt_deg}
        if sway is not None:
            truth["plant_sway"] = {"R": sway[0].tolist(), "pivot_mm": sway[1].tolist()}
        return image, cov, truth

    def plant_sway(self, tilt_index: int, angle_index: int) -> tuple[np.ndarray, np.ndarray]:
        """Rotation (3, 3) and pivot (3,) mm of the plant at one stop (same for all cameras).

        The plant's vertices ``X`` (plant.npz, rest pose) are at ``pivot + R (X - pivot)``.
        """
        from plantscan_core.data import rotation_about_axis

        rng = np.random.default_rng([self.params.seed, 7, tilt_index, angle_index])
        a = rng.uniform(0.0, 2.0 * np.pi)
        angle = float(rng.normal(0.0, self.params.sway_deg))
        r = rotation_about_axis([math.cos(a), math.sin(a), 0.0], angle)
        return r, np.array([0.0, 0.0, self.soil_z])

    # ------------------------------------------------------------------ checks
    def check_rig(self, planned) -> None:
        """Refuse a rig that cannot work, before anything is rendered (``RigError``)."""
        errors: list[tuple[str, str]] = []
        v = self.plant.mesh.vertices
        radius = float(np.hypot(v[:, 0], v[:, 1]).max())
        z0, z1 = self.params.pot_z_bottom_mm, float(v[:, 2].max())
        # Pot rim and plant points that must be in every plant view.
        a = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        p = self.params
        rims = np.concatenate([
            np.stack([r * np.cos(a), r * np.sin(a), np.full_like(a, z)], 1)
            for r, z in ((p.pot_r_bottom_mm, p.pot_z_bottom_mm), (p.pot_r_top_mm, p.pot_z_top_mm))])
        plant_pts = v[:: max(1, len(v) // 20000)]
        if p.sway_deg > 0:  # the plant must stay in view when it sways by up to 3 sigma
            from plantscan_core.data import rotation_about_axis

            pivot = np.array([0.0, 0.0, self.soil_z])
            plant_pts = np.concatenate([plant_pts] + [
                pivot + (plant_pts - pivot) @ rotation_about_axis(ax, 3.0 * p.sway_deg).T
                for ax in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))])
        pts = np.concatenate([plant_pts, rims])
        corners = self.board_corners()
        _, n, _, _ = self._board_frame()
        board_seen: dict[tuple[str, int], int] = {}
        bad_views = []
        w, h = self.rig.image_size
        for pv in planned:
            cam = self.rig.camera(pv.camera, pv.tilt_deg, pv.angle_deg)
            c = cam.pose.centre
            where = f"camera {pv.camera!r} at tilt {pv.tilt_deg:g} deg"
            if pv.role == "plant":
                if np.hypot(c[0], c[1]) <= radius + 20.0 and z0 - 20.0 <= c[2] <= z1 + 20.0:
                    errors.append((f"scan.cameras ({pv.camera})",
                                   f"{where} is inside the plant (centre {np.round(c, 1)} mm, "
                                   f"plant within {radius:.0f} mm of the axis up to z={z1:.0f}); "
                                   "increase distance_mm"))
                    continue
                if np.any(cam.depth(pts) <= 1.0):
                    bad_views.append((pv, "behind"))
                    continue
                uv = cam.project(pts)
                if not (np.all(uv[:, 0] >= 1) and np.all(uv[:, 0] <= w - 2) and
                        np.all(uv[:, 1] >= 1) and np.all(uv[:, 1] <= h - 2)):
                    bad_views.append((pv, "outside"))
            elif pv.role == "calibration":
                key = (pv.camera, pv.tilt_index)
                board_seen.setdefault(key, 0)
                if self._board_visible(cam, corners, n, pv.angle_deg):
                    board_seen[key] += 1
        if bad_views:
            pv, why = bad_views[0]
            errors.append((f"scan.cameras ({pv.camera})",
                           f"the plant and pot leave the image in {len(bad_views)} plant view(s), "
                           f"e.g. camera {pv.camera!r} tilt {pv.tilt_deg:g} deg angle "
                           f"{pv.angle_deg:g} deg; increase distance_mm or hfov_deg, or set "
                           "target_height_mm"))
        for (camera, ti), count in sorted(board_seen.items()):
            if count == 0:
                errors.append(("scan.scene.params.board_tilt_deg",
                               f"the calibration board is never fully visible to camera "
                               f"{camera!r} at tilt index {ti}; change board_tilt_deg, "
                               "board_height_mm or the camera's elevation"))
        self.board_visibility = {f"{c}/t{t}": n_ for (c, t), n_ in board_seen.items()}
        if errors:
            raise RigError(errors, "virtual scanner rig")

    def _board_visible(self, cam: Camera, corners, normal, angle_deg: float) -> bool:
        n_w = normal  # world frame; the board turns with the plate, the camera view includes it
        c = cam.pose.centre
        to_cam = c - corners.mean(0)
        cosang = float(n_w @ to_cam / np.linalg.norm(to_cam))
        if cosang < math.cos(math.radians(72.0)):
            return False
        uv = cam.project(corners)
        w, h = self.rig.image_size
        m = 0.02 * w
        return bool(np.all(np.isfinite(uv)) and np.all(uv[:, 0] > m) and np.all(uv[:, 0] < w - m)
                    and np.all(uv[:, 1] > m) and np.all(uv[:, 1] < h - m))

    # ------------------------------------------------------------------ truth
    def write_truth(self, scan: ScanFolder) -> None:
        """Write ``ground_truth/`` (docs/formats.md); on resume, reconcile per-view truth."""
        gt = scan.ground_truth_dir
        try:
            gt.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ScanFolderError(f"{gt}: cannot write the ground truth ({exc.strerror})") from exc
        self.rig.calibration().save(gt / "calibration.yaml")
        plant = self.plant
        faces = plant.mesh.faces
        leaf_id = plant.mesh.face_attr.astype(np.int32)
        import io

        buf = io.BytesIO()
        organ = plant.face_organ.astype(np.int8)
        np.savez_compressed(buf, vertices=plant.mesh.vertices, faces=faces, face_leaf_id=leaf_id,
                            face_organ=organ)
        atomic_write_bytes(gt / "plant.npz", buf.getvalue())
        atomic_write_bytes(gt / "plant.ply", ply_bytes(plant.mesh.vertices, faces, leaf_id, organ))
        organs = {"format": "plantscan-sim-organs/1",
                  "organs": dict(enumerate(ORGANS)),
                  "face_area_mm2": {name: float(_area(plant.mesh.vertices,
                                                      faces[organ == code]))
                                    for code, name in enumerate(ORGANS)},
                  "leaves": plant.leaf_records()}
        atomic_write_text(gt / "organs.json", json.dumps(plain(organs), indent=1))
        p = self.params
        pot = {
            "units": "mm, turntable frame (z up from the top of the plate)",
            "pot": {"z_bottom_mm": p.pot_z_bottom_mm, "z_top_mm": p.pot_z_top_mm,
                    "r_bottom_mm": p.pot_r_bottom_mm, "r_top_mm": p.pot_r_top_mm,
                    "soil_z_mm": self.soil_z, "foreground": True},
            "carrier": {"z_bottom_mm": 0.0, "z_top_mm": p.pot_z_bottom_mm,
                        "r_bottom_mm": p.carrier_radius_mm, "r_top_mm": p.carrier_radius_mm,
                        "foreground": False},
            "plate": {"z_bottom_mm": -60.0, "z_top_mm": 0.0, "r_bottom_mm": p.plate_radius_mm,
                      "r_top_mm": p.plate_radius_mm, "foreground": False},
        }
        atomic_write_text(gt / "pot.yaml", yaml.safe_dump(pot, sort_keys=False))
        plant.traits().save(gt / "traits.csv", gt / "plant_traits.json")
        recipe = self.context.recipe
        corners = self.board_corners()
        scene = {
            "format": "plantscan-sim-scene/1",
            "params": self.params.model_dump(mode="json"),
            "seed": p.seed,
            "preset": p.preset,
            "plant": plain(plant.info),
            "rig": {
                "image_size": list(self.rig.image_size),
                "tilts_deg": self.rig.tilts_deg,
                "tilt_axis": self.rig.axis.to_dict(),
                "cameras": {n: c.model_dump(mode="json") for n, c in self.rig.params.items()},
                "turntable": recipe.scan.turntable.model_dump(mode="json"),
                "tilt_arm": None if recipe.scan.tilt_arm is None
                else recipe.scan.tilt_arm.model_dump(mode="json"),
            },
            "board": {
                "pattern": p.board, "squares": list(p.board_squares),
                "square_mm": p.board_square_mm, "tilt_deg": p.board_tilt_deg,
                "inner_corners": [p.board_squares[0] - 1, p.board_squares[1] - 1],
                "charuco": None if p.board != "charuco" else {
                    "dictionary": p.charuco_dictionary, "marker_mm": 0.75 * p.board_square_mm},
                "corners_world_mm": np.round(corners, 6).tolist(),
                "lowest_corner_z_mm": float(corners[:, 2].min()),
                "views_fully_visible": getattr(self, "board_visibility", {}),
            },
            "true_angles": "per view in cameras.jsonl (true_angle_deg, true_tilt_deg)",
            "foreground": "pot + plant (masks/)",
        }
        atomic_write_text(gt / "scene.yaml", yaml.safe_dump(plain(scene), sort_keys=False))
        finalize_truth(scan)

    def stage_view_truth(self, scan: ScanFolder, rel_image: str, truth: dict,
                         coverage: np.ndarray | None) -> None:
        """Keep the truth of one image until its index is known (see ``finalize_truth``)."""
        import cv2

        base = _staging_base(scan, rel_image)
        base.parent.mkdir(parents=True, exist_ok=True)
        if coverage is not None:
            ok, png = cv2.imencode(".png", np.where(coverage >= 0.5, 255, 0).astype(np.uint8))
            atomic_write_bytes(base.with_name(base.name + ".mask.png"), png.tobytes())
        atomic_write_text(base.with_name(base.name + ".json"), json.dumps(truth))


def soil_height(p: SimSceneParams) -> float:
    """Height of the soil surface (mm, turntable frame) of the scene's pot."""
    return p.pot_z_top_mm - p.soil_depth_mm


def scene_ground(p: SimSceneParams) -> Ground:
    """Soil and pot rim the plant's blades must clear (mm, turntable frame)."""
    soil = soil_height(p)
    frac = (soil - p.pot_z_bottom_mm) / (p.pot_z_top_mm - p.pot_z_bottom_mm)
    r_in_soil = p.pot_r_bottom_mm + frac * (p.pot_r_top_mm - p.pot_r_bottom_mm) - 3.0
    return Ground(soil, p.pot_z_top_mm, r_in_soil, p.pot_r_top_mm, p.pot_z_bottom_mm)


def scene_plant(p: SimSceneParams) -> Plant:
    """The plant a scene with parameters ``p`` holds: its truth, without a rig or a render."""
    return build_plant(p.preset, p.seed, soil_height(p), p.leaf_thickness_mm, p.mesh_path,
                       p.mesh_labels_path, p.mesh_scale, age=p.age, ground=scene_ground(p))


def _staging_base(scan: ScanFolder, rel_image: str) -> Path:
    rel = Path(rel_image)
    parts = rel.parts[1:] if rel.parts and rel.parts[0] == "images" else rel.parts
    return scan.ground_truth_dir / TRUTH_VIEWS_DIR / Path(*parts).with_suffix("")


def finalize_truth(scan: ScanFolder) -> int:
    """Write ``cameras.jsonl`` and ``masks/<index>.png`` for every view in ``views.jsonl``.

    A view's index is only known once the orchestrator lists it, so per-view
    truth is staged by image name under ``ground_truth/views/`` and joined here;
    idempotent (called when a sim camera closes and when a scan resumes).
    Returns the number of views with truth.
    """
    scan = ScanFolder.open(scan.root)
    gt = scan.ground_truth_dir
    lines = []
    masks = gt / "masks"
    for view in scan.views:
        base = _staging_base(scan, view.file)
        js = base.with_name(base.name + ".json")
        if not js.exists():
            continue
        truth = json.loads(js.read_text())
        lines.append(json.dumps({"index": view.index, "file": view.file, **truth},
                                sort_keys=True))
        mask = base.with_name(base.name + ".mask.png")
        if view.role == "plant" and mask.exists():
            masks.mkdir(parents=True, exist_ok=True)
            dst = masks / f"{view.index:05d}.png"
            if dst.exists() and os.path.samefile(dst, mask):
                continue
            tmp = dst.with_name(f".{dst.name}.tmp")
            tmp.unlink(missing_ok=True)
            try:
                os.link(mask, tmp)
            except OSError:
                shutil.copyfile(mask, tmp)
            os.replace(tmp, dst)
    atomic_write_text(gt / "cameras.jsonl", "".join(line + "\n" for line in lines))
    return len(lines)


def read_truth_cameras(truth_dir: Path) -> dict[int, Camera]:
    """Index -> exact Camera of every view, from ``ground_truth/cameras.jsonl``."""
    path = Path(truth_dir) / "cameras.jsonl"
    if not path.exists():
        raise DataError(f"{path}: not found (is this a virtual scan?)")
    out = {}
    for line in path.read_text().splitlines():
        if line.strip():
            d = json.loads(line)
            out[int(d["index"])] = Camera.from_dict(d["camera"])
    return out


def _area(vertices: np.ndarray, faces: np.ndarray) -> float:
    t = vertices[faces]
    return 0.5 * float(np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())


def ply_bytes(vertices: np.ndarray, faces: np.ndarray, face_leaf_id: np.ndarray,
              face_organ: np.ndarray | None = None) -> bytes:
    """Binary little-endian PLY with per-face ``leaf_id`` and ``organ`` properties."""
    if face_organ is None:
        face_organ = np.where(face_leaf_id >= 0, ORGANS.index("blade"), 0)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment plantscan virtual plant, mm\n"
        f"comment organ codes: {' '.join(f'{c}={n}' for c, n in enumerate(ORGANS))}\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
        "property int leaf_id\nproperty uchar organ\nend_header\n"
    ).encode()
    fdt = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("leaf", "<i4"), ("organ", "u1")])
    fa = np.empty(len(faces), dtype=fdt)
    fa["n"] = 3
    fa["v"] = faces
    fa["leaf"] = face_leaf_id
    fa["organ"] = face_organ
    return header + vertices.astype("<f4").tobytes() + fa.tobytes()


def scene_of(context: Any) -> SimScene:
    """The sim scene of an acquisition (``context.shared['sim_scene']``)."""
    scene = context.shared.get(SHARED_KEY) if context is not None else None
    if scene is None:
        from plantscan_core.errors import HardwareError

        raise HardwareError("sim cameras and axes need the virtual scene: add "
                            "'scene: {plugin: sim}' to the recipe's scan section")
    return scene


__all__ = ["SimScene", "SimSceneParams", "RigError", "finalize_truth", "read_truth_cameras",
           "PRESETS", "ViewRecord", "Pose"]
