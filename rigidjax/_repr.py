"""Readable reprs: arrays as a dtype and shape with their values only when they are few, so that a
model of 10^4 bodies prints in one short line and a model holding tracers (inside ``jax.jit``)
prints its shapes instead of failing.

``summarize(x)`` is the one array summary; ``fields_repr`` builds ``Name(field=summary, ...)``.
"""

import dataclasses

import jax
import numpy as np

__all__ = ["dataclass_fields", "fields_repr", "summarize", "summarizing"]

# Arrays with at most this many entries show their values (a 3x3 tensor does; a batch does not).
MAX_SHOWN = 9


def _dtype_name(dtype) -> str:
    """``float64`` -> ``f64``, ``int32`` -> ``i32``, ``bool`` -> ``bool`` (equinox's short names)."""
    dtype = np.dtype(dtype)
    if dtype == np.bool_:
        return "bool"
    kind = {"f": "f", "i": "i", "u": "u", "c": "c"}.get(dtype.kind)
    return f"{kind}{8 * dtype.itemsize}" if kind else dtype.name


def _number(value, digits: int) -> str:
    if isinstance(value, bool | np.bool_):
        return str(bool(value))
    return f"{value:.{digits}g}"


def _nested(values, digits: int) -> str:
    if values.ndim == 0:
        return _number(values.item(), digits)
    return "(" + ", ".join(_nested(v, digits) for v in values) + ")"


def _concrete(x):
    """``x`` as a NumPy array, or None for a tracer or an abstract value (shapes only)."""
    if isinstance(x, jax.core.Tracer) or isinstance(x, jax.ShapeDtypeStruct):
        return None
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError, TypeError):
        return None


def _array(x, digits: int) -> str:
    shape, dtype = tuple(x.shape), x.dtype
    head = f"{_dtype_name(dtype)}[{','.join(map(str, shape))}]"
    if int(np.prod(shape, dtype=np.int64)) > MAX_SHOWN:
        return head
    values = _concrete(x)
    if values is None:
        return head
    if values.ndim == 0:
        text = _number(values.item(), digits)
        if values.dtype.kind == "f" and text.lstrip("-").isdigit():
            text += ".0"  # a float shows as one: mass=1.0
        return text
    return f"{head} {_nested(values, digits)}"


def summarize(x, digits: int = 6) -> str:
    """A short text for ``x``: an array as ``f64[3] (1, 2, 3)`` (values shown up to ``MAX_SHOWN``
    entries; a 0-d array as its number), a batch or a tracer as its dtype and shape only
    (``f64[10000,3]``); modules by their own repr; callables by name; containers item by item."""
    if x is None or isinstance(x, bool | str):
        return repr(x)
    if isinstance(x, int | float):
        return _number(x, digits)
    if hasattr(x, "shape") and hasattr(x, "dtype"):
        return _array(x, digits)
    if isinstance(x, dict):
        return "{" + ", ".join(f"{k!r}: {summarize(v, digits)}" for k, v in x.items()) + "}"
    if isinstance(x, list | tuple) and not hasattr(x, "_fields"):
        items = [summarize(v, digits) for v in x]
        if isinstance(x, list):
            return "[" + ", ".join(items) + "]"
        return "(" + ", ".join(items) + ("," if len(items) == 1 else "") + ")"
    if hasattr(x, "_fields"):  # a NamedTuple
        return fields_repr(type(x).__name__, [(n, getattr(x, n)) for n in x._fields], digits)
    if dataclasses.is_dataclass(x):  # equinox modules: theirs, or the generic one of their fields
        if getattr(type(x).__repr__, "_summarizes", False):
            return repr(x)
        return fields_repr(type(x).__name__, dataclass_fields(x), digits)
    if callable(x):
        return getattr(x, "__qualname__", None) or getattr(x, "__name__", None) or type(x).__name__
    text = repr(x)
    return text if len(text) <= 60 else f"<{type(x).__name__}>"


def dataclass_fields(obj) -> list:
    """``(name, value)`` of each field of a dataclass (an equinox module), in declaration order."""
    return [(f.name, getattr(obj, f.name, None)) for f in dataclasses.fields(obj) if f.repr]


def fields_repr(name: str, fields, digits: int = 6) -> str:
    """``name(field=summary, ...)`` for ``(field, value)`` pairs."""
    return f"{name}({', '.join(f'{field}={summarize(value, digits)}' for field, value in fields)})"


def summarizing(method):
    """Marks a ``__repr__`` as one built from :func:`summarize` (so nesting uses it, not a dump)."""
    method._summarizes = True
    return method


@summarizing
def module_repr(self) -> str:
    """A ``__repr__`` for an equinox module: its class and fields, arrays as dtype, shape and (when
    few) values, no array dumps. Assign it: ``__repr__ = module_repr``."""
    return fields_repr(type(self).__name__, dataclass_fields(self))
