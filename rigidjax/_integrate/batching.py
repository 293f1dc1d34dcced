"""Per-body batching: a scene and a state with leading batch axes become flat per-body arrays
``(n, ...)``, are cut into chunks of bounded size, and are put back into the user's shape.

Every per-body array of a scene is described by its ``BodyLeaf`` (``model.body_leaves()``): its
trailing ``core`` axes belong to one body, the leading axes are batch axes that broadcast against
the state's. The integrator, the closed forms and :class:`rigidjax.Trajectory` all batch through
this module.

Chunks: bodies sorted by speed (torque-free bodies also by period) are cut into ``n_chunks`` chunks
of ``chunk`` bodies (the last one padded with copies of a real body, dropped again); chunks run
one after another in a loop that writes each chunk's results into the arrays of all the bodies
(:func:`map_chunks_into`: bounded memory for 10^6 bodies, and one copy of the results) and, with
several devices, are sharded across them.
"""

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

from .._dynamics.models import leaf_shape


def batch_shape(model, *state_arrays, names=("state0.omega", "state0.orientation")) -> tuple[int, ...]:
    """The broadcast batch shape of a scene and state arrays (each ``(..., k)``: one core axis).

    A ``ValueError`` (while tracing) when they do not broadcast, naming every per-body array with its
    shape and batch shape (``names`` names the state arrays, in order)."""
    named = []
    # Called by the class: equinox binds a method to its Module by building a Module (~40 us of
    # Python per call, as long as the closed form of 10^3 bodies takes).
    for leaf in type(model).body_leaves(model):
        shape = leaf_shape(model, leaf)
        named.append((f"model.{leaf.label}", shape, shape[: len(shape) - leaf.core]))
        _check_auto_sharding(leaf.get(model), f"model.{leaf.label}")
    for i, x in enumerate(state_arrays):
        if x is not None:
            name = names[i] if i < len(names) else f"state array {i}"
            named.append((name, tuple(x.shape), tuple(x.shape[:-1])))
            _check_auto_sharding(x, name)
    try:
        return tuple(jnp.broadcast_shapes(*[batch for _, _, batch in named]))
    except ValueError:
        pass
    arrays = "; ".join(f"{name} has shape {shape} (batch {batch})" for name, shape, batch in named)
    raise ValueError(
        f"The batch shapes of the model and the state do not broadcast: {arrays}. Leading axes are "
        "batch axes and must broadcast against each other as NumPy's do: e.g. inertia (N, 3) with "
        "omega (N, 3) for N bodies, or one inertia (3,) shared by omega (N, 3)."
    )


def _check_auto_sharding(x, name: str) -> None:
    """A ``ValueError`` naming ``name`` when ``x`` is sharded over an ``Explicit`` mesh axis, which
    the sorting and the chunks' ``shard_map`` cannot take (JAX's raw errors named neither)."""
    if not isinstance(x, jax.Array):
        return
    if not isinstance(x, jax.core.Tracer):
        if not isinstance(x.sharding, NamedSharding):  # one device: the common case, ~0.3 us
            return
    sharding = jax.typeof(x).sharding
    axes = {
        a
        for entry in sharding.spec
        if entry is not None
        for a in (entry if isinstance(entry, tuple) else (entry,))
    }
    kinds = dict(zip(sharding.mesh.axis_names, sharding.mesh.axis_types, strict=True))
    explicit = sorted(a for a in axes if kinds.get(a) == AxisType.Explicit)
    if explicit:
        raise ValueError(
            f"simulate: {name} is sharded over the Explicit mesh axis {explicit[0]!r} (jax.make_mesh "
            "makes Explicit axes by default); simulate spreads the bodies itself and needs Auto axes: "
            f"jax.make_mesh(shape, names, axis_types=(jax.sharding.AxisType.Auto,) * len(names))."
        )


def flatten(x, batch: tuple[int, ...], core_ndim: int = 1):
    """``x`` broadcast to ``batch + core`` and reshaped to ``(n, *core)``."""
    core = x.shape[x.ndim - core_ndim :]
    return jnp.broadcast_to(x, batch + core).reshape((math.prod(batch),) + core)


def flatten_model(model, batch: tuple[int, ...], dtype=None):
    """The scene's per-body arrays as a list of ``(n, *core)`` arrays, in ``model.body_leaves()``
    order; cast to ``dtype`` when given."""
    leaves = model.body_leaves()
    flat = []
    for leaf in leaves:
        value = flatten(jnp.asarray(leaf.get(model)), batch, leaf.core)
        flat.append(value if dtype is None else value.astype(dtype))
    return leaves, flat


def body_model(model, leaves, values):
    """The scene of one body (or one chunk), from its per-body arrays."""
    return model.replace_body_leaves(leaves, values)


def model_per_time(model, batch: tuple[int, ...]):
    """The scene with a length-1 time axis after its batch axes, to broadcast over ``(..., T, ...)``
    samples."""
    leaves = model.body_leaves()
    values = []
    for leaf in leaves:
        value = jnp.asarray(leaf.get(model))
        value = jnp.broadcast_to(value, batch + value.shape[value.ndim - leaf.core :])
        values.append(jnp.expand_dims(value, len(batch)))
    return model.replace_body_leaves(leaves, values)


class ChunkPlan(NamedTuple):
    """How ``n`` bodies are cut into ``n_chunks`` chunks of ``chunk`` bodies."""

    n: int
    chunk: int
    n_chunks: int
    order: Any  # body index in chunk order (fastest first when sorted)
    shard: bool  # chunks are spread over several devices
    sorted: bool = False  # False: ``order`` is the identity and no gather is needed


def chunk_layout(n: int, chunk_size: int, *, shardable: bool = True) -> tuple[int, int, bool]:
    """``(chunk, n_chunks, sharded)`` for ``n`` bodies in chunks of at most ``chunk_size``: the fewest
    chunks, all of one size, as even as possible, so that the padding stays under one body per
    chunk. With several devices the chunk count is then rounded up to a multiple of the device count
    with chunks of padding, so that the chunks, and the trajectories, are those of one device. On
    an H200, 10^5 tennis-racket bodies, "balanced": two chunks of 65536 (31072 of them padding)
    0.069 s against one chunk of 10^5 0.059 s in one run, two chunks of 50000 0.064 s against
    0.061 s in another (``benchmarks/results/accelerator.gpu*.json``)."""
    n_chunks = -(-n // min(chunk_size, n))
    chunk = -(-n // n_chunks)
    n_devices = jax.device_count()
    shard = shardable and n_devices > 1 and n_chunks > 1
    if shard:
        n_chunks = -(-n_chunks // n_devices) * n_devices
    return chunk, n_chunks, shard


def plan_chunks(n: int, chunk_size: int, sort_keys=None, *, shardable: bool = True) -> ChunkPlan:
    """Plans chunks of at most ``chunk_size`` bodies; with ``sort_keys``, a tuple of ``(n,)`` keys
    (the last one primary, as in ``jnp.lexsort``), the bodies are ordered by increasing keys so that
    bodies that need similar steps at the same times share a chunk and its step size. With several
    devices the chunk count is a multiple of the device count (whole chunks per device)."""
    chunk, n_chunks, shard = chunk_layout(n, chunk_size, shardable=shardable)
    if sort_keys is not None and n_chunks > 1:
        return ChunkPlan(n, chunk, n_chunks, lexsort(sort_keys), shard, sorted=True)
    return ChunkPlan(n, chunk, n_chunks, jnp.arange(n), shard)


def to_chunks(plan: ChunkPlan, x):
    """``(n, ...)`` -> ``(n_chunks, chunk, ...)`` in chunk order, padding with copies of a body."""
    if x is None:
        return None
    padded = plan.n_chunks * plan.chunk
    if plan.sorted:
        x = x[plan.order[jnp.minimum(jnp.arange(padded), plan.n - 1)]]
    elif padded > plan.n:
        x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (padded - plan.n,) + x.shape[1:])])
    return x.reshape((plan.n_chunks, plan.chunk) + x.shape[1:])


def from_chunks(plan: ChunkPlan, x):
    """``(n_chunks, chunk, ...)`` -> ``(n, ...)`` in the user's body order, padding dropped."""
    if x is None:
        return None
    x = x.reshape((plan.n_chunks * plan.chunk,) + x.shape[2:])[: plan.n]
    if not plan.sorted:
        return x
    return x[inverse_permutation(plan.order)]


def lexsort(keys):
    """``jnp.lexsort(keys)``: the order by the last key, ties by the one before, ..., then by index
    (where ``jnp.lexsort`` puts every NaN last, here one with its sign bit set comes first; -0 comes
    before 0).

    One stable pass per 32-bit word of each key, least significant first, each a sort of single
    64-bit integers (the word above the position): XLA's sorts of several operands compare through
    a comparator call each, 5-8x slower on CPU (10^4 bodies: ``jnp.lexsort`` of 3 keys 2.7 ms,
    ``jnp.argsort`` 1.6 ms, ``jnp.sort`` of int64 0.26 ms). Without 64-bit types (``jax_enable_x64``
    off) or beyond 2^31 bodies, ``jnp.lexsort`` itself."""
    n = keys[0].shape[0]
    if not jax.config.jax_enable_x64 or n >= 2**31:
        return jnp.lexsort(keys)
    position = jnp.arange(n, dtype=jnp.uint64)
    order = None
    for key in keys:
        for word in _ordered_words(key):  # each pass stable in the order of the previous ones
            word = word if order is None else word[order]
            packed = jnp.sort((word.astype(jnp.uint64) << 32) | position)
            step = (packed & 0xFFFFFFFF).astype(jnp.int32)
            order = step if order is None else order[step]
    return order


def _ordered_words(key):
    """``key`` as uint32 words, least significant first, whose lexicographic order (most
    significant word first) is the key's order: a float's bits with the sign bit set where it is
    positive and all bits flipped where it is negative (NaN above inf, -0 below 0), a signed
    integer's with the sign bit flipped."""
    if key.dtype == jnp.bool_:
        key = key.astype(jnp.int32)
    elif jnp.issubdtype(key.dtype, jnp.floating) and jnp.dtype(key.dtype).itemsize < 4:
        key = key.astype(jnp.float32)  # exact
    wide = jnp.dtype(key.dtype).itemsize == 8
    unsigned = jnp.uint64 if wide else jnp.uint32
    sign = unsigned(1 << (63 if wide else 31))
    if jnp.issubdtype(key.dtype, jnp.floating):
        bits = jax.lax.bitcast_convert_type(key, unsigned)
        bits = jnp.where((bits & sign) != 0, ~bits, bits | sign)
    elif jnp.issubdtype(key.dtype, jnp.unsignedinteger):
        bits = key.astype(unsigned)
    else:
        bits = jax.lax.bitcast_convert_type(key.astype(jnp.int64 if wide else jnp.int32), unsigned) ^ sign
    if not wide:
        return [bits.astype(jnp.uint32)]
    return [(bits & 0xFFFFFFFF).astype(jnp.uint32), (bits >> 32).astype(jnp.uint32)]


def inverse_permutation(order):
    """The permutation that undoes ``order`` (``order[inverse[i]] == i``), by a scatter rather than a
    second sort."""
    return jnp.zeros_like(order).at[order].set(jnp.arange(order.shape[0], dtype=order.dtype))


def map_chunks(fn: Callable, chunks, shared, plan: ChunkPlan):
    """``fn(chunk, shared)`` for every chunk: one after another with ``lax.map``, and across devices
    with ``shard_map`` when the plan shards. ``shared`` (arrays only) is passed explicitly, not
    closed over, so that the same function runs under both."""

    def run(chunks, shared):
        return jax.lax.map(lambda c: fn(c, shared), chunks)

    if plan.shard:
        mesh = jax.make_mesh((jax.device_count(),), ("bodies",), axis_types=(AxisType.Auto,))
        chunks = jax.lax.with_sharding_constraint(chunks, NamedSharding(mesh, P("bodies")))
        run = jax.shard_map(
            run, mesh=mesh, in_specs=(P("bodies"), P()), out_specs=P("bodies"), check_vma=False
        )
    return run(chunks, shared)


def map_chunks_into(fn: Callable, chunks, shared, plan: ChunkPlan):
    """``fn(chunk, shared) -> (per_body, per_chunk)`` for every chunk, returning ``per_body``'s arrays
    for all the bodies ``(n, ...)`` in the user's order and ``per_chunk``'s ``(n_chunks, ...)``.

    On one device the chunks run one after another in a loop that writes each chunk's bodies into
    the output arrays where they belong (a scatter, in place; the padding is dropped). Stacking the
    chunks' results (``lax.map``) and putting them back in the bodies' order afterwards held a second
    copy of every sample. Sharded plans run :func:`map_chunks` and :func:`from_chunks`."""
    if plan.shard:
        per_body, per_chunk = map_chunks(fn, chunks, shared, plan)
        return jax.tree.map(lambda x: from_chunks(plan, x), per_body), per_chunk
    padded = plan.n_chunks * plan.chunk
    slots = jnp.arange(padded, dtype=plan.order.dtype)
    # Each slot's body, a distinct index beyond the bodies for the padding (dropped by the scatter).
    bodies = jnp.where(slots < plan.n, plan.order[jnp.minimum(slots, plan.n - 1)], slots)
    bodies = bodies.reshape(plan.n_chunks, plan.chunk)
    first = jax.tree.map(lambda x: x[0], chunks)
    # jit's trace cache: the loop's call below reuses the trace that gives the output shapes.
    fn = jax.jit(fn)
    per_body_shape, per_chunk_shape = jax.eval_shape(fn, first, shared)
    outputs = (
        jax.tree.map(lambda s: jnp.zeros((plan.n,) + s.shape[1:], s.dtype), per_body_shape),
        jax.tree.map(lambda s: jnp.zeros((plan.n_chunks,) + s.shape, s.dtype), per_chunk_shape),
    )

    def one_chunk(i, outputs):
        chunk = jax.tree.map(lambda x: x[i], chunks)
        per_body, per_chunk = fn(chunk, shared)
        into = bodies[i]
        return (
            jax.tree.map(
                lambda whole, part: whole.at[into].set(part, mode="drop", unique_indices=True),
                outputs[0],
                per_body,
            ),
            jax.tree.map(lambda whole, part: whole.at[i].set(part), outputs[1], per_chunk),
        )

    return jax.lax.fori_loop(0, plan.n_chunks, one_chunk, outputs)
