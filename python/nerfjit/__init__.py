"""nerfjit from Python: `.sdf` scene scripts compiled by nerfjit's own JIT (Cranelift, for the CPU it runs
on), their functions on numpy arrays, and runs of their blocks.

    import numpy as np
    import nerfjit

    script = nerfjit.Script("fn sdf(p: vec3) -> f32 = length(p) - 1.0")
    script.eval("sdf", np.zeros((4, 3)))        # array([-1., -1., -1., -1.], dtype=float32)
    script.grad("sdf", np.eye(3))               # the unit normals
    nerfjit.run("examples/train_box.sdf", set=["train.steps=200"], out="box")
    for metrics in nerfjit.Trainer("examples/train_box.sdf", out="box").steps(every=100):
        print(metrics["step"], metrics["loss"])
    field = nerfjit.load("box/train_box.ckpt.safetensors")
    image, depth, opacity = field.render(c2w, focal=50.0, size=64)   # numpy (64, 64, 3), (64, 64), (64, 64)
    bake, report = nerfjit.bake("box/train_box.ckpt.safetensors", "box.bake", tune=30)   # Gaussian splats
    image, depth, opacity = bake.render(c2w, focal=50.0, size=64)    # drawn by the CPU splat renderer
    vertices, faces = nerfjit.Script("torus").mesh("sdf", resolution=64, bounds=1.5)

`nerfjit.data.load(path)` reads a data set's cameras and images as numpy arrays. `nerfjit.torch` (imported
on its own, needs torch) makes a script's function a `torch.nn.Module` whose
forward and backward passes are nerfjit's kernels.
"""

from . import data
from ._nerfjit import Bake, Field, NerfjitError, Script, ScriptError, Steps, bake, load, run
from .training import Trainer

__all__ = [
    "Script", "Field", "Bake", "Trainer", "Steps", "ScriptError", "NerfjitError", "load", "bake", "run", "data",
]
