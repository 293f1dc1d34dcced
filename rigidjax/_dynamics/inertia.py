"""Inertia: principal axes, physical validity, the parallel-axis theorem, common shapes, composites.

Units are SI: masses in kg, lengths in m, moments of inertia in kg m^2. ``inertia`` is principal
moments ``(..., 3)`` (the body axes are principal axes) or a full symmetric tensor ``(..., 3, 3)`` in
body axes; a trailing ``(3, 3)`` is always read as a tensor. Every function broadcasts over leading
batch axes, except :func:`composite_inertia`, whose leading axis enumerates the parts.

Differentiation at degenerate moments (a symmetric top has ``I1 = I2``, a sphere or a cube
``I1 = I2 = I3``) is safe: :func:`principal_axes` uses an eigendecomposition with its own JVP, which
drops the ``1 / (I_j - I_i)`` terms of the eigenvector derivative where two moments coincide to
within roundoff, so gradients stay finite there.

Bad input: shapes other than documented, and complex or boolean dtypes, raise ``ValueError`` /
``TypeError`` while tracing (integer arrays are promoted to float). At run time (``eqx.error_if``,
also under ``jit`` and ``vmap``): NaN or inf raises in every function here except
:func:`is_physical_inertia`, a predicate that answers False for it; negative masses or lengths
raise in the shape helpers, :func:`parallel_axis` and :func:`composite_inertia` (whose total mass
must be positive, and whose ``rotations`` must be rotation matrices); :func:`check_inertia` raises
for a non-physical inertia. The shape helpers accept zero sizes (a thin rod has ``Iz = 0``): such
moments are valid parts of a composite, and :func:`check_inertia` rejects them for a whole body.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._checks import (
    as_float_array,
    check_finite,
    check_last_axis,
    check_last_two_axes,
    check_rotation_matrix,
    common_float,
    is_full_tensor,
)
from .._numerics import eps
from .._types import Inertia, Matrix, MatrixOut, Scalar, ScalarOut, Vector, VectorOut

# Two moments closer than this many eps (relative to the largest |moment|) count as degenerate in
# the eigenvector derivative. Roundoff of a 3x3 ``eigh`` is a few eps, so 1e3 eps leaves a wide margin
# while still resolving physically distinct moments (1e-13 relative in float64, 1e-4 in float32).
_DEGENERACY_EPS = 1e3
# Relative tolerance (times eps times the largest |entry|) for a tensor to count as symmetric.
_SYMMETRY_EPS = 1e3
# Roundoff allowance (times eps times the trace) for the triangle inequality, which is an equality
# for a flat plate, and for the positivity of eigenvalues of a tensor.
_TRIANGLE_EPS = 1e2


def _swap(a):
    return jnp.swapaxes(a, -1, -2)


def _eigh3_impl(a):
    w, v = jnp.linalg.eigh(a, symmetrize_input=False)
    # Right-handed axes: flip the last column where the basis came out left-handed.
    sign = jnp.where(jnp.linalg.det(v) < 0, -1.0, 1.0).astype(v.dtype)
    v = jnp.concatenate([v[..., :2], v[..., 2:] * sign[..., None, None]], axis=-1)
    return w, v


_eigh3 = jax.custom_jvp(_eigh3_impl)
"""Ascending eigenvalues and right-handed eigenvectors (columns) of symmetric ``(..., 3, 3)`` input.

The JVP is the textbook one (``dw_i = v_i^T dA v_i``, ``dV = V (F o E)`` with ``F = V^T dA V`` and
``E_ij = 1 / (w_j - w_i)``), except that ``E_ij`` is set to 0 where ``|w_j - w_i|`` is below
``_DEGENERACY_EPS * eps * max|w|``: inside a degenerate eigenspace the eigenvectors are arbitrary and
the derivative of any basis-invariant (spectral) function does not depend on that choice.
"""


@_eigh3.defjvp
def _eigh3_jvp(primals, tangents):
    (a,) = primals
    (da,) = tangents
    w, v = _eigh3(a)  # the custom rule again, so higher derivatives are also safe
    da = 0.5 * (da + _swap(da))
    f = _swap(v) @ da @ v
    dw = jnp.diagonal(f, axis1=-2, axis2=-1)
    gap = w[..., None, :] - w[..., :, None]  # gap[i, j] = w_j - w_i
    scale = jnp.max(jnp.abs(w), axis=-1)
    tol = _DEGENERACY_EPS * eps(w.dtype) * scale
    keep = jnp.abs(gap) > tol[..., None, None]  # the diagonal (gap 0) is never kept
    inv_gap = jnp.where(keep, 1.0 / jnp.where(keep, gap, jnp.ones_like(gap)), jnp.zeros_like(gap))
    dv = v @ (f * inv_gap)
    return (w, v), (dw, dv)


def principal_axes(tensor: Matrix) -> tuple[VectorOut, MatrixOut]:
    """Principal moments and principal axes of an inertia tensor.

    **Arguments:**

    - `tensor`: symmetric inertia tensor ``(..., 3, 3)`` in body axes (kg m^2). It is symmetrised as
      ``(A + A^T) / 2`` first; use :func:`check_inertia` to reject a non-symmetric one. NaN or inf
      raises at run time.

    **Returns:** ``(moments, axes)``:

    - `moments`: principal moments ``(..., 3)`` in ascending order (kg m^2).
    - `axes`: ``(..., 3, 3)`` orthonormal matrix whose COLUMNS are the principal axes (body-frame
      components), right-handed (``det = +1``), so ``tensor = axes @ diag(moments) @ axes.T``.
      ``axes`` maps principal-frame components to body-frame components. Each axis is defined up to
      sign (only ``det = +1`` is enforced), and for coinciding moments any orthonormal basis of the
      degenerate plane (or space) is returned.

    Gradients are finite everywhere, including at ``I1 = I2`` and ``I1 = I2 = I3``: the eigenvector
    derivative drops the ``1 / (I_j - I_i)`` terms of moments that coincide to within roundoff. The
    gradient of the moments, and of any function of the output that does not depend on the choice of
    basis within a degenerate plane (a spectral function such as ``sum(moments)`` or
    ``det(tensor)``), is then correct; derivatives of the axes themselves are not defined there.
    """
    (tensor,) = common_float(tensor, names=["tensor"])
    check_last_two_axes(tensor, "tensor")
    tensor = check_finite(tensor, "tensor", "principal_axes")
    return _eigh3(0.5 * (tensor + _swap(tensor)))


def _check_inertia_shape(inertia, name: str) -> bool:
    return is_full_tensor(inertia, name)


# Failure codes, in increasing order of how fundamental the problem is: across a batch the largest
# code present is reported.
_OK, _TRIANGLE, _NOT_POSITIVE, _NOT_SYMMETRIC, _NOT_FINITE = 0, 1, 2, 3, 4


def _inertia_failure(inertia):
    """Per-body failure code (0 = physical) of principal moments or a tensor, shape ``(...)``."""
    inertia = as_float_array(inertia)
    tol_eps = eps(inertia.dtype)
    if _check_inertia_shape(inertia, "inertia"):
        finite = jnp.all(jnp.isfinite(inertia), axis=(-2, -1))
        safe = jnp.where(finite[..., None, None], inertia, jnp.eye(3, dtype=inertia.dtype))
        scale = jnp.max(jnp.abs(safe), axis=(-2, -1))
        asym = jnp.max(jnp.abs(safe - _swap(safe)), axis=(-2, -1))
        symmetric = asym <= _SYMMETRY_EPS * tol_eps * scale
        moments, _ = _eigh3(0.5 * (safe + _swap(safe)))
        trace = jnp.trace(safe, axis1=-2, axis2=-1)
        # Eigenvalues carry roundoff of order eps * trace: one within it of zero counts as zero.
        positive = jnp.all(moments > _TRIANGLE_EPS * tol_eps * jnp.abs(trace)[..., None], axis=-1)
    else:
        finite = jnp.all(jnp.isfinite(inertia), axis=-1)
        moments = jnp.where(finite[..., None], inertia, jnp.ones_like(inertia))
        symmetric = jnp.ones_like(finite)
        positive = jnp.all(moments > 0, axis=-1)
        trace = jnp.sum(moments, axis=-1)
    tol = _TRIANGLE_EPS * tol_eps * jnp.abs(trace)
    # I1 + I2 - I3 and its cyclic permutations: trace - 2 I_k >= 0.
    triangle = jnp.all(trace[..., None] - 2.0 * moments >= -tol[..., None], axis=-1)
    code = jnp.where(triangle, _OK, _TRIANGLE)
    code = jnp.where(positive, code, _NOT_POSITIVE)
    code = jnp.where(symmetric, code, _NOT_SYMMETRIC)
    return jnp.where(finite, code, _NOT_FINITE)


def is_physical_inertia(inertia: Inertia) -> Bool[Array, "..."]:
    """Whether ``inertia`` can be the inertia of a rigid body, per body: shape ``(...)``.

    ``inertia`` is principal moments ``(..., 3)`` or a tensor ``(..., 3, 3)`` (kg m^2); a trailing
    ``(3, 3)`` is read as a tensor. Physical means: all entries finite; for a tensor, symmetric to a
    relative tolerance of ``1e3 eps`` (of its largest entry); all principal moments positive (for a
    tensor, larger than the eigenvalue roundoff ``1e2 eps trace``); and the triangle inequality
    ``I1 + I2 >= I3`` and its cyclic permutations, with the flat-plate equality ``I1 + I2 = I3``
    allowed up to ``1e2 eps trace``. A tensor is checked through its eigenvalues.

    Raises ``ValueError`` (while tracing) for shapes other than ``(..., 3)`` and ``(..., 3, 3)``.
    See :func:`check_inertia` for the raising version, which names the problem.
    """
    return _inertia_failure(inertia) == _OK


def check_inertia(inertia: Inertia, *, name: str = "inertia") -> Inertia:
    """Returns ``inertia`` (as a JAX float array) with a run-time check that it is physical.

    The checks are those of :func:`is_physical_inertia`. The returned array is wrapped in
    ``equinox.error_if``, so this works inside ``jax.jit``; the check only runs if the returned value
    is used. On failure the error message names ``name`` and the problem (non-finite entries, a
    non-symmetric tensor, non-positive moments, or a violated triangle inequality); across a batch the
    most fundamental problem present is reported. Raises ``ValueError`` while tracing for shapes other
    than ``(..., 3)`` and ``(..., 3, 3)``.
    """
    inertia = as_float_array(inertia, name)
    tensor = _check_inertia_shape(inertia, name)
    code = _inertia_failure(inertia)
    what = "tensor" if tensor else "principal moments"
    msgs = [
        "",
        f"{name} violates the triangle inequality I1 + I2 >= I3 (and cyclic) of its principal "
        "moments: no distribution of mass has these moments. Each moment must be at most the sum of "
        "the other two (equality is a flat plate).",
        f"{name} has a non-positive principal moment: every moment of inertia of a rigid body must "
        "be > 0 kg m^2. (A thin rod has a zero moment about its axis: it is only valid as a part of "
        "a composite body.)",
        f"{name} is a (..., 3, 3) tensor that is not symmetric: an inertia tensor must equal its "
        "transpose. If you meant a batch of three bodies' principal moments, note that a trailing "
        "(3, 3) shape is always read as a tensor: pass them as shape (3, 1, 3), e.g. "
        "inertia[:, None, :].",
        f"{name} ({what}) contains NaN or infinite values.",
    ]
    return eqx.branched_error_if(inertia, code != _OK, jnp.max(code), msgs)


def _as_tensor(inertia):
    """A ``(..., 3, 3)`` tensor from principal moments or a tensor (already float arrays)."""
    if is_full_tensor(inertia):
        return inertia
    return inertia[..., None, :] * jnp.eye(3, dtype=inertia.dtype)


def _point_mass_tensor(mass, displacement):
    """``m (|d|^2 1 - d d^T)``: the inertia of a point mass ``m`` at ``d``, shape ``(..., 3, 3)``."""
    d2 = jnp.sum(displacement * displacement, axis=-1)
    eye = jnp.eye(3, dtype=displacement.dtype)
    outer = displacement[..., :, None] * displacement[..., None, :]
    return mass[..., None, None] * (d2[..., None, None] * eye - outer)


def parallel_axis(inertia_com: Inertia, mass: Scalar, displacement: Vector) -> MatrixOut:
    """Parallel-axis theorem: the inertia tensor about a point away from the centre of mass.

    **Arguments:**

    - `inertia_com`: inertia about the centre of mass, principal moments ``(..., 3)`` (body axes are
      principal) or a tensor ``(..., 3, 3)`` in body axes (kg m^2).
    - `mass`: the body's mass ``(...)`` (kg).
    - `displacement`: ``(..., 3)`` body-frame vector from the centre of mass to the new reference
      point (m); its sign does not matter.

    **Returns:** the tensor ``I + m (|d|^2 1 - d d^T)`` ``(..., 3, 3)`` about the new point, in the
    same (body) axes. E.g. the inertia about the pivot that :class:`HeavyTop` expects is
    ``parallel_axis(inertia_com, mass, com)``.
    """
    inertia_com, mass, displacement = common_float(
        inertia_com, mass, displacement, names=["inertia_com", "mass", "displacement"]
    )
    _check_inertia_shape(inertia_com, "inertia_com")
    check_last_axis(displacement, 3, "displacement")
    where = "parallel_axis"
    inertia_com = check_finite(inertia_com, "inertia_com", where)
    mass = _check_nonnegative(mass, "mass", where)
    displacement = check_finite(displacement, "displacement", where)
    return _as_tensor(inertia_com) + _point_mass_tensor(mass, displacement)


# --- common shapes -------------------------------------------------------------------------------


def _check_nonnegative(x, name: str, where: str):
    """``x`` wrapped in run-time checks: finite and ``>= 0`` (a mass in kg or a length in m)."""
    x = check_finite(x, name, where)
    return eqx.error_if(x, jnp.any(x < 0), f"{where}: {name} must be >= 0, got a negative value.")


def _nonnegative(where, **values):
    """Float arrays of one dtype, each checked by :func:`_check_nonnegative`, in argument order."""
    arrays = common_float(*values.values(), names=list(values))
    return [_check_nonnegative(a, n, where) for a, n in zip(arrays, values, strict=True)]


def _moments(mass, *factors):
    """Stacks ``mass * factor`` along a new last axis."""
    return mass[..., None] * jnp.stack(jnp.broadcast_arrays(*factors), axis=-1)


def solid_box(mass: Scalar, size: Vector) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a uniform solid box (cuboid) about its centre.

    `mass` in kg; `size` ``(..., 3)`` are the FULL edge lengths ``(a, b, c)`` along the box's x, y, z
    axes (m). ``Ix = m (b^2 + c^2) / 12`` and cyclic.
    """
    mass, size = common_float(mass, size, names=["mass", "size"])
    check_last_axis(size, 3, "size")
    mass, size = _nonnegative("solid_box", mass=mass, size=size)
    s2 = size * size
    a2, b2, c2 = s2[..., 0], s2[..., 1], s2[..., 2]
    return _moments(mass, (b2 + c2) / 12.0, (c2 + a2) / 12.0, (a2 + b2) / 12.0)


def solid_cylinder(mass: Scalar, radius: Scalar, height: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a uniform solid cylinder about its centre.

    The symmetry axis is z; `radius` and `height` (full length along z) in m, `mass` in kg.
    ``Ix = Iy = m (3 r^2 + h^2) / 12``, ``Iz = m r^2 / 2``.
    """
    mass, radius, height = _nonnegative("solid_cylinder", mass=mass, radius=radius, height=height)
    r2, h2 = radius * radius, height * height
    transverse = (3.0 * r2 + h2) / 12.0
    return _moments(mass, transverse, transverse, r2 / 2.0)


def hollow_cylinder(mass: Scalar, radius: Scalar, height: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a thin-walled open tube about its centre.

    All the mass is on the curved wall at `radius` (no end caps); the axis is z and `height` is the
    full length along it (m). ``Ix = Iy = m (6 r^2 + h^2) / 12``, ``Iz = m r^2``.
    """
    mass, radius, height = _nonnegative("hollow_cylinder", mass=mass, radius=radius, height=height)
    r2, h2 = radius * radius, height * height
    transverse = (6.0 * r2 + h2) / 12.0
    return _moments(mass, transverse, transverse, r2)


def solid_sphere(mass: Scalar, radius: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a uniform solid ball: ``2 m r^2 / 5`` each."""
    mass, radius = _nonnegative("solid_sphere", mass=mass, radius=radius)
    i = 0.4 * radius * radius
    return _moments(mass, i, i, i)


def hollow_sphere(mass: Scalar, radius: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a thin spherical shell: ``2 m r^2 / 3`` each."""
    mass, radius = _nonnegative("hollow_sphere", mass=mass, radius=radius)
    i = (2.0 / 3.0) * radius * radius
    return _moments(mass, i, i, i)


def solid_ellipsoid(mass: Scalar, semi_axes: Vector) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a uniform solid ellipsoid about its centre.

    `semi_axes` ``(..., 3)`` are the semi-axes ``(a, b, c)`` along x, y, z (m).
    ``Ix = m (b^2 + c^2) / 5`` and cyclic.
    """
    mass, semi_axes = common_float(mass, semi_axes, names=["mass", "semi_axes"])
    check_last_axis(semi_axes, 3, "semi_axes")
    mass, semi_axes = _nonnegative("solid_ellipsoid", mass=mass, semi_axes=semi_axes)
    s2 = semi_axes * semi_axes
    a2, b2, c2 = s2[..., 0], s2[..., 1], s2[..., 2]
    return _moments(mass, (b2 + c2) / 5.0, (c2 + a2) / 5.0, (a2 + b2) / 5.0)


def thin_rod(mass: Scalar, length: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a thin uniform rod along z, about its centre.

    ``Ix = Iy = m L^2 / 12`` and ``Iz = 0`` exactly. A body needs positive moments, so a thin rod is
    only valid as a part of a composite body (:func:`composite_inertia`), not on its own; use
    :func:`solid_cylinder` for a rod of finite radius.
    """
    mass, length = _nonnegative("thin_rod", mass=mass, length=length)
    transverse = length * length / 12.0
    return _moments(mass, transverse, transverse, jnp.zeros_like(transverse))


def thin_disc(mass: Scalar, radius: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a thin uniform disc in the xy-plane (axis z).

    ``Ix = Iy = m r^2 / 4``, ``Iz = m r^2 / 2 = Ix + Iy`` (exactly): the flat-plate limit of the
    triangle inequality, which :func:`check_inertia` accepts.
    """
    mass, radius = _nonnegative("thin_disc", mass=mass, radius=radius)
    quarter = radius * radius / 4.0
    return _moments(mass, quarter, quarter, 2.0 * quarter)


# --- composite bodies ----------------------------------------------------------------------------


def composite_inertia(
    masses: Float[ArrayLike, "parts ..."],
    coms: Float[ArrayLike, "parts ... 3"],
    inertias: Float[ArrayLike, "parts ... 3"] | Float[ArrayLike, "parts ... 3 3"],
    rotations: Float[ArrayLike, "parts ... 3 3"] | None = None,
) -> tuple[ScalarOut, VectorOut, MatrixOut]:
    """Mass, centre of mass and inertia of a rigid body made of parts.

    The parts are stacked along the LEADING axis (size ``P``); any further axes are batch axes,
    broadcast as usual.

    **Arguments:**

    - `masses`: ``(P, ...)`` part masses (kg).
    - `coms`: ``(P, ..., 3)`` part centres of mass in the body frame (m).
    - `inertias`: each part's inertia about its own centre of mass in its own axes: principal moments
      ``(P, ..., 3)`` or tensors ``(P, ..., 3, 3)`` (kg m^2). Tensors need the parts axis, so an
      ``inertias`` of shape ``(3, 3)`` is three parts' principal moments; with batch axes a trailing
      ``(3, 3)`` is read as tensors.
    - `rotations`: ``(P, ..., 3, 3)`` rotation matrices mapping each part's axes to the body axes
      (``v_body = R @ v_part``), or ``None`` if all parts are aligned with the body axes.

    **Returns:** ``(total_mass, com, inertia)``: the total mass ``(...)`` (kg), the combined centre of
    mass ``(..., 3)`` in the body frame (m), and the inertia tensor ``(..., 3, 3)`` about the combined
    centre of mass in body axes (kg m^2): ``sum_p R_p I_p R_p^T + m_p (|d_p|^2 1 - d_p d_p^T)`` with
    ``d_p = com_p - com``. Use :func:`principal_axes` for its principal moments and axes, and
    :func:`parallel_axis` to move it to a pivot.
    """
    names = ["masses", "coms", "inertias"]
    args = [masses, coms, inertias]
    if rotations is not None:
        names.append("rotations")
        args.append(rotations)
    args = common_float(*args, names=names)
    masses, coms, inertias = args[:3]
    if masses.ndim < 1:
        raise ValueError(f"masses must have a leading parts axis, shape (P, ...), got {masses.shape}.")
    check_last_axis(coms, 3, "coms")
    if inertias.ndim >= 3 and inertias.shape[-2:] == (3, 3):
        part_tensors = inertias
    else:
        check_last_axis(inertias, 3, "inertias")
        part_tensors = inertias[..., None, :] * jnp.eye(3, dtype=inertias.dtype)
    if rotations is not None:
        rotations = args[3]
        check_last_two_axes(rotations, "rotations")
        rotations = check_rotation_matrix(rotations, "rotations", "composite_inertia")
        part_tensors = rotations @ part_tensors @ _swap(rotations)
    n_parts = masses.shape[0]
    for arr, nm in ((coms, "coms"), (part_tensors, "inertias"), (rotations, "rotations")):
        if arr is not None and (arr.ndim < 2 or arr.shape[0] != n_parts):
            raise ValueError(
                f"{nm} must have the parts axis first, with {n_parts} parts like masses, "
                f"got shape {arr.shape}."
            )
    where = "composite_inertia"
    masses = _check_nonnegative(masses, "masses", where)
    coms = check_finite(coms, "coms", where)
    part_tensors = check_finite(part_tensors, "inertias", where)
    total_mass = jnp.sum(masses, axis=0)
    total_mass = eqx.error_if(
        total_mass,
        jnp.any(total_mass <= 0),
        f"{where}: the total mass is 0: the centre of mass is undefined. Give the parts positive masses.",
    )
    com = jnp.sum(masses[..., None] * coms, axis=0) / total_mass[..., None]
    offsets = coms - com
    inertia = jnp.sum(part_tensors + _point_mass_tensor(masses, offsets), axis=0)
    return total_mass, com, inertia
