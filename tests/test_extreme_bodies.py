"""Bodies at the extremes: near-spherical bodies, flat plates, SI scales (the Earth), the separatrix.

Every case is measured against a reference that does not use the code under test: scipy's DOP853 at
rtol = atol = 1e-13 on problems rescaled to O(1) (per-component scales for the Earth's wobble),
the closed-form symmetric-top motion, the heteroclinic (separatrix) solution
(``helpers.separatrix``) evaluated with mpmath, and the variational equations integrated by DOP853
for derivatives.
Each measured number is asserted against a bound a few times above it and recorded with the
``extreme`` fixture for the published table.

Compile time dominates on a small CPU: every group below is a batch of ``N`` bodies sampled at ``T``
times, so that each (preset, with/without orientation) compiles once and is reused for all groups.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest
from helpers import (
    DOP853_TOL,
    IDENTITY_Q,
    dop853_free_body,
    euler_rhs,
    quat_axis_angle,
    quat_multiply,
    quat_rotate,
    separatrix,
)
from scipy.integrate import solve_ivp

import rigidjax as rj

N = 8  # bodies per group
UNIT_TS = np.linspace(0.0, 1.0, 21)
PRESETS = ("fast", "balanced", "precise", "exact")
Q_ID = IDENTITY_Q

# --------------------------------------------------------------------------------------------------
# Independent references (numpy / scipy / mpmath only)


def euler_jac(inertia, w):
    """d f / d omega and d f / d inertia of Euler's torque-free equations (``helpers.euler_rhs``)."""
    I1, I2, I3 = inertia
    jw = np.array(
        [
            [0.0, (I2 - I3) / I1 * w[2], (I2 - I3) / I1 * w[1]],
            [(I3 - I1) / I2 * w[2], 0.0, (I3 - I1) / I2 * w[0]],
            [(I1 - I2) / I3 * w[1], (I1 - I2) / I3 * w[0], 0.0],
        ]
    )
    a, b, c = w[1] * w[2], w[2] * w[0], w[0] * w[1]
    ji = np.array(
        [
            [-(I2 - I3) / I1**2 * a, a / I1, -a / I1],
            [-b / I2, -(I3 - I1) / I2**2 * b, b / I2],
            [c / I3, -c / I3, -(I1 - I2) / I3**2 * c],
        ]
    )
    return jw, ji


def dop853(inertia, omega0, ts, q0=None, sigma=None):
    """DOP853 at rtol = atol = 1e-13 on the rescaled problem: omega / sigma (per component, default
    |omega0|) against the time s t, s = |omega0| (I_max - I_min) / I_max (the wobble rate: for a nearly
    spherical body the problem then has O(1) coefficients over a short interval). Returns omega (T, 3)
    and q (T, 4) or None."""
    inertia = np.asarray(inertia, float)
    gap = (inertia.max() - inertia.min()) / inertia.max()
    assert gap > 0, "use symmetric_top for a sphere"
    s = np.linalg.norm(omega0) * min(gap, 1.0)
    return dop853_free_body(inertia, omega0, ts, q0, time_scale=s, omega_scale=s if sigma is None else sigma)


def variational(inertia, omega0, t):
    """d omega(t) / d omega0 and d omega(t) / d inertia (3x3 each) from the variational equations,
    integrated by DOP853 on the rescaled problem."""
    inertia, omega0 = np.asarray(inertia, float), np.asarray(omega0, float)
    c = inertia.max()
    hat = inertia / c
    s = np.linalg.norm(omega0)

    def rhs(tau, y):
        u = y[:3]
        jw, ji = euler_jac(hat, u)  # f is homogeneous: f(s u) = s^2 f(u)
        phi_w = y[3:12].reshape(3, 3)
        phi_i = y[12:].reshape(3, 3)  # d u / d hat
        return np.concatenate([euler_rhs(hat, u), (jw @ phi_w).ravel(), (jw @ phi_i + ji).ravel()])

    y0 = np.concatenate([omega0 / s, np.eye(3).ravel(), np.zeros(9)])
    sol = solve_ivp(rhs, (0.0, t * s), y0, method="DOP853", rtol=DOP853_TOL, atol=DOP853_TOL)
    y = sol.y[:, -1]
    # omega = s u(s t), hat = I / c: d omega / d I = s (d u / d hat) / c. d omega / d omega0 =
    # d u / d u0 (also through s, but u(tau) is homogeneous of degree 1 in u0 jointly with tau).
    d_w = y[3:12].reshape(3, 3)
    d_i = y[12:].reshape(3, 3) * s / c
    return d_w, d_i


def symmetric_top(inertia, omega0, q0, ts):
    """Closed-form motion of a symmetric top (I1 = I2): the transverse omega turns at
    Omega = (I3 - I1) / I1 w3 in the body frame, q(t) = q0 exp(t L0 / I1) exp(-Omega t e3)."""
    I1, I2, I3 = inertia
    assert I1 == I2
    w1, w2, w3 = omega0
    big = (I3 - I1) / I1 * w3
    c, s = np.cos(big * ts), np.sin(big * ts)
    omega = np.stack([w1 * c - w2 * s, w1 * s + w2 * c, np.full_like(ts, w3)], -1)
    w_l = np.asarray(inertia) * np.asarray(omega0) / I1
    speed = np.linalg.norm(w_l)
    axis = w_l / speed
    e3 = np.array([0.0, 0.0, 1.0])
    q = quat_multiply(quat_multiply(q0, quat_axis_angle(axis, speed * ts)), quat_axis_angle(e3, -big * ts))
    return omega, q


def q_distance(q, ref):
    """Distance between unit quaternions up to sign, per sample."""
    return np.minimum(np.linalg.norm(q - ref, axis=-1), np.linalg.norm(q + ref, axis=-1))


def invariants(inertia, omega, q=None):
    """Relative drifts of energy, |L| and (with q) space-frame L over the samples, per body."""
    inertia = np.asarray(inertia)[..., None, :]
    energy = np.sum(inertia * omega * omega, -1)
    lb = inertia * omega
    size = np.linalg.norm(lb, axis=-1)
    out = {
        "energy": np.max(np.abs(energy / energy[..., :1] - 1), -1),
        "momentum": np.max(np.abs(size / size[..., :1] - 1), -1),
    }
    if q is not None:
        q = np.asarray(q)
        ls = quat_rotate(q, lb)
        out["space"] = np.max(np.linalg.norm(ls - ls[:, :1], axis=-1), -1) / size[:, 0]
    return out


# --------------------------------------------------------------------------------------------------
# The groups: N bodies each, sampled at ts of one shape (T,) so that every compile is reused.


def _earth():
    A = 8.0101e37  # kg m^2
    C = A * (1 + 3.27e-3)
    B = A * (1 + 2.2e-5)
    w3 = 7.292115e-5  # rad/s
    euler_period = 2 * np.pi / ((C - A) / A * w3)
    inertia, omega = [], []
    for moments, tilt in [
        ((A, A, C), 1e-6),
        ((A, A, C), 1e-3),
        ((A, A, C), 1e-9),
        ((A, A, C), 0.0),
        ((A, B, C), 1e-6),
        ((A, B, C), 1e-3),
        ((A, A, C), 0.3),
        ((A, B, C), 1e-9),
    ]:
        inertia.append(moments)
        omega.append([0.6 * tilt * w3, -0.8 * tilt * w3, w3])
    return np.array(inertia), np.array(omega), 2.5 * euler_period


# Dimensionless shapes, reused at SI scales: flat plates (I3 = I1 + I2 exactly), one 1e-14 beyond (inside
# check_inertia's roundoff allowance of 1e2 eps trace), a rod-like plate, generic and symmetric bodies.
SHAPES_I = np.array(
    [
        [1.0, 2.0, 3.0],
        [1.0, 2.0, 3.0],
        [1.0, 1.0, 2.0],
        [1e-3, 1.0, 1.0 + 1e-3],
        [1.0, 2.0, 2.5],
        [2.5, 1.0, 2.0],
        [2.0, 2.0, 1.0],
        [1.0, 2.0, 3.0 * (1 + 1e-14)],
    ]
)
SHAPES_W = np.array(
    [
        [0.3, 0.2, 1.0],
        [0.4, 1.0, 0.2],
        [0.5, 0.1, 1.0],
        [0.1, 0.3, 1.0],
        [1.0, 0.5, -0.7],
        [0.1, 1.0, 0.05],
        [0.3, -0.4, 1.0],
        [0.3, 0.2, 1.0],
    ]
)
FLAT = [0, 1, 2, 3]
# Inertia magnitudes (kg m^2) alternating tiny / huge within the SI groups.
TINY_HUGE = np.array([1e-9, 8e37] * 4)[:, None]

NEAR_D = [0.0, 1e-15, 1e-9, 1e-6]
NEAR_I = np.array(
    [[1.0, 1 + d, 1 + 2 * d] for d in NEAR_D]
    + [[1.0, 1.0, 1.8], [2.0, 2.0, 1.0], [1.0, 1.0, 1.0 + 1e-9], [1.0 + 2e-12, 1.0, 1.0 + 1e-12]]
)
NEAR_W = np.tile(np.array([0.6, -0.8, 0.5]), (N, 1))
NEAR_LABEL = [
    "sphere (1, 1, 1)",
    "moments equal to 1e-15 relative",
    "moments equal to 1e-9 relative",
    "moments equal to 1e-6 relative",
    "symmetric oblate top (1, 1, 1.8)",
    "symmetric prolate top (2, 2, 1)",
    "symmetric near-sphere (1, 1, 1 + 1e-9)",
    "moments equal to 1e-12, axes unsorted",
]

# Separatrix: I = (1, 2.5, 3) has I1 (I2 - I1) = I3 (I3 - I2), so omega0 = (-+d, 1, d) lies EXACTLY on
# the separatrix in floating point (L^2 - 2 E I2 = 0 with no rounding).
SEP_I = np.array([1.0, 2.5, 3.0])
SEP_CASES = [  # (omega0, label)
    ([0.0, 1.0, 0.0], "perturbation 0 (equilibrium)"),
    ([-1e-15, 1.0, 1e-15], "perturbation 1e-15, unstable branch"),
    ([-1e-8, 1.0, 1e-8], "perturbation 1e-8, unstable branch"),
    ([1e-15, 1.0, 1e-15], "perturbation 1e-15, stable manifold"),
    ([1e-8, 1.0, 1e-8], "perturbation 1e-8, stable manifold"),
    ([0.0, -1.0, 0.0], "perturbation 0, negative spin"),
    ([-1e-8, 1.0, 1e-8], "perturbation 1e-8, unstable branch (duplicate slot)"),
    ([1e-8, -1.0, 1e-8], "perturbation 1e-8, unstable branch, negative spin"),
]
SEP_W = np.array([w for w, _ in SEP_CASES])


def _flip_time(omega0):
    return separatrix(SEP_I, omega0, [0.0])[1]


def _group_inputs():
    earth_i, earth_w, earth_t = _earth()
    flips = [_flip_time(SEP_W[1]), _flip_time(SEP_W[2])]
    sep_ts = np.sort(np.concatenate([np.linspace(0.0, 100.0, 19), flips]))
    return {
        "near": (NEAR_I, NEAR_W, 20.0 * UNIT_TS),
        "unit": (SHAPES_I, SHAPES_W, 40.0 * UNIT_TS),
        "fast": (SHAPES_I * TINY_HUGE, SHAPES_W * 1e5, 40e-5 * UNIT_TS),
        "slow": (SHAPES_I * TINY_HUGE[::-1], SHAPES_W * 1e-9, 40e9 * UNIT_TS),
        "earth": (earth_i, earth_w, earth_t * UNIT_TS),
        "sep": (np.tile(SEP_I, (N, 1)), SEP_W, sep_ts),
    }


@pytest.fixture(scope="module")
def groups():
    return _group_inputs()


@pytest.fixture(scope="module")
def runs(groups):
    return _runs(groups)


def _runs(groups):
    """simulate for every group, preset, and with / without orientation (q0 = identity)."""
    out = {}
    for name, (inertia, omega0, ts) in groups.items():
        model = rj.FreeBody(jnp.asarray(inertia))
        for preset in PRESETS:
            for with_q in (False, True):
                state = rj.State(jnp.asarray(omega0), jnp.tile(Q_ID, (N, 1)) if with_q else None)
                try:
                    traj = rj.simulate(model, state, jnp.asarray(ts), accuracy=preset)
                    traj.omega.block_until_ready()
                except eqx.EquinoxRuntimeError as error:  # see test_fast_preset_with_orientation_at_1e5
                    out[name, preset, with_q] = str(error)
                    continue
                out[name, preset, with_q] = (
                    np.asarray(traj.omega),
                    None if traj.orientation is None else np.asarray(traj.orientation),
                    np.asarray(traj.stats["num_steps"]),
                )
    return out


@pytest.fixture(scope="module")
def references(groups):
    return _references(groups)


def _references(groups):
    """omega and q references per group: DOP853 on the rescaled problem, the symmetric-top closed
    form where I1 = I2 (the Earth), the separatrix solution for the separatrix group."""
    refs = {}
    # Dimensionless shapes once; the SI groups are exact rescalings (omega s, t / s, any inertia scale).
    unit = [dop853(i, w, 40.0 * UNIT_TS, Q_ID) for i, w in zip(SHAPES_I, SHAPES_W, strict=True)]
    refs["unit"] = (np.stack([u[0] for u in unit]), np.stack([u[1] for u in unit]))
    refs["fast"] = (refs["unit"][0] * 1e5, refs["unit"][1])
    refs["slow"] = (refs["unit"][0] * 1e-9, refs["unit"][1])
    near = [
        symmetric_top(i, w, Q_ID, 20.0 * UNIT_TS) if i[0] == i[1] else dop853(i, w, 20.0 * UNIT_TS, Q_ID)
        for i, w in zip(NEAR_I, NEAR_W, strict=True)
    ]
    refs["near"] = (np.stack([u[0] for u in near]), np.stack([u[1] for u in near]))
    inertia, omega0, ts = groups["earth"]
    om, qs = [], []
    for i, w in zip(inertia, omega0, strict=True):
        if i[0] == i[1]:
            o, q = symmetric_top(i, w, Q_ID, ts)
        else:
            tilt = max(np.hypot(w[0], w[1]), 1e-300)
            o, q = dop853(i, w, ts, sigma=[tilt, tilt, w[2]])[0], None
        om.append(o)
        qs.append(q)
    refs["earth"] = (np.stack(om), qs)
    inertia, omega0, ts = groups["sep"]
    om = []
    for w in omega0:
        om.append(np.tile(w, (len(ts), 1)) if w[0] == 0 else separatrix(SEP_I, w, ts)[0])
    refs["sep"] = (np.stack(om), None)
    return refs


def rel_err(omega, ref, scale):
    """max over samples of |omega - ref| / scale, per body."""
    return np.max(np.linalg.norm(omega - ref, axis=-1), -1) / scale


def q_err(q, ref):
    return np.max(q_distance(q, ref), -1)


# Bounds of the published rows: a few times what was measured (loaded 2-core CPU, float64, jax 0.10.2).
BOUNDS: dict[str, float] = {  # key: bound, # measured
    "near/fast/False/spheres": 1e-14,  # 2.92e-15
    "near/fast/False/symmetric": 8e-05,  # 2.13e-05
    "near/fast/True/spheres": 1e-14,  # 2.86e-15
    "near/fast/True/symmetric": 3e-06,  # 9.33e-07
    "near/fast/q": 0.0008,  # 2.37e-04
    "near/balanced/False/spheres": 1e-14,  # 3.22e-15
    "near/balanced/False/symmetric": 8e-07,  # 2.56e-07
    "near/balanced/True/spheres": 1.5e-14,  # 4.44e-15
    "near/balanced/True/symmetric": 1.5e-08,  # 4.83e-09
    "near/balanced/q": 1.5e-07,  # 4.82e-08
    "near/precise/False/spheres": 1.5e-14,  # 3.78e-15
    "near/precise/False/symmetric": 6e-12,  # 1.79e-12
    "near/precise/True/spheres": 2e-14,  # 5.97e-15
    "near/precise/True/symmetric": 2e-14,  # 5.02e-15
    "near/precise/q": 3e-11,  # 7.09e-12
    "near/exact/False/spheres": 1e-14,  # 2.85e-15
    "near/exact/False/symmetric": 5e-16,  # 9.93e-17
    "near/exact/True/spheres": 1e-14,  # 2.85e-15
    "near/exact/True/symmetric": 5e-16,  # 9.93e-17
    "near/exact/q": 2e-12,  # 5.59e-13
    "grad/near/cf_i/0": 3e-15,  # 7.40e-16
    "grad/near/cf_i/1": 0.02,  # 6.42e-03
    "grad/near/cf_i/7": 4e-05,  # 1.07e-05
    "grad/near/cf_i/2": 3e-08,  # 9.51e-09
    "grad/near/cf_i/3": 3e-11,  # 6.93e-12
    "grad/near/cf_w": 2e-14,  # 5.32e-15
    "grad/near/fd": 4e-10,  # 1.20e-10
    "grad/near/sim_spheres": 4e-15,  # 1.13e-15
    "grad/near/sim_symmetric": 1.5e-07,  # 4.68e-08
    "flat/fast/w": 0.0003,  # 8.48e-05
    "flat/fast/q": 0.0008,  # 2.48e-04
    "flat/balanced/w": 1.5e-07,  # 3.60e-08
    "flat/balanced/q": 5e-08,  # 1.59e-08
    "flat/precise/w": 1.5e-11,  # 4.57e-12
    "flat/precise/q": 3e-11,  # 9.69e-12
    "flat/exact/w": 2e-12,  # 6.58e-13
    "flat/exact/q": 1e-10,  # 3.33e-11
    "scale/fast/fast/w": 0.0003,  # 8.60e-05
    "scale/fast/fast/energy": 8e-05,  # 2.03e-05
    "scale/slow/fast/w": 0.0003,  # 8.49e-05
    "scale/slow/fast/energy": 6e-05,  # 1.84e-05
    "scale/slow/fast/q": 0.002,  # 5.99e-04
    "scale/slow/fast/space": 0.00015,  # 4.33e-05
    "scale/fast/fast/q": 0.002,  # ran to max_steps (NaN) before simulate's NaN-safe error norm
    "scale/fast/fast/space": 0.00015,
    "scale/fast/balanced/w": 1.5e-07,  # 4.01e-08
    "scale/fast/balanced/energy": 6e-08,  # 1.88e-08
    "scale/fast/balanced/q": 8e-08,  # 2.15e-08
    "scale/fast/balanced/space": 8e-08,  # 2.60e-08
    "scale/slow/balanced/w": 1.5e-07,  # 3.49e-08
    "scale/slow/balanced/energy": 5e-08,  # 1.53e-08
    "scale/slow/balanced/q": 8e-08,  # 2.26e-08
    "scale/slow/balanced/space": 1.5e-07,  # 4.02e-08
    "scale/fast/precise/w": 1.5e-11,  # 4.59e-12
    "scale/fast/precise/energy": 3e-12,  # 9.90e-13
    "scale/fast/precise/q": 3e-11,  # 8.52e-12
    "scale/fast/precise/space": 4e-11,  # 1.03e-11
    "scale/slow/precise/w": 1.5e-11,  # 4.67e-12
    "scale/slow/precise/energy": 3e-12,  # 9.90e-13
    "scale/slow/precise/q": 3e-11,  # 8.55e-12
    "scale/slow/precise/space": 4e-11,  # 1.02e-11
    "scale/fast/exact/w": 2e-12,  # 6.58e-13
    "scale/fast/exact/energy": 2e-15,  # 5.55e-16
    "scale/fast/exact/q": 1e-10,  # 3.33e-11
    "scale/fast/exact/space": 3e-15,  # 9.32e-16
    "scale/slow/exact/w": 2e-12,  # 6.64e-13
    "scale/slow/exact/energy": 3e-15,  # 8.88e-16
    "scale/slow/exact/q": 1e-10,  # 3.33e-11
    "scale/slow/exact/space": 4e-15,  # 1.11e-15
    "grad/unit/cf": 2e-12,  # 6.35e-13
    "grad/unit/sim": 1e-07,  # 2.71e-08
    "grad/fast/cf": 1.5e-12,  # 4.67e-13
    "grad/slow/cf": 2e-12,  # 6.50e-13
    "grad/slow/sim": 1e-07,  # 2.71e-08
    "grad/fast/sim": 1e-07,  # NaN before the first-step fix in simulate
    "earth/fast/wobble": 0.00015,  # 4.94e-05
    "earth/fast/q": 0.15,  # 4.00e-02
    "earth/fast/space": 1.5e-07,  # 3.34e-08
    "earth/balanced/wobble": 1e-06,  # 2.86e-07
    "earth/balanced/q": 6e-06,  # 1.90e-06
    "earth/balanced/space": 4e-09,  # 1.09e-09
    "earth/precise/wobble": 1.5e-11,  # 4.46e-12
    "earth/precise/q": 1.5e-08,  # 3.60e-09
    "earth/precise/space": 3e-13,  # 8.93e-14
    "earth/exact/wobble": 1.5e-12,  # 4.43e-13
    "earth/exact/q": 1.5e-12,  # 4.55e-13
    "earth/exact/space": 3e-15,  # 7.87e-16
    "sep/fast/flip": 3,  # 7.69e-01
    "sep/fast/unstable": 1.5,  # 3.94e-01
    "sep/fast/stable": 3e-07,  # 8.78e-08
    "sep/balanced/flip": 0.03,  # 7.37e-03
    "sep/balanced/unstable": 0.015,  # 3.69e-03
    "sep/balanced/stable": 3e-09,  # 8.83e-10
    "sep/precise/flip": 0.00015,  # 4.38e-05
    "sep/precise/unstable": 0.003,  # 9.52e-04
    "sep/precise/stable": 3e-12,  # 9.55e-13
    "sep/exact/flip": 2e-14,  # 6.38e-15
    "sep/exact/unstable": 1.5e-14,  # 3.34e-15
    "sep/exact/stable": 2e-15,  # 5.55e-16
    "grad/sep/cf_w/perturbation 0 (equilibrium)": 8e-13,  # 2.03e-13
    "grad/sep/cf_w/1e-15": 8e-13,  # 2.03e-13
    "grad/sep/cf_w/1e-8": 6e-13,  # 1.99e-13
    "grad/sep/cf_i": 1.5e-15,  # 3.87e-16
    "grad/sep/sim": 0.015,  # 3.69e-03
    "grad/sep/sim_i": 2e-06,  # 6.05e-07
    "stability/value": 4e-16,  # 9.52e-17
    "stability/grad": 4e-16,  # 9.37e-17
    "sep/period/value": 1e-15,  # 2.98e-16
    "sep/period/grad": 1e-8,  # 3.35e-09
}


def check(extreme, key, area, case, behaviour, measured, advice):
    bound = BOUNDS[key]
    extreme(area, case, behaviour, measured, bound, advice)
    assert np.isfinite(measured) and measured <= bound, (key, measured, bound)


ADVICE = {
    "fast": "quick looks; ω only",
    "balanced": "default",
    "precise": "long or sensitive runs",
    "exact": "torque-free bodies: roundoff",
}


def _run(runs, group, preset, with_q):
    out = runs[group, preset, with_q]
    assert not isinstance(out, str), out
    omega, q, steps = out
    assert np.all(np.isfinite(omega)) and (q is None or np.all(np.isfinite(q)))
    return omega, q, steps


# --------------------------------------------------------------------------------------------------
# Near-spherical bodies and exact symmetric tops

NEAR_SPHERES = [0, 1, 2, 3, 7]
SYMMETRIC = [4, 5, 6]


@pytest.mark.slow
@pytest.mark.parametrize("preset", PRESETS)
def test_near_spherical_bodies(preset, groups, runs, references, extreme):
    inertia, omega0, ts = groups["near"]
    ref_w, ref_q = references["near"]
    scale = np.linalg.norm(omega0, axis=-1)
    area = "near-spherical body"
    for with_q in (False, True):
        omega, q, _ = _run(runs, "near", preset, with_q)
        err = rel_err(omega, ref_w, scale)
        # A sphere: Euler's right-hand side is exactly 0, so omega is constant to the last bit.
        assert err[0] == 0.0
        what = "with orientation" if with_q else "ω only"
        check(
            extreme,
            f"near/{preset}/{with_q}/spheres",
            area,
            f"moments equal to 0, 1e-15, 1e-12, 1e-9, 1e-6 relative, accuracy={preset!r}, {what}",
            "max |ω - ω_ref| / |ω0| over 20 s (ref: DOP853 on time rescaled by the moment gap)",
            np.max(err[NEAR_SPHERES]),
            "any preset",
        )
        check(
            extreme,
            f"near/{preset}/{with_q}/symmetric",
            area,
            f"exact symmetric tops I1 = I2 (1,1,1.8), (2,2,1), (1,1,1+1e-9), accuracy={preset!r}, {what}",
            "max |ω - ω_ref| / |ω0| over 20 s, ~2 wobble periods (ref: symmetric-top closed form)",
            np.max(err[SYMMETRIC]),
            ADVICE[preset],
        )
        if with_q:
            # Spheres and symmetric tops against the closed form; near-spheres against DOP853 (its own
            # error on q over 20 rad of rotation is ~5e-13).
            check(
                extreme,
                f"near/{preset}/q",
                area,
                f"sphere, near-spheres and symmetric tops, accuracy={preset!r}",
                "max |q - q_ref| over 20 s (~20 rad of rotation)",
                np.max(q_err(q, ref_q)),
                ADVICE[preset],
            )


# --------------------------------------------------------------------------------------------------
# Derivatives: jax.jacfwd of the closed form and jax.jacrev of simulate ("balanced", omega only) at the
# last sample, against the variational equations (DOP853) and central differences.

GRAD_T = {"near": 20.0, "unit": 40.0, "fast": 40e-5, "slow": 40e9, "sep": 20.0}


def _closed_form(inertia, omega0, t):
    return rj.torque_free_omega(inertia, omega0, t)


_cf_jacfwd = jax.jit(jax.jacfwd(_closed_form, argnums=(0, 1)))
_cf_value = jax.jit(_closed_form)


def _simulate_sum(inertia, omega0, ts):
    # Bodies are independent, so d(sum over bodies)/d(body b's inputs) is body b's own Jacobian.
    traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts, accuracy="balanced")
    return jnp.sum(traj.omega[:, -1, :], axis=0)


_sim_jacrev = jax.jit(jax.jacrev(_simulate_sum, argnums=(0, 1)))


def _blocks(jac):
    """(N, 3, N, 3) -> the per-body (N, 3, 3) blocks."""
    jac = np.asarray(jac)
    return np.stack([jac[b, :, b, :] for b in range(jac.shape[0])])


@pytest.fixture(scope="module")
def jacobians(groups):
    out = {}
    for name, t in GRAD_T.items():
        inertia, omega0, _ = groups[name]
        args = (jnp.asarray(inertia), jnp.asarray(omega0))
        cf = _cf_jacfwd(*args, jnp.full(N, t))
        sim = _sim_jacrev(*args, jnp.asarray(t * UNIT_TS))
        var = [variational(i, w, t) for i, w in zip(inertia, omega0, strict=True)]
        out[name] = {
            "cf": (_blocks(cf[0]), _blocks(cf[1])),
            "sim": tuple(np.transpose(np.asarray(j), (1, 0, 2)) for j in sim),
            "ref": (np.stack([v[1] for v in var]), np.stack([v[0] for v in var])),  # (d/dI, d/dw0)
        }
    return out


def jac_err(jac, ref):
    """Per body: max |jac - ref| / max |ref|."""
    size = np.max(np.abs(ref), axis=(1, 2))
    return np.max(np.abs(jac - ref), axis=(1, 2)) / np.where(size > 0, size, 1.0)


@pytest.mark.slow
def test_near_spherical_gradients(groups, jacobians, extreme):
    inertia, omega0, _ = groups["near"]
    jac = jacobians["near"]
    ref_i, ref_w = jac["ref"]
    area = "near-spherical body, gradients"
    cf_i = jac_err(jac["cf"][0], ref_i)
    # The flow is analytic in the moments, and d omega(t) / d inertia ~ t |omega|^2 / I stays O(1) as
    # the moments meet; the closed form's parametrisation (amplitudes, rate, m) has 1 / (I_j - I_k)
    # terms that cancel, so its derivative loses ~eps / gap. Measured per gap:
    gaps = np.array([0.0, 1e-15, 1e-9, 1e-6, 1e-9, 1e-9, 1e-9, 1e-12])
    for b, label in [
        (0, "d = 0 (sphere)"),
        (1, "d = 1e-15"),
        (7, "d = 1e-12"),
        (2, "d = 1e-9"),
        (3, "d = 1e-6"),
    ]:
        check(
            extreme,
            f"grad/near/cf_i/{b}",
            area,
            f"torque_free_omega, jax.jacfwd d ω(20 s)/d inertia, moments equal to {label}",
            "max abs error / max |J| vs the variational equations (DOP853)",
            cf_i[b],
            "smooth; for d < 1e-9 differentiate simulate instead" if b in (1, 7) else "any",
        )
    # The relative error grows like eps / gap, nowhere worse:
    eps = np.finfo(float).eps
    assert np.all(cf_i[1:] <= 1e2 * eps / gaps[1:] + 1e-12)
    check(
        extreme,
        "grad/near/cf_w",
        area,
        "torque_free_omega, jax.jacfwd d ω(20 s)/d ω0, spheres, near-spheres, symmetric tops",
        "max abs error / max |J| vs the variational equations",
        np.max(jac_err(jac["cf"][1], ref_w)),
        "any",
    )
    # Central differences of the closed form (step 1e-6 relative): the flow is smooth in the moments
    # at any gap, and the differences agree with the variational equations where jacfwd does not.
    h = 1e-6
    fd = np.zeros((N, 3, 3))
    for k in range(3):
        step = np.zeros((N, 3))
        step[:, k] = h * inertia[:, k]
        plus = np.asarray(_cf_value(jnp.asarray(inertia + step), jnp.asarray(omega0), jnp.full(N, 20.0)))
        minus = np.asarray(_cf_value(jnp.asarray(inertia - step), jnp.asarray(omega0), jnp.full(N, 20.0)))
        fd[:, :, k] = (plus - minus) / (2 * step[:, k : k + 1])
    check(
        extreme,
        "grad/near/fd",
        area,
        "central differences (step 1e-6 relative) of torque_free_omega w.r.t. inertia, all gaps",
        "max abs error / max |J| vs the variational equations",
        np.max(jac_err(fd, ref_i)),
        "FD with a step >> the moment gap is fine: the flow is analytic in I",
    )
    sim_i, sim_w = jac["sim"]
    check(
        extreme,
        "grad/near/sim_spheres",
        area,
        "simulate('balanced') jax.jacrev d ω(20 s)/d (inertia, ω0), sphere and near-spheres",
        "max abs error / max |J| vs the variational equations",
        max(np.max(jac_err(sim_i, ref_i)[NEAR_SPHERES]), np.max(jac_err(sim_w, ref_w)[NEAR_SPHERES])),
        "any",
    )
    check(
        extreme,
        "grad/near/sim_symmetric",
        area,
        "simulate('balanced') jax.jacrev d ω(20 s)/d (inertia, ω0), symmetric tops",
        "max abs error / max |J| vs the variational equations",
        max(np.max(jac_err(sim_i, ref_i)[SYMMETRIC]), np.max(jac_err(sim_w, ref_w)[SYMMETRIC])),
        "balanced: ~rtol",
    )


# --------------------------------------------------------------------------------------------------
# The flat plate I3 = I1 + I2, and just beyond it

PLATES = [0, 1, 2, 3, 7]


@pytest.mark.slow
@pytest.mark.parametrize("preset", PRESETS)
def test_flat_plate_limit(preset, groups, runs, references, extreme):
    inertia, omega0, ts = groups["unit"]
    ref_w, ref_q = references["unit"]
    scale = np.linalg.norm(omega0, axis=-1)
    area = "flat plate I3 = I1 + I2"
    omega, _, _ = _run(runs, "unit", preset, False)
    _, q, _ = _run(runs, "unit", preset, True)
    check(
        extreme,
        f"flat/{preset}/w",
        area,
        f"(1,2,3) twice, disc (1,1,2), rod-like (1e-3,1,1.001), (1,2,3(1+1e-14)); accuracy={preset!r}",
        "max |ω - ω_ref| / |ω0| over 40 s, ~3 wobble periods (ref: DOP853"
        + ("; at 'exact' this is DOP853's own error)" if preset == "exact" else ")"),
        np.max(rel_err(omega, ref_w, scale)[PLATES]),
        ADVICE[preset],
    )
    check(
        extreme,
        f"flat/{preset}/q",
        area,
        f"the same plates with orientation, accuracy={preset!r}",
        "max |q - q_ref| over 40 s (ref: DOP853)",
        np.max(q_err(q, ref_q)[PLATES]),
        ADVICE[preset],
    )


@pytest.mark.slow
def test_beyond_the_flat_plate_is_rejected(groups, runs, extreme):
    """check_inertia allows the triangle equality up to 1e2 eps trace: for (1, 2, 3(1 + x)) that is
    x <= 200 eps = 4.4e-14. x = 1e-14 is accepted (and moves like the plate, test above); x = 1e-13
    and 1e-12 are rejected, by simulate with every preset (a ValueError before integrating; inside
    the user's jit an EquinoxRuntimeError, test_bad_input) and by spin_stability."""
    eps = np.finfo(float).eps
    for x, ok in [(0.0, True), (1e-14, True), (150 * eps, True), (1e-13, False), (1e-12, False)]:
        assert bool(rj.is_physical_inertia(jnp.array([1.0, 2.0, 3.0 * (1 + x)]))) == ok, x
    inertia, omega0, ts = groups["unit"]
    bad = inertia.copy()
    bad[7] = [1.0, 2.0, 3.0 * (1 + 1e-12)]
    model = rj.FreeBody(jnp.asarray(bad))  # construction does not check values; simulate does
    for preset in PRESETS:
        for with_q in (False, True):
            state = rj.State(jnp.asarray(omega0), jnp.tile(Q_ID, (N, 1)) if with_q else None)
            with pytest.raises(ValueError, match="triangle inequality"):
                rj.simulate(model, state, jnp.asarray(ts), accuracy=preset).omega.block_until_ready()
    with pytest.raises(ValueError, match="triangle inequality"):  # eager: checked on the host
        rj.spin_stability(jnp.asarray(bad), 1.0).growth_rate.block_until_ready()
    extreme(
        "flat plate I3 = I1 + I2",
        "I3 = (I1 + I2)(1 + x): x <= 4.4e-14 (1e2 eps trace) accepted, x = 1e-13, 1e-12 rejected",
        "simulate (all presets; inside jit too) and spin_stability raise 'violates the triangle inequality'",
        None,
        None,
        "moments from measurements: round onto the plate",
    )


def test_closed_forms_reject_beyond_the_flat_plate(groups):
    inertia, omega0, _ = groups["unit"]
    bad = inertia.copy()
    bad[7] = [1.0, 2.0, 3.0 * (1 + 1e-12)]
    # Under the test's own jax.jit the error arrives as a JaxRuntimeError carrying the message.
    with pytest.raises(Exception, match="triangle inequality"):
        _cf_value(jnp.asarray(bad), jnp.asarray(omega0), jnp.full(N, 1.0)).block_until_ready()
    with pytest.raises(ValueError, match="triangle inequality"):
        rj.torque_free_period(jnp.asarray(bad), jnp.asarray(omega0))


# --------------------------------------------------------------------------------------------------
# SI scales: 1e5 rad/s and 1e-9 rad/s, moments from 1e-9 to 8e37 kg m^2, the Earth

SCALES = {"fast": "|ω0| ~ 1e5 rad/s", "slow": "|ω0| ~ 1e-9 rad/s"}


@pytest.mark.slow
@pytest.mark.parametrize("preset", PRESETS)
def test_dimensionless_tolerances_at_si_scales(preset, groups, runs, references, extreme):
    """The same eight dimensionless bodies at |omega| ~ 1 and rescaled to SI extremes (omega s,
    t / s, inertia alternately 1e-9 and 8e37 kg m^2) come out with the same relative errors and the
    same number of steps: the tolerances are dimensionless, as _simulate.py's docstring says."""
    area = "SI scales"
    unit_w, _, unit_steps = _run(runs, "unit", preset, False)
    unit_err = rel_err(unit_w, references["unit"][0], np.linalg.norm(groups["unit"][1], axis=-1))
    for name, label in SCALES.items():
        inertia, omega0, ts = groups[name]
        ref_w, ref_q = references[name]
        omega, _, steps = _run(runs, name, preset, False)
        err = rel_err(omega, ref_w, np.linalg.norm(omega0, axis=-1))
        # Dimensionless: the same error to a few roundoff units, not a tolerance rescaled by 1e5.
        assert np.all(err <= 1.5 * unit_err + 1e-14), (name, err, unit_err)
        if preset != "exact":
            assert abs(int(steps[0]) - int(unit_steps[0])) <= 0.15 * int(unit_steps[0]), (steps, unit_steps)
        check(
            extreme,
            f"scale/{name}/{preset}/w",
            area,
            f"{label}, inertia 1e-9 and 8e37 kg m^2, accuracy={preset!r}, ω only",
            "max |ω - ω_ref| / |ω0| over ~3 wobble periods (same as at |ω0| ~ 1)"
            + ("; at 'exact' DOP853's own error" if preset == "exact" else ""),
            np.max(err),
            ADVICE[preset],
        )
        drift = invariants(inertia, omega)
        check(
            extreme,
            f"scale/{name}/{preset}/energy",
            area,
            f"{label}, energy 0.5 ω·Iω and |L|, accuracy={preset!r}, ω only",
            "max relative drift of energy and |L| over ~3 wobble periods",
            max(np.max(drift["energy"]), np.max(drift["momentum"])),
            ADVICE[preset],
        )
        omega, q, _ = _run(runs, name, preset, True)
        check(
            extreme,
            f"scale/{name}/{preset}/q",
            area,
            f"{label}, inertia 1e-9 and 8e37 kg m^2, accuracy={preset!r}, with orientation",
            "max |q - q_ref| over ~40 rad of rotation",
            np.max(q_err(q, ref_q)),
            ADVICE[preset],
        )
        drift = invariants(inertia, omega, q)
        check(
            extreme,
            f"scale/{name}/{preset}/space",
            area,
            f"{label}, space-frame L, accuracy={preset!r}",
            "max |L_space(t) - L_space(0)| / |L| over ~3 wobble periods",
            np.max(drift["space"]),
            ADVICE[preset],
        )


@pytest.mark.slow
def test_si_scale_gradients(jacobians, extreme):
    area = "SI scales, gradients"
    for name, label in [("unit", "|ω0| ~ 1"), *SCALES.items()]:
        jac = jacobians[name]
        ref_i, ref_w = jac["ref"]
        check(
            extreme,
            f"grad/{name}/cf",
            area,
            f"{label}: torque_free_omega jax.jacfwd d ω/d (inertia, ω0) after ~3 wobble periods",
            "max abs error / max |J| vs the variational equations (flat plates included)",
            max(np.max(jac_err(jac["cf"][0], ref_i)), np.max(jac_err(jac["cf"][1], ref_w))),
            "any",
        )
        sim_i, sim_w = jac["sim"]
        check(
            extreme,
            f"grad/{name}/sim",
            area,
            f"{label}: simulate('balanced') jax.jacrev d ω/d (inertia, ω0) after ~3 wobble periods",
            "max abs error / max |J| vs the variational equations",
            max(np.max(jac_err(sim_i, ref_i)), np.max(jac_err(sim_w, ref_w))),
            "balanced",
        )


@pytest.mark.slow
@pytest.mark.parametrize("preset", PRESETS)
def test_earth(preset, groups, runs, references, extreme):
    """The Earth in SI units: A = 8.0101e37 kg m^2, (C - A) / A = 3.27e-3, omega3 = 7.29e-5 rad/s, with
    wobbles of 0 to 0.3 of the spin (and triaxial, (B - A) / A = 2.2e-5), over 2.5 Euler periods (770
    turns). The wobble is measured relative to its own amplitude (per-component scales)."""
    inertia, omega0, ts = groups["earth"]
    ref_w, ref_q = references["earth"]
    area = "SI scales: the Earth"
    tilt = np.hypot(omega0[:, 0], omega0[:, 1])
    wobbling = tilt > 0
    omega, _, _ = _run(runs, "earth", preset, False)
    wobble = np.max(np.linalg.norm(omega[..., :2] - ref_w[..., :2], axis=-1), -1)
    assert np.all(omega[~wobbling] == omega0[~wobbling][:, None])  # pure spin stays exact
    check(
        extreme,
        f"earth/{preset}/wobble",
        area,
        f"wobble 1e-9 to 0.3 of the spin, accuracy={preset!r}, ω only",
        "max |ω_⊥ - ref| / wobble amplitude over 2.5 Euler periods",
        np.max(wobble[wobbling] / tilt[wobbling]),
        ADVICE[preset],
    )
    omega, q, _ = _run(runs, "earth", preset, True)
    symmetric = [b for b in range(N) if ref_q[b] is not None]
    check(
        extreme,
        f"earth/{preset}/q",
        area,
        f"symmetric Earth with orientation, accuracy={preset!r}",
        "max |q - q_ref| after 770 turns (ref: symmetric-top closed form)",
        max(np.max(q_distance(q[b], ref_q[b])) for b in symmetric),
        ADVICE[preset],
    )
    drift = invariants(inertia, omega, q)
    check(
        extreme,
        f"earth/{preset}/space",
        area,
        f"space-frame L and energy, symmetric and triaxial, accuracy={preset!r}",
        "max relative drift over 770 turns",
        max(np.max(drift["space"]), np.max(drift["energy"])),
        ADVICE[preset],
    )


# --------------------------------------------------------------------------------------------------
# Starting exactly on the separatrix: spin about the intermediate axis of (1, 2.5, 3)

UNSTABLE = [1, 2, 6, 7]
STABLE = [3, 4]
EQUILIBRIA = [0, 5]


@pytest.mark.slow
@pytest.mark.parametrize("preset", PRESETS)
def test_separatrix(preset, groups, runs, references, extreme):
    inertia, omega0, ts = groups["sep"]
    ref_w, _ = references["sep"]
    area = "separatrix (intermediate axis)"
    lam = 0.5  # W sqrt((I3 - I2)(I2 - I1) / (I1 I3)) with W = 1 + O(1e-16)
    for with_q in (False, True):
        omega, q, _ = _run(runs, "sep", preset, with_q)
        # Exactly on the axis Euler's right-hand side is exactly 0: an equilibrium for every method.
        assert np.all(omega[EQUILIBRIA] == omega0[EQUILIBRIA][:, None])
        if with_q:
            drift = invariants(inertia, omega, q)
            # precise: 1.3e-11 measured (the same step as without the orientation)
            assert np.max(drift["space"]) < {"fast": 1e-4, "balanced": 1e-7}.get(preset, 4e-11)
            continue
        err = np.linalg.norm(omega - ref_w, axis=-1)  # |omega0| = 1
        flips = []
        for b in UNSTABLE:
            t0 = separatrix(SEP_I, omega0[b], [0.0])[1]
            k = int(np.argmin(np.abs(ts - t0)))
            assert abs(ts[k] - t0) < 1e-12 * t0  # a sample at the flip
            flips.append(abs(omega[b, k, 1]) / lam)  # omega2 crosses 0 with slope -+W lam
        check(
            extreme,
            f"sep/{preset}/flip",
            area,
            f"perturbation 1e-15 (flip at 70.0 s), 1e-8 (37.8 s), unstable branch, accuracy={preset!r}",
            "flip-time error |ω2(t_flip)| / (W λ) (s), t_flip from the heteroclinic solution",
            max(flips),
            "exact" if preset != "exact" else "exact: any perturbation",
        )
        check(
            extreme,
            f"sep/{preset}/unstable",
            area,
            f"perturbation 1e-15, 1e-8 on the unstable branch, accuracy={preset!r}",
            "max |ω - ω_ref| / |ω0| over 100 s (one flip, then the approach to -axis)",
            np.max(err[UNSTABLE]),
            "exact" if preset != "exact" else "exact",
        )
        window = ts <= 30.0
        check(
            extreme,
            f"sep/{preset}/stable",
            area,
            f"perturbation 1e-15, 1e-8 on the stable manifold, accuracy={preset!r}",
            "max |ω - ω_ref| / |ω0| over 30 s (before roundoff, amplified by exp(λ t), takes over)",
            np.max(err[STABLE][:, window]),
            "any; no method follows the stable manifold past ~35 s",
        )
        if preset == "exact":
            # Past the closest approach (~sqrt(eps) times the perturbation) even the closed form leaves
            # the axis: the separatrix defect L^2 - 2 E I2 of the float input is only known to
            # ~eps L^2 (the jitted sum rounds differently from exact zero), and the motion
            # amplifies that by exp(lambda t). Backward stable, but not the exact stable manifold.
            extreme(
                area,
                "perturbation 1e-8 on the stable manifold, accuracy='exact', 100 s",
                "closest approach ~1e-16 at ~37 s, then leaves the axis as an eps-perturbed input would",
                np.max(err[STABLE]),
                1e-2,
                "no float method can do better",
            )
            assert np.max(err[STABLE]) <= 1e-2


@pytest.mark.slow
def test_separatrix_gradients(groups, jacobians, extreme):
    """d omega(t) / d omega0 is the flow's derivative: finite on the separatrix and at the equilibrium,
    growing like cosh(lambda t) (lambda = 0.5 here). torque_free_omega now carries it at steady
    rotations too (the linearised flow exp(J t)); simulate differentiates its own steps."""
    inertia, omega0, _ = groups["sep"]
    jac = jacobians["sep"]
    ref_i, ref_w = jac["ref"]
    area = "separatrix, gradients"
    size = np.max(np.abs(ref_w), axis=(1, 2))
    np.testing.assert_allclose(size, np.cosh(0.5 * 20.0), rtol=2e-3)  # the size is the growth
    cf_w = jac_err(jac["cf"][1], ref_w)
    for idx, label in [
        (EQUILIBRIA, "perturbation 0 (equilibrium)"),
        ([1, 3], "1e-15"),
        ([2, 4, 6, 7], "1e-8"),
    ]:
        check(
            extreme,
            f"grad/sep/cf_w/{label}",
            area,
            f"torque_free_omega jax.jacfwd d ω(20 s)/d ω0, {label}; |J| = cosh(λ t) = 1.1e4",
            "max abs error / max |J| vs the variational equations",
            np.max(cf_w[idx]),
            "finite; grows like exp(λ t)",
        )
    # d omega / d inertia vanishes at the equilibrium and is O(perturbation) near it: compare in
    # absolute terms, relative to |omega| t / I.
    check(
        extreme,
        "grad/sep/cf_i",
        area,
        "torque_free_omega jax.jacfwd d ω(20 s)/d inertia, perturbations 0, 1e-15, 1e-8",
        "max |J - J_ref| / (|ω0| t / I1)",
        np.max(np.abs(jac["cf"][0] - ref_i)) / 20.0,
        "any",
    )
    sim_i, sim_w = jac["sim"]
    check(
        extreme,
        "grad/sep/sim",
        area,
        "simulate('balanced') jax.jacrev d ω(20 s)/d ω0, perturbations 0, 1e-15, 1e-8",
        "max abs error / max |J| vs the variational equations",
        np.max(jac_err(sim_w, ref_w)),
        "balanced",
    )
    check(
        extreme,
        "grad/sep/sim_i",
        area,
        "simulate('balanced') jax.jacrev d ω(20 s)/d inertia, perturbations 0, 1e-15, 1e-8",
        "max |J - J_ref| / (|ω0| t / I1)",
        np.max(np.abs(sim_i - ref_i)) / 20.0,
        "balanced",
    )


# --------------------------------------------------------------------------------------------------
# spin_stability at near-spheres, spheres and symmetric tops, against 40-digit mpmath


def _lambda2(inertia, i):
    a, b, c = inertia[i], inertia[(i + 1) % 3], inertia[(i + 2) % 3]
    return (a - b) * (c - a) / (b * c)


def test_spin_stability_near_spheres(extreme):
    inertia = NEAR_I
    omega = 0.7
    result = rj.spin_stability(jnp.asarray(inertia), omega)
    growth, freq = np.asarray(result.growth_rate), np.asarray(result.frequency)

    def rates(i):
        out = rj.spin_stability(i, omega)
        return out.growth_rate, out.frequency

    jac_g, jac_f = (_blocks(j) for j in jax.jit(jax.jacfwd(rates))(jnp.asarray(inertia)))
    assert np.all(np.isfinite(jac_g)) and np.all(np.isfinite(jac_f))
    value_err, grad_err = 0.0, 0.0
    with mp.workdps(40):
        for b in range(N):
            moments = [mp.mpf(float(x)) for x in inertia[b]]
            for i in range(3):
                l2 = _lambda2(moments, i)
                ref_g = omega * mp.sqrt(l2) if l2 > 0 else mp.mpf(0)
                ref_f = omega * mp.sqrt(-l2) if l2 < 0 else mp.mpf(0)
                for value, ref in ((growth[b, i], ref_g), (freq[b, i], ref_f)):
                    if ref == 0:
                        assert value == 0.0
                    else:
                        value_err = max(value_err, float(abs(value - ref) / ref))
                if l2 == 0:  # a sphere or a degenerate axis: the kink of sqrt; the gradient is 0
                    assert result.marginal[b, i]
                    assert np.all(jac_g[b, i] == 0) and np.all(jac_f[b, i] == 0)
                    continue
                for k in range(3):  # d/d I_k of omega sqrt(+-lambda^2), analytic where lambda^2 != 0

                    def rate(x, i=i, k=k, sign=1 if l2 > 0 else -1, moments=moments):
                        m = list(moments)
                        m[k] = x
                        return omega * mp.sqrt(sign * _lambda2(m, i))

                    ref = mp.diff(rate, moments[k])
                    got = (jac_g if l2 > 0 else jac_f)[b, i, k]
                    grad_err = max(grad_err, float(abs(got - ref) / (abs(ref) + omega)))
    assert np.all(np.asarray(result.marginal[0]))  # the sphere
    check(
        extreme,
        "stability/value",
        "near-spherical body, spin_stability",
        "growth rate and nutation frequency, moments equal to 0, 1e-15, 1e-12, 1e-9, 1e-6, symmetric tops",
        "max relative error vs 40-digit mpmath (moment differences are exact: Sterbenz)",
        value_err,
        "any",
    )
    check(
        extreme,
        "stability/grad",
        "near-spherical body, spin_stability",
        "jax.jacfwd d(rate)/d inertia, the same bodies, where λ^2 != 0 (0 at a sphere's kink)",
        "max |J - J_ref| / (|J_ref| + Ω) vs mpmath.diff",
        grad_err,
        "any",
    )


def test_period_near_the_separatrix(extreme):
    """torque_free_period for omega0 = (0, 1, d): T ~ (4 / lambda) log(1 / d) diverges on the separatrix
    and dT/dd ~ -4 / (lambda d) blows up like 1 / d. Both against 40-digit mpmath (Landau & Lifshitz:
    T = 4 K(m) / rate); exactly on the separatrix T = inf."""
    deltas = [1e-1, 1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12, 0.0]
    inertia = np.tile(SEP_I, (N, 1))
    omega0 = np.array([[0.0, 1.0, d] for d in deltas])

    def period_of(d):
        w = omega0.copy()
        w[:, 2] = d
        return np.asarray(rj.torque_free_period(jnp.asarray(inertia), jnp.asarray(w)))

    period = period_of(omega0[:, 2])
    assert period[-1] == np.inf
    # Central differences with a step 1e-4 d (jax.jacfwd of the period is a 9 s compile here;
    # tests/test_torque_free.py differentiates it): truncation ~1e-8, roundoff ~1e-11 relative.
    d = omega0[:-1, 2]
    h = 1e-4 * d
    grad = (period_of(np.append(d + h, 0.0))[:-1] - period_of(np.append(d - h, 0.0))[:-1]) / (2 * h)

    def reference(d):
        I1, I2, I3 = (mp.mpf(float(x)) for x in SEP_I)
        w = [mp.mpf(0), mp.mpf(1), d]
        L2 = sum((i * x) ** 2 for i, x in zip((I1, I2, I3), w, strict=True))
        E2 = sum(i * x**2 for i, x in zip((I1, I2, I3), w, strict=True))
        rate = mp.sqrt((I3 - I2) * (L2 - E2 * I1) / (I1 * I2 * I3))
        m = (I2 - I1) * (E2 * I3 - L2) / ((I3 - I2) * (L2 - E2 * I1))
        return 4 * mp.ellipk(m) / rate

    value_err, grad_err, sizes = 0.0, 0.0, []
    with mp.workdps(40):
        for b, d in enumerate(deltas[:-1]):
            d = mp.mpf(d)
            value_err = max(value_err, float(abs(period[b] - reference(d)) / reference(d)))
            slope = mp.diff(reference, d)
            grad_err = max(grad_err, float(abs(grad[b] - slope) / abs(slope)))
            sizes.append(float(abs(slope) * d))
    # The blow-up: d |dT/dd| -> 4 / lambda = 8 (lambda = 0.5) as d -> 0.
    assert abs(sizes[-1] - 8.0) < 1e-6
    check(
        extreme,
        "sep/period/value",
        "separatrix (intermediate axis)",
        "torque_free_period, ω0 = (0, 1, d), d = 1e-1 ... 1e-12 (T = 27.6 s ... 230 s)",
        "max relative error of T vs 40-digit mpmath",
        value_err,
        "any",
    )
    check(
        extreme,
        "sep/period/grad",
        "separatrix (intermediate axis)",
        "central differences dT/dd, the same d: grow like 4 / (λ d) (8e12 s at d = 1e-12)",
        "max relative error vs mpmath.diff",
        grad_err,
        "finite off the separatrix, diverges on it",
    )
