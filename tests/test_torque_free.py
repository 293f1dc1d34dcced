"""Closed-form torque-free motion against high-precision integration, closed forms and invariants."""

import functools

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest
import sympy as sp
from helpers import (
    central_difference,
    counted_calls,
    dop853,
    dop853_free_body,
    perturbed_inertia,
    perturbed_omega,
    quat_axis_angle,
    quat_multiply,
    random_quaternions,
    separatrix,
    variational_dop853,
)
from scipy.spatial.transform import Rotation

import rigidjax as rj
from rigidjax import torque_free_motion, torque_free_omega, torque_free_period
from rigidjax._closed_form.precession import (  # the third-kind integral itself
    _precession_parts,
    _precession_phase,
)

omega_at = jax.jit(torque_free_omega)


def dop853_omega(inertia, omega0, ts):
    """omega by DOP853 at rtol = 1e-13, atol = 1e-14 (in rad/s)."""
    return dop853_free_body(inertia, omega0, ts, atol=1e-14)[0]


# (inertia, omega0): both sides of the separatrix, axes in every order (odd and even relabellings),
# symmetric tops (prolate and oblate), the HLW body.
CASES = [
    ([1.0, 2.0, 2.5], [3.0, 0.1, 0.2]),
    ([1.0, 2.0, 2.5], [0.1, 0.2, 3.0]),
    ([2.5, 1.0, 2.0], [0.2, 3.0, 0.1]),
    ([2.0, 1.0, 2.5], [0.3, -0.5, 1.0]),
    ([2.0, 2.5, 1.0], [-0.7, 0.4, 0.9]),
    ([2.0, 2.0, 3.0], [0.3, 0.0, 5.0]),
    ([3.0, 2.0, 2.0], [1.0, 0.3, 0.2]),
    ([2 / 3, 1 / 2, 2 / 5], [np.cos(1.1) * 1.5, 0.0, np.sin(1.1) * 2.5]),
]


@pytest.mark.parametrize("inertia, omega0", CASES)
def test_matches_dop853(inertia, omega0):
    inertia, omega0 = np.array(inertia), np.array(omega0)
    ts = np.linspace(0.0, 20.0, 81)
    exact = np.asarray(omega_at(jnp.asarray(inertia), jnp.asarray(omega0), jnp.asarray(ts)))
    np.testing.assert_allclose(exact, dop853_omega(inertia, omega0, ts), atol=1e-11 * np.linalg.norm(omega0))


def test_exactly_on_the_separatrix_one_side_per_body():
    """Reference: the heteroclinic solution (sech, tanh; ``helpers.separatrix``, 40-digit mpmath). I = (1,
    2.5, 3) puts omega0 = (d1, w2, d3) with |d1| = |d3| exactly on the separatrix in floating point;
    where XLA fuses the multiply-adds of L^2 - 2 E I2, its two terms' cancellation leaves the sign of
    one product's roundoff, and every part of the solution must still take the same side (it once took
    both: omega3 started with the sign of omega1). All sign combinations, perturbations whose squares
    round, the axes relabelled; omega(0) = omega0, and the motion through the flip. On the stable
    manifold roundoff grows like cosh(lam t) (the closest approach, then away from the axis; no float
    method follows it), hence the bound."""
    base = np.array([1.0, 2.5, 3.0])
    cases = []
    for d in (1e-8, 1e-3, 0.3, 0.7):
        for s1, s2, s3 in ((1, 1, 1), (-1, 1, 1), (1, -1, 1), (1, 1, -1), (-1, -1, 1), (-1, 1, -1)):
            cases.append((s1 * d, s2 * 1.0, s3 * d))
    omega_sorted = np.array(cases)
    ts = np.linspace(0.0, 60.0, 13)
    lam = np.array([separatrix(base, w, ts[:1])[2] for w in omega_sorted])
    bound = 1e-14 * np.cosh(lam[:, None, None] * ts[:, None])
    # An odd relabelling of the axes flips the cross product in Euler's equations: in those axes the
    # same numbers move as the sorted body does backwards in time.
    for order, sense in (((0, 1, 2), 1), ((2, 1, 0), -1), ((1, 2, 0), 1)):
        order = list(order)
        inertia = np.tile(base[order], (len(cases), 1))
        omega0 = omega_sorted[:, order]
        expected = np.stack([separatrix(base, w, sense * ts)[0] for w in omega_sorted])[..., order]
        omega = np.asarray(omega_at(inertia[:, None], omega0[:, None], ts[None, :]))
        np.testing.assert_array_equal(np.sign(omega[:, 0]), np.sign(omega0))
        np.testing.assert_allclose(omega[:, 0], omega0, rtol=1e-15)
        motion = np.asarray(torque_free_motion(inertia[:, None], omega0[:, None], Q0, ts[None, :])[0])
        traj = np.asarray(rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts, accuracy="exact").omega)
        for result in (omega, motion, traj):
            assert np.all(np.abs(result - expected) < bound), np.max(np.abs(result - expected) / bound)


@pytest.mark.slow
def test_near_separatrix_against_30_digit_integration():
    """DOP853 at 1e-13 is off by 2.5e-11 here; the closed form agrees with mpmath's 30-digit Taylor
    integration to roundoff."""
    mp.mp.dps = 30
    I = [mp.mpf(1), mp.mpf(2), mp.mpf("2.5")]

    def f(t, w):
        return [
            (I[1] - I[2]) * w[1] * w[2] / I[0],
            (I[2] - I[0]) * w[2] * w[0] / I[1],
            (I[0] - I[1]) * w[0] * w[1] / I[2],
        ]

    solution = mp.odefun(f, 0, [mp.mpf("0.05"), mp.mpf(4), mp.mpf("0.05")])
    # Both times in one call at 81 samples (the rest repeat the last), as test_matches_dop853: its
    # compiled program (omega is evaluated sample by sample).
    times = [7.0, 20.0]
    ts = np.pad(times, (0, 81 - len(times)), mode="edge")
    exact = np.asarray(omega_at(jnp.array([1.0, 2.0, 2.5]), jnp.array([0.05, 4.0, 0.05]), jnp.asarray(ts)))
    for k, t in enumerate(times):
        reference = np.array([float(v) for v in solution(t)])
        np.testing.assert_allclose(exact[k], reference, atol=4 * 1e-14)


def test_symmetric_top_and_period():
    I1, I3, w0 = 2.0, 3.0, np.array([0.3, -0.1, 5.0])
    ts = np.linspace(0.0, 10.0, 81)  # 81 samples, as test_matches_dop853: its compiled program
    exact = np.asarray(omega_at(jnp.array([I1, I1, I3]), jnp.asarray(w0), jnp.asarray(ts)))
    Omega = (I3 - I1) / I1 * w0[2]
    transverse = (w0[0] + 1j * w0[1]) * np.exp(1j * Omega * ts)
    np.testing.assert_allclose(exact[:, 0] + 1j * exact[:, 1], transverse, atol=1e-14)
    np.testing.assert_allclose(exact[:, 2], w0[2], rtol=1e-15)
    period = float(torque_free_period(jnp.array([I1, I1, I3]), jnp.asarray(w0)))
    np.testing.assert_allclose(period, 2 * np.pi / Omega, rtol=1e-14)


def test_hairer_lubich_wanner_period_and_half_period_flip():
    inertia = jnp.array([2 / 3, 1 / 2, 2 / 5])
    omega0 = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)]) / inertia
    period = float(torque_free_period(inertia, omega0))
    assert abs(period - 10.73147) < 5e-6  # the published value, 7 digits
    ts = jnp.linspace(0.0, 3.0, 81)  # 81 samples, as test_matches_dop853: its compiled program
    now = np.asarray(omega_at(inertia, omega0, ts))
    later = np.asarray(omega_at(inertia, omega0, (ts + period)))
    half = np.asarray(omega_at(inertia, omega0, (ts + period / 2)))
    np.testing.assert_allclose(later, now, atol=1e-12)
    # Half a period on, the components along axes a (cn) and b (sn) flip sign, axis c (dn) does not.
    # Here L^2 = 1 < 2 E I2 = 1.148, so omega circles the axis of the SMALLEST moment (body z, 2/5):
    # c is body z, b is body y, a is body x.
    np.testing.assert_allclose(half[:, 0], -now[:, 0], atol=1e-12)
    np.testing.assert_allclose(half[:, 1], -now[:, 1], atol=1e-12)
    np.testing.assert_allclose(half[:, 2], now[:, 2], atol=1e-12)
    assert np.all(now[:, 2] > 0)


def test_flip_timing_against_dop853_events():
    """References: the period 4 K(m) / lambda of Landau & Lifshitz in 30-digit mpmath, and scipy's
    DOP853 (rtol 1e-12) with an event at every sign change of the intermediate axis's component for
    the next flip. motion_timing (simulate orders bodies by it) on both sides of the separatrix, near
    it, with negative components, axes in every order, from every quarter of the period; inf and 0
    where the body does not flip. Near the separatrix the integrated crossing times carry the
    saddle's conditioning (6e-8 relative measured at s = 4e-10), hence their looser tolerance."""
    from scipy.integrate import solve_ivp

    from rigidjax._closed_form.torque_free import motion_timing

    rng = np.random.default_rng(7)
    cases = [
        ([1.0, 2.0, 2.5], [0.05, 4.0, 0.05]),  # the tennis racket, circling the largest axis
        ([1.0, 2.0, 2.5], [2.0, 0.5, 0.3]),  # circling the smallest axis
        ([2.5, 1.0, 2.0], [-0.3, 0.7, 1.5]),  # axes relabelled
        ([2.0, 2.5, 1.0], [0.4, -1.0, 0.2]),
        ([1.0, 2.0, 3.0], [1e-4, 2.0, 1e-4]),  # s = +1.5e-9 from the separatrix
        ([3.0, 2.0, 1.0], [-0.5e-4, 2.0, 1e-4]),
    ]
    cases += [(rng.uniform(1.0, 3.0, 3), rng.normal(size=3)) for _ in range(10)]
    inertia = np.array([c[0] for c in cases], float)
    omega0 = np.array([c[1] for c in cases], float)
    period, next_flip = (np.asarray(x) for x in motion_timing(jnp.asarray(inertia), jnp.asarray(omega0)))
    for k, (moments, w0) in enumerate(zip(inertia, omega0, strict=True)):
        middle = int(np.argsort(moments)[1])
        c = [(moments[1] - moments[2]) / moments[0], (moments[2] - moments[0]) / moments[1]]
        c.append((moments[0] - moments[1]) / moments[2])

        def euler(t, w, c=c):
            return [c[0] * w[1] * w[2], c[1] * w[2] * w[0], c[2] * w[0] * w[1]]

        def crossing(t, w, middle=middle):
            return w[middle]

        reference = float(_landau_lifshitz_period(moments, w0, with_turn=False))
        np.testing.assert_allclose(period[k], reference, rtol=1e-13, err_msg=str(k))
        sol = solve_ivp(
            euler, (0.0, 1.2 * reference), w0, method="DOP853", rtol=1e-12, atol=1e-14, events=crossing
        )
        times = sol.t_events[0]
        assert len(times) >= 2, (k, times)
        tolerance = 2e-7 if k in (4, 5) else 1e-9
        np.testing.assert_allclose(next_flip[k], times[0], rtol=tolerance, err_msg=str(k))
        np.testing.assert_allclose(next_flip[k] + period[k] / 2, times[1], rtol=tolerance, err_msg=str(k))
    # A spin about a principal axis, a sphere, the separatrix: no flip.
    still_i = jnp.array([[1.0, 2.0, 3.0], [2.0, 2.0, 2.0], [1.0, 2.5, 3.0]])
    still_w = jnp.array([[0.0, 0.0, 1.0], [0.3, 0.2, 0.1], [-1e-8, 1.0, 1e-8]])
    period, next_flip = motion_timing(still_i, still_w)
    assert np.all(np.isinf(np.asarray(period))) and np.all(np.asarray(next_flip) == 0.0)


def test_conserves_energy_and_momentum_to_roundoff_over_long_times():
    inertia = jnp.array([1.0, 2.0, 2.5])
    omega0 = jnp.array([0.05, 4.0, 0.05])
    ts = np.linspace(0.0, 1e4, 1001)
    # The 1001 samples in 13 calls of 81 (the last padded with the final time), as
    # test_matches_dop853: its compiled program (omega is evaluated sample by sample).
    rows = np.pad(ts, (0, 13 * 81 - len(ts)), mode="edge").reshape(13, 81)
    omega = jnp.concatenate([omega_at(inertia, omega0, jnp.asarray(row)) for row in rows])[: len(ts)]
    energy = rj.kinetic_energy(inertia, omega)
    L2 = jnp.sum(rj.angular_momentum(inertia, omega) ** 2, axis=-1)
    assert float(jnp.max(jnp.abs(energy / energy[0] - 1))) < 1e-12
    assert float(jnp.max(jnp.abs(L2 / L2[0] - 1))) < 1e-12


def test_steady_rotations_and_sphere():
    for inertia, omega0 in [
        ([1.0, 2.0, 2.5], [0.0, 4.0, 0.0]),  # the unstable equilibrium itself
        ([1.0, 2.0, 2.5], [3.0, 0.0, 0.0]),
        ([1.0, 2.0, 2.5], [0.0, 0.0, -3.0]),
        ([1.0, 1.0, 1.0], [1.0, 2.0, 3.0]),
        ([2.0, 2.0, 3.0], [0.6, 0.8, 0.0]),  # in the degenerate plane of a symmetric top
    ]:
        # 81 samples, as test_matches_dop853: its compiled program.
        out = np.asarray(omega_at(jnp.asarray(inertia), jnp.asarray(omega0), jnp.linspace(0.0, 50.0, 81)))
        np.testing.assert_allclose(out, np.broadcast_to(omega0, out.shape), atol=1e-14)


def _motion_state(inertia, omega0, q0, t):
    """omega and q of torque_free_motion side by side, ``(..., 7)``."""
    omega, q = torque_free_motion(inertia, omega0, q0, t)
    return jnp.concatenate([omega, q], axis=-1)


# d/d(inertia, omega0, t) of _motion_state for _N_BODIES bodies, one time each, in forward and in
# reverse mode: the derivative tests below share these two programs (the closed form's derivatives
# take seconds to compile, reverse mode the longer).
_N_BODIES = 7
_jacfwd = jax.jit(jax.jacfwd(_motion_state, argnums=(0, 1, 3)))
_jacrev = jax.jit(jax.jacrev(_motion_state, argnums=(0, 1, 3)))


@pytest.mark.parametrize(
    "inertia, omega0",
    [
        ([1.0, 2.0, 2.5], [0.0, 0.0, 1.3]),  # the largest axis
        ([1.0, 2.0, 2.5], [-0.9, 0.0, 0.0]),  # the smallest
        ([1.0, 2.0, 2.5], [0.0, 1.1, 0.0]),  # the intermediate: the perturbation grows
        ([1.0, 1.0, 1.0], [0.3, 1.0, -0.5]),  # a sphere
        ([2.0, 2.0, 1.0], [0.6, 0.8, 0.0]),  # a symmetric body about an axis of its degenerate plane
        ([1.0, 2.0, 2.5], [0.0, 0.0, 0.0]),  # at rest
        ([1.0, 2.0, 2.5], [0.0, 1e-17, 1.3]),  # off the largest axis by roundoff
        ([1.0, 2.0, 2.5], [-0.9, 1e-12, 0.0]),  # off the smallest axis by 1e-12
    ],
    ids=[
        "largest axis",
        "smallest axis",
        "intermediate axis",
        "sphere",
        "degenerate plane",
        "rest",
        "1e-17 off the largest axis",
        "1e-12 off the smallest axis",
    ],  # fmt: skip
)
def test_motion_derivatives_at_steady_rotations_are_the_perturbed_motions(inertia, omega0):
    """At a steady rotation the derivatives of omega(t) and q(t) in the moments and in omega0 (forward
    and reverse mode) are those of the motion a perturbation starts (a wobble; growth about the
    intermediate axis), not those of the uniform rotation, and so they are a hair off a stable axis,
    where the elliptic form's derivatives lose eps / offset (32 times their size at 1e-17): against
    central differences of DOP853 (rtol 1e-13) from perturbed starts; omega alone
    (torque_free_omega) too."""
    q0 = np.array([np.cos(0.4), 0.0, np.sin(0.4) * 0.6, np.sin(0.4) * 0.8])
    t = 1.5

    def reference(inertia, omega0):
        omega, q = dop853_free_body(inertia, omega0, [0.0, t], q0)
        return np.concatenate([omega[-1], q[-1]])

    inertia, omega0 = np.asarray(inertia), np.asarray(omega0)
    # The body in every row of the batch of the reverse-mode test below, at its shapes: the same two
    # compiled programs (jacfwd, jacrev) serve every case here and that test. Row 0's own block.
    batch = [np.tile(x, (_N_BODIES, 1)) for x in (inertia, omega0, q0)] + [np.full(_N_BODIES, t)]
    forward_all, backward_all = (f(*(jnp.asarray(x) for x in batch)) for f in (_jacfwd, _jacrev))
    forward, backward = ([np.asarray(j)[0, :, 0] for j in jac[:2]] for jac in (forward_all, backward_all))
    # omega alone: d/d(inertia, omega0) in one program (test_batches_and_gradients runs it too).
    omega_jacobians = jax.jacfwd(torque_free_omega, argnums=(0, 1))(
        jnp.asarray(inertia), jnp.asarray(omega0), jnp.asarray(t)
    )
    h = 1e-5
    for arg, (jac, jac_rev) in enumerate(zip(forward, backward, strict=True)):
        columns = []
        for k in range(3):
            step = np.zeros(3)
            step[k] = h
            plus = reference(*[(inertia, omega0)[j] + step * (j == arg) for j in (0, 1)])
            minus = reference(*[(inertia, omega0)[j] - step * (j == arg) for j in (0, 1)])
            columns.append((plus - minus) / (2 * h))
        numeric = np.stack(columns, -1)
        np.testing.assert_allclose(np.asarray(jac), numeric, rtol=0, atol=1e-7)
        np.testing.assert_allclose(np.asarray(jac_rev), np.asarray(jac), rtol=0, atol=1e-14)
        omega_alone = omega_jacobians[arg]
        np.testing.assert_allclose(np.asarray(omega_alone), numeric[:3], rtol=0, atol=1e-7)


@pytest.mark.slow
def test_batches_and_gradients():
    rng = np.random.default_rng(3)
    inertia = perturbed_inertia(rng, 4, 0.05)
    omega0 = rng.normal(size=(4, 3))
    ts = np.linspace(0.0, 5.0, 6)
    batch = np.asarray(
        omega_at(jnp.asarray(inertia)[:, None], jnp.asarray(omega0)[:, None], jnp.asarray(ts)[None, :])
    )
    assert batch.shape == (4, 6, 3)
    for i in range(4):
        np.testing.assert_allclose(batch[i], dop853_omega(inertia[i], omega0[i], ts), atol=1e-11)

    def final(inertia, omega0):
        return torque_free_omega(inertia, omega0, jnp.asarray(3.0))

    I0, w0 = jnp.asarray(inertia[0]), jnp.asarray(omega0[0])
    jac_I, jac_w = jax.jacfwd(final, argnums=(0, 1))(I0, w0)
    jac_I_rev, jac_w_rev = jax.jacrev(final, argnums=(0, 1))(I0, w0)
    np.testing.assert_allclose(jac_I, jac_I_rev, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(jac_w, jac_w_rev, rtol=1e-9, atol=1e-12)
    dI = central_difference(lambda I: final(I, w0), I0, h=1e-6)
    dw = central_difference(lambda w: final(I0, w), w0, h=1e-6)
    np.testing.assert_allclose(np.asarray(jac_I), dI, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(np.asarray(jac_w), dw, rtol=1e-6, atol=1e-8)


def test_float32():
    ts = np.linspace(0.0, 5.0, 11).astype(np.float32)
    out = omega_at(np.array([1.0, 2.0, 2.5], np.float32), np.array([3.0, 0.1, 0.2], np.float32), ts)
    assert out.dtype == jnp.float32
    reference = dop853_omega(np.array([1.0, 2.0, 2.5]), np.array([3.0, 0.1, 0.2]), ts.astype(np.float64))
    np.testing.assert_allclose(np.asarray(out, np.float64), reference, atol=3e-5)


@pytest.mark.slow
def test_simulate_exact_switches_to_the_closed_form():
    """accuracy="exact" is one word away from integration and agrees with it on a racket batch."""
    rng = np.random.default_rng(0)
    inertia = jnp.asarray(perturbed_inertia(rng, 16, 0.05))
    omega0 = jnp.asarray(perturbed_omega(rng, 16, 0.01))
    ts = jnp.linspace(0.0, 20.0, 41)
    exact = rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts, accuracy="exact")
    precise = rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts, accuracy="precise")
    assert exact.omega.shape == (16, 41, 3) and bool(jnp.all(exact.success))
    np.testing.assert_allclose(np.asarray(exact.omega), np.asarray(precise.omega), atol=1e-7)
    assert float(jnp.max(exact.invariants()["energy"])) < 1e-13
    # Time is measured from ts[0].
    shifted = rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts + 100.0, accuracy="exact")
    np.testing.assert_allclose(np.asarray(shifted.omega), np.asarray(exact.omega), atol=1e-12)
    # An asymmetric heavy top has no closed form: the error says which condition fails.
    with pytest.raises(ValueError, match="I1 = I2"):
        rj.simulate(
            rj.HeavyTop(inertia[0], 1.0, jnp.array([0.0, 0.0, 0.1])),
            rj.State(omega0[0], jnp.array([1.0, 0, 0, 0])),
            ts,
            accuracy="exact",
        )
    # One body beyond the flat plate in the same batch: the exact program above (16 bodies) checks it.
    with pytest.raises(Exception, match="triangle"):
        rj.simulate(
            rj.FreeBody(inertia.at[5].set(jnp.array([1.0, 2.0, 4.0]))), rj.State(omega0), ts, accuracy="exact"
        ).omega.block_until_ready()


# --------------------------------------------------------------------------------------------------
# Orientation: torque_free_motion

# Every value test below calls this with inertia/omega0 (8, 1, 3), q0 (8, 1, 4) and ts (8, 41): one compile.
motion_at = jax.jit(torque_free_motion)
N_CASES, N_TIMES = 8, 41


def unit(q):
    q = np.asarray(q, float)
    return q / np.linalg.norm(q)


Q0 = unit([0.8, 0.2, -0.4, 0.4])


def run_cases(inertia, omega0, q0, ts):
    inertia, omega0, q0, ts = (np.asarray(x, float) for x in (inertia, omega0, q0, ts))
    assert inertia.shape == (N_CASES, 3) and ts.shape == (N_CASES, N_TIMES)
    q0 = np.broadcast_to(q0.reshape(-1, 4), (N_CASES, 4))
    omega, q = motion_at(
        jnp.asarray(inertia[:, None]), jnp.asarray(omega0[:, None]), jnp.asarray(q0[:, None]), jnp.asarray(ts)
    )
    return np.asarray(omega), np.asarray(q)


def dop853_motion(inertia, omega0, q0, ts):
    """Euler's equations with dq/dt = q (0, omega) / 2 by DOP853 at rtol = atol = 1e-13, in units with
    max(I) = 1 and |omega0| = 1 (the equations keep their form), so SI-scale bodies are fine too."""
    scale = np.linalg.norm(omega0)
    return dop853_free_body(inertia, omega0, ts, q0, time_scale=scale, omega_scale=scale)


EARTH = np.array([8.0101e37, 8.0103e37, 8.0365e37])  # kg m^2, (C - A) / A = 3.3e-3
EARTH_SPIN = 7.292115e-5 * np.array([3e-6, -2e-6, 1.0])  # rad/s, with a small polar wobble

# Both sides of the separatrix, relabelled axes (odd and even), near it (s = 8e-5), symmetric tops,
# the Earth in SI units, a flat plate (I3 = I1 + I2) on both sides.
DOP_CASES = [
    ([1.0, 2.0, 2.5], [3.0, 0.1, 0.2]),
    ([1.0, 2.0, 2.5], [0.1, 0.2, 3.0]),
    ([2.5, 1.0, 2.0], [0.2, 3.0, 0.1]),
    ([2.0, 2.5, 1.0], [-0.7, 0.4, 0.9]),
    ([1.0, 2.0, 3.0], [0.05, 4.0, -0.05]),
    ([2.0, 2.0, 3.0], [0.3, -0.4, 5.0]),
    (EARTH, EARTH_SPIN),
    ([1.0, 2.0, 3.0], [0.6, 0.8, 1.5]),
]


@pytest.mark.slow
def test_orientation_matches_dop853():
    inertia = np.array([c[0] for c in DOP_CASES])
    omega0 = np.array([c[1] for c in DOP_CASES])
    # Three periods of omega or more; for the Earth 1.1 Euler periods (350 turns: DOP853 costs 10 s
    # per thousand turns at this tolerance).
    horizon = np.array([12.0, 12.0, 12.0, 40.0, 30.0, 10.0, 3.0e7, 15.0])
    ts = np.linspace(0.0, 1.0, N_TIMES)[None, :] * horizon[:, None]
    omega, q = run_cases(inertia, omega0, Q0, ts)
    for i in range(N_CASES):
        w_ref, q_ref = dop853_motion(inertia[i], omega0[i], Q0, ts[i])
        np.testing.assert_allclose(omega[i], w_ref, atol=1e-10 * np.linalg.norm(omega0[i]), err_msg=str(i))
        # Same sign as the integrated quaternion: q(t) is continuous with q(0) = q0.
        np.testing.assert_allclose(q[i], q_ref, atol=1e-10, err_msg=str(i))
    # the flat plate on the other side of the separatrix
    w0 = np.array([2.0, 0.5, 0.3])
    ts = np.linspace(0.0, 20.0, N_TIMES)
    omega, q = run_cases(np.tile([1.0, 2.0, 3.0], (8, 1)), np.tile(w0, (8, 1)), Q0, np.tile(ts, (8, 1)))
    w_ref, q_ref = dop853_motion([1.0, 2.0, 3.0], w0, Q0, ts)
    np.testing.assert_allclose(q[0], q_ref, atol=1e-10)
    np.testing.assert_allclose(omega[0], w_ref, atol=1e-10 * np.linalg.norm(w0))


def space_momentum(inertia, omega, q):
    """R(q) I omega with scipy's rotation (scalar-first input)."""
    flat_q = q.reshape(-1, 4)
    flat_l = (inertia * omega).reshape(-1, 3)
    return Rotation.from_quat(flat_q, scalar_first=True).apply(flat_l).reshape(omega.shape)


def test_symmetric_tops_and_steady_rotations_in_closed_form():
    """Symmetric tops: R(t) = Rot(L_space, |L| t / I1) R0 Rot(e_sym, -Omega t), Omega = (I3 - I1) w3 / I1.
    Steady rotations (any principal axis, the intermediate one included; a sphere; the degenerate plane
    of a symmetric top; omega0 = 0): R(t) = R0 Rot(omega0, |omega0| t)."""
    cases = [
        ([2.0, 2.0, 3.0], [0.3, -0.4, 5.0], 2),  # oblate, symmetry axis z
        ([2.0, 1.0, 2.0], [0.1, 3.0, 0.2], 1),  # prolate, symmetry axis y (the odd moment is smallest)
        ([1.5, 1.5, 1.5], [1.0, 2.0, 3.0], None),  # sphere
        ([1.0, 2.0, 3.0], [3.0, 0.0, 0.0], None),
        ([1.0, 2.0, 3.0], [0.0, 4.0, 0.0], None),  # the unstable equilibrium
        ([1.0, 2.0, 3.0], [0.0, 0.0, -3.0], None),
        ([1.0, 2.0, 3.0], [0.0, 0.0, 0.0], None),
        ([2.0, 2.0, 3.0], [0.6, 0.8, 0.0], None),  # in the degenerate plane
    ]
    inertia = np.array([c[0] for c in cases])
    omega0 = np.array([c[1] for c in cases])
    ts = np.tile(np.linspace(0.0, 20.0, N_TIMES), (N_CASES, 1))
    omega, q = run_cases(inertia, omega0, Q0, ts)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(omega))
    for i, (I, w0, axis) in enumerate(cases):
        I, w0 = np.array(I), np.array(w0)
        if axis is None:
            expected = quat_multiply(
                Q0, quat_axis_angle(w0 if np.any(w0) else [1.0, 0, 0], np.linalg.norm(w0) * ts[i])
            )
            np.testing.assert_allclose(omega[i], np.broadcast_to(w0, omega[i].shape), atol=1e-15)
        else:
            I_eq = I[(axis + 1) % 3]
            L_space = Rotation.from_quat(Q0, scalar_first=True).apply(I * w0)
            Omega = (I[axis] - I_eq) / I_eq * w0[axis]
            e_sym = np.eye(3)[axis]
            expected = quat_multiply(
                quat_multiply(quat_axis_angle(L_space, np.linalg.norm(L_space) / I_eq * ts[i]), Q0),
                quat_axis_angle(e_sym, -Omega * ts[i]),
            )
        np.testing.assert_allclose(q[i], expected, atol=2e-14, err_msg=str(i))


def _landau_lifshitz_period(inertia, omega0, dps=30, with_turn=True):
    """The period P of omega and the angle by which the body turns about the space-frame L in one period.

    Independent of rigidjax: Landau & Lifshitz's solution in mpmath, with the axes relabelled so that
    omega circles axis 3 (w3 = A3 dn(lambda t | m)), and dphi/dt = |L| (2E - I3 w3^2) / (L^2 - I3^2 w3^2)
    integrated over tau = lambda t in [0, 4K] by mpmath's quadrature (the phase does not matter over a
    whole period). 30 digits: near the separatrix 1 - m loses as many digits as it is small.
    ``with_turn=False``: the period alone.
    """
    with mp.workdps(dps):
        I = [mp.mpf(float(x)) for x in inertia]
        w = [mp.mpf(float(x)) for x in omega0]
        L2 = sum(I[i] ** 2 * w[i] ** 2 for i in range(3))
        E2 = sum(I[i] * w[i] ** 2 for i in range(3))
        order = sorted(range(3), key=lambda i: I[i])
        if L2 < E2 * I[order[1]]:
            order = order[::-1]  # omega circles the axis of the smallest moment
        I1, I2, I3 = (I[i] for i in order)
        lam = mp.sqrt((I3 - I2) * (L2 - E2 * I1) / (I1 * I2 * I3))
        m = (I2 - I1) * (E2 * I3 - L2) / ((I3 - I2) * (L2 - E2 * I1))
        A3sq = (L2 - E2 * I1) / (I3 * (I3 - I1))
        K = mp.ellipk(m)
        if not with_turn:
            return 4 * K / lam

        def rate(tau):
            w3sq = A3sq * mp.ellipfun("dn", tau, m) ** 2
            return mp.sqrt(L2) * (E2 - I3 * w3sq) / (L2 - I3**2 * w3sq)

        # dn^2 is even about 0 and about K: the period is four copies of [0, K].
        turn = 4 * mp.quad(rate, [0, K]) / lam
        return 4 * K / lam, turn


@pytest.mark.slow
def test_conservation_and_long_times():
    """Over 1e4 periods: |q| = 1 and the space-frame L constant to roundoff, and the orientation equals
    Rot(L_space, N dphi) q(t) after N whole periods, dphi the precession per period from mpmath."""
    cases = [
        ([1.0, 2.0, 2.5], [3.0, 0.1, 0.2]),
        ([2.0, 2.5, 1.0], [-0.7, 0.4, 0.9]),
        ([1.0, 2.0, 3.0], [1e-4, 2.0, 1e-4]),  # s = +1.5e-9
        ([3.0, 2.0, 1.0], [-0.5e-4, 2.0, 1e-4]),  # s = -4e-10, odd relabelling
        (EARTH, EARTH_SPIN),
        ([1.0, 2.0, 3.0], [0.6, 0.8, 1.5]),  # flat plate
        ([1.0, 2.5, 3.0], [0.5, 1.0, 0.5]),  # exactly on the separatrix: L^2 = 2 E I2 in floating point
        ([1.0, 2.0, 2.0 + 1e-3], [0.1, 0.2, 3.0]),  # nearly symmetric about b-c: n = 2000
    ]
    inertia = np.array([c[0] for c in cases], float)
    omega0 = np.array([c[1] for c in cases], float)
    n_periods = 10_000
    refs = {}
    ts = np.zeros((N_CASES, N_TIMES))
    for i in range(N_CASES):
        if i == 6:  # infinite period: just a long time
            ts[i] = np.linspace(0.0, 1e3, N_TIMES)
            continue
        period, turn = _landau_lifshitz_period(inertia[i], omega0[i])
        start = np.linspace(0.0, float(period), 20)
        ts[i] = np.concatenate([start, float(n_periods * period) + start, [float(n_periods * period * 1.5)]])
        refs[i] = float(mp.fmod(n_periods * turn, 4 * mp.pi))
    omega, q = run_cases(inertia, omega0, Q0, ts)
    assert np.max(np.abs(np.linalg.norm(q, axis=-1) - 1)) < 1e-15 * 4
    L_space = space_momentum(inertia[:, None], omega, q)
    L0 = space_momentum(inertia, omega0, np.broadcast_to(Q0, (N_CASES, 4)))
    size = np.linalg.norm(L0, axis=-1)[:, None, None]
    assert np.max(np.abs(L_space - L0[:, None]) / size) < 2e-14 * 5
    energy = np.sum(inertia[:, None] * omega**2, axis=-1)
    assert np.max(np.abs(energy / energy[:, :1] - 1)) < 1e-13
    for i, angle in refs.items():
        n_hat = L0[i] / np.linalg.norm(L0[i])
        later = quat_multiply(quat_axis_angle(n_hat, angle), q[i, :20])
        # q and -q are the same rotation. q's conditioning in t is eps |omega| t: 1e-11 for the unit
        # bodies, 4e-9 for the Earth (1.9e7 rad of spin in 1e4 Euler periods).
        err = np.minimum(np.abs(q[i, 20:40] - later).max(), np.abs(q[i, 20:40] + later).max())
        assert err < 1e-11 + 10 * np.finfo(float).eps * np.linalg.norm(omega0[i]) * ts[i, 39], (i, err)


def test_third_kind_integral_against_mpmath():
    """G(tau) = Pi(-n; am tau | m) = g tau + c V from theta products (both nomes, the imaginary shift
    from 0 and from K') vs mpmath's ellippi, and the reduced phase rho (Carlson forms, direct and
    measured from K) vs mpmath's ellipf: from m = 0 to 1 - m = 1e-14, the separatrix, n up to 3000;
    and the half-period continuation for cn < 0."""
    grid = [
        (phi, p, n)
        for phi in [0.05, -0.6, 0.78, 0.79, 1.2, 1.5707, 2.0, -2.9]
        for p in [1.0, 0.9, 0.5, 0.3, 1e-3, 1e-8, 1e-14, 0.0]
        for n in [0.0, 1e-6, 0.3, 30.0, 3000.0]
        if not (p == 0 and abs(phi) > np.pi / 2)  # K = inf: no half period
    ]
    phi, p, n = (np.array(x) for x in zip(*grid, strict=True))
    m = 1 - p
    nu = np.where(m > 0, n / np.where(m > 0, m, 1.0), np.where(n > 0, np.inf, 0.0))
    sn, cn = np.sin(phi), np.cos(phi)
    dn = np.sqrt(cn**2 + p * sn**2)

    @jax.jit
    def integrals(sn, cn, dn, m, p, n, nu):
        body = _precession_parts(m, p, n, nu, (sn, cn, dn))
        turns = jnp.where(cn < 0, jnp.sign(sn), 0.0)  # tau = rho + 2 j K with j = 0 or +-1
        rho = body["rho0"]
        quarter = jnp.where(p > 0, body["quarter"], 1.0)  # K = inf on the separatrix
        tau = rho + 2 * turns * quarter
        g = body["slope"] * tau + body["c"] * _precession_phase(rho, turns, body)
        quarter_g = body["slope"] * quarter + body["c"] * _precession_phase(quarter, 0.0, body)
        return tau, g, quarter_g

    out = integrals(*(jnp.asarray(x) for x in (sn, cn, dn, m, p, n, nu)))
    tau, g, quarter_g = (np.asarray(x).tolist() for x in out)
    with mp.workdps(30):
        for k, (ph, pp, nn) in enumerate(grid):
            mm = 1 - mp.mpf(pp)
            ref_f = mp.ellipf(ph, mm)
            ref_g = mp.ellippi(-nn, ph, mm)
            size = mp.ellipk(mm) if pp > 0 else abs(ref_f) + 1
            # Absolute errors of a few ulp of K.
            assert abs(tau[k] - ref_f) < 1e-15 * size, (ph, pp, nn, float(tau[k] - ref_f))
            assert abs(g[k] - ref_g) < 2e-15 * size, (ph, pp, nn, float(g[k] - ref_g))
            if pp > 0:
                # 1 - c Im Z(i beta) cancels for m < 1/2 and n >> 1: ~eps sqrt(n) relative.
                tolerance = 2e-15 * (1 if pp < 0.5 else np.sqrt(1 + nn))
                assert abs(float(quarter_g[k]) / mp.ellippi(-nn, mm) - 1) < tolerance, (pp, nn)


def _final_state(inertia, omega0):
    # Two sample times: the body's arrays keep their own shape against t (K, G(K), the initial phase,
    # the AGM computed once per body), and the derivatives, d/d inertia included, must follow.
    omega, q = torque_free_motion(inertia, omega0, jnp.asarray(Q0), jnp.asarray([3.0, 1.0]))
    return jnp.concatenate([omega, q], axis=-1)  # (2, 7)


@jax.jit
def directional_derivative(inertia, omega0, d_inertia, d_omega0):
    """A column combination of jacfwd: one jvp compiles 2.5x faster than the 6 columns."""
    return jax.jvp(_final_state, (inertia, omega0), (d_inertia, d_omega0))[1]


SEPARATRIX_OFFSETS = (0.0, 1e-12, -1e-12, 1e-10)


def _separatrix_start(offset):
    """inertia, omega0 and q0 of the body a relative ``offset`` from the separatrix."""
    omega0 = np.array([np.sqrt(3.0) * 1e-2 * (1 + offset), 1.0, 1e-2])  # L^2 = 2 E I_2 at offset 0
    return np.array([1.0, 2.0, 3.0]), omega0, unit([0.9, 0.1, -0.3, 0.2])


@functools.cache
def _separatrix_jacobians():
    """d q(T = 3) / d omega0 in reverse mode for every offset of SEPARATRIX_OFFSETS: one call of the
    derivative tests' shared program (_jacrev, _N_BODIES bodies; the rows past the offsets repeat
    the first), ``(4, 3)`` each."""
    starts = [_separatrix_start(offset) for offset in SEPARATRIX_OFFSETS]
    starts += starts[:1] * (_N_BODIES - len(starts))
    inertia, omega0, q0 = (jnp.asarray(np.stack(x)) for x in zip(*starts, strict=True))
    # np.full, not jnp.full: jnp.full(n, 3.0) is weakly typed, and a weak-typed argument is a new
    # signature for jit: _jacrev compiled a second time (its longest compile in this file).
    d_omega0 = np.asarray(
        _jacrev(inertia, omega0, q0, jnp.asarray(np.full(_N_BODIES, 3.0)))[1]
    )  # (7, 7, 7, 3)
    return {offset: d_omega0[k, 3:, k] for k, offset in enumerate(SEPARATRIX_OFFSETS)}


@pytest.mark.slow
@pytest.mark.parametrize("offset", SEPARATRIX_OFFSETS)
def test_orientation_derivatives_near_the_separatrix(offset):
    """d q(T) / d omega0 (reverse mode) of a body a relative ``offset`` from the separatrix (omega0_1
    scaled by 1 + offset; both sides, and on it to the last bit), against the variational equations
    integrated by scipy's DOP853 (rtol 1e-13; "precise" agrees with them to 2e-11). The initial
    phase measured back from K cancelled terms of size 1/p in its derivative: 6e-7 off at 1e-12,
    1.5e-8 at 1e-10, 1e-3 on the separatrix."""
    inertia, omega0, q0 = _separatrix_start(offset)
    T = 3.0
    got = _separatrix_jacobians()[offset]  # (4, 3)
    w, q = sp.symbols("w1:4"), sp.symbols("q0:4")
    I1, I2, I3 = inertia
    rhs = [(I2 - I3) * w[1] * w[2] / I1, (I3 - I1) * w[2] * w[0] / I2, (I1 - I2) * w[0] * w[1] / I3]
    rhs += [(-q[1] * w[0] - q[2] * w[1] - q[3] * w[2]) / 2, (q[0] * w[0] + q[2] * w[2] - q[3] * w[1]) / 2]
    rhs += [(q[0] * w[1] - q[1] * w[2] + q[3] * w[0]) / 2, (q[0] * w[2] + q[1] * w[1] - q[2] * w[0]) / 2]
    _, S = variational_dop853(rhs, [*w, *q], np.concatenate([omega0, q0]), np.eye(7, 3), T)
    np.testing.assert_allclose(got, S[3:], rtol=0, atol=1e-12 * np.max(np.abs(S[3:])))


def test_gradients_match_finite_differences_and_stay_finite():
    """Forward-mode derivatives w.r.t. inertia and omega0 (random directions, so every column of the
    Jacobian contributes) at two sample times vs central differences (h = 1e-6); finite at singular
    points."""
    rng = np.random.default_rng(11)
    h = 1e-6
    points = [
        ([1.0, 2.0, 2.5], [0.3, -0.5, 1.0]),
        ([2.5, 1.0, 2.0], [0.2, 3.0, 0.1]),  # relabelled axes, the other side of the separatrix
        ([2.0, 2.0, 3.0], [0.3, 0.1, 5.0]),  # exactly symmetric: d/dI breaks the symmetry
        (
            [1.0, 2.0, 2.9],
            [0.05, 4.0, -0.05],
        ),  # near the separatrix (off the flat plate: FD steps stay physical)
    ]
    zero = np.zeros(3)
    rows_I, rows_w, expected = [], [], []
    for I, w in points:
        I, w = np.array(I), np.array(w)
        for dI, dw in [(rng.normal(size=3), zero), (zero, rng.normal(size=3))]:
            rows_I += [I + h * dI, I - h * dI]
            rows_w += [w + h * dw, w - h * dw]
            expected.append(np.asarray(directional_derivative(*(jnp.asarray(x) for x in (I, w, dI, dw)))))
    ts = np.full((N_CASES, N_TIMES), 3.0)
    ts[:, 1] = 1.0
    rows_I, rows_w = np.array(rows_I), np.array(rows_w)
    values = []
    for k in (0, 8):  # the 16 shifted inputs in two calls of the shared (8, 41) shape, at t = 3 and 1
        omega, q = run_cases(rows_I[k : k + 8], rows_w[k : k + 8], Q0, ts)
        values.append(np.concatenate([omega[:, :2], q[:, :2]], axis=-1))
    values = np.concatenate(values)
    finite_differences = (values[0::2] - values[1::2]) / (2 * h)
    np.testing.assert_allclose(np.array(expected), finite_differences, rtol=1e-6, atol=1e-7)
    # Singular points (steady rotations, the exact separatrix, a sphere): finite.
    for I, w in [
        ([1.0, 2.0, 3.0], [0.0, 4.0, 0.0]),
        ([1.0, 2.0, 3.0], [0.0, 0.0, 2.0]),
        ([1.0, 2.0, 3.0], [0.0, 0.0, 0.0]),
        ([1.5, 1.5, 1.5], [1.0, 2.0, 3.0]),
        ([2.0, 2.0, 3.0], [0.6, 0.8, 0.0]),
        ([1.0, 2.5, 3.0], [0.5, 1.0, 0.5]),  # exactly on the separatrix
    ]:
        d = directional_derivative(
            jnp.array(I), jnp.array(w), *(jnp.asarray(rng.normal(size=3)) for _ in "Iw")
        )
        assert np.all(np.isfinite(np.asarray(d))), (I, w)


def test_orientation_batches_and_restart():
    """Broadcasting like torque_free_omega; restarting from a state on the trajectory continues it."""
    rng = np.random.default_rng(5)
    inertia = perturbed_inertia(rng, N_CASES, 0.1)
    omega0 = rng.normal(size=(N_CASES, 3))
    q0 = random_quaternions(rng, N_CASES)
    ts = np.tile(np.linspace(0.0, 10.0, N_TIMES), (N_CASES, 1))
    omega, q = run_cases(inertia, omega0, q0[:, None], ts)
    # Broadcasting (shapes only: tracing, no compile): one q0 for all bodies, times on their own axis.
    shape = jax.eval_shape(torque_free_motion, inertia[:, None], omega0[:, None], q0[0], ts[0])
    assert shape[0].shape == (N_CASES, N_TIMES, 3) and shape[1].shape == (N_CASES, N_TIMES, 4)
    assert jax.eval_shape(torque_free_motion, inertia[0], omega0[0], q0[0], 1.0)[1].shape == (4,)
    # q(t) of a state reached at t1, continued for t2, is q(t1 + t2) (up to sign).
    w1, q1 = omega[:, 10], q[:, 10]
    _, q2 = run_cases(inertia, w1, q1[:, None], ts - ts[:, 10:11])
    sign = np.sign(np.sum(q2[:, 10:] * q[:, 10:], axis=-1, keepdims=True))
    np.testing.assert_allclose(q2[:, 10:] * sign, q[:, 10:], atol=1e-13)


@pytest.mark.slow
def test_simulate_exact_returns_the_closed_form_orientation():
    rng = np.random.default_rng(2)
    inertia = perturbed_inertia(rng, N_CASES, 0.05)
    omega0 = perturbed_omega(rng, N_CASES, 0.3)
    q0 = random_quaternions(rng, N_CASES)
    ts = np.linspace(2.0, 22.0, N_TIMES)
    model, state = rj.FreeBody(jnp.asarray(inertia)), rj.State(jnp.asarray(omega0), jnp.asarray(q0))
    exact = rj.simulate(model, state, jnp.asarray(ts), accuracy="exact")
    assert exact.orientation.shape == (N_CASES, N_TIMES, 4)
    omega, q = run_cases(inertia, omega0, q0[:, None], np.tile(ts - ts[0], (N_CASES, 1)))
    np.testing.assert_allclose(np.asarray(exact.orientation), q, atol=1e-14)
    np.testing.assert_allclose(np.asarray(exact.omega), omega, atol=1e-14)
    invariants = exact.invariants()
    assert float(jnp.max(invariants["space_angular_momentum"])) < 1e-13
    # Nothing normalises the closed form's quaternions: |q| of the samples is 1 to rounding.
    assert exact.stats["quaternion_norm_error"] is None
    assert float(jnp.max(invariants["quaternion_norm"])) < 1e-15
    np.testing.assert_allclose(
        np.asarray(invariants["quaternion_norm"]),
        np.max(np.abs(np.linalg.norm(np.asarray(exact.orientation), axis=-1) - 1), axis=-1),
        rtol=0,
        atol=3e-16,
    )
    bad = rj.State(jnp.asarray(omega0), jnp.asarray(q0).at[3].multiply(1.1))
    with pytest.raises(Exception, match="unit quaternion"):
        rj.simulate(model, bad, jnp.asarray(ts), accuracy="exact").orientation.block_until_ready()


@pytest.mark.parametrize("n_times", [2, 7])
def test_simulate_exact_in_blocks_of_bodies_and_at_two_times(n_times):
    """Blocks of bodies (chunk_size) give the one-block values; with two sample times the first is
    the initial state itself and the second the closed form (torque_free_motion, called directly).
    Derivatives (at several sample times: the two-time program differs only in which samples it
    evaluates): forward mode through blocks along random directions equals the reverse-mode
    gradient without blocks (reverse mode through blocks compiles 2-3 times longer than either, and
    runs the same transposed code)."""
    rng = np.random.default_rng(5)
    inertia = perturbed_inertia(rng, 15, 0.05).reshape(3, 5, 3)
    omega0 = perturbed_omega(rng, 15, 0.3).reshape(3, 5, 3)
    q0 = 1.01 * random_quaternions(rng, 15).reshape(3, 5, 4)  # normalised by simulate's closed form
    ts = jnp.linspace(0.5, 9.5, n_times)
    model, state = rj.FreeBody(jnp.asarray(inertia)), rj.State(jnp.asarray(omega0), jnp.asarray(q0) / 1.01)
    whole = rj.simulate(model, state, ts, accuracy="exact")
    blocks = rj.simulate(model, state, ts, accuracy="exact", chunk_size=4)
    assert int(blocks.stats["chunk_size"]) == 4
    np.testing.assert_allclose(np.asarray(blocks.omega), np.asarray(whole.omega), rtol=0, atol=1e-14)
    np.testing.assert_allclose(
        np.asarray(blocks.orientation), np.asarray(whole.orientation), rtol=0, atol=1e-14
    )
    omega_only = rj.simulate(model, rj.State(state.omega), ts, accuracy="exact", chunk_size=4)
    np.testing.assert_allclose(np.asarray(omega_only.omega), np.asarray(whole.omega), rtol=0, atol=1e-14)
    # The closed form called directly at the seven times in both cases, by the value tests' program
    # (run_cases: the 15 bodies and the first again in two calls of 8, the seven times then the last
    # repeated): the two times are its first and last.
    seven = jnp.linspace(0.5, 9.5, 7)
    columns = np.arange(7) if n_times == 7 else np.array([0, 6])
    np.testing.assert_array_equal(np.asarray(seven - seven[0])[columns], np.asarray(ts - ts[0]))
    times = np.tile(np.pad(np.asarray(seven - seven[0]), (0, N_TIMES - 7), mode="edge"), (N_CASES, 1))
    bodies = [
        np.asarray(x).reshape(15, -1)[np.r_[0:15, 0]] for x in (inertia, state.omega, state.orientation)
    ]
    parts = [run_cases(*(x[k : k + 8] for x in bodies), times) for k in (0, 8)]
    omega, q = (
        np.concatenate(x)[:15][:, columns].reshape(3, 5, len(columns), -1) for x in zip(*parts, strict=True)
    )
    np.testing.assert_allclose(np.asarray(whole.omega), np.asarray(omega), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(whole.orientation), np.asarray(q), rtol=0, atol=1e-14)
    if n_times == 2:
        np.testing.assert_array_equal(np.asarray(whole.omega[..., 0, :]), omega0)
        unit = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
        np.testing.assert_allclose(np.asarray(whole.orientation[..., 0, :]), unit, rtol=0, atol=4e-16)
        return

    def loss(w, chunk_size):
        traj = rj.simulate(model, rj.State(w, state.orientation), ts, accuracy="exact", chunk_size=chunk_size)
        return jnp.sum(traj.orientation[..., -1, :] * jnp.arange(4.0)) + jnp.sum(traj.omega[..., -1, :] ** 2)

    grad_whole = np.asarray(jax.grad(loss)(state.omega, None))
    assert np.all(np.isfinite(grad_whole)) and np.max(np.abs(grad_whole)) > 1e-3
    for direction in rng.normal(size=(2,) + state.omega.shape):
        _, along = jax.jvp(lambda w: loss(w, 4), (state.omega,), (jnp.asarray(direction),))
        np.testing.assert_allclose(float(along), np.sum(grad_whole * direction), rtol=1e-12)


def test_simulate_exact_takes_an_inertia_tensor():
    """A body given by its inertia tensor (principal moments turned by a random rotation: a generic
    body, a symmetric top, a sphere, two moments 1e-9 apart) in closed form. Reference: scipy's
    DOP853 of Euler's equations with the full tensor in the body axes, ``J dw/dt = (J w) x w``, which
    knows no principal axes. The omega-only call gives the same omega; the derivative in omega0
    matches central differences; a derivative in the tensor itself is refused with the reason."""
    moments = np.array([[1.0, 2.0, 2.5], [2.0, 2.0, 3.0], [1.5, 1.5, 1.5], [1.0, 2.0, 2.0 + 1e-9]])
    axes = Rotation.random(4, random_state=3).as_matrix()
    tensors = np.einsum("nij,nj,nkj->nik", axes, moments, axes)
    rng = np.random.default_rng(7)
    omega0, q0 = rng.normal(size=(4, 3)), random_quaternions(rng, 4)
    ts = jnp.linspace(0.0, 10.0, 21)
    model = rj.FreeBody(jnp.asarray(tensors))
    traj = rj.simulate(model, rj.State(jnp.asarray(omega0), jnp.asarray(q0)), ts, accuracy="exact")
    assert bool(jnp.all(traj.success)) and traj.model.inertia.shape == (4, 3, 3)
    for i, (tensor, w0) in enumerate(zip(tensors, omega0, strict=True)):
        inverse = np.linalg.inv(tensor)
        w_ref, q_ref = dop853(lambda t, w, q, J=tensor, inv=inverse: inv @ np.cross(J @ w, w), w0, ts, q0[i])
        np.testing.assert_allclose(np.asarray(traj.omega[i]), w_ref, rtol=0, atol=1e-11 * np.linalg.norm(w0))
        np.testing.assert_allclose(np.asarray(traj.orientation[i]), q_ref, rtol=0, atol=1e-11)
    omega_only = rj.simulate(model, rj.State(jnp.asarray(omega0)), ts, accuracy="exact")
    np.testing.assert_allclose(np.asarray(omega_only.omega), np.asarray(traj.omega), rtol=0, atol=1e-14)

    first = jnp.asarray(tensors[0])

    def loss(w, tensor=first):
        motion = rj.simulate(rj.FreeBody(tensor), rj.State(w, jnp.asarray(q0[0])), ts, accuracy="exact")
        return jnp.sum(motion.omega[-1] ** 2) + jnp.sum(motion.orientation[-1] * jnp.arange(4.0))

    gradient = jax.jit(jax.grad(loss))(jnp.asarray(omega0[0]))
    np.testing.assert_allclose(gradient, central_difference(loss, omega0[0], 1e-6), rtol=1e-7)
    with pytest.raises(ValueError, match="principal axes, which have no derivative"):
        jax.grad(lambda tensor: loss(jnp.asarray(omega0[0]), tensor))(first)


@pytest.mark.parametrize(
    "dtype, scales, tol",
    [(np.float32, [1e-12, 1e-15, 4.6e-28, 1e20], 2e-5), (np.float64, [1e-120, 1e-300, 1e150], 1e-11)],
)
def test_the_scale_of_the_moments_does_not_change_the_motion(dtype, scales, tol):
    """Euler's equations depend on the moments' ratios only. Small bodies in SI units (a mm-sized
    part, 1e-12 kg m^2; a levitated microsphere, 4.6e-28) made the closed forms' products of moments
    underflow: in float32 a tumbling body came out steady (omega frozen at omega0, period inf) or
    wrong by 0.05 rad/s, with success True; float64 likewise below about 1e-110. Reference: scipy's
    DOP853 of the moments (1, 2, 3); the period and the gradient scale as the unscaled body's."""
    moments, omega0, q0 = np.array([1.0, 2.0, 3.0]), np.array([0.1, 1.0, 0.05]), np.array([1.0, 0, 0, 0])
    ts = np.linspace(0.0, 5.0, 11)
    w_ref, q_ref = dop853_free_body(moments, omega0, ts, q0=q0)
    period = float(torque_free_period(moments, omega0))
    w0, start, times = (jnp.asarray(x, dtype) for x in (omega0, q0, ts))
    for scale in scales:
        inertia = jnp.asarray(moments * scale, dtype)
        traj = rj.simulate(rj.FreeBody(inertia), rj.State(w0, start), times, accuracy="exact")
        assert bool(traj.success) and traj.omega.dtype == dtype
        np.testing.assert_allclose(np.asarray(traj.omega, float), w_ref, rtol=0, atol=tol, err_msg=str(scale))
        np.testing.assert_allclose(
            np.asarray(traj.orientation, float), q_ref, rtol=0, atol=tol, err_msg=str(scale)
        )
        np.testing.assert_allclose(float(torque_free_period(inertia, w0)), period, rtol=10 * tol)
    if dtype == np.float64:
        gradient = jax.grad(lambda inertia: torque_free_motion(inertia, w0, start, times[-1])[1][1])
        np.testing.assert_allclose(
            scales[0] * np.asarray(gradient(jnp.asarray(moments * scales[0]))),
            np.asarray(gradient(jnp.asarray(moments))),
            rtol=1e-12,
        )


def test_blocks_of_bodies_write_their_samples_in_place():
    """In blocks, each block's samples are written into the arrays of all the bodies: beside the
    output, the program needs memory for about one block's work, not a second copy of every sample
    (stacked blocks, then cut to the bodies: 0.85 of the output; in place: 0.43; 3001 bodies in 31
    blocks, the last overlapping the one before it). Reference: XLA's memory analysis of the compiled
    program; the overlapping block's bodies are those of one block."""
    n = 3001
    rng = np.random.default_rng(11)
    inertia = jnp.asarray(perturbed_inertia(rng, n, 0.05))
    omega0, q0 = jnp.asarray(perturbed_omega(rng, n, 0.3)), jnp.asarray(random_quaternions(rng, n))
    ts = jnp.linspace(0.0, 5.0, 11)

    def motion(inertia, omega0, q0, chunk_size):
        state = rj.State(omega0, q0)
        traj = rj.simulate(rj.FreeBody(inertia), state, ts, accuracy="exact", chunk_size=chunk_size)
        return traj.omega, traj.orientation

    in_blocks = jax.jit(motion, static_argnums=3)
    memory = in_blocks.lower(inertia, omega0, q0, 100).compile().memory_analysis()
    assert memory.temp_size_in_bytes < 0.6 * memory.output_size_in_bytes, memory
    blocks = in_blocks(inertia, omega0, q0, 100)
    tail = slice(n - 150, n)  # the last block and the one it overlaps
    whole = motion(inertia[tail], omega0[tail], q0[tail], None)
    for got, expected in zip(blocks, whole, strict=True):
        np.testing.assert_allclose(np.asarray(got[tail]), np.asarray(expected), rtol=0, atol=1e-14)


def test_blocks_of_bodies_trace_the_closed_form_once(monkeypatch):
    """In blocks, the closed form is traced once, for the loop over blocks (a trace for the shapes of
    its results alone took 0.2 s more per program). Reference: a count of the closed form's calls
    while JAX traces 30 bodies in blocks of 8 (the last overlapping), and the one-block values."""
    from rigidjax._integrate import exact

    calls = counted_calls(monkeypatch, exact, "_torque_free_motion")
    rng = np.random.default_rng(13)
    inertia = jnp.asarray(perturbed_inertia(rng, 30, 0.05))
    omega0, q0 = jnp.asarray(perturbed_omega(rng, 30, 0.3)), jnp.asarray(random_quaternions(rng, 30))
    ts = jnp.linspace(0.0, 5.0, 5)

    def orientation(inertia, chunk_size):
        state = rj.State(omega0, q0)
        return rj.simulate(
            rj.FreeBody(inertia), state, ts, accuracy="exact", chunk_size=chunk_size
        ).orientation

    lowered = jax.jit(orientation, static_argnums=1).lower(inertia, 8)
    assert len(calls) == 1
    np.testing.assert_allclose(lowered.compile()(inertia), orientation(inertia, None), rtol=0, atol=1e-14)


@pytest.mark.slow
def test_orientation_near_separatrix_against_taylor_integration():
    """s = (L^2 - 2 E I2) / L^2 = -4e-10, axes relabelled (odd), in the middle of the first flip:
    the closed form agrees with mpmath's 20-digit Taylor integration of omega and q to roundoff."""
    inertia, omega0 = [3.0, 2.0, 1.0], [-0.5e-4, 2.0, 1e-4]
    with mp.workdps(20):
        I = [mp.mpf(x) for x in inertia]

        def f(t, y):
            x, y_, z, qw, qx, qy, qz = y
            return [
                (I[1] - I[2]) * y_ * z / I[0],
                (I[2] - I[0]) * z * x / I[1],
                (I[0] - I[1]) * x * y_ / I[2],
                (-qx * x - qy * y_ - qz * z) / 2,
                (qw * x + qy * z - qz * y_) / 2,
                (qw * y_ - qx * z + qz * x) / 2,
                (qw * z + qx * y_ - qy * x) / 2,
            ]

        solution = mp.odefun(f, 0, [mp.mpf(float(v)) for v in list(omega0) + list(Q0)])
        reference = np.array([float(v) for v in solution(11.0)])
    omega, q = run_cases(np.tile(inertia, (8, 1)), np.tile(omega0, (8, 1)), Q0, np.full((8, N_TIMES), 11.0))
    assert abs(reference[1]) < 1.9  # really mid-flip: omega has left the intermediate axis
    np.testing.assert_allclose(omega[0, 0], reference[:3], atol=1e-14)
    np.testing.assert_allclose(q[0, 0], reference[3:], atol=1e-14)


_CLOSED_FORMS_SCRIPT = """
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import rigidjax as rj
inertia, omega0, q0 = np.array([1.0, 2.0, 2.5]), np.array([0.05, 4.0, 0.05]), np.array([1.0, 0.0, 0.0, 0.0])
ts = np.linspace(0.0, 5.0, 11)
rj.torque_free_motion(inertia, omega0, q0, ts)
rj.torque_free_omega(inertia, omega0, ts)
rj.torque_free_period(inertia, omega0)
"""


@pytest.mark.slow
def test_closed_form_programs_are_kept_between_processes(tmp_path):
    """The public closed forms called on concrete arrays hold no host callback (their value checks
    are a program of their own that returns the failed conditions), so JAX's persistent cache keeps
    their programs and a second process loads every one of them instead of compiling it."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(tmp_path / "cache"), JAX_LOG_COMPILES="1")
    env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"

    def run():
        child = subprocess.run(
            [sys.executable, "-c", _CLOSED_FORMS_SCRIPT], env=env, capture_output=True, text=True, timeout=300
        )
        assert child.returncode == 0, child.stderr
        return child.stderr

    run()
    second = run()
    for name in ("motion", "omega", "period"):
        for program in (f"_{name}_program", f"_{name}_failures"):
            hit = f"Persistent compilation cache hit for 'jit_{program}'"
            assert hit in second, (program, second[-3000:])


def test_eager_bad_values_raise_value_error_and_jit_keeps_its_checks():
    """Concrete bad values raise ValueError before the computing program runs; inside the user's
    jit (no values) the checks are in the program and still fire."""
    bad_inertia = np.array([1.0, 2.0, 3.0 * (1 + 1e-12)])  # beyond the flat plate
    with pytest.raises(ValueError, match="triangle inequality"):
        torque_free_omega(bad_inertia, np.array([0.1, 1.0, 0.1]), 0.5)
    with pytest.raises(ValueError, match="omega0 contains NaN"):
        torque_free_period(np.array([1.0, 2.0, 2.5]), np.array([np.nan, 1.0, 0.1]))
    with pytest.raises(ValueError, match="q0"):
        torque_free_motion(np.array([1.0, 2.0, 2.5]), np.array([0.1, 1.0, 0.1]), np.zeros(4), 0.5)
    traced = jax.jit(lambda inertia: torque_free_omega(inertia, jnp.array([0.1, 1.0, 0.1]), 0.5))
    with pytest.raises(Exception, match="triangle inequality"):
        jax.block_until_ready(traced(jnp.asarray(bad_inertia)))
    # valid inputs: the unchecked program gives what the checked one gives (under jit)
    good = np.array([1.0, 2.0, 2.5])
    eager = torque_free_omega(good, np.array([0.1, 1.0, 0.1]), 0.5)
    np.testing.assert_array_equal(np.asarray(eager), np.asarray(traced(jnp.asarray(good))))


def test_reverse_mode_matches_forward_mode_and_the_equations_of_motion():
    """jax.jacrev of omega(t) and q(t) with respect to (inertia, omega0, t) equals jax.jacfwd (the
    reverse mode transposes a contraction of per-sample Jacobians, the forward mode applies it), and
    the time column equals Euler's equations and dq/dt = q (0, omega) / 2 evaluated at the returned
    state (independent of any derivative code), for generic bodies, near and exactly on the
    separatrix, a symmetric top, a steady spin about the intermediate axis and a body at rest."""
    inertia = np.array(
        [
            [1.0, 2.0, 2.5],
            [2.5, 1.0, 2.0],
            [1.0, 2.0, 2.9],
            [1.0, 2.5, 3.0],
            [2.0, 2.0, 3.0],
            [1.0, 2.0, 3.0],
            [1.0, 2.0, 3.0],
        ]
    )
    omega0 = np.array(
        [
            [0.3, -0.5, 1.0],
            [0.2, 3.0, 0.1],
            [0.05, 4.0, -0.05],
            [0.5, 1.0, 0.5],
            [0.3, 0.1, 5.0],
            [0.0, 4.0, 0.0],
            [0.0, 0.0, 0.0],
        ]
    )
    q0 = random_quaternions(np.random.default_rng(4), len(inertia))
    t = np.array([3.0, 1.0, 2.0, 3.0, 0.5, 2.0, 1.0])
    args = tuple(jnp.asarray(x) for x in (inertia, omega0, q0, t))
    forward = _jacfwd(*args)
    reverse = _jacrev(*args)
    for name, f, r in zip(("inertia", "omega0", "t"), forward, reverse, strict=True):
        f, r = np.asarray(f), np.asarray(r)
        assert np.all(np.isfinite(r)), name
        np.testing.assert_allclose(r, f, rtol=1e-12, atol=1e-12 * np.max(np.abs(f)), err_msg=name)
    # Bodies do not influence each other: every off-diagonal block is exactly zero.
    off_diagonal = ~np.eye(len(t), dtype=bool)
    for r in reverse:
        assert np.all(np.moveaxis(np.asarray(r), 2, 1)[off_diagonal] == 0)

    # The state by the value tests' program (run_cases: 8 bodies, each at its time in the first of 41
    # samples; the eighth repeats the first).
    pad = lambda x: np.concatenate([x, x[:1]])  # noqa: E731
    omega, q = run_cases(pad(inertia), pad(omega0), pad(q0), np.repeat(pad(t)[:, None], N_TIMES, 1))
    omega, q = omega[: len(t), 0], q[: len(t), 0]
    I1, I2, I3 = inertia.T
    w1, w2, w3 = omega.T
    euler = np.stack([(I2 - I3) * w2 * w3 / I1, (I3 - I1) * w3 * w1 / I2, (I1 - I2) * w1 * w2 / I3], -1)
    q_rate = 0.5 * quat_multiply(q, np.concatenate([np.zeros((len(t), 1)), omega], -1))
    d_dt = np.asarray(reverse[2])[np.arange(len(t)), :, np.arange(len(t))]
    np.testing.assert_allclose(d_dt[:, :3], euler, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(d_dt[:, 3:], q_rate, rtol=1e-11, atol=1e-12)


def _symmetric_rod_orientation(moments, omega0, q0, ts):
    """A body with I2 = I3 = B about its first axis: R(t) = exp(t [L_space]x / B) R0 exp(t w1 (B - A) / B
    [e1]x) (the body-frame omega is L / B plus a spin about the axis), by scipy's rotations."""
    a, b = moments[0], moments[1]
    r0 = Rotation.from_quat(q0, scalar_first=True)
    momentum = r0.apply(np.asarray(moments) * np.asarray(omega0))
    spin = omega0[0] * (b - a) / b
    out = [
        (Rotation.from_rotvec(momentum * t / b) * r0 * Rotation.from_rotvec([spin * t, 0.0, 0.0])).as_quat(
            scalar_first=True
        )
        for t in ts
    ]
    return np.array(out)


def test_thin_rods_keep_their_orientation():
    """A thin rod spinning about its long axis (I1 << I2 = I3): the precession rate was formed as
    (|L| / I1) (1 + (I1 - I3) / I3 g), which cancels to an absolute error of eps |L| / I1: 4e-7 rad
    after 40 s at I1 = 1e-9 and 3e-4 at 1e-12, in float64; 0.19 rad at I1 = 1e-6 in float32, with
    success True. Reference: the symmetric body's rotation about L composed with its spin."""
    q0 = np.asarray(rj.quat_from_euler(np.array([0.3, 0.7, -0.2])))
    ts = np.linspace(0.0, 40.0, 41)
    omega0 = np.array([2.0, 0.3, 0.2])
    rods = np.array([[1e-12, 1.0, 1.0], [1e-9, 1.0, 1.0], [1e-6, 1.0, 1.0], [1e-3, 1.0, 1.0]])
    # The four rods twice: N_CASES bodies at N_TIMES samples, the shapes (and in float64 the compiled
    # program) of test_simulate_exact_returns_the_closed_form_orientation.
    for dtype, tolerance in ((np.float64, 1e-12), (np.float32, 5e-5)):
        traj = rj.simulate(
            rj.FreeBody(np.tile(rods, (2, 1)).astype(dtype)),
            rj.State(np.tile(omega0, (N_CASES, 1)).astype(dtype), np.tile(q0, (N_CASES, 1)).astype(dtype)),
            ts.astype(dtype),
            accuracy="exact",
        )
        for k, moments in enumerate(rods.astype(dtype).astype(np.float64)):
            reference = _symmetric_rod_orientation(moments, omega0.astype(dtype), q0.astype(dtype), ts)
            q = np.asarray(traj.orientation[k], np.float64)
            sign = np.where(np.sum(q * reference, axis=-1, keepdims=True) < 0, -1.0, 1.0)
            np.testing.assert_allclose(q * sign, reference, rtol=0, atol=tolerance)
