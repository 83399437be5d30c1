"use strict";
// kpcn view: the page of kpcn_keras/viewer.py (its docstring lists the endpoints). Views arrive as linear
// float32 RGB and are drawn through the display transform of prep.colour.tonemap after the exposure:
// v = max(x * 2^EV, 0), (v / (1 + v))^(1 / 2.2), rounded to 8 bits (tests/test_viewer_browser.py checks a pixel
// against it). A brush stroke paints log λ into the page's copy of the map; when the stroke ends, the map's
// rectangle under it goes to the server, which answers that rectangle denoised again. With a pair, the adapt
// button starts the model's adaptation to the two halves on the server and polls its progress (GET api/adapt)
// until it is done, then shows the adapted view beside kpcn's.

const $ = (id) => document.getElementById(id);
const LAMBDA_VIEW = "lambda";
const SOFT_EDGE = 0.3; // the outer share of the brush radius over which its weight falls to 0
const DIVIDER_GRAB = 6; // screen pixels either side of the swipe divider that grab it in pan mode
const POLL_MS = 250; // how often the page asks how the adaptation goes

const state = {
  info: null, views: {}, images: {}, left: "input", right: "denoised", split: 0.5, exposure: 0,
  zoom: 1, ox: 0, oy: 0, mode: "pan", radius: 24, brushGrey: 1, map: null,
  pending: null, inflight: false, painting: false, strokes: 0, drag: null, mouse: null, lastStroke: null,
  stale: new Set(), adapting: false, adaptations: 0, adaptStatus: null,
};
// for tests and the curious: ready once every view is drawn; busy while a stroke is painted or re-applied
window.kpcn = {
  ready: false, state,
  busy: () => state.painting || state.inflight || state.pending !== null || state.adapting,
};

const canvas = $("canvas");
const ctx = canvas.getContext("2d");

function status(text) { $("status").textContent = text; }

// ------------------------------------------------------------------ λ and its grey level (slope_map.from_grey)

function slopeOfGrey(g) {
  const [lo, hi] = state.info.brush.range;
  return lo * Math.pow(hi / lo, g);
}

function greyOfSlope(s) {
  const [lo, hi] = state.info.brush.range;
  return Math.min(Math.max(Math.log(s / lo) / Math.log(hi / lo), 0), 1);
}

// ------------------------------------------------------------------ views as 8-bit images

function tonemapByte(x, gain) {
  const v = x * gain;
  if (!(v > 0)) return 0; // negative and NaN show black, as max(x, 0) does
  if (v === Infinity) return 255;
  return Math.round(255 * Math.pow(v / (1 + v), 1 / 2.2));
}

// write view `name`'s pixels of rect [y0, y1) x [x0, x1) into its offscreen image
function refresh(name, y0, y1, x0, x1) {
  const { width } = state.info;
  const image = state.images[name];
  const rw = x1 - x0, rh = y1 - y0;
  const data = new ImageData(rw, rh);
  const out = data.data;
  if (name === LAMBDA_VIEW) {
    for (let y = 0; y < rh; y++) for (let x = 0; x < rw; x++) {
      const g = Math.round(255 * greyOfSlope(state.map[(y0 + y) * width + x0 + x]));
      const o = 4 * (y * rw + x);
      out[o] = out[o + 1] = out[o + 2] = g; out[o + 3] = 255;
    }
  } else {
    const src = state.views[name], gain = Math.pow(2, state.exposure);
    for (let y = 0; y < rh; y++) for (let x = 0; x < rw; x++) {
      const i = 3 * ((y0 + y) * width + x0 + x), o = 4 * (y * rw + x);
      out[o] = tonemapByte(src[i], gain); out[o + 1] = tonemapByte(src[i + 1], gain);
      out[o + 2] = tonemapByte(src[i + 2], gain); out[o + 3] = 255;
    }
  }
  image.getContext("2d").putImageData(data, x0, y0);
}

// the views on screen now, the others when they are chosen (a 1920 x 1080 view is 2 M pixels to tonemap)
function refreshAll() {
  state.stale = new Set(Object.keys(state.images));
  refreshShown();
}

function refreshShown() {
  const { width, height } = state.info;
  for (const name of new Set([state.left, state.right])) {
    if (state.stale.delete(name)) refresh(name, 0, height, 0, width);
  }
}

// ------------------------------------------------------------------ drawing: swipe, zoom, pan

function resize() {
  const dpr = window.devicePixelRatio || 1;
  canvas.width = Math.round(canvas.clientWidth * dpr);
  canvas.height = Math.round(canvas.clientHeight * dpr);
}

function fit() {
  const { width, height } = state.info;
  state.zoom = Math.min(canvas.width / width, canvas.height / height);
  state.ox = (canvas.width - width * state.zoom) / 2;
  state.oy = (canvas.height - height * state.zoom) / 2;
  draw();
}

function zoomAbout(factor, sx, sy) {
  const zoom = Math.min(Math.max(state.zoom * factor, 1 / 16), 64);
  state.ox = sx - (sx - state.ox) * (zoom / state.zoom);
  state.oy = sy - (sy - state.oy) * (zoom / state.zoom);
  state.zoom = zoom;
  draw();
}

function draw() {
  if (!state.info) return;
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#181818";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.imageSmoothingEnabled = state.zoom < 1; // pixels stay square when zoomed in
  const splitX = Math.round(canvas.width * state.split);
  for (const [name, x0, x1] of [[state.left, 0, splitX], [state.right, splitX, canvas.width]]) {
    if (x1 <= x0) continue;
    ctx.save();
    ctx.beginPath(); ctx.rect(x0, 0, x1 - x0, canvas.height); ctx.clip();
    ctx.setTransform(state.zoom, 0, 0, state.zoom, state.ox, state.oy);
    ctx.drawImage(state.images[name], 0, 0);
    ctx.restore();
  }
  ctx.fillStyle = "rgba(255,255,255,0.7)";
  ctx.fillRect(splitX - 0.5, 0, 1, canvas.height);
  if (state.mode === "paint" && state.mouse) {
    ctx.strokeStyle = "rgba(255,200,0,0.9)";
    ctx.beginPath();
    ctx.arc(state.mouse.sx, state.mouse.sy, state.radius * state.zoom, 0, 2 * Math.PI);
    ctx.stroke();
  }
  $("zoom-value").textContent = `${Math.round(state.zoom * 100)} %`;
}

function toImage(event) {
  const dpr = window.devicePixelRatio || 1;
  const sx = event.offsetX * dpr, sy = event.offsetY * dpr;
  return { sx, sy, x: (sx - state.ox) / state.zoom, y: (sy - state.oy) / state.zoom };
}

// ------------------------------------------------------------------ the brush

// paint the brush once at image point (cx, cy) into the map; returns the rectangle it touched, or null
function stamp(cx, cy) {
  const { width, height } = state.info;
  const r = state.radius;
  const y0 = Math.max(Math.floor(cy - r), 0), y1 = Math.min(Math.ceil(cy + r) + 1, height);
  const x0 = Math.max(Math.floor(cx - r), 0), x1 = Math.min(Math.ceil(cx + r) + 1, width);
  if (y0 >= y1 || x0 >= x1) return null;
  const target = Math.log(slopeOfGrey(state.brushGrey));
  for (let y = y0; y < y1; y++) for (let x = x0; x < x1; x++) {
    const d = Math.hypot(x + 0.5 - cx, y + 0.5 - cy);
    const w = Math.min(Math.max((r - d) / (SOFT_EDGE * r), 0), 1);
    if (w > 0) {
      const i = y * width + x;
      state.map[i] = Math.exp(Math.log(state.map[i]) + w * (target - Math.log(state.map[i])));
    }
  }
  return [y0, y1, x0, x1];
}

function grow(rect, other) {
  if (!rect) return other;
  if (!other) return rect;
  return [Math.min(rect[0], other[0]), Math.max(rect[1], other[1]), Math.min(rect[2], other[2]),
    Math.max(rect[3], other[3])];
}

function paintTo(point) {
  const from = state.drag.last;
  const steps = Math.max(1, Math.ceil(Math.hypot(point.x - from.x, point.y - from.y) / Math.max(state.radius / 4, 0.5)));
  let rect = null;
  for (let s = 1; s <= steps; s++) {
    rect = grow(rect, stamp(from.x + (point.x - from.x) * s / steps, from.y + (point.y - from.y) * s / steps));
  }
  state.drag.last = point;
  if (rect) {
    state.drag.rect = grow(state.drag.rect, rect);
    refresh(LAMBDA_VIEW, ...rect);
  }
}

function queue(rect) {
  state.pending = grow(state.pending, rect);
  if (!state.inflight) send();
}

async function send() {
  const [y0, y1, x0, x1] = state.pending;
  state.pending = null;
  state.inflight = true;
  const { width } = state.info;
  const values = new Float32Array((y1 - y0) * (x1 - x0));
  for (let y = y0; y < y1; y++) values.set(state.map.subarray(y * width + x0, y * width + x1), (y - y0) * (x1 - x0));
  const begin = performance.now();
  try {
    const res = await fetch(`api/stroke?y0=${y0}&y1=${y1}&x0=${x0}&x1=${x1}`, { method: "POST", body: values });
    if (!res.ok) throw new Error(await res.text());
    const rgb = new Float32Array(await res.arrayBuffer());
    const view = state.views.denoised, rw = x1 - x0;
    for (let y = y0; y < y1; y++) view.set(rgb.subarray(3 * (y - y0) * rw, 3 * (y - y0 + 1) * rw), 3 * (y * width + x0));
    refresh("denoised", y0, y1, x0, x1);
    state.strokes += 1;
    const server = 1000 * Number(res.headers.get("X-Seconds"));
    state.lastStroke = { rect: [y0, y1, x0, x1], serverMs: server, roundTripMs: performance.now() - begin };
    status(`λ re-applied to ${rw}×${y1 - y0} pixels: ${server.toFixed(0)} ms in kpcn, ` +
      `${(performance.now() - begin).toFixed(0)} ms round trip (stroke ${state.strokes})`);
  } catch (err) {
    status(`stroke not applied: ${err.message}`);
  }
  state.inflight = false;
  draw();
  if (state.pending) send();
}

// ------------------------------------------------------------------ the adaptation (with --pair)

function adaptText(s) {
  const loss = s.loss === null ? "" : `, loss ${s.loss.toPrecision(4)}`;
  const budget = s.steps !== null ? `step ${s.step} of ${s.steps}` : `${s.seconds.toFixed(1)} of ${s.budget_seconds} s, step ${s.step}`;
  return `adapting: ${budget}${loss}`;
}

async function startAdapt() {
  const seconds = $("adapt-seconds").value;
  try {
    const res = await fetch(`api/adapt?seconds=${encodeURIComponent(seconds)}`, { method: "POST" });
    if (!res.ok) throw new Error(await res.text());
  } catch (err) {
    status(`adaptation not started: ${err.message}`);
    return;
  }
  state.adapting = true;
  $("adapt-run").disabled = true;
  pollAdapt();
}

async function pollAdapt() {
  let s;
  try {
    s = await (await fetch("api/adapt")).json();
  } catch (err) {
    s = { state: "failed", error: err.message };
  }
  state.adaptStatus = s;
  if (s.state === "running") {
    $("adapt-state").textContent = adaptText(s);
    setTimeout(pollAdapt, POLL_MS);
    return;
  }
  if (s.state === "done") await showAdapted(s.outcome);
  else {
    $("adapt-state").textContent = `adaptation ${s.state}`;
    status(`adaptation ${s.state}: ${s.error}`);
  }
  state.adapting = false;
  $("adapt-run").disabled = false;
}

// the adapted view beside kpcn's: fetched, its option enabled, kpcn left and adapted right
async function showAdapted(outcome) {
  const { width, height } = state.info;
  state.views.adapted = new Float32Array(await (await fetch("api/view/adapted")).arrayBuffer());
  if (!state.images.adapted) {
    state.images.adapted = document.createElement("canvas");
    state.images.adapted.width = width; state.images.adapted.height = height;
  }
  for (const id of ["left", "right"]) {
    const option = Array.from($(id).options).find((o) => o.value === "adapted");
    option.disabled = false; option.textContent = "kpcn adapted";
  }
  state.left = "denoised"; state.right = "adapted";
  $("left").value = "denoised"; $("right").value = "adapted";
  state.stale.add("adapted"); state.stale.add("denoised");
  refreshShown();
  draw();
  state.adaptations += 1;
  $("adapt-state").textContent = outcome.kept ? "adapted: kept" : "adapted: not kept (the model as it was)";
  status(`kpcn | kpcn adapted: ${outcome.line}`);
}

// ------------------------------------------------------------------ events

function setMode(mode) {
  if (mode === "paint" && !state.info.brush) return;
  state.mode = mode;
  canvas.classList.toggle("paint", mode === "paint");
  for (const radio of document.querySelectorAll("input[name=mode]")) radio.checked = radio.value === mode;
  draw();
}

function pixelText(point) {
  const { width, height } = state.info;
  const x = Math.floor(point.x), y = Math.floor(point.y);
  if (x < 0 || y < 0 || x >= width || y >= height) return "";
  const rgb = (name) => {
    if (name === LAMBDA_VIEW) return `λ ${state.map[y * width + x].toFixed(2)}`;
    const v = state.views[name], i = 3 * (y * width + x);
    return `${name} (${v[i].toPrecision(3)}, ${v[i + 1].toPrecision(3)}, ${v[i + 2].toPrecision(3)})`;
  };
  return `x ${x}, y ${y}: ${rgb(state.left)} | ${rgb(state.right)}` + (state.map ? `, λ ${state.map[y * width + x].toFixed(2)}` : "");
}

canvas.addEventListener("pointerdown", (event) => {
  const p = toImage(event);
  canvas.setPointerCapture(event.pointerId);
  const splitX = canvas.width * state.split;
  if (state.mode === "paint") {
    state.painting = true;
    state.drag = { kind: "paint", last: p, rect: stamp(p.x, p.y) };
    if (state.drag.rect) refresh(LAMBDA_VIEW, ...state.drag.rect);
  } else if (Math.abs(p.sx - splitX) <= DIVIDER_GRAB * (window.devicePixelRatio || 1)) {
    state.drag = { kind: "split" };
  } else {
    state.drag = { kind: "pan", sx: p.sx, sy: p.sy, ox: state.ox, oy: state.oy };
  }
  draw();
});

canvas.addEventListener("pointermove", (event) => {
  const p = toImage(event);
  state.mouse = p;
  const drag = state.drag;
  if (drag && drag.kind === "paint") paintTo(p);
  else if (drag && drag.kind === "split") {
    state.split = Math.min(Math.max(p.sx / canvas.width, 0), 1);
    $("split").value = state.split;
  } else if (drag && drag.kind === "pan") {
    state.ox = drag.ox + p.sx - drag.sx; state.oy = drag.oy + p.sy - drag.sy;
  }
  if (!state.inflight) status(pixelText(p) || $("status").textContent);
  draw();
});

function endDrag() {
  if (state.drag && state.drag.kind === "paint") {
    state.painting = false;
    if (state.drag.rect) queue(state.drag.rect);
  }
  state.drag = null;
}
canvas.addEventListener("pointerup", endDrag);
canvas.addEventListener("pointercancel", endDrag);
canvas.addEventListener("pointerleave", () => { state.mouse = null; draw(); });

canvas.addEventListener("wheel", (event) => {
  event.preventDefault();
  const p = toImage(event);
  zoomAbout(event.deltaY < 0 ? 1.25 : 1 / 1.25, p.sx, p.sy);
}, { passive: false });

window.addEventListener("keydown", (event) => {
  if (event.target.tagName === "INPUT" || event.target.tagName === "SELECT") return;
  const actions = {
    b: () => setMode("paint"), h: () => setMode("pan"), 0: fit, 1: () => zoomAbout(1 / state.zoom, canvas.width / 2, canvas.height / 2),
    "+": () => zoomAbout(1.25, canvas.width / 2, canvas.height / 2), "-": () => zoomAbout(1 / 1.25, canvas.width / 2, canvas.height / 2),
  };
  if (actions[event.key]) actions[event.key]();
});

window.addEventListener("resize", () => { resize(); fit(); });

function bindControls() {
  $("left").addEventListener("change", (e) => { state.left = e.target.value; refreshShown(); draw(); });
  $("right").addEventListener("change", (e) => { state.right = e.target.value; refreshShown(); draw(); });
  $("split").addEventListener("input", (e) => { state.split = Number(e.target.value); draw(); });
  $("exposure").addEventListener("input", (e) => {
    state.exposure = Number(e.target.value);
    $("exposure-value").textContent = `${state.exposure > 0 ? "+" : ""}${state.exposure} EV`;
    refreshAll();
    draw();
  });
  $("zoom-fit").addEventListener("click", fit);
  $("zoom-1").addEventListener("click", () => zoomAbout(1 / state.zoom, canvas.width / 2, canvas.height / 2));
  $("zoom-in").addEventListener("click", () => zoomAbout(1.25, canvas.width / 2, canvas.height / 2));
  $("zoom-out").addEventListener("click", () => zoomAbout(1 / 1.25, canvas.width / 2, canvas.height / 2));
  for (const radio of document.querySelectorAll("input[name=mode]")) {
    radio.addEventListener("change", (e) => setMode(e.target.value));
  }
  $("brush-slope").addEventListener("input", (e) => {
    state.brushGrey = Number(e.target.value);
    $("brush-slope-value").textContent = slopeOfGrey(state.brushGrey).toFixed(2);
  });
  $("brush-radius").addEventListener("input", (e) => {
    state.radius = Number(e.target.value);
    $("brush-radius-value").textContent = `${state.radius} px`;
    draw();
  });
  $("adapt-run").addEventListener("click", startAdapt);
  $("fill").addEventListener("click", () => {
    const { width, height } = state.info;
    state.map.fill(slopeOfGrey(state.brushGrey));
    refresh(LAMBDA_VIEW, 0, height, 0, width);
    queue([0, height, 0, width]);
  });
}

function fillSelects(names) {
  for (const [id, chosen] of [["left", state.left], ["right", state.right]]) {
    const select = $(id);
    for (const view of names) {
      const option = new Option(view.label + (view.available ? "" : ` (${view.missing})`), view.name, false,
        view.name === chosen);
      option.disabled = !view.available;
      select.add(option);
    }
  }
}

async function load() {
  const info = await (await fetch("api/info")).json();
  state.info = info;
  const names = info.views.slice();
  const available = names.filter((v) => v.available).map((v) => v.name);
  await Promise.all(available.map(async (name) => {
    state.views[name] = new Float32Array(await (await fetch(`api/view/${name}`)).arrayBuffer());
  }));
  for (const name of available) {
    state.images[name] = document.createElement("canvas");
    state.images[name].width = info.width; state.images[name].height = info.height;
  }
  if (info.brush) {
    state.map = new Float32Array(info.width * info.height).fill(info.brush.slope);
    state.brushGrey = 1;
    $("brush-slope").value = 1;
    $("brush-slope-value").textContent = slopeOfGrey(1).toFixed(2);
    state.images[LAMBDA_VIEW] = document.createElement("canvas");
    state.images[LAMBDA_VIEW].width = info.width; state.images[LAMBDA_VIEW].height = info.height;
    names.push({ name: LAMBDA_VIEW, label: "λ map", available: true });
  } else {
    $("brush").classList.add("off");
    document.querySelector("input[value=paint]").disabled = true;
  }
  if (info.adapt) $("adapt-seconds").value = info.adapt.seconds;
  else {
    $("adapt").classList.add("off");
    $("adapt").title = info.adapt_note;
    $("adapt-run").disabled = true;
  }
  $("brush-radius-value").textContent = `${state.radius} px`;
  fillSelects(names);
  bindControls();
  refreshAll();
  resize();
  fit();
  $("title").textContent = `kpcn view · ${info.name}`;
  status(`${info.name}: ${info.width}×${info.height}, model ${info.model}` +
    (info.brush ? `; λ ${info.brush.slope} everywhere, range ${info.brush.range[0]}–${info.brush.range[1]}`
      : `; no λ brush: ${info.brush_note}`));
  window.kpcn.ready = true;
}

load().catch((err) => status(`could not load the frame: ${err.message}`));
