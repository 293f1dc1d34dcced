"""Stability of steady spin (tennis-racket theorem) and of the sleeping top, checked by simulation.

The references are independent of rigidjax._stability: rigidjax.simulate of the full nonlinear
motion started next to the steady spin, with growth rates and frequencies fitted from the simulated
samples (a straight line through log|perturbation|; linear prediction / Prony fits of the sampled
oscillation); numpy eigenvalues of a hand-written Jacobian of Euler's equations; numpy roots of the
characteristic polynomial; central finite differences.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import box_moments, central_difference, euler_rhs, expect_error

import rigidjax as rj
from rigidjax import SleepingTop, SpinStability, sleeping_top, spin_stability

G = 9.81
# Jitted once per input signature: the many small calls below would otherwise run op by op.
SPIN = jax.jit(spin_stability)
TOP = jax.jit(sleeping_top, static_argnames="symmetry_rtol")


# ----------------------------------------------------------------------------------------------
# Independent numpy references
# ----------------------------------------------------------------------------------------------


def transverse_jacobian(inertia, axis, omega):
    """Jacobian of Euler's equations at steady spin ``omega`` about ``axis``, restricted to the two
    transverse components (central differences of the exactly quadratic right-hand side)."""
    others = [a for a in range(3) if a != axis]
    w0 = omega * np.eye(3)[axis]
    jac = np.zeros((3, 3))
    for c in range(3):
        step = np.eye(3)[c] * 1e-3 * max(abs(omega), 1.0)
        jac[:, c] = (euler_rhs(inertia, w0 + step) - euler_rhs(inertia, w0 - step)) / (2 * step[c])
    return jac[np.ix_(others, others)], others


def fit_frequency(x, dt, offset=False):
    """Angular frequency of sampled sinusoids ``x (T, ...)`` by linear prediction:
    ``x[n+1] + x[n-1] = 2 cos(nu dt) x[n]`` holds exactly for any amplitude and phase (plus a
    constant ``2 (1 - cos(nu dt)) a`` for a sinusoid about an offset ``a``, fitted with ``offset``)."""
    mid, around = x[1:-1].reshape(len(x) - 2, -1), (x[2:] + x[:-2]).reshape(len(x) - 2, -1)
    columns = [2.0 * mid.ravel()] + ([np.ones(mid.size)] if offset else [])
    coef, *_ = np.linalg.lstsq(np.stack(columns, axis=1), around.ravel(), rcond=None)
    return np.arccos(coef[0]) / dt


def prony2(z, dt):
    """Exponents ``s`` of a two-mode complex signal ``z = A exp(s1 t) + B exp(s2 t)`` (Prony's method:
    ``z[n+2] = a z[n+1] + b z[n]``, roots of ``r^2 - a r - b``), sorted by |Im s|."""
    design = np.stack([z[1:-1], z[:-2]], axis=1)
    (a, b), *_ = np.linalg.lstsq(design, z[2:], rcond=None)
    s = np.log(np.roots([1.0, -a, -b])) / dt
    return s[np.argsort(np.abs(s.imag))]


def symmetry_axis_space(q):
    """Space-frame components of the body z axis, the third column of R(q), from the quaternion."""
    w, x, y, z = np.moveaxis(np.asarray(q), -1, 0)
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=-1)


# ----------------------------------------------------------------------------------------------
# Torque-free spin about each principal axis, simulated
# ----------------------------------------------------------------------------------------------

# Asymmetric bodies; the last has its intermediate moment on axis 3 (moments not sorted).
BODIES = np.array([[1.0, 2.0, 3.0], [2.0, 2.5, 4.0], [0.6, 1.5, 1.2]])
# Target |lambda| (1/s or rad/s) per body; the spin rate is set from the numpy Jacobian to reach it.
TARGET_RATE = np.array([1.0, 1.2, 0.9])
SPIN_TS = np.linspace(0.0, 16.0, 321)
PERTURBATION = 1e-8  # relative to Omega


@pytest.fixture(scope="module")
def spin_runs():
    """One batched simulation: each body spun about each principal axis (9 runs, one compile).

    Unstable axis: the perturbation is along the growing eigenvector of the linearised equations
    (numpy), so the decaying mode is absent and log|dw| is a straight line from the start. Stable
    axes: one transverse component is perturbed."""
    inertia, omega0, runs = [], [], []
    for body, rate in zip(BODIES, TARGET_RATE, strict=True):
        for axis in range(3):
            jac, others = transverse_jacobian(body, axis, 1.0)  # eigenvalues scale with Omega
            vals, vecs = np.linalg.eig(jac)
            spin = rate / np.max(np.abs(vals))
            w0 = spin * np.eye(3)[axis]
            if np.max(vals.real) > 1e-9:
                v = np.real(vecs[:, np.argmax(vals.real)])
                w0[others] += PERTURBATION * spin * v / np.linalg.norm(v)
            else:
                w0[others[0]] += PERTURBATION * spin
            inertia.append(body)
            omega0.append(w0)
            runs.append((axis, others, spin))
    traj = rj.simulate(
        rj.FreeBody(jnp.asarray(np.array(inertia))),
        rj.State(jnp.asarray(np.array(omega0))),
        jnp.asarray(SPIN_TS),
        accuracy="precise",
    )
    omega = np.asarray(traj.omega)
    predicted = spin_stability(
        jnp.asarray(np.array(inertia)), jnp.asarray(np.array([spin for _, _, spin in runs]))
    )
    return omega, runs, predicted


@pytest.mark.slow
def test_intermediate_axis_growth_rate_matches_simulation(spin_runs):
    """Fit log|dw| against t where |dw| is between 1e-7 and 1e-3 of Omega (linear regime, past the
    start) and compare the slope with the predicted growth rate (measured agreement ~1e-8)."""
    omega, runs, predicted = spin_runs
    n_unstable = 0
    for n, (axis, others, spin) in enumerate(runs):
        if not bool(predicted.unstable[n, axis]):
            continue
        n_unstable += 1
        assert BODIES[n // 3, axis] == np.median(BODIES[n // 3])  # the intermediate moment
        dw = np.linalg.norm(omega[n][:, others], axis=-1) / spin
        window = (dw > 1e-7) & (dw < 1e-3)
        assert window.sum() > 100
        slope = np.polyfit(SPIN_TS[window], np.log(dw[window]), 1)[0]
        np.testing.assert_allclose(slope, predicted.growth_rate[n, axis], rtol=1e-5)
        assert float(predicted.frequency[n, axis]) == 0.0
        assert dw[-1] > 1e-2  # and it really left the axis (the racket flips)
    assert n_unstable == len(BODIES)


@pytest.mark.slow
def test_stable_axes_frequency_matches_simulation(spin_runs):
    """The transverse components circle the largest and smallest axes at the predicted body-frame
    frequency (fitted by linear prediction; measured agreement ~1e-13) and stay small."""
    omega, runs, predicted = spin_runs
    dt = SPIN_TS[1] - SPIN_TS[0]
    n_stable = 0
    for n, (axis, others, spin) in enumerate(runs):
        if not bool(predicted.stable[n, axis]):
            continue
        n_stable += 1
        transverse = omega[n][:, others] / spin
        assert np.max(np.abs(transverse)) < 1e2 * PERTURBATION
        np.testing.assert_allclose(fit_frequency(transverse, dt), predicted.frequency[n, axis], rtol=1e-8)
        assert float(predicted.growth_rate[n, axis]) == 0.0
    assert n_stable == 2 * len(BODIES)


# ----------------------------------------------------------------------------------------------
# spin_stability: formula checks, edge cases, gradients, batches, errors
# ----------------------------------------------------------------------------------------------


def test_spin_stability_matches_jacobian_eigenvalues():
    """Random physical bodies (any moment order), random spin rates: growth rate and frequency equal
    the real and imaginary parts of the numpy eigenvalues of the linearised Euler equations."""
    rng = np.random.default_rng(3)
    inertia = box_moments(rng.uniform(0.2, 2.0, (20, 3)))
    spin = rng.uniform(-5.0, 5.0, 20)
    result = SPIN(jnp.asarray(inertia), jnp.asarray(spin))
    assert isinstance(result, SpinStability)
    for n in range(20):
        for axis in range(3):
            vals = np.linalg.eigvals(transverse_jacobian(inertia[n], axis, spin[n])[0])
            np.testing.assert_allclose(result.growth_rate[n, axis], np.max(vals.real), atol=1e-9)
            np.testing.assert_allclose(result.frequency[n, axis], np.max(vals.imag), atol=1e-9)
    # Exactly one unstable axis per asymmetric body: the intermediate one.
    np.testing.assert_array_equal(result.unstable, inertia == np.median(inertia, axis=-1, keepdims=True))
    np.testing.assert_array_equal(result.stable, ~result.unstable)
    assert not np.any(result.marginal)


# d(growth_rate, frequency)/d(inertia, omega): one compile for all the edge cases below.
SPIN_RATES_GRAD = jax.jit(
    jax.jacrev(lambda I, w: jnp.stack([SPIN(I, w).growth_rate, SPIN(I, w).frequency]), argnums=(0, 1))
)


def test_symmetric_top_and_sphere_without_nan():
    """I1 = I2: the odd axis oscillates at the free precession rate; axes in the degenerate plane are
    marginal (lambda = 0). A sphere, and zero spin, are marginal about every axis. Values and
    gradients are finite."""
    spin = jnp.asarray(3.0)
    for inertia in ([1.0, 1.0, 1.6], [1.6, 1.0, 1.0], [0.7, 1.0, 0.7]):
        inertia = jnp.asarray(inertia)
        odd = int(np.argmax(np.asarray(inertia) != np.median(np.asarray(inertia))))
        I_t, I_odd = float(np.median(np.asarray(inertia))), inertia[odd]
        result = SPIN(inertia, spin)
        expected = abs(float(rj.free_precession_rate(jnp.asarray(I_t), I_odd, spin)))
        np.testing.assert_allclose(result.frequency[odd], expected, rtol=1e-14)
        plane = [a for a in range(3) if a != odd]
        np.testing.assert_array_equal(result.marginal, np.arange(3) != odd)
        assert bool(result.stable[odd]) and not np.any(np.asarray(result.stable)[plane])
        np.testing.assert_array_equal(np.asarray(result.growth_rate), 0.0)
        np.testing.assert_array_equal(np.asarray(result.frequency)[plane], 0.0)
        assert all(np.all(np.isfinite(g)) for g in SPIN_RATES_GRAD(inertia, spin))
    for inertia, w in (([2.0, 2.0, 2.0], 3.0), ([1.0, 2.0, 2.5], 0.0)):
        result = SPIN(jnp.asarray(inertia), jnp.asarray(w))
        assert np.all(result.marginal) and not np.any(result.stable) and not np.any(result.unstable)
        np.testing.assert_array_equal(np.asarray(result.growth_rate), 0.0)
        assert all(np.all(np.isfinite(g)) for g in SPIN_RATES_GRAD(jnp.asarray(inertia), jnp.asarray(w)))


@pytest.mark.parametrize("field,axis", [("growth_rate", 1), ("frequency", 0), ("frequency", 2)])
def test_spin_stability_gradient_matches_finite_differences(field, axis):
    inertia, spin = np.array([1.0, 1.7, 2.2]), 2.5

    def value(I, w=None):
        return getattr(SPIN(I, jnp.asarray(spin) if w is None else w), field)[axis]

    grad = jax.grad(value)(jnp.asarray(inertia))
    np.testing.assert_allclose(grad, central_difference(value, inertia, 1e-6), rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(jax.jacfwd(value)(jnp.asarray(inertia)), grad, rtol=1e-12)
    d_spin = jax.grad(lambda w: value(jnp.asarray(inertia), w))(jnp.asarray(spin))
    np.testing.assert_allclose(d_spin, float(value(jnp.asarray(inertia))) / spin, rtol=1e-12)


def test_an_angular_velocity_vector_is_not_read_as_three_spin_rates():
    """``spin_stability(I, omega)`` with a body's angular velocity vector gave a (3, 3) result, each
    component read as a spin rate of its own, without a word. Reference: the intermediate axis's
    growth rate ``Omega sqrt((I2 - I3)(I1 - I2) / (I3 I1))`` at the rate ``|omega|``."""
    inertia, omega = jnp.asarray([1.0, 2.0, 2.5]), jnp.asarray([0.1, 3.0, 0.2])
    for bad in (omega, jnp.stack([omega, 2 * omega])):
        for call in (spin_stability, jax.jit(spin_stability)):
            with pytest.raises(ValueError, match=r"omega_magnitude has shape .*norm\(omega, axis=-1\)"):
                call(inertia, bad)
    rate = float(np.linalg.norm(omega))
    expected = np.sqrt((2.0 - 2.5) * (1.0 - 2.0) / (2.5 * 1.0))
    np.testing.assert_allclose(spin_stability(inertia, rate).growth_rate[1], rate * expected, rtol=1e-14)
    rates = jnp.asarray([1.0, 2.0, 3.0])
    three = spin_stability(inertia[None], rates)
    assert three.growth_rate.shape == (3, 3)
    np.testing.assert_allclose(three.growth_rate[:, 1], rates * expected, rtol=1e-14)


def test_a_top_s_angular_velocity_vector_is_not_read_as_three_spins():
    """``sleeping_top`` takes the spin about the symmetry axis; the vector (0, 0, 30) gave three
    tops' results, two of them spinning at 0, without a word. Reference: the critical spin
    ``2 sqrt(m g l I1) / I3`` of the one top."""
    inertia, com = jnp.asarray([1.0, 1.0, 0.5]), jnp.asarray([0.0, 0.0, 0.1])
    with pytest.raises(ValueError, match=r"omega3 has shape \(3,\) .*pass omega\[\.\.\., 2\]"):
        sleeping_top(inertia, 2.0, com, jnp.asarray([0.0, 0.0, 30.0]))
    spins = jnp.asarray([10.0, 20.0, 30.0])
    three = sleeping_top(inertia[None], 2.0, com[None], spins)
    critical = 2.0 * np.sqrt(2.0 * 9.81 * 0.1 * 1.0) / 0.5
    np.testing.assert_allclose(three.critical_spin, critical, rtol=1e-12)
    np.testing.assert_array_equal(three.stable, np.asarray(spins) > critical)


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2, 1)])
def test_spin_stability_batch_shapes(shape):
    rng = np.random.default_rng(5)
    inertia = box_moments(rng.uniform(0.2, 2.0, shape + (3,)))
    spin = rng.uniform(0.5, 4.0, (4,) + (1,) * len(shape))  # broadcasts to (4, *shape)
    result = spin_stability(jnp.asarray(inertia), jnp.asarray(spin))
    full = (4,) + shape
    for field in ("growth_rate", "frequency", "stable", "marginal"):
        assert getattr(result, field).shape == full + (3,)
    flat_inertia = np.broadcast_to(inertia, full + (3,)).reshape(-1, 3)
    flat_spin = np.broadcast_to(spin, full).reshape(-1)
    for n in range(flat_spin.size):
        one = SPIN(jnp.asarray(flat_inertia[n]), jnp.asarray(flat_spin[n]))
        np.testing.assert_array_equal(np.asarray(result.growth_rate).reshape(-1, 3)[n], one.growth_rate)
        np.testing.assert_array_equal(np.asarray(result.frequency).reshape(-1, 3)[n], one.frequency)
    jitted = jax.jit(spin_stability)(jnp.asarray(inertia), jnp.asarray(spin))
    np.testing.assert_allclose(jitted.growth_rate, result.growth_rate, rtol=1e-15)


def test_spin_stability_vmap_and_float32():
    inertia = jnp.asarray([[1.0, 2.0, 3.0], [3.0, 1.0, 2.5]])
    spin = jnp.asarray([1.0, 2.0])
    mapped = jax.jit(jax.vmap(spin_stability))(inertia, spin)
    direct = SPIN(inertia, spin)
    np.testing.assert_allclose(mapped.frequency, direct.frequency, rtol=1e-15)
    single = SPIN(inertia.astype(jnp.float32), spin.astype(jnp.float32))
    assert single.growth_rate.dtype == jnp.float32
    np.testing.assert_allclose(single.growth_rate, direct.growth_rate, rtol=1e-6)


def test_spin_stability_bad_input(without_runtime_typecheck):
    with pytest.raises(ValueError, match="principal_axes"):
        spin_stability(jnp.eye(3), jnp.asarray(1.0))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        spin_stability(jnp.ones(4), jnp.asarray(1.0))
    expect_error(lambda: spin_stability(jnp.asarray([1.0, 1.0, 3.0]), jnp.asarray(1.0)), "triangle")
    expect_error(lambda: spin_stability(jnp.asarray([-1.0, 1.0, 1.5]), jnp.asarray(1.0)), "non-positive")
    expect_error(
        lambda: jax.jit(spin_stability)(jnp.asarray([1.0, 1.0, 3.0]), jnp.asarray(1.0)).growth_rate,
        "triangle",
    )


def test_spin_stability_bad_shape_under_typecheck():
    with pytest.raises((ValueError, TypeError)):
        spin_stability(jnp.ones(4), jnp.asarray(1.0))


# ----------------------------------------------------------------------------------------------
# The sleeping top, simulated
# ----------------------------------------------------------------------------------------------

# (I1 = I2, I3) about the pivot, mass, l: a tall top (I3 < I1) and a squat one (I3 > I1).
TOPS = [((4e-4, 4e-4, 2e-4), 0.1, 0.04), ((2.5e-4, 2.5e-4, 3e-4), 0.08, 0.03)]
SPIN_FACTORS = (1.5, 0.5)  # times the critical spin, computed here from the textbook criterion
THETA0 = 1e-4
TOP_TS = np.linspace(0.0, 2.0, 401)


@pytest.fixture(scope="module")
def top_runs():
    """Each top released at rest at tilt THETA0, spinning above and below its critical spin (one
    batched simulation). Returns the space-frame tilt X + iY of the symmetry axis, the tilt angle,
    and the predictions."""
    inertia, mass, com, spin = [], [], [], []
    for moments, m, l in TOPS:
        critical = 2.0 * np.sqrt(moments[0] * m * G * l) / moments[2]
        for factor in SPIN_FACTORS:
            inertia.append(moments)
            mass.append(m)
            com.append((0.0, 0.0, l))
            spin.append(factor * critical)
    inertia, mass, com, spin = (jnp.asarray(np.array(a)) for a in (inertia, mass, com, spin))
    omega0 = jnp.zeros((len(spin), 3)).at[:, 2].set(spin)
    q0 = jnp.broadcast_to(rj.quat_from_euler(jnp.asarray([0.0, THETA0, 0.0])), (len(spin), 4))
    traj = rj.simulate(
        rj.HeavyTop(inertia, mass, com, jnp.asarray(G)),
        rj.State(omega0, q0),
        jnp.asarray(TOP_TS),
        accuracy="precise",
    )
    axis = symmetry_axis_space(traj.orientation)
    xi = axis[..., 0] + 1j * axis[..., 1]
    theta = np.arctan2(np.abs(xi), axis[..., 2])
    predicted = sleeping_top(inertia, mass, com, spin, jnp.asarray(G))
    return xi, theta, predicted


@pytest.mark.slow
def test_sleeping_top_above_critical_spin_matches_simulation(top_runs):
    """Above w_crit the tilt is the sum of two circular modes exp(i lambda t); Prony's fit of the
    simulated tilt gives both roots of I1 lambda^2 - I3 w3 lambda + m g l = 0 (measured agreement
    ~3e-9), with no growth, and theta stays within the predicted band [theta0, theta0 (fast + slow) /
    (fast - slow)]: its nutation frequency is fast - slow."""
    xi, theta, predicted = top_runs
    dt = TOP_TS[1] - TOP_TS[0]
    for n in (0, 2):
        assert bool(predicted.stable[n]) and float(predicted.margin[n]) > 0
        slow, fast = float(predicted.slow_rate[n]), float(predicted.fast_rate[n])
        s = prony2(xi[n], dt)
        np.testing.assert_allclose(s.imag, [slow, fast], rtol=1e-7)
        np.testing.assert_allclose(s.real, 0.0, atol=1e-7 * fast)
        assert float(predicted.growth_rate[n]) == 0.0
        band = THETA0 * (fast + slow) / (fast - slow)
        assert np.max(theta[n]) <= band * (1 + 1e-6) and np.max(theta[n]) > band * (1 - 1e-3)
        assert np.min(theta[n]) > THETA0 * (1 - 1e-6)
        # The nutation of theta itself: |X + iY|^2 = a + b cos((fast - slow) t + phase).
        np.testing.assert_allclose(fit_frequency(np.abs(xi[n]) ** 2, dt, offset=True), fast - slow, rtol=1e-7)


@pytest.mark.slow
def test_sleeping_top_below_critical_spin_matches_simulation(top_runs):
    """Below w_crit the tilt grows as exp(growth_rate t) while turning at I3 w3 / (2 I1): Prony's fit
    of the linear part (theta < 1e-3) gives both (measured ~1e-6), and a straight line through
    log(theta) between 2e-3 and 2e-2 gives the growth rate to ~1.5e-4."""
    xi, theta, predicted = top_runs
    dt = TOP_TS[1] - TOP_TS[0]
    for n in (1, 3):
        assert not bool(predicted.stable[n]) and float(predicted.margin[n]) < 0
        growth, turn = float(predicted.growth_rate[n]), float(predicted.fast_rate[n])
        assert float(predicted.slow_rate[n]) == turn
        linear = np.cumprod(theta[n] < 1e-3).astype(bool)
        s = prony2(xi[n][linear], dt)
        np.testing.assert_allclose(np.sort(s.real), [-growth, growth], rtol=1e-5)
        np.testing.assert_allclose(s.imag, turn, rtol=1e-4)
        before_fall = TOP_TS < TOP_TS[np.argmax(theta[n] > 0.1)]
        window = (theta[n] > 2e-3) & (theta[n] < 2e-2) & before_fall
        assert window.sum() > 30
        slope = np.polyfit(TOP_TS[window], np.log(theta[n][window]), 1)[0]
        np.testing.assert_allclose(slope, growth, rtol=1e-3)
        assert np.max(theta[n]) > 0.5  # it falls


# ----------------------------------------------------------------------------------------------
# sleeping_top: formula checks, edge cases, gradients, errors
# ----------------------------------------------------------------------------------------------


def test_sleeping_top_matches_numpy_roots():
    rng = np.random.default_rng(11)
    n = 30
    I1 = rng.uniform(1e-4, 1e-3, n)
    I3 = I1 * rng.uniform(0.2, 1.9, n)
    mass, l = rng.uniform(0.05, 0.5, n), rng.uniform(-0.05, 0.1, n)
    spin = rng.uniform(-300.0, 300.0, n)
    inertia = np.stack([I1, I1, I3], axis=-1)
    com = np.stack([np.zeros(n), np.zeros(n), l], axis=-1)
    result = TOP(*(jnp.asarray(a) for a in (inertia, mass, com, spin)), jnp.asarray(G))
    assert isinstance(result, SleepingTop)
    k = mass * G * l
    np.testing.assert_allclose(result.margin, (I3 * spin) ** 2 - 4 * I1 * k, rtol=1e-12)
    np.testing.assert_allclose(result.critical_spin, np.where(l > 0, 2 * np.sqrt(np.abs(I1 * k)) / I3, 0.0))
    np.testing.assert_array_equal(result.stable, (I3 * spin) ** 2 > 4 * I1 * k)
    np.testing.assert_array_equal(result.stable, (np.abs(spin) > result.critical_spin) | (l <= 0))
    for i in range(n):
        roots = np.roots([I1[i], -I3[i] * spin[i], k[i]])
        roots = roots[np.argsort(np.abs(roots))]
        if np.all(np.abs(roots.imag) == 0):
            np.testing.assert_allclose([result.slow_rate[i], result.fast_rate[i]], roots.real, rtol=1e-9)
            assert float(result.growth_rate[i]) == 0.0
        else:
            np.testing.assert_allclose(result.fast_rate[i], roots[0].real, rtol=1e-9)
            np.testing.assert_allclose(result.slow_rate[i], roots[0].real, rtol=1e-9)
            np.testing.assert_allclose(result.growth_rate[i], abs(roots[0].imag), rtol=1e-9)


def test_sleeping_top_fast_top_slow_root_without_cancellation():
    """A fast top: slow precession m g l / (I3 w3) to full precision (the naive root formula would
    lose ~8 digits to cancellation here)."""
    I1, I3, m, l, w3 = 1e-4, 1.5e-4, 0.1, 0.04, 1e5
    result = TOP(
        jnp.asarray([I1, I1, I3]), jnp.asarray(m), jnp.asarray([0.0, 0.0, l]), jnp.asarray(w3), jnp.asarray(G)
    )
    k = m * G * l
    slow = k / (I3 * w3) * (1 + I1 * k / (I3 * w3) ** 2)  # series of the small root, next term ~1e-18
    np.testing.assert_allclose(result.slow_rate, slow, rtol=1e-14)


def test_sleeping_top_edge_cases_without_nan():
    inertia, mass, com = jnp.asarray([2e-4, 2e-4, 1e-4]), jnp.asarray(0.1), jnp.asarray([0.0, 0.0, 0.04])
    critical = float(TOP(inertia, mass, com, jnp.asarray(0.0)).critical_spin)
    # No spin: the inverted pendulum, growth sqrt(m g l / I1), no turning.
    still = TOP(inertia, mass, com, jnp.asarray(0.0))
    np.testing.assert_allclose(still.growth_rate, np.sqrt(0.1 * G * 0.04 / 2e-4), rtol=1e-14)
    assert float(still.fast_rate) == 0.0 and float(still.slow_rate) == 0.0
    # Exactly critical: a double root I3 w3 / (2 I1), marginal (not stable), zero growth.
    at = TOP(
        jnp.asarray([1.0, 1.0, 1.0]),
        jnp.asarray(1.0),
        jnp.asarray([0.0, 0.0, 1.0]),
        jnp.asarray(2.0),
        jnp.asarray(1.0),
    )
    assert float(at.margin) == 0.0 and not bool(at.stable) and float(at.growth_rate) == 0.0
    assert float(at.fast_rate) == 1.0 and float(at.slow_rate) == 1.0
    # Spinning the other way: same criterion, rates change sign.
    fwd = TOP(inertia, mass, com, jnp.asarray(2.0 * critical))
    back = TOP(inertia, mass, com, jnp.asarray(-2.0 * critical))
    np.testing.assert_allclose([back.slow_rate, back.fast_rate], [-fwd.slow_rate, -fwd.fast_rate])
    assert bool(back.stable)
    # A hanging top (l < 0) is stable at any spin, a spinning top held at its centre of mass (no
    # torque of gravity) too; w_crit = 0. (At l = 0 without spin the margin is 0: marginal, reported
    # not stable.)
    at_pivot = jnp.zeros(3)
    for c, g, spins in ((jnp.asarray([0.0, 0.0, -0.04]), 9.81, (0.0, 5.0)), (at_pivot, 9.81, (5.0,))):
        for w in spins:
            result = TOP(inertia, mass, c, jnp.asarray(w), jnp.asarray(g))
            assert bool(result.stable) and float(result.critical_spin) == 0.0
            assert float(result.growth_rate) == 0.0
    # Gradients are finite at all of these points, including the double root and w3 = l = 0.
    unit, up = jnp.asarray([1.0, 1.0, 1.0]), jnp.asarray([0.0, 0.0, 1.0])
    points = [
        (inertia, mass, com, 0.0, G),
        (unit, jnp.asarray(1.0), up, 2.0, 1.0),
        (inertia, mass, jnp.zeros(3), 0.0, G),
    ]
    fields = ("growth_rate", "slow_rate", "fast_rate", "critical_spin", "margin")

    @jax.jit
    def jacobian(*args):
        def values(*args):
            result = TOP(*args)
            return jnp.stack([getattr(result, f) for f in fields])

        return jax.jacrev(values, argnums=(0, 1, 2, 3, 4))(*args)

    for I, m, c, w, g in points:
        grads = jacobian(I, m, c, jnp.asarray(w), jnp.asarray(g))
        assert all(np.all(np.isfinite(x)) for x in grads), grads


@pytest.mark.parametrize("field,factor", [("growth_rate", 0.6), ("fast_rate", 1.4), ("slow_rate", 1.4)])
def test_sleeping_top_gradient_matches_finite_differences(field, factor):
    params = np.array([3e-4, 1.5e-4, 0.1, 0.04])  # I1, I3, m, l
    critical = 2.0 * np.sqrt(params[0] * params[2] * G * params[3]) / params[1]

    def value(p):
        w = jnp.asarray(factor * critical)
        inertia = jnp.stack([p[0], p[0], p[1]])
        com = jnp.stack([jnp.zeros(()), jnp.zeros(()), p[3]])
        return getattr(TOP(inertia, p[2], com, w, jnp.asarray(G)), field)

    grad = jax.grad(value)(jnp.asarray(params))
    fd = central_difference(value, params, 1e-7 * params)  # relative steps
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_sleeping_top_critical_spin_gradient():
    def critical(mass):
        return TOP(
            jnp.asarray([3e-4, 3e-4, 1.5e-4]), mass, jnp.asarray([0.0, 0.0, 0.04]), jnp.asarray(0.0)
        ).critical_spin

    m = jnp.asarray(0.1)
    np.testing.assert_allclose(jax.grad(critical)(m), critical(m) / (2 * m), rtol=1e-12)


def test_sleeping_top_batch_shapes():
    inertia = jnp.asarray([[2e-4, 2e-4, 1e-4], [3e-4, 3e-4, 4e-4]])  # (2, 3)
    spin = jnp.asarray([[10.0], [50.0], [200.0]])  # (3, 1) -> batch (3, 2)
    result = sleeping_top(inertia, jnp.asarray(0.1), jnp.asarray([0.0, 0.0, 0.04]), spin)
    for field in ("margin", "critical_spin", "stable", "slow_rate", "fast_rate", "growth_rate"):
        assert getattr(result, field).shape == (3, 2)
    one = TOP(inertia[1], jnp.asarray(0.1), jnp.asarray([0.0, 0.0, 0.04]), spin[2, 0])
    assert float(one.fast_rate) == float(result.fast_rate[2, 1])
    jitted = jax.jit(sleeping_top)(inertia, jnp.asarray(0.1), jnp.asarray([0.0, 0.0, 0.04]), spin)
    np.testing.assert_allclose(jitted.fast_rate, result.fast_rate, rtol=1e-15)


def test_sleeping_top_bad_input(without_runtime_typecheck):
    mass, com, w = jnp.asarray(0.1), jnp.asarray([0.0, 0.0, 0.04]), jnp.asarray(30.0)
    expect_error(
        lambda: sleeping_top(jnp.asarray([2e-4, 2.2e-4, 1e-4]), mass, com, w).margin, "symmetric top"
    )
    # Within symmetry_rtol the mean transverse moment is used.
    loose = sleeping_top(jnp.asarray([2e-4, 2.2e-4, 1e-4]), mass, com, w, symmetry_rtol=0.2)
    mean = sleeping_top(jnp.asarray([2.1e-4, 2.1e-4, 1e-4]), mass, com, w)
    np.testing.assert_allclose(loose.margin, mean.margin, rtol=1e-14)
    expect_error(
        lambda: sleeping_top(jnp.asarray([2e-4, 2e-4, 1e-4]), mass, jnp.asarray([0.01, 0.0, 0.04]), w).margin,
        "symmetry axis",
    )
    expect_error(lambda: sleeping_top(jnp.asarray([1e-4, 1e-4, 3e-4]), mass, com, w).margin, "triangle")
    with pytest.raises(ValueError, match="principal_axes"):
        sleeping_top(jnp.eye(3) * 1e-4, mass, com, w)
    with pytest.raises(ValueError, match="com"):
        sleeping_top(jnp.asarray([2e-4, 2e-4, 1e-4]), mass, jnp.asarray([0.0, 0.04]), w)


def test_float32_stays_float32_with_python_numbers():
    """float32 arrays with plain Python numbers (the default gravity, a mass of 0.1) stay float32."""
    inertia = jnp.asarray([3e-4, 3e-4, 1.5e-4], jnp.float32)
    com = jnp.asarray([0.0, 0.0, 0.04], jnp.float32)
    single = sleeping_top(inertia, 0.1, com, jnp.asarray(200.0, jnp.float32))
    double = sleeping_top(inertia.astype(jnp.float64), 0.1, com.astype(jnp.float64), jnp.asarray(200.0))
    for field in ("margin", "critical_spin", "slow_rate", "fast_rate"):
        assert getattr(single, field).dtype == jnp.float32
        np.testing.assert_allclose(getattr(single, field), getattr(double, field), rtol=1e-5)
    assert spin_stability(jnp.asarray([1.0, 2.0, 3.0], jnp.float32), 2.0).frequency.dtype == jnp.float32
