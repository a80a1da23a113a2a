"""What the tests share: a small scene whose answers are known (a box rendered by nerfjit from four
cameras, and a script that learns it back)."""

import json
import pathlib

import pytest

import nerfjit

CAMERAS = {
    "image_size": [40, 40],
    "cameras": [
        {"image": f"view_00{i}.png", "focal": 1.0, "principal_point": [0, 0], "eye": eye,
         "scene_center": [0, 0, 0], "up": [0, 1, 0]}
        for i, eye in enumerate([[-2.5, 0.3, 0.0], [-1.0, 0.5, -2.2], [0.0, -0.4, -2.5], [1.8, 0.8, -1.6]])
    ],
}

FIELD = (
    "fn opacity(p: vec3) -> f32 = opacity_laplace(box(p - center, sides), alpha: 1.0, beta: 0.05)\n"
    "fn color(p: vec3) -> vec3 = clamp(abs(p - center), 0.02, 0.98)\n"
)


@pytest.fixture
def box_views(tmp_path: pathlib.Path) -> pathlib.Path:
    """A folder holding `cams.json` and the true box's four views, rendered by `nerfjit.run`."""
    (tmp_path / "cams.json").write_text(json.dumps(CAMERAS))
    truth = tmp_path / "truth.sdf"
    truth.write_text(
        "const center = [0.2, -0.1, 0.1]\nconst sides = [1.2, 0.8, 1.0]\n" + FIELD
        + f'render volume {{ camera: cameras("{tmp_path / "cams.json"}"), size: 40, near: 0, far: 5, '
        'samples: 48, out: "view.png" }\n'
    )
    nerfjit.run(str(truth), out=tmp_path)
    assert (tmp_path / "view_003.png").is_file()
    return tmp_path


def trainer(folder: pathlib.Path, steps: int) -> pathlib.Path:
    """A script in `folder` that learns the box's center and sides from its views in `steps` steps."""
    script = folder / "train.sdf"
    script.write_text(
        "param center: vec3 = [0, 0, 0]\nparam sides: vec3 = [1.0, 1.0, 1.0]\n" + FIELD
        + f'train {{ data: views("{folder / "cams.json"}"), near: 0, far: 5, samples: 48, steps: {steps}, '
        'batch: 800, lr: 0.01, schedule: exponential(gamma: 0.1, every: 400), checkpoint_every: 50, '
        'summary: "summary.json" }\n'
    )
    return script
