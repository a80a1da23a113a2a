#!/usr/bin/env python3
"""Files that change under a run: the training images and the script deleted while a run trains, and the disk
filling up while a mesh, a video, a GIF, numbered frames or a training run's checkpoint are written. Each ends
in a clear error naming the file (or, for the deleted inputs, does not matter: they were read at the start),
the last checkpoint stays whole and resumes, and no partial file is left under an output's name.

    sudo python3 tests/faults/files_change.py --nerfjit target/release/nerfjit

A full disk is a small tmpfs mounted for the test (root is needed for that part; without it, it is skipped
with a message). Needs no data (box_scene.py). Prints one line a fault; exits non-zero when a promise breaks.
"""

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import box_scene


def fail(message):
    sys.exit(f"files_change: {message}")


def wait_for(condition, seconds=60):
    deadline = time.time() + seconds
    while not condition():
        if time.time() > deadline:
            fail("timed out")
        time.sleep(0.05)


def inputs_deleted(nerfjit):
    work = box_scene.make_views(nerfjit, "nerfjit-files-change-")
    (work / "train.sdf").write_text(box_scene.trainer(1_000_000, settings='checkpoint: "box.ckpt.safetensors", checkpoint_every: 20'))
    log = work / "train.metrics.jsonl"
    run = subprocess.Popen([nerfjit, "run", "train.sdf"], cwd=work, stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE, text=True)
    wait_for(lambda: log.exists() and len(log.read_text().splitlines()) > 20)
    for view in work.glob("view_*.png"):
        view.unlink()
    (work / "train.sdf").write_text("")
    before = len(log.read_text().splitlines())
    time.sleep(1.5)
    after = len(log.read_text().splitlines())
    if run.poll() is not None or after <= before:
        fail(f"the run stopped when its inputs were deleted ({before} -> {after} log lines)")
    run.send_signal(signal.SIGINT)
    _, err = run.communicate(timeout=30)
    step = box_scene.checkpoint_step(work / "box.ckpt.safetensors")
    if "training stopped at step" not in err:
        fail(f"the interrupted run said: {err}")
    resumed = subprocess.run([nerfjit, "run", "train.sdf", "--resume"], cwd=work, capture_output=True, text=True)
    if resumed.returncode == 0 or "nothing to run" not in resumed.stderr:
        fail(f"a resume with the emptied script: {resumed.stderr}")
    print(f"inputs deleted: the images and the script deleted at log line {before}, the run trained on "
          f"({after} lines 1.5 s later), stopped with a whole checkpoint of step {step}; the emptied script "
          f"then says: {resumed.stderr.strip().splitlines()[-1][:80]}...")


def mounted_disk(size):
    folder = Path(tempfile.mkdtemp(prefix="nerfjit-full-disk-"))
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], check=True)
    return folder


def outputs_on_a_full_disk(nerfjit, examples):
    disk = mounted_disk("16k")
    try:
        def frames(size):
            return [str(examples / "sdf_to_density.sdf"), "--path", "surround(radius: 9, frames: 40, up: y, focal: 1)",
                    "--size", str(size), "--near", "5", "--far", "13", "--samples", "32"]
        cases = [
            ("mesh", ["mesh", str(examples / "torus.sdf"), "--res", "200", "--out", str(disk / "torus.ply")], "torus.ply"),
            ("video", ["render", *frames(400), "--out", str(disk / "orbit.mp4")], "orbit.mp4"),
            ("GIF", ["render", *frames(160), "--out", str(disk / "orbit.gif")], "orbit.gif"),
            ("frames", ["render", *frames(160), "--out", str(disk / "frames")], None),
        ]
        for what, args, name in cases:
            out = subprocess.run([nerfjit, *args], capture_output=True, text=True)
            error = out.stderr.strip()
            if out.returncode == 0 or "No space left on device" not in error:
                fail(f"{what} on a full disk: exit {out.returncode}, {error}")
            partial = [p.name for p in disk.rglob("*.partial")]
            if partial or (name and (disk / name).exists()):
                fail(f"{what}: left {partial or name}")
            written = sorted((disk / "frames").glob("*.png")) if name is None else []
            if not all(p.read_bytes()[-8:-4] == b"IEND" for p in written):
                fail("a numbered frame was left half written")
            note = f" ({len(written)} whole frames written before it)" if name is None else ""
            print(f"full disk, {what}: '{error.splitlines()[-1]}', nothing left under its name{note}")
    finally:
        subprocess.run(["umount", str(disk)], check=True)


def training_on_a_filling_disk(nerfjit):
    work = box_scene.make_views(nerfjit, "nerfjit-files-change-")
    disk = mounted_disk("4m")
    try:
        (work / "train.sdf").write_text(box_scene.trainer(
            1_000_000, settings=f'checkpoint: "{disk}/box.ckpt.safetensors", checkpoint_every: 20'))
        run = subprocess.Popen([nerfjit, "run", "train.sdf"], cwd=work, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)
        wait_for(lambda: (disk / "box.ckpt.safetensors").exists())
        time.sleep(0.5)
        with open(disk / "filler", "wb") as filler:
            try:
                while True:
                    filler.write(b"\0" * 65536)
                    filler.flush()
            except OSError:
                pass
        try:
            _, err = run.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            run.kill()
            fail("the run trained on for 30 s with a full disk")
        error = err.strip().splitlines()[-1]
        if run.returncode == 0 or "No space left on device" not in error:
            fail(f"training on a full disk: exit {run.returncode}, {err}")
        step = box_scene.checkpoint_step(disk / "box.ckpt.safetensors")
        litter = [p.name for p in disk.iterdir() if p.name not in ("box.ckpt.safetensors", "filler", ".nerfjit.lock")]
        if litter:
            fail(f"left {litter}")
        (disk / "filler").unlink()
        (work / "train.sdf").write_text(box_scene.trainer(
            step + 20, settings=f'checkpoint: "{disk}/box.ckpt.safetensors"'))
        resumed = subprocess.run([nerfjit, "run", "train.sdf", "--resume"], cwd=work, capture_output=True, text=True)
        if resumed.returncode != 0 or "trained 20 steps" not in resumed.stdout:
            fail(f"the resume after the disk was freed: {resumed.stderr}")
        print(f"full disk while training: '{error}'; the checkpoint of step {step} whole, nothing else left, "
              f"and resumed once the disk had room")
    finally:
        subprocess.run(["umount", str(disk)], check=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--nerfjit", default="target/release/nerfjit")
    nerfjit = os.path.abspath(parser.parse_args().nerfjit)
    examples = Path(__file__).resolve().parent.parent.parent / "examples"
    inputs_deleted(nerfjit)
    if os.geteuid() != 0:
        print("full disk: skipped (mounting a small tmpfs needs root)")
        return
    outputs_on_a_full_disk(nerfjit, examples)
    training_on_a_filling_disk(nerfjit)


if __name__ == "__main__":
    main()
