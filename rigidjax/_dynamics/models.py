"""Scenes: the models that move a body (the state is in ``state.py``, the torques in ``torques.py``).

Models are ``eqx.Module`` pytrees: their numbers (inertia, mass, centre of mass, torque values) are
leaves, so ``jax.grad`` with respect to them works through :func:`rigidjax.simulate`. A batch is a
leading axis on the model's array fields and on the state's fields.

Every model answers three questions the integrator asks: does it need the orientation (if not, only
Euler's three equations are integrated), what is the body-frame angular acceleration, and what is
the potential energy. Torques are body-frame, in N m.
"""

import abc
import operator
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import as_float_array, check_last_axis, is_tensor_shape
from .._kinematics.quaternion import _quat_rotate
from .._repr import dataclass_fields, fields_repr, summarizing
from .equations import _euler_equations, _inertia_times, is_full_tensor
from .state import State
from .torques import GRAVITY_RULES, _as_torque_tuple, _total_torque, gravity_torque

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

    def _leaf_rules(self) -> dict[str, tuple[Callable, str]]:
        """Value rules of the scene's own per-body fields beyond finiteness (and a physical
        inertia), checked by ``simulate`` at run time (also under ``jit``): field name to
        ``(bad(value) -> bool array, what it must be)``. None by default."""
        return {}

    def leaf_rules(self) -> dict[str, tuple[Callable, str]]:
        """The value rules of the scene's own fields (:meth:`_leaf_rules`) and of its torques'
        (:meth:`AbstractTorque._leaf_rules`), by the labels of :meth:`body_leaves`."""
        torques = {
            f"torques[{i}].{name}": rule
            for i, torque in enumerate(getattr(self, "torques", ()))
            for name, rule in torque._leaf_rules().items()
        }
        return {**type(self)._leaf_rules(self), **torques}

    def replace_body_leaves(self, leaves: list[BodyLeaf], values: list) -> "AbstractModel":
        """A copy with the arrays of ``leaves`` (from :meth:`body_leaves`) replaced by ``values``."""
        return eqx.tree_at(
            lambda m: [leaf.get(m) for leaf in leaves], self, list(values), is_leaf=lambda x: x is None
        )

    def batch_shape(self) -> tuple[int, ...]:
        shapes = []
        for leaf in self.body_leaves():
            shape = leaf_shape(self, leaf)
            shapes.append(shape[: len(shape) - leaf.core])
        return jnp.broadcast_shapes(*shapes) if shapes else ()

    @property
    def inertia_core_ndim(self) -> int:
        """2 when the scene's inertia is a tensor per body, 1 for principal moments: fixed when the
        scene is built (a batch of three bodies' moments cut from a larger batch, shape ``(3, 3)``,
        stays three bodies), from the shape for a scene that does not record it."""
        fixed = getattr(self, "_inertia_ndim", None)
        return fixed if fixed is not None else inertia_ndim(self.inertia)


def leaf_shape(model: AbstractModel, leaf: BodyLeaf) -> tuple[int, ...]:
    """The shape of a per-body array of ``model``; a ``ValueError`` naming it when the field that
    ``per_body_ndims`` names is missing or has fewer axes than one body's value."""
    try:
        shape = tuple(np.shape(leaf.get(model)))
    except AttributeError:
        owner, _, name = leaf.label.rpartition(".")
        raise ValueError(
            f"model field {leaf.label!r}: the per_body_ndims of {owner or type(model).__name__} names "
            f"{name!r}, which is not one of its fields."
        ) from None
    if len(shape) < leaf.core:
        raise ValueError(
            f"model field {leaf.label!r} has shape {shape}: one body's value has {leaf.core} "
            f"{'axis' if leaf.core == 1 else 'axes'} (per_body_ndims), so the field needs at least that many."
        )
    return shape


def inertia_ndim(inertia) -> int:
    """The per-body ndim of ``inertia`` from its shape: 2 for ``(..., 3, 3)``, else 1. (Constructors
    call it before their converters check the shape: NumPy's shape, which takes lists too.)"""
    return 2 if is_tensor_shape(np.shape(inertia)) else 1


# Records the inertia's form when a scene is built; slicing or reshaping its batch keeps it.
_INERTIA_NDIM = eqx.field(static=True, init=False, repr=False)


def replace_static(module: eqx.Module, **fields) -> eqx.Module:
    """A copy of ``module`` with the static ``fields`` replaced (``eqx.tree_at`` reaches only the
    leaves); the copy is a new object, so no other holder of ``module`` sees the change."""
    copy = jax.tree_util.tree_map(lambda leaf: leaf, module)
    for name, value in fields.items():
        object.__setattr__(copy, name, value)
    return copy


def keep_inertia_ndim(rebuilt: "AbstractModel", original: "AbstractModel") -> "AbstractModel":
    """``rebuilt``, a scene built from ``original``'s arrays, with ``original``'s inertia form: its
    constructor reads the form from the shape, which takes a slice of three bodies' principal
    moments, ``(3, 3)``, for one tensor."""
    return replace_static(rebuilt, _inertia_ndim=original.inertia_core_ndim)


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
    _inertia_ndim: int = _INERTIA_NDIM

    def __init__(self, inertia):
        self.inertia = inertia
        self._inertia_ndim = inertia_ndim(inertia)

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
        if self.inertia_core_ndim == 2:
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
    _inertia_ndim: int = _INERTIA_NDIM

    def __init__(self, inertia, torque=None):
        self.inertia = inertia
        self.torques = torque
        self._inertia_ndim = inertia_ndim(inertia)

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
        if not self.torques and self.inertia_core_ndim == 1:
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
    _inertia_ndim: int = _INERTIA_NDIM

    def __init__(self, inertia, mass, com, gravity=9.81, torque=None):
        self.inertia = inertia
        self.mass = mass
        self.com = com
        self.gravity = gravity
        self.torques = torque
        self._inertia_ndim = inertia_ndim(inertia)

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
        moments = jnp.linalg.eigvalsh(inertia) if self.inertia_core_ndim == 2 else inertia
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

    def _leaf_rules(self):
        return GRAVITY_RULES


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
