#!/usr/bin/env python3
"""nerfjit beside its peers, one after the other in one sitting, on the same workloads.

Runs the machine's FMA peak, then for each workload nerfjit's benchmark followed by each peer's
(JAX, Dr.Jit, fidget from ../shared/bench), every run holding /tmp/bench.lock and waiting for a quiet
machine (../shared/bench/peak/quiet.sh), and prints a Markdown table of the figures and the ratios
nerfjit / peer (< 1: nerfjit faster).

    python3 bench/peers.py [--workloads W1,W2,W3,W4,W5,W6,W7] [--peers jax,drjit,fidget] [--bench ../shared/bench]
                           [--bf16]

--bf16 also runs nerfjit's networks (W4, W5, W6) with `--products bf16` (bfloat16 operands, f32 sums; on AMX or
AVX-512 BF16 where the CPU has them) and adds their rows beside the f32 ones.

W3 to W6 need ../shared/data (nerfjit's and JAX's runs read the course's box images, lego and the bunny).

The peers must be installed as their run.sh files describe (jax 0.10.2, drjit 1.5.0 with libLLVM 19,
tcmalloc); a peer that fails to run is reported as such and the others go on.
"""

import argparse
import datetime
import glob
import json
import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NERFJIT = os.path.join(ROOT, "target", "release", "nerfjit")

# (workload, figure, unit, nerfjit output pattern)
FIGURES = {
    "W1": [("torus frame", "ms", r"^\s+([0-9.]+) ms/frame")],
    "W2": [("box volume frame (exact)", "ms", r"^\s+([0-9.]+) ms/frame")],
    "W3": [("box training step", "ms", r"trained \d+ steps in [^(]*\(([0-9.]+) ms/step")],
    "W4": [
        ("NeRF training step", "ms", r"trained \d+ steps in [^(]*\(([0-9.]+) ms/step"),
        ("NeRF render one 128² view", "s", r"([0-9.]+) s/view"),
    ],
    "W5": [("neural SDF step", "ms", r"\(([0-9.]+) ms/step")],
    "W6": [("VolSDF step", "ms", r"trained \d+ steps in [^(]*\(([0-9.]+) ms/step")],
    "W7": [
        ("distance, 2 threads", "ns/point", r"distance\s+2 threads:\s+([0-9.]+) ns/point"),
        ("distance + gradient, 2 threads", "ns/point", r"distance\+gradient\s+2 threads:\s+([0-9.]+) ns/point"),
    ],
}

# nerfjit's --reps per workload: W4 and W6 train 10 steps a rep (~1 s each), so fewer reps keep a run short.
NERFJIT_REPS = {"W4": "3", "W6": "3"}

# Dr.Jit's peer covers W1, W2 and W7 (its W4 runs drjit.nn at ~5 s a step; see its RESULTS.md).
DRJIT_WORKLOADS = {"W1", "W2", "W7"}


def locked(bench, cmd, env=None):
    """Runs cmd inside the benchmark lock on a quiet machine; returns its stdout (raises on failure)."""
    full = ["flock", "/tmp/bench.lock", os.path.join(bench, "peak", "quiet.sh")] + cmd
    out = subprocess.run(full, capture_output=True, text=True, env=env, check=True)
    return out.stdout


def json_lines(text):
    return [json.loads(l) for l in text.splitlines() if l.startswith("{")]


def peak(bench):
    """The FMA peak by vector width and threads. On a CPU without AVX-512 gcc refuses peak.c's 512-bit
    kernel: a copy without it (the shared file untouched) measures the other widths, with 12 accumulators
    instead of 16. Without AVX-512 there are 16 vector registers, so 16 accumulators and the two operands
    do not fit: gcc keeps three accumulators on the stack, and the store-to-load round trips of their
    chains halve the measured rate (58.6 against 101 GFLOP/s on one thread on 2026-11-25). 12 chains are
    still more than the 8 that two FMA pipes of latency 4 need."""
    source = os.path.join(bench, "peak", "peak.c")
    compile_peak = lambda src: subprocess.run(["gcc", "-O3", "-march=native", "-fopenmp", src, "-o",
                                               "/tmp/peak_bin"], capture_output=True)
    if compile_peak(source).returncode != 0:
        with open(source) as f:
            text = f.read()
        text = "".join(l for l in text.splitlines(True) if not l.startswith("KERNEL(fma512"))
        text = text.replace('{"fma512", fma512, 16}, ', "").replace("i < 3;", "i < (int)(sizeof ks / sizeof ks[0]);")
        text = re.sub(r"#define CHAINS 16\b", "#define CHAINS 12", text)
        with open("/tmp/peak_no512.c", "w") as f:
            f.write(text)
        compile_peak("/tmp/peak_no512.c").check_returncode()
        print("[peers] no AVX-512 here: peak measured without the 512-bit kernel", file=sys.stderr)
    lines = json_lines(locked(bench, ["/tmp/peak_bin", "7"]))
    fma = {(r["test"], r["threads"]): r["gflops_median"] for r in lines if "gflops_median" in r}
    return fma


# The workloads whose networks can multiply in bf16.
BF16_WORKLOADS = {"W4", "W5", "W6"}


def nerfjit(bench, workload, products="f32"):
    text = locked(bench, [NERFJIT, "bench", workload.lower(), "--reps", NERFJIT_REPS.get(workload, "9"),
                          "--products", products])
    values = []
    for _, _, pattern in FIGURES[workload]:
        m = re.search(pattern, text, re.M)
        values.append(float(m.group(1)) if m else None)
    return values


def jax(bench, workload):
    rec = json_lines(locked(bench, ["python3", os.path.join(bench, "jax", "peer.py"), workload,
                                    "--reps", "10", "--wait-idle", "0"]))[-1]
    if workload == "W7":
        return [rec["dist_ns_per_point"], rec["dist_grad_ns_per_point"]]
    if workload == "W4":
        return [rec["train_step_ms"], rec["render_view_s"]]
    if workload in ("W3", "W5", "W6"):
        return [rec["step_ms"]]
    return [rec["frame_s"] * 1e3]


def drjit_env():
    env = dict(os.environ)
    llvm = sorted(glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM.so.19*"))
    if llvm:
        env["DRJIT_LIBLLVM_PATH"] = llvm[0]
    return env


def drjit(bench, workload):
    if workload not in DRJIT_WORKLOADS:
        return None
    rec = json_lines(locked(bench, ["python3", os.path.join(bench, "drjit", "peer.py"), "--only", workload,
                                    "--threads", "2", "--reps", "7"], env=drjit_env()))[-1]
    if workload == "W7":
        return [rec["ns_per_point_dist"], rec["ns_per_point_distgrad"]]
    return [rec["s_per_frame"] * 1e3]


def fidget(bench, workload):
    if workload != "W7":
        return None
    build = "/tmp/fidget-peer"
    os.makedirs(os.path.join(build, "src"), exist_ok=True)
    for f in ["Cargo.toml", "src/main.rs"]:
        with open(os.path.join(bench, "fidget", f)) as src, open(os.path.join(build, f), "w") as dst:
            dst.write(src.read())
    subprocess.run(["cargo", "build", "--release", "-q"], cwd=build, check=True)
    rec = json_lines(locked(bench, [os.path.join(build, "target", "release", "fidget-peer"), "15", "16384"]))[-1]
    return [rec["ns_per_point_dist_2t"], rec["ns_per_point_distgrad_2t"]]


PEERS = {"jax": jax, "drjit": drjit, "fidget": fidget}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workloads", default="W1,W2,W3,W4,W5,W6,W7")
    ap.add_argument("--peers", default="jax,drjit,fidget")
    ap.add_argument("--bench", default=os.path.join(ROOT, "..", "shared", "bench"))
    ap.add_argument("--bf16", action="store_true", help="also nerfjit's W4-W6 with bf16 products")
    args = ap.parse_args()
    bench = os.path.abspath(args.bench)
    subprocess.run(["cargo", "build", "--release", "-q"], cwd=ROOT, check=True)
    peers = [p for p in args.peers.split(",") if p]
    started = datetime.datetime.now(datetime.timezone.utc)
    fma = peak(bench)
    rows = []
    for w in args.workloads.split(","):
        ours = nerfjit(bench, w)
        ours_bf16 = nerfjit(bench, w, "bf16") if args.bf16 and w in BF16_WORKLOADS else None
        theirs = {}
        for p in peers:
            try:
                theirs[p] = PEERS[p](bench, w)
            except (subprocess.CalledProcessError, KeyError, IndexError, OSError) as e:
                print(f"[peers] {p} {w} failed: {e}", file=sys.stderr)
                theirs[p] = "failed"
        for k, (figure, unit, _) in enumerate(FIGURES[w]):
            peer_figures = {p: (v[k] if isinstance(v, list) else v) for p, v in theirs.items()}
            rows.append((w, figure, unit, ours[k], peer_figures))
            if ours_bf16:
                rows.append((w, figure + " (bf16 products)", unit, ours_bf16[k], peer_figures))
        print(f"[peers] {w} done", file=sys.stderr)
    peak_line = ", ".join(f"{bits}-bit {fma.get((f'fma{bits}', 1), '?')} / {fma.get((f'fma{bits}', 2), '?')}"
                          for bits in (512, 256))
    print(f"Side by side, {started:%Y-%m-%d %H:%M} UTC; FMA peak GFLOP/s (1 / 2 threads): {peak_line}")
    print()
    head = "| workload | figure | nerfjit | " + " | ".join(peers) + " | " + " | ".join(f"÷ {p}" for p in peers) + " |"
    print(head)
    print("|" + "---|" * (3 + 2 * len(peers)))
    fmt = lambda v: "—" if v is None else (v if isinstance(v, str) else f"{v:.0f}" if v >= 100 else f"{v:.3g}")
    for w, figure, unit, ours, theirs in rows:
        ratios = [fmt(ours / theirs[p]) if isinstance(theirs.get(p), float) and ours else "—" for p in peers]
        print(f"| {w} | {figure}, {unit} | {fmt(ours)} | " + " | ".join(fmt(theirs.get(p)) for p in peers)
              + " | " + " | ".join(ratios) + " |")


if __name__ == "__main__":
    main()
