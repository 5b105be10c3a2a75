"""What a model builder returns."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ModelMesh:
    """A solid ready for the precompute.

    points : (N, 3) vertex positions in metres.
    tets : (M, 4) positively oriented linear tetrahedra.
    fixed : selector string for the support region Λu (see ``pmask.precompute.selectors``).
    contact : selector string for the region a probe can touch, or None for every free vertex.
    material : default Young's modulus ``E`` [Pa] and Poisson ratio ``nu``.
    groups : named boolean point masks (gmsh physical groups) usable as ``group:NAME``.
    regions : named boolean masks over the tetrahedra (physical volumes, an inclusion): where
        ``--materials`` (or ``material["regions"]``) puts other materials.
    info : facts about the model worth keeping in the artifact (JSON-serialisable).
    """

    points: np.ndarray
    tets: np.ndarray
    fixed: str
    contact: str | None = None
    material: dict = field(default_factory=lambda: {"E": 1.0e4, "nu": 0.45})
    groups: dict = field(default_factory=dict)
    regions: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


def save_model_mesh(path, model: ModelMesh) -> None:
    """Store a ModelMesh as .npz (atomically): the mesh checkpoint and the reference meshes use it."""
    import json

    from pmask.runtime.files import atomic_write

    meta = {"fixed": model.fixed, "contact": model.contact, "material": model.material, "info": model.info}
    atomic_write(path, lambda tmp: np.savez_compressed(
        tmp, points=model.points, tets=model.tets.astype(np.int32), meta=json.dumps(meta),
        **{f"group_{k}": np.asarray(v, bool) for k, v in model.groups.items()},
        **{f"region_{k}": np.asarray(v, bool) for k, v in model.regions.items()}), suffix=".npz")


def load_model_mesh(path) -> ModelMesh:
    """Read a ModelMesh written by :func:`save_model_mesh`."""
    import json

    with np.load(path) as ck:
        meta = json.loads(str(ck["meta"]))
        groups = {k[6:]: ck[k] for k in ck.files if k.startswith("group_")}
        regions = {k[7:]: ck[k] for k in ck.files if k.startswith("region_")}
        return ModelMesh(points=ck["points"], tets=ck["tets"].astype(np.int64), groups=groups, regions=regions,
                         **meta)
