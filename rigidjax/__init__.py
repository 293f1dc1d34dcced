"""rigidjax: rotational dynamics of rigid bodies in JAX.

Conventions (see the README): SI units, radians; quaternions are unit and scalar-first
``(w, x, y, z)``; orientations map body-frame to space-frame components; ``omega`` is in body-frame
components; Euler angles default to the 3-1-3 (``"zxz"``) sequence.
"""

from importlib.metadata import PackageNotFoundError, version

from ._dynamics import angular_momentum as angular_momentum
from ._dynamics import euler_equations as euler_equations
from ._dynamics import free_precession_rate as free_precession_rate
from ._dynamics import inertia_times as inertia_times
from ._dynamics import is_full_tensor as is_full_tensor
from ._dynamics import kinetic_energy as kinetic_energy
from ._dynamics import space_angular_momentum as space_angular_momentum
from ._elliptic import ellipe as ellipe
from ._elliptic import ellipeinc as ellipeinc
from ._elliptic import ellipj as ellipj
from ._elliptic import ellipj_m1 as ellipj_m1
from ._elliptic import ellipk as ellipk
from ._elliptic import ellipkinc as ellipkinc
from ._elliptic import ellipkm1 as ellipkm1
from ._elliptic import elliprj as elliprj
from ._euler import PROPER_SEQUENCES as PROPER_SEQUENCES
from ._euler import SEQUENCES as SEQUENCES
from ._euler import TAIT_BRYAN_SEQUENCES as TAIT_BRYAN_SEQUENCES
from ._euler import body_angular_velocity as body_angular_velocity
from ._euler import euler_from_matrix as euler_from_matrix
from ._euler import euler_from_quat as euler_from_quat
from ._euler import euler_rates as euler_rates
from ._euler import is_proper_sequence as is_proper_sequence
from ._euler import matrix_from_euler as matrix_from_euler
from ._euler import quat_from_euler as quat_from_euler
from ._euler import space_angular_velocity as space_angular_velocity
from ._fit import InertiaFit as InertiaFit
from ._fit import estimate_inertia as estimate_inertia
from ._fit import fit_inertia as fit_inertia
from ._fit import fit_inertia_to_orientation as fit_inertia_to_orientation
from ._fit import omega_from_orientations as omega_from_orientations
from ._inertia import check_inertia as check_inertia
from ._inertia import composite_inertia as composite_inertia
from ._inertia import hollow_cylinder as hollow_cylinder
from ._inertia import hollow_sphere as hollow_sphere
from ._inertia import is_physical_inertia as is_physical_inertia
from ._inertia import parallel_axis as parallel_axis
from ._inertia import principal_axes as principal_axes
from ._inertia import solid_box as solid_box
from ._inertia import solid_cylinder as solid_cylinder
from ._inertia import solid_ellipsoid as solid_ellipsoid
from ._inertia import solid_sphere as solid_sphere
from ._inertia import thin_disc as thin_disc
from ._inertia import thin_rod as thin_rod
from ._lie_group import RKMK as RKMK
from ._lie_group import dexpinv as dexpinv
from ._lie_group import quat_exp as quat_exp
from ._lie_group import rigid_body_vector_field as rigid_body_vector_field
from ._lie_group import rkmk_step as rkmk_step
from ._lie_group import simulate_structure_preserving as simulate_structure_preserving
from ._models import AbstractModel as AbstractModel
from ._models import AbstractTorque as AbstractTorque
from ._models import ConstantTorque as ConstantTorque
from ._models import FreeBody as FreeBody
from ._models import GravityTorque as GravityTorque
from ._models import HeavyTop as HeavyTop
from ._models import RigidBody as RigidBody
from ._models import State as State
from ._models import Torque as Torque
from ._models import ViscousDamping as ViscousDamping
from ._quaternion import matrix_from_quat as matrix_from_quat
from ._quaternion import quat_conjugate as quat_conjugate
from ._quaternion import quat_from_matrix as quat_from_matrix
from ._quaternion import quat_multiply as quat_multiply
from ._quaternion import quat_normalize as quat_normalize
from ._quaternion import quat_rotate as quat_rotate
from ._simulate import PRESETS as PRESETS
from ._simulate import simulate as simulate
from ._splitting import HeavyTopSplitting as HeavyTopSplitting
from ._splitting import LiePoissonSplitting as LiePoissonSplitting
from ._splitting import free_body_vector_field as free_body_vector_field
from ._splitting import heavy_top_splitting_step as heavy_top_splitting_step
from ._splitting import heavy_top_vector_field as heavy_top_vector_field
from ._splitting import split_free_body as split_free_body
from ._splitting import split_heavy_top as split_heavy_top
from ._splitting import splitting_step as splitting_step
from ._stability import SleepingTop as SleepingTop
from ._stability import SpinStability as SpinStability
from ._stability import sleeping_top as sleeping_top
from ._stability import spin_stability as spin_stability
from ._torque_free import torque_free_motion as torque_free_motion
from ._torque_free import torque_free_omega as torque_free_omega
from ._torque_free import torque_free_orientation as torque_free_orientation
from ._torque_free import torque_free_period as torque_free_period
from ._trajectory import Trajectory as Trajectory

try:
    __version__ = version("rigidjax")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"
