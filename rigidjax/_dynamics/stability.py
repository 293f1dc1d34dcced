"""Linear stability of steady rotations: the tennis-racket theorem and the sleeping top.

Both analyses linearise the equations of motion about a steady spin and read the stability off the
exponents ``lambda`` of perturbations ``~ exp(lambda t)``: a positive real part is an exponential
instability (its size is the growth rate), a purely imaginary one an oscillation (its size is the
angular frequency). Both are closed forms, broadcast over leading batch axes, work inside ``jit``
and ``vmap``, and have finite gradients everywhere (including the boundaries between stable and
unstable, where the square roots have an infinite slope: there the gradient of the vanishing branch
is taken as 0).
"""

import numbers

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._checks import (
    check_batch_shapes,
    check_finite,
    check_last_axis,
    common_float,
    compiled_when_eager,
    error_if,
)
from .._numerics import safe_sqrt
from .._repr import module_repr
from .._types import Inertia, Scalar, Vector
from .equations import is_full_tensor
from .inertia import check_inertia
from .torques import POSITIVE_MASS


def _is_plain_number(a) -> bool:
    """A Python ``int``/``float``, or what ``jit`` makes of one (a weakly typed scalar tracer)."""
    if type(a) in (int, float):
        return True
    aval = getattr(a, "aval", None)
    return bool(getattr(aval, "weak_type", False)) and getattr(aval, "ndim", 1) == 0


def _common_float(*args, names):
    """Float arrays of one dtype: the widest float among the array arguments (``common_float``).
    Plain Python numbers (e.g. the default ``gravity=9.81``, also when ``jit`` traced them) take that
    dtype instead of widening float32 input to float64."""
    typed = [(a, n) for a, n in zip(args, names, strict=True) if not _is_plain_number(a)]
    if typed:
        arrays = common_float(*[a for a, _ in typed], names=[n for _, n in typed])
        dtype = arrays[0].dtype
    else:
        dtype = jnp.result_type(float)
    out = []
    for a in args:
        out.append(jnp.asarray(a, dtype) if _is_plain_number(a) else arrays.pop(0))
    return out


def _principal_moments(inertia, function: str):
    if is_full_tensor(inertia):
        raise ValueError(
            f"{function} needs principal moments of shape (..., 3) (kg m^2), got a tensor of shape "
            f"{tuple(jnp.shape(inertia))}. Diagonalise it first: moments, axes = "
            "rigidjax.principal_axes(tensor); the spin axes are then the columns of `axes`. (A "
            "trailing (3, 3) is always read as a tensor; a batch of three bodies' moments is "
            "inertia[:, None, :].)"
        )
    check_last_axis(inertia, 3, "inertia")
    return check_inertia(inertia)


class SpinStability(eqx.Module):
    """Linear stability of steady torque-free spin about each principal axis.

    Returned by :func:`spin_stability`. An axis is exponentially unstable where neither ``stable``
    nor ``marginal`` holds (``growth_rate > 0``); :attr:`unstable` says so.

    **Attributes:**

    Every field has shape ``(..., 3)``; entry ``i`` is about spin about principal axis ``i``.

    - `growth_rate`: the real part of ``lambda`` (1/s), ``> 0`` only for the axis of the
      intermediate moment: a perturbation grows as ``exp(growth_rate * t)`` (the tennis-racket /
      Dzhanibekov instability). 0 elsewhere.
    - `frequency`: the imaginary part of ``lambda`` (rad/s), ``> 0`` for the axes of the largest
      and smallest moments: the transverse body-frame angular velocity circles the spin axis (on an
      ellipse) at this angular frequency. 0 elsewhere.
    - `stable`: ``lambda^2 < 0``: bounded oscillation about the axis.
    - `marginal`: ``lambda^2 == 0``: no exponential growth and no oscillation. This happens for
      spin about an axis whose moment equals another's (see :func:`spin_stability`) and at zero
      spin rate.
    """

    growth_rate: Float[Array, "*batch 3"]
    frequency: Float[Array, "*batch 3"]
    stable: Bool[Array, "*batch 3"]
    marginal: Bool[Array, "*batch 3"]

    @property
    def unstable(self) -> Bool[Array, "*batch 3"]:
        """``lambda^2 > 0``: an exponentially growing perturbation (``growth_rate > 0``)."""
        return ~(self.stable | self.marginal)

    __repr__ = module_repr


@compiled_when_eager
def spin_stability(inertia: Inertia, omega_magnitude: Scalar) -> SpinStability:
    """Stability of a torque-free body spinning steadily about each of its principal axes.

    For spin at rate ``Omega`` about principal axis ``i`` (the other two being ``j``, ``k``), Euler's
    equations linearised in the small transverse components give ``d^2 dw_j / dt^2 = lambda^2 dw_j``
    with ``lambda^2 = Omega^2 (I_i - I_j) (I_k - I_i) / (I_j I_k)``.

    ``lambda^2 > 0`` only when ``I_i`` lies strictly between ``I_j`` and ``I_k``: spin about the
    intermediate axis is unstable with growth rate ``|lambda|`` (the tennis-racket theorem). About the
    largest and the smallest axes ``lambda^2 < 0``: the perturbation oscillates with body-frame
    angular frequency ``|lambda|``.

    Equal moments (a symmetric top, ``I1 = I2 != I3``): spin about the odd axis is stable, with
    frequency ``|I3 - I1| / I1 * Omega``, the free precession rate
    (:func:`rigidjax.free_precession_rate`). Spin about any axis in the degenerate plane has
    ``lambda = 0`` and is reported ``marginal``: the linearised perturbation grows linearly, not
    exponentially (the spin axis drifts through the degenerate plane, where every axis is
    principal, while the symmetry axis stays put). For a sphere every axis is marginal. Moments are
    compared exactly: two moments that differ by roundoff count as distinct and give a tiny
    ``growth_rate`` or ``frequency``.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` (kg m^2). A full tensor ``(..., 3, 3)`` is
      rejected with a ``ValueError``: diagonalise it with :func:`rigidjax.principal_axes` first.
      Non-physical moments (non-positive, violating the triangle inequality, NaN) are an error
      (``ValueError``; ``equinox.error_if`` inside ``jit``).
    - `omega_magnitude`: spin rate ``Omega`` (rad/s), shape ``(...)``, broadcast against the batch
      axes of `inertia`; its sign does not matter. Beside one body's moments ``(3,)`` a trailing
      axis of 3 is refused (``ValueError``): it looks like an angular velocity vector, whose
      magnitude is the rate; three rates of one body go with ``inertia[None]``.

    **Returns:** a :class:`SpinStability` with ``growth_rate``, ``frequency``, ``stable`` and
    ``marginal``, each ``(..., 3)``. Gradients with respect to both arguments are finite everywhere;
    at ``lambda = 0`` (the square root's branch point) the derivative of the vanishing part is 0.
    """
    inertia, omega = _common_float(inertia, omega_magnitude, names=["inertia", "omega_magnitude"])
    omega = check_finite(omega, "omega_magnitude", "spin_stability")
    inertia = _principal_moments(inertia, "spin_stability")
    if inertia.ndim == 1 and omega.ndim >= 1 and omega.shape[-1] == 3:
        raise ValueError(
            f"spin_stability: omega_magnitude has shape {omega.shape} beside the one body of inertia "
            f"{inertia.shape}: its last axis would read as three spin rates, but an angular velocity "
            "vector is not a spin rate. Pass the rate, jnp.linalg.norm(omega, axis=-1); for three "
            "rates of one body, give the body a batch axis: spin_stability(inertia[None], rates)."
        )
    check_batch_shapes("spin_stability", ("inertia", inertia, 1), ("omega_magnitude", omega, 0))
    # Axis i with its neighbours j = i + 1 and k = i + 2 (cyclic); the product is symmetric in j, k.
    I_i = inertia
    I_j = jnp.roll(inertia, -1, axis=-1)
    I_k = jnp.roll(inertia, -2, axis=-1)
    # lambda^2 / Omega^2, dimensionless, as a product of ratios: the products of two moments
    # overflow (or underflow) float32 for moments beyond ~1e19 kg m^2 (a planet) or below ~1e-19.
    shape = ((I_i - I_j) / I_j) * ((I_k - I_i) / I_k)
    speed = jnp.abs(omega)[..., None]
    # The sign of lambda^2 from its factors: Omega^2 underflows to 0 for a slow spin in float32.
    spinning = speed > 0
    return SpinStability(
        growth_rate=speed * safe_sqrt(shape),
        frequency=speed * safe_sqrt(-shape),
        stable=spinning & (shape < 0),
        marginal=~spinning | (shape == 0),
    )


class SleepingTop(eqx.Module):
    """Linear stability of a heavy symmetric top spinning upright ("sleeping").

    Returned by :func:`sleeping_top`.

    **Attributes:**

    Every field has the batch shape ``(...)``.

    - `margin`: ``(I3 w3)^2 - 4 I1 m g l`` (kg^2 m^4 / s^2); positive means stable.
    - `critical_spin`: ``w_crit = 2 sqrt(I1 m g l) / I3`` (rad/s), the spin below which the upright
      top falls; 0 when ``l <= 0`` (centre of mass at or below the pivot: stable at any spin).
    - `stable`: ``margin > 0`` (at ``margin == 0`` the two modes merge and the tilt grows linearly).
    - `slow_rate`, `fast_rate`: the two roots ``lambda`` of ``I1 lambda^2 - I3 w3 lambda + m g l
      = 0`` (rad/s): the tilt of the symmetry axis, as the complex number ``X + iY`` of its
      space-frame direction, is a sum of two circular modes ``exp(i lambda t)``: the slow precession
      (``~ m g l / (I3 w3)`` for a fast top) and the fast nutation (``~ I3 w3 / I1``); positive in
      the sense of the spin. ``fast_rate`` is the root of larger magnitude. Below ``w_crit`` the
      roots are complex conjugates: both fields are then their common real part ``I3 w3 / (2 I1)``,
      the rate at which the growing tilt turns about the vertical.
    - `growth_rate`: the imaginary part of the roots (1/s): 0 when stable, else
      ``sqrt(4 I1 m g l - (I3 w3)^2) / (2 I1)``: the tilt grows as ``exp(growth_rate * t)``.
    """

    margin: Float[Array, "*batch"]
    critical_spin: Float[Array, "*batch"]
    stable: Bool[Array, "*batch"]
    slow_rate: Float[Array, "*batch"]
    fast_rate: Float[Array, "*batch"]
    growth_rate: Float[Array, "*batch"]

    __repr__ = module_repr


@compiled_when_eager(static_argnames=("symmetry_rtol",))
def sleeping_top(
    inertia: Inertia,
    mass: Scalar,
    com: Vector,
    omega3: Scalar,
    gravity: Scalar = 9.81,
    *,
    symmetry_rtol: float = 1e-4,
) -> SleepingTop:
    """Stability of a heavy symmetric top spinning upright about its vertical symmetry axis.

    The top is the :class:`rigidjax.HeavyTop` scene: a fixed pivot, gravity ``g`` along space -Z,
    the body z axis (the symmetry axis) vertical and spinning at ``w3``. Linearising in the tilt
    gives the characteristic equation ``I1 lambda^2 - I3 w3 lambda + m g l = 0`` for circular modes
    ``exp(i lambda t)`` of the tilt, so the upright top is stable when
    ``(I3 w3)^2 > 4 I1 m g l``, i.e. ``|w3| > w_crit = 2 sqrt(I1 m g l) / I3``.

    **Assumptions.** A symmetric top: ``I1 = I2`` (the transverse moments about the PIVOT) and the
    centre of mass on the symmetry axis. The moments are checked to within `symmetry_rtol`
    (``|I1 - I2| <= symmetry_rtol * (I1 + I2) / 2``) and their mean is used as ``I1``; a more
    asymmetric top is an error (its upright stability is not given by this criterion), as is a
    centre of mass off the body z axis (``|(com_x, com_y)| > symmetry_rtol * |com|``). These raise
    ``ValueError`` (``equinox.error_if`` checks inside ``jit``). ``l = com_z`` is signed: with the
    centre of mass below the pivot (``l < 0``, a hanging top) the criterion holds at any spin.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` about the pivot, ``(I1, I2, I3)`` with ``I3`` about
      the symmetry axis body z (kg m^2). A tensor ``(..., 3, 3)`` is rejected (``ValueError``):
      diagonalise it and express `com` in the principal axes first. Non-physical moments are an
      error, as in :func:`rigidjax.check_inertia`.
    - `mass`: mass (kg), shape ``(...)``.
    - `com`: body-frame position of the centre of mass relative to the pivot ``(..., 3)`` (m), on
      the z axis: ``(0, 0, l)``.
    - `omega3`: spin about the symmetry axis (rad/s), shape ``(...)``; its sign sets the sense of
      the precession rates. Beside one top (`inertia` ``(3,)``, `com` ``(3,)``) a trailing axis of
      3 is refused (``ValueError``): it looks like the angular velocity vector.
    - `gravity`: ``g`` (m/s^2), positive, shape ``(...)``: one magnitude per top (gravity points
      along space -Z), not a vector.
    - `symmetry_rtol`: relative tolerance of the symmetry checks above (default 1e-4: well above the
      roundoff of moments from ``principal_axes``, float32 included, and tight enough to reject a
      visibly asymmetric top).

    **Returns:** a :class:`SleepingTop` with ``margin``, ``critical_spin``, ``stable``,
    ``slow_rate``, ``fast_rate`` and ``growth_rate``, each ``(...)`` (the broadcast batch shape).
    Gradients are finite everywhere, including at ``margin = 0``.
    """
    inertia, mass, com, omega3, gravity = _common_float(
        inertia, mass, com, omega3, gravity, names=["inertia", "mass", "com", "omega3", "gravity"]
    )
    check_last_axis(com, 3, "com")
    # A tolerance is an option, not data: a NaN one switched both symmetry checks off.
    if isinstance(symmetry_rtol, bool) or not isinstance(symmetry_rtol, numbers.Real):
        raise TypeError(
            f"sleeping_top: symmetry_rtol must be a number (a relative tolerance), got {symmetry_rtol!r}."
        )
    if not 0 <= float(symmetry_rtol) < 1:
        raise ValueError(f"sleeping_top: symmetry_rtol must be a number in [0, 1), got {symmetry_rtol!r}.")
    mass, com, omega3, gravity = (
        check_finite(x, name, "sleeping_top")
        for x, name in ((mass, "mass"), (com, "com"), (omega3, "omega3"), (gravity, "gravity"))
    )
    mass = error_if(mass, jnp.any(mass <= 0), f"sleeping_top: mass {POSITIVE_MASS}.")
    gravity = error_if(
        gravity,
        jnp.any(gravity <= 0),
        "sleeping_top: gravity must be positive (m/s^2): the magnitude of gravity, which points along "
        "space -Z, one number per top (not a vector); a top without gravity spins as a torque-free "
        "body (spin_stability).",
    )
    inertia = _principal_moments(inertia, "sleeping_top")
    if inertia.ndim == 1 and com.ndim == 1 and omega3.ndim >= 1 and omega3.shape[-1] == 3:
        raise ValueError(
            f"sleeping_top: omega3 has shape {omega3.shape} beside the one top of inertia {inertia.shape}: "
            "its last axis would read as three spins, but omega3 is the spin about the symmetry "
            "axis, a number, not the angular velocity vector: pass omega[..., 2]; for three spins of "
            "one top, give the top a batch axis: sleeping_top(inertia[None], mass, com[None], spins)."
        )
    check_batch_shapes(
        "sleeping_top",
        *[("inertia", inertia, 1), ("mass", mass, 0), ("com", com, 1), ("omega3", omega3, 0)],
        ("gravity", gravity, 0),
    )
    I1, I2, I3 = inertia[..., 0], inertia[..., 1], inertia[..., 2]
    I1 = error_if(
        I1,
        jnp.abs(I1 - I2) > symmetry_rtol * 0.5 * (I1 + I2),
        f"sleeping_top: inertia must be that of a symmetric top, I1 = I2 (to a relative "
        f"{symmetry_rtol:g}): the criterion (I3 w3)^2 > 4 I1 m g l does not hold for an asymmetric "
        "top. Put the symmetry axis along body z, or raise symmetry_rtol to use (I1 + I2) / 2.",
    )
    transverse = jnp.sqrt(com[..., 0] ** 2 + com[..., 1] ** 2)
    lever = error_if(
        com[..., 2],
        transverse > symmetry_rtol * jnp.sqrt(transverse**2 + com[..., 2] ** 2),
        "sleeping_top: com must lie on the symmetry axis, com = (0, 0, l) in body axes: a centre of "
        "mass off the axis has no upright equilibrium.",
    )
    I1 = 0.5 * (I1 + I2)
    k = mass * gravity * lever  # m g l (N m), signed
    b = I3 * omega3  # axial angular momentum
    disc = b * b - 4.0 * I1 * k  # the margin
    root = safe_sqrt(disc)
    # Roots without cancellation: q = (b + sign(b) sqrt(disc)) / 2, fast = q / I1, slow = k / q.
    sign = jnp.where(b < 0, -1.0, 1.0).astype(b.dtype)
    q = 0.5 * (b + sign * root)
    q_safe = jnp.where(q == 0, jnp.ones_like(q), q)
    stable = disc > 0
    fast = jnp.where(stable, q / I1, b / (2.0 * I1))
    slow = jnp.where(stable, jnp.where(q == 0, jnp.zeros_like(q), k / q_safe), b / (2.0 * I1))
    growth = safe_sqrt(-disc) / (2.0 * I1)
    critical = jnp.broadcast_to(2.0 * safe_sqrt(I1 * k) / I3, disc.shape)
    return SleepingTop(
        margin=disc,
        critical_spin=critical,
        stable=stable,
        slow_rate=slow,
        fast_rate=fast,
        growth_rate=growth,
    )
