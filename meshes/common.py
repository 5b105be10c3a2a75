"""What a model builder returns."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ModelMesh:
    """A solid ready for the precompute.

    points : (N, 3) vertex positions in metres.
    tets : (M, 4) positively oriented linear tetrahedra.
    fixed : selector string for the support region Λu (see ``precompute.selectors``).
    contact : selector string for the region a probe can touch, or None for every free vertex.
    material : default Young's modulus ``E`` [Pa] and Poisson ratio ``nu``.
    groups : named boolean point masks (gmsh physical groups) usable as ``group:NAME``.
    info : facts about the model worth keeping in the artifact (JSON-serialisable).
    """

    points: np.ndarray
    tets: np.ndarray
    fixed: str
    contact: str | None = None
    material: dict = field(default_factory=lambda: {"E": 1.0e4, "nu": 0.45})
    groups: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)
