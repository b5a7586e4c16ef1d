// crosspath view: draws the frames the server sends over /ws on a canvas. No build step.
// World units are metres (x east, y north); the canvas flips y.
"use strict";

const MODE_COLOURS = { AUTO: "#1f6fd1", C_SLOW: "#d62728", C_FAST: "#2ca02c" };
const MODE_LABELS = {
  AUTO: "AUTO: plans alone",
  C_SLOW: "C_SLOW: told to yield",
  C_FAST: "C_FAST: told to go first",
};
const OTHER = "#7f7f7f";
const CP_COLOUR = "rgba(148, 103, 189, 0.5)";
const ZONE_COLOUR = "rgba(255, 150, 30, 0.35)";
const BUILDING = "#c9ccd1";
const ROAD = "#e9ebee";

const $ = (id) => document.getElementById(id);
const canvas = $("map");
const ctx = canvas.getContext("2d");

let map = null;          // static map from the server
let frame = null;        // latest frame
let view = null;         // [xmin, ymin, xmax, ymax] shown
let userView = false;    // the user panned or zoomed: keep their view
let showPaths = true;
let frames = 0;
let socket = null;
let scrubbing = false;
const firstSeen = {};    // car id -> [x, y] where the page first saw it
const sparks = {};       // car id -> its latest sparkline (not every frame carries them)

function modeColour(mode) { return MODE_COLOURS[mode] || OTHER; }

// ---------------------------------------------------------------- transform

function fitBox(box) {
  const pad = 0.04 * Math.max(box[2] - box[0], box[3] - box[1], 1);
  view = [box[0] - pad, box[1] - pad, box[2] + pad, box[3] + pad];
}

function transform() {
  const w = canvas.clientWidth, h = canvas.clientHeight;
  const [x0, y0, x1, y1] = view;
  const s = Math.min(w / (x1 - x0), h / (y1 - y0));
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  return { s, tx: w / 2 - cx * s, ty: h / 2 + cy * s, w, h };
}

function toScreen(T, x, y) { return [T.tx + x * T.s, T.ty - y * T.s]; }

function polyline(T, pts) {
  ctx.beginPath();
  pts.forEach((p, i) => {
    const [sx, sy] = toScreen(T, p[0], p[1]);
    if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
  });
}

// ---------------------------------------------------------------- drawing

function drawMap(T) {
  ctx.fillStyle = "#f4f1ea";
  ctx.fillRect(0, 0, T.w, T.h);
  if (!map) return;
  for (const lane of map.lanes) {           // roads: each lane as a wide grey band
    ctx.strokeStyle = ROAD; ctx.lineWidth = Math.max(1, lane.width * T.s); ctx.lineCap = "butt";
    polyline(T, lane.points); ctx.stroke();
  }
  for (const lane of map.lanes) {           // lane centre lines, thin and dashed
    ctx.strokeStyle = "#b8bdc4"; ctx.lineWidth = 1; ctx.setLineDash([6, 6]);
    polyline(T, lane.points); ctx.stroke();
  }
  ctx.setLineDash([]);
  for (const b of map.buildings) {
    ctx.fillStyle = BUILDING; ctx.strokeStyle = "#a9adb4"; ctx.lineWidth = 1;
    polyline(T, b.polygon); ctx.closePath(); ctx.fill(); ctx.stroke();
  }
  for (const it of map.intersections) {
    ctx.fillStyle = ZONE_COLOUR; ctx.strokeStyle = "rgba(220, 110, 0, 0.9)"; ctx.lineWidth = 1.5;
    polyline(T, it.zone); ctx.closePath(); ctx.fill(); ctx.stroke();
    // the id beside the zone's lower right corner, clear of the RSU marker at the centre
    const [sx, sy] = toScreen(T, Math.max(...it.zone.map((p) => p[0])), Math.min(...it.zone.map((p) => p[1])));
    ctx.fillStyle = "#8a4b00"; ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "left";
    ctx.fillText(it.id, sx + 3, sy + 12);
  }
}

function drawRsus(T) {
  const rsus = (frame && frame.rsus) || (map && map.rsus) || [];
  for (const r of rsus) {
    const [sx, sy] = toScreen(T, r.x, r.y);
    ctx.strokeStyle = "rgba(90, 60, 160, 0.7)"; ctx.lineWidth = 1.5; ctx.setLineDash([8, 5]);
    ctx.beginPath(); ctx.arc(sx, sy, r.r * T.s, 0, 2 * Math.PI); ctx.stroke();
    ctx.setLineDash([]);
    ctx.fillStyle = "#5a3ca0";
    ctx.beginPath(); ctx.moveTo(sx, sy - 7); ctx.lineTo(sx + 6, sy + 5); ctx.lineTo(sx - 6, sy + 5);
    ctx.closePath(); ctx.fill();
    ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "left";
    ctx.fillText(r.id, sx + 8, sy + 4);
  }
}

function drawPaths(T, car) {
  if (!showPaths) return;
  if (car.cp && car.cp.length > 1) {        // coordinated path from the RSU: wide violet band
    ctx.strokeStyle = CP_COLOUR; ctx.lineWidth = Math.max(8, 3 * T.s); ctx.lineCap = "round";
    polyline(T, car.cp); ctx.stroke();
  }
  if (car.fp && car.fp.length > 1) {        // broadcast future path: dashed, car's mode colour
    ctx.strokeStyle = modeColour(car.mode); ctx.lineWidth = 2; ctx.setLineDash([5, 4]);
    polyline(T, car.fp); ctx.stroke(); ctx.setLineDash([]);
    const end = car.fp[car.fp.length - 1];
    const [ex, ey] = toScreen(T, end[0], end[1]);
    ctx.fillStyle = modeColour(car.mode); ctx.beginPath(); ctx.arc(ex, ey, 3, 0, 2 * Math.PI); ctx.fill();
  }
}

function drawCar(T, car) {
  const [sx, sy] = toScreen(T, car.x, car.y);
  const L = Math.max(car.len * T.s, 10), W = Math.max(car.wid * T.s, 5);
  ctx.save();
  ctx.globalAlpha = car.stale ? 0.4 : 1;
  ctx.translate(sx, sy); ctx.rotate(-car.h);
  ctx.fillStyle = modeColour(car.mode); ctx.strokeStyle = "#111"; ctx.lineWidth = 1.2;
  ctx.beginPath(); ctx.rect(-L / 2, -W / 2, L, W); ctx.fill(); ctx.stroke();
  ctx.fillStyle = "rgba(255,255,255,0.85)";   // windscreen: which way is forward
  ctx.fillRect(L / 2 - Math.max(3, L * 0.22), -W / 2 + 1.5, Math.max(2, L * 0.1), W - 3);
  ctx.restore();
  ctx.font = "bold 12px system-ui, sans-serif"; ctx.textAlign = "center";
  ctx.lineWidth = 3; ctx.strokeStyle = "#fff"; ctx.strokeText(car.id, sx, sy - W / 2 - 6);
  ctx.fillStyle = "#111"; ctx.fillText(car.id, sx, sy - W / 2 - 6);
}

function niceLength(m) {
  const p = Math.pow(10, Math.floor(Math.log10(m)));
  for (const k of [5, 2, 1]) if (k * p <= m) return k * p;
  return p;
}

function drawScale(T) {
  const metres = niceLength(120 / T.s);
  const px = metres * T.s, x = 14, y = T.h - 16;
  ctx.strokeStyle = "#111"; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(x, y - 5); ctx.lineTo(x, y); ctx.lineTo(x + px, y); ctx.lineTo(x + px, y - 5); ctx.stroke();
  ctx.fillStyle = "#111"; ctx.font = "12px system-ui, sans-serif"; ctx.textAlign = "center";
  ctx.fillText(`${metres} m`, x + px / 2, y - 6);
  ctx.textAlign = "right"; ctx.fillStyle = "#555";
  ctx.fillText("x east, y north (m)", T.w - 10, T.h - 10);
}

function draw() {
  const dpr = window.devicePixelRatio || 1;
  const w = canvas.clientWidth, h = canvas.clientHeight;
  if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
    canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
  }
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  if (!map && !userView && frame && frame.cars.length) view = null;  // no map: follow the cars
  if (!view) {
    if (map) fitBox(map.focus);
    else if (frame && frame.cars.length) fitBox(carBox(frame.cars));
    else fitBox([-50, -50, 50, 50]);
  }
  const T = transform();
  drawMap(T);
  drawRsus(T);
  if (frame) {
    for (const car of frame.cars) drawPaths(T, car);
    for (const car of frame.cars) if (!car.left) drawCar(T, car);
  }
  drawScale(T);
}

function carBox(cars) {
  const xs = cars.map((c) => c.x), ys = cars.map((c) => c.y);
  return [Math.min(...xs) - 30, Math.min(...ys) - 30, Math.max(...xs) + 30, Math.max(...ys) + 30];
}

// ---------------------------------------------------------------- side panel

function legendSwatch(drawFn) {
  const c = document.createElement("canvas");
  c.width = 68; c.height = 28;
  const g = c.getContext("2d"); g.scale(2, 2); drawFn(g);
  return c;
}

function buildLegend() {
  const el = $("legend");
  const add = (fn, text) => {
    el.appendChild(legendSwatch(fn));
    const s = document.createElement("span"); s.textContent = text; el.appendChild(s);
  };
  for (const mode of ["AUTO", "C_SLOW", "C_FAST"]) {
    add((g) => { g.fillStyle = MODE_COLOURS[mode]; g.strokeStyle = "#111"; g.fillRect(7, 3, 20, 8); g.strokeRect(7, 3, 20, 8); },
      `car, mode ${MODE_LABELS[mode]}`);
  }
  add((g) => { g.strokeStyle = "#1f6fd1"; g.lineWidth = 2; g.setLineDash([5, 4]); g.beginPath(); g.moveTo(2, 7); g.lineTo(32, 7); g.stroke(); },
    "future path it broadcasts (mode colour)");
  add((g) => { g.strokeStyle = CP_COLOUR; g.lineWidth = 6; g.lineCap = "round"; g.beginPath(); g.moveTo(4, 7); g.lineTo(30, 7); g.stroke(); },
    "coordinated path the RSU sent it");
  add((g) => { g.fillStyle = ZONE_COLOUR; g.strokeStyle = "rgba(220,110,0,0.9)"; g.fillRect(8, 1, 18, 12); g.strokeRect(8, 1, 18, 12); },
    "conflict zone of an intersection");
  add((g) => { g.strokeStyle = "rgba(90,60,160,0.7)"; g.lineWidth = 1.5; g.setLineDash([4, 3]); g.beginPath(); g.arc(17, 16, 13, Math.PI * 1.1, Math.PI * 1.9); g.stroke(); g.fillStyle = "#5a3ca0"; g.beginPath(); g.moveTo(17, 2); g.lineTo(21, 9); g.lineTo(13, 9); g.fill(); },
    "RSU and its coverage");
  add((g) => { g.fillStyle = BUILDING; g.strokeStyle = "#a9adb4"; g.fillRect(8, 1, 18, 12); g.strokeRect(8, 1, 18, 12); },
    "building (blocks the view)");
}

function sparkline(c, car, vmax) {
  const w = c.clientWidth || 280, h = c.clientHeight || 34, dpr = window.devicePixelRatio || 1;
  c.width = Math.round(w * dpr); c.height = Math.round(h * dpr);
  const g = c.getContext("2d"); g.scale(dpr, dpr);
  g.fillStyle = "#fafbfc"; g.fillRect(0, 0, w, h);
  const pts = car.spark;
  if (!pts.length) return;
  const t1 = pts[pts.length - 1][0], t0 = Math.min(pts[0][0], t1 - 10);
  const X = (t) => 2 + (w - 4) * (t - t0) / Math.max(t1 - t0, 1e-6);
  const Y = (v) => h - 3 - (h - 8) * v / vmax;
  g.strokeStyle = modeColour(car.mode); g.lineWidth = 1.5; g.beginPath();
  pts.forEach((p, i) => { if (i === 0) g.moveTo(X(p[0]), Y(p[1])); else g.lineTo(X(p[0]), Y(p[1])); });
  g.stroke();
  g.fillStyle = "#6b7280"; g.font = "10px system-ui, sans-serif"; g.textAlign = "left";
  g.fillText(`${vmax.toFixed(0)} m/s`, 3, 10);
  g.textAlign = "right"; g.fillText(`last ${(t1 - t0).toFixed(0)} s`, w - 3, h - 3);
}

function updatePanel() {
  const cars = frame.cars;
  $("ncars").textContent = `(${cars.length})`;
  const vmax = Math.max(5, ...cars.flatMap((c) => c.spark.map((p) => p[1])));
  const box = $("cars");
  const seen = new Set();
  for (const car of cars) {
    seen.add(car.id);
    let el = box.querySelector(`[data-id="${CSS.escape(car.id)}"]`);
    if (!el) {
      el = document.createElement("div"); el.className = "car"; el.dataset.id = car.id;
      el.innerHTML = '<div class="row"><span class="id"></span><span class="mode"></span><span class="v"></span></div>' +
        '<div class="reason"></div><canvas></canvas>';
      box.appendChild(el);
    }
    el.classList.toggle("stale", car.stale || car.left);
    el.style.borderLeftColor = modeColour(car.mode);
    el.querySelector(".id").textContent = car.id;
    const m = el.querySelector(".mode"); m.textContent = car.mode; m.style.background = modeColour(car.mode);
    el.querySelector(".v").textContent = `${car.v.toFixed(1)} m/s`;
    el.querySelector(".reason").textContent =
      `(${car.x.toFixed(1)}, ${car.y.toFixed(1)}) m` + (car.reason ? ` · ${car.reason}` : "") +
      (car.cp.length ? ` · coordinated by ${car.cp_rsu}` : "") + (car.left ? " · at goal" : "");
    el.dataset.x = car.x; el.dataset.y = car.y; el.dataset.mode = car.mode;
    sparkline(el.querySelector("canvas"), car, vmax);
  }
  for (const el of [...box.children]) if (!seen.has(el.dataset.id)) el.remove();
  const c = frame.counters;
  $("counters").textContent = Object.keys(c).map((k) => `${k.padEnd(17)}${c[k]}`).join("\n");
}

function updateHeader() {
  const t = frame.t;
  $("clock").textContent = t === null ? "t = –" : `t = ${t.toFixed(2)} s`;
  const run = frame.run || {};
  const name = (map && map.name) || run.scenario;
  $("scenario").textContent = name ? `scenario ${name}` : "no run yet";
  const bits = [];
  if (run.mode) bits.push(`mode ${run.mode}`);
  if (run.policy && run.mode === "rsu") bits.push(`policy ${run.policy}`);
  if (run.seed !== undefined) bits.push(`seed ${run.seed}`);
  if (frame.ended) bits.push("run ended");
  $("runinfo").textContent = bits.join(" · ");
  const st = $("status");
  st.textContent = frame.source === "live" ? "live" : "replay";
  st.className = frame.source === "live" ? "live" : "";
  const rp = frame.replay;
  $("replaybar").classList.toggle("hidden", !rp);
  if (rp) {
    $("btn-play").textContent = rp.playing ? "pause" : "play";
    const s = $("scrub");
    s.min = rp.t_start; s.max = rp.t_end;
    if (!scrubbing) s.value = rp.t;
    $("tlabel").textContent = `${rp.t.toFixed(2)} / ${rp.t_end.toFixed(2)} s`;
    const sel = $("rate");
    if (document.activeElement !== sel) {
      let opt = [...sel.options].find((o) => Number(o.value) === rp.rate);
      if (!opt) { opt = new Option(`${rp.rate}x`, String(rp.rate)); sel.add(opt); }
      sel.value = opt.value;
    }
  }
}

function exposeState() {
  // For tests and scripts: where each car is, and how far it moved since the page first saw it.
  const moved = {};
  for (const car of frame.cars) {
    if (!(car.id in firstSeen)) firstSeen[car.id] = [car.x, car.y];
    const [x0, y0] = firstSeen[car.id];
    moved[car.id] = Math.round(Math.hypot(car.x - x0, car.y - y0) * 100) / 100;
  }
  const st = $("state");
  st.dataset.cars = JSON.stringify(frame.cars.map((c) => ({ id: c.id, x: c.x, y: c.y, mode: c.mode })));
  st.dataset.moved = JSON.stringify(moved);
  st.dataset.t = frame.t === null ? "" : String(frame.t);
  document.body.dataset.frames = String(frames);
  window.crosspathView = { frame, moved, frames };
}

// ---------------------------------------------------------------- wiring

function send(obj) { if (socket && socket.readyState === 1) socket.send(JSON.stringify(obj)); }

function connect() {
  const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`;
  socket = new WebSocket(url);
  socket.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.type === "map") {
      map = msg.map; view = null;
    } else if (msg.type === "frame") {
      frame = msg; frames += 1;
      for (const car of frame.cars) {
        if (car.spark) sparks[car.id] = car.spark;
        car.spark = sparks[car.id] || [];
      }
      for (const id of Object.keys(sparks)) if (!frame.cars.some((c) => c.id === id)) delete sparks[id];
      updateHeader(); updatePanel(); exposeState();
    }
    draw();
  };
  socket.onclose = () => {
    $("status").textContent = "disconnected"; $("status").className = "down";
    setTimeout(connect, 1000);
  };
}

let drag = null;
canvas.addEventListener("mousedown", (e) => { userView = true; drag = [e.clientX, e.clientY, view.slice()]; canvas.style.cursor = "grabbing"; });
window.addEventListener("mouseup", () => { drag = null; canvas.style.cursor = "grab"; });
window.addEventListener("mousemove", (e) => {
  if (!drag) return;
  const T = transform();
  const dx = (e.clientX - drag[0]) / T.s, dy = (e.clientY - drag[1]) / T.s;
  const v = drag[2];
  view = [v[0] - dx, v[1] + dy, v[2] - dx, v[3] + dy]; draw();
});
canvas.addEventListener("wheel", (e) => {
  e.preventDefault();
  userView = true;
  const T = transform();
  const r = canvas.getBoundingClientRect();
  const wx = (e.clientX - r.left - T.tx) / T.s, wy = (T.ty - (e.clientY - r.top)) / T.s;
  const k = e.deltaY > 0 ? 1.2 : 1 / 1.2;
  view = [wx + (view[0] - wx) * k, wy + (view[1] - wy) * k, wx + (view[2] - wx) * k, wy + (view[3] - wy) * k];
  draw();
}, { passive: false });
$("btn-focus").onclick = () => { if (map) fitBox(map.focus); draw(); };
$("btn-fit").onclick = () => { if (map) fitBox(map.bounds); else if (frame) fitBox(carBox(frame.cars)); draw(); };
$("btn-paths").onclick = () => { showPaths = !showPaths; $("btn-paths").textContent = `paths: ${showPaths ? "on" : "off"}`; draw(); };
$("btn-play").onclick = () => send({ cmd: frame && frame.replay && frame.replay.playing ? "pause" : "play" });
$("scrub").addEventListener("input", () => { scrubbing = true; send({ cmd: "seek", t: Number($("scrub").value) }); });
$("scrub").addEventListener("change", () => { scrubbing = false; });
$("rate").addEventListener("change", () => send({ cmd: "rate", rate: Number($("rate").value) }));
window.addEventListener("resize", draw);

buildLegend();
draw();
connect();
