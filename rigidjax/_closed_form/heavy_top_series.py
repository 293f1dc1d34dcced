"""Lagrange's top by Fourier series in the nutation phase: the fast path of :mod:`.heavy_top`.

Each Cayley-Klein half ``Z_k`` (``w + i z`` and ``x + i y`` of the quaternion) is ``e^{i Omega_k t}``
times a function of the elliptic phase ``tau`` with the nutation period ``2K``, where ``Omega_k`` is
the half's mean phase rate. Classically (Klein and Sommerfeld) ``Z_k e^{-i Omega_k t}`` is a ratio
of theta functions whose denominator ``Theta(tau)`` vanishes only at ``Im tau = +-K'``: it is
analytic in that strip however close the motion passes to a pole of ``Z_k``, so its Fourier
coefficients decay like the nome ``q^j`` (``q ~ m / 16``), unlike those of the phase rate
``1 / (1 + k u)`` itself. So per body the exact closed form is evaluated at ``M`` equispaced
points of one nutation period and turned into ``2J + 1`` Fourier coefficients by a fixed matrix;
per sample only ``e^{i j phi}`` by complex multiplication and two sums per half remain (``Z_k`` and
``dZ_k/dt``), and ``omega = 2 conj(q) dq/dt``. No elliptic function, Carlson integral or branch is
evaluated per sample.

A body qualifies when its coefficients of the two highest harmonics are below ``eps`` (the
truncation error is then below one ``eps``) and it is none of the special cases that the elliptic
path treats in their own forms (no motion, a nutation below ``eps^(2/3)``, a half whose pole is a
turning circle). Only values come from here: :mod:`.heavy_top` differentiates the elliptic path.
"""

import jax
import jax.numpy as jnp
import numpy as np

# Points per nutation period; the series keeps the harmonics -J..J, J = M/2 - 1.
SERIES_NODES = _NODES = 32
_HARMONICS = _NODES // 2 - 1


def _fourier_matrix(dtype):
    """``(M, 2J + 1)``: coefficients ``c_j`` (``j = -J..J``) of a periodic function from its values."""
    i = np.arange(_NODES)
    j = np.arange(-_HARMONICS, _HARMONICS + 1)
    matrix = np.exp(-2j * np.pi * np.outer(i, j) / _NODES) / _NODES
    return jnp.asarray(matrix, jnp.complex128 if dtype == jnp.float64 else jnp.complex64)


def _mean_rates(body, quarter, g_quarter):
    """``Omega_k``: each half's phase advance over a nutation period divided by the period."""
    rates = []
    for half, gk in zip(body["halves"], g_quarter, strict=True):
        spin = half["k"] * (body["w3"] - body["a"])
        near = jnp.where(half["near"] > 0, half["near"], 1.0)
        rates.append(0.5 * (spin + half["coeff"] * gk / (near * quarter)))
    return rates


def series_setup(body, quarter, g_quarter, motion):
    """Per-body Fourier coefficients of both halves and whether the series is exact for each body.

    **Arguments:**

    - `body`: the per-body quantities of :func:`.heavy_top._body`.
    - `quarter`: ``K(m)``; `g_quarter`: for each half, ``int_0^K dtau / (1 + n sn^2)``.
    - `motion`: the exact ``(omega, q)`` as a function of times (the elliptic path).

    **Returns:** a dict with the coefficients ``c`` (one array per half, last axis ``j = -J..J``),
    the mean rates, the phase rate ``pi lambda / K`` and the boolean mask ``ok``.
    """
    dtype = body["m"].dtype
    eps = float(jnp.finfo(dtype).eps)
    linear = body["amp"] <= eps ** (2 / 3) * body["pole_gap"]
    ok = (body["amp"] > 0) & (body["rate"] > 0) & (body["g0"] > 0) & ~linear
    for half in body["halves"]:
        ok &= ~half["reached"]
    rate = jnp.where(ok, body["rate"], 1.0)
    period = 2 * quarter / rate
    nodes = period[..., None] * jnp.asarray(np.arange(_NODES) / _NODES, dtype)
    # The bodies' quantities with a trailing axis for the nodes (the halves' signs k stay floats).
    expand = jax.tree.map(lambda v: v[..., None] if isinstance(v, jax.Array) else v, body)
    _, q_nodes = motion(expand, nodes)
    omegas = _mean_rates(body, quarter, g_quarter)
    matrix = _fourier_matrix(dtype)
    coeffs = []
    for (re, im), omega in zip(((0, 3), (1, 2)), omegas, strict=True):
        z = jax.lax.complex(q_nodes[..., re], q_nodes[..., im])
        turn = -omega[..., None] * nodes
        w = z * jax.lax.complex(jnp.cos(turn), jnp.sin(turn))
        c = w @ matrix
        tail = jnp.abs(c[..., 0]) + jnp.abs(c[..., 1]) + jnp.abs(c[..., -1]) + jnp.abs(c[..., -2])
        ok &= (tail <= 8 * eps) & jnp.all(jnp.isfinite(jnp.abs(c)), axis=-1)
        coeffs.append(c)
    return dict(c=coeffs, omegas=omegas, freq=jnp.pi * rate / quarter, ok=ok)


def series_motion(body, setup, t):
    """Body-frame ``omega`` and ``q`` at times ``t`` from the per-body series (where ``setup["ok"]``).

    **Arguments:**

    - `body`: the per-body quantities of :func:`.heavy_top._body`; `setup`: :func:`series_setup`'s.
    - `t`: times, broadcast against the bodies.

    **Returns:** ``(omega, q)`` as :func:`.heavy_top.lagrange_top_motion`.
    """
    freq = setup["freq"]
    phi = freq * t
    cos1, sin1 = jnp.cos(phi), jnp.sin(phi)
    # Per half, in real arithmetic (vectorises; complex products do not on CPU): with
    # A_j = c_j + c_-j and B_j = i (c_j - c_-j),  W = c_0 + sum A_j cos(j phi) + B_j sin(j phi) and
    # dW/dphi = sum j (B_j cos(j phi) - A_j sin(j phi)).
    terms = []
    for c in setup["c"]:
        plus, minus = c[..., _HARMONICS + 1 :], c[..., _HARMONICS - 1 :: -1]
        a, b = plus + minus, plus - minus
        terms.append((jnp.real(a), jnp.imag(a), -jnp.imag(b), jnp.real(b)))
    powers = [(cos1, sin1)]
    for _ in range(_HARMONICS - 1):
        cj, sj = powers[-1]
        powers.append((cj * cos1 - sj * sin1, sj * cos1 + cj * sin1))
    # Summed from the highest harmonic down, the mean last: the small terms first, for rounding.
    sums = []
    for (ar, ai, br, bi), c in zip(terms, setup["c"], strict=True):
        acc = [jnp.zeros_like(phi)] * 4
        for j in range(_HARMONICS, 0, -1):
            cj, sj = powers[j - 1]
            a_r, a_i, b_r, b_i = ar[..., j - 1], ai[..., j - 1], br[..., j - 1], bi[..., j - 1]
            acc[0] = acc[0] + (a_r * cj + b_r * sj)
            acc[1] = acc[1] + (a_i * cj + b_i * sj)
            acc[2] = acc[2] + j * (b_r * cj - a_r * sj)
            acc[3] = acc[3] + j * (b_i * cj - a_i * sj)
        mean = c[..., _HARMONICS]
        sums.append((acc[0] + jnp.real(mean), acc[1] + jnp.imag(mean), acc[2], acc[3]))
    halves = []
    for (w_r, w_i, d_r, d_i), omega in zip(sums, setup["omegas"], strict=True):
        # Z = e^{i Omega t} W,  dZ/dt = e^{i Omega t} (i Omega W + freq dW/dphi).
        turn = omega * t
        rc, rs = jnp.cos(turn), jnp.sin(turn)
        s_r, s_i = freq * d_r - omega * w_i, freq * d_i + omega * w_r
        halves.append((w_r * rc - w_i * rs, w_r * rs + w_i * rc, s_r * rc - s_i * rs, s_r * rs + s_i * rc))
    (pw, pz, dw, dz), (mx, my, dx, dy) = halves
    # The series' |q| = 1 holds to a few eps; dividing by it puts q on the unit sphere to rounding.
    norm2 = pw * pw + mx * mx + my * my + pz * pz
    inv = 1 / jnp.sqrt(norm2)
    q = jnp.stack([pw, mx, my, pz], axis=-1) * inv[..., None]
    # omega = 2 conj(q) dq/dt / |q|^2 (vector part); omega_3 is the constant of the motion.
    w1 = 2 * (pw * dx - mx * dw - my * dz + pz * dy) / norm2
    w2 = 2 * (pw * dy + mx * dz - my * dw - pz * dx) / norm2
    w3 = jnp.broadcast_to(body["w3"], w1.shape)
    return jnp.stack([w1, w2, w3], axis=-1), q
