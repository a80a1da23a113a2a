#!/usr/bin/env python3
"""Hours, not minutes: a long training of `instant_lego_full.sdf` with the viewer attached and a page connected
that asks for a frame every 5 s. Every 10 s it samples the process's resident memory, open descriptors and
threads (from /proc); the step time of each minute comes from the run's metrics log (training seconds over
steps). It prints, and writes as drift.json in the output folder:

- resident memory after the first minute of training and at the end (growth, %; the promise: under 5%),
- the step time of the fifth minute and of the last (the promise: within 10%),
- descriptors and threads after the first minute, and their most at any later sample (the promise: no more).

    python3 tests/faults/long_run.py --nerfjit target/release/nerfjit --minutes 60 --out target/long-run

Needs ../shared/data/lego (about a minute to load). Takes the minutes asked for plus about three. The machine
should be otherwise idle: step times follow the load.
"""

import argparse
import base64
import json
import math
import os
import re
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path


class Page:
    """A minimal WebSocket client of the viewer's page protocol: asks for frames, answers pings."""

    def __init__(self, address, token):
        host, port = address.split(":")
        self.sock = socket.create_connection((host, int(port)))
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /ws?token={token} HTTP/1.1\r\nHost: {address}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n")
                          .encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        if b" 101 " not in head.split(b"\r\n")[0]:
            sys.exit(f"the page was refused: {head!r}")
        self.lock = threading.Lock()
        self.frames = 0
        self.last_frame = time.time()
        self.closed = None

    def send(self, opcode, payload):
        mask = os.urandom(4)
        header = bytes([0x80 | opcode])
        n = len(payload)
        header += bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
        with self.lock:
            self.sock.sendall(header + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))

    def exact(self, n):
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("closed")
            data += chunk
        return data

    def read_forever(self):
        try:
            while True:
                first, second = self.exact(2)
                n = second & 0x7F
                if n == 126:
                    (n,) = struct.unpack(">H", self.exact(2))
                elif n == 127:
                    (n,) = struct.unpack(">Q", self.exact(8))
                payload = self.exact(n)
                opcode = first & 0x0F
                if opcode == 0x9:
                    self.send(0xA, payload)
                elif opcode == 0x2:
                    self.frames += 1
                    self.last_frame = time.time()
                elif opcode == 0x8:
                    self.closed = payload
                    return
        except (ConnectionError, OSError) as e:
            self.closed = str(e)

    def ask_for_frames(self, stop):
        camera = {"eye": [0, -4, 1.5], "target": [0, 0, 0], "up": [0, 0, 1], "focal": 2.0}
        i = 0
        while not stop.is_set():
            i += 1
            angle = i * 0.2
            camera["eye"] = [4 * math.sin(angle), -4 * math.cos(angle), 1.5]
            request = {"type": "camera", "id": i, "width": 200, "height": 200, "layer": "color", **camera}
            self.send(0x1, json.dumps(request).encode())
            stop.wait(5)


def usage(pid):
    status = Path(f"/proc/{pid}/status").read_text()
    rss = int(re.search(r"VmRSS:\s+(\d+)", status).group(1))
    threads = int(re.search(r"Threads:\s+(\d+)", status).group(1))
    return rss, len(os.listdir(f"/proc/{pid}/fd")), threads


def step_ms(records, minute):
    """The mean step time (ms) over training minute `minute` (1-based), from the log's step records."""
    inside = [r for r in records if 60 * (minute - 1) <= r["train_seconds"] <= 60 * minute and "loss" in r]
    if len(inside) < 2:
        return None
    first, last = inside[0], inside[-1]
    return 1000 * (last["train_seconds"] - first["train_seconds"]) / (last["step"] - first["step"])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--nerfjit", default="target/release/nerfjit")
    parser.add_argument("--minutes", type=float, default=60)
    parser.add_argument("--out", default="target/long-run")
    args = parser.parse_args()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    command = [os.path.abspath(args.nerfjit), "run", "examples/instant_lego_full.sdf", "--out", str(out),
               "--set", f"train.minutes={args.minutes}", "--set", "train.steps=100000000",
               "--view", "--port", "0"]
    stderr = out / "run.log"
    run = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=stderr.open("w"), text=True)
    url = run.stdout.readline()
    found = re.search(r"http://([\d.]+:\d+)/\?token=(\w+)", url)
    if not found:
        sys.exit(f"no viewer URL in {url!r}")
    page = Page(found.group(1), found.group(2))
    stop = threading.Event()
    threading.Thread(target=page.read_forever, daemon=True).start()
    threading.Thread(target=page.ask_for_frames, args=(stop,), daemon=True).start()
    log = out / "instant_lego_full.metrics.jsonl"
    samples = []
    started = None
    while run.poll() is None:
        time.sleep(10)
        if started is None and log.exists() and log.stat().st_size > 0:
            started = time.time()
        if started is None:
            continue
        try:
            rss, fds, threads = usage(run.pid)
        except (OSError, AttributeError):
            break
        samples.append({"seconds": round(time.time() - started), "rss_kb": rss, "fds": fds, "threads": threads,
                        "frames": page.frames})
        # The run trains, renders its orbit, then keeps serving its viewer until stopped.
        if "the viewer stays open" in stderr.read_text(errors="replace"):
            break
    page_open = page.closed is None
    stop.set()
    run.terminate()
    run.wait()
    records = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    last_minute = int(max(r["train_seconds"] for r in records) // 60)
    after_first = [s for s in samples if s["seconds"] >= 60]
    result = {
        "minutes": args.minutes,
        "rss_mb_after_first_minute": after_first[0]["rss_kb"] / 1024,
        "rss_mb_at_end": after_first[-1]["rss_kb"] / 1024,
        "rss_growth_percent": 100 * (after_first[-1]["rss_kb"] / after_first[0]["rss_kb"] - 1),
        "rss_mb_most": max(s["rss_kb"] for s in after_first) / 1024,
        "step_ms_minute_5": step_ms(records, 5),
        f"step_ms_minute_{last_minute}": step_ms(records, last_minute),
        "fds_after_first_minute": after_first[0]["fds"],
        "fds_most_later": max(s["fds"] for s in after_first),
        "threads_after_first_minute": after_first[0]["threads"],
        "threads_most_later": max(s["threads"] for s in after_first),
        "frames_received": page.frames,
        "page_open_to_the_end": page_open,
        "steps": records[-1]["step"],
        "samples": samples,
    }
    (out / "drift.json").write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "samples"}, indent=1))


if __name__ == "__main__":
    main()
