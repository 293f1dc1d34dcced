"""``simulate(..., error_estimate=True)``: the per-body estimate against the true error.

The true error of each body comes from a reference that shares no code with the integration: the
closed form (``accuracy="exact"``) for torque-free bodies, scipy's DOP853 at rtol = atol = 1e-13 for
heavy tops. Per body, the estimate must lie between the true error and ten times it. Below a
roundoff floor the true error is not the integrator's to control (nor the reference's to measure),
so there the estimate must only stay above the true error and within ten times the floor. The
floor of a torque-free body grows near the separatrix like ``eps / |s|``,
``s = (|L|^2 - 2 E I2) / |L|^2`` (docs/guides/accuracy.md).
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    EPS64,
    dop853,
    perturbed_inertia,
    quat_multiply,
    quat_rotate,
    random_moments,
    random_quaternions,
)

import rigidjax as rj
from rigidjax.solvers import HeavyTopSplitting


def _omega_error(omega, reference):
    """Largest |omega - reference| over the samples, relative to the body's largest |omega|."""
    diff = np.max(np.linalg.norm(np.asarray(omega) - reference, axis=-1), axis=-1)
    return diff / np.max(np.linalg.norm(reference, axis=-1), axis=-1)


def _angle_error(q, reference):
    """Largest rotation angle (rad) between the orientations over the samples."""
    rel = quat_multiply(np.asarray(q) * np.array([1.0, -1.0, -1.0, -1.0]), reference)
    return np.max(2 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), np.abs(rel[..., 0])), axis=-1)


def _separatrix_distance(inertia, omega):
    """``s = (|L|^2 - 2 E I2) / |L|^2`` per body, cancellation-free: sum_i I_i (I_i - I2) w_i^2."""
    L2 = np.sum((inertia * omega) ** 2, axis=-1)
    return np.sum(inertia * (inertia - inertia[:, 1:2]) * omega**2, axis=-1) / L2


def _torque_free_floor(inertia, omega):
    """The roundoff floor of a torque-free body: 1000 eps, growing like eps / |s| near the separatrix."""
    return EPS64 * np.maximum(1e3, 10 / np.abs(_separatrix_distance(inertia, omega)))


def _check(estimate, true, floor, what):
    """estimate / true in [1, 10] above the floor; below it, estimate >= true and <= 10 floor."""
    estimate, true = np.asarray(estimate), np.asarray(true)
    floor = np.broadcast_to(floor, true.shape)
    above = true > floor
    assert above.sum() >= true.size // 2, f"{what}: the batch is mostly at the roundoff floor"
    ratio = estimate / true
    assert np.all(ratio[above] >= 1.0) and np.all(ratio[above] <= 10.0), (
        f"{what}: estimate / true error {np.sort(ratio[above])}"
    )
    assert np.all(estimate[~above] >= true[~above]) and np.all(estimate[~above] <= 10 * floor[~above]), what
    return ratio[above]


@functools.cache
def _tumbling_problem():
    """24 random bodies tumbling for 5 s: their fast-preset run with the estimate, the closed form
    and the roundoff floor."""
    rng = np.random.default_rng(0)
    n = 24
    inertia = random_moments(rng, (n,))
    omega0 = 2 * rng.normal(size=(n, 3))
    model = rj.FreeBody(jnp.asarray(inertia))
    state0 = rj.State(jnp.asarray(omega0), jnp.asarray(random_quaternions(rng, n)))
    ts = jnp.linspace(0.0, 5.0, 26)
    exact = rj.simulate(model, state0, ts, accuracy="exact")
    traj = rj.simulate(model, state0, ts, accuracy="fast", error_estimate=True)
    return traj, exact, _torque_free_floor(inertia, omega0)


@pytest.fixture(scope="module")
def tumbling():
    """24 random bodies tumbling for 5 s, the fast preset, against the closed form."""
    return _tumbling_problem()


def test_tumbling_batch(tumbling):
    traj, exact, floor = tumbling
    estimate = traj.error_estimate()
    _check(estimate["omega"], _omega_error(traj.omega, np.asarray(exact.omega)), floor, "omega")
    _check(estimate["orientation"], _angle_error(traj.orientation, np.asarray(exact.orientation)), floor, "q")


@pytest.mark.slow
def test_fast_tennis_racket_batch_near_the_separatrix():
    """Spun at 30 rad/s near the intermediate axis, 1e-5 <= |s| <= 1e-2, the balanced preset."""
    rng = np.random.default_rng(1)
    n = 24
    inertia = perturbed_inertia(rng, n, 0.05)
    # One small component dominates the other (no cancellation in s): half the bodies on each side.
    shape = np.ones((n, 3)) * rng.uniform(0.0, 0.3, (n, 1))
    shape[np.arange(n), np.where(np.arange(n) % 2, 0, 2)] = 1.0
    shape[:, 1] = 0.0
    coefficient = np.abs(np.sum(inertia * (inertia - inertia[:, 1:2]) * shape**2, -1))
    target = 10 ** rng.uniform(-5, -2.3, n)  # |s|
    amplitude = np.sqrt(target * (30.0 * inertia[:, 1]) ** 2 / coefficient)
    omega0 = rng.choice([-1.0, 1.0], (n, 3)) * shape * amplitude[:, None] + np.array([0.0, 30.0, 0.0])
    s = np.abs(_separatrix_distance(inertia, omega0))
    assert 1e-5 < s.min() and s.max() < 1e-2 and np.sum(s < 1e-3) >= n // 3
    model = rj.FreeBody(jnp.asarray(inertia))
    state0 = rj.State(jnp.asarray(omega0), jnp.asarray(random_quaternions(rng, n)))
    ts = jnp.linspace(0.0, 2.0, 26)  # the shapes of the tumbling batch: its closed-form program
    exact = rj.simulate(model, state0, ts, accuracy="exact")
    traj = rj.simulate(model, state0, ts, accuracy="balanced", error_estimate=True)
    estimate = traj.error_estimate()
    floor = _torque_free_floor(inertia, omega0)
    _check(estimate["omega"], _omega_error(traj.omega, np.asarray(exact.omega)), floor, "omega")
    _check(estimate["orientation"], _angle_error(traj.orientation, np.asarray(exact.orientation)), floor, "q")


def _heavy_tops(n):
    rng = np.random.default_rng(2)
    inertia = np.array([1.0, 1.1, 0.6]) * (1 + 0.05 * rng.uniform(-1, 1, (n, 3)))
    mass = rng.uniform(0.8, 1.2, n)
    com = np.stack([np.zeros(n), np.zeros(n), rng.uniform(0.3, 0.6, n)], -1)
    omega0 = np.stack([0.5 * rng.normal(size=n), 0.5 * rng.normal(size=n), rng.uniform(5, 15, n)], -1)
    tilt = rng.uniform(0.2, 1.0, n)
    q0 = np.stack([np.cos(tilt / 2), np.sin(tilt / 2), np.zeros(n), np.zeros(n)], -1)
    return inertia, mass, com, omega0, q0


@pytest.fixture(scope="module")
def heavy_top_reference():
    """12 asymmetric heavy tops for 2 s and their DOP853 motion (rtol = atol = 1e-13)."""
    inertia, mass, com, omega0, q0 = _heavy_tops(12)
    ts = np.linspace(0.0, 2.0, 21)
    omega, q = [], []
    for b in range(len(mass)):

        def accel(t, w, q, b=b):
            down = quat_rotate(q * np.array([1.0, -1.0, -1.0, -1.0]), np.array([0.0, 0.0, -9.81 * mass[b]]))
            return (np.cross(inertia[b] * w, w) + np.cross(com[b], down)) / inertia[b]

        w, qb = dop853(accel, omega0[b], ts, q0[b], omega_scale=np.linalg.norm(omega0[b]))
        omega.append(w)
        q.append(qb)
    model = rj.HeavyTop(jnp.asarray(inertia), jnp.asarray(mass), jnp.asarray(com))
    return model, rj.State(jnp.asarray(omega0), jnp.asarray(q0)), ts, np.array(omega), np.array(q)


@pytest.mark.parametrize(
    "options",
    [
        pytest.param({"accuracy": "balanced"}, id="balanced"),
        # A fixed step's estimate (Richardson at dt0 / 2) is in the fast tier with ConstantStepSize.
        pytest.param(
            {"solver": HeavyTopSplitting(), "dt0": 0.01}, id="HeavyTopSplitting", marks=pytest.mark.slow
        ),
    ],
)
def test_heavy_top_batch(heavy_top_reference, options):
    model, state0, ts, omega, q = heavy_top_reference
    traj = rj.simulate(model, state0, jnp.asarray(ts), error_estimate=True, **options)
    estimate = traj.error_estimate()
    floor = 1e3 * EPS64  # the reference's own error is ~1e-13
    _check(estimate["omega"], _omega_error(traj.omega, omega), floor, "omega")
    _check(estimate["orientation"], _angle_error(traj.orientation, q), floor, "q")


def _tumbling_with(options, jit=False):
    """The tumbling batch with an estimate under the user's step control, eagerly or under jit."""
    _, exact, floor = _tumbling_problem()

    def run(model, state0):
        return rj.simulate(model, state0, exact.ts, error_estimate=True, **options)

    state0 = rj.State(exact.omega[:, 0], exact.orientation[:, 0])
    traj = (eqx.filter_jit(run) if jit else run)(exact.model, state0)
    return traj, exact, floor


PID = diffrax.PIDController(rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize(
    ("options", "jit"),
    [
        pytest.param({"solver": diffrax.Tsit5(), "stepsize_controller": PID}, False, id="PIDController"),
        # Steps held at dtmax: the second run took the same steps (an estimate of 2e-15 for 2e-9).
        pytest.param(
            {"solver": diffrax.Tsit5(), "stepsize_controller": diffrax.PIDController(1e-3, 1e-3, dtmax=0.1)},
            False,
            id="PIDController-dtmax",
        ),
        pytest.param(
            {"solver": diffrax.Tsit5(), "stepsize_controller": diffrax.ConstantStepSize(), "dt0": 0.02},
            False,
            id="ConstantStepSize",
        ),
        pytest.param({"accuracy": "fast"}, True, id="fast-under-jit"),
    ],
)
def test_user_step_control_and_jit(options, jit):
    """A PIDController's second run is at tolerances / 100 (and dtmax / 100^(1/order)), a
    ConstantStepSize's at dt0 / 2 (Richardson); under the user's jit the estimate is computed
    inside the program."""
    traj, exact, floor = _tumbling_with(options, jit)
    estimate = traj.error_estimate()
    _check(estimate["omega"], _omega_error(traj.omega, np.asarray(exact.omega)), floor, "omega")
    _check(estimate["orientation"], _angle_error(traj.orientation, np.asarray(exact.orientation)), floor, "q")


def test_exact_estimate_is_at_roundoff_level(tumbling):
    """The closed form's estimate (a second evaluation at inputs 1 eps away) is roundoff-sized."""
    _, exact, _ = tumbling
    state0 = rj.State(exact.omega[:, 0], exact.orientation[:, 0])
    traj = rj.simulate(exact.model, state0, exact.ts, accuracy="exact", error_estimate=True)
    for value in traj.error_estimate().values():
        assert np.all(np.asarray(value) >= 10 * EPS64) and np.all(np.asarray(value) < 1e-11)


def test_without_the_estimate_a_clear_error(tumbling):
    traj, _, _ = tumbling
    plain = rj.Trajectory(traj.ts, traj.omega, traj.orientation, traj.model, traj.success, stats={})
    with pytest.raises(ValueError, match=r"error_estimate=True"):
        plain.error_estimate()


def test_the_estimate_is_saved_and_loaded(tumbling, tmp_path):
    traj, _, _ = tumbling
    traj.save(tmp_path / "t.npz")
    loaded = rj.Trajectory.load(tmp_path / "t.npz").error_estimate()
    for key, value in traj.error_estimate().items():
        np.testing.assert_array_equal(loaded[key], value)


def test_unsupported_step_control_is_refused_before_any_run():
    controller = diffrax.StepTo(ts=jnp.linspace(0.0, 1.0, 11))
    with pytest.raises(ValueError, match=r"error_estimate=True works with"):
        rj.simulate(
            rj.FreeBody(jnp.array([1.0, 2.0, 3.0])),
            rj.State(jnp.array([1.0, 0.1, 0.0])),
            jnp.linspace(0.0, 1.0, 3),
            stepsize_controller=controller,
            error_estimate=True,
        )


@pytest.mark.slow
def test_float32_results_are_checked_by_a_float64_solve(tumbling):
    """float32 with x64 on: the second solve runs in float64, so float32 roundoff is measured too.
    The fast preset's omega is at float32's roundoff floor here (errors 1e-7 to 2e-6), most of its
    orientation errors (5e-7 to 6e-4) above it."""
    traj64, _, _ = tumbling
    model = rj.FreeBody(traj64.model.inertia.astype(jnp.float32))
    state0 = rj.State(traj64.omega[:, 0].astype(jnp.float32), traj64.orientation[:, 0].astype(jnp.float32))
    ts = traj64.ts.astype(jnp.float32)
    traj = rj.simulate(model, state0, ts, accuracy="fast", error_estimate=True)
    wide = jax.tree_util.tree_map(
        lambda x: x.astype(jnp.float64) if eqx.is_inexact_array(x) else x, (model, state0)
    )
    exact = rj.simulate(*wide, ts.astype(jnp.float64), accuracy="exact")  # of the float32 inputs
    estimate = traj.error_estimate()
    assert estimate["omega"].dtype == jnp.float32
    floor = 100 * float(np.finfo(np.float32).eps)
    true_omega = _omega_error(traj.omega.astype(jnp.float64), np.asarray(exact.omega))
    omega = np.asarray(estimate["omega"], np.float64)
    assert np.all(omega >= true_omega) and np.all(omega <= 10 * floor)
    true_angle = _angle_error(traj.orientation.astype(jnp.float64), np.asarray(exact.orientation))
    _check(estimate["orientation"], true_angle, 10 * float(np.finfo(np.float32).eps), "q")


def test_tolerances_at_the_roundoff_floor_leave_no_finer_solve_and_say_so():
    """float32 without x64 at "balanced" (rtol raised to float32's floor, 1.2e-6) ran its second
    solve at the same floor: two identical runs, whose difference read as an error estimate of
    1.2e-6 for every body (the command line's float32 runs: true errors up to 1e-4 rad). Now
    refused, as is a float64 rtol below float64's floor; "fast" in float32 has a finer solve."""
    inertia, omega0 = jnp.array([1.0, 2.0, 3.0]), jnp.array([0.1, 1.0, 0.1])
    with jax.enable_x64(False):
        model = rj.FreeBody(inertia.astype(jnp.float32))
        state = rj.State(omega0.astype(jnp.float32))
        ts = jnp.linspace(0.0, 2.0, 3, dtype=jnp.float32)
        with pytest.raises(ValueError, match=r"at or below float32's floor.*turn on jax_enable_x64"):
            rj.simulate(model, state, ts, error_estimate=True)
        fast = rj.simulate(model, state, ts, accuracy="fast", error_estimate=True)
        assert float(fast.stats["error_estimate_omega"]) > 10 * float(np.finfo(np.float32).eps)
    with pytest.raises(ValueError, match=r"\(1e-15, 1e-15\) are at or below float64's floor.*loosen them\.$"):
        rj.simulate(rj.FreeBody(inertia), rj.State(omega0), jnp.linspace(0.0, 2.0, 3), rtol=1e-15,
                    error_estimate=True)  # fmt: skip


def test_the_estimate_has_a_finite_gradient():
    """The two solutions agree exactly at ts[0], where the norm of their difference had a NaN
    derivative: jax.grad of the estimate through simulate was NaN in every component. Reference:
    central differences of the estimate from the two solutions' samples (both depend on the
    parameters, and they agree at the first sample, as a coarse and a fine solve do)."""
    from rigidjax._integrate.error_estimate import _estimate_from_arrays

    rng = np.random.default_rng(0)
    omega0 = jnp.asarray(rng.normal(size=(2, 5, 3)))
    q0 = jnp.asarray(random_quaternions(rng, 10).reshape(2, 5, 4))
    later = jnp.array([0.0, 1.0, 1.0, 1.0, 1.0])[:, None]
    ok = jnp.ones(2, bool)

    def unit(q):
        return q / jnp.linalg.norm(q, axis=-1, keepdims=True)

    @jax.jit  # one program for the 14 central differences (eagerly, one program per op: 74 compiles)
    def estimate(x):
        fine_omega, fine_q = omega0 + x[:3], unit(q0 + x[3:])
        omega, q = fine_omega + 0.1 * later * x[:3], unit(fine_q + 0.1 * later * x[3:])
        out = _estimate_from_arrays(omega, q, ok, fine_omega, fine_q, ok, 2.0, 0.0)
        return out["error_estimate_omega"].sum() + out["error_estimate_orientation"].sum()

    x = jnp.asarray(rng.normal(size=7) * 1e-2)
    gradient = np.asarray(jax.grad(estimate)(x))
    assert np.all(np.isfinite(gradient))
    h = 1e-7
    central = [(estimate(x + h * e) - estimate(x - h * e)) / (2 * h) for e in np.eye(7)]
    np.testing.assert_allclose(gradient, central, rtol=1e-5, atol=1e-9)
