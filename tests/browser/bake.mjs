// A bake in the live viewer, in a real browser: headless Chromium (Debian's `chromium`) opens `nerfjit view
// BAKE`, checks the page shows the splats (not a blank canvas) with the checkpoint's script read-only, sets the
// canvas to SIZE×SIZE, then orbits the camera with the mouse for SECONDS without pause (the pointer moved at
// every display refresh, around a circle) and counts the frames the page shows: the display refreshes (animation
// frames) at which a new frame had been drawn on the canvas since the refresh before. Prints frames a second,
// camera request → frame on screen, the server's render and encode times (medians) and the cores the server and
// the browser kept busy as JSON, with the machine's load average; fails below --min-fps, or when frames fall
// behind the camera (they queue).
//
// usage: node tests/browser/bake.mjs NERFJIT_BINARY BAKE OUT_DIR [--size 800] [--seconds 5] [--min-fps 2]
//        (after `npm ci` in tests/browser)

import { mkdirSync, readdirSync, readFileSync } from "node:fs";
import { join } from "node:path";
import { parseArgs } from "node:util";
import { launchChromium, startViewer } from "./launch.mjs";

const { values: options, positionals } = parseArgs({
  allowPositionals: true,
  options: {
    size: { type: "string", default: "800" },
    seconds: { type: "string", default: "5" },
    "min-fps": { type: "string", default: "2" },
  },
});
const [binary, bake, outDir] = positionals;
if (!binary || !bake || !outDir) {
  console.error("usage: node bake.mjs NERFJIT_BINARY BAKE OUT_DIR [--size 800] [--seconds 5] [--min-fps 2]");
  process.exit(2);
}
const size = Number(options.size), seconds = Number(options.seconds), minFps = Number(options["min-fps"]);
mkdirSync(outDir, { recursive: true });

function fail(message) {
  throw new Error(message);
}

function quantile(values, q) {
  const sorted = [...values].sort((a, b) => a - b);
  return sorted.length === 0 ? NaN : sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
}

const round = (x) => Math.round(10 * x) / 10;
const load = () => readFileSync("/proc/loadavg", "utf8").split(" ").slice(0, 3).map(Number);

// The CPU seconds (user and system, at Linux's 100 ticks a second) used so far by the server (and any process
// under it) and by the browser (every other process under this one, this one left out).
function cpuSeconds() {
  const processes = new Map();
  for (const entry of readdirSync("/proc").filter((name) => /^\d+$/.test(name))) {
    try {
      const fields = readFileSync(`/proc/${entry}/stat`, "utf8").replace(/^.*\) /, "").split(" ");
      processes.set(Number(entry), { parent: Number(fields[1]), ticks: Number(fields[11]) + Number(fields[12]) });
    } catch {
      // The process ended while the folder was read.
    }
  }
  const under = (pid, root) => pid === root || (processes.has(pid) && pid > 1 && under(processes.get(pid).parent, root));
  const used = { server: 0, browser: 0 };
  for (const [pid, { ticks }] of processes) {
    if (under(pid, server.pid)) {
      used.server += ticks / 100;
    } else if (pid !== process.pid && under(pid, process.pid)) {
      used.browser += ticks / 100;
    }
  }
  return used;
}

const { server, url } = await startViewer(binary, [bake]);
const browser = await launchChromium();
const results = { bake, size: [size, size], seconds, load_average_before: load() };
try {
  const page = await browser.newPage({ viewport: { width: size + 900, height: size + 300 } });
  page.on("pageerror", (e) => fail(`error in the page: ${e.message}`));
  await page.goto(url);
  const waitFor = (predicate, arg) => page.waitForFunction(predicate, arg, { timeout: 120_000 });
  await waitFor(() => window.nerfjitViewer.stats.finalFrames >= 1);

  // The page shows a bake: the splats count, and the script is read-only.
  const name = await page.textContent("#name");
  if (!/splats baked from/.test(name)) fail(`the page does not say it shows a bake: ${name}`);
  if (!(await page.evaluate(() => document.getElementById("source").readOnly))) fail("the script is editable");
  results.page = name;

  // The canvas at SIZE×SIZE; a small drag asks for a frame of that size.
  await page.evaluate((size) => {
    const canvas = document.getElementById("canvas");
    canvas.width = canvas.height = size;
    canvas.style.width = canvas.style.height = `${size}px`;
  }, size);
  const box = await page.locator("#canvas").boundingBox();
  const [cx, cy] = [box.x + box.width / 2, box.y + box.height / 2];
  await page.mouse.move(cx, cy);
  await page.mouse.down();
  await page.mouse.move(cx + 2, cy);
  await page.mouse.up();
  await waitFor(() => {
    const v = window.nerfjitViewer;
    return v.lastFinal && v.lastFinal.cameraId === v.lastCameraId;
  });
  const first = await page.evaluate(async () => {
    const v = window.nerfjitViewer;
    const bitmap = await createImageBitmap(v.lastFinal.blob);
    const canvas = document.getElementById("canvas");
    const shown = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height).data;
    let sum = 0, squares = 0;
    for (let i = 0; i < shown.length; i += 4) {
      for (let c = 0; c < 3; c++) {
        sum += shown[i + c];
        squares += shown[i + c] ** 2;
      }
    }
    const n = (shown.length / 4) * 3;
    return { frame: [bitmap.width, bitmap.height], spread: Math.sqrt(squares / n - (sum / n) ** 2) };
  });
  if (first.frame[0] !== size || first.frame[1] !== size) fail(`a frame of ${first.frame}, not ${size}²`);
  if (!(first.spread > 8)) fail(`the canvas looks blank (spread ${first.spread})`);
  results.spread = round(first.spread);

  // Count, in the page, the display refreshes at which a new frame had been drawn since the last one.
  await page.evaluate(() => {
    const v = window.nerfjitViewer;
    v.shown = { refreshes: 0, withNewFrame: 0 };
    let drawn = v.stats.frames;
    const tick = () => {
      v.shown.refreshes += 1;
      if (v.stats.frames !== drawn) {
        v.shown.withNewFrame += 1;
        drawn = v.stats.frames;
      }
      requestAnimationFrame(tick);
    };
    requestAnimationFrame(tick);
  });
  const snapshot = () => page.evaluate(() => {
    const v = window.nerfjitViewer;
    return {
      now: performance.now(), drawn: v.stats.frames, finals: v.stats.finalFrames, shown: { ...v.shown },
      lastCameraId: v.lastCameraId, latencies: v.stats.cameraToFrame.length, renders: v.stats.renderMs.length,
    };
  });

  // Orbit without pause: the mouse button goes down on the canvas, then the pointer moves at every display
  // refresh around a circle (dragging orbits both ways). The moves are dispatched in the page: moving the
  // mouse from the test driver waits for a round trip each (about 35 ms under load), too slow to drag at
  // the display's rate.
  await page.evaluate(() => {
    document.getElementById("canvas").addEventListener("pointerdown", (e) => { window.draggingPointer = e.pointerId; });
  });
  await page.mouse.move(cx + 120, cy);
  await page.mouse.down();
  const cpuBefore = cpuSeconds();
  const before = await snapshot();
  await page.evaluate(([cx, cy, seconds]) => new Promise((resolve) => {
    const canvas = document.getElementById("canvas");
    const start = performance.now();
    let step = 0;
    const move = () => {
      if (performance.now() - start >= 1000 * seconds) {
        resolve();
        return;
      }
      step += 1;
      const angle = step * 0.05;
      canvas.dispatchEvent(new PointerEvent("pointermove", {
        pointerId: window.draggingPointer, clientX: cx + 120 * Math.cos(angle), clientY: cy + 120 * Math.sin(angle),
        bubbles: true,
      }));
      requestAnimationFrame(move);
    };
    requestAnimationFrame(move);
  }), [cx, cy, seconds]);
  const after = await snapshot();
  const cpuAfter = cpuSeconds();
  await page.mouse.up();
  results.load_average_after = load();
  const stats = await page.evaluate(() => window.nerfjitViewer.stats);
  const elapsed = (after.now - before.now) / 1000;
  const latencies = stats.cameraToFrame.slice(before.latencies, after.latencies);
  const renders = stats.renderMs.slice(before.renders, after.renders);
  const encodes = stats.encodeMs.slice(before.renders, after.renders);
  results.orbit = {
    seconds: round(elapsed),
    camera_requests: after.lastCameraId - before.lastCameraId,
    frames_drawn: after.drawn - before.drawn,
    final_frames: after.finals - before.finals,
    display_refreshes: after.shown.refreshes - before.shown.refreshes,
    frames_shown: after.shown.withNewFrame - before.shown.withNewFrame,
  };
  results.fps_shown = round(results.orbit.frames_shown / elapsed);
  results.camera_to_frame_ms = { median: round(quantile(latencies, 0.5)), p90: round(quantile(latencies, 0.9)), count: latencies.length };
  results.server_ms = { render_median: round(quantile(renders, 0.5)), encode_median: round(quantile(encodes, 0.5)) };
  // Cores busy on average during the orbit (of the machine's two).
  results.cores_used = {
    server: round((cpuAfter.server - cpuBefore.server) / elapsed),
    browser: round((cpuAfter.browser - cpuBefore.browser) / elapsed),
  };

  // At rest, the last camera's frame comes as PNG.
  await waitFor(() => {
    const v = window.nerfjitViewer;
    return v.lastFinal && v.lastFinal.cameraId === v.lastCameraId;
  });
  await page.screenshot({ path: join(outDir, "viewer-bake.png") });
} finally {
  await browser.close();
  server.kill();
}

console.log(JSON.stringify(results));
if (!(results.fps_shown >= minFps)) fail(`${results.fps_shown} frames a second shown, fewer than ${minFps}`);
// Frames do not queue (the newest camera request wins): a frame answers a request made at most about one
// frame earlier, where a queue of the 60 requests a second would fall seconds behind.
const lagLimit = 3 * results.server_ms.render_median + 100;
if (!(results.camera_to_frame_ms.median <= lagLimit)) {
  fail(`camera → frame ${results.camera_to_frame_ms.median} ms, more than ${lagLimit} ms: frames queue`);
}
