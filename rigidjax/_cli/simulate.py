"""``rigidjax simulate``: batch-simulate a scene of many bodies (the scenes: ``scenes.py``).

With no options it integrates 10,000 heavy tops (random but reproducible inertia, spin and tilt;
``--seed``) for 5 s, prints a summary, and writes the trajectories to ``rigidjax_simulate.npz`` and a
figure to ``rigidjax_simulate.png``. Other scenes: ``--scene free`` (torque-free asymmetric bodies, a
third of them spun near the unstable intermediate axis: the tennis-racket flip) and ``--scene earth``
(the rigid Earth as a symmetric top in SI units; its free wobble, the Euler period of about 300 days,
against the closed form).

The batch runs in blocks of identical shape, so :func:`rigidjax.simulate` compiles once
(``batch.py``); a first call on block 0 over a milliradian of the fastest body's rotation (same
shapes, so the same compiled program, but almost no integration) is reported as the compile time.

The ``.npz`` file (all arrays are NumPy, readable with ``numpy.load`` and no pickle):

- ``ts`` (T_saved,): the stored sample times (s), every ``save_every``-th output sample and the
  last;
- ``omega`` (N, T_saved, 3): body-frame angular velocity (rad/s);
- ``orientation`` (N, T_saved, 4) and ``euler_angles`` (N, T_saved, 3) (``zxz``: precession phi,
  nutation theta, spin psi, unwrapped in time) for scenes with an orientation (not ``earth``,
  where only Euler's equations are integrated);
- the model parameters and initial state (``inertia`` (N, 3), ``omega0`` (N, 3), and per scene
  ``mass``, ``com``, ``gravity``, ``euler0``, ``orientation0``), per-body results (``drift_<name>``
  for each invariant of :meth:`rigidjax.Trajectory.invariants`, ``success``, the error estimate
  ``error_estimate_omega`` and ``error_estimate_orientation`` of
  :meth:`rigidjax.Trajectory.error_estimate` unless ``--no-error-estimate``, and the scene's own,
  e.g. ``theta_max``), and ``summary_json`` (the printed summary as JSON, the worst body's error
  estimate and its index included).

Samples are stored as float32 by default (``--save-dtype``) and, by default, thinned in time to the
smallest stride that keeps the stored trajectories under 32 MiB (``--save-every``); all analysis
(invariants, maxima, periods) uses every sample at the simulation dtype before thinning.

Ctrl-C ends the run with exit status 130 and leaves no file half-written; the bodies of the blocks
finished before it are kept in ``<out>.partial.npz`` (the same arrays for those bodies, their
indices in the scene in ``body``, and ``blocks_done`` of ``blocks``).
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import rigidjax as rj

from .batch import Batch, Interrupted, Plan, done_bodies, plan_run, run_block, simulate_blocks
from .common import (
    FIGURE_EXTENSIONS,
    DefaultsHelpFormatter,
    UsageError,
    check_output,
    counted,
    file_size,
    finite_or_none,
    info,
    positive_float,
    positive_int,
    rng_seed,
    solver_text,
    write_figure,
    write_npz,
    write_or_rescue,
)
from .scenes import DAY, SCENE_BUILDERS, block_params

SCENES = tuple(SCENE_BUILDERS)
ACCURACIES = ("fast", "balanced", "precise", "exact")
DEFAULT_OUT = "rigidjax_simulate.npz"
DEFAULT_PLOT = "rigidjax_simulate.png"
ANIMATION_EXTENSIONS = (".gif", ".mp4")
ANIMATED_BODIES = 3  # --animate draws the first bodies of the scene


def _summary(plan: Plan, batch: Batch, args, compile_time: float) -> tuple[dict, list]:
    """The run's numbers (printed, and stored as ``summary_json``) and the scene's summary rows."""
    drifts = {k[len("drift_") :]: v for k, v in batch.results.items() if k.startswith("drift_")}
    success = batch.results["success"]
    # Over the bodies that integrated (failed ones are NaN and counted apart); a NaN drift stays NaN.
    worst = {k: float(np.max(v[success])) if success.any() else float("nan") for k, v in drifts.items()}
    if success.any():
        scene_rows, scene_extra = plan.scene.summarize(batch.results, plan.ts, args)
    else:
        scene_rows, scene_extra = [("scene checks", "none: no body integrated")], {}
    # The body to distrust most, per quantity: its index in the scene and its estimate.
    worst_estimate = {}
    for key, value in batch.results.items():
        if key.startswith("error_estimate_") and not np.all(np.isnan(value)):
            body = int(np.nanargmax(value))
            worst_estimate[key[len("error_estimate_") :]] = {"body": body, "estimate": float(value[body])}
    summary = {
        "scene": args.scene,
        "bodies": plan.n,
        "blocks": plan.blocks,
        "block_size": plan.block_size,
        "padding_bodies": plan.padded - plan.n,
        "dtype": args.dtype,
        "accuracy": args.accuracy,
        "duration_s": float(plan.duration),
        "samples": plan.samples,
        "seed": args.seed,
        "chunk_size": batch.chunk_size,
        "devices": jax.device_count(),
        "solver_steps": batch.steps_total,
        "body_steps": batch.body_steps,
        "wall_time_s": batch.sim_time,
        "compile_time_s": compile_time,
        "analysis_time_s": batch.loop_time - batch.sim_time,
        "body_steps_per_s": batch.body_steps / batch.sim_time if batch.sim_time > 0 else float("nan"),
        "worst_drift": worst,
        "worst_error_estimate": worst_estimate,
        "failed_bodies": int(np.sum(~success)),
        "save_every": plan.save_every,
        "save_dtype": args.save_dtype,
        **scene_extra,
    }
    return summary, scene_rows


def _per_body_worst(plan: Plan, batch: Batch) -> np.ndarray:
    drifts = [v for k, v in batch.results.items() if k.startswith("drift_")]
    return np.max(np.stack(drifts, -1), axis=-1) if drifts else np.zeros(plan.n)


def _run_settings(plan: Plan, args) -> dict[str, np.ndarray]:
    """The settings a stored run was made with."""
    return {
        "scene": np.array(args.scene),
        "dtype": np.array(args.dtype),
        "accuracy": np.array(args.accuracy),
        "seed": np.array(args.seed),
        "save_every": np.array(plan.save_every),
    }


def _write_npz(plan: Plan, batch: Batch, args, summary: dict, path: str) -> None:
    arrays = {
        "ts": plan.ts[plan.keep],
        **batch.store,
        "omega0": plan.scene.omega0,
        "success": batch.results["success"],
        "per_body_worst_drift": _per_body_worst(plan, batch),
    }
    if plan.has_q:
        arrays["orientation0"] = plan.scene.orientation0
    arrays.update(plan.scene.params)
    arrays.update({k: v for k, v in batch.results.items() if k != "success"})
    arrays.update(
        _run_settings(plan, args), summary_json=np.array(json.dumps(finite_or_none(summary), allow_nan=False))
    )
    write_npz(path, arrays)


def partial_path(out: str) -> str:
    """Where an interrupted run keeps the bodies it finished: ``<out without .npz>.partial.npz``."""
    return os.path.splitext(out)[0] + ".partial.npz"


def _second_run(args) -> str:
    """What the error estimate runs a second time (a float32 run: in float64)."""
    wider = ", in float64" if args.dtype == "float32" else ""
    if args.accuracy == "exact":
        return "second evaluation" + (wider or ", at inputs perturbed by a rounding unit")
    return "second, finer solve" + wider


def _blocks_note(plan: Plan, args) -> str:
    """Why the run has another number of blocks than ``--blocks`` asked for, or nothing."""
    if args.blocks is None or args.blocks == plan.blocks:
        return ""
    why = (
        "three bodies' principal moments would read as one inertia tensor, so blocks of 3 hold 4"
        if math.ceil(plan.n / min(args.blocks, plan.n)) == 3
        else "the blocks are equal, and more would hold only padding"
    )
    return f" (not --blocks {args.blocks}: {why})"


def _write_partial(plan: Plan, batch: Batch, blocks_done: int, args) -> None:
    """The stored samples and per-body results of the bodies of the finished blocks, with their
    indices in the scene (``body``), beside ``--out``; one line on stderr says where."""
    bodies = done_bodies(plan, blocks_done)
    arrays = {"ts": plan.ts[plan.keep], "body": bodies, "omega0": plan.scene.omega0[bodies]}
    arrays.update({key: value[bodies] for key, value in batch.store.items()})
    arrays.update({key: value[bodies] for key, value in batch.results.items()})
    if plan.has_q:
        arrays["orientation0"] = plan.scene.orientation0[bodies]
    arrays.update(block_params(plan.scene.params, bodies, plan.n))
    arrays.update(_run_settings(plan, args), blocks_done=np.array(blocks_done), blocks=np.array(plan.blocks))
    path = write_or_rescue("simulate", "--out", partial_path(args.out), lambda p: write_npz(p, arrays))
    if path is None:
        return
    print(
        f"rigidjax simulate: the {counted(len(bodies), 'body', 'bodies')} of the "
        f"{counted(blocks_done, 'finished block', 'finished blocks')} (of {plan.blocks}) are in {path} "
        "(their indices in 'body').",
        file=sys.stderr,
        flush=True,
    )


def _matplotlib_or_say_why() -> bool:
    """Whether matplotlib can be imported; says on stderr that the plot is skipped when it cannot."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        print(
            "rigidjax simulate: matplotlib is not installed; skipping the plot "
            "(pip install 'rigidjax[plot]').",
            file=sys.stderr,
        )
        return False
    return True


def _plot(plan: Plan, batch: Batch, args) -> str | None:
    """The scene's two panels and a histogram of the per-body drift; the path written (None when
    no file could be written)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    plan.scene.plot(axes, plan.ts, batch.traces, batch.results)
    per_body_worst = _per_body_worst(plan, batch)
    values = np.maximum(per_body_worst[np.isfinite(per_body_worst)], 1e-17)
    if values.size:
        lo, hi = math.floor(np.log10(values.min())), math.ceil(np.log10(values.max()))
        axes[2].hist(values, bins=np.logspace(lo, max(hi, lo + 1), 41))
    axes[2].set(
        xscale="log",
        xlabel="worst relative drift of the invariants",
        ylabel="bodies",
        title=f"Invariant drift per body ({args.dtype}, {args.accuracy})",
    )
    fig.suptitle(f"rigidjax simulate --scene {args.scene}: {plan.scene.description}", fontsize=10)
    fig.tight_layout()
    try:
        return write_or_rescue("simulate", "--plot", args.plot, lambda path: write_figure(path, fig))
    finally:
        plt.close(fig)


def _check_animate(args) -> None:
    """``--animate PATH`` checked before the run: the extension, the directory, a scene with
    orientations, matplotlib, and ffmpeg for ``.mp4``."""
    path = check_output(args.animate, "--animate", ANIMATION_EXTENSIONS)
    if args.scene == "earth":
        raise UsageError(
            "--animate needs orientations, and the earth scene integrates omega only (Euler's "
            "equations); animate --scene heavy-top or --scene free."
        )
    try:
        from matplotlib import animation
    except ImportError:
        raise UsageError(
            "--animate needs matplotlib, which is not installed: pip install 'rigidjax[plot]'."
        ) from None
    if os.path.splitext(path)[1].lower() == ".mp4" and not animation.writers.is_available("ffmpeg"):
        raise UsageError(
            f"--animate {path!r}: writing .mp4 needs ffmpeg, which was not found; give a .gif path."
        )


def _animate(plan: Plan, batch: Batch, args) -> str | None:
    """The first bodies of the scene, from the stored samples, animated to ``args.animate``."""
    import matplotlib

    matplotlib.use("Agg")
    plot = importlib.import_module("rigidjax.plot")
    count = min(ANIMATED_BODIES, plan.n)
    index = np.arange(count)
    params = block_params(plan.scene.params, index, plan.n)
    # Diagonal tensors: three bodies' principal moments, a (3, 3) array, would read as one tensor.
    params["inertia"] = np.asarray(params["inertia"])[..., None] * np.eye(3)
    trajectory = rj.Trajectory(
        ts=jnp.asarray(plan.ts[plan.keep], plan.dtype),
        omega=jnp.asarray(batch.store["omega"][:count], plan.dtype),
        orientation=jnp.asarray(batch.store["orientation"][:count], plan.dtype),
        model=plan.scene.make_model(params, plan.dtype),
        success=jnp.asarray(batch.results["success"][:count]),
        stats={},
    )
    bodies = tuple(range(count))
    return write_or_rescue(
        "simulate", "--animate", args.animate, lambda path: plot.animate(trajectory, path, bodies=bodies)
    )


def _devices_text(count: int) -> str:
    kind = jax.default_backend()
    if count == 1:
        return f"1 {kind} device"
    return f"{count} {kind} devices (each block's chunks spread over them; --cpu-devices on a CPU)"


def _drift_text(value: float, dtype: str, eps: float) -> str:
    if not np.isfinite(value):  # NaN: every body failed (the failed ones are left out of the worst)
        return "n/a (no body finished)"
    return f"{value:.3e}" if value > 0 else f"0 (below {dtype}'s resolution, {eps:.1e})"


def _print_summary(plan: Plan, batch: Batch, args, summary: dict, scene_rows, out_files, t_start) -> None:
    blocks, block_size, padded = plan.blocks, plan.block_size, plan.padded
    mean_steps = batch.steps_total / max(1, blocks * math.ceil(block_size / max(batch.chunk_size, 1)))
    duration = plan.duration
    duration_text = f"{duration:.6g} s" + (f" ({duration / DAY:.1f} days)" if duration > 10 * DAY else "")
    if args.accuracy == "exact":
        method = "exact (closed form, no integration steps)"
    else:
        method = f"{args.accuracy} ({solver_text(args.accuracy, block_size, plan.dtype)})"
    copies = padded - plan.n
    padding = f", last padded with {copies} cop{'y' if copies == 1 else 'ies'}" if copies else ""
    lines = [
        ("scene", f"{args.scene}: {plan.scene.description}"),
        ("bodies", f"{plan.n:,} ({counted(blocks, 'block', 'blocks')} of {block_size:,}{padding})"),
        ("dtype", args.dtype),
        ("accuracy", method),
        ("samples", f"{plan.samples:,} over {duration_text}"),
        ("devices", _devices_text(summary["devices"])),
        (
            "solver steps",
            f"{batch.steps_total:,} (summed over chunks of <= "
            f"{counted(batch.chunk_size, 'body', 'bodies')} sharing one step size; "
            f"mean {mean_steps:,.0f} per chunk)",
        ),
        ("body-steps", f"{batch.body_steps:,} (steps x bodies of each chunk, padding copies included)"),
        (
            "wall time",
            f"{batch.sim_time:.2f} s (all blocks, excluding compile"
            + (f"; with the error estimate's {_second_run(args)})" if args.error_estimate else ")"),
        ),
        (
            "compile time",
            f"{summary['compile_time_s']:.2f} s (first call: block 0 over a milliradian of rotation)",
        ),
        ("analysis time", f"{summary['analysis_time_s']:.2f} s (Euler angles, invariants, scene checks)"),
        (
            "body-steps/s",
            f"{summary['body_steps_per_s']:.3e}"
            + (
                " (the run's body-steps over the wall time of both solves: --no-error-estimate times "
                "the run alone)"
                if args.error_estimate
                else ""
            ),
        ),
    ]
    if args.accuracy == "exact":  # no steps to count: the closed form is evaluated at each sample
        lines = [row for row in lines if row[0] not in ("solver steps", "body-steps", "body-steps/s")]
    eps = float(np.finfo(plan.dtype).eps)
    lines += [
        (
            f"worst drift {key}",
            _drift_text(value, args.dtype, eps),
        )
        for key, value in summary["worst_drift"].items()
    ]
    units = {"omega": "relative to the body's largest |omega|", "orientation": "rad"}
    lines += [
        (f"worst error estimate {key}", f"{w['estimate']:.3e} {units[key]} (body {w['body']:,})")
        for key, w in summary["worst_error_estimate"].items()
    ]
    lines.append(("failed bodies", f"{summary['failed_bodies']:,}"))
    lines += scene_rows
    lines += [("wrote", f"{path} ({file_size(path)})") for path in out_files]
    if args.out and plan.save_every > 1:
        lines.append(
            (
                "stored samples",
                f"1 in every {plan.save_every} samples and the last ({len(plan.keep)} of {plan.samples}), "
                f"{args.save_dtype}; --save-every 1 keeps all",
            )
        )
    lines.append(("total time", f"{time.perf_counter() - t_start:.2f} s"))
    width = max(len(k) for k, _ in lines) + 2
    print(f"rigidjax {rj.__version__} simulate")
    for key, value in lines:
        print(f"  {key + ':':<{width}} {value}")


def _warm_up_times(plan: Plan) -> np.ndarray:
    """Sample times of the compiling call: as many as the run's (one compiled program serves both),
    over the run's span or the time the fastest body takes to turn a milliradian if that is
    shorter, so that the call costs few steps at any duration and its times stay distinct."""
    fastest = float(np.max(np.linalg.norm(plan.scene.omega0, axis=-1)))
    span = min(plan.duration, 1e-3 / fastest) if fastest > 0 else plan.duration
    return np.linspace(0.0, span, plan.samples)


def run(args) -> int:
    """The ``simulate`` command: plan, compile, simulate block by block, write, summarise."""
    if not jax.config.read("jax_enable_x64"):
        # Before any array of this run is made. float32 runs too: their arrays are made float32
        # explicitly, and the error estimate's finer solve runs in float64 (in float32 it could be
        # no finer than the run itself at the balanced and precise tolerances).
        jax.config.update("jax_enable_x64", True)
    # Every output path is checked before the run, so a typo cannot cost the results.
    if args.out:
        check_output(args.out, "--out", (".npz",))
    if args.plot and not args.no_plot:
        check_output(args.plot, "--plot", FIGURE_EXTENSIONS)
    if args.animate:
        _check_animate(args)
    t_start = time.perf_counter()
    plan = plan_run(args)
    # Spacings below the smallest normal number are flushed to zero in XLA's arithmetic.
    if not np.all(np.diff(plan.ts.astype(plan.dtype)) >= np.finfo(plan.dtype).tiny):
        raise UsageError(
            f"--duration {plan.duration:g}: its {plan.samples} sample times are not distinct in "
            f"{plan.dtype.name} (their spacing is below its resolution); give a longer --duration."
        )
    if args.out and args.save_every is not None and plan.save_every >= plan.samples:
        raise UsageError(
            f"--save-every {plan.save_every} is not below the number of samples ({plan.samples}); give "
            f"at most {plan.samples - 1}, which stores the first and the last sample only (or --out '' to "
            "store nothing)."
        )
    info(
        args,
        f"rigidjax simulate: {plan.scene.description}; {counted(plan.blocks, 'block', 'blocks')} of "
        f"{counted(plan.block_size, 'body', 'bodies')}{_blocks_note(plan, args)}, "
        f"{args.dtype}, accuracy {args.accuracy}",
    )
    info(args, "compiling (first call: block 0 over a time span of a milliradian of rotation)...")
    t0 = time.perf_counter()
    try:  # the scene is valid: what simulate refuses is the span (--duration)
        run_block(plan, args, 0, jnp.asarray(_warm_up_times(plan), plan.dtype))
        compile_time = time.perf_counter() - t0
        info(args, f"compiled in {compile_time:.2f} s")
        batch = simulate_blocks(plan, args)
    except ValueError as error:
        raise UsageError(f"--duration {plan.duration:g}: {error}") from None
    except Interrupted as stop:
        if args.out and stop.blocks_done:  # what the finished blocks computed is kept
            _write_partial(plan, stop.batch, stop.blocks_done, args)
        raise KeyboardInterrupt from None
    summary, scene_rows = _summary(plan, batch, args, compile_time)
    # A write that fails after the run goes to the temporary directory instead (and exit status 1).
    out_files, misplaced = [], False
    if args.out:
        written = write_or_rescue(
            "simulate", "--out", args.out, lambda path: _write_npz(plan, batch, args, summary, path)
        )
        out_files += [written] if written else []
        misplaced |= written != args.out
    if args.plot and not args.no_plot and _matplotlib_or_say_why():
        written = _plot(plan, batch, args)
        out_files += [written] if written else []
        misplaced |= written != args.plot
    if args.animate:
        count = min(ANIMATED_BODIES, plan.n)
        info(args, "animating body 0..." if count == 1 else f"animating the first {count} bodies...")
        written = _animate(plan, batch, args)
        out_files += [written] if written else []
        misplaced |= written != args.animate
    if not args.quiet:
        _print_summary(plan, batch, args, summary, scene_rows, out_files, t_start)
    if summary["failed_bodies"]:
        if args.accuracy == "exact":
            what, advice = (
                "the closed form failed",
                "a shorter --duration" + (" or --dtype float64" if args.dtype == "float32" else ""),
            )
        else:
            what, advice = "the integration failed", "--accuracy fast or a shorter --duration"
        print(
            f"rigidjax simulate: {what} for {counted(summary['failed_bodies'], 'body', 'bodies')} (NaN "
            f"rows from the first failed sample on, success=False in the npz); try {advice}.",
            file=sys.stderr,
        )
        return 1
    return 1 if misplaced else 0


# ---------------------------------------------------------------------------------------------
# Arguments.


def _samples(text: str) -> int:
    value = positive_int(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"must be at least 2 (the initial time and one more), got {value}")
    return value


def _save_every(text: str) -> int | None:
    return None if text == "auto" else positive_int(text)


def add_parser(subparsers) -> None:
    sim = subparsers.add_parser(
        "simulate",
        help="batch-simulate a scene of many bodies; write an .npz and a figure",
        description="Batch-simulate many rigid bodies with rigidjax.simulate, print a summary (timings, "
        "solver steps, invariant drift, the scene's physics against closed forms), and write the "
        "trajectories (.npz) and a figure (.png). Default: 10,000 heavy tops for 5 s.",
        formatter_class=DefaultsHelpFormatter,
    )
    sim.add_argument(
        "--scene",
        choices=SCENES,
        default="heavy-top",
        help="heavy-top: tops on a pivot (some too slow to stay up); free: torque-free asymmetric "
        "bodies incl. intermediate-axis (tennis-racket) spins; earth: the rigid Earth's free "
        "wobble (SI units)",
    )
    sim.add_argument(
        "-n",
        "--bodies",
        type=positive_int,
        default=None,
        help="number of bodies (default: 10,000; 100 for earth)",
    )
    sim.add_argument(
        "--duration",
        type=positive_float,
        default=None,
        help="simulated time in seconds (default: 5 s; 3 Euler periods, about 911 days, for earth)",
    )
    sim.add_argument(
        "--samples", type=_samples, default=None, help="output samples, including t=0 (default: 200)"
    )
    sim.add_argument(
        "--accuracy",
        choices=ACCURACIES,
        default="balanced",
        help="rigidjax.simulate preset; exact is the closed form (torque-free bodies, and the heavy-top "
        "scene made of symmetric tops)",
    )
    sim.add_argument(
        "--dtype",
        choices=("float64", "float32"),
        default="float64",
        help="simulation dtype (the error estimate of a float32 run compares with a float64 solve)",
    )
    sim.add_argument(
        "--seed", type=rng_seed, default=0, help="seed of numpy.random.default_rng for the scene"
    )
    sim.add_argument(
        "--blocks",
        type=positive_int,
        default=None,
        help="number of equal blocks the batch is run in (default: min(10, ceil(n/100)))",
    )
    sim.add_argument(
        "--chunk-size",
        type=positive_int,
        default=None,
        help="bodies per shared-step chunk inside rigidjax.simulate (default: 256 on CPU, 512 per GPU core)",
    )
    sim.add_argument(
        "--out",
        default=DEFAULT_OUT,
        help="output .npz path ('' to skip); checked before the run, written atomically",
    )
    sim.add_argument(
        "--save-every",
        type=_save_every,
        default=None,
        metavar="K",
        help="store every K-th sample and the last in the .npz (default 'auto': the smallest K that "
        "keeps the stored trajectories under 32 MiB, or the first and last sample if none does)",
    )
    sim.add_argument(
        "--save-dtype",
        choices=("float32", "float64"),
        default="float32",
        help="dtype of the stored trajectories",
    )
    sim.add_argument(
        "--plot",
        default=DEFAULT_PLOT,
        help="output figure path: .png, .pdf or .svg (needs matplotlib); checked before the run",
    )
    sim.add_argument("--no-plot", action="store_true", help="do not write the figure")
    sim.add_argument(
        "--animate",
        default=None,
        metavar="PATH",
        help=f"also write a 3-D animation of the first {ANIMATED_BODIES} bodies (from the stored samples) "
        "to PATH: .gif, or .mp4 with ffmpeg (needs matplotlib); checked before the run",
    )
    sim.add_argument(
        "--error-estimate",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="solve the batch a second time, more accurately, for a per-body error estimate "
        "(rigidjax.simulate(..., error_estimate=True)); the summary names the worst body, the .npz "
        "stores error_estimate_omega and error_estimate_orientation per body. The second solve, "
        "at a hundredth of the tolerance, takes more steps: the default job integrates in 0.9-1.0 s "
        "without it and 2.6-3.0 s with it on 2 CPU cores (compile time unchanged: the second solve "
        "is the same program)",
    )
    sim.add_argument("-q", "--quiet", action="store_true", help="no progress bar and no summary")
    sim.set_defaults(func=run)
