"""The scene the fault scripts train: four views of a box rendered by nerfjit itself (as
tests/integration/common.rs makes them), a script that learns the box's center and sides, and readers of what a
run leaves (its checkpoint's step, its summary's parameters)."""

import json
import struct
import subprocess
import tempfile
from pathlib import Path

CAMERAS = {
    "image_size": [40, 40],
    "cameras": [
        {"image": f"view_{i:03}.png", "focal": 1.0, "principal_point": [0, 0], "eye": eye,
         "scene_center": [0, 0, 0], "up": [0, 1, 0]}
        for i, eye in enumerate([[-2.5, 0.3, 0.0], [-1.0, 0.5, -2.2], [0.0, -0.4, -2.5], [1.8, 0.8, -1.6]])
    ],
}
FIELD = """fn opacity(p: vec3) -> f32 = opacity_laplace(box(p - center, sides), alpha: 1.0, beta: 0.05)
fn color(p: vec3) -> vec3 = clamp(abs(p - center), 0.02, 0.98)
"""
TRUTH = "const center = [0.2, -0.1, 0.1]\nconst sides = [1.2, 0.8, 1.0]\n" + FIELD + \
    'render volume { camera: cameras("cams.json"), size: 40, near: 0, far: 5, samples: 48, out: "view.png" }\n'


def make_views(nerfjit, prefix):
    """A new folder holding cams.json and the box's four views."""
    work = Path(tempfile.mkdtemp(prefix=prefix))
    (work / "cams.json").write_text(json.dumps(CAMERAS))
    (work / "truth.sdf").write_text(TRUTH)
    subprocess.run([nerfjit, "run", "truth.sdf"], cwd=work, check=True, stdout=subprocess.DEVNULL)
    return work


def trainer(steps, params="", settings='checkpoint: "box.ckpt.safetensors"'):
    """A script that learns the box's center and sides in `steps` steps (with more `params` and `settings`)."""
    return "param center: vec3 = [0, 0, 0]\nparam sides: vec3 = [1.0, 1.0, 1.0]\n" + params + FIELD + \
        f'train {{ data: views("cams.json"), near: 0, far: 5, samples: 48, steps: {steps}, batch: 800, ' \
        f'lr: 0.01, schedule: exponential(gamma: 0.1, every: 400), summary: "summary.json", {settings} }}\n'


def checkpoint_step(path):
    """The step of a whole safetensors checkpoint; raises when it is not whole."""
    data = path.read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + n])
    end = max(t["data_offsets"][1] for k, t in header.items() if k != "__metadata__")
    if 8 + n + end != len(data):
        raise ValueError(f"{path}: {len(data)} bytes, the header says {8 + n + end}")
    return int(header["__metadata__"]["step"])


def params(folder):
    """The steps and the learnt center and sides in a run's summary."""
    summary = json.loads((folder / "summary.json").read_text())
    return summary["steps"], summary["params"]["center"] + summary["params"]["sides"]
