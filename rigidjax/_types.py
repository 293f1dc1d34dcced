"""jaxtyping aliases shared by the package.

Every function works on one body and broadcasts over leading batch axes, so the aliases use an
anonymous ``...`` batch: arguments of one call may have different (broadcastable) batch shapes.
"""

from typing import TypeAlias

from jaxtyping import Array, ArrayLike, Float

Scalar: TypeAlias = Float[ArrayLike, "..."]
"""A float or an array of floats that broadcasts against the batch."""

Vector: TypeAlias = Float[ArrayLike, "... 3"]
"""A 3-vector per body, e.g. ``omega`` in rad/s or a torque in N m."""

Quaternion: TypeAlias = Float[ArrayLike, "... 4"]
"""A unit quaternion per body, scalar first: ``(w, x, y, z)``."""

Matrix: TypeAlias = Float[ArrayLike, "... 3 3"]
"""A 3x3 matrix per body (rotation matrix or inertia tensor)."""

Inertia: TypeAlias = Float[ArrayLike, "... 3"] | Float[ArrayLike, "... 3 3"]
"""Principal moments ``(..., 3)`` or a full symmetric tensor ``(..., 3, 3)``, in kg m^2."""

Angles: TypeAlias = Float[ArrayLike, "... 3"]
"""Euler angles ``(phi, theta, psi)`` in radians, in the order of the sequence."""

VectorOut: TypeAlias = Float[Array, "... 3"]
QuaternionOut: TypeAlias = Float[Array, "... 4"]
MatrixOut: TypeAlias = Float[Array, "... 3 3"]
ScalarOut: TypeAlias = Float[Array, "..."]
