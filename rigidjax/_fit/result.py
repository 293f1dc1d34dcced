"""The result of a fit, :class:`InertiaFit`, and the fitted model's predictions."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._checks import as_float_array, check_finite
from .._closed_form.torque_free import torque_free_motion, torque_free_omega
from .._dynamics.models import RigidBody
from .._dynamics.state import State
from .._integrate.simulate import simulate
from .._kinematics.quaternion import _quat_conjugate, _quat_from_matrix, _quat_multiply
from .._repr import summarize
from .problem import NOISE_RATIO_LIMIT, _on_flat_body_edge


class InertiaFit(eqx.Module):
    """The result of :func:`fit_inertia` and :func:`fit_inertia_to_orientation`.

    **Attributes:**

    - `inertia`: principal moments ``(3,)`` about the sensor axes, or the full tensor ``(3, 3)`` in
      sensor axes with ``full_tensor=True``; trace 1 unless a scale was given (then kg m^2).
    - `omega0`: fitted initial angular velocity (rad/s), ``(3,)``, or ``(segments, 3)``: one per
      window, at `segment_starts`.
    - `loss`: final mean (robust) squared residual, (rad/s)^2 (rad^2 for orientation fits).
    - `history`: the loss per iteration.
    - `converged`: the optimiser met its tolerance before its step limit. That is a minimum, not
      necessarily the right one: compare `residual_rms` with `noise_estimate`. A ratio well above 1
      means a wrong wobble frequency (a local minimum): use ``segments="auto"``.
    - `num_steps`: iterations of the optimiser.
    - `inertia_stderr`, `omega0_stderr`: standard errors (Gauss–Newton approximation of the
      covariance at the optimum, scaled by the residual variance; with a robust loss by
      ``(1.4826 MAD)^2`` of the residuals, which outliers do not inflate), same shapes as the
      values;
      ``inf`` for a value the record does not determine (a steady spin about a principal axis says
      nothing of the inertia; a torque of zero fixes no scale).
    - `principal_moments`: the fitted inertia's principal moments, ascending.
    - `principal_axes`: its principal axes as columns (sensor-frame components, ``det = +1``).
    - `residual_rms`: root-mean-square residual per component (rad/s; rad for orientation fits);
      with a robust loss, its robust estimate ``1.4826 median |residual|``, which the outliers the
      loss discounts do not inflate.
    - `noise_estimate`: the noise per component estimated from the record alone, in the residual's
      units: for angular velocity, from its scatter about local fits; for orientations, from the
      fourth differences of the samples' errors (one value for all three axes; within 5 % of the
      noise added to test records at 30 and 120 samples per second). A wobble sampled only a few
      times per period reads partly as noise.
    - `orientation0`, `orientation0_stderr`: for :func:`fit_inertia_to_orientation`, the fitted
      initial orientation(s) (unit quaternions) and their standard errors (rad, a rotation vector
      about the body axes); None for angular-velocity fits.
    - `segment_starts`: the start time (s) of each window, float64 on the host (a NumPy array):
      clock times such as Unix timestamps keep their resolution in a float32 fit.
    - `initial_inertia`: the data-driven starting estimate (same gauge as `inertia`).
    - `covariance`: the covariance of the optimiser's scaled parameters (``inf`` on the diagonal of
      a parameter the record does not determine).
    - `normalised`: True when `inertia` has trace 1 (no scale was given).
    - `method`: the optimiser, ``"optax"`` or ``"levenberg-marquardt"``.
    - `torque`: the known torque of the fit (a tuple of torques), or None: torque-free.

    The property `warnings` lists what these numbers say against trusting the fit (empty when
    nothing does): moments the record does not determine, and residuals over twice the noise.
    """

    inertia: Float[Array, "3"] | Float[Array, "3 3"]
    omega0: Float[Array, "3"] | Float[Array, "segments 3"]
    loss: Float[Array, ""]
    history: Float[Array, " steps"]
    converged: Bool[Array, ""]
    num_steps: int
    inertia_stderr: Float[Array, "3"] | Float[Array, "3 3"]
    omega0_stderr: Float[Array, "3"] | Float[Array, "segments 3"]
    principal_moments: Float[Array, "3"]
    principal_axes: Float[Array, "3 3"]
    residual_rms: Float[Array, "3"]
    noise_estimate: Float[Array, "3"]
    orientation0: Float[Array, "4"] | Float[Array, "segments 4"] | None
    orientation0_stderr: Float[Array, "3"] | Float[Array, "segments 3"] | None
    segment_starts: Float[ArrayLike, " segments"]
    initial_inertia: Float[Array, "3"] | Float[Array, "3 3"]
    covariance: Float[Array, "p p"]
    normalised: bool = eqx.field(static=True)
    method: str = eqx.field(static=True)
    torque: Any = None

    @property
    def warnings(self) -> list[str]:
        """What the fit's own numbers say against trusting it, one sentence each (empty when nothing
        does): moments the record does not determine (infinite standard errors; a flat body's, on
        the edge of the physical moments, named as such), and `residual_rms` over twice
        `noise_estimate` (a wrong wobble frequency, a wrong time unit, or outliers under a squared
        loss). The command line prints these."""
        return _fit_warnings(
            np.asarray(self.inertia_stderr, float),
            np.asarray(self.residual_rms, float),
            np.asarray(self.noise_estimate, float),
            np.asarray(self.principal_moments, float),
            orientations=self.orientation0 is not None,
        )

    def __repr__(self) -> str:
        """A few lines: the fitted inertia and its standard errors, whether the optimiser converged,
        in how many steps, the loss and residuals, the initial state; arrays as dtype, shape and (when
        few) values, also for traced values inside ``jax.jit``."""

        def show(x):
            return summarize(x, digits=4)

        gauge = "normalised to trace 1" if self.normalised else "kg m^2"
        data = "angular velocity" if self.orientation0 is None else "orientation"
        lines = [f"inertia={show(self.inertia)} ({gauge})", f"inertia_stderr={show(self.inertia_stderr)}"]
        if self.inertia.ndim == 2:
            lines.append(f"principal_moments={show(self.principal_moments)}")
        lines += [
            f"converged={show(self.converged)}, num_steps={show(self.num_steps)}, method={self.method!r}",
            f"loss={show(self.loss)}, residual_rms={show(self.residual_rms)}",
            f"noise_estimate={show(self.noise_estimate)}",
            f"omega0={show(self.omega0)}, segments={self.segment_starts.shape[0]}, fitted to {data}",
        ]
        if self.torque is not None:
            lines.append(f"torque={show(self.torque)}")
        return "InertiaFit(\n" + "".join(f"    {line},\n" for line in lines) + ")"

    def _windows(self, ts):
        """``(window, elapsed)``: the window each time falls in (the first before
        `segment_starts[0]`) and the time since its start, in the fit's dtype. The difference is
        taken in float64, on the host for concrete times: a float32 fit of a record in clock time
        (1.7e9 s since 1970: float32's spacing there is 128 s) predicts from its elapsed times."""
        checked = as_float_array(ts, "ts")
        if checked.ndim > 1:
            raise ValueError(f"ts must be times (s), (T,) or a number, got shape {tuple(checked.shape)}.")
        dtype = self.inertia.dtype
        if isinstance(ts, jax.core.Tracer) or isinstance(self.segment_starts, jax.core.Tracer):
            wide = jnp.result_type(float)
            times = check_finite(checked, "ts", "predict").astype(wide)
            starts = jnp.asarray(self.segment_starts, wide)
            window = jnp.clip(jnp.searchsorted(starts, times, side="right") - 1, 0, starts.shape[0] - 1)
            return window, (times - starts[window]).astype(dtype)
        times = np.asarray(ts, np.float64)
        if not np.all(np.isfinite(times)):
            raise ValueError("ts must be finite times (s); it contains NaN or inf.")
        starts = np.asarray(self.segment_starts, np.float64)
        window = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, starts.shape[0] - 1)
        return window, jnp.asarray(times - starts[window], dtype)

    def _predict_with_torque(self, ts, with_orientation: bool):
        """Integrates the fitted model under its known torque from each window's start ("precise")."""
        window, elapsed = self._windows(ts)
        if isinstance(elapsed, jax.core.Tracer):
            raise TypeError(
                "The predictions of a fit with a known torque integrate on the host, window by window: "
                "call them outside jax.jit."
            )
        if np.any(elapsed < 0):
            raise ValueError(
                f"ts must not precede the first window's start ({float(self.segment_starts[0])!r} s) "
                "for a fit with a known torque: its model is integrated forward from there."
            )
        scalar = np.ndim(window) == 0
        window, elapsed = np.atleast_1d(window), np.atleast_1d(np.asarray(elapsed, np.float64))
        omega0 = self.omega0.reshape(-1, 3)
        q0 = None if self.orientation0 is None else self.orientation0.reshape(-1, 4)
        dtype = self.inertia.dtype
        out = np.zeros((window.shape[0], 4 if with_orientation else 3))
        for k in np.unique(window):
            rows = np.flatnonzero(window == k)
            order = np.argsort(elapsed[rows], kind="stable")
            times = np.concatenate([[0.0], elapsed[rows][order]])
            keep = np.concatenate([[True], np.diff(times) > 0])  # repeated times, one at the start
            state = State(omega0[k], q0[k] if q0 is not None else None)
            traj = simulate(
                RigidBody(self.inertia, torque=self.torque),
                state,
                jnp.asarray(times[keep], dtype),
                accuracy="precise",
            )
            values = np.asarray(traj.orientation if with_orientation else traj.omega)
            index = np.cumsum(keep) - 1
            out[rows[order]] = values[index[1:]]
        return jnp.asarray(out[0] if scalar else out, dtype)

    def predict_omega(self, ts) -> Float[Array, "*T 3"]:
        """The fitted model's angular velocity at given times.

        Each time is predicted from the window it falls in (the first window before
        `segment_starts[0]`): by the closed form, or integrated under the known torque if the fit
        had one. Under ``jax.jit``, compile ``eqx.filter_jit(fit.predict_omega)`` or a function that
        calls it (``jax.jit(fit.predict_omega)`` would need to hash the fit's arrays); a fit with a
        known torque predicts outside ``jit`` only.

        **Arguments:**

        - `ts`: times (s), ``(T,)`` or a number.

        **Returns:** the body-frame angular velocity (rad/s, sensor axes), ``(T, 3)`` (``(3,)`` for
        a number).
        """
        if self.torque is not None:
            return self._predict_with_torque(ts, with_orientation=False)
        window, elapsed = self._windows(ts)
        omega0 = self.omega0.reshape(-1, 3)
        if self.inertia.ndim == 2:
            axes = self.principal_axes
            return torque_free_omega(self.principal_moments, omega0[window] @ axes, elapsed) @ axes.T
        return torque_free_omega(self.inertia, omega0[window], elapsed)

    def predict_orientation(self, ts) -> Float[Array, "*T 4"]:
        """The fitted model's orientation at given times; orientation fits only.

        Each time is predicted from the window it falls in, as in :meth:`predict_omega`.

        **Arguments:**

        - `ts`: times (s), ``(T,)`` or a number.

        **Returns:** unit quaternions (scalar first, body -> space), ``(T, 4)`` (``(4,)`` for a
        number).
        """
        if self.orientation0 is None:
            raise ValueError("This fit has no orientation: it was fitted to angular velocity only.")
        if self.torque is not None:
            return self._predict_with_torque(ts, with_orientation=True)
        window, elapsed = self._windows(ts)
        omega0 = self.omega0.reshape(-1, 3)
        q0 = self.orientation0.reshape(-1, 4)
        axes = self.principal_axes
        q_axes = _quat_from_matrix(axes)
        q = torque_free_motion(
            self.principal_moments,
            omega0[window] @ axes,
            _quat_multiply(q0[window], q_axes),
            elapsed,
        )[1]
        return _quat_multiply(q, _quat_conjugate(q_axes))


def _fit_warnings(stderr, rms, noise, moments, orientations: bool = False) -> list[str]:
    """:attr:`InertiaFit.warnings` from the standard errors, residuals, noise estimate and principal
    moments (numpy arrays) of a fit to angular velocities or, with ``orientations``, quaternions."""
    out = []
    if not np.all(np.isfinite(stderr)) and _on_flat_body_edge(moments):
        out.append(
            "the largest principal moment is the sum of the other two: a flat body (its mass in one "
            "plane), on the edge of the physical moments, whose distance from that edge the record "
            "cannot give (an infinite standard error); the moments shown are the edge's."
        )
    elif not np.all(np.isfinite(stderr)):
        out.append(
            "the record does not determine every moment (infinite standard errors): a spin about one "
            "principal axis, or a wobble below the noise, fixes no inertia ratio; the values shown for "
            "those moments are arbitrary."
        )
    ratio = np.max(rms / np.maximum(noise, np.finfo(float).tiny))
    if np.all(np.isfinite(noise)) and np.all(noise > 0) and ratio > NOISE_RATIO_LIMIT:
        out.append(
            f"the residuals (residual_rms) are {ratio:.1f} times the record's noise estimate: the fit "
            "explains the record worse than its noise, most often a wrong wobble frequency. Check the "
            "time unit (seconds)"
            + (", the quaternions' order (scalar first, (w, x, y, z))" if orientations else "")
            + ", and fit in windows (segments='auto') or with a robust loss (outliers)."
        )
    return out
