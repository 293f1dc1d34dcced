"""How the error of each preset grows as a torque-free body nears the separatrix, and how its
``error_estimate`` follows.

Bodies with moments (1, 2, 2.5) spun at 30 rad/s about the intermediate axis with a small
``omega_1`` that sets ``s = (|L|^2 - 2 E I2) / |L|^2`` from 1e-1 down to 1e-10, for 10 s (101
samples). The reference is a Taylor-series integration in NumPy extended precision (x87 80-bit, eps
1.1e-19), run at two step sizes: their difference is listed, the reference's own error. Errors are
the largest |omega - omega_ref| over the samples relative to |omega|.

    python benchmarks/separatrix_error.py [--out benchmarks/results/separatrix_error.json]

About a minute on 2 CPU cores. The table goes to stdout and to docs/guides/accuracy.md by hand.
"""

from __future__ import annotations

import argparse
import json
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rigidjax as rj  # noqa: E402

MOMENTS = np.array([1.0, 2.0, 2.5])
SPIN = 30.0  # rad/s
DURATION = 10.0  # s
S_TARGETS = np.logspace(-1, -10, 10)


def taylor_omega(inertia, omega0, ts, h, order=24):
    """omega at ``ts`` of Euler's torque-free equations, Taylor series in extended precision."""
    ld = np.longdouble
    inertia, w = np.asarray(inertia, ld), np.asarray(omega0, ld).copy()
    i1, i2, i3 = inertia[..., 0], inertia[..., 1], inertia[..., 2]
    c = ((i2 - i3) / i1, (i3 - i1) / i2, (i1 - i2) / i3)
    out, t = [w.copy()], ld(0)
    for t1 in np.asarray(ts, ld)[1:]:
        n = int(np.ceil(float((t1 - t) / ld(h))))
        dt = (t1 - t) / n
        for _ in range(n):
            terms = [w]
            for m in range(order):
                pair = [
                    sum(terms[j][..., a] * terms[m - j][..., b] for j in range(m + 1))
                    for a, b in ((1, 2), (2, 0), (0, 1))
                ]
                terms.append(np.stack([c[k] * pair[k] for k in range(3)], -1) / (m + 1))
            w = terms[-1]
            for term in reversed(terms[:-1]):
                w = w * dt + term
        t = t1
        out.append(w.copy())
    return np.stack(out, -2)


def relative_error(omega, reference):
    """Per body, as ``error_estimate`` measures: relative to the body's largest |omega|."""
    diff = np.max(np.linalg.norm(np.asarray(omega, np.float64) - reference, axis=-1), -1)
    return diff / np.max(np.linalg.norm(reference, axis=-1), -1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="benchmarks/results/separatrix_error.json")
    args = parser.parse_args(argv)
    # s = I1 (I1 - I2) w1^2 / |L|^2 with omega = (w1, SPIN, 0).
    w1 = np.sqrt(S_TARGETS * (MOMENTS[1] * SPIN) ** 2 / (MOMENTS[0] * (MOMENTS[1] - MOMENTS[0])))
    n = len(w1)
    omega0 = np.stack([w1, np.full(n, SPIN), np.zeros(n)], -1)
    inertia = np.broadcast_to(MOMENTS, (n, 3))
    s = np.abs(np.sum(inertia * (inertia - MOMENTS[1]) * omega0**2, -1) / np.sum((inertia * omega0) ** 2, -1))
    ts = np.linspace(0.0, DURATION, 101)
    reference = taylor_omega(inertia, omega0, ts, h=0.004).astype(np.float64)
    second = taylor_omega(inertia, omega0, ts, h=0.0025, order=22).astype(np.float64)
    reference_error = relative_error(second, reference)
    model = rj.FreeBody(jnp.asarray(inertia))
    state0 = rj.State(jnp.asarray(omega0), jnp.asarray(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))))
    rows = {"|s|": s, "reference self-difference": reference_error}
    runs = {
        "exact": {"accuracy": "exact"},
        "fast": {"accuracy": "fast", "chunk_size": 1},
        "balanced": {"accuracy": "balanced", "chunk_size": 1},
        "precise": {"accuracy": "precise", "chunk_size": 1},
        "LiePoissonSplitting(order=4), dt0 1e-3": {
            "solver": rj.solvers.LiePoissonSplitting(order=4),
            "dt0": 1e-3,
        },
    }
    for name, options in runs.items():
        traj = rj.simulate(model, state0, jnp.asarray(ts), error_estimate=True, **options)
        error = relative_error(traj.omega, reference)
        rows[name] = error
        rows[name + ": estimate / error"] = np.asarray(traj.error_estimate()["omega"]) / error
    print("| " + " | ".join(rows) + " |")
    print("|" + " --- |" * len(rows))
    for i in range(n):
        print(
            "| "
            + " | ".join(f"{v[i]:.2g}" if "estimate" in k else f"{v[i]:.1e}" for k, v in rows.items())
            + " |"
        )
    eps = float(np.finfo(np.float64).eps)
    near = s <= 1e-5
    slope = np.polyfit(np.log(s[near]), np.log(rows["precise"][near]), 1)[0]
    ratio = np.round(rows["precise"][near] * s[near] / eps, 1)
    print(f"precise, |s| <= 1e-5: error ~ |s|^{slope:.2f}; error * |s| / eps = {ratio}")
    with open(args.out, "w") as f:
        json.dump(
            {k: np.asarray(v, np.float64).tolist() for k, v in rows.items()}
            | {"precise_slope_s_le_1e-5": float(slope)},
            f,
            indent=1,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
