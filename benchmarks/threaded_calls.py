"""Whether a second CPU core can serve ``simulate`` on one JAX device: calls of the compiled
integration from several Python threads against one call.

On a single CPU device ``simulate`` solves its chunks one after another on one core, while a
user-written ``jax.vmap(diffeqsolve(...))`` of the whole batch gets XLA's own threads for its large
arrays. XLA's CPU runtime runs two independent loops of one program one after the other, but two
programs called from two Python threads at the same time. This script times, on the work-precision
scene (tennis-racket bodies, T = 20 s, "balanced", two sample times), alternating rounds of:

- one call on all bodies;
- the batch split into one part per thread, the parts called one after another;
- the same parts called from one Python thread each, at the same time.

The split changes which bodies share a chunk (each part is planned on its own), so the parts'
results agree with the one call to the preset's tolerance, not bitwise; the largest difference is
printed.

Usage:
    python benchmarks/threaded_calls.py                # 10^4 bodies, as many threads as cores
    python benchmarks/threaded_calls.py --n 1000 --threads 2 --rounds 3
Writes benchmarks/results/threaded_calls.md (``--out`` to change).
"""

from __future__ import annotations

import argparse
import os
import statistics
import threading
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _harness import reference_scene, run_meta, write_markdown  # noqa: E402

import rigidjax as rj  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=10_000, help="bodies")
    p.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)), help="parts and threads")
    p.add_argument("--rounds", type=int, default=7, help="alternating timed rounds")
    p.add_argument("--out", default=str(RESULTS / "threaded_calls.md"))
    a = p.parse_args(argv)
    inertia, omega0, q0 = reference_scene(a.n)
    ts = np.array([0.0, 20.0])
    parts = np.array_split(np.arange(a.n), a.threads)

    def call(index):
        model, state = rj.FreeBody(inertia[index]), rj.State(omega0[index], q0[index])
        return rj.simulate(model, state, ts, accuracy="balanced").omega.block_until_ready()

    outputs = [None] * len(parts)

    def run_part(k):
        outputs[k] = call(parts[k])

    def threaded():
        workers = [threading.Thread(target=run_part, args=(k,)) for k in range(len(parts))]
        for w in workers:
            w.start()
        for w in workers:
            w.join()

    whole = call(np.arange(a.n))  # compiles; the parts compile below (one program per part size)
    threaded()
    difference = float(np.max(np.abs(np.concatenate(outputs) - np.asarray(whole))))
    ways = {
        "one call": lambda: call(np.arange(a.n)),
        f"{len(parts)} parts, one after another": lambda: [run_part(k) for k in range(len(parts))],
        f"{len(parts)} parts, one thread each": threaded,
    }
    times = {name: [] for name in ways}
    for _ in range(a.rounds):
        for name, fn in ways.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    one = statistics.median(times["one call"])
    rows = []
    for name, values in times.items():
        median = statistics.median(values)
        rows.append(f"| {name} | {median * 1e3:.1f} | {min(values) * 1e3:.1f} | {one / median:.2f} |")
        print(
            f"{name:32s} median {median * 1e3:7.1f} ms  min {min(values) * 1e3:7.1f} ms  "
            f"speed-up {one / median:.2f}"
        )
    print(f"largest |omega(T)| difference, parts against one call: {difference:.1e}")
    meta = run_meta("benchmarks/threaded_calls.py", argv, n=a.n, threads=a.threads)
    caption = (
        f"`simulate` 'balanced' from {a.threads} Python threads on one CPU device, N = {a.n} tennis-racket "
        f"bodies, T = 20 s, two sample times; medians of {a.rounds} alternating rounds "
        f"(`{meta['command']}`, {meta['devices'][0]}, jax {meta['jax']}, "
        f"{os.cpu_count()} CPUs). Largest difference of omega(T), parts against one call: {difference:.1e}."
    )
    write_markdown(a.out, caption, ["calls", "median ms", "min ms", "speed-up"], rows)


if __name__ == "__main__":
    main()
