"""Lagrange's top in closed form against the integrating presets, side by side in one process.

10^4 symmetric heavy tops (the parameters of ``rigidjax simulate``'s heavy-top scene with I1 = I2),
200 samples over 5 s, float64. Each setting is called once to compile (timed apart), then
``--repeats`` times with ``block_until_ready``; the median is reported. Errors are measured against
``accuracy="exact"``, whose own accuracy against scipy's DOP853 (rtol 1e-13) is checked in
tests/test_heavy_top_exact.py (<= 4e-11 over >= 10 nutation periods).

    python benchmarks/heavy_top_exact.py [-n 10000] [--repeats 5] [--json PATH]
"""

import argparse
import json
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import rigidjax as rj  # noqa: E402


def tops(n, seed=0):
    rng = np.random.default_rng(seed)
    i_perp = 1.0e-4 * rng.uniform(0.8, 1.2, n)
    inertia = np.stack([i_perp, i_perp, i_perp * rng.uniform(0.5, 0.7, n)], -1)
    mass = rng.uniform(0.09, 0.11, n)
    com = np.stack([np.zeros(n), np.zeros(n), rng.uniform(0.025, 0.035, n)], -1)
    omega0 = np.stack([np.zeros(n), np.zeros(n), rng.uniform(30.0, 150.0, n)], -1)
    angles = np.stack([np.zeros(n), rng.uniform(0.05, 1.0, n), rng.uniform(0.0, 2 * np.pi, n)], -1)
    q0 = np.asarray(rj.quat_from_euler(angles, "zxz"))
    return rj.HeavyTop(inertia, mass, com), rj.State(omega0, q0)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("-n", type=int, default=10_000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    model, state = tops(args.n)
    ts = np.linspace(0.0, 5.0, 200)
    rows, reference = [], None
    for accuracy in ("exact", "fast", "balanced", "precise"):

        def run(accuracy=accuracy):
            traj = rj.simulate(model, state, ts, accuracy=accuracy)
            jax.block_until_ready(traj.omega)
            return traj

        start = time.perf_counter()
        traj = run()
        first = time.perf_counter() - start
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
        omega = np.asarray(traj.omega)
        if reference is None:
            reference = omega
        scale = np.max(np.abs(reference), axis=(-2, -1))
        error = float(np.max(np.max(np.abs(omega - reference), axis=(-2, -1)) / scale))
        rows.append(
            {
                "accuracy": accuracy,
                "run_s": float(np.median(times)),
                "compile_s": first - float(np.median(times)),
                "max_rel_omega_vs_exact": error,
            }
        )
        print(
            f"{accuracy:9s} run {np.median(times):8.3f} s  compile {first - np.median(times):6.1f} s  "
            f"max rel omega error vs exact {error:.2e}"
        )
    exact = rows[0]["run_s"]
    for row in rows[1:]:
        print(f"{row['accuracy']} takes {row['run_s'] / exact:.2f}x the run time of exact")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"bodies": args.n, "samples": len(ts), "duration_s": 5.0, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
