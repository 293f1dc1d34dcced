"""What several test files share: independent references, the finite-difference check, scene builders
and tolerances.

Everything here is numpy / scipy / mpmath (no rigidjax), so a reference built from it does not share code with
what it checks. Import it as ``from helpers import ...`` (pytest puts tests/ on ``sys.path``).
"""

import jax
import mpmath as mp
import numpy as np
import pytest
import sympy as sp
from scipy.integrate import solve_ivp

# --------------------------------------------------------------------------------------------------
# Tolerances

EPS64 = float(np.finfo(np.float64).eps)
EPS32 = float(np.finfo(np.float32).eps)
# The reference integrator's tolerance: rtol = atol = 1e-13 on an O(1) problem, a few hundred times
# eps; the checks against it allow ~1e-11 relative (or a few times what was measured).
DOP853_TOL = 1e-13
IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])
IDENTITY_Q.setflags(write=False)


# --------------------------------------------------------------------------------------------------
# Euler's equations and quaternions in numpy


def euler_rhs(inertia, omega, torque=0.0):
    """Euler's equations in principal axes, ``I1 w1' = (I2 - I3) w2 w3 + tau1`` and cyclic (transcribed
    from the textbook), broadcasting over leading axes. ``I_j - I_k`` of nearly equal moments is exact
    (Sterbenz), so near-spheres keep their accuracy."""
    inertia, omega, torque = np.broadcast_arrays(
        np.asarray(inertia, float), np.asarray(omega, float), np.asarray(torque, float)
    )
    I1, I2, I3 = inertia[..., 0], inertia[..., 1], inertia[..., 2]
    w1, w2, w3 = omega[..., 0], omega[..., 1], omega[..., 2]
    return np.stack(
        [
            ((I2 - I3) * w2 * w3 + torque[..., 0]) / I1,
            ((I3 - I1) * w3 * w1 + torque[..., 1]) / I2,
            ((I1 - I2) * w1 * w2 + torque[..., 2]) / I3,
        ],
        axis=-1,
    )


def quat_multiply(p, q):
    """Hamilton product of scalar-first quaternions, broadcasting over leading axes."""
    p, q = np.asarray(p, float), np.asarray(q, float)
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - np.sum(pv * qv, axis=-1, keepdims=True)
    return np.concatenate([w, pw * qv + qw * pv + np.cross(pv, qv)], axis=-1)


def quat_axis_angle(axis, angle):
    """Quaternion of a rotation by ``angle`` about ``axis`` (normalised here; continuous in the angle,
    no wrapping). ``angle`` may be an array: the result has its shape plus ``(4,)``."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    angle = np.asarray(angle, float)[..., None]
    return np.concatenate([np.cos(angle / 2), np.sin(angle / 2) * axis], axis=-1)


def quat_rotate(q, v):
    """``R(q) v`` (body to space) by ``q (0, v) q*``."""
    q = np.asarray(q, float)
    qv = np.concatenate([np.zeros(np.shape(v)[:-1] + (1,)), np.asarray(v, float)], axis=-1)
    return quat_multiply(quat_multiply(q, qv), q * np.array([1.0, -1.0, -1.0, -1.0]))[..., 1:]


# --------------------------------------------------------------------------------------------------
# The reference integrator: scipy's DOP853


def dop853(accel, omega0, ts, q0=None, *, time_scale=1.0, omega_scale=1.0, tol=DOP853_TOL, atol=None):
    """Reference motion by scipy's DOP853: ``d omega/dt = accel(t, omega, q)`` and, with ``q0``,
    ``dq/dt = q (0, omega) / 2``.

    Solved for ``u = omega / omega_scale`` (a scalar or per component) against ``tau = time_scale t``,
    so that a body that is very fast, very slow or barely wobbling is an O(1) problem for the
    tolerances ``rtol = tol``, ``atol = atol or tol``. ``accel`` gets physical ``t``, ``omega`` and
    ``q`` (None without ``q0``). Returns omega ``(T, 3)`` and q ``(T, 4)`` (or None) at ``ts``.
    """
    ts = np.asarray(ts, float)
    sigma = np.broadcast_to(np.asarray(omega_scale, float), (3,))
    s = float(time_scale)

    def rhs(tau, y):
        w = sigma * y[:3]
        du = np.asarray(accel(tau / s, w, None if q0 is None else y[3:]), float) / (sigma * s)
        if q0 is None:
            return du
        qw, qx, qy, qz = y[3:]
        wx, wy, wz = w
        # q (0, omega), written out: this runs ~1e5 times per reference.
        dq = [-qx * wx - qy * wy - qz * wz, qw * wx + qy * wz - qz * wy, qw * wy - qx * wz + qz * wx]
        dq.append(qw * wz + qx * wy - qy * wx)
        return np.concatenate([du, np.multiply(dq, 0.5 / s)])

    y0 = np.asarray(omega0, float) / sigma
    if q0 is not None:
        y0 = np.concatenate([y0, np.asarray(q0, float)])
    atol = tol if atol is None else atol
    sol = solve_ivp(rhs, (0.0, ts[-1] * s), y0, t_eval=ts * s, method="DOP853", rtol=tol, atol=atol)
    assert sol.success, sol.message
    y = sol.y.T
    return y[:, :3] * sigma, None if q0 is None else y[:, 3:]


def dop853_free_body(inertia, omega0, ts, q0=None, **scales):
    """:func:`dop853` of the torque-free body (Euler's equations in principal axes). The equations
    depend on the moments' ratios only: they are divided by the largest, so SI-scale moments (the
    Earth's 8e37 kg m^2) are fine too. ``scales``: ``time_scale``, ``omega_scale``, ``tol``, ``atol``."""
    I1, I2, I3 = np.asarray(inertia, float) / np.max(inertia)

    def accel(t, w, q):  # scalar arithmetic: this runs ~1e5 times per reference
        return [(I2 - I3) * w[1] * w[2] / I1, (I3 - I1) * w[2] * w[0] / I2, (I1 - I2) * w[0] * w[1] / I3]

    return dop853(accel, omega0, ts, q0, **scales)


# --------------------------------------------------------------------------------------------------
# The finite-difference check


def central_difference(f, x, h=1e-6):
    """``df/dx`` by central differences, shape ``f(x).shape + x.shape``; ``h`` is one step or a step
    per entry of ``x`` (relative steps: ``h = 1e-7 * x``). Truncation error ~h^2 f''', roundoff
    ~eps |f| / h."""
    x = np.asarray(x, float)
    h = np.broadcast_to(np.asarray(h, float), x.shape)
    cols = []
    for idx in np.ndindex(*x.shape):
        dx = np.zeros_like(x)
        dx[idx] = h[idx]
        cols.append((np.asarray(f(x + dx), float) - np.asarray(f(x - dx), float)) / (2 * h[idx]))
    out = np.stack(cols, axis=-1)
    return out.reshape(out.shape[:-1] + x.shape)


def log_log_slope(x, y):
    """The slope of log(y) against log(x) by least squares: a method's convergence order (``x`` the
    steps, ``y`` the errors), or the power of a growth law."""
    return np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0]


def expect_error(fn, *words):
    """``fn()`` raises (eagerly, or when its result is computed), and the message has every word."""
    with pytest.raises(Exception) as info:
        jax.block_until_ready(fn())
    text = str(info.value)
    for word in words:
        assert word in text, f"{word!r} not in error message:\n{text}"


def cli_in_fresh_cache(tmp_path, *args):
    """A function that runs ``rigidjax <args>`` in a new process with no cache directory chosen (so
    the command uses its own, ``$XDG_CACHE_HOME/rigidjax/jax`` under ``tmp_path``) and JAX's compile
    log on, asserts it succeeded and returns ``(stdout, stderr)``."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    env["JAX_LOG_COMPILES"] = "1"
    argv = [sys.executable, "-m", "rigidjax._cli", *args]

    def run():
        child = subprocess.run(argv, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert child.returncode == 0, child.stderr
        return child.stdout, child.stderr

    return run


# --------------------------------------------------------------------------------------------------
# Scene builders. Each draws from the generator it is given, in a fixed order, so that a test that
# builds its scene from them gets the same bodies on every run.

# A body with three distinct moments; spun near its intermediate axis (RACKET_OMEGA) it flips
# (the tennis-racket theorem), spun near its largest axis it wobbles.
RACKET_INERTIA = np.array([1.0, 2.0, 2.5])
RACKET_OMEGA = np.array([0.05, 4.0, 0.05])
RACKET_INERTIA.setflags(write=False)
RACKET_OMEGA.setflags(write=False)


def perturbed_inertia(rng, n, spread, base=RACKET_INERTIA):
    """``n`` bodies with the moments ``base`` each scaled by ``1 + spread u``, ``u`` uniform in
    [-1, 1]: ``(n, 3)``. Physical for ``base = (1, 2, 2.5)`` and ``spread <= 0.1``."""
    return np.asarray(base, float) * (1 + spread * rng.uniform(-1, 1, (n, 3)))


def perturbed_omega(rng, n, spread, base=RACKET_OMEGA):
    """``n`` angular velocities ``base + spread * normal``: ``(n, 3)``."""
    return np.asarray(base, float) + spread * rng.normal(size=(n, 3))


def random_quaternions(rng, n):
    """``n`` unit quaternions, uniform on the sphere (normalised Gaussians): ``(n, 4)``."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def random_rotation(rng, shape=()):
    """Rotation matrices ``shape + (3, 3)``, uniform (QR of a Gaussian matrix, signs fixed)."""
    q, r = np.linalg.qr(rng.normal(size=shape + (3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[..., None, :]
    return q * np.sign(np.linalg.det(q))[..., None, None]


def random_moments(rng, shape=()):
    """Physical principal moments ``shape + (3,)``: those of boxes of random mass and size, in random
    order."""
    mass = rng.uniform(0.5, 2.0, size=shape)  # (drawn first)
    return box_moments(rng.uniform(0.2, 2.0, size=shape + (3,)), mass)


def box_moments(size, mass=1.0):
    """Principal moments of a solid box (``m (b^2 + c^2) / 12`` and cyclic): always physical, in the
    order of ``size``. Written out here so that references do not call rigidjax's ``solid_box``."""
    size, mass = np.asarray(size, float), np.asarray(mass, float)
    a2, b2, c2 = size[..., 0] ** 2, size[..., 1] ** 2, size[..., 2] ** 2
    return mass[..., None] / 12 * np.stack([b2 + c2, c2 + a2, a2 + b2], axis=-1)


# --------------------------------------------------------------------------------------------------
# Closed-form references


def separatrix(inertia, omega0, ts):
    """The heteroclinic solution on the separatrix (I1 < I2 < I3, L^2 = 2 E I2), derived from Euler's
    equations with the ansatz omega1 = s1 a sech, omega3 = s3 c sech, omega2 = sigma W tanh:

        W = |L| / I2, lam = W sqrt((I3 - I2)(I2 - I1) / (I1 I3)),
        a = W sqrt(I2 (I3 - I2) / (I1 (I3 - I1))), c = W sqrt(I2 (I2 - I1) / (I3 (I3 - I1))),
        omega2 = sigma W tanh(lam (t - t0)), sigma = s1 s3, sech(lam t0) = |omega1(0)| / a,
        t0 = -sign(omega2(0) sigma) acosh(a / |omega1(0)|) / lam.

    sigma = -1 leaves the axis (flip at t0 > 0), sigma = +1 approaches it (the stable manifold).
    Evaluated with 40-digit mpmath from the float inputs. Returns omega (T, 3), t0 and lam.
    """
    with mp.workdps(40):
        I1, I2, I3 = (mp.mpf(float(x)) for x in inertia)
        w = [mp.mpf(float(x)) for x in omega0]
        assert I1 < I2 < I3
        defect = I1 * (I1 - I2) * w[0] ** 2 + I3 * (I3 - I2) * w[2] ** 2
        assert defect == 0, "not on the separatrix"
        size = mp.sqrt(sum((i * x) ** 2 for i, x in zip((I1, I2, I3), w, strict=True)))
        W = size / I2
        lam = W * mp.sqrt((I3 - I2) * (I2 - I1) / (I1 * I3))
        a = W * mp.sqrt(I2 * (I3 - I2) / (I1 * (I3 - I1)))
        c = W * mp.sqrt(I2 * (I2 - I1) / (I3 * (I3 - I1)))
        s1, s3 = mp.sign(w[0]), mp.sign(w[2])
        sigma = s1 * s3
        t0 = -mp.sign(w[1] * sigma) * mp.acosh(a / abs(w[0])) / lam
        out = []
        for t in ts:
            x = lam * (mp.mpf(float(t)) - t0)
            out.append(
                [float(s1 * a * mp.sech(x)), float(sigma * W * mp.tanh(x)), float(s3 * c * mp.sech(x))]
            )
        return np.array(out), float(t0), float(lam)


def removed_after(monkeypatch, module, name, directory):
    """``module.name`` replaced by a call that removes ``directory`` once the original returns (an
    output directory that goes away during a run), and the system's temporary directory pointed at
    a new ``directory.parent / "temporary"``, which the function returns: where outputs are rescued."""
    import shutil
    import tempfile

    original = getattr(module, name)

    def call_then_remove(*args, **kwargs):
        result = original(*args, **kwargs)
        shutil.rmtree(directory)
        return result

    monkeypatch.setattr(module, name, call_then_remove)
    rescue = directory.parent / "temporary"
    rescue.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(rescue))
    return rescue


def variational_dop853(rhs, z, z0, dz0, t1, second=False, tol=1e-13):
    """``z(t1)`` of ``z' = rhs(z)`` (sympy expressions in the symbols ``z``; a parameter is a state
    with zero rate) with its derivatives ``S = dz(t1)/dp`` and, with ``second``,
    ``H = d^2 z(t1)/dp^2``, for initial conditions linear in ``p`` (``dz0 = dz(0)/dp``): the
    variational equations ``S' = G_z S`` and ``H_ab' = G_z H_ab + G_zz[S_a, S_b]``, integrated with
    the motion by scipy's DOP853. No rigidjax and no JAX: a reference for derivatives independent of
    both (and nothing to compile)."""
    n, m = dz0.shape
    jacobian = sp.Matrix(rhs).jacobian(z)
    g, gz = sp.lambdify([z], rhs, "numpy"), sp.lambdify([z], jacobian, "numpy")
    gzz = sp.lambdify([z], sp.derive_by_array(jacobian, z), "numpy")  # [k, i, j]: d2 G_i / dz_j dz_k

    def ode(t, y):
        x, S = y[:n], y[n : n + n * m].reshape(n, m)
        Gz = np.asarray(gz(x), float)
        out = [np.asarray(g(x), float), (Gz @ S).ravel()]
        if second:
            H = y[n + n * m :].reshape(n, m, m)
            Gzz = np.asarray(gzz(x), float)
            out.append((np.einsum("ij,jab->iab", Gz, H) + np.einsum("kij,ja,kb->iab", Gzz, S, S)).ravel())
        return np.concatenate(out)

    y0 = np.concatenate([z0, np.ravel(dz0)] + ([np.zeros(n * m * m)] if second else []))
    sol = solve_ivp(ode, (0.0, t1), y0, method="DOP853", rtol=tol, atol=tol)
    assert sol.success, sol.message
    y = sol.y[:, -1]
    S = y[n : n + n * m].reshape(n, m)
    return (y[:n], S, y[n + n * m :].reshape(n, m, m)) if second else (y[:n], S)


def counted_calls(monkeypatch, module, name):
    """A list that grows by one at each call of ``module.<name>`` (replaced by a counting wrapper)."""
    calls, original = [], getattr(module, name)

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, counted)
    return calls
