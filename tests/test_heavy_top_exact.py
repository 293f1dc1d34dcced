"""Lagrange's top in closed form (``simulate(HeavyTop, accuracy="exact")``) against independent references.

References: scipy's DOP853 at rtol = atol = 1e-13 on Euler's equations with the gravity torque and the
quaternion kinematics (written below in numpy); the roots of the cubic ``f(u)`` by ``numpy.roots``
with ``scipy.special.ellipk`` for the nutation period; the classical results (fast-top nutation,
the two steady-precession rates, the sleeping-top threshold, the cusps); central differences for
gradients.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference, dop853, expect_error, quat_multiply, quat_rotate, random_quaternions
from scipy.spatial.transform import Rotation
from scipy.special import ellipk

import rigidjax as rj
from rigidjax._closed_form.heavy_top import lagrange_top_motion, lagrange_top_parts

G = 9.81
TOP = np.array([1.0, 1.0, 0.5])  # (A, A, C) about the pivot


def euler_zxz(angles):
    return Rotation.from_euler("ZXZ", angles).as_quat(scalar_first=True)


def reference(inertia, mass, com, gravity, omega0, q0, ts, time_scale=1.0):
    """DOP853 of the heavy top: ``I w' = (I w) x w + (R^T Z) x (m g com)``, ``q' = q (0, w) / 2``."""
    I1, I2, I3 = (float(x) for x in np.asarray(inertia, float))
    cx, cy, cz = (float(mass * gravity * x) for x in np.asarray(com, float))

    def accel(t, w, q):  # scalar arithmetic: DOP853 calls it ~1e5 times per reference
        w1, w2, w3 = w.tolist()
        qw, qx, qy, qz = q.tolist()
        # R^T Z, the space vertical in the body frame: the third row of R(q), as q* (0, Z) q.
        ux, uy, uz = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), qw * qw - qx * qx - qy * qy + qz * qz
        L1, L2, L3 = I1 * w1, I2 * w2, I3 * w3
        return [
            (L2 * w3 - L3 * w2 + uy * cz - uz * cy) / I1,
            (L3 * w1 - L1 * w3 + uz * cx - ux * cz) / I2,
            (L1 * w2 - L2 * w1 + ux * cy - uy * cx) / I3,
        ]

    scale = max(np.linalg.norm(omega0), 1e-3)
    return dop853(accel, omega0, ts, q0, omega_scale=scale, time_scale=time_scale)


# The closed form itself, for the fast tier: JAX's persistent cache keeps this program, while
# simulate's (with its run-time value checks, host callbacks) compiles anew in each run (~10 s).
_closed_form = jax.jit(lagrange_top_motion)


def exact(inertia, mass, com, omega0, q0, ts, gravity=G, dtype=jnp.float64, direct=False):
    """``simulate(HeavyTop(...), accuracy="exact")`` (or, with ``direct``, the closed form it calls)."""
    if direct:
        args = (inertia, mass, com, gravity, omega0, q0, ts)
        w, q = _closed_form(*(jnp.asarray(x, dtype) for x in args))
        return np.asarray(w, float), np.asarray(q, float)
    top = rj.HeavyTop(jnp.asarray(inertia, dtype), jnp.asarray(mass, dtype), jnp.asarray(com, dtype),
                      jnp.asarray(gravity, dtype))  # fmt: skip
    state = rj.State(jnp.asarray(omega0, dtype), jnp.asarray(q0, dtype))
    trajectory = rj.simulate(top, state, jnp.asarray(ts, dtype), accuracy="exact")
    return np.asarray(trajectory.omega, float), np.asarray(trajectory.orientation, float)


def axis_height(q):
    """``u = cos(theta)``: the space Z component of the body z axis."""
    return quat_rotate(q, np.array([0.0, 0.0, 1.0]))[..., 2]


def steady_rates(inertia, mass, l, omega3, theta):
    """The slow and fast steady-precession rates: roots of ``A cos(theta) W^2 - C w3 W + m g l = 0``."""
    A, C = inertia[0], inertia[2]
    disc = np.sqrt((C * omega3) ** 2 - 4 * A * np.cos(theta) * mass * G * l)
    return [2 * mass * G * l / (C * omega3 + s * disc) for s in (1, -1)]  # slow, fast (no cancellation)


def precessing(inertia, mass, l, omega3, theta, rate, psi=0.2):
    """Body omega and q0 of steady precession at ``rate`` with theta' = 0."""
    w0 = [rate * np.sin(theta) * np.sin(psi), rate * np.sin(theta) * np.cos(psi), omega3]
    return w0, euler_zxz([0.1, theta, psi])


# name: (inertia, mass, com_z, omega0, Euler angles (zxz), duration, time scale of the reference)
_slow, _fast = steady_rates(TOP, 1.0, 0.3, 20.0, 0.6)
REGIMES = {
    "generic": (TOP, 1.0, 0.3, [0.3, -0.2, 8.0], [0.2, 0.7, 0.1], 20.0, 1.0),
    "fast top": (TOP, 1.0, 0.3, [0.0, 0.0, 80.0], [0.0, 0.5, 0.0], 3.0, 1.0),
    "cusps": (TOP, 1.0, 0.3, [0.0, 0.0, 15.0], [0.3, 0.9, 0.2], 12.0, 1.0),
    "looping": (TOP, 1.0, 0.3, [0.0, 2.0, 10.0], [0.3, 0.8, 0.2], 20.0, 1.0),
    "precession sign change": (TOP, 1.0, 0.3, [0.0, -1.5, 10.0], [0.3, 0.8, 0.2], 20.0, 1.0),
    "hanging": (TOP, 1.0, -0.3, [0.5, 0.4, 3.0], [0.1, 0.4, 0.3], 20.0, 1.0),
    "hanging, axis down": (TOP, 1.0, -0.3, [0.5, 0.4, 3.0], [0.1, 2.5, 0.3], 40.0, 1.0),
    "sleeping": (TOP, 1.0, 0.3, [0.0, 0.0, 15.0], [0.3, 0.0, 0.2], 20.0, 1.0),
    "sleeping, kicked": (TOP, 1.0, 0.3, [0.2, 0.1, 15.0], [0.3, 0.0, 0.2], 20.0, 1.0),
    "nearly sleeping": (TOP, 1.0, 0.3, [0.2, 0.1, 15.0], [0.3, 1e-5, 0.2], 20.0, 1.0),
    "sleeping, tilted 1e-6": (TOP, 1.0, 0.3, [0.0, 0.0, 15.0], [0.3, 1e-6, 0.2], 20.0, 1.0),
    "upright, falling through the bottom": (TOP, 1.0, 0.3, [2.0, 0.0, 1.0], [0.3, 0.0, 0.2], 30.0, 1.0),
    "slow spin, swinging through": (TOP, 1.0, 0.3, [0.0, 0.0, 0.0], [0.3, 0.5, 0.2], 40.0, 1.0),
    "steady slow precession": (
        TOP,
        1.0,
        0.3,
        *precessing(TOP, 1.0, 0.3, 20.0, 0.6, _slow)[:1],
        [0.1, 0.6, 0.2],
        20.0,
        1.0,
    ),  # fmt: skip
    "steady fast precession": (
        TOP,
        1.0,
        0.3,
        *precessing(TOP, 1.0, 0.3, 20.0, 0.6, _fast)[:1],
        [0.1, 0.6, 0.2],
        5.0,
        1.0,
    ),  # fmt: skip
    "very slow top": (TOP, 1.0, 0.3, [1e-3, 0.0, 2e-3], [0.1, 0.4, 0.2], 2.0e4, 1e-2),
    "centre of mass at the pivot": (TOP, 1.0, 0.0, [0.3, 0.1, 4.0], [0.1, 0.5, 0.2], 40.0, 1.0),
}
# The very slow top has g = 1e-4 (below): its nutation period is ~130 s.
GRAVITY = {"very slow top": 1e-4}
# Max |error| vs DOP853 measured over the durations above (omega relative to max |omega|, q absolute):
# <= 4e-11 in every regime but the very slow top (1.4e-10 over 2e4 s); the bound is 2e-9.
TOLERANCE = 2e-9
FAST_TIER = ("generic", "sleeping, kicked")
# Every single-top call uses this many samples: one compiled program serves all of them.
SAMPLES = 401


def _setup(name, samples=SAMPLES):
    inertia, mass, l, w0, angles, duration, time_scale = REGIMES[name]
    ts = np.linspace(0.0, duration, samples)
    return inertia, mass, [0.0, 0.0, l], np.asarray(w0, float), euler_zxz(angles), ts, time_scale


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=() if n in FAST_TIER else pytest.mark.slow) for n in REGIMES]
)
def test_against_dop853(name):
    """Every regime over >= 10 nutation periods (steady ones: >= 10 precession periods or turns)."""
    inertia, mass, com, w0, q0, ts, time_scale = _setup(name)
    gravity = GRAVITY.get(name, G)
    w, q = exact(inertia, mass, com, w0, q0, ts, gravity, direct=name in FAST_TIER)
    w_ref, q_ref = reference(inertia, mass, com, gravity, w0, q0, ts, time_scale)
    tol = TOLERANCE
    assert np.all(np.isfinite(w)) and np.all(np.isfinite(q))
    assert np.max(np.abs(w - w_ref)) <= tol * np.max(np.abs(w_ref))
    assert np.max(np.abs(q - q_ref)) <= tol
    assert np.max(np.abs(np.linalg.norm(q, axis=-1) - 1)) <= 1e-15
    u = axis_height(q_ref)
    peaks = np.sum((u[1:-1] > u[:-2]) & (u[1:-1] >= u[2:]))
    if np.ptp(u) > 1e-6:  # a nutating top: at least 10 nutation periods
        assert peaks >= 10, peaks


def _conserved(inertia, mass, l, w, q):
    """Energy, L_z (space vertical) and L_3 (body symmetry axis) at every sample, in numpy."""
    momentum = np.asarray(inertia) * w
    energy = 0.5 * np.sum(w * momentum, -1) + mass * G * l * axis_height(q)
    return energy, quat_rotate(q, momentum)[..., 2], momentum[..., 2]


@pytest.mark.parametrize(
    "name",
    [
        "generic",
        *(
            pytest.param(n, marks=pytest.mark.slow)
            for n in ("cusps", "hanging", "sleeping, kicked", "looping")
        ),
    ],
)
def test_conservation_to_roundoff(name):
    """E, L_z, L_3 at 401 samples over 1000 s (hundreds of nutation periods)."""
    inertia, mass, com, w0, q0, _, _ = _setup(name)
    ts = np.linspace(0.0, 1000.0, SAMPLES)
    w, q = exact(inertia, mass, com, w0, q0, ts, direct=True)
    for values in _conserved(inertia, mass, com[2], w, q):
        scale = np.max(np.abs(_conserved(inertia, mass, abs(com[2]), np.abs(w), np.ones(4) / 2)))
        assert np.max(np.abs(values - values[0])) <= 1e-12 * max(scale, 1.0)


def _crossings(ts, x):
    """Times where ``x`` crosses its mean upwards (linear interpolation)."""
    x = x - 0.5 * (np.max(x) + np.min(x))
    i = np.nonzero((x[:-1] < 0) & (x[1:] >= 0))[0]
    return ts[i] - x[i] * (ts[i + 1] - ts[i]) / (x[i + 1] - x[i])


def _period_from_cubic(inertia, mass, l, w0, q0):
    """Nutation period ``2 K(m) / lambda`` from ``numpy.roots`` of ``f(u)`` (standing top)."""
    A, C = inertia[0], inertia[2]
    R = Rotation.from_quat(q0, scalar_first=True).as_matrix()
    L = R @ (np.asarray(inertia) * w0)
    u0 = R[2, 2]
    a, b, beta = C * w0[2] / A, L[2] / A, 2 * mass * G * l / A
    alpha = (w0[0] ** 2 + w0[1] ** 2) + beta * u0
    # f(u) = beta u^3 - (alpha + a^2) u^2 + (2 a b - beta) u + (alpha - b^2)
    u1, u2, u3 = np.sort(np.roots([beta, -(alpha + a * a), 2 * a * b - beta, alpha - b * b]).real)
    lam = np.sqrt(beta * (u3 - u1)) / 2
    return 2 * ellipk((u2 - u1) / (u3 - u1)) / lam, (u1, u2)


def test_fast_top_nutation():
    """Released with spin only: nutation at ~C w3 / A with amplitude ~beta sin^2(theta0) / a^2."""
    inertia, mass, com, w0, q0, _, _ = _setup("fast top")
    A, C, l = inertia[0], inertia[2], com[2]
    a, beta = C * w0[2] / A, 2 * mass * G * l / A
    exact_period, (u1, _) = _period_from_cubic(inertia, mass, l, w0, q0)
    # Samples at multiples of half the period from the roots: maxima (u0) and minima (u1) alternate.
    ts = exact_period / 2 * np.arange(SAMPLES)
    w, q = exact(inertia, mass, com, w0, q0, ts, direct=True)
    u = axis_height(q)
    u0 = axis_height(q0)
    assert np.max(np.abs(u[0::2] - u0)) <= 1e-13
    assert np.max(np.abs(u[1::2] - u1)) <= 1e-11  # numpy.roots' u1 is good to ~eps / (u2 - u1)
    # Classical fast top: frequency a (relative correction O(beta / a^2) = 3.7e-3 here) and
    # u0 - u1 = beta sin^2(theta0) / a^2 to first order.
    small = beta / a**2
    assert abs(exact_period * a / (2 * np.pi) - 1) <= 2 * small
    assert abs((u0 - u1) / (beta * (1 - u0**2) / a**2) - 1) <= 4 * small


@pytest.mark.parametrize("which", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_steady_precession_rates(which):
    """theta' = 0 and phi' = a root of A cos(theta) W^2 - C w3 W + m g l = 0: theta stays, the axis
    turns about Z at W (both the slow and the fast root)."""
    theta, w3 = 0.6, 20.0
    rate = steady_rates(TOP, 1.0, 0.3, w3, theta)[which]
    w0, q0 = precessing(TOP, 1.0, 0.3, w3, theta, rate)
    ts = np.linspace(0.0, 40.0 / abs(rate), SAMPLES)
    _, q = exact(TOP, 1.0, [0.0, 0.0, 0.3], w0, q0, ts, direct=True)
    axis = quat_rotate(q, np.array([0.0, 0.0, 1.0]))
    expected = Rotation.from_rotvec(np.outer(rate * ts, [0.0, 0.0, 1.0])).apply(axis[0])
    assert np.max(np.abs(axis - expected)) <= 1e-11
    assert np.max(np.abs(axis[:, 2] - np.cos(theta))) <= 1e-13


@pytest.mark.parametrize("factor", [1.2, pytest.param(0.8, marks=pytest.mark.slow)])
def test_sleeping_top_threshold(factor):
    """Upright with a 1e-6 rad tilt: above the critical spin 2 sqrt(A m g l) / C (from
    rigidjax.sleeping_top) the tilt stays ~1e-6; below it the top falls."""
    com = [0.0, 0.0, 0.3]
    critical = float(rj.sleeping_top(jnp.asarray(TOP), 1.0, jnp.asarray(com), 1.0).critical_spin)
    assert abs(critical - 2 * np.sqrt(TOP[0] * G * 0.3) / TOP[2]) <= 1e-12
    q0 = euler_zxz([0.3, 1e-6, 0.2])
    ts = np.linspace(0.0, 30.0, SAMPLES)
    _, q = exact(TOP, 1.0, com, [0.0, 0.0, factor * critical], q0, ts, direct=True)
    tilt = np.arccos(np.clip(axis_height(q), -1, 1))
    if factor > 1:
        assert np.max(tilt) <= 1e-4
    else:
        assert np.max(tilt) >= 1.0


def test_cusps_and_loops():
    """Released with spin only (theta' = phi' = 0): A sin^2(theta) phi' = L_z - L_3 u >= 0, zero at
    the top circle u2 = u0, reached once per nutation period (cusps; the period from numpy.roots).
    Started with phi' < 0 the axis loops: phi' changes sign."""

    def transverse_momentum(name, ts):  # L_z - L_3 u from the closed form's output
        inertia, mass, com, w0, q0, _, _ = _setup(name)
        w, q = exact(inertia, mass, com, w0, q0, ts, direct=True)
        L = quat_rotate(q, np.asarray(inertia) * w)
        return L[:, 2] - inertia[2] * w[:, 2] * axis_height(q), axis_height(q), axis_height(q0)

    inertia, mass, com, w0, q0, _, _ = _setup("cusps")
    period, _ = _period_from_cubic(inertia, mass, com[2], w0, q0)
    ts = period / 20 * np.arange(SAMPLES)  # every 20th sample a cusp
    h, u, u0 = transverse_momentum("cusps", ts)
    assert np.max(u) <= u0 + 1e-14
    assert np.min(h) >= -1e-12 * np.max(h)
    assert np.max(np.abs(h[::20])) <= 1e-10 * np.max(h)
    h, _, _ = transverse_momentum("precession sign change", np.linspace(0.0, 20.0, SAMPLES))
    assert np.min(h) < -0.1 * np.max(np.abs(h)) and np.max(h) > 0.1 * np.max(np.abs(h))


def _random_tops(n, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.uniform(0.5, 2.0, n)
    inertia = np.stack([A, A, A * rng.uniform(0.2, 1.9, n)], -1)
    mass = rng.uniform(0.5, 2.0, n)
    com = np.zeros((n, 3))
    com[:, 2] = rng.choice([-1.0, 1.0], n) * rng.uniform(0.05, 0.5, n)
    omega = np.concatenate([rng.normal(0.0, 1.0, (n, 2)), rng.uniform(-30.0, 30.0, (n, 1))], -1)
    return inertia, mass, com, omega, random_quaternions(rng, n)


# In one program: evaluated op by op, the parts compiled ~150 small programs (~10 s).
_lagrange_top_parts = jax.jit(lagrange_top_parts)


def _elliptic_parameter(inertia, mass, com, omega, q0):
    return np.asarray(_lagrange_top_parts(*(jnp.asarray(x) for x in (inertia, mass, com, G, omega, q0)))["m"])


def _tops_of_sides(sides):
    """60 random tops whose elliptic parameters lie on the given side(s) of 1/2 (tops repeat): the
    same number in each case, so that one compiled program serves all of them."""
    tops = _random_tops(200)
    m = _elliptic_parameter(*tops)
    lower, upper = np.flatnonzero(m <= 0.5), np.flatnonzero(m > 0.5)
    assert lower.size >= 30 and upper.size >= 5
    chosen = {
        "both": np.concatenate([lower[:40], np.resize(upper, 20)]),
        "m <= 1/2": lower[:60],
        "m > 1/2": np.resize(upper, 60),
    }[sides]
    return tuple(x[chosen] for x in tops)


@pytest.mark.parametrize("sides", ["both", "m <= 1/2", "m > 1/2"])
@pytest.mark.parametrize("n_samples", [11, 2])
def test_blocks_of_tops_match_one_block(sides, n_samples):
    """60 random tops evaluated in blocks of 7 == in one block, with tops whose elliptic parameters
    lie on one side of 1/2 or both (each block masks the two sides' theta series, as one block
    does); the last block overlaps the one before it. The closed form's rare branches are chosen per
    block."""
    inertia, mass, com, omega, q0 = _tops_of_sides(sides)
    top = rj.HeavyTop(*(jnp.asarray(x) for x in (inertia, mass, com)), G)
    state, ts = rj.State(jnp.asarray(omega), jnp.asarray(q0)), jnp.linspace(0.0, 5.0, n_samples)
    whole = rj.simulate(top, state, ts, accuracy="exact")
    blocks = rj.simulate(top, state, ts, accuracy="exact", chunk_size=7)
    scale = np.max(np.abs(np.asarray(whole.omega)))
    np.testing.assert_allclose(np.asarray(blocks.omega), np.asarray(whole.omega), rtol=0, atol=1e-13 * scale)
    np.testing.assert_allclose(
        np.asarray(blocks.orientation), np.asarray(whole.orientation), rtol=0, atol=1e-13
    )
    np.testing.assert_allclose(
        np.asarray(blocks.invariants()["quaternion_norm"]),
        np.asarray(whole.invariants()["quaternion_norm"]),
        rtol=0,
        atol=1e-15,
    )


def test_derivative_through_blocks_in_both_modes():
    """The derivative of a function of the motion along a direction in the tops' masses, through
    blocks of 7 tops, against central differences: in forward mode (``jax.jvp``) and in reverse
    mode taken outside a ``jit`` around ``simulate`` (linearised and transposed)."""
    # The tops, sample times and blocks of the blocks test above: the central differences' values
    # come from its compiled program.
    inertia, mass, com, omega, q0 = _tops_of_sides("both")
    ts = jnp.linspace(0.0, 5.0, 11)

    def loss(mass, chunk_size):
        top = rj.HeavyTop(jnp.asarray(inertia), mass, jnp.asarray(com), G)
        traj = rj.simulate(top, rj.State(jnp.asarray(omega), jnp.asarray(q0)), ts, accuracy="exact",
                           chunk_size=chunk_size)  # fmt: skip
        return jnp.sum(traj.omega[..., 0] ** 2) + jnp.sum(traj.orientation[..., 1])

    direction = jnp.asarray(np.random.default_rng(4).normal(size=mass.shape))
    _, d_forward = jax.jvp(lambda x: loss(x, 7), (jnp.asarray(mass),), (direction,))
    value, gradient = jax.value_and_grad(jax.jit(lambda x: loss(x, 7)))(jnp.asarray(mass))
    d_reverse = jnp.sum(gradient * direction)
    # The loss is ~6e5: roundoff ~eps 6e5 / h (5e-8 relative here), truncation ~h^2 (1.7e-7 at h = 1e-4).
    h = 3e-5
    plus, minus = (loss(jnp.asarray(mass) + sign * h * direction, 7) for sign in (1, -1))
    central = (plus - minus) / (2 * h)
    np.testing.assert_allclose(float(d_reverse), float(central), rtol=2e-7)
    np.testing.assert_allclose(float(d_forward), float(central), rtol=2e-7)
    np.testing.assert_allclose(float(d_forward), float(d_reverse), rtol=1e-12)
    np.testing.assert_allclose(float(value), float(loss(jnp.asarray(mass), 7)), rtol=1e-13)


@pytest.mark.slow
def test_batch_matches_single_tops():
    """1000 random tops (standing and hanging, any spin) in one call == each top alone."""
    inertia, mass, com, omega, q0 = _random_tops(1000)
    # 7 samples, as the gradient tests' loss: each top alone runs the program of their central differences.
    ts = np.linspace(0.0, 5.0, 7)
    w, q = exact(inertia, mass, com, omega, q0, ts)
    assert w.shape == (1000, 7, 3) and q.shape == (1000, 7, 4)
    assert np.all(np.isfinite(w)) and np.all(np.isfinite(q))
    for i in range(0, 1000, 125):
        w_i, q_i = exact(inertia[i], mass[i], com[i], omega[i], q0[i], ts)
        np.testing.assert_allclose(w[i], w_i, rtol=0, atol=1e-12 * np.max(np.abs(w_i)))
        np.testing.assert_allclose(q[i], q_i, rtol=0, atol=1e-13)


@pytest.mark.slow
def test_random_tops_against_dop853():
    """12 random tops (standing and hanging, any spin) at 101 times over 10 s against DOP853."""
    inertia, mass, com, omega, q0 = _random_tops(12, seed=1)
    ts = np.linspace(0.0, 10.0, 101)
    # Each top alone, by simulate's program of the single tops of test_against_dop853 (SAMPLES samples:
    # these times, then more at the same spacing); a batch of 12 at 101 samples compiled a program of its
    # own (~15 s), and test_batch_matches_single_tops checks that a batch gives each top's values.
    extended = np.concatenate([ts, ts[-1] + (ts[1] - ts[0]) * np.arange(1, SAMPLES - len(ts) + 1)])
    for i in range(12):
        w, q = (x[: len(ts)] for x in exact(inertia[i], mass[i], com[i], omega[i], q0[i], extended))
        w_ref, q_ref = reference(inertia[i], mass[i], com[i], G, omega[i], q0[i], ts)
        assert np.max(np.abs(w - w_ref)) <= 2e-9 * np.max(np.abs(w_ref))
        assert np.max(np.abs(q - q_ref)) <= 2e-9


@pytest.mark.slow
@pytest.mark.parametrize(
    "theta, w0, com_z, tol",
    [
        # Swung up to 1.3e-5 (relative speed) short of the unstable vertical: m = 1 - O(1e-5).
        (1.635, [np.sqrt(2 * G * 0.3 * (1 + np.cos(1.635))) * (1 + 1.3e-5), 0.0, 1e-3], -0.3, 1e-7),
        # The same speed, standing.
        (1.635, [np.sqrt(2 * G * 0.3 * (1 + np.cos(1.635))) * (1 + 1.3e-5), 0.0, 1e-3], 0.3, 1e-7),
        # Hanging 6.8e-9 rad off the vertical with a fast spin (a pole 1e-17 from a turning circle).
        (6.8e-9, [1.16e-3, -1.59e-3, 17.97], -0.3, 2e-9),
        # Released almost at rest: a standing top falls and swings within ~eps of the downward
        # vertical, a hanging one within ~eps of the upward one, where the pole's distance from the
        # turning circle (~eps^2) is far below the numbers it was formed from (the closed form was
        # off by 0.1-2 rad there, marked successful).
        (0.4, [1e-6, 0.0, 1e-6], 0.3, 2e-9),
        (0.4, [1e-8, 0.0, 1e-8], 0.3, 2e-9),
        (0.4, [1e-4, 0.0, 1e-4], -0.3, 2e-9),
        (0.4, [1e-8, 0.0, 1e-8], -0.3, 2e-9),
        # Standing 1e-8 rad from the upward vertical, tilting away from it at 3 rad/s.
        (1e-8, [3.0, 0.0, 50.0], 0.3, 2e-9),
        # Released 1e-8 and 1e-7 rad from upright below the sleeping threshold (6.9 rad/s), spinning
        # and at rest: the resolvent's roots are 0, ~1e-16 and -4, and the deflated pair's sum
        # s2 + lone cancelled (the top at rest never fell; 2.4e-3 and 8.5e-6 off spinning). At rest
        # the fall time is ill-conditioned: two DOP853 references differ by 8e-9.
        (1e-8, [0.0, 0.0, 4.0], 0.3, 2e-9),
        (1e-7, [0.0, 0.0, 4.0], 0.3, 2e-9),
        (1e-8, [0.0, 0.0, 0.0], 0.3, 1e-7),
    ],
)
def test_near_separatrix_and_near_the_poles(theta, w0, com_z, tol):
    """Tops next to the separatrix (the nutation period's K ~ 7 and more) and a top hanging within 1e-8
    rad of the vertical: against DOP853 over 10 s (the separatrix cases to its conditioning), at the
    SAMPLES times of the value tests above (their compiled program)."""
    q0 = np.array([np.cos(theta / 2), np.sin(theta / 2), 0.0, 0.0])
    w0, com = np.asarray(w0), [0.0, 0.0, com_z]
    ts = np.linspace(0.0, 10.0, SAMPLES)
    w, q = exact(TOP, 1.0, com, w0, q0, ts, direct=True)
    w_ref, q_ref = reference(TOP, 1.0, com, G, w0, q0, ts)
    assert np.max(np.abs(w - w_ref)) <= tol * np.max(np.abs(w_ref))
    assert np.max(np.abs(q - q_ref)) <= tol


@pytest.mark.parametrize("offset", [0.0, 1e-12, -1e-12, 1e-10, -1e-10, 1e-8])
def test_a_top_rising_towards_upright_next_to_its_separatrix(offset):
    """A top released at theta = 1 rad with b = a and alpha = beta, for which u = 1 is a double root
    of f(u) = (1 - u)^2 (beta (1 + u) - a^2): it rises towards upright for ever (the heavy top's
    separatrix); its precession rate scaled by 1 + offset. The turning circle and the third root
    lie together by the pole, and the resolvent's root G0 in a close pair known to ~sqrt(eps):
    g0 - beta x_o cancelled, and the closed form was off by 6e-3 (offset 1e-12), 2e-2 (1e-10) and
    7e-7 (0) in omega, up to 1.45 in q, marked successful. Against DOP853 over 3 s (two references,
    one at half the time scale, agree to 5e-13); the double root itself leaves 5e-8 at offset 0."""
    inertia, mass, com = np.array([1e-2, 1e-2, 5e-3]), 0.5, [0.0, 0.0, 0.05]
    beta = 2 * mass * G * com[2] / inertia[0]
    theta = 1.0
    a = np.sqrt(beta * (1 + np.cos(theta)))
    rate = a / (1 + np.cos(theta))  # phi' with b = a
    q0 = np.array([np.cos(theta / 2), np.sin(theta / 2), 0.0, 0.0])
    w0 = np.array([0.0, rate * np.sin(theta) * (1 + offset), inertia[0] / inertia[2] * a])
    ts = np.linspace(0.0, 3.0, SAMPLES)
    w, q = exact(inertia, mass, com, w0, q0, ts, direct=True)
    w_ref, q_ref = reference(inertia, mass, com, G, w0, q0, ts)
    assert np.max(np.abs(w - w_ref)) <= 1e-7 * np.max(np.abs(w_ref))
    assert np.max(np.abs(q - q_ref)) <= 2e-7


# --------------------------------------------------------------------------------------------------
# Gradients


# Upright tops on an unstable equilibrium (below the sleeping threshold |omega3| C / A >= 2 sqrt(m g l
# / A), 6.9 rad/s here): not in REGIMES, whose values are checked against DOP853 over 20 s, where the
# reference's own roundoff grows by e^34 and leaves the equilibrium.
UNSTABLE_UPRIGHT = {
    "upright below the sleeping threshold": (TOP, 1.0, 0.3, [0.0, 0.0, 4.0], [0.3, 0.0, 0.2], 3.0, 1.0),
    "upright at rest": (TOP, 1.0, 0.3, [0.0, 0.0, 0.0], [0.3, 0.0, 0.2], 3.0, 1.0),
}


def _loss_parts(name):
    regime = UNSTABLE_UPRIGHT.get(name) or REGIMES[name]
    inertia, mass, l, w0 = regime[0], regime[1], regime[2], np.asarray(regime[3], float)
    com = [0.0, 0.0, l]
    angles = np.asarray(regime[4], float)
    ts = jnp.linspace(0.0, 3.0, 7)
    weights = np.random.default_rng(3).normal(size=(2, 7, 4))

    def loss(x):  # x = (A, C, mass, l, w1, w2, w3, phi, theta, psi)
        top = rj.HeavyTop(jnp.stack([x[0], x[0], x[1]]), x[2], jnp.stack([0.0 * x[3], 0.0 * x[3], x[3]]))
        q0 = rj.quat_from_euler(x[7:])
        trajectory = rj.simulate(top, rj.State(x[4:7], q0), ts, accuracy="exact")
        return jnp.sum(trajectory.omega * weights[0, :, :3]) + jnp.sum(trajectory.orientation * weights[1])

    x = np.concatenate([[inertia[0], inertia[2], mass, com[2]], w0, angles])
    return loss, x


@pytest.mark.parametrize(
    "name",
    ["generic", "fast top", "cusps", "hanging", "looping", "sleeping, kicked", "steady slow precession",
     "steady fast precession"],
)  # fmt: skip
@pytest.mark.slow
def test_gradients_match_central_differences(name):
    """d/d(A = I1 = I2, I3, mass, com_z, omega0, q0's Euler angles): reverse mode against central
    differences (relative step 1e-6), steady precession included (its first-order nutation carries
    the derivatives). At an exactly upright start the tilt direction is excluded: see the module's
    note in heavy_top.py (the pole branch's phase is taken as exactly uniform)."""
    loss, x = _loss_parts(name)
    grad = np.asarray(jax.grad(loss)(jnp.asarray(x)))
    numeric = central_difference(lambda y: loss(jnp.asarray(y)), x, h=1e-6 * np.maximum(np.abs(x), 1.0))
    check = np.ones(len(x), bool)
    if REGIMES[name][4][1] == 0.0:
        check[8] = False
    assert np.all(np.isfinite(grad))
    np.testing.assert_allclose(grad[check], numeric[check], rtol=1e-6, atol=1e-6 * np.max(np.abs(numeric)))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sleeping", *UNSTABLE_UPRIGHT])
def test_gradients_at_the_sleeping_equilibrium(name):
    """Exactly upright: the value is the steady spin (or rest), the derivatives those of the
    linearised motion, against central differences. Above the sleeping threshold the tilt's two
    modes circle; below it and at rest one grows exponentially (e^5 over the 3 s here), and the
    derivatives grow with it."""
    loss, x = _loss_parts(name)
    grad = np.asarray(jax.grad(loss)(jnp.asarray(x)))
    assert np.all(np.isfinite(grad))
    numeric = central_difference(lambda y: loss(jnp.asarray(y)), x, h=1e-6 * np.maximum(np.abs(x), 1.0))
    np.testing.assert_allclose(grad, numeric, rtol=1e-6, atol=1e-6 * np.max(np.abs(numeric)))


# --------------------------------------------------------------------------------------------------
# Errors, jit, float32


def _state():
    return rj.State(jnp.array([0.3, -0.2, 8.0]), jnp.asarray(euler_zxz([0.2, 0.7, 0.1])))


def test_errors_name_the_condition():
    ts = jnp.linspace(0.0, 1.0, 3)
    state = _state()
    asym = rj.HeavyTop(jnp.array([1.0, 1.1, 0.5]), 1.0, jnp.array([0.0, 0.0, 0.3]))
    expect_error(lambda: rj.simulate(asym, state, ts, accuracy="exact"), "I1 = I2", "I2 = 1.1,")
    # Just beyond roundoff: the moments print apart, with the deviation and the tolerance.
    near = rj.HeavyTop(jnp.array([1e-2, 1e-2 * (1 + 1e-13), 5e-3]), 1.0, jnp.array([0.0, 0.0, 0.3]))
    expect_error(
        lambda: rj.simulate(near, state, ts, accuracy="exact"),
        "I1 = 0.01, I2 = 0.010000000000001,",
        "differ by 1e-13 of the larger, more than the roundoff of 2.2e-14 (float64)",
    )
    off = rj.HeavyTop(jnp.array([1.0, 1.0, 0.5]), 1.0, jnp.array([0.1, 0.0, 0.3]))
    expect_error(lambda: rj.simulate(off, state, ts, accuracy="exact"), "body z", "com = (0.1, 0, 0.3)")
    tensor = rj.HeavyTop(jnp.diag(jnp.array([1.0, 1.1, 0.5])), 1.0, jnp.array([0.0, 0.0, 0.3]))
    expect_error(
        lambda: rj.simulate(tensor, state, ts, accuracy="exact"),
        "symmetric about the line from the pivot through the centre of mass",
        "departs from that symmetry by 0.091 of its transverse moment",
    )
    tilted = rj.HeavyTop(jnp.diag(jnp.array([1.0, 1.0, 0.5])), 1.0, jnp.array([0.1, 0.0, 0.3]))
    expect_error(lambda: rj.simulate(tilted, state, ts, accuracy="exact"), "departs from that symmetry")
    damped = rj.HeavyTop(TOP, 1.0, jnp.array([0.0, 0.0, 0.3]), torque=rj.ViscousDamping(0.1))
    expect_error(lambda: rj.simulate(damped, state, ts, accuracy="exact"), "extra torques")


def test_errors_under_eager_grad_are_value_errors():
    """Under grad (outside jit) the inputs' values are known: the same ValueError as for plain values,
    raised before the differentiated program runs (the gradient tests above run that program)."""
    loss, x = _loss_parts("generic")
    x[2] = -1.0  # the mass
    with pytest.raises(ValueError, match="mass"):
        jax.grad(loss)(jnp.asarray(x))

    def free_loss(scale):
        state = rj.State(jnp.array([0.1, 1.0, 0.2]), jnp.array([1.0, 0.0, 0.0, 0.0]) * scale)
        body = rj.FreeBody(jnp.array([1.0, 2.0, 3.0]))
        return jnp.sum(rj.simulate(body, state, jnp.linspace(0.0, 1.0, 3), accuracy="exact").omega)

    with pytest.raises(ValueError, match="unit quaternion"):
        jax.grad(free_loss)(2.0)


@pytest.mark.slow
def test_jit_traced_model():
    """Under jit the model's values are traced: the same conditions are checked at run time."""
    # 7 samples, as the single tops of test_batch_matches_single_tops and the gradient tests' loss: the
    # eager call below runs their compiled program.
    ts = jnp.linspace(0.0, 1.0, 7)

    @eqx.filter_jit
    def run(inertia, com):
        return rj.simulate(rj.HeavyTop(inertia, 1.0, com), _state(), ts, accuracy="exact").orientation

    q = run(jnp.asarray(TOP), jnp.array([0.0, 0.0, 0.3]))
    _, q_eager = exact(TOP, 1.0, [0.0, 0.0, 0.3], np.array([0.3, -0.2, 8.0]), euler_zxz([0.2, 0.7, 0.1]), ts)
    np.testing.assert_allclose(q, q_eager, rtol=0, atol=1e-15)
    expect_error(lambda: run(jnp.array([1.0, 1.2, 0.5]), jnp.array([0.0, 0.0, 0.3])), "I1 = I2")
    expect_error(lambda: run(jnp.asarray(TOP), jnp.array([0.0, 0.2, 0.3])), "body z")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["generic", "fast top", "hanging", "sleeping, kicked", "looping"])
def test_float32(name):
    """float32 against the float64 closed form over 20 s. Measured: q within 1.7e-5 except the fast
    top (8.1e-5: |omega| t = 1600 rad there) and the looping top (1.4e-4); omega within 7e-6 of
    max |omega| except the looping top (7.1e-5)."""
    inertia, mass, com, w0, q0, _, _ = _setup(name)
    ts = np.linspace(0.0, 20.0, SAMPLES)
    w32, q32 = exact(inertia, mass, com, w0, q0, ts, dtype=jnp.float32)
    w64, q64 = exact(inertia, mass, com, w0, q0, ts)
    assert np.max(np.abs(w32 - w64)) <= 2e-4 * np.max(np.abs(w64))
    assert np.max(np.abs(q32 - q64)) <= 3e-4


def test_float32_gradient_follows_float64():
    """jax.grad of q_x(1 s) in omega0 through "exact" in float32 against the float64 derivative, by
    central differences of the float64 values (relative step 1e-6: ~1e-9 off; a float64 jax.grad,
    which the gradient tests check against central differences of DOP853, compiled 40 s here):
    1.2e-6 of the largest entry. A guard on the resolvent root's last Newton step, set at 1e-8
    relative, dropped that step's derivative in float32, whose rounding moves it further (17 % off)."""

    def final(omega0, dtype):
        top = rj.HeavyTop(jnp.asarray([1e-2, 1e-2, 5e-3], dtype), jnp.asarray(0.5, dtype),
                          jnp.asarray([0.0, 0.0, 0.05], dtype))  # fmt: skip
        q0 = jnp.asarray(euler_zxz([0.0, 0.4, 0.0]), dtype)
        trajectory = rj.simulate(top, rj.State(omega0, q0), jnp.asarray([0.0, 1.0], dtype), accuracy="exact")
        return trajectory.orientation[-1, 1]

    omega0 = np.array([0.3, -0.2, 40.0])
    # q_x(1 s) in float64 by exact()'s program of the value tests above (SAMPLES samples, the last at 1 s).
    ts = np.linspace(0.0, 1.0, SAMPLES)
    inertia, mass, com, q0 = [1e-2, 1e-2, 5e-3], 0.5, [0.0, 0.0, 0.05], euler_zxz([0.0, 0.4, 0.0])
    g64 = central_difference(
        lambda w: exact(inertia, mass, com, w, q0, ts)[1][-1, 1],
        omega0,
        h=1e-6 * np.maximum(np.abs(omega0), 1.0),
    )
    g32 = np.asarray(jax.grad(final)(jnp.asarray(omega0, jnp.float32), jnp.float32), float)
    assert np.max(np.abs(g32 - g64)) <= 1e-4 * np.max(np.abs(g64))


TIME_DERIVATIVE_TOPS = ("generic", "sleeping, kicked")


@functools.cache
def _time_jacobians():
    """jax.jacrev and jax.jacfwd of the closed form at 7 times with respect to the times, for the tops
    of TIME_DERIVATIVE_TOPS: each top's Jacobian ``(7 samples, 7, 7 times)``. The tops are one batch
    (each output depends on its own top alone), so one program per mode serves them all; their values
    are constants of it (XLA folds what depends on them alone: several times faster to compile than
    with the tops as arguments)."""
    ts = np.linspace(0.0, 3.0, 7)
    setups = [_setup(name, samples=2)[:5] for name in TIME_DERIVATIVE_TOPS]
    # (tops, 1, ...): the batch axis against the times' axis.
    inertia, mass, com, w0, q0 = (jnp.asarray(np.stack([np.asarray(s[i], float) for s in setups]))[:, None]
                                  for i in range(5))  # fmt: skip
    gravity = jnp.full(mass.shape, G)

    def state(t):
        w, q = lagrange_top_motion(inertia, mass, com, gravity, w0, q0, t)
        return jnp.concatenate([w, q], axis=-1)  # (tops, 7 samples, 7)

    reverse = np.asarray(jax.jit(jax.jacrev(state))(jnp.asarray(ts)))  # (tops, 7 samples, 7, 7 times)
    forward = np.asarray(jax.jit(jax.jacfwd(state))(jnp.asarray(ts)))
    return ts, {name: (reverse[k], forward[k]) for k, name in enumerate(TIME_DERIVATIVE_TOPS)}


@pytest.mark.parametrize("name", TIME_DERIVATIVE_TOPS)
def test_time_derivative_in_reverse_mode_is_the_equations_of_motion(name):
    """jax.jacrev of the closed form with respect to the sample times (the derivative transposes every
    sample's Jacobian) equals I w' = (I w) x w + (R^T Z) x (m g com) and q' = q (0, w) / 2 at the
    returned state, and jax.jacfwd to rounding; each sample depends on its own time only."""
    inertia, mass, com, w0, q0, _, _ = _setup(name, samples=2)
    ts, jacobians = _time_jacobians()
    reverse, forward = jacobians[name]  # (7 samples, 7, 7 times)
    np.testing.assert_allclose(reverse, forward, rtol=1e-12, atol=1e-12 * np.max(np.abs(forward)))
    off_diagonal = ~np.eye(len(ts), dtype=bool)
    assert np.all(np.moveaxis(reverse, 2, 1)[off_diagonal] == 0)
    rates = reverse[np.arange(len(ts)), :, np.arange(len(ts))]
    # The state by the closed form's program of the value tests above (SAMPLES samples: the times,
    # then the last repeated); evaluated op by op instead it compiled hundreds of small programs.
    w, q = exact(inertia, mass, com, w0, q0, np.pad(ts, (0, SAMPLES - len(ts)), mode="edge"), direct=True)
    w, q = w[: len(ts)], q[: len(ts)]
    qw, qx, qy, qz = q.T
    vertical = np.stack(
        [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), qw * qw - qx * qx - qy * qy + qz * qz], -1
    )
    torque = np.cross(vertical, mass * G * np.asarray(com))
    w_rate = (np.cross(inertia * w, w) + torque) / inertia
    q_rate = 0.5 * quat_multiply(q, np.concatenate([np.zeros((len(ts), 1)), w], -1))
    scale = np.max(np.abs(w_rate))
    np.testing.assert_allclose(rates[:, :3], w_rate, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(rates[:, 3:], q_rate, rtol=1e-9, atol=1e-9 * np.max(np.abs(q_rate)))


def _tensor_reference(tensor, mass, com, omega0, q0, ts):
    """DOP853 of the heavy top in the tensor's own body axes, no principal axes:
    ``J w' = (J w) x w + (R^T Z) x (m g com)``."""
    inverse, c = np.linalg.inv(tensor), mass * G * np.asarray(com, float)

    def accel(t, w, q):
        qw, qx, qy, qz = q
        up = [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), qw * qw - qx * qx - qy * qy + qz * qz]
        return inverse @ (np.cross(tensor @ w, w) + np.cross(up, c))

    return dop853(accel, omega0, ts, q0, omega_scale=max(np.linalg.norm(omega0), 1e-3))


@pytest.mark.parametrize(
    "moments, length",
    [
        ((1.0, 1.0, 0.5), 0.3),  # the odd moment the smallest (a long top)
        ((1.0, 1.0, 0.5), -0.3),  # hanging below the pivot
        ((1.0, 1.0, 1.8), 0.2),  # the odd moment the largest (a flat top)
        ((1.0, 1.0, 0.5), 0.0),  # centre of mass at the pivot: the axes from the moments
        ((1.0, 1.0, 1.8), 0.0),
        ((1.0, 1.0, 1.0), 0.3),  # a sphere about the pivot: the axis from com alone
    ],
)
def test_a_top_given_as_a_tensor(moments, length):
    """A Lagrange top given by its tensor about the pivot in tilted body axes (as composite_inertia
    gives one) takes the closed form in the axes of its symmetry; the reference integrates the tensor
    in the body axes (scipy DOP853). A derivative with respect to the tensor or com is refused; one
    with respect to the mass works and matches central differences."""
    turn = Rotation.from_rotvec([0.4, -0.7, 0.9]).as_matrix()
    tensor = turn @ np.diag(moments) @ turn.T
    com = turn @ np.array([0.0, 0.0, length])
    omega0 = turn @ np.array([0.3, 0.1, 4.0])
    q0 = euler_zxz([0.1, 0.6, 0.2])
    ts = np.linspace(0.0, 5.0, 41)
    top = rj.HeavyTop(jnp.asarray(tensor), 1.0, jnp.asarray(com))
    traj = rj.simulate(top, rj.State(jnp.asarray(omega0), jnp.asarray(q0)), jnp.asarray(ts), accuracy="exact")
    w_ref, q_ref = _tensor_reference(tensor, 1.0, com, omega0, q0, ts)
    assert np.all(np.asarray(traj.success))
    assert np.max(np.abs(np.asarray(traj.omega) - w_ref)) <= 1e-9 * np.max(np.abs(w_ref))
    assert np.max(np.abs(np.asarray(traj.orientation) - q_ref)) <= 1e-9
    if length != 0.3 or moments != (1.0, 1.0, 0.5):
        return

    def loss(tensor, mass, com):
        top = rj.HeavyTop(tensor, mass, com)
        state = rj.State(jnp.asarray(omega0), jnp.asarray(q0))
        return jnp.sum(rj.simulate(top, state, jnp.asarray(ts[:3]), accuracy="exact").omega[-1] ** 2)

    args = (jnp.asarray(tensor), jnp.asarray(1.0), jnp.asarray(com))
    for argnum in (0, 2):
        with pytest.raises(ValueError, match="no derivative with respect to them"):
            jax.grad(loss, argnums=argnum)(*args)
    grad = jax.grad(loss, argnums=1)(*args)
    expected = central_difference(lambda m: float(loss(args[0], m, args[2])), 1.0, 1e-5)
    np.testing.assert_allclose(float(grad), expected, rtol=1e-7)
