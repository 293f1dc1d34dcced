"""simulate() against closed forms, conservation laws, convergence order, finite differences and the
variational equations (derivatives integrated by scipy).

Compiles are the expensive part on a small CPU, so tests share shapes and configurations: the
tolerance is a traced array (no recompilation), and a few module-level trajectories serve several
tests. References for derivatives integrate the variational equations with scipy rather than
differentiate a second rigidjax program (nothing to compile, and independent of JAX).
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp
from helpers import counted_calls, variational_dop853

import rigidjax as rj

F64 = jnp.float64
IDENTITY = jnp.array([1.0, 0.0, 0.0, 0.0])


def euler_equations_sympy(inertia, torque=(0, 0, 0)):
    """Euler's equations ``I_i w_i' = (I_j - I_k) w_j w_k + tau_i`` in the symbols ``w1:4`` (and those
    of ``inertia`` and ``torque`` where they are symbols): (rhs, the symbols of omega)."""
    I1, I2, I3 = inertia
    w1, w2, w3 = w = sp.symbols("w1:4")
    t1, t2, t3 = torque
    rhs = [((I2 - I3) * w2 * w3 + t1) / I1, ((I3 - I1) * w3 * w1 + t2) / I2, ((I1 - I2) * w1 * w2 + t3) / I3]
    return rhs, list(w)


def symmetric_top_exact(I1, I3, omega0, ts):
    """Torque-free symmetric top: w1 + i w2 = (w1 + i w2)(0) exp(i Omega t), Omega = (I3-I1)/I1 w3."""
    Omega = (I3 - I1) / I1 * omega0[2]
    transverse = (omega0[0] + 1j * omega0[1]) * np.exp(1j * Omega * ts)
    return np.stack([transverse.real, transverse.imag, np.full_like(ts, omega0[2])], axis=-1)


# One compiled configuration per preset (FreeBody principal, omega-only, one body, 801 samples) serves
# the symmetric-top tests: the Earth, a 1e5 rad/s rotor and a laboratory top, each on its own span.
# 801 samples (every 20th one of 41 evenly spaced) so that the test of the
# presets between the solver's steps checks the same programs rather than compiling three more.
SYM_TS = np.linspace(0.0, 1.0, 801)
SYM_INERTIA = np.array(
    [
        [8.0101e37, 8.0101e37, 8.0365e37],  # the Earth (kg m^2), dynamical ellipticity ~3.3e-3
        [2.0e-6, 2.0e-6, 3.5e-6],  # a small 1e5 rad/s rotor
        [2.0, 2.0, 3.0],  # a laboratory top
    ]
)
EARTH_SPIN = 7.292115e-5
EULER_PERIOD = 2 * np.pi / ((SYM_INERTIA[0, 2] - SYM_INERTIA[0, 0]) / SYM_INERTIA[0, 0] * EARTH_SPIN)
SYM_OMEGA = np.array([[1e-11, 0.0, EARTH_SPIN], [300.0, -200.0, 1e5], [0.3, 0.0, 5.0]])
# Each body gets its own time span by scaling: simulate the Earth over 1.5 Euler periods, the
# rotor over ~3 ms and the top over 10 s, all with the same 41 samples of normalised time.
SYM_SPANS = np.array([1.5 * EULER_PERIOD, 3e-3, 10.0])


def _simulate_symmetric(i, accuracy):
    ts = jnp.asarray(SYM_TS * SYM_SPANS[i])
    return rj.simulate(
        rj.FreeBody(jnp.asarray(SYM_INERTIA[i])), rj.State(jnp.asarray(SYM_OMEGA[i])), ts, accuracy=accuracy
    )


@pytest.mark.parametrize("accuracy, bound", [("fast", 1e-3), ("balanced", 1e-6), ("precise", 1e-9)])
@pytest.mark.parametrize("body", [0, 1, 2], ids=["earth", "rotor", "top"])
def test_symmetric_top_closed_form_in_any_units(body, accuracy, bound):
    """The wobble is resolved relative to its own amplitude: the Earth's 1e-11 rad/s on a 7e-5 rad/s
    spin, and a 1e5 rad/s rotor, come out at the preset's accuracy with default arguments."""
    traj = _simulate_symmetric(body, accuracy)
    ts = SYM_TS * SYM_SPANS[body]
    exact = symmetric_top_exact(SYM_INERTIA[body, 0], SYM_INERTIA[body, 2], SYM_OMEGA[body], ts)
    omega = np.asarray(traj.omega)
    amplitude = np.hypot(*SYM_OMEGA[body, :2])
    wobble_error = np.max(np.abs(omega[:, :2] - exact[:, :2])) / amplitude
    assert wobble_error < bound, wobble_error
    np.testing.assert_allclose(omega[:, 2], exact[:, 2], rtol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("accuracy, bound", [("fast", 1e-3), ("balanced", 1e-6), ("precise", 1e-9)])
def test_preset_accuracy_holds_at_every_one_of_800_sample_times(accuracy, bound):
    """The presets' promises hold between the solver's steps too, where the samples come from its
    dense output ("precise" puts a step on every sample time): each symmetric body above over its
    span, 801 samples instead of 41, every sample against the closed form."""
    assert SYM_TS.shape == (801,)  # the closed-form test's programs, compiled once for both
    for body in range(3):
        ts = SYM_TS * SYM_SPANS[body]
        traj = _simulate_symmetric(body, accuracy)
        exact = symmetric_top_exact(SYM_INERTIA[body, 0], SYM_INERTIA[body, 2], SYM_OMEGA[body], ts)
        amplitude = np.hypot(*SYM_OMEGA[body, :2])
        wobble_error = np.max(np.abs(np.asarray(traj.omega)[:, :2] - exact[:, :2])) / amplitude
        assert wobble_error < bound, (body, wobble_error)


def test_free_precession_rate_matches_simulated_wobble():
    traj = _simulate_symmetric(0, "balanced")
    omega = np.asarray(traj.omega)
    phase = np.unwrap(np.arctan2(omega[:, 1], omega[:, 0]))
    rate = np.polyfit(np.asarray(traj.ts), phase, 1)[0]
    expected = rj.free_precession_rate(SYM_INERTIA[0, 0], SYM_INERTIA[0, 2], EARTH_SPIN)
    np.testing.assert_allclose(rate, float(expected), rtol=1e-7)


# The free rigid body of Hairer, Lubich & Wanner (Geometric Numerical Integration, IV.1): period
# 10.73147 s. Their moments (2, 1, 2/3) violate the triangle inequality; the physical body with the
# same angular-momentum motion has 1/I' = 1/I + 1.
HLW_INERTIA = jnp.array([2 / 3, 1 / 2, 2 / 5])
HLW_L0 = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])
HLW_PERIOD = 10.73147


@pytest.fixture(scope="module")
def hlw_trajectory():
    ts = jnp.linspace(0.0, 3 * HLW_PERIOD, 301)
    return rj.simulate(
        rj.FreeBody(HLW_INERTIA), rj.State(HLW_L0 / HLW_INERTIA, IDENTITY), ts, accuracy="precise"
    )


def test_hairer_lubich_wanner_period(hlw_trajectory):
    """omega returns to its start after each published period (ts hits t = P, 2P, 3P exactly)."""
    omega = np.asarray(hlw_trajectory.omega)
    # The period is given to 6 digits: allow |d omega/dt| ~ 1 times 5e-6 s per period elapsed.
    for k, index in enumerate([100, 200, 300], start=1):
        np.testing.assert_allclose(omega[index], omega[0], atol=1e-5 * k)
    # Half a period away it is far from the start, so the check above cannot pass by accident.
    assert np.max(np.abs(omega[50] - omega[0])) > 0.1


def test_torque_free_conservation(hlw_trajectory):
    inv = {k: float(v) for k, v in hlw_trajectory.invariants().items()}
    assert inv["energy"] < 1e-11
    assert inv["angular_momentum_norm"] < 1e-11
    assert inv["space_angular_momentum"] < 1e-9
    assert inv["quaternion_norm"] < 1e-9
    # Independent check of the space-frame momentum: R(q) @ (I omega) with matrices, not quat_rotate.
    R = np.asarray(rj.matrix_from_quat(hlw_trajectory.orientation))
    L_space = np.einsum("tij,tj->ti", R, np.asarray(HLW_INERTIA) * np.asarray(hlw_trajectory.omega))
    np.testing.assert_allclose(L_space, np.broadcast_to(np.asarray(HLW_L0), L_space.shape), atol=1e-9)


def test_omega_only_and_quaternion_agree(hlw_trajectory):
    ts = hlw_trajectory.ts
    omega_only = rj.simulate(rj.FreeBody(HLW_INERTIA), rj.State(HLW_L0 / HLW_INERTIA), ts, accuracy="precise")
    assert omega_only.orientation is None
    np.testing.assert_allclose(np.asarray(omega_only.omega), np.asarray(hlw_trajectory.omega), atol=1e-9)


# A batch of tennis-racket bodies near each principal axis (module scope: compiled once).
def _racket_batch(n_per_axis=4, seed=0):
    rng = np.random.default_rng(seed)
    inertia = np.array([1.0, 2.0, 2.5]) * (1 + 0.02 * rng.uniform(-1, 1, (3 * n_per_axis, 3)))
    omega = np.zeros((3 * n_per_axis, 3))
    for axis in range(3):
        rows = slice(axis * n_per_axis, (axis + 1) * n_per_axis)
        omega[rows] = 0.01 * rng.normal(size=(n_per_axis, 3))
        omega[rows, axis] = 3.0
    return jnp.asarray(inertia), jnp.asarray(omega)


@pytest.fixture(scope="module")
def racket():
    inertia, omega = _racket_batch()
    q0 = jnp.broadcast_to(IDENTITY, (omega.shape[0], 4))
    ts = jnp.linspace(0.0, 20.0, 201)
    traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega, q0), ts, chunk_size=5)
    return inertia, omega, q0, ts, traj


def test_tennis_racket_flip(racket):
    _, omega0, _, _, traj = racket
    omega = np.asarray(traj.omega)
    n = omega.shape[0] // 3
    for axis in range(3):
        w = omega[axis * n : (axis + 1) * n, :, axis]
        flipped = np.any(w < 0, axis=-1)
        if axis == 1:
            assert flipped.all(), "spin near the intermediate axis must flip"
        else:
            assert not flipped.any(), f"spin near axis {axis + 1} must stay stable"


def test_batch_equals_per_body(racket):
    """Chunked, sorted, shared-step batch integration agrees with one-body solves."""
    inertia, omega0, q0, ts, traj = racket
    for i in [0, 5, 11]:
        single = rj.simulate(rj.FreeBody(inertia[i]), rj.State(omega0[i], q0[i]), ts)
        # Chaotic flips amplify differences in step sequence; compare well before the first flip
        # and the invariants everywhere.
        np.testing.assert_allclose(np.asarray(traj.omega[i, :40]), np.asarray(single.omega[:40]), atol=1e-6)
    inv = traj.invariants()
    assert float(jnp.max(inv["energy"])) < 1e-7
    assert float(jnp.max(inv["space_angular_momentum"])) < 1e-5


def test_batch_shapes_broadcast():
    inertia = jnp.array([1.0, 2.0, 3.0])
    omega = jnp.broadcast_to(jnp.array([0.1, 3.0, 0.1]), (2, 3, 3))
    ts = jnp.linspace(0.0, 1.0, 5)
    traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega), ts)
    assert traj.omega.shape == (2, 3, 5, 3)
    assert traj.success.shape == (2, 3)
    np.testing.assert_allclose(np.asarray(traj.omega[1, 2]), np.asarray(traj.omega[0, 0]), rtol=1e-12)


@pytest.mark.slow
def test_heavy_top_conservation_and_precession():
    inertia = jnp.array([1.0, 1.0, 0.5]) * 1e-2
    mass, l, g = 0.5, 0.05, 9.81
    top = rj.HeavyTop(inertia, mass, jnp.array([0.0, 0.0, l]), g)
    omega3 = 200.0
    theta0 = 0.4
    q0 = rj.quat_from_euler(jnp.array([0.0, theta0, 0.0]))
    ts = jnp.linspace(0.0, 4.0, 401)
    traj = rj.simulate(top, rj.State(jnp.array([0.0, 0.0, omega3]), q0), ts, accuracy="precise")
    inv = traj.invariants()
    assert float(inv["energy"]) < 1e-10
    assert float(inv["vertical_angular_momentum"]) < 1e-10
    angles = np.asarray(traj.euler_angles())
    rate = np.polyfit(np.asarray(ts), angles[:, 0], 1)[0]
    fast_top = mass * g * l / (float(inertia[2]) * omega3)
    np.testing.assert_allclose(rate, fast_top, rtol=0.02)
    # Nutation stays small for a fast top: theta within a few percent of its start.
    assert np.max(np.abs(angles[:, 1] - theta0)) < 0.05


def test_euler_angles_follow_a_spin_of_more_than_pi_per_sample():
    """A torque-free symmetric top (A = 1, C = 0.5) with L along space Z: theta constant,
    phi' = C w3 / (A cos theta), psi' = w3 (A - C) / A (Goldstein 5.6), here 108.6 and 100 rad/s,
    sampled every 0.05 s (5.4 and 5 rad per sample). Unwrapping by the nearest branch ran both
    angles backwards."""
    a, c, omega3, theta = 1.0, 0.5, 200.0, 0.4
    phi_rate, psi_rate = c * omega3 / (a * np.cos(theta)), omega3 * (a - c) / a
    omega0 = jnp.array([0.0, phi_rate * np.sin(theta), omega3])
    ts = jnp.linspace(0.0, 2.0, 41)
    state = rj.State(omega0, rj.quat_from_euler(jnp.array([0.0, theta, 0.0])))
    traj = rj.simulate(rj.FreeBody(jnp.array([a, a, c])), state, ts, accuracy="exact")
    expected = np.stack([phi_rate * np.asarray(ts), np.full(41, theta), psi_rate * np.asarray(ts)], axis=-1)
    np.testing.assert_allclose(np.asarray(traj.euler_angles()), expected, rtol=0, atol=1e-9)


@pytest.mark.slow
def test_sleeping_top_criterion():
    """(I3 w3)^2 > 4 I1 m g l: an upright top stays up; below it, it falls."""
    I1, I3, mass, l, g = 1e-2, 5e-3, 0.5, 0.05, 9.81
    critical = np.sqrt(4 * I1 * mass * g * l) / I3
    inertia = jnp.array([[I1, I1, I3], [I1, I1, I3]])
    top = rj.HeavyTop(inertia, mass, jnp.array([0.0, 0.0, l]), g)
    omega = jnp.array([[0.0, 0.0, 1.3 * critical], [0.0, 0.0, 0.7 * critical]])
    q0 = jnp.broadcast_to(rj.quat_from_euler(jnp.array([0.0, 1e-3, 0.0])), (2, 4))
    traj = rj.simulate(top, rj.State(omega, q0), jnp.linspace(0.0, 3.0, 301))
    theta = np.asarray(traj.euler_angles())[..., 1]
    assert np.max(theta[0]) < 0.01
    assert np.max(theta[1]) > 0.5


@pytest.mark.slow
def test_constant_and_damping_torques_on_a_sphere():
    """For a sphere the gyroscopic term vanishes: body torque gives w0 + tau t / I, damping gives
    w0 exp(-c t / I), and a space-fixed torque changes the space-frame momentum as L0 + tau t."""
    I = 0.4
    inertia = jnp.array([I, I, I])
    ts = jnp.linspace(0.0, 2.0, 21)
    w0 = jnp.array([1.0, -2.0, 0.5])
    tau = jnp.array([0.1, 0.2, -0.3])
    # The closed forms in NumPy (eager jnp operations would each compile a program of their own).
    t, w0_, tau_ = np.asarray(ts), np.asarray(w0), np.asarray(tau)
    traj = rj.simulate(rj.RigidBody(inertia, rj.ConstantTorque(tau)), rj.State(w0), ts)
    np.testing.assert_allclose(np.asarray(traj.omega), w0_ + tau_ * t[:, None] / I, rtol=1e-9)
    c = 0.3
    traj = rj.simulate(rj.RigidBody(inertia, rj.ViscousDamping(c)), rj.State(w0), ts, accuracy="precise")
    np.testing.assert_allclose(np.asarray(traj.omega), w0_ * np.exp(-c * t / I)[:, None], rtol=1e-9)
    q0 = rj.quat_from_euler(jnp.array([0.3, 0.7, -0.2]))
    traj = rj.simulate(rj.RigidBody(inertia, rj.ConstantTorque(tau, frame="space")), rj.State(w0, q0), ts)
    L0 = np.asarray(rj.matrix_from_quat(q0)) @ (I * w0_)  # R(q0) L0 with a matrix, not quat_rotate
    np.testing.assert_allclose(np.asarray(traj.space_angular_momentum()), L0 + tau_ * t[:, None], atol=1e-7)


def test_user_torque_callable_and_no_recompilation():
    traces = []

    def spin_up(t, state, args):
        traces.append(1)
        return jnp.array([0.0, 0.0, 1.0], state.omega.dtype) * args

    inertia = jnp.array([1.0, 1.0, 2.0])
    ts = jnp.linspace(0.0, 1.0, 11)
    model = rj.RigidBody(inertia, rj.Torque(spin_up, needs_orientation=False))
    traj = rj.simulate(model, rj.State(jnp.array([0.0, 0.0, 1.0])), ts, args=jnp.asarray(2.0))
    np.testing.assert_allclose(np.asarray(traj.omega[:, 2]), np.asarray(1.0 + 2.0 * ts / 2.0), rtol=1e-9)
    n_traces = len(traces)
    # New numbers, same shapes, same tolerance preset: no new trace (hence no recompilation).
    model2 = rj.RigidBody(inertia * 1.5, rj.Torque(spin_up, needs_orientation=False))
    traj2 = rj.simulate(
        model2, rj.State(jnp.array([0.1, 0.0, 2.0])), ts * 2, args=jnp.asarray(3.0), rtol=1e-9
    )
    traj2.omega.block_until_ready()
    assert len(traces) == n_traces


@pytest.mark.parametrize("solver, order", [(diffrax.Tsit5(), 5), (diffrax.Dopri8(), 8)])
def test_convergence_order(solver, order):
    """Fixed steps on a smooth scene: log(error) against log(dt) has the solver's slope."""
    inertia = jnp.array([2.0, 2.0, 3.0])
    w0 = jnp.array([0.3, 0.0, 5.0])
    ts = jnp.array([0.0, 4.0])
    exact = symmetric_top_exact(2.0, 3.0, np.asarray(w0), np.asarray(ts))[-1]
    steps = np.array([0.2, 0.1, 0.05]) if order == 5 else np.array([0.4, 0.2, 0.1])
    errors = []
    for dt in steps:
        traj = rj.simulate(
            rj.FreeBody(inertia),
            rj.State(w0),
            ts,
            solver=solver,
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=float(dt),
        )
        errors.append(np.max(np.abs(np.asarray(traj.omega[-1]) - exact)))
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert order - 0.5 < slope < order + 1.0, (slope, errors)


def test_float32_close_to_float64_on_a_regular_scene():
    inertia = np.array([2.0, 2.0, 3.0])
    w0 = np.array([0.3, 0.0, 5.0])
    ts = np.linspace(0.0, 5.0, 11)
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    t32 = rj.simulate(
        rj.FreeBody(inertia.astype(np.float32)),
        rj.State(w0.astype(np.float32), q0.astype(np.float32)),
        ts.astype(np.float32),
        accuracy="fast",
    )
    assert t32.omega.dtype == jnp.float32 and t32.orientation.dtype == jnp.float32
    exact = symmetric_top_exact(2.0, 3.0, w0, ts)
    np.testing.assert_allclose(np.asarray(t32.omega, np.float64), exact, atol=1e-4)


def test_float32_earth_in_si_units():
    """Moments of 8e37 kg m^2 in float32: products of moments overflow float32, so the scale
    computation must work with ratios. The wobble comes out to float32's limit, which is set by the
    moment ratio itself ((C - A)/A = 3.3e-3 known to ~1e-7 / 3.3e-3 = 3e-5 relative)."""
    inertia = SYM_INERTIA[0].astype(np.float32)
    normalised = np.linspace(0.0, 1.0, 41)  # a float32 program of its own
    ts = (normalised * SYM_SPANS[0]).astype(np.float32)
    traj = rj.simulate(rj.FreeBody(inertia), rj.State(SYM_OMEGA[0].astype(np.float32)), ts)
    omega = np.asarray(traj.omega, np.float64)
    exact = symmetric_top_exact(SYM_INERTIA[0, 0], SYM_INERTIA[0, 2], SYM_OMEGA[0], normalised * SYM_SPANS[0])
    assert traj.omega.dtype == jnp.float32 and bool(traj.success)
    assert np.max(np.abs(omega[:, :2] - exact[:, :2])) / 1e-11 < 3e-4
    assert all(np.isfinite(float(v)) for v in traj.invariants().values())


@pytest.mark.slow
def test_gradient_matches_finite_differences():
    ts = jnp.array([0.0, 3.0])
    w0 = jnp.array([0.2, 1.0, 0.3])

    def final_omega(inertia):
        return rj.simulate(rj.FreeBody(inertia), rj.State(w0), ts, accuracy="precise").omega[-1]

    inertia = jnp.array([1.0, 2.0, 2.5])
    jac = np.asarray(jax.jit(jax.jacrev(final_omega))(inertia))  # one program, not op by op
    # Reference: the variational equations in the moments (states of zero rate), by scipy. Central
    # differences of the "precise" solve (h = 1e-6, the reference before) are within 1.7e-8 of it,
    # jacrev within 1.2e-11.
    moments = sp.symbols("I1:4")
    rhs, w = euler_equations_sympy(moments)
    z0 = np.concatenate([np.asarray(w0), np.asarray(inertia)])
    _, S = variational_dop853(rhs + [0, 0, 0], w + list(moments), z0, np.eye(6, 3, k=-3), float(ts[-1]))
    np.testing.assert_allclose(jac, S[:3], rtol=1e-5, atol=1e-7)


def test_single_output_time_returns_initial_state():
    q0 = rj.quat_from_euler(jnp.array([0.1, 0.2, 0.3]))
    traj = rj.simulate(
        rj.FreeBody(jnp.array([1.0, 2.0, 2.5])), rj.State(jnp.array([1.0, 2.0, 3.0]), q0), jnp.array([0.5])
    )
    np.testing.assert_allclose(np.asarray(traj.omega[0]), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(np.asarray(traj.orientation[0]), np.asarray(q0), atol=1e-15)


# ------------------------------------------------------------------------------------------------
# Bad input: a clear error naming the problem, also inside jit.

GOOD_INERTIA = jnp.array([1.0, 2.0, 2.5])
GOOD_TS = jnp.linspace(0.0, 1.0, 3)


@pytest.mark.parametrize(
    "inertia, omega, q, ts, match",
    [
        (jnp.array([1.0, 2.0, 4.0]), jnp.ones(3), None, GOOD_TS, "triangle"),
        (jnp.array([-1.0, 2.0, 2.5]), jnp.ones(3), None, GOOD_TS, "positive"),
        (GOOD_INERTIA, jnp.array([1.0, jnp.nan, 0.0]), None, GOOD_TS, "NaN"),
        (GOOD_INERTIA, jnp.ones(3), jnp.array([1.0, 0.1, 0.0, 0.0]), GOOD_TS, "unit quaternion"),
        (GOOD_INERTIA, jnp.ones(3), None, jnp.array([0.0, 1.0, 0.5]), "strictly increasing"),
        (GOOD_INERTIA, jnp.ones(3), None, jnp.array([0.0, 1.0, 1.0]), "strictly increasing"),
    ],
)
def test_bad_input_errors(inertia, omega, q, ts, match):
    with pytest.raises(Exception, match=match):
        traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega, q), ts)
        traj.omega.block_until_ready()


def test_wrong_shapes_and_missing_orientation():
    with pytest.raises(ValueError, match="omega"):
        rj.State(jnp.ones(4))
    with pytest.raises(ValueError, match="orientation"):
        rj.simulate(
            rj.HeavyTop(GOOD_INERTIA, 1.0, jnp.array([0.0, 0.0, 0.1])), rj.State(jnp.ones(3)), GOOD_TS
        )
    with pytest.raises(ValueError, match="ts"):
        rj.simulate(rj.FreeBody(GOOD_INERTIA), rj.State(jnp.ones(3)), jnp.ones((2, 2)))
    with pytest.raises(ValueError, match="accuracy"):
        rj.simulate(rj.FreeBody(GOOD_INERTIA), rj.State(jnp.ones(3)), GOOD_TS, accuracy="sloppy")


def test_step_limit_is_reported():
    model, state = rj.FreeBody(GOOD_INERTIA), rj.State(jnp.array([0.1, 3.0, 0.1]))
    ts = jnp.linspace(0.0, 20.0, 3)
    with pytest.raises(Exception, match="max_steps"):
        rj.simulate(model, state, ts, max_steps=5).omega.block_until_ready()
    traj = rj.simulate(model, state, ts, max_steps=5, throw=False)
    assert not bool(traj.success)
    # The initial state is all the run reached: kept; the samples it never reached are NaN.
    assert int(traj.stats["first_failed_sample"]) == 1
    np.testing.assert_array_equal(np.asarray(traj.omega[0]), [0.1, 3.0, 0.1])
    assert np.all(np.isnan(np.asarray(traj.omega[1:])))


# ------------------------------------------------------------------------------------------------
# Orientation representations and devices.


@pytest.mark.slow
def test_euler_angle_state_agrees_with_quaternions_and_stops_at_gimbal_lock():
    top = rj.HeavyTop(jnp.array([1.0, 1.0, 0.5]), 1.0, jnp.array([0.0, 0.0, 0.1]))
    state = rj.State(jnp.array([0.5, 0.2, 60.0]), rj.quat_from_euler(jnp.array([0.2, 0.5, 0.1])))
    ts = jnp.linspace(0.0, 2.0, 21)
    quat = rj.simulate(top, state, ts, accuracy="precise")
    euler = rj.simulate(top, state, ts, accuracy="precise", representation="euler")
    R_quat = np.asarray(rj.matrix_from_quat(quat.orientation))
    R_euler = np.asarray(rj.matrix_from_quat(euler.orientation))
    np.testing.assert_allclose(R_euler, R_quat, atol=1e-8)
    np.testing.assert_allclose(np.asarray(euler.omega), np.asarray(quat.omega), atol=1e-7)
    # A free body turning about its line of nodes passes exactly through theta = pi.
    free = rj.FreeBody(jnp.array([1.0, 2.0, 2.5]))
    through_lock = rj.State(jnp.array([3.0, 0.0, 0.0]), rj.quat_from_euler(jnp.array([0.0, 1.0, 0.0])))
    # theta = 1 + 3 t comes within 1e-3 (sin theta) of pi at t = (pi - asin(1e-3) - 1) / 3 = 0.7135:
    # the lock is located in time, inside the sample interval (0.7, 0.8) (it was seen only at the
    # end of the step that crossed it, up to a step later).
    with pytest.raises(Exception, match=r"between t = 0.7 s and t = 0.8 s.*gimbal lock"):
        rj.simulate(free, through_lock, ts, representation="euler").omega.block_until_ready()
    flagged = rj.simulate(free, through_lock, ts, representation="euler", throw=False)
    # The quaternion state goes through the same motion without trouble.
    ok = rj.simulate(free, through_lock, ts)
    assert bool(ok.success) and float(ok.invariants()["energy"]) < 1e-7
    # The samples before the lock are kept and agree with the quaternion run, the run is NaN from
    # the first sample after it.
    first = int(flagged.stats["first_failed_sample"])
    t_lock = (np.pi - np.arcsin(1e-3) - 1.0) / 3.0
    assert not bool(flagged.success) and float(ts[first - 1]) < t_lock <= float(ts[first])
    before = np.asarray(ts) < t_lock
    np.testing.assert_allclose(np.asarray(flagged.omega)[before], np.asarray(ok.omega)[before], atol=1e-7)
    assert np.all(np.isnan(np.asarray(flagged.omega[first:])))
    # float32 (under x64): the root finder's time tolerance is one float32 resolves (at 1e-8 it did
    # not converge: "diffrax result code 7"), and its condition is compared in the default dtype.
    f32 = np.float32
    free32 = rj.FreeBody(f32([1.0, 2.0, 2.5]))
    lock32 = rj.State(f32([3.0, 0.0, 0.0]), rj.quat_from_euler(f32([0.0, 1.0, 0.0])))
    with pytest.raises(Exception, match=r"between t = 0.7 s and t = 0.8 s.*gimbal lock"):
        rj.simulate(free32, lock32, ts.astype(f32), representation="euler", accuracy="fast")


@pytest.mark.slow
def test_per_body_torques_in_a_batch():
    """Torque fields carry batch axes like the model's: each sphere gets its own torque."""
    I = 0.4
    n = 5
    inertia = jnp.full((n, 3), I)
    ts = jnp.linspace(0.0, 2.0, 11)
    w0 = jnp.array([1.0, -2.0, 0.5])
    tau = jnp.linspace(-0.3, 0.3, 3 * n).reshape(n, 3)
    traj = rj.simulate(rj.RigidBody(inertia, rj.ConstantTorque(tau)), rj.State(w0), ts, accuracy="precise")
    # The closed forms in NumPy (eager jnp operations would each compile a program of their own).
    t, w0_, tau_ = np.asarray(ts), np.asarray(w0), np.asarray(tau)
    expected = w0_ + tau_[:, None, :] * t[None, :, None] / I
    np.testing.assert_allclose(np.asarray(traj.omega), expected, rtol=1e-9, atol=1e-12)
    c = jnp.linspace(0.1, 0.5, n)[:, None]  # per-body scalar coefficients: shape (N, 1)
    traj = rj.simulate(rj.RigidBody(inertia, rj.ViscousDamping(c)), rj.State(w0), ts, accuracy="precise")
    expected = w0_ * np.exp(-np.asarray(c)[:, :, None] * t[None, :, None] / I)
    np.testing.assert_allclose(np.asarray(traj.omega), expected, rtol=1e-9)


@pytest.mark.slow
def test_one_fast_body_cannot_hide_in_a_slow_batch():
    """63 slow symmetric tops and one 1000x faster (400 wobble cycles). The shared step is accepted
    only when the worst body is within tolerance, so the fast body is exactly as accurate in the
    batch as alone, and the slow ones are better than the preset; an RMS norm over the batch (what
    diffrax does by default) lets the fast body's error grow ~14x."""
    import optimistix as optx

    n, fast = 64, 17
    speed = np.ones(n)
    speed[fast] = 1000.0
    omega0 = np.stack([0.3 * speed, np.zeros(n), 5.0 * speed], axis=-1)
    ts = np.linspace(0.0, 1.0, 21)
    model = rj.FreeBody(jnp.array([2.0, 2.0, 3.0]))

    def errors(traj, rows):
        omega = np.asarray(traj.omega)
        return np.array(
            [
                np.max(np.abs(omega[k, :, :2] - symmetric_top_exact(2.0, 3.0, omega0[i], ts)[:, :2]))
                / (0.3 * speed[i])
                for k, i in enumerate(rows)
            ]
        )

    batch = errors(rj.simulate(model, rj.State(jnp.asarray(omega0)), jnp.asarray(ts)), range(n))
    alone = errors(
        rj.simulate(model, rj.State(jnp.asarray(omega0[fast : fast + 1])), jnp.asarray(ts)), [fast]
    )
    rms = errors(
        rj.simulate(
            model,
            rj.State(jnp.asarray(omega0)),
            jnp.asarray(ts),
            solver=diffrax.Dopri8(),
            stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8, norm=optx.rms_norm),
        ),
        [fast],
    )
    assert batch[fast] <= 1.01 * alone[0] and batch[fast] < 5e-6, (batch[fast], alone[0])
    assert np.max(np.delete(batch, fast)) < 1e-8
    assert rms[0] > 5 * batch[fast], (rms[0], batch[fast])


_OWN_CONTROLLER = {
    "solver": diffrax.Tsit5(),
    "stepsize_controller": diffrax.PIDController(rtol=1e-8, atol=1e-8),
}


@pytest.mark.parametrize(
    "settings, rtol",
    [
        ({"accuracy": "fast"}, 5e-2),
        ({"accuracy": "balanced"}, 1e-4),
        ({"accuracy": "precise"}, 1e-7),
        pytest.param(_OWN_CONTROLLER, 1e-5, id="own-PIDController"),
    ],
    ids=lambda x: x.get("accuracy") if isinstance(x, dict) else None,
)
def test_derivatives_at_rest_follow_the_linearised_motion(settings, rtol):
    """A top at rest hanging below its pivot and one balanced above it: the state never changes, and
    the controller, which sees only the state's error, took one step over the whole run; the
    derivatives were those of that step (d omega_1(T) / d omega_1(0) = -1044 instead of -0.887).
    Reference: the linearised motion, a pendulum of rate k = sqrt(m g l / I_1): hanging,
    d omega_1(T) / d omega_1(0) = cos(k T) and d q_x(T) / d omega_1(0) = sin(k T) / (2 k); upright,
    cosh and sinh. Forward mode, and reverse mode for "balanced". A diffrax ``PIDController`` of
    one's own without a ``dtmax`` gets the same bound (-1044 before too)."""
    inertia, mass, arm, T = np.array([1e-2, 1e-2, 5e-3]), 0.5, 0.05, 2.0
    top = rj.HeavyTop(jnp.asarray(np.tile(inertia, (2, 1))), jnp.full(2, mass),
                      jnp.array([[0.0, 0.0, -arm], [0.0, 0.0, arm]]))  # fmt: skip
    q0, ts = jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (2, 1)), jnp.linspace(0.0, T, 2)

    def final(omega0):  # (2 tops, 3) -> (2 tops, 2): omega_1(T), q_x(T)
        trajectory = rj.simulate(top, rj.State(omega0, q0), ts, **settings)
        return jnp.stack([trajectory.omega[:, -1, 0], trajectory.orientation[:, -1, 1]], axis=-1)

    k = np.sqrt(mass * 9.81 * arm / inertia[0])
    expected = np.array(
        [[np.cos(k * T), np.sin(k * T) / (2 * k)], [np.cosh(k * T), np.sinh(k * T) / (2 * k)]]
    )
    jacobian = np.asarray(jax.jit(jax.jacfwd(final))(jnp.zeros((2, 3))))  # (2, 2, 2, 3)
    along_omega_1 = jacobian[np.arange(2), :, np.arange(2), 0]
    np.testing.assert_allclose(along_omega_1, expected, rtol=rtol)
    if settings.get("accuracy") == "balanced":
        gradient = np.asarray(jax.jit(jax.grad(lambda w: jnp.sum(final(w)[:, 0])))(jnp.zeros((2, 3))))
        np.testing.assert_allclose(gradient[:, 0], expected[:, 0], rtol=rtol)


@pytest.mark.slow
def test_heavy_top_gradients_wrt_mass_omega0_and_com():
    """jax.grad through simulate w.r.t. the model's and the state's numbers, against central
    finite differences (the final nutation angle's cosine, a smooth scalar)."""
    inertia = jnp.array([1.0, 1.0, 0.5]) * 1e-2
    q0 = rj.quat_from_euler(jnp.array([0.0, 0.4, 0.0]))
    ts = jnp.array([0.0, 0.5])

    def height(mass, omega0, com):
        top = rj.HeavyTop(inertia, mass, com)
        traj = rj.simulate(top, rj.State(omega0, q0), ts, accuracy="precise")
        return rj.quat_rotate(traj.orientation[-1], jnp.array([0.0, 0.0, 1.0]))[2]

    args = (jnp.asarray(0.5), jnp.array([0.3, -0.2, 40.0]), jnp.array([0.0, 0.01, 0.05]))
    gradient = jax.jit(jax.grad(height, argnums=(0, 1, 2)))  # one program, not op by op
    grads = np.concatenate([np.ravel(g) for g in gradient(*args)])
    # Reference: the variational equations of I w' = (I w) x w + (R^T Z) x (m g com), q' = q (0, w) / 2
    # in (mass, omega0, com), the mass and com states of zero rate, by scipy. Central differences of
    # the "precise" solve (relative step 1e-6, the reference before) are within 1.5e-7 of it, the
    # gradient within 3.3e-10.
    qw, qx, qy, qz = q = sp.symbols("q0:4")
    m, *c = sp.symbols("m c1:4")
    vertical = sp.Matrix([2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), qw**2 - qx**2 - qy**2 + qz**2])
    rhs, w = euler_equations_sympy(np.asarray(inertia), vertical.cross(9.81 * m * sp.Matrix(c)))
    w1, w2, w3 = w
    rhs += [(-qx * w1 - qy * w2 - qz * w3) / 2, (qw * w1 + qy * w3 - qz * w2) / 2]
    rhs += [(qw * w2 - qx * w3 + qz * w1) / 2, (qw * w3 + qx * w2 - qy * w1) / 2, 0, 0, 0, 0]
    z0 = np.concatenate([np.asarray(args[1]), np.asarray(q0), [float(args[0])], np.asarray(args[2])])
    dz0 = np.zeros((11, 7))
    dz0[[7, 0, 1, 2, 8, 9, 10], range(7)] = 1.0  # p = (mass, omega0, com)
    z1, S = variational_dop853(rhs, [*w, *q, m, *c], z0, dz0, float(ts[-1]))
    # d/dp of the height qw^2 - qx^2 - qy^2 + qz^2
    reference = 2 * (z1[3] * S[3] - z1[4] * S[4] - z1[5] * S[5] + z1[6] * S[6])
    np.testing.assert_allclose(grads, reference, rtol=1e-5, atol=1e-8)


class _SpinUp(rj.AbstractTorque):
    """A user-defined torque class: a body-frame torque growing linearly in time."""

    rate: jax.Array
    needs_orientation = False

    def __call__(self, t, state, args):
        return jnp.array([0.0, 0.0, 1.0], state.omega.dtype) * self.rate * t


def test_user_torque_subclass_and_public_types():
    """A subclass of AbstractTorque works in simulate: on a sphere omega3 = w0 + rate t^2 / (2 I)."""
    I = 0.5
    ts = jnp.linspace(0.0, 2.0, 9)
    model = rj.RigidBody(jnp.full(3, I), _SpinUp(jnp.asarray(0.3)))
    assert isinstance(model, rj.AbstractModel)
    traj = rj.simulate(model, rj.State(jnp.array([0.0, 0.0, 1.0])), ts, accuracy="precise")
    assert isinstance(traj, rj.Trajectory)
    np.testing.assert_allclose(
        np.asarray(traj.omega[:, 2]), np.asarray(1.0 + 0.3 * ts**2 / (2 * I)), rtol=1e-10
    )
    assert set(rj.solvers.PRESETS) == {"fast", "balanced", "precise"}


@pytest.mark.slow
def test_simulate_routes_structure_preserving_solvers():
    """simulate(solver=HeavyTopSplitting/RKMK, dt0=...) runs the fixed-step structure-preserving path
    and agrees with the adaptive Dopri8 path; without dt0 it says what is missing."""
    top = rj.HeavyTop(inertia=jnp.array([1.0, 1.0, 0.4]), mass=1.0, com=jnp.array([0.0, 0.0, 0.3]))
    q0 = rj.quat_from_euler(jnp.array([0.0, 0.5, 0.0]))
    state0 = rj.State(jnp.array([0.0, 0.0, 12.0]), q0)
    # 21 samples, as the heavy top of the Euler-angle test below: its "precise" program serves here.
    ts = jnp.linspace(0.0, 1.0, 21)
    reference = rj.simulate(top, state0, ts, accuracy="precise")
    splitting = rj.solvers.HeavyTopSplitting.from_model(top, order=4)
    split = rj.simulate(top, state0, ts, solver=splitting, dt0=2e-3)
    np.testing.assert_allclose(split.omega, reference.omega, atol=1e-6)
    assert np.max(np.abs(np.linalg.norm(np.asarray(split.orientation), axis=-1) - 1.0)) < 1e-13
    with pytest.raises(ValueError, match="fixed step: pass dt0"):
        rj.simulate(top, state0, ts, solver=rj.solvers.RKMK())


@pytest.mark.parametrize(
    "model, accuracy",
    [
        (rj.FreeBody(jnp.array([1.0, 2.0, 3.0])), "fast"),
        (rj.FreeBody(jnp.array([1.0, 2.0, 3.0])), "exact"),
        (rj.HeavyTop(jnp.array([1.0, 1.0, 0.5]), 1.0, jnp.array([0.0, 0.0, 0.3])), "exact"),
    ],
    ids=["free body, fast", "free body, exact", "heavy top, exact"],
)
def test_simulate_inside_a_jit_that_closes_over_its_inputs(model, accuracy):
    """Arrays a jitted function closes over are constants of its program: their checks read their
    values while it is traced, the program gives the eager values, and a bad one raises the eager
    ``ValueError`` when the function is traced."""
    # 41 samples, as the spin test above: the eager "exact" free body is the program it compiled.
    omega0, ts = jnp.array([0.1, 2.0, 0.1]), jnp.linspace(0.0, 1.0, 41)
    q0 = jnp.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
    eager = rj.simulate(model, rj.State(omega0, q0), ts, accuracy=accuracy)
    closed_over = jax.jit(lambda: rj.simulate(model, rj.State(omega0, q0), ts, accuracy=accuracy))()
    np.testing.assert_allclose(closed_over.omega, eager.omega, rtol=0, atol=1e-14)
    np.testing.assert_allclose(closed_over.orientation, eager.orientation, rtol=0, atol=1e-14)
    not_unit = jnp.array([1.0, 0.1, 0.0, 0.0])
    with pytest.raises(ValueError, match="state0.orientation is not a unit quaternion"):
        jax.jit(lambda: rj.simulate(model, rj.State(omega0, not_unit), ts, accuracy=accuracy))()


def test_heavy_top_accepts_a_list_for_com():
    top = rj.HeavyTop([1.0, 1.0, 0.5], 1.0, [0.0, 0.0, 0.1])
    assert top.com.shape == (3,)
    with pytest.raises(ValueError, match="HeavyTop.com"):
        rj.HeavyTop([1.0, 1.0, 0.5], 1.0, [0.0, 0.1])


def test_chunk_lexsort_is_numpys_lexsort():
    """The chunk planner's lexsort (one stable integer sort per 32-bit word of each key) gives the
    order of NumPy's ``np.lexsort`` (independent reference) for keys with many ties, float64 keys
    that differ in their last bits, negative values, +-inf, integer and float32 keys, under jit."""
    from rigidjax._integrate import batching

    rng = np.random.default_rng(3)
    n = 5000
    base = rng.normal(size=n)
    close = np.where(rng.random(n) < 0.5, base, np.nextafter(base, np.inf))  # last-bit differences
    close[:7] = [np.inf, -np.inf, 0.0, 1e-300, -1e-300, 1e300, -1e300]
    keys = (
        close,
        rng.integers(-3, 3, n),  # int64, many ties
        rng.integers(0, 4, n).astype(np.float32),
        rng.integers(0, 2, n).astype(np.float64),
    )
    for k in range(1, len(keys) + 1):
        expected = np.lexsort(keys[:k])
        got = jax.jit(batching.lexsort)(tuple(jnp.asarray(x) for x in keys[:k]))
        np.testing.assert_array_equal(np.asarray(got), expected)
    int32_key = rng.integers(-(2**31), 2**31 - 1, n, dtype=np.int32)
    np.testing.assert_array_equal(
        np.asarray(batching.lexsort((jnp.asarray(int32_key),))), np.argsort(int32_key, kind="stable")
    )


def test_torque_free_bodies_share_chunks_by_period_and_phase():
    """Bodies of one speed class go into chunks by the period of their motion (the closed form's
    torque_free_period), and within groups of four chunks by the time of their next flip (the first
    sign change of the intermediate component, found on a fine grid of the closed form), so that the
    bodies of a chunk flip at the same times: twice as fast bodies come first, the groups' period
    ranges do not overlap, each chunk spans under half its group's flip times, a tensor inertia
    is ordered as its principal moments, and on tennis-racket bodies (periods 13 - 30 s) at random
    phases the sorted chunks take fewer steps than chunks of the bodies in their given order."""
    from rigidjax._integrate import chunked
    from rigidjax._integrate.formulations import ScaledODE

    rng = np.random.default_rng(3)
    n, chunk = 1024, 64
    inertia = np.array([1.0, 2.0, 2.5]) * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, (n, 3)))
    # 3 rad/s: the speed classes are 2^(1/4) wide from 1 rad/s, and 3 (1 +- 2 %) lies inside one.
    omega0 = np.array([0.04, 3.0, 0.04]) + 0.008 * rng.standard_normal((n, 3))
    free = rj.FreeBody(jnp.asarray(inertia))
    period = np.array(rj.torque_free_period(jnp.asarray(inertia), jnp.asarray(omega0)))
    start = rng.uniform(0, 1, n) * period  # random phases
    omega0 = np.array(rj.torque_free_omega(free.inertia, jnp.asarray(omega0), jnp.asarray(start)))
    omega0[:chunk] *= 2.0  # a faster speed class
    period[:chunk] /= 2.0
    grid = np.linspace(0.0, 0.5 * period.max(), 4001)
    traj = rj.simulate(free, rj.State(jnp.asarray(omega0)), jnp.asarray(grid), accuracy="exact")
    w2 = np.asarray(traj.omega[..., 1])
    next_flip = grid[np.argmax(np.sign(w2) != np.sign(w2[:, :1]), axis=1)]
    ts = jnp.array([0.0, 20.0])

    @jax.jit  # the planner as one program (eagerly, each of its operations compiles on its own)
    def order(model, omega):
        return chunked.plan_bodies(model, omega, None, ts, None, ScaledODE(), chunk, True)[-1].order

    def chunks_of(model, omega):
        return np.asarray(order(model, jnp.asarray(omega))).reshape(-1, chunk)

    chunks = chunks_of(free, omega0)
    np.testing.assert_array_equal(np.sort(chunks[0]), np.arange(chunk))  # the fast class first
    # Groups of four chunks in the order by speed class and period: the first holds the fast class.
    groups = [chunks[1:4]] + [chunks[i : i + 4] for i in range(4, len(chunks), 4)]
    for group, later in zip(groups, groups[1:], strict=False):
        assert period[group].max() <= period[later].min()
    for group in groups:
        spread = np.ptp(next_flip[group])
        assert np.all(np.ptp(next_flip[group], axis=1) < 0.5 * spread), (next_flip[group], spread)

    turn = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    tensors = np.einsum("ij,nj,kj->nik", turn, inertia, turn)  # the same bodies, turned
    np.testing.assert_array_equal(chunks_of(rj.FreeBody(jnp.asarray(tensors)), omega0 @ turn.T), chunks)

    state = rj.State(jnp.asarray(omega0[chunk:]))
    slow = rj.FreeBody(jnp.asarray(inertia[chunk:]))
    by_timing = rj.simulate(slow, state, ts, chunk_size=chunk)
    given = rj.simulate(slow, state, ts, chunk_size=chunk, sort_by_speed=False)
    steps = [float(np.mean(t.stats["num_steps"])) for t in (by_timing, given)]
    assert steps[0] < 0.9 * steps[1], steps


@pytest.mark.parametrize("devices", [1, 2])
def test_chunks_are_equal_and_the_padding_under_one_body_per_chunk(devices, monkeypatch):
    """Against the definition, by enumeration: the fewest chunks of at most ``chunk_size`` bodies,
    all of one size, the smallest size that holds the batch; with two devices the same chunks, and
    a chunk of padding where their count is odd (so that the trajectories are those of one device)."""
    from rigidjax._integrate import batching

    monkeypatch.setattr(jax, "device_count", lambda: devices)
    for n in (1, 2, 7, 255, 256, 257, 300, 10_000, 100_000):
        for chunk_size in (1, 4, 256, 65536):
            chunk, n_chunks, shard = batching.chunk_layout(n, chunk_size)
            fewest = min(k for k in range(1, n + 1) if k * chunk_size >= n)
            assert chunk == min(c for c in range(1, n + 1) if c * fewest >= n) <= chunk_size
            assert 0 <= fewest * chunk - n < fewest
            padding_chunk = devices > 1 and fewest > 1 and fewest % 2
            assert n_chunks == fewest + padding_chunk and shard == (devices > 1 and fewest > 1)


def test_simulate_reports_its_equal_chunks():
    """300 bodies in chunks of at most 256 run as two chunks of 150 (not 256 and 44 padded to 256),
    and meet the preset's accuracy against the closed form."""
    rng = np.random.default_rng(11)
    inertia = jnp.asarray(np.array([1.0, 2.0, 2.5]) * (1 + 0.05 * rng.uniform(-1, 1, (300, 3))))
    omega0 = jnp.asarray(np.array([0.3, 1.0, 0.2]) + 0.05 * rng.normal(size=(300, 3)))
    model, state = rj.FreeBody(inertia), rj.State(omega0)
    ts = jnp.linspace(0.0, 5.0, 3)
    traj = rj.simulate(model, state, ts, chunk_size=256)
    assert int(traj.stats["chunk_size"]) == 150 and np.asarray(traj.stats["num_steps"]).shape == (2,)
    exact = rj.simulate(model, state, ts, accuracy="exact")
    scale = np.max(np.abs(np.asarray(exact.omega)), axis=(1, 2), keepdims=True)
    assert np.max(np.abs(np.asarray(traj.omega) - np.asarray(exact.omega)) / scale) < 5e-7


def test_chunks_write_their_samples_in_place():
    """Each chunk's samples are written into the arrays of all the bodies, in the bodies' order,
    as the chunk finishes: beside the output, the program needs memory for about one chunk's work,
    not a second copy of every sample (stacked chunks, then put back in the bodies' order: 0.89 of
    the output; in place: 0.43; 3001 bodies sorted by speed into 12 chunks). References: XLA's
    memory analysis of the compiled program; every body against the closed form."""
    rng = np.random.default_rng(12)
    n = 3001
    inertia = jnp.asarray(np.array([1.0, 2.0, 2.5]) * (1 + 0.05 * rng.uniform(-1, 1, (n, 3))))
    omega0 = jnp.asarray(np.array([0.3, 1.0, 0.2]) + 0.05 * rng.normal(size=(n, 3)))
    q0 = jnp.broadcast_to(IDENTITY, (n, 4))
    ts = jnp.linspace(0.0, 5.0, 21)

    def motion(inertia, accuracy):
        traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega0, q0), ts, accuracy=accuracy)
        return traj.omega, traj.orientation

    balanced = jax.jit(motion, static_argnums=1)
    memory = balanced.lower(inertia, "balanced").compile().memory_analysis()
    assert memory.temp_size_in_bytes < 0.6 * memory.output_size_in_bytes, memory
    omega, q = balanced(inertia, "balanced")
    exact_omega, exact_q = motion(inertia, "exact")
    scale = np.max(np.abs(np.asarray(exact_omega)), axis=(1, 2), keepdims=True)
    assert np.max(np.abs(np.asarray(omega) - np.asarray(exact_omega)) / scale) < 5e-7
    assert np.max(np.abs(np.asarray(q) - np.asarray(exact_q))) < 5e-7


def test_a_batch_in_chunks_traces_its_solve_once(monkeypatch):
    """The loop over chunks traces the chunk's diffrax solve once: the shapes of its results come
    from the same trace (a trace for the shapes alone, then another for the loop, took 0.3-0.6 s
    more per program). Reference: a count of the calls of the driver's solve while JAX traces a
    batch of 40 bodies in 4 chunks, and the samples against the closed form."""
    from rigidjax._integrate import driver

    calls = counted_calls(monkeypatch, driver, "solve")
    rng = np.random.default_rng(3)
    inertia = jnp.asarray(np.array([1.0, 2.0, 2.5]) * (1 + 0.05 * rng.uniform(-1, 1, (40, 3))))
    omega0 = jnp.asarray(np.array([0.3, 1.0, 0.2]) + 0.05 * rng.normal(size=(40, 3)))
    ts = jnp.linspace(0.0, 3.0, 4)

    def omega(inertia):
        return rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts, chunk_size=10).omega

    lowered = jax.jit(omega).lower(inertia)
    assert len(calls) == 1
    exact = rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts, accuracy="exact").omega
    np.testing.assert_allclose(lowered.compile()(inertia), exact, rtol=0, atol=1e-6)


class _Device:
    def __init__(self, platform):
        self.platform = platform

    core_count = 132

    @staticmethod
    def memory_stats():
        return {"bytes_limit": 139 * 2**30}


def test_default_chunk_size_on_an_accelerator(monkeypatch):
    """On a pretend H200 (132 cores, 139 GiB): 512 bodies per core; with 10^5 sample times a chunk's
    samples (saved, then gathered: 2 x 7 components x 8 bytes each) and about 32 stages' states
    stay under an eighth of the memory; on CPU 256."""
    from rigidjax._integrate.presets import default_chunk_size

    monkeypatch.setattr(jax, "devices", lambda *a: [_Device("cpu")])
    assert default_chunk_size() == 256
    monkeypatch.setattr(jax, "devices", lambda *a: [_Device("gpu")])
    assert default_chunk_size() == 512 * 132
    per_body = (100_000 + 32) * 7 * 2 * 8
    assert default_chunk_size(100_000, 8) == 139 * 2**30 // (8 * per_body) < 512 * 132
    assert default_chunk_size(100_000, 4) == 139 * 2**30 // (8 * per_body // 2)


def test_options_as_users_pass_them(without_runtime_typecheck):
    """The Euler-angle state returned -q0 at t = 0 for about half of the initial orientations;
    BacksolveAdjoint failed deep inside diffrax; float64 times that collapse in a float32 run were
    reported as the user's times not increasing; jacrev(jacrev(f)) raised JAX's "Reverse-mode
    differentiation does not work for lax.while_loop". Reference for the second derivative: the
    exact Hessian, by the second variational equations (scipy)."""
    body = rj.FreeBody(jnp.array([1.0, 2.0, 2.5]))
    q0 = jnp.array([-0.9234, 0.3078, 0.2052, 0.1026])
    q0 = q0 / jnp.linalg.norm(q0)
    euler = rj.simulate(
        body, rj.State(jnp.array([0.3, 1.0, 0.2]), q0), jnp.linspace(0.0, 1.0, 21), representation="euler"
    )
    np.testing.assert_allclose(euler.orientation[0], q0, atol=1e-12)
    with pytest.raises(ValueError, match="BacksolveAdjoint.*does not support"):
        rj.simulate(
            body, rj.State(jnp.ones(3)), jnp.linspace(0.0, 1.0, 3), adjoint=diffrax.BacksolveAdjoint()
        )
    f32 = np.float32
    with pytest.raises(ValueError, match="ts increase in float64 but not once cast to float32"):
        rj.simulate(
            rj.FreeBody(f32([1.0, 2.0, 2.5])),
            rj.State(f32([0.3, 1.0, 0.2])),
            np.array([1e5, 1e5 + 1e-3, 1e5 + 2e-3]),
        )
    w, ts = jnp.array([0.3, 1.0, 0.2]), jnp.linspace(0.0, 1.0, 3)

    def f(inertia, **options):
        return jnp.sum(rj.simulate(rj.FreeBody(inertia), rj.State(w), ts, **options).omega[-1] ** 2)

    inertia = jnp.array([1.0, 2.0, 2.5])
    twice = jax.jit(jax.jacrev(jax.jacrev(f)))(inertia)  # one program, not op by op
    # sum_i w_i^2: its Hessian is 2 sum_i (dw_i/dI dw_i/dI^T + w_i d2w_i/dI^2), with the second
    # variational equations in the moments integrated by scipy (the closed form's jax.hessian, 10-30 s
    # to compile, agrees with it to 4e-15).
    moments = sp.symbols("I1:4")
    rhs, symbols = euler_equations_sympy(moments)
    z0 = np.concatenate([np.asarray(w), np.asarray(inertia)])
    omega, S, H = variational_dop853(
        rhs + [0, 0, 0], symbols + list(moments), z0, np.eye(6, 3, k=-3), float(ts[-1]), second=True
    )
    omega, S, H = omega[:3], S[:3], H[:3]
    reference = 2 * (S.T @ S + np.einsum("i,iab->ab", omega, H))
    np.testing.assert_allclose(twice, reference, atol=1e-8)
