"""``simulate`` on one CPU device: its chunks from one Python thread per core (the default) against
one compiled call.

On a single CPU device XLA runs one call of a program on one core (a ``lax.map`` of while loops does
not spread over XLA's threads), while a user-written ``jax.vmap(diffeqsolve(...))`` of the whole
batch gets XLA's threads for its large arrays. Calls made from several Python threads do run side by
side, so ``simulate`` runs its chunks as one block per core, each from its own thread, with the same
chunks and steps as one call. This script times, on the work-precision scene (tennis-racket bodies,
T = 20 s, two sample times), alternating rounds of:

- ``simulate`` as it runs by default (one block per core, ``rigidjax`` decides the threads);
- the same call as one compiled program (the thread count forced to 1);

for each preset in ``--accuracies``, and checks that both give the same trajectories to the bit.

Usage:
    python benchmarks/threaded_calls.py                # 10^4 bodies, "balanced" and "precise"
    python benchmarks/threaded_calls.py --n 1000 --rounds 3 --accuracies fast
Writes benchmarks/results/threaded_calls.md (``--out`` to change).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _harness import reference_scene, run_meta, write_markdown  # noqa: E402

import rigidjax as rj  # noqa: E402
from rigidjax._integrate import progress  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=10_000, help="bodies")
    p.add_argument("--accuracies", default="balanced,precise")
    p.add_argument("--rounds", type=int, default=7, help="alternating timed rounds")
    p.add_argument("--out", default=str(RESULTS / "threaded_calls.md"))
    a = p.parse_args(argv)
    inertia, omega0, q0 = reference_scene(a.n)
    ts = np.array([0.0, 20.0])
    model, state = rj.FreeBody(inertia), rj.State(omega0, q0)
    default_threads = progress.host_threads

    def call(accuracy, one_program):
        progress.host_threads = (lambda *args: 1) if one_program else default_threads
        try:
            traj = rj.simulate(model, state, ts, accuracy=accuracy)
            return jax.block_until_ready(traj)
        finally:
            progress.host_threads = default_threads

    threads = default_threads(model, state.omega, state.orientation, ts, None, 256)
    rows = []
    for accuracy in [s.strip() for s in a.accuracies.split(",") if s.strip()]:
        first, first_s = {}, {}
        for one_program in (True, False):  # first calls: compile apart
            start = time.perf_counter()
            first[one_program] = call(accuracy, one_program)
            first_s[one_program] = time.perf_counter() - start
            print(f"{accuracy}: first call, {'one program' if one_program else 'threads'} "
                  f"{first_s[one_program]:.2f} s", flush=True)  # fmt: skip
        same = all(
            np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
            for x, y in zip(
                jax.tree_util.tree_leaves((first[True].omega, first[True].orientation)),
                jax.tree_util.tree_leaves((first[False].omega, first[False].orientation)),
                strict=True,
            )
        )
        times = {True: [], False: []}
        for _ in range(a.rounds):
            for one_program in (True, False):
                start = time.perf_counter()
                call(accuracy, one_program)
                times[one_program].append(time.perf_counter() - start)
        one, many = statistics.median(times[True]), statistics.median(times[False])
        for label, key in (("one compiled call", True), (f"{threads} threads (default)", False)):
            median = statistics.median(times[key])
            rows.append(
                f"| {accuracy} | {label} | {median * 1e3:.1f} | {min(times[key]) * 1e3:.1f} | "
                f"{one / median:.2f} | {first_s[key]:.2f} | {'yes' if same else 'NO'} |"
            )
        print(f"{accuracy}: one call {one * 1e3:.1f} ms, {threads} threads {many * 1e3:.1f} ms "
              f"({one / many:.2f}x), the same to the bit: {same}", flush=True)  # fmt: skip
    meta = run_meta("benchmarks/threaded_calls.py", argv, n=a.n, threads=threads)
    caption = (
        f"`simulate` on one CPU device, {threads} threads against one compiled call, N = {a.n} "
        f"tennis-racket bodies, T = 20 s, two sample times; medians of {a.rounds} alternating rounds, "
        f"compile excluded; the first call (compile and run, one program for all the threads) timed "
        f"apart (`{meta['command']}`, {meta['devices'][0]}, jax {meta['jax']}, "
        f"{os.cpu_count()} CPUs, load {meta['loadavg_start']})."
    )
    headers = [
        "accuracy",
        "calls",
        "median ms",
        "min ms",
        "speed-up",
        "first call s",
        "same trajectories to the bit",
    ]
    write_markdown(a.out, caption, headers, rows)


if __name__ == "__main__":
    main()
