// The live viewer in a real browser: headless Chromium (Debian's `chromium`) opens `nerfjit view
// examples/showcase.sdf`, checks the canvas shows the scene as the CLI renders it from the same camera,
// orbits with the mouse, types edits into the script (a const, then a mistake) and sees new frames and
// the diagnostic, and saves screenshots. Prints the measured latencies (medians) as JSON.
//
// usage: node tests/browser/viewer.mjs NERFJIT_BINARY OUT_DIR   (after `npm ci` in tests/browser)

import { execFileSync } from "node:child_process";
import { readFileSync, mkdirSync } from "node:fs";
import { join } from "node:path";
import { launchChromium, startViewer } from "./launch.mjs";

const [binary, outDir] = process.argv.slice(2);
if (!binary || !outDir) {
  console.error("usage: node viewer.mjs NERFJIT_BINARY OUT_DIR");
  process.exit(2);
}
mkdirSync(outDir, { recursive: true });

function fail(message) {
  throw new Error(message);
}

function median(values) {
  const sorted = [...values].sort((a, b) => a - b);
  return sorted.length === 0 ? NaN : sorted[Math.floor(sorted.length / 2)];
}

// The reference: the CLI's render of the script's first camera at the canvas size.
execFileSync(binary, [
  "run", "examples/showcase.sdf",
  "--set", "render.camera=orbit(radius: 8.0, elevation: 35, frames: 1, up: y, focal: 1.2)",
  "--set", "render.size=512",
  "--set", 'render.out="reference.png"',
  "--out", outDir,
], { stdio: ["ignore", "ignore", "inherit"] });
const reference = readFileSync(join(outDir, "reference.png")).toString("base64");

const { server, url } = await startViewer(binary, ["examples/showcase.sdf"]);
const browser = await launchChromium();
const results = {};
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  page.on("pageerror", (e) => fail(`error in the page: ${e.message}`));
  await page.goto(url);
  const stats = () => page.evaluate(() => ({ ...window.nerfjitViewer.stats, lastSourceId: window.nerfjitViewer.lastSourceId }));
  const waitFor = (predicate, arg) => page.waitForFunction(predicate, arg, { timeout: 60_000 });

  // 1. The first full-size frame matches the CLI's render of the same camera.
  await waitFor(() => window.nerfjitViewer.stats.finalFrames >= 1);
  const compared = await page.evaluate(async (png) => {
    const canvas = document.getElementById("canvas");
    const shown = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height).data;
    const image = new Image();
    image.src = `data:image/png;base64,${png}`;
    await image.decode();
    const other = new OffscreenCanvas(image.width, image.height).getContext("2d");
    other.drawImage(image, 0, 0);
    const expected = other.getImageData(0, 0, image.width, image.height).data;
    let difference = 0, sum = 0, squares = 0;
    for (let i = 0; i < shown.length; i += 4) {
      for (let c = 0; c < 3; c++) {
        difference += Math.abs(shown[i + c] - expected[i + c]);
        sum += shown[i + c];
        squares += shown[i + c] ** 2;
      }
    }
    const n = (shown.length / 4) * 3;
    return { size: [image.width, image.height], difference: difference / n, spread: Math.sqrt(squares / n - (sum / n) ** 2) };
  }, reference);
  if (compared.size[0] !== 512 || compared.size[1] !== 512) fail(`reference size ${compared.size}`);
  if (!(compared.spread > 8)) fail(`the canvas looks blank (spread ${compared.spread})`);
  if (!(compared.difference < 2)) fail(`the canvas differs from the CLI render by ${compared.difference} per channel`);
  results.difference_from_cli = compared.difference;

  // 2. Orbiting with the mouse: each move gets a frame; camera move → first frame on screen.
  const box = await page.locator("#canvas").boundingBox();
  await page.mouse.move(box.x + 256, box.y + 256);
  await page.mouse.down();
  for (let i = 1; i <= 30; i++) {
    const before = (await stats()).cameraToFrame.length;
    await page.mouse.move(box.x + 256 + 6 * i, box.y + 256 + (i % 5));
    await waitFor((n) => window.nerfjitViewer.stats.cameraToFrame.length > n, before);
  }
  await page.mouse.up();
  const orbit = (await stats()).cameraToFrame;
  results.camera_to_frame_ms = { median: median(orbit), count: orbit.length };
  await waitFor(() => {
    const v = window.nerfjitViewer;
    return v.lastFinal && v.lastFinal.cameraId === v.lastCameraId;
  });
  await page.screenshot({ path: join(outDir, "viewer.png") });

  // 3. Typing into the editor: each edit of the const k is re-compiled and re-rendered.
  const selectInEditor = (text, from, length) => page.evaluate(([text, from, length]) => {
    const editor = document.getElementById("source");
    const at = editor.value.indexOf(text);
    if (at < 0) throw new Error(`no ${text} in the editor`);
    editor.focus();
    editor.setSelectionRange(at + from, at + from + length);
  }, [text, from, length]);
  const editsBefore = (await stats()).editToFrame.length;
  await selectInEditor("const k = 0.25", 10, 4);
  await page.keyboard.type("0.6");
  for (const digit of "123456789") {
    await selectInEditor("const k = 0.6", 13, 1);
    await page.keyboard.type(digit);
    const id = (await stats()).lastSourceId;
    await waitFor((id) => window.nerfjitViewer.stats.editToFrame.length > 0 && !window.nerfjitViewer.sourceSent.has(id), id);
  }
  const edits = (await stats()).editToFrame.slice(editsBefore);
  results.edit_to_frame_ms = { median: median(edits), count: edits.length };
  const slider = Number(await page.inputValue("#const-k"));
  if (Math.abs(slider - 0.69) > 1e-6) fail(`the slider does not follow the edited const: ${slider}`);
  // The slider rewrites the const in the script, which is re-rendered.
  await page.evaluate(() => {
    const s = document.getElementById("const-k");
    s.value = "0.3";
    s.dispatchEvent(new Event("input"));
  });
  if (!(await page.inputValue("#source")).includes("const k = 0.3 ")) fail("the slider did not rewrite the const");
  const moved = (await stats()).lastSourceId;
  await waitFor((id) => !window.nerfjitViewer.sourceSent.has(id), moved);

  // 4. A mistake: the diagnostic appears at its line and column, marked in the editor.
  await selectInEditor("sphere(p - [0, 0.95", 0, 6);
  await page.keyboard.type("spere");
  // Typed a key at a time, the script passes through other mistakes ('s', 'sp', ...) on the way.
  await waitFor(() => [...document.querySelectorAll("#diagnostics li")].some((li) => li.textContent.includes("'spere'")));
  const diagnostic = await page.textContent("#diagnostics li");
  if (!/showcase\.sdf:\d+:\d+: error: .*spere/.test(diagnostic)) fail(`unexpected diagnostic: ${diagnostic}`);
  if ((await page.locator("#highlight mark").count()) < 1) fail("the mistake is not marked in the editor");
  results.diagnostic = diagnostic;
  await page.screenshot({ path: join(outDir, "viewer-diagnostic.png") });
  // Fixing it clears the diagnostic.
  await selectInEditor("spere(p - [0, 0.95", 0, 5);
  await page.keyboard.type("sphere");
  const fixed = (await stats()).lastSourceId;
  await waitFor((id) => !window.nerfjitViewer.sourceSent.has(id) && document.querySelectorAll("#diagnostics li").length === 0, fixed);
} finally {
  await browser.close();
  server.kill();
}

for (const [name, target] of [["camera_to_frame_ms", 50], ["edit_to_frame_ms", 150]]) {
  results[name].target = target;
  // Far beyond the target means something is broken, not merely slow.
  if (!(results[name].median < 20 * target)) fail(`${name}: median ${results[name].median} ms`);
}
console.log(JSON.stringify(results));
