"""The result of :func:`rigidjax.simulate` and the physics it can report about itself."""

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._dynamics.equations import _kinetic_energy
from .._dynamics.models import AbstractModel
from .._kinematics.euler import _euler_from_quat, _euler_rates
from .._kinematics.quaternion import _quat_rotate
from .._numerics import safe_norm
from .._repr import _concrete
from . import storage
from .batching import model_per_time


def _stable_norm(v):
    """Vector norm without overflow of the squares (|L| of the Earth is 6e33 kg m^2/s), with
    gradient 0 at the zero vector (a drift is 0 at the first sample), not NaN."""
    big = jnp.max(jnp.abs(v), axis=-1, keepdims=True)
    safe = jnp.where(big > 0, big, 1.0)
    return big[..., 0] * safe_norm(v / safe)


def first_failed_sample(bad):
    """Per body (``bad``: ``(bodies, T)``, True at a failed sample) the index of its first failed
    sample, ``T`` when it has none: ``Trajectory.stats["first_failed_sample"]``."""
    return jnp.where(jnp.any(bad, axis=-1), jnp.argmax(bad, axis=-1), bad.shape[-1])


class Trajectory(eqx.Module):
    """Sampled motion of one body or a batch.

    ``ts`` (T,) in s; ``omega`` (*batch, T, 3) body-frame rad/s; ``orientation`` (*batch, T, 4) unit
    quaternions (scalar first, body -> space) or None for an omega-only scene. ``success`` (*batch)
    is False where the integration failed (only with ``throw=False``): such a body keeps the samples
    before its failure and is NaN from there on; with ``accuracy="exact"`` a body fails where a
    sample of the closed form is NaN or inf (inputs beyond the dtype's range) or its phase is
    rounded by more than 1e-3 rad, and is NaN from that sample on too.
    ``stats`` holds solver counts: ``num_steps`` (accepted + rejected steps of each chunk),
    ``chunk_size`` (bodies per chunk, an int32 array), ``quaternion_norm_error`` (largest
    | |q| - 1 | before normalisation, per body; None for ``accuracy="exact"``, whose quaternions
    nothing normalises: :meth:`invariants` measures their norm from the samples),
    ``result`` (per body: 0 for success, otherwise diffrax's result code, or -1 for a state that turned
    NaN or inf under a fixed-step solver) and ``first_failed_sample`` (per body: the index of its
    first NaN sample, ``T`` when it has none; the closed form has this one only, its first failed
    sample); with
    ``simulate(..., error_estimate=True)`` also ``error_estimate_omega`` and
    ``error_estimate_orientation`` (:meth:`error_estimate`).

    ``traj[i]`` is body ``i``'s trajectory, with its own scene, success and per-body stats;
    ``traj[:100]``, ``traj[traj.success]``, ``traj[[0, 5]]`` and ``traj[2, 1]`` (a two-axis batch)
    select several bodies as NumPy selects from an array of shape :attr:`batch_shape`, and
    ``for body in traj`` runs over the first batch axis. An index beyond the batch raises
    ``IndexError`` naming it; ``stats["num_steps"]`` and ``stats["chunk_size"]`` stay those of the
    whole run.

    The quantities along the trajectory (:meth:`euler_angles`, the energies, the angular momenta,
    :meth:`invariants`) are each one compiled program per trajectory shape: in a new process
    ``invariants()`` of a batch of heavy tops takes ~0.2 s, where its ~40 operations one by one took
    ~1.5 s, and a later call ~0.2 ms instead of ~10 ms.
    """

    ts: Float[Array, " T"]
    omega: Float[Array, "*batch T 3"]
    orientation: Float[Array, "*batch T 4"] | None
    model: AbstractModel
    success: Bool[Array, "*batch"]
    stats: dict

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.omega.shape[:-2]

    def __getitem__(self, index) -> "Trajectory":
        """The trajectories of the bodies that ``index`` selects, as a :class:`Trajectory`.

        ``index`` indexes the batch axes only, as NumPy indexes an array of shape
        :attr:`batch_shape`: ``traj[3]`` (one body, batch shape ``()``), ``traj[:100]``,
        ``traj[traj.success]`` (a boolean mask), ``traj[[0, 5, 9]]``, ``traj[2, 1]`` for a
        two-axis batch, ``traj[..., 0]``. The samples, the model's per-body fields (broadcast to the
        batch first, so ``traj[i].model`` is body ``i``'s scene), ``success`` and the per-body
        stats (``result``, ``first_failed_sample``, ``quaternion_norm_error`` and the error
        estimates) are those bodies'; ``stats["num_steps"]`` and ``stats["chunk_size"]`` stay
        those of the whole run. Times are not indexed here: take ``traj.ts[k]`` and
        ``traj.omega[..., k, :]`` for samples.

        Raises ``IndexError`` naming the index and the batch shape for an index beyond the
        batch (also an integer array's entries, when their values are known: under ``jit``,
        traced integer indices are clamped to the batch as ``jax.numpy`` clamps them) and
        ``TypeError`` for an index that is not an integer, a slice, an integer or boolean array
        or ``...`` (``None`` adds no body).
        """
        batch = self.batch_shape
        index = _body_index(index, batch)
        success = self.success[index]

        def per_body(x, leading=batch):
            return jnp.broadcast_to(x, batch + x.shape[len(leading) :])[index]

        ts = self.ts
        if ts.ndim > 1:  # one time axis per body, from a jax.vmap of simulate over ts
            lead = ts.shape[:-1]
            ts = per_body(jnp.reshape(ts, lead + (1,) * (len(batch) - len(lead)) + ts.shape[-1:]))
        leaves = self.model.body_leaves()
        values = []
        for leaf in leaves:
            value = jnp.asarray(leaf.get(self.model))
            values.append(
                value if value.ndim == leaf.core else per_body(value, value.shape[: -leaf.core or None])
            )
        stats = {
            name: per_body(x) if name in _PER_BODY_STATS and x is not None else x
            for name, x in self.stats.items()
        }
        return Trajectory(
            ts=ts,
            omega=self.omega[index],
            orientation=None if self.orientation is None else self.orientation[index],
            model=self.model.replace_body_leaves(leaves, values),
            success=success,
            stats=stats,
        )

    def __iter__(self):
        """The trajectories of the bodies along the first batch axis, one :class:`Trajectory` each
        (``traj[0]``, ``traj[1]``, ...). Raises ``TypeError`` for a single body (batch shape
        ``()``)."""
        if not self.batch_shape:
            raise TypeError(
                "Trajectory: a single body's trajectory (batch_shape ()) has no bodies to iterate over."
            )
        return (self[i] for i in range(self.batch_shape[0]))

    def save(self, path: str | os.PathLike) -> None:
        """Writes the trajectory to one ``.npz`` file that :meth:`Trajectory.load` reads back exactly.

        The file holds NumPy arrays only (``numpy.load(path, allow_pickle=False)`` opens it): the
        model (``model/class`` and each of its fields, its torques' included, e.g. ``model/inertia``,
        ``model/torques/0/frame``), ``ts``, ``omega``, ``orientation`` (absent for an omega-only
        scene), ``success``, ``stats/<name>`` for every stat that is an array or a number, and
        ``meta/format``, ``meta/format_version``, ``meta/rigidjax_version``, ``meta/dtype``. The
        write goes to a temporary file beside ``path`` that replaces ``path`` only when complete, so
        an interrupted save leaves any earlier file as it was.

        **Arguments:**

        - `path`: the file to write, used as given (no suffix is added; ``.npz`` is customary). An
          existing file is replaced.

        **Returns:**

        None. Raises ``FileNotFoundError``, ``IsADirectoryError`` or ``PermissionError`` naming the
        path when it cannot be written, and ``ValueError`` when the model cannot be stored
        faithfully (a :class:`rigidjax.Torque` wraps Python code; custom scenes and torques are not
        rigidjax's to rebuild): save the arrays with ``numpy.savez`` yourself then, or when an array
        is sharded over several processes (a ``jax.distributed`` run: gather it in every process
        with ``multihost_utils.process_allgather`` first, then save from one). All before anything
        is written.
        """
        path = storage.check_writable(path)
        storage.write_atomic(path, storage.encode(self))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Trajectory":
        """Reads a trajectory written by :meth:`Trajectory.save`.

        **Arguments:**

        - `path`: the ``.npz`` file.

        **Returns:**

        The :class:`Trajectory` as it was saved: the same model class and fields, the same arrays
        with the same dtypes and values bit for bit, the same stats (so ``invariants()`` agrees).
        Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the path for a
        file that is not a rigidjax trajectory, is damaged, is of a format version this rigidjax
        does not read, holds a scene that :func:`rigidjax.simulate` refuses (a non-physical
        inertia, a negative mass), or holds float64 arrays while JAX runs in 32-bit mode.
        """
        return cls(**storage.read(path))

    def error_estimate(self) -> dict[str, Float[Array, "*batch"]]:
        """The per-body error estimate of ``simulate(..., error_estimate=True)``.

        **Returns:**

        ``{"omega": ..., "orientation": ...}`` (``orientation`` only with an orientation), each of
        shape ``(*batch)``: ``omega`` the largest error of the angular velocity over the samples,
        relative to the body's largest ``|omega|``; ``orientation`` the largest angle (rad) by which
        the orientation is off. From a second, more accurate solution (see
        :func:`rigidjax.simulate`); NaN for a body whose integration failed, inf for one whose
        second integration failed. Raises ``ValueError`` when the trajectory was simulated without
        ``error_estimate=True``.
        """
        if "error_estimate_omega" not in self.stats:
            raise ValueError(
                "This trajectory has no error estimate: simulate with "
                "rigidjax.simulate(..., error_estimate=True), which solves the batch a second time, "
                "more accurately, and compares."
            )
        out = {"omega": self.stats["error_estimate_omega"]}
        if self.stats.get("error_estimate_orientation") is not None:
            out["orientation"] = self.stats["error_estimate_orientation"]
        return out

    def __repr__(self) -> str:
        """One line: the scene and its torques, the batch shape, the number of samples, the time span,
        the dtype, whether there are orientations and how many bodies succeeded; no array values."""
        if not all(hasattr(x, "shape") and hasattr(x, "dtype") for x in (self.ts, self.omega, self.success)):
            # Leaves that are not arrays (a tree_map to their shapes, say): the generic form.
            return eqx.tree_pformat(self)
        model = type(self.model).__name__
        torques = getattr(self.model, "torques", ())
        if torques:
            model += "[" + ", ".join(type(t).__name__ for t in torques) + "]"
        parts = [model, f"batch_shape={self.batch_shape}", f"{self.ts.shape[-1]} samples"]
        # Inside jit, and for jax.eval_shape's abstract values: shapes only.
        ts, success = _concrete(self.ts), _concrete(self.success)
        if ts is not None and ts.size:
            # One time axis, or one per body where jax.vmap of simulate stacked them.
            parts.append(f"t={np.min(ts[..., 0]):g} to {np.max(ts[..., -1]):g} s")
        parts.append(str(self.omega.dtype))
        parts.append("omega only" if self.orientation is None else "with orientation")
        if success is not None:
            parts.append(f"{int(success.sum())}/{success.size} bodies succeeded")
        return f"Trajectory({', '.join(parts)})"

    def _model_per_time(self) -> AbstractModel:
        """The model with a length-1 time axis inserted after its batch axes, to broadcast over T."""
        return model_per_time(self.model, self.batch_shape)

    @eqx.filter_jit
    def euler_angles(self, seq: str = "zxz") -> Float[Array, "*batch T 3"]:
        """Euler angles ``(phi, theta, psi)`` along the trajectory, unwrapped in time so that angles
        that keep turning (precession, spin) are continuous over many turns.

        Each step between samples is taken on the branch (a multiple of ``2 pi``) that the Euler
        rates at its two ends predict (their mean times the step), so an angle that turns by more
        than ``pi`` between samples (a fast spin sampled sparsely) is followed too. Where the rates
        are unbounded (gimbal lock) or change by more than ``pi`` over the step, the step nearest to
        zero is taken, as by ``jnp.unwrap``."""
        if self.orientation is None:
            raise ValueError(
                "This trajectory has no orientation (omega-only scene); simulate with an orientation."
            )
        return _unwrapped_euler_angles(self.orientation, self.omega, self.ts, seq)

    @eqx.filter_jit
    def kinetic_energy(self) -> Float[Array, "*batch T"]:
        """Rotational kinetic energy ``omega . I omega / 2`` (J)."""
        return _kinetic_energy(self._model_per_time().inertia, self.omega)

    @eqx.filter_jit
    def potential_energy(self) -> Float[Array, "*batch T"]:
        """Potential energy (J); zero for scenes without a field."""
        if self.orientation is None:
            return jnp.zeros(self.omega.shape[:-1], self.omega.dtype)
        return self._model_per_time().potential_energy(self.orientation)

    @eqx.filter_jit
    def energy(self) -> Float[Array, "*batch T"]:
        """Total energy, kinetic plus potential (J)."""
        return self.kinetic_energy() + self.potential_energy()

    @eqx.filter_jit
    def angular_momentum(self) -> Float[Array, "*batch T 3"]:
        """Body-frame angular momentum (kg m^2/s): ``I omega``, plus the rotors' ``h`` for a
        :class:`rigidjax.Gyrostat` (the scene's ``angular_momentum``)."""
        return self._model_per_time().angular_momentum(self.omega)

    @eqx.filter_jit
    def space_angular_momentum(self) -> Float[Array, "*batch T 3"]:
        """Space-frame angular momentum ``R L`` (kg m^2/s), ``L`` of :meth:`angular_momentum`."""
        if self.orientation is None:
            raise ValueError("space_angular_momentum needs an orientation; simulate with one.")
        return _quat_rotate(self.orientation, self.angular_momentum())

    @eqx.filter_jit
    def invariants(self) -> dict[str, Float[Array, "*batch"]]:
        """Largest relative drift of each quantity the scene conserves, per body.

        ``energy`` (torque-free and conservative scenes; relative to the largest kinetic plus
        absolute potential energy along the trajectory, which is not 0 for a body that moves, as
        the energy itself is for a top released at rest with its centre of mass level with the
        pivot), ``angular_momentum_norm`` (no external torque, a gyrostat's rotors included:
        ``L = I omega + h``), ``space_angular_momentum`` (the same, with orientation,
        ``|L(t) - L(0)| / |L(0)|``), ``vertical_angular_momentum`` (heavy top, relative to the
        largest |L| along the trajectory: a top released at rest has ``L(0) = 0``), ``quaternion_norm``
        (``| |q| - 1 |`` before the output was normalised; for ``accuracy="exact"``, whose output
        nothing normalises, ``| |q| - 1 |`` of the samples). NaN for a body that failed
        (``success`` False), whose samples stop being a motion where it failed.
        """
        out = {}
        model = self.model
        tiny = jnp.finfo(self.omega.dtype).tiny

        def drift(x, scale):
            return jnp.max(jnp.abs(x - x[..., :1]), axis=-1) / jnp.maximum(scale, tiny)

        if model.conserves_energy:
            kinetic, potential = self.kinetic_energy(), self.potential_energy()
            out["energy"] = drift(kinetic + potential, jnp.max(kinetic + jnp.abs(potential), axis=-1))
        L = self.angular_momentum()
        L_norm = _stable_norm(L)
        if model.conserves_angular_momentum:
            out["angular_momentum_norm"] = drift(L_norm, L_norm[..., 0])
            if self.orientation is not None:
                Ls = self.space_angular_momentum()
                out["space_angular_momentum"] = jnp.max(
                    _stable_norm(Ls - Ls[..., :1, :]), axis=-1
                ) / jnp.maximum(L_norm[..., 0], tiny)
        if model.conserves_vertical_angular_momentum:
            Lz = self.space_angular_momentum()[..., 2]
            out["vertical_angular_momentum"] = drift(Lz, jnp.max(L_norm, axis=-1))
        if self.orientation is not None:
            q_norm = self.stats.get("quaternion_norm_error")
            if q_norm is None:
                q_norm = jnp.max(jnp.abs(jnp.linalg.norm(self.orientation, axis=-1) - 1), axis=-1)
            # The solver's own record keeps the steps before the failure: a clean-looking value.
            out["quaternion_norm"] = jnp.where(self.success, q_norm, jnp.nan)
        return out


_PER_BODY_STATS = frozenset(
    {
        "result",
        "first_failed_sample",
        "quaternion_norm_error",
        "error_estimate_omega",
        "error_estimate_orientation",
    }
)


def _body_index(index, batch: tuple[int, ...]) -> tuple:
    """``index`` as a tuple over the batch axes ``batch``, ``...`` spelled out and lists as arrays,
    checked where its values are known: see :meth:`Trajectory.__getitem__`."""
    shown = f"Trajectory[{index!r}]"
    entries = []
    for entry in index if isinstance(index, tuple) else (index,):
        if isinstance(entry, list):
            entry = np.asarray(entry)
        if entry is Ellipsis or isinstance(entry, slice):
            entries.append((entry, 1))
        elif isinstance(entry, int | np.integer) and not isinstance(entry, bool | np.bool_):
            entries.append((entry, 1))
        elif isinstance(entry, jax.Array | np.ndarray) and np.dtype(entry.dtype) == np.bool_ and entry.ndim:
            entries.append((entry, entry.ndim))
        elif isinstance(entry, jax.Array | np.ndarray) and np.issubdtype(np.dtype(entry.dtype), np.integer):
            entries.append((entry, 1))
        else:
            raise TypeError(
                f"{shown}: {type(entry).__name__} {entry!r} is not an index of bodies; use an integer, a "
                "slice, an integer or boolean array, or ...."
            )
    ellipses = [i for i, (entry, _) in enumerate(entries) if entry is Ellipsis]
    if len(ellipses) > 1:
        raise IndexError(f"{shown}: an index can hold only one ... (batch_shape {batch}).")
    taken = sum(count for entry, count in entries if entry is not Ellipsis)
    if taken > len(batch):
        takes = f"{taken} axis" if taken == 1 else f"{taken} axes"
        has = f"{len(batch)} batch axis" if len(batch) == 1 else f"{len(batch)} batch axes"
        raise IndexError(
            f"{shown}: the index takes {takes}, but the trajectory has {has} (batch_shape {batch}); it "
            "selects bodies. For samples, index traj.ts and traj.omega[..., k, :]."
        )
    if ellipses:
        at = ellipses[0]
        entries[at : at + 1] = [(slice(None), 1)] * (len(batch) - taken)
    axis = 0
    for entry, count in entries:
        sizes = batch[axis : axis + count]
        known = None if isinstance(entry, slice | jax.core.Tracer) else np.asarray(entry)
        if known is not None and known.dtype == np.bool_:
            if known.shape != sizes:
                raise IndexError(
                    f"{shown}: a boolean mask of shape {known.shape} for batch axes of sizes {sizes} "
                    f"(batch_shape {batch})."
                )
        elif known is not None:
            beyond = known[(known >= sizes[0]) | (known < -sizes[0])]
            if beyond.size:
                raise IndexError(
                    f"{shown}: index {beyond.ravel()[0]} is beyond batch axis {axis} of size {sizes[0]} "
                    f"(batch_shape {batch})."
                )
        axis += count
    return tuple(entry for entry, _ in entries)


def _unwrapped_euler_angles(q, omega, ts, seq):
    """Euler angles of the orientations ``q`` (``(..., T, 4)``), unwrapped in time along ``ts`` by the
    Euler rates of the angular velocities ``omega`` (``(..., T, 3)``): see
    :meth:`Trajectory.euler_angles`."""
    angles = _euler_from_quat(q, seq)
    return _unwrapped_by_rates(angles, _euler_rates(angles, omega, seq, throw=False), ts)


def _unwrapped_by_rates(angles, rates, ts):
    """``angles`` ``(..., T, 3)`` unwrapped along the samples: each step gets the multiple of ``2 pi``
    that brings it closest to the trapezoid of ``rates`` over it, where that is finite and the rates
    change by less than ``pi`` over the step (else the closest to zero)."""
    step = jnp.diff(angles, axis=-2)
    dt = jnp.diff(ts, axis=-1)[..., None]  # ts (T,), or (..., T) from a user's vmap of simulate
    early, late = rates[..., :-1, :], rates[..., 1:, :]
    predicted = 0.5 * (early + late) * dt
    trusted = jnp.isfinite(predicted) & (jnp.abs(late - early) * dt < jnp.pi)
    predicted = jnp.where(trusted, predicted, 0.0)
    turns = jax.lax.stop_gradient(jnp.round((predicted - step) / (2 * jnp.pi)))  # a discrete choice
    first = jnp.zeros_like(angles[..., :1, :])  # (turns is empty for a single sample)
    return angles + 2 * jnp.pi * jnp.concatenate([first, jnp.cumsum(turns, axis=-2)], axis=-2)
