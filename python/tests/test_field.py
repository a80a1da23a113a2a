"""`nerfjit.load` and meshes: a field renders into numpy as nerfjit renders it into files, a checkpoint
carries its trained params, and level sets come back as arrays."""

import json
import math

import numpy as np
import pytest
from PIL import Image

import nerfjit
from conftest import FIELD, trainer

TRUTH = "const center = [0.2, -0.1, 0.1]\nconst sides = [1.2, 0.8, 1.0]\n" + FIELD


def blender_frames(count=3, radius=3.0, angle=0.9):
    """Blender transforms of cameras on a circle about the y axis, looking at the origin (OpenGL axes)."""
    frames = []
    for i in range(count):
        azimuth = 2 * math.pi * i / count + 0.3
        eye = np.array([radius * math.sin(azimuth), 0.8, radius * math.cos(azimuth)])
        back = eye / np.linalg.norm(eye)
        right = np.cross([0.0, 1.0, 0.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, back, eye
        frames.append({"file_path": f"./unused_{i}", "transform_matrix": c2w.tolist()})
    return {"camera_angle_x": angle, "frames": frames}


def test_a_field_renders_what_the_render_block_writes(tmp_path):
    transforms = blender_frames()
    (tmp_path / "transforms.json").write_text(json.dumps(transforms))
    script = tmp_path / "truth.sdf"
    script.write_text(TRUTH + f'render volume {{ camera: cameras("{tmp_path / "transforms.json"}"), size: 40, '
                      'near: 0, far: 5, samples: 48, out: "view.png" }\n')
    nerfjit.run(str(script), out=tmp_path)
    field = nerfjit.load(str(script), near=0, far=5, samples=48)
    assert field.rendering == (0.0, 5.0, 48, [0.0, 0.0, 0.0])
    focal = 0.5 * 40 / math.tan(0.5 * transforms["camera_angle_x"])
    for i, frame in enumerate(transforms["frames"]):
        image, depth, opacity = field.render(np.array(frame["transform_matrix"]), focal, 40)
        assert image.shape == (40, 40, 3) and depth.shape == (40, 40) and opacity.shape == (40, 40)
        written = np.asarray(Image.open(tmp_path / f"view_{i:03}.png").convert("RGB"))
        # The PNG holds the same colours, truncated to 8 bits as nerfjit writes them: bit for bit.
        np.testing.assert_array_equal((np.clip(image, 0, 1) * np.float32(255)).astype(np.uint8), written)
        assert 0.05 < opacity.mean() < 0.95 and np.all(depth[opacity > 0.99] > 1.0)


def test_a_checkpoint_renders_with_its_trained_params(box_views):
    script = trainer(box_views, steps=300)
    nerfjit.run(str(script), out=box_views)
    field = nerfjit.load(str(box_views / "train.ckpt.safetensors"))
    center, sides = field.params["center"], field.params["sides"]
    np.testing.assert_allclose(np.concatenate([center, sides]), [0.2, -0.1, 0.1, 1.2, 0.8, 1.0], atol=0.05)
    assert field.script.params["center"].tolist() == center.tolist()
    truth = nerfjit.load(str(box_views / "truth.sdf"), near=0, far=5, samples=48)
    c2w = np.array(blender_frames(1)["frames"][0]["transform_matrix"])
    learned, _, _ = field.render(c2w, focal=(45.0, 44.0), size=(48, 32), principal=(25.0, 15.0))
    expected, _, _ = truth.render(c2w, focal=(45.0, 44.0), size=(48, 32), principal=(25.0, 15.0))
    assert learned.shape == (32, 48, 3)
    psnr = -10 * np.log10(np.mean((learned - expected) ** 2))
    assert psnr > 30, psnr


def test_meshes_come_back_as_arrays():
    sphere = nerfjit.Script("fn sdf(p: vec3) -> f32 = length(p - vec3(0.1, 0.0, 0.0)) - 0.5")
    vertices, faces = sphere.mesh(resolution=48)
    assert vertices.dtype == np.float32 and faces.dtype == np.uint32 and faces.shape[1] == 3
    np.testing.assert_allclose(np.linalg.norm(vertices - [0.1, 0, 0], axis=1), 0.5, atol=2e-3)
    # Closed: every edge is shared by exactly two faces, once in each direction.
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len({tuple(e) for e in edges.tolist()}) == len(edges)
    assert {tuple(e) for e in edges.tolist()} == {(b, a) for a, b in edges.tolist()}
    # A box given by its corners, a level other than 0.
    shifted, _ = sphere.mesh("sdf", resolution=32, bounds=((-1, -1, -1), (1.2, 1, 1)), level=0.2)
    np.testing.assert_allclose(np.linalg.norm(shifted - [0.1, 0, 0], axis=1), 0.7, atol=5e-3)


def test_bad_renders_and_fields_say_what_is_wrong(tmp_path):
    sdf_only = tmp_path / "ball.sdf"
    sdf_only.write_text("fn sdf(p: vec3) -> f32 = length(p) - 1.0\n")
    field = nerfjit.load(str(sdf_only))
    assert field.script.mesh(resolution=16)[0].shape[1] == 3
    with pytest.raises(nerfjit.NerfjitError, match="density|opacity"):
        field.render(np.eye(4), 20.0, 16)
    truth = tmp_path / "truth.sdf"
    truth.write_text(TRUTH)
    field = nerfjit.load(str(truth))
    with pytest.raises(ValueError, match="4×4 or 3×4"):
        field.render(np.eye(3), 20.0, 16)
    with pytest.raises(ValueError, match="each side is 1 to 16384"):
        field.render(np.eye(4), 20.0, 0)
    with pytest.raises(ValueError, match="focal"):
        field.render(np.eye(4), -1.0, 16)
    with pytest.raises(ValueError, match="background 'grey'"):
        nerfjit.load(str(truth), background="grey")
    with pytest.raises(nerfjit.NerfjitError, match="nothing.ckpt.safetensors"):
        nerfjit.load(str(tmp_path / "nothing.ckpt.safetensors"))


def test_data_sets_load_as_arrays_whose_cameras_render_their_images(box_views):
    views = nerfjit.data.load(box_views / "cams.json")
    assert views["read_as"] == "read as the course's cameras"
    assert views["images"].shape == (4, 40, 40, 3) and views["c2w"].shape == (4, 4, 4)
    assert views["intrinsics"].shape == (4, 4) and views["masks"] is None
    # The PyTorch3D cameras of the course's file, handed back in the OpenGL convention with pixel
    # intrinsics, render the images they took.
    truth = nerfjit.load(str(box_views / "truth.sdf"), near=0, far=5, samples=48)
    for i in range(4):
        fx, fy, cx, cy = views["intrinsics"][i]
        image, _, _ = truth.render(views["c2w"][i], (fx, fy), 40, principal=(cx, cy))
        assert np.abs(np.floor(image * 255) / 255 - views["images"][i]).max() <= 1.01 / 255
    with pytest.raises(nerfjit.NerfjitError, match="nothing: file not found"):
        nerfjit.data.load(box_views / "nothing")
    (box_views / "nothing").mkdir()
    with pytest.raises(nerfjit.NerfjitError, match="holds no data set nerfjit reads"):
        nerfjit.data.load(box_views / "nothing")
    with pytest.raises(ValueError, match="format 'mip360'"):
        nerfjit.data.load(box_views / "cams.json", format="mip360")
