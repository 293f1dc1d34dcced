"""The records a fit reads: checks of sample times, angular velocities and quaternions (each
message names the argument and the fix), sign alignment of quaternions, and angular velocity from
orientation samples."""

import jax
import numpy as np

from .._checks import evaluated_now
from .._kinematics.quaternion import _quat_log, _quat_multiply


def _check_times(ts):
    """``ts`` as a float array, checked: 1-D, finite, strictly increasing."""
    ts = _real_array(ts, "ts")
    if ts.ndim != 1:
        raise ValueError(f"ts must be a 1-D array of sample times, got shape {ts.shape}.")
    if not np.all(np.isfinite(ts)):
        raise ValueError("ts contains NaN or inf; every sample needs a finite time.")
    if ts.shape[0] > 1 and not np.all(np.diff(ts) > 0):
        bad = int(np.argmin(np.diff(ts) > 0))
        raise ValueError(
            f"ts must be strictly increasing; ts[{bad}] = {ts[bad]} is followed by "
            f"ts[{bad + 1}] = {ts[bad + 1]}."
        )
    return ts


def _real_array(x, name):
    """``x`` as a float array; a ``TypeError`` naming ``name`` unless it holds real numbers (with
    values: the records are checked and prepared on the host, before anything is compiled)."""
    if isinstance(x, jax.core.Tracer):
        raise TypeError(
            f"{name} is traced (inside jax.jit, vmap or grad): the fitting functions read a record's "
            "values on the host, so call them outside jit with NumPy or JAX arrays."
        )
    try:
        x = np.asarray(x)
    except ValueError:  # NumPy's "inhomogeneous shape" of a ragged nested list
        raise ValueError(
            f"{name} is a ragged nested list (its rows have different lengths); give an array of one shape."
        ) from None
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise TypeError(f"{name} must hold real numbers, got dtype {x.dtype}.")
    return x.astype(float)


def _check_data(ts, omega_observed):
    """``(ts, omega)`` of a gyro record, checked: shapes ``(T,)`` and ``(T, 3)``, no inf."""
    ts = _check_times(ts)
    omega = _real_array(omega_observed, "omega_observed")
    if omega.shape != (ts.shape[0], 3):
        raise ValueError(
            f"omega_observed must have shape (T, 3) = ({ts.shape[0]}, 3) to match ts, got {omega.shape}."
        )
    if np.any(np.isinf(omega)):
        raise ValueError("omega_observed contains inf; mark missing samples with NaN instead.")
    return ts, omega


def _check_quaternions(ts, q_observed, name="orientation_observed"):
    """``(ts, q)`` of an orientation record, checked: unit quaternions ``(T, 4)``, no inf; a row
    with any NaN becomes all NaN. ``name``: the caller's name of ``q_observed``."""
    ts = _check_times(ts)
    q = _real_array(q_observed, name)
    if q.shape != (ts.shape[0], 4):
        raise ValueError(
            f"{name} must have shape (T, 4) = ({ts.shape[0]}, 4) (unit quaternions, scalar "
            f"first) to match ts, got {q.shape}."
        )
    if np.any(np.isinf(q)):
        raise ValueError(f"{name} contains inf; mark missing samples with NaN instead.")
    q = np.where(np.isnan(q).any(axis=1, keepdims=True), np.nan, q)  # a quaternion is all or nothing
    with np.errstate(invalid="ignore"):
        not_unit = np.abs(np.linalg.norm(q, axis=1) - 1.0) > 1e-5
    if np.any(not_unit):
        row = int(np.argmax(not_unit))
        raise ValueError(
            f"{name} must hold unit quaternions; row {row} has norm {np.linalg.norm(q[row]):.8g}"
            f" ({np.count_nonzero(not_unit)} of {len(q)} rows are not unit). Normalise them "
            "(rigidjax.quat_normalize) first."
        )
    return ts, q


def _align_signs(q):
    """Flips quaternion signs so that neighbouring valid samples have a positive dot product."""
    q = q.copy()
    previous = None
    for i in range(q.shape[0]):
        if np.isnan(q[i, 0]):
            continue
        if previous is not None and np.dot(q[i], previous) < 0:
            q[i] = -q[i]
        previous = q[i]
    return q


def omega_from_orientations(ts, q_observed):
    """Body-frame angular velocity from orientation samples, by central differences.

    From the rotation vector of each step, ``s_k = log(q_k^* q_{k+1})``, and its length
    ``h_k = t_{k+1} - t_k``: ``omega_i = (h_i / h_{i-1} s_{i-1} + h_{i-1} / h_i s_i) / (h_{i-1} +
    h_i)``, second order also where the spacing varies; one-sided (first order) at the ends. Each
    step is taken as the shorter of the two rotations between its samples, so the body may turn by
    up to ``pi`` per step (a difference over two steps would alias a spin of more than ``pi / 2``
    per step). ``q`` and ``-q`` are the same orientation. A starting point for fits, not a smoothed
    estimate.

    **Arguments:**

    - `ts`: sample times (s), strictly increasing, shape ``(T,)``.
    - `q_observed`: ``(T, 4)`` unit quaternions (scalar first, body -> space); a row with a NaN is a
      missing sample.

    **Returns:** the angular velocity (rad/s), ``(T, 3)``; NaN where the sample or a neighbour is
    missing.
    """
    ts, q = _check_quaternions(ts, q_observed, "q_observed")
    q = _align_signs(q)
    T = ts.shape[0]
    if T < 2:  # no difference to take: the one sample's omega was [nan, inf, nan]
        raise ValueError(f"omega_from_orientations needs at least 2 samples, got {T}.")
    step = _rotation_steps(q)
    h = np.diff(ts)[:, None]
    omega = np.empty((T, 3))
    omega[0], omega[-1] = step[0] / h[0], step[-1] / h[-1]
    h1, h2 = h[:-1], h[1:]
    omega[1:-1] = (h2 / h1 * step[:-1] + h1 / h2 * step[1:]) / (h1 + h2)
    return omega


def _rotation_steps(q):
    """The rotation vector of each step, ``log(q_k^* q_{k+1})`` (the shorter of the two rotations),
    ``(T - 1, 3)``, NaN where a sample is missing."""
    conj = q[:-1] * np.array([1.0, -1.0, -1.0, -1.0])
    return np.asarray(evaluated_now(_step_rotation, conj, q[1:]), float)


def _step_rotation(conj_start, end):
    return _quat_log(_quat_multiply(conj_start, end))


def orientation_noise(ts, q):
    """The noise of orientation samples (rad, the same for each body axis: the body turns its axes
    through the observer's), or NaN where fewer than five consecutive samples are present.

    Independent errors ``e_k`` (a small body-frame rotation per sample, standard deviation ``sigma``)
    enter each step as ``e_{k+1} - e_k``; the third difference of the steps (scaled to the median
    step length) carries them as a fourth difference, of variance ``70 sigma^2``, and the motion only
    at fourth order in the step. ``sigma`` from the median absolute value (``1.4826 MAD``), which a
    few outliers do not move."""
    h = np.diff(ts)
    steps = _rotation_steps(q) * (np.median(h) / h)[:, None]
    fourth = steps[:-3] - 3.0 * steps[1:-2] + 3.0 * steps[2:-1] - steps[3:]
    if fourth.shape[0] == 0 or not np.isfinite(fourth).any():
        return np.full(3, np.nan)
    return np.full(3, 1.4826 * np.nanmedian(np.abs(fourth)) / np.sqrt(70.0))
