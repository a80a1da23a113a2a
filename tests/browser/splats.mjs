// Issue 91: the 3D Gaussian splatting .ply that `nerfjit export BAKE --format splat-ply` writes, opened in a
// real splat renderer: headless Chromium (Debian's `chromium`, driven by playwright-core) draws it with the
// three.js splat renderer Spark (@sparkjsdev/spark, from npm) from a training camera, and its picture is
// compared with nerfjit's own render of the bake from the same camera.
//
// usage: node tests/browser/splats.mjs NERFJIT BAKE TRANSFORMS_JSON OUT_DIR
//            [--size S] [--frame I] [--min-psnr DB] [--fps SECONDS]        (after `npm ci` in tests/browser)
//
//   NERFJIT          the nerfjit binary
//   BAKE             a .bake of a field trained on TRANSFORMS_JSON
//   TRANSFORMS_JSON  its cameras, in the Blender (NeRF-synthetic) layout: `camera_angle_x` and frames'
//                    `transform_matrix` (camera to world, OpenGL axes: looking down −z, y up, x right, as
//                    three.js cameras are; the splats are in the same scene units and axes)
//   --size S         the square pictures' side in pixels (default 200)
//   --frame I        the frame of TRANSFORMS_JSON to look from (default 0)
//   --min-psnr DB    fail if the PSNR between the browser's picture and nerfjit's is below this (default 35)
//   --fps SECONDS    then orbit the camera about the z axis (the Blender scenes' up) for this long, drawing a
//                    frame per requestAnimationFrame, and report the frames per second the page showed
//                    (default 0: not measured)
//
// Writes OUT_DIR/scene.ply (the export), OUT_DIR/camera.json (the one frame) and OUT_DIR/nerfjit/ (nerfjit's
// render from it over white), OUT_DIR/browser.png (the canvas as shown), OUT_DIR/compare.png (browser |
// nerfjit | their difference × 4, white where equal), and prints a JSON line: the PSNR, the viewer and its
// version, the splat count, the times to load and to the first sorted frame, and the fps if measured.
// Where the frame's training image is there at S×S, both renders are also scored against it (alpha over
// white): the target is the browser's score within 1 dB of nerfjit's, which fails the run too.
//
// Exits non-zero if the PSNR is under --min-psnr, the browser's score is more than 1 dB under nerfjit's,
// the page shows an error, the viewer holds fewer splats than the file or its picture is blank.
//
// Spark is set up to draw as nerfjit does (runtime/src/splats/raster.rs): the 3DGS EWA projection with
// 0.3 px² added to the 2D covariance's diagonal and no opacity compensation (preBlurAmount 0.3, blurAmount
// 0: Spark's defaults are the reverse, the "antialiased" variant), splats sorted by distance from the
// camera (sortRadial), alphas under 1/255 skipped, extended (float32 center, half-float color and scale)
// splat encoding instead of the packed 8/16-bit one, no LoD. Degree-0 spherical harmonics only: the
// .ply has no others. The canvas is S×S at devicePixelRatio 1 over white, without antialiasing. No color
// space conversion happens: Spark writes the .ply's colors (0.5 + C0 · f_dc) as they are when three.js's
// output color space is sRGB (its default), and those are the display values nerfjit writes to its PNGs.
// No SharedArrayBuffer is needed, so the page is served without cross-origin isolation headers.

import { execFileSync } from "node:child_process";
import { createServer } from "node:http";
import { createReadStream, existsSync, mkdirSync, readFileSync, readdirSync, rmSync, statSync, writeFileSync } from "node:fs";
import { dirname, join, resolve, sep } from "node:path";
import { fileURLToPath } from "node:url";
import { chromium } from "playwright-core";

const usage = "usage: node splats.mjs NERFJIT BAKE TRANSFORMS_JSON OUT_DIR [--size S] [--frame I] [--min-psnr DB] [--fps SECONDS]";
const options = { size: 200, frame: 0, "min-psnr": 35, fps: 0 };
const positional = [];
for (let i = 2; i < process.argv.length; i++) {
  const arg = process.argv[i];
  if (!arg.startsWith("--")) {
    positional.push(arg);
    continue;
  }
  const name = arg.slice(2);
  const value = Number(process.argv[++i]);
  if (!(name in options) || !Number.isFinite(value)) {
    console.error(usage);
    process.exit(2);
  }
  options[name] = value;
}
if (positional.length !== 4) {
  console.error(usage);
  process.exit(2);
}
const [binary, bake, transformsPath, outDir] = positional.map((p) => resolve(p));
const size = options.size;
if (!(Number.isInteger(size) && size >= 16 && size <= 2048)) {
  console.error(`--size ${size}: a whole number from 16 to 2048`);
  process.exit(2);
}
mkdirSync(outDir, { recursive: true });

const modules = join(dirname(fileURLToPath(import.meta.url)), "node_modules");
const versionOf = (name) => JSON.parse(readFileSync(join(modules, name, "package.json"), "utf8")).version;
const result = { viewer: `@sparkjsdev/spark@${versionOf("@sparkjsdev/spark")}`, three: versionOf("three"), size };

// 1. The bake as the 3D Gaussian splatting .ply.
const ply = join(outDir, "scene.ply");
execFileSync(binary, ["export", bake, "--format", "splat-ply", "--out", ply], { stdio: ["ignore", "ignore", "inherit"] });
const plyHeader = readFileSync(ply).subarray(0, 4096).toString("latin1");
result.splats = Number(plyHeader.match(/element vertex (\d+)/)?.[1]);
if (!(result.splats > 0)) throw new Error(`no splats in ${ply}`);

// 2. A training camera, and nerfjit's render of the bake from it over white.
const transforms = JSON.parse(readFileSync(transformsPath, "utf8"));
const frame = transforms.frames?.[options.frame];
if (!frame || !(transforms.camera_angle_x > 0)) throw new Error(`${transformsPath}: no camera_angle_x or no frame ${options.frame}`);
const cameraFile = join(outDir, "camera.json");
writeFileSync(cameraFile, JSON.stringify({ camera_angle_x: transforms.camera_angle_x, frames: [frame] }, null, 1));
const nerfjitDir = join(outDir, "nerfjit");
rmSync(nerfjitDir, { recursive: true, force: true });
execFileSync(binary, ["render", bake, "--cameras", cameraFile, "--size", String(size), "--background", "white", "--out", nerfjitDir],
  { stdio: ["ignore", "ignore", "inherit"] });
const pngs = readdirSync(nerfjitDir).filter((f) => f.endsWith(".png"));
if (pngs.length !== 1) throw new Error(`nerfjit render wrote ${pngs.length} PNGs to ${nerfjitDir}, not 1`);
const reference = readFileSync(join(nerfjitDir, pngs[0]));
// The frame's training image, if it is there.
const imagePath = frame.file_path && resolve(dirname(transformsPath), /\.\w+$/.test(frame.file_path) ? frame.file_path : `${frame.file_path}.png`);
const truth = imagePath && existsSync(imagePath) ? readFileSync(imagePath) : null;

// 3. The page: Spark draws the .ply from the frame's camera. A square picture: the vertical field of view
// is the horizontal one.
const config = { size, fov: (transforms.camera_angle_x * 180) / Math.PI, pose: frame.transform_matrix };
const page = `<!doctype html>
<html><head><meta charset="utf-8"><title>nerfjit splats</title>
<style>html, body { margin: 0; padding: 0; background: #fff; overflow: hidden; } canvas { display: block; }</style>
<script type="importmap">{"imports": {
  "three": "/node_modules/three/build/three.module.js",
  "three/addons/": "/node_modules/three/examples/jsm/",
  "@sparkjsdev/spark": "/node_modules/@sparkjsdev/spark/dist/spark.module.js"
}}</script></head>
<body>
<script type="application/json" id="config">${JSON.stringify(config)}</script>
<script type="module">
import * as THREE from "three";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";

const config = JSON.parse(document.getElementById("config").textContent);
const state = window.splats = { frames: 0, loadedMs: null, firstFrameMs: null, error: null };
window.addEventListener("error", (e) => { state.error ??= String(e.message); });
window.addEventListener("unhandledrejection", (e) => { state.error ??= String(e.reason && e.reason.stack || e.reason); });

const renderer = new THREE.WebGLRenderer({ antialias: false, alpha: false, precision: "highp" });
renderer.setPixelRatio(1);
renderer.setSize(config.size, config.size);
renderer.setClearColor(0xffffff, 1);
renderer.outputColorSpace = THREE.SRGBColorSpace; // three.js's default: Spark then converts no colors
document.body.appendChild(renderer.domElement);

const camera = new THREE.PerspectiveCamera(config.fov, 1, 0.01, 1000);
new THREE.Matrix4().set(...config.pose.flat()).decompose(camera.position, camera.quaternion, camera.scale);
camera.updateMatrixWorld(true);

const scene = new THREE.Scene();
const spark = new SparkRenderer({
  renderer,
  preBlurAmount: 0.3,
  blurAmount: 0.0,
  sortRadial: true,
  minAlpha: 1 / 255,
  enableLod: false,
});
scene.add(spark);
const mesh = new SplatMesh({ url: "/scene.ply", extSplats: true, lod: false });
scene.add(mesh);

function draw() {
  renderer.render(scene, camera);
  state.frames++;
}
const sorted = () => !spark.sorting && !spark.sortDirty && spark.orderingTexture;
const later = () => new Promise((done) => setTimeout(done, 10));

// Draws until a frame shows the splats sorted for the camera: the first draw after loading makes Spark
// read the splats' distances back and sort them in its worker; the next draw uses that order.
state.settle = async () => {
  for (let tries = 0; tries < 20; tries++) {
    draw();
    while (!sorted()) await later();
    draw();
    if (sorted()) return true; // this draw started no new sort: it showed the sorted splats
  }
  return false;
};

// Orbits the camera about the z axis through the origin for \`seconds\`, a frame per animation frame.
state.orbit = (seconds) => new Promise((done) => {
  const start = performance.now(), frames = state.frames;
  const { x, y, z } = camera.position;
  camera.up.set(0, 0, 1);
  const step = (now) => {
    const t = (now - start) / 1000;
    camera.position.set(x * Math.cos(0.6 * t) - y * Math.sin(0.6 * t), x * Math.sin(0.6 * t) + y * Math.cos(0.6 * t), z);
    camera.lookAt(0, 0, 0);
    draw();
    if (t < seconds) requestAnimationFrame(step);
    else done({ frames: state.frames - frames, seconds: (performance.now() - start) / 1000 });
  };
  requestAnimationFrame(step);
});

mesh.initialized.then(async () => {
  state.loadedMs = performance.now();
  state.splatCount = (mesh.extSplats || mesh.packedSplats).numSplats;
  state.settled = await state.settle();
  // WebGL draws asynchronously: reading a pixel back waits until the frame is drawn.
  const gl = renderer.getContext();
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
  state.firstFrameMs = performance.now();
  state.ready = true;
}, (e) => { state.error ??= String(e && e.stack || e); });

// Pixels of a PNG, over white.
async function pixels(base64) {
  const image = new Image();
  image.src = "data:image/png;base64," + base64;
  await image.decode();
  const context = new OffscreenCanvas(image.width, image.height).getContext("2d");
  context.fillStyle = "#fff";
  context.fillRect(0, 0, image.width, image.height);
  context.drawImage(image, 0, 0);
  return context.getImageData(0, 0, image.width, image.height);
}
function psnr(a, b) {
  let squares = 0;
  for (let i = 0; i < a.data.length; i += 4) {
    for (let c = 0; c < 3; c++) squares += ((a.data[i + c] - b.data[i + c]) / 255) ** 2;
  }
  const mse = squares / (a.width * a.height * 3);
  return mse > 0 ? -10 * Math.log10(mse) : 99;
}
// The PSNR between the browser's picture and nerfjit's (RGB in [0, 1]), their scores against the training
// image if given and of the same size, the spread of the browser's picture, and the two side by side with
// their difference.
window.compare = async (shownBase64, expectedBase64, truthBase64) => {
  const shown = await pixels(shownBase64), expected = await pixels(expectedBase64);
  const { width, height } = shown;
  if (expected.width !== width || expected.height !== height) {
    return { error: "the pictures are " + width + "×" + height + " and " + expected.width + "×" + expected.height };
  }
  const canvas = new OffscreenCanvas(3 * width, height);
  const context = canvas.getContext("2d");
  context.putImageData(shown, 0, 0);
  context.putImageData(expected, width, 0);
  const difference = context.createImageData(width, height);
  let sum = 0, squares = 0;
  for (let i = 0; i < shown.data.length; i += 4) {
    for (let c = 0; c < 3; c++) {
      difference.data[i + c] = 255 - Math.min(255, 4 * Math.abs(shown.data[i + c] - expected.data[i + c]));
      sum += shown.data[i + c] / 255;
      squares += (shown.data[i + c] / 255) ** 2;
    }
    difference.data[i + 3] = 255;
  }
  context.putImageData(difference, 2 * width, 0);
  const n = width * height * 3;
  const out = { psnr: psnr(shown, expected), spread: Math.sqrt(Math.max(0, squares / n - (sum / n) ** 2)) };
  if (truthBase64) {
    const truth = await pixels(truthBase64);
    if (truth.width === width && truth.height === height) {
      out.truth = { browser: psnr(shown, truth), nerfjit: psnr(expected, truth) };
    }
  }
  const blob = await canvas.convertToBlob({ type: "image/png" });
  out.picture = btoa(Array.from(new Uint8Array(await blob.arrayBuffer()), (b) => String.fromCharCode(b)).join(""));
  return out;
};
</script></body></html>`;

const types = { ".js": "text/javascript", ".map": "application/json", ".wasm": "application/wasm" };
const server = createServer((request, response) => {
  const path = decodeURIComponent(new URL(request.url, "http://localhost").pathname);
  let file = null;
  if (path === "/") {
    response.writeHead(200, { "Content-Type": "text/html", "Cache-Control": "no-store" }).end(page);
    return;
  } else if (path === "/scene.ply") {
    file = ply;
  } else if (path.startsWith("/node_modules/")) {
    const candidate = resolve(modules, path.slice("/node_modules/".length));
    if (candidate.startsWith(modules + sep) && types[candidate.slice(candidate.lastIndexOf("."))]) file = candidate;
  }
  if (!file || !statSync(file, { throwIfNoEntry: false })?.isFile()) {
    response.writeHead(path === "/favicon.ico" ? 204 : 404).end();
    return;
  }
  const type = file === ply ? "application/octet-stream" : types[file.slice(file.lastIndexOf("."))];
  response.writeHead(200, { "Content-Type": type, "Cache-Control": "no-store" });
  createReadStream(file).pipe(response);
});
await new Promise((done) => server.listen(0, "127.0.0.1", done));

// 4. Chromium draws it (software WebGL: SwiftShader); the canvas as shown is compared with nerfjit's PNG.
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--force-color-profile=srgb"],
});
const problems = [];
try {
  const tab = await browser.newPage({ viewport: { width: size, height: size }, deviceScaleFactor: 1 });
  tab.on("pageerror", (e) => problems.push(`error in the page: ${e.message}`));
  tab.on("console", (m) => { if (m.type() === "error") problems.push(`console error in the page: ${m.text()}`); });
  await tab.goto(`http://127.0.0.1:${server.address().port}/`);
  await tab.waitForFunction(() => window.splats && (window.splats.ready || window.splats.error), null, { timeout: 120_000 });
  const drawn = await tab.evaluate(() => {
    const s = window.splats, canvas = document.querySelector("canvas");
    const gl = canvas.getContext("webgl2");
    const info = gl && gl.getExtension("WEBGL_debug_renderer_info");
    return { error: s.error, settled: s.settled, count: s.splatCount, loadedMs: s.loadedMs, firstFrameMs: s.firstFrameMs,
      frames: s.frames, width: canvas.width, height: canvas.height, dpr: window.devicePixelRatio,
      webgl: info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : null };
  });
  if (drawn.error) throw new Error(`the page failed: ${drawn.error}`);
  if (drawn.width !== size || drawn.height !== size || drawn.dpr !== 1) {
    throw new Error(`the canvas is ${drawn.width}×${drawn.height} at devicePixelRatio ${drawn.dpr}, not ${size}² at 1`);
  }
  const shown = await tab.locator("canvas").screenshot({ type: "png" });
  writeFileSync(join(outDir, "browser.png"), shown);
  const compared = await tab.evaluate(([a, b, c]) => window.compare(a, b, c),
    [shown.toString("base64"), reference.toString("base64"), truth && truth.toString("base64")]);
  if (compared.error) throw new Error(compared.error);
  writeFileSync(join(outDir, "compare.png"), Buffer.from(compared.picture, "base64"));
  Object.assign(result, {
    psnr: Number(compared.psnr.toFixed(2)),
    min_psnr: options["min-psnr"],
    psnr_vs_training_image: compared.truth
      ? { browser: Number(compared.truth.browser.toFixed(2)), nerfjit: Number(compared.truth.nerfjit.toFixed(2)) }
      : null,
    splats_in_viewer: drawn.count,
    load_ms: Math.round(drawn.loadedMs),
    first_frame_ms: Math.round(drawn.firstFrameMs),
    frames_to_settle: drawn.frames,
    webgl: drawn.webgl,
  });
  if (!drawn.settled) problems.push("the viewer's sort did not settle");
  if (drawn.count !== result.splats) problems.push(`the viewer holds ${drawn.count} of the ${result.splats} splats`);
  if (!(compared.spread > 0.03)) problems.push(`the browser's picture looks blank (spread ${compared.spread.toFixed(4)})`);
  if (!(compared.psnr >= options["min-psnr"])) problems.push(`PSNR ${compared.psnr.toFixed(2)} dB against nerfjit's render, under ${options["min-psnr"]} dB`);
  if (compared.truth && !(compared.truth.browser >= compared.truth.nerfjit - 1)) {
    problems.push(`against the training image the browser scores ${compared.truth.browser.toFixed(2)} dB, nerfjit ${compared.truth.nerfjit.toFixed(2)} dB`);
  }

  if (options.fps > 0) {
    const orbit = await tab.evaluate((seconds) => window.splats.orbit(seconds), options.fps);
    Object.assign(result, { fps: Number((orbit.frames / orbit.seconds).toFixed(2)), fps_frames: orbit.frames, fps_seconds: Number(orbit.seconds.toFixed(2)) });
    await tab.locator("canvas").screenshot({ path: join(outDir, "orbit.png") });
  }
} finally {
  await browser.close();
  server.close();
}
console.log(JSON.stringify(result));
if (problems.length) {
  for (const problem of problems) console.error(`splats.mjs: ${problem}`);
  process.exit(1);
}
