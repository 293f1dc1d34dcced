"""Dynamics: Euler's equations and the quantities derived from them.

References are independent of rigidjax: numpy transcriptions of the textbook equations (Euler's
equations in principal axes: ``helpers.euler_rhs``), scipy rotations, central finite differences, a
numpy RK4 integration, and the closed-form free precession of a symmetric top.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference, euler_rhs, quat_multiply
from scipy.spatial.transform import Rotation

import rigidjax as rj
from rigidjax._checks import is_full_tensor  # the shape rule (no longer public)

N = 8
_rng = np.random.default_rng(2024)
INERTIA = _rng.uniform(0.5, 3.0, (N, 3))
OMEGA = _rng.normal(size=(N, 3))
TORQUE = _rng.normal(size=(N, 3))
ROT = Rotation.random(N, rng=np.random.default_rng(7))
QR = ROT.as_matrix()  # (N, 3, 3): principal axes of the full tensors below, as columns


# ----------------------------------------------------------------------------------------------
# Independent numpy references
# ----------------------------------------------------------------------------------------------


def np_euler_tensor(T, w, tau=0.0):
    """I w' = tau - w x (I w)."""
    L = np.einsum("...ij,...j->...i", T, w)
    rhs = tau - np.cross(w, L)
    T, rhs = np.broadcast_arrays(T, rhs[..., None])
    return np.linalg.solve(T, rhs)[..., 0]


def tensors(inertia=INERTIA, Q=QR):
    """Full tensors ``Q diag(I) Q^T``: the body frame rotated by ``Q^T`` away from principal axes."""
    return np.einsum("...ij,...j,...kj->...ik", Q, inertia, Q)


def rk4(f, y0, h, steps):
    ys = [y0]
    y = y0
    for _ in range(steps):
        k1 = f(y)
        k2 = f(y + 0.5 * h * k1)
        k3 = f(y + 0.5 * h * k2)
        k4 = f(y + h * k3)
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        ys.append(y)
    return np.stack(ys)


# ----------------------------------------------------------------------------------------------
# 1. Euler's equations
# ----------------------------------------------------------------------------------------------


def test_principal_form_matches_numpy_transcription():
    out = rj.euler_equations(INERTIA, OMEGA, TORQUE)
    assert out.shape == (N, 3) and out.dtype == jnp.float64
    np.testing.assert_allclose(out, euler_rhs(INERTIA, OMEGA, TORQUE), rtol=1e-14, atol=1e-14)
    free = rj.euler_equations(INERTIA, OMEGA)
    np.testing.assert_allclose(free, euler_rhs(INERTIA, OMEGA), rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(free, rj.euler_equations(INERTIA, OMEGA, np.zeros(3)))
    # A sphere feels no gyroscopic torque; a spin about a principal axis is steady.
    np.testing.assert_allclose(rj.euler_equations(np.full(3, 2.0), OMEGA, TORQUE), TORQUE / 2.0, atol=1e-15)
    # (Four bodies: a trailing (3, 3) would be read as one full tensor.)
    steady = np.array([[0.0, 0.0, 3.0], [0.0, -2.0, 0.0], [1.5, 0.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(rj.euler_equations(INERTIA[:4], steady), 0.0)


def test_full_tensor_matches_principal_form_in_rotated_frame():
    T = tensors()
    w_rot = np.einsum("nij,nj->ni", QR, OMEGA)
    tau_rot = np.einsum("nij,nj->ni", QR, TORQUE)
    expected = np.einsum("nij,nj->ni", QR, euler_rhs(INERTIA, OMEGA, TORQUE))
    np.testing.assert_allclose(rj.euler_equations(T, w_rot, tau_rot), expected, rtol=1e-12, atol=1e-12)
    expected_free = np.einsum("nij,nj->ni", QR, euler_rhs(INERTIA, OMEGA))
    np.testing.assert_allclose(rj.euler_equations(T, w_rot), expected_free, rtol=1e-12, atol=1e-12)
    # Direct transcription of I w' = tau - w x (I w).
    np.testing.assert_allclose(
        rj.euler_equations(T, OMEGA, TORQUE), np_euler_tensor(T, OMEGA, TORQUE), atol=1e-12
    )
    # A diagonal tensor is the principal form.
    diag = np.einsum("ni,ij->nij", INERTIA, np.eye(3))
    np.testing.assert_allclose(
        rj.euler_equations(diag, OMEGA, TORQUE), euler_rhs(INERTIA, OMEGA, TORQUE), atol=1e-13
    )


@pytest.mark.parametrize("form", ["principal", "tensor"])
def test_torque_free_conserves_energy_and_momentum(form):
    inertia = INERTIA if form == "principal" else tensors()
    Iw = np.einsum("nij,nj->ni", inertia, OMEGA) if form == "tensor" else inertia * OMEGA
    wdot = np.asarray(rj.euler_equations(inertia, OMEGA))
    Iwdot = np.einsum("nij,nj->ni", inertia, wdot) if form == "tensor" else inertia * wdot
    scale = np.linalg.norm(OMEGA, axis=-1) * np.linalg.norm(Iw, axis=-1) * np.linalg.norm(OMEGA, axis=-1)
    # d/dt (omega . I omega / 2) = omega . I omega'  (I symmetric)
    np.testing.assert_allclose(np.sum(OMEGA * Iwdot, -1) / scale, 0.0, atol=1e-14)
    # d/dt |I omega|^2 / 2 = (I omega) . (I omega')
    np.testing.assert_allclose(
        np.sum(Iw * Iwdot, -1) / (scale * np.linalg.norm(Iw, axis=-1)), 0.0, atol=1e-14
    )
    # In the body frame L' = -omega x L.
    np.testing.assert_allclose(Iwdot, -np.cross(OMEGA, Iw), atol=1e-13)
    # With a torque, the power is omega . tau and (I omega) . (I omega') = L . tau.
    wdot = np.asarray(rj.euler_equations(inertia, OMEGA, TORQUE))
    Iwdot = np.einsum("nij,nj->ni", inertia, wdot) if form == "tensor" else inertia * wdot
    np.testing.assert_allclose(np.sum(OMEGA * Iwdot, -1), np.sum(OMEGA * TORQUE, -1), atol=1e-13)
    np.testing.assert_allclose(np.sum(Iw * Iwdot, -1), np.sum(Iw * TORQUE, -1), atol=1e-13)


# ----------------------------------------------------------------------------------------------
# 2. Gradients
# ----------------------------------------------------------------------------------------------

_SYM = np.array([1.3, 1.3, 2.1])  # I1 = I2: symmetric top
GRAD_CASES = {
    "principal": (INERTIA[0], OMEGA[0], TORQUE[0]),
    "symmetric": (_SYM, OMEGA[1], TORQUE[1]),
    "symmetric-free": (_SYM, np.array([0.4, -0.7, 2.0]), None),
    "tensor": (tensors()[2], OMEGA[2], TORQUE[2]),
    "tensor-symmetric": (tensors(_SYM, QR[3]), OMEGA[3], None),
}


@pytest.mark.parametrize(
    "case",
    [
        pytest.param(c, marks=pytest.mark.slow if c in ("symmetric", "tensor-symmetric") else ())
        for c in GRAD_CASES
    ],
)
def test_gradients_match_finite_differences(case):
    inertia, w, tau = GRAD_CASES[case]
    f = functools.partial(rj.euler_equations, torque=tau)
    for argnum, x in ((0, inertia), (1, w)):
        g = (lambda x: f(x, w)) if argnum == 0 else (lambda x: f(inertia, x))
        # Each derivative one compiled program (eagerly, each of its operations compiles on its own).
        fwd = np.asarray(jax.jit(jax.jacfwd(g))(jnp.asarray(x)))
        rev = np.asarray(jax.jit(jax.jacrev(g))(jnp.asarray(x)))
        fd = central_difference(g, x)
        assert fwd.shape == (3,) + x.shape
        np.testing.assert_allclose(fwd, rev, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(fwd, fd, rtol=1e-7, atol=1e-8)
    # Derivative w.r.t. the torque is the inverse inertia.
    if tau is not None:
        J = np.asarray(jax.jit(jax.jacfwd(lambda t: rj.euler_equations(inertia, w, t)))(jnp.asarray(tau)))
        Iinv = np.linalg.inv(inertia) if inertia.ndim == 2 else np.diag(1 / inertia)
        np.testing.assert_allclose(J, Iinv, rtol=1e-13, atol=1e-13)


def test_symmetric_top_gradient_closed_form():
    """At I1 = I2: d w1'/d I3 = -w2 w3 / I1, d w2'/d I3 = w3 w1 / I2, d w3'/d I* = 0 when tau = 0."""
    w = np.array([0.4, -0.7, 2.0])
    J = np.asarray(jax.jacrev(lambda inertia: rj.euler_equations(inertia, w))(jnp.asarray(_SYM)))
    I1, I2, I3 = _SYM
    w1, w2, w3 = w
    expected = np.array(
        [
            [-(I2 - I3) * w2 * w3 / I1**2, w2 * w3 / I1, -w2 * w3 / I1],
            [-w3 * w1 / I2, -(I3 - I1) * w3 * w1 / I2**2, w3 * w1 / I2],
            [w1 * w2 / I3, -w1 * w2 / I3, 0.0],  # (I1 - I2) = 0
        ]
    )
    np.testing.assert_allclose(J, expected, rtol=1e-14, atol=1e-15)


# ----------------------------------------------------------------------------------------------
# 3. Energy, momentum, precession
# ----------------------------------------------------------------------------------------------


def test_kinetic_energy_and_angular_momentum():
    np.testing.assert_allclose(
        rj.kinetic_energy(INERTIA, OMEGA), 0.5 * np.sum(INERTIA * OMEGA**2, -1), rtol=1e-15
    )
    np.testing.assert_allclose(rj.angular_momentum(INERTIA, OMEGA), INERTIA * OMEGA, rtol=1e-15)
    T = tensors()
    w_rot = np.einsum("nij,nj->ni", QR, OMEGA)
    L_rot = np.asarray(rj.angular_momentum(T, w_rot))
    np.testing.assert_allclose(L_rot, np.einsum("nij,nj->ni", T, w_rot), rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(L_rot, np.einsum("nij,nj->ni", QR, INERTIA * OMEGA), rtol=1e-12, atol=1e-13)
    # Energy is frame independent.
    np.testing.assert_allclose(rj.kinetic_energy(T, w_rot), rj.kinetic_energy(INERTIA, OMEGA), rtol=1e-13)
    np.testing.assert_allclose(
        rj.kinetic_energy(T, w_rot), 0.5 * np.einsum("ni,nij,nj->n", w_rot, T, w_rot), rtol=1e-13
    )
    assert rj.kinetic_energy(INERTIA, OMEGA).shape == (N,)
    assert rj.kinetic_energy(INERTIA[0], OMEGA[0]).shape == ()


def test_space_angular_momentum():
    q = ROT.as_quat(scalar_first=True)
    L_space = np.asarray(rj.space_angular_momentum(INERTIA, OMEGA, q))
    np.testing.assert_allclose(L_space, ROT.apply(INERTIA * OMEGA), rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(
        L_space, np.einsum("nij,nj->ni", np.asarray(rj.matrix_from_quat(q)), INERTIA * OMEGA), atol=1e-14
    )
    T = tensors()
    np.testing.assert_allclose(
        rj.space_angular_momentum(T, OMEGA, q), ROT.apply(np.einsum("nij,nj->ni", T, OMEGA)), atol=1e-13
    )


def test_space_angular_momentum_is_conserved_along_free_motion():
    """Integrate omega (Euler) and q (dq/dt = q ⊗ (0, omega) / 2) with a numpy RK4; R L stays fixed."""
    inertia = np.array([1.0, 2.0, 3.5])
    w0 = np.array([0.3, 2.0, -0.4])  # near the unstable middle axis: omega changes a lot
    q0 = ROT[0].as_quat(scalar_first=True)

    def f(y):
        w, q = y[:3], y[3:]
        return np.concatenate([euler_rhs(inertia, w), 0.5 * quat_multiply(q, np.concatenate([[0.0], w]))])

    ys = rk4(f, np.concatenate([w0, q0]), 2e-3, 1500)
    w, q = ys[:, :3], ys[:, 3:]
    assert np.ptp(w[:, 1]) > 1.0  # the motion is not trivial
    L_space = np.asarray(rj.space_angular_momentum(inertia, w, q))
    assert L_space.shape == (len(ys), 3)
    np.testing.assert_allclose(L_space, np.broadcast_to(L_space[0], L_space.shape), atol=1e-9)
    # The inverse rotation would not conserve it: the convention is body -> space.
    wrong = np.asarray(rj.quat_rotate(rj.quat_conjugate(q), inertia * w))
    assert np.max(np.abs(wrong - wrong[0])) > 0.1
    E = np.asarray(rj.kinetic_energy(inertia, w))
    np.testing.assert_allclose(E, E[0], rtol=1e-10)


def test_free_precession_rate_closed_form():
    I1, I3, w3 = INERTIA[:, 0], INERTIA[:, 2], OMEGA[:, 2]
    out = rj.free_precession_rate(I1, I3, w3)
    assert out.shape == (N,) and out.dtype == jnp.float64
    np.testing.assert_allclose(out, (I3 - I1) / I1 * w3, rtol=1e-15)
    assert rj.free_precession_rate(np.float64(2.0), np.float64(2.0), np.float64(5.0)) == 0.0  # sphere
    # Broadcasts: one body, many spin rates.
    assert rj.free_precession_rate(np.float64(1.0), np.float64(1.5), w3).shape == (N,)
    # Earth-like oblate top: I3 > I1 precesses forwards (with the spin) in the body frame.
    assert rj.free_precession_rate(np.float64(1.0), np.float64(1.0033), np.float64(1.0)) > 0
    r32 = rj.free_precession_rate(np.float32(1.0), np.float32(2.0), np.float32(3.0))
    assert r32.dtype == jnp.float32 and r32 == 3.0


@pytest.mark.parametrize(("I1", "I3"), [(2.0, 1.0), (1.0, 2.5)], ids=["prolate", "oblate"])
def test_symmetric_top_transverse_omega_turns_at_precession_rate(I1, I3):
    """Integrate Euler's equations (rigidjax's right-hand side, numpy RK4) and compare with
    w1 + i w2 = A exp(i Omega t), Omega = free_precession_rate(I1, I3, w3)."""
    inertia = np.array([I1, I1, I3])
    w0 = np.array([0.3, -0.2, 2.0])
    rhs = jax.jit(rj.euler_equations)
    h, steps = 0.01, 300
    ws = rk4(lambda w: np.asarray(rhs(inertia, w)), w0, h, steps)
    t = h * np.arange(steps + 1)
    Omega = float(rj.free_precession_rate(np.float64(I1), np.float64(I3), np.float64(w0[2])))
    assert abs(Omega * t[-1]) > 1.0  # turns through a good angle
    analytic = (w0[0] + 1j * w0[1]) * np.exp(1j * Omega * t)
    np.testing.assert_allclose(ws[:, 0] + 1j * ws[:, 1], analytic, atol=1e-8)
    np.testing.assert_allclose(ws[:, 2], w0[2], atol=1e-14)
    # Sign check made explicit: prolate (I3 < I1) turns backwards, against the spin.
    phase = np.unwrap(np.angle(ws[:, 0] + 1j * ws[:, 1]))
    assert np.sign(phase[-1] - phase[0]) == np.sign(I3 - I1) * np.sign(w0[2])
    # The analytic solution satisfies rigidjax's Euler equations pointwise.
    w_t = np.stack([analytic.real, analytic.imag, np.full_like(t, w0[2])], -1)
    dw_t = np.stack([(1j * Omega * analytic).real, (1j * Omega * analytic).imag, np.zeros_like(t)], -1)
    np.testing.assert_allclose(rhs(inertia, w_t), dw_t, atol=1e-13)


# ----------------------------------------------------------------------------------------------
# 4. Batch broadcasting
# ----------------------------------------------------------------------------------------------


def test_batch_broadcasting():
    T = tensors()
    cases = [
        # (inertia, omega, torque, expected shape, numpy reference)
        (INERTIA, OMEGA, None, (N, 3), euler_rhs(INERTIA, OMEGA)),
        (INERTIA[0], OMEGA, None, (N, 3), euler_rhs(INERTIA[0], OMEGA)),
        (INERTIA, OMEGA[0], TORQUE, (N, 3), euler_rhs(INERTIA, OMEGA[0], TORQUE)),
        (
            INERTIA[:, None, :],
            OMEGA[:3],
            TORQUE[0],
            (N, 3, 3),
            euler_rhs(INERTIA[:, None], OMEGA[:3], TORQUE[0]),
        ),
        (T[0], OMEGA, None, (N, 3), np_euler_tensor(T[0], OMEGA)),
        (T[0], OMEGA, TORQUE[0], (N, 3), np_euler_tensor(T[0], OMEGA, TORQUE[0])),
        (T, OMEGA[0], None, (N, 3), np_euler_tensor(T, OMEGA[0])),
        (T, OMEGA, TORQUE, (N, 3), np_euler_tensor(T, OMEGA, TORQUE)),
        (T[:4, None], OMEGA[:3], None, (4, 3, 3), np_euler_tensor(T[:4, None], OMEGA[:3])),
    ]
    for k, (inertia, w, tau, shape, expected) in enumerate(cases):
        out = np.asarray(rj.euler_equations(inertia, w, tau))
        assert out.shape == shape, k
        np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-12, err_msg=str(k))
        # And element by element of the batch.
        batch = shape[:-1]
        full_I = np.broadcast_to(
            inertia, batch + inertia.shape[-2:] if inertia.shape[-2:] == (3, 3) else shape
        )
        full_w = np.broadcast_to(w, shape)
        full_tau = None if tau is None else np.broadcast_to(tau, shape)
        for idx in [(0,) * len(batch), tuple(n - 1 for n in batch)]:
            single = rj.euler_equations(full_I[idx], full_w[idx], None if tau is None else full_tau[idx])
            np.testing.assert_allclose(out[idx], single, rtol=1e-14, atol=1e-14, err_msg=str(k))
    # The derived quantities broadcast the same way.
    assert rj.kinetic_energy(INERTIA[0], OMEGA).shape == (N,)
    assert rj.kinetic_energy(T[0], OMEGA).shape == (N,)
    assert rj.angular_momentum(T, OMEGA[0]).shape == (N, 3)
    q = ROT.as_quat(scalar_first=True)
    assert rj.space_angular_momentum(INERTIA[0], OMEGA[0], q).shape == (N, 3)
    np.testing.assert_allclose(
        rj.space_angular_momentum(INERTIA[0], OMEGA[0], q), ROT.apply(INERTIA[0] * OMEGA[0]), atol=1e-14
    )


def test_batch_matches_vmap():
    T = jnp.asarray(tensors())
    f = jax.vmap(rj.euler_equations)
    np.testing.assert_allclose(
        rj.euler_equations(T, OMEGA, TORQUE), f(T, jnp.asarray(OMEGA), jnp.asarray(TORQUE)), atol=1e-14
    )
    np.testing.assert_allclose(
        rj.euler_equations(INERTIA, OMEGA, TORQUE),
        f(jnp.asarray(INERTIA), jnp.asarray(OMEGA), jnp.asarray(TORQUE)),
        atol=1e-15,
    )


def test_float32():
    inertia, w, tau = INERTIA.astype(np.float32), OMEGA.astype(np.float32), TORQUE.astype(np.float32)
    T = tensors().astype(np.float32)
    for out, ref in (
        (rj.euler_equations(inertia, w, tau), euler_rhs(inertia, w, tau)),
        (rj.euler_equations(T, w), np_euler_tensor(T.astype(float), w.astype(float))),
        (rj.kinetic_energy(inertia, w), 0.5 * np.sum(inertia * w * w, -1)),
        (rj.angular_momentum(T, w), np.einsum("nij,nj->ni", T, w)),
    ):
        assert out.dtype == jnp.float32
        np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("scale", [1e-30, 1e-13, 1e13, 8e37])
def test_float32_tensor_over_the_whole_range(scale):
    """A float32 tensor of moments from 1e-30 to 8e37 kg m^2 (the Earth's): the adjugate solve's
    cofactors and determinant (two and three entries multiplied) over- or underflowed float32 from
    5e12 up and 1e-13 down. Reference: numpy's float64 solve of the same (rounded) tensor."""
    tensor = (tensors()[0] * scale).astype(np.float32)
    w = OMEGA[0].astype(np.float32) * (1e-6 if scale > 1e30 else 1.0)  # I omega within float32
    ref = np_euler_tensor(tensor.astype(np.float64)[None], w.astype(np.float64)[None])[0]
    for fn in (rj.euler_equations, jax.jit(rj.euler_equations)):
        out = fn(tensor, w)
        assert out.dtype == jnp.float32
        np.testing.assert_allclose(out, ref, rtol=2e-6, atol=2e-6 * np.max(np.abs(ref)))


# ----------------------------------------------------------------------------------------------
# 5. Bad input
# ----------------------------------------------------------------------------------------------


BAD_SHAPE_CALLS = [
    (lambda: rj.euler_equations(np.ones(3), np.zeros(4)), "omega"),
    (lambda: rj.euler_equations(np.ones(3), np.zeros((2, 2))), "omega"),
    (lambda: rj.euler_equations(np.ones(3), np.zeros(3), np.zeros(2)), "torque"),
    (lambda: rj.euler_equations(np.ones(4), np.zeros(3)), "inertia"),
    (lambda: rj.euler_equations(np.ones((2, 2)), np.zeros(3)), "inertia"),
    (lambda: rj.euler_equations(np.ones((3, 2)), np.zeros(3)), "inertia"),
    (lambda: rj.kinetic_energy(np.ones(2), np.zeros(3)), "inertia"),
    (lambda: rj.angular_momentum(np.ones(3), np.zeros(2)), "omega"),
    (lambda: rj.space_angular_momentum(np.ones(3), np.zeros(3), np.array([1.0, 0.0, 0.0])), "orientation"),
]


@pytest.mark.parametrize(("call", "name"), BAD_SHAPE_CALLS)
def test_bad_shape_raises_value_error_naming_argument(call, name, without_runtime_typecheck):
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        call()


@pytest.mark.parametrize(("call", "name"), BAD_SHAPE_CALLS)
def test_bad_shape_rejected_under_runtime_typecheck(call, name):
    with pytest.raises((ValueError, TypeError), match=rf"\b{name}\b"):
        call()


def test_angular_momentum_and_tensor_shape_rule():
    rng = np.random.default_rng(7)
    moments = rng.uniform(1.0, 2.0, (4, 3))
    omega = rng.normal(size=(4, 3))
    np.testing.assert_allclose(np.asarray(rj.angular_momentum(moments, omega)), moments * omega, rtol=1e-15)
    A = rng.normal(size=(4, 3, 3))
    tensor = A @ np.swapaxes(A, -1, -2) + 3 * np.eye(3)
    np.testing.assert_allclose(
        np.asarray(rj.angular_momentum(tensor, omega)), np.einsum("nij,nj->ni", tensor, omega), rtol=1e-13
    )
    assert is_full_tensor(np.ones((3, 3))) and is_full_tensor(np.ones((5, 3, 3)))
    assert not is_full_tensor(np.ones(3)) and not is_full_tensor(np.ones((5, 3)))
    with pytest.raises(ValueError, match="inertia"):
        is_full_tensor(np.ones((2, 4)))


def test_torques_and_scenes_as_a_user_writes_them(without_runtime_typecheck):
    """Python numbers (the default gravity=9.81, mass=1.0, ViscousDamping(0.1)) made a float32 scene
    run in float64; a tuple holding a bare function was refused although documented; a torque
    function returning None, complex or bool numbers gave a raw error or was used silently (complex:
    its imaginary part dropped; bool: 1 N m); reading the orientation of a scene without one was a
    raw TypeError. Reference for the values: a sphere under a constant torque, omega0 + tau t / I."""
    f32 = np.float32
    state32 = rj.State(f32([0.5, -0.3, 1.2]), f32([1.0, 0.0, 0.0, 0.0]))
    ts32 = f32([0.0, 0.5, 1.0])
    for model in (
        rj.HeavyTop(f32([1.0, 1.0, 0.5]), f32(1.0), f32([0.0, 0.0, 0.3])),
        rj.HeavyTop(f32([1.0, 2.0, 2.5]), 1.0, f32([0.0, 0.0, 0.3])),
        rj.RigidBody(f32([1.0, 2.0, 2.5]), rj.ViscousDamping(0.1)),
    ):
        assert rj.simulate(model, state32, ts32, accuracy="fast").omega.dtype == jnp.float32
    sphere, tau = 2.0, np.array([1.0, 0.0, 0.0])
    both = rj.RigidBody(
        jnp.full(3, sphere), (rj.ConstantTorque(jnp.asarray(tau)), lambda t, s, a: jnp.asarray(tau))
    )
    at_rest = rj.State(jnp.zeros(3), jnp.array([1.0, 0.0, 0.0, 0.0]))
    traj = rj.simulate(both, at_rest, jnp.array([0.0, 1.0]), accuracy="precise")
    np.testing.assert_allclose(traj.omega[-1], 2 * tau / sphere, rtol=1e-10)
    for returned, what in (
        (None, "NoneType"),
        (jnp.array([1j, 0, 0]), "complex"),
        (jnp.array([True, False, False]), "bool"),
    ):
        body = rj.RigidBody(jnp.full(3, sphere), lambda t, s, a, r=returned: r)
        with pytest.raises(TypeError, match=rf"Torque\(.*\) returned .*{what}.*real numbers"):
            rj.simulate(body, at_rest, jnp.array([0.0, 1.0]))
    reads_q = rj.Torque(lambda t, s, a: s.orientation[1:], needs_orientation=False)
    with pytest.raises(TypeError, match="without an orientation.*needs_orientation=True"):
        rj.simulate(rj.RigidBody(jnp.full(3, sphere), reads_q), rj.State(jnp.zeros(3)), jnp.array([0.0, 1.0]))
    # A function that fails on something else is not blamed on the orientation: simulate's args
    # forgotten (the third argument None), or an error of its own.
    reads_args = rj.Torque(lambda t, s, a: a["k"] * s.omega, needs_orientation=False)
    with pytest.raises(TypeError, match=r"its third argument was None: pass simulate\(..., args=...\)"):
        rj.simulate(
            rj.RigidBody(jnp.full(3, sphere), reads_args), rj.State(jnp.ones(3)), jnp.array([0.0, 1.0])
        )
    own_error = rj.Torque(lambda t, s, a: s.omega.no_such_method(), needs_orientation=False)
    with pytest.raises(AttributeError, match="no_such_method") as raised:
        rj.simulate(
            rj.RigidBody(jnp.full(3, sphere), own_error), rj.State(jnp.ones(3)), jnp.array([0.0, 1.0])
        )
    assert "orientation" not in str(raised.value)
    with pytest.raises(ValueError, match="Gyrostat's rotors"):
        rj.simulate(rj.Gyrostat(jnp.array([1.0, 2.0, 2.5]), jnp.array([0.0, 0.0, 0.5])),
                    rj.State(jnp.ones(3)), jnp.array([0.0, 1.0]), accuracy="exact")  # fmt: skip


class _Magnetorquer(rj.AbstractTorque):
    """A dipole in a space-fixed field: tau = m x (R^T B), one dipole per body."""

    dipole: jax.Array
    needs_orientation = True

    def per_body_ndims(self):
        return {"dipole": 1}

    def __call__(self, t, state, args):
        field = rj.quat_rotate(rj.quat_conjugate(state.orientation), jnp.array([0.0, 0.0, 0.4]))
        return jnp.cross(self.dipole, field)


class _TorsionSpring(rj.AbstractModel):
    """A body held by a torsion spring toward the identity orientation: tau = -k q_vector."""

    inertia: jax.Array
    stiffness: jax.Array
    needs_orientation = True

    def per_body_ndims(self):
        return {"inertia": 1, "stiffness": 0}

    def angular_acceleration(self, t, state, args):
        return rj.euler_equations(self.inertia, state.omega, -self.stiffness * state.orientation[1:])


def _scipy_motion(inertia, omega0, q0, torque, ts):
    """Euler's equations with ``torque(q)`` (textbook transcription) and dq/dt = q (0, omega) / 2,
    by scipy's DOP853 at rtol 1e-12."""
    from scipy.integrate import solve_ivp

    def rhs(t, y):
        omega, q = y[:3], y[3:]
        dq = 0.5 * quat_multiply(q, np.concatenate([[0.0], omega]))
        return np.concatenate([euler_rhs(inertia, omega, torque(q)), dq])

    y0 = np.concatenate([omega0, q0])
    sol = solve_ivp(rhs, (ts[0], ts[-1]), y0, method="DOP853", t_eval=ts, rtol=1e-12, atol=1e-14)
    return sol.y[:3].T


def test_a_scene_and_a_torque_of_ones_own_batch_per_body():
    """A subclass of AbstractTorque / AbstractModel declares its per-body fields with
    per_body_ndims (public: a scene of one's own could not be written without a private method, and
    a torque of one's own could not differ from body to body). Each body of a batch against scipy's
    DOP853 of that body's equations."""
    inertia, omega0 = np.array([1.0, 2.0, 3.0]), np.array([0.4, -0.2, 0.7])
    q0 = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
    ts = np.linspace(0.0, 6.0, 7)
    state = rj.State(jnp.asarray(omega0), jnp.asarray(q0))
    dipoles = np.array([[1.0, 0.0, 0.0], [0.0, 0.5, 0.5], [0.0, 0.0, 0.0]])
    magnetised = rj.RigidBody(jnp.asarray(inertia), torque=_Magnetorquer(jnp.asarray(dipoles)))
    springs = _TorsionSpring(jnp.asarray(inertia), jnp.array([0.5, 2.0]))
    assert magnetised.batch_shape() == (3,) and springs.batch_shape() == (2,)

    def field_torque(dipole):
        return lambda q: np.cross(dipole, Rotation.from_quat(q[[1, 2, 3, 0]]).inv().apply([0.0, 0.0, 0.4]))

    def spring_torque(k):
        return lambda q: -k * q[1:]

    for model, torques in (
        (magnetised, [field_torque(d) for d in dipoles]),
        (springs, [spring_torque(k) for k in (0.5, 2.0)]),
    ):
        traj = rj.simulate(model, state, jnp.asarray(ts), accuracy="precise")
        assert traj.omega.shape == (len(torques), len(ts), 3) and bool(jnp.all(traj.success))
        for body, torque in enumerate(torques):
            reference = _scipy_motion(inertia, omega0, q0, torque, ts)
            np.testing.assert_allclose(traj.omega[body], reference, atol=1e-7)
    # The dipole-free body is torque-free: its motion is the closed form's.
    free = rj.simulate(rj.FreeBody(jnp.asarray(inertia)), state, jnp.asarray(ts), accuracy="exact")
    np.testing.assert_allclose(
        rj.simulate(magnetised, state, jnp.asarray(ts), accuracy="precise").omega[2], free.omega, atol=1e-7
    )


class _MisspelledMagnetorquer(_Magnetorquer):
    def per_body_ndims(self):
        return {"dipol": 1}


def test_a_torque_of_ones_own_with_fields_that_do_not_fit_its_per_body_ndims(without_runtime_typecheck):
    """A field with fewer axes than one body's value (a scalar dipole) failed inside the torque's
    own jnp.cross with "axis -1 is out of bounds"; a name per_body_ndims misspells, with a bare
    AttributeError; a dipole given as a list, with "isfinite requires ndarray"."""
    state = rj.State(jnp.full((4, 3), 0.1), jnp.array([1.0, 0.0, 0.0, 0.0]))
    ts = jnp.array([0.0, 0.5])
    inertia = jnp.array([1.0, 2.0, 3.0])
    with pytest.raises(
        ValueError, match=r"'torques\[0\]\.dipole' has shape \(\): one body's value has 1 axis"
    ):
        rj.simulate(rj.RigidBody(inertia, torque=_Magnetorquer(jnp.array(1.0))), state, ts)
    with pytest.raises(
        ValueError, match=r"'torques\[0\]\.dipol': the per_body_ndims of torques\[0\] names 'dipol'"
    ):
        rj.simulate(rj.RigidBody(inertia, torque=_MisspelledMagnetorquer(jnp.ones(3))), state, ts)
    as_list = rj.simulate(rj.RigidBody(inertia, torque=_Magnetorquer([1.0, 0.0, 0.0])), state, ts)
    as_array = rj.simulate(rj.RigidBody(inertia, torque=_Magnetorquer(jnp.array([1.0, 0.0, 0.0]))), state, ts)
    np.testing.assert_array_equal(as_list.omega, as_array.omega)
