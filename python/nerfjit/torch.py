"""A script's function inside PyTorch's autograd: its forward pass is nerfjit's JIT kernel, its backward
pass the kernel of its vector-Jacobian product (with respect to the points and to every param).

    import torch
    from nerfjit.torch import ScriptModule

    sdf = ScriptModule(nerfjit.Script("scene.sdf"), "sdf")   # the script's params become nn.Parameters
    loss = sdf(points).abs().mean()
    loss.backward()                                           # points.grad, sdf.params["radius"].grad, ...

Second derivatives through nerfjit work for losses on the points' gradient (an eikonal term on
`torch.autograd.grad(sdf(p).sum(), p, create_graph=True)`), by nerfjit's `vjp_backward` kernel; a loss on the
params' gradients is refused, and third derivatives are not supported (torch says so).
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
    and the params, twice in the points (its backward pass is itself differentiable, see `_Vjp`)."""

    @staticmethod
    def forward(ctx, points, script, name, names, *params):
        for param, value in zip(names, params):
            script.set_param(param, _numpy(value))
        values = script.eval(name, _numpy(points))
        ctx.script, ctx.name, ctx.names = script, name, names
        ctx.save_for_backward(points, *params)
        return torch.from_numpy(np.ascontiguousarray(values)).to(points.dtype)

    @staticmethod
    def backward(ctx, cotangent):
        points, *params = ctx.saved_tensors
        d_points, *d_params = _Vjp.apply(points, cotangent, ctx.script, ctx.name, ctx.names, *params)
        return (d_points, None, None, None, *d_params)


class _Vjp(torch.autograd.Function):
    """The vector-Jacobian product of a script's function, as a function of the points, the cotangent and
    the params: `(d_points, *d_params)`. Its own backward pass (torch's double backward: a loss on a
    gradient taken with `create_graph=True`) is nerfjit's `vjp_backward` kernel, in the points, the
    cotangent and the params, for losses on d_points; a loss on d_params itself is refused."""

    @staticmethod
    def forward(ctx, points, cotangent, script, name, names, *params):
        for param, value in zip(names, params):
            script.set_param(param, _numpy(value))
        _, d_points, d_params = script.vjp(name, _numpy(points), _numpy(cotangent))
        ctx.script, ctx.name, ctx.names = script, name, names
        ctx.save_for_backward(points, cotangent, *params)
        grads = [torch.from_numpy(d_params[n]).to(p.dtype).reshape(p.shape) for n, p in zip(names, params)]
        return (torch.from_numpy(d_points).to(points.dtype), *grads)

    @staticmethod
    @once_differentiable
    def backward(ctx, d_points_cotangent, *d_params_cotangents):
        points, cotangent, *params = ctx.saved_tensors
        if any(g is not None and bool(torch.any(g != 0)) for g in d_params_cotangents):
            raise RuntimeError(
                "nerfjit.torch: a loss on the params' gradients is not differentiable through nerfjit "
                "(losses on the points' gradient, such as an eikonal term, are)"
            )
        if d_points_cotangent is None:
            d_points_cotangent = torch.zeros_like(points)
        for param, value in zip(ctx.names, params):
            ctx.script.set_param(param, _numpy(value))
        d_x, d_c, d_params = ctx.script.vjp_backward(
            ctx.name, _numpy(points), _numpy(cotangent), _numpy(d_points_cotangent)
        )
        grads = [torch.from_numpy(d_params[n]).to(p.dtype).reshape(p.shape) for n, p in zip(ctx.names, params)]
        d_c = torch.from_numpy(np.ascontiguousarray(d_c)).to(cotangent.dtype).reshape(cotangent.shape)
        return (torch.from_numpy(d_x).to(points.dtype), d_c, None, None, None, *grads)


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
