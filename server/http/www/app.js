// lifemap's browser view (issue 38): pages over lifemapd's /api endpoints (docs/API.md,
// "Browser view"). No framework: a hash router, fetch with the API key, three.js for 3D.
'use strict';

const KEY_STORAGE = 'lifemap-api-key';
const view = document.getElementById('view');
const crumbs = document.getElementById('crumbs');

function escapeHtml(text) {
  return String(text).replace(/[&<>"']/g, (c) => ({
    '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;'})[c]);
}
function enc(name) { return encodeURIComponent(name); }
function date(s) { return s > 0 ? new Date(s * 1000).toISOString().replace('T', ' ').slice(0, 16) : '—'; }

class ApiError extends Error {
  constructor(status, code, message) { super(message); this.status = status; this.code = code; }
}

function authHeaders() {
  const key = sessionStorage.getItem(KEY_STORAGE);
  return key ? {Authorization: 'Bearer ' + key} : {};
}

// fetch with the key; JSON errors become ApiError (401 opens the key form).
async function request(path, options = {}) {
  const response = await fetch(path, Object.assign({}, options,
    {headers: Object.assign({}, options.headers || {}, authHeaders())}));
  if (!response.ok) {
    let body = {code: String(response.status), message: response.statusText};
    try { body = await response.json(); } catch (e) { /* not JSON */ }
    if (response.status === 401) showKeyForm();
    throw new ApiError(response.status, body.code, body.message);
  }
  return response;
}
async function api(path, options) { return (await request(path, options)).json(); }
async function bytes(path) { return (await request(path)).arrayBuffer(); }
// An image fetched with the key, as an object URL for <img src>.
async function imageUrl(path) { return URL.createObjectURL(await (await request(path)).blob()); }

function showKeyForm() { document.getElementById('key-form').hidden = false; }
document.getElementById('key-button').onclick = showKeyForm;
document.getElementById('key-form').onsubmit = (e) => {
  e.preventDefault();
  sessionStorage.setItem(KEY_STORAGE, document.getElementById('key-input').value.trim());
  document.getElementById('key-form').hidden = true;
  route();
};

function showError(err) {
  view.innerHTML = `<p class="error" id="error">${escapeHtml(err.message)}` +
    (err.status === 401 ? ' — enter an API key above.' : '') + '</p>';
  document.body.dataset.ready = 'error';
}

function setCrumbs(parts) {
  crumbs.innerHTML = parts.map(([text, href]) =>
    href ? `<a href="${href}">${escapeHtml(text)}</a>` : escapeHtml(text)).join(' › ');
}

// ---- maps --------------------------------------------------------------------------------
async function mapsPage() {
  setCrumbs([['maps', '#/']]);
  const {maps} = await api('/api/maps');
  const rows = maps.map((m) => `<tr class="map-row"><td><a href="#/map/${enc(m.name)}">` +
    `${escapeHtml(m.name)}</a></td><td>${escapeHtml(m.description)}</td><td>${m.visit_count}</td>` +
    `<td class="keyframe-count">${m.keyframe_count}</td><td>${date(m.created_time_s)}</td>` +
    `<td><a href="#/3d/${enc(m.name)}">3D</a></td></tr>`).join('');
  view.innerHTML = `<h1>Maps</h1>` + (maps.length === 0 ? '<p>No maps yet: stream a recording ' +
    'with <code>lifemap stream</code>.</p>' : `<table id="maps"><tr><th>map</th><th>description` +
    `</th><th>visits</th><th>keyframes</th><th>created</th><th></th></tr>${rows}</table>`);
}

// ---- one map: timeline, visits, floor plans, keyframe strip ------------------------------
// When a visit was recorded: its frames' own capture times where it has stored keyframes
// (visits recorded months apart and streamed minutes apart), else when the server received it.
function recorded(v) {
  if (v.data_start_time_s > 0) return [v.data_start_time_s, v.data_end_time_s];
  return [v.start_time_s, v.end_time_s || v.start_time_s];
}

function timelineSvg(visits) {
  if (visits.length === 0) return '';
  const width = 900, row = 22, height = 30 + row * visits.length;
  const t0 = Math.min(...visits.map((v) => recorded(v)[0]));
  const t1 = Math.max(...visits.map((v) => Math.max(...recorded(v)))) || t0 + 1;
  const x = (t) => 150 + (width - 170) * (t - t0) / Math.max(1, t1 - t0);
  const bars = visits.map((v, i) => {
    const y = 20 + i * row;
    const [start, end] = recorded(v);
    const a = x(start), b = Math.max(a + 6, x(end));
    const colour = v.in_map_frame ? '#2a2' : '#d80';
    return `<g class="visit-bar" data-visit="${v.id}"><text x="4" y="${y + 13}" font-size="12">` +
      `visit ${v.id} ${escapeHtml(v.label || v.robot)}</text><rect x="${a}" y="${y}" ` +
      `width="${b - a}" height="16" fill="${colour}"><title>${escapeHtml(v.frame_why)}</title>` +
      `</rect></g>`;
  }).join('');
  return `<svg class="timeline" id="timeline" width="${width}" height="${height}">` +
    `<text x="150" y="12" font-size="11">${date(t0)}</text><text x="${width - 120}" y="12" ` +
    `font-size="11">${date(t1)}</text>${bars}</svg>`;
}

async function mapPage(name) {
  setCrumbs([['maps', '#/'], [name, null]]);
  const map = await api(`/api/maps/${enc(name)}`);
  const visitRows = map.visits.map((v) => `<tr class="visit-row" data-visit="${v.id}">` +
    `<td>${v.id}</td><td>${escapeHtml(v.robot)}</td><td>${escapeHtml(v.label)}</td>` +
    `<td>${date(recorded(v)[0])}</td><td>${date(v.start_time_s)}</td>` +
    `<td>${v.keyframe_count}</td><td>${v.frame_count}</td>` +
    `<td class="${v.in_map_frame ? 'in-map' : 'own-frame'}">` +
    `${v.in_map_frame ? 'map frame' : 'own frame'}: ${escapeHtml(v.frame_why)}` +
    `${v.anchor_dropped ? ' (anchor dropped: ' + escapeHtml(v.anchor_dropped) + ')' : ''}</td>` +
    `<td>${v.has_plan ? `<button class="plan-button" data-visit="${v.id}">plan</button>` : '—'}` +
    `</td><td><button class="strip-button" data-visit="${v.id}">keyframes</button></td></tr>`)
    .join('');
  const options = map.visits.map((v) => `<option value="${v.id}">${v.id}</option>`).join('');
  view.innerHTML = `<h1 id="map-name">${escapeHtml(map.name)}</h1>
    <p>${escapeHtml(map.description)} — <span id="visit-count">${map.visit_count}</span> visits,
    <span id="keyframe-count">${map.keyframe_count}</span> keyframes,
    ${map.annotation_count} annotations. <a href="#/3d/${enc(map.name)}">3D view</a></p>
    <h2>Visits</h2>${timelineSvg(map.visits)}
    <table id="visits"><tr><th>visit</th><th>robot</th><th>label</th><th>recorded</th><th>received</th>
    <th>keyframes</th><th>frames</th><th>frame</th><th>floor plan</th><th></th></tr>
    ${visitRows}</table>
    <p>Changes between visit <select id="from">${options}</select> and
    <select id="to">${options}</select> <button id="changes-button">compare</button></p>
    <div id="changes"></div>
    <div id="plan" class="plan" hidden></div>
    <h2>Keyframes <span id="strip-title"></span></h2><div id="strip" class="strip"></div>
    <button id="more" hidden>more</button>`;
  let visit = 0, offset = 0;
  const loadStrip = async (reset) => {
    if (reset) { offset = 0; document.getElementById('strip').innerHTML = ''; }
    const page = await api(`/api/maps/${enc(name)}/keyframes?visit=${visit}&offset=${offset}` +
      '&limit=48');
    const strip = document.getElementById('strip');
    for (const k of page.keyframes) {
      const a = document.createElement('a');
      a.href = `#/keyframe/${enc(name)}/${k.id}`;
      a.className = 'thumb';
      a.innerHTML = `<img alt="keyframe ${k.id}"><span>${k.id} · v${k.visit_id}</span>`;
      strip.appendChild(a);
      imageUrl(`/api/maps/${enc(name)}/keyframes/${k.id}/thumb`)
        .then((url) => { a.querySelector('img').src = url; }).catch(() => {});
    }
    offset = page.next_offset || offset;
    document.getElementById('more').hidden = !page.next_offset;
    document.getElementById('strip-title').textContent = visit ? `of visit ${visit}` : '(all visits)';
  };
  document.getElementById('more').onclick = () => loadStrip(false);
  view.querySelectorAll('.strip-button').forEach((b) => b.onclick = () => {
    visit = Number(b.dataset.visit); loadStrip(true);
  });
  view.querySelectorAll('.plan-button').forEach((b) => b.onclick = async () => {
    const response = await request(`/api/maps/${enc(name)}/visits/${b.dataset.visit}/plan.svg`);
    const plan = document.getElementById('plan');
    plan.innerHTML = await response.text();
    plan.hidden = false;
    plan.querySelectorAll('circle.keyframe').forEach((c) => c.onclick = () => {
      location.hash = `#/keyframe/${enc(name)}/${c.dataset.id}`;
    });
  });
  if (map.visits.length > 1) document.getElementById('to').selectedIndex = map.visits.length - 1;
  document.getElementById('changes-button').onclick = async () => {
    const out = document.getElementById('changes');
    out.textContent = 'comparing…';
    try {
      const c = await api(`/api/maps/${enc(name)}/changes?from=${document.getElementById('from').value}` +
        `&to=${document.getElementById('to').value}`);
      out.innerHTML = `<table id="changes-table"><tr><th>change</th><th>class</th><th>where (m)</th>` +
        `<th>voxels</th></tr>` + c.objects.map((o) => `<tr><td>${o.kind}</td>` +
        `<td>${escapeHtml(o.class)}</td><td>${o.center.map((v) => v.toFixed(2)).join(', ')}</td>` +
        `<td>${o.voxels}</td></tr>`).join('') + `</table><p>${escapeHtml(c.classes)}</p>`;
    } catch (err) { out.innerHTML = `<p class="error">${escapeHtml(err.message)}</p>`; }
  };
  await loadStrip(true);
}

// ---- one keyframe: images and overlays, matches ------------------------------------------
async function keyframePage(name, id) {
  setCrumbs([['maps', '#/'], [name, `#/map/${enc(name)}`], [`keyframe ${id}`, null]]);
  const k = await api(`/api/maps/${enc(name)}/keyframes/${id}`);
  const base = `/api/maps/${enc(name)}/keyframes/${id}`;
  const match = (m, kind) => m.keyframe_id ?
    `<li><a href="#/keyframe/${enc(m.map)}/${m.keyframe_id}">map ${escapeHtml(m.map)}, visit ` +
    `${m.visit_id}, keyframe ${m.keyframe_id}</a> (score ${m.score.toFixed(2)}, ${m.inliers} ` +
    `inliers)</li>` : `<li><a href="#/map/${enc(m.map)}">map ${escapeHtml(m.map)}</a>, visit ` +
    `${m.visit_id} (${kind} score ${m.score.toFixed(2)})</li>`;
  const pose = k.pose ? k.pose.t.map((v) => v.toFixed(3)).join(', ') : 'none';
  view.innerHTML = `<h1>Keyframe <span id="keyframe-id">${k.id}</span></h1>
    <p>visit ${k.visit_id}, sequence ${k.sequence}, ${date(k.timestamp_s)}; position ${pose}
    (${k.pose_source}); ${k.superjuts ?? 0} superjuts, ${k.keypoints_stored ?? 0} keypoints kept,
    ${k.keypoints_masked ?? 0} masked.</p>
    <p id="overlay-toggles">${['entropy', 'labels', 'fused'].map((o) =>
      `<label><input type="checkbox" class="overlay-toggle" value="${o}"> ${o === 'entropy' ?
      'entropy mask' : o === 'labels' ? 'labels (forest)' : 'fused labels (octree)'}</label>`)
      .join(' ')} <span id="overlay-status"></span></p>
    <div class="images"><div class="frame" id="frame"><img id="color" alt="colour"></div>
    <img id="depth" alt="depth"></div>
    <h2>Appearance matches</h2><ul id="appearance">${k.appearance_matches.map((m) =>
      match(m, 'appearance')).join('') || `<li>none${k.appearance_status ? ': ' +
      escapeHtml(k.appearance_status) : ''}</li>`}</ul>
    <h2>Architecture matches (its visit's floor plan)</h2><ul id="architecture">
    ${k.architecture_matches.map((m) => match(m, 'architecture')).join('') ||
      `<li>none${k.architecture_status ? ': ' + escapeHtml(k.architecture_status) : ''}</li>`}</ul>`;
  const [color, depth] = await Promise.all([imageUrl(`${base}/color`), imageUrl(`${base}/depth`)]);
  document.getElementById('color').src = color;
  document.getElementById('depth').src = depth;
  await new Promise((resolve) => {
    const img = document.getElementById('color');
    if (img.complete) resolve(); else img.onload = resolve;
  });
  view.querySelectorAll('.overlay-toggle').forEach((box) => box.onchange = async () => {
    const frame = document.getElementById('frame');
    const existing = frame.querySelector(`img.overlay[data-overlay="${box.value}"]`);
    if (!box.checked) { if (existing) existing.remove(); return; }
    const status = document.getElementById('overlay-status');
    status.textContent = `computing ${box.value}…`;
    try {
      const img = document.createElement('img');
      img.className = 'overlay';
      img.dataset.overlay = box.value;
      img.src = await imageUrl(`${base}/${box.value}`);
      frame.appendChild(img);
      status.textContent = '';
    } catch (err) {
      status.innerHTML = `<span class="error">${escapeHtml(err.message)}</span>`;
      box.checked = false;
    }
  });
}

// ---- 3D: trajectories, frusta, cloud, semantic octree; annotation -------------------------
let scene3d = null;  // the running view, stopped when leaving the page

async function scenePage(name) {
  setCrumbs([['maps', '#/'], [name, `#/map/${enc(name)}`], ['3D', null]]);
  view.innerHTML = `<div id="scene"><div id="canvas-holder"></div><div id="scene-panel">
    <p id="scene-status">loading…</p>
    <p><label><input type="checkbox" id="show-cloud" checked> cloud</label>
    <label><input type="checkbox" id="show-tracks" checked> trajectories</label>
    <label><input type="checkbox" id="show-octree" checked> octree</label></p>
    <div id="classes"></div>
    <h3>Annotate</h3>
    <p>Click voxels to select them (click again to drop), or select a whole class. <button
    id="grow">grow</button> adds the neighbours of the same class; <button id="clear">clear</button>.</p>
    <p><span id="selected-count">0</span> voxels selected.</p>
    <p><label>class <input id="annotation-class" size="14"></label>
    <button id="annotate">annotate</button></p><p id="annotate-status"></p>
    <p><span id="annotation-count">0</span> annotations.
    <button id="training">download training folder</button></p>
    </div></div>`;
  const W = Math.min(window.innerWidth - 320, 1000), H = Math.min(window.innerHeight - 120, 700);
  const renderer = new THREE.WebGLRenderer({antialias: false, preserveDrawingBuffer: true});
  renderer.setSize(W, H);
  renderer.setClearColor(0x202830);
  document.getElementById('canvas-holder').appendChild(renderer.domElement);
  renderer.domElement.id = 'scene-canvas';
  const scene = new THREE.Scene();
  const camera = new THREE.PerspectiveCamera(60, W / H, 0.05, 500);
  camera.up.set(0, 0, 1);
  const controls = new THREE.OrbitControls(camera, renderer.domElement);
  const state = {frames: 0, frameMs: [], selected: new Set(), voxels: null, running: true};
  scene3d = state;
  window.lifemapScene = state;  // read by the browser tests (frame times, counts)
  const groups = {cloud: new THREE.Group(), tracks: new THREE.Group(), octree: new THREE.Group()};
  Object.values(groups).forEach((g) => scene.add(g));
  for (const k of ['cloud', 'tracks', 'octree']) {
    document.getElementById(`show-${k}`).onchange = (e) => { groups[k].visible = e.target.checked; };
  }
  const bounds = new THREE.Box3();
  const status = [];
  const say = () => { document.getElementById('scene-status').textContent = status.join('; '); };

  const sceneJson = await api(`/api/maps/${enc(name)}/scene`);
  const palette = [0x33aa33, 0xdd8800, 0x3388ff, 0xdd3344, 0xaa44cc, 0x22bbbb];
  sceneJson.visits.forEach((v, i) => {
    const pts = [];
    for (let j = 0; j < v.positions.length; j += 3) {
      pts.push(new THREE.Vector3(v.positions[j], v.positions[j + 1], v.positions[j + 2]));
    }
    pts.forEach((p) => bounds.expandByPoint(p));
    const colour = palette[i % palette.length];
    groups.tracks.add(new THREE.Line(new THREE.BufferGeometry().setFromPoints(pts),
      new THREE.LineBasicMaterial({color: colour})));
    // A frustum every few keyframes: apex at the camera, a 0.15 m deep pyramid along +z.
    const every = Math.max(1, Math.floor(pts.length / 60));
    const seg = [];
    const corners = [[-0.1, -0.075, 0.15], [0.1, -0.075, 0.15], [0.1, 0.075, 0.15], [-0.1, 0.075, 0.15]];
    for (let j = 0; j < pts.length; j += every) {
      const q = new THREE.Quaternion(...v.orientations.slice(4 * j, 4 * j + 4));
      const c = corners.map((x) => new THREE.Vector3(...x).applyQuaternion(q).add(pts[j]));
      for (let m = 0; m < 4; m++) seg.push(pts[j], c[m], c[m], c[(m + 1) % 4]);
    }
    groups.tracks.add(new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(seg),
      new THREE.LineBasicMaterial({color: colour, transparent: true, opacity: 0.6})));
  });
  status.push(`${sceneJson.visits.length} visits in the map's frame`);

  // Level of detail: #/3d/MAP?points=N&voxel=M (defaults 1,000,000 points, 2 cm voxels).
  const query = new URLSearchParams(location.hash.split('?')[1] || '');
  const maxPoints = Number(query.get('points')) || 1000000;
  const voxel = Number(query.get('voxel')) || 0.02;
  try {
    const buf = await bytes(`/api/maps/${enc(name)}/cloud.bin?max_points=${maxPoints}&voxel_m=${voxel}`);
    const n = new DataView(buf).getUint32(0, true);
    const pos = new Float32Array(n * 3), col = new Float32Array(n * 3);
    const dv = new DataView(buf, 4);
    for (let i = 0; i < n; i++) {
      const o = i * 15;
      pos[3 * i] = dv.getFloat32(o, true);
      pos[3 * i + 1] = dv.getFloat32(o + 4, true);
      pos[3 * i + 2] = dv.getFloat32(o + 8, true);
      col[3 * i] = dv.getUint8(o + 12) / 255;
      col[3 * i + 1] = dv.getUint8(o + 13) / 255;
      col[3 * i + 2] = dv.getUint8(o + 14) / 255;
    }
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(pos, 3));
    g.setAttribute('color', new THREE.BufferAttribute(col, 3));
    g.computeBoundingBox();
    bounds.union(g.boundingBox);
    groups.cloud.add(new THREE.Points(g, new THREE.PointsMaterial({size: 0.02, vertexColors: true})));
    state.points = n;
    status.push(`${n} cloud points`);
  } catch (err) { status.push(`no cloud: ${err.message}`); }

  let octreeInfo = null;
  try {
    octreeInfo = await api(`/api/maps/${enc(name)}/octree`);
    const buf = await bytes(`/api/maps/${enc(name)}/octree.bin`);
    const n = new DataView(buf).getUint32(0, true);
    const dv = new DataView(buf, 4);
    const vox = {x: new Float32Array(n), y: new Float32Array(n), z: new Float32Array(n),
      size: new Float32Array(n), cls: new Uint8Array(n)};
    for (let i = 0; i < n; i++) {
      const o = i * 17;
      vox.x[i] = dv.getFloat32(o, true); vox.y[i] = dv.getFloat32(o + 4, true);
      vox.z[i] = dv.getFloat32(o + 8, true); vox.size[i] = dv.getFloat32(o + 12, true);
      vox.cls[i] = dv.getUint8(o + 16);
    }
    state.voxels = vox;
    state.classPoints = {};
    for (const c of octreeInfo.classes) {
      const idx = [];
      for (let i = 0; i < n; i++) if (vox.cls[i] === c.id) idx.push(i);
      if (idx.length === 0) continue;
      const pos = new Float32Array(idx.length * 3);
      idx.forEach((v, j) => { pos[3 * j] = vox.x[v]; pos[3 * j + 1] = vox.y[v]; pos[3 * j + 2] = vox.z[v]; });
      const g = new THREE.BufferGeometry();
      g.setAttribute('position', new THREE.BufferAttribute(pos, 3));
      const pts = new THREE.Points(g, new THREE.PointsMaterial({
        size: octreeInfo.resolution_m, color: new THREE.Color(c.color)}));
      pts.userData = {indices: idx, classId: c.id};
      groups.octree.add(pts);
      state.classPoints[c.id] = pts;
    }
    document.getElementById('classes').innerHTML = '<table id="class-table"><tr><th></th>' +
      '<th>class</th><th>voxels</th><th></th></tr>' + octreeInfo.classes.map((c) =>
      `<tr class="class-row"><td><input type="checkbox" class="class-toggle" data-class="${c.id}"` +
      ` checked></td><td><span class="swatch" style="background:${c.color}"></span> ` +
      `<span class="class-name">${escapeHtml(c.name)}</span></td><td>${c.voxels}</td><td>` +
      `<button class="select-class" data-class="${c.id}">select</button></td></tr>`).join('') +
      '</table>';
    view.querySelectorAll('.class-toggle').forEach((b) => b.onchange = () => {
      const p = state.classPoints[b.dataset.class];
      if (p) p.visible = b.checked;
    });
    view.querySelectorAll('.select-class').forEach((b) => b.onclick = () => {
      for (let i = 0; i < n; i++) if (vox.cls[i] === Number(b.dataset.class)) state.selected.add(i);
      showSelection();
    });
    status.push(`${n} labelled voxels (model ${octreeInfo.model})`);
  } catch (err) { status.push(`no octree: ${err.message}`); }
  say();

  // Selection: the picked voxels drawn again, white and larger.
  const selection = new THREE.Points(new THREE.BufferGeometry(),
    new THREE.PointsMaterial({size: (octreeInfo ? octreeInfo.resolution_m : 0.05) * 1.4, color: 0xffffff}));
  scene.add(selection);
  function showSelection() {
    const v = state.voxels, ids = [...state.selected];
    const pos = new Float32Array(ids.length * 3);
    ids.forEach((i, j) => { pos[3 * j] = v.x[i]; pos[3 * j + 1] = v.y[i]; pos[3 * j + 2] = v.z[i]; });
    selection.geometry.dispose();
    selection.geometry = new THREE.BufferGeometry();
    selection.geometry.setAttribute('position', new THREE.BufferAttribute(pos, 3));
    document.getElementById('selected-count').textContent = ids.length;
  }
  const raycaster = new THREE.Raycaster();
  raycaster.params.Points.threshold = octreeInfo ? octreeInfo.resolution_m / 2 : 0.05;
  renderer.domElement.addEventListener('click', (e) => {
    if (!state.voxels) return;
    const r = renderer.domElement.getBoundingClientRect();
    raycaster.setFromCamera(new THREE.Vector2((e.clientX - r.left) / r.width * 2 - 1,
      -(e.clientY - r.top) / r.height * 2 + 1), camera);
    const hits = raycaster.intersectObjects(groups.octree.children.filter((p) => p.visible));
    if (hits.length === 0) return;
    const i = hits[0].object.userData.indices[hits[0].index];
    if (state.selected.has(i)) state.selected.delete(i); else state.selected.add(i);
    showSelection();
  });
  document.getElementById('clear').onclick = () => { state.selected.clear(); showSelection(); };
  document.getElementById('grow').onclick = () => {
    // Voxels of the same class touching the selection (26-neighbourhood), once per click.
    const v = state.voxels, res = octreeInfo.resolution_m, cell = new Map();
    const key = (x, y, z) => `${Math.round(x / res)},${Math.round(y / res)},${Math.round(z / res)}`;
    for (let i = 0; i < v.cls.length; i++) cell.set(key(v.x[i], v.y[i], v.z[i]), i);
    for (const i of [...state.selected]) {
      for (let dx = -1; dx <= 1; dx++) for (let dy = -1; dy <= 1; dy++) for (let dz = -1; dz <= 1; dz++) {
        const j = cell.get(key(v.x[i] + dx * res, v.y[i] + dy * res, v.z[i] + dz * res));
        if (j !== undefined && v.cls[j] === v.cls[i]) state.selected.add(j);
      }
    }
    showSelection();
  };
  const countAnnotations = async () => {
    const a = await api(`/api/maps/${enc(name)}/annotations`);
    document.getElementById('annotation-count').textContent = a.annotations.length;
  };
  document.getElementById('annotate').onclick = async () => {
    const out = document.getElementById('annotate-status');
    const cls = document.getElementById('annotation-class').value.trim();
    const v = state.voxels;
    const boxes = [...state.selected].map((i) => {
      const h = v.size[i] / 2;
      return [v.x[i] - h, v.y[i] - h, v.z[i] - h, v.x[i] + h, v.y[i] + h, v.z[i] + h];
    });
    try {
      const a = await api(`/api/maps/${enc(name)}/annotations`, {method: 'POST',
        headers: {'Content-Type': 'application/json'}, body: JSON.stringify({class: cls, boxes})});
      out.textContent = `annotation ${a.id}: ${a.boxes} voxels are '${a.class}'`;
      state.selected.clear(); showSelection(); await countAnnotations();
    } catch (err) { out.innerHTML = `<span class="error">${escapeHtml(err.message)}</span>`; }
  };
  document.getElementById('training').onclick = async () => {
    const out = document.getElementById('annotate-status');
    try {
      const response = await request(`/api/maps/${enc(name)}/training.tar`);
      const a = document.createElement('a');
      a.href = URL.createObjectURL(await response.blob());
      a.download = `${name}-training.tar`;
      a.click();
      out.textContent = `${response.headers.get('X-Lifemap-Views')} views, ` +
        `${response.headers.get('X-Lifemap-Labelled-Pixels')} labelled pixels`;
    } catch (err) { out.innerHTML = `<span class="error">${escapeHtml(err.message)}</span>`; }
  };
  await countAnnotations().catch(() => {});

  if (bounds.isEmpty()) bounds.set(new THREE.Vector3(-1, -1, -1), new THREE.Vector3(1, 1, 1));
  const centre = bounds.getCenter(new THREE.Vector3());
  const size = bounds.getSize(new THREE.Vector3()).length();
  camera.position.copy(centre).add(new THREE.Vector3(size * 0.6, -size * 0.6, size * 0.5));
  controls.target.copy(centre);
  controls.update();
  // Drawn when something changed (the camera, a toggle, the selection), not continuously:
  // an idle page costs nothing.
  let pending = false;
  const draw = () => {
    if (pending || !state.running) return;
    pending = true;
    requestAnimationFrame(() => {
      pending = false;
      const start = performance.now();
      renderer.render(scene, camera);
      state.frameMs.push(performance.now() - start);
      if (state.frameMs.length > 120) state.frameMs.shift();
      state.frames++;
    });
  };
  controls.addEventListener('change', draw);
  view.addEventListener('change', draw);
  view.addEventListener('click', draw);
  // Turns the camera round the map for `n` frames, each drawn and finished (gl.finish), and
  // returns their times in ms: how interactive the view is (the browser tests and
  // docs/BENCHMARKS.md use it).
  state.orbit = (n) => {
    const gl = renderer.getContext(), times = [];
    for (let i = 0; i < n; i++) {
      const start = performance.now();
      camera.position.sub(controls.target).applyAxisAngle(new THREE.Vector3(0, 0, 1), 0.05)
        .add(controls.target);
      camera.lookAt(controls.target);
      renderer.render(scene, camera);
      gl.finish();
      times.push(performance.now() - start);
    }
    state.frames += n;
    return times;
  };
  state.draw = draw;
  draw();
}

// ---- router --------------------------------------------------------------------------------
async function route() {
  if (scene3d) { scene3d.running = false; scene3d = null; }
  document.body.dataset.ready = '';
  const [path] = location.hash.replace(/^#/, '').split('?');
  const parts = path.split('/').filter(Boolean).map(decodeURIComponent);
  try {
    const session = await api('/api/session');
    document.getElementById('session').textContent =
      session.auth_required ? `key ${session.key} (${session.role})` : 'no authentication';
    if (parts[0] === 'map' && parts[1]) await mapPage(parts[1]);
    else if (parts[0] === 'keyframe' && parts[2]) await keyframePage(parts[1], parts[2]);
    else if (parts[0] === '3d' && parts[1]) await scenePage(parts[1]);
    else await mapsPage();
    document.body.dataset.ready = '1';
  } catch (err) { showError(err); }
}
window.addEventListener('hashchange', route);
route();
