"""Lie–Poisson splitting for the free rigid body and the heavy top (McLachlan 1993; Touma & Wisdom
1994; Dullweber, Leimkuhler & McLachlan 1997).

The state of one body is its body-frame angular momentum ``L`` (3,) and its orientation ``q`` (4,),
a unit quaternion scalar first that maps body to space (``dq/dt = q ⊗ (0, omega) / 2``,
``omega = L / I``). The Hamiltonian ``H = sum_i L_i^2 / (2 I_i)`` is split into its three terms;
the flow of ``H_i`` for a time ``h`` is exact: with ``theta = h L_i / I_i`` (``L_i`` is constant
under it), ``L`` turns about body axis ``i`` by ``-theta`` (``dL/dt = L x omega``) and
``q <- q ⊗ (cos(theta/2), sin(theta/2) e_i)``. Each sub-flow is therefore a rotation: ``|L|``
is kept to roundoff, and so is the space-frame angular momentum ``R(q) L`` (the rotation
applied to ``q`` undoes the one applied to ``L``); only each step's rounding accumulates, as a
random walk (``|L|`` of tumbling bodies over 4e5 steps of 0.01 s: up to 1e-13 relative in
float64, 3e-6 to 8e-5 in float32; the rotations are written as ``L + (c - 1) L + s L x e_i`` with
``c - 1 = -2 sin^2(theta/2)``, since a rounded ``cos`` of a small angle repeats its error every
step). ``q`` is normalised at the start of each step, against the steady drift of ``|q|`` that the
rotations' roundoff would otherwise accumulate. The energy is not conserved exactly
but its error stays bounded (the map is symplectic), with no secular drift.

Order 2 is the Strang composition ``H1(h/2) H2(h/2) H3(h) H2(h/2) H1(h/2)``; order 4 composes it
with the Yoshida/Suzuki triple jump ``S(w1 h) S(w0 h) S(w1 h)``, ``w1 = 1 / (2 - 2^(1/3))``,
``w0 = 1 - 2 w1``.

The heavy top adds ``V(q) = m g (R(q) com) . Z`` (gravity along space -Z). Its flow for a time ``h``
is a kick: ``q`` is fixed, so the body-frame gravity torque ``tau = m g (R^T Z) x com`` is constant
and ``L <- L + h tau`` is exact. The kick conserves the vertical angular momentum ``(R L) . Z``
exactly (``R tau = m g Z x (R com)`` has no Z component), and the free-body maps conserve all of
``R L``, so every composition conserves ``L_Z`` to roundoff. Order 2 is ``K(h/2) S(h) K(h/2)`` with
``S`` the free-body Strang map (symmetric, hence order 2); order 4 is its Yoshida triple jump.

Arrays carry bodies on leading axes (``L`` is ``(..., 3)``, ``q`` is ``(..., 4)``, ``inertia``
``(..., 3)`` broadcasts against them), so a batch needs no ``vmap`` (though ``vmap`` works too).
"""

import abc
import functools
from collections.abc import Callable
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..._checks import (
    as_float_array,
    check_batch_shapes,
    check_finite,
    check_last_axis,
    check_rotation_quaternion,
    common_float,
    compiled_once,
    compiled_when_eager,
    error_if,
    is_tensor_shape,
    is_traced,
)
from ..._dynamics.inertia import check_inertia
from ..._dynamics.models import replace_static
from ..._dynamics.torques import POSITIVE_GRAVITY, POSITIVE_MASS, gravity_torque
from ..._kinematics.quaternion import _quat_kinematics, _quat_multiply
from ..._numerics import short_norm
from .direction import time_direction

_YOSHIDA_W1 = 1.0 / (2.0 - 2.0 ** (1.0 / 3.0))
_YOSHIDA_W0 = 1.0 - 2.0 * _YOSHIDA_W1


def _axis_flow(inertia, L, q, h, i: int):
    """Exact flow of ``H_i = L_i^2 / (2 I_i)`` for a time ``h``."""
    j, k = (i + 1) % 3, (i + 2) % 3
    theta = h * L[..., i] / inertia[..., i]
    half = 0.5 * theta
    sin_half, cos_half = jnp.sin(half), jnp.cos(half)
    # The rotation as L + (c - 1) L + s L x e_i with c - 1 = -2 sin^2(theta/2): the rounded cos of a
    # small angle missed c^2 + s^2 = 1 by the same amount at every step of a steady tumble, and |L|
    # drifted linearly (float32, 4e5 steps of 0.01 s: 2e-3; now 3e-6).
    s = 2.0 * sin_half * cos_half
    c_minus_1 = -2.0 * sin_half * sin_half
    Lj, Lk = L[..., j], L[..., k]
    parts = [None, None, None]
    parts[i] = L[..., i]
    parts[j] = Lj + (c_minus_1 * Lj + s * Lk)
    parts[k] = Lk + (c_minus_1 * Lk - s * Lj)
    L_new = jnp.stack(parts, axis=-1)
    zero = jnp.zeros_like(half)
    vec = [zero, zero, zero]
    vec[i] = sin_half
    r = jnp.stack([cos_half] + vec, axis=-1)
    return L_new, _quat_multiply(q, r)


def _strang(inertia, L, q, h):
    L, q = _axis_flow(inertia, L, q, 0.5 * h, 0)
    L, q = _axis_flow(inertia, L, q, 0.5 * h, 1)
    L, q = _axis_flow(inertia, L, q, h, 2)
    L, q = _axis_flow(inertia, L, q, 0.5 * h, 1)
    L, q = _axis_flow(inertia, L, q, 0.5 * h, 0)
    return L, q


def splitting_step(inertia, L, q, h, order: int = 2):
    """One step of length ``h`` of the free body's splitting map of the given ``order`` (2 or 4).

    ``inertia``: principal moments ``(..., 3)`` (kg m^2); ``L``: body angular momentum ``(..., 3)``;
    ``q``: unit quaternion ``(..., 4)``, scalar first, body to space; ``h``: the step (s), a scalar.
    The batch axes broadcast against each other. Returns ``(L, q)`` after the step. A non-physical
    inertia, a zero quaternion or NaN/inf raise at run time.
    """
    _check_order(order)
    inertia, L, q, h = _checked_state("splitting_step", inertia, L, q, h)
    return _splitting_step(inertia, L, q, h, order)


def _checked_n_steps(n_steps, where: str) -> int:
    """``n_steps`` as an ``int``; a ``ValueError`` unless it is a non-negative integer (0: the
    initial state)."""
    if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer) or n_steps < 0:
        raise ValueError(f"{where}: n_steps must be a non-negative integer (a Python int), got {n_steps!r}.")
    return int(n_steps)


def _check_order(order) -> int:
    """``order`` as a Python int (2 or 4: NumPy integers included, 4.0 and True not)."""
    if isinstance(order, bool | np.bool_) or not isinstance(order, int | np.integer) or order not in (2, 4):
        raise ValueError(f"order must be 2 or 4, got {order!r}.")
    return int(order)


def _checked_state(where, inertia, L, q, h, names=("L", "q", "h"), **extra):
    """The public steps' and runs' arguments: one float dtype; shapes, a scalar step and the batch
    shapes checked while tracing; values at run time; ``L`` and ``q`` broadcast to the batch shape
    of all arrays. ``names``: the caller's names of ``L``, ``q`` and the step. ``extra``: more
    per-body arrays, ``name=(array, core axes)`` (a core axis is a vector ``(..., 3)``), returned
    after the step in the same dtype; their values are the caller's to check."""
    l_name, q_name, h_name = names
    _check_principal(inertia, where)
    inertia, L, q, *more = common_float(
        inertia, L, q, *[x for x, _ in extra.values()], names=["inertia", *names[:2], *extra]
    )
    h = as_float_array(h, h_name).astype(L.dtype)  # the step follows the state's dtype
    cores = [core for _, core in extra.values()]
    for x, name, size in ((inertia, "inertia", 3), (L, l_name, 3), (q, q_name, 4)):
        check_last_axis(x, size, name)
    for x, name, core in zip(more, extra, cores, strict=True):
        if core:
            check_last_axis(x, 3, name)
    if h.ndim != 0:
        raise ValueError(f"{where}: {h_name} must be a scalar (s), got shape {tuple(h.shape)}.")
    batch = check_batch_shapes(
        where,
        ("inertia", inertia, 1),
        (l_name, L, 1),
        (q_name, q, 1),
        *[(name, x, core) for x, name, core in zip(more, extra, cores, strict=True)],
    )
    inertia = check_inertia(inertia, name=f"{where}: inertia")
    L = jnp.broadcast_to(check_finite(L, l_name, where), batch + (3,))
    q = jnp.broadcast_to(check_rotation_quaternion(q, q_name, where), batch + (4,))
    return inertia, L, q, check_finite(h, h_name, where), *more


def _unit(q):
    """``q / |q|``: each step starts from a unit quaternion. The sub-flows are rotations, but their
    roundoff drifts ``|q|`` steadily (float32: 6.7e-10 per step, 2.7e-4 after 4e5 steps), and the
    heavy top's gravity torque reads ``R(q)`` as if ``|q| = 1``; a ``q`` given off unit norm means
    the rotation of ``q / |q|``."""
    return q / short_norm(q, keepdims=True)


def _composed(strang, L, q, h, order: int):
    """The second-order map ``strang(L, q, h)`` from a unit ``q``: itself (order 2) or Yoshida's
    triple jump of it (order 4)."""
    q = _unit(q)
    if order == 2:
        return strang(L, q, h)
    if order == 4:
        # A loop over the three weights rather than three inlined Strang maps: the inlined form,
        # vmapped inside a loop, hung the XLA CPU runtime (jax on this machine) at run time.
        weights = jnp.array([_YOSHIDA_W1, _YOSHIDA_W0, _YOSHIDA_W1], dtype=L.dtype)

        def sub(state, w):
            return strang(*state, w * h), None

        return jax.lax.scan(sub, (L, q), weights)[0]
    raise ValueError(f"order must be 2 or 4, got {order!r}.")


def _splitting_step(inertia, L, q, h, order: int = 2):
    return _composed(functools.partial(_strang, inertia), L, q, h, order)


def _check_principal(inertia, who: str):
    """Trace-time ValueError for a ``(..., 3, 3)`` tensor: the axis flows need principal moments."""
    if np.ndim(inertia) >= 2 and np.shape(inertia)[-2:] == (3, 3):
        raise ValueError(
            f"{who} needs principal moments (..., 3), got a (..., 3, 3) inertia tensor: diagonalise it "
            "with rigidjax.principal_axes and express the state (and com) in those axes, or use "
            "rigidjax.simulate(..., solver=..., dt0=...), which does that for you. (A batch of three "
            "bodies' moments, shape (3, 3), reads as one tensor, as everywhere in rigidjax: give it a "
            "second batch axis, (3, 1, 3).)"
        )


def _checked_moments(inertia, where):
    inertia = as_float_array(inertia, "inertia")
    _check_principal(inertia, where)
    check_last_axis(inertia, 3, "inertia")
    return check_inertia(inertia, name=f"{where}: inertia")


def _require_parameters(solver, name: str, constructor: str):
    if solver.inertia is None:
        raise ValueError(
            f"{name}() without the scene's parameters works only through rigidjax.simulate, which takes "
            f"them from the model; as a diffrax solver construct {constructor}."
        )


@compiled_when_eager(static_argnames=("n_steps", "order"))
def split_free_body(
    inertia: Float[ArrayLike, "... 3"],
    L0: Float[ArrayLike, "... 3"],
    q0: Float[ArrayLike, "... 4"],
    dt: Float[ArrayLike, ""],
    n_steps: int,
    order: int = 2,
) -> tuple[Float[Array, "... 3"], Float[Array, "... 4"]]:
    """Integrates a free rigid body for ``n_steps`` steps of ``dt`` with the Lie–Poisson splitting.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)``.
    - `L0`: body-frame angular momentum ``(..., 3)`` (``L = I omega``).
    - `q0`: unit quaternion ``(..., 4)``, scalar first, body to space.
    - `dt`: step (a scalar).
    - `n_steps`: number of steps (a Python int).
    - `order`: 2 (Strang) or 4 (Yoshida triple jump of Strang).

    **Returns:**

    ``(L, q)`` at ``t = n_steps * dt``, batch shape the broadcast of the inputs'. The dtype is
    the inputs' (float32 inputs stay float32).
    """
    _check_order(order)
    n_steps = _checked_n_steps(n_steps, "split_free_body")
    inertia, L0, q0, dt = _checked_state("split_free_body", inertia, L0, q0, dt, names=("L0", "q0", "dt"))

    def body(_, state):
        return _splitting_step(inertia, *state, dt, order)

    return jax.lax.fori_loop(0, n_steps, body, (L0, q0))


class SubStepInterpolation(diffrax.AbstractLocalInterpolation):
    """Dense output of the splittings: at a time ``t`` inside a step, the solver's own map from the
    step's start over ``t - t0``. Its values keep what the map keeps (unit ``q``, ``|L|``, the
    space-frame or vertical ``L``) and the method's order, which a linear interpolation between the
    step's ends would not (``|q| - 1`` of 4e-6 mid-step at dt = 0.01, first order).
    """

    t0: Any
    t1: Any
    y0: Any
    y1: Any
    solver: diffrax.AbstractSolver
    direction: Any

    def evaluate(self, t0, t1=None, left: bool = True):
        del left
        if t1 is not None:
            return jax.tree.map(jnp.subtract, self.evaluate(t1), self.evaluate(t0))
        L0, q0 = self.y0
        return self.solver.map_over(L0, q0, jnp.asarray(self.direction * (t0 - self.t0)).astype(L0.dtype))


def with_model_parameters(solver, *parameters):
    """A splitting for one chunk of :func:`rigidjax.simulate`: the model's parameters (checked
    there; principal moments ``(n, 3)``, which for three bodies have the shape of one tensor) in
    place of the solver's own, without the constructor's checks."""
    names = ("inertia",) if isinstance(solver, LiePoissonSplitting) else ("inertia", "mass", "com", "gravity")
    solver = eqx.tree_at(
        lambda s: [getattr(s, n) for n in names], solver, list(parameters), is_leaf=lambda x: x is None
    )
    return replace_static(solver, _moments_from_model=True)


class _SplittingSolver(diffrax.AbstractSolver):
    """A splitting's map as a fixed-step diffrax solver: ``map_over`` steps ``(L, q)`` by a signed
    time (backward when diffrax integrates from a later to an earlier time) and gives the dense
    output too (:class:`SubStepInterpolation`); ``_check_parameters`` fails a solver without them."""

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., SubStepInterpolation]] = SubStepInterpolation

    @abc.abstractmethod
    def map_over(self, L, q, h): ...

    @abc.abstractmethod
    def _check_parameters(self): ...

    def order(self, terms):
        return self.splitting_order

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        L0, q0 = y0
        self._check_parameters()
        direction = time_direction(terms)
        y1 = self.map_over(L0, q0, jnp.asarray(direction * (t1 - t0)).astype(L0.dtype))
        dense_info = dict(y0=y0, y1=y1, solver=self, direction=direction)
        return y1, None, dense_info, None, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


class LiePoissonSplitting(_SplittingSolver):
    """The Lie–Poisson splitting map as a fixed-step diffrax solver for a free rigid body.

    The state is the pytree ``(L, q)`` (body angular momentum ``(..., 3)``, unit quaternion
    ``(..., 4)``); the moments come from the ``inertia`` field, not from the term. The term is used
    only by ``func`` (e.g. for dense-output derivatives), so any vector field can be passed::

        diffrax.diffeqsolve(diffrax.ODETerm(vf), LiePoissonSplitting(inertia, order=2), t0, t1, dt,
                            (L0, q0), stepsize_controller=diffrax.ConstantStepSize())

    Fixed steps only: there is no error estimate, so an adaptive controller cannot be used.
    With :func:`rigidjax.simulate` the moments come from the model: ``LiePoissonSplitting(order=4)``.
    """

    inertia: Array | None
    splitting_order: int = eqx.field(static=True, default=2)
    _moments_from_model: bool = eqx.field(static=True, default=False, repr=False)

    def __init__(self, inertia=None, order: int = 2):
        order = _check_order(order)
        if inertia is not None:
            inertia = as_float_array(inertia, "inertia")
            if jnp.ndim(inertia) == 0:
                # LiePoissonSplitting(4) would otherwise silently mean inertia=4, order 2.
                raise ValueError(
                    f"LiePoissonSplitting's first argument is the inertia; got the scalar {inertia}. "
                    "For the order write LiePoissonSplitting(order=4)."
                )
            if not is_tensor_shape(inertia.shape):
                check_last_axis(inertia, 3, "inertia")
            inertia = check_inertia(inertia, name="LiePoissonSplitting: inertia")
        self.inertia = inertia
        self.splitting_order = order
        self._moments_from_model = False

    def map_over(self, L, q, h):
        """The splitting map over a time ``h`` from ``(L, q)``."""
        return _splitting_step(self.inertia.astype(L.dtype), L, q, h, self.splitting_order)

    def _check_parameters(self):
        _require_parameters(self, "LiePoissonSplitting", "LiePoissonSplitting(inertia, order)")
        if not self._moments_from_model:
            _check_principal(self.inertia, "LiePoissonSplitting")


def free_body_vector_field(inertia):
    """``(L, q) -> (dL/dt, dq/dt)`` of the free body, for references and for ``ODETerm``.

    ``inertia``: principal moments ``(..., 3)`` (kg m^2), checked here (shape while tracing, a
    physical inertia at run time); ``L`` and ``q`` are the solver's state."""
    return _FreeBodyVectorField(_checked_moments(inertia, "free_body_vector_field"))


class _FreeBodyVectorField(eqx.Module):
    """A module rather than a closure: a term of another inertia has the same structure, so a
    jitted ``diffeqsolve`` compiles once for every inertia (a closure is a new function each time)."""

    inertia: Any

    def __call__(self, t, y, args):
        if is_traced(self.inertia, y):
            return _free_body_derivative(self.inertia, y)
        return compiled_once(_free_body_derivative)(self.inertia, y)  # eager: one program, not ~15


def _free_body_derivative(inertia, y):
    L, q = y
    omega = L / inertia.astype(L.dtype)
    return jnp.cross(L, omega), _quat_kinematics(q, omega)


# ---------------------------------------------------------------------------------------------
# The heavy top: free-body splitting plus the exact gravity kick.


def _gravity_kick(weight_com, L, q, h):
    """Exact flow of ``V(q)`` for a time ``h``: ``L <- L + h m g (R^T Z) x com`` (``q`` fixed).

    ``weight_com`` is ``m g com`` (N m, body frame); the torque matches
    :meth:`rigidjax.HeavyTop.gravity_torque`.
    """
    return L + h * gravity_torque(q, weight_com)


def _heavy_top_strang(inertia, weight_com, L, q, h):
    L = _gravity_kick(weight_com, L, q, 0.5 * h)
    L, q = _strang(inertia, L, q, h)
    return _gravity_kick(weight_com, L, q, 0.5 * h), q


def heavy_top_splitting_step(inertia, weight_com, L, q, h, order: int = 2):
    """One step of length ``h`` of the heavy-top splitting of the given ``order`` (2 or 4).

    ``inertia``: principal moments about the pivot ``(..., 3)``; ``weight_com``: ``m g com``
    ``(..., 3)`` (N m, body frame); ``L`` body angular momentum ``(..., 3)``; ``q`` unit quaternion
    ``(..., 4)`` (body to space); ``h``: the step (s), a scalar. The batch axes broadcast against each
    other. Returns ``(L, q)`` after the step. A non-physical inertia, a zero quaternion or NaN/inf
    raise at run time.
    """
    _check_order(order)
    where = "heavy_top_splitting_step"
    inertia, L, q, h, weight_com = _checked_state(where, inertia, L, q, h, weight_com=(weight_com, 1))
    weight_com = check_finite(weight_com, "weight_com", where)
    return _heavy_top_splitting_step(inertia, weight_com, L, q, h, order)


def _heavy_top_splitting_step(inertia, weight_com, L, q, h, order: int = 2):
    return _composed(functools.partial(_heavy_top_strang, inertia, weight_com), L, q, h, order)


def _checked_top_parameters(mass, com, gravity, where):
    mass, com, gravity = (
        as_float_array(x, n) for x, n in ((mass, "mass"), (com, "com"), (gravity, "gravity"))
    )
    mass = check_finite(mass, "mass", where)
    mass = error_if(mass, jnp.any(mass <= 0), f"{where}: mass {POSITIVE_MASS}.")
    gravity = check_finite(gravity, "gravity", where)
    gravity = error_if(gravity, jnp.any(gravity <= 0), f"{where}: gravity {POSITIVE_GRAVITY}.")
    return mass, check_finite(com, "com", where), gravity


def heavy_top_weight_com(mass, com, gravity, dtype=None):
    """``m g com`` (N m, body frame), the one combination of the heavy top's parameters the
    splitting needs; ``mass``, ``gravity`` ``(...)``, ``com`` ``(..., 3)``."""
    mass, com, gravity = (
        as_float_array(x, n) for x, n in ((mass, "mass"), (com, "com"), (gravity, "gravity"))
    )
    check_last_axis(com, 3, "com")
    dtype = dtype or jnp.result_type(mass.dtype, com.dtype, gravity.dtype)
    return (mass.astype(dtype) * gravity.astype(dtype))[..., None] * com.astype(dtype)


@compiled_when_eager(static_argnames=("n_steps", "order"))
def split_heavy_top(
    inertia: Float[ArrayLike, "... 3"],
    mass: Float[ArrayLike, "..."],
    com: Float[ArrayLike, "... 3"],
    gravity: Float[ArrayLike, "..."],
    L0: Float[ArrayLike, "... 3"],
    q0: Float[ArrayLike, "... 4"],
    dt: Float[ArrayLike, ""],
    n_steps: int,
    order: int = 2,
) -> tuple[Float[Array, "... 3"], Float[Array, "... 4"]]:
    """Integrates a heavy top for ``n_steps`` steps of ``dt`` with the Lie–Poisson splitting.

    **Arguments:**

    - `inertia`: principal moments about the pivot ``(..., 3)`` (kg m^2); body axes are principal.
    - `mass`: mass (kg), ``(...)``.
    - `com`: body-frame centre of mass relative to the pivot ``(..., 3)`` (m).
    - `gravity`: gravitational acceleration (m/s^2) along space -Z, ``(...)``.
    - `L0`: body-frame angular momentum about the pivot ``(..., 3)`` (``L = I omega``).
    - `q0`: unit quaternion ``(..., 4)``, scalar first, body to space.
    - `dt`: step (s, a scalar).
    - `n_steps`: number of steps (a Python int).
    - `order`: 2 (Strang) or 4 (Yoshida triple jump of Strang).

    **Returns:**

    ``(L, q)`` at ``t = n_steps * dt``, batch shape the broadcast of the inputs'. Energy error
    bounded, ``L_Z = (R L) . Z`` and ``|q|`` conserved to roundoff.
    """
    _check_order(order)
    where = "split_heavy_top"
    n_steps = _checked_n_steps(n_steps, where)
    inertia, L0, q0, dt, mass, com, gravity = _checked_state(
        where, inertia, L0, q0, dt, ("L0", "q0", "dt"), mass=(mass, 0), com=(com, 1), gravity=(gravity, 0)
    )
    mass, com, gravity = _checked_top_parameters(mass, com, gravity, where)
    weight_com = heavy_top_weight_com(mass, com, gravity, L0.dtype)
    batch = jnp.broadcast_shapes(L0.shape[:-1], weight_com.shape[:-1])
    L0 = jnp.broadcast_to(L0, batch + (3,))
    q0 = jnp.broadcast_to(q0, batch + (4,))

    def body(_, state):
        return _heavy_top_splitting_step(inertia, weight_com, *state, dt, order)

    return jax.lax.fori_loop(0, n_steps, body, (L0, q0))


class HeavyTopSplitting(_SplittingSolver):
    """The heavy-top Lie–Poisson splitting as a fixed-step diffrax solver.

    The state is the pytree ``(L, q)`` (body angular momentum about the pivot ``(..., 3)``, unit
    quaternion ``(..., 4)``); the parameters come from the fields (principal moments ``inertia``,
    ``mass``, ``com``, ``gravity`` as in :class:`rigidjax.HeavyTop`), not from the term, which is only
    used by ``func``. In diffrax the inertia must be principal moments ``(..., 3)``; with
    ``rigidjax.simulate`` (which takes the parameters from the model) a tensor works too.
    :func:`heavy_top_vector_field` gives a matching term::

        diffrax.diffeqsolve(diffrax.ODETerm(heavy_top_vector_field(I, m, com, g)),
                            HeavyTopSplitting(I, m, com, g, order=4), t0, t1, dt, (L0, q0),
                            stepsize_controller=diffrax.ConstantStepSize())

    Fixed steps only (no error estimate). With :func:`rigidjax.simulate` the parameters come from
    the model: ``HeavyTopSplitting(order=4)``.
    """

    inertia: Array | None
    mass: Array | None
    com: Array | None
    gravity: Array | None
    splitting_order: int = eqx.field(static=True, default=2)
    _moments_from_model: bool = eqx.field(static=True, default=False, repr=False)

    def __init__(self, inertia=None, mass=None, com=None, gravity=9.81, order: int = 2):
        order = _check_order(order)
        if inertia is None and mass is None and com is None:
            # The scene's parameters come from the model (rigidjax.simulate).
            self.inertia = self.mass = self.com = self.gravity = None
            self.splitting_order = order
            self._moments_from_model = False
            return
        if inertia is None or mass is None or com is None:
            raise ValueError(
                "HeavyTopSplitting needs all of inertia, mass and com, or none of them (simulate)."
            )
        inertia = as_float_array(inertia, "inertia")
        if not is_tensor_shape(inertia.shape):
            check_last_axis(inertia, 3, "inertia")
        self.inertia = check_inertia(inertia, name="HeavyTopSplitting: inertia")
        mass, com, gravity = _checked_top_parameters(mass, com, gravity, "HeavyTopSplitting")
        self.mass = mass
        self.com = com
        check_last_axis(self.com, 3, "com")
        self.gravity = gravity
        self.splitting_order = order
        self._moments_from_model = False

    @classmethod
    def from_model(cls, model, order: int = 2) -> "HeavyTopSplitting":
        """The splitting for a :class:`rigidjax.HeavyTop` without extra torques."""
        if not all(hasattr(model, field) for field in ("inertia", "mass", "com", "gravity")):
            raise ValueError(
                f"HeavyTopSplitting.from_model needs a HeavyTop, got a {type(model).__name__}; for a "
                "torque-free body use LiePoissonSplitting(model.inertia)."
            )
        if getattr(model, "torques", ()):
            raise ValueError(
                "HeavyTopSplitting integrates gravity only; the model has extra torques. Use "
                "rigidjax's RKMK solver for arbitrary torques."
            )
        return cls(model.inertia, model.mass, model.com, model.gravity, order)

    def map_over(self, L, q, h):
        """The splitting map over a time ``h`` from ``(L, q)``."""
        weight_com = heavy_top_weight_com(self.mass, self.com, self.gravity, L.dtype)
        return _heavy_top_splitting_step(
            self.inertia.astype(L.dtype), weight_com, L, q, h, self.splitting_order
        )

    def _check_parameters(self):
        _require_parameters(
            self, "HeavyTopSplitting", "HeavyTopSplitting(inertia, mass, com, gravity, order)"
        )
        if not self._moments_from_model:
            _check_principal(self.inertia, "HeavyTopSplitting as a diffrax solver")


def heavy_top_vector_field(inertia, mass, com, gravity=9.81):
    """``(L, q) -> (dL/dt, dq/dt)`` of the heavy top (principal ``inertia`` about the pivot), for
    references and for ``ODETerm``: ``dL/dt = L x omega + m g (R^T Z) x com``. The parameters are
    checked here, as :func:`split_heavy_top`'s."""
    where = "heavy_top_vector_field"
    inertia = _checked_moments(inertia, where)
    check_last_axis(as_float_array(com, "com"), 3, "com")
    mass, com, gravity = _checked_top_parameters(mass, com, gravity, where)
    check_batch_shapes(
        where, ("inertia", inertia, 1), ("mass", mass, 0), ("com", com, 1), ("gravity", gravity, 0)
    )
    return _HeavyTopVectorField(inertia, mass, com, gravity)


class _HeavyTopVectorField(eqx.Module):
    """A module, as :class:`_FreeBodyVectorField`: one compile for every top of one shape."""

    inertia: Any
    mass: Any
    com: Any
    gravity: Any

    def __call__(self, t, y, args):
        parameters = (self.inertia, self.mass, self.com, self.gravity)
        if is_traced(parameters, y):
            return _heavy_top_derivative(parameters, y)
        return compiled_once(_heavy_top_derivative)(parameters, y)  # eager: one program, not ~16


def _heavy_top_derivative(parameters, y):
    inertia, mass, com, gravity = parameters
    dL, dq = _free_body_derivative(jnp.asarray(inertia), y)
    weight_com = heavy_top_weight_com(mass, com, gravity, y[0].dtype)
    return dL + gravity_torque(y[1], weight_com), dq
