#!/usr/bin/env python3
"""Checks a glTF binary file that `nerfjit mesh` wrote with two readers of other tools: the Khronos glTF
Validator (validate_gltf.mjs beside this file, on node; `npm ci` here first) must report no error, and
trimesh must open it with the file's vertices and triangles and, for a textured file, its texture at the size
the file's PNG has.

    python3 tests/readers/gltf_check.py FILE.glb [--up z] [--textured] [--color 'np.clip(np.abs(p), 0.02, 0.98)']
        [--vertex-colors SAME.ply]

--up z: the file was written with `--up z`, so the scene (the mesh turned by its node) must stand with the
mesh's z along y.
--color: a numpy expression of the vertices' positions `p` (n×3) giving the colors (n×3 in [0, 1]) that
trimesh must read from the texture at the vertices' UVs, within 1/255 and a rounding.
--vertex-colors: the same mesh written as a PLY with vertex colors (`--color` the same function): the texture
must hold each vertex's color at the vertex's UVs, within 1/255 and a rounding.
"""

import argparse
import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import trimesh


def glb_document(path):
    """The JSON document of a GLB file and its binary chunk, read from the container by hand."""
    data = Path(path).read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data)), (magic, version, length)
    json_length, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    document = json.loads(data[20:20 + json_length])
    bin_length, kind = struct.unpack_from("<I4s", data, 20 + json_length)
    assert kind == b"BIN\0"
    return document, data[28 + json_length:28 + json_length + bin_length]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("file")
    parser.add_argument("--up", choices=["y", "z"], default="y", help="the scene's up axis")
    parser.add_argument("--textured", action="store_true", help="the file must have a texture")
    parser.add_argument("--color", help="numpy expression of p: the colors the texture holds at the vertices")
    parser.add_argument("--vertex-colors", help="a PLY of the same mesh with the colors its vertices must have")
    args = parser.parse_args()

    validator = Path(__file__).with_name("validate_gltf.mjs")
    run = subprocess.run(["node", str(validator), args.file], capture_output=True, text=True)
    if run.returncode not in (0, 1) or not run.stdout.strip():
        sys.exit(f"the glTF validator did not run: {run.stderr.strip()}")
    report = json.loads(run.stdout)
    print(f"glTF validator {report['validator']}: {report['errors']} errors, {report['warnings']} warnings, "
          f"{report['infos']} infos, {report['hints']} hints; {report['vertices']} vertices, "
          f"{report['triangles']} triangles, images {report['images']}, extensions {report['extensions']}")
    for issue in report["issues"]:
        print(f"  {issue}")
    assert report["errors"] == 0, "the glTF validator reports errors"

    document, binary = glb_document(args.file)
    primitive = document["meshes"][0]["primitives"][0]
    vertices = document["accessors"][primitive["attributes"]["POSITION"]]["count"]
    triangles = document["accessors"][primitive["indices"]]["count"] // 3
    scene = trimesh.load(args.file, process=False)
    assert isinstance(scene, trimesh.Scene), type(scene)
    (mesh,) = scene.geometry.values()
    print(f"trimesh {trimesh.__version__}: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles, "
          f"visual {mesh.visual.kind}")
    assert (len(mesh.vertices), len(mesh.faces)) == (vertices, triangles), (vertices, triangles)
    assert report["vertices"] == vertices and report["triangles"] == triangles
    # The scene's box is the mesh's, turned to y up when the scene's up is z.
    turned = mesh.bounds if args.up == "y" else mesh.bounds[:, [0, 2, 1]] * [1, 1, -1]
    assert np.allclose(np.sort(scene.bounds, axis=0), np.sort(turned, axis=0), atol=1e-5), (scene.bounds, turned)
    if not args.textured:
        return
    assert mesh.visual.kind == "texture" and mesh.visual.uv.shape == (vertices, 2), mesh.visual.kind
    view = document["bufferViews"][document["images"][0]["bufferView"]]
    png = binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]]
    size = struct.unpack_from(">II", png, 16)  # the PNG's IHDR: width, height
    texture = mesh.visual.material.baseColorTexture
    print(f"trimesh: texture {texture.size[0]}×{texture.size[1]} ({texture.mode}), the file's PNG {size[0]}×{size[1]}")
    assert texture.size == size
    got = mesh.visual.to_color().vertex_colors[:, :3] / 255.0
    p = np.asarray(mesh.vertices)
    if args.color:
        want = eval(args.color, {"np": np, "p": p})  # noqa: S307 (CI's own expression)
        worst = float(np.abs(got - want).max())
        print(f"trimesh: the texture's colors at the {len(p)} vertices within {worst * 255:.2f}/255 of {args.color}")
        assert worst <= 1.5 / 255, worst
    if args.vertex_colors:
        ply = trimesh.load(args.vertex_colors, process=False)
        # The glTF file's vertices are the PLY's, each repeated for the patches it is a corner of.
        index = {tuple(v): k for k, v in enumerate(np.asarray(ply.vertices, dtype=np.float32))}
        of = np.array([index[tuple(v)] for v in p.astype(np.float32)])
        want = ply.visual.vertex_colors[of, :3] / 255.0
        worst = float(np.abs(got - want).max())
        print(f"trimesh: the texture's colors at the {len(p)} vertices within {worst * 255:.2f}/255 of the colors of "
              f"the {len(ply.vertices)} vertices of {args.vertex_colors}")
        assert worst <= 1.5 / 255, worst


if __name__ == "__main__":
    main()
