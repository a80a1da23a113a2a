"""`nerfjit.run`: a script's blocks run from Python, and Ctrl-C stops training with its checkpoint kept."""

import json
import signal
import subprocess
import sys
import time

import pytest

import nerfjit
from conftest import trainer


def test_a_run_learns_the_box_from_views_it_rendered(box_views):
    script = trainer(box_views, steps=300)
    nerfjit.run(str(script), out=box_views)
    summary = json.loads((box_views / "summary.json").read_text())
    center, sides = summary["params"]["center"], summary["params"]["sides"]
    errors = [abs(a - b) for a, b in zip(center + sides, [0.2, -0.1, 0.1, 1.2, 0.8, 1.0])]
    assert summary["steps"] == 300 and max(errors) < 0.05, summary["params"]
    assert (box_views / "train.ckpt.safetensors").is_file()


def test_set_overrides_and_errors_reach_python(box_views):
    script = trainer(box_views, steps=300)
    nerfjit.run(str(script), set=["train.steps=20"], out=box_views)
    assert json.loads((box_views / "summary.json").read_text())["steps"] == 20
    with pytest.raises(nerfjit.ScriptError, match="train.stepz"):
        nerfjit.run(str(script), set=["train.stepz=20"], out=box_views)
    with pytest.raises(nerfjit.NerfjitError, match="nothing.sdf"):
        nerfjit.run(str(box_views / "nothing.sdf"))


def test_ctrl_c_stops_training_with_its_checkpoint_and_resume_continues(box_views):
    script = trainer(box_views, steps=100_000)
    child = subprocess.Popen(
        [sys.executable, "-c", f"import nerfjit; nerfjit.run({str(script)!r}, out={str(box_views)!r})"],
        stderr=subprocess.PIPE, text=True,
    )
    metrics = box_views / "train.metrics.jsonl"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (not metrics.is_file() or len(metrics.read_text().splitlines()) < 3):
        time.sleep(0.05)
    child.send_signal(signal.SIGINT)
    _, err = child.communicate(timeout=60)
    assert child.returncode != 0 and "KeyboardInterrupt" in err, err
    assert "training stopped at step" in err and "run again with --resume" in err, err
    stopped = int(err.split("training stopped at step ")[1].split(":")[0])
    assert stopped > 0 and (box_views / "train.ckpt.safetensors").is_file()
    nerfjit.run(str(script), set=[f"train.steps={stopped + 10}"], out=box_views, resume=True)
    assert json.loads((box_views / "summary.json").read_text())["steps"] == stopped + 10
