#!/usr/bin/env python3
"""Writes synthetic data sets whose answer is known, in the layouts real ones come in.

`../shared/data` holds one NeRF-synthetic scene (lego, which the recipes were tuned on) and no capture whose
background is part of the scene. This script makes one of each from truth scenes in `.sdf`, rendered by
`nerfjit run`:

- `room`: a phone capture, an object (a textured ball, box and ring on a checkered floor) inside a room of
  striped walls 3 to 5 units away, walked around by `--views` cameras at varying heights and distances, written
  as a nerfstudio `transforms.json` (OpenGL camera-to-world matrices, `fl_x`/`cx`, instant-ngp's `aabb_scale`)
  in a frame of other units, up axis and origin than the scene's, as a phone's capture comes out of COLMAP.
  Train it as the README says for one's own photos:

      python3 bench/captures/synthetic.py room --out /tmp/room
      nerfjit run examples/instant_capture.sdf --set 'train.data=nerfstudio("/tmp/room/transforms.json")'

  Every 8th view held out (the recipe's `val: holdout(every: 8)`) is the score. `--shape` chooses the
  photos' shape (ROOM_SHAPES): `landscape` (320×240, the default), `portrait` (180×320: a phone held
  upright, its 1080×1920 photos read at a sixth, the landscape lens turned) or `wide` (400×160, a
  panorama-like crop of a wider lens).
- `object`: a NeRF-synthetic ("Blender") scene, a toy of thin rods, a thin ring, a striped ball and a bitten
  block on a checkered plate, in the layout of `../shared/data/lego`: 80 training and 10 validation views of
  800×800 RGBA PNGs (the alpha from renders on black and on white) from the upper hemisphere at lego's
  distance and field of view, `transforms_train.json` and `transforms_val.json`. Train a lego recipe on it by
  changing only its data paths.
"""

import argparse
import json
import math
import os
import shutil
import subprocess
import sys

import numpy as np

ROOM_TRUTH = """\
// The truth of the synthetic room capture (bench/captures/synthetic.py room): in the scene's own frame (z up, floor at
// z = 0), an object of three parts near the origin in a room of 8 x 7 x 3 units.
fn objects(p: vec3) -> f32 {
    let ball = sphere(p - [0.0, 0.0, 0.45], 0.45);
    let block = box(rotate_z(p - [0.75, 0.35, 0.25], 0.5), [0.5, 0.3, 0.5]);
    let ring = torus(p - [-0.6, 0.5, 0.12], 0.3, 0.1);
    min(min(ball, block), ring)
}
// Negative in the walls, floor and ceiling (the room's inside is where this is positive).
fn room(p: vec3) -> f32 = -box(p - [0.5, -0.5, 1.5], [8.0, 7.0, 3.0])
fn scene(p: vec3) -> f32 = min(objects(p), room(p))
fn density(p: vec3) -> f32 = 400.0 * sigmoid(-scene(p) * 150.0)
fn color(p: vec3) -> vec3 {
    let stripes = 0.5 + 0.5 * sin(p * 7.0);
    let checker = step(0.0, sin(p.x * 4.0) * sin(p.y * 4.0));
    let wall = [0.75, 0.7, 0.6] * (0.6 + 0.4 * stripes.z) + [0.1, 0.0, 0.15] * stripes.x;
    let floor = mix([0.25, 0.2, 0.15], [0.8, 0.75, 0.7], checker);
    let ball = [0.85, 0.2, 0.1] * (0.5 + 0.5 * stripes.y) + [0.0, 0.3, 0.0] * stripes.x;
    let block = [0.1, 0.35, 0.8] * (0.6 + 0.4 * stripes.x);
    let ring = [0.9, 0.8, 0.2];
    let o = objects(p);
    let near_ball = step(length(p - [0.0, 0.0, 0.45]) - 0.5, 0.0);
    let near_ring = step(length(p - [-0.6, 0.5, 0.12]) - 0.45, 0.0);
    let object = mix(mix(block, ring, near_ring), ball, near_ball);
    let surroundings = select(step(p.z, 0.02), floor, wall);
    select(step(o, 0.05), object, surroundings)
}
"""

ROOM_RENDER = """
render volume {{
    camera: cameras("transforms.json", normalize: false),
    size: [{width}, {height}],
    near: 0.05,
    far: 14.0,
    samples: {samples},
    skip_empty: grid(bounds: [-4.0, -4.5, -0.5, 5.0, 3.5, 3.5], resolution: 128, threshold: 1e-3),
    early_termination: 1e-4,
    out: "images/frame.png",
}}
"""

OBJECT_TRUTH = """\
// The truth of the synthetic NeRF-synthetic scene (bench/captures/synthetic.py object): a toy on a plate,
// z up, within lego's extent.
fn plate(p: vec3) -> f32 = rounded_box(p - [0.0, 0.0, -0.45], [1.5, 1.7, 0.12], 0.03)
fn ball(p: vec3) -> f32 = sphere(p - [0.15, -0.3, 0.05], 0.38)
fn block(p: vec3) -> f32 =
    smooth_difference(box(rotate_z(p - [-0.35, 0.45, -0.1], 0.4), [0.5, 0.4, 0.6]), sphere(p - [-0.1, 0.55, 0.15], 0.25), 0.03)
fn ring(p: vec3) -> f32 = torus(rotate_x(p - [0.15, -0.3, 0.05], 1.1), 0.62, 0.025)
fn rods(p: vec3) -> f32 {
    let q = vec3(abs(p.x) - 0.6, abs(p.y) - 0.7, p.z);
    capsule(q, [0.0, 0.0, -0.4], [0.0, 0.0, 0.75], 0.03)
}
fn scene(p: vec3) -> f32 = min(min(min(plate(p), ball(p)), min(block(p), ring(p))), rods(p))
fn density(p: vec3) -> f32 = 400.0 * sigmoid(-scene(p) * 150.0)
fn color(p: vec3) -> vec3 {
    let stripes = 0.5 + 0.5 * sin(p * 23.0);
    let checker = step(0.0, sin(p.x * 12.0) * sin(p.y * 12.0));
    let plate_color = mix([0.15, 0.15, 0.2], [0.85, 0.85, 0.8], checker);
    let ball_color = [0.9, 0.3, 0.1] * (0.4 + 0.6 * stripes.z) + [0.0, 0.2, 0.4] * stripes.x;
    let block_color = [0.2, 0.6, 0.3] * (0.5 + 0.5 * stripes.y);
    let thin = [0.95, 0.85, 0.2];
    let nearest_thin = min(ring(p), rods(p));
    let c = select(step(nearest_thin, 0.02), thin, select(step(ball(p), 0.02), ball_color, block_color));
    select(step(plate(p), 0.02), plate_color, c)
}
"""

OBJECT_RENDER = """
render volume {{
    camera: cameras("transforms_{split}.json"),
    size: {size},
    near: 2.0,
    far: 6.0,
    samples: {samples},
    skip_empty: grid(bounds: 1.5, resolution: 128, threshold: 1e-3),
    early_termination: 1e-4,
    background: [{bg}, {bg}, {bg}],
    out: "{split}_{bg}/r.png",
}}
"""


def look_at(eye, target, up):
    """The OpenGL camera-to-world rotation (x right, y up, z backward) of a camera at eye looking at target."""
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    return np.stack([right, true_up, -forward], axis=1)


def camera_to_world(rotation, eye):
    """The 4×4 camera-to-world matrix of a camera at eye with the given rotation."""
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, eye
    return matrix


def run_nerfjit(nerfjit, folder, script):
    """Writes `script` to truth.sdf in `folder` and runs it."""
    with open(os.path.join(folder, "truth.sdf"), "w") as file:
        file.write(script)
    subprocess.run([os.path.abspath(nerfjit), "run", "truth.sdf"], cwd=folder, check=True)


# The room capture's photo shapes: width, height and focal length in pixels.
ROOM_SHAPES = {
    "landscape": (320, 240, 0.62 * 320),
    "portrait": (180, 320, 0.62 * 320),
    "wide": (400, 160, 0.45 * 400),
}


def room(args):
    """The phone capture of an object in a room (see the module's docs)."""
    os.makedirs(os.path.join(args.out, "images"), exist_ok=True)
    rng = np.random.default_rng(7)
    # The capture's frame: the scene rotated (z up becomes y up, as nerfstudio's OpenGL worlds often are),
    # scaled by 0.37 and moved, so that nothing about the scene's own frame helps the reader.
    to_capture = 0.37 * np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    offset = np.array([2.0, -1.0, 0.5])
    width, height, focal = ROOM_SHAPES[args.shape]
    frames = []
    for i in range(args.views):
        azimuth = 2.0 * math.pi * i / args.views + rng.uniform(-0.05, 0.05)
        radius = rng.uniform(1.9, 2.6)
        height_above = rng.uniform(0.7, 1.6)
        eye = np.array([radius * math.cos(azimuth), radius * math.sin(azimuth), height_above])
        target = np.array([0.0, 0.1, 0.35]) + rng.uniform(-0.15, 0.15, 3)
        rotation = look_at(eye, target, np.array([0.0, 0.0, 1.0]))
        frames.append({"file_path": f"images/frame_{i:03d}.png", "matrix": camera_to_world(rotation, eye)})

    def write(matrix_of):
        transforms = {
            "camera_model": "PINHOLE",
            "fl_x": focal,
            "fl_y": focal,
            "cx": width / 2,
            "cy": height / 2,
            "w": width,
            "h": height,
            "aabb_scale": 16,
            "frames": [{"file_path": f["file_path"], "transform_matrix": matrix_of(f).tolist()} for f in frames],
        }
        with open(os.path.join(args.out, "transforms.json"), "w") as file:
            json.dump(transforms, file, indent=1)

    # Rendered in the scene's frame, then written in the capture's.
    write(lambda f: f["matrix"])
    run_nerfjit(args.nerfjit, args.out, ROOM_TRUTH + ROOM_RENDER.format(width=width, height=height, samples=2048))

    def captured(f):
        rotation = to_capture @ f["matrix"][:3, :3] / 0.37
        return camera_to_world(rotation, to_capture @ f["matrix"][:3, 3] + offset)

    write(captured)
    return f"{args.views} views of {width}x{height} and transforms.json"


def hemisphere_views(rng, count, radius):
    """Camera-to-world matrices of `count` cameras at random on the upper hemisphere, looking at the origin."""
    matrices = []
    for _ in range(count):
        azimuth = rng.uniform(0.0, 2.0 * math.pi)
        elevation = math.asin(rng.uniform(0.05, 0.95))
        eye = radius * np.array(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
        )
        matrices.append(camera_to_world(look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0])), eye))
    return matrices


def synthetic_object(args):
    """The NeRF-synthetic scene (see the module's docs)."""
    from PIL import Image

    rng = np.random.default_rng(11)
    size = args.size
    for split, count in (("train", 80), ("val", 10)):
        matrices = hemisphere_views(rng, count, 4.0311)
        transforms = {
            "camera_angle_x": 0.6911112070083618,
            "frames": [
                {"file_path": f"./{split}/r_{i}", "transform_matrix": m.tolist()} for i, m in enumerate(matrices)
            ],
        }
        with open(os.path.join(args.out, f"transforms_{split}.json"), "w") as file:
            json.dump(transforms, file, indent=1)
        script = OBJECT_TRUTH + "".join(
            OBJECT_RENDER.format(split=split, size=size, samples=1024, bg=bg) for bg in (0, 1)
        )
        for bg in (0, 1):
            os.makedirs(os.path.join(args.out, f"{split}_{bg}"), exist_ok=True)
        os.makedirs(os.path.join(args.out, split), exist_ok=True)
        run_nerfjit(args.nerfjit, args.out, script)
        # On black a pixel is α·c, on white α·c + 1 − α: α and c from the two.
        for i in range(count):
            black, white = (
                np.asarray(Image.open(os.path.join(args.out, f"{split}_{bg}", f"r_{i:03d}.png")), dtype=np.float64)
                / 255.0
                for bg in (0, 1)
            )
            alpha = np.clip(1.0 - (white - black).mean(axis=2), 0.0, 1.0)
            color = np.clip(black / np.maximum(alpha, 1e-6)[..., None], 0.0, 1.0)
            rgba = np.concatenate([color, alpha[..., None]], axis=2)
            Image.fromarray(np.round(rgba * 255.0).astype(np.uint8), "RGBA").save(
                os.path.join(args.out, split, f"r_{i}.png")
            )
        for bg in (0, 1):
            shutil.rmtree(os.path.join(args.out, f"{split}_{bg}"))
    return f"80 training and 10 validation views of {size}x{size} RGBA, transforms_train.json and transforms_val.json"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", choices=["room", "object"])
    parser.add_argument("--out", required=True, help="folder to write the data set into")
    parser.add_argument("--views", type=int, default=64, help="room: the capture's views")
    parser.add_argument("--size", type=int, default=800, help="object: the views' width and height")
    parser.add_argument("--shape", choices=sorted(ROOM_SHAPES), default="landscape", help="room: the photos' shape")
    parser.add_argument("--nerfjit", default="target/release/nerfjit")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    wrote = room(args) if args.scene == "room" else synthetic_object(args)
    print(f"wrote {wrote} to {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
