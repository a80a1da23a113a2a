"""nerfjit from Python: `.sdf` scene scripts compiled by nerfjit's own JIT (Cranelift, for the CPU it runs
on), their functions on numpy arrays, and runs of their blocks.

    import numpy as np
    import nerfjit

    script = nerfjit.Script("fn sdf(p: vec3) -> f32 = length(p) - 1.0")
    script.eval("sdf", np.zeros((4, 3)))        # array([-1., -1., -1., -1.], dtype=float32)
    script.grad("sdf", np.eye(3))               # the unit normals
    nerfjit.run("examples/train_box.sdf", set=["train.steps=200"], out="box")

`nerfjit.torch` (imported on its own, needs torch) makes a script's function a `torch.nn.Module` whose
forward and backward passes are nerfjit's kernels.
"""

from ._nerfjit import NerfjitError, Script, ScriptError, run

__all__ = ["Script", "ScriptError", "NerfjitError", "run"]
