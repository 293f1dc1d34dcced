"""The arrays a figure draws, taken from a :class:`rigidjax.Trajectory` as NumPy: one body of a
(flattened) batch, its conserved quantities, its orientation as rotation matrices."""

from __future__ import annotations

import operator

import numpy as np

from .._integrate.trajectory import Trajectory
from .._kinematics.quaternion import matrix_from_quat


def check_trajectory(trajectory, where: str) -> None:
    """A ``TypeError`` naming ``where``'s argument unless it is a :class:`rigidjax.Trajectory`
    (anything else failed with an ``AttributeError`` on the first field read)."""
    if not isinstance(trajectory, Trajectory):
        raise TypeError(
            f"{where}: trajectory must be a rigidjax.Trajectory (what rigidjax.simulate returns, or "
            f"rigidjax.Trajectory.load reads), got {type(trajectory).__name__}."
        )


def n_bodies(trajectory) -> int:
    """The number of bodies of the trajectory's batch (1 for a single body)."""
    return int(np.prod(trajectory.batch_shape, dtype=np.int64))


def body_index(trajectory, body, name: str = "body") -> int:
    """``body`` as an index into the flattened batch (negative indices count from the end); a
    ``ValueError`` naming the argument ``name`` for anything else."""
    n = n_bodies(trajectory)
    try:
        if isinstance(body, bool):
            raise TypeError
        index = operator.index(body)
    except TypeError:
        raise ValueError(
            f"{name} must be an integer index into the trajectory's flattened batch, got {body!r}."
        ) from None
    if not -n <= index < n:
        bodies = "1 body" if n == 1 else f"{n} bodies"
        raise ValueError(
            f"{name}={index} is out of range: the trajectory holds {bodies} (batch shape "
            f"{tuple(trajectory.batch_shape)}); give an index from 0 to {n - 1}."
        )
    return index % n


def need_orientation(trajectory, what: str) -> None:
    if trajectory.orientation is None:
        raise ValueError(
            f"{what} needs the trajectory's orientations, and this trajectory has none "
            "(trajectory.orientation is None: omega only was simulated). Simulate with "
            "State(omega, orientation) to get them."
        )


def per_body(values, trajectory, core: int) -> np.ndarray:
    """``values`` (batch axes first, then ``core`` trailing axes) as NumPy with the batch flattened."""
    values = np.asarray(values)
    n = n_bodies(trajectory)
    tail = values.shape[values.ndim - core :] if core else ()
    return np.broadcast_to(values, tuple(trajectory.batch_shape) + tail).reshape((n,) + tail)


def ts(trajectory, i: int | None = None) -> np.ndarray:
    """The sample times ``(T,)``: of body ``i``, or the ones every body shares (``i`` None). A
    trajectory from a user's ``jax.vmap`` of ``simulate`` holds times per body, ``(..., T)``; a figure
    of several bodies needs them to be the same for all (else a ``ValueError``)."""
    times = np.asarray(trajectory.ts)
    if times.ndim == 1:
        return times
    rows = np.broadcast_to(times, tuple(trajectory.batch_shape) + times.shape[-1:]).reshape(
        -1, times.shape[-1]
    )
    if i is not None:
        return rows[i]
    if not np.all(rows == rows[:1]):
        raise ValueError(
            f"the trajectory's bodies have different sample times (ts of shape {times.shape}, as from a "
            "jax.vmap of simulate over the times), and this figure draws them on one time axis: plot "
            "one body at a time, jax.tree.map(lambda x: x[i], trajectory), or simulate the bodies "
            "with one ts."
        )
    return rows[0]


def omega(trajectory, i: int) -> np.ndarray:
    """Body-frame omega of body ``i``, (T, 3)."""
    return per_body(trajectory.omega, trajectory, 2)[i]


def orientation(trajectory, i: int) -> np.ndarray:
    """Orientation quaternions of body ``i``, (T, 4)."""
    return per_body(trajectory.orientation, trajectory, 2)[i]


def inertia(trajectory, i: int) -> np.ndarray:
    """Body ``i``'s inertia as a (3, 3) tensor (principal moments made diagonal)."""
    model = trajectory.model
    core = model.inertia_core_ndim
    value = per_body(model.inertia, trajectory, core)[i]
    return np.diag(value) if core == 1 else value


def rotation_matrices(quaternions: np.ndarray) -> np.ndarray:
    """(T, 3, 3) body -> space matrices; NaN where a quaternion is not finite (a failed body)."""
    quaternions = np.asarray(quaternions)
    finite = np.all(np.isfinite(quaternions), axis=-1) & np.any(quaternions != 0, axis=-1)
    out = np.full(quaternions.shape[:-1] + (3, 3), np.nan)
    if finite.any():
        out[finite] = np.asarray(matrix_from_quat(quaternions[finite]))
    return out


def to_space(quaternions: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Body-frame ``vectors`` (T, 3) in space-frame components at the orientations (T, 4)."""
    return np.einsum("tij,tj->ti", rotation_matrices(quaternions), vectors)
