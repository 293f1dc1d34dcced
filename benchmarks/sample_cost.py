"""How the number of sample times changes ``simulate``'s lead over the user-written vmapped Tsit5.

Scene: the tennis-racket bodies of ``work_precision.py`` (``_harness.reference_scene``), float64,
T = 20 s, sampled at K evenly spaced times (K = 2, 101 and 801 by default). Methods:
``simulate`` with ``"balanced"``, ``"precise"`` and ``"exact"``, and what a user writes:
``jax.jit(jax.vmap(diffeqsolve(Tsit5(), PIDController(rtol, atol=rtol), saveat=SaveAt(ts=ts))))``
at rtol 1e-8 (the peer's setting that reaches ω errors below 1e-6 in ``work_precision.py``).

Errors: the largest relative ω error over every body and every sample, and the largest angle
between orientations, against the float64 closed form (``"exact"``, which ``work_precision.py``
checks against an 80-bit Taylor-series reference). Times: compile excluded (first call reported
apart), ``block_until_ready``, the methods called in turn for ``--rounds`` rounds, the median.

Usage:
    python benchmarks/sample_cost.py                       # ~5 min on 2 cores
    python benchmarks/sample_cost.py --n 2000 --samples 2,801
Writes benchmarks/results/sample_cost.json and .md (``--out`` for another stem).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _harness import T_END, _call, peer_program, quat_angle, reference_scene, run_meta  # noqa: E402

import rigidjax as rj  # noqa: E402

PEER_RTOL = 1e-8
PRESETS = ("exact", "balanced", "precise")  # "exact" first: the others' reference


def methods_at(scene, ts):
    """Name -> zero-argument function returning ``(omega, q)``, each ``(N, K, ·)``."""
    inertia, omega0, q0 = (jnp.asarray(x) for x in scene)
    model, state0 = rj.FreeBody(inertia), rj.State(omega0, q0)

    def preset(accuracy):
        def run():
            traj = rj.simulate(model, state0, ts, accuracy=accuracy)
            return traj.omega, traj.orientation

        return run

    solve = peer_program(ts)
    y0 = jnp.concatenate([omega0, q0], axis=-1)
    rtol = jnp.asarray(PEER_RTOL)

    def peer():
        ys = solve(inertia, y0, rtol, rtol)
        return ys[..., :3], ys[..., 3:]

    methods = {f"simulate {accuracy!r}": preset(accuracy) for accuracy in PRESETS}
    methods[f"vmapped Tsit5, rtol {PEER_RTOL:g}"] = peer
    return methods


def errors(out, reference):
    """Largest relative ω error and largest angle (rad) over every body and sample."""
    omega, q = (np.asarray(x) for x in out)
    omega_ref, q_ref = reference
    rel = np.linalg.norm(omega - omega_ref, axis=-1) / np.linalg.norm(omega_ref, axis=-1)
    return float(np.max(rel)), float(np.max(quat_angle(q, q_ref)))


def measure(scene, n_samples: int, rounds: int) -> list[dict]:
    ts = jnp.linspace(0.0, T_END, n_samples)
    methods = methods_at(scene, ts)
    rows = {}
    reference = None
    for name, fn in methods.items():
        out, first = _call(fn)
        if name == "simulate 'exact'":
            reference = tuple(np.asarray(x) for x in out)
        rel, angle = errors(out, reference)
        rows[name] = {"method": name, "samples": n_samples, "first_call_s": first, "runs_s": []}
        rows[name].update(max_rel_omega=rel, max_angle=angle)
        del out
    for _ in range(rounds):
        for name, fn in methods.items():
            rows[name]["runs_s"].append(_call(fn)[1])
    peer = f"vmapped Tsit5, rtol {PEER_RTOL:g}"
    for row in rows.values():
        row["run_s"] = float(np.median(row["runs_s"]))
        row["compile_s"] = max(row["first_call_s"] - row["run_s"], 0.0)
    for row in rows.values():
        row["lead_over_peer"] = rows[peer]["run_s"] / row["run_s"]
    return list(rows.values())


def table(rows, n_bodies) -> str:
    lines = [
        "| samples | method | run s | per body-sample (ns) | max rel ω (all samples) | max angle (rad) "
        "| peer's time / this |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        per_sample = 1e9 * r["run_s"] / (n_bodies * r["samples"])
        is_reference = r["method"] == "simulate 'exact'"
        rel, angle = (
            ("(reference)",) * 2 if is_reference else (f"{r['max_rel_omega']:.1e}", f"{r['max_angle']:.1e}")
        )
        lines.append(
            f"| {r['samples']} | {r['method']} | {r['run_s']:.4g} | {per_sample:.0f} | {rel} | {angle} | "
            f"{r['lead_over_peer']:.1f}× |"
        )
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=10_000, help="bodies")
    parser.add_argument("--samples", default="2,101,801", help="comma-separated numbers of sample times")
    parser.add_argument("--rounds", type=int, default=3, help="timed rounds (each method once per round)")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "sample_cost"))
    opts = parser.parse_args(argv)
    sample_counts = [int(k) for k in opts.samples.split(",")]
    if any(k < 2 for k in sample_counts):
        parser.error("--samples: each number of sample times must be at least 2 (the ends)")
    scene = reference_scene(opts.n)
    meta = run_meta("benchmarks/sample_cost.py", argv, n=opts.n, T=T_END, rounds=opts.rounds)
    rows = []
    for k in sample_counts:
        rows += measure(scene, k, opts.rounds)
        print(table([r for r in rows if r["samples"] == k], opts.n), flush=True)
    meta["loadavg_end"] = list(os.getloadavg())
    out = Path(opts.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    header = (
        f"Sample cost, tennis-racket scene, {opts.n} bodies, T = {T_END:g} s, float64, "
        f"{meta['devices'][0]}, jax {meta['jax']} (`{meta['command']}`)\n\n"
    )
    out.with_suffix(".md").write_text(header + table(rows, opts.n) + "\n")
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
