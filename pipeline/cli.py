"""``pmask`` command line (also ``python -m pmask.pipeline``).

Subcommands: ``precompute``, ``models``, ``info``, ``export``, ``export-table``, ``reference``, ``figures``, ``view``, ``inspect``.  An error the
user can fix (:class:`pmask.errors.PmaskError`) prints one line and exits with 2; anything else is a
bug in pmask and shows its traceback with a request to report it.  ``--verbose`` shows the traceback
of every error.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import traceback
from pathlib import Path

from pmask import interrupt
from pmask.errors import InputError, PmaskError

log = logging.getLogger("pmask")

#: what each extra brings (pyproject.toml), checked before a command that needs it
EXTRAS = {"precompute": ("scipy", "skfem", "gmsh", "meshio", "trimesh", "cvxopt", "tqdm"), "figures": ("matplotlib",),
          "segmentation": ("nibabel", "nrrd", "skimage", "highdicom"), "repair": ("pymeshfix",)}


def require_extra(*extras: str) -> None:
    """One line that says which extra to install, instead of an ImportError deep in a command."""
    import importlib.util

    for extra in extras:
        missing = [m for m in EXTRAS[extra] if importlib.util.find_spec(m) is None]
        if missing:
            raise InputError(f"this command needs the {extra} extra ({', '.join(missing)} not installed): "
                             f"pip install 'pmask[{extra}]'")


def _param(text: str):
    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"--param needs KEY=VALUE, got '{text}'")
    try:
        return key, float(value)
    except ValueError:
        return key, value


def add_precompute(sub) -> None:
    p = sub.add_parser("precompute", help="mesh, condense and write the Green's-function artifact",
                       description="Precompute the boundary Green's functions Ξ of a model or of your own geometry.")
    p.add_argument("model", nargs="?", default=None,
                   help="registered model (see 'pmask models'); a label when --surface/--volume is given")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--surface", help="closed triangle surface (STL, OBJ, PLY, ...), remeshed by gmsh")
    src.add_argument("--volume", help="tetrahedral mesh (.msh, .vtu, ...)")
    src.add_argument("--segmentation", help="label image (NIfTI .nii/.nii.gz, NRRD or DICOM SEG .dcm): the organ of --label "
                                            "(a DICOM SEG's segment number) becomes the surface (needs the segmentation extra)")
    p.add_argument("--label", type=int, help="with --segmentation: the organ's label value")
    p.add_argument("--repair", nargs="?", const="meshfix", choices=("meshfix", "voxel", "auto"), default=None,
                   help="repair the surface first, with a report of what changed: meshfix (the default; pymeshfix: "
                        "largest shell, holes, non-manifold parts, self-intersections; the repair extra), voxel "
                        "(rebuilt from the solid it encloses at a third of --edge-length; mends what meshfix cannot, "
                        "rounds features below a voxel; the segmentation extra) or auto (as it is, then meshfix if it "
                        "keeps 95 %% of the area, then voxel, then meshfix whatever it keeps; reports the route and "
                        "the distance to the input; both extras)")
    p.add_argument("--inclusion", action="append", default=[], metavar="FILE",
                   help="with --surface: a closed surface inside the body (a tumour, a vessel), meshed conformally as a "
                        "region of its own with --inclusion-E and --inclusion-nu; repeat for several (regions "
                        "inclusion1, inclusion2, ...; one is 'inclusion')")
    p.add_argument("--inclusion-E", action="append", type=float, default=[], metavar="E",
                   help="Young's modulus of each --inclusion [Pa] (one for all, or one per inclusion)")
    p.add_argument("--inclusion-nu", action="append", type=float, default=[], metavar="NU",
                   help="Poisson ratio of each --inclusion (default: the body's)")
    p.add_argument("--no-display", dest="display", action="store_false",
                   help="do not keep the input surface as the display surface (by default a --surface file or a "
                        "label image's surface, up to 2M triangles, is kept at its own resolution and deformed with "
                        "the simulation surface: pmask view shows it)")
    p.add_argument("--shell", type=int, metavar="K",
                   help="with --surface: precompute the K-th largest shell (by area; 1 = the largest) of a file that "
                        "holds several bodies (pmask inspect lists them)")
    p.add_argument("--edge-length", type=float, help="target edge length for --surface (input units)")
    p.add_argument("--fixed", help="support region selector: 'z<-0.9', 'box:x0,y0,z0,x1,y1,z1', "
                                   "'sphere:cx,cy,cz,r', 'group:NAME', unions with '|'")
    p.add_argument("--contact", help="region a probe can touch (same selectors); default: every free vertex")
    p.add_argument("--r-max", type=float, help="largest mask radius the runtime may use (input units)")
    p.add_argument("-E", "--youngs-modulus", dest="E", type=float, help="Young's modulus [Pa]")
    p.add_argument("--nu", type=float, help="Poisson's ratio, in (-1, 0.5)")
    p.add_argument("--materials", help="materials by region, NAME:E:nu,... (NAME a physical volume of a --volume mesh "
                                       "or a model's region, e.g. the palpation model's 'inclusion'); the rest of "
                                       "the body keeps -E/--nu"),
    p.add_argument("--units", default=None, help="length unit of the input geometry: m, cm, mm, um (default m; a file "
                                                 "more than 2 m across is then refused as probably in mm)")
    p.add_argument("--mesh-timeout", type=float, default=600.0,
                   help="seconds gmsh may take to remesh a --surface before it is stopped (default 600)")
    p.add_argument("--solve-timeout", type=float, default=3600.0,
                   help="seconds allowed to the factorisation and Green's functions together (default 3600); "
                        "Ctrl-C and this budget stop them within a supernode")
    p.add_argument("--size", type=float, help="mesh size parameter of the model (kidney: largest edge [m])")
    p.add_argument("--param", type=_param, action="append", default=[], metavar="KEY=VALUE",
                   help="further model parameter (repeatable), e.g. --param h_load=0.00125")
    p.add_argument("--float32", action="store_true", help="store Ξ in single precision (half the size)")
    p.add_argument("--compress", nargs="?", type=float, const=1e-4, default=None, metavar="TOL",
                   help="store Ξ compressed: the near field (pairs within --r-max) exact, the far field in low-rank "
                        "blocks within TOL relative per block (default 1e-4): from the dense Ξ where it fits and no "
                        "Dask option is given, else in tiles on Dask without the dense Ξ (for organs whose Ξ does "
                        "not fit one machine; taken without being asked, with a warning, where the dense Ξ does not "
                        "fit)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="with --compress: run the tiles on this Dask scheduler "
                                                          "(default: a LocalCluster on this machine)")
    p.add_argument("--workers", type=int, help="with --compress: local worker processes (default: one per core), "
                                                "the tiled route even where the dense Ξ fits")
    p.add_argument("--worker-memory", metavar="BYTES",
                   help="with --compress: each local worker's memory limit, e.g. 4G (default: dask's share)")
    p.add_argument("--element", choices=("auto", "P1", "P2"), default="auto",
                   help="tetrahedra: auto (the default: P2 where P1 would lock, nu >= 0.4, P1 otherwise), P2 "
                        "(quadratic, with the volumetric term at the centroid: accurate in bending and up to nu = "
                        "0.499) or P1 (linear: 4-5x faster, locks for nearly incompressible tissue)")
    p.add_argument("--reactions", action=argparse.BooleanOptionalAction, default=None,
                   help="store the support reactions (default: when they cost no more than Ξ)")
    p.add_argument("-o", "--out", help="artifact path (default artifacts/MODEL.h5)")
    p.add_argument("--force", action="store_true", help="recompute even if the artifact is up to date")
    p.set_defaults(func=cmd_precompute)


def inclusion_materials(args) -> str | None:
    """``--materials`` with each ``--inclusion``'s material added ("inclusion:E:nu", or "inclusion1:...", ...):
    one --inclusion-E (and --inclusion-nu) for all, or one per inclusion; ν defaults to the body's."""
    from pmask.meshes.common import ModelMesh
    from pmask.precompute.meshing import inclusion_names

    n = len(args.inclusion)
    if not n:
        if args.inclusion_E or args.inclusion_nu:
            raise InputError("--inclusion-E and --inclusion-nu need --inclusion FILE")
        return args.materials
    if not args.inclusion_E:
        raise InputError("--inclusion needs --inclusion-E (the inclusion's Young's modulus in Pa, e.g. 5e4 for a mass "
                         "5x stiffer than the default tissue)")
    body_nu = args.nu if args.nu is not None else ModelMesh(points=None, tets=None, fixed="").material["nu"]
    per = []
    for name, values in (("--inclusion-E", args.inclusion_E), ("--inclusion-nu", args.inclusion_nu or [body_nu])):
        if len(values) not in (1, n):
            raise InputError(f"{name}: give one value for all {n} inclusions or one per inclusion, got {len(values)}")
        per.append(values * n if len(values) == 1 else values)
    added = ",".join(f"{name}:{E!r}:{nu!r}" for name, E, nu in zip(inclusion_names(n), *per))
    return f"{args.materials},{added}" if args.materials else added


def cmd_precompute(args) -> int:
    require_extra("precompute")
    from pmask.pipeline.stages import Spec, run

    if args.model is None and not (args.surface or args.volume or args.segmentation):
        raise InputError("name a model (see 'pmask models') or give --surface, --volume or --segmentation FILE")
    if args.segmentation:
        require_extra("segmentation")
    if args.repair:
        for extra in {"meshfix": ("repair",), "voxel": ("segmentation",), "auto": ("repair", "segmentation")}[args.repair]:
            require_extra(extra)
    materials = inclusion_materials(args)
    label = args.model or Path(args.surface or args.volume or args.segmentation).name.split(".")[0]
    params = dict(args.param)
    if args.size is not None:
        params["size"] = args.size
    spec = Spec(model=label, params=params, surface=args.surface, volume=args.volume, fixed=args.fixed,
                contact=args.contact, E=args.E, nu=args.nu, materials=materials, r_max=args.r_max,
                units=args.units.lower().replace("µ", "u") if args.units else None,
                edge_length=args.edge_length, dtype="float32" if args.float32 else "float64",
                element=args.element, reactions=args.reactions, mesh_timeout=args.mesh_timeout,
                solve_timeout=args.solve_timeout,
                segmentation=args.segmentation, label=args.label, repair=args.repair, shell=args.shell,
                inclusions=tuple(args.inclusion), display=args.display,
                compress=args.compress,
                scheduler=args.scheduler, workers=args.workers, worker_memory=args.worker_memory)
    out = Path(args.out) if args.out else Path("artifacts") / f"{label}.h5"
    summary = run(spec, out, force=args.force, progress=not args.quiet and sys.stderr.isatty())
    if summary["up_to_date"]:
        print(f"{out} is up to date (input hash {summary['input_hash'][:12]}); --force recomputes it")
        return 0
    t = summary["timings"]
    print(f"wrote {out} ({summary['size_bytes'] / 2**20:.1f} MiB)")
    print(f"  mesh: {summary['volume_vertices']} vertices, {summary['tets']} tets, {summary['dofs']} dofs condensed")
    print(f"  surface: {summary['surface_vertices']} vertices: {summary['free']} free (Λp), "
          f"{summary['fixed']} fixed (Λu), {summary['contact']} in Ξ")
    if summary.get("cavities"):
        names = ["cavity"] if len(summary["cavities"]) == 1 else [f"cavity{k + 1}" for k in range(len(summary["cavities"]))]
        print(f"  hollow: {len(names)} cavit{'y' if len(names) == 1 else 'ies'} ("
              + ", ".join(f"group:{n}, {w} wall vertices" for n, w in zip(names, summary["cavities"]))
              + "); a wall is touchable only where --contact selects it")
    if summary.get("remesh"):
        g = summary["remesh"]
        if g.get("auto"):
            a = g["auto"]
            print(f"  repair auto: {'route ' + a['route'] if a['route'] != 'none' else 'no repair needed'}; the "
                  f"surface lies within {1e3 * a['hausdorff_to_input_m']:.3g} mm of the input (Hausdorff) with "
                  f"{100 * a['area_kept']:.1f} % of its area" + "".join(f"\n    not used: {t}" for t in a["tried"]))
        if g.get("repair"):
            b, a = g["repair"]["before"], g["repair"]["after"]
            if g["repair"].get("route") == "voxel":
                print(f"  repair: rebuilt from {1e3 * g['repair']['voxel']:.3g} mm voxels, {g['repair']['solids']} "
                      f"separate solid(s), the largest kept; {b['triangles']} -> {a['triangles']} triangles")
            else:
                print(f"  repair: {b['boundary_edges']} boundary and {b['non_manifold_edges']} non-manifold edges "
                      f"before; {g['repair'].get('changes') or str(b['triangles']) + ' -> ' + str(a['triangles']) + ' triangles'}")
        print(f"  remesh: surface moved by up to {1e3 * g['hausdorff_m']:.3g} mm (Hausdorff, sampled every "
              f"{1e3 * g['sample_spacing_m']:.2g} mm), volume {100 * g['volume_change']:+.2f} %")
    c = (summary.get("factor_stats") or {}).get("compress")
    if c:
        print(f"  compressed Ξ: {c['ratio']:.1f}x smaller than dense ({c['stored_bytes'] / 2**20:.1f} of "
              f"{c['dense_bytes'] / 2**20:.1f} MiB), {c['dense_blocks']} dense + {c['lowrank_blocks']} low-rank blocks "
              f"(rank <= {c['max_rank']}), {c['tiles']} tiles "
              + ("from the dense Ξ (it fits)" if c.get("route") == "dense Xi" else f"on {c.get('workers', 0)} Dask workers")
              + (f", {c['tiles_reused']} reused" if c["tiles_reused"] else ""))
    print("  time: " + ", ".join(f"{k} {v:.2f}s" for k, v in t.items()) + f"; total {sum(t.values()):.2f}s"
          + (f" (resumed after: {', '.join(summary['resumed'])})" if summary["resumed"] else ""))
    return 0


def add_models(sub) -> None:
    p = sub.add_parser("models", help="list the registered models")
    p.set_defaults(func=cmd_models)


def cmd_models(args) -> int:
    require_extra("precompute")
    from pmask.pipeline.models import MODELS

    for name, (_, desc) in MODELS.items():
        print(f"{name:10s} {desc}")
    return 0


def add_info(sub) -> None:
    p = sub.add_parser("info", help="describe an artifact (counts, material, units, provenance) or a runtime table")
    p.add_argument("artifact", help="an artifact (.h5) or a runtime table (pmask export-table), checked as read")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_info)


def _print_info(info: dict, as_json: bool) -> int:
    if as_json:
        print(json.dumps(info, indent=2, default=str))
    else:
        for k, v in info.items():
            print(f"{k:16s} {v}")
    return 0


def table_info(path: str) -> dict:
    """What a runtime table (:mod:`pmask.runtime.table`) holds, read and checked as both loaders check it: its
    format, the contact surface's counts, how it couples contacts (a ζ table, or a compressed Ξ's sections and how
    they store the far field and the exact pairs), the display surface, the mask and its source."""
    from pmask.runtime.table import read_table

    t = read_table(path)
    meta = t["meta"]
    info = {"file": path, "format": f"pmask runtime table {meta.get('format', '?')}",
            "size": f"{Path(path).stat().st_size / 2**20:,.1f} MiB",
            "surface": f"{len(t['points']):,} vertices, {len(t['triangles']):,} triangles"
                       + (f" (the mesh's {len(t['mesh_triangles']):,} subdivided {meta.get('levels')} times)"
                          if "mesh_triangles" in t else " (the mesh's own)")}
    if "zeta" in t:
        info["coupling"] = f"zeta table {t['zeta'].shape[0]:,} x {t['zeta'].shape[1]:,} (float64)"
    elif "xi_info" in t:
        n, item, symmetric = (int(x) for x in t["xi_info"][0])
        factors = {2: "16 bits with a scale per column", 4: "float32", 8: "float64"}[item]
        pairs = "48-bit fixed point" if "xi_near_exact48" in t else "float64"
        info["coupling"] = (f"compressed Green's functions over {n:,} contact vertices (tolerance "
                            f"{meta.get('greens', {}).get('tolerance', '?')}): {len(t['xi_dense_index']):,} dense "
                            f"and {len(t['xi_lowrank_index']):,} low-rank blocks"
                            + (", those on and above the diagonal" if symmetric else "")
                            + f"; the far field's factors in {factors}, the pairs within r_max in {pairs}")
    else:
        info["coupling"] = "none (exported with --no-zeta: single contacts only)"
    info["display"] = (f"{len(t['display_points']):,} vertices, {len(t['display_triangles']):,} triangles"
                       if "display_points" in t else "none")
    info.update({k: meta.get(k) for k in ("mask", "radius", "k_rigid", "normal_radius", "units", "source",
                                          "pmask_version")})
    return info


def cmd_info(args) -> int:
    from pmask.runtime.artifact import read_artifact
    from pmask.runtime.table import MAGIC

    try:
        with open(args.artifact, "rb") as f:
            is_table = f.read(len(MAGIC)) == MAGIC
    except OSError:
        is_table = False  # (read_artifact says what is wrong with the path)
    if is_table:
        info = table_info(args.artifact)
        if not args.json:  # (six digits of the lengths and stiffness to read; --json keeps every one)
            info = {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in info.items()}
        return _print_info(info, args.json)
    d = read_artifact(args.artifact)
    a = d["attrs"]
    info = {
        "file": args.artifact, "format": f"{a['format_name']} {a['format_version']}", "model": a["model"],
        "element": a.get("element", "P1"),
        "surface_vertices": len(d["surface/points"]), "triangles": len(d["surface/triangles"]),
        "free": len(d["surface/free"]), "fixed": len(d["surface/fixed"]), "contact": len(d["surface/contact"]),
        "volume_vertices": len(d["volume/points"]), "tets": len(d["volume/tets"]),
        "material": a["material"], "units": a["units"], "r_max": float(a["r_max"]),
        "Xi": (f"{d['greens/Xi'].shape} {d['greens/Xi'].dtype}" if "greens/Xi" in d else
               f"compressed, tolerance {a['tolerance']:g}: {len(d['greens/hmatrix/dense_index'])} dense and "
               f"{len(d['greens/hmatrix/lowrank_index'])} low-rank blocks, "
               + (f"{d['greens/hmatrix/dense'].dtype}" if d.get("greens/hmatrix/dense") is not None else
                  ("pairs within r_max in 48-bit fixed point" if d.get("greens/hmatrix/near_exact48") is not None
                   else f"pairs within r_max in {d['greens/hmatrix/near_exact'].dtype}")
                  + ", the dense blocks' others in 16 bits")
               + (", the far field's factors in 16 bits" if d.get("greens/hmatrix/U16") is not None
                  else f", the far field's factors in {d['greens/hmatrix/U'].dtype}")),
        "input_hash": a["input_hash"],
        "libraries": a["provenance"].get("libraries"), "timings": a["timings"],
    }
    return _print_info(info, args.json)


def add_reference(sub) -> None:
    p = sub.add_parser("reference", help="recompute the stored reference tables (tests/reference) and show the diff")
    p.add_argument("--remesh", action="store_true", help="mesh anew with gmsh instead of using the stored meshes")
    p.add_argument("--dir", default=None, help="reference folder (default tests/reference)")
    p.set_defaults(func=cmd_reference)


def cmd_reference(args) -> int:
    require_extra("precompute")
    from pmask.pipeline.reference import DOCS_PAGE, REFERENCE_DIR, regenerate, write_docs_page

    ref_dir = Path(args.dir) if args.dir else REFERENCE_DIR
    if not (ref_dir / "meshes").is_dir() and not args.remesh:
        raise InputError(f"pmask reference recomputes the tables of a source checkout from the meshes stored beside "
                         f"them ({ref_dir / 'meshes'} is missing): run it in a checkout, or give --remesh --dir FOLDER "
                         "to mesh anew and write the tables there")
    diffs = regenerate(ref_dir, remesh=args.remesh)
    if ref_dir == REFERENCE_DIR and DOCS_PAGE.parent.parent.is_dir():
        print(f"wrote {write_docs_page(ref_dir)}")
    for name, d in diffs.items():
        print(f"{name}: {'unchanged' if not d else f'{len(d)} changes'}")
        for line in d[:20]:
            print(f"  {line}")
    if any(diffs.values()):
        print("A changed reference needs its reason in the commit message.")
    return 0


def add_figures(sub) -> None:
    p = sub.add_parser("figures", help="the paper's Figure 6 maps for a model, and Figures 1 and 4 (PNG)",
                       description="Figure 6 (vertex area, single-vertex and masked stiffness maps) for the model; "
                                   "Figures 1 (a point load on three refinements) and 4 (single-vertex vs cone "
                                   "mask pulls) on the Figure 5 ellipsoid family (stored meshes).")
    p.add_argument("model", help="registered model name or an artifact path (.h5)")
    p.add_argument("--out", default="docs", help="output folder (default docs)")
    p.add_argument("--radius-factor", type=float, default=2.0, help="cone radius in mean edge lengths")
    p.add_argument("--no-loop", action="store_true", help="Figure 6 only (skip Figures 1 and 4)")
    p.set_defaults(func=cmd_figures)


def cmd_figures(args) -> int:
    require_extra("precompute", "figures")
    from pmask.pipeline.figures import figure6
    from pmask.pipeline.truth import figure6_numbers
    from pmask.runtime import Model

    path = Path(args.model)
    if path.suffix != ".h5":  # a model's name: its artifact from `pmask precompute`, never a silent precompute here
        from pmask.pipeline.models import get_model

        get_model(args.model)
        path = Path("artifacts") / f"{args.model}.h5"
        if not path.exists():
            raise InputError(f"{path} does not exist: run `pmask precompute {args.model}` first (or give an "
                             "artifact's path)")
    model = Model.load(path)
    nums = figure6_numbers(model, args.radius_factor)
    out = figure6(model, Path(args.out) / f"figure6_{path.stem}.png", args.radius_factor, nums)
    print(f"wrote {out}")
    for name in ("single", "masked"):
        n = nums[name]
        print(f"  {name:6s} rank correlation with vertex area {n['rank_correlation_with_area']:+.3f}, "
              f"roughness {n['roughness']:.4f}, median ‖K‖₂ {n['median_norm']:.2f} N/m")
    numbers = {"figure6" if path.stem == "kidney" else f"figure6_{path.stem}": {"artifact": path.name, **nums}}
    if model.attrs.get("material", {}).get("regions"):  # an organ with a mass: the same press over it and beside it
        from pmask.pipeline.figures import mass_figure

        png, mass = mass_figure(model, Path(args.out) / f"{path.stem}_mass.png", args.radius_factor)
        print(f"wrote {png}: {mass['force_N']:g} N over the {mass['region']} indents "
              f"{mass['indentation_over_mm']:.2f} mm, mirrored {mass['indentation_mirrored_mm']:.2f} mm "
              f"({mass['ratio']:.2f}x)")
        numbers[f"mass_{path.stem}"] = mass
    if "display" in model.attrs:  # a scan kept at its resolution: pressed by a probe
        from pmask.pipeline.figures import scan_figure

        png, scan = scan_figure(model, Path(args.out) / f"scan_{path.stem}.png")
        print(f"wrote {png}: the scan ({scan['display_triangles']:,} triangles) pressed {scan['depth_mm']:.2f} mm lies "
              f"{scan['probe_to_scan_mm']:.3f} mm from the probe (the simulation surface {scan['probe_to_simulation_mm']:.3f} mm)")
        numbers[f"scan_{path.stem}"] = scan
    if not args.no_loop:
        from pmask.pipeline.figures import loop_figures

        res = loop_figures(Path(args.out), Path("artifacts") / ".figures")
        print(f"wrote {res['figure1']}: displacement at the point load "
              + ", ".join(f"{p * 1e3:.2f}" for p in res["figure1_peaks"]) + " mm per N (finer to the right)")
        print(f"wrote {res['figure4']}: single-vertex {res['figure4_peaks']['single'] * 1e3:.2f}, cone mask "
              f"{res['figure4_peaks']['linear'] * 1e3:.2f} mm per N at the load")
        numbers["figure1_peaks_mm_per_N"] = [1e3 * float(p) for p in res["figure1_peaks"]]
        numbers["figure4_peaks_mm_per_N"] = {k: 1e3 * float(v) for k, v in res["figure4_peaks"].items()}
    # the figures' numbers beside them, for the docs (the `measured` role reads docs/figures.json)
    data = Path(args.out) / "figures.json"
    old = json.loads(data.read_text()) if data.exists() else {}
    data.write_text(json.dumps({**old, **numbers}, indent=1, default=float) + "\n")
    print(f"wrote {data}")
    return 0


def _vector(text: str):
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"need three comma-separated numbers, got '{text}'")
    return v


def add_export(sub) -> None:
    p = sub.add_parser("export", help="write the surface with areas, regions and stiffness for ParaView (meshio)")
    p.add_argument("artifact")
    p.add_argument("out", help="output file, e.g. kidney.vtu")
    p.add_argument("--mask", default="linear", help="mask for K_masked_norm (default linear)")
    p.add_argument("--radius", type=float, help="mask radius in model units (default 2 mean edge lengths)")
    p.add_argument("--contact-vertex", type=int, help="add the deformation for a contact at this surface vertex")
    p.add_argument("--force", type=_vector, default=[0.0, 0.0, -0.1], help="contact force fx,fy,fz [N]")
    p.set_defaults(func=cmd_export)


def cmd_export(args) -> int:
    require_extra("precompute")
    from pmask.pipeline.export import export_surface
    from pmask.runtime import Model

    out = export_surface(Model.load(args.artifact), Path(args.out), mask=args.mask, radius=args.radius,
                         contact_vertex=args.contact_vertex, force=args.force)
    print(f"wrote {out}")
    return 0


def add_levels(p) -> None:
    """``--levels``: the contact surface the haptic contact runs on (export-table, view)."""
    p.add_argument("--levels", default="auto", choices=["0", "1", "2", "3", "auto"],
                   help="contact surface: auto (default) the mesh's Loop subdivision surface after the fewest "
                        "levels whose facets meet the contact normals within 3.5 degrees (closed loops then give "
                        "back far less energy: see the haptics guide), n after n levels, 0 the mesh itself")


def levels_of(args):
    """The ``levels`` argument of :class:`pmask.runtime.Contacts` for ``--levels``."""
    return args.levels if args.levels == "auto" else int(args.levels)


def add_export_table(sub) -> None:
    p = sub.add_parser("export-table", help="write a runtime table for the native servo core (C/C++ applications)",
                       description="Export what the haptic step reads for one mask and radius: the mesh, contact "
                                   "normals, rendered vertex stiffness K_i, taper, spatial grid and (unless --no-zeta) "
                                   "the zeta table for coupled contacts and deformation.  See pmask.runtime.table.")
    p.add_argument("artifact")
    p.add_argument("-o", "--out", required=True, help="table file to write, e.g. kidney.tbl")
    p.add_argument("--mask", default="linear", help="pressure mask: linear, gaussian, wendland, disk or single")
    p.add_argument("--radius", type=float, help="mask radius in model units (default 2 mean edge lengths)")
    p.add_argument("--k-rigid", type=float, help="stiffness the support ramps to [N/m] (default: see Model.stiffness)")
    p.add_argument("--normal-radius", type=float, help="crease-blending radius of the contact normals (default 3 mask radii)")
    add_levels(p)
    p.add_argument("--no-zeta", action="store_true",
                   help="leave out the zeta table (3n_c x 3n_c doubles), or a compressed artifact's Green's functions: "
                        "single and uncoupled contacts only, no deformation")
    p.set_defaults(func=cmd_export_table)


def cmd_export_table(args) -> int:
    from pmask.runtime.table import export_table

    from pmask.runtime.model import Model

    model = Model.load(args.artifact)
    compressed = model.attrs.get("greens_form") == "hmatrix"
    out = export_table(model, Path(args.out), mask=args.mask, radius=args.radius, k_rigid=args.k_rigid,
                       normal_radius=args.normal_radius, zeta=not args.no_zeta, levels=levels_of(args))
    print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MiB)")
    if compressed and not args.no_zeta:
        n3 = 3 * len(model.contact)
        print(f"  with the compressed Green's functions in place of the zeta table (a dense {n3} x {n3} array, "
              f"{n3 * n3 * 8 / 2**30:.1f} GiB): the C core couples contacts and deforms the surface from them")
    return 0


def add_c_core(sub) -> None:
    p = sub.add_parser("c-core", help="where the servo core's C files are, for a C application's build",
                       description="Print the servo core's include folder (--include, the default) and its C files "
                                   "(--sources, space-separated), one line each, for a Makefile: "
                                   "cc -I$(pmask c-core --include) app.c $(pmask c-core --sources) -lm -lpthread.  "
                                   "Needs only the runtime (numpy and h5py).")
    p.add_argument("--include", action="store_true", help="the include folder")
    p.add_argument("--sources", action="store_true", help="the C files, space-separated")
    p.set_defaults(func=cmd_c_core)


def cmd_c_core(args) -> int:
    from pmask.runtime.servo import include_dir, sources

    if args.include or not args.sources:
        print(include_dir())
    if args.sources:
        print(" ".join(str(f) for f in sources()))
    return 0


def add_view(sub) -> None:
    p = sub.add_parser("view", help="see and probe a model in a browser (a local server; the servo runs at 1 kHz)",
                       description="Serve a page that shows the surface coloured by stiffness, area or region, with "
                                   "the mouse as a haptic probe (shift-drag: a second, coupled one).  Listens on "
                                   "127.0.0.1 only unless --host is given.  Ctrl-C stops.")
    p.add_argument("artifact")
    p.add_argument("--port", type=int, default=8765, help="TCP port (default 8765; 0 picks a free one)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0 exposes it)")
    p.add_argument("--mask", default="linear", help="pressure mask: linear, gaussian, wendland, disk or single")
    p.add_argument("--radius", type=float, help="initial mask radius in model units (default 2 mean edge lengths)")
    p.add_argument("--engine", choices=("native", "python"), help="servo engine (default: native if built)")
    add_levels(p)
    p.set_defaults(func=cmd_view)


def cmd_view(args) -> int:
    import signal

    from pmask.viewer import serve

    def stop(signum, frame):  # SIGTERM stops as Ctrl-C does
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, stop)
    serve(args.artifact, host=args.host, port=args.port, mask=args.mask, radius=args.radius, engine=args.engine,
          levels=levels_of(args))
    return 0


def add_inspect(sub) -> None:
    p = sub.add_parser("inspect", help="shells, defects, bounding box and a suggested --edge-length of a surface file",
                       description="Look at a triangle surface before precomputing it: its shells, defects, bounding "
                                   "box (in the file's units) and the --edge-length for a number of surface vertices.")
    p.add_argument("surface")
    p.add_argument("--units", default=None, help="the file's length unit (only for the report's wording)")
    p.add_argument("--vertices", type=int, nargs="*", default=[500, 2000, 5000],
                   help="surface vertex counts to suggest an --edge-length for (default 500 2000 5000)")
    p.set_defaults(func=cmd_inspect)


def cmd_inspect(args) -> int:
    require_extra("precompute")
    from pmask.pipeline.inspect import inspect_surface, report

    if not Path(args.surface).is_file():
        raise InputError(f"{args.surface}: no such file")
    if not args.vertices or min(args.vertices) < 4:
        raise InputError("--vertices needs counts of at least 4")
    print(report(inspect_surface(args.surface, args.units, tuple(args.vertices))))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pmask", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=version_line())
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging and full tracebacks")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (add_precompute, add_models, add_info, add_export, add_export_table, add_c_core, add_reference,
                add_figures, add_view, add_inspect):
        add(sub)
    return parser


def version_line() -> str:
    """``pmask --version``: the version and which compiled parts this installation has."""
    import importlib.util

    import pmask

    def built(name):
        try:
            return importlib.util.find_spec(name) is not None
        except ImportError:
            return False

    parts = {"selected inversion (C over CHOLMOD)": built("pmask.precompute._selinv"),
             "servo core (C)": built("pmask.runtime.servo._core")}
    have = ", ".join(f"{k}: {'built' if v else 'not built, pip-only fallback'}" for k, v in parts.items())
    return f"pmask {pmask.__version__} ({have})"


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else (logging.WARNING if args.quiet else logging.INFO),
                        format="%(levelname)s %(name)s: %(message)s")
    if not args.verbose:
        logging.getLogger("skfem").setLevel(logging.WARNING)
    previous = _interrupts_recorded()
    try:
        return args.func(args)
    except PmaskError as exc:
        if args.verbose:
            raise
        print(f"pmask: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        interrupt.clear()
        print("pmask: interrupted; run the same command again to resume from the last finished stage",
              file=sys.stderr)
        return 130
    except Exception:  # not the user's to fix: a bug in pmask
        if args.verbose:
            raise
        traceback.print_exc()
        print(f"pmask: internal error: this is a bug in pmask, not in your input; please report it with the "
              f"command line above and `{version_line()}`", file=sys.stderr)
        return 3
    finally:
        if previous is not None:
            import signal

            for sig, handler in previous.items():
                signal.signal(sig, handler)


def _interrupts_recorded():
    """Ctrl-C and SIGTERM (a scheduler's or a supervisor's stop) end a command alike: the cleanup runs (the
    gmsh worker is killed, temporary folders go, finished stages are kept) instead of the process vanishing
    mid-way, and the request is recorded (:mod:`pmask.interrupt`) so that a library that swallows
    ``KeyboardInterrupt`` cannot lose it.  Returns the previous handlers (None off the main thread, or when
    SIGINT is ignored, as in a shell's background job)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    interrupt.clear()
    previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, interrupt.handler)}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, interrupt.handler)
    return previous
