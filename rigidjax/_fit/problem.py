"""The fit's residuals as a function of one flat parameter vector, and its parametrisation.

Every parameter value is a valid inertia; nothing is clipped or penalised:

- principal moments: ``I_k = (J_i + J_j) / 2`` with second moments ``J = softmax(z1, z2, 0)``
  (``J_k = int x_k^2 dm`` up to scale). Positive ``J`` is exactly the set of moments satisfying the
  triangle inequalities strictly, and ``sum(J) = 1`` fixes the scale gauge: ``trace(I) = 1``.
- full tensor: the same moments in principal axes ``R(r)`` (rotation vector ``r``), so the tensor is
  ``R diag(I) R^T``.
- a known torque fixes the scale: one more parameter, the log of the trace.

After the inertia come the initial angular velocity of each window (scaled by ``omega_scale``) and,
for orientation records, a rotation-vector correction of each window's initial orientation.

The forward model is the closed-form torque-free motion (exact, cheap and smooth in the parameters,
so no integration error enters the fit), or under a known torque Dopri8 at rtol 1e-10 through
:func:`rigidjax._integrate.driver.solve`.
"""

import itertools
import math
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._closed_form.torque_free import _torque_free_motion, _torque_free_omega
from .._dynamics.equations import _euler_equations
from .._dynamics.state import State
from .._dynamics.torques import _total_torque
from .._integrate.driver import solve
from .._kinematics.quaternion import _quat_conjugate, _quat_derivative, _quat_exp, _quat_multiply


def _moments_from_z(z):
    """Principal moments with trace 1 from two free numbers (see the module docstring)."""
    J = jax.nn.softmax(jnp.concatenate([z, jnp.zeros((1,), z.dtype)]))
    return 0.5 * jnp.stack([J[1] + J[2], J[0] + J[2], J[0] + J[1]])


# How close to the flat-body edge (the largest moment the sum of the other two) a fitted body is taken
# as on it, relative: I3 >= (1 - FLAT_BODY_EDGE) (I1 + I2). A square plate whose thickness is 1/1000
# of its side lies 1e-6 from the edge (I1 + I2 - I3 = 2 t^2 / (2 a^2 + 2 t^2) of I1 + I2), so only
# thinner bodies count as on it.
FLAT_BODY_EDGE = 1e-6

# Residuals above this many times the record's noise estimate mean the fitted motion does not follow
# the record (a wrong basin): the fit's restarts, its RuntimeWarning and `InertiaFit.warnings` use it.
NOISE_RATIO_LIMIT = 2.0


def _on_flat_body_edge(moments) -> bool:
    """Whether principal moments (numpy, any scale) lie on the flat-body edge of the physical moments:
    the largest the sum of the other two within ``FLAT_BODY_EDGE``, relative. A fit ends there for a
    flat body and from a start whose moments are wrongly ordered."""
    return bool(_beyond_edge(*np.sort(np.asarray(moments, dtype=float))))


def _beyond_edge(low, middle, high):
    """The flat-body edge's condition on sorted moments (NumPy or traced)."""
    return high >= (1 - FLAT_BODY_EDGE) * (low + middle)


def _unmeasured_edge_distance(inertia_stderr, inertia, moments, axes, full_tensor, known_moment):
    """``inertia_stderr`` infinite for the largest moment (its entries of the tensor) of a fit on the
    flat-body edge, where the record bounds that moment from one side only: its distance from the
    edge is not measured. The covariance's projector sees that only while the saturated softmax
    that keeps the moments physical still has a gradient there; in float32 it underflows to zero,
    and the standard error came out 0. A known moment keeps its zero error."""
    on_edge = _beyond_edge(moments[0], moments[1], moments[2])
    if full_tensor:
        on_largest = jnp.abs(axes[:, 2, None] * axes[None, :, 2]) > 1e-3
    else:
        on_largest = jnp.arange(3) == jnp.argmax(inertia)
    if known_moment is not None:
        known = jnp.arange(3) == known_moment[0]
        on_largest = on_largest & ~(known[:, None] & known[None, :] if full_tensor else known)
    return jnp.where(on_edge & on_largest, jnp.inf, inertia_stderr)


def _reordered_starts(data, p0, full_tensor):
    """``p0`` with the moments of a generic body, ``(2, 3, 4) / 9`` (well inside the physical moments
    and well apart, where a start from very noisy data can lie by the flat-body edge or have two
    moments nearly equal), in each of the six orders, about the estimate's axes."""
    start = np.asarray(data.inertia_start, float)
    axes = np.linalg.eigh(start)[1] if full_tensor else None
    n = len(_inertia_params(start, full_tensor))
    for order in itertools.permutations(range(3)):
        reordered = np.array([2.0, 3.0, 4.0])[list(order)] / 9.0
        inertia = reordered if axes is None else (axes * reordered) @ axes.T
        start_p = np.array(p0, float)
        start_p[:n] = _inertia_params(inertia, full_tensor)
        yield start_p


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


LOSSES = ("squared", "huber", "soft_l1", "cauchy")
"""The fit's losses, in the order of :attr:`_Problem.loss_index`."""

WINDOW_MAX_STEPS = 200_000
"""Step limit of one window's integration under a known torque."""


class _Problem(eqx.Module):
    """Residuals of the fit as a function of one flat parameter vector (all in scaled units)."""

    t: Float[Array, "segments samples"]  # time since the window start, times omega_scale
    # omega / omega_scale (0 where missing), or unit quaternions (identity where missing)
    observed: Float[Array, "segments samples 3"] | Float[Array, "segments samples 4"]
    mask: Bool[Array, "segments samples 3"]
    f_scale: Float[Array, ""]
    q_reference: Float[Array, "segments 4"] | None  # orientation fits: observed q at window starts
    weights: Float[Array, "3"]  # per-component residual weights (inverse noise, mean square 1)
    # The loss, an index into LOSSES: traced, so that one compiled fit serves every loss.
    loss_index: Int[Array, ""]
    full_tensor: bool = eqx.field(static=True)
    # A known torque (tuple of AbstractTorque) fixes the scale: the motion is integrated (Dopri8,
    # forward-mode adjoint unless reverse_mode) and a log-scale parameter is fitted. omega_scale
    # converts the scaled units (omega / s, t * s) back for the torque.
    torque: Any = None
    # A traced value, not a static field: a static float would differ from record to record, and
    # every new record would recompile the fit (20-40 s each).
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
        return _quat_multiply(self.q_reference, _quat_exp(dq))

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
        omega = _torque_free_omega(moments, w0[:, None, :], self.t, checked=False)
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
        """One window's states at its sample times ``t`` (from 0): Dopri8 at rtol 1e-10 through
        the package's one driver. A failed solve leaves its unreached samples at inf (the
        optimisers reject such a step; the fit reports a non-finite final loss): no error callback
        in the compiled fit, so JAX's persistent cache keeps it."""
        adjoint = diffrax.RecursiveCheckpointAdjoint() if self.reverse_mode else diffrax.ForwardMode()
        return solve(
            vector_field,
            diffrax.Dopri8(),
            y0,
            t,
            t0=0.0,
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            args=t_start,
            adjoint=adjoint,
            max_steps=WINDOW_MAX_STEPS,
        ).ys

    def predict_orientation(self, p):
        p_inertia, w0, dq = self.split(p)
        moments, axes = self.tensor_parts(p_inertia)
        q0 = self.initial_orientations(dq)
        if self.torque is not None:
            return self.integrate_orientation(self.inertia(p_inertia), w0, q0)
        if axes is None:
            return _torque_free_motion(moments, w0[:, None, :], q0[:, None, :], self.t, checked=False)[1]
        # The principal frame is the sensor frame turned by the rotation vector p_inertia[2:].
        q_axes = _quat_exp(p_inertia[2:5])
        q_principal = _torque_free_motion(
            moments, (w0 @ axes)[:, None, :], _quat_multiply(q0, q_axes)[:, None, :], self.t, checked=False
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
        return self._weighted(self.raw_residuals(p))

    def residuals_and_raw(self, p):
        """``(residuals(p), raw_residuals(p))`` from one evaluation of the model."""
        raw = self.raw_residuals(p)
        return self._weighted(raw), raw

    def _weighted(self, raw):
        r = raw * self.weights
        z = (r / self.f_scale) ** 2
        safe_z = jnp.where(z > 0, z, 1.0)
        index = self.loss_index
        huber = jnp.where(z <= 1.0, z, 2.0 * jnp.sqrt(safe_z) - 1.0)
        soft_l1 = 2.0 * (jnp.sqrt(1.0 + z) - 1.0)
        cauchy = jnp.log1p(z)
        rho = jnp.select([index == 1, index == 2], [huber, soft_l1], cauchy)
        # -> 1 at r = 0, so the residual stays smooth; exactly 1 (no derivative) for "squared".
        ratio = jnp.where((z > 0) & (index != 0), rho / safe_z, 1.0)
        return (r * jnp.sqrt(ratio)).reshape(-1)

    def count(self):
        return jnp.sum(self.mask).astype(self.observed.dtype)

    def loss(self, p):
        r = self.residuals(p)
        return jnp.sum(r * r) / self.count()


def _inertia_params(inertia_start, full_tensor):
    """The inertia parameters of a starting inertia (numpy): ``z`` and, for a tensor, ``r``."""
    if not full_tensor:
        return _z_from_moments(inertia_start)
    evals, evecs = np.linalg.eigh(inertia_start)
    if np.linalg.det(evecs) < 0:
        evecs[:, 0] = -evecs[:, 0]
    return np.concatenate([_z_from_moments(evals), _rotvec_from_matrix(evecs)])
