"""The scenes of ``rigidjax simulate``: heavy tops, torque-free bodies, the rigid Earth.

Each scene draws its parameters (NumPy float64) from ``numpy.random.default_rng(seed)``, builds the
rigidjax model of a block of bodies, analyses the block's trajectories, summarises the physics
against closed forms and draws its panels of the figure.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax
import numpy as np

import rigidjax as rj

from .common import counted

GRAVITY = 9.81  # m/s^2

# The rigid Earth (SI): its polar moment C, the equatorial A from the dynamical ellipticity
# H = (C - A) / C (IERS Conventions 2010; C - A is a small difference of large numbers, so A is
# derived rather than rounded on its own), sidereal rotation rate.
EARTH_C = 8.0365e37  # kg m^2
EARTH_H = 3.2737949e-3
EARTH_INERTIA = (EARTH_C * (1 - EARTH_H), EARTH_C * (1 - EARTH_H), EARTH_C)  # kg m^2
EARTH_OMEGA3 = 7.292115e-5  # rad/s
DAY = 86400.0  # s


def euler_rate(inertia=EARTH_INERTIA, omega3: float = EARTH_OMEGA3) -> float:
    """Closed-form free-wobble rate ``Omega = (C - A) / A * omega3`` of a symmetric top (rad/s)."""
    a, _, c = (float(x) for x in inertia)
    return (c - a) / a * omega3


# ---------------------------------------------------------------------------------------------
# The scene record and helpers.


@dataclasses.dataclass
class Scene:
    """A scene of ``rigidjax simulate``: its bodies and what to do with their trajectories."""

    name: str
    description: str
    params: dict  # name -> per-body arrays (leading axis N) or scalars; stored in the npz
    omega0: np.ndarray  # (N, 3)
    orientation0: np.ndarray | None  # (N, 4) or None (omega-only)
    make_model: Callable  # (params restricted to a block, dtype) -> rigidjax model
    analyze: Callable  # (ts, omega, euler or None, params of the block) -> dict of per-body arrays
    summarize: Callable  # (per-body results, ts, args) -> (summary rows (label, text), dict for JSON)
    plot: Callable  # (fig axes, ts, plot traces, per-body results) -> None
    plot_indices: np.ndarray  # bodies whose full-resolution traces are kept for the figure


def _quantile_indices(values: np.ndarray, qs=(0.05, 0.25, 0.5, 0.75, 0.95)) -> np.ndarray:
    order = np.argsort(values, kind="stable")
    picks = [order[min(len(order) - 1, int(q * len(order)))] for q in qs]
    return np.array(sorted(set(int(i) for i in picks)), dtype=np.int64)


def _quat_from_zxz(angles: np.ndarray) -> np.ndarray:
    """``rigidjax.quat_from_euler(angles, "zxz")`` as float64 NumPy, whatever the run's dtype."""
    with jax.enable_x64(True):
        return np.asarray(rj.quat_from_euler(np.asarray(angles, np.float64), "zxz"))


def block_params(params: dict, index: np.ndarray, n: int) -> dict:
    """The parameters of the bodies ``index``: per-body arrays (leading axis ``n``) indexed, the rest kept."""
    return {k: (v[index] if np.ndim(v) and np.shape(v)[0] == n else v) for k, v in params.items()}


def _heavy_top_scene(n: int, rng: np.random.Generator, symmetric: bool = False) -> Scene:
    """Toy tops on a pivot: I_perp ~ 1e-4 kg m^2 about the pivot, I3 = 0.5-0.7 I_perp, m ~ 0.1 kg,
    pivot-to-centre-of-mass l ~ 3 cm, so the sleeping-top spin is about 57 rad/s at the centre of
    the ranges; spins of 30-150 rad/s put a fifth or so of the tops below it. The tops are slightly
    asymmetric (I2/I1 up to 1.02); ``symmetric=True`` makes them Lagrange tops (I1 = I2), which
    have a closed form, with every other parameter the same."""
    i_perp = 1.0e-4 * rng.uniform(0.8, 1.2, n)
    asym = rng.uniform(0.0, 0.02, n) * (0.0 if symmetric else 1.0)  # I2/I1 - 1
    inertia = np.stack(
        [i_perp * (1 - asym / 2), i_perp * (1 + asym / 2), i_perp * rng.uniform(0.5, 0.7, n)], -1
    )
    mass = rng.uniform(0.09, 0.11, n)
    length = rng.uniform(0.025, 0.035, n)
    com = np.stack([np.zeros(n), np.zeros(n), length], -1)
    omega3 = rng.uniform(30.0, 150.0, n)
    theta0 = rng.uniform(0.05, 1.0, n)
    euler0 = np.stack([np.zeros(n), theta0, rng.uniform(0.0, 2 * np.pi, n)], -1)
    omega0 = np.stack([np.zeros(n), np.zeros(n), omega3], -1)
    orientation0 = _quat_from_zxz(euler0)
    params = {"inertia": inertia, "mass": mass, "com": com, "gravity": np.float64(GRAVITY), "euler0": euler0}

    def make_model(p, dtype):
        return rj.HeavyTop(
            np.asarray(p["inertia"], dtype),
            np.asarray(p["mass"], dtype),
            np.asarray(p["com"], dtype),
            gravity=np.asarray(p["gravity"], dtype),
        )

    def analyze(ts, omega, euler, p):
        theta = euler[..., 1]
        return {"theta_max": np.max(theta, axis=-1), "phi_end": euler[:, -1, 0] - euler[:, 0, 0]}

    def predictions():
        """Closed form for the symmetric top (I_perp = (I1 + I2)/2) released with theta' = phi' = 0:
        with u = cos(theta), the other turning point solves beta (1 - u^2) = a^2 (u0 - u)."""
        i_sym = 0.5 * (inertia[:, 0] + inertia[:, 1])
        mgl = mass * GRAVITY * length
        a2 = (inertia[:, 2] * omega3 / i_sym) ** 2
        beta = 2 * mgl / i_sym
        u0 = np.cos(theta0)
        disc = a2**2 - 4 * beta * a2 * u0 + 4 * beta**2
        u1 = 2 * (a2 * u0 - beta) / (a2 + np.sqrt(np.maximum(disc, 0.0)))
        sleeping = (inertia[:, 2] * omega3) ** 2 > 4 * i_sym * mgl
        # u' ^ 2 = beta (u0 - u)(u - u1)(u3 - u): theta reaches its turning point after half a
        # nutation period, 2 K(m) / sqrt(beta (u3 - u1)) with m = (u0 - u1) / (u3 - u1).
        u3 = (a2 + np.sqrt(np.maximum(disc, 0.0))) / (2 * beta)
        with jax.enable_x64(True):
            k = np.asarray(rj.elliptic.ellipk(np.clip((u0 - u1) / (u3 - u1), 0.0, 1.0)))
        half_period = 2 * k / np.sqrt(beta * (u3 - u1))
        return np.arccos(np.clip(u1, -1.0, 1.0)), sleeping, half_period

    theta_max_pred, sleeping, half_period = predictions()
    params["theta_max_pred"] = theta_max_pred
    params["sleeping_criterion"] = sleeping
    params["turning_time_pred"] = half_period

    def summarize(res, ts, args):
        theta_max = res["theta_max"]
        ok = res["success"]
        fell = (theta_max > np.pi / 2) & ok
        fell_pred = theta_max_pred > np.pi / 2
        # Only a top that reaches its turning point within the run shows its largest tilt, and only
        # samples at most an eighth of a nutation period apart show it: the largest sampled tilt is
        # then within 1 - cos(pi/8) = 8 % of the nutation's amplitude of the largest tilt.
        spacing = float(np.max(np.diff(ts))) if len(ts) > 1 else np.inf
        within_run = ok & (half_period <= ts[-1] - ts[0])
        reached = within_run & (spacing <= half_period / 4)
        agree = int(np.sum((fell == fell_pred) & reached))
        err = np.abs(theta_max - theta_max_pred)[reached]
        n_ok, n_reached = int(np.sum(ok)), int(np.sum(reached))
        unresolved = int(np.sum(within_run & ~reached))
        between = (
            f"between samples too far apart to show it ({spacing:.3g} s, over an eighth of their "
            "nutation period: more --samples)"
        )
        if n_reached:
            comparison = (
                f"{n_reached:,} of {n_ok:,} reach their turning point within the run, "
                f"{int(fell_pred[reached].sum()):,} of them predicted to fall; simulation agrees for "
                f"{agree:,} of {n_reached:,} (symmetric-top turning point, I_perp = (I1+I2)/2)"
                + (f"; {unresolved:,} more reach it {between}" if unresolved else "")
            )
        elif unresolved:
            comparison = f"nothing to compare: {unresolved:,} reach their turning point {between}"
        else:
            comparison = (
                f"no top reaches its turning point within the run (half a nutation period, the "
                f"shortest {np.min(half_period):.3g} s): nothing to compare"
            )
        rows = [
            (
                "upright / fell",
                f"{n_ok - int(fell.sum()):,} stayed above horizontal, {int(fell.sum()):,} fell "
                "(max theta > 90 deg at a sample: the centre of mass went below the pivot)",
            ),
            ("closed form", comparison),
            (
                "max theta error",
                f"median {np.median(err):.2e} rad vs closed form (sampled maximum of the tops that "
                f"reach their turning point{'' if symmetric else '; tops are up to 2% asymmetric'})"
                if err.size
                else "none to compare",
            ),
            (
                "sleeping criterion",
                f"(I3 w3)^2 > 4 I_perp m g l met by {int(sleeping.sum()):,}; fell: "
                f"{int((fell & sleeping).sum()):,} of those, "
                f"{int((fell & ~sleeping).sum()):,} of the {int((~sleeping).sum()):,} slower "
                "(it is a criterion for an upright start; these start tilted)",
            ),
        ]
        return rows, {
            "fell": int(fell.sum()),
            "fell_predicted": int(fell_pred.sum()),
            "reached_turning_point": n_reached,
            "fall_agreement": agree,
            "sleeping": int(sleeping.sum()),
        }

    def plot(axes, ts, traces, res):
        idx = plot_indices
        for k, i in enumerate(idx):
            label = f"w3={omega3[i]:.0f} rad/s, theta0={theta0[i]:.2f}"
            axes[0].plot(ts, traces["euler"][k, :, 1], lw=0.8, label=label)
            axes[1].plot(ts, traces["euler"][k, :, 0] - traces["euler"][k, 0, 0], lw=0.8, label=label)
        axes[0].axhline(np.pi / 2, color="k", lw=0.5, ls=":")
        axes[0].set(xlabel="t (s)", ylabel="nutation theta (rad)", title="Nutation of a few tops")
        axes[1].set(xlabel="t (s)", ylabel="precession phi - phi0 (rad)", title="Precession (unwrapped)")
        axes[0].legend(fontsize=6)

    plot_indices = _quantile_indices(omega3)
    return Scene(
        "heavy-top",
        f"{n:,} heavy top{'' if n == 1 else 's'} ({'symmetric' if symmetric else 'slightly asymmetric'}, "
        "spin 30-150 rad/s, "
        "tilt 0.05-1 rad)",
        params,
        omega0,
        orientation0,
        make_model,
        analyze,
        summarize,
        plot,
        plot_indices,
    )


def _free_scene(n: int, rng: np.random.Generator) -> Scene:
    """Torque-free asymmetric bodies (solid ellipsoids, 1 kg, semi-axes 0.1-2 m), each spun within
    1e-3-1e-1 rad of one principal axis: minor, intermediate (the tennis-racket flip) or major."""
    c = rng.uniform(1.0, 2.0, n)
    b = c * rng.uniform(0.4, 0.8, n)
    a = b * rng.uniform(0.25, 0.75, n)
    inertia = np.sort(np.stack([b**2 + c**2, a**2 + c**2, a**2 + b**2], -1) / 5.0, axis=-1)
    axis = rng.integers(0, 3, n)
    speed = rng.uniform(2.0, 20.0, n)
    delta = 10.0 ** rng.uniform(-3.0, -1.0, n)
    beta = rng.uniform(0.0, 2 * np.pi, n)
    unit = np.zeros((n, 3))
    rows = np.arange(n)
    unit[rows, axis] = np.cos(delta)
    unit[rows, (axis + 1) % 3] = np.sin(delta) * np.cos(beta)
    unit[rows, (axis + 2) % 3] = np.sin(delta) * np.sin(beta)
    omega0 = speed[:, None] * unit
    q = rng.normal(size=(n, 4))
    orientation0 = q / np.linalg.norm(q, axis=-1, keepdims=True)
    params = {"inertia": inertia, "spin_axis": axis, "orientation0": orientation0}

    def make_model(p, dtype):
        return rj.FreeBody(np.asarray(p["inertia"], dtype))

    def analyze(ts, omega, euler, p):
        k = np.asarray(p["spin_axis"])
        main = np.take_along_axis(omega, k[:, None, None], axis=-1)[..., 0]
        flipped = main * main[:, :1] < 0
        first = np.where(flipped.any(-1), ts[np.argmax(flipped, axis=-1)], np.nan)
        return {"flipped": flipped.any(-1), "first_flip_time": first}

    def summarize(res, ts, args):
        flipped = res["flipped"] & res["success"]
        rows = []
        names = ("minor", "intermediate", "major")
        for k, name in enumerate(names):
            sel = axis == k
            note = "unstable: flips expected" if k == 1 else "stable: no flips expected"
            rows.append(
                (
                    f"spun near {name}",
                    f"{counted(int(sel.sum()), 'body', 'bodies')}, {int(flipped[sel].sum()):,} flipped "
                    f"({note})",
                )
            )
        intermediate = axis == 1
        if intermediate.any() and len(ts) > 1:
            # The main component is reversed for about half of each period: sparser samples miss flips.
            with jax.enable_x64(True):
                period = np.asarray(rj.torque_free_period(inertia[intermediate], omega0[intermediate]))
            spacing = float(ts[1] - ts[0])
            if spacing > 0.25 * np.median(period):
                rows.append(
                    (
                        "flip detection",
                        f"samples {spacing:.3g} s apart, over a quarter of the median wobble period of "
                        f"{np.median(period):.3g} s: flips can fall between samples (more --samples)",
                    )
                )
        inter = flipped & intermediate
        if inter.any():
            rows.append(
                (
                    "first flip time",
                    f"median {np.nanmedian(res['first_flip_time'][inter]):.2f} s "
                    "(intermediate-axis spins that flipped)",
                )
            )
        extra = {f"flipped_{name}": int(flipped[axis == k].sum()) for k, name in enumerate(names)}
        return rows, extra

    def plot(axes, ts, traces, res):
        for k, i in enumerate(plot_indices):
            w = traces["omega"][k] / np.linalg.norm(omega0[i])
            target = axes[0] if axis[i] == 1 else axes[1]
            name = names[axis[i]]
            target.plot(
                ts, w[:, axis[i]], lw=0.8, label=f"{name} axis {axis[i] + 1}, |w0|={speed[i]:.1f} rad/s"
            )
        axes[0].set(xlabel="t (s)", ylabel="w2 / |w0|", title="Spins near the intermediate axis (flips)")
        axes[1].set(
            xlabel="t (s)", ylabel="w about the spin axis / |w0|", title="Spins near the minor or major axis"
        )
        for ax, near in zip(axes[:2], ("intermediate", "minor or major"), strict=True):
            if ax.lines:
                ax.legend(fontsize=6)
            else:  # no body of this run was spun near these axes
                ax.text(0.5, 0.5, f"no body of this run\nwas spun near the {near} axis", ha="center",
                        va="center", transform=ax.transAxes, color="0.4")  # fmt: skip

    names = ("minor", "intermediate", "major")
    inter = np.flatnonzero(axis == 1)
    minor, major = np.flatnonzero(axis == 0), np.flatnonzero(axis == 2)
    # One spin near the minor axis and one near the major, where the run has both.
    stable = (
        (minor[:1].tolist() + major[:1].tolist())
        if minor.size and major.size
        else (minor[:2].tolist() + major[:2].tolist())
    )
    plot_indices = np.array(sorted(set(inter[:3].tolist() + stable)), dtype=np.int64)
    return Scene(
        "free",
        f"{n:,} torque-free asymmetric bod{'y' if n == 1 else 'ies'} spun near a principal axis",
        params,
        omega0,
        orientation0,
        make_model,
        analyze,
        summarize,
        plot,
        plot_indices,
    )


def _earth_scene(n: int, rng: np.random.Generator) -> Scene:
    """The rigid Earth: n copies with different free-wobble amplitudes (1e-11-1e-10 rad/s, i.e. the
    rotation axis 0.03-0.3 arcsec from the figure axis) and phases; omega-only (Euler's equations)."""
    inertia = np.broadcast_to(np.array(EARTH_INERTIA), (n, 3)).copy()
    amp = 10.0 ** rng.uniform(-11.0, -10.0, n)
    phase = rng.uniform(0.0, 2 * np.pi, n)
    omega0 = np.stack([amp * np.cos(phase), amp * np.sin(phase), np.full(n, EARTH_OMEGA3)], -1)
    rate = euler_rate()
    params = {"inertia": inertia}

    def make_model(p, dtype):
        return rj.FreeBody(np.asarray(p["inertia"], dtype))

    def analyze(ts, omega, euler, p):
        angle = np.unwrap(np.arctan2(omega[..., 1], omega[..., 0]), axis=-1)
        t = ts - ts[0]
        tc = t - t.mean()
        slope = ((angle - angle.mean(-1, keepdims=True)) @ tc) / (tc @ tc)  # least-squares rate
        period = 2 * np.pi / np.abs(slope)
        amplitude = np.hypot(omega[..., 0], omega[..., 1])  # conserved for a symmetric top
        drift = np.max(np.abs(amplitude - amplitude[:, :1]), axis=-1) / amplitude[:, 0]
        return {"wobble_period": period, "wobble_amplitude_drift": drift}

    def summarize(res, ts, args):
        ok = res["success"]
        closed = 2 * np.pi / rate
        cycles = (ts[-1] - ts[0]) * rate / (2 * np.pi)
        rows = [
            (
                "closed form",
                f"2 pi / Omega = {closed:.9e} s = {closed / DAY:.4f} days, "
                f"Omega = (C - A)/A w3 = {rate:.6e} rad/s",
            )
        ]
        extra = {"wobble_period_closed_form": closed}
        if 2 * np.pi * cycles / (len(ts) - 1) > 2.0:
            rows.append(
                (
                    "wobble period",
                    f"not measured: {len(ts)} samples are too few for {cycles:.1f} "
                    "wobble cycles (need < 2 rad of wobble per sample)",
                )
            )
            return rows, extra
        period = res["wobble_period"][ok]
        rel = np.abs(period / closed - 1.0)
        rows.append(
            (
                "wobble period",
                f"{np.mean(period):.9e} s = {np.mean(period) / DAY:.4f} days "
                f"(mean over {len(period):,} Earths, fit over {cycles:.2f} cycles)",
            )
        )
        rows.append(
            ("period rel. error", f"max {np.max(rel):.2e}, mean {np.mean(rel):.2e} vs the closed form")
        )
        rows.append(
            (
                "wobble amp. drift",
                f"max {np.max(res['wobble_amplitude_drift'][ok]):.2e} (relative; |w1 + i w2| "
                "is conserved for a symmetric top)",
            )
        )
        rows.append(("note", "the observed Chandler wobble is ~433 days: the real Earth is not rigid"))
        extra.update(wobble_period=float(np.mean(period)), wobble_period_max_rel_error=float(np.max(rel)))
        return rows, extra

    def plot(axes, ts, traces, res):
        days = ts / DAY
        for k, i in enumerate(plot_indices):
            w = traces["omega"][k]
            axes[0].plot(days, w[:, 0] * 1e11, lw=0.8, label=f"w1, Earth {i}")
            axes[0].plot(days, w[:, 1] * 1e11, lw=0.8, ls="--", label=f"w2, Earth {i}")
            axes[1].plot(w[:, 0] * 1e11, w[:, 1] * 1e11, lw=0.8)
        axes[0].set(xlabel="t (days)", ylabel="w (1e-11 rad/s)", title="Free wobble of the rigid Earth")
        axes[1].set(
            xlabel="w1 (1e-11 rad/s)", ylabel="w2 (1e-11 rad/s)", title="Polhode (body frame)", aspect="equal"
        )
        axes[0].legend(fontsize=6)

    plot_indices = _quantile_indices(amp, qs=(0.5, 0.95))
    return Scene(
        "earth",
        f"{n:,} rigid Earth{'' if n == 1 else 's'} (SI units), free wobble of 1e-11-1e-10 rad/s",
        params,
        omega0,
        None,
        make_model,
        analyze,
        summarize,
        plot,
        plot_indices,
    )


SCENE_BUILDERS = {"heavy-top": _heavy_top_scene, "free": _free_scene, "earth": _earth_scene}
# Defaults per scene: bodies, duration (s), samples.
SCENE_DEFAULTS = {
    "heavy-top": (10_000, 5.0, 200),
    "free": (10_000, 5.0, 200),
    "earth": (100, 3 * 2 * math.pi / euler_rate(), 200),
}
