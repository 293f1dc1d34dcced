"""Batch size and chunk size on one device, and the closed form against the device's memory bandwidth.

Written for a GPU (where a step of 10^4 bodies costs about what a step of one body does, so the
number of kernel launches sets the time), and runs anywhere: on a CPU with ``--quick`` for a check.

Section ``sizes``: the tennis-racket scene of ``_harness.py`` (N torque-free bodies, T = 20 s,
float64) for every N in ``--sizes``, side by side in one process with interleaved rounds
(``_harness.run_methods``): ``simulate`` "balanced" with its default chunk size and with each of
``--chunks`` (those below N, and N itself: one chunk), "fast", the closed form, and the user-written
``jax.jit(jax.vmap(diffeqsolve(Tsit5(), PIDController)))`` at rtol 1e-7 and 1e-8 (the first reaches
about 1e-6, the accuracy "balanced" promises; the peer's time at 1e-6 is interpolated between
them, log-log, as in ``work_precision.py``). Errors at t = T against the float64 closed form
(relative omega, max over bodies). The device's peak memory (``memory_stats``, where the device
reports it) after each size.

Section ``bandwidth``: the closed form (``accuracy="exact"``) for ``--bw-bodies`` bodies at
``--bw-samples`` sample times, omega + orientation and omega only, float64 and float32, against a
program that only writes an array of the same size as the closed form's output (``jnp.full``): the
time the device needs to store the result at all. Ratio = closed form / that floor.

Usage:
    python benchmarks/accelerator.py                       # N = 1e4, 1e5, 1e6 (for a GPU)
    python benchmarks/accelerator.py --quick --out /tmp/accelerator_cpu.json
Writes PREFIX.json and PREFIX.md (``--out``, default benchmarks/results/accelerator.json).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import rigidjax as rj  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _harness as B  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "results", "accelerator.json")


def _peak_device_bytes():
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def size_section(n: int, chunks, repeats: int, log) -> dict:
    scene = B.reference_scene(n)
    t0 = time.perf_counter()
    omega_ref, q_ref, first = B.closed_form_reference(scene)
    log(f"  N={n}: reference {time.perf_counter() - t0:.1f} s")
    methods = [
        B.simulate_method(scene, "simulate 'balanced'", "default chunk", "balanced", accuracy="balanced")
    ]
    for c in sorted({c for c in chunks if c < n} | {n}):
        methods.append(
            B.simulate_method(
                scene,
                "simulate 'balanced'",
                f"chunk_size={c}",
                f"balanced-{c}",
                accuracy="balanced",
                chunk_size=c,
            )
        )
    methods.append(B.simulate_method(scene, "simulate 'fast'", "default chunk", "fast", accuracy="fast"))
    methods.append(B.simulate_method(scene, "simulate 'exact' (closed form)", "-", "exact", accuracy="exact"))
    methods += [B.vmap_diffrax_method(scene, r) for r in (1e-7, 1e-8)]
    rows = B.run_methods(
        methods,
        scene,
        (omega_ref, q_ref),
        repeats=repeats,
        progress=lambda what, k, total: log(f"  N={n} [{k}/{total}] {what}"),
        first_calls={"exact": first},
    )
    for r in rows:
        r["n"] = n
    return {"n": n, "rows": rows, "peak_device_bytes": _peak_device_bytes()}


def _median_time(fn, repeats):
    jax.block_until_ready(fn())  # compile
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    return statistics.median(runs)


def bandwidth_section(n: int, n_samples: int, repeats: int, log, blocks=()) -> list[dict]:
    inertia, omega0, q0 = B.reference_scene(n)
    rows = []
    cases = [(jnp.float64, True, None), (jnp.float64, False, None), (jnp.float32, True, None)]
    cases += [(jnp.float32, False, None)] + [(jnp.float64, True, b) for b in blocks]
    for dtype, with_q, block in cases:
        model = rj.FreeBody(jnp.asarray(inertia, dtype))
        ts = jnp.linspace(0.0, B.T_END, n_samples, dtype=dtype)
        state = rj.State(jnp.asarray(omega0, dtype), jnp.asarray(q0, dtype) if with_q else None)

        def closed_form(model=model, state=state, ts=ts, block=block):
            traj = rj.simulate(model, state, ts, accuracy="exact", chunk_size=block)
            return traj.omega, traj.orientation

        components = 7 if with_q else 3
        out_bytes = n * n_samples * components * jnp.dtype(dtype).itemsize
        fill = jax.jit(lambda s, shape=(n, n_samples, components), dtype=dtype: jnp.full(shape, s, dtype))
        scalar = jnp.asarray(1.0, dtype)
        t_cf = _median_time(closed_form, repeats)
        t_fill = _median_time(lambda fill=fill, scalar=scalar: fill(scalar), repeats)
        row = {
            "dtype": jnp.dtype(dtype).name,
            "outputs": "omega + orientation" if with_q else "omega only",
            "bodies_per_block": block,
            "n_bodies": n,
            "n_samples": n_samples,
            "output_bytes": int(out_bytes),
            "closed_form_s": t_cf,
            "write_floor_s": t_fill,
            "ratio_to_floor": t_cf / t_fill,
            "closed_form_GB_per_s": out_bytes / t_cf / 1e9,
            "write_floor_GB_per_s": out_bytes / t_fill / 1e9,
            "body_samples_per_s": n * n_samples / t_cf,
        }
        log(
            f"  {row['dtype']} {row['outputs']} blocks of {block}: closed form {t_cf * 1e3:.3g} ms, "
            f"write floor {t_fill * 1e3:.3g} ms ({row['ratio_to_floor']:.2f}x)"
        )
        rows.append(row)
    return rows


def _fmt_s(x):
    return f"{x:.3g}" if x is not None else "-"


def to_markdown(result: dict) -> str:
    meta = result["meta"]
    lines = [
        f"Batch and chunk size on {', '.join(meta['devices'])}, jax {meta['jax']} (`{meta['command']}`)",
        "",
    ]
    for section in result.get("sizes", []):
        n = section["n"]
        peak = section["peak_device_bytes"]
        lines += [
            f"N = {n} tennis-racket bodies, T = 20 s, float64"
            + (f"; device peak memory so far {peak / 2**30:.2f} GiB" if peak else ""),
            "",
            "| method | setting | run s (median) | compile s | max rel omega err "
            "| vs vmapped Tsit5 at <= 1e-6 |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        peer_rows = [r for r in section["rows"] if r["family"].startswith("vmap")]
        peer, _ = B.time_at_error(peer_rows, 1e-6)

        def ratio(r, peer=peer):
            if r["integrator"] and r["max_rel_omega"] > 1e-6:
                return "- (error over 1e-6)"
            return f"{peer / r['run_s']:.2f}x"

        for r in section["rows"]:
            error = "reference" if not r["integrator"] else f"{r['max_rel_omega']:.1e}"
            lines.append(
                f"| {r['family']} | {r['setting']} | {r['run_s']:.3g} | {_fmt_s(r['compile_s'])} | "
                f"{error} | {ratio(r)} |"
            )
        lines.append("")
    if result.get("bandwidth"):
        lines += [
            "Closed form against the time to write its output (`jnp.full` of the same shape)",
            "",
            "| dtype | outputs | bodies x samples | bodies per block | output GB | closed form ms "
            "| write floor ms | ratio | closed form GB/s |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for r in result["bandwidth"]:
            lines.append(
                f"| {r['dtype']} | {r['outputs']} | {r['n_bodies']} x {r['n_samples']} | "
                f"{r.get('bodies_per_block') or 'default'} | "
                f"{r['output_bytes'] / 1e9:.2f} | {r['closed_form_s'] * 1e3:.3g} | "
                f"{r['write_floor_s'] * 1e3:.3g} | "
                f"{r['ratio_to_floor']:.2f} | {r['closed_form_GB_per_s']:.0f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="10000,100000,1000000", help="comma-separated body counts")
    p.add_argument("--chunks", default="65536,262144", help="chunk sizes tried besides one chunk")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--bw-bodies", type=int, default=1_000_000)
    p.add_argument("--bw-samples", type=int, default=64)
    p.add_argument("--bw-blocks", default="", help="closed form in blocks of these many bodies too")
    p.add_argument("--sections", default="sizes,bandwidth")
    p.add_argument("--quick", action="store_true", help="small sizes, for a check on a CPU")
    p.add_argument("--replot", action="store_true", help="only rewrite OUT's .md from OUT")
    p.add_argument("--out", default=DEFAULT_OUT, help="writes OUT (JSON) and OUT with .md")
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.chunks, a.bw_bodies, a.bw_samples, a.repeats = "2000", "256", 2000, 8, 1
        a.bw_blocks = a.bw_blocks and "500"
    out_md = os.path.splitext(a.out)[0] + ".md"
    if a.replot:
        with open(a.out) as f, open(out_md, "w") as md:
            md.write(to_markdown(json.load(f)))
        return
    sections = set(a.sections.split(","))
    started = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - started:7.1f} s] {msg}", flush=True)

    result = {"meta": B.run_meta("benchmarks/accelerator.py", argv, backend=jax.default_backend())}

    def save():
        with open(a.out, "w") as f:
            json.dump(result, f, indent=1)
        with open(out_md, "w") as f:
            f.write(to_markdown(result))

    if "sizes" in sections:
        result["sizes"] = []
        chunks = [int(c) for c in a.chunks.split(",") if c]
        for n in (int(s) for s in a.sizes.split(",")):
            result["sizes"].append(size_section(n, chunks, a.repeats, log))
            save()
    if "bandwidth" in sections:
        log(f"bandwidth: {a.bw_bodies} bodies x {a.bw_samples} samples")
        blocks = [int(b) for b in a.bw_blocks.split(",") if b]
        result["bandwidth"] = bandwidth_section(a.bw_bodies, a.bw_samples, a.repeats, log, blocks)
    result["meta"]["total_s"] = time.perf_counter() - started
    save()
    print(to_markdown(result))


if __name__ == "__main__":
    main()
