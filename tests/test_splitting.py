"""Lie–Poisson splitting for the free rigid body and the heavy top: orders, invariants, diffrax
wrappers, batch, float32."""

import functools

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dop853, dop853_free_body, log_log_slope

from rigidjax import matrix_from_quat, quat_normalize, quat_rotate, torque_free_omega
from rigidjax._integrate.solvers.rkmk import rigid_body_vector_field
from rigidjax.solvers import LiePoissonSplitting, free_body_vector_field, split_free_body, splitting_step

# Asymmetric body, well away from the separatrix (L^2 - 2 E I2 = 2.5 - ... clearly nonzero).
INERTIA = jnp.array([1.0, 2.0, 3.0])
OMEGA0 = jnp.array([1.0, 0.1, 0.5])
L0 = INERTIA * OMEGA0
Q0 = quat_normalize(jnp.array([0.9, 0.1, -0.3, 0.2]))
T = 5.0


def _energy(L):
    return 0.5 * jnp.sum(L * L / INERTIA.astype(L.dtype), axis=-1)


def _reference(T_end):
    """Tight Dopri8 solution of (L, q)."""
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(free_body_vector_field(INERTIA)),
        diffrax.Dopri8(),
        0.0,
        T_end,
        0.01,
        (L0, Q0),
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=100_000,
    )
    return sol.ys[0][-1], sol.ys[1][-1]


@pytest.mark.parametrize("order", [2, 4])
def test_convergence_order(order):
    L_exact = INERTIA * torque_free_omega(INERTIA, OMEGA0, jnp.asarray(T))
    L_ref, q_ref = _reference(T)
    assert jnp.max(jnp.abs(L_ref - L_exact)) < 1e-12  # the reference agrees with the closed form
    R_ref = matrix_from_quat(q_ref)
    hs, err_L, err_R = [], [], []
    for n in (50, 100, 200, 400):
        L, q = split_free_body(INERTIA, L0, Q0, T / n, n, order)
        hs.append(T / n)
        err_L.append(float(jnp.max(jnp.abs(L - L_exact))))
        err_R.append(float(jnp.max(jnp.abs(matrix_from_quat(q) - R_ref))))
    slope_L, slope_R = log_log_slope(hs, err_L), log_log_slope(hs, err_R)
    print(f"order {order}: L errors {err_L} slope {slope_L:.4f}; R errors {err_R} slope {slope_R:.4f}")
    assert abs(slope_L - order) < 0.1
    assert abs(slope_R - order) < 0.1
    assert err_L[-1] < (1e-5 if order == 2 else 1e-8)


def _run_recording(step, n_steps, dt):
    def body(state, _):
        state = step(*state, dt)
        L, q = state
        return state, (_energy(L), jnp.linalg.norm(L), jnp.linalg.norm(q), quat_rotate(q, L))

    return jax.jit(lambda s: jax.lax.scan(body, s, None, length=n_steps))((L0, Q0))


def test_invariants_long_run():
    n, dt = 100_000, 0.01
    _, (E, normL, normq, Lspace) = _run_recording(
        lambda L, q, h: splitting_step(INERTIA, L, q, h, 2), n, jnp.asarray(dt)
    )
    E0, normL0, Ls0 = _energy(L0), jnp.linalg.norm(L0), quat_rotate(Q0, L0)
    # The reductions in NumPy (float64): eagerly each jnp operation on the records compiled a program.
    E, normL, normq, Lspace, E0, normL0, Ls0 = (
        np.asarray(x) for x in (E, normL, normq, Lspace, E0, normL0, Ls0)
    )
    rel_L = float(np.max(np.abs(normL - normL0)) / normL0)
    q_dev = float(np.max(np.abs(normq - 1.0)))
    dE = np.abs(E - E0) / E0
    first, second = float(np.max(dE[: n // 2])), float(np.max(dE[n // 2 :]))
    space = float(np.max(np.linalg.norm(Lspace - Ls0, axis=-1)) / normL0)
    print(
        f"1e5 Strang steps dt={dt}: max rel ||L| drift {rel_L:.2e}, max ||q|-1| {q_dev:.2e}, "
        f"max |dE/E| first half {first:.3e}, second half {second:.3e}, space-L drift {space:.2e}"
    )
    assert rel_L < 1e-14 * 10  # a few ulps accumulated over 1e5 rotations; see the report
    assert q_dev < 1e-13
    assert second <= 2.0 * first
    assert first < 1e-3
    assert space < 1e-12


def _rk4_step(L, q, h):
    vf = free_body_vector_field(INERTIA)

    def f(y):
        return vf(0.0, y, None)

    def add(y, k, a):
        return jax.tree_util.tree_map(lambda u, v: u + a * v, y, k)

    y = (L, q)
    k1 = f(y)
    k2 = f(add(y, k1, 0.5 * h))
    k3 = f(add(y, k2, 0.5 * h))
    k4 = f(add(y, k3, h))
    return jax.tree_util.tree_map(
        lambda u, a, b, c, d: u + h / 6.0 * (a + 2 * b + 2 * c + d), y, k1, k2, k3, k4
    )


def test_space_angular_momentum_vs_rk4():
    n, dt = 20_000, jnp.asarray(0.05)
    Ls0, normL0 = quat_rotate(Q0, L0), jnp.linalg.norm(L0)
    _, (Es, _, _, Ls_split) = _run_recording(lambda L, q, h: splitting_step(INERTIA, L, q, h, 2), n, dt)
    _, (Er, _, nq_rk4, Ls_rk4) = _run_recording(_rk4_step, n, dt)
    drift_split = float(jnp.linalg.norm(Ls_split[-1] - Ls0) / normL0)
    drift_rk4 = float(jnp.linalg.norm(Ls_rk4[-1] - Ls0) / normL0)
    E0 = _energy(L0)
    dE_split = float(jnp.max(jnp.abs(Es - E0)) / E0)
    dE_rk4 = float(jnp.abs(Er[-1] - E0) / E0)
    print(
        f"{n} steps dt=0.05: space-L drift split {drift_split:.2e} vs RK4 {drift_rk4:.2e}; "
        f"|dE/E| split max {dE_split:.2e} vs RK4 final {dE_rk4:.2e}; "
        f"RK4 ||q|-1| {abs(float(nq_rk4[-1]) - 1):.2e}"
    )
    assert drift_split < 1e-11
    assert drift_rk4 > 1e3 * drift_split


@pytest.mark.parametrize("order", [2, 4])
def test_diffrax_wrapper_matches(order):
    n = 100
    dt = T / n
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(free_body_vector_field(INERTIA)),
        LiePoissonSplitting(INERTIA, order=order),
        0.0,
        T,
        dt,
        (L0, Q0),
        stepsize_controller=diffrax.ConstantStepSize(),
        saveat=diffrax.SaveAt(t1=True),
    )
    L, q = split_free_body(INERTIA, L0, Q0, dt, n, order)
    assert sol.stats["num_steps"] == n
    np.testing.assert_allclose(sol.ys[0][-1], L, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.ys[1][-1], q, rtol=0, atol=1e-12)
    assert LiePoissonSplitting(INERTIA, order=order).order(None) == order


def test_diffrax_wrapper_dense_and_ts():
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(free_body_vector_field(INERTIA)),
        LiePoissonSplitting(INERTIA),
        0.0,
        1.0,
        0.01,
        (L0, Q0),
        stepsize_controller=diffrax.ConstantStepSize(),
        saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, 1.0, 11)),
    )
    L_exact = INERTIA * torque_free_omega(INERTIA[None], OMEGA0[None], jnp.linspace(0.0, 1.0, 11))
    assert jnp.max(jnp.abs(sol.ys[0] - L_exact)) < 1e-4


@pytest.mark.parametrize("order", [2, 4])
def test_dense_output_between_steps_keeps_the_structure_and_the_order(order):
    """Values saved off the step grid came from a linear interpolation between the step's ends:
    |q| - 1 of 4e-6 mid-step at dt = 0.01, and first order. Reference: the closed form
    (torque_free_omega); the order from halving dt."""
    ts = jnp.array([0.0, 0.905, 1.805, 2.705])  # inside a step for both step sizes
    L_exact = INERTIA * torque_free_omega(INERTIA[None], OMEGA0[None], ts)
    errors = []
    # One term (its vector field a closure, static in diffeqsolve's jit: a new one per step size
    # compiled anew) and dt0 an array (a Python float is static too): one program for both steps.
    term, solver = diffrax.ODETerm(free_body_vector_field(INERTIA)), LiePoissonSplitting(INERTIA, order=order)
    for dt in (0.02, 0.01):
        sol = diffrax.diffeqsolve(
            term, solver,
            0.0, 3.0, jnp.asarray(dt), (L0, Q0), stepsize_controller=diffrax.ConstantStepSize(),
            saveat=diffrax.SaveAt(ts=ts),
        )  # fmt: skip
        L, q = sol.ys
        assert np.max(np.abs(np.linalg.norm(q, axis=-1) - 1.0)) < 1e-14
        np.testing.assert_allclose(np.linalg.norm(L, axis=-1), np.linalg.norm(L0), rtol=1e-14)
        errors.append(float(jnp.max(jnp.abs(L - L_exact))))
    assert abs(np.log2(errors[0] / errors[1]) - order) < 0.3, errors


def test_bad_order():
    with pytest.raises(ValueError):
        LiePoissonSplitting(INERTIA, order=3)
    with pytest.raises(ValueError):
        split_free_body(INERTIA, L0, Q0, 0.1, 10, order=3)


@jax.jit
def _random_bodies(key):
    """16 random bodies: moments, omega and a unit quaternion. One program (eagerly, each random
    draw, the sort and the normalisation compiled one of their own)."""
    k1, k2, k3 = jax.random.split(key, 3)
    B = 16
    inertia = jnp.sort(jax.random.uniform(k1, (B, 3), minval=1.0, maxval=3.0), axis=-1)
    omega0 = jax.random.normal(k2, (B, 3))
    q0 = quat_normalize(jax.random.normal(k3, (B, 4)))
    return inertia, omega0, q0, inertia * omega0


def test_batch_vmap_and_broadcast():
    inertia, omega0, q0, L0_batch = _random_bodies(jax.random.PRNGKey(0))
    n = 400
    # jit around the vmap: vmapped eagerly, split_free_body ran op by op (a program per operation).
    run = jax.jit(jax.vmap(lambda I, L, q: split_free_body(I, L, q, T / n, n, 4)))
    L_v, q_v = run(inertia, L0_batch, q0)
    L_b, q_b = split_free_body(inertia, L0_batch, q0, T / n, n, 4)  # leading batch axis
    np.testing.assert_allclose(L_v, L_b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(q_v, q_b, rtol=0, atol=1e-12)
    inertia_np, L_v_np = np.asarray(inertia), np.asarray(L_v)  # the error in NumPy: no eager programs
    L_exact = inertia_np * np.asarray(torque_free_omega(inertia, omega0, jnp.asarray(T)))
    err = np.max(np.abs(L_v_np - L_exact), axis=-1) / np.linalg.norm(L_exact, axis=-1)
    assert np.all(err < 1e-5)
    L0_np, q0_np = np.asarray(L0_batch), np.asarray(q0)  # NumPy rows: no eager indexing programs
    for b in (0, 7):
        L1, q1 = split_free_body(inertia_np[b], L0_np[b], q0_np[b], T / n, n, 4)
        np.testing.assert_allclose(L1, L_v_np[b], rtol=0, atol=1e-12)


@pytest.mark.parametrize("order", [2, 4])
def test_float32(order):
    I32, L32, q32 = INERTIA.astype(jnp.float32), L0.astype(jnp.float32), Q0.astype(jnp.float32)
    n = 10_000
    L, q = split_free_body(I32, L32, q32, np.float32(0.01), n, order)
    assert L.dtype == jnp.float32 and q.dtype == jnp.float32
    L_exact = INERTIA * torque_free_omega(INERTIA, OMEGA0, jnp.asarray(0.01 * n))
    normL0 = float(jnp.linalg.norm(L0))
    rel_norm = abs(float(jnp.linalg.norm(L.astype(jnp.float64))) - normL0) / normL0
    q_dev = abs(float(jnp.linalg.norm(q.astype(jnp.float64))) - 1.0)
    err = float(jnp.max(jnp.abs(L.astype(jnp.float64) - L_exact)))
    print(
        f"float32 order {order}, 1e4 steps: rel |L| drift {rel_norm:.2e}, "
        f"||q|-1| {q_dev:.2e}, L err {err:.2e}"
    )
    assert rel_norm < 1e-4  # the rotations' rounding, a random walk
    assert q_dev < 1e-6  # normalised at each step: it drifted to 7e-6 here without
    assert err < 1e-2
    # A steady tumble over 2e5 steps: the rounded cos of the same small angle at every step gave a
    # linear |L| drift (1.1e-3 here; the random walk of the rounding alone stays near 1e-5).
    I, L_tumble = jnp.array([1.0, 2.0, 2.5], jnp.float32), jnp.array([0.3, 0.2, 5.0], jnp.float32)
    L, _ = split_free_body(I, L_tumble, q32, np.float32(0.01), 200_000, order)
    norm0 = np.linalg.norm(np.asarray(L_tumble, np.float64))
    assert abs(np.linalg.norm(np.asarray(L, np.float64)) / norm0 - 1.0) < 5e-5
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(free_body_vector_field(I32)),
        LiePoissonSplitting(I32, order=order),
        jnp.float32(0.0),  # float32 times: diffrax promotes y0 to the time dtype
        jnp.float32(1.0),
        jnp.float32(0.01),
        (L32, q32),
        stepsize_controller=diffrax.ConstantStepSize(),
    )
    assert sol.ys[0].dtype == jnp.float32


# ---------------------------------------------------------------------------------------------
# The heavy top: gravity kick + free-body splitting.

from rigidjax import HeavyTop, State  # noqa: E402
from rigidjax._integrate.solvers.splitting import (  # noqa: E402
    HeavyTopSplitting,
    _gravity_kick,
    _strang,
    heavy_top_splitting_step,
    heavy_top_vector_field,
    heavy_top_weight_com,
    split_heavy_top,
)

# An asymmetric top, com off every axis, fast spin plus a wobble: nothing special about it.
TOP = HeavyTop(jnp.array([1.0, 1.4, 0.6]), 1.2, jnp.array([0.05, -0.03, 0.4]), 9.81)
TOP_OMEGA0 = jnp.array([0.8, -0.4, 9.0])
TOP_L0 = TOP.inertia * TOP_OMEGA0
TOP_Q0 = quat_normalize(jnp.array([0.95, 0.25, -0.1, 0.15]))
TOP_WCOM = heavy_top_weight_com(TOP.mass, TOP.com, TOP.gravity)
TOP_T = 2.0


def _top_energy(L, q):
    return 0.5 * jnp.sum(L * L / TOP.inertia, axis=-1) + TOP.potential_energy(q)


def _top_Lz(L, q):
    return quat_rotate(q, L)[..., 2]


# The model's own angular acceleration for scipy's DOP853: one compiled program for every reference.
_top_accel = jax.jit(lambda w, q: TOP.angular_acceleration(0.0, State(w, q), None))


@functools.cache
def _top_reference(T_end):
    """scipy DOP853 (tests/helpers.py) at rtol = atol = 1e-13 on HeavyTop.angular_acceleration (the
    model's own equations, not the splitting's) with dq/dt = q (0, omega) / 2."""
    w, q = dop853(
        lambda t, w, q: np.asarray(_top_accel(jnp.asarray(w), jnp.asarray(q))),
        TOP_OMEGA0,
        [T_end],
        TOP_Q0,
        tol=1e-13,
    )
    return np.asarray(TOP.inertia) * w[-1], q[-1]


def test_heavy_top_vector_field_matches_model():
    """The splitting's equations are the model's: dL/dt = I domega/dt along the model, at random states;
    the kick changes L by h times the model's gravity torque."""
    w = jax.random.normal(jax.random.PRNGKey(3), (5, 3))
    q = quat_normalize(jax.random.normal(jax.random.PRNGKey(4), (5, 4)))
    vf = heavy_top_vector_field(TOP.inertia, TOP.mass, TOP.com, TOP.gravity)

    @jax.jit
    def compare(w, q):
        dL, _ = vf(0.0, (TOP.inertia * w, q), None)
        model = TOP.inertia * jax.vmap(lambda a, b: TOP.angular_acceleration(0.0, State(a, b), None))(w, q)
        kick = _gravity_kick(TOP_WCOM, TOP.inertia * w, q, 0.3) - TOP.inertia * w
        return dL, model, kick, 0.3 * TOP.gravity_torque(q)

    dL, expected, kick, expected_kick = compare(w, q)
    np.testing.assert_allclose(dL, expected, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(kick, expected_kick, rtol=1e-13, atol=1e-14)


@functools.cache
def _top_integrator(order):
    """One compiled run for every step count (a dynamic trip count) of the given order."""

    def run(dt, n):
        def body(_, state):
            return heavy_top_splitting_step(TOP.inertia, TOP_WCOM, *state, dt, order)

        return jax.lax.fori_loop(0, n, body, (TOP_L0, TOP_Q0))

    return jax.jit(run)


@pytest.mark.parametrize("order", [2, 4])
def test_heavy_top_convergence_order(order):
    L_ref, q_ref = _top_reference(TOP_T)
    R_ref = matrix_from_quat(jnp.asarray(q_ref))
    ns = (100, 200, 400, 800)
    hs, err_L, err_R = [], [], []
    for n in ns:
        L, q = _top_integrator(order)(jnp.asarray(TOP_T / n), n)
        hs.append(TOP_T / n)
        err_L.append(float(jnp.max(jnp.abs(L - L_ref))))
        err_R.append(float(jnp.max(jnp.abs(matrix_from_quat(q) - R_ref))))
    slope_L, slope_R = log_log_slope(hs, err_L), log_log_slope(hs, err_R)
    print(
        f"heavy top order {order}: L errors {err_L} slope {slope_L:.4f}; R errors {err_R} slope {slope_R:.4f}"
    )
    assert abs(slope_L - order) < 0.1
    assert abs(slope_R - order) < 0.1
    assert err_L[-1] < (1e-4 if order == 2 else 1e-7)


def test_heavy_top_substeps_conserve_Lz():
    """Each sub-flow alone conserves the vertical angular momentum (R L) . Z to roundoff."""
    q = quat_normalize(jax.random.normal(jax.random.PRNGKey(5), (64, 4)))
    L = jax.random.normal(jax.random.PRNGKey(6), (64, 3))

    @jax.jit
    def changes(L, q):
        Lz0 = _top_Lz(L, q)
        L_kick = _gravity_kick(TOP_WCOM, L, q, 0.7)
        L_free, q_free = _strang(TOP.inertia, L, q, 0.7)
        scale = jnp.linalg.norm(L, axis=-1) + 0.7 * jnp.linalg.norm(TOP_WCOM)
        return (
            jnp.max(jnp.abs(L_kick - L)),
            jnp.max(jnp.abs(_top_Lz(L_kick, q) - Lz0) / scale),
            jnp.max(jnp.abs(_top_Lz(L_free, q_free) - Lz0) / scale),
        )

    kick_size, kick_dev, free_dev = (float(x) for x in changes(L, q))
    print(f"L_Z change: kick {kick_dev:.2e}, free Strang {free_dev:.2e}")
    assert kick_size > 0.1  # the kick does change L
    assert kick_dev < 1e-15 * 8
    assert free_dev < 1e-15 * 8


def _top_run_recording(n_steps, dt, order):
    def body(state, _):
        state = heavy_top_splitting_step(TOP.inertia, TOP_WCOM, *state, dt, order)
        L, q = state
        return state, (_top_energy(L, q), _top_Lz(L, q), jnp.linalg.norm(q))

    return jax.jit(lambda s: jax.lax.scan(body, s, None, length=n_steps))((TOP_L0, TOP_Q0))


def test_heavy_top_invariants_long_run():
    n, dt = 100_000, jnp.asarray(0.005)
    _, (E, Lz, normq) = _top_run_recording(n, dt, 2)
    E0, Lz0, normL0 = _top_energy(TOP_L0, TOP_Q0), _top_Lz(TOP_L0, TOP_Q0), jnp.linalg.norm(TOP_L0)
    # Energy relative to kinetic + |potential| at t = 0 (the potential may cross zero).
    E_scale = 0.5 * jnp.sum(TOP_L0**2 / TOP.inertia) + jnp.abs(TOP.potential_energy(TOP_Q0))
    # The reductions in NumPy (float64): eagerly each jnp operation on the records compiled a program.
    E, Lz, normq, E0, Lz0, normL0, E_scale = (np.asarray(x) for x in (E, Lz, normq, E0, Lz0, normL0, E_scale))
    dE = np.abs(E - E0) / E_scale
    first, second = float(np.max(dE[: n // 2])), float(np.max(dE[n // 2 :]))
    lz = float(np.max(np.abs(Lz - Lz0)) / normL0)
    q_dev = float(np.max(np.abs(normq - 1.0)))
    print(
        f"heavy top 1e5 Strang steps dt={float(dt)}: max |dE|/E first half {first:.3e}, second half "
        f"{second:.3e}; max |dL_Z|/|L| {lz:.2e}; max ||q|-1| {q_dev:.2e}"
    )
    assert second <= 1.5 * first  # bounded, no drift
    assert first < 1e-3
    assert lz < 1e-12
    assert q_dev < 1e-13


def test_heavy_top_diffrax_wrapper(order=4):  # order 2 is the same code path with another static order
    n = 200
    dt = TOP_T / n
    vf = heavy_top_vector_field(TOP.inertia, TOP.mass, TOP.com, TOP.gravity)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf),
        HeavyTopSplitting.from_model(TOP, order=order),
        0.0,
        TOP_T,
        dt,
        (TOP_L0, TOP_Q0),
        stepsize_controller=diffrax.ConstantStepSize(),
        saveat=diffrax.SaveAt(t1=True),
    )
    L, q = split_heavy_top(TOP.inertia, TOP.mass, TOP.com, TOP.gravity, TOP_L0, TOP_Q0, dt, n, order)
    assert sol.stats["num_steps"] == n
    np.testing.assert_allclose(sol.ys[0][-1], L, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.ys[1][-1], q, rtol=0, atol=1e-12)
    assert HeavyTopSplitting(TOP.inertia, TOP.mass, TOP.com, order=order).order(None) == order


def test_a_quaternion_off_unit_norm_means_its_rotation():
    """A q of norm 2 means the rotation of q / |q| (as the input checks say): the gravity kick read
    R(q) as if |q| were 1, a torque 4x too large (omega(2 s) off by 2 rad/s)."""
    dt, n = TOP_T / 200, 200
    args = (TOP.inertia, TOP.mass, TOP.com, TOP.gravity)
    L, q = split_heavy_top(*args, TOP_L0, TOP_Q0, dt, n)
    L2, q2 = split_heavy_top(*args, TOP_L0, 2.0 * TOP_Q0, dt, n)
    np.testing.assert_allclose(L2, L, rtol=0, atol=1e-13 * float(jnp.max(jnp.abs(L))))
    np.testing.assert_allclose(q2, q, rtol=0, atol=1e-14)


def test_heavy_top_errors():
    with pytest.raises(ValueError, match="order"):
        HeavyTopSplitting(TOP.inertia, 1.0, TOP.com, order=3)
    # A (3, 3) inertia is a tensor: the axis flows need principal moments.
    with pytest.raises(ValueError, match="principal moments"):
        split_heavy_top(jnp.eye(3), 1.0, TOP.com, 9.81, TOP_L0, TOP_Q0, 0.1, 2)
    with pytest.raises(ValueError, match="principal moments"):
        split_free_body(jnp.eye(3), L0, Q0, 0.1, 2)
    with pytest.raises(ValueError, match="principal moments"):
        diffrax.diffeqsolve(
            diffrax.ODETerm(heavy_top_vector_field(TOP.inertia, 1.0, TOP.com)),
            HeavyTopSplitting(jnp.eye(3), 1.0, TOP.com),
            0.0,
            0.1,
            0.05,
            (TOP_L0, TOP_Q0),
        )
    with pytest.raises(ValueError, match="extra torques"):
        HeavyTopSplitting.from_model(HeavyTop(TOP.inertia, 1.0, TOP.com, torque=lambda t, s, a: -s.omega))


def test_heavy_top_batch_matches_single():
    """Leading batch axes (per-body mass and com) agree with one body at a time."""
    masses = jnp.array([0.5, 1.0, 2.0])
    coms = jnp.array([[0.0, 0.0, 0.3], [0.05, -0.03, 0.4], [0.1, 0.1, 0.2]])
    n = 100
    L_b, q_b = split_heavy_top(TOP.inertia, masses, coms, 9.81, TOP_L0, TOP_Q0, 0.01, n, 4)
    assert L_b.shape == (3, 3) and q_b.shape == (3, 4)
    for b in range(3):
        L1, q1 = split_heavy_top(TOP.inertia, masses[b], coms[b], 9.81, TOP_L0, TOP_Q0, 0.01, n, 4)
        np.testing.assert_allclose(L_b[b], L1, rtol=0, atol=1e-12)
        np.testing.assert_allclose(q_b[b], q1, rtol=0, atol=1e-12)


def test_solvers_without_parameters_for_simulate():
    """LiePoissonSplitting(order=4) / HeavyTopSplitting(order=4) take the scene's parameters from
    the model in simulate: the heavy top conserves energy and L_Z (independent of the solver); a
    scalar first argument (LiePoissonSplitting(4)) is rejected rather than read as the inertia, and
    a parameterless solver used directly in diffrax says what is missing."""
    import rigidjax as rj

    ts = jnp.linspace(0.0, TOP_T, 11)
    traj = rj.simulate(TOP, State(TOP_OMEGA0, TOP_Q0), ts, solver=HeavyTopSplitting(order=4), dt0=0.005)
    inv = traj.invariants()
    # Order 4 measured 6.5e-9 (order 2 gives 6.1e-6: the bound catches a silently ignored order).
    assert float(inv["energy"]) < 2e-8 and float(inv["vertical_angular_momentum"]) < 1e-12, inv
    with pytest.raises(ValueError, match="first argument is the inertia"):
        LiePoissonSplitting(4)
    with pytest.raises(ValueError, match="only through rigidjax.simulate"):
        diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: y),
            LiePoissonSplitting(order=4),
            0.0,
            0.1,
            0.05,
            (TOP_L0, TOP_Q0),
        )


# ---------------------------------------------------------------------------------------------
# Backward in time, and simulate's chunks of three bodies.


def _backward(solver, vector_field, y0, dt):
    """``diffeqsolve`` from t = 0 back to t = -1, sampled at -0.37 (inside a step) and -1."""
    return diffrax.diffeqsolve(
        diffrax.ODETerm(vector_field),
        solver,
        0.0,
        -1.0,
        -dt,
        y0,
        stepsize_controller=diffrax.ConstantStepSize(),
        saveat=diffrax.SaveAt(ts=jnp.array([-0.37, -1.0])),
    ).ys


def test_backward_in_time_is_the_motion_backward():
    """diffeqsolve from a later to an earlier time runs forward in -t with the terms wrapped; the
    splittings and RKMK step by their own maps, so they returned the motion forward in time (the
    state at +1 s as that at -1 s). Reference: scipy's DOP853 integrating backward, on the model's
    equations (tests/helpers.py)."""
    from rigidjax.solvers import RKMK

    ts = np.array([-0.37, -1.0])
    free_w, free_q = dop853_free_body(np.asarray(INERTIA), np.asarray(OMEGA0), ts, np.asarray(Q0), tol=1e-13)
    top_w, top_q = dop853(
        lambda t, w, q: np.asarray(_top_accel(jnp.asarray(w), jnp.asarray(q))),
        TOP_OMEGA0,
        ts,
        TOP_Q0,
        tol=1e-13,
    )
    L, q = _backward(LiePoissonSplitting(INERTIA, order=4), free_body_vector_field(INERTIA), (L0, Q0), 0.01)
    np.testing.assert_allclose(L / INERTIA, free_w, atol=1e-8)
    np.testing.assert_allclose(q, free_q, atol=1e-8)
    top_vf = heavy_top_vector_field(TOP.inertia, TOP.mass, TOP.com, TOP.gravity)
    L, q = _backward(HeavyTopSplitting.from_model(TOP, order=4), top_vf, (TOP_L0, TOP_Q0), 0.001)
    np.testing.assert_allclose(L / TOP.inertia, top_w, atol=1e-7)
    np.testing.assert_allclose(q, top_q, atol=1e-8)
    model_vf = rigid_body_vector_field(lambda t, w, q, args: TOP.angular_acceleration(t, State(w, q), args))
    w, q = _backward(RKMK("dopri5"), model_vf, (TOP_OMEGA0, TOP_Q0), 0.001)
    np.testing.assert_allclose(w, top_w, atol=1e-8)
    np.testing.assert_allclose(q, top_q, atol=1e-9)


@pytest.mark.parametrize("scene", ["free", "heavy top"])
def test_simulate_with_a_splitting_on_three_bodies(scene):
    """Three states of one body: the chunk's moments, (3, 3), reached the splitting, which refused
    them as one inertia tensor. Reference: each body simulated alone (the steps are fixed: the same
    arithmetic)."""
    import rigidjax as rj

    inertia = jnp.array([1.0, 2.0, 3.0])
    # NumPy states: their rows below compile nothing (eagerly each jnp index was a program).
    omega0 = np.array([[1.0, 0.1, 0.5], [0.2, 1.0, -0.3], [0.4, -0.2, 2.0]])
    q0 = np.tile(np.asarray(Q0), (3, 1))
    if scene == "free":
        model, solver = rj.FreeBody(inertia), LiePoissonSplitting(order=4)
    else:
        model, solver = rj.HeavyTop(inertia, 1.0, jnp.array([0.0, 0.0, 0.1])), HeavyTopSplitting(order=4)
    ts = jnp.linspace(0.0, 1.0, 5)
    traj = rj.simulate(model, rj.State(omega0, q0), ts, solver=solver, dt0=0.01)
    omega, orientation = np.asarray(traj.omega), np.asarray(traj.orientation)
    for i in range(3):
        alone = rj.simulate(model, rj.State(omega0[i], q0[i]), ts, solver=solver, dt0=0.01)
        np.testing.assert_allclose(omega[i], alone.omega, rtol=0, atol=1e-13)
        np.testing.assert_allclose(orientation[i], alone.orientation, rtol=0, atol=1e-13)


def test_vector_fields_of_other_parameters_share_one_compiled_solve():
    """The vector fields are modules, not closures: a term of another inertia (or of the same
    acceleration function) has the same structure, so a jitted solve traces once. A new closure per
    call compiled diffeqsolve again for every inertia. Reference: each solve against DOP853."""
    import equinox as eqx

    from rigidjax.solvers import heavy_top_vector_field

    y0 = (jnp.array([0.3, 2.0, 0.1]), jnp.array([1.0, 0.0, 0.0, 0.0]))

    def solve(vf):
        term, controller = diffrax.ODETerm(vf), diffrax.PIDController(rtol=1e-10, atol=1e-12)
        return diffrax.diffeqsolve(
            term, diffrax.Tsit5(), 0.0, 1.0, 0.01, y0, stepsize_controller=controller
        ).ys

    free = eqx.filter_jit(eqx.debug.assert_max_traces(solve, max_traces=1))
    for inertia in ([1.0, 2.0, 3.0], [1.0, 2.0, 2.5]):
        L, q = free(free_body_vector_field(jnp.array(inertia)))
        omega_ref, q_ref = dop853_free_body(np.array(inertia), np.asarray(y0[0]) / inertia, [0.0, 1.0], y0[1])
        np.testing.assert_allclose(np.asarray(L[-1]) / inertia, omega_ref[-1], atol=1e-8)
        np.testing.assert_allclose(np.asarray(q[-1]), q_ref[-1], atol=1e-8)
    top = eqx.filter_jit(eqx.debug.assert_max_traces(solve, max_traces=1))
    for mass in (0.5, 0.7):
        top(heavy_top_vector_field(jnp.array([1.0, 1.0, 0.5]), jnp.asarray(mass), jnp.array([0.0, 0.0, 0.1])))
    damped = eqx.filter_jit(eqx.debug.assert_max_traces(solve, max_traces=1))

    def damping(t, omega, q, args):
        return -0.1 * omega

    for _ in range(2):
        omega, _ = damped(rigid_body_vector_field(damping))
        np.testing.assert_allclose(np.asarray(omega[-1]), np.asarray(y0[0]) * np.exp(-0.1), rtol=1e-9)
