// pmask view: the page.  Draws the surface (three.js), colours it by a field the server sends, turns
// the mouse into probes and shows what the server's 1 kHz servo renders for them: force, proxy,
// status, and the deformation of eq. 16.  The contact algorithm is not here: the page only sets probe
// positions (POST /api/probe) and reads the servo's latest state, as a device driver would.
import * as THREE from 'three';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';

const $ = (id) => document.getElementById(id);
const PRESS_MS = 150;            // a press ramps from just outside to the set depth over this long
// an idle page (no probe of its own or another page's, the surface at rest) asks the server this often instead of
// every frame, and draws only when something it shows changed: it leaves the cores to the servo and to a rebuild
const IDLE_POLL_MS = 100;
const COLOURS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]]; // viridis stops
const PROBE_COLOURS = [0xff5a5a, 0x5ab4ff];
// this page's id: the server applies the probes of one page at a time and tells the others
const CLIENT = Array.from({ length: 4 }, () => Math.floor(Math.random() * 2 ** 32).toString(16)).join('');

function colourAt(t) {
  t = Math.min(1, Math.max(0, t)) * (COLOURS.length - 1);
  const i = Math.min(COLOURS.length - 2, Math.floor(t));
  const f = t - i;
  return COLOURS[i].map((c, k) => (c + f * (COLOURS[i + 1][k] - c)) / 255);
}

function fmt(x, digits = 6) {
  return Number(x).toPrecision(digits);
}

async function api(path, body) {
  const r = await fetch(path, body === undefined ? {} : {
    method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) });
  const j = await r.json();
  if (!r.ok) throw new Error(j.error || r.statusText);
  return j;
}

async function main() {
  const model = await api('/api/model');
  const mm = model.units === 'm' ? 1000 : 1;            // lengths shown in mm when the model is in metres
  const lenUnit = model.units === 'm' ? 'mm' : model.units;
  $('title').textContent = `pmask view · ${model.name}`;
  const typed = (b64, T) => new T(Uint8Array.from(atob(b64), (ch) => ch.charCodeAt(0)).buffer);
  const n = model.points.length / 3;
  // the surface at rest where the contact surface has its vertices (rounded at creases; the server sends it
  // again when the radius changes it): the deformation is drawn on it, so the shown surface meets the tool
  const base = typed(model.rest, Float32Array);
  const index = model.triangles;

  // ---------------------------------------------------------------- scene
  const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setSize(window.innerWidth, window.innerHeight);
  $('view').appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x1b1d22);
  const centre = new THREE.Vector3();
  for (let i = 0; i < n; i++) centre.add(new THREE.Vector3(base[3 * i], base[3 * i + 1], base[3 * i + 2]));
  centre.multiplyScalar(1 / n);
  const camera = new THREE.PerspectiveCamera(35, window.innerWidth / window.innerHeight, model.diag * 0.01, model.diag * 20);
  camera.position.copy(centre).add(new THREE.Vector3(0.3, -0.75, 1.25).multiplyScalar(model.diag));
  camera.up.set(0, 0, 1);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x303040, 1.6));
  const sun = new THREE.DirectionalLight(0xffffff, 1.4);
  camera.add(sun);
  sun.position.set(0.3, 0.5, 1);
  scene.add(camera);

  const geom = new THREE.BufferGeometry();
  geom.setAttribute('position', new THREE.BufferAttribute(base.slice(), 3));
  geom.setAttribute('color', new THREE.BufferAttribute(new Float32Array(3 * n), 3));
  geom.setIndex(index);
  geom.computeVertexNormals();
  const mesh = new THREE.Mesh(geom, new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide }));
  scene.add(mesh);
  // the scan's surface at its own resolution, carried by the simulation surface (pmask.runtime.display)
  let scan = null;
  if (model.display) {
    const d = model.display;
    scan = { base: typed(d.points, Float32Array), tris: typed(d.triangles, Uint32Array),
      v: typed(d.vertices, Uint32Array), b: typed(d.bary, Float32Array), lift: typed(model.lift, Float32Array) };
    scan.n = scan.base.length / 3;
    scan.geom = new THREE.BufferGeometry();
    scan.geom.setAttribute('position', new THREE.BufferAttribute(scan.base.slice(), 3));
    scan.geom.setAttribute('color', new THREE.BufferAttribute(new Float32Array(3 * scan.n), 3));
    scan.geom.setIndex(new THREE.BufferAttribute(scan.tris, 1));
    scan.geom.computeVertexNormals();
    scan.mesh = new THREE.Mesh(scan.geom, new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide }));
    scene.add(scan.mesh);
    mesh.visible = false;
    $('scanBox').hidden = false;
    $('scanCount').textContent = (scan.tris.length / 3).toLocaleString('en');
    $('scan').addEventListener('change', () => {
      scan.mesh.visible = $('scan').checked; mesh.visible = !$('scan').checked; redraw();
    });
  }
  // picking uses the undeformed surface: the probe is where the hand is, not where the tissue went
  const pickGeom = new THREE.BufferGeometry();
  pickGeom.setAttribute('position', new THREE.BufferAttribute(base, 3));
  pickGeom.setIndex(index);
  const pickMesh = new THREE.Mesh(pickGeom, new THREE.MeshBasicMaterial({ visible: false, side: THREE.DoubleSide }));
  scene.add(pickMesh);

  // drawn on demand: a frame is drawn only after something shown changed (the camera, a reply, a colour)
  let dirty = true;
  const redraw = () => { dirty = true; };
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.target.copy(centre);
  controls.addEventListener('change', redraw);
  controls.update();

  const markers = [0, 1].map((k) => {
    const r = 0.35 * model.mean_edge;
    const probe = new THREE.Mesh(new THREE.SphereGeometry(r, 16, 12),
      new THREE.MeshBasicMaterial({ color: PROBE_COLOURS[k], wireframe: true }));
    const proxy = new THREE.Mesh(new THREE.SphereGeometry(0.8 * r, 16, 12), new THREE.MeshBasicMaterial({ color: 0xffe14d }));
    const arrow = new THREE.ArrowHelper(new THREE.Vector3(0, 0, 1), new THREE.Vector3(), 1, PROBE_COLOURS[k]);
    for (const o of [probe, proxy, arrow]) { o.visible = false; scene.add(o); }
    return { probe, proxy, arrow };
  });

  // ---------------------------------------------------------------- colour
  const fields = model.fields;
  const contactIdx = [];
  fields.contact.forEach((c, i) => { if (c > 0) contactIdx.push(i); });
  const FIELD_INFO = {
    masked: ['‖K_i‖₂ with the mask [N/m] (2nd to 98th percentile of the contact region, beyond clamped)', 'N/m'],
    single: ['‖K_i‖₂ single vertex [N/m] (2nd to 98th percentile of the contact region, beyond clamped)', 'N/m'],
    area: [`vertex area [${lenUnit}²]`, `${lenUnit}²`],
    fixed: ['fixed region (yellow)', ''],
    contact: ['contact region (yellow)', ''],
  };
  function percentile(sorted, q) {   // numpy's default (linear between the closest ranks)
    const x = (q / 100) * (sorted.length - 1), i = Math.floor(x), f = x - i;
    return i + 1 < sorted.length ? sorted[i] + f * (sorted[i + 1] - sorted[i]) : sorted[i];
  }
  function recolour() {
    const name = $('field').value;
    const v = fields[name];
    const scale = name === 'area' ? mm * mm : 1;
    let lo = Infinity, hi = -Infinity;
    const over = (name === 'masked' || name === 'single') && contactIdx.length ? contactIdx : v.map((_, i) => i);
    if (name === 'masked' || name === 'single') {
      // a robust range: the few stiff vertices by the support would leave the rest of the organ one colour
      const sorted = over.map((i) => v[i]).sort((a, b) => a - b);
      lo = percentile(sorted, 2); hi = percentile(sorted, 98);
    } else {
      for (const i of over) { lo = Math.min(lo, v[i]); hi = Math.max(hi, v[i]); }
    }
    if (name === 'fixed' || name === 'contact') { lo = 0; hi = 1; }
    const col = geom.attributes.color.array;
    for (let i = 0; i < n; i++) {
      const c = colourAt(hi > lo ? (v[i] - lo) / (hi - lo) : 0.5);
      col[3 * i] = c[0]; col[3 * i + 1] = c[1]; col[3 * i + 2] = c[2];
    }
    geom.attributes.color.needsUpdate = true;
    if (scan) {   // the scan's vertices take the colour of their closest point on the simulation surface
      const dc = scan.geom.attributes.color.array;
      for (let d = 0; d < scan.n; d++)
        for (let c = 0; c < 3; c++) {
          dc[3 * d + c] = scan.b[3 * d] * col[3 * scan.v[3 * d] + c] + scan.b[3 * d + 1] * col[3 * scan.v[3 * d + 1] + c]
            + scan.b[3 * d + 2] * col[3 * scan.v[3 * d + 2] + c];
        }
      scan.geom.attributes.color.needsUpdate = true;
    }
    $('legendTitle').textContent = FIELD_INFO[name][0];
    const unit = FIELD_INFO[name][1];
    $('cmin').textContent = name === 'fixed' || name === 'contact' ? 'no' : `${fmt(lo * scale, 4)} ${unit}`;
    $('cmax').textContent = name === 'fixed' || name === 'contact' ? 'yes' : `${fmt(hi * scale, 4)} ${unit}`;
    $('cmin').dataset.value = lo; $('cmax').dataset.value = hi;
    redraw();
  }
  $('bar').style.background = `linear-gradient(to right, ${COLOURS.map((c) => `rgb(${c})`).join(',')})`;
  $('field').addEventListener('change', recolour);
  recolour();

  // ---------------------------------------------------------------- sliders
  let notice = '';   // a standing message (the radius's single-vertex fallback) the probe loop keeps on show
  const radius = $('radius');
  radius.min = model.radius_range[0]; radius.max = model.radius_range[1];
  radius.step = (model.radius_range[1] - model.radius_range[0]) / 400;
  radius.value = model.radius;
  function setRest(r) {   // the rest surface and the scan's lift onto it for the new radius
    base.set(typed(r.rest, Float32Array));
    if (scan) scan.lift.set(typed(r.lift, Float32Array));
    pickGeom.attributes.position.needsUpdate = true;
    pickGeom.computeBoundingSphere();
    pickGeom.computeBoundingBox();
    geom.attributes.position.array.set(base);   // until the next deformation is drawn on it
    geom.attributes.position.needsUpdate = true;
    geom.computeVertexNormals();
    redraw();
  }
  const showRadius = () => { $('radiusLabel').textContent = `${fmt(radius.value * mm, 3)} ${lenUnit}`; };
  showRadius();
  radius.addEventListener('input', showRadius);
  radius.addEventListener('change', async () => {
    radius.disabled = true;
    try {
      const r = await api('/api/radius', { radius: Number(radius.value) });
      fields.masked = r.masked;
      radius.value = r.radius;
      setRest(r);
      recolour();
      notice = r.single_vertex > 0   // kept on show (the probe loop's replies would clear a plain message)
        ? `at this radius ${r.single_vertex} of ${r.masks} masks reach no neighbour and fall back to the `
          + 'single-vertex stiffness (which softens with refinement): use at least one mean edge length' : '';
      $('error').textContent = notice;
    } catch (e) { $('error').textContent = `radius: ${e.message}`; }
    radius.disabled = false;
    radius.dataset.applied = radius.value;
  });
  const depth = $('depth');
  depth.min = 0; depth.max = 4 * model.mean_edge; depth.step = model.mean_edge / 50; depth.value = model.mean_edge;
  const showDepth = () => { $('depthLabel').textContent = `${fmt(depth.value * mm, 3)} ${lenUnit}`; };
  showDepth();
  depth.addEventListener('input', showDepth);
  const exaggeration = $('exaggeration');
  exaggeration.addEventListener('input', () => { $('exaggerationLabel').textContent = exaggeration.value; redraw(); });
  $('exaggerationLabel').textContent = exaggeration.value;

  // ---------------------------------------------------------------- probes
  const press = [null, null];     // {point, normal, t0} per probe while it is on the body
  let drag = null;                // which probe the mouse holds
  const raycaster = new THREE.Raycaster();
  function hitAt(ev) {
    const rect = renderer.domElement.getBoundingClientRect();
    const ndc = new THREE.Vector2(((ev.clientX - rect.left) / rect.width) * 2 - 1,
      -((ev.clientY - rect.top) / rect.height) * 2 + 1);
    raycaster.setFromCamera(ndc, camera);
    const hits = raycaster.intersectObject(pickMesh, false);
    if (!hits.length) return null;
    const h = hits[0];
    const normal = h.face.normal.clone();
    if (normal.dot(raycaster.ray.direction) > 0) normal.negate();   // the side the ray came from
    return { point: h.point.clone(), normal };
  }
  // capture phase on the container: a press on the body is the probe's, anything else orbits
  $('view').addEventListener('pointerdown', (ev) => {
    if (ev.button !== 0) return;
    const hit = hitAt(ev);
    const k = ev.shiftKey ? 1 : 0;
    if (!hit) { if (k === 1) press[1] = null; return; }
    ev.stopPropagation();
    drag = k;
    press[k] = { ...hit, t0: performance.now() };
    renderer.domElement.setPointerCapture(ev.pointerId);
  }, true);
  renderer.domElement.addEventListener('pointermove', (ev) => {
    if (drag === null || !press[drag]) return;
    const hit = hitAt(ev);
    if (hit) { press[drag].point = hit.point; press[drag].normal = hit.normal; }
  });
  const release = () => {
    if (drag === 0) press[0] = null;   // probe 1 lifts; probe 2 stays where it was left
    drag = null;
  };
  renderer.domElement.addEventListener('pointerup', release);
  renderer.domElement.addEventListener('pointercancel', release);
  function probePositions(now) {
    return press.map((p) => {
      if (!p) return null;
      const d = Number(depth.value);
      const start = -0.5 * model.mean_edge;            // begin just outside: contact starts by crossing
      const s = Math.min(1, (now - p.t0) / PRESS_MS);
      const x = p.point.clone().addScaledVector(p.normal, -(start + s * (d - start)));
      return [x.x, x.y, x.z];
    });
  }

  // ---------------------------------------------------------------- server round trips
  // wasDeformed: the last reply's surface was displaced, so the page keeps asking for the deformation after a
  // release until the servo reports it flat (one request raced the servo's release and left it dented)
  let inflight = false, wasDeformed = false, othersProbe = false, retryAt = 0, backoff = 0, lastPoll = -Infinity;
  let shown = '';   // what the last drawn reply showed (contacts and deformation): an equal reply draws nothing
  const stats = { fps: 0, ups: 0, rtt: 0, frames: 0, updates: 0, failures: 0, drawn: 0, reads: 0, t0: performance.now(), history: [] };
  const disp = geom.attributes.position.array;
  function applyReply(reply) {
    const key = JSON.stringify(reply.contacts) + (reply.deformation || '');
    if (key !== shown) { shown = key; redraw(); }
    reply.contacts.forEach((c, k) => {
      const touching = c.status === 'CONTACT' || c.status === 'REGION_EDGE' || c.status === 'DEEP';
      $(`status${k}`).textContent = c.status;
      $(`force${k}`).textContent = `${fmt(c.force_norm)} N (${c.force.map((x) => fmt(x)).join(', ')})`;
      $(`force${k}`).dataset.force = JSON.stringify(c.force);
      $(`depth${k}`).textContent = `${fmt(c.depth * mm, 4)} ${lenUnit}`;
      $(`kx${k}`).textContent = c.k_norm === null ? '—' : `${fmt(c.k_norm, 4)} N/m`;
      $(`probe${k}`).dataset.probe = JSON.stringify(c.probe);
      $(`probe${k}`).textContent = c.probe ? `probe (${c.probe.map((x) => fmt(x * mm, 5)).join(', ')}) ${lenUnit}` : '';
      const m = markers[k];
      m.probe.visible = c.probe !== null;
      if (c.probe) m.probe.position.set(...c.probe);
      m.proxy.visible = c.proxy !== null && touching;
      if (c.proxy) m.proxy.position.set(...c.proxy);
      m.arrow.visible = touching && c.force_norm > 0;
      if (m.arrow.visible && c.proxy) {
        const dir = new THREE.Vector3(...c.force).normalize();
        const len = Math.min(0.3 * model.diag, 0.05 * model.diag * (1 + Math.log1p(c.force_norm / 0.1)));
        m.arrow.position.set(...c.proxy);
        m.arrow.setDirection(dir);
        m.arrow.setLength(len, 0.2 * len, 0.1 * len);
      }
    });
    const s = reply.servo;
    $('step').textContent = `${s.engine} thread at ${s.rate} Hz · step max ${fmt(s.step_max * 1e6, 3)} µs · `
      + `late ${s.late} of ${s.ticks} ticks`;
    let umax = 0;
    if (reply.deformation) {
      const bytes = Uint8Array.from(atob(reply.deformation), (ch) => ch.charCodeAt(0));
      const u = new Float32Array(bytes.buffer);
      const e = Number(exaggeration.value);
      for (let i = 0; i < 3 * n; i++) disp[i] = base[i] + e * u[i];
      geom.attributes.position.needsUpdate = true;
      geom.computeVertexNormals();
      for (let i = 0; i < n; i++) umax = Math.max(umax, Math.hypot(u[3 * i], u[3 * i + 1], u[3 * i + 2]));
      $('umax').textContent = `${fmt(umax * mm, 3)} ${lenUnit}`;
      if (scan) deformScan(u, e, reply);
    }
    return umax;
  }
  // x_d' = x_d + e Σ_k b_k u_{v_k} − w_d ℓ_d, w_d = max over the contacts' proxies of smoothstep(1 − |x_d − p| / r):
  // the scan lies on the deformed simulation surface where the tool presses (pmask.runtime.display)
  function deformScan(u, e, reply) {
    const proxies = reply.contacts.filter((c) => c.proxy && (c.status === 'CONTACT' || c.status === 'REGION_EDGE'
      || c.status === 'DEEP')).map((c) => c.proxy);
    const r = reply.radius, pos = scan.geom.attributes.position.array;
    for (let d = 0; d < scan.n; d++) {
      let w = 0;
      for (const p of proxies) {
        const s = Math.min(1, Math.max(0, 1 - Math.hypot(scan.base[3 * d] - p[0], scan.base[3 * d + 1] - p[1],
          scan.base[3 * d + 2] - p[2]) / r));
        w = Math.max(w, s * s * (3 - 2 * s));
      }
      const v0 = 3 * scan.v[3 * d], v1 = 3 * scan.v[3 * d + 1], v2 = 3 * scan.v[3 * d + 2];
      const b0 = scan.b[3 * d], b1 = scan.b[3 * d + 1], b2 = scan.b[3 * d + 2];
      for (let c = 0; c < 3; c++)
        pos[3 * d + c] = scan.base[3 * d + c] + e * (b0 * u[v0 + c] + b1 * u[v1 + c] + b2 * u[v2 + c])
          - w * scan.lift[3 * d + c];
    }
    scan.geom.attributes.position.needsUpdate = true;
    scan.geom.computeVertexNormals();
  }
  function serverLost(message) {   // no stale force on show, and no request every frame to a stopped server
    stats.failures++;
    backoff = Math.min(2000, backoff ? 2 * backoff : 100);
    retryAt = performance.now() + backoff;
    $('error').textContent = `server: ${message} (retrying every ${(backoff / 1000).toFixed(1)} s)`;
    shown = '';
    redraw();
    for (let k = 0; k < markers.length; k++) {
      $(`status${k}`).textContent = 'NO SERVER';
      $(`force${k}`).textContent = '—';
      $(`force${k}`).dataset.force = '';
      markers[k].arrow.visible = false;
    }
  }
  async function update(now) {
    inflight = true;
    lastPoll = now;
    const probes = probePositions(now);
    const touching = probes.some((p) => p !== null);
    const deform = Number(exaggeration.value) > 0 && (touching || wasDeformed || othersProbe);
    const t0 = performance.now();
    try {
      const reply = await api('/api/probe', { probes, deform, client: CLIENT });
      const umax = applyReply(reply);
      stats.updates++;
      stats.reads++;
      stats.rtt = performance.now() - t0;
      wasDeformed = deform && umax > 0;
      othersProbe = reply.owner === false;   // another page's probes are shown, and this page's wait
      document.body.dataset.owner = othersProbe ? '0' : '1';
      backoff = 0;
      $('error').textContent = othersProbe ? reply.notice : notice;
    } catch (e) { serverLost(e.message); }
    inflight = false;
  }

  // ---------------------------------------------------------------- frames
  window.addEventListener('resize', () => {
    camera.aspect = window.innerWidth / window.innerHeight;
    camera.updateProjectionMatrix();
    renderer.setSize(window.innerWidth, window.innerHeight);
    redraw();
  });
  function frame(now) {
    requestAnimationFrame(frame);
    const idle = !press.some((p) => p !== null) && !wasDeformed && !othersProbe && drag === null;
    if (!inflight && performance.now() >= retryAt && (!idle || now - lastPoll >= IDLE_POLL_MS)) update(now);
    controls.update();
    if (dirty) {
      dirty = false;
      renderer.render(scene, camera);
      stats.frames++;
      stats.drawn++;
    }
    if (now - stats.t0 >= 1000) {
      stats.fps = (1000 * stats.frames) / (now - stats.t0);
      stats.ups = (1000 * stats.updates) / (now - stats.t0);
      stats.frames = 0; stats.updates = 0; stats.t0 = now;
      stats.history.push({ fps: stats.fps, ups: stats.ups, rtt: stats.rtt, touching: press.some((p) => p !== null) });
      if (stats.history.length > 120) stats.history.shift();
      $('fps').textContent = `${fmt(stats.fps, 3)} frames/s · ${fmt(stats.ups, 3)} servo reads/s · round trip ${fmt(stats.rtt, 2)} ms`;
      $('fps').dataset.fps = stats.fps; $('fps').dataset.ups = stats.ups;
    }
  }
  requestAnimationFrame(frame);

  // test hooks: where a vertex is on the screen (for a scripted drag), and the page's rates
  window.pmaskView = {
    screenOf(i) {
      const v = new THREE.Vector3(base[3 * i], base[3 * i + 1], base[3 * i + 2]).project(camera);
      const rect = renderer.domElement.getBoundingClientRect();
      return [rect.left + (v.x + 1) / 2 * rect.width, rect.top + (1 - v.y) / 2 * rect.height];
    },
    facing(i) {   // the vertex normal points towards the camera and the vertex is the first thing hit
      const p = new THREE.Vector3(base[3 * i], base[3 * i + 1], base[3 * i + 2]);
      raycaster.set(camera.position, p.clone().sub(camera.position).normalize());
      const hits = raycaster.intersectObject(pickMesh, false);
      return hits.length > 0 && hits[0].point.distanceTo(p) < 0.5 * model.mean_edge;
    },
    rest(i) { return [base[3 * i], base[3 * i + 1], base[3 * i + 2]]; },   // where the surface is drawn at rest
    scanVertices() { return scan ? scan.n : 0; },
    scanPosition(d) { return scan ? Array.from(scan.geom.attributes.position.array.slice(3 * d, 3 * d + 3)) : null; },
    displacement() {   // the largest displacement shown (before exaggeration), for a scripted release
      let d = 0;
      for (let i = 0; i < n; i++) d = Math.max(d, Math.hypot(disp[3 * i] - base[3 * i], disp[3 * i + 1] - base[3 * i + 1],
        disp[3 * i + 2] - base[3 * i + 2]));
      return d;
    },
    stats,
    ready: true,
  };
  document.body.dataset.ready = '1';
}

main().catch((e) => { document.getElementById('error').textContent = `could not start: ${e.message}`; });
