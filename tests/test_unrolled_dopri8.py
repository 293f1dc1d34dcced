"""UnrolledDopri8 against diffrax's own Dopri8 (the same tableau run as a stage loop), a closed-form
solution (its order of convergence) and finite differences (its derivatives in both modes)."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rigidjax as rj
from rigidjax.solvers import UnrolledDopri8


def _field(t, y, a):
    return jnp.stack([y[1] * jnp.sin(t) + a, -y[0] * y[1], jnp.cos(y[0]) * t])


Y0 = jnp.array([0.3, 1.2, -0.4])


@pytest.mark.parametrize("fence_stages", [True, False])
def test_one_step_matches_diffrax_dopri8(fence_stages):
    """Reference: diffrax.Dopri8's step (stage loop over a buffer): solution, error estimate, the
    dense output inside the step and the last stage's field (first same as last) agree to rounding,
    with the stages fenced or left to XLA to fuse."""
    term = diffrax.ODETerm(_field)
    ours, theirs = UnrolledDopri8(fence_stages=fence_stages), diffrax.Dopri8()
    a = ours.step(term, 0.1, 0.4, Y0, 0.5, ours.init(term, 0.1, 0.4, Y0, 0.5), False)
    b = theirs.step(term, 0.1, 0.4, Y0, 0.5, theirs.init(term, 0.1, 0.4, Y0, 0.5), False)
    np.testing.assert_allclose(a[0], b[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(a[1], b[1], rtol=0, atol=1e-16)
    for t in (0.1, 0.13, 0.25, 0.37, 0.4):
        ours_at_t = ours.interpolation_cls(t0=0.1, t1=0.4, **a[2]).evaluate(t)
        theirs_at_t = theirs.interpolation_cls(t0=0.1, t1=0.4, **b[2]).evaluate(t)
        np.testing.assert_allclose(ours_at_t, theirs_at_t, rtol=0, atol=1e-14)  # sums in another order
    np.testing.assert_allclose(a[3], _field(0.4, a[0], 0.5), rtol=0, atol=1e-15)


def test_adaptive_solve_and_dense_output_match_diffrax_dopri8():
    """Reference: the same adaptive solve with diffrax.Dopri8: the same steps, samples and dense
    output to 1e-10, 1e-4 of either solve's error (1.4e-6): the error estimate is a small
    difference of stage sums, summed here in another order, so the controller sees estimates that
    differ by rounding and takes steps that differ by as much."""
    ts = jnp.linspace(0.0, 3.0, 37)

    def solve(solver):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(_field), solver, 0.0, 3.0, 0.01, Y0, args=0.5,
            saveat=diffrax.SaveAt(ts=ts, dense=True),
            stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
        )  # fmt: skip

    ours, theirs = solve(UnrolledDopri8()), solve(diffrax.Dopri8())
    assert int(ours.stats["num_steps"]) == int(theirs.stats["num_steps"])
    np.testing.assert_allclose(ours.ys, theirs.ys, rtol=0, atol=1e-10)
    between = ts[:-1] + 0.37 * jnp.diff(ts)
    np.testing.assert_allclose(
        jax.vmap(ours.evaluate)(between), jax.vmap(theirs.evaluate)(between), atol=1e-10
    )


def test_eighth_order_convergence_against_a_closed_form():
    """Reference: y' = A y with A skew plus damping, y(t) = expm(A t) y0 by eigen-decomposition
    (numpy); halving the step divides the error by ~2^8."""
    a = np.array([[-0.1, 2.0], [-2.0, -0.1]])
    lam, vec = np.linalg.eig(a)
    exact = np.real(vec @ np.diag(np.exp(lam * 4.0)) @ np.linalg.solve(vec, [1.0, 0.5]))
    errors = []
    for dt in (0.4, 0.2, 0.1):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: jnp.asarray(a) @ y), UnrolledDopri8(), 0.0, 4.0, dt,
            jnp.array([1.0, 0.5]), stepsize_controller=diffrax.ConstantStepSize(),
        )  # fmt: skip
        errors.append(np.max(np.abs(np.asarray(sol.ys[-1]) - exact)))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders > 7.5), (errors, orders)


# Reverse mode through the written-out stages compiles for ~15 s; the fast tier keeps forward mode.
@pytest.mark.parametrize("mode", [pytest.param("reverse", marks=pytest.mark.slow), "forward"])
def test_derivatives_match_finite_differences(mode):
    """Reference: central finite differences of the solution in the parameter ``a``."""
    ts = jnp.linspace(0.0, 2.0, 9)
    adjoint = diffrax.RecursiveCheckpointAdjoint() if mode == "reverse" else diffrax.ForwardMode()

    def loss(a):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(_field), UnrolledDopri8(), 0.0, 2.0, 0.05, Y0, args=a,
            saveat=diffrax.SaveAt(ts=ts), stepsize_controller=diffrax.ConstantStepSize(), adjoint=adjoint,
        )  # fmt: skip
        return jnp.sum(sol.ys**2)

    derivative = jax.grad(loss)(0.5) if mode == "reverse" else jax.jacfwd(loss)(0.5)
    h = 1e-5
    finite = (loss(0.5 + h) - loss(0.5 - h)) / (2 * h)
    np.testing.assert_allclose(derivative, finite, rtol=1e-7)


def test_rejects_terms_that_are_not_an_ode():
    """A stochastic term cannot be stepped by an ODE method: diffrax's clear refusal, not a wrong
    answer."""
    brownian = diffrax.VirtualBrownianTree(0.0, 1.0, tol=1e-3, shape=(), key=jax.random.PRNGKey(0))
    terms = diffrax.MultiTerm(
        diffrax.ODETerm(lambda t, y, a: -y), diffrax.ControlTerm(lambda t, y, a: 0.1, brownian)
    )
    with pytest.raises(Exception, match="Terms are not compatible with solver"):
        diffrax.diffeqsolve(terms, UnrolledDopri8(), 0.0, 1.0, 0.1, 1.0)


def test_float32_stays_float32():
    """Reference: exp(-1) for y' = -y."""
    one = jnp.float32(1.0)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, y, a: -y), UnrolledDopri8(), 0 * one, one, 0.1 * one, one,
        stepsize_controller=diffrax.PIDController(rtol=1e-5, atol=1e-5),
    )  # fmt: skip
    assert sol.ys.dtype == jnp.float32
    np.testing.assert_allclose(sol.ys[-1], np.exp(-1.0), rtol=2e-6)


@pytest.mark.slow
def test_simulate_presets_match_diffrax_dopri8_through_simulate():
    """Reference: simulate with solver=diffrax.Dopri8() and the same tolerance, on 1024 tennis-racket
    bodies with orientation (a batch the preset runs with UnrolledDopri8): both within the
    tolerance's reach of each other, and of the closed form."""
    n = 1024
    rng = np.random.default_rng(3)
    inertia = jnp.asarray(np.array([1.0, 2.0, 2.5]) * (1 + 0.05 * rng.uniform(-1, 1, (n, 3))))
    omega0 = jnp.asarray(np.array([0.05, 4.0, 0.05]) + 0.01 * rng.normal(size=(n, 3)))
    state = rj.State(omega0, jnp.tile(jnp.array([1.0, 0, 0, 0]), (n, 1)))
    ts = jnp.linspace(0.0, 10.0, 41)
    ours = rj.simulate(rj.FreeBody(inertia), state, ts, accuracy="balanced")
    assert isinstance(rj.solvers.PRESETS["balanced"][0](), UnrolledDopri8)
    theirs = rj.simulate(rj.FreeBody(inertia), state, ts, solver=diffrax.Dopri8(), rtol=1e-8, atol=1e-8)
    exact = rj.simulate(rj.FreeBody(inertia), state, ts, accuracy="exact")
    scale = jnp.linalg.norm(exact.omega, axis=-1, keepdims=True)
    assert float(jnp.max(jnp.abs(ours.omega - theirs.omega) / scale)) < 1e-7
    assert float(jnp.max(jnp.abs(ours.omega - exact.omega) / scale)) < 1e-6
    assert float(jnp.max(jnp.abs(ours.orientation - exact.orientation))) < 1e-6


def test_differentiated_presets_run_diffrax_dopri8_with_the_same_values():
    """Under jax.grad / jacfwd (also inside jit and vmap), and for small batches, the presets run
    diffrax's own Dopri8 (the written-out stages compile slowly); the value of a differentiated call
    agrees with the plain call's (reference: the plain call) and its gradient with finite
    differences."""
    from rigidjax._integrate import driver
    from rigidjax._integrate.presets import preset_solver

    seen = []

    def probe(x):
        seen.append(driver.is_differentiated(x))
        return jnp.sum(x**2)

    x = jnp.ones(2)
    probe(x)
    jax.grad(probe)(x)
    jax.jacfwd(probe)(x)
    jax.jit(jax.grad(probe))(x)
    jax.vmap(jax.grad(probe))(jnp.ones((3, 2)))
    assert seen == [False, True, True, True, True]
    assert type(preset_solver("balanced", True, 10_000)) is diffrax.Dopri8
    assert isinstance(preset_solver("precise", False, 10_000), UnrolledDopri8)
    assert type(preset_solver("precise", False, 100)) is diffrax.Dopri8  # compile outweighs the steps
    assert type(preset_solver("fast", True, 10_000)) is diffrax.Tsit5

    state = rj.State(jnp.array([0.1, 2.0, 0.1]), jnp.array([1.0, 0.0, 0.0, 0.0]))
    ts = jnp.linspace(0.0, 5.0, 11)

    def loss(inertia):
        return jnp.sum(rj.simulate(rj.FreeBody(inertia), state, ts).omega ** 2)

    inertia = jnp.array([1.0, 2.0, 2.5])
    value, gradient = jax.value_and_grad(loss)(inertia)
    np.testing.assert_allclose(value, loss(inertia), rtol=1e-10)
    h = 1e-6
    finite = [(loss(inertia + h * e) - loss(inertia - h * e)) / (2 * h) for e in jnp.eye(3)]
    np.testing.assert_allclose(gradient, finite, rtol=1e-5)


def test_simulate_traces_the_vector_field_once_or_twice(monkeypatch):
    """A written-out step evaluates the field 13 times and diffrax traces its step three times; the
    field is a compiled function of its own, so it is traced once or twice per program rather than
    at every stage (the integration's tracing time): a plain process traces it once, under this
    suite's runtime type checks the first-step guess and diffrax's check of the term trace it apart.
    Counted on the Python function that builds it, with the solver written out."""
    import equinox as eqx

    from rigidjax._integrate import formulations

    traces = []
    build = formulations._scaled_vector_field.__wrapped__

    def counted(*args, **kwargs):
        traces.append(1)
        return build(*args, **kwargs)

    monkeypatch.setattr(formulations, "_scaled_vector_field", eqx.filter_jit(counted))
    model = rj.FreeBody(jnp.asarray([[1.0, 2.0, 3.0], [1.5, 2.0, 2.5]]))
    state = rj.State(jnp.asarray([[0.1, 2.0, 0.1], [1.0, 0.2, 0.3]]), jnp.asarray([[1.0, 0.0, 0.0, 0.0]] * 2))
    ts = jnp.linspace(0.0, 3.0, 4)
    traj = rj.simulate(model, state, ts, solver=UnrolledDopri8(), rtol=1e-9, atol=1e-9)
    assert 1 <= len(traces) <= 2
    reference = rj.simulate(model, state, ts, accuracy="exact")
    np.testing.assert_allclose(np.asarray(traj.omega), np.asarray(reference.omega), rtol=0, atol=1e-7)


def test_preset_names_what_simulate_runs(without_runtime_typecheck):
    """``rigidjax.solvers.preset`` against runs of simulate: its solver and tolerance, passed to
    simulate explicitly, give the preset's trajectories to the bit (the command line's summary
    named UnrolledDopri8 and rtol 1e-8 for float32 blocks of 100 bodies, which ran Dopri8 at 1.2e-6)."""
    from rigidjax.solvers import preset

    assert [type(preset("balanced", n)[0]) for n in (1000, 1024)] == [diffrax.Dopri8, UnrolledDopri8]
    assert type(preset("precise", 4096, differentiated=True)[0]) is diffrax.Dopri8
    assert type(preset("fast", 10**6)[0]) is diffrax.Tsit5
    assert preset("balanced", 5, jnp.float32)[1] == 10 * float(np.finfo(np.float32).eps)
    assert preset("precise", 5, jnp.float64)[1] == 1e-11
    inertia = jnp.array([[1.0, 2.0, 2.5], [1.5, 2.0, 3.0]], jnp.float32)
    state = rj.State(jnp.array([0.1, 3.0, 0.2], jnp.float32), jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32))
    ts = jnp.linspace(0.0, 2.0, 5, dtype=jnp.float32)
    solver, rtol = preset("balanced", 2, jnp.float32)
    ran = rj.simulate(rj.FreeBody(inertia), state, ts, accuracy="balanced")
    named = rj.simulate(rj.FreeBody(inertia), state, ts, solver=solver, rtol=rtol, atol=rtol)
    np.testing.assert_array_equal(ran.omega, named.omega)
    np.testing.assert_array_equal(ran.orientation, named.orientation)
    for call, error, match in (
        (lambda: preset("exact"), ValueError, r"accuracy must be one of .*the closed form: no solver"),
        (lambda: preset("balance"), ValueError, "accuracy must be one of 'fast', 'balanced', 'precise'"),
        (lambda: preset("fast", 0), ValueError, "n_bodies must be a positive integer"),
        (lambda: preset("fast", 2, jnp.float16), ValueError, "dtype must be float32 or float64"),
        (lambda: preset("fast", 2, differentiated="yes"), TypeError, "differentiated must be True or False"),
    ):
        with pytest.raises(error, match=match):
            call()
