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


def test_a_trainer_yields_the_metrics_of_every_nth_step(box_views):
    script = trainer(box_views, steps=120)
    seen = list(nerfjit.Trainer(str(script), out=box_views).steps(every=20))
    assert [m["step"] for m in seen] == [20, 40, 60, 80, 100, 120], seen
    # The log holds every 10th step: every 25 steps is the first logged at or after each multiple.
    assert [m["step"] for m in nerfjit.Trainer(str(script), out=box_views).steps(every=25)] == [30, 50, 80, 100, 120]
    assert all(m["loss"] > 0 for m in seen) and seen[-1]["loss"] < seen[0]["loss"]
    assert json.loads((box_views / "summary.json").read_text())["steps"] == 120
    with pytest.raises(ValueError, match="every is at least 1"):
        nerfjit.Trainer(str(script)).steps(every=0)
    with pytest.raises(nerfjit.ScriptError, match="train.stepz"):
        list(nerfjit.Trainer(str(script), set=["train.stepz=1"], out=box_views).steps())


def test_leaving_the_loop_stops_training_with_its_checkpoint(box_views):
    script = trainer(box_views, steps=1_000_000)
    for metrics in nerfjit.Trainer(str(script), out=box_views).steps(every=10):
        if metrics["step"] >= 30:
            break
    summary = json.loads((box_views / "summary.json").read_text())
    assert 30 <= summary["steps"] < 1_000_000 and (box_views / "train.ckpt.safetensors").is_file()
    resumed = list(nerfjit.Trainer(str(script), set=[f"train.steps={summary['steps'] + 20}"], out=box_views,
                                   resume=True).steps(every=10))
    assert resumed[-1]["step"] == summary["steps"] + 20


def test_ctrl_c_stops_a_trainer_loop(box_views):
    script = trainer(box_views, steps=1_000_000)
    code = (f"import nerfjit\nfor m in nerfjit.Trainer({str(script)!r}, out={str(box_views)!r}).steps(every=10):\n"
            "    print(m['step'], flush=True)\n")
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "10"
    child.send_signal(signal.SIGINT)
    _, err = child.communicate(timeout=60)
    assert "KeyboardInterrupt" in err and "training stopped at step" in err, err
    assert (box_views / "train.ckpt.safetensors").is_file()
