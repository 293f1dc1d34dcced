"""Euler angles in all twelve intrinsic sequences, and the angular velocity they imply.

``angles = (phi, theta, psi)`` are applied as intrinsic rotations about the axes of ``seq`` in order:
for the default ``seq="zxz"`` (3-1-3), ``phi`` (precession) about space Z, ``theta`` (nutation) about
the line of nodes (the new x), ``psi`` (spin) about body z, so ``R = Rz(phi) Rx(theta) Rz(psi)`` maps
body-frame to space-frame components. This is scipy's upper-case (intrinsic) ``from_euler``.

Proper sequences (first axis = third axis) are singular at ``sin(theta) = 0``; Tait-Bryan sequences
at ``cos(theta) = 0``. There only ``phi ± psi`` is defined: the conversions back to angles return the
documented split ``psi = 0`` (all of the rotation in ``phi``) and never NaN, with finite gradients.

Bad input: wrong shapes, complex or boolean dtypes and unknown sequences raise ``ValueError`` /
``TypeError`` while tracing (integer arrays are promoted to float). At run time (``ValueError``
for concrete inputs, ``eqx.error_if`` under ``jit`` and ``vmap``) NaN or inf in any input raises, as
do a zero quaternion in :func:`euler_from_quat` (any other ``q`` means the rotation of
``q / |q|``, as in scipy) and a matrix in :func:`euler_from_matrix` that is not a rotation
(``max|R R^T - 1|`` beyond ``1e-6`` in float64, ``1e-4`` in float32, or ``det R < 0``; tiny
non-orthogonality is accepted).
:func:`euler_rates` with ``throw=False`` raises nothing and returns NaN instead.
Rigidjax's own integrators call unchecked private cores (``_euler_from_quat``...).
"""

import jax
import jax.numpy as jnp

from .._checks import (
    check_batch_shapes,
    check_finite,
    check_flag,
    check_last_axis,
    check_last_two_axes,
    check_rotation_matrix,
    check_rotation_quaternion,
    common_float,
    compiled_when_eager,
    error_if,
)
from .._numerics import eps, safe_atan2, safe_hypot
from .._types import Angles, Matrix, MatrixOut, Quaternion, Vector, VectorOut
from .quaternion import _quat_from_matrix, _quat_multiply

PROPER_SEQUENCES = ("zxz", "zyz", "xyx", "xzx", "yxy", "yzy")
"""The six proper Euler sequences (first axis = third axis), singular at ``sin(theta) = 0``."""
TAIT_BRYAN_SEQUENCES = ("xyz", "xzy", "yxz", "yzx", "zxy", "zyx")
"""The six Tait-Bryan sequences (three different axes), singular at ``cos(theta) = 0``."""
SEQUENCES = PROPER_SEQUENCES + TAIT_BRYAN_SEQUENCES
"""All twelve intrinsic sequences accepted as ``seq`` (lower case; the argument may be given in
upper case too, meaning the same intrinsic rotations, but not in a mix of cases)."""
_AXIS = {"x": 0, "y": 1, "z": 2}


def _parse_seq(seq: str, name: str = "seq") -> tuple[int, int, int]:
    """The axes of an Euler sequence; a ``ValueError`` naming ``name`` (the caller's argument) for
    any other value."""
    if not isinstance(seq, str) or seq.lower() not in SEQUENCES:
        raise ValueError(
            f"{name} must be one of the twelve intrinsic Euler sequences {SEQUENCES} "
            f"(in lower or upper case), got {seq!r}."
        )
    if seq not in (seq.lower(), seq.upper()):
        # scipy reads case as meaning: upper case intrinsic, lower case extrinsic, and refuses a mix.
        raise ValueError(
            f"{name} {seq!r} mixes upper and lower case: write it in one case ({seq.lower()!r}; both "
            "cases mean intrinsic rotations here, where scipy's lower case means extrinsic ones)."
        )
    return tuple(_AXIS[c] for c in seq.lower())


def is_proper_sequence(seq: str) -> bool:
    """Whether an Euler sequence is proper (first axis = third axis) rather than Tait-Bryan.

    **Arguments:**

    - `seq`: one of the twelve sequences of ``SEQUENCES``, in lower or upper case. Any other value raises
      ``ValueError``.

    **Returns:** True for proper sequences (``"zxz"``...), False for Tait-Bryan (``"xyz"``...).
    """
    i, _, k = _parse_seq(seq)
    return i == k


def _axis_matrix(axis: int, angle):
    """Active rotation matrix about coordinate axis ``axis`` by ``angle``, shape (..., 3, 3)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    j, k = (axis + 1) % 3, (axis + 2) % 3
    m = [[None] * 3 for _ in range(3)]
    m[axis][axis] = one
    m[axis][j] = m[axis][k] = m[j][axis] = m[k][axis] = zero
    m[j][j], m[j][k] = c, -s
    m[k][j], m[k][k] = s, c
    return jnp.stack([jnp.stack(row, axis=-1) for row in m], axis=-2)


def _axis_quat(axis: int, angle):
    half = 0.5 * angle
    zero = jnp.zeros_like(half)
    vec = [zero, zero, zero]
    vec[axis] = jnp.sin(half)
    return jnp.stack([jnp.cos(half), *vec], axis=-1)


def _unit(axis: int, like):
    return jnp.zeros(like.shape + (3,), like.dtype).at[..., axis].set(1.0)


def _rotate_back(axis: int, angle, v):
    """``R_axis(angle).T @ v`` for a batch of vectors ``v``."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    j, k = (axis + 1) % 3, (axis + 2) % 3
    out = [None] * 3
    out[axis] = v[..., axis]
    out[j] = c * v[..., j] + s * v[..., k]
    out[k] = -s * v[..., j] + c * v[..., k]
    return jnp.stack(out, axis=-1)


def _split_angles(angles):
    (angles,) = common_float(angles, names=["angles"])
    check_last_axis(angles, 3, "angles")
    return angles, angles[..., 0], angles[..., 1], angles[..., 2]


def _matrix_from_euler(angles: Angles, seq: str = "zxz") -> MatrixOut:
    """Rotation matrix ``R = R_a(phi) R_b(theta) R_c(psi)`` for ``seq = "abc"`` (body -> space)."""
    i, j, k = _parse_seq(seq)
    _, phi, theta, psi = _split_angles(angles)
    return _axis_matrix(i, phi) @ _axis_matrix(j, theta) @ _axis_matrix(k, psi)


def _quat_from_euler(angles: Angles, seq: str = "zxz") -> Quaternion:
    """Unit quaternion ``(w, x, y, z)`` of the same rotation as :func:`matrix_from_euler`."""
    i, j, k = _parse_seq(seq)
    _, phi, theta, psi = _split_angles(angles)
    return _quat_multiply(_quat_multiply(_axis_quat(i, phi), _axis_quat(j, theta)), _axis_quat(k, psi))


def _wrap(angle):
    return jnp.where(
        angle < -jnp.pi, angle + 2 * jnp.pi, jnp.where(angle > jnp.pi, angle - 2 * jnp.pi, angle)
    )


def _euler_from_quat(q: Quaternion, seq: str = "zxz") -> Angles:
    """Euler angles of a quaternion (Bernardes & Viollet 2022, as in scipy).

    Ranges: ``phi, psi`` in ``[-pi, pi]``; ``theta`` in ``[0, pi]`` for proper sequences and
    ``[-pi/2, pi/2]`` for Tait-Bryan. At gimbal lock (within roundoff of it) ``psi = 0`` and ``phi``
    carries the whole rotation about the aligned axis; values and gradients are finite there.
    """
    i, j, k = _parse_seq(seq)
    (q,) = common_float(q, names=["q"])
    check_last_axis(q, 4, "q")
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    # Intrinsic angles of (i, j, k) are the reversed extrinsic angles of (k, j, i).
    i, k = k, i
    symmetric = i == k
    if symmetric:
        k = 3 - i - j
    sign = (i - j) * (j - k) * (k - i) // 2
    w, v = q[..., 0], q[..., 1:]
    if symmetric:
        a, b, c, d = w, v[..., i], v[..., j], v[..., k] * sign
    else:
        a = w - v[..., j]
        b = v[..., i] + v[..., k] * sign
        c = v[..., j] + w
        d = v[..., k] * sign - v[..., i]
    norm_cd, norm_ab = safe_hypot(c, d), safe_hypot(a, b)
    middle = 2.0 * jnp.arctan2(norm_cd, norm_ab)
    # (a, b, c, d) has norm 1 (symmetric) or sqrt(2) (Tait-Bryan); a lock is a vanishing pair.
    tol = 4.0 * eps(q.dtype)
    lock_zero = norm_cd <= tol
    lock_pi = norm_ab <= tol
    half_sum = safe_atan2(b, a)
    half_diff = safe_atan2(d, c)
    first = jnp.where(lock_zero, 2.0 * half_sum, jnp.where(lock_pi, 2.0 * half_diff, half_sum + half_diff))
    third = jnp.where(lock_zero | lock_pi, jnp.zeros_like(middle), half_sum - half_diff)
    if not symmetric:
        first = first * sign
        middle = middle - 0.5 * jnp.pi
    angles = jnp.stack([_wrap(first), middle, _wrap(third)], axis=-1)
    # The NaN-safe norms read NaN as 0, a gimbal lock: a NaN sample (a failed body's) would give
    # finite angles (theta = psi = 0).
    return jnp.where(jnp.isnan(a + b + c + d)[..., None], jnp.nan, angles)


def _euler_from_matrix(R: Matrix, seq: str = "zxz") -> Angles:
    """Euler angles of a rotation matrix; same ranges and gimbal-lock split as :func:`euler_from_quat`."""
    (R,) = common_float(R, names=["R"])
    check_last_two_axes(R, "R")
    return _euler_from_quat(_quat_from_matrix(R), seq)


def _rate_axes(angles, seq):
    """Body-frame unit vectors ``u1, u2, u3`` with ``omega_body = phi' u1 + theta' u2 + psi' u3``."""
    i, j, k = _parse_seq(seq)
    angles, _, theta, psi = _split_angles(angles)
    u3 = _unit(k, psi)
    u2 = _rotate_back(k, psi, _unit(j, psi))
    u1 = _rotate_back(k, psi, _rotate_back(j, theta, _unit(i, psi)))
    return angles, u1, u2, u3


def _body_angular_velocity(angles: Angles, rates: Vector, seq: str = "zxz") -> VectorOut:
    """Body-frame angular velocity from Euler angles and their time derivatives (rad/s).

    For ``"zxz"``: ``omega = (phi' sin(theta) sin(psi) + theta' cos(psi),
    phi' sin(theta) cos(psi) - theta' sin(psi), phi' cos(theta) + psi')``. Euler-angle rates are
    not the components of omega.
    """
    angles, rates = common_float(angles, rates, names=["angles", "rates"])
    check_last_axis(rates, 3, "rates")
    _, u1, u2, u3 = _rate_axes(angles, seq)
    return rates[..., 0:1] * u1 + rates[..., 1:2] * u2 + rates[..., 2:3] * u3


def _space_angular_velocity(angles: Angles, rates: Vector, seq: str = "zxz") -> VectorOut:
    """Space-frame angular velocity ``R @ body_angular_velocity(angles, rates, seq)``."""
    omega_body = _body_angular_velocity(angles, rates, seq)
    R = _matrix_from_euler(jnp.asarray(angles, omega_body.dtype), seq)
    return jnp.einsum("...ij,...j->...i", R, omega_body)


def _euler_rates(angles: Angles, omega: Vector, seq: str = "zxz", *, throw: bool = True) -> VectorOut:
    """:func:`euler_rates` without the NaN/inf input checks (integrator right-hand sides); the
    gimbal-lock handling (``throw``) is the same."""
    return _raise_if_unreachable(*_rates_and_lock(angles, omega, seq), seq, throw)


def _rates_and_lock(angles, omega, seq):
    """The Euler-angle rates (NaN where the angles cannot follow omega) and where that is."""
    angles, omega = common_float(angles, omega, names=["angles", "omega"])
    check_last_axis(omega, 3, "omega")
    _, u1, u2, u3 = _rate_axes(angles, seq)
    u1, u2, u3 = jnp.broadcast_arrays(u1, u2, u3, omega)[:3]
    n23, n31, n12 = jnp.cross(u2, u3), jnp.cross(u3, u1), jnp.cross(u1, u2)
    det = jnp.sum(u1 * n23, axis=-1)
    tol = 16.0 * eps(omega.dtype)
    locked = jnp.abs(det) <= tol
    safe_det = jnp.where(locked, jnp.ones_like(det), det)
    regular = jnp.stack([jnp.sum(omega * n, axis=-1) / safe_det for n in (n23, n31, n12)], axis=-1)
    # At the lock u1 = ±u3 and omega must lie in span(u2, u3), whose normal is u2 x u3.
    along_u3 = jnp.sum(omega * u3, axis=-1) * jnp.sign(jnp.sum(u1 * u3, axis=-1))
    split = jnp.stack([along_u3, jnp.sum(omega * u2, axis=-1), jnp.zeros_like(det)], axis=-1)
    scale = jnp.max(jnp.abs(omega), axis=-1)
    unreachable = locked & (jnp.abs(jnp.sum(omega * n23, axis=-1)) > 64.0 * eps(omega.dtype) * scale)
    rates = jnp.where(locked[..., None], split, regular)
    return jnp.where(unreachable[..., None], jnp.nan, rates), unreachable


def _raise_if_unreachable(rates, unreachable, seq, throw):
    if throw:
        rates = error_if(
            rates,
            unreachable,
            f"euler_rates: the Euler angles are at gimbal lock for seq={seq!r} "
            f"({'sin' if is_proper_sequence(seq) else 'cos'}(theta) = 0, first and third axes "
            "aligned) and omega has a component the angles cannot follow: the rates are unbounded. "
            "Use quaternions for this orientation, or pass throw=False to get NaN rates instead.",
        )
    return rates


# --- the public, checked functions -------------------------------------------------------------------


# The computations after the checks, each one compiled program, for the eager calls that
# `compiled_when_eager` passes through as they are (lists, tuples): op by op, each of their operations
# was a program of its own (euler_from_matrix: 54 programs, 1.6 s in a new process; eager_calls.py).
# Called with arrays, the whole checked function is one program and these are inlined into it.
_compiled_matrix_from_euler = jax.jit(_matrix_from_euler, static_argnames="seq")
_compiled_quat_from_euler = jax.jit(_quat_from_euler, static_argnames="seq")
_compiled_euler_from_quat = jax.jit(_euler_from_quat, static_argnames="seq")
_compiled_euler_from_matrix = jax.jit(_euler_from_matrix, static_argnames="seq")
_compiled_body_angular_velocity = jax.jit(_body_angular_velocity, static_argnames="seq")
_compiled_space_angular_velocity = jax.jit(_space_angular_velocity, static_argnames="seq")
_compiled_rates_and_lock = jax.jit(_rates_and_lock, static_argnames="seq")


def _checked_angles(angles, where):
    (angles,) = common_float(angles, names=["angles"])
    check_last_axis(angles, 3, "angles")
    return check_finite(angles, "angles", where)


@compiled_when_eager(static_argnames=("seq",), case_insensitive={"seq": SEQUENCES})
def matrix_from_euler(angles: Angles, seq: str = "zxz") -> MatrixOut:
    """Rotation matrix ``R = R_a(phi) R_b(theta) R_c(psi)`` of Euler angles, for ``seq = "abc"``.

    Equals scipy's ``Rotation.from_euler(seq.upper(), angles).as_matrix()``.

    **Arguments:**

    - `angles`: Euler angles ``(phi, theta, psi)`` (rad), shape ``(..., 3)``.
    - `seq`: the intrinsic sequence, one of the twelve of ``SEQUENCES`` (default ``"zxz"``, 3-1-3),
      in lower or upper case (not a mix); any other value raises ``ValueError``.

    **Returns:** the rotation matrix ``(..., 3, 3)``, mapping body-frame to space-frame components.
    NaN or inf raises at run time.
    """
    _parse_seq(seq)
    return _compiled_matrix_from_euler(_checked_angles(angles, "matrix_from_euler"), seq=seq)


@compiled_when_eager(static_argnames=("seq",), case_insensitive={"seq": SEQUENCES})
def quat_from_euler(angles: Angles, seq: str = "zxz") -> Quaternion:
    """Unit quaternion of Euler angles: the same rotation as :func:`matrix_from_euler`.

    **Arguments:**

    - `angles`: Euler angles ``(phi, theta, psi)`` (rad), shape ``(..., 3)``.
    - `seq`: the intrinsic sequence, one of the twelve of ``SEQUENCES`` (default ``"zxz"``, 3-1-3),
      in lower or upper case (not a mix); any other value raises ``ValueError``.

    **Returns:** the unit quaternion ``(w, x, y, z)``, shape ``(..., 4)``, mapping body-frame to
    space-frame components. NaN or inf raises at run time.
    """
    _parse_seq(seq)
    return _compiled_quat_from_euler(_checked_angles(angles, "quat_from_euler"), seq=seq)


@compiled_when_eager(static_argnames=("seq",), case_insensitive={"seq": SEQUENCES})
def euler_from_quat(q: Quaternion, seq: str = "zxz") -> Angles:
    """Euler angles of a quaternion (Bernardes & Viollet 2022, as in scipy).

    At gimbal lock (within roundoff of it) ``psi = 0`` and ``phi`` carries the whole rotation about
    the aligned axis; values and gradients are finite there.

    **Arguments:**

    - `q`: orientation, scalar first ``(w, x, y, z)``, shape ``(..., 4)``. It is normalised first
      (as scipy's ``from_quat``), and ``q`` and ``-q`` give the same angles. A zero `q`, or NaN or
      inf, raises at run time.
    - `seq`: the intrinsic sequence, one of the twelve of ``SEQUENCES`` (default ``"zxz"``, 3-1-3),
      in lower or upper case (not a mix); any other value raises ``ValueError``.

    **Returns:** the angles ``(phi, theta, psi)`` (rad), shape ``(..., 3)``: ``phi, psi`` in
    ``[-pi, pi]``; ``theta`` in ``[0, pi]`` for proper sequences and ``[-pi/2, pi/2]`` for
    Tait-Bryan.
    """
    _parse_seq(seq)
    (q,) = common_float(q, names=["q"])
    check_last_axis(q, 4, "q")
    return _compiled_euler_from_quat(check_rotation_quaternion(q, "q", "euler_from_quat"), seq=seq)


@compiled_when_eager(static_argnames=("seq",), case_insensitive={"seq": SEQUENCES})
def euler_from_matrix(R: Matrix, seq: str = "zxz") -> Angles:
    """Euler angles of a rotation matrix.

    **Arguments:**

    - `R`: rotation matrix ``(..., 3, 3)``, mapping body-frame to space-frame components. NaN or
      inf, ``max|R R^T - 1|`` beyond ``1e-6`` (float64) / ``1e-4`` (float32), or ``det R < 0`` raises
      at run time; tiny non-orthogonality is accepted.
    - `seq`: the intrinsic sequence, one of the twelve of ``SEQUENCES`` (default ``"zxz"``, 3-1-3),
      in lower or upper case (not a mix); any other value raises ``ValueError``.

    **Returns:** the angles ``(phi, theta, psi)`` (rad), shape ``(..., 3)``, with the same ranges
    and gimbal-lock split as :func:`euler_from_quat`.
    """
    _parse_seq(seq)
    (R,) = common_float(R, names=["R"])
    check_last_two_axes(R, "R")
    return _compiled_euler_from_matrix(check_rotation_matrix(R, "R", "euler_from_matrix"), seq=seq)


@compiled_when_eager(static_argnames=("seq",), case_insensitive={"seq": SEQUENCES})
def body_angular_velocity(angles: Angles, rates: Vector, seq: str = "zxz") -> VectorOut:
    """Body-frame angular velocity from Euler angles and their time derivatives.

    For ``"zxz"``: ``omega = (phi' sin(theta) sin(psi) + theta' cos(psi),
    phi' sin(theta) cos(psi) - theta' sin(psi), phi' cos(theta) + psi')``. Euler-angle rates are
    not the components of omega. The map has no singularity (it is smooth at gimbal lock too).

    **Arguments:**

    - `angles`: Euler angles ``(phi, theta, psi)`` (rad), shape ``(..., 3)``.
    - `rates`: their time derivatives ``(phi', theta', psi')`` (rad/s), shape ``(..., 3)``,
      broadcast against `angles`.
    - `seq`: the intrinsic sequence, one of the twelve of ``SEQUENCES`` (default ``"zxz"``, 3-1-3),
      in lower or upper case (not a mix); any other value raises ``ValueError``.

    **Returns:** ``omega`` in body-frame components (rad/s), shape ``(..., 3)``. NaN or inf raises at
    run time.
    """
    _parse_seq(seq)
    angles, rates = common_float(angles, rates, names=["angles", "rates"])
    check_last_axis(angles, 3, "angles")
    check_last_axis(rates, 3, "rates")
    check_batch_shapes("body_angular_velocity", ("angles", angles, 1), ("rates", rates, 1))
    where = "body_angular_velocity"
    return _compiled_body_angular_velocity(
        check_finite(angles, "angles", where), check_finite(rates, "rates", where), seq=seq
    )


@compiled_when_eager(static_argnames=("seq",), case_insensitive={"seq": SEQUENCES})
def space_angular_velocity(angles: Angles, rates: Vector, seq: str = "zxz") -> VectorOut:
    """Space-frame angular velocity from Euler angles and their time derivatives.

    This is ``R @ body_angular_velocity(angles, rates, seq)`` with ``R = matrix_from_euler(angles,
    seq)``.

    **Arguments:**

    - `angles`: Euler angles ``(phi, theta, psi)`` (rad), shape ``(..., 3)``.
    - `rates`: their time derivatives ``(phi', theta', psi')`` (rad/s), shape ``(..., 3)``,
      broadcast against `angles`.
    - `seq`: the intrinsic sequence, one of the twelve of ``SEQUENCES`` (default ``"zxz"``, 3-1-3),
      in lower or upper case (not a mix); any other value raises ``ValueError``.

    **Returns:** ``omega`` in space-frame components (rad/s), shape ``(..., 3)``. NaN or inf raises
    at run time.
    """
    _parse_seq(seq)
    angles, rates = common_float(angles, rates, names=["angles", "rates"])
    check_last_axis(angles, 3, "angles")
    check_last_axis(rates, 3, "rates")
    check_batch_shapes("space_angular_velocity", ("angles", angles, 1), ("rates", rates, 1))
    where = "space_angular_velocity"
    return _compiled_space_angular_velocity(
        check_finite(angles, "angles", where), check_finite(rates, "rates", where), seq=seq
    )


@compiled_when_eager(static_argnames=("seq", "throw"), case_insensitive={"seq": SEQUENCES})
def euler_rates(angles: Angles, omega: Vector, seq: str = "zxz", *, throw: bool = True) -> VectorOut:
    """Euler-angle rates ``(phi', theta', psi')`` from the body-frame angular velocity.

    The inverse of :func:`body_angular_velocity`. Its determinant is ``±sin(theta)`` (proper) or
    ``±cos(theta)`` (Tait-Bryan): near gimbal lock the rates grow like ``1/sin(theta)``, which is
    the truth, not an artefact. Within roundoff of the lock the rates are unbounded unless ``omega``
    lies in the plane the angles can follow; then the split ``psi' = 0`` is returned (matching the
    angle split of :func:`euler_from_quat`).

    **Arguments:**

    - `angles`: Euler angles ``(phi, theta, psi)`` (rad), shape ``(..., 3)``.
    - `omega`: angular velocity in body-frame components (rad/s), shape ``(..., 3)``, broadcast
      against `angles`.
    - `seq`: the intrinsic sequence, one of the twelve of ``SEQUENCES`` (default ``"zxz"``, 3-1-3),
      in lower or upper case (not a mix); any other value raises ``ValueError``.
    - `throw`: at gimbal lock with an ``omega`` the angles cannot follow, True fails with an error
      naming gimbal lock; False returns NaN rates instead (for ``vmap`` users). NaN or inf in the
      input raises with ``throw=True`` and propagates as NaN with ``throw=False``.

    **Returns:** the rates ``(phi', theta', psi')`` (rad/s), shape ``(..., 3)``.
    """
    _parse_seq(seq)
    throw = check_flag(throw, "throw", "euler_rates")
    angles, omega = common_float(angles, omega, names=["angles", "omega"])
    check_last_axis(angles, 3, "angles")
    check_last_axis(omega, 3, "omega")
    check_batch_shapes("euler_rates", ("angles", angles, 1), ("omega", omega, 1))
    if throw:
        angles = check_finite(angles, "angles", "euler_rates")
        omega = check_finite(omega, "omega", "euler_rates")
    rates = _raise_if_unreachable(*_compiled_rates_and_lock(angles, omega, seq=seq), seq, throw)
    if throw:
        return rates
    # The rates do not depend on phi, and an infinite omega gives infinite rates: without this a
    # non-finite input could come back as finite or infinite rates rather than NaN.
    finite = jnp.isfinite(angles).all(axis=-1, keepdims=True) & jnp.isfinite(omega).all(
        axis=-1, keepdims=True
    )
    return jnp.where(finite, rates, jnp.nan)
