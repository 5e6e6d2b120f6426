"""Who a plant is: MIAPPE-named metadata in recipes, overridable per plant by a sample sheet.

A recipe's ``experiment:`` section names the MIAPPE 1.1 *investigation* and
*study* a scan belongs to; its ``plant:`` section the *observation unit* (the
plant: ``id``) and its *biological material* (species, genotype, accession),
*factor values* (``treatment`` and any ``factors``), ``replicate``,
``sowing_date`` and free key-values (``extra``).  A **sample sheet** (CSV: one
row per scan folder or plant id) overrides them plant by plant for ``scan``,
``process``, ``batch`` and ``store``; ``docs/experiments.md`` shows one.

Values left empty are "not given": resolving a plant's metadata takes, field by
field, the last value given in recipe < the scan's own record (``scan.yaml``)
< the sample sheet row (``resolve_metadata``).
"""

from __future__ import annotations

import csv
import datetime as _dt
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from plantscan_core.errors import RecipeError


class _Meta(BaseModel):
    model_config = ConfigDict(extra="forbid")

    @field_validator("*", mode="before")
    @classmethod
    def _scalars_as_text(cls, v: Any, info) -> Any:
        # YAML reads `genotype: 1` as an int and `accession: no` as a bool: text fields keep
        # what the user wrote (as YAML gave it) instead of refusing it.
        annotation = cls.model_fields[info.field_name].annotation
        if annotation is str and isinstance(v, (int, float, bool)):
            return str(v)
        return v


def _text_map(v: Any, what: str) -> dict[str, str]:
    if v is None:
        return {}
    if not isinstance(v, dict):
        raise ValueError(f"{what} must be a mapping of name: value")
    out = {}
    for k, x in v.items():
        if isinstance(x, (dict, list)):
            raise ValueError(f"{what}.{k}: must be a single value, not a {type(x).__name__}")
        out[str(k)] = "" if x is None else str(x)
    return out


def parse_date(v: Any) -> _dt.date | None:
    """A calendar date from a ``date`` or an ISO 8601 ``YYYY-MM-DD`` string (else ValueError).

    Numbers are refused: ``20260301`` is not read as seconds since 1970.
    """
    if v is None or v == "":
        return None
    if isinstance(v, _dt.datetime):
        return v.date()
    if isinstance(v, _dt.date):
        return v
    if isinstance(v, str):
        try:
            return _dt.date.fromisoformat(v.strip())
        except ValueError:
            pass
    raise ValueError(f"{v!r} is not a date (write it as YYYY-MM-DD)")


class ExperimentSpec(_Meta):
    """The MIAPPE investigation and study a scan belongs to (``experiment:``)."""

    investigation_id: str = Field("", description="MIAPPE Investigation unique ID")
    investigation_title: str = ""
    study_id: str = Field("", description="MIAPPE Study unique ID: one experiment of the "
                          "investigation; plants, scans and traits are grouped by it")
    study_title: str = ""
    description: str = ""
    location: str = Field("", description="MIAPPE Experimental site name (growth chamber, "
                          "greenhouse...)")
    start_date: _dt.date | None = Field(None, description="MIAPPE Start date of study")
    extra: dict[str, str] = Field(default_factory=dict, description="free key-values")

    @field_validator("start_date", mode="before")
    @classmethod
    def _start_date(cls, v: Any) -> _dt.date | None:
        return parse_date(v)

    @field_validator("extra", mode="before")
    @classmethod
    def _extra(cls, v: Any) -> dict[str, str]:
        return _text_map(v, "extra")


class PlantSpec(_Meta):
    """The plant (MIAPPE observation unit) and its biological material (``plant:``)."""

    id: str = Field("plant", min_length=1, description="MIAPPE Observation unit ID: the "
                    "same plant keeps its id on every day it is scanned")
    species: str = Field("", description="MIAPPE Organism (e.g. Arabidopsis thaliana)")
    genotype: str = Field("", description="genotype or line (e.g. Col-0)")
    accession: str = Field("", description="MIAPPE Material source ID (seed stock accession)")
    biological_material_id: str = Field("", description="MIAPPE Biological material ID")
    treatment: str = Field("", description="the treatment group (e.g. drought)")
    factors: dict[str, str] = Field(default_factory=dict, description="MIAPPE Experimental "
                                    "factor type -> value (e.g. watering: 30%)")
    replicate: int | None = Field(None, ge=1, le=1_000_000)
    sowing_date: _dt.date | None = None
    extra: dict[str, str] = Field(default_factory=dict, description="free key-values")

    @field_validator("sowing_date", mode="before")
    @classmethod
    def _sowing_date(cls, v: Any) -> _dt.date | None:
        return parse_date(v)

    @field_validator("factors", "extra", mode="before")
    @classmethod
    def _maps(cls, v: Any, info) -> dict[str, str]:
        return _text_map(v, info.field_name)

    @field_validator("replicate", mode="before")
    @classmethod
    def _replicate(cls, v: Any) -> Any:
        if isinstance(v, bool) or isinstance(v, float) and not v.is_integer():
            raise ValueError(f"{v!r} is not a whole number")
        return None if v == "" else v


# The plant fields that say what a plant *is*: one plant id cannot have two of them.
PLANT_IDENTITY_FIELDS = ("species", "genotype", "accession", "biological_material_id",
                         "treatment", "factors", "replicate", "sowing_date")


# --------------------------------------------------------------------------- resolution
def _given(v: Any) -> bool:
    return v not in (None, "", {})


def merge_metadata(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``base`` with every value *given* in ``over``; ``factors``/``extra`` merge key by key."""
    out = dict(base)
    for k, v in over.items():
        if not _given(v):
            continue
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = {**out[k], **{kk: vv for kk, vv in v.items() if _given(vv)}}
        else:
            out[k] = v
    return out


@dataclass
class Metadata:
    """The resolved metadata of one scan: its plant and its experiment."""

    plant: PlantSpec
    experiment: ExperimentSpec

    def to_dict(self) -> dict[str, Any]:
        return {"plant": self.plant.model_dump(mode="json"),
                "experiment": self.experiment.model_dump(mode="json")}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Metadata:
        return cls(PlantSpec.model_validate(d.get("plant") or {}),
                   ExperimentSpec.model_validate(d.get("experiment") or {}))


def scan_record(scan_info: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """What a scan folder says of its plant and experiment (``scan.yaml``), older scans too."""
    plant = dict(scan_info.get("plant") or {})
    if scan_info.get("plant_id"):
        plant["id"] = scan_info["plant_id"]
    if scan_info.get("species") and not plant.get("species"):
        plant["species"] = scan_info["species"]
    return {"plant": plant, "experiment": dict(scan_info.get("experiment") or {})}


def resolve_metadata(recipe_plant: PlantSpec, recipe_experiment: ExperimentSpec,
                     scan_info: dict[str, Any] | None = None,
                     row: SampleRow | None = None) -> Metadata:
    """A scan's metadata: recipe < the scan's record < the sample sheet row, field by field."""
    plant = recipe_plant.model_dump()
    experiment = recipe_experiment.model_dump()
    if scan_info:
        rec = scan_record(scan_info)
        plant = merge_metadata(plant, rec["plant"])
        experiment = merge_metadata(experiment, rec["experiment"])
    if row is not None:
        plant = merge_metadata(plant, row.plant)
        experiment = merge_metadata(experiment, row.experiment)
    return Metadata(PlantSpec.model_validate(plant), ExperimentSpec.model_validate(experiment))


def apply_to_raw_recipe(raw: dict[str, Any], row: SampleRow) -> dict[str, Any]:
    """The raw recipe with a sample sheet row's values in ``plant:`` and ``experiment:``."""
    raw = dict(raw)
    for section, values in (("plant", row.plant), ("experiment", row.experiment)):
        current = raw.get(section) if isinstance(raw.get(section), dict) else {}
        raw[section] = merge_metadata(current, {k: _yaml_value(v) for k, v in values.items()})
    return raw


def _yaml_value(v: Any) -> Any:
    return v.isoformat() if isinstance(v, _dt.date) else v


# --------------------------------------------------------------------------- sample sheets
class SampleSheetError(RecipeError):
    """A sample sheet is invalid: ``errors`` holds every ``(file:line, message)`` at once."""


KEY_COLUMNS = ("scan", "plant_id")
_PLANT_COLUMNS = {"plant_id": "id", **{f: f for f in PlantSpec.model_fields
                                        if f not in ("id", "factors", "extra")}}
_EXPERIMENT_COLUMNS = {f: f for f in ExperimentSpec.model_fields if f != "extra"}
_PREFIXES = {"factor.": ("plant", "factors"), "extra.": ("plant", "extra"),
             "experiment.extra.": ("experiment", "extra")}


def sheet_columns() -> list[str]:
    """The columns a sample sheet may have (plus ``factor.NAME``, ``extra.KEY``)."""
    return ["scan", *_PLANT_COLUMNS, *_EXPERIMENT_COLUMNS]


@dataclass
class SampleRow:
    """One row of a sample sheet: what it overrides for the scan or plant it names.

    Attributes
    ----------
    line : int
        Line number in the file (the header is line 1).
    scan : Path or None
        The scan folder it names (absolute), when it has a ``scan`` cell.
    plant_id : str or None
        The plant id it names or assigns.
    plant, experiment : dict
        Values given (validated), by ``PlantSpec`` / ``ExperimentSpec`` field.
    """

    line: int
    scan: Path | None
    plant_id: str | None
    plant: dict[str, Any] = field(default_factory=dict)
    experiment: dict[str, Any] = field(default_factory=dict)


@dataclass
class SampleSheet:
    """A validated sample sheet (``load_sample_sheet``)."""

    path: Path
    rows: list[SampleRow]

    def row_for(self, scan_dir: Path | None = None, plant_id: str | None = None
                ) -> SampleRow | None:
        """The row naming ``scan_dir`` (by path), else the scan-less row naming ``plant_id``."""
        if scan_dir is not None:
            target = Path(scan_dir).resolve()
            for row in self.rows:
                if row.scan is not None and row.scan == target:
                    return row
        if plant_id:
            for row in self.rows:
                if row.scan is None and row.plant_id == plant_id:
                    return row
        return None

    def metadata_for(self, recipe_plant: PlantSpec, recipe_experiment: ExperimentSpec,
                     scan_dir: Path | None, scan_info: dict[str, Any] | None) -> Metadata:
        """``resolve_metadata`` with this sheet's row for the scan (by folder, else plant id)."""
        plant_id = scan_record(scan_info or {})["plant"].get("id") or recipe_plant.id
        return resolve_metadata(recipe_plant, recipe_experiment, scan_info,
                                self.row_for(scan_dir, plant_id))


def load_sample_sheet(path: str | Path, *, require_scans: bool = True) -> SampleSheet:
    """Read and check a sample sheet; ``SampleSheetError`` with every problem at once.

    Parameters
    ----------
    path : path of a CSV file
        Header row, then one row per scan folder (``scan`` column, relative to
        the sheet's folder or absolute) or per plant (``plant_id`` column).
    require_scans : bool
        Every ``scan`` cell must name an existing scan folder (``process``,
        ``batch``, ``store``); ``scan`` (acquisition) sets it False.

    Refused, each naming ``file:line`` and the column: an unknown column, a row
    with neither a scan nor a plant id, a scan folder that does not exist, a
    date that is not ``YYYY-MM-DD``, a replicate that is not a whole number, a
    scan named twice, and a plant id given two different genotypes (or species,
    treatment, ... of ``PLANT_IDENTITY_FIELDS``) on two rows.
    """
    path = Path(path)
    src = str(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise SampleSheetError([(src, "sample sheet not found")], src) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SampleSheetError([(src, f"cannot read the sample sheet ({exc})")], src) from None
    reader = csv.reader(text.splitlines())
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise SampleSheetError([(src, "empty sample sheet (no header row)")], src) from None
    except csv.Error as exc:
        raise SampleSheetError([(f"{src}:1", f"not CSV ({exc})")], src) from None
    errors: list[tuple[str, str]] = []
    valid = sheet_columns()
    known_columns = set()
    for i, name in enumerate(header):
        known = name in valid or any(name.startswith(p) and len(name) > len(p)
                                     for p in _PREFIXES)
        if known:
            known_columns.add(name)
        else:
            errors.append((f"{src}:1", f"column {i + 1} {name!r}: unknown column; valid: "
                           f"{', '.join(valid)}, factor.NAME, extra.KEY"))
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        errors.append((f"{src}:1", f"column(s) {dup} repeated"))
    if not set(KEY_COLUMNS) & set(header):
        errors.append((f"{src}:1", "needs a 'scan' or a 'plant_id' column to say which "
                       "scan or plant each row is for"))
        raise SampleSheetError(errors, src)

    rows: list[SampleRow] = []
    try:
        records = list(enumerate(reader, start=2))
    except csv.Error as exc:
        raise SampleSheetError([(src, f"not CSV ({exc})")], src) from None
    for line, cells in records:
        if not any(c.strip() for c in cells):
            continue
        where = f"{src}:{line}"
        if len(cells) > len(header):
            errors.append((where, f"{len(cells)} cells but the header has {len(header)} columns"))
            continue
        values = {h: c.strip() for h, c in zip(header, cells)
                  if c.strip() and h in known_columns}
        row, row_errors = _parse_row(values, line, where, path.parent, require_scans)
        errors += row_errors
        if row is not None:
            rows.append(row)
    errors += _cross_row_errors(rows, src)
    if errors:
        raise SampleSheetError(errors, src)
    return SampleSheet(path, rows)


def _parse_row(values: dict[str, str], line: int, where: str, base: Path,
               require_scans: bool) -> tuple[SampleRow | None, list[tuple[str, str]]]:
    errors: list[tuple[str, str]] = []
    scan = None
    if "scan" in values:
        scan = (base / values["scan"]).resolve()
        if require_scans and not (scan / "scan.yaml").is_file():
            what = "is not a plantscan scan folder (no scan.yaml)" if scan.is_dir() else \
                "no such scan folder"
            errors.append((where, f"scan {values['scan']!r}: {what} ({scan})"))
    plant_id = values.get("plant_id")
    if scan is None and not plant_id:
        errors.append((where, "neither a scan nor a plant_id: which plant is this row for?"))
    plant: dict[str, Any] = {}
    experiment: dict[str, Any] = {}
    for column, value in values.items():
        if column == "scan":
            continue
        if column in _PLANT_COLUMNS:
            plant[_PLANT_COLUMNS[column]] = value
        elif column in _EXPERIMENT_COLUMNS:
            experiment[_EXPERIMENT_COLUMNS[column]] = value
        else:
            prefix = max((p for p in _PREFIXES if column.startswith(p)), key=len)
            section, key = _PREFIXES[prefix]
            target = plant if section == "plant" else experiment
            target.setdefault(key, {})[column[len(prefix):]] = value
    for model, given, columns in ((PlantSpec, plant, _PLANT_COLUMNS),
                                  (ExperimentSpec, experiment, _EXPERIMENT_COLUMNS)):
        try:
            checked = model.model_validate({**({"id": "x"} if model is PlantSpec else {}),
                                            **given})
        except ValidationError as exc:
            names = {v: k for k, v in columns.items()}
            for e in exc.errors():
                loc = [str(p) for p in e["loc"]]
                column = names.get(loc[0], loc[0]) if loc else ""
                if loc and loc[0] in ("factors", "extra"):
                    column = ".".join(loc)
                msg = e["msg"].removeprefix("Value error, ")
                value = given_value(given, loc)
                if value.removesuffix(": ") in msg:
                    value = ""
                errors.append((where, f"column {column!r}: {value}{msg}"))
            continue
        for k in given:  # keep the parsed values (dates as dates, replicate as int)
            given[k] = getattr(checked, k)
    if errors:
        return None, errors
    return SampleRow(line, scan, plant_id, plant, experiment), []


def given_value(given: dict[str, Any], loc: list[str]) -> str:
    v: Any = given
    for p in loc:
        if not isinstance(v, dict) or p not in v:
            return ""
        v = v[p]
    return f"{v!r}: "


def _cross_row_errors(rows: list[SampleRow], src: str) -> list[tuple[str, str]]:
    errors: list[tuple[str, str]] = []
    seen_scans: dict[Path, int] = {}
    seen_plants: dict[str, int] = {}
    for row in rows:
        if row.scan is not None:
            if row.scan in seen_scans:
                errors.append((f"{src}:{row.line}", f"scan {str(row.scan)!r} already has a row "
                               f"(line {seen_scans[row.scan]})"))
            seen_scans.setdefault(row.scan, row.line)
        elif row.plant_id in seen_plants:
            errors.append((f"{src}:{row.line}", f"plant_id {row.plant_id!r} already has a row "
                           f"(line {seen_plants[row.plant_id]}); give one row per plant, or a "
                           "'scan' column for one row per scan"))
        else:
            seen_plants[row.plant_id or ""] = row.line
    # One plant id, one genotype (species, treatment...): rows of the same plant must agree.
    first: dict[tuple[str, str], tuple[Any, int]] = {}
    for row in rows:
        if not row.plant_id:
            continue
        for name in PLANT_IDENTITY_FIELDS:
            if name not in row.plant:
                continue
            value = row.plant[name]
            key = (row.plant_id, name)
            if key in first and first[key][0] != value:
                other, other_line = first[key]
                errors.append((f"{src}:{row.line}", f"plant_id {row.plant_id!r} has {name} "
                               f"{_show(value)} here but {_show(other)} on line {other_line}: "
                               "one plant id is one plant (give the other plant its own id)"))
            first.setdefault(key, (value, row.line))
    return errors


def _show(v: Any) -> str:
    return repr(v.isoformat()) if isinstance(v, _dt.date) else repr(v)


def check_plant_consistency(metadata: list[tuple[str, Metadata]]) -> list[tuple[str, str]]:
    """Scans that resolve to the same plant id (in one study) with different identities.

    ``metadata`` is ``(where, Metadata)`` per scan (``where`` names the scan);
    returns ``(where, message)`` errors, as ``load_sample_sheet`` does for rows.
    """
    errors: list[tuple[str, str]] = []
    first: dict[tuple[str, str, str, str], tuple[Any, str]] = {}
    for where, md in metadata:
        study = (md.experiment.investigation_id, md.experiment.study_id)
        for name in PLANT_IDENTITY_FIELDS:
            value = getattr(md.plant, name)
            if not _given(value):
                continue
            key = (*study, md.plant.id, name)
            if key in first and first[key][0] != value:
                errors.append((where, f"plant {md.plant.id!r} has {name} {_show(value)} but "
                               f"{_show(first[key][0])} in {first[key][1]}"))
            first.setdefault(key, (value, where))
    return errors


# --------------------------------------------------------------------------- scans
def scan_summary(scan) -> dict[str, Any]:
    """What a run records of its scan (``run.json: scan_record``), for the results store.

    ``uid`` identifies the scan wherever its folder lies (SHA-256 of its
    ``scan.yaml``, which holds its creation time stamp); ``acquired_at`` is the
    scan's ``created`` time stamp (UTC, ISO 8601), else its first image's.
    """
    import hashlib

    from plantscan_core.scanfolder import SCAN_YAML

    acquired = scan.info.get("created") or min(
        (v.captured_at for v in scan.views if v.captured_at), default="")
    rig = scan.info.get("rig") or {}
    return {"uid": hashlib.sha256((scan.root / SCAN_YAML).read_bytes()).hexdigest()[:32],
            "path": str(scan.root.resolve()), "acquired_at": str(acquired),
            "protocol": str(rig.get("protocol", "")),
            "views": len(scan.views_by_role("plant"))}
