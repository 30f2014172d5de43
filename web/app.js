// The cmr-agent web page: plain JavaScript, no framework, no build step, nothing fetched from
// outside this server. It uses the public API only:
//   GET /v1/maps, GET /v1/maps/{id}/points, POST /v1/maps/{id}/localize,
//   PUT/DELETE /v1/maps/{id} (with the admin token), and GET /ui/demo.json (the demo request).
// Every failure is shown as the API's own {error, error_type}.
'use strict';

const POINTS_MAX = 20000; // points fetched per region for drawing (the route allows 1..=100000)
const NEAR_M = 2.0; // depth colour scale, as src/render (NEAR_M, FAR_M, depth_color)
const FAR_M = 60.0;
const MIN_DEPTH_M = 0.1; // as src/geometry/camera.rs MIN_DEPTH_M
const MAX_CANVAS_WIDTH = 1600; // the overlay route's panel width limit, too

// KITTI odometry image_2 (sequence 00) and nuScenes CAM_FRONT.
const PRESETS = {
  kitti: { fx: 718.856, fy: 718.856, cx: 607.1928, cy: 185.2157, size: [1241, 376] },
  nuscenes: { fx: 1266.417203, fy: 1266.417203, cx: 816.267020, cy: 491.507066, size: [1600, 900] },
};

const $ = (id) => document.getElementById(id);

const state = {
  maps: [],
  mapId: null,
  points: null, // Float64Array x,y,z,... in the map frame, metres
  pointsFor: null,
  image: null, // { base64, el: HTMLImageElement, width, height, label }
  result: null, // the localize response
  poses: [], // [start of the chosen hypothesis, after step 1, ..., the polished answer] as 4x4 row-major arrays
  polished: false, // the last of `poses` is the polish's, not a step's
  iteration: 0,
  timer: null,
};

class ApiError extends Error {
  constructor(status, body) {
    super(`${body.error_type}: ${body.error}`);
    this.status = status;
    this.body = body;
  }
}

// fetch() that turns a non-2xx answer into an ApiError carrying the API's {error, error_type}.
async function api(path, options = {}) {
  let response;
  try {
    response = await fetch(path, options);
  } catch (e) {
    throw new ApiError(0, { error: `no answer from the server (${e.message})`, error_type: 'network' });
  }
  if (response.ok) return response;
  let body;
  const text = await response.text();
  try {
    body = JSON.parse(text);
  } catch (_) {
    body = null;
  }
  if (!body || typeof body.error !== 'string') {
    body = { error: text.slice(0, 300) || response.statusText, error_type: `http_${response.status}` };
  }
  throw new ApiError(response.status, body);
}

function showError(e) {
  const box = $('error');
  if (!e) {
    box.hidden = true;
    box.textContent = '';
    return;
  }
  box.hidden = false;
  box.textContent = e instanceof ApiError ? `${e.message}${e.status ? ` (HTTP ${e.status})` : ''}` : String(e.message || e);
  if (e instanceof ApiError) {
    box.dataset.errorType = e.body.error_type;
  } else {
    delete box.dataset.errorType;
  }
}

function setBusy(stateName) {
  document.body.dataset.state = stateName;
  $('run').disabled = stateName === 'running';
}

// ---------------------------------------------------------------- regions

async function loadMaps(select) {
  const r = await api('/v1/maps');
  state.maps = (await r.json()).maps;
  const list = $('regions');
  list.textContent = '';
  for (const m of state.maps) {
    const li = document.createElement('li');
    const b = document.createElement('button');
    b.type = 'button';
    b.dataset.id = m.id;
    b.textContent = `${m.id}`;
    const n = document.createElement('span');
    n.className = 'muted';
    n.textContent = ` ${m.num_points.toLocaleString('en')} points`;
    b.appendChild(n);
    b.addEventListener('click', () => selectMap(m.id).catch(showError));
    li.appendChild(b);
    list.appendChild(li);
  }
  if (!state.maps.length) {
    const li = document.createElement('li');
    li.className = 'muted';
    li.textContent = 'no regions stored';
    list.appendChild(li);
  }
  const keep = select || state.mapId;
  const wanted = state.maps.find((m) => m.id === keep) || state.maps.find((m) => m.id === 'demo') || state.maps[0];
  if (wanted) await selectMap(wanted.id);
  else {
    state.mapId = null;
    $('region-info').textContent = '';
  }
}

async function selectMap(id) {
  state.mapId = id;
  for (const b of $('regions').querySelectorAll('button')) b.classList.toggle('selected', b.dataset.id === id);
  const m = state.maps.find((x) => x.id === id);
  $('region-info').textContent = m && m.metadata && m.metadata.description ? m.metadata.description : '';
  if (state.pointsFor !== id) {
    state.points = null;
    const r = await api(`/v1/maps/${encodeURIComponent(id)}/points?max=${POINTS_MAX}`);
    state.points = decodePoints(await r.arrayBuffer(), r.headers.get('x-map-origin'));
    state.pointsFor = id;
  }
  if (state.result && state.result.map_id !== id) clearResult();
  draw();
}

// The points route's body: count × (x, y, z) little-endian float32, metres, relative to the
// region's origin (header x-map-origin "x,y,z"); returned in the map frame as float64, so
// regions at UTM-size coordinates keep centimetres.
function decodePoints(buffer, originHeader) {
  const view = new DataView(buffer);
  const n = Math.floor(buffer.byteLength / 12);
  const origin = (originHeader || '0,0,0').split(',').map(Number);
  const out = new Float64Array(n * 3);
  for (let i = 0; i < n * 3; i++) out[i] = view.getFloat32(i * 4, true) + origin[i % 3];
  return out;
}

// ---------------------------------------------------------------- image and intrinsics

function mimeOf(base64) {
  if (base64.startsWith('/9j/')) return 'image/jpeg';
  if (base64.startsWith('iVBORw0KGgo')) return 'image/png';
  return 'application/octet-stream';
}

function setImage(base64, label) {
  return new Promise((resolve, reject) => {
    const el = new Image();
    el.onload = () => {
      state.image = { base64, el, width: el.naturalWidth, height: el.naturalHeight, label };
      $('image-info').textContent = `${label}: ${el.naturalWidth}×${el.naturalHeight}`;
      clearResult();
      resolve();
    };
    el.onerror = () => reject(new Error(`${label}: the browser cannot read this image (JPEG or PNG expected)`));
    el.src = `data:${mimeOf(base64)};base64,${base64}`;
  });
}

function readFile(file) {
  return new Promise((resolve, reject) => {
    const reader = new FileReader();
    reader.onload = () => resolve(String(reader.result).split(',', 2)[1] || '');
    reader.onerror = () => reject(reader.error);
    reader.readAsDataURL(file);
  });
}

async function useFile(file) {
  if (!file) return;
  showError(null);
  const base64 = await readFile(file);
  await setImage(base64, file.name);
  // A preset whose image size matches is a good first guess.
  for (const [name, p] of Object.entries(PRESETS)) {
    if (Math.abs(p.size[0] - state.image.width) <= 2 && Math.abs(p.size[1] - state.image.height) <= 2) applyPreset(name);
  }
  draw();
}

async function useDemo() {
  showError(null);
  const demo = await (await api('/ui/demo.json')).json();
  await setImage(demo.image, 'demo image');
  setIntrinsics(demo.intrinsics);
  $('preset').value = 'custom';
  if (demo.max_iterations) $('max-iterations').value = demo.max_iterations;
  if (state.maps.some((m) => m.id === 'demo')) await selectMap('demo');
  draw();
}

function applyPreset(name) {
  const p = PRESETS[name];
  if (!p) return;
  $('preset').value = name;
  setIntrinsics(p);
}

function setIntrinsics(k) {
  for (const key of ['fx', 'fy', 'cx', 'cy']) $(key).value = k[key];
}

function intrinsics() {
  // Empty or non-numeric fields go to the server as null: its validation names them.
  const num = (id) => {
    const v = $(id).value.trim();
    return v === '' ? null : Number(v);
  };
  return { fx: num('fx'), fy: num('fy'), cx: num('cx'), cy: num('cy') };
}

// ---------------------------------------------------------------- localize

async function localize() {
  showError(null);
  if (!state.mapId) throw new Error('pick a region first');
  if (!state.image) throw new Error('drop an image or use the demo image first');
  const body = { image: state.image.base64, intrinsics: intrinsics() };
  const iters = $('max-iterations').value.trim();
  if (iters !== '') body.max_iterations = Number(iters);
  const hyps = $('hypotheses').value.trim();
  if (hyps !== '') body.hypotheses = Number(hyps);
  const prior = $('prior').value.trim();
  if (prior !== '') {
    try {
      body.prior_camera_from_map = JSON.parse(prior);
    } catch (e) {
      throw new Error(`prior: not JSON (${e.message})`);
    }
  }
  setBusy('running');
  stop();
  try {
    const r = await api(`/v1/maps/${encodeURIComponent(state.mapId)}/localize`, {
      method: 'POST',
      headers: { 'content-type': 'application/json' },
      body: JSON.stringify(body),
    });
    const result = await r.json();
    state.result = result;
    state.intrinsicsUsed = body.intrinsics;
    const chosen = result.hypotheses[result.chosen_hypothesis];
    state.poses = [chosen.start_camera_from_map, ...result.trajectory.map((s) => s.camera_from_map)];
    // The continuous polish (docs/server.md) moves the search's answer a little: its own last frame.
    state.polished = Boolean(result.polish) && (result.polish.rotation_deg > 0 || result.polish.translation_m > 0);
    if (state.polished) state.poses.push(result.pose.camera_from_map);
    const slider = $('iteration');
    slider.max = String(state.poses.length - 1);
    slider.disabled = false;
    $('play').disabled = state.poses.length < 2;
    showResult(result);
    setIteration(state.poses.length - 1);
    setBusy('done');
  } catch (e) {
    setBusy('error');
    throw e;
  }
}

function clearResult() {
  stop();
  state.result = null;
  state.poses = [];
  state.polished = false;
  state.iteration = 0;
  const slider = $('iteration');
  slider.max = '0';
  slider.value = '0';
  slider.disabled = true;
  $('play').disabled = true;
  $('iter-label').textContent = 'no result yet';
  $('results').textContent = 'Pick a region and an image, then Localize.';
  $('results').className = 'muted';
}

function setIteration(k) {
  state.iteration = Math.max(0, Math.min(k, state.poses.length - 1));
  $('iteration').value = String(state.iteration);
  const r = state.result;
  let label;
  if (state.polished && state.iteration === state.poses.length - 1) {
    const p = r.polish;
    label = `polished: turned ${p.rotation_deg.toFixed(2)}°, moved ${p.translation_m.toFixed(2)} m, alignment ${p.from_alignment.toFixed(3)} → ${p.alignment.toFixed(3)}`;
  } else if (state.iteration === 0) {
    const chosen = r.hypotheses[r.chosen_hypothesis];
    label = `start (prior ${chosen.start_yaw_offset_deg >= 0 ? '+' : ''}${chosen.start_yaw_offset_deg.toFixed(0)}°)`;
  } else {
    const s = r.trajectory[state.iteration - 1];
    const a = s.action;
    label = `step ${state.iteration} of ${r.trajectory.length}: yaw ${fmtSigned(a.yaw_deg, 1)}°, tx ${fmtSigned(a.tx_m, 1)} m, tz ${fmtSigned(a.tz_m, 1)} m, alignment ${s.alignment.toFixed(3)}`;
  }
  $('iter-label').textContent = label;
  draw();
}

function stop() {
  if (state.timer) clearInterval(state.timer);
  state.timer = null;
  $('play').textContent = '▶ Play';
}

function togglePlay() {
  if (state.timer) return stop();
  if (state.iteration >= state.poses.length - 1) setIteration(0);
  $('play').textContent = '❚❚ Pause';
  state.timer = setInterval(() => {
    if (state.iteration >= state.poses.length - 1) return stop();
    setIteration(state.iteration + 1);
  }, 600);
}

const fmt = (v, d) => Number(v).toFixed(d);
const fmtSigned = (v, d) => `${v >= 0 ? '+' : ''}${Number(v).toFixed(d)}`;

function cell(tag, text, cls) {
  const e = document.createElement(tag);
  e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

// The calibrated verdict in words (docs/server.md, "Is the answer right?"): whether to act on
// the pose, with the probability behind it.
function verdictText(c) {
  if (c.p_registered === null || c.p_registered === undefined) return 'not localized: the model set has no calibrator';
  const p = `p_registered ${fmt(c.p_registered, 3)}`;
  return c.localized ? `localized (${p})` : `NOT localized (${p}): do not act on this pose`;
}

function showResult(r) {
  const out = $('results');
  out.textContent = '';
  out.className = '';
  const summary = document.createElement('dl');
  const chosen = r.hypotheses[r.chosen_hypothesis];
  const rows = [
    ['verdict', verdictText(r.confidence), 'verdict'],
    ['confidence', `${fmt(r.confidence.score, 3)}  (frustum IoU ${fmt(r.confidence.frustum_iou, 3)}, policy ${fmt(r.confidence.policy_certainty, 3)}, alignment ${fmt(r.confidence.alignment, 3)})`, 'confidence'],
    ['converged', r.converged ? 'yes' : 'no (ran out of iterations)', 'converged'],
    ['iterations', String(r.iterations), 'iterations'],
    ['hypothesis', `${r.chosen_hypothesis + 1} of ${r.hypotheses.length} (start ${fmtSigned(chosen.start_yaw_offset_deg, 0)}°)`, 'hypothesis'],
    ['position', `${r.pose.position_m.map((v) => fmt(v, 2)).join(', ')} m (map frame)`, 'position'],
    ['heading', `${fmt(r.pose.heading_deg, 1)}° (ccw from map +x)`, 'heading'],
  ];
  for (const [k, v, id] of rows) {
    summary.appendChild(cell('dt', k));
    const dd = cell('dd', v);
    dd.id = `r-${id}`;
    if (id === 'verdict') dd.className = r.confidence.localized ? 'verdict-yes' : 'verdict-no';
    summary.appendChild(dd);
  }
  out.appendChild(summary);

  out.appendChild(cell('h3', 'camera_from_map (p_cam = R·p_map + t)'));
  const table = document.createElement('table');
  table.id = 'pose';
  table.className = 'matrix';
  table.dataset.cameraFromMap = JSON.stringify(r.pose.camera_from_map);
  for (const row of r.pose.camera_from_map) {
    const tr = document.createElement('tr');
    for (const v of row) tr.appendChild(cell('td', fmt(Math.abs(v) < 5e-7 ? 0 : v, 6)));
    table.appendChild(tr);
  }
  out.appendChild(table);

  out.appendChild(cell('h3', 'timings (ms)'));
  const t = document.createElement('table');
  t.id = 'timings';
  t.className = 'timings';
  for (const [k, v] of Object.entries(r.timings_ms)) {
    const tr = document.createElement('tr');
    tr.appendChild(cell('td', k.replace(/_/g, ' ')));
    tr.appendChild(cell('td', fmt(v, 1), 'num'));
    t.appendChild(tr);
  }
  out.appendChild(t);
}

// ---------------------------------------------------------------- drawing

// The colour of a point depth_m in front of the camera: the same ramp as src/render depth_color
// (red near, yellow, green, cyan, blue far; log depth between NEAR_M and FAR_M).
const STOPS = [[200, 20, 20], [250, 90, 20], [250, 210, 40], [120, 240, 60], [30, 220, 200], [40, 120, 250], [60, 40, 180]];
function depthColor(depth) {
  const t = Math.min(1, Math.max(0, Math.log(Math.max(depth, 1e-3) / NEAR_M) / Math.log(FAR_M / NEAR_M)));
  const x = t * (STOPS.length - 1);
  const i = Math.min(Math.floor(x), STOPS.length - 2);
  const f = x - i;
  const c = (j) => Math.round(STOPS[i][j] * (1 - f) + STOPS[i + 1][j] * f);
  return `rgb(${c(0)},${c(1)},${c(2)})`;
}

// Projects the map points with camera_from_map T (4x4 row-major) and pinhole intrinsics k.
// This mirrors src/geometry: p_cam = R·p_map + t (pose.rs, camera_from_map); the camera frame is
// OpenCV's (x right, y down, z forward); a point is projected only when z >= MIN_DEPTH_M, to
// (u, v) = (fx·x/z + cx, fy·y/z + cy) with pixel centres at integers (camera.rs
// Intrinsics::project), and kept when -0.5 <= u < W-0.5 and -0.5 <= v < H-0.5
// (Intrinsics::in_frustum). Returns [u, v, depth] far first, as src/render project_points.
function projectPoints(points, T, k, width, height) {
  const out = [];
  const [r0, r1, r2] = T;
  for (let i = 0; i < points.length; i += 3) {
    const x = points[i], y = points[i + 1], z = points[i + 2];
    const cz = r2[0] * x + r2[1] * y + r2[2] * z + r2[3];
    if (!(cz >= MIN_DEPTH_M)) continue;
    const cx = r0[0] * x + r0[1] * y + r0[2] * z + r0[3];
    const cy = r1[0] * x + r1[1] * y + r1[2] * z + r1[3];
    const u = (k.fx * cx) / cz + k.cx;
    const v = (k.fy * cy) / cz + k.cy;
    if (u >= -0.5 && v >= -0.5 && u < width - 0.5 && v < height - 0.5) out.push([u, v, cz]);
  }
  out.sort((a, b) => b[2] - a[2]);
  return out;
}

// Intrinsics of the image scaled by s, pixel centres at integers on both sides (as src/render
// scaled_intrinsics).
function scaled(k, s) {
  return { fx: k.fx * s, fy: k.fy * s, cx: (k.cx + 0.5) * s - 0.5, cy: (k.cy + 0.5) * s - 0.5 };
}

function draw() {
  drawImageView();
  drawTopView();
}

function drawImageView() {
  const canvas = $('image-canvas');
  const ctx = canvas.getContext('2d');
  const img = state.image;
  if (!img) {
    ctx.fillStyle = '#20242b';
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    canvas.dataset.drawnPoints = '0';
    return;
  }
  const s = Math.min(1, MAX_CANVAS_WIDTH / img.width);
  canvas.width = Math.round(img.width * s);
  canvas.height = Math.round(img.height * s);
  ctx.drawImage(img.el, 0, 0, canvas.width, canvas.height);
  const pose = state.poses[state.iteration];
  if (!pose || !state.points || !state.intrinsicsUsed) {
    canvas.dataset.drawnPoints = '0';
    return;
  }
  ctx.fillStyle = 'rgba(0,0,0,0.35)'; // darken so the points read
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const k = scaled(state.intrinsicsUsed, s);
  const projected = projectPoints(state.points, pose, k, canvas.width, canvas.height);
  const r = Math.max(1.2, canvas.width / 1000);
  for (const [u, v, z] of projected) {
    ctx.fillStyle = depthColor(z);
    ctx.fillRect(u - r, v - r, 2 * r, 2 * r);
  }
  canvas.dataset.drawnPoints = String(projected.length);
}

// The camera centre in the map frame (-Rᵀt) and its optical axis (row 3 of R) on the ground
// plane, as src/geometry/pose.rs camera_position_in_map and camera_heading_in_map_deg.
function cameraInMap(T) {
  const R = [T[0].slice(0, 3), T[1].slice(0, 3), T[2].slice(0, 3)];
  const t = [T[0][3], T[1][3], T[2][3]];
  const c = [0, 1, 2].map((j) => -(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]));
  return { x: c[0], y: c[1], heading: Math.atan2(R[2][1], R[2][0]) };
}

function drawTopView() {
  const canvas = $('top-canvas');
  const ctx = canvas.getContext('2d');
  const W = canvas.width, H = canvas.height;
  ctx.fillStyle = '#14171c';
  ctx.fillRect(0, 0, W, H);
  const pts = state.points;
  if (!pts || !pts.length) {
    canvas.dataset.drawnPoints = '0';
    return;
  }
  // Bounds: the 1st..99th percentile of the points, grown to hold every camera shown. Float64
  // throughout: map-frame coordinates can be UTM-size (y ~ 5e6 m), where float32 steps are 0.5 m.
  const n = pts.length / 3;
  const xs = new Float64Array(n), ys = new Float64Array(n);
  for (let i = 0; i < n; i++) {
    xs[i] = pts[3 * i];
    ys[i] = pts[3 * i + 1];
  }
  const sx = Float64Array.from(xs).sort(), sy = Float64Array.from(ys).sort();
  const q = (a, f) => a[Math.min(a.length - 1, Math.floor(f * a.length))];
  let x0 = q(sx, 0.01), x1 = q(sx, 0.99), y0 = q(sy, 0.01), y1 = q(sy, 0.99);
  const cams = state.result ? [state.result.prior_camera_from_map, ...state.poses].map(cameraInMap) : [];
  for (const c of cams) {
    x0 = Math.min(x0, c.x - 3); x1 = Math.max(x1, c.x + 3);
    y0 = Math.min(y0, c.y - 3); y1 = Math.max(y1, c.y + 3);
  }
  const span = Math.max(x1 - x0, y1 - y0, 1) * 1.05;
  const mx = (x0 + x1) / 2, my = (y0 + y1) / 2;
  const scale = Math.min(W, H) / span;
  const X = (x) => W / 2 + (x - mx) * scale;
  const Y = (y) => H / 2 - (y - my) * scale; // map +y up on screen

  // Points, brighter when higher (z up).
  let zs = [];
  for (let i = 0; i < n; i += 7) zs.push(pts[3 * i + 2]);
  zs.sort((a, b) => a - b);
  const z0 = q(zs, 0.05), z1 = Math.max(q(zs, 0.95), z0 + 0.1);
  let drawn = 0;
  for (let i = 0; i < n; i++) {
    const px = X(xs[i]), py = Y(ys[i]);
    if (px < 0 || py < 0 || px >= W || py >= H) continue;
    const t = Math.min(1, Math.max(0, (pts[3 * i + 2] - z0) / (z1 - z0)));
    const g = Math.round(70 + 150 * t);
    ctx.fillStyle = `rgb(${g},${g},${Math.min(255, g + 20)})`;
    ctx.fillRect(px, py, 1.2, 1.2);
    drawn++;
  }
  canvas.dataset.drawnPoints = String(drawn);

  // Scale bar.
  const bar = [1, 2, 5, 10, 20, 50, 100, 200, 500].find((m) => m * scale >= 60) || 1000;
  ctx.strokeStyle = '#ccc';
  ctx.fillStyle = '#ccc';
  ctx.lineWidth = 2;
  ctx.beginPath();
  ctx.moveTo(12, H - 14);
  ctx.lineTo(12 + bar * scale, H - 14);
  ctx.stroke();
  ctx.font = '12px sans-serif';
  ctx.fillText(`${bar} m`, 14, H - 20);

  if (!cams.length) return;
  const arrow = (c, color, len, width) => {
    const x = X(c.x), y = Y(c.y);
    const hx = Math.cos(c.heading), hy = -Math.sin(c.heading);
    ctx.strokeStyle = color;
    ctx.fillStyle = color;
    ctx.lineWidth = width;
    ctx.beginPath();
    ctx.arc(x, y, width + 2, 0, 2 * Math.PI);
    ctx.fill();
    ctx.beginPath();
    ctx.moveTo(x, y);
    ctx.lineTo(x + hx * len, y + hy * len);
    ctx.stroke();
  };
  const [prior, ...path] = cams;
  arrow(prior, '#9aa0a6', 22, 2);
  ctx.strokeStyle = '#4fa3ff';
  ctx.lineWidth = 1.5;
  ctx.beginPath();
  path.forEach((c, i) => (i ? ctx.lineTo(X(c.x), Y(c.y)) : ctx.moveTo(X(c.x), Y(c.y))));
  ctx.stroke();
  path.forEach((c) => arrow(c, '#4fa3ff', 12, 1));
  arrow(path[state.iteration], '#ff9f1c', 30, 3);
}

// ---------------------------------------------------------------- admin

function authHeaders() {
  const token = $('token').value.trim();
  return token ? { authorization: `Bearer ${token}` } : {};
}

async function upload() {
  showError(null);
  const id = $('upload-id').value.trim();
  const file = $('upload-file').files[0];
  if (!id) throw new Error('upload: give the new region an id');
  if (!file) throw new Error('upload: choose a point-cloud file');
  const params = new URLSearchParams();
  const description = $('upload-description').value.trim();
  if (description) params.set('description', description);
  $('admin-info').textContent = `uploading ${file.name} …`;
  try {
    const query = params.toString();
    const r = await api(`/v1/maps/${encodeURIComponent(id)}${query ? `?${query}` : ''}`, {
      method: 'PUT',
      headers: { 'content-type': 'application/octet-stream', ...authHeaders() },
      body: file,
    });
    const body = await r.json();
    $('admin-info').textContent = `${body.replaced ? 'replaced' : 'registered'} ${body.map.id}: ${body.map.num_points.toLocaleString('en')} points in ${fmt(body.timings_ms.total, 0)} ms`;
  } catch (e) {
    $('admin-info').textContent = '';
    throw e;
  }
  state.pointsFor = null;
  await loadMaps(id);
}

async function removeSelected() {
  showError(null);
  const id = state.mapId;
  if (!id) throw new Error('delete: no region selected');
  if (!window.confirm(`Delete region "${id}" and its embeddings?`)) return;
  await api(`/v1/maps/${encodeURIComponent(id)}`, { method: 'DELETE', headers: authHeaders() });
  $('admin-info').textContent = `deleted ${id}`;
  state.mapId = null;
  state.pointsFor = null;
  state.points = null;
  clearResult();
  await loadMaps();
}

// ---------------------------------------------------------------- wiring

function guard(f) {
  return (...args) => Promise.resolve().then(() => f(...args)).catch((e) => {
    if (document.body.dataset.state !== 'running') document.body.dataset.state = 'error';
    showError(e);
  });
}

async function start() {
  $('refresh').addEventListener('click', guard(() => loadMaps()));
  $('demo').addEventListener('click', guard(useDemo));
  $('file').addEventListener('change', guard((e) => useFile(e.target.files[0])));
  // An image dropped anywhere on the page is taken (the browser would otherwise open it).
  const drop = $('drop');
  document.addEventListener('dragover', (e) => {
    e.preventDefault();
    drop.classList.add('over');
  });
  document.addEventListener('dragleave', (e) => {
    if (!e.relatedTarget) drop.classList.remove('over');
  });
  document.addEventListener('drop', guard((e) => {
    e.preventDefault();
    drop.classList.remove('over');
    return useFile(e.dataTransfer && e.dataTransfer.files[0]);
  }));
  drop.addEventListener('keydown', (e) => {
    if (e.key === 'Enter' || e.key === ' ') {
      e.preventDefault();
      $('file').click();
    }
  });
  $('preset').addEventListener('change', (e) => applyPreset(e.target.value));
  for (const key of ['fx', 'fy', 'cx', 'cy']) $(key).addEventListener('input', () => ($('preset').value = 'custom'));
  $('run').addEventListener('click', guard(localize));
  $('iteration').addEventListener('input', (e) => {
    stop();
    setIteration(Number(e.target.value));
  });
  $('play').addEventListener('click', togglePlay);
  $('upload').addEventListener('click', guard(upload));
  $('delete').addEventListener('click', guard(removeSelected));
  applyPreset('kitti');
  draw();
  try {
    const info = await (await api('/v1/info')).json();
    const prov = info.manifest.provenance || {};
    $('server').textContent = `${info.name} ${info.version}${prov.created ? ` · model of ${prov.created.slice(0, 10)}` : ''}`;
    await loadMaps();
    setBusy('idle');
  } catch (e) {
    setBusy('error');
    showError(e);
  }
}

document.addEventListener('DOMContentLoaded', start);
