"""Stage orchestration: mesh → condense (factorise) → Green's functions → artifact.

Each expensive stage leaves a checkpoint (written atomically) in a work folder
named after the input hash, next to the artifact.  A run that is interrupted
resumes from the last finished stage; a run whose inputs are unchanged finds
the artifact up to date and does nothing.  The work folder is removed once the
artifact is written.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import platform
import re
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pmask.errors import InputError, OutputError, ResourceError
from pmask.meshes.common import ModelMesh, load_model_mesh, save_model_mesh
from pmask.runtime.artifact import FORMAT_VERSION
from pmask.runtime.files import atomic_write

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
CODE_DIRS = ("precompute", "meshes", "pipeline")
CODE_FILES = ("runtime/artifact.py", "runtime/geometry.py")


@dataclass
class Spec:
    """Everything that determines an artifact.

    model : registered model name, or a label for a user's geometry.
    params : keyword arguments of the model builder.
    surface, volume : a user's geometry file (at most one), instead of a registered model.
    fixed, contact : region selectors (None: the model's defaults).
    E, nu : material (None: the model's defaults).  units : length unit of the input geometry.
    r_max : largest mask radius [m] the runtime may use (None: model default).
    edge_length : target edge length [m] when remeshing a --surface.
    dtype : storage precision of Ξ, "float64" or "float32" (half the size; see README).
    element : "P1" (selected inversion) or "P2" (blocked solves; for small contact regions).
    """

    model: str
    params: dict = field(default_factory=dict)
    surface: str | None = None
    volume: str | None = None
    fixed: str | None = None
    contact: str | None = None
    E: float | None = None
    nu: float | None = None
    units: str = "m"
    r_max: float | None = None
    edge_length: float | None = None
    dtype: str = "float64"
    element: str = "P1"


UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6}


def file_digest(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def code_digest() -> str:
    """Hash of the source that produces an artifact (a code change invalidates artifacts)."""
    h = hashlib.sha256()
    files = sorted(p for d in CODE_DIRS for ext in ("*.py", "*.c") for p in (ROOT / d).rglob(ext))
    files += [ROOT / f for f in CODE_FILES]
    for p in files:
        h.update(str(p.relative_to(ROOT)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def library_versions() -> dict:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for name in ("numpy", "scipy", "h5py", "gmsh", "scikit-fem", "meshio", "cvxopt", "trimesh"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = None
    from pmask.precompute import native

    out["cholmod"] = native.cholmod_version()
    return out


def input_hash(spec: Spec) -> str:
    """SHA-256 of every input: geometry, parameters, code and the libraries that shape the mesh."""
    d = asdict(spec)
    for key in ("surface", "volume"):
        if d[key]:
            d[key] = {"sha256": file_digest(d[key])}
    versions = library_versions()
    d["code"] = code_digest()
    d["format_version"] = FORMAT_VERSION
    d["libraries"] = {k: versions[k] for k in ("gmsh", "scikit-fem")}
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()


def artifact_hash(path: Path) -> str | None:
    """The input hash stored in an existing artifact, or None."""
    try:
        import h5py

        with h5py.File(path, "r") as f:
            v = f.attrs.get("input_hash")
            return v.decode() if isinstance(v, bytes) else v
    except (OSError, KeyError):
        return None


def _save_npz(path: Path, **arrays) -> None:
    atomic_write(path, lambda tmp: np.savez(tmp, **arrays), suffix=".npz")


def build_mesh(spec: Spec):
    """Stage 1: the volume mesh and its regions from a model or a user's file."""
    from pmask.pipeline.models import get_model
    from pmask.precompute import meshing

    scale = UNITS[spec.units]
    if spec.surface:
        if spec.edge_length is None:
            raise InputError("--surface needs --edge-length (target edge length in the file's units)")
        points, tets = meshing.remesh_surface(Path(spec.surface), edge_length=spec.edge_length * scale, scale=scale)
        return ModelMesh(points=points, tets=tets, fixed=spec.fixed or "", info={"source": Path(spec.surface).name})
    if spec.volume and spec.volume.endswith(".npz"):  # a stored ModelMesh (reference meshes)
        return load_model_mesh(spec.volume)
    if spec.volume:
        points, tets, groups = meshing.read_volume(Path(spec.volume), scale=scale)
        return ModelMesh(points=points, tets=tets, fixed=spec.fixed or "", groups=groups,
                         info={"source": Path(spec.volume).name})
    return get_model(spec.model)(**spec.params)


def _p1_greens(model, surf_vertices, reg, areas, E, nu, work, timings, resumed, bar, label):
    """P1: assemble, factorise K_FF (checkpointed), then Ξ by selected inversion."""
    from pmask.precompute import condense, elasticity

    t0 = time.perf_counter()
    factor_ck = work / "factor.npz"
    if factor_ck.exists():
        factor = condense.factor_from_arrays(np.load(factor_ck))
        resumed.append("factor")
        timings["assemble"] = 0.0
        timings["factor"] = time.perf_counter() - t0
    else:
        K = elasticity.stiffness_matrix(model.points, model.tets, E, nu)
        timings["assemble"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        contact_v = surf_vertices[reg.contact]
        fixed_v = surf_vertices[reg.fixed]
        interior = np.setdiff1d(np.arange(len(model.points)), np.concatenate([contact_v, fixed_v]))
        factor = condense.surface_factor(K, model.tets, interior, contact_v, fixed_v)
        del K
        timings["factor"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        _save_npz(factor_ck, **condense.factor_arrays(factor))
        timings["checkpoint"] = time.perf_counter() - t0
    _checkpoint_reached("factor")
    bar.update()
    bar.set_description(f"{label}: Green's functions")
    t0 = time.perf_counter()
    Xi, reactions = condense.greens_functions(factor, areas[reg.contact])
    timings["greens"] = time.perf_counter() - t0
    bar.update()
    bar.set_description(f"{label}: write")
    return Xi, reactions, {**factor.stats, "element": "P1"}


def _bytes(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


def check_memory(n_contact: int, element: str) -> None:
    """Refuse, before any heavy work, a contact region whose dense Ξ cannot be computed in this
    machine's memory.  Peak working set per byte of Ξ (3 n_c)² float64, measured: ~1.6 for the
    native selected inversion (its result buffer also holds the rows next to the support), ~2.5 for
    the pip-only one (a permuted copy); ~3 assumed for P2 (Ξ, solves and copies)."""
    from pmask.precompute import condense

    xi = 8.0 * (3 * n_contact) ** 2
    factor = (1.6 if condense.cholmod_backend() == "native" else 2.5) if element == "P1" else 3.0
    avail = condense.available_memory()
    if avail is not None and xi * factor > avail:
        raise ResourceError(
            f"Ξ of {n_contact} contact vertices is a dense {3 * n_contact} x {3 * n_contact} matrix "
            f"({_bytes(xi)} in float64, ~{_bytes(xi * factor)} to compute), more than the "
            f"{_bytes(avail)} this machine has available: restrict the region a probe can touch "
            "(--contact SELECTOR) or coarsen the mesh (--size, --edge-length)")


def _checkpoint_reached(stage: str) -> None:
    """Test hook: ``PMASK_PAUSE_AFTER=<stage>`` sleeps after that stage's checkpoint, so that a test
    can kill a real run mid-way and check that the next run resumes from there."""
    if os.environ.get("PMASK_PAUSE_AFTER") == stage:
        log.warning("pausing after stage %s (PMASK_PAUSE_AFTER)", stage)
        time.sleep(float(os.environ.get("PMASK_PAUSE_SECONDS", "600")))


def run(spec: Spec, out: Path, *, force: bool = False, progress: bool = False) -> dict:
    """Run the precompute for ``spec`` into ``out``; return a summary dict.

    ``progress`` shows a bar over the stages on stderr (the CLI turns it on for a terminal).
    """
    from pmask.precompute import elasticity, regions, selectors, surface
    from pmask.precompute.writer import write_artifact
    from pmask.runtime.geometry import mean_edge_length, vertex_areas

    out = Path(out)
    if spec.element not in ("P1", "P2"):
        raise InputError(f"element must be P1 or P2, got {spec.element!r}")
    if spec.dtype not in ("float64", "float32"):
        raise InputError(f"dtype must be float64 or float32, got {spec.dtype!r}")
    if spec.units not in UNITS:
        raise InputError(f"unknown length unit '{spec.units}'; use one of {', '.join(UNITS)}")
    for key in ("surface", "volume"):
        p = getattr(spec, key)
        if p and not Path(p).is_file():
            raise InputError(f"--{key} {p}: no such file")
    if spec.E is not None or spec.nu is not None:
        elasticity.check_material(spec.E if spec.E is not None else 1.0, spec.nu if spec.nu is not None else 0.3)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out.parent, prefix=".pmask-write-test-"):
            pass
    except OSError as exc:
        raise OutputError(f"cannot write to {out.parent} ({exc.strerror or exc}); "
                              "choose a writable folder with --out") from None
    h = input_hash(spec)
    if out.exists() and not force and artifact_hash(out) == h:
        log.debug("%s is up to date (input hash %s)", out, h[:12])
        return {"up_to_date": True, "artifact": str(out), "input_hash": h}

    work = out.parent / ".work" / f"{out.stem}-{h[:16]}"
    work.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    resumed: list[str] = []
    bar = tqdm(total=4, desc=f"{spec.model}: mesh", disable=not progress, file=sys.stderr, leave=False,
               bar_format="{desc:<40} {bar} {n_fmt}/{total_fmt} [{elapsed}]")

    # -- stage 1: mesh ---------------------------------------------------------------------
    t0 = time.perf_counter()
    mesh_ck = work / "mesh.npz"
    if mesh_ck.exists():
        model = load_model_mesh(mesh_ck)
        resumed.append("mesh")
    else:
        model = build_mesh(spec)
        save_model_mesh(mesh_ck, model)
    timings["mesh"] = time.perf_counter() - t0
    _checkpoint_reached("mesh")
    bar.update()
    bar.set_description(f"{spec.model}: assemble + factorise")

    E = spec.E if spec.E is not None else model.material["E"]
    nu = spec.nu if spec.nu is not None else model.material["nu"]
    elasticity.check_material(E, nu)
    scale = UNITS[spec.units]

    # -- regions (cheap) -------------------------------------------------------------------
    t0 = time.perf_counter()
    surf_vertices, triangles = surface.boundary_surface(model.points, model.tets)
    spoints = model.points[surf_vertices]
    areas = vertex_areas(spoints, triangles)
    fixed_sel = spec.fixed or model.fixed
    if not fixed_sel:
        raise regions.RegionError("no fixed region given: use --fixed SELECTOR (e.g. 'z<-0.9' or 'group:NAME')")
    contact_sel = spec.contact if spec.contact is not None else model.contact
    fixed_mask = selectors.select(fixed_sel, model.points / scale, model.groups)[surf_vertices]
    contact_mask = (selectors.select(contact_sel, model.points / scale, model.groups)[surf_vertices]
                    if contact_sel else None)
    bbox = float(np.linalg.norm(spoints.max(axis=0) - spoints.min(axis=0)))
    if spec.r_max is not None:
        r_max = spec.r_max * scale
    elif contact_mask is None:
        r_max = bbox  # every free vertex is in Ξ: any mask is complete
    else:
        r_max = model.info.get("r_max_m", 4.0 * mean_edge_length(spoints, triangles))
    reg = regions.surface_regions(spoints, fixed_mask, contact_mask, r_max,
                                  fixed_selector=fixed_sel, contact_selector=contact_sel or "")
    timings["regions"] = time.perf_counter() - t0
    check_memory(len(reg.contact), spec.element)

    if spec.element == "P2":
        # P2: one sparse factorisation and blocked solves (no factor checkpoint)
        from pmask.precompute import p2

        t0 = time.perf_counter()
        K2, edges = p2.p2_stiffness(model.points, model.tets, E, nu)
        B = p2.surface_load_matrix(model.points, surf_vertices[triangles], edges)
        timings["assemble"] = time.perf_counter() - t0
        bar.update()
        t0 = time.perf_counter()
        Xi, reactions, factor_stats = p2.greens_by_solves(K2, B, edges, surf_vertices[reg.contact],
                                                          surf_vertices[reg.fixed])
        del K2
        timings["greens"] = time.perf_counter() - t0
        bar.update()
    else:
        Xi, reactions, factor_stats = _p1_greens(model, surf_vertices, reg, areas, E, nu, work, timings,
                                                 resumed, bar, spec.model)

    # -- stage 4: write ------------------------------------------------------------------------
    t0 = time.perf_counter()
    meta = {
        "model": spec.model, "input_hash": h, "E": float(E), "nu": float(nu), "r_max": float(r_max),
        "fixed_selector": fixed_sel, "contact_selector": contact_sel or "",
        "parameters": {**asdict(spec), "model_info": model.info},
        "provenance": {"libraries": library_versions(), "code_sha256": code_digest(),
                       "created_unix": time.time(), "host": platform.node(), "resumed_stages": resumed,
                       "factor": factor_stats},
        "timings": timings,
    }
    meta["element"] = spec.element
    write_artifact(out, meta=meta, volume_points=model.points, tets=model.tets, surface_vertices=surf_vertices,
                   triangles=triangles, areas=areas, regions=reg, Xi=Xi, reactions=reactions,
                   dtype=np.dtype(spec.dtype))
    timings["write"] = time.perf_counter() - t0
    bar.update()
    bar.close()
    mine = re.compile(rf"^{re.escape(out.stem)}-[0-9a-f]{{16}}$")
    for stale in (out.parent / ".work").glob(f"{out.stem}-*"):  # this run's and older runs' checkpoints
        if mine.match(stale.name):
            shutil.rmtree(stale, ignore_errors=True)
    try:
        (out.parent / ".work").rmdir()
    except OSError:
        pass
    return {"up_to_date": False, "artifact": str(out), "input_hash": h, "timings": timings, "resumed": resumed,
            "volume_vertices": len(model.points), "tets": len(model.tets), "surface_vertices": len(spoints),
            "free": len(reg.free), "fixed": len(reg.fixed), "contact": len(reg.contact),
            "size_bytes": out.stat().st_size, "dofs": factor_stats.get("dofs"),
            "backend": factor_stats.get("backend"), "element": spec.element, "factor_stats": factor_stats}
