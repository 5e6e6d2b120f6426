"""A MIAPPE-shaped ISA-Tab export of a store's studies, and its check against its own columns.

ISA-Tab (tab-separated) as MIAPPE 1.1 lays it out:

* ``i_investigation.txt`` -- the investigation, and per study its identifier,
  title, site, start date, factors, assay and trait dictionary files;
* ``s_<study>.txt`` -- one row per plant (MIAPPE observation unit): its
  biological material (organism, genotype, accession, material id), factor
  values (treatment, factors), replicate and sowing date;
* ``a_<study>_phenotyping.txt`` -- one row per scan run: the plant, the scan
  folder (raw data), the time of the scan, the recipe;
* ``d_<study>_traits.txt`` -- the data matrix: one row per run and plant-level
  trait columns, then one row per leaf (``Leaf ID`` set) with leaf traits;
* ``tdf_<study>.txt`` -- the trait dictionary (MIAPPE observed variables):
  variable id, trait, method, scale (unit), level.

``validate_isatab(folder)`` checks an export against the columns this module
states for each file (``COLUMNS``), and the links between them: every file the
investigation names exists, every assay row's plant is in the study file,
every data row's assay is in the assay file, every data column is a variable
of the trait dictionary with a unit.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import select

from plantscan_store import schema as S
from plantscan_store.traitdefs import LEAF_NUMBERS, definition

if TYPE_CHECKING:
    from plantscan_store.store import Store

STUDY_COLUMNS = ("Source Name", "Characteristics[Organism]", "Characteristics[Genotype]",
                 "Characteristics[Material source ID]", "Characteristics[Biological material ID]",
                 "Characteristics[Replicate]", "Comment[Sowing date]", "Protocol REF",
                 "Sample Name", "Characteristics[Observation unit type]",
                 "Factor Value[treatment]")
ASSAY_COLUMNS = ("Sample Name", "Protocol REF", "Assay Name", "Raw Data File",
                 "Comment[Scan time (UTC)]", "Comment[Recipe]", "Comment[Quality flag]",
                 "Comment[Quality reasons]", "Derived Data File")
DATA_KEY_COLUMNS = ("Assay Name", "Sample Name", "Leaf ID", "Date")
TRAIT_DICTIONARY_COLUMNS = ("Variable ID", "Variable name", "Trait", "Method", "Scale", "Level",
                            "Description")
COLUMNS = {"study": STUDY_COLUMNS, "assay": ASSAY_COLUMNS,
           "trait_dictionary": TRAIT_DICTIONARY_COLUMNS}
"""The stated columns of each table file (factor columns ``Factor Value[NAME]`` follow the
study's, trait columns the data matrix keys)."""


class IsaTabError(ValueError):
    """An ISA-Tab folder does not match its stated columns or links (every problem listed)."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = problems
        super().__init__("\n".join(problems))


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "study"


def _text(v: Any) -> str:
    """A text cell: empty for a missing value (None, NaN)."""
    return "" if v is None or v != v else str(v)


def _write_table(path: Path, header: list[str], rows: list[list[Any]]) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, delimiter="\t", lineterminator="\n")
        w.writerow(header)
        for row in rows:
            w.writerow(["" if v is None else v for v in row])


def export_isatab(store: Store, out: Path, **filters: Any) -> list[Path]:
    """Write the ISA-Tab of the studies (and runs) matching ``filters``; the files written.

    ``filters`` as ``Store.plant_traits``.  The investigation is the first
    matching study's (one export, one investigation: filter by
    ``investigation`` when a store holds several).
    """
    import pandas as pd

    plants = store.plant_traits(**filters)
    if plants.empty:
        raise ValueError("no stored run matches: nothing to export")
    leaves = store.leaf_traits(**filters)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with store.connect() as conn:
        experiments = {(r.investigation_id, r.study_id): r for r in
                       conn.execute(select(S.experiments)).all()}
        defined = {r.name: r for r in conn.execute(select(S.trait_definitions)).all()}
    investigation = plants["investigation_id"].iloc[0]
    plants = plants[plants["investigation_id"] == investigation]
    written: list[Path] = []
    studies = []
    for study_id, sp in plants.groupby("study_id", sort=True):
        exp = experiments[(investigation, study_id)]
        stem = _safe(study_id or "study")
        factor_cols = sorted(c for c in sp.columns if c.startswith("factor."))
        factors = ["treatment", *(c.removeprefix("factor.") for c in factor_cols)]
        # study: one row per plant
        study_rows = []
        for _, p in sp.drop_duplicates("plant_id").iterrows():
            study_rows.append([
                f"{p.genotype or p.species or 'material'}", p.species, p.genotype, p.accession,
                p.biological_material_id, "" if pd.isna(p.replicate) else int(p.replicate),
                "" if p.sowing_date is None or pd.isna(p.sowing_date) else str(p.sowing_date),
                "growth", p.plant_id, "plant", p.treatment,
                *(p[c] for c in factor_cols)])
        s_file = out / f"s_{stem}.txt"
        _write_table(s_file, [*STUDY_COLUMNS, *(f"Factor Value[{f}]" for f in factors[1:])],
                     study_rows)
        # assay: one row per run
        d_file = out / f"d_{stem}_traits.txt"
        a_file = out / f"a_{stem}_phenotyping.txt"
        _write_table(a_file, list(ASSAY_COLUMNS), [
            [p.plant_id, "turntable 3D scan", p.run_key, p.scan_path,
             p.scan_time.isoformat(timespec="seconds"), p.recipe_name,
             p.plant_quality_flag or "", _text(p.plant_quality_reasons), d_file.name]
            for _, p in sp.iterrows()])
        # data matrix: plant rows, then leaf rows
        plant_traits = [c for c in sp.columns if c in defined and defined[c].level == "plant"]
        lv = leaves[(leaves["investigation_id"] == investigation)
                    & (leaves["study_id"] == study_id)]
        leaf_traits = [c for c in LEAF_NUMBERS if c in lv and lv[c].notna().any()]
        variables = [*plant_traits, *(f"leaf_{c}" for c in leaf_traits)]
        rows = [[p.run_key, p.plant_id, "", p.scan_time.isoformat(timespec="seconds"),
                 *(p[c] for c in plant_traits), *([""] * len(leaf_traits))]
                for _, p in sp.iterrows()]
        rows += [[r.run_key, r.plant_id, int(r.leaf_id), r.scan_time.isoformat(timespec="seconds"),
                  *([""] * len(plant_traits)),
                  *("" if pd.isna(r[c]) else r[c] for c in leaf_traits)]
                 for _, r in lv.iterrows()]
        _write_table(d_file, [*DATA_KEY_COLUMNS, *variables], rows)
        # trait dictionary
        t_file = out / f"tdf_{stem}.txt"
        tdf = []
        for v in variables:
            name = v.removeprefix("leaf_") if v.startswith("leaf_") else v
            level = "leaf" if v.startswith("leaf_") else "plant"
            d = defined.get(name) or definition(name, level)
            tdf.append([v, name, d.description or name, d.method or "plantscan", d.unit, level,
                        d.description])
        _write_table(t_file, list(TRAIT_DICTIONARY_COLUMNS), tdf)
        written += [s_file, a_file, d_file, t_file]
        studies.append((exp, stem, factors, s_file, a_file, t_file))
    i_file = out / "i_investigation.txt"
    first = studies[0][0]
    lines = [
        "ONTOLOGY SOURCE REFERENCE", "Term Source Name", "INVESTIGATION",
        f"Investigation Identifier\t{investigation}",
        f"Investigation Title\t{first.investigation_title}",
        "Investigation Description\t", "Comment[MIAPPE version]\t1.1",
        "INVESTIGATION PUBLICATIONS", "INVESTIGATION CONTACTS"]
    for exp, _stem, factors, s_file, a_file, t_file in studies:
        lines += [
            "STUDY", f"Study Identifier\t{exp.study_id}", f"Study Title\t{exp.study_title}",
            f"Study Description\t{exp.description}",
            f"Study Start Date\t{exp.start_date or ''}",
            f"Comment[Study experimental site name]\t{exp.location}",
            f"Study File Name\t{s_file.name}",
            f"Comment[Trait Definition File]\t{t_file.name}",
            "STUDY DESIGN DESCRIPTORS", "STUDY PUBLICATIONS", "STUDY FACTORS",
            "Study Factor Name\t" + "\t".join(factors),
            "STUDY ASSAYS", "Study Assay Measurement Type\tplant phenotyping",
            "Study Assay Technology Type\tturntable 3D imaging",
            f"Study Assay File Name\t{a_file.name}", "STUDY PROTOCOLS",
            "Study Protocol Name\tgrowth\tturntable 3D scan",
            "Study Protocol Type\tgrowth\tphenotyping", "STUDY CONTACTS"]
    i_file.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return [i_file, *written]


def _read_table(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(encoding="utf-8", newline="") as f:
        rows = list(csv.reader(f, delimiter="\t"))
    header = rows[0] if rows else []
    return header, [dict(zip(header, r)) for r in rows[1:]]


def validate_isatab(folder: Path) -> None:
    """Check an export against ``COLUMNS`` and its links; ``IsaTabError`` listing every problem."""
    folder = Path(folder)
    problems: list[str] = []
    i_file = folder / "i_investigation.txt"
    if not i_file.exists():
        raise IsaTabError([f"{i_file}: missing"])
    fields: dict[str, list[list[str]]] = {}
    for line in i_file.read_text(encoding="utf-8").splitlines():
        key, *values = line.split("\t")
        fields.setdefault(key, []).append(values)
    for key in ("Investigation Identifier", "Study Identifier", "Study File Name",
                "Study Assay File Name", "Comment[Trait Definition File]"):
        if key not in fields:
            problems.append(f"{i_file}: no '{key}'")
    if problems:
        raise IsaTabError(problems)
    for n, (s_name, a_name, t_name, factors) in enumerate(zip(
            fields["Study File Name"], fields["Study Assay File Name"],
            fields["Comment[Trait Definition File]"], fields["Study Factor Name"])):
        paths = {kind: folder / names[0] for kind, names in
                 (("study", s_name), ("assay", a_name), ("trait_dictionary", t_name))}
        missing = [str(p) for p in paths.values() if not p.exists()]
        if missing:
            problems += [f"{p}: named by {i_file.name} (study {n + 1}) but missing"
                         for p in missing]
            continue
        tables = {kind: _read_table(p) for kind, p in paths.items()}
        expected = {"study": [*STUDY_COLUMNS, *(f"Factor Value[{f}]" for f in factors[1:])],
                    "assay": list(ASSAY_COLUMNS),
                    "trait_dictionary": list(TRAIT_DICTIONARY_COLUMNS)}
        for kind, (header, _rows) in tables.items():
            if header != expected[kind]:
                problems.append(f"{paths[kind]}: columns {header} are not the stated "
                                f"{expected[kind]}")
        samples = {r["Sample Name"] for r in tables["study"][1]}
        variables = {r["Variable ID"]: r for r in tables["trait_dictionary"][1]}
        assays = set()
        for i, r in enumerate(tables["assay"][1], start=2):
            assays.add(r.get("Assay Name"))
            if r.get("Sample Name") not in samples:
                problems.append(f"{paths['assay']}:{i}: sample {r.get('Sample Name')!r} is not "
                                f"in {paths['study'].name}")
            data = folder / (r.get("Derived Data File") or "")
            if not data.is_file():
                problems.append(f"{paths['assay']}:{i}: derived data file {data.name!r} missing")
        for data_name in {r.get("Derived Data File") for r in tables["assay"][1]}:
            data = folder / (data_name or "")
            if not data.is_file():
                continue
            header, rows = _read_table(data)
            if header[:len(DATA_KEY_COLUMNS)] != list(DATA_KEY_COLUMNS):
                problems.append(f"{data}: first columns {header[:4]} are not the stated "
                                f"{list(DATA_KEY_COLUMNS)}")
            for v in header[len(DATA_KEY_COLUMNS):]:
                if v not in variables:
                    problems.append(f"{data}: column {v!r} is not a variable of "
                                    f"{paths['trait_dictionary'].name}")
                elif not variables[v].get("Scale"):
                    problems.append(f"{paths['trait_dictionary']}: variable {v!r} has no unit")
            for i, r in enumerate(rows, start=2):
                if r.get("Assay Name") not in assays:
                    problems.append(f"{data}:{i}: assay {r.get('Assay Name')!r} is not in "
                                    f"{paths['assay'].name}")
                for v in header[len(DATA_KEY_COLUMNS):]:
                    cell = r.get(v, "")
                    if cell:
                        try:
                            float(cell)
                        except ValueError:
                            problems.append(f"{data}:{i}: {v} {cell!r} is not a number")
    if problems:
        raise IsaTabError(problems)
