"""Static figures of a trajectory: the Poinsot construction, the body and space cones, Euler angles
and the drift of the conserved quantities."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from .._integrate.trajectory import _unwrapped_euler_angles
from .._kinematics.euler import _parse_seq
from . import data

_MAX_SEPARATE_BODIES = 8  # invariant_drift draws more bodies than this as their worst case


def _new_figure(fig, figsize):
    if fig is None:
        return plt.figure(figsize=figsize)
    if not isinstance(fig, Figure):
        raise TypeError(
            f"fig must be a matplotlib Figure (or None for a new one), got {type(fig).__name__}"
            + ("; for an Axes pass its .figure" if isinstance(fig, Axes) else "")
        )
    fig.clear()
    return fig


def _unit_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors that, with the unit ``normal``, make a right-handed orthonormal basis."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def _energy_ellipsoid(inertia: np.ndarray, two_energy: float, n: int = 25):
    """Grid points of ``omega . I omega = 2E`` (a full tensor is fine): each unit direction ``u``
    scaled by ``sqrt(2E / u . I u)``."""
    theta, phi = np.meshgrid(np.linspace(0, np.pi, n), np.linspace(0, 2 * np.pi, 2 * n))
    u = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    r = np.sqrt(two_energy / np.einsum("...i,ij,...j->...", u, inertia, u))
    points = u * r[..., None]
    return points[..., 0], points[..., 1], points[..., 2]


def _equal_3d(ax, points: np.ndarray) -> None:
    half = np.nanmax(np.abs(points)) * 1.05
    ax.set(xlim=(-half, half), ylim=(-half, half), zlim=(-half, half))
    ax.set_box_aspect((1, 1, 1))


def _body_label(trajectory, i: int) -> str:
    return "" if data.n_bodies(trajectory) == 1 else f" (body {i})"


def poinsot(trajectory, body=0, *, fig=None):
    """Poinsot's construction of a torque-free body: the polhode on the energy ellipsoid and the
    herpolhode on the invariable plane.

    The left panel (3-D, body frame) draws the energy ellipsoid ``omega . I omega = 2E`` and on it
    the polhode, the path of the body-frame ``omega``; torque-free, the polhode is also on the
    momentum sphere ``|I omega| = |L|``, and it is the ellipsoid's intersection with it. The right
    panel (2-D, space frame) draws the herpolhode, the path of the tip of the space-frame ``omega``
    in the invariable plane: the plane perpendicular to ``L`` at the distance ``2E / |L|`` from the
    fixed point, on which the ellipsoid rolls without slipping. Its axes are two orthonormal
    directions of the plane; the origin is where ``L`` pierces it.

    **Arguments:**

    - `trajectory`: a :class:`rigidjax.Trajectory` of a torque-free rigid body (a
      :class:`rigidjax.FreeBody`, or a :class:`rigidjax.RigidBody` without torques) simulated with
      orientations. (A gyrostat's rotors break the construction: its ``omega`` does not stay in a
      fixed plane.)
    - `body`: the body to draw, an index into the flattened batch (``0`` for a single body;
      negative indices count from the end).
    - `fig`: a matplotlib Figure to draw into (it is cleared first); a new one by default.

    **Returns:**

    The matplotlib Figure, with two axes: the polhode's (3-D) and the herpolhode's. Raises
    ``ValueError`` naming `body` when it is not an index of the batch or does not rotate (no
    invariable plane), and naming `trajectory` when its scene has torques or it has no orientations.
    """
    data.check_trajectory(trajectory, "poinsot")
    if not trajectory.model.torque_free:
        raise ValueError(
            "poinsot: Poinsot's construction is for a torque-free rigid body (a FreeBody, or a "
            f"RigidBody without torques); the trajectory's scene is a {type(trajectory.model).__name__} "
            "with torques, a field or rotors."
        )
    data.need_orientation(trajectory, "poinsot")
    i = data.body_index(trajectory, body)
    omega = data.omega(trajectory, i)
    inertia = data.inertia(trajectory, i)
    two_energy = 2 * data.per_body(trajectory.kinetic_energy(), trajectory, 1)[i][0]
    momentum = data.per_body(trajectory.space_angular_momentum(), trajectory, 2)[i][0]
    if not np.all(np.isfinite(momentum)):
        raise ValueError(
            f"poinsot: body {i} failed from its first sample (trajectory.success is False and its "
            "state is not finite): there is no motion to draw."
        )
    if not np.linalg.norm(momentum) > 0:
        raise ValueError(
            f"poinsot: body {i} does not rotate (angular momentum {np.linalg.norm(momentum):.3g}): "
            "without angular momentum there is no invariable plane to draw."
        )
    normal = momentum / np.linalg.norm(momentum)
    omega_space = data.to_space(data.orientation(trajectory, i), omega)
    e1, e2 = _unit_basis(normal)

    fig = _new_figure(fig, (11, 5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    ellipsoid = _energy_ellipsoid(inertia, two_energy)
    ax.plot_wireframe(*ellipsoid, color="0.6", lw=0.3, alpha=0.5)
    ax.plot(omega[:, 0], omega[:, 1], omega[:, 2], color="C3", lw=1.5, label="polhode")
    ax.scatter(*omega[0], color="C3", s=15)
    _equal_3d(ax, np.stack(ellipsoid, axis=-1))  # the polhode lies on the ellipsoid
    ax.set(xlabel="omega_1 (rad/s)", ylabel="omega_2 (rad/s)", zlabel="omega_3 (rad/s)")
    ax.set_title("Polhode on the energy ellipsoid (body frame)" + _body_label(trajectory, i))

    ax2 = fig.add_subplot(1, 2, 2)
    ax2.plot(omega_space @ e1, omega_space @ e2, color="C0", lw=1.0, label="herpolhode")
    ax2.plot([0], [0], "k+", label="L pierces the plane")
    ax2.set(
        xlabel="omega along e1 (rad/s)",
        ylabel="omega along e2 (rad/s)",
        aspect="equal",
        title=f"Herpolhode on the invariable plane (2E/|L| = {two_energy / np.linalg.norm(momentum):.4g})",
    )
    ax2.legend(fontsize=8)
    fig.tight_layout()
    return fig


def cones(trajectory, body=0, *, fig=None):
    """The body cone and the space cone: the directions of ``omega`` in the body and in space.

    The left panel (3-D) draws the unit vector ``omega / |omega|`` in body-frame components over
    time, its path on the unit sphere and a few of the generators from the origin (the body cone),
    with the body axes. The right panel draws the same direction in space-frame components (the
    space cone) with the direction of the space-frame angular momentum ``L`` at the first sample.
    For a torque-free symmetric body both are circular cones, and the body cone rolls on the space
    cone.

    **Arguments:**

    - `trajectory`: a :class:`rigidjax.Trajectory` simulated with orientations (any scene).
    - `body`: the body to draw, an index into the flattened batch (negative indices count from
      the end).
    - `fig`: a matplotlib Figure to draw into (it is cleared first); a new one by default.

    **Returns:**

    The matplotlib Figure, with two 3-D axes (body cone, space cone). Raises ``ValueError`` naming
    `body` for an index outside the batch, naming `trajectory` when it has no orientations.
    Samples where ``omega`` is zero or not finite are left out.
    """
    data.check_trajectory(trajectory, "cones")
    data.need_orientation(trajectory, "cones")
    i = data.body_index(trajectory, body)
    omega = data.omega(trajectory, i)
    omega_space = data.to_space(data.orientation(trajectory, i), omega)
    momentum = data.per_body(trajectory.space_angular_momentum(), trajectory, 2)[i][0]

    fig = _new_figure(fig, (11, 5))
    panels = (
        ("Body cone (body frame)", omega, "e", np.eye(3)),
        ("Space cone (space frame)", omega_space, "X", None),
    )
    for k, (title, vectors, prefix, axes_lines) in enumerate(panels):
        norm = np.linalg.norm(vectors, axis=-1, keepdims=True)
        good = (norm[:, 0] > 0) & np.all(np.isfinite(vectors), axis=-1)
        unit = vectors[good] / norm[good]
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.plot(unit[:, 0], unit[:, 1], unit[:, 2], color="C3", lw=1.5, label="omega / |omega|")
        picks = unit[np.linspace(0, len(unit) - 1, min(len(unit), 24)).astype(int)]
        segments = np.concatenate([np.zeros_like(picks), picks, np.full_like(picks, np.nan)], 1)
        ax.plot(*segments.reshape(-1, 3).T, color="C3", lw=0.4, alpha=0.6)
        if axes_lines is not None:
            for j, color in enumerate(("C0", "C2", "C1")):
                ax.plot(*np.stack([np.zeros(3), axes_lines[j]]).T, color=color, lw=1.0, label=f"e{j + 1}")
        elif np.all(np.isfinite(momentum)) and np.any(momentum != 0):
            direction = momentum / np.linalg.norm(momentum)
            ax.plot(*np.stack([np.zeros(3), direction]).T, color="k", lw=1.2, label="L / |L|")
        ax.set(xlim=(-1, 1), ylim=(-1, 1), zlim=(-1, 1))
        ax.set_box_aspect((1, 1, 1))
        ax.set(xlabel=f"{prefix}1", ylabel=f"{prefix}2", zlabel=f"{prefix}3")
        ax.set_title(title + _body_label(trajectory, i))
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return fig


def euler_angles(trajectory, body=0, sequence: str = "zxz", *, fig=None):
    """The Euler angles ``phi``, ``theta``, ``psi`` of one body over time, one panel each.

    The angles are :func:`rigidjax.euler_from_quat` of the trajectory's orientations in the given
    sequence, unwrapped in time (as :meth:`rigidjax.Trajectory.euler_angles`: each step on the branch
    the Euler rates predict) so that an angle that keeps turning (precession, spin) is drawn
    continuously over many turns rather than jumping by ``2 pi``. For the default
    ``"zxz"`` sequence they are the precession, the nutation and the spin.

    **Arguments:**

    - `trajectory`: a :class:`rigidjax.Trajectory` simulated with orientations.
    - `body`: the body to draw, an index into the flattened batch (negative indices count from
      the end).
    - `sequence`: one of the twelve sequences of ``rigidjax.kinematics.SEQUENCES`` (default
      ``"zxz"``).
    - `fig`: a matplotlib Figure to draw into (it is cleared first); a new one by default.

    **Returns:**

    The matplotlib Figure, with three axes sharing the time axis (``phi``, ``theta``, ``psi``, in
    rad). Raises ``ValueError`` naming `body` for an index outside the batch, naming `trajectory`
    when it has no orientations, and for an unknown `sequence`. Samples whose orientation is not
    finite (a failed body) are left out.
    """
    data.check_trajectory(trajectory, "euler_angles")
    _parse_seq(sequence, "sequence")
    data.need_orientation(trajectory, "euler_angles")
    i = data.body_index(trajectory, body)
    q = data.orientation(trajectory, i)
    t = data.ts(trajectory, i)
    good = np.all(np.isfinite(q), axis=-1)
    angles = np.asarray(_unwrapped_euler_angles(q[good], data.omega(trajectory, i)[good], t[good], sequence))
    fig = _new_figure(fig, (8, 7))
    axes = fig.subplots(3, 1, sharex=True)
    names = ("phi", "theta", "psi")
    for k, ax in enumerate(axes):
        ax.plot(t[good], angles[:, k], color=f"C{k}", lw=1.0)
        ax.set_ylabel(f"{names[k]} (rad)")
    axes[-1].set_xlabel("t (s)")
    axes[0].set_title(f"Euler angles, sequence {sequence}, unwrapped" + _body_label(trajectory, i))
    fig.tight_layout()
    return fig


def _drift_series(trajectory) -> dict[str, np.ndarray]:
    """Per conserved quantity of the scene, the relative drift ``|x(t) - x(0)| / scale`` per body and
    sample, (N, T), with the scales of :meth:`rigidjax.Trajectory.invariants`."""
    model = trajectory.model
    out = {}

    def flat(values, core=1):
        return data.per_body(values, trajectory, core).astype(np.float64)

    def relative(x, scale):
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.abs(x - x[:, :1]) / np.maximum(scale, np.finfo(np.float64).tiny)[:, None]

    if model.conserves_energy:
        e = flat(trajectory.energy())
        kinetic0 = flat(trajectory.kinetic_energy())[:, 0]
        potential0 = np.abs(flat(trajectory.potential_energy())[:, 0])
        out["energy"] = relative(e, np.maximum(np.abs(e[:, 0]), kinetic0 + potential0))
    momentum = flat(trajectory.angular_momentum(), 2)
    norm = np.linalg.norm(momentum, axis=-1)
    if model.conserves_angular_momentum:
        out["|L|"] = relative(norm, norm[:, 0])
        if trajectory.orientation is not None:
            space = flat(trajectory.space_angular_momentum(), 2)
            with np.errstate(divide="ignore", invalid="ignore"):
                out["space-frame L"] = np.linalg.norm(space - space[:, :1], axis=-1) / norm[:, :1]
    if model.conserves_vertical_angular_momentum and trajectory.orientation is not None:
        vertical = flat(trajectory.space_angular_momentum(), 2)[..., 2]
        out["L_z"] = relative(vertical, norm[:, 0])
    return out


def invariant_drift(trajectory, bodies=None, *, ax=None):
    """The relative drift of the quantities the scene conserves, over time, on a log scale.

    The quantities are those of :meth:`rigidjax.Trajectory.invariants`, from the scene's own
    definitions (the total energy with the potential of a :class:`rigidjax.HeavyTop`, the angular
    momentum with a :class:`rigidjax.Gyrostat`'s rotors): ``energy`` where the scene conserves it,
    ``|L|`` and the space-frame ``L`` (``|L(t) - L(0)| / |L(0)|``) for torque-free scenes, ``L_z``
    (the vertical space-frame component, relative to ``|L(0)|``) for a heavy top. Each is
    ``|x(t) - x(0)|`` over the scale that :meth:`~rigidjax.Trajectory.invariants` uses; values
    below a hundredth of the dtype's epsilon (zero, at ``t = 0``) are drawn at that floor.

    **Arguments:**

    - `trajectory`: a :class:`rigidjax.Trajectory`.
    - `bodies`: the bodies to draw, indices into the flattened batch; by default every body, each
      in its own lines when there are at most 8, otherwise the worst over all bodies at each
      sample. Bodies that failed (``trajectory.success`` False) are left out of the worst case, and
      its label counts them; drawn by index, a failed body's lines end where it failed.
    - `ax`: a matplotlib Axes to draw into; a new figure by default.

    **Returns:**

    The matplotlib Figure. Raises ``ValueError`` naming `bodies` for an index outside the batch,
    and naming `trajectory` when its scene conserves none of these quantities (torques that are
    not conservative).
    """
    data.check_trajectory(trajectory, "invariant_drift")
    series = _drift_series(trajectory)
    if not series:
        raise ValueError(
            "invariant_drift: the trajectory's scene conserves neither energy nor angular momentum "
            f"({type(trajectory.model).__name__} with non-conservative torques); there is no drift to draw."
        )
    n = data.n_bodies(trajectory)
    if bodies is None:
        chosen = list(range(n)) if n <= _MAX_SEPARATE_BODIES else None
    else:
        if np.ndim(bodies) == 0:
            bodies = [bodies]
        chosen = [data.body_index(trajectory, b, "bodies") for b in bodies]
        if not chosen:
            raise ValueError("bodies is empty; give at least one body index, or None for all.")
    floor = float(np.finfo(np.asarray(trajectory.omega).dtype).eps) / 100
    t = data.ts(trajectory)
    if ax is None:
        fig, ax = plt.subplots(figsize=(8, 4.5))
    elif not isinstance(ax, Axes):
        raise TypeError(f"ax must be a matplotlib Axes (or None for a new figure), got {type(ax).__name__}")
    success = data.per_body(trajectory.success, trajectory, 0)
    failed = int(np.sum(~success))
    for k, (name, values) in enumerate(series.items()):
        if chosen is None:
            # A failed body's NaN rows would hide in nanmax: it is counted apart, and drawn by index.
            drawn = n - failed
            counted = f"worst of {drawn} {'body' if drawn == 1 else 'bodies'}"
            counted += f"; {failed} failed, not drawn" if failed else ""
            if failed < n:
                worst = np.nanmax(values[success], axis=0)
                ax.plot(t, np.maximum(worst, floor), color=f"C{k}", lw=1.0, label=f"{name} ({counted})")
            else:
                ax.plot([], [], color=f"C{k}", label=f"{name} (all {n} bodies failed)")
            continue
        for j, i in enumerate(chosen):
            label = name if len(chosen) == 1 and n == 1 else f"{name}, body {i}"
            label += "" if success[i] else " (failed: drawn until it did)"
            ax.plot(t, np.maximum(values[i], floor), color=f"C{k}", lw=1.0, alpha=1.0 - 0.6 * j / len(chosen),
                    ls=("-", "--", ":", "-.")[j % 4], label=label)  # fmt: skip
    ax.set(yscale="log", xlabel="t (s)", ylabel="relative drift", title="Drift of the conserved quantities")
    ax.legend(fontsize=7)
    return ax.figure
