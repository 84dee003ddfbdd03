// Guidance page of cgail_planner gui_node: external 3D view, internal tip view, status, replay.
// Also the page of record_demos: with a "record" item there is no planned path, a recording
// panel shows the episode, and the keyboard is a gamepad (sent as "joy" messages).
// State arrives over the WebSocket /ws as JSON "state" messages (see cgail_gui/protocol.py):
// positions in metres (frame phantom), angles in rad. The scene is drawn in millimetres and
// every readout is in mm and degrees. Messages only merge into `S` and mark it dirty; drawing
// happens once per animation frame, so a 40 Hz tracker never queues frames.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const MM = 1000;
const DEG = 180 / Math.PI;
const $ = (id) => document.getElementById(id);
const S = {};                       // latest items by name
const dirty = new Set();            // items changed since the last frame
const now_s = () => (performance.timeOrigin + performance.now()) / 1000;

// Exposed for tests and the latency benchmark: what arrived and what was drawn.
const G = window.gui = {
  connected: false, messages: 0, fullStates: 0, frames: 0, source: 'live', epoch: -1,
  webgl: false, lastTipReceived: 0,
  drawn: { tipSeq: 0, tipMm: null, pathPoints: 0, meshVertices: 0, meshFaces: 0,
           target: false, waypoint: false, deformT: null, bendArrow: null, timer: '' },
  latencies: [],  // [tip seq, ms from the pose's header stamp to the frame that drew it]
  renderMs: [],     // [external, internal] WebGL render call durations, ms
  rxLatencies: [],  // [tip seq, ms from the pose's header stamp to its WebSocket message]
  keyboard: { sent: 0, held: [], discards: 0 },  // record_demos: what the keyboard sent
  send: (obj) => ws && ws.readyState === 1 && ws.send(typeof obj === 'string' ? obj : JSON.stringify(obj)),
};

// ------------------------------------------------------------------ WebSocket, reconnecting
let ws = null;
let backoff = 500;
function connect() {
  ws = new WebSocket(`ws://${location.host}/ws`);
  ws.onopen = () => { G.connected = true; backoff = 500; setConn(); };
  ws.onclose = () => {
    G.connected = false; setConn();
    setTimeout(connect, backoff); backoff = Math.min(backoff * 2, 4000);
  };
  ws.onerror = () => {};
  ws.onmessage = (ev) => {
    let msg;
    try { msg = JSON.parse(ev.data); } catch (e) { console.warn('bad message', e); return; }
    if (msg.type !== 'state') return;
    G.messages += 1;
    ws.send('{"type":"ack"}');   // one state in flight: the node merges what comes meanwhile
    if (msg.full) {
      G.fullStates += 1;
      for (const k of Object.keys(S)) delete S[k];
      resetScene();
      for (const k of ['mesh', 'path', 'target', 'tip', 'guide', 'waypoint', 'bend', 'deform',
                       'diagnostics', 'trial', 'replay', 'config']) dirty.add(k);
      trail.length = 0;
    }
    if (msg.source !== G.source || msg.epoch !== G.epoch) { G.source = msg.source; G.epoch = msg.epoch; dirty.add('source'); }
    for (const [k, v] of Object.entries(msg.items)) {
      S[k] = v; dirty.add(k);
      if (k === 'tip' && v) {
        G.lastTipReceived = now_s(); pushTrail(v.p);
        G.rxLatencies.push([v.seq, (G.lastTipReceived - v.stamp) * 1000]);
        if (G.rxLatencies.length > 5000) G.rxLatencies.splice(0, 1000);
      }
      if (k === 'trial' && v) v.receivedAt = now_s();
      if (k === 'record' && v && G.recordSerial !== v.serial) { G.recordSerial = v.serial; trail.length = 0; dirty.add('trail'); }
    }
  };
}
function setConn() {
  const el = $('conn');
  el.textContent = G.connected ? 'Connected' : 'Disconnected - retrying';
  el.className = 'badge ' + (G.connected ? 'ok' : 'bad');
}

// ------------------------------------------------------------------ scene (millimetres)
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x0b0e13);
scene.add(new THREE.HemisphereLight(0xffffff, 0x30343c, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.4); sun.position.set(200, 300, 400); scene.add(sun);
const EXT = 1, INT = 2;  // layers seen only by the external / internal camera

// Software WebGL (SwiftShader: headless or no GPU) draws without MSAA at pixel ratio 1.
function softwareGL() {
  try {
    const gl = document.createElement('canvas').getContext('webgl2');
    const info = gl && gl.getExtension('WEBGL_debug_renderer_info');
    return !!info && /swiftshader|llvmpipe|software/i.test(gl.getParameter(info.UNMASKED_RENDERER_WEBGL));
  } catch (e) { return false; }
}
const SOFT = softwareGL();
const PIXEL_RATIO = SOFT ? 1 : (window.devicePixelRatio || 1);
let extRenderer = null, intRenderer = null;
try {
  extRenderer = new THREE.WebGLRenderer({ antialias: !SOFT, preserveDrawingBuffer: true });
  intRenderer = new THREE.WebGLRenderer({ antialias: !SOFT, preserveDrawingBuffer: true });
  $('external-box').appendChild(extRenderer.domElement);
  $('internal-box').insertBefore(intRenderer.domElement, $('overlay'));
  G.webgl = true;
  const gl = extRenderer.getContext(), info = gl.getExtension('WEBGL_debug_renderer_info');
  G.glRenderer = info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
} catch (e) {
  console.error('WebGL unavailable', e); $('nogl').hidden = false;
}
const extCam = new THREE.PerspectiveCamera(40, 1, 1, 5000);
extCam.up.set(0, 0, 1);
extCam.layers.enable(EXT);
const intCam = new THREE.PerspectiveCamera(90, 1, 0.5, 400);
intCam.layers.enable(INT);
const controls = extRenderer ? new OrbitControls(extCam, extRenderer.domElement) : null;
if (controls) { controls.enableDamping = false; controls.addEventListener('change', () => dirty.add('camera')); }

const aortaMat = new THREE.MeshPhongMaterial({ color: 0xe06660, transparent: true, opacity: 0.28,
  side: THREE.DoubleSide, depthWrite: false, shininess: 20 });
const lumenMat = new THREE.MeshPhongMaterial({ color: 0xb8544c, side: THREE.BackSide, shininess: 8,
  emissive: 0x2a0d0b });
const edgeMat = new THREE.LineBasicMaterial({ color: 0xff8a80, transparent: true, opacity: 0.10 });
let aortaGeo = null, aortaMesh = null, lumenMesh = null, aortaEdges = null;
let homeView = null;

const pathMat = new THREE.MeshBasicMaterial({ color: 0x35d0ff });
let pathMesh = null, pathLine = null, pathLinePts = null;
const pathLineMat = new THREE.LineBasicMaterial({ color: 0x35d0ff });
const tipGroup = new THREE.Group();
const tipBall = new THREE.Mesh(new THREE.SphereGeometry(3.5, 24, 16), new THREE.MeshPhongMaterial({ color: 0xff9f1c, emissive: 0x552200 }));
const tipArrow = new THREE.ArrowHelper(new THREE.Vector3(0, 1, 0), new THREE.Vector3(), 25, 0xff9f1c, 7, 4.5);
const tipHalo = new THREE.Mesh(new THREE.SphereGeometry(7, 24, 16), new THREE.MeshBasicMaterial({ color: 0xff9f1c, transparent: true, opacity: 0.35, depthTest: false }));
tipHalo.renderOrder = 5;   // seen through the vessel wall
tipGroup.add(tipBall, tipArrow, tipHalo);
tipGroup.traverse((o) => o.layers.set(EXT));
tipGroup.visible = false;
scene.add(tipGroup);
const targetBall = new THREE.Mesh(new THREE.SphereGeometry(2.5, 24, 16), new THREE.MeshPhongMaterial({ color: 0x3ddc84, emissive: 0x0c4020 }));
const targetZone = new THREE.Mesh(new THREE.SphereGeometry(1, 32, 20), new THREE.MeshBasicMaterial({ color: 0x3ddc84, transparent: true, opacity: 0.15, depthWrite: false }));
targetBall.visible = targetZone.visible = false;
scene.add(targetBall, targetZone);
const wpBall = new THREE.Mesh(new THREE.SphereGeometry(2.2, 20, 14), new THREE.MeshBasicMaterial({ color: 0xffd43b }));
wpBall.visible = false;
wpBall.layers.set(EXT);   // the internal view marks the waypoint in its overlay
scene.add(wpBall);
const TRAIL_MAX = 4000;
const trail = [];
const trailGeo = new THREE.BufferGeometry();
trailGeo.setAttribute('position', new THREE.BufferAttribute(new Float32Array(TRAIL_MAX * 3), 3));
trailGeo.setDrawRange(0, 0);
const trailLine = new THREE.Line(trailGeo, new THREE.LineBasicMaterial({ color: 0xb56cff }));
trailLine.layers.set(EXT);
trailLine.frustumCulled = false;
scene.add(trailLine);

function pushTrail(p) {
  const last = trail[trail.length - 1];
  if (last && Math.hypot(p[0] - last[0], p[1] - last[1], p[2] - last[2]) < 0.0003) return;
  trail.push(p); if (trail.length > TRAIL_MAX) trail.shift();
  dirty.add('trail');
}

function resetScene() {
  if (pathMesh) { scene.remove(pathMesh, pathLine); pathMesh.geometry.dispose(); pathLine.geometry.dispose(); pathMesh = pathLine = null; }
  tipGroup.visible = targetBall.visible = targetZone.visible = wpBall.visible = false;
  G.drawn.pathPoints = 0; G.drawn.target = false; G.drawn.waypoint = false;
}

function b64(text, Type) {
  const bin = atob(text); const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return new Type(bytes.buffer);
}
const v3 = (p) => new THREE.Vector3(p[0] * MM, p[1] * MM, p[2] * MM);

function drawMesh(m) {
  if (aortaMesh) { scene.remove(aortaMesh, lumenMesh, aortaEdges); aortaGeo.dispose(); }
  aortaMesh = lumenMesh = aortaEdges = aortaGeo = null;
  G.drawn.meshVertices = G.drawn.meshFaces = 0;
  if (!m) return;
  const pos = b64(m.vertices, Float32Array).map((x) => x * MM);
  const idx = b64(m.faces, Uint32Array);
  aortaGeo = new THREE.BufferGeometry();
  aortaGeo.setAttribute('position', new THREE.BufferAttribute(pos, 3));
  aortaGeo.setIndex(new THREE.BufferAttribute(idx, 1));
  aortaGeo.computeVertexNormals();
  aortaGeo.computeBoundingSphere();
  aortaMesh = new THREE.Mesh(aortaGeo, aortaMat); aortaMesh.layers.set(EXT); aortaMesh.renderOrder = 2;
  lumenMesh = new THREE.Mesh(aortaGeo, lumenMat); lumenMesh.layers.set(INT);
  aortaEdges = new THREE.LineSegments(new THREE.WireframeGeometry(aortaGeo), edgeMat); aortaEdges.layers.set(EXT);
  scene.add(aortaMesh, lumenMesh, aortaEdges);
  G.drawn.meshVertices = m.vertex_count; G.drawn.meshFaces = m.face_count;
  aortaGeo.computeBoundingBox();
  homeView = aortaGeo.boundingBox.clone();
  resetView();
}
// Home view: anterior (looking along +y, head up = +z), the whole aorta fitted to the panel.
function resetView() {
  if (!homeView || !controls) return;
  const box = $('external-box'), aspect = box.clientWidth / Math.max(box.clientHeight, 1);
  const size = homeView.getSize(new THREE.Vector3()), centre = homeView.getCenter(new THREE.Vector3());
  const t = Math.tan((extCam.fov / 2) / DEG);
  const dist = 1.04 * Math.max(size.z / 2 / t, size.x / 2 / (t * aspect)) + size.y / 4;
  extCam.aspect = aspect; extCam.updateProjectionMatrix();
  extCam.position.set(centre.x, centre.y - dist, centre.z); controls.target.copy(centre);
  extCam.up.set(0, 0, 1); controls.update(); dirty.add('camera');
}
// Labels of the tip and the target in the external view (DOM, placed by projection).
function labels() {
  const box = $('external-box'), w = box.clientWidth, h = box.clientHeight;
  for (const [id, obj, text] of [['label-tip', tipGroup, 'tip'], ['label-target', targetBall, 'target']]) {
    let el = $(id);
    if (!el) { el = document.createElement('div'); el.id = id; el.className = 'label3d'; el.textContent = text; box.appendChild(el); }
    if (!obj.visible) { el.style.display = 'none'; continue; }
    const p = obj.position.clone().project(extCam);
    el.style.display = p.z < 1 ? 'block' : 'none';
    el.style.left = `${Math.round((p.x + 1) / 2 * w) + 12}px`; el.style.top = `${Math.round((1 - p.y) / 2 * h) - 8}px`;
  }
}
// Scale bar of the external view, at the depth of the orbit centre.
function scaleBar() {
  const el = $('scalebar'); if (!el || !controls) return;
  const h = $('external-box').clientHeight;
  const d = extCam.position.distanceTo(controls.target);
  const pxPerMm = (h / 2) / (Math.tan((extCam.fov / 2) / DEG) * d);
  const mm = [5, 10, 20, 50, 100].find((v) => v * pxPerMm >= 60) || 100;
  el.style.width = `${Math.round(mm * pxPerMm)}px`; el.textContent = `${mm} mm`;
}
function applyDeform(d) {
  if (!d || !aortaGeo) return;
  const v = b64(d.vertices, Float32Array);
  const attr = aortaGeo.getAttribute('position');
  if (v.length !== attr.array.length) return;
  for (let i = 0; i < v.length; i++) attr.array[i] = v[i] * MM;
  attr.needsUpdate = true; aortaGeo.computeVertexNormals();
  if (aortaEdges) aortaEdges.visible = false;   // a beating wall reads better without the static mesh lines
  G.drawn.deformT = d.t;
}
function drawPath(p) {
  if (pathMesh) { scene.remove(pathMesh, pathLine); pathMesh.geometry.dispose(); pathLine.geometry.dispose(); pathMesh = pathLine = null; }
  G.drawn.pathPoints = 0;
  if (!p || p.points.length < 2) return;
  const curve = new THREE.CatmullRomCurve3(p.points.map(v3), false, 'centripetal');
  pathMesh = new THREE.Mesh(new THREE.TubeGeometry(curve, Math.min(1200, p.points.length * 4), 0.9, 8, false), pathMat);
  pathMesh.layers.set(EXT);
  // the internal view gets a thin line: a tube right in front of the camera would hide the lumen
  pathLine = new THREE.Line(new THREE.BufferGeometry().setFromPoints(curve.getPoints(Math.min(2000, p.points.length * 8))), pathLineMat);
  pathLine.layers.set(INT);
  pathLinePts = pathLine.geometry.getAttribute('position');
  scene.add(pathMesh, pathLine);
  G.drawn.pathPoints = p.points.length;
  if (tipGroup.visible) trimInternalPath(tipGroup.position);
}
function drawTip(t) {
  if (!t) { tipGroup.visible = false; return; }
  const p = v3(t.p), h = new THREE.Vector3(...t.heading), up = new THREE.Vector3(...t.up);
  tipGroup.visible = true; tipGroup.position.copy(p); tipArrow.setDirection(h);
  intCam.position.copy(p); intCam.up.copy(up); intCam.lookAt(p.clone().add(h));
  trimInternalPath(p);
  G.drawn.tipSeq = t.seq; G.drawn.tipMm = [p.x, p.y, p.z];
}
// The internal view shows the path ahead only: from the point nearest the tip, 4 mm on.
function trimInternalPath(p) {
  if (!pathLine || !pathLinePts) return;
  const a = pathLinePts.array, n = pathLinePts.count;
  let best = 0, bestD = Infinity;
  for (let i = 0; i < n; i++) {
    const d = (a[3 * i] - p.x) ** 2 + (a[3 * i + 1] - p.y) ** 2 + (a[3 * i + 2] - p.z) ** 2;
    if (d < bestD) { bestD = d; best = i; }
  }
  let i = best;
  while (i < n - 1 && (a[3 * i] - p.x) ** 2 + (a[3 * i + 1] - p.y) ** 2 + (a[3 * i + 2] - p.z) ** 2 < 16) i++;
  pathLine.geometry.setDrawRange(i, n - i);
}
function drawTarget(t) {
  targetBall.visible = targetZone.visible = !!t; G.drawn.target = !!t;
  if (!t) return;
  targetBall.position.copy(v3(t.p)); targetZone.position.copy(targetBall.position);
  targetZone.scale.setScalar(((S.config && S.config.success_radius) || 0.01) * MM);
}
function drawWaypoint(w) {
  wpBall.visible = !!w; G.drawn.waypoint = !!w;
  if (w) wpBall.position.copy(v3(w.p));
}
function drawTrail() {
  const a = trailGeo.getAttribute('position');
  for (let i = 0; i < trail.length; i++) { a.array[3 * i] = trail[i][0] * MM; a.array[3 * i + 1] = trail[i][1] * MM; a.array[3 * i + 2] = trail[i][2] * MM; }
  a.needsUpdate = true; trailGeo.setDrawRange(0, trail.length);
}

// ------------------------------------------------------------------ internal-view overlay (2D)
const overlay = $('overlay');
const octx = overlay.getContext('2d');
function fmtMm(m) { return m == null ? '\u2013' : `${(m * MM).toFixed(1)} mm`; }
function wallClass(m, len) { return m < 0.003 ? 'bad' : m < 0.008 ? 'warn' : 'ok'; }

function drawOverlay() {
  const w = overlay.clientWidth, h = overlay.clientHeight, dpr = window.devicePixelRatio || 1;
  if (overlay.width !== Math.round(w * dpr) || overlay.height !== Math.round(h * dpr)) { overlay.width = Math.round(w * dpr); overlay.height = Math.round(h * dpr); }
  octx.setTransform(dpr, 0, 0, dpr, 0, 0); octx.clearRect(0, 0, w, h);
  const cx = w / 2, cy = h / 2;
  const f = (h / 2) / Math.tan((intCam.fov / 2) / DEG);           // pixels per tan(angle)
  const R = Math.min(w, h) * 0.40;                                  // bend dial: 90 deg at R
  const maxBend = (S.config && S.config.max_bend) || Math.PI / 2;
  const tip = S.tip, guide = S.guide || {};
  if (!tip) {
    octx.fillStyle = '#8b97a6'; octx.font = '16px system-ui'; octx.textAlign = 'center';
    octx.fillText('waiting for the tip pose (em_tracker/tip_pose)', cx, cy); return;
  }
  // bend dial: rings at 1/3, 2/3 and the full reachable bend
  octx.lineWidth = 1;
  for (const frac of [1 / 3, 2 / 3, 1]) {
    octx.strokeStyle = frac === 1 ? 'rgba(255,255,255,0.55)' : 'rgba(255,255,255,0.22)';
    octx.setLineDash(frac === 1 ? [] : [4, 4]);
    octx.beginPath(); octx.arc(cx, cy, R * frac, 0, 2 * Math.PI); octx.stroke();
    octx.fillStyle = 'rgba(255,255,255,0.6)'; octx.font = '11px system-ui'; octx.textAlign = 'left';
    octx.fillText(`${Math.round(maxBend * frac * DEG)}\u00b0`, cx - R * frac * 0.383 + 3, cy + R * frac * 0.924 - 3);
  }
  octx.setLineDash([]);
  // heading crosshair
  octx.strokeStyle = '#ff9f1c'; octx.lineWidth = 2;
  octx.beginPath(); octx.moveTo(cx - 12, cy); octx.lineTo(cx + 12, cy); octx.moveTo(cx, cy - 12); octx.lineTo(cx, cy + 12); octx.stroke();
  // wall rays: ticks on the cone, coloured by the distance to the wall
  if (guide.rays) {
    const n = guide.rays.dist.length - 1, cone = guide.rays.cone, rr = f * Math.tan(cone);
    for (let i = 0; i < n; i++) {
      const az = 2 * Math.PI * i / n, d = guide.rays.dist[i + 1];
      const x = cx + rr * Math.cos(az), y = cy - rr * Math.sin(az);
      octx.fillStyle = { bad: '#ff4d4f', warn: '#ffb020', ok: 'rgba(61,220,132,0.8)' }[wallClass(d)];
      octx.beginPath(); octx.arc(x, y, 5, 0, 2 * Math.PI); octx.fill();
      octx.font = '11px system-ui'; octx.textAlign = 'center'; octx.fillStyle = '#e6edf3';
      octx.fillText(d >= guide.rays.length - 1e-6 ? '>' + Math.round(guide.rays.length * MM) : (d * MM).toFixed(0), x, y - 8);
    }
  }
  // next waypoint, in perspective (clamped to the edge with an arrow when outside the view)
  if (guide.waypoint) {
    const wpt = guide.waypoint, l = wpt.local;
    let x, y, inside = l[1] > 1e-6;
    if (inside) { x = cx + f * l[0] / l[1]; y = cy - f * l[2] / l[1]; inside = x > 10 && x < w - 10 && y > 10 && y < h - 10; }
    if (!inside) { const s = Math.min(w, h) * 0.46; x = cx + s * wpt.screen[0]; y = cy - s * wpt.screen[1]; }
    octx.strokeStyle = '#ffd43b'; octx.fillStyle = 'rgba(255,212,59,0.25)'; octx.lineWidth = 2.5;
    octx.beginPath(); octx.arc(x, y, inside ? 10 : 8, 0, 2 * Math.PI); octx.fill(); octx.stroke();
    octx.fillStyle = '#ffd43b'; octx.font = '12px system-ui'; octx.textAlign = 'center';
    octx.fillText(`waypoint ${(wpt.distance * MM).toFixed(0)} mm${inside ? '' : ' (off view)'}`, x, y + 26);
  }
  // suggested bend: arrow from the heading, length = magnitude on the 0..max dial
  const b = S.bend;
  G.drawn.bendArrow = null;
  if (b) {
    const frac = Math.min(b.magnitude / maxBend, 1.05), len = R * frac;
    const ex = cx + len * b.screen[0], ey = cy - len * b.screen[1];
    const over = b.magnitude > maxBend + 1e-6;
    octx.strokeStyle = over ? '#ff4d4f' : '#35d0ff'; octx.fillStyle = octx.strokeStyle; octx.lineWidth = 5;
    octx.beginPath(); octx.moveTo(cx, cy); octx.lineTo(ex, ey); octx.stroke();
    if (len > 4) {
      const a = Math.atan2(ey - cy, ex - cx);
      octx.beginPath(); octx.moveTo(ex + 6 * Math.cos(a), ey + 6 * Math.sin(a));
      octx.lineTo(ex - 14 * Math.cos(a - 0.45), ey - 14 * Math.sin(a - 0.45));
      octx.lineTo(ex - 14 * Math.cos(a + 0.45), ey - 14 * Math.sin(a + 0.45)); octx.closePath(); octx.fill();
    }
    // label beside the middle of the arrow (a short arrow has its value in the readout only)
    if (len > 50) {
      const px = b.screen[1], py = b.screen[0];          // perpendicular on the canvas
      octx.font = '600 13px system-ui'; octx.textAlign = 'center';
      octx.fillText(`bend ${(b.magnitude * DEG).toFixed(0)}\u00b0`, (cx + ex) / 2 + 34 * px, (cy + ey) / 2 + 34 * py + 4);
    }
    G.drawn.bendArrow = [ex - cx, cy - ey];
  }
  // tip axes legend
  octx.fillStyle = 'rgba(230,237,243,0.55)'; octx.font = '11px system-ui'; octx.textAlign = 'left';
  octx.fillText('+ heading (tip y) \u00b7 right = tip x \u00b7 up = tip z \u00b7 dots: distance to the wall along rays, mm \u00b7 rings: bend range', 8, h - 8);
}

function readouts() {
  const g = S.guide || {}, b = S.bend, maxBend = (S.config && S.config.max_bend) || Math.PI / 2;
  const tgt = $('ro-target');
  tgt.textContent = g.dist_target == null ? '\u2013' : fmtMm(g.dist_target);
  tgt.className = 'v ' + (g.dist_target != null && S.config && g.dist_target < S.config.success_radius ? 'ok' : '');
  const wall = $('ro-wall');
  if (g.wall_min == null) { wall.textContent = '\u2013'; wall.className = 'v'; }
  else {
    const len = g.rays.length, ahead = g.wall_ahead >= len - 1e-6 ? `>${Math.round(len * MM)}` : (g.wall_ahead * MM).toFixed(1);
    wall.textContent = `${ahead} / ${(g.wall_min * MM).toFixed(1)} mm`; wall.className = 'v ' + wallClass(g.wall_min);
  }
  const bend = $('ro-bend');
  bend.textContent = b ? `${(b.magnitude * DEG).toFixed(0)}\u00b0 of ${(maxBend * DEG).toFixed(0)}\u00b0` : '\u2013';
  bend.title = b ? `alpha ${(b.alpha * DEG).toFixed(1)} deg, gamma ${(b.gamma * DEG).toFixed(1)} deg` : '';
  bend.className = 'v ' + (b && b.magnitude > maxBend ? 'bad' : '');
  const wp = $('ro-waypoint');
  wp.textContent = g.waypoint ? `${(g.waypoint.distance * MM).toFixed(0)} mm at ${(g.waypoint.angle * DEG).toFixed(0)}\u00b0` : '\u2013';
}

// ------------------------------------------------------------------ status panels
const pad = (n) => String(Math.floor(n)).padStart(2, '0');
const clock = (s) => `${pad(s / 60)}:${pad(s % 60)}`;
function timer() {
  const t = S.trial; if (!t) return;
  let e = t.elapsed_s;
  if (t.phase === 'running' && G.source === 'live') e = Math.min(t.limit_s, e + now_s() - t.receivedAt);
  const el = $('timer');
  el.textContent = clock(e); G.drawn.timer = el.textContent;
  const late = t.phase === 'running' && e > t.limit_s - 30;
  el.className = 'timer ' + (late ? 'late' : t.phase);
  $('timer-limit').textContent = `limit ${clock(t.limit_s)}`;
  $('timer-phase').textContent = { armed: 'starts when the tip moves', running: late ? `${Math.ceil(t.limit_s - e)} s left` : 'running',
    reached: 'TARGET REACHED', timeout: 'TIME LIMIT - trial failed', stopped: 'stopped' }[t.phase] || t.phase;
}
function tracker() {
  const el = $('tracker'), d = S.diagnostics, stale = ((S.config && S.config.stale_after_s) || 0.5);
  if (S.record) {  // record_demos: the tip comes from the simulator, sent when it moves
    el.textContent = `Simulator \u00b7 ${S.record.mode}`; el.title = 'record_demos'; el.className = 'badge ok';
    return;
  }
  const age = G.lastTipReceived ? now_s() - G.lastTipReceived : Infinity;
  let level = 'ERROR', text = 'Tracker: no data';
  const st = d && d.tracker ? d.statuses[d.tracker] : null;
  if (age <= stale) { level = st ? st.level : 'OK'; text = `Tracker: ${st ? st.level : 'tracking'}`; }
  else if (G.lastTipReceived) { level = 'STALE'; text = `Tracker: no pose for ${age < 99 ? age.toFixed(1) : '>99'} s`; }
  if (st && st.level !== 'OK') { level = st.level; text = `Tracker: ${st.level} ${st.message}`.slice(0, 48); }
  el.textContent = text; el.title = st ? `${d.tracker}: ${st.message}` : '';
  el.className = 'badge ' + ({ OK: 'ok', WARN: 'warn' }[level] || 'bad');
}
function diagnostics() {
  const d = S.diagnostics, ul = $('diag'); ul.replaceChildren();
  if (!d) { ul.innerHTML = '<li class="STALE">no /diagnostics received</li>'; return; }
  for (const [name, s] of Object.entries(d.statuses)) {
    const li = document.createElement('li'); li.className = s.level;
    li.textContent = `${name}: ${s.level}`;
    const m = document.createElement('span'); m.className = 'msg'; m.textContent = s.message.slice(0, 60); li.appendChild(m);
    ul.appendChild(li);
  }
}
function replayPanel() {
  const r = S.replay, sel = $('replay-bag');
  const src = $('source');
  src.textContent = G.source === 'replay' ? `REPLAY ${r && r.bag ? r.bag : ''}` : 'LIVE';
  src.className = 'badge ' + (G.source === 'replay' ? 'replay' : 'live');
  if (!r) return;
  const names = r.bags.join('\n');
  if (sel.dataset.names !== names) {
    sel.replaceChildren(...r.bags.map((n) => new Option(n, n))); sel.dataset.names = names;
    if (!r.bags.length) sel.appendChild(new Option('(no bags in bags_dir)', ''));
  }
  $('replay-status').textContent = r.phase === 'idle' ? `${r.bags.length} bag(s) available` : `${r.phase} ${r.bag || ''} ${r.message || ''}`;
}

// ------------------------------------------------------------------ recording (record_demos)
const OUTCOMES = { success: 'TARGET REACHED', collision: 'COLLISION', exited: 'LEFT THE ANATOMY',
  timeout: 'TIME LIMIT', discarded: 'DISCARDED' };
function recordPanel() {
  const r = S.record, on = !!r;
  document.body.classList.toggle('recording', on);
  $('record-panel').hidden = !on;
  if (!on) return;
  $('title').innerHTML = 'Record demonstrations <span class="sub">no planned path: navigate to the target</span>';
  $('ro-bend-k').textContent = 'Commanded bend';
  $('rec-episode').textContent = `Episode ${r.episode} of ${r.episodes} \u00b7 start ${r.start} \u2192 target ${r.target} \u00b7 ${r.mode}`;
  const last = r.last, el = $('rec-phase');
  let text = '', cls = '';
  if (r.phase === 'waiting') { text = 'Waiting for the first insertion'; cls = 'waiting'; }
  else if (r.phase === 'running') text = `Recording \u00b7 ${clock(r.time_left_s)} left`;
  else if (last) {
    text = `${OUTCOMES[last.outcome] || last.outcome}${last.saved ? ' \u00b7 saved' : ''}`;
    cls = last.outcome === 'success' && !last.note ? 'success' : 'fail';
    if (r.phase === 'pause') text += ` \u00b7 next episode in ${Math.ceil(r.pause_left_s)} s`;
    if (r.phase === 'done') text += ' \u00b7 all episodes recorded';
  }
  el.textContent = text; el.className = 'rec-phase ' + cls;
  $('rec-counts').textContent = `saved ${r.saved} (${r.successes} successful) \u00b7 discarded ${r.discarded} \u00b7 by ${r.who || '?'} \u00b7 driver ${r.driver} \u00b7 ${r.out}`;
  $('rec-device').textContent = G.keyboard.held.length ? `keyboard: ${G.keyboard.held.join(' + ')}` : '';
}
// The keyboard as a gamepad, in teleop's layout (the "layout" of the record item).
const KEYMAP = { ' ': 'deadman', e: 'insert', q: 'retract', w: 'up', arrowup: 'up', s: 'down',
  arrowdown: 'down', a: 'left', arrowleft: 'left', d: 'right', arrowright: 'right' };
const held = new Set();
function sendKeys() {
  const r = S.record; if (!r || !r.layout) return;
  const L = r.layout, axes = new Array(L.n_axes).fill(0), buttons = new Array(L.n_buttons).fill(0);
  const k = (name) => (held.has(name) ? 1 : 0);
  axes[L.axis_insertion] = k('insert') - k('retract');
  axes[L.axis_bend_alpha] = k('up') - k('down');
  axes[L.axis_bend_gamma] = k('left') - k('right');
  buttons[L.enable_button] = k('deadman');
  if (G.connected) { G.send({ type: 'joy', axes, buttons }); G.keyboard.sent += 1; }
  G.keyboard.held = [...held].sort();
  dirty.add('record');
}
function discard() {
  if (S.record && G.connected) { G.send({ type: 'record', action: 'discard' }); G.keyboard.discards += 1; }
}
window.addEventListener('keydown', (ev) => {
  if (!S.record || ev.ctrlKey || ev.metaKey || ev.altKey) return;
  const key = ev.key.toLowerCase();
  if (key === 'escape' || key === 'backspace') { ev.preventDefault(); if (!ev.repeat) discard(); return; }
  const name = KEYMAP[key]; if (!name) return;
  ev.preventDefault();
  if (!held.has(name)) { held.add(name); sendKeys(); }
});
window.addEventListener('keyup', (ev) => {
  const name = KEYMAP[ev.key.toLowerCase()];
  if (name && held.delete(name)) sendKeys();
});
window.addEventListener('blur', () => { if (held.size) { held.clear(); sendKeys(); } });
// while a key is held the state is repeated: the recorder drops a state older than 0.5 s
setInterval(() => { if (held.size) sendKeys(); }, 100);
$('rec-discard').onclick = discard;

// ------------------------------------------------------------------ frame loop
// Software WebGL is fill-rate bound: while frames come slower than 12 per second the 3D views
// draw at a lower resolution (down to half), and at full resolution again once the data
// stops for 0.4 s (so a still scene, and a screenshot of it, is sharp).
let renderScale = 1, slowFrames = 0, lastFrameAt = 0, lastDataAt = 0;
function adaptResolution(t, hadData) {
  if (!SOFT) return;
  if (hadData) {
    const dt = t - lastFrameAt;
    slowFrames = dt > 83 ? slowFrames + 1 : 0;
    if (slowFrames >= 3 && renderScale > 0.5) { renderScale = Math.max(0.5, renderScale - 0.15); slowFrames = 0; }
    lastDataAt = t;
  } else if (renderScale < 1 && t - lastDataAt > 400) {
    renderScale = 1; dirty.add('camera');
  }
  G.renderScale = renderScale;
}
function resize(renderer, cam, box) {
  const w = box.clientWidth, h = box.clientHeight;
  const c = renderer.domElement, ratio = PIXEL_RATIO * renderScale;
  if (c.width !== Math.round(w * ratio) || c.height !== Math.round(h * ratio)) {
    renderer.setPixelRatio(ratio); renderer.setSize(w, h, false);
    cam.aspect = w / Math.max(h, 1); cam.updateProjectionMatrix(); return true;
  }
  return false;
}
function frame() {
  requestAnimationFrame(frame);
  const has = (k) => dirty.has(k);
  if (has('mesh')) drawMesh(S.mesh);
  if (has('deform')) applyDeform(S.deform);
  if (has('path')) drawPath(S.path);
  if (has('target') || has('config')) drawTarget(S.target);
  if (has('waypoint')) drawWaypoint(S.waypoint);
  if (has('tip')) drawTip(S.tip);
  if (has('trail')) drawTrail();
  if (has('diagnostics')) diagnostics();
  if (has('replay') || has('source')) replayPanel();
  if (has('record')) recordPanel();
  timer(); tracker();
  let render = dirty.size > 0;
  const t = performance.now();
  adaptResolution(t, has('tip') || has('deform') || has('path'));
  if (G.webgl) {
    render = resize(extRenderer, extCam, $('external-box')) | resize(intRenderer, intCam, $('internal-box')) || render;
    if (render) {
      const t0 = performance.now();
      extRenderer.render(scene, extCam);
      const t1 = performance.now();
      intRenderer.render(scene, intCam);
      G.renderMs.push([t1 - t0, performance.now() - t1]);
      if (G.renderMs.length > 1000) G.renderMs.splice(0, 500);
    }
  }
  if (render) { drawOverlay(); readouts(); scaleBar(); labels(); }
  if (has('tip') && S.tip) {
    G.latencies.push([S.tip.seq, (now_s() - S.tip.stamp) * 1000]);
    if (G.latencies.length > 5000) G.latencies.splice(0, 1000);
  }
  if (render) { G.frames += 1; lastFrameAt = t; }
  dirty.clear();
}

// ------------------------------------------------------------------ controls
$('reset-view').onclick = resetView;
for (const a of ['start', 'stop', 'reset']) $(`trial-${a}`).onclick = () => G.send({ type: 'trial', action: a });
$('replay-play').onclick = () => {
  const bag = $('replay-bag').value; if (!bag) return;
  G.send({ type: 'replay', action: 'start', bag, rate: parseFloat($('replay-rate').value), loop: $('replay-loop').checked });
};
$('replay-live').onclick = () => G.send({ type: 'replay', action: 'stop' });
window.addEventListener('resize', () => dirty.add('camera'));

setConn();
connect();
requestAnimationFrame(frame);
