"""The viewer in a real browser (Debian's chromium, headless, software WebGL through SwiftShader): frames
per second the page draws and servo reads per second it makes, idle and while a probe presses and slides
with the deformation shown, at the default kidney and at ~4,000 surface vertices; the servo thread's late
ticks meanwhile; and the README's screenshot (docs/viewer.png).

Headless chromium here draws with the CPU (no GPU on this machine), on the same 2 cores as the server, its
1 kHz servo thread and the browser's own processes: a floor, not what a desktop with a GPU shows.
"""
from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

import numpy as np

DOCS = Path(__file__).resolve().parent.parent / "docs"
WINDOW = (1280, 800)


def _browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    o = Options()
    o.binary_location = shutil.which("chromium")
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={WINDOW[0]},{WINDOW[1]}",
              "--enable-unsafe-swiftshader", "--use-angle=swiftshader"):
        o.add_argument(a)
    return webdriver.Chrome(options=o, service=Service(shutil.which("chromedriver")))


def _windows(d, since: int, touching: bool):
    h = d.execute_script("return window.pmaskView.stats.history")[since:]
    return [w for w in h if w["touching"] == touching]


def one(path: Path, screenshot: Path | None = None) -> dict:
    from selenium.webdriver.common.action_chains import ActionChains

    from pmask.runtime import Model
    from pmask.viewer.server import ViewerSession, make_server

    m = Model.load(path)
    session = ViewerSession(m)
    srv = make_server(session, "127.0.0.1", 0)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    d = _browser()
    try:
        d.get(f"http://127.0.0.1:{srv.server_address[1]}/")
        for _ in range(400):
            if d.execute_script("return document.body.dataset.ready") == "1":
                break
            time.sleep(0.05)
        time.sleep(6.5)  # idle: rendering alone
        idle = _windows(d, 1, False)
        # a probe on the vertex nearest the screen centre that faces the camera, far from the support
        P = m.points
        core = m.contact[m.core]
        far = core[np.min(np.linalg.norm(P[core][:, None] - P[m.fixed][None], axis=2), axis=1) > 4 * m.mean_edge_length]
        order = far[np.argsort(np.linalg.norm(P[far] - P.mean(axis=0), axis=1))]
        v = next(int(i) for i in order if d.execute_script(f"return window.pmaskView.facing({int(i)})"))
        x, y = d.execute_script(f"return window.pmaskView.screenOf({v})")
        n0 = len(d.execute_script("return window.pmaskView.stats.history"))
        t0 = session.contacts.tick_stats()
        a = ActionChains(d, duration=50)
        a.w3c_actions.pointer_action.move_to_location(int(x), int(y))
        a.w3c_actions.pointer_action.pointer_down()
        for k in range(160):  # 8 s of sliding back and forth, 50 ms per move
            a.w3c_actions.pointer_action.move_by(6 if (k // 20) % 2 == 0 else -6, 0)
        a.perform()
        t1 = session.contacts.tick_stats()
        if screenshot is not None:
            d.execute_script("const e = document.getElementById('exaggeration'); e.value = 3; e.dispatchEvent(new Event('input'));")
            time.sleep(1.0)
            d.save_screenshot(str(screenshot))
        ActionChains(d).release().perform()
        probing = _windows(d, n0 + 1, True)
        radius = radius_change(session)
    finally:
        d.quit()
    try:  # the same changes with the page closed: the server's own cost, without the browser on the same cores
        radius["alone"] = radius_change(session)
    finally:
        srv.shutdown()
        srv.server_close()
        session.close()

    def summary(ws):
        f = [w["fps"] for w in ws]
        u = [w["ups"] for w in ws]
        return {"windows": len(ws), "fps_median": float(np.median(f)) if f else None, "fps_min": min(f) if f else None,
                "reads_median": float(np.median(u)) if u else None}

    return {"surface_vertices": len(m.points), "idle": summary(idle), "probing": summary(probing),
            "servo_ticks": t1["ticks"] - t0["ticks"], "servo_late": t1["late"] - t0["late"], "window": list(WINDOW),
            "radius_change": radius}


def radius_change(session, changes: int = 6) -> dict:
    """A radius change as the page makes it (POST /api/radius: K_i, contact surface, ζ table, a new servo
    thread, the swap), between 2 and 2.5 mean edges and back, with the page open and polling; meanwhile a
    probe request every 2 ms from another thread, whose longest gap between answers shows whether the probe
    stayed live.  The same probe loop without a rebuild is the noise reference."""
    import json

    from pmask.viewer.server import N_PROBES

    h = session.model.mean_edge_length
    def gaps(seconds=None, during=None):
        out, last = [], time.perf_counter()
        start = last
        while during() if during else time.perf_counter() - start < seconds:
            session.probe([None] * N_PROBES, deform=False)
            now = time.perf_counter()
            out.append(now - last)
            last = now
            time.sleep(0.002)
        return out

    times, live = [], []
    for k in range(changes):
        r = (2.5 if k % 2 == 0 else 2.0) * h
        t = threading.Thread(target=lambda r=r: times.append(_timed(session.respond, "POST", "/api/radius",
                                                                     json.dumps({"radius": r}).encode())))
        t.start()
        live += gaps(during=t.is_alive)
        t.join()
    idle = gaps(seconds=2.0)
    return {"changes": changes, "rebuild_s_median": float(np.median(times)), "rebuild_s_max": float(max(times)),
            "probe_gap_ms_max": 1e3 * float(max(live)), "probe_gap_ms_max_idle": 1e3 * float(max(idle))}


def _timed(f, *args) -> float:
    t0 = time.perf_counter()
    status = f(*args)[0]
    if status != 200:
        raise RuntimeError(f"radius change answered {status}")
    return time.perf_counter() - t0


def run(arts: dict) -> dict:
    """arts: {surface vertices: artifact path}; the default kidney's run also writes docs/viewer.png."""
    if not (shutil.which("chromium") and shutil.which("chromedriver")):
        return {"skipped": "no chromium + chromedriver (make system-deps)"}
    out = {}
    for n, path in sorted(arts.items()):
        print(f"viewer {n} vertices ...", flush=True)
        out[str(n)] = one(path, DOCS / "viewer.png" if 1000 < n < 2000 else None)
    return out


def markdown(res: dict) -> str:
    if "skipped" in res:
        return f"**Viewer**: not measured ({res['skipped']})."
    L = [f"**Viewer** (`pmask view` in headless chromium, {res[next(iter(res))]['window'][0]}x"
         f"{res[next(iter(res))]['window'][1]}, software WebGL on the same 2 cores as the server and its 1 kHz servo "
         "thread; 1 s windows): frames per second drawn and servo reads per second (each a round trip that sets the "
         "probes and fetches forces and the deformation), idle and while a probe presses and slides.  The page draws "
         "on demand (a frame only after something it shows changed) and, idle, asks the server 10 times a second: "
         "an idle page leaves the cores to the servo and to a radius change",
         "", "| surface vertices | idle: frames drawn/s (median) | idle: servo reads/s (median) | probing fps median | "
         "probing fps min | probing: servo reads/s median | servo late ticks while probing |",
         "|---|---|---|---|---|---|---|"]
    for n, r in res.items():
        i, p = r["idle"], r["probing"]
        idle_reads = f"{i['reads_median']:.0f}" if i.get("reads_median") is not None else "–"
        L.append(f"| {n} | {i['fps_median']:.0f} | {idle_reads} | {p['fps_median']:.0f} | {p['fps_min']:.0f} | "
                 f"{p['reads_median']:.0f} | {r['servo_late']} of {r['servo_ticks']} |")
    rc = {n: r["radius_change"] for n, r in res.items() if r.get("radius_change")}
    if rc:
        L += ["", "**Radius change in the viewer** (POST /api/radius between 2 and 2.5 mean edges, the page open: K_i, "
              "contact surface, ζ table and a new servo thread built beside the running one, then swapped; a probe "
              "request every 2 ms meanwhile, its longest wait beside the same loop's with no rebuild; then the same "
              "changes with the page closed: the server's own cost, without the browser's software rendering on the "
              "same 2 cores)", "",
              "| surface vertices | changes | rebuild s median | rebuild s max | longest probe wait during, ms | "
              "longest probe wait idle, ms | page closed: rebuild s median | page closed: rebuild s max |",
              "|---|---|---|---|---|---|---|---|"]
        for n, r in rc.items():
            a = r.get("alone")
            alone = f"{a['rebuild_s_median']:.2f} | {a['rebuild_s_max']:.2f}" if a else "– | –"
            L.append(f"| {n} | {r['changes']} | {r['rebuild_s_median']:.2f} | {r['rebuild_s_max']:.2f} | "
                     f"{r['probe_gap_ms_max']:.1f} | {r['probe_gap_ms_max_idle']:.1f} | {alone} |")
    return "\n".join(L)


if __name__ == "__main__":
    import sys

    from pmask.runtime import Model

    res = run({len(Model.load(p).points): Path(p) for p in sys.argv[1:]})
    print(markdown(res))
