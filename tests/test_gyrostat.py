"""The gyrostat (a body carrying constant-rate rotors): conservation laws, the body without rotors,
scipy's DOP853, the linearised stability of a spin about the intermediate axis, finite differences,
batches, float32, files and bad input.

Each test names its independent reference: numpy formulas written here from ``I omega' = -omega x
(I omega + h) + tau``, scipy, the linear solution derived in :func:`linear_transverse`, or
rigidjax's FreeBody (for h = 0). Shapes are shared so that few programs are compiled.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference, dop853, expect_error, quat_rotate

import rigidjax as rj

# One scene for most tests: three distinct moments, rotors along no principal axis, a tumble.
INERTIA = np.array([2.0, 3.0, 4.0])
H = np.array([0.3, -0.5, 0.8])
OMEGA0 = np.array([0.7, -0.4, 1.1])
Q0 = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
TS = np.linspace(0.0, 10.0, 51)
TORQUE = np.array([0.05, 0.0, -0.02])


def gyrostat_accel(inertia, h, torque=(0.0, 0.0, 0.0)):
    """``omega'`` of a gyrostat in numpy, from ``I omega' = tau - omega x (I omega + h)``: principal
    moments ``(3,)`` or a tensor ``(3, 3)``."""
    inertia, h, tau = (np.asarray(x, float) for x in (inertia, h, torque))
    if inertia.ndim == 2:
        inverse = np.linalg.inv(inertia)
        return lambda t, w, q: inverse @ (tau - np.cross(w, inertia @ w + h))
    I1, I2, I3 = inertia
    h1, h2, h3 = h

    def accel(t, w, q):  # scalar arithmetic: DOP853 calls it ~1e4 times
        L1, L2, L3 = I1 * w[0] + h1, I2 * w[1] + h2, I3 * w[2] + h3
        return [
            (tau[0] - (w[1] * L3 - w[2] * L2)) / I1,
            (tau[1] - (w[2] * L1 - w[0] * L3)) / I2,
            (tau[2] - (w[0] * L2 - w[1] * L1)) / I3,
        ]

    return accel


def momentum(inertia, h, omega):
    """``L = I omega + h`` in numpy (principal moments)."""
    return np.asarray(inertia) * np.asarray(omega) + np.asarray(h)


def rel_err(x, ref):
    return float(np.max(np.abs(np.asarray(x) - ref)) / np.max(np.abs(ref)))


# --------------------------------------------------------------------------------------------------
# Conservation laws


@pytest.mark.parametrize(
    "method, bound", [pytest.param("precise", 1e-12, marks=pytest.mark.slow), ("rkmk", 1e-7)]
)
def test_torque_free_gyrostat_conserves_energy_and_angular_momentum(method, bound):
    """Reference: the conservation laws. ``omega . I omega / 2``, ``|I omega + h|`` and the
    space-frame ``R (I omega + h)`` are constant without torques (computed here in numpy from the
    samples); RKMK keeps ``|q| = 1`` to roundoff."""
    kwargs = {"accuracy": "precise"} if method == "precise" else {"solver": rj.solvers.RKMK(), "dt0": 0.01}
    traj = rj.simulate(rj.Gyrostat(INERTIA, H), rj.State(OMEGA0, Q0), TS, **kwargs)
    omega, q = np.asarray(traj.omega), np.asarray(traj.orientation)
    energy = 0.5 * np.sum(omega * INERTIA * omega, axis=-1)
    L = momentum(INERTIA, H, omega)
    L_space = quat_rotate(q, L)
    L_norm = np.linalg.norm(L, axis=-1)
    assert np.max(np.abs(energy / energy[0] - 1)) < bound
    assert np.max(np.abs(L_norm / L_norm[0] - 1)) < bound
    assert np.max(np.linalg.norm(L_space - L_space[0], axis=-1)) / L_norm[0] < 10 * bound
    # The rotors matter: I omega alone is far from conserved in space.
    L_rigid = quat_rotate(q, INERTIA * omega)
    assert np.max(np.linalg.norm(L_rigid - L_rigid[0], axis=-1)) / L_norm[0] > 0.1
    # What the trajectory reports about itself agrees.
    invariants = traj.invariants()
    assert float(invariants["energy"]) < bound
    assert float(invariants["quaternion_norm"]) < (1e-9 if method == "precise" else 1e-14)
    for name in ("angular_momentum_norm", "space_angular_momentum"):
        if name in invariants:  # reported only where the trajectory's L includes the rotors
            assert float(invariants[name]) < 10 * bound
    np.testing.assert_allclose(np.asarray(traj.model.angular_momentum(traj.omega)), L, rtol=1e-15, atol=1e-15)


@pytest.mark.slow
def test_zero_rotor_momentum_is_the_free_body():
    """Reference: rigidjax's FreeBody. With h = 0 the equations are Euler's: RKMK (fixed steps, no
    per-scene scales) takes the same steps and gives the same numbers up to a few roundoffs: the two
    models are different programs, and where XLA contracts multiply-adds into fused ones (its default
    emitters on CPU) the last bit differs; the preset agrees to its tolerance."""
    rotors = rj.Gyrostat(INERTIA, np.zeros(3))
    free = rj.FreeBody(INERTIA)
    state = rj.State(OMEGA0, Q0)
    # dt0 = 0.01: the rotors' run is the torque-free test's RKMK program.
    a = rj.simulate(rotors, state, TS, solver=rj.solvers.RKMK(), dt0=0.01)
    b = rj.simulate(free, state, TS, solver=rj.solvers.RKMK(), dt0=0.01)
    np.testing.assert_array_equal(np.asarray(a.stats["num_steps"]), np.asarray(b.stats["num_steps"]))
    np.testing.assert_allclose(np.asarray(a.omega), np.asarray(b.omega), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(a.orientation), np.asarray(b.orientation), rtol=0, atol=1e-14)
    a = rj.simulate(rotors, state, TS, accuracy="precise")
    b = rj.simulate(free, state, TS, accuracy="precise")
    assert rel_err(a.omega, np.asarray(b.omega)) < 1e-10
    assert float(np.max(np.abs(np.asarray(a.orientation) - np.asarray(b.orientation)))) < 1e-10


# --------------------------------------------------------------------------------------------------
# Against scipy


@pytest.mark.parametrize(
    "accuracy, bound",
    [
        pytest.param("fast", 1e-3, marks=pytest.mark.slow),
        ("balanced", 1e-6),
        pytest.param("precise", 1e-9, marks=pytest.mark.slow),
        pytest.param("rkmk", 1e-6, marks=pytest.mark.slow),
    ],
)
def test_against_dop853_with_a_torque(accuracy, bound):
    """Reference: scipy's DOP853 (rtol 1e-13) on the gyrostat's equations written in numpy, with a
    constant body torque on top of the rotors, omega and orientation."""
    model = rj.Gyrostat(INERTIA, H, torque=rj.ConstantTorque(TORQUE))
    if accuracy == "rkmk":
        kwargs = {"solver": rj.solvers.RKMK(), "dt0": 0.01}
    else:
        kwargs = {"accuracy": accuracy}
    traj = rj.simulate(model, rj.State(OMEGA0, Q0), TS, **kwargs)
    omega_ref, q_ref = dop853(gyrostat_accel(INERTIA, H, TORQUE), OMEGA0, TS, Q0)
    assert rel_err(traj.omega, omega_ref) < bound
    assert float(np.max(np.abs(np.asarray(traj.orientation) - q_ref))) < bound


@pytest.mark.slow
def test_tensor_inertia_against_dop853():
    """Reference: scipy's DOP853 on ``I omega' = -omega x (I omega + h)`` with a full tensor (the
    principal body turned by a fixed rotation, h and omega turned with it)."""
    c, s = np.cos(0.4), np.sin(0.4)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
    )
    tensor = R @ np.diag(INERTIA) @ R.T
    traj = rj.simulate(rj.Gyrostat(tensor, R @ H), rj.State(R @ OMEGA0), TS, accuracy="precise")
    omega_ref, _ = dop853(gyrostat_accel(tensor, R @ H), R @ OMEGA0, TS)
    assert rel_err(traj.omega, omega_ref) < 1e-9
    # The same motion seen in principal axes.
    principal, _ = dop853(gyrostat_accel(INERTIA, H), OMEGA0, TS)
    assert rel_err(np.asarray(traj.omega) @ R, principal) < 1e-9


# --------------------------------------------------------------------------------------------------
# Stability of a spin about the intermediate axis, with a wheel along it

# I1 < I2 < I3: a spin about body axis 2 tumbles without rotors (the tennis-racket instability).
# Linearising I omega' = -omega x (I omega + h) about omega = (0, W, 0), h = (0, h2, 0) for small
# (e1, e3):   I1 e1' = A e3,   I3 e3' = -B e1,   A = I2 W + h2 - I3 W,   B = I2 W + h2 - I1 W,
# so e1'' = -(A B / (I1 I3)) e1: bounded oscillation iff A B > 0, exponential growth iff A B < 0.
# With W = 1: stable for h2 > (I3 - I2) W = 1 or h2 < -(I2 - I1) W = -1.
RACKET = np.array([1.0, 2.0, 3.0])
SPIN = 1.0
WHEELS = np.array([-2.0, -1.1, -0.9, 0.0, 0.8, 0.95, 1.05, 1.2, 3.0])
EPS = 1e-5
STABILITY_TS = np.linspace(0.0, 30.0, 301)


def linear_transverse(inertia, spin, h2, e0, ts):
    """The linear solution (e1, e3)(t) of ``I1 e1' = A e3, I3 e3' = -B e1`` from (e1, e3)(0) = e0:
    ``e1 = e1(0) C + A e3(0) / (I1 k) S``, ``e3 = e3(0) C - B e1(0) / (I3 k) S`` with ``k^2 = |A B| /
    (I1 I3)`` and (C, S) = (cos, sin)(k t) where A B > 0, (cosh, sinh)(k t) where A B < 0."""
    I1, I2, I3 = inertia
    A, B = I2 * spin + h2 - I3 * spin, I2 * spin + h2 - I1 * spin
    k = np.sqrt(abs(A * B) / (I1 * I3))
    C, S = (np.cos(k * ts), np.sin(k * ts)) if A * B > 0 else (np.cosh(k * ts), np.sinh(k * ts))
    return e0[0] * C + A * e0[1] / (I1 * k) * S, e0[1] * C - B * e0[0] / (I3 * k) * S


def test_momentum_wheel_stabilises_the_intermediate_axis():
    """Reference: the linearised criterion (A B > 0, derived above) and the linear solution. A batch
    of perturbed spins about the intermediate axis, wheels on both sides of both thresholds: the
    transverse motion stays within a few times the perturbation exactly where A B > 0 and grows by
    orders of magnitude where A B < 0, and while it is small it follows the linear solution."""
    n = WHEELS.size
    h = np.zeros((n, 3))
    h[:, 1] = WHEELS
    omega0 = np.tile([EPS, SPIN, EPS], (n, 1))
    traj = rj.simulate(rj.Gyrostat(RACKET, h), rj.State(omega0), STABILITY_TS, accuracy="precise")
    omega = np.asarray(traj.omega)
    I1, I2, I3 = RACKET
    A, B = I2 * SPIN + WHEELS - I3 * SPIN, I2 * SPIN + WHEELS - I1 * SPIN
    stable = A * B > 0
    np.testing.assert_array_equal(stable, [True, True, False, False, False, False, True, True, True])
    transverse = np.max(np.hypot(omega[..., 0], omega[..., 2]), axis=-1)
    bounded = transverse < 20 * EPS
    growing = transverse > 100 * EPS
    np.testing.assert_array_equal(bounded, stable)
    np.testing.assert_array_equal(growing, ~stable)
    for i, h2 in enumerate(WHEELS):
        e1, e3 = linear_transverse(RACKET, SPIN, h2, (EPS, EPS), STABILITY_TS)
        small = np.hypot(e1, e3) < 1e-3  # the linear regime: nonlinear terms ~1e-3 relative
        amplitude = np.max(np.hypot(e1, e3)[small])
        assert np.max(np.abs(omega[i, small, 0] - e1[small])) < 5e-3 * amplitude, h2
        assert np.max(np.abs(omega[i, small, 2] - e3[small])) < 5e-3 * amplitude, h2


# --------------------------------------------------------------------------------------------------
# Gradients


def _final_omega(h, inertia, **kwargs):
    # The scene of test_against_dop853_with_a_torque (orientation included): the central differences
    # below run its compiled solves again.
    model = rj.Gyrostat(inertia, h, torque=rj.ConstantTorque(TORQUE))
    return rj.simulate(model, rj.State(OMEGA0, Q0), TS, **kwargs).omega[-1]


@pytest.mark.slow
@pytest.mark.parametrize("method, step, tol", [("precise", 1e-4, 3e-6), ("rkmk", 1e-5, 1e-7)])
def test_grad_wrt_rotor_momentum_and_inertia_vs_central_differences(method, step, tol):
    """Reference: central differences of the final omega against reverse-mode jax.jacrev with
    respect to the rotor momentum and the moments. Steps: RKMK's fixed steps make the result a
    smooth function of the parameters (measured: the difference falls as step^2, 5e-9 relative at
    1e-5); the adaptive preset's step choices add noise of ~rtol / step."""
    kwargs = {"accuracy": "precise"} if method == "precise" else {"solver": rj.solvers.RKMK(), "dt0": 0.01}
    # One compiled program for the derivative: eagerly each operation around the solve compiles one
    # of its own. The differences call simulate as the comparison with DOP853 does (same scene and
    # options), which loads its solve instead of compiling a program of their own.
    final = functools.partial(_final_omega, **kwargs)
    jac_h, jac_inertia = jax.jit(jax.jacrev(final, argnums=(0, 1)))(jnp.asarray(H), jnp.asarray(INERTIA))
    fd_h = central_difference(lambda x: final(x, INERTIA), H, step)
    fd_inertia = central_difference(lambda x: final(H, x), INERTIA, step * INERTIA)
    np.testing.assert_allclose(np.asarray(jac_h), fd_h, rtol=0, atol=tol * np.max(np.abs(fd_h)))
    np.testing.assert_allclose(
        np.asarray(jac_inertia), fd_inertia, rtol=0, atol=tol * np.max(np.abs(fd_inertia))
    )
    assert np.max(np.abs(fd_h)) > 0.1  # the rotors move the result


# --------------------------------------------------------------------------------------------------
# Batches and float32


@pytest.mark.slow
def test_batch_matches_per_body():
    """Reference: the same bodies one at a time. Leading axes on the inertia and the rotor momentum,
    broadcast against each other and against the state. (Bodies of a chunk share a step size, so the
    batch and the single runs agree to the tolerance, not bit for bit. The precise preset, as the
    torque-free test: the single runs are its compiled solve.)"""
    rng = np.random.default_rng(7)
    inertia = INERTIA * (1 + 0.05 * rng.uniform(-1, 1, (4, 3)))  # physical: I1 + I2 > I3
    h = H + 0.5 * rng.normal(size=(4, 3))
    omega0 = OMEGA0 + 0.3 * rng.normal(size=(4, 3))
    batch = rj.simulate(rj.Gyrostat(inertia, h), rj.State(omega0, Q0), TS, accuracy="precise")
    shared = rj.simulate(rj.Gyrostat(inertia, H), rj.State(omega0, Q0), TS, accuracy="precise")
    assert batch.omega.shape == (4, TS.size, 3) and batch.orientation.shape == (4, TS.size, 4)
    # NumPy rows and differences: eagerly each jnp index and difference compiled a program.
    batch_omega, batch_q, shared_omega = (
        np.asarray(x) for x in (batch.omega, batch.orientation, shared.omega)
    )
    for i in range(4):
        one = rj.simulate(rj.Gyrostat(inertia[i], h[i]), rj.State(omega0[i], Q0), TS, accuracy="precise")
        assert rel_err(batch_omega[i], np.asarray(one.omega)) < 1e-6
        assert float(np.max(np.abs(batch_q[i] - np.asarray(one.orientation)))) < 1e-6
        omega_ref, _ = dop853(gyrostat_accel(inertia[i], H), omega0[i], TS)
        assert rel_err(shared_omega[i], omega_ref) < 1e-6


@pytest.mark.slow
def test_float32():
    """Reference: the float64 run. Float32 inputs give float32 results at float32's accuracy."""
    model = rj.Gyrostat(INERTIA.astype(np.float32), H.astype(np.float32))
    state = rj.State(OMEGA0.astype(np.float32), Q0.astype(np.float32))
    traj = rj.simulate(model, state, TS.astype(np.float32))
    assert traj.omega.dtype == jnp.float32 and traj.orientation.dtype == jnp.float32
    ref = rj.simulate(rj.Gyrostat(INERTIA, H), rj.State(OMEGA0, Q0), TS, accuracy="precise")
    assert rel_err(traj.omega, np.asarray(ref.omega)) < 1e-4
    assert float(traj.invariants()["energy"]) < 1e-5


# --------------------------------------------------------------------------------------------------
# Files and bad input


def test_save_and_load_round_trip(tmp_path):
    """Reference: the trajectory before saving, bit for bit, and a rerun of the loaded model."""
    model = rj.Gyrostat(INERTIA, H, torque=rj.ConstantTorque(TORQUE))
    traj = rj.simulate(model, rj.State(OMEGA0, Q0), TS)
    traj.save(tmp_path / "gyro.npz")
    back = rj.Trajectory.load(tmp_path / "gyro.npz")
    assert type(back.model) is rj.Gyrostat
    np.testing.assert_array_equal(np.asarray(back.model.rotor_momentum), H)
    np.testing.assert_array_equal(np.asarray(back.model.torques[0].torque), TORQUE)
    np.testing.assert_array_equal(np.asarray(back.omega), np.asarray(traj.omega))
    assert {k: float(v) for k, v in back.invariants().items()} == {
        k: float(v) for k, v in traj.invariants().items()
    }
    again = rj.simulate(back.model, rj.State(OMEGA0, Q0), TS)
    np.testing.assert_array_equal(np.asarray(again.omega), np.asarray(traj.omega))


def test_bad_input_names_the_argument():
    """Reference: the messages. Shapes raise when the model is built, NaN when it is simulated, and
    the closed form and the Lie-Poisson splitting, which have no rotors, say so."""
    with pytest.raises(ValueError, match="rotor_momentum"):
        rj.Gyrostat(INERTIA, [0.0, 1.0])
    with pytest.raises(TypeError, match="rotor_momentum"):
        rj.Gyrostat(INERTIA, np.array([1j, 0, 0]))
    state = rj.State(OMEGA0, Q0)
    expect_error(
        lambda: rj.simulate(rj.Gyrostat(INERTIA, [0.0, np.nan, 0.0]), state, TS), "rotor_momentum", "NaN"
    )
    with pytest.raises(ValueError, match="rotor_momentum"):
        rj.simulate(rj.Gyrostat(INERTIA, np.zeros((2, 3))), rj.State(np.zeros((3, 3))), TS)
    with pytest.raises(ValueError, match="Gyrostat") as info:
        rj.simulate(rj.Gyrostat(INERTIA, H), state, TS, accuracy="exact")
    assert "exact" in str(info.value)
    with pytest.raises(ValueError, match="Gyrostat"):
        rj.simulate(rj.Gyrostat(INERTIA, H), state, TS, solver=rj.solvers.LiePoissonSplitting(), dt0=0.1)


@pytest.mark.slow
def test_invariants_with_damping():
    """Reference: the physics. With a viscous torque nothing is conserved and nothing is reported
    as if it were."""
    model = rj.Gyrostat(INERTIA, H, torque=rj.ViscousDamping(0.1))
    traj = rj.simulate(model, rj.State(OMEGA0, Q0), TS)
    assert set(traj.invariants()) == {"quaternion_norm"}
    assert not model.conserves_energy and not model.conserves_angular_momentum
    energy = 0.5 * np.sum(np.asarray(traj.omega) ** 2 * INERTIA, axis=-1)
    assert np.all(np.diff(energy) < 0)  # d/dt (omega . I omega / 2) = -0.1 |omega|^2


@pytest.mark.slow
def test_trajectory_angular_momentum_includes_the_rotors():
    """Reference: ``L = I omega + h`` in numpy. Trajectory.angular_momentum and the |L| invariants
    should use the model's angular momentum."""
    traj = rj.simulate(rj.Gyrostat(INERTIA, H), rj.State(OMEGA0, Q0), TS, accuracy="precise")
    np.testing.assert_allclose(
        np.asarray(traj.angular_momentum()), momentum(INERTIA, H, np.asarray(traj.omega)), rtol=1e-14
    )
    assert float(traj.invariants()["angular_momentum_norm"]) < 1e-12
