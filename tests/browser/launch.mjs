// What the viewer's browser checks share: `nerfjit view` started on a free port (its URL read from the first
// line it prints) and headless Chromium launched as CI runs it.
import { spawn } from "node:child_process";
import { createInterface } from "node:readline";
import { chromium } from "playwright-core";

/** Starts `binary view ...args` on a free port; resolves to the server process and the page's URL. */
export async function startViewer(binary, args) {
  const server = spawn(binary, ["view", ...args, "--port", "0"], { stdio: ["ignore", "pipe", "inherit"] });
  const url = await new Promise((resolve, reject) => {
    createInterface({ input: server.stdout }).once("line", (line) => {
      const found = line.match(/http:\/\/\S+/);
      found ? resolve(found[0]) : reject(new Error(`no URL in ${line}`));
    });
    server.once("exit", (code) => reject(new Error(`nerfjit view exited with ${code}`)));
  });
  return { server, url };
}

/** Headless Chromium (`$CHROMIUM`, else /usr/bin/chromium) without a GPU, a sandbox or background traffic. */
export function launchChromium() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
    args: ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
      "--disable-component-update", "--disable-sync"],
  });
}
