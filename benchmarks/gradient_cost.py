"""Gradient cost: reverse and forward mode through ``simulate`` relative to the forward simulation.

The tennis-racket scene (``_harness.reference_scene``: N bodies near the intermediate axis, T = 20 s,
float64).
Per method (``accuracy`` preset or closed form), each timed as the median of ``--repeats`` calls
after a first call (compile = first call - median), ``block_until_ready`` on each:

- ``forward``: ``simulate`` alone, omega(T) and q(T) of every body;
- ``grad (reverse)``: ``jax.grad`` of the scalar ``sum(a . omega(T) + b . q(T))`` (fixed random
  weights a, b) with respect to all N inertias and initial omegas (6N parameters, one backward pass;
  diffrax's ``RecursiveCheckpointAdjoint``, the default);
- ``jvp (forward)``: one directional derivative of (omega(T), q(T)) along a random direction of the
  6N parameters (``adjoint=diffrax.ForwardMode()``);
- ``jacobian fwd (6 jvps)``: every body's full 7 x 6 Jacobian d(omega(T), q(T)) / d(I, omega0) as 6
  batched JVPs (bodies are independent, so the k-th basis tangent for all bodies at once gives column
  k of every body's Jacobian);
- ``jacobian rev (7 vjps)``: the same Jacobians as 7 batched VJPs.

Checks printed and stored: reverse gradient against forward JVP (<grad, v> = jvp . weights) and every
integrator's Jacobian against the closed form's, relative to the Jacobian's size, max over bodies.

Usage:
    python benchmarks/gradient_cost.py                # N = 1e4 (~4 min on 2 cores)
    python benchmarks/gradient_cost.py --n 1000 --repeats 3
Writes benchmarks/results/gradient_cost.json (``--out`` to change).
"""

from __future__ import annotations

import argparse
import functools
import json
import os

import jax

jax.config.update("jax_enable_x64", True)

import _harness as B  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rigidjax as rj  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def programs(accuracy, q0, ts):
    """The five jitted programs of one accuracy setting."""

    def final(inertia, omega0, adjoint=None):
        kwargs = {} if adjoint is None else {"adjoint": adjoint}
        traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega0, q0), ts, accuracy=accuracy, **kwargs)
        return jnp.concatenate([traj.omega[:, -1], traj.orientation[:, -1]], axis=-1)  # (N, 7)

    forward_mode = None if accuracy == "exact" else diffrax.ForwardMode()

    @jax.jit
    def forward(inertia, omega0):
        return final(inertia, omega0)

    @jax.jit
    def grad(inertia, omega0, weights):
        return jax.grad(lambda i, w: jnp.sum(weights * final(i, w)), argnums=(0, 1))(inertia, omega0)

    @jax.jit
    def jvp(inertia, omega0, d_inertia, d_omega0):
        return jax.jvp(lambda i, w: final(i, w, forward_mode), (inertia, omega0), (d_inertia, d_omega0))[1]

    @jax.jit
    def jac_fwd(inertia, omega0):
        n = inertia.shape[0]
        basis = jnp.broadcast_to(jnp.eye(6, dtype=inertia.dtype)[:, None, :], (6, n, 6))

        def column(e):
            return jax.jvp(lambda i, w: final(i, w, forward_mode), (inertia, omega0), (e[:, :3], e[:, 3:]))[1]

        return jnp.moveaxis(jax.vmap(column)(basis), 0, -1)  # (N, 7, 6)

    @jax.jit
    def jac_rev(inertia, omega0):
        out, pullback = jax.vjp(final, inertia, omega0)
        basis = jnp.broadcast_to(jnp.eye(7, dtype=out.dtype)[:, None, :], (7,) + out.shape)
        d_i, d_w = jax.vmap(pullback)(basis)
        return jnp.moveaxis(jnp.concatenate([d_i, d_w], axis=-1), 0, 1)  # (N, 7, 6)

    return forward, grad, jvp, jac_fwd, jac_rev


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=B.positive_int, default=10_000)
    p.add_argument("--repeats", type=B.positive_int, default=3)
    p.add_argument(
        "--accuracies",
        type=B.names_from(("exact", "fast", "balanced", "precise")),
        default=["exact", "fast", "balanced", "precise"],
    )
    p.add_argument("--out", default=os.path.join(HERE, "results", "gradient_cost.json"))
    a = p.parse_args(argv)

    inertia_np, omega0_np, q0_np = B.reference_scene(a.n)
    inertia, omega0, q0 = (jnp.asarray(x) for x in (inertia_np, omega0_np, q0_np))
    ts = jnp.asarray([0.0, B.T_END])
    rng = np.random.default_rng(7)
    weights = jnp.asarray(rng.standard_normal((a.n, 7)))
    d_inertia = jnp.asarray(rng.standard_normal((a.n, 3)) * 0.01)
    d_omega0 = jnp.asarray(rng.standard_normal((a.n, 3)) * 0.01)
    meta = B.run_meta(
        "benchmarks/gradient_cost.py", argv, n=a.n, repeats=a.repeats, T=B.T_END, diffrax=diffrax.__version__
    )
    print(f"N={a.n}, T={B.T_END} s, {meta['devices']}, load {meta['loadavg_start']}", flush=True)
    rows, jacobians = [], {}
    for accuracy in a.accuracies:
        forward, grad, jvp, jac_fwd, jac_rev = programs(accuracy, q0, ts)
        _, t_fwd = B.timed_calls(functools.partial(forward, inertia, omega0), a.repeats)
        (g_i, g_w), t_grad = B.timed_calls(functools.partial(grad, inertia, omega0, weights), a.repeats)
        tangent, t_jvp = B.timed_calls(
            functools.partial(jvp, inertia, omega0, d_inertia, d_omega0), a.repeats
        )
        jf, t_jf = B.timed_calls(functools.partial(jac_fwd, inertia, omega0), a.repeats)
        jr, t_jr = B.timed_calls(functools.partial(jac_rev, inertia, omega0), a.repeats)
        jacobians[accuracy] = np.asarray(jf)
        # <grad, v> against the JVP contracted with the weights: reverse vs forward mode.
        lhs = float(jnp.sum(g_i * d_inertia) + jnp.sum(g_w * d_omega0))
        rhs = float(jnp.sum(weights * tangent))
        scale = np.max(np.abs(np.asarray(jf)), axis=(1, 2))
        fwd_vs_rev = float(np.max(np.max(np.abs(np.asarray(jf) - np.asarray(jr)), axis=(1, 2)) / scale))
        row = dict(
            accuracy=accuracy,
            forward=t_fwd,
            grad_reverse=t_grad,
            jvp_forward=t_jvp,
            jacobian_forward_6jvp=t_jf,
            jacobian_reverse_7vjp=t_jr,
            ratio_grad_reverse=t_grad["run_s"] / t_fwd["run_s"],
            ratio_jvp_forward=t_jvp["run_s"] / t_fwd["run_s"],
            ratio_jacobian_forward=t_jf["run_s"] / t_fwd["run_s"],
            ratio_jacobian_reverse=t_jr["run_s"] / t_fwd["run_s"],
            check_grad_dot_v_vs_jvp=abs(lhs - rhs) / max(abs(lhs), abs(rhs)),
            check_jacobian_fwd_vs_rev_max_rel=fwd_vs_rev,
            jacobian_size_median=float(np.median(scale)),
            jacobian_size_max=float(np.max(scale)),
            finite=bool(np.all(np.isfinite(np.asarray(jf))) and np.all(np.isfinite(np.asarray(g_i)))),
        )
        rows.append(row)
        print(
            f"{accuracy:9s} forward {t_fwd['run_s']:.3g} s (compile {t_fwd['compile_s']:.1f}) | grad rev "
            f"{t_grad['run_s']:.3g} s = {row['ratio_grad_reverse']:.2f}x "
            f"(compile {t_grad['compile_s']:.1f}) | "
            f"jvp {t_jvp['run_s']:.3g} s = {row['ratio_jvp_forward']:.2f}x | jacobian 6 jvp "
            f"{t_jf['run_s']:.3g} s = {row['ratio_jacobian_forward']:.2f}x | 7 vjp {t_jr['run_s']:.3g} s = "
            f"{row['ratio_jacobian_reverse']:.2f}x | <g,v> vs jvp {row['check_grad_dot_v_vs_jvp']:.1e}, "
            f"jac fwd vs rev {fwd_vs_rev:.1e}",
            flush=True,
        )
    if "exact" in jacobians:
        ref = jacobians["exact"]
        scale = np.max(np.abs(ref), axis=(1, 2))
        for row in rows:
            rel = np.max(np.abs(jacobians[row["accuracy"]] - ref), axis=(1, 2)) / scale
            row["jacobian_vs_closed_form_max_rel"] = float(np.max(rel))
            row["jacobian_vs_closed_form_median_rel"] = float(np.median(rel))
            print(
                f"{row['accuracy']:9s} Jacobian vs the closed form's: "
                f"max {np.max(rel):.1e}, median {np.median(rel):.1e}"
            )
    meta["loadavg_end"] = os.getloadavg()
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    with open(a.out, "w") as fh:
        json.dump(dict(meta=meta, rows=rows), fh, indent=1)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
