// elastreg viewer: the model's boundary surface deforming live, the point cloud, the estimated
// forces as arrows, and each frame's status, error estimate and latency.
//   /viewer?session=ID            watch a session (WS /sessions/{id}/watch)
//   /viewer?model=ID&demo=1       stream a synthetic sequence itself (GET /models/{id}/demo, WS /stream)
//   optional: &rate=10 (demo frames per second), &frames=40, &points=500, &colour=error
//   a token, where the server needs one: #token=T, as it is or percent-encoded (the fragment
//   never reaches a server)
import * as THREE from './vendor/three.module.min.js';
import { OrbitControls } from './vendor/OrbitControls.js';

const params = new URLSearchParams(location.search);
const token = fragmentValue('token');

// A fragment's value, split by hand: URLSearchParams decodes a form, where a token's '+' (base64)
// would become a space; a percent-encoded value (%2B) still decodes
function fragmentValue(name) {
  for (const part of location.hash.slice(1).split('&')) {
    const eq = part.indexOf('=');
    if ((eq < 0 ? part : part.slice(0, eq)) !== name) continue;
    const raw = eq < 0 ? '' : part.slice(eq + 1);
    try {
      return decodeURIComponent(raw);
    } catch {  // a stray '%': no server token holds one (token68), its 401 will say so
      return raw;
    }
  }
  return null;
}
const state = {
  framesRendered: 0, lastError: null, overloads: 0, lastOverload: null, mode: null, session: null, model: null,
  lastFrameId: null, lastSeq: null, lastAck: null, errorEstimate: null, latencyMs: null, fps: null,
  renderLog: [],  // {frame_id, seq, t}: t = wall clock (ms) when the frame was on screen
};
window.elastregViewer = state;

const $ = (id) => document.getElementById(id);
function fail(err) {
  const text = (err && err.message) ? err.message : String(err);
  state.lastError = text;
  $('error').hidden = false;
  $('error').textContent = text;
  $('status').textContent = 'error';
  $('status').className = 'bad';
}
window.addEventListener('error', (e) => fail(e.error || e.message));
window.addEventListener('unhandledrejection', (e) => fail(e.reason));

// -- the API ------------------------------------------------------------------------------------

const headers = token ? { Authorization: `Bearer ${token}` } : {};
const API_TRIES = 10;  // a request refused under overload (503) is asked again, at most this often
async function api(path) {
  for (let tries = 1; ; tries++) {
    const r = await fetch(path, { headers: { Accept: 'application/json', ...headers } });
    const body = await r.json().catch(() => ({}));
    if (r.ok) return body;
    if (r.status === 503 && tries < API_TRIES) {  // the mesh and demo requests share the solve pool
      const wait = Number(r.headers.get('Retry-After')) || 1;
      busy(`${path}: ${JSON.stringify(body.detail ?? body)}`, wait, 'asking again');
      await new Promise((done) => setTimeout(done, 1e3 * wait));
      continue;
    }
    throw new Error(`${path}: ${r.status} ${JSON.stringify(body.detail ?? body)}`);
  }
}
function wsUrl(path) {
  return `${location.protocol === 'https:' ? 'wss' : 'ws'}://${location.host}${path}`;
}
const flat = (rows) => Float32Array.from(rows.flat());

// -- the scene ----------------------------------------------------------------------------------

const canvas = $('view');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x15181d);
const camera = new THREE.PerspectiveCamera(40, 1, 1e-4, 1e3);
const controls = new OrbitControls(camera, canvas);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404050, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.4);
scene.add(sun);

let mesh = null;  // {nodes Float32Array(3n), n, faces, surfaceNodes, size}
let surface, cloud, shafts, heads;
let dirty = true;
controls.addEventListener('change', () => { dirty = true; });
controls.addEventListener('start', () => { aimed = true; });

function resize() {
  const w = window.innerWidth, h = window.innerHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
  dirty = true;
}
window.addEventListener('resize', resize);
resize();

const REST_GREY = 0.6;  // the surface's colour before (or without) displacements
// viridis, 5 stops
const STOPS = [[0.267, 0.005, 0.329], [0.231, 0.322, 0.545], [0.129, 0.569, 0.549],
  [0.369, 0.788, 0.384], [0.993, 0.906, 0.144]];
function colormap(t, out, i) {
  const x = Math.min(Math.max(t, 0), 1) * (STOPS.length - 1);
  const k = Math.min(Math.floor(x), STOPS.length - 2), f = x - k;
  for (let c = 0; c < 3; c++) out[3 * i + c] = STOPS[k][c] * (1 - f) + STOPS[k + 1][c] * f;
}

function setMesh(m) {
  const nodes = flat(m.nodes);
  const n = nodes.length / 3;
  const box = new THREE.Box3().setFromArray(nodes);
  const size = box.getSize(new THREE.Vector3()).length();
  const centre = box.getCenter(new THREE.Vector3());
  mesh = { nodes, n, size, surfaceNodes: Int32Array.from(m.surface_nodes) };

  const geom = new THREE.BufferGeometry();
  geom.setAttribute('position', new THREE.BufferAttribute(nodes.slice(), 3));
  geom.setAttribute('color', new THREE.BufferAttribute(new Float32Array(3 * n).fill(REST_GREY), 3));
  geom.setIndex(Array.from(m.surface_faces.flat()));
  geom.computeVertexNormals();
  surface = new THREE.Mesh(geom, new THREE.MeshPhongMaterial({
    vertexColors: true, side: THREE.DoubleSide, shininess: 25, flatShading: false }));
  scene.add(surface);
  const edges = new THREE.LineSegments(new THREE.WireframeGeometry(geom),
    new THREE.LineBasicMaterial({ color: 0x000000, transparent: true, opacity: 0.12 }));
  surface.add(edges);
  surface.userData.edges = edges;

  cloud = new THREE.Points(new THREE.BufferGeometry(),
    new THREE.PointsMaterial({ color: 0xff5fd2, size: 0.012 * size, sizeAttenuation: true }));
  scene.add(cloud);
  shafts = new THREE.LineSegments(new THREE.BufferGeometry(),
    new THREE.LineBasicMaterial({ color: 0xffa500 }));
  scene.add(shafts);
  heads = new THREE.InstancedMesh(new THREE.ConeGeometry(0.012 * size, 0.035 * size, 8),
    new THREE.MeshBasicMaterial({ color: 0xffa500 }), Math.max(n, 1));
  heads.count = 0;
  scene.add(heads);
  for (const o of [cloud, shafts, heads]) o.frustumCulled = false;  // their geometry changes every frame

  controls.target.copy(centre);
  camera.position.copy(centre).add(new THREE.Vector3(0.6, -1.1, 0.8).multiplyScalar(size));
  camera.up.set(0, 0, 1);
  camera.near = size * 1e-3; camera.far = size * 100;
  camera.updateProjectionMatrix();
  sun.position.copy(camera.position);
  controls.update();
  dirty = true;
}

let uMax = 0;  // the colour scale grows with the largest displacement seen
let fSeen = 0;
const up = new THREE.Vector3(0, 1, 0), dir = new THREE.Vector3(), mat = new THREE.Matrix4();
const quat = new THREE.Quaternion(), scl = new THREE.Vector3(), pos = new THREE.Vector3();

let aimed = false;
function aim(points) {
  // once: look at the side the cloud was seen from (where the tool is), unless the user moved
  aimed = true;
  const c = new THREE.Vector3();
  for (const p of points) c.add(pos.set(p[0], p[1], p[2]));
  c.multiplyScalar(1 / Math.max(points.length, 1));
  const d = c.sub(controls.target);
  if (d.length() < 1e-12) return;
  d.normalize().add(new THREE.Vector3(0, 0, 0.35)).normalize();
  camera.position.copy(controls.target).addScaledVector(d, 1.5 * mesh.size);
  sun.position.copy(camera.position);
  controls.update();
}

function showFrame(points, result) {
  if (!aimed && points.length) aim(points);
  const n = mesh.n;
  const x = surface.geometry.attributes.position.array;
  const colour = surface.geometry.attributes.color.array;
  const mag = new Float32Array(n);
  x.set(mesh.nodes);
  // a session whose outputs leave displacements out: the surface stays at rest, and the page says so
  const moved = Boolean(result.displacement || result.surface_displacement);
  state.displacementShown = moved;
  $('notice').hidden = moved;
  if (result.displacement) {
    const u = result.displacement;
    for (let i = 0; i < n; i++) {
      const [a, b, c] = u[i];
      x[3 * i] += a; x[3 * i + 1] += b; x[3 * i + 2] += c;
      mag[i] = Math.hypot(a, b, c);
    }
  } else if (result.surface_displacement) {
    const u = result.surface_displacement, s = mesh.surfaceNodes;
    for (let j = 0; j < s.length; j++) {
      const i = s[j], [a, b, c] = u[j];
      x[3 * i] += a; x[3 * i + 1] += b; x[3 * i + 2] += c;
      mag[i] = Math.hypot(a, b, c);
    }
  }
  const byError = $('colour').value === 'error' && typeof result.error_estimate === 'number';
  let hi;
  if (byError) {  // one estimate per frame: the whole surface in its colour, scaled to max_error or 5 mm
    hi = (state.maxError || 0.005);
    for (let i = 0; i < n; i++) colormap(result.error_estimate / hi, colour, i);
  } else if (!moved) {  // no displacement, no scale: the rest colour, and no range claimed
    colour.fill(REST_GREY);
    hi = null;
  } else {
    for (let i = 0; i < n; i++) uMax = Math.max(uMax, mag[i]);
    hi = uMax;  // 0 until something moves: the scale reads 0 mm, the surface its lowest colour
    for (let i = 0; i < n; i++) colormap(hi > 0 ? mag[i] / hi : 0, colour, i);
  }
  $('legend-hi').textContent = hi === null ? '-' : `${(1e3 * hi).toFixed(2)} mm`;
  surface.geometry.attributes.position.needsUpdate = true;
  surface.geometry.attributes.color.needsUpdate = true;
  surface.geometry.computeVertexNormals();
  surface.geometry.computeBoundingSphere();
  surface.remove(surface.userData.edges);
  surface.userData.edges.geometry.dispose();
  surface.userData.edges.geometry = new THREE.WireframeGeometry(surface.geometry);
  surface.add(surface.userData.edges);

  cloud.geometry.setAttribute('position', new THREE.BufferAttribute(flat(points), 3));
  cloud.visible = $('show-points').checked;

  // forces: an arrow per support node, length relative to the largest force
  const f = result.forces, s = result.support;
  let count = 0;
  if (f && s && f.length) {
    for (const v of f) fSeen = Math.max(fSeen, Math.hypot(...v));
    const fMax = fSeen;  // arrows scaled to the largest force seen, so a growing load shows
    const seg = new Float32Array(6 * f.length);
    const scale = fMax > 0 ? 0.18 * mesh.size / fMax : 0;
    for (let j = 0; j < f.length; j++) {
      const len = Math.hypot(...f[j]);
      if (len < 0.05 * fMax) continue;
      const i = s[j];
      const p0 = [x[3 * i], x[3 * i + 1], x[3 * i + 2]];
      const p1 = [p0[0] + f[j][0] * scale, p0[1] + f[j][1] * scale, p0[2] + f[j][2] * scale];
      seg.set([...p0, ...p1], 6 * count);
      dir.set(f[j][0], f[j][1], f[j][2]).normalize();
      quat.setFromUnitVectors(up, dir);
      pos.set(...p1);
      const k = Math.min(1, Math.max(0.3, 3 * len / fMax));  // small forces get small heads
      heads.setMatrixAt(count, mat.compose(pos, quat, scl.set(k, k, k)));
      count++;
    }
    shafts.geometry.setAttribute('position', new THREE.BufferAttribute(seg.subarray(0, 6 * count), 3));
  }
  heads.count = count;
  heads.instanceMatrix.needsUpdate = true;
  shafts.visible = heads.visible = $('show-forces').checked && count > 0;
  state.pointsShown = points.length;
  state.arrowsShown = count;
  dirty = true;
}

function showStatus(result, latencyMs) {
  state.lastFrameId = result.frame_id ?? null;
  state.errorEstimate = typeof result.error_estimate === 'number' ? result.error_estimate : null;
  state.latencyMs = latencyMs;
  $('frame').textContent = `${result.frame_id ?? '-'}  (${result.iterations} iterations)`;
  $('status').textContent = result.status + (result.method_used ? ` (${result.method_used})` : '');
  $('status').className = result.converged ? '' : 'warn';
  if (state.errorEstimate !== null) {
    $('estimate').textContent = `${(1e3 * state.errorEstimate).toFixed(3)} mm`;
    $('estimate').className = state.maxError && state.errorEstimate > state.maxError ? 'bad' : '';
  } else {
    $('estimate').textContent = 'not reported';
  }
  const t = result.timing_ms || {};
  const solve = t.total !== undefined ? `solve ${t.total.toFixed(1)} ms` : '';
  $('latency').textContent = `${latencyMs.toFixed(1)} ms on screen${solve ? ' · ' + solve : ''}`;
  const nf = result.net_force;
  if (nf) $('force').textContent = `${Math.hypot(...nf).toFixed(3)} N`;
}

// frames arrive on sockets; the newest one waiting is drawn at the next animation frame
let pending = null;
const shownAt = [];
function queue(points, result, t0, seq) { pending = { points, result, t0, seq }; }

// a watch socket is told each frame we have drawn, so it sends the newest next, not a backlog
let watchSocket = null;
function ack(seq) {
  if (watchSocket && watchSocket.readyState === WebSocket.OPEN && seq > (state.lastAck ?? -1)) {
    watchSocket.send(JSON.stringify({ ack: seq }));
    state.lastAck = seq;
  }
}

function loop() {
  requestAnimationFrame(loop);
  try {
    if (pending && mesh) {
      const p = pending; pending = null;
      showFrame(p.points, p.result);
      renderer.render(scene, camera);
      dirty = false;
      const now = performance.timeOrigin + performance.now();
      state.framesRendered++;
      state.lastSeq = p.seq;
      showStatus(p.result, now - p.t0);
      if (state.mode === 'watch') ack(p.seq);
      state.renderLog.push({ frame_id: p.result.frame_id ?? null, seq: p.seq, t: now });
      if (state.renderLog.length > 5000) state.renderLog.splice(0, 1000);
      shownAt.push(now);
      while (shownAt.length && now - shownAt[0] > 2000) shownAt.shift();
      state.fps = shownAt.length > 1 ? 1e3 * (shownAt.length - 1) / (now - shownAt[0]) : null;
      $('fps').textContent = state.fps ? state.fps.toFixed(1) : '-';
    } else if (dirty) {
      renderer.render(scene, camera);
      dirty = false;
    }
  } catch (err) {
    fail(err);
  }
}

// -- modes --------------------------------------------------------------------------------------

function opened(ws, first) {
  return new Promise((resolve, reject) => {
    ws.onopen = () => ws.send(JSON.stringify(first));
    ws.onerror = () => reject(new Error(`WebSocket ${ws.url} failed`));
    ws.onclose = (e) => reject(new Error(`WebSocket closed (${e.code}) ${e.reason}`));
    ws.onmessage = (e) => {
      const msg = JSON.parse(e.data);
      if (msg.error) reject(new Error(`${msg.error.code}: ${msg.error.detail}`));
      else resolve(msg);
    };
  });
}

async function watch(sessionId) {
  state.mode = 'watch';
  $('mode').textContent = 'watching';
  $('session').textContent = sessionId;
  const ws = new WebSocket(wsUrl(`/sessions/${encodeURIComponent(sessionId)}/watch`));
  const hello = await opened(ws, token ? { token } : {});
  state.session = hello.watching;
  state.model = hello.model;
  state.maxError = hello.config && hello.config.max_error;
  // frames are taken from now on (drawn once the mesh is in): a frame lost here would go unacked
  ws.onmessage = (e) => {
    const msg = JSON.parse(e.data);
    if (msg.error) return fail(new Error(`${msg.error.code}: ${msg.error.detail}`));
    queue(msg.points, msg.result, 1e3 * msg.time - (msg.result.timing_ms?.server ?? 0), msg.seq);
    if (document.hidden) ack(msg.seq);  // a hidden page draws nothing: it has handled the frame
  };
  ws.onclose = (e) => {  // 1000: the session ended; anything else (the server gone, a policy close) is an error
    if (e.code === 1000) $('status').textContent = `ended: ${e.reason || 'closed'}`;
    else fail(new Error(`watch closed (${e.code})${e.reason ? ` ${e.reason}` : ''}: no more frames will come`));
  };
  watchSocket = ws;
  ack(0);
  setMesh(await api(`/models/${encodeURIComponent(hello.model)}/mesh`));
  $('status').textContent = 'waiting for frames';  // drawn frames replace it at the next animation frame
}

// a 503 refuses one frame under overload and the stream stays open (API.md): say so where the
// status goes, not as an error, and send again after its retry_after
function overloaded(error, send) {
  const wait = error.retry_after ?? 1;
  busy(error.detail, wait, 'sending again');
  setTimeout(send, 1e3 * wait);
}
// a refusal under overload, counted and shown where the status goes (an error shown stays)
function busy(detail, wait, doing) {
  state.overloads++;
  state.lastOverload = detail;
  if (state.lastError === null) {
    $('status').textContent = `server busy (503): ${doing} in ${wait} s`;
    $('status').className = 'warn';
  }
}

async function demo(model) {
  state.mode = 'demo';
  $('mode').textContent = 'demo';
  const rate = Number(params.get('rate') || 10);
  const frames = Number(params.get('frames') || 40), points = Number(params.get('points') || 500);
  $('status').textContent = 'computing the demo sequence';
  const [m, seq] = await Promise.all([
    api(`/models/${encodeURIComponent(model)}/mesh`),
    api(`/models/${encodeURIComponent(model)}/demo?frames=${frames}&points=${points}`),
  ]);
  state.model = model;
  setMesh(m);
  const ws = new WebSocket(wsUrl('/stream'));
  const config = { model, support: seq.support, outputs: ['displacement', 'forces'] };
  if (token) config.token = token;
  const hello = await opened(ws, config);
  state.session = hello.session;
  state.maxError = hello.config && hello.config.max_error;
  $('session').textContent = hello.session;
  // ping-pong through the sequence: the tool pulls, then lets go, and again
  const order = [...seq.clouds.keys(), ...[...seq.clouds.keys()].reverse().slice(1, -1)];
  let k = 0, sentAt = 0;
  const send = () => {
    if (ws.readyState !== WebSocket.OPEN) return;  // a retry timed after the stream closed
    const t = k % order.length;
    sentAt = performance.timeOrigin + performance.now();
    ws.send(JSON.stringify({ points: seq.clouds[order[t]], frame_id: k }));
    k++;
  };
  ws.onmessage = (e) => {
    const msg = JSON.parse(e.data);
    if (msg.error && msg.error.code === 503) return overloaded(msg.error, send);
    if (msg.error) return fail(new Error(`frame: ${msg.error.code}: ${msg.error.detail}`));
    queue(seq.clouds[order[(msg.frame_id) % order.length]], msg, sentAt, k);
    const wait = Math.max(0, 1e3 / rate - (performance.timeOrigin + performance.now() - sentAt));
    setTimeout(send, wait);  // paced at `rate`, never more than one frame in flight
  };
  ws.onclose = (e) => { if (e.code !== 1000) fail(new Error(`stream closed (${e.code}) ${e.reason}`)); };
  send();
}

requestAnimationFrame(loop);
const start = params.get('session') ? watch(params.get('session'))
  : (params.get('demo') && params.get('model')) ? demo(params.get('model'))
  : Promise.reject(new Error('open /viewer?session=ID to watch a session, or /viewer?model=ID&demo=1'));
if (params.get('colour')) $('colour').value = params.get('colour');
start.catch(fail);
