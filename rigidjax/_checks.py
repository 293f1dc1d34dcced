"""Input checks shared by every public entry point: dtypes, shapes, finiteness, unit quaternions,
rotation matrices and sample times.

Two kinds of error, as everywhere in rigidjax: shape and dtype problems raise ``ValueError`` /
``TypeError`` while tracing; value problems (NaN, a non-unit quaternion, decreasing times) are
``eqx.error_if`` checks that work under ``jit`` and ``vmap``. Messages name the argument.
"""

import contextlib
import functools
import inspect
from collections.abc import Collection, Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._numerics import short_norm, short_sum

_COMPUTED_FLOATS = (np.dtype(np.float32), np.dtype(np.float64))


def as_float_array(x, name: str = "array"):
    """Converts ``x`` to a JAX float array, keeping a float32/float64 dtype if it has one.

    Integer inputs become the default float dtype. Complex and boolean input is rejected with a
    ``TypeError`` naming ``name`` (a boolean array where numbers are expected is a mistake, not data).
    Half-precision floats (float16, bfloat16) become float32, as in ``scipy.special``: rigidjax
    computes in float32 and float64, whose accuracy it measures (in float16 a quaternion's norm is
    off by 1e-3).
    """
    if isinstance(x, jax.Array) and x.dtype in _COMPUTED_FLOATS:
        return x  # the common case, without jnp.asarray's cost (~20 us a call)
    try:
        x = jnp.asarray(x)
    except (TypeError, ValueError) as error:
        raise TypeError(
            f"{name} must be a real number or array of them, got {type(x).__name__} {x!r:.60}."
        ) from error
    if not (jnp.issubdtype(x.dtype, jnp.number) or x.dtype == jnp.bool_):
        raise TypeError(f"{name} must be a real number or array of them, got dtype {x.dtype}.")
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise TypeError(f"{name} must be real, got dtype {x.dtype}.")
    if x.dtype == jnp.bool_:
        raise TypeError(f"{name} must be a real number array, got dtype bool.")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    elif jnp.finfo(x.dtype).bits < 32:
        x = x.astype(jnp.float32)
    return x


def common_float(*arrays, names=None):
    """Converts all inputs to float arrays of one common dtype (the widest float among them)."""
    names = names or [f"argument {i}" for i in range(len(arrays))]
    # Python numbers take the arrays' dtype (as in NumPy and JAX): ellipj(float32 u, 0.5) stays
    # float32. Among arrays, numpy's promotion, not jax's: widening float32 to float64 here is
    # deliberate, and must not depend on the user's jax_numpy_dtype_promotion setting.
    # Weakly typed arrays count as Python numbers: a Python time or scalar made an array on its way
    # into a compiled program keeps taking the other arguments' dtype.
    python_number = [
        (isinstance(a, int | float) and not isinstance(a, bool)) or bool(getattr(a, "weak_type", False))
        for a in arrays
    ]
    arrays = [as_float_array(a, n) for a, n in zip(arrays, names, strict=True)]
    decide = [a for a, number in zip(arrays, python_number, strict=True) if not number] or arrays
    dtype = np.result_type(*[np.dtype(a.dtype) for a in decide])
    return [a.astype(dtype) for a in arrays]


def check_last_axis(x, size: int, name: str):
    if x.ndim < 1 or x.shape[-1] != size:
        raise ValueError(f"{name} must have shape (..., {size}), got shape {tuple(x.shape)}.")


def check_last_two_axes(x, name: str):
    if x.ndim < 2 or x.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got shape {tuple(x.shape)}.")


def check_batch_shapes(where: str, *arrays) -> tuple[int, ...]:
    """The broadcast batch shape of ``arrays``, ``(name, array, core)`` triples whose last ``core``
    axes are not batch axes (0 for a scalar, 1 for a vector, 2 for a tensor; ``array`` may be None).
    A ``ValueError`` while tracing, naming every argument with its shape, when they do not broadcast."""
    named = [(name, tuple(jnp.shape(x)), core) for name, x, core in arrays if x is not None]
    batches = [shape[: len(shape) - core] for _, shape, core in named]
    try:
        return tuple(np.broadcast_shapes(*batches))
    except ValueError:
        listing = ", ".join(
            f"{name} {shape} (batch {batch})" for (name, shape, _), batch in zip(named, batches, strict=True)
        )
        raise ValueError(
            f"{where}: the batch shapes of the arguments do not broadcast: {listing}. Batch axes are "
            "matched from the right, as in NumPy broadcasting; to pair every element of one batch with "
            "every element of another, add axes of size 1 (e.g. x[:, None])."
        ) from None


def is_tensor_shape(shape) -> bool:
    """An inertia's shape rule: ``(..., 3, 3)`` is a tensor per body, else principal moments."""
    return len(shape) >= 2 and tuple(shape[-2:]) == (3, 3)


def is_full_tensor(inertia, name: str = "inertia") -> bool:
    """True when ``inertia`` is a ``(..., 3, 3)`` tensor, False for principal moments ``(..., 3)``;
    a ``ValueError`` naming ``name`` for any other shape."""
    shape = jnp.shape(inertia)
    if is_tensor_shape(shape):
        return True
    if len(shape) >= 1 and shape[-1] == 3:
        return False
    raise ValueError(
        f"{name} must be principal moments of shape (..., 3) or a tensor of shape (..., 3, 3) "
        f"(kg m^2), got shape {tuple(shape)}."
    )


# --- run-time value checks of the public functions (eqx.error_if: they work under jit and vmap) ----

# While a program is traced inside collected_failures(), the checks below record their conditions
# instead of wrapping values in eqx.error_if: the program then holds no host callback (which JAX's
# persistent compilation cache cannot keep), returns the conditions, and the caller raises from them.
_collected: list | None = None


@contextlib.contextmanager
def collected_failures():
    """Within this context the checks record ``(condition, index, messages)`` in the yielded list
    rather than adding ``eqx.error_if`` to the traced program; :func:`raise_collected` raises from it."""
    global _collected
    outer, _collected = _collected, []
    try:
        yield _collected
    finally:
        _collected = outer


def is_traced(*trees) -> bool:
    """Whether any array in ``trees`` is a tracer (the user's jit, grad or vmap): no values to check."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(trees))


def evaluated_now(function, *args):
    """``function(*args)`` on arguments that have values, with values: called as it is, or, where the
    call is being traced (the user's ``jit`` closing over the arguments, which are constants of its
    program), called again under ``jax.ensure_compile_time_eval`` (the traced call's result is
    unused and leaves the program). Only there: the context's programs are cached apart from the
    others' (an eager call would compile them twice)."""
    out = function(*args)
    if is_traced(out):
        with jax.ensure_compile_time_eval():
            out = function(*args)
    return out


class _NoValue(Exception):
    pass


def _value(x):
    if not isinstance(x, jax.core.Tracer):
        return x
    value = getattr(x, "to_concrete_value", lambda: None)()
    if value is None:
        raise _NoValue
    return value


def known_values(tree):
    """``tree`` with each tracer replaced by its value, or ``None`` when some tracer has none.

    Outside ``jit`` and ``vmap`` the tracers of ``grad``, ``jvp``, ``jacfwd`` and ``jacrev`` carry
    their primal values: those inputs can be checked like concrete ones, with a ``ValueError`` and
    without a host callback in the differentiated program.
    """
    try:
        return jax.tree_util.tree_map(_value, tree)
    except _NoValue:
        return None


@contextlib.contextmanager
def checks_done():
    """Within this context the checks add nothing to the traced program: the caller has checked the
    same values already (a program traced here holds no host callback for them)."""
    with collected_failures():
        yield


def packed_failures(failures) -> tuple:
    """The conditions recorded by :func:`collected_failures`, packed in the program that computed them
    for :func:`raise_collected`: one ``int32`` array (per condition ``-1`` where it does not hold,
    else the index of its message) and the messages. One array is one transfer to the host (each
    array read back is a transfer of its own, ~0.1 ms on CPU).

    The conditions are recorded unreduced and reduced here, those of one size together: reduced one
    by one, each was an XLA kernel of its own, and every kernel is compiled code (the checks of a
    heavy-top scene: 34 kernels, 0.45 s to compile)."""
    if not failures:
        return None, ()
    # One reduction per size: conditions of the same number of elements are stacked and reduced
    # together (a reduction each was a kernel each).
    by_size = {}
    for k, (condition, index, _) in enumerate(failures):
        code = jnp.ravel(jnp.where(condition, 0 if index is None else index, -1).astype(jnp.int8))
        by_size.setdefault(code.size, []).append((k, code))
    order, largest = [], []
    for size, group in by_size.items():
        order += [k for k, _ in group]
        if size == 0:  # an empty batch: nothing fails
            largest.append(jnp.full((len(group),), -1, jnp.int8))
        else:
            largest.append(jnp.max(jnp.stack([code for _, code in group]), axis=1))
    codes = jnp.concatenate(largest)[np.argsort(order)].astype(jnp.int32)
    return codes, tuple(messages for _, _, messages in failures)


def raise_collected(packed) -> None:
    """Raises ``ValueError`` with the message of the first recorded condition that holds
    (``packed``: from :func:`packed_failures`)."""
    codes, messages = packed
    if codes is None:
        return
    for code, texts in zip(np.asarray(codes).tolist(), messages, strict=True):
        if code >= 0:
            raise ValueError(texts[code])


def error_if(x, condition, message: str):
    """``eqx.error_if``, or a recorded condition inside :func:`collected_failures`. A condition with
    a value (an eager call, also under eager ``grad``) is checked here and raises ``ValueError``: no
    program of its own to compile for each shape and message."""
    if _collected is not None:
        _collected.append((jnp.asarray(condition), None, (message,)))
        return x
    if not isinstance(condition, jax.core.Tracer):
        if np.any(np.asarray(condition)):
            raise ValueError(message)
        return x
    return eqx.error_if(x, condition, message)


def branched_error_if(x, condition, index, messages):
    """``eqx.branched_error_if``, or a recorded condition inside :func:`collected_failures`; checked
    here (``ValueError``) when the condition has a value, as in :func:`error_if`."""
    if _collected is not None:
        _collected.append((jnp.asarray(condition), jnp.max(index), tuple(messages)))
        return x
    if not isinstance(condition, jax.core.Tracer) and not isinstance(index, jax.core.Tracer):
        if np.any(np.asarray(condition)):
            raise ValueError(messages[int(np.max(np.asarray(index)))])
        return x
    return eqx.branched_error_if(x, condition, index, messages)


def floats_as_arrays(tree, *, ints: bool = False):
    """``tree`` with its Python and NumPy floating-point scalars as JAX arrays (of their own
    precision; Python's weakly typed). Passed to ``eqx.filter_jit`` they were static arguments, so
    each new value (a sweep of a torque's gain) compiled the whole program again; as arrays they are
    traced. Bools stay Python values, and so do ints unless ``ints``: a user's code may branch on
    them or use them as counts."""
    kinds = "iufc" if ints else "fc"

    def convert(x):
        if isinstance(x, bool | np.bool_):
            return x
        if isinstance(x, float | complex) or (isinstance(x, np.generic) and x.dtype.kind in kinds):
            return jnp.asarray(x)
        if ints and isinstance(x, int):
            return jnp.asarray(x)
        return x

    return jax.tree.map(convert, tree)


@functools.cache
def compiled_once(function):
    """``jax.jit(function)``, one for each function: a public function called eagerly then compiles
    once per shape and dtype. Called op by op, its loops (``lax.scan``, ``fori_loop``) were traced and
    compiled again at every call (0.1 to 0.3 s each), their bodies closing over the call's arrays."""
    return jax.jit(function)


def call_checked(program, failures, *args, names: tuple[str, ...]):
    """``program(*args, checked=...)`` with its inputs' value checks done where they cost least.

    Inputs with values (concrete, or the primal values of an eager ``grad`` or ``jvp``) are checked by
    ``failures(*values)``, a compiled function that returns the recorded conditions (see
    :func:`collected_failures`); a failed one raises ``ValueError`` here and ``program`` runs with
    ``checked=False``. Neither program then holds a host callback, so JAX's persistent compilation
    cache keeps both and a new process compiles nothing. Inputs without values (the user's ``jit``
    or ``vmap``) run ``program`` with ``checked=True``: ``eqx.error_if`` checks in the program.
    """
    # A Python number, or a list of them, would be static arguments of the programs (equinox's
    # filter_jit): each new value (t = 0.1 k in a loop) compiled both again, 1-3 s a call, and a list
    # of times reached the programs' array code as a list. As arrays they are traced.
    args = tuple(
        floats_as_arrays(a, ints=True)
        if _is_scalar(a)
        else as_float_array(a, name)
        if isinstance(a, list | tuple)
        else a
        for a, name in zip(args, names, strict=True)
    )
    values = known_values(args)
    if values is None:
        return program(*args, checked=True)
    raise_collected(evaluated_now(failures, *values))
    return program(*args, checked=False)


def _is_scalar(x) -> bool:
    return isinstance(x, int | float | complex | np.generic)


class StaticValue(eqx.Module):
    """Python values (message texts, ints, None) carried through ``jax.jit``'s output structure
    rather than as arrays: the structure is fixed when the program is traced."""

    value: Any = eqx.field(static=True)


def _carries_value(x) -> bool:
    """A tracer of an eager ``grad``, ``vjp`` or ``jvp``, which carries its primal value (not one of
    ``jit`` or ``vmap``)."""
    return isinstance(x, jax.core.Tracer) and known_values(x) is not None


def _has_value(x) -> bool:
    """An argument that an eager call passes as it is and a compiled program takes as an array."""
    if isinstance(x, jax.core.Tracer) or isinstance(x, bool | np.bool_):
        return False
    if isinstance(x, np.ndarray | np.generic):
        return x.dtype.kind in "biufc"  # others (strings, objects) get the function's own message
    if isinstance(x, eqx.Module):  # a State: a pytree of arrays only (no functions, no options)
        leaves = jax.tree_util.tree_leaves(x)
        return all(isinstance(leaf, jax.Array | np.ndarray) and _has_value(leaf) for leaf in leaves)
    return x is None or isinstance(x, jax.Array | int | float)


def compiled_when_eager(
    function=None,
    *,
    static_argnames: tuple[str, ...] = (),
    case_insensitive: Mapping[str, Collection[str]] | None = None,
):
    """``function`` (a public, checked function) as one compiled program when called eagerly.

    Called op by op, each of its operations (the checks' reductions, each component of a formula)
    compiled a program of its own for every new shape: ``check_inertia`` of a new tensor compiled 78
    of them (2.7 s; ``benchmarks/eager_calls.py``). Called with arrays or numbers that have values,
    it runs as one ``jax.jit`` traced inside :func:`collected_failures`: the checks' conditions come
    back with the result and a failed one raises ``ValueError`` here, with the message it raises
    otherwise. The tracers of an eager ``grad`` or ``jvp`` carry values: the program is
    differentiated as a whole, its conditions checked the same way. Traced arguments without values
    (the user's ``jit`` or ``vmap``), values that are constants of the user's ``jit``, other argument
    types (lists, ...), and calls inside another compiled check run ``function`` as it is.

    ``static_argnames``: arguments that are Python values (names in messages, options), part of the
    program rather than its inputs; another type there (an array) also runs ``function`` as it is,
    which names the problem. ``case_insensitive``: static string arguments that mean the same in any
    case (Euler sequences), with their lower-case values: a valid value in any case, or the default,
    is passed lower-cased, so that ``"ZXZ"``, ``"zxz"`` and no argument share one program (an invalid
    one as it is, for the message)."""
    case_insensitive = dict(case_insensitive or {})
    if function is None:
        return functools.partial(
            compiled_when_eager, static_argnames=static_argnames, case_insensitive=case_insensitive
        )

    signature = inspect.signature(function)

    @functools.partial(jax.jit, static_argnames=static_argnames)
    def program(**arguments):
        with collected_failures() as failures:
            out = function(**arguments)
        codes, messages = packed_failures(failures)
        arrays, static = eqx.partition(out, eqx.is_array)
        return arrays, codes, StaticValue((static, messages))

    @functools.wraps(function)
    def called(*args, **kwargs):
        try:
            arguments = signature.bind(*args, **kwargs).arguments
        except TypeError:
            return function(*args, **kwargs)  # which names the missing or unexpected argument
        dynamic = [v for k, v in arguments.items() if k not in static_argnames]
        static = [v for k, v in arguments.items() if k in static_argnames]
        if (
            _collected is not None
            or not all(_has_value(x) or _carries_value(x) for x in dynamic)
            or not all(isinstance(v, str | int | float | None) for v in static)
        ):
            return function(*args, **kwargs)
        for name, choices in case_insensitive.items():
            value = arguments.get(name, signature.parameters[name].default)
            if (
                isinstance(value, str)
                and value.lower() in choices
                and value in (value.lower(), value.upper())
            ):
                arguments[name] = value.lower()  # (a mix of cases is left to the function to refuse)
        arrays, codes, out_static = program(**arguments)
        # The tracers of an eager grad or jvp: the program is differentiated as a whole (op by op,
        # each operation was a program of its own: 34 for euler_from_quat's gradient), and its
        # conditions come back with values.
        carried = any(_carries_value(x) for x in dynamic)
        if is_traced(codes):
            codes = known_values(codes)
            if codes is None:
                # Constants of the user's jit: the program above leaves it unused, and the checks go
                # into the user's program as they would without this wrapper.
                return function(*args, **kwargs)
        elif is_traced(arrays) and not carried:
            return function(*args, **kwargs)
        out_static, messages = out_static.value
        raise_collected((codes, messages))
        return eqx.combine(arrays, out_static)

    return called


def unit_tolerance(dtype) -> float:
    """How far ``R R^T`` may be from ``1`` for a matrix to count as a rotation: ``1e-6`` in float64,
    ``1e-4`` in lower precision. The same tolerance as :func:`rigidjax.simulate` uses for the norm of
    ``state0.orientation``."""
    return 1e-6 if np.dtype(dtype) == np.float64 else 1e-4


def check_finite(x, name: str, where: str):
    """``x`` wrapped in a run-time check that all its entries are finite."""
    return error_if(x, ~jnp.isfinite(x), f"{where}: {name} contains NaN or inf.")


def check_rotation_quaternion(q, name: str, where: str):
    """``q`` wrapped in run-time checks: finite, and with a norm that can be divided by (``|q|^2``
    neither 0 nor under- or overflowing). Such a ``q`` means the rotation of ``q / |q|``."""
    q = check_finite(q, name, where)
    sq = short_sum(q * q)
    return error_if(
        q,
        ~jnp.isfinite(sq) | (sq < np.finfo(q.dtype).tiny),
        f"{where}: {name} has zero norm (or one whose square under- or overflows): it is not a "
        "rotation. A rotation is a unit quaternion (w, x, y, z), e.g. (1, 0, 0, 0) for the identity.",
    )


def check_rotation_matrix(R, name: str, where: str):
    """``R`` wrapped in run-time checks: finite, ``max|R R^T - 1| <= unit_tolerance`` and ``det R > 0``."""
    R = check_finite(R, name, where)
    tol = unit_tolerance(R.dtype)
    gram = jnp.einsum("...ij,...kj->...ik", R, R)
    off = jnp.max(jnp.abs(gram - jnp.eye(3, dtype=R.dtype)), axis=(-2, -1))
    R = error_if(
        R,
        off > tol,
        f"{where}: {name} is not a rotation matrix (max |{name} {name}^T - 1| > {tol:g}); "
        "orthonormalise it first (e.g. the polar factor U V^T of its SVD).",
    )
    return error_if(
        R,
        jnp.linalg.det(R) <= 0,
        f"{where}: {name} has determinant -1: it is a reflection, not a rotation.",
    )


# --- the dtype rule, sample times, states and scenes ---------------------------------------------


def is_positive_int(value) -> bool:
    """Whether ``value`` is a positive integer: a Python or NumPy integer, not a ``bool``."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_) and value >= 1


def check_callable(function, name: str, call: str, count: int) -> None:
    """A ``TypeError`` naming ``name`` and showing ``call`` (how it is called) unless ``function`` is
    callable with ``count`` positional arguments; one whose signature cannot be read (builtins, some
    C callables) passes. A wrong signature would otherwise fail only when first called, after the
    work before it (a fit's compile)."""
    if callable(function):
        try:
            signature = inspect.signature(function)
        except (TypeError, ValueError):
            return
        try:
            signature.bind(*([None] * count))
            return
        except TypeError:
            shown = f"{getattr(function, '__qualname__', type(function).__name__)}{signature}"
    else:
        shown = repr(function)
    raise TypeError(f"{name} must be callable as {call}, got {shown}.")


def check_flag(value, name: str, where: str | None, *, none: bool = False) -> bool | None:
    """``value`` as a Python ``bool`` if it is ``True`` or ``False`` (``None`` too where ``none``);
    a ``TypeError`` naming ``name`` (after ``where``, the function, when given) otherwise: a string
    such as ``"no"`` or a number would silently read as true or false."""
    if none and value is None:
        return None
    if not isinstance(value, bool | np.bool_):
        allowed = "True, False or None" if none else "True or False"
        prefix = f"{where}: " if where else ""
        raise TypeError(f"{prefix}{name} must be {allowed}, got {value!r}.")
    return bool(value)


def check_positive_int(value, name: str, where: str):
    """``value`` as a Python ``int`` if it is a positive integer (:func:`is_positive_int`); a
    ``ValueError`` naming ``name`` otherwise. ``None`` passes through (the caller's default)."""
    if value is None:
        return None
    if not is_positive_int(value):
        raise ValueError(f"{where}: {name} must be a positive integer or None, got {value!r}.")
    return int(value)


def float_dtype(*xs):
    """The one dtype rule of rigidjax's entry points: the widest floating dtype among the inputs'
    (NumPy promotion: float32 with float64 is float64, whatever ``jax_numpy_dtype_promotion`` says),
    weakly typed ones (Python numbers) counting only when no other input is floating; the default
    float when no input is floating (integers)."""
    arrays = [x if isinstance(x, jax.Array) else jnp.asarray(x) for x in xs if x is not None]
    floats = [x for x in arrays if np.issubdtype(np.dtype(x.dtype), np.floating)]
    # Weakly typed values (Python numbers, a default such as gravity=9.81) take the others' dtype:
    # a float32 scene with the default gravity stays float32.
    strong = [x for x in floats if not getattr(x, "weak_type", False)] or floats
    return (
        np.result_type(*[np.dtype(x.dtype) for x in strong]) if strong else np.dtype(jnp.result_type(float))
    )


def check_times_shape(ts, name: str = "ts"):
    """``ts`` as a JAX array, with trace-time errors: a ``TypeError`` unless its values are real
    numbers (complex times lost their imaginary part, booleans ran as 0 and 1 s, text failed inside
    NumPy), a ``ValueError`` unless it is 1-D with at least one time or where times that increase as
    given collapse in JAX's dtype (float64 NumPy times with 64-bit mode off)."""
    if isinstance(ts, jax.Array):
        given = ts
    else:
        try:
            given = np.asarray(ts)
        except (TypeError, ValueError):
            given = np.asarray(None)
    if not (jnp.issubdtype(given.dtype, jnp.floating) or jnp.issubdtype(given.dtype, jnp.integer)):
        raise TypeError(
            f"{name} must be real sample times in seconds (integers or floats), got "
            f"{type(ts).__name__} of dtype {given.dtype}."
        )
    if given.ndim != 1 or given.shape[0] < 1:
        raise ValueError(f"{name} must be a 1-D array of at least one time, got shape {tuple(given.shape)}.")
    return given if isinstance(given, jax.Array) else times_in_dtype(given, None)


def times_in_dtype(ts, dtype):
    """``ts`` as a JAX array in ``dtype`` (None: JAX's own for it); a ``ValueError`` where times that
    increase as given round to equal or decreasing ones there (float64 times 1e5 + 1e-3 apart in
    float32: the check of increasing times then blamed the user's times)."""
    cast = jnp.asarray(ts, dtype)
    if cast.dtype != ts.dtype and ts.shape[0] > 1 and not is_traced(ts):
        given, run = np.asarray(ts), np.asarray(cast)
        if np.all(np.diff(given) > 0) and not np.all(np.diff(run) > 0):
            raise ValueError(
                f"simulate: ts increase in {given.dtype} but not once cast to {run.dtype}, the dtype of "
                "the run (of the model and state0, or JAX's 32-bit mode): neighbouring times round to "
                "the same value. Give the model and state0 in float64 (with jax_enable_x64), or measure "
                "the times from ts[0]."
            )
    return cast


def check_times(ts, where: str, name: str = "ts"):
    """``ts`` wrapped in run-time checks: finite and strictly increasing (``ts[0]`` is the initial
    time)."""
    ts = check_finite(ts, name, where)
    if ts.shape[0] > 1:
        ts = error_if(
            ts,
            jnp.diff(ts) <= 0,
            f"{where}: {name} must be strictly increasing (found a decreasing or repeated time); "
            f"{name}[0] is the initial time.",
        )
    return ts


def check_unit_quaternion(q, name: str, where: str):
    """``q`` wrapped in run-time checks (finite, ``| |q| - 1 |`` within :func:`unit_tolerance`) and
    divided by its norm, so that roundoff in a user's quaternion does not enter the motion."""
    q = check_finite(q, name, where)
    tol = unit_tolerance(q.dtype)
    norm = short_norm(q, keepdims=True)
    q = error_if(
        q,
        jnp.abs(norm - 1.0) > tol,
        f"{where}: {name} is not a unit quaternion (| |q| - 1 | > {tol:g}); normalise it "
        "(rigidjax.quat_normalize) or build it with quat_from_euler / quat_from_matrix.",
    )
    return q / norm
