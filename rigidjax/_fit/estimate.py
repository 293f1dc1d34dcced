"""The data-driven starting point of a fit: local quadratic fits of the record (smoothed omega,
omega_dot and the noise per component), the dominant wobble period, and the inertia from Euler's
equations, which are LINEAR in the inertia (torque-free: up to scale; with a known torque: in
kg m^2)."""

import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_flag
from .._dynamics.state import State
from .._dynamics.torques import _total_torque
from .data import _check_data

# Symmetric tensor entries (Ixx, Iyy, Izz, Ixy, Ixz, Iyz), and the principal moments alone.
_TENSOR_ENTRIES = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
_MOMENT_ENTRIES = [(0, 0), (1, 1), (2, 2)]


def _local_derivatives(ts, omega, half_width: int):
    """Value and time derivative of each component by a local quadratic least-squares fit over
    ``2 half_width + 1`` neighbouring samples (a Savitzky–Golay filter for uneven times), and each
    sample's leverage in its own fit.

    NaN is a missing value. Where the rows hold fewer than four values of a component, the fit is
    over the two nearest observed values on each side (and the row's own): a record with values
    missing at random then has a fit at nearly every row, where the rows alone often held too few
    (60 % missing left no row with a fit of all three components). Not across a gap of more than
    four times the rows' span, nor beyond a component's first or last value: a quadratic
    extrapolated there would not follow the motion."""
    T = ts.shape[0]
    value, slope, leverage = (np.full_like(omega, np.nan) for _ in range(3))
    # The fits over the rows all at once (one lstsq per row and component took 6 s for 20 000
    # samples), in blocks of rows that bound the memory.
    offsets = np.arange(-half_width, half_width + 1)
    block = max(1, 2**18 // offsets.size)
    for start in range(0, T, block):
        rows = np.arange(start, min(T, start + block))
        window = rows[:, None] + offsets
        inside = (window >= 0) & (window < T)
        window = np.clip(window, 0, T - 1)
        y = np.moveaxis(omega[window], -1, 0)  # (3, rows, samples)
        used = inside & np.isfinite(y)
        fits = _quadratic_fits(ts[window] - ts[rows, None], y, used)
        for out, fit in zip((value, slope, leverage), fits, strict=True):
            out[rows] = fit.T
    rows = np.arange(T)
    row_span = ts[np.minimum(rows + half_width, T - 1)] - ts[np.maximum(rows - half_width, 0)]
    for c in range(3):
        observed = np.flatnonzero(np.isfinite(omega[:, c]))
        few = np.flatnonzero(np.isnan(value[:, c]))
        if observed.size < 4 or few.size == 0:
            continue
        # Too few values among the rows: the two nearest observed on each side (and the row's own).
        after = np.searchsorted(observed, few)
        own = observed[np.minimum(after, observed.size - 1)] == few
        lo, hi = after - 2, after + 2 + own
        inner = (lo >= 0) & (hi <= observed.size)
        few, lo, hi = few[inner], lo[inner], hi[inner]
        narrow = ts[observed[hi - 1]] - ts[observed[lo]] <= 4.0 * row_span[few]
        few, lo = few[narrow], lo[narrow]
        # Windows of 4 or 5 values: padded to 5 with the window's own first value, unused.
        picked = observed[np.minimum(lo[:, None] + np.arange(5), observed.size - 1)]
        used = np.arange(5) < (4 + own[inner][narrow])[:, None]
        fits = _quadratic_fits(ts[picked] - ts[few, None], omega[picked, c], used)
        for out, fit in zip((value, slope, leverage), fits, strict=True):
            out[few, c] = fit
    return value, slope, leverage


def _quadratic_fits(dt, y, used):
    """The quadratic least-squares fits of ``y`` against ``dt`` (same shapes, the last axis a fit's
    samples, those ``used`` only) at ``dt = 0``: its value, slope and the leverage of a sample
    there, each of the shape without the last axis; NaN for a fit of fewer than four samples."""
    dt, y = np.where(used, dt, 0.0), np.where(used, y, 0.0)
    scale = np.max(np.abs(dt), axis=-1)
    x = dt / np.where(scale > 0, scale, 1.0)[..., None]
    # The normal equations: the Gram matrix of (1, x, x^2) holds the sums of x^0 .. x^4.
    powers = [used.astype(x.dtype)]
    for _ in range(4):
        powers.append(powers[-1] * x)
    sums = [p.sum(axis=-1) for p in powers]
    gram = np.stack([np.stack(sums[i : i + 3], axis=-1) for i in range(3)], axis=-2)
    rhs = np.stack([(powers[k] * y).sum(axis=-1) for k in range(3)], axis=-1)
    enough = used.sum(axis=-1) >= 4
    gram = np.where(enough[..., None, None], gram, np.eye(3))
    inverse = np.linalg.inv(gram)
    coef = np.einsum("...ij,...j->...i", inverse, rhs)
    conditioned = np.linalg.cond(gram) < 1e12
    return (
        np.where(enough, coef[..., 0], np.nan),
        np.where(enough, coef[..., 1] / np.where(scale > 0, scale, 1.0), np.nan),
        np.where(enough & conditioned, inverse[..., 0, 0], np.nan),  # the sample sits at x = 0
    )


def _dominant_period(ts, omega, power_fraction=None):
    """Period of the strongest oscillation in the record (via the FFT of the resampled data); with
    ``power_fraction``, the period of the lowest frequency below which that fraction of the
    record's power lies (shorter for a wobble with sharp features: a tennis-racket flip)."""
    n = max(64, ts.shape[0])
    grid = np.linspace(ts[0], ts[-1], n)
    power = np.zeros(n // 2 + 1)
    for c in range(3):
        y = omega[:, c]
        ok = np.isfinite(y)
        if ok.sum() < 4:
            continue
        y = np.interp(grid, ts[ok], y[ok])
        power += np.abs(np.fft.rfft(y - y.mean())) ** 2
    power[0] = 0.0
    if power_fraction is None or not power.sum() > 0:
        k = int(np.argmax(power))
    else:
        k = int(np.searchsorted(np.cumsum(power), power_fraction * power.sum()))
    return (ts[-1] - ts[0]) / k if k > 0 else ts[-1] - ts[0]


def estimate_inertia(ts, omega_observed, *, full_tensor: bool = False, half_width: int | None = None):
    """Data-driven inertia estimate from Euler's torque-free equations, which are linear in the inertia.

    With ``omega`` and ``omega_dot`` from a local quadratic fit (smoothed finite differences), every
    sample gives ``I omega_dot + omega x (I omega) = 0``: three linear equations in the three
    principal moments (or six tensor entries). The right singular vector of the smallest singular
    value is the estimate, normalised to trace 1 and made physical (second moments floored at a small
    positive value). A starting point for :func:`fit_inertia`, not a final answer: noise biases it,
    and so does the smoothing (about 1 % on noise-free records). A record whose angular velocity is
    constant to within its noise in every component is refused with a ``ValueError``: a steady
    rotation about a principal axis satisfies the torque-free equations for any inertia.

    **Arguments:**

    - `ts`: sample times (s), strictly increasing, shape ``(T,)``.
    - `omega_observed`: ``(T, 3)`` body(sensor)-frame angular velocity (rad/s); NaN marks a missing
      sample (per component).
    - `full_tensor`: estimate a full tensor in sensor axes instead of principal moments about them.
    - `half_width`: each local fit spans ``2 half_width + 1`` samples; by default about a sixteenth
      of the period below which 90 % of the record's power lies (the wobble period, or shorter
      for sharp features such as tennis-racket flips; at least 2, at most 50 samples each side).
      Where those samples hold fewer than four values of a component, its fit is over the two
      nearest observed values on each side instead (a record with most values missing at random),
      but not across a gap longer than four fit spans or beyond the component's first or last value.

    **Returns:** ``(inertia, smoothed_omega)``: moments ``(3,)`` or a tensor ``(3, 3)`` with trace 1,
    and the smoothed record ``(T, 3)`` (NaN where a component has no local fit).
    """
    ts, omega = _check_data(ts, omega_observed)
    if ts.shape[0] < 5:
        raise ValueError(
            f"estimate_inertia needs at least 5 samples of omega_observed (each local quadratic fit "
            f"spans 2 half_width + 1 >= 5 of them), got {ts.shape[0]}."
        )
    full_tensor = check_flag(full_tensor, "full_tensor", "estimate_inertia")
    if half_width is not None and (
        not isinstance(half_width, int | np.integer) or isinstance(half_width, bool) or half_width < 2
    ):
        raise ValueError(
            "half_width must be an integer >= 2 (each local quadratic fit needs at least 4 observed "
            f"samples), got {half_width!r}."
        )
    if half_width is not None and 2 * half_width + 1 > ts.shape[0]:
        # Every local fit would span the whole record: one quadratic through all of it.
        raise ValueError(
            f"half_width {half_width} makes each local fit span {2 * half_width + 1} samples, more than "
            f"the record's {ts.shape[0]}; use at most {(ts.shape[0] - 1) // 2}."
        )
    estimate = _estimate(ts, omega, full_tensor=full_tensor, half_width=half_width)
    if estimate.inertia is None:
        raise ValueError(f"estimate_inertia: {_NO_EQUATIONS}; widen half_width (now {estimate.half_width}).")
    _require_a_wobble(estimate)
    return estimate.inertia, estimate.smoothed


def _require_a_wobble(estimate: "_Estimate"):
    """A ``ValueError`` when the smoothed record does not vary beyond one sample's noise in any
    component: a rotation at constant angular velocity (about a principal axis) satisfies the
    torque-free equations for every inertia, so the estimate would be arbitrary."""
    smoothed = estimate.smoothed[np.all(np.isfinite(estimate.smoothed), axis=1)]
    if smoothed.shape[0] == 0:
        return
    variation = np.std(smoothed, axis=0)
    size = float(np.sqrt(np.mean(np.sum(smoothed * smoothed, axis=1))))
    noise = np.nan_to_num(estimate.noise, nan=0.0)
    # The floor: a record computed in float64 at constant angular velocity still varies by rounding.
    threshold = np.maximum(noise, 1e-13 * size)
    if np.all(variation <= threshold):
        raise ValueError(
            "estimate_inertia: omega_observed does not determine the inertia: its angular velocity is "
            f"constant to within the record's noise (variation {_vector(variation)} rad/s per component, "
            f"noise {_vector(noise)} rad/s). A rotation at constant angular velocity, about a principal "
            "axis, satisfies Euler's torque-free equations for any moments; a record with a wobble (or a "
            "known torque, with fit_inertia) determines them."
        )


def _vector(values) -> str:
    return "(" + ", ".join(f"{v:.2g}" for v in values) + ")"


_NO_EQUATIONS = (
    "no sample of omega_observed has enough observed neighbours in all three components for a local "
    "fit (at least 4 finite values of each of wx, wy, wz nearby), so there is no equation to estimate "
    "the inertia from"
)


class _Estimate(NamedTuple):
    inertia: np.ndarray | None  # trace 1: moments (3,) or tensor (3, 3); None without equations
    smoothed: np.ndarray  # (T, 3): the local fits' values, outliers rejected
    noise: np.ndarray  # (3,): noise per component, from the scatter about the local fits
    # (value, slope) of the local fits to the record as given (before outlier rejection): the
    # equations with a known torque are solved with these.
    raw_fits: tuple[np.ndarray, np.ndarray]
    half_width: int


def _estimate(ts, omega_observed, *, full_tensor: bool = False, half_width: int | None = None):
    """:func:`estimate_inertia` with the noise per component and the local fits it used."""
    # NaN is a missing sample: a component with no local fit gives NaN statistics, which are
    # handled below and by the callers, without NumPy's 'all-NaN slice' warnings.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return _estimate_quietly(ts, omega_observed, full_tensor, half_width)


def _estimate_quietly(ts, omega_observed, full_tensor, half_width):
    ts = np.asarray(ts, float)
    omega = np.asarray(omega_observed, float)
    if half_width is None:
        # A wobble's sharp features set the width: the flips of a body spinning near its
        # intermediate axis last a fraction of its period, and fits over 1/16 of the period
        # smoothed them into a 10 % bias of the inertia, without noise.
        period = _dominant_period(ts, omega, power_fraction=0.9)
        samples_per_period = period / max(np.median(np.diff(ts)), 1e-300)
        half_width = int(np.clip(samples_per_period / 16.0, 2, 50))
    value, slope, leverage = _local_derivatives(ts, omega, half_width)
    raw_fits = (value, slope)
    # One pass of outlier rejection: samples far from the local fit (5 robust sigma) are dropped.
    deviation = np.abs(omega - value)
    sigma = 1.4826 * np.nanmedian(deviation, axis=0)
    outlier = deviation > 5.0 * np.maximum(sigma, 1e-300)
    if np.any(outlier):
        omega = np.where(outlier, np.nan, omega)
        value, slope, leverage = _local_derivatives(ts, omega, half_width)
    # Noise per component, from the scatter about local fits of at most 7 samples: over the fits
    # above (1/16 of the wobble period, or of the record when that is shorter) a quadratic leaves
    # about 1e-2 of the amplitude unexplained, which reads as noise (a record of 800 samples with
    # noise 1e-3 of a unit amplitude gave 1.4-1.7e-3; 7 samples: 0.94-1.0e-3). A residual about
    # the local fit that includes the sample has variance sigma^2 (1 - h), h the sample's leverage
    # (0.49 for 5 equally spaced samples): undo that.
    noise_width = min(half_width, 3)
    if noise_width != half_width:
        near_value, _, near_leverage = _local_derivatives(ts, omega, noise_width)
    else:
        near_value, near_leverage = value, leverage
    scaled = np.abs(omega - near_value) / np.sqrt(np.clip(1.0 - near_leverage, 0.05, 1.0))
    noise = 1.4826 * np.nanmedian(scaled, axis=0) if np.isfinite(scaled).any() else np.full(3, np.nan)
    ok = np.all(np.isfinite(value) & np.isfinite(slope), axis=1)
    w, wd = value[ok], slope[ok]
    scale = np.sqrt(np.mean(np.sum(w * w, axis=1))) if w.size else 1.0
    if not scale > 0:  # divided by below: the SVD then failed to converge on NaN
        raise ValueError(
            "the record shows no rotation (its angular velocity is 0 at every sample): it says "
            "nothing of the inertia."
        )
    w, wd = w / scale, wd / scale**2  # omega_dot scales as omega^2 in the torque-free equations
    # No complete local fit: no equation, no estimate (the caller says so, or has its own start).
    inertia = _torque_free_inertia(w, wd, full_tensor) if w.shape[0] else None
    return _Estimate(inertia, value, noise, raw_fits, half_width)


def _torque_free_inertia(w, wd, full_tensor):
    """The trace-1 physical inertia nearest the null space of the torque-free equations."""
    if not full_tensor:
        w1, w2, w3 = w.T
        rows = [
            np.stack([wd[:, 0], -w2 * w3, w2 * w3], axis=1),
            np.stack([w3 * w1, wd[:, 1], -w3 * w1], axis=1),
            np.stack([-w1 * w2, w1 * w2, wd[:, 2]], axis=1),
        ]
        A = np.concatenate(rows, axis=0)
        if A.shape[0] < 3:
            return np.full(3, 1.0 / 3.0)
        v = np.linalg.svd(A, full_matrices=False)[2][-1]
        v = v * np.sign(v.sum()) if v.sum() != 0 else np.ones(3)
        moments = np.abs(v) / np.abs(v).sum()
        J = np.maximum(0.5 - moments, 2e-3)
        J = J / J.sum()
        return 0.5 * (J.sum() - J)
    basis = _symmetric_basis(_TENSOR_ENTRIES)
    A = _euler_columns(w, wd, basis)
    if A.shape[0] < 6:
        return np.eye(3) / 3.0
    v = np.linalg.svd(A, full_matrices=False)[2][-1]
    tensor = np.einsum("k,kij->ij", v, basis)
    tensor = tensor * np.sign(np.trace(tensor)) if np.trace(tensor) != 0 else np.eye(3)
    # Physical projection: second-moment matrix S = trace/2 - I must be positive definite.
    tensor = tensor / np.trace(tensor)
    S = 0.5 * np.eye(3) - tensor
    evals, evecs = np.linalg.eigh(S)
    evals = np.maximum(evals, 2e-3)
    S = (evecs * (evals / evals.sum())) @ evecs.T  # trace 1, so I = (1 - S) / 2 has trace 1
    return 0.5 * (np.eye(3) - S)


def _symmetric_basis(entries):
    """One symmetric 0/1 matrix per tensor entry ``(i, j)``: shape ``(len(entries), 3, 3)``."""
    basis = np.zeros((len(entries), 3, 3))
    for k, (i, j) in enumerate(entries):
        basis[k, i, j] = basis[k, j, i] = 1.0
    return basis


def _euler_columns(w, wd, basis):
    """``I omega_dot + omega x (I omega)`` is linear in the entries of ``I``: its matrix, one
    column per basis tensor, one row per sample and component."""
    return np.stack([(wd @ B.T + np.cross(w, w @ B.T)).reshape(-1) for B in basis], axis=1)


def _torque_estimate(ts, raw_fits, torques, full_tensor, inertia_free, orientations=None):
    """Inertia from the linear equations ``I omega_dot + omega x (I omega) = tau(t, omega)`` (least
    squares, with omega and omega_dot the local fits ``raw_fits`` of :func:`_estimate`) as
    ``(trace-1 shape, trace)``; falls back to the torque-free shape with its scale by least squares
    if the unconstrained solve is not physical."""
    value, slope = raw_fits
    ok = np.all(np.isfinite(value) & np.isfinite(slope), axis=1)
    w, wd, t = value[ok], slope[ok], ts[ok]
    if orientations is None:
        tau = np.asarray(
            jax.vmap(lambda t, w: _total_torque(torques, t, State(w), None))(jnp.asarray(t), jnp.asarray(w))
        )
    else:
        q = np.asarray(orientations)[ok]
        ok_q = np.all(np.isfinite(q), axis=1)
        w, wd, t, q = w[ok_q], wd[ok_q], t[ok_q], q[ok_q]
        tau = np.asarray(
            jax.vmap(lambda t, w, q: _total_torque(torques, t, State(w, q), None))(
                jnp.asarray(t), jnp.asarray(w), jnp.asarray(q)
            )
        )
    basis = _symmetric_basis(_TENSOR_ENTRIES if full_tensor else _MOMENT_ENTRIES)
    A = _euler_columns(w, wd, basis)
    b = tau.reshape(-1)
    tensor_free = inertia_free if full_tensor else np.diag(inertia_free)
    shape_column = (wd @ tensor_free.T + np.cross(w, w @ tensor_free.T)).reshape(-1)
    denominator = float(shape_column @ shape_column)
    scale = float(shape_column @ b) / denominator if denominator > 0 else 0.0
    coef = np.linalg.lstsq(A, b, rcond=None)[0]
    tensor = np.einsum("k,kij->ij", coef, basis)
    trace = float(np.trace(tensor))
    if trace > 0:
        candidate = tensor / trace
        S = 0.5 * np.eye(3) - candidate
        evals, evecs = np.linalg.eigh(S)
        if np.all(evals > 0):
            return (candidate if full_tensor else np.diag(candidate)), trace
    if scale > 0:
        return inertia_free, scale
    raise ValueError(
        "The torque does not fix the scale of this record (the least-squares inertia is not "
        "positive); check the torque's units and sign, or give inertia_init."
    )
