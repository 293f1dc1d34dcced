"""Trajectory.invariants() where the conserved quantities start at zero, and its derivatives.

References: the conservation laws themselves. A heavy top released at rest with its centre of mass
level with the pivot has energy 0 and angular momentum 0 at t = 0; its closed form (accuracy="exact")
conserves both to roundoff, so their drift, relative to a scale of the motion, must be roundoff.
The drift of an integrator must stay within its tolerance's reach. Dividing by the values at t = 0
reported a drift of 4e8 (energy) and 1.9e300 (vertical angular momentum) for these tops.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rigidjax as rj

TS = jnp.linspace(0.0, 3.0, 31)
LEVEL = rj.quat_from_euler(jnp.array([0.0, np.pi / 2, 0.0]))  # symmetry axis horizontal


@pytest.mark.parametrize("accuracy, bound", [("exact", 1e-14), ("balanced", 1e-6)])
def test_a_top_released_level_and_at_rest(accuracy, bound):
    top = rj.HeavyTop(jnp.array([1.0, 1.0, 0.5]), 1.0, jnp.array([0.0, 0.0, 0.3]))
    traj = rj.simulate(top, rj.State(jnp.zeros(3), LEVEL), TS, accuracy=accuracy)
    # It falls: the energies are not 0 along the way (m g l = 2.9 J), only at the start.
    assert float(jnp.max(traj.kinetic_energy())) > 1.0 and abs(float(traj.energy()[0])) < 1e-15
    drifts = traj.invariants()
    assert float(drifts["energy"]) < bound
    assert float(drifts["vertical_angular_momentum"]) < bound


def test_an_asymmetric_top_released_at_rest():
    top = rj.HeavyTop(jnp.array([1.0, 1.2, 0.5]), 1.0, jnp.array([0.02, 0.0, 0.3]))
    q0 = rj.quat_from_euler(jnp.array([0.3, 0.5, 0.2]))
    traj = rj.simulate(top, rj.State(jnp.zeros(3), q0), TS, accuracy="precise")
    drifts = traj.invariants()
    assert float(drifts["vertical_angular_momentum"]) < 1e-8
    assert float(drifts["energy"]) < 1e-8


def test_every_invariant_has_a_finite_gradient():
    """The space angular momentum's drift is 0 at the first sample: its norm's derivative there was
    NaN, and so was the gradient of the drift in the moments."""
    omega, q0 = jnp.array([0.3, 1.0, -0.2]), jnp.array([1.0, 0.0, 0.0, 0.0])

    def drifts(inertia):
        return rj.simulate(rj.FreeBody(inertia), rj.State(omega, q0), TS).invariants()

    gradients = jax.jacrev(drifts)(jnp.array([1.0, 2.0, 3.0]))
    assert set(gradients) == {"energy", "angular_momentum_norm", "space_angular_momentum", "quaternion_norm"}
    for name, gradient in gradients.items():
        assert np.all(np.isfinite(gradient)), name

    def top_drifts(mass):
        top = rj.HeavyTop(jnp.array([1.0, 1.0, 0.5]), mass, jnp.array([0.0, 0.0, 0.3]))
        return rj.simulate(top, rj.State(jnp.zeros(3), LEVEL), TS).invariants()

    for name, gradient in jax.jacrev(top_drifts)(1.0).items():
        assert np.all(np.isfinite(gradient)), name
