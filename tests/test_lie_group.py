"""RKMK on R^3 x SO(3) and the fixed-step structure-preserving simulate: Lie-group pieces vs scipy,
convergence orders and an adaptive run vs scipy DOP853 (a torque depending on time and orientation),
unit quaternions, vmap/jit, jacfwd vs finite differences, scenes vs closed forms."""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dop853, log_log_slope
from scipy.spatial.transform import Rotation

import rigidjax as rj
from rigidjax import (
    FreeBody,
    HeavyTop,
    RigidBody,
    State,
    ViscousDamping,
    matrix_from_quat,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    torque_free_omega,
)
from rigidjax._integrate.chunked import _integrate_traced
from rigidjax.kinematics import quat_exp
from rigidjax.solvers import (
    RKMK,
    HeavyTopSplitting,
    LiePoissonSplitting,
    dexpinv,
    rigid_body_vector_field,
    rkmk_step,
)


def simulate_structure_preserving(model, state0, ts, solver, dt, *, args=None):
    """A scene at the fixed step ``dt`` with a structure-preserving solver, through ``simulate``."""
    return rj.simulate(model, state0, ts, solver=solver, dt0=dt, args=args)


# A heavy top written as a user torque, plus a time-dependent body-frame drive: the torque depends on
# time and orientation.
TOP = HeavyTop(jnp.array([1.0, 1.4, 0.6]), 1.2, jnp.array([0.05, -0.03, 0.4]), 9.81)
OMEGA0 = jnp.array([0.8, -0.4, 9.0])
Q0 = quat_normalize(jnp.array([0.95, 0.25, -0.1, 0.15]))
T = 2.0


def _accel(t, w, q, args):
    drive = 0.3 * jnp.sin(2.0 * t) * jnp.array([1.0, 0.0, 0.0], w.dtype)
    scale = 1.0 if args is None else args
    gravity = TOP.angular_acceleration(t, State(w, q), None).astype(w.dtype)  # TOP's fields are float64
    return gravity + scale * drive / TOP.inertia.astype(w.dtype)


VF = rigid_body_vector_field(_accel)


_ACCEL = jax.jit(lambda t, w, q: _accel(t, w, q, None))


@functools.cache
def _reference(t_eval=(T,)):
    """scipy DOP853 (tests/helpers.py) on the model's angular acceleration with dq/dt = q (0, omega)/2
    at rtol = atol = 1e-13; (T, 3), (T, 4)."""
    return dop853(
        lambda t, w, q: np.asarray(_ACCEL(t, jnp.asarray(w), jnp.asarray(q))), OMEGA0, t_eval, Q0, tol=1e-13
    )


def test_quat_exp_vs_scipy_and_small_angles():
    rng = np.random.default_rng(0)
    thetas = np.concatenate(
        [rng.normal(size=(20, 3)), 1e-5 * rng.normal(size=(5, 3)), 1e-9 * rng.normal(size=(3, 3))]
    )
    q = jax.jit(quat_exp)(jnp.asarray(thetas))
    R_scipy = Rotation.from_rotvec(thetas).as_matrix()
    np.testing.assert_allclose(matrix_from_quat(q), R_scipy, rtol=0, atol=1e-15 * 4)
    assert float(jnp.max(jnp.abs(jnp.linalg.norm(q, axis=-1) - 1.0))) < 4e-16
    # Value and gradient at exactly zero are finite; d Exp / d theta at 0 is [0; I/2].
    jac0, grad0 = jax.jit(lambda t: (jax.jacfwd(quat_exp)(t), jax.grad(lambda u: jnp.sum(quat_exp(u)))(t)))(
        jnp.zeros(3)
    )
    np.testing.assert_allclose(jac0, np.vstack([np.zeros(3), 0.5 * np.eye(3)]), atol=1e-15)
    assert jnp.all(jnp.isfinite(grad0))


def test_dexpinv_vs_finite_differences():
    """theta(t) on a curve: the body rate of Exp(theta(t)) is 2 vec(Exp* dExp/dt); dexpinv of it must
    give d(theta)/dt up to the first dropped term, O(|theta|^4 |omega|)."""

    @jax.jit
    def error(theta):
        theta_dot = jnp.array([0.3, 1.1, -0.5])
        dq = jax.jvp(quat_exp, (theta,), (theta_dot,))[1]
        omega = 2.0 * quat_multiply(quat_conjugate(quat_exp(theta)), dq)[1:]
        return jnp.linalg.norm(dexpinv(theta, omega) - theta_dot)

    errs = [float(error(size * jnp.array([0.6, -0.3, 0.74]))) for size in (0.2, 0.1, 0.05)]
    slope = log_log_slope([0.2, 0.1, 0.05], errs)
    print(f"dexpinv truncation errors {errs}, slope {slope:.3f}")
    assert abs(slope - 4.0) < 0.15
    assert errs[0] < 1e-4


@functools.cache
def _fixed_step_runner(tableau):
    """One compile per tableau for every step count (dynamic trip count)."""

    def run(h, n, w0, q0, amp=1.0):
        def body(k, y):
            return rkmk_step(_accel, k.astype(h.dtype) * h, *y, h, amp, tableau)

        return jax.lax.fori_loop(0, n, body, (w0, q0))

    return jax.jit(run)


@pytest.mark.parametrize("tableau,order", [("bosh3", 3), ("dopri5", 5)])
def test_convergence_order_time_and_orientation_torque(tableau, order):
    w_ref, q_ref = (x[-1] for x in _reference())
    R_ref = Rotation.from_quat(q_ref, scalar_first=True).as_matrix()
    ns = (100, 200, 400, 800) if order == 3 else (50, 100, 200, 400)
    errs_w, errs_R = [], []
    for n in ns:
        w, q = _fixed_step_runner(tableau)(jnp.asarray(T / n), n, OMEGA0, Q0)
        errs_w.append(float(jnp.max(jnp.abs(w - w_ref))))
        errs_R.append(float(jnp.max(jnp.abs(matrix_from_quat(q) - R_ref))))
    hs = [T / n for n in ns]
    slope_w, slope_R = log_log_slope(hs, errs_w), log_log_slope(hs, errs_R)
    print(f"RKMK {tableau}: omega errors {errs_w} slope {slope_w:.3f}; R errors {errs_R} slope {slope_R:.3f}")
    assert abs(slope_w - order) < 0.15
    assert abs(slope_R - order) < 0.15
    assert errs_w[-1] < (1e-4 if order == 3 else 1e-9)


def _rk4_step(t, y, h):
    """Classical RK4 on the plain ODE: the quaternion norm is not preserved (the contrast)."""

    def f(s, z):
        return VF(s, z, None)

    def add(z, k, a):
        return jax.tree_util.tree_map(lambda u, v: u + a * v, z, k)

    k1 = f(t, y)
    k2 = f(t + h / 2, add(y, k1, h / 2))
    k3 = f(t + h / 2, add(y, k2, h / 2))
    k4 = f(t + h, add(y, k3, h))
    return jax.tree_util.tree_map(
        lambda u, a, b, c, d: u + h / 6 * (a + 2 * b + 2 * c + d), y, k1, k2, k3, k4
    )


def test_quaternion_unit_over_1e4_steps():
    @jax.jit
    def run(h):
        def body(ys, k):
            y, z = ys
            y = rkmk_step(_accel, k * h, *y, h)
            z = _rk4_step(k * h, z, h)
            return (y, z), (jnp.abs(jnp.linalg.norm(y[1]) - 1.0), jnp.abs(jnp.linalg.norm(z[1]) - 1.0))

        return jax.lax.scan(body, ((OMEGA0, Q0), (OMEGA0, Q0)), jnp.arange(10_000.0))[1]

    dev, dev_rk4 = (float(jnp.max(x)) for x in run(jnp.asarray(0.01)))
    print(f"1e4 steps h=0.01: max ||q| - 1| RKMK dopri5 {dev:.2e}, classical RK4 {dev_rk4:.2e}")
    assert dev < 2e-14  # roundoff only: a random walk of ~1e4 unit-quaternion products
    assert dev_rk4 > 1e3 * dev


@functools.cache
def _adaptive_solver():
    """An adaptive RKMK solve, jitted and vmapped over bodies (one compile for the tests below)."""

    def solve(w0, q0, rtol, ts):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(VF),
            RKMK("dopri5"),
            0.0,
            T,
            None,
            (w0, q0),
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol),
            saveat=diffrax.SaveAt(ts=ts),
            max_steps=10_000,
        )

    return jax.jit(jax.vmap(solve, in_axes=(0, 0, None, None)))


@pytest.mark.slow
def test_adaptive_pid_matches_reference_under_vmap():
    """Body 0 vs scipy DOP853; body 1 (another start, same batch) vs a fine fixed-step RKMK run."""
    ts = jnp.linspace(0.0, T, 5)
    w_refs, q_refs = _reference(tuple(float(t) for t in ts))
    w_ref, q_ref = w_refs[-1], q_refs[-1]
    w0s = jnp.stack([OMEGA0, OMEGA0 + jnp.array([0.4, 0.3, -1.0])])
    q0s = jnp.stack([Q0, quat_normalize(Q0 + jnp.array([0.0, 0.2, 0.1, -0.1]))])
    w1_fine, q1_fine = _fixed_step_runner("dopri5")(jnp.asarray(T / 800), 800, w0s[1], q0s[1])
    errs, steps = [], []
    for rtol in (1e-6, 1e-9):
        sol = _adaptive_solver()(w0s, q0s, jnp.asarray(rtol), ts)
        err = float(jnp.max(jnp.abs(sol.ys[0][0, -1] - w_ref)) / jnp.linalg.norm(OMEGA0))
        err_q = float(jnp.max(jnp.abs(sol.ys[1][0, -1] - q_ref)))
        err1 = float(jnp.max(jnp.abs(sol.ys[0][1, -1] - w1_fine)) / jnp.linalg.norm(w0s[1]))
        err1_q = float(jnp.max(jnp.abs(sol.ys[1][1, -1] - q1_fine)))
        errs.append(err)
        steps.append(np.asarray(sol.stats["num_steps"]))
        print(
            f"rtol {rtol:g}: body 0 rel omega error {err:.2e}, q error {err_q:.2e}; body 1 {err1:.2e}, "
            f"{err1_q:.2e}; steps {steps[-1]}"
        )
        # Global error at t = 2 s (three turns), like diffrax's Dopri5 at the same tolerance (report).
        for e in (err, err_q, err1, err1_q):
            assert e < 30 * rtol
        assert float(jnp.max(jnp.abs(jnp.linalg.norm(sol.ys[1], axis=-1) - 1.0))) < 1e-14  # dense too
    assert np.all(steps[1] > 2 * steps[0])  # the error estimate drives the step size
    assert steps[0][0] != steps[0][1]  # each body of the vmapped solve takes its own steps
    assert errs[1] < errs[0] / 30  # accuracy follows the tolerance
    # Dense output (cubic Hermite in omega and in the algebra) at interior sample times (rtol 1e-9).
    dense_err = float(jnp.max(jnp.abs(sol.ys[0][0] - w_refs)) / jnp.linalg.norm(OMEGA0))
    print(f"dense output rel omega error at rtol 1e-9: {dense_err:.2e}")
    assert dense_err < 1e-6


def test_jacfwd_vs_finite_differences():
    """d(omega(T), q(T)) / d(omega0, drive amplitude) through 100 fixed RKMK steps."""
    run = _fixed_step_runner("bosh3")
    h, n, amp = jnp.asarray(0.01), 100, jnp.asarray(1.5)

    def final(w0, a):
        return jnp.concatenate(run(h, n, w0, Q0, a))

    jac_w, jac_a = jax.jit(jax.jacfwd(final, argnums=(0, 1)))(OMEGA0, amp)
    eps = 1e-6
    fd_w = jnp.stack(
        [(final(OMEGA0 + eps * e, amp) - final(OMEGA0 - eps * e, amp)) / (2 * eps) for e in jnp.eye(3)],
        axis=-1,
    )
    fd_a = (final(OMEGA0, amp + eps) - final(OMEGA0, amp - eps)) / (2 * eps)
    dw, da = float(jnp.max(jnp.abs(jac_w - fd_w))), float(jnp.max(jnp.abs(jac_a - fd_a)))
    print(f"jacfwd vs FD: omega0 {dw:.2e}, amplitude {da:.2e}")
    np.testing.assert_allclose(jac_w, fd_w, rtol=0, atol=1e-7 * float(jnp.max(jnp.abs(fd_w))))
    np.testing.assert_allclose(jac_a, fd_a, rtol=0, atol=1e-7 * float(jnp.max(jnp.abs(fd_a))))
    assert float(jnp.max(jnp.abs(fd_a))) > 1e-3  # the parameter matters


def test_float32():
    f32 = jnp.float32
    w, q = _fixed_step_runner("dopri5")(f32(T / 200), 200, OMEGA0.astype(f32), Q0.astype(f32), f32(1.0))
    assert w.dtype == f32 and q.dtype == f32
    w_ref, q_ref = (x[-1] for x in _reference())
    err = float(jnp.max(jnp.abs(w.astype(jnp.float64) - w_ref)) / jnp.linalg.norm(OMEGA0))
    q_dev = abs(float(jnp.linalg.norm(q.astype(jnp.float64))) - 1.0)
    print(f"float32 RKMK dopri5, 200 steps: rel omega error {err:.2e}, ||q| - 1| {q_dev:.2e}")
    assert err < 1e-5
    assert q_dev < 3e-6  # ~25 float32 ulps after 200 unit-quaternion products


def test_bad_tableau():
    with pytest.raises(ValueError, match="tableau"):
        RKMK("rk4")
    with pytest.raises(ValueError, match="tableau"):
        rkmk_step(_accel, 0.0, OMEGA0, Q0, 0.1, tableau="euler")


# ---------------------------------------------------------------------------------------------
# simulate_structure_preserving


@pytest.mark.slow
def test_simulate_heavy_top_splitting_tensor_inertia():
    """Two copies of TOP given by inertia TENSORS: one diagonal, one in body axes turned by P. Both vs
    scipy (the second mapped by P), and the splitting's invariants."""
    P = jnp.asarray(Rotation.from_rotvec([0.3, -0.8, 0.5]).as_matrix())
    p = quat_normalize(jnp.asarray(Rotation.from_matrix(np.asarray(P)).as_quat(scalar_first=True)))
    tensor = jnp.stack([jnp.diag(TOP.inertia), P @ jnp.diag(TOP.inertia) @ P.T])
    model = HeavyTop(tensor, 1.2, jnp.stack([TOP.com, P @ TOP.com]), 9.81)
    state0 = State(jnp.stack([OMEGA0, P @ OMEGA0]), jnp.stack([Q0, quat_multiply(Q0, quat_conjugate(p))]))
    ts = jnp.linspace(0.0, 1.0, 6)
    accel = jax.jit(lambda w, q: TOP.angular_acceleration(0.0, State(w, q), None))
    w_ref, q_ref = dop853(
        lambda t, w, q: np.asarray(accel(jnp.asarray(w), jnp.asarray(q))), OMEGA0, ts, Q0, tol=1e-12
    )
    R_ref = matrix_from_quat(jnp.asarray(q_ref))
    traj = simulate_structure_preserving(model, state0, ts, HeavyTopSplitting.from_model(TOP, order=4), 0.01)
    assert traj.omega.shape == (2, 6, 3) and traj.orientation.shape == (2, 6, 4)
    assert int(traj.stats["num_steps"][0]) == 100 and bool(jnp.all(traj.success))
    R = matrix_from_quat(traj.orientation)
    # Body 1 is body 0 seen in other axes: omega_body = P omega, R_body = R P^T.
    err_w = [float(jnp.max(jnp.abs(traj.omega[b] - w_ref @ M.T))) for b, M in ((0, jnp.eye(3)), (1, P))]
    err_R = [float(jnp.max(jnp.abs(R[b] - R_ref @ M.T))) for b, M in ((0, jnp.eye(3)), (1, P))]
    print(f"tensor-inertia heavy top, Yoshida dt 0.01: omega errors {err_w}, R errors {err_R}")
    assert max(err_w) < 2e-5 and max(err_R) < 4e-6
    inv = traj.invariants()
    print({k: np.asarray(v) for k, v in inv.items()})
    assert jnp.all(inv["vertical_angular_momentum"] < 1e-14)
    assert jnp.all(inv["quaternion_norm"] < 1e-14)
    assert jnp.all(inv["energy"] < 1e-6)


def test_simulate_free_body_splitting_vs_closed_form():
    inertia = jnp.array([[1.0, 2.0, 3.0], [2.0, 2.5, 4.0]])
    omega0 = jnp.array([[1.0, 0.1, 0.5], [0.2, 1.0, -0.3]])
    ts = jnp.array([0.0, 0.35, 1.0, 2.2])  # uneven gaps: a different step count per interval
    traj = simulate_structure_preserving(
        FreeBody(inertia), State(omega0), ts, LiePoissonSplitting(inertia[0], 4), 0.02
    )
    assert traj.orientation is None and traj.omega.shape == (2, 4, 3)
    exact = jax.jit(torque_free_omega)(inertia[:, None, :], omega0[:, None, :], ts - ts[0])
    err = float(jnp.max(jnp.abs(traj.omega - exact)))
    print(f"free body, Yoshida dt <= 0.02: max omega error {err:.2e}")
    assert err < 1e-6
    assert int(traj.stats["num_steps"][0]) == 18 + 33 + 60
    # New values of the same shapes (and the same largest per-interval step count) do not retrace.
    traces = eqx.debug.get_num_traces(_integrate_traced)
    again = simulate_structure_preserving(
        FreeBody(1.1 * inertia), State(-omega0), ts + 0.01, LiePoissonSplitting(inertia[0], 4), 0.02
    )
    assert eqx.debug.get_num_traces(_integrate_traced) == traces
    assert not jnp.allclose(again.omega, traj.omega)


@pytest.mark.slow
def test_simulate_rkmk_damped_sphere_closed_form_and_grad():
    """Spherical body (I) with per-body viscous damping c: omega = omega0 exp(-c t / I) about a fixed axis,
    turned angle |omega0| I / c (1 - exp(-c t / I))."""
    I = 2.0
    c = jnp.array([[0.5], [1.5]])
    omega0 = jnp.array([[0.3, -1.2, 0.8], [1.0, 0.4, 0.2]])
    model = RigidBody(jnp.full(3, I), ViscousDamping(c))
    ts = jnp.linspace(0.0, 1.5, 4)
    traj = simulate_structure_preserving(model, State(omega0, Q0), ts, RKMK("bosh3"), 0.01)
    # The closed form in NumPy (eager jnp operations would each compile a program of their own).
    c_, w0_, t_ = np.asarray(c), np.asarray(omega0), np.asarray(ts)
    decay = np.exp(-c_[:, :, None] * t_[None, :, None] / I)  # (2, T, 1)
    np.testing.assert_allclose(traj.omega, w0_[:, None, :] * decay, rtol=0, atol=1e-8)
    angle = np.linalg.norm(w0_, axis=-1)[:, None] * I / c_ * (1.0 - decay[..., 0])
    axis = w0_ / np.linalg.norm(w0_, axis=-1, keepdims=True)
    rot = Rotation.from_rotvec((angle[..., None] * axis[:, None, :]).reshape(-1, 3))
    expected = Rotation.from_quat(np.asarray(Q0), scalar_first=True) * rot
    np.testing.assert_allclose(
        matrix_from_quat(traj.orientation).reshape(-1, 3, 3), expected.as_matrix(), rtol=0, atol=1e-8
    )

    # Reverse mode through the fixed-step loop vs central differences (w.r.t. the damping), each a
    # compiled program (the differences' four evaluations share one).
    @jax.jit
    def final_speed(coef):
        m = RigidBody(jnp.full(3, I), ViscousDamping(coef))
        return jnp.sum(
            simulate_structure_preserving(m, State(omega0, Q0), ts, RKMK("bosh3"), 0.01).omega[:, -1]
        )

    g = jax.jit(jax.grad(final_speed))(c)
    eps = 1e-6
    fd = np.stack(
        [(final_speed(c + eps * e) - final_speed(c - eps * e)) / (2 * eps) for e in np.eye(2)[:, :, None]]
    )
    np.testing.assert_allclose(g[:, 0], fd, rtol=1e-6, atol=0)


def test_simulate_errors():
    ts = jnp.linspace(0.0, 1.0, 3)
    state = State(OMEGA0, Q0)
    with pytest.raises(ValueError, match="HeavyTopSplitting"):
        simulate_structure_preserving(
            FreeBody(TOP.inertia), state, ts, HeavyTopSplitting.from_model(TOP), 0.1
        )
    with pytest.raises(ValueError, match="torque-free"):
        simulate_structure_preserving(TOP, state, ts, LiePoissonSplitting(TOP.inertia), 0.1)
    with pytest.raises(ValueError, match="dt"):
        simulate_structure_preserving(TOP, state, ts, RKMK(), 0.0)
    with pytest.raises(ValueError, match="increasing"):
        simulate_structure_preserving(TOP, state, ts[::-1], RKMK(), 0.1)
    with pytest.raises(ValueError, match="orientation"):
        simulate_structure_preserving(TOP, State(OMEGA0), ts, RKMK(), 0.1)


def test_fixed_step_inside_a_jit_takes_the_times_it_closes_over():
    """The step count comes from the sample times, so they must be known when a jitted function is
    traced: NumPy times (and a list) it closes over are, and give the eager values. They raised
    "ts must be concrete ... do not trace them under jit", as traced times still do."""
    ts = np.linspace(0.0, 1.0, 3)
    state = State(OMEGA0, Q0)
    eager = simulate_structure_preserving(TOP, state, ts, RKMK("bosh3"), 0.1)
    for given in (ts, list(ts)):
        inside = jax.jit(lambda g=given: simulate_structure_preserving(TOP, state, g, RKMK("bosh3"), 0.1))()
        np.testing.assert_allclose(inside.omega, eager.omega, rtol=0, atol=1e-14)
        np.testing.assert_allclose(inside.orientation, eager.orientation, rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match="ts must be concrete"):
        jax.jit(lambda t: simulate_structure_preserving(TOP, state, t, RKMK("bosh3"), 0.1))(ts)


def test_deprecated_simulate_structure_preserving_is_simulate():
    """The earlier entry point warns and runs the same fixed-step path as simulate(solver=, dt0=)."""
    ts = jnp.linspace(0.0, 1.0, 3)
    with pytest.warns(DeprecationWarning, match="simulate"):
        old = rj.simulate_structure_preserving(TOP, State(OMEGA0, Q0), ts, RKMK("bosh3"), 0.1)
    new = simulate_structure_preserving(TOP, State(OMEGA0, Q0), ts, RKMK("bosh3"), 0.1)
    np.testing.assert_array_equal(old.omega, new.omega)
