"""Every public array function against generated bad input: a clear error or a documented answer.

For each function of the public namespaces, hypothesis corrupts one argument of a good call in one
of six ways -- a NaN or an inf at a random position, a wrong last-axis size, a batch axis that does
not broadcast against another argument's, an empty batch, a complex dtype -- eagerly or under
``jax.jit``, and the outcome must be one of:

- a ``ValueError``, ``TypeError`` or a run-time error from ``eqx.error_if`` whose message names the
  argument (for a batch mismatch: the arguments) and is not one of JAX's own broadcasting or
  indexing errors;
- for an empty batch: results with an empty batch;
- for NaN or inf into the elliptic functions, whose documented rule is "NaN in, NaN out" (a batch
  with one bad element keeps its other results): a NaN result.

A function that answers anything else -- a raw error, a silent NaN, a wrong input accepted -- fails.
``test_every_public_function_is_swept`` keeps the table complete: a public callable is either in it
or named with the test that covers its bad input elsewhere (signatures that are not arrays).
"""

import importlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dop853_free_body
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import rigidjax as rj
from rigidjax import convert, elliptic, kinematics, solvers

I3 = np.array([1.0, 2.0, 2.5])
SYMMETRIC = np.array([1.0, 1.0, 1.5])
W = np.array([0.3, -1.2, 0.8])
Q = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
ANG = np.array([0.3, 1.1, -0.7])
R = np.asarray(rj.matrix_from_quat(Q))
TENSOR = R @ np.diag(I3) @ R.T
COM = np.array([0.0, 0.0, 0.1])
TS = np.linspace(0.0, 1.0, 12)
QS = np.asarray(rj.quat_from_euler(np.stack([0.3 * TS, 0.2 + 0.1 * TS, TS], axis=-1)))
OMEGAS = dop853_free_body(I3, W, TS)[0]  # scipy: no program to compile while the tests are collected


def _accel(t, omega, q, args):
    return rj.euler_equations(I3, omega)


class Arg:
    """One argument: its good value, its core axes (None: any shape is valid) and the words an
    error about it may use (its name first)."""

    def __init__(self, value, core, *names):
        self.value, self.core, self.names = np.asarray(value, float), core, names


def _vec(value, name, *aliases):
    return Arg(value, 1, name, *aliases)


def _scalar(value, name):
    return Arg(value, 0, name)


# name -> (function of the arrays, arguments, rule for NaN and inf: "raise"; "propagate" (NaN in, NaN
# out); "answer" (a False answer: is_physical_inertia); "missing" (NaN marks a missing sample))
SWEEP = {
    # kinematics
    "matrix_from_euler": (lambda a: rj.matrix_from_euler(a, "zxz"), [_vec(ANG, "angles")], "raise"),
    "quat_from_euler": (lambda a: rj.quat_from_euler(a, "xyz"), [_vec(ANG, "angles")], "raise"),
    "euler_from_matrix": (lambda m: rj.euler_from_matrix(m, "zyz"), [Arg(R, 2, "R")], "raise"),
    "euler_from_quat": (lambda q: rj.euler_from_quat(q, "zyx"), [_vec(Q, "q")], "raise"),
    "matrix_from_quat": (rj.matrix_from_quat, [_vec(Q, "q")], "raise"),
    "quat_from_matrix": (rj.quat_from_matrix, [Arg(R, 2, "R")], "raise"),
    "quat_multiply": (rj.quat_multiply, [_vec(Q, "p"), _vec(Q, "q")], "raise"),
    "quat_conjugate": (rj.quat_conjugate, [_vec(Q, "q")], "raise"),
    "quat_rotate": (rj.quat_rotate, [_vec(Q, "q"), _vec(W, "v")], "raise"),
    "quat_normalize": (rj.quat_normalize, [_vec(Q, "q")], "raise"),
    "quat_exp": (kinematics.quat_exp, [_vec(W, "theta")], "raise"),
    "quat_log": (kinematics.quat_log, [_vec(Q, "q")], "raise"),
    "quat_slerp": (
        kinematics.quat_slerp,
        [_vec(Q, "p"), _vec(QS[5], "q"), _scalar(0.3, "fraction")],
        "raise",
    ),
    "quat_angle_between": (kinematics.quat_angle_between, [_vec(Q, "p"), _vec(QS[5], "q")], "raise"),
    "body_angular_velocity": (
        lambda a, r: rj.body_angular_velocity(a, r, "zxz"),
        [_vec(ANG, "angles"), _vec(W, "rates")],
        "raise",
    ),
    "space_angular_velocity": (
        lambda a, r: rj.space_angular_velocity(a, r, "yzx"),
        [_vec(ANG, "angles"), _vec(W, "rates")],
        "raise",
    ),
    "euler_rates": (
        lambda a, w: rj.euler_rates(a, w, "zxz"),
        [_vec(ANG, "angles"), _vec(W, "omega")],
        "raise",
    ),
    # dynamics
    "euler_equations": (
        rj.euler_equations,
        [_vec(I3, "inertia"), _vec(W, "omega"), _vec(W, "torque")],
        "raise",
    ),
    "angular_momentum": (rj.angular_momentum, [Arg(TENSOR, 2, "inertia"), _vec(W, "omega")], "raise"),
    "kinetic_energy": (rj.kinetic_energy, [_vec(I3, "inertia"), _vec(W, "omega")], "raise"),
    "space_angular_momentum": (
        rj.space_angular_momentum,
        [_vec(I3, "inertia"), _vec(W, "omega"), _vec(Q, "orientation")],
        "raise",
    ),
    "free_precession_rate": (
        rj.free_precession_rate,
        [_scalar(1.0, "I1"), _scalar(1.5, "I3"), _scalar(2.0, "omega3")],
        "raise",
    ),
    "principal_axes": (lambda t: rj.principal_axes(t)[0], [Arg(TENSOR, 2, "tensor")], "raise"),
    "check_inertia": (rj.check_inertia, [_vec(I3, "inertia")], "raise"),
    "is_physical_inertia": (rj.is_physical_inertia, [Arg(TENSOR, 2, "inertia")], "answer"),
    "parallel_axis": (
        rj.parallel_axis,
        [_vec(I3, "inertia_com"), _scalar(2.0, "mass"), _vec(COM, "displacement")],
        "raise",
    ),
    "composite_inertia": (
        lambda m, c, i: rj.composite_inertia(m, c, i)[2],
        [
            Arg([1.0, 2.0], 0, "masses"),
            Arg([[0, 0, 0.1], [0, 0.2, 0]], 1, "coms"),
            Arg([I3, I3], 1, "inertias"),
        ],
        "raise",
    ),
    "solid_box": (rj.solid_box, [_scalar(2.0, "mass"), _vec([1.0, 2.0, 3.0], "size")], "raise"),
    "solid_cylinder": (
        rj.solid_cylinder,
        [_scalar(2.0, "mass"), _scalar(0.5, "radius"), _scalar(1.0, "height")],
        "raise",
    ),
    "hollow_cylinder": (
        rj.hollow_cylinder,
        [_scalar(2.0, "mass"), _scalar(0.5, "radius"), _scalar(1.0, "height")],
        "raise",
    ),
    "solid_sphere": (rj.solid_sphere, [_scalar(2.0, "mass"), _scalar(0.5, "radius")], "raise"),
    "hollow_sphere": (rj.hollow_sphere, [_scalar(2.0, "mass"), _scalar(0.5, "radius")], "raise"),
    "solid_ellipsoid": (
        rj.solid_ellipsoid,
        [_scalar(2.0, "mass"), _vec([1.0, 2.0, 3.0], "semi_axes")],
        "raise",
    ),
    "thin_rod": (rj.thin_rod, [_scalar(2.0, "mass"), _scalar(1.0, "length")], "raise"),
    "thin_disc": (rj.thin_disc, [_scalar(2.0, "mass"), _scalar(0.5, "radius")], "raise"),
    "sleeping_top": (
        lambda i, m, c, w3: rj.sleeping_top(i, m, c, w3).margin,
        [_vec(SYMMETRIC, "inertia"), _scalar(2.0, "mass"), _vec(COM, "com"), _scalar(30.0, "omega3")],
        "raise",
    ),
    "spin_stability": (
        lambda i, w: rj.spin_stability(i, w).growth_rate,
        [_vec(I3, "inertia"), _scalar(2.0, "omega_magnitude")],
        "raise",
    ),
    # closed forms
    "torque_free_omega": (
        rj.torque_free_omega,
        [_vec(I3, "inertia"), _vec(W, "omega0"), Arg(TS, None, "t")],
        "raise",
    ),
    "torque_free_motion": (
        rj.torque_free_motion,
        [_vec(I3, "inertia"), _vec(W, "omega0"), _vec(Q, "q0"), Arg(TS, None, "t")],
        "raise",
    ),
    "torque_free_period": (rj.torque_free_period, [_vec(I3, "inertia"), _vec(W, "omega0")], "raise"),
    # records for the fits: NaN is a missing sample
    "omega_from_orientations": (
        rj.omega_from_orientations,
        [Arg(TS, None, "ts"), Arg(QS, 1, "q_observed")],
        "missing",
    ),
    "estimate_inertia": (
        lambda t, w: rj.estimate_inertia(t, w)[0],
        [Arg(TS, None, "ts"), Arg(OMEGAS, 1, "omega_observed")],
        "missing",
    ),
    # elliptic functions: NaN in, NaN out
    "ellipk": (elliptic.ellipk, [_scalar(0.3, "m")], "propagate"),
    "ellipkm1": (elliptic.ellipkm1, [_scalar(0.3, "p")], "propagate"),
    "ellipe": (elliptic.ellipe, [_scalar(0.3, "m")], "propagate"),
    "ellipkinc": (elliptic.ellipkinc, [_scalar(0.7, "phi"), _scalar(0.3, "m")], "propagate"),
    "ellipeinc": (elliptic.ellipeinc, [_scalar(0.7, "phi"), _scalar(0.3, "m")], "propagate"),
    "ellipj": (elliptic.ellipj, [_scalar(0.7, "u"), _scalar(0.3, "m")], "propagate"),
    "ellipj_m1": (elliptic.ellipj_m1, [_scalar(0.7, "u"), _scalar(0.3, "p")], "propagate"),
    "elliprj": (
        elliptic.elliprj,
        [_scalar(1.0, "x"), _scalar(2.0, "y"), _scalar(3.0, "z"), _scalar(4.0, "p")],
        "propagate",
    ),
    # conversions
    "quat_from_scalar_last": (convert.quat_from_scalar_last, [_vec(Q, "q")], "raise"),
    "quat_to_scalar_last": (convert.quat_to_scalar_last, [_vec(Q, "q")], "raise"),
    "to_scipy_rotation": (lambda q: convert.to_scipy_rotation(q).as_quat(), [_vec(Q, "q")], "raise"),
    "from_mujoco_free_joint": (
        lambda a, b: convert.from_mujoco_free_joint(a, b),
        [_vec(np.r_[0.1, 0.2, 0.3, Q], "qpos"), _vec(np.r_[0.0, 0.0, 0.0, W], "qvel")],
        "raise",
    ),
    "to_mujoco_free_joint": (
        lambda w, q: convert.to_mujoco_free_joint(rj.State(w, q)),
        [_vec(W, "state.omega", "State.omega", "omega"), _vec(Q, "state.orientation", "State.orientation")],
        "raise",
    ),
    # steps and fixed-step runs of the structure-preserving solvers
    "dexpinv": (solvers.dexpinv, [_vec(0.1 * W, "theta"), _vec(W, "omega")], "raise"),
    "rkmk_step": (
        lambda t, w, q, h: solvers.rkmk_step(_accel, t, w, q, h),
        [_scalar(0.0, "t"), _vec(W, "omega"), _vec(Q, "q"), _scalar(0.01, "h")],
        "raise",
    ),
    "splitting_step": (
        solvers.splitting_step,
        [_vec(I3, "inertia"), _vec(W, "L"), _vec(Q, "q"), _scalar(0.01, "h")],
        "raise",
    ),
    "heavy_top_splitting_step": (
        solvers.heavy_top_splitting_step,
        [
            _vec(I3, "inertia"),
            _vec([0, 0, 0.981], "weight_com"),
            _vec(W, "L"),
            _vec(Q, "q"),
            _scalar(0.01, "h"),
        ],
        "raise",
    ),
    "free_body_vector_field": (
        lambda i: solvers.free_body_vector_field(i)(0.0, (W, Q), None)[0],
        [_vec(I3, "inertia")],
        "raise",
    ),
    "heavy_top_vector_field": (
        lambda i, m, c: solvers.heavy_top_vector_field(i, m, c)(0.0, (W, Q), None)[0],
        [_vec(I3, "inertia"), _scalar(1.0, "mass"), _vec(COM, "com")],
        "raise",
    ),
    "split_free_body": (
        lambda i, l, q, dt: solvers.split_free_body(i, l, q, dt, 3),
        [_vec(I3, "inertia"), _vec(W, "L0"), _vec(Q, "q0"), _scalar(0.01, "dt")],
        "raise",
    ),
    "split_heavy_top": (
        lambda i, m, c, g, l, q, dt: solvers.split_heavy_top(i, m, c, g, l, q, dt, 3),
        [
            _vec(I3, "inertia"),
            _scalar(1.0, "mass"),
            _vec(COM, "com"),
            _scalar(9.81, "gravity"),
            _vec(W, "L0"),
            _vec(Q, "q0"),
            _scalar(0.01, "dt"),
        ],
        "raise",
    ),
}

# Public callables whose arguments are not arrays of numbers, with the tests of their bad input.
ELSEWHERE = {
    "simulate": "test_bad_input.py::test_simulate_rejects_bad_values",
    "use_compilation_cache": "test_compilation_cache.py::test_bad_paths_are_named",
    "use_cpu_cores": "test_cpu_cores.py::test_count_must_be_a_positive_integer",
    "Trajectory": "test_storage.py::test_damaged_files",
    "fit_inertia": "test_bad_input.py::test_fit_rejects_bad_options_before_any_work",
    "fit_inertia_to_orientation": "test_bad_input.py::test_fit_rejects_bad_options_before_any_work",
    "InertiaFit": "test_fit.py::test_principal_fit_recovers_truth_and_methods_agree",
    "State": "test_bad_input.py::test_scene_structural_errors",
    "FreeBody": "test_bad_input.py::test_simulate_rejects_bad_values",
    "RigidBody": "test_bad_input.py::test_mismatched_batch_shapes_name_every_array",
    "HeavyTop": "test_bad_input.py::test_values_without_a_meaningful_result_raise",
    "Gyrostat": "test_gyrostat.py::test_bad_input_names_the_argument",
    "Torque": "test_bad_input.py::test_torque_of_the_wrong_shape_is_named",
    "ConstantTorque": "test_bad_input.py::test_simulate_rejects_bad_values",
    "GravityTorque": "test_bad_input.py::test_fit_rejects_a_non_finite_known_torque",
    "ViscousDamping": "test_bad_input.py::test_scene_structural_errors",
    "AbstractModel": "test_simulate.py::test_user_torque_subclass_and_public_types",
    "AbstractTorque": "test_bad_input.py::test_torque_of_the_wrong_shape_is_named",
    "SleepingTop": "test_stability.py::test_sleeping_top_bad_input",
    "SpinStability": "test_stability.py::test_spin_stability_bad_input",
    "is_proper_sequence": "test_bad_input_sweep.py::test_sequence_functions_reject_unknown_sequences",
    "from_scipy_rotation": "test_convert.py::test_scipy_bad_inputs_named",
    "RKMK": "test_lie_group.py::test_bad_tableau",
    "LiePoissonSplitting": "test_splitting.py::test_solvers_without_parameters_for_simulate",
    "HeavyTopSplitting": "test_splitting.py::test_heavy_top_errors",
    "UnrolledDopri8": "test_unrolled_dopri8.py::test_rejects_terms_that_are_not_an_ode",
    "preset": "test_unrolled_dopri8.py::test_preset_names_what_simulate_runs",
    "rigid_body_vector_field": "test_bad_input_sweep.py::test_vector_field_of_a_non_function",
    "animate": "test_plot.py::test_bad_bodies_and_missing_orientations",
    "cones": "test_plot.py::test_bad_bodies_and_missing_orientations",
    "euler_angles": "test_plot.py::test_bad_bodies_and_missing_orientations",
    "invariant_drift": "test_plot.py::test_bad_bodies_and_missing_orientations",
    "poinsot": "test_plot.py::test_bad_bodies_and_missing_orientations",
}

NAMESPACES = (rj, kinematics, elliptic, convert, solvers, importlib.import_module("rigidjax.plot"))


def test_every_public_function_is_swept():
    public = {name for module in NAMESPACES for name in module.__all__ if callable(getattr(module, name))}
    missing = sorted(public - set(SWEEP) - set(ELSEWHERE))
    assert not missing, f"public callables without a bad-input test: {missing}"
    for name, where in ELSEWHERE.items():
        assert name in public, f"{name} is not public"
        path, test = where.split("::")
        module = importlib.import_module(path.removesuffix(".py"))
        assert callable(getattr(module, test, None)), f"{where} does not exist"


KINDS = ("nan", "inf", "shape", "mismatch", "empty", "complex")
# JAX's own errors, which name no argument of ours.
RAW = ("ncompatible shapes", "broadcast_shapes", "index out of", "dot_general requires", "cannot reshape")


def _corrupted(args, i, kind, draw, follow=True):
    """The good arrays with argument ``i`` corrupted, or None where the kind does not apply."""
    arrays = [a.value.copy() for a in args]
    x, core = arrays[i], args[i].core
    if kind in ("nan", "inf"):
        x.flat[draw(st.integers(0, x.size - 1))] = np.nan if kind == "nan" else np.inf
    elif kind == "shape":
        if not core:  # a scalar or a free shape: no last axis can be wrong
            return None
        x = np.zeros(x.shape[:-1] + (x.shape[-1] + draw(st.sampled_from([-1, 1, 2])),))
    elif kind == "mismatch":
        others = [j for j, a in enumerate(args) if j != i and a.core is not None]
        if not others or args[i].core is None:
            return None
        j = draw(st.sampled_from(others))
        # Batch sizes other than 3: a (3, 3) block would be read as a tensor, a valid input.
        n, m = draw(st.lists(st.sampled_from([2, 4, 5, 7]), min_size=2, max_size=2, unique=True))
        arrays[j] = np.broadcast_to(arrays[j], (m,) + arrays[j].shape).copy()
        x = np.broadcast_to(x, (n,) + x.shape).copy()
    elif kind == "empty":
        if args[i].core is None:
            return None
        x = np.zeros((0,) + x.shape)
        for j, a in enumerate(args):  # the free-shaped arguments (sample times) follow the batch
            if follow and j != i and a.core is None:
                arrays[j] = arrays[j][None][:0]
    elif kind == "complex":
        x = x.astype(complex)
    arrays[i] = x
    return arrays


def _verdict(name, args, i, kind, outcome):
    """None when the outcome is a clear error or a documented answer, else what is wrong."""
    fn, _, rule = SWEEP[name]
    names = args[i].names if kind != "mismatch" else tuple(n for a in args for n in a.names)
    if isinstance(outcome, BaseException):
        message = str(outcome)
        if rule == "missing" and isinstance(outcome, TypeError) and "is traced" in message:
            return None  # under jit: the records' functions read values on the host
        clear = isinstance(
            outcome, ValueError | TypeError | eqx.EquinoxRuntimeError | jax.errors.JaxRuntimeError
        )
        if not clear or any(r in message for r in RAW) or not any(n in message for n in names):
            return f"{type(outcome).__name__}: {message[:300]}"
        return None
    leaves = [np.asarray(x) for x in jax.tree.leaves(outcome)]
    if kind == "empty":
        return (
            None
            if all(x.size == 0 for x in leaves)
            else f"an empty batch gave shapes {[x.shape for x in leaves]}"
        )
    floats = [x for x in leaves if np.issubdtype(x.dtype, np.inexact)]
    if kind == "nan" and rule == "propagate":
        return None if any(np.isnan(x).any() for x in floats) else "NaN input gave a finite result"
    if kind == "inf" and rule == "propagate":
        return None  # the function's limit there (e.g. K(m) -> 0 as m -> -inf, as scipy), or NaN
    if kind == "nan" and rule == "missing":
        return None  # a missing sample: a result (NaN where it is needed) or a named error
    if kind in ("nan", "inf") and rule == "answer":
        return None if not any(np.any(x) for x in leaves) else "a non-finite input was called physical"
    return f"accepted ({kind}): returned {[x.shape for x in leaves]}"


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SWEEP))
@settings(
    max_examples=12,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(data=st.data())
def test_generated_bad_input_gets_a_clear_error(name, data, without_runtime_typecheck):
    fn, args, _ = SWEEP[name]
    i = data.draw(st.integers(0, len(args) - 1), label="argument")
    kind = data.draw(st.sampled_from(KINDS), label="kind")
    # A record's sample times are one series, not a batch: they do not follow an empty batch.
    arrays = _corrupted(args, i, kind, data.draw, follow=SWEEP[name][2] != "missing")
    if arrays is None:
        return
    jit = data.draw(st.booleans(), label="jit")
    try:
        outcome = jax.block_until_ready((jax.jit(fn) if jit else fn)(*arrays))
    except Exception as error:  # noqa: BLE001 (every exception is judged below)
        outcome = error
    problem = _verdict(name, args, i, kind, outcome)
    assert problem is None, f"{name}({args[i].names[0]} {kind}, jit={jit}): {problem}"


@pytest.mark.parametrize("name", list(SWEEP))
def test_good_input_gives_finite_output(name):
    """The table's good calls are good: the corruptions above are the only problem. The same call
    inside a ``jit`` that closes over the arrays (constants of the traced program, whose checks
    read their values while it is traced) gives the eager values."""
    fn, args, _ = SWEEP[name]
    arrays = [jnp.asarray(a.value) for a in args]
    eager = jax.tree.leaves(fn(*arrays))
    for out in eager:
        assert np.all(np.isfinite(np.asarray(out, float))), name
    closed_over = jax.tree.leaves(jax.jit(lambda: fn(*arrays))())
    assert len(closed_over) == len(eager)
    for x, y in zip(closed_over, eager, strict=True):
        np.testing.assert_allclose(np.asarray(x, float), np.asarray(y, float), rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("name", list(SWEEP))
def test_python_lists_give_the_array_answer(name, without_runtime_typecheck):
    """The table's good calls with every array argument written as a Python list (a number as a
    float), as a user types them: the same values as with arrays. The closed forms of the torque-free
    body failed on a list of times with JAX's own "broadcast_to requires ndarray" error."""
    fn, args, _ = SWEEP[name]
    from_arrays = jax.tree.leaves(fn(*[jnp.asarray(a.value) for a in args]))
    from_lists = jax.tree.leaves(fn(*[a.value.tolist() for a in args]))
    assert len(from_lists) == len(from_arrays)
    for x, y in zip(from_lists, from_arrays, strict=True):
        np.testing.assert_allclose(np.asarray(x, float), np.asarray(y, float), rtol=1e-13, atol=1e-15)


def test_sequence_functions_reject_unknown_sequences():
    with pytest.raises(ValueError, match="seq must be one of the twelve"):
        kinematics.is_proper_sequence("xyx z")


def test_vector_field_of_a_non_function(without_runtime_typecheck):
    """A function of the wrong arity failed only inside diffeqsolve, with Python's own message."""
    message = r"angular_acceleration must be callable as f\(t, omega, q, args\)"
    with pytest.raises(TypeError, match=message + r".*got array"):
        solvers.rigid_body_vector_field(np.zeros(3))
    with pytest.raises(TypeError, match=message + r".*got .*\(t, omega\)"):
        solvers.rigid_body_vector_field(lambda t, omega: -omega)
    solvers.rigid_body_vector_field(lambda *arguments: jnp.zeros(3))
