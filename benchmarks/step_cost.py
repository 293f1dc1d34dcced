"""Where an adaptive Runge-Kutta integration spends its time, in nanoseconds per body and step.

Scene: the tennis-racket bodies of ``work_precision.py`` (``_harness.reference_scene``), float64,
Dormand-Prince 8(7) at rtol = atol = 1e-8 over T = 20 s (the ``"balanced"`` preset).

Rows, each the median of ``--repeats`` timed calls after a first (compiling) call:

- ``simulate`` on ``--n`` bodies, run time / (steps summed over chunks x chunk): the preset
  (:class:`rigidjax.solvers.UnrolledDopri8`, chunks of 256 bodies on CPU), the same with chunks of
  1024, with diffrax's ``Dopri8`` (a loop over a stage buffer) in its place, and the preset with 801
  sample times (the dense output at every step);
- the vector field alone, as ``simulate`` evaluates it (state one ``(7, N)`` array, the scene's
  one-body ``angular_acceleration`` under ``jax.vmap``) and written row by row (Euler's equations
  and the quaternion rate for principal moments), per body-evaluation, on one chunk of ``--chunk``;
- one step in a ``fori_loop`` on that chunk and field: diffrax's ``Dopri8.step``, ``UnrolledDopri8``
  and ``UnrolledDopri8`` without its fences (XLA then fuses each stage's field evaluation into every
  later stage sum that reads it).

Usage:
    python benchmarks/step_cost.py                 # ~3 min on 2 cores
    python benchmarks/step_cost.py --chunk 512 --repeats 7
Writes benchmarks/results/step_cost.md (``--out`` to change).
"""

from __future__ import annotations

import argparse
import platform
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _harness import reference_scene, timed_calls  # noqa: E402

import rigidjax as rj  # noqa: E402
from rigidjax._integrate import batching  # noqa: E402
from rigidjax._integrate.formulations import ScaledODE  # noqa: E402
from rigidjax._integrate.solvers import unrolled  # noqa: E402
from rigidjax._kinematics.quaternion import NORM_PULL  # noqa: E402
from rigidjax.solvers import UnrolledDopri8  # noqa: E402

T_END = 20.0
RTOL = 1e-8
LOOP_STEPS = 200


def row_vector_field(inertia_rows):
    """Euler's equations (principal moments) and the quaternion rate, row by row on ``(7, N)``, with
    the norm-attracting pull of the package's quaternion rate."""
    i1, i2, i3 = inertia_rows

    def field(t, y, args):
        w1, w2, w3, qw, qx, qy, qz = (y[i] for i in range(7))
        speed = jnp.sqrt(w1 * w1 + w2 * w2 + w3 * w3)
        pull = NORM_PULL * speed * (1.0 - (qw * qw + qx * qx + qy * qy + qz * qz))
        return jnp.stack(
            [
                (i2 - i3) / i1 * w2 * w3,
                (i3 - i1) / i2 * w3 * w1,
                (i1 - i2) / i3 * w1 * w2,
                0.5 * (-qx * w1 - qy * w2 - qz * w3) + pull * qw,
                0.5 * (qw * w1 + qy * w3 - qz * w2) + pull * qx,
                0.5 * (qw * w2 + qz * w1 - qx * w3) + pull * qy,
                0.5 * (qw * w3 + qx * w2 - qy * w1) + pull * qz,
            ]
        )

    return field


class UnfencedDopri8(UnrolledDopri8):
    """``UnrolledDopri8`` with its stage fences lifted (for this comparison only)."""

    def step(self, *args):
        fence = unrolled._fence
        unrolled._fence = lambda tree: tree
        try:
            return super().step(*args)
        finally:
            unrolled._fence = fence


def median_time(fn, arg, repeats):
    """Median seconds of ``repeats`` calls of ``fn(arg)`` after a first, compiling call."""
    return timed_calls(lambda: fn(arg), repeats)[1]["run_s"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=10_000, help="bodies for the simulate row")
    parser.add_argument("--chunk", type=int, default=256, help="bodies for the field and step rows")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "step_cost.md"))
    opts = parser.parse_args(argv)
    rows = []

    inertia, omega0, q0 = reference_scene(opts.n)
    model = rj.FreeBody(jnp.asarray(inertia))
    state0 = rj.State(jnp.asarray(omega0), jnp.asarray(q0))
    ends = jnp.array([0.0, T_END])
    for name, ts, settings in (
        ("simulate(accuracy='balanced'), whole run", ends, {}),
        ("the same, chunk_size=1024", ends, {"chunk_size": 1024}),
        ("the same with diffrax's Dopri8", ends, {"solver": diffrax.Dopri8(), "rtol": RTOL, "atol": RTOL}),
        ("simulate(accuracy='balanced'), 801 sample times", jnp.linspace(0.0, T_END, 801), {}),
    ):
        trajectory = rj.simulate(model, state0, ts, **settings)
        steps = int(np.sum(trajectory.stats["num_steps"])) * trajectory.stats["chunk_size"]
        run = median_time(
            lambda s, ts=ts, kw=settings: rj.simulate(model, s, ts, **kw).omega, state0, opts.repeats
        )
        rows.append((name, run / steps, f"{opts.n} bodies, chunks of {trajectory.stats['chunk_size']}"))

    n = opts.chunk
    inertia, omega0, q0 = (jnp.asarray(x[:n]) for x in (inertia, omega0, q0))
    leaves, flat = batching.flatten_model(rj.FreeBody(inertia), (n,), jnp.float64)
    shell = rj.FreeBody(inertia).replace_body_leaves(leaves, [None] * len(leaves))
    sigma = jnp.ones((n, 3))
    package_field = ScaledODE().vector_field(shell, leaves, flat, sigma)
    y_package = ScaledODE().initial_state(flat, leaves, omega0, q0, sigma)
    field = row_vector_field(inertia.T)

    def field_loop(vf):
        def loop(y):
            return jax.lax.fori_loop(0, LOOP_STEPS, lambda i, y: y + 1e-9 * vf(0.0, y, None), y)

        return jax.jit(loop)

    for name, vf in (("simulate's", package_field), ("written row by row", field)):
        cost = median_time(field_loop(vf), y_package, opts.repeats) / (LOOP_STEPS * n)
        rows.append((f"vector field alone, {name}, per evaluation", cost, f"{n} bodies"))

    def step_loop(solver, vf):
        term = diffrax.ODETerm(vf)

        def loop(y):
            def body(i, carry):
                y, state = carry
                y1, error, dense, state, _ = solver.step(term, 0.0, 1e-4, y, None, state, jnp.array(False))
                # Keeps the dense output alive (its stages or, for UnrolledDopri8, its polynomial).
                dense_output = jax.tree_util.tree_leaves(dense)[0][-1]
                return y1 + 1e-30 * (error + dense_output), state

            return jax.lax.fori_loop(0, LOOP_STEPS, body, (y, solver.init(term, 0.0, 1e-4, y, None)))[0]

        return jax.jit(loop)

    for name, solver in (
        ("diffrax Dopri8.step", diffrax.Dopri8()),
        ("UnrolledDopri8.step", UnrolledDopri8()),
        ("UnrolledDopri8.step without its fences", UnfencedDopri8()),
    ):
        cost = median_time(step_loop(solver, package_field), y_package, opts.repeats) / (LOOP_STEPS * n)
        rows.append((f"one step in a loop: {name}", cost, f"{n} bodies"))

    header = (
        f"Step cost, tennis-racket scene, Dopri8 at rtol {RTOL:g}, T = {T_END:g} s, float64, "
        f"{jax.devices()[0].platform}, {platform.machine()}, jax {jax.__version__} "
        f"(`python benchmarks/step_cost.py --chunk {opts.chunk}`)"
    )
    lines = [
        header,
        "",
        "| what | ns per body-step (field rows: per evaluation) | bodies |",
        "| --- | --- | --- |",
    ]
    lines += [f"| {name} | {1e9 * cost:.0f} | {note} |" for name, cost, note in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    Path(opts.out).write_text(text)


if __name__ == "__main__":
    main()
