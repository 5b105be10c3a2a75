"""Reference stiffness tables: computed from stored meshes, kept in ``tests/reference``, checked by CI.

The meshes are stored too (``tests/reference/meshes/*.npz``), so that a new gmsh
cannot move the numbers silently: ``pmask reference`` recomputes the tables
from the stored meshes, ``pmask reference --remesh`` meshes anew first.
"""
from __future__ import annotations

import csv
import io
import logging
from pathlib import Path

import numpy as np

from pmask.meshes import halfspace, kidney, loop
from pmask.meshes.common import load_model_mesh, save_model_mesh

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
REFERENCE_DIR = ROOT / "tests" / "reference"
HALFSPACE_R = halfspace.LOAD_RADIUS
HALFSPACE_DIVISIONS = (4, 8, 16)  # h = r / k at the load (P1)
HALFSPACE_P2_DIVISIONS = (4, 8)  # P2 converges faster and costs ~6x the dofs per mesh
KIDNEY_SMALL_SIZE = 0.009
HALFSPACE_FAR = 120.0
INCOMPRESSIBLE_NU = (0.3, 0.45, 0.49, 0.499)

#: stored mesh name -> builder
MESHES = {
    **{f"loop{k}": (lambda k=k: loop.build(k)) for k in range(4)},
    **{f"halfspace_h{k}": (lambda k=k: halfspace.build(h_load=HALFSPACE_R / k)) for k in HALFSPACE_DIVISIONS},
    # the nearly-incompressible rows: the hemisphere 4x farther (R = 120 r) so that the far support's
    # stiffening (+1..2 % at R = 30 r, not shrinking with h) stays below the element's own error
    "halfspace_far_h4": lambda: halfspace.build(h_load=HALFSPACE_R / 4, far=HALFSPACE_FAR),
    "kidney": lambda: kidney.build(),
    "kidney_small": lambda: kidney.build(KIDNEY_SMALL_SIZE),
}


def ensure_meshes(mesh_dir: Path, remesh: bool = False) -> None:
    mesh_dir.mkdir(parents=True, exist_ok=True)
    for name, build in MESHES.items():
        p = mesh_dir / f"{name}.npz"
        if remesh or not p.exists():
            log.info("meshing %s", name)
            save_model_mesh(p, build())


def artifact_for(name: str, mesh_dir: Path, work: Path, nu: float | None = None, element: str = "auto") -> Path:
    """Precompute (or reuse) the artifact of a stored mesh (``auto``: the element pmask chooses for its material,
    as ``pmask precompute`` does)."""
    from pmask.pipeline.stages import Spec, run

    out = work / (f"{name}_{element}" + ("" if nu is None else f"_nu{nu:g}") + ".h5")
    run(Spec(model=name, volume=str(mesh_dir / f"{name}.npz"), nu=nu, element=element), out)
    return out


def figure5_table(mesh_dir: Path, work: Path, element: str = "P1"):
    """The paper's Figure 5 on the Loop family with ``element`` (P1: ``figure5.csv``; P2: ``figure5_p2.csv``)."""
    from pmask.pipeline.truth import figure5_row
    from pmask.runtime import Model

    models = [Model.load(artifact_for(f"loop{k}", mesh_dir, work, element=element)) for k in range(4)]
    radius = models[0].mean_edge_length
    base = load_model_mesh(mesh_dir / "loop0.npz").info["base_vertex_position"]
    rows = []
    for k, m in enumerate(models):
        r = figure5_row(m, base, radius)
        rows.append({"model": f"loop{k}", "surface_vertices": r["vertices"], "mean_edge_m": r["mean_edge"],
                     "single_norm_N_per_m": r["single"], "masked_norm_N_per_m": r["masked"],
                     "mask_vertices": r["mask_size"]})
    meta = {"table": "paper Figure 5: vertex stiffness vs Loop level", "model": "loop0..loop3 ellipsoid "
            "80 x 40 x 40 mm, fixed cap x >= 12 mm (0.3 a), held by area (the mesh fitted to its rim)", "resolution": "34/130/514/2050 surface vertices",
            "mask": f"linear cone, r = {radius:.6e} m (mean edge length of loop0)",
            "vertex": "base vertex 17 (ring 3, segment 0)", "units": "N/m (norm = largest singular value)",
            "material": f"E = {models[0].E:g} Pa, nu = {models[0].nu:g}"}
    if element != "P1":
        meta["element"] = f"{element} (the traction stays piecewise linear; Xi read at the corners)"
    return meta, rows


def halfspace_table(mesh_dir: Path, work: Path, elements=("P1", "P2")):
    from pmask.pipeline.truth import analytic_centre_stiffness, centre_stiffness
    from pmask.runtime import Model

    rows = []
    divisions = {"P1": HALFSPACE_DIVISIONS, "P2": HALFSPACE_P2_DIVISIONS}
    cases = [(element, nu, k) for element in elements for nu in (0.3, 0.45) for k in divisions[element]]
    for element, nu, k in cases:
        name = f"halfspace_h{k}"
        m = Model.load(artifact_for(name, mesh_dir, work, nu=nu, element=element))
        for kind in ("linear", "disk", "wendland", "gaussian", "single"):
            c = centre_stiffness(m, kind, HALFSPACE_R)
            kn_a, kt_a = analytic_centre_stiffness(kind, m.E, m.nu, HALFSPACE_R)
            ratio_a = 2 * (1 - m.nu) / (2 - m.nu)
            rows.append({"element": element, "mesh": name, "h_over_r": 1.0 / k, "nu": nu, "mask": kind,
                         "kn_N_per_m": c["kn"],
                         "kt_N_per_m": c["kt"], "kt_over_kn": c["ratio"], "kn_analytic": kn_a,
                         "kt_analytic": kt_a, "kn_error": c["kn"] / kn_a - 1 if kn_a else float("nan"),
                         "kt_error": c["kt"] / kt_a - 1 if kt_a else float("nan"),
                         "ratio_error": c["ratio"] / ratio_a - 1, "volume_vertices": len(m.volume()[0])})
    meta = {"table": "centre stiffness of masks on a half-space vs Boussinesq/Cerruti",
            "model": f"hemisphere R = 30 r fixed on its curved surface, r = {HALFSPACE_R} m, E = 1e4 Pa",
            "resolution": "h = r/4, r/8, r/16 (P1) and r/4, r/8 (P2) at the load, growing 0.2 per unit distance",
            "mask": "linear cone, uniform disk, Wendland C2, truncated Gaussian, single vertex; radius r",
            "units": "N/m; errors relative", "element": "P1 and P2 (column 'element')"}
    return meta, rows


def incompressible_table(mesh_dir: Path, work: Path):
    """P2 (the P2-P0 volumetric rule) on the far half-space at h = r/4 for ν up to 0.499, against
    Boussinesq/Cerruti (the soft-tissue issue: k_n and k_t within 3 % at ν = 0.45 and 0.49)."""
    from pmask.pipeline.truth import analytic_centre_stiffness, centre_stiffness
    from pmask.runtime import Model

    rows = []
    for nu in INCOMPRESSIBLE_NU:
        m = Model.load(artifact_for("halfspace_far_h4", mesh_dir, work, nu=nu, element="P2"))
        for kind in ("linear", "disk", "wendland", "gaussian"):
            c = centre_stiffness(m, kind, HALFSPACE_R)
            kn_a, kt_a = analytic_centre_stiffness(kind, m.E, m.nu, HALFSPACE_R)
            rows.append({"element": "P2", "mesh": "halfspace_far_h4", "h_over_r": 0.25, "nu": nu, "mask": kind,
                         "kn_N_per_m": c["kn"], "kt_N_per_m": c["kt"], "kn_analytic": kn_a, "kt_analytic": kt_a,
                         "kn_error": c["kn"] / kn_a - 1, "kt_error": c["kt"] / kt_a - 1,
                         "volume_vertices": len(m.volume()[0])})
    meta = {"table": "nearly incompressible tissue: P2 centre stiffness on a half-space vs Boussinesq/Cerruti",
            "model": f"hemisphere R = {HALFSPACE_FAR:g} r fixed on its curved surface, r = {HALFSPACE_R} m, E = 1e4 Pa",
            "resolution": "h = r/4 at the load, growing 0.2 per unit distance",
            "mask": "linear cone, uniform disk, Wendland C2, truncated Gaussian; radius r",
            "units": "N/m; errors relative", "element": "P2 (volumetric term at the centroid: P2-P0)"}
    return meta, rows


def kidney_tables(mesh_dir: Path, work: Path):
    from pmask.pipeline import strokes
    from pmask.pipeline.truth import figure6_numbers, vertex_norms
    from pmask.runtime import Model

    m = Model.load(artifact_for("kidney", mesh_dir, work))
    f6 = figure6_numbers(m, 2.0)
    smooth = {}
    for name, stiff in (("single", m.stiffness("single")), ("masked", m.stiffness("linear", f6["radius"]))):
        forces, status = strokes.run_stroke(stiff, strokes.stroke_path())
        smooth[name] = strokes.smoothness(forces, status)
    rows = [{"stiffness": name, "rank_correlation_with_area": f6[name]["rank_correlation_with_area"],
             "vertex_roughness": f6[name]["roughness"], "normal_stiffness_roughness": f6[name]["normal_roughness"],
             "median_norm_N_per_m": f6[name]["median_norm"],
             "stroke_roughness": smooth[name]["roughness"], "stroke_rms_step_N": smooth[name]["rms_step"],
             "stroke_mean_force_N": smooth[name]["mean_force"]} for name in ("single", "masked")]
    meta6 = {"table": "paper Figure 6: what the stiffness maps show",
             "model": f"kidney (default resolution, default element: {m.attrs.get('element', 'P1')})",
             "resolution": f"{len(m.points)} surface vertices, {len(m.free)} free",
             "mask": f"single vertex; linear cone r = 2 x mean edge = {f6['radius']:.6e} m",
             "stroke": "pmask.pipeline.strokes: y = 12 mm, x = -45..45 mm, 1.5 mm deep, 35 mm/s, 1 kHz, on the "
                       "default contact surface (levels auto)",
             "units": "N/m, N; roughness relative"}
    small = Model.load(artifact_for("kidney_small", mesh_dir, work))
    r = 2.0 * small.mean_edge_length
    single, masked = vertex_norms(small.stiffness("single")), vertex_norms(small.stiffness("linear", r))
    verts = small.contact[small.core]
    vrows = [{"vertex": int(v), "x_m": small.points[v, 0], "y_m": small.points[v, 1], "z_m": small.points[v, 2],
              "area_m2": small.vertex_areas[v], "single_norm_N_per_m": s, "masked_norm_N_per_m": k}
             for v, s, k in zip(verts, single, masked)]
    metav = {"table": "per-vertex stiffness of a small kidney",
             "model": f"kidney size = {KIDNEY_SMALL_SIZE} m, element {small.attrs.get('element', 'P1')}",
             "resolution": f"{len(small.points)} surface vertices", "mask": f"single; linear cone r = {r:.6e} m",
             "units": "m, m^2, N/m"}
    return (meta6, rows), (metav, vrows)


def compute_all(mesh_dir: Path, work: Path, elements=("P1", "P2")) -> dict:
    """Every reference table; ``elements`` limits the half-space table's rows (the P2 rows are the slow ones;
    without P2 the incompressible table is left out too)."""
    f6, kv = kidney_tables(mesh_dir, work)
    out = {"figure5": figure5_table(mesh_dir, work), "halfspace": halfspace_table(mesh_dir, work, elements),
           "figure6": f6, "kidney_vertices": kv}
    if "P2" in elements:
        out["incompressible"] = incompressible_table(mesh_dir, work)
        out["figure5_p2"] = figure5_table(mesh_dir, work, "P2")
    return out


def format_table(meta: dict, rows: list[dict]) -> str:
    buf = io.StringIO()
    for k, v in meta.items():
        buf.write(f"# {k}: {v}\n")
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.10g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def read_table(path: Path) -> tuple[dict, list[dict]]:
    meta, lines = {}, []
    for line in Path(path).read_text().splitlines():
        if line.startswith("# "):
            k, _, v = line[2:].partition(": ")
            meta[k] = v
        else:
            lines.append(line)
    return meta, list(csv.DictReader(lines))


def compare(old: list[dict], new: list[dict], rtol: float) -> list[str]:
    """Differences beyond rtol between two tables (numbers) or any text change."""
    if len(old) != len(new):
        return [f"{len(old)} rows stored, {len(new)} computed"]
    out = []
    for i, (a, b) in enumerate(zip(old, new)):
        for key in a:
            x, y = a[key], b.get(key)
            try:
                fx, fy = float(x), float(y)
            except (TypeError, ValueError):
                if str(x) != str(y):
                    out.append(f"row {i} {key}: {x} -> {y}")
                continue
            if not (np.isnan(fx) and np.isnan(fy)) and abs(fx - fy) > rtol * max(abs(fx), abs(fy), 1e-300):
                out.append(f"row {i} {key}: {x} -> {y} (rel {abs(fx - fy) / max(abs(fx), abs(fy)):.2e})")
    return out


def regenerate(ref_dir: Path = REFERENCE_DIR, *, remesh: bool = False, work: Path | None = None) -> dict:
    """Recompute every table (from stored meshes unless ``remesh``), write them, return the diffs."""
    import tempfile

    mesh_dir = ref_dir / "meshes"
    ensure_meshes(mesh_dir, remesh)
    with tempfile.TemporaryDirectory() as tmp:
        tables = compute_all(mesh_dir, Path(work) if work else Path(tmp))
    diffs = {}
    for name, (meta, rows) in tables.items():
        path = ref_dir / f"{name}.csv"
        if path.exists():
            diffs[name] = compare(read_table(path)[1], read_table_from_text(format_table(meta, rows)), 1e-9)
        else:
            diffs[name] = ["new table"]
        path.write_text(format_table(meta, rows))
    return diffs


def read_table_from_text(text: str) -> list[dict]:
    return list(csv.DictReader(line for line in text.splitlines() if not line.startswith("# ")))


#: the reference tables in the order the docs show them
DOCS_ORDER = ("figure5", "figure5_p2", "figure6", "halfspace", "incompressible", "kidney_vertices")
#: the page `make reference` writes into the docs (docs/generated/reference.md)
DOCS_PAGE = ROOT / "docs" / "generated" / "reference.md"


def _cell(column: str, value: str) -> str:
    """A stored value as the docs show it: relative errors as signed per cent, counts as integers, other
    numbers to four significant digits, text as it is."""
    try:
        x = float(value)
    except ValueError:
        return value
    if column.endswith("_error") or column == "error":
        return f"{100 * x:+.1f} %"
    if x == int(x) and abs(x) < 1e15 and "." not in value and "e" not in value.lower():
        return f"{int(x):,}"
    return f"{x:.4g}"


def docs_page(ref_dir: Path = REFERENCE_DIR, max_rows: int = 40) -> str:
    """The stored reference tables as one Markdown page (``make reference`` writes it; a test checks that the
    committed page equals this rendering of the committed tables, so no number on it is typed by hand)."""
    out = ["<!-- generated by `make reference` from tests/reference/*.csv: do not edit -->", "",
           "# Reference tables", "",
           "Every table below is stored in `tests/reference/` (CSV with a header saying model, resolution, mask and "
           "units), recomputed by CI from meshes stored beside it (`tests/test_reference.py`) and regenerated by "
           "`make reference`, which also rewrites this page.", ""]
    for name in DOCS_ORDER:
        path = ref_dir / f"{name}.csv"
        if not path.exists():
            continue
        meta, rows = read_table(path)
        out += [f"(ref-{name.replace('_', '-')})=", f"## {meta.get('table', name)} (`{name}.csv`)", ""]
        out += [f"- **{k}**: {v}" for k, v in meta.items() if k != "table"] + [""]
        cols = list(rows[0]) if rows else []
        out.append("| " + " | ".join(cols) + " |")
        out.append("|" + "---|" * len(cols))
        for r in rows[:max_rows]:
            out.append("| " + " | ".join(_cell(c, r[c]) for c in cols) + " |")
        if len(rows) > max_rows:
            out.append(f"\n({len(rows) - max_rows} more rows in `{name}.csv`.)")
        out.append("")
    return "\n".join(out).rstrip() + "\n"


def write_docs_page(ref_dir: Path = REFERENCE_DIR, page: Path = DOCS_PAGE) -> Path:
    page.parent.mkdir(parents=True, exist_ok=True)
    page.write_text(docs_page(ref_dir))
    return page
