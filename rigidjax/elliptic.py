"""Elliptic integrals and Jacobi elliptic functions in JAX: jit-able, batched, differentiable in
every argument, float32 and float64, with scipy's parameter convention (``m = k^2``).

``ellipkm1`` and ``ellipj_m1`` take the complementary parameter ``p = 1 - m`` so that values near
``m = 1`` (a body near the separatrix) keep full relative accuracy. These are the building blocks of
rigidjax's closed-form torque-free motion.
"""

from ._closed_form.carlson import elliprj as elliprj
from ._closed_form.elliptic import ellipe as ellipe
from ._closed_form.elliptic import ellipeinc as ellipeinc
from ._closed_form.elliptic import ellipj as ellipj
from ._closed_form.elliptic import ellipj_m1 as ellipj_m1
from ._closed_form.elliptic import ellipk as ellipk
from ._closed_form.elliptic import ellipkinc as ellipkinc
from ._closed_form.elliptic import ellipkm1 as ellipkm1

__all__ = ["ellipe", "ellipeinc", "ellipj", "ellipj_m1", "ellipk", "ellipkinc", "ellipkm1", "elliprj"]
