"""Gradients of random scripts against JAX's and torch's autodiff, implementations independent of nerfjit's:
each script is a random expression over a point's coordinates and two params, written once as a `.sdf`
function and once for the other library; the values, the gradients in the points and the vector-Jacobian
products in the params agree to float32 precision (torch's through `nerfjit.torch.ScriptModule`)."""

import random

import numpy as np
import pytest

jax = pytest.importorskip("jax")
jnp = jax.numpy

import nerfjit  # noqa: E402

# (nerfjit's spelling, JAX's), each defined and smooth on all of R (or made so).
UNARY = [
    ("sin({})", "jnp.sin({})"),
    ("cos({})", "jnp.cos({})"),
    ("tanh({})", "jnp.tanh({})"),
    ("sigmoid({})", "jax.nn.sigmoid({})"),
    ("softplus({})", "jax.nn.softplus({})"),
    ("exp(-({}) * ({}))", "jnp.exp(-({}) * ({}))"),
    ("sqrt(({}) * ({}) + 1.0)", "jnp.sqrt(({}) * ({}) + 1.0)"),
    ("log(({}) * ({}) + 0.5)", "jnp.log(({}) * ({}) + 0.5)"),
]
# Written alike in both: x + y, x − y, x·y, x / (1 + y²).
BINARY = ["({0} + {1})", "({0} - {1})", "({0} * {1})", "({0} / (1.0 + {1} * {1}))"]
LEAVES = [("p.x", "p[0]"), ("p.y", "p[1]"), ("p.z", "p[2]"), ("a", "a"), ("b", "b")]


def expression(rng: random.Random, depth: int):
    """A random expression: (nerfjit text, JAX text)."""
    if depth == 0 or (depth < 5 and rng.random() < 0.2):
        if rng.random() < 0.2:
            c = f"{rng.uniform(-2, 2):.3f}"
            return c, f"C({c})"  # C: a constant as the other library takes it
        return rng.choice(LEAVES)
    if rng.random() < 0.45:
        mine, theirs = rng.choice(UNARY)
        x, y = expression(rng, depth - 1)
        return mine.format(*[x] * mine.count("{}")), theirs.format(*[y] * theirs.count("{}"))
    form = rng.choice(BINARY)
    (x1, y1), (x2, y2) = expression(rng, depth - 1), expression(rng, depth - 1)
    return form.format(x1, x2), form.format(y1, y2)


@pytest.mark.parametrize("seed", range(25))
def test_a_random_script_differentiates_as_jax_does(seed):
    rng = random.Random(seed)
    mine, theirs = expression(rng, depth=5)
    a, b = rng.uniform(-1, 1), rng.uniform(-1, 1)
    script = nerfjit.Script(f"param a: f32 = {a}\nparam b: f32 = {b}\nfn f(p: vec3) -> f32 = {mine}\n")
    f = eval(f"lambda p, a, b: {theirs}", {"jnp": jnp, "jax": jax, "C": float})  # noqa: S307 (our own text)

    points = np.random.default_rng(seed).uniform(-1.5, 1.5, size=(256, 3)).astype(np.float32)
    cotangent = np.random.default_rng(seed + 1000).normal(size=256).astype(np.float32)
    a32, b32 = np.float32(a), np.float32(b)
    values = jax.vmap(f, in_axes=(0, None, None))(points, a32, b32)
    d_points = jax.vmap(jax.grad(f), in_axes=(0, None, None))(points, a32, b32)
    d_a, d_b = jax.grad(lambda a, b: jnp.sum(cotangent * jax.vmap(f, in_axes=(0, None, None))(points, a, b)),
                        argnums=(0, 1))(a32, b32)

    scale = 1.0 + np.abs(np.asarray(values)).max()
    context = f"seed {seed}: f(p) = {mine}"
    np.testing.assert_allclose(script.eval("f", points), values, atol=2e-5 * scale, err_msg=context)
    gscale = 1.0 + np.abs(np.asarray(d_points)).max()
    np.testing.assert_allclose(script.grad("f", points), d_points, atol=5e-5 * gscale, err_msg=context)
    _, _, d_params = script.vjp("f", points, cotangent)
    pscale = 1.0 + abs(float(d_a)) + abs(float(d_b))
    np.testing.assert_allclose([d_params["a"], d_params["b"]], [d_a, d_b], atol=2e-4 * pscale, err_msg=context)


def torch_text(jax_text: str) -> str:
    """The JAX expression in torch's spelling."""
    return (jax_text.replace("jax.nn.sigmoid", "torch.sigmoid").replace("jax.nn.softplus", "F.softplus")
            .replace("jnp.", "torch."))


@pytest.mark.parametrize("seed", range(25, 40))
def test_a_random_script_in_torch_differentiates_as_torch_does(seed):
    torch = pytest.importorskip("torch")
    from nerfjit.torch import ScriptModule

    rng = random.Random(seed)
    mine, theirs = expression(rng, depth=5)
    a, b = rng.uniform(-1, 1), rng.uniform(-1, 1)
    module = ScriptModule(f"param a: f32 = {a}\nparam b: f32 = {b}\nfn f(p: vec3) -> f32 = {mine}\n", "f")
    text = torch_text(theirs).replace("p[0]", "p[:, 0]").replace("p[1]", "p[:, 1]").replace("p[2]", "p[:, 2]")
    f = eval(f"lambda p, a, b: {text} + 0 * p[:, 0] + 0 * a + 0 * b",  # noqa: S307 (our own text)
             {"torch": torch, "F": torch.nn.functional, "C": torch.tensor})

    generator = torch.Generator().manual_seed(seed)
    points = (torch.rand(256, 3, generator=generator) * 3 - 1.5).requires_grad_(True)
    weights = torch.randn(256, generator=generator)
    (module(points) * weights).sum().backward()
    twin = points.detach().clone().requires_grad_(True)
    ta, tb = torch.tensor(module.params["a"].item(), requires_grad=True), torch.tensor(module.params["b"].item(), requires_grad=True)
    values = f(twin, ta, tb)
    (values * weights).sum().backward()

    context = f"seed {seed}: f(p) = {mine}"
    scale = 1.0 + values.abs().max().item()
    torch.testing.assert_close(module(points).detach(), values.detach(), atol=2e-5 * scale, rtol=0, msg=context)
    gscale = 1.0 + twin.grad.abs().max().item()
    torch.testing.assert_close(points.grad, twin.grad, atol=5e-5 * gscale, rtol=0, msg=context)
    pscale = 1.0 + ta.grad.abs().item() + tb.grad.abs().item()
    for name, theirs_grad in (("a", ta.grad), ("b", tb.grad)):
        torch.testing.assert_close(module.params[name].grad, theirs_grad, atol=2e-4 * pscale, rtol=0, msg=context)
