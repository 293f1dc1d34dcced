"""Batch-integration strategies for N torque-free rigid bodies: a work-precision comparison.

Decides how ``rigidjax.simulate`` should integrate a batch of bodies. Standalone: it does not
import rigidjax, so every strategy uses the very same right-hand side written here.

Scene (fixed): principal moments I_k = (1, 2, 2.5) * (1 + 0.05 u_k), u_k ~ U(-1, 1)^3, then
omega0_k = (0.05, 4.0, 0.05) + 0.01 n_k, n_k ~ N(0, 1)^3, both from numpy default_rng(0); identity
orientation; integrate to T = 20 s; only the final state matters. The bodies spin near the
intermediate (unstable) axis and flip several times, so errors are amplified.

State per body: omega (3) and the scalar-first quaternion q (4); Euler's equations
I1 w1' = (I2 - I3) w2 w3 (cyclic) and dq/dt = q (x) (0, omega) / 2.

Strategies
  A  jax.jit(jax.vmap(diffeqsolve)): per-body adaptive step ("user-written"); state (N, 7).
  B  one diffeqsolve over the whole batch; PIDController(norm=optx.max_norm); (N, 7) and (7, N).
     B-rms: the same with diffrax's default RMS norm, to show that it under-resolves hard bodies.
  C  hand-written fixed-step RK4, state (7, N), lax.fori_loop; also lax.map over chunks.
  D  B in chunks: lax.map over chunks, each chunk one shared-step diffeqsolve.

Reference: diffrax Dopri8 rtol = atol = 1e-13 (shared max-norm step by default, or per-body under
jax.vmap with --ref vmap) for all bodies; the worst-conditioned bodies (largest change against a
looser run) are redone in extended precision with a Taylor-series integrator, and a few bodies are
cross-checked with scipy solve_ivp DOP853 at 1e-13. The hardest bodies amplify float64 roundoff
so much that no float64 integration gets their omega(T) to much better than ~1e-8.

Usage: python benchmarks/batch_strategies.py [--n 10000] [--repeats 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402

T_END = 20.0


# ----------------------------------------------------------------------------- scene


def make_scene(n: int):
    """Returns y0 (7, N) and the Euler coefficients c (3, N): c1 = (I2 - I3) / I1, cyclic."""
    rng = np.random.default_rng(0)
    u = rng.uniform(-1.0, 1.0, size=(n, 3))
    inertia = np.array([1.0, 2.0, 2.5]) * (1.0 + 0.05 * u)
    nrm = rng.standard_normal(size=(n, 3))
    omega0 = np.array([0.05, 4.0, 0.05]) + 0.01 * nrm
    I1, I2, I3 = inertia.T
    c = np.stack([(I2 - I3) / I1, (I3 - I1) / I2, (I1 - I2) / I3])
    y0 = np.concatenate([omega0.T, np.tile(np.array([[1.0], [0.0], [0.0], [0.0]]), (1, n))])
    return y0, c, inertia, omega0


def rhs_components(y, c):
    """The 7 derivative components from the 7 state components (any common shape)."""
    w1, w2, w3, q0, q1, q2, q3 = y
    c1, c2, c3 = c
    return (
        c1 * w2 * w3,
        c2 * w3 * w1,
        c3 * w1 * w2,
        0.5 * (-q1 * w1 - q2 * w2 - q3 * w3),
        0.5 * (q0 * w1 + q2 * w3 - q3 * w2),
        0.5 * (q0 * w2 - q1 * w3 + q3 * w1),
        0.5 * (q0 * w3 + q1 * w2 - q2 * w1),
    )


def vf_first(t, y, c):
    """Components on the first axis: y (7, ...) and c (3, ...). Used for (7, N) and per body (7,)."""
    return jnp.stack(rhs_components(y, c), axis=0)


def vf_last(t, y, c):
    """Components on the last axis: y (N, 7), c (N, 3)."""
    return jnp.stack(rhs_components(jnp.moveaxis(y, -1, 0), jnp.moveaxis(c, -1, 0)), axis=-1)


# ----------------------------------------------------------------------------- errors


def quat_err_angle(q, qr):
    """Rotation angle of conj(qr) (x) q, for (4, N) arrays (numpy)."""
    w = qr[0] * q[0] + qr[1] * q[1] + qr[2] * q[2] + qr[3] * q[3]
    x = qr[0] * q[1] - qr[1] * q[0] - qr[2] * q[3] + qr[3] * q[2]
    y = qr[0] * q[2] + qr[1] * q[3] - qr[2] * q[0] - qr[3] * q[1]
    z = qr[0] * q[3] - qr[1] * q[2] + qr[2] * q[1] - qr[3] * q[0]
    return 2.0 * np.arctan2(np.sqrt(x * x + y * y + z * z), np.abs(w))


def errors(yT, yref):
    """yT, yref (7, N) numpy. Relative omega errors per body and orientation angle errors."""
    rel = np.linalg.norm(yT[:3] - yref[:3], axis=0) / np.linalg.norm(yref[:3], axis=0)
    ang = quat_err_angle(yT[3:], yref[3:])
    return rel, ang


# ----------------------------------------------------------------------------- strategies

SOLVERS = {"Tsit5": diffrax.Tsit5, "Dopri5": diffrax.Dopri5, "Dopri8": diffrax.Dopri8}


def strat_A(solver, rtol, atol, max_steps):
    """Per-body adaptive: jax.vmap over diffeqsolve. Input y (N, 7), c (N, 3)."""

    def one(y, c):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(vf_first),
            SOLVERS[solver](),
            0.0,
            T_END,
            None,
            y,
            args=c,
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
            saveat=diffrax.SaveAt(t1=True),
            max_steps=max_steps,
            throw=False,
        )
        return sol.ys[-1], sol.stats["num_steps"], diffrax.is_successful(sol.result)

    def f(y, c):
        yT, steps, ok = jax.vmap(one)(y, c)
        return yT, steps, ok

    return f, "N7"


def shared_solve(y, c, solver, rtol, atol, max_steps, layout, norm):
    vf = vf_first if layout == "7N" else vf_last
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf),
        SOLVERS[solver](),
        0.0,
        T_END,
        None,
        y,
        args=c,
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol, norm=norm),
        saveat=diffrax.SaveAt(t1=True),
        max_steps=max_steps,
        throw=False,
    )
    return sol.ys[-1], sol.stats["num_steps"], diffrax.is_successful(sol.result)


def strat_B(solver, rtol, atol, max_steps, layout, norm=optx.max_norm):
    """Shared step over the whole batch as one array."""

    def f(y, c):
        return shared_solve(y, c, solver, rtol, atol, max_steps, layout, norm)

    return f, layout


def to_chunks(y, chunk):
    """(k, N) -> (N/chunk, k, chunk)."""
    k, n = y.shape
    return y.reshape(k, n // chunk, chunk).transpose(1, 0, 2)


def from_chunks(yc):
    m, k, chunk = yc.shape
    return yc.transpose(1, 0, 2).reshape(k, m * chunk)


def strat_D(solver, rtol, atol, max_steps, chunk):
    """Shared step per chunk (layout (7, chunk)), chunks run sequentially with lax.map."""

    def f(y, c):
        def one(args):
            return shared_solve(*args, solver, rtol, atol, max_steps, "7N", optx.max_norm)

        yT, steps, ok = jax.lax.map(one, (to_chunks(y, chunk), to_chunks(c, chunk)))
        return from_chunks(yT), steps, ok

    return f, "7N"


def rk4_solve(y, c, dt, nsteps, unroll=1):
    def step(_, y):
        k1 = vf_first(None, y, c)
        k2 = vf_first(None, y + (0.5 * dt) * k1, c)
        k3 = vf_first(None, y + (0.5 * dt) * k2, c)
        k4 = vf_first(None, y + dt * k3, c)
        return y + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

    return jax.lax.fori_loop(0, nsteps, step, y, unroll=unroll)


def strat_C(dt, chunk=None, unroll=1):
    """Fixed-step RK4 on (7, N); optionally lax.map over chunks of (7, chunk)."""
    nsteps = int(round(T_END / dt))
    assert abs(nsteps * dt - T_END) < 1e-9

    def f(y, c):
        if chunk is None:
            yT = rk4_solve(y, c, dt, nsteps, unroll)
        else:
            yT = from_chunks(
                jax.lax.map(
                    lambda a: rk4_solve(*a, dt, nsteps, unroll), (to_chunks(y, chunk), to_chunks(c, chunk))
                )
            )
        return yT, jnp.asarray(nsteps), jnp.asarray(True)

    return f, "7N"


# ----------------------------------------------------------------------------- running


def timed(f, layout, y0, c, repeats):
    """AOT-compiles f, then runs it `repeats` times. Returns outputs in (7, N) and timings."""
    if layout == "N7":
        y_in, c_in = jnp.asarray(y0.T.copy()), jnp.asarray(c.T.copy())
    else:
        y_in, c_in = jnp.asarray(y0), jnp.asarray(c)
    jax.block_until_ready((y_in, c_in))
    t0 = time.perf_counter()
    compiled = jax.jit(f).lower(y_in, c_in).compile()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(y_in, c_in))
        times.append(time.perf_counter() - t0)
    yT, steps, ok = (np.asarray(o) for o in out)
    if layout == "N7":
        yT = yT.T
    return yT, steps, ok, compile_s, times


def taylor_longdouble(y0, c, h=0.05, order=24):
    """Taylor-series integration in numpy extended precision (x87 80-bit, eps 1.1e-19).

    The right-hand side is quadratic, so the Taylor coefficients follow exactly from Cauchy
    products. The nearest complex-time singularity of these solutions is ~pi / (2 lambda) ~ 0.9 s
    away (lambda ~ 1.8 /s the separatrix growth rate), so h = 0.05 with 24 terms truncates at
    ~1e-30: the result is limited only by extended-precision roundoff. y0 (7, K), c (3, K).
    """
    LD = np.longdouble
    y, c = np.asarray(y0, LD), np.asarray(c, LD)
    nsteps = int(round(T_END / h))
    hh = LD(T_END) / nsteps
    inv = 1 / np.arange(1, order + 1, dtype=LD)
    half = LD(0.5)
    for _ in range(nsteps):
        Y = np.zeros((order + 1, 7, y.shape[1]), LD)
        Y[0] = y
        for k in range(order):
            Wr = Y[k::-1, 0:3]
            WW = np.einsum("jan,jbn->abn", Y[: k + 1, 0:3], Wr)  # sum_j w_a[j] w_b[k-j]
            QW = np.einsum("jan,jbn->abn", Y[: k + 1, 3:7], Wr)  # sum_j q_a[j] w_b[k-j]
            i = inv[k]
            Y[k + 1, 0] = c[0] * WW[1, 2] * i
            Y[k + 1, 1] = c[1] * WW[2, 0] * i
            Y[k + 1, 2] = c[2] * WW[0, 1] * i
            Y[k + 1, 3] = half * i * (-QW[1, 0] - QW[2, 1] - QW[3, 2])
            Y[k + 1, 4] = half * i * (QW[0, 0] + QW[2, 2] - QW[3, 1])
            Y[k + 1, 5] = half * i * (QW[0, 1] - QW[1, 2] + QW[3, 0])
            Y[k + 1, 6] = half * i * (QW[0, 2] + QW[1, 1] - QW[2, 0])
        y = Y[order]
        for k in range(order - 1, -1, -1):
            y = y * hh + Y[k]
    return y


def reference(y0, c, n_taylor, n_scipy, ref_kind="shared"):
    """Reference final states (7, N) and a description of how good they are.

    1. diffrax Dopri8 rtol = atol = 1e-13 on all bodies, either one shared step with a max norm
       ("shared", default: every body gets the smallest step, and it is fast) or per-body PID under
       jax.vmap ("vmap"), and the same at a looser tolerance; the difference flags the
       ill-conditioned bodies.
    2. The n_taylor most ill-conditioned bodies are re-integrated in extended precision
       (taylor_longdouble) and those values replace the Dopri8 ones; a second extended-precision
       run from initial conditions perturbed by ~1 ulp of float64 measures the float64 floor.
    3. scipy solve_ivp DOP853 rtol = atol = 1e-13 on n_scipy bodies, as an independent check.
    """
    info = {}
    if ref_kind == "vmap":  # per-body PID, as a user would write it (slow: ~30-100 s at N = 1e4 on 2 cores)
        fa, la = strat_A("Dopri8", 1e-13, 1e-13, 1_000_000)
        fb, lb = strat_A("Dopri8", 1e-12, 1e-12, 1_000_000)
        name = "Dopri8 per-body PID (vmap), rtol=atol=1e-13; ranked against 1e-12"
    else:  # one shared step for the whole batch, max norm: every body gets the smallest step
        fa, la = strat_B("Dopri8", 1e-13, 1e-13, 1_000_000, "7N")
        fb, lb = strat_B("Dopri8", 1e-11, 1e-11, 1_000_000, "7N")
        name = "Dopri8 shared step, max-norm PID, rtol=atol=1e-13; ranked against 1e-11"
    y13, steps, ok, cs, ts = timed(fa, la, y0, c, 1)
    assert ok.all(), "reference failed"
    info["float64_reference"] = dict(
        kind=name, compile_s=cs, run_s=ts[0], max_steps=int(steps.max()), mean_steps=float(steps.mean())
    )
    y12, _, ok12, _, ts12 = timed(fb, lb, y0, c, 1)
    d12, a12 = errors(y12, y13)
    info["float64_looser_vs_reference"] = dict(
        max_rel_omega=float(d12.max()),
        median_rel_omega=float(np.median(d12)),
        max_angle=float(a12.max()),
        run_s=ts12[0],
    )
    print(
        f"{name}: {ts[0]:.1f} s, max steps {int(steps.max())}; looser run differs by max "
        f"{d12.max():.2e}, median {np.median(d12):.2e}",
        flush=True,
    )

    yref = y13.copy()
    hard = np.argsort(-d12)[: min(n_taylor, y0.shape[1])]
    if len(hard):
        t0 = time.perf_counter()
        yt = taylor_longdouble(y0[:, hard], c[:, hard])
        t_taylor = time.perf_counter() - t0
        # ~1 ulp relative perturbation of omega0 (float64 eps), integrated in extended precision
        sign = np.where(np.random.default_rng(1).random((3, len(hard))) < 0.5, -1.0, 1.0)
        y0p = np.asarray(y0[:, hard], np.longdouble)
        y0p[:3] *= 1 + sign * np.longdouble(2.0**-52)
        ytp = taylor_longdouble(y0p, c[:, hard])
        floor, _ = errors(np.asarray(ytp, np.float64), np.asarray(yt, np.float64))
        yt = np.asarray(yt, np.float64)
        d13, _ = errors(y13[:, hard], yt)
        rest = np.setdiff1d(np.arange(y0.shape[1]), hard)
        yref[:, hard] = yt
        info["taylor_longdouble"] = dict(
            n_bodies=len(hard),
            run_s=t_taylor,
            h=0.05,
            order=24,
            float64_ref_err_on_these_max=float(d13.max()),
            float64_ref_err_on_these_median=float(np.median(d13)),
            one_ulp_omega0_perturbation_effect_max=float(floor.max()),
            one_ulp_omega0_perturbation_effect_median=float(np.median(floor)),
            other_bodies_max_looser_vs_ref=float(d12[rest].max()) if len(rest) else 0.0,
        )
        print(
            f"extended-precision Taylor on the {len(hard)} worst-conditioned bodies ({t_taylor:.0f} s): "
            f"float64 reference error there max {d13.max():.2e}; a 1-ulp change of omega0 moves "
            f"omega(T) by up to {floor.max():.2e} (lower bound on the float64 floor); other bodies' "
            f"looser-vs-reference max "
            f"{info['taylor_longdouble']['other_bodies_max_looser_vs_ref']:.2e}",
            flush=True,
        )
    if n_scipy:
        from scipy.integrate import solve_ivp

        idx = np.unique(
            np.concatenate(
                [hard[: n_scipy // 2], np.linspace(0, y0.shape[1] - 1, n_scipy - n_scipy // 2).astype(int)]
            )
        )
        devs = []
        for i in idx:
            ci = c[:, i]
            fun = lambda t, y, ci=ci: np.array(rhs_components(y, ci))  # noqa: E731
            s = solve_ivp(fun, (0.0, T_END), y0[:, i], method="DOP853", rtol=1e-13, atol=1e-13)
            r, a = errors(s.y[:, -1:], yref[:, i : i + 1])
            devs.append((float(r[0]), float(a[0])))
        devs = np.array(devs)
        info["scipy_DOP853_1e-13_vs_ref"] = dict(
            n_bodies=len(idx),
            max_rel_omega=float(devs[:, 0].max()),
            median_rel_omega=float(np.median(devs[:, 0])),
            max_angle=float(devs[:, 1].max()),
        )
        print(
            f"scipy DOP853 1e-13 vs reference on {len(idx)} bodies (half of them the worst-conditioned): "
            f"max rel omega {devs[:, 0].max():.2e}, median {np.median(devs[:, 0]):.2e}",
            flush=True,
        )
    return yref, info


def build_configs(n, chunk, max_steps):
    """(strategy, setting, factory) in run order. atol = 1e-2 * rtol everywhere (state components
    range from ~0.01 to ~4, so a pure-rtol test would be too strict for components crossing zero).
    The sweep is trimmed to keep a run near 10-15 min on a loaded 2-core CPU."""
    cfg = []
    atol_f = 1e-2
    for rtol in (1e-6, 1e-8, 1e-10):
        cfg.append(("A", f"Tsit5 rtol={rtol:g}", lambda r=rtol: strat_A("Tsit5", r, r * atol_f, max_steps)))
    cfg.append(("A", "Dopri8 rtol=1e-08", lambda: strat_A("Dopri8", 1e-8, 1e-10, max_steps)))
    grid = (
        [("Tsit5", r) for r in (1e-4, 1e-6, 1e-8, 1e-10)]
        + [("Dopri5", r) for r in (1e-6, 1e-8)]
        + [("Dopri8", r) for r in (1e-6, 1e-8, 1e-10)]
    )
    for layout in ("N7", "7N"):
        for solver, rtol in grid:
            cfg.append(
                (
                    f"B({layout[0]},{layout[1]})",
                    f"{solver} rtol={rtol:g}",
                    lambda s=solver, r=rtol, lay=layout: strat_B(s, r, r * atol_f, max_steps, lay),
                )
            )
    for solver, rtol in (("Tsit5", 1e-6), ("Dopri8", 1e-8)):
        cfg.append(
            (
                "B-rms(7,N)",
                f"{solver} rtol={rtol:g}",
                lambda s=solver, r=rtol: strat_B(s, r, r * atol_f, max_steps, "7N", optx.rms_norm),
            )
        )
    for dt in (0.04, 0.02, 0.01, 0.005, 0.0025):
        cfg.append(("C(7,N)", f"RK4 dt={dt:g}", lambda d=dt: strat_C(d)))
    cfg.append(("C(7,N)", "RK4 dt=0.01 unroll=4", lambda: strat_C(0.01, unroll=4)))
    if chunk < n:
        for dt in (0.02, 0.01, 0.005):
            cfg.append((f"C-chunk{chunk}", f"RK4 dt={dt:g}", lambda d=dt: strat_C(d, chunk)))
        for solver, rtol in (("Tsit5", 1e-6), ("Tsit5", 1e-8), ("Dopri8", 1e-8), ("Dopri8", 1e-10)):
            cfg.append(
                (
                    f"D-chunk{chunk}",
                    f"{solver} rtol={rtol:g}",
                    lambda s=solver, r=rtol: strat_D(s, r, r * atol_f, max_steps, chunk),
                )
            )
    return cfg


def prepare(f, layout, y0, c):
    """AOT-compiles f for inputs in its layout; returns (compiled, inputs, compile seconds)."""
    if layout == "N7":
        args = (jnp.asarray(y0.T.copy()), jnp.asarray(c.T.copy()))
    else:
        args = (jnp.asarray(y0), jnp.asarray(c))
    jax.block_until_ready(args)
    t0 = time.perf_counter()
    compiled = jax.jit(f).lower(*args).compile()
    return compiled, args, time.perf_counter() - t0


def run_once(compiled, args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    return out, time.perf_counter() - t0


def summarize(rows, thresholds):
    """Fastest row per strategy family reaching each max-error threshold."""
    out = {}
    for thr in thresholds:
        best = {}
        for r in rows:
            if r["all_ok"] and r["max_rel_omega"] <= thr:
                if r["strategy"] not in best or r["run_s_median"] < best[r["strategy"]]["run_s_median"]:
                    best[r["strategy"]] = r
        out[f"{thr:g}"] = {
            k: dict(setting=v["setting"], run_s_median=v["run_s_median"], max_rel_omega=v["max_rel_omega"])
            for k, v in best.items()
        }
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=10_000)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--chunk", type=int, default=1000)
    p.add_argument("--max-steps", type=int, default=100_000)
    p.add_argument(
        "--taylor-bodies",
        type=int,
        default=100,
        help="worst-conditioned bodies whose reference is redone in extended precision",
    )
    p.add_argument("--scipy-bodies", type=int, default=10)
    p.add_argument(
        "--ref", choices=("shared", "vmap"), default="shared", help="float64 reference integration"
    )
    p.add_argument("--only", default=None, help="regex on 'strategy setting' to select rows")
    p.add_argument(
        "--out", default=None, help="JSON path (default benchmarks/results/batch_strategies_n{N}.json)"
    )
    a = p.parse_args(argv)
    assert a.chunk >= a.n or a.n % a.chunk == 0, "n must be a multiple of chunk"
    out = a.out or os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "results", f"batch_strategies_n{a.n}.json"
    )

    y0, c, _, _ = make_scene(a.n)
    meta = dict(
        n=a.n,
        repeats=a.repeats,
        chunk=a.chunk,
        T=T_END,
        jax=jax.__version__,
        diffrax=diffrax.__version__,
        backend=jax.default_backend(),
        devices=[str(d) for d in jax.devices()],
        cpu_count=os.cpu_count(),
        platform=platform.platform(),
        python=sys.version.split()[0],
        atol_rule="atol = 1e-2 * rtol",
        timing="AOT compile (lower+compile) timed separately; then `repeats` timed calls per config, "
        "interleaved round-robin over configs (the first round also gives the accuracy); "
        "block_until_ready on every call",
        loadavg_start=os.getloadavg(),
    )
    print(f"N={a.n} on {meta['devices']}, {os.cpu_count()} CPUs, load {meta['loadavg_start']}", flush=True)
    t_start = time.perf_counter()
    yref, refinfo = reference(y0, c, a.taylor_bodies, a.scipy_bodies, a.ref)
    meta["reference"] = refinfo

    # compile everything first (timed separately), then `repeats` rounds, round-robin over configs
    entries = []
    for strat, setting, factory in build_configs(a.n, a.chunk, a.max_steps):
        if a.only and not re.search(a.only, f"{strat} {setting}"):
            continue
        f, layout = factory()
        compiled, args, cs = prepare(f, layout, y0, c)
        entries.append(
            dict(
                compiled=compiled,
                args=args,
                times=[],
                layout=layout,
                row=dict(strategy=strat, setting=setting, layout=layout, compile_s=cs),
            )
        )
        print(f"  compiled {strat} {setting}: {cs:.2f} s", flush=True)
    for rep in range(a.repeats):
        for e in entries:
            out_, t = run_once(e["compiled"], e["args"])
            e["times"].append(t)
            if rep == 0:
                yT, steps, ok = (np.asarray(o) for o in out_)
                if e["layout"] == "N7":
                    yT = yT.T
                rel, ang = errors(yT, yref)
                e["row"].update(
                    max_rel_omega=float(rel.max()),
                    median_rel_omega=float(np.median(rel)),
                    p99_rel_omega=float(np.quantile(rel, 0.99)),
                    max_angle=float(ang.max()),
                    median_angle=float(np.median(ang)),
                    steps_max=int(np.max(steps)),
                    steps_mean=float(np.mean(steps)),
                    all_ok=bool(np.all(ok)),
                )
                print(f"  ran {e['row']['strategy']} {e['row']['setting']}: {t:.3f} s", flush=True)
        print(
            f"  round {rep + 1}/{a.repeats} done ({time.perf_counter() - t_start:.0f} s so far)", flush=True
        )

    rows = []
    print(
        f"\n{'strategy':<14} {'setting':<21} {'compile s':>9} {'run s med':>9} {'[min, max]':>17} "
        f"{'max rel w':>9} {'med rel w':>9} {'p99 rel w':>9} {'max angle':>9} {'steps max':>9} {'mean':>7}"
    )
    for e in entries:
        row = e["row"]
        row["run_s"] = e["times"]
        row["run_s_median"] = statistics.median(e["times"])
        rows.append(row)
        ts = e["times"]
        print(
            f"{row['strategy']:<14} {row['setting']:<21} {row['compile_s']:9.2f} {row['run_s_median']:9.3f} "
            f"[{min(ts):7.3f},{max(ts):7.3f}] {row['max_rel_omega']:9.1e} {row['median_rel_omega']:9.1e} "
            f"{row['p99_rel_omega']:9.1e} {row['max_angle']:9.1e} {row['steps_max']:9d} "
            f"{row['steps_mean']:7.0f}"
            f"{'' if row['all_ok'] else '  FAILED (max_steps?)'}",
            flush=True,
        )
    meta["summary_fastest_per_strategy_by_max_error"] = summarize(rows, (1e-5, 1e-6, 1e-7, 3e-8, 1e-8))
    print("\nfastest per strategy reaching max rel omega error <= threshold:")
    for thr, best in meta["summary_fastest_per_strategy_by_max_error"].items():
        items = sorted(best.items(), key=lambda kv: kv[1]["run_s_median"])
        print(f"  <= {thr}: " + "; ".join(f"{k} {v['setting']} {v['run_s_median']:.3f} s" for k, v in items))
    meta["total_s"] = time.perf_counter() - t_start
    meta["loadavg_end"] = os.getloadavg()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out, "w") as fh:
        json.dump(dict(meta=meta, rows=rows), fh, indent=1)
    print(f"total {meta['total_s']:.0f} s; wrote {out}", flush=True)


if __name__ == "__main__":
    main()
