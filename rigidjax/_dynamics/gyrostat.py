"""The gyrostat: a rigid body carrying rotors spun at constant rates relative to it.

A gyroscope's rotor in its frame, a satellite's momentum or reaction wheel at a constant speed: the
rotors add an angular momentum ``h`` that is fixed in the body, so ``L = I omega + h`` and Euler's
equations become ``I omega' = -omega x (I omega + h) + tau``.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import as_float_array, check_last_axis
from .equations import _cross, _euler_equations, _inertia_times
from .models import _INERTIA_NDIM, AbstractModel, _inertia_field, inertia_ndim
from .torques import _as_torque_tuple, _total_torque


class Gyrostat(AbstractModel):
    """A rigid body carrying rotors spun at constant rates relative to it (a gyrostat).

    The rotors' angular momentum relative to the body, ``h``, is fixed in the body frame, so the
    angular momentum is ``L = I omega + h`` and Euler's equations read

    ``I omega' = -omega x (I omega + h) + tau``.

    Without torques the kinetic energy ``omega . I omega / 2``, ``|L| = |I omega + h|`` and the
    space-frame ``R L`` are conserved. (The rotors' own spin energy is not part of it: whatever keeps
    their rates constant does work on them.) A large enough ``h`` along the intermediate axis makes
    a spin about that axis stable: for a spin ``Omega`` about body axis 2 with ``h = (0, h2, 0)``
    the linearised motion is bounded iff ``(I2 Omega + h2 - I1 Omega)(I2 Omega + h2 - I3 Omega) > 0``.

    Runs with every accuracy preset and with :class:`rigidjax.solvers.RKMK`; ``accuracy="exact"``
    and the splittings are for bodies without rotors. ``jax.grad`` with respect to ``h`` and the
    inertia works through :func:`rigidjax.simulate`.

    **Arguments:**

    - `inertia`: of the whole body with its rotors (kg m^2), in body axes: principal moments
      ``(..., 3)`` or a tensor ``(..., 3, 3)``; leading axes are batch axes.
    - `rotor_momentum`: ``h``, the rotors' angular momentum relative to the body in body-frame
      components (N m s = kg m^2/s), ``(..., 3)``: for one wheel, its axial moment of inertia times
      its spin rate relative to the body times its unit axis. Leading axes are batch axes.
    - `torque`: external torques, as for :class:`rigidjax.RigidBody`; None for a torque-free
      gyrostat.
    """

    inertia: Float[ArrayLike, "*batch 3"] | Float[ArrayLike, "*batch 3 3"] = eqx.field(
        converter=_inertia_field
    )
    rotor_momentum: Float[Array, "*batch 3"] = eqx.field(
        converter=lambda x: as_float_array(x, "rotor_momentum")
    )
    torques: tuple = eqx.field(converter=_as_torque_tuple, default=())
    _inertia_ndim: int = _INERTIA_NDIM

    def __init__(self, inertia, rotor_momentum, torque=None):
        self.inertia = inertia
        self.rotor_momentum = rotor_momentum
        self.torques = torque
        self._inertia_ndim = inertia_ndim(inertia)

    def __check_init__(self):
        check_last_axis(self.rotor_momentum, 3, "Gyrostat.rotor_momentum")

    @property
    def needs_orientation(self) -> bool:
        return any(t.needs_orientation for t in self.torques)

    @property
    def torque_free(self) -> bool:
        # False on purpose: torque_free promises the motion of a FreeBody (the closed form, the
        # Lie-Poisson splitting and the polhode scales rely on it), which the rotors change.
        return False

    @property
    def conserves_angular_momentum(self) -> bool:
        return not self.torques

    @property
    def conserves_energy(self) -> bool:
        # d/dt (omega . I omega / 2) = omega . (-omega x L + tau) = omega . tau: the rotors do no work
        # on the body's own kinetic energy.
        return all(t.conservative for t in self.torques)

    def angular_momentum(self, omega):
        """Body-frame ``L = I omega + h`` (kg m^2/s) at the body-frame ``omega`` (rad/s,
        ``(..., 3)``, broadcast against the scene's batch axes: for batched samples
        ``(*batch, T, 3)`` insert a time axis after the batch axes of both fields first)."""
        return _inertia_times(self.inertia, omega) + self.rotor_momentum.astype(omega.dtype)

    def angular_acceleration(self, t, state, args):
        omega = state.omega
        h = self.rotor_momentum.astype(omega.dtype)
        # The rotors enter as the gyroscopic torque -omega x h on top of the external ones.
        tau = _total_torque(self.torques, t, state, args) - _cross(omega, h)
        return _euler_equations(self.inertia, omega, tau)

    def omega_scale(self, state, duration, args):
        """Without torques, the bound ``|omega_i| <= sqrt(omega . I omega / I_i)`` from the conserved
        kinetic energy (per component for principal moments, the smallest moment for a tensor);
        with torques the default, ``|omega0|``."""
        if self.torques:
            return super().omega_scale(state, duration, args)
        omega = state.omega
        inertia = self.inertia
        tensor = self.inertia_core_ndim == 2
        moments = jnp.linalg.eigvalsh(inertia) if tensor else inertia
        # Ratios of moments only: SI-scale moments would overflow float32 in the products.
        top = jnp.max(moments)
        twice_energy = jnp.sum(omega * _inertia_times(inertia / top, omega))
        if tensor:
            return jnp.broadcast_to(jnp.sqrt(twice_energy / (jnp.min(moments) / top)), (3,))
        return jnp.sqrt(twice_energy / (moments / top))

    def per_body_ndims(self):
        return {"inertia": self.inertia_core_ndim, "rotor_momentum": 1}
