"""fit_inertia: synthetic truth -> noisy observations -> fit -> truth within the stated uncertainty.

The synthetic records come from the closed-form torque-free motion, checked independently against
scipy in test_torque_free.py. Records of one length share one compiled fit (the shapes and the method
are what compile, not the loss), so the file compiles only a handful of times.
"""

import functools
import json
import os
import subprocess
import sys
import types
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.optimize
from conftest import TEST_XLA_FLAGS

import rigidjax as rj
from rigidjax import estimate_inertia, fit_inertia, fit_inertia_to_orientation
from rigidjax._fit.estimate import _estimate, _local_derivatives
from rigidjax._fit.problem import LOSSES, _Problem

I_TRUE = np.array([1.0, 2.0, 2.5])
W0_TRUE = np.array([0.3, 0.05, 1.0])  # wobble about the largest axis
TRUTH = I_TRUE / I_TRUE.sum()


def record(inertia, omega0, ts, noise, rng, rotation=None):
    w = np.asarray(rj.torque_free_omega(inertia, omega0, ts))
    if rotation is not None:
        w = w @ rotation.T
    return w + noise * np.std(w, axis=0) * rng.standard_normal(w.shape)


def scipy_omega(inertia, omega0, ts, torque=0.0):
    """omega at ``ts`` of Euler's equations in principal axes with a constant body torque, by scipy's
    DOP853 at rtol 1e-12 (independent of rigidjax)."""
    from scipy.integrate import solve_ivp

    inertia, torque = np.asarray(inertia, float), np.asarray(torque, float)
    sol = solve_ivp(
        lambda t, w: (np.cross(inertia * w, w) + torque) / inertia,
        (ts[0], ts[-1]),
        np.asarray(omega0, float),
        method="DOP853",
        rtol=1e-12,
        atol=1e-14,
        t_eval=ts,
    )
    return sol.y.T


@jax.jit
def perturbed(q, rotvec):
    """``q`` turned by the small body-frame rotations ``rotvec`` (the motion-capture noise): one compiled
    program per record length instead of quat_exp's two dozen eager ops, each compiled anew."""
    return rj.quat_multiply(q, rj.kinematics.quat_exp(rotvec))


@functools.cache
def short_times():
    period = float(rj.torque_free_period(I_TRUE, W0_TRUE))
    return np.linspace(0.0, 4.0 * period, 240)


@functools.cache
def long_times():
    period = float(rj.torque_free_period(I_TRUE, W0_TRUE))
    return np.linspace(0.0, 45.0 * period, 1800)


@pytest.mark.slow
def test_principal_fit_recovers_truth_and_methods_agree():
    rng = np.random.default_rng(0)
    ts = short_times()
    obs = record(I_TRUE, W0_TRUE, ts, 0.01, rng)
    lbfgs = fit_inertia(ts, obs)  # optax (L-BFGS) by default
    lm = fit_inertia(ts, obs, method="levenberg-marquardt")
    assert lbfgs.method == "optax" and lm.method == "levenberg-marquardt"
    for fit in (lm, lbfgs):
        assert bool(fit.converged)
        assert fit.inertia.shape == (3,) and fit.omega0.shape == (3,)
        assert abs(float(jnp.sum(fit.inertia)) - 1.0) < 1e-12  # the trace-1 gauge
        z = (np.asarray(fit.inertia) - TRUTH) / np.asarray(fit.inertia_stderr)
        assert np.all(np.abs(z) < 4.0), z
        z0 = (np.asarray(fit.omega0) - W0_TRUE) / np.asarray(fit.omega0_stderr)
        assert np.all(np.abs(z0) < 4.0), z0
        assert np.all(np.isfinite(fit.history)) and fit.history.shape == (fit.num_steps,)
        assert float(fit.history[-1]) <= float(fit.history[0])
    np.testing.assert_allclose(lm.inertia, lbfgs.inertia, rtol=1e-6)
    # Levenberg–Marquardt needs far fewer iterations.
    assert lm.num_steps < lbfgs.num_steps
    # The fitted model reproduces the record to the noise level.
    pred = np.asarray(lm.predict_omega(ts))
    noise = 0.01 * np.std(np.asarray(rj.torque_free_omega(I_TRUE, W0_TRUE, ts)), axis=0)
    assert np.all(np.sqrt(np.mean((pred - obs) ** 2, axis=0)) < 1.3 * noise)
    np.testing.assert_allclose(lm.residual_rms, np.sqrt(np.mean((pred - obs) ** 2, axis=0)), rtol=1e-6)


@pytest.mark.slow
def test_forward_and_reverse_gradients_give_the_same_fit(monkeypatch):
    """Long records take the optax gradient in reverse mode, short ones through the forward-mode
    Jacobian: the two derivatives of one loss, so the same fit to the optimiser's tolerance."""
    from rigidjax._fit import optimisers

    rng = np.random.default_rng(0)
    ts = short_times()
    obs = record(I_TRUE, W0_TRUE, ts, 0.01, rng)
    forward = fit_inertia(ts, obs)
    monkeypatch.setattr(optimisers, "FORWARD_GRADIENT_SAMPLES", 0)
    reverse = fit_inertia(ts, obs)
    assert bool(forward.converged) and bool(reverse.converged)
    np.testing.assert_allclose(reverse.inertia, forward.inertia, rtol=1e-7)
    np.testing.assert_allclose(reverse.inertia_stderr, forward.inertia_stderr, rtol=1e-5)


@pytest.mark.slow
def test_standard_errors_are_honest():
    """Over repeated noise draws the truth lies within 2 sigma about 95 % of the time."""
    rng = np.random.default_rng(1)
    ts = short_times()
    inside = []
    for _ in range(30):
        obs = record(I_TRUE, W0_TRUE, ts, 0.03, rng)
        fit = fit_inertia(ts, obs)
        inside.append(np.abs(np.asarray(fit.inertia) - TRUTH) < 2.0 * np.asarray(fit.inertia_stderr))
        inside.append(np.abs(np.asarray(fit.omega0) - W0_TRUE) < 2.0 * np.asarray(fit.omega0_stderr))
    fraction = np.mean(inside)
    # 180 checks (correlated within a draw); a 95 % rate gives 0.90-1.0 here, 0.8 means the errors
    # are understated by ~1.5x.
    assert 0.88 <= fraction <= 1.0, fraction


@pytest.mark.slow
@pytest.mark.parametrize("method", ["optax", "levenberg-marquardt"])
def test_float32_fit_reaches_the_float64_optimum(method):
    """In float32 the loss resolves only ~1e-7 of itself, far coarser than the default tolerance:
    the fit still converges (the default L-BFGS stops where even a steepest-descent line search
    finds no lower loss) and lands within a small fraction of a standard error of the float64 fit.
    Levenberg-Marquardt solves for its steps from the Jacobian: 0.003 measured, 0.05 asserted.
    L-BFGS's line search compares losses, whose float32 roundoff is ~1e-6 of them: 0.02 to 0.07
    measured on the same record (the stopping point moves with the roundoff of the compiled
    program), 0.15 asserted."""
    rng = np.random.default_rng(0)
    ts = short_times()
    obs = record(I_TRUE, W0_TRUE, ts, 0.01, rng)
    reference = fit_inertia(ts, obs, method=method)
    single = fit_inertia(ts, obs, method=method, dtype=jnp.float32)
    assert single.inertia.dtype == jnp.float32 and single.omega0.dtype == jnp.float32
    assert bool(single.converged) and bool(reference.converged)
    z = (np.asarray(single.inertia, np.float64) - np.asarray(reference.inertia)) / np.asarray(
        reference.inertia_stderr
    )
    limit = 0.15 if method == "optax" else 0.05
    assert np.all(np.abs(z) < limit), z
    z0 = (np.asarray(single.omega0, np.float64) - np.asarray(reference.omega0)) / np.asarray(
        reference.omega0_stderr
    )
    assert np.all(np.abs(z0) < limit), z0
    np.testing.assert_allclose(single.inertia_stderr, reference.inertia_stderr, rtol=1e-3)


def test_float32_standard_errors_of_a_flat_body_match_float64():
    """A flat body (I3 = I1 + I2) sits on the edge of the physical moments, where the record does not
    determine the direction across the edge: that moment's standard error is infinite and the other
    two are finite, in float32 as in float64 (the float64 fit is the reference). With the eigenvalues of
    J^T J rather than the singular values of J, float32 gave every standard error infinite."""
    rng = np.random.default_rng(1)
    ts = jnp.linspace(0.0, 20.0, 240)  # as many samples as short_times(): the same compiled fits
    flat = np.array([1.0, 2.0, 3.0])
    clean = rj.simulate(
        rj.FreeBody(jnp.asarray(flat)), rj.State(jnp.array([0.3, 0.2, 1.0])), ts, accuracy="exact"
    )
    obs = np.asarray(clean.omega) + 1e-3 * rng.standard_normal(clean.omega.shape)
    # From the estimated start, given as inertia_init: without it each fit, ending on the flat-body
    # edge (the truth), fits again from six other starts, all of which end at a loss 4e4 times
    # higher (measured), so each returns this same first fit.
    start, _ = estimate_inertia(ts, obs)
    reference = fit_inertia(ts, obs, inertia_init=start)
    single = fit_inertia(ts, obs, dtype=jnp.float32, inertia_init=start)
    stderr64 = np.asarray(reference.inertia_stderr)
    stderr32 = np.asarray(single.inertia_stderr, np.float64)
    assert np.isinf(stderr64[2]) and np.isinf(stderr32[2])
    assert np.all(np.isfinite(stderr64[:2])) and np.all(np.isfinite(stderr32[:2]))
    np.testing.assert_allclose(stderr32[:2], stderr64[:2], rtol=0.02)


@pytest.mark.slow
def test_a_flat_body_fit_under_xla_defaults_keeps_its_infinite_standard_error():
    """The float32 flat-body fit of the test above, compiled as users compile it (XLA's default
    optimisation, not the suite's -O1), in a process of its own. On the flat-body edge the softmax
    that keeps the moments physical saturates; there its gradient underflowed to exactly zero, and the
    largest moment's standard error came out 0 (a claim of exact knowledge) without the flat-body
    warning."""
    code = """
import json
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import rigidjax as rj
rng = np.random.default_rng(1)
ts = jnp.linspace(0.0, 20.0, 240)
body, state = rj.FreeBody(jnp.array([1.0, 2.0, 3.0])), rj.State(jnp.array([0.3, 0.2, 1.0]))
clean = rj.simulate(body, state, ts, accuracy="exact")
obs = np.asarray(clean.omega) + 1e-3 * rng.standard_normal(clean.omega.shape)
start, _ = rj.estimate_inertia(ts, obs)
fit = rj.fit_inertia(ts, obs, dtype=jnp.float32, inertia_init=start)
print(json.dumps([np.asarray(fit.inertia_stderr, np.float64).tolist(), fit.warnings]))
"""
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if f != TEST_XLA_FLAGS)
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    stderr, warnings_shown = json.loads(done.stdout.strip().splitlines()[-1])
    assert np.isinf(stderr[2]) and np.all(np.isfinite(stderr[:2])), stderr
    assert any("flat body" in warning for warning in warnings_shown), warnings_shown


@pytest.mark.slow
def test_gauge_scaled_inertia_and_known_scale():
    """c I moves the same way as I: the normalised fit is the same; a known scale gives c I back."""
    rng = np.random.default_rng(2)
    ts = short_times()
    c = 3.7e-4
    obs = record(c * I_TRUE, W0_TRUE, ts, 0.01, rng)
    normalised = fit_inertia(ts, obs)
    assert normalised.normalised
    absolute = fit_inertia(ts, obs, known_moment=(2, c * I_TRUE[2]))
    assert not absolute.normalised
    np.testing.assert_allclose(absolute.inertia / jnp.sum(absolute.inertia), normalised.inertia, rtol=1e-10)
    z = (np.asarray(absolute.inertia[:2]) - c * I_TRUE[:2]) / np.asarray(absolute.inertia_stderr[:2])
    assert np.all(np.abs(z) < 4.0), z
    assert float(absolute.inertia_stderr[2]) < 1e-12 * c  # the known moment carries no error
    by_trace = fit_inertia(ts, obs, inertia_trace=c * I_TRUE.sum())
    np.testing.assert_allclose(by_trace.inertia, c * I_TRUE.sum() * normalised.inertia, rtol=1e-10)


@pytest.mark.slow
def test_multiple_shooting_succeeds_where_single_shooting_fails():
    """45 wobble cycles from a poor start (moments 8 % off): single shooting locks onto a wrong
    frequency; windows of about one cycle recover the truth."""
    rng = np.random.default_rng(3)
    ts = long_times()
    obs = record(I_TRUE, W0_TRUE, ts, 0.02, rng)
    poor = np.array([1.0, 1.7, 2.6])
    with pytest.warns(RuntimeWarning, match=r"residuals are \d+\.\d times the record's noise"):
        single = fit_inertia(ts, obs, inertia_init=poor)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the right minimum: no warning
        multiple = fit_inertia(ts, obs, inertia_init=poor, segments="auto")
    assert multiple.omega0.shape[0] >= 40
    assert np.max(np.abs(np.asarray(single.inertia) - TRUTH)) > 1e-2
    z = (np.asarray(multiple.inertia) - TRUTH) / np.asarray(multiple.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), z
    assert float(multiple.loss) < 0.01 * float(single.loss)
    # Both "converge"; the residual against the estimated noise tells the local minimum apart.
    assert np.max(np.asarray(single.residual_rms / single.noise_estimate)) > 2.0
    assert np.max(np.asarray(multiple.residual_rms / multiple.noise_estimate)) < 1.25
    # `warnings` says so in words; the right minimum has none.
    assert any("times the record's noise estimate" in w for w in single.warnings) and multiple.warnings == []
    # Each window starts at one of the sample times, and the windows' predictions fit the record.
    assert np.all(np.isin(np.asarray(multiple.segment_starts), ts)) and multiple.segment_starts[0] == ts[0]
    exact = np.asarray(rj.torque_free_omega(I_TRUE, W0_TRUE, ts))
    residual = np.asarray(multiple.predict_omega(ts)) - obs
    assert np.all(np.sqrt(np.mean(residual**2, axis=0)) < 1.3 * 0.02 * np.std(exact, axis=0))


@pytest.mark.slow
def test_missing_samples_and_outliers_need_a_robust_loss(monkeypatch):
    rng = np.random.default_rng(4)
    ts = long_times()
    obs = record(I_TRUE, W0_TRUE, ts, 0.02, rng)
    obs[rng.choice(ts.size, 90, replace=False)] = np.nan  # whole samples missing
    obs[rng.choice(ts.size, 40, replace=False), 1] = np.nan  # single components missing
    flat = rng.choice(obs.size, 40, replace=False)
    obs.flat[flat] = np.where(np.isnan(obs.flat[flat]), np.nan, obs.flat[flat] + 3.0)  # gross outliers
    segments = 45
    # The squared fit from the estimated start, given as inertia_init: without it the fit, ending on
    # the flat-body edge, fits again from six other starts (seven L-BFGS runs of up to 2000 steps, 60 s
    # on a 2-core CPU), each of which also ends on the edge at no lower loss (measured: 2.4833 from the
    # estimate, 2.4833 to 2.5173 from the others), so it returns this same first fit.
    start, _ = estimate_inertia(ts, obs)
    with pytest.warns(RuntimeWarning, match="times the record's noise"):
        squared = fit_inertia(ts, obs, segments=segments, inertia_init=start)
    traces = []
    evaluate = _Problem.residuals_and_raw
    monkeypatch.setattr(_Problem, "residuals_and_raw", lambda self, p: traces.append(1) or evaluate(self, p))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        robust = fit_inertia(ts, obs, segments=segments, loss="soft_l1")
    assert not traces  # the loss is a traced value: the squared fit's compiled program serves it
    assert np.all(np.isfinite(robust.inertia)) and bool(robust.converged)
    z = (np.asarray(robust.inertia) - TRUTH) / np.asarray(robust.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), z
    err_squared = np.max(np.abs(np.asarray(squared.inertia) - TRUTH))
    err_robust = np.max(np.abs(np.asarray(robust.inertia) - TRUTH))
    assert err_robust < 0.2 * err_squared
    # The squared fit ends with a moment on the flat-body edge, undetermined; `warnings` names it.
    assert any("flat body" in w for w in squared.warnings) and robust.warnings == [], squared.warnings


SCIPY_LOSSES = {"squared": "linear", "huber": "huber", "soft_l1": "soft_l1", "cauchy": "cauchy"}


@pytest.mark.parametrize("loss, scipy_loss", SCIPY_LOSSES.items())
def test_losses_are_scipys(loss, scipy_loss):
    """The fit's sum of squared weighted residuals is ``f^2 sum rho((r / f)^2)`` with scipy's rho:
    against the cost scipy.optimize.least_squares reports for the same residuals (twice it: scipy's
    cost has a factor 1/2), residuals that do not depend on the parameter so that scipy stops where
    it starts; with weights, and with residuals of zero."""
    rng = np.random.default_rng(11)
    raw = np.concatenate([rng.normal(scale=2.0, size=(20, 3)), np.zeros((2, 3))])
    weights, f_scale = np.array([0.5, 1.0, 2.0]), 0.7
    stand_in = types.SimpleNamespace(
        weights=jnp.asarray(weights), f_scale=jnp.asarray(f_scale), loss_index=jnp.asarray(LOSSES.index(loss))
    )
    ours = float(jnp.sum(_Problem._weighted(stand_in, jnp.asarray(raw)) ** 2))
    scaled = (raw * weights).ravel()
    theirs = scipy.optimize.least_squares(lambda x: scaled, [0.0], loss=scipy_loss, f_scale=f_scale)
    assert theirs.nfev == 1 and np.array_equal(theirs.x, [0.0])
    np.testing.assert_allclose(ours, 2.0 * theirs.cost, rtol=1e-14)


@pytest.mark.slow
def test_full_tensor_recovers_tensor_and_axes():
    rng = np.random.default_rng(5)
    ts = short_times()
    R = np.asarray(rj.matrix_from_euler(np.array([0.4, 0.7, -0.3])))
    tensor = R @ np.diag(I_TRUE) @ R.T
    obs = record(I_TRUE, W0_TRUE, ts, 0.01, rng, rotation=R)
    fit = fit_inertia(ts, obs, full_tensor=True)
    assert fit.inertia.shape == (3, 3)
    np.testing.assert_allclose(fit.inertia, fit.inertia.T, atol=1e-15)
    z = (np.asarray(fit.inertia) - tensor / np.trace(tensor)) / np.asarray(fit.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), z
    np.testing.assert_allclose(fit.principal_moments, TRUTH, atol=5 * float(np.max(fit.inertia_stderr)))
    # Axes up to sign: |cos| of the angle between fitted and true principal axes.
    cosines = np.abs(np.sum(np.asarray(fit.principal_axes) * R, axis=0))
    assert np.all(cosines > 1 - 1e-4), cosines
    assert bool(jnp.all(rj.is_physical_inertia(fit.inertia)))


@pytest.mark.slow
def test_earth_like_body_in_si_units():
    """(C - A)/A = 3.3e-3, omega ~ 7e-5 rad/s, a wobble period of ~300 days, 1 % gyro noise, and the
    scale fixed by a known polar moment: absolute moments in kg m^2."""
    rng = np.random.default_rng(6)
    A = 8.0e37
    inertia = np.array([A, A * (1 + 1e-4), A * (1 + 3.3e-3)])
    omega0 = np.array([7.292e-6, 0.0, 7.292e-5])
    period = float(rj.torque_free_period(inertia, omega0))
    assert 290 * 86400 < period < 320 * 86400
    ts = np.linspace(0.0, 3.0 * period, 240)
    obs = record(inertia, omega0, ts, 0.01, rng)
    fit = fit_inertia(ts, obs, known_moment=(2, inertia[2]))
    assert bool(fit.converged)
    z = (np.asarray(fit.inertia[:2]) - inertia[:2]) / np.asarray(fit.inertia_stderr[:2])
    assert np.all(np.abs(z) < 4.0), z
    ellipticity = (fit.inertia[2] - fit.inertia[0]) / fit.inertia[0]
    assert abs(float(ellipticity) - 3.3e-3) < 3e-5


def test_estimate_is_a_good_start():
    rng = np.random.default_rng(7)
    ts = short_times()
    obs = record(I_TRUE, W0_TRUE, ts, 0.01, rng)
    moments, smoothed = estimate_inertia(ts, obs)
    assert np.max(np.abs(moments - TRUTH)) < 0.02
    assert np.all(rj.is_physical_inertia(jnp.asarray(moments)))
    exact = np.asarray(rj.torque_free_omega(I_TRUE, W0_TRUE, ts))
    assert np.nanmax(np.abs(smoothed - exact)) < 0.05


@pytest.mark.parametrize("noise", [0.0, 1e-3, 0.1])
@pytest.mark.parametrize("full_tensor", [False, True])
def test_a_steady_rotation_does_not_determine_the_inertia(noise, full_tensor):
    """A rotation at constant angular velocity about a principal axis satisfies Euler's torque-free
    equations for every inertia (omega x (I omega) = 0 for any diagonal I: checked below for two
    unlike bodies), so no estimate from such a record means anything: a ValueError, not the
    arbitrary moments returned before (0.499, 0.25, 0.25 for any body)."""
    ts = np.linspace(0.0, 10.0, 400)
    steady = np.array([0.0, 0.0, 2.0])
    for moments in (np.array([1.0, 2.0, 2.5]), np.array([3.0, 1.0, 2.0])):
        assert np.all(np.cross(steady, moments * steady) == 0.0)
    record = steady + noise * np.random.default_rng(3).normal(size=(ts.size, 3))
    with pytest.raises(ValueError, match="omega_observed does not determine the inertia"):
        estimate_inertia(ts, record, full_tensor=full_tensor)
    # A wobble of 10 times the noise (or of 1e-6 rad/s without noise) is estimated.
    wobble = max(10.0 * noise, 1e-6)
    wobbling = np.asarray(rj.torque_free_omega(I_TRUE, jnp.array([0.0, wobble, 2.0]), jnp.asarray(ts)))
    estimate_inertia(ts, wobbling + noise * np.random.default_rng(4).normal(size=(ts.size, 3)))


@pytest.mark.parametrize("duration, samples", [(20.0, 800), (20.0, 200), (60.0, 2400)])
def test_noise_estimate_is_the_noise_added(duration, samples):
    """The noise per component estimated from a record is the Gaussian noise added to it (1e-3 of a
    unit angular velocity), also on a record shorter than two wobble periods, where the fits that
    smooth the record span a large part of a period and their residuals hold model error."""
    inertia, omega0 = np.array([1.0, 2.0, 2.5]) / 5.5, np.array([0.3, 1.0, -0.5])
    ts = np.linspace(0.0, duration, samples)
    # The times padded (with the last one) to 2400, the longest record's: one compiled closed form
    # serves the three records (it is evaluated at each time on its own).
    padded = np.concatenate([ts, np.full(2400 - samples, ts[-1])])
    clean = rj.torque_free_omega(jnp.asarray(inertia), jnp.asarray(omega0), jnp.asarray(padded))
    clean = np.asarray(clean)[:samples]
    noisy = clean + 1e-3 * np.random.default_rng(0).normal(size=clean.shape)
    noise = _estimate(ts, noisy).noise
    np.testing.assert_allclose(noise, 1e-3, rtol=0.2)


def test_local_fits_are_least_squares_quadratics():
    """The local fits that smooth a record (now solved for all rows at once) are the least-squares
    quadratics of NumPy's ``polyfit`` over each row's window: the rows ``i - 3 .. i + 3`` with their
    observed values where those hold four or more, else the two nearest observed values on each
    side and the row's own; on irregular times with 60 % of the values missing."""
    rng = np.random.default_rng(11)
    ts = np.cumsum(rng.uniform(0.05, 0.15, 120))
    omega = np.stack([np.sin(ts), np.cos(1.3 * ts), ts * np.exp(-0.1 * ts)], axis=1)
    omega[rng.random(omega.shape) < 0.6] = np.nan
    value, slope, leverage = _local_derivatives(ts, omega, 3)
    checked = {"rows": 0, "nearest": 0}
    for c in range(3):
        observed = np.flatnonzero(np.isfinite(omega[:, c]))
        for i in range(ts.size):
            window = observed[(observed >= i - 3) & (observed <= i + 3)]
            kind = "rows"
            if window.size < 4:
                kind, after = "nearest", np.searchsorted(observed, i)
                own = after < observed.size and observed[after] == i
                if after < 2 or after + 2 + own > observed.size:
                    assert np.isnan(value[i, c])
                    continue
                window = observed[after - 2 : after + 2 + own]
            dt = ts[window] - ts[i]
            if kind == "nearest" and np.ptp(dt) > 4 * (ts[min(i + 3, ts.size - 1)] - ts[max(i - 3, 0)]):
                assert np.isnan(value[i, c])
                continue
            quadratic, linear, constant = np.polyfit(dt, omega[window, c], 2)
            np.testing.assert_allclose([value[i, c], slope[i, c]], [constant, linear], rtol=1e-9, atol=1e-9)
            V = np.vander(dt, 3, increasing=True)
            np.testing.assert_allclose(leverage[i, c], np.linalg.inv(V.T @ V)[0, 0], rtol=1e-9)
            checked[kind] += 1
    assert checked["rows"] > 50 and checked["nearest"] > 50, checked


def test_a_record_with_most_values_missing_is_estimated():
    """60 % of the values missing at random, few rows complete: the local fits took a fixed run of
    rows, which often held under four values of a component, so the noise estimate of a component
    was NaN or off by a factor of two (0.49 to 1.27 of the noise over these six draws), and a short
    record had no row with all three fits, hence no start estimate. Reference: the Gaussian noise
    added (1e-3 rad/s) and the moments that made the record."""
    inertia, omega0 = np.array([1.0, 2.0, 2.5]) / 5.5, np.array([0.3, 1.0, -0.5])
    ts = np.linspace(0.0, 20.0, 300)
    # Padded to the 2400 times of the test above: the same compiled closed form.
    padded = np.concatenate([ts, np.full(2400 - ts.size, ts[-1])])
    clean = np.asarray(rj.torque_free_omega(jnp.asarray(inertia), jnp.asarray(omega0), jnp.asarray(padded)))
    ratios = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        noisy = clean[: ts.size] + 1e-3 * rng.normal(size=(ts.size, 3))
        noisy[rng.random(noisy.shape) < 0.6] = np.nan
        estimate = _estimate(ts, noisy)
        ratios.append(estimate.noise / 1e-3)
        assert np.max(np.abs(estimate.inertia - inertia)) < 0.005
    ratios = np.array(ratios)
    assert np.all((ratios > 0.75) & (ratios < 1.35)), ratios
    assert abs(np.mean(ratios) - 1.0) < 0.1, ratios
    # A short record: 100 samples, under ten of them complete.
    short = ts[::3][:100]
    noisy = clean[: ts.size : 3][:100] + 1e-3 * np.random.default_rng(7).normal(size=(100, 3))
    noisy[np.random.default_rng(8).random(noisy.shape) < 0.6] = np.nan
    assert np.isfinite(noisy).all(axis=1).sum() < 10
    moments, _ = estimate_inertia(short, noisy)
    assert np.max(np.abs(np.asarray(moments) - inertia)) < 0.02


@pytest.mark.parametrize("samples, spin", [(240, 1.0), (960, 1.0), (240, 5.0)])
def test_orientation_noise_estimate_is_the_noise_added(samples, spin):
    """The noise of orientation samples (1 mrad body-frame rotations added to the closed-form motion)
    as the orientation fit estimates it, over 5 noise draws: within 8 % of the noise on average
    and 20 % in each. It was read from the differentiated angular velocity's scatter about local
    fits, which absorbed part of it: 25 % low at 960 samples, 23 % low at 240 with a 5x spin."""
    from rigidjax._fit.data import _check_quaternions
    from rigidjax._fit.prepare import _prepare_orientation

    ts = np.linspace(0.0, 8.0, samples)
    q0 = np.asarray(rj.quat_from_euler(np.array([0.3, 0.7, -0.2])))
    clean = rj.torque_free_motion(I_TRUE, spin * np.array([0.3, 0.1, 2.0]), q0, ts)[1]
    ratios = []
    for seed in range(5):
        rng = np.random.default_rng(seed)
        q = np.asarray(perturbed(clean, 1e-3 * rng.normal(size=(samples, 3))))
        ts_checked, q_checked = _check_quaternions(ts, q)
        data = _prepare_orientation(
            ts_checked, q_checked, 1, False, None, None, None, "squared", None, jnp.float64
        )
        ratios.append(np.asarray(data.noise) / 1e-3)
    assert np.all(np.abs(np.array(ratios) - 1.0) < 0.2), ratios
    assert np.all(np.abs(np.mean(ratios, axis=0) - 1.0) < 0.08), np.mean(ratios, axis=0)


@pytest.mark.slow
def test_known_torque_fixes_the_scale():
    """A known constant body torque makes the absolute inertia identifiable: the fit integrates the
    torqued motion and returns kg m^2. The record is made by simulate (an independent integrator
    path: Dopri8 through rigidjax.simulate at the precise preset)."""
    inertia = np.array([0.02, 0.04, 0.05])
    tau = np.array([0.002, -0.001, 0.003])
    ts = np.linspace(0.0, 3.0, 240)
    model = rj.RigidBody(jnp.asarray(inertia), rj.ConstantTorque(jnp.asarray(tau)))
    w = np.asarray(rj.simulate(model, rj.State(jnp.array([3.0, 0.5, 10.0])), ts, accuracy="precise").omega)
    rng = np.random.default_rng(10)
    obs = w + 0.01 * np.std(w, axis=0) * rng.standard_normal(w.shape)
    # LM: the optax path differentiates the integrator in reverse mode, a second large compile.
    fit = fit_inertia(ts, obs, torque=rj.ConstantTorque(jnp.asarray(tau)), method="levenberg-marquardt")
    assert bool(fit.converged) and not fit.normalised
    z = (np.asarray(fit.inertia) - inertia) / np.asarray(fit.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), z
    assert np.all(np.asarray(fit.residual_rms / fit.noise_estimate) < 1.2)
    # The fitted model's prediction integrates the torque too (not the torque-free closed form).
    predicted = np.asarray(fit.predict_omega(ts[::10]))
    assert np.max(np.abs(predicted - w[::10]) / np.std(w, axis=0)) < 0.01
    with pytest.raises(ValueError, match="already fixes the scale"):
        fit_inertia(ts, obs, torque=rj.ConstantTorque(jnp.asarray(tau)), inertia_trace=1.0)
    with pytest.raises(ValueError, match="needs the orientation"):
        fit_inertia(ts, obs, torque=rj.ConstantTorque(jnp.asarray(tau), frame="space"))


@pytest.mark.slow
def test_the_default_optimiser_converges_with_a_known_torque():
    """With a known torque the loss comes from an integrator and carries its noise (here 4e-7 of the
    loss, for 1e-3 rad/s of measurement noise); L-BFGS at the optimum accepted steps that moved the
    loss either way by that much and ran to its 2000-step limit with converged=False. Record:
    scipy's DOP853 (rtol 1e-12) of Euler's equations with the torque."""
    inertia, tau, w0 = np.array([1.0, 2.0, 2.5]), np.array([0.2, -0.1, 0.3]), np.array([0.3, 0.1, 2.0])
    ts = np.linspace(0.0, 4.0, 100)
    obs = scipy_omega(inertia, w0, ts, tau) + 1e-3 * np.random.default_rng(3).standard_normal((100, 3))
    fit = fit_inertia(ts, obs, torque=rj.ConstantTorque(jnp.asarray(tau)))
    assert bool(fit.converged) and fit.num_steps < 200, (fit.converged, fit.num_steps)
    z = (np.asarray(fit.inertia) - inertia) / np.asarray(fit.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), z
    assert np.all(np.asarray(fit.residual_rms / fit.noise_estimate) < 1.2)


def test_a_record_that_does_not_determine_the_inertia_has_infinite_standard_errors():
    """A steady spin about a principal axis (omega constant for any inertia) returned the starting
    estimate with standard errors of 0 and converged=True: the pseudo-inverse of J^T J dropped the
    directions it could not invert. The same for a zero known torque, which fixes no scale."""
    # The record lengths of the tests above (240 samples without a torque, 100 with one), whose
    # compiled fits serve here.
    ts = np.linspace(0.0, 10.0, 240)
    moments = np.array([1.0, 2.0, 2.8])
    steady = np.asarray(rj.torque_free_omega(moments, np.array([0.0, 0.0, 1.0]), ts))
    fit = rj.fit_inertia(ts, steady)
    assert np.all(np.isinf(np.asarray(fit.inertia_stderr)))
    tumbling = np.asarray(rj.torque_free_omega(moments, np.array([0.3, 0.5, 1.0]), ts))
    zero = rj.ConstantTorque(np.zeros(3))
    scaled = rj.fit_inertia(ts[:100], tumbling[:100], torque=zero, inertia_init=np.array([5.0, 10.0, 14.0]))
    assert np.all(np.isinf(np.asarray(scaled.inertia_stderr)))
    # A tumbling record determines the normalised inertia: finite errors, and the truth within 5 of them.
    noisy = tumbling + 1e-3 * np.random.default_rng(0).normal(size=tumbling.shape)
    fit = rj.fit_inertia(ts, noisy)
    stderr = np.asarray(fit.inertia_stderr)
    assert np.all(np.isfinite(stderr)) and np.all(stderr > 0)
    assert np.all(np.abs(np.asarray(fit.inertia) - moments / moments.sum()) < 5 * stderr)


@pytest.mark.slow
def test_robust_loss_standard_errors_match_the_spread_over_noise_draws():
    """With a robust loss and outliers, the standard errors were scaled by the residuals' plain
    variance, outliers included: 27x the spread of the fitted values over noise draws (20 outliers
    of 3 rad/s among 600 values). Reference: the empirical spread over 8 draws (the closed form
    torque_free_omega makes the records), here with 20 outliers among 720 values: 240 samples, as
    short_times(), whose compiled fit serves here (the loss is a traced value)."""
    inertia, w0, ts = np.array([1.0, 2.0, 2.5]), np.array([0.3, 0.05, 1.0]), np.linspace(0.0, 20.0, 240)
    w = np.asarray(rj.torque_free_omega(inertia, w0, ts))
    errors, reported = [], []
    for seed in range(8):
        rng = np.random.default_rng(seed)
        obs = (w + 1e-3 * rng.standard_normal(w.shape)).reshape(-1)
        obs[rng.choice(obs.size, 20, replace=False)] += rng.choice([-3.0, 3.0], 20)
        fit = fit_inertia(ts, obs.reshape(w.shape), loss="soft_l1")
        errors.append(np.asarray(fit.inertia) - inertia / inertia.sum())
        reported.append(np.asarray(fit.inertia_stderr))
        # The diagnostic rms against the noise: outliers made the plain rms ~400x the 1e-3 noise,
        # which the docstring reads as a local minimum; its robust estimate is the noise.
        np.testing.assert_allclose(fit.residual_rms, 1e-3, rtol=0.25)
    ratio = np.mean(reported, axis=0) / np.std(errors, axis=0)
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio


def test_gravity_torque_is_com_cross_weight():
    """GravityTorque against r x F with rotation matrices: F = m g R^T (0, 0, -1) in body axes."""
    q = rj.quat_from_euler(jnp.array([0.3, 0.7, -1.1]))
    com, mass, g = np.array([0.1, -0.2, 0.3]), 1.7, 9.81
    tau = np.asarray(rj.GravityTorque(mass, jnp.asarray(com), g)(0.0, rj.State(jnp.zeros(3), q), None))
    R = np.asarray(rj.matrix_from_quat(q))
    np.testing.assert_allclose(tau, np.cross(com, R.T @ np.array([0.0, 0.0, -mass * g])), atol=1e-14)


@pytest.mark.slow
def test_heavy_top_gravity_fixes_the_scale_from_orientations():
    """Motion capture of a heavy top on its pivot, with the weight m g and the centre of mass known
    (GravityTorque): the inertia about the pivot comes out in kg m^2 within its standard errors. The
    record is made by simulate(HeavyTop) (the model class, not GravityTorque); q and -q are mixed
    and one row is missing."""
    inertia, mass, com = np.array([1.3, 1.0, 0.6]), 1.0, np.array([0.0, 0.0, 0.3])
    ts = np.linspace(0.0, 2.0, 151)
    q0 = rj.quat_from_euler(jnp.array([0.2, 0.5, 0.1]))
    top = rj.HeavyTop(jnp.asarray(inertia), mass, jnp.asarray(com))
    truth = rj.simulate(top, rj.State(jnp.array([0.8, -0.5, 9.0]), q0), ts, accuracy="precise").orientation
    rng = np.random.default_rng(12)
    noise = 1e-3
    q = np.array(perturbed(truth, jnp.asarray(noise * rng.standard_normal((151, 3)))))
    q *= np.where(rng.uniform(size=(151, 1)) < 0.3, -1.0, 1.0)
    q[70] = np.nan
    fit = fit_inertia_to_orientation(
        ts, q, torque=rj.GravityTorque(mass, jnp.asarray(com)), method="levenberg-marquardt"
    )
    assert bool(fit.converged) and not fit.normalised
    z = (np.asarray(fit.inertia) - inertia) / np.asarray(fit.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), (fit.inertia, z)
    assert np.all(np.asarray(fit.inertia_stderr) < 3e-3)  # 0.1-0.2 % of the moments at 1 mrad noise
    assert np.all(np.asarray(fit.residual_rms) < 1.25 * noise), fit.residual_rms
    predicted = np.asarray(fit.predict_orientation(ts[::15]))
    assert np.max(1 - np.abs(np.sum(predicted * np.asarray(truth[::15]), axis=-1))) < (3 * noise) ** 2


def orientation_record(rng, noise, rotation=None):
    """Motion-capture-like samples: the closed-form orientation turned by small random rotations,
    with random signs (q and -q are the same orientation) and a few missing rows."""
    ts = short_times()
    q0 = np.asarray(rj.quat_from_euler(np.array([0.3, 1.0, -0.5])))
    q = rj.torque_free_motion(I_TRUE, W0_TRUE, q0, ts)[1]
    q = perturbed(q, noise * rng.standard_normal((ts.size, 3)))
    if rotation is not None:  # sensor axes turned away from the principal axes
        q = rj.quat_multiply(q, rj.quat_conjugate(rj.quat_from_matrix(rotation)))
    q = np.array(q) * rng.choice([-1.0, 1.0], size=(ts.size, 1))
    q[rng.choice(ts.size, 12, replace=False)] = np.nan
    return ts, q, q0


@pytest.mark.slow
def test_orientation_fit_principal():
    rng = np.random.default_rng(8)
    ts, q, q0 = orientation_record(rng, 2e-3)
    # The default optimiser (L-BFGS) here, Levenberg–Marquardt for the full tensor below: both
    # compile the model once (the first call ~34 s on a 2-core CPU; with optax.lbfgs()'s own line
    # search, 71 s).
    fit = fit_inertia_to_orientation(ts, q)
    assert bool(fit.converged)
    z = (np.asarray(fit.inertia) - TRUTH) / np.asarray(fit.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), z
    z0 = (np.asarray(fit.omega0) - W0_TRUE) / np.asarray(fit.omega0_stderr)
    assert np.all(np.abs(z0) < 4.0), z0
    # The fitted start equals the true one up to sign, within its stated error.
    angle = 2 * np.arccos(min(1.0, abs(float(np.dot(np.asarray(fit.orientation0), q0)))))
    assert angle < 4 * float(np.linalg.norm(fit.orientation0_stderr))
    np.testing.assert_allclose(fit.residual_rms, 2e-3, rtol=0.15)  # the noise per axis, in rad
    np.testing.assert_allclose(fit.noise_estimate, 2e-3, rtol=0.5)
    predicted = np.asarray(fit.predict_orientation(ts))
    valid = ~np.isnan(q[:, 0])
    overlap = np.abs(np.sum(predicted[valid] * q[valid], axis=1))
    assert np.all(2 * np.arccos(np.minimum(overlap, 1.0)) < 5 * 2e-3 * np.sqrt(3))
    # The same record scalar last, (x, y, z, w), is a motion no torque-free body makes: the fit
    # says so and names the order.
    with pytest.warns(RuntimeWarning, match=r"times the record's noise.*scalar first, \(w, x, y, z\)"):
        scalar_last = fit_inertia_to_orientation(ts, q[:, [1, 2, 3, 0]])
    assert any("scalar first" in warning for warning in scalar_last.warnings)
    assert fit.warnings == []


@pytest.mark.slow
def test_orientation_fit_full_tensor():
    rng = np.random.default_rng(9)
    R = np.asarray(rj.matrix_from_euler(np.array([0.4, 0.7, -0.3])))
    ts, q, _ = orientation_record(rng, 2e-3, rotation=R)
    fit = fit_inertia_to_orientation(ts, q, full_tensor=True, method="levenberg-marquardt")
    tensor = R @ np.diag(I_TRUE) @ R.T
    z = (np.asarray(fit.inertia) - tensor / np.trace(tensor)) / np.asarray(fit.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), z
    cosines = np.abs(np.sum(np.asarray(fit.principal_axes) * R, axis=0))
    assert np.all(cosines > 1 - 1e-4), cosines


def test_orientation_input_errors():
    ts = np.arange(20.0)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (20, 1))
    with pytest.raises(ValueError, match="unit quaternions; row 3"):
        fit_inertia_to_orientation(ts, np.where(np.arange(20)[:, None] == 3, 2 * q, q))
    with pytest.raises(ValueError, match=r"shape \(T, 4\)"):
        fit_inertia_to_orientation(ts, q[:, :3])
    with pytest.raises(ValueError, match="strictly increasing"):
        fit_inertia_to_orientation(ts[::-1], q)


@pytest.mark.parametrize(
    "ts, omega, kwargs, match",
    [
        (np.array([0.0, 1.0, 0.5, 2.0, 3.0]), np.ones((5, 3)), {}, "strictly increasing"),
        (np.arange(5.0), np.ones((5, 2)), {}, r"shape \(T, 3\)"),
        (np.arange(5.0), np.ones((4, 3)), {}, r"shape \(T, 3\)"),
        (np.array([0.0, 1.0, np.nan, 3.0, 4.0]), np.ones((5, 3)), {}, "NaN or inf"),
        (np.arange(5.0), np.full((5, 3), np.inf), {}, "inf"),
        (np.arange(2.0), np.ones((2, 3)), {}, "Too few samples"),
        (np.arange(40.0), np.ones((40, 3)), {"segments": 30}, "segments=30 is too many for 40 samples"),
        (np.arange(40.0), np.ones((40, 3)), {"loss": "l1"}, "loss must be one of"),
        (np.arange(40.0), np.ones((40, 3)), {"method": "newton"}, "method must be one of"),
        (np.arange(40.0), np.ones((40, 3)), {"segments": 0}, "positive integer"),
        (np.arange(40.0), np.ones((40, 3)), {"inertia_init": np.ones(4)}, "inertia_init must have"),
        (np.arange(40.0), np.ones((40, 3)), {"inertia_trace": 1.0, "known_moment": (0, 1.0)}, "at most one"),
    ],
)
def test_bad_input_is_named(ts, omega, kwargs, match):
    with pytest.raises(ValueError, match=match):
        fit_inertia(ts, omega, **kwargs)


@pytest.mark.slow
def test_omega_from_orientations_converges_at_second_order():
    """Central differences of closed-form orientations against the closed-form omega: the error falls
    4x per halving of the sample spacing, and flipping quaternion signs changes nothing."""
    q0 = np.asarray(rj.quat_from_euler(np.array([0.3, 1.0, -0.5])))
    even = [np.linspace(0.0, 8.0, n) for n in (201, 401)]
    # Also where the spacing alternates h, 2h (the difference over two steps was first order there).
    uneven = [np.cumsum(np.r_[0.0, np.resize([1.0, 2.0], n - 1)]) * 8.0 / (1.5 * (n - 1)) for n in (41, 81)]
    # The closed form at all four grids in one call (one compiled program instead of four), the 724
    # times padded (with the last one) to the lengths of the noise-estimate tests' records, 960
    # orientations and 2400 angular velocities, whose compiled closed forms serve here.
    grids = even + uneven
    every = np.concatenate(grids)

    def padded(n):
        return np.concatenate([every, np.full(n - every.size, every[-1])])

    q_all = np.asarray(rj.torque_free_motion(I_TRUE, W0_TRUE, q0, padded(960))[1])[: every.size]
    exact_all = np.asarray(rj.torque_free_omega(I_TRUE, W0_TRUE, padded(2400)))[: every.size]
    starts = np.cumsum([0] + [ts.size for ts in grids])
    errors = []
    for i, ts in enumerate(grids):
        q = q_all[starts[i] : starts[i + 1]].copy()
        exact = exact_all[starts[i] : starts[i + 1]]
        estimate = rj.omega_from_orientations(ts, q)
        errors.append(np.max(np.abs(estimate[1:-1] - exact[1:-1])))
        q[::3] *= -1.0
        np.testing.assert_allclose(rj.omega_from_orientations(ts, q), estimate, rtol=0, atol=1e-12)
    assert 3.5 < errors[0] / errors[1] < 4.5, errors
    assert 3.5 < errors[2] / errors[3] < 4.5, errors


def test_omega_from_orientations_of_a_fast_spin():
    """A spin of 2 rad per sample (under pi per step): the log over two steps (4 rad, beyond pi)
    aliased it to -11.4 rad/s at every interior sample. Reference: the uniform spin itself."""
    ts = np.arange(6) * 0.1
    q = np.stack([np.cos(10.0 * ts), 0 * ts, 0 * ts, np.sin(10.0 * ts)], axis=1)  # 20 rad/s about z
    np.testing.assert_allclose(
        rj.omega_from_orientations(ts, q), np.tile([0.0, 0.0, 20.0], (6, 1)), atol=1e-12
    )


@pytest.mark.slow
def test_a_diverging_optimiser_is_an_error_that_says_so():
    """An optax step far too long sends the parameters to inf/NaN: the fit raises a
    FloatingPointError naming the optimiser and what to try (before, the closed form's value check
    fired inside the compiled fit with "inertia has a non-positive principal moment")."""
    ts = np.linspace(0.0, 20.0, 60)
    w = np.asarray(rj.torque_free_omega(np.array([1.0, 2.0, 2.7]), np.array([0.3, 1.0, 0.2]), ts))
    with pytest.raises(FloatingPointError, match="optax optimiser diverged.*levenberg-marquardt"):
        rj.fit_inertia(ts, w, method="optax", optimizer=optax.sgd(1e3), steps=50)


@pytest.mark.slow
def test_a_known_torque_that_cannot_be_integrated_is_an_error_that_says_so():
    """A record of 2e4 s (~30,000 turns) needs far more than the fit's 200,000 integration steps per
    window: the loss at the start is inf, Levenberg–Marquardt stops at once, and the fit raises a
    FloatingPointError saying the motion could not be integrated and what to do (segments)."""
    inertia = np.array([0.02, 0.04, 0.05])
    ts = np.linspace(0.0, 2e4, 240)
    w = np.asarray(rj.torque_free_omega(jnp.asarray(inertia), jnp.array([3.0, 0.5, 10.0]), jnp.asarray(ts)))
    torque = rj.ConstantTorque(jnp.array([2e-9, -1e-9, 3e-9]))
    with pytest.raises(FloatingPointError, match="could not be integrated.*segments"):
        fit_inertia(ts, w, torque=torque, method="levenberg-marquardt", inertia_init=jnp.asarray(inertia))


def test_a_float32_fit_of_a_record_in_clock_time_predicts_at_its_own_times():
    """Times 1.7e9 s since 1970 (float32's spacing there is 128 s): the fit subtracted each window's
    start on the host, but the predictions subtracted it in float32, every time collapsed onto one
    and predict_omega was off by ~2 rad/s. Record: scipy's DOP853 (rtol 1e-12) of Euler's equations."""
    elapsed = np.linspace(0.0, 10.0, 240)
    observed, clock = scipy_omega(I_TRUE, [0.3, 1.0, 0.4], elapsed), 1.7e9 + 37.3 + elapsed
    fit = fit_inertia(clock, observed, method="levenberg-marquardt", dtype=jnp.float32)
    np.testing.assert_allclose(fit.inertia, TRUTH, atol=1e-5)
    assert fit.segment_starts.dtype == np.float64 and fit.segment_starts[0] == clock[0]
    np.testing.assert_allclose(fit.predict_omega(clock), observed, atol=2e-5)
    np.testing.assert_allclose(fit.predict_omega(clock[120]), observed[120], atol=2e-5)
    np.testing.assert_allclose(jax.jit(fit.predict_omega.__func__)(fit, clock), observed, atol=2e-5)
    for ts, error, match in (
        ("noon", TypeError, "ts must be a real number"),
        (clock[:2] * 1j, TypeError, "ts must be real"),
        (clock[None, :2], ValueError, r"ts must be times \(s\), \(T,\) or a number, got shape \(1, 2\)"),
        (np.array([clock[0], np.nan]), ValueError, "ts must be finite"),
    ):
        with pytest.raises(error, match=match):
            fit.predict_omega(ts)
    for dtype, match in ((jnp.float16, "float32 or float64"), (np.int32, "float32 or float64")):
        with pytest.raises(ValueError, match=match):
            fit_inertia(clock, observed, dtype=dtype)
    with jax.enable_x64(False), pytest.raises(ValueError, match="float64 needs JAX's 64-bit mode"):
        fit_inertia(clock, observed, dtype=np.float64)


def test_a_tennis_racket_record_of_two_flips_is_fitted_from_the_default_start():
    """Near the intermediate axis the flips last a fraction of the wobble period; the starting
    estimate's local fits spanned 1/16 of that period and smoothed the flips into a start of
    (0.1846, 0.3261, 0.4894) from which the fit ended on the flat-plate edge (0.049, 0.451, 0.5)
    with residuals 100x the noise. Record: scipy's DOP853 (rtol 1e-12) of Euler's equations,
    I = (1, 2, 3), two flips in 40 s."""
    inertia, ts = np.array([1.0, 2.0, 3.0]), np.linspace(0.0, 40.0, 400)
    exact = scipy_omega(inertia, [0.01, 1.0, 0.01], ts)
    assert np.sum(np.diff(np.sign(exact[:, 1])) != 0) == 2  # two flips
    observed = exact + 0.005 * np.random.default_rng(0).standard_normal((ts.size, 3))
    start, _ = estimate_inertia(ts, observed)
    np.testing.assert_allclose(start, inertia / 6.0, atol=0.006)
    fit = fit_inertia(ts, observed, method="levenberg-marquardt", segments="auto")
    z = (np.asarray(fit.inertia) - inertia / 6.0) / np.asarray(fit.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), (fit.inertia, z)
    assert np.all(np.asarray(fit.residual_rms / fit.noise_estimate) < 1.3)


def test_a_noisy_gyro_record_is_fitted_from_the_default_start():
    """Gyro noise 0.2 rad/s on a wobble of 0.3 rad/s: the estimated start lay by the flat-body edge
    ((0.498, 0.356, 0.146) for I = (1, 2, 2.5) / 5.5) and Levenberg–Marquardt ended on it at
    (0.5, 0.306, 0.194), "converged", with a standard error of 2e-18 on I_x; a rough start
    (1, 1.5, 2) reaches the optimum at half the loss. Record: scipy's DOP853 (rtol 1e-12)."""
    inertia, ts = np.array([1.0, 2.0, 2.5]), np.linspace(0.0, 8.0, 240)
    observed = scipy_omega(inertia, [0.3, 0.1, 2.0], ts) + 0.2 * np.random.default_rng(3).normal(
        size=(240, 3)
    )
    fit = fit_inertia(ts, observed, method="levenberg-marquardt")
    rough = fit_inertia(ts, observed, method="levenberg-marquardt", inertia_init=[1.0, 1.5, 2.0])
    np.testing.assert_allclose(float(fit.loss), float(rough.loss), rtol=1e-9)
    stderr = np.asarray(fit.inertia_stderr)
    assert np.all(stderr > 1e-3), stderr  # a 0.2 rad/s noise leaves percent-level errors
    z = (np.asarray(fit.inertia) - inertia / inertia.sum()) / stderr
    assert np.all(np.abs(z) < 4.0), (fit.inertia, z)


@pytest.mark.slow
def test_a_motion_capture_record_is_fitted_from_the_default_start():
    """1 mrad noise on 240 orientations over 8 s: the angular velocity differentiated from them is
    0.1 rad/s off, the estimated start ordered the moments wrongly ((0.203, 0.498, 0.299) for
    (0.182, 0.364, 0.455)) and the fit ended on the flat-body edge (0.5, 0, 0.5) with NaN standard
    errors (Levenberg–Marquardt) or at (4e-10, 0.5, 0.5), "converged", with residuals 1000 times
    the noise (the default optimiser)."""
    inertia, ts = np.array([1.0, 2.0, 2.5]), np.linspace(0.0, 8.0, 240)
    q0 = np.asarray(rj.quat_from_euler(np.array([0.3, 0.7, -0.2])))
    q = rj.torque_free_motion(inertia, np.array([0.3, 0.1, 2.0]), q0, ts)[1]
    rng = np.random.default_rng(6)
    q = perturbed(q, 1e-3 * rng.normal(size=(240, 3)))
    q = np.asarray(q) * rng.choice([-1.0, 1.0], size=(240, 1))
    for method in ("levenberg-marquardt", None):
        fit = fit_inertia_to_orientation(ts, q, method=method)
        z = (np.asarray(fit.inertia) - inertia / inertia.sum()) / np.asarray(fit.inertia_stderr)
        assert np.all(np.abs(z) < 4.0), (method, fit.inertia, z)
        assert np.all(np.asarray(fit.residual_rms / fit.noise_estimate) < 1.5), method


def test_a_few_outliers_in_a_squared_fit_start_no_restarts(monkeypatch):
    """Five gross outliers (1 rad/s) among 720 values raise a squared fit's rms above twice the
    noise estimate, but its median residual stays at the noise: the fit is in the right basin, and
    fitting again from six other starts (seven times the work) cannot lower residuals that the
    outliers set. Record: scipy's DOP853 (rtol 1e-12) with 1 % noise."""
    import rigidjax._fit.fit as fit_module

    inertia, ts = np.array([1.0, 2.0, 2.5]), np.linspace(0.0, 8.0, 240)
    rng = np.random.default_rng(8)
    observed = scipy_omega(inertia, [0.3, 0.1, 2.0], ts) + 0.01 * rng.normal(size=(240, 3))
    observed[rng.choice(240, 5, replace=False), 0] += 1.0
    runs = []
    run = fit_module._run
    monkeypatch.setattr(fit_module, "_run", lambda *args: runs.append(1) or run(*args))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nor a warning of residuals above the noise
        fit = fit_inertia(ts, observed, method="levenberg-marquardt")
    assert np.max(np.asarray(fit.residual_rms / fit.noise_estimate)) > 2.0  # the plain rms
    assert len(runs) == 1
    z = (np.asarray(fit.inertia) - inertia / inertia.sum()) / np.asarray(fit.inertia_stderr)
    assert np.all(np.abs(z) < 4.0), (fit.inertia, z)
