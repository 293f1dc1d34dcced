"""Scenes: the state of a body, the models that move it, and the torques a user can add.

Models are ``eqx.Module`` pytrees: their numbers (inertia, mass, centre of mass, torque values) are
leaves, so ``jax.grad`` with respect to them works through :func:`rigidjax.simulate`. A batch is a
leading axis on the model's array fields and on the state's fields.

Every model answers three questions the integrator asks: does it need the orientation (if not, only
Euler's three equations are integrated), what is the body-frame angular acceleration, and what is
the potential energy. Torques are body-frame, in N m.
"""

import abc
import inspect
import operator
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import as_float_array, check_last_axis
from .._kinematics.quaternion import _quat_conjugate, _quat_rotate
from .._repr import dataclass_fields, fields_repr, module_repr, summarizing
from .equations import _components, _cross_components, _euler_equations, _inertia_times, is_full_tensor

_Z = (0.0, 0.0, 1.0)


def gravity_torque(orientation, weight_com):
    """Body-frame torque (N m) of uniform gravity along space -Z on a body held at a fixed point:
    ``(R^T Z) x (m g com)``, with ``weight_com = m g com`` the weight times the body-frame position of
    the centre of mass relative to the fixed point. The one formula behind :class:`HeavyTop`,
    :class:`GravityTorque` and the heavy-top splitting's gravity kick.

    ``R^T Z = (2 (x z - w y), 2 (y z + w x), 1 - 2 (x^2 + y^2))``, ``q* (0, Z) q`` expanded, written
    component by component: inside an integrator's step XLA fuses it into plain elementwise code,
    which it did not for the slices and concatenations of ``jnp.cross`` (10^4 heavy tops,
    ``"balanced"``, 5 s, 11 samples: 0.34 -> 0.26 s, medians of four alternated runs)."""
    w, x, y, z = (orientation[..., i] for i in range(4))
    up = (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
    return jnp.stack(_cross_components(up, _components(weight_com)), axis=-1)


class State(eqx.Module):
    """The state of one body or a batch: angular velocity and, optionally, orientation.

    **Arguments:**

    - `omega`: body-frame angular velocity ``(..., 3)`` (rad/s).
    - `orientation`: a unit quaternion ``(..., 4)`` (scalar first, body -> space), or None. With
      None a scene that does not need the orientation integrates only Euler's equations.

    Both are converted to one floating dtype (the wider of the two).
    """

    omega: Float[Array, "*batch 3"]
    orientation: Float[Array, "*batch 4"] | None = None

    def __init__(self, omega, orientation=None):
        omega = as_float_array(omega, "omega")
        check_last_axis(omega, 3, "State.omega")
        self.omega = omega
        if orientation is not None:
            orientation = as_float_array(orientation, "orientation")
            check_last_axis(orientation, 4, "State.orientation")
            if omega.dtype != orientation.dtype:
                dtype = jnp.result_type(omega.dtype, orientation.dtype)
                self.omega = omega.astype(dtype)
                orientation = orientation.astype(dtype)
        self.orientation = orientation


# ---------------------------------------------------------------------------------------------
# Torques


class AbstractTorque(eqx.Module):
    """A body-frame torque ``tau(t, state, args)`` (N m) acting on one body.

    A torque of your own is a subclass: array fields, ``needs_orientation`` (a class attribute or
    property: whether ``__call__`` reads ``state.orientation``), ``__call__`` for one body, and
    :meth:`per_body_ndims` for the fields that hold one value per body:

    ```python
    class Magnetorquer(rj.AbstractTorque):
        dipole: jax.Array                      # (..., 3) body-frame dipole (A m^2), one per body
        needs_orientation = True

        def per_body_ndims(self):
            return {"dipole": 1}

        def __call__(self, t, state, args):
            b_body = rj.quat_rotate(rj.quat_conjugate(state.orientation), jnp.array([0.0, 0.0, 3e-5]))
            return jnp.cross(self.dipole, b_body)
    ```

    ``RigidBody(inertia, torque=Magnetorquer(dipoles))`` with ``dipoles`` of shape ``(N, 3)`` is
    then a batch of ``N`` bodies, each ``__call__`` seeing its own ``(3,)`` dipole.
    """

    needs_orientation: eqx.AbstractClassVar[bool]
    conservative: ClassVar[bool] = False

    def per_body_ndims(self) -> dict[str, int]:
        """The array fields that hold one value per body, each with the number of trailing axes one
        body's value has (``{"dipole": 1}`` for a ``(..., 3)`` field, 0 for a scalar per body):
        leading axes beyond those are batch axes, broadcast against the scene's. Fields not listed
        are shared by every body of the batch. None by default."""
        return {}

    def _leaf_rules(self) -> dict[str, tuple[Callable, str]]:
        """Value rules of per-body fields beyond finiteness, checked by ``simulate`` at run time
        (also under ``jit``): field name to ``(bad(value) -> bool array, what it must be)``."""
        return {}

    @abc.abstractmethod
    def __call__(self, t, state: State, args: Any) -> Float[Array, "3"]: ...

    __repr__ = module_repr


class ConstantTorque(AbstractTorque):
    """A constant torque, given in body-frame or space-frame components.

    **Arguments:**

    - `torque`: the torque ``(..., 3)`` (N m); leading axes are per-body batch axes.
    - `frame`: ``"body"`` (default) or ``"space"``. A space-frame torque is fixed in space and is
      rotated into the body frame with the orientation (so the scene needs one).
    """

    torque: Float[ArrayLike, "*batch 3"] = eqx.field(converter=lambda x: as_float_array(x, "torque"))
    frame: str = eqx.field(static=True, default="body")

    def __check_init__(self):
        if self.frame not in ("body", "space"):
            raise ValueError(f"ConstantTorque frame must be 'body' or 'space', got {self.frame!r}.")
        check_last_axis(jnp.asarray(self.torque), 3, "ConstantTorque.torque")

    @property
    def needs_orientation(self) -> bool:  # type: ignore[override]
        return self.frame == "space"

    def per_body_ndims(self):
        return {"torque": 1}

    def __call__(self, t, state, args):
        tau = jnp.asarray(self.torque, state.omega.dtype)
        if self.frame == "space":
            return _quat_rotate(_quat_conjugate(state.orientation), tau)
        return tau


_NON_NEGATIVE_DAMPING = (
    "must be non-negative (N m s): a negative damping coefficient feeds energy in (write such a "
    "torque as Torque(fn))"
)


class ViscousDamping(AbstractTorque):
    """Linear viscous damping ``tau = -coefficient * omega``.

    **Arguments:**

    - `coefficient`: N m s, non-negative; a scalar, or ``(..., 3)`` per body axis. For a batch of
      per-body scalars use shape ``(N, 1)`` (other trailing lengths are an error).
    """

    coefficient: Float[ArrayLike, "*batch"] | Float[ArrayLike, "*batch 3"] = eqx.field(
        converter=lambda x: as_float_array(x, "coefficient")
    )
    needs_orientation: ClassVar[bool] = False

    def __check_init__(self):
        # A trailing axis of other lengths was read as a batch of per-body scalars, except 3 (per
        # body axis): N bodies' coefficients meant the one or the other depending on N.
        shape = jnp.shape(self.coefficient)
        if shape and shape[-1] not in (1, 3):
            raise ValueError(
                "ViscousDamping.coefficient must be a scalar, (..., 3) per body axis or (..., 1) per "
                f"body, got shape {shape}; for N bodies' scalar coefficients use shape (N, 1)."
            )

    def _leaf_rules(self):
        return {"coefficient": (lambda c: c < 0, _NON_NEGATIVE_DAMPING)}

    def per_body_ndims(self):
        # A trailing axis of 3 (or 1) is per body axis; so a batch of per-body scalars is (N, 1).
        shape = jnp.shape(self.coefficient)
        return {"coefficient": 1 if shape and shape[-1] in (1, 3) else 0}

    def __call__(self, t, state, args):
        return -jnp.asarray(self.coefficient, state.omega.dtype) * state.omega


class Torque(AbstractTorque):
    """A user torque: any callable returning a body-frame torque (N m).

    **Arguments:**

    - `fn`: ``fn(t, state, args) -> (3,)``. It sees one body (``state.omega`` of shape ``(3,)``);
      batching is done for you. ``fn`` is compiled once per function object: numbers it reads
      from globals, closures or an object's attributes are constants of that program, and a later
      change to them is not seen (a sweep that sets a global between runs gets the first value
      every time). Pass numbers that change through `params` or ``simulate``'s ``args``.
    - `params`: numbers you want gradients for; ``fn`` then receives them as its third argument,
      ``fn(t, state, params)``, instead of ``simulate``'s ``args``.
    - `needs_orientation`: set False when ``fn`` ignores ``state.orientation``, so that scenes
      without an orientation can integrate only Euler's equations.
    """

    fn: Callable = eqx.field(static=True)
    params: Any = None
    needs_orientation: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        if not callable(self.fn):
            kind = type(self.fn).__name__
            raise TypeError(f"Torque: fn must be a function fn(t, state, args), got {kind}.")
        try:
            signature = inspect.signature(self.fn)
        except (TypeError, ValueError):  # builtins and some C callables have none to read
            return
        try:
            signature.bind(None, None, None)
        except TypeError:
            name = getattr(self.fn, "__qualname__", type(self.fn).__name__)
            raise TypeError(
                f"Torque: fn must take three arguments fn(t, state, args) (args: simulate's args, or "
                f"the torque's params), got {name}{signature}."
            ) from None

    def __call__(self, t, state, args):
        name = getattr(self.fn, "__qualname__", type(self.fn).__name__)
        try:
            out = self.fn(t, state, self.params if self.params is not None else args)
        except (TypeError, AttributeError) as error:
            if state.orientation is None:
                raise TypeError(
                    f"Torque({name}) failed on a state without an orientation ({error}). A torque "
                    "that reads state.orientation needs needs_orientation=True (the default) and an "
                    "orientation in the initial state."
                ) from error
            raise
        try:
            kind = None if out is None else jnp.result_type(out)
        except (TypeError, ValueError):
            kind = None
        if kind is None or not (jnp.issubdtype(kind, jnp.floating) or jnp.issubdtype(kind, jnp.integer)):
            got = type(out).__name__ if kind is None else f"dtype {kind}"
            raise TypeError(
                f"Torque({name}) returned {got}; a torque function returns the body-frame torque "
                "(N m) as real numbers, shape (3,)."
            )
        return jnp.asarray(out, state.omega.dtype)


class GravityTorque(AbstractTorque):
    """Uniform gravity on a body held at a fixed point (a pivot, a gimbal, a bearing).

    The torque is ``com x (m g R^T (-Z))`` in body axes (N m), gravity along space -Z.
    ``RigidBody(I, torque=GravityTorque(m, com))`` moves as ``HeavyTop(I, m, com)`` (without its
    potential energy in the trajectory's energies and invariants); as a known torque it
    gives :func:`rigidjax.fit_inertia_to_orientation` the scale (a heavy top's m g l).

    **Arguments:**

    - `mass`: kg, ``(...)``, positive (a body without mass feels no gravity: use a torque-free scene).
    - `com`: body-frame position (m) of the centre of mass relative to the fixed point, ``(..., 3)``.
    - `gravity`: gravitational acceleration (m/s^2), default 9.81.
    """

    mass: Float[ArrayLike, "*batch"] = eqx.field(converter=lambda x: as_float_array(x, "mass"))
    com: Float[ArrayLike, "*batch 3"] = eqx.field(converter=lambda x: as_float_array(x, "com"))
    gravity: Float[ArrayLike, "*batch"] = eqx.field(
        converter=lambda x: as_float_array(x, "gravity"), default=9.81
    )
    needs_orientation: ClassVar[bool] = True
    # Not flagged conservative: RigidBody's energy has no potential term (HeavyTop's has).

    def __check_init__(self):
        check_last_axis(jnp.asarray(self.com), 3, "GravityTorque.com")

    def per_body_ndims(self):
        return {"mass": 0, "com": 1, "gravity": 0}

    def __call__(self, t, state, args):
        dtype = state.omega.dtype
        weight = jnp.asarray(self.mass, dtype) * jnp.asarray(self.gravity, dtype)
        return gravity_torque(state.orientation, weight[..., None] * jnp.asarray(self.com, dtype))


def _torque_name(i: int, torque) -> str:
    if isinstance(torque, Torque):
        fn = getattr(torque.fn, "__qualname__", None) or type(torque.fn).__name__
        return f"torque {i} (Torque({fn}))"
    return f"torque {i} ({type(torque).__name__})"


def _total_torque(torques, t, state, args):
    """The sum of the torques on ``state``; each must return a body-frame vector of the state's
    shape (or one that broadcasts to it without changing it): a ``ValueError`` naming the torque and
    the shapes otherwise, while tracing (a scalar, or a batch returned for one body, would otherwise
    be broadcast silently into a wrong torque)."""
    total = jnp.zeros_like(state.omega)
    for i, torque in enumerate(torques):
        tau = torque(t, state, args)
        shape, expected = jnp.shape(tau), jnp.shape(state.omega)
        try:
            fits = len(shape) >= 1 and shape[-1] == 3 and jnp.broadcast_shapes(shape, expected) == expected
        except ValueError:
            fits = False
        if not fits:
            raise ValueError(
                f"{_torque_name(i, torque)} returned shape {tuple(shape)}; a torque returns the "
                f"body-frame torque (N m) on the body it is given, shape {tuple(expected)} (state.omega's "
                "shape: a torque function sees one body, batching is done for it; an AbstractTorque "
                "whose fields hold one value per body lists them in per_body_ndims)."
            )
        total = total + tau
    return total


def _as_torque_tuple(torque) -> tuple:
    if torque is None:
        return ()
    if isinstance(torque, AbstractTorque):
        return (torque,)
    if callable(torque):
        return (Torque(torque),)
    if isinstance(torque, list | tuple):
        bad = [type(x).__name__ for x in torque if not (isinstance(x, AbstractTorque) or callable(x))]
        if not bad:
            return tuple(x if isinstance(x, AbstractTorque) else Torque(x) for x in torque)
        got = f"a {type(torque).__name__} holding {', '.join(bad)}"
    else:
        got = type(torque).__name__
    raise TypeError(
        "torque must be an AbstractTorque (ConstantTorque, ViscousDamping, Torque(fn)), a callable "
        f"fn(t, state, args), or a tuple of them; got {got}."
    )


# ---------------------------------------------------------------------------------------------
# Models


class BodyLeaf(NamedTuple):
    """A per-body array of a scene: a label for messages, how to reach it, its per-body ndim."""

    label: str
    get: Callable
    core: int


def _torque_field_getter(index: int, name: str):
    return lambda model: getattr(model.torques[index], name)


class AbstractModel(eqx.Module):
    """A scene: how one rigid body's angular velocity changes.

    A scene of your own is a subclass with array fields (``inertia`` among them: the momentum and
    energy of the trajectory read it), ``needs_orientation``, ``angular_acceleration`` for one body
    and :meth:`per_body_ndims`; ``simulate`` batches, checks and integrates it with every
    integrating preset and solver:

    ```python
    class TorsionSpring(rj.AbstractModel):             # held toward the identity orientation
        inertia: jax.Array                             # (..., 3) principal moments, kg m^2
        stiffness: jax.Array                           # (...) N m
        needs_orientation = True

        def per_body_ndims(self):
            return {"inertia": 1, "stiffness": 0}

        def angular_acceleration(self, t, state, args):
            return rj.euler_equations(self.inertia, state.omega, -self.stiffness * state.orientation[1:])
    ```
    """

    @property
    @abc.abstractmethod
    def needs_orientation(self) -> bool: ...

    @abc.abstractmethod
    def angular_acceleration(self, t, state: State, args: Any) -> Float[Array, "3"]:
        """Body-frame ``d(omega)/dt`` for one body."""

    def potential_energy(self, orientation) -> Float[Array, "..."]:
        """Potential energy (J) of one body at ``orientation``; 0 unless the scene has a field."""
        return jnp.zeros(jnp.shape(orientation)[:-1], jnp.result_type(orientation))

    @property
    def torque_free(self) -> bool:
        return False

    @property
    def conserves_energy(self) -> bool:
        return False

    @summarizing
    def __repr__(self) -> str:
        """The scene, its arrays as dtype, shape and (when few) values, its torques and its batch
        shape: one short line however many bodies, also for traced values inside ``jax.jit``."""
        fields = []
        for name, value in dataclass_fields(self):
            if name == "torques":
                if value:
                    fields.append(("torque", value[0] if len(value) == 1 else tuple(value)))
            else:
                fields.append((name, value))
        try:
            batch = self.batch_shape()
        except (ValueError, TypeError, AttributeError):  # fields that do not broadcast
            batch = ()
        if batch:
            fields.append(("batch_shape", batch))
        return fields_repr(type(self).__name__, fields)

    @property
    def conserves_angular_momentum(self) -> bool:
        """True for scenes on which no external torque acts: ``|L|`` and the space-frame ``L`` (of
        :meth:`angular_momentum`) are conserved."""
        return self.torque_free

    def angular_momentum(self, omega) -> Float[Array, "... 3"]:
        """Body-frame angular momentum (kg m^2/s) at the body-frame ``omega`` (rad/s, ``(..., 3)``,
        broadcast against the scene's batch axes): ``I omega``. A scene whose body carries momentum
        of its own (a :class:`rigidjax.Gyrostat`'s rotors) adds it."""
        return _inertia_times(self.inertia, omega)

    @property
    def conserves_vertical_angular_momentum(self) -> bool:
        """True for scenes in a vertical field whose space-frame L_z is conserved (the heavy top);
        torque-free scenes report the whole space-frame L instead."""
        return False

    def omega_scale(self, state: State, duration, args: Any) -> Float[Array, "3"]:
        """Per-component angular-velocity scale (rad/s) for one body, used to make tolerances
        dimensionless: |omega0|, or, for a body starting at rest, |d(omega)/dt| times the duration."""
        speed = jnp.linalg.norm(state.omega)
        accel = jnp.linalg.norm(self.angular_acceleration(0.0, state, args))
        scale = jnp.where(speed > 0, speed, accel * duration)
        return jnp.broadcast_to(scale, (3,))

    @abc.abstractmethod
    def per_body_ndims(self) -> dict[str, int]:
        """The array fields that hold one value per body, each with the number of trailing axes one
        body's value has (``inertia``: 1 for principal moments ``(..., 3)``, 2 for a tensor ``(..., 3,
        3)``; 0 for a scalar per body): leading axes beyond those are batch axes, broadcast together.
        Fields not listed are shared by every body."""

    def body_leaves(self) -> list[BodyLeaf]:
        """Every per-body array of the scene, its own fields and then each torque's, with its number
        of trailing per-body axes; leading axes beyond those are batch axes."""
        # Methods called by the class: bound to a Module instance, each call would build a Module.
        own = type(self).per_body_ndims(self)
        leaves = [BodyLeaf(n, operator.attrgetter(n), c) for n, c in own.items()]
        for i, torque in enumerate(getattr(self, "torques", ())):
            for n, c in type(torque).per_body_ndims(torque).items():
                leaves.append(BodyLeaf(f"torques[{i}].{n}", _torque_field_getter(i, n), c))
        return leaves

    def leaf_rules(self) -> dict[str, tuple[Callable, str]]:
        """The torques' value rules (:meth:`AbstractTorque._leaf_rules`) by the labels of
        :meth:`body_leaves`."""
        return {
            f"torques[{i}].{name}": rule
            for i, torque in enumerate(getattr(self, "torques", ()))
            for name, rule in torque._leaf_rules().items()
        }

    def replace_body_leaves(self, leaves: list[BodyLeaf], values: list) -> "AbstractModel":
        """A copy with the arrays of ``leaves`` (from :meth:`body_leaves`) replaced by ``values``."""
        return eqx.tree_at(
            lambda m: [leaf.get(m) for leaf in leaves], self, list(values), is_leaf=lambda x: x is None
        )

    def batch_shape(self) -> tuple[int, ...]:
        shapes = []
        for leaf in self.body_leaves():
            shape = jnp.shape(leaf.get(self))
            shapes.append(shape[: len(shape) - leaf.core])
        return jnp.broadcast_shapes(*shapes) if shapes else ()

    @property
    def inertia_core_ndim(self) -> int:
        return 2 if is_full_tensor(self.inertia) else 1


def _inertia_field(inertia):
    inertia = as_float_array(inertia, "inertia")
    is_full_tensor(inertia)  # validates the shape
    return inertia


class FreeBody(AbstractModel):
    """A torque-free rigid body. Energy, ``|L|`` and space-frame ``L`` are conserved.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` or a tensor ``(..., 3, 3)`` in body axes (kg m^2);
      leading axes are batch axes.
    """

    inertia: Float[ArrayLike, "*batch 3"] | Float[ArrayLike, "*batch 3 3"] = eqx.field(
        converter=_inertia_field
    )

    @property
    def needs_orientation(self) -> bool:
        return False

    @property
    def torque_free(self) -> bool:
        return True

    @property
    def conserves_energy(self) -> bool:
        return True

    def angular_acceleration(self, t, state, args):
        return _euler_equations(self.inertia, state.omega)

    def omega_scale(self, state, duration, args):
        if is_full_tensor(self.inertia):
            return jnp.broadcast_to(jnp.linalg.norm(state.omega), (3,))
        return _polhode_scale(self.inertia, state.omega)

    def per_body_ndims(self):
        return {"inertia": self.inertia_core_ndim}


class RigidBody(AbstractModel):
    """A rigid body under user torques.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` or a tensor ``(..., 3, 3)`` in body axes (kg m^2).
    - `torque`: an :class:`AbstractTorque` (body frame, N m), a callable ``fn(t, state, args)``, or
      a tuple of them (summed); None for a torque-free body.
    """

    inertia: Float[ArrayLike, "*batch 3"] | Float[ArrayLike, "*batch 3 3"] = eqx.field(
        converter=_inertia_field
    )
    torques: tuple = eqx.field(converter=_as_torque_tuple, default=())

    def __init__(self, inertia, torque=None):
        self.inertia = inertia
        self.torques = torque

    @property
    def needs_orientation(self) -> bool:
        return any(t.needs_orientation for t in self.torques)

    @property
    def torque_free(self) -> bool:
        return not self.torques

    @property
    def conserves_energy(self) -> bool:
        return all(t.conservative for t in self.torques)

    def angular_acceleration(self, t, state, args):
        return _euler_equations(self.inertia, state.omega, _total_torque(self.torques, t, state, args))

    def omega_scale(self, state, duration, args):
        if not self.torques and not is_full_tensor(self.inertia):
            return _polhode_scale(self.inertia, state.omega)
        return super().omega_scale(state, duration, args)

    def per_body_ndims(self):
        return {"inertia": self.inertia_core_ndim}


class HeavyTop(AbstractModel):
    """A rigid body on a fixed pivot in uniform gravity (the heavy top, the gyroscope).

    Total energy and the vertical component of the space-frame angular momentum are conserved
    without extra torques.

    **Arguments:**

    - `inertia`: about the PIVOT, in body axes (kg m^2): moments ``(..., 3)`` or a tensor
      ``(..., 3, 3)``.
    - `mass`: kg, ``(...)``, positive (a body without mass feels no gravity: use a torque-free scene).
    - `com`: body-frame position of the centre of mass relative to the pivot (m), ``(..., 3)``.
    - `gravity`: m/s^2 along space -Z, default 9.81.
    - `torque`: extra torques (e.g. friction), as for :class:`RigidBody`.
    """

    inertia: Float[ArrayLike, "*batch 3"] | Float[ArrayLike, "*batch 3 3"] = eqx.field(
        converter=_inertia_field
    )
    mass: Float[Array, "*batch"] = eqx.field(converter=lambda x: as_float_array(x, "mass"))
    com: Float[Array, "*batch 3"] = eqx.field(converter=lambda x: as_float_array(x, "com"))
    gravity: Float[Array, "*batch"] = eqx.field(converter=lambda x: as_float_array(x, "gravity"))
    torques: tuple = eqx.field(converter=_as_torque_tuple)

    def __init__(self, inertia, mass, com, gravity=9.81, torque=None):
        self.inertia = inertia
        self.mass = mass
        self.com = com
        self.gravity = gravity
        self.torques = torque

    def __check_init__(self):
        check_last_axis(self.com, 3, "HeavyTop.com")

    @property
    def needs_orientation(self) -> bool:
        return True

    @property
    def conserves_energy(self) -> bool:
        return all(t.conservative for t in self.torques)

    @property
    def conserves_vertical_angular_momentum(self) -> bool:
        # Gravity along -Z exerts no torque about the vertical through the pivot.
        return self.conserves_energy

    def gravity_torque(self, orientation):
        """Body-frame gravity torque ``com x (m g R^T (-Z))`` (N m)."""
        dtype = orientation.dtype
        weight = (self.mass * self.gravity).astype(dtype)
        return gravity_torque(orientation, weight[..., None] * self.com.astype(dtype))

    def angular_acceleration(self, t, state, args):
        tau = self.gravity_torque(state.orientation) + _total_torque(self.torques, t, state, args)
        return _euler_equations(self.inertia, state.omega, tau)

    def omega_scale(self, state, duration, args):
        """Bound on |omega| from energy: the top can at most turn all of ``V0 - V_min`` into
        kinetic energy, and ``KE >= I_min |omega|^2 / 2``."""
        inertia = self.inertia
        moments = jnp.linalg.eigvalsh(inertia) if is_full_tensor(inertia) else inertia
        kinetic = 0.5 * jnp.sum(state.omega * _inertia_times(inertia, state.omega))
        drop = self.potential_energy(state.orientation) + self.mass * self.gravity * jnp.linalg.norm(self.com)
        bound = jnp.sqrt(2.0 * (kinetic + jnp.maximum(drop, 0.0)) / jnp.min(moments))
        return jnp.broadcast_to(jnp.maximum(bound, jnp.linalg.norm(state.omega)), (3,))

    def potential_energy(self, orientation):
        """``m g Z_com``: the height of the centre of mass above the pivot times the weight (J)."""
        com_space = _quat_rotate(orientation, self.com.astype(orientation.dtype))
        return (self.mass * self.gravity).astype(orientation.dtype) * com_space[..., 2]

    def per_body_ndims(self):
        return {"inertia": self.inertia_core_ndim, "mass": 0, "com": 1, "gravity": 0}


# ---------------------------------------------------------------------------------------------
# Angular-velocity scales: what "relative error" is measured against, per body and component.


def _polhode_scale(inertia, omega):
    """Largest value each |omega_i| reaches on a torque-free principal-axis body (rad/s).

    From energy and |L|^2 conservation: for components i, k and a third axis j with
    sign(I_j - I_i) = sign(I_j - I_k), ``omega_i^2 + r omega_k^2`` is conserved-bounded with
    ``r = I_k (I_j - I_k) / (I_i (I_j - I_i)) >= 0``. Written in these terms there is no
    cancellation, so the Earth's 1e-11 rad/s wobble on a 7e-5 rad/s spin gets its own scale.
    """
    # Only ratios of moments enter: normalise first, so that SI-scale moments (the Earth, 8e37 kg m^2)
    # do not overflow float32 in the products below.
    inertia = inertia / jnp.max(inertia)
    x = omega * omega
    # Energy bound, always valid: omega_i^2 <= 2E / I_i.
    bounds = [x[i] + (sum(inertia[k] * x[k] for k in range(3) if k != i)) / inertia[i] for i in range(3)]
    for i in range(3):
        best = bounds[i]
        for j in range(3):
            if j == i:
                continue
            k = 3 - i - j
            di, dk = inertia[j] - inertia[i], inertia[j] - inertia[k]
            usable = (di * dk >= 0) & (di != 0)
            r = inertia[k] * dk / (inertia[i] * jnp.where(usable, di, 1.0))
            best = jnp.where(usable, jnp.minimum(best, x[i] + r * x[k]), best)
        bounds[i] = best
    return jnp.sqrt(jnp.stack(bounds))
