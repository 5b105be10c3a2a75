"""A loaded artifact: the surface, the free/fixed/contact sets and Ξ."""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from pmask.errors import InputError
from pmask.runtime.artifact import NEAR, REACTIONS, RUNTIME, SLICED, VOLUME, read_artifact, stored_bytes
from pmask.runtime.compressed import CompressedXi
from pmask.runtime.device import Device
from pmask.runtime.geometry import mean_edge_length
from pmask.runtime.masks import check_radius, pressure_masks
from pmask.runtime.stiffness import Stiffness, StiffnessError, check_positive_definite, vertex_stiffness

log = logging.getLogger(__name__)


class Model:
    """Green's functions of one solid, ready to build stiffnesses from.

    Attributes (surface indices unless said otherwise): ``points``, ``triangles``,
    ``vertex_areas``, ``free`` (Λp), ``fixed`` (Λu), ``contact`` (rows/columns of Ξ),
    ``core`` (bool over contact: touchable), ``Xi`` (3 n_c, 3 n_c; an array, or a
    :class:`pmask.runtime.compressed.CompressedXi` for a compressed artifact), ``E``, ``nu``, ``r_max``,
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
        if a.get("greens_form") == "hmatrix":  # near field exact, far field low-rank (pmask.runtime.compressed)
            self.Xi = CompressedXi.from_datasets(data, float(a["tolerance"]))
        else:
            self.Xi = data["greens/Xi"]  # float64, or float32 if stored so (K_i are summed in float64)
        self.E = float(a["material"]["E"])
        self.nu = float(a["material"]["nu"])
        self.r_max = float(a["r_max"])
        self.mean_edge_length = mean_edge_length(self.points, self.triangles)
        self.load_seconds = None
        self.xi_rows = None  # Ξᵀ kept for repeated ζ tables (hold_transpose)

    #: far fields larger than this stay in the file (far_field="auto")
    FAR_FIELD_IN_MEMORY = 512 * 2**20
    #: near fields larger than this are read when first needed (near_field="auto")
    NEAR_FIELD_AT_OPEN = 256 * 2**20
    #: the bytes of a near field read on demand held at once (near_field_bytes="auto"): beyond it the blocks
    #: least recently used are let go and read again when needed
    NEAR_FIELD_HELD = 2**30

    @classmethod
    def load(cls, path, *, verify: bool = True, far_field: str = "auto", near_field: str = "auto",
             near_field_bytes="auto") -> "Model":
        """Read what the runtime uses (the surface and Ξ) and check it; refuses foreign, corrupt,
        altered or newer-major files (``ArtifactError``).

        far_field: for a compressed artifact, where its low-rank far field lives: "memory", "file" (read in
        slices when a deformation or a coupling needs them, :class:`pmask.runtime.artifact.FileArray`), or
        "auto": in the file when larger than :data:`FAR_FIELD_IN_MEMORY` (a far field a single contact never
        reads: the bench page gives its size at 20,000 vertices).

        near_field: when a compressed artifact's exact near field (what K_i and the couplings read) is read:
        "open" (here, every block checked by its SHA-256 before this returns), "demand" (a block at a time when
        first needed, each checked by its SHA-256 as it is read, :class:`pmask.runtime.artifact.BlocksOnDemand`:
        a corrupt block is refused then, by the first :meth:`stiffness` at the latest), or "auto": on demand
        when larger than :data:`NEAR_FIELD_AT_OPEN`.  Read at open, it stays in memory.

        near_field_bytes: read on demand, the bytes of it held at once (format 1.6 stores its exact pairs and the
        dense blocks' 16-bit values apart: they share them by size): beyond them the blocks least recently
        used are let go and read (and checked) again when next needed, so that every K_i of an organ whose
        near field exceeds the memory to spare runs within it.  "auto": :data:`NEAR_FIELD_HELD`; None: all of
        it, kept once read."""
        if far_field not in ("auto", "memory", "file"):
            raise InputError(f"far_field must be 'auto', 'memory' or 'file', got {far_field!r}")
        if near_field not in ("auto", "open", "demand"):
            raise InputError(f"near_field must be 'auto', 'open' or 'demand', got {near_field!r}")
        if near_field_bytes == "auto":
            near_field_bytes = cls.NEAR_FIELD_HELD
        elif near_field_bytes is not None and (isinstance(near_field_bytes, bool) or not isinstance(
                near_field_bytes, (int, np.integer)) or near_field_bytes < 0):
            raise InputError(f"near_field_bytes must be 'auto', None or a number of bytes >= 0, got "
                             f"{near_field_bytes!r}")
        t0 = time.perf_counter()
        in_file = ()
        if far_field != "memory":
            in_file = cls._far_field_in_file(path, far_field)
        on_demand = ()
        if near_field != "open":
            size = sum(stored_bytes(path, (d,)) or 0 for d in NEAR) or None  # (the parts this file has)
            if size is not None and (near_field == "demand" or size > cls.NEAR_FIELD_AT_OPEN):
                on_demand = NEAR
        m = cls(read_artifact(path, datasets=RUNTIME, verify=verify, in_file=in_file, on_demand=on_demand,
                              on_demand_budget=near_field_bytes), str(path))
        m.verify = verify
        m.load_seconds = time.perf_counter() - t0
        return m

    def hold_transpose(self) -> None:
        """Keep Ξᵀ (contiguous rows: the columns of Ξ) for every ζ table made from this model from now on
        (:meth:`pmask.runtime.stiffness.Stiffness.zeta_table` transposes Ξ each time otherwise): for a caller
        that changes the mask radius repeatedly, as the viewer does.  It costs the memory of a second Ξ;
        a compressed Ξ has no ζ table, and nothing is kept."""
        if self.xi_rows is None and isinstance(self.Xi, np.ndarray):
            n3 = self.Xi.shape[0]
            self.xi_rows = np.ascontiguousarray(self.Xi.T, dtype=float).reshape(n3 // 3, 3 * n3)

    def volume(self) -> tuple[np.ndarray, np.ndarray]:
        """The tetrahedral mesh the Green's functions came from: (points, tets), read on demand."""
        d = read_artifact(self.path, datasets=VOLUME, verify=getattr(self, "verify", True))
        return d["volume/points"], d["volume/tets"]

    @classmethod
    def _far_field_in_file(cls, path, far_field: str) -> tuple:
        """The far-field datasets to leave in the file (none for a dense artifact)."""
        for far, widen in ((SLICED[:2], 1), (SLICED[2:], 2)):  # the far field's factors (format 1.8: in 16 bits,
            size = stored_bytes(path, far)  # float32 once read into memory)
            if size is not None:
                return far if far_field == "file" or widen * size > cls.FAR_FIELD_IN_MEMORY else ()
        return ()

    def display(self):
        """The display surface at the scan's resolution (:class:`pmask.runtime.display.DisplaySurface`), read on
        demand; None when the artifact has none (a built-in model, a --volume mesh, --no-display)."""
        from pmask.runtime.display import DisplaySurface

        return DisplaySurface.from_artifact(self.path, getattr(self, "verify", True)) if self.path else None

    def reactions(self) -> np.ndarray | None:
        """Support reactions (3 n_u, 3 n_c), per unit traction at each contact dof; None if the
        artifact was written without them.  Read on demand."""
        return read_artifact(self.path, datasets=REACTIONS, verify=getattr(self, "verify", True))["greens/reactions"]

    #: the default mask radius, in mean edge lengths: a cone over the vertex's neighbours and theirs (smaller
    #: masks reach no neighbour on much of a mesh and fall back to single vertices)
    DEFAULT_RADIUS_EDGES = 2.0

    @property
    def default_radius(self) -> float:
        """The mask radius used when none is given: 2 mean edge lengths, at most r_max (the one place this
        default is set)."""
        return float(min(self.DEFAULT_RADIUS_EDGES * self.mean_edge_length, self.r_max))

    def masks(self, mask: str = "linear", radius: float | None = None, *, band: bool = False):
        """Pressure masks of the touchable contact vertices (``band``: of the contact vertices outside
        the region, whose masks the region's edge truncates), over the contact vertices.  ``radius=None``:
        :attr:`default_radius`."""
        if radius is None and mask != "single":
            radius = self.default_radius
        r = check_radius(mask, radius, self.r_max)
        pts = self.points[self.contact]
        centres = np.flatnonzero(~self.core if band else self.core)
        return pressure_masks(pts, self.vertex_areas[self.contact], centres, mask, r)

    def stiffness(self, mask: str = "linear", radius: float | None = None, *, k_rigid: float | None = None,
                  symmetric: bool = True, device: Device | None = None,
                  support_blend: float | None = None) -> Stiffness:
        """Vertex stiffnesses for a mask (eq. 12, 14) and the surface stiffness built from them (eq. 15).

        Parameters
        ----------
        mask
            'linear' (paper's cone), 'gaussian', 'wendland', 'disk' or 'single'.
        radius
            mask radius r in model units (the probe tip size), 0 < r <= r_max; default
            :attr:`default_radius` (2 mean edge lengths).
        device
            the haptic device (:class:`pmask.runtime.Device`); its stable stiffness bound
            2 b / T caps the default k_rigid.
        k_rigid
            stiffness the support ramps to [N/m]; default min(10 x the median free ‖K_i‖₂,
            half the device's stable bound).
        support_blend
            distance [model units] over which a fixed vertex's stiffness ramps from the
            tissue's next to it to k_rigid; default 4 mask radii (at least 4 mean edges).
        symmetric
            render (K + Kᵀ)/2 (passive when sticking); False renders the full K_i.

        Refuses (:class:`pmask.runtime.stiffness.StiffnessError`, naming the vertices) Green's functions
        whose vertex stiffnesses are not positive definite.
        """
        device = Device() if device is None else device
        if not isinstance(device, Device):
            raise InputError(f"device must be a pmask.runtime.Device, got {device!r}")
        m = self.masks(mask, radius)
        if m.single_vertex and mask != "single":
            log.info("%d of %d masks reach no neighbour at r = %g (single-vertex stiffness there)",
                     m.single_vertex, len(m.centres), m.radius)
        K = vertex_stiffness(self.Xi, m)
        try:
            check_positive_definite(K, self.contact[m.centres])
        except StiffnessError:
            if mask == "single":  # with P2 a vertex's point load is not the adjoint of its point value: the
                # block need not be positive definite on a coarse mesh, and nothing is corrupt
                check_positive_definite(K, self.contact[m.centres], cause=(
                    f"a point load observed at its own vertex on a mesh this coarse ({len(self.points)} surface "
                    f"vertices, mean edge {self.mean_edge_length:.3g}): use a mask (e.g. 'linear') or a finer mesh"))
            # with P1 the point-force blocks Ξ_ii / a_i of an elastic body are positive definite: if they are,
            # the mask is to blame (spread over it, the traction can move the centre against the force on a
            # coarse or small body), not the Green's functions.  With P2 they need not be (above): a
            # sign-flipped Ξ makes most K_i negative definite, a mask too large for its body some indefinite
            if str(self.attrs.get("element", "P1")).upper() == "P1":
                single = self.masks("single")
                check_positive_definite(vertex_stiffness(self.Xi, single), self.contact[single.centres])
            elif np.mean(np.linalg.eigvalsh(0.5 * (K + np.swapaxes(K, -1, -2)))[:, -1] < 0) > 0.5:
                check_positive_definite(K, self.contact[m.centres])
            check_positive_definite(K, self.contact[m.centres], cause=(
                f"the {mask} mask of radius {m.radius:.3g} (mean edge {self.mean_edge_length:.3g}) moves these "
                "centres against the force it spreads, which a mask large for its body or mesh can do; use a "
                "smaller mask radius"))
        band = self.masks(mask, radius, band=True) if not self.core.all() else None
        K_band = vertex_stiffness(self.Xi, band) if band is not None and len(band.centres) else None
        if K_band is not None:
            check_positive_definite(K_band, self.contact[band.centres])
        if k_rigid is None:
            k_rigid = min(10.0 * float(np.median(np.linalg.norm(K, ord=2, axis=(1, 2)))),
                          0.5 * device.stable_stiffness())
        elif not (np.isfinite(k_rigid) and k_rigid > 0):
            raise InputError(f"k_rigid must be a finite stiffness > 0, got {k_rigid!r}")
        if support_blend is None:
            support_blend = max(4.0 * m.radius, 4.0 * self.mean_edge_length)
        elif not (np.isfinite(support_blend) and support_blend > 0):
            raise InputError(f"support_blend must be a finite length > 0, got {support_blend!r}")
        return Stiffness(self, m, K, k_rigid, symmetric, band_masks=band, K_band=K_band,
                         support_blend=support_blend, device=device)

    def __repr__(self) -> str:
        return (f"Model({Path(self.path).name if self.path else '?'}: {len(self.points)} surface vertices, "
                f"{len(self.free)} free, {len(self.fixed)} fixed, {len(self.contact)} in Ξ)")
