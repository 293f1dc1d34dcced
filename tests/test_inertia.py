"""Inertia helpers: principal axes (values and safe gradients), validity checks, shapes, composites."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import expect_error, random_moments, random_rotation

from rigidjax import (
    check_inertia,
    composite_inertia,
    hollow_cylinder,
    hollow_sphere,
    is_physical_inertia,
    parallel_axis,
    principal_axes,
    solid_box,
    solid_cylinder,
    solid_ellipsoid,
    solid_sphere,
    thin_disc,
    thin_rod,
)

BATCH_SHAPES = [(), (1,), (3, 1, 2)]

# Jitted once here: most tests go through these, so each input shape compiles once for the file
# (eager dispatch compiles every primitive separately, several times slower). Eager calls are
# tested where the behaviour differs: error_if raising at call time.
PRINCIPAL_AXES = jax.jit(principal_axes)
IS_PHYSICAL = jax.jit(is_physical_inertia)
CHECK = jax.jit(check_inertia, static_argnames="name")


def tensor_from(moments, rotation):
    return np.einsum("...ij,...j,...kj->...ik", rotation, moments, rotation)


# --- principal_axes ------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_principal_axes_matches_numpy(shape):
    rng = np.random.default_rng(0)
    tensor = tensor_from(random_moments(rng, shape), random_rotation(rng, shape))
    moments, axes = PRINCIPAL_AXES(tensor)
    assert moments.shape == shape + (3,) and axes.shape == shape + (3, 3)
    np.testing.assert_allclose(moments, np.linalg.eigh(tensor)[0], rtol=1e-12, atol=1e-14)
    assert np.all(np.diff(np.asarray(moments), axis=-1) >= 0)
    rebuilt = axes @ (moments[..., :, None] * jnp.swapaxes(axes, -1, -2))
    np.testing.assert_allclose(rebuilt, tensor, atol=1e-13)
    np.testing.assert_allclose(
        jnp.swapaxes(axes, -1, -2) @ axes, np.broadcast_to(np.eye(3), axes.shape), atol=1e-13
    )
    np.testing.assert_allclose(np.linalg.det(axes), 1.0, atol=1e-13)


def test_principal_axes_symmetrises_input():
    rng = np.random.default_rng(1)
    tensor = tensor_from(random_moments(rng), random_rotation(rng))
    skew = np.array([[0.0, 0.3, -0.1], [-0.3, 0.0, 0.2], [0.1, -0.2, 0.0]])
    np.testing.assert_allclose(PRINCIPAL_AXES(tensor + skew)[0], PRINCIPAL_AXES(tensor)[0], atol=1e-13)


def test_principal_axes_right_handed_for_diagonal_and_degenerate():
    for tensor in [np.diag([3.0, 1.0, 2.0]), np.eye(3), np.diag([1.0, 1.0, 2.0]), -np.eye(3)[::-1]]:
        moments, axes = PRINCIPAL_AXES(tensor)
        np.testing.assert_allclose(np.linalg.det(axes), 1.0, atol=1e-14)
        np.testing.assert_allclose(axes @ np.diag(moments) @ axes.T, tensor, atol=1e-14)


def shape_error(fn, name):
    """A wrong shape fails while tracing: ``ValueError`` naming the argument, or, when the test run's
    jaxtyping checks catch it first, their ``TypeCheckError`` (a ``TypeError``)."""
    with pytest.raises((ValueError, TypeError)) as info:
        fn()
    if info.type is ValueError:
        assert name in str(info.value)


def test_principal_axes_rejects_bad_shape():
    shape_error(lambda: principal_axes(np.ones((3, 4))), "tensor")


def sign_invariant_axes_function(axes):
    """A smooth function of the principal axes that does not depend on each axis' sign."""
    w = jnp.array([0.3, -0.7, 0.5], dtype=axes.dtype)
    proj = jnp.einsum("...ik,...i->...k", axes, w)
    return jnp.sum(jnp.array([1.0, 2.0, 3.0], dtype=axes.dtype) * proj**2, axis=-1)


def rebuild(a):
    m, v = principal_axes(a)
    return v @ (m[..., :, None] * jnp.swapaxes(v, -1, -2))


def everything(a):
    """All outputs of principal_axes, and a sign-invariant function of the axes: shape (13,)."""
    m, v = principal_axes(a)
    return jnp.concatenate([m, v.ravel(), sign_invariant_axes_function(v)[None]])


def spectral(a):
    """Functions that do not depend on the choice of axes within a degenerate plane: shape (5,)."""
    m = principal_axes(a)[0]
    r = rebuild(a)
    return jnp.stack([jnp.sum(m), jnp.sum(m**2), jnp.sum(r**2), jnp.linalg.det(r), jnp.sum(m**3)])


def spectral_exact_gradient(a):
    """Gradients of ``spectral``: 1, 2A, 2A, det(A) A^-T, 3A^2."""
    return np.stack([np.eye(3), 2 * a, 2 * a, np.linalg.det(a) * np.linalg.inv(a).T, 3 * a @ a])


@functools.cache
def batched(f):
    """jit(vmap(f)): one compilation for a stack of (3, 3) test matrices."""
    return jax.jit(jax.vmap(f))


def fd_jacobian(f, a, h=1e-6):
    """Central finite differences of ``f`` w.r.t. each entry of the (3, 3) matrix ``a``: (..., 3, 3)."""
    steps = h * np.eye(9).reshape(9, 3, 3)
    values = np.asarray(batched(f)(np.concatenate([a + steps, a - steps])))
    return np.moveaxis((values[:9] - values[9:]) / (2 * h), 0, -1).reshape(values.shape[1:] + (3, 3))


def test_gradients_match_finite_differences_away_from_degeneracy():
    rng = np.random.default_rng(2)
    tensor = tensor_from(np.array([1.0, 1.7, 2.3]), random_rotation(rng))
    fd = fd_jacobian(everything, tensor)
    for jac in (jax.jacfwd, jax.jacrev):
        np.testing.assert_allclose(jax.jit(jac(everything))(tensor), fd, atol=1e-8, err_msg=jac.__name__)
    # The reconstruction is the symmetrising projection.
    eye = np.eye(3)
    sym = 0.5 * (np.einsum("ik,jl->ijkl", eye, eye) + np.einsum("il,jk->ijkl", eye, eye))
    for jac in (jax.jacfwd, jax.jacrev):
        np.testing.assert_allclose(jax.jit(jac(rebuild))(tensor), sym, atol=1e-10, err_msg=jac.__name__)


def degenerate_tensors():
    rng = np.random.default_rng(3)
    rot = random_rotation(rng)
    return {
        "two-fold diagonal": np.diag([1.0, 1.0, 2.0]),
        "two-fold rotated": tensor_from(np.array([1.0, 1.0, 2.0]), rot),
        "two-fold top rotated": tensor_from(np.array([1.0, 2.0, 2.0]), rot),
        "three-fold": 1.5 * np.eye(3),
        "three-fold rotated": tensor_from(np.array([1.5, 1.5, 1.5]), rot),
        "near two-fold": tensor_from(np.array([1.0, 1.0 + 1e-15, 2.0]), rot),
    }


def test_gradients_finite_at_degeneracy():
    names, tensors = zip(*degenerate_tensors().items(), strict=True)
    tensors = np.stack(tensors)
    hessian = batched(jax.hessian(lambda a: jnp.sum(jnp.exp(principal_axes(a)[0]))))
    for label, jac in [
        ("jacfwd", batched(jax.jacfwd(everything))),
        ("jacrev", batched(jax.jacrev(everything))),
        ("hessian", hessian),
    ]:
        values = np.asarray(jac(tensors))
        for name, value in zip(names, values, strict=True):
            assert np.all(np.isfinite(value)), (label, name)


def test_invariant_gradients_right_at_degeneracy():
    cases = degenerate_tensors()
    tensors = np.stack(list(cases.values()))
    for jac in (jax.jacfwd, jax.jacrev):
        grads = np.asarray(batched(jac(spectral))(tensors))
        for name, tensor, g in zip(cases, tensors, grads, strict=True):
            np.testing.assert_allclose(g, spectral_exact_gradient(tensor), atol=1e-10, err_msg=name)
    # The finite differences of these smooth functions agree too.
    for name, tensor, g in zip(cases, tensors, grads, strict=True):
        np.testing.assert_allclose(g, fd_jacobian(spectral, tensor), atol=1e-7, err_msg=name)


def test_principal_axes_float32():
    rng = np.random.default_rng(4)
    tensor = tensor_from(random_moments(rng, (5,)), random_rotation(rng, (5,))).astype(np.float32)
    moments, axes = PRINCIPAL_AXES(tensor)
    assert moments.dtype == jnp.float32 and axes.dtype == jnp.float32
    np.testing.assert_allclose(moments, np.linalg.eigh(tensor.astype(np.float64))[0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(axes), 1.0, atol=1e-5)
    grad = jax.jit(jax.grad(lambda a: jnp.sum(sign_invariant_axes_function(principal_axes(a)[1]))))
    g = grad(np.broadcast_to(np.diag(np.array([1.0, 1.0, 2.0], np.float32)), (2, 3, 3)))
    assert g.dtype == jnp.float32 and np.all(np.isfinite(g))


# --- validity -------------------------------------------------------------------------------------


def physical_examples():
    rng = np.random.default_rng(5)
    rot = random_rotation(rng)
    disc = np.asarray(thin_disc(2.0, 0.3))
    rod_cross = composite_inertia(
        np.array([1.0, 1.0, 1.0]),
        np.zeros((3, 3)),
        np.stack([thin_rod(1.0, 2.0)] * 3),
        np.stack(
            [
                np.eye(3),
                np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
                np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
            ]
        ),
    )[2]
    return {
        "box": solid_box(3.0, np.array([0.1, 0.2, 0.3])),
        "sphere": solid_sphere(1.0, 0.5),
        "disc (flat plate, exact equality)": disc,
        "disc rotated tensor": tensor_from(disc, rot),
        "rod cross": rod_cross,
        "box tensor": tensor_from(np.asarray(solid_box(1.0, np.array([1.0, 2.0, 3.0]))), rot),
        "batch": solid_ellipsoid(np.array([1.0, 2.0]), np.array([[1.0, 2.0, 3.0], [0.1, 0.1, 0.1]])),
    }


@pytest.mark.parametrize("name", list(physical_examples()))
def test_physical_inertia_passes(name):
    inertia = physical_examples()[name]
    assert np.all(IS_PHYSICAL(inertia))
    np.testing.assert_array_equal(CHECK(inertia), inertia)


def test_check_inertia_eager_passes():
    for inertia in [np.asarray(thin_disc(2.0, 0.3)), np.diag(np.asarray(solid_sphere(1.0, 0.5)))]:
        assert is_physical_inertia(inertia)
        np.testing.assert_array_equal(check_inertia(inertia), inertia)


def test_flat_plate_equality_is_exact_for_thin_disc():
    i = np.asarray(thin_disc(np.array([0.3, 7.0]), np.array([0.11, 3.0])))
    np.testing.assert_array_equal(i[..., 0] + i[..., 1], i[..., 2])


BAD = {
    "negative": (np.array([1.0, -1.0, 1.0]), ["non-positive", "> 0"]),
    "zero (lone thin rod)": (np.asarray(thin_rod(1.0, 1.0)), ["non-positive", "composite"]),
    "triangle": (np.array([1.0, 2.0, 3.5]), ["triangle inequality"]),
    "triangle tensor": (np.diag([3.5, 1.0, 2.0]), ["triangle inequality"]),
    "nan": (np.array([1.0, np.nan, 1.0]), ["NaN"]),
    "inf tensor": (np.diag([1.0, np.inf, 1.0]), ["NaN or infinite"]),
    "non-symmetric": (
        np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
        ["not symmetric", "(3, 1, 3)"],
    ),
    "negative tensor": (np.diag([1.0, 1.0, -0.5]), ["non-positive"]),
    "one bad in batch": (np.array([[[1.0, 1.0, 1.0]], [[1.0, 1.0, 3.0]]]), ["triangle"]),
    "nan beats triangle in batch": (np.array([[1.0, 1.0, 3.0], [np.nan, 1.0, 1.0]])[:, None], ["NaN"]),
}


@pytest.mark.parametrize("name", list(BAD))
def test_non_physical_inertia_rejected(name):
    inertia, words = BAD[name]
    assert not np.all(IS_PHYSICAL(inertia))
    expect_error(lambda: check_inertia(inertia, name="my_inertia"), "my_inertia", *words)
    expect_error(lambda: CHECK(inertia, name="my_inertia"), "my_inertia", *words)


def test_validity_per_body_and_under_vmap():
    inertia = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 3.0], [-1.0, 1.0, 1.0], [1.0, 1.0, 2.0]])
    np.testing.assert_array_equal(IS_PHYSICAL(inertia), [True, False, False, True])
    np.testing.assert_array_equal(jax.vmap(is_physical_inertia)(inertia), [True, False, False, True])
    ok = inertia[[0, 3]]
    np.testing.assert_array_equal(jax.vmap(check_inertia)(ok), ok)
    # The most fundamental problem in the batch is reported: [-1, 1, 1] before the triangle.
    expect_error(lambda: jax.vmap(check_inertia)(inertia), "non-positive")


def test_wrong_shapes_raise_value_error():
    for shape in [(2,), (4, 2), (3, 4), ()]:
        shape_error(lambda shape=shape: check_inertia(np.ones(shape), name="my_inertia"), "my_inertia")
        shape_error(lambda shape=shape: is_physical_inertia(np.ones(shape)), "inertia")


def test_tensor_true_needs_a_tensor_shape():
    """tensor=True with moments of shape (3,) or (4, 3) checked them as moments and passed."""
    for shape in [(3,), (4, 3)]:
        with pytest.raises(ValueError, match=r"my_inertia: tensor=True needs shape \(\.\.\., 3, 3\)"):
            check_inertia(np.ones(shape), name="my_inertia", tensor=True)
    np.testing.assert_array_equal(check_inertia(np.eye(3), tensor=True), np.eye(3))


def test_check_inertia_float32():
    rng = np.random.default_rng(6)
    disc = np.asarray(thin_disc(2.0, 0.3))
    tensor = tensor_from(disc, random_rotation(rng, (20,))).astype(np.float32)
    assert np.all(IS_PHYSICAL(tensor))
    assert CHECK(tensor).dtype == jnp.float32
    assert CHECK(disc.astype(np.float32)).dtype == jnp.float32


# --- shapes ---------------------------------------------------------------------------------------


def test_shapes_textbook_formulas():
    m, r, h = 2.0, 0.5, 3.0
    np.testing.assert_allclose(solid_box(m, np.array([1.0, 2.0, 3.0])), m / 12 * np.array([13.0, 10.0, 5.0]))
    np.testing.assert_allclose(solid_cylinder(m, r, h), [m * (3 * r**2 + h**2) / 12] * 2 + [m * r**2 / 2])
    np.testing.assert_allclose(hollow_cylinder(m, r, h), [m * r**2 / 2 + m * h**2 / 12] * 2 + [m * r**2])
    np.testing.assert_allclose(solid_sphere(m, r), [0.4 * m * r**2] * 3)
    np.testing.assert_allclose(hollow_sphere(m, r), [2 / 3 * m * r**2] * 3)
    np.testing.assert_allclose(
        solid_ellipsoid(m, np.array([1.0, 2.0, 3.0])), m / 5 * np.array([13.0, 10.0, 5.0])
    )
    np.testing.assert_allclose(thin_rod(m, h), [m * h**2 / 12, m * h**2 / 12, 0.0])
    np.testing.assert_allclose(thin_disc(m, r), [m * r**2 / 4] * 2 + [m * r**2 / 2])
    # Limits: a sphere is an ellipsoid with equal semi-axes; a cube is a box.
    np.testing.assert_allclose(solid_ellipsoid(m, np.full(3, r)), solid_sphere(m, r))
    np.testing.assert_allclose(solid_cylinder(m, r, 0.0), thin_disc(m, r))
    np.testing.assert_allclose(solid_cylinder(m, 0.0, h), thin_rod(m, h))


def test_shapes_broadcast_over_batch():
    mass = np.array([[1.0], [2.0]])  # (2, 1)
    radius = np.array([0.1, 0.2, 0.3])  # (3,)
    out = solid_cylinder(mass, radius, 1.0)
    assert out.shape == (2, 3, 3)
    np.testing.assert_allclose(out[1, 2], solid_cylinder(2.0, 0.3, 1.0))
    out = solid_box(mass, np.ones((3, 3)))
    assert out.shape == (2, 3, 3)
    shape_error(lambda: solid_box(1.0, np.ones(2)), "size")


def monte_carlo_moments(points, mass):
    """Principal moments (diagonal of the tensor, axes aligned) and 6-sigma tolerances."""
    x2 = points**2
    samples = np.stack([x2[:, 1] + x2[:, 2], x2[:, 2] + x2[:, 0], x2[:, 0] + x2[:, 1]], axis=-1) * mass
    mean = samples.mean(axis=0)
    sigma = samples.std(axis=0) / np.sqrt(len(samples))
    # Off-diagonal products vanish by symmetry: check them too.
    off = mass * np.stack(
        [points[:, 0] * points[:, 1], points[:, 1] * points[:, 2], points[:, 2] * points[:, 0]], -1
    )
    # (A floor of 1e-10 relative for summation roundoff where a moment has no spread, e.g. a shell's Iz.)
    return mean, 6 * sigma + 1e-10 * mean, off.mean(axis=0), 6 * off.std(axis=0) / np.sqrt(len(off)) + 1e-15


def check_monte_carlo(formula, points, mass):
    mean, tol, off, off_tol = monte_carlo_moments(points, mass)
    assert np.all(np.abs(np.asarray(formula) - mean) <= tol), (formula, mean, tol)
    assert np.all(np.abs(off) <= off_tol)


N = 300_000


def test_box_and_ellipsoid_vs_monte_carlo():
    rng = np.random.default_rng(7)
    mass = 2.5
    size = np.array([0.4, 1.0, 2.2])
    check_monte_carlo(solid_box(mass, size), rng.uniform(-0.5, 0.5, (N, 3)) * size, mass)
    semi = np.array([0.3, 0.8, 1.5])
    cube = rng.uniform(-1.0, 1.0, (2 * N, 3))
    ball = cube[np.sum(cube**2, axis=-1) <= 1.0]
    check_monte_carlo(solid_ellipsoid(mass, semi), ball * semi, mass)


def test_round_shapes_vs_monte_carlo():
    rng = np.random.default_rng(8)
    mass, r, h = 1.3, 0.4, 1.7
    # Solid cylinder: uniform in the disc (r sqrt(u)) times uniform height.
    rho = r * np.sqrt(rng.uniform(size=N))
    phi = rng.uniform(0, 2 * np.pi, N)
    z = rng.uniform(-h / 2, h / 2, N)
    check_monte_carlo(
        solid_cylinder(mass, r, h), np.stack([rho * np.cos(phi), rho * np.sin(phi), z], -1), mass
    )
    check_monte_carlo(thin_disc(mass, r), np.stack([rho * np.cos(phi), rho * np.sin(phi), 0 * z], -1), mass)
    shell = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    check_monte_carlo(hollow_cylinder(mass, r, h), shell, mass)
    g = rng.normal(size=(N, 3))
    unit = g / np.linalg.norm(g, axis=-1, keepdims=True)
    check_monte_carlo(hollow_sphere(mass, r), r * unit, mass)
    check_monte_carlo(solid_sphere(mass, r), r * unit * rng.uniform(size=(N, 1)) ** (1 / 3), mass)


# --- parallel axis and composites -----------------------------------------------------------------


def point_mass_tensor(masses, points, about):
    d = points - about
    return np.einsum(
        "p,pij->ij",
        masses,
        np.einsum("pk,pk->p", d, d)[:, None, None] * np.eye(3) - d[:, :, None] * d[:, None, :],
    )


def test_parallel_axis_vs_point_masses():
    rng = np.random.default_rng(9)
    masses = rng.uniform(0.1, 1.0, 7)
    points = rng.normal(size=(7, 3))
    com = masses @ points / masses.sum()
    i_com = point_mass_tensor(masses, points, com)
    for about in [np.zeros(3), np.array([0.3, -2.0, 1.0])]:
        expected = point_mass_tensor(masses, points, about)
        np.testing.assert_allclose(parallel_axis(i_com, masses.sum(), about - com), expected, atol=1e-12)
        np.testing.assert_allclose(parallel_axis(i_com, masses.sum(), com - about), expected, atol=1e-12)
    # Principal input gives the same as its diagonal tensor, and broadcasting works.
    moments = np.array([1.0, 2.0, 2.5])
    d = rng.normal(size=(4, 1, 3))
    out = parallel_axis(moments, np.array([1.0, 2.0]), d)
    assert out.shape == (4, 2, 3, 3)
    np.testing.assert_allclose(out, parallel_axis(np.diag(moments), np.array([1.0, 2.0]), d))
    np.testing.assert_allclose(
        parallel_axis(moments, 3.0, np.array([0.0, 0.0, 2.0])), np.diag([13.0, 14.0, 2.5])
    )


def t_handle_hand_calculation(m1, r1, l1, h1, m2, r2, l2):
    """Handle along body z with centre at z = h1; cross bar along body x through the origin."""
    M = m1 + m2
    zc = m1 * h1 / M
    d1, d2 = h1 - zc, -zc
    shift = m1 * d1**2 + m2 * d2**2
    handle_t = m1 * (3 * r1**2 + l1**2) / 12
    bar_t = m2 * (3 * r2**2 + l2**2) / 12
    ixx = m2 * r2**2 / 2 + handle_t + shift
    iyy = bar_t + handle_t + shift
    izz = bar_t + m1 * r1**2 / 2
    return M, np.array([0.0, 0.0, zc]), np.diag([ixx, iyy, izz])


def test_t_handle_composite_vs_hand_calculation():
    m1, r1, l1, h1 = 0.03, 0.004, 0.05, 0.03  # handle (stem)
    m2, r2, l2 = 0.02, 0.005, 0.06  # cross bar
    ry90 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # part z -> body x
    masses = np.array([m1, m2])
    coms = np.array([[0.0, 0.0, h1], [0.0, 0.0, 0.0]])
    inertias = jnp.stack([solid_cylinder(m1, r1, l1), solid_cylinder(m2, r2, l2)])
    rotations = np.stack([np.eye(3), ry90])
    M, com, inertia = composite_inertia(masses, coms, inertias, rotations)
    M_ref, com_ref, inertia_ref = t_handle_hand_calculation(m1, r1, l1, h1, m2, r2, l2)
    np.testing.assert_allclose(M, M_ref, rtol=1e-14)
    np.testing.assert_allclose(com, com_ref, atol=1e-16)
    np.testing.assert_allclose(inertia, inertia_ref, rtol=1e-12, atol=1e-18)
    # Same result from tensors already in body axes and no rotations.
    body_tensors = rotations @ (inertias[:, :, None] * np.eye(3)) @ np.swapaxes(rotations, -1, -2)
    np.testing.assert_allclose(
        composite_inertia(masses, coms, body_tensors)[2], inertia_ref, rtol=1e-12, atol=1e-18
    )
    # Three distinct moments: the T-handle has an unstable intermediate axis, and it is physical.
    moments, _ = principal_axes(inertia)
    assert np.all(np.diff(np.asarray(moments)) > 1e-3 * moments[-1])
    assert is_physical_inertia(inertia)


def test_composite_of_point_like_parts_and_batch():
    rng = np.random.default_rng(10)
    masses = rng.uniform(0.1, 1.0, 3)
    points = rng.normal(size=(3, 3))
    com_ref = masses @ points / masses.sum()
    # (3, 3) inertias are three parts' principal moments (a tensor needs the parts axis).
    M, com, inertia = composite_inertia(masses, points, np.zeros((3, 3)))
    np.testing.assert_allclose(M, masses.sum())
    np.testing.assert_allclose(com, com_ref, atol=1e-14)
    np.testing.assert_allclose(inertia, point_mass_tensor(masses, points, com_ref), atol=1e-13)
    # Batch axes after the parts axis agree with a loop.
    bm = rng.uniform(0.1, 1.0, (3, 4))
    bc = rng.normal(size=(3, 4, 3))
    bi = random_moments(rng, (3, 4))
    br = random_rotation(rng, (3, 4))
    Mb, cb, ib = composite_inertia(bm, bc, bi, br)
    assert Mb.shape == (4,) and cb.shape == (4, 3) and ib.shape == (4, 3, 3)
    for k in range(4):
        Mk, ck, ik = composite_inertia(bm[:, k], bc[:, k], bi[:, k], br[:, k])
        np.testing.assert_allclose(ib[k], ik, atol=1e-14)
        np.testing.assert_allclose(cb[k], ck, atol=1e-14)
    shape_error(lambda: composite_inertia(np.ones(2), np.zeros((3, 3)), np.ones((3, 3))), "parts")


def test_float32_stays_float32():
    f32 = np.float32
    assert solid_box(f32(1.0), np.ones(3, f32)).dtype == jnp.float32
    assert thin_disc(np.ones(2, f32), f32(0.2)).dtype == jnp.float32
    assert parallel_axis(np.ones(3, f32), f32(2.0), np.ones(3, f32)).dtype == jnp.float32
    out = composite_inertia(
        np.ones(2, f32), np.zeros((2, 3), f32), np.ones((2, 3), f32), np.stack([np.eye(3, dtype=f32)] * 2)
    )
    assert all(o.dtype == jnp.float32 for o in out)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_triangle_inequality_holds_near_the_float_range(dtype):
    """Moments near the largest float: their sum overflowed to inf, and the triangle inequality
    passed for any moments ([1e307, 1e307, 1.79e308] accepted; in float32 [1e37, 1e37, 3.3e38],
    within a factor 4 of the Earth's moments in kg m^2). Reference: the inequality in exact
    rational arithmetic."""
    from fractions import Fraction

    big = float(np.finfo(dtype).max)
    for moments in ([0.06 * big, 0.06 * big, 0.99 * big], [0.4 * big, 0.4 * big, 0.7 * big]):
        moments = np.asarray(moments, dtype)
        exact = [Fraction(float(m)) for m in moments]
        physical = exact[0] + exact[1] >= exact[2]
        for inertia in (moments, np.diag(moments)):
            assert bool(is_physical_inertia(jnp.asarray(inertia))) == physical, (moments, physical)
            if not physical:
                expect_error(lambda inertia=inertia: check_inertia(jnp.asarray(inertia)), "triangle")
