"""Stage orchestration: mesh → regions → factorise → Green's functions → artifact.

Every stage is a function of its inputs that returns its result; :func:`run` validates everything
before any work, then calls the stages in order.  The two expensive stages leave a checkpoint (written
atomically) in ``.work/OUT-STEM/`` next to the artifact, keyed by a hash of exactly the inputs that
stage depends on: the mesh by the geometry, the factor by the mesh, material, regions and element.
So a run that is interrupted resumes from its last finished stage, and a run that changes only what a
later stage depends on (following an error's advice to restrict ``--contact``, say) reuses the mesh.
A run whose inputs are all unchanged finds the artifact up to date and does nothing.  The work folder
goes once the artifact is written; a failure keeps only checkpoints a corrected run can reuse.
"""
from __future__ import annotations

import ast
import functools
import contextlib
import hashlib
import inspect
import json
import logging
import os
import platform
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from pmask import interrupt
from pmask.errors import InputError, OutputError, ResourceError
from pmask.meshes.common import ModelMesh, load_model_mesh, save_model_mesh
from pmask.precompute.meshing import file_digest
from pmask.runtime.artifact import FORMAT_VERSION, stored_input_hash
from pmask.runtime.files import Background

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
#: the source whose changes change an artifact's numbers (docstrings and comments excluded)
RESULT_CODE = ("precompute/*.py", "precompute/*.c", "meshes/*.py", "pipeline/stages.py", "pipeline/models.py",
               "runtime/artifact.py", "runtime/geometry.py")
UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6}


@dataclass
class Spec:
    """Everything that determines an artifact.

    Attributes
    ----------
    model
        registered model name, or a label for a user's geometry.
    params
        keyword arguments of the model builder.
    surface, volume
        a user's geometry file (at most one), instead of a registered model.
    fixed, contact
        region selectors (None: the model's defaults).
    E, nu
        material (None: the model's defaults).  units : length unit of the input geometry (None:
        metres, and a user's file more than 2 m across is refused as probably in mm).
    r_max
        largest mask radius the runtime may use, in the input's units (None: model default).
    edge_length
        target edge length when remeshing a --surface, in the input's units.
    dtype
        storage precision of Ξ, "float64" or "float32" (half the size; see README).
    element
        a name from :data:`pmask.precompute.elements.ELEMENTS`.
    reactions
        store the support reactions; None: when they cost no more than Ξ (see
        :func:`pmask.precompute.greens.factorise`).
    mesh_timeout, solve_timeout
        seconds allowed to the gmsh worker, and to the factorisation and
        Green's functions together (native route: Ctrl-C and the budget stop them between supernodes).
    compress
        store Ξ compressed, far-field blocks within this relative tolerance (None: dense;
        :mod:`pmask.precompute.compress`); scheduler : a Dask scheduler's address for its tiles (None: a
        LocalCluster); workers : local worker processes (None: one per core); worker_memory : each local
        worker's memory limit ('4G'; None: dask's share of the machine).
    """

    model: str
    params: dict = field(default_factory=dict)
    surface: str | None = None
    volume: str | None = None
    fixed: str | None = None
    contact: str | None = None
    E: float | None = None
    nu: float | None = None
    materials: str | None = None
    units: str | None = None
    r_max: float | None = None
    edge_length: float | None = None
    dtype: str = "float64"
    element: str = "auto"
    reactions: bool | None = None
    mesh_timeout: float = 600.0
    solve_timeout: float = 3600.0
    segmentation: str | None = None
    label: int | None = None
    repair: str | None = None
    shell: int | None = None
    inclusions: tuple = ()
    display: bool = True
    compress: float | None = None
    scheduler: str | None = None
    workers: int | None = None
    worker_memory: str | None = None

    @property
    def scale(self) -> float:
        """Metres per input length unit."""
        return UNITS[self.units or "m"]


@dataclass
class SimulationSurface:
    """The simulation surface: the boundary of the volume mesh and its regions (stage 2), as distinct from the
    display surface (the scan at its own resolution, :mod:`pmask.precompute.display`) and the runtime's contact
    surface (:class:`pmask.runtime.contact.ContactSurface`).

    vertices : volume indices of the surface vertices (sorted); triangles : into ``vertices``,
    counter-clockwise from outside; areas : a_i = ∫ φ_i dΓ; regions : free/fixed/contact/core sets
    (surface indices); r_max : largest mask radius [m]; fixed_selector, contact_selector : as given;
    held : bool over ``triangles``, the facets the support holds (all three corners fixed); cavities : the
    vertex count of each cavity's wall (a hollow body; groups ``cavity``, ``cavity1``, ...).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    areas: np.ndarray
    regions: object
    r_max: float
    fixed_selector: str
    contact_selector: str
    held: np.ndarray
    cavities: tuple = ()

    def held_facets(self) -> np.ndarray:
        """The held facets as volume vertex indices (k, 3)."""
        return self.vertices[self.triangles[self.held]]


# ------------------------------------------------------------------------------- hashing
def _without_docstrings(source: str) -> str:
    """The module's syntax tree without docstrings: what the interpreter runs, minus prose."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(body, list) and body and isinstance(body[0], ast.Expr)
                and isinstance(getattr(body[0], "value", None), ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree)


@functools.lru_cache(maxsize=1)  # the files do not change during a run (0.2 s per computation)
def code_digest() -> str:
    """Hash of the code that produces an artifact's numbers (:data:`RESULT_CODE`): editing a help
    text, a docstring or a comment does not invalidate artifacts, changing what runs does."""
    h = hashlib.sha256()
    for p in sorted(q for pattern in RESULT_CODE for q in ROOT.glob(pattern)):
        h.update(str(p.relative_to(ROOT)).encode())
        text = p.read_text()
        h.update((_without_docstrings(text) if p.suffix == ".py" else text).encode())
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


def _digest(d: dict) -> str:
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()


def stage_keys(spec: Spec) -> dict:
    """The hashes of each stage's inputs: ``mesh`` (the geometry), ``factor`` (+ material, regions,
    element) and ``artifact`` (+ storage; the artifact's ``input_hash``)."""
    d = asdict(spec)
    d["units"] = d["units"] or "m"  # not given = metres (the same artifact as --units m)
    for key in ("surface", "volume", "segmentation"):
        if d[key]:
            d[key] = {"sha256": file_digest(d[key])}
    d["inclusions"] = [{"sha256": file_digest(q)} for q in d.get("inclusions") or ()]
    versions = library_versions()
    code = code_digest()
    geometry = ("model", "params", "surface", "volume", "units", "edge_length") + (
        ("segmentation", "label") if d["segmentation"] else ()) + (("repair",) if d["repair"] else ()) + (
        ("shell",) if d.get("shell") is not None else ()) + (("inclusions",) if d["inclusions"] else ())
    # (the optional keys only when used: earlier artifacts keep their keys)
    mesh = _digest({k: d[k] for k in geometry}
                   | {"code": code, "libraries": {k: versions[k] for k in ("gmsh", "scikit-fem")}})
    factor = _digest({"mesh": mesh} | {k: d[k] for k in ("fixed", "contact", "E", "nu", "r_max", "element", "reactions")}
                     | ({"materials": d["materials"]} if d.get("materials") else {}))
    return {"mesh": mesh, "factor": factor, "artifact": artifact_key(spec, factor)}


def artifact_key(spec: Spec, factor: str) -> str:
    """The artifact's input hash from its factor's key and how Ξ is stored (:func:`stage_keys`)."""
    return _digest({"factor": factor, "dtype": spec.dtype, "format_version": FORMAT_VERSION}
                   | ({"compress": spec.compress} if spec.compress else {})
                   | ({"display": bool(spec.display)} if spec.surface or spec.segmentation else {}))


def input_hash(spec: Spec) -> str:
    """SHA-256 of every input: geometry, parameters, code and the libraries that shape the mesh."""
    return stage_keys(spec)["artifact"]


# ------------------------------------------------------------------------------- validation
def model_parameters(name: str) -> dict:
    """The keyword parameters a registered model's builder takes (name -> default)."""
    import functools

    from pmask.pipeline.models import get_model

    builder = get_model(name)
    bound = builder.keywords if isinstance(builder, functools.partial) else {}
    sig = inspect.signature(builder.func if isinstance(builder, functools.partial) else builder)
    return {k: p.default for k, p in sig.parameters.items() if k not in bound}


def validate(spec: Spec, out: Path) -> None:
    """Everything that can be checked before any work, each with one line that says what to change."""
    from pmask.precompute import elasticity, elements, selectors

    if spec.element != elements.AUTO:
        elements.get_element(spec.element)
    if spec.dtype not in ("float64", "float32"):
        raise InputError(f"dtype must be float64 or float32, got {spec.dtype!r}")
    if spec.units is not None and spec.units not in UNITS:
        raise InputError(f"unknown length unit '{spec.units}'; use one of {', '.join(UNITS)}")
    for key in ("surface", "volume", "segmentation"):
        p = getattr(spec, key)
        if p and not Path(p).is_file():
            raise InputError(f"--{key} {p}: no such file")
    if sum(bool(x) for x in (spec.surface, spec.volume, spec.segmentation)) > 1:
        raise InputError("give one of --surface, --volume and --segmentation")
    if spec.segmentation and (spec.label is None or isinstance(spec.label, bool) or not isinstance(spec.label, int)):
        raise InputError("--segmentation needs --label N (the label value of the organ in the image)")
    if spec.repair not in (None, False, True, "meshfix", "voxel", "auto"):
        raise InputError(f"--repair {spec.repair}: use meshfix, voxel or auto")
    if spec.repair and not (spec.surface or spec.segmentation):
        raise InputError("--repair applies to --surface and --segmentation inputs")
    if spec.inclusions:
        if not spec.surface:
            raise InputError("--inclusion applies to --surface inputs (a --volume mesh carries its regions as physical "
                             "volumes: name them in --materials)")
        for q in spec.inclusions:
            if not Path(q).is_file():
                raise InputError(f"--inclusion {q}: no such file")
        if spec.repair:
            raise InputError("--inclusion with --repair: mend the outer surface first (the repaired surface is not "
                             "kept for the next run), then give it with --inclusion")
    if spec.shell is not None and (isinstance(spec.shell, bool) or not isinstance(spec.shell, int) or spec.shell < 1
                                   or not spec.surface):
        raise InputError("--shell K applies to --surface inputs and counts from 1 (the largest shell by area)")
    if spec.compress is not None:
        from pmask.precompute import compress

        compress.check_tolerance(spec.compress)
        if spec.worker_memory is not None:
            compress.parse_memory(spec.worker_memory)
        if spec.workers is not None and (isinstance(spec.workers, bool) or not isinstance(spec.workers, int)
                                         or spec.workers < 1):
            raise InputError(f"--workers must be a whole number >= 1, got {spec.workers!r}")
        if spec.scheduler:  # reachable now, not after an hour of meshing and factorising
            compress.connect(spec.scheduler, None, None).close()
    elif spec.scheduler or spec.workers or spec.worker_memory:
        raise InputError("--scheduler, --workers and --worker-memory apply to --compress (the tiled route)")
    if spec.segmentation and spec.edge_length is None:
        raise InputError("--segmentation needs --edge-length (target edge length in the image's units)")
    if not (spec.surface or spec.volume or spec.segmentation):
        allowed = model_parameters(spec.model)
        unknown = sorted(set(spec.params) - set(allowed))
        if unknown:
            flags = ", ".join("--size" if k == "size" else f"--param {k}=..." for k in unknown)
            raise InputError(f"model {spec.model} has no parameter {', '.join(unknown)} ({flags}); its parameters: "
                             + (", ".join(f"{k} (default {v!r})" for k, v in allowed.items()) or "none"))
        for k, v in spec.params.items():
            default = allowed[k]
            if isinstance(default, (int, float)) and not isinstance(default, bool) and not isinstance(v, (int, float)):
                raise InputError(f"model {spec.model}: parameter {k} must be a number, got {v!r}")
    if spec.surface and spec.edge_length is None:
        raise InputError("--surface needs --edge-length (target edge length in the file's units)")
    for flag, value in (("--mesh-timeout", spec.mesh_timeout), ("--solve-timeout", spec.solve_timeout)):
        if not (np.isfinite(value) and value > 0):
            raise InputError(f"{flag} must be a number of seconds > 0, got {value}")
    if spec.edge_length is not None and not (np.isfinite(spec.edge_length) and spec.edge_length > 0):
        raise InputError(f"--edge-length must be a finite length > 0, got {spec.edge_length}")
    if spec.r_max is not None and not (np.isfinite(spec.r_max) and spec.r_max > 0):
        raise InputError(f"--r-max must be a finite length > 0, got {spec.r_max}")
    if spec.E is not None or spec.nu is not None:
        elasticity.check_material(spec.E if spec.E is not None else 1.0, spec.nu if spec.nu is not None else 0.3)
    if spec.nu is not None:  # a locking element is refused (or warned about) before any meshing
        _warn_once(elements.get_element(elements.element_name(spec.element, spec.nu)).locking(spec.nu))
    for sel in (spec.fixed, spec.contact):
        if sel is not None:
            selectors.parse(sel)
    if spec.materials:  # the text's syntax and each material before any meshing (the names against the mesh later)
        from pmask.precompute.materials import parse_materials

        parse_materials(spec.materials)
    out = Path(out)
    if out.is_dir():
        raise OutputError(f"--out {out} is a folder; give the artifact's file name, e.g. {out / spec.model}.h5")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out.parent, prefix=".pmask-write-test-"):
            pass
    except OSError as exc:
        raise OutputError(f"cannot write to {out.parent} ({exc.strerror or exc}); "
                          "choose a writable folder with --out") from None


# ------------------------------------------------------------------------------- stages
def check_selectors_before_meshing(spec: Spec, points: np.ndarray, triangles: np.ndarray) -> None:
    """A support or contact selector that matches none (or, for the support, all) of a user's surface is
    refused before the minutes of meshing (#25): tested on its vertices, edge midpoints and triangle
    centroids (in the file's units, as the selectors are)."""
    from pmask.precompute import selectors
    from pmask.precompute.regions import RegionError

    T = np.asarray(triangles, np.int64)
    samples = np.vstack([points, points[T].mean(axis=1), 0.5 * (points[T[:, 0]] + points[T[:, 1]]),
                         0.5 * (points[T[:, 1]] + points[T[:, 2]]), 0.5 * (points[T[:, 2]] + points[T[:, 0]])])
    for what, sel in (("fixed-region", spec.fixed), ("contact-region", spec.contact)):
        if not sel or "group:" in sel:
            continue
        hit = selectors.select(sel, samples)
        if not hit.any():
            lo, hi = np.round(points.min(axis=0), 4).tolist(), np.round(points.max(axis=0), 4).tolist()
            raise RegionError(f"the {what} selector '{sel}' matches no point of the input surface (its box is "
                              f"{lo} to {hi} in the file's units); choose a region that touches it")
        if what == "fixed-region" and hit.all():
            raise RegionError(f"the fixed-region selector '{sel}' matches the whole input surface, so nothing is "
                              "free to touch; choose a smaller support region")


def segmentation_inclusions(spec: Spec) -> list[int]:
    """A multi-label segmentation's inner labels: the ``--materials`` entries whose name is a label value
    (``--materials 2:5e4:0.45`` makes label 2, inside ``--label``'s organ, a region of its own)."""
    if not (spec.segmentation and spec.materials):
        return []
    from pmask.precompute.materials import parse_materials

    return [int(name) for name in parse_materials(spec.materials) if name.isdigit() and int(name) != spec.label]


def mesh_stage(spec: Spec) -> ModelMesh:
    """Stage 1: the volume mesh (metres) and its named groups, from a model or a user's file."""
    from pmask.pipeline.models import get_model
    from pmask.precompute import meshing

    if spec.segmentation:
        from pmask.precompute.segmentation import label_surface

        inner = segmentation_inclusions(spec)
        pts, tris, report = label_surface(Path(spec.segmentation), spec.label, spec.units, with_labels=inner)
        check_selectors_before_meshing(spec, pts, tris)
        import meshio

        folder = Path(tempfile.mkdtemp(prefix="pmask-label-"))
        ply = folder / f"label{spec.label}.ply"  # the --surface route's input
        meshio.write_points_cells(ply, pts, [("triangle", tris.astype(np.int32))])
        inclusions = []
        for lab in inner:  # a multi-label segmentation: each inner label's surface an inclusion of its own
            p, t, _ = label_surface(Path(spec.segmentation), lab, spec.units)
            inclusions.append(folder / f"label{lab}.ply")
            meshio.write_points_cells(inclusions[-1], p, [("triangle", t.astype(np.int32))])
        try:
            points, tets, change, regions = meshing.remesh_bounded(
                ply, edge_length=spec.edge_length * spec.scale, scale=spec.scale, units_given=True,
                timeout=spec.mesh_timeout, repair=spec.repair, xi_of_all=spec.contact is None,
                inclusions=inclusions, with_regions=True, region_names=[str(lab) for lab in inner],
                angle_deg=180.0)  # an organ has no creases a voxel grid can show: its sharp edges are the voxels'
                                  # (a thick-slice liver kept 9,317 of them as features and gmsh ran out its 600 s)
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        return ModelMesh(points=points, tets=tets, fixed=spec.fixed or "", regions=regions,
                         info={"source": Path(spec.segmentation).name, "segmentation": report, "remesh": change}
                         | ({"labels": [spec.label, *inner]} if inner else {}))
    if spec.surface:
        read = None
        with contextlib.suppress(meshing.MeshError):  # an unreadable file is the remesh's to report
            read = meshing.read_surface_file(Path(spec.surface))
        if read is not None:
            pts, tris = read
            # the unit first: a file in another unit misses every selector, and the unit is the cause
            meshing.check_extent(pts * spec.scale, spec.units is not None, spec.surface, spec.edge_length * spec.scale)
            check_selectors_before_meshing(spec, pts, tris)
        points, tets, change, regions = meshing.remesh_bounded(
            Path(spec.surface), edge_length=spec.edge_length * spec.scale, scale=spec.scale,
            units_given=spec.units is not None, timeout=spec.mesh_timeout, repair=spec.repair,
            xi_of_all=spec.contact is None, shell=spec.shell, inclusions=[Path(q) for q in spec.inclusions],
            with_regions=True)
        return ModelMesh(points=points, tets=tets, fixed=spec.fixed or "", regions=regions,
                         info={"source": Path(spec.surface).name, "remesh": change}
                         | ({"inclusions": [Path(q).name for q in spec.inclusions]} if spec.inclusions else {}))
    if spec.volume and spec.volume.endswith(".npz"):  # a stored ModelMesh (reference meshes)
        return load_model_mesh(spec.volume)
    if spec.volume:
        points, tets, groups, regions = meshing.read_volume(Path(spec.volume), scale=spec.scale, with_regions=True)
        meshing.check_extent(points, spec.units is not None, spec.volume)
        return ModelMesh(points=points, tets=tets, fixed=spec.fixed or "", groups=groups, regions=regions,
                         info={"source": Path(spec.volume).name})
    return get_model(spec.model)(**spec.params)


def support_stage(spec: Spec, mesh: ModelMesh) -> ModelMesh:
    """Stage 1b: fit the mesh to a geometric support selector (:func:`pmask.precompute.supports.conform`),
    so the fixed area is the selected part of the surface on every mesh, not whatever whole triangles
    the vertices happen to give.  Physical groups (``group:``) are whole facets already."""

    from pmask.precompute import supports

    selector = spec.fixed or mesh.fixed
    if not selector or not supports.conformable(selector):
        return mesh
    points, rim, report = supports.conform(mesh.points, mesh.tets, selector, spec.scale)
    if report["unresolved"]:
        log.info("support '%s': %d of %d crossing edges could not be fitted without flattening a tetrahedron; "
                 "they keep vertex membership", selector, report["unresolved"], report["crossing_edges"])
    return replace(mesh, points=points, groups={**mesh.groups, supports.RIM: rim},
                   info={**mesh.info, "support_fit": report})


#: a user's support outside this share of the surface area gets a warning (see _check_support_share)
SUPPORT_SHARE = (0.02, 0.5)


def _check_support_share(share: float, n_fixed: int, selector: str, units: str | None) -> None:
    """Warn about supports that are probably not what was meant: most of the surface (a selector read in
    the wrong units: ``z<-0.025`` on a mm file fixes half the body), or a sliver (59 vertices at a liver's
    tip gave stiffness 0.02-0.57x Boussinesq: a body held by so little swings about it)."""
    if share > SUPPORT_SHARE[1]:
        log.warning("the support '%s' covers %.0f %% of the surface; selectors are read in the input's units (%s): "
                    "is that the region you meant?", selector, 100 * share, units or "m")
    elif share < SUPPORT_SHARE[0]:
        log.warning("the support '%s' is only %.2f %% of the surface (%d vertices): a body held by so little "
                    "is soft against anything but a local push; widen it unless that is what you model",
                    selector, 100 * share, n_fixed)


def surface_stage(spec: Spec, mesh: ModelMesh) -> SimulationSurface:
    """Stage 2: the boundary surface, its vertex areas, and the fixed, free and contact regions."""
    from pmask.precompute import regions, selectors, supports, surface
    from pmask.runtime.geometry import mean_edge_length, triangle_areas, vertex_areas

    vertices, triangles = surface.boundary_surface(mesh.points, mesh.tets)
    spoints = mesh.points[vertices]
    areas = vertex_areas(spoints, triangles)
    fixed_sel = spec.fixed or mesh.fixed
    if not fixed_sel:
        raise regions.RegionError("no fixed region given: use --fixed SELECTOR (e.g. 'z<-0.9' or 'group:NAME')")
    contact_sel = spec.contact if spec.contact is not None else mesh.contact
    # a hollow body: its cavities' walls are groups of their own, and the geometric selectors and the default
    # contact region are the outer surface's (a probe touches the organ from outside; z<-8 is where it rests)
    walls = surface.cavity_walls(spoints, triangles)
    wall = np.any(walls, axis=0) if walls else np.zeros(len(vertices), bool)
    groups, outer = dict(mesh.groups), np.ones(len(mesh.points), bool)
    outer[vertices[wall]] = False
    for name, w in zip(surface.cavity_names(len(walls)), walls):
        groups[name] = np.zeros(len(mesh.points), bool)
        groups[name][vertices[w]] = True
    fixed_mask = selectors.select(fixed_sel, mesh.points / spec.scale, groups, outer if walls else None)[vertices]
    if supports.conformable(fixed_sel):  # held by area: the vertices of the facets inside the support
        fixed_mask |= mesh.groups.get(supports.RIM, np.zeros(len(mesh.points), bool))[vertices] & ~wall
        held = supports.fixed_facets(fixed_mask, triangles)
        fixed_mask = np.zeros(len(vertices), bool)
        fixed_mask[triangles[held]] = True
    contact_mask = (selectors.select(contact_sel, mesh.points / spec.scale, groups, outer if walls else None)[vertices]
                    if contact_sel else None)
    if spec.r_max is not None:
        r_max = spec.r_max * spec.scale
    elif contact_mask is None and not spec.compress:
        r_max = float(np.linalg.norm(spoints.max(axis=0) - spoints.min(axis=0)))  # every free vertex is in Ξ
    else:
        r_max = mesh.info.get("r_max_m", 4.0 * mean_edge_length(spoints, triangles))
    reg = regions.surface_regions(spoints, fixed_mask, contact_mask, r_max,
                                  fixed_selector=fixed_sel, contact_selector=contact_sel or "")
    if walls:  # a cavity's wall is in Ξ only where a selector names it (masks stay on the side they touch)
        reg = regions.without(reg, wall & ~(contact_mask if contact_mask is not None else np.zeros_like(wall)))
    held = supports.fixed_facets(np.isin(np.arange(len(vertices)), reg.fixed), triangles)
    facet_areas = triangle_areas(spoints, triangles)
    held_area = float(facet_areas[held].sum())
    log.info("support '%s': %d vertices, %d facets, %.6g m² (%.2f %% of the surface)", fixed_sel, len(reg.fixed),
             int(held.sum()), held_area, 100 * held_area / facet_areas.sum())
    if spec.surface or spec.segmentation or (spec.volume and not spec.volume.endswith(".npz")):  # a user's selector
        _check_support_share(held_area / float(facet_areas.sum()), len(reg.fixed), fixed_sel, spec.units)
    return SimulationSurface(vertices, triangles, areas, reg, float(r_max), fixed_sel, contact_sel or "", held,
                             tuple(int(w.sum()) for w in walls))


@functools.lru_cache(maxsize=16)
def _warn_once(message: str | None) -> None:
    if message:
        log.warning(message)


def material(spec: Spec, mesh: ModelMesh) -> tuple[float, float]:
    from pmask.precompute.elasticity import check_material

    from pmask.precompute.elements import get_element

    E = spec.E if spec.E is not None else mesh.material["E"]
    nu = spec.nu if spec.nu is not None else mesh.material["nu"]
    check_material(E, nu)
    _warn_once(get_element(element_name(spec, mesh)).locking(nu))
    return float(E), float(nu)


def element_materials(spec: Spec, mesh: ModelMesh):
    """Materials by region (:mod:`pmask.precompute.materials`): (E, nu, region label, report) per tetrahedron
    from ``--materials`` or the model's ``material["regions"]``, or None for one material."""
    from pmask.precompute import materials

    assigned = materials.parse_materials(spec.materials) if spec.materials else {
        k: tuple(v) for k, v in mesh.material.get("regions", {}).items()}
    if not assigned:
        return None
    base = (spec.E if spec.E is not None else mesh.material["E"], spec.nu if spec.nu is not None else mesh.material["nu"])
    return materials.per_element(mesh.regions, len(mesh.tets), base, assigned)


def _region_report(regions, mesh: ModelMesh) -> dict:
    """What the artifact records of materials by region: each region's material, tetrahedra and volume, and
    every tetrahedron's region (-1: the body's material)."""
    from pmask.precompute.meshing import signed_volumes

    _, _, label, report = regions
    vol = np.abs(signed_volumes(mesh.points, mesh.tets))
    for k, r in enumerate(report):
        r["volume_m3"] = float(vol[label == k].sum())
    return {"regions": report, "label": label}


def element_name(spec: Spec, mesh: ModelMesh) -> str:
    """The element this run uses: ``spec.element``, or for ``auto`` the one the material asks for."""
    from pmask.precompute.elements import element_name as resolve

    nu = spec.nu if spec.nu is not None else mesh.material["nu"]
    regions = element_materials(spec, mesh) if (spec.materials or mesh.material.get("regions")) else None
    if regions is not None:  # the element for the most nearly incompressible region
        nu = max(float(nu), float(regions[1].max()))
    return resolve(spec.element, float(nu))


def check_memory(element, n_volume_vertices: int, n_contact: int, spec: Spec | None = None) -> dict:
    """Refuse, before any heavy work, a job whose Green's-function stage cannot fit in this machine's
    memory (Ξ, the sparse factor and the working arrays: ``element.memory_estimate``).  The compressed
    route (``spec.compress``) is checked as its tiled form, which never holds the dense Ξ (where the dense Ξ fits
    it is compressed from it instead: :func:`compress_from_dense`): the factor and the W sweep on one worker
    (:func:`pmask.precompute.compress.factor_phase_bytes`),
    then, once they are gone, on each local worker one tile (:func:`pmask.precompute.compress.tile_bytes`) with a
    chunk of W (:data:`pmask.precompute.compress.READ_BYTES` at most; P2's tiles also a chunk of W_B): the larger
    of the two phases, and nothing of the factor on this machine with ``--scheduler`` (the client never holds
    it).  The later phases are checked where their sizes are known (the W sweep's from the factor's tree and
    its worker's limit, the tiles' from the workers' limits, the assembly's from the finished tiles:
    :func:`pmask.precompute.compress.check_phase_memory`)."""
    from pmask.precompute import greens

    need = element.memory_estimate(n_volume_vertices, n_contact)
    if spec is not None and spec.compress:
        from pmask.precompute import compress

        local = 0 if spec.scheduler else (spec.workers or os.cpu_count() or 1)
        panel = compress.panel_size(n_contact)
        # the factor's worker, then the tiles (they sum W's products); the sweep's own check, from the factor's
        # tree, runs before it starts
        sweep = compress.factor_phase_bytes(need["factor"]) if local else 0.0
        chunks = compress.READ_BYTES * (1 if element.name == "P1" else 2)
        need["total"] = max(sweep, local * compress.tile_bytes(chunks, n_contact, panel, 1))
        avail = greens.available_memory()
        if avail is not None and need["total"] > avail:
            raise ResourceError(
                f"the sparse factor (~{_bytes(need['factor'])}) and {local} local Dask workers, each with one tile "
                f"({element.name}), "
                f"need ~{_bytes(need['total'])}, more than the {_bytes(avail)} this machine has "
                "available: use fewer workers (--workers), a cluster (--scheduler) or a coarser mesh")
        return need
    if greens.cholmod_backend() != "native":
        need["total"] += 0.9 * need["Xi"]  # the pip-only route permutes a copy
    avail = greens.available_memory()
    if avail is not None and need["total"] > avail:
        raise ResourceError(
            f"Ξ of {n_contact} contact vertices is a dense {3 * n_contact} x {3 * n_contact} matrix "
            f"({_bytes(need['Xi'])} in float64); with the sparse factor (~{_bytes(need['factor'])}) the "
            f"{element.name} Green's functions need ~{_bytes(need['total'])}, more than the {_bytes(avail)} this "
            "machine has available: restrict the region a probe can touch (--contact SELECTOR) or coarsen the "
            "mesh (--size, --edge-length)")
    return need


def compress_from_dense(spec: Spec, element, n_volume_vertices: int, n_contact: int) -> bool:
    """Whether ``--compress`` computes the dense Ξ first and compresses its blocks in this process
    (:class:`pmask.precompute.compress.DenseSource`) rather than tiling it from W on Dask workers: where the dense
    route fits in this machine's memory with one tile's working arrays beside it (:func:`check_memory` without
    ``--compress``, :func:`pmask.precompute.compress.tile_bytes`) and no Dask option (``--scheduler``,
    ``--workers``, ``--worker-memory``) asks for the tiled route.  The same blocks to round-off, within the same
    tolerance (tested); the dense route's native selected inversion and no W sweep, no workers to start: the bench
    page's whole runs compare the two routes with the dense one where all three fit.  Above that size the tiles
    hold a bounded share of Ξ at a time (the large-organs guide)."""
    if not spec.compress or spec.scheduler or spec.workers or spec.worker_memory:
        return False
    from pmask.precompute import compress, greens

    try:
        need = check_memory(element, n_volume_vertices, n_contact, replace(spec, compress=None))
    except ResourceError:
        return False
    avail = greens.available_memory()
    # a tile's formed rows, a group's gathered rows and the tile's outputs: each at most a panel (3n x 3·panel)
    one = compress.tile_bytes(0.0, n_contact, compress.panel_size(n_contact), copies=3)
    return avail is None or need["total"] + one <= avail


def factor_stage(spec: Spec, mesh: ModelMesh, surf: SimulationSurface):
    """Stage 3: assemble the element's stiffness and load, factorise K_FF.  Returns (factor, timings)."""
    from pmask.precompute import elements, greens

    element = elements.get_element(element_name(spec, mesh))
    E, nu = material(spec, mesh)
    regions = element_materials(spec, mesh)
    if regions is not None:  # a material per tetrahedron (materials by region)
        E, nu = regions[0], regions[1]
    t0 = time.perf_counter()
    d = element.discretise(mesh.points, mesh.tets)
    K = element.stiffness(d, E, nu)
    contact = surf.vertices[surf.regions.contact]
    B, scale = element.load(d, surf.vertices[surf.triangles], contact, surf.areas[surf.regions.contact])
    dirichlet = elements.dofs(element.dirichlet_nodes(d, surf.vertices[surf.regions.fixed], surf.held_facets()))
    t_assemble = time.perf_counter() - t0
    t0 = time.perf_counter()
    factor = greens.factorise(K, dirichlet, elements.observed_dofs(contact), B, scale=scale,
                              graph_elements=d.connectivity, reactions=spec.reactions)
    factor.stats["element"] = element.name
    return factor, {"assemble": t_assemble, "factor": time.perf_counter() - t0}


def greens_stage(spec: Spec, mesh: ModelMesh, surf: SimulationSurface, factor, *, work: Path | None = None, key: str = "",
                 from_dense: bool = False):
    """Stage 4: Ξ and the support reactions per fixed vertex from the factor.  With ``spec.compress``: Ξ's
    compressed arrays (tiles on Dask, their store in ``work``; ``from_dense``: from the dense Ξ, which fits:
    :func:`compress_from_dense`), no reactions."""
    from pmask.precompute import elements, greens

    if spec.compress:
        from pmask.precompute import compress

        if surf.r_max >= float(np.linalg.norm(np.ptp(mesh.points, axis=0))):
            log.warning("r_max %.3g m spans the body: every pair of vertices is near field and nothing is compressed; "
                        "give --r-max, the largest probe tip radius", surf.r_max)
        limit = compress.parse_memory(spec.worker_memory) if spec.worker_memory else None
        arrays, stats = compress.compressed_greens(
            factor, mesh.points[surf.vertices[surf.regions.contact]], surf.r_max, tol=spec.compress,
            store=Path(work) / f"tiles-{key[:16]}.h5", key=key, scheduler=spec.scheduler, workers=spec.workers,
            memory_limit=limit, dtype=np.dtype(spec.dtype),
            dense=(lambda: greens.greens_functions(factor)[0]) if from_dense else None)
        factor.stats["compress"] = stats
        return arrays, None

    Xi, R = greens.greens_functions(factor)
    if R is None:
        return Xi, None
    element = elements.get_element(element_name(spec, mesh))
    d = element.discretise(mesh.points, mesh.tets) if element.name != "P1" else None
    return Xi, element.lump_reactions(d, surf.vertices[surf.regions.fixed], surf.held_facets(), R)


def display_stage(spec: Spec, mesh: ModelMesh, surf: SimulationSurface) -> dict | None:
    """Stage 4b: the display surface (:mod:`pmask.precompute.display`): the ``--surface`` file as given (the
    ``--shell`` chosen), or a label image's smoothed surface, embedded in the simulation surface; None for
    models, ``--volume`` meshes and ``--no-display``."""
    from pmask.precompute import display, meshing

    if not spec.display or not (spec.surface or spec.segmentation):
        return None
    if spec.segmentation:
        from pmask.precompute.segmentation import label_surface

        pts, tris, _ = label_surface(Path(spec.segmentation), spec.label, spec.units,
                                     with_labels=segmentation_inclusions(spec))
    else:
        pts, tris = meshing.read_surface_file(Path(spec.surface))
        if spec.shell is not None:
            pts, tris = meshing.select_shell(pts, tris, spec.shell, spec.surface)
    return display.display_surface(pts * spec.scale, tris, mesh.points[surf.vertices], surf.triangles,
                                   spec.surface or spec.segmentation)


def write_stage(spec: Spec, out: Path, mesh: ModelMesh, surf: SimulationSurface, Xi, reactions, *, keys, factor_stats,
                timings, resumed, display: dict | None = None) -> None:
    """Stage 5: the artifact, written atomically with its checksums and provenance."""
    from pmask.precompute.writer import write_artifact

    E, nu = material(spec, mesh)
    regions = element_materials(spec, mesh)
    meta = {
        "model": spec.model, "input_hash": keys["artifact"], "E": E, "nu": nu, "r_max": surf.r_max,
        "materials": None if regions is None else _region_report(regions, mesh),
        "tolerance": spec.compress,
        "fixed_selector": surf.fixed_selector, "contact_selector": surf.contact_selector, "element": element_name(spec, mesh),
        "parameters": {**asdict(spec), "model_info": mesh.info},
        "provenance": {"libraries": library_versions(), "code_sha256": code_digest(), "stage_keys": keys,
                       "created_unix": time.time(), "host": platform.node(), "resumed_stages": resumed,
                       "factor": factor_stats},
        "timings": timings,
    }
    write_artifact(out, meta=meta, volume_points=mesh.points, tets=mesh.tets, surface_vertices=surf.vertices,
                   triangles=surf.triangles, areas=surf.areas, regions=surf.regions, Xi=Xi, reactions=reactions,
                   dtype=np.dtype(spec.dtype), display=display)


# ------------------------------------------------------------------------------- orchestration
def _bytes(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


class _Stages:
    """Timings, progress and the work folder of one run."""

    def __init__(self, spec: Spec, out: Path, keys: dict, progress: bool):
        self.work = out.parent / ".work" / out.stem
        self.keys = keys
        self.timings: dict[str, float] = {}
        self.resumed: list[str] = []
        self.bar = None
        if progress:
            from tqdm import tqdm

            self.bar = tqdm(total=5, desc=f"{spec.model}: mesh", file=sys.stderr, leave=False,
                            bar_format="{desc:<40} {bar} {n_fmt}/{total_fmt} [{elapsed}]")

    def checkpoint(self, stage: str) -> Path:
        return self.work / f"{stage}-{self.keys[stage][:16]}.npz"

    @contextlib.contextmanager
    def timed(self, name: str, next_label: str | None = None):
        interrupt.check()  # a Ctrl-C a library swallowed ends the run here (pmask.interrupt)
        t0 = time.perf_counter()
        yield
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
        if self.bar is not None:
            self.bar.update()
            if next_label:
                self.bar.set_description(next_label)

    def close(self, success: bool) -> None:
        if self.bar is not None:
            self.bar.close()
        if success:
            shutil.rmtree(self.work, ignore_errors=True)
        else:  # keep only checkpoints a corrected run can reuse: the finished stages'
            for p in self.work.glob("*"):
                if p.name.startswith("."):
                    p.unlink(missing_ok=True)
            kept = sorted([*self.work.glob("*.npz"), *self.work.glob("tiles-*.h5"), *self.work.glob("W-tiles-*.bin")]
                          ) if self.work.exists() else []
            if kept:
                log.warning("kept the finished stages (%s) in %s, %s: the next run with the same geometry reuses "
                            "them; delete the folder to free the space", ", ".join(dict.fromkeys(p.name.split("-")[0] for p in kept)),
                            self.work, _bytes(sum(p.stat().st_size for p in kept)))
        for folder in (self.work, self.work.parent):  # when empty
            with contextlib.suppress(OSError):
                folder.rmdir()


#: the far-field tolerance the compressed route takes when it is chosen for a dense Ξ that does not fit
AUTO_COMPRESS = 1e-4


def auto_compress(auto: Spec, mesh: ModelMesh, element, dense: ResourceError) -> SimulationSurface:
    """The compressed route in place of a dense Ξ this machine cannot hold (``dense``, check_memory's refusal):
    its surface (the masks' r_max is the model's, not the whole body) after its own memory check, with a
    warning that says so; the dense refusal and the compressed one in one line when neither fits.  Where
    both fit the dense route runs: it is exact everywhere, not only within r_max, and coupled contacts keep
    the native step (a ζ table), while the compressed route saves little time at that size (the bench's
    whole runs)."""
    surf = surface_stage(auto, mesh)
    try:
        check_memory(element, len(mesh.points), len(surf.regions.contact), auto)
    except ResourceError as exc:
        raise ResourceError(f"{dense}; stored compressed (--compress) it would not fit either: {exc}") from None
    log.warning("the dense Ξ would not fit in this machine's memory (%s); storing it compressed instead (--compress "
                "%g: K_i and pairs within r_max %.3g %s exact, the far field within the tolerance)",
                str(dense).split(";")[0].split(", more than")[0], auto.compress, surf.r_max / auto.scale,
                auto.units or "m")
    return surf


def _segmentation_units(spec: Spec) -> Spec:
    """A label image's lengths are in its header's unit: --edge-length, selectors and --r-max follow it."""
    if not spec.segmentation or spec.units is not None:
        return spec

    from pmask.precompute.segmentation import read_label_image

    unit = read_label_image(Path(spec.segmentation))[2]
    return replace(spec, units=unit) if unit in UNITS else spec


def run(spec: Spec, out: Path, *, force: bool = False, progress: bool = False) -> dict:
    """Run the precompute for ``spec`` into ``out``; return a summary dict.

    ``progress`` shows a bar over the stages on stderr (the CLI turns it on for a terminal).
    """
    from pmask.precompute import elements, greens, native

    out = Path(out)
    validate(spec, out)
    spec = _segmentation_units(spec)
    keys = stage_keys(spec)
    # without --compress, the compressed route is taken where the dense Ξ does not fit (auto_compress)
    auto = replace(spec, compress=AUTO_COMPRESS) if spec.compress is None else None
    auto_keys = dict(keys, artifact=artifact_key(auto, keys["factor"])) if auto is not None else None
    stored = stored_input_hash(out) if out.exists() and not force else None
    if stored is not None and stored in (keys["artifact"], auto_keys and auto_keys["artifact"]):
        log.debug("%s is up to date (input hash %s)", out, stored[:12])
        return {"up_to_date": True, "artifact": str(out), "input_hash": stored}
    st = _Stages(spec, out, keys, progress)
    st.work.mkdir(parents=True, exist_ok=True)

    def tile_store(k):  # the compressed route's tile store and W's (its name)
        return st.work / f"tiles-{k['artifact'][:16]}.h5"

    tiles = tile_store(keys)
    reusable = (st.checkpoint("mesh"), st.checkpoint("factor"), *(
        t for t in {tiles, *([tile_store(auto_keys)] if auto_keys else [])}
        for t in (t, t.with_name(f"W-{t.stem}.bin"), t.with_name(f"W-{t.stem}.index.npz"))))
    for stale in [*st.work.glob("*.npz"), *st.work.glob("tiles-*.h5"), *st.work.glob("W-tiles-*")]:
        if stale not in reusable:  # other inputs': not reusable by this run
            stale.unlink(missing_ok=True)
    ok = False
    solve = contextlib.ExitStack()
    try:
        with st.timed("mesh", f"{spec.model}: regions"):
            ck = st.checkpoint("mesh")
            if ck.exists():
                mesh = load_model_mesh(ck)
                st.resumed.append("mesh")
            else:
                mesh = mesh_stage(spec)
                save_model_mesh(ck, mesh)
            mesh = support_stage(spec, mesh)
        with st.timed("regions", f"{spec.model}: assemble + factorise"):
            surf = surface_stage(spec, mesh)
            element = elements.get_element(element_name(spec, mesh))
            try:
                check_memory(element, len(mesh.points), len(surf.regions.contact), spec)
            except ResourceError as dense:
                if auto is None:
                    raise
                surf = auto_compress(auto, mesh, element, dense)
                spec, keys = auto, auto_keys
                st.keys, tiles = keys, tile_store(keys)
        solve.enter_context(native.budget(spec.solve_timeout))  # factorisation and Green's functions together
        ck = st.checkpoint("factor")
        factor, saving = None, None
        from_dense = compress_from_dense(spec, element, len(mesh.points), len(surf.regions.contact))
        on_worker = bool(spec.compress) and not from_dense
        if on_worker:  # assembled, factorised and swept on a Dask worker (#27): the client holds neither
            from pmask.precompute import compress

            need = element.memory_estimate(len(mesh.points), len(surf.regions.contact))["factor"]
            factor = compress.FactorJob(functools.partial(factor_stage, spec, mesh, surf), ck, spec.solve_timeout,
                               element.name, compress.factor_phase_bytes(need))
            if st.bar is not None:
                st.bar.update()
        elif ck.exists():
            t0 = time.perf_counter()
            factor = greens.load_checkpoint(ck)  # None when damaged on disk: start over
            if factor is not None:
                st.resumed.append("factor")
                st.timings.update({"assemble": 0.0, "factor": time.perf_counter() - t0})
                if st.bar is not None:
                    st.bar.update()
        if factor is None:
            factor, t = factor_stage(spec, mesh, surf)
            st.timings.update(t)
            saving = Background(greens.save_checkpoint, ck, factor)  # written while the Green's functions are computed
            solve.callback(saving.wait)  # a run that fails meanwhile still lets the write finish
        with st.timed("greens", f"{spec.model}: write"):
            Xi, reactions = greens_stage(spec, mesh, surf, factor, work=st.work, key=keys["artifact"],
                                         from_dense=from_dense)
        if on_worker:  # what the worker measured, and whether it reused the checkpoint or W; the GF stage's wall
            made = {k: factor.timings[k] for k in ("assemble", "factor") if k in factor.timings}
            st.timings.update(made)  # time held the assembly and factorisation: the stages add up to the run
            st.timings["greens"] -= sum(made.values())
            st.resumed.extend(["factor"] if factor.resumed else [])
        if saving is not None:
            with st.timed("checkpoint"):  # what is left of the factor checkpoint's write (usually nothing)
                saving.join()
        with st.timed("display"):
            display = display_stage(spec, mesh, surf)
        with st.timed("write"):
            write_stage(spec, out, mesh, surf, Xi, reactions, keys=keys, factor_stats=factor.stats,
                        timings=st.timings, resumed=st.resumed, display=display)
        ok = True
    finally:
        solve.close()
        st.close(ok)
    reg = surf.regions
    return {"up_to_date": False, "artifact": str(out), "input_hash": keys["artifact"], "timings": st.timings,
            "resumed": st.resumed, "volume_vertices": len(mesh.points), "tets": len(mesh.tets),
            "surface_vertices": len(surf.vertices), "free": len(reg.free), "fixed": len(reg.fixed),
            "contact": len(reg.contact), "cavities": list(surf.cavities), "size_bytes": out.stat().st_size, "dofs": factor.stats.get("dofs"),
            "backend": factor.stats.get("backend"), "element": element_name(spec, mesh), "factor_stats": factor.stats,
            "remesh": mesh.info.get("remesh")}
