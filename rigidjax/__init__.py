"""rigidjax: rotational dynamics of rigid bodies in JAX.

Conventions (docs/conventions.md): SI units, radians; quaternions are unit and scalar-first
``(w, x, y, z)``; orientations map body-frame to space-frame components; ``omega`` is in body-frame
components; Euler angles default to the 3-1-3 (``"zxz"``) sequence.

The top level holds what most users need. Families have their own namespaces:
``rigidjax.kinematics`` (every rotation helper, the Euler sequences), ``rigidjax.elliptic`` (elliptic
integrals and functions), ``rigidjax.solvers`` (structure-preserving diffrax solvers, the presets),
``rigidjax.convert`` (to and from scipy's rotations and MuJoCo's free joint).
"""

import warnings as _warnings
from importlib.metadata import PackageNotFoundError, version

from . import convert as convert
from . import elliptic as elliptic
from . import kinematics as kinematics
from . import solvers as solvers
from ._closed_form.torque_free import torque_free_motion as torque_free_motion
from ._closed_form.torque_free import torque_free_omega as torque_free_omega
from ._closed_form.torque_free import torque_free_period as torque_free_period
from ._compilation_cache import use_compilation_cache as use_compilation_cache
from ._dynamics.equations import angular_momentum as angular_momentum
from ._dynamics.equations import euler_equations as euler_equations
from ._dynamics.equations import free_precession_rate as free_precession_rate
from ._dynamics.equations import kinetic_energy as kinetic_energy
from ._dynamics.equations import space_angular_momentum as space_angular_momentum
from ._dynamics.gyrostat import Gyrostat as Gyrostat
from ._dynamics.inertia import check_inertia as check_inertia
from ._dynamics.inertia import composite_inertia as composite_inertia
from ._dynamics.inertia import hollow_cylinder as hollow_cylinder
from ._dynamics.inertia import hollow_sphere as hollow_sphere
from ._dynamics.inertia import is_physical_inertia as is_physical_inertia
from ._dynamics.inertia import parallel_axis as parallel_axis
from ._dynamics.inertia import principal_axes as principal_axes
from ._dynamics.inertia import solid_box as solid_box
from ._dynamics.inertia import solid_cylinder as solid_cylinder
from ._dynamics.inertia import solid_ellipsoid as solid_ellipsoid
from ._dynamics.inertia import solid_sphere as solid_sphere
from ._dynamics.inertia import thin_disc as thin_disc
from ._dynamics.inertia import thin_rod as thin_rod
from ._dynamics.models import AbstractModel as AbstractModel
from ._dynamics.models import FreeBody as FreeBody
from ._dynamics.models import HeavyTop as HeavyTop
from ._dynamics.models import RigidBody as RigidBody
from ._dynamics.stability import SleepingTop as SleepingTop
from ._dynamics.stability import SpinStability as SpinStability
from ._dynamics.stability import sleeping_top as sleeping_top
from ._dynamics.stability import spin_stability as spin_stability
from ._dynamics.state import State as State
from ._dynamics.torques import AbstractTorque as AbstractTorque
from ._dynamics.torques import ConstantTorque as ConstantTorque
from ._dynamics.torques import GravityTorque as GravityTorque
from ._dynamics.torques import Torque as Torque
from ._dynamics.torques import ViscousDamping as ViscousDamping
from ._fit import InertiaFit as InertiaFit
from ._fit import estimate_inertia as estimate_inertia
from ._fit import fit_inertia as fit_inertia
from ._fit import fit_inertia_to_orientation as fit_inertia_to_orientation
from ._fit import omega_from_orientations as omega_from_orientations
from ._integrate.cores import use_cpu_cores as use_cpu_cores
from ._integrate.simulate import simulate as simulate
from ._integrate.trajectory import Trajectory as Trajectory
from ._kinematics.euler import body_angular_velocity as body_angular_velocity
from ._kinematics.euler import euler_from_matrix as euler_from_matrix
from ._kinematics.euler import euler_from_quat as euler_from_quat
from ._kinematics.euler import euler_rates as euler_rates
from ._kinematics.euler import matrix_from_euler as matrix_from_euler
from ._kinematics.euler import quat_from_euler as quat_from_euler
from ._kinematics.euler import space_angular_velocity as space_angular_velocity
from ._kinematics.quaternion import matrix_from_quat as matrix_from_quat
from ._kinematics.quaternion import quat_conjugate as quat_conjugate
from ._kinematics.quaternion import quat_from_matrix as quat_from_matrix
from ._kinematics.quaternion import quat_multiply as quat_multiply
from ._kinematics.quaternion import quat_normalize as quat_normalize
from ._kinematics.quaternion import quat_rotate as quat_rotate

try:
    __version__ = version("rigidjax")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = [
    # kinematics
    "body_angular_velocity",
    "euler_from_matrix",
    "euler_from_quat",
    "euler_rates",
    "matrix_from_euler",
    "matrix_from_quat",
    "quat_conjugate",
    "quat_from_euler",
    "quat_from_matrix",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "space_angular_velocity",
    # dynamics
    "angular_momentum",
    "euler_equations",
    "free_precession_rate",
    "kinetic_energy",
    "principal_axes",
    "space_angular_momentum",
    # inertia of shapes
    "check_inertia",
    "composite_inertia",
    "hollow_cylinder",
    "hollow_sphere",
    "is_physical_inertia",
    "parallel_axis",
    "solid_box",
    "solid_cylinder",
    "solid_ellipsoid",
    "solid_sphere",
    "thin_disc",
    "thin_rod",
    # scenes
    "AbstractModel",
    "AbstractTorque",
    "ConstantTorque",
    "FreeBody",
    "GravityTorque",
    "Gyrostat",
    "HeavyTop",
    "RigidBody",
    "State",
    "Torque",
    "ViscousDamping",
    # simulation and closed forms
    "Trajectory",
    "simulate",
    "torque_free_motion",
    "torque_free_omega",
    "torque_free_period",
    "use_compilation_cache",
    "use_cpu_cores",
    # stability
    "SleepingTop",
    "SpinStability",
    "sleeping_top",
    "spin_stability",
    # fitting
    "InertiaFit",
    "estimate_inertia",
    "fit_inertia",
    "fit_inertia_to_orientation",
    "omega_from_orientations",
]


def _torque_free_orientation(inertia, omega0, q0, t):
    return torque_free_motion(inertia, omega0, q0, t)[1]


def _simulate_structure_preserving(model, state0, ts, solver, dt, *, args=None):
    return simulate(model, state0, ts, solver=solver, dt0=dt, args=args)


def _is_full_tensor(inertia):
    from ._checks import is_full_tensor

    return is_full_tensor(inertia)


# Names of earlier releases, kept working for one release: each warns and names its replacement.
_MOVED = {
    **{
        name: ("rigidjax.kinematics", name)
        for name in (
            "SEQUENCES",
            "PROPER_SEQUENCES",
            "TAIT_BRYAN_SEQUENCES",
            "is_proper_sequence",
            "quat_exp",
        )
    },
    **{name: ("rigidjax.elliptic", name) for name in elliptic.__all__},
    **{name: ("rigidjax.solvers", name) for name in solvers.__all__},
}
_REPLACED = {
    "inertia_times": (angular_momentum, "rigidjax.angular_momentum (the same function)"),
    "torque_free_orientation": (_torque_free_orientation, "rigidjax.torque_free_motion(...)[1]"),
    "simulate_structure_preserving": (
        _simulate_structure_preserving,
        "rigidjax.simulate(model, state0, ts, solver=solver, dt0=dt)",
    ),
    "is_full_tensor": (_is_full_tensor, "inertia.shape[-2:] == (3, 3)"),
}


def __getattr__(name):
    if name in _MOVED:
        namespace, attr = _MOVED[name]
        _warnings.warn(
            f"rigidjax.{name} has moved to {namespace}.{attr}; the top-level name will be removed.",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(
            {"rigidjax.kinematics": kinematics, "rigidjax.elliptic": elliptic, "rigidjax.solvers": solvers}[
                namespace
            ],
            attr,
        )
    if name in _REPLACED:
        value, replacement = _REPLACED[name]
        _warnings.warn(
            f"rigidjax.{name} is deprecated; use {replacement}. It will be removed.",
            DeprecationWarning,
            stacklevel=2,
        )
        return value
    raise AttributeError(f"module 'rigidjax' has no attribute {name!r}")


def __dir__():
    return sorted(__all__ + ["convert", "elliptic", "kinematics", "solvers", "__version__"])
