"""Lie–Poisson splitting for the free rigid body: orders, invariants, diffrax wrapper, batch, float32."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rigidjax._quaternion import matrix_from_quat, quat_normalize, quat_rotate
from rigidjax._splitting import (
    LiePoissonSplitting,
    free_body_vector_field,
    split_free_body,
    splitting_step,
)
from rigidjax._torque_free import torque_free_omega

# Asymmetric body, well away from the separatrix (L^2 - 2 E I2 = 2.5 - ... clearly nonzero).
INERTIA = jnp.array([1.0, 2.0, 3.0])
OMEGA0 = jnp.array([1.0, 0.1, 0.5])
L0 = INERTIA * OMEGA0
Q0 = quat_normalize(jnp.array([0.9, 0.1, -0.3, 0.2]))
T = 5.0


def _energy(L):
    return 0.5 * jnp.sum(L * L / INERTIA.astype(L.dtype), axis=-1)


def _reference(T_end):
    """Tight Dopri8 solution of (L, q)."""
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(free_body_vector_field(INERTIA)),
        diffrax.Dopri8(),
        0.0,
        T_end,
        0.01,
        (L0, Q0),
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=100_000,
    )
    return sol.ys[0][-1], sol.ys[1][-1]


@pytest.mark.parametrize("order", [2, 4])
def test_convergence_order(order):
    L_exact = INERTIA * torque_free_omega(INERTIA, OMEGA0, jnp.asarray(T))
    L_ref, q_ref = _reference(T)
    assert jnp.max(jnp.abs(L_ref - L_exact)) < 1e-12  # the reference agrees with the closed form
    R_ref = matrix_from_quat(q_ref)
    hs, err_L, err_R = [], [], []
    for n in (50, 100, 200, 400):
        L, q = split_free_body(INERTIA, L0, Q0, T / n, n, order)
        hs.append(T / n)
        err_L.append(float(jnp.max(jnp.abs(L - L_exact))))
        err_R.append(float(jnp.max(jnp.abs(matrix_from_quat(q) - R_ref))))
    slope_L = np.polyfit(np.log(hs), np.log(err_L), 1)[0]
    slope_R = np.polyfit(np.log(hs), np.log(err_R), 1)[0]
    print(f"order {order}: L errors {err_L} slope {slope_L:.4f}; R errors {err_R} slope {slope_R:.4f}")
    assert abs(slope_L - order) < 0.1
    assert abs(slope_R - order) < 0.1
    assert err_L[-1] < (1e-5 if order == 2 else 1e-8)


def _run_recording(step, n_steps, dt):
    def body(state, _):
        state = step(*state, dt)
        L, q = state
        return state, (_energy(L), jnp.linalg.norm(L), jnp.linalg.norm(q), quat_rotate(q, L))

    return jax.jit(lambda s: jax.lax.scan(body, s, None, length=n_steps))((L0, Q0))


def test_invariants_long_run():
    n, dt = 100_000, 0.01
    _, (E, normL, normq, Lspace) = _run_recording(
        lambda L, q, h: splitting_step(INERTIA, L, q, h, 2), n, jnp.asarray(dt)
    )
    E0, normL0, Ls0 = _energy(L0), jnp.linalg.norm(L0), quat_rotate(Q0, L0)
    rel_L = float(jnp.max(jnp.abs(normL - normL0)) / normL0)
    q_dev = float(jnp.max(jnp.abs(normq - 1.0)))
    dE = jnp.abs(E - E0) / E0
    first, second = float(jnp.max(dE[: n // 2])), float(jnp.max(dE[n // 2 :]))
    space = float(jnp.max(jnp.linalg.norm(Lspace - Ls0, axis=-1)) / normL0)
    print(
        f"1e5 Strang steps dt={dt}: max rel ||L| drift {rel_L:.2e}, max ||q|-1| {q_dev:.2e}, "
        f"max |dE/E| first half {first:.3e}, second half {second:.3e}, space-L drift {space:.2e}"
    )
    assert rel_L < 1e-14 * 10  # a few ulps accumulated over 1e5 rotations; see the report
    assert q_dev < 1e-13
    assert second <= 2.0 * first
    assert first < 1e-3
    assert space < 1e-12


def _rk4_step(L, q, h):
    vf = free_body_vector_field(INERTIA)

    def f(y):
        return vf(0.0, y, None)

    def add(y, k, a):
        return jax.tree_util.tree_map(lambda u, v: u + a * v, y, k)

    y = (L, q)
    k1 = f(y)
    k2 = f(add(y, k1, 0.5 * h))
    k3 = f(add(y, k2, 0.5 * h))
    k4 = f(add(y, k3, h))
    return jax.tree_util.tree_map(
        lambda u, a, b, c, d: u + h / 6.0 * (a + 2 * b + 2 * c + d), y, k1, k2, k3, k4
    )


def test_space_angular_momentum_vs_rk4():
    n, dt = 20_000, jnp.asarray(0.05)
    Ls0, normL0 = quat_rotate(Q0, L0), jnp.linalg.norm(L0)
    _, (Es, _, _, Ls_split) = _run_recording(lambda L, q, h: splitting_step(INERTIA, L, q, h, 2), n, dt)
    _, (Er, _, nq_rk4, Ls_rk4) = _run_recording(_rk4_step, n, dt)
    drift_split = float(jnp.linalg.norm(Ls_split[-1] - Ls0) / normL0)
    drift_rk4 = float(jnp.linalg.norm(Ls_rk4[-1] - Ls0) / normL0)
    E0 = _energy(L0)
    dE_split = float(jnp.max(jnp.abs(Es - E0)) / E0)
    dE_rk4 = float(jnp.abs(Er[-1] - E0) / E0)
    print(
        f"{n} steps dt=0.05: space-L drift split {drift_split:.2e} vs RK4 {drift_rk4:.2e}; "
        f"|dE/E| split max {dE_split:.2e} vs RK4 final {dE_rk4:.2e}; "
        f"RK4 ||q|-1| {abs(float(nq_rk4[-1]) - 1):.2e}"
    )
    assert drift_split < 1e-11
    assert drift_rk4 > 1e3 * drift_split


@pytest.mark.parametrize("order", [2, 4])
def test_diffrax_wrapper_matches(order):
    n = 100
    dt = T / n
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(free_body_vector_field(INERTIA)),
        LiePoissonSplitting(INERTIA, order=order),
        0.0,
        T,
        dt,
        (L0, Q0),
        stepsize_controller=diffrax.ConstantStepSize(),
        saveat=diffrax.SaveAt(t1=True),
    )
    L, q = split_free_body(INERTIA, L0, Q0, dt, n, order)
    assert sol.stats["num_steps"] == n
    np.testing.assert_allclose(sol.ys[0][-1], L, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.ys[1][-1], q, rtol=0, atol=1e-12)
    assert LiePoissonSplitting(INERTIA, order=order).order(None) == order


def test_diffrax_wrapper_dense_and_ts():
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(free_body_vector_field(INERTIA)),
        LiePoissonSplitting(INERTIA),
        0.0,
        1.0,
        0.01,
        (L0, Q0),
        stepsize_controller=diffrax.ConstantStepSize(),
        saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, 1.0, 11)),
    )
    L_exact = INERTIA * torque_free_omega(INERTIA[None], OMEGA0[None], jnp.linspace(0.0, 1.0, 11))
    assert jnp.max(jnp.abs(sol.ys[0] - L_exact)) < 1e-4


def test_bad_order():
    with pytest.raises(ValueError):
        LiePoissonSplitting(INERTIA, order=3)
    with pytest.raises(ValueError):
        split_free_body(INERTIA, L0, Q0, 0.1, 10, order=3)


def test_batch_vmap_and_broadcast():
    key = jax.random.PRNGKey(0)
    k1, k2, k3 = jax.random.split(key, 3)
    B = 16
    inertia = jnp.sort(jax.random.uniform(k1, (B, 3), minval=1.0, maxval=3.0), axis=-1)
    omega0 = jax.random.normal(k2, (B, 3))
    q0 = quat_normalize(jax.random.normal(k3, (B, 4)))
    n = 400
    run = jax.vmap(lambda I, L, q: split_free_body(I, L, q, T / n, n, 4))
    L_v, q_v = run(inertia, inertia * omega0, q0)
    L_b, q_b = split_free_body(inertia, inertia * omega0, q0, T / n, n, 4)  # leading batch axis
    np.testing.assert_allclose(L_v, L_b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(q_v, q_b, rtol=0, atol=1e-12)
    L_exact = inertia * torque_free_omega(inertia, omega0, jnp.asarray(T))
    err = jnp.max(jnp.abs(L_v - L_exact), axis=-1) / jnp.linalg.norm(L_exact, axis=-1)
    assert jnp.all(err < 1e-5)
    for b in (0, 7):
        L1, q1 = split_free_body(inertia[b], inertia[b] * omega0[b], q0[b], T / n, n, 4)
        np.testing.assert_allclose(L1, L_v[b], rtol=0, atol=1e-12)


@pytest.mark.parametrize("order", [2, 4])
def test_float32(order):
    I32, L32, q32 = INERTIA.astype(jnp.float32), L0.astype(jnp.float32), Q0.astype(jnp.float32)
    n = 10_000
    L, q = split_free_body(I32, L32, q32, np.float32(0.01), n, order)
    assert L.dtype == jnp.float32 and q.dtype == jnp.float32
    L_exact = INERTIA * torque_free_omega(INERTIA, OMEGA0, jnp.asarray(0.01 * n))
    normL0 = float(jnp.linalg.norm(L0))
    rel_norm = abs(float(jnp.linalg.norm(L.astype(jnp.float64))) - normL0) / normL0
    q_dev = abs(float(jnp.linalg.norm(q.astype(jnp.float64))) - 1.0)
    err = float(jnp.max(jnp.abs(L.astype(jnp.float64) - L_exact)))
    print(
        f"float32 order {order}, 1e4 steps: rel |L| drift {rel_norm:.2e}, "
        f"||q|-1| {q_dev:.2e}, L err {err:.2e}"
    )
    assert rel_norm < 1e-4
    assert q_dev < 1e-4
    assert err < 1e-2
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(free_body_vector_field(I32)),
        LiePoissonSplitting(I32, order=order),
        jnp.float32(0.0),  # float32 times: diffrax promotes y0 to the time dtype
        jnp.float32(1.0),
        jnp.float32(0.01),
        (L32, q32),
        stepsize_controller=diffrax.ConstantStepSize(),
    )
    assert sol.ys[0].dtype == jnp.float32
