"""``rigidjax bench``: time and error of each ``accuracy`` setting of :func:`rigidjax.simulate`.

Scene: N torque-free bodies spun near their intermediate axis, so that they flip (the tennis-racket
effect): principal moments ``(1, 2, 2.5) (1 + 0.05 u)``, ``u ~ U(-1, 1)^3``, then
``omega0 = (0.05, 4, 0.05) + 0.01 n`` rad/s, ``n ~ N(0, 1)^3``, both from
``numpy.random.default_rng(seed)``; identity orientation; ``T = 20`` s. It is the scene of
``benchmarks/work_precision.py`` in the source tree, which also runs hand-written RK4, the vmapped
diffrax solve a user would write, scipy and MuJoCo against an extended-precision reference.

Each setting (the presets and the closed form, ``accuracy="exact"``) is called once (trace, compile
and run), then ``--repeats`` more times, round-robin over the settings, each call ended by
``block_until_ready``: the run time is the median of the repeats, the compile time the first call
minus that median. Errors at ``t = T`` against the float64 closed form, over the bodies: relative
omega error ``|omega - omega_ref| / |omega_ref|`` and orientation error angle (rad).
"""

from __future__ import annotations

import json
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import rigidjax as rj

from .common import (
    DocstringHelpFormatter,
    StatusLine,
    UsageError,
    bar,
    check_output,
    plain,
    positive_float,
    positive_int,
    rng_seed,
    solver_text,
    write_or_rescue,
    write_text,
)

METHODS = ("fast", "balanced", "precise", "exact")


def tennis_racket_scene(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Inertia (N, 3) and omega0 (N, 3) rad/s of the benchmark's bodies, float64 NumPy."""
    rng = np.random.default_rng(seed)
    inertia = np.array([1.0, 2.0, 2.5]) * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, size=(n, 3)))
    omega0 = np.array([0.05, 4.0, 0.05]) + 0.01 * rng.standard_normal(size=(n, 3))
    return inertia, omega0


def _final_state(accuracy: str, inertia, omega0, duration: float):
    """A zero-argument call: ``rigidjax.simulate`` of every body over [0, T]; (omega(T), q(T), steps)."""
    dtype = inertia.dtype
    # A batch axis of one per body: three bodies' moments, a (3, 3) array, would read as one tensor.
    inertia, omega0 = inertia[:, None], omega0[:, None]
    q0 = jnp.zeros(omega0.shape[:-1] + (4,), dtype).at[..., 0].set(1.0)
    ts = jnp.asarray([0.0, duration], dtype)
    model, state0 = rj.FreeBody(inertia), rj.State(omega0, q0)

    def call():
        traj = rj.simulate(model, state0, ts, accuracy=accuracy)
        return traj.omega[:, 0, -1], traj.orientation[:, 0, -1], traj.stats.get("num_steps")

    return call


def _timed(fn):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t0


def _errors(omega, q, omega_ref, q_ref) -> dict[str, float]:
    """Max and median over bodies of the relative omega error and the orientation error angle."""
    omega, q = (np.asarray(x, np.float64) for x in (omega, q))
    rel = np.linalg.norm(omega - omega_ref, axis=-1) / np.linalg.norm(omega_ref, axis=-1)
    d = np.asarray(rj.quat_multiply(rj.quat_conjugate(jnp.asarray(q_ref)), jnp.asarray(q)))
    angle = 2.0 * np.arctan2(np.linalg.norm(d[:, 1:], axis=-1), np.abs(d[:, 0]))
    errors = {}
    for name, values in (("rel_omega", rel), ("angle", angle)):
        values = np.where(np.isfinite(values), values, np.inf)
        errors[f"max_{name}"], errors[f"median_{name}"] = float(np.max(values)), float(np.median(values))
    return errors


def _fmt(x, spec: str = ".1e") -> str:
    return "-" if x is None else format(x, spec)


def format_table(rows, reference_row: str | None) -> str:
    """A markdown table, one row per setting; the setting the errors are measured against says so."""
    columns = ("accuracy", "solver", "run s", "compile s", "steps", "max rel ω err", "median rel ω err")
    lines = ["| " + " | ".join(columns + ("max angle err rad",)) + " |", "|" + " --- |" * 8]
    for r in rows:
        if r["accuracy"] == reference_row:
            errors = "(reference) | (reference) | (reference)"
        else:
            errors = f"{_fmt(r['max_rel_omega'])} | {_fmt(r['median_rel_omega'])} | {_fmt(r['max_angle'])}"
        lines.append(
            f"| {r['accuracy']} | {r['solver']} | {r['run_s']:.3g} | {r['compile_s']:.1f} | "
            f"{_fmt(r['steps'], ',d')} | {errors} |"
        )
    return "\n".join(lines)


def run(args) -> int:
    """The ``bench`` command: every selected setting, timed, against the float64 closed form."""
    if not jax.config.read("jax_enable_x64"):
        jax.config.update("jax_enable_x64", True)  # the reference is float64
    methods = [k.strip() for k in args.methods.split(",") if k.strip()]
    bad = sorted(set(methods) - set(METHODS))
    if bad or not methods:
        given = f"unknown --methods {', '.join(bad)}" if bad else "--methods names no method"
        raise UsageError(f"{given}; choose from {','.join(METHODS)}")
    methods = list(dict.fromkeys(methods))
    if args.json:
        check_output(args.json, "--json", (".json",))  # before the run, so a typo cannot cost it
    inertia, omega0 = tennis_racket_scene(args.bodies, args.seed)
    dtype = jnp.dtype(args.dtype)
    calls = {
        m: _final_state(m, jnp.asarray(inertia, dtype), jnp.asarray(omega0, dtype), args.duration)
        for m in methods
    }
    shares_reference = args.dtype == "float64" and "exact" in methods
    total = len(methods) * (1 + args.repeats) + (0 if shares_reference else 1)
    status, t_start, done = StatusLine(sys.stderr, not args.quiet), time.perf_counter(), 0

    def step(what: str) -> None:
        nonlocal done
        status.show(
            f"bench [{bar(done, total)}] {done}/{total} calls, {time.perf_counter() - t_start:.0f} s  {what}",
            last=done == total,
        )
        done += 1

    firsts, outputs = {}, {}
    if not shares_reference:
        step("reference: float64 closed form")
        (omega_ref, q_ref, _), _ = _timed(
            _final_state("exact", jnp.asarray(inertia), jnp.asarray(omega0), args.duration)
        )
    for m in methods:
        step(f"first call {m}")
        outputs[m], firsts[m] = _timed(calls[m])
    if shares_reference:
        omega_ref, q_ref, _ = outputs["exact"]
    omega_ref, q_ref = np.asarray(omega_ref), np.asarray(q_ref)
    times = {m: [] for m in methods}
    for _ in range(args.repeats):
        for m in methods:
            step(f"timing {m}")
            times[m].append(_timed(calls[m])[1])
    step("done")

    rows = []
    for m in methods:
        omega, q, steps = outputs[m]
        run_s = statistics.median(times[m]) if times[m] else firsts[m]
        rows.append(
            {
                "accuracy": m,
                "solver": solver_text(m, args.bodies, dtype),
                "dtype": str(np.asarray(omega).dtype),
                "run_s": run_s,
                "runs_s": times[m],
                "first_call_s": firsts[m],
                "compile_s": max(firsts[m] - run_s, 0.0),
                "steps": None if m == "exact" or steps is None else int(np.max(np.asarray(steps))),
                **_errors(omega, q, omega_ref, q_ref),
            }
        )
    reference_row = "exact" if shares_reference else None
    device = jax.devices()[0]
    print(
        f"rigidjax {rj.__version__} bench: {args.bodies:,} torque-free bodies near the intermediate axis, "
        f"T = {args.duration:g} s, {args.dtype}, {device.platform} ({jax.device_count()} device(s)). "
        f"Run time: median of {args.repeats} calls, compile apart. Errors at t = T against the float64 "
        'closed form (accuracy="exact").'
    )
    print()
    print(format_table(rows, reference_row))
    print()
    print("The full comparison with other integrators: benchmarks/work_precision.py in the source tree.")
    if args.json:
        meta = {k: getattr(args, k) for k in ("bodies", "duration", "dtype", "seed", "repeats")}
        text = json.dumps({**meta, "devices": [str(d) for d in jax.devices()], "rows": rows}, indent=1)
        if write_or_rescue("bench", "--json", args.json, lambda path: write_text(path, text)) != args.json:
            return 1
    return 0


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "bench",
        help="time and error of each accuracy setting of rigidjax.simulate on tennis-racket bodies",
        description=plain(__doc__),
        formatter_class=DocstringHelpFormatter,
    )
    p.add_argument("-n", "--bodies", type=positive_int, default=300, help="number of bodies")
    p.add_argument("--duration", type=positive_float, default=20.0, help="T in seconds")
    p.add_argument(
        "--methods",
        default=",".join(METHODS),
        help=f"comma-separated accuracy settings out of {','.join(METHODS)} (default: all)",
    )
    p.add_argument("--repeats", type=positive_int, default=3, help="timed calls per setting after the first")
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64", help="simulation dtype")
    p.add_argument("--seed", type=rng_seed, default=0, help="seed of numpy.random.default_rng for the scene")
    p.add_argument(
        "--json", default=None, help="also write the rows to this .json file (checked before the run)"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=run)
