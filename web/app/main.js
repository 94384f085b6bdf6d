// mrptv's observer page: subscribes to a live session over /v1/watch (protocol/README.md) and
// draws its velocity vectors as instanced arrows, in a flat 3D view or in WebXR.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/OrbitControls.js';
import { decodeBatch, fieldCells, KIND_CAUSAL, KIND_REFINED, RECORD_FLOATS } from './protocol.js';
import { speedColor, niceCeiling, rampCss } from './colormap.js';
import { Placement } from './placement.js';

const params = new URLSearchParams(location.search);
const TRAIL_FRAMES = 12;
// Field cells with fewer samples are drawn faded: their mean is still noisy.
const FIELD_FULL_SAMPLES = 20;
const BACKGROUND = new THREE.Color(0x101214);
const $ = (id) => document.getElementById(id);

// ---------------------------------------------------------------- scene
const renderer = new THREE.WebGLRenderer({ antialias: true, alpha: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
renderer.xr.enabled = true;
renderer.xr.setReferenceSpaceType('local-floor');
$('scene').appendChild(renderer.domElement);

const scene = new THREE.Scene();
scene.background = BACKGROUND;

const FLOOR_ANCHOR = [0, 1.3, -1.2];
const HEAD_ANCHOR = [0, -0.3, -1.2];
const placement = new Placement({
  anchor: FLOOR_ANCHOR,
  trueScale: params.get('scale') === 'true',
  fitSize: Number(params.get('size')) || 0.6,
});
$('true-scale').checked = placement.trueScale;

const camera = new THREE.PerspectiveCamera(50, 1, 0.01, 200);
camera.position.set(placement.anchor[0] + 0.35, placement.anchor[1] + 0.3, placement.anchor[2] + 1.1);
const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(...placement.anchor);
controls.update();

// The session's world, mapped into the observer's space by `volume`'s transform.
const volume = new THREE.Group();
scene.add(volume);

// One unit arrow along +y (shaft and head as one lathe), scaled per instance.
const arrowGeometry = new THREE.LatheGeometry(
  [[0, 0], [0.06, 0], [0.06, 0.68], [0.17, 0.68], [0, 1]].map(([r, y]) => new THREE.Vector2(r, y)),
  10,
);
// Unlit, so an arrow's colour is exactly the legend's colour for its speed.
const arrowMaterial = new THREE.MeshBasicMaterial({ color: 0xffffff });
let arrows = makeArrows(1024);
// The mean-flow field's arrows, one per cell.
let fieldArrows = makeArrows(256);

function makeArrows(capacity) {
  const mesh = new THREE.InstancedMesh(arrowGeometry, arrowMaterial, capacity);
  mesh.instanceMatrix.setUsage(THREE.DynamicDrawUsage);
  mesh.setColorAt(0, new THREE.Color());
  mesh.instanceColor.setUsage(THREE.DynamicDrawUsage);
  mesh.count = 0;
  // Instances move every frame: bounds would be stale; the volume is small anyway.
  mesh.frustumCulled = false;
  volume.add(mesh);
  return mesh;
}

function growableBuffer(object, capacity, itemSize) {
  const attribute = new THREE.BufferAttribute(new Float32Array(capacity * itemSize), itemSize);
  attribute.setUsage(THREE.DynamicDrawUsage);
  object.geometry.setAttribute('position', attribute);
  object.geometry.setDrawRange(0, 0);
  return attribute;
}

const points = new THREE.Points(
  new THREE.BufferGeometry(),
  new THREE.PointsMaterial({ color: 0xffffff, size: 4, sizeAttenuation: false }),
);
points.frustumCulled = false;
volume.add(points);
growableBuffer(points, 1024, 3);

const trails = new THREE.LineSegments(
  new THREE.BufferGeometry(),
  new THREE.LineBasicMaterial({ color: 0x8ab4f8, transparent: true, opacity: 0.45 }),
);
trails.frustumCulled = false;
volume.add(trails);
growableBuffer(trails, 8192, 3);

const box = new THREE.LineSegments(
  new THREE.EdgesGeometry(new THREE.BoxGeometry(1, 1, 1)),
  new THREE.LineBasicMaterial({ color: 0x5f6368 }),
);
box.visible = false;
volume.add(box);

function resize() {
  const w = window.innerWidth;
  const h = window.innerHeight;
  renderer.setSize(w, h);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}
window.addEventListener('resize', resize);
resize();

// ---------------------------------------------------------------- state
const state = {
  socket: null,
  connection: 'connecting',
  reconnectDelayMs: 1000,
  sessions: [],
  wanted: params.get('session'),
  subscribed: null,
  kind: params.get('kind') === 'refined' ? KIND_REFINED : KIND_CAUSAL,
  paused: false,
  latest: new Map(), // session number -> { batch, receivedAt, drawn }
  trails: new Map(), // track key -> { xyz: Float32Array, n, lastSeen }
  dirty: false,
  dropped: new Map(), // session id -> frames_dropped
  rttMs: null,
  pingSentAt: new Map(),
  nextPing: 1,
  speedMax: null,
  arrowSeconds: null,
  causalTimes: [], // [receivedAt, vectors]
  latencies: [], // [drawnAt, ms]
  frameIndex: null,
  batchesDrawn: 0,
  drawChecksum: 0,
  badBatches: 0,
  xrFrames: 0,
  xrMode: null,
  xrReferenceSpace: null,
  pixelProbe: null,
  contextLosses: 0,
  // The subscribed session's newest `field` message, per session number.
  fields: new Map(),
  showField: params.get('field') === 'true',
  fieldMessages: 0,
};
$('field').checked = state.showField;
$('kind').value = state.kind === KIND_REFINED ? 'refined' : 'causal';

function showMessage(text) {
  const m = $('message');
  m.textContent = text;
  m.hidden = !text;
}

// ---------------------------------------------------------------- protocol
// A server started with a watch secret wants it as ?token=; browsers cannot set headers on a
// WebSocket, so the page passes on its own ?token=.
const token = params.get('token');
const tokenQuery = token ? `?token=${encodeURIComponent(token)}` : '';

function watchUrl() {
  const scheme = location.protocol === 'https:' ? 'wss:' : 'ws:';
  return `${scheme}//${location.host}/v1/watch${tokenQuery}`;
}

/** After a connection that never opened: says so if the server wants a (different) secret. */
async function explainRefusal() {
  try {
    const response = await fetch(`/v1/sessions${tokenQuery}`);
    if (response.status === 401) {
      const body = await response.json().catch(() => ({}));
      showMessage(
        token
          ? `the server refused this page's token: ${body.message ?? 'wrong secret'}`
          : 'this server needs the viewers\' secret: open this page as …/?token=WATCH_SECRET',
      );
    }
  } catch {
    // The server is not there: the reconnect loop says so.
  }
}

function connect() {
  const socket = new WebSocket(watchUrl());
  socket.binaryType = 'arraybuffer';
  state.socket = socket;
  socket.onopen = () => {
    state.connection = 'open';
    state.reconnectDelayMs = 1000;
    showMessage('');
    ping();
  };
  socket.onmessage = (event) => {
    if (typeof event.data === 'string') onText(event.data);
    else onBatch(event.data);
  };
  socket.onclose = () => {
    if (state.connection !== 'open') explainRefusal();
    state.socket = null;
    state.subscribed = null;
    state.pingSentAt.clear();
    state.connection = `reconnecting in ${(state.reconnectDelayMs / 1000).toFixed(0)} s`;
    setTimeout(connect, state.reconnectDelayMs);
    state.reconnectDelayMs = Math.min(state.reconnectDelayMs * 2, 10000);
  };
}

function send(message) {
  if (state.socket?.readyState === WebSocket.OPEN) state.socket.send(JSON.stringify(message));
}

function ping() {
  if (state.socket?.readyState !== WebSocket.OPEN) return;
  const id = state.nextPing++;
  state.pingSentAt.set(id, performance.now());
  send({ type: 'ping', id });
  // A pong that never came (a reconnect in between) is not waited for forever.
  for (const old of state.pingSentAt.keys()) if (old < id - 10) state.pingSentAt.delete(old);
}
setInterval(ping, 1000);

function sessionNumber(id) {
  const n = Number(String(id).replace(/^s/, ''));
  return Number.isInteger(n) ? n : null;
}

function onText(text) {
  let msg;
  try {
    msg = JSON.parse(text);
  } catch {
    return showMessage(`unreadable message from the server: ${text.slice(0, 80)}`);
  }
  switch (msg.type) {
    case 'sessions':
      state.sessions = Array.isArray(msg.sessions) ? msg.sessions : [];
      updatePicker();
      chooseSession();
      break;
    case 'subscribed':
      state.subscribed = msg.session;
      break;
    case 'unsubscribed':
      state.subscribed = null;
      break;
    case 'status':
      state.dropped.set(msg.session, msg.counters?.frames_dropped ?? 0);
      break;
    case 'field': {
      const n = sessionNumber(msg.session);
      if (n === null || state.paused) break;
      state.fields.set(n, { session: msg.session, cells: fieldCells(msg), samples: msg.samples ?? 0, cellM: msg.cell_m });
      state.fieldMessages++;
      state.dirty = true;
      break;
    }
    case 'field_reset':
      for (const id of msg.sessions ?? []) state.fields.delete(sessionNumber(id));
      state.dirty = true;
      break;
    case 'session_ended': {
      const n = sessionNumber(msg.session);
      state.latest.delete(n);
      state.fields.delete(n);
      for (const key of state.trails.keys()) if (key.startsWith(`${n}:`)) state.trails.delete(key);
      state.dirty = true;
      break;
    }
    case 'pong': {
      const sent = state.pingSentAt.get(msg.id);
      if (sent !== undefined) {
        state.pingSentAt.delete(msg.id);
        const rtt = performance.now() - sent;
        state.rttMs = state.rttMs === null ? rtt : 0.8 * state.rttMs + 0.2 * rtt;
      }
      break;
    }
    case 'error':
      showMessage(`server: ${msg.message ?? msg.code}`);
      if (msg.code === 'unknown_session') {
        state.wanted = null;
        chooseSession();
      }
      break;
    case 'bye':
      showMessage(`server: ${msg.reason ?? 'bye'}`);
      break;
    default:
      // Protocol rule: unknown message types are ignored.
      break;
  }
}

function updatePicker() {
  const picker = $('session');
  const options = [['*', 'all sessions']];
  for (const s of state.sessions) {
    options.push([s.id, `${s.id} — ${s.client ?? ''} (${s.counters?.frames_processed ?? 0} frames)`]);
  }
  if (state.sessions.length === 0) options.push(['', 'no live session']);
  picker.replaceChildren(...options.map(([value, label]) => new Option(label, value)));
  picker.value = state.wanted ?? '';
}

function chooseSession() {
  const live = new Set(state.sessions.map((s) => s.id));
  let wanted = state.wanted;
  if (wanted !== '*' && !live.has(wanted)) wanted = state.sessions[0]?.id ?? null;
  if (wanted && wanted !== state.subscribed) subscribe(wanted);
  $('session').value = wanted ?? '';
}

function subscribe(session) {
  state.wanted = session;
  if (state.subscribed !== session) {
    state.latest.clear();
    state.trails.clear();
    state.dropped.clear();
    state.fields.clear();
    placement.reset();
    state.speedMax = null;
    state.dirty = true;
  }
  send({ type: 'subscribe', session, convention: 'webxr', uncertainty: true });
}

function onBatch(buffer) {
  let batch;
  try {
    batch = decodeBatch(buffer);
  } catch (e) {
    state.badBatches++;
    return showMessage(`bad vector batch: ${e.message}`);
  }
  const now = performance.now();
  if (batch.kind === KIND_CAUSAL) state.causalTimes.push([now, batch.count]);
  if (batch.kind !== state.kind || state.paused) return;
  placement.observe(batch.floats, batch.count);
  state.latest.set(batch.session, { batch, receivedAt: now, drawn: false });
  updateTrails(batch);
  state.dirty = true;
}

function updateTrails(batch) {
  const { floats, count, session, frameIndex } = batch;
  for (let i = 0; i < count; i++) {
    const key = `${session}:${batch.trackId(i)}`;
    let t = state.trails.get(key);
    if (!t) {
      t = { xyz: new Float32Array(TRAIL_FRAMES * 3), n: 0, lastSeen: 0 };
      state.trails.set(key, t);
    }
    t.xyz.copyWithin(3, 0, (TRAIL_FRAMES - 1) * 3);
    t.xyz.set(floats.subarray(i * RECORD_FLOATS + 2, i * RECORD_FLOATS + 5), 0);
    t.n = Math.min(t.n + 1, TRAIL_FRAMES);
    t.lastSeen = frameIndex;
  }
  for (const [key, t] of state.trails) {
    if (key.startsWith(`${session}:`) && frameIndex - t.lastSeen > TRAIL_FRAMES) state.trails.delete(key);
  }
}

// ---------------------------------------------------------------- drawing
const tmp = {
  m: new THREE.Matrix4(),
  q: new THREE.Quaternion(),
  p: new THREE.Vector3(),
  s: new THREE.Vector3(),
  d: new THREE.Vector3(),
  up: new THREE.Vector3(0, 1, 0),
  c: new THREE.Color(),
  rgb: [0, 0, 0],
};

function fixScales() {
  if (placement.medianSpeed > 0 && (state.speedMax === null || !placement.fixed)) {
    state.speedMax = niceCeiling(2 * placement.medianSpeed);
    // Arrows of the median speed span about a tenth of the volume.
    state.arrowSeconds = niceCeiling((0.1 * placement.extent) / placement.medianSpeed);
    updateLegend();
  }
}

function placeVolume() {
  const s = placement.scale;
  volume.scale.setScalar(s);
  volume.position.set(...placement.anchor.map((a, k) => a - s * placement.centre[k]));
  box.visible = placement.batchesSeen > 0;
  box.position.set(...placement.lo.map((lo, k) => (lo + placement.hi[k]) / 2));
  box.scale.set(...placement.lo.map((lo, k) => Math.max(placement.hi[k] - lo, 1e-3)));
}

function redraw(now) {
  fixScales();
  placeVolume();
  const speedMax = state.speedMax ?? 1;
  const tau = state.arrowSeconds ?? 0.1;
  const minWidth = 0.5 * placement.medianSpeed * tau;
  let total = 0;
  for (const { batch } of state.latest.values()) total += batch.count;
  if (total > arrows.instanceMatrix.count) {
    volume.remove(arrows);
    arrows.dispose();
    arrows = makeArrows(2 ** Math.ceil(Math.log2(total)));
  }
  let pointAttr = points.geometry.getAttribute('position');
  if (total > pointAttr.count) pointAttr = growableBuffer(points, arrows.instanceMatrix.count, 3);
  let n = 0;
  let checksum = 0;
  for (const entry of state.latest.values()) {
    const { batch } = entry;
    const f = batch.floats;
    const sigmas = batch.sigmas;
    for (let i = 0; i < batch.count; i++) {
      const o = i * RECORD_FLOATS;
      tmp.p.set(f[o + 2], f[o + 3], f[o + 4]);
      tmp.d.set(f[o + 5], f[o + 6], f[o + 7]);
      const speed = tmp.d.length();
      const length = Math.max(speed * tau, 1e-6);
      if (speed > 0) tmp.q.setFromUnitVectors(tmp.up, tmp.d.divideScalar(speed));
      else tmp.q.identity();
      const width = Math.max(length, minWidth);
      tmp.s.set(width, length, width);
      tmp.m.compose(tmp.p, tmp.q, tmp.s);
      arrows.setMatrixAt(n, tmp.m);
      speedColor(speed, speedMax, tmp.rgb);
      tmp.c.setRGB(tmp.rgb[0], tmp.rgb[1], tmp.rgb[2], THREE.SRGBColorSpace);
      if (sigmas) {
        // An uncertain vector is drawn lighter: faded toward the background by its error
        // relative to its speed (fully faded at 50 %, never below a third of its colour).
        const error = Math.hypot(sigmas[3 * i], sigmas[3 * i + 1], sigmas[3 * i + 2]);
        const relative = error / Math.max(speed, 1e-9);
        tmp.c.lerp(BACKGROUND, Math.min(relative / 0.5, 1) * 0.67);
      }
      arrows.setColorAt(n, tmp.c);
      pointAttr.setXYZ(n, f[o + 2], f[o + 3], f[o + 4]);
      checksum += f[o + 2] + f[o + 6];
      n++;
    }
    if (!entry.drawn) {
      entry.drawn = true;
      state.batchesDrawn++;
      state.frameIndex = batch.frameIndex;
      if (state.rttMs !== null) {
        state.latencies.push([now, batch.ageUs / 1000 + state.rttMs / 2 + (now - entry.receivedAt)]);
      }
    }
  }
  arrows.count = n;
  arrows.instanceMatrix.needsUpdate = true;
  if (arrows.instanceColor) arrows.instanceColor.needsUpdate = true;
  pointAttr.needsUpdate = true;
  points.geometry.setDrawRange(0, n);
  state.drawChecksum = checksum;
  drawTrails();
  drawField(speedMax);
}

/** The median of the cells' mean speeds (0 without cells). */
function medianCellSpeed(fields) {
  const speeds = [];
  for (const field of fields) for (const c of field.cells) speeds.push(Math.hypot(c.u, c.v, c.w));
  speeds.sort((a, b) => a - b);
  return speeds.length ? speeds[Math.floor(speeds.length / 2)] : 0;
}

function drawField(speedMax) {
  let total = 0;
  if (state.showField) for (const field of state.fields.values()) total += field.cells.length;
  if (total > fieldArrows.instanceMatrix.count) {
    volume.remove(fieldArrows);
    fieldArrows.dispose();
    fieldArrows = makeArrows(2 ** Math.ceil(Math.log2(total)));
  }
  let n = 0;
  if (state.showField) {
    const fields = [...state.fields.values()];
    // Arrows sized to their cells, not to the live vectors' time scale: a cell of the median
    // speed gets an arrow 0.8 of its side, so neighbouring cells' arrows do not overlap.
    const median = medianCellSpeed(fields);
    for (const field of fields) {
      const tau = median > 0 ? (0.8 * field.cellM) / median : 0;
      const width = 0.6 * field.cellM;
      for (const cell of field.cells) {
        tmp.p.set(cell.x, cell.y, cell.z);
        tmp.d.set(cell.u, cell.v, cell.w);
        const speed = tmp.d.length();
        const length = Math.max(speed * tau, 1e-6);
        if (speed > 0) tmp.q.setFromUnitVectors(tmp.up, tmp.d.divideScalar(speed));
        else tmp.q.identity();
        tmp.s.set(width, length, width);
        tmp.m.compose(tmp.p, tmp.q, tmp.s);
        fieldArrows.setMatrixAt(n, tmp.m);
        speedColor(speed, speedMax, tmp.rgb);
        tmp.c.setRGB(tmp.rgb[0], tmp.rgb[1], tmp.rgb[2], THREE.SRGBColorSpace);
        if (cell.n < FIELD_FULL_SAMPLES) tmp.c.lerp(BACKGROUND, 0.6);
        fieldArrows.setColorAt(n, tmp.c);
        n++;
      }
    }
  }
  fieldArrows.count = n;
  fieldArrows.instanceMatrix.needsUpdate = true;
  if (fieldArrows.instanceColor) fieldArrows.instanceColor.needsUpdate = true;
}

function drawTrails() {
  if (!$('trails').checked) {
    trails.geometry.setDrawRange(0, 0);
    return;
  }
  let segments = 0;
  for (const t of state.trails.values()) segments += Math.max(t.n - 1, 0);
  let attr = trails.geometry.getAttribute('position');
  if (segments * 2 > attr.count) attr = growableBuffer(trails, 2 ** Math.ceil(Math.log2(segments * 2)), 3);
  const a = attr.array;
  let v = 0;
  for (const t of state.trails.values()) {
    for (let k = 0; k + 1 < t.n; k++) {
      a.set(t.xyz.subarray(k * 3, k * 3 + 6), v * 3);
      v += 2;
    }
  }
  attr.needsUpdate = true;
  trails.geometry.setDrawRange(0, v);
}

function updateLegend() {
  const max = state.speedMax;
  $('legend-mid').textContent = max === null ? '–' : formatNumber(max / 2);
  $('legend-hi').textContent = max === null ? '–' : `≥ ${formatNumber(max)}`;
  $('legend-note').textContent =
    state.arrowSeconds === null
      ? 'waiting for vectors'
      : `arrow length = velocity × ${formatNumber(state.arrowSeconds)} s · ` +
        (placement.trueScale ? 'true scale' : `scale ${formatNumber(placement.scale)} : 1`);
}
$('legend-bar').style.background = rampCss();

function formatNumber(x) {
  if (x === 0) return '0';
  const digits = Math.max(0, 2 - Math.floor(Math.log10(Math.abs(x))));
  return x.toFixed(Math.min(digits, 6));
}

// ---------------------------------------------------------------- HUD
function windowed(list, now, spanMs) {
  while (list.length && now - list[0][0] > spanMs) list.shift();
  return list;
}

function hudFigures(now = performance.now()) {
  const causal = windowed(state.causalTimes, now, 1000);
  const latencies = windowed(state.latencies, now, 2000)
    .map(([, ms]) => ms)
    .sort((a, b) => a - b);
  let dropped = 0;
  for (const d of state.dropped.values()) dropped += d;
  return {
    framesPerSecond: causal.length,
    vectorsPerSecond: causal.reduce((sum, [, count]) => sum + count, 0),
    latencyMs: latencies.length ? latencies[Math.floor(latencies.length / 2)] : null,
    droppedFrames: dropped,
  };
}

function updateHud() {
  const h = hudFigures();
  $('hud-connection').textContent = state.subscribed
    ? `${state.connection}, ${state.subscribed === '*' ? 'all sessions' : state.subscribed}`
    : state.connection === 'open'
      ? state.sessions.length ? 'open' : 'open, waiting for a headset'
      : state.connection;
  $('hud-vectors').textContent = String(h.vectorsPerSecond);
  $('hud-fps').textContent = String(h.framesPerSecond);
  $('hud-latency').textContent =
    h.latencyMs === null ? '–' : `${h.latencyMs.toFixed(1)} ms (rtt ${state.rttMs.toFixed(1)})`;
  $('hud-dropped').textContent = String(h.droppedFrames);
  $('hud-frame').textContent = state.frameIndex === null ? '–' : `${state.frameIndex}${state.paused ? ' (paused)' : ''}`;
  const fields = [...state.fields.values()];
  $('hud-field').textContent = fields.length
    ? `${fields.reduce((sum, f) => sum + f.cells.length, 0)} cells of ${formatNumber(fields[0].cellM)} m, ` +
      `${fields.reduce((sum, f) => sum + f.samples, 0)} samples${state.showField ? '' : ' (hidden)'}`
    : '–';
  updateLegend();
}
setInterval(updateHud, 500);

// ---------------------------------------------------------------- controls
$('session').addEventListener('change', (e) => {
  if (e.target.value) subscribe(e.target.value);
});
$('kind').addEventListener('change', (e) => {
  state.kind = e.target.value === 'refined' ? KIND_REFINED : KIND_CAUSAL;
  state.latest.clear();
  state.trails.clear();
  state.dirty = true;
});
$('trails').addEventListener('change', () => (state.dirty = true));
$('field').addEventListener('change', (e) => {
  state.showField = e.target.checked;
  state.dirty = true;
});
$('reset-field').addEventListener('click', () => {
  if (state.subscribed) send({ type: 'reset_field', session: state.subscribed });
});
$('true-scale').addEventListener('change', (e) => {
  placement.trueScale = e.target.checked;
  state.dirty = true;
});
$('pause').addEventListener('click', () => {
  state.paused = !state.paused;
  $('pause').textContent = state.paused ? 'Resume' : 'Pause';
});
$('recentre').addEventListener('click', () => {
  placement.reset();
  state.speedMax = null;
  state.arrowSeconds = null;
  state.dirty = true;
});

// WebXR: a button per mode, shown only where the browser says the mode is supported.
async function offerXr() {
  // Browsers hide WebXR from pages that are not secure contexts (http from another device).
  $('xr-hint').hidden = window.isSecureContext;
  if (!navigator.xr) return;
  for (const [mode, id] of [['immersive-vr', 'enter-vr'], ['immersive-ar', 'enter-ar']]) {
    let supported = false;
    try {
      supported = await navigator.xr.isSessionSupported(mode);
    } catch {
      supported = false;
    }
    const button = $(id);
    button.hidden = !supported;
    button.onclick = () => toggleXr(mode);
  }
}

async function toggleXr(mode) {
  const current = renderer.xr.getSession();
  if (current) {
    await current.end();
    return;
  }
  let session;
  try {
    session = await navigator.xr.requestSession(mode, { optionalFeatures: ['local-floor'] });
  } catch (e) {
    return showMessage(`cannot start ${mode}: ${e.message}`);
  }
  // 'local-floor' puts the anchor at a height above the floor; a device without floor tracking
  // gets 'local' (origin at the head at the start), and the anchor moves to 0.3 m below the eyes.
  const floor = await session.requestReferenceSpace('local-floor').then(() => true, () => false);
  renderer.xr.setReferenceSpaceType(floor ? 'local-floor' : 'local');
  placement.anchor = floor ? FLOOR_ANCHOR : HEAD_ANCHOR;
  state.xrReferenceSpace = floor ? 'local-floor' : 'local';
  state.dirty = true;
  state.xrMode = mode;
  // Passthrough shows the room in AR: no painted background.
  scene.background = mode === 'immersive-ar' ? null : BACKGROUND;
  session.addEventListener('end', () => {
    state.xrMode = null;
    placement.anchor = FLOOR_ANCHOR;
    state.dirty = true;
    scene.background = BACKGROUND;
    $('enter-vr').textContent = 'Enter VR';
    $('enter-ar').textContent = 'Enter AR';
  });
  await renderer.xr.setSession(session);
  $(mode === 'immersive-vr' ? 'enter-vr' : 'enter-ar').textContent = mode === 'immersive-vr' ? 'Exit VR' : 'Exit AR';
}

// ---------------------------------------------------------------- frame loop
function readPixels() {
  const gl = renderer.getContext();
  const w = gl.drawingBufferWidth;
  const h = gl.drawingBufferHeight;
  const pixels = new Uint8Array(w * h * 4);
  gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
  return { pixels, w, h, contextLost: gl.isContextLost() };
}

const PROBE_BACKGROUND = new THREE.Color(0x000000);

/**
 * Renders the frame once more with the arrows alone on black and counts the pixels they cover
 * (the darkest ramp colour, (68, 1, 84), is far above the threshold whatever the speeds), and
 * the strongly coloured pixels of the real frame; then renders the real frame again.
 */
function probeFrame() {
  const frame = readPixels();
  let coloured = 0;
  for (let i = 0; i < frame.pixels.length; i += 4) {
    const r = frame.pixels[i], g = frame.pixels[i + 1], b = frame.pixels[i + 2];
    if (Math.max(r, g, b) - Math.min(r, g, b) > 60) coloured++;
  }
  const shown = [points.visible, trails.visible, box.visible, scene.background];
  points.visible = trails.visible = box.visible = false;
  scene.background = PROBE_BACKGROUND;
  renderer.render(scene, camera);
  const alone = readPixels();
  [points.visible, trails.visible, box.visible, scene.background] = shown;
  renderer.render(scene, camera);
  let arrowPixels = 0;
  for (let i = 0; i < alone.pixels.length; i += 4) {
    if (Math.max(alone.pixels[i], alone.pixels[i + 1], alone.pixels[i + 2]) > 24) arrowPixels++;
  }
  return {
    arrowPixels,
    coloured,
    total: frame.w * frame.h,
    width: frame.w,
    height: frame.h,
    contextLost: frame.contextLost,
  };
}

// Browsers take the WebGL context away when the GPU (or its software stand-in) resets or is
// starved; three.js rebuilds what it needs once it is restored. Say so rather than go blank.
renderer.domElement.addEventListener('webglcontextlost', () => {
  state.contextLosses++;
  showMessage('graphics context lost: waiting for the browser to restore it');
});
renderer.domElement.addEventListener('webglcontextrestored', () => {
  showMessage('');
  state.dirty = true;
});

renderer.setAnimationLoop((time, frame) => {
  const now = performance.now();
  if (state.dirty) {
    state.dirty = false;
    redraw(now);
  }
  if (frame) state.xrFrames++;
  else controls.update();
  renderer.render(scene, camera);
  if (state.pixelProbe) {
    const resolve = state.pixelProbe;
    state.pixelProbe = null;
    resolve({ ...probeFrame(), presenting: renderer.xr.isPresenting });
  }
});

// A small read-only window for tests and for the curious (browser console: mrptv.stats()).
window.mrptv = {
  stats: () => ({
    connection: state.connection,
    subscribed: state.subscribed,
    sessions: state.sessions.map((s) => s.id),
    arrows: arrows.count,
    fieldArrows: fieldArrows.count,
    fieldCells: [...state.fields.values()].reduce((sum, f) => sum + f.cells.length, 0),
    fieldSamples: [...state.fields.values()].reduce((sum, f) => sum + f.samples, 0),
    sigmasSeen: [...state.latest.values()].some(({ batch }) => batch.sigmas !== null),
    fieldMessages: state.fieldMessages,
    trailVertices: trails.geometry.drawRange.count,
    batchesDrawn: state.batchesDrawn,
    frameIndex: state.frameIndex,
    drawChecksum: state.drawChecksum,
    badBatches: state.badBatches,
    rttMs: state.rttMs,
    speedMax: state.speedMax,
    arrowSeconds: state.arrowSeconds,
    placement: { anchor: placement.anchor, centre: placement.centre, scale: placement.scale, fixed: placement.fixed },
    xrPresenting: renderer.xr.isPresenting,
    xrMode: state.xrMode,
    xrReferenceSpace: state.xrMode ? state.xrReferenceSpace : null,
    xrFrames: state.xrFrames,
    contextLosses: state.contextLosses,
    ...hudFigures(),
  }),
  /** Resolves after the next rendered frame with how many of its pixels the arrows cover. */
  probePixels: () => new Promise((resolve) => (state.pixelProbe = resolve)),
};

offerXr();
connect();
updateLegend();
