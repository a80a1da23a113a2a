"""The course's box fit from Python: `examples/train_box.sdf` run by nerfjit (differentiable volume
rendering of four images), its loss and PSNR read from the run's metrics and plotted with matplotlib, and
the learned box's signed distance checked on numpy points against the script's own function.

    python python/examples/box_fit.py [--data ../shared/data/assignment3/box_cameras.json] [--out box_fit]

Writes `box_fit/box_fit.png` (the curves) beside the run's files.
"""

import argparse
import json
import pathlib

import numpy as np

import nerfjit

ROOT = pathlib.Path(__file__).resolve().parents[2]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(ROOT.parent / "shared/data/assignment3/box_cameras.json"))
    parser.add_argument("--out", default="box_fit")
    parser.add_argument("--steps", type=int, default=4000)
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    script = str(ROOT / "examples/train_box.sdf")
    overrides = [f'train.data=views("{args.data}")', f"train.steps={args.steps}", "render.size=64"]
    nerfjit.run(script, set=overrides, out=out)

    summary = json.loads((out / "train_box.json").read_text())
    center, sides = np.array(summary["params"]["center"]), np.array(summary["params"]["sides"])
    print(f"learned box: center {center.round(3)}, sides {sides.round(3)}")

    # The learned params in the script: the box's surface is where its distance is 0.
    box = nerfjit.Script("param center: vec3 = [0, 0, 0]\nparam sides: vec3 = [1, 1, 1]\n"
                         "fn sdf(p: vec3) -> f32 = box(p - center, sides)")
    box.set_param("center", center)
    box.set_param("sides", sides)
    corners = center + 0.5 * sides * np.array([[1, 1, 1], [-1, 1, -1], [1, -1, 1]])
    print("distance at three corners of the learned box:", box.eval("sdf", corners).round(5))

    rows = [json.loads(line) for line in (out / "train_box.metrics.jsonl").read_text().splitlines()]
    steps = [r["step"] for r in rows]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (loss, psnr) = plt.subplots(1, 2, figsize=(9, 3.2))
    loss.semilogy(steps, [r["loss"] for r in rows])
    loss.set(xlabel="step", ylabel="loss", title="the box fit's loss")
    psnr.plot(steps, [r["psnr"] for r in rows])
    psnr.set(xlabel="step", ylabel="PSNR (dB)", title="its training PSNR")
    fig.tight_layout()
    fig.savefig(out / "box_fit.png", dpi=110)
    print(f"wrote {out / 'box_fit.png'}")


if __name__ == "__main__":
    main()
