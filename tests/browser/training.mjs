// A training run followed in a real browser: `nerfjit run examples/instant_lego.sdf --view` (needs
// ../shared/data) with headless Chromium watching; checks the page's progress, chart, frames of the
// trained params and pause/resume, saves a screenshot, and compares the run's ms/step with the same run
// without a viewer, run before and after it (the machine's speed drifts: the mean of the two), the
// target being at least 0.9× the steps/s. Prints the figures as JSON.
//
// usage: node tests/browser/training.mjs NERFJIT_BINARY OUT_DIR STEPS   (after `npm ci` in tests/browser)

import { spawn, execFileSync } from "node:child_process";
import { readFileSync, mkdirSync } from "node:fs";
import { join } from "node:path";
import { createInterface } from "node:readline";
import { chromium } from "playwright-core";

const [binary, outDir, stepsText] = process.argv.slice(2);
const steps = Number(stepsText);
if (!binary || !outDir || !(steps >= 100)) {
  console.error("usage: node training.mjs NERFJIT_BINARY OUT_DIR STEPS (at least 100)");
  process.exit(2);
}

function fail(message) {
  throw new Error(message);
}

// The run, shortened: validation once at the end on two views, a tiny render block.
const settings = (folder) => [
  "run", "examples/instant_lego.sdf", "--out", folder,
  "--set", `train.steps=${steps}`, "--set", `train.val_every=${steps}`, "--set", "train.val_minutes=[]",
  "--set", "train.val_views=2", "--set", "render.size=16",
];
const msPerStep = (folder) => JSON.parse(readFileSync(join(folder, "instant_lego.json"), "utf8")).ms_per_step;

// Without a viewer, before and after the watched run.
const runAlone = (name) => {
  const folder = join(outDir, name);
  mkdirSync(folder, { recursive: true });
  execFileSync(binary, settings(folder), { stdio: ["ignore", "ignore", "inherit"] });
  return msPerStep(folder);
};
const aloneBefore = runAlone("alone");

// With one: the page watches from the first step to the last.
const watched = join(outDir, "watched");
mkdirSync(watched, { recursive: true });
const run = spawn(binary, [...settings(watched), "--view", "--port", "0"], { stdio: ["ignore", "pipe", "ignore"] });
const lines = createInterface({ input: run.stdout });
const url = await new Promise((resolve, reject) => {
  lines.once("line", (line) => {
    const found = line.match(/http:\/\/\S+/);
    found ? resolve(found[0]) : reject(new Error(`no URL in ${line}`));
  });
  run.once("exit", (code) => reject(new Error(`nerfjit run exited with ${code}`)));
});
const finished = new Promise((resolve) => lines.on("line", (line) => line.startsWith("trained ") && resolve(line)));

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync"],
});
const results = { steps };
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 900 } });
  page.on("pageerror", (e) => fail(`error in the page: ${e.message}`));
  await page.goto(url);
  // Polled once a second: polling every animation frame would keep the browser busy, taking the cores
  // from the training it measures.
  const waitFor = (predicate, arg) => page.waitForFunction(predicate, arg, { timeout: 300_000, polling: 1000 });
  const history = () => page.evaluate(() => window.nerfjitViewer.training.history.length);
  await waitFor(() => window.nerfjitViewer.training && window.nerfjitViewer.training.history.length >= 3
    && window.nerfjitViewer.stats.frames >= 2);
  if (!(await page.isVisible("#chart"))) fail("the training chart is hidden");
  if (await page.isEditable("#source")) fail("the script is editable while it trains");
  const status = await page.textContent("#train-status");
  if (!/step \d+\/\d+ · loss .* PSNR .* steps\/s/.test(status)) fail(`unexpected status: ${status}`);

  // Pause: no record for a second; resume: records again.
  await page.click("#pause");
  await page.waitForTimeout(500);
  const paused = await history();
  await page.waitForTimeout(1000);
  if ((await history()) !== paused) fail("records came while paused");
  if (!(await page.textContent("#train-status")).includes("paused")) fail("the status does not say paused");
  await page.click("#pause");
  await waitFor((n) => window.nerfjitViewer.training.history.length > n, paused);

  results.summary = await finished;
  // The last params (published at the last step) are shown once the run has ended.
  await waitFor((last) => window.nerfjitViewer.paramsStep === last, steps);
  await page.waitForTimeout(1500);
  await page.screenshot({ path: join(outDir, "viewer-training.png") });
  results.frames_shown = await page.evaluate(() => window.nerfjitViewer.stats.frames);
} finally {
  await browser.close();
  run.kill();
}

results.ms_per_step_alone_before_after = [aloneBefore, runAlone("alone-after")];
results.ms_per_step_alone = (aloneBefore + results.ms_per_step_alone_before_after[1]) / 2;
results.ms_per_step_watched = msPerStep(watched);
results.speed_watched_vs_alone = results.ms_per_step_alone / results.ms_per_step_watched;
results.target = 0.9;
console.log(JSON.stringify(results));
// Far below the target means the viewer takes the cores from training, not merely noise.
if (!(results.speed_watched_vs_alone > 0.7)) fail(`training with a viewer ran at ${results.speed_watched_vs_alone}×`);
