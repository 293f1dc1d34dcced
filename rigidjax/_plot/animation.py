"""3-D animations of bodies turning: a box (or a top on its pivot) with its body axes and omega,
written to a GIF or an MP4 file."""

from __future__ import annotations

import contextlib
import math
import os
import tempfile

import numpy as np
from matplotlib import animation as mpl_animation
from matplotlib.figure import Figure

from .._checks import is_positive_int
from .._dynamics.models import HeavyTop
from .._integrate.storage import check_writable
from . import data

EXTENSIONS = (".gif", ".mp4")
MAX_BODIES = 6


def ffmpeg_available() -> bool:
    """Whether matplotlib finds ffmpeg, which writing ``.mp4`` needs."""
    return mpl_animation.writers.is_available("ffmpeg")


def check_animation_path(path, name: str = "path") -> str:
    """``path`` as a string after checking its extension and that ffmpeg is there for ``.mp4``."""
    try:
        path = os.fsdecode(os.fspath(path))
    except TypeError:
        raise TypeError(
            f"{name} must be a file path (str or os.PathLike) ending in .gif or .mp4, "
            f"got {type(path).__name__}."
        ) from None
    extension = os.path.splitext(path)[1].lower()
    if extension not in EXTENSIONS:
        raise ValueError(
            f"{name} {path!r}: an animation is written as .gif or .mp4; the name must end in one."
        )
    if extension == ".mp4" and not ffmpeg_available():
        raise RuntimeError(
            f"{name} {path!r}: writing .mp4 needs ffmpeg, which matplotlib cannot find; install ffmpeg "
            "or write a .gif instead."
        )
    return path


def _is_number(value) -> bool:
    return isinstance(value, int | float | np.number) and not isinstance(value, bool | np.bool_)


def _polyline(segments: list[np.ndarray]) -> np.ndarray:
    """Polylines (each (k, 3)) as one (m, 3) array with NaN rows between them (one matplotlib line)."""
    gap = np.full((1, 3), np.nan)
    return np.concatenate([part for segment in segments for part in (segment, gap)])


def _box(moments: np.ndarray) -> np.ndarray:
    """The 12 edges of the uniform box with these principal moments, largest half-side 1."""
    total = moments.sum()
    half = np.sqrt(np.maximum(total - 2 * moments, 1e-3 * total))  # a_k^2 ~ I_j + I_l - I_k
    half /= half.max()
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return _polyline([corners[[a, b]] for a, b in edges])


def _top(axis: np.ndarray) -> np.ndarray:
    """A cone from the pivot (the origin, its apex) along the unit ``axis``, length 1."""
    e1 = np.cross(axis, np.eye(3)[int(np.argmin(np.abs(axis)))])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    angles = np.linspace(0, 2 * np.pi, 25)
    rim = axis + 0.35 * (np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2)
    generators = [np.stack([np.zeros(3), rim[k]]) for k in range(0, 24, 4)]
    return _polyline([rim, *generators, np.stack([np.zeros(3), 1.25 * axis])])


def _shape(trajectory, i: int) -> tuple[np.ndarray, float]:
    """The body-frame outline of body ``i`` (polylines) and the length of its body axes."""
    if isinstance(trajectory.model, HeavyTop):
        com = data.per_body(trajectory.model.com, trajectory, 1)[i].astype(np.float64)
        norm = np.linalg.norm(com)
        return _top(com / norm if norm > 0 else np.eye(3)[2]), 0.6
    moments, vectors = np.linalg.eigh(data.inertia(trajectory, i).astype(np.float64))
    return _box(moments) @ vectors.T, 1.3


def animate(trajectory, path, bodies=(0,), *, fps=20, frames=60, dpi=80) -> str:
    """A 3-D animation of bodies turning, written to a ``.gif`` or ``.mp4`` file.

    Each body has its own panel, in space-frame axes: a box with the body's proportions (the
    uniform box of its principal moments) or, for a :class:`rigidjax.HeavyTop`, a cone from the
    pivot along the centre of mass with the vertical drawn dashed; its body axes (red, green,
    blue for 1, 2, 3); and ``omega`` in black, scaled so that the largest ``|omega|`` shown spans
    the panel. The frames are ``frames`` samples of the trajectory spread evenly over its time
    span (every sample if it has fewer), each titled with its time.

    The file is written to a temporary file beside `path` that replaces `path` only when complete.

    **Arguments:**

    - `trajectory`: a :class:`rigidjax.Trajectory` simulated with orientations.
    - `path`: the file to write: ``.gif`` (with Pillow, which matplotlib requires) or ``.mp4``
      (needs ffmpeg).
    - `bodies`: the bodies to draw, indices into the flattened batch (at most 6).
    - `fps`: frames per second of the file.
    - `frames`: the largest number of frames; the samples are thinned to at most this many.
    - `dpi`: resolution of the frames (dots per inch of a 4-inch-high panel).

    A body that failed (``trajectory.success`` False) is drawn until its first failed sample and
    left blank after it; its panel's title says so.

    **Returns:**

    `path`, as a string. Raises ``ValueError`` naming `path` for another extension, `bodies` for
    an index outside the batch or more than 6 bodies, `trajectory` when it has no orientations,
    and `frames`, `fps` or `dpi` when not positive; ``TypeError`` naming `path` when it is not a
    path; ``RuntimeError`` for ``.mp4`` without ffmpeg;
    ``FileNotFoundError`` or ``PermissionError`` when `path`'s directory is missing or not
    writable. All before any frame is drawn.
    """
    data.check_trajectory(trajectory, "animate")
    path = check_animation_path(path)
    path = check_writable(path, where="animate")
    data.need_orientation(trajectory, "animate")
    if np.ndim(bodies) == 0:
        bodies = [bodies]
    chosen = [data.body_index(trajectory, b, "bodies") for b in bodies]
    if not 1 <= len(chosen) <= MAX_BODIES:
        raise ValueError(f"bodies: give 1 to {MAX_BODIES} body indices, got {len(chosen)}.")
    if not is_positive_int(frames):
        raise ValueError(f"frames must be a positive integer, got {frames!r}.")
    if not (_is_number(fps) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}.")
    if not (_is_number(dpi) and math.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi must be a positive number, got {dpi!r}.")
    success = data.per_body(trajectory.success, trajectory, 0)

    t = data.ts(trajectory)
    picks = np.unique(np.round(np.linspace(0, len(t) - 1, min(int(frames), len(t)))).astype(int))
    columns = min(len(chosen), 3)
    rows = math.ceil(len(chosen) / columns)
    fig = Figure(figsize=(4 * columns, 4 * rows + 0.4))
    title = fig.suptitle("")
    updates = []
    for k, i in enumerate(chosen):
        ax = fig.add_subplot(rows, columns, k + 1, projection="3d")
        ax.set(xlim=(-1.5, 1.5), ylim=(-1.5, 1.5), zlim=(-1.5, 1.5), xlabel="X", ylabel="Y", zlabel="Z")
        ax.set_box_aspect((1, 1, 1))
        ax.set_title(f"body {i}" if success[i] else f"body {i} (failed: drawn until it did)", fontsize=9)
        matrices = data.rotation_matrices(data.orientation(trajectory, i)[picks])
        omega = np.einsum("tij,tj->ti", matrices, data.omega(trajectory, i)[picks].astype(np.float64))
        speeds = np.linalg.norm(omega, axis=-1)
        speed = speeds[np.isfinite(speeds)].max(initial=0.0)
        omega = omega * (1.4 / speed if speed > 0 else 0.0)
        outline, length = _shape(trajectory, i)
        if isinstance(trajectory.model, HeavyTop):
            ax.plot([0, 0], [0, 0], [-1.5, 1.5], color="0.5", lw=0.8, ls="--")
        shape_line = ax.plot([], [], [], color="0.2", lw=1.0)[0]
        axis_lines = [ax.plot([], [], [], color=c, lw=2.0)[0] for c in ("tab:red", "tab:green", "tab:blue")]
        omega_line = ax.plot([], [], [], color="k", lw=2.5, label="omega")[0]
        ax.legend(fontsize=7, loc="upper left")

        def update(f, matrices=matrices, omega=omega, outline=outline, length=length,
                   shape_line=shape_line, axis_lines=axis_lines, omega_line=omega_line):  # fmt: skip
            rotated = outline @ matrices[f].T
            shape_line.set_data_3d(rotated[:, 0], rotated[:, 1], rotated[:, 2])
            # Arrays, not lists: a failed body's NaN samples are then left blank (matplotlib masks
            # NaN in arrays; in a list it fails on them).
            for j, line in enumerate(axis_lines):
                tip = length * matrices[f][:, j]
                line.set_data_3d(*np.stack([np.zeros(3), tip], axis=1))
            omega_line.set_data_3d(*np.stack([np.zeros(3), omega[f]], axis=1))

        updates.append(update)

    def draw(f):
        title.set_text(f"t = {t[picks[f]]:.4g} s")
        for update in updates:
            update(f)
        return []

    movie = mpl_animation.FuncAnimation(fig, draw, frames=len(picks), interval=1000 / fps, blit=False)
    extension = os.path.splitext(path)[1].lower()
    writer = (
        mpl_animation.PillowWriter(fps=fps) if extension == ".gif" else mpl_animation.FFMpegWriter(fps=fps)
    )
    directory, name = os.path.split(os.path.abspath(path))
    fd, scratch = tempfile.mkstemp(prefix=f".{name}.", suffix=extension, dir=directory)
    os.close(fd)
    try:
        movie.save(scratch, writer=writer, dpi=dpi)
        if os.path.isfile(path):  # an overwrite keeps the file's permissions
            os.chmod(scratch, os.stat(path).st_mode & 0o7777)
        else:
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(scratch, 0o666 & ~umask)
        os.replace(scratch, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(scratch)
        raise
    return path
