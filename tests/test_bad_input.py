"""Bad inputs to every public function: a clear error, nothing silent, nothing lost.

The policy (module docstrings of rigidjax/_kinematics, _dynamics and _checks.py):

1. Structural problems -- wrong shape, complex or boolean dtype, unknown sequence -- raise
   ``ValueError``/``TypeError`` while tracing, naming the argument. Integer arrays are promoted to
   the default float dtype (``_checks.as_float_array``).
2. Value problems -- NaN or inf, non-physical inertia, a zero quaternion, a matrix that is not a
   rotation, unsorted times -- raise at run time through ``eqx.error_if``, eagerly, under ``jax.jit``
   and under ``jax.vmap``, naming the argument and the problem (``EquinoxRuntimeError`` eagerly and
   under ``eqx.filter_jit``; under a plain ``jax.jit`` equinox's message arrives as a
   ``jax.errors.JaxRuntimeError``, or a ``ValueError`` from a reused compiled program). Host-side
   entry points (the fitting functions, which work in NumPy) raise ``ValueError`` at call time.
3. Finite valid input never manufactures NaN or inf (tests/test_gimbal_lock.py covers gimbal lock;
   here: zero omega, identity and half-turn quaternions, zero-size shapes).

``_ONCE_SILENT`` lists the cases that returned NaN or meaningless output silently when this suite was
written (strict xfails then); their checks are in place now and the cases must raise.

Compiling is the cost: each function is jitted once (module-level cache) and every bad value of
the same shape reuses that program; structural errors raise before anything compiles.
"""

import functools
import re
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dop853_free_body
from hypothesis import example, given, settings
from hypothesis import strategies as st

import rigidjax as rj

nan, inf = np.nan, np.inf
I3 = np.array([1.0, 2.0, 2.5])  # physical principal moments (kg m^2)
TENSOR = np.array([[2.0, 0.1, 0.0], [0.1, 1.5, 0.2], [0.0, 0.2, 2.5]])
W = np.array([0.1, 1.0, 0.2])
Q = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
ANG = np.array([0.3, 1.1, -0.7])
R = np.asarray(rj.matrix_from_quat(Q))
T = np.array(0.5)
COM = np.array([0.0, 0.0, 0.1])

# eqx.error_if raises EquinoxRuntimeError eagerly and under eqx.filter_jit. Under a plain jax.jit
# the same message arrives as a jax.errors.JaxRuntimeError on the first call and -- measured with
# jax 0.10.2, when the compiled program is reused through JAX's fast dispatch path -- as a plain
# ValueError. The tests therefore match on the message, which is what is stable.
RUNTIME = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, ValueError)


def with_value(x, value, index=0):
    x = np.array(x, dtype=float)
    x.flat[index] = value
    return x


# ----------------------------------------------------------------------------------------------
# The table: name -> (function of positional array arguments, good arguments, argument names)
# ----------------------------------------------------------------------------------------------

CALLS = {
    # kinematics
    "matrix_from_euler": (lambda a: rj.matrix_from_euler(a, "zxz"), (ANG,), ("angles",)),
    "quat_from_euler": (lambda a: rj.quat_from_euler(a, "xyz"), (ANG,), ("angles",)),
    "euler_from_matrix": (lambda m: rj.euler_from_matrix(m, "zyz"), (R,), ("R",)),
    "euler_from_quat": (lambda q: rj.euler_from_quat(q, "zyx"), (Q,), ("q",)),
    "matrix_from_quat": (rj.matrix_from_quat, (Q,), ("q",)),
    "quat_from_matrix": (rj.quat_from_matrix, (R,), ("R",)),
    "quat_multiply": (rj.quat_multiply, (Q, Q), ("p", "q")),
    "quat_conjugate": (rj.quat_conjugate, (Q,), ("q",)),
    "quat_rotate": (rj.quat_rotate, (Q, W), ("q", "v")),
    "quat_normalize": (rj.quat_normalize, (Q,), ("q",)),
    "body_angular_velocity": (
        lambda a, r: rj.body_angular_velocity(a, r, "zxz"),
        (ANG, W),
        ("angles", "rates"),
    ),
    "space_angular_velocity": (
        lambda a, r: rj.space_angular_velocity(a, r, "yzx"),
        (ANG, W),
        ("angles", "rates"),
    ),
    "euler_rates": (lambda a, w: rj.euler_rates(a, w, "zxz"), (ANG, W), ("angles", "omega")),
    # dynamics
    "euler_equations": (rj.euler_equations, (I3, W, W), ("inertia", "omega", "torque")),
    "euler_equations_tensor": (rj.euler_equations, (TENSOR, W), ("inertia", "omega")),
    "angular_momentum": (rj.angular_momentum, (I3, W), ("inertia", "omega")),
    "kinetic_energy": (rj.kinetic_energy, (TENSOR, W), ("inertia", "omega")),
    "space_angular_momentum": (rj.space_angular_momentum, (I3, W, Q), ("inertia", "omega", "orientation")),
    "free_precession_rate": (
        rj.free_precession_rate,
        (np.array(1.0), np.array(1.5), T),
        ("I1", "I3", "omega3"),
    ),
    # inertia
    "check_inertia": (rj.check_inertia, (I3,), ("inertia",)),
    "check_inertia_tensor": (rj.check_inertia, (TENSOR,), ("inertia",)),
    "principal_axes": (lambda t: rj.principal_axes(t)[0], (TENSOR,), ("tensor",)),
    "parallel_axis": (rj.parallel_axis, (I3, np.array(2.0), COM), ("inertia_com", "mass", "displacement")),
    "composite_inertia": (
        lambda m, c, i: rj.composite_inertia(m, c, i)[2],
        (np.array([1.0, 2.0]), np.array([[0, 0, 0.1], [0, 0.2, 0]]), np.array([I3, I3])),
        ("masses", "coms", "inertias"),
    ),
    "solid_box": (rj.solid_box, (np.array(2.0), np.array([1.0, 2.0, 3.0])), ("mass", "size")),
    "solid_cylinder": (rj.solid_cylinder, (np.array(2.0), T, T), ("mass", "radius", "height")),
    "hollow_cylinder": (rj.hollow_cylinder, (np.array(2.0), T, T), ("mass", "radius", "height")),
    "solid_sphere": (rj.solid_sphere, (np.array(2.0), T), ("mass", "radius")),
    "hollow_sphere": (rj.hollow_sphere, (np.array(2.0), T), ("mass", "radius")),
    "solid_ellipsoid": (
        rj.solid_ellipsoid,
        (np.array(2.0), np.array([1.0, 2.0, 3.0])),
        ("mass", "semi_axes"),
    ),
    "thin_rod": (rj.thin_rod, (np.array(2.0), T), ("mass", "length")),
    "thin_disc": (rj.thin_disc, (np.array(2.0), T), ("mass", "radius")),
}


GOOD_ARGS = {name: tuple(np.asarray(a, np.float64) for a in good) for name, (_, good, _) in CALLS.items()}


@jax.jit
def _all_calls(args):
    """Every function of the table in ONE compiled program. Bad values have the shapes of the good
    ones, so all the jit cases below reuse this single compile; the one bad argument's check fires."""
    return {name: CALLS[name][0](*a) for name, a in args.items()}


def call(name, args, mode):
    if mode == "jit":
        return jax.block_until_ready(_all_calls({**GOOD_ARGS, name: tuple(args)})[name])
    return jax.block_until_ready(CALLS[name][0](*args))


def replaced(name, arg, value):
    fn, good, names = CALLS[name]
    args = list(good)
    args[names.index(arg)] = value
    return args


@pytest.mark.slow
def test_good_inputs_give_finite_output():
    jitted = _all_calls(GOOD_ARGS)
    for name in CALLS:
        for out in (call(name, GOOD_ARGS[name], "eager"), jitted[name]):
            assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(out)), name


# ----------------------------------------------------------------------------------------------
# 1. Structural problems: trace-time ValueError / TypeError naming the argument
# ----------------------------------------------------------------------------------------------


def _wrong_shape(x):
    x = np.asarray(x)
    if x.ndim == 0:
        return None  # scalars broadcast: no shape is wrong
    if x.shape[-2:] == (3, 3):
        return np.zeros(x.shape[:-2] + (3, 2))
    return np.zeros(x.shape[:-1] + (x.shape[-1] + 2,))


SHAPE_CASES = [
    (name, arg)
    for name, (_, good, names) in CALLS.items()
    for arg, x in zip(names, good, strict=True)
    if _wrong_shape(x) is not None
]


@pytest.mark.parametrize("mode", ["eager", "jit"])
@pytest.mark.parametrize(("name", "arg"), SHAPE_CASES, ids=[f"{n}-{a}" for n, a in SHAPE_CASES])
def test_wrong_shape_raises_naming_the_argument(name, arg, mode, without_runtime_typecheck):
    args = replaced(name, arg, _wrong_shape(CALLS[name][1][CALLS[name][2].index(arg)]))
    fn = jax.jit(CALLS[name][0]) if mode == "jit" else CALLS[name][0]  # (raises while tracing)
    with pytest.raises(ValueError, match=rf"\b{arg}\b.*shape"):
        fn(*args)


DTYPE_CASES = [(name, names[0]) for name, (_, _, names) in CALLS.items()]


@pytest.mark.parametrize(("name", "arg"), DTYPE_CASES, ids=[n for n, _ in DTYPE_CASES])
def test_complex_and_bool_raise_type_error(name, arg, without_runtime_typecheck):
    good = np.asarray(CALLS[name][1][0])
    for bad, what in ((good.astype(complex), "real"), (good != 0, "bool")):
        for fn in (CALLS[name][0], jax.jit(CALLS[name][0])):
            with pytest.raises(TypeError, match=rf"\b{arg}\b.*{what}"):
                fn(*replaced(name, arg, bad))


def test_integers_are_promoted(without_runtime_typecheck, extreme):
    out = rj.matrix_from_euler(np.array([0, 1, 0]))
    assert out.dtype == jnp.float64
    np.testing.assert_allclose(out, rj.matrix_from_euler(np.array([0.0, 1.0, 0.0])))
    assert rj.euler_equations(np.array([1, 2, 2]), np.array([0, 0, 1])).dtype == jnp.float64
    assert rj.solid_box(3, np.array([1, 2, 3])).dtype == jnp.float64
    extreme(
        "bad input",
        "wrong shape, complex or boolean dtype, unknown sequence (all public array functions)",
        "ValueError/TypeError while tracing, naming the argument; integer arrays promoted to float",
    )


@pytest.mark.parametrize("half", [np.float16, jnp.bfloat16])
def test_half_precision_is_computed_in_float32(half, without_runtime_typecheck):
    """float16 and bfloat16 input is computed in float32 (as scipy.special does): the same values as
    the float32 call on the same (rounded) numbers, not a half-precision result wrong by 1e-3."""
    q = jnp.asarray(np.array([1.0, 0.2, -0.3, 0.1]), half)
    out = rj.quat_normalize(q)
    assert out.dtype == jnp.float32
    np.testing.assert_array_equal(out, rj.quat_normalize(q.astype(jnp.float32)))
    inertia, omega = jnp.asarray(I3, half), jnp.asarray(W, half)
    ts, q0 = jnp.asarray([0.0, 0.5, 1.0], half), jnp.full(4, 0.5, half)  # unit in half precision
    for accuracy in ("balanced", "exact"):
        traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega, q0), ts, accuracy=accuracy)
        ref = rj.simulate(
            rj.FreeBody(inertia.astype(jnp.float32)),
            rj.State(omega.astype(jnp.float32), q0.astype(jnp.float32)),
            ts.astype(jnp.float32),
            accuracy=accuracy,
        )
        assert traj.omega.dtype == jnp.float32 and traj.orientation.dtype == jnp.float32
        np.testing.assert_allclose(traj.omega, ref.omega, rtol=1e-6)


# ----------------------------------------------------------------------------------------------
# 2. Value problems: run-time errors (eqx.error_if) eagerly and under jit
# ----------------------------------------------------------------------------------------------

_FLIP = np.diag([1.0, 1.0, -1.0])
VALUE_CASES = [
    # (name, argument, bad value, regex the message must match)
    *[
        (name, arg, with_value(x, bad), rf"{name.split('_tensor')[0]}: {arg} contains NaN or inf")
        for name, (_, good, names) in CALLS.items()
        if not name.startswith("check_inertia")
        for arg, x in zip(names, good, strict=True)
        for bad in (nan, inf)
    ],
    ("check_inertia", "inertia", with_value(I3, nan), r"inertia \(principal moments\) contains NaN"),
    ("check_inertia", "inertia", np.array([1.0, 1.0, 3.0]), "triangle inequality"),
    ("check_inertia", "inertia", np.array([-1.0, 2.0, 2.5]), "non-positive principal moment"),
    ("check_inertia_tensor", "inertia", TENSOR + np.triu(np.ones((3, 3)), 1), "not symmetric"),
    ("check_inertia_tensor", "inertia", with_value(TENSOR, inf, 4), r"inertia \(tensor\) contains NaN"),
    ("euler_equations", "inertia", np.array([0.0, 2.0, 2.5]), "euler_equations: inertia is singular"),
    ("euler_equations_tensor", "inertia", np.ones((3, 3)), "euler_equations: inertia is singular"),
    ("free_precession_rate", "I1", np.array(0.0), "free_precession_rate: I1 = 0"),
    *[
        (name, arg, np.zeros(4), rf"{name}: {arg} has zero norm")
        for name, arg in [
            ("matrix_from_quat", "q"),
            ("euler_from_quat", "q"),
            ("quat_rotate", "q"),
            ("quat_normalize", "q"),
            ("space_angular_momentum", "orientation"),
        ]
    ],
    ("quat_from_matrix", "R", 1.01 * R, r"quat_from_matrix: R is not a rotation matrix"),
    ("euler_from_matrix", "R", R + 1e-5, r"euler_from_matrix: R is not a rotation matrix"),
    ("quat_from_matrix", "R", R @ _FLIP, r"quat_from_matrix: R has determinant -1"),
    ("euler_from_matrix", "R", -R, r"euler_from_matrix: R has determinant -1"),
    *[
        (name, "mass", np.array(-1.0), rf"{name}: mass must be >= 0")
        for name in ("parallel_axis", "solid_box", "solid_cylinder", "solid_sphere", "thin_rod", "thin_disc")
    ],
    ("solid_ellipsoid", "semi_axes", np.array([1.0, -2.0, 3.0]), "semi_axes must be >= 0"),
    ("hollow_cylinder", "height", np.array(-1.0), "height must be >= 0"),
    ("composite_inertia", "masses", np.array([-1.0, 2.0]), "masses must be >= 0"),
    ("composite_inertia", "masses", np.array([0.0, 0.0]), "total mass is 0"),
    # A part's moments may be zero (a point mass), not negative, and obey the triangle inequality.
    (
        "parallel_axis",
        "inertia_com",
        np.array([1.0, -1.0, 1.0]),
        "inertia_com has a negative principal moment",
    ),
    (
        "parallel_axis",
        "inertia_com",
        np.array([1.0, 1.0, 5.0]),
        "inertia_com violates the triangle inequality",
    ),
    ("parallel_axis", "inertia_com", np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]), "not symmetric"),
    (
        "composite_inertia",
        "inertias",
        np.array([[1.0, 1, 1], [-1, 1, 1]]),
        "inertias has a negative principal",
    ),
    ("composite_inertia", "inertias", np.array([[1.0, 1, 1], [1, 1, 3]]), "inertias violates the triangle"),
]
VALUE_IDS = [f"{n}-{a}-{i}" for i, (n, a, _, _) in enumerate(VALUE_CASES)]


@pytest.mark.parametrize("mode", ["eager", "jit"])
@pytest.mark.parametrize(("name", "arg", "bad", "match"), VALUE_CASES, ids=VALUE_IDS)
def test_bad_values_raise_at_run_time(name, arg, bad, match, mode):
    with pytest.raises(RUNTIME, match=match):
        call(name, replaced(name, arg, bad), mode)


def test_bad_value_under_vmap(extreme):
    """One bad row in a vmapped batch fails the whole call, naming the argument."""
    q = np.stack([Q, Q, np.zeros(4)])
    with pytest.raises(RUNTIME, match="matrix_from_quat: q has zero norm"):
        jax.block_until_ready(jax.vmap(rj.matrix_from_quat)(q))
    omega = np.stack([W, with_value(W, nan)])
    with pytest.raises(RUNTIME, match="euler_equations: omega contains NaN"):
        jax.block_until_ready(jax.jit(jax.vmap(rj.euler_equations, in_axes=(None, 0)))(I3, omega))
    np.testing.assert_allclose(jax.vmap(rj.matrix_from_quat)(q[:2]), np.stack([R, R]), atol=1e-15)
    for area, case, behaviour in [
        (
            "bad input",
            "NaN or inf in any array argument",
            "ValueError (EquinoxRuntimeError from a compiled function) naming the function and argument",
        ),
        (
            "bad input",
            "non-physical inertia (check_inertia, simulate, models)",
            "ValueError (EquinoxRuntimeError from a compiled function) naming the problem "
            "(triangle inequality, non-positive, non-symmetric)",
        ),
        (
            "bad input",
            "zero quaternion; matrix off a rotation by > 1e-6 (float64) / 1e-4 (float32), or det -1",
            "ValueError (EquinoxRuntimeError from a compiled function); a non-unit but nonzero "
            "quaternion is normalised (as scipy)",
        ),
        (
            "bad input",
            "negative mass or length; zero total mass",
            "ValueError (EquinoxRuntimeError from a compiled function) naming the argument",
        ),
    ]:
        extreme(area, case, behaviour, advice="errors fire under jit and vmap too (eqx.error_if)")


def test_non_unit_quaternion_is_normalised_not_rejected():
    """The contract's quaternions are unit, but any nonzero q means the rotation of q/|q| (scipy's
    from_quat; tests/test_kinematics.py pins it for euler_from_quat): matrices stay orthogonal and
    rotated vectors keep their length."""
    for scale in (1 + 1e-9, 2.5, 1e-3):
        np.testing.assert_allclose(rj.matrix_from_quat(scale * Q), R, atol=1e-15)
        np.testing.assert_allclose(rj.quat_rotate(scale * Q, W), R @ W, atol=1e-15)
        np.testing.assert_allclose(rj.quat_normalize(scale * Q), Q, atol=1e-16)
        np.testing.assert_allclose(rj.euler_from_quat(scale * Q), rj.euler_from_matrix(R), atol=1e-15)


def test_tiny_non_orthogonality_is_accepted():
    np.testing.assert_allclose(rj.quat_from_matrix(R + 1e-9), Q, atol=1e-8)
    R32 = (R + 1e-5).astype(np.float32)  # float32 tolerance is 1e-4
    assert rj.quat_from_matrix(R32).dtype == jnp.float32
    with pytest.raises(RUNTIME, match="not a rotation matrix"):
        jax.block_until_ready(rj.quat_from_matrix((R + 1e-3).astype(np.float32)))


def test_is_physical_inertia_answers_instead_of_raising():
    out = rj.is_physical_inertia(np.array([I3, with_value(I3, nan), [1.0, 1.0, 3.0], [-1.0, 2.0, 2.5]]))
    np.testing.assert_array_equal(out, [True, False, False, False])


def test_euler_rates_throw_false_propagates_nan():
    out = rj.euler_rates(ANG, with_value(W, nan), throw=False)
    assert np.all(np.isnan(out))
    # The rates do not depend on phi, and an infinite omega made infinite rates: both came back
    # as numbers (phi NaN gave the rates of a healthy body) instead of NaN.
    nan_phi = np.array([[nan, 0.7, 0.3], [0.1, 0.7, 0.3]])
    out = jax.vmap(lambda a, w: rj.euler_rates(a, w, throw=False))(nan_phi, np.ones((2, 3)))
    assert np.all(np.isnan(out[0])) and np.all(np.isfinite(out[1]))
    assert np.all(np.isnan(rj.euler_rates(np.array([0.1, 0.7, 0.3]), np.array([inf, 0.0, 0.0]), throw=False)))


# ----------------------------------------------------------------------------------------------
# 3. Finite valid input never manufactures NaN or inf
# ----------------------------------------------------------------------------------------------


def test_valid_degenerate_inputs_stay_finite(extreme):
    zero = np.zeros(3)
    outs = [
        rj.euler_equations(I3, zero),
        rj.euler_equations(TENSOR, zero),
        rj.kinetic_energy(I3, zero),
        rj.quat_rotate(Q, zero),
        rj.euler_rates(ANG, zero),
        rj.euler_rates(np.array([0.3, 0.0, 0.2]), zero),  # at gimbal lock, omega = 0 is followable
        rj.body_angular_velocity(np.array([0.3, 0.0, 0.2]), zero),
        rj.quat_from_matrix(np.eye(3)),
        rj.quat_from_matrix(np.diag([1.0, -1.0, -1.0])),
        rj.euler_from_quat(np.array([0.0, 0.0, 0.0, 1.0])),
        rj.thin_rod(np.array(1.0), np.array(0.0)),
        rj.solid_sphere(np.array(0.0), T),
        rj.principal_axes(np.eye(3))[1],
        rj.free_precession_rate(np.array(1.0), np.array(2.0), np.array(0.0)),
        rj.parallel_axis(I3, np.array(0.0), COM),
    ]
    for out in outs:
        assert np.all(np.isfinite(np.asarray(out)))
    # Gradients too, at zero omega and the identity rotation (each one compiled program: eagerly,
    # a program per operation).
    g = jax.jit(jax.grad(lambda w: rj.kinetic_energy(I3, w) + jnp.sum(rj.euler_equations(I3, w))))(zero)
    assert np.all(np.isfinite(g))
    g = jax.jit(jax.jacrev(rj.quat_from_matrix))(np.eye(3))
    assert np.all(np.isfinite(g))
    extreme(
        "bad input",
        "valid degenerate input: zero omega, identity / half-turn rotations, zero-size parts",
        "finite values and gradients (no manufactured NaN/inf)",
    )


# ----------------------------------------------------------------------------------------------
# 4. Elliptic functions: scipy.special's conventions
# ----------------------------------------------------------------------------------------------

ELLIPTIC = {
    "ellipk": (rj.elliptic.ellipk, (0.5,)),
    "ellipkm1": (rj.elliptic.ellipkm1, (0.5,)),
    "ellipe": (rj.elliptic.ellipe, (0.5,)),
    "ellipkinc": (rj.elliptic.ellipkinc, (0.3, 0.5)),
    "ellipeinc": (rj.elliptic.ellipeinc, (0.3, 0.5)),
    "ellipj": (rj.elliptic.ellipj, (0.3, 0.5)),
    "ellipj_m1": (rj.elliptic.ellipj_m1, (0.3, 0.5)),
    "elliprj": (rj.elliptic.elliprj, (1.0, 2.0, 3.0, 4.0)),
}


@pytest.mark.parametrize("name", list(ELLIPTIC))
def test_elliptic_bad_inputs(name, without_runtime_typecheck, extreme):
    """Elementwise special functions keep scipy's semantics: NaN in, NaN out (never a finite
    number), while structural problems raise naming the argument."""
    fn, good = ELLIPTIC[name]
    args = [np.asarray(a) for a in good]
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(fn(*args)))
    nan_out = fn(*([np.asarray(nan)] + args[1:]))
    assert all(np.all(np.isnan(x)) for x in jax.tree.leaves(nan_out))
    for bad, error in ((args[0].astype(complex), "must be real"), (np.asarray(True), "bool")):
        with pytest.raises(TypeError, match=error):
            fn(*([bad] + args[1:]))
    # Half precision is computed in float32, as scipy.special does.
    half = fn(*[a.astype(np.float16) for a in args])
    single = fn(*[a.astype(np.float16).astype(np.float32) for a in args])
    for h, s in zip(jax.tree.leaves(half), jax.tree.leaves(single), strict=True):
        assert h.dtype == np.float32
        np.testing.assert_array_equal(h, s)
    if len(args) > 1:
        with pytest.raises(ValueError, match="must broadcast"):
            fn(*([np.ones(2)] + [np.full(3, a) for a in args[1:]]))
    if name == "ellipk":
        extreme(
            "bad input",
            "elliptic functions: NaN or out-of-domain arguments",
            "NaN results, as scipy.special (elementwise; a batch keeps its other elements)",
            advice="check domains (0 <= m <= 1) before calling",
        )


# ----------------------------------------------------------------------------------------------
# 5. Entry points of the other modules: scenes, simulate, closed forms, fitting, integrators
# ----------------------------------------------------------------------------------------------

TS = np.linspace(0.0, 1.0, 5)


def _simulate(model=None, state=None, ts=TS):
    model = rj.FreeBody(I3) if model is None else model
    state = rj.State(W, Q) if state is None else state
    return jax.block_until_ready(rj.simulate(model, state, ts, accuracy="fast").omega)


def _heavy_top(mass=1.0, com=COM, torque=W):
    """One model structure (so one compile) for the model-field cases: a heavy top with a torque."""
    return rj.HeavyTop(I3, np.asarray(mass), com, torque=rj.ConstantTorque(torque))


SIMULATE_CASES = {
    "nan-inertia": (lambda: _simulate(rj.FreeBody(with_value(I3, nan))), "inertia .*contains NaN"),
    "non-physical-inertia": (
        lambda: _simulate(rj.FreeBody(np.array([1.0, 1.0, 3.0]))),
        "triangle inequality",
    ),
    "negative-moment": (lambda: _simulate(rj.FreeBody(np.array([-1.0, 2.0, 2.5]))), "non-positive"),
    "nan-omega": (lambda: _simulate(state=rj.State(with_value(W, nan), Q)), "state0.omega contains NaN"),
    "inf-orientation": (lambda: _simulate(state=rj.State(W, with_value(Q, inf))), "orientation contains NaN"),
    "non-unit-orientation": (lambda: _simulate(state=rj.State(W, 1.1 * Q)), "not a unit quaternion"),
    "zero-orientation": (lambda: _simulate(state=rj.State(W, np.zeros(4))), "not a unit quaternion"),
    "unsorted-ts": (lambda: _simulate(ts=TS[::-1]), "strictly increasing"),
    "duplicate-ts": (lambda: _simulate(ts=np.array([0.0, 0.5, 0.5, 0.7, 1.0])), "strictly increasing"),
    "nan-ts": (lambda: _simulate(ts=with_value(TS, nan, 2)), "ts contains NaN"),
    "heavy-top-nan-mass": (lambda: _simulate(_heavy_top(mass=nan)), "'mass' contains NaN"),
    "heavy-top-nan-com": (lambda: _simulate(_heavy_top(com=with_value(COM, nan))), "'com' contains NaN"),
    "constant-torque-nan": (lambda: _simulate(_heavy_top(torque=with_value(W, nan))), "torque' contains NaN"),
}


# Each case compiles a simulation: the fast tier keeps one per kind of problem.
SIMULATE_FAST = ("nan-inertia", "non-unit-orientation", "unsorted-ts")


@pytest.mark.parametrize(
    "case", [pytest.param(c, marks=() if c in SIMULATE_FAST else pytest.mark.slow) for c in SIMULATE_CASES]
)
def test_simulate_rejects_bad_values(case):
    """simulate is itself jitted (eqx.filter_jit): these are run-time errors inside a compiled program."""
    fn, match = SIMULATE_CASES[case]
    with pytest.raises(RUNTIME, match=match):
        fn()


@pytest.mark.parametrize("solver", ["adaptive", "fixed-step"])
def test_errors_under_eager_grad_are_value_errors(solver):
    """Under grad or jvp outside jit the inputs' primal values are known: the integrators raise the
    same ValueError as for plain arrays, before the differentiated program is compiled, rather than
    an EquinoxRuntimeError from inside it."""
    options = {"accuracy": "fast"} if solver == "adaptive" else {"solver": rj.solvers.RKMK(), "dt0": 0.25}

    def loss(scale, inertia, ts=TS):
        state = rj.State(jnp.asarray(W), jnp.asarray(Q) * scale)
        return jnp.sum(rj.simulate(rj.FreeBody(inertia), state, ts, **options).omega)

    cases = {
        "not a unit quaternion": (1.1, I3, TS),
        "triangle inequality": (1.0, np.array([1.0, 1.0, 3.0]), TS),
        "strictly increasing": (1.0, I3, TS[::-1]),
    }
    for match, (scale, inertia, ts) in cases.items():
        with pytest.raises(ValueError, match=match) as raised:
            jax.grad(loss)(scale, inertia, ts)
        assert not isinstance(raised.value, eqx.EquinoxRuntimeError)
        with pytest.raises(ValueError, match=match):
            jax.jvp(functools.partial(loss, inertia=inertia, ts=ts), (scale,), (1.0,))
    with pytest.raises(ValueError, match="triangle inequality"):
        jax.grad(lambda i: loss(1.0, i))(jnp.array([1.0, 1.0, 3.0]))


def test_scene_structural_errors(without_runtime_typecheck, extreme):
    for fn, match in [
        (lambda: rj.State(np.ones(4)), r"State\.omega must have shape"),
        (lambda: rj.State(W, np.ones(3)), r"State\.orientation must have shape"),
        (lambda: rj.State(W.astype(complex)), r"State\.omega must be real"),
        (lambda: rj.State(W, Q.astype(complex)), r"State\.orientation must be real"),
        (lambda: rj.FreeBody(np.ones(4)), "inertia must be principal moments"),
        (lambda: rj.HeavyTop(I3, 1.0, np.ones(2)), r"HeavyTop\.com must have shape"),
        (lambda: rj.ConstantTorque(np.ones(2)), r"ConstantTorque\.torque must have shape"),
        (lambda: rj.ConstantTorque(W, frame="world"), "frame must be 'body' or 'space'"),
        (
            lambda: rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS, accuracy="bogus"),
            "accuracy must be one of",
        ),
        (  # a fixed-step solver ignores accuracy; its typo ran silently
            lambda: rj.simulate(
                rj.FreeBody(I3),
                rj.State(W, Q),
                TS,
                solver=rj.solvers.LiePoissonSplitting(),
                dt0=0.1,
                accuracy="bogus",
            ),
            "accuracy must be one of",
        ),
        (lambda: rj.simulate(rj.FreeBody(I3), rj.State(W, Q), np.ones((2, 3))), "ts must be a 1-D array"),
    ]:
        with pytest.raises((ValueError, TypeError), match=match):
            fn()
    trajectory = rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS, accuracy="fast")
    with pytest.raises(ValueError, match="seq must be one of"):
        trajectory.euler_angles("abc")
    omega_only = rj.simulate(rj.FreeBody(I3), rj.State(W), TS, accuracy="fast")
    for method in (omega_only.space_angular_momentum, omega_only.euler_angles):
        with pytest.raises(ValueError, match="orientation"):
            method()
    extreme(
        "bad input",
        "simulate: NaN/inf in the model or state, non-physical inertia, non-unit orientation, "
        "unsorted or repeated ts",
        "ValueError before integrating (EquinoxRuntimeError inside the user's jit), naming the field",
    )


@pytest.mark.parametrize("accuracy", ["fast", "exact"])
def test_sample_times_that_are_not_real_numbers_or_collapse_are_named(accuracy, without_runtime_typecheck):
    """Complex times lost their imaginary part and booleans ran as 0 and 1 s, silently; text and
    None failed inside NumPy or JAX without naming ts. float64 times that collapse in a float32 run
    were blamed as "not strictly increasing" by the closed form and in 32-bit mode."""
    body = rj.FreeBody(I3)
    for ts, kind in (
        (np.array([0.0, 1 + 5j, 2 + 7j]), "complex128"),
        (np.array([False, True]), "bool"),
        ("0 1 2", "<U5"),
        (None, "object"),
        (["0", "1"], "<U1"),
    ):
        with pytest.raises(TypeError, match=rf"^ts must be real sample times in seconds .*dtype {kind}"):
            rj.simulate(body, rj.State(W, Q), ts, accuracy=accuracy)
    collapse = "ts increase in float64 but not once cast to float32"
    times = np.array([1e5, 1e5 + 1e-3, 1e5 + 2e-3])
    f32 = np.float32
    with pytest.raises(ValueError, match=collapse):
        rj.simulate(rj.FreeBody(f32(I3)), rj.State(f32(W), f32(Q)), times, accuracy=accuracy)
    with jax.enable_x64(False), pytest.raises(ValueError, match=collapse):
        rj.simulate(rj.FreeBody(f32(I3)), rj.State(f32(W), f32(Q)), times, accuracy=accuracy)


_TS_FIT = np.linspace(0.0, 10.0, 41)
# Records of a torque-free body by scipy (no program to compile while the tests are collected).
_W_FIT, _Q_FIT = dop853_free_body(I3, W, _TS_FIT, Q)
FIT_CASES = {
    "fit_inertia-inf": (
        lambda: rj.fit_inertia(_TS_FIT, with_value(_W_FIT, inf)),
        "omega_observed contains inf",
    ),
    "fit_inertia-unsorted": (lambda: rj.fit_inertia(_TS_FIT[::-1], _W_FIT), "strictly increasing"),
    "fit_inertia-nan-ts": (lambda: rj.fit_inertia(with_value(_TS_FIT, nan), _W_FIT), "ts contains NaN"),
    "fit_inertia-shape": (
        lambda: rj.fit_inertia(_TS_FIT, _W_FIT[:, :2]),
        r"omega_observed must have shape \(T, 3\)",
    ),
    "fit_inertia-all-missing": (
        lambda: rj.fit_inertia(_TS_FIT, np.full_like(_W_FIT, nan)),
        "Too few samples",
    ),
    "fit_to_orientation-non-unit": (
        lambda: rj.fit_inertia_to_orientation(_TS_FIT, 1.1 * _Q_FIT),
        # the first row that is not unit, not the one roundoff made the worst
        r"orientation_observed must hold unit quaternions; row 0 has norm 1.1 \(41 of 41 rows",
    ),
    "fit_to_orientation-unsorted": (
        lambda: rj.fit_inertia_to_orientation(_TS_FIT[::-1], _Q_FIT),
        "strictly increasing",
    ),
    "omega_from_orientations-zero": (
        lambda: rj.omega_from_orientations(_TS_FIT, with_value(_Q_FIT, 0.0) * (np.arange(41) > 0)[:, None]),
        "unit quaternions; row 0 has norm 0",
    ),
    "omega_from_orientations-unsorted": (
        lambda: rj.omega_from_orientations(_TS_FIT[::-1], _Q_FIT),
        "strictly increasing",
    ),
    "omega_from_orientations-inf": (
        lambda: rj.omega_from_orientations(_TS_FIT, with_value(_Q_FIT, inf)),
        "q_observed contains inf",  # the argument's own name
    ),
}


@pytest.mark.parametrize("case", list(FIT_CASES))
def test_fitting_rejects_bad_data_at_call_time(case):
    """The fitting entry points prepare data in NumPy: errors are ValueErrors before any compile.
    NaN samples are missing data by contract, not an error (all missing: too few samples)."""
    fn, match = FIT_CASES[case]
    with pytest.raises(ValueError, match=match):
        fn()


def _raises_or_nan(fn):
    """Pass only if ``fn`` raises (a finite or NaN result fails)."""
    with pytest.raises((RuntimeError, ValueError, TypeError)):
        out = jax.block_until_ready(fn())
        assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(out) if hasattr(x, "dtype"))


_ONCE_SILENT = {
    # case -> (call, what it did before its check was added)
    "torque_free_omega-nan": (
        lambda: rj.torque_free_omega(I3, with_value(W, nan), 0.5),
        "torque_free_omega: NaN/inf in inertia, omega0 or t returned NaN silently",
    ),
    "torque_free_period-negative-moment": (
        lambda: rj.torque_free_period(np.array([-1.0, 2.0, 2.5]), W),
        "torque_free_period: non-positive moments gave NaN silently",
    ),
    "torque_free_motion-zero-q0": (
        lambda: rj.torque_free_motion(I3, W, np.zeros(4), 0.5),
        "torque_free_motion: a zero q0 returned a finite (meaningless) quaternion",
    ),
    "spin_stability-nan-omega": (
        lambda: rj.spin_stability(I3, nan),
        "spin_stability: NaN omega_magnitude returned NaN rates silently",
    ),
    "sleeping_top-nan-omega3": (
        lambda: rj.sleeping_top(np.array([1.0, 1.0, 0.5]), 1.0, COM, nan),
        "sleeping_top: NaN omega3 (or mass, gravity) returned NaN silently",
    ),
    "sleeping_top-negative-mass": (
        lambda: rj.sleeping_top(np.array([1.0, 1.0, 0.5]), -1.0, COM, 20.0),
        "sleeping_top: a negative mass was accepted",
    ),
    "simulate-heavy-top-negative-mass": (
        lambda: _simulate(_heavy_top(mass=-1.0)),
        "simulate: HeavyTop with a negative mass was simulated without error",
    ),
    "estimate_inertia-unsorted": (
        lambda: rj.estimate_inertia(_TS_FIT[::-1], _W_FIT),
        "estimate_inertia: unsorted ts gave NaN results instead of the ValueError fit_inertia raises",
    ),
    "estimate_inertia-inf": (
        lambda: rj.estimate_inertia(_TS_FIT, with_value(_W_FIT, inf)),
        "estimate_inertia: inf samples gave NaN results instead of a ValueError",
    ),
    "quat_exp-nan": (
        lambda: rj.kinematics.quat_exp(with_value(W, nan)),
        "kinematics.quat_exp: NaN/inf theta returned NaN silently",
    ),
    "dexpinv-nan": (
        lambda: rj.solvers.dexpinv(W, with_value(W, nan)),
        "solvers.dexpinv: NaN/inf returned NaN silently",
    ),
    "rkmk_step-nan-omega": (
        lambda: rj.solvers.rkmk_step(lambda t, w, q, args: -w, 0.0, with_value(W, nan), Q, 0.1),
        "solvers.rkmk_step: NaN omega/q/h returned NaN silently",
    ),
    "simulate-RKMK-nan-omega": (
        lambda: (
            rj.simulate(
                rj.FreeBody(I3), rj.State(with_value(W, nan), Q), TS, solver=rj.solvers.RKMK(), dt0=0.1
            ).omega
        ),
        "simulate(solver=RKMK()): NaN state0.omega gave a NaN trajectory (the presets raised)",
    ),
    "simulate-RKMK-non-physical": (
        lambda: (
            rj.simulate(
                rj.FreeBody(np.array([1.0, 1.0, 3.0])), rj.State(W, Q), TS, solver=rj.solvers.RKMK(), dt0=0.1
            ).omega
        ),
        "simulate(solver=RKMK()): non-physical inertia was integrated (the presets raised)",
    ),
    "split_free_body-nan": (
        lambda: rj.solvers.split_free_body(with_value(I3, nan), W, Q, 0.1, 2),
        "solvers.split_free_body: NaN/inf inertia, L0, q0 or dt returned NaN silently",
    ),
    "split_free_body-zero-q0": (
        lambda: rj.solvers.split_free_body(I3, W, np.zeros(4), 0.1, 2),
        "solvers.split_free_body: a zero q0 was integrated silently",
    ),
    "split_heavy_top-nan": (
        lambda: rj.solvers.split_heavy_top(I3, nan, COM, 9.81, W, Q, 0.1, 2),
        "solvers.split_heavy_top: NaN mass (or other input) returned NaN silently",
    ),
    "LiePoissonSplitting-nan": (
        lambda: rj.solvers.LiePoissonSplitting(with_value(I3, nan)).inertia,
        "solvers.LiePoissonSplitting: NaN/non-physical inertia was accepted at construction",
    ),
    "HeavyTopSplitting-nan": (
        lambda: rj.solvers.HeavyTopSplitting(I3, nan, COM).inertia,
        "solvers.HeavyTopSplitting: NaN mass was accepted at construction",
    ),
}


@pytest.mark.parametrize(
    "case",
    [
        pytest.param(c, marks=pytest.mark.slow if c.startswith(("simulate", "torque_free_motion")) else ())
        for c in _ONCE_SILENT
    ],
)
def test_values_without_a_meaningful_result_raise(case):
    """Each case returned NaN or meaningless output silently when this suite was written; the
    check named in the reason is now in place."""
    _raises_or_nan(_ONCE_SILENT[case][0])


@functools.cache
def _gravity_runs():
    """The scene of the gravity cases, and each model's run under jit: one jitted function per model
    for all the cases, so the zero and negative gravities (the same signature) share one compiled
    program. (It holds the run-time checks' host callbacks, which the persistent cache does not keep:
    a fresh ``jax.jit`` per case compiled it again.)"""
    state, ts = rj.State(W, Q), jnp.linspace(0.0, 0.1, 3)
    models = (
        lambda g: rj.HeavyTop(I3, 0.5, COM, gravity=g),
        lambda g: rj.RigidBody(I3, torque=rj.GravityTorque(0.5, COM, gravity=g)),
    )
    runs = [
        (model, jax.jit(lambda g, model=model: rj.simulate(model(g), state, ts).omega)) for model in models
    ]
    return state, ts, runs


@pytest.mark.parametrize("gravity", [0.0, -9.81, (0.0, 0.0, -9.81)], ids=["zero", "negative", "vector"])
def test_gravity_is_a_positive_magnitude(gravity):
    """gravity = 0 or -9.81 ran (and sleeping_top called an upright top stable at any spin), and a
    gravity vector (0, 0, -9.81) ran as three tops with g = 0, 0 and -9.81; also under jit.
    sleeping_top took g = 0, so (0, 0, 9.81) read as three tops, two of them stable."""
    gravity = jnp.asarray(gravity)
    state, ts, runs = _gravity_runs()
    pattern = r"model field '(torques\[0\]\.)?gravity' must be positive \(m/s\^2\).*not a vector"
    for model, jitted in runs:
        with pytest.raises(ValueError, match=pattern):
            rj.simulate(model(gravity), state, ts)
        with pytest.raises(Exception, match=pattern):
            jitted(gravity).block_until_ready()
    with pytest.raises(ValueError, match=r"torque \(GravityTorque\): gravity must be positive.*not a vector"):
        rj.fit_inertia_to_orientation(_TS_FIT, _Q_FIT, torque=rj.GravityTorque(0.5, COM, gravity=gravity))
    # sleeping_top read the vector as three tops, two of them "stable" without gravity.
    with pytest.raises(ValueError, match=r"sleeping_top: gravity must be positive.*not a vector"):
        rj.sleeping_top(np.array([1.0, 1.0, 0.5]), 0.5, COM, 5.0, gravity)
    if gravity.ndim == 0:
        with pytest.raises(ValueError, match=r"split_heavy_top: gravity must be positive"):
            rj.solvers.split_heavy_top(I3, 0.5, COM, gravity, I3 * W, Q, 0.1, 3)


def test_a_solver_without_an_error_estimate_asks_for_a_fixed_step():
    """diffrax.Euler() with dt0 and no controller raised diffrax's bare RuntimeError ("Cannot use
    adaptive step sizes with a solver that does not provide error estimates"), naming no argument.
    With a constant step it runs: against the closed form, Euler's error is first order in dt."""
    state, ts = rj.State(W, Q), jnp.linspace(0.0, 1.0, 3)
    for solver in (diffrax.Euler(), diffrax.LeapfrogMidpoint()):
        with pytest.raises(
            ValueError, match=rf"solver={type(solver).__name__}\(\) has no error estimate.*ConstantStepSize"
        ):
            rj.simulate(rj.FreeBody(I3), state, ts, solver=solver, dt0=0.01)
    exact = np.asarray(rj.torque_free_omega(I3, W, ts))  # (simulate's "exact" program took 4 s more)
    errors = [
        np.max(np.abs(np.asarray(rj.simulate(rj.FreeBody(I3), state, ts, solver=diffrax.Euler(), dt0=dt,
                                             stepsize_controller=diffrax.ConstantStepSize()).omega) - exact))
        for dt in (0.01, 0.005)
    ]  # fmt: skip
    assert 1.8 < errors[0] / errors[1] < 2.2


@pytest.mark.parametrize("controller", [None, diffrax.ConstantStepSize()])
def test_a_partitioned_solver_is_named(controller):
    """diffrax.SemiImplicitEuler() integrates a system in two parts, (positions, momenta): the error
    for its missing error estimate asked for a constant step, which then failed with diffrax's
    TermAndSolverIncompatible. Now it is named, with or without the step, before anything runs, and so
    is an implicit-explicit solver."""
    state, ts = rj.State(W, Q), jnp.linspace(0.0, 1.0, 3)
    for solver in (diffrax.SemiImplicitEuler(), diffrax.KenCarp4()):
        with pytest.raises(
            ValueError, match=rf"solver={type(solver).__name__}\(\) integrates a system split"
        ):
            rj.simulate(rj.FreeBody(I3), state, ts, solver=solver, dt0=0.01, stepsize_controller=controller)


def test_the_fixed_step_runs_and_rkmk_step_name_their_arguments(without_runtime_typecheck):
    """A negative or fractional n_steps returned the initial state or a raw fori_loop TypeError;
    lists made the jitted run raise TracerArrayConversionError; a bad mass came out as "INTERNAL:
    CpuCallback error"; rkmk_step's acceleration of the wrong shape was a broadcasting error, and a
    NaN one gave NaN silently; a batch of three bodies' moments (3, 3) was called a tensor without
    the way to pass it."""
    run = rj.solvers.split_free_body
    for n_steps in (-5, 2.0, True):
        with pytest.raises(ValueError, match=r"split_free_body: n_steps must be a non-negative integer"):
            run(I3, I3 * W, Q, 0.1, n_steps)
    L, q = run(I3, I3 * W, Q, 0.1, 0)  # no step: the initial state
    np.testing.assert_array_equal(L, I3 * W)
    np.testing.assert_array_equal(q, Q)
    lists = run(I3.tolist(), (I3 * W).tolist(), Q.tolist(), 0.1, 3)
    np.testing.assert_array_equal(lists[0], run(I3, I3 * W, Q, 0.1, 3)[0])
    with pytest.raises(ValueError, match=r"^split_heavy_top: mass must be positive"):
        rj.solvers.split_heavy_top(I3, -1.0, COM, 9.81, I3 * W, Q, 0.1, 3)
    with pytest.raises(ValueError, match=r"split_free_body needs principal moments.*\(3, 1, 3\)"):
        run(np.stack([I3, I3, I3]), np.stack([W, W, W]), Q, 0.1, 3)
    step = rj.solvers.rkmk_step
    with pytest.raises(ValueError, match=r"angular_acceleration must return .* shape \(3,\).*got \(4,\)"):
        step(lambda t, w, q, a: jnp.ones(4), 0.0, W, Q, 0.1)
    with pytest.raises(ValueError, match=r"rkmk_step: the step's omega is NaN or inf"):
        step(lambda t, w, q, a: w * jnp.nan, 0.0, W, Q, 0.1)


def test_the_fixed_step_solvers_options(without_runtime_typecheck):
    """dt0=np.float32(0.01) was refused and dt0=True ran with 1 s steps; a traced dt0 was a raw
    ConcretizationTypeError; max_steps below the grid's steps was ignored; order=4.0 was stored as
    a float and np.int64(4) warned three times; HeavyTopSplitting.from_model of a free body was an
    AttributeError."""
    solver = rj.solvers.LiePoissonSplitting(order=4)
    body, state, ts = rj.FreeBody(I3), rj.State(W, Q), jnp.linspace(0.0, 1.0, 3)
    as_float = rj.simulate(body, state, ts, solver=solver, dt0=0.0078125)
    as_numpy = rj.simulate(body, state, ts, solver=solver, dt0=np.float32(0.0078125))  # exact in float32
    np.testing.assert_array_equal(as_numpy.omega, as_float.omega)
    with pytest.raises(TypeError, match="dt0 must be a step in seconds, got True"):
        rj.simulate(body, state, ts, solver=solver, dt0=True)
    with pytest.raises(ValueError, match="dt0 must be concrete"):
        jax.jit(lambda dt: rj.simulate(body, state, ts, solver=solver, dt0=dt).omega)(0.01)
    with pytest.raises(ValueError, match=r"dt0 takes 128 steps over ts, more than max_steps=5"):
        rj.simulate(body, state, ts, solver=solver, dt0=0.0078125, max_steps=5)
    with pytest.raises(ValueError, match=r"order must be 2 or 4, got 4\.0"):
        rj.solvers.LiePoissonSplitting(order=4.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert rj.solvers.LiePoissonSplitting(I3, order=np.int64(4)).splitting_order == 4
    with pytest.raises(ValueError, match="from_model needs a HeavyTop, got a FreeBody"):
        rj.solvers.HeavyTopSplitting.from_model(body)


def test_fit_rejects_complex_data():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (the warning, not a fit: this stays cheap)
        with pytest.raises(TypeError, match="omega_observed"):
            rj.fit_inertia(_TS_FIT, _W_FIT.astype(complex), steps=1)


def test_dexpinv_shape_error_names_argument(without_runtime_typecheck):
    with pytest.raises(ValueError, match=r"\btheta\b"):
        rj.solvers.dexpinv(np.ones(4), W)


def test_estimate_inertia_shape_error_names_argument():
    with pytest.raises(ValueError, match="omega_observed"):
        rj.estimate_inertia(_TS_FIT, _W_FIT[:, :2])


@pytest.mark.parametrize("samples", [0, 1, 4])
def test_estimate_inertia_on_too_short_a_record_says_so(samples):
    """Fewer samples than one local quadratic fit spans: a ValueError naming the record and the count,
    not NumPy's IndexError or a NaN conversion error from an empty fit."""
    with pytest.raises(ValueError, match=rf"at least 5 samples of omega_observed .*got {samples}\."):
        rj.estimate_inertia(_TS_FIT[:samples], _W_FIT[:samples])


def test_other_structural_errors(without_runtime_typecheck):
    for fn, match in [
        (lambda: rj.torque_free_omega(np.ones(4), W, 0.5), "inertia must have shape"),
        (lambda: rj.torque_free_motion(I3, W, np.zeros(3), 0.5), "q0 must have shape"),
        (lambda: rj.torque_free_period(I3.astype(complex), W), "inertia must be real"),
        (lambda: rj.kinematics.quat_exp(np.ones(4)), "theta must have shape"),
        (
            lambda: rj.solvers.rkmk_step(lambda t, w, q, a: w, 0.0, np.ones(4), Q, 0.1),
            "omega must have shape",
        ),
        (
            lambda: rj.solvers.rkmk_step(lambda t, w, q, a: w, 0.0, W, Q, 0.1, tableau="bogus"),
            "tableau must be one of",
        ),
        (lambda: rj.solvers.split_free_body(I3, np.ones(4), Q, 0.1, 2), "must have shape"),
        (lambda: rj.solvers.split_free_body(np.eye(3), W, Q, 0.1, 2), "needs principal moments"),
        (lambda: rj.solvers.split_free_body(I3, W, Q, 0.1, 2, order=3), "order must be 2 or 4"),
        (lambda: rj.spin_stability(TENSOR, 1.0), "needs principal moments"),
        (
            lambda: rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS[::-1], solver=rj.solvers.RKMK(), dt0=0.1),
            "strictly increasing",
        ),
    ]:
        with pytest.raises((ValueError, TypeError), match=match):
            fn()


# ----------------------------------------------------------------------------------------------
# fit_inertia / fit_inertia_to_orientation: every option checked before any work (no compile), so
# a bad option is a ValueError/TypeError naming it -- never a raw IndexError after the fit, and
# never a negative or NaN inertia reported as converged.
# ----------------------------------------------------------------------------------------------

_FIT_FNS = {
    "fit_inertia": lambda **kw: rj.fit_inertia(_TS_FIT, _W_FIT, **kw),
    "fit_inertia_to_orientation": lambda **kw: rj.fit_inertia_to_orientation(_TS_FIT, _Q_FIT, **kw),
}
FIT_OPTION_CASES = {
    # case -> (keyword arguments, error type, message)
    "inertia_trace-negative": (
        {"inertia_trace": -1.0},
        ValueError,
        r"inertia_trace must be a positive finite",
    ),
    "inertia_trace-zero": ({"inertia_trace": 0.0}, ValueError, r"inertia_trace must be a positive finite"),
    "inertia_trace-nan": ({"inertia_trace": nan}, ValueError, r"inertia_trace must be a positive finite"),
    "inertia_trace-inf": ({"inertia_trace": inf}, ValueError, r"inertia_trace must be a positive finite"),
    "inertia_trace-array": ({"inertia_trace": np.ones(3)}, TypeError, r"inertia_trace must be a number"),
    "inertia_trace-text": ({"inertia_trace": "1"}, TypeError, r"inertia_trace must be a number"),
    "known_moment-negative": ({"known_moment": (2, -1.0)}, ValueError, r"known_moment's moment I_kk"),
    "known_moment-zero": ({"known_moment": (2, 0.0)}, ValueError, r"known_moment's moment I_kk"),
    "known_moment-nan": ({"known_moment": (2, nan)}, ValueError, r"known_moment's moment I_kk"),
    "known_moment-index-5": ({"known_moment": (5, 1.0)}, ValueError, r"index 5, which is out of range"),
    "known_moment-index-negative": (
        {"known_moment": (-1, 1.0)},
        ValueError,
        r"index -1, which is out of range",
    ),
    "known_moment-index-float": (
        {"known_moment": (2.0, 1.0)},
        ValueError,
        r"index 2.0, which is not an integer",
    ),
    "known_moment-not-a-pair": ({"known_moment": 2.5}, ValueError, r"known_moment must be \(k, I_kk\)"),
    "both-scales": ({"inertia_trace": 1.0, "known_moment": (0, 1.0)}, ValueError, "at most one scale"),
    "steps-zero": ({"steps": 0}, ValueError, r"steps must be a positive integer"),
    "steps-negative": ({"steps": -5}, ValueError, r"steps must be a positive integer"),
    "steps-float": ({"steps": 10.5}, ValueError, r"steps must be a positive integer"),
    "tol-negative": ({"tol": -1e-9}, ValueError, r"tol must be a non-negative finite"),
    "tol-nan": ({"tol": nan}, ValueError, r"tol must be a non-negative finite"),
    "f_scale-zero": ({"f_scale": 0.0}, ValueError, r"f_scale must be a positive finite"),
    "loss-unknown": ({"loss": "l1"}, ValueError, r"loss must be one of"),
    "method-unknown": ({"method": "newton"}, ValueError, r"method must be one of"),
    "optimizer-with-lm": (
        {"method": "levenberg-marquardt", "optimizer": object()},
        ValueError,
        r"optimizer is used only with method='optax'",
    ),
    "optimizer-not-optax": ({"optimizer": "adam"}, TypeError, r"optimizer must be an optax"),
    "callback-not-callable": ({"callback": 3}, TypeError, r"callback must be callable"),
    # a callback of the wrong arity failed inside the compiled fit as "CpuCallback error", after compiling
    "callback-no-arguments": ({"callback": lambda: None}, TypeError, r"callback\(iteration, loss\), got"),
    "progress-one-argument": ({"progress": lambda i: None}, TypeError, r"progress\(iteration, loss\), got"),
    "dtype-int": ({"dtype": np.int32}, ValueError, r"dtype must be a floating dtype"),
    "dtype-garbage": ({"dtype": "float99"}, TypeError, r"dtype must be a floating dtype"),
    "full_tensor-not-bool": ({"full_tensor": "yes"}, TypeError, r"full_tensor must be True or False"),
    "segments-zero": ({"segments": 0}, ValueError, r"segments must be a positive integer or 'auto'"),
    "segments-negative": ({"segments": -2}, ValueError, r"segments must be a positive integer or 'auto'"),
    "segments-float": ({"segments": 2.0}, ValueError, r"segments must be a positive integer or 'auto'"),
    "segments-over-samples": ({"segments": 41}, ValueError, r"segments=41 is too many for 41 samples"),
    "inertia_init-negative": (
        {"inertia_init": np.array([-1.0, 2.0, 2.5])},
        ValueError,
        "inertia_init has a non-positive principal moment",
    ),
    # XLA on CPU reads a subnormal as 0: the message says so, a positive moment is not "non-positive" alone.
    "inertia_init-subnormal": (
        {"inertia_init": np.array([1.0, 1.0, 5e-320])},
        ValueError,
        r"inertia_init has a non-positive principal moment \(a moment below float64's smallest normal "
        r"number, 2.23e-308, is 0\)",
    ),
    "inertia_init-nan": ({"inertia_init": with_value(I3, nan)}, ValueError, "inertia_init contains NaN"),
    "inertia_init-triangle": (
        {"inertia_init": np.array([1.0, 1.0, 3.0])},
        ValueError,
        "inertia_init violates the triangle inequality",
    ),
    "inertia_init-shape": (
        {"inertia_init": np.ones(4)},
        ValueError,
        r"inertia_init must have shape \(3,\) \(principal moments\)",
    ),
    "inertia_init-tensor-shape": (
        {"inertia_init": I3, "full_tensor": True},
        ValueError,
        r"inertia_init must have shape \(3, 3\) \(a tensor",
    ),
    "inertia_init-asymmetric": (
        {"inertia_init": TENSOR + np.triu(np.ones((3, 3)), 1), "full_tensor": True},
        ValueError,
        "inertia_init is not symmetric",
    ),
    "omega0_init-shape": ({"omega0_init": np.ones(4)}, ValueError, r"omega0_init must have shape \(3,\)"),
    "omega0_init-segments": (
        {"omega0_init": np.ones((3, 3)), "segments": 2},
        ValueError,
        r"omega0_init must have shape \(3,\) or \(2, 3\)",
    ),
    "omega0_init-nan": ({"omega0_init": with_value(W, nan)}, ValueError, "omega0_init contains NaN"),
}
_FIT_ONLY_GYRO = {
    "noise-text": (
        {"noise": "loud"},
        ValueError,
        r"noise must be a number, three numbers \(rad/s\) or 'equal'",
    ),
    "noise-shape": ({"noise": np.ones(2)}, ValueError, r"noise must be a scalar or have shape \(3,\)"),
    "noise-negative": ({"noise": -0.1}, ValueError, "noise must be positive finite"),
}
_FIT_ONLY_ORIENTATION = {
    "orientation0_init-shape": (
        {"orientation0_init": np.ones(3)},
        ValueError,
        r"orientation0_init must have shape \(4,\)",
    ),
    "orientation0_init-zero": (
        {"orientation0_init": np.zeros(4)},
        ValueError,
        "orientation0_init has a zero",
    ),
    "orientation0_init-nan": (
        {"orientation0_init": with_value(Q, nan)},
        ValueError,
        "orientation0_init contains NaN",
    ),
}
_FIT_OPTION_PARAMS = [
    pytest.param(fn, case, kw, err, match, id=f"{fn}-{case}")
    for fn in _FIT_FNS
    for case, (kw, err, match) in {
        **FIT_OPTION_CASES,
        **(_FIT_ONLY_GYRO if fn == "fit_inertia" else _FIT_ONLY_ORIENTATION),
    }.items()
]


@pytest.mark.parametrize(("fn", "case", "kwargs", "error", "match"), _FIT_OPTION_PARAMS)
def test_fit_rejects_bad_options_before_any_work(
    fn, case, kwargs, error, match, monkeypatch, without_runtime_typecheck
):
    """Each bad option is named before the optimiser is compiled: the compiled fit is replaced by a
    function that fails the test, so a check that came too late (or not at all) cannot pass. (The
    test run's annotation checker is off: users do not have it, and rigidjax's own message is the
    one to check.)"""
    from rigidjax._fit import fit as fit_module

    def no_fit(*args, **kw):
        raise AssertionError(f"{case}: the fit ran instead of rejecting the option")

    monkeypatch.setattr(fit_module, "_run", no_fit)
    with pytest.raises(error, match=match):
        _FIT_FNS[fn](**kwargs)


@pytest.mark.parametrize(
    ("options", "match"),
    [
        # fixed steps counted in int64 overflowed (IndexError) or allocated their grid (MemoryError)
        ({"solver": rj.solvers.RKMK(), "dt0": 1e-300}, r"dt0 = 1e-300 takes 5e\+300 fixed steps"),
        ({"solver": rj.solvers.RKMK(), "dt0": 1e-9}, r"dt0 = 1e-09 takes 5e\+09 fixed steps over ts \(5 s\)"),
        ({"solver": rj.solvers.LiePoissonSplitting(), "dt0": 1e-320}, r"takes inf fixed steps"),
        ({"max_steps": 10**20}, r"max_steps must be at most 2,147,483,647"),  # was JAX's OverflowError
        ({"progress": lambda: None}, r"progress must be callable as progress\(done_bodies, total_bodies\)"),
    ],
    ids=["rkmk-1e-300", "rkmk-1e-9", "splitting-subnormal", "max-steps-1e20", "progress-arity"],
)
def test_options_beyond_what_can_run_are_named_before_any_work(options, match, monkeypatch):
    """Options that cannot run are named before anything compiles (the integration is replaced by a
    function that fails the test): dt0 so small that the fixed steps overflowed their count or filled
    the memory, a max_steps beyond 32-bit integers, a progress callable of the wrong arity (a raw
    TypeError at its first call, after the compile)."""
    from rigidjax._integrate import simulate as simulate_module

    def no_run(*args, **kwargs):
        raise AssertionError("the integration ran instead of rejecting the option")

    monkeypatch.setattr(simulate_module, "integrate", no_run)
    error = TypeError if "progress" in options else ValueError
    with pytest.raises(error, match=match):
        rj.simulate(rj.FreeBody(I3), rj.State(W, Q), np.linspace(0.0, 5.0, 11), **options)


class _FitReached(Exception):
    pass


def _stop_at_the_fit(monkeypatch):
    from rigidjax._fit import fit as fit_module

    def reached(*args, **kw):
        raise _FitReached

    monkeypatch.setattr(fit_module, "_run", reached)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"inertia_trace": np.float32(2.5)},
        {"inertia_trace": 3},
        {"known_moment": [np.int64(2), 2.5]},
        {"known_moment": (0, np.float64(1e-3))},
        {"steps": np.int32(5), "tol": 0.0, "f_scale": 0.1, "dtype": "float64"},
        {
            "segments": np.int64(3),
            "omega0_init": np.ones((3, 3)),
            "inertia_init": TENSOR,
            "full_tensor": True,
        },
        {"method": "levenberg-marquardt", "noise": [0.1, 0.2, 0.3]},
        {"segments": 20},
    ],
)
def test_fit_accepts_good_options(kwargs, monkeypatch, without_runtime_typecheck):
    """The option checks let every valid spelling through to the optimiser (stopped there)."""
    _stop_at_the_fit(monkeypatch)
    with pytest.raises(_FitReached):
        rj.fit_inertia(_TS_FIT, _W_FIT, **kwargs)


@settings(max_examples=60, deadline=None)
@given(
    value=st.one_of(st.floats(max_value=0.0), st.sampled_from([nan, inf, -inf])),
    index=st.integers(min_value=-10, max_value=10),
)
def test_fit_scale_options_reject_every_bad_value(value, index):
    """Generated: any non-positive or non-finite scale, any index outside 0..2, is named."""
    with pytest.raises(ValueError, match="inertia_trace must be a positive finite number"):
        rj.fit_inertia(_TS_FIT, _W_FIT, inertia_trace=value)
    with pytest.raises(ValueError, match="known_moment"):
        rj.fit_inertia(_TS_FIT, _W_FIT, known_moment=(index, value))
    if not 0 <= index <= 2:
        with pytest.raises(ValueError, match=f"index {index}, which is out of range"):
            rj.fit_inertia(_TS_FIT, _W_FIT, known_moment=(index, 1.0))


# ----------------------------------------------------------------------------------------------
# Batch shapes: the ambiguous (3, 3) inertia, model/state batches that do not broadcast, and a
# torque that returns the wrong shape -- each named, never a raw broadcasting error or a silent
# broadcast.
# ----------------------------------------------------------------------------------------------

_SPHERES = np.full((3, 3), 0.4)  # three identical spheres' principal moments, read as one tensor


@pytest.mark.parametrize("mode", ["eager", "jit"])
def test_three_spheres_as_a_3x3_array_get_the_batch_hint(mode):
    """``(3, 3)`` principal moments of three identical spheres are a symmetric tensor (eigenvalues
    1.2, 0, 0): the error once said only "non-positive moment ... thin rod"; it now says that the
    shape is read as one tensor and how to pass a batch of three."""
    fn = rj.check_inertia if mode == "eager" else jax.jit(rj.check_inertia)
    with pytest.raises(RUNTIME, match="non-positive") as info:
        jax.block_until_ready(fn(_SPHERES))
    message = str(info.value)
    assert "read as ONE inertia tensor" in message and "batch of three bodies" in message
    assert "moments[..., None] * jnp.eye(3)" in message and "(3, 1, 3)" in message
    assert "thin rod" not in message


@pytest.mark.parametrize(
    ("inertia", "words"),
    [
        (np.diag([1.0, 1.0, -0.5]), ["non-positive", "thin rod"]),
        (np.diag([3.5, 1.0, 2.0]), ["triangle inequality"]),
        (np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), ["not symmetric", "(3, 1, 3)"]),
    ],
    ids=["negative", "triangle", "asymmetric"],
)
def test_a_non_physical_tensor_whose_rows_are_not_moments_gets_no_batch_hint(inertia, words):
    """The hint is for (3, 3) arrays whose rows are valid moments; a plain bad tensor keeps its message."""
    with pytest.raises(RUNTIME) as info:
        rj.check_inertia(inertia)
    message = str(info.value)
    assert all(w in message for w in words) and "read as ONE inertia tensor" not in message


def test_the_suggested_tensor_form_is_the_batch_of_three():
    """The hint's spelling, ``moments[..., None] * eye(3)``, is three diagonal tensors: physical, and
    Euler's equations in tensor form give the principal-form result body by body (the independent
    reference: I1 w1' = (I2 - I3) w2 w3 + tau1, cyclic, written out here)."""
    moments = np.array([[0.4, 0.4, 0.4], [1.0, 2.0, 2.5], [2.0, 2.0, 1.0]])
    tensors = moments[..., None] * np.eye(3)
    assert tensors.shape == (3, 3, 3)
    np.testing.assert_array_equal(rj.check_inertia(tensors), tensors)
    omega = np.array([[0.1, 1.0, 0.2], [0.3, -0.2, 1.1], [1.0, 0.5, -0.4]])
    i1, i2, i3 = moments.T
    w1, w2, w3 = omega.T
    expected = np.stack([(i2 - i3) * w2 * w3 / i1, (i3 - i1) * w3 * w1 / i2, (i1 - i2) * w1 * w2 / i3], -1)
    np.testing.assert_allclose(rj.euler_equations(tensors, omega), expected, rtol=1e-14, atol=1e-15)


@pytest.mark.slow
def test_three_spheres_hint_inside_simulate():
    """The same hint from inside the compiled simulation (the model's run-time check)."""
    with pytest.raises(RUNTIME, match="read as ONE inertia tensor"):
        rj.simulate(rj.FreeBody(_SPHERES), rj.State(np.ones((3, 3))), TS, accuracy="fast")


_QS = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
BATCH_MISMATCH = {
    "inertia-vs-omega": (
        lambda: rj.simulate(rj.FreeBody(np.tile(I3, (2, 1))), rj.State(np.ones((3, 3))), TS),
        [r"model.inertia has shape (2, 3) (batch (2,))", r"state0.omega has shape (3, 3) (batch (3,))"],
    ),
    "omega-vs-orientation": (
        lambda: rj.simulate(rj.FreeBody(I3), rj.State(np.ones((2, 3)), _QS), TS),
        ["state0.omega has shape (2, 3)", "state0.orientation has shape (3, 4) (batch (3,))"],
    ),
    "within-the-model": (
        lambda: rj.simulate(rj.HeavyTop(np.tile(I3, (2, 1)), np.ones(3), COM), rj.State(np.ones(3), Q), TS),
        ["model.inertia has shape (2, 3)", "model.mass has shape (3,) (batch (3,))"],
    ),
    "torque-batch": (
        lambda: rj.simulate(
            rj.RigidBody(I3, torque=rj.ConstantTorque(np.ones((4, 3)))), rj.State(np.ones((2, 3))), TS
        ),
        ["model.torques[0].torque has shape (4, 3) (batch (4,))", "state0.omega has shape (2, 3)"],
    ),
}


@pytest.mark.parametrize("case", list(BATCH_MISMATCH))
def test_mismatched_batch_shapes_name_every_array(case, without_runtime_typecheck):
    """Once a raw ``Incompatible shapes for broadcasting``; now every array with its shape, before
    anything compiles."""
    fn, words = BATCH_MISMATCH[case]
    with pytest.raises(ValueError, match="batch shapes of the model and the state do not broadcast") as info:
        fn()
    for word in words:
        assert word in str(info.value)


def _wrong_torque(shape):
    def wrong_shape_torque(t, state, args):
        return jnp.zeros(shape, state.omega.dtype)

    return rj.RigidBody(I3, torque=rj.Torque(wrong_shape_torque, needs_orientation=False))


@pytest.mark.parametrize("shape", [(2,), (2, 3), (), (1, 3)], ids=str)
def test_torque_of_the_wrong_shape_is_named(shape, without_runtime_typecheck):
    """A user torque must return the one body's (3,) torque. (2,) was a raw broadcasting error;
    a scalar, (1, 3) and (2, 3) were broadcast silently into a different torque or state shape."""
    with pytest.raises(
        ValueError, match=r"torque 0 \(Torque\(.*wrong_shape_torque\)\) returned shape"
    ) as info:
        rj.simulate(_wrong_torque(shape), rj.State(W), TS, accuracy="fast")
    assert f"returned shape {shape}" in str(info.value) and "shape (3,)" in str(info.value)


def _interleaved(w):
    """Each sample observes one component (an interleaving sensor): no complete row anywhere."""
    out = np.full_like(w, nan)
    for i in range(w.shape[0]):
        out[i, i % 3] = w[i, i % 3]
    return out


def _in_turn(w):
    """Each component observed over a third of the record, alone: no two components at once."""
    out = np.full_like(w, nan)
    n = w.shape[0]
    for c in range(3):
        block = slice(c * n // 3, (c + 1) * n // 3)
        out[block, c] = w[block, c]
    return out


_W_NO_Z = with_value(_W_FIT, nan) * np.where(np.arange(3) == 2, nan, 1.0)
ESTIMATE_CASES = {
    # Each returned a made-up inertia (1/3, 1/3, 1/3) silently: there was no equation to solve.
    "estimate-axis-never-observed": (
        lambda: rj.estimate_inertia(_TS_FIT, _W_NO_Z),
        "estimate_inertia: no sample",
    ),
    "estimate-half_width-1": (
        lambda: rj.estimate_inertia(_TS_FIT, _W_FIT, half_width=1),
        "half_width must be",
    ),
    "estimate-half_width-float": (
        lambda: rj.estimate_inertia(_TS_FIT, _W_FIT, half_width=3.0),
        "half_width must be an integer >= 2",
    ),
    "fit-axis-never-observed": (
        lambda: rj.fit_inertia(_TS_FIT, _W_NO_Z),
        r"omega_observed has no finite sample of wz \(column 2\)",
    ),
    "fit-in-turn-without-start": (
        lambda: rj.fit_inertia(_TS_FIT, _in_turn(_W_FIT)),
        "Cannot estimate a starting inertia: .* Give inertia_init",
    ),
}


@pytest.mark.parametrize("case", list(ESTIMATE_CASES))
def test_no_made_up_starting_inertia(case, monkeypatch, without_runtime_typecheck):
    _stop_at_the_fit(monkeypatch)
    fn, match = ESTIMATE_CASES[case]
    with pytest.raises(ValueError, match=match):
        fn()


def test_a_ragged_record_is_named():
    """A nested list with rows of different lengths gave NumPy's "inhomogeneous shape" error
    without the argument's name."""
    with pytest.raises(ValueError, match="omega_observed is a ragged nested list"):
        rj.fit_inertia(_TS_FIT[:2], [[1.0, 2.0, 3.0], [1.0, 2.0]])
    with pytest.raises(ValueError, match="ts is a ragged nested list"):
        rj.estimate_inertia([[0.0, 1.0], [2.0]], np.ones((2, 3)))


def test_an_interleaved_record_is_estimated():
    """A record whose samples each observe one component in turn has local fits of each component
    over its own values (the two nearest on each side), so the torque-free equations hold at every
    row and give a start; it was refused for want of a complete row. Reference: the moments of the
    DOP853 record."""
    moments, _ = rj.estimate_inertia(_TS_FIT, _interleaved(_W_FIT))
    assert np.max(np.abs(np.asarray(moments) - I3 / I3.sum())) < 0.02


def test_interleaved_record_with_a_start_reaches_the_fit(monkeypatch):
    """With inertia_init, a record whose samples each observe one component starts every window from
    observed values (it was a raw IndexError: no complete sample in a window)."""
    _stop_at_the_fit(monkeypatch)
    with pytest.raises(_FitReached):
        rj.fit_inertia(_TS_FIT, _interleaved(_W_FIT), inertia_init=I3, segments=3)


def test_shape_errors_are_the_same_inside_a_users_jit(without_runtime_typecheck):
    """Batch and torque shapes are known while tracing: inside a user's ``jax.jit`` the same
    ValueError comes out, before anything compiles."""

    @jax.jit
    def run(inertia, omega):
        return rj.simulate(rj.FreeBody(inertia), rj.State(omega), TS).omega

    with pytest.raises(ValueError, match=r"model.inertia has shape \(2, 3\) \(batch \(2,\)\)"):
        run(np.tile(I3, (2, 1)), np.ones((3, 3)))

    @jax.jit
    def run_torque(omega):
        return rj.simulate(_wrong_torque(()), rj.State(omega), TS, accuracy="fast").omega

    with pytest.raises(ValueError, match=r"returned shape \(\); a torque returns"):
        run_torque(W)


KNOWN_TORQUE_CASES = {
    # Each was integrated into a NaN loss (or a negative weight) with no error before the fit.
    "constant-nan": (
        lambda: rj.fit_inertia(_TS_FIT, _W_FIT, torque=rj.ConstantTorque(with_value(W, nan))),
        "NaN",
    ),
    "damping-inf": (lambda: rj.fit_inertia(_TS_FIT, _W_FIT, torque=rj.ViscousDamping(inf)), "NaN or inf"),
    "user-params-nan": (
        lambda: rj.fit_inertia(
            _TS_FIT,
            _W_FIT,
            torque=rj.Torque(lambda t, s, p: -p * s.omega, params=jnp.asarray(nan), needs_orientation=False),
        ),
        r"torque \(Torque\) holds NaN or inf",
    ),
    "gravity-negative-mass": (
        lambda: rj.fit_inertia_to_orientation(_TS_FIT, _Q_FIT, torque=rj.GravityTorque(-1.0, COM)),
        r"torque \(GravityTorque\): mass must be positive \(kg\)",
    ),
    "gravity-nan-com": (
        lambda: rj.fit_inertia_to_orientation(
            _TS_FIT, _Q_FIT, torque=rj.GravityTorque(1.0, with_value(COM, nan))
        ),
        r"torque \(GravityTorque\) holds NaN or inf",
    ),
}


@pytest.mark.parametrize("case", list(KNOWN_TORQUE_CASES))
def test_fit_rejects_a_non_finite_known_torque(case, monkeypatch, without_runtime_typecheck):
    _stop_at_the_fit(monkeypatch)
    fn, match = KNOWN_TORQUE_CASES[case]
    with pytest.raises(ValueError, match=match):
        fn()


_TS_LONG = np.linspace(0.0, 20.0, 81)
_W_LONG, _Q_LONG = dop853_free_body(I3, W, _TS_LONG, np.array([1.0, 0.0, 0.0, 0.0]))


@settings(max_examples=30, deadline=None)
@example(T=0, seed=0, density=0.0, segments="auto", full_tensor=False, orientation=False)  # IndexError
@example(T=1, seed=0, density=0.0, segments="auto", full_tensor=False, orientation=True)  # NaN -> int
@given(
    T=st.integers(0, 81),
    seed=st.integers(0, 2**16),
    density=st.sampled_from([0.0, 0.3, 0.7, 0.95, 1.0]),
    segments=st.one_of(st.integers(-1, 45), st.just("auto")),
    full_tensor=st.booleans(),
    orientation=st.booleans(),
)
def test_any_record_is_named_or_fitted(T, seed, density, segments, full_tensor, orientation):
    """Generated records (any length, any fraction of missing samples, any number of windows): the
    fit either names the problem (ValueError/TypeError) or reaches the optimiser -- never a raw
    IndexError, ZeroDivisionError or LinAlgError from the preparation. (segments='auto' on an empty
    or one-sample record was a raw IndexError / 'cannot convert float NaN to integer'.)"""
    drop = np.random.default_rng(seed).random((81, 3)) < density
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # numpy's 'mean of empty slice'
            with pytest.MonkeyPatch.context() as patch:
                _stop_at_the_fit(patch)
                if orientation:
                    q = np.where(drop[:T, :1], nan, _Q_LONG[:T])
                    rj.fit_inertia_to_orientation(_TS_LONG[:T], q, segments=segments, full_tensor=full_tensor)
                else:
                    w = np.where(drop[:T], nan, _W_LONG[:T])
                    rj.fit_inertia(_TS_LONG[:T], w, segments=segments, full_tensor=full_tensor)
    except (ValueError, TypeError, _FitReached):
        pass


@pytest.mark.parametrize("accuracy", ["fast", "exact"])
@pytest.mark.parametrize(
    "name, value", [("chunk_size", 0), ("chunk_size", 2.5), ("chunk_size", True), ("max_steps", -3)]
)
def test_simulate_names_a_bad_chunk_size_or_step_limit(accuracy, name, value, without_runtime_typecheck):
    """Checked before anything is compiled, for the integrators and the closed forms alike (with the
    test run's annotation checks off: a user's call gets this error, not a type-check error)."""
    message = rf"simulate: {name} must be a positive integer or None, got {value!r}"
    with pytest.raises(ValueError, match=message):
        rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS, accuracy=accuracy, **{name: value})


@pytest.mark.parametrize(
    "options, match",
    [
        ({"rtol": -1e-6}, r"rtol must be a number in \[0, 1\).*got -1e-06"),
        ({"rtol": float("nan")}, r"rtol must be a number in \[0, 1\).*got nan"),
        ({"rtol": float("inf")}, r"rtol must be a number in \[0, 1\).*got inf"),
        ({"rtol": 2.0}, r"rtol must be a number in \[0, 1\).*got 2.0"),
        ({"rtol": 1e-6, "atol": -1e-9}, r"atol must be a number in \[0, 1\).*got -1e-09"),
        ({"rtol": 0.0}, r"rtol and atol must not both be below float64's roundoff unit.*rtol=0.0, atol=0.0"),
        (
            {"rtol": 1e-20, "atol": 0.0},
            r"rtol and atol must not both be below float64's roundoff unit.*1e-20",
        ),
        ({"rtol": np.array([1e-6, 1e-7])}, r"rtol must be a single number, got shape \(2,\)"),
    ],
)
def test_simulate_names_a_bad_tolerance(options, match, without_runtime_typecheck):
    """Tolerances that no step can meet, or that accept any step, were run (a negative or infinite
    rtol "succeeded"; rtol = 0 failed as if the state had turned NaN): a ValueError names them before
    anything is compiled."""
    with pytest.raises(ValueError, match="simulate: " + match):
        rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS, accuracy="fast", **options)


def test_a_bad_tolerance_under_jit_is_a_run_time_error(without_runtime_typecheck):
    """Inside the user's jit the tolerance is a tracer: the check is in the program. A valid traced
    tolerance gives the run at that tolerance given as a number."""

    def run(rtol):
        return rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS, accuracy="fast", rtol=rtol).omega

    run = jax.jit(run)
    np.testing.assert_allclose(
        np.asarray(run(1e-7)),
        np.asarray(rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS, accuracy="fast", rtol=1e-7).omega),
        rtol=0,
        atol=1e-13,
    )
    with pytest.raises(RUNTIME, match=r"rtol and atol each must be a number in \[0, 1\)"):
        jax.block_until_ready(run(-1e-7))


@pytest.mark.parametrize(
    "name, value",
    [
        ("solver", diffrax.Tsit5()),
        ("rtol", 1e-6),
        ("atol", 1e-6),
        ("stepsize_controller", diffrax.PIDController(rtol=1e-6, atol=1e-6)),
        ("dt0", 0.1),
        ("adjoint", diffrax.ForwardMode()),
        ("representation", "euler"),
    ],
)
def test_exact_names_an_integrator_option_instead_of_ignoring_it(name, value, without_runtime_typecheck):
    """The closed form integrates nothing: an integrator's option given with accuracy='exact' was
    silently unused (a solver asked for was not the one that ran)."""
    message = rf"accuracy='exact' is a closed form, no integration: {name} does not apply"
    with pytest.raises(ValueError, match=message):
        rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS, accuracy="exact", **{name: value})


def test_tolerances_beside_a_step_size_controller_are_an_error(without_runtime_typecheck):
    """rtol and atol configure the preset's controller: beside the user's own they were ignored."""
    controller = diffrax.PIDController(rtol=1e-3, atol=1e-3)
    message = r"with stepsize_controller given, set the tolerances on it.*rtol=1e-12"
    with pytest.raises(ValueError, match=message):
        rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS, rtol=1e-12, stepsize_controller=controller)


@pytest.mark.parametrize(
    "options, error, match",
    [
        # A string is truthy: "no" ran with throw=True, and sort_by_speed="no" sorted the bodies.
        ({"throw": "no"}, TypeError, "throw must be True or False, got 'no'"),
        ({"sort_by_speed": "no"}, TypeError, "sort_by_speed must be True or False, got 'no'"),
        ({"error_estimate": 1}, TypeError, "error_estimate must be True or False, got 1"),
        # A string failed with an AttributeError deep in diffrax, a class with a functools error.
        ({"solver": "Tsit5"}, TypeError, "solver must be a diffrax solver .*got str 'Tsit5'"),
        ({"solver": diffrax.Tsit5}, TypeError, r"solver must be .*the class Tsit5 itself .*Tsit5\(...\)"),
        ({"stepsize_controller": 1e-3}, TypeError, "stepsize_controller must be a diffrax step-size"),
        ({"adjoint": "forward"}, TypeError, "adjoint must be a diffrax adjoint"),
        # dt0 <= 0 or NaN failed as a state that had turned NaN, or after max_steps.
        ({"dt0": -0.1}, ValueError, "dt0 must be a positive finite step .*got -0.1"),
        ({"dt0": 0.0}, ValueError, "dt0 must be a positive finite step .*got 0.0"),
        ({"dt0": float("nan")}, ValueError, "dt0 must be a positive finite step .*got nan"),
        ({"dt0": np.array([0.1, 0.2])}, ValueError, r"dt0 must be a single step \(s\), got shape \(2,\)"),
        # A negative or NaN margin failed as a NaN state; 2 as "within 2 of gimbal lock".
        ({"lock_tolerance": -1.0}, ValueError, r"lock_tolerance must be a number in \(0, 1\).*got -1.0"),
        ({"lock_tolerance": 2.0}, ValueError, r"lock_tolerance must be a number in \(0, 1\).*got 2.0"),
        ({"lock_tolerance": float("nan")}, ValueError, r"lock_tolerance must be a number in \(0, 1\)"),
        ({"lock_tolerance": "small"}, TypeError, r"lock_tolerance must be a number in \(0, 1\)"),
    ],
)
def test_simulate_names_a_bad_option(options, error, match, without_runtime_typecheck):
    """Options of the wrong kind or value are named before anything is compiled, instead of being
    read as something else or failing as the integration's fault."""
    representation = {"representation": "euler"} if "lock_tolerance" in options else {}
    with pytest.raises(error, match="simulate: " + match):
        rj.simulate(rj.FreeBody(I3), rj.State(W, Q), TS, accuracy="fast", **representation, **options)


@pytest.mark.parametrize("accuracy", ["fast", "exact"])
def test_an_empty_batch_of_bodies_is_named(accuracy):
    """Zero bodies failed with a ZeroDivisionError in the chunking."""
    model, state = rj.FreeBody(np.ones((0, 3)) * I3), rj.State(np.ones((0, 3)), None)
    with pytest.raises(ValueError, match=r"simulate: the batch of bodies is empty \(batch shape \(0,\)"):
        rj.simulate(model, state, TS, accuracy=accuracy)


@pytest.mark.parametrize("scene", ["free body", "heavy top"])
def test_a_closed_form_beyond_the_float_range_is_a_failure_not_a_success(scene):
    """An angular velocity of 1e160 rad/s passes the input checks (finite), but the closed form's
    angular momentum squared overflows: it was NaN with success True. Now the body fails: an error
    naming it and the first sample time, under jit too; with throw=False success and
    first_failed_sample agree with NumPy's isfinite of the samples, and the other bodies keep their
    values (those of a call without the failed body)."""
    ts = np.linspace(0.0, 1.0, 4)
    omega = np.array([[0.1, 0.3, 8.0], [0.1, 1e160, 0.2], [0.2, -0.1, 6.0]])
    q0 = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    if scene == "free body":
        model = rj.FreeBody(np.array([1.0, 2.0, 2.5]))
    else:
        model = rj.HeavyTop(np.array([1.0, 1.0, 0.5]), 1.0, np.array([0.0, 0.0, 0.3]))
    with pytest.raises(
        ValueError, match=r"closed form of body 1 is NaN or inf at t = 0 s: its inputs are beyond"
    ):
        rj.simulate(model, rj.State(omega, q0), ts, accuracy="exact")
    traj = rj.simulate(model, rj.State(omega, q0), ts, accuracy="exact", throw=False)
    finite = np.isfinite(np.asarray(traj.omega)).all(-1) & np.isfinite(np.asarray(traj.orientation)).all(-1)
    assert not finite[1].all() and finite[[0, 2]].all()
    np.testing.assert_array_equal(np.asarray(traj.success), finite.all(-1))
    np.testing.assert_array_equal(np.asarray(traj.stats["first_failed_sample"]), [4, np.argmin(finite[1]), 4])
    assert np.isnan(np.asarray(traj.omega)[1, np.argmin(finite[1]) :]).all()
    # Without the failed body: body 0 in its place keeps the batch's shape (the eager call's program
    # serves it; two bodies compiled another, 15 s).
    alone = rj.simulate(model, rj.State(omega[[0, 0, 2]], q0[[0, 0, 2]]), ts, accuracy="exact")
    np.testing.assert_array_equal(np.asarray(traj.omega)[[0, 2]], np.asarray(alone.omega)[[0, 2]])
    jitted = jax.jit(lambda w: rj.simulate(model, rj.State(w, jnp.asarray(q0)), ts, accuracy="exact").omega)
    with pytest.raises(Exception, match="closed form of a body is NaN or inf"):
        jitted(jnp.asarray(omega)).block_until_ready()
    np.testing.assert_array_equal(
        np.asarray(jitted(jnp.asarray(omega[[0, 0, 2]])))[2], np.asarray(alone.omega)[2]
    )


@pytest.mark.parametrize("function", ["torque_free_omega", "torque_free_motion", "torque_free_period"])
def test_the_closed_forms_name_an_angular_momentum_beyond_the_float_range(function):
    """Finite inputs whose |I omega|^2 overflows float64 gave NaN without an error. The closed forms
    compute with the moments scaled so that the largest is in [1/2, 1) (0.625 here), whose |I omega| is
    6.5e154 at omega = 1e155 (beyond); two powers of ten less (|L|^2 = 1.1e306 unscaled, finite) is
    evaluated, ~1e3 rad of motion at t = 1e-150 s: finite, with |I omega|^2 conserved to rounding."""
    inertia, direction = np.array([1.0, 2.0, 2.5]), np.array([0.1, 1.0, 0.2])
    q0, t = np.array([1.0, 0.0, 0.0, 0.0]), np.array([1e-150])
    calls = {
        "torque_free_omega": lambda w: rj.torque_free_omega(inertia, w, t),
        "torque_free_motion": lambda w: rj.torque_free_motion(inertia, w, q0, t),
        "torque_free_period": lambda w: rj.torque_free_period(inertia, w),
    }
    with pytest.raises(ValueError, match=rf"{function}: the angular momentum .* beyond the range of float64"):
        calls[function](direction * 1e155)
    within = [np.asarray(x) for x in jax.tree.leaves(calls[function](direction * 1e153))]
    assert all(np.isfinite(x).all() for x in within)
    if function != "torque_free_period":
        momentum2 = np.sum((inertia * within[0]) ** 2, axis=-1)
        np.testing.assert_allclose(momentum2, np.sum((inertia * direction * 1e153) ** 2), rtol=1e-12)
    jitted = jax.jit(calls[function])
    with pytest.raises(Exception, match="the angular momentum of inertia and omega0 is beyond the range"):
        jax.block_until_ready(jitted(jnp.asarray(direction * 1e155)))


def _elliptic_rate(inertia, omega):
    """|d tau / dt| of the torque-free body's Jacobi functions from Landau & Lifshitz section 37's
    formula (sorted moments, L^2 and 2E from the inputs), the rate of the closed form's phase."""
    order = np.argsort(inertia)
    i1, i2, i3 = inertia[order]
    w = omega[order]
    momentum2, energy2 = np.sum((inertia[order] * w) ** 2), np.sum(inertia[order] * w * w)
    if momentum2 > energy2 * i2:
        return np.sqrt((i3 - i2) * (momentum2 - energy2 * i1) / (i1 * i2 * i3))
    return np.sqrt((i2 - i1) * (energy2 * i3 - momentum2) / (i1 * i2 * i3))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_closed_forms_refuse_a_phase_beyond_what_the_dtype_resolves(dtype, extreme):
    """The closed forms' absolute error grows as eps x phase (float32 against float64, 1 rad/s:
    5e-8 at 10 s, 2e-3 at 1e5 s); at t = 1e16 s in float64 the results were noise and at 1e18 s the
    quaternion had a norm of 3e6, all without an error. Now a phase whose rounding exceeds 1e-3 rad
    is an error naming the sample: the elliptic argument's rate from Landau & Lifshitz's formula puts
    the limit of omega alone at t = 1e-3 / (eps lambda): 1 % below it the value is kept (in float32
    within 2e-3 of float64's), 1 % above it is refused, also under jit. A steady rotation's omega has
    no phase (it is omega0 at any t); its orientation has one. Inputs that are constants of the
    user's jit are checked at run time too."""
    inertia, omega = np.array([1.0, 2.0, 3.0]), np.array([1.0, 0.5, 0.2])
    q0 = np.array([1.0, 0.0, 0.0, 0.0], dtype)
    limit = 1e-3 / (np.finfo(dtype).eps * _elliptic_rate(inertia, omega))
    inertia, omega = inertia.astype(dtype), omega.astype(dtype)
    inside, beyond = np.array([0.0, 0.99 * limit], dtype), np.array([1.0, 1.01 * limit], dtype)
    kept = rj.torque_free_omega(inertia, omega, inside)
    assert kept.dtype == dtype
    if dtype == np.float32:
        reference = rj.torque_free_omega(
            inertia.astype(np.float64), omega.astype(np.float64), inside.astype(np.float64)
        )
        error = np.max(np.abs(np.asarray(kept) - np.asarray(reference)))
        assert error <= 2e-3
        extreme(
            "long horizon",
            f"closed form in float32 at 99 % of its phase limit (t = {float(inside[1]):.3g} s at 0.65 rad/s)",
            "evaluated (1 % further: ValueError naming the sample); omega error against float64",
            error,
            2e-3,
            "float64 (limit 4.5e12 rad) or restart from a later state",
        )
    name = np.dtype(dtype).name
    for function, call in [
        ("torque_free_omega", lambda t: rj.torque_free_omega(inertia, omega, t)),
        ("torque_free_motion", lambda t: rj.torque_free_motion(inertia, omega, q0, t)),
    ]:
        message = re.escape(
            f"{function}: at t = {float(beyond[1]):.6g} s (element (1,) of the broadcast batch) the "
        )
        with pytest.raises(ValueError, match=message + rf"closed form's phase is .* which {name} holds only"):
            call(beyond)
        with pytest.raises(RUNTIME, match=rf"{function}: a phase of the closed form is beyond what {name}"):
            jax.block_until_ready(jax.jit(call)(jnp.asarray(beyond)))
        with pytest.raises(RUNTIME, match=rf"{function}: a phase of the closed form is beyond what {name}"):
            jax.block_until_ready(jax.jit(lambda call=call: call(beyond))())  # constants of the jit
    steady = np.array([0.0, 0.0, 1.0], dtype)
    np.testing.assert_array_equal(np.asarray(rj.torque_free_omega(inertia, steady, beyond))[1], steady)
    # The steady body's bad time sits in the shape of `beyond` (element 1, after t = 1 s): the motion
    # programs compiled above serve it (a scalar t compiled both again, ~3 s).
    with pytest.raises(ValueError, match="torque_free_motion: at t = "):
        rj.torque_free_motion(inertia, steady, q0, np.array([1.0, 4e-3 / np.finfo(dtype).eps], dtype))


@pytest.mark.parametrize("scene", ["free body", "heavy top"])
def test_simulate_exact_fails_a_body_whose_phase_is_beyond_what_the_dtype_resolves(scene):
    """A body spinning at 1e3 rad/s over 1e10 s (a phase of ~1e13 rad: float64 holds it to more
    than 1e-3 rad) was evaluated with success True. Now it fails: an error naming it and the sample
    time, under jit too; with throw=False the other bodies keep their values (those of a call
    without it)."""
    ts = np.array([0.0, 1.0, 1e6, 1e10])
    omega = np.array([[1e-6, 2e-6, 1e-5], [0.1, 1e3, 0.2], [2e-6, -1e-6, 1e-5]])
    q0 = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    if scene == "free body":
        model = rj.FreeBody(np.array([1.0, 2.0, 2.5]))
    else:
        model = rj.HeavyTop(np.array([1.0, 1.0, 0.5]), 1.0, np.array([0.0, 0.0, 0.3]))
    with pytest.raises(ValueError, match=r"at t = 1e\+10 s for body 1, the closed form's phase is beyond"):
        rj.simulate(model, rj.State(omega, q0), ts, accuracy="exact")
    traj = rj.simulate(model, rj.State(omega, q0), ts, accuracy="exact", throw=False)
    np.testing.assert_array_equal(np.asarray(traj.success), [True, False, True])
    np.testing.assert_array_equal(np.asarray(traj.stats["first_failed_sample"]), [4, 3, 4])
    # Its samples from the failed one on are NaN, as an integrated body's (they held the noise
    # evaluated there), those before it finite.
    for values in (
        np.asarray(traj.omega)[1],
        np.asarray(traj.orientation)[1],
        np.asarray(traj.euler_angles())[1],
    ):
        assert np.isfinite(values[:3]).all() and np.isnan(values[3:]).all()  # Euler angles were (nan, 0, 0)
    if scene == "free body":  # and under the user's jit
        run = jax.jit(lambda w: rj.simulate(model, rj.State(w, q0), ts, accuracy="exact", throw=False).omega)
        np.testing.assert_array_equal(np.asarray(run(jnp.asarray(omega))), np.asarray(traj.omega))
    # Without the failed body: body 0 in its place keeps the batch's shape (one program less).
    alone = rj.simulate(model, rj.State(omega[[0, 0, 2]], q0[[0, 0, 2]]), ts, accuracy="exact")
    np.testing.assert_array_equal(np.asarray(traj.omega)[[0, 2]], np.asarray(alone.omega)[[0, 2]])
    jitted = jax.jit(lambda w: rj.simulate(model, rj.State(w, jnp.asarray(q0)), ts, accuracy="exact").omega)
    with pytest.raises(Exception, match="NaN or inf, or its phase is beyond what float64 resolves"):
        jitted(jnp.asarray(omega)).block_until_ready()


def test_a_span_too_long_for_the_step_floor_names_the_closed_form():
    """A tumbling body over 1e12 s (3e11 turns) needs steps below the floor that stops a NaN body
    early (1e-12 of the span): the error said only that the state or torque had turned NaN. On the
    default step limit the span is refused before any step (a span of 1e15 s once ran for hours,
    up to the limit of 2^30 steps); with a limit given, the run stops at the floor."""
    model, state, ts = rj.FreeBody(I3), rj.State(W, None), np.array([0.0, 1e12])
    turns = np.linalg.norm(W) * 1e12 / (2 * np.pi)
    with pytest.raises(
        ValueError, match=rf"ts spans {re.escape(f'{turns:.3g}')} turns.*accuracy='exact'.*max_steps"
    ):
        rj.simulate(model, state, ts, accuracy="fast")
    with pytest.raises(RUNTIME, match=r"step size collapsed.*more turns than steps of that size.*'exact'"):
        rj.simulate(model, state, ts, accuracy="fast", max_steps=100_000)


def test_flags_that_are_not_bools_and_unused_sequences_are_refused(without_runtime_typecheck):
    """euler_rates read throw=None or 0 as False and throw="no" as True; check_inertia read
    tensor="no" as True; Torque kept needs_orientation="no" (truthy); simulate accepted
    euler_seq="zzz" unless the Euler-angle state read it. Each is now named; bools (NumPy's too)
    and the sequences in any case still pass."""
    angles, rates = jnp.array([0.3, 1.1, -0.7]), jnp.array([0.1, 0.2, 0.3])
    for throw in (None, 0, "no"):
        with pytest.raises(TypeError, match=rf"euler_rates: throw must be True or False, got {throw!r}"):
            rj.euler_rates(angles, rates, throw=throw)
    np.testing.assert_array_equal(
        rj.euler_rates(angles, rates, throw=np.bool_(False)), rj.euler_rates(angles, rates, throw=True)
    )
    with pytest.raises(TypeError, match="check_inertia: tensor must be True, False or None, got 'no'"):
        rj.check_inertia(jnp.eye(3), tensor="no")
    with pytest.raises(TypeError, match="Torque: needs_orientation must be True or False, got 'no'"):
        rj.Torque(lambda t, state, args: jnp.zeros(3), needs_orientation="no")
    with pytest.raises(ValueError, match="simulate: euler_seq: seq must be one of the twelve"):
        rj.simulate(rj.FreeBody(I3), rj.State(W), np.array([0.0, 1.0]), euler_seq="zzz")


def test_times_far_from_zero_for_their_dtype_are_named_as_the_cause():
    """float32 sample times at 3e5 s are 0.031 s apart at best: the solver's shorter steps did not
    advance t, the run used up max_steps and the error asked for more of them "between t = 300000 s
    and t = 300000 s". Now it names the times' resolution and the remedies; the same scene from
    t = 0 succeeds."""
    f32 = np.float32
    model, state = rj.FreeBody(f32([1.0, 2.0, 3.0])), rj.State(f32([0.1, 1.0, 0.05]), f32([1, 0, 0, 0]))
    ts = np.linspace(0.0, 5.0, 11, dtype=f32)
    assert bool(rj.simulate(model, state, ts).success)
    with pytest.raises(
        RUNTIME,
        match=r"between t = 300000 s and t = 300000\.5 s.*float32: .* resolves only 0\.031 s.*ts - ts\[0\]",
    ):
        rj.simulate(model, state, f32(3e5) + ts)


def test_a_span_of_ten_million_turns_is_the_most_the_default_step_limit_takes():
    """The refusal sits at 2^30 / 100 turns of the fastest body (100 steps per turn, the default
    limit's budget): just below it, the limit is 2^30 (checked without running)."""
    from rigidjax._integrate.presets import LARGEST_DEFAULT_MAX_STEPS, STEPS_PER_TURN, default_max_steps

    omega0 = np.array([[0.0, 0.0, 2 * np.pi], [0.0, 1.0, 0.0]])  # the fastest: one turn per second
    most = LARGEST_DEFAULT_MAX_STEPS / STEPS_PER_TURN
    assert default_max_steps(omega0, np.array([0.0, 0.999 * most])) == 2**30
    with pytest.raises(ValueError, match="more than an integrator steps through"):
        default_max_steps(omega0, np.array([0.0, 1.001 * most]))


def test_an_angular_velocity_whose_square_overflows_is_named_by_its_turns():
    """|omega0| = 1.7e200 rad/s: NumPy's norm of it overflowed (a RuntimeWarning), the span check saw
    an infinite speed and passed, and the integration failed at its first step."""
    state = rj.State(jnp.full(3, 1e200), jnp.array([1.0, 0.0, 0.0, 0.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=r"ts spans 2.76e\+199 turns .*\|omega0\| = 1.73e\+200 rad/s"):
            rj.simulate(rj.FreeBody(I3), state, jnp.linspace(0.0, 1.0, 5))


def test_the_default_step_limit_covers_a_step_per_sample_time():
    """ "precise" ends a step on every sample time: a slow body (0.37 rad/s) sampled 150,001 times
    over 10 s needs 150,000 steps, and stopped at the limit of 10^5 (checked without running; the
    run itself takes ~40 s: 150,000 steps, success)."""
    from rigidjax._integrate.presets import default_max_steps

    omega0 = np.array([0.1, 0.2, 0.3])
    assert default_max_steps(omega0, np.linspace(0.0, 10.0, 150_001)) >= 150_000 + 100 * 0.6
    assert default_max_steps(omega0, np.linspace(0.0, 10.0, 1_001)) == 100_000


def test_nan_in_the_params_of_a_torque_function_is_named_also_under_jit():
    """NaN in ``Torque(fn, params=...)`` ran and failed with a step size that collapsed at t = 0."""
    message = r"simulate: model field 'torques\[0\].params' contains NaN or inf"

    # One torque function for every call: a lambda made inside final_omega was a new static part of
    # the model each call, and each eager call compiled simulate's input checks again.
    def damping(t, s, p):
        return -p["k"] * s.omega

    def final_omega(k):
        torque = rj.Torque(damping, params={"k": k}, needs_orientation=False)
        return rj.simulate(rj.RigidBody(I3, torque), rj.State(W, None), TS, accuracy="fast").omega[-1]

    with pytest.raises(ValueError, match=message):
        final_omega(np.nan)  # a Python float
    with pytest.raises(ValueError, match=message):
        final_omega(jnp.array(jnp.inf))
    with pytest.raises(RUNTIME, match=message):
        jax.block_until_ready(jax.jit(final_omega)(jnp.array(jnp.nan)))
    # finite parameters run: the torque -k omega takes energy out (dE/dt = -k |omega|^2)
    slowed = np.asarray(final_omega(jnp.array(0.1)))
    assert np.sum(I3 * slowed**2) < np.exp(-0.1 / I3.max()) * np.sum(I3 * W**2)


@pytest.mark.parametrize("shape", [(2,), (4,), (5, 2)])
def test_a_damping_coefficient_of_an_undocumented_shape_is_named(shape):
    """A trailing axis other than 1 or 3 was read as a batch of per-body scalars (2 bodies from
    shape (2,)), while (3,) is per body axis: N bodies' coefficients meant either, depending on N."""
    with pytest.raises(ValueError, match=r"ViscousDamping.coefficient must be .*use shape \(N, 1\)"):
        rj.ViscousDamping(np.full(shape, 0.1))


def test_a_negative_damping_coefficient_is_named_also_under_jit():
    """A negative coefficient ran and pumped energy in under the name of damping."""
    message = r"'torques\[0\].coefficient' must be non-negative \(N m s\)"

    def final_omega(c):
        model = rj.RigidBody(I3, rj.ViscousDamping(c))
        return rj.simulate(model, rj.State(W, None), TS, accuracy="fast").omega[..., -1, :]

    with pytest.raises(ValueError, match="simulate: model field " + message):
        final_omega(np.array([[0.1], [-0.1]]))
    with pytest.raises(RUNTIME, match=message):
        jax.block_until_ready(jax.jit(final_omega)(-0.1))
    # The accepted shapes keep their meaning: per body axis, and per body (N, 1).
    per_axis = final_omega(np.array([0.1, 0.2, 0.3]))
    per_body = final_omega(np.array([[0.1], [0.2]]))
    assert per_axis.shape == (3,) and per_body.shape == (2, 3)
    with pytest.raises(ValueError, match=r"torque \(ViscousDamping\): coefficient must be non-negative"):
        rj.fit_inertia(TS, np.ones((TS.shape[0], 3)), torque=rj.ViscousDamping(-0.1))


@pytest.mark.parametrize("fn", [lambda t: np.zeros(3), lambda t, state: np.zeros(3), 3.0])
def test_a_torque_function_of_the_wrong_arity_is_named(fn, without_runtime_typecheck):
    """fn(t) failed inside the integration with Python's own 'takes 1 positional argument but 3 were
    given', which names neither the torque nor the arguments it is called with."""
    message = r"Torque: fn must be callable as fn\(t, state, args\) \(three arguments"
    with pytest.raises(TypeError, match=message):
        rj.Torque(fn)
    if callable(fn):
        with pytest.raises(TypeError, match=message):
            rj.RigidBody(I3, fn)
    # Defaults, *args and callables without a readable signature stay accepted.
    rj.Torque(lambda t, state, args=None, scale=1.0: np.zeros(3))
    rj.Torque(lambda *a: np.zeros(3))


def test_the_closed_forms_read_a_trailing_3_by_3_as_three_bodies_moments():
    """A diagonal tensor passed as inertia ran as three 'bodies' of moments (1, 0, 0), ... with no
    error, each returning omega0 unchanged (a steady rotation): the physicality check read the
    (3, 3) as one tensor, the closed form as three bodies' principal moments."""
    moments = np.array([1.0, 2.0, 3.0])
    message = r"torque_free_omega: inertia \(principal moments .*three bodies' moments.* non-positive"
    with pytest.raises(ValueError, match=message):
        rj.torque_free_omega(np.diag(moments), W, 1.0)
    with pytest.raises(ValueError, match="torque_free_period: inertia .* non-positive"):
        rj.torque_free_period(np.diag(moments), W)
    # Three bodies' moments in a (3, 3) array keep working, each row its own body (reference: the
    # same body alone; Euler's equations are invariant under a common scale of the moments).
    rows = np.stack([moments, 2 * moments, moments[::-1]])
    alone = [np.asarray(rj.torque_free_omega(row, W, 1.0)) for row in rows]
    np.testing.assert_allclose(np.asarray(rj.torque_free_omega(rows, W, 1.0)), np.stack(alone), atol=1e-15)


def test_torque_free_motion_wants_a_unit_quaternion_like_simulate():
    """A q0 of norm 2 returned a 'unit quaternion' q(t) of norm 2."""
    q0 = np.array([2.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"torque_free_motion: q0 is not a unit quaternion"):
        rj.torque_free_motion(I3, W, q0, 1.0)
    with pytest.raises(RUNTIME, match=r"q0 is not a unit quaternion"):
        jax.block_until_ready(jax.jit(rj.torque_free_motion)(I3, W, q0, 1.0))


def _composite_by_hand(masses, coms, moments, rotations):
    """Mass, centre of mass and inertia of one body of parts, in NumPy from the definitions."""
    mass = masses.sum()
    com = (masses[:, None] * coms).sum(0) / mass
    inertia = np.zeros((3, 3))
    for m, c, i, r in zip(masses, coms, moments, rotations, strict=True):
        d = c - com
        inertia += r @ np.diag(i) @ r.T + m * (d @ d * np.eye(3) - np.outer(d, d))
    return mass, com, inertia


def test_composite_inertia_broadcasts_batch_axes_after_the_parts_axis(without_runtime_typecheck):
    """Arguments with fewer batch axes were broadcast from the right, lining a batch axis up with
    the parts axis: masses (2,) with coms (2, 2, 3) gave a centre of mass of 0.25 for a body whose
    is 0.75, silently; with unequal sizes a raw broadcasting error named no argument."""
    rng = np.random.default_rng(7)
    masses = np.array([1.0, 3.0])  # (P,): shared by the batch
    coms = rng.normal(size=(2, 4, 3))  # (P, B, 3)
    moments = rng.uniform(1.0, 2.0, size=(2, 3))  # (P, 3): shared
    angles = rng.uniform(0.0, 1.0, size=(2, 4, 3))
    rotations = np.asarray(rj.matrix_from_euler(angles))  # (P, B, 3, 3)
    total, com, inertia = (np.asarray(x) for x in rj.composite_inertia(masses, coms, moments, rotations))
    assert total.shape == (4,) and com.shape == (4, 3) and inertia.shape == (4, 3, 3)
    for b in range(4):
        mass_b, com_b, inertia_b = _composite_by_hand(masses, coms[:, b], moments, rotations[:, b])
        np.testing.assert_allclose(total[b], mass_b, rtol=1e-14)
        np.testing.assert_allclose(com[b], com_b, rtol=0, atol=1e-14)
        np.testing.assert_allclose(inertia[b], inertia_b, rtol=0, atol=1e-13)
    message = r"composite_inertia: the batch axes .* do not broadcast: masses \(2, 4\) \(batch \(4,\)\), coms"
    with pytest.raises(ValueError, match=message):
        rj.composite_inertia(np.ones((2, 4)), np.zeros((2, 5, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError, match=r"rotations must have the parts axis first, with 2 parts"):
        rj.composite_inertia(np.ones(2), np.zeros((2, 3)), np.ones((2, 3)), np.ones((3, 3, 3)))
    with pytest.raises(ValueError, match=r"inertias must have the parts axis first.*got shape \(3,\)"):
        rj.composite_inertia(np.ones(1), np.zeros((1, 3)), np.ones(3))


@pytest.mark.parametrize(
    "moments, speed",
    [
        ([8.008e37, 8.008e37, 8.034e37], 7.29e-5),  # the Earth
        ([1e20, 2e20, 2.5e20], 1.0),
        ([4e-33, 5e-33, 6e-33], 1.0),  # a nanoparticle
        ([1.0, 2.0, 2.5], 1e-30),
    ],
)
def test_spin_stability_in_float32_at_extreme_scales(moments, speed):
    """Products of two moments overflowed (or underflowed) float32: the Earth's spin axis came out
    unstable with frequency 0, and for (1e20, 2e20, 2.5e20) every axis unstable with growth 0.
    Reference: lambda^2 = Omega^2 (I_i - I_j)(I_k - I_i) / (I_j I_k) in NumPy float64."""
    I = np.array(moments)
    I_j, I_k = np.roll(I, -1), np.roll(I, -2)
    lam2 = speed**2 * (I - I_j) * (I_k - I) / (I_j * I_k)
    out = rj.spin_stability(jnp.asarray(I, jnp.float32), jnp.float32(speed))
    np.testing.assert_array_equal(np.asarray(out.stable), lam2 < 0)
    np.testing.assert_array_equal(np.asarray(out.unstable), lam2 > 0)
    np.testing.assert_allclose(np.asarray(out.frequency), np.sqrt(np.maximum(-lam2, 0)), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(out.growth_rate), np.sqrt(np.maximum(lam2, 0)), rtol=1e-5)


@pytest.mark.parametrize(
    "value, error, match",
    [
        # NaN switched both symmetry checks off; -1 rejected every top "to a relative -1"; text
        # failed inside with a sequence error.
        (float("nan"), ValueError, r"must be a number in \[0, 1\), got nan"),
        (-1.0, ValueError, r"must be a number in \[0, 1\), got -1.0"),
        ("0.01", TypeError, "must be a number"),
    ],
)
def test_sleeping_top_names_a_bad_symmetry_tolerance(value, error, match, without_runtime_typecheck):
    """An asymmetric, off-axis top got a result with symmetry_rtol=nan."""
    top = (np.array([1.0, 1.5, 0.7]), 1.0, np.array([1.0, 0.0, 0.3]), 5.0)
    with pytest.raises(error, match="sleeping_top: symmetry_rtol " + match):
        rj.sleeping_top(*top, symmetry_rtol=value)


def test_records_without_rotation_or_a_difference_are_named():
    """A body at rest failed with NumPy's 'SVD did not converge'; one orientation sample gave an
    angular velocity of [nan, inf, nan]; tol >= 1 stopped at the start and said converged."""
    ts = np.linspace(0.0, 10.0, 200)
    message = r"the record shows no rotation \(its angular velocity is 0 at every sample\)"
    with pytest.raises(ValueError, match=message):
        rj.fit_inertia(ts, np.zeros((200, 3)))
    with pytest.raises(ValueError, match=message):
        rj.estimate_inertia(ts, np.zeros((200, 3)))
    with pytest.raises(ValueError, match=message):
        rj.fit_inertia_to_orientation(ts, np.tile([1.0, 0.0, 0.0, 0.0], (200, 1)))
    with pytest.raises(ValueError, match="omega_from_orientations needs at least 2 samples, got 1"):
        rj.omega_from_orientations(ts[:1], np.array([[1.0, 0.0, 0.0, 0.0]]))
    with pytest.raises(ValueError, match=r"tol must be below 1 .*got 1.0"):
        rj.fit_inertia(ts, np.ones((200, 3)), tol=1.0)


def test_a_diagonal_float32_tensor_is_checked_by_its_diagonal():
    """A float32 thin rod (moments 5e-7 of a 0.17 trace) was physical as moments and 'non-positive'
    as the diagonal tensor of the same moments: the eigenvalue roundoff floor applied to a tensor
    whose moments are exact."""
    moments = rj.solid_cylinder(jnp.float32(1.0), jnp.float32(1e-3), jnp.float32(1.0))
    assert bool(rj.is_physical_inertia(moments)) and bool(rj.is_physical_inertia(jnp.diag(moments)))
    rj.check_inertia(jnp.diag(moments))
    # Zero and triangle-violating diagonals stay non-physical.
    assert not bool(rj.is_physical_inertia(jnp.diag(jnp.array([1.0, 1.0, 0.0], jnp.float32))))
    assert not bool(rj.is_physical_inertia(jnp.diag(jnp.array([1.0, 2.0, 3.1], jnp.float32))))


def test_estimate_inertia_names_a_half_width_longer_than_the_record():
    """half_width=1000 on 200 samples returned a poor estimate from one quadratic through it all."""
    ts = np.linspace(0.0, 10.0, 200)
    omega = np.asarray(rj.torque_free_omega(np.array([1.0, 2.0, 2.8]), np.array([0.3, 0.5, 1.0]), ts))
    message = r"half_width 1000 makes each local fit span 2001 samples.*at most 99"
    with pytest.raises(ValueError, match=message):
        rj.estimate_inertia(ts, omega, half_width=1000)
    rj.estimate_inertia(ts, omega, half_width=99)


def test_stability_functions_keep_float32_under_jit():
    """A Python number traced by jit widened float32 input to float64 (float32 eagerly)."""
    moments = jnp.array([1.0, 2.0, 2.5], jnp.float32)
    top = (jnp.array([1.0, 1.0, 0.5], jnp.float32), 1.0, jnp.array([0.0, 0.0, 0.3], jnp.float32), 5.0)
    for f, args in ((rj.spin_stability, (moments, 2.0)), (rj.sleeping_top, top)):
        eager, jitted = f(*args), jax.jit(f)(*args)
        for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted), strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert jax.tree.leaves(jitted)[0].dtype in (jnp.float32, jnp.bool_)
