"""The default fit's strong-Wolfe line search, driven by hand on one-dimensional functions whose
values and slopes are written out here in numpy: every accepted step is checked against the Wolfe
conditions themselves (Nocedal and Wright, eq. 3.7), and the default fit's optimum against
scipy.optimize.least_squares on the same record."""

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import rigidjax as rj
from rigidjax._fit.linesearch import CURVATURE, MAX_TRIES, SUFFICIENT_DECREASE, wolfe_advance, wolfe_start


def search(phi, t0=1.0):
    """Runs the search on ``phi(t) -> (value, slope)``; returns the stepsizes tried and the final
    state."""
    value0, slope0 = phi(0.0)
    state = wolfe_start(jnp.float64(value0), jnp.float64(slope0), t0)
    tried = []
    while not (bool(state.accepted) or bool(state.failed)):
        t = float(state.stepsize)
        tried.append(t)
        state = wolfe_advance(state, *(jnp.float64(x) for x in phi(t)))
        assert len(tried) <= MAX_TRIES + 1
    return tried, state


def quadratic(t):
    return (t - 2.0) ** 2, 2.0 * (t - 2.0)


def steep_wall(t):  # a minimum at t = 0.01 behind a wall of 1e6 t^2: L-BFGS's first step, overshooting
    return 1e6 * (t - 0.01) ** 2, 2e6 * (t - 0.01)


def slow_descent(t):  # the minimum at t = 50: the search expands
    return (t - 50.0) ** 2 / 100.0, (t - 50.0) / 50.0


def rosenbrock_line(t):  # Rosenbrock's function from (-1.2, 1) along its steepest descent
    x0, d = np.array([-1.2, 1.0]), np.array([215.6, 88.0]) / np.hypot(215.6, 88.0)
    x, y = x0 + t * d

    def grad(x, y):
        return np.array([-2 * (1 - x) - 400 * x * (y - x * x), 200 * (y - x * x)])

    return (1 - x) ** 2 + 100 * (y - x * x) ** 2, float(grad(x, y) @ d)


def nan_beyond(t):  # the model cannot be evaluated past t = 0.3 (an integration that fails)
    if t > 0.3:
        return np.nan, np.nan
    return quadratic(t)


@pytest.mark.parametrize("phi", [quadratic, steep_wall, slow_descent, rosenbrock_line, nan_beyond])
def test_accepted_step_meets_the_strong_wolfe_conditions(phi):
    tried, state = search(phi)
    assert bool(state.accepted) and not bool(state.failed)
    t = tried[-1]
    value0, slope0 = phi(0.0)
    value, slope = phi(t)
    assert value <= value0 + SUFFICIENT_DECREASE * t * slope0
    assert abs(slope) <= CURVATURE * abs(slope0)


def test_a_quadratic_is_bracketed_once_and_solved_by_its_cubic():
    """From t = 5 (past the minimum at 2, where the loss is above the start's) the bracket [0, 5]
    holds the data of a quadratic, which the interpolating cubic reproduces: the second trial is
    t = 2."""
    tried, state = search(quadratic, t0=5.0)
    assert tried[0] == 5.0
    assert tried[1] == pytest.approx(2.0, rel=1e-14)
    assert len(tried) == 2 and bool(state.accepted)


def test_expansion_reaches_a_distant_minimum():
    """The slope stays steeper than the curvature condition allows up to t = 3: the search triples
    the step until it is met (at t = 9: slope -0.82 against -1 at the start)."""
    tried, state = search(slow_descent, t0=1.0)
    assert bool(state.accepted)
    assert tried == [1.0, 3.0, 9.0]


def test_a_direction_with_no_finite_trial_fails():
    """Every trial NaN: the search halves towards zero, finds no lower point and says so."""
    tried, state = search(lambda t: (1.0, -1.0) if t == 0.0 else (np.nan, np.nan))
    assert bool(state.failed) and not bool(state.accepted)
    assert len(tried) == MAX_TRIES


def test_roundoff_flat_loss_takes_the_approximate_conditions():
    """At a minimum the loss changes by roundoff only (here 1e-20 on 4e-6, below the sufficient
    decrease's resolution) while the slope still shows where the minimum lies: Hager and Zhang's
    approximate Wolfe conditions accept the step instead of shrinking it to nothing."""
    v0, s0 = 3.8288467375777e-6, -6.5e-21

    def flat(t):
        return v0 + 1e-20 * np.sin(7.0 * t), s0 * (1.0 - t)

    tried, state = search(flat)
    assert bool(state.accepted)
    assert len(tried) <= 2


@pytest.mark.slow
def test_default_fit_reaches_scipys_least_squares_optimum():
    """Equal noise on every axis makes the fit's loss the plain sum of squares: the default fit
    (L-BFGS with this line search) and scipy.optimize.least_squares (trust-region reflective, its own
    central-difference Jacobian) on the same residuals reach the same inertia and omega0."""
    inertia_true, omega0_true = np.array([1.0, 2.0, 2.5]), np.array([0.3, 0.05, 1.0])
    period = float(rj.torque_free_period(inertia_true, omega0_true))
    ts = np.linspace(0.0, 4.0 * period, 240)
    rng = np.random.default_rng(7)
    observed = np.asarray(rj.torque_free_omega(inertia_true, omega0_true, ts))
    observed = observed + 0.005 * rng.standard_normal(observed.shape)
    fit = rj.fit_inertia(ts, observed, noise=0.005)
    assert bool(fit.converged)

    def residuals(x):
        inertia = np.array([x[0], x[1], 1.0 - x[0] - x[1]])
        return (np.asarray(rj.torque_free_omega(inertia, x[2:], ts)) - observed).ravel()

    start = np.concatenate([inertia_true[:2] / inertia_true.sum(), omega0_true])
    theirs = scipy.optimize.least_squares(residuals, start, jac="3-point", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert theirs.success
    # The two optima agree to 3e-8 (scipy's finite differences), 1e-5 of a standard error.
    np.testing.assert_allclose(fit.inertia[:2], theirs.x[:2], rtol=1e-7)
    np.testing.assert_allclose(fit.omega0, theirs.x[2:], rtol=0, atol=1e-8)
    np.testing.assert_allclose(float(fit.loss) * observed.size, 2.0 * theirs.cost, rtol=1e-9)
