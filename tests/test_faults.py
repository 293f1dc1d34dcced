"""Faults during a run: a body whose torque or state turns non-finite is named (index and time) with
``throw=True`` and, with ``throw=False``, is flagged and NaN from its fault on while every other body
of the batch keeps its full result, also when it shares a chunk's step size with the bad one.

The healthy bodies are checked against scipy's DOP853 (tests/helpers.py), independent of rigidjax."""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dop853_free_body

import rigidjax as rj
from rigidjax.solvers import RKMK

INERTIA = np.array([1.0, 2.0, 3.0])
OMEGA = np.array([1.0, 0.2, 0.3])
T_FAULT = 1.0
TS = jnp.linspace(0.0, 3.0, 31)
_TS = np.asarray(TS)  # for indexing on the host: no small program per index


def _scene(n, bad, shape=None):
    """``n`` torque-free bodies, except that body ``bad`` (flat index) gets a NaN torque after
    ``T_FAULT``: it alone spins faster, and the torque turns NaN above that speed."""
    omega0 = np.tile(OMEGA, (n, 1))
    omega0[bad, 0] = 5.0
    torque = rj.Torque(
        lambda t, s, a: jnp.where((t > T_FAULT) & (s.omega[0] > 3.0), jnp.nan, 0.0) * jnp.ones(3),
        needs_orientation=False,
    )
    inertia = np.tile(INERTIA, (n, 1))
    if shape is not None:
        omega0, inertia = omega0.reshape(shape + (3,)), inertia.reshape(shape + (3,))
    return rj.RigidBody(jnp.asarray(inertia), torque), rj.State(jnp.asarray(omega0))


def _reference(omega0):
    omega, _ = dop853_free_body(INERTIA, omega0, np.asarray(TS), tol=1e-12)
    return omega


def _check_isolated(traj, bad):
    omega = np.asarray(traj.omega).reshape(-1, TS.shape[0], 3)
    success = np.asarray(traj.success).ravel()
    assert np.flatnonzero(~success).tolist() == [bad]
    healthy = _reference(OMEGA)
    for body in range(omega.shape[0]):
        if body != bad:
            np.testing.assert_allclose(omega[body], healthy, rtol=0, atol=1e-7)
    # The bad body: its own motion up to the fault, NaN from the first sample after it.
    first = int(np.asarray(traj.stats["first_failed_sample"]).ravel()[bad])
    assert _TS[first - 1] <= T_FAULT <= _TS[first]
    bad_reference = _reference(np.array([5.0, OMEGA[1], OMEGA[2]]))
    np.testing.assert_allclose(omega[bad, :first], bad_reference[:first], rtol=0, atol=2e-6)
    assert np.all(np.isnan(omega[bad, first:]))


def test_one_bad_body_in_a_shared_step_chunk_keeps_the_others():
    """50 bodies in one chunk (one shared step size): the bad one does not take the 49 with it."""
    model, state = _scene(50, bad=17)
    traj = rj.simulate(model, state, TS, throw=False)
    assert int(traj.stats["chunk_size"]) == 50
    _check_isolated(traj, 17)


def test_a_body_that_needs_more_steps_than_max_steps_is_the_one_named_and_flagged():
    """Three bodies in one chunk, the middle one 100 times faster: with max_steps=50 (the slow ones
    need 23 and 36 alone) the chunk stopped, the error named body 0 and every body was flagged, NaN
    from the third sample. The chunk is run again body by body, as for a NaN torque."""
    omega0 = np.array([[0.3, 0.1, 2.0], [30.0, 10.0, 200.0], [0.1, 3.0, 0.1]])
    model, state = rj.FreeBody(jnp.asarray(INERTIA)), rj.State(jnp.asarray(omega0))
    ts = jnp.linspace(0.0, 10.0, 101)
    with pytest.raises(eqx.EquinoxRuntimeError, match="body 1 failed between .* reached max_steps=50"):
        rj.simulate(model, state, ts, max_steps=50)
    traj = rj.simulate(model, state, ts, max_steps=50, throw=False)
    assert np.asarray(traj.success).tolist() == [True, False, True]
    omega = np.asarray(traj.omega)
    for body in (0, 2):
        expected = dop853_free_body(INERTIA, omega0[body], np.asarray(ts))[0]
        np.testing.assert_allclose(omega[body], expected, rtol=0, atol=1e-5)
    first = int(np.asarray(traj.stats["first_failed_sample"])[1])
    assert np.all(np.isnan(omega[1, first:])) and not np.any(np.isnan(omega[1, :first]))


def test_a_failed_body_has_no_quaternion_drift_to_report():
    """The failed body's quaternion drift was the solver's record of its steps before the failure,
    a clean-looking number beside the NaN of its other invariants."""
    # Built with numpy and handed over as arrays: no small program per array operation.
    ts = np.linspace(0.0, 1.0, 3)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (2, 3, 1))
    q[1, 2] = np.nan
    omega = np.ones((2, 3, 3))
    omega[1, 2] = np.nan
    traj = rj.Trajectory(
        jnp.asarray(ts), jnp.asarray(omega), jnp.asarray(q), rj.FreeBody(jnp.asarray(INERTIA)),
        jnp.asarray([True, False]), {"quaternion_norm_error": jnp.asarray([1e-15, 1e-15])},
    )  # fmt: skip
    invariants = traj.invariants()
    assert float(invariants["quaternion_norm"][0]) == 1e-15
    for name in ("quaternion_norm", "energy", "angular_momentum_norm"):
        assert np.isnan(float(invariants[name][1])), name


@pytest.mark.slow
def test_a_nan_torque_is_named_with_body_and_time_not_as_max_steps():
    model, state = _scene(50, bad=17)
    with pytest.raises(eqx.EquinoxRuntimeError) as info:
        rj.simulate(model, state, TS)
    message = str(info.value)
    assert "body 17 failed between t = 0.9 s and t = 1 s" in message, message
    assert "NaN or inf" in message and "max_steps" not in message, message
    assert "throw=False" in message


def test_a_body_that_fails_at_its_first_step_is_named_with_that_time():
    """A torque that is NaN from the start: not even the initial sample is written, and the message
    names the first step rather than an interval that runs backwards."""
    torque = rj.Torque(lambda t, s, a: jnp.full(3, jnp.nan), needs_orientation=False)
    message = r"the body failed at its first step from t = 0 s: it stopped"
    with pytest.raises(eqx.EquinoxRuntimeError, match=message):
        rj.simulate(rj.RigidBody(jnp.asarray(INERTIA), torque), rj.State(jnp.asarray(OMEGA)), TS)


@pytest.mark.slow
def test_batch_index_is_named_in_the_batch_shape():
    """The 50 bodies of the tests above, as a (5, 10) batch: body 13 is (1, 3)."""
    model, state = _scene(50, bad=13, shape=(5, 10))
    with pytest.raises(eqx.EquinoxRuntimeError, match=re.escape("body (1, 3) failed")):
        rj.simulate(model, state, TS)


def test_under_jit_the_fault_is_still_an_error():
    model, state = _scene(4, bad=2)
    run = eqx.filter_jit(lambda m, s: rj.simulate(m, s, TS).omega)
    with pytest.raises(Exception, match="NaN or inf"):
        jax.block_until_ready(run(model, state))


def test_fixed_step_solver_flags_only_the_bad_body():
    """RKMK at a fixed step has no shared error control: the bad body turns NaN alone."""
    model, state = _scene(6, bad=4)
    traj = rj.simulate(model, state, TS, solver=RKMK(), dt0=0.01, throw=False)
    code = np.asarray(traj.stats["result"])
    assert np.flatnonzero(~np.asarray(traj.success)).tolist() == [4] and code[4] != 0
    omega = np.asarray(traj.omega)
    np.testing.assert_allclose(omega[0], _reference(OMEGA), rtol=0, atol=1e-6)
    first = int(np.asarray(traj.stats["first_failed_sample"])[4])
    assert _TS[first - 1] <= T_FAULT <= _TS[first] and np.all(np.isnan(omega[4, first:]))
    with pytest.raises(eqx.EquinoxRuntimeError, match="body 4 failed between t = 1 s and t = 1.1 s"):
        rj.simulate(model, state, TS, solver=RKMK(), dt0=0.01)


@pytest.mark.slow
def test_ten_thousand_bodies_in_chunks_lose_only_the_bad_one():
    """10^4 bodies in chunks of 1024 sharing a step size: only the chunk with the bad body is run
    again body by body, and only the bad body is lost."""
    n, bad = 10_000, 6_543
    model, state = _scene(n, bad)
    traj = rj.simulate(model, state, TS, throw=False, chunk_size=1024)
    success = np.asarray(traj.success)
    assert np.flatnonzero(~success).tolist() == [bad]
    omega = np.asarray(traj.omega)
    healthy = _reference(OMEGA)
    assert np.max(np.abs(np.delete(omega, bad, axis=0) - healthy)) < 1e-7
    first = int(np.asarray(traj.stats["first_failed_sample"])[bad])
    assert np.all(np.isfinite(omega[bad, :first])) and np.all(np.isnan(omega[bad, first:]))


@pytest.mark.slow
def test_precise_keeps_healthy_bodies_whose_steps_land_on_sample_times():
    """ "precise" lands a step on every sample time, which can clip a step to almost nothing; the
    fault floor acts on rejected steps only, so no healthy body is stopped (300 random free bodies,
    one per chunk: 5 stopped with a floor on every step), and each agrees with scipy's DOP853."""
    rng = np.random.default_rng(0)
    n = 300
    inertia = np.array([2.0, 3.0, 4.0]) * (1 + 0.05 * rng.uniform(-1, 1, (n, 3)))
    omega0 = np.array([0.7, -0.4, 1.1]) + 0.3 * rng.normal(size=(n, 3))
    q0 = rng.normal(size=(n, 4))
    q0 /= np.linalg.norm(q0, axis=-1, keepdims=True)
    ts = np.linspace(0.0, 10.0, 51)
    traj = rj.simulate(
        rj.FreeBody(jnp.asarray(inertia)),
        rj.State(jnp.asarray(omega0), jnp.asarray(q0)),
        jnp.asarray(ts),
        accuracy="precise",
        throw=False,
        chunk_size=1,
    )
    assert bool(np.all(np.asarray(traj.success)))
    for body in (0, 137, 299):
        reference, _ = dop853_free_body(inertia[body], omega0[body], ts, tol=1e-13)
        np.testing.assert_allclose(np.asarray(traj.omega)[body], reference, rtol=0, atol=1e-9)


@pytest.mark.slow
def test_precise_reports_a_nan_torque_as_such():
    """Steps land on the sample times: the sample at the fault (t = 1) is reached, the next not."""
    model, state = _scene(50, bad=3)  # the tests' 50 bodies: their checks' and reruns' programs
    with pytest.raises(
        eqx.EquinoxRuntimeError, match="body 3 failed between t = 1 s and t = 1.1 s: it stopped"
    ):
        rj.simulate(model, state, TS, accuracy="precise")
