// mems-stereo live: the browser viewer's page (served by mems_stereo.viz.live_browser).
// Receives one binary WebSocket message per frame on /frames and draws its points on a
// 2D canvas, coloured by range, sigma_r or age (2nd-98th percentile of the frame).
// Self-contained: no library, nothing fetched but this server's own files.
"use strict";

const BG = [17, 17, 17];
const state = {
  frames: 0, index: null, start: null, end: null, points: 0, dropped: 0, drawn: 0,
  connected: false, error: null,
};
window.msViewer = state;  // read by the tests: frames received, last frame's counts

let lut = null;           // 256 x [r, g, b]
let frame = null;         // {head, cols: {x, y, z, range, sigma_r, age, dt}}
let view = null;          // {target, yaw, pitch, dist, f}
let pick = null;          // Int32Array: point index per pixel, -1: none

const canvas = document.getElementById("cloud");
const tip = document.getElementById("tip");
const ctx = canvas.getContext("2d");
const $ = (id) => document.getElementById(id);

function parse(buf) {
  const dv = new DataView(buf);
  const len = dv.getUint32(0, true);
  const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, len)));
  const off = 4 + len + ((4 - ((4 + len) % 4)) % 4);
  const n = head.points;
  const cols = {};
  head.fields.forEach((name, i) => {
    cols[name] = new Float32Array(buf, off + 4 * i * n, n);
  });
  return { head, cols };
}

function percentile(values, q) {
  const v = Array.from(values).filter(Number.isFinite).sort((a, b) => a - b);
  if (!v.length) return NaN;
  return v[Math.min(v.length - 1, Math.max(0, Math.round(q * (v.length - 1))))];
}

function basis(yaw, pitch) {
  // OpenCV camera frame (x right, y down, z forward); yaw about -y, pitch about x
  const f = [Math.cos(pitch) * Math.sin(yaw), Math.sin(pitch), Math.cos(pitch) * Math.cos(yaw)];
  const r = [Math.cos(yaw), 0, -Math.sin(yaw)];
  const u = [f[1] * r[2] - f[2] * r[1], f[2] * r[0] - f[0] * r[2], f[0] * r[1] - f[1] * r[0]];
  return { f, r, u };
}

function sensorView(c) {
  // the sensor's own view: the camera at the origin looking along +z at the median depth
  const zmed = percentile(c.z, 0.5);
  const depth = Number.isFinite(zmed) && zmed > 0 ? zmed : 1;
  view = { target: [0, 0, depth], yaw: 0, pitch: 0, dist: depth, f: null };
}

function camera() {
  const b = basis(view.yaw, view.pitch);
  const t = view.target;
  b.pos = [t[0] - view.dist * b.f[0], t[1] - view.dist * b.f[1], t[2] - view.dist * b.f[2]];
  return b;
}

function fitFocal(c, cam, w, h) {
  // the largest focal length (px) that keeps the frame's points inside the canvas
  let f = Infinity;
  for (let i = 0; i < c.x.length; i++) {
    const d = [c.x[i] - cam.pos[0], c.y[i] - cam.pos[1], c.z[i] - cam.pos[2]];
    const zc = d[0] * cam.f[0] + d[1] * cam.f[1] + d[2] * cam.f[2];
    if (!(zc > 1e-6)) continue;
    const xc = Math.abs(d[0] * cam.r[0] + d[1] * cam.r[1] + d[2] * cam.r[2]) / zc;
    const yc = Math.abs(d[0] * cam.u[0] + d[1] * cam.u[1] + d[2] * cam.u[2]) / zc;
    if (xc > 1e-9) f = Math.min(f, 0.45 * w / xc);
    if (yc > 1e-9) f = Math.min(f, 0.45 * h / yc);
  }
  return Number.isFinite(f) ? f : 0.5 * w;
}

function draw() {
  const w = canvas.clientWidth, h = canvas.clientHeight;
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  const img = ctx.createImageData(w, h);
  const px = img.data;
  for (let i = 0; i < w * h; i++) {
    px[4 * i] = BG[0]; px[4 * i + 1] = BG[1]; px[4 * i + 2] = BG[2]; px[4 * i + 3] = 255;
  }
  pick = new Int32Array(w * h).fill(-1);
  state.drawn = 0;
  if (!frame || !lut || !view || !w || !h) { ctx.putImageData(img, 0, 0); return; }
  const c = frame.cols, n = frame.head.points;
  const cam = camera();
  if (view.f === null) view.f = fitFocal(c, cam, w, h);
  const key = $("colorBy").value;
  const vals = c[key] || c.range;
  const lo = percentile(vals, 0.02), hi = percentile(vals, 0.98);
  const span = hi > lo ? hi - lo : 1;
  legend(key, lo, hi);
  const zbuf = new Float32Array(w * h).fill(Infinity);
  const s = Number($("pointSize").value), half = Math.floor((s - 1) / 2);
  for (let i = 0; i < n; i++) {
    const d0 = c.x[i] - cam.pos[0], d1 = c.y[i] - cam.pos[1], d2 = c.z[i] - cam.pos[2];
    const zc = d0 * cam.f[0] + d1 * cam.f[1] + d2 * cam.f[2];
    if (!(zc > 1e-6)) continue;
    const u = Math.round(w / 2 + view.f * (d0 * cam.r[0] + d1 * cam.r[1] + d2 * cam.r[2]) / zc);
    const v = Math.round(h / 2 + view.f * (d0 * cam.u[0] + d1 * cam.u[1] + d2 * cam.u[2]) / zc);
    const val = vals[i];
    const k = Number.isFinite(val) ? lutIndex((val - lo) / span) : -1;
    const rgb = k < 0 ? [128, 128, 128] : lut[k];
    let hit = false;
    for (let dv = -half; dv < s - half; dv++) {
      const y = v + dv;
      if (y < 0 || y >= h) continue;
      for (let du = -half; du < s - half; du++) {
        const x = u + du;
        if (x < 0 || x >= w) continue;
        const p = y * w + x;
        if (zc >= zbuf[p]) continue;
        zbuf[p] = zc; pick[p] = i; hit = true;
        px[4 * p] = rgb[0]; px[4 * p + 1] = rgb[1]; px[4 * p + 2] = rgb[2];
      }
    }
    if (hit) state.drawn++;
  }
  ctx.putImageData(img, 0, 0);
}

// values 0..1 to the colormap's entries LUT0..255 (turbo's darkest tenth left out: it
// would not show on the dark background)
const LUT0 = 26;
function lutIndex(q) { return LUT0 + Math.round((255 - LUT0) * Math.max(0, Math.min(1, q))); }

function fmt(x, d) { return Number.isFinite(x) ? x.toFixed(d) : "–"; }

function legend(key, lo, hi) {
  const unit = key === "age" ? " frames" : " m";
  $("vmin").textContent = fmt(lo, key === "age" ? 0 : 3) + unit;
  $("vmax").textContent = fmt(hi, key === "age" ? 0 : 3) + unit;
  const ramp = $("ramp"), rc = ramp.getContext("2d");
  for (let x = 0; x < ramp.width; x++) {
    const rgb = lut[lutIndex(x / (ramp.width - 1))];
    rc.fillStyle = `rgb(${rgb[0]},${rgb[1]},${rgb[2]})`;
    rc.fillRect(x, 0, 1, ramp.height);
  }
}

function showStatus() {
  const link = state.connected ? "" : " · waiting for mems-stereo live";
  if (state.index === null) { $("status").textContent = "no frame yet" + link; return; }
  $("status").textContent =
    `frame ${state.index} · ${fmt(state.start, 3)}–${fmt(state.end, 3)} s · ` +
    `${state.points} points · dropped ${state.dropped}${link}`;
}

function onFrame(buf) {
  frame = parse(buf);
  const hd = frame.head;
  if (view === null && hd.points > 0) sensorView(frame.cols);  // fitted to the first points
  Object.assign(state, { index: hd.index, start: hd.start, end: hd.end, points: hd.points,
                         dropped: hd.dropped });
  draw();
  state.frames++;
  showStatus();
}

function connect() {
  const ws = new WebSocket(`ws://${location.host}/frames`);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => { state.connected = true; showStatus(); };
  ws.onmessage = (ev) => {
    try { onFrame(ev.data); } catch (e) { state.error = String(e); throw e; }
  };
  ws.onclose = () => { state.connected = false; showStatus(); setTimeout(connect, 1000); };
}

function hover(ev) {
  if (!frame || !pick) return;
  const rect = canvas.getBoundingClientRect();
  const x0 = Math.round(ev.clientX - rect.left), y0 = Math.round(ev.clientY - rect.top);
  let best = -1, bestD = Infinity;
  for (let dy = -6; dy <= 6; dy++) {
    for (let dx = -6; dx <= 6; dx++) {
      const x = x0 + dx, y = y0 + dy;
      if (x < 0 || y < 0 || x >= canvas.width || y >= canvas.height) continue;
      const i = pick[y * canvas.width + x];
      if (i >= 0 && dx * dx + dy * dy < bestD) { best = i; bestD = dx * dx + dy * dy; }
    }
  }
  if (best < 0) { tip.hidden = true; return; }
  const c = frame.cols;
  tip.textContent =
    `x ${fmt(c.x[best], 3)}  y ${fmt(c.y[best], 3)}  z ${fmt(c.z[best], 3)} m\n` +
    `range ${fmt(c.range[best], 3)} m  σ ${fmt(1000 * c.sigma_r[best], 1)} mm\n` +
    `age ${fmt(c.age[best], 0)} frames  t ${fmt(frame.head.start + c.dt[best], 4)} s`;
  tip.style.left = `${x0 + 14}px`; tip.style.top = `${y0 + 14}px`;
  tip.hidden = false;
}

let drag = null;
canvas.addEventListener("mousedown", (ev) => { drag = [ev.clientX, ev.clientY]; });
window.addEventListener("mouseup", () => { drag = null; });
canvas.addEventListener("mousemove", (ev) => {
  if (drag && view) {
    view.yaw += 0.005 * (ev.clientX - drag[0]);
    view.pitch = Math.max(-1.5, Math.min(1.5, view.pitch + 0.005 * (ev.clientY - drag[1])));
    drag = [ev.clientX, ev.clientY];
    draw();
  }
  hover(ev);
});
canvas.addEventListener("mouseleave", () => { tip.hidden = true; });
canvas.addEventListener("wheel", (ev) => {
  if (!view) return;
  ev.preventDefault();
  view.dist *= ev.deltaY > 0 ? 1.1 : 1 / 1.1;
  draw();
}, { passive: false });
canvas.addEventListener("dblclick", () => { if (frame) { sensorView(frame.cols); draw(); } });
$("colorBy").addEventListener("change", draw);
$("pointSize").addEventListener("change", draw);
window.addEventListener("resize", () => { if (view) view.f = null; draw(); });

fetch("colormap.json").then((r) => r.json()).then((m) => {
  lut = m.turbo;
  showStatus();
  connect();
}).catch((e) => { state.error = String(e); $("status").textContent = `error: ${e}`; });
