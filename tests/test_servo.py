"""The native servo core against the Python engine: one algorithm, two front ends.

Recorded probe traces (the haptics issue's tour with bad samples mixed in, the edge of a contact region,
several coupled instruments, random fuzz) through both engines must give identical statuses and forces
equal to 1e-12 N (they are bit-identical: the C is written operation for operation like the Python and
compiled without fused multiply-adds; 1e-12 N is the issue's bound, about 1e-11 of the forces here).
Runtime tables are refused by both loaders for the same reasons; the C example builds and runs, and its
own trace replays through the Python engine.
"""
from __future__ import annotations

import gc
import json
import math
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pmask.pipeline.strokes import region_edge_slide, tour
from pmask.runtime import Contacts, HapticContact, Model, Status
from pmask.runtime.contact import ContactSurface
from pmask.runtime.table import TableError, read_table, surface_sections, table_arrays, table_bytes, write_table
from pmask.errors import InputError
from pmask.runtime import servo

pytestmark = pytest.mark.skipif(not servo.available(), reason="the native servo core is not built")

FORCE_TOL = 1e-12  # N: the bound (the engines agree to the bit; see the module docstring)


@pytest.fixture(scope="module")
def table_path(surface, tmp_path_factory):
    surface.coupling()
    return write_table(tmp_path_factory.mktemp("tables") / "kidney.tbl", surface, {"mask": "linear"})


class Raises:
    def __float__(self):
        raise RuntimeError("a bad driver value")


def with_bad_samples(probes, seed):
    """The trace with bad samples mixed in: NaN, inf, absurd and raising values, wrong shapes, and jumps
    (single and long runs that restart tracking)."""
    rng = np.random.default_rng(seed)
    out = [tuple(p) for p in probes]
    bad = [(math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), [10 ** 400, 0, 0], [Raises(), 0.0, 0.0], None, "abc", (1.0, 2.0),
           np.array([0.0, 0.0, 0.0], np.float32)]
    for k in rng.choice(len(out), 40, replace=False):
        out[k] = bad[int(rng.integers(len(bad)))]
    for k in rng.choice(len(out) - 80, 6, replace=False):  # jumps: 3 ticks, and 60 ticks (tracking restarts)
        n = 3 if rng.random() < 0.5 else 60
        for j in range(k, k + n):
            if isinstance(out[j], tuple) and len(out[j]) == 3:
                out[j] = (out[j][0] + 0.05, out[j][1], out[j][2])
    return out


def run(contacts, trace):
    forces, statuses = [], []
    for probes in trace:
        f, s = contacts.step(probes)
        forces.append(f)
        statuses.append(s)
    return np.array(forces, float), statuses


def assert_same(a, b):
    fa, sa = a
    fb, sb = b
    assert len(sa) == len(sb)
    diff = [k for k, (x, y) in enumerate(zip(sa, sb)) if x != y]
    assert not diff, f"statuses differ first at tick {diff[0]}: {sa[diff[0]]} vs {sb[diff[0]]}"
    assert np.abs(fa - fb).max() <= FORCE_TOL


# ------------------------------------------------------------------------------- one algorithm, two engines
@pytest.mark.parametrize("options", [{}, {"friction": 0.5, "dynamic_friction": 0.3, "damping": 0.5, "tool_radius": 1e-3}],
                         ids=["frictionless", "friction-damping-tool"])
def test_the_tour_with_bad_samples_gives_the_same_statuses_and_forces(surface, options):
    probes, _ = tour()
    trace = [[p] for p in with_bad_samples(probes, seed=len(options))]
    py = run(Contacts(surface, 1, engine="python", **options), trace)
    c = run(Contacts(surface, 1, engine="native", **options), trace)
    assert_same(py, c)
    statuses = set(py[1][k][0] for k in range(len(trace)))
    assert {Status.CONTACT, Status.NO_CONTACT, Status.BAD_SAMPLE, Status.JUMP} <= statuses  # the trace exercises them
    # and the single-instrument front end returns the same through step1
    h = HapticContact(surface, engine="native", **options)
    for probes_k, (f_ref, s_ref) in zip(trace[:3000], zip(c[0][:3000], c[1][:3000])):
        f, s = h.step(probes_k[0])
        assert s == s_ref[0] and f == tuple(f_ref[0])


def test_the_edge_of_a_contact_region_and_the_support(kidney_top):
    """kidney_top: Ξ only over the upper half, the rest a band (taper λ) and the hilum's support."""
    m = Model.load(kidney_top)
    srf = ContactSurface(m.stiffness("linear", 2 * m.mean_edge_length))
    probes = region_edge_slide()
    trace = [[p] for p in probes]
    py = run(Contacts(srf, 1, engine="python", friction=0.3), trace)
    c = run(Contacts(srf, 1, engine="native", friction=0.3), trace)
    assert_same(py, c)
    seen = {s[0] for s in py[1]}
    assert {Status.CONTACT, Status.REGION_EDGE} <= seen


def _coupled_trace(model, n, ticks=1500):
    """n probes pressing and circling on the upper face, 8 mm apart."""
    top = model.contact[model.core]
    order = np.argsort(-model.points[top, 2])
    starts = [model.points[top[order[0]]]]
    for i in order[1:]:
        if all(np.linalg.norm(model.points[top[i]] - s) > 0.008 for s in starts):
            starts.append(model.points[top[i]])
        if len(starts) == n:
            break
    trace = []
    for k in range(ticks):
        d = 2e-3 * math.sin(math.pi * k / ticks) - 5e-4
        trace.append([s + np.array([1.5e-3 * math.sin(0.01 * k + l), 1.5e-3 * math.cos(0.013 * k + l), -d])
                      for l, s in enumerate(starts)])
    return trace


@pytest.mark.parametrize("n, friction", [(2, 0.0), (3, 0.4), (4, 0.0)])
def test_several_coupled_instruments(model, surface, n, friction):
    """n probes pressing and circling on the upper face, coupled through the ζ table."""
    ticks = 1500
    trace = _coupled_trace(model, n, ticks)
    trace[700][1] = (math.nan, 0.0, 0.0)  # one instrument's bad sample while the others press on
    opts = {"friction": friction, "dynamic_friction": 0.5 * friction}
    py_contacts = Contacts(surface, n, engine="python", **opts)
    assert py_contacts.coupled
    py = run(py_contacts, trace)
    c = run(Contacts(surface, n, engine="native", **opts), trace)
    assert_same(py, c)
    assert sum(s == Status.CONTACT for row in py[1] for s in row) > 0.5 * n * ticks


def _has_avx2() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            return any(line.startswith("flags") and " avx2" in line for line in f)
    except OSError:
        return False


@pytest.mark.parametrize("coupled", [True, False], ids=["coupled", "independent"])
def test_a_pair_s_kernels_give_the_python_s_forces_to_the_bit(model, surface, coupled, monkeypatch):
    """Two frictionless instruments pressing and circling (a pair, as the bench's): the C sums a coupled pair's
    blocks four entries a register where the CPU has AVX2, two (SSE2) where not or where the environment's
    PMASK_DISABLE_CPU_FEATURES names AVX2, and runs the two laws of a Jacobi sweep (or of two uncoupled contacts)
    in the two lanes of a register.  Every lane is the scalar's operations in the Python's order, so the two
    kernels' forces are equal to the bit and the Python engine's too (exact equality, not FORCE_TOL)."""
    trace = _coupled_trace(model, 2)
    py = run(Contacts(surface, 2, engine="python", coupled=coupled), trace)
    native = []
    for env in (None, "AVX2"):
        if env is None:
            monkeypatch.delenv("PMASK_DISABLE_CPU_FEATURES", raising=False)
        else:
            monkeypatch.setenv("PMASK_DISABLE_CPU_FEATURES", env)
        c = Contacts(surface, 2, engine="native", coupled=coupled)
        kernel = c._native.servo.kernel()
        if env is not None:
            assert kernel == "baseline"
        elif sys.platform == "linux":  # (/proc/cpuinfo says what the CPU has)
            assert kernel == ("avx2" if _has_avx2() else "baseline")
        native.append(run(c, trace))
    for f, s in native:
        assert s == py[1]
        assert np.array_equal(f, py[0])
    assert sum(s == Status.CONTACT for row in py[1] for s in row) > 0.5 * 2 * len(trace)


def test_a_deep_coupled_pair_freezes_and_pulls_the_same_way_in_both_engines(model, surface):
    """Two frictionless instruments 10-15 mm apart on the upper face pressed 6 mm, one after the other, and
    released in turn: both freeze past δ*, and the shallower one is carried away by the other's dent on most
    ticks (counted by hand: 156 ticks the pair presses with a frozen contact, the pair's normal problem solved
    on the stack in the C; 655 where one pulls, the general pivoting path): the C forces and statuses are the
    Python's to 1e-12 N on every tick (they are bit-identical)."""
    top = model.contact[model.core]
    P = model.points
    a = top[np.argmax(P[top, 2])]
    near = top[np.argsort(np.linalg.norm(P[top] - P[a], axis=1))]
    b = next(v for v in near if 0.010 < np.linalg.norm(P[v] - P[a]) < 0.015)
    n = np.array([0.0, 0.0, 1.0])
    ticks = 2000
    trace = []
    for k in range(ticks):
        x = k / ticks  # a deepest at 3/8 of the trace and out by 3/4; b in from 1/4, deepest at 5/8
        da = 6e-3 * max(0.0, math.sin(math.pi * min(x / 0.75, 1.0))) - 5e-4
        db = 6e-3 * max(0.0, math.sin(math.pi * max(0.0, (x - 0.25) / 0.75))) - 5e-4
        trace.append([P[a] - da * n, P[b] - db * n + np.array([1e-3 * math.sin(0.02 * k), 0.0, 0.0])])
    py_contacts = Contacts(surface, 2, engine="python")
    forces, statuses, frozen = [], [], set()
    for probes in trace:
        f, st_ = py_contacts.step(probes)
        forces.append(f)
        statuses.append(st_)
        frozen |= {l for l, c in enumerate(py_contacts._states) if c.frozen}
    c = run(Contacts(surface, 2, engine="native"), trace)
    assert_same((np.array(forces, float), statuses), c)
    assert frozen == {0, 1}  # both went past δ*: the frozen branch ran
    assert sum(all(s in (Status.CONTACT, Status.DEEP) for s in row) for row in statuses) > 0.2 * ticks


def _without_zeta(surface, monkeypatch):
    """The native core on this surface's table without its ζ section (what a compressed artifact's surface has),
    coupling through the surface's pair function; returns the list the counting pair function appends to
    (the triangles, and the thread that asked)."""
    import threading

    table = servo.load_table(table_arrays(surface_sections(surface, zeta=False), surface.meta))
    assert not table.counts()[2]
    monkeypatch.setattr(servo, "_native_table", lambda srf, zeta: table)
    calls, pair_blocks = [], surface.pair_blocks

    def counted(ta, tb):
        calls.append((ta, tb, threading.get_ident()))
        return pair_blocks(ta, tb)

    monkeypatch.setattr(surface, "pair_blocks", counted)
    return calls


@pytest.mark.parametrize("levels, friction", [(0, 0.0), (0, 0.4), (2, 0.4)])
def test_a_pair_function_couples_as_the_zeta_table_does(model, stiff, surface, levels, friction, monkeypatch):
    """Coupled contacts without a ζ table (the hands issue's compressed artifacts, pm_servo_create_paired): the
    core asks for a pair of mesh triangles' nine vertex-pair blocks when two contacts first land on them and
    keeps them while both stay.  Given the blocks the surface's ζ table holds, three coupled instruments get the
    ζ table's forces and statuses tick for tick (bit for bit: the same sums of the same numbers), on the mesh and
    on its subdivision surface (whose contact triangles the core maps to the mesh's before it asks); the pair
    function is asked only when a pair's triangles change (not per tick), and not again while the pair is among
    the last 64 the core keeps (contacts go back and forth over edges)."""
    if levels:
        surface = ContactSurface.of(stiff, levels=levels)
    trace = _coupled_trace(model, 3)
    opts = {"friction": friction, "dynamic_friction": 0.5 * friction}
    ref = run(Contacts(surface, 3, engine="native", **opts), trace)
    calls = _without_zeta(surface, monkeypatch)
    paired = Contacts(surface, 3, engine="native", **opts)
    assert paired._native.servo is not None and not paired._native.has_greens
    got, moves = [], 0
    last = None
    for probes in trace:
        got.append(paired.step(probes))
        tris = tuple(paired._native.state(k).tri for k in range(3))
        moves += tris != last
        last = tris
    assert_same((np.array([f for f, _ in got], float), [s for _, s in got]), ref)
    assert 0 < len(calls) <= 3 * moves < len(trace)  # three pairs; asked only when a triangle changes
    asked = [(ta, tb) for ta, tb, _ in calls]
    assert all(p not in asked[max(0, k - 64):k] for k, p in enumerate(asked))  # not again among the last 64


def test_the_servo_thread_asks_for_pairs_through_the_gil(model, surface, monkeypatch):
    """Thread mode with a pair function: the servo's own thread takes the GIL to ask for a new pair's blocks
    (the Python loop waits in exchange() without it), and the forces a tick-synchronous device loop reads are
    the ζ table's step on the same trace, bit for bit."""
    import threading

    trace = _coupled_trace(model, 2, ticks=1200)
    ref = run(Contacts(surface, 2, engine="native", friction=0.3), trace)
    calls = _without_zeta(surface, monkeypatch)
    c = Contacts(surface, 2, engine="native", friction=0.3)
    c.start(1000.0, exchange=True)
    try:
        got = [c.exchange(p) for p in trace]
        stats = c.tick_stats()
    finally:
        c.stop()
    assert_same((np.array([f for f, _ in got], float), [s for _, s in got]), ref)
    assert calls and threading.get_ident() not in {t for *_, t in calls}  # asked on the servo's thread
    assert stats["ticks"] >= len(trace)


def test_a_pair_function_s_mistakes_fail_the_step_loudly_or_hold_the_force(model, surface, monkeypatch, caplog):
    """Our own pair function's bugs: a wrong count of numbers raises from the step (a traceback: our bug, not
    the user's); a non-finite block is refused by the core (INTERNAL_ERROR, the last force held, logged), and
    once the function gives good blocks again both contacts are back in contact at the next tick.  Without a ζ table or a pair function coupled contacts are
    refused at creation with the line that says what to give."""
    from pmask.runtime.servo import _core

    trace = _coupled_trace(model, 2, ticks=400)
    _without_zeta(surface, monkeypatch)
    good = surface.pair_blocks
    monkeypatch.setattr(surface, "pair_blocks", lambda ta, tb: good(ta, tb)[:80])
    c = Contacts(surface, 2, engine="native")
    with pytest.raises(ValueError, match="81 numbers, got 80"):
        for probes in trace:
            c.step(probes)
    bad = {"nan": True}
    monkeypatch.setattr(surface, "pair_blocks",
                        lambda ta, tb: [math.nan] * 81 if bad["nan"] else good(ta, tb))
    c = Contacts(surface, 2, engine="native")
    with caplog.at_level("ERROR"):
        statuses = [c.step(p)[1] for p in trace[:250]]
    assert any(Status.INTERNAL_ERROR in s for s in statuses)
    assert any("internal error in the native haptic step" in r.message for r in caplog.records)
    bad["nan"] = False
    assert c.step(trace[250])[1] == [Status.CONTACT, Status.CONTACT]
    table = servo.load_table(table_arrays(surface_sections(surface, zeta=False), surface.meta))
    with pytest.raises(ValueError, match="zeta section .* or a pair function"):
        _core.Servo(table, 2, (0.0, 0.0, 0.0, 0.0, 1e-3, 1000.0, 0.01, 0.9, 1.25, 50, 24, 1, 1), print)
    with pytest.raises(TypeError, match="callable"):
        _core.Servo(table, 2, (0.0, 0.0, 0.0, 0.0, 1e-3, 1000.0, 0.01, 0.9, 1.25, 50, 24, 1, 1), print, 3)


samples = st.one_of(
    st.tuples(*[st.floats(allow_nan=True, allow_infinity=True, width=64)] * 3),
    st.tuples(*[st.floats(-0.06, 0.06)] * 3),
    st.tuples(*[st.floats(-0.03, 0.03)] * 3),
    st.lists(st.floats(-0.1, 0.1), min_size=0, max_size=5),
    st.just([10 ** 400, 0, 0]), st.just([Raises(), 0.0, 0.0]), st.none(), st.text(max_size=3),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(1, 3), st.lists(st.lists(samples, min_size=3, max_size=3), min_size=1, max_size=40),
       st.sampled_from([0.0, 0.4]))
def test_random_sequences_give_the_same_results(surface, n, seq, friction):
    trace = [row[:n] for row in seq]
    a = run(Contacts(surface, n, engine="python", friction=friction), trace)
    b = run(Contacts(surface, n, engine="native", friction=friction), trace)
    assert_same(a, b)


def test_an_internal_error_is_held_the_same_way(surface, caplog):
    """A table whose contact normals vanish over one triangle (a bug's stand-in): both engines divide by
    zero at the same tick and hold the last force decaying with INTERNAL_ERROR, and say so in the log."""
    secs = surface_sections(surface, zeta=False)
    t = int(np.argmax(surface.P[surface.T].mean(axis=1)[:, 2]))  # the top triangle
    normals = secs["normals"].copy()
    normals[surface.T[t]] = 0.0
    secs["normals"] = normals
    srf = ContactSurface.from_table(read_table(table_bytes(secs, {})))
    centre = surface.P[surface.T[t]].mean(axis=0)
    trace = [[centre + np.array([0.0, 0.0, 2e-3 - 4e-3 * k / 200])] for k in range(200)]
    with caplog.at_level("ERROR"):
        a = run(Contacts(srf, 1, engine="python"), trace)
        b = run(Contacts(srf, 1, engine="native"), trace)
    assert_same(a, b)
    assert Status.INTERNAL_ERROR in [s[0] for s in a[1]]
    assert any("internal error in the haptic step" in r.message for r in caplog.records)
    assert any("internal error in the native haptic step" in r.message for r in caplog.records)


def test_a_probe_far_outside_is_reported_once_by_the_native_engine(surface, caplog):
    h = HapticContact(surface, engine="native")
    with caplog.at_level("WARNING"):
        statuses = [h.step(surface.P[0] * 1000.0)[1] for _ in range(3)]
    assert statuses == [Status.FAR_OUTSIDE] * 3
    assert sum("same length unit" in r.message for r in caplog.records) == 1


# ------------------------------------------------------------------------------- tables
def test_a_table_round_trips_and_both_loaders_read_the_same(table_path, surface):
    t = read_table(table_path)
    srf = ContactSurface.from_table(t)
    for name in ("P", "T", "tri_geom", "neighbours", "vertex_normals", "K", "taper", "gradient", "mesh_T", "parent",
                 "corners"):
        assert np.array_equal(getattr(srf, name), getattr(surface, name)), name
    assert srf.levels == surface.levels
    native = servo.load_table(table_path)
    assert native.counts() == (surface.n_mesh, len(surface.mesh_T), 1)  # the mesh's: the deformation's size
    # where the deformation is drawn (pm_table_points): the mesh's vertices as the contact surface has them
    assert np.array_equal(np.frombuffer(native.points()).reshape(-1, 3), surface.mesh_points)
    assert servo.table_meta(native)["mask"] == "linear"
    # K(x) in a batch from C against eq. 15 in numpy
    rng = np.random.default_rng(3)
    tri = rng.integers(0, len(surface.T), 5000)
    bary = rng.dirichlet([1, 1, 1], 5000)
    out = np.empty((5000, 9))
    native.stiffness(tri.astype(np.int64), bary, out)
    ref = np.einsum("nk,nkj->nj", bary, surface.K[surface.T[tri]])
    assert np.abs(out - ref).max() <= 1e-14 * np.abs(ref).max()


def test_a_table_written_a_chunk_at_a_time_is_the_one_made_in_memory(surface, tmp_path, monkeypatch):
    """write_table streams each section to the file in chunks (a large organ's export holds its sections once,
    not the table's bytes too), its CRC-32 carried from chunk to chunk: with chunks of an odd size, so that they
    straddle sections' ends, the file is byte for byte the table table_bytes makes in memory, and both loaders
    accept its checksums."""
    from pmask.runtime import table

    monkeypatch.setattr(table, "WRITE_CHUNK", 4099)
    meta = {"mask": "linear"}
    path = write_table(tmp_path / "chunked.tbl", surface, meta)
    assert path.read_bytes() == bytes(table_bytes(surface_sections(surface), meta))
    assert read_table(path)["meta"] == meta
    if servo.available():
        assert servo.load_table(path).counts()[2] == 1


def test_byte_sections_keep_their_length_in_memory_and_in_a_file(surface):
    """A byte section given as bytes, bytearray or a memoryview (a table's own, read back) is its bytes, the empty
    one included (np.asarray(b"") is one zero byte of type S1: an empty section handed to the core became one
    byte), in memory (table_arrays) and in a file (table_bytes, read back)."""
    sections = surface_sections(surface, zeta=False)
    for given in (b"", b"\x01\x02\x03", bytearray(b"\x04"), memoryview(b"\x05\x06")):
        assert bytes(table_arrays({"extra": given}, {})["extra"]) == bytes(given)
        assert bytes(read_table(table_bytes({**sections, "extra": given}, {}))["extra"]) == bytes(given)


def test_a_surface_from_a_table_hands_its_own_arrays_to_the_core(model, table_path, tmp_path):
    """ContactSurface.from_table reads the file once: its sections are views of the file's bytes, and the native
    core borrows those same arrays rather than loading the file again (a 674 MiB table was held three times:
    the file's bytes, their copies, the C loader's).  So the file may go once the surface is made: two coupled
    contacts made after it is deleted step as on the surface of a fresh read, bit for bit."""
    if not servo.available():
        pytest.skip("the native core is not built")
    copy = tmp_path / "gone.tbl"
    copy.write_bytes(table_path.read_bytes())
    srf = ContactSurface.from_table(copy)
    t = srf.table
    assert t["zeta"].base is not None and not t["zeta"].flags.owndata  # a view of the file's bytes
    copy.unlink()
    trace = _coupled_trace(model, 2, ticks=400)
    got = run(Contacts(srf, 2, engine="native", friction=0.3), trace)
    ref = run(Contacts(ContactSurface.from_table(table_path), 2, engine="native", friction=0.3), trace)
    assert_same(got, ref)


def test_the_native_grid_finds_the_nearest_triangle(table_path, surface):
    """C grid, Python grid and a scan over every triangle agree, ties included, inside and outside the box."""
    native = servo.load_table(table_path)
    rng = np.random.default_rng(4)
    span = surface.hi - surface.lo
    pts = np.concatenate([rng.uniform(surface.lo - 0.3 * span, surface.hi + 0.3 * span, (300, 3)),
                          surface.P[rng.integers(0, len(surface.P), 100)]])  # on vertices: ties
    for p in pts:
        scan = surface.grid.nearest_scan(p)
        assert surface.grid.nearest(p) == scan == native.nearest(p)


def _rewrite(buf: bytes, *, major=None, flip_section=None, extra=None, negate_stiffness=False, drop=None) -> bytes:
    """A table rewritten with valid checksums (a newer major, a negated K, a section dropped as a 1.0 table
    lacks the 1.1 law's), or with one flipped byte."""
    t = read_table(buf)
    meta = t.pop("meta")
    if drop:
        del t[drop]
    if negate_stiffness:
        t["stiffness"] = -t["stiffness"]
    if extra:
        t.update(extra)
    out = bytearray(table_bytes(t, meta))
    if major is not None:
        out[8:12] = struct.pack("<I", major)
        head = bytes(out[:36]) + b"\0\0\0\0" + bytes(out[40:64])
        n = struct.unpack_from("<I", out, 32)[0]
        out[36:40] = struct.pack("<I", zlib.crc32(bytes(out[64:64 + 64 * n]), zlib.crc32(head)))
    if flip_section is not None:
        n = struct.unpack_from("<I", out, 32)[0]
        for i in range(n):
            name, _, _, off, _, _ = struct.unpack_from("<32sIIQQQ", out, 64 + 64 * i)
            if name.rstrip(b"\0").decode() == flip_section:
                out[off + 5] ^= 0x01
    return bytes(out)


@pytest.mark.parametrize("case, match", [
    ("foreign", "not a pmask runtime table"),
    ("truncated", "truncated"),
    ("corrupt", "section 'stiffness' fails its checksum"),
    ("newer", r"format 2\.\d+ is not one this"),
    ("negated", "not positive definite"),
    ("older", "section 'normal_stiffness' is missing .* export it again"),
])
def test_both_loaders_refuse_bad_tables(table_path, kidney_default, tmp_path, case, match):
    good = table_path.read_bytes()
    data = {"foreign": lambda: kidney_default.read_bytes(),
            "truncated": lambda: good[:len(good) // 2],
            "corrupt": lambda: _rewrite(good, flip_section="stiffness"),
            "newer": lambda: _rewrite(good, major=2),
            "negated": lambda: _rewrite(good, negate_stiffness=True),
            "older": lambda: _rewrite(good, drop="normal_stiffness")}[case]()
    p = tmp_path / "bad.tbl"
    p.write_bytes(data)
    with pytest.raises(TableError, match=match):
        read_table(p)
    with pytest.raises(TableError, match=match):
        servo.load_table(p)
    with pytest.raises(TableError, match=match):
        servo.load_table(data)


@pytest.mark.parametrize("case, match", [
    ("negated", "not positive definite"),
    ("older", "section 'normal_stiffness' is missing"),
    ("nan", "a non-finite number"),
    ("index", "a triangle or neighbour index is out of range"),
    ("row", "a contact row is out of range"),
    ("shape", "section 'frames' has the wrong type or shape"),
])
def test_a_table_over_arrays_is_checked_as_a_file_is(surface, case, match):
    """pm_table_from_sections (the viewer's route: no serialising, no copy) refuses what the file loader
    refuses, with the same message: the same checks run on the same sections, bar the checksums."""
    secs = surface_sections(surface, zeta=True)
    if case == "negated":
        secs["stiffness"] = -secs["stiffness"]
    elif case == "older":
        del secs["normal_stiffness"]
    elif case == "nan":
        secs["normals"] = secs["normals"].copy()
        secs["normals"][7, 1] = np.nan
    elif case == "index":
        secs["triangles"] = secs["triangles"].copy()
        secs["triangles"][3, 2] = len(secs["points"])
    elif case == "row":
        secs["contact_row"] = secs["contact_row"].copy()
        secs["contact_row"][0] = len(secs["zeta"]) // 3
    elif case == "shape":
        secs["frames"] = secs["frames"][:, :11]
    with pytest.raises(TableError, match=match):
        servo.load_table(table_bytes(secs, {}))
    with pytest.raises(TableError, match=match):
        servo.load_table(table_arrays(secs, {}))


def test_a_table_over_arrays_holds_them_and_reads_as_the_file_does(surface, table_path):
    """The borrowed table keeps its arrays alive (the dict and the caller's names gone, memory churned) and
    answers as the file's table, bit for bit: K(x) in a batch, nearest triangles, metadata (the coupled runs
    above compare the two engines over such tables); an array that is not float64/int64 is refused in one
    line."""
    file_table = servo.load_table(table_path)
    secs = surface_sections(surface, zeta=True)
    secs = {k: v.copy() for k, v in secs.items()}  # arrays only this dict holds
    borrowed = servo.load_table(table_arrays(secs, {"mask": "linear"}))
    del secs
    gc.collect()
    _ = [np.ones(10_000) for _ in range(200)]  # reuse freed memory, were any of it freed
    rng = np.random.default_rng(5)
    tri = rng.integers(0, len(surface.T), 2000).astype(np.int64)
    bary = rng.dirichlet([1, 1, 1], 2000)
    a, b = np.empty((2000, 9)), np.empty((2000, 9))
    file_table.stiffness(tri, bary, a)
    borrowed.stiffness(tri, bary, b)
    assert np.array_equal(a, b)
    assert borrowed.counts() == file_table.counts() and servo.table_meta(borrowed) == {"mask": "linear"}
    for p in surface.P[rng.integers(0, len(surface.P), 50)] + 1e-4:
        assert borrowed.nearest(p) == file_table.nearest(p)
    with pytest.raises(TableError, match="section 'points' must be a 2-D float64 or int64 array"):
        servo.load_table({**table_arrays(surface_sections(surface, zeta=False), {}),
                          "points": surface.P.astype(np.float32)})


def test_a_subdivided_table_round_trips_and_a_broken_map_is_refused(stiff, tmp_path):
    """Table 1.3 with the subdivided contact surface: both loaders read the same surface and its map to the mesh
    (the C loader's counts are the mesh's, the size of the deformation it returns); a map that points outside the
    mesh or corners that are not barycentrics are refused by both with one line."""
    surface = ContactSurface(stiff, levels=1)
    surface.coupling()
    path = write_table(tmp_path / "sub.tbl", surface, {"mask": "linear", "levels": 1})
    t = read_table(path)
    srf = ContactSurface.from_table(t)
    assert srf.levels == 1 and len(srf.T) == 4 * len(srf.mesh_T)
    for name in ("P", "T", "mesh_T", "parent", "corners", "K", "vertex_normals"):
        assert np.array_equal(getattr(srf, name), getattr(surface, name)), name
    assert servo.load_table(path).counts() == (surface.n_mesh, len(surface.mesh_T), 1)
    sections = {k: v for k, v in t.items() if k != "meta"}
    for name, value, message in (("parent", np.full_like(t["parent"], len(t["mesh_triangles"])), "out of range"),
                                 ("corners", t["corners"] * 2.0, "barycentrics")):
        data = bytes(table_bytes({**sections, name: value}, t["meta"]))
        with pytest.raises(TableError, match=message):
            read_table(data)
        with pytest.raises(TableError, match=message):
            servo.load_table(data)
    alone = {k: v for k, v in sections.items() if k not in ("mesh_triangles", "parent")}  # corners without the rest
    data = bytes(table_bytes(alone, t["meta"]))
    for load in (read_table, servo.load_table):
        with pytest.raises(TableError, match="go together"):
            load(data)


def test_a_newer_minor_table_with_an_unknown_section_is_read(table_path):
    data = bytearray(_rewrite(table_path.read_bytes(), extra={"future_section": np.ones((4, 2))}))
    data[12:16] = struct.pack("<I", 7)  # minor 7
    head = bytes(data[:36]) + b"\0\0\0\0" + bytes(data[40:64])
    n = struct.unpack_from("<I", data, 32)[0]
    data[36:40] = struct.pack("<I", zlib.crc32(bytes(data[64:64 + 64 * n]), zlib.crc32(head)))
    t = read_table(bytes(data))
    assert "future_section" in t
    assert servo.load_table(bytes(data)).counts()[0] == ContactSurface.from_table(t).n_mesh


def test_export_table_command(kidney_small, tmp_path):
    out = tmp_path / "small.tbl"
    r = subprocess.run([sys.executable, "-m", "pmask.pipeline", "export-table", str(kidney_small), "--mask", "linear", "--radius", "0.006",
                        "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    t = read_table(out)
    assert t["meta"]["mask"] == "linear" and t["meta"]["radius"] == pytest.approx(0.006)
    assert "zeta" in t and servo.load_table(out).counts()[2] == 1
    info = subprocess.run([sys.executable, "-m", "pmask.pipeline", "info", str(out)], capture_output=True, text=True)
    assert info.returncode == 0, info.stderr
    n3 = len(t["zeta"])
    assert f"zeta table {n3:,} x {n3:,}" in info.stdout and "format           pmask runtime table 1." in info.stdout
    info = subprocess.run([sys.executable, "-m", "pmask.pipeline", "info", "--json", str(out)], capture_output=True,
                          text=True)
    assert json.loads(info.stdout)["radius"] == t["meta"]["radius"]  # (--json: every digit, as a number)
    cut = tmp_path / "cut.tbl"  # a truncated table: the loaders' one line, no traceback
    cut.write_bytes(out.read_bytes()[:-100])
    info = subprocess.run([sys.executable, "-m", "pmask.pipeline", "info", str(cut)], capture_output=True, text=True)
    assert info.returncode == 2 and "truncated" in info.stderr and len(info.stderr.strip().splitlines()) == 1
    # the coarse test kidney: the default (the automatic choice) subdivides it
    assert t["meta"]["levels"] >= 2 and len(t["triangles"]) == 4 ** t["meta"]["levels"] * len(t["mesh_triangles"])
    assert servo.load_table(out).counts()[:2] == (int(t["mesh_triangles"].max()) + 1, len(t["mesh_triangles"]))
    r = subprocess.run([sys.executable, "-m", "pmask.pipeline", "export-table", str(kidney_small), "--levels", "0",
                        "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    t = read_table(out)
    assert "parent" not in t and t["meta"]["levels"] == 0  # the mesh, when asked for
    bad = subprocess.run([sys.executable, "-m", "pmask.pipeline", "export-table", str(kidney_small), "--radius", "-1", "-o", str(out)],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "radius" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1


def test_the_native_zeta_rows_are_numpys(model):
    """pm_zeta_rows (C, eight columns in registers) fills the ζ table as Stiffness.zeta_table's numpy loop does,
    to 1e-12 relative (the same sums in another order: measured 1e-16), with the zero rows left zero; masks
    whose indices leave the table are refused with the C core's line."""
    import dataclasses

    numpy_table = model.stiffness("linear", model.default_radius).zeta_table()
    native = model.stiffness("linear", model.default_radius).zeta_table(rows=servo.zeta_rows)
    assert np.abs(native - numpy_table).max() <= 1e-12 * np.abs(numpy_table).max()
    assert np.array_equal(native == 0, numpy_table == 0)
    m = model.stiffness("linear", model.default_radius).masks
    n3 = len(numpy_table)
    out = np.zeros((n3 // 3, 3 * n3))
    bad = dataclasses.replace(m, indices=np.where(np.arange(len(m.indices)) == 5, n3, m.indices))
    with pytest.raises(ValueError, match="mask vertex out of range"):
        servo.zeta_rows(out, bad, out)
    with pytest.raises(ValueError, match="C-contiguous float64"):
        servo.zeta_rows(out, m, out[:, ::2])


# ------------------------------------------------------------------------------- display, thread, fallback
def test_the_native_deformation_equals_the_python_display(surface, model):
    top = model.contact[model.core]
    i = top[np.argmax(model.points[top, 2])]
    starts = [model.points[i], model.points[i] + np.array([0.012, 0.0, -0.001])]
    n = np.array([0.0, 0.0, 1.0])
    a, b = Contacts(surface, 2, engine="python", friction=0.4), Contacts(surface, 2, engine="native", friction=0.4)
    for d in np.linspace(-1e-3, 1.5e-3, 100):
        probes = [s - d * n for s in starts]
        a.step(probes)
        b.step(probes)
    va, vb = a.deformation(), b.deformation()
    assert np.abs(va - vb).max() <= 1e-10 * np.abs(va).max()  # LU in C against LAPACK's: round-off apart
    assert np.abs(va).max() > 1e-4


def test_the_native_thread_runs_the_same_step(surface, model):
    """Thread mode: a probe set from Python above the surface and then 1.5 mm into it; the native thread's
    force, once the probe rests, equals the Python engine's for the same samples (the velocity filter has
    decayed: 0.9^200 ~ 1e-9 of the motion)."""
    top = model.contact[model.core]
    i = top[np.argmax(model.points[top, 2])]
    above, inside = model.points[i] + [0, 0, 1e-3], model.points[i] - [0, 0, 1.5e-3]
    c = Contacts(surface, 1, engine="native")
    c.start(1000.0)
    try:
        import time

        c.set_probes([above])
        time.sleep(0.05)
        c.set_probes([inside])
        time.sleep(0.4)
        forces, statuses = c.read()
        stats = c.tick_stats()
    finally:
        c.stop()
    assert not c.running and statuses == [Status.CONTACT]
    assert stats["ticks"] >= 200
    ref = Contacts(surface, 1, engine="python")
    for p in [above] * 5 + [inside] * 400:
        f_ref, _ = ref.step([p])
    np.testing.assert_allclose(forces[0], f_ref[0], rtol=1e-6, atol=1e-9)


def test_the_python_thread_mode_has_the_same_api(surface, model):
    import time

    top = model.contact[model.core]
    i = top[np.argmax(model.points[top, 2])]
    c = Contacts(surface, 1, engine="python")
    c.start(500.0)
    try:
        c.set_probes([model.points[i] + [0, 0, 1e-3]])
        time.sleep(0.05)
        c.set_probes([model.points[i] - [0, 0, 1e-3]])
        time.sleep(0.2)
        _, statuses = c.read()
    finally:
        c.stop()
    assert statuses == [Status.CONTACT] and c.tick_stats()["ticks"] > 50


@pytest.mark.parametrize("engine", ["native", "python"])
def test_a_device_loop_in_python_exchanges_samples_tick_by_tick(surface, model, engine):
    """The haptics issue's tick-synchronous way for a Python device loop: with start(exchange=True) each sample
    given to exchange() is used by exactly one tick of the servo thread, in order, so the forces the loop reads
    equal the binding's own step on the same trace, tick for tick (bit for bit: the same C, or the same Python,
    on the same samples).  Before, set_probes/read beside the running thread skipped and repeated ticks: the
    force change the loop saw per tick was up to 10x the step's on the same path."""
    import time

    probes, _ = tour()
    trace = [[p] for p in probes[:1500]]
    c = Contacts(surface, 1, engine=engine, friction=0.3)
    c.start(1000.0, exchange=True)
    got = []
    try:
        for k, smp in enumerate(trace):
            got.append(c.exchange(smp))
            if k % 97 == 0:
                time.sleep(0.003)  # a loop that falls behind now and then: the thread idles, nothing is lost
        stats = c.tick_stats()
        with pytest.raises(InputError, match="exchange mode"):
            c.set_probes(trace[0])
    finally:
        c.stop()
    ref = run(Contacts(surface, 1, engine=engine, friction=0.3), trace)
    assert_same((np.array([f for f, _ in got], float), [s for _, s in got]), ref)
    assert stats["idle"] > 0 and stats["ticks"] >= len(trace)
    assert {Status.CONTACT, Status.NO_CONTACT} <= {s[0] for s in ref[1]}


@pytest.mark.parametrize("engine", ["native", "python"])
def test_text_and_truth_values_are_not_samples(surface, model, engine):
    """step("000") was a probe at the origin and step(b"\x00\x01\x02") one at (0, 1, 2) m; bools were
    coordinates too.  All are BAD_SAMPLE now, in both engines, and a real sample after them still works."""
    i = model.contact[model.core][np.argmax(model.points[model.contact[model.core], 2])]
    h = HapticContact(surface, engine=engine)
    for bad in ("000", b"\x00\x01\x02", bytearray(b"abc"), [True, False, True], (0.0, True, 0.0),
                np.array([1, 0, 1], bool), ["0", "0", "0"], [b"1", 0.0, 0.0], (np.bool_(True), 0.0, 0.0)):
        assert h.step(bad)[1] == Status.BAD_SAMPLE, bad
    assert h.step(model.points[i] + [0, 0, 1e-3])[1] == Status.NO_CONTACT
    assert h.step(model.points[i] - [0, 0, 1e-3])[1] == Status.CONTACT


def test_without_the_native_core_the_python_engine_runs(surface, monkeypatch):
    from pmask.errors import InputError

    monkeypatch.setattr(servo, "_core", None)
    assert HapticContact(surface).engine == "python"
    with pytest.raises(InputError, match="not built"):
        HapticContact(surface, engine="native")


def test_the_c_servo_refuses_bad_options(table_path):
    from pmask.runtime.servo import _core

    table = servo.load_table(table_path)
    good = (0.0, 0.0, 0.0, 0.0, 1e-3, 1000.0, 0.01, 0.9, 1.25, 50, 24, 1, 0)
    for k, value, name in [(0, -1.0, "friction"), (3, 1e9, "tool_radius"), (5, math.nan, "rate"),
                           (7, 1.0, "decay"), (9, 0, "reset_after"), (8, 0.5, "proxy_speed")]:
        opts = list(good)
        opts[k] = value
        with pytest.raises(ValueError, match=name):
            _core.Servo(table, 1, tuple(opts), print)
    with pytest.raises(ValueError, match="instruments"):
        _core.Servo(table, 0, good, print)


# ------------------------------------------------------------------------------- the C example
def test_the_c_example_builds_runs_and_replays_through_python(table_path, surface, tmp_path):
    """examples/c/haptic_loop.c, compiled as a C application would (C99, pedantic, warnings as errors),
    runs its scripted session over the table; its per-tick trace replayed through the Python engine gives
    the same statuses and forces, and at the end of its hold the device rests: the rendered force balances
    the grip's pull (within 1 %: the contact's oscillation, ~55 rad/s with damping ratio ~0.2, has decayed
    for 0.5 s to e^-5)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    exe = tmp_path / "haptic_loop"
    # the paths as the C API page's build line takes them: `pmask c-core --include` and `--sources`
    where = subprocess.run([sys.executable, "-m", "pmask.pipeline", "c-core", "--include", "--sources"],
                           capture_output=True, text=True)
    assert where.returncode == 0, where.stderr
    inc, srcs = where.stdout.splitlines()
    assert Path(inc) == Path(servo.include_dir()) and srcs.split() == [str(f) for f in servo.sources()]
    build = [cc, "-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-O2", "-ffp-contract=off", f"-I{inc}",
             "examples/c/haptic_loop.c", *srcs.split(), "-lm", "-lpthread", "-o", str(exe)]
    r = subprocess.run(build, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    trace = tmp_path / "trace.csv"
    r = subprocess.run([str(exe), str(table_path), "--trace", str(trace)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rows = np.loadtxt(trace, delimiter=",", skiprows=1)
    probes, forces, statuses = rows[:, 1:4], rows[:, 4:7], rows[:, 7].astype(int)
    ref = HapticContact(surface, engine="python", friction=0.4, dynamic_friction=0.3)
    out = [ref.step(p) for p in probes]
    assert [int(s) for _, s in out] == statuses.tolist()
    assert np.abs(np.array([f for f, _ in out]) - forces).max() <= FORCE_TOL
    assert (statuses == Status.CONTACT).sum() > 3000
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("end of hold"))
    nums = [float(x) for x in line.replace("(", " ").replace(")", " ").replace(",", " ").split()
            if x.replace(".", "").replace("-", "").isdigit()]
    f, grip = np.array(nums[:3]), np.array(nums[3:6])
    assert np.linalg.norm(f) > 0.05 and np.linalg.norm(f + grip) <= 0.01 * np.linalg.norm(f)
    # thread mode: the device in the library's own tick
    r = subprocess.run([str(exe), str(table_path), "--thread"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "thread:" in r.stdout, r.stderr
    # and a corrupt table is refused by the program with the loader's message
    bad = tmp_path / "bad.tbl"
    bad.write_bytes(b"not a table")
    r = subprocess.run([str(exe), str(bad)], capture_output=True, text=True)
    assert r.returncode == 1 and "not a pmask runtime table" in r.stderr
