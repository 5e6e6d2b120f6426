"""What the report says about how far to trust a run, and how it writes numbers.

The report's first block is a verdict: the plant's quality flag and its
reasons when the measurer gives one (``ok`` / ``check`` / ``fail``), otherwise
"not assessed"; then one line per thing a scientist checks before using the
numbers (the calibration, the leaves warned about, what the stages warned).
Numbers are written with a fixed number of decimals per unit, so one column
never mixes plain and scientific notation.

Where a verdict comes from (for plugin authors; docs/report.md):

* the plant flag: ``Traits.plant["quality_flag"]`` (``ok``/``check``/``fail``)
  and ``Traits.plant["quality_reasons"]`` (messages), as the ``leaf-geometry``
  measurer writes them into ``plant_traits.json``; "not assessed" without;
* a leaf's trust: its ``LeafTraits.confidence`` (0-1), ``confidence_reasons``
  (``;``-separated codes) and ``quality_flag`` (``check``: low confidence);
* warnings about one leaf: a ``StageWarning`` of the stage's report that names
  the leaf (``leaf``; for runs read back from disk, the same record in
  ``run.json``, or a message that starts ``leaf <id>:``);
* the calibration: ``Calibration.quality`` keys ``rms_px``, ``max_px``,
  ``corners``, ``detections``, ``flags`` (a list of notes), when present.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

from plantscan_core.stages import RunResult

FLAGS = ("ok", "check", "fail")
NOT_ASSESSED = "not assessed"

# Calibration verdict: a turntable calibration whose corners reproject within half a pixel
# (RMS) is as good as the corner detector (0.05-0.3 px on the virtual and real boards of
# docs/calibration.md); above 1 px a leaf's position is off by a pixel in some views, which
# the hull turns into carved-away leaf edges.
CALIBRATION_OK_RMS_PX = 0.5
CALIBRATION_FAIL_RMS_PX = 1.0

_LEAF_PREFIX = re.compile(r"^\s*leaf (\d+)\s*:\s*")


# --------------------------------------------------------------------------- numbers
@dataclass(frozen=True)
class Unit:
    """How one kind of value is written: unit text and decimals."""

    text: str
    decimals: int


# By the suffix of a name (traits.csv / plant_traits.json keys carry their unit).
_SUFFIX_UNITS = {
    "_mm": Unit("mm", 1), "_mm2": Unit("mm²", 0), "_mm3": Unit("mm³", 0),
    "_deg": Unit("°", 1), "_px": Unit("px", 2), "_s": Unit("s", 1), "_share": Unit("%", 1),
}


def unit_of(name: str) -> Unit | None:
    """The unit of a trait or figure named ``name`` (``area_mm2`` -> mm², 0 decimals), or None."""
    for suffix, unit in sorted(_SUFFIX_UNITS.items(), key=lambda kv: -len(kv[0])):
        if name.endswith(suffix):
            return unit
    return None


def label_of(name: str) -> str:
    """``total_leaf_area_mm2`` -> ``total leaf area``."""
    unit = unit_of(name)
    base = name
    if unit is not None:
        base = name[: name.rfind("_")]
    return base.replace("_", " ")


def format_number(value: Any, decimals: int) -> str:
    """Fixed-point text with ``decimals`` decimals; thousands grouped by a thin space.

    Never scientific notation: a column of one unit lines up and reads the same
    for 8110 and 18240.  Not a finite number: an em dash.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if not math.isfinite(v):
        return "—"
    text = f"{v:,.{decimals}f}"
    return text.replace(",", "\u2009")


def format_value(name: str, value: Any) -> str:
    """``value`` of the trait/figure ``name`` with its unit: ``18 240 mm²``, ``12``, ``2.4 %``."""
    if isinstance(value, bool) or value is None:
        return str(value)
    if not isinstance(value, (int, float)) and not hasattr(value, "__float__"):
        return str(value)
    unit = unit_of(name)
    if name.endswith("_count") or (unit is None and float(value).is_integer()):
        return format_number(value, 0)
    if unit is None:
        return format_number(value, 3)
    if unit.text == "%":  # shares are stored 0-1
        return f"{format_number(100 * float(value), unit.decimals)} %"
    return f"{format_number(value, unit.decimals)} {unit.text}"


# --------------------------------------------------------------------------- warnings
@dataclass
class StageNote:
    """One warning of one stage, with the leaf it names (if any)."""

    section: str
    message: str
    leaf: int | None = None
    code: str = ""


def stage_notes(run: RunResult) -> list[StageNote]:
    """Every stage's warnings, in stage order, each once (a cached re-run repeats none).

    Read from the run's typed ``StageReport``s (``run.reports``); a run rebuilt
    from disk without them falls back to ``run.json``'s ``stages.<section>.info``.
    """
    notes: list[StageNote] = []
    seen: set[tuple[str, str]] = set()

    def add(section: str, message: str, leaf: Any, code: str) -> None:
        if leaf is None and (m := _LEAF_PREFIX.match(message)):
            leaf = int(m.group(1))
        if (section, message) not in seen:
            seen.add((section, message))
            notes.append(StageNote(section, message, None if leaf is None else int(leaf), code))

    reports = getattr(run, "reports", None) or {}
    if reports:
        for section, report in reports.items():
            for w in report.warnings:
                add(section, w.message, w.leaf, w.code)
        return notes
    for section, record in (run.info or {}).get("stages", {}).items():
        for w in (record.get("info") or {}).get("warnings") or []:
            if isinstance(w, dict):
                add(section, str(w.get("message", "")), w.get("leaf"), str(w.get("code", "")))
            else:
                add(section, str(w), None, "")
    return notes


def leaf_notes(run: RunResult) -> dict[int, list[StageNote]]:
    """Leaf id -> the warnings that name it."""
    out: dict[int, list[StageNote]] = {}
    for n in stage_notes(run):
        if n.leaf is not None:
            out.setdefault(n.leaf, []).append(n)
    return out


def short_reason(note: StageNote) -> str:
    """A few words for the traits table (the full message is in the warnings list)."""
    text = _LEAF_PREFIX.sub("", note.message)
    lowered = f"{note.code} {text}".lower()
    if "phantom" in lowered or "thick" in lowered:
        share = re.match(r"(\d+) %", text)
        return f"phantom volume ({share.group(1)} % of area)" if share else "phantom volume"
    if "perimeter" in lowered and "length" in lowered:
        return "perimeter too short for its length"
    first = re.split(r"[;:(]", text, maxsplit=1)[0].strip()
    return first if len(first) <= 48 else first[:45] + "…"


# --------------------------------------------------------------------------- verdict
@dataclass
class Verdict:
    """The plant flag (``ok``/``check``/``fail`` or ``not assessed``) and its reasons."""

    flag: str
    reasons: list[str] = field(default_factory=list)
    source: str = ""


def plant_verdict(run: RunResult) -> Verdict:
    """The plant's quality flag and reasons from its traits; else ``not assessed``."""
    plant = run.traits.plant if run.traits is not None else {}
    flag = plant.get("quality_flag")
    if flag in FLAGS:
        reasons = plant.get("quality_reasons") or []
        reasons = [reasons] if isinstance(reasons, str) else [str(r) for r in reasons]
        return Verdict(str(flag), reasons, "measurer")
    return Verdict(NOT_ASSESSED, ["the measurer in this run gives no plant quality flag; read "
                                  "the leaf warnings and the calibration line below"])


def low_confidence(leaf: Any) -> bool:
    """Whether the measurer flags ``leaf`` for a look (``quality_flag`` ``check``)."""
    return getattr(leaf, "quality_flag", "") == "check"


# Confidence reason codes of the leaf-geometry measurer (plantscan_leaves/trust.py), in a
# few words for the table; another measurer's codes are shown as they are.
_REASON_WORDS = {"phantom": "phantom volume", "outline": "perimeter too short for its length",
                 "rejoined": "rejoined from pieces", "small": "few voxels across",
                 "shape": "area does not fit length × width",
                 "model": "leaves like it measured > 10 % off (trust model)"}
# The warning that repeats a leaf's confidence reasons as a sentence (measure's report).
_CONFIDENCE_WARNING = "low-confidence"


def leaf_reasons(leaf: Any, notes: list[StageNote]) -> list[str]:
    """Short reasons a leaf is doubtful: its confidence reasons, then its warnings'."""
    codes = [c for c in str(getattr(leaf, "confidence_reasons", "") or "").split(";") if c]
    words = [_REASON_WORDS.get(c, c) for c in codes]
    words += [short_reason(n) for n in notes if not (codes and n.code == _CONFIDENCE_WARNING)]
    out: list[str] = []
    for w in words:  # "phantom volume (18 % of area)" and "phantom volume" say one thing:
        same = [i for i, o in enumerate(out) if w.startswith(o) or o.startswith(w)]
        if not same:
            out.append(w)
        elif len(w) > len(out[same[0]]):  # the one with the figure
            out[same[0]] = w
    return out


@dataclass
class LeafDoubt:
    """Why one leaf's numbers are to be read with care (``doubtful``), in short."""

    low_confidence: bool
    warned: bool  # a stage warning names it (beyond restating its confidence)
    reasons: list[str]

    @property
    def doubtful(self) -> bool:
        return self.low_confidence or self.warned or bool(self.reasons)


def leaf_doubts(run: RunResult) -> dict[int, LeafDoubt]:
    """Leaf id -> its ``LeafDoubt``, for every measured leaf of ``run``."""
    if run.traits is None:
        return {}
    notes = leaf_notes(run)
    out = {}
    for leaf in run.traits.leaves:
        said = notes.get(leaf.leaf_id, [])
        out[leaf.leaf_id] = LeafDoubt(
            low_confidence(leaf), any(n.code != _CONFIDENCE_WARNING for n in said),
            leaf_reasons(leaf, said))
    return out


def calibration_line(quality: dict[str, Any] | None) -> tuple[str, str]:
    """(level ``ok``/``check``/``fail``/``—``, one sentence) for a calibration's quality."""
    q = quality or {}
    rms = q.get("rms_px")
    if not isinstance(rms, (int, float)) or isinstance(rms, bool):
        return "—", "the calibrator reported no reprojection error"
    parts = [f"reprojection RMS {rms:.2f} px"]
    if isinstance(q.get("max_px"), (int, float)):
        parts.append(f"max {q['max_px']:.2f} px")
    if isinstance(q.get("corners"), int):
        parts.append(f"over {q['corners']} corners")
    if isinstance(q.get("detections"), int):
        parts.append(f"in {q['detections']} board views")
    heldout = (q.get("cross_validation") or {}).get("rms_heldout_px") \
        if isinstance(q.get("cross_validation"), dict) else None
    if isinstance(heldout, (int, float)):
        parts.append(f"held-out views {heldout:.2f} px")
    flags = [str(f) for f in q.get("flags") or []] if isinstance(q.get("flags"), list) else []
    if rms > CALIBRATION_FAIL_RMS_PX:
        level = "fail"
    elif rms > CALIBRATION_OK_RMS_PX or flags:
        level = "check"
    else:
        level = "ok"
    text = ", ".join(parts)
    if flags:
        text += f"; {len(flags)} note(s): " + "; ".join(flags)
    return level, text


def section_title(section: str, run: RunResult) -> str:
    """A stage section as a user names it: ``export.1`` -> ``export ply``."""
    if section.startswith("export."):
        plugin = ((run.info or {}).get("stages", {}).get(section) or {}).get("plugin")
        if plugin is None and run.recipe is not None:
            try:
                plugin = run.recipe.export[int(section.split(".", 1)[1])].plugin
            except (ValueError, IndexError):
                plugin = None
        return f"export {plugin}" if plugin else section
    return section


def protocol_summary(run: RunResult) -> str:
    """What was captured, from the scan's own views: images per role, cameras, tilts, angles."""
    scan = run.scan
    if scan is None or not scan.views:
        return ""
    plant = scan.views_by_role("plant")
    parts = []
    if plant:
        cams = sorted({v.camera for v in plant})
        tilts = sorted({v.tilt_deg for v in plant})
        angles = len({(v.tilt_index, v.angle_index) for v in plant}) // max(len(tilts), 1)
        parts.append(f"{len(plant)} plant images: {len(cams)} camera(s) ({', '.join(cams)}) × "
                     f"{len(tilts)} tilt(s) ({', '.join(f'{t:g}°' for t in tilts)}) × "
                     f"{angles} angles")
    for role in ("calibration", "background"):
        n = len(scan.views_by_role(role))
        if n:
            parts.append(f"{n} {role}")
    size = (scan.info.get("rig") or {}).get("image_size")
    if size:
        parts.append(f"{size[0]}×{size[1]} px")
    return "; ".join(parts)
