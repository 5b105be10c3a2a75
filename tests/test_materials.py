"""Materials by region (#26): the per-element assembly against the composite sphere's closed form."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import spd_lu
from pmask.precompute import assembly
from pmask.precompute.elements import P2


def composite_sphere(a: float, b: float, h: float):
    """A ball of radius b with a concentric core of radius a, meshed conformally by gmsh (the core's surface an
    interface inside the volume): points, tets, and whether each tet is in the core."""
    import gmsh

    gmsh.initialize(["-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        outer = gmsh.model.occ.addSphere(0, 0, 0, b)
        inner = gmsh.model.occ.addSphere(0, 0, 0, a)
        gmsh.model.occ.fragment([(3, outer)], [(3, inner)])
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        index = np.zeros(int(tags.max()) + 1, np.int64)
        index[tags.astype(np.int64)] = np.arange(len(tags))
        points = coords.reshape(-1, 3)
        tets, core = [], []
        for _, vol in gmsh.model.getEntities(3):
            types, _, nodes = gmsh.model.mesh.getElements(3, vol)
            t = index[nodes[list(types).index(4)].astype(np.int64)].reshape(-1, 4)
            xmax = gmsh.model.getBoundingBox(3, vol)[3]
            tets.append(t)
            core.append(np.full(len(t), xmax < 0.5 * (a + b)))
    finally:
        gmsh.finalize()
    tets, core = np.vstack(tets), np.concatenate(core)
    used = np.unique(tets)
    remap = np.full(len(points), -1)
    remap[used] = np.arange(len(used))
    points, tets = points[used], remap[tets]
    e = points[tets[:, 1:]] - points[tets[:, :1]]
    flip = np.linalg.det(e) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return points, tets, core


def lame_composite(a, b, E1, nu1, E2, nu2, p):
    """Radial displacement at r = b of a core (E1, ν1) of radius a bonded in a shell (E2, ν2) to radius b, under
    external pressure p: u = A r (core), A r + B / r² (shell); σ_rr = 3 K A − 4 G B / r³; u and σ_rr continuous
    at a, σ_rr(b) = −p."""
    K1, K2 = E1 / (3 * (1 - 2 * nu1)), E2 / (3 * (1 - 2 * nu2))
    G2 = E2 / (2 * (1 + nu2))
    M = np.array([[a, -a, -1 / a**2], [3 * K1, -3 * K2, 4 * G2 / a**3], [0.0, 3 * K2, -4 * G2 / b**3]])
    A1, A2, B2 = np.linalg.solve(M, [0.0, 0.0, -p])
    return A2 * b + B2 / b**2


def pressed(points, tets, E, nu, p):
    """P2 displacement of the ball under external pressure p (pmask's assembly, scikit-fem's consistent
    pressure load), held only against the six rigid motions (a statically determinate set of dofs: the load is
    self-equilibrated, so they take no force)."""
    from skfem import ElementTetP2, ElementVector, FacetBasis, LinearForm, MeshTet, asm
    from skfem.helpers import dot

    d = P2().discretise(points, tets)
    K = assembly.stiffness(points, tets, E, nu, order=2, edges=d.edges, n_nodes=d.n_nodes).tocsc()
    mesh = MeshTet(np.ascontiguousarray(points.T), np.ascontiguousarray(tets.T))
    fb = FacetBasis(mesh, ElementVector(ElementTetP2()), facets=mesh.boundary_facets(), intorder=4)

    @LinearForm
    def load(v, w):
        return -p * dot(w.n, v)

    f = asm(load, fb)
    r = np.linalg.norm(points, axis=1)
    c = int(np.argmin(r))
    x_axis = int(np.argmin(np.linalg.norm(points - [0.5 * r.max(), 0, 0], axis=1)))
    y_axis = int(np.argmin(np.linalg.norm(points - [0, 0.5 * r.max(), 0], axis=1)))
    held = np.array([3 * c, 3 * c + 1, 3 * c + 2, 3 * x_axis + 1, 3 * x_axis + 2, 3 * y_axis + 2])
    free = np.setdiff1d(np.arange(K.shape[0]), held)
    u = np.zeros(K.shape[0])
    u[free] = spd_lu(K[free][:, free]).solve(f[free])
    U = u[:3 * len(points)].reshape(-1, 3)
    outer = r > 0.999 * r.max()
    return float(np.mean(np.einsum("ij,ij->i", U[outer], points[outer] / r[outer, None]))), u


@pytest.fixture(scope="module")
def ball():
    return composite_sphere(0.005, 0.01, 0.0018)


def test_a_stiff_core_in_a_soft_ball_meets_the_lame_solution(ball):
    """A core 5x stiffer (radius 5 mm) bonded in a 10 mm ball under 100 Pa of external pressure: the mean radial
    displacement of the outer surface within 1 % of the closed form with P2 at h = 1.8 mm (the issue's bound),
    and equal to a single material's to round-off when the two moduli are equal."""
    points, tets, core = ball
    E = np.where(core, 5e4, 1e4)
    nu = np.where(core, 0.45, 0.45)
    u_fe, _ = pressed(points, tets, E, nu, 100.0)
    u_exact = lame_composite(0.005, 0.01, 5e4, 0.45, 1e4, 0.45, 100.0)
    assert u_exact < 0 and abs(u_fe / u_exact - 1) < 0.01, (u_fe, u_exact)
    soft = lame_composite(0.005, 0.01, 1e4, 0.45, 1e4, 0.45, 100.0)
    assert abs(u_exact) < 0.9 * abs(soft)  # the core is felt: the ball yields less than a uniform one
    _, u_same = pressed(points, tets, np.full(len(tets), 1e4), np.full(len(tets), 0.45), 100.0)
    _, u_uniform = pressed(points, tets, 1e4, 0.45, 100.0)
    assert np.abs(u_same - u_uniform).max() <= 1e-12 * np.abs(u_uniform).max()


@pytest.fixture(scope="module")
def palpation(tmp_path_factory):
    """The palpation block (a 10x stiffer ball 10 mm under the upper face), built as a user would."""
    from conftest import build
    from pmask.pipeline.stages import Spec

    return build(tmp_path_factory, "palpation", Spec(model="palpation"))


def test_greens_functions_with_a_mass_equal_a_full_solve(palpation):
    """Ξ of the block with its stiffer ball equals independent full finite-element solves (scikit-fem's
    assembly with each tetrahedron's material read back from the artifact's record, SuperLU) to round-off,
    and the artifact records the region, its material and its volume."""
    from conftest import FullSystem, relerr
    from pmask.runtime.artifact import read_artifact

    d = read_artifact(palpation)
    mat = d["attrs"]["material"]
    (inc,) = mat["regions"]
    assert inc["name"] == "inclusion" and inc["E"] == 10 * mat["E"] and inc["tets"] > 0
    assert 0.5 * (4 / 3 * np.pi * 0.005 ** 3) < inc["volume_m3"] < 4 / 3 * np.pi * 0.005 ** 3  # faceted, coarse
    contact = d["surface/contact"]
    cols = np.sort(np.random.default_rng(3).choice(len(contact), 3, replace=False))
    tractions = np.zeros((len(d["surface/points"]), 3, 9))
    for k, c in enumerate(cols):
        for comp in range(3):
            tractions[contact[c], comp, 3 * k + comp] = 1.0
    u, _ = FullSystem(palpation).solve(tractions)
    U = u[d["surface/volume_index"][contact]]
    for k, c in enumerate(cols):
        assert relerr(d["greens/Xi"][:, 3 * c:3 * c + 3], U[:, :, 3 * k:3 * k + 3].reshape(-1, 3)) < 1e-8


def test_the_mass_is_felt_through_the_surface(palpation, tmp_path):
    """Pressed from above over the ball, the normal stiffness is higher than the same block's without the mass
    (--materials inclusion at the tissue's material) at the same points: measured 1.15x for a ball of 5 mm
    radius 10 mm deep (5 mm of tissue over it), 10x stiffer, on the default 4 mm mesh."""
    from pmask.pipeline.stages import Spec, run
    from pmask.runtime import Model

    def kzz(path):
        m = Model.load(path)
        s = m.stiffness("linear", 2 * m.mean_edge_length)
        top = m.contact[m.core][m.points[m.contact[m.core], 2] > -1e-6]
        r = np.hypot(*m.points[top, :2].T)
        return s.K_vertex[top][:, 2, 2], r

    k, r = kzz(palpation)
    plain = tmp_path / "plain.h5"
    run(Spec(model="palpation", materials="inclusion:1e4:0.45"), plain)
    k0, r0 = kzz(plain)
    over, without = k[r < 0.003].mean(), k0[r0 < 0.003].mean()
    assert over > 1.1 * without, (over, without)


def test_materials_by_region_refusals_are_one_line(tmp_path, capsys):
    from pmask.pipeline.cli import main

    for materials, message in (("tumour:1e5:0.45", "no volume region named 'tumour' (regions in this mesh: "
                                                   "inclusion, tissue)"),
                               ("inclusion:1e5", "give NAME:E:nu"),
                               ("inclusion:1e5:0.6", "Poisson"),
                               ("inclusion:1e5:0.45,inclusion:2e5:0.45", "twice")):
        code = main(["precompute", "palpation", "--materials", materials, "-o", str(tmp_path / "x.h5")])
        err = capsys.readouterr().err
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_a_volume_meshs_physical_volumes_take_their_materials(tmp_path):
    """A --volume mesh whose physical volumes name a core and a shell: `--materials core:E:nu` puts the core's
    material on exactly the core's tetrahedra (the artifact's record), the shell keeps -E/--nu."""
    from conftest import gmsh_volume
    from pmask.pipeline.cli import main
    from pmask.runtime.artifact import read_artifact

    def cored(gmsh):
        box = gmsh.model.occ.addBox(-0.02, -0.02, -0.02, 0.04, 0.04, 0.04)
        ball = gmsh.model.occ.addSphere(0, 0, 0, 0.008)
        gmsh.model.occ.fragment([(3, box)], [(3, ball)])
        gmsh.model.occ.synchronize()
        vols = [t for _, t in gmsh.model.getEntities(3)]
        core = [t for t in vols if gmsh.model.getBoundingBox(3, t)[3] < 0.01]
        bottom = [t for _, t in gmsh.model.getEntities(2) if gmsh.model.getBoundingBox(2, t)[5] < -0.02 + 1e-5]
        return {"core": (3, core), "shell": (3, [t for t in vols if t not in core]), "support": (2, bottom)}

    msh = gmsh_volume(tmp_path / "cored.msh", cored, 0.006)
    out = tmp_path / "cored.h5"
    assert main(["-q", "precompute", "cored", "--volume", str(msh), "--fixed", "group:support", "-E", "2e4",
                 "--materials", "core:2e5:0.4", "-o", str(out)]) == 0
    d = read_artifact(out)
    (reg,) = d["attrs"]["material"]["regions"]
    label = d["volume/material_region"]
    P, T = d["volume/points"], d["volume/tets"]
    r = np.linalg.norm(P[T].mean(axis=1), axis=1)  # tet centroids' distance from the ball's centre
    assert reg["name"] == "core" and reg["E"] == 2e5 and reg["nu"] == 0.4 and d["attrs"]["material"]["E"] == 2e4
    assert reg["tets"] == int(np.sum(label == 0)) and np.all(r[label == 0] < 0.008)  # inside the faceted ball
    assert np.mean(r[label == -1] > 0.008) > 0.9  # the shell's (a few lie in the sliver between facets and ball)
    assert 0.8 < reg["volume_m3"] / (4 / 3 * np.pi * 0.008 ** 3) < 1.0


# ------------------------------------------------------------------ --inclusion: a user's surfaces, meshed conformally
def _ball_stl(path, radius_mm, centre=(0.0, 0.0, 0.0), sub=3):
    import meshio
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=sub, radius=radius_mm)
    meshio.write_points_cells(path, np.asarray(s.vertices) + centre, [("triangle", np.asarray(s.faces))])
    return str(path)


def test_an_inclusion_surface_is_meshed_conformally_and_meets_the_lame_solution(tmp_path):
    """The tumour issue's item 1 from a user's files: a 10 mm ball's surface and a 5 mm ball's inside it
    (`--surface outer.stl --inclusion inner.stl --inclusion-E 5e4 -E 1e4`).  The artifact's own volume mesh has
    the inclusion's tetrahedra inside its surface and the body's outside (conformal: no tetrahedron straddles
    the interface, up to the remesh's chords, 0.1 h), the artifact records the region's material, and the
    pressed ball on that mesh meets the composite sphere's closed form within 1 % (the issue's bound; measured
    0.4 %, the icosphere's facets and the remesh's chords of the 5 mm interface included)."""
    from pmask.pipeline.cli import main
    from pmask.runtime import Model
    from pmask.runtime.artifact import read_artifact

    outer, inner = _ball_stl(tmp_path / "outer.stl", 10.0, sub=4), _ball_stl(tmp_path / "inner.stl", 5.0)
    out = tmp_path / "ball.h5"
    assert main(["precompute", "--surface", outer, "--inclusion", inner, "--inclusion-E", "5e4", "-E", "1e4",
                 "--units", "mm", "--edge-length", "1.8", "--fixed", "z<-9", "-o", str(out)]) == 0
    a = read_artifact(out)
    region = a["volume/material_region"]
    assert [r["name"] for r in a["attrs"]["material"]["regions"]] == ["inclusion"]
    assert a["attrs"]["material"]["regions"][0]["E"] == 5e4
    p, t = Model.load(out).volume()
    r = np.linalg.norm(p[t], axis=2)  # each tetrahedron's corners' radii
    assert r[region >= 0].max() <= 0.005 * (1 + 1e-9) and r[region < 0].min() >= 0.005 * (1 - 0.1 * 1.8 / 5.0)
    u_fe, _ = pressed(p, t, np.where(region >= 0, 5e4, 1e4), np.full(len(t), 0.45), 100.0)
    u_exact = lame_composite(0.005, 0.01, 5e4, 0.45, 1e4, 0.45, 100.0)
    assert abs(u_fe / u_exact - 1) < 0.01, (u_fe, u_exact)


@pytest.mark.parametrize("inner, modulus, says", [
    ((4.0, (7.0, 0.0, 0.0)), True, "crosses the outer surface"),
    ((4.0, (5.5, 0.0, 0.0)), True, "touches the outer surface"),
    ((0.4, (0.0, 0.0, 0.0)), True, "thinner than an element"),
    ((4.0, (0.0, 0.0, 0.0)), False, "needs --inclusion-E"),
])
def test_inclusion_refusals_are_one_line(tmp_path, capsys, inner, modulus, says):
    """An inclusion that crosses the body's surface, touches it (less than half an edge of tissue between:
    where it meets the support too), is thinner than an element, or has no modulus: one line saying which,
    before any meshing, and no artifact."""
    from pmask.pipeline.cli import main

    outer = _ball_stl(tmp_path / "outer.stl", 10.0)
    inc = _ball_stl(tmp_path / "inner.stl", inner[0], inner[1], sub=2)
    extra = ["--inclusion-E", "5e4"] if modulus else []
    code = main(["precompute", "--surface", outer, "--inclusion", inc, *extra, "--units", "mm", "--edge-length",
                 "2", "--fixed", "z<-9", "-o", str(tmp_path / "x.h5")])
    err = capsys.readouterr().err
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "x.h5").exists()


def test_two_inclusions_that_overlap_are_refused(tmp_path, capsys):
    from pmask.pipeline.cli import main

    outer = _ball_stl(tmp_path / "outer.stl", 10.0)
    a = _ball_stl(tmp_path / "a.stl", 3.0, (-1.5, 0.0, 0.0), sub=2)
    b = _ball_stl(tmp_path / "b.stl", 3.0, (1.5, 0.0, 0.0), sub=2)
    code = main(["precompute", "--surface", outer, "--inclusion", a, "--inclusion", b, "--inclusion-E", "5e4",
                 "--units", "mm", "--edge-length", "2", "--fixed", "z<-9", "-o", str(tmp_path / "x.h5")])
    err = capsys.readouterr().err
    assert code == 2 and "overlap" in err, err


# ------------------------------------------------------------------ the liver with a mass (a model)
@pytest.fixture(scope="module")
def livers(tmp_path_factory):
    """The built-in liver, coarse (7.5 mm), with its 5x mass and with the mass at the tissue's modulus."""
    from conftest import build
    from pmask.pipeline.stages import Spec

    return {c: build(tmp_path_factory, f"liver{c:g}", Spec(model="liver", params={"size": 0.0075, "contrast": c}))
            for c in (5.0, 1.0)}


def test_the_liver_model_has_its_mass_and_a_press_over_it_is_stiffer(livers, tmp_path):
    """`pmask precompute liver`: the artifact records the mass's region (25 kPa in 5 kPa tissue) where the
    model puts it (every corner of its tetrahedra within the 10 mm ball centred 20 mm under the surface at
    x = 20 mm, the tissue's outside it) and the figure's press over the mass indents
    less than the same press at the mirrored point (x -> -x: the lobe is symmetric), by more than 5 %
    (measured 8 % at this size).  With the mass at the tissue's modulus the two presses agree within 3 %
    (the mesh is not mirror-symmetric): the difference is the mass, not the geometry."""
    from pmask.pipeline.figures import mass_figure
    from pmask.runtime import Model

    m = Model.load(livers[5.0])
    (region,) = m.attrs["material"]["regions"]
    assert region["name"] == "mass" and region["E"] == 5 * m.attrs["material"]["E"] == 2.5e4
    from pmask.runtime.artifact import MATERIALS, VOLUME, read_artifact

    a = read_artifact(livers[5.0], datasets=VOLUME + MATERIALS)
    centre = np.array([0.02, 0.0, 0.04 * np.sqrt(1 - (0.02 / 0.075) ** 2) - 0.02])
    r = np.linalg.norm(a["volume/points"][a["volume/tets"]] - centre, axis=2)
    inside = a["volume/material_region"] == 0
    assert inside.sum() == region["tets"] and r[inside].max() <= 0.01 * (1 + 1e-9)
    # the tissue's corners on or outside the ball (its interface nodes lie on the sphere; a mislabelled
    # tetrahedron inside would have a corner near the centre, well under 0.7 r)
    assert r[~inside].min() >= 0.01 * (1 - 0.3)
    _, stiff = mass_figure(m, tmp_path / "mass.png")
    assert (tmp_path / "mass.png").stat().st_size > 10_000
    assert stiff["ratio"] < 0.95, stiff
    _, plain = mass_figure(Model.load(livers[1.0]), tmp_path / "plain.png")
    assert abs(plain["ratio"] - 1) < 0.03, plain
