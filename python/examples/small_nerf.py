"""A small NeRF from Python: `examples/nerf_lego_small.sdf` (2 × 32 MLP on lego at 128²) trained by nerfjit
while Python follows its metrics, then the trained field rendered from a held-out view with
`nerfjit.load(...).render(...)`, the cameras and images read with `nerfjit.data.load`, and a matplotlib figure
of the PSNR curve, the render and its target.

    python python/examples/small_nerf.py [--data ../shared/data/lego] [--steps 2000] [--out small_nerf]

Writes `small_nerf/small_nerf.png`; Ctrl-C stops training with its checkpoint (run again with --resume).
"""

import argparse
import pathlib

import numpy as np

import nerfjit

ROOT = pathlib.Path(__file__).resolve().parents[2]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(ROOT.parent / "shared/data/lego"))
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--out", default="small_nerf")
    parser.add_argument("--resume", action="store_true")
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    data = pathlib.Path(args.data)
    overrides = [
        f'train.data=blender("{data / "transforms_train.json"}", size: 128, background: [0, 0, 0])',
        f"train.steps={args.steps}",
        "render.size=32",
    ]
    trainer = nerfjit.Trainer(str(ROOT / "examples/nerf_lego_small.sdf"), set=overrides, out=out, resume=args.resume)
    curve = []
    for metrics in trainer.steps(every=100):
        curve.append((metrics["step"], metrics["psnr"]))
        print(f"step {metrics['step']:>5}: loss {metrics['loss']:.5f}, training PSNR {metrics['psnr']:.2f} dB")

    field = nerfjit.load(str(out / "nerf_lego_small.ckpt.safetensors"), background="black")
    views = nerfjit.data.load(data / "transforms_val.json", width=128)
    fx, fy, cx, cy = views["intrinsics"][0]
    image, depth, opacity = field.render(views["c2w"][0], (fx, fy), 128, principal=(cx, cy))
    target = views["images"][0]
    psnr = -10 * np.log10(np.mean((image - target) ** 2))
    print(f"held-out view 0: {psnr:.2f} dB")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(13, 3.3))
    axes[0].plot(*zip(*curve))
    axes[0].set(xlabel="step", ylabel="training PSNR (dB)", title="nerf_lego_small")
    for ax, picture, title in [(axes[1], image, f"render, {psnr:.1f} dB"), (axes[2], target, "held-out view 0"),
                               (axes[3], depth, "expected depth")]:
        ax.imshow(np.clip(picture, 0, 1) if picture.ndim == 3 else picture)
        ax.set(title=title, xticks=[], yticks=[])
    fig.tight_layout()
    fig.savefig(out / "small_nerf.png", dpi=100)
    print(f"wrote {out / 'small_nerf.png'}")


if __name__ == "__main__":
    main()
