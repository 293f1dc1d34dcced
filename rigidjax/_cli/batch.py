"""How ``rigidjax simulate`` runs a scene: in blocks of identical shape, so that it compiles once.

The bodies are ordered by initial |omega| (fastest first, so that bodies of similar speed share a
block and the step size of its chunks); the last block is padded with copies of the last body. Each
block is one :func:`rigidjax.simulate` call, timed with ``block_until_ready``, then analysed (Euler
angles, invariants, the scene's own checks) at the simulation dtype, before the stored samples are
thinned.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import rigidjax as rj

from .common import StatusLine, UsageError, bar
from .scenes import SCENE_BUILDERS, SCENE_DEFAULTS, Scene, block_params

SAVE_BUDGET_BYTES = 32 * 2**20


@dataclasses.dataclass
class Plan:
    """What one run integrates and stores: the scene, the sample times, the blocks, the stride."""

    scene: Scene
    n: int
    duration: float
    samples: int
    blocks: int
    block_size: int
    order: np.ndarray  # (blocks * block_size,) body of each slot, padded with copies of the last
    ts: np.ndarray  # (samples,) float64
    dtype: np.dtype
    save_every: int
    keep: np.ndarray  # indices of the stored samples

    @property
    def has_q(self) -> bool:
        return self.scene.orientation0 is not None

    @property
    def padded(self) -> int:
        return self.blocks * self.block_size


@dataclasses.dataclass
class Batch:
    """What the block loop gathers: stored samples, per-body results, figure traces, counts, times."""

    store: dict[str, np.ndarray]
    results: dict[str, np.ndarray]
    traces: dict[str, np.ndarray]
    steps_total: int = 0
    body_steps: int = 0
    chunk_size: int = 0
    sim_time: float = 0.0
    loop_time: float = 0.0


WORKING_COPIES = 4
"""A block's trajectories (omega, orientation, Euler angles) are held about this many times over
while they are computed and analysed."""


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):  # not a POSIX system that tells
        return None


def _check_memory(args, n: int, samples: int, block_size: int) -> None:
    """A :class:`UsageError` before the run when one block's trajectories and the stored samples
    need more memory than the machine has (the run would end in an allocation failure)."""
    memory = _physical_memory()
    values = 3 + 4 + 3  # omega, orientation, Euler angles per body and sample
    block = block_size * samples * values * np.dtype(args.dtype).itemsize * WORKING_COPIES
    per_sample = n * values * np.dtype(args.save_dtype).itemsize if args.out else 0
    if args.save_every is None:  # within the budget, or the first and the last sample
        stored = min(samples * per_sample, max(SAVE_BUDGET_BYTES, 2 * per_sample))
    else:
        stored = (samples // args.save_every + 2) * per_sample
    if memory is not None and block + stored > memory:
        raise UsageError(
            f"-n {n:,} bodies at --samples {samples:,} need about {(block + stored) / 2**30:.3g} GiB "
            f"(each block's trajectories {block / 2**30:.3g} GiB, the stored samples "
            f"{stored / 2**30:.3g} GiB), more than this machine's {memory / 2**30:.3g} GiB; use fewer "
            "samples or bodies, more --blocks, or a larger --save-every."
        )


def _stored_samples(samples: int, every: int) -> np.ndarray:
    """The indices of the samples ``--save-every every`` stores: every ``every``-th from the first,
    and the last (the final state)."""
    return np.union1d(np.arange(0, samples, every), [samples - 1])


def _save_every_within_budget(samples: int, per_sample: int) -> int:
    """The smallest K whose stored samples fit ``SAVE_BUDGET_BYTES`` (the first and the last
    always: K = samples - 1 when nothing smaller fits)."""
    largest = max(1, samples - 1)
    every = min(max(1, math.ceil(samples * per_sample / SAVE_BUDGET_BYTES)), largest)
    while every < largest and len(_stored_samples(samples, every)) * per_sample > SAVE_BUDGET_BYTES:
        every += 1
    return every


def plan_run(args) -> Plan:
    n_default, duration_default, samples_default = SCENE_DEFAULTS[args.scene]
    n = args.bodies if args.bodies is not None else n_default
    duration = args.duration if args.duration is not None else duration_default
    samples = args.samples if args.samples is not None else samples_default
    blocks = args.blocks if args.blocks is not None else min(10, max(1, math.ceil(n / 100)))
    block_size = math.ceil(n / min(blocks, n))
    if block_size == 3:
        # Three bodies' moments, a (3, 3) array, would read as one inertia tensor: pad to four.
        block_size = 4
    blocks = math.ceil(n / block_size)
    _check_memory(args, n, samples, block_size)
    rng = np.random.default_rng(args.seed)
    if args.scene == "heavy-top" and args.accuracy == "exact":
        scene = SCENE_BUILDERS[args.scene](n, rng, symmetric=True)  # the closed form is Lagrange's top
    else:
        scene = SCENE_BUILDERS[args.scene](n, rng)
    # Fastest bodies first, so that bodies of similar speed share a block (and its step size).
    order = np.argsort(-np.linalg.norm(scene.omega0, axis=-1), kind="stable")
    order = np.concatenate([order, np.full(blocks * block_size - n, order[-1])])
    has_q = scene.orientation0 is not None
    per_sample = n * (3 + (7 if has_q else 0)) * np.dtype(args.save_dtype).itemsize
    if args.save_every is None:  # at least the first and the last sample, whatever their size
        save_every = _save_every_within_budget(samples, per_sample)
    else:
        save_every = args.save_every
    return Plan(
        scene,
        n,
        duration,
        samples,
        blocks,
        block_size,
        order,
        np.linspace(0.0, duration, samples),
        np.dtype(args.dtype),
        save_every,
        _stored_samples(samples, save_every),
    )


def run_block(plan: Plan, args, b: int, times):
    """``rigidjax.simulate`` on block ``b`` at ``times``; returns the block's bodies and trajectory."""
    index = plan.order[b * plan.block_size : (b + 1) * plan.block_size]
    model = plan.scene.make_model(block_params(plan.scene.params, index, plan.n), plan.dtype)
    q0 = jnp.asarray(plan.scene.orientation0[index], plan.dtype) if plan.has_q else None
    state0 = rj.State(jnp.asarray(plan.scene.omega0[index], plan.dtype), q0)
    traj = rj.simulate(
        model,
        state0,
        times,
        accuracy=args.accuracy,
        chunk_size=args.chunk_size,
        throw=False,
        error_estimate=getattr(args, "error_estimate", False),
    )
    jax.block_until_ready(traj)
    return index, traj


def _empty_batch(plan: Plan, save_dtype) -> Batch:
    stored, traced = len(plan.keep), len(plan.scene.plot_indices)
    store = {"omega": np.empty((plan.n, stored, 3), save_dtype)}
    traces = {"omega": np.empty((traced, plan.samples, 3))}
    if plan.has_q:
        store["orientation"] = np.empty((plan.n, stored, 4), save_dtype)
        store["euler_angles"] = np.empty((plan.n, stored, 3), save_dtype)
        traces["euler"] = np.empty((traced, plan.samples, 3))
    return Batch(store, {}, traces)


def _collect(plan: Plan, batch: Batch, b: int, index, traj, derived) -> None:
    """Counts, per-body results, stored samples and figure traces of block ``b``."""
    real = slice(0, min(plan.block_size, plan.n - b * plan.block_size))  # padding copies dropped
    index = index[real]
    steps = np.atleast_1d(np.asarray(traj.stats["num_steps"])).astype(np.int64)  # one per chunk
    batch.chunk_size = int(traj.stats["chunk_size"])
    per_chunk = np.minimum(batch.chunk_size, plan.block_size - batch.chunk_size * np.arange(len(steps)))
    batch.steps_total += int(steps.sum())
    batch.body_steps += int(np.sum(steps * per_chunk))

    euler, invariants = derived(traj)  # a failed body's samples are NaN from its failure on
    omega = np.asarray(traj.omega)[real]
    euler = np.asarray(euler)[real] if plan.has_q else None
    res = plan.scene.analyze(
        plan.ts,
        omega.astype(np.float64),
        None if euler is None else euler.astype(np.float64),
        block_params(plan.scene.params, index, plan.n),
    )
    res["success"] = np.asarray(traj.success)[real]
    for key, value in invariants.items():
        res["drift_" + key] = np.asarray(value, np.float64)[real]
    if "error_estimate_omega" in traj.stats:  # simulate(..., error_estimate=True)
        for key, value in traj.error_estimate().items():
            res["error_estimate_" + key] = np.asarray(value, np.float64)[real]
    for key, value in res.items():
        if key not in batch.results:
            batch.results[key] = np.empty((plan.n,) + np.shape(value)[1:], np.asarray(value).dtype)
        batch.results[key][index] = value

    batch.store["omega"][index] = omega[:, plan.keep]
    if plan.has_q:
        batch.store["orientation"][index] = np.asarray(traj.orientation)[real][:, plan.keep]
        batch.store["euler_angles"][index] = euler[:, plan.keep]
    plot_pos = {int(i): k for k, i in enumerate(plan.scene.plot_indices)}
    for row, i in enumerate(index):
        if int(i) in plot_pos:
            batch.traces["omega"][plot_pos[int(i)]] = omega[row]
            if plan.has_q:
                batch.traces["euler"][plot_pos[int(i)]] = euler[row]


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during the block loop, with what the blocks finished before it computed."""

    def __init__(self, batch: Batch, blocks_done: int):
        super().__init__()
        self.batch, self.blocks_done = batch, blocks_done


def done_bodies(plan: Plan, blocks_done: int) -> np.ndarray:
    """The indices (ascending) of the bodies of the first ``blocks_done`` blocks."""
    return np.unique(plan.order[: min(plan.n, blocks_done * plan.block_size)])


def simulate_blocks(plan: Plan, args) -> Batch:
    """Every block in turn: simulate (timed), then analyse; a progress line on stderr."""
    batch = _empty_batch(plan, np.dtype(args.save_dtype))
    ts = jnp.asarray(plan.ts, plan.dtype)
    # Euler angles and invariants of a block, in one compiled call (the same shapes for every block).
    derived = eqx.filter_jit(lambda tr: (tr.euler_angles("zxz") if plan.has_q else None, tr.invariants()))
    status = StatusLine(sys.stderr, not args.quiet)

    def show(done: int, elapsed: float) -> None:
        left = f", ~{elapsed / done * (plan.blocks - done):.1f} s left" if 0 < done < plan.blocks else ""
        status.show(
            f"simulating [{bar(done, plan.blocks)}] {done}/{plan.blocks} blocks, "
            f"{min(plan.n, done * plan.block_size):,}/{plan.n:,} bodies, {elapsed:.1f} s{left}",
            last=done == plan.blocks,
        )

    show(0, 0.0)
    t_loop = time.perf_counter()
    done = 0
    try:
        for b in range(plan.blocks):
            t0 = time.perf_counter()
            index, traj = run_block(plan, args, b, ts)
            batch.sim_time += time.perf_counter() - t0
            _collect(plan, batch, b, index, traj, derived)
            done = b + 1
            show(done, time.perf_counter() - t_loop)
    except KeyboardInterrupt:
        raise Interrupted(batch, done) from None
    batch.loop_time = time.perf_counter() - t_loop
    return batch
