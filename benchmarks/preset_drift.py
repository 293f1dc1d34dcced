"""Drift of the ``simulate`` accuracy presets over 10^4 wobble periods (long horizons).

The free-body scene of ``benchmarks/long_horizon.py`` (I = (1, 2, 2.5), omega0 = (0.3, 0.05, 1.0),
q0 = identity), integrated by ``simulate`` with each preset over 10^4 wobble periods (1.04e5 s;
``long_horizon.py``'s 10^6 steps of the order-4 splitting span 3.0e4 s of the same body), 2001
samples. Reports, per preset: relative
energy error (max over the first and the second half, so a drift shows as growth), |L| drift,
space-frame L drift, | |q| - 1 | before the output normalisation, omega error and orientation angle
against the closed form, number of steps, wall time (compile excluded, one run).

Usage: python benchmarks/preset_drift.py [--periods 10000] [--out benchmarks/results/preset_drift.json]
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import _harness as B  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rigidjax as rj  # noqa: E402

INERTIA = jnp.array([1.0, 2.0, 2.5])
OMEGA0 = jnp.array([0.3, 0.05, 1.0])
Q0 = jnp.array([1.0, 0.0, 0.0, 0.0])


def _halves(x):
    rel = np.abs(x - x[0]) / np.abs(x[0])
    half = len(x) // 2
    return float(np.max(rel[: half + 1])), float(np.max(rel[half:]))


def _angle(q, q_ref):
    w = np.abs(np.sum(q * q_ref, axis=-1))
    vec = q_ref[:, :1] * q[:, 1:] - q[:, :1] * q_ref[:, 1:] - np.cross(q_ref[:, 1:], q[:, 1:])
    return 2 * np.arctan2(np.linalg.norm(vec, axis=-1), w)


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--periods", type=float, default=1e4)
    parser.add_argument("--samples", type=B.positive_int, default=2001)
    parser.add_argument("--out", default="benchmarks/results/preset_drift.json")
    args = parser.parse_args(argv)
    if not 0 < args.periods < float("inf"):
        parser.error(f"argument --periods: must be a positive number, got {args.periods:g}")
    period = float(rj.torque_free_period(INERTIA, OMEGA0))
    ts = jnp.linspace(0.0, args.periods * period, args.samples)
    omega_ref, q_ref = (np.asarray(x) for x in rj.torque_free_motion(INERTIA, OMEGA0, Q0, ts))
    inertia = np.asarray(INERTIA)
    rows = []
    for accuracy in ("fast", "balanced", "precise", "exact"):

        def run(accuracy=accuracy):
            traj = rj.simulate(
                rj.FreeBody(INERTIA), rj.State(OMEGA0, Q0), ts, accuracy=accuracy, max_steps=10**8
            )
            jax.block_until_ready(traj)
            return traj

        start = time.perf_counter()
        run()
        first = time.perf_counter() - start
        start = time.perf_counter()
        traj = run()
        wall = time.perf_counter() - start
        w, q = np.asarray(traj.omega), np.asarray(traj.orientation)
        energy = 0.5 * np.sum(inertia * w**2, axis=-1)
        momentum = inertia * w
        L_space = np.asarray(rj.quat_rotate(traj.orientation, jnp.asarray(momentum)))
        e1, e2 = _halves(energy)
        l1, l2 = _halves(np.linalg.norm(momentum, axis=-1))
        row = dict(
            accuracy=accuracy,
            energy_error_first_half=e1,
            energy_error_second_half=e2,
            momentum_error=max(l1, l2),
            space_L_error=float(
                np.max(np.linalg.norm(L_space - L_space[0], axis=-1)) / np.linalg.norm(L_space[0])
            ),
            quaternion_norm_error=float(np.max(np.asarray(traj.invariants()["quaternion_norm"]))),
            omega_error=float(np.max(np.abs(w - omega_ref)) / np.max(np.abs(omega_ref))),
            angle_error=float(np.max(_angle(q, q_ref))),
            steps=int(np.max(np.asarray(traj.stats["num_steps"]))) if "num_steps" in traj.stats else None,
            run_s=wall,
            compile_s=first - wall,
        )
        rows.append(row)
        print(json.dumps(row))
    out = dict(periods=args.periods, horizon_s=float(ts[-1]), samples=args.samples, rows=rows)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
