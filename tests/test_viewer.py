"""``pmask view``: the page in a real browser against the runtime, and a server that hostile input cannot stop.

The browser tests drive Debian's chromium headless through selenium (``make system-deps`` installs it);
without it they skip, except where ``PMASK_REQUIRE_BROWSER=1`` (CI) makes a missing browser a failure.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pmask.runtime import Contacts, Model
from pmask.viewer.server import N_PROBES, ViewerSession, make_server

CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")


@pytest.fixture(scope="module")
def session(kidney_small):
    s = ViewerSession(Model.load(kidney_small))
    yield s
    s.close()


@pytest.fixture(scope="module")
def server(session):
    srv = make_server(session, "127.0.0.1", 0)
    t = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    t.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}/", srv.server_address[1]
    srv.shutdown()
    srv.server_close()


@pytest.fixture(scope="module")
def browser():
    if not (CHROMIUM and CHROMEDRIVER):
        if os.environ.get("PMASK_REQUIRE_BROWSER", "") not in ("", "0"):
            pytest.fail("PMASK_REQUIRE_BROWSER is set but chromium/chromedriver are missing (make system-deps)")
        pytest.skip("no chromium + chromedriver (make system-deps installs them)")
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    opts = Options()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1100,800",
              "--enable-unsafe-swiftshader", "--use-angle=swiftshader"):
        opts.add_argument(a)
    d = webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))
    yield d
    d.quit()


def _until(ready, what: str, seconds: float = 60.0) -> None:
    """Wait until ``ready()`` is true, or fail saying what never came.  A radius change rebuilds every K_i and the
    contact surface (0.8 s median on the default kidney by the bench); 60 s, because one CI run here, with the
    other xdist process busy, did not see it within the ~12 s of the 200 polls this replaced."""
    deadline = time.monotonic() + seconds
    while not ready():
        if time.monotonic() > deadline:
            raise AssertionError(f"the page never applied {what} within {seconds:.0f} s")
        time.sleep(0.05)


def _open(browser, url):
    """Load the page and wait until it runs and owns the probes (a page the previous test left pressing, e.g.
    with a shift-drag probe on the body, owns them until its lease lapses, OWNER_LEASE after it went away)."""
    browser.get(url)
    for _ in range(200):
        if browser.execute_script("return document.body.dataset.ready === '1' && document.body.dataset.owner === '1'"):
            return
        time.sleep(0.05)
    raise AssertionError("the page did not start or never owned the probes: "
                         + browser.find_element("id", "error").text)


def _screen_vertices(browser, model, count, min_sep):
    """Core contact vertices that face the camera, far from the support and (several) from each other."""
    P = model.points
    core = model.contact[model.core]
    far = core[np.min(np.linalg.norm(P[core][:, None] - P[model.fixed][None], axis=2), axis=1) > 4 * model.mean_edge_length]
    centre = P.mean(axis=0)
    chosen = []
    for i in far[np.argsort(np.linalg.norm(P[far] - centre, axis=1))]:
        if any(np.linalg.norm(P[i] - P[j]) < min_sep for j in chosen):
            continue
        if browser.execute_script(f"return window.pmaskView.facing({int(i)})"):
            chosen.append(int(i))
            if len(chosen) == count:
                return chosen
    raise AssertionError("no vertex of the contact region faces the camera")


def _steady(browser, element_id, attr, tries=60):
    """The page's value once two reads 0.25 s apart agree (the servo has settled on a held probe)."""
    last = None
    for _ in range(tries):
        el = browser.find_element("id", element_id)
        now = (el.text, el.get_attribute(attr))
        if now == last:
            return now
        last = now
        time.sleep(0.25)
    raise AssertionError(f"{element_id} never settled: {last}")


def _displayed_force(browser, k):
    text, _ = _steady(browser, f"force{k}", "data-force")
    # "|f| N (fx, fy, fz)": what the page shows, to 6 significant digits
    inner = text.split("(", 1)[1].rstrip(")")
    return np.array([float(x) for x in inner.split(",")]), browser.find_element("id", f"status{k}").text


def _reference(session, targets, approach):
    """The runtime's own forces for these probe positions, by a fresh Contacts (Python engine) that comes in
    from outside along ``approach`` and holds still for 1.5 s of ticks."""
    c = Contacts(session.stiffness, N_PROBES, engine="python", max_jump=2.0 * session.diag)
    starts = [session.park if t is None else (np.asarray(t) + a).tolist() for t, a in zip(targets, approach)]
    for s in np.linspace(0.0, 1.0, 300):
        c.step([session.park if t is None else ((1 - s) * np.asarray(a0) + s * np.asarray(t)).tolist()
                for t, a0 in zip(targets, starts)])
    for _ in range(1500):
        forces, statuses = c.step([session.park if t is None else t for t in targets])
    return np.array(forces), [int(x) for x in statuses]


def _drag(browser, xy, shift=False, slide=(24, 10)):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    a = ActionChains(browser, duration=20)
    if shift:
        a.key_down(Keys.SHIFT)
    a.w3c_actions.pointer_action.move_to_location(int(xy[0]), int(xy[1]))
    a.w3c_actions.pointer_action.pointer_down()
    for _ in range(6):  # press, then slide over the surface
        a.w3c_actions.pointer_action.move_by(slide[0] // 6, slide[1] // 6)
    a.perform()
    if shift:
        ActionChains(browser).key_up(Keys.SHIFT).perform()


def _shallow(browser, session, *vertices):
    """Set the page's press depth to 80 % of the least δ_t near the vertices (the depth past which a contact's
    increments keep the stiffness where they began, pmask.runtime.contact.law): shallower, a frictionless
    held probe's force depends on where it is, not on the path that brought it there."""
    from pmask.runtime.contact import ContactSurface, law

    srf = ContactSurface(session.stiffness)
    P = session.model.points
    near = np.flatnonzero(np.min([np.linalg.norm(P - P[v], axis=1) for v in vertices], axis=0)
                          < 3 * session.model.mean_edge_length)
    dt = min(law.increment_depth(srf._dlin[i], srf._k[i], *srf._G[i]) for i in near)
    browser.execute_script(f"document.getElementById('depth').value = {0.8 * dt!r};")


def test_the_force_the_page_shows_is_the_runtimes_for_that_probe(browser, server, session):
    """Drag a probe onto the body and slide, hold, and read the force the panel shows: it equals the force
    a fresh runtime contact gives for the probe position the page reports, to the 6 digits shown (the
    servo is frictionless and the press shallower than δ_t, so a held probe's force depends on where it is,
    not on the path)."""
    url, _ = server
    _open(browser, url)
    m = session.model
    (v,) = _screen_vertices(browser, m, 1, 0.0)
    _shallow(browser, session, v)
    _drag(browser, browser.execute_script(f"return window.pmaskView.screenOf({v})"))
    try:
        f_page, status = _displayed_force(browser, 0)
        probe = json.loads(browser.find_element("id", "probe0").get_attribute("data-probe"))
    finally:
        from selenium.webdriver.common.action_chains import ActionChains
        ActionChains(browser).release().perform()
    assert status == "CONTACT"
    out = 1.5 * m.mean_edge_length * _outward(m, probe)
    f_ref, statuses = _reference(session, [probe, None], [out, None])
    assert statuses[0] == 1
    assert np.linalg.norm(f_ref[0]) > 1e-2  # a real press: newtons, not round-off
    # 6 significant digits per shown component
    assert np.allclose(f_page, f_ref[0], rtol=1e-5, atol=1e-5 * np.linalg.norm(f_ref[0]))


def test_what_the_page_hides_is_not_shown(browser, server):
    """Every element the page marks hidden is not drawn: `#panel label {display: block}` once overrode the
    attribute, so a model without a display surface showed its checkbox, "the scan's surface ( triangles)" (in
    the README's screenshot); the small kidney has no display surface, so that box is among them."""
    url, _ = server
    _open(browser, url)
    shown = browser.execute_script(
        "return [...document.querySelectorAll('[hidden]')].filter(e => getComputedStyle(e).display !== 'none')"
        ".map(e => e.id || e.tagName)")
    assert browser.execute_script("return document.getElementById('scanBox').hidden")
    assert shown == []


def test_after_a_release_the_surface_springs_back(browser, server, session):
    """#28: after a release the surface often stayed deformed: the page asked for the deformation once, and
    the reply raced the servo's release.  It now asks until the servo reports the surface flat: pressed, the
    shown surface is displaced; released, it returns to the rest shape within a second."""
    from selenium.webdriver.common.action_chains import ActionChains

    url, _ = server
    _open(browser, url)
    m = session.model
    (v,) = _screen_vertices(browser, m, 1, 0.0)
    _drag(browser, browser.execute_script(f"return window.pmaskView.screenOf({v})"), slide=(0, 0))
    try:
        pressed = 0.0
        for _ in range(60):
            pressed = max(pressed, browser.execute_script("return window.pmaskView.displacement()"))
            time.sleep(0.05)
    finally:
        ActionChains(browser).release().perform()
    assert pressed > 0.1 * m.mean_edge_length
    for _ in range(40):
        time.sleep(0.05)
        if browser.execute_script("return window.pmaskView.displacement()") == 0.0:
            break
    assert browser.execute_script("return window.pmaskView.displacement()") == 0.0


def test_an_idle_page_leaves_the_cores_alone_and_a_press_draws(browser, server, session):
    """An idle page drew every frame and asked the server every frame (49 frames/s of software WebGL on these
    2 cores, most of one core, so a radius change took 3x as long with the page open).  Idle now, it draws
    nothing new and asks 10 times a second (IDLE_POLL_MS = 100 ms: between 5 and 12 answers in a second, a
    lenient band for a loaded machine's timers); a press draws again, a frame per changed reply."""
    from selenium.webdriver.common.action_chains import ActionChains

    url, _ = server
    _open(browser, url)
    time.sleep(1.0)  # the first frames (the colours, the camera) are drawn
    count = "return [window.pmaskView.stats.drawn, window.pmaskView.stats.reads]"
    d0, r0 = browser.execute_script(count)
    time.sleep(2.0)
    d1, r1 = browser.execute_script(count)
    assert d1 - d0 == 0, d1 - d0
    assert 10 <= r1 - r0 <= 24, r1 - r0
    (v,) = _screen_vertices(browser, session.model, 1, 0.0)
    _drag(browser, browser.execute_script(f"return window.pmaskView.screenOf({v})"))
    try:
        time.sleep(0.3)
        d2, r2 = browser.execute_script(count)
    finally:
        ActionChains(browser).release().perform()
    assert d2 - d1 >= 5 and r2 - r1 >= 5, (d2 - d1, r2 - r1)


def test_a_stopped_server_is_shown_and_not_hammered(browser, kidney_small):
    """#28: when the server stopped, the page kept showing the last force and retried every frame (66
    console errors in a few seconds).  Now it shows NO SERVER and no force, and backs off (100 ms doubling to
    2 s): at most a dozen attempts in 4 s.  (The server is `pmask view` in its own process, killed as a
    user's Ctrl-C or a crash ends it: its connections die with it.)"""
    p = subprocess.Popen(_pmask("view", str(kidney_small), "--port", "0"), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        url = [p.stdout.readline() for _ in range(3)][2].split()[1]
        _open(browser, url)
        time.sleep(0.5)
        p.kill()
        p.communicate(timeout=30)
        time.sleep(0.5)
        before = browser.execute_script("return window.pmaskView.stats.failures")
        time.sleep(4.0)
        failures = browser.execute_script("return window.pmaskView.stats.failures") - before
    finally:
        if p.poll() is None:
            p.kill()
    assert 1 <= failures <= 12, failures
    assert browser.find_element("id", "status0").text == "NO SERVER"
    assert browser.find_element("id", "force0").text == "—"
    assert "retrying" in browser.find_element("id", "error").text


def test_two_probes_are_coupled_through_the_body(browser, server, session):
    """Shift-drag leaves a second probe on the body; dragging the first next to it, both forces shown are
    the runtime's coupled two-contact solve for the two probe positions, and they differ from what two
    independent contacts would give (the coupling is visible).  Both press shallower than δ_t (_shallow), so
    the forces depend on where the probes are, not on the path: pressed deeper, the page's press and the
    reference's approach froze the stiffness at different points, by up to 0.9 % of the force when the machine
    was loaded (the page's samples sparser), near the coupling's own size."""
    url, _ = server
    _open(browser, url)
    m = session.model
    v1, v2 = _screen_vertices(browser, m, 2, 3.0 * m.mean_edge_length)
    _shallow(browser, session, v1, v2)
    _drag(browser, browser.execute_script(f"return window.pmaskView.screenOf({v2})"), shift=True, slide=(0, 0))
    from selenium.webdriver.common.action_chains import ActionChains
    ActionChains(browser).release().perform()  # probe 2 stays pressed
    _drag(browser, browser.execute_script(f"return window.pmaskView.screenOf({v1})"), slide=(0, 0))
    try:
        f0, s0 = _displayed_force(browser, 0)
        f1, s1 = _displayed_force(browser, 1)
        probes = [json.loads(browser.find_element("id", f"probe{k}").get_attribute("data-probe")) for k in (0, 1)]
    finally:
        ActionChains(browser).release().perform()
    assert (s0, s1) == ("CONTACT", "CONTACT")
    out = [1.5 * m.mean_edge_length * _outward(m, p) for p in probes]
    f_ref, statuses = _reference(session, probes, out)
    assert statuses == [1, 1]
    assert min(np.linalg.norm(f) for f in f_ref) > 1e-2  # real presses: newtons, not round-off
    # 6 significant digits per shown component (the coupling is > 1 %, below)
    for f_page, f in zip((f0, f1), f_ref):
        assert np.allclose(f_page, f, rtol=1e-5, atol=1e-5 * np.linalg.norm(f))
    alone = [_reference(session, [p, None], [o, None])[0][0] for p, o in zip(probes, out)]
    assert max(np.linalg.norm(a - f) / np.linalg.norm(f) for a, f in zip(alone, f_ref)) > 0.01


def test_the_radius_slider_rebuilds_the_stiffness_and_its_colour_range(browser, server, session):
    """The End key on the radius slider (a user's keyboard) moves it to its largest radius; the server
    rebuilds every K_i and the colour bar's range becomes the 2nd to 98th percentile of the new masked ‖K_i‖
    over the contact region, computed here from the model directly (the full range, set by the stiff ring at
    the support, left most of the kidney one colour); at the smallest radius the page says how many masks
    fall back to a single vertex."""
    from selenium.webdriver.common.keys import Keys

    url, _ = server
    _open(browser, url)
    lo0 = float(browser.find_element("id", "cmin").get_attribute("data-value"))
    hi0 = float(browser.find_element("id", "cmax").get_attribute("data-value"))
    browser.find_element("id", "radius").send_keys(Keys.END)
    _until(lambda: browser.find_element("id", "radius").get_attribute("data-applied"), "the largest radius")
    r = float(browser.find_element("id", "radius").get_attribute("data-applied"))
    m = session.model
    assert r == pytest.approx(session.radius_range[1], rel=1e-9)
    K = m.stiffness("linear", r).K_vertex[m.contact[m.core]]
    norms = np.linalg.norm(K, ord=2, axis=(1, 2))
    lo = float(browser.find_element("id", "cmin").get_attribute("data-value"))
    hi = float(browser.find_element("id", "cmax").get_attribute("data-value"))
    assert (lo, hi) != (lo0, hi0)
    assert lo == pytest.approx(np.percentile(norms, 2), rel=1e-12)
    assert hi == pytest.approx(np.percentile(norms, 98), rel=1e-12)
    # and the surface is drawn where the new contact surface has the vertices: its rounding of the hilum's lip
    # follows the normals' blending radius, three mask radii (float32 on the page)
    rest = session.rest
    assert np.array_equal(rest, Contacts(m.stiffness("linear", r), 1, engine="python").surface.mesh_points)
    moved = np.linalg.norm(rest - m.points, axis=1)
    v = int(np.argmax(moved))
    assert moved[v] > 1e-4  # (it is rounded: more than 0.1 mm here)
    shown = np.array(browser.execute_script(f"return window.pmaskView.rest({v})"))
    assert np.abs(shown - rest[v]).max() <= 1e-6 * np.abs(rest).max()
    browser.find_element("id", "radius").send_keys(Keys.HOME)
    _until(lambda: float(browser.find_element("id", "radius").get_attribute("data-applied")) != r, "the smallest radius")
    single = session.stiffness.masks.single_vertex
    text = browser.find_element("id", "error").text
    assert (f"{single} of {len(session.stiffness.masks.centres)} masks reach no neighbour" in text) if single else not text, text
    # leave the module's session as the other tests expect it
    session.respond("POST", "/api/radius", json.dumps({"radius": 2.0 * m.mean_edge_length}).encode())


def _outward(model, p):
    """The area-weighted normal at the vertex nearest p (outward for a closed, consistently oriented surface)."""
    P, T = model.points, model.triangles
    i = int(np.argmin(np.linalg.norm(P - np.asarray(p), axis=1)))
    n = np.zeros(3)
    for t in T[(T == i).any(axis=1)]:
        n += np.cross(P[t[1]] - P[t[0]], P[t[2]] - P[t[0]])
    return n / np.linalg.norm(n)


# ---------------------------------------------------------------------------------- hostile input
_json_values = st.recursive(st.none() | st.booleans() | st.floats(allow_nan=True) | st.integers() | st.text(max_size=8),
                            lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=6), kids, max_size=4),
                            max_leaves=20)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(method=st.sampled_from(["GET", "POST", "PUT", "DELETE", "HEAD", "X"]),
       path=st.sampled_from(["/", "/api/probe", "/api/radius", "/api/model", "/api/health", "/../etc/passwd",
                             "/api/probe?x=1", "/static/../../setup.py"]) | st.text(max_size=30).map(lambda s: "/" + s),
       body=st.binary(max_size=200) | _json_values.map(lambda v: json.dumps(v).encode())
       | st.fixed_dictionaries({"probes": _json_values, "deform": _json_values}).map(lambda v: json.dumps(v).encode())
       | st.fixed_dictionaries({"radius": _json_values}).map(lambda v: json.dumps(v).encode()))
def test_no_message_breaks_the_server(session, method, path, body):
    """Random and malformed requests: a 2xx or a 4xx with one line of JSON, never a 500 (our bug), and
    the session still answers afterwards."""
    status, ctype, payload = session.respond(method, path, body)
    assert status < 500, payload
    if status >= 400:
        err = json.loads(payload)["error"]
        assert err and "\n" not in err
    assert session.respond("GET", "/api/health")[0] == 200


def test_the_socket_survives_garbage(server):
    """Raw bytes on the socket: a broken request line, a missing or huge or lying Content-Length, a
    client that stops mid-body, 1 MB of junk; afterwards the server still answers."""
    _, port = server

    def send(data, read=True):
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            try:
                s.sendall(data)
            except OSError:  # the server hung up on junk before reading it all: what it should do
                pass
            if not read:
                return b""
            try:
                s.shutdown(socket.SHUT_WR)
            except OSError:  # already closed by the server
                pass
            try:
                return s.recv(65536)
            except OSError:
                return b""

    answer = send(b"\x00\xff garbage \r\n\r\n")
    assert json.loads(answer.split(b"\r\n\r\n", 1)[-1])["error"].startswith("400 ")  # HTTP/0.9: no headers
    assert b" 411 " in send(b"POST /api/probe HTTP/1.1\r\nHost: x\r\n\r\n{}")
    assert b" 413 " in send(b"POST /api/probe HTTP/1.1\r\nContent-Length: 99999999\r\n\r\n")
    send(b"POST /api/probe HTTP/1.1\r\nContent-Length: 100\r\n\r\n{\"probes\"", read=False)
    send(os.urandom(1 << 20))
    assert b" 400 " in send(b"POST /api/probe HTTP/1.1\r\nContent-Length: 12\r\n\r\n{\"probes\":1}")
    import urllib.request
    assert json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health", timeout=5)) == {"ok": True}


def test_probe_and_radius_messages_are_checked(session):
    bad = [({"probes": [[0, 0]]}, "probes must be a list of 2"), ({"probes": [[0, 0, "a"], None]}, "3 numbers"),
           ({"probes": [[0, 0, 1e999], None]}, "finite"), ({"probes": [None, None], "deform": 1}, "deform"),
           ({"radius": -1}, "radius must lie in"), ({"radius": "big"}, "finite number")]
    for msg, match in bad:
        path = "/api/radius" if "radius" in msg else "/api/probe"
        status, _, payload = session.respond("POST", path, json.dumps(msg).encode())
        assert status == 400 and match in json.loads(payload)["error"], (msg, payload)


def test_the_slider_ends_are_taken_though_they_come_back_a_digit_off(session):
    """A range input's ends come back through the browser's decimal arithmetic: its minimum arrived a last
    digit below the server's and was refused (seen once in CI).  Within RANGE_SLACK of an end is that end;
    beyond it, still refused."""
    from pmask.viewer.server import RANGE_SLACK

    lo, hi = session.radius_range
    try:
        for asked, applied in ((lo * (1 - 1e-12), lo), (hi * (1 + 1e-12), hi)):
            status, _, payload = session.respond("POST", "/api/radius", json.dumps({"radius": asked}).encode())
            assert status == 200 and json.loads(payload)["radius"] == applied == session.radius
        status, _, payload = session.respond("POST", "/api/radius",
                                             json.dumps({"radius": lo - 10 * RANGE_SLACK * hi}).encode())
        assert status == 400 and "radius must lie in" in json.loads(payload)["error"]
    finally:
        session.respond("POST", "/api/radius", json.dumps({"radius": session.model.default_radius}).encode())


def test_a_radius_change_keeps_the_probe_live_and_swaps_at_once(session):
    """The first-hour issue's item 4: a radius change rebuilds K_i, the contact surface and the ζ table while
    the old servo thread keeps answering the probe (it froze for the whole rebuild, 2-17 s); the new radius
    arrives in one piece (every reply has one radius and the force of that radius' servo).  How long a
    rebuild takes is a bench row (bench/viewer_bench.py), not a test."""
    m = session.model
    r0 = session.radius
    r1 = r0 * 1.25 if r0 * 1.25 <= session.radius_range[1] else r0 * 0.8
    done = []
    t = threading.Thread(target=lambda: done.append(session.respond("POST", "/api/radius",
                                                                    json.dumps({"radius": r1}).encode())))
    t.start()
    during, ticks = [], []
    while t.is_alive():
        reply = session.probe([None] * N_PROBES, deform=False)
        if session.build_lock.locked():
            during.append(reply["radius"])
            if reply["radius"] == r0:
                ticks.append(reply["servo"]["ticks"])
        time.sleep(0.002)
    t.join()
    assert done[0][0] == 200 and json.loads(done[0][2])["radius"] == pytest.approx(r1)
    # answered during the rebuild, by the old radius' servo, which kept ticking
    assert len(during) >= 3 and set(during) <= {r0, r1}, (len(during), set(during))
    assert len(ticks) >= 3 and ticks[-1] > ticks[0]
    assert session.probe([None] * N_PROBES, deform=False)["radius"] == pytest.approx(r1)
    session.respond("POST", "/api/radius", json.dumps({"radius": r0}).encode())
    assert session.radius == pytest.approx(r0) and m is session.model


def _press_path(session, v, steps=30):
    """Probe positions from 1.5 mean edges outside vertex v to 1 mean edge inside."""
    m = session.model
    n = _outward(m, m.points[v])
    return [(m.points[v] + (1.5 - 2.5 * s) * m.mean_edge_length * n).tolist() for s in np.linspace(0, 1, steps)]


def test_one_page_owns_the_probes_and_the_others_are_told(session):
    """The first-hour issue's item 4: two open pages fought over one probe (each page's position overwrote
    the other's every frame; one contact flickered, the other page showed it as its own).  The page that
    touches first owns the probes until it lets go (or goes silent for OWNER_LEASE); a second page's probes
    are not applied, and its reply says so and shows the owner's probe."""
    from pmask.viewer.server import OWNER_LEASE

    core = session.model.contact[session.model.core]
    a_path, b_path = _press_path(session, core[0]), _press_path(session, core[len(core) // 2])

    def post(client, probe):
        status, _, body = session.respond("POST", "/api/probe", json.dumps(
            {"probes": [probe] + [None] * (N_PROBES - 1), "client": client}).encode())
        assert status == 200
        return json.loads(body)

    for pa, pb in zip(a_path, b_path):
        ra, rb = post("page-a", pa), post("page-b", pb)
        assert ra["owner"] and not rb["owner"] and "another page is probing" in rb["notice"]
        assert rb["contacts"][0]["probe"] == pa  # b sees a's probe, not its own
        time.sleep(0.003)
    assert post("page-a", a_path[-1])["contacts"][0]["status"] == "CONTACT"
    assert post("page-a", None)["owner"]  # a lets go ...
    assert post("page-b", b_path[0])["owner"]  # ... and b takes over
    time.sleep(1.2 * OWNER_LEASE)  # b goes silent (a closed tab): the lease lapses
    assert post("page-a", a_path[0])["owner"]
    post("page-a", None)
    status, _, body = session.respond("POST", "/api/probe", json.dumps({"probes": [None] * N_PROBES,
                                                                       "client": "x" * 65}).encode())
    assert status == 400 and "client" in json.loads(body)["error"]


def test_a_slow_answer_is_not_the_owners_silence(session, monkeypatch):
    """The lease counts the owner's silence from the server's answer to its last request: an answer that takes
    longer than OWNER_LEASE (here a deformation made slow; the first answer on a new contact surface took 0.14 s
    on the default kidney by hand, and a run of the suite on a loaded machine once lost the owner test above to
    a slow answer) leaves the probes with the page that asked, though a third page that does not touch asks all
    the while (an open tab polls: one that came in as the slow answer ended took the lapsed lease and left the
    probes free), and a second page asking next is told another page is probing.  The lease is 3 s here (1 s in
    use): the second page asks as soon as the first answer is back, but on a loaded CI machine (two test processes
    and a dask test's workers on two cores) more than 1 s once passed between the two, and the lease had lapsed."""
    from pmask.viewer import server

    monkeypatch.setattr(server, "OWNER_LEASE", 3.0)
    OWNER_LEASE = server.OWNER_LEASE

    core = session.model.contact[session.model.core]
    probe = _press_path(session, core[0])[-1]
    deformation = session.contacts.deformation

    def slow():
        time.sleep(1.5 * OWNER_LEASE)
        return deformation()

    def post(client, probe, deform=False):
        status, _, body = session.respond("POST", "/api/probe", json.dumps(
            {"probes": [probe] + [None] * (N_PROBES - 1), "client": client, "deform": deform}).encode())
        assert status == 200
        return json.loads(body)

    done = threading.Event()

    def poll():  # the open tab
        while not done.is_set():
            post("page-c", None)
            time.sleep(0.005)

    monkeypatch.setattr(session.contacts, "deformation", slow)
    tab = threading.Thread(target=poll, daemon=True)
    tab.start()
    try:
        assert post("page-a", probe, deform=True)["owner"]
        rb = post("page-b", probe)
    finally:
        done.set()
        tab.join()
    assert not rb["owner"] and "another page is probing" in rb["notice"]
    assert post("page-a", None)["owner"]  # a lets go, and the probes are free again


def test_a_second_page_shows_who_owns_the_probe(browser, server, session):
    """In Chromium: while another page (here a script posting as one) holds the probe, a drag on this page
    moves nothing, and the page says why (and shows the other page's contact); once the other page lets go,
    the drag is this page's again."""
    import urllib.request

    from selenium.webdriver.common.action_chains import ActionChains

    url, port = server
    _open(browser, url)
    m = session.model
    v, w = _screen_vertices(browser, m, 2, 6 * m.mean_edge_length)
    other = _press_path(session, w)
    stop = threading.Event()

    def other_page():
        k = 0
        while not stop.is_set():
            req = urllib.request.Request(f"http://127.0.0.1:{port}/api/probe", method="POST", data=json.dumps(
                {"probes": [other[min(k, len(other) - 1)]] + [None] * (N_PROBES - 1), "client": "other"}).encode(),
                headers={"Content-Type": "application/json"})
            urllib.request.urlopen(req, timeout=5).read()
            k += 1
            time.sleep(0.02)

    t = threading.Thread(target=other_page)
    t.start()
    try:
        time.sleep(1.0)  # the other page is pressing
        _drag(browser, browser.execute_script(f"return window.pmaskView.screenOf({v})"), slide=(0, 0))
        for _ in range(40):
            if browser.execute_script("return document.body.dataset.owner") == "0":
                break
            time.sleep(0.05)
        assert browser.execute_script("return document.body.dataset.owner") == "0"
        assert "another page is probing" in browser.find_element("id", "error").text
        shown = json.loads(browser.find_element("id", "probe0").get_attribute("data-probe"))
        assert np.allclose(shown, other[-1])  # the other page's probe, not this page's
    finally:
        stop.set()
        t.join()
        ActionChains(browser).release().perform()
    time.sleep(0.1)
    session.respond("POST", "/api/probe", json.dumps({"probes": [None] * N_PROBES, "client": "other"}).encode())
    _drag(browser, browser.execute_script(f"return window.pmaskView.screenOf({v})"), slide=(0, 0))
    try:
        for _ in range(40):
            if browser.execute_script("return document.body.dataset.owner") == "1":
                break
            time.sleep(0.05)
        assert browser.execute_script("return document.body.dataset.owner") == "1"
        assert "another page" not in browser.find_element("id", "error").text
    finally:
        ActionChains(browser).release().perform()


# ---------------------------------------------------------------------------------- the command
def _pmask(*args):
    return [sys.executable, "-m", "pmask.pipeline", *args]


def test_port_in_use_is_one_line(kidney_small):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = subprocess.run(_pmask("view", str(kidney_small), "--port", str(port)), capture_output=True, text=True,
                           timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and f"port {port}" in r.stderr and "--port" in r.stderr
    assert "Traceback" not in r.stderr


def test_a_corrupt_artifact_is_refused_before_the_server_starts(kidney_small, tmp_path):
    bad = tmp_path / "bad.h5"
    data = bytearray(kidney_small.read_bytes())
    data[len(data) // 2:len(data) // 2 + 64] = bytes(64)
    bad.write_bytes(bytes(data))
    r = subprocess.run(_pmask("view", str(bad), "--port", "0"), capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "listening" not in r.stdout
    assert r.stderr.strip().count("\n") == 0 and "bad.h5" in r.stderr and "Traceback" not in r.stderr


def test_ctrl_c_stops_cleanly_and_it_listens_on_localhost_only(kidney_small):
    p = subprocess.Popen(_pmask("view", str(kidney_small), "--port", "0"), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        lines = [p.stdout.readline() for _ in range(3)]
        assert "127.0.0.1 only" in lines[1] and "--host" in lines[1], lines
        url = lines[2].split()[1]
        port = int(url.rstrip("/").rsplit(":", 1)[1])
        import urllib.request
        assert json.load(urllib.request.urlopen(url + "api/health", timeout=5)) == {"ok": True}
        with pytest.raises(OSError):  # not on the machine's other addresses
            other = _other_address()
            if other is None:
                raise OSError("no other address to try")
            socket.create_connection((other, port), timeout=2).close()
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=30)
    finally:
        p.kill()
    assert p.returncode == 0, err
    assert "stopped" in out and "Traceback" not in err


def _other_address():
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("10.255.255.255", 1))
            a = s.getsockname()[0]
        return None if a.startswith("127.") else a
    except OSError:
        return None


def test_the_viewer_runs_the_subdivided_contact_surface(session, kidney_small):
    """``pmask view`` (``--levels auto``, the default): the probes run on the mesh's Loop subdivision surface (three
    levels on the test kidney: 64 contact triangles to a mesh triangle), so a press at a triangle's centroid holds
    the proxy on the smooth surface, off the flat triangle by a fraction of an edge (its sagitta), where a
    ``--levels 0`` session's proxy lies in the triangle's plane."""
    from pmask.pipeline.cli import build_parser, levels_of

    assert levels_of(build_parser().parse_args(["view", "m.h5", "--levels", "2"])) == 2
    assert levels_of(build_parser().parse_args(["view", "m.h5"])) == "auto"
    assert levels_of(build_parser().parse_args(["view", "m.h5", "--levels", "0"])) == 0
    m = session.model
    P, T = m.points, m.triangles
    core = set(m.contact[m.core].tolist())
    t = next(i for i, tri in enumerate(T) if core.issuperset(tri.tolist()))
    c, h = P[T[t]].mean(axis=0), m.mean_edge_length
    n = np.cross(P[T[t][1]] - P[T[t][0]], P[T[t][2]] - P[T[t][0]])
    n /= np.linalg.norm(n)
    if np.dot(n, _outward(m, c)) < 0:
        n = -n
    path = [(c + (1.5 - 1.7 * s) * h * n).tolist() for s in np.linspace(0, 1, 30)]  # to 0.2 edges deep: the
    # proxy stays in the triangle (the interpolated normal is within a few degrees of the facet's there)
    mesh = ViewerSession(m, levels=0)
    try:
        srf = session.contacts.surface
        assert srf.levels >= 2 and len(srf.T) == 4 ** srf.levels * len(srf.mesh_T)
        off = {}
        for name, s in (("mesh", mesh), ("subdivided", session)):
            for p in path:
                reply = s.probe([p] + [None] * (N_PROBES - 1), deform=False, client="levels")
                time.sleep(0.003)
            time.sleep(0.05)
            reply = s.probe([path[-1]] + [None] * (N_PROBES - 1), deform=False, client="levels")
            s.probe([None] * N_PROBES, deform=False, client="levels")
            assert reply["contacts"][0]["status"] in ("CONTACT", "DEEP"), (name, reply["contacts"][0])
            off[name] = abs(float(np.dot(np.array(reply["contacts"][0]["proxy"]) - c, n)))
        assert off["mesh"] <= 1e-9 * h and 1e-4 * h < off["subdivided"] <= 0.1 * h, off
    finally:
        mesh.close()
