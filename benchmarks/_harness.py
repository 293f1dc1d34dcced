"""The harness of the benchmarks in this directory: the tennis-racket scene, an extended-precision
reference, the methods compared (rigidjax's and its peers'), the timing rule, the run metadata and
the reading of the results (time to reach an error, the performance targets, the tables).

Scripts run as ``python benchmarks/<name>.py``, so this directory is on ``sys.path`` and they
``import _harness``; rigidjax is used through its public names only.

Scene: N torque-free bodies with principal moments I_k = (1, 2, 2.5) (1 + 0.05 u_k),
u_k ~ U(-1, 1)^3, then omega0_k = (0.05, 4, 0.05) + 0.01 n_k, n_k ~ N(0, 1)^3, both from
``numpy.random.default_rng(0)``; identity orientation; T = 20 s (several tennis-racket flips).

Errors at t = T, per body, against a float64 reference: relative omega error
``|omega - omega_ref| / |omega_ref|``, orientation error angle (rad) of ``conj(q_ref) (x) q``, and
relative energy drift ``|E(T) - E(0)| / E(0)``; each reported as max and median over bodies.

Timing (wall seconds): a first call (trace + compile + run), then ``repeats`` calls, each with
``block_until_ready``; run time is their median and compile time is (first call - median), booked
on the first method of a compile group (a new rtol of the same solver is a traced array in
``simulate`` and does not recompile).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

import rigidjax as rj

T_END = 20.0  # s
BASE_MOMENTS = (1.0, 2.0, 2.5)
BASE_OMEGA = (0.05, 4.0, 0.05)  # rad/s


def reference_scene(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tennis-racket scene as float64 NumPy: inertia (N, 3), omega0 (N, 3) rad/s, q0 (N, 4)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1.0, 1.0, size=(n, 3))
    inertia = np.array(BASE_MOMENTS) * (1.0 + 0.05 * u)
    omega0 = np.array(BASE_OMEGA) + 0.01 * rng.standard_normal(size=(n, 3))
    q0 = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (n, 1))
    return inertia, omega0, q0


def separatrix_distance(inertia: np.ndarray, omega0: np.ndarray) -> np.ndarray:
    """s = (|L|^2 - 2 E I_mid) / |L|^2 per body (0 on the separatrix; roundoff grows like 1/|s|)."""
    L = inertia * omega0
    two_e = np.sum(inertia * omega0**2, axis=-1)
    l2 = np.sum(L * L, axis=-1)
    return (l2 - two_e * np.sort(inertia, axis=-1)[:, 1]) / l2


def quat_angle(q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) between orientations ``q`` and ``q_ref`` (..., 4), sign-insensitive."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    r = q_ref / np.linalg.norm(q_ref, axis=-1, keepdims=True)
    w = np.sum(q * r, axis=-1)
    # vector part of conj(r) (x) q
    v = r[..., :1] * q[..., 1:] - q[..., :1] * r[..., 1:] - np.cross(r[..., 1:], q[..., 1:])
    return 2.0 * np.arctan2(np.linalg.norm(v, axis=-1), np.abs(w))


def body_errors(inertia, omega0, omega, q, omega_ref, q_ref) -> dict[str, np.ndarray]:
    """Per-body errors at t = T: ``rel_omega``, ``angle`` (rad; None if ``q`` is None), ``energy``
    (relative drift)."""
    omega = np.asarray(omega, np.float64)
    e0 = np.sum(inertia * omega0**2, axis=-1)
    return {
        "rel_omega": np.linalg.norm(omega - omega_ref, axis=-1) / np.linalg.norm(omega_ref, axis=-1),
        "angle": None if q is None else quat_angle(np.asarray(q, np.float64), q_ref),
        "energy": np.abs(np.sum(inertia * omega**2, axis=-1) - e0) / e0,
    }


# ---------------------------------------------------------------------------------------------
# Methods: each is a zero-argument callable returning (omega(T) (N, 3), q(T) (N, 4)).


@dataclasses.dataclass
class Method:
    """One point of the work-precision plot.

    ``family`` groups the points of one curve; ``kind`` is ``"rigidjax"`` (presets, closed form,
    structure-preserving solvers, diffrax solvers through ``simulate``), ``"peer"`` (what a user
    would otherwise write) or ``"reference"``; ``integrator`` is False for the closed form.
    ``subset``: the bodies it runs on (per-body peers such as scipy run on a few); its time is then
    scaled by N / len(subset). ``group``: methods of one group share one compiled program.
    ``fn`` returns what the method computes as it computes it (a whole trajectory, a state array);
    ``at_end`` takes omega and q at T from that on the host, outside the timed call, so that every
    method's time is its own computation and not the eager indexing of its output.
    """

    family: str
    setting: str
    fn: Callable[[], tuple]
    group: str
    dtype: str = "float64"
    kind: str = "rigidjax"
    integrator: bool = True
    subset: np.ndarray | None = None
    subset_note: str = "random"
    at_end: Callable[[object], tuple] = lambda out: out


def _jnp_inputs(inertia, omega0, q0, dtype):
    import jax.numpy as jnp

    dt = {"float64": jnp.float64, "float32": jnp.float32}[dtype]
    return (
        jnp.asarray(inertia, dt),
        jnp.asarray(omega0, dt),
        jnp.asarray(q0, dt),
        jnp.asarray([0.0, T_END], dt),
    )


def simulate_method(
    scene,
    family: str,
    setting: str,
    group: str,
    dtype: str = "float64",
    subset: np.ndarray | None = None,
    omega_only: bool = False,
    **kwargs,
) -> Method:
    """``rigidjax.simulate(FreeBody(I), State(omega0, q0), [0, T], **kwargs)``, state at t = T;
    on the bodies ``subset`` only if given; without the orientation if ``omega_only``."""
    part = scene if subset is None else tuple(x[subset] for x in scene)
    inertia, omega0, q0, ts = _jnp_inputs(*part, dtype)
    model, state0 = rj.FreeBody(inertia), rj.State(omega0, None if omega_only else q0)

    def fn():
        traj = rj.simulate(model, state0, ts, **kwargs)
        return traj.omega, traj.orientation

    def at_end(out):
        omega, q = out
        return np.asarray(omega)[:, -1], None if q is None else np.asarray(q)[:, -1]

    return Method(
        family,
        setting,
        fn,
        group,
        dtype,
        integrator=kwargs.get("accuracy") != "exact",
        subset=subset,
        subset_note="incl. the 100 nearest the separatrix",
        at_end=at_end,
    )


def sensitive_subset(scene, size: int, n_sensitive: int = 100, seed: int = 4) -> np.ndarray:
    """``size`` bodies: the ``n_sensitive`` nearest the separatrix and a random rest (sorted
    indices), so that a method run on a subset still meets the worst-conditioned bodies."""
    n = scene[0].shape[0]
    if size >= n:
        return np.arange(n)
    order = np.argsort(np.abs(separatrix_distance(scene[0], scene[1])))
    k = min(n_sensitive, size)
    rest = np.random.default_rng(seed).choice(order[k:], size - k, replace=False)
    return np.sort(np.concatenate([order[:k], rest]))


_PROGRAMS: dict[str, Callable] = {}


def _rk4_program():
    """Hand-written fixed-step RK4 over the whole batch, state laid out (7, N) (bodies last)."""
    if "rk4" not in _PROGRAMS:
        import jax

        def rhs(y, c):
            w1, w2, w3, q0, q1, q2, q3 = y
            c1, c2, c3 = c
            return jax.numpy.stack(
                [
                    c1 * w2 * w3,
                    c2 * w3 * w1,
                    c3 * w1 * w2,
                    0.5 * (-q1 * w1 - q2 * w2 - q3 * w3),
                    0.5 * (q0 * w1 + q2 * w3 - q3 * w2),
                    0.5 * (q0 * w2 - q1 * w3 + q3 * w1),
                    0.5 * (q0 * w3 + q1 * w2 - q2 * w1),
                ]
            )

        @jax.jit
        def rk4(y, c, dt, n_steps):
            def step(_, y):
                k1 = rhs(y, c)
                k2 = rhs(y + (0.5 * dt) * k1, c)
                k3 = rhs(y + (0.5 * dt) * k2, c)
                k4 = rhs(y + dt * k3, c)
                return y + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

            return jax.lax.fori_loop(0, n_steps, step, y)

        _PROGRAMS["rk4"] = rk4
    return _PROGRAMS["rk4"]


def rk4_method(scene, dt: float, dtype: str = "float64") -> Method:
    """Fixed-step RK4 written by hand: ``fori_loop`` over a (7, N) state, c_1 = (I2 - I3)/I1 (cyclic)."""
    import jax.numpy as jnp

    inertia, omega0, q0 = scene
    i1, i2, i3 = inertia.T
    c = np.stack([(i2 - i3) / i1, (i3 - i1) / i2, (i1 - i2) / i3])
    jd = {"float64": jnp.float64, "float32": jnp.float32}[dtype]
    y0 = jnp.asarray(np.concatenate([omega0.T, q0.T]), jd)
    c = jnp.asarray(c, jd)
    n_steps = round(T_END / dt)
    h = jnp.asarray(T_END / n_steps, jd)
    rk4 = _rk4_program()

    def fn():
        return rk4(y0, c, h, n_steps)

    def at_end(y):
        y = np.asarray(y)
        return y[:3].T, y[3:].T

    return Method("hand RK4 (7,N)", f"dt={dt:g}", fn, f"rk4-{dtype}", dtype, kind="peer", at_end=at_end)


def peer_vector_field(t, y, inertia):
    """The user-written peer's field for one body: Euler's equations for principal moments and the
    quaternion rate, on ``y = (omega, q)`` of shape ``(7,)``."""
    import jax.numpy as jnp

    w, q = y[:3], y[3:]
    i1, i2, i3 = inertia
    dw = jnp.stack([(i2 - i3) / i1 * w[1] * w[2], (i3 - i1) / i2 * w[2] * w[0], (i1 - i2) / i3 * w[0] * w[1]])
    dq = 0.5 * jnp.stack(
        [
            -q[1] * w[0] - q[2] * w[1] - q[3] * w[2],
            q[0] * w[0] + q[2] * w[2] - q[3] * w[1],
            q[0] * w[1] - q[1] * w[2] + q[3] * w[0],
            q[0] * w[2] + q[1] * w[1] - q[2] * w[0],
        ]
    )
    return jnp.concatenate([dw, dq])


def peer_program(ts=None):
    """The user-written peer: ``jax.jit(jax.vmap(diffeqsolve(Tsit5(), PIDController)))`` per body,
    ``solve(inertia, y0, rtol, atol)``: the state at ``T_END`` ``(N, 7)`` when ``ts`` is None, else
    the states at the sample times ``ts`` (from 0 to ``T_END``), ``(N, T, 7)``."""
    import diffrax
    import jax
    import jax.numpy as jnp

    saveat = diffrax.SaveAt(t1=True) if ts is None else diffrax.SaveAt(ts=ts)

    @jax.jit
    def solve(inertia, y0, rtol, atol):
        def one(inertia, y0):
            sol = diffrax.diffeqsolve(
                diffrax.ODETerm(peer_vector_field),
                diffrax.Tsit5(),
                # Times in the state's dtype: diffrax promotes a float32 state to float64
                # times (under x64), which would make the float32 peer a float64 one.
                jnp.asarray(0.0, y0.dtype),
                jnp.asarray(T_END, y0.dtype),
                None,
                y0,
                args=inertia,
                stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
                saveat=saveat,
                max_steps=100_000,
                throw=False,
            )
            return sol.ys[-1] if ts is None else sol.ys

        return jax.vmap(one)(inertia, y0)

    return solve


def _vmap_diffrax_program():
    """:func:`peer_program` at ``T_END``, compiled once for every tolerance."""
    if "vmap" not in _PROGRAMS:
        _PROGRAMS["vmap"] = peer_program()
    return _PROGRAMS["vmap"]


def vmap_diffrax_method(scene, rtol: float, dtype: str = "float64") -> Method:
    """What a user writes: ``jax.vmap`` of ``diffeqsolve(Tsit5(), PIDController(rtol, atol=rtol))``."""
    import jax.numpy as jnp

    inertia, omega0, q0 = scene
    jd = {"float64": jnp.float64, "float32": jnp.float32}[dtype]
    args = (
        jnp.asarray(inertia, jd),
        jnp.asarray(np.concatenate([omega0, q0], axis=-1), jd),
        jnp.asarray(rtol, jd),
        jnp.asarray(rtol, jd),
    )
    solve = _vmap_diffrax_program()

    def fn():
        return solve(*args)

    def at_end(y):
        y = np.asarray(y)
        return y[:, :3], y[:, 3:]

    return Method(
        "vmap diffeqsolve Tsit5 (user)",
        f"rtol={rtol:g}",
        fn,
        f"vmap-tsit5-{dtype}",
        dtype,
        kind="peer",
        at_end=at_end,
    )


METHOD_KEYS = (
    "fast",
    "balanced",
    "precise",
    "exact",
    "tsit5",
    "dopri5",
    "dopri8",
    "rk4",
    "splitting",
    "rkmk",
    "vmap",
    "float32",
)


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (a one-line usage error otherwise)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def names_from(valid: Sequence[str]) -> Callable[[str], list[str]]:
    """argparse type: a comma-separated, non-empty list of names from ``valid``."""

    def parse(text: str) -> list[str]:
        names = [k.strip() for k in text.split(",") if k.strip()]
        unknown = [k for k in names if k not in valid]
        if unknown or not names:
            given = f"unknown {', '.join(unknown)}" if unknown else "no name given"
            raise argparse.ArgumentTypeError(f"{given}; choose from {','.join(valid)}")
        return list(dict.fromkeys(names))

    return parse


def standard_methods(scene, level: str = "full", include: Sequence[str] | None = None) -> list[Method]:
    """The methods of the work-precision run. ``level``: ``"full"`` or ``"quick"`` (fewer points,
    for development). ``include``: keys of :data:`METHOD_KEYS` to keep (default: all)."""
    import diffrax

    if level not in ("full", "quick"):
        raise ValueError(f"level must be 'full' or 'quick', got {level!r}.")
    keys = set(METHOD_KEYS) if include is None else set(include)
    unknown = keys - set(METHOD_KEYS)
    if unknown:
        raise ValueError(f"unknown benchmark methods {sorted(unknown)}; choose from {METHOD_KEYS}.")
    quick = level == "quick"
    inertia = scene[0]
    m: list[Method] = []
    presets = ("fast", "balanced", "precise")
    for p in presets:
        if p in keys:
            m.append(simulate_method(scene, f"simulate {p!r}", "preset", f"preset-{p}", accuracy=p))
    if "balanced" in keys and len(inertia) > 1024:
        # One chunk for the whole batch instead of lax.map over chunks of 1024 (matters on a GPU).
        m.append(
            simulate_method(
                scene,
                "simulate 'balanced'",
                "chunk_size=N",
                "preset-balanced-onechunk",
                accuracy="balanced",
                chunk_size=len(inertia),
            )
        )
    if "exact" in keys:
        m.append(simulate_method(scene, "simulate 'exact' (closed form)", "-", "exact", accuracy="exact"))
        m.append(
            simulate_method(
                scene,
                "simulate 'exact' (closed form)",
                "omega only",
                "exact-omega",
                omega_only=True,
                accuracy="exact",
            )
        )
    sweeps = {
        "Tsit5": (1e-5, 1e-7) if quick else (1e-4, 1e-6, 1e-8),
        "Dopri5": (1e-6, 1e-8) if quick else (1e-6, 1e-8, 1e-10),
        "Dopri8": (1e-6, 1e-10) if quick else (1e-6, 1e-8, 1e-10, 1e-12),
    }
    for name, rtols in sweeps.items():
        if name.lower() not in keys:
            continue
        for r in rtols:
            m.append(
                simulate_method(
                    scene,
                    f"simulate solver={name}",
                    f"rtol={r:g}",
                    f"simulate-{name}",
                    solver=getattr(diffrax, name)(),
                    rtol=r,
                )
            )
    if "rk4" in keys:
        dts = (0.02, 0.01, 0.005) if quick else (0.04, 0.02, 0.01, 0.005, 0.0025)
        m += [rk4_method(scene, dt) for dt in dts]
    if "splitting" in keys:
        # ~30x the cost of hand RK4 per step: run on 1000 bodies (the 100 nearest the separatrix
        # and a random rest), time scaled to N (the cost is linear in N from ~1e3 bodies).
        sub = sensitive_subset(scene, 1000)
        split = {2: (0.01, 0.0025), 4: (0.02,) if quick else (0.02, 0.005)}
        for order, dts in split.items():
            for dt in dts:
                m.append(
                    simulate_method(
                        scene,
                        f"LiePoissonSplitting order {order}",
                        f"dt={dt:g}",
                        f"split{order}-{dt}",
                        subset=None if sub.size == len(inertia) else sub,
                        solver=rj.solvers.LiePoissonSplitting(inertia[sub], order=order),
                        dt0=dt,
                    )
                )
    if "rkmk" in keys:
        for dt in (0.02,) if quick else (0.04, 0.02):
            m.append(
                simulate_method(
                    scene,
                    "RKMK dopri5 (fixed step)",
                    f"dt={dt:g}",
                    f"rkmk-{dt}",
                    solver=rj.solvers.RKMK("dopri5"),
                    dt0=dt,
                )
            )
    if "vmap" in keys:
        # rtol 1e-7 puts a point near the error 1e-6 at which the balanced target reads the peer's time.
        sweep = (1e-6, 1e-8) if quick else (1e-6, 1e-7, 1e-8, 1e-9, 1e-10)
        m += [vmap_diffrax_method(scene, r) for r in sweep]
    if "float32" in keys:
        m += _float32_methods(scene, quick)
    return m


def _float32_methods(scene, quick: bool) -> list[Method]:
    """Every method family again in float32 (errors against the float64 reference): presets, the
    closed form, the diffrax solvers at rtol 1e-4 / 1e-6, hand RK4, the splittings, RKMK and the
    vmapped peer. scipy and MuJoCo compute in float64 only."""
    import diffrax
    import jax.numpy as jnp

    f32 = "float32"
    inertia = scene[0]
    m = [
        simulate_method(scene, f"simulate {p!r}", "preset", f"f32-preset-{p}", f32, accuracy=p)
        for p in (("fast", "balanced") if quick else ("fast", "balanced", "precise"))
    ]
    m.append(
        simulate_method(scene, "simulate 'exact' (closed form)", "-", "f32-exact", f32, accuracy="exact")
    )
    m.append(
        simulate_method(
            scene,
            "simulate 'exact' (closed form)",
            "omega only",
            "f32-exact-omega",
            f32,
            omega_only=True,
            accuracy="exact",
        )
    )
    for name in ("Tsit5",) if quick else ("Tsit5", "Dopri5", "Dopri8"):
        for r in (1e-4, 1e-6):
            m.append(
                simulate_method(
                    scene,
                    f"simulate solver={name}",
                    f"rtol={r:g}",
                    f"f32-simulate-{name}",
                    f32,
                    solver=getattr(diffrax, name)(),
                    rtol=r,
                )
            )
    m += [rk4_method(scene, dt, f32) for dt in ((0.02, 0.01) if quick else (0.04, 0.02, 0.01, 0.005))]
    sub = sensitive_subset(scene, 1000)
    for order, dt in ((2, 0.01), (4, 0.02)):
        m.append(
            simulate_method(
                scene,
                f"LiePoissonSplitting order {order}",
                f"dt={dt:g}",
                f"f32-split{order}-{dt}",
                f32,
                subset=None if sub.size == len(inertia) else sub,
                solver=rj.solvers.LiePoissonSplitting(jnp.asarray(inertia[sub], jnp.float32), order=order),
                dt0=dt,
            )
        )
    for dt in (0.04,) if quick else (0.04, 0.02):
        m.append(
            simulate_method(
                scene,
                "RKMK dopri5 (fixed step)",
                f"dt={dt:g}",
                f"f32-rkmk-{dt}",
                f32,
                solver=rj.solvers.RKMK("dopri5"),
                dt0=dt,
            )
        )
    m += [vmap_diffrax_method(scene, r, f32) for r in (1e-4, 1e-6)]
    return m


# ---------------------------------------------------------------------------------------------
# Running and timing.


def run_meta(script: str, argv: Sequence[str] | None, **extra) -> dict:
    """What a benchmark's JSON records about its run: ``extra`` first, then jax's version and devices,
    the machine, the load at the start and the command line that reproduces it."""
    import os
    import platform
    import sys

    import jax

    return dict(
        **extra,
        jax=jax.__version__,
        devices=[str(d) for d in jax.devices()],
        cpu_count=os.cpu_count(),
        platform=platform.platform(),
        python=sys.version.split()[0],
        loadavg_start=os.getloadavg(),
        command=" ".join(["python", script] + list(sys.argv[1:] if argv is None else argv)),
    )


def timed_calls(fn: Callable[[], object], repeats: int) -> tuple[object, dict]:
    """``fn()``'s result and its timing: a first call (compile + run), then ``repeats`` calls, each
    with ``block_until_ready``; ``run_s`` is their median, ``compile_s`` = first call - median."""
    out, first = _call(fn)
    runs = [_call(fn)[1] for _ in range(repeats)]
    run = statistics.median(runs) if runs else first
    return out, {"run_s": run, "runs_s": runs, "compile_s": max(first - run, 0.0), "first_call_s": first}


def _call(fn):
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t0


def _round_time(fn, quick: float = 0.05, total: float = 0.2, most: int = 51) -> float:
    """One round's time of ``fn``: one call, or for a call under ``quick`` seconds the median of
    calls repeated until they add up to ``total`` seconds (at most ``most``)."""
    _, t = _call(fn)
    if t >= quick:
        return t
    runs = [t]
    while sum(runs) < total and len(runs) < most:
        runs.append(_call(fn)[1])
    return statistics.median(runs)


def run_methods(
    methods: Sequence[Method],
    scene,
    reference: tuple[np.ndarray, np.ndarray],
    repeats: int = 3,
    progress: Callable[[str, int, int], None] | None = None,
    checked: np.ndarray | None = None,
    first_calls: dict[str, float] | None = None,
) -> list[dict]:
    """Runs every method once (compile + accuracy), then ``repeats`` timed rounds, round-robin
    over the methods (on a shared machine the load drifts; interleaving spreads it evenly).
    A round's time of a method that takes a few milliseconds is the median of back-to-back calls
    adding up to ~0.2 s (at most 51; :func:`_round_time`): one such call alone, right after a
    method that ran for seconds, measures a cold cache and the machine's noise as much as the method.
    Returns one result row (a JSON-ready dict) per method.

    ``checked``: the bodies whose reference is independent of the float64 closed form (see
    :func:`refined_reference`); the float64 closed form's errors are measured on those only
    (elsewhere it is the reference itself). ``first_calls``: first-call times of compile groups
    already run elsewhere (the reference's closed form), used for their compile time."""
    first_calls = dict(first_calls or {})
    inertia, omega0, _ = scene
    n = inertia.shape[0]
    omega_ref, q_ref = reference
    rows, seen = [], set()
    total = len(methods) * (1 + repeats)
    done = 0
    firsts = []
    for m in methods:
        if progress:
            progress(f"first call {m.family} {m.setting} {m.dtype}", done, total)
        out, first = _call(m.fn)
        omega, q = m.at_end(out)
        done += 1
        omega, q = np.asarray(omega), None if q is None else np.asarray(q)
        if omega.dtype != np.dtype(m.dtype):  # e.g. a solver that silently promoted float32 state
            raise RuntimeError(f"{m.family} {m.setting}: computed in {omega.dtype}, declared {m.dtype}.")
        sub = slice(None) if m.subset is None else m.subset
        errors_on = "all bodies" if m.subset is None else f"{len(m.subset)} bodies ({m.subset_note})"
        if not m.integrator and m.dtype == "float64" and checked is not None:
            sub, omega, q = checked, omega[checked], None if q is None else q[checked]
            errors_on = f"{len(checked)} checked bodies"
        err = body_errors(inertia[sub], omega0[sub], omega, q, omega_ref[sub], q_ref[sub])
        row = {
            "family": m.family,
            "setting": m.setting,
            "dtype": m.dtype,
            "kind": m.kind,
            "integrator": m.integrator,
            "group": m.group,
            "n_bodies_timed": n if m.subset is None else len(m.subset),
            "time_scale": 1.0 if m.subset is None else n / len(m.subset),
            "errors_on": errors_on,
            "first_call_s": first,
            "new_compile": m.group not in seen,
            "finite": bool(np.all(np.isfinite(omega)) and (q is None or np.all(np.isfinite(q)))),
        }
        seen.add(m.group)
        for key, values in err.items():
            if values is None:
                row[f"max_{key}"] = row[f"median_{key}"] = row[f"p99_{key}"] = None
                continue
            v = np.where(np.isfinite(values), values, np.inf)
            row[f"max_{key}"] = float(np.max(v))
            row[f"median_{key}"] = float(np.median(v))
            row[f"p99_{key}"] = float(np.quantile(v, 0.99))
        rows.append(row)
        firsts.append(first)
    times: list[list[float]] = [[] for _ in methods]
    for _ in range(repeats):
        for k, m in enumerate(methods):
            if progress:
                progress(f"timing {m.family} {m.setting} {m.dtype}", done, total)
            times[k].append(_round_time(m.fn))
            done += 1
    for row, ts in zip(rows, times, strict=True):
        med = statistics.median(ts) if ts else row["first_call_s"]
        row["run_s_all"] = [t * row["time_scale"] for t in ts]
        row["run_s"] = med * row["time_scale"]
        first = first_calls.get(row["group"], row["first_call_s"])
        row["compile_s"] = max(first - med, 0.0) if row["new_compile"] else None
    if progress:
        progress("done", total, total)
    return rows


# ---------------------------------------------------------------------------------------------
# Reading the results: time to reach an error, targets, the table.


def time_at_error(
    rows: Sequence[dict], error: float, key: str = "max_rel_omega", extrapolate: bool = False
) -> tuple[float | None, bool]:
    """Run time a family of rows needs to reach ``error``, by log-log interpolation along its Pareto
    front, and whether that was an extrapolation. Above its least accurate point: that point's time
    (favours the family). Below its most accurate point: None, or with ``extrapolate`` the slope of
    its last two points continued (for fixed-step methods of known order)."""
    pts = [(r[key], r["run_s"]) for r in rows if math.isfinite(r[key]) and r[key] > 0]
    front = []  # increasing time, decreasing error
    for e, t in sorted(pts, key=lambda p: p[1]):
        if not front or e < front[-1][0]:
            front.append((e, t))
    if not front:
        return None, False
    if error >= front[0][0]:
        return front[0][1], False

    def loglog(p0, p1):
        (e0, t0), (e1, t1) = p0, p1
        w = (math.log(error) - math.log(e0)) / (math.log(e1) - math.log(e0))
        return math.exp(math.log(t0) + w * (math.log(t1) - math.log(t0)))

    for p0, p1 in zip(front, front[1:], strict=False):
        if p1[0] <= error <= p0[0]:
            return loglog(p0, p1), False
    if extrapolate and len(front) >= 2:
        (e0, t0), (e1, t1) = front[-2], front[-1]
        # Only in the truncation-error regime (error falling at least like time^-1.5): a method at
        # its roundoff floor cannot be extrapolated to a smaller error.
        if math.log(e1 / e0) / math.log(t1 / t0) <= -1.5:
            return loglog(front[-2], front[-1]), True
    return None, False


def _find(rows, family_prefix, dtype="float64"):
    return [r for r in rows if r["family"].startswith(family_prefix) and r["dtype"] == dtype]


def evaluate_targets(rows: Sequence[dict]) -> list[dict]:
    """The performance targets (float64 rows): each with ``met`` (bool, or None if not measurable
    here), the measured ratio or value, the required one, and a sentence saying by how much."""
    out = []
    preset = {p: (_find(rows, f"simulate {p!r}") or [None])[0] for p in ("balanced", "precise")}
    peer = _find(rows, "vmap diffeqsolve")
    rk4 = _find(rows, "hand RK4")

    def add(name, met, value, required, text):
        out.append({"target": name, "met": met, "value": value, "required": required, "text": text})

    fast_rj = [
        r
        for r in rows
        if r["family"].startswith("simulate") and r["integrator"] and r["dtype"] == "float64" and r["finite"]
    ]
    for name, threshold, factor in (("balanced", 1e-6, 10.0), ("precise", 1e-8, 5.0)):
        r = preset[name]
        if not (r and peer):
            continue
        err = r["max_rel_omega"]
        # The peer's time to reach the threshold (or this preset's error if that is worse): the
        # reading most favourable to the peer, since the preset may deliver more than the threshold.
        t_peer, _ = time_at_error(peer, max(err, threshold))
        t_same, _ = time_at_error(peer, err)
        ratio = None if t_peer is None else t_peer / r["run_s"]
        met = None if ratio is None else bool(err <= threshold and ratio >= factor)
        text = f"{name}: max rel omega {err:.1e} in {r['run_s']:.3g} s; "
        text += f"vmapped Tsit5 to reach {max(err, threshold):.0e}: "
        if t_peer is None:
            best = min(peer, key=lambda x: x["max_rel_omega"])
            text += (
                f"not reached by the swept tolerances (its best: {best['max_rel_omega']:.1e} in "
                f"{best['run_s']:.3g} s, so the ratio is > {best['run_s'] / r['run_s']:.1f}x)"
            )
        else:
            text += f"{t_peer:.3g} s -> {ratio:.1f}x"
        if t_same is not None and err < threshold:
            text += f" (at the preset's own error {err:.1e}: {t_same:.3g} s, {t_same / r['run_s']:.1f}x)"
        elif t_same is None and t_peer is not None and err < threshold:
            best = min(peer, key=lambda x: x["max_rel_omega"])
            text += (
                f" (at the preset's own error {err:.1e}: not reached; its best, {best['max_rel_omega']:.1e}, "
                f"takes {best['run_s'] / r['run_s']:.1f}x the preset's time)"
            )
        if err > threshold:
            text += f"; the preset's error is {err / threshold:.1f}x the threshold"
        elif ratio is not None and ratio < factor:
            text += f"; short of {factor:g}x by {factor / ratio:.1f}x"
        ok_rows = [x for x in fast_rj if x["max_rel_omega"] <= threshold]
        if t_peer is not None and ok_rows:
            quickest = min(ok_rows, key=lambda x: x["run_s"])
            text += (
                f". Fastest simulate configuration reaching {threshold:.0e}: {quickest['family']} "
                f"{quickest['setting']} ({quickest['max_rel_omega']:.1e}, {quickest['run_s']:.3g} s) -> "
                f"{t_peer / quickest['run_s']:.1f}x"
            )
        add(f"{name} >= {factor:g}x vmapped diffrax at <= {threshold:.0e}", met, ratio, factor, text)
    b = preset["balanced"]
    if b and rk4:
        ratios = {}
        for key in ("max_rel_omega", "p99_rel_omega", "median_rel_omega"):
            t_rk4, extra = time_at_error(rk4, b[key], key=key, extrapolate=True)
            ratios[key] = (None if t_rk4 is None else b["run_s"] / t_rk4, extra, t_rk4)
        ratio, extra, t_rk4 = ratios["max_rel_omega"]
        used = "max"
        if ratio is None:  # RK4 never reaches balanced's max error (roundoff floor): compare the p99
            ratio, extra, t_rk4 = ratios["p99_rel_omega"]
            used = "p99"
        text = f"balanced {b['run_s']:.3g} s; "
        for key, label in (
            ("max_rel_omega", "max"),
            ("p99_rel_omega", "p99"),
            ("median_rel_omega", "median"),
        ):
            rt, ex, t = ratios[key]
            text += f"hand RK4 at balanced's {label} error {b[key]:.1e}: "
            text += (
                "not reached; " if rt is None else f"{t:.3g} s{' (extrapolated)' if ex else ''} ({rt:.2f}x); "
            )
        text += f"judged on the {used} error"
        if ratio is not None and ratio > 1.5:
            text += f": {ratio / 1.5:.1f}x over the 1.5x allowance"
        add(
            "balanced within 1.5x of hand RK4 at the same error",
            None if ratio is None else bool(ratio <= 1.5),
            ratio,
            1.5,
            text,
        )
    exact = (_find(rows, "simulate 'exact'") or [None])[0]
    # Rows whose max is over a random subset of bodies miss the worst-conditioned ones: not comparable.
    integ = [
        r
        for r in rows
        if r["integrator"] and r["dtype"] == "float64" and r["finite"] and "random" not in r["errors_on"]
    ]
    if exact and integ:
        # Omega and orientation both count: an integrator's error here is the larger of its max
        # relative omega error and its max angle error (rad).
        def both(r):
            angle = r.get("max_angle")
            return max(r["max_rel_omega"], angle if angle is not None else math.inf)

        reaching = [r for r in integ if both(r) <= 1e-9]
        if reaching:
            basis = min(reaching, key=lambda r: r["run_s"])
            basis_text = "fastest integrator at <= 1e-9"
        else:
            # None reaches 1e-9 (roundoff near the separatrix): the most accurate one is the least
            # any integrator needs to come near it.
            basis = min(integ, key=both)
            basis_text = "no integrator reaches 1e-9 in omega and angle here; the most accurate"
        ratio = basis["run_s"] / exact["run_s"]
        exact_error = both(exact)
        ok = exact_error <= 1e-9 and ratio >= 100
        fastest = min(integ, key=lambda r: r["run_s"])
        text = (
            f"exact: {exact['run_s']:.3g} s, max error {exact_error:.1e} (omega and angle, "
            f"{exact['errors_on']}); {basis_text}: {basis['family']} {basis['setting']}, "
            f"{both(basis):.1e} in {basis['run_s']:.3g} s -> {ratio:.1f}x"
        )
        if ratio < 100:
            text += f"; short of 100x by {100 / ratio:.1f}x"
        text += (
            f". (The fastest integrator of any accuracy, {fastest['family']} {fastest['setting']} at "
            f"{both(fastest):.1e}, takes {fastest['run_s'] / exact['run_s']:.2g}x the closed form's time.)"
        )
        add(
            "exact >= 100x the fastest integrator at <= 1e-9 (omega and orientation)",
            bool(ok),
            ratio,
            100.0,
            text,
        )
        if peer:
            t_peer, _ = time_at_error(peer, 1e-6)
            if t_peer is not None:
                ratio_peer = t_peer / exact["run_s"]
                add(
                    "exact >= 250x vmapped Tsit5 at <= 1e-6",
                    bool(ratio_peer >= 250 and exact_error <= 1e-6),
                    ratio_peer,
                    250.0,
                    f"exact: {exact['run_s']:.3g} s; vmapped Tsit5 to reach 1e-6 in omega: {t_peer:.3g} s "
                    f"-> {ratio_peer:.0f}x"
                    + ("" if ratio_peer >= 250 else f"; short by {250 / ratio_peer:.1f}x"),
                )
    comp = [r for r in rows if r["compile_s"] is not None and r["family"].startswith("simulate")]
    if comp:
        worst = max(comp, key=lambda r: r["compile_s"])
        over = [r for r in comp if r["compile_s"] > 5.0]
        add(
            "simulate compile <= 5 s per configuration",
            not over,
            worst["compile_s"],
            5.0,
            f"{len(over)} of {len(comp)} configurations over 5 s; largest {worst['family']} "
            f"{worst['setting']} {worst['dtype']}: {worst['compile_s']:.1f} s (first call - median run)",
        )
    return out


def format_targets(targets: Sequence[dict]) -> str:
    lines = []
    for t in targets:
        flag = {True: "MET    ", False: "NOT MET", None: "n/a    "}[t["met"]]
        lines.append(f"[{flag}] {t['target']}: {t['text']}")
    return "\n".join(lines)


def _fmt(x, spec=".1e"):
    if x is None:
        return "-"
    if isinstance(x, float) and not math.isfinite(x):
        return "inf"
    return format(x, spec)


def format_table(rows: Sequence[dict]) -> str:
    """A markdown table, one row per method."""
    calls = {len(r.get("run_s_all") or ()) for r in rows}
    timing = "run s (one call)" if calls == {1} else "run s (median)"  # --repeats 1 has no median
    head = (
        f"| method | setting | dtype | {timing} | compile s | max rel ω err | median rel ω err "
        "| p99 rel ω err | max angle err rad | median angle err | max rel energy drift | errors on |"
    )
    lines = [head, "|" + " --- |" * 12]
    for r in rows:
        run = _fmt(r["run_s"], ".3g") + (f" (scaled ×{r['time_scale']:.3g})" if r["time_scale"] != 1 else "")
        lines.append(
            f"| {r['family']} | {r['setting']} | {r['dtype']} | {run} | {_fmt(r['compile_s'], '.1f')} "
            f"| {_fmt(r['max_rel_omega'])} | {_fmt(r['median_rel_omega'])} | {_fmt(r['p99_rel_omega'])} "
            f"| {_fmt(r['max_angle'])} "
            f"| {_fmt(r['median_angle'])} | {_fmt(r['max_energy'])} | {r['errors_on']} |"
        )
    return "\n".join(lines)


def write_markdown(path, caption: str, header: Sequence[str], rows: Sequence[str]) -> None:
    """``caption``, then a markdown table of ``header`` and the already formatted ``rows``, to ``path``."""
    table = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header), *rows]
    Path(path).write_text(caption + "\n\n" + "\n".join(table) + "\n")
    print(f"wrote {path}")


def taylor_reference(scene, index: np.ndarray, h: float = 0.05, order: int = 24):
    """omega(T), q(T) of the bodies ``index`` by a Taylor-series integration in NumPy extended
    precision (x87 80-bit, eps 1.1e-19; on platforms without it, float64).

    The right-hand side is quadratic, so the Taylor coefficients follow exactly from Cauchy
    products; the nearest complex-time singularity is ~0.9 s away, so h = 0.05 s with 24 terms
    truncates far below roundoff and the result is limited by extended-precision roundoff only.
    """
    ld = np.longdouble
    inertia, omega0, q0 = (np.asarray(x[index], ld) for x in scene)
    i1, i2, i3 = inertia.T
    c = np.stack([(i2 - i3) / i1, (i3 - i1) / i2, (i1 - i2) / i3])
    y = np.concatenate([omega0.T, q0.T])
    n_steps = round(T_END / h)
    hh = ld(T_END) / n_steps
    inv = 1 / np.arange(1, order + 1, dtype=ld)
    half = ld(0.5)
    for _ in range(n_steps):
        Y = np.zeros((order + 1, 7, y.shape[1]), ld)
        Y[0] = y
        for k in range(order):
            wr = Y[k::-1, 0:3]
            ww = np.einsum("jan,jbn->abn", Y[: k + 1, 0:3], wr)  # sum_j w_a[j] w_b[k-j]
            qw = np.einsum("jan,jbn->abn", Y[: k + 1, 3:7], wr)  # sum_j q_a[j] w_b[k-j]
            i = inv[k]
            Y[k + 1, 0] = c[0] * ww[1, 2] * i
            Y[k + 1, 1] = c[1] * ww[2, 0] * i
            Y[k + 1, 2] = c[2] * ww[0, 1] * i
            Y[k + 1, 3] = half * i * (-qw[1, 0] - qw[2, 1] - qw[3, 2])
            Y[k + 1, 4] = half * i * (qw[0, 0] + qw[2, 2] - qw[3, 1])
            Y[k + 1, 5] = half * i * (qw[0, 1] - qw[1, 2] + qw[3, 0])
            Y[k + 1, 6] = half * i * (qw[0, 2] + qw[1, 1] - qw[2, 0])
        y = Y[order]
        for k in range(order - 1, -1, -1):
            y = y * hh + Y[k]
    y = np.asarray(y, np.float64)
    return y[:3].T, y[3:].T


def refined_reference(scene, n_sensitive: int = 50, n_random: int = 50, seed: int = 1):
    """The float64 closed form for every body, with the ``n_sensitive`` bodies closest to the
    separatrix and ``n_random`` others replaced by the extended-precision Taylor solution.

    Returns ``(omega_ref, q_ref, checked, info)``: ``checked`` are the replaced bodies' indices and
    ``info`` the closed form's deviation from the Taylor solution on them (max and median).
    """
    n = scene[0].shape[0]
    omega_cf, q_cf, first = closed_form_reference(scene)
    order = np.argsort(np.abs(separatrix_distance(scene[0], scene[1])))
    rest = order[n_sensitive:]
    pick = np.random.default_rng(seed).choice(rest, size=min(n_random, rest.size), replace=False)
    checked = np.unique(np.concatenate([order[:n_sensitive], pick])).astype(np.int64)
    t0 = time.perf_counter()
    omega_t, q_t = taylor_reference(scene, checked)
    t_taylor = time.perf_counter() - t0
    err = body_errors(scene[0][checked], scene[1][checked], omega_cf[checked], q_cf[checked], omega_t, q_t)
    omega_ref, q_ref = omega_cf.copy(), q_cf.copy()
    omega_ref[checked], q_ref[checked] = omega_t, q_t
    info = {
        "n_bodies": n,
        "checked_bodies": int(checked.size),
        "checked_most_sensitive": int(min(n_sensitive, n)),
        "min_abs_s": float(np.min(np.abs(separatrix_distance(scene[0], scene[1])))),
        "taylor_s": t_taylor,
        "closed_form_first_call_s": first,
        "longdouble_eps": float(np.finfo(np.longdouble).eps),
        "closed_form_vs_taylor_max_rel_omega": float(err["rel_omega"].max()),
        "closed_form_vs_taylor_median_rel_omega": float(np.median(err["rel_omega"])),
        "closed_form_vs_taylor_max_angle": float(err["angle"].max()),
        "closed_form_vs_taylor_median_angle": float(np.median(err["angle"])),
    }
    return omega_ref, q_ref, checked, info


def closed_form_reference(scene) -> tuple[np.ndarray, np.ndarray, float]:
    """omega(T), q(T) of every body from ``simulate(..., accuracy="exact")`` in float64 (the same
    compiled program as the ``exact`` method, so it compiles once), and the call's wall time."""
    m = simulate_method(scene, "exact", "-", "exact", accuracy="exact")
    out, first = _call(m.fn)
    omega, q = m.at_end(out)
    return np.asarray(omega), np.asarray(q), first
