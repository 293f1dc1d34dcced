"""Fit an inertia tensor (and the initial angular velocity) to an observed wobble: the public entry
points :func:`fit_inertia` (gyroscope records) and :func:`fit_inertia_to_orientation` (motion
capture), their option checks, and the uncertainties of the optimum.

The scale gauge: the torque-free motion of ``c I`` is that of ``I``, so the record fixes the inertia
only up to a common factor. The fit returns ``trace(I) = 1`` unless a scale is supplied
(``inertia_trace=`` or ``known_moment=``), in which case the result is in kg m^2.

With a known torque (``torque=``: a constant or damping torque for gyro records; anything, gravity on
a pivot included, for orientation records) the torque fixes the scale, a log-scale parameter is
fitted, and the forward model is Dopri8 (rtol 1e-10, scaled units) instead of the closed form.
"""

import dataclasses
import math
import sys
import warnings
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._checks import check_callable, check_flag, compiled_once, is_positive_int
from .._dynamics.torques import _as_torque_tuple
from .data import _check_data, _check_quaternions
from .optimisers import _run
from .prepare import _Data, _prepare_omega, _prepare_orientation
from .problem import (
    LOSSES,
    NOISE_RATIO_LIMIT,
    WINDOW_MAX_STEPS,
    _moments_from_z,
    _on_flat_body_edge,
    _reordered_starts,
    _unmeasured_edge_distance,
)
from .result import InertiaFit


def _printed(iteration: int) -> bool:
    """Iterations 1-10, then every 10th to 100, then every 100th: a readable log of a long fit."""
    return iteration <= 10 or (iteration <= 100 and iteration % 10 == 0) or iteration % 100 == 0


@dataclasses.dataclass(frozen=True)
class _Hooks:
    """The host calls after each iteration: the user's ``callback``, ``progress`` (a callable, or
    ``print_lines`` for ``progress=True``)."""

    callback: Callable | None
    progress: Callable | None
    print_lines: bool

    def __call__(self, iteration, loss, step_norm):
        iteration, loss = int(iteration), float(loss)
        if self.callback is not None:
            self.callback(iteration, loss)
        if self.progress is not None:
            self.progress(iteration, loss)
        if self.print_lines and _printed(iteration):
            print(
                f"fit: iteration {iteration}, loss {loss:.6e}, step {float(step_norm):.3e}", file=sys.stderr
            )


_ACTIVE: list[_Hooks] = []
"""The hooks of the fit now running. The compiled fit calls :func:`_dispatch`, one function for all
hooks, so a new callable (a fresh lambda on every call) does not compile the fit again."""


def _dispatch(iteration, loss, step_norm):
    if _ACTIVE:
        _ACTIVE[-1](iteration, loss, step_norm)


def _hooks(callback, progress) -> _Hooks | None:
    """The iteration hooks of ``callback`` and ``progress``, or None when there are none."""
    if callback is not None:
        check_callable(callback, "callback", "callback(iteration, loss)", 2)
    if isinstance(progress, bool | np.bool_) or progress is None:
        print_lines, progress = bool(progress), None
    elif callable(progress):
        check_callable(progress, "progress", "progress(iteration, loss)", 2)
        print_lines = False
    else:
        raise TypeError(
            "progress must be True (a line per iteration on stderr), False, or a callable "
            f"progress(iteration, loss); got {progress!r}."
        )
    if callback is None and progress is None and not print_lines:
        return None
    return _Hooks(callback, progress, print_lines)


_METHODS = ("levenberg-marquardt", "optax")


def _known_torques(torque, inertia_trace, known_moment, *, orientation_data: bool):
    """The known torque as a tuple of torques (None without one), checked against the other scales
    and, for gyro records, against torques that need the orientation."""
    if torque is None:
        return None
    torques = _as_torque_tuple(torque)
    if not orientation_data and any(t.needs_orientation for t in torques):
        raise ValueError(
            "torque: a torque that needs the orientation (gravity on a heavy top, a space-fixed "
            "torque) cannot be fitted from angular velocity alone; fit orientation samples with "
            "fit_inertia_to_orientation(ts, q, torque=...) instead."
        )
    if inertia_trace is not None or known_moment is not None:
        raise ValueError("A known torque already fixes the scale; drop inertia_trace / known_moment.")
    for i, known in enumerate(torques):
        name = (
            f"torque {i} ({type(known).__name__})" if len(torques) > 1 else f"torque ({type(known).__name__})"
        )
        for value in jax.tree.leaves(eqx.filter(known, eqx.is_array_like)):
            if not np.all(np.isfinite(np.asarray(value))):
                raise ValueError(f"{name} holds NaN or inf; a known torque must be finite.")
        for field, (bad, rule) in known._leaf_rules().items():
            value = np.asarray(getattr(known, field))
            if np.any(bad(value)):
                raise ValueError(f"{name}: {field} {rule}; got {value}.")
    return torques


def _is_integer(x) -> bool:
    return isinstance(x, int | np.integer) and not isinstance(x, bool | np.bool_)


def _positive_number(value, name: str, what: str, *, allow_zero: bool = False) -> float:
    """``value`` as a Python float; a ``TypeError`` unless it is one real number, a ``ValueError``
    naming ``name`` unless it is finite and positive (or zero, with ``allow_zero``)."""
    kind = np.asarray(value).dtype.kind if not isinstance(value, str) else "U"
    if isinstance(value, bool | np.bool_) or np.ndim(value) != 0 or kind not in "iuf":
        raise TypeError(f"{name} must be a number ({what}), got {value!r}.")
    number = float(value)
    low_ok = number >= 0 if allow_zero else number > 0
    if not (math.isfinite(number) and low_ok):
        sign = "non-negative" if allow_zero else "positive"
        raise ValueError(f"{name} must be a {sign} finite number ({what}), got {number!r}.")
    return number


def _check_known_moment(known_moment):
    """``(k, I_kk)`` checked: an axis index 0, 1 or 2 and a positive finite moment."""
    usage = "known_moment must be (k, I_kk): a sensor axis index k (0, 1 or 2) and its moment I_kk (kg m^2)"
    if isinstance(known_moment, str) or not isinstance(known_moment, tuple | list) or len(known_moment) != 2:
        raise ValueError(f"{usage}; got {known_moment!r}.")
    axis, value = known_moment
    if not _is_integer(axis):
        raise ValueError(f"{usage}; got the index {axis!r}, which is not an integer.")
    if not 0 <= axis <= 2:
        raise ValueError(f"{usage}; got the index {axis}, which is out of range.")
    value = _positive_number(value, "known_moment's moment I_kk", "kg m^2")
    return int(axis), value


def _check_options(
    loss, method, optimizer, inertia_trace, known_moment, *, steps, tol, f_scale, dtype, full_tensor
):
    """Every option of a fit checked before any work: returns ``(method, steps, inertia_trace,
    known_moment, dtype)`` with the defaults filled in (``"optax"``; 200 or 2000 steps)."""
    if not isinstance(loss, str) or loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}.")
    if method is None:
        method = "optax"
    if not isinstance(method, str) or method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}.")
    if optimizer is not None:
        if method != "optax":
            raise ValueError(f"optimizer is used only with method='optax', not {method!r}; drop one of them.")
        if not (callable(getattr(optimizer, "init", None)) and callable(getattr(optimizer, "update", None))):
            raise TypeError(
                f"optimizer must be an optax GradientTransformation (e.g. optax.lbfgs()), got "
                f"{type(optimizer).__name__}."
            )
    check_flag(full_tensor, "full_tensor", None)
    if inertia_trace is not None and known_moment is not None:
        raise ValueError("Give at most one scale: inertia_trace or known_moment, not both.")
    if inertia_trace is not None:
        inertia_trace = _positive_number(inertia_trace, "inertia_trace", "the trace of the inertia, kg m^2")
    if known_moment is not None:
        known_moment = _check_known_moment(known_moment)
    if steps is None:
        steps = 200 if method == "levenberg-marquardt" else 2000
    elif not is_positive_int(steps):
        raise ValueError(f"steps must be a positive integer (the iteration limit), got {steps!r}.")
    _positive_number(tol, "tol", "the relative tolerance on the loss", allow_zero=True)
    if float(tol) >= 1:  # a relative change of the loss below 1 is met by the first iteration
        raise ValueError(f"tol must be below 1 (the relative tolerance on the loss), got {float(tol)!r}.")
    if f_scale is not None:
        _positive_number(f_scale, "f_scale", "the robust loss's scale, in the units of the residual")
    if dtype is None:
        dtype = jnp.result_type(float)
    else:
        try:
            dtype = np.dtype(dtype)
        except TypeError:
            raise TypeError(f"dtype must be a floating dtype (float32 or float64), got {dtype!r}.") from None
        if dtype not in (np.float32, np.float64):
            raise ValueError(f"dtype must be a floating dtype (float32 or float64), got {dtype}.")
        if dtype == np.float64 and not jax.config.jax_enable_x64:
            raise ValueError(
                "dtype float64 needs JAX's 64-bit mode: jax.config.update('jax_enable_x64', True) "
                "before any array is created (JAX computes in float32 otherwise)."
            )
    return method, int(steps), inertia_trace, known_moment, dtype


@jax.jit  # called eagerly once per fit: one program rather than one per operation
def _covariance_out(covariance):
    """The covariance of the scaled parameters, infinite on the diagonal of a parameter with a
    component (more than 1e-3) along a direction the record does not determine."""
    matrix, undetermined = covariance
    hidden = jnp.diagonal(undetermined) > 1e-6
    return jnp.where(jnp.diag(hidden), jnp.inf, matrix)


def _doubtful(out, data) -> bool:
    """Whether a fit from the estimated start may have ended in the wrong basin: not finite, the
    residuals over twice the noise estimate, or on the flat-body edge (where a wrongly ordered start
    ends). The residuals are measured robustly (median absolute value), as the noise is: a few
    outliers in a squared-loss fit raise the rms, which no other start would lower."""
    p, _, _, _, _, final_loss, _, robust_rms = out
    p = np.asarray(p, float)
    if not (np.all(np.isfinite(p)) and np.isfinite(float(final_loss))):
        return True
    moments = np.asarray(compiled_once(_moments_from_z)(jnp.asarray(p[:2])))  # one program, not 12
    return bool(_residual_ratio(robust_rms, data) > NOISE_RATIO_LIMIT or _on_flat_body_edge(moments))


def _residual_ratio(robust_rms, data) -> float:
    """The largest ratio of a component's median-based residual scale to its noise estimate: about 1
    where the fitted motion follows the record, whatever its outliers."""
    noise = np.asarray(data.noise, float)
    return float(
        np.max(np.asarray(robust_rms, float) * data.residual_unit / np.where(noise > 0, noise, np.inf))
    )


def _solve(data: _Data, *, full_tensor, method, optimizer, steps, tol, dtype, callback, scale):
    """Runs the optimiser on a prepared problem and returns the fit in the user's units, with
    standard errors from the covariance of the scaled parameters."""
    problem = data.problem
    p0 = jnp.asarray(data.p0, dtype)
    # optax's own internals (L-BFGS's memory indices) mix int32 and int64, which a user's strict
    # dtype promotion would reject; rigidjax's arithmetic does not depend on the setting.
    if callback is not None:
        _ACTIVE.append(callback)
    try:
        with jax.numpy_dtype_promotion("standard"):

            def run(start):
                hook = None if callback is None else _dispatch
                return _run(problem, start, method, optimizer, int(steps), float(tol), hook)

            out = run(p0)
            if data.estimated_start and _doubtful(out, data):
                # The estimate comes from differentiated noisy data and can order the moments
                # wrongly or lie by the flat-body edge; the fit then ends in another basin (on the
                # edge, or with residuals far above the noise). Starts in every order, the best kept.
                if callback is not None and callback.print_lines:
                    print(
                        "fit: the fit from the estimated start ended on the flat-body edge or above "
                        "the noise; fitting again from the moments (2, 3, 4) in each order",
                        file=sys.stderr,
                    )
                for start in _reordered_starts(data, p0, full_tensor):
                    other = run(jnp.asarray(start, dtype))
                    if np.isfinite(np.asarray(other[5])) and not float(other[5]) >= float(out[5]):
                        out = other
        if callback is not None:
            jax.block_until_ready(out)
            jax.effects_barrier()  # every iteration's call has run
    finally:
        if callback is not None:
            _ACTIVE.pop()
    p, history, n_steps, converged, covariance, final_loss, rms, robust_rms = out
    if not (np.all(np.isfinite(np.asarray(p))) and np.isfinite(np.asarray(final_loss))):
        if problem.torque is not None:
            raise FloatingPointError(
                "the fit's loss is NaN or inf: with a known torque the motion could not be integrated "
                f"over the record at the parameters reached after {int(n_steps)} iterations (more than "
                f"{WINDOW_MAX_STEPS:,} steps per window, or a torque that is NaN or inf there), or the "
                "optimiser diverged. Use more segments (shorter windows), check the torque, or try "
                "method='levenberg-marquardt'."
            )
        raise FloatingPointError(
            f"the {method} optimiser diverged: its parameters turned NaN or inf within {int(n_steps)} "
            "iterations. Try method='levenberg-marquardt', a smaller learning rate, or more segments "
            "(shorter windows) for a long record."
        )
    ratio = _residual_ratio(robust_rms, data)
    if ratio > NOISE_RATIO_LIMIT:
        warnings.warn(
            f"the fit's residuals are {ratio:.1f} times the record's noise estimate (measured by "
            "1.4826 times their median absolute value, which outliers do not move, where "
            "InertiaFit.warnings compares residual_rms): the fitted motion does not follow the record, "
            "whatever `converged` says. Check the time unit (seconds)"
            + (
                ", the quaternions' order (scalar first, (w, x, y, z): a scalar-last record fits nothing)"
                if problem.q_reference is not None
                else ""
            )
            + ", and try segments='auto' (a wrong wobble frequency over a long record) or a robust "
            "loss (many outliers).",
            RuntimeWarning,
            stacklevel=3,
        )
    if callback is not None and callback.print_lines:
        verdict = "converged" if bool(converged) else "not converged (the iteration limit or a stall)"
        print(f"fit: {int(n_steps)} iterations, loss {float(final_loss):.6e}, {verdict}", file=sys.stderr)
    inertia_trace, known_moment = scale
    segments = data.starts.shape[0]

    values = _user_values(
        problem,
        p,
        covariance,
        jnp.asarray(data.omega_scale, dtype),
        None if inertia_trace is None else jnp.asarray(inertia_trace, dtype),
        None if known_moment is None else (int(known_moment[0]), jnp.asarray(known_moment[1], dtype)),
    )
    inertia, w0_fit, inertia_stderr, w0_stderr, q0, q0_stderr, evals, evecs = values
    initial = jnp.asarray(data.inertia_start, dtype)
    if inertia_trace is not None:
        initial = initial * inertia_trace
    elif known_moment is not None:
        diag0 = np.diag(data.inertia_start) if full_tensor else data.inertia_start
        initial = initial * (known_moment[1] / diag0[known_moment[0]])
    one = (lambda x: x[0]) if segments == 1 else (lambda x: x)
    if problem.q_reference is not None:
        orientation0, orientation0_stderr = one(q0), one(q0_stderr)
    else:
        orientation0 = orientation0_stderr = None
    unit2 = data.residual_unit**2
    return InertiaFit(
        inertia=inertia,
        omega0=one(w0_fit),
        loss=final_loss * unit2,
        history=history[: int(n_steps)] * unit2,
        converged=converged,
        num_steps=int(n_steps),
        inertia_stderr=inertia_stderr,
        omega0_stderr=one(w0_stderr),
        orientation0=orientation0,
        orientation0_stderr=orientation0_stderr,
        principal_moments=evals,
        principal_axes=evecs,
        residual_rms=rms * data.residual_unit,
        noise_estimate=jnp.asarray(data.noise, dtype),
        segment_starts=np.asarray(data.starts, np.float64),
        initial_inertia=initial,
        covariance=_covariance_out(covariance),
        normalised=inertia_trace is None and known_moment is None and problem.torque is None,
        method=method,
        torque=problem.torque,
    )


@eqx.filter_jit
def _user_values(problem, p, covariance, omega_scale, inertia_trace, known_moment):
    """The fit in the user's units from the scaled parameters ``p``: inertia, omega0, their standard
    errors, the initial orientations of an orientation fit with theirs (else None), and the principal
    moments and axes (a proper rotation). One compiled program rather than a few hundred eager
    operations, each compiled on its own at a first fit."""
    full_tensor = problem.full_tensor

    def user_values(p):
        p_inertia, w0, dq = problem.split(p)
        inertia = problem.inertia(p_inertia)
        diag = jnp.diagonal(inertia) if full_tensor else inertia
        if inertia_trace is not None:
            inertia = inertia * inertia_trace
        elif known_moment is not None:
            axis, value = known_moment
            inertia = inertia * (value / diag[axis])
        return inertia, w0 * omega_scale, dq

    # The covariance is that of the scaled parameters (dimensionless z, omega0 / omega_scale, the
    # orientation corrections in rad); user_values' Jacobian carries the units.
    inertia, w0_fit, dq = user_values(p)
    jac_inertia, jac_w0, jac_dq = jax.jacfwd(user_values)(p)

    covariance, undetermined = covariance

    def stderr(jac):
        flat = jac.reshape(-1, p.shape[0])
        variance = jnp.einsum("ip,pq,iq->i", flat, covariance, flat)
        # A value that depends on a direction the record does not determine (more than 1e-3 of its
        # gradient there) is not measured: infinite.
        hidden = jnp.einsum("ip,pq,iq->i", flat, undetermined, flat) > 1e-6 * jnp.sum(flat * flat, axis=-1)
        # NaN (a covariance that is not finite, at a degenerate optimum) measures nothing either.
        hidden = hidden | ~jnp.isfinite(variance)
        return jnp.where(hidden, jnp.inf, jnp.sqrt(jnp.maximum(variance, 0.0))).reshape(jac.shape[:-1])

    tensor = inertia if full_tensor else jnp.diag(inertia)
    evals, evecs = jnp.linalg.eigh(tensor)
    evecs = evecs * jnp.where(jnp.linalg.det(evecs) < 0, jnp.array([-1.0, 1.0, 1.0], p.dtype), 1.0)
    if problem.q_reference is None:
        q0 = q0_stderr = None
    else:
        q0, q0_stderr = problem.initial_orientations(dq), stderr(jac_dq)
    inertia_stderr = _unmeasured_edge_distance(
        stderr(jac_inertia), inertia, evals, evecs, full_tensor, known_moment
    )
    return inertia, w0_fit, inertia_stderr, stderr(jac_w0), q0, q0_stderr, evals, evecs


_COMMON_ARGS_DOC = """\
    - `inertia_init`: starting inertia (moments, or a tensor with ``full_tensor``); by default a
      data-driven estimate (:func:`estimate_inertia`); a fit from the estimate that ends on the
      flat-body edge or with residuals over twice the noise estimate is run again from the moments
      ``(2, 3, 4)`` in each of the six orders, keeping the lowest loss (very noisy data can order
      the estimate's moments wrongly). Any positive scale; only ratios matter.
    - `omega0_init`: starting ``omega0`` ``(3,)`` or ``(segments, 3)``; by default the smoothed
      (estimated) angular velocity at each window start.
    - `segments`: multiple shooting: the record is cut into this many windows of consecutive
      samples, each with its own fitted initial state, all sharing one inertia. Long records (many
      wobble cycles) and chaotic tennis-racket records need it: a single window's loss is riddled
      with local minima at wrong wobble frequencies. Windows of about one wobble period work best;
      ``"auto"`` picks that from the record's spectrum.
    - `full_tensor`: fit a full tensor in sensor axes (principal moments and axes) instead of
      principal moments about the sensor axes.
    - `method`: ``"optax"`` (default: `optimizer` on the mean robust squared residual, the gradient
      through the residuals' forward-mode Jacobian up to 4096 samples, by reverse mode beyond and
      with a known torque) or ``"levenberg-marquardt"`` (Gauss–Newton with damping, the Jacobian by
      forward mode: few parameters, many residuals). Both reach the same optimum; Levenberg–Marquardt
      needs 4-16x fewer iterations, compiles about as fast (13-16 s vs 14-18 s for the first call on
      a loaded 2-core CPU) and runs up to 2x faster once compiled (1.1 s vs 2.4 s on an 1800-sample
      record in 45 windows; 0.18 s vs 0.22 s on 240 samples, ``benchmarks/fit_methods.py``): pass it
      when fitting many records.
    - `optimizer`: any optax ``GradientTransformation`` for ``"optax"``. By default L-BFGS: optax's
      ``scale_by_lbfgs`` directions with a strong-Wolfe line search that the fit's loop runs, so
      that the model is compiled once; ``optax.lbfgs()``, whose own line search calls the model from
      two more places, takes about 1.7x as long to compile (24 s vs 14 s on 240 samples). The
      optimiser is part of the compiled fit: pass the same object again to avoid a recompile.
    - `steps`: iteration limit (default 200 for Levenberg–Marquardt, 2000 for optax).
    - `loss`: ``"squared"``, or a robust loss against outliers: ``"huber"``, ``"soft_l1"``,
      ``"cauchy"`` (as in ``scipy.optimize.least_squares``).
    - `f_scale`: the robust loss's scale, in the units of the residual; default three times the
      noise level estimated from the data.
    - `inertia_trace`: fixes the scale gauge: the trace of the inertia (kg m^2; e.g.
      ``2 * sum(m r^2)`` from a mass and a shape). Without it or `known_moment`, the result has
      trace 1.
    - `known_moment`: fixes the scale gauge instead by ``(k, I_kk)``: one known diagonal entry in
      sensor axes (kg m^2).
    - `tol`: relative tolerance on the loss for convergence; at least ten times the machine epsilon
      of `dtype` (2.2e-15 in float64, 1.2e-6 in float32).
    - `dtype`: float dtype of the fit (default: JAX's default float; float64 with x64 enabled).
    - `callback`: called on the host as ``callback(iteration, loss)`` after every iteration; the
      loss is in the optimiser's scaled units. A fit run again from other starts (see
      `inertia_init`) counts its iterations from 1 again.
    - `progress`: ``True`` prints the iteration, the loss (scaled units) and the norm of the step in
      the scaled parameters to stderr (iterations 1-10, then every 10th up to 100, then every 100th)
      and a last line with the iteration count and whether the fit converged; a callable is called
      as ``progress(iteration, loss)`` after every iteration instead. The fit is the same with or
      without it.
"""


def fit_inertia(
    ts,
    omega_observed,
    *,
    inertia_init=None,
    omega0_init=None,
    segments: int | str = 1,
    full_tensor: bool = False,
    optimizer: optax.GradientTransformation | None = None,
    steps: int | None = None,
    method: str | None = None,
    loss: str = "squared",
    f_scale: float | None = None,
    noise: Any = None,
    inertia_trace: float | None = None,
    known_moment: tuple[int, float] | None = None,
    torque: Any = None,
    tol: float = 1e-10,
    dtype: Any = None,
    callback: Callable[[int, float], None] | None = None,
    progress: bool | Callable[[int, float], None] = False,
) -> InertiaFit:
    """Fits the inertia of a body to body-frame angular-velocity samples (a gyroscope).

    **Arguments:**

    - `ts`: sample times (s), strictly increasing, shape ``(T,)``.
    - `omega_observed`: ``(T, 3)`` body(sensor)-frame angular velocity (rad/s); NaN marks a missing
      sample (per component).
    - `noise`: the gyro noise per axis (rad/s, a scalar or ``(3,)``): residuals are weighted by its
      inverse (generalised least squares). Default: estimated from the record (scatter about local
      quadratic fits); ``"equal"`` weights the axes equally.
    - `torque`: a KNOWN body-frame torque acting during the record (a rigidjax torque such as
      ``ConstantTorque(tau)``, ``ViscousDamping(c)`` or ``Torque(fn)``, or a tuple; not one that
      needs the orientation). It fixes the scale, so the inertia comes out in kg m^2; the motion
      is then integrated (Dopri8, rtol 1e-10; derivatives in forward mode for Levenberg–Marquardt,
      in reverse mode for optax) instead of the closed form.
    {common}

    **Returns:** an :class:`InertiaFit` (``orientation0`` is None).
    A ``RuntimeWarning`` says when the residuals (their median absolute value) are more than twice
    the noise estimate: the fitted motion then does not follow the record.
    """
    ts, omega = _check_data(ts, omega_observed)
    method, steps, inertia_trace, known_moment, dtype = _check_options(
        loss,
        method,
        optimizer,
        inertia_trace,
        known_moment,
        steps=steps,
        tol=tol,
        f_scale=f_scale,
        dtype=dtype,
        full_tensor=full_tensor,
    )
    hooks = _hooks(callback, progress)
    torques = _known_torques(torque, inertia_trace, known_moment, orientation_data=False)
    data = _prepare_omega(
        ts,
        omega,
        segments,
        full_tensor,
        inertia_init,
        omega0_init,
        loss,
        f_scale,
        noise,
        dtype,
        torques,
        reverse_mode=torques is not None and method == "optax",
    )
    return _solve(
        data,
        full_tensor=full_tensor,
        method=method,
        optimizer=optimizer,
        steps=steps,
        tol=tol,
        dtype=dtype,
        callback=hooks,
        scale=(inertia_trace, known_moment),
    )


def fit_inertia_to_orientation(
    ts,
    orientation_observed,
    *,
    inertia_init=None,
    omega0_init=None,
    orientation0_init=None,
    segments: int | str = 1,
    full_tensor: bool = False,
    optimizer: optax.GradientTransformation | None = None,
    steps: int | None = None,
    method: str | None = None,
    loss: str = "squared",
    f_scale: float | None = None,
    inertia_trace: float | None = None,
    known_moment: tuple[int, float] | None = None,
    torque: Any = None,
    tol: float = 1e-10,
    dtype: Any = None,
    callback: Callable[[int, float], None] | None = None,
    progress: bool | Callable[[int, float], None] = False,
) -> InertiaFit:
    """Fits the inertia of a body to orientation samples (motion capture).

    The motion is torque-free, or under a known torque. The residual of a sample is the rotation
    vector (rad) from the predicted to the observed orientation, ``2 sign(w) vec(q_pred^* q_obs)``,
    so ``q`` and ``-q`` are the same observation. Each window fits its initial angular velocity and
    its initial orientation (a rotation-vector correction of the observed one).

    **Arguments:**

    - `ts`: sample times (s), strictly increasing, shape ``(T,)``.
    - `orientation_observed`: ``(T, 4)`` unit quaternions (scalar first, body -> space); a row with
      a NaN is a missing sample.
    - `orientation0_init`: starting orientation per window ``(4,)`` or ``(segments, 4)``; by
      default the observed one at each window start.
    - `torque`: a KNOWN body-frame torque acting during the record, which may depend on the
      orientation: ``GravityTorque(mass, com)`` for a heavy top or a gyroscope on a pivot (then the
      inertia is about the pivot), a space-frame ``ConstantTorque``, ``Torque(fn)``, or a tuple. It
      fixes the scale (inertia in kg m^2); (omega, q) is then integrated (Dopri8, rtol 1e-10;
      derivatives in forward mode for Levenberg–Marquardt, in reverse mode for optax) instead of
      the closed form.
    {common}

    **Returns:** an :class:`InertiaFit` with ``orientation0`` and ``orientation0_stderr`` (rad, about
    the body axes).
    A ``RuntimeWarning`` says when the residuals (their median absolute value) are more than twice
    the noise estimate: the fitted motion then does not follow the record.
    """
    ts, q = _check_quaternions(ts, orientation_observed)
    method, steps, inertia_trace, known_moment, dtype = _check_options(
        loss,
        method,
        optimizer,
        inertia_trace,
        known_moment,
        steps=steps,
        tol=tol,
        f_scale=f_scale,
        dtype=dtype,
        full_tensor=full_tensor,
    )
    hooks = _hooks(callback, progress)
    torques = _known_torques(torque, inertia_trace, known_moment, orientation_data=True)
    data = _prepare_orientation(
        ts,
        q,
        segments,
        full_tensor,
        inertia_init,
        omega0_init,
        orientation0_init,
        loss,
        f_scale,
        dtype,
        torques,
        reverse_mode=torques is not None and method == "optax",
    )
    return _solve(
        data,
        full_tensor=full_tensor,
        method=method,
        optimizer=optimizer,
        steps=steps,
        tol=tol,
        dtype=dtype,
        callback=hooks,
        scale=(inertia_trace, known_moment),
    )


fit_inertia.__doc__ = fit_inertia.__doc__.replace("    {common}\n", _COMMON_ARGS_DOC)
fit_inertia_to_orientation.__doc__ = fit_inertia_to_orientation.__doc__.replace(
    "    {common}\n", _COMMON_ARGS_DOC
)
