"""Where an adaptive Runge-Kutta integration spends its time, in nanoseconds per body and step.

Scene: the tennis-racket bodies of ``work_precision.py`` (``_harness.reference_scene``), float64,
one chunk of ``--chunk`` bodies (the CPU default), Dormand-Prince 8(7) (diffrax's ``Dopri8``, the
``"balanced"`` and ``"precise"`` presets' method) at rtol = atol = 1e-8 over T = 20 s.

Rows, each the median of ``--repeats`` timed calls after a first (compiling) call:

- ``simulate(accuracy="balanced")`` on ``--n`` bodies: run time / (steps summed over chunks x chunk);
- the vector field alone, as ``simulate`` evaluates it (state ``(u (3, N), q (4, N))``, the scene's
  one-body ``angular_acceleration`` under ``jax.vmap``), and written row by row on a ``(7, N)``
  state (Euler's equations and the quaternion rate for principal moments), per body-evaluation;
- one step in a ``fori_loop``: diffrax's ``Dopri8.step`` on the first vector field; the same
  tableau with its 14 stages unrolled, on ``simulate``'s state and field and on the row-wise ones;
- ``diffeqsolve`` with that unrolled step (a diffrax solver written here) saving only the end point
  (``SaveAt(t1=True)``) and saving at two sample times (``SaveAt(ts=[0, T])``, dense output).

Usage:
    python benchmarks/step_cost.py                 # ~2 min on 2 cores
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
from rigidjax._integrate.chunked import max_norm  # noqa: E402
from rigidjax._integrate.formulations import ScaledODE  # noqa: E402

T_END = 20.0
RTOL = 1e-8
LOOP_STEPS = 200
TABLEAU = diffrax.Dopri8.tableau
A_ROWS = [np.asarray(a, np.float64) for a in TABLEAU.a_lower]
C_NODES = np.asarray(TABLEAU.c, np.float64)
B_ERROR = np.asarray(TABLEAU.b_error, np.float64)


def _combine(y, coefficients, ks):
    """``y + sum_j coefficients[j] ks[j]`` leaf by leaf, skipping the tableau's zeros."""

    def leaf(y, *k):
        for c, k_j in zip(coefficients, k, strict=False):
            if c != 0.0:
                y = y + c * k_j
        return y

    return jax.tree_util.tree_map(leaf, y, *ks)


class UnrolledDopri8(diffrax.Dopri8):
    """diffrax's Dopri8 tableau with its stages unrolled (first-same-as-last, the same dense output)."""

    def init(self, terms, t0, t1, y0, args):
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        f0 = jax.lax.cond(made_jump, lambda: terms.vf(t0, y0, args), lambda: solver_state)
        h = terms.contr(t0, t1)
        ks = [terms.prod(f0, h)]
        for a, c in zip(A_ROWS, C_NODES, strict=True):
            y_stage = _combine(y0, a, ks)
            f_stage = terms.vf(t1 if c == 1.0 else t0 + c * h, y_stage, args)
            ks.append(terms.prod(f_stage, h))
        y1, f1 = y_stage, f_stage  # the last stage is evaluated at y1 (first same as last)
        y_error = _combine(jax.tree_util.tree_map(jnp.zeros_like, y0), B_ERROR, ks)
        dense_info = dict(y0=y0, y1=y1, k=jax.tree_util.tree_map(lambda *k: jnp.stack(k), *ks))
        return y1, y_error, dense_info, f1, diffrax.RESULTS.successful


def row_vector_field(inertia_rows):
    """Euler's equations (principal moments) and the quaternion rate, row by row on ``(7, N)``."""
    i1, i2, i3 = inertia_rows

    def field(t, y, args):
        w1, w2, w3, qw, qx, qy, qz = (y[i] for i in range(7))
        pull = jnp.sqrt(w1 * w1 + w2 * w2 + w3 * w3) * (1.0 - (qw * qw + qx * qx + qy * qy + qz * qz))
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


def median_time(fn, arg, repeats):
    """Median seconds of ``repeats`` calls of ``fn(arg)`` after a first, compiling call."""
    return timed_calls(lambda: fn(arg), repeats)[1]["run_s"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=10_000, help="bodies for the simulate row")
    parser.add_argument("--chunk", type=int, default=1024, help="bodies per chunk for the other rows")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "step_cost.md"))
    opts = parser.parse_args(argv)
    rows = []

    inertia, omega0, q0 = reference_scene(opts.n)
    model = rj.FreeBody(jnp.asarray(inertia))
    state0 = rj.State(jnp.asarray(omega0), jnp.asarray(q0))
    ts = jnp.array([0.0, T_END])
    trajectory = rj.simulate(model, state0, ts, accuracy="balanced")
    steps = int(np.sum(trajectory.stats["num_steps"])) * trajectory.stats["chunk_size"]
    run = median_time(lambda s: rj.simulate(model, s, ts, accuracy="balanced").omega, state0, opts.repeats)
    rows.append(("simulate(accuracy='balanced'), whole run", run / steps, f"{opts.n} bodies"))

    n = opts.chunk
    inertia, omega0, q0 = (jnp.asarray(x[:n]) for x in (inertia, omega0, q0))
    leaves, flat = batching.flatten_model(rj.FreeBody(inertia), (n,), jnp.float64)
    shell = rj.FreeBody(inertia).replace_body_leaves(leaves, [None] * len(leaves))
    sigma = jnp.ones((n, 3))
    package_field = ScaledODE().vector_field(shell, leaves, flat, sigma)
    y_package = ScaledODE().initial_state(flat, leaves, omega0, q0, sigma)
    field = row_vector_field(inertia.T)
    y_rows = jnp.concatenate([omega0.T, q0.T])

    def field_loop(vf):
        def loop(y):
            return jax.lax.fori_loop(
                0,
                LOOP_STEPS,
                lambda i, y: jax.tree_util.tree_map(lambda a, b: a + 1e-9 * b, y, vf(0.0, y, None)),
                y,
            )

        return jax.jit(loop)

    for name, vf, y in (("simulate's", package_field, y_package), ("row-wise (7, N)", field, y_rows)):
        cost = median_time(field_loop(vf), y, opts.repeats) / (LOOP_STEPS * n)
        rows.append((f"vector field alone, {name}, per evaluation", cost, f"{n} bodies"))

    def step_loop(solver, vf):
        term = diffrax.ODETerm(vf)

        def loop(y):
            def body(i, carry):
                y, state = carry
                y1, error, dense, state, _ = solver.step(term, 0.0, 1e-4, y, None, state, jnp.array(False))
                keep = jax.tree_util.tree_map(lambda a, e, k: a + 1e-30 * (e + k[-1]), y1, error, dense["k"])
                return keep, state

            return jax.lax.fori_loop(0, LOOP_STEPS, body, (y, solver.init(term, 0.0, 1e-4, y, None)))[0]

        return jax.jit(loop)

    for name, solver, vf, y in (
        ("diffrax Dopri8.step, simulate's field", diffrax.Dopri8(), package_field, y_package),
        ("unrolled Dopri8 step, simulate's field and state", UnrolledDopri8(), package_field, y_package),
        ("unrolled Dopri8 step, row-wise (7, N)", UnrolledDopri8(), field, y_rows),
    ):
        cost = median_time(step_loop(solver, vf), y, opts.repeats) / (LOOP_STEPS * n)
        rows.append((f"one step in a loop: {name}", cost, f"{n} bodies"))

    for name, saveat in (
        ("end point only", diffrax.SaveAt(t1=True)),
        ("two sample times", diffrax.SaveAt(ts=ts)),
    ):

        def solve(y, saveat=saveat):
            solution = diffrax.diffeqsolve(
                diffrax.ODETerm(field), UnrolledDopri8(), 0.0, T_END, 1e-3, y, saveat=saveat,
                stepsize_controller=diffrax.PIDController(rtol=RTOL, atol=RTOL, norm=max_norm),
                max_steps=100_000, throw=False,
            )  # fmt: skip
            return solution.ys, solution.stats["num_steps"]

        solve = jax.jit(solve)
        taken = int(solve(y_rows)[1])
        cost = median_time(lambda y, solve=solve: solve(y)[0], y_rows, opts.repeats) / (taken * n)
        rows.append(
            (f"diffeqsolve, unrolled step, row-wise (7, N), {name}", cost, f"{n} bodies, {taken} steps")
        )

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
