"""A script's function inside torch's autograd, checked against the same expression written in torch."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import nerfjit  # noqa: E402
from nerfjit.torch import ScriptModule  # noqa: E402

SCENE = """
param center: vec3 = [0.1, -0.2, 0.3]
param radius: f32 = 0.7
fn sdf(p: vec3) -> f32 = length(p - center) - radius + 0.1 * sin(3.0 * p.x) * p.y
fn shade(p: vec3) -> vec3 = vec3(sigmoid(p.x * radius), exp(-p.y * p.y), p.z * center.x)
"""


def torch_sdf(p, center, radius):
    return torch.linalg.norm(p - center, dim=1) - radius + 0.1 * torch.sin(3.0 * p[:, 0]) * p[:, 1]


def torch_shade(p, center, radius):
    return torch.stack([torch.sigmoid(p[:, 0] * radius), torch.exp(-p[:, 1] ** 2), p[:, 2] * center[0]], dim=1)


@pytest.mark.parametrize("name, reference", [("sdf", torch_sdf), ("shade", torch_shade)])
def test_forward_and_backward_equal_torch_autograd(name, reference):
    module = ScriptModule(nerfjit.Script(SCENE), name)
    points = torch.randn(500, 3, dtype=torch.float32, generator=torch.Generator().manual_seed(1), requires_grad=True)
    mine = module(points)
    weights = torch.randn(mine.shape, generator=torch.Generator().manual_seed(2))
    (mine * weights).sum().backward()

    twin = points.detach().clone().requires_grad_(True)
    center = torch.tensor([0.1, -0.2, 0.3], requires_grad=True)
    radius = torch.tensor(0.7, requires_grad=True)
    theirs = reference(twin, center, radius)
    (theirs * weights).sum().backward()

    torch.testing.assert_close(mine, theirs.detach(), rtol=1e-5, atol=2e-6)
    torch.testing.assert_close(points.grad, twin.grad, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(module.params["center"].grad, center.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(module.params["radius"].grad, radius.grad, rtol=1e-4, atol=1e-4)


def test_float64_points_keep_their_dtype_and_gradcheck_holds():
    module = ScriptModule(SCENE, "sdf")
    points = torch.randn(20, 3, dtype=torch.float64, requires_grad=True)
    out = module(points)
    assert out.dtype == torch.float64 and out.shape == (20,)
    # float32 kernels: gradcheck with float32-sized tolerances.
    assert torch.autograd.gradcheck(lambda p: module(p), (points,), eps=1e-3, atol=2e-3, rtol=1e-3)


def test_a_torch_optimizer_fits_the_scripts_params():
    """Adam on the module's params fits a sphere to points on a sphere of radius 1.3 about (0.5, 0, -0.2)."""
    module = ScriptModule("param center: vec3 = [0, 0, 0]\nparam radius: f32 = 1.0\n"
                          "fn sdf(p: vec3) -> f32 = length(p - center) - radius", "sdf")
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(2000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    surface = torch.from_numpy(1.3 * directions + [0.5, 0.0, -0.2]).float()
    optimizer = torch.optim.Adam(module.parameters(), lr=0.02)
    for _ in range(400):
        optimizer.zero_grad()
        loss = module(surface).pow(2).mean()
        loss.backward()
        optimizer.step()
    torch.testing.assert_close(module.params["radius"].detach(), torch.tensor(1.3), atol=5e-3, rtol=0)
    torch.testing.assert_close(module.params["center"].detach(), torch.tensor([0.5, 0.0, -0.2]), atol=5e-3, rtol=0)


def test_second_derivatives_in_the_points_equal_torch_autograd():
    """An eikonal loss on the gradient in the points, differentiated again in the points and the params."""
    module = ScriptModule(nerfjit.Script(SCENE), "sdf")
    points = torch.randn(300, 3, generator=torch.Generator().manual_seed(3), requires_grad=True)
    (normals,) = torch.autograd.grad(module(points).sum(), points, create_graph=True)
    eikonal = (normals.norm(dim=1) - 1).pow(2).mean()
    eikonal.backward()

    twin = points.detach().clone().requires_grad_(True)
    center = torch.tensor([0.1, -0.2, 0.3], requires_grad=True)
    radius = torch.tensor(0.7, requires_grad=True)
    (theirs,) = torch.autograd.grad(torch_sdf(twin, center, radius).sum(), twin, create_graph=True)
    (theirs.norm(dim=1) - 1).pow(2).mean().backward()

    torch.testing.assert_close(normals.detach(), theirs.detach(), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(points.grad, twin.grad, rtol=1e-3, atol=1e-5)
    torch.testing.assert_close(module.params["center"].grad, center.grad, rtol=1e-3, atol=1e-5)


def test_a_vector_functions_double_backward_checks_out():
    """gradgradcheck of a vector function: second derivatives in the points and the cotangent."""
    module = ScriptModule(SCENE, "shade")
    points = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradgradcheck(lambda p: module(p), (points,), eps=1e-3, atol=5e-3, rtol=1e-3)


def test_a_loss_on_the_params_gradient_is_refused():
    module = ScriptModule(SCENE, "sdf")
    points = torch.randn(4, 3)
    (d_radius,) = torch.autograd.grad(module(points).sum(), module.params["radius"], create_graph=True)
    with pytest.raises(RuntimeError, match="params' gradients is not differentiable through nerfjit"):
        d_radius.pow(2).backward()
