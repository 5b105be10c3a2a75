"""A loaded artifact: the surface, the free/fixed/contact sets and Ξ."""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from pmask.errors import InputError

from pmask.runtime.artifact import REACTIONS, RUNTIME, VOLUME, read_artifact
from pmask.runtime.geometry import mean_edge_length
from pmask.runtime.masks import check_radius, pressure_masks
from pmask.runtime.stiffness import Stiffness, vertex_stiffness

log = logging.getLogger(__name__)


class Model:
    """Green's functions of one solid, ready to build stiffnesses from.

    Attributes (surface indices unless said otherwise): ``points``, ``triangles``,
    ``vertex_areas``, ``free`` (Λp), ``fixed`` (Λu), ``contact`` (rows/columns of Ξ),
    ``core`` (bool over contact: touchable), ``Xi`` (3 n_c, 3 n_c), ``E``, ``nu``, ``r_max``,
    ``attrs`` (all artifact attributes).  The volume mesh and the support reactions are read only
    when asked for (:meth:`volume`, :meth:`reactions`).
    """

    def __init__(self, data: dict, path: str | None = None):
        a = data["attrs"]
        self.path = path
        self.attrs = a
        self.points = data["surface/points"]
        self.triangles = data["surface/triangles"]
        self.vertex_areas = data["surface/vertex_areas"]
        self.free = data["surface/free"]
        self.fixed = data["surface/fixed"]
        self.contact = data["surface/contact"]
        self.core = data["surface/contact_core"]
        self.Xi = data["greens/Xi"]  # float64, or float32 if stored so (K_i are summed in float64)
        self.E = float(a["material"]["E"])
        self.nu = float(a["material"]["nu"])
        self.r_max = float(a["r_max"])
        self.mean_edge_length = mean_edge_length(self.points, self.triangles)
        self.load_seconds = None

    @classmethod
    def load(cls, path, *, verify: bool = True) -> "Model":
        """Read what the runtime uses (the surface and Ξ) and check it; refuses foreign, corrupt,
        altered or newer-major files (``ArtifactError``)."""
        t0 = time.perf_counter()
        m = cls(read_artifact(path, datasets=RUNTIME, verify=verify), str(path))
        m.verify = verify
        m.load_seconds = time.perf_counter() - t0
        return m

    def volume(self) -> tuple[np.ndarray, np.ndarray]:
        """The tetrahedral mesh the Green's functions came from: (points, tets), read on demand."""
        d = read_artifact(self.path, datasets=VOLUME, verify=getattr(self, "verify", True))
        return d["volume/points"], d["volume/tets"]

    def reactions(self) -> np.ndarray | None:
        """Support reactions (3 n_u, 3 n_c), per unit traction at each contact dof; None if the
        artifact was written without them.  Read on demand."""
        return read_artifact(self.path, datasets=REACTIONS, verify=getattr(self, "verify", True))["greens/reactions"]

    def masks(self, mask: str = "linear", radius: float | None = None):
        """Pressure masks of the touchable contact vertices, over the contact vertices."""
        r = check_radius(mask, radius, self.r_max)
        pts = self.points[self.contact]
        return pressure_masks(pts, self.vertex_areas[self.contact], np.flatnonzero(self.core), mask, r)

    def stiffness(self, mask: str = "linear", radius: float | None = None, *, k_rigid: float | None = None,
                  symmetric: bool = True) -> Stiffness:
        """Vertex stiffnesses for a mask (eq. 12, 14) and the surface stiffness built from them (eq. 15).

        mask : 'linear' (paper's cone), 'gaussian', 'wendland', 'disk' or 'single'.
        radius : mask radius r in model units (the probe tip size), 0 < r <= r_max.
        k_rigid : stiffness of fixed vertices [N/m]; default 10 x the median free ‖K_i‖₂.
        symmetric : render (K + Kᵀ)/2 (passive); False renders the full K_i.
        """
        m = self.masks(mask, radius)
        if m.single_vertex and mask != "single":
            log.info("%d of %d masks reach no neighbour at r = %g (single-vertex stiffness there)",
                     m.single_vertex, len(m.centres), m.radius)
        K = vertex_stiffness(self.Xi, m)
        if k_rigid is None:
            k_rigid = 10.0 * float(np.median(np.linalg.norm(K, ord=2, axis=(1, 2))))
        elif not (np.isfinite(k_rigid) and k_rigid > 0):
            raise InputError(f"k_rigid must be a finite stiffness > 0, got {k_rigid!r}")
        return Stiffness(self, m, K, k_rigid, symmetric)

    def __repr__(self) -> str:
        return (f"Model({Path(self.path).name if self.path else '?'}: {len(self.points)} surface vertices, "
                f"{len(self.free)} free, {len(self.fixed)} fixed, {len(self.contact)} in Ξ)")
