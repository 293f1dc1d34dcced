"""Closed-form torque-free motion against high-precision integration, closed forms and invariants."""

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import rigidjax as rj
from rigidjax._torque_free import torque_free_omega, torque_free_period

omega_at = jax.jit(torque_free_omega)


def dop853(inertia, omega0, ts):
    I1, I2, I3 = inertia

    def f(t, w):
        return [(I2 - I3) * w[1] * w[2] / I1, (I3 - I1) * w[2] * w[0] / I2, (I1 - I2) * w[0] * w[1] / I3]

    return solve_ivp(f, (0.0, ts[-1]), omega0, t_eval=ts, method="DOP853", rtol=1e-13, atol=1e-14).y.T


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
    np.testing.assert_allclose(exact, dop853(inertia, omega0, ts), atol=1e-11 * np.linalg.norm(omega0))


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
    for t in [7.0, 20.0]:
        reference = np.array([float(v) for v in solution(t)])
        exact = np.asarray(omega_at(jnp.array([1.0, 2.0, 2.5]), jnp.array([0.05, 4.0, 0.05]), jnp.asarray(t)))
        np.testing.assert_allclose(exact, reference, atol=4 * 1e-14)


def test_symmetric_top_and_period():
    I1, I3, w0 = 2.0, 3.0, np.array([0.3, -0.1, 5.0])
    ts = np.linspace(0.0, 10.0, 51)
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
    ts = jnp.linspace(0.0, 3.0, 7)
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


def test_conserves_energy_and_momentum_to_roundoff_over_long_times():
    inertia = jnp.array([1.0, 2.0, 2.5])
    omega0 = jnp.array([0.05, 4.0, 0.05])
    ts = jnp.linspace(0.0, 1e4, 1001)
    omega = omega_at(inertia, omega0, ts)
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
        out = np.asarray(omega_at(jnp.asarray(inertia), jnp.asarray(omega0), jnp.linspace(0.0, 50.0, 11)))
        np.testing.assert_allclose(out, np.broadcast_to(omega0, out.shape), atol=1e-14)


def test_batches_and_gradients():
    rng = np.random.default_rng(3)
    inertia = np.array([1.0, 2.0, 2.5]) * (1 + 0.05 * rng.uniform(-1, 1, (4, 3)))
    omega0 = rng.normal(size=(4, 3))
    ts = np.linspace(0.0, 5.0, 6)
    batch = np.asarray(
        omega_at(jnp.asarray(inertia)[:, None], jnp.asarray(omega0)[:, None], jnp.asarray(ts)[None, :])
    )
    assert batch.shape == (4, 6, 3)
    for i in range(4):
        np.testing.assert_allclose(batch[i], dop853(inertia[i], omega0[i], ts), atol=1e-11)

    def final(inertia, omega0):
        return torque_free_omega(inertia, omega0, jnp.asarray(3.0))

    I0, w0 = jnp.asarray(inertia[0]), jnp.asarray(omega0[0])
    jac_I, jac_w = jax.jacfwd(final, argnums=(0, 1))(I0, w0)
    jac_I_rev, jac_w_rev = jax.jacrev(final, argnums=(0, 1))(I0, w0)
    np.testing.assert_allclose(jac_I, jac_I_rev, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(jac_w, jac_w_rev, rtol=1e-9, atol=1e-12)
    h = 1e-6
    for k in range(3):
        dI = (np.asarray(final(I0.at[k].add(h), w0)) - np.asarray(final(I0.at[k].add(-h), w0))) / (2 * h)
        dw = (np.asarray(final(I0, w0.at[k].add(h))) - np.asarray(final(I0, w0.at[k].add(-h)))) / (2 * h)
        np.testing.assert_allclose(np.asarray(jac_I)[:, k], dI, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(np.asarray(jac_w)[:, k], dw, rtol=1e-6, atol=1e-8)


def test_float32():
    ts = np.linspace(0.0, 5.0, 11).astype(np.float32)
    out = omega_at(np.array([1.0, 2.0, 2.5], np.float32), np.array([3.0, 0.1, 0.2], np.float32), ts)
    assert out.dtype == jnp.float32
    reference = dop853(np.array([1.0, 2.0, 2.5]), np.array([3.0, 0.1, 0.2]), ts.astype(np.float64))
    np.testing.assert_allclose(np.asarray(out, np.float64), reference, atol=3e-5)


def test_simulate_exact_switches_to_the_closed_form():
    """accuracy="exact" is one word away from integration and agrees with it on a racket batch."""
    rng = np.random.default_rng(0)
    inertia = jnp.asarray(np.array([1.0, 2.0, 2.5]) * (1 + 0.05 * rng.uniform(-1, 1, (16, 3))))
    omega0 = jnp.asarray(np.array([0.05, 4.0, 0.05]) + 0.01 * rng.normal(size=(16, 3)))
    ts = jnp.linspace(0.0, 20.0, 41)
    exact = rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts, accuracy="exact")
    precise = rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts, accuracy="precise")
    assert exact.omega.shape == (16, 41, 3) and bool(jnp.all(exact.success))
    np.testing.assert_allclose(np.asarray(exact.omega), np.asarray(precise.omega), atol=1e-7)
    assert float(jnp.max(exact.invariants()["energy"])) < 1e-13
    # Time is measured from ts[0].
    shifted = rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts + 100.0, accuracy="exact")
    np.testing.assert_allclose(np.asarray(shifted.omega), np.asarray(exact.omega), atol=1e-12)
    with pytest.raises(ValueError, match="torque-free"):
        rj.simulate(
            rj.HeavyTop(inertia[0], 1.0, jnp.array([0.0, 0.0, 0.1])),
            rj.State(omega0[0], jnp.array([1.0, 0, 0, 0])),
            ts,
            accuracy="exact",
        )
    with pytest.raises(NotImplementedError, match="orientation"):
        rj.simulate(
            rj.FreeBody(inertia[0]), rj.State(omega0[0], jnp.array([1.0, 0, 0, 0])), ts, accuracy="exact"
        )
    with pytest.raises(Exception, match="triangle"):
        rj.simulate(
            rj.FreeBody(jnp.array([1.0, 2.0, 4.0])), rj.State(omega0[0]), ts, accuracy="exact"
        ).omega.block_until_ready()
