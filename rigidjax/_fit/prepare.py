"""From a checked record to a :class:`_Problem` and its starting point: the windows of multiple
shooting, the data-driven start (inertia, each window's initial state), the scaled units, the
padded per-window arrays and the residual weights."""

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from .._checks import is_positive_int
from .._dynamics.inertia_checks import (
    _NOT_FINITE,
    _NOT_POSITIVE,
    _NOT_SYMMETRIC,
    _OK,
    _TRIANGLE,
    _inertia_failure,
)
from .data import _align_signs, _real_array, omega_from_orientations, orientation_noise
from .estimate import _NO_EQUATIONS, _dominant_period, _estimate, _torque_estimate
from .problem import LOSSES, _inertia_params, _Problem


class _Data(NamedTuple):
    problem: _Problem
    p0: np.ndarray
    starts: np.ndarray  # window start times (s)
    inertia_start: np.ndarray
    residual_unit: float  # residuals are in units of this (omega_scale for omega, 1 rad for q)
    omega_scale: float
    noise: np.ndarray  # per-component noise estimate, in the residual's units (rad/s or rad)
    estimated_start: bool  # the starting inertia is the estimate (no inertia_init given)


def _prepare_omega(
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
    torques=None,
    reverse_mode=False,
):
    """The problem of a gyro record ``omega`` ``(T, 3)`` (rad/s, NaN where missing)."""
    segments = _resolve_segments(segments, ts, omega)
    valid = np.isfinite(omega)
    n_params = (5 if full_tensor else 2) + 3 * segments + (1 if torques is not None else 0)
    if valid.sum() < n_params + 1:
        raise ValueError(
            f"Too few samples: {int(valid.sum())} observed components in {ts.shape[0]} samples for "
            f"{n_params} parameters ({segments} window(s)); need more than the number of parameters."
        )
    unobserved = [
        f"{name} (column {c})" for c, name in enumerate(("wx", "wy", "wz")) if not valid[:, c].any()
    ]
    if unobserved:
        raise ValueError(
            f"omega_observed has no finite sample of {', '.join(unobserved)}: every body axis needs "
            "observations to fix the inertia."
        )
    bounds, windows = _windows(ts, valid.all(axis=1) | valid.any(axis=1), segments, n_params)
    estimate = _estimate(ts, omega, full_tensor=full_tensor)
    inertia_start, scale_start = _start_inertia(ts, estimate, torques, inertia_init, full_tensor)
    w0 = _window_start_values(windows, estimate.smoothed, omega, omega0_init, segments, "omega0_init")
    # Scaled units: omega / s and t * s (the torque-free motion is homogeneous), so residuals are O(1).
    omega_scale = float(np.sqrt(np.nanmean(np.sum(np.nan_to_num(omega) ** 2, axis=1)))) or 1.0
    padded = _padded_windows(ts, windows, omega_scale, np.nan_to_num(omega / omega_scale), valid, np.zeros(3))
    # Noise per component, from the scatter about the local fits (robust: a scaled MAD). Weighting
    # the residuals by its inverse is generalised least squares: a gyro axis that is quieter (or
    # sees a smaller signal) is not drowned by a noisier one, and the standard errors stay honest.
    estimated = estimate.noise
    if noise is None:
        usable = np.isfinite(estimated) & (estimated > 0)
        sigma = np.where(usable, estimated, np.max(estimated[usable]) if usable.any() else np.nan)
    elif isinstance(noise, str) and noise == "equal":
        sigma = np.ones(3)
    else:
        if isinstance(noise, str):
            raise ValueError(f"noise must be a number, three numbers (rad/s) or 'equal', got {noise!r}.")
        sigma = _real_array(noise, "noise")
        if sigma.shape not in ((), (1,), (3,)):
            raise ValueError(
                f"noise must be a scalar or have shape (3,) (rad/s per axis), got {sigma.shape}."
            )
        sigma = np.broadcast_to(sigma, (3,))
        if not np.all(np.isfinite(sigma) & (sigma > 0)):
            raise ValueError(f"noise must be positive finite standard deviations (rad/s), got {noise!r}.")
    if not np.all(np.isfinite(sigma) & (sigma > 0)):
        sigma = np.ones(3)
    sigma = np.maximum(sigma, 1e-3 * sigma.max())  # at most 1000x weight contrast
    reference = float(np.sqrt(np.mean(sigma**2)))
    if f_scale is None:
        f_scale_scaled = 3.0 * max(reference / omega_scale, 1e-12)
    else:
        f_scale_scaled = float(f_scale) / omega_scale
    return _assemble(
        ts,
        bounds,
        padded,
        q_reference=None,
        weights=reference / sigma,
        f_scale=f_scale_scaled,
        inertia_start=inertia_start,
        scale_start=scale_start,
        w0=w0,
        omega_scale=omega_scale,
        residual_unit=omega_scale,
        noise=estimated,
        full_tensor=full_tensor,
        loss=loss,
        torques=torques,
        reverse_mode=reverse_mode,
        dtype=dtype,
        estimated_start=inertia_init is None,
    )


def _prepare_orientation(
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
    torques=None,
    reverse_mode=False,
):
    """The problem of an orientation record ``q`` ``(T, 4)`` (unit quaternions, NaN rows missing)."""
    omega_fd = omega_from_orientations(ts, q)
    segments = _resolve_segments(segments, ts, omega_fd)
    valid_rows = np.isfinite(q[:, 0])
    n_params = (5 if full_tensor else 2) + 6 * segments + (1 if torques is not None else 0)
    bounds, windows = _windows(ts, valid_rows, segments, n_params)
    estimate = _estimate(ts, omega_fd, full_tensor=full_tensor)
    q_aligned = _align_signs(q)
    inertia_start, scale_start = _start_inertia(ts, estimate, torques, inertia_init, full_tensor, q_aligned)
    w0 = _window_start_values(windows, estimate.smoothed, omega_fd, omega0_init, segments, "omega0_init")
    if orientation0_init is not None:
        q_ref = _per_window(orientation0_init, segments, "orientation0_init", 4)
        norm = np.linalg.norm(q_ref, axis=1, keepdims=True)
        if np.any(norm < 1e-6):
            raise ValueError(
                "orientation0_init has a zero quaternion: a starting orientation must be a unit "
                "quaternion (w, x, y, z), e.g. (1, 0, 0, 0) for the identity."
            )
        q_ref = q_ref / norm
    else:
        q_ref = np.stack([q_aligned[a + int(np.argmax(valid_rows[a:b]))] for a, b in windows])
    omega_scale = float(np.sqrt(np.nanmean(np.sum(omega_fd**2, axis=1)))) or 1.0
    observed = np.where(valid_rows[:, None], np.nan_to_num(q_aligned), [1.0, 0.0, 0.0, 0.0])
    mask = np.broadcast_to(valid_rows[:, None], (ts.shape[0], 3))
    padded = _padded_windows(ts, windows, omega_scale, observed, mask, np.array([1.0, 0.0, 0.0, 0.0]))
    # Noise of the orientation samples (rad) from fourth differences of their errors; with
    # no five consecutive samples, from the roughness of the finite-difference omega (central
    # differences of independent angle errors e have scatter sqrt(2) e / (2 dt)).
    noise = orientation_noise(ts, q_aligned)
    if not np.all(np.isfinite(noise)):
        rough = float(np.sqrt(np.nanmean(estimate.noise**2)))
        noise = np.full(3, rough * 2.0 * np.median(np.diff(ts)) / np.sqrt(2.0))
    noise_rad = float(np.sqrt(np.mean(noise**2)))
    if f_scale is None:
        f_scale = 3.0 * max(noise_rad, 1e-12)
    return _assemble(
        ts,
        bounds,
        padded,
        q_reference=q_ref,
        weights=np.ones(3),
        f_scale=float(f_scale),
        inertia_start=inertia_start,
        scale_start=scale_start,
        w0=w0,
        omega_scale=omega_scale,
        residual_unit=1.0,
        noise=noise,
        full_tensor=full_tensor,
        loss=loss,
        torques=torques,
        reverse_mode=reverse_mode,
        dtype=dtype,
        estimated_start=inertia_init is None,
    )


def _windows(ts, valid_rows, segments, n_params):
    """The sample bounds of ``segments`` windows of consecutive samples, and ``(start, stop)`` pairs."""
    T = ts.shape[0]
    if T < 4 or valid_rows.sum() * 3 < n_params + 1:
        raise ValueError(
            f"Too few samples: {int(valid_rows.sum())} complete samples of {T} for {n_params} "
            f"parameters ({segments} window(s)); need more observations than parameters."
        )
    bounds = np.linspace(0, T, segments + 1).round().astype(int)
    windows = list(zip(bounds[:-1], bounds[1:], strict=True))
    if np.any(np.diff(bounds) < 2) or any(valid_rows[a:b].sum() < 1 for a, b in windows):
        raise ValueError(
            f"Too few samples per window: {T} samples cut into {segments} windows leaves a window with "
            "fewer than 2 samples or no complete observation; use fewer segments."
        )
    return bounds, windows


def _resolve_segments(segments, ts, omega):
    """The number of windows: ``segments``, checked, or for ``"auto"`` about one per wobble."""
    if isinstance(segments, str) and segments == "auto" and ts.shape[0] < 16:
        segments = 1  # at most T // 8 windows: one (and too short a record is reported as such)
    if isinstance(segments, str) and segments == "auto":
        # About one dominant oscillation per window: short enough that a poor start's frequency
        # error cannot slip by a whole cycle within a window, long enough to see the cycle.
        period = _dominant_period(ts, omega)
        segments = int(np.clip(round((ts[-1] - ts[0]) / period), 1, max(1, ts.shape[0] // 8)))
    if not is_positive_int(segments):
        raise ValueError(f"segments must be a positive integer or 'auto', got {segments!r}.")
    if segments > max(ts.shape[0] // 2, 1):
        raise ValueError(
            f"segments={segments} is too many for {ts.shape[0]} samples: each window needs at least 2 "
            f"samples, so at most {ts.shape[0] // 2} windows (or segments='auto')."
        )
    return int(segments)


def _start_inertia(ts, estimate, torques, inertia_init, full_tensor, orientations=None):
    """The starting inertia with trace 1, and with a known torque the starting trace (kg m^2)."""
    inertia, scale_start = estimate.inertia, None
    init = None if inertia_init is None else _check_inertia_init(inertia_init, full_tensor)
    if init is None and inertia is None:
        raise ValueError(f"Cannot estimate a starting inertia: {_NO_EQUATIONS}. Give inertia_init.")
    if torques is not None:
        if init is None:
            inertia, scale_start = _torque_estimate(
                ts, estimate.raw_fits, torques, full_tensor, inertia, orientations
            )
        else:
            scale_start = float(np.trace(init) if full_tensor else init.sum())
    return _inertia_start(init, inertia, full_tensor), scale_start


_INERTIA_PROBLEMS = {
    _TRIANGLE: "violates the triangle inequality I1 + I2 >= I3 (and cyclic) of its principal moments",
    _NOT_POSITIVE: "has a non-positive principal moment",
    _NOT_SYMMETRIC: "is not symmetric",
    _NOT_FINITE: "contains NaN or inf",
}


def _check_inertia_init(inertia_init, full_tensor):
    """``inertia_init`` as a float array of the fit's shape, checked to be a physical inertia."""
    start = _real_array(inertia_init, "inertia_init")
    expected = (3, 3) if full_tensor else (3,)
    if start.shape != expected:
        form = "a tensor, as full_tensor=True" if full_tensor else "principal moments"
        raise ValueError(f"inertia_init must have shape {expected} ({form}), got shape {start.shape}.")
    code = int(_inertia_failure(start))
    if code != _OK:
        problem = _INERTIA_PROBLEMS[code]
        if code == _NOT_POSITIVE:
            tiny = np.finfo(start.dtype).tiny
            problem += f" (a moment below {start.dtype.name}'s smallest normal number, {tiny:.3g}, is 0)"
        raise ValueError(
            f"inertia_init {problem}: it is not the inertia of a rigid body; got "
            f"{start.tolist()}. Any positive scale will do (only ratios matter)."
        )
    return start


def _inertia_start(init, estimate, full_tensor):
    """The checked ``inertia_init`` or the estimate, normalised to trace 1."""
    if init is None:
        return estimate
    return init / (np.trace(init) if full_tensor else init.sum())


def _per_window(init, segments, name, size):
    """A starting value per window: ``init`` of shape ``(size,)`` or ``(segments, size)``, finite."""
    values = _real_array(init, name)
    if values.shape == (size,):
        values = values[None]
    if values.shape != (segments, size):
        raise ValueError(f"{name} must have shape ({size},) or ({segments}, {size}), got {values.shape}.")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{name} contains NaN or inf; a starting value must be finite.")
    return values


def _window_start_values(windows, smoothed, fallback, init, segments, name):
    """``init`` per window (checked), or the first complete smoothed (else raw) sample of each."""
    if init is not None:
        return _per_window(init, segments, name, 3)
    values = []
    for a, b in windows:
        rows = [r for r in range(a, b) if np.all(np.isfinite(smoothed[r]))]
        rows = rows or [r for r in range(a, b) if np.all(np.isfinite(fallback[r]))]
        if rows:
            values.append(smoothed[rows[0]] if np.all(np.isfinite(smoothed[rows[0]])) else fallback[rows[0]])
            continue
        # No complete sample in the window (components sampled at different times): per component,
        # its first value in the window, else in the record.
        value = []
        for c in range(smoothed.shape[1]):
            for column in (smoothed[a:b, c], fallback[a:b, c], smoothed[:, c], fallback[:, c]):
                finite = column[np.isfinite(column)]
                if finite.size:
                    value.append(finite[0])
                    break
            else:
                raise ValueError(f"{name}: component {c} is never observed; give {name} explicitly.")
        values.append(np.array(value))
    return np.stack(values)


def _padded_windows(ts, windows, omega_scale, observed, mask, fill):
    """Per-window arrays padded to the longest window: scaled time since the window start
    ``(K, M)`` (the padding repeats the last time, so sample times never decrease), the observations
    ``(K, M, D)`` (``fill`` in the padding) and the mask ``(K, M, 3)`` (False in the padding)."""
    M = max(b - a for a, b in windows)
    t_win = np.zeros((len(windows), M))
    obs_win = np.tile(np.asarray(fill, float), (len(windows), M, 1))
    mask_win = np.zeros((len(windows), M, 3), bool)
    for k, (a, b) in enumerate(windows):
        t_win[k, : b - a] = (ts[a:b] - ts[a]) * omega_scale
        t_win[k, b - a :] = t_win[k, b - a - 1]
        obs_win[k, : b - a] = observed[a:b]
        mask_win[k, : b - a] = mask[a:b]
    return t_win, obs_win, mask_win


def _assemble(
    ts,
    bounds,
    padded,
    *,
    q_reference,
    weights,
    f_scale,
    inertia_start,
    scale_start,
    w0,
    omega_scale,
    residual_unit,
    noise,
    full_tensor,
    loss,
    torques,
    reverse_mode,
    dtype,
    estimated_start,
):
    """The :class:`_Problem` in ``dtype`` and the flat starting point: inertia parameters (with the
    log of the starting trace under a known torque), ``omega0 / omega_scale`` per window and, for
    orientation records, zero corrections of the initial orientations."""
    t_win, obs_win, mask_win = padded
    p_inertia = _inertia_params(inertia_start, full_tensor)
    if torques is not None:
        p_inertia = np.concatenate([p_inertia, [math.log(scale_start)]])
        inertia_start = inertia_start * scale_start
    p0 = [p_inertia, (w0 / omega_scale).reshape(-1)]
    if q_reference is not None:
        p0.append(np.zeros(3 * len(w0)))
    starts = ts[bounds[:-1]]
    problem = _Problem(
        t=jnp.asarray(t_win, dtype),
        observed=jnp.asarray(obs_win, dtype),
        mask=jnp.asarray(mask_win),
        f_scale=jnp.asarray(f_scale, dtype),
        q_reference=None if q_reference is None else jnp.asarray(q_reference, dtype),
        weights=jnp.asarray(weights, dtype),
        full_tensor=full_tensor,
        loss_index=jnp.asarray(LOSSES.index(loss)),
        torque=torques,
        omega_scale=jnp.asarray(omega_scale, dtype),
        reverse_mode=reverse_mode,
        t_start=jnp.asarray(starts, dtype),
    )
    return _Data(
        problem, np.concatenate(p0), starts, inertia_start, residual_unit, omega_scale, noise, estimated_start
    )
