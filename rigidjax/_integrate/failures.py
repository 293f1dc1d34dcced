"""How a failed ``simulate`` says so: the first failed body, where and why, as a ``ValueError`` or
``EquinoxRuntimeError`` with the values at hand, or as run-time errors under the user's ``jit``."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._closed_form.frame import PHASE_ROUNDING_LIMIT, phase_advice
from . import driver
from .chunked import NON_FINITE
from .formulations import ScaledODE

__all__ = ["error_if_failed", "raise_if_exact_failed", "raise_if_failed"]


def _failure_reason(code: int, max_steps: int, formulation) -> str:
    if code == driver.MAX_STEPS_REACHED:
        return f"reached max_steps={max_steps}. Increase max_steps, choose a lower accuracy, or shorten ts"
    if code == driver.EVENT_OCCURRED and isinstance(formulation, ScaledODE):
        return (
            f"came within {formulation.lock_tolerance:g} of gimbal lock in its Euler-angle state "
            f"(seq={formulation.euler_seq!r}: first and third axes aligned, where Euler-angle rates are "
            "unbounded). Use representation='quaternion' (the default)"
        )
    if code == driver.DT_MIN_REACHED:
        return (
            "stopped because its step size collapsed there (below the smaller of 1e-12 times the span of "
            "ts and 1e-3 times the smallest gap between sample times): its state or torque became NaN "
            "or inf, the scene is singular there, or ts spans more turns than steps of that size can "
            "resolve (a torque-free body over so long a span: accuracy='exact'). Check the torque "
            "functions and the inputs"
        )
    if code == NON_FINITE:
        return (
            "has a state that became NaN or inf (a torque returning NaN or inf, or too long a fixed step dt0)"
        )
    return f"ended with diffrax result code {code}"


def raise_if_failed(traj, max_steps, formulation):
    """A failed run's error, naming the first failed body, where it failed and why."""
    failure = _first_failed_body(traj)
    if failure is None:
        return
    first, sample, who, others = failure
    code = int(np.asarray(traj.stats["result"]).ravel()[first])
    ts = np.asarray(traj.ts)
    if sample == 0:  # not even the first step was taken
        when = f"at its first step from t = {ts[0]:.6g} s"
    elif sample < ts.shape[0]:
        digits = next((d for d in (6, 9, 12, 17) if f"{ts[sample - 1]:.{d}g}" != f"{ts[sample]:.{d}g}"), 17)
        when = f"between t = {ts[sample - 1]:.{digits}g} s and t = {ts[sample]:.{digits}g} s"
    else:
        when = "before the last sample time"
    reason = _failure_reason(code, max_steps, formulation)
    if code == driver.MAX_STEPS_REACHED:
        reason += _time_resolution_hint(ts)
    raise eqx.EquinoxRuntimeError(
        f"simulate: {who} failed {when}: it {reason}.{others} "
        "With throw=False the other bodies keep their results, the failed ones are NaN from their "
        "failure on and Trajectory.success says which."
    )


def _time_resolution_hint(ts) -> str:
    """For a run out of steps: whether ``ts`` lie so far from zero that their dtype resolves time only
    coarsely there (float32 at |t| = 3e5 s: 0.03 s), so that the solver's steps, shorter than that,
    did not advance t at all; '' otherwise."""
    largest = float(np.max(np.abs(ts)))
    resolution = float(np.spacing(ts.dtype.type(largest)))
    if ts.shape[0] < 2 or resolution <= 1e-3 * float(np.mean(np.diff(ts))):
        return ""
    return (
        f". But ts lie far from zero for {ts.dtype}: at |t| = {largest:.3g} s it resolves only "
        f"{resolution:.2g} s, and steps shorter than that do not advance t, so more steps cannot help: "
        "pass ts - ts[0] (a scene depends on t only through a torque that reads it) or simulate in float64"
    )


def error_if_failed(traj, max_steps, formulation):
    """Under the user's jit the failure is raised at run time, without the values to name the body."""
    code = traj.stats["result"]
    omega = traj.omega
    for value in (driver.EVENT_OCCURRED, driver.MAX_STEPS_REACHED, driver.DT_MIN_REACHED, NON_FINITE):
        omega = eqx.error_if(
            omega,
            jnp.any(code == value),
            f"simulate: a body {_failure_reason(value, max_steps, formulation)}. Call simulate outside "
            "jit to have the body and the time named, or pass throw=False for NaN rows and "
            "Trajectory.success.",
        )
    omega = eqx.error_if(
        omega,
        ~jnp.all(traj.success),
        "simulate: the integration failed. Pass throw=False for NaN rows and Trajectory.success.",
    )
    return eqx.tree_at(lambda t: t.omega, traj, omega)


def _first_failed_body(traj):
    """``(flat index, first failed sample, "body ...", " (n of N bodies ...)")`` of the first body
    whose ``success`` is False, or None when all succeeded."""
    success = np.asarray(traj.success)
    if success.all():
        return None
    failed = np.flatnonzero(~success.ravel())
    first, batch = int(failed[0]), traj.batch_shape
    sample = int(np.asarray(traj.stats["first_failed_sample"]).ravel()[first])
    index = tuple(int(i) for i in np.unravel_index(first, batch))
    who = "the body" if not batch else f"body {index[0] if len(batch) == 1 else index}"
    others = (
        f" ({failed.size} of {success.size} bodies failed; the first is named)" if failed.size > 1 else ""
    )
    return first, sample, who, others


def raise_if_exact_failed(traj):
    """The closed form's error for a body with a sample that is NaN or inf or whose phase is beyond
    what the dtype resolves, naming the first such body and sample time (under the user's ``jit``:
    the causes only)."""
    dtype = traj.omega.dtype
    rows = "Pass throw=False for these rows and Trajectory.success."
    beyond = (
        f"its inputs are beyond what {dtype} can evaluate (for instance an angular momentum whose "
        f"square overflows). {rows}"
    )
    advice = phase_advice(dtype, "the first sample")
    phase = (
        f"the closed form's phase is beyond what {dtype} resolves (its rounding exceeds "
        f"{PHASE_ROUNDING_LIMIT:g} rad): the samples would be noise"
    )
    if isinstance(traj.success, jax.core.Tracer):
        message = (
            f"simulate: the closed form of a body is NaN or inf, or its phase is beyond what {dtype} "
            f"resolves (rounded by more than {PHASE_ROUNDING_LIMIT:g} rad). {advice} {rows}"
        )
        return eqx.tree_at(lambda t: t.omega, traj, eqx.error_if(traj.omega, ~jnp.all(traj.success), message))
    failure = _first_failed_body(traj)
    if failure is None:
        return traj
    first, sample, who, others = failure
    t = float(np.asarray(traj.ts)[sample])
    samples = [x for x in (traj.omega, traj.orientation) if x is not None]
    if all(np.isfinite(np.asarray(x).reshape((-1,) + x.shape[-2:])[first, sample]).all() for x in samples):
        raise ValueError(f"simulate: at t = {t:.6g} s for {who}, {phase}{others}. {advice} {rows}")
    raise ValueError(f"simulate: the closed form of {who} is NaN or inf at t = {t:.6g} s{others}: {beyond}")
