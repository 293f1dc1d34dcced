"""Kinematics: Euler angles in all twelve sequences, quaternions, and the angular velocity.

Every check compares against something that does not share code with rigidjax: scipy's
``Rotation`` (intrinsic upper-case sequences), a sympy derivation of ``R^T dR/dt``, central finite
differences of scipy matrices, or closed forms transcribed from API.md.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import rigidjax as rj
from rigidjax.kinematics import PROPER_SEQUENCES, SEQUENCES, TAIT_BRYAN_SEQUENCES

N = 8  # samples per batch; one batch size throughout keeps JAX's per-shape compile cache warm
TOL64 = 1e-13
TOL32 = 2e-5
_AXIS = {"x": 0, "y": 1, "z": 2}


# ----------------------------------------------------------------------------------------------
# Shared inputs and independent references
# ----------------------------------------------------------------------------------------------


def is_proper(seq):
    return seq[0] == seq[2]


def random_angles(seq, n, seed, margin=0.1):
    """Angles in scipy's canonical ranges, at least ``margin`` away from gimbal lock."""
    rng = np.random.default_rng(seed)
    phi = rng.uniform(-np.pi, np.pi, n)
    psi = rng.uniform(-np.pi, np.pi, n)
    if is_proper(seq):
        theta = rng.uniform(margin, np.pi - margin, n)
    else:
        theta = rng.uniform(-np.pi / 2 + margin, np.pi / 2 - margin, n)
    return np.stack([phi, theta, psi], axis=-1)


ANGLES = {seq: random_angles(seq, N, seed) for seed, seq in enumerate(SEQUENCES)}
RATES = np.random.default_rng(100).normal(size=(N, 3))
ROTATIONS = Rotation.random(N, rng=np.random.default_rng(101))


def scipy_rot(angles, seq):
    return Rotation.from_euler(seq.upper(), np.asarray(angles, np.float64))


def scipy_quat(rot):
    return rot.as_quat(scalar_first=True)


def assert_quat_close(q, expected, atol):
    """Equal as rotations: ``q = ±expected`` element-wise."""
    q, expected = np.asarray(q), np.asarray(expected)
    sign = np.where(np.sum(q * expected, axis=-1, keepdims=True) < 0, -1.0, 1.0)
    np.testing.assert_allclose(q * sign, expected, rtol=0, atol=atol)


def wrapped(diff):
    """Angle difference mapped to (-pi, pi]."""
    return np.angle(np.exp(1j * np.asarray(diff, np.float64)))


def assert_angles_close(a, b, atol):
    np.testing.assert_allclose(wrapped(np.asarray(a, np.float64) - np.asarray(b, np.float64)), 0.0, atol=atol)


def axial(W):
    """Axial vector of a (near) skew-symmetric matrix: ``W v = w x v``."""
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], -1
    )


def _sym_axis_matrix(axis, a):
    """Active rotation about a coordinate axis, written out by hand (not sympy's passive rot_axis)."""
    c, s = sp.cos(a), sp.sin(a)
    if axis == 0:
        return sp.Matrix([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == 1:
        return sp.Matrix([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return sp.Matrix([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@functools.cache
def sympy_body_omega(seq):
    """``omega_body(angles, rates)`` from ``R^T dR/dt`` with ``R = R_a(phi) R_b(theta) R_c(psi)``."""
    t = sp.Symbol("t")
    funcs = [sp.Function(name)(t) for name in ("phi", "theta", "psi")]
    R = sp.eye(3)
    for axis_name, f in zip(seq, funcs, strict=True):
        R = R * _sym_axis_matrix(_AXIS[axis_name], f)
    W = R.T * R.diff(t)
    angle_syms = sp.symbols("a0:3")
    rate_syms = sp.symbols("r0:3")
    subs = {f.diff(t): r for f, r in zip(funcs, rate_syms, strict=True)}
    W = W.subs(subs).subs(dict(zip(funcs, angle_syms, strict=True)))
    # W must be skew-symmetric; take its axial vector.
    omega = [W[2, 1], W[0, 2], W[1, 0]]
    skew_residual = [W[0, 0], W[1, 1], W[2, 2], W[0, 1] + W[1, 0], W[0, 2] + W[2, 0], W[1, 2] + W[2, 1]]
    f_omega = sp.lambdify((*angle_syms, *rate_syms), omega, "numpy")
    f_resid = sp.lambdify((*angle_syms, *rate_syms), skew_residual, "numpy")

    def body_omega(angles, rates):
        args = [*np.moveaxis(np.asarray(angles, np.float64), -1, 0), *np.moveaxis(np.asarray(rates), -1, 0)]
        out = np.broadcast_arrays(*f_omega(*args))
        resid = np.broadcast_arrays(*f_resid(*args))
        scale = 1.0 + max(np.max(np.abs(a)) for a in args)
        np.testing.assert_allclose(np.stack(resid, -1), 0.0, atol=1e-14 * scale)  # sanity of the derivation
        return np.stack(out, axis=-1)

    return body_omega


def lock_sign(seq, theta):
    """``s`` with ``R = R_a(phi + s psi) R_b(theta)`` at gimbal lock: ``s = e_a . R_b(theta) e_c``."""
    i, j, k = (_AXIS[c] for c in seq)
    return np.sign(Rotation.from_euler(seq[1].upper(), theta).as_matrix()[i, k])


def lock_thetas(seq):
    """Exactly at and 1e-9 from each gimbal lock of ``seq``."""
    if is_proper(seq):
        return [0.0, 1e-9, np.pi - 1e-9, np.pi]
    return [np.pi / 2, np.pi / 2 - 1e-9, -np.pi / 2 + 1e-9, -np.pi / 2]


LOCK_PHI_PSI = np.array(
    [[0.7, -1.9], [-2.5, 2.9], [3.0, 3.1], [0.0, 0.0], [-np.pi, 1.0], [1.2, -np.pi], [-0.3, 0.3], [2.0, 2.0]]
)


def lock_batch(seq):
    """``(N, 3)`` angles: two ``(phi, psi)`` pairs at each of the four ``lock_thetas(seq)``."""
    theta = np.repeat(lock_thetas(seq), 2)
    return np.stack([LOCK_PHI_PSI[:, 0], theta, LOCK_PHI_PSI[:, 1]], axis=-1)


def is_exact_lock(theta):
    return np.isin(theta, [0.0, np.pi, np.pi / 2, -np.pi / 2])


# The code paths of the angle extraction: proper/Tait-Bryan x the two parities of the sequence.
# (Gradient and float32 checks compile a lot per sequence, so they run on these four.)
FOUR_SEQUENCES = ["zxz", "zyz", "xyz", "zyx"]
SLOW = pytest.mark.slow


def fast_tier(values, fast):
    """Parameters ``values``, those not in ``fast`` marked slow: the fast tier (``-m "not slow"``) runs
    every code path once, the full run every case."""
    return [pytest.param(v, marks=() if v in fast else SLOW) for v in values]


# Every sequence in the full run; the four code paths of the angle extraction in the fast tier.
EVERY_SEQUENCE = fast_tier(SEQUENCES, FOUR_SEQUENCES)


# ----------------------------------------------------------------------------------------------
# 1. Conversions against scipy
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seq", EVERY_SEQUENCE)
def test_matrix_and_quat_from_euler_match_scipy(seq):
    # Include angles outside the canonical ranges: the forward map does not care.
    angles = np.concatenate([ANGLES[seq], np.random.default_rng(7).uniform(-7, 7, (8, 3))])
    rot = scipy_rot(angles, seq)
    # In two batches of N: the batch shape of this sequence's other calls (one program per function).
    Rs = [rj.matrix_from_euler(a, seq) for a in (angles[:N], angles[N:])]
    qs = [rj.quat_from_euler(a, seq) for a in (angles[:N], angles[N:])]
    assert all(R.shape == (N, 3, 3) and R.dtype == jnp.float64 for R in Rs)
    assert all(q.shape == (N, 4) and q.dtype == jnp.float64 for q in qs)
    R, q = np.concatenate(Rs), np.concatenate(qs)
    assert len(R) == len(q) == len(angles)
    np.testing.assert_allclose(R, rot.as_matrix(), rtol=0, atol=1e-14)
    assert_quat_close(q, scipy_quat(rot), atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)


def test_default_sequence_is_zxz_and_case_insensitive():
    a = ANGLES["zxz"]
    np.testing.assert_array_equal(rj.matrix_from_euler(a), rj.matrix_from_euler(a, "zxz"))
    np.testing.assert_array_equal(rj.matrix_from_euler(a, "ZXZ"), rj.matrix_from_euler(a, "zxz"))
    # A mix of cases, which scipy refuses (its lower case means extrinsic), is refused too.
    for call in (lambda: rj.matrix_from_euler(a, "ZXz"), lambda: rj.euler_from_quat(np.eye(4)[0], "zXz")):
        with pytest.raises(ValueError, match=r"seq '(ZXz|zXz)' mixes upper and lower case: write it in one"):
            call()
    # API.md: matrix_from_euler(angles, "zxz") = Rz(phi) Rx(theta) Rz(psi); the passive A is its transpose.
    phi, theta, psi = a[0]
    Rz = lambda t: np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])  # noqa: E731
    Rx = lambda t: np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])  # noqa: E731
    np.testing.assert_allclose(rj.matrix_from_euler(a[0]), Rz(phi) @ Rx(theta) @ Rz(psi), atol=1e-15)
    A = Rz(-psi) @ Rx(-theta) @ Rz(-phi)  # Rz(psi) Rx(theta) Rz(phi) in the passive convention
    np.testing.assert_allclose(rj.matrix_from_euler(a[0]).T, A, atol=1e-15)


@pytest.mark.parametrize("seq", EVERY_SEQUENCE)
def test_euler_from_matrix_and_quat_round_trip(seq):
    angles = ANGLES[seq]
    rot = scipy_rot(angles, seq)
    # Inputs come from scipy, the output is turned back into a matrix by scipy.
    from_matrix = np.asarray(rj.euler_from_matrix(rot.as_matrix(), seq))
    from_quat = np.asarray(rj.euler_from_quat(scipy_quat(rot), seq))
    from_neg_quat = np.asarray(rj.euler_from_quat(-scipy_quat(rot), seq))
    expected = rot.as_euler(seq.upper())
    for out in (from_matrix, from_quat, from_neg_quat):
        np.testing.assert_allclose(scipy_rot(out, seq).as_matrix(), rot.as_matrix(), rtol=0, atol=TOL64)
        assert_angles_close(out, expected, atol=1e-12)
        assert_angles_close(out, angles, atol=1e-12)  # inputs were already in canonical ranges
    # Canonical ranges.
    assert np.all(np.abs(from_matrix[:, [0, 2]]) <= np.pi)
    if is_proper(seq):
        assert np.all((from_matrix[:, 1] >= 0) & (from_matrix[:, 1] <= np.pi))
    else:
        assert np.all(np.abs(from_matrix[:, 1]) <= np.pi / 2)
    # rigidjax's own round trip through its forward maps.
    np.testing.assert_allclose(
        rj.matrix_from_euler(rj.euler_from_matrix(rj.matrix_from_euler(angles, seq), seq), seq),
        rot.as_matrix(),
        atol=TOL64,
    )
    assert_quat_close(
        rj.quat_from_euler(rj.euler_from_quat(rj.quat_from_euler(angles, seq), seq), seq),
        scipy_quat(rot),
        atol=TOL64,
    )


@pytest.mark.parametrize("seq", EVERY_SEQUENCE)
def test_euler_from_unnormalised_quat(seq):
    rot = scipy_rot(ANGLES[seq], seq)  # all N: the batch shape of the round trip's program
    out = rj.euler_from_quat(2.5 * scipy_quat(rot), seq)
    assert_angles_close(out, rot.as_euler(seq.upper()), atol=1e-12)


def special_rotations():
    """Identity, half turns about coordinate and oblique axes, and near-half turns (Shepperd branches)."""
    axes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, -1], [1, -2, 3], [-1, -1, -1]], float)
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    rotvecs = [np.zeros(3)]
    for angle in (np.pi, np.pi - 1e-7, 0.5, 1e-8):
        rotvecs.extend(angle * axes)
    return Rotation.from_rotvec(np.array(rotvecs))


def test_quat_from_matrix_and_matrix_from_quat_match_scipy():
    rot = Rotation.concatenate([ROTATIONS, special_rotations()])
    q = np.asarray(rj.quat_from_matrix(rot.as_matrix()))
    assert_quat_close(q, scipy_quat(rot), atol=1e-14)
    assert np.all(q[:, 0] >= 0)  # documented w >= 0
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(rj.matrix_from_quat(scipy_quat(rot)), rot.as_matrix(), atol=1e-15)
    # A quaternion that drifted off unit norm still gives the same (orthogonal) matrix.
    np.testing.assert_allclose(rj.matrix_from_quat(1.01 * scipy_quat(rot)), rot.as_matrix(), atol=1e-14)


def test_quat_from_matrix_derivative_where_two_branches_tie():
    """At an exact quarter turn about an axis (or a third of a turn about a diagonal) two of
    Shepperd's candidates are equal; the derivative averaged them (0 instead of -0.35 along a
    further turn about x, and the Euler angles' theta' came out 0 instead of 1). References: the
    round trip's Jacobian is the unit sphere's tangent projector I - q q^T, and central differences
    of scipy's quaternion and ZXZ angles along a further rotation."""
    round_trip = jax.jacfwd(lambda q: rj.quat_from_matrix(rj.matrix_from_quat(q)))
    for q in (np.full(4, 0.5), np.array([1.0, 1.0, 0.0, 0.0]) / np.sqrt(2.0)):
        np.testing.assert_allclose(round_trip(q), np.eye(4) - np.outer(q, q), atol=1e-14)
    quarter_turn_x = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    hat_x = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

    def turned(t):  # a further rotation by t about space x
        return Rotation.from_rotvec([t, 0.0, 0.0]).as_matrix() @ quarter_turn_x

    h = 1e-6
    for ours, theirs in (
        (rj.quat_from_matrix, lambda m: scipy_quat(Rotation.from_matrix(m))),
        (rj.euler_from_matrix, lambda m: Rotation.from_matrix(m).as_euler("ZXZ")),
    ):
        _, tangent = jax.jvp(ours, (quarter_turn_x,), (hat_x @ quarter_turn_x,))
        central = (theirs(turned(h)) - theirs(turned(-h))) / (2 * h)
        np.testing.assert_allclose(tangent, central, atol=1e-8)


def test_quat_multiply_conjugate_rotate():
    p, r = ROTATIONS, Rotation.random(N, rng=np.random.default_rng(5))
    pq, rq = scipy_quat(p), scipy_quat(r)
    prod = np.asarray(rj.quat_multiply(pq, rq))
    # Composition: p ⊗ r is "apply r first, then p" = P @ R.
    np.testing.assert_allclose(rj.matrix_from_quat(prod), p.as_matrix() @ r.as_matrix(), atol=1e-14)
    assert_quat_close(prod, scipy_quat(p * r), atol=1e-15)
    # Hamilton's rules i j = k, j k = i, k i = j.
    e = np.eye(4)
    np.testing.assert_array_equal(rj.quat_multiply(e[1], e[2]), e[3])
    np.testing.assert_array_equal(rj.quat_multiply(e[2], e[3]), e[1])
    np.testing.assert_array_equal(rj.quat_multiply(e[3], e[1]), e[2])
    # Conjugate is the inverse.
    conj = np.asarray(rj.quat_conjugate(pq))
    np.testing.assert_allclose(rj.quat_multiply(pq, conj), np.broadcast_to(e[0], pq.shape), atol=1e-15)
    np.testing.assert_allclose(rj.matrix_from_quat(conj), np.swapaxes(p.as_matrix(), -1, -2), atol=1e-15)
    assert_quat_close(conj, scipy_quat(p.inv()), atol=1e-15)
    # quat_rotate = R @ v (body -> space).
    v = np.random.default_rng(6).normal(size=(N, 3))
    np.testing.assert_allclose(rj.quat_rotate(pq, v), p.apply(v), atol=1e-14)
    np.testing.assert_allclose(rj.quat_rotate(pq, v), np.einsum("nij,nj->ni", p.as_matrix(), v), atol=1e-14)


# ----------------------------------------------------------------------------------------------
# 2. Angular velocity
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seq", EVERY_SEQUENCE)
def test_body_angular_velocity_matches_sympy(seq):
    angles, rates = ANGLES[seq], RATES
    expected = sympy_body_omega(seq)(angles, rates)
    np.testing.assert_allclose(rj.body_angular_velocity(angles, rates, seq), expected, rtol=0, atol=1e-14)


def test_body_angular_velocity_zxz_formula_from_api():
    angles, rates = ANGLES["zxz"], RATES
    phi, theta, psi = angles.T
    dphi, dtheta, dpsi = rates.T
    expected = np.stack(
        [
            dphi * np.sin(theta) * np.sin(psi) + dtheta * np.cos(psi),
            dphi * np.sin(theta) * np.cos(psi) - dtheta * np.sin(psi),
            dphi * np.cos(theta) + dpsi,
        ],
        axis=-1,
    )
    np.testing.assert_allclose(rj.body_angular_velocity(angles, rates), expected, atol=1e-14)
    np.testing.assert_allclose(rj.body_angular_velocity(angles, rates, "zxz"), expected, atol=1e-14)


def _path(t):
    """A smooth path of Euler angles and its exact time derivative."""
    a0 = np.array([0.3, 1.1, -0.8])
    a1 = np.array([0.9, -0.4, 1.7])
    a2 = np.array([0.5, 0.3, -0.6])
    w = np.array([1.3, 2.1, 0.7])
    return a0 + a1 * t + a2 * np.sin(w * t), a1 + a2 * w * np.cos(w * t)


@pytest.mark.parametrize("seq", EVERY_SEQUENCE)
def test_space_angular_velocity_matches_finite_differences(seq):
    # Seven times on [-1, 1] and one more: N samples, body_angular_velocity's batch shape elsewhere.
    ts = np.append(np.linspace(-1.0, 1.0, 7), 0.5)
    h = 1e-5
    angles, rates = _path(ts[:, None])
    R = scipy_rot(angles, seq).as_matrix()
    dR = (
        scipy_rot(_path(ts[:, None] + h)[0], seq).as_matrix()
        - scipy_rot(_path(ts[:, None] - h)[0], seq).as_matrix()
    ) / (2 * h)
    omega_space_fd = axial(dR @ np.swapaxes(R, -1, -2))
    omega_body_fd = axial(np.swapaxes(R, -1, -2) @ dR)
    np.testing.assert_allclose(rj.space_angular_velocity(angles, rates, seq), omega_space_fd, atol=1e-9)
    np.testing.assert_allclose(rj.body_angular_velocity(angles, rates, seq), omega_body_fd, atol=1e-9)


@pytest.mark.parametrize("seq", EVERY_SEQUENCE)
def test_euler_rates_inverts_body_angular_velocity(seq):
    angles, rates = ANGLES[seq], RATES
    omega = sympy_body_omega(seq)(angles, rates)
    np.testing.assert_allclose(rj.euler_rates(angles, omega, seq), rates, rtol=0, atol=1e-12)
    np.testing.assert_allclose(rj.euler_rates(angles, omega, seq, throw=False), rates, rtol=0, atol=1e-12)
    # And the other way round.
    omega2 = np.random.default_rng(8).normal(size=(N, 3))
    back = sympy_body_omega(seq)(angles, np.asarray(rj.euler_rates(angles, omega2, seq)))
    np.testing.assert_allclose(back, omega2, atol=1e-12)


def test_euler_rates_zxz_closed_form():
    angles = ANGLES["zxz"]
    omega = np.random.default_rng(9).normal(size=(N, 3))
    _, theta, psi = angles.T
    w1, w2, w3 = omega.T
    dphi = (w1 * np.sin(psi) + w2 * np.cos(psi)) / np.sin(theta)
    expected = np.stack([dphi, w1 * np.cos(psi) - w2 * np.sin(psi), w3 - dphi * np.cos(theta)], -1)
    np.testing.assert_allclose(rj.euler_rates(angles, omega), expected, rtol=1e-12, atol=1e-12)


# ----------------------------------------------------------------------------------------------
# 3. Gimbal lock
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seq", EVERY_SEQUENCE)
def test_euler_from_matrix_and_quat_at_gimbal_lock(seq):
    angles = lock_batch(seq)
    theta = angles[:, 1]
    exact = is_exact_lock(theta)
    rot = scipy_rot(angles, seq)
    s = np.array([lock_sign(seq, t) for t in theta])
    determined = angles[:, 0] + s * angles[:, 2]
    for out in (rj.euler_from_matrix(rot.as_matrix(), seq), rj.euler_from_quat(scipy_quat(rot), seq)):
        out = np.asarray(out)
        assert np.all(np.isfinite(out))
        np.testing.assert_allclose(scipy_rot(out, seq).as_matrix(), rot.as_matrix(), rtol=0, atol=2e-15)
        np.testing.assert_allclose(out[:, 1], theta, atol=1e-15)
        assert_angles_close(out[:, 0] + s * out[:, 2], determined, atol=1e-14)
        np.testing.assert_array_equal(out[exact, 2], 0.0)  # documented split psi = 0
    # rigidjax's own forward maps at the lock.
    out = rj.euler_from_quat(rj.quat_from_euler(angles, seq), seq)
    np.testing.assert_allclose(rj.matrix_from_euler(out, seq), rot.as_matrix(), atol=2e-15)


@pytest.mark.parametrize(
    ("seq", "fn", "jac"),
    [
        ("zxz", rj.euler_from_quat, jax.jacfwd),
        ("zxz", rj.euler_from_matrix, jax.jacrev),
        ("xyz", rj.euler_from_quat, jax.jacrev),
        ("xyz", rj.euler_from_matrix, jax.jacfwd),
    ],
    ids=["zxz-quat-fwd", "zxz-matrix-rev", "xyz-quat-rev", "xyz-matrix-fwd"],
)
def test_gradients_finite_at_gimbal_lock(seq, fn, jac):
    angles = lock_batch(seq)
    rot = scipy_rot(angles, seq)
    if fn is rj.euler_from_matrix:
        x, exact_x = rot.as_matrix(), np.asarray(rj.matrix_from_euler(angles, seq))
    else:
        x, exact_x = scipy_quat(rot), np.asarray(rj.quat_from_euler(angles, seq))
    # Odd rows from rigidjax's forward map: at theta = 0 those carry exact zeros (where a plain
    # atan2 or norm has a NaN gradient); even rows carry scipy's roundoff instead.
    x = np.where((np.arange(N) % 2 == 1).reshape((N,) + (1,) * (x.ndim - 1)), exact_x, x)
    J = np.asarray(jax.jit(jax.vmap(jac(functools.partial(fn, seq=seq))))(jnp.asarray(x)))
    assert J.shape == (N, 3) + x.shape[1:]
    assert np.all(np.isfinite(J)), J


@pytest.mark.parametrize(("seq", "via", "jac"), [("zyz", "quat", jax.jacfwd), ("zyx", "matrix", jax.jacrev)])
def test_euler_jacobian_is_identity_away_from_lock(seq, via, jac):
    """The chain rule through angles -> quaternion/matrix -> angles gives the identity."""
    if via == "quat":
        f = lambda a: rj.euler_from_quat(rj.quat_from_euler(a, seq), seq)  # noqa: E731
    else:
        f = lambda a: rj.euler_from_matrix(rj.matrix_from_euler(a, seq), seq)  # noqa: E731
    J = jax.jit(jax.vmap(jac(f)))
    np.testing.assert_allclose(J(jnp.asarray(ANGLES[seq])), np.broadcast_to(np.eye(3), (N, 3, 3)), atol=1e-12)
    # ... and at the lock the Jacobian of the round trip is still finite.
    assert np.all(np.isfinite(np.asarray(J(jnp.asarray(lock_batch(seq))))))


def _lock_plane(seq, angles):
    """Followable directions ``u2, u3`` (from sympy) and the unfollowable normal at ``angles``."""
    body = sympy_body_omega(seq)
    u2 = body(angles, np.array([0.0, 1.0, 0.0]))
    u3 = body(angles, np.array([0.0, 0.0, 1.0]))
    return u2, u3, np.cross(u2, u3)


def _rates_lock_inputs(seq):
    """Angles at both locks of ``seq``, omegas in the followable plane and ones off it."""
    locks = [0.0, np.pi] if is_proper(seq) else [np.pi / 2, -np.pi / 2]
    angles = np.array([[0.4, locks[0], -1.1], [-2.0, locks[1], 0.9]])
    u2, u3, normal = _lock_plane(seq, angles)
    omega_ok = np.array([[0.7], [-0.2]]) * u2 + np.array([[-1.3], [0.8]]) * u3
    return angles, omega_ok, omega_ok + 0.5 * normal


@pytest.mark.parametrize("seq", EVERY_SEQUENCE)
def test_euler_rates_at_gimbal_lock(seq):
    # The two locks repeated to N rows: the batch shape of the other euler_rates and
    # body_angular_velocity calls of this sequence (their programs, not new ones).
    angles, omega_ok, omega_bad = (np.tile(x, (N // 2, 1)) for x in _rates_lock_inputs(seq))
    # omega in the followable plane: the documented split psi' = 0, which reproduces omega.
    rates = np.asarray(rj.euler_rates(angles, omega_ok, seq))
    assert np.all(np.isfinite(rates))
    np.testing.assert_array_equal(rates[:, 2], 0.0)
    np.testing.assert_allclose(sympy_body_omega(seq)(angles, rates), omega_ok, atol=1e-14)
    np.testing.assert_allclose(rj.body_angular_velocity(angles, rates, seq), omega_ok, atol=1e-14)
    # omega with a component the angles cannot follow: an error naming gimbal lock...
    for i in range(2):
        with pytest.raises(Exception, match="gimbal lock"):
            jax.block_until_ready(rj.euler_rates(angles[i], omega_bad[i], seq))
    # ... or NaN with throw=False, only where unreachable.
    for i in range(2):
        mixed = omega_ok.copy()
        mixed[i] = omega_bad[i]
        out = np.asarray(rj.euler_rates(angles, mixed, seq, throw=False))
        assert np.all(np.isnan(out[i]))
        others = np.arange(N) != i  # the other lock (row 1 - i) and the repeats
        np.testing.assert_allclose(out[others], rates[others], atol=1e-15)


@pytest.mark.parametrize("seq", ["zxz", "yxz"])
def test_euler_rates_at_gimbal_lock_under_jit_and_vmap(seq):
    angles, omega_ok, omega_bad = _rates_lock_inputs(seq)
    with pytest.raises(Exception, match="gimbal lock"):
        jax.block_until_ready(jax.jit(functools.partial(rj.euler_rates, seq=seq))(angles[0], omega_bad[0]))
    f = jax.jit(jax.vmap(functools.partial(rj.euler_rates, seq=seq, throw=False)))
    out = np.asarray(f(np.concatenate([angles, angles]), np.concatenate([omega_ok, omega_bad])))
    assert np.all(np.isfinite(out[:2])) and np.all(np.isnan(out[2:]))
    np.testing.assert_allclose(out[:2], rj.euler_rates(angles, omega_ok, seq), atol=1e-15)


@pytest.mark.parametrize("seq", EVERY_SEQUENCE)
@pytest.mark.parametrize("side", [-1.0, 1.0])
def test_euler_rates_near_gimbal_lock(seq, side):
    lock = 0.0 if is_proper(seq) else np.pi / 2
    theta = lock + side * 1e-6
    angles = np.array([0.4, theta, -1.1])
    omega = np.array([0.3, -1.2, 0.8])
    rates = np.asarray(rj.euler_rates(angles, omega, seq))
    assert np.all(np.isfinite(rates))
    assert np.max(np.abs(rates)) > 1e4  # ~ |omega_perp| / 1e-6: the truth, not an artefact
    np.testing.assert_allclose(sympy_body_omega(seq)(angles, rates), omega, atol=1e-8)


# ----------------------------------------------------------------------------------------------
# 4. Batch shapes and broadcasting
# ----------------------------------------------------------------------------------------------

BATCH_SHAPES = [(), (1,), (3, 1, 2)]
_BSEQ = "yxz"
# Jitted once at module level: a new batch shape compiles far faster as one program than op by op.
BATCH_CASES = {
    name: (jax.jit(fn), kinds, tail)
    for name, fn, kinds, tail in [
        ("matrix_from_euler", lambda a: rj.matrix_from_euler(a, _BSEQ), "a", (3, 3)),
        ("quat_from_euler", lambda a: rj.quat_from_euler(a, _BSEQ), "a", (4,)),
        ("euler_from_matrix", lambda m: rj.euler_from_matrix(m, _BSEQ), "m", (3,)),
        ("euler_from_quat", lambda q: rj.euler_from_quat(q, _BSEQ), "q", (3,)),
        ("matrix_from_quat", rj.matrix_from_quat, "q", (3, 3)),
        ("quat_from_matrix", rj.quat_from_matrix, "m", (4,)),
        ("body_angular_velocity", lambda a, r: rj.body_angular_velocity(a, r, _BSEQ), "ar", (3,)),
        ("euler_rates", lambda a, w: rj.euler_rates(a, w, _BSEQ), "av", (3,)),
    ]
}


@pytest.mark.parametrize("batch", fast_tier(BATCH_SHAPES, [(), (3, 1, 2)]))
def test_batch_shapes(batch):
    rng = np.random.default_rng(11)
    n = int(np.prod(batch))
    rot = Rotation.random(n, rng=rng)
    inputs = {
        "a": random_angles(_BSEQ, n, 12).reshape(batch + (3,)),
        "r": rng.normal(size=batch + (3,)),
        "v": rng.normal(size=batch + (3,)),
        "q": scipy_quat(rot).reshape(batch + (4,)),
        "m": rot.as_matrix().reshape(batch + (3, 3)),
    }
    for name, (fn, kinds, tail) in BATCH_CASES.items():
        args = [inputs[k] for k in kinds]
        out = np.asarray(fn(*args))
        assert out.shape == batch + tail, name
        for idx in np.ndindex(*batch):
            single = np.asarray(fn(*[a[idx] for a in args]))
            assert single.shape == tail, name
            np.testing.assert_allclose(out[idx], single, rtol=1e-14, atol=1e-14, err_msg=name)


def test_broadcasting_angles_against_rates():
    seq = "zyx"
    angles = random_angles(seq, 4, 13).reshape(4, 1, 3)
    rates = np.random.default_rng(14).normal(size=(5, 3))
    full_angles, full_rates = np.broadcast_to(angles, (4, 5, 3)), np.broadcast_to(rates, (4, 5, 3))
    body = sympy_body_omega(seq)
    jit = functools.partial(jax.jit, static_argnums=2)
    for fn in (rj.body_angular_velocity, rj.space_angular_velocity, rj.euler_rates):
        out = np.asarray(jit(fn)(angles, rates, seq))
        assert out.shape == (4, 5, 3), fn.__name__
        full = np.asarray(jit(fn)(full_angles, full_rates, seq))
        np.testing.assert_allclose(out, full, rtol=1e-14, atol=1e-14, err_msg=fn.__name__)
    # Against the references, element by element.
    np.testing.assert_allclose(
        jit(rj.body_angular_velocity)(angles, rates, seq), body(full_angles, full_rates), atol=1e-14
    )
    np.testing.assert_allclose(
        body(full_angles, np.asarray(jit(rj.euler_rates)(angles, rates, seq))), full_rates, atol=1e-12
    )
    # One set of angles against a batch of rates, and the reverse (eager).
    assert rj.body_angular_velocity(angles[0, 0], rates, seq).shape == (5, 3)
    assert rj.euler_rates(angles[:, 0], rates[0], seq).shape == (4, 3)
    # Quaternion products broadcast too.
    p = scipy_quat(Rotation.random(2, rng=np.random.default_rng(15))).reshape(2, 1, 4)
    q = scipy_quat(Rotation.random(3, rng=np.random.default_rng(16)))
    pq = np.asarray(rj.quat_multiply(p, q))
    assert pq.shape == (2, 3, 4)
    P = Rotation.from_quat(np.broadcast_to(p, (2, 3, 4)).reshape(6, 4), scalar_first=True)
    Q = Rotation.from_quat(np.broadcast_to(q, (2, 3, 4)).reshape(6, 4), scalar_first=True)
    assert_quat_close(pq.reshape(6, 4), scipy_quat(P * Q), atol=1e-15)
    assert rj.quat_rotate(p, rates).shape == (2, 5, 3)


# ----------------------------------------------------------------------------------------------
# 5. float32
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seq", fast_tier(FOUR_SEQUENCES, ["zxz", "zyx"]))
def test_float32_conversions(seq):
    angles = ANGLES[seq].astype(np.float32)
    rot = scipy_rot(angles, seq)  # reference from the float32 values, computed in float64
    R = rj.matrix_from_euler(angles, seq)
    q = rj.quat_from_euler(angles, seq)
    assert R.dtype == jnp.float32 and q.dtype == jnp.float32
    np.testing.assert_allclose(R, rot.as_matrix(), atol=TOL32)
    assert_quat_close(q, scipy_quat(rot), atol=TOL32)

    R32 = rot.as_matrix().astype(np.float32)
    q32 = scipy_quat(rot).astype(np.float32)
    for out in (rj.euler_from_matrix(R32, seq), rj.euler_from_quat(q32, seq)):
        assert out.dtype == jnp.float32
        assert_angles_close(out, rot.as_euler(seq.upper()), atol=1e-4)
        np.testing.assert_allclose(scipy_rot(out, seq).as_matrix(), rot.as_matrix(), atol=TOL32)
    qm = rj.quat_from_matrix(R32)
    assert qm.dtype == jnp.float32
    assert_quat_close(qm, scipy_quat(rot), atol=TOL32)
    assert rj.matrix_from_quat(q32).dtype == jnp.float32
    np.testing.assert_allclose(rj.matrix_from_quat(q32), rot.as_matrix(), atol=TOL32)

    rates = RATES.astype(np.float32)
    omega = rj.body_angular_velocity(angles, rates, seq)
    assert omega.dtype == jnp.float32
    np.testing.assert_allclose(omega, sympy_body_omega(seq)(angles, rates), atol=TOL32)
    omega_space = rj.space_angular_velocity(angles, rates, seq)
    assert omega_space.dtype == jnp.float32
    np.testing.assert_allclose(omega_space, rot.apply(sympy_body_omega(seq)(angles, rates)), atol=TOL32)
    back = rj.euler_rates(angles, omega, seq)
    assert back.dtype == jnp.float32
    np.testing.assert_allclose(back, rates, atol=1e-4)

    # At (float32 values of) the lock: finite, and the rotation round-trips to float32 accuracy.
    lock = lock_batch(seq).astype(np.float32)
    rot = scipy_rot(lock, seq)
    for out in (
        rj.euler_from_matrix(rot.as_matrix().astype(np.float32), seq),
        rj.euler_from_quat(scipy_quat(rot).astype(np.float32), seq),
    ):
        assert out.dtype == jnp.float32
        assert np.all(np.isfinite(np.asarray(out)))
        np.testing.assert_allclose(scipy_rot(out, seq).as_matrix(), rot.as_matrix(), atol=TOL32)


@pytest.mark.parametrize("seq", ["zyx"])
def test_float32_gradients_finite_at_gimbal_lock(seq):
    q = jnp.asarray(scipy_quat(scipy_rot(lock_batch(seq), seq)), jnp.float32)
    jac = jax.jit(jax.vmap(jax.jacrev(functools.partial(rj.euler_from_quat, seq=seq))))(q)
    assert jac.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(jac)))


def test_float32_quaternion_ops():
    pq = scipy_quat(ROTATIONS).astype(np.float32)
    rq = np.roll(pq, 1, axis=0)
    v = np.random.default_rng(17).normal(size=(N, 3)).astype(np.float32)
    for out in (
        rj.quat_multiply(pq, rq),
        rj.quat_conjugate(pq),
        rj.quat_rotate(pq, v),
        rj.quat_normalize(pq),
    ):
        assert out.dtype == jnp.float32
    P = Rotation.from_quat(pq.astype(np.float64), scalar_first=True)
    Rr = Rotation.from_quat(rq.astype(np.float64), scalar_first=True)
    assert_quat_close(rj.quat_multiply(pq, rq), scipy_quat(P * Rr), atol=TOL32)
    np.testing.assert_allclose(rj.quat_rotate(pq, v), P.apply(v.astype(np.float64)), atol=TOL32)


# ----------------------------------------------------------------------------------------------
# 6. Bad input
# ----------------------------------------------------------------------------------------------


BAD_SHAPE_CALLS = [
    (lambda: rj.matrix_from_euler(np.zeros(4)), "angles"),
    (lambda: rj.quat_from_euler(np.zeros((2, 2))), "angles"),
    (lambda: rj.euler_from_matrix(np.eye(4)), "R"),
    (lambda: rj.euler_from_matrix(np.zeros((3, 2))), "R"),
    (lambda: rj.euler_from_quat(np.zeros(3)), "q"),
    (lambda: rj.matrix_from_quat(np.zeros((2, 3))), "q"),
    (lambda: rj.quat_from_matrix(np.zeros((2, 3))), "R"),
    (lambda: rj.quat_multiply(np.zeros(4), np.zeros(3)), "q"),
    (lambda: rj.quat_multiply(np.zeros(5), np.zeros(4)), "p"),
    (lambda: rj.quat_rotate(np.zeros(4), np.zeros(4)), "v"),
    (lambda: rj.body_angular_velocity(np.zeros(3), np.zeros(2)), "rates"),
    (lambda: rj.body_angular_velocity(np.zeros(2), np.zeros(3)), "angles"),
    (lambda: rj.space_angular_velocity(np.zeros(3), np.zeros(4)), "rates"),
    (lambda: rj.euler_rates(np.zeros(3), np.zeros((5, 2))), "omega"),
]


@pytest.mark.parametrize(("call", "name"), BAD_SHAPE_CALLS)
def test_bad_shape_raises_value_error_naming_argument(call, name, without_runtime_typecheck):
    with pytest.raises(ValueError, match=rf"\b{name} must have shape"):
        call()


@pytest.mark.parametrize(("call", "name"), BAD_SHAPE_CALLS)
def test_bad_shape_rejected_under_runtime_typecheck(call, name):
    # With jaxtyping's runtime checks on (as in this test run) the annotation check fires first.
    with pytest.raises((ValueError, TypeError), match=rf"\b{name}\b"):
        call()


@pytest.mark.parametrize("seq", ["abc", "zzx", "xyzx", "", "xy", "ZXX"])
def test_unknown_sequence_raises(seq):
    for call in (
        lambda: rj.matrix_from_euler(np.zeros(3), seq),
        lambda: rj.quat_from_euler(np.zeros(3), seq),
        lambda: rj.euler_from_matrix(np.eye(3), seq),
        lambda: rj.euler_from_quat(np.array([1.0, 0, 0, 0]), seq),
        lambda: rj.body_angular_velocity(np.zeros(3), np.zeros(3), seq),
        lambda: rj.euler_rates(np.zeros(3), np.zeros(3), seq),
    ):
        with pytest.raises(ValueError, match="seq"):
            call()


def test_sequence_lists():
    assert set(SEQUENCES) == set(PROPER_SEQUENCES) | set(TAIT_BRYAN_SEQUENCES)
    assert len(set(SEQUENCES)) == 12
    assert all(rj.kinematics.is_proper_sequence(s) for s in PROPER_SEQUENCES)
    assert not any(rj.kinematics.is_proper_sequence(s) for s in TAIT_BRYAN_SEQUENCES)


# ----------------------------------------------------------------------------------------------
# Property test
# ----------------------------------------------------------------------------------------------

_angle = st.floats(-2 * np.pi, 2 * np.pi, allow_nan=False, allow_infinity=False)
_lockish = st.sampled_from(
    [0.0, np.pi / 2, -np.pi / 2, np.pi, -np.pi, 1e-9, np.pi / 2 - 1e-12, np.pi - 1e-15]
)


@settings(max_examples=50, deadline=None)
@given(seq=st.sampled_from(SEQUENCES), phi=_angle, theta=st.one_of(_angle, _lockish), psi=_angle)
def test_round_trip_property(seq, phi, theta, psi):
    """Any angles (any range, at or near lock) -> rotation -> angles -> the same rotation."""
    angles = np.array([phi, theta, psi])
    rot = scipy_rot(angles, seq)
    for out in (rj.euler_from_matrix(rot.as_matrix(), seq), rj.euler_from_quat(scipy_quat(rot), seq)):
        out = np.asarray(out)
        assert np.all(np.isfinite(out))
        np.testing.assert_allclose(scipy_rot(out, seq).as_matrix(), rot.as_matrix(), atol=1e-13)
        assert abs(out[0]) <= np.pi and abs(out[2]) <= np.pi
        if is_proper(seq):
            assert 0.0 <= out[1] <= np.pi
        else:
            assert abs(out[1]) <= np.pi / 2


def test_quat_exp_refuses_an_angle_beyond_what_the_dtype_resolves():
    """|theta| = 2e154 squared overflowed: a NaN quaternion without an error (1e154 gave a "unit"
    quaternion of a rotation whose angle float64 cannot hold). Below 1/eps the values stay those of
    the closed form (cos(n/2), sin(n/2) theta/n)."""
    for theta in ([2e154, 0.0, 0.0], [1e16, 0.0, 0.0]):
        with pytest.raises(ValueError, match="quat_exp: theta's angle is beyond what its dtype resolves"):
            rj.kinematics.quat_exp(jnp.asarray(theta))
    n = 1e6
    np.testing.assert_allclose(
        rj.kinematics.quat_exp(jnp.array([0.0, 0.0, n])), [np.cos(n / 2), 0, 0, np.sin(n / 2)], atol=1e-9
    )
