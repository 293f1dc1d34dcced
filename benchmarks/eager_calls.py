"""What an eager call of a public function costs: the first call in a new process (without the
persistent compilation cache, the programs it compiles counted) and a later call.

Each function runs in a process of its own (``python benchmarks/eager_calls.py --one NAME``), float64,
on a batch of 5 inputs; a later call is the median of 50 calls with ``block_until_ready``.

Usage:
    python benchmarks/eager_calls.py          # ~1 min on 2 cores
Writes benchmarks/results/eager_calls.md (``--out`` to change).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path


def _cases():
    import jax
    import jax.numpy as jnp
    import numpy as np

    import rigidjax as rj

    # Inputs made with NumPy and placed on the device as they are: no JAX operation (and so no
    # compiled program) before the measured call.
    angles = jnp.asarray(np.array([[0.1, 0.7, 0.3]] * 5))
    w, x, y, z = np.array([0.9, 0.1, 0.3, 0.2]) / np.linalg.norm([0.9, 0.1, 0.3, 0.2])
    q = jnp.asarray(np.array([[w, x, y, z]] * 5))
    matrix = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    R = jnp.asarray(np.array([matrix] * 5))
    moments, omega = jnp.asarray(np.array([1.0, 2.0, 3.0])), jnp.asarray(np.array([[0.1, 0.2, 0.3]] * 5))
    tensor = jnp.asarray(np.diag([1.0, 2.0, 3.0]))
    top = rj.HeavyTop(jnp.array([1.0, 1.0, 0.5]), 1.0, jnp.array([0.0, 0.0, 0.3]))
    state = rj.State(jnp.array([[0.3, -0.2, 8.0]] * 4), jnp.array([[1.0, 0.0, 0.0, 0.0]] * 4))
    state5 = rj.State(omega, q)
    masses, parts = jnp.asarray(np.ones(4)), jnp.asarray(np.array([[1.0, 2.0, 2.5]] * 4))
    coms = jnp.asarray(np.array([[0.1, 0.2, 0.3], [0.0, -0.1, 0.2], [0.3, 0.0, 0.0], [-0.2, 0.1, 0.1]]))
    return {
        "quat_from_euler": lambda: rj.quat_from_euler(angles),
        "matrix_from_euler": lambda: rj.matrix_from_euler(angles),
        "euler_from_quat": lambda: rj.euler_from_quat(q),
        "euler_from_matrix": lambda: rj.euler_from_matrix(R),
        "quat_from_matrix": lambda: rj.quat_from_matrix(R),
        "body_angular_velocity": lambda: rj.body_angular_velocity(angles, angles),
        "euler_rates": lambda: rj.euler_rates(angles, omega),
        "euler_equations": lambda: rj.euler_equations(moments, omega),
        "kinetic_energy": lambda: rj.kinetic_energy(moments, omega),
        "space_angular_momentum": lambda: rj.space_angular_momentum(moments, omega, q),
        "principal_axes": lambda: rj.principal_axes(tensor),
        "check_inertia": lambda: rj.check_inertia(tensor),
        "is_physical_inertia": lambda: rj.is_physical_inertia(tensor),
        "parallel_axis": lambda: rj.parallel_axis(moments, 2.0, omega[0]),
        "spin_stability": lambda: rj.spin_stability(moments, 3.0),
        "quat_multiply": lambda: rj.quat_multiply(q, q),
        "quat_rotate": lambda: rj.quat_rotate(q, omega),
        "quat_normalize": lambda: rj.quat_normalize(q),
        "matrix_from_quat": lambda: rj.matrix_from_quat(q),
        "solid_box": lambda: rj.solid_box(2.0, omega),
        "composite_inertia (4 parts)": lambda: rj.composite_inertia(masses, coms, parts),
        "kinematics.quat_exp": lambda: rj.kinematics.quat_exp(omega),
        "convert.to_mujoco_free_joint": lambda: rj.convert.to_mujoco_free_joint(state5),
        "jax.grad of a sum of euler_from_quat": lambda: jax.grad(lambda q: rj.euler_from_quat(q).sum())(q),
        "Trajectory.invariants (heavy top)": (
            lambda: rj.simulate(top, state, jnp.linspace(0.0, 1.0, 5), accuracy="exact"),
            lambda traj: traj.invariants(),
        ),
    }


def _measure_one(name: str) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_enable_compilation_cache", False)
    case = _cases()[name]
    setup, call = case if isinstance(case, tuple) else (lambda: None, lambda _: case())
    subject = jax.block_until_ready(setup())
    compiled = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **kw: compiled.append(duration) if "backend_compile" in event else None
    )
    start = time.perf_counter()
    jax.block_until_ready(call(subject))
    first = time.perf_counter() - start
    n_compiled, compile_s = len(compiled), sum(compiled)
    later = []
    for _ in range(50):
        start = time.perf_counter()
        jax.block_until_ready(call(subject))
        later.append(time.perf_counter() - start)
    return {
        "first_s": first,
        "programs": n_compiled,
        "compile_s": compile_s,
        "later_ms": 1e3 * statistics.median(later),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--one", help="measure this case in this process and print it as JSON")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "eager_calls.md"))
    args = parser.parse_args()
    if args.one:
        print(json.dumps(_measure_one(args.one)))
        return
    env = dict(os.environ, JAX_ENABLE_COMPILATION_CACHE="false")
    rows = []
    for name in _cases():
        out = subprocess.run(
            [sys.executable, __file__, "--one", name], env=env, capture_output=True, text=True, check=True
        )
        r = json.loads(out.stdout.strip().splitlines()[-1])
        cells = [f"`{name}`", f"{r['first_s']:.3f}", str(r["programs"]), f"{r['compile_s']:.3f}"]
        rows.append("| " + " | ".join(cells + [f"{r['later_ms']:.2f}"]) + " |")
        print(rows[-1], flush=True)
    import _harness as H
    import jax

    caption = (
        f"Eager calls, float64, batch of 5, one new process per row, no persistent compilation cache; "
        f"{platform.processor() or platform.machine()}, jax {jax.__version__} "
        "(`python benchmarks/eager_calls.py`)"
    )
    header = ["call", "first call s", "programs compiled", "their compile s", "later call ms (median of 50)"]
    H.write_markdown(args.out, caption, header, rows)


if __name__ == "__main__":
    main()
