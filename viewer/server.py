"""The viewer's server: one page, a JSON API, and the haptic servo running at 1 kHz beside them.

API (every answer is JSON; an error is ``{"error": "one line saying what to fix"}`` with a 4xx status):

``GET /api/model``
    the surface (points, triangles), units, mask, radius and its slider range, and the fields the page
    colours by: ``masked`` and ``single`` (‖K_i‖₂ [N/m] of the rendered vertex stiffness, eq. 12 with the
    mask, or with single-vertex masks), ``area`` (vertex areas), ``fixed`` (Λu) and ``contact`` (the
    touchable contact region).
``POST /api/probe`` ``{"probes": [[x, y, z] | null, ...], "deform": bool, "client": "id"}``
    sets the servo thread's probes (null: lifted) and returns each contact's force on the hand [N], status,
    penetration depth, proxy point and ‖K(x)‖ at the proxy, the servo's timing, and with ``deform`` the
    surface displacement (eq. 16, float32, base64) that meets every contact.  One page owns the probes at a
    time: the one that touches first, until it lets go or goes silent for :data:`OWNER_LEASE` seconds (counted
    from the server's answer to its last request, so that a slow answer is not the page's silence); the
    others' probes are not applied, and their replies (``"owner": false`` and a ``notice``) show the owner's
    contacts and say why.
``POST /api/radius`` ``{"radius": r}`` (the reply also counts the masks that reach no neighbour)
    rebuilds the K_i for a new mask radius (0 < r ≤ r_max) and restarts the servo on them.

The request handling (:meth:`ViewerSession.respond`) is a plain function of (method, path, body), which
the fuzz test drives directly as well as through the socket.  Nothing a client sends can stop the server:
malformed or hostile messages get a 4xx and one line; a bug of ours gets a 500, and its traceback goes to
the server's log, not to the client.
"""
from __future__ import annotations

import base64
import errno
import http.server
import json
import logging
import math
import threading
import time
from pathlib import Path

import numpy as np

from pmask.errors import InputError, PmaskError
from pmask.runtime.contact import tracking
from pmask.runtime.haptics import Contacts, Status
from pmask.runtime.model import Model

log = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"
#: the files the server hands out (nothing else on disk is reachable)
FILES = {"/": ("index.html", "text/html; charset=utf-8"),
         "/index.html": ("index.html", "text/html; charset=utf-8"),
         "/viewer.bundle.js": ("viewer.bundle.js", "text/javascript; charset=utf-8")}
#: a probe message is ~200 bytes; anything far larger is not from the page
MAX_BODY = 64 * 1024
#: probes the page can drive (the mouse, and shift-drag for a second one coupled through the body)
N_PROBES = 2
#: the servo thread's rate [Hz]: the rate a device would run at
RATE = 1000.0
#: a page that owns the probes and sends nothing for this long [s] gives them up (a closed tab)
OWNER_LEASE = 1.0
#: what a page that does not own the probes is told
NOT_OWNER = ("another page is probing this model: its contacts are shown here, and yours wait until it lets go "
             "(one probe set per server)")


class ViewerError(PmaskError):
    """What keeps the viewer from starting (port in use, page not built), in one line."""


class BadRequest(Exception):
    """A client's message the server refuses (400), with the line that says why."""


#: how far (relative to the largest radius) a requested radius may fall outside the slider's range and be
#: taken as its end: Chromium's range input works in decimals and gave back its minimum a last digit low
RANGE_SLACK = 1e-9


def _vec3(v, what: str) -> list:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise BadRequest(f"{what} must be [x, y, z]")
    out = []
    for c in v:
        if isinstance(c, bool) or not isinstance(c, (int, float)):
            raise BadRequest(f"{what} must hold 3 numbers")
        c = float(c)
        if not math.isfinite(c):
            raise BadRequest(f"{what} must hold finite numbers")
        out.append(c)
    return out


class ViewerSession:
    """One model on the server: its stiffness for the current mask radius and the contacts' servo thread.

    model : a loaded :class:`pmask.runtime.Model`; mask : the pressure mask kind; radius : the initial
    mask radius (default :attr:`pmask.runtime.Model.default_radius`); engine : the servo engine (None: native if built);
    levels : the contact surface (:class:`pmask.runtime.Contacts`: "auto" the default, n the mesh's Loop subdivision
    surface after n levels, 0 the mesh).
    """

    def __init__(self, model: Model, *, mask: str = "linear", radius: float | None = None, engine: str | None = None,
                 rate: float = RATE, spin: float = 0.0, levels="auto"):
        self.model = model
        self.levels = levels
        self.mask = mask
        self.engine = engine
        self.rate = float(rate)
        self.spin = float(spin)
        self.lock = threading.Lock()  # held to read or swap the live contacts, never during a rebuild
        self.build_lock = threading.Lock()
        self.owner, self.owner_seen = None, 0.0  # the page that owns the probes, and when it last spoke
        self.applied = [None] * N_PROBES  # the probes the owner last set
        P = model.points
        lo, hi = P.min(axis=0), P.max(axis=0)
        self.diag = float(np.linalg.norm(hi - lo))
        # a lifted probe waits here: outside the body, near enough not to be "far outside"
        self.park = (hi + 0.25 * self.diag).tolist()
        h = model.mean_edge_length
        self.radius_range = (0.5 * h, float(min(model.r_max, 0.25 * self.diag)))
        radius = model.default_radius if radius is None else float(radius)
        model.hold_transpose()  # every radius change makes a ζ table: Ξᵀ once, not per change
        single = model.stiffness("single")
        self.fields = {"single": _norms(single.K_vertex), "area": model.vertex_areas.astype(float),
                       "fixed": np.isin(np.arange(len(P)), model.fixed).astype(float),
                       "contact": np.isin(np.arange(len(P)), model.contact[model.core]).astype(float)}
        self.contacts, self.rest = None, None
        self.display = model.display()  # the scan's surface at its own resolution, if the artifact keeps one
        try:
            self._build(radius)
        except BadRequest as exc:
            raise InputError(f"--radius: {exc}") from None

    # ------------------------------------------------------------------ state
    def _build(self, radius: float) -> None:
        """Make K_i, the contact surface, the ζ table and a running servo thread for ``radius`` while the old
        one keeps serving the probes (``self.lock`` is not held: a probe request is answered meanwhile), then
        swap them in at once under the lock.  One rebuild at a time (``self.build_lock``)."""
        lo, hi = self.radius_range
        slack = RANGE_SLACK * hi  # a slider's ends come back through the browser's decimal arithmetic
        if not (lo - slack <= radius <= hi + slack):
            raise BadRequest(f"radius must lie in [{lo:.6g}, {hi:.6g}] (model units), got {radius:.6g}")
        radius = min(max(radius, lo), hi)
        with self.build_lock:
            stiffness = self.model.stiffness(self.mask, radius)
            # the mouse is not a device: a drag may move the probe several edge lengths between two page
            # updates, which a device's plausibility check (max_jump) would hold as an implausible jump
            contacts = Contacts(stiffness, N_PROBES, engine=self.engine, max_jump=2.0 * self.diag, levels=self.levels)
            contacts.start(self.rate, spin=self.spin)
            contacts.set_probes([self.park] * N_PROBES)
            # what the replies read per contact (the proxy point and the mesh point under it), made now
            contacts.surface.python_views(contacts.surface.POINT_VIEWS)
            masked = _norms(stiffness.K_vertex)
            rest = np.array(contacts.surface.mesh_points)  # the mesh where the contact surface has its vertices
            with self.lock:
                old, self.contacts = self.contacts, contacts
                self.rest = rest
                self.stiffness = stiffness
                self.radius = float(radius)
                self.fields["masked"] = masked
            if old is not None:
                old.stop()

    def close(self) -> None:
        """Stop the servo thread."""
        with self.lock:
            if self.contacts is not None:
                self.contacts.stop()

    def rest_json(self) -> dict:
        """The surface at rest as the page draws it for the current radius: the mesh where the contact surface has
        its vertices (:attr:`pmask.runtime.contact.ContactSurface.mesh_points`: the model's points, except that the
        contact surface rounds creases at the contact normals' blending radius, which follows the mask's radius),
        and the scan's lift onto it (:meth:`pmask.runtime.display.DisplaySurface.on`), base64 float32."""
        with self.lock:
            rest = self.rest
        out = {"rest": _b64(rest, np.float32)}
        if self.display is not None:
            out["lift"] = _b64(self.display.on(rest).lift, np.float32)
        return out

    def model_json(self) -> dict:
        m = self.model
        units = m.attrs.get("units", {}) if isinstance(m.attrs.get("units"), dict) else {}
        return {"name": Path(m.path).name if m.path else "model", "units": units.get("length", "model units"),
                "points": m.points.ravel().tolist(), "triangles": m.triangles.ravel().tolist(), **self.rest_json(),
                "mask": self.mask, "radius": self.radius, "radius_range": list(self.radius_range),
                "mean_edge": m.mean_edge_length, "diag": self.diag, "n_probes": N_PROBES,
                "engine": self.contacts.engine, "rate": self.rate,
                "fields": {k: v.tolist() for k, v in self.fields.items()},
                "display": None if self.display is None else {
                    "points": _b64(self.display.points, np.float32), "triangles": _b64(self.display.triangles, np.uint32),
                    "vertices": _b64(self.display.vertices, np.uint32), "bary": _b64(self.display.bary, np.float32)}}

    def probe(self, probes: list, deform: bool, client: str = "") -> dict:
        """Set the probes (None: lifted) and return the servo thread's latest contacts.  ``client``: the page's
        id; the probes are applied only for the page that owns them (module docstring)."""
        with self.lock:
            c, stiffness = self.contacts, self.stiffness  # one radius for the whole answer
            now = time.monotonic()
            touching = any(p is not None for p in probes)
            owner = (self.owner is None or self.owner == client or now - self.owner_seen > OWNER_LEASE)
            if owner:
                self.owner = client if touching else None
                self.owner_seen = now
                c.set_probes([self.park if p is None else p for p in probes])
                self.applied = list(probes)
            shown = probes if owner else self.applied  # a page that does not own them sees the owner's probes
            forces, statuses = c.read()
            states = c.states
            stats = c.tick_stats()
            u = c.deformation() if deform else None
            if owner:  # the page's silence counts from here, not from when the server began its answer
                self.owner_seen = time.monotonic()
        out = []
        for k, (f, s, st) in enumerate(zip(forces, statuses, states)):
            f = [float(x) for x in f]
            entry = {"probe": shown[k], "force": f, "force_norm": math.sqrt(sum(x * x for x in f)),
                     "status": Status(int(s)).name, "depth": float(st.depth), "proxy": None, "k_norm": None}
            if st.tri >= 0 and shown[k] is not None:
                entry["proxy"] = list(tracking.point(c.surface, st.tri, *st.b))  # on the contact surface
                tm, *beta = c.surface.mesh_point(st.tri, *st.b)  # K(x) (eq. 15) on the mesh, where K_i live
                K = (np.asarray(beta) @ stiffness.table[tm]).reshape(3, 3)
                entry["k_norm"] = float(np.linalg.norm(K, 2))
            out.append(entry)
        reply = {"contacts": out, "servo": {"engine": c.engine, "rate": self.rate, "ticks": int(stats["ticks"]),
                                           "late": int(stats["late"]), "step_max": float(stats["step_max"])},
                 "radius": self.radius, "owner": owner}
        if not owner:
            reply["notice"] = NOT_OWNER
        if u is not None:
            reply["deformation"] = _b64(u, np.float32)
        return reply

    # ------------------------------------------------------------------ requests
    def respond(self, method: str, path: str, body: bytes = b"") -> tuple[int, str, bytes]:
        """(status, content type, payload) for one request.  Never raises."""
        try:
            return self._respond(method, path.split("?", 1)[0], body)
        except BadRequest as exc:
            return _json(400, {"error": str(exc)})
        except Exception:  # a bug of ours: the log gets the traceback, the client one line
            log.exception("internal error in the viewer (please report it)")
            return _json(500, {"error": "internal error in the viewer; see the server's log"})

    def _respond(self, method, path, body):
        if method == "GET" and path in FILES:
            name, ctype = FILES[path]
            try:
                return 200, ctype, (STATIC / name).read_bytes()
            except OSError:
                return _json(500, {"error": f"{name} is missing from the installation (see pmask view's error)"})
        if method == "GET" and path == "/api/model":
            return _json(200, self.model_json())
        if method == "GET" and path == "/api/health":
            return _json(200, {"ok": True})
        if method == "POST" and path == "/api/probe":
            msg = _message(body)
            probes = msg.get("probes")
            if not isinstance(probes, list) or len(probes) != N_PROBES:
                raise BadRequest(f"probes must be a list of {N_PROBES} entries, each [x, y, z] or null")
            probes = [None if p is None else _vec3(p, "a probe") for p in probes]
            deform = msg.get("deform", False)
            if not isinstance(deform, bool):
                raise BadRequest("deform must be true or false")
            client = msg.get("client", "")
            if not isinstance(client, str) or len(client) > 64:
                raise BadRequest("client must be a string of at most 64 characters (the page's id)")
            try:
                return _json(200, self.probe(probes, deform, client))
            except InputError:  # the servo stopped under the request: the server is closing
                if self.contacts is not None and self.contacts.running:
                    raise
                return _json(503, {"error": "the servo has stopped: the server is shutting down"})
        if method == "POST" and path == "/api/radius":
            r = _message(body).get("radius")
            if isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r):
                raise BadRequest("radius must be a finite number (model units)")
            try:
                self._build(float(r))
            except PmaskError as exc:  # e.g. a mask too large for the body: the old radius stays
                raise BadRequest(str(exc)) from None
            with self.lock:
                masks, radius, masked = self.stiffness.masks, self.radius, self.fields["masked"]
            return _json(200, {"radius": radius, "masked": masked.tolist(), **self.rest_json(),
                               "single_vertex": int(masks.single_vertex), "masks": int(len(masks.centres))})
        if path in FILES or path.startswith("/api/"):
            return _json(405, {"error": f"{method[:20]!r} is not allowed on {path[:200]!r}"})
        return _json(404, {"error": f"no such page: {path[:200]!r}"})


def _message(body: bytes) -> dict:
    try:
        msg = json.loads(body.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise BadRequest("the body must be a JSON object (UTF-8)") from None
    if not isinstance(msg, dict):
        raise BadRequest("the body must be a JSON object")
    return msg


def _json(status: int, obj) -> tuple[int, str, bytes]:
    return status, "application/json", json.dumps(obj, allow_nan=False).encode()


def _b64(a: np.ndarray, dtype) -> str:
    """An array as base64 of its little-endian values (the page reads them as typed arrays)."""
    return base64.b64encode(np.ascontiguousarray(a, np.dtype(dtype).newbyteorder("<")).tobytes()).decode()


def _norms(K: np.ndarray) -> np.ndarray:
    """‖K_i‖₂ per vertex (the largest eigenvalue of the symmetric rendered K_i)."""
    return np.linalg.norm(K, ord=2, axis=(1, 2))


class _Handler(http.server.BaseHTTPRequestHandler):
    session: ViewerSession = None
    disable_nagle_algorithm = True  # headers and body are two writes: Nagle + delayed ACK held each answer 40 ms
    timeout = 10  # a client that stops sending mid-request gives up its thread after this long
    protocol_version = "HTTP/1.1"
    server_version = "pmask-view"

    def send_error(self, code, message=None, explain=None):
        """The standard library's own refusals (a request line it cannot parse, a header too long) as one
        JSON line like every other answer."""
        self.close_connection = True
        line = f"{code} {message or self.responses.get(code, ('',))[0]}"
        try:
            self._answer(*_json(code, {"error": line[:300]}))
        except OSError:
            pass

    def _answer(self, status, ctype, payload):
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(payload)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(payload)

    def _handle(self):
        body = b""
        if self.command == "POST":
            length = self.headers.get("Content-Length")
            try:
                n = int(length)
            except (TypeError, ValueError):
                self.close_connection = True
                return self._answer(*_json(411, {"error": "a POST needs a Content-Length"}))
            if n < 0 or n > MAX_BODY:
                self.close_connection = True
                return self._answer(*_json(413, {"error": f"the body must be at most {MAX_BODY} bytes"}))
            body = self.rfile.read(n)
            if len(body) != n:
                self.close_connection = True
                return
        self._answer(*self.session.respond(self.command, self.path, body))

    do_GET = do_POST = _handle

    def do_PUT(self):
        self._answer(*_json(405, {"error": f"{self.command} is not allowed"}))

    do_DELETE = do_PATCH = do_OPTIONS = do_HEAD = do_PUT

    def log_message(self, fmt, *args):  # the console stays for the URL and real problems
        log.debug("%s %s", self.address_string(), fmt % args)


class ViewerServer(http.server.ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def handle_error(self, request, client_address):  # a client that hangs up mid-answer is not news
        log.debug("connection from %s ended badly", client_address, exc_info=True)


def check_page() -> None:
    """The bundled page exists (it is built from npm when the package is built)."""
    if not (STATIC / "viewer.bundle.js").is_file():
        raise ViewerError("the viewer's page was not built into this installation (npm was missing when it was "
                          "built): install Node.js and npm, then reinstall pmask (make venv), or run "
                          "`npm ci --prefix viewer && npm run --prefix viewer build` in a checkout")


def make_server(session: ViewerSession, host: str = "127.0.0.1", port: int = 8765) -> ViewerServer:
    """Bind the server (port 0: any free port); a port in use is one line."""
    handler = type("Handler", (_Handler,), {"session": session})
    try:
        return ViewerServer((host, port), handler)
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise ViewerError(f"port {port} on {host} is already in use: choose another with --port "
                              "(--port 0 picks a free one)") from None
        if exc.errno in (errno.EADDRNOTAVAIL, errno.EACCES) or isinstance(exc, __import__("socket").gaierror):
            raise ViewerError(f"cannot listen on {host}:{port} ({exc.strerror or exc}); check --host and --port") from None
        raise


def serve(artifact, *, host: str = "127.0.0.1", port: int = 8765, mask: str = "linear", radius=None,
          engine: str | None = None, levels="auto", ready=None) -> None:
    """``pmask view``: load (refusing a foreign or corrupt artifact before anything listens), bind, print
    the URL, serve until Ctrl-C (KeyboardInterrupt) and stop the servo thread.  ``ready(url)`` is called
    once it listens (tests)."""
    check_page()
    if port is not None and not (0 <= int(port) <= 65535):
        raise InputError(f"--port must lie in 0..65535, got {port}")
    t0 = time.perf_counter()
    model = Model.load(artifact)
    session = ViewerSession(model, mask=mask, radius=radius, engine=engine, levels=levels)
    try:
        server = make_server(session, host, port)
    except BaseException:
        session.close()
        raise
    url = f"http://{host if ':' not in host else '[' + host + ']'}:{server.server_address[1]}/"
    where = ("127.0.0.1 only (this machine; --host to change)" if host == "127.0.0.1"
             else f"{host}: other machines may reach it")
    lv = session.contacts.surface.levels
    on = f" on its subdivision surface ({lv} level{'s' if lv > 1 else ''})" if lv else ""
    print(f"pmask view: {Path(str(artifact)).name} ({len(model.points)} surface vertices, servo {session.contacts.engine} "
          f"at {session.rate:.0f} Hz{on}, ready in {time.perf_counter() - t0:.1f} s)\n"
          f"listening on {where}\nopen {url}  (Ctrl-C stops)", flush=True)
    if ready is not None:
        ready(url)
    try:
        server.serve_forever(poll_interval=0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
        session.close()
    print("pmask view: stopped", flush=True)
