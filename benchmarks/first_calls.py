"""What the first call of a typical job costs in a new process, without and with the compiled
programs kept on disk (``rigidjax.use_compilation_cache``).

Each case runs three times, each in a new process (``python benchmarks/first_calls.py --one NAME
--cache DIR``): without a cache; with a new, empty cache (which it fills); and again with that
cache. The first call's wall time includes tracing, compiling (or loading) and running; the
programs JAX reports and their compile (or load) time are counted. A later call, with everything
compiled, is timed too (median of 5).

Usage:
    python benchmarks/first_calls.py          # ~8 min on 2 cores
Writes benchmarks/results/first_calls.md (``--out`` to change).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _cases():
    """Each job: a function that makes its inputs and returns the call to time."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import rigidjax as rj

    rng = np.random.default_rng(0)
    n, ts = 1000, jnp.linspace(0.0, 5.0, 200)
    q0 = jnp.asarray(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)))

    def closed_form():
        omega0, q = np.array([[[0.1, 0.9, 0.3]]] * 5), np.tile([1.0, 0.0, 0.0, 0.0], (5, 1, 1))
        return lambda: rj.torque_free_motion(np.array([1.0, 2.0, 3.0]), omega0, q, np.linspace(0.0, 10.0, 11))

    def free_bodies():
        inertia = np.array([1.0, 2.0, 2.5]) * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, (n, 3)))
        omega = np.array([0.05, 4.0, 0.05]) + 0.01 * rng.standard_normal((n, 3))
        state = rj.State(jnp.asarray(omega), q0)
        return lambda: rj.simulate(rj.FreeBody(jnp.asarray(inertia)), state, ts).omega

    def heavy_tops(accuracy):
        top = rj.HeavyTop(jnp.asarray(np.tile([1.0, 1.0, 0.5], (n, 1))), 1.0, jnp.array([0.0, 0.0, 0.3]))
        state = rj.State(jnp.asarray(np.array([0.3, -0.2, 8.0]) + 0.1 * rng.standard_normal((n, 3))), q0)
        return lambda: rj.simulate(top, state, ts, accuracy=accuracy).omega

    def fit():
        # Moments off the flat-plate edge, as the orientation fit's: (1, 2, 3) has I3 = I1 + I2, where
        # every fit ends on the edge and starts again from the six orders of the moments (~5 s).
        record_ts = np.linspace(0.0, 20.0, 240)
        clean = np.asarray(
            rj.torque_free_omega(np.array([1.0, 2.0, 2.5]), np.array([0.3, 0.5, 1.0]), record_ts)
        )
        record = clean + 1e-3 * rng.standard_normal(clean.shape)
        return lambda: rj.fit_inertia(record_ts, record).inertia

    def orientation_fit():
        record_ts = np.linspace(0.0, 20.0, 240)
        start = np.asarray(rj.quat_from_euler(np.array([0.3, 1.0, -0.5])))
        clean = rj.torque_free_motion(
            np.array([1.0, 2.0, 2.5]), np.array([0.3, 0.05, 1.0]), start, record_ts
        )[1]
        noise = rj.kinematics.quat_exp(2e-3 * rng.standard_normal((record_ts.size, 3)))
        record = np.asarray(rj.quat_multiply(clean, noise))
        return lambda: rj.fit_inertia_to_orientation(record_ts, record).inertia

    def gradient(accuracy, compiled):
        # d/d(omega0) of a function of the trajectory: the integrator's adjoint ("balanced"), or
        # the closed form's per-sample Jacobians ("exact"), both in reverse mode; called as it is
        # (the forward and transposed programs then compile apart, and so does each of the loss's
        # own operations) or inside jax.jit.
        top = rj.HeavyTop(jnp.asarray(np.tile([1.0, 1.0, 0.5], (n, 1))), 1.0, jnp.array([0.0, 0.0, 0.3]))
        omega = jnp.asarray(np.array([0.3, -0.2, 8.0]) + 0.1 * rng.standard_normal((n, 3)))

        def loss(w):
            trajectory = rj.simulate(top, rj.State(w, q0), ts, accuracy=accuracy)
            return jnp.sum(trajectory.omega[:, -1] ** 2) + jnp.sum(trajectory.orientation[:, -1, 1])

        gradient_of = jax.jit(jax.grad(loss)) if compiled else jax.grad(loss)
        return lambda: gradient_of(omega)

    return {
        "torque_free_motion (5 bodies, 11 times)": closed_form,
        'simulate "balanced", 1000 free bodies, 200 samples': free_bodies,
        'simulate "balanced", 1000 heavy tops, 200 samples': lambda: heavy_tops("balanced"),
        'simulate "exact", 1000 heavy tops, 200 samples': lambda: heavy_tops("exact"),
        "fit_inertia (240 samples)": fit,
        "fit_inertia_to_orientation (240 samples)": orientation_fit,
        'jax.grad of simulate "balanced", 1000 heavy tops': lambda: gradient("balanced", False),
        "the same in jax.jit": lambda: gradient("balanced", True),
        'jax.grad of simulate "exact", 1000 heavy tops, in jax.jit': lambda: gradient("exact", True),
    }


def _measure_one(name: str, cache: str | None) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import rigidjax as rj

    if cache:
        rj.use_compilation_cache(cache)
    else:
        jax.config.update("jax_enable_compilation_cache", False)
    call = _cases()[name]()  # the inputs are made before the timing
    compiled = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **kw: compiled.append(duration) if "backend_compile" in event else None
    )
    start = time.perf_counter()
    jax.block_until_ready(call())
    first = time.perf_counter() - start
    n_compiled, compile_s = len(compiled), sum(compiled)
    later = []
    for _ in range(5):
        start = time.perf_counter()
        jax.block_until_ready(call())
        later.append(time.perf_counter() - start)
    return {
        "first_s": first,
        "programs": n_compiled,
        "compile_s": compile_s,
        "later_s": statistics.median(later),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--one", help="measure this case in this process and print it as JSON")
    parser.add_argument("--cache", default="", help="with --one: the cache directory ('' for none)")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "first_calls.md"))
    args = parser.parse_args()
    if args.one:
        print(json.dumps(_measure_one(args.one, args.cache or None)))
        return
    env = {
        k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT"))
    }

    def run(name, cache):
        out = subprocess.run(
            [sys.executable, __file__, "--one", name, "--cache", cache],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        return json.loads(out.stdout.strip().splitlines()[-1])

    rows = []
    for name in _cases():
        with tempfile.TemporaryDirectory() as cache:
            off, filling, filled = run(name, ""), run(name, cache), run(name, cache)
        cells = [
            name,
            f"{off['first_s']:.2f} ({off['programs']}, {off['compile_s']:.2f})",
            f"{filling['first_s']:.2f}",
            f"{filled['first_s']:.2f} ({filled['compile_s']:.2f})",
            f"{off['later_s']:.3f}",
        ]
        rows.append("| " + " | ".join(cells) + " |")
        print(rows[-1], flush=True)
    import _harness as H
    import jax

    caption = (
        "First call of a job in a new process, float64; each column a new process "
        f"({platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, jax {jax.__version__}, "
        "`python benchmarks/first_calls.py`). Seconds of the first call (tracing, compiling or "
        "loading, running); in brackets the programs JAX compiled and their compile time, or with a "
        "filled cache their load time."
    )
    header = [
        "job",
        "no cache: first call s (programs, compile s)",
        "empty cache: first call s",
        "filled cache: first call s (load s)",
        "later call s",
    ]
    H.write_markdown(args.out, caption, header, rows)


if __name__ == "__main__":
    main()
