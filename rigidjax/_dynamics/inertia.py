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
moments are valid parts of a composite, and :func:`check_inertia` rejects them for a whole body. They
raise where a moment overflows the dtype, or underflows it (zero or subnormal from a positive mass
and size): other units, or float64, keep the moments in range.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .._checks import (  # noqa: F401 (re-exported)
    as_float_array,
    check_batch_shapes,
    check_finite,
    check_last_axis,
    check_last_two_axes,
    check_rotation_matrix,
    common_float,
    compiled_when_eager,
    error_if,
    is_full_tensor,
)
from .._numerics import _eigh3, _swap
from .._types import Inertia, Matrix, MatrixOut, Scalar, ScalarOut, Vector, VectorOut
from .inertia_checks import check_inertia, check_part_inertia, is_physical_inertia  # noqa: F401


@jax.jit  # one program for the eager calls the decorator passes through as they are (lists)
def _symmetric_eigh(tensor):
    return _eigh3(0.5 * (tensor + _swap(tensor)))


@compiled_when_eager
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
    gradient of symmetric functions of the moments (``sum(moments)``, their product, ``sum(moments**2)``)
    is then correct; derivatives of the axes themselves are not defined there, and neither is
    correct a function that rebuilds a matrix from both outputs, such as the inverse tensor
    ``axes @ diag(1 / moments) @ axes.T`` (at a symmetric top its derivative along an off-diagonal
    perturbation within the degenerate plane is 0, not -2): compute such a function from the
    tensor itself (``jnp.linalg.inv``).
    """
    (tensor,) = common_float(tensor, names=["tensor"])
    check_last_two_axes(tensor, "tensor")
    return _symmetric_eigh(check_finite(tensor, "tensor", "principal_axes"))


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


@compiled_when_eager
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
    tensor = is_full_tensor(inertia_com, "inertia_com")
    check_last_axis(displacement, 3, "displacement")
    where = "parallel_axis"
    check_batch_shapes(
        where,
        ("inertia_com", inertia_com, 2 if tensor else 1),
        ("mass", mass, 0),
        ("displacement", displacement, 1),
    )
    inertia_com = check_part_inertia(inertia_com, "inertia_com", where)
    mass = _check_nonnegative(mass, "mass", where)
    displacement = check_finite(displacement, "displacement", where)
    return _as_tensor(inertia_com) + _point_mass_tensor(mass, displacement)


# --- common shapes -------------------------------------------------------------------------------


def _check_nonnegative(x, name: str, where: str):
    """``x`` wrapped in run-time checks: finite and ``>= 0`` (a mass in kg or a length in m)."""
    x = check_finite(x, name, where)
    return error_if(x, jnp.any(x < 0), f"{where}: {name} must be >= 0, got a negative value.")


_VECTORS = ("size", "semi_axes")  # the (..., 3) arguments of the shape functions; the rest are scalars


def _nonnegative(where, **values):
    """Float arrays of one dtype, each checked by :func:`_check_nonnegative`, in argument order."""
    arrays = common_float(*values.values(), names=list(values))
    check_batch_shapes(where, *[(n, a, int(n in _VECTORS)) for n, a in zip(values, arrays, strict=True)])
    return [_check_nonnegative(a, n, where) for a, n in zip(arrays, values, strict=True)]


def _moments(mass, *factors):
    """Stacks ``mass * factor`` along a new last axis."""
    return mass[..., None] * jnp.stack(jnp.broadcast_arrays(*factors), axis=-1)


def _shape(where: str, formula, **values):
    """``formula(mass, *sizes)``, the principal moments of a shape, after the checks of
    :func:`_nonnegative`, with a run-time check that they are within the dtype's range.

    A moment is out of range if it is not finite (it, or a squared length, overflowed), or if it is
    zero or subnormal (below ``finfo.tiny``) while ``formula`` of the inputs' signs (0 or 1) is not
    zero: a positive mass and size gave no moment (an underflow). Moments that are zero by the
    formula (a thin rod about its axis, a zero mass or size) pass."""
    mass, *sizes = _nonnegative(where, **values)
    moments = formula(mass, *sizes)
    # A NaN, inf or negative input is named by its own check, which comes first. (On CPU a subnormal
    # input reads as 0, here and in the formula alike: its moments are zero as for a zero input, and
    # check_inertia names them for a whole body.)
    expected = formula(*[(a != 0).astype(moments.dtype) for a in (mass, *sizes)]) != 0
    name, finfo = np.dtype(moments.dtype).name, np.finfo(moments.dtype)
    hint = "." if name == "float64" else ", or compute in float64."
    # The checks ride on the mass, and the moments are computed again from it: the program that
    # returns them, and its derivatives, are those without the checks (checked moments changed the
    # compiler's fusion of a derivative, and its last bit).
    mass = error_if(
        mass,
        ~jnp.isfinite(moments),
        f"{where}: the moments of inertia overflow {name}: they, or the squared lengths they are "
        f"computed from, exceed its largest number ({finfo.max:.4g}). Give the mass and lengths in "
        f"larger units (e.g. tonnes and km){hint}",
    )
    mass = error_if(
        mass,
        expected & (jnp.abs(moments) < finfo.tiny),
        f"{where}: the moments of inertia underflow {name}: a positive mass and size give a moment, "
        f"or a squared length, below its smallest normal number ({finfo.tiny:.4g}), which is "
        f"subnormal or flushed to 0. Give the mass and lengths in smaller units (e.g. g and mm){hint}",
    )
    return formula(mass, *sizes)


@compiled_when_eager
def solid_box(mass: Scalar, size: Vector) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a uniform solid box (cuboid) about its centre.

    `mass` in kg; `size` ``(..., 3)`` are the FULL edge lengths ``(a, b, c)`` along the box's x, y, z
    axes (m). ``Ix = m (b^2 + c^2) / 12`` and cyclic.
    """
    mass, size = common_float(mass, size, names=["mass", "size"])
    check_last_axis(size, 3, "size")
    return _shape("solid_box", _box, mass=mass, size=size)


def _box(mass, size):
    s2 = size * size
    a2, b2, c2 = s2[..., 0], s2[..., 1], s2[..., 2]
    return _moments(mass, (b2 + c2) / 12.0, (c2 + a2) / 12.0, (a2 + b2) / 12.0)


@compiled_when_eager
def solid_cylinder(mass: Scalar, radius: Scalar, height: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a uniform solid cylinder about its centre.

    The symmetry axis is z; `radius` and `height` (full length along z) in m, `mass` in kg.
    ``Ix = Iy = m (3 r^2 + h^2) / 12``, ``Iz = m r^2 / 2``.
    """
    return _shape("solid_cylinder", _cylinder, mass=mass, radius=radius, height=height)


def _cylinder(mass, radius, height):
    r2, h2 = radius * radius, height * height
    transverse = (3.0 * r2 + h2) / 12.0
    return _moments(mass, transverse, transverse, r2 / 2.0)


@compiled_when_eager
def hollow_cylinder(mass: Scalar, radius: Scalar, height: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a thin-walled open tube about its centre.

    All the mass is on the curved wall at `radius` (no end caps); the axis is z and `height` is the
    full length along it (m). ``Ix = Iy = m (6 r^2 + h^2) / 12``, ``Iz = m r^2``.
    """
    return _shape("hollow_cylinder", _tube, mass=mass, radius=radius, height=height)


def _tube(mass, radius, height):
    r2, h2 = radius * radius, height * height
    transverse = (6.0 * r2 + h2) / 12.0
    return _moments(mass, transverse, transverse, r2)


@compiled_when_eager
def solid_sphere(mass: Scalar, radius: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a uniform solid ball: ``2 m r^2 / 5`` each."""
    return _shape("solid_sphere", _ball, mass=mass, radius=radius)


def _ball(mass, radius):
    i = 0.4 * radius * radius
    return _moments(mass, i, i, i)


@compiled_when_eager
def hollow_sphere(mass: Scalar, radius: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a thin spherical shell: ``2 m r^2 / 3`` each."""
    return _shape("hollow_sphere", _shell, mass=mass, radius=radius)


def _shell(mass, radius):
    i = (2.0 / 3.0) * radius * radius
    return _moments(mass, i, i, i)


@compiled_when_eager
def solid_ellipsoid(mass: Scalar, semi_axes: Vector) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a uniform solid ellipsoid about its centre.

    `semi_axes` ``(..., 3)`` are the semi-axes ``(a, b, c)`` along x, y, z (m).
    ``Ix = m (b^2 + c^2) / 5`` and cyclic.
    """
    mass, semi_axes = common_float(mass, semi_axes, names=["mass", "semi_axes"])
    check_last_axis(semi_axes, 3, "semi_axes")
    return _shape("solid_ellipsoid", _ellipsoid, mass=mass, semi_axes=semi_axes)


def _ellipsoid(mass, semi_axes):
    s2 = semi_axes * semi_axes
    a2, b2, c2 = s2[..., 0], s2[..., 1], s2[..., 2]
    return _moments(mass, (b2 + c2) / 5.0, (c2 + a2) / 5.0, (a2 + b2) / 5.0)


@compiled_when_eager
def thin_rod(mass: Scalar, length: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a thin uniform rod along z, about its centre.

    ``Ix = Iy = m L^2 / 12`` and ``Iz = 0`` exactly. A body needs positive moments, so a thin rod is
    only valid as a part of a composite body (:func:`composite_inertia`), not on its own; use
    :func:`solid_cylinder` for a rod of finite radius.
    """
    return _shape("thin_rod", _rod, mass=mass, length=length)


def _rod(mass, length):
    transverse = length * length / 12.0
    return _moments(mass, transverse, transverse, jnp.zeros_like(transverse))


@compiled_when_eager
def thin_disc(mass: Scalar, radius: Scalar) -> VectorOut:
    """Principal moments ``(..., 3)`` (kg m^2) of a thin uniform disc in the xy-plane (axis z).

    ``Ix = Iy = m r^2 / 4``, ``Iz = m r^2 / 2 = Ix + Iy`` (exactly): the flat-plate limit of the
    triangle inequality, which :func:`check_inertia` accepts.
    """
    return _shape("thin_disc", _disc, mass=mass, radius=radius)


def _disc(mass, radius):
    quarter = radius * radius / 4.0
    return _moments(mass, quarter, quarter, 2.0 * quarter)


# --- composite bodies ----------------------------------------------------------------------------


@compiled_when_eager
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
    tensors = inertias.ndim >= 3 and inertias.shape[-2:] == (3, 3)
    if not tensors:
        check_last_axis(inertias, 3, "inertias")
    if rotations is not None:
        rotations = args[3]
        check_last_two_axes(rotations, "rotations")
    # The parts axis leads; the batch axes sit between it and each argument's own trailing axes, so
    # they are broadcast there (NumPy's rule from the right would line a batch axis up with parts).
    n_parts = masses.shape[0]
    parted = [("masses", masses, 0), ("coms", coms, 1), ("inertias", inertias, 2 if tensors else 1)]
    if rotations is not None:
        parted.append(("rotations", rotations, 2))
    for name, arr, core in parted:
        if arr.ndim < core + 1 or arr.shape[0] != n_parts:
            raise ValueError(
                f"composite_inertia: {name} must have the parts axis first, with {n_parts} parts like "
                f"masses, got shape {arr.shape}."
            )
    batches = [arr.shape[1 : arr.ndim - core] for _, arr, core in parted]
    try:
        batch = jnp.broadcast_shapes(*batches)
    except ValueError:
        shapes = ", ".join(
            f"{name} {arr.shape} (batch {b})" for (name, arr, _), b in zip(parted, batches, strict=True)
        )
        raise ValueError(
            "composite_inertia: the batch axes (between the leading parts axis and the trailing ones) "
            f"do not broadcast: {shapes}."
        ) from None

    def parts_first(arr, own_batch, core):
        core_shape = arr.shape[arr.ndim - core :]
        padded = arr.reshape((n_parts,) + (1,) * (len(batch) - len(own_batch)) + own_batch + core_shape)
        return jnp.broadcast_to(padded, (n_parts, *batch, *core_shape))

    masses, coms, inertias, *rest = (
        parts_first(arr, b, core) for (_, arr, core), b in zip(parted, batches, strict=True)
    )
    where = "composite_inertia"
    inertias = check_part_inertia(inertias, "inertias", where, tensor=tensors)
    part_tensors = inertias if tensors else inertias[..., None, :] * jnp.eye(3, dtype=inertias.dtype)
    if rotations is not None:
        rotations = check_rotation_matrix(rest[0], "rotations", "composite_inertia")
        part_tensors = rotations @ part_tensors @ _swap(rotations)
    masses = _check_nonnegative(masses, "masses", where)
    coms = check_finite(coms, "coms", where)
    total_mass = jnp.sum(masses, axis=0)
    total_mass = error_if(
        total_mass,
        jnp.any(total_mass <= 0),
        f"{where}: the total mass is 0: the centre of mass is undefined. Give the parts positive masses.",
    )
    com = jnp.sum(masses[..., None] * coms, axis=0) / total_mass[..., None]
    offsets = coms - com
    inertia = jnp.sum(part_tensors + _point_mass_tensor(masses, offsets), axis=0)
    return total_mass, com, inertia
