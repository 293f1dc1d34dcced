"""Forward and reverse mode through simulate on default settings: jax.jacfwd and jax.jacrev agree
with each other and with central finite differences (a HeavyTop, RKMK at a fixed step, tangents
closed over by a torque) or the closed form's derivative (a FreeBody with orientation under jit);
the rule that picks the adjoint for each transformation; an adjoint given by the user is used as
given."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference

import rigidjax as rj
from rigidjax._integrate import driver

TS = jnp.linspace(0.0, 1.0, 3)
Q0 = rj.quat_from_euler(jnp.array([0.3, 0.8, -0.2]))
W0 = jnp.array([0.4, 1.1, -0.3])
INERTIA = jnp.array([1.0, 1.7, 2.4])
TOP = rj.HeavyTop(jnp.array([1.2, 1.0, 0.6]), 0.8, jnp.array([0.05, 0.0, 0.3]), 9.81)


def free_body(w, **kwargs):
    traj = rj.simulate(rj.FreeBody(INERTIA), rj.State(w, Q0), TS, **kwargs)
    return jnp.concatenate([traj.omega[-1], traj.orientation[-1]])


def heavy_top(w, **kwargs):
    traj = rj.simulate(TOP, rj.State(w, Q0), TS, **kwargs)
    return jnp.concatenate([traj.omega[-1], traj.orientation[-1]])


def rkmk(w, **kwargs):
    return free_body(w, solver=rj.solvers.RKMK(), dt0=0.05, **kwargs)


@pytest.mark.parametrize(
    "f", [heavy_top, pytest.param(rkmk, marks=pytest.mark.slow)], ids=["heavy_top", "rkmk"]
)
def test_jacfwd_and_jacrev_agree_with_finite_differences(f):
    forward = np.asarray(jax.jacfwd(f)(W0))
    reverse = np.asarray(jax.jacrev(f)(W0))
    reference = central_difference(f, W0, h=1e-5)
    scale = np.max(np.abs(reference))
    assert scale > 0.1  # the outputs depend on omega0: a zero Jacobian would not pass
    np.testing.assert_allclose(forward, reverse, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(forward, reference, rtol=0, atol=1e-6 * scale)


@pytest.mark.slow
def test_free_body_under_jit():
    """A FreeBody with orientation: jit around jacfwd (the tangents wrap jit tracers) finds forward
    mode, jit around jacrev stays in reverse mode (vmap nesting: test_default_adjoint_by_mode).
    Reference: the derivative of the closed form (Jacobi elliptic functions, no integration), which
    the 4-step solve matches to 6e-9. Central differences of the solve are no reference here: a
    change of 1e-5 in omega0 changes the step sizes, and the differences were off by 8e-7."""
    forward = np.asarray(jax.jit(jax.jacfwd(free_body))(W0))
    reverse = np.asarray(jax.jit(jax.jacrev(free_body))(W0))
    reference = np.asarray(jax.jacfwd(lambda w: free_body(w, accuracy="exact"))(W0))
    scale = np.max(np.abs(reference))
    assert scale > 0.1
    np.testing.assert_allclose(forward, reverse, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(forward, reference, rtol=0, atol=1e-7 * scale)


@pytest.mark.slow
def test_tangents_closed_over_by_a_torque():
    """A torque function closing over a traced number hides the tangents from the inputs: the solve
    is traced again in forward mode."""
    inertia = jnp.array([1.0, 2.0, 2.5])

    def f(k):
        body = rj.RigidBody(inertia, rj.Torque(lambda t, s, a: -k * s.omega, needs_orientation=False))
        return rj.simulate(body, rj.State(W0), TS, accuracy="fast").omega[-1]

    k = jnp.array(0.2)
    forward = np.asarray(jax.jacfwd(f)(k))
    reference = (np.asarray(f(k + 1e-5)) - np.asarray(f(k - 1e-5))) / 2e-5
    np.testing.assert_allclose(forward, reference, rtol=0, atol=1e-6 * np.max(np.abs(reference)))
    assert np.max(np.abs(reference)) > 0.01


def test_default_adjoint_by_mode():
    """The rule itself, on the tracers each transformation passes in."""
    seen = {}

    def record(name):
        def f(x):
            seen[name] = type(driver.default_adjoint({"a": x, "b": None}, 1.0))
            return jnp.sum(jnp.sin(x))

        return f

    x = jnp.ones(3)
    jax.jacfwd(record("jacfwd"))(x)
    jax.jit(jax.jacfwd(record("jit_jacfwd")))(x)
    jax.jacfwd(lambda x: jax.vmap(record("jacfwd_vmap"))(x[None])[0])(x)
    jax.vmap(jax.jacfwd(record("vmap_jacfwd")))(x[None])
    jax.jvp(record("jvp"), (x,), (x,))
    jax.grad(record("grad"))(x)
    jax.jacrev(record("jacrev"))(x)
    jax.jit(record("jit"))(x)
    record("eager")(x)
    jax.hessian(record("hessian"))(x)
    jax.jacrev(jax.jacfwd(record("jacrev_jacfwd")))(x)
    jax.grad(lambda x: jax.grad(record("grad_grad"))(x)[0])(x)
    forward = diffrax.ForwardMode
    reverse = diffrax.RecursiveCheckpointAdjoint
    both = diffrax.DirectAdjoint
    assert seen == {
        "jacfwd": forward, "jit_jacfwd": forward, "jacfwd_vmap": forward, "vmap_jacfwd": forward,
        "jvp": forward, "grad": reverse, "jacrev": reverse, "jit": reverse, "eager": reverse,
        "hessian": both, "jacrev_jacfwd": both, "grad_grad": both,  # reverse twice: the checkpointed
        # adjoint's loop raised "Reverse-mode differentiation does not work for lax.while_loop"
    }  # fmt: skip


@pytest.mark.slow
def test_hessian_on_default_settings_matches_the_closed_form():
    """jax.hessian (forward over reverse) of a function of simulate's omega, without an adjoint
    given: the direct adjoint is picked for the nested modes. Against the hessian of the closed form
    (torque_free_omega, differentiated as it is computed, no integrator)."""

    def integrated(w):
        omega = rj.simulate(rj.FreeBody(INERTIA), rj.State(w), TS).omega[-1]
        return jnp.sum(omega**2 * jnp.arange(1.0, 4.0))

    def closed_form(w):
        return jnp.sum(rj.torque_free_omega(INERTIA, w, TS[-1]) ** 2 * jnp.arange(1.0, 4.0))

    hessian = np.asarray(jax.hessian(integrated)(W0))
    reference = np.asarray(jax.hessian(closed_form)(W0))
    assert np.max(np.abs(reference)) > 0.1
    np.testing.assert_allclose(hessian, reference, rtol=0, atol=1e-6 * np.max(np.abs(reference)))


def test_explicit_adjoint_is_respected():
    """A given adjoint is never replaced: the checkpointed adjoint cannot push tangents, ForwardMode
    cannot be transposed, and each says so when asked for the other mode."""
    with pytest.raises(TypeError, match="custom_vjp"):
        jax.jacfwd(lambda w: free_body(w, adjoint=diffrax.RecursiveCheckpointAdjoint()))(W0)
    with pytest.raises(ValueError, match="[Rr]everse-mode"):
        jax.jacrev(lambda w: free_body(w, adjoint=diffrax.ForwardMode()))(W0)
