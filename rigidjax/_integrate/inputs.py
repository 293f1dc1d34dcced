"""simulate's run-time checks of its inputs: one program that returns the failed conditions for
concrete inputs, ``eqx.error_if`` in the user's program for traced ones."""

import equinox as eqx
import jax.numpy as jnp

from .._checks import (
    check_model,
    check_state,
    check_times,
    checks_done,
    collected_failures,
    error_if,
    evaluated_now,
    is_traced,
    known_values,
    packed_failures,
    raise_collected,
)
from .._kinematics.euler import _euler_from_quat
from .formulations import lock_distance

__all__ = ["checked_inputs"]


def checked_inputs(model, omega0, q0, ts, euler_seq, lock_tolerance):
    """simulate's inputs after their run-time checks. With concrete inputs the checks are a program
    of their own that returns the failed conditions, from which a ``ValueError`` is raised here: it
    holds no host callback, so JAX's persistent compilation cache keeps it and a second run in a new
    process compiles nothing. The tracers of an eager grad or jvp carry their primal values: those
    are checked the same way, and the differentiated program gets no checks of its own. Inputs
    without values (the user's jit or vmap) get ``eqx.error_if`` checks in the user's program."""
    values = known_values((model, omega0, q0, ts))
    if values is None:
        return _checks_in_program(model, omega0, q0, ts, euler_seq, lock_tolerance)
    checked, failures = evaluated_now(_checks_collected, *values, euler_seq, lock_tolerance)
    raise_collected(failures)
    if not is_traced(model, omega0, q0, ts):
        return checked
    with checks_done():
        return _checks_in_program(model, omega0, q0, ts, euler_seq, lock_tolerance)


@eqx.filter_jit
def _checks_collected(model, omega0, q0, ts, euler_seq, lock_tolerance):
    with collected_failures() as failures:
        checked = _checks_in_program(model, omega0, q0, ts, euler_seq, lock_tolerance)
    return checked, packed_failures(failures)


def _checks_in_program(model, omega0, q0, ts, euler_seq, lock_tolerance):
    model = check_model(model, "simulate")
    omega0, q0 = check_state(omega0, q0, "simulate")
    ts = check_times(ts, "simulate")
    if euler_seq is not None:
        q0 = error_if(
            q0,
            jnp.any(lock_distance(_euler_from_quat(q0, euler_seq), euler_seq) < lock_tolerance),
            f"simulate: the initial orientation is within {lock_tolerance:g} of gimbal lock for the "
            f"Euler-angle state (seq={euler_seq!r}); use representation='quaternion'.",
        )
    return model, omega0, q0, ts
