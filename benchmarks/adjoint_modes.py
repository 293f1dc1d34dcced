"""Forward and reverse mode through ``simulate``: time and peak memory of each adjoint.

N free bodies (random inertias, omega0 and orientations, seed 0), 50 samples over T = 10 s
(``--duration``), the balanced preset, float64. The function differentiated is a scalar of every output,
``sum(a * omega) + sum(b * orientation)`` (fixed random weights), of an offset ``d`` (3,) added to
every body's omega0: ``jax.jacfwd`` pushes 3 tangents, ``jax.jacrev`` pulls 1 cotangent.

Each case is one ``jax.jit`` program: compile once, then the median of ``--repeats`` calls. Memory is
XLA's own account of the compiled program (``memory_analysis()``: temporary buffers, the peak
working memory beyond inputs and outputs).

Cases: the forward simulation (default, and with ``DirectAdjoint``); ``jacrev`` with
``RecursiveCheckpointAdjoint``; ``jacfwd`` with ``ForwardMode``; both with ``DirectAdjoint``; both with
the default (no ``adjoint=``).

Usage:
    python benchmarks/adjoint_modes.py                 # N = 1 and 256 (~5 min on 2 cores)
    python benchmarks/adjoint_modes.py --n 1 --repeats 3
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


def scene(n):
    rng = np.random.default_rng(0)
    inertia = jnp.asarray(rng.uniform(2.0, 3.0, (n, 3)))  # every triple physical
    omega0 = jnp.asarray(rng.normal(size=(n, 3)))
    q0 = rj.quat_from_euler(jnp.asarray(rng.uniform(0.2, 1.2, (n, 3))))
    a = jnp.asarray(rng.normal(size=(n, 50, 3)))
    b = jnp.asarray(rng.normal(size=(n, 50, 4)))
    return inertia, omega0, q0, a, b


def loss_fn(n, adjoint, duration=10.0):
    inertia, omega0, q0, a, b = scene(n)
    ts = jnp.linspace(0.0, duration, 50)
    kwargs = {} if adjoint is None else {"adjoint": adjoint}

    def loss(d):
        traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega0 + d, q0), ts, **kwargs)
        return jnp.sum(a * traj.omega) + jnp.sum(b * traj.orientation)

    return loss


def measure(fn, repeats):
    d = jnp.zeros(3)
    start = time.perf_counter()
    compiled = jax.jit(fn).lower(d).compile()
    compile_s = time.perf_counter() - start
    mem = compiled.memory_analysis()
    temp = None if mem is None else int(mem.temp_size_in_bytes)
    jax.block_until_ready(compiled(d))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(d))
        times.append(time.perf_counter() - start)
    return {"compile_s": compile_s, "run_s": float(np.median(times)), "temp_bytes": temp}


CASES = {
    "forward": (None, None),
    "forward DirectAdjoint": (None, diffrax.DirectAdjoint()),
    "jacrev RecursiveCheckpoint": ("rev", diffrax.RecursiveCheckpointAdjoint()),
    "jacfwd ForwardMode": ("fwd", diffrax.ForwardMode()),
    "jacrev DirectAdjoint": ("rev", diffrax.DirectAdjoint()),
    "jacfwd DirectAdjoint": ("fwd", diffrax.DirectAdjoint()),
    "jacrev default": ("rev", None),
    "jacfwd default": ("fwd", None),
}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=int, nargs="+", default=[1, 256])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--duration", type=float, default=10.0, help="T (s): the last sample time")
    parser.add_argument("--cases", nargs="+", default=list(CASES))
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    results = []
    for n in args.n:
        for name in args.cases:
            mode, adjoint = CASES[name]
            loss = loss_fn(n, adjoint, args.duration)
            fn = loss if mode is None else (jax.jacrev if mode == "rev" else jax.jacfwd)(loss)
            try:
                row = {"n": n, "T": args.duration, "case": name, **measure(fn, args.repeats)}
            except Exception as err:  # noqa: BLE001  (a mode an adjoint does not support)
                row = {
                    "n": n,
                    "T": args.duration,
                    "case": name,
                    "error": f"{type(err).__name__}: {str(err).splitlines()[0]}",
                }
            results.append(row)
            print(json.dumps(row), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
