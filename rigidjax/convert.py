"""Converters to and from other libraries' rotations and states: scipy's ``Rotation`` and MuJoCo's
free joint.

rigidjax's conventions: unit quaternions scalar first ``(w, x, y, z)``, mapping body-frame to
space-frame components; ``omega`` in body-frame components (rad/s). scipy's quaternions are scalar
last ``(x, y, z, w)`` (the same rotation); a MuJoCo free joint's ``qpos`` is the position then the
same scalar-first body-to-world quaternion, and its ``qvel`` the world-frame linear velocity then
the BODY-frame angular velocity. scipy is imported only by the functions that need it, never by
``import rigidjax``; the MuJoCo converters work on arrays and need no MuJoCo.
"""

from ._kinematics.convert import from_mujoco_free_joint as from_mujoco_free_joint
from ._kinematics.convert import from_scipy_rotation as from_scipy_rotation
from ._kinematics.convert import quat_from_scalar_last as quat_from_scalar_last
from ._kinematics.convert import quat_to_scalar_last as quat_to_scalar_last
from ._kinematics.convert import to_mujoco_free_joint as to_mujoco_free_joint
from ._kinematics.convert import to_scipy_rotation as to_scipy_rotation

__all__ = [
    "from_mujoco_free_joint",
    "from_scipy_rotation",
    "quat_from_scalar_last",
    "quat_to_scalar_last",
    "to_mujoco_free_joint",
    "to_scipy_rotation",
]
