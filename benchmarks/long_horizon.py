"""Long horizons: structure-preserving solvers against diffrax's classical solvers at equal accuracy.

Scenes (float64):
  free   torque-free body I = (1, 2, 2.5), omega0 = (0.3, 0.05, 1.0) (wobble about the largest axis),
         q0 = identity; the reference is the closed form (``torque_free_motion``).
  top    heavy top I = (1, 1, 0.4) about the pivot, m = 1, com = (0, 0, 0.3), g = 9.81,
         omega0 = (0, 0, 12), tilted 0.5 rad; the reference is Dopri8 at rtol 1e-13 over one period.

For each method the fixed step is the largest of a geometric sweep (1 s down to 2.5e-4 s) whose
relative omega error after ``--calib`` seconds meets ``--target`` (equal short-time accuracy);
then every method runs the same
horizon (``--steps`` steps of the order-4 splitting's dt, 1e6 by default), saving 200 samples, and
reports: relative energy error (max over the first and the second half: a drift shows as growth),
|L| (free) or vertical L (top) relative drift, space-frame L drift (free), | |q| - 1 |, wall time
(compile excluded; ``block_until_ready``; one run: the invariants are the point here).

Methods: Lie–Poisson splitting order 2 and 4 (``split_free_body`` / ``split_heavy_top``; exact
sub-flows), RKMK Dormand–Prince 5 (``rkmk_step``; q <- q Exp(theta)), and diffrax Tsit5, Dopri5,
Dopri8 with ``ConstantStepSize`` on (omega, q) with dq/dt = q (0, omega) / 2 (no renormalisation, as
a user would write it).

Usage: python benchmarks/long_horizon.py [--steps 1000000] [--target 1e-6]
       [--out benchmarks/results/long_horizon.json]
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rigidjax as rj  # noqa: E402

FREE_I = jnp.array([1.0, 2.0, 2.5])
FREE_W0 = jnp.array([0.3, 0.05, 1.0])
TOP = dict(inertia=jnp.array([1.0, 1.0, 0.4]), mass=1.0, com=jnp.array([0.0, 0.0, 0.3]), gravity=9.81)
TOP_W0 = jnp.array([0.0, 0.0, 12.0])
Q_ID = jnp.array([1.0, 0.0, 0.0, 0.0])


def top_q0():
    return rj.quat_from_euler(jnp.array([0.0, 0.5, 0.0]))


def omega_dot(scene, omega, q):
    if scene == "free":
        return rj.euler_equations(FREE_I, omega)
    model = rj.HeavyTop(**TOP)
    return model.angular_acceleration(0.0, rj.State(omega, q), None)


def invariants(scene, omega, q):
    """Per-sample invariants: energy, |L| (free) or L_Z (top), space-frame L (free)."""
    if scene == "free":
        L = omega * FREE_I
        energy = 0.5 * jnp.sum(omega * L, axis=-1)
        space_L = rj.quat_rotate(q, L)
        return energy, jnp.linalg.norm(L, axis=-1), space_L
    inertia, mass, com, g = TOP["inertia"], TOP["mass"], TOP["com"], TOP["gravity"]
    L = omega * inertia
    height = rj.quat_rotate(q, jnp.broadcast_to(com, q.shape[:-1] + (3,)))[..., 2]
    energy = 0.5 * jnp.sum(omega * L, axis=-1) + mass * g * height
    Lz = rj.quat_rotate(q, L)[..., 2]
    return energy, Lz, None


def run_splitting(scene, order, dt, n_steps, n_save):
    """n_steps of the splitting, saving n_save evenly spaced states (a scan of fori_loops)."""
    per = n_steps // n_save

    @jax.jit
    def go(L0, q0):
        def chunk(state, _):
            L, q = state
            if scene == "free":
                L, q = rj.solvers.split_free_body(FREE_I, L, q, dt, per, order)
            else:
                L, q = rj.solvers.split_heavy_top(
                    TOP["inertia"], TOP["mass"], TOP["com"], TOP["gravity"], L, q, dt, per, order
                )
            return (L, q), (L, q)

        return jax.lax.scan(chunk, (L0, q0), None, length=n_save)[1]

    inertia = FREE_I if scene == "free" else TOP["inertia"]
    w0, q0 = (FREE_W0, Q_ID) if scene == "free" else (TOP_W0, top_q0())
    args = (w0 * inertia, q0)
    return go, args, lambda out: (out[0] / inertia, out[1]), per * n_save


def run_rkmk(scene, dt, n_steps, n_save):
    per = n_steps // n_save

    def accel(t, omega, q, args):
        return omega_dot(scene, omega, q)

    @jax.jit
    def go(w0, q0):
        def chunk(state, _):
            def body(i, s):
                w, q = s
                w, q = rj.solvers.rkmk_step(accel, 0.0, w, q, dt, None)[:2]
                return w, q

            state = jax.lax.fori_loop(0, per, body, state)
            return state, state

        return jax.lax.scan(chunk, (w0, q0), None, length=n_save)[1]

    w0, q0 = (FREE_W0, Q_ID) if scene == "free" else (TOP_W0, top_q0())
    return go, (w0, q0), lambda out: out, per * n_save


def run_diffrax(scene, solver, dt, n_steps, n_save):
    def vf(t, y, args):
        w, q = y
        pure = jnp.concatenate([jnp.zeros(1), w])
        return omega_dot(scene, w, q), 0.5 * rj.quat_multiply(q, pure)

    t1 = n_steps * dt
    ts = jnp.linspace(0.0, t1, n_save + 1)[1:]

    @jax.jit
    def go(w0, q0):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(vf),
            solver,
            0.0,
            t1,
            dt,
            (w0, q0),
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=n_steps + 16,
        )
        return sol.ys

    w0, q0 = (FREE_W0, Q_ID) if scene == "free" else (TOP_W0, top_q0())
    return go, (w0, q0), lambda out: out, n_steps


def reference(scene, t):
    if scene == "free":
        return rj.torque_free_motion(FREE_I, FREE_W0, Q_ID, t)
    top = rj.HeavyTop(**TOP)
    traj = rj.simulate(top, rj.State(TOP_W0, top_q0()), jnp.array([0.0, t]), accuracy="precise", rtol=1e-13)
    return traj.omega[-1], traj.orientation[-1]


def short_error(scene, method, dt, calib):
    """omega error (relative) after ``calib`` seconds with step ``dt``."""
    n = max(1, int(round(calib / dt)))
    dt = calib / n
    go, args, unpack, _ = make(scene, method, dt, n, 1)
    w, q = unpack(go(*args))
    w_ref, _ = reference(scene, n * dt)
    return float(jnp.linalg.norm(w[-1] - w_ref) / jnp.linalg.norm(w_ref)), dt


def make(scene, method, dt, n_steps, n_save):
    if method.startswith("splitting"):
        return run_splitting(scene, int(method[-1]), dt, n_steps, n_save)
    if method == "rkmk-dopri5":
        return run_rkmk(scene, dt, n_steps, n_save)
    solver = {"tsit5": diffrax.Tsit5(), "dopri5": diffrax.Dopri5(), "dopri8": diffrax.Dopri8()}[method]
    return run_diffrax(scene, solver, dt, n_steps, n_save)


METHODS = ("splitting-2", "splitting-4", "rkmk-dopri5", "tsit5", "dopri5", "dopri8")


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--target", type=float, default=1e-6)
    parser.add_argument("--calib", type=float, default=10.0)
    parser.add_argument("--scenes", default="free,top")
    parser.add_argument("--out", default="benchmarks/results/long_horizon.json")
    args = parser.parse_args()
    results = {"steps_of_splitting_4": args.steps, "target": args.target, "scenes": {}}
    n_save = 200
    for scene in args.scenes.split(","):
        chosen = {}
        for method in METHODS:
            best = None
            # The largest step that meets the target over the calibration time (equal accuracy).
            for dt in np.geomspace(1.0, 2.5e-4, 20):
                err, dt_used = short_error(scene, method, float(dt), args.calib)
                best = (err, dt_used)
                if err <= args.target:
                    break
            chosen[method] = best
            print(
                f"{scene} {method:12s} dt {best[1]:.4g} error after {args.calib} s: {best[0]:.2e}", flush=True
            )
        horizon = args.steps * chosen["splitting-4"][1]
        rows = []
        for method in METHODS:
            short_err, dt = chosen[method]
            n = int(round(horizon / dt))
            n = max(n_save, n - n % n_save)  # whole save intervals, at least one
            dt = horizon / n
            go, fargs, unpack, n_done = make(scene, method, dt, n, n_save)
            t0 = time.perf_counter()
            jax.block_until_ready(go(*fargs))
            first = time.perf_counter() - t0
            t0 = time.perf_counter()
            out = jax.block_until_ready(go(*fargs))
            run_s = time.perf_counter() - t0
            w, q = unpack(out)
            w0 = FREE_W0 if scene == "free" else TOP_W0
            q0 = Q_ID if scene == "free" else top_q0()
            e0, m0, s0 = invariants(scene, w0, q0)
            e, m, s = invariants(scene, w, q)
            energy_err = np.abs(np.asarray((e - e0) / e0))
            half = energy_err.shape[0] // 2
            row = {
                "method": method,
                "dt": dt,
                "steps": n_done,
                "short_time_error": short_err,
                "energy_error_first_half": float(energy_err[:half].max()),
                "energy_error_second_half": float(energy_err[half:].max()),
                "momentum_error": float(np.max(np.abs(np.asarray((m - m0) / m0)))),
                "quaternion_norm_error": float(np.max(np.abs(np.linalg.norm(np.asarray(q), axis=-1) - 1))),
                "run_s": run_s,
                "compile_s": max(first - run_s, 0.0),
            }
            if s is not None:
                row["space_L_error"] = float(np.max(np.linalg.norm(np.asarray(s - s0), axis=-1)) / float(m0))
            rows.append(row)
            print(
                f"{scene} {method:12s} dt {dt:.4g} steps {n_done:8d} "
                f"energy {row['energy_error_first_half']:.2e} -> {row['energy_error_second_half']:.2e} "
                f"momentum {row['momentum_error']:.2e} "
                f"|q|-1 {row['quaternion_norm_error']:.2e} run {run_s:.2f} s",
                flush=True,
            )
        results["scenes"][scene] = {"horizon_s": horizon, "rows": rows}
    with open(args.out, "w", encoding="utf-8") as handle:
        json.dump(results, handle, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
