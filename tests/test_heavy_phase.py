"""The heavy top's phase integrals by the theta form (``rigidjax._closed_form.heavy_phase``) against
mpmath's ``ellippi``, and the vectorised ``atan2`` against numpy."""

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest

from rigidjax._closed_form.heavy_phase import _atan2, _quarter_period, _theta_parts, _theta_phase

_EPS = float(np.finfo(np.float64).eps)


def _pi_reference(big_n, m, taus):
    """``int_0^tau dtau' / (1 - N sn^2(tau' | m))`` at each ``tau``: ``2 j Pi(N | m) + Pi(N; am(rho) | m)``
    with ``tau = rho + 2 j K``, ``|rho| <= K`` (so that ``am(rho) = asin(sn(rho))``)."""
    with mp.workdps(40):
        m_mp, n_mp = mp.mpf(m), mp.mpf(big_n)
        k = mp.ellipk(m_mp)
        complete = mp.ellippi(n_mp, m_mp)
        out = []
        for tau in taus:
            j = mp.nint(mp.mpf(tau) / (2 * k))
            rho = mp.mpf(tau) - 2 * j * k
            phi = mp.asin(mp.ellipfun("sn", rho, m=m_mp))
            out.append(float(2 * j * complete + mp.ellippi(n_mp, phi, m_mp)))
    return np.array(out)


def _phase(parts, x):
    x = jnp.asarray(x)
    return _theta_phase(x, parts)


# m on either side of 1/2 and near 1; n small (beta from 0) and large (from K', a pole close by).
_CASES = [(m, n) for m in (0.0, 0.2, 0.45, 0.6, 0.95, 1 - 1e-9) for n in (1e-3, 0.4, 7.0, 1e5)]


@pytest.mark.parametrize("m, n", _CASES)
def test_theta_form_against_ellippi(m, n):
    """``G(tau) = int dtau / (1 + n sn^2) = g tau + c (V(tau) - V(0))`` over three periods, and the
    slope ``g = Pi(-n | m) / K`` with its deficit ``1 - g`` each to their own relative accuracy."""
    m_, p_, n_ = (jnp.asarray(x, jnp.float64) for x in (m, 1 - m, n))
    parts = _theta_parts(m_, p_, n_, m_ / n_)
    quarter = float(parts["quarter"])
    taus = np.concatenate([np.linspace(-3 * quarter, 3 * quarter, 13), [1e-3, 0.7 * quarter, quarter]])
    delta_v = np.asarray(_phase(parts, taus) - _phase(parts, 0.0))
    got = float(parts["slope"]) * taus + float(parts["c"]) * delta_v
    expected = _pi_reference(-n, m, taus)
    # Within the conditioning: the integrand is at most 1, the argument good to eps |tau|.
    assert np.max(np.abs(got - expected)) <= 4 * _EPS * (np.max(np.abs(expected)) + np.max(np.abs(taus)))
    # The mean slope G(K) / K: g, and for m > 1/2 the step 2b of V per period.
    slope, deficit, step = (float(parts[k]) for k in ("slope", "deficit", "b"))
    step = float(parts["c"]) * step / quarter
    with mp.workdps(40):
        mean = mp.ellippi(-mp.mpf(n), mp.mpf(m)) / mp.ellipk(mp.mpf(m))
        assert abs((slope + step) / float(mean) - 1) <= 1e-14
        assert abs(deficit / float(1 - mean + step) - 1) <= 1e-13


@pytest.mark.parametrize("m", [0.0, 0.3, 0.7, 1 - 1e-6])
@pytest.mark.parametrize("big_n_over", [1e-6, 0.5, 1 - 1e-9])
def test_pole_between_circles(m, big_n_over):
    """``N`` in ``(m, 1)`` (a half whose pole lies between the other turning circle and the third root):
    ``int dtau / (1 - N sn^2)`` from the theta form half a period on, with ``n' = (N - m) / (1 - N)``."""
    big_n = m + (1 - m) * big_n_over
    n_prime = (big_n - m) / (1 - big_n)
    ratio = m / n_prime
    m_, p_ = jnp.asarray(m, jnp.float64), jnp.asarray(1 - m, jnp.float64)
    parts = _theta_parts(m_, p_, jnp.asarray(n_prime), jnp.asarray(ratio))
    quarter = float(_quarter_period(m_, p_))
    taus = np.linspace(-2.5 * quarter, 2.5 * quarter, 11)
    slope = float(parts["slope"]) - ratio * float(parts["deficit"])
    wave = (1 + ratio) * float(parts["c"])
    x0 = -quarter
    delta_v = np.asarray(_phase(parts, x0 + taus) - _phase(parts, x0))
    got = (slope * taus + wave * delta_v) / (1 - big_n)
    expected = _pi_reference(big_n, m, taus)
    # Within the conditioning: the integrand reaches 1 / (1 - N) at the pole's turning circle.
    bound = 4 * _EPS * (np.max(np.abs(expected)) + np.max(np.abs(taus)) / (1 - big_n))
    assert np.max(np.abs(got - expected)) <= bound


def test_atan2_against_numpy():
    rng = np.random.default_rng(0)
    y, x = rng.normal(size=(2, 10000)) * 10.0 ** rng.uniform(-5, 5, (2, 10000))
    axes = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [-1.0, 0.0], [1.0, 1.0], [-1.0, -1.0], [0.0, 0.0]])
    y, x = np.concatenate([y, axes[:, 0]]), np.concatenate([x, axes[:, 1]])
    got = np.asarray(jax.jit(_atan2)(jnp.asarray(y), jnp.asarray(x)))
    assert np.max(np.abs(got - np.arctan2(y, x))) <= 4.5e-16
    got32 = np.asarray(_atan2(jnp.asarray(y, jnp.float32), jnp.asarray(x, jnp.float32)))
    assert np.max(np.abs(got32 - np.arctan2(y.astype(np.float32), x.astype(np.float32)))) <= 5e-7
    # The derivative is the closed form (x dy - y dx) / (x^2 + y^2).
    dy, dx = jax.grad(_atan2, argnums=(0, 1))(0.3, -1.2)
    assert np.allclose([dy, dx], [-1.2 / 1.53, -0.3 / 1.53], rtol=1e-15)
