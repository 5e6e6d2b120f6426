"""A virtual growth experiment's design: genotypes x treatments x replicates x daily scans.

A genotype is a plant family of the virtual scanner (or a fixed preset, which
does not grow); a replicate is a validation seed (>= 1000: nothing was tuned
on them), the same seed under both treatments; a treatment sets the pace of
development (drought develops at ``DROUGHT_PACE`` of the control's), so the
plant scanned on day ``d`` is ``(first_age + d) * pace`` days old.  The truth
of each planned scan is ``truth_plant(scan)`` (no rendering), and its sample
sheet row says who the plant is (MIAPPE fields, docs/experiments.md).

Used by ``benchmarks/experiment.py`` (rendered, processed, stored) and by the
store's tests (the truth's traits stored directly, tests/store).
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from plantscan_sim.families import FAMILIES

DROUGHT_PACE = 0.7  # a drought plant on day d has the control's development at 0.7 d
TREATMENTS = {"control": 1.0, "drought": DROUGHT_PACE}
WATERING = {"control": "100%", "drought": "30%"}  # the factor the treatment stands for
VALIDATION_SEED0 = 1000
SEEDS_PER_GENOTYPE = 100  # genotype i draws its replicates from 1000 + 100 i + 1, ...
STUDY_ID = "virtual-growth"
INVESTIGATION_ID = "VIRT-1"
SOWN = _dt.date(2026, 4, 20)
FIRST_SCAN = _dt.datetime(2026, 5, 4, 9, 0)  # day 0, 09:00 UTC
SHEET_COLUMNS = ("plant_id", "genotype", "treatment", "replicate", "sowing_date", "species",
                 "study_id", "investigation_id", "factor.watering")


@dataclass(frozen=True)
class PlannedScan:
    """One scan of the experiment: which plant, on which day, at which age (days)."""

    plant_id: str
    genotype: str
    family: str
    treatment: str
    replicate: int
    seed: int
    day: int
    age: float | None  # None: a fixed preset (mature, does not grow)
    slot: int = 0  # the plant's place in each day's round (scanned 5 min apart)

    @property
    def scan_time(self) -> _dt.datetime:
        """When the scan is made (naive UTC): day ``day`` of the experiment, 09:00 plus
        5 min per plant scanned before it that day."""
        return FIRST_SCAN + _dt.timedelta(days=self.day, minutes=5 * self.slot)


def growth_design(genotypes: Mapping[str, str], days: int = 5, replicates: int = 3,
                  first_age: float = 14.0, seed0: int = VALIDATION_SEED0) -> list[PlannedScan]:
    """Every scan of the experiment, plant by plant and day by day.

    Parameters
    ----------
    genotypes : {genotype name: plant family or fixed preset}
    days : int
        Daily scans per plant.
    replicates : int
        Plants per genotype and treatment (seeds ``seed0 + 100 i + 1 ...`` for the
        ``i``-th genotype; the same seeds under both treatments).
    first_age : float
        Age (days after emergence) of a control plant on day 0.
    seed0 : int
        First seed: validation (>= 1000) by default; below 1000 a development
        design (for tuning a stage on the same kind of plants).
    """
    if days < 1 or replicates < 1:
        raise ValueError(f"days ({days}) and replicates ({replicates}) must be >= 1")
    out: list[PlannedScan] = []
    slot = 0
    for gi, (genotype, family) in enumerate(genotypes.items()):
        for treatment, pace in TREATMENTS.items():
            for rep in range(1, replicates + 1):
                seed = seed0 + SEEDS_PER_GENOTYPE * gi + rep
                for day in range(days):
                    age = round((first_age + day) * pace, 3) if family in FAMILIES else None
                    out.append(PlannedScan(f"{genotype}-{treatment}-r{rep}", genotype, family,
                                           treatment, rep, seed, day, age, slot))
                slot += 1
    return out


def sample_sheet(design: Sequence[PlannedScan]) -> str:
    """The experiment's sample sheet (CSV text): one row per plant, for all its scans."""
    plants = {s.plant_id: s for s in design}
    lines = [",".join(SHEET_COLUMNS)]
    for pid, s in sorted(plants.items()):
        lines.append(f"{pid},{s.genotype},{s.treatment},{s.replicate},{SOWN},"
                     f"virtual {s.family},{STUDY_ID},{INVESTIGATION_ID},{WATERING[s.treatment]}")
    return "\n".join(lines) + "\n"


def scene_params(scan: PlannedScan) -> dict:
    """The virtual scanner's scene parameters of ``scan``'s plant (preset, seed, age)."""
    return {"preset": scan.family, "seed": scan.seed,
            **({} if scan.age is None else {"age": scan.age})}


def truth_plant(scan: PlannedScan, **scene: object):
    """The plant of ``scan`` as the virtual scanner holds it (``plantscan_sim.plants.Plant``):
    its leaf ids are kept across ages, ``plant.traits()`` is the truth.  ``scene``: further
    scene parameters (pot, leaf thickness), the recipe's defaults otherwise."""
    from plantscan_sim.scene import SimSceneParams, scene_plant

    return scene_plant(SimSceneParams(**scene_params(scan), **scene))


TRUTH_LEAF_COLUMNS = ("length_mm", "width_mm", "area_mm2", "perimeter_mm", "centroid_x_mm",
                      "centroid_y_mm", "centroid_z_mm")


def truth_leaves(plant) -> list[dict[str, float]]:
    """The truth's leaves of ``plant`` (``truth_plant``): id, flat-leaf traits (mm, mm²) and
    the area-weighted centroid of the blade (mm, turntable frame), by leaf id."""
    from plantscan_core.data import Mesh

    mesh = Mesh(plant.mesh.vertices, plant.mesh.faces)
    centroids = mesh.label_centroids(plant.mesh.face_attr)
    out = []
    for leaf in sorted(plant.traits().leaves, key=lambda t: t.leaf_id):
        c = centroids[leaf.leaf_id]
        out.append({"leaf_id": leaf.leaf_id, "length_mm": leaf.length_mm,
                    "width_mm": leaf.width_mm, "area_mm2": leaf.area_mm2,
                    "perimeter_mm": leaf.perimeter_mm, "centroid_x_mm": float(c[0]),
                    "centroid_y_mm": float(c[1]), "centroid_z_mm": float(c[2])})
    return out
