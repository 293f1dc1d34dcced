"""The ``accuracy`` presets of :func:`rigidjax.simulate`: a diffrax solver and a relative tolerance.

Chosen by measurement (``benchmarks/batch_strategies.py``, 10^4 tennis-racket bodies, shared step,
max norm): Dopri8 needs 185 shared steps at rtol 1e-8 where Tsit5 needs 1048, and is faster at every
error below ~1e-5.
"""

from types import MappingProxyType
from typing import Any

import diffrax
import jax.numpy as jnp

PRESETS = MappingProxyType(
    {
        "fast": (diffrax.Tsit5, 1e-5),
        "balanced": (diffrax.Dopri8, 1e-8),
        "precise": (diffrax.Dopri8, 1e-11),
    }
)
"""``accuracy`` name -> ``(diffrax solver class, rtol)``; read-only. ``"exact"`` is the closed form."""

ACCURACIES = (*PRESETS, "exact")


class FaultStopPIDController(diffrax.PIDController):
    """diffrax's ``PIDController`` that also stops when a *rejected* step would shrink below
    ``fault_dtmin``.

    A body whose torque or state turns NaN makes every trial step fail; without a floor the chunk
    would burn ``max_steps`` rejections and be reported as out of steps. diffrax's own ``dtmin``
    cannot be the floor when steps land on sample times (``step_ts``): the controller grows the
    next step from the last *accepted* one, which a nearby sample time may have clipped to almost
    nothing, and a healthy body would stop. Accepted steps never trigger this floor.
    """

    fault_dtmin: Any = None

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        keep, next_t0, next_t1, made_jump, state, result = super().adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state
        )
        if self.fault_dtmin is not None:
            stuck = jnp.logical_not(keep) & (next_t1 - next_t0 < self.fault_dtmin)
            result = diffrax.RESULTS.where(stuck, diffrax.RESULTS.dt_min_reached, result)
        return keep, next_t0, next_t1, made_jump, state, result
