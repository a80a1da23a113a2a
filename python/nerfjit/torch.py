"""A script's function inside PyTorch's autograd: its forward pass is nerfjit's JIT kernel, its backward
pass the kernel of its vector-Jacobian product (with respect to the points and to every param).

    import torch
    from nerfjit.torch import ScriptModule

    sdf = ScriptModule(nerfjit.Script("scene.sdf"), "sdf")   # the script's params become nn.Parameters
    loss = sdf(points).abs().mean()
    loss.backward()                                           # points.grad, sdf.params["radius"].grad, ...

Second derivatives through nerfjit (a loss on `torch.autograd.grad(..., create_graph=True)`) are not
supported: the backward pass is once differentiable and says so when differentiated again.
"""

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from ._nerfjit import Script

__all__ = ["ScriptFunction", "ScriptModule"]


def _numpy(tensor):
    return tensor.detach().to("cpu", torch.float32).contiguous().numpy()


class ScriptFunction(torch.autograd.Function):
    """`ScriptFunction.apply(points, script, name, names, *params)`: function `name` of `script` at
    `points` (N, k) with its params `names` set to the tensors `params`; differentiable in the points
    and the params."""

    @staticmethod
    def forward(ctx, points, script, name, names, *params):
        for param, value in zip(names, params):
            script.set_param(param, _numpy(value))
        values = script.eval(name, _numpy(points))
        ctx.script, ctx.name, ctx.names = script, name, names
        ctx.save_for_backward(points, *params)
        return torch.from_numpy(np.ascontiguousarray(values)).to(points.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, cotangent):
        points, *params = ctx.saved_tensors
        for param, value in zip(ctx.names, params):
            ctx.script.set_param(param, _numpy(value))
        _, d_points, d_params = ctx.script.vjp(ctx.name, _numpy(points), _numpy(cotangent))
        grads = [torch.from_numpy(d_params[n]).to(p.dtype).reshape(p.shape) for n, p in zip(ctx.names, params)]
        return (torch.from_numpy(d_points).to(points.dtype), None, None, None, *grads)


class ScriptModule(torch.nn.Module):
    """Function `function` of `script` (a `nerfjit.Script`, or what `Script` takes) as a module: the
    script's params are its `params` (a `ParameterDict`, initialized from the script's values), trained by
    any torch optimizer; `forward(points)` evaluates the function at `points` (N, k)."""

    def __init__(self, script, function):
        super().__init__()
        self.script = script if isinstance(script, Script) else Script(script)
        self.function = function
        values = self.script.params
        self.params = torch.nn.ParameterDict(
            {name: torch.nn.Parameter(torch.from_numpy(np.array(v, dtype=np.float32))) for name, v in values.items()}
        )

    def forward(self, points):
        names = tuple(self.params.keys())
        return ScriptFunction.apply(points, self.script, self.function, names, *self.params.values())
