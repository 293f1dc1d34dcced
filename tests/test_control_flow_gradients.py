"""simulate inside JAX control flow (a control loop in ``lax.scan``): reverse mode on default
settings, forward mode with the adjoint the Gradients guide names, against central differences of
the same loop."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rigidjax as rj

INERTIA = jnp.asarray([1.0, 2.0, 2.5])


def rollout(omega0, adjoint=None):
    """Three control steps of 0.2 s: a torque-free step, then a kick of -0.1 omega per step. Fixed
    steps of Tsit5: the central differences see a smooth function (no step-size control)."""
    kwargs = {} if adjoint is None else {"adjoint": adjoint}
    fixed = {"solver": diffrax.Tsit5(), "stepsize_controller": diffrax.ConstantStepSize(), "dt0": 0.02}

    def step(omega, _):
        traj = rj.simulate(rj.FreeBody(INERTIA), rj.State(omega), jnp.asarray([0.0, 0.2]), **fixed, **kwargs)
        after = traj.omega[-1]
        return 0.9 * after, jnp.sum(after**2)

    _, costs = jax.lax.scan(step, omega0, None, length=3)
    return jnp.sum(costs)


@pytest.mark.slow
def test_a_control_loop_in_scan_differentiates_in_both_modes():
    omega0 = jnp.asarray([0.3, 0.8, 0.4])
    h = 1e-6
    value = jax.jit(rollout)
    numeric = np.array([(value(omega0 + h * e) - value(omega0 - h * e)) / (2 * h) for e in np.eye(3)])
    reverse = np.asarray(jax.grad(rollout)(omega0))
    np.testing.assert_allclose(reverse, numeric, rtol=1e-6, atol=1e-8)
    forward = np.asarray(jax.jacfwd(lambda w: rollout(w, diffrax.ForwardMode()))(omega0))
    np.testing.assert_allclose(forward, numeric, rtol=1e-6, atol=1e-8)
    # On default settings the scan hides the tangents from simulate: JAX's own error, as documented.
    with pytest.raises(TypeError, match="can't apply forward-mode autodiff"):
        jax.jacfwd(rollout)(omega0)
