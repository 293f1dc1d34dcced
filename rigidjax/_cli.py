"""The ``rigidjax`` command line: ``rigidjax simulate`` batch-simulates a scene of many bodies
(``rigidjax fit``: see ``_fit_cli``; ``rigidjax bench``, a small work-precision benchmark: ``_bench``).

``rigidjax simulate`` with no options integrates 10,000 heavy tops (random but reproducible
inertia, spin and tilt; ``--seed``) for 5 s, prints a summary, and writes the trajectories to
``rigidjax_simulate.npz`` and a figure to ``rigidjax_simulate.png``. Other scenes: ``--scene free``
(torque-free asymmetric bodies, a third of them spun near the unstable intermediate axis: the
tennis-racket flip) and ``--scene earth`` (the rigid Earth as a symmetric top in SI units; its
free wobble, the Euler period of about 300 days, against the closed form).

How the batch is run: the bodies are ordered by initial |omega| (fastest first, so that bodies of
similar speed share a block and the step size of its chunks) and cut into blocks of identical shape,
so :func:`rigidjax.simulate` compiles once. The first call, on block 0 with the time span shrunk by
1e-9 (same shapes, so the same compiled program, but almost no integration), is reported as the
compile time; every block is then timed with ``block_until_ready``.

The ``.npz`` file (all arrays are NumPy, readable with ``numpy.load`` and no pickle):

- ``ts`` (T_saved,): the stored sample times (s), every ``save_every``-th output sample;
- ``omega`` (N, T_saved, 3): body-frame angular velocity (rad/s);
- ``orientation`` (N, T_saved, 4) and ``euler_angles`` (N, T_saved, 3) (``zxz``: precession phi,
  nutation theta, spin psi, unwrapped in time) for scenes with an orientation (not ``earth``,
  where only Euler's equations are integrated);
- the model parameters and initial state (``inertia`` (N, 3), ``omega0`` (N, 3), and per scene
  ``mass``, ``com``, ``gravity``, ``euler0``, ``orientation0``), per-body results (``drift_<name>``
  for each invariant of :meth:`rigidjax.Trajectory.invariants`, ``success``, and the scene's own,
  e.g. ``theta_max``), and ``summary_json`` (the printed summary as JSON).

Samples are stored as float32 by default (``--save-dtype``) and, by default, thinned in time to the
smallest stride that keeps the stored trajectories under 32 MiB (``--save-every``); all analysis
(invariants, maxima, periods) uses every sample at the simulation dtype before thinning.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np

from . import _bench, _fit_cli

SCENES = ("heavy-top", "free", "earth")
ACCURACIES = ("fast", "balanced", "precise")
DEFAULT_OUT = "rigidjax_simulate.npz"
DEFAULT_PLOT = "rigidjax_simulate.png"
SAVE_BUDGET_BYTES = 32 * 2**20
GRAVITY = 9.81  # m/s^2

# The rigid Earth (SI): principal moments near the real ones, sidereal rotation rate.
EARTH_INERTIA = (8.0101e37, 8.0101e37, 8.0365e37)  # kg m^2
EARTH_OMEGA3 = 7.292115e-5  # rad/s
DAY = 86400.0  # s


def euler_rate(inertia=EARTH_INERTIA, omega3: float = EARTH_OMEGA3) -> float:
    """Closed-form free-wobble rate ``Omega = (C - A) / A * omega3`` of a symmetric top (rad/s)."""
    a, _, c = (float(x) for x in inertia)
    return (c - a) / a * omega3


# ---------------------------------------------------------------------------------------------
# Scenes: parameters (NumPy float64, drawn from default_rng(seed)), model construction, analysis.


@dataclasses.dataclass
class Scene:
    name: str
    description: str
    params: dict[str, np.ndarray]  # per-body arrays (leading axis N) or scalars; stored in the npz
    omega0: np.ndarray  # (N, 3)
    orientation0: np.ndarray | None  # (N, 4) or None (omega-only)
    make_model: Callable  # (params restricted to a block, dtype) -> rigidjax model
    analyze: Callable  # (ts, omega, euler or None, params of the block) -> dict of per-body arrays
    summarize: Callable  # (per-body results, ts, args) -> (summary rows (label, text), dict for JSON)
    plot: Callable  # (fig axes, ts, plot traces, per-body results) -> None
    plot_indices: np.ndarray  # bodies whose full-resolution traces are kept for the figure


def _quantile_indices(values: np.ndarray, qs=(0.05, 0.25, 0.5, 0.75, 0.95)) -> np.ndarray:
    order = np.argsort(values, kind="stable")
    picks = [order[min(len(order) - 1, int(q * len(order)))] for q in qs]
    return np.array(sorted(set(int(i) for i in picks)), dtype=np.int64)


def _quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    pw, pv, qw, qv = p[..., :1], p[..., 1:], q[..., :1], q[..., 1:]
    return np.concatenate(
        [pw * qw - np.sum(pv * qv, -1, keepdims=True), pw * qv + qw * pv + np.cross(pv, qv)], -1
    )


def _quat_from_zxz(angles: np.ndarray) -> np.ndarray:
    """``rigidjax.quat_from_euler(angles, "zxz")`` in float64 NumPy (independent of jax_enable_x64)."""
    half = 0.5 * np.asarray(angles, np.float64)
    c, s, zero = np.cos(half), np.sin(half), np.zeros(half.shape[:-1])
    qz1 = np.stack([c[..., 0], zero, zero, s[..., 0]], -1)
    qx = np.stack([c[..., 1], s[..., 1], zero, zero], -1)
    qz2 = np.stack([c[..., 2], zero, zero, s[..., 2]], -1)
    return _quat_multiply(_quat_multiply(qz1, qx), qz2)


def _block(params: dict[str, np.ndarray], index: np.ndarray, n: int) -> dict[str, np.ndarray]:
    return {k: (v[index] if np.ndim(v) and np.shape(v)[0] == n else v) for k, v in params.items()}


def _heavy_top_scene(n: int, rng: np.random.Generator) -> Scene:
    """Toy tops on a pivot: I_perp ~ 1e-4 kg m^2 about the pivot, I3 = 0.5-0.7 I_perp, m ~ 0.1 kg,
    pivot-to-centre-of-mass l ~ 3 cm, so the sleeping-top spin is about 57 rad/s at the centre of
    the ranges; spins of 30-150 rad/s put a fifth or so of the tops below it."""
    import rigidjax as rj

    i_perp = 1.0e-4 * rng.uniform(0.8, 1.2, n)
    asym = rng.uniform(0.0, 0.02, n)  # I2/I1 - 1: a slightly asymmetric top
    inertia = np.stack(
        [i_perp * (1 - asym / 2), i_perp * (1 + asym / 2), i_perp * rng.uniform(0.5, 0.7, n)], -1
    )
    mass = rng.uniform(0.09, 0.11, n)
    length = rng.uniform(0.025, 0.035, n)
    com = np.stack([np.zeros(n), np.zeros(n), length], -1)
    omega3 = rng.uniform(30.0, 150.0, n)
    theta0 = rng.uniform(0.05, 1.0, n)
    euler0 = np.stack([np.zeros(n), theta0, rng.uniform(0.0, 2 * np.pi, n)], -1)
    omega0 = np.stack([np.zeros(n), np.zeros(n), omega3], -1)
    orientation0 = _quat_from_zxz(euler0)
    params = {"inertia": inertia, "mass": mass, "com": com, "gravity": np.float64(GRAVITY), "euler0": euler0}

    def make_model(p, dtype):
        return rj.HeavyTop(
            np.asarray(p["inertia"], dtype),
            np.asarray(p["mass"], dtype),
            np.asarray(p["com"], dtype),
            gravity=np.asarray(p["gravity"], dtype),
        )

    def analyze(ts, omega, euler, p):
        theta = euler[..., 1]
        return {"theta_max": np.max(theta, axis=-1), "phi_end": euler[:, -1, 0] - euler[:, 0, 0]}

    def predictions():
        """Closed form for the symmetric top (I_perp = (I1 + I2)/2) released with theta' = phi' = 0:
        with u = cos(theta), the other turning point solves beta (1 - u^2) = a^2 (u0 - u)."""
        i_sym = 0.5 * (inertia[:, 0] + inertia[:, 1])
        mgl = mass * GRAVITY * length
        a2 = (inertia[:, 2] * omega3 / i_sym) ** 2
        beta = 2 * mgl / i_sym
        u0 = np.cos(theta0)
        disc = a2**2 - 4 * beta * a2 * u0 + 4 * beta**2
        u1 = 2 * (a2 * u0 - beta) / (a2 + np.sqrt(np.maximum(disc, 0.0)))
        sleeping = (inertia[:, 2] * omega3) ** 2 > 4 * i_sym * mgl
        return np.arccos(np.clip(u1, -1.0, 1.0)), sleeping

    theta_max_pred, sleeping = predictions()
    params["theta_max_pred"] = theta_max_pred
    params["sleeping_criterion"] = sleeping

    def summarize(res, ts, args):
        theta_max = res["theta_max"]
        ok = res["success"]
        fell = (theta_max > np.pi / 2) & ok
        fell_pred = theta_max_pred > np.pi / 2
        agree = int(np.sum((fell == fell_pred) & ok))
        err = np.abs(theta_max - theta_max_pred)[ok]
        n_ok = int(np.sum(ok))
        rows = [
            (
                "upright / fell",
                f"{n_ok - int(fell.sum()):,} stayed above horizontal, {int(fell.sum()):,} fell "
                "(max theta > 90 deg: the centre of mass went below the pivot)",
            ),
            (
                "closed form",
                f"{int(fell_pred.sum()):,} predicted to fall; simulation agrees for {agree:,} of "
                f"{n_ok:,} (symmetric-top turning point, I_perp = (I1+I2)/2)",
            ),
            (
                "max theta error",
                f"median {np.median(err) if err.size else float('nan'):.2e} rad vs closed form "
                "(sampled maximum; tops are up to 2% asymmetric)",
            ),
            (
                "sleeping criterion",
                f"(I3 w3)^2 > 4 I_perp m g l met by {int(sleeping.sum()):,}; fell: "
                f"{int((fell & sleeping).sum()):,} of those, "
                f"{int((fell & ~sleeping).sum()):,} of the {int((~sleeping).sum()):,} slower "
                "(it is a criterion for an upright start; these start tilted)",
            ),
        ]
        return rows, {
            "fell": int(fell.sum()),
            "fell_predicted": int(fell_pred.sum()),
            "fall_agreement": agree,
            "sleeping": int(sleeping.sum()),
        }

    def plot(axes, ts, traces, res):
        idx = plot_indices
        for k, i in enumerate(idx):
            label = f"w3={omega3[i]:.0f} rad/s, theta0={theta0[i]:.2f}"
            axes[0].plot(ts, traces["euler"][k, :, 1], lw=0.8, label=label)
            axes[1].plot(ts, traces["euler"][k, :, 0] - traces["euler"][k, 0, 0], lw=0.8, label=label)
        axes[0].axhline(np.pi / 2, color="k", lw=0.5, ls=":")
        axes[0].set(xlabel="t (s)", ylabel="nutation theta (rad)", title="Nutation of a few tops")
        axes[1].set(xlabel="t (s)", ylabel="precession phi - phi0 (rad)", title="Precession (unwrapped)")
        axes[0].legend(fontsize=6)

    plot_indices = _quantile_indices(omega3)
    return Scene(
        "heavy-top",
        f"{n:,} heavy tops (slightly asymmetric, spin 30-150 rad/s, tilt 0.05-1 rad)",
        params,
        omega0,
        orientation0,
        make_model,
        analyze,
        summarize,
        plot,
        plot_indices,
    )


def _free_scene(n: int, rng: np.random.Generator) -> Scene:
    """Torque-free asymmetric bodies (solid ellipsoids, 1 kg, semi-axes 0.1-2 m), each spun within
    1e-3-1e-1 rad of one principal axis: minor, intermediate (the tennis-racket flip) or major."""
    import rigidjax as rj

    c = rng.uniform(1.0, 2.0, n)
    b = c * rng.uniform(0.4, 0.8, n)
    a = b * rng.uniform(0.25, 0.75, n)
    inertia = np.sort(np.stack([b**2 + c**2, a**2 + c**2, a**2 + b**2], -1) / 5.0, axis=-1)
    axis = rng.integers(0, 3, n)
    speed = rng.uniform(2.0, 20.0, n)
    delta = 10.0 ** rng.uniform(-3.0, -1.0, n)
    beta = rng.uniform(0.0, 2 * np.pi, n)
    unit = np.zeros((n, 3))
    rows = np.arange(n)
    unit[rows, axis] = np.cos(delta)
    unit[rows, (axis + 1) % 3] = np.sin(delta) * np.cos(beta)
    unit[rows, (axis + 2) % 3] = np.sin(delta) * np.sin(beta)
    omega0 = speed[:, None] * unit
    q = rng.normal(size=(n, 4))
    orientation0 = q / np.linalg.norm(q, axis=-1, keepdims=True)
    params = {"inertia": inertia, "spin_axis": axis, "orientation0": orientation0}

    def make_model(p, dtype):
        return rj.FreeBody(np.asarray(p["inertia"], dtype))

    def analyze(ts, omega, euler, p):
        k = np.asarray(p["spin_axis"])
        main = np.take_along_axis(omega, k[:, None, None], axis=-1)[..., 0]
        flipped = main * main[:, :1] < 0
        first = np.where(flipped.any(-1), ts[np.argmax(flipped, axis=-1)], np.nan)
        return {"flipped": flipped.any(-1), "first_flip_time": first}

    def summarize(res, ts, args):
        flipped = res["flipped"] & res["success"]
        rows = []
        names = ("minor", "intermediate", "major")
        for k, name in enumerate(names):
            sel = axis == k
            note = "unstable: flips expected" if k == 1 else "stable: no flips expected"
            rows.append(
                (
                    f"spun near {name}",
                    f"{int(sel.sum()):,} bodies, {int(flipped[sel].sum()):,} flipped ({note})",
                )
            )
        inter = flipped & (axis == 1)
        if inter.any():
            rows.append(
                (
                    "first flip time",
                    f"median {np.nanmedian(res['first_flip_time'][inter]):.2f} s "
                    "(intermediate-axis spins that flipped)",
                )
            )
        extra = {f"flipped_{name}": int(flipped[axis == k].sum()) for k, name in enumerate(names)}
        return rows, extra

    def plot(axes, ts, traces, res):
        for k, i in enumerate(plot_indices):
            w = traces["omega"][k] / np.linalg.norm(omega0[i])
            target = axes[0] if axis[i] == 1 else axes[1]
            target.plot(ts, w[:, axis[i]], lw=0.8, label=f"axis {axis[i] + 1}, |w0|={speed[i]:.1f} rad/s")
        axes[0].set(xlabel="t (s)", ylabel="w2 / |w0|", title="Spins near the intermediate axis (flips)")
        axes[1].set(xlabel="t (s)", ylabel="w_axis / |w0|", title="Spins near the minor/major axis")
        for ax in axes[:2]:
            ax.legend(fontsize=6)

    inter = np.flatnonzero(axis == 1)
    stable = np.flatnonzero(axis != 1)
    plot_indices = np.array(sorted(set(inter[:3].tolist() + stable[:2].tolist())), dtype=np.int64)
    return Scene(
        "free",
        f"{n:,} torque-free asymmetric bodies spun near a principal axis",
        params,
        omega0,
        orientation0,
        make_model,
        analyze,
        summarize,
        plot,
        plot_indices,
    )


def _earth_scene(n: int, rng: np.random.Generator) -> Scene:
    """The rigid Earth: n copies with different free-wobble amplitudes (1e-11-1e-10 rad/s, i.e. the
    rotation axis 0.03-0.3 arcsec from the figure axis) and phases; omega-only (Euler's equations)."""
    import rigidjax as rj

    inertia = np.broadcast_to(np.array(EARTH_INERTIA), (n, 3)).copy()
    amp = 10.0 ** rng.uniform(-11.0, -10.0, n)
    phase = rng.uniform(0.0, 2 * np.pi, n)
    omega0 = np.stack([amp * np.cos(phase), amp * np.sin(phase), np.full(n, EARTH_OMEGA3)], -1)
    rate = euler_rate()
    params = {"inertia": inertia}

    def make_model(p, dtype):
        return rj.FreeBody(np.asarray(p["inertia"], dtype))

    def analyze(ts, omega, euler, p):
        angle = np.unwrap(np.arctan2(omega[..., 1], omega[..., 0]), axis=-1)
        t = ts - ts[0]
        tc = t - t.mean()
        slope = ((angle - angle.mean(-1, keepdims=True)) @ tc) / (tc @ tc)  # least-squares rate
        period = 2 * np.pi / np.abs(slope)
        amplitude = np.hypot(omega[..., 0], omega[..., 1])  # conserved for a symmetric top
        drift = np.max(np.abs(amplitude - amplitude[:, :1]), axis=-1) / amplitude[:, 0]
        return {"wobble_period": period, "wobble_amplitude_drift": drift}

    def summarize(res, ts, args):
        ok = res["success"]
        closed = 2 * np.pi / rate
        cycles = (ts[-1] - ts[0]) * rate / (2 * np.pi)
        rows = [
            (
                "closed form",
                f"2 pi / Omega = {closed:.9e} s = {closed / DAY:.4f} days, "
                f"Omega = (C - A)/A w3 = {rate:.6e} rad/s",
            )
        ]
        extra = {"wobble_period_closed_form": closed}
        if 2 * np.pi * cycles / (len(ts) - 1) > 2.0:
            rows.append(
                (
                    "wobble period",
                    f"not measured: {len(ts)} samples are too few for {cycles:.1f} "
                    "wobble cycles (need < 2 rad of wobble per sample)",
                )
            )
            return rows, extra
        period = res["wobble_period"][ok]
        rel = np.abs(period / closed - 1.0)
        rows.append(
            (
                "wobble period",
                f"{np.mean(period):.9e} s = {np.mean(period) / DAY:.4f} days "
                f"(mean over {len(period):,} Earths, fit over {cycles:.2f} cycles)",
            )
        )
        rows.append(
            ("period rel. error", f"max {np.max(rel):.2e}, mean {np.mean(rel):.2e} vs the closed form")
        )
        rows.append(
            (
                "wobble amp. drift",
                f"max {np.max(res['wobble_amplitude_drift'][ok]):.2e} (relative; |w1 + i w2| "
                "is conserved for a symmetric top)",
            )
        )
        rows.append(("note", "the observed Chandler wobble is ~433 days: the real Earth is not rigid"))
        extra.update(wobble_period=float(np.mean(period)), wobble_period_max_rel_error=float(np.max(rel)))
        return rows, extra

    def plot(axes, ts, traces, res):
        days = ts / DAY
        for k, i in enumerate(plot_indices):
            w = traces["omega"][k]
            axes[0].plot(days, w[:, 0] * 1e11, lw=0.8, label=f"w1, Earth {i}")
            axes[0].plot(days, w[:, 1] * 1e11, lw=0.8, ls="--", label=f"w2, Earth {i}")
            axes[1].plot(w[:, 0] * 1e11, w[:, 1] * 1e11, lw=0.8)
        axes[0].set(xlabel="t (days)", ylabel="w (1e-11 rad/s)", title="Free wobble of the rigid Earth")
        axes[1].set(
            xlabel="w1 (1e-11 rad/s)", ylabel="w2 (1e-11 rad/s)", title="Polhode (body frame)", aspect="equal"
        )
        axes[0].legend(fontsize=6)

    plot_indices = _quantile_indices(amp, qs=(0.5, 0.95))
    return Scene(
        "earth",
        f"{n:,} rigid Earths (SI units), free wobble of 1e-11-1e-10 rad/s",
        params,
        omega0,
        None,
        make_model,
        analyze,
        summarize,
        plot,
        plot_indices,
    )


_SCENE_BUILDERS = {"heavy-top": _heavy_top_scene, "free": _free_scene, "earth": _earth_scene}
# Defaults per scene: bodies, duration (s), samples.
_SCENE_DEFAULTS = {
    "heavy-top": (10_000, 5.0, 200),
    "free": (10_000, 5.0, 200),
    "earth": (100, 3 * 2 * math.pi / euler_rate(), 200),
}


# ---------------------------------------------------------------------------------------------
# Progress bar (plain text on stderr).


class _Progress:
    def __init__(self, blocks: int, bodies: int, stream, enabled: bool):
        self.blocks, self.bodies, self.stream, self.enabled = blocks, bodies, stream, enabled
        self.tty = enabled and hasattr(stream, "isatty") and stream.isatty()
        self.width = 30

    def update(self, done: int, bodies_done: int, elapsed: float) -> None:
        if not self.enabled:
            return
        filled = round(self.width * done / self.blocks)
        bar = "#" * filled + "." * (self.width - filled)
        left = f", ~{elapsed / done * (self.blocks - done):.1f} s left" if 0 < done < self.blocks else ""
        line = (
            f"simulating [{bar}] {done}/{self.blocks} blocks, {bodies_done:,}/{self.bodies:,} bodies, "
            f"{elapsed:.1f} s{left}"
        )
        if self.tty:
            self.stream.write("\r" + line)
            if done == self.blocks:
                self.stream.write("\n")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


def _info(args, message: str) -> None:
    if not args.quiet:
        print(message, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# The simulate command.


def _size(path: str) -> str:
    size = os.path.getsize(path)
    return f"{size / 2**20:.1f} MiB" if size >= 2**20 else f"{size / 2**10:.1f} KiB"


def _run_simulate(args) -> int:
    import jax

    if args.dtype == "float64" and not jax.config.read("jax_enable_x64"):
        jax.config.update("jax_enable_x64", True)  # before any array of this run is made
    import equinox as eqx
    import jax.numpy as jnp

    import rigidjax as rj

    t_start = time.perf_counter()
    dtype = np.dtype(args.dtype)
    n_default, duration_default, samples_default = _SCENE_DEFAULTS[args.scene]
    n = args.bodies if args.bodies is not None else n_default
    duration = args.duration if args.duration is not None else duration_default
    samples = args.samples if args.samples is not None else samples_default
    rng = np.random.default_rng(args.seed)
    scene = _SCENE_BUILDERS[args.scene](n, rng)
    blocks = args.blocks if args.blocks is not None else min(10, max(1, math.ceil(n / 100)))
    blocks = min(blocks, n)
    block_size = math.ceil(n / blocks)
    blocks = math.ceil(n / block_size)
    padded = blocks * block_size
    # Fastest bodies first, so that bodies of similar speed share a block (and its step size).
    order = np.argsort(-np.linalg.norm(scene.omega0, axis=-1), kind="stable")
    order = np.concatenate([order, np.full(padded - n, order[-1])])  # pad with copies of the last

    ts_np = np.linspace(0.0, duration, samples)
    ts = jnp.asarray(ts_np, dtype)
    save_dtype = np.dtype(args.save_dtype)
    has_q = scene.orientation0 is not None
    per_sample = n * (3 + (7 if has_q else 0)) * save_dtype.itemsize
    if args.save_every is None:
        save_every = max(1, math.ceil(samples * per_sample / SAVE_BUDGET_BYTES))
    else:
        save_every = args.save_every
    keep = np.arange(0, samples, save_every)

    def run_block(b: int, times):
        index = order[b * block_size : (b + 1) * block_size]
        model = scene.make_model(_block(scene.params, index, n), dtype)
        q0 = None if not has_q else jnp.asarray(scene.orientation0[index], dtype)
        state0 = rj.State(jnp.asarray(scene.omega0[index], dtype), q0)
        traj = rj.simulate(
            model, state0, times, accuracy=args.accuracy, chunk_size=args.chunk_size, throw=False
        )
        jax.block_until_ready(traj)
        return index, traj

    _info(
        args,
        f"rigidjax simulate: {scene.description}; {blocks} block(s) of {block_size:,} bodies, "
        f"{args.dtype}, accuracy {args.accuracy}",
    )
    _info(args, "compiling (first call on block 0 with the time span shrunk by 1e-9)...")
    t0 = time.perf_counter()
    run_block(0, ts * 1e-9)
    compile_time = time.perf_counter() - t0
    _info(args, f"compiled in {compile_time:.2f} s")

    store = {"omega": np.empty((n, len(keep), 3), save_dtype)}
    if has_q:
        store["orientation"] = np.empty((n, len(keep), 4), save_dtype)
        store["euler_angles"] = np.empty((n, len(keep), 3), save_dtype)
    results: dict[str, np.ndarray] = {}
    plot_pos = {int(i): k for k, i in enumerate(scene.plot_indices)}
    traces = {"omega": np.empty((len(plot_pos), samples, 3))}
    if has_q:
        traces["euler"] = np.empty((len(plot_pos), samples, 3))
    steps_total = 0
    body_steps = 0
    chunk_size = 0
    sim_time = 0.0
    # Euler angles and invariants of a block, in one compiled call (the same shapes for every block).
    derived = eqx.filter_jit(lambda tr: (tr.euler_angles("zxz") if has_q else None, tr.invariants()))
    progress = _Progress(blocks, n, sys.stderr, not args.quiet)
    progress.update(0, 0, 0.0)
    t_loop = time.perf_counter()
    for b in range(blocks):
        t0 = time.perf_counter()
        index, traj = run_block(b, ts)
        sim_time += time.perf_counter() - t0
        real = slice(0, min(block_size, n - b * block_size))
        index = index[real]
        steps = np.asarray(traj.stats["num_steps"]).astype(np.int64)
        chunk_size = int(traj.stats["chunk_size"])
        per_chunk = np.minimum(chunk_size, block_size - chunk_size * np.arange(len(steps)))
        steps_total += int(steps.sum())
        body_steps += int(np.sum(steps * per_chunk))

        euler, invariants = derived(traj)
        omega = np.asarray(traj.omega)[real]
        euler = np.asarray(euler)[real] if has_q else None
        block_params = _block(scene.params, index, n)
        block_res = scene.analyze(
            ts_np, omega.astype(np.float64), None if euler is None else euler.astype(np.float64), block_params
        )
        block_res["success"] = np.asarray(traj.success)[real]
        for key, value in invariants.items():
            block_res["drift_" + key] = np.asarray(value, np.float64)[real]
        for key, value in block_res.items():
            if key not in results:
                results[key] = np.empty((n,) + np.shape(value)[1:], np.asarray(value).dtype)
            results[key][index] = value
        store["omega"][index] = omega[:, keep]
        if has_q:
            store["orientation"][index] = np.asarray(traj.orientation)[real][:, keep]
            store["euler_angles"][index] = euler[:, keep]
        for row, i in enumerate(index):
            if int(i) in plot_pos:
                traces["omega"][plot_pos[int(i)]] = omega[row]
                if has_q:
                    traces["euler"][plot_pos[int(i)]] = euler[row]
        progress.update(b + 1, min(n, (b + 1) * block_size), time.perf_counter() - t_loop)
    loop_time = time.perf_counter() - t_loop

    drifts = {k[len("drift_") :]: v for k, v in results.items() if k.startswith("drift_")}
    success = results["success"]
    # Over the bodies that integrated (failed ones are NaN and counted apart); a NaN drift stays NaN.
    worst = {k: float(np.max(v[success])) if success.any() else float("nan") for k, v in drifts.items()}
    per_body_worst = np.max(np.stack(list(drifts.values()), -1), axis=-1) if drifts else np.zeros(n)
    scene_rows, scene_extra = scene.summarize(results, ts_np, args)

    summary = {
        "scene": args.scene,
        "bodies": n,
        "blocks": blocks,
        "block_size": block_size,
        "padding_bodies": padded - n,
        "dtype": args.dtype,
        "accuracy": args.accuracy,
        "duration_s": float(duration),
        "samples": samples,
        "seed": args.seed,
        "chunk_size": chunk_size,
        "solver_steps": steps_total,
        "body_steps": body_steps,
        "wall_time_s": sim_time,
        "compile_time_s": compile_time,
        "analysis_time_s": loop_time - sim_time,
        "body_steps_per_s": body_steps / sim_time if sim_time > 0 else float("nan"),
        "worst_drift": worst,
        "failed_bodies": int(np.sum(~success)),
        "save_every": save_every,
        "save_dtype": args.save_dtype,
        **scene_extra,
    }

    out_files = []
    if args.out:
        arrays = {
            "ts": ts_np[keep],
            **store,
            "omega0": scene.omega0,
            "success": success,
            "per_body_worst_drift": per_body_worst,
        }
        if has_q:
            arrays["orientation0"] = scene.orientation0
        arrays.update(scene.params)
        arrays.update({k: v for k, v in results.items() if k != "success"})
        arrays.update(
            scene=np.array(args.scene),
            dtype=np.array(args.dtype),
            accuracy=np.array(args.accuracy),
            seed=np.array(args.seed),
            save_every=np.array(save_every),
            summary_json=np.array(json.dumps(summary)),
        )
        np.savez(args.out, **arrays)
        out_files.append(args.out)
    if args.plot and not args.no_plot:
        if _plot(scene, ts_np, traces, results, per_body_worst, args):
            out_files.append(args.plot)

    if not args.quiet:
        mean_steps = steps_total / max(1, blocks * math.ceil(block_size / max(chunk_size, 1)))
        duration_text = f"{duration:.6g} s" + (f" ({duration / DAY:.1f} days)" if duration > 10 * DAY else "")
        solver = rj.PRESETS[args.accuracy]
        lines = [
            ("scene", f"{args.scene}: {scene.description}"),
            (
                "bodies",
                f"{n:,}"
                + (
                    f" ({blocks} block{'s' if blocks > 1 else ''} of {block_size:,}"
                    + (f", last padded with {padded - n} copies" if padded > n else "")
                    + ")"
                ),
            ),
            ("dtype", args.dtype),
            ("accuracy", f"{args.accuracy} ({solver[0].__name__}, rtol {solver[1]:g})"),
            ("samples", f"{samples:,} over {duration_text}"),
            (
                "solver steps",
                f"{steps_total:,} (summed over chunks of <= {chunk_size:,} bodies sharing one step size;"
                f" mean {mean_steps:,.0f} per chunk)",
            ),
            ("body-steps", f"{body_steps:,} (steps x bodies of each chunk, padding copies included)"),
            ("wall time", f"{sim_time:.2f} s (all blocks, excluding compile)"),
            ("compile time", f"{compile_time:.2f} s (first call: block 0 over a 1e-9-shrunk time span)"),
            ("analysis time", f"{loop_time - sim_time:.2f} s (Euler angles, invariants, scene checks)"),
            ("body-steps/s", f"{summary['body_steps_per_s']:.3e}"),
        ]
        for key, value in worst.items():
            lines.append((f"worst drift {key}", f"{value:.3e}"))
        lines.append(("failed bodies", f"{summary['failed_bodies']:,}"))
        lines.extend(scene_rows)
        for path in out_files:
            lines.append(("wrote", f"{path} ({_size(path)})"))
        if args.out and save_every > 1:
            lines.append(
                (
                    "stored samples",
                    f"1 in every {save_every} samples ({len(keep)} of {samples}), "
                    f"{args.save_dtype}; --save-every 1 keeps all",
                )
            )
        lines.append(("total time", f"{time.perf_counter() - t_start:.2f} s"))
        width = max(len(k) for k, _ in lines) + 2
        print(f"rigidjax {rj.__version__} simulate")
        for key, value in lines:
            print(f"  {key + ':':<{width}} {value}")
    if summary["failed_bodies"]:
        print(
            f"rigidjax simulate: the integration failed for {summary['failed_bodies']} bodies (NaN rows, "
            "success=False in the npz); try --accuracy fast or a shorter --duration.",
            file=sys.stderr,
        )
        return 1
    return 0


def _plot(scene: Scene, ts, traces, results, per_body_worst, args) -> bool:
    try:
        import matplotlib
    except ImportError:
        print(
            "rigidjax simulate: matplotlib is not installed; skipping the plot "
            "(pip install 'rigidjax[plot]').",
            file=sys.stderr,
        )
        return False
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    scene.plot(axes, ts, traces, results)
    tiny = 1e-17
    values = np.maximum(per_body_worst[np.isfinite(per_body_worst)], tiny)
    if values.size:
        lo, hi = math.floor(np.log10(values.min())), math.ceil(np.log10(values.max()))
        bins = np.logspace(lo, max(hi, lo + 1), 41)
        axes[2].hist(values, bins=bins)
    axes[2].set(
        xscale="log",
        xlabel="worst relative drift of the invariants",
        ylabel="bodies",
        title=f"Invariant drift per body ({args.dtype}, {args.accuracy})",
    )
    fig.suptitle(f"rigidjax simulate --scene {args.scene}: {scene.description}", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.plot, dpi=110)
    plt.close(fig)
    return True


# ---------------------------------------------------------------------------------------------
# Argument parsing.


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def _samples(text: str) -> int:
    value = _positive_int(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"must be at least 2 (the initial time and one more), got {value}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


def _save_every(text: str) -> int | None:
    return None if text == "auto" else _positive_int(text)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="rigidjax", description="Rotational dynamics of rigid bodies in JAX: command-line tools."
    )
    parser.add_argument("--version", action="version", version=f"rigidjax {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _fit_cli.add_parser(sub)
    _bench.add_parser(sub)
    sim = sub.add_parser(
        "simulate",
        help="batch-simulate a scene of many bodies; write an .npz and a figure",
        description="Batch-simulate many rigid bodies with rigidjax.simulate, print a summary (timings, "
        "solver steps, invariant drift, the scene's physics against closed forms), and write the "
        "trajectories (.npz) and a figure (.png). Default: 10,000 heavy tops for 5 s.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
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
        type=_positive_int,
        default=None,
        help="number of bodies (default: 10,000; 100 for earth)",
    )
    sim.add_argument(
        "--duration",
        type=_positive_float,
        default=None,
        help="simulated time in seconds (default: 5 s; 3 Euler periods, about 908 days, for earth)",
    )
    sim.add_argument(
        "--samples", type=_samples, default=None, help="output samples, including t=0 (default: 200)"
    )
    sim.add_argument("--accuracy", choices=ACCURACIES, default="balanced", help="rigidjax.simulate preset")
    sim.add_argument(
        "--dtype",
        choices=("float64", "float32"),
        default="float64",
        help="simulation dtype (float64 turns on jax_enable_x64)",
    )
    sim.add_argument("--seed", type=int, default=0, help="seed of numpy.random.default_rng for the scene")
    sim.add_argument(
        "--blocks",
        type=_positive_int,
        default=None,
        help="number of equal blocks the batch is run in (default: min(10, ceil(n/100)))",
    )
    sim.add_argument(
        "--chunk-size",
        type=_positive_int,
        default=1024,
        help="bodies per shared-step chunk inside rigidjax.simulate",
    )
    sim.add_argument("--out", default=DEFAULT_OUT, help="output .npz path ('' to skip)")
    sim.add_argument(
        "--save-every",
        type=_save_every,
        default=None,
        metavar="K",
        help="store every K-th sample in the .npz (default 'auto': the smallest K that keeps the "
        "stored trajectories under 32 MiB)",
    )
    sim.add_argument(
        "--save-dtype",
        choices=("float32", "float64"),
        default="float32",
        help="dtype of the stored trajectories",
    )
    sim.add_argument("--plot", default=DEFAULT_PLOT, help="output .png path (needs matplotlib)")
    sim.add_argument("--no-plot", action="store_true", help="do not write the figure")
    sim.add_argument("-q", "--quiet", action="store_true", help="no progress bar and no summary")
    sim.set_defaults(func=_run_simulate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``rigidjax`` command; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a usage error (already printed)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    if args.command is None:
        parser.print_help()
        return 0
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
