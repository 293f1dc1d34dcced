"""The public surface: the names ``import rigidjax`` offers, its namespaces (``rigidjax.kinematics``,
``.elliptic``, ``.solvers``), and the names of earlier releases kept for one release as aliases that
warn with ``DeprecationWarning``.
"""

import importlib
import warnings

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rigidjax as rj

NAMESPACES = ("kinematics", "elliptic", "solvers")
TOP_LEVEL_LIMIT = 60  # the top level stays the short list most users need

# The top-level names of the public contract (../shared/API.md).
CONTRACT = [
    "matrix_from_euler",
    "quat_from_euler",
    "euler_from_matrix",
    "euler_from_quat",
    "matrix_from_quat",
    "quat_from_matrix",
    "quat_multiply",
    "quat_conjugate",
    "quat_rotate",
    "body_angular_velocity",
    "space_angular_velocity",
    "euler_rates",
    "euler_equations",
    "principal_axes",
    "kinetic_energy",
    "angular_momentum",
    "free_precession_rate",
    "State",
    "FreeBody",
    "HeavyTop",
    "simulate",
    "Trajectory",
    "fit_inertia",
    "InertiaFit",
]

# Names that moved from the top level to a namespace: the alias is the identical object.
MOVED = {
    **dict.fromkeys(
        ["SEQUENCES", "PROPER_SEQUENCES", "TAIT_BRYAN_SEQUENCES", "is_proper_sequence", "quat_exp"],
        "kinematics",
    ),
    **dict.fromkeys(
        ["ellipk", "ellipkm1", "ellipe", "ellipkinc", "ellipeinc", "ellipj", "ellipj_m1", "elliprj"],
        "elliptic",
    ),
    **dict.fromkeys(
        [
            "RKMK",
            "LiePoissonSplitting",
            "HeavyTopSplitting",
            "PRESETS",
            "rkmk_step",
            "dexpinv",
            "rigid_body_vector_field",
            "free_body_vector_field",
            "heavy_top_vector_field",
            "split_free_body",
            "split_heavy_top",
            "splitting_step",
            "heavy_top_splitting_step",
        ],
        "solvers",
    ),
}
# Names replaced by another public spelling of the same thing.
REPLACED = ["inertia_times", "torque_free_orientation", "simulate_structure_preserving", "is_full_tensor"]


def deprecated(name):
    """``rigidjax.<name>``, asserting that getting it warns once, with a DeprecationWarning naming it."""
    with pytest.warns(DeprecationWarning, match=rf"rigidjax\.{name}\b") as record:
        value = getattr(rj, name)
    assert len(record) == 1, [str(w.message) for w in record]
    return value


# ----------------------------------------------------------------------------------------------
# What exists


def test_top_level_names_exist():
    assert len(set(rj.__all__)) == len(rj.__all__), "duplicates in rigidjax.__all__"
    missing = [name for name in rj.__all__ if name not in vars(rj)]
    assert not missing, missing


def test_top_level_is_short():
    assert len(rj.__all__) <= TOP_LEVEL_LIMIT, len(rj.__all__)


@pytest.mark.parametrize("namespace", NAMESPACES)
def test_namespace_names_exist(namespace):
    module = importlib.import_module(f"rigidjax.{namespace}")
    assert getattr(rj, namespace) is module
    assert module.__all__ and len(set(module.__all__)) == len(module.__all__)
    missing = [name for name in module.__all__ if name not in vars(module)]
    assert not missing, missing


def test_everyday_kinematics_are_the_same_objects_at_the_top_level():
    """rigidjax.kinematics holds every rotation helper; the everyday ones are also at the top level."""
    shared = [name for name in rj.kinematics.__all__ if name in rj.__all__]
    assert "matrix_from_euler" in shared and "quat_rotate" in shared
    for name in shared:
        assert getattr(rj, name) is getattr(rj.kinematics, name), name


def test_contract_names_import_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        namespace = {}
        exec(f"from rigidjax import {', '.join(CONTRACT)}", namespace)
        exec("from rigidjax import *", namespace)
        for name in NAMESPACES:
            exec(f"import rigidjax.{name}", namespace)
    assert set(CONTRACT) <= set(rj.__all__)
    assert all(namespace[name] is getattr(rj, name) for name in rj.__all__)


def test_dir_lists_the_public_names_only():
    names = dir(rj)
    assert set(rj.__all__) <= set(names) and set(NAMESPACES) <= set(names)
    assert not set(MOVED) & set(names) and not set(REPLACED) & set(names)


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        rj.no_such_name  # noqa: B018
    with pytest.raises(ImportError):
        exec("from rigidjax import no_such_name", {})


# ----------------------------------------------------------------------------------------------
# Deprecated names: they warn, and give the replacement


@pytest.mark.parametrize("name", list(MOVED))
def test_moved_name_warns_and_is_the_same_object(name):
    namespace = MOVED[name]
    with pytest.warns(DeprecationWarning, match=rf"rigidjax\.{namespace}\.{name}"):
        old = getattr(rj, name)
    assert old is getattr(getattr(rj, namespace), name)
    assert name not in rj.__all__ and name in getattr(rj, namespace).__all__


def test_moved_name_warns_on_from_import():
    with pytest.warns(DeprecationWarning, match=r"rigidjax\.elliptic\.ellipk"):
        namespace = {}
        exec("from rigidjax import ellipk", namespace)
    assert namespace["ellipk"] is rj.elliptic.ellipk


def test_inertia_times_is_angular_momentum():
    assert deprecated("inertia_times") is rj.angular_momentum


def test_is_full_tensor_is_the_shape_rule():
    is_full_tensor = deprecated("is_full_tensor")
    for shape in [(3,), (5, 3), (3, 3), (5, 3, 3), (2, 5, 3, 3)]:
        assert is_full_tensor(np.ones(shape)) == (shape[-2:] == (3, 3)), shape


def test_torque_free_orientation_is_the_orientation_of_torque_free_motion():
    """The same program (compared as jaxprs: tracing only, no compile) as torque_free_motion(...)[1]."""
    torque_free_orientation = deprecated("torque_free_orientation")
    q0 = jnp.asarray([0.8, 0.2, -0.4, 0.4]) / jnp.linalg.norm(jnp.asarray([0.8, 0.2, -0.4, 0.4]))
    args = (jnp.asarray([1.0, 2.0, 2.5]), jnp.asarray([0.3, 0.05, 1.0]), q0, jnp.linspace(0.0, 3.0, 4))
    old = jax.make_jaxpr(torque_free_orientation)(*args)
    new = jax.make_jaxpr(lambda *a: rj.torque_free_motion(*a)[1])(*args)
    assert str(old) == str(new)


def test_simulate_structure_preserving_is_simulate_with_a_solver():
    """The same program (compared as jaxprs) as simulate(..., solver=, dt0=)."""
    simulate_structure_preserving = deprecated("simulate_structure_preserving")
    model = rj.FreeBody(jnp.asarray([1.0, 2.0, 2.5]))
    state0 = rj.State(jnp.asarray([0.3, 0.05, 1.0]), jnp.asarray([1.0, 0.0, 0.0, 0.0]))
    ts, solver = jnp.linspace(0.0, 1.0, 5), rj.solvers.LiePoissonSplitting()
    # (ts stay concrete: they fix the number of steps.)
    old = jax.make_jaxpr(lambda m, s: simulate_structure_preserving(m, s, ts, solver, 0.1).omega)
    new = jax.make_jaxpr(lambda m, s: rj.simulate(m, s, ts, solver=solver, dt0=0.1).omega)
    assert str(old(model, state0)) == str(new(model, state0))


def _events_during(call, event_name: str) -> int:
    """How many of JAX's duration events named ``event_name`` ``call()`` records."""
    seen = []

    def listen(event, duration, **kwargs):
        if event == event_name:
            seen.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        jax.block_until_ready(call())
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return len(seen)


def _programs_compiled(call) -> int:
    """How many XLA programs ``call()`` compiles (JAX's compile events)."""
    return _events_during(call, "/jax/core/compile/backend_compile_duration")


def test_the_public_vector_fields_called_eagerly_compile_one_program():
    """``solvers.free_body_vector_field(I)(t, y, args)`` and the heavy top's, called eagerly (a user
    checking a state's rates before a solve), ran operation by operation: 13 programs each on a new
    shape. Now one each, with the values of the call traced inside ``jax.jit`` (as ``diffeqsolve``
    traces it)."""
    rng = np.random.default_rng(11)
    L = jnp.asarray(rng.normal(size=(7, 3)))
    q = jnp.asarray(rng.normal(size=(7, 4)))
    y = (L, q / jnp.linalg.norm(q, axis=-1, keepdims=True))
    fields = [
        rj.solvers.free_body_vector_field(jnp.array([1.0, 2.0, 2.5])),
        rj.solvers.heavy_top_vector_field(jnp.array([1.0, 1.0, 0.5]), 1.5, jnp.array([0.0, 0.0, 0.2])),
    ]
    for field in fields:
        assert _programs_compiled(lambda field=field: jax.block_until_ready(field(0.0, y, None))) == 1
        traced = jax.jit(lambda y, field=field: field(0.0, y, None))(y)
        for eager, inside in zip(field(0.0, y, None), traced, strict=True):
            np.testing.assert_allclose(np.asarray(eager), np.asarray(inside), rtol=1e-15, atol=1e-15)


def test_eager_calls_compile_one_program_not_one_per_operation():
    """Called eagerly, Trajectory's quantities are one compiled program each (their ~40 operations
    one by one were as many programs, each compiled in every new process), on a shape no other test
    uses. The Euler-angle functions compute in one program specialised on the sequence after their
    checks: a new sequence on a shape already checked compiles exactly that program (operation by
    operation it compiled nothing new, and each call dispatched some 30 operations)."""
    rng = np.random.default_rng(0)
    q = jnp.asarray(rng.normal(size=(13, 4)))
    traj = rj.simulate(
        rj.HeavyTop(jnp.array([1.0, 1.0, 0.5]), 1.0, jnp.array([0.0, 0.0, 0.3])),
        rj.State(jnp.asarray(rng.normal(size=(13, 3))), q / jnp.linalg.norm(q, axis=-1, keepdims=True)),
        jnp.linspace(0.0, 1.0, 7),
        accuracy="exact",
    )
    assert _programs_compiled(traj.invariants) == 1
    assert _programs_compiled(traj.energy) == 1
    rj.euler_from_quat(q)
    assert _programs_compiled(lambda: rj.euler_from_quat(q, "xyz")) == 1
    angles = rj.euler_from_quat(q)
    rj.euler_rates(angles, traj.omega[:, 0])
    assert _programs_compiled(lambda: rj.euler_rates(angles, traj.omega[:, 0], "yxz")) == 1


def _programs_compiled_afresh(call) -> int:
    """:func:`_programs_compiled` with JAX's persistent compilation cache off during ``call()``: a
    program another run left on disk is compiled (and counted) rather than loaded."""
    enabled = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        return _programs_compiled(call)
    finally:
        jax.config.update("jax_enable_compilation_cache", enabled)


def test_eager_derivatives_of_simulate_compile_its_checks_once():
    """Under an eager ``jax.vjp`` or ``jax.jvp`` the inputs are tracers with values: simulate checks
    the values in one program, and what the checks do to the tracers (a quaternion divided by its
    norm) ran operation by operation, each operation a program of its own for each new shape (49
    programs for the forward pass of a free body's vjp, 19 for its jvp, a third of a first
    ``jax.grad``'s time). Now one more program. Reference: JAX's compile events, on shapes no other
    test uses, with the persistent cache off."""
    ts = jnp.linspace(0.0, 0.5, 9)
    omega = jnp.asarray(np.random.default_rng(1).normal(size=(4, 3)))
    inertia = jnp.array([[1.0, 2.0, 2.5]] * 4)

    def motion(inertia):
        return rj.simulate(rj.FreeBody(inertia), rj.State(omega), ts).omega

    # The checks, the checked tracers, the integration and two of the driver's operations.
    assert _programs_compiled_afresh(lambda: jax.vjp(motion, inertia)[0]) <= 6
    assert _programs_compiled_afresh(lambda: jax.jvp(motion, (inertia,), (jnp.ones_like(inertia),))[1]) <= 4


def test_eager_derivatives_of_checked_functions_compile_their_program():
    """Under an eager ``jax.grad`` or ``jax.jvp`` a checked public function (``euler_from_quat``
    here) ran operation by operation, its checks included: 24 programs for the gradient of a loss
    of it on a new shape, 9 for its jvp. Its program is now differentiated as a whole, with the
    values of the jitted gradient, and a bad value still raises the ``ValueError`` naming the
    argument. Reference: JAX's compile events, persistent cache off; the jitted gradient."""
    q = jnp.asarray(np.random.default_rng(2).normal(size=(6, 4)))
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)

    def loss(q):
        return jnp.sum(rj.euler_from_quat(q, "zyx") ** 2)

    # The function's program (primal and transposed) and the loss's own operations.
    assert _programs_compiled_afresh(lambda: jax.grad(loss)(q)) <= 12
    assert _programs_compiled_afresh(lambda: jax.jvp(loss, (q,), (q,))) <= 4
    np.testing.assert_allclose(jax.grad(loss)(q), jax.jit(jax.grad(loss))(q), rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match="euler_from_quat: q contains NaN or inf"):
        jax.grad(loss)(q.at[0, 0].set(jnp.nan))


def test_shapes_and_composites_compile_one_program_when_eager():
    """The shape helpers and ``composite_inertia`` ran operation by operation when called eagerly:
    ``solid_box(1.0, sizes)`` compiled 19 programs on a new shape, ``composite_inertia`` of four
    parts 76. Each is one program now, and a new mass compiles nothing. Reference: JAX's compile
    events, persistent cache off, on shapes no other test uses; the values against the formulas."""
    sizes = jnp.asarray(np.random.default_rng(3).uniform(0.1, 1.0, size=(7, 3)))
    assert _programs_compiled_afresh(lambda: rj.solid_box(1.0, sizes)) == 1
    assert _programs_compiled_afresh(lambda: rj.solid_box(2.5, sizes)) == 0
    a, b, c = np.asarray(sizes).T
    np.testing.assert_allclose(
        rj.solid_box(2.5, sizes), 2.5 / 12 * np.stack([b**2 + c**2, a**2 + c**2, a**2 + b**2], -1)
    )
    masses, coms = (
        jnp.asarray([1.0, 2.0, 0.5, 1.5]),
        jnp.asarray(np.random.default_rng(4).normal(size=(4, 3))),
    )
    moments = rj.solid_box(1.0, jnp.asarray(np.random.default_rng(5).uniform(0.1, 1.0, size=(4, 3))))
    assert _programs_compiled_afresh(lambda: rj.composite_inertia(masses, coms, moments)) == 1
    total, com, tensor = rj.composite_inertia(masses, coms, moments)
    m, d = np.asarray(masses), np.asarray(coms)
    com_ref = (m[:, None] * d).sum(0) / m.sum()
    r = d - com_ref
    tensor_ref = sum(
        np.diag(moments[p]) + m[p] * (r[p] @ r[p] * np.eye(3) - np.outer(r[p], r[p])) for p in range(4)
    )
    np.testing.assert_allclose(total, m.sum())
    np.testing.assert_allclose(com, com_ref, rtol=1e-14)
    np.testing.assert_allclose(tensor, tensor_ref, rtol=1e-13)


@pytest.mark.parametrize(
    "name", ["quat_exp", "dexpinv", "quat_from_scalar_last", "from_mujoco_free_joint", "to_mujoco_free_joint"]
)
def test_conversions_compile_one_program_when_eager(name):
    """These ran operation by operation when called eagerly (``quat_exp`` compiled 23 programs on a
    new shape, ``quat_from_scalar_last`` 12, ``from_mujoco_free_joint`` 7, ``to_mujoco_free_joint`` of
    a ``State`` and a position 14, ``dexpinv`` 3); one program each now, with the values of the
    same call under ``jax.jit`` (their values are checked against scipy and MuJoCo in test_kinematics
    and test_convert). Reference: JAX's compile events, persistent cache off, on a shape no other
    test uses."""
    from rigidjax import convert, kinematics, solvers

    rng = np.random.default_rng(6)
    theta, omega = jnp.asarray(rng.normal(size=(9, 3))), jnp.asarray(rng.normal(size=(9, 3)))
    q = jnp.asarray(rng.normal(size=(9, 4)))
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    qpos = jnp.concatenate([jnp.asarray(rng.normal(size=(9, 3))), q], axis=-1)
    qvel = jnp.asarray(rng.normal(size=(9, 6)))
    function, args = {
        "quat_exp": (kinematics.quat_exp, (theta,)),
        "dexpinv": (solvers.dexpinv, (0.1 * theta, omega)),
        "quat_from_scalar_last": (convert.quat_from_scalar_last, (q,)),
        "from_mujoco_free_joint": (convert.from_mujoco_free_joint, (qpos, qvel)),
        "to_mujoco_free_joint": (convert.to_mujoco_free_joint, (rj.State(omega, q), qpos[:, :3])),
    }[name]
    assert _programs_compiled_afresh(lambda: function(*args)) == 1
    for eager, jitted in zip(
        jax.tree.leaves(function(*args)), jax.tree.leaves(jax.jit(function)(*args)), strict=True
    ):
        np.testing.assert_allclose(eager, jitted, rtol=0, atol=1e-15)


def test_lagrange_checks_of_exact_are_one_program():
    """``accuracy="exact"`` checks that a heavy top is Lagrange's (``I1 = I2``, centre of mass on
    the axis) before its closed form: operation by operation the call compiled 14 programs for each
    new batch shape, now at most two. Here the check fails (one top of six is asymmetric), so
    nothing else compiles. Reference: JAX's compile events, persistent cache off, on a shape no
    other test uses."""
    inertia = jnp.tile(jnp.array([1.0, 1.0, 0.5]), (6, 1)).at[4, 1].set(1.2)
    top = rj.HeavyTop(inertia, 1.0, jnp.array([0.0, 0.0, 0.1]))
    q0 = jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (6, 1))
    state = rj.State(jnp.tile(jnp.array([0.1, 0.2, 9.0]), (6, 1)), q0)

    def call():
        with pytest.raises(
            ValueError, match="needs equal transverse moments I1 = I2.*got I1 = 1.0, I2 = 1.2"
        ):
            rj.simulate(top, state, jnp.linspace(0.0, 1.0, 5), accuracy="exact")

    assert _programs_compiled_afresh(call) <= 2


def _programs_traced(call) -> int:
    """How many functions ``call()`` traces (JAX's trace events): none when every program it runs is
    one JAX already holds, whether or not the persistent cache would have supplied its compilation."""
    return _events_during(call, "/jax/core/compile/jaxpr_trace_duration")


def test_a_sequence_in_another_case_runs_the_same_program():
    """Euler sequences are case-insensitive: "ZXZ" and the default after "zxz" (and "YXZ" after
    "yxz" for the rates) run the program of the first call, with the same values. Each spelling
    traced and compiled a program of its own before. (A mix, "ZxZ", is refused: test_kinematics.)
    Reference: JAX's trace events."""
    angles = jnp.asarray([[0.3, 0.7, -1.1], [2.0, 0.2, 0.4]])
    rates = jnp.asarray([[0.1, -0.2, 0.3], [0.0, 0.5, 1.0]])
    calls = {
        "matrix_from_euler": lambda seq: rj.matrix_from_euler(angles, *seq),
        "quat_from_euler": lambda seq: rj.quat_from_euler(angles, *seq),
        "body_angular_velocity": lambda seq: rj.body_angular_velocity(angles, rates, *seq),
        "euler_rates": lambda seq: rj.euler_rates(angles, rates, *seq),
    }
    for name, call in calls.items():
        first = np.asarray(call(("zxz",)))
        for seq in [("ZXZ",), ()]:
            assert _programs_traced(lambda call=call, seq=seq: call(seq)) == 0, (name, seq)
            np.testing.assert_array_equal(np.asarray(call(seq)), first)
    rj.euler_rates(angles, rates, "yxz")
    assert _programs_traced(lambda: rj.euler_rates(angles, rates, "YXZ")) == 0


@pytest.mark.parametrize("kind", ["Python float", "Python list", "array"])
def test_a_second_eager_call_with_new_values_compiles_nothing(kind, request):
    """The elliptic functions ran their loops operation by operation, compiling them again at every
    call (0.1 to 0.3 s each, arrays or not); the closed forms took a Python float time as a static
    argument of their programs, compiled again for each new value (1 to 3 s a call), and a list of
    times failed inside them with JAX's "broadcast_to requires ndarray" error. A second call with
    new values of the same shapes now compiles nothing. Reference: JAX's compile events."""
    convert = {"Python float": float, "Python list": lambda v: [v, 2 * v], "array": jnp.asarray}[kind]
    if kind == "Python list":  # beyond the annotations (arrays and numbers), as users may call them
        request.getfixturevalue("without_runtime_typecheck")
    inertia, omega0, q0 = np.array([1.0, 2.0, 2.5]), np.array([0.3, 0.1, 1.0]), np.array([1.0, 0.0, 0.0, 0.0])
    calls = {
        "ellipk": lambda v: rj.elliptic.ellipk(v),
        "ellipkm1": lambda v: rj.elliptic.ellipkm1(v),
        "ellipe": lambda v: rj.elliptic.ellipe(v),
        "ellipkinc": lambda v: rj.elliptic.ellipkinc(v, 0.3),
        "ellipeinc": lambda v: rj.elliptic.ellipeinc(v, 0.3),
        "ellipj": lambda v: rj.elliptic.ellipj(v, 0.3),
        "ellipj_m1": lambda v: rj.elliptic.ellipj_m1(v, 0.3),
        "elliprj": lambda v: rj.elliptic.elliprj(v, 1.0, 2.0, 0.5),
        "torque_free_omega": lambda v: rj.torque_free_omega(inertia, omega0, v),
        "torque_free_motion": lambda v: rj.torque_free_motion(inertia, omega0, q0, v),
    }
    for name, call in calls.items():
        first = call(convert(0.17))
        assert _programs_compiled(lambda call=call: call(convert(0.13))) == 0, name
        # Each call's own values, not the first call's.
        assert not np.array_equal(
            np.asarray(jax.tree.leaves(call(convert(0.13)))[0]), np.asarray(jax.tree.leaves(first)[0])
        ), name
    # A Python number still takes the other arguments' dtype (NumPy's and JAX's rule).
    single = [jnp.asarray(x, jnp.float32) for x in (inertia, omega0, q0)]
    assert rj.torque_free_omega(*single[:2], 1.5).dtype == jnp.float32
    assert rj.torque_free_motion(*single, 1.5)[1].dtype == jnp.float32
    assert rj.elliptic.ellipj(jnp.float32(1.5), 0.3)[0].dtype == jnp.float32


@pytest.mark.parametrize("through", ["params", "args"])
def test_a_torque_gain_swept_as_python_floats_compiles_once(through):
    """A Python float in a Torque's params or in simulate's args was a static argument of the
    compiled integration: every new value compiled it again (7-12 s a call). Floats are arrays now.
    Reference: a damped sphere, I = 2, torque -k omega: omega(t) = omega0 exp(-k t / 2)."""

    def damping(t, state, k):
        return -k * state.omega

    ts, omega0 = jnp.linspace(0.0, 1.0, 5), jnp.asarray([0.3, 0.1, 1.0])

    def run(k):
        params, args = (k, None) if through == "params" else (None, k)
        torque = rj.Torque(damping, params=params, needs_orientation=False)
        model = rj.RigidBody(jnp.asarray([2.0, 2.0, 2.0]), torque)
        return rj.simulate(model, rj.State(omega0), ts, args=args, accuracy="fast").omega

    run(0.1)
    for k in (0.2, 0.3):
        assert _programs_compiled(lambda k=k: run(k)) == 0
        exact = np.asarray(omega0) * np.exp(-k * np.asarray(ts)[:, None] / 2)
        np.testing.assert_allclose(np.asarray(run(k)), exact, rtol=1e-4)


def test_a_sweep_of_fixed_steps_compiles_once():
    """A Python-float dt0 for a diffrax solver was a static argument of the compiled solve: each
    step of a convergence study compiled it again. Reference: the closed form, and Tsit5's fifth
    order (the error falls about 32-fold per halving)."""
    inertia, omega0, ts = jnp.asarray([1.0, 2.0, 2.5]), jnp.asarray([0.3, 0.1, 1.0]), jnp.asarray([0.0, 4.0])
    exact = np.asarray(rj.torque_free_omega(inertia, omega0, 4.0))

    def error(dt0):
        fixed = {"solver": diffrax.Tsit5(), "stepsize_controller": diffrax.ConstantStepSize(), "dt0": dt0}
        traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega0), ts, **fixed)
        return np.max(np.abs(np.asarray(traj.omega[-1]) - exact))

    errors = [error(0.1)]
    for dt0 in (0.05, 0.025):
        assert _programs_compiled(lambda dt0=dt0: error(dt0)) == 0
        errors.append(error(dt0))
    ratios = np.asarray(errors[:-1]) / np.asarray(errors[1:])
    assert np.all((ratios > 20) & (ratios < 45)), errors


def test_checked_functions_called_eagerly_are_one_program_with_the_same_errors():
    """Called eagerly, each checked public function (its input checks and its formula) is one
    compiled program, on a shape no other test uses: ``check_inertia`` operation by operation
    compiled 79 programs for a new shape, ``parallel_axis`` 58, ``spin_stability`` 43,
    ``quat_rotate`` 22. A failed check is the ``ValueError`` an eager check raises, naming the
    argument; under ``jit`` the check stays in the user's program."""
    rng = np.random.default_rng(1)
    n = 17
    moments = jnp.asarray(rng.uniform(1.0, 1.5, size=(n, 3)))
    omega, d = jnp.asarray(rng.normal(size=(n, 3))), jnp.asarray(rng.normal(size=(n, 3)))
    q = jnp.asarray(rng.normal(size=(n, 4)))
    mass, spin = jnp.asarray(rng.uniform(1.0, 2.0, size=n)), jnp.asarray(rng.normal(size=n))
    top, com = jnp.asarray(np.tile([1.0, 1.0, 0.5], (n, 1))), jnp.asarray(np.tile([0.0, 0.0, 0.3], (n, 1)))
    transverse = jnp.asarray(rng.uniform(1.0, 2.0, size=n))
    turn = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]  # NumPy: no program compiled before the calls
    tensor = jnp.asarray(turn @ (np.asarray(moments)[..., None] * np.swapaxes(turn, -1, -2)))
    calls = {
        "check_inertia": lambda: rj.check_inertia(moments, name="I_body"),
        "is_physical_inertia": lambda: rj.is_physical_inertia(moments),
        "parallel_axis": lambda: rj.parallel_axis(moments, mass, d),
        "spin_stability": lambda: rj.spin_stability(moments, spin),
        "sleeping_top": lambda: rj.sleeping_top(top, mass, com, spin),
        "euler_equations": lambda: rj.euler_equations(moments, omega, d),
        "angular_momentum": lambda: rj.angular_momentum(moments, omega),
        "space_angular_momentum": lambda: rj.space_angular_momentum(moments, omega, q),
        "kinetic_energy": lambda: rj.kinetic_energy(moments, omega),
        "free_precession_rate": lambda: rj.free_precession_rate(transverse, mass, spin),
        "quat_multiply": lambda: rj.quat_multiply(q, q),
        "quat_conjugate": lambda: rj.quat_conjugate(q),
        "quat_rotate": lambda: rj.quat_rotate(q, d),
        "quat_normalize": lambda: rj.quat_normalize(q),
        "matrix_from_quat": lambda: rj.matrix_from_quat(q),
        "principal_axes": lambda: rj.principal_axes(tensor),
    }
    programs = {name: _programs_compiled(call) for name, call in calls.items()}
    assert programs == dict.fromkeys(calls, 1)
    # The results are those of the formulas (independent of the checks' program).
    np.testing.assert_allclose(
        rj.kinetic_energy(moments, omega), 0.5 * np.sum(moments * omega**2, -1), rtol=1e-14
    )
    np.testing.assert_allclose(rj.parallel_axis(moments, mass, d)[0], np.diag(moments[0]) + mass[0] * (
        np.dot(d[0], d[0]) * np.eye(3) - np.outer(d[0], d[0])), rtol=1e-14)  # fmt: skip

    flat = moments.at[3].set(jnp.array([1.0, 1.0, 3.0]))  # I1 + I2 < I3
    with pytest.raises(ValueError, match="I_body violates the triangle inequality"):
        rj.check_inertia(flat, name="I_body")
    assert not bool(rj.is_physical_inertia(flat)[3]) and bool(jnp.all(rj.is_physical_inertia(moments)))
    with pytest.raises(ValueError, match="quat_rotate: q has zero norm"):
        rj.quat_rotate(q.at[5].set(0.0), d)
    with pytest.raises(ValueError, match="euler_equations: omega contains NaN or inf"):
        rj.euler_equations(moments, omega.at[2, 1].set(jnp.nan))
    with pytest.raises(ValueError, match="principal_axes: tensor contains NaN or inf"):
        rj.principal_axes(tensor.at[4, 0, 1].set(jnp.inf))
    # Independent reference: NumPy's symmetric eigensolver (ascending moments, axes up to sign).
    moments_out, axes = rj.principal_axes(tensor)
    np.testing.assert_allclose(moments_out, np.linalg.eigvalsh(np.asarray(tensor)), rtol=1e-13)
    np.testing.assert_allclose(
        axes @ (moments_out[..., None] * np.swapaxes(axes, -1, -2)), tensor, atol=1e-13
    )
    with pytest.raises(Exception, match="I_body violates the triangle inequality"):
        jax.block_until_ready(jax.jit(lambda x: rj.check_inertia(x, name="I_body"))(flat))
