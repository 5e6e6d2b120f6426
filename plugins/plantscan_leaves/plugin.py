"""plantscan_leaves: leaf segmentation (``learned-organs``, ``curvature-regions``) and leaf traits
(``leaf-geometry``).

See ``docs/leaves.md`` for the method, parameters and per-species guidance.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from plantscan_core.data import LabelledMesh, Mesh, Traits
from plantscan_core.hookspecs import hookimpl
from plantscan_core.stages import Measurer, MeshSegmenter
from plantscan_leaves.evaluate import evaluate_traits
from plantscan_leaves.measure import LeafGeometryParams, measure_plant
from plantscan_leaves.organs import LearnedOrgansParams, segment_organs
from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves

log = logging.getLogger(__name__)


class CurvatureRegions(MeshSegmenter):
    """Leaves and stem by curvature-constrained region growing (every face labelled)."""

    name = "curvature-regions"
    Params = CurvatureRegionsParams

    def input_files(self, scan) -> list[Path]:
        """The judges' model files in use: the run's cache key hashes their content, so a
        model retrained under the same name segments again (files the package ships
        included: an upgrade that retrains one does too)."""
        from plantscan_leaves import pairs, pieces, stem_parts

        p = self.params
        files = []
        if p.judge_pieces:
            files.append(pieces.model_location(p.piece_model, pieces.MODEL_FILE))
        if p.judge_stem_parts:
            files.append(pieces.model_location(p.stem_part_model, stem_parts.MODEL_FILE))
        if p.judge_pairs:
            files.append(pieces.model_location(p.pair_model, pairs.MODEL_FILE))
        return [Path(str(f)) for f in files]

    def segment(self, mesh: Mesh) -> LabelledMesh:
        labelled, self.report = segment_leaves(mesh, self.params)
        return labelled


class LearnedOrgans(MeshSegmenter):
    """Leaves, stem and debris by an organ classifier learned from the virtual scanner."""

    name = "learned-organs"
    Params = LearnedOrgansParams

    def input_files(self, scan) -> list[Path]:
        """The organ model's files: the run's cache key hashes their content."""
        from plantscan_leaves.organs import MODEL_FILES, model_root

        root = model_root(self.params.model_dir)
        return [Path(str(root / name)) for name in MODEL_FILES.values()]

    def segment(self, mesh: Mesh) -> LabelledMesh:
        labelled, self.report = segment_organs(mesh, self.params)
        return labelled


class LeafGeometry(Measurer):
    """Flat-leaf length, width, area, perimeter of every leaf; plant-level traits."""

    name = "leaf-geometry"
    Params = LeafGeometryParams

    def input_files(self, scan) -> list[Path]:
        """The trust and tip models' files when named: the run's cache key hashes their
        content."""
        from plantscan_leaves.pieces import model_location

        names = (self.params.trust_model, self.params.tip_model)
        return [Path(str(model_location(n, n))) for n in names if n is not None]

    def measure(self, labelled: LabelledMesh) -> Traits:
        scan = self.context.scan
        views = None if scan is None else len(scan.views_by_role("plant"))
        traits, _, self.report = measure_plant(labelled, self.params, views)
        return traits


@hookimpl
def plantscan_register_stages(registry) -> None:
    registry.add(CurvatureRegions)
    registry.add(LearnedOrgans)
    registry.add(LeafGeometry)


@hookimpl
def plantscan_evaluate(run_dir: Path, truth_dir: Path) -> dict[str, Any] | None:
    return evaluate_traits(run_dir, truth_dir)


@hookimpl
def plantscan_warm_up() -> str | None:
    from plantscan_leaves import kernels

    return kernels.warm_up()
