"""Lagrange's top in closed form against the integrating presets, side by side in one process.

N symmetric heavy tops (the parameters of ``rigidjax simulate``'s heavy-top scene with I1 = I2:
spins 30-150 rad/s, tilts 0.05-1 rad), ``--samples`` samples over each horizon T of ``--durations``,
float64. Each setting is called once to compile (timed apart), then ``--repeats`` times with
``block_until_ready``; the median is reported. Errors:

- against scipy's DOP853 at rtol = atol = 1e-13 (an independent reference, written below in numpy)
  on ``--ref-bodies`` bodies spread over the batch, all solved as one system: omega relative to the
  body's max |omega|, q absolute (the max over samples and bodies);
- against ``accuracy="exact"`` on every body (omega, same scale);
- the drift of the energy and of the vertical angular momentum (``Trajectory.invariants()``).

The closed form evaluates each sample directly, so its cost depends on the number of samples, not
on T; an integrator's grows with T (more steps).

    python benchmarks/heavy_top_exact.py [-n 10000] [--durations 20,200] [--samples 200]
        [--repeats 3] [--accuracies exact,balanced,precise] [--ref-bodies 16] [--max-steps 1000000]
        [--json PATH]

``max_steps`` is raised from simulate's default (10^5 per chunk): ``precise`` needs more than that
for these tops at T = 200 s.
"""

import argparse
import json
import os
import platform
import time

import jax
import numpy as np
from scipy.integrate import solve_ivp

jax.config.update("jax_enable_x64", True)

import rigidjax as rj  # noqa: E402

GRAVITY = 9.81


def tops(n, seed=0):
    rng = np.random.default_rng(seed)
    i_perp = 1.0e-4 * rng.uniform(0.8, 1.2, n)
    inertia = np.stack([i_perp, i_perp, i_perp * rng.uniform(0.5, 0.7, n)], -1)
    mass = rng.uniform(0.09, 0.11, n)
    com = np.stack([np.zeros(n), np.zeros(n), rng.uniform(0.025, 0.035, n)], -1)
    omega0 = np.stack([np.zeros(n), np.zeros(n), rng.uniform(30.0, 150.0, n)], -1)
    angles = np.stack([np.zeros(n), rng.uniform(0.05, 1.0, n), rng.uniform(0.0, 2 * np.pi, n)], -1)
    q0 = np.asarray(rj.quat_from_euler(angles, "zxz"))
    return (inertia, mass, com, omega0, q0), rj.HeavyTop(inertia, mass, com, GRAVITY), rj.State(omega0, q0)


def dop853(inertia, mass, com, omega0, q0, ts, tol=1e-13):
    """Every body at once: ``I w' = (I w) x w + e x (m g com)`` with ``e`` the body-frame vertical,
    ``q' = q (0, w) / 2``; omega divided by each body's |omega0| so that all unknowns are O(1)."""
    k = len(mass)
    sigma = np.linalg.norm(omega0, axis=-1)[:, None]
    weight_com = (mass * GRAVITY)[:, None] * com

    def rhs(t, y):
        y = y.reshape(k, 7)
        w = sigma * y[:, :3]
        qw, qx, qy, qz = y[:, 3], y[:, 4], y[:, 5], y[:, 6]
        # body-frame vertical: the third row of R(q)
        e = np.stack([2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)], -1)
        dw = (np.cross(inertia * w, w) + np.cross(e, weight_com)) / inertia
        wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
        dq = 0.5 * np.stack(
            [
                -qx * wx - qy * wy - qz * wz,
                qw * wx + qy * wz - qz * wy,
                qw * wy - qx * wz + qz * wx,
                qw * wz + qx * wy - qy * wx,
            ],
            -1,
        )
        return np.concatenate([dw / sigma, dq], -1).ravel()

    y0 = np.concatenate([omega0 / sigma, q0], -1).ravel()
    sol = solve_ivp(rhs, (0.0, ts[-1]), y0, t_eval=ts, method="DOP853", rtol=tol, atol=tol)
    assert sol.success, sol.message
    y = sol.y.T.reshape(len(ts), k, 7).transpose(1, 0, 2)
    return y[..., :3] * sigma[:, None, :], y[..., 3:], sol.nfev


def rel_omega(omega, ref):
    scale = np.max(np.linalg.norm(ref, axis=-1), axis=-1)
    return float(np.max(np.max(np.linalg.norm(omega - ref, axis=-1), axis=-1) / scale))


def abs_q(q, ref):
    return float(np.max(np.minimum(np.linalg.norm(q - ref, axis=-1), np.linalg.norm(q + ref, axis=-1))))


def run_duration(params, model, state, duration, args):
    ts = np.linspace(0.0, duration, args.samples)
    pick = np.linspace(0, args.n - 1, args.ref_bodies).astype(int) if args.ref_bodies else None
    ref = None
    if pick is not None:
        start = time.perf_counter()
        w_ref, q_ref, nfev = dop853(*(p[pick] for p in params), ts)
        ref = (w_ref, q_ref)
        print(f"T = {duration:g} s: DOP853 reference on {len(pick)} bodies, {nfev} evaluations, "
              f"{time.perf_counter() - start:.0f} s", flush=True)  # fmt: skip
    rows, exact_omega = [], None
    for accuracy in args.accuracies.split(","):

        def run(accuracy=accuracy):
            traj = rj.simulate(model, state, ts, accuracy=accuracy, max_steps=args.max_steps)
            jax.block_until_ready((traj.omega, traj.orientation))
            return traj

        start = time.perf_counter()
        traj = run()
        first = time.perf_counter() - start
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
        omega, q = np.asarray(traj.omega), np.asarray(traj.orientation)
        drift = {k: float(np.max(v)) for k, v in traj.invariants().items()}
        if accuracy == "exact":
            exact_omega = omega
        row = {
            "accuracy": accuracy,
            "run_s": float(np.median(times)),
            "run_s_all": times,
            "compile_s": first - float(np.median(times)),
            "us_per_body_sample": 1e6 * float(np.median(times)) / (args.n * len(ts)),
            "max_rel_omega_vs_dop853": None if ref is None else rel_omega(omega[pick], ref[0]),
            "max_abs_q_vs_dop853": None if ref is None else abs_q(q[pick], ref[1]),
            "max_rel_omega_vs_exact": None if exact_omega is None else rel_omega(omega, exact_omega),
            "energy_drift": drift.get("energy"),
            "vertical_L_drift": drift.get("vertical_angular_momentum"),
        }
        rows.append(row)

        def fmt(x):
            return "-" if x is None else f"{x:.1e}"

        print(
            f"T = {duration:g} s  {accuracy:9s} run {row['run_s']:8.3f} s  "
            f"compile {row['compile_s']:6.1f} s  "
            f"omega vs DOP853 {fmt(row['max_rel_omega_vs_dop853'])}  "
            f"q vs DOP853 {fmt(row['max_abs_q_vs_dop853'])}  "
            f"omega vs exact {fmt(row['max_rel_omega_vs_exact'])}  energy {fmt(row['energy_drift'])}  "
            f"L_z {fmt(row['vertical_L_drift'])}",
            flush=True,
        )
    by = {r["accuracy"]: r["run_s"] for r in rows}
    if "exact" in by:
        for acc, t in by.items():
            if acc != "exact":
                print(
                    f"T = {duration:g} s: {acc} takes {t / by['exact']:.2f}x the run time of exact",
                    flush=True,
                )
    return {"duration_s": duration, "samples": len(ts), "ref_bodies": None if pick is None else pick.tolist(),
            "rows": rows}  # fmt: skip


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("-n", type=int, default=10_000)
    p.add_argument("--durations", default="20,200", help="horizons T in s, comma-separated")
    p.add_argument("--samples", type=int, default=200)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--accuracies", default="exact,balanced,precise")
    p.add_argument("--ref-bodies", type=int, default=16, help="bodies checked against DOP853 (0: none)")
    p.add_argument("--max-steps", type=int, default=1_000_000, help="simulate's step limit per chunk")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    params, model, state = tops(args.n)
    load = os.getloadavg()
    results = [run_duration(params, model, state, float(d), args) for d in args.durations.split(",")]
    out = {
        "bodies": args.n,
        "repeats": args.repeats,
        "max_steps": args.max_steps,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {jax.devices()[0].platform}",
        "load_average_start": load,
        "load_average_end": os.getloadavg(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "jax": jax.__version__,
        "horizons": results,
    }
    print(f"load average {load[0]:.1f} at the start, {out['load_average_end'][0]:.1f} at the end")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
