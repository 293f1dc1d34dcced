"""Euler's equations and the dynamical quantities of a rotating rigid body.

Everything is in the body frame, where the inertia tensor is constant. ``inertia`` is principal
moments ``(..., 3)`` (body axes are principal axes) or a full symmetric tensor ``(..., 3, 3)``: a
trailing ``(3, 3)`` is always read as a tensor.

Bad input: shapes other than these, and complex or boolean dtypes, raise ``ValueError``/``TypeError``
while tracing (integer arrays are promoted to float). At run time (``eqx.error_if``, also under
``jit`` and ``vmap``) NaN or inf raises, and so does an ``inertia`` the formula cannot use: in
:func:`euler_equations` a zero principal moment or a singular tensor (it is divided by). These are
pointwise formulas, valid for any moments (and differentiated entry by entry): physical validity
(positive moments, the triangle inequality) is checked where a body is built and simulated
(:func:`rigidjax.check_inertia`, :func:`rigidjax.simulate`), not here. A zero ``orientation``
quaternion raises (any other is normalised, as in :func:`rigidjax.quat_rotate`). Rigidjax's own
integrators call unchecked private cores (``_euler_equations``...).
"""

import jax
import jax.numpy as jnp

from .._checks import (
    check_batch_shapes,
    check_finite,
    check_last_axis,
    check_rotation_quaternion,
    common_float,
    compiled_when_eager,
    error_if,
    is_full_tensor,
)
from .._kinematics.quaternion import _quat_normalize, _quat_rotate
from .._numerics import eps
from .._types import Inertia, Quaternion, Scalar, ScalarOut, Vector, VectorOut


def _components(x):
    return [x[..., i] for i in range(3)]


def _cross_components(a, b):
    """The three components of ``a x b`` from those of ``a`` and ``b``."""
    (a0, a1, a2), (b0, b1, b2) = a, b
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


def _cross(a, b):
    """``a x b`` component by component (``jnp.cross`` slices and concatenates, which XLA does not
    fuse into the elementwise code of an integrator's step)."""
    return jnp.stack(_cross_components(_components(a), _components(b)), axis=-1)


def _solve_3x3(matrix, rhs):
    """``matrix^-1 rhs`` for ``(..., 3, 3)`` matrices by the adjugate (Cramer's rule), elementwise.

    A batched ``jnp.linalg.solve`` of 3 x 3 systems inside an integrator's step made a full-tensor
    body 8x slower than one with principal moments (10^4 bodies, "balanced": 5.4 s against 0.68 s);
    the adjugate is a few dozen fused multiplications. For an inertia tensor (symmetric positive
    definite) its error is of the same order as LU's, ``cond * eps``.

    Both sides are divided by the matrix's largest entry first: its cofactors are products of two
    entries and its determinant of three, which overflow float32 for moments from ~5e12 kg m^2 up
    (and underflow from ~1e-13 down)."""
    matrix, rhs = _unit_scaled(matrix, rhs)
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = (_components(matrix[..., i, :]) for i in range(3))
    c00, c01, c02 = a11 * a22 - a12 * a21, a12 * a20 - a10 * a22, a10 * a21 - a11 * a20
    c10, c11, c12 = a02 * a21 - a01 * a22, a00 * a22 - a02 * a20, a01 * a20 - a00 * a21
    c20, c21, c22 = a01 * a12 - a02 * a11, a02 * a10 - a00 * a12, a00 * a11 - a01 * a10
    det = a00 * c00 + a01 * c01 + a02 * c02
    b0, b1, b2 = _components(rhs)
    x0 = c00 * b0 + c10 * b1 + c20 * b2
    x1 = c01 * b0 + c11 * b1 + c21 * b2
    x2 = c02 * b0 + c12 * b1 + c22 * b2
    return jnp.stack([x0, x1, x2], axis=-1) / det[..., None]


def _unit_scaled(matrix, *vectors):
    """``matrix`` (``(..., 3, 3)``) and ``vectors`` (``(..., 3)``) divided by the matrix's largest
    entry, by its reciprocal square root twice: the reciprocal itself of a float32 entry above ~1e38
    is subnormal, which the CPU flushes to zero."""
    scale = jnp.max(jnp.abs(matrix), axis=(-2, -1))
    root = jax.lax.rsqrt(jnp.where(scale > 0, scale, jnp.ones_like(scale)))
    matrix = matrix * root[..., None, None] * root[..., None, None]
    return (matrix, *(v * root[..., None] * root[..., None] for v in vectors))


def _inertia_times(inertia: Inertia, omega: Vector) -> VectorOut:
    """``I @ omega`` for principal moments or a full tensor."""
    inertia, omega = common_float(inertia, omega, names=["inertia", "omega"])
    check_last_axis(omega, 3, "omega")
    if is_full_tensor(inertia):  # written out: a batched einsum does not fuse into a step
        w0, w1, w2 = _components(omega)
        rows = [_components(inertia[..., i, :]) for i in range(3)]
        return jnp.stack([a0 * w0 + a1 * w1 + a2 * w2 for a0, a1, a2 in rows], axis=-1)
    return inertia * omega


def _euler_equations(inertia: Inertia, omega: Vector, torque: Vector | None = None) -> VectorOut:
    """Angular acceleration ``d(omega)/dt`` in the body frame (rad/s^2).

    Principal moments: ``I1 w1' = (I2 - I3) w2 w3 + tau1`` and cyclic. Full tensor:
    ``I w' = tau - w x (I w)``, solved for ``w'``. ``torque`` is in body-frame components (N m).
    """
    torque_free = torque is None
    if torque_free:
        inertia, omega = common_float(inertia, omega, names=["inertia", "omega"])
        torque = jnp.zeros((), omega.dtype)
    else:
        inertia, omega, torque = common_float(inertia, omega, torque, names=["inertia", "omega", "torque"])
        check_last_axis(torque, 3, "torque")
    check_last_axis(omega, 3, "omega")
    if is_full_tensor(inertia):
        return _solve_3x3(inertia, torque - _cross(omega, _inertia_times(inertia, omega)))
    I1, I2, I3 = inertia[..., 0], inertia[..., 1], inertia[..., 2]
    w1, w2, w3 = omega[..., 0], omega[..., 1], omega[..., 2]
    # Dimensionless ratios of the moments alone: inside an integrator's loop XLA computes them once,
    # where a division would run at every stage (divisions were the hottest instructions of an
    # omega-only "balanced" step). Ratios, not reciprocals: 1/I of the Earth in SI units is at the
    # edge of float32's normal range.
    ratios = jnp.stack([(I2 - I3) / I1, (I3 - I1) / I2, (I1 - I2) / I3], axis=-1)
    products = jnp.stack([w2 * w3, w3 * w1, w1 * w2], axis=-1)
    gyroscopic = ratios * products
    return gyroscopic if torque_free else gyroscopic + torque / inertia


def _angular_momentum(inertia: Inertia, omega: Vector) -> VectorOut:
    """Angular momentum ``L = I omega`` in body-frame components (kg m^2/s)."""
    return _inertia_times(inertia, omega)


def _space_angular_momentum(inertia: Inertia, omega: Vector, orientation: Quaternion) -> VectorOut:
    """Angular momentum in space-frame components, ``R L_body``; conserved when torque-free."""
    L = _inertia_times(inertia, omega)
    orientation = jnp.asarray(orientation, L.dtype)
    check_last_axis(orientation, 4, "orientation")  # name the caller's argument, not quat_rotate's q
    return _quat_rotate(orientation, L)


def _kinetic_energy(inertia: Inertia, omega: Vector) -> ScalarOut:
    """Rotational kinetic energy ``omega . (I omega) / 2`` (J)."""
    L = _inertia_times(inertia, omega)
    return 0.5 * jnp.sum(jnp.asarray(omega, L.dtype) * L, axis=-1)


def _free_precession_rate(I1: Scalar, I3: Scalar, omega3: Scalar) -> ScalarOut:
    """Body-frame free precession rate ``(I3 - I1) / I1 * omega3`` of a torque-free symmetric top.

    ``I1 = I2`` are the transverse moments and ``I3`` the symmetry-axis moment. The transverse
    angular velocity turns about the body symmetry axis as ``w1 + i w2 = A exp(i Omega t)``, so a
    prolate body (``I3 < I1``) precesses backwards. For the Earth this is the Euler wobble rate.
    """
    I1, I3, omega3 = common_float(I1, I3, omega3, names=["I1", "I3", "omega3"])
    return (I3 - I1) / I1 * omega3


# --- the public, checked functions -------------------------------------------------------------------


def _checked(inertia, omega, where, extra=(), invertible=False):
    """Float arrays of one dtype, shape-checked while tracing, value-checked at run time."""
    names = ["inertia", "omega"] + [n for n, _, _ in extra]
    arrays = common_float(inertia, omega, *[a for _, a, _ in extra], names=names)
    inertia, omega, *rest = arrays
    tensor = is_full_tensor(inertia)
    check_last_axis(omega, 3, "omega")
    for (name, _, size), array in zip(extra, rest, strict=True):
        check_last_axis(array, size, name)
    check_batch_shapes(
        where,
        ("inertia", inertia, 2 if tensor else 1),
        ("omega", omega, 1),
        *[(name, array, 1) for (name, _, _), array in zip(extra, rest, strict=True)],
    )
    inertia = check_finite(inertia, "inertia", where)
    omega = check_finite(omega, "omega", where)
    if invertible:
        if tensor:
            # On the tensor divided by its largest entry: scale**3 overflows float32 from ~5e12 up.
            singular = jnp.abs(jnp.linalg.det(_unit_scaled(inertia)[0])) <= 1e2 * eps(inertia.dtype)
        else:
            singular = jnp.any(inertia == 0, axis=-1)
        inertia = error_if(
            inertia,
            jnp.any(singular),
            f"{where}: inertia is singular (a zero principal moment): I omega' = ... cannot be "
            "solved for omega'. Every moment of inertia of a rigid body is > 0 kg m^2.",
        )
    return inertia, omega, rest


@compiled_when_eager
def euler_equations(inertia: Inertia, omega: Vector, torque: Vector | None = None) -> VectorOut:
    """Euler's equations: the angular acceleration ``d(omega)/dt`` in the body frame.

    Principal moments: ``I1 w1' = (I2 - I3) w2 w3 + tau1`` and cyclic. Full tensor:
    ``I w' = tau - w x (I w)``, solved for ``w'``. This is a pointwise formula: the moments are not
    checked for physical validity here (``check_inertia`` and ``simulate`` do that).

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` or a full symmetric tensor ``(..., 3, 3)`` in body
      axes (kg m^2); a trailing ``(3, 3)`` is always read as a tensor.
      A zero principal moment or a singular tensor (it is divided by) raises at run time.
    - `omega`: angular velocity in body-frame components (rad/s), shape ``(..., 3)``, broadcast
      against the batch axes of `inertia`.
    - `torque`: applied torque in body-frame components (N m), shape ``(..., 3)``; None (the
      default) for a torque-free body.

    **Returns:** ``d(omega)/dt`` in body-frame components (rad/s^2), shape ``(..., 3)``. NaN or inf
    in any input raises at run time.
    """
    if torque is None:
        inertia, omega, _ = _checked(inertia, omega, "euler_equations", invertible=True)
        return _euler_equations(inertia, omega)
    inertia, omega, (torque,) = _checked(
        inertia, omega, "euler_equations", [("torque", torque, 3)], invertible=True
    )
    return _euler_equations(inertia, omega, check_finite(torque, "torque", "euler_equations"))


@compiled_when_eager
def angular_momentum(inertia: Inertia, omega: Vector) -> VectorOut:
    """Angular momentum ``L = I omega`` in body-frame components.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` or a full symmetric tensor ``(..., 3, 3)`` in body
      axes (kg m^2); a trailing ``(3, 3)`` is always read as a tensor.
    - `omega`: angular velocity in body-frame components (rad/s), shape ``(..., 3)``, broadcast
      against the batch axes of `inertia`.

    **Returns:** ``L`` in body-frame components (kg m^2/s), shape ``(..., 3)``. NaN or inf raises at
    run time.
    """
    inertia, omega, _ = _checked(inertia, omega, "angular_momentum")
    return _inertia_times(inertia, omega)


@compiled_when_eager
def space_angular_momentum(inertia: Inertia, omega: Vector, orientation: Quaternion) -> VectorOut:
    """Angular momentum in space-frame components, ``R L_body``; conserved when torque-free.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` or a full symmetric tensor ``(..., 3, 3)`` in body
      axes (kg m^2); a trailing ``(3, 3)`` is always read as a tensor.
    - `omega`: angular velocity in body-frame components (rad/s), shape ``(..., 3)``, broadcast
      against the batch axes of `inertia`.
    - `orientation`: unit quaternion ``(w, x, y, z)`` mapping body-frame to space-frame components,
      shape ``(..., 4)``. It is normalised first; a zero quaternion raises at run time.

    **Returns:** ``L`` in space-frame components (kg m^2/s), shape ``(..., 3)``. NaN or inf raises at
    run time.
    """
    where = "space_angular_momentum"
    inertia, omega, (orientation,) = _checked(inertia, omega, where, [("orientation", orientation, 4)])
    orientation = _quat_normalize(check_rotation_quaternion(orientation, "orientation", where))
    return _space_angular_momentum(inertia, omega, orientation)


@compiled_when_eager
def kinetic_energy(inertia: Inertia, omega: Vector) -> ScalarOut:
    """Rotational kinetic energy ``omega . (I omega) / 2``.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` or a full symmetric tensor ``(..., 3, 3)`` in body
      axes (kg m^2); a trailing ``(3, 3)`` is always read as a tensor.
    - `omega`: angular velocity in body-frame components (rad/s), shape ``(..., 3)``, broadcast
      against the batch axes of `inertia`.

    **Returns:** the energy (J), shape ``(...)``. NaN or inf raises at run time.
    """
    inertia, omega, _ = _checked(inertia, omega, "kinetic_energy")
    return _kinetic_energy(inertia, omega)


@compiled_when_eager
def free_precession_rate(I1: Scalar, I3: Scalar, omega3: Scalar) -> ScalarOut:
    """Free precession rate ``Omega = (I3 - I1) / I1 * omega3`` of a torque-free symmetric top.

    ``Omega`` is a body-frame rate: the transverse angular velocity turns about the body symmetry
    axis as ``w1 + i w2 = A exp(i Omega t)``, so a prolate body (``I3 < I1``) precesses backwards.
    For the Earth this is the Euler wobble rate. Like Euler's equations this is a pointwise formula
    and does not check the moments for physical validity.

    **Arguments:**

    - `I1`: the transverse moment ``I1 = I2`` (kg m^2), shape ``(...)``. ``I1 = 0`` (it is divided
      by) raises at run time.
    - `I3`: the moment about the symmetry axis (kg m^2), shape ``(...)``.
    - `omega3`: the spin, the body-frame angular velocity about the symmetry axis (rad/s), shape
      ``(...)``. The three arguments broadcast against each other.

    **Returns:** ``Omega`` (rad/s), shape ``(...)``. NaN or inf in any input raises at run time.
    """
    where = "free_precession_rate"
    I1, I3, omega3 = common_float(I1, I3, omega3, names=["I1", "I3", "omega3"])
    check_batch_shapes(where, ("I1", I1, 0), ("I3", I3, 0), ("omega3", omega3, 0))
    I1, I3, omega3 = (check_finite(x, n, where) for x, n in ((I1, "I1"), (I3, "I3"), (omega3, "omega3")))
    I1 = error_if(I1, jnp.any(I1 == 0), f"{where}: I1 = 0; the transverse moment must be > 0 kg m^2.")
    return _free_precession_rate(I1, I3, omega3)
