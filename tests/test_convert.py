"""rigidjax.convert: scipy's Rotation and MuJoCo's free joint, checked against the libraries themselves.

The MuJoCo tests build a one-body model with a free joint and check what MuJoCo computes from the
converted coordinates: the body's orientation (xquat, xmat), the frames of the angular velocity
(mj_objectVelocity), and a torque-free motion integrated by MuJoCo against rigidjax's closed form."""

import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rigidjax as rj
from rigidjax import convert

RUNTIME = (ValueError, eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError)  # eager, and inside jit


def _random_quats(shape, seed=0):
    q = np.random.default_rng(seed).normal(size=shape + (4,))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _same_up_to_sign(a, b, atol):
    a, b = np.asarray(a), np.asarray(b)
    sign = np.sign(np.sum(a * b, axis=-1, keepdims=True))
    np.testing.assert_allclose(a, sign * b, rtol=0, atol=atol)


# --- scipy ---------------------------------------------------------------------------------------


def test_import_rigidjax_imports_neither_scipy_nor_mujoco():
    import subprocess

    code = "import sys, rigidjax; print('scipy' in sys.modules, 'mujoco' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_scalar_order_round_trip_and_values():
    q = _random_quats((5, 2))
    last = convert.quat_to_scalar_last(q)
    # The same numbers, reordered: round trips are exact.
    np.testing.assert_array_equal(np.asarray(last), q[..., [1, 2, 3, 0]])
    np.testing.assert_array_equal(np.asarray(convert.quat_from_scalar_last(last)), q)
    jitted = jax.jit(convert.quat_to_scalar_last)(q)
    np.testing.assert_array_equal(np.asarray(jitted), np.asarray(last))


def test_scipy_round_trip_and_matrix_agree():
    from scipy.spatial.transform import Rotation

    q = _random_quats((50,))
    rotation = convert.to_scipy_rotation(q)
    assert isinstance(rotation, Rotation) and len(rotation) == 50
    back = convert.from_scipy_rotation(rotation)
    assert back.shape == (50, 4) and back.dtype == jnp.float64
    _same_up_to_sign(back, q, 1e-15)
    np.testing.assert_allclose(
        rotation.as_matrix(), np.asarray(rj.kinematics.matrix_from_quat(q)), atol=1e-14
    )
    # The same action on vectors: body -> space.
    v = np.random.default_rng(1).normal(size=(50, 3))
    np.testing.assert_allclose(rotation.apply(v), np.asarray(rj.quat_rotate(q, v)), atol=1e-14)
    # And from scipy's side: a scipy rotation, through rigidjax, is the same rotation.
    r = Rotation.from_euler("ZXZ", [0.3, 1.1, -2.0])
    q1 = convert.from_scipy_rotation(r)
    assert q1.shape == (4,)
    np.testing.assert_allclose(np.asarray(rj.matrix_from_quat(q1)), r.as_matrix(), atol=1e-14)
    np.testing.assert_allclose(
        np.asarray(rj.quat_from_euler(np.array([0.3, 1.1, -2.0]), "zxz")), np.asarray(q1), atol=1e-14
    )
    assert convert.to_scipy_rotation(np.asarray(q1)).single


def test_scipy_batched_shapes_and_float32():
    q = _random_quats((3, 4))
    rotation = convert.to_scipy_rotation(q)
    assert rotation.as_quat().shape == (3, 4, 4)
    back = convert.from_scipy_rotation(rotation)
    assert back.shape == (3, 4, 4)
    _same_up_to_sign(back, q, 1e-15)
    q32 = q.astype(np.float32)
    back32 = convert.from_scipy_rotation(convert.to_scipy_rotation(q32), dtype=jnp.float32)
    assert back32.dtype == jnp.float32
    _same_up_to_sign(back32, q32, 1e-6)
    last32 = convert.quat_to_scalar_last(q32)
    assert last32.dtype == jnp.float32 and last32.shape == (3, 4, 4)


def test_scipy_bad_inputs_named():
    with pytest.raises(ValueError, match=r"q must have shape \(\.\.\., 4\)"):
        convert.to_scipy_rotation(np.ones(3))
    with pytest.raises(ValueError, match="q contains NaN"):
        convert.to_scipy_rotation(np.array([np.nan, 0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="q is not a unit quaternion"):
        convert.to_scipy_rotation(np.array([2.0, 0.0, 0.0, 0.0]))
    with pytest.raises(TypeError, match="rotation must be a scipy"):
        convert.from_scipy_rotation(np.array([1.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match=r"q must have shape \(\.\.\., 4\)"):
        convert.quat_to_scalar_last(np.ones((2, 5)))
    with pytest.raises(RUNTIME, match="quat_from_scalar_last: q is not a unit quaternion"):
        convert.quat_from_scalar_last(np.array([0.0, 0.0, 0.0, 1.5]))
    with pytest.raises(RUNTIME, match="quat_to_scalar_last: q contains NaN"):
        jax.jit(convert.quat_to_scalar_last)(np.array([np.inf, 0.0, 0.0, 1.0]))


# --- MuJoCo: array conventions -------------------------------------------------------------------


def test_mujoco_round_trip_batched_and_jit():
    q = _random_quats((6,))
    omega = np.random.default_rng(2).normal(size=(6, 3))
    position = np.arange(3.0)
    state = rj.State(omega, q)
    qpos, qvel = jax.jit(convert.to_mujoco_free_joint)(state, position)
    assert qpos.shape == (6, 7) and qvel.shape == (6, 6)
    np.testing.assert_array_equal(np.asarray(qpos[:, :3]), np.broadcast_to(position, (6, 3)))
    np.testing.assert_array_equal(np.asarray(qvel[:, :3]), np.zeros((6, 3)))
    np.testing.assert_array_equal(np.asarray(qvel[:, 3:]), omega)
    back, pos, vel = jax.jit(convert.from_mujoco_free_joint)(qpos, qvel)
    np.testing.assert_array_equal(np.asarray(back.orientation), q)
    np.testing.assert_array_equal(np.asarray(back.omega), omega)
    np.testing.assert_array_equal(np.asarray(pos), np.asarray(qpos[:, :3]))
    assert vel.shape == (6, 3)
    # vmap over bodies gives the same as the batched call.
    qpos_v, qvel_v = jax.vmap(convert.to_mujoco_free_joint, in_axes=(0, None))(state, position)
    np.testing.assert_array_equal(np.asarray(qpos_v), np.asarray(qpos))
    np.testing.assert_array_equal(np.asarray(qvel_v), np.asarray(qvel))
    # float32 is kept.
    s32 = rj.State(omega.astype(np.float32), q.astype(np.float32))
    qpos32, qvel32 = convert.to_mujoco_free_joint(s32)
    assert qpos32.dtype == jnp.float32 and qvel32.dtype == jnp.float32
    assert convert.from_mujoco_free_joint(qpos32, qvel32)[0].omega.dtype == jnp.float32


def test_mujoco_bad_inputs_named():
    with pytest.raises(ValueError, match="state.orientation is None"):
        convert.to_mujoco_free_joint(rj.State(np.ones(3)))
    with pytest.raises(ValueError, match=r"position must have shape \(\.\.\., 3\)"):
        convert.to_mujoco_free_joint(rj.State(np.ones(3), np.array([1.0, 0, 0, 0])), position=np.ones(2))
    with pytest.raises(ValueError, match=r"qpos must have shape \(\.\.\., 7\)"):
        convert.from_mujoco_free_joint(np.ones(6), np.ones(6))
    with pytest.raises(ValueError, match=r"qvel must have shape \(\.\.\., 6\)"):
        convert.from_mujoco_free_joint(np.ones(7), np.ones(7))
    with pytest.raises(RUNTIME, match="state.orientation is not a unit quaternion"):
        convert.to_mujoco_free_joint(rj.State(np.ones(3), np.array([2.0, 0, 0, 0])))
    with pytest.raises(RUNTIME, match="velocity contains NaN"):
        convert.to_mujoco_free_joint(
            rj.State(np.ones(3), np.array([1.0, 0, 0, 0])), velocity=np.full(3, np.nan)
        )
    with pytest.raises(RUNTIME, match="qpos.*not a unit quaternion"):
        convert.from_mujoco_free_joint(np.array([0, 0, 0, 1.0, 1.0, 0, 0]), np.zeros(6))
    with pytest.raises(RUNTIME, match="qvel contains NaN"):
        convert.from_mujoco_free_joint(np.array([0, 0, 0, 1.0, 0, 0, 0]), np.full(6, np.nan))


# --- MuJoCo itself -------------------------------------------------------------------------------

INERTIA = np.array([0.02, 0.035, 0.045])  # kg m^2, principal axes along the body's axes
MASS = 1.0


def _free_body_model(mujoco):
    xml = f"""
    <mujoco>
      <option gravity="0 0 0" integrator="RK4" timestep="1e-4"/>
      <worldbody>
        <body name="box">
          <freejoint/>
          <inertial pos="0 0 0" mass="{MASS}" diaginertia="{" ".join(str(float(i)) for i in INERTIA)}"/>
          <geom type="box" size="0.1 0.2 0.3" contype="0" conaffinity="0" mass="0"/>
        </body>
      </worldbody>
    </mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    np.testing.assert_allclose(model.body_inertia[1], INERTIA)
    np.testing.assert_allclose(model.body_iquat[1], [1, 0, 0, 0])  # inertial frame = body frame
    return model


def test_mujoco_orientation_and_angular_velocity_frames():
    mujoco = pytest.importorskip("mujoco")
    model = _free_body_model(mujoco)
    data = mujoco.MjData(model)
    q = _random_quats((), seed=3)
    omega = np.array([1.0, -2.0, 0.5])
    position, velocity = np.array([0.1, -0.2, 0.3]), np.array([0.4, 0.5, -0.6])
    qpos, qvel = convert.to_mujoco_free_joint(rj.State(omega, q), position, velocity)
    data.qpos[:], data.qvel[:] = np.asarray(qpos), np.asarray(qvel)
    mujoco.mj_forward(model, data)
    R = np.asarray(rj.kinematics.matrix_from_quat(q))
    _same_up_to_sign(data.xquat[1], q, 1e-15)
    np.testing.assert_allclose(data.xmat[1].reshape(3, 3), R, atol=1e-14)
    np.testing.assert_allclose(data.xpos[1], position, atol=1e-15)
    local, world = np.zeros(6), np.zeros(6)  # (angular, linear)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, 1, local, 1)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, 1, world, 0)
    # qvel's angular part is rigidjax's body-frame omega; in world components it is R omega.
    np.testing.assert_allclose(local[:3], omega, atol=1e-14)
    np.testing.assert_allclose(world[:3], R @ omega, atol=1e-14)
    # qvel's linear part is in world components.
    np.testing.assert_allclose(world[3:], velocity, atol=1e-14)
    np.testing.assert_allclose(local[3:], R.T @ velocity, atol=1e-14)
    # And back: MuJoCo's coordinates give the same state.
    state, pos, vel = convert.from_mujoco_free_joint(data.qpos, data.qvel)
    _same_up_to_sign(state.orientation, q, 1e-15)
    np.testing.assert_allclose(np.asarray(state.omega), omega, atol=0)
    np.testing.assert_allclose(np.asarray(pos), position, atol=0)
    np.testing.assert_allclose(np.asarray(vel), velocity, atol=0)


def test_mujoco_torque_free_motion_matches_closed_form():
    """MuJoCo's RK4 at dt = 1e-4 against rigidjax's closed form, through the converters."""
    mujoco = pytest.importorskip("mujoco")
    model = _free_body_model(mujoco)
    data = mujoco.MjData(model)
    omega0 = np.array([0.3, 4.0, 0.2])  # near the unstable intermediate axis: a sensitive test
    q0 = _random_quats((), seed=4)
    velocity = np.array([0.1, 0.0, -0.2])
    qpos, qvel = convert.to_mujoco_free_joint(rj.State(omega0, q0), velocity=velocity)
    data.qpos[:], data.qvel[:] = np.asarray(qpos), np.asarray(qvel)
    steps, samples = 2000, 4  # 0.2 s
    ts = [0.0]
    qpos_mj, qvel_mj = [data.qpos.copy()], [data.qvel.copy()]
    for _ in range(samples):
        mujoco.mj_step(model, data, nstep=steps // samples)
        ts.append(data.time)
        qpos_mj.append(data.qpos.copy())
        qvel_mj.append(data.qvel.copy())
    state_mj, pos_mj, vel_mj = convert.from_mujoco_free_joint(np.array(qpos_mj), np.array(qvel_mj))
    traj = rj.simulate(rj.FreeBody(INERTIA), rj.State(omega0, q0), np.array(ts), accuracy="exact")
    # RK4 at omega dt = 4e-4 is accurate to ~1e-14 here; the margin is for other MuJoCo versions.
    np.testing.assert_allclose(np.asarray(state_mj.omega), np.asarray(traj.omega), atol=1e-9)
    _same_up_to_sign(state_mj.orientation, traj.orientation, 1e-9)
    # The centre of mass moves uniformly in a straight line.
    np.testing.assert_allclose(np.asarray(pos_mj), np.array(ts)[:, None] * velocity, atol=1e-12)
    np.testing.assert_allclose(np.asarray(vel_mj), np.broadcast_to(velocity, (len(ts), 3)), atol=1e-12)
