#!/usr/bin/env python3
"""Ranks that die: `kill -9` of one rank of a 2-rank `mpirun` job of `nerfjit run`, in the middle of a step,
inside the all-reduce and during a checkpoint write. Each job must end within 30 s with mpirun's error naming
the lost rank, leave its last checkpoint whole, and `--resume` over 2 ranks must reach exactly the parameters
of a run without the fault (over 1 rank: the same steps, the rays split differently).

    python3 tests/faults/ranks_die.py --nerfjit target/release/nerfjit   # built with --features mpi

Needs no data: it renders its own views of a box (box_scene.py). The model carries a
2M-value padding param so that a checkpoint (25 MB) takes long enough to write to be caught in the act.
Prints one line a fault and exits non-zero when a promise is broken.
"""

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import box_scene

STEPS = 600
TRAIN = box_scene.trainer(STEPS, "param pad: mat<1024, 2048> = uniform(-1e-4, 1e-4, seed: 1)\n",
                          'checkpoint: "box.ckpt.safetensors", checkpoint_every: 50')


def mpirun(nerfjit, ranks, *args):
    return ["mpirun", "--allow-run-as-root", "--oversubscribe", "-np", str(ranks), nerfjit, "--threads", "1", *args]


def rank_pids(job):
    """The pids of the job's ranks, by rank (Open MPI puts each rank in its environment)."""
    ranks = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes().split(b"\0")
            if (entry / "cmdline").read_bytes().split(b"\0")[0] != job.encode():
                continue
        except OSError:
            continue
        for var in environ:
            if var.startswith(b"OMPI_COMM_WORLD_RANK="):
                ranks[int(var.split(b"=")[1])] = int(entry.name)
    return ranks


def faulted_run(nerfjit, work, name, fault):
    """Starts a 2-rank run in `work/name`, lets `fault` kill a rank, and checks how the job ended."""
    out = work / name
    job = subprocess.Popen(mpirun(nerfjit, 2, "run", "train.sdf", "--out", name), cwd=work,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 60
    while len(rank_pids(nerfjit)) < 2 or not (out / "box.ckpt.safetensors").exists():
        assert time.time() < deadline and job.poll() is None, "the job did not start"
        time.sleep(0.01)
    ranks = rank_pids(nerfjit)
    lost = fault(ranks, out)
    killed = time.time()
    try:
        log, _ = job.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        job.kill()
        sys.exit(f"{name}: the job still ran 30 s after rank {lost} was killed")
    ended = time.time() - killed
    named = re.search(rf"process rank {lost} .* exited on signal 9", log.replace("\n", " "))
    if job.returncode == 0 or not named:
        sys.exit(f"{name}: the job ended with {job.returncode} without naming rank {lost}:\n{log}")
    step = box_scene.checkpoint_step(out / "box.ckpt.safetensors")
    litter = [p.name for p in out.iterdir() if p.name.startswith(".tmp")]
    return out, lost, ended, step, litter


def mid_step(ranks, out):
    time.sleep(1.0)
    os.kill(ranks[1], signal.SIGKILL)
    return 1


def in_all_reduce(ranks, out):
    # Rank 0 stopped, rank 1 finishes its step and waits for rank 0's gradient in the all-reduce: killed there.
    os.kill(ranks[0], signal.SIGSTOP)
    time.sleep(1.0)
    os.kill(ranks[1], signal.SIGKILL)
    os.kill(ranks[0], signal.SIGCONT)
    return 1


def writing_checkpoint(ranks, out):
    # Rank 0 writes the checkpoint into a temporary file beside it, then renames it: killed while it exists.
    seen = {p.name for p in out.iterdir()}
    while not any(p.name.startswith(".tmp") and p.name not in seen for p in out.iterdir()):
        time.sleep(0.0005)
    os.kill(ranks[0], signal.SIGKILL)
    return 0


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--nerfjit", default="target/release/nerfjit")
    nerfjit = os.path.abspath(parser.parse_args().nerfjit)
    work = box_scene.make_views(nerfjit, "nerfjit-ranks-die-")
    (work / "train.sdf").write_text(TRAIN)
    try:
        subprocess.run(mpirun(nerfjit, 2, "run", "train.sdf", "--out", "reference"), cwd=work, check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        reference = box_scene.params(work / "reference")
        for name, fault in [("mid-step", mid_step), ("all-reduce", in_all_reduce), ("checkpoint", writing_checkpoint)]:
            out, lost, ended, step, litter = faulted_run(nerfjit, work, name, fault)
            resumed = {}
            for ranks in (2, 1):
                copy = work / f"{name}-{ranks}"
                subprocess.run(["cp", "-r", str(out), str(copy)], check=True)
                subprocess.run(mpirun(nerfjit, ranks, "run", "train.sdf", "--out", copy.name, "--resume"), cwd=work,
                               check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                resumed[ranks] = box_scene.params(copy)
            if resumed[2] != reference:
                sys.exit(f"{name}: resumed over 2 ranks to {resumed[2]}, the run without the fault to {reference}")
            steps, values = resumed[1]
            drift = max(abs(a - b) for a, b in zip(values, reference[1]))
            if steps != reference[0] or drift > 1e-3:
                sys.exit(f"{name}: resumed over 1 rank to {resumed[1]}, the run without the fault to {reference}")
            print(f"{name}: rank {lost} killed, the job ended {ended:.1f} s later naming it; the checkpoint of step "
                  f"{step} whole ({len(litter)} temporary file left: {litter}); resumed to step {STEPS}: over 2 ranks "
                  f"the same parameters bit for bit, over 1 rank within {drift:.1e}")
    finally:
        # Its runs hold 25 MB checkpoints and 64 MB summaries each.
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
