"""The state of a body or a batch of bodies: angular velocity and, optionally, orientation."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._checks import as_float_array, check_last_axis


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
        omega = as_float_array(omega, "State.omega")
        check_last_axis(omega, 3, "State.omega")
        self.omega = omega
        if orientation is not None:
            orientation = as_float_array(orientation, "State.orientation")
            check_last_axis(orientation, 4, "State.orientation")
            if omega.dtype != orientation.dtype:
                dtype = jnp.result_type(omega.dtype, orientation.dtype)
                self.omega = omega.astype(dtype)
                orientation = orientation.astype(dtype)
        self.orientation = orientation
