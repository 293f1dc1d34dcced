"""quat_log, quat_slerp and quat_angle_between against scipy's Rotation (as_rotvec, Slerp,
magnitude), mpmath at angles where the usual formulas lose digits, and central differences for
their gradients; their bad input and their behaviour at the identity and at half a turn."""

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from rigidjax import kinematics as kin

RNG = np.random.default_rng(11)


def _random_quats(n):
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _scipy(q):
    return Rotation.from_quat(np.roll(np.asarray(q), -1, axis=-1))  # scipy is scalar-last


def _same_rotation(a, b):
    """Largest difference of two quaternion arrays up to the sign of each quaternion."""
    a, b = np.asarray(a), np.asarray(b)
    return np.max(np.minimum(np.abs(a - b).max(axis=-1), np.abs(a + b).max(axis=-1)))


def test_log_is_scipys_rotation_vector_and_inverts_exp():
    q = _random_quats(500)
    q[:250] *= -1  # both signs of the same rotations give the same vector
    theta = kin.quat_log(q)
    np.testing.assert_allclose(theta, _scipy(q).as_rotvec(), rtol=0, atol=2e-15)
    assert np.all(np.linalg.norm(theta, axis=-1) <= np.pi + 1e-15)
    assert _same_rotation(kin.quat_exp(theta), q) < 2e-15
    # A quaternion off unit norm means the rotation of q / |q|.
    np.testing.assert_allclose(kin.quat_log(3.0 * q[:5]), theta[:5], rtol=0, atol=2e-15)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-7, 2e-4, 0.3, np.pi - 1e-6, np.pi])
def test_log_at_small_angles_and_half_a_turn_against_mpmath(angle):
    axis = np.array([0.36, -0.48, 0.8])
    mpmath.mp.dps = 40
    half = mpmath.mpf(angle) / 2
    q = np.array([float(mpmath.cos(half))] + [float(mpmath.sin(half) * mpmath.mpf(a)) for a in axis])
    # The rotation vector of the float64 quaternion as given, in 40 digits: 2 atan2(|v|, w) v / |v|.
    v = [mpmath.mpf(float(x)) for x in q[1:]]
    s = mpmath.sqrt(sum(x * x for x in v))
    scale = 2 * mpmath.atan2(s, mpmath.mpf(float(q[0]))) / s if s else mpmath.mpf(2)
    expected = np.array([float(scale * x) for x in v])
    np.testing.assert_allclose(kin.quat_log(q), expected, rtol=4e-16, atol=1e-300)


def test_log_gradient_is_finite_and_matches_central_differences():
    def total(q):
        return jnp.sum(kin.quat_log(q) * jnp.array([1.0, -2.0, 0.5]))

    # The identity: log(1 + (0, v)) = 2 v to first order; the w-derivative of a normalised input is 0.
    np.testing.assert_allclose(jax.grad(total)(jnp.array([1.0, 0.0, 0.0, 0.0])), [0.0, 2.0, -4.0, 1.0])
    h = 1e-6
    for q in [np.array([1.0, 2e-5, -1e-5, 3e-5]), _random_quats(1)[0], np.array([1e-3, 0.6, 0.0, 0.8])]:
        q = q / np.linalg.norm(q)
        central = [(total(q + h * e) - total(q - h * e)) / (2 * h) for e in np.eye(4)]
        np.testing.assert_allclose(jax.grad(total)(jnp.asarray(q)), central, rtol=1e-7, atol=1e-8)


def test_angle_between_is_scipys_magnitude_and_keeps_small_angles():
    p, q = _random_quats(500), _random_quats(500)
    expected = (_scipy(p).inv() * _scipy(q)).magnitude()
    np.testing.assert_allclose(kin.quat_angle_between(p, q), expected, rtol=0, atol=4e-15)
    np.testing.assert_allclose(kin.quat_angle_between(p, -q), expected, rtol=0, atol=4e-15)
    # 1e-9 rad apart: exact to roundoff, where 2 acos(|p . q|) gives ~2e-8.
    small = kin.quat_exp(np.array([0.0, 1e-9, 0.0]))
    np.testing.assert_allclose(kin.quat_angle_between(p[0], kin.quat_multiply(p[0], small)), 1e-9, rtol=1e-7)
    assert np.max(kin.quat_angle_between(p, p)) < 4e-16  # p* ⊗ p is the identity to roundoff


def test_angle_between_gradient():
    p = jnp.asarray(_random_quats(1)[0])
    # Where the two coincide the angle has a kink, as |x| at 0: a finite gradient of at most 2, not
    # NaN; the squared angle is smooth there, with gradient 0 to roundoff.
    at_kink = jax.grad(kin.quat_angle_between, argnums=1)(p, p)
    assert np.all(np.isfinite(at_kink)) and np.linalg.norm(at_kink) <= 2.0 + 1e-12
    identity = jnp.array([1.0, 0.0, 0.0, 0.0])  # p* ⊗ q exactly the identity: no direction at all
    np.testing.assert_array_equal(
        jax.grad(kin.quat_angle_between, argnums=1)(identity, identity), np.zeros(4)
    )
    squared = jax.grad(lambda q: kin.quat_angle_between(p, q) ** 2)(p)
    np.testing.assert_allclose(squared, np.zeros(4), rtol=0, atol=1e-15)
    q = jnp.asarray(_random_quats(1)[0])
    h = 1e-6
    central = [
        (kin.quat_angle_between(p, q + h * e) - kin.quat_angle_between(p, q - h * e)) / (2 * h)
        for e in np.eye(4)
    ]
    np.testing.assert_allclose(
        jax.grad(kin.quat_angle_between, argnums=1)(p, q), central, rtol=1e-7, atol=1e-9
    )


def test_slerp_is_scipys_slerp_at_a_constant_rate():
    p, q = _random_quats(2)
    fractions = np.linspace(0.0, 1.0, 11)
    path = kin.quat_slerp(p, q, fractions)
    assert path.shape == (11, 4)
    reference = Slerp([0.0, 1.0], _scipy(np.stack([p, q])))(fractions).as_quat()
    assert _same_rotation(path, np.roll(reference, 1, axis=-1)) < 1e-15
    np.testing.assert_allclose(path[0], p, rtol=0, atol=1e-15)
    # One axis at a constant rate: the angle from p grows linearly, also beyond the end points.
    total = kin.quat_angle_between(p, q)
    ahead = np.array([-0.2, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(
        kin.quat_angle_between(p, kin.quat_slerp(p, q, ahead)), np.abs(ahead) * total, rtol=1e-13
    )
    # The shorter arc: -q is the same end rotation.
    assert _same_rotation(kin.quat_slerp(p, -q, fractions), path) < 1e-15


def test_slerp_broadcasts_batches_and_differentiates():
    p, q = _random_quats(6).reshape(2, 3, 4)
    fraction = np.array([0.1, 0.5, 0.9])
    batched = kin.quat_slerp(p, q, fraction)
    for i in range(3):
        assert _same_rotation(batched[i], kin.quat_slerp(p[i], q[i], fraction[i])) < 1e-15
    assert jax.jit(kin.quat_slerp)(p, q, fraction).shape == (3, 4)
    # The rate of the angle from p along the arc is the total angle.
    rate = jax.grad(lambda f: kin.quat_angle_between(p[0], kin.quat_slerp(p[0], q[0], f)))(0.4)
    np.testing.assert_allclose(rate, kin.quat_angle_between(p[0], q[0]), rtol=1e-12)
    # Between identical orientations every fraction is that orientation, with finite derivatives.
    np.testing.assert_allclose(kin.quat_slerp(p[0], p[0], 0.7), p[0], rtol=0, atol=1e-15)
    assert np.all(np.isfinite(jax.jacfwd(kin.quat_slerp, argnums=(0, 1, 2))(p[0], p[0], 0.7)[0]))


def test_float32():
    p, q = (jnp.asarray(x, jnp.float32) for x in _random_quats(2))
    assert kin.quat_slerp(p, q, jnp.float32(0.3)).dtype == jnp.float32
    np.testing.assert_allclose(
        kin.quat_angle_between(p, q), kin.quat_angle_between(p.astype(float), q.astype(float)), rtol=2e-6
    )
    np.testing.assert_allclose(kin.quat_log(q), kin.quat_log(q.astype(float)), rtol=0, atol=2e-6)


@pytest.mark.parametrize(
    "call, words",
    [
        (lambda: kin.quat_log(np.zeros(4)), "quat_log: q has zero norm"),
        (lambda: kin.quat_log(np.array([1.0, np.nan, 0.0, 0.0])), "quat_log: q contains NaN or inf"),
        (lambda: kin.quat_log(np.ones(3)), "q must have shape"),
        (lambda: kin.quat_slerp(np.zeros(4), np.ones(4), 0.5), "quat_slerp: p has zero norm"),
        (lambda: kin.quat_slerp(np.ones(4), np.ones(4), np.nan), "quat_slerp: fraction contains NaN"),
        (lambda: kin.quat_slerp(np.ones((2, 4)), np.ones(4), np.ones(3)), "fraction"),
        (lambda: jax.jit(kin.quat_angle_between)(np.ones(4), np.zeros(4)), "quat_angle_between: q has zero"),
    ],
)
def test_bad_input_is_named(call, words, without_runtime_typecheck):
    with pytest.raises((ValueError, TypeError, jax.errors.JaxRuntimeError)) as raised:
        call()
    assert words in str(raised.value)
