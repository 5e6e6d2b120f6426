"""Shared phantoms of the leaf tests (meshed once per session: marching cubes is the slow part)."""

from __future__ import annotations

import numpy as np
import pytest
from plantscan_leaves import phantoms as ph

from plantscan_core.data import Mesh


@pytest.fixture(scope="session")
def mock_plant() -> tuple[ph.MockPlant, Mesh, np.ndarray]:
    """Stem + 5 leaves on 20 mm petioles voxelised at 0.8 mm, and each face's true part
    (-1 stem and petioles, 0.. leaves)."""
    plant = ph.mock_plant(5, thickness=2.0, petiole_mm=20.0)
    mesh = plant.mesh(voxel_mm=0.8)
    return plant, mesh, plant.part_of(mesh.vertices[mesh.faces].mean(axis=1))


@pytest.fixture(scope="session")
def mock_plant_measured(mock_plant):
    """The mock plant through both stages (default parameters): (labelled, traits)."""
    from plantscan_leaves.measure import measure_plant
    from plantscan_leaves.segment import segment_leaves

    _, mesh, _ = mock_plant
    labelled, _ = segment_leaves(mesh)
    traits, _, _ = measure_plant(labelled)
    return labelled, traits
