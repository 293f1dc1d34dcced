"""Selecting bodies from a batched Trajectory: ``traj[i]``, slices, masks, iteration.

References: the per-body quantities of a selection are checked against NumPy arithmetic on the
selected arrays (the kinetic energy 0.5 omega . I omega, the heavy top's potential m g z of the centre
of mass) and against the same method on the whole batch; the indexing itself against NumPy's
indexing of the same arrays.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rigidjax as rj

TS = jnp.linspace(0.0, 1.0, 5)
INERTIA = np.array([[1.0, 2.0, 3.0], [1.0, 2.5, 3.0], [2.0, 2.0, 3.0], [1.5, 2.0, 2.5]])
OMEGA = np.array([[1.0, 0.2, 0.1], [0.3, 2.0, 0.1], [0.1, 0.1, 3.0], [0.5, -1.0, 0.7]])
IDENTITY = np.tile([1.0, 0.0, 0.0, 0.0], (4, 1))


@pytest.fixture(scope="module")
def free_bodies():
    """Four bodies, each with its own moments, with error estimates (per-body stats)."""
    model = rj.FreeBody(jnp.asarray(INERTIA))
    return rj.simulate(model, rj.State(jnp.asarray(OMEGA), jnp.asarray(IDENTITY)), TS, error_estimate=True)


def test_one_body_is_that_bodys_trajectory(free_bodies):
    traj = free_bodies
    for i in (1, -1):
        one = traj[i]
        assert one.batch_shape == ()
        np.testing.assert_array_equal(one.omega, traj.omega[i])
        np.testing.assert_array_equal(one.orientation, traj.orientation[i])
        np.testing.assert_array_equal(one.model.inertia, INERTIA[i])
        # The kinetic energy from the selected body's own moments, by NumPy.
        w = np.asarray(traj.omega[i])
        np.testing.assert_allclose(
            one.kinetic_energy(), 0.5 * np.sum(INERTIA[i] * w * w, axis=-1), rtol=1e-14
        )
        for name, value in one.invariants().items():
            np.testing.assert_allclose(value, traj.invariants()[name][i], rtol=1e-12, err_msg=name)
        for name in ("result", "first_failed_sample", "quaternion_norm_error", "error_estimate_omega"):
            np.testing.assert_array_equal(one.stats[name], traj.stats[name][i], err_msg=name)
        np.testing.assert_array_equal(
            one.error_estimate()["orientation"], traj.error_estimate()["orientation"][i]
        )
        # The run's step counts stay those of the run.
        np.testing.assert_array_equal(one.stats["num_steps"], traj.stats["num_steps"])


def test_slices_lists_masks_and_ellipsis_select_as_numpy_does(free_bodies):
    traj = free_bodies
    selections = {
        "slice": slice(1, 3),
        "list": [3, 0, 3],
        "array": np.array([2, -4]),
        "jax array": jnp.array([1, 2]),
        "mask": np.array([True, False, True, True]),
        "ellipsis": (..., slice(None, None, 2)),
    }
    for label, index in selections.items():
        part = traj[index]
        expected = np.arange(4)[index if not isinstance(index, list) else np.asarray(index)]
        assert part.batch_shape == expected.shape, label
        np.testing.assert_array_equal(part.omega, np.asarray(traj.omega)[expected], err_msg=label)
        np.testing.assert_array_equal(part.model.inertia, INERTIA[expected], err_msg=label)
        np.testing.assert_array_equal(part.success, np.asarray(traj.success)[expected], err_msg=label)
    assert [body.batch_shape for body in traj] == [()] * 4
    np.testing.assert_array_equal(np.stack([body.omega for body in traj]), traj.omega)


def test_one_scene_for_many_states_is_broadcast_per_body():
    """A heavy top's scene shared by a 2 x 3 batch of initial states, with per-body masses: each
    selected body carries the shared fields and its own mass; its potential energy is m g z_com."""
    mass = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    top = rj.HeavyTop(jnp.array([1.0, 1.0, 0.5]), jnp.asarray(mass), jnp.array([0.0, 0.0, 0.1]), 9.81)
    rng = np.random.default_rng(0)
    omega = rng.normal(size=(2, 3, 3))
    half = 0.3 * rng.normal(size=(2, 3, 3))
    q0 = np.concatenate([np.ones((2, 3, 1)), half], axis=-1)
    q0 /= np.linalg.norm(q0, axis=-1, keepdims=True)
    traj = rj.simulate(top, rj.State(jnp.asarray(omega), jnp.asarray(q0)), TS, accuracy="precise")
    assert traj.batch_shape == (2, 3)
    one = traj[1, 2]
    assert one.batch_shape == () and float(one.model.mass) == 6.0
    np.testing.assert_array_equal(one.model.com, [0.0, 0.0, 0.1])
    # z of the centre of mass: the third component of R(q) com, with R from the quaternion by NumPy.
    w, x, y, z = np.moveaxis(np.asarray(traj.orientation[1, 2]), -1, 0)
    z_com = 0.1 * (w * w - x * x - y * y + z * z)
    np.testing.assert_allclose(one.potential_energy(), 6.0 * 9.81 * z_com, rtol=1e-12)
    np.testing.assert_allclose(traj[1].energy(), traj.energy()[1], rtol=1e-14)
    np.testing.assert_allclose(traj[:, 0].energy(), traj.energy()[:, 0], rtol=1e-14)
    np.testing.assert_allclose(traj[traj.success].energy(), np.reshape(traj.energy(), (6, -1)), rtol=1e-14)


def test_selection_under_jit_and_from_a_vmap_over_times(free_bodies):
    traj = free_bodies
    np.testing.assert_array_equal(jax.jit(lambda t: t[2].omega)(traj), traj.omega[2])

    # One time axis per body: a jax.vmap of simulate over the sample times.
    times = jnp.stack([TS, 2.0 * TS])
    model = rj.FreeBody(jnp.asarray(INERTIA[0]))
    state = rj.State(jnp.asarray(OMEGA[0]), jnp.asarray(IDENTITY[0]))
    mapped = jax.vmap(lambda ts: rj.simulate(model, state, ts))(times)
    second = mapped[1]
    np.testing.assert_array_equal(second.ts, 2.0 * TS)
    alone = rj.simulate(model, state, 2.0 * TS)
    np.testing.assert_allclose(second.omega, alone.omega, rtol=1e-12)
    np.testing.assert_allclose(second.euler_angles(), alone.euler_angles(), rtol=1e-10, atol=1e-12)


def test_a_vmapped_trajectory_is_saved_body_by_body(tmp_path):
    times = jnp.stack([TS, 2.0 * TS])
    model = rj.FreeBody(jnp.asarray(INERTIA[0]))
    state = rj.State(jnp.asarray(OMEGA[0]), jnp.asarray(IDENTITY[0]))
    mapped = jax.vmap(lambda ts: rj.simulate(model, state, ts))(times)
    with pytest.raises(ValueError, match=r"ts has shape \(2, 5\), one time axis per body.*traj\[i\]\.save"):
        mapped.save(tmp_path / "all.npz")
    assert not (tmp_path / "all.npz").exists()
    mapped[1].save(tmp_path / "second.npz")
    loaded = rj.Trajectory.load(tmp_path / "second.npz")
    np.testing.assert_array_equal(loaded.ts, 2.0 * TS)
    np.testing.assert_array_equal(loaded.omega, mapped.omega[1])


def test_a_selection_saves_and_loads(free_bodies, tmp_path):
    part = free_bodies[[0, 2]]
    part.save(tmp_path / "part.npz")
    loaded = rj.Trajectory.load(tmp_path / "part.npz")
    np.testing.assert_array_equal(loaded.omega, part.omega)
    np.testing.assert_array_equal(loaded.model.inertia, INERTIA[[0, 2]])


@pytest.mark.parametrize(
    "index, error, words",
    [
        (7, IndexError, "index 7 is beyond batch axis 0 of size 4"),
        (-5, IndexError, "index -5 is beyond batch axis 0 of size 4"),
        ([0, 9], IndexError, "index 9 is beyond"),
        (jnp.array([4]), IndexError, "index 4 is beyond"),
        ((0, 1), IndexError, "takes 2 axes, but the trajectory has 1 batch axis"),
        (np.array([True, False]), IndexError, "boolean mask of shape (2,) for batch axes of sizes (4,)"),
        ((..., ...), IndexError, "only one ..."),
        (None, TypeError, "None is not an index of bodies"),
        (1.5, TypeError, "float 1.5 is not an index of bodies"),
        (True, TypeError, "bool True is not an index of bodies"),
        (np.array([0.0, 1.0]), TypeError, "is not an index of bodies"),
    ],
)
def test_an_index_beyond_the_batch_is_named(free_bodies, index, error, words):
    with pytest.raises(error) as raised:
        free_bodies[index]
    message = str(raised.value)
    assert message.startswith("Trajectory[") and words in message
    if error is IndexError:
        assert "batch_shape (4,)" in message


def test_a_single_body_has_no_bodies_to_iterate(free_bodies):
    with pytest.raises(TypeError, match=r"single body's trajectory \(batch_shape \(\)\)"):
        list(free_bodies[0])
    with pytest.raises(IndexError, match="the index takes 1 axis, but the trajectory has 0 batch axes"):
        free_bodies[0][0]
