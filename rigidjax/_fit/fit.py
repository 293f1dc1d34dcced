"""Fit an inertia tensor (and the initial angular velocity) to an observed torque-free wobble.

The forward model is the closed-form torque-free motion (:func:`torque_free_omega`): exact, cheap,
and smooth in the parameters, so no integration error enters the fit and the cost does not grow with
the length of the record.

Parametrisation (every parameter value is a valid inertia; nothing is clipped or penalised):

- principal moments: ``I_k = (J_i + J_j) / 2`` with second moments ``J = softmax(z1, z2, 0)``
  (``J_k = int x_k^2 dm`` up to scale). Positive ``J`` is exactly the set of moments satisfying the
  triangle inequalities strictly, and ``sum(J) = 1`` fixes the scale gauge: ``trace(I) = 1``.
- full tensor: the same moments in principal axes ``R(r)`` (rotation vector ``r``), so the tensor is
  ``R diag(I) R^T``; the axes are returned as well.

The scale gauge: the torque-free motion of ``c I`` is that of ``I``, so the record fixes the inertia
only up to a common factor. The fit returns ``trace(I) = 1`` unless a scale is supplied
(``inertia_trace=`` or ``known_moment=``), in which case the result is in kg m^2.

With a known torque (``torque=``: a constant or damping torque for gyro records; anything, gravity on
a pivot included, for orientation records) the torque fixes the scale, a log-scale parameter is
fitted, and the forward model is Dopri8 (rtol 1e-10, scaled units) instead of the closed form.
"""

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Bool, Float

from .._closed_form.torque_free import torque_free_motion, torque_free_omega
from .._dynamics.equations import _euler_equations
from .._dynamics.models import RigidBody, State, _as_torque_tuple, _total_torque
from .._integrate.simulate import _quat_derivative, simulate
from .._kinematics.quaternion import _quat_conjugate, _quat_from_matrix, _quat_multiply
from .._kinematics.quaternion import _quat_exp as quat_exp

_LOSSES = ("squared", "huber", "soft_l1", "cauchy")
_METHODS = ("levenberg-marquardt", "optax")


class InertiaFit(eqx.Module):
    """The result of :func:`fit_inertia`.

    - ``inertia``: principal moments ``(3,)`` about the sensor axes, or the full tensor ``(3, 3)`` in
      sensor axes with ``full_tensor=True``; trace 1 unless a scale was given (then kg m^2).
    - ``omega0``: fitted initial angular velocity (rad/s), ``(3,)``, or ``(segments, 3)``: one per
      window, at ``segment_starts``.
    - ``loss``: final mean (robust) squared residual, (rad/s)^2; ``history``: loss per iteration.
    - ``converged``: the optimiser met its tolerance before its step limit. That is a minimum, not
      necessarily the right one: compare ``residual_rms`` with ``noise_estimate`` (the noise per
      component estimated from the record's scatter about local fits). A ratio well above 1 means
      a wrong wobble frequency (a local minimum): use ``segments="auto"``.
    - ``inertia_stderr`` / ``omega0_stderr``: standard errors (Gauss–Newton approximation of the
      covariance at the optimum, scaled by the residual variance), same shapes as the values.
    - ``principal_moments`` (ascending) and ``principal_axes`` (columns, sensor-frame components,
      ``det = +1``) of the fitted inertia.
    - ``residual_rms``: root-mean-square residual per component (rad/s; rad for orientation fits).
    - ``orientation0`` / ``orientation0_stderr``: for :func:`fit_inertia_to_orientation`, the fitted
      initial orientation(s) (unit quaternions) and their standard errors (rad, a rotation vector
      about the body axes); None for angular-velocity fits.
    - ``initial_inertia``: the data-driven starting estimate (same gauge as ``inertia``).
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
    segment_starts: Float[Array, " segments"]
    initial_inertia: Float[Array, "3"] | Float[Array, "3 3"]
    covariance: Float[Array, "p p"]
    normalised: bool = eqx.field(static=True)
    method: str = eqx.field(static=True)
    torque: Any = None  # the known torque of the fit (a tuple of torques), or None: torque-free

    def _predict_with_torque(self, ts, with_orientation: bool):
        """Integrates the fitted model under its known torque from each window's start ("precise")."""
        ts = np.asarray(ts, float)
        starts = np.asarray(self.segment_starts)
        window = np.clip(np.searchsorted(starts, ts, side="right") - 1, 0, starts.shape[0] - 1)
        omega0 = self.omega0.reshape(-1, 3)
        q0 = None if self.orientation0 is None else self.orientation0.reshape(-1, 4)
        dtype = self.inertia.dtype
        out = np.zeros((ts.shape[0], 4 if with_orientation else 3))
        for k in np.unique(window):
            rows = np.flatnonzero(window == k)
            times = np.concatenate([[starts[k]], ts[rows]])
            keep = np.concatenate([[True], np.diff(times) > 0])  # a sample exactly at the start
            state = State(omega0[k], q0[k] if q0 is not None else None)
            traj = simulate(
                RigidBody(self.inertia, torque=self.torque),
                state,
                jnp.asarray(times[keep], dtype),
                accuracy="precise",
            )
            values = np.asarray(traj.orientation if with_orientation else traj.omega)
            index = np.cumsum(keep) - 1
            out[rows] = values[index[1:]]
        return jnp.asarray(out, dtype)

    def predict_omega(self, ts) -> Float[Array, "T 3"]:
        """The fitted model's angular velocity (rad/s) at times ``ts`` (s), each from its window
        (integrated under the known torque if the fit had one)."""
        if self.torque is not None:
            return self._predict_with_torque(ts, with_orientation=False)
        ts = jnp.asarray(ts, self.inertia.dtype)
        starts = self.segment_starts
        omega0 = self.omega0.reshape(-1, 3)
        window = jnp.clip(jnp.searchsorted(starts, ts, side="right") - 1, 0, starts.shape[0] - 1)
        if self.inertia.ndim == 2:
            axes = self.principal_axes
            w = torque_free_omega(self.principal_moments, omega0[window] @ axes, ts - starts[window])
            return w @ axes.T
        return torque_free_omega(self.inertia, omega0[window], ts - starts[window])

    def predict_orientation(self, ts) -> Float[Array, "T 4"]:
        """The fitted orientation (unit quaternions) at times ``ts`` (s); orientation fits only."""
        if self.orientation0 is None:
            raise ValueError("This fit has no orientation: it was fitted to angular velocity only.")
        if self.torque is not None:
            return self._predict_with_torque(ts, with_orientation=True)
        ts = jnp.asarray(ts, self.inertia.dtype)
        starts = self.segment_starts
        omega0 = self.omega0.reshape(-1, 3)
        q0 = self.orientation0.reshape(-1, 4)
        window = jnp.clip(jnp.searchsorted(starts, ts, side="right") - 1, 0, starts.shape[0] - 1)
        axes = self.principal_axes
        q_axes = _quat_from_matrix(axes)
        q = torque_free_motion(
            self.principal_moments,
            omega0[window] @ axes,
            _quat_multiply(q0[window], q_axes),
            ts - starts[window],
        )[1]
        return _quat_multiply(q, _quat_conjugate(q_axes))


# --- parametrisation -------------------------------------------------------------------------


def _moments_from_z(z):
    """Principal moments with trace 1 from two free numbers (see the module docstring)."""
    J = jax.nn.softmax(jnp.concatenate([z, jnp.zeros((1,), z.dtype)]))
    return 0.5 * jnp.stack([J[1] + J[2], J[0] + J[2], J[0] + J[1]])


def _z_from_moments(moments):
    """Inverse of :func:`_moments_from_z` for valid moments (numpy, used for the starting point)."""
    moments = np.asarray(moments, float)
    moments = moments / moments.sum()
    J = np.maximum(0.5 * moments.sum() - moments, 1e-3)  # J_k = trace/2 - I_k; keep it strictly valid
    J = J / J.sum()
    return np.log(J[:2] / J[2])


def _rotation_matrix(r):
    """Rotation matrix of the rotation vector ``r`` (Rodrigues), NaN-free with its gradient at 0."""
    angle2 = jnp.sum(r * r)
    small = angle2 < 1e-8
    safe2 = jnp.where(small, 1.0, angle2)
    angle = jnp.sqrt(safe2)
    sinc = jnp.where(small, 1.0 - angle2 / 6.0, jnp.sin(angle) / angle)
    cosc = jnp.where(small, 0.5 - angle2 / 24.0, (1.0 - jnp.cos(angle)) / safe2)
    K = jnp.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]], dtype=r.dtype)
    return jnp.eye(3, dtype=r.dtype) + sinc * K + cosc * (K @ K)


def _rotvec_from_matrix(R):
    """Rotation vector of a proper rotation matrix (numpy; starting point only)."""
    R = np.asarray(R, float)
    angle = math.acos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    if angle < 1e-8:
        return np.zeros(3)
    if angle > math.pi - 1e-6:
        axis = np.sqrt(np.maximum((np.diag(R) + 1.0) / 2.0, 0.0))
        k = int(np.argmax(axis))
        axis = R[:, k] + np.eye(3)[:, k]
        return angle * axis / np.linalg.norm(axis)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2.0 * math.sin(angle))
    return angle * axis


class _Problem(eqx.Module):
    """Residuals of the fit as a function of one flat parameter vector (all in scaled units)."""

    t: Float[Array, "segments samples"]  # time since the window start, times omega_scale
    # omega / omega_scale (0 where missing), or unit quaternions (identity where missing)
    observed: Float[Array, "segments samples 3"] | Float[Array, "segments samples 4"]
    mask: Bool[Array, "segments samples 3"]
    f_scale: Float[Array, ""]
    q_reference: Float[Array, "segments 4"] | None  # orientation fits: observed q at window starts
    weights: Float[Array, "3"]  # per-component residual weights (inverse noise, mean square 1)
    full_tensor: bool = eqx.field(static=True)
    loss_kind: str = eqx.field(static=True)
    # A known torque (tuple of AbstractTorque) fixes the scale: the motion is integrated (Dopri8,
    # forward-mode adjoint) and a log-scale parameter is fitted. omega_scale converts the scaled
    # units (omega / s, t * s) back for the torque.
    torque: Any = None
    # A traced value, not a static field: a static float differs from record to record and made
    # every new record recompile the fit (20-40 s each).
    omega_scale: Float[Array, ""] | float = 1.0
    reverse_mode: bool = eqx.field(static=True, default=False)  # the optimiser differentiates in reverse
    t_start: Float[Array, " segments"] | None = None  # window start times (s): the torque's clock

    @property
    def n_inertia_params(self) -> int:
        return (5 if self.full_tensor else 2) + (1 if self.torque is not None else 0)

    def split(self, p):
        """(inertia parameters, omega0 per window, orientation corrections per window or None)."""
        k = self.n_inertia_params
        K = self.t.shape[0]
        w0 = p[k : k + 3 * K].reshape(K, 3)
        if self.q_reference is None:
            return p[:k], w0, jnp.zeros((K, 0), p.dtype)
        return p[:k], w0, p[k + 3 * K :].reshape(K, 3)

    def initial_orientations(self, dq):
        return _quat_multiply(self.q_reference, quat_exp(dq))

    def tensor_parts(self, p_inertia):
        moments = _moments_from_z(p_inertia[:2])
        if self.torque is not None:
            moments = moments * jnp.exp(p_inertia[-1])  # absolute scale, kg m^2
        if self.full_tensor:
            return moments, _rotation_matrix(p_inertia[2:5])
        return moments, None

    def inertia(self, p_inertia):
        moments, axes = self.tensor_parts(p_inertia)
        if axes is None:
            return moments
        return (axes * moments) @ axes.T

    def predict(self, p):
        p_inertia, w0, _ = self.split(p)
        if self.torque is not None:
            return self.integrate(self.inertia(p_inertia), w0)
        moments, axes = self.tensor_parts(p_inertia)
        if axes is not None:
            w0 = w0 @ axes  # sensor -> principal components: axes^T w0
        omega = torque_free_omega(moments, w0[:, None, :], self.t)
        if axes is not None:
            omega = omega @ axes.T
        return omega

    def integrate(self, inertia, w0):
        """omega of every window with the known torque, by Dopri8 at rtol 1e-10 (scaled units)."""
        torques, s = self.torque, self.omega_scale

        def vector_field(t, w, t_start):
            tau = _total_torque(torques, t_start + t / s, State(w * s), None) / s**2
            return _euler_equations(inertia, w, tau)

        return jax.vmap(lambda w0, t, t_start: self._solve_window(vector_field, w0, t, t_start))(
            w0, self.t, self._window_starts()
        )

    def integrate_orientation(self, inertia, w0, q0):
        """(omega, q) of every window with the known torque (which may need the orientation), by
        Dopri8 at rtol 1e-10 in scaled units; unit norm of q is made attracting as in ``simulate``."""
        torques, s = self.torque, self.omega_scale

        def vector_field(t, y, t_start):
            w, q = y
            tau = _total_torque(torques, t_start + t / s, State(w * s, q), None) / s**2
            return _euler_equations(inertia, w, tau), _quat_derivative(q, w)

        def window(w0, q0, t, t_start):
            _, q = self._solve_window(vector_field, (w0, q0), t, t_start)
            return q / jnp.linalg.norm(q, axis=-1, keepdims=True)

        return jax.vmap(window)(w0, q0, self.t, self._window_starts())

    def _window_starts(self):
        if self.t_start is None:
            return jnp.zeros(self.t.shape[:1], self.t.dtype)
        return self.t_start

    def _solve_window(self, vector_field, y0, t, t_start):
        solution = diffrax.diffeqsolve(
            diffrax.ODETerm(vector_field),
            diffrax.Dopri8(),
            0.0,
            t[-1],
            None,
            y0,
            args=t_start,
            saveat=diffrax.SaveAt(ts=t),
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            adjoint=diffrax.RecursiveCheckpointAdjoint() if self.reverse_mode else diffrax.ForwardMode(),
            max_steps=200_000,
        )
        return solution.ys

    def predict_orientation(self, p):
        p_inertia, w0, dq = self.split(p)
        moments, axes = self.tensor_parts(p_inertia)
        q0 = self.initial_orientations(dq)
        if self.torque is not None:
            return self.integrate_orientation(self.inertia(p_inertia), w0, q0)
        if axes is None:
            return torque_free_motion(moments, w0[:, None, :], q0[:, None, :], self.t)[1]
        # The principal frame is the sensor frame turned by the rotation vector p_inertia[2:].
        q_axes = quat_exp(p_inertia[2:5])
        q_principal = torque_free_motion(
            moments, (w0 @ axes)[:, None, :], _quat_multiply(q0, q_axes)[:, None, :], self.t
        )[1]
        return _quat_multiply(q_principal, _quat_conjugate(q_axes))

    def raw_residuals(self, p):
        if self.q_reference is None:
            return jnp.where(self.mask, self.predict(p) - self.observed, 0.0)
        # Rotation vector from predicted to observed (small-angle form), the same for q and -q.
        relative = _quat_multiply(_quat_conjugate(self.predict_orientation(p)), self.observed)
        sign = jnp.where(relative[..., :1] < 0, -1.0, 1.0)
        return jnp.where(self.mask, 2.0 * sign * relative[..., 1:], 0.0)

    def residuals(self, p):
        """Weighted residuals whose sum of squares is the robust loss (``f^2 rho((r/f)^2)``),
        flattened."""
        r = self.raw_residuals(p) * self.weights
        if self.loss_kind == "squared":
            return r.reshape(-1)
        z = (r / self.f_scale) ** 2
        safe_z = jnp.where(z > 0, z, 1.0)
        if self.loss_kind == "huber":
            rho = jnp.where(z <= 1.0, z, 2.0 * jnp.sqrt(safe_z) - 1.0)
        elif self.loss_kind == "soft_l1":
            rho = 2.0 * (jnp.sqrt(1.0 + z) - 1.0)
        else:  # cauchy
            rho = jnp.log1p(z)
        ratio = jnp.where(z > 0, rho / safe_z, 1.0)  # -> 1 at r = 0, so the residual stays smooth
        return (r * jnp.sqrt(ratio)).reshape(-1)

    def count(self):
        return jnp.sum(self.mask).astype(self.observed.dtype)

    def loss(self, p):
        r = self.residuals(p)
        return jnp.sum(r * r) / self.count()


# --- optimisers --------------------------------------------------------------------------------


def _levenberg_marquardt(problem: _Problem, p0, steps: int, tol: float, callback):
    """Levenberg–Marquardt with Marquardt's diagonal scaling; the Jacobian by forward mode (few
    parameters, many residuals).

    Returns ``(p, history, iterations, converged, J)`` with the Jacobian at the final ``p``. The
    Jacobian appears once in the program (at the top of the loop body; the loop runs one extra,
    step-free pass to evaluate it at the final point), which halves the compile time against
    evaluating it again after the loop.
    """
    jacobian = jax.jacfwd(problem.residuals)
    n = problem.count()

    def cond(carry):
        return ~carry["exit"]

    def body(carry):
        p, r, lam, i = carry["p"], carry["r"], carry["lam"], carry["i"]
        J = jacobian(p)
        finished = carry["finished"]
        g = J.T @ r
        A = J.T @ J
        d = jnp.maximum(jnp.diag(A), 1e-12 * jnp.max(jnp.diag(A)) + 1e-300)
        f = jnp.sum(r * r)

        # Try the step, raising the damping until it lowers the loss (at most 12 tries).
        def retry_cond(c):
            _, _, f_new, tries, _ = c
            return ~finished & ((tries == 0) | (~(f_new < f) & (tries < 12)))

        def retry_body(c):
            lam, _, _, tries, _ = c
            lam = jnp.where(tries == 0, lam, lam * 4.0)
            step = jnp.linalg.solve(A + lam * jnp.diag(d), -g)
            r_new = problem.residuals(p + step)
            return lam, step, jnp.sum(r_new * r_new), tries + 1, r_new

        init = (lam, jnp.zeros_like(p), jnp.asarray(jnp.inf, f.dtype), 0, r)
        lam, step, f_new, _, r_new = jax.lax.while_loop(retry_cond, retry_body, init)
        improved = ~finished & jnp.isfinite(f_new) & (f_new < f)
        p_next = jnp.where(improved, p + step, p)
        r_next = jnp.where(improved, r_new, r)
        f_next = jnp.where(improved, f_new, f)
        lam = jnp.where(improved, jnp.maximum(lam / 5.0, 1e-12), lam)
        small_change = (f - f_next) <= tol * f_next
        small_step = jnp.max(jnp.abs(step)) <= tol * (1.0 + jnp.max(jnp.abs(p)))
        tiny_gradient = jnp.max(jnp.abs(g)) <= tol * tol * (f + 1e-300)
        converged = (improved & (small_change | small_step)) | tiny_gradient
        # No damping makes the step lower the loss: a minimum to roundoff if the last accepted step
        # barely changed the loss, a failure otherwise.
        stalled = ~finished & ~improved
        converged = converged | (stalled & (carry["last_decrease"] <= jnp.sqrt(tol)))
        decrease = jnp.where(improved, (f - f_next) / jnp.maximum(f_next, 1e-300), carry["last_decrease"])
        history = jnp.where(finished, carry["history"], carry["history"].at[i].set(f_next / n))
        if callback is not None:
            jax.debug.callback(callback, i + 1, f_next / n, ordered=True)
        i_next = jnp.where(finished, i, i + 1)
        return {
            "p": p_next,
            "r": r_next,
            "lam": lam,
            "i": i_next,
            "history": history,
            # The pass after the last step only evaluates J at the final point.
            "exit": finished,
            "finished": finished | converged | stalled | (i_next >= steps),
            "converged": carry["converged"] | (~finished & converged),
            "last_decrease": decrease,
            "J": J,
        }

    r0 = problem.residuals(p0)
    false = jnp.asarray(False)
    init = {
        "p": p0,
        "r": r0,
        "lam": jnp.asarray(1.0, p0.dtype),
        "i": jnp.asarray(0),
        "history": jnp.full((steps,), jnp.nan, p0.dtype),
        "exit": false,
        "finished": jnp.asarray(steps <= 0),
        "converged": false,
        "last_decrease": jnp.asarray(jnp.inf, p0.dtype),
        "J": jnp.zeros((r0.shape[0], p0.shape[0]), p0.dtype),
    }
    out = jax.lax.while_loop(cond, body, init)
    return out["p"], out["history"], out["i"], out["converged"], out["J"]


@functools.cache
def _default_optimizer():
    # One object for every call: the optimiser is static in the compiled fit, so a new object
    # would recompile it.
    return optax.lbfgs()


def _optax_fit(problem: _Problem, p0, optimizer, steps: int, tol: float, callback):
    optimizer = optax.with_extra_args_support(optimizer)
    state0 = optimizer.init(p0)
    try:  # line-search optimisers (L-BFGS) keep the last value and gradient in their state
        reuses_value = optax.tree_utils.tree_get(state0, "value", None) is not None
    except (KeyError, ValueError):
        reuses_value = False
    if reuses_value:
        value_and_grad = optax.value_and_grad_from_state(problem.loss)
    else:

        def value_and_grad(p, state):
            del state
            return jax.value_and_grad(problem.loss)(p)

    def cond(carry):
        _, _, i, _, done, _ = carry
        return (i < steps) & ~done

    def body(carry):
        p, state, i, history, _, previous = carry
        value, grad = value_and_grad(p, state=state)
        updates, state = optimizer.update(grad, state, p, value=value, grad=grad, value_fn=problem.loss)
        p = optax.apply_updates(p, updates)
        history = history.at[i].set(value)
        if callback is not None:
            jax.debug.callback(callback, i + 1, value, ordered=True)
        # Converged when the loss has stopped changing over the last ten iterations. An integrated
        # model's loss is smooth only to about the solver's rtol (1e-10; step-size decisions jump),
        # so changes below 1e-8 of it are noise there (and statistically irrelevant: parameters move
        # by ~1e-4 of their standard errors).
        loss_tol = tol if problem.torque is None else max(tol, 1e-8)
        previous = previous.at[i % 10].set(value)
        spread = jnp.max(previous) - jnp.min(previous)
        done = (i >= 10) & (spread <= loss_tol * jnp.abs(value))
        return p, state, i + 1, history, done, previous

    history = jnp.full((steps,), jnp.nan, p0.dtype)
    recent = jnp.full((10,), jnp.inf, p0.dtype)
    init = (p0, state0, jnp.asarray(0), history, jnp.asarray(False), recent)
    p, _, i, history, done, _ = jax.lax.while_loop(cond, body, init)
    return p, history, i, done


@eqx.filter_jit
def _run(problem: _Problem, p0, method: str, optimizer, steps: int, tol: float, callback):
    if method == "levenberg-marquardt":
        p, history, n_steps, done, J = _levenberg_marquardt(problem, p0, steps, tol, callback)
    else:
        p, history, n_steps, done = _optax_fit(problem, p0, optimizer, steps, tol, callback)
        # The integrated (torque) model is differentiable in reverse mode only on this path.
        J = (jax.jacrev if problem.reverse_mode else jax.jacfwd)(problem.residuals)(p)
    r = problem.residuals(p)
    n = problem.count()
    dof = jnp.maximum(n - p.shape[0], 1.0)
    variance = jnp.sum(r * r) / dof
    covariance = variance * jnp.linalg.pinv(J.T @ J, hermitian=True)
    raw = problem.raw_residuals(p)
    counts = jnp.sum(problem.mask, axis=(0, 1)).astype(raw.dtype)
    rms = jnp.sqrt(jnp.sum(raw * raw, axis=(0, 1)) / jnp.maximum(counts, 1.0))
    return p, history, n_steps, done, covariance, problem.loss(p), rms


# --- the data-driven starting point ----------------------------------------------------------


def _local_derivatives(ts, omega, half_width: int):
    """Value and time derivative of each component by a local quadratic least-squares fit over
    ``2 half_width + 1`` neighbouring samples (NaN-aware; a Savitzky–Golay filter for uneven times)."""
    T = ts.shape[0]
    value = np.full_like(omega, np.nan)
    slope = np.full_like(omega, np.nan)
    leverage = np.full_like(omega, np.nan)  # the hat-matrix diagonal of each sample in its own fit
    for i in range(T):
        lo, hi = max(0, i - half_width), min(T, i + half_width + 1)
        dt = ts[lo:hi] - ts[i]
        for c in range(3):
            y = omega[lo:hi, c]
            ok = np.isfinite(y)
            if ok.sum() < 4:
                continue
            scale = np.max(np.abs(dt[ok])) or 1.0
            x = dt[ok] / scale
            V = np.stack([np.ones_like(x), x, x * x], axis=1)
            coef, *_ = np.linalg.lstsq(V, y[ok], rcond=None)
            value[i, c] = coef[0]
            slope[i, c] = coef[1] / scale
            gram = V.T @ V
            if np.linalg.cond(gram) < 1e12:
                leverage[i, c] = np.linalg.inv(gram)[0, 0]  # the sample sits at x = 0
    return value, slope, leverage


def _dominant_period(ts, omega):
    """Period of the strongest oscillation in the record (via the FFT of the resampled data)."""
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
    k = int(np.argmax(power))
    return (ts[-1] - ts[0]) / k if k > 0 else ts[-1] - ts[0]


def estimate_inertia(ts, omega_observed, *, full_tensor: bool = False, half_width: int | None = None):
    """Data-driven inertia estimate from Euler's torque-free equations, which are LINEAR in the inertia.

    With ``omega`` and ``omega_dot`` from a local quadratic fit (smoothed finite differences), every
    sample gives ``I omega_dot + omega x (I omega) = 0``: three linear equations in the three
    principal moments (or six tensor entries). The right singular vector of the smallest singular
    value is the estimate, normalised to trace 1 and made physical (second moments floored at a small
    positive value). A starting point for :func:`fit_inertia`, biased by noise; not a final answer.

    Returns ``(inertia, smoothed_omega)``: moments ``(3,)`` or tensor ``(3, 3)``, and the smoothed
    record ``(T, 3)`` (NaN where too few neighbours were observed).
    """
    ts, omega = _check_data(ts, omega_observed)
    return _estimate(ts, omega, full_tensor=full_tensor, half_width=half_width)[:2]


def _estimate(ts, omega_observed, *, full_tensor: bool = False, half_width: int | None = None):
    """:func:`estimate_inertia` plus the noise per component (from the same local fits)."""
    ts = np.asarray(ts, float)
    omega = np.asarray(omega_observed, float)
    if half_width is None:
        period = _dominant_period(ts, omega)
        samples_per_period = period / max(np.median(np.diff(ts)), 1e-300)
        half_width = int(np.clip(samples_per_period / 16.0, 2, 50))
    value, slope, leverage = _local_derivatives(ts, omega, half_width)
    # One pass of outlier rejection: samples far from the local fit (5 robust sigma) are dropped.
    deviation = np.abs(omega - value)
    sigma = 1.4826 * np.nanmedian(deviation, axis=0)
    outlier = deviation > 5.0 * np.maximum(sigma, 1e-300)
    if np.any(outlier):
        omega = np.where(outlier, np.nan, omega)
        value, slope, leverage = _local_derivatives(ts, omega, half_width)
    # Noise per component: a residual about the local fit that includes the sample has variance
    # sigma^2 (1 - h), h the sample's leverage (0.49 for 5 equally spaced samples): undo that.
    scaled = np.abs(omega - value) / np.sqrt(np.clip(1.0 - leverage, 0.05, 1.0))
    noise = 1.4826 * np.nanmedian(scaled, axis=0) if np.isfinite(scaled).any() else np.full(3, np.nan)
    ok = np.all(np.isfinite(value) & np.isfinite(slope), axis=1)
    w, wd = value[ok], slope[ok]
    scale = np.sqrt(np.mean(np.sum(w * w, axis=1))) if w.size else 1.0
    w, wd = w / scale, wd / scale**2  # omega_dot scales as omega^2 in the torque-free equations
    if not full_tensor:
        w1, w2, w3 = w.T
        rows = [
            np.stack([wd[:, 0], -w2 * w3, w2 * w3], axis=1),
            np.stack([w3 * w1, wd[:, 1], -w3 * w1], axis=1),
            np.stack([-w1 * w2, w1 * w2, wd[:, 2]], axis=1),
        ]
        A = np.concatenate(rows, axis=0)
        if A.shape[0] < 3:
            return np.full(3, 1.0 / 3.0), value, noise
        v = np.linalg.svd(A, full_matrices=False)[2][-1]
        v = v * np.sign(v.sum()) if v.sum() != 0 else np.ones(3)
        moments = np.abs(v) / np.abs(v).sum()
        J = np.maximum(0.5 - moments, 2e-3)
        J = J / J.sum()
        return 0.5 * (J.sum() - J), value, noise
    # Symmetric tensor entries (Ixx, Iyy, Izz, Ixy, Ixz, Iyz): I omega_dot + omega x (I omega) = 0.
    basis = np.zeros((6, 3, 3))
    for k, (i, j) in enumerate([(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]):
        basis[k, i, j] = basis[k, j, i] = 1.0
    cols = []
    for B in basis:
        Bw = w @ B.T
        cols.append((wd @ B.T + np.cross(w, Bw)).reshape(-1))
    A = np.stack(cols, axis=1)
    if A.shape[0] < 6:
        return np.eye(3) / 3.0, value, noise
    v = np.linalg.svd(A, full_matrices=False)[2][-1]
    tensor = np.einsum("k,kij->ij", v, basis)
    tensor = tensor * np.sign(np.trace(tensor)) if np.trace(tensor) != 0 else np.eye(3)
    # Physical projection: second-moment matrix S = trace/2 - I must be positive definite.
    tensor = tensor / np.trace(tensor)
    S = 0.5 * np.eye(3) - tensor
    evals, evecs = np.linalg.eigh(S)
    evals = np.maximum(evals, 2e-3)
    S = (evecs * (evals / evals.sum())) @ evecs.T  # trace 1, so I = (1 - S) / 2 has trace 1
    return 0.5 * (np.eye(3) - S), value, noise


# --- the public entry point ----------------------------------------------------------------


def _check_times(ts):
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
    x = np.asarray(x)
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise TypeError(f"{name} must hold real numbers, got dtype {x.dtype}.")
    return x.astype(float)


def _check_data(ts, omega_observed):
    ts = _check_times(ts)
    omega = _real_array(omega_observed, "omega_observed")
    if omega.shape != (ts.shape[0], 3):
        raise ValueError(
            f"omega_observed must have shape (T, 3) = ({ts.shape[0]}, 3) to match ts, got {omega.shape}."
        )
    if np.any(np.isinf(omega)):
        raise ValueError("omega_observed contains inf; mark missing samples with NaN instead.")
    return ts, omega


def _check_quaternions(ts, q_observed):
    ts = _check_times(ts)
    q = _real_array(q_observed, "orientation_observed")
    if q.shape != (ts.shape[0], 4):
        raise ValueError(
            f"orientation_observed must have shape (T, 4) = ({ts.shape[0]}, 4) (unit quaternions, scalar "
            f"first) to match ts, got {q.shape}."
        )
    if np.any(np.isinf(q)):
        raise ValueError("orientation_observed contains inf; mark missing samples with NaN instead.")
    q = np.where(np.isnan(q).any(axis=1, keepdims=True), np.nan, q)  # a quaternion is all or nothing
    norm_error = np.abs(np.linalg.norm(q, axis=1) - 1.0)
    if np.nanmax(norm_error, initial=0.0) > 1e-5:
        row = int(np.nanargmax(norm_error))
        raise ValueError(
            f"orientation_observed must hold unit quaternions; row {row} has norm "
            f"{np.linalg.norm(q[row]):.8g}. Normalise them (rigidjax.quat_normalize) first."
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
    """Body-frame angular velocity (rad/s) from orientation samples by central differences:
    ``omega_i = log(q_{i-1}^* q_{i+1}) / (t_{i+1} - t_{i-1})`` (one-sided at the ends; NaN where a
    neighbour is missing). ``q`` and ``-q`` are the same orientation. A starting point for fits."""
    ts, q = _check_quaternions(ts, q_observed)
    q = _align_signs(q)
    T = ts.shape[0]
    lo = np.clip(np.arange(T) - 1, 0, T - 1)
    hi = np.clip(np.arange(T) + 1, 0, T - 1)
    conj = q[lo] * np.array([1.0, -1.0, -1.0, -1.0])
    rel = np.asarray(_quat_multiply(conj, q[hi]))
    rel = rel * np.where(rel[:, :1] < 0, -1.0, 1.0)
    vec_norm = np.linalg.norm(rel[:, 1:], axis=1)
    angle = 2.0 * np.arctan2(vec_norm, rel[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        axis = np.where(vec_norm[:, None] > 0, rel[:, 1:] / vec_norm[:, None], 0.0)
        omega = axis * (angle / (ts[hi] - ts[lo]))[:, None]
    return omega


class _Data(NamedTuple):
    problem: _Problem
    p0: np.ndarray
    starts: np.ndarray  # window start times (s)
    inertia_start: np.ndarray
    residual_unit: float  # residuals are in units of this (omega_scale for omega, 1 rad for q)
    omega_scale: float
    noise: np.ndarray  # per-component noise estimate, in the residual's units (rad/s or rad)


def _windows(ts, valid_rows, segments, n_params):
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
    if segments == "auto":
        # About one dominant oscillation per window: short enough that a poor start's frequency
        # error cannot slip by a whole cycle within a window, long enough to see the cycle.
        period = _dominant_period(ts, omega)
        segments = int(np.clip(round((ts[-1] - ts[0]) / period), 1, max(1, ts.shape[0] // 8)))
    if not (isinstance(segments, int | np.integer) and not isinstance(segments, bool) and segments >= 1):
        raise ValueError(f"segments must be a positive integer or 'auto', got {segments!r}.")
    return int(segments)


def _inertia_start(inertia_init, estimate, full_tensor):
    if inertia_init is None:
        return estimate
    start = np.asarray(inertia_init, float)
    expected = (3, 3) if full_tensor else (3,)
    if start.shape != expected:
        raise ValueError(f"inertia_init must have shape {expected}, got {start.shape}.")
    return start / (np.trace(start) if full_tensor else start.sum())


def _inertia_params(inertia_start, full_tensor):
    if not full_tensor:
        return _z_from_moments(inertia_start)
    evals, evecs = np.linalg.eigh(inertia_start)
    if np.linalg.det(evecs) < 0:
        evecs[:, 0] = -evecs[:, 0]
    return np.concatenate([_z_from_moments(evals), _rotvec_from_matrix(evecs)])


def _window_start_values(windows, smoothed, fallback, init, segments, name):
    if init is not None:
        values = np.asarray(init, float).reshape(-1, 3)
        if values.shape[0] != segments:
            raise ValueError(f"{name} must have shape (3,) or ({segments}, 3), got {np.shape(init)}.")
        return values
    values = []
    for a, b in windows:
        rows = [r for r in range(a, b) if np.all(np.isfinite(smoothed[r]))]
        rows = rows or [r for r in range(a, b) if np.all(np.isfinite(fallback[r]))]
        values.append(smoothed[rows[0]] if np.all(np.isfinite(smoothed[rows[0]])) else fallback[rows[0]])
    return np.stack(values)


def _torque_estimate(ts, omega, torques, full_tensor, inertia_free, orientations=None):
    """Inertia from the LINEAR equations I omega_dot + omega x (I omega) = tau(t, omega) (least
    squares with omega, omega_dot from local quadratic fits) as (trace-1 shape, trace); falls back
    to the torque-free shape with its scale by least squares if the unconstrained solve is not
    physical."""
    period = _dominant_period(ts, omega)
    half_width = int(np.clip(period / max(np.median(np.diff(ts)), 1e-300) / 16.0, 2, 50))
    value, slope, _ = _local_derivatives(ts, omega, half_width)
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
    if full_tensor:
        pairs = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    else:
        pairs = [(0, 0), (1, 1), (2, 2)]
    basis = np.zeros((len(pairs), 3, 3))
    for k, (i, j) in enumerate(pairs):
        basis[k, i, j] = basis[k, j, i] = 1.0
    A = np.stack([(wd @ B.T + np.cross(w, w @ B.T)).reshape(-1) for B in basis], axis=1)
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
    segments = _resolve_segments(segments, ts, omega)
    valid = np.isfinite(omega)
    n_params = (5 if full_tensor else 2) + 3 * segments + (1 if torques is not None else 0)
    if valid.sum() < n_params + 1:
        raise ValueError(
            f"Too few samples: {int(valid.sum())} observed components in {ts.shape[0]} samples for "
            f"{n_params} parameters ({segments} window(s)); need more than the number of parameters."
        )
    bounds, windows = _windows(ts, valid.all(axis=1) | valid.any(axis=1), segments, n_params)
    estimate, smoothed, estimated = _estimate(ts, omega, full_tensor=full_tensor)
    scale_start = None
    if torques is not None:
        if inertia_init is None:
            estimate, scale_start = _torque_estimate(ts, omega, torques, full_tensor, estimate)
        else:
            init = np.asarray(inertia_init, float)
            scale_start = float(np.trace(init) if init.ndim == 2 else init.sum())
    inertia_start = _inertia_start(inertia_init, estimate, full_tensor)
    w0 = _window_start_values(windows, smoothed, omega, omega0_init, segments, "omega0_init")
    # Scaled units: omega / s and t * s (the torque-free motion is homogeneous), so residuals are O(1).
    omega_scale = float(np.sqrt(np.nanmean(np.sum(np.nan_to_num(omega) ** 2, axis=1)))) or 1.0
    M = int(np.diff(bounds).max())
    t_win = np.zeros((segments, M))
    obs_win = np.zeros((segments, M, 3))
    mask_win = np.zeros((segments, M, 3), bool)
    for k, (a, b) in enumerate(windows):
        t_win[k, : b - a] = (ts[a:b] - ts[a]) * omega_scale
        t_win[k, b - a :] = t_win[k, b - a - 1]  # padding repeats the last time: non-decreasing
        obs_win[k, : b - a] = np.nan_to_num(omega[a:b] / omega_scale)
        mask_win[k, : b - a] = valid[a:b]
    # Noise per component, from the scatter about the local fits (robust: a scaled MAD). Weighting
    # the residuals by its inverse is generalised least squares: a gyro axis that is quieter (or
    # sees a smaller signal) is not drowned by a noisier one, and the standard errors stay honest.
    if noise is None:
        sigma = np.where(np.isfinite(estimated) & (estimated > 0), estimated, np.nanmax(estimated))
    elif isinstance(noise, str) and noise == "equal":
        sigma = np.ones(3)
    else:
        sigma = np.broadcast_to(np.asarray(noise, float), (3,))
        if not np.all(np.isfinite(sigma) & (sigma > 0)):
            raise ValueError(f"noise must be positive finite standard deviations (rad/s), got {noise!r}.")
    if not np.all(np.isfinite(sigma) & (sigma > 0)):
        sigma = np.ones(3)
    sigma = np.maximum(sigma, 1e-3 * sigma.max())  # at most 1000x weight contrast
    reference = float(np.sqrt(np.mean(sigma**2)))
    weights = reference / sigma
    if f_scale is None:
        f_scale_scaled = 3.0 * max(reference / omega_scale, 1e-12)
    else:
        f_scale_scaled = float(f_scale) / omega_scale
    p_inertia = _inertia_params(inertia_start, full_tensor)
    if torques is not None:
        p_inertia = np.concatenate([p_inertia, [math.log(scale_start)]])
        inertia_start = inertia_start * scale_start
    p0 = np.concatenate([p_inertia, (w0 / omega_scale).reshape(-1)])
    problem = _Problem(
        t=jnp.asarray(t_win, dtype),
        observed=jnp.asarray(obs_win, dtype),
        mask=jnp.asarray(mask_win),
        f_scale=jnp.asarray(f_scale_scaled, dtype),
        q_reference=None,
        weights=jnp.asarray(weights, dtype),
        full_tensor=full_tensor,
        loss_kind=loss,
        torque=torques,
        omega_scale=jnp.asarray(omega_scale, dtype),
        reverse_mode=reverse_mode,
        t_start=jnp.asarray(ts[bounds[:-1]], dtype),
    )
    return _Data(problem, p0, ts[bounds[:-1]], inertia_start, omega_scale, omega_scale, estimated)


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
    omega_fd = omega_from_orientations(ts, q)
    segments = _resolve_segments(segments, ts, omega_fd)
    valid_rows = np.isfinite(q[:, 0])
    n_params = (5 if full_tensor else 2) + 6 * segments + (1 if torques is not None else 0)
    bounds, windows = _windows(ts, valid_rows, segments, n_params)
    estimate, smoothed, fd_noise = _estimate(ts, omega_fd, full_tensor=full_tensor)
    scale_start = None
    if torques is not None:
        if inertia_init is None:
            estimate, scale_start = _torque_estimate(
                ts, omega_fd, torques, full_tensor, estimate, _align_signs(q)
            )
        else:
            init = np.asarray(inertia_init, float)
            scale_start = float(np.trace(init) if init.ndim == 2 else init.sum())
    inertia_start = _inertia_start(inertia_init, estimate, full_tensor)
    w0 = _window_start_values(windows, smoothed, omega_fd, omega0_init, segments, "omega0_init")
    q_aligned = _align_signs(q)
    if orientation0_init is not None:
        q_ref = np.asarray(orientation0_init, float).reshape(-1, 4)
        if q_ref.shape[0] != segments:
            raise ValueError(
                f"orientation0_init must have shape (4,) or ({segments}, 4), "
                f"got {np.shape(orientation0_init)}."
            )
        q_ref = q_ref / np.linalg.norm(q_ref, axis=1, keepdims=True)
    else:
        q_ref = np.stack([q_aligned[a + int(np.argmax(valid_rows[a:b]))] for a, b in windows])
    omega_scale = float(np.sqrt(np.nanmean(np.sum(omega_fd**2, axis=1)))) or 1.0
    M = int(np.diff(bounds).max())
    t_win = np.zeros((segments, M))
    obs_win = np.zeros((segments, M, 4))
    obs_win[..., 0] = 1.0
    mask_win = np.zeros((segments, M, 3), bool)
    for k, (a, b) in enumerate(windows):
        t_win[k, : b - a] = (ts[a:b] - ts[a]) * omega_scale
        obs_win[k, : b - a] = np.where(valid_rows[a:b, None], np.nan_to_num(q_aligned[a:b]), [1.0, 0, 0, 0])
        mask_win[k, : b - a] = valid_rows[a:b, None]
    # Noise of the orientation samples (rad) from the roughness of the finite-difference omega:
    # central differences of independent angle errors e have scatter sqrt(2) e / (2 dt).
    rough = float(np.sqrt(np.nanmean(fd_noise**2)))
    noise_rad = float(rough * 2.0 * np.median(np.diff(ts)) / np.sqrt(2.0))
    if f_scale is None:
        f_scale = 3.0 * max(noise_rad, 1e-12)
    p_inertia = _inertia_params(inertia_start, full_tensor)
    if torques is not None:
        p_inertia = np.concatenate([p_inertia, [math.log(scale_start)]])
        inertia_start = inertia_start * scale_start
    p0 = np.concatenate([p_inertia, (w0 / omega_scale).reshape(-1), np.zeros(3 * segments)])
    problem = _Problem(
        t=jnp.asarray(t_win, dtype),
        observed=jnp.asarray(obs_win, dtype),
        mask=jnp.asarray(mask_win),
        f_scale=jnp.asarray(float(f_scale), dtype),
        q_reference=jnp.asarray(q_ref, dtype),
        weights=jnp.ones(3, dtype),
        full_tensor=full_tensor,
        loss_kind=loss,
        torque=torques,
        omega_scale=jnp.asarray(omega_scale, dtype),
        reverse_mode=reverse_mode,
        t_start=jnp.asarray(ts[bounds[:-1]], dtype),
    )
    return _Data(problem, p0, ts[bounds[:-1]], inertia_start, 1.0, omega_scale, np.full(3, noise_rad))


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
    return torques


def _check_options(loss, method, optimizer, inertia_trace, known_moment):
    if loss not in _LOSSES:
        raise ValueError(f"loss must be one of {_LOSSES}, got {loss!r}.")
    if method is None:
        method = "optax"
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}.")
    if inertia_trace is not None and known_moment is not None:
        raise ValueError("Give at most one scale: inertia_trace or known_moment, not both.")
    return method


def _solve(data: _Data, *, full_tensor, method, optimizer, steps, tol, dtype, callback, scale):
    problem = data.problem
    if steps is None:
        steps = 200 if method == "levenberg-marquardt" else 2000
    if method == "optax" and optimizer is None:
        optimizer = _default_optimizer()
    p0 = jnp.asarray(data.p0, dtype)
    # optax's own internals (L-BFGS's memory indices) mix int32 and int64, which a user's strict
    # dtype promotion would reject; rigidjax's arithmetic does not depend on the setting.
    with jax.numpy_dtype_promotion("standard"):
        p, history, n_steps, converged, covariance, final_loss, rms = _run(
            problem, p0, method, optimizer, int(steps), float(tol), callback
        )
    inertia_trace, known_moment = scale
    omega_scale = data.omega_scale
    segments = data.starts.shape[0]

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
    inertia, w0_fit, _ = user_values(p)
    jac_inertia, jac_w0, jac_dq = jax.jacfwd(user_values)(p)

    def stderr(jac):
        flat = jac.reshape(-1, p.shape[0])
        variance = jnp.einsum("ip,pq,iq->i", flat, covariance, flat)
        return jnp.sqrt(jnp.maximum(variance, 0.0)).reshape(jac.shape[:-1])

    tensor = inertia if full_tensor else jnp.diag(inertia)
    evals, evecs = jnp.linalg.eigh(tensor)
    evecs = evecs * jnp.where(jnp.linalg.det(evecs) < 0, jnp.array([-1.0, 1.0, 1.0], dtype), 1.0)
    initial = jnp.asarray(data.inertia_start, dtype)
    if inertia_trace is not None:
        initial = initial * inertia_trace
    elif known_moment is not None:
        diag0 = np.diag(data.inertia_start) if full_tensor else data.inertia_start
        initial = initial * (known_moment[1] / diag0[known_moment[0]])
    one = (lambda x: x[0]) if segments == 1 else (lambda x: x)
    if problem.q_reference is not None:
        q0 = problem.initial_orientations(problem.split(p)[2])
        orientation0, orientation0_stderr = one(q0), one(stderr(jac_dq))
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
        inertia_stderr=stderr(jac_inertia),
        omega0_stderr=one(stderr(jac_w0)),
        orientation0=orientation0,
        orientation0_stderr=orientation0_stderr,
        principal_moments=evals,
        principal_axes=evecs,
        residual_rms=rms * data.residual_unit,
        noise_estimate=jnp.asarray(data.noise, dtype),
        segment_starts=jnp.asarray(data.starts, dtype),
        initial_inertia=initial,
        covariance=covariance,
        normalised=inertia_trace is None and known_moment is None and problem.torque is None,
        method=method,
        torque=problem.torque,
    )


_COMMON_ARGS_DOC = """\
    - `inertia_init`: starting inertia (moments, or a tensor with ``full_tensor``); by default a
      data-driven estimate (:func:`estimate_inertia`). Any positive scale; only ratios matter.
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
      by reverse mode) or ``"levenberg-marquardt"`` (Gauss–Newton with damping, the Jacobian by
      forward mode: few parameters, many residuals). Both reach the same optimum; Levenberg–Marquardt
      needs 4-15x fewer iterations and is ~2.5x faster per fit once compiled (0.2 s vs 0.5-0.6 s on a
      240-sample record, ``benchmarks/fit_methods.py``): pass it when fitting many records.
    - `optimizer`: any optax ``GradientTransformation`` (default ``optax.lbfgs()``) for ``"optax"``.
      It is part of the compiled fit: pass the same object again to avoid a recompile.
    - `steps`: iteration limit (default 200 for Levenberg–Marquardt, 2000 for optax).
    - `loss`: ``"squared"``, or a robust loss against outliers: ``"huber"``, ``"soft_l1"``,
      ``"cauchy"`` (as in ``scipy.optimize.least_squares``) with scale `f_scale` (in the units of the
      residual; default three times the noise level estimated from the data).
    - `inertia_trace` / `known_moment`: fix the scale gauge: the trace of the inertia (kg m^2; e.g.
      ``2 * sum(m r^2)`` from a mass and a shape), or ``(k, I_kk)``: one known diagonal entry in
      sensor axes. Without either, the result has trace 1.
    - `tol`: relative tolerance on the loss for convergence.
    - `dtype`: float dtype of the fit (default: JAX's default float; float64 with x64 enabled).
    - `callback`: called on the host as ``callback(iteration, loss)`` after every iteration (a
      progress display); the loss is in the optimiser's scaled units.
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
      is then integrated (Dopri8, rtol 1e-10, forward-mode derivatives) instead of the closed form.
    {common}
    **Returns:** an :class:`InertiaFit` (``orientation0`` is None).
    """
    ts, omega = _check_data(ts, omega_observed)
    method = _check_options(loss, method, optimizer, inertia_trace, known_moment)
    dtype = np.dtype(dtype) if dtype is not None else jnp.result_type(float)
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
        callback=callback,
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
) -> InertiaFit:
    """Fits the inertia of a body to orientation samples (motion capture): torque-free, or under a
    known torque.

    The residual of a sample is the rotation vector (rad) from the predicted to the observed
    orientation, ``2 sign(w) vec(q_pred^* q_obs)``, so ``q`` and ``-q`` are the same observation.
    Each window fits its initial angular velocity and its initial orientation (a rotation-vector
    correction of the observed one).

    **Arguments:**

    - `ts`: sample times (s), strictly increasing, shape ``(T,)``.
    - `orientation_observed`: ``(T, 4)`` unit quaternions (scalar first, body -> space); a row with
      a NaN is a missing sample.
    - `orientation0_init`: starting orientation per window ``(4,)`` or ``(segments, 4)``; by
      default the observed one at each window start.
    - `torque`: a KNOWN body-frame torque acting during the record, which may depend on the
      orientation: ``GravityTorque(mass, com)`` for a heavy top or a gyroscope on a pivot (then the
      inertia is about the pivot), a space-frame ``ConstantTorque``, ``Torque(fn)``, or a tuple. It
      fixes the scale (inertia in kg m^2); (omega, q) is then integrated (Dopri8, rtol 1e-10,
      forward-mode derivatives) instead of the closed form.
    {common}
    **Returns:** an :class:`InertiaFit` with ``orientation0`` and ``orientation0_stderr`` (rad, about
    the body axes).
    """
    ts, q = _check_quaternions(ts, orientation_observed)
    method = _check_options(loss, method, optimizer, inertia_trace, known_moment)
    dtype = np.dtype(dtype) if dtype is not None else jnp.result_type(float)
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
        callback=callback,
        scale=(inertia_trace, known_moment),
    )


fit_inertia.__doc__ = fit_inertia.__doc__.replace("    {common}\n", _COMMON_ARGS_DOC)
fit_inertia_to_orientation.__doc__ = fit_inertia_to_orientation.__doc__.replace(
    "    {common}\n", _COMMON_ARGS_DOC
)
