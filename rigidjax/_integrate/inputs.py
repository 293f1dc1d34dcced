"""simulate's run-time checks of its inputs: one program that returns the failed conditions for
concrete inputs, ``eqx.error_if`` in the user's program for traced ones."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import (
    as_float_array,
    check_finite,
    check_flag,
    check_times,
    check_unit_quaternion,
    checks_done,
    collected_failures,
    error_if,
    evaluated_now,
    is_traced,
    known_values,
    packed_failures,
    raise_collected,
)
from .._dynamics.inertia_checks import check_inertia
from .._kinematics.euler import _euler_from_quat
from .formulations import lock_distance

__all__ = ["check_model", "check_options", "check_solver_steps", "check_state", "checked_inputs"]


def check_solver_steps(solver, stepsize_controller):
    """A diffrax ``solver`` must integrate one ODE (diffrax's own error for a partitioned solver was
    ``TermAndSolverIncompatible``), and without an error estimate it needs a fixed-step controller:
    diffrax's own error names neither argument."""
    if solver is None:
        return
    structure = getattr(solver, "term_structure", diffrax.AbstractTerm)
    if not (isinstance(structure, type) and issubclass(structure, diffrax.AbstractTerm)):
        raise ValueError(
            f"simulate: solver={type(solver).__name__}() integrates a system split into parts (its terms: "
            f"{structure}), such as positions and momenta or an implicit-explicit pair; simulate gives the "
            "solver one ODE, d(state)/dt = f(t, state): use an ODE solver such as diffrax.Tsit5() or "
            "diffrax.Dopri8(), or one of rigidjax.solvers (RKMK, LiePoissonSplitting, HeavyTopSplitting)."
        )
    if isinstance(solver, diffrax.AbstractAdaptiveSolver):
        return
    if not isinstance(stepsize_controller, diffrax.ConstantStepSize | diffrax.StepTo):
        raise ValueError(
            f"simulate: solver={type(solver).__name__}() has no error estimate, so an adaptive step-size "
            "controller cannot choose its steps: pass a fixed step, dt0=... with "
            "stepsize_controller=diffrax.ConstantStepSize() (or the steps' times with "
            "diffrax.StepTo(ts=...)), or a solver with an error estimate such as diffrax.Tsit5()."
        )


def check_state(omega0, q0, where: str):
    """The initial state's run-time checks: finite ``omega``, unit ``orientation`` (or None)."""
    omega0 = check_finite(omega0, "state0.omega", where)
    if q0 is not None:
        q0 = check_unit_quaternion(q0, "state0.orientation", where)
    return omega0, q0


def check_model_field(label: str, value, where: str, core: int | None = None):
    """Run-time checks of one per-body array of a scene: a physical ``inertia`` (``core`` its
    per-body ndim, None: from its shape), finite values; each scene's own rules are
    :meth:`AbstractModel.leaf_rules`."""
    if label == "inertia":
        return check_inertia(value, name=f"{where}: inertia", tensor=None if core is None else core == 2)
    value = as_float_array(value, f"model field {label!r}")
    value = error_if(value, ~jnp.isfinite(value), f"{where}: model field {label!r} contains NaN or inf.")
    return value


def check_model(model, where: str):
    """``model`` with every per-body array run-time checked (:func:`check_model_field`)."""
    leaves, rules = model.body_leaves(), model.leaf_rules()
    checked = []
    for leaf in leaves:
        value = check_model_field(leaf.label, leaf.get(model), where, leaf.core)
        if leaf.label in rules:
            bad, rule = rules[leaf.label]
            value = error_if(value, bad(value), f"{where}: model field {leaf.label!r} {rule}.")
        checked.append(value)
    return _checked_torque_params(model.replace_body_leaves(leaves, checked), where)


def _checked_torque_params(model, where: str):
    """``model`` with the numbers each ``Torque(fn, params=...)`` hands its function checked to be
    finite: a NaN there would surface only as a step size that collapsed at the first step."""
    for i, torque in enumerate(getattr(model, "torques", ())):
        params = getattr(torque, "params", None)
        if params is None:
            continue
        message = f"{where}: model field 'torques[{i}].params' contains NaN or inf."

        def check(x, message=message):
            if isinstance(x, float) and not np.isfinite(x):
                raise ValueError(message)
            return error_if(x, ~jnp.isfinite(x), message) if eqx.is_inexact_array(x) else x

        model = eqx.tree_at(lambda m, i=i: m.torques[i].params, model, jax.tree.map(check, params))
    return model


def checked_inputs(model, omega0, q0, ts, euler_seq, lock_tolerance):
    """simulate's inputs after their run-time checks. With concrete inputs the checks are a program
    of their own that returns the failed conditions, from which a ``ValueError`` is raised here: it
    holds no host callback, so JAX's persistent compilation cache keeps it and a second run in a new
    process compiles nothing. The tracers of an eager grad or jvp carry their primal values: those
    are checked the same way, and the differentiated program gets no checks of its own. Inputs
    without values (the user's jit or vmap) get ``eqx.error_if`` checks in the user's program."""
    values = known_values((model, omega0, q0, ts))
    if values is None:
        return _checks_in_program(model, omega0, q0, ts, euler_seq, lock_tolerance)
    checked, failures = evaluated_now(_checks_collected, *values, euler_seq, lock_tolerance)
    raise_collected(failures)
    if not is_traced(model, omega0, q0, ts):
        return checked
    return _checked_traced(model, omega0, q0, ts, euler_seq, lock_tolerance)


@eqx.filter_jit
def _checked_traced(model, omega0, q0, ts, euler_seq, lock_tolerance):
    """What the checks do to the tracers of an eager grad or jvp, whose values passed them already
    (the unit quaternion's division by its norm): one compiled program. Called op by op, each of
    the checks' operations on a tracer compiled a program of its own, about 45 for a free body (a
    third of the first ``jax.grad`` call's time), their conditions then unused."""
    with checks_done():
        return _checks_in_program(model, omega0, q0, ts, euler_seq, lock_tolerance)


@eqx.filter_jit
def _checks_collected(model, omega0, q0, ts, euler_seq, lock_tolerance):
    with collected_failures() as failures:
        checked = _checks_in_program(model, omega0, q0, ts, euler_seq, lock_tolerance)
    return checked, packed_failures(failures)


def _checks_in_program(model, omega0, q0, ts, euler_seq, lock_tolerance):
    model = check_model(model, "simulate")
    omega0, q0 = check_state(omega0, q0, "simulate")
    ts = check_times(ts, "simulate")
    if euler_seq is not None:
        q0 = error_if(
            q0,
            lock_distance(_euler_from_quat(q0, euler_seq), euler_seq) < lock_tolerance,
            f"simulate: the initial orientation is within {lock_tolerance:g} of gimbal lock for the "
            f"Euler-angle state (seq={euler_seq!r}); use representation='quaternion'.",
        )
    return model, omega0, q0, ts


# The options that take an object: its base class and an example of one.
_OBJECT_OPTIONS = {
    "solver": (diffrax.AbstractSolver, "a diffrax solver such as diffrax.Tsit5() or rigidjax.solvers.RKMK()"),
    "stepsize_controller": (
        diffrax.AbstractStepSizeController,
        "a diffrax step-size controller such as diffrax.PIDController(rtol=1e-8, atol=1e-8)",
    ),
    "adjoint": (diffrax.AbstractAdjoint, "a diffrax adjoint such as diffrax.ForwardMode()"),
}


def check_options(*, flags, objects, dt0, lock_tolerance):
    """simulate's options that need no values of the scene, checked before anything runs: ``flags``
    (name: value) are ``True`` or ``False`` (a string such as ``"no"`` would otherwise count as
    true), ``objects`` (name: value) are None or instances of their diffrax base class, ``dt0`` is
    None or a positive finite step where its value is known, and ``lock_tolerance`` a number in
    ``(0, 1)``. A ``TypeError`` or ``ValueError`` naming the option otherwise."""
    for name, value in flags.items():
        check_flag(value, name, "simulate")
    for name, value in objects.items():
        base, example = _OBJECT_OPTIONS[name]
        if value is None or isinstance(value, base):
            continue
        if isinstance(value, type):
            got = f"the class {value.__name__} itself (an instance is needed: {value.__name__}(...))"
        else:
            got = f"{type(value).__name__} {value!r}"
        raise TypeError(f"simulate: {name} must be {example}; got {got}.")
    if isinstance(objects.get("adjoint"), diffrax.BacksolveAdjoint):
        raise ValueError(
            "simulate: adjoint=BacksolveAdjoint() does not support the way simulate saves its samples "
            "(SaveAt(fn=...)); leave adjoint out (the default works in both modes) or pass "
            "diffrax.RecursiveCheckpointAdjoint(), DirectAdjoint() or ForwardMode()."
        )
    if dt0 is not None:
        if isinstance(dt0, bool | np.bool_):
            raise TypeError(f"simulate: dt0 must be a step in seconds, got {dt0!r}.")
        if np.ndim(dt0) != 0:
            raise ValueError(f"simulate: dt0 must be a single step (s), got shape {np.shape(dt0)}.")
        values = known_values((dt0,))
        if values is not None and not (np.isfinite(float(values[0])) and float(values[0]) > 0):
            raise ValueError(f"simulate: dt0 must be a positive finite step (s), got {float(values[0])!r}.")
    if isinstance(lock_tolerance, bool) or not isinstance(lock_tolerance, int | float | np.number):
        raise TypeError(f"simulate: lock_tolerance must be a number in (0, 1), got {lock_tolerance!r}.")
    if not 0 < float(lock_tolerance) < 1:
        raise ValueError(
            "simulate: lock_tolerance must be a number in (0, 1) (the smallest |sin(theta)| the "
            f"Euler-angle state may reach; |cos(theta)| for Tait-Bryan sequences), got {lock_tolerance!r}."
        )
