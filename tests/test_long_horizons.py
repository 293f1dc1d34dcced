"""Extremes in time and batch: long horizons, float32, mixed batches, gradients through long and
chaotic horizons, and the zero cases.

References are independent of the integrators under test: the closed-form torque-free motion
(``torque_free_motion``, itself checked against 80-bit Taylor integration in tests/test_torque_free.py),
conservation laws computed here with numpy, and central finite differences.

Compiles dominate on a small CPU, so every ``simulate`` call here has the same shapes (a batch of
8 bodies with orientation, 201 samples): the "fast" preset compiles once, "balanced"/"precise" share
one compile (the tolerance is traced), float32 adds one more.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    IDENTITY_Q,
    RACKET_INERTIA,
    RACKET_OMEGA,
    euler_rhs,
    log_log_slope,
    perturbed_inertia,
    perturbed_omega,
    quat_rotate,
)

import rigidjax as rj

# jacfwd through a diffrax solve needs the forward-mode adjoint (the default adjoint is reverse-mode).
FORWARD = diffrax.ForwardMode()
N_BODIES = 8
N_SAMPLES = 201
IDENTITY = IDENTITY_Q
# A wobble about the largest axis, clear of the separatrix: the long-horizon scene of
# benchmarks/long_horizon.py.
FREE_I = RACKET_INERTIA
FREE_W0 = np.array([0.3, 0.05, 1.0])


def _batch(inertia, omega):
    inertia = np.broadcast_to(np.asarray(inertia, float), (N_BODIES, 3))
    omega = np.broadcast_to(np.asarray(omega, float), (N_BODIES, 3))
    return jnp.asarray(inertia), jnp.asarray(omega), jnp.asarray(np.broadcast_to(IDENTITY, (N_BODIES, 4)))


def _run(inertia, omega, q, ts, accuracy, dtype=jnp.float64, **kwargs):
    cast = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    return rj.simulate(
        rj.FreeBody(cast(inertia)), rj.State(cast(omega), cast(q)), cast(ts), accuracy=accuracy, **kwargs
    )


_BATCHED_CLOSED_FORM = jax.jit(jax.vmap(rj.torque_free_motion, in_axes=(0, 0, 0, None)))


def _reference(inertia, omega, q, ts):
    """Closed-form omega and q, float64, shapes (N, T, 3) and (N, T, 4). One compiled program per
    shape (all of this file's calls are of N_BODIES bodies and N_SAMPLES samples: one program)."""
    return _BATCHED_CLOSED_FORM(
        jnp.asarray(inertia, jnp.float64),
        jnp.asarray(omega, jnp.float64),
        jnp.asarray(q, jnp.float64),
        jnp.asarray(ts, jnp.float64),
    )


def _energy_and_momentum(inertia, omega):
    inertia = np.asarray(inertia, np.float64)[:, None, :]
    omega = np.asarray(omega, np.float64)
    return 0.5 * np.sum(inertia * omega**2, axis=-1), np.linalg.norm(inertia * omega, axis=-1)


def _relative_drift(x):
    """Largest |x(t) - x(0)| / |x(0)| per body over the first and over the second half."""
    rel = np.abs(x - x[:, :1]) / np.abs(x[:, :1])
    half = x.shape[1] // 2
    return np.max(rel[:, : half + 1]), np.max(rel[:, half:])


def _rotation_angle_error(q, q_ref):
    """Angle (rad) of the rotation q_ref^* q, accurate down to roundoff (no arccos near 1)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q_ref = np.asarray(q_ref, np.float64)
    w = np.sum(q * q_ref, axis=-1)
    w_ref, v_ref, w_q, v_q = q_ref[..., 0], q_ref[..., 1:], q[..., 0], q[..., 1:]
    vector = w_ref[..., None] * v_q - w_q[..., None] * v_ref - np.cross(v_ref, v_q)
    return 2 * np.arctan2(np.linalg.norm(vector, axis=-1), np.abs(w))


# ----------------------------------------------------------------------------------------------
# Long horizons


FREE_PERIOD = float(rj.torque_free_period(jnp.asarray(FREE_I), jnp.asarray(FREE_W0)))
LONG_PERIODS = 1000


@pytest.fixture(scope="module")
def long_runs():
    inertia, omega, q = _batch(FREE_I, FREE_W0)
    ts = np.linspace(0.0, LONG_PERIODS * FREE_PERIOD, N_SAMPLES)
    runs = {acc: _run(inertia, omega, q, ts, acc) for acc in ("fast", "balanced", "precise", "exact")}
    return inertia, omega, q, ts, runs


# Energy-error bounds after 1000 wobble periods (1.04e4 s), about 3x what was measured (fast 1.7e-3,
# balanced 2.7e-7, precise 1.1e-10, exact 3.4e-16): the same as without the orientation (2.6e-3,
# 2.8e-7, 1.1e-10), whose equation does not set the step.
LONG_BOUNDS = {"fast": 5e-3, "balanced": 8e-7, "precise": 3e-10, "exact": 2e-15}
# | |q| - 1 | of the integrated quaternion before the output is normalised (measured 2.5e-5,
# 1.8e-7, 3.7e-12, 1.3e-15): unit norm is attracting in simulate's quaternion equation.
QNORM_BOUNDS = {"fast": 1.5e-4, "balanced": 1e-6, "precise": 1e-11, "exact": 1e-14}


@pytest.mark.slow
@pytest.mark.parametrize("accuracy", ["fast", "balanced", "precise", "exact"])
def test_long_horizon_drift_per_preset(long_runs, accuracy, extreme):
    inertia, omega, q, ts, runs = long_runs
    traj = runs[accuracy]
    omega_ref, q_ref = (np.asarray(x)[:1] for x in _reference(inertia, omega, q, ts))  # the shared shape
    w = np.asarray(traj.omega)[:1]  # NumPy slices: no eager programs
    energy, momentum = _energy_and_momentum(inertia[:1], w)
    e_first, e_second = _relative_drift(energy)
    l_first, l_second = _relative_drift(momentum)
    # Before normalisation for the integrators; the closed form's samples, which nothing normalises.
    qnorm = np.max(np.abs(np.linalg.norm(np.asarray(traj.invariants()["quaternion_norm"]))))
    omega_err = np.max(np.abs(w - np.asarray(omega_ref))) / np.max(np.abs(np.asarray(omega_ref)))
    angle_err = np.max(_rotation_angle_error(np.asarray(traj.orientation)[:1], q_ref))
    bound = LONG_BOUNDS[accuracy]
    assert max(e_first, e_second) <= bound, (e_first, e_second)
    assert max(l_first, l_second) <= bound, (l_first, l_second)
    assert qnorm <= QNORM_BOUNDS[accuracy], qnorm
    print(accuracy, e_first, e_second, l_first, l_second, qnorm, omega_err, angle_err)
    extreme(
        "long horizon",
        f"1000 wobble periods ({ts[-1]:.0f} s), accuracy={accuracy!r}",
        "energy drifts linearly" if accuracy != "exact" else "roundoff at any time (eps x phase)",
        max(e_first, e_second),
        bound,
        "accuracy='exact' (torque-free) or a splitting solver for conservation over long runs",
    )
    extreme("long horizon", f"1000 periods, accuracy={accuracy!r}: omega error", "", omega_err, None)
    extreme(
        "long horizon", f"1000 periods, accuracy={accuracy!r}: orientation angle error", "", angle_err, None
    )


@pytest.mark.slow
def test_closed_form_after_ten_thousand_periods(extreme):
    """The closed form's cost and error do not grow with time: 1e4 periods against the omega
    periodicity (omega(t + P) = omega(t)) and the conserved space-frame L."""
    inertia, omega, q = (jnp.asarray(x) for x in (FREE_I, FREE_W0, IDENTITY))
    ts = jnp.asarray([0.0, 0.3, 1e4 * FREE_PERIOD, 1e4 * FREE_PERIOD + 0.3])
    w, qs = (np.asarray(x) for x in rj.torque_free_motion(inertia, omega, q, ts))
    # The errors in NumPy (float64 throughout): eagerly each jnp operation compiled a program.
    err = float(np.max(np.abs(w[2:] - w[:2])))
    L_space = quat_rotate(qs, FREE_I * w)
    l_err = float(np.max(np.abs(L_space - L_space[0])) / np.linalg.norm(L_space[0]))
    q_err = float(np.max(np.abs(np.linalg.norm(qs, axis=-1) - 1)))
    assert err < 1e-10 and l_err < 1e-13 and q_err < 1e-15, (err, l_err, q_err)
    extreme(
        "long horizon",
        "closed form at 1e4 periods",
        "omega periodic, L and |q| exact",
        max(err, l_err),
        1e-10,
        "accuracy='exact'",
    )


@pytest.mark.slow
@pytest.mark.parametrize("order, bound", [(2, 1e-4), (4, 1e-7)])
def test_splitting_energy_error_is_bounded(order, bound, extreme):
    """Structure-preserving splittings do not drift: over 1e5 steps the energy error of the second
    half is no larger than that of the first (contrast with the presets above)."""
    inertia, omega, q = (jnp.asarray(x) for x in (FREE_I, FREE_W0, IDENTITY))
    dt = 0.03
    ts = jnp.linspace(0.0, 1e5 * dt, N_SAMPLES)
    traj = rj.simulate(
        rj.FreeBody(inertia),
        rj.State(omega, q),
        ts,
        solver=rj.solvers.LiePoissonSplitting(order=order),
        dt0=dt,
    )
    energy, momentum = _energy_and_momentum(inertia[None], np.asarray(traj.omega)[None])
    e_first, e_second = _relative_drift(energy)
    l_first, l_second = _relative_drift(momentum)
    qnorm = float(np.max(np.abs(np.linalg.norm(np.asarray(traj.orientation), axis=-1) - 1)))
    assert max(e_first, e_second) <= bound
    assert e_second < 1.2 * e_first, (e_first, e_second)
    assert max(l_first, l_second) < 1e-12 and qnorm < 1e-12, (l_first, l_second, qnorm)
    extreme(
        "long horizon",
        f"1e5 steps of LiePoissonSplitting({order}), dt = 0.03 s",
        "energy error bounded, |L| and |q| to roundoff",
        max(e_first, e_second),
        bound,
        "a splitting for long conservative runs (1e6 steps: benchmarks/long_horizon.py)",
    )


# ----------------------------------------------------------------------------------------------
# Mixed batches: one fast body among slow ones


@pytest.mark.slow
def test_mixed_batch_every_body_meets_the_tolerance(extreme):
    """Seven bodies at |omega| ~ 1 and one 1000x faster, integrated together with one shared step:
    no body is less accurate than when integrated on its own (the step is accepted only when every
    body passes), and the slow bodies meet the tolerance."""
    rng = np.random.default_rng(3)
    inertia = perturbed_inertia(rng, N_BODIES, 0.1)
    omega = rng.normal(size=(N_BODIES, 3))
    fast = 3
    omega[fast] *= 1000.0
    inertia, omega, q = _batch(inertia, omega)
    ts = np.linspace(0.0, 10.0, N_SAMPLES)
    omega_ref, _ = _reference(inertia, omega, q, ts)
    scale = np.linalg.norm(np.asarray(omega), axis=-1)[:, None, None]
    alone_inertia, alone_omega, _ = _batch(inertia[fast], omega[fast])
    for accuracy, bound in (("fast", 3e-4), ("balanced", 3e-7), ("precise", 3e-10)):
        err = np.max(
            np.abs(np.asarray(_run(inertia, omega, q, ts, accuracy).omega) - omega_ref) / scale, axis=(1, 2)
        )
        alone = _run(alone_inertia, alone_omega, q, ts, accuracy).omega[0]
        err_alone = np.max(np.abs(np.asarray(alone) - omega_ref[fast])) / scale[fast, 0, 0]
        slow = np.delete(err, fast)
        print(accuracy, err, err_alone)
        assert np.all(slow <= bound), (accuracy, slow)
        # The fast body turns ~1600 times in 10 s, so its error is the global error of a long run,
        # the same as on its own.
        assert err[fast] <= 1.5 * err_alone, (accuracy, err[fast], err_alone)
        extreme(
            "mixed batch",
            f"one body 1000x faster, accuracy={accuracy!r}: slow bodies",
            "meet the tolerance (shared step, max norm)",
            np.max(slow),
            bound,
            "nothing to do; sort_by_speed keeps the slow bodies cheap in big batches",
        )
        extreme(
            "mixed batch",
            f"one body 1000x faster, accuracy={accuracy!r}: the fast body",
            "as accurate as integrated alone",
            err[fast] / err_alone,
            1.5,
            "",
        )


# ----------------------------------------------------------------------------------------------
# float32: adequate on regular motion, not on the chaotic batch scene


def _racket_scene(n, seed=0):
    """The n bodies of the benchmarks' tennis-racket scene (benchmarks/README.md) closest to the
    separatrix, s = (|L|^2 - 2 E I_2) / |L|^2."""
    rng = np.random.default_rng(seed)
    inertia = perturbed_inertia(rng, 10_000, 0.05)
    omega = perturbed_omega(rng, 10_000, 0.01)
    L2 = np.sum((inertia * omega) ** 2, axis=-1)
    s = (L2 - np.sum(inertia * omega**2, axis=-1) * inertia[:, 1]) / L2
    hardest = np.argsort(np.abs(s))[:n]
    return inertia[hardest], omega[hardest]


@pytest.mark.slow
def test_float32_regular_motion_and_chaotic_scene(extreme):
    regular = _batch(FREE_I, FREE_W0)
    ts_regular = np.linspace(0.0, 10 * FREE_PERIOD, N_SAMPLES)
    racket = _batch(*_racket_scene(N_BODIES))
    ts_racket = np.linspace(0.0, 20.0, N_SAMPLES)
    cases = (
        # name, scene, times, bound on the integrator's error, bound on the closed form's error
        ("regular wobble, 10 periods", regular, ts_regular, 1e-5, 1e-5),
        (
            "tennis-racket scene, 8 bodies nearest the separatrix, T = 20 s",
            racket,
            ts_racket,
            2.0,
            1e-2,
        ),
    )
    for name, (inertia, omega, q), ts, bound, bound_exact in cases:
        omega_ref, _ = _reference(inertia, omega, q, ts)
        scale = np.max(np.abs(np.asarray(omega_ref)))
        traj32 = _run(inertia, omega, q, ts, "balanced", jnp.float32)
        exact32 = _run(inertia, omega, q, ts, "exact", jnp.float32)
        for traj in (traj32, exact32):
            assert traj.omega.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(traj.omega)))
        err32 = np.max(np.abs(np.asarray(traj32.omega, np.float64) - np.asarray(omega_ref))) / scale
        err_exact32 = np.max(np.abs(np.asarray(exact32.omega, np.float64) - np.asarray(omega_ref))) / scale
        print(name, err32, err_exact32)
        assert err32 <= bound and err_exact32 <= bound_exact, (name, err32, err_exact32)
        chaotic = bound > 1
        if chaotic:
            # The integrator in float32 loses the flip phase on this scene: the error is O(1), not
            # O(eps32). The closed form keeps it (roundoff enters through s only once).
            assert err32 > 0.1, err32
        advice = (
            "float64; in float32 only accuracy='exact' keeps the flip phase (error ~1e-3)"
            if chaotic
            else "float32 is fine (error ~ 1e-6 relative)"
        )
        behaviour = "loses the flip phase" if chaotic else "integrates, no NaN"
        extreme("float32", f"{name}, accuracy='balanced'", behaviour, err32, bound, advice)
        extreme("float32", f"{name}, accuracy='exact'", "evaluates, no NaN", err_exact32, bound_exact, advice)


# ----------------------------------------------------------------------------------------------
# Gradients through long horizons


@pytest.mark.slow
def test_gradient_growth_near_the_separatrix_matches_the_period_sensitivity(extreme):
    """Torque-free motion is integrable, so d omega(T)/d omega0 grows LINEARLY with T, with the
    secular coefficient (d omega/dt) (T/P) dP/d omega0; near the separatrix dP/d omega0 ~ 1/s is
    huge. The gradient through the integrator (jacfwd through simulate) agrees with the gradient of
    the closed form, and the growth per period matches -omega_dot * dP/d omega0 / P."""
    inertia = jnp.asarray(RACKET_INERTIA)
    omega0 = jnp.asarray(RACKET_OMEGA)
    period = float(rj.torque_free_period(inertia, omega0))
    dperiod = np.asarray(jax.jit(jax.grad(rj.torque_free_period, argnums=1))(inertia, omega0))

    def final_omega_sim(w0, t1):
        ts = jnp.stack([jnp.zeros_like(t1), t1])
        return rj.simulate(rj.FreeBody(inertia), rj.State(w0), ts, accuracy="precise", adjoint=FORWARD).omega[
            -1
        ]

    def final_omega_exact(w0, t1):
        return rj.torque_free_omega(inertia, w0, t1)

    jac_sim = jax.jit(jax.jacfwd(final_omega_sim))
    jac_exact = jax.jit(jax.jacfwd(final_omega_exact))
    norms = []
    # Sample the same phase of the motion (t = k P + t_phase) so the secular growth is visible.
    t_phase = 0.3 * period
    for k in (1, 2, 4, 8):
        t1 = jnp.asarray(k * period + t_phase)
        j_sim, j_exact = np.asarray(jac_sim(omega0, t1)), np.asarray(jac_exact(omega0, t1))
        np.testing.assert_allclose(j_sim, j_exact, rtol=1e-5, atol=1e-5 * np.max(np.abs(j_exact)))
        norms.append(np.max(np.abs(j_exact)))
    # Linear growth: the difference between successive samples is the secular term per period.
    j_k = [np.asarray(jac_exact(omega0, jnp.asarray(k * period + t_phase))) for k in (8, 9)]
    secular = j_k[1] - j_k[0]
    # Euler's equations in NumPy (tests/helpers.py): one eager program fewer.
    omega_dot = euler_rhs(
        RACKET_INERTIA, np.asarray(rj.torque_free_omega(inertia, omega0, jnp.asarray(t_phase)))
    )
    predicted = -np.outer(omega_dot, dperiod)
    np.testing.assert_allclose(secular, predicted, rtol=1e-6, atol=1e-6 * np.max(np.abs(predicted)))
    growth = log_log_slope([1, 2, 4, 8], norms)
    assert 0.7 < growth < 1.1, growth
    extreme(
        "gradients",
        "tennis racket (integrable), d omega(T)/d omega0 over 1-8 flips",
        f"grows linearly (log-log slope {growth:.2f}), {np.max(np.abs(predicted)):.0f} per period",
        float(np.max(np.abs(secular - predicted)) / np.max(np.abs(predicted))),
        1e-6,
        "fit long records with segments= (multiple shooting)",
    )


# An asymmetric heavy top (centre of mass off every principal axis) is not integrable: its
# trajectories separate exponentially and so do gradients through them.
CHAOS_TOP = dict(inertia=jnp.asarray([1.0, 2.0, 3.0]), mass=1.0, com=jnp.asarray([1.0, 0.0, 0.0]))
CHAOS_W0 = jnp.asarray([0.0, 0.0, 1.0])
CHAOS_Q0 = rj.quat_from_euler(jnp.asarray([0.0, 1.2, 0.0]))
CHAOS_T = (2.0, 4.0, 8.0, 16.0)


def _top_final_omega(w0, t1, t0, q0=CHAOS_Q0):
    ts = jnp.stack([t0, t1])
    traj = rj.simulate(rj.HeavyTop(**CHAOS_TOP), rj.State(w0, q0), ts, accuracy="precise", adjoint=FORWARD)
    return traj.omega[-1]


_top_jac = jax.jit(jax.jacfwd(_top_final_omega))
_top_final = jax.jit(_top_final_omega)


@pytest.mark.slow
def test_gradient_growth_through_chaos_and_multiple_shooting(extreme):
    """Gradients through the chaotic heavy top grow exponentially with the horizon; they agree with
    central finite differences while those are meaningful; and windows of fixed length (multiple
    shooting) keep each window's sensitivity at the short-horizon size."""
    t0 = jnp.asarray(0.0)
    norms = []
    for t1 in CHAOS_T:
        # q0 passed, as in the windows below: the same arguments, one compiled program for both.
        jac = np.asarray(_top_jac(CHAOS_W0, jnp.asarray(t1), t0, CHAOS_Q0))
        norms.append(np.linalg.norm(jac, 2))
        if t1 <= 4.0:
            h = 1e-6
            fd = np.stack(
                [
                    (
                        np.asarray(_top_final(np.asarray(CHAOS_W0) + h * e, jnp.asarray(t1), t0))
                        - np.asarray(_top_final(np.asarray(CHAOS_W0) - h * e, jnp.asarray(t1), t0))
                    )
                    / (2 * h)
                    for e in np.eye(3)  # NumPy: no eager program per step
                ],
                axis=-1,
            )
            np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-6 * np.max(np.abs(fd)))
    rate = np.polyfit(CHAOS_T, np.log(norms), 1)[0]
    # Exponential, not linear growth: log|J| rises by a roughly constant amount per unit time.
    print(rate, norms)
    assert rate > 0.4, (rate, norms)
    assert norms[-1] > 1e3 * norms[0], norms
    # Multiple shooting: four windows of 4 s over the 16 s record, each with its own start state
    # (taken from the trajectory itself), have sensitivities of the 4 s size.
    traj = rj.simulate(
        rj.HeavyTop(**CHAOS_TOP),
        rj.State(CHAOS_W0, CHAOS_Q0),
        jnp.asarray([0.0, 4.0, 8.0, 12.0]),
        accuracy="precise",
    )
    starts_omega, starts_q = np.asarray(traj.omega), np.asarray(traj.orientation)  # NumPy rows: no programs
    window_norms = [
        np.linalg.norm(
            np.asarray(
                _top_jac(starts_omega[k], jnp.asarray(4.0 * k + 4.0), jnp.asarray(4.0 * k), starts_q[k])
            ),
            2,
        )
        for k in range(4)
    ]
    assert max(window_norms) < norms[-1] / 10, (window_norms, norms)
    extreme(
        "gradients",
        "chaotic heavy top, |d omega(T)/d omega0| for T = 2..16 s",
        f"grows like exp({rate:.2f} T): {norms[0]:.1f} -> {norms[-1]:.3g}",
        norms[-1],
        None,
        f"multiple shooting (fit_inertia(segments=K)): per-window sensitivity <= {max(window_norms):.3g}",
    )


# ----------------------------------------------------------------------------------------------
# The zero cases


@pytest.mark.slow
def test_zero_angular_velocity_value_and_gradient(extreme):
    """A body at rest stays at rest, and the linearisation about rest is exact: d omega(T)/d omega0
    = identity and d q(T)/d omega0 = [0; (T/2) identity] (q = exp(omega0 T / 2) to first order)."""
    inertia, omega, q = _batch(FREE_I, np.zeros(3))
    ts = np.linspace(0.0, 2.0, N_SAMPLES)
    expected = np.concatenate([np.eye(3), np.zeros((1, 3)), 0.5 * ts[-1] * np.eye(3)])
    for accuracy in ("balanced", "exact"):
        traj = _run(inertia, omega, q, ts, accuracy)
        assert np.all(np.asarray(traj.omega) == 0.0)
        np.testing.assert_allclose(
            np.asarray(traj.orientation), np.broadcast_to(IDENTITY, (N_BODIES, N_SAMPLES, 4)), atol=1e-15
        )

    # Through the integrator (forward mode) and through the closed form.
    def final_simulated(w0):
        tr = _run(inertia, jnp.broadcast_to(w0, (N_BODIES, 3)), q, ts, "balanced", adjoint=FORWARD)
        return jnp.concatenate([tr.omega[0, -1], tr.orientation[0, -1]])

    def final_exact(w0):
        return jnp.concatenate(rj.torque_free_motion(inertia[0], w0, q[0], jnp.asarray(ts[-1])))

    for name, fn in (("balanced", final_simulated), ("exact", final_exact)):
        jac = np.asarray(jax.jit(jax.jacfwd(fn))(jnp.zeros(3)))  # one program (eager: one per op)
        assert np.all(np.isfinite(jac)), (name, jac)
        np.testing.assert_allclose(jac, expected, atol=1e-9)
        extreme(
            "zero cases",
            f"omega = 0, accuracy={name!r}",
            "stays at rest; gradient = linearisation",
            float(np.max(np.abs(jac - expected))),
            1e-9,
            "",
        )


@pytest.mark.slow
def test_zero_torque_zero_duration_single_time(extreme):
    inertia = jnp.asarray(FREE_I)
    omega = jnp.asarray([0.3, -0.2, 1.0])
    ts = np.linspace(0.0, 3.0, 31)  # NumPy: its slice below compiles nothing
    free = rj.simulate(rj.FreeBody(inertia), rj.State(omega), ts)
    # A zero constant torque goes through the torqued code path: same motion as the free body.
    zero_torque = rj.simulate(
        rj.RigidBody(inertia, torque=rj.ConstantTorque(jnp.zeros(3))), rj.State(omega), ts
    )
    exact = rj.torque_free_omega(inertia, omega, ts)
    for traj in (free, zero_torque):
        np.testing.assert_allclose(np.asarray(traj.omega), np.asarray(exact), rtol=0, atol=1e-7)
    # A single output time is zero duration: the initial state comes back (integrators:
    # tests/test_simulate.py::test_single_output_time_returns_initial_state).
    one = rj.simulate(rj.FreeBody(inertia), rj.State(omega, jnp.asarray(IDENTITY)), ts[:1], accuracy="exact")
    assert one.omega.shape == (1, 3) and one.orientation.shape == (1, 4)
    np.testing.assert_array_equal(np.asarray(one.omega)[0], np.asarray(omega))
    np.testing.assert_allclose(np.asarray(one.orientation)[0], IDENTITY, rtol=0, atol=4e-16)
    # Two equal times are a zero-length interval with two samples: rejected, with the reason.
    with pytest.raises(Exception, match="increasing"):
        rj.simulate(rj.FreeBody(inertia), rj.State(omega), jnp.asarray([1.0, 1.0]))
    extreme(
        "zero cases",
        "zero torque, one output time, ts = [t0, t0]",
        "= FreeBody; returns the initial state; duplicate times rejected",
        None,
        None,
        "",
    )


@pytest.mark.slow
def test_default_step_limit_grows_with_the_turns(extreme):
    """5093 turns of a fast spinner (2000 rad/s for 16 s) at "precise" take ~1.1e5 steps, more than
    the fixed 1e5 limit allowed: the default limit now scales with the turns (100 per turn, a power of
    two), the run succeeds and matches the closed form; the old limit, passed explicitly, still stops
    with the error that names it."""
    body = rj.FreeBody(jnp.array([1.0, 2.0, 3.0]))
    state = rj.State(jnp.array([20.0, 1.0, 2000.0]), jnp.asarray(IDENTITY))
    ts = jnp.array([0.0, 16.0])
    trajectory = rj.simulate(body, state, ts, accuracy="precise")
    assert int(np.max(trajectory.stats["num_steps"])) > 100_000
    # The comparison in NumPy: eagerly each jnp index and difference compiled a program.
    reference = [
        np.asarray(x)
        for x in rj.torque_free_motion(body.inertia, state.omega, state.orientation, np.asarray(ts)[-1])
    ]
    omega_end, q_end = np.asarray(trajectory.omega)[-1], np.asarray(trajectory.orientation)[-1]
    assert np.max(np.abs(omega_end - reference[0])) <= 1e-9 * 2000.0
    assert np.max(np.abs(q_end - reference[1])) <= 1e-8
    extreme(
        "long horizon",
        "5093 turns at 2000 rad/s, accuracy='precise', default max_steps",
        "the default step limit grows with the turns: the run completes",
        float(np.max(np.abs(omega_end - reference[0])) / 2000.0),
        1e-9,
        "a longer run or a faster body raises the default limit; under jit pass max_steps",
    )
    with pytest.raises(Exception, match="max_steps=100000"):
        rj.simulate(body, state, ts, accuracy="precise", max_steps=100_000)
