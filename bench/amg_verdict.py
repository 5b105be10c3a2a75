"""AMG against the factor where the factor is refused (issue #27 item 7), as run for bench/amg_verdict.json.

    python bench/amg_verdict.py SIZE INTERIOR OUT.json

The kidney at SIZE with its volume meshed down to INTERIOR (the same: not graded): the memory check's answer
for the factor (with one worker, the most memory a factor can have) and for AMG, then AMG's setup and the
solve of COLS of Ξ's columns (pyamg's smoothed aggregation, block CG), timed.  The whole AMG route solves
3 n_c such columns.  This script ran at the commit before ``--solver amg`` was removed; it needs that
commit's ``pmask.precompute.amg``, so it was removed with it (git history keeps it).
"""
import json, sys, time, resource
from pathlib import Path
import numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parent))
from compress_bench import R_MAX, TOL, PeakRSS
from run import machine
from pmask.pipeline import stages
from pmask.precompute import amg, compress, elements, greens
from pmask.errors import ResourceError

COLS = 9  # three vertices
size = {"size": float(sys.argv[1]), "interior": float(sys.argv[2])}
out = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": machine(), "params": size, "columns_solved": COLS}
spec = stages.Spec(model="kidney", params=size, r_max=R_MAX, element="P1", compress=TOL, workers=1)  # the most a factor gets
t0 = time.perf_counter()
mesh = stages.support_stage(spec, stages.mesh_stage(spec))
surf = stages.surface_stage(spec, mesh)
out["mesh_s"] = time.perf_counter() - t0
contact = surf.vertices[surf.regions.contact]
out["volume_vertices"], out["contact"] = int(len(mesh.points)), int(len(contact))
out["available_bytes"] = greens.available_memory()
element = elements.get_element("P1")
try:
    stages.check_memory(element, len(mesh.points), len(contact), spec)
    out["factor_refused"] = None
except ResourceError as e:
    out["factor_refused"] = str(e)
spec_amg = stages.Spec(model="kidney", params=size, r_max=R_MAX, element="P1", compress=TOL, solver="amg")
try:
    out["amg_need"] = stages.check_memory(element, len(mesh.points), len(contact), spec_amg)
    out["amg_refused"] = None
except ResourceError as e:
    out["amg_refused"] = str(e)
print(json.dumps(out, default=str), flush=True)
t0 = time.perf_counter()
d = element.discretise(mesh.points, mesh.tets)
K = element.stiffness(d, *stages.material(spec, mesh))
B, scale = element.load(d, surf.vertices[surf.triangles], contact, surf.areas[surf.regions.contact])
dirichlet = elements.dofs(element.dirichlet_nodes(d, surf.vertices[surf.regions.fixed], surf.held_facets()))
out["assemble_s"] = time.perf_counter() - t0
out["dofs"] = int(K.shape[0])
with PeakRSS() as m:
    system = amg.amg_system(K, dirichlet, elements.observed_dofs(contact), d.points, B, scale=scale)
    t0 = time.perf_counter(); system.hierarchy(); out["amg_setup_s"] = time.perf_counter() - t0
    print(json.dumps(out, default=str), flush=True)
    tree = compress.cluster_tree(mesh.points[contact])
    t0 = time.perf_counter(); X = compress.panel_columns(system, tree.perm, 0, COLS // 3)
    out["panel_s"] = time.perf_counter() - t0
out["panel_columns"] = int(X.shape[1])
out["amg_bytes"] = int(system.nbytes())
out["pcg_steps"] = int(system.stats["iterations"][-1])
out["peak_rss_bytes"] = int(m.peak)
print(json.dumps(out, default=str), flush=True)
Path(sys.argv[3]).write_text(json.dumps(out, default=str, indent=1))
