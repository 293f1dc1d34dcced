"""``rigidjax.simulate`` across processes on JAX's own runtime (``jax.distributed``): one process
against two on the same batch.

Scene: the tennis-racket batch of ``_harness.py`` (N torque-free bodies near the intermediate axis,
identity orientation, T = 20 s), ``accuracy="balanced"``, float64, sampled at ``--samples`` times.

The launcher starts every case as fresh worker processes (``--worker``, one per process; two
processes join one job through ``jax.distributed.initialize`` with a coordinator on localhost and
CPU collectives over gloo, each process has one CPU device). With two processes the batch is a
global ``jax.Array`` sharded over its batch axis: each process builds only its half
(``jax.make_array_from_process_local_data``), ``simulate`` spreads whole chunks over the two
devices, and ``jax.experimental.multihost_utils.process_allgather`` brings the trajectories to every
process. Timing: a first call (trace + compile + run), then ``--repeats`` calls, each with
``block_until_ready``; run time is their median, compile time is first call - median. Cases
alternate (1, 2, 1, 2, ...) for ``--rounds`` rounds, because the load of a shared machine drifts.
The trajectories of one and two processes are compared.

With ``--two-devices`` a third case is one process with two CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=2``): the same split of the chunks over two
devices, without a second process, to tell the cost of the processes from that of the machine's load.

Usage: python benchmarks/distributed.py [--bodies 4096] [--samples 2] [--repeats 3] [--rounds 2]
       [--chunk-size 1024] [--two-devices] [--out results.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
T_END = 20.0


# ------------------------------------------------------------------------------ worker (one process)


def worker(process_id: int, num_processes: int, port: int, spec: dict, out: str) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    if num_processes > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(
            coordinator_address=f"localhost:{port}",
            num_processes=num_processes,
            process_id=process_id,
            initialization_timeout=120,
        )
    import numpy as np
    from _harness import reference_scene, timed_calls
    from jax.experimental import multihost_utils
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    import rigidjax as rj

    n = spec["bodies"]
    inertia, omega0, q0 = reference_scene(n)
    mesh = jax.make_mesh((jax.device_count(),), ("bodies",), axis_types=(AxisType.Auto,))
    rows = NamedSharding(mesh, P("bodies"))
    lo, hi = process_id * n // num_processes, (process_id + 1) * n // num_processes
    inertia, omega0, q0 = (
        jax.make_array_from_process_local_data(rows, x[lo:hi], x.shape) for x in (inertia, omega0, q0)
    )
    ts = np.linspace(0.0, T_END, spec["samples"])

    def call():
        return rj.simulate(rj.FreeBody(inertia), rj.State(omega0, q0), ts, chunk_size=spec["chunk_size"])

    traj, timing = timed_calls(call, spec["repeats"])
    omega = multihost_utils.process_allgather(traj.omega, tiled=True)
    orientation = multihost_utils.process_allgather(traj.orientation, tiled=True)
    result = dict(
        timing,
        processes=jax.process_count(),
        process_index=jax.process_index(),
        devices=jax.device_count(),
        local_devices=jax.local_device_count(),
        chunks=int(np.size(traj.stats["num_steps"])),
        chunk_size=int(traj.stats["chunk_size"]),
        all_success=bool(np.all(multihost_utils.process_allgather(traj.success, tiled=True))),
    )
    np.savez(out + ".npz", omega=omega, orientation=orientation)
    with open(out + ".json", "w") as f:
        json.dump(result, f)
    if num_processes > 1:
        jax.distributed.shutdown()


# ------------------------------------------------------------------------------------- launcher


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


CASES = {  # name: (processes, CPU devices per process)
    "1 process": (1, 1),
    "2 processes": (2, 1),
    "1 process, 2 devices": (1, 2),
}


def run_case(case: str, spec: dict, workdir: str, tag: str, timeout: float = 900.0) -> list[dict]:
    """Starts the case's workers, waits for them (none is left running) and returns their results
    (process 0 first); a failed worker raises with its output."""
    num_processes, devices = CASES[case]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    if devices > 1:
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    port = _free_port()
    procs, outs, logs = [], [], []
    deadline = time.monotonic() + timeout
    try:
        for i in range(num_processes):
            out, log = os.path.join(workdir, f"{tag}_p{i}"), os.path.join(workdir, f"{tag}_p{i}.log")
            cmd = [sys.executable, os.path.abspath(__file__), "--worker", str(i), str(num_processes)]
            cmd += [str(port), json.dumps(spec), out]
            with open(log, "w") as f:
                procs.append(subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT, cwd=HERE))
            outs.append(out)
            logs.append(log)
        while time.monotonic() < deadline:
            codes = [p.poll() for p in procs]
            if all(c == 0 for c in codes) or any(c not in (None, 0) for c in codes):
                break
            time.sleep(0.2)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()
    for i, (p, log) in enumerate(zip(procs, logs, strict=True)):
        if p.returncode != 0:
            with open(log) as f:
                raise RuntimeError(f"{case}: process {i} ended with {p.returncode}:\n{f.read()[-4000:]}")
    results = []
    for out in outs:
        with open(out + ".json") as f:
            results.append(json.load(f))
    return results


def _loads():
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bodies", type=int, default=4096, help="batch size (even), default 4096")
    parser.add_argument("--samples", type=int, default=2, help="sample times on [0, 20 s], default 2")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls after the first, default 3")
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds of the cases, default 2")
    parser.add_argument("--chunk-size", type=int, default=1024, help="bodies per chunk, default 1024")
    parser.add_argument(
        "--two-devices",
        action="store_true",
        help="also time one process with two CPU devices (XLA_FLAGS), the same split without processes",
    )
    parser.add_argument("--out", default=None, help="also write the results as JSON here")
    parser.add_argument(
        "--worker", nargs=5, metavar=("ID", "COUNT", "PORT", "SPEC", "OUT"), help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    if args.worker:
        process_id, count, port, spec, out = args.worker
        try:
            worker(int(process_id), int(count), int(port), json.loads(spec), out)
        except BaseException:
            import traceback

            traceback.print_exc()
            sys.stderr.flush()
            os._exit(1)  # not sys.exit: the runtime's shutdown at exit would wait for the other process
        return
    if args.bodies % 2:
        parser.error("--bodies must be even (the batch is split in two halves)")
    spec = {
        "bodies": args.bodies,
        "samples": args.samples,
        "repeats": args.repeats,
        "chunk_size": args.chunk_size,
    }
    chunks = -(-args.bodies // args.chunk_size)
    cases = list(CASES)[: 3 if args.two_devices else 2]

    import jax
    import numpy as np

    today = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    print(f"rigidjax.simulate on 1 and 2 processes (jax.distributed, CPU collectives: gloo), {today}")
    print(
        f"machine: {os.cpu_count()}-core CPU ({platform.machine()}), jax {jax.__version__}, "
        f"load at start {_loads()}"
    )
    print(
        f"scene: tennis-racket batch, {args.bodies} bodies, T = {T_END:g} s, {args.samples} samples, "
        f'"balanced", float64, chunk_size {args.chunk_size} ({chunks} chunk{"s" * (chunks > 1)})'
    )
    print(
        f"each process has one CPU device; with 2 processes on this {os.cpu_count()}-core machine "
        "each process gets at most half of the cores"
    )
    if chunks < 2:
        print("note: a batch of one chunk is not split, the two processes would both integrate all of it")
    rows = {case: [] for case in cases}
    with tempfile.TemporaryDirectory() as workdir:
        for r in range(args.rounds):
            for k, case in enumerate(cases):
                results = run_case(case, spec, workdir, f"r{r}_c{k}")
                rows[case].append(results)
                print(
                    f"  round {r + 1}, {case}: run {max(x['run_s'] for x in results):.3f} s "
                    f"(median of {args.repeats}), compile {max(x['compile_s'] for x in results):.1f} s",
                    flush=True,
                )
        one = np.load(os.path.join(workdir, "r0_c0_p0.npz"))
        diffs = {}  # per case, the largest over its processes
        for k, case in enumerate(cases[1:], start=1):
            for p in range(CASES[case][0]):
                other = np.load(os.path.join(workdir, f"r0_c{k}_p{p}.npz"))
                d = max(float(np.max(np.abs(one[key] - other[key]))) for key in ("omega", "orientation"))
                diffs[case] = max(diffs.get(case, 0.0), d)
    # Per round: the slower process; over rounds: the median.
    run = {case: statistics.median(max(x["run_s"] for x in res) for res in rows[case]) for case in cases}
    comp = {case: statistics.median(max(x["compile_s"] for x in res) for res in rows[case]) for case in cases}
    base = run[cases[0]]
    print()
    print("| case | devices | compile s | run s | speedup |")
    print("| --- | --- | --- | --- | --- |")
    for case in cases:
        devices = rows[case][0][0]["devices"]
        print(f"| {case} | {devices} | {comp[case]:.1f} | {run[case]:.3f} | {base / run[case]:.2f} |")
    print(
        f"(run s: median over {args.rounds} rounds of each round's median of {args.repeats} calls, "
        "of the slower process; compile s: first call - run)"
    )
    print(
        "trajectories (omega, orientation; every process's gathered copy) against 1 process: "
        + ", ".join(
            f"{name} " + ("bit-equal" if d == 0.0 else f"max |difference| {d:.2e}")
            for name, d in diffs.items()
        )
    )
    print(f"load at end {_loads()}")
    if args.out:
        record = {
            "spec": spec,
            "date": today,
            "jax": jax.__version__,
            "cpu_count": os.cpu_count(),
            "cases": rows,
            "run_s": run,
            "compile_s": comp,
            "max_abs_difference": diffs,
        }
        with open(args.out, "w") as f:
            json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
