"""Trajectories on disk: one ``.npz`` file that NumPy reads without pickling.

The file holds NumPy arrays only (``numpy.load(path, allow_pickle=False)`` opens it), under these
names:

- ``meta/format`` (``"rigidjax.Trajectory"``), ``meta/format_version`` (an integer, now 1),
  ``meta/rigidjax_version`` (the writer's version) and ``meta/dtype`` (the floating dtype of the
  states, e.g. ``"float64"``).
- ``ts``, ``omega``, ``orientation`` (absent for an omega-only scene) and ``success``: the
  trajectory's arrays, as they are in memory.
- ``stats/<name>``: each entry of ``Trajectory.stats`` that is an array or a number (or None);
  ``meta/stats`` lists their names in order.
- ``model/class``: the scene's class (``"FreeBody"``, ``"RigidBody"``, ``"HeavyTop"``,
  ``"Gyrostat"``); ``model/<field>`` each of its fields (``model/inertia``, ``model/mass``,
  ``model/rotor_momentum``, ...). Its torques are
  ``model/torques/length`` and, for the i-th, ``model/torques/<i>/class`` (``"ConstantTorque"``,
  ``"ViscousDamping"``, ``"GravityTorque"``) and ``model/torques/<i>/<field>``, static settings such
  as ``model/torques/<i>/frame`` included.
- ``meta/none`` (names whose value is None: ``orientation``, a stat), ``meta/python_scalars``
  (names that hold a Python ``bool``/``int``/``float``/``str`` rather than an array, e.g.
  ``stats/chunk_size`` or a torque's frame) and ``meta/weak_type`` (arrays that JAX holds as weakly
  typed): what it takes to give back the same Python objects.

Loading rebuilds the scene with its public constructor (so a damaged file meets the usual checks) and
checks that every array comes back with its dtype and shape. The write goes to a temporary file in the
target's directory that replaces the target only once it is complete (:func:`write_file_atomic`, which
the ``rigidjax`` command uses for its own output files too).
"""

import contextlib
import dataclasses
import os
import secrets
import stat
import warnings
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from typing import Any, BinaryIO

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._dynamics.gyrostat import Gyrostat
from .._dynamics.models import AbstractModel, FreeBody, HeavyTop, RigidBody, inertia_ndim
from .._dynamics.torques import ConstantTorque, GravityTorque, Torque, ViscousDamping
from . import batching
from .inputs import check_model

FORMAT = "rigidjax.Trajectory"
FORMAT_VERSION = 1

# The classes a file can name, and so the only ones save() accepts: their fields are numbers and
# settings, and their public constructor rebuilds them from those.
_CLASSES = {
    cls.__name__: cls
    for cls in (FreeBody, RigidBody, HeavyTop, Gyrostat, ConstantTorque, ViscousDamping, GravityTorque)
}
_PYTHON_SCALARS = (bool, int, float, str)
_PYTHON_TYPES = {"b": bool, "i": int, "f": float, "U": str}  # dtype kind -> the Python type it came from
_ARRAY_KINDS = "biuf"  # bool, signed and unsigned integers, floats: what a .npy stores without pickling


def _rigidjax_version() -> str:
    try:
        return version("rigidjax")
    except PackageNotFoundError:  # a source tree that is not installed
        return "0.0.0+unknown"


# ---------------------------------------------------------------------------------------------
# Writing


class _Encoder:
    """Flattens a trajectory into named NumPy arrays, refusing what it cannot store faithfully."""

    def __init__(self):
        self.arrays: dict[str, np.ndarray] = {}
        self.none: list[str] = []
        self.python_scalars: list[str] = []
        self.weak_type: list[str] = []

    def array(self, key: str, x) -> None:
        if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer) and not x.is_fully_addressable:
            if not x.is_fully_replicated:
                raise ValueError(
                    f"Trajectory.save: {key} is sharded over the devices of several processes (a "
                    "jax.distributed run), and this process holds only its own rows. Gather the "
                    "trajectory in every process first, traj = jax.tree.map(lambda x: "
                    "multihost_utils.process_allgather(x, tiled=True), traj) with "
                    "jax.experimental.multihost_utils, then save it from one process."
                )
            x = x.addressable_data(0)  # every process holds all of it
        try:
            a = np.asarray(x)
        except jax.errors.TracerArrayConversionError as err:
            raise ValueError(
                f"Trajectory.save: {key} is a traced value; save concrete results, outside jax.jit."
            ) from err
        if a.dtype.kind not in _ARRAY_KINDS or not a.dtype.isbuiltin:
            raise ValueError(
                f"Trajectory.save: {key} has dtype {a.dtype}, which a .npz file cannot hold without "
                "pickling; convert it to a float, integer or boolean array first."
            )
        self.arrays[key] = a
        if isinstance(x, jax.Array) and x.weak_type:
            self.weak_type.append(key)

    def value(self, key: str, x, where: str) -> None:
        """Any value of a stored model: an array, a Python number or string, None, a tuple or a
        rigidjax scene or torque."""
        if x is None:
            self.none.append(key)
        elif isinstance(x, jax.Array | np.ndarray | np.generic):  # before float: np.float64 is one
            self.array(key, x)
        elif isinstance(x, _PYTHON_SCALARS):
            self.arrays[key] = np.asarray(x)
            self.python_scalars.append(key)
        elif isinstance(x, tuple):
            self.arrays[f"{key}/length"] = np.asarray(len(x), np.int64)
            for i, item in enumerate(x):
                self.value(f"{key}/{i}", item, f"{where}[{i}]")
        elif isinstance(x, eqx.Module):
            self.module(key, x, where)
        else:
            raise ValueError(
                f"Trajectory.save: {where} holds a {type(x).__name__}, which a .npz file cannot store "
                "faithfully. Save the arrays you need yourself (numpy.savez(path, ts=..., omega=...))."
            )

    def module(self, key: str, module: eqx.Module, where: str) -> None:
        cls = type(module)
        if isinstance(module, Torque):
            raise ValueError(
                f"Trajectory.save: {where} is a Torque(fn), which wraps arbitrary Python "
                "code that a .npz file cannot store, so this trajectory cannot be saved faithfully. "
                "Describe the torque with ConstantTorque, ViscousDamping or GravityTorque if it is one "
                "of those, or save the arrays yourself: numpy.savez(path, ts=np.asarray(traj.ts), "
                "omega=np.asarray(traj.omega), ...)."
            )
        if _CLASSES.get(cls.__name__) is not cls:
            raise ValueError(
                f"Trajectory.save: {where} is a {cls.__module__}.{cls.__qualname__}, which "
                "rigidjax cannot rebuild from a file; only its own scenes (FreeBody, RigidBody, "
                "HeavyTop, Gyrostat) and torques (ConstantTorque, ViscousDamping, GravityTorque) are stored. "
                "Save the arrays you need yourself (numpy.savez(path, ts=..., omega=...))."
            )
        if isinstance(module, AbstractModel) and module.inertia_core_ndim != inertia_ndim(module.inertia):
            raise ValueError(
                f"Trajectory.save: {where} holds principal moments of shape "
                f"{tuple(module.inertia.shape)} (a batch cut from a larger one), which a file reads back "
                "as inertia tensors; give the batch an axis of length 1 before the moments, e.g. "
                "inertia[..., None, :], with omega and orientation alike."
            )
        self.arrays[f"{key}/class"] = np.asarray(cls.__name__)
        for field in dataclasses.fields(module):
            if field.init:  # a field the constructor sets itself (the inertia's form) is rebuilt by it
                self.value(f"{key}/{field.name}", getattr(module, field.name), f"{where}.{field.name}")


def encode(traj: eqx.Module) -> dict[str, np.ndarray]:
    """The named NumPy arrays of the file for the :class:`Trajectory` ``traj``; a ``ValueError`` for
    anything that cannot be stored faithfully (a user torque, a custom scene, an object array)."""
    if np.ndim(traj.ts) > 1:  # one time axis per body: a jax.vmap of simulate over its inputs
        raise ValueError(
            f"Trajectory.save: ts has shape {tuple(np.shape(traj.ts))}, one time axis per body (a "
            "jax.vmap of simulate), where the file holds one time axis for all bodies: save each "
            "body's trajectory, traj[i].save(path_i), or simulate the batch in one call (a leading "
            "batch axis) instead of vmapping."
        )
    enc = _Encoder()
    enc.module("model", traj.model, "model")
    enc.array("ts", traj.ts)
    enc.array("omega", traj.omega)
    if traj.orientation is None:
        enc.none.append("orientation")
    else:
        enc.array("orientation", traj.orientation)
    enc.array("success", traj.success)
    _check_consistent(  # on the arrays as written (host copies made once)
        lambda problem: ValueError(f"Trajectory.save: {problem}; it could not be loaded back."),
        enc.arrays,
        traj.model,
    )
    stats = []
    for name, x in traj.stats.items():
        key = f"stats/{name}"
        if not isinstance(name, str):
            warnings.warn(
                f"Trajectory.save: stats key {name!r} is not a string and is not saved.", stacklevel=3
            )
        elif isinstance(x, jax.Array | np.ndarray | np.generic) and np.dtype(x.dtype).kind in _ARRAY_KINDS:
            enc.array(key, x)
            stats.append(name)
        elif x is None or (isinstance(x, _PYTHON_SCALARS) and not isinstance(x, np.generic)):
            enc.value(key, x, key)
            stats.append(name)
        else:
            warnings.warn(
                f"Trajectory.save: stats[{name!r}] (a {type(x).__name__}) is not an array or a number "
                "and is not saved.",
                stacklevel=3,
            )
    enc.arrays.update(
        {
            "meta/format": np.asarray(FORMAT),
            "meta/format_version": np.asarray(FORMAT_VERSION, np.int64),
            "meta/rigidjax_version": np.asarray(_rigidjax_version()),
            "meta/dtype": np.asarray(np.dtype(traj.omega.dtype).name),
            "meta/stats": np.asarray(stats, dtype=str),
            "meta/none": np.asarray(enc.none, dtype=str),
            "meta/python_scalars": np.asarray(enc.python_scalars, dtype=str),
            "meta/weak_type": np.asarray(enc.weak_type, dtype=str),
        }
    )
    return enc.arrays


def checked_path(path, where: str) -> str:
    """``path`` as a string; a ``TypeError`` or ``ValueError`` naming it unless it is a non-empty
    ``str``, ``bytes`` or ``os.PathLike``."""
    if not isinstance(path, str | bytes | os.PathLike):
        raise TypeError(f"{where}: path must be a file path (str or os.PathLike), got {type(path).__name__}.")
    path = os.fsdecode(os.fspath(path))
    if not path:
        raise ValueError(f"{where}: path is empty; give a file path such as 'trajectory.npz'.")
    return path


def check_writable(path, where: str = "Trajectory.save", example: str = "trajectory.npz") -> str:
    """``path`` as a string, after checking that a file can be created there: a ``FileNotFoundError``,
    ``IsADirectoryError`` or ``PermissionError`` whose message starts with ``where`` and names the
    path otherwise (for a directory, suggesting the file ``example`` in it)."""
    path = checked_path(path, where)
    if os.path.isdir(path):
        raise IsADirectoryError(
            f"{where}: {path!r} is a directory; give a file path such as {os.path.join(path, example)!r}."
        )
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise FileNotFoundError(
            f"{where}: cannot write {path!r}: the directory {directory!r} does not exist; create it first."
        )
    if not os.access(directory, os.W_OK | os.X_OK):
        raise PermissionError(f"{where}: cannot write {path!r}: the directory {directory!r} is not writable.")
    # Permission bits do not tell everything (a read-only or virtual file system, a superuser):
    # create and remove a file where the write will create its temporary file.
    try:
        fd, probe = _open_temporary(directory, os.path.basename(path))
    except OSError as error:
        raise PermissionError(
            f"{where}: cannot write {path!r}: a file cannot be created in {directory!r} "
            f"({error.strerror or error})."
        ) from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)
    return path


def _write_arrays(file, arrays: dict[str, np.ndarray]) -> None:
    """Writes the archive into an open binary file (the step a failed write interrupts)."""
    np.savez(file, **arrays)


def _open_temporary(directory: str, name: str) -> tuple[int, str]:
    """A new file beside the target, created with the permissions a plain ``open`` would give."""
    for _ in range(100):
        tmp = os.path.join(directory, f".{name}.{secrets.token_hex(6)}.tmp")
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"could not create a temporary file in {directory!r} to write {name!r}.")


def write_file_atomic(path: str, write: Callable[[BinaryIO], object]) -> None:
    """Calls ``write(file)`` on a temporary file in ``path``'s directory, then moves it onto ``path``:
    a reader sees the old file or the complete new one, never a part. If ``write`` raises (or the
    process is interrupted, ``KeyboardInterrupt`` included) the temporary file is removed and
    ``path`` is untouched."""
    directory, name = os.path.split(os.path.abspath(path))
    fd, tmp = _open_temporary(directory, name)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        if os.path.isfile(path):  # an overwrite keeps the file's permissions
            os.chmod(tmp, stat.S_IMODE(os.stat(path).st_mode))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError, AttributeError):  # make the rename itself durable (POSIX)
        dir_fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def write_atomic(path: str, arrays: dict[str, np.ndarray]) -> None:
    """Writes ``arrays`` as a ``.npz`` (no pickles) through :func:`write_file_atomic`."""
    write_file_atomic(path, lambda f: _write_arrays(f, arrays))


# ---------------------------------------------------------------------------------------------
# Reading


def _weakly_typed(x):
    """``x`` as a weakly typed array (how JAX holds results of Python scalars), where JAX allows it."""
    try:
        from jax._src.lax.lax import _convert_element_type
    except ImportError:  # pragma: no cover - a JAX without it: the array stays strongly typed
        return x
    return _convert_element_type(x, weak_type=True)


class _Decoder:
    """Rebuilds the stored objects from the named arrays, and fails with the path and the reason."""

    def __init__(self, path: str, arrays: dict[str, np.ndarray]):
        self.path = path
        self.arrays = arrays
        self.used: set[str] = set()
        self.none = set(self.text_list("meta/none"))
        self.python_scalars = set(self.text_list("meta/python_scalars"))
        self.weak_type = set(self.text_list("meta/weak_type"))

    def fail(self, problem: str) -> ValueError:
        return ValueError(f"Trajectory.load: {self.path!r} is not a readable rigidjax trajectory: {problem}.")

    def raw(self, key: str) -> np.ndarray:
        if key not in self.arrays:
            raise self.fail(f"the entry {key!r} is missing (the file is damaged or incomplete)")
        self.used.add(key)
        return self.arrays[key]

    def text(self, key: str) -> str:
        a = self.raw(key)
        if a.shape != () or a.dtype.kind != "U":
            raise self.fail(f"{key!r} should be a string, got dtype {a.dtype} and shape {a.shape}")
        return str(a)

    def text_list(self, key: str) -> list[str]:
        a = self.raw(key)
        if a.ndim != 1 or (a.size and a.dtype.kind != "U"):
            raise self.fail(f"{key!r} should be a list of names, got dtype {a.dtype} and shape {a.shape}")
        return [str(s) for s in a]

    def array(self, key: str):
        a = self.raw(key)
        if a.dtype.kind not in "biufc":
            raise self.fail(f"{key!r} should hold numbers, got dtype {a.dtype}")
        x = jnp.asarray(a)
        if x.dtype != a.dtype:
            raise ValueError(
                f"Trajectory.load: {self.path!r} holds {key} as {a.dtype}, which JAX would read as "
                f"{x.dtype}: turn on 64-bit mode first (jax.config.update('jax_enable_x64', True)) to "
                "read it back exactly."
            )
        return _weakly_typed(x) if key in self.weak_type else x

    def value(self, key: str):
        if f"{key}/class" in self.arrays:
            return self.module(key)
        if f"{key}/length" in self.arrays:
            length = self.raw(f"{key}/length")
            if length.shape != () or length.dtype.kind not in "iu":
                raise self.fail(f"{key + '/length'!r} should be an integer")
            return tuple(self.value(f"{key}/{i}") for i in range(int(length)))
        if key in self.none and key not in self.arrays:
            return None
        if key in self.python_scalars:
            a = self.raw(key)
            if a.shape != () or a.dtype.kind not in _PYTHON_TYPES:
                raise self.fail(f"{key!r} should be a single number or string")
            return _PYTHON_TYPES[a.dtype.kind](a.item())
        return self.array(key)

    def module(self, key: str):
        name = self.text(f"{key}/class")
        cls = _CLASSES.get(name)
        if cls is None:
            known = ", ".join(_CLASSES)
            raise self.fail(f"{key} is a {name!r}, which this rigidjax cannot rebuild (it knows {known})")
        fields = {
            field.name: self.value(f"{key}/{field.name}") for field in dataclasses.fields(cls) if field.init
        }
        kwargs = dict(fields)
        if "torques" in kwargs:  # the scenes take their torques as `torque=`
            kwargs["torque"] = kwargs.pop("torques")
        try:
            module = cls(**kwargs)
        except Exception as err:
            raise self.fail(f"{name} cannot be rebuilt from {key}/*: {err}") from err
        for field_name, stored in fields.items():
            rebuilt = getattr(module, field_name)
            if isinstance(stored, jax.Array) and (
                not isinstance(rebuilt, jax.Array)
                or rebuilt.dtype != stored.dtype
                or rebuilt.shape != stored.shape
            ):
                raise self.fail(
                    f"{name}.{field_name} did not come back as stored ({stored.dtype}{stored.shape})"
                )
        return module


def decode(path: str, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """The fields of the stored :class:`Trajectory` (its constructor's keyword arguments)."""
    if "meta/format" not in arrays:
        names = ", ".join(sorted(arrays)[:8]) + (", ..." if len(arrays) > 8 else "")
        raise ValueError(
            f"Trajectory.load: {path!r} is a .npz file but not a rigidjax trajectory (it has no "
            f"'meta/format' entry; its entries are: {names or 'none'}). Files written by "
            "Trajectory.save are."
        )
    fmt = arrays["meta/format"]
    if fmt.shape != () or fmt.dtype.kind != "U" or str(fmt) != FORMAT:
        raise ValueError(
            f"Trajectory.load: {path!r} is not a rigidjax trajectory: its meta/format is {fmt!r}."
        )
    found = arrays.get("meta/format_version")
    if found is None or found.shape != () or found.dtype.kind not in "iu":
        raise ValueError(
            f"Trajectory.load: {path!r} has no integer meta/format_version; the file is damaged."
        )
    if int(found) != FORMAT_VERSION:
        writer = arrays.get("meta/rigidjax_version")
        by = f" (written by rigidjax {writer})" if writer is not None else ""
        newer = "; upgrade rigidjax to read it" if int(found) > FORMAT_VERSION else ""
        raise ValueError(
            f"Trajectory.load: {path!r} is in trajectory format version {int(found)}{by}, which this "
            f"rigidjax ({_rigidjax_version()}) cannot read: it reads version {FORMAT_VERSION}{newer}."
        )
    dec = _Decoder(path, arrays)
    dec.used.update({"meta/format", "meta/format_version"})
    dec.text("meta/rigidjax_version")
    dtype = dec.text("meta/dtype")
    fields = {
        "ts": dec.array("ts"),
        "omega": dec.array("omega"),
        "orientation": dec.value("orientation"),
        "model": dec.module("model"),
        "success": dec.array("success"),
        "stats": {},
    }
    if fields["omega"].dtype.name != dtype:
        raise dec.fail(f"omega is {fields['omega'].dtype}, but meta/dtype says {dtype}")
    for name in dec.text_list("meta/stats"):
        fields["stats"][name] = dec.value(f"stats/{name}")
    unread = sorted(set(arrays) - dec.used)
    if unread:
        raise dec.fail(f"it has entries this rigidjax does not know ({', '.join(unread)})")
    _check_consistent(dec.fail, arrays, fields["model"])
    return fields


def _check_consistent(fail: Callable[[str], Exception], arrays: dict[str, np.ndarray], model) -> None:
    """The arrays fit together as :func:`rigidjax.simulate` writes them; ``fail(problem)`` is the
    exception otherwise. Checked on load (a file edited or pieced together loaded, then failed in
    the first computation with a broadcasting error) and on save (a trajectory built by hand that
    load would refuse is refused before it is written, while its values are still in memory)."""
    ts, omega, q, success = (np.asarray(arrays.get(k)) for k in ("ts", "omega", "orientation", "success"))
    has_q = "orientation" in arrays
    if ts.ndim != 1 or ts.size < 1:
        raise fail(f"ts should be 1-D with at least one time, got shape {ts.shape}")
    if omega.ndim < 2 or omega.shape[-2:] != (ts.size, 3):
        raise fail(f"omega should have shape (..., {ts.size}, 3) for {ts.size} times, got {omega.shape}")
    batch = omega.shape[:-2]
    if has_q and q.shape != batch + (ts.size, 4):
        raise fail(f"orientation should have shape {batch + (ts.size, 4)} beside omega, got {q.shape}")
    if success.shape != batch or success.dtype != np.bool_:
        raise fail(
            f"success should be booleans of shape {batch} (one per body), got {success.dtype} {success.shape}"
        )
    try:
        model_batch = batching.batch_shape(model)
        ok = np.broadcast_shapes(model_batch, batch) == batch
    except ValueError:
        ok = False
    if not ok:
        raise fail(f"the model's bodies do not broadcast to the {batch} bodies of omega")
    try:  # the checks simulate makes: a hand-edited negative moment loaded, then gave wrong energies
        check_model(model, "its model")
    except ValueError as err:
        raise fail(str(err).rstrip(".")) from None
    if not (np.all(np.isfinite(ts)) and np.all(np.diff(ts) > 0)):
        raise fail("ts should be finite and strictly increasing")
    pairs = [("ts", ts)] + ([("orientation", q)] if has_q else [])
    mixed = [f"{name} is {a.dtype}" for name, a in pairs if a.dtype != omega.dtype]
    if mixed:
        raise fail(f"its arrays should share omega's dtype ({omega.dtype}): {', '.join(mixed)}")
    with np.errstate(invalid="ignore"):
        finite = np.all(np.isfinite(omega), axis=(-2, -1))
    if np.any(success & ~finite):
        raise fail("a body marked successful has non-finite omega (a failed body's success is False)")
    if has_q:
        with np.errstate(invalid="ignore"):
            off = (
                np.abs(np.linalg.norm(q.astype(np.float64), axis=-1) - 1.0) > 1e-3
            )  # NaN rows: failed bodies
        if np.any(off):
            raise fail("its orientations are not unit quaternions")


def read(path) -> dict[str, Any]:
    """Reads the file at ``path`` and returns the fields of the stored :class:`Trajectory`."""
    path = checked_path(path, "Trajectory.load")
    if os.path.isdir(path):
        raise IsADirectoryError(f"Trajectory.load: {path!r} is a directory, not a trajectory file.")
    try:
        with open(path, "rb") as file:
            magic = file.read(6)
    except FileNotFoundError:
        raise FileNotFoundError(f"Trajectory.load: there is no file {path!r}.") from None
    if not (magic.startswith(b"PK") or magic == b"\x93NUMPY"):
        # NumPy reads any other file as pickled data and suggests allow_pickle: never for this.
        raise ValueError(
            f"Trajectory.load: {path!r} is not a rigidjax trajectory: it is not a .npz archive (a "
            "zip file, as Trajectory.save writes)."
        )
    try:
        archive = np.load(path, allow_pickle=False)
    except Exception as err:
        raise ValueError(
            f"Trajectory.load: {path!r} is not a rigidjax trajectory: NumPy cannot read it as a .npz "
            f"archive ({err})."
        ) from err
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise ValueError(
            f"Trajectory.load: {path!r} holds a single NumPy array (a .npy file), not a rigidjax "
            "trajectory (.npz written by Trajectory.save)."
        )
    with archive:
        try:
            arrays = {key: archive[key] for key in archive.files}
        except Exception as err:
            raise ValueError(
                f"Trajectory.load: {path!r} is not a readable rigidjax trajectory: an entry cannot be "
                f"read without pickling or is damaged ({err})."
            ) from err
    return decode(path, arrays)
