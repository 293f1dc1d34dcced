"""``simulate(..., progress=...)``: the batch run from the host in blocks of whole chunks, with a
report after each block.

The bodies are put in the order the one-program run would chunk them in (sorted by speed, as
:func:`.chunked.integrate` sorts them), cut into equal blocks of whole chunks, and every block runs
through the same compiled integration (one shape, so one compile; the last block is padded with
copies of the last body, as the last chunk is). Each chunk therefore holds the same bodies, in the
same order, as without progress, and takes the same steps.

The same blocks give ``simulate`` every core of a CPU that JAX sees as one device: XLA runs one call
of a program on one core (a ``lax.map`` of while loops does not spread over its threads), but calls
made from several Python threads run side by side. Where :func:`host_threads` finds more than one
core and chunk, the batch runs as one block per core, each from its own thread, with the same chunks
and steps, and so the same trajectories to the bit, as one call.
"""

import concurrent.futures
import functools
import math
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax._src import config as jax_config

from .._checks import check_callable, is_traced
from . import batching
from .chunked import plan_bodies
from .cores import available_cores
from .trajectory import Trajectory

MAX_BLOCKS = 20
"""At most this many blocks (reports): one report per 5% of the bodies; every block is one call of
the compiled integration, so fewer blocks cost less dispatch."""


def check_progress(progress) -> Callable[[int, int], None] | None:
    """``None`` when progress is off; otherwise the function called as ``report(done, total)``."""
    if isinstance(progress, bool | np.bool_):
        return ProgressBar() if progress else None
    if progress is None:
        return None
    if callable(progress):
        check_callable(progress, "progress", "progress(done_bodies, total_bodies) (two arguments)", 2)
        return progress
    raise TypeError(
        "progress must be True (a progress bar on stderr), False, or a callable "
        f"progress(done_bodies, total_bodies); got {progress!r}."
    )


def bar(done: int, total: int, width: int = 30) -> str:
    """A text progress bar: ``done / total`` of ``width`` characters filled with ``#``."""
    filled = min(width, max(0, round(width * done / max(total, 1))))
    return "#" * filled + "." * (width - filled)


class StatusLine:
    """One progress line on a stream: rewritten in place on a terminal, one line per update otherwise."""

    def __init__(self, stream, enabled: bool = True):
        self.stream, self.enabled = stream, enabled
        self.tty = enabled and hasattr(stream, "isatty") and stream.isatty()
        self._width = 0

    def show(self, line: str, last: bool = False) -> None:
        if not self.enabled:
            return
        if self.tty:
            self.stream.write("\r" + line.ljust(self._width) + ("\n" if last else ""))
            self._width = 0 if last else len(line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def end(self) -> None:
        """Ends the line a terminal's last update left open (the next output starts below it)."""
        if self.tty and self._width:
            self.stream.write("\n")
            self.stream.flush()
            self._width = 0


def passes(report, count: int) -> list[Callable[[int, int], None]]:
    """``count`` reports for ``count`` solves of the same batch, one after the other, that make one
    report to ``report``: pass ``i``'s ``(done, total)`` arrives as ``(i total + done, count total)``."""
    if isinstance(report, ProgressBar):
        report.passes = count

    def one(i):
        def report_pass(done, total):
            if i == 0 or done > 0:  # a later pass's start is the previous pass's end, reported
                report(i * total + done, count * total)

        return report_pass

    return [one(i) for i in range(count)]


class ProgressBar:
    """One line on stderr: bodies done, elapsed time and an estimate of the time left. Rewritten in
    place on a terminal, one line per update otherwise (a log file)."""

    def __init__(self, stream=None):
        self.line = StatusLine(sys.stderr if stream is None else stream)
        self._start = self._first = None
        self.passes = 1  # solves per body (2 with an error estimate)

    def __call__(self, done: int, total: int) -> None:
        now = time.perf_counter()
        if self._start is None or done == 0:
            self._start, self._first = now, None
        elapsed = now - self._start
        left = ""
        if 0 < done < total:
            if self._first is None:  # the first block includes the compile: no estimate yet
                self._first = (done, now)
            else:
                rate = (now - self._first[1]) / max(done - self._first[0], 1)
                left = f", ~{rate * (total - done):.1f} s left"
        last = done >= total
        what = (
            "bodies" if self.passes == 1 else f"body solves ({self.passes} per body: result, error estimate)"
        )
        self.line.show(
            f"simulate [{bar(done, total)}] {done:,}/{total:,} {what}, {elapsed:.1f} s{left}", last
        )
        if last:
            self._start = None


@eqx.filter_jit
def _chunk_order(model, omega0, q0, ts, args, formulation, chunk_size, sort):
    """The body order of :func:`.chunked.integrate`'s chunks."""
    plan = plan_bodies(model, omega0, q0, ts, args, formulation, chunk_size, sort)[-1]
    return plan.order


_TRACED = (
    "simulate: progress needs concrete inputs (it runs the batch in blocks from Python and reports "
    "between them), so it cannot be used under jax.jit, grad or vmap; pass progress=False there."
)


def report_start(report, n: int, *inputs) -> None:
    """The first report, ``(0, n)``, of a batch computed in one program (the closed forms); a
    ``ValueError`` for traced ``inputs``."""
    if is_traced(*inputs):
        raise ValueError(_TRACED)
    report(0, n)


MAX_HOST_THREADS = 4
"""At most this many threads, each running its blocks through the one compiled program."""

THREADED_MAX_BYTES = 1 << 30
"""The largest trajectory (omega and orientation at every sample time) that :func:`host_threads`
runs in threads: the blocks' results are joined and put back in order afterwards, one more copy
of it beside the blocks'."""


def host_threads(model, omega0, q0, ts, args, chunk_size: int) -> int:
    """How many Python threads :func:`rigidjax.simulate` runs its chunks from: one per core of the
    process (at most one per chunk and ``MAX_HOST_THREADS``) where JAX has a single CPU device, the
    inputs have values and the trajectory has more than one sample time and at most
    ``THREADED_MAX_BYTES``; else 1 (one compiled call). With several devices the chunks are spread
    over the devices instead.

    Measured with ``benchmarks/threaded_calls.py`` (10^4 tennis-racket bodies, "balanced", 2-core
    CPU): two threads 1.46-1.77x faster than one call, the trajectories the same to the bit. The
    threads call one compiled program (the blocks are of one size), which XLA runs from several
    threads side by side, so the first call compiles once."""
    if is_traced(model, omega0, q0, ts, args) or ts.shape[0] < 2:
        return 1
    devices = jax.devices()
    if len(devices) != 1 or devices[0].platform != "cpu":
        return 1
    n = math.prod(batching.batch_shape(model, omega0, q0))
    rows = 3 if q0 is None else 7
    if n * ts.shape[0] * rows * omega0.dtype.itemsize > THREADED_MAX_BYTES:
        return 1
    _, n_chunks, _ = batching.chunk_layout(n, chunk_size)
    return max(1, min(available_cores(), n_chunks, MAX_HOST_THREADS))


def _same_jax_context(pool) -> bool:
    """Whether a thread of ``pool`` traces in the same JAX context as this one (JAX's context
    managers hold per thread); False where this JAX cannot tell."""
    context = getattr(jax_config, "trace_context", None)
    if context is None:  # pragma: no cover - a JAX without it
        return False
    return pool.submit(context).result() == context()


def _ignore(done: int, total: int) -> None:
    pass


def run_in_blocks(run, report, model, omega0, q0, ts, args, formulation, chunk_size, sort, threads=1):
    """``run(model, omega0, q0, chunk_size, sort)`` over the batch in blocks of whole chunks, calling
    ``report(done_bodies, total_bodies)`` after each (None: no reports, one block per thread); the
    blocks' results assembled into one :class:`Trajectory`, equal to ``run`` over the whole batch.
    With ``threads`` > 1 the blocks run from that many Python threads at once."""
    if is_traced(model, omega0, q0, ts, args):
        raise ValueError(_TRACED)
    blocks_wanted = MAX_BLOCKS if report is not None else threads
    report = _ignore if report is None else report
    batch = batching.batch_shape(model, omega0, q0)
    n = int(np.prod(batch))
    # The chunks of the whole batch's program (which shards where ts has several samples).
    chunk, n_chunks, _ = batching.chunk_layout(n, chunk_size)
    if ts.shape[0] == 1 or n_chunks == 1:
        report(0, n)
        traj = jax.block_until_ready(run(model, omega0, q0, chunk_size, sort))
        report(n, n)
        return traj
    order = np.asarray(_chunk_order(model, omega0, q0, ts, args, formulation, chunk_size, bool(sort)))
    devices = jax.device_count()
    per_block = -(-n_chunks // blocks_wanted)
    per_block = -(-per_block // devices) * devices  # whole chunks per device
    n_blocks = -(-n_chunks // per_block)
    size = per_block * chunk
    # Padded with copies of the last body in chunk order, as the last chunk is padded.
    take = order[np.minimum(np.arange(n_blocks * size), n - 1)]
    # Every block's inputs gathered at once (they are small next to the trajectories). Threads run
    # on the CPU only, where NumPy gathers them without dispatching a JAX operation each.
    host = threads > 1
    xp = np if host else jnp
    take = xp.asarray(take)
    leaves, flat = batching.flatten_model(model, batch)
    flat = [xp.asarray(v)[take] for v in flat]
    omega_flat = xp.asarray(batching.flatten(omega0, batch))[take]
    q_flat = None if q0 is None else xp.asarray(batching.flatten(q0, batch))[take]

    def solve_block(b):
        index = slice(b * size, (b + 1) * size)
        return run(
            model.replace_body_leaves(leaves, [v[index] for v in flat]),
            omega_flat[index],
            None if q_flat is None else q_flat[index],
            chunk,
            False,
        )

    parts = []
    report(0, n)
    if threads > 1:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            # JAX's context managers (enable_x64, default_device, ...) hold per thread: where a
            # worker thread would trace in another context than this one, the blocks run here.
            if _same_jax_context(pool):
                futures = {
                    pool.submit(lambda b: jax.block_until_ready(solve_block(b)), b): b
                    for b in range(n_blocks)
                }
                parts = [None] * n_blocks
                done = 0
                try:
                    # Reported as blocks finish, not in order: the first block holds the fastest
                    # bodies (the most steps), and the others finished behind it unreported.
                    for future in concurrent.futures.as_completed(futures):
                        b = futures[future]
                        parts[b] = future.result()
                        done += min(n, (b + 1) * size) - min(n, b * size)
                        report(done, n)
                except BaseException:
                    # Ctrl-C: the blocks not yet started never start, and the running ones end first
                    # (a compiled computation still running when Python exits can crash it).
                    for future in futures:
                        future.cancel()
                    concurrent.futures.wait(futures)
                    raise
                return _assemble(parts, order, batch, n, n_chunks, model)
    for b in range(n_blocks + 1):
        if b < n_blocks:  # dispatched before the previous block is waited for: no idle gap
            parts.append(solve_block(b))
        if b > 0:
            jax.block_until_ready(parts[b - 1].omega)
            report(min(n, b * size), n)
    return _assemble(parts, order, batch, n, n_chunks, model)


def _assemble(parts, order, batch, n, n_chunks, model):
    """The blocks' results (bodies in chunk order, padded) back in the user's order and shape, in one
    compiled program. Joined with NumPy and then made a JAX array, 10^5 bodies at 101 samples spent
    0.88 s of a 2.4 s call in the copies (fresh host memory for each of three); here 0.2 s."""
    fields = (
        lambda p: p.omega,
        lambda p: p.orientation,
        lambda p: p.success,
        lambda p: p.stats["quaternion_norm_error"],
        lambda p: p.stats["result"],
        lambda p: p.stats["first_failed_sample"],
    )
    per_field = tuple(None if get(parts[0]) is None else tuple(get(p) for p in parts) for get in fields)
    steps = tuple(p.stats["num_steps"] for p in parts)
    joined, num_steps = _joined(per_field, steps, jnp.asarray(np.argsort(order)), batch, n, n_chunks)
    omega, orientation, success, q_norm_error, result, first_failed = joined
    stats = {
        "num_steps": num_steps,
        "chunk_size": parts[0].stats["chunk_size"],
        "quaternion_norm_error": q_norm_error,
        "result": result,
        "first_failed_sample": first_failed,
    }
    return Trajectory(
        ts=parts[0].ts, omega=omega, orientation=orientation, model=model, success=success, stats=stats
    )


@functools.partial(jax.jit, static_argnums=(3, 4, 5))
def _joined(per_field, steps, back, batch, n, n_chunks):
    def join(parts):
        x = jnp.concatenate(parts)[:n][back]
        return x.reshape(batch + x.shape[1:])

    joined = tuple(None if parts is None else join(parts) for parts in per_field)
    return joined, jnp.concatenate(steps)[:n_chunks]
