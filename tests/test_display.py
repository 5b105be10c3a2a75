"""The display surface at the scan's resolution (the scans issue's item 6): the user's surface kept in the
artifact, embedded in the simulation surface and deformed with it, in Python, in C and in the viewer."""
from __future__ import annotations

import numpy as np
import pytest

from pmask.pipeline.stages import Spec, run
from pmask.precompute.meshing import surface_distance
from pmask.runtime import HapticContact, Model
from pmask.runtime.contact import tracking
from test_viewer import browser  # noqa: F401  (the headless chromium fixture)


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """A 20 mm ball exported as a 20,480-triangle "scan", precomputed at 4 mm edges (about 500 surface
    vertices): the display surface is 40x finer than the simulation's."""
    import meshio
    import trimesh

    d = tmp_path_factory.mktemp("scan")
    s = trimesh.creation.icosphere(subdivisions=5, radius=20.0)
    meshio.write_points_cells(d / "scan.stl", np.asarray(s.vertices), [("triangle", np.asarray(s.faces))])
    run(Spec(model="scan", surface=str(d / "scan.stl"), units="mm", edge_length=4.0, fixed="z<-17"), d / "scan.h5")
    return Model.load(d / "scan.h5"), np.asarray(s.vertices) * 1e-3, np.asarray(s.faces)


def test_laid_onto_another_rest_the_scan_meets_it_at_a_contact_and_keeps_its_shape_away(scan):
    """A display surface laid onto the simulation surface drawn elsewhere (DisplaySurface.on: the contact surface
    rounds a mesh's creases, and the mesh is drawn where it has its vertices): its embedding's foot plus the new
    lift is the scan's vertex (to round-off); next to a contact (w = 1) the deformed scan lies on the rest surface
    plus u, a mask radius away it is the scan plus u, as before."""
    model, _, _ = scan
    ds = model.display()
    rng = np.random.default_rng(3)
    rest = model.points + rng.normal(scale=2e-4, size=model.points.shape)
    on = ds.on(rest)
    assert np.abs(np.einsum("dk,dkc->dc", on.bary, rest[on.vertices]) + on.lift - on.points).max() <= 1e-15
    u = rng.normal(scale=1e-3, size=model.points.shape)
    x, r = ds.points[0], 0.004
    shown = on.deform(u, [x], r)
    d = np.linalg.norm(ds.points - x, axis=1)
    near, far = d <= 1e-4 * r, d >= r
    assert near.any() and far.any()
    foot = np.einsum("dk,dkc->dc", ds.bary, (rest + u)[ds.vertices])
    assert np.abs(shown[near] - foot[near]).max() <= 1e-12
    assert np.abs(shown[far] - ds.deform(u)[far]).max() <= 1e-15


def test_the_scan_is_kept_and_embedded_at_its_closest_points(scan):
    """Every vertex of the scan is kept (in metres) and embedded at its closest point on the simulation
    surface: the foot Σ b P plus the lift gives the vertex back (to round-off), the lift's length is the
    vertex's distance to the simulation surface computed independently (trimesh's closest point over every
    candidate triangle, 1e-9 m), and no display triangle folds on a ball (its curvature radius, 20 mm, is 5
    edges)."""
    model, points, faces = scan
    ds = model.display()
    assert model.attrs["display"]["triangles"] == len(faces) and len(ds.points) == len(points)
    assert model.attrs["display"]["folded"] == 0
    foot = np.einsum("dk,dkc->dc", ds.bary, model.points[ds.vertices])
    assert np.abs(foot + ds.lift - ds.points).max() <= 1e-12
    assert np.all(ds.bary >= 0) and np.allclose(ds.bary.sum(axis=1), 1.0)
    d = surface_distance(ds.points, model.points, model.triangles, candidates=64)
    assert np.abs(np.linalg.norm(ds.lift, axis=1) - d).max() <= 1e-9
    # the display surface is the scan (the same points up to the order np.unique gives them)
    assert np.allclose(np.sort(ds.points, axis=0), np.sort(points, axis=0))


def _press(model, depth=3e-3):
    stiff = model.stiffness("linear", model.default_radius)
    h = HapticContact(stiff)
    top = model.points[np.argmax(model.points[:, 2])]
    for z in np.linspace(2e-3, -depth, 400):
        _, status = h.step(top + [0.0, 0.0, z])
    return h, stiff, top + [0.0, 0.0, -depth], status


def test_the_pressed_scan_meets_the_tool_and_keeps_its_detail_away_from_it(scan):
    """A probe pressed 3 mm into the top: the deformed scan lies within 0.03 mm of the deformed simulation
    surface's own distance to the probe (the simulation surface meets the tool up to its display forces'
    interpolation, measured 0.09 mm here; without laying the scan onto it the gap grows by its lift, measured
    0.16 mm), and within the scans issue's 0.1 mm of the tool (measured 0.073 mm; pressed 5 mm, a quarter of the
    ball's radius, 0.18 mm, of which 0.165 mm is the simulation surface's own gap: the linear model that deep);
    a mask radius away from the contact the scan moves exactly as the simulation surface under it
    (x' − x = Σ b u, to round-off)."""
    model, _, _ = scan
    ds = model.display()
    h, stiff, probe, status = _press(model)
    assert int(status) == 1  # CONTACT
    u = h.deformation()
    proxy = np.asarray(h.proxy)
    x = ds.deform(u, [proxy], stiff.masks.radius)
    gap_sim = surface_distance(probe[None], model.points + u, model.triangles)[0]
    gap_scan = surface_distance(probe[None], x, ds.triangles)[0]
    assert gap_scan <= gap_sim + 3e-5, (gap_scan, gap_sim)
    assert gap_scan <= 1e-4, gap_scan
    far = np.linalg.norm(ds.points - proxy, axis=1) > stiff.masks.radius
    carried = np.einsum("dk,dkc->dc", ds.bary, u[ds.vertices])
    assert np.abs((x - ds.points)[far] - carried[far]).max() <= 1e-15
    assert np.linalg.norm(x - ds.points, axis=1).max() > 1e-3  # it moved


def test_the_native_core_deforms_the_scan_as_the_python_runtime_does(scan, tmp_path):
    """pm_display_deform (C, through a runtime table exported with the display surface) equals
    DisplaySurface.deform to 1e-12 relative (the same sums in the same order; measured: bit for bit)."""
    from pmask.runtime import servo
    from pmask.runtime.table import export_table, read_table

    if not servo.available():
        pytest.skip("the native core is not built")
    model, _, _ = scan
    path = export_table(model, tmp_path / "scan.tbl", zeta=False)
    assert read_table(path)["display_points"].shape == model.display().points.shape
    table = servo.load_table(path)
    ds = model.display()
    rng = np.random.default_rng(1)
    u = rng.normal(size=(len(model.points), 3)) * 1e-3
    contacts = [model.points[3], model.points[200]]
    for c, r in ((contacts, 0.008), ((), 0.0)):
        a, b = ds.deform(u, c, r), servo.display_deform(table, u, c, r)
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max()


def test_no_display_for_models_and_when_asked(scan, kidney_small, tmp_path):
    """A built-in model has no scan to keep; --no-display leaves it out of a --surface artifact."""
    model, _, _ = scan
    assert Model.load(kidney_small).display() is None
    out = tmp_path / "plain.h5"
    run(Spec(model="scan", surface=model.attrs["parameters"]["surface"], units="mm", edge_length=8.0, fixed="z<-17",
             display=False), out)
    assert Model.load(out).display() is None and "display" not in Model.load(out).attrs


@pytest.fixture(scope="module")
def scan_server(scan):
    import threading

    from pmask.viewer.server import ViewerSession, make_server

    model, _, _ = scan
    session = ViewerSession(model)
    srv = make_server(session, "127.0.0.1", 0)
    threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
    yield session, f"http://127.0.0.1:{srv.server_address[1]}/"
    srv.shutdown()
    srv.server_close()
    session.close()


def test_the_viewer_shows_the_scan_and_deforms_it_as_the_runtime_does(browser, scan, scan_server):
    """`pmask view` of an artifact with a scan draws the scan (not the simulation mesh) and deforms it in the
    page from the simulation surface's displacement it already receives: pressed and held, the page's scan
    vertices near the contact are where DisplaySurface.deform puts them for the servo's deformation (1e-6 m:
    float32 on the wire and in WebGL's buffers; the servo settles on a held probe)."""
    import time

    from selenium.webdriver.common.action_chains import ActionChains

    from test_viewer import _drag, _open

    model, _, _ = scan
    session, url = scan_server
    ds = model.display()
    _open(browser, url)
    assert browser.execute_script("return window.pmaskView.scanVertices()") == len(ds.points)
    # the contact vertex drawn nearest the middle of the view, facing the camera (on a ball every vertex is
    # as far from the centroid, which is how test_viewer chooses one on the kidney)
    size = browser.execute_script("return [window.innerWidth, window.innerHeight]")
    core = model.contact[model.core]
    xy = np.array([browser.execute_script(f"return window.pmaskView.screenOf({int(i)})") for i in core])
    order = core[np.argsort(np.linalg.norm(xy - [0.5 * size[0], 0.5 * size[1]], axis=1))]
    v = next(int(i) for i in order if browser.execute_script(f"return window.pmaskView.facing({int(i)})"))
    _drag(browser, browser.execute_script(f"return window.pmaskView.screenOf({v})"), slide=(0, 0))
    try:
        time.sleep(1.5)  # pressed and held: the servo and the page settle
        c = session.contacts
        st = c.states[0]
        assert int(st.status) == 1, browser.find_element("id", "status0").text
        u = c.deformation()
        proxy = np.asarray(tracking.point(c.surface, st.tri, *st.b))  # as the server sends it
        want = ds.on(session.rest).deform(u, [proxy], session.radius)  # (a ball: no crease to round, ds itself)
        near = np.argsort(np.linalg.norm(ds.points - proxy, axis=1))[:20]
        shown = np.array([browser.execute_script(f"return window.pmaskView.scanPosition({int(d)})") for d in near])
    finally:
        ActionChains(browser).release().perform()
    assert np.abs(shown - want[near]).max() <= 1e-6
    assert np.linalg.norm(want[near] - ds.points[near], axis=1).max() > 1e-4  # they moved
