"""Scripts for W7's gradient taken through the nearest primitive of each kind only.

Reverse mode runs the backward pass of all 20 primitives of W7's scene although only the nearest one's adjoint
is not 0. These scripts compute the same scene's value, and then evaluate one sphere, one box and one torus
whose constants are those of the nearest primitive of their kind, so that the gradient kernel runs 3
backward passes instead of 20. Their gradients are W7's wherever the nearest primitive is unique; their
value is that of the nearest primitive (not the `min` tree's, so they are a measurement, not a product).

    python3 bench/experiments/nearest_primitive_gradient.py /tmp
    nerfjit bench w7 --scene /tmp/nearest_by_index.sdf     # constants chosen by compares on the winner's index
    nerfjit bench w7 --scene /tmp/nearest_along_tree.sdf   # constants chosen by each min node's comparison
    nerfjit bench w7                                       # the scene itself, to compare

Since `dsl::nearest` (which these scripts led to), `nerfjit bench w7` takes the scene's own gradient through
the nearest primitive of each shape; `kernels::with_plain_gradient` is plain reverse mode.
"""

import math
import os
import sys

SPHERES = [((2.5 * math.cos(i * math.pi / 4), 0.4 * math.sin(i), 2.5 * math.sin(i * math.pi / 4)), 0.3 + 0.05 * i)
           for i in range(8)]
BOXES = [((1.2 * math.cos(i * math.pi / 3 + 0.3), -1.0 + 0.4 * i, 1.2 * math.sin(i * math.pi / 3 + 0.3)),
          (0.5, 0.3 + 0.05 * i, 0.4)) for i in range(6)]
TORI = [((0.8 * math.cos(i * math.pi / 3), 1.5 + 0.1 * i, 0.8 * math.sin(i * math.pi / 3)), 0.4 + 0.03 * i,
         0.1 + 0.01 * i) for i in range(6)]
# The scene's min tree (examples/complex_scene.sdf), over the leaves d0 … d19.
TREE = ((((0, 1), (2, 3)), ((4, 5), (6, 7))), ((((8, 9), (10, 11)), ((12, 13), (14, 15))), ((16, 17), (18, 19))))


def num(x):
    return repr(float(x))


def leaves():
    """The primitives' lines, and for each leaf its kind and the constants that vary within its kind."""
    lines, kinds = [], {}
    for k, (c, r) in enumerate(SPHERES):
        lines.append(f"    let d{k} = sphere(p - [{num(c[0])}, {num(c[1])}, {num(c[2])}], {num(r)});")
        kinds[k] = ("sphere", [c[0], c[1], c[2], r])
    for j, (c, s) in enumerate(BOXES):
        k = 8 + j
        lines.append(f"    let d{k} = box(p - [{num(c[0])}, {num(c[1])}, {num(c[2])}], [{num(s[0])}, {num(s[1])}, {num(s[2])}]);")
        kinds[k] = ("box", [c[0], c[1], c[2], s[1]])
    for j, (c, big, small) in enumerate(TORI):
        k = 14 + j
        lines.append(f"    let d{k} = torus_y(p - [{num(c[0])}, {num(c[1])}, {num(c[2])}], {num(big)}, {num(small)});")
        kinds[k] = ("torus", [c[0], c[1], c[2], big, small])
    return lines, kinds


def shadows(constants, flags):
    """One primitive of each kind with the chosen constants, and the nearest kind's value."""
    s, b, t = constants["sphere"], constants["box"], constants["torus"]
    return [
        f"    let s0 = sphere(p - vec3({s[0]}, {s[1]}, {s[2]}), {s[3]});",
        f"    let s1 = box(p - vec3({b[0]}, {b[1]}, {b[2]}), vec3(0.5, {b[3]}, 0.4));",
        f"    let s2 = torus_y(p - vec3({t[0]}, {t[1]}, {t[2]}), {t[3]}, {t[4]});",
        f"    select({flags['sphere']}, s0, select({flags['box']}, s1, s2))",
    ]


def by_index():
    lines, kinds = leaves()
    count = [0]

    def walk(node):
        if isinstance(node, int):
            return f"d{node}", f"{node}.0"
        (vx, ix), (vy, iy) = walk(node[0]), walk(node[1])
        j = count[0]
        count[0] += 1
        lines.append(f"    let v{j} = min({vx}, {vy});")
        lines.append(f"    let i{j} = select({vy} < {vx}, {iy}, {ix});")
        return f"v{j}", f"i{j}"

    _, index = walk(TREE)
    constants = {}
    for kind in ("sphere", "box", "torus"):
        members = [k for k in sorted(kinds) if kinds[k][0] == kind]
        chosen = []
        for slot in range(len(kinds[members[0]][1])):
            expr = num(kinds[members[0]][1][slot])
            for k in members[1:]:
                expr = f"select({index} == {k}.0, {num(kinds[k][1][slot])}, {expr})"
            name = f"{kind}{slot}"
            lines.append(f"    let {name} = {expr};")
            chosen.append(name)
        constants[kind] = chosen
    flags = {"sphere": f"{index} < 8.0", "box": f"{index} < 14.0"}
    return lines + shadows(constants, flags)


def along_tree():
    lines, kinds = leaves()
    count = [0]

    def walk(node):
        """The node's value, each kind's constants of its nearest leaf of that kind, and per kind whether
        the nearest leaf is of that kind."""
        if isinstance(node, int):
            kind, values = kinds[node]
            flags = {k: ("1.0" if k == kind else "0.0") for k in ("sphere", "box", "torus")}
            return f"d{node}", {kind: [num(v) for v in values]}, flags
        (vx, cx, fx), (vy, cy, fy) = walk(node[0]), walk(node[1])
        j = count[0]
        count[0] += 1
        lines.append(f"    let v{j} = min({vx}, {vy});")
        lines.append(f"    let t{j} = {vy} < {vx};")
        constants = {}
        for kind in ("sphere", "box", "torus"):
            if kind in cx and kind in cy:
                chosen = []
                for slot, (a, b) in enumerate(zip(cx[kind], cy[kind])):
                    if a == b:
                        chosen.append(a)
                        continue
                    lines.append(f"    let {kind}{slot}_{j} = select(t{j}, {b}, {a});")
                    chosen.append(f"{kind}{slot}_{j}")
                constants[kind] = chosen
            elif kind in cx or kind in cy:
                constants[kind] = cx.get(kind) or cy[kind]
        flags = {}
        for kind in ("sphere", "box", "torus"):
            a, b = fx[kind], fy[kind]
            if a == b:
                flags[kind] = a
            else:
                lines.append(f"    let {kind}_nearest_{j} = select(t{j}, {b}, {a});")
                flags[kind] = f"{kind}_nearest_{j}"
        return f"v{j}", constants, flags

    _, constants, flags = walk(TREE)
    return lines + shadows(constants, flags)


def main():
    folder = sys.argv[1] if len(sys.argv) > 1 else "."
    for name, body in (("nearest_by_index.sdf", by_index()), ("nearest_along_tree.sdf", along_tree())):
        path = os.path.join(folder, name)
        with open(path, "w") as f:
            f.write("// W7's scene, differentiated through the nearest primitive of each kind only\n")
            f.write("// (bench/experiments/nearest_primitive_gradient.py).\n")
            f.write("fn sdf(p: vec3) -> f32 {\n" + "\n".join(body) + "\n}\n")
        print(path)


if __name__ == "__main__":
    main()
