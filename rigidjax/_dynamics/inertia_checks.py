"""Physical inertia: the checks behind :func:`check_inertia` and :func:`is_physical_inertia`
(finite, symmetric, positive moments, the triangle inequality), scaled so that a trace near the
float range neither overflows nor passes what it should not."""

import jax.numpy as jnp
from jaxtyping import Array, Bool

from .._checks import as_float_array, branched_error_if, check_flag, compiled_when_eager, is_full_tensor
from .._numerics import _SYMMETRY_EPS, _TRIANGLE_EPS, _eigh3, _swap, eps, power_of_two_scaled, short_sum
from .._types import Inertia


def _inertia_form(inertia, name: str, tensor: bool | None) -> tuple[bool, bool]:
    """(read as a tensor, shape is one's): a ``ValueError`` for ``tensor=True`` without a (3, 3)."""
    shape_says = is_full_tensor(inertia, name)
    if tensor and not shape_says:
        raise ValueError(f"{name}: tensor=True needs shape (..., 3, 3), got {tuple(inertia.shape)}.")
    return shape_says if tensor is None else tensor, shape_says


# Failure codes, in increasing order of how fundamental the problem is: across a batch the largest
# code present is reported.
_OK, _TRIANGLE, _NOT_POSITIVE, _NOT_SYMMETRIC, _NOT_FINITE = 0, 1, 2, 3, 4


def _inertia_failure(inertia, zero_allowed: bool = False):
    """Per-body failure code (0 = physical) of principal moments or a tensor, shape ``(...)``. With
    ``zero_allowed``, zero moments pass (a part: a point mass, a thin rod), negative ones do not."""
    inertia = as_float_array(inertia, "inertia")
    tol_eps = eps(inertia.dtype)
    if is_full_tensor(inertia, "inertia"):
        finite = jnp.all(jnp.isfinite(inertia), axis=(-2, -1))
        safe = jnp.where(finite[..., None, None], inertia, jnp.eye(3, dtype=inertia.dtype))
        safe = power_of_two_scaled(safe, axis=(-2, -1))
        scale = jnp.max(jnp.abs(safe), axis=(-2, -1))
        asym = jnp.max(jnp.abs(safe - _swap(safe)), axis=(-2, -1))
        symmetric = asym <= _SYMMETRY_EPS * tol_eps * scale
        moments, _ = _eigh3(0.5 * (safe + _swap(safe)))
        trace = jnp.trace(safe, axis1=-2, axis2=-1)
        # Eigenvalues carry roundoff of order eps * trace: one within it of zero counts as zero. A
        # diagonal tensor's moments are its diagonal, exactly (float32: a thin rod's 5e-7 of a 0.17
        # trace was below that roundoff and rejected as non-positive, its moments accepted).
        diagonal = jnp.diagonal(safe, axis1=-2, axis2=-1)
        exact = jnp.all(safe == diagonal[..., None] * jnp.eye(3, dtype=safe.dtype), axis=(-2, -1))
        moments = jnp.where(exact[..., None], diagonal, moments)
        floor = jnp.where(exact, 0.0, _TRIANGLE_EPS * tol_eps * jnp.abs(trace))
        if zero_allowed:
            positive = jnp.all(moments >= -floor[..., None], axis=-1)
        else:
            positive = jnp.all(moments > floor[..., None], axis=-1)
    else:
        finite = jnp.all(jnp.isfinite(inertia), axis=-1)
        moments = jnp.where(finite[..., None], inertia, jnp.ones_like(inertia))
        moments = power_of_two_scaled(moments, axis=-1)
        symmetric = jnp.ones_like(finite)
        positive = jnp.all(moments >= 0 if zero_allowed else moments > 0, axis=-1)
        trace = short_sum(moments)
    tol = _TRIANGLE_EPS * tol_eps * jnp.abs(trace)
    # I1 + I2 - I3 and its cyclic permutations: trace - 2 I_k >= 0.
    triangle = jnp.all(trace[..., None] - 2.0 * moments >= -tol[..., None], axis=-1)
    code = jnp.where(triangle, _OK, _TRIANGLE)
    code = jnp.where(positive, code, _NOT_POSITIVE)
    code = jnp.where(symmetric, code, _NOT_SYMMETRIC)
    return jnp.where(finite, code, _NOT_FINITE)


@compiled_when_eager
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


def _triangle_message(name: str) -> str:
    return (
        f"{name} violates the triangle inequality I1 + I2 >= I3 (and cyclic) of its principal "
        "moments: no distribution of mass has these moments. Each moment must be at most the sum of "
        "the other two (equality is a flat plate)."
    )


def _asymmetric_message(name: str) -> str:
    return (
        f"{name} is a (..., 3, 3) tensor that is not symmetric: an inertia tensor must equal its transpose."
    )


@compiled_when_eager(static_argnames=("name", "tensor"))
def check_inertia(inertia: Inertia, *, name: str = "inertia", tensor: bool | None = None) -> Inertia:
    """Returns ``inertia`` (as a JAX float array) with a run-time check that it is physical.

    The checks are those of :func:`is_physical_inertia`. The returned array is wrapped in
    ``equinox.error_if``, so this works inside ``jax.jit``; the check only runs if the returned value
    is used. On failure the error message names ``name`` and the problem (non-finite entries, a
    non-symmetric tensor, non-positive moments, or a violated triangle inequality); across a batch the
    most fundamental problem present is reported. Raises ``ValueError`` while tracing for shapes other
    than ``(..., 3)`` and ``(..., 3, 3)``. ``tensor``: whether the trailing axes are a tensor (None:
    a trailing ``(3, 3)`` is one; a scene knows the form of its own inertia).
    """
    tensor = check_flag(tensor, "tensor", "check_inertia", none=True)
    inertia = as_float_array(inertia, name)
    tensor, shape_says = _inertia_form(inertia, name, tensor)
    # Principal moments of shape (..., 3, 3): an axis before them keeps them from reading as tensors.
    code = _inertia_failure(inertia if tensor == shape_says else inertia[..., None, :])
    what = "tensor" if tensor else "principal moments"
    dtype = jnp.dtype(inertia.dtype)
    # XLA on CPU reads a subnormal as 0 in arithmetic and comparisons: such a moment fails as zero.
    subnormal = (
        f" A positive moment below {jnp.finfo(dtype).tiny:.3g} kg m^2 ({dtype.name}'s smallest normal "
        "number) reads as 0 on CPU: give such a body's inertia in smaller units"
        + ("." if dtype == jnp.float64 else ", or use float64.")
    )
    problems = [
        "",
        _triangle_message(name),
        f"{name} has a non-positive principal moment: every moment of inertia of a rigid body must "
        "be > 0 kg m^2." + subnormal,
        _asymmetric_message(name),
    ]
    msgs = [
        *problems[:2],
        problems[2] + " (A thin rod has a zero moment about its axis: it is only valid as a part of a "
        "composite body.)",
        problems[3] + " If you meant a batch of principal moments, note that a trailing (3, 3) shape "
        "is always read as a tensor: add an axis (three bodies: shape (3, 1, 3), moments[:, None, :]) "
        "and the same to the state's arrays.",
        f"{name} ({what}) contains NaN or infinite values.",
    ]
    index = jnp.max(code, initial=_OK)  # an empty batch has nothing to report
    if tensor and shape_says and inertia.ndim == 2:
        # A (3, 3) array is ambiguous: one tensor, or the principal moments of three bodies (three
        # identical spheres even give a symmetric one). It is read as a tensor; when that tensor is
        # not physical but each row is a valid set of moments, say how to pass a batch of three.
        rows_physical = jnp.all(_inertia_failure(inertia[:, None, :]) == _OK)
        ambiguous = rows_physical & (index != _OK) & (index != _NOT_FINITE)
        index = jnp.where(ambiguous, index + _NOT_FINITE, index)
        msgs += [
            problem + f" Note: {name} has shape (3, 3), which is read as ONE inertia tensor, while each "
            "of its rows is a valid set of principal moments. If you meant the principal moments of a "
            "batch of three bodies, pass them as tensors, moments[..., None] * jnp.eye(3) (shape "
            "(3, 3, 3), with omega of shape (3, 3)), or as shape (3, 1, 3), moments[:, None, :], with "
            "the state's arrays of shape (3, 1, 3) too."
            for problem in problems[1:]
        ]
    return branched_error_if(inertia, code != _OK, index, msgs)


def check_part_inertia(inertia, name: str, where: str, tensor: bool | None = None):
    """``inertia`` (principal moments or a tensor, as a JAX float array) with a run-time check that
    it can be the inertia of a part about its own centre of mass: the checks of
    :func:`check_inertia` with zero moments allowed (a point mass, a thin rod about its axis).
    ``tensor``: whether the trailing axes are a tensor (None: a trailing ``(3, 3)`` is one)."""
    tensor, _ = _inertia_form(inertia, name, tensor)
    code = _inertia_failure(inertia if tensor else inertia[..., None, :], zero_allowed=True)
    messages = [
        "",
        f"{where}: {_triangle_message(name)}",
        f"{where}: {name} has a negative principal moment: a moment of inertia is >= 0 kg m^2 (0 for a "
        "point mass).",
        f"{where}: {_asymmetric_message(name)}",
        f"{where}: {name} contains NaN or inf.",
    ]
    return branched_error_if(inertia, code != _OK, jnp.max(code, initial=_OK), messages)
