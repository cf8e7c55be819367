// slag-edge web page: prompt -> GET /query.ply -> Gaussian-splat render (@mkkellogg/gaussian-splats-3d).
// State for tests and people: document.body.dataset.state = idle | loading | rendered | error |
// no-viewer, document.body.dataset.matches = painted Gaussians of the last answer,
// document.body.dataset.objects = objects drawn (a box and a label each, in the colour their
// Gaussians are painted: /query.ply?color_by=object), and
// document.body.dataset.ready = "1" once the submit handler is attached and the viewer module has
// settled (loaded or failed): a click before that would be lost, so tests wait for it.

const $ = (id) => document.getElementById(id);
const status = (msg) => { $('status').textContent = msg; };
const setState = (s) => { document.body.dataset.state = s; };

// The viewer module loads in the background; the submit handler (at the end) is attached at once
// and awaits it, so a prompt typed while the module is still loading is answered, not dropped.
let GS = null;
let THREE = null;
const viewerLoaded = Promise.all([import('@mkkellogg/gaussian-splats-3d'), import('three')]).then(
  ([m, t]) => { GS = m; THREE = t; return m; },
  (e) => {
    $('help').hidden = false;
    status('viewer not vendored: run bash scripts/web-vendor.sh');
    setState('no-viewer');
    console.error('viewer import failed', e);
    return null;
  },
);

// Bounds of the means in a binary little-endian .ply (float properties x, y, z).
function plyBounds(buf) {
  const head = new TextDecoder().decode(new Uint8Array(buf, 0, Math.min(buf.byteLength, 4096)));
  const end = head.indexOf('end_header\n');
  if (end < 0) throw new Error('not a .ply answer');
  const lines = head.slice(0, end).split('\n');
  const n = parseInt((lines.find((l) => l.startsWith('element vertex')) || '').split(' ')[2], 10);
  const props = lines.filter((l) => l.startsWith('property float')).map((l) => l.split(' ')[2]);
  const stride = props.length;
  const ix = props.indexOf('x');
  const f = new Float32Array(buf.slice(end + 'end_header\n'.length));
  const c = [0, 0, 0];
  for (let i = 0; i < n; i++) for (let a = 0; a < 3; a++) c[a] += f[i * stride + ix + a] / n;
  const d = [];
  for (let i = 0; i < n; i++) {
    let s = 0;
    for (let a = 0; a < 3; a++) s += (f[i * stride + ix + a] - c[a]) ** 2;
    d.push(Math.sqrt(s));
  }
  d.sort((a, b) => a - b);
  return { n, center: c, radius: d.length ? d[Math.floor(0.9 * (d.length - 1))] : 1 };
}

let viewer = null;

// The colours of an answer's objects: slag-edge's OBJECT_PALETTE (view.rs), in answer order.
const PALETTE = [
  [0.12, 0.47, 0.71], [1.0, 0.5, 0.05], [0.17, 0.63, 0.17], [0.84, 0.15, 0.16], [0.58, 0.4, 0.74],
  [0.55, 0.34, 0.29], [0.09, 0.75, 0.81], [0.74, 0.74, 0.13], [1.0, 1.0, 1.0], [0.0, 0.3, 1.0],
];

// An object's oriented box (12 edges) and a label above it, in the object's colour.
function objectMarks(o, k, up, labelSize) {
  const rgb = PALETTE[k % PALETTE.length];
  const colour = new THREE.Color(rgb[0], rgb[1], rgb[2]);
  const { center, axes, extents } = o.obb;
  const corner = (sx, sy, sz) => [0, 1, 2].map((a) => center[a]
    + (sx * extents[0] * axes[0][a] + sy * extents[1] * axes[1][a] + sz * extents[2] * axes[2][a]) / 2);
  const signs = [-1, 1];
  const pts = [];
  for (const a of signs) for (const b of signs) {
    pts.push(corner(-1, a, b), corner(1, a, b));
    pts.push(corner(a, -1, b), corner(a, 1, b));
    pts.push(corner(a, b, -1), corner(a, b, 1));
  }
  const geom = new THREE.BufferGeometry();
  geom.setAttribute('position', new THREE.Float32BufferAttribute(pts.flat(), 3));
  const lines = new THREE.LineSegments(geom, new THREE.LineBasicMaterial({ color: colour, depthTest: false }));
  lines.renderOrder = 10;
  const canvas = document.createElement('canvas');
  canvas.width = 512; canvas.height = 96;
  const g = canvas.getContext('2d');
  g.fillStyle = 'rgba(0,0,0,0.6)'; g.fillRect(0, 0, 512, 96);
  g.fillStyle = `#${colour.getHexString()}`; g.font = 'bold 44px system-ui, sans-serif';
  g.fillText(`#${k + 1}  ${o.gaussians} · ${o.mean_score.toFixed(2)}`, 14, 64);
  const label = new THREE.Sprite(new THREE.SpriteMaterial({ map: new THREE.CanvasTexture(canvas), depthTest: false }));
  label.renderOrder = 11;
  label.scale.set(labelSize, labelSize * 96 / 512, 1);
  const lift = 0.5 * Math.max(...extents) + 0.1 * labelSize;
  label.position.set(...center.map((c, a) => c + up[a] * lift));
  return [lines, label];
}

async function show(text, token) {
  setState('loading');
  status(`asking for “${text}”…`);
  const headers = token ? { Authorization: `Bearer ${token}` } : {};
  const q = encodeURIComponent(text);
  const [r, j] = await Promise.all([
    fetch(`/query.ply?dim=0.35&color_by=object&text=${q}`, { headers }),
    fetch(`/query?top_k=1&text=${q}`, { headers }),
  ]);
  if (!r.ok) {
    let msg = `${r.status}`;
    try { msg = (await r.json()).error; } catch (_) { /* not JSON */ }
    throw new Error(msg);
  }
  const buf = await r.arrayBuffer();
  status(`“${text}”: loading ${buf.byteLength} bytes into the viewer…`);
  const matches = r.headers.get('x-slag-matches') || '0';
  const up = (r.headers.get('x-slag-up') || '0,0,1').split(',').map(Number);
  const b = plyBounds(buf);
  if (b.n === 0) throw new Error('the store holds no Gaussians: fetch a radius first');
  const objects = j.ok ? (await j.json()).objects || [] : [];
  const marks = new THREE.Scene();
  objects.forEach((o, k) => objectMarks(o, k, up, 0.25 * b.radius).forEach((m) => marks.add(m)));
  // Camera: 1.4 radii (90th percentile distance of the means) from the centre, horizontal
  // offset perpendicular to up, slightly above.
  const side = Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  const dot = side[0] * up[0] + side[1] * up[1] + side[2] * up[2];
  const h = side.map((v, a) => v - dot * up[a]);
  const hl = Math.hypot(...h);
  const dist = 1.4 * b.radius;
  const eye = b.center.map((c, a) => c + (h[a] / hl) * dist + up[a] * 0.3 * dist);
  // The viewer's dispose() removes its root element from document.body: give each answer a
  // fresh root there.
  if (viewer) { await viewer.dispose(); viewer = null; }
  const root = document.createElement('div');
  root.className = 'view';
  document.body.appendChild(root);
  viewer = new GS.Viewer({
    rootElement: root,
    cameraUp: up,
    initialCameraPosition: eye,
    initialCameraLookAt: b.center,
    sharedMemoryForWorkers: false,
    gpuAcceleratedSort: false,
    sphericalHarmonicsDegree: 0,
    antialiased: false,
    threeScene: marks,
  });
  const url = URL.createObjectURL(new Blob([buf]));
  await viewer.addSplatScene(url, {
    format: GS.SceneFormat.Ply,
    showLoadingUI: false,
    progressiveLoad: false,
    splatAlphaRemovalThreshold: 1,
  });
  URL.revokeObjectURL(url);
  status(`“${text}”: rendering ${b.n} Gaussians…`);
  viewer.start();
  // Let the sort worker and a few frames finish before calling it rendered.
  for (let i = 0; i < 6; i++) await new Promise((res) => requestAnimationFrame(res));
  document.body.dataset.matches = matches;
  document.body.dataset.objects = String(objects.length);
  status(`“${text}”: ${matches} of ${b.n} Gaussians match, ${objects.length} objects (boxes, `
    + `labelled #rank count · mean score; other matches magenta). Drag to orbit, scroll to zoom.`);
  setState('rendered');
}

$('bar').addEventListener('submit', (ev) => {
  ev.preventDefault();
  const text = $('text').value.trim();
  if (!text) { status('type what to look for first'); return; }
  const token = $('token').value.trim();
  setState('loading');
  viewerLoaded
    .then((m) => {
      if (!m) { setState('no-viewer'); return undefined; }
      return show(text, token);
    })
    .catch((e) => {
      status(`error: ${e.message}`);
      setState('error');
    });
});
// Handlers attached; ready once the viewer module has settled too.
viewerLoaded.then(() => { document.body.dataset.ready = '1'; });
