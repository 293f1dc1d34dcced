"""Forward and reverse mode through simulate on default settings: jax.jacfwd and jax.jacrev agree
with each other and with central finite differences (a HeavyTop, RKMK at a fixed step, tangents
closed over by a torque) or the exact derivative (a FreeBody with orientation under jit, and the
Hessian: Euler's equations' variational equations, integrated by scipy); the rule that picks the
adjoint for each transformation; an adjoint given by the user is used as given."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp
from helpers import central_difference, variational_dop853

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


def free_body_equations(inertia, with_orientation):
    """Euler's equations of a torque-free body (principal moments ``inertia``) and, with
    ``with_orientation``, ``q' = q (0, w) / 2``, as sympy expressions: (rhs, symbols)."""
    I1, I2, I3 = (float(x) for x in np.asarray(inertia))
    w1, w2, w3 = w = sp.symbols("w1:4")
    rhs = [(I2 - I3) * w2 * w3 / I1, (I3 - I1) * w3 * w1 / I2, (I1 - I2) * w1 * w2 / I3]
    if not with_orientation:
        return rhs, list(w)
    qw, qx, qy, qz = q = sp.symbols("q0:4")
    rhs += [
        (-qx * w1 - qy * w2 - qz * w3) / 2,
        (qw * w1 + qy * w3 - qz * w2) / 2,
        (qw * w2 - qx * w3 + qz * w1) / 2,
        (qw * w3 + qx * w2 - qy * w1) / 2,
    ]
    return rhs, [*w, *q]


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
    Reference: the exact derivative, by the variational equations integrated by scipy's DOP853 at
    rtol = atol = 1e-13 (the closed form's derivative, which took 25 s to compile, agrees with it to
    5e-14; the 4-step solve matches it to 6e-9). Central differences of the solve are no reference
    here: a change of 1e-5 in omega0 changes the step sizes, and the differences were off by 8e-7."""
    forward = np.asarray(jax.jit(jax.jacfwd(free_body))(W0))
    reverse = np.asarray(jax.jit(jax.jacrev(free_body))(W0))
    rhs, z = free_body_equations(INERTIA, with_orientation=True)
    z0 = np.concatenate([np.asarray(W0), np.asarray(Q0)])
    _, reference = variational_dop853(rhs, z, z0, np.eye(7, 3), float(TS[-1]))
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
    # Central differences of the same damped solve, with k passed in args to one torque function (one
    # program for both calls: f, with a new function and k compiled in, compiled a program per call).
    damped = rj.RigidBody(inertia, rj.Torque(lambda t, s, a: -a * s.omega, needs_orientation=False))

    def g(k):
        return np.asarray(rj.simulate(damped, rj.State(W0), TS, accuracy="fast", args=k).omega[-1])

    reference = (g(k + 1e-5) - g(k - 1e-5)) / 2e-5
    np.testing.assert_allclose(forward, reference, rtol=0, atol=1e-6 * np.max(np.abs(reference)))
    assert np.max(np.abs(reference)) > 0.01


def test_default_adjoint_by_mode():
    """The rule itself, on the tracers each transformation passes in."""
    seen = {}

    def record(name):
        def f(x):
            seen[name] = type(driver.default_adjoint({"a": x, "b": None}, 1.0))
            return jnp.sum(x)  # one cheap operation: each transformation compiles it eagerly

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
    given: the direct adjoint is picked for the nested modes. Against the exact Hessian: Euler's
    equations' first and second variational equations integrated by scipy's DOP853 at 1e-13 (no
    rigidjax, no JAX; the closed form's jax.hessian, 20 s to compile, agrees with it to 3e-14)."""
    weights = jnp.arange(1.0, 4.0)

    def integrated(w):
        omega = rj.simulate(rj.FreeBody(INERTIA), rj.State(w), TS).omega[-1]
        return jnp.sum(omega**2 * weights)

    hessian = np.asarray(jax.hessian(integrated)(W0))
    # sum_i c_i w_i^2: its Hessian is 2 sum_i c_i (dw_i/dw0 dw_i/dw0^T + w_i d2w_i/dw0^2).
    rhs, z = free_body_equations(INERTIA, with_orientation=False)
    w, S, H = variational_dop853(rhs, z, np.asarray(W0), np.eye(3), float(TS[-1]), second=True)
    c = np.asarray(weights)
    reference = 2 * (np.einsum("i,ia,ib->ab", c, S, S) + np.einsum("i,i,iab->ab", c, w, H))
    assert np.max(np.abs(reference)) > 0.1
    np.testing.assert_allclose(hessian, reference, rtol=0, atol=1e-6 * np.max(np.abs(reference)))


def test_explicit_adjoint_is_respected():
    """A given adjoint is never replaced: the checkpointed adjoint cannot push tangents, ForwardMode
    cannot be transposed, and each says so when asked for the other mode."""
    with pytest.raises(TypeError, match="custom_vjp"):
        jax.jacfwd(lambda w: free_body(w, adjoint=diffrax.RecursiveCheckpointAdjoint()))(W0)
    with pytest.raises(ValueError, match="[Rr]everse-mode"):
        # Traced only (eval_shape): eagerly the forward pass compiled a solve before the transpose
        # raised the same error.
        jax.eval_shape(jax.jacrev(lambda w: free_body(w, adjoint=diffrax.ForwardMode())), W0)
