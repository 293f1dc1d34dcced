"""``simulate(..., error_estimate=True)``: a per-body error estimate from a second, more accurate
solution of the same problem.

The batch is solved twice: as asked (the result the user gets) and once more, more accurately:

- an adaptive step (a preset, or a user's ``PIDController``): both tolerances divided by
  :data:`TOLERANCE_FACTOR` (never below ten roundoff units), the same solver, and a controller's
  ``dtmax`` and ``dtmin`` by ``TOLERANCE_FACTOR^(1/order)`` (steps held at a bound are then finer
  too, by what lowers a step's error as much as the tolerances do). The finer solution's
  error is then a small fraction of the first's (for Dopri8 about ``100^(-8/9)``, 1/60; for Tsit5
  about 1/40), so their difference is the first solution's error to a few per cent;
- a fixed step (``rigidjax.solvers``' RKMK and splittings, or ``ConstantStepSize``): half the step.
  For a method of order ``p`` the errors scale as ``h^p``, so the difference is
  ``1 - 2^-p`` of the first solution's error (Richardson): it is divided by that;
- float32 results with ``jax_enable_x64`` on: the second solve as above, but in float64, so that
  it measures float32 roundoff too (for ``accuracy="exact"``: the float64 closed form);
- ``accuracy="exact"``: the closed form has no truncation error; its error is roundoff amplified by
  the conditioning of the motion (near a separatrix, at long times). The second solution is the
  closed form at inputs perturbed by :data:`EXACT_PERTURBATION` roundoff unit (moments and initial
  angular velocity), so the difference, taken as it is, measures how much rounding the inputs moves
  the result: an estimate of the order of magnitude of that amplification, not a bound.

Per body, ``stats["error_estimate_omega"]`` is :data:`SAFETY` times (for ``"exact"``: once) the
largest difference of the angular velocities over the samples, relative to the body's largest
``|omega|``, and ``stats["error_estimate_orientation"]`` (with an orientation) the same for the
rotation angle (rad) between the two orientations; each is at least :data:`FLOOR` roundoff units.
NaN for a body whose integration failed, inf for one whose finer integration failed (e.g.
``max_steps``: it is the same for both runs).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import float_dtype
from .._kinematics.quaternion import _quat_angle_between
from .._numerics import safe_norm
from . import driver
from . import progress as _progress
from .presets import PRESETS, preset_rtol
from .solvers import STRUCTURE_PRESERVING
from .trajectory import Trajectory

TOLERANCE_FACTOR = 100.0
"""The finer adaptive solution's tolerances are the first's divided by this."""

SAFETY = 2.0
"""The difference of the two solutions is multiplied by this, so that the estimate stays above the
true error when the finer solution's own error (a few per cent of the first's) adds to it by chance;
measured ratios estimate / true error lie between about 1.5 and 3 (docs/guides/accuracy.md)."""

FLOOR = 10.0
"""No estimate is below this many roundoff units (``eps`` of the dtype): below it the two solutions
differ by roundoff only, which is no measure of the error."""

EXACT_PERTURBATION = 1.0
"""``accuracy="exact"``: the inputs of the second evaluation are perturbed by this many roundoff
units, relative (what rounding the inputs does); the difference is the estimate, without SAFETY."""


def with_error_estimate(simulate, model, state0, ts, **kwargs) -> Trajectory:
    """``simulate(model, state0, ts, **kwargs)`` with ``stats["error_estimate_omega"]`` and, with an
    orientation, ``stats["error_estimate_orientation"]`` added (see the module's docstring)."""
    dtype = float_dtype(
        state0.omega, state0.orientation, *jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))
    )
    eps = float(jnp.finfo(dtype).eps)
    fine_model, fine_state0, fine_ts = model, state0, ts
    fine_eps = eps
    if dtype == np.float32 and jax.config.read("jax_enable_x64"):
        # float32 results: the second solve in float64, so that their roundoff is measured too.
        fine_model, fine_state0, fine_ts = _as_float64(model, state0, ts)
        fine_eps = float(jnp.finfo(np.float64).eps)
    fine_kwargs = dict(kwargs, throw=False)
    report = _progress.check_progress(kwargs["progress"])
    if report is not None:  # one report over both solves
        kwargs["progress"], fine_kwargs["progress"] = _progress.passes(report, 2)
    factor = 1.0
    if kwargs["accuracy"] == "exact":
        if fine_eps == eps:  # no wider dtype: how much rounding the inputs moves the result
            fine_model, fine_state0 = _perturbed(model, state0, EXACT_PERTURBATION * eps, dtype)
            factor = 1.0 / SAFETY
    elif isinstance(kwargs["solver"], STRUCTURE_PRESERVING):
        if kwargs["dt0"] is not None:  # without, the first simulate call raises
            fine_kwargs["dt0"] = kwargs["dt0"] / 2
            factor = _richardson(kwargs["solver"].order(None), ts, kwargs["dt0"])
    else:  # checked before the first run: an unsupported controller raises at once
        fine_kwargs, factor = _finer_adaptive(fine_kwargs, dtype, fine_eps)
    coarse = simulate(model, state0, ts, **kwargs)
    fine = simulate(fine_model, fine_state0, fine_ts, **fine_kwargs)
    stats = dict(coarse.stats)
    stats.update(estimate(coarse, fine, SAFETY * factor, FLOOR * eps))
    return eqx.tree_at(lambda t: t.stats, coarse, stats)


def _as_float64(model, state0, ts):
    """The problem in float64 (its floating arrays cast)."""

    def wide(x):
        return x.astype(np.float64) if eqx.is_inexact_array(x) else x

    model = jax.tree_util.tree_map(wide, model)
    state0 = jax.tree_util.tree_map(wide, state0)
    return model, state0, jnp.asarray(ts).astype(np.float64)


def estimate(coarse: Trajectory, fine: Trajectory, scale: float, floor: float) -> dict:
    """Per body: ``scale`` times the largest difference of ``coarse`` and ``fine`` (omega relative to
    the body's largest |omega|, orientation as a rotation angle), at least ``floor``; NaN where
    ``coarse`` failed, inf where only ``fine`` did."""
    return _estimate_from_arrays(
        coarse.omega,
        coarse.orientation,
        coarse.success,
        fine.omega,
        fine.orientation,
        fine.success,
        scale,
        floor,
    )


@jax.jit  # one program: eagerly, its ~25 operations each compiled a program of their own
def _estimate_from_arrays(omega, q, success, fine_omega, fine_q, fine_success, scale, floor):
    dtype = omega.dtype
    tiny = jnp.finfo(dtype).tiny
    fine_omega = fine_omega.astype(dtype)
    size = jnp.max(jnp.linalg.norm(fine_omega, axis=-1), axis=-1)
    # safe_norm: the two solutions agree exactly at ts[0], where a plain norm's derivative is NaN.
    diff = jnp.max(safe_norm(omega - fine_omega), axis=-1)
    out = {"error_estimate_omega": diff / jnp.maximum(size, tiny)}
    if q is not None:
        angle = _quat_angle_between(q, fine_q.astype(dtype))
        out["error_estimate_orientation"] = jnp.max(angle, axis=-1)
    for name, value in out.items():
        value = jnp.maximum(scale * value, floor)  # NaN stays NaN
        value = jnp.where(success & ~fine_success, jnp.inf, value)
        out[name] = jnp.where(success, value, jnp.nan)
    return out


def _perturbed(model, state0, delta, dtype):
    """``model`` and ``state0`` with the moments scaled by ``(1 + d, 1 + d, 1 - d)`` (a symmetric top
    stays symmetric) and omega0 by ``(1 + d, 1 - d, 1 + d)``."""
    sign_i = jnp.asarray([1.0 + delta, 1.0 + delta, 1.0 - delta], dtype)
    sign_w = jnp.asarray([1.0 + delta, 1.0 - delta, 1.0 + delta], dtype)
    inertia = jnp.asarray(model.inertia).astype(dtype) * sign_i
    model = eqx.tree_at(lambda m: m.inertia, model, inertia)
    state0 = eqx.tree_at(lambda s: s.omega, state0, jnp.asarray(state0.omega).astype(dtype) * sign_w)
    return model, state0


def _richardson(order, ts, dt0) -> float:
    """``1 / (1 - r^-p)``, ``r`` the smallest ratio of the step counts of the two grids over a sample
    interval (2 where ``dt0`` divides the intervals; the smallest is the conservative choice)."""
    ts = np.asarray(ts, np.float64)
    if ts.shape[0] < 2:
        return 1.0
    coarse, _ = driver.fixed_step_grid(ts, dt0)
    fine, _ = driver.fixed_step_grid(ts, dt0 / 2)
    ratio = np.min(np.diff(np.searchsorted(fine, ts)) / np.diff(np.searchsorted(coarse, ts)))
    return 1.0 / (1.0 - float(ratio) ** (-order))


def _tighter(tol, floor):
    """``tol / TOLERANCE_FACTOR``, at least ``floor``: a Python float where ``tol`` is concrete."""
    try:
        return max(float(tol) / TOLERANCE_FACTOR, floor)
    except jax.errors.ConcretizationTypeError:  # a traced tolerance
        return jnp.maximum(tol / TOLERANCE_FACTOR, floor)


def _check_finer(tolerances, finer, dtype):
    """Refuses a finer run that is not finer: each concrete tolerance must have come down."""
    try:
        same = all(float(f) >= float(t) for t, f in zip(tolerances, finer, strict=True))
    except (jax.errors.ConcretizationTypeError, TypeError):  # traced tolerances: nothing to compare
        return
    if same:
        floor = 10 * float(np.finfo(dtype).eps)
        wider = (
            ""
            if dtype == np.float64
            else " or turn on jax_enable_x64 (the second solve then runs in float64)"
        )
        raise ValueError(
            f"error_estimate=True: the tolerances (rtol, atol) = ({float(tolerances[0]):g}, "
            f"{float(tolerances[1]):g}) are at or below {np.dtype(dtype).name}'s floor of ten roundoff units "
            f"({floor:.2g}), so no more accurate second solve exists to compare with; loosen them{wider}."
        )


def _solver_order(kwargs) -> int:
    """The order of the run's solver: the user's, or the preset's."""
    return (kwargs["solver"] or PRESETS[kwargs["accuracy"]][0]()).order(None)


def _finer_adaptive(kwargs, dtype, fine_eps):
    """The finer run's arguments: tolerances divided by TOLERANCE_FACTOR (not below ten roundoff
    units of the finer run's dtype, ``fine_eps``), or half the constant step. Tolerances already at
    that floor leave no finer run: a ``ValueError`` (the difference of two identical runs would
    read as an error of ten roundoff units, whatever the error)."""
    floor = 10 * fine_eps
    controller = kwargs["stepsize_controller"]
    if controller is None:
        rtol = kwargs["rtol"]
        rtol = preset_rtol(kwargs["accuracy"], dtype) if rtol is None else rtol
        atol = rtol if kwargs["atol"] is None else kwargs["atol"]
        kwargs["rtol"], kwargs["atol"] = _tighter(rtol, floor), _tighter(atol, floor)
        _check_finer((rtol, atol), (kwargs["rtol"], kwargs["atol"]), dtype)
        return kwargs, 1.0
    if isinstance(controller, diffrax.PIDController):
        finer = (_tighter(controller.rtol, floor), _tighter(controller.atol, floor))
        _check_finer((controller.rtol, controller.atol), finer, dtype)
        controller = eqx.tree_at(lambda c: (c.rtol, c.atol), controller, finer)
        # Steps held at dtmax (or dtmin) would be the same in both runs, and their difference would
        # miss the error (2e-15 for a true 2e-9): the bounds shrink by what makes a step's error
        # TOLERANCE_FACTOR smaller at the solver's order.
        shrink = TOLERANCE_FACTOR ** (1.0 / _solver_order(kwargs))
        for bound in ("dtmax", "dtmin"):
            if getattr(controller, bound) is not None:
                smaller = getattr(controller, bound) / shrink
                controller = eqx.tree_at(lambda c, bound=bound: getattr(c, bound), controller, smaller)
        kwargs["stepsize_controller"] = controller
        return kwargs, 1.0
    if isinstance(controller, diffrax.ConstantStepSize):
        if kwargs["dt0"] is None:
            raise ValueError("error_estimate with ConstantStepSize needs dt0.")
        kwargs["dt0"] = kwargs["dt0"] / 2
        return kwargs, 1.0 / (1.0 - 2.0 ** (-_solver_order(kwargs)))
    raise ValueError(
        "error_estimate=True works with the presets' step control, a diffrax.PIDController (a second "
        "run at tolerances / 100) or a ConstantStepSize (a second run at dt0 / 2); got "
        f"{type(controller).__name__}."
    )
