"""Several processes on JAX's own runtime: two processes on this machine join one
``jax.distributed`` job (a localhost coordinator, CPU collectives), hold one half each of a global
batch sharded over the batch axis, and ``rigidjax.simulate`` integrates it across both; the gathered
trajectories are those of one process.

The workers are this file run as a script (``python tests/test_distributed.py --worker ...``); the
reference is computed in the test process from the same NumPy scene.
"""

import json
import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

N_BODIES = 16
CHUNK = 4  # 4 chunks: 2 per process (a batch of one chunk is not split)
TS = np.linspace(0.0, 1.0, 5)
TIMEOUT_S = 180


def _scene(n=N_BODIES):
    """``n`` distinct asymmetric heavy tops, tilted and spinning: NumPy float64 arrays."""
    rng = np.random.default_rng(7)
    inertia = np.array([1.0, 1.2, 0.5]) * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, (n, 3)))
    mass = 1.0 + 0.5 * rng.uniform(size=n)
    com = np.array([0.0, 0.0, 0.4]) + 0.05 * rng.normal(size=(n, 3))
    omega = np.array([0.5, -0.3, 8.0]) + rng.normal(size=(n, 3))
    tilt = 0.3 + 0.5 * rng.uniform(size=n)  # about body x
    q0 = np.stack([np.cos(tilt / 2), np.sin(tilt / 2), np.zeros(n), np.zeros(n)], axis=-1)
    return inertia, mass, com, omega, q0


def _worker(process_id, num_processes, port, out):
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=f"localhost:{port}",
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=60,
    )
    from jax.experimental import multihost_utils
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    import rigidjax as rj

    mesh = jax.make_mesh((jax.device_count(),), ("bodies",), axis_types=(AxisType.Auto,))
    rows = NamedSharding(mesh, P("bodies"))
    n = N_BODIES
    lo, hi = process_id * n // num_processes, (process_id + 1) * n // num_processes

    def global_array(x):  # this process passes only its own rows
        return jax.make_array_from_process_local_data(rows, x[lo:hi], x.shape)

    inertia, mass, com, omega, q0 = (global_array(x) for x in _scene())
    model = rj.HeavyTop(inertia, mass, com)
    traj = rj.simulate(model, rj.State(omega, q0), TS, chunk_size=CHUNK)
    gathered = {
        "omega": multihost_utils.process_allgather(traj.omega, tiled=True),
        "orientation": multihost_utils.process_allgather(traj.orientation, tiled=True),
        "success": multihost_utils.process_allgather(traj.success, tiled=True),
    }
    # The model's arrays are this process's rows: saving them would write half a scene. Refused, with
    # the recipe, which then saves the whole trajectory.
    try:
        traj.save(out + ".refused.npz")
        refusal = None
    except ValueError as err:
        refusal = str(err)
    whole = jax.tree.map(lambda x: multihost_utils.process_allgather(x, tiled=True), traj)
    if process_id == 0:
        whole.save(out + ".trajectory.npz")
    info = {
        "refusal": refusal,
        "process_index": jax.process_index(),
        "process_count": jax.process_count(),
        "device_count": jax.device_count(),
        "local_device_count": jax.local_device_count(),
        "local_rows": [[s.index[0].start, s.index[0].stop] for s in omega.addressable_shards],
        "num_chunks": int(np.size(traj.stats["num_steps"])),
    }
    np.savez(out, **gathered)
    with open(out + ".json", "w") as f:
        json.dump(info, f)
    jax.distributed.shutdown()


def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _run_workers(tmp_path, meanwhile, num_processes=2):
    """Starts the workers, calls ``meanwhile()``, waits for all the workers (none is left running) and
    returns ``meanwhile()``'s result and the workers' outputs; a failed or stuck worker fails the
    test with its output (stdout and stderr)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_ENABLE_X64="True")
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "xla_force_host_platform_device_count" not in f]
    env["XLA_FLAGS"] = " ".join(flags)  # one CPU device per process; the suite's compile flags kept
    port = _free_port()
    procs, outs, logs = [], [], []
    deadline = time.monotonic() + TIMEOUT_S
    try:
        for i in range(num_processes):
            out, log = str(tmp_path / f"process{i}.npz"), tmp_path / f"process{i}.log"
            cmd = [sys.executable, __file__, "--worker", str(i), str(num_processes), str(port), out]
            with open(log, "w") as f:  # a file, not a pipe: a full pipe would block the worker
                procs.append(subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT))
            outs.append(out)
            logs.append(log)
        local = meanwhile()
        while time.monotonic() < deadline:
            codes = [p.poll() for p in procs]
            if all(c == 0 for c in codes) or any(c not in (None, 0) for c in codes):
                break  # all done, or one failed: the others would wait for it until they time out
            time.sleep(0.1)
    finally:
        why = f"timed out after {TIMEOUT_S} s" if time.monotonic() >= deadline else "stopped by the test"
        status = [why if p.poll() is None else f"exit code {p.returncode}" for p in procs]
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()
    failed = [
        f"process {i} ({state}):\n{log.read_text()[-4000:]}"
        for i, (p, log, state) in enumerate(zip(procs, logs, status, strict=True))
        if p.returncode != 0
    ]
    if failed:
        pytest.fail("a worker failed or timed out:\n" + "\n".join(failed))
    results = []
    for out in outs:
        with np.load(out) as data:
            arrays = {k: data[k] for k in data.files}
        with open(out + ".json") as f:
            results.append((arrays, json.load(f)))
    return local, results


def _one_process():
    import jax.numpy as jnp

    import rigidjax as rj

    inertia, mass, com, omega, q0 = (jnp.asarray(x) for x in _scene())
    model = rj.HeavyTop(inertia, mass, com)
    traj = rj.simulate(model, rj.State(omega, q0), jnp.asarray(TS), chunk_size=CHUNK)
    return np.asarray(traj.omega), np.asarray(traj.orientation)


@pytest.mark.slow
def test_two_processes_equal_one_process(tmp_path):
    """Also: a trajectory whose scene is sharded over the processes is not saved from one process's
    rows (it was a raw JAX RuntimeError); gathered as the message says, it saves and loads whole."""
    import rigidjax as rj

    (omega_ref, q_ref), results = _run_workers(tmp_path, meanwhile=_one_process)
    for _, info in results:
        assert "model/inertia is sharded over the devices of several processes" in info["refusal"]
        assert "process_allgather" in info["refusal"]
    assert sorted(p.name for p in tmp_path.glob("*.npz")) == [
        "process0.npz",
        "process0.npz.trajectory.npz",
        "process1.npz",
    ]
    saved = rj.Trajectory.load(tmp_path / "process0.npz.trajectory.npz")
    assert saved.model.inertia.shape == (N_BODIES, 3)
    np.testing.assert_allclose(np.asarray(saved.omega), omega_ref, rtol=0, atol=1e-12)
    # The bodies are distinct, so a batch put together in the wrong order could not pass.
    swapped = np.roll(np.arange(N_BODIES), N_BODIES // 2)
    assert np.min(np.abs(omega_ref - omega_ref[swapped])[:, -1]) > 1e-3
    for process_id, (gathered, info) in enumerate(results):
        assert info["process_index"] == process_id
        assert info["process_count"] == 2 and info["device_count"] == 2 and info["local_device_count"] == 1
        half = N_BODIES // 2
        assert info["local_rows"] == [[process_id * half, (process_id + 1) * half]]
        assert info["num_chunks"] == N_BODIES // CHUNK
        assert gathered["omega"].shape == (N_BODIES, TS.size, 3)
        assert gathered["orientation"].shape == (N_BODIES, TS.size, 4)
        assert np.all(gathered["success"])
        np.testing.assert_allclose(gathered["omega"], omega_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(gathered["orientation"], q_ref, rtol=0, atol=1e-12)


if __name__ == "__main__" and sys.argv[1:2] == ["--worker"]:
    try:
        _worker(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5])
    except BaseException:
        import traceback

        traceback.print_exc()
        sys.stderr.flush()
        os._exit(1)  # not sys.exit: the runtime's shutdown at exit would wait for the other process
