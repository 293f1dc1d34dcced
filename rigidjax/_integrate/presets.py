"""The ``accuracy`` presets of :func:`rigidjax.simulate`: a diffrax solver and a relative tolerance.

Chosen by measurement (``benchmarks/batch_strategies.py``, 10^4 tennis-racket bodies, shared step,
max norm): Dopri8 needs 185 shared steps at rtol 1e-8 where Tsit5 needs 1048, and is faster at every
error below ~1e-5.
"""

from types import MappingProxyType

import diffrax

PRESETS = MappingProxyType(
    {
        "fast": (diffrax.Tsit5, 1e-5),
        "balanced": (diffrax.Dopri8, 1e-8),
        "precise": (diffrax.Dopri8, 1e-11),
    }
)
"""``accuracy`` name -> ``(diffrax solver class, rtol)``; read-only. ``"exact"`` is the closed form."""

ACCURACIES = (*PRESETS, "exact")
