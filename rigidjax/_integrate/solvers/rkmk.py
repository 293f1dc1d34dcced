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

:func:`simulate_structure_preserving` runs a rigidjax scene at a fixed step with these solvers or
the Lie–Poisson splittings of :mod:`rigidjax._splitting` and returns a :class:`rigidjax.Trajectory`.
"""

import math
from collections.abc import Callable
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..._checks import check_finite, check_last_axis, check_rotation_quaternion, common_float
from ..._dynamics.inertia import principal_axes
from ..._dynamics.models import AbstractModel, HeavyTop, State
from ..._kinematics.quaternion import _quat_conjugate, _quat_exp, _quat_from_matrix, _quat_multiply
from ..trajectory import Trajectory
from .splitting import (
    HeavyTopSplitting,
    LiePoissonSplitting,
    heavy_top_splitting_step,
    heavy_top_weight_com,
    splitting_step,
)

# ---------------------------------------------------------------------------------------------
# Lie-group pieces


def dexpinv(theta: Float[ArrayLike, "... 3"], omega: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """``d(theta)/dt`` for ``q = q0 ⊗ Exp(theta)`` rotating at body rate ``omega``, truncated after
    the second commutator: ``omega + theta x omega / 2 + theta x (theta x omega) / 12``. NaN/inf
    inputs are an error."""
    theta, omega = common_float(theta, omega, names=["theta", "omega"])
    check_last_axis(theta, 3, "theta")
    check_last_axis(omega, 3, "omega")
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


def _rkmk(accel, t0, omega0, q0, h, args, tableau, f0=None):
    """One RKMK step. Returns ``(omega1, q1, theta1, (err_omega, err_q), f0, f1)`` where ``f0``,
    ``f1`` are ``d(omega)/dt`` at the start and at the new point (FSAL)."""
    a_rows, b, b_err, c, _ = _TABLEAUX[tableau]
    dtype = omega0.dtype
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
            f_i = accel(t0 + c[i] * h, omega_i, q_i, args)
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

    ``angular_acceleration(t, omega, q, args)`` returns body-frame ``d(omega)/dt`` (rad/s^2) for
    arrays of the shapes given here (it may use leading batch axes). Returns ``(omega, q)`` at
    ``t + h``; ``q`` is ``q ⊗ Exp(theta)`` and so unit to roundoff.
    """
    _check_tableau(tableau)
    omega, q = jnp.asarray(omega), jnp.asarray(q)
    check_last_axis(omega, 3, "omega")
    check_last_axis(q, 4, "q")
    omega = check_finite(omega, "omega", "rkmk_step")
    q = check_rotation_quaternion(q, "q", "rkmk_step")
    h = check_finite(jnp.asarray(h), "h", "rkmk_step")
    omega1, q1, *_ = _rkmk(angular_acceleration, t, omega, q.astype(omega.dtype), h, args, tableau)
    return omega1, q1


def rigid_body_vector_field(angular_acceleration: Callable) -> Callable:
    """The ODE ``(omega, q) -> (d(omega)/dt, dq/dt)`` of ``angular_acceleration(t, omega, q, args)``
    with ``dq/dt = q ⊗ (0, omega) / 2``, as a diffrax vector field ``vf(t, y, args)``.

    :class:`RKMK` uses only its first component (the orientation kinematics are built in); any
    other diffrax solver integrates it as a plain ODE (reference solutions)."""

    def vf(t, y, args):
        omega, q = y
        pure = jnp.concatenate([jnp.zeros_like(omega[..., :1]), omega], axis=-1)
        return angular_acceleration(t, omega, q, args), 0.5 * _quat_multiply(q, pure)

    return vf


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

    def _at(self, t):
        omega0, q0 = self.y0
        omega1, _ = self.y1
        dt = self.t1 - self.t0
        s = jnp.asarray((t - self.t0) / jnp.where(dt == 0, 1.0, dt), omega0.dtype)
        dt = jnp.asarray(dt, omega0.dtype)
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
        omega1, q1, theta1, err, f0, f1 = _rkmk(accel, t0, omega0, q0, t1 - t0, args, self.tableau, f0)
        dense_info = dict(y0=y0, y1=(omega1, q1), theta1=theta1, f0=f0, f1=f1)
        return (omega1, q1), err, dense_info, f1, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


# ---------------------------------------------------------------------------------------------
# A rigidjax scene at a fixed step with a structure-preserving solver.


def _sample_grid(ts, dt):
    """Per-interval step counts ``n_i = ceil(dt_i / dt)`` (concrete) and their maximum."""
    ts_np = np.asarray(ts, dtype=np.float64)
    gaps = np.diff(ts_np)
    counts = (
        np.maximum(1, np.ceil(gaps / dt * (1 - 1e-12))).astype(np.int64) if gaps.size else np.zeros(0, int)
    )
    return counts, int(counts.max()) if counts.size else 0


def _flatten_model(model, batch, dtype):
    leaves = model.body_leaves()
    n = math.prod(batch)
    flat = []
    for leaf in leaves:
        value = jnp.asarray(leaf.get(model))
        core_shape = value.shape[value.ndim - leaf.core :]
        flat.append(jnp.broadcast_to(value, batch + core_shape).reshape((n,) + core_shape).astype(dtype))
    return leaves, flat


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces, for the no-recompile test
def _structure_preserving_traced(model, omega0, q0, ts, counts, args, solver, n_max, has_orientation):
    dtype = omega0.dtype
    batch = jnp.broadcast_shapes(model.batch_shape(), omega0.shape[:-1], q0.shape[:-1])
    n = math.prod(batch)
    leaves, flat = _flatten_model(model, batch, dtype)
    omega0 = jnp.broadcast_to(omega0, batch + (3,)).reshape(n, 3)
    q0 = jnp.broadcast_to(q0, batch + (4,)).reshape(n, 4)
    values = dict(zip([leaf.label for leaf in leaves], flat, strict=True))

    if isinstance(solver, RKMK):

        def accel_one(body_values, t, w, q, a):
            body = model.replace_body_leaves(leaves, body_values)
            return body.angular_acceleration(t, State(w, q), a)

        def accel(t, w, q, a):
            return jax.vmap(accel_one, in_axes=(0, None, 0, 0, None))(flat, t, w, q, a).astype(dtype)

        # The state carries d(omega)/dt at its own time: FSAL, one evaluation fewer per step.
        def to_y(w, q):
            return w, q, accel(ts[0], w, q, args)

        def from_y(y):
            return y[0], y[1]

        def step(t, y, h):
            w, q, _, _, _, f1 = _rkmk(accel, t, y[0], y[1], h, args, solver.tableau, y[2])
            return w, q, f1

    else:
        inertia = values["inertia"]
        if inertia.ndim == 3:  # (n, 3, 3) tensors: integrate in each body's principal axes
            inertia, axes = principal_axes(inertia)  # axes: principal -> body components
            axes_q = _quat_from_matrix(axes)
        else:
            axes = axes_q = None

        def to_principal(v):
            return v if axes is None else jnp.einsum("nji,nj->ni", axes, v)

        if isinstance(solver, HeavyTopSplitting):
            weight_com = to_principal(
                heavy_top_weight_com(values["mass"], values["com"], values["gravity"], dtype)
            )

            def step(t, y, h):
                return heavy_top_splitting_step(inertia, weight_com, *y, h, solver.splitting_order)

        else:

            def step(t, y, h):
                return splitting_step(inertia, *y, h, solver.splitting_order)

        def to_y(w, q):
            if axes is not None:
                w, q = to_principal(w), _quat_multiply(q, axes_q)
            return inertia * w, q

        def from_y(y):
            w, q = y[0] / inertia, y[1]
            if axes is not None:
                w, q = jnp.einsum("nij,nj->ni", axes, w), _quat_multiply(q, _quat_conjugate(axes_q))
            return w, q

    def interval(y, xs):
        t_start, gap, count = xs
        h = gap / count.astype(dtype)

        def body(k, y):
            y_new = step(t_start + k.astype(dtype) * h, y, h)
            keep = k < count
            return jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), y_new, y)

        y = jax.lax.fori_loop(0, n_max, body, y)
        return y, from_y(y)

    y0 = to_y(omega0, q0)
    xs = (ts[:-1], jnp.diff(ts), counts)
    _, (omegas, qs) = jax.lax.scan(interval, y0, xs)
    omega = jnp.concatenate([omega0[None], omegas], axis=0)  # (T, n, 3)
    q = jnp.concatenate([q0[None], qs], axis=0)
    finite = jnp.all(jnp.isfinite(omega), axis=(0, 2)) & jnp.all(jnp.isfinite(q), axis=(0, 2))
    q_norm = jnp.linalg.norm(q, axis=-1)
    q_norm_error = jnp.max(jnp.abs(q_norm - 1.0), axis=0).reshape(batch)
    n_times = ts.shape[0]
    omega = jnp.moveaxis(omega, 0, 1).reshape(batch + (n_times, 3))
    q = jnp.moveaxis(q / q_norm[..., None], 0, 1).reshape(batch + (n_times, 4))
    stats = {
        "num_steps": jnp.sum(counts),
        "chunk_size": n,
        "quaternion_norm_error": q_norm_error if has_orientation else None,
    }
    model_b = model.replace_body_leaves(leaves, [v.reshape(batch + v.shape[1:]) for v in flat])
    return Trajectory(
        ts=ts,
        omega=omega,
        orientation=q if has_orientation else None,
        model=model_b,
        success=finite.reshape(batch),
        stats=stats,
    )


_structure_preserving_impl = eqx.filter_jit(_structure_preserving_traced)


def simulate_structure_preserving(
    model: AbstractModel,
    state0: State,
    ts: Float[ArrayLike, " T"],
    solver: "HeavyTopSplitting | LiePoissonSplitting | RKMK",
    dt: float,
    *,
    args: Any = None,
) -> Trajectory:
    """Integrates a scene at a fixed step with a structure-preserving solver; samples it at ``ts``.

    Args:
        model: :class:`FreeBody`, :class:`RigidBody` or :class:`HeavyTop`, possibly batched (leading
            axes on its array fields, as in :func:`rigidjax.simulate`).
        state0: initial :class:`State`; batch axes broadcast against the model's. Without an
            orientation (scenes that do not need one) the output orientation is None.
        ts: strictly increasing sample times (s), ``(T,)``, concrete (not traced): they fix the
            number of steps. ``ts[0]`` is the initial time.
        solver: chooses the method; the physical parameters always come from ``model`` (the
            solver's own numeric fields are not used). :class:`HeavyTopSplitting` for a
            :class:`HeavyTop` without extra torques, :class:`LiePoissonSplitting` for a torque-free
            body (a ``(..., 3, 3)`` inertia tensor is diagonalised once per body and the motion
            integrated in its principal axes); :class:`RKMK` for any scene.
        dt: largest step (s), a Python float. Each interval ``[ts[i], ts[i+1]]`` is cut into
            ``ceil((ts[i+1] - ts[i]) / dt)`` equal steps, so samples fall on steps (no interpolation).
        args: passed to user torques.

    Returns:
        A :class:`Trajectory` (``success`` is False for a body whose state became non-finite;
        there is no other failure mode at a fixed step); ``stats["num_steps"]`` is the number of
        steps per body and ``stats["quaternion_norm_error"]`` the largest ``| |q| - 1 |`` before
        the output was normalised. Differentiable (forward and reverse mode) with respect to the
        model and the state.
    """
    if not isinstance(model, AbstractModel):
        raise TypeError(f"model must be a rigidjax scene such as HeavyTop, got {type(model).__name__}.")
    if not isinstance(state0, State):
        raise TypeError(f"state0 must be a rigidjax.State, got {type(state0).__name__}.")
    if isinstance(solver, HeavyTopSplitting):
        if not isinstance(model, HeavyTop) or model.torques:
            raise ValueError(
                "HeavyTopSplitting integrates a HeavyTop under gravity alone; for extra torques or "
                f"other scenes use RKMK (got {type(model).__name__})."
            )
    elif isinstance(solver, LiePoissonSplitting):
        if not model.torque_free:
            raise ValueError(
                "LiePoissonSplitting integrates torque-free bodies only; use HeavyTopSplitting for a "
                f"HeavyTop or RKMK for torques (got {type(model).__name__})."
            )
    elif not isinstance(solver, RKMK):
        raise TypeError(
            f"solver must be HeavyTopSplitting, LiePoissonSplitting or RKMK, got {type(solver).__name__}."
        )
    if state0.orientation is None and model.needs_orientation:
        raise ValueError(
            f"{type(model).__name__} needs an orientation: pass State(omega, orientation=q) with a unit "
            "quaternion q."
        )
    try:
        ts_np = np.asarray(ts, dtype=np.float64)
    except jax.errors.TracerArrayConversionError as err:
        raise ValueError(
            "simulate_structure_preserving: ts must be concrete (they fix the number of steps); "
            "do not trace them under jit."
        ) from err
    if ts_np.ndim != 1 or ts_np.shape[0] < 1:
        raise ValueError(f"ts must be a 1-D array of at least one time, got shape {ts_np.shape}.")
    if np.any(np.diff(ts_np) <= 0) or not np.all(np.isfinite(ts_np)):
        raise ValueError("ts must be finite and strictly increasing; ts[0] is the initial time.")
    if not (isinstance(dt, int | float) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive Python float (it fixes the number of steps), got {dt!r}.")
    counts, n_max = _sample_grid(ts_np, dt)
    dtypes = [state0.omega.dtype] + [
        x.dtype for x in jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_inexact_array))
    ]
    if state0.orientation is not None:
        dtypes.append(state0.orientation.dtype)
    dtype = np.result_type(*[np.dtype(d) for d in dtypes])  # numpy promotion: widen float32 + float64
    model = jax.tree_util.tree_map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, model)
    from ..simulate import _check_inputs  # (_simulate imports this module

    model, _, _, _ = _check_inputs(
        model,
        model.body_leaves(),
        state0.omega.astype(dtype),
        None,
        jnp.asarray(ts_np, dtype),
        dtype,
        where="simulate_structure_preserving",
    )
    omega0 = state0.omega.astype(dtype)
    omega0 = eqx.error_if(
        omega0,
        ~jnp.all(jnp.isfinite(omega0)),
        "simulate_structure_preserving: state0.omega contains NaN or inf.",
    )
    has_orientation = state0.orientation is not None
    if has_orientation:
        q0 = state0.orientation.astype(dtype)
        q0 = eqx.error_if(
            q0,
            ~jnp.all(jnp.isfinite(q0)),
            "simulate_structure_preserving: state0.orientation contains NaN or inf.",
        )
        norm = jnp.linalg.norm(q0, axis=-1, keepdims=True)
        tol = 1e-6 if dtype == jnp.float64 else 1e-4
        q0 = eqx.error_if(
            q0,
            jnp.any(jnp.abs(norm - 1.0) > tol),
            "simulate_structure_preserving: state0.orientation is not a unit quaternion; normalise it.",
        )
        q0 = q0 / norm
    else:
        q0 = jnp.array([1.0, 0.0, 0.0, 0.0], dtype)
    return _structure_preserving_impl(
        model,
        omega0,
        q0,
        jnp.asarray(ts_np, dtype),
        jnp.asarray(counts, jnp.int32),
        args,
        solver,
        n_max,
        has_orientation,
    )
