"""``simulate``: one entry point for every way rigidjax moves a scene through time.

It checks the arguments, resolves the accuracy preset (or the user's solver) into a formulation, a
solver and a step-size rule, and hands the batch to :func:`.chunked.integrate`, which runs it
through the one driver; ``accuracy="exact"`` evaluates the closed form instead (:mod:`.exact`).
"""

import math
from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import (
    check_positive_int,
    check_times_shape,
    error_if,
    float_dtype,
    floats_as_arrays,
    known_values,
    times_in_dtype,
)
from .._dynamics.models import AbstractModel, HeavyTop
from .._dynamics.state import State
from .._kinematics.euler import is_proper_sequence
from . import batching, driver
from . import progress as _progress
from .chunked import integrate, max_norm
from .error_estimate import with_error_estimate
from .exact import nan_from_first_failure, simulate_exact
from .failures import error_if_failed, raise_if_exact_failed, raise_if_failed
from .formulations import LieGroupODE, ScaledODE, SplittingODE
from .inputs import check_options, check_solver_steps, checked_inputs
from .presets import (
    MAX_STEPS_LIMIT,
    MIN_MAX_STEPS,
    PRESETS,
    FaultStopPIDController,
    default_chunk_size,
    default_max_steps,
    preset_rtol,
    preset_solver,
)
from .solvers import STRUCTURE_PRESERVING, HeavyTopSplitting, LiePoissonSplitting
from .trajectory import Trajectory


def _fixed_step_setup(model, state0, ts, solver, dt0, tolerances_given):
    """Formulation, step grid and step count of a structure-preserving solver at the fixed step dt0."""
    name = type(solver).__name__
    if dt0 is None:
        raise ValueError(
            f"{name} runs at a fixed step: pass dt0 (s), e.g. simulate(..., solver=solver, dt0=1e-3). "
            "rtol, atol and stepsize_controller do not apply to it."
        )
    if tolerances_given:
        raise ValueError(
            f"{name} runs at the fixed step dt0; rtol, atol and stepsize_controller do not apply to it "
            "(for an adaptive Lie-group solver call diffrax.diffeqsolve with rigidjax.solvers.RKMK "
            "directly)."
        )
    if isinstance(solver, HeavyTopSplitting):
        if not isinstance(model, HeavyTop) or model.torques:
            raise ValueError(
                "HeavyTopSplitting integrates a HeavyTop under gravity alone; for extra torques or "
                f"other scenes use RKMK (got {type(model).__name__})."
            )
        formulation = SplittingODE(heavy_top=True, order=solver.splitting_order)
    elif isinstance(solver, LiePoissonSplitting):
        if not model.torque_free:
            raise ValueError(
                "LiePoissonSplitting integrates torque-free bodies only; use HeavyTopSplitting for a "
                f"HeavyTop or RKMK for torques (got {type(model).__name__})."
            )
        formulation = SplittingODE(heavy_top=False, order=solver.splitting_order)
    else:
        formulation = LieGroupODE()
    try:
        ts_np = np.asarray(ts, dtype=np.float64)
    except jax.errors.TracerArrayConversionError as err:
        raise ValueError(
            f"simulate with {name}: ts must be concrete (they fix the number of steps); do not trace "
            "them under jit."
        ) from err
    if np.any(np.diff(ts_np) <= 0) or not np.all(np.isfinite(ts_np)):
        raise ValueError("ts must be finite and strictly increasing; ts[0] is the initial time.")
    if isinstance(dt0, jax.core.Tracer):
        raise ValueError(
            f"simulate with {name}: dt0 must be concrete (it fixes the number of steps); do not trace "
            "it under jit or differentiate with respect to it."
        )
    if isinstance(dt0, jax.Array | np.ndarray | np.number) and np.ndim(dt0) == 0:
        dt0 = dt0.item()
    if isinstance(dt0, bool) or not (isinstance(dt0, int | float) and np.isfinite(dt0) and dt0 > 0):
        raise ValueError(f"dt0 must be a positive number (it fixes the number of steps), got {dt0!r}.")
    grid, n_steps = driver.fixed_step_grid(ts_np, float(dt0))
    return formulation, grid, n_steps


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
    max_steps: int | None = None,
    chunk_size: int | None = None,
    sort_by_speed: bool = True,
    throw: bool = True,
    args: Any = None,
    representation: str = "quaternion",
    euler_seq: str = "zxz",
    lock_tolerance: float = 1e-3,
    progress: bool | Callable[[int, int], None] = False,
    error_estimate: bool = False,
) -> Trajectory:
    """Integrates ``model`` from ``state0`` and samples it at times ``ts``.

    **Arguments:**

    - `model`: a scene (:class:`FreeBody`, :class:`RigidBody`, :class:`HeavyTop`,
      :class:`Gyrostat`), possibly batched: a leading batch axis on its array fields.
    - `state0`: initial :class:`State`; its batch axes broadcast against the model's. With
      ``orientation=None`` and a scene that does not need it, only Euler's equations (three per
      body) are integrated.
    - `ts`: strictly increasing sample times (s), shape ``(T,)``; ``ts[0]`` is the initial time.
    - `accuracy`: ``"fast"`` (Tsit5, rtol 1e-5), ``"balanced"`` (Dopri8, 1e-8) or ``"precise"``
      (Dopri8, 1e-11, a step on every sample time); on 1024 bodies or more, when not differentiated,
      Dopri8 runs with its stages written out (:class:`rigidjax.solvers.UnrolledDopri8`: the same
      values, cheaper steps, a longer compile). Or ``"exact"``: a closed form, no integration. For a
      torque-free body, omega by Jacobi elliptic functions and, when ``state0`` has an orientation,
      the orientation by Jacobi's theta form of the third-kind integral (see
      :func:`rigidjax.torque_free_motion`); an inertia tensor is diagonalised first and the motion
      turned back into the body axes (a derivative with respect to the tensor itself is a
      ``ValueError``: its principal axes have none where moments coincide). For Lagrange's top, a
      :class:`HeavyTop` with principal moments ``I1 = I2`` about the pivot, the centre of mass on
      the body z axis (above or below the pivot) and no extra torques, the nutation by Jacobi
      functions and the precession and spin by third-kind integrals, including tops that pass
      through the vertical; a top given by its tensor about the pivot, symmetric about the line
      through the centre of mass, runs in the axes of that symmetry (no derivative with respect to
      the tensor or com); any other HeavyTop is a ``ValueError`` naming the condition it fails.
      Accurate to roundoff at any time (up to the conditioning of the motion); the cost does not
      grow with the duration.
      Differentiable in both modes: with an orientation the derivative is every sample's Jacobian
      (forward mode, contracted with the tangents), so that a reverse-mode gradient costs about
      one JVP and keeps 7 numbers per body, sample time and differentiated input component (42
      for the inertia and omega0; the Gradients guide has the measurements).
      ``rigidjax.solvers.PRESETS`` lists the presets.
    - `solver`: any diffrax solver instead of the preset's; or a structure-preserving solver from
      ``rigidjax.solvers`` (:class:`RKMK`, :class:`LiePoissonSplitting`,
      :class:`HeavyTopSplitting`), which runs at the fixed step ``dt0``: each interval
      ``[ts[i], ts[i+1]]`` is cut into ``ceil((ts[i+1] - ts[i]) / dt0)`` equal steps so samples fall
      on steps, ``ts`` must be concrete, and the scene's parameters come from ``model`` (the
      solver's own numeric fields are not used).
    - `rtol`, `atol`: dimensionless tolerances of the preset's step-size controller (each body's
      omega is measured against its own scale, the quaternion is O(1)), each in ``[0, 1)`` and not
      both below the dtype's roundoff unit; ``atol`` defaults to ``rtol``.
    - `stepsize_controller`: any diffrax step-size controller (e.g. ``ConstantStepSize`` with
      ``dt0``) instead of the preset's ``PIDController``; it carries its own tolerances (``rtol``
      and ``atol`` beside it are an error). A ``PIDController`` without a ``dtmax`` gets the
      presets' bound on each step, the time scale of the motion linearised about the initial
      state (for derivatives at rest; moving bodies' steps stay below it). With
      ``accuracy="exact"``, which integrates nothing, ``solver``, ``rtol``, ``atol``,
      ``stepsize_controller``, ``dt0``, ``adjoint`` and ``representation="euler"`` are an error
      rather than unused.
    - `dt0`: the first (or fixed) step (s).
    - `adjoint`: a diffrax adjoint, always used when given (not ``BacksolveAdjoint``, which does
      not support the way the samples are saved). Default: ``diffrax.ForwardMode()``
      when ``model``, ``state0``, ``ts`` or ``args`` carry forward-mode tangents (``jax.jvp``,
      ``jax.jacfwd``, also under ``jit`` or ``vmap``), else diffrax's checkpointed reverse mode
      (``RecursiveCheckpointAdjoint``: ``jax.grad``, ``jax.jacrev``, ``jax.vjp``), so both modes work
      without choosing; with both modes nested (``jax.hessian``, ``jacrev(jacfwd(f))``) or reverse
      mode twice (``jacrev(jacrev(f))``)
      ``diffrax.DirectAdjoint()``, and so in reverse mode on several devices
      (:func:`rigidjax.use_cpu_cores`; the checkpointed adjoint fails there through
      ``shard_map``). A ``jax.jit``, ``jax.checkpoint`` or ``lax`` loop or branch between
      ``jacfwd`` and ``simulate`` (``jacfwd(jit(f))``, ``simulate`` in a ``lax.scan`` body) hides
      the tangents: pass ``adjoint=diffrax.ForwardMode()`` (or ``DirectAdjoint()``) there, or jit
      outside the ``jacfwd``.
    - `max_steps`: step limit per chunk; reaching it is an error (or NaN rows with
      ``throw=False``). Default: 100 steps per turn of the fastest body over the span of ``ts``
      (``max|omega0| (ts[-1] - ts[0]) / 2 pi`` turns), at least 1e5, rounded up to a power of two;
      a span of more than 2^30 / 100 (about 1e7) turns is an error that says so (hours of steps,
      ``accuracy="exact"`` where a closed form exists, or ``max_steps`` to integrate anyway);
      1e5 inside ``jit``, where the values are unknown, and with ``adjoint=diffrax.DirectAdjoint()``
      (whose loop is sized by the limit). Otherwise the limit costs no memory (reverse mode keeps
      ``log(max_steps)`` checkpoints).
    - `chunk_size`: bodies per shared-step chunk, at most (the chunks are made equal, so the last
      one is not mostly padding). Default: 256 on CPU (cache-sized chunks run one after another,
      and on a single CPU device, outside ``jax.jit``, in one block per core, each block from its
      own Python thread: the same trajectories to the bit); on accelerators 512 per core (67584
      on an H200; ``benchmarks/README.md``), fewer where the samples of one chunk would take over
      an eighth of the device's memory. With
      ``accuracy="exact"``: bodies evaluated together (default on CPU: 2^17 body-samples per
      block, which keeps the closed form's intermediates in the cache; one block on accelerators).
    - `sort_by_speed`: group bodies of similar angular-velocity scale into the same chunk, and
      torque-free bodies of one speed class (a factor ``2^(1/4)``) by the period of their motion
      and the time of their next flip, so that the bodies of a chunk flip at the same times and
      the shared step is long in between (10^4 tennis-racket bodies, "balanced": 102 instead of
      126 steps per chunk started in phase, 115 instead of 127 at random phases). ``False``:
      chunks of the bodies in their given order.
    - `throw`: raise when a body fails during the run (default); the error names the first
      failed body (its index in the batch), the sample times around the failure and the cause
      (under the user's ``jit``: the cause). Invalid inputs (NaN or inf, non-physical inertia, a
      non-unit quaternion, unsorted times) raise whatever ``throw`` says: a check of the inputs
      is never a failure of one body. With ``throw=False`` a failed body is flagged in
      ``Trajectory.success`` and is NaN from its failure on, while every other body keeps its
      result: bodies share steps within a chunk, so a chunk stopped by a body whose torque or state
      turned NaN, or that needed more than ``max_steps``, is run again body by body (not inside the
      user's ``jax.jit``, where the chunk's bodies are flagged together: call ``simulate`` outside
      the ``jit``, or pass ``chunk_size=1``). With ``accuracy="exact"`` a body fails where its
      closed form is NaN or inf (inputs beyond the dtype's range) or its phase is rounded by more
      than 1e-3 rad (float64: a phase of 4.5e12 rad, float32: 8.4e3 rad; the samples would be
      noise), and is NaN from that sample on too.
    - `args`: passed to user torques as ``fn(t, state, args)``; its floating-point numbers become
      JAX arrays (one compiled program for every value), as a torque's ``params`` do.
    - `representation`: how the orientation is integrated when there is one: ``"quaternion"``
      (default; unit norm kept without drift) or ``"euler"`` (the Euler angles of ``euler_seq`` as
      state, for users who want them). The Euler-angle state stops with an error when
      ``|sin(theta)|`` (``|cos(theta)|`` for Tait-Bryan) falls below ``lock_tolerance``: near gimbal
      lock its equations are singular. Output orientations are quaternions either way.
    - `euler_seq`, `lock_tolerance`: the sequence and the gimbal-lock margin of
      ``representation="euler"``.
    - `progress`: ``True`` prints a progress line to stderr as the batch runs (bodies done of the
      total, elapsed time, an estimate of the time left); a callable is called as
      ``progress(done_bodies, total_bodies)`` instead: with 0 first, then after each block, the
      total last. The batch then
      runs from Python in up to 20 blocks of whole chunks (the same bodies per chunk, so the same
      result), one compiled program for all blocks; the last block is padded to the same shape. Not
      under ``jax.jit``, ``grad`` or ``vmap`` (a ``ValueError``). ``False`` (default): one program for
      the whole batch.
    - `error_estimate`: ``True`` solves the batch a second time, more accurately, and stores a
      per-body error estimate in ``stats`` (:meth:`Trajectory.error_estimate`): for the presets
      and a ``PIDController`` the same solver at the tolerances divided by 100, for a fixed step
      (``dt0``, ``ConstantStepSize``) half the step with a Richardson correction for the solver's
      order (float32 results with ``jax_enable_x64`` on: the second solve in float64); the
      estimate is twice the difference of the two solutions. Measured, it lay between 1.9 and
      2.4 times the true error on tumbling, tennis-racket and heavy-top batches
      (``docs/guides/accuracy.md``), down to 1.4 for the bodies nearest a separatrix and 1.7 with
      ``representation="euler"``, never below 1; where the true error is at the roundoff floor (which grows
      like ``eps/|s|`` near a torque-free separatrix) it stays above it. For ``accuracy="exact"``
      the difference of the closed form at inputs one roundoff unit away: how rounding is
      amplified, an order of magnitude, not a bound (float32 with x64 on: twice the difference
      to the float64 closed form). Every estimate is at least ten roundoff
      units. The cost is the second solve: about the first's again (no new compile for the
      presets). ``throw`` applies to the first solve; a body whose second solve fails gets an inf
      estimate. ``progress`` makes one report over both solves: its total is twice the bodies.

    **Returns:**

    A :class:`Trajectory` with ``omega`` ``(*batch, T, 3)`` and ``orientation``
    ``(*batch, T, 4)`` or None; ``stats["num_steps"]`` holds the steps of each chunk.
    """
    if not isinstance(model, AbstractModel):
        raise TypeError(
            f"model must be a rigidjax scene such as FreeBody or HeavyTop, got {type(model).__name__}."
        )
    if not isinstance(state0, State):
        raise TypeError(f"state0 must be a rigidjax.State, got {type(state0).__name__}.")
    check_options(
        flags=dict(throw=throw, sort_by_speed=sort_by_speed, error_estimate=error_estimate),
        objects=dict(solver=solver, stepsize_controller=stepsize_controller, adjoint=adjoint),
        dt0=dt0,
        lock_tolerance=lock_tolerance,
    )
    if error_estimate:
        return with_error_estimate(
            simulate, model, state0, ts, accuracy=accuracy, solver=solver, rtol=rtol, atol=atol,
            stepsize_controller=stepsize_controller, dt0=dt0, adjoint=adjoint, max_steps=max_steps,
            chunk_size=chunk_size, sort_by_speed=sort_by_speed, throw=throw, args=args,
            representation=representation, euler_seq=euler_seq, lock_tolerance=lock_tolerance,
            progress=progress,
        )  # fmt: skip
    args = floats_as_arrays(args)
    report = _progress.check_progress(progress)
    batch = batching.batch_shape(model, state0.omega, state0.orientation)
    if math.prod(batch) == 0:
        raise ValueError(
            f"simulate: the batch of bodies is empty (batch shape {batch}, from the model's and "
            "state0's leading axes): there is no body to integrate."
        )
    chunk_size = check_positive_int(chunk_size, "chunk_size", "simulate")
    max_steps = check_positive_int(max_steps, "max_steps", "simulate")
    if max_steps is not None and max_steps > MAX_STEPS_LIMIT:
        raise ValueError(
            f"simulate: max_steps must be at most {MAX_STEPS_LIMIT:,} (2**31 - 1, the largest 32-bit "
            f"integer; so many steps take hours), got {max_steps:,}."
        )
    if accuracy == "exact":
        _check_no_integrator_options(
            solver=solver, rtol=rtol, atol=atol, stepsize_controller=stepsize_controller, dt0=dt0,
            adjoint=adjoint, representation=None if representation == "quaternion" else representation,
        )  # fmt: skip
        if report is not None:  # one closed-form program: all bodies at once
            _progress.report_start(report, math.prod(batch), model, state0, ts)
        traj = simulate_exact(model, state0, ts, chunk_size)
        if report is not None:
            jax.block_until_ready(traj.omega)
            report(math.prod(batch), math.prod(batch))
        return raise_if_exact_failed(traj) if throw else nan_from_first_failure(traj)
    if accuracy not in PRESETS:  # also with a fixed-step solver, which ignores it: a typo is named
        raise ValueError(f"accuracy must be one of 'fast', 'balanced', 'precise', 'exact'; got {accuracy!r}.")
    ts, given_ts = check_times_shape(ts), ts  # NumPy times closed over by a jit are known, not traced
    fixed_step = isinstance(solver, STRUCTURE_PRESERVING)
    if fixed_step:
        tolerances_given = rtol is not None or atol is not None or stepsize_controller is not None
        formulation, grid, n_steps = _fixed_step_setup(model, state0, given_ts, solver, dt0, tolerances_given)
    else:
        check_solver_steps(solver, stepsize_controller)
    if not fixed_step and stepsize_controller is not None and (rtol is not None or atol is not None):
        raise ValueError(
            "simulate: rtol and atol set the preset's step-size controller; with stepsize_controller "
            f"given, set the tolerances on it instead (got rtol={rtol!r}, atol={atol!r})."
        )
    if state0.orientation is None and model.needs_orientation:
        raise ValueError(
            f"{type(model).__name__} needs an orientation: pass State(omega, orientation=q) with a unit "
            "quaternion q (e.g. rigidjax.quat_from_euler(angles))."
        )
    if representation not in ("quaternion", "euler"):
        raise ValueError(f"representation must be 'quaternion' or 'euler', got {representation!r}.")
    if representation == "euler":
        if fixed_step:
            raise ValueError(f"representation='euler' needs a diffrax solver, not {type(solver).__name__}.")
        if state0.orientation is None:
            raise ValueError("representation='euler' needs an initial orientation in state0.")
    try:  # the name is checked also where only the Euler-angle state would read it
        is_proper_sequence(euler_seq)
    except ValueError as err:
        raise ValueError(f"simulate: euler_seq: {err}") from None
    dtype = float_dtype(
        state0.omega, state0.orientation, *jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))
    )
    ts = times_in_dtype(ts, dtype)
    omega0 = state0.omega.astype(dtype)
    q0 = None if state0.orientation is None else state0.orientation.astype(dtype)
    model = jax.tree_util.tree_map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, model)
    if chunk_size is None:
        chunk_size = default_chunk_size(ts.shape[0], jnp.dtype(dtype).itemsize)
    # The user's adjoint, or the one that works in the mode of differentiation (driver.default_adjoint).
    adjoint_chosen = adjoint is None
    adjoint = driver.default_adjoint(model, state0, ts, args) if adjoint_chosen else adjoint
    if fixed_step and max_steps is not None and n_steps > max_steps:
        raise ValueError(
            f"simulate: the fixed step dt0 takes {n_steps} steps over ts, more than max_steps={max_steps}; "
            "raise max_steps (or leave it out: a fixed step takes exactly its grid's steps) or take a "
            "larger dt0."
        )
    if max_steps is None:
        # DirectAdjoint runs nested scans sized by max_steps: its cost grows with the limit.
        direct = isinstance(adjoint, diffrax.DirectAdjoint)
        max_steps = MIN_MAX_STEPS if direct else default_max_steps(omega0, ts)
    if fixed_step:
        controller = diffrax.StepTo(ts=jnp.asarray(grid, dtype)) if n_steps else diffrax.ConstantStepSize()
        dt0 = None
        max_steps = max(n_steps, 1)  # exactly the grid's steps
    else:
        formulation = ScaledODE(euler_seq if representation == "euler" else None, float(lock_tolerance))
        tolerance = preset_rtol(accuracy, dtype)
        solver_from_preset = solver is None
        if solver is None:
            differentiated = driver.is_differentiated(model, state0, ts, args)
            n_bodies = math.prod(batching.batch_shape(model, omega0, q0))
            solver = preset_solver(accuracy, differentiated, n_bodies)
        if dt0 is not None:
            # Traced, not a static argument of the compiled solve: a sweep of steps compiles once.
            dt0 = jnp.asarray(dt0, dtype)
        controller = stepsize_controller
        if controller is None:
            controller = _preset_controller(
                accuracy, solver_from_preset, tolerance, rtol, atol, ts, omega0, dtype, representation
            )
    euler = formulation.euler_seq if isinstance(formulation, ScaledODE) else None
    model, omega0, q0, ts = checked_inputs(model, omega0, q0, ts, euler, float(lock_tolerance))

    def run(model, omega0, q0, chunk_size, sort):
        def call(adjoint):
            return integrate(
                model, omega0, q0, ts, args, controller, solver, adjoint, dt0, formulation=formulation,
                max_steps=int(max_steps), chunk_size=int(chunk_size), sort=bool(sort),
            )  # fmt: skip

        return driver.solve_in_either_mode(call, adjoint, adjoint_chosen)

    threads = _progress.host_threads(model, omega0, q0, ts, args, chunk_size)
    if report is None and threads == 1:
        traj = run(model, omega0, q0, chunk_size, sort_by_speed)
    else:
        traj = _progress.run_in_blocks(
            run, report, model, omega0, q0, ts, args, formulation, chunk_size, sort_by_speed, threads
        )
    if isinstance(traj.success, jax.core.Tracer):  # inside the user's jit: no values to look at
        traj = _in_the_hemisphere_of(traj, q0) if representation == "euler" else traj
        return error_if_failed(traj, max_steps, formulation) if throw else traj
    traj = _isolate_faults(traj, model, omega0, q0, run)
    if representation == "euler":  # after the faults' reruns, which return their own signs
        traj = _in_the_hemisphere_of(traj, q0)
    if throw:
        raise_if_failed(traj, max_steps, formulation)
    return traj


def _in_the_hemisphere_of(traj, q0):
    """The Euler-angle state's quaternions with the sign of ``q0``: converted from angles, a body's
    trajectory came out as ``-q`` for about half of the initial orientations (the same rotations,
    but not the ``q0`` given, which losses on ``q`` and their gradients see)."""
    first = traj.orientation[..., 0, :]
    sign = jnp.where(jnp.sum(first * jnp.broadcast_to(q0, first.shape), axis=-1) < 0, -1.0, 1.0)
    return eqx.tree_at(
        lambda t: t.orientation, traj, traj.orientation * sign[..., None, None].astype(q0.dtype)
    )


def _isolate_faults(traj, model, omega0, q0, run):
    """Bodies share steps within a chunk: one whose state or torque turns non-finite (the step size
    collapses), or that needs more than ``max_steps``, stops its chunk. Those chunks' bodies are run
    again one by one: each healthy body gets its full result, the faulty one is NaN from its fault on."""
    code = np.asarray(traj.stats["result"]).ravel()
    redo = np.flatnonzero((code == driver.DT_MIN_REACHED) | (code == driver.MAX_STEPS_REACHED))
    if redo.size == 0 or traj.stats["chunk_size"] == 1:
        return traj
    batch = traj.batch_shape
    leaves, flat = batching.flatten_model(model, batch)
    again = run(
        model.replace_body_leaves(leaves, [v[redo] for v in flat]),
        batching.flatten(omega0, batch)[redo],
        None if q0 is None else batching.flatten(q0, batch)[redo],
        1,
        False,
    )
    n = code.size

    def merge(old, new):
        if old is None:
            return None
        core = old.shape[len(batch) :]
        return old.reshape((n,) + core).at[redo].set(new).reshape(old.shape)

    stats = dict(traj.stats)
    for name in ("result", "first_failed_sample", "quaternion_norm_error"):
        stats[name] = merge(traj.stats[name], again.stats[name])
    return Trajectory(
        ts=traj.ts,
        omega=merge(traj.omega, again.omega),
        orientation=merge(traj.orientation, again.orientation),
        model=traj.model,
        success=merge(traj.success, again.success),
        stats=stats,
    )


def _check_no_integrator_options(**options):
    """``accuracy="exact"`` evaluates a closed form: options that configure an integrator are an error
    there rather than silently unused."""
    given = [name for name, value in options.items() if value is not None]
    if given:
        raise ValueError(
            f"simulate: accuracy='exact' is a closed form, no integration: {', '.join(given)} "
            f"{'does' if len(given) == 1 else 'do'} not apply to it; an integrator takes "
            f"{'it' if len(given) == 1 else 'them'}: accuracy='fast', 'balanced' or 'precise'."
        )


def _checked_tolerances(rtol, atol, dtype):
    """``rtol`` and ``atol`` as arrays of ``dtype``, each a single number in ``[0, 1)`` and not both
    below one roundoff unit of ``dtype`` (no step could meet them); a ``ValueError`` naming the
    argument where the values are known, a run-time error under ``jit``."""
    eps = float(jnp.finfo(dtype).eps)
    for name, value in (("rtol", rtol), ("atol", atol)):
        if jnp.ndim(value) != 0:
            raise ValueError(f"simulate: {name} must be a single number, got shape {jnp.shape(value)}.")
    rule = (
        "must be a number in [0, 1) (a tolerance per step, relative to each body's scale of omega; "
        "the quaternion is of size 1)"
    )
    floor = (
        f"rtol and atol must not both be below {np.dtype(dtype).name}'s roundoff unit {eps:.3g}: "
        "no step can meet them"
    )
    values = known_values((rtol, atol))
    if values is not None:
        values = tuple(float(v) for v in values)
        for name, value in zip(("rtol", "atol"), values, strict=True):
            if not 0.0 <= value < 1.0:
                raise ValueError(f"simulate: {name} {rule}, got {value!r}.")
        if max(values) < eps:
            raise ValueError(f"simulate: {floor}; got rtol={values[0]!r}, atol={values[1]!r}.")
        return _device_scalar(values[0], dtype), _device_scalar(values[1], dtype)
    rtol, atol = jnp.asarray(rtol, dtype), jnp.asarray(atol, dtype)
    valid = (rtol >= 0) & (rtol < 1) & (atol >= 0) & (atol < 1) & (jnp.maximum(rtol, atol) >= eps)
    return error_if(rtol, ~valid, f"simulate: rtol and atol each {rule}, and {floor}."), atol


def _device_scalar(value, dtype):
    """A Python number as a 0-d array of ``dtype``, converted on the host and put on the device:
    ``jnp.asarray`` compiles a small program the first time in every process."""
    return jax.device_put(np.asarray(value, dtype))


def _fault_dtmin(ts):
    """The controller's floor on rejected steps: ``min(1e-12 span, 1e-3 min gap)`` of the sample
    times; computed with NumPy where their values are known (eager jnp would compile five small
    programs in each new process, ~0.3 s), in the program otherwise."""
    values = known_values((ts,))
    xp, ts = (np, np.asarray(values[0])) if values is not None else (jnp, ts)
    span = ts[-1] - ts[0]
    min_gap = xp.min(xp.diff(ts)) if ts.shape[0] > 1 else span
    floor = xp.minimum(1e-12 * span, 1e-3 * min_gap)
    return _device_scalar(floor, ts.dtype) if xp is np else floor


def _preset_controller(
    accuracy, solver_from_preset, tolerance, rtol, atol, ts, omega0, dtype, representation
):
    """The preset's ``PIDController`` on the chunk's max norm; ``tolerance``: the preset's, in
    ``dtype`` (:func:`.preset_rtol`)."""
    # Arrays, not Python floats, so that a new tolerance does not trigger a recompilation.
    if rtol is None and atol is None:
        rtol = atol = _device_scalar(tolerance, dtype)
    else:
        rtol = tolerance if rtol is None else rtol
        rtol, atol = _checked_tolerances(rtol, rtol if atol is None else atol, dtype)
    # "precise" lands a step on every sample time: Dopri8's dense output is accurate to ~1e-9 only,
    # far worse than its steps; the other presets' interpolants are within their tolerance.
    step_ts = ts if accuracy == "precise" and solver_from_preset else None
    dtmax = None
    if representation == "euler":
        # The gimbal-lock event is checked at step ends (signed sin/cos theta): at most 0.5 rad of
        # turn per step, so a step cannot jump over the lock unseen (a turn about the line of nodes
        # is integrated exactly, and the controller would otherwise take 1-2 s steps).
        speed = jnp.max(jnp.linalg.norm(omega0, axis=-1))
        dtmax = jnp.where(speed > 0, 0.5 / jnp.where(speed > 0, speed, 1.0), jnp.inf)
    # A body whose torque or state turns NaN makes every trial step fail: with a floor on rejected
    # steps the chunk stops there at once (DT_MIN_REACHED, a fault) instead of after max_steps.
    fault_dtmin = _fault_dtmin(ts)
    return FaultStopPIDController(
        rtol=rtol, atol=atol, norm=max_norm, step_ts=step_ts, dtmax=dtmax, fault_dtmin=fault_dtmin
    )
