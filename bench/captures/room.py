#!/usr/bin/env python3
"""Writes a synthetic phone capture: an object on a floor inside a textured room, walked around.

nerfjit's capture recipe (`examples/instant_capture.sdf`) is meant for captures whose background is part of
the scene: an object on a table in a room, a phone walked around it. `../shared/data` holds no such capture
(DTU's backgrounds are black, fern faces one way), so this script makes one whose answer is known: a truth
scene in `.sdf` (a textured sphere, box and torus on a checkered floor, inside a room of striped walls 3 to 5
units away), rendered by `nerfjit run` from `--views` cameras circling the object at varying heights and
distances, written as a nerfstudio `transforms.json` (OpenGL camera-to-world matrices, `fl_x`/`cx`, and
instant-ngp's `aabb_scale`) in a frame of other units, up axis and origin than the scene's, as a phone's
capture comes out of COLMAP. Train it as the README says for one's own photos:

    python3 bench/captures/room.py --out /tmp/room
    nerfjit run examples/instant_capture.sdf --set 'train.data=nerfstudio("/tmp/room/transforms.json")'

Every 8th view held out (the recipe's `val: holdout(every: 8)`) is the score.
"""

import argparse
import json
import math
import os
import subprocess
import sys

import numpy as np

TRUTH = """\
// The truth of the synthetic room capture (bench/captures/room.py): in the scene's own frame (z up, floor at
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

RENDER = """
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


def look_at(eye, target, up):
    """The OpenGL camera-to-world rotation (x right, y up, z backward) of a camera at eye looking at target."""
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    return np.stack([right, true_up, -forward], axis=1)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder to write transforms.json and images/ into")
    parser.add_argument("--views", type=int, default=64)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--samples", type=int, default=2048, help="samples a ray of the truth renders")
    parser.add_argument("--nerfjit", default="target/release/nerfjit")
    args = parser.parse_args()
    os.makedirs(os.path.join(args.out, "images"), exist_ok=True)
    rng = np.random.default_rng(7)
    # The capture's frame: the scene rotated (z up becomes y up, as nerfstudio's OpenGL worlds often are),
    # scaled by 0.37 and moved, so that nothing about the scene's own frame helps the reader.
    to_capture = 0.37 * np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    offset = np.array([2.0, -1.0, 0.5])
    focal = 0.62 * args.width
    frames = []
    for i in range(args.views):
        azimuth = 2.0 * math.pi * i / args.views + rng.uniform(-0.05, 0.05)
        radius = rng.uniform(1.9, 2.6)
        height = rng.uniform(0.7, 1.6)
        eye = np.array([radius * math.cos(azimuth), radius * math.sin(azimuth), height])
        target = np.array([0.0, 0.1, 0.35]) + rng.uniform(-0.15, 0.15, 3)
        rotation = look_at(eye, target, np.array([0.0, 0.0, 1.0]))
        scene_matrix = np.eye(4)
        scene_matrix[:3, :3], scene_matrix[:3, 3] = rotation, eye
        frames.append({"file_path": f"images/frame_{i:03d}.png", "scene_matrix": scene_matrix})

    def write(matrix_of):
        transforms = {
            "camera_model": "PINHOLE",
            "fl_x": focal,
            "fl_y": focal,
            "cx": args.width / 2,
            "cy": args.height / 2,
            "w": args.width,
            "h": args.height,
            "aabb_scale": 16,
            "frames": [{"file_path": f["file_path"], "transform_matrix": matrix_of(f).tolist()} for f in frames],
        }
        with open(os.path.join(args.out, "transforms.json"), "w") as file:
            json.dump(transforms, file, indent=1)

    # Rendered in the scene's frame, then written in the capture's.
    write(lambda f: f["scene_matrix"])
    with open(os.path.join(args.out, "truth.sdf"), "w") as file:
        file.write(TRUTH + RENDER.format(width=args.width, height=args.height, samples=args.samples))
    nerfjit = os.path.abspath(args.nerfjit)
    subprocess.run([nerfjit, "run", "truth.sdf"], cwd=args.out, check=True)

    def captured(f):
        matrix = np.eye(4)
        matrix[:3, :3] = to_capture @ f["scene_matrix"][:3, :3] / 0.37
        matrix[:3, 3] = to_capture @ f["scene_matrix"][:3, 3] + offset
        return matrix

    write(captured)
    print(f"wrote {args.views} views of {args.width}x{args.height} and transforms.json to {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
