"""The cost of one shared step of ``simulate`` on one device, for variants of its solver.

The tennis-racket scene of ``_harness.py`` (N bodies, T = 20 s, float64, one chunk, two sample
times): ``simulate`` "balanced" and "precise" with :class:`rigidjax.solvers.UnrolledDopri8` with its
stages fenced (each stage's field a separate value) and unfenced (XLA free to fuse the stages),
diffrax's own ``Dopri8`` at the same tolerance, and the user-written vmapped Tsit5 at rtol 1e-6 and
1e-7 (the "precise" preset also lands a step on every sample time, its unfenced variant does not,
so those two differ by more than the fence). For each: median run time of ``--repeats`` calls
after a first (compile) call, shared steps, time per step, max relative omega error at T against
the float64 closed form, and the number of kernels-to-be in the compiled program (fusions, custom
calls and copies in the optimised HLO).

On a GPU a step of 10^4 bodies costs about its kernel launches and loop bookkeeping, so the variants
differ by how many kernels XLA makes of a step; on a CPU, by the arithmetic and the cache.

Usage:
    python benchmarks/gpu_step_variants.py [--n 10000] [--out results/gpu_step_variants.json]
    XLA_FLAGS=--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL python benchmarks/gpu_step_variants.py
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rigidjax as rj  # noqa: E402
from rigidjax.solvers import UnrolledDopri8  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _harness as B  # noqa: E402

_KERNEL_LINE = re.compile(r"=\s*\S+\s+(fusion|custom-call|copy|sort|reduce|scatter|gather)\(")


def _kernel_count(compiled_text: str) -> int:
    return sum(1 for line in compiled_text.splitlines() if _KERNEL_LINE.search(line))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=10_000)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--out", default=None, help="JSON results (default: print only)")
    p.add_argument("--hlo-dir", default=None, help="write each variant's optimised HLO here")
    a = p.parse_args(argv)

    inertia, omega0, q0 = B.reference_scene(a.n)
    omega_ref, _, _ = B.closed_form_reference((inertia, omega0, q0))
    model = rj.FreeBody(jnp.asarray(inertia))
    state = rj.State(jnp.asarray(omega0), jnp.asarray(q0))
    ts = jnp.array([0.0, B.T_END])
    peer = B.peer_program()
    peer_args = (jnp.asarray(inertia), jnp.asarray(np.concatenate([omega0, q0], -1)))

    def sim(**kw):
        def run(model, state, ts):
            tr = rj.simulate(model, state, ts, chunk_size=a.n, throw=False, **kw)
            return tr.omega[:, -1], tr.stats["num_steps"]

        return jax.jit(run), (model, state, ts)

    variants = {
        # The solver named: below 1024 bodies the presets choose diffrax's Dopri8.
        "balanced, stages fenced": sim(solver=UnrolledDopri8(), rtol=1e-8, atol=1e-8),
        "balanced, stages unfenced": sim(solver=UnrolledDopri8(fence_stages=False), rtol=1e-8, atol=1e-8),
        "balanced tolerance, diffrax Dopri8": sim(solver=diffrax.Dopri8(), rtol=1e-8, atol=1e-8),
        "precise, stages fenced": sim(solver=UnrolledDopri8(), rtol=1e-11, atol=1e-11),
        "precise, stages unfenced": sim(solver=UnrolledDopri8(fence_stages=False), rtol=1e-11, atol=1e-11),
        "fast (Tsit5)": sim(accuracy="fast"),
    }
    for rtol in (1e-6, 1e-7):
        r = jnp.asarray(rtol)
        variants[f"vmapped Tsit5, rtol {rtol:g}"] = (
            jax.jit(lambda i, y, r=r: (peer(i, y, r, r)[:, :3], jnp.zeros((1,), jnp.int32))),
            peer_args,
        )

    rows = []
    for name, (fn, args) in variants.items():
        t0 = time.perf_counter()
        compiled = fn.lower(*args).compile()
        compile_s = time.perf_counter() - t0
        text = compiled.as_text()
        if a.hlo_dir:
            os.makedirs(a.hlo_dir, exist_ok=True)
            slug = re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_")
            with open(os.path.join(a.hlo_dir, f"{slug}.hlo.txt"), "w") as fh:
                fh.write(text)
        omega, steps = jax.block_until_ready(compiled(*args))
        times = []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(*args))
            times.append(time.perf_counter() - t0)
        run_s = statistics.median(times)
        err = np.max(
            np.linalg.norm(np.asarray(omega) - omega_ref, axis=-1) / np.linalg.norm(omega_ref, axis=-1)
        )
        n_steps = int(np.max(np.asarray(steps)))
        row = dict(
            name=name,
            run_s=run_s,
            compile_s=compile_s,
            steps=n_steps,
            us_per_step=1e6 * run_s / n_steps if n_steps else None,
            max_rel_omega=float(err),
            kernels=_kernel_count(text),
        )
        rows.append(row)
        per_step = f"{row['us_per_step']:7.1f} us/step" if n_steps else "       -       "
        print(
            f"{name:38s} {run_s * 1e3:8.2f} ms  steps {n_steps:4d}  {per_step}  err {err:.1e}  "
            f"kernels {row['kernels']:4d}  compile {compile_s:.1f} s",
            flush=True,
        )
    meta = dict(
        n=a.n,
        devices=[str(d) for d in jax.devices()],
        jax=jax.__version__,
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        command="python benchmarks/gpu_step_variants.py " + " ".join(argv or sys.argv[1:]),
    )
    if a.out:
        with open(a.out, "w") as fh:
            json.dump(dict(meta=meta, rows=rows), fh, indent=1)


if __name__ == "__main__":
    main()
