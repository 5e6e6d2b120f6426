"""Recipes: one YAML per species / scan protocol, validated in full before anything runs.

A recipe names the plugin and parameters of every stage and the scan
protocol.  ``load_recipe`` reports *every* error at once as ``path: message``
(``segment.params.alpha: Input should be greater than or equal to 0``); plugin
names resolve only through the registry, never as import paths.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import ConfigDict, Field, ValidationError, field_validator

from plantscan_core.bounds import CheckedModel, FiniteFloat, ImageSidePx, error_path
from plantscan_core.data import ROLES
from plantscan_core.errors import PluginError, RecipeError
from plantscan_core.metadata import ExperimentSpec, PlantSpec
from plantscan_core.steps import CORE_TABLE, StageTable
from plantscan_core.trajectory import (
    TRAJECTORY_KINDS,
    RigLimits,
    Stop,
    Trajectory,
    duplicate_stops,
)
from plantscan_core.userfiles import InputFileError, load_yaml, parse_yaml


class _Model(CheckedModel):
    pass


class StageSpec(_Model):
    """Which plugin runs a stage, with its parameters (checked by the plugin's ``Params``)."""

    plugin: str
    params: dict[str, Any] = Field(default_factory=dict)


class SegmentSpec(StageSpec):
    """The segmenter, and the image resolution it works at."""

    reduce: Literal[1, 2, 4, 8, "auto"] = Field(
        default="auto",
        description="decode plant images at 1/reduce of their size (JPEG DCT scaling: faster, "
                    "4x less memory per step); masks and the hull then work at that size. "
                    "auto: the largest reduction that keeps the image's long side >= "
                    "2400 px (18 MP -> 2, 3000x2000 and smaller -> 1; docs/decisions.md)")
    bad_images: Literal["error", "skip"] = Field(
        default="error",
        description="a plant image that cannot be trusted (truncated, corrupt, or another size "
                    "than its camera's other images): stop with an error naming it, or skip "
                    "that view with a warning (run.json quality.views_skipped says how many)")


class CameraSpec(StageSpec):
    """A camera of the rig: its name (used in views and calibration) and its plugin."""

    name: str


class RoleSpec(_Model):
    """How one role of the protocol is captured; unset fields fall back to the scan's."""

    enabled: bool = True
    tilts_deg: list[FiniteFloat] | None = Field(default=None, min_length=1)
    images_per_revolution: int | None = Field(default=None, ge=1, le=3600)


class AdaptiveSpec(_Model):
    """``plantscan scan --adaptive``: plan more plant views where the hull is unsure.

    After the base views (the plant role's grid or trajectory) the scan is
    processed quickly (a coarse hull), the recipe's ``plan`` stage chooses the
    next stops among the candidates, they are captured, and so on until the
    predicted gain is small or a budget is spent (docs/trajectories.md).
    """

    max_plant_images: int = Field(100, ge=1, le=100_000,
                                  description="plant images of the whole scan, base included")
    max_capture_s: float | None = Field(
        360.0, gt=0.0, le=1e6, description="capture time of the plant role by the timing "
        "model, base included (null: no time budget)")
    tilts_deg: list[FiniteFloat] | None = Field(
        None, min_length=1, description="tilts the planner may choose (each gets a background "
        "plate per camera); default: the plant views' tilts")
    pan_step_deg: float = Field(5.0, ge=0.1, le=90.0,
                                description="candidate turntable angles every this many deg")
    stops_per_round: int = Field(8, ge=1, le=1000,
                                 description="stops planned per round (before re-planning)")
    max_rounds: int = Field(4, ge=1, le=100)
    min_gain_fraction: float = Field(
        0.005, ge=0.0, le=1.0, description="stop when a round is predicted to carve less than "
        "this share of the hull's volume")
    resolution: int = Field(128, ge=16, le=1024,
                            description="voxels along the longest side of the coarse hull the "
                            "planner works on (reconstruct.params.resolution of the quick runs)")


def _default_roles() -> dict[str, RoleSpec]:
    return {
        "calibration": RoleSpec(),
        "background": RoleSpec(images_per_revolution=1),
        "plant": RoleSpec(),
    }


class ScanSpec(_Model):
    """The rig and the scan protocol."""

    protocol: str = "custom"
    cameras: list[CameraSpec] = Field(min_length=1)
    turntable: StageSpec
    tilt_arm: StageSpec | None = None
    scene: StageSpec | None = None
    tilts_deg: list[FiniteFloat] = Field(default_factory=lambda: [0.0], min_length=1)
    images_per_revolution: int = Field(default=36, ge=1, le=3600)
    image_size: tuple[ImageSidePx, ImageSidePx] = (1200, 800)
    image_format: Literal["png", "jpg"] = "png"
    jpeg_quality: int = Field(default=95, ge=1, le=100)
    roles: dict[str, RoleSpec] = Field(default_factory=_default_roles)
    trajectory: Trajectory | None = Field(
        None, description="the plant views as (pan, tilt) stops: a list or a generator "
        "(grid, per-tilt, spiral, golden-angle, views); default: tilts_deg x "
        "images_per_revolution (docs/trajectories.md)")
    limits: RigLimits = Field(default_factory=RigLimits,
                              description="what the rig can do: tilt travel, axis speeds")
    adaptive: AdaptiveSpec | None = Field(
        None, description="settings of plantscan scan --adaptive (defaults when absent)")

    @field_validator("image_size")
    @classmethod
    def _positive_size(cls, v: tuple[int, int]) -> tuple[int, int]:
        if v[0] < 16 or v[1] < 16:
            raise ValueError("image size must be at least 16 x 16 px")
        return v

    @field_validator("roles")
    @classmethod
    def _known_roles(cls, v: dict[str, RoleSpec]) -> dict[str, RoleSpec]:
        bad = sorted(set(v) - set(ROLES))
        if bad:
            raise ValueError(f"unknown role(s) {bad}; valid: {', '.join(ROLES)}")
        return v

    @field_validator("cameras")
    @classmethod
    def _unique_camera_names(cls, v: list[CameraSpec]) -> list[CameraSpec]:
        names = [c.name for c in v]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"camera names must be unique; repeated: {dup}")
        return v

    def role_tilts(self, role: str) -> list[float]:
        """The distinct tilts of ``role``'s stops, in order.

        The background plates default to every tilt a plant view may be taken
        at: the plant views' and the adaptive planner's candidates.
        """
        spec = self.roles.get(role)
        if role == "plant" and self.trajectory is not None:
            return _distinct(s.tilt_deg for s in self.trajectory.stops())
        if spec and spec.tilts_deg is not None:
            return list(spec.tilts_deg)
        if role == "background":
            return _distinct([*self.tilts_deg, *self.role_tilts("plant"),
                              *self.adaptive_tilts()])
        return list(self.tilts_deg)

    def role_angles(self, role: str) -> list[float]:
        """Commanded turntable angles (deg) of ``role``'s grid: evenly spaced over a revolution."""
        spec = self.roles.get(role)
        n = spec.images_per_revolution if spec and spec.images_per_revolution else None
        n = n or self.images_per_revolution
        return [i * 360.0 / n for i in range(n)]

    def role_stops(self, role: str) -> list[Stop]:
        """The rig positions of ``role`` (the plant's trajectory, else tilts x angles)."""
        if role == "plant" and self.trajectory is not None:
            return self.trajectory.stops()
        angles = self.role_angles(role)
        return [Stop(a, t, i) for t in self.role_tilts(role) for i, a in enumerate(angles)]

    def adaptive_tilts(self) -> list[float]:
        """Tilts the adaptive planner may choose (``adaptive.tilts_deg``, default the plant's)."""
        if self.adaptive is None or self.adaptive.tilts_deg is None:
            return self.role_tilts("plant") if self.adaptive is not None else []
        return list(self.adaptive.tilts_deg)

    def enabled_roles(self) -> list[str]:
        return [r for r in ROLES if r in self.roles and self.roles[r].enabled]


def _distinct(values) -> list[float]:
    out: list[float] = []
    for v in values:
        if v not in out:
            out.append(float(v))
    return out


class Recipe(_Model):
    """A whole recipe.  Processing stages are optional (a recipe may only scan).

    The processing sections are the stage table's (``plantscan_core.steps``):
    one field per core step below; a step a plugin adds to its registry's
    table is a section too (an extra key, checked against the registry's
    table by ``validate_recipe``: any other key is an error).
    """

    model_config = ConfigDict(extra="allow")
    __pydantic_extra__: dict[str, StageSpec | None] = Field(init=False)

    name: str = "recipe"
    description: str = ""
    experiment: ExperimentSpec = Field(default_factory=ExperimentSpec)
    plant: PlantSpec = Field(default_factory=PlantSpec)
    scan: ScanSpec
    calibrate: StageSpec | None = None
    segment: SegmentSpec | None = None
    reconstruct: StageSpec | None = None
    plan: StageSpec | None = Field(None, description="the view planner (plugin next-best-view): "
                                   "where more views would carve the hull (plantscan plan, "
                                   "plantscan scan --adaptive)")
    mesh: StageSpec | None = None
    segment_mesh: StageSpec | None = None
    measure: StageSpec | None = None
    export: list[StageSpec] = Field(default_factory=list)
    store: StageSpec | None = Field(None, description="the results store the run is kept in "
                                    "after the exporters (plugin sqlite or postgresql; "
                                    "docs/experiments.md)")


PROCESSING_SECTIONS: dict[str, str] = {s.section: s.stage for s in CORE_TABLE if not s.many}
"""Recipe section -> stage kind of the core's steps (exporters aside), in pipeline order."""


def _table(registry) -> StageTable:
    return registry.steps if registry is not None else CORE_TABLE


def stage_spec(recipe: Recipe, section: str) -> StageSpec | list[StageSpec] | None:
    """The recipe's spec of a step's ``section`` (a field, or an added step's extra key)."""
    if section in Recipe.model_fields:
        return getattr(recipe, section)
    return (recipe.model_extra or {}).get(section)


# --------------------------------------------------------------------------- overrides
def parse_override(text: str) -> tuple[list[str], Any]:
    """``"scan.image_size=[1200,800]"`` -> (["scan", "image_size"], [1200, 800])."""
    if "=" not in text:
        raise RecipeError([("--set", f"{text!r}: expected PATH=VALUE")])
    path, _, value = text.partition("=")
    keys = [k for k in path.strip().split(".") if k]
    if not keys:
        raise RecipeError([("--set", f"{text!r}: empty path")])
    try:
        parsed = parse_yaml(value, "--set") if value.strip() else ""
    except InputFileError as exc:
        raise RecipeError([(error_path(tuple(keys)), f"--set value {value!r}: {exc.detail}")],
                          "--set") from None
    return keys, parsed


def apply_overrides(raw: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``--set PATH=VALUE`` overrides to a raw recipe dict (list items by index)."""
    errors: list[tuple[str, str]] = []
    for text in overrides:
        keys, value = parse_override(text)
        node: Any = raw
        for i, key in enumerate(keys):
            last = i == len(keys) - 1
            where = error_path(tuple(keys[: i + 1]))
            if isinstance(node, list):
                if not key.isdigit() or int(key) >= len(node):
                    errors.append((where, f"no list item {key} (list has {len(node)})"))
                    break
                if last:
                    node[int(key)] = value
                else:
                    node = node[int(key)]
            elif isinstance(node, dict):
                if last:
                    node[key] = value
                else:
                    if node.get(key) is None:
                        node[key] = {}
                    node = node[key]
            else:
                errors.append((where, f"cannot set inside a {type(node).__name__}"))
                break
    if errors:
        raise RecipeError(errors, "--set")
    return raw


# --------------------------------------------------------------------------- validation
_loc = error_path


def _stage_specs(recipe: Recipe, table: StageTable = CORE_TABLE
                 ) -> list[tuple[str, str, StageSpec]]:
    """(recipe path, stage kind, spec) of every stage the recipe names."""
    out: list[tuple[str, str, StageSpec]] = []
    for i, cam in enumerate(recipe.scan.cameras):
        out.append((f"scan.cameras.{i}", "camera", cam))
    out.append(("scan.turntable", "axis", recipe.scan.turntable))
    if recipe.scan.tilt_arm is not None:
        out.append(("scan.tilt_arm", "axis", recipe.scan.tilt_arm))
    if recipe.scan.scene is not None:
        out.append(("scan.scene", "scene", recipe.scan.scene))
    for step in table:
        spec = stage_spec(recipe, step.section)
        if step.many:
            out += [(f"{step.section}.{i}", step.stage, s) for i, s in enumerate(spec or [])]
        elif spec is not None:
            out.append((step.section, step.stage, spec))
    return out


def validate_recipe(raw: Any, registry=None, source: str = "recipe") -> Recipe:
    """Validate a raw recipe dict in full; raise ``RecipeError`` with every error.

    With a ``registry`` (``plantscan_core.plugins.StageRegistry``) plugin names
    and each plugin's parameters are checked too, and the sections of the
    steps it added are known; without one, the core's table.
    """
    if not isinstance(raw, dict):
        raise RecipeError([("", "a recipe must be a YAML mapping")], source)
    unknown = _unknown_sections(raw, _table(registry))
    try:
        recipe = Recipe.model_validate(raw)
    except ValidationError as exc:
        errors = unknown + [(_loc(_trajectory_loc(e["loc"])), e["msg"]) for e in exc.errors()
                            if not e["loc"] or e["loc"][0] not in dict(unknown)]
        # Still check the plugin sections that parsed, so all errors come out together.
        errors += _check_plugins_raw(raw, registry)
        raise RecipeError(errors, source) from None
    errors = unknown + (check_plugins(recipe, registry) + check_limits(recipe, registry)
                        if registry is not None else [])
    errors += _check_protocol(recipe)
    if errors:
        raise RecipeError(errors, source)
    return recipe


def _unknown_sections(raw: dict[str, Any], table: StageTable) -> list[tuple[str, str]]:
    known = set(Recipe.model_fields) | set(table.sections)
    return [(error_path((key,)), f"unknown recipe section; sections: {', '.join(sorted(known))}")
            for key in sorted(set(raw) - known, key=str)]


def _check_protocol(recipe: Recipe) -> list[tuple[str, str]]:
    errors: list[tuple[str, str]] = []
    scan = recipe.scan
    if len(scan.tilts_deg) > 1 and scan.tilt_arm is None:
        errors.append(("scan.tilt_arm", f"{len(scan.tilts_deg)} tilts need a tilt_arm axis"))
    # Checked here, not in the model, so that a bad tilt does not hide the other protocol errors.
    tilt_lists = [("scan.tilts_deg", scan.tilts_deg)] + [
        (f"scan.roles.{role}.tilts_deg", spec.tilts_deg) for role, spec in scan.roles.items()
        if spec.tilts_deg is not None]
    if scan.adaptive is not None and scan.adaptive.tilts_deg is not None:
        tilt_lists.append(("scan.adaptive.tilts_deg", scan.adaptive.tilts_deg))
    for where, tilts in tilt_lists:
        for i, t in enumerate(tilts):
            if not -90.0 <= t <= 90.0:
                errors.append((f"{where}.{i}", f"tilt {t:g} outside [-90, 90] deg"))
            elif not scan.limits.tilt_ok(t):
                errors.append((f"{where}.{i}", _outside_limits(t, scan)))
    errors += _check_trajectory(scan)
    plant_on = "plant" in scan.roles and scan.roles["plant"].enabled
    if plant_on and "background" in scan.roles and scan.roles["background"].enabled:
        bg = set(scan.role_tilts("background"))
        for what, tilts in (("plant", scan.role_tilts("plant")),
                            ("adaptive", scan.adaptive_tilts())):
            if not set(tilts) <= bg:
                errors.append(("scan.roles.background.tilts_deg",
                               f"{what} tilts {sorted(set(tilts) - bg)} have no background "
                               "plate"))
    calibration = scan.roles.get("calibration")
    if plant_on and calibration is not None and calibration.enabled \
            and recipe.calibrate is not None:
        cal = set(scan.role_tilts("calibration"))
        other = (set(scan.role_tilts("plant")) | set(scan.adaptive_tilts())) - cal
        if other and len(cal) < 2:
            errors.append(("scan.roles.calibration.tilts_deg",
                           f"plant tilts {sorted(other)} are not calibrated, and one "
                           "calibration tilt cannot give the tilt axis their cameras come "
                           "from: calibrate at two tilts or more"))
    return errors


def _outside_limits(tilt: float, scan: ScanSpec) -> str:
    lo, hi = scan.limits.tilt_deg
    return f"tilt {tilt:g} outside the rig's tilt range [{lo:g}, {hi:g}] deg (scan.limits.tilt_deg)"


# A recipe lists at most this many stops outside the rig's limits (the count is given).
MAX_STOP_ERRORS = 5


def _check_trajectory(scan: ScanSpec) -> list[tuple[str, str]]:
    """The plant trajectory: inside the rig's limits, no stop twice, one way of giving it."""
    traj = scan.trajectory
    if traj is None:
        return []
    errors: list[tuple[str, str]] = []
    plant = scan.roles.get("plant")
    if plant is not None and (plant.tilts_deg is not None or plant.images_per_revolution):
        errors.append(("scan.roles.plant", "give the plant views either as scan.trajectory or "
                       "as roles.plant.tilts_deg / images_per_revolution, not both"))
    stops = traj.stops()
    bad = [(i, s) for i, s in enumerate(stops)
           if not -90.0 <= s.tilt_deg <= 90.0 or not scan.limits.tilt_ok(s.tilt_deg)]
    for i, s in bad[:MAX_STOP_ERRORS]:
        where = f"scan.trajectory.views.{i}" if traj.kind == "views" else "scan.trajectory"
        errors.append((where, f"stop {i} (pan {s.pan_deg:g}, tilt {s.tilt_deg:g} deg): "
                       + _outside_limits(s.tilt_deg, scan)))
    if len(bad) > MAX_STOP_ERRORS:
        errors.append(("scan.trajectory", f"{len(bad)} stops in all are outside the rig's tilt "
                       "range"))
    for first, again in duplicate_stops(stops)[:MAX_STOP_ERRORS]:
        errors.append(("scan.trajectory", f"stop {again} repeats stop {first} (pan "
                       f"{stops[first].pan_deg:g}, tilt {stops[first].tilt_deg:g} deg)"))
    tilts = {s.tilt_deg for s in stops} | set(scan.adaptive_tilts())
    if len(tilts) > 1 and scan.tilt_arm is None:
        errors.append(("scan.tilt_arm", f"the plant views' {len(tilts)} tilts need a tilt_arm "
                       "axis"))
    return errors


def check_limits(recipe: Recipe, registry) -> list[tuple[str, str]]:
    """Axis speeds set above the rig's limits (``scan.limits``), from each plugin's Params."""
    errors: list[tuple[str, str]] = []
    lim = recipe.scan.limits
    for key, spec in (("turntable", recipe.scan.turntable), ("tilt", recipe.scan.tilt_arm)):
        if spec is None:
            continue
        where = "scan.turntable" if key == "turntable" else "scan.tilt_arm"
        try:
            params = registry.get("axis", spec.plugin).cls.Params.model_validate(spec.params)
        except (PluginError, ValidationError):
            continue  # reported by check_plugins
        for name, unit in (("velocity", "deg/s"), ("acceleration", "deg/s²")):
            limit = getattr(lim, f"{key}_{name}_deg_s" + ("2" if name == "acceleration" else ""))
            value = getattr(params, f"{name}_deg_s" + ("2" if name == "acceleration" else ""),
                            None)
            if limit is not None and value is not None and float(value) > limit + 1e-9:
                field = f"{name}_deg_s" + ("2" if name == "acceleration" else "")
                errors.append((f"{where}.params.{field}",
                               f"{float(value):g} {unit} is more than the rig allows "
                               f"(scan.limits.{key}_{field}: {limit:g})"))
    return errors


def _trajectory_loc(loc: tuple) -> tuple:
    """A pydantic location without the tag of the trajectory kind (``scan.trajectory.stops``)."""
    out = list(loc)
    for i in range(len(out) - 1):
        if out[i] == "trajectory" and out[i + 1] in TRAJECTORY_KINDS:
            del out[i + 1]
            break
    return tuple(out)


def check_plugins(recipe: Recipe, registry) -> list[tuple[str, str]]:
    errors: list[tuple[str, str]] = []
    for path, stage, spec in _stage_specs(recipe, _table(registry)):
        errors += _check_one(path, stage, spec.plugin, spec.params, registry)
    return errors


def _check_one(path: str, stage: str, plugin: str, params: Any, registry) -> list[tuple[str, str]]:
    if registry is None:
        return []
    try:
        reg = registry.get(stage, plugin)
    except PluginError as exc:
        return [(f"{path}.plugin", str(exc))]
    if not isinstance(params, dict):
        return [(f"{path}.params", "must be a mapping")]
    try:
        reg.cls.Params.model_validate(params)
    except ValidationError as exc:
        return [(f"{path}.params.{_loc(e['loc'])}".rstrip("."), e["msg"]) for e in exc.errors()]
    return []


def _check_plugins_raw(raw: dict[str, Any], registry) -> list[tuple[str, str]]:
    """Plugin checks on a recipe that failed structural validation (best effort)."""
    if registry is None:
        return []
    errors: list[tuple[str, str]] = []
    candidates: list[tuple[str, str, Any]] = []
    scan = raw.get("scan") if isinstance(raw.get("scan"), dict) else {}
    for i, cam in enumerate(scan.get("cameras") or [] if isinstance(scan, dict) else []):
        candidates.append((f"scan.cameras.{i}", "camera", cam))
    for key, stage in (("turntable", "axis"), ("tilt_arm", "axis"), ("scene", "scene")):
        candidates.append((f"scan.{key}", stage, scan.get(key)))
    for step in registry.steps:
        spec = raw.get(step.section)
        if step.many:
            candidates += [(f"{step.section}.{i}", step.stage, s)
                           for i, s in enumerate(spec if isinstance(spec, list) else [])]
        else:
            candidates.append((step.section, step.stage, spec))
    for path, stage, spec in candidates:
        if isinstance(spec, dict) and isinstance(spec.get("plugin"), str):
            errors += _check_one(path, stage, spec["plugin"], spec.get("params") or {}, registry)
    return errors


def read_recipe_file(path: Path) -> dict[str, Any]:
    """The raw recipe mapping of a YAML file (UTF-8, bounded; ``RecipeError`` naming file:line)."""
    path = Path(path)
    try:
        raw = load_yaml(path)
    except InputFileError as exc:
        where = f"{path}:{exc.line}" if exc.line is not None else str(path)
        raise RecipeError([("", exc.detail)], where) from None
    return raw if raw is not None else {}


def _shipped_recipes_dir() -> Path:
    """The folder of the shipped recipes: ``recipes/`` of a source checkout, else the copy
    a wheel installs under ``<prefix>/share/plantscan/recipes`` (``pip install``)."""
    checkout = Path(__file__).resolve().parent.parent / "recipes"
    if checkout.is_dir():
        return checkout
    from importlib import metadata

    try:
        dist = metadata.distribution("plantscan")
        for f in dist.files or []:
            if f.name.endswith(".yaml") and f.parent.name == "recipes" \
                    and "share" in f.parts:
                return Path(dist.locate_file(f)).resolve().parent
    except metadata.PackageNotFoundError:
        pass
    return checkout


RECIPES_DIR = _shipped_recipes_dir()


def shipped_recipes() -> list[str]:
    """Names of the shipped recipes (``plantscan recipe list``), sorted."""
    return sorted(p.stem for p in RECIPES_DIR.glob("*.yaml"))


def resolve_recipe_path(name_or_path: str | Path) -> Path:
    """A recipe file path, or a bare name of a file in the shipped ``recipes/`` folder.

    A path that does not exist but names a shipped recipe (``recipes/plastic-dicot.yaml``
    outside the checkout) is an error that says to use the name instead.
    """
    p = Path(name_or_path)
    if p.exists():
        return p
    if p.suffix in (".yaml", ".yml") or "/" in str(name_or_path):
        if (RECIPES_DIR / f"{p.stem}.yaml").exists():
            raise RecipeError([("", f"no such file; plantscan ships a recipe of that name: "
                                    f"use `{p.stem}` (works from any folder; `plantscan recipe "
                                    "list` shows them all)")], str(p))
        return p
    shipped = RECIPES_DIR / f"{name_or_path}.yaml"
    return shipped if shipped.exists() else p


def load_recipe(path: str | Path, overrides: list[str] | None = None, registry=None) -> Recipe:
    """Read, override (``--set``) and validate a recipe file."""
    path = resolve_recipe_path(path)
    raw = apply_overrides(read_recipe_file(path), list(overrides or []))
    return validate_recipe(raw, registry, str(path))


def recipe_json_schema() -> dict[str, Any]:
    """JSON Schema of recipes (plugin parameters are checked by each plugin's Params)."""
    return Recipe.model_json_schema()
