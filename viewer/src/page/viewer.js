// The page of `nerfjit view`: draws the frames the server renders, sends camera moves and script edits.
// Protocol (one WebSocket, /ws?token=...):
//   page → server (JSON): {type: "camera", id, eye, target, up, focal, width, height, layer}
//                         {type: "source", id, text}
//   server → page (JSON): hello {name, source, checkpoint, bake: {path, splats, checkpoint} or null},
//                         scene {kind, layers, cameras, consts, ...},
//                         diagnostics {source_id, items: [{message, hint, at: {line, column, end_line, end_column}}]},
//                         error {message}
//   server → page (binary): frame = u32 LE header length, JSON header {camera_id, source_id, width, height,
//                           final, format, render_ms, encode_ms}, PNG or JPEG bytes.
"use strict";

const $ = (id) => document.getElementById(id);
const canvas = $("canvas");
const context = canvas.getContext("2d");
const editor = $("source");

// Everything the page knows, also read by the browser test (window.nerfjitViewer).
const viewer = {
  socket: null,
  nextId: 1,
  name: "",
  scene: null,
  camera: null,          // {eye, target, up, focal}
  layer: "color",
  cameraSent: new Map(), // camera request id → time sent
  sourceSent: new Map(), // source request id → time sent
  lastCameraId: 0,
  lastSourceId: 0,
  stats: { cameraToFrame: [], editToFrame: [], frames: 0, finalFrames: 0, renderMs: [], encodeMs: [] },
  lastFinal: null,       // {cameraId, sourceId, blob} of the last full-size frame
  diagnostics: [],
  training: null,        // {history: [records], paused} during `nerfjit run --view`
  exported: [],          // {name, size} of the files the server made for the export buttons
  paramsStep: null,      // the training step of the params in the last frame drawn
  bake: null,            // {path, splats, checkpoint} when the page shows a bake
};
window.nerfjitViewer = viewer;

// ---- small vector helpers -------------------------------------------------------------------------
const add = (a, b) => a.map((x, i) => x + b[i]);
const sub = (a, b) => a.map((x, i) => x - b[i]);
const scale = (a, s) => a.map((x) => x * s);
const dot = (a, b) => a.reduce((s, x, i) => s + x * b[i], 0);
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.hypot(...a);
const unit = (a) => scale(a, 1 / (norm(a) || 1));
// Rotates v about unit axis k by angle (Rodrigues).
function rotate(v, k, angle) {
  const c = Math.cos(angle), s = Math.sin(angle);
  return add(add(scale(v, c), scale(cross(k, v), s)), scale(k, dot(k, v) * (1 - c)));
}

// ---- connection -----------------------------------------------------------------------------------
function connect() {
  const token = new URLSearchParams(location.search).get("token") || "";
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const socket = new WebSocket(`${scheme}://${location.host}/ws?token=${encodeURIComponent(token)}`);
  socket.binaryType = "arraybuffer";
  socket.onmessage = (event) => {
    if (typeof event.data === "string") {
      onMessage(JSON.parse(event.data));
    } else {
      onFrame(event.data);
    }
  };
  socket.onclose = () => setStatus("disconnected: reload the page (is `nerfjit view` still running?)");
  viewer.socket = socket;
}

function send(message) {
  if (viewer.socket && viewer.socket.readyState === WebSocket.OPEN) {
    viewer.socket.send(JSON.stringify(message));
  }
}

function setStatus(text) {
  $("status").textContent = text;
}

function onMessage(message) {
  switch (message.type) {
    case "hello":
      viewer.name = message.name;
      $("name").textContent = message.name + (message.checkpoint ? " (trained checkpoint)" : "");
      editor.value = message.source;
      refreshEditor();
      if (message.bake) {
        // The splats do not follow the script: it is shown read-only, as the field they were baked from.
        viewer.bake = message.bake;
        viewer.name = message.bake.path;
        editor.readOnly = true;
        $("name").textContent = `${message.bake.path}: ${message.bake.splats.toLocaleString("en")} splats baked from ` +
          `${message.bake.checkpoint} (its script, read-only)`;
      }
      if (message.training) {
        viewer.training = message.training;
        editor.readOnly = true;
        $("training").hidden = false;
        showTraining();
      }
      break;
    case "progress":
      viewer.training.history.push(message.record);
      showTraining();
      break;
    case "scene":
      onScene(message);
      break;
    case "diagnostics":
      viewer.diagnostics = message.items;
      refreshEditor();
      showDiagnostics(message.items);
      break;
    case "error":
      setStatus("error: " + message.message);
      break;
  }
}

function onScene(scene) {
  const first = viewer.scene === null;
  viewer.scene = scene;
  const layer = $("layer");
  layer.replaceChildren(...scene.layers.map((name) => new Option(name, name, false, name === viewer.layer)));
  if (!scene.layers.includes(viewer.layer)) {
    viewer.layer = "color";
  }
  const cameras = $("camera");
  cameras.replaceChildren(new Option("free", "free"),
    ...scene.cameras.map((camera, i) => new Option(camera.label, String(i))));
  buildSliders(scene.consts);
  if (first) {
    viewer.camera = scene.cameras.length > 0 ? { ...scene.cameras[0] }
      : { eye: [2.5, 2, -4], target: [0, 0, 0], up: [0, 1, 0], focal: 1.5 };
    if (scene.cameras.length > 0) {
      cameras.value = "0";
    }
  }
  const made = scene.kind === "splats" ? "ready" : "compiled";
  setStatus(`${scene.kind} · ${made} in ${scene.compile_ms.toFixed(0)} ms` + (scene.note ? ` · ${scene.note}` : ""));
  updateCommands();
  requestFrame();
}

// ---- frames ---------------------------------------------------------------------------------------
let frameQueued = false;
// Sends the current camera once per animation frame at most (the server renders the latest anyway).
function requestFrame() {
  if (frameQueued) {
    return;
  }
  frameQueued = true;
  requestAnimationFrame(() => {
    frameQueued = false;
    if (!viewer.camera) {
      return;
    }
    const id = viewer.nextId++;
    viewer.cameraSent.set(id, performance.now());
    viewer.lastCameraId = id;
    send({ type: "camera", id, ...viewer.camera, width: canvas.width, height: canvas.height, layer: viewer.layer });
  });
}

// Frames are drawn in the order they arrive (the server's order), even when a later one decodes first.
let framesArrived = 0, framesDrawn = 0;
async function onFrame(data) {
  const order = ++framesArrived;
  const view = new DataView(data);
  const headerLength = view.getUint32(0, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(data, 4, headerLength)));
  if (header.type === "file") {
    const file = new Blob([new Uint8Array(data, 4 + headerLength)], { type: header.mime });
    viewer.exported.push({ name: header.name, size: file.size });
    download(file, header.name);
    setStatus(`exported ${header.name} (${(file.size / 1024).toFixed(0)} KiB)`);
    return;
  }
  const blob = new Blob([new Uint8Array(data, 4 + headerLength)], { type: `image/${header.format}` });
  const bitmap = await createImageBitmap(blob);
  if (order < framesDrawn) {
    return;
  }
  framesDrawn = order;
  context.imageSmoothingEnabled = !header.final;
  context.drawImage(bitmap, 0, 0, canvas.width, canvas.height);
  const now = performance.now();
  viewer.stats.frames += 1;
  viewer.stats.renderMs.push(header.render_ms);
  viewer.stats.encodeMs.push(header.encode_ms);
  viewer.paramsStep = header.params_step;
  const sent = viewer.cameraSent.get(header.camera_id);
  if (sent !== undefined) {
    viewer.stats.cameraToFrame.push(now - sent);
    viewer.cameraSent.delete(header.camera_id);
  }
  const edited = viewer.sourceSent.get(header.source_id);
  if (edited !== undefined) {
    viewer.stats.editToFrame.push(now - edited);
    viewer.sourceSent.delete(header.source_id);
  }
  if (header.final) {
    viewer.stats.finalFrames += 1;
    viewer.lastFinal = { cameraId: header.camera_id, sourceId: header.source_id, blob };
  }
  const size = `${header.width}×${header.height}`;
  const kind = viewer.scene ? viewer.scene.kind : "";
  const errors = viewer.diagnostics.length;
  setStatus(`${kind} · ${size} in ${header.render_ms.toFixed(1)} ms` + (header.final ? "" : " (refining…)")
    + (errors > 0 ? ` · ${errors} error${errors > 1 ? "s" : ""}: showing the last scene that compiled` : ""));
}

// ---- camera controls: drag to orbit, shift-drag or right-drag to pan, wheel or pinch to zoom --------
function orbit(dx, dy) {
  const c = viewer.camera;
  const up = unit(c.up);
  let offset = sub(c.eye, c.target);
  offset = rotate(offset, up, -dx * 0.008);
  const right = unit(cross(up, offset));
  const turned = rotate(offset, right, dy * 0.008);
  // Stop short of the poles, where the view would flip.
  if (Math.abs(dot(unit(turned), up)) < 0.995) {
    offset = turned;
  }
  c.eye = add(c.target, offset);
  cameraMoved();
}

function pan(dx, dy) {
  const c = viewer.camera;
  const forward = unit(sub(c.target, c.eye));
  const right = unit(cross(forward, c.up));
  const upward = cross(right, forward);
  const step = norm(sub(c.eye, c.target)) / (c.focal * canvas.height * 0.5);
  const move = add(scale(right, -dx * step), scale(upward, dy * step));
  c.eye = add(c.eye, move);
  c.target = add(c.target, move);
  cameraMoved();
}

function zoom(factor) {
  const c = viewer.camera;
  c.eye = add(c.target, scale(sub(c.eye, c.target), factor));
  cameraMoved();
}

// The equivalent commands are rewritten once the camera pauses: rewriting them at every move of a drag
// kept the browser a third busier (0.6 of a core instead of 0.4 in headless Chromium, orbiting a bake).
let commandsTimer = 0;
function cameraMoved() {
  $("camera").value = "free";
  clearTimeout(commandsTimer);
  commandsTimer = setTimeout(updateCommands, 150);
  requestFrame();
}

const pointers = new Map();
let pinchDistance = 0;
canvas.addEventListener("contextmenu", (e) => e.preventDefault());
canvas.addEventListener("pointerdown", (e) => {
  canvas.setPointerCapture(e.pointerId);
  pointers.set(e.pointerId, { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 });
  canvas.classList.add("dragging");
  if (pointers.size === 2) {
    const [a, b] = [...pointers.values()];
    pinchDistance = Math.hypot(a.x - b.x, a.y - b.y);
  }
});
canvas.addEventListener("pointermove", (e) => {
  const p = pointers.get(e.pointerId);
  if (!p || !viewer.camera) {
    return;
  }
  const dx = e.clientX - p.x, dy = e.clientY - p.y;
  p.x = e.clientX;
  p.y = e.clientY;
  if (pointers.size === 2) {
    const [a, b] = [...pointers.values()];
    const distance = Math.hypot(a.x - b.x, a.y - b.y);
    if (pinchDistance > 0 && distance > 0) {
      zoom(pinchDistance / distance);
    }
    pinchDistance = distance;
  } else if (p.pan) {
    pan(dx, dy);
  } else {
    orbit(dx, dy);
  }
});
const release = (e) => {
  pointers.delete(e.pointerId);
  if (pointers.size === 0) {
    canvas.classList.remove("dragging");
  }
};
canvas.addEventListener("pointerup", release);
canvas.addEventListener("pointercancel", release);
canvas.addEventListener("wheel", (e) => {
  e.preventDefault();
  if (viewer.camera) {
    zoom(Math.exp(e.deltaY * 0.001));
  }
}, { passive: false });

$("layer").addEventListener("change", (e) => {
  viewer.layer = e.target.value;
  requestFrame();
});
$("camera").addEventListener("change", (e) => {
  const i = Number(e.target.value);
  if (viewer.scene && Number.isInteger(i) && viewer.scene.cameras[i]) {
    viewer.camera = { ...viewer.scene.cameras[i] };
    updateCommands();
    requestFrame();
  }
});

// ---- a training run: progress, a chart of PSNR, pause -----------------------------------------------
function showTraining() {
  const { history, paused } = viewer.training;
  $("pause").textContent = paused ? "resume" : "pause";
  const last = history[history.length - 1];
  if (last) {
    const eta = Number.isFinite(last.eta_seconds) ? `${Math.round(last.eta_seconds)} s to go` : "";
    const val = last.val_psnr != null ? ` · val ${last.val_psnr.toFixed(2)} dB` : "";
    $("train-status").textContent = `step ${last.step}/${last.steps} · loss ${last.loss.toPrecision(4)} · ` +
      `PSNR ${last.psnr.toFixed(2)} dB${val} · ${last.steps_per_s.toFixed(1)} steps/s · ${paused ? "paused" : eta}`;
  }
  drawChart(history);
}

function drawChart(history) {
  const chart = $("chart");
  const g = chart.getContext("2d");
  const w = chart.width, h = chart.height, pad = 28;
  g.clearRect(0, 0, w, h);
  const points = history.filter((r) => Number.isFinite(r.psnr));
  if (points.length === 0) {
    return;
  }
  const values = points.flatMap((r) => (r.val_psnr != null ? [r.psnr, r.val_psnr] : [r.psnr]));
  const lo = Math.floor(Math.min(...values)), hi = Math.ceil(Math.max(...values)) + 1;
  const steps = points[0].steps;
  const x = (step) => pad + ((w - 2 * pad) * step) / steps;
  const y = (v) => h - pad + ((2 * pad - h) * (v - lo)) / (hi - lo);
  g.fillStyle = "#8a92a0";
  g.font = "11px sans-serif";
  g.fillText(`${hi} dB`, 2, pad - 4);
  g.fillText(`${lo} dB`, 2, h - pad + 12);
  g.fillText(`step ${steps}`, w - pad - 40, h - 6);
  g.strokeStyle = "#6cb6ff";
  g.beginPath();
  points.forEach((r, i) => (i === 0 ? g.moveTo(x(r.step), y(r.psnr)) : g.lineTo(x(r.step), y(r.psnr))));
  g.stroke();
  g.fillStyle = "#ffb86c";
  for (const r of points.filter((r) => r.val_psnr != null)) {
    g.beginPath();
    g.arc(x(r.step), y(r.val_psnr), 3, 0, 2 * Math.PI);
    g.fill();
  }
  g.fillText("train PSNR", pad + 4, 12);
  g.fillStyle = "#ffb86c";
  g.fillText("● val PSNR", pad + 80, 12);
}

$("pause").addEventListener("click", () => {
  viewer.training.paused = !viewer.training.paused;
  send({ type: "pause", id: viewer.nextId++, paused: viewer.training.paused });
  showTraining();
});

// ---- the editor -----------------------------------------------------------------------------------
function escapeHtml(text) {
  return text.replace(/&/g, "&amp;").replace(/</g, "&lt;").replace(/>/g, "&gt;");
}

// The offset in `text` of 1-based `line` and `column` (in code points).
function offsetOf(text, line, column) {
  let offset = 0;
  for (let l = 1; l < line; l++) {
    const next = text.indexOf("\n", offset);
    if (next < 0) {
      return text.length;
    }
    offset = next + 1;
  }
  let rest = column - 1;
  while (rest > 0 && offset < text.length && text[offset] !== "\n") {
    offset += text.codePointAt(offset) > 0xffff ? 2 : 1;
    rest -= 1;
  }
  return offset;
}

// Redraws the line numbers and the marks under each diagnostic's span.
function refreshEditor() {
  const text = editor.value;
  const badLines = new Set(viewer.diagnostics.filter((d) => d.at).map((d) => d.at.line));
  const lines = text.split("\n").length;
  let gutter = "";
  for (let i = 1; i <= lines; i++) {
    gutter += badLines.has(i) ? `<span class="bad">${i}</span>\n` : `${i}\n`;
  }
  $("gutter").innerHTML = gutter;
  const spans = viewer.diagnostics
    .filter((d) => d.at)
    .map((d) => ({
      start: offsetOf(text, d.at.line, d.at.column),
      end: offsetOf(text, d.at.end_line, d.at.end_column),
      message: d.message,
    }))
    .sort((a, b) => a.start - b.start);
  let html = "", at = 0;
  for (const s of spans) {
    if (s.start < at) {
      continue;
    }
    html += escapeHtml(text.slice(at, s.start));
    const marked = text.slice(s.start, Math.max(s.end, s.start));
    const title = escapeHtml(s.message).replace(/"/g, "&quot;");
    html += marked.length > 0
      ? `<mark title="${title}">${escapeHtml(marked)}</mark>`
      : `<mark class="point" title="${title}"></mark>`;
    at = Math.max(s.end, s.start);
  }
  html += escapeHtml(text.slice(at)) + "\n";
  $("highlight").innerHTML = html;
  syncScroll();
}

function syncScroll() {
  $("highlight").scrollTop = editor.scrollTop;
  $("highlight").scrollLeft = editor.scrollLeft;
  $("gutter").scrollTop = editor.scrollTop;
}

function showDiagnostics(items) {
  const list = $("diagnostics");
  list.replaceChildren(...items.map((d) => {
    const li = document.createElement("li");
    const place = d.at ? `${viewer.name}:${d.at.line}:${d.at.column}: ` : "";
    li.textContent = `${place}error: ${d.message}`;
    if (d.hint) {
      const hint = document.createElement("div");
      hint.className = "hint";
      hint.textContent = `hint: ${d.hint}`;
      li.append(hint);
    }
    if (d.at) {
      li.addEventListener("click", () => {
        const offset = offsetOf(editor.value, d.at.line, d.at.column);
        editor.focus();
        editor.setSelectionRange(offset, offsetOf(editor.value, d.at.end_line, d.at.end_column));
      });
    }
    return li;
  }));
  if (items.length > 0) {
    setStatus(`${items.length} error${items.length > 1 ? "s" : ""}: the last scene that compiled stays on screen`);
  }
}

// Sends the editor's text as a new version of the script.
function sourceChanged() {
  refreshEditor();
  const id = viewer.nextId++;
  viewer.sourceSent.set(id, performance.now());
  viewer.lastSourceId = id;
  send({ type: "source", id, text: editor.value });
  updateCommands();
}
editor.addEventListener("input", sourceChanged);
editor.addEventListener("scroll", syncScroll);
editor.addEventListener("keydown", (e) => {
  if (e.key === "Tab") {
    e.preventDefault();
    editor.setRangeText("    ", editor.selectionStart, editor.selectionEnd, "end");
    sourceChanged();
  }
});

// ---- sliders for the script's consts (only those written as a plain number: a slider rewrites it) --
const number = String.raw`-?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?`;
const constPattern = (name) => new RegExp(String.raw`^(\s*const\s+${name}\s*=\s*)(${number})(?=\s*(?://.*)?$)`, "m");

// The range a slider for `value` spans.
const sliderRange = (value) => (value > 0 ? [0, 2 * value] : value < 0 ? [2 * value, 0] : [-1, 1]);

// One slider per movable const. A script whose consts keep their names keeps its sliders (one being
// dragged is left alone), so the edits a slider makes do not rebuild it under the pointer.
function buildSliders(consts) {
  const box = $("sliders");
  const movable = consts.filter(({ name }) => constPattern(name).test(editor.value));
  const key = movable.map((c) => c.name).join(",");
  if (box.dataset.names === key) {
    for (const { name, value } of movable) {
      const slider = document.getElementById(`const-${name}`);
      if (slider !== document.activeElement) {
        const [lo, hi] = sliderRange(value);
        slider.min = Math.min(Number(slider.min), lo);
        slider.max = Math.max(Number(slider.max), hi);
        slider.value = value;
        slider.nextElementSibling.textContent = String(value);
      }
    }
    return;
  }
  box.dataset.names = key;
  box.replaceChildren();
  for (const { name, value } of movable) {
    const magnitude = Math.abs(value) > 0 ? Math.abs(value) : 1;
    const [lo, hi] = sliderRange(value);
    const label = document.createElement("label");
    label.textContent = name;
    const slider = Object.assign(document.createElement("input"), {
      type: "range", min: lo, max: hi, step: magnitude / 100, value, id: `const-${name}`,
    });
    const shown = document.createElement("output");
    shown.textContent = String(value);
    slider.addEventListener("input", () => {
      const v = Number(Number(slider.value).toPrecision(4));
      shown.textContent = String(v);
      editor.value = editor.value.replace(constPattern(name), (_, head) => head + String(v));
      sourceChanged();
    });
    box.append(label, slider, shown);
  }
}

// ---- exports ----------------------------------------------------------------------------------------
const fmt = (v) => `[${v.map((x) => Number(x.toFixed(4))).join(", ")}]`;

function lookAt() {
  const c = viewer.camera;
  return `look_at(eye: ${fmt(c.eye)}, at: ${fmt(c.target)}, up: ${fmt(c.up)}, focal: ${Number(c.focal.toFixed(4))})`;
}

function orbitPath() {
  const c = viewer.camera;
  const offset = sub(c.eye, c.target);
  const up = unit(c.up);
  const radius = norm(offset);
  const elevation = (Math.asin(Math.max(-1, Math.min(1, dot(offset, up) / radius))) * 180) / Math.PI;
  const axis = up[2] !== 0 ? "z" : "y";
  return `orbit(radius: ${radius.toFixed(3)}, elevation: ${elevation.toFixed(1)}, frames: 60, up: ${axis}, focal: ${Number(c.focal.toFixed(4))})`;
}

function updateCommands() {
  if (!viewer.scene || !viewer.camera) {
    return;
  }
  const name = viewer.name;
  const size = canvas.width;
  // The same settings as the export buttons (an orbit of 60 frames, a 160³ mesh).
  if (viewer.bake) {
    const checkpoint = viewer.bake.checkpoint;
    $("command-text").textContent = [
      `# this view as a PNG (in views/)`,
      `nerfjit render ${name} --path '${lookAt()}' --size ${size} --out views`,
      `# an orbit video`,
      `nerfjit render ${name} --path '${orbitPath()}' --size 256 --out orbit.mp4`,
      `# a mesh of the field the splats were baked from`,
      `nerfjit mesh ${checkpoint} --function density --level 10 --bounds 1.5 --res 160 --out mesh.ply`,
      `# the exported checkpoint is that field's (${checkpoint}): the script is read-only`,
    ].join("\n");
    return;
  }
  const lines = viewer.scene.kind === "surface"
    ? [
      `# this view as a PNG`,
      `nerfjit run ${name} --set 'render.camera=${lookAt()}' --set render.size=${size} --set 'render.out="view.png"'`,
      `# an orbit video`,
      `nerfjit run ${name} --set 'render.camera=${orbitPath()}' --set render.size=256 --set 'render.out="orbit.mp4"'`,
      `# a mesh`,
      `nerfjit mesh ${name} --bounds 4 --res 160 --out mesh.ply`,
    ]
    : [
      `# this view as a PNG (in views/)`,
      `nerfjit render ${name} --path '${lookAt()}' --size ${size} --out views`,
      `# an orbit video`,
      `nerfjit render ${name} --path '${orbitPath()}' --size 128 --out orbit.mp4`,
      `# a mesh of the density`,
      `nerfjit mesh ${name} --function density --level 10 --bounds 1.5 --res 160 --out mesh.ply`,
    ];
  const base = name.replace(/\.sdf$/, "");
  lines.push(viewer.training
    ? `# a checkpoint: the run itself writes ${base}.ckpt.safetensors (every checkpoint_every steps, at the end\n# and on Ctrl-C); the exported one holds the params shown and the script, without Adam's moments`
    : `# a checkpoint: the params shown with the script as edited, for render, mesh, eval-views and view\n# (written by the page; a train block's run writes ${base}.ckpt.safetensors itself)`);
  $("command-text").textContent = lines.join("\n");
}

function download(blob, filename) {
  const link = Object.assign(document.createElement("a"), { href: URL.createObjectURL(blob), download: filename });
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 1000);
}

const baseName = () => viewer.name.replace(/^.*\//, "").replace(/\.(sdf|bake)$/, "");
$("export-png").addEventListener("click", () => {
  if (viewer.lastFinal) {
    download(viewer.lastFinal.blob, `${baseName()}.png`);
  }
});
for (const what of ["video", "mesh", "checkpoint"]) {
  $(`export-${what}`).addEventListener("click", () => {
    if (viewer.camera) {
      send({ type: "export", id: viewer.nextId++, what, ...viewer.camera });
      setStatus(`exporting the ${what}… (the view pauses until it is done)`);
    }
  });
}
$("save-script").addEventListener("click", () => {
  download(new Blob([editor.value], { type: "text/plain" }), `${baseName()}.sdf`);
});

connect();
