"""`nerfjit.Script`: compiling, params, and functions on numpy arrays checked against closed forms and
central differences."""

import numpy as np
import pytest

import nerfjit

SCENE = """
param center: vec3 = [0.1, -0.2, 0.3]
param radius: f32 = 0.7
param m: mat<2, 3> = xavier(seed: 1)
fn sdf(p: vec3) -> f32 = length(p - center) - radius + 0.1 * sin(3.0 * p.x) * p.y
fn feature(p: vec3) -> vec2 = tanh(dense(m, p))
fn shade(p: vec3, d: vec3) -> vec3 = vec3(sigmoid(dot(p, d)), exp(-p.y * p.y) * d.z, p.z * p.x)
"""


def reference_sdf(p, center=(0.1, -0.2, 0.3), radius=0.7):
    return np.linalg.norm(p - np.asarray(center), axis=1) - radius + 0.1 * np.sin(3.0 * p[:, 0]) * p[:, 1]


@pytest.fixture
def script():
    return nerfjit.Script(SCENE)


@pytest.fixture
def points():
    return np.random.default_rng(7).normal(size=(1000, 3))


def central_differences(f, p, h=1e-3):
    """The Jacobian of f (N, ...) -> (N, m) at p (N, k) by central differences in float64: (N, m, k)."""
    columns = []
    for j in range(p.shape[1]):
        step = np.zeros_like(p)
        step[:, j] = h
        columns.append((f(p + step) - f(p - step)) / (2 * h))
    return np.stack(columns, axis=-1)


def test_functions_and_params_read_as_the_script_declares_them(script):
    assert script.functions == [
        "fn sdf(p: vec3) -> f32",
        "fn feature(p: vec3) -> vec2",
        "fn shade(p: vec3, d: vec3) -> vec3",
    ]
    params = script.params
    assert list(params) == ["center", "radius", "m"]
    assert params["radius"].shape == () and params["radius"] == np.float32(0.7)
    assert params["m"].shape == (2, 3) and np.all(params["m"] != 0) and np.all(abs(params["m"]) <= 1.1)
    np.testing.assert_array_equal(params["center"], np.float32([0.1, -0.2, 0.3]))


def test_values_match_the_closed_form_for_any_float_array(script, points):
    values = script.eval("sdf", points)
    assert values.dtype == np.float32 and values.shape == (1000,)
    np.testing.assert_allclose(values, reference_sdf(points), atol=2e-6)
    # float32, float64, Fortran order and lists give the same values.
    for same in (points.astype(np.float32), np.asfortranarray(points), points.tolist()):
        np.testing.assert_array_equal(script.eval("sdf", same), values)
    m = script.params["m"]
    np.testing.assert_allclose(script.eval("feature", points), np.tanh(points @ m.T), atol=2e-6)


def test_gradients_match_central_differences(script, points):
    grad = script.grad("sdf", points)
    assert grad.shape == (1000, 3)
    expected = central_differences(lambda p: reference_sdf(p)[:, None], points)[:, 0, :]
    np.testing.assert_allclose(grad, expected, atol=2e-4)
    # Two inputs (6 scalars a point), three outputs: the Jacobian (N, 3, 6).
    both = np.concatenate([points, np.random.default_rng(8).normal(size=(1000, 3))], axis=1)
    jacobian = script.grad("shade", both)
    assert jacobian.shape == (1000, 3, 6)
    numeric = central_differences(lambda q: script.eval("shade", q).astype(np.float64), both)
    np.testing.assert_allclose(jacobian, numeric, atol=5e-3)


def test_vector_jacobian_products_in_points_and_params(script, points):
    cotangent = np.random.default_rng(9).normal(size=1000).astype(np.float32)
    values, d_points, d_params = script.vjp("sdf", points, cotangent)
    np.testing.assert_array_equal(values, script.eval("sdf", points))
    np.testing.assert_allclose(d_points, cotangent[:, None] * script.grad("sdf", points), rtol=1e-5, atol=1e-6)
    # d/d radius of Σ cᵢ sdfᵢ is −Σ cᵢ; d/d center is −Σ cᵢ (p − c)/|p − c|.
    offset = points - np.array([0.1, -0.2, 0.3])
    unit = offset / np.linalg.norm(offset, axis=1, keepdims=True)
    np.testing.assert_allclose(d_params["radius"], -cotangent.sum(), rtol=1e-4)
    np.testing.assert_allclose(d_params["center"], -(cotangent[:, None] * unit).sum(axis=0), rtol=1e-3, atol=1e-3)
    np.testing.assert_array_equal(d_params["m"], np.zeros((2, 3), np.float32))


def test_set_param_changes_what_functions_compute(script, points):
    script.set_param("radius", 0.25)
    script.set_param("center", [0.0, 0.0, 0.0])
    np.testing.assert_allclose(script.eval("sdf", points), reference_sdf(points, (0, 0, 0), 0.25), atol=2e-6)
    with pytest.raises(KeyError, match="no param 'radius2': the script's params are center, radius, m"):
        script.set_param("radius2", 1.0)
    with pytest.raises(ValueError, match=r"param 'm' is mat<2, 3> \(6 values\)"):
        script.set_param("m", np.zeros(5))
    with pytest.raises(ValueError, match="must be finite"):
        script.set_param("radius", np.nan)


def test_bad_scripts_and_calls_raise_clear_errors(script):
    with pytest.raises(nerfjit.ScriptError) as error:
        nerfjit.Script("fn sdf(p: vec3) -> f32 = lenght(p)")
    message = str(error.value)
    assert "unknown function 'lenght'" in message and "^^^^^^" in message and "did you mean 'length'?" in message
    assert "<text>:1:26" in message
    with pytest.raises(nerfjit.ScriptError, match="no function 'sdff'"):
        script.eval("sdff", np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"sdf reads 3 scalars per point: pass an array of shape \(N, 3\)"):
        script.eval("sdf", np.zeros((2, 2)))
    with pytest.raises(ValueError, match="cotangent"):
        script.vjp("sdf", np.zeros((2, 3)), np.zeros(3))
    with pytest.raises(nerfjit.NerfjitError, match="missing.sdf"):
        nerfjit.Script("missing.sdf")
    # Arrays that are not numbers, or not of points, are refused by numpy's conversion or by shape.
    with pytest.raises((TypeError, ValueError)):
        script.eval("sdf", np.array([["a", "b", "c"]]))
    with pytest.raises(TypeError, match="points must be real numbers, not complex"):
        script.eval("sdf", np.array([[1 + 2j, 0, 0]]))
    with pytest.raises(ValueError, match=r"pass an array of shape \(N, 3\)"):
        script.eval("sdf", np.zeros((2, 3, 1)))
    # Non-finite points give non-finite values, nothing worse.
    assert np.isnan(script.eval("sdf", np.array([[np.nan, 0, 0]]))[0])
    assert script.eval("sdf", np.zeros((0, 3))).shape == (0,)


def test_scripts_load_from_files_examples_and_overrides(tmp_path):
    path = tmp_path / "ball.sdf"
    path.write_text("const r = 1.0\nfn sdf(p: vec3) -> f32 = length(p) - r\n")
    points = np.array([[2.0, 0.0, 0.0]])
    assert nerfjit.Script(str(path)).eval("sdf", points)[0] == 1.0
    assert nerfjit.Script(str(path), set=["r=1.5"]).eval("sdf", points)[0] == 0.5
    torus = nerfjit.Script("torus")
    assert torus.eval("sdf", np.array([[1.0, 0.0, 0.0]]))[0] == pytest.approx(-0.25)


def test_large_batches_run_over_every_core_to_the_same_values(script):
    points = np.random.default_rng(3).normal(size=(100_003, 3))
    values = script.eval("sdf", points)
    np.testing.assert_allclose(values, reference_sdf(points), atol=3e-6)
    _, _, d_params = script.vjp("sdf", points, np.ones(len(points)))
    np.testing.assert_allclose(d_params["radius"], -len(points), rtol=1e-6)
