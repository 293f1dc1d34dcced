"""``rigidjax.use_cpu_cores`` and ``--cpu-devices``: the CPU as several JAX devices. The reference
for the trajectories is the same batch integrated on this process's single device: splitting the
chunks over devices must not change a bit where both programs are compiled alike (the suite's
``--xla_backend_optimization_level=1``, tests/conftest.py; with XLA's default optimisation the
sharded program can round differently, which the guide states)."""

import json
import os
import subprocess
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_cli import _run

import rigidjax as rj


def _fresh_process(*args: str, **env) -> str:
    """Runs ``python *args`` in a new process (JAX not started, no device count chosen unless
    ``env`` chooses one), asserts it succeeded and returns its stdout."""
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if "device_count" not in f)
    environment = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu", **env}
    argv = [sys.executable, *args]
    done = subprocess.run(argv, env=environment, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return done.stdout


@pytest.mark.parametrize("count", [0, -2, 1.5, True, "2"])
def test_count_must_be_a_positive_integer(count, without_runtime_typecheck):
    with pytest.raises(ValueError, match="use_cpu_cores: count must be a positive integer"):
        rj.use_cpu_cores(count)


def test_a_count_beyond_any_cpu_is_refused_before_jax_is_asked():
    """10**30 was accepted, and JAX's backend then failed to start ("Unable to initialize backend
    'cpu'"); 10**11 made the command line end in a jaxlib traceback."""
    for count in (4097, 10**11, 10**30):
        with pytest.raises(ValueError, match=rf"count must be at most 4096 .*got {count}"):
            rj.use_cpu_cores(count)


def test_after_jax_started_only_its_count_is_accepted():
    jnp.zeros(1).block_until_ready()  # JAX has started in this process
    current = len(jax.devices("cpu"))
    assert rj.use_cpu_cores(current) == current
    with pytest.raises(RuntimeError, match=rf"already started .* {current} CPU device.*right after"):
        rj.use_cpu_cores(current + 1)
    assert len(jax.devices("cpu")) == current
    if rj._integrate.cores.available_cores() != current:  # the default asks for another count
        with pytest.raises(RuntimeError, match=r"use_cpu_cores\(\) \(\d+ devices\): JAX has already"):
            rj.use_cpu_cores()


def test_a_count_chosen_by_xla_flags_is_kept_and_every_core_is_the_default():
    code = "import rigidjax as rj, jax; n = rj.use_cpu_cores(); print(n, jax.device_count('cpu'))"
    out = _fresh_process("-c", code, XLA_FLAGS="--xla_force_host_platform_device_count=3")
    assert out.split() == ["3", "3"]
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert _fresh_process("-c", code).split() == [str(cores), str(cores)]


_BATCH = """
import numpy as np
rng = np.random.default_rng(7)
inertia = np.array([1.0, 2.0, 2.5]) * (1 + 0.05 * rng.uniform(-1, 1, (45, 3)))
omega = np.array([0.05, 4.0, 0.05]) + 0.01 * rng.normal(size=(45, 3))
q0 = np.tile([1.0, 0.0, 0.0, 0.0], (45, 1))
"""


def _batch():
    scope = {}
    exec(_BATCH, scope)
    return scope["inertia"], scope["omega"], scope["q0"]


@pytest.mark.slow
def test_two_devices_give_the_trajectories_of_one(tmp_path):
    """45 bodies in five chunks of nine: on two devices a sixth chunk of padding, the same chunks and
    bitwise the same trajectories as on one device, also when run in blocks to report progress."""
    path, gradient = tmp_path / "two.npy", tmp_path / "gradient.npy"
    code = f"""
import rigidjax as rj
assert rj.use_cpu_cores(2) == 2
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
assert jax.device_count() == 2, jax.devices()
{_BATCH}
model, state = rj.FreeBody(jnp.asarray(inertia)), rj.State(jnp.asarray(omega), jnp.asarray(q0))
traj = rj.simulate(model, state, jnp.linspace(0.0, 5.0, 6), chunk_size=10)
assert len(traj.omega.sharding.device_set) == 2  # the chunks ran on both devices
blocks = rj.simulate(model, state, jnp.linspace(0.0, 5.0, 6), chunk_size=10, progress=lambda *_: None)
assert np.array_equal(blocks.omega, traj.omega) and np.array_equal(blocks.orientation, traj.orientation)
np.save({str(path)!r}, np.concatenate([np.asarray(traj.omega), np.asarray(traj.orientation)], axis=-1))
# Reverse mode through chunks on both devices (it failed in the checkpointed adjoint's backward loop).
ts = jnp.linspace(0.0, 5.0, 6)
run = lambda w: rj.simulate(model, rj.State(w, state.orientation), ts, chunk_size=10)
loss = lambda w: jnp.sum(run(w).omega[:, -1] ** 2)
np.save({str(gradient)!r}, np.asarray(jax.grad(loss)(state.omega)))
"""
    _fresh_process("-c", code)
    inertia, omega, q0 = _batch()
    traj = rj.simulate(
        rj.FreeBody(jnp.asarray(inertia)),
        rj.State(jnp.asarray(omega), jnp.asarray(q0)),
        jnp.linspace(0.0, 5.0, 6),
        chunk_size=10,
    )
    assert int(traj.stats["chunk_size"]) == 9  # five chunks: one of padding on two devices
    one = np.concatenate([np.asarray(traj.omega), np.asarray(traj.orientation)], axis=-1)
    np.testing.assert_array_equal(np.load(path), one)
    model, state = rj.FreeBody(jnp.asarray(inertia)), rj.State(jnp.asarray(omega), jnp.asarray(q0))

    def loss(w):  # the adjoint the two devices' reverse mode takes by default
        ts, direct = jnp.linspace(0.0, 5.0, 6), diffrax.DirectAdjoint()
        traj = rj.simulate(model, rj.State(w, state.orientation), ts, chunk_size=10, adjoint=direct)
        return jnp.sum(traj.omega[:, -1] ** 2)

    got = np.load(gradient)
    np.testing.assert_allclose(got, np.asarray(jax.grad(loss)(state.omega)), rtol=1e-9, atol=1e-12)


def test_the_command_names_a_device_count_it_cannot_have(tmp_path):
    jnp.zeros(1).block_until_ready()
    wanted = len(jax.devices("cpu")) + 1
    out = str(tmp_path / "x.npz")
    argv = ["simulate", "--scene", "free", "-n", "4", "--cpu-devices", str(wanted), "--out", out]
    code, _, err = _run(argv)
    assert code == 2
    assert f"--cpu-devices {wanted}: use_cpu_cores({wanted}): JAX has already started" in err
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.slow
def test_the_command_on_two_devices_writes_what_one_device_writes(tmp_path):
    argv = ["simulate", "--scene", "free", "-n", "600", "--blocks", "2", "--duration", "2", "--samples", "5"]
    argv += ["--no-plot", "-q"]  # blocks of 300 bodies: two chunks each, one per device
    for devices in ("1", "2"):
        out = str(tmp_path / f"{devices}.npz")
        command = ["-m", "rigidjax._cli", *argv, "--cpu-devices", devices, "--out", out]
        _fresh_process(*command, RIGIDJAX_NO_COMPILATION_CACHE="1")
    with np.load(tmp_path / "1.npz") as one, np.load(tmp_path / "2.npz") as two:
        assert set(one.files) == set(two.files)
        for key in set(one.files) - {"summary_json"}:
            np.testing.assert_array_equal(one[key], two[key], err_msg=key)
        summaries = [json.loads(str(f["summary_json"])) for f in (one, two)]
    assert [s["devices"] for s in summaries] == [1, 2]
    timings = ("wall_time_s", "compile_time_s", "analysis_time_s", "body_steps_per_s", "devices")
    one, two = ({k: v for k, v in s.items() if k not in timings} for s in summaries)
    assert one == two and one["bodies"] == 600 and one["failed_bodies"] == 0


def test_inputs_on_an_explicit_mesh_axis_are_refused_by_name():
    """jax.make_mesh makes Explicit axes by default; inputs sharded over one stopped simulate with
    JAX's raw "Arguments to sort must be unsharded over the sorting dimension"."""
    code = """
import rigidjax as rj
rj.use_cpu_cores(2)
import jax, jax.numpy as jnp
from jax.sharding import NamedSharding, PartitionSpec as P
mesh = jax.make_mesh((2,), ("bodies",))
omega = jax.device_put(jnp.ones((8, 3)), NamedSharding(mesh, P("bodies")))
try:
    rj.simulate(rj.FreeBody(jnp.array([1.0, 2.0, 2.5])), rj.State(omega), jnp.linspace(0.0, 1.0, 3))
except ValueError as err:
    print(err)
"""
    out = _fresh_process("-c", code)
    assert out.startswith("simulate: state0.omega is sharded over the Explicit mesh axis 'bodies'")
    assert "AxisType.Auto" in out
