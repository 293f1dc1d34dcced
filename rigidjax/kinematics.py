"""Kinematics: rotations as matrices, unit quaternions and Euler angles in all twelve sequences,
and the maps between Euler-angle rates and angular velocity.

Conventions: quaternions are unit and scalar-first ``(w, x, y, z)``; an orientation maps body-frame
components to space-frame components (``v_space = R @ v_body``); Euler angles
``(phi, theta, psi)`` are intrinsic rotations in the order of ``seq`` (default ``"zxz"``, the 3-1-3
convention), with the meaning of scipy's upper-case sequences.

The everyday functions are also in the top-level ``rigidjax`` namespace.
"""

from ._kinematics.euler import PROPER_SEQUENCES as PROPER_SEQUENCES
from ._kinematics.euler import SEQUENCES as SEQUENCES
from ._kinematics.euler import TAIT_BRYAN_SEQUENCES as TAIT_BRYAN_SEQUENCES
from ._kinematics.euler import body_angular_velocity as body_angular_velocity
from ._kinematics.euler import euler_from_matrix as euler_from_matrix
from ._kinematics.euler import euler_from_quat as euler_from_quat
from ._kinematics.euler import euler_rates as euler_rates
from ._kinematics.euler import is_proper_sequence as is_proper_sequence
from ._kinematics.euler import matrix_from_euler as matrix_from_euler
from ._kinematics.euler import quat_from_euler as quat_from_euler
from ._kinematics.euler import space_angular_velocity as space_angular_velocity
from ._kinematics.quaternion import matrix_from_quat as matrix_from_quat
from ._kinematics.quaternion import quat_angle_between as quat_angle_between
from ._kinematics.quaternion import quat_conjugate as quat_conjugate
from ._kinematics.quaternion import quat_exp as quat_exp
from ._kinematics.quaternion import quat_from_matrix as quat_from_matrix
from ._kinematics.quaternion import quat_log as quat_log
from ._kinematics.quaternion import quat_multiply as quat_multiply
from ._kinematics.quaternion import quat_normalize as quat_normalize
from ._kinematics.quaternion import quat_rotate as quat_rotate
from ._kinematics.quaternion import quat_slerp as quat_slerp

__all__ = [
    "PROPER_SEQUENCES",
    "SEQUENCES",
    "TAIT_BRYAN_SEQUENCES",
    "body_angular_velocity",
    "euler_from_matrix",
    "euler_from_quat",
    "euler_rates",
    "is_proper_sequence",
    "matrix_from_euler",
    "matrix_from_quat",
    "quat_angle_between",
    "quat_conjugate",
    "quat_exp",
    "quat_from_euler",
    "quat_from_matrix",
    "quat_log",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_slerp",
    "space_angular_velocity",
]
