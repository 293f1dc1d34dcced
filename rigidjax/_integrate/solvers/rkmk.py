"""Runge–Kutta–Munthe-Kaas (RKMK) integration on R^3 x SO(3) for arbitrary torques.

The state of one body is its body-frame angular velocity ``omega`` (3,) (rad/s) and a unit
quaternion ``q`` (4,) (scalar first, body to space), with ``d(omega)/dt = f(t, omega, q)`` for any
user function ``f`` and ``dq/dt = q ⊗ (0, omega) / 2``. A step of length ``h`` writes the new
orientation as ``q1 = q0 ⊗ Exp(theta)`` with ``theta`` in the Lie algebra R^3 and runs an explicit
Runge–Kutta tableau on ``(omega, theta)``, where ``theta`` obeys
``d(theta)/dt = dexpinv(theta, omega) = omega + theta x omega / 2 + theta x (theta x omega) / 12``
(the right-trivialised inverse derivative of the exponential, truncated after the second
commutator: Munthe-Kaas (1998) needs terms up to order p - 2, so this is exact enough for order 5).
``Exp(theta) = (cos(|theta|/2), sin(|theta|/2) theta / |theta|)`` is a unit quaternion, so ``|q|``
stays 1 up to roundoff by construction, with no projection.

Tableaux: ``"dopri5"`` (Dormand–Prince 5(4), 7 stages, FSAL) and ``"bosh3"`` (Bogacki–Shampine
3(2), 4 stages, FSAL). The embedded lower-order solution gives the error estimate, so
:class:`RKMK` is a diffrax ``AbstractAdaptiveSolver`` usable with ``PIDController``.

:func:`rigidjax.simulate` runs a scene with it (``solver=RKMK(), dt0=...``) through the same driver
as every other solver.
"""

from collections.abc import Callable
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..._checks import (
    as_float_array,
    check_batch_shapes,
    check_callable,
    check_finite,
    check_last_axis,
    check_rotation_quaternion,
    common_float,
    compiled_when_eager,
    error_if,
)
from ..._dynamics.torques import broadcasts_to
from ..._kinematics.quaternion import _quat_exp, _quat_kinematics, _quat_multiply
from .direction import time_direction

# ---------------------------------------------------------------------------------------------
# Lie-group pieces


@compiled_when_eager
def dexpinv(theta: Float[ArrayLike, "... 3"], omega: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """``d(theta)/dt`` for ``q = q0 ⊗ Exp(theta)`` rotating at body rate ``omega``, truncated after
    the second commutator: ``omega + theta x omega / 2 + theta x (theta x omega) / 12``. NaN/inf
    inputs are an error."""
    theta, omega = common_float(theta, omega, names=["theta", "omega"])
    check_last_axis(theta, 3, "theta")
    check_last_axis(omega, 3, "omega")
    check_batch_shapes("dexpinv", ("theta", theta, 1), ("omega", omega, 1))
    theta = check_finite(theta, "theta", "dexpinv")
    omega = check_finite(omega, "omega", "dexpinv")
    return _dexpinv(theta, omega)


def _dexpinv(theta, omega):
    t_x_w = jnp.cross(theta, omega)
    return omega + 0.5 * t_x_w + jnp.cross(theta, t_x_w) / 12.0


# ---------------------------------------------------------------------------------------------
# Tableaux: (a rows, b, b - b_hat, c, order). Both are FSAL: the last stage is at the new point.

_TABLEAUX: dict[str, tuple] = {
    "bosh3": (
        ((), (1 / 2,), (0.0, 3 / 4), (2 / 9, 1 / 3, 4 / 9)),
        (2 / 9, 1 / 3, 4 / 9, 0.0),
        (2 / 9 - 7 / 24, 1 / 3 - 1 / 4, 4 / 9 - 1 / 3, -1 / 8),
        (0.0, 1 / 2, 3 / 4, 1.0),
        3,
    ),
    "dopri5": (
        (
            (),
            (1 / 5,),
            (3 / 40, 9 / 40),
            (44 / 45, -56 / 15, 32 / 9),
            (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
            (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
            (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
        ),
        (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0),
        (
            35 / 384 - 1951 / 21600,
            0.0,
            500 / 1113 - 22642 / 50085,
            125 / 192 - 451 / 720,
            -2187 / 6784 + 12231 / 42400,
            11 / 84 - 649 / 6300,
            -1 / 60,
        ),
        (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0),
        5,
    ),
}


def _check_tableau(tableau: str):
    if tableau not in _TABLEAUX:
        raise ValueError(f"tableau must be one of {sorted(_TABLEAUX)}, got {tableau!r}.")


def _combine(coeffs, ks, h):
    """``h * sum_j coeffs[j] ks[j]`` over the nonzero coefficients (None when all are zero)."""
    total = None
    for a, k in zip(coeffs, ks, strict=False):
        if a != 0.0:
            term = a * k
            total = term if total is None else total + term
    return None if total is None else h * total


def _rkmk(accel, t0, omega0, q0, h, args, tableau, f0=None, stage_dt=None):
    """One RKMK step. Returns ``(omega1, q1, theta1, (err_omega, err_q), f0, f1)`` where ``f0``,
    ``f1`` are ``d(omega)/dt`` at the start and at the new point (FSAL). ``stage_dt``: the step in
    ``accel``'s own time, for the stages' times (default ``h``; a diffrax term wrapped for
    integration backward in time runs forward in ``-t``)."""
    a_rows, b, b_err, c, _ = _TABLEAUX[tableau]
    dtype = omega0.dtype
    stage_dt = h if stage_dt is None else stage_dt
    h = jnp.asarray(h).astype(dtype)
    k_w, k_th = [], []
    omega_i = theta_i = None
    for i, row in enumerate(a_rows):
        if i == 0:
            omega_i, theta_i, q_i = omega0, jnp.zeros_like(omega0), q0
            f_i = accel(t0, omega0, q0, args) if f0 is None else f0
            f0 = f_i
            k_th.append(omega0)  # dexpinv(0, omega) = omega
        else:
            omega_i = omega0 + _combine(row, k_w, h)
            theta_i = _combine(row, k_th, h)
            q_i = _quat_multiply(q0, _quat_exp(theta_i))
            f_i = accel(t0 + c[i] * stage_dt, omega_i, q_i, args)
            k_th.append(_dexpinv(theta_i, omega_i))
        k_w.append(jnp.asarray(f_i, dtype))
    # FSAL: the last row of a is b, so the last stage point is the solution.
    omega1, theta1, q1, f1 = omega_i, theta_i, q_i, k_w[-1]
    err_omega = _combine(b_err, k_w, h)
    theta_hat = theta1 - _combine(b_err, k_th, h)
    err_q = q1 - _quat_multiply(q0, _quat_exp(theta_hat))
    return omega1, q1, theta1, (err_omega, err_q), f0, f1


def rkmk_step(
    angular_acceleration: Callable,
    t: Float[ArrayLike, ""],
    omega: Float[ArrayLike, "... 3"],
    q: Float[ArrayLike, "... 4"],
    h: Float[ArrayLike, ""],
    args: Any = None,
    tableau: str = "dopri5",
) -> tuple[Float[Array, "... 3"], Float[Array, "... 4"]]:
    """One RKMK step of length ``h`` (s) from ``(omega, q)`` at time ``t``.

    **Arguments:**

    - `angular_acceleration`: ``f(t, omega, q, args)`` returning body-frame ``d(omega)/dt``
      (rad/s^2) for arrays of the shapes given here (it may use leading batch axes).
    - `t`: the time at the start of the step (s).
    - `omega`: body angular velocity ``(..., 3)`` (rad/s).
    - `q`: unit quaternion ``(..., 4)``, scalar first, body to space.
    - `h`: the step (s).
    - `args`: passed to ``angular_acceleration``.
    - `tableau`: ``"dopri5"`` (order 5) or ``"bosh3"`` (order 3).

    **Returns:**

    ``(omega, q)`` at ``t + h``; ``q`` is ``q ⊗ Exp(theta)`` and so unit to roundoff.
    """
    _check_tableau(tableau)
    where = "rkmk_step"
    omega, q = common_float(omega, q, names=["omega", "q"])
    check_last_axis(omega, 3, "omega")
    check_last_axis(q, 4, "q")
    t, h = (as_float_array(x, name).astype(omega.dtype) for x, name in ((t, "t"), (h, "h")))
    for x, name in ((t, "t"), (h, "h")):
        if x.ndim != 0:
            raise ValueError(f"{where}: {name} must be a scalar (s), got shape {tuple(x.shape)}.")
    batch = check_batch_shapes(where, ("omega", omega, 1), ("q", q, 1))
    omega = jnp.broadcast_to(check_finite(omega, "omega", where), batch + (3,))
    q = jnp.broadcast_to(check_rotation_quaternion(q, "q", where), batch + (4,))
    # t reaches the result only through the user's angular acceleration: its check is tied to omega.
    omega = error_if(omega, ~jnp.isfinite(t), f"{where}: t contains NaN or inf.")
    h = check_finite(h, "h", where)
    rate = jax.eval_shape(angular_acceleration, t, omega, q, args)
    if not (hasattr(rate, "shape") and broadcasts_to(rate.shape, omega.shape)):
        raise ValueError(
            f"{where}: angular_acceleration must return d(omega)/dt of omega's shape {omega.shape} "
            f"(or one that broadcasts to it), got {getattr(rate, 'shape', type(rate).__name__)}."
        )
    omega1, q1, *_ = _rkmk(angular_acceleration, t, omega, q, h, args, tableau)
    omega1 = error_if(
        omega1,
        ~jnp.isfinite(omega1),
        f"{where}: the step's omega is NaN or inf: angular_acceleration returned NaN or inf, or "
        "overflowed, within the step.",
    )
    return omega1, q1


def rigid_body_vector_field(angular_acceleration: Callable) -> Callable:
    """The ODE ``(omega, q) -> (d(omega)/dt, dq/dt)`` of ``angular_acceleration(t, omega, q, args)``
    with ``dq/dt = q ⊗ (0, omega) / 2``, as a diffrax vector field ``vf(t, y, args)``.

    :class:`RKMK` uses only its first component (the orientation kinematics are built in); any
    other diffrax solver integrates it as a plain ODE (reference solutions)."""

    check_callable(
        angular_acceleration,
        "rigid_body_vector_field: angular_acceleration",
        "f(t, omega, q, args) (four arguments)",
        4,
    )

    return _RigidBodyVectorField(angular_acceleration)


class _RigidBodyVectorField(eqx.Module):
    """A module rather than a closure: terms of the same ``angular_acceleration`` have the same
    structure, so a jitted ``diffeqsolve`` compiles once for them."""

    angular_acceleration: Callable

    def __call__(self, t, y, args):
        omega, q = y
        return self.angular_acceleration(t, omega, q, args), _quat_kinematics(q, omega)


class _GeodesicHermiteInterpolation(diffrax.AbstractLocalInterpolation):
    """Dense output of an RKMK step: cubic Hermite in ``omega`` (end slopes ``f0``, ``f1``) and in
    the algebra ``theta`` (slopes ``omega0`` and ``dexpinv(theta1, omega1)``), ``q = q0 ⊗ Exp(theta)``:
    third order, and unit quaternions between steps."""

    t0: Any
    t1: Any
    y0: Any
    y1: Any
    theta1: Any
    f0: Any
    f1: Any
    direction: Any

    def _at(self, t):
        omega0, q0 = self.y0
        omega1, _ = self.y1
        dt = self.t1 - self.t0
        s = jnp.asarray((t - self.t0) / jnp.where(dt == 0, 1.0, dt), omega0.dtype)
        dt = jnp.asarray(self.direction * dt, omega0.dtype)  # the slopes are per unit of the caller's time
        h00 = (1 + 2 * s) * (1 - s) ** 2
        h10 = s * (1 - s) ** 2
        h01 = s * s * (3 - 2 * s)
        h11 = s * s * (s - 1)
        omega = h00 * omega0 + h10 * dt * self.f0 + h01 * omega1 + h11 * dt * self.f1
        theta = h10 * dt * omega0 + h01 * self.theta1 + h11 * dt * _dexpinv(self.theta1, omega1)
        return omega, _quat_multiply(q0, _quat_exp(theta))

    def evaluate(self, t0, t1=None, left=True):
        del left
        if t1 is None:
            return self._at(t0)
        return jax.tree_util.tree_map(lambda a, b: a - b, self._at(t1), self._at(t0))


class RKMK(diffrax.AbstractAdaptiveSolver):
    """Runge–Kutta–Munthe-Kaas on ``(omega, q)``: adaptive (embedded error estimate), unit
    quaternions by construction, any torque.

    The state is the pytree ``(omega, q)`` (body angular velocity ``(..., 3)``, unit quaternion
    ``(..., 4)``). The term's vector field returns ``(d(omega)/dt, dq/dt)``; only ``d(omega)/dt`` is
    used (the kinematics ``dq/dt = q ⊗ (0, omega) / 2`` are built in). Build it with
    :func:`rigid_body_vector_field`::

        term = diffrax.ODETerm(rigid_body_vector_field(lambda t, w, q, args: ...))
        diffrax.diffeqsolve(term, RKMK("dopri5"), t0, t1, None, (omega0, q0),
                            stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8))

    ``tableau``: ``"dopri5"`` (order 5, error estimate of order 4) or ``"bosh3"`` (order 3).
    The error estimate covers ``omega`` and the quaternion (``q1 - q0 ⊗ Exp(theta_hat)``).
    """

    tableau: str = eqx.field(static=True, default="dopri5")

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., _GeodesicHermiteInterpolation]] = _GeodesicHermiteInterpolation

    def __check_init__(self):
        _check_tableau(self.tableau)

    def order(self, terms):
        return _TABLEAUX[self.tableau][4]

    def init(self, terms, t0, t1, y0, args):
        return jnp.asarray(self._accel(terms)(t0, *y0, args), y0[0].dtype)

    @staticmethod
    def _accel(terms):
        return lambda t, omega, q, args: terms.vf(t, (omega, q), args)[0]

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        omega0, q0 = y0
        accel = self._accel(terms)
        f0 = jax.lax.cond(
            made_jump, lambda: jnp.asarray(accel(t0, omega0, q0, args), omega0.dtype), lambda: solver_state
        )
        direction = time_direction(terms)
        h = direction * (t1 - t0)  # in the caller's time
        omega1, q1, theta1, err, f0, f1 = _rkmk(accel, t0, omega0, q0, h, args, self.tableau, f0, t1 - t0)
        dense_info = dict(y0=y0, y1=(omega1, q1), theta1=theta1, f0=f0, f1=f1, direction=direction)
        return (omega1, q1), err, dense_info, f1, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)
