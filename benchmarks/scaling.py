"""How ``rigidjax.simulate`` scales: bodies, horizon, float32 vs float64, and sharding over devices.

Scene (the tennis-racket scene of ``_harness.py``, the same as ``batch_strategies.py``): N
torque-free bodies with principal moments I_k = (1, 2, 2.5) * (1 + 0.05 u_k), u_k ~ U(-1, 1)^3, then
omega0_k = (0.05, 4.0, 0.05) + 0.01 n_k, n_k ~ N(0, 1)^3, both from numpy default_rng(0); identity
orientation (1, 0, 0, 0); ts = [0, T]; ``rj.simulate(rj.FreeBody(I), rj.State(omega0, q0), ts,
accuracy=...)``; float64 (jax_enable_x64) unless stated. The bodies spin near the intermediate axis
and flip, so errors grow along the way.

Sections
  1 scaling   N = 1 ... 1e6 at T = 20, "balanced": compile time, run time, body-steps/s, peak memory.
  2 horizon   T = 2, 20, 200 at N = 1e4, "balanced".
  3 precision float32 and float64, every preset, N = 1e4, T = 20 and T = 2: relative omega error at
              t = T against a float64 reference ("precise" with rtol = 1e-12), and run time.
  4 sharding  N = 1e4 "balanced" with XLA_FLAGS=--xla_force_host_platform_device_count=2 and without
              (N = 1e4 with --quick too: with N <= chunk_size there is a single chunk and no sharding),
              in --shard-pairs alternating pairs of subprocesses (the load of a shared machine drifts).

Every case runs in a fresh subprocess (``--worker``), so that compile caches do not carry over and
the peak resident memory belongs to that case alone. In a worker:
  * baseline: VmHWM after importing jax and rigidjax and building the inputs as device arrays;
  * first call (trace + compile + run), then ``repeats`` timed calls, each ``block_until_ready``;
    run time is their median; compile time is reported as (first call - median run) and as jax's
    own trace / lower / backend-compile durations (``jax.monitoring``);
  * peak memory: ``ru_maxrss`` at the end of the timed calls (whole-process peak, compile included),
    and the peak of the timed calls alone (VmHWM reset through /proc/self/clear_refs before them);
  * body-steps = sum over chunks of stats['num_steps'] * stats['chunk_size'] (padding bodies of the
    last chunk included), per second of median run time;
  * for the scaling section, XLA's memory analysis of the compiled program (arguments, outputs,
    temporaries), from a separate jax.jit of the same call, after the measurements.

Usage: python benchmarks/scaling.py [--quick] [--repeats 3] [--out benchmarks/results/scaling.json]
       [--sections scaling,horizon,precision,sharding] [--shard-pairs 5] [--merge]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "results", "scaling.json")
SHARD_FLAG = "--xla_force_host_platform_device_count=2"


# ----------------------------------------------------------------------------- worker (one case)


def _largest_norm_error(traj) -> float:
    """``| |q| - 1 |`` at its largest: the integrators' statistic (before their output is normalised),
    or that of the samples where nothing normalises them (the closed form)."""
    import numpy as np

    error = traj.stats["quaternion_norm_error"]
    if error is None:
        error = np.abs(np.linalg.norm(np.asarray(traj.orientation), axis=-1) - 1)
    return float(np.max(np.asarray(error)))


def _proc_status():
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(("VmHWM", "VmRSS")):
                key, value = line.split(":")
                out[key] = int(value.split()[0]) * 1024  # kB -> bytes
    return out


def _reset_hwm():
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def worker(spec: dict) -> dict:
    import resource

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import rigidjax as rj

    events: dict[str, float] = {}

    def listener(name, duration, **kwargs):
        if name.startswith("/jax/core/compile/"):
            events[name] = events.get(name, 0.0) + duration

    jax.monitoring.register_event_duration_secs_listener(listener)

    n, t_end, accuracy = int(spec["n"]), float(spec["T"]), spec["accuracy"]
    dtype = {"float64": jnp.float64, "float32": jnp.float32}[spec["dtype"]]
    kwargs = {"accuracy": accuracy}
    if spec.get("rtol") is not None:
        kwargs["rtol"] = float(spec["rtol"])

    from _harness import reference_scene  # the tennis-racket scene, one definition

    inertia_np, omega_np, q_np = reference_scene(n)
    inertia = jnp.asarray(inertia_np, dtype)
    omega0 = jnp.asarray(omega_np, dtype)
    q0 = jnp.asarray(q_np, dtype)
    ts = jnp.asarray([0.0, t_end], dtype)
    jax.block_until_ready((inertia, omega0, q0, ts))
    del inertia_np, omega_np, q_np
    base = _proc_status()
    base_maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

    def call():
        traj = rj.simulate(rj.FreeBody(inertia), rj.State(omega0, q0), ts, **kwargs)
        return jax.block_until_ready(traj)

    load_before = os.getloadavg()
    t0 = time.perf_counter()
    traj = call()
    first_s = time.perf_counter() - t0
    after_first = _proc_status()
    compile_events = dict(events)

    num_steps = np.asarray(traj.stats["num_steps"])
    chunk_size = int(traj.stats["chunk_size"])
    out_bytes = int(traj.omega.nbytes + traj.orientation.nbytes + traj.success.nbytes)
    result = {
        "spec": spec,
        "devices": jax.device_count(),
        "out_dtype": str(traj.omega.dtype),
        "all_success": bool(np.all(np.asarray(traj.success))),
        "all_finite": bool(np.all(np.isfinite(np.asarray(traj.omega)))),
        "num_chunks": int(num_steps.size),
        "chunk_size": chunk_size,
        "num_steps_sum": int(num_steps.sum()),
        "num_steps_min": int(num_steps.min()),
        "num_steps_max": int(num_steps.max()),
        "body_steps": int(num_steps.sum()) * chunk_size,
        "output_bytes": out_bytes,
        "omega_bytes": int(traj.omega.nbytes),
        "orientation_bytes": int(traj.orientation.nbytes),
        "input_bytes": int(inertia.nbytes + omega0.nbytes + q0.nbytes),
        "quaternion_norm_error_max": _largest_norm_error(traj),
    }
    if spec.get("save"):
        np.savez(
            spec["save"],
            omega=np.asarray(traj.omega[:, -1], np.float64),
            orientation=np.asarray(traj.orientation[:, -1], np.float64),
        )
    del traj

    # Repeats: fewer when one call is slow (one repeat when a call takes more than ~7 min); each
    # row records its repeats.
    est_run = max(first_s - sum(compile_events.values()), 1e-6)
    repeats = int(spec["repeats"])
    budget = float(spec.get("repeat_budget_s", 420.0))
    if est_run * repeats > budget:
        repeats = max(1, int(budget // est_run))
    reset_ok = _reset_hwm()
    rss_before_runs = _proc_status()["VmRSS"]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        traj = call()
        times.append(time.perf_counter() - t0)
        del traj
    load_after = os.getloadavg()
    after_runs = _proc_status()
    end_maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    run_s = statistics.median(times)

    result.update(
        {
            "repeats": repeats,
            "times_s": times,
            "run_s": run_s,
            "first_call_s": first_s,
            "compile_s": first_s - run_s,
            "compile_events_s": compile_events,
            "body_steps_per_s": result["body_steps"] / run_s,
            "real_body_steps_per_s": n * result["num_steps_sum"] / result["num_chunks"] / run_s,
            "mem": {
                "baseline_hwm": base["VmHWM"],
                "baseline_maxrss": base_maxrss,
                "hwm_after_first_call": after_first["VmHWM"],
                "maxrss_end": end_maxrss,
                "peak_minus_baseline": end_maxrss - base_maxrss,
                "hwm_reset_ok": reset_ok,
                "rss_before_timed_runs": rss_before_runs,
                "hwm_timed_runs": after_runs["VmHWM"] if reset_ok else None,
                "timed_runs_peak_minus_rss_before": (after_runs["VmHWM"] - rss_before_runs)
                if reset_ok
                else None,
            },
            "loadavg_before": load_before,
            "loadavg_after": load_after,
        }
    )

    if spec.get("memory_analysis"):
        try:
            fn = jax.jit(
                lambda i, w, q: (lambda tr: (tr.omega, tr.orientation, tr.success, tr.stats["num_steps"]))(
                    rj.simulate(rj.FreeBody(i), rj.State(w, q), ts, **kwargs)
                )
            )
            m = fn.lower(inertia, omega0, q0).compile().memory_analysis()
            result["xla_memory"] = {
                "argument_bytes": int(m.argument_size_in_bytes),
                "output_bytes": int(m.output_size_in_bytes),
                "temp_bytes": int(m.temp_size_in_bytes),
                "alias_bytes": int(m.alias_size_in_bytes),
            }
        except Exception as e:  # diagnostic only
            result["xla_memory"] = {"error": repr(e)}
    return result


# ----------------------------------------------------------------------------- orchestrator


def run_case(spec: dict, *, shard: bool = False, timeout: float = 3000.0) -> dict:
    env = dict(os.environ)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "xla_force_host_platform_device_count" not in f]
    if shard:
        flags.append(SHARD_FLAG)
    if flags:
        env["XLA_FLAGS"] = " ".join(flags)
    else:
        env.pop("XLA_FLAGS", None)
    label = f"N={spec['n']} T={spec['T']} {spec['accuracy']} {spec['dtype']}" + (" shard=2" if shard else "")
    print(f"  running {label} ...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, os.path.abspath(__file__), "--worker", json.dumps(spec)],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    wall = time.perf_counter() - t0
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        sys.stderr.write(proc.stderr[-4000:])
        raise RuntimeError(f"worker failed ({label}), rc={proc.returncode}")
    res = json.loads(lines[-1][len("RESULT ") :])
    res["subprocess_wall_s"] = wall
    res["xla_flags"] = env.get("XLA_FLAGS", "")
    print(
        f"    run {res['run_s']:.4g} s (x{res['repeats']}), compile {res['compile_s']:.3g} s, "
        f"peak {res['mem']['maxrss_end'] / 2**20:.0f} MiB, wall {wall:.0f} s",
        file=sys.stderr,
        flush=True,
    )
    return res


def rel_errors(path, ref_path):
    import numpy as np

    a, r = np.load(path), np.load(ref_path)
    rel = np.linalg.norm(a["omega"] - r["omega"], axis=-1) / np.linalg.norm(r["omega"], axis=-1)
    # rotation angle between the final orientations (rad)
    # (vector part of conj(qr) x q, by atan2: arccos of the dot product has a ~1e-8 floor)
    q, qr = a["orientation"].T, r["orientation"].T
    w = qr[0] * q[0] + qr[1] * q[1] + qr[2] * q[2] + qr[3] * q[3]
    x = qr[0] * q[1] - qr[1] * q[0] - qr[2] * q[3] + qr[3] * q[2]
    y = qr[0] * q[2] + qr[1] * q[3] - qr[2] * q[0] - qr[3] * q[1]
    z = qr[0] * q[3] - qr[1] * q[2] + qr[2] * q[1] - qr[3] * q[0]
    ang = 2.0 * np.arctan2(np.sqrt(x * x + y * y + z * z), np.abs(w))
    return {
        "max_rel_omega": float(np.max(rel)),
        "median_rel_omega": float(np.median(rel)),
        "p99_rel_omega": float(np.quantile(rel, 0.99)),
        "frac_rel_omega_gt_1e-2": float(np.mean(rel > 1e-2)),
        "frac_rel_omega_gt_1e-1": float(np.mean(rel > 1e-1)),
        "max_angle_rad": float(np.max(ang)),
        "median_angle_rad": float(np.median(ang)),
    }


def mib(b):
    return b / 2**20


def fmt_table(headers, rows):
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) for i, h in enumerate(headers)]
    line = " | ".join(str(h).ljust(w) for h, w in zip(headers, widths, strict=True))
    sep = "-+-".join("-" * w for w in widths)
    body = "\n".join(" | ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows)
    return f"{line}\n{sep}\n{body}"


def plot_scaling(path: str) -> str:
    """Run time and memory against the number of bodies (the scaling section of ``path``), log-log,
    with the linear trend through N = 10^4; written beside ``path`` as ``<stem>.png``."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(path) as f:
        rows = json.load(f)["scaling"]
    n = np.array([r["spec"]["n"] for r in rows], float)
    run = np.array([r["run_s"] for r in rows])
    peak = np.array([r["mem"]["peak_minus_baseline"] / 2**20 for r in rows])
    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(9, 3.6))
    ax_t.loglog(n, run, "o-", label="simulate, balanced")
    anchor = int(np.argmin(np.abs(n - 1e4)))
    ax_t.loglog(n, run[anchor] * n / n[anchor], "k:", label="linear in N")
    ax_t.set(xlabel="bodies N", ylabel="run time (s, compile excluded)", title="Time, T = 20 s")
    ax_t.legend()
    ax_m.loglog(n, peak, "s-", color="C1")
    ax_m.set(xlabel="bodies N", ylabel="peak memory above baseline (MiB)", title="Memory (whole process)")
    for ax in (ax_t, ax_m):
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"rigidjax.simulate scaling, tennis-racket scene, {rows[0]['spec']['dtype']}, 2-core CPU")
    fig.tight_layout()
    out = os.path.splitext(path)[0] + ".png"
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--quick", action="store_true", help="smaller sizes (N <= 1e4; other sections at N = 1e3)"
    )
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--out", default=None, help=f"JSON output (default {DEFAULT_OUT}; --quick: scaling_quick.json)"
    )
    ap.add_argument("--sections", default="scaling,horizon,precision,sharding")
    ap.add_argument("--shard-pairs", type=int, default=5, help="alternating 1-device / 2-device runs")
    ap.add_argument("--merge", action="store_true", help="update the sections run in an existing --out JSON")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument(
        "--plot", default=None, metavar="JSON", help="only draw JSON's scaling plot (PNG beside it)"
    )
    a = ap.parse_args()

    if a.plot is not None:
        print(plot_scaling(a.plot))
        return

    if a.worker is not None:
        print("RESULT " + json.dumps(worker(json.loads(a.worker))), flush=True)
        return

    out = a.out or (os.path.join(HERE, "results", "scaling_quick.json") if a.quick else DEFAULT_OUT)
    sections = set(a.sections.split(","))
    ns = [1, 100, 1000, 10_000] if a.quick else [1, 100, 1000, 10_000, 100_000, 1_000_000]
    n_other = 1000 if a.quick else 10_000
    n_shard = 10_000  # also with --quick: at N <= chunk_size (1024) there is one chunk, nothing to shard
    reps = a.repeats

    import jax

    t_start = time.perf_counter()
    results = {
        "meta": {
            "script": "benchmarks/scaling.py",
            "argv": sys.argv[1:],
            "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "jax": jax.__version__,
            "cpu_count": os.cpu_count(),
            "loadavg_start": os.getloadavg(),
            "scene": "tennis-racket scene: I=(1,2,2.5)(1+0.05u), omega0=(0.05,4,0.05)+0.01n, rng(0), "
            "q0=identity",
            "notes": "medians of the timed repeats; compile_s = first call - median run; "
            "memory in bytes; body_steps counts padding bodies of the last chunk",
        }
    }
    tmp = tempfile.mkdtemp(prefix="rj_scaling_")

    def spec(n, T, accuracy="balanced", dtype="float64", **kw):
        return {"n": n, "T": T, "accuracy": accuracy, "dtype": dtype, "repeats": reps, **kw}

    # 1. scaling in N
    if "scaling" in sections:
        print("1. scaling in N (T = 20, balanced, float64)", file=sys.stderr)
        results["scaling"] = [run_case(spec(n, 20.0, memory_analysis=True)) for n in ns]

    # 2. horizon
    if "horizon" in sections:
        print(f"2. horizon (N = {n_other}, balanced, float64)", file=sys.stderr)
        results["horizon"] = [run_case(spec(n_other, T)) for T in (2.0, 20.0, 200.0)]

    # 3. float32 vs float64
    if "precision" in sections:
        print(f"3. float32 vs float64 (N = {n_other})", file=sys.stderr)
        prec = {"reference": {}, "rows": []}
        for T in (20.0, 2.0):
            ref_path = os.path.join(tmp, f"ref_T{T:g}.npz")
            ref = run_case({**spec(n_other, T, "precise", rtol=1e-12, save=ref_path), "repeats": 1})
            prec["reference"][f"T={T:g}"] = ref
            for dtype in ("float64", "float32"):
                for acc in ("fast", "balanced", "precise"):
                    path = os.path.join(tmp, f"{dtype}_{acc}_T{T:g}.npz")
                    r = run_case(spec(n_other, T, acc, dtype, save=path))
                    r["errors"] = rel_errors(path, ref_path)
                    prec["rows"].append(r)
        results["precision"] = prec

    # 4. sharding over 2 host devices
    if "sharding" in sections:
        print(f"4. sharding (N = {n_shard}, balanced, float64)", file=sys.stderr)
        import numpy as np

        # The two settings alternate in pairs of subprocesses: on a shared 2-core machine the load
        # changes within a minute, and two devices need both cores, so one pair is not enough.
        pairs = []
        for k in range(a.shard_pairs):
            p1, p2 = os.path.join(tmp, f"shard1_{k}.npz"), os.path.join(tmp, f"shard2_{k}.npz")
            one = run_case(spec(n_shard, 20.0, save=p1))
            two = run_case(spec(n_shard, 20.0, save=p2), shard=True)
            x1, x2 = np.load(p1), np.load(p2)
            pairs.append(
                {
                    "one_device": one,
                    "two_devices": two,
                    "ratio_1dev_over_2dev": one["run_s"] / two["run_s"],
                    "max_abs_diff_omega": float(np.max(np.abs(x1["omega"] - x2["omega"]))),
                    "max_abs_diff_orientation": float(np.max(np.abs(x1["orientation"] - x2["orientation"]))),
                    "bitwise_identical": bool(
                        np.array_equal(x1["omega"], x2["omega"])
                        and np.array_equal(x1["orientation"], x2["orientation"])
                    ),
                }
            )
        results["sharding"] = {
            "n": n_shard,
            "pairs": pairs,
            "ratios_1dev_over_2dev": [q["ratio_1dev_over_2dev"] for q in pairs],
            "median_ratio_1dev_over_2dev": statistics.median(q["ratio_1dev_over_2dev"] for q in pairs),
            "max_abs_diff_omega": max(q["max_abs_diff_omega"] for q in pairs),
            "max_abs_diff_orientation": max(q["max_abs_diff_orientation"] for q in pairs),
            "bitwise_identical": all(q["bitwise_identical"] for q in pairs),
        }

    results["meta"]["total_wall_s"] = time.perf_counter() - t_start
    results["meta"]["loadavg_end"] = os.getloadavg()
    if a.merge and os.path.exists(out):
        with open(out) as f:
            merged = json.load(f)
        merged.setdefault("meta_runs", []).append(results["meta"])
        merged.update({k: v for k, v in results.items() if k != "meta"})
        results = merged
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out, "w") as f:
        json.dump(results, f, indent=1)

    if "scaling" in results:
        print("plot:", plot_scaling(out))

    # ------------------------------------------------------------------ tables
    if "scaling" in results:
        rows = []
        for r in results["scaling"]:
            m = r["mem"]
            xm = r.get("xla_memory", {})
            rows.append(
                [
                    r["spec"]["n"],
                    f"{r['compile_s']:.2f}",
                    f"{r['run_s']:.4g}",
                    r["repeats"],
                    f"{r['num_steps_min']}-{r['num_steps_max']}",
                    f"{r['body_steps_per_s']:.3g}",
                    f"{mib(m['baseline_maxrss']):.0f}",
                    f"{mib(m['maxrss_end']):.0f}",
                    f"{mib(m['peak_minus_baseline']):.0f}",
                    f"{mib(m['timed_runs_peak_minus_rss_before']):.0f}"
                    if m["timed_runs_peak_minus_rss_before"] is not None
                    else "-",
                    f"{mib(r['output_bytes']):.2f}",
                    f"{mib(xm['temp_bytes']):.1f}" if "temp_bytes" in xm else "-",
                ]
            )
        print("\n1. Scaling in N (T = 20, balanced, float64); memory in MiB")
        print(
            fmt_table(
                [
                    "N",
                    "compile s",
                    "run s",
                    "reps",
                    "steps/chunk",
                    "body-steps/s",
                    "baseline",
                    "peak",
                    "peak-base",
                    "run-only peak",
                    "output",
                    "XLA temp",
                ],
                rows,
            )
        )
    if "horizon" in results:
        rows = [
            [
                r["spec"]["T"],
                f"{r['compile_s']:.2f}",
                f"{r['run_s']:.4g}",
                f"{r['num_steps_min']}-{r['num_steps_max']}",
                f"{r['body_steps_per_s']:.3g}",
                f"{mib(r['mem']['maxrss_end']):.0f}",
            ]
            for r in results["horizon"]
        ]
        print(f"\n2. Horizon (N = {n_other}, balanced, float64)")
        print(fmt_table(["T", "compile s", "run s", "steps/chunk", "body-steps/s", "peak MiB"], rows))
    if "precision" in results:
        rows = []
        for r in results["precision"]["rows"]:
            e = r["errors"]
            rows.append(
                [
                    r["spec"]["T"],
                    r["spec"]["dtype"],
                    r["spec"]["accuracy"],
                    f"{r['run_s']:.4g}",
                    f"{r['num_steps_min']}-{r['num_steps_max']}",
                    f"{e['max_rel_omega']:.2g}",
                    f"{e['median_rel_omega']:.2g}",
                    f"{e['p99_rel_omega']:.2g}",
                    f"{e['frac_rel_omega_gt_1e-2']:.3g}",
                    f"{e['max_angle_rad']:.2g}",
                    str(r["all_success"]),
                ]
            )
        print(f"\n3. float32 vs float64 (N = {n_other}); errors at t = T vs float64 precise rtol 1e-12")
        print(
            fmt_table(
                [
                    "T",
                    "dtype",
                    "preset",
                    "run s",
                    "steps/chunk",
                    "max rel w",
                    "median rel w",
                    "p99 rel w",
                    "frac>1e-2",
                    "max angle",
                    "success",
                ],
                rows,
            )
        )
        for k, ref in results["precision"]["reference"].items():
            print(
                f"   reference {k}: run {ref['run_s']:.3g} s, "
                f"steps/chunk {ref['num_steps_min']}-{ref['num_steps_max']}"
            )
    if "sharding" in results:
        s = results["sharding"]
        rows = []
        for k, q in enumerate(s["pairs"]):
            for key in ("one_device", "two_devices"):
                r = q[key]
                rows.append(
                    [
                        k,
                        r["devices"],
                        f"{r['compile_s']:.2f}",
                        f"{r['run_s']:.4g}",
                        " ".join(f"{t:.3g}" for t in r["times_s"]),
                        f"{r['loadavg_before'][0]:.1f}",
                        f"{q['ratio_1dev_over_2dev']:.3g}" if key == "two_devices" else "",
                    ]
                )
        print(f"\n4. Sharding (N = {s['n']}, T = 20, balanced, float64), alternating pairs of subprocesses")
        print(
            fmt_table(
                ["pair", "devices", "compile s", "run s", "times s", "load 1 min", "ratio 1/2 dev"], rows
            )
        )
        print(
            f"   median ratio 1-device / 2-device run time: {s['median_ratio_1dev_over_2dev']:.3g} "
            f"(pairs: {' '.join(f'{x:.3g}' for x in s['ratios_1dev_over_2dev'])}); "
            f"max |diff| omega {s['max_abs_diff_omega']:.3g}, "
            f"orientation {s['max_abs_diff_orientation']:.3g}; "
            f"bitwise identical: {s['bitwise_identical']}"
        )
    print(f"\nwrote {out} (this run {time.perf_counter() - t_start:.0f} s)")


if __name__ == "__main__":
    main()
