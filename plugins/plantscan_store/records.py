"""What the store keeps of one run: a ``RunRecord``, read from a run folder (and its scan).

A run folder has ``run.json`` (recipe, stages, plugin versions, provenance and,
since this store, the resolved ``metadata`` and ``scan_record``),
``traits.csv`` and ``plant_traits.json``; ``labelled.npz`` gives each leaf's
centroid (for matching leaves between the scans of one plant).  The scan folder
named in ``run.json`` fills in what an older run folder lacks.
"""

from __future__ import annotations

import csv
import datetime as _dt
import hashlib
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from plantscan_core.errors import DataError
from plantscan_core.metadata import (
    ExperimentSpec,
    Metadata,
    PlantSpec,
    SampleSheet,
    resolve_metadata,
    scan_summary,
)
from plantscan_store.schema import QUALITY_FLAGS

RUN_JSON = "run.json"


@dataclass
class LeafRecord:
    """One leaf of a run (mm, mm²; centroid in the turntable frame at angle 0)."""

    leaf_id: int
    length_mm: float | None
    width_mm: float | None
    area_mm2: float | None
    perimeter_mm: float | None
    thick_share: float | None = None
    confidence: float | None = None
    quality_flag: str | None = None
    centroid_mm: tuple[float, float, float] | None = None
    confidence_reasons: str | None = None  # reason codes, ";"-separated (docs/leaves.md)


@dataclass
class WarningRecord:
    stage: str
    message: str
    code: str = ""
    leaf_id: int | None = None


@dataclass
class ScanRecord:
    """The acquisition a run was made from.

    ``uid`` identifies it wherever its folder lies (a hash of its ``scan.yaml``);
    ``acquired_at`` is UTC (naive).
    """

    uid: str
    path: str
    acquired_at: _dt.datetime
    protocol: str = ""
    views: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"uid": self.uid, "path": self.path, "acquired_at": iso_utc(self.acquired_at),
                "protocol": self.protocol, "views": self.views}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ScanRecord:
        return cls(str(d["uid"]), str(d.get("path", "")), parse_utc(d["acquired_at"]),
                   str(d.get("protocol", "")), int(d.get("views", 0)))


@dataclass
class RunRecord:
    """Everything the store keeps of one run.

    ``run_key`` (the scan's uid and the recipe's hash) identifies the run:
    storing a run with a key already in the store replaces the old one.
    """

    metadata: Metadata
    scan: ScanRecord
    recipe_name: str
    recipe_hash: str
    leaves: list[LeafRecord] = field(default_factory=list)
    plant_traits: dict[str, float] = field(default_factory=dict)
    quality_flag: str | None = None
    warnings: list[WarningRecord] = field(default_factory=list)
    run_dir: str = ""
    plantscan_version: str = ""
    plugins: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    quality_reasons: str | None = None  # why the plant is flagged, "; "-separated messages

    @property
    def run_key(self) -> str:
        return run_key(self.scan.uid, self.recipe_hash)

    @property
    def plant_id(self) -> str:
        return self.metadata.plant.id


def run_key(scan_uid: str, recipe_hash: str) -> str:
    return hashlib.sha256(f"{scan_uid}\n{recipe_hash}".encode()).hexdigest()[:40]


# --------------------------------------------------------------------------- time
def parse_utc(text: str | _dt.datetime) -> _dt.datetime:
    """An ISO 8601 time stamp as a naive UTC datetime (a stamp without a zone is UTC)."""
    t = text if isinstance(text, _dt.datetime) else _dt.datetime.fromisoformat(str(text))
    if t.tzinfo is not None:
        t = t.astimezone(_dt.UTC).replace(tzinfo=None)
    return t


def iso_utc(t: _dt.datetime) -> str:
    return t.replace(tzinfo=_dt.UTC).isoformat(timespec="seconds")


# --------------------------------------------------------------------------- the scan
def scan_record_of(scan_dir: Path) -> ScanRecord:
    """The ``ScanRecord`` of a scan folder (``plantscan_core.metadata.scan_summary``)."""
    from plantscan_core.scanfolder import SCAN_YAML, ScanFolder

    scan = ScanFolder.open(Path(scan_dir))
    summary = scan_summary(scan)
    if not summary["acquired_at"]:
        raise DataError(f"{scan.root / SCAN_YAML}: no acquisition time (no 'created')")
    return ScanRecord.from_dict(summary)


# --------------------------------------------------------------------------- the run
def recipe_hash_of(stages: dict[str, Any]) -> str:
    """Hash of what the run computed with: each stage's plugin and parameters.

    Plugin versions and the plant's metadata are left out: re-processing a scan
    with the same recipe replaces its earlier run in the store.  So are the
    exporters and the store itself: they change no measurement (and the store
    step is not yet in ``run.json`` while it runs).
    """
    spec = {name: {"plugin": s.get("plugin"), "params": s.get("params")}
            for name, s in sorted(stages.items())
            if isinstance(s, dict) and name != "store" and not name.startswith("export")}
    return hashlib.sha256(json.dumps(spec, sort_keys=True, default=str).encode()).hexdigest()


def _num(v: Any) -> float | None:
    if v in (None, ""):
        return None
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def _flag(v: Any, where: str) -> str | None:
    if v in (None, ""):
        return None
    text = str(v).strip().lower()
    if text not in QUALITY_FLAGS:
        raise DataError(f"{where}: quality flag {v!r} is not one of {', '.join(QUALITY_FLAGS)}")
    return text


def read_leaves(traits_csv: Path) -> list[LeafRecord]:
    """The leaves of ``traits.csv`` (optional ``thick_share``, ``confidence``,
    ``confidence_reasons``, ``quality_flag`` or ``quality``)."""
    rows = list(csv.DictReader(io.StringIO(Path(traits_csv).read_text())))
    out = []
    for n, r in enumerate(rows, start=2):
        try:
            leaf_id = int(r["leaf_id"])
        except (KeyError, TypeError, ValueError):
            raise DataError(f"{traits_csv}:{n}: no leaf_id") from None
        out.append(LeafRecord(
            leaf_id, _num(r.get("length_mm")), _num(r.get("width_mm")), _num(r.get("area_mm2")),
            _num(r.get("perimeter_mm")), _num(r.get("thick_share")), _num(r.get("confidence")),
            _flag(r.get("quality_flag", r.get("quality")), f"{traits_csv}:{n}"),
            confidence_reasons=(r.get("confidence_reasons") or "").strip() or None))
    return out


def leaf_centroids(labelled_npz: Path) -> dict[int, tuple[float, float, float]]:
    """Area-weighted centroid (mm, turntable frame) of every leaf label of a labelled mesh."""
    from plantscan_core.data import LabelledMesh

    labelled = LabelledMesh.load(labelled_npz)
    return {label: (float(c[0]), float(c[1]), float(c[2]))
            for label, c in labelled.mesh.label_centroids(labelled.face_labels).items()}


def _warnings(stages: dict[str, Any]) -> list[WarningRecord]:
    out = []
    for stage, s in stages.items():
        info = (s or {}).get("info") or {} if isinstance(s, dict) else {}
        for w in info.get("warnings") or []:
            if isinstance(w, dict):
                out.append(WarningRecord(stage, str(w.get("message", "")), str(w.get("code", "")),
                                         w.get("leaf")))
            else:
                out.append(WarningRecord(stage, str(w)))
    return out


def record_from_run_dir(run_dir: Path, sample_sheet: SampleSheet | None = None) -> RunRecord:
    """Read a run folder (and, for what it lacks, its scan folder) into a ``RunRecord``.

    ``sample_sheet`` overrides the metadata the run recorded (runs processed
    before the sheet existed).  ``DataError`` naming the file when the run has
    no traits or a file is unreadable.
    """
    run_dir = Path(run_dir)
    path = run_dir / RUN_JSON
    try:
        info = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{run_dir}: not a run folder (no {RUN_JSON})") from None
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: unreadable ({exc})") from exc
    traits_csv = run_dir / "traits.csv"
    if not traits_csv.exists():
        raise DataError(f"{run_dir}: the run has no traits.csv (did the measure stage run?)")
    scan_dir = Path(info.get("scan", ""))
    if info.get("scan_record"):
        scan = ScanRecord.from_dict(info["scan_record"])
    else:
        if not (scan_dir / "scan.yaml").exists():
            raise DataError(f"{path}: its scan folder {scan_dir} is gone and run.json has no "
                            "scan_record (re-process the scan with this plantscan)")
        scan = scan_record_of(scan_dir)
    recipe = info.get("recipe") or {}
    if info.get("metadata"):
        # what the run resolved (recipe < scan < the sheet it was processed with) ...
        metadata = Metadata.from_dict(info["metadata"])
        if sample_sheet is not None:  # ... corrected by this sheet's row
            row = sample_sheet.row_for(scan_dir, metadata.plant.id)
            metadata = resolve_metadata(metadata.plant, metadata.experiment, None, row)
    else:  # a run folder from before run.json recorded its metadata
        scan_info = None
        if (scan_dir / "scan.yaml").exists():
            from plantscan_core.scanfolder import ScanFolder

            scan_info = ScanFolder.open(scan_dir).info
        plant = PlantSpec.model_validate(recipe.get("plant") or {})
        experiment = ExperimentSpec.model_validate(recipe.get("experiment") or {})
        metadata = (sample_sheet.metadata_for(plant, experiment, scan_dir, scan_info)
                    if sample_sheet is not None else
                    resolve_metadata(plant, experiment, scan_info))
    leaves = read_leaves(traits_csv)
    labelled = run_dir / "labelled.npz"
    if labelled.exists():
        centroids = leaf_centroids(labelled)
        for leaf in leaves:
            leaf.centroid_mm = centroids.get(leaf.leaf_id)
    plant: dict[str, Any] = {}
    if (run_dir / "plant_traits.json").exists():
        plant = json.loads((run_dir / "plant_traits.json").read_text())
    flag = _flag(plant.get("quality_flag", plant.get("quality")), str(run_dir /
                                                                        "plant_traits.json"))
    traits = {k: float(v) for k, v in plant.items()
              if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}
    traits.setdefault("leaf_count", float(len(leaves)))
    stages = info.get("stages") or {}
    provenance = {k: info.get(k) for k in ("created", "scan", "overrides", "timings_s",
                                           "input_hashes", "recipe") if k in info}
    return RunRecord(
        metadata=metadata, scan=scan, recipe_name=str(recipe.get("name", "")),
        recipe_hash=recipe_hash_of(stages), leaves=leaves, plant_traits=traits,
        quality_flag=flag, warnings=_warnings(stages), run_dir=str(run_dir.resolve()),
        plantscan_version=str(info.get("plantscan_version", "")),
        plugins={k: {"plugin": s.get("plugin"), "version": s.get("version")}
                 for k, s in stages.items() if isinstance(s, dict)},
        provenance=provenance, quality_reasons=_reasons(plant.get("quality_reasons")))


def _reasons(v: Any) -> str | None:
    """A plant's quality reasons (a list of messages, or one text) as "; "-separated text."""
    if v is None:
        return None
    items = [str(x).strip() for x in v] if isinstance(v, (list, tuple)) else [str(v).strip()]
    return "; ".join(x for x in items if x) or None


def find_run_dirs(paths: list[Path]) -> list[Path]:
    """Run folders among ``paths``: each path is a run folder or holds run folders (a batch)."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if (p / RUN_JSON).exists():
            out.append(p)
        elif p.is_dir():
            found = sorted(d for d in p.iterdir() if (d / RUN_JSON).exists())
            if not found:
                raise DataError(f"{p}: neither a run folder nor a folder of run folders "
                                f"(no {RUN_JSON})")
            out += found
        else:
            raise DataError(f"{p}: no such run folder")
    return out
