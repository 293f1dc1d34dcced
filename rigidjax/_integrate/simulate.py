"""``simulate``: integrate a scene over time for one body or a batch, with diffrax.

How a batch is integrated (chosen by measurement, see ``benchmarks/``): bodies are sorted by their
angular-velocity scale and cut into chunks; each chunk is one diffrax solve with one shared step
size, accepted only when EVERY body in it meets the tolerance (a max norm over the chunk, so a fast
body cannot hide among slow ones). Chunks run one after another with ``lax.map`` (bounded memory for
10^6 bodies) and, with several devices, are sharded across them.

Tolerances are dimensionless. Each body's angular velocity is divided by a per-component scale
(``model.omega_scale``: for a torque-free body, the largest value each component reaches; otherwise
|omega0|), and the quaternion is O(1), so ``rtol`` and ``atol`` mean the same thing for the Earth in
SI units and for a 1e5 rad/s rotor.
"""

import math
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

from .._closed_form.torque_free import torque_free_motion, torque_free_omega
from .._dynamics.equations import is_full_tensor
from .._dynamics.inertia import check_inertia
from .._dynamics.models import AbstractModel, FreeBody, State
from .._kinematics.euler import _euler_from_quat, _euler_rates, _quat_from_euler, is_proper_sequence
from .._kinematics.quaternion import _quat_multiply
from .._numerics import safe_norm
from .presets import PRESETS
from .solvers.rkmk import RKMK, simulate_structure_preserving
from .solvers.splitting import HeavyTopSplitting, LiePoissonSplitting
from .trajectory import Trajectory


def _max_norm(x):
    """Max norm of the scaled error over the chunk. NaN counts as infinitely large: a trial step so
    long that it overflows (the first step of a 1e4 rad/s body) is rejected and shortened, instead
    of turning the step size into NaN for good."""
    norm = jnp.max(jnp.abs(jnp.concatenate([jnp.ravel(leaf) for leaf in jax.tree_util.tree_leaves(x)])))
    return jnp.where(jnp.isnan(norm), jnp.inf, norm)


def _quat_derivative(q, omega):
    """``dq/dt = q ⊗ (0, omega) / 2`` plus ``|omega| (1 - |q|^2) q``, which leaves the rotation
    unchanged but makes unit norm attracting, so the norm does not drift."""
    pure = jnp.concatenate([jnp.zeros_like(omega[..., :1]), omega], axis=-1)
    speed = safe_norm(omega, keepdims=True)  # the gradient of |omega| at rest is 0, not NaN
    return 0.5 * _quat_multiply(q, pure) + speed * (1.0 - jnp.sum(q * q, axis=-1, keepdims=True)) * q


def _check_field(where, label, value):
    if label == "inertia":
        return check_inertia(value, name=f"{where}: inertia")
    value = eqx.error_if(
        value, ~jnp.all(jnp.isfinite(value)), f"{where}: model field {label!r} contains NaN or inf."
    )
    if label.split(".")[-1] == "mass":
        value = eqx.error_if(
            value, jnp.any(value <= 0), f"{where}: model field {label!r} must be positive (kg)."
        )
    return value


def _check_inputs(model, leaves, omega0, q0, ts, dtype, where="simulate"):
    checked = [_check_field(where, leaf.label, leaf.get(model)) for leaf in leaves]
    model = model.replace_body_leaves(leaves, checked)
    omega0 = eqx.error_if(
        omega0, ~jnp.all(jnp.isfinite(omega0)), f"{where}: state0.omega contains NaN or inf."
    )
    if q0 is not None:
        q0 = eqx.error_if(q0, ~jnp.all(jnp.isfinite(q0)), "simulate: state0.orientation contains NaN or inf.")
        tol = 1e-6 if dtype == jnp.float64 else 1e-4
        norm = jnp.linalg.norm(q0, axis=-1)
        q0 = eqx.error_if(
            q0,
            jnp.any(jnp.abs(norm - 1.0) > tol),
            f"simulate: state0.orientation is not a unit quaternion (| |q| - 1 | > {tol:g}); "
            "normalise it (rigidjax.quat_normalize) or build it with quat_from_euler / quat_from_matrix.",
        )
        q0 = q0 / norm[..., None]
    ts = eqx.error_if(ts, ~jnp.all(jnp.isfinite(ts)), f"{where}: ts contains NaN or inf.")
    if ts.shape[0] > 1:
        ts = eqx.error_if(
            ts,
            jnp.any(jnp.diff(ts) <= 0),
            "simulate: ts must be strictly increasing (found a decreasing or repeated time); "
            "ts[0] is the initial time.",
        )
    return model, omega0, q0, ts


@eqx.filter_jit
def _simulate_impl(
    model,
    omega0,
    q0,
    ts,
    args,
    *,
    solver,
    controller,
    adjoint,
    dt0,
    max_steps,
    chunk_size,
    sort,
    throw,
    euler_seq,
    lock_tolerance,
):
    dtype = omega0.dtype
    leaves = model.body_leaves()
    model, omega0, q0, ts = _check_inputs(model, leaves, omega0, q0, ts, dtype)
    batch = jnp.broadcast_shapes(model.batch_shape(), omega0.shape[:-1], () if q0 is None else q0.shape[:-1])
    n = math.prod(batch)
    flat = []
    for leaf in leaves:
        value = leaf.get(model)
        core_shape = value.shape[value.ndim - leaf.core :]
        flat.append(jnp.broadcast_to(value, batch + core_shape).reshape((n,) + core_shape).astype(dtype))
    omega0 = jnp.broadcast_to(omega0, batch + (3,)).reshape(n, 3)
    if q0 is not None:
        q0 = jnp.broadcast_to(q0, batch + (4,)).reshape(n, 4)
    n_times = ts.shape[0]

    def body_model(body_values):
        return model.replace_body_leaves(leaves, body_values)

    duration = ts[-1] - ts[0]

    def scale_one(body_values, w, q):
        m = body_model(body_values)
        return m.omega_scale(State(w, q), duration, args)

    sigma = jax.vmap(scale_one, in_axes=(0, 0, None if q0 is None else 0))(flat, omega0, q0)
    sigma = jax.lax.stop_gradient(sigma)
    peak = jnp.max(sigma, axis=-1, keepdims=True)
    floor = 10 * jnp.finfo(dtype).eps * peak
    sigma = jnp.where(peak > 0, jnp.maximum(sigma, floor), jnp.ones_like(sigma))

    chunk = min(chunk_size, n)
    n_chunks = -(-n // chunk)
    n_devices = jax.device_count()
    shard = n_devices > 1 and n_chunks > 1 and n_times > 1
    if shard:  # whole chunks per device; padding bodies are copies of a real one, dropped later
        n_chunks = -(-n_chunks // n_devices) * n_devices
    if sort and n_chunks > 1:
        order = jnp.argsort(-jnp.max(sigma, axis=-1))
    else:
        order = jnp.arange(n)
    take = order[jnp.minimum(jnp.arange(n_chunks * chunk), n - 1)]

    def to_chunks(x):
        return x[take].reshape((n_chunks, chunk) + x.shape[1:])

    if euler_seq is not None:
        lock = _lock_distance(_euler_from_quat(q0, euler_seq), euler_seq)
        q0 = eqx.error_if(
            q0,
            jnp.any(lock < lock_tolerance),
            f"simulate: the initial orientation is within {lock_tolerance:g} of gimbal lock for the "
            f"Euler-angle state (seq={euler_seq!r}); use representation='quaternion'.",
        )
        attitude0 = _euler_from_quat(q0, euler_seq)
    else:
        attitude0 = q0
    chunks = (
        [to_chunks(v) for v in flat],
        to_chunks(omega0 / sigma),
        None if attitude0 is None else to_chunks(attitude0),
        to_chunks(sigma),
    )

    # Everything a chunk solve needs besides its own bodies, passed explicitly (not closed over) so
    # that the same function runs under lax.map and under shard_map.
    shared_dynamic, shared_static = eqx.partition(
        (model.replace_body_leaves(leaves, [None] * len(leaves)), args, ts, controller, solver, adjoint),
        eqx.is_array,
    )

    def solve_chunk(c, shared_dynamic):
        c_values, u0, cq0, c_sigma = c
        shared_model, args, ts, controller, solver, adjoint = eqx.combine(shared_dynamic, shared_static)

        def body_rhs(body_values, t, y, s):
            u, attitude = y
            w = u * s
            if euler_seq is None:
                q = attitude
                dattitude = None if q is None else _quat_derivative(q, w)
            else:
                q = _quat_from_euler(attitude, euler_seq)
                dattitude = _euler_rates(attitude, w, euler_seq, throw=False)
            body = shared_model.replace_body_leaves(leaves, body_values)
            dw = body.angular_acceleration(t, State(w, q), args)
            return (dw / s, dattitude)

        def near_lock(t, y, args, **kwargs):
            return jnp.any(_lock_distance(y[1].T, euler_seq) < lock_tolerance)

        def vector_field(t, y, _):
            # Bodies on the last (contiguous) axis of the state: measured 1.5-2x faster than
            # bodies-first on CPU (benchmarks/batch_strategies.py).
            return jax.vmap(body_rhs, in_axes=(0, None, 1, 0), out_axes=1)(c_values, t, y, c_sigma)

        y0 = (u0.T, None if cq0 is None else cq0.T)
        first_step = dt0
        if first_step is None and not isinstance(controller, diffrax.ConstantStepSize):
            # A first trial step of 1% of the fastest body's turn (or of sqrt(1/|omega_dot|) for a
            # body at rest): diffrax's generic guess overshoots by orders of magnitude at 1e4 rad/s,
            # overflows, and the rejected NaN step poisons reverse-mode gradients.
            speed = jnp.max(jnp.abs(u0 * c_sigma))
            accel = jnp.max(jnp.abs(vector_field(ts[0], y0, None)[0] * c_sigma.T))
            rate = jax.lax.stop_gradient(jnp.maximum(speed, jnp.sqrt(accel)))
            span = ts[-1] - ts[0]
            first_step = jnp.where(rate > 0, jnp.minimum(0.01 / jnp.where(rate > 0, rate, 1.0), span), span)
            first_step = jnp.where(first_step > 0, first_step, 1.0)  # a single output time
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(vector_field),
            solver,
            ts[0],
            ts[-1],
            first_step,
            y0,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=controller,
            adjoint=adjoint,
            max_steps=max_steps,
            throw=False,
            event=None if euler_seq is None else diffrax.Event(near_lock),
        )
        u, q = sol.ys  # (T, components, bodies)
        u = jnp.transpose(u, (2, 0, 1))
        q = None if q is None else jnp.transpose(q, (2, 0, 1))
        if euler_seq is not None:
            q = _quat_from_euler(q, euler_seq)
        return (
            u,
            q,
            sol.result._value,
            sol.stats["num_steps"],
        )

    if n_times == 1:
        u_all = chunks[1][:, :, None, :]
        q_all = None if q0 is None else chunks[2][:, :, None, :]
        codes = jnp.zeros((n_chunks,), jnp.int32)
        steps = jnp.zeros((n_chunks,), jnp.int32)
    else:

        def solve_chunks(chunks, shared_dynamic):
            return jax.lax.map(lambda c: solve_chunk(c, shared_dynamic), chunks)

        if shard:
            mesh = jax.make_mesh((n_devices,), ("bodies",), axis_types=(AxisType.Auto,))
            chunks = jax.lax.with_sharding_constraint(chunks, NamedSharding(mesh, P("bodies")))
            solve_chunks = jax.shard_map(
                solve_chunks, mesh=mesh, in_specs=(P("bodies"), P()), out_specs=P("bodies"), check_vma=False
            )
        u_all, q_all, codes, steps = solve_chunks(chunks, shared_dynamic)

    ok_chunk = codes == diffrax.RESULTS.successful._value
    max_steps_hit = codes == diffrax.RESULTS.max_steps_reached._value
    hit_lock = codes == diffrax.RESULTS.event_occurred._value
    if throw and euler_seq is not None:
        u_all = eqx.error_if(
            u_all,
            jnp.any(hit_lock),
            f"simulate: the Euler-angle state (seq={euler_seq!r}) came within {lock_tolerance:g} of "
            "gimbal lock (first and third axes aligned), where Euler-angle rates are unbounded. "
            "Use representation='quaternion' (the default), or throw=False for NaN rows.",
        )
    if throw:
        u_all = eqx.error_if(
            u_all,
            jnp.any(max_steps_hit),
            f"simulate: the integrator reached max_steps={max_steps} before the last time in ts. "
            "Increase max_steps, choose a lower accuracy, or shorten ts.",
        )
        u_all = eqx.error_if(
            u_all,
            jnp.any(~ok_chunk),
            "simulate: the integration failed (step size underflow or a non-finite state, e.g. a "
            "singular scene). Check the inputs, or pass throw=False to get NaN rows and a success flag.",
        )

    inverse = jnp.argsort(order)

    def from_chunks(x):
        x = x.reshape((n_chunks * chunk,) + x.shape[2:])[:n]
        return x[inverse]

    ok = from_chunks(jnp.broadcast_to(ok_chunk[:, None], (n_chunks, chunk)))
    omega = from_chunks(u_all) * sigma[:, None, :]
    omega = jnp.where(ok[:, None, None], omega, jnp.nan)
    out_q = None
    q_norm_error = None
    if q_all is not None:
        qs = from_chunks(q_all)
        q_norm = jnp.linalg.norm(qs, axis=-1, keepdims=True)
        q_norm_error = jnp.max(jnp.abs(q_norm[..., 0] - 1.0), axis=-1).reshape(batch)
        out_q = jnp.where(ok[:, None, None], qs / q_norm, jnp.nan).reshape(batch + (n_times, 4))
    stats = {"num_steps": steps, "chunk_size": chunk, "quaternion_norm_error": q_norm_error}
    model_b = model.replace_body_leaves(leaves, [v.reshape(batch + v.shape[1:]) for v in flat])
    return Trajectory(
        ts=ts,
        omega=omega.reshape(batch + (n_times, 3)),
        orientation=out_q,
        model=model_b,
        success=ok.reshape(batch),
        stats=stats,
    )


def _lock_distance(angles, seq):
    """sin(theta) (proper sequences) or cos(theta) (Tait-Bryan): 0 at gimbal lock.

    Signed on purpose: theta starts inside (0, pi) or (-pi/2, pi/2), so a step that jumps over the
    lock (the event is only checked at step ends) leaves a negative value and is still caught.
    """
    theta = angles[..., 1]
    return jnp.sin(theta) if is_proper_sequence(seq) else jnp.cos(theta)


def _float_dtype(*xs):
    dtypes = [jnp.asarray(x).dtype for x in xs if x is not None]
    dtypes = [d for d in dtypes if jnp.issubdtype(d, jnp.floating)]
    return jnp.result_type(*dtypes) if dtypes else jnp.result_type(float)


@eqx.filter_jit
def _exact_impl(model, omega0, q0, ts):
    model, omega0, q0, ts = _check_inputs(model, model.body_leaves(), omega0, q0, ts, omega0.dtype)
    batch = jnp.broadcast_shapes(
        model.inertia.shape[:-1], omega0.shape[:-1], () if q0 is None else q0.shape[:-1]
    )
    inertia = jnp.broadcast_to(model.inertia, batch + (3,))
    omega0 = jnp.broadcast_to(omega0, batch + (3,))
    if q0 is None:
        omega = torque_free_omega(inertia[..., None, :], omega0[..., None, :], ts - ts[0])
        orientation = None
        q_norm_error = None
    else:
        q0 = jnp.broadcast_to(q0, batch + (4,))
        omega, orientation = torque_free_motion(
            inertia[..., None, :], omega0[..., None, :], q0[..., None, :], ts - ts[0]
        )
        q_norm_error = jnp.max(jnp.abs(jnp.linalg.norm(orientation, axis=-1) - 1.0), axis=-1)
    return Trajectory(
        ts=ts,
        omega=omega,
        orientation=orientation,
        model=model.replace_body_leaves(model.body_leaves(), [inertia]),
        success=jnp.ones(batch, bool),
        stats={"num_steps": jnp.zeros((), jnp.int32), "chunk_size": 0, "quaternion_norm_error": q_norm_error},
    )


def _simulate_exact(model, state0, ts, *, throw):
    """``accuracy="exact"``: the closed-form torque-free solution, no integration."""
    del throw  # the closed form cannot fail; invalid input still raises
    if not (isinstance(model, AbstractModel) and model.torque_free):
        raise ValueError(
            "accuracy='exact' is the closed-form torque-free solution: it needs a FreeBody (or a "
            f"RigidBody without torques), got {type(model).__name__} with torques or a field."
        )
    if is_full_tensor(model.inertia):
        raise ValueError(
            "accuracy='exact' needs principal moments (..., 3); diagonalise the tensor with "
            "rigidjax.principal_axes and rotate omega into those axes first."
        )
    ts = jnp.asarray(ts)
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(f"ts must be a 1-D array of at least one time, got shape {tuple(ts.shape)}.")
    dtype = _float_dtype(state0.omega, state0.orientation, model.inertia)
    q0 = None if state0.orientation is None else jnp.asarray(state0.orientation, dtype)
    return _exact_impl(
        FreeBody(jnp.asarray(model.inertia, dtype)), state0.omega.astype(dtype), q0, ts.astype(dtype)
    )


def simulate(
    model: AbstractModel,
    state0: State,
    ts,
    *,
    accuracy: str = "balanced",
    solver: diffrax.AbstractSolver | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    dt0: float | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    max_steps: int = 100_000,
    chunk_size: int | None = None,
    sort_by_speed: bool = True,
    throw: bool = True,
    args: Any = None,
    representation: str = "quaternion",
    euler_seq: str = "zxz",
    lock_tolerance: float = 1e-3,
) -> Trajectory:
    """Integrates ``model`` from ``state0`` and samples it at times ``ts``.

    Args:
        model: a scene (:class:`FreeBody`, :class:`RigidBody`, :class:`HeavyTop`), possibly batched:
            a leading batch axis on its array fields.
        state0: initial :class:`State`; its batch axes broadcast against the model's. With
            ``orientation=None`` and a scene that does not need it, only Euler's equations (three
            per body) are integrated.
        ts: strictly increasing sample times (s), shape (T,); ``ts[0]`` is the initial time.
        accuracy: ``"fast"`` (Tsit5, rtol 1e-5), ``"balanced"`` (Dopri8, 1e-8) or ``"precise"``
            (Dopri8, 1e-11), or ``"exact"``: the closed-form torque-free solution, no integration
            (FreeBody with principal moments; omega by Jacobi elliptic functions and, when ``state0``
            has an orientation, the orientation by Carlson's ``R_J``: see
            ``rigidjax.torque_free_motion``). Accurate to roundoff at any time; the cost does not
            grow with the duration.
        solver, rtol, atol, stepsize_controller, dt0, adjoint: override the preset with any diffrax
            solver, step-size controller (e.g. ``ConstantStepSize`` with ``dt0``) or adjoint.
            ``rtol``/``atol`` are dimensionless (see the module docstring); ``atol`` defaults to
            ``rtol``.
        max_steps: step limit per chunk; reaching it is an error (or NaN rows with ``throw=False``).
        chunk_size: bodies per shared-step chunk. Default: 1024 on CPU (cache-sized chunks run
            one after another), 65536 on accelerators (one H100 ran 10^4 bodies 9.4x faster as one
            chunk than as ten; ``benchmarks/README.md``).
        sort_by_speed: group bodies of similar angular-velocity scale into the same chunk.
        throw: raise on invalid input or failed integration (default). With ``throw=False`` a failed
            integration gives NaN rows and ``Trajectory.success = False`` instead.
        args: passed to user torques as ``fn(t, state, args)``.
        representation: how the orientation is integrated when there is one: ``"quaternion"``
            (default; unit norm kept without drift) or ``"euler"`` (the Euler angles of
            ``euler_seq`` as state, for users who want them). The Euler-angle state stops with an
            error when ``|sin(theta)|`` (``|cos(theta)|`` for Tait-Bryan) falls below
            ``lock_tolerance``: near gimbal lock its equations are singular. Output orientations
            are quaternions either way.

    Returns:
        A :class:`Trajectory` with ``omega`` (*batch, T, 3) and ``orientation`` (*batch, T, 4) or None.
    """
    if not isinstance(model, AbstractModel):
        raise TypeError(
            f"model must be a rigidjax scene such as FreeBody or HeavyTop, got {type(model).__name__}."
        )
    if not isinstance(state0, State):
        raise TypeError(f"state0 must be a rigidjax.State, got {type(state0).__name__}.")
    if accuracy == "exact":
        return _simulate_exact(model, state0, ts, throw=throw)
    if isinstance(solver, HeavyTopSplitting | LiePoissonSplitting | RKMK):
        # Structure-preserving solvers keep their own state layout (unscaled omega or L, unit
        # quaternion) and run at a fixed step: they cannot go through the scaled, adaptive path.
        if dt0 is None:
            raise ValueError(
                f"{type(solver).__name__} runs at a fixed step: pass dt0 (s), e.g. simulate(..., "
                "solver=solver, dt0=1e-3). rtol, atol and stepsize_controller do not apply to it."
            )
        if rtol is not None or atol is not None or stepsize_controller is not None:
            raise ValueError(
                f"{type(solver).__name__} runs at the fixed step dt0; rtol, atol and stepsize_controller "
                "do not apply to it (for an adaptive Lie-group solver call diffrax.diffeqsolve with "
                "rigidjax.RKMK directly)."
            )
        return simulate_structure_preserving(model, state0, ts, solver, float(dt0), args=args)
    if accuracy not in PRESETS:
        raise ValueError(f"accuracy must be one of 'fast', 'balanced', 'precise', 'exact'; got {accuracy!r}.")
    if state0.orientation is None and model.needs_orientation:
        raise ValueError(
            f"{type(model).__name__} needs an orientation: pass State(omega, orientation=q) with a unit "
            "quaternion q (e.g. rigidjax.quat_from_euler(angles))."
        )
    if representation not in ("quaternion", "euler"):
        raise ValueError(f"representation must be 'quaternion' or 'euler', got {representation!r}.")
    if representation == "euler":
        if state0.orientation is None:
            raise ValueError("representation='euler' needs an initial orientation in state0.")
        is_proper_sequence(euler_seq)  # validates the sequence name
    ts = jnp.asarray(ts)
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(f"ts must be a 1-D array of at least one time, got shape {tuple(ts.shape)}.")
    dtype = _float_dtype(
        state0.omega, state0.orientation, *jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))
    )
    ts = ts.astype(dtype)
    omega0 = state0.omega.astype(dtype)
    q0 = None if state0.orientation is None else state0.orientation.astype(dtype)
    model = jax.tree_util.tree_map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, model)
    preset_solver, preset_rtol = PRESETS[accuracy]
    solver_from_preset = solver is None
    solver = preset_solver() if solver is None else solver
    # Arrays, not Python floats, so that a new tolerance does not trigger a recompilation.
    # A preset never asks for less than ten roundoff units (float32: 1.2e-6).
    floor = 10 * float(jnp.finfo(dtype).eps)
    rtol = jnp.asarray(max(preset_rtol, floor) if rtol is None else rtol, dtype)
    atol = rtol if atol is None else jnp.asarray(atol, dtype)
    if stepsize_controller is None:
        # "precise" lands a step on every sample time: Dopri8's dense output is accurate to ~1e-9
        # only, far worse than its steps; the other presets' interpolants are within their tolerance.
        step_ts = ts if accuracy == "precise" and solver_from_preset else None
        dtmax = None
        if representation == "euler":
            # The gimbal-lock event is checked at step ends (signed sin/cos theta): at most 0.5 rad
            # of turn per step, so a step cannot jump over the lock unseen (a turn about the line of
            # nodes is integrated exactly, and the controller would otherwise take 1-2 s steps).
            speed = jnp.max(jnp.linalg.norm(jnp.asarray(state0.omega, dtype), axis=-1))
            dtmax = jnp.where(speed > 0, 0.5 / jnp.where(speed > 0, speed, 1.0), jnp.inf)
        stepsize_controller = diffrax.PIDController(
            rtol=rtol, atol=atol, norm=_max_norm, step_ts=step_ts, dtmax=dtmax
        )
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    if chunk_size is None:
        chunk_size = 1024 if jax.default_backend() == "cpu" else 65536
    if max_steps < 1 or chunk_size < 1:
        raise ValueError("max_steps and chunk_size must be positive integers.")
    return _simulate_impl(
        model,
        omega0,
        q0,
        ts,
        args,
        solver=solver,
        controller=stepsize_controller,
        adjoint=adjoint,
        dt0=dt0,
        max_steps=int(max_steps),
        chunk_size=int(chunk_size),
        sort=bool(sort_by_speed),
        throw=bool(throw),
        euler_seq=euler_seq if representation == "euler" else None,
        lock_tolerance=float(lock_tolerance),
    )
