// texavatars view: the page. It keeps the user's camera and pose, sends one JSON request
// per change (at most one per animation frame) over the WebSocket, and shows the frames the
// server sends back (protocol: src/view/protocol.rs). The server renders the latest request
// of each page; replies older than the one on screen are dropped here.
'use strict';

const $ = (id) => document.getElementById(id);
const RAD = Math.PI / 180;
// Pose sliders: [label, field, index, min, max] in radians.
const POSE = [
  ['jaw open', 'jaw', 0, -0.1, 0.6], ['jaw sideways', 'jaw', 1, -0.25, 0.25],
  ['neck pitch', 'neck', 0, -0.6, 0.6], ['neck yaw', 'neck', 1, -0.8, 0.8], ['neck roll', 'neck', 2, -0.5, 0.5],
  ['eyes pitch', 'eyes', 0, -0.5, 0.5], ['eyes yaw', 'eyes', 1, -0.6, 0.6],
];

// What the page exposes for tests and curious users (window.viewer).
const viewer = {
  info: null, ready: false, framesShown: 0, lastHeader: null, errors: [],
  fps: 0, latencyMs: null,
  // Every frame's input-to-frame latency (ms) and display time, for measurements
  // (benches/view_browser.py); the last 10,000.
  latencies: [], shownAt: [],
};
window.viewer = viewer;

let info = null;
let socket = null;
let nextId = 1;
let shownId = 0;
let sentId = 0;
let dirty = false;
let inputAt = null;            // time of the first input not yet sent
const inputTimes = new Map();  // request id -> input time
const shownTimes = [];         // display times of the last second's frames
let renderUrl = null;
let gtUrl = null;
let playing = false;
let lastAdvance = 0;

const state = {
  orbit: null, preset: null, frame: null, etaFrame: null,
  expr: [], jaw: [0, 0, 0], neck: [0, 0, 0], eyes: [0, 0, 0, 0, 0, 0], eta: true,
};

function status(text) { $('status').textContent = text || ''; }

function slider(parent, label, min, max, step, value, oninput, name) {
  const row = document.createElement('label');
  row.className = 'row';
  const span = document.createElement('span');
  span.textContent = label;
  span.title = label;
  const input = document.createElement('input');
  Object.assign(input, { type: 'range', min, max, step, value });
  if (name !== undefined) input.dataset.name = name;
  const out = document.createElement('output');
  out.textContent = Number(value).toFixed(2);
  input.addEventListener('input', () => {
    out.textContent = Number(input.value).toFixed(2);
    oninput(Number(input.value));
  });
  row.append(span, input, out);
  parent.append(row);
  return input;
}

function buildControls() {
  const e = info.expressions.length;
  state.expr = new Array(e).fill(0);
  const box = $('exprsliders');
  info.expressions.forEach((name, k) => {
    slider(box, name, -info.expression_range, info.expression_range, 0.01, 0, (v) => {
      state.expr[k] = v; posed();
    }, name);
  });
  const pose = $('posesliders');
  for (const [label, field, i, min, max] of POSE) {
    slider(pose, label, min, max, 0.01, 0, (v) => {
      if (field === 'eyes') { state.eyes[i] = v; state.eyes[i + 3] = v; } else { state[field][i] = v; }
      posed();
    }, label);
  }
  $('filter').addEventListener('input', () => {
    const q = $('filter').value.trim().toLowerCase();
    for (const row of box.children) {
      row.hidden = q !== '' && !row.textContent.toLowerCase().includes(q);
    }
  });
  $('eta').disabled = !info.reads_eta;
  $('eta').addEventListener('change', () => { state.eta = $('eta').checked; request(); });
  $('neutral').addEventListener('click', neutral);
  $('reset').addEventListener('click', () => {
    state.orbit = { ...info.default_orbit };
    state.preset = null;
    $('preset').value = '';
    request();
  });
  $('scale').addEventListener('change', request);
  const m = info.motion;
  if (m) {
    $('motionbox').hidden = false;
    $('scrub').max = String(m.frames - 1);
    $('scrub').addEventListener('input', () => showFrame(Number($('scrub').value)));
    $('play').addEventListener('click', () => {
      playing = !playing;
      $('play').textContent = playing ? 'Pause' : 'Play';
      if (playing && state.frame === null) showFrame(Number($('scrub').value));
    });
    $('showgt').addEventListener('change', request);
    $('gtlabel').hidden = !m.ground_truth;
    for (const c of m.cameras) {
      const o = document.createElement('option');
      o.value = String(c);
      o.textContent = `dataset camera ${c}`;
      $('preset').append(o);
    }
  }
  $('preset').disabled = !m || m.cameras.length === 0;
  $('preset').addEventListener('change', () => {
    state.preset = $('preset').value === '' ? null : Number($('preset').value);
    request();
  });
  $('savepng').addEventListener('click', () => send('png'));
  $('saveply').addEventListener('click', () => send('ply'));
  updateMode();
}

function updateMode() {
  const m = info.motion;
  $('mode').textContent = state.frame === null ? '(sliders)' : `(motion frame ${state.frame})`;
  if (m) $('frameno').textContent = `${Number($('scrub').value) + 1} / ${m.frames}`;
}

function neutral() {
  state.expr.fill(0);
  state.jaw = [0, 0, 0]; state.neck = [0, 0, 0]; state.eyes = [0, 0, 0, 0, 0, 0];
  for (const input of document.querySelectorAll('#exprsliders input, #posesliders input')) {
    input.value = '0';
    input.nextElementSibling.textContent = '0.00';
  }
  posed();
}

// A slider moved: show the sliders' pose (with the eta of the motion frame last shown).
function posed() {
  if (state.frame !== null) state.etaFrame = state.frame;
  state.frame = null;
  playing = false;
  $('play').textContent = 'Play';
  updateMode();
  request();
}

function showFrame(k) {
  state.frame = k;
  state.etaFrame = k;
  $('scrub').value = String(k);
  updateMode();
  request();
}

// The orbit's image size: the stage's box at the default aspect, times the size setting.
function orbitSize() {
  const stage = $('stage');
  const aspect = info.default_orbit.width / info.default_orbit.height;
  const panes = $('gtfig').hidden ? 1 : 2;
  let h = Math.max(stage.clientHeight - 24, 64);
  let w = h * aspect;
  const maxW = stage.clientWidth / panes - 8;
  if (w > maxW) { w = maxW; h = w / aspect; }
  const s = Number($('scale').value);
  const clamp = (v) => Math.round(Math.min(Math.max(v * s, info.min_side), info.max_side));
  return [clamp(w), clamp(h)];
}

function message(type) {
  const [width, height] = orbitSize();
  const camera = state.preset === null
    ? { orbit: { ...state.orbit, width, height } }
    : { preset: state.preset };
  return {
    type, id: nextId++, camera, frame: state.frame, expr: state.expr,
    jaw: state.jaw, neck: state.neck, eyes: state.eyes, eta: state.eta,
    eta_frame: state.etaFrame,
    ground_truth: $('showgt').checked && state.preset !== null && state.frame !== null,
  };
}

// Something changed: send the new state with the next animation frame.
function request() {
  if (inputAt === null) inputAt = performance.now();
  if (dirty) return;
  dirty = true;
  requestAnimationFrame(() => { dirty = false; send('frame'); });
}

function send(type) {
  if (!socket || socket.readyState !== WebSocket.OPEN || !info) return;
  const m = message(type);
  if (type === 'frame') {
    inputTimes.set(m.id, inputAt ?? performance.now());
    inputAt = null;
    sentId = m.id;
  }
  socket.send(JSON.stringify(m));
}

function download(bytes, mime, name) {
  const url = URL.createObjectURL(new Blob([bytes], { type: mime }));
  const a = document.createElement('a');
  a.href = url; a.download = name;
  document.body.append(a); a.click(); a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

function onFrame(h, payload) {
  const name = `texavatars_${h.frame === null ? 'sliders' : 'frame' + h.frame}_${h.id}`;
  if (h.type === 'png') { download(payload.subarray(0, h.bytes), h.mime, name + '.png'); return; }
  if (h.type === 'ply') { download(payload.subarray(0, h.bytes), h.mime, name + '.ply'); return; }
  if (h.id < shownId) return; // an older frame than the one on screen
  shownId = h.id;
  const img = new Blob([payload.subarray(0, h.bytes)], { type: h.mime });
  const url = URL.createObjectURL(img);
  const el = $('render');
  el.onload = () => {
    if (renderUrl) URL.revokeObjectURL(renderUrl);
    renderUrl = url;
    const now = performance.now();
    shownTimes.push(now);
    while (shownTimes.length && now - shownTimes[0] > 1000) shownTimes.shift();
    viewer.fps = shownTimes.length;
    const t0 = inputTimes.get(h.id);
    if (t0 !== undefined) {
      viewer.latencyMs = now - t0;
      viewer.latencies.push(viewer.latencyMs);
      viewer.shownAt.push(now);
      if (viewer.latencies.length > 10000) { viewer.latencies.shift(); viewer.shownAt.shift(); }
    }
    for (const k of inputTimes.keys()) if (k <= h.id) inputTimes.delete(k);
    viewer.framesShown += 1;
    viewer.lastHeader = h;
    stats(h);
  };
  el.src = url;
  const gt = h.gt_bytes > 0;
  $('gtfig').hidden = !gt;
  if (gt) {
    const gurl = URL.createObjectURL(new Blob([payload.subarray(h.bytes, h.bytes + h.gt_bytes)], { type: 'image/png' }));
    $('gt').onload = () => { if (gtUrl) URL.revokeObjectURL(gtUrl); gtUrl = gurl; };
    $('gt').src = gurl;
    $('gtcap').textContent = h.psnr === null ? 'ground truth (identical)' : `ground truth · PSNR ${h.psnr.toFixed(2)} dB`;
  }
}

function stats(h) {
  const t = h.timings_ms;
  const stages = t.stages.map(([k, v]) => `${k} ${v.toFixed(0)} ms`).join(' · ');
  const lat = viewer.latencyMs === null ? '' : ` · latency ${viewer.latencyMs.toFixed(0)} ms`;
  $('stats').textContent = `${viewer.fps} FPS${lat} · ${stages} · encode ${t.encode.toFixed(0)} ms · ` +
    `${h.width}×${h.height} · ${h.gaussians.toLocaleString()} Gaussians · dropped ${h.dropped}`;
}

function onMessage(ev) {
  if (typeof ev.data === 'string') {
    const e = JSON.parse(ev.data);
    viewer.errors.push(e);
    status(`server: ${e.error}`);
    return;
  }
  const bytes = new Uint8Array(ev.data);
  const len = new DataView(ev.data).getUint32(0, true);
  const h = JSON.parse(new TextDecoder().decode(bytes.subarray(4, 4 + len)));
  status('');
  onFrame(h, bytes.subarray(4 + len));
}

function connect() {
  const proto = location.protocol === 'https:' ? 'wss:' : 'ws:';
  socket = new WebSocket(`${proto}//${location.host}/ws`);
  socket.binaryType = 'arraybuffer';
  socket.onopen = () => { status(''); viewer.ready = true; request(); };
  socket.onmessage = onMessage;
  socket.onclose = () => {
    viewer.ready = false;
    status('disconnected from the server; retrying…');
    setTimeout(connect, 1000);
  };
}

// Playback: the next frame once the previous one is on screen and 40 ms (25 fps) passed.
function tick(now) {
  if (playing && info.motion && shownId >= sentId && now - lastAdvance >= 40) {
    lastAdvance = now;
    showFrame((Number($('scrub').value) + 1) % info.motion.frames);
  }
  requestAnimationFrame(tick);
}

// Orbit, pan and zoom with pointer events (mouse, pen and touch alike).
function orbitControls() {
  const stage = $('stage');
  const pointers = new Map();
  let pinch = null;
  const toOrbit = () => {
    if (state.preset !== null) { state.preset = null; $('preset').value = ''; }
  };
  const pan = (dx, dy) => {
    const o = state.orbit;
    // Model units per pixel on screen at the orbit's centre.
    const shown = $('render').clientHeight || orbitSize()[1];
    const perPixel = 2 * o.distance * Math.tan(o.fov * RAD / 2) / shown;
    o.pan = [o.pan[0] - dx * perPixel, o.pan[1] + dy * perPixel];
  };
  stage.addEventListener('contextmenu', (e) => e.preventDefault());
  stage.addEventListener('pointerdown', (e) => {
    stage.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey });
    pinch = null;
  });
  stage.addEventListener('pointermove', (e) => {
    const p = pointers.get(e.pointerId);
    if (!p) return;
    const dx = e.clientX - p.x; const dy = e.clientY - p.y;
    p.x = e.clientX; p.y = e.clientY;
    toOrbit();
    const o = state.orbit;
    if (pointers.size === 1) {
      if (p.pan) pan(dx, dy);
      else {
        o.yaw -= dx * 0.3;
        o.pitch = Math.min(Math.max(o.pitch + dy * 0.3, -85), 85);
      }
    } else if (pointers.size === 2) {
      const [a, b] = [...pointers.values()];
      const dist = Math.hypot(a.x - b.x, a.y - b.y);
      const mid = [(a.x + b.x) / 2, (a.y + b.y) / 2];
      if (pinch) {
        o.distance = Math.min(Math.max(o.distance * pinch.dist / Math.max(dist, 1), 0.1), 10);
        pan(mid[0] - pinch.mid[0], mid[1] - pinch.mid[1]);
      }
      pinch = { dist, mid };
    }
    request();
  });
  const up = (e) => { pointers.delete(e.pointerId); pinch = null; };
  stage.addEventListener('pointerup', up);
  stage.addEventListener('pointercancel', up);
  stage.addEventListener('wheel', (e) => {
    e.preventDefault();
    toOrbit();
    state.orbit.distance = Math.min(Math.max(state.orbit.distance * Math.exp(e.deltaY * 0.001), 0.1), 10);
    request();
  }, { passive: false });
  window.addEventListener('resize', request);
}

async function main() {
  const r = await fetch('/api/info');
  info = await r.json();
  viewer.info = info;
  state.orbit = { ...info.default_orbit };
  const m = info.motion ? `, motion ${info.motion.kind} (${info.motion.frames} frames)` : '';
  $('model').textContent = `${info.model}: ${info.source} · ${info.gaussians.toLocaleString()} Gaussians · ${info.backend}${m}`;
  buildControls();
  orbitControls();
  connect();
  requestAnimationFrame(tick);
}

main().catch((e) => status(`could not start: ${e}`));
