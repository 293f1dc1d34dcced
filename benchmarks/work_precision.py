"""Work-precision benchmark: wall time against error for every way of integrating the tennis-racket scene.

Scene: N torque-free bodies, principal moments I_k = (1, 2, 2.5) (1 + 0.05 u_k),
u_k ~ U(-1, 1)^3, then omega0_k = (0.05, 4, 0.05) + 0.01 n_k, n_k ~ N(0, 1)^3, both from
numpy default_rng(0); identity orientation; T = 20 s (several tennis-racket flips).

Reference: the float64 closed form (``simulate(accuracy="exact")``) for every body; the bodies
closest to the separatrix and a random sample are re-integrated in extended precision (Taylor
series, 80-bit long double) and those values replace the closed form there; scipy ``solve_ivp``
DOP853 at rtol = atol = 1e-13 on a subset of those is compared with both.

Methods, side by side in one run (float64 unless stated): the accuracy presets; diffrax Tsit5,
Dopri5, Dopri8 through ``simulate`` over a tolerance sweep; hand-written fixed-step RK4 over the
whole batch, state (7, N); the Lie-Poisson splitting (orders 2 and 4) over a step sweep; RKMK at
fixed steps; the closed form; the user-written ``jax.vmap`` of ``diffeqsolve(Tsit5(),
PIDController)``; scipy ``solve_ivp`` per body (on a subset; time scaled to N); MuJoCo if installed;
float32 presets, closed form and RK4.

Errors at t = T (relative omega, orientation angle, relative energy drift; max and median over
bodies), run time = median of ``--repeats`` rounds after a first call (compile reported apart),
``block_until_ready`` on each call. Rounds are interleaved round-robin over methods; a round of a
method under 50 ms is the median of its back-to-back calls over ~0.2 s.

Usage:
    python benchmarks/work_precision.py                 # N = 1e4, every method (~7-8 min, loaded 2 cores)
    python benchmarks/work_precision.py --quick --n 1000
Writes benchmarks/results/work_precision.{json,md,png} (``--out-prefix`` to change).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import _harness as B  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_PREFIX = os.path.join(HERE, "results", "work_precision")


def _euler_rhs(inertia):
    i1, i2, i3 = inertia
    c1, c2, c3 = (i2 - i3) / i1, (i3 - i1) / i2, (i1 - i2) / i3

    def rhs(t, y):
        w1, w2, w3, q0, q1, q2, q3 = y
        return np.array(
            [
                c1 * w2 * w3,
                c2 * w3 * w1,
                c3 * w1 * w2,
                0.5 * (-q1 * w1 - q2 * w2 - q3 * w3),
                0.5 * (q0 * w1 + q2 * w3 - q3 * w2),
                0.5 * (q0 * w2 - q1 * w3 + q3 * w1),
                0.5 * (q0 * w3 + q1 * w2 - q2 * w1),
            ]
        )

    return rhs


def scipy_solve(scene, index, method, rtol, atol):
    """scipy solve_ivp per body (what a NumPy user writes); omega(T) (k, 3), q(T) (k, 4)."""
    from scipy.integrate import solve_ivp

    inertia, omega0, q0 = scene
    out = np.empty((len(index), 7))
    for k, i in enumerate(index):
        y0 = np.concatenate([omega0[i], q0[i]])
        sol = solve_ivp(_euler_rhs(inertia[i]), (0.0, B.T_END), y0, method=method, rtol=rtol, atol=atol)
        out[k] = sol.y[:, -1]
    return out[:, :3], out[:, 3:]


def scipy_methods(scene, index, quick, note):
    settings = [("RK45", 1e-6), ("DOP853", 1e-8)] + ([] if quick else [("DOP853", 1e-10)])
    return [
        B.Method(
            f"scipy solve_ivp {meth} per body",
            f"rtol={r:g}",
            lambda meth=meth, r=r: scipy_solve(scene, index, meth, r, r),
            f"scipy-{meth}-{r}",
            kind="peer",
            subset=index,
            subset_note=note,
        )
        for meth, r in settings
    ]


def _mujoco_solver(scene, integrator, dt):
    """All N bodies as free joints of ONE MuJoCo model (no geoms, gravity off): omega(T), q(T).

    MuJoCo's free-joint angular velocity (qvel[3:6]) is in body axes and its quaternion is scalar
    first, body to world: the same conventions as rigidjax (checked against the closed form to 1e-12
    before this benchmark was written). The model is built on the first call (counted as compile)."""
    import mujoco

    inertia, omega0, q0 = scene
    n_steps = int(round(B.T_END / dt))
    cache = {}

    def run():
        if "model" not in cache:
            bodies = "".join(
                '<body><freejoint/><inertial pos="0 0 0" mass="1" '
                f'diaginertia="{a:.17g} {b:.17g} {c:.17g}"/></body>'
                for a, b, c in inertia
            )
            xml = (
                '<mujoco><size memory="1G"/>'  # MuJoCo's default arena is too small for 1e4 bodies
                f'<option gravity="0 0 0" integrator="{integrator}" timestep="{dt:.17g}"/>'
                f"<worldbody>{bodies}</worldbody></mujoco>"
            )
            cache["model"] = mujoco.MjModel.from_xml_string(xml)
        model = cache["model"]
        data = mujoco.MjData(model)
        qpos = data.qpos.reshape(-1, 7)
        qvel = data.qvel.reshape(-1, 6)
        qpos[:, 3:] = q0
        qvel[:, 3:] = omega0
        for _ in range(n_steps):
            mujoco.mj_step(model, data)
        state_q = data.qpos.reshape(-1, 7)[:, 3:].copy()
        state_w = data.qvel.reshape(-1, 6)[:, 3:].copy()
        return state_w, state_q

    return run


def mujoco_methods(scene, quick):
    """MuJoCo free bodies (gravity off), RK4 and Euler; [] with a note when it is not installed."""
    try:
        import mujoco
    except ImportError:
        return [], "mujoco is not installed (optional: pip install mujoco, the bench extra); skipped"
    settings = [("RK4", 0.01), ("Euler", 0.01)] + ([] if quick else [("RK4", 0.0025)])
    methods = [
        B.Method(
            f"MuJoCo {integrator} (all bodies in one model)",
            f"dt={dt:g}",
            _mujoco_solver(scene, integrator, dt),
            f"mujoco-{integrator}-{dt}",
            kind="peer",
        )
        for integrator, dt in settings
    ]
    return methods, f"mujoco {mujoco.__version__}: {', '.join(f'{i} dt={d:g}' for i, d in settings)}"


def check_reference(scene, checked, omega_ref, q_ref, omega_cf, q_cf, n_scipy):
    """scipy DOP853 rtol = atol = 1e-13 on ``n_scipy`` of the Taylor-checked bodies (half the most
    sensitive, half random) against the Taylor solution and the float64 closed form."""
    s = np.abs(B.separatrix_distance(scene[0], scene[1]))[checked]
    by_s = checked[np.argsort(s)]
    rng = np.random.default_rng(2)
    half = n_scipy // 2
    idx = np.unique(np.concatenate([by_s[:half], rng.choice(by_s[half:], n_scipy - half, replace=False)]))
    t0 = time.perf_counter()
    w, q = scipy_solve(scene, idx, "DOP853", 1e-13, 1e-13)
    elapsed = time.perf_counter() - t0
    e_t = B.body_errors(scene[0][idx], scene[1][idx], w, q, omega_ref[idx], q_ref[idx])
    e_c = B.body_errors(scene[0][idx], scene[1][idx], w, q, omega_cf[idx], q_cf[idx])
    return {
        "n_bodies": int(idx.size),
        "run_s": elapsed,
        "dop853_vs_taylor_max_rel_omega": float(e_t["rel_omega"].max()),
        "dop853_vs_taylor_median_rel_omega": float(np.median(e_t["rel_omega"])),
        "dop853_vs_taylor_max_angle": float(e_t["angle"].max()),
        "dop853_vs_closed_form_max_rel_omega": float(e_c["rel_omega"].max()),
        "dop853_vs_closed_form_median_rel_omega": float(np.median(e_c["rel_omega"])),
        "dop853_vs_closed_form_max_angle": float(e_c["angle"].max()),
    }


def plot(rows, path, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(16, 6.5), sharey=True)
    families = {}
    for r in rows:  # one curve per family; single-point variants of a preset get their own marker
        name = r["family"] + (f", {r['setting']}" if r["setting"] in ("chunk_size=N", "omega only") else "")
        families.setdefault((name, r["dtype"]), []).append(r)
    colors = [plt.get_cmap("tab20")(i) for i in range(20)] + [plt.get_cmap("Dark2")(i) for i in range(8)]
    for k, ((family, dtype), rs) in enumerate(families.items()):
        rs = sorted(rs, key=lambda r: r["run_s"])
        style = dict(
            color=colors[k % len(colors)],
            marker="x" if dtype != "float64" else ("s" if rs[0]["kind"] == "peer" else "o"),
            ls="-" if dtype == "float64" else ":",
            label=f"{family}" + ("" if dtype == "float64" else " (float32)"),
        )
        for ax, key in zip(axes, ("max_rel_omega", "median_rel_omega"), strict=True):
            errs = [max(r[key], 1e-17) for r in rs]
            ax.plot(errs, [r["run_s"] for r in rs], **style)
    for ax, what in zip(axes, ("max", "median"), strict=True):
        ax.set(xscale="log", yscale="log", xlabel=f"{what} relative omega error at t = T over bodies")
        ax.grid(True, which="both", lw=0.3)
    axes[0].set_ylabel("run time, s (median, compile excluded)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 0.8, 1))
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="center right")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_reports(meta, rows, targets, prefix, no_plot=False):
    """PREFIX.md (table and targets) and PREFIX.png (work-precision plot) from the results."""
    load = f"load {meta['loadavg_start'][0]:.1f} -> {meta['loadavg_end'][0]:.1f} on {meta['cpu_count']} CPUs"
    with open(prefix + ".md", "w") as fh:
        fh.write(
            f"Work-precision, tennis-racket scene, N = {meta['n']}, T = {meta['T']:g} s, "
            f"{meta['devices'][0]}, jax {meta['jax']} (`{meta['command']}`; {load})\n\n"
            + B.format_table(rows)
            + "\n\nTargets:\n\n"
        )
        fh.write("\n".join(f"- {line}" for line in B.format_targets(targets).splitlines()) + "\n")
    if not no_plot:
        try:
            scene = f"tennis-racket scene, N = {meta['n']}, T = 20 s"
            title = f"Work-precision, {scene}, {meta['devices'][0]} ({load})"
            plot(rows, prefix + ".png", title)
        except ImportError:
            print("matplotlib is not installed: no plot", file=sys.stderr)


README = os.path.join(os.path.dirname(HERE), "docs", "guides", "accuracy.md")
README_MARKERS = ("<!-- work-precision-table -->", "<!-- /work-precision-table -->")

# (label, family prefix, setting or None for any, dtype) of the rows the accuracy guide shows.
README_ROWS = [
    ('`simulate` "fast"', "simulate 'fast'", "preset", "float64"),
    ('`simulate` "balanced"', "simulate 'balanced'", "preset", "float64"),
    ('`simulate` "precise"', "simulate 'precise'", "preset", "float64"),
    ('`simulate` "exact" (closed form, ω and q)', "simulate 'exact'", "-", "float64"),
    ('`simulate` "exact", ω only', "simulate 'exact'", "omega only", "float64"),
    ("`simulate(solver=Dopri8(), rtol=1e-6)`", "simulate solver=Dopri8", "rtol=1e-06", "float64"),
    ("hand-written RK4 (7, N), dt 0.01", "hand RK4", "dt=0.01", "float64"),
    ("hand-written RK4 (7, N), dt 0.0025", "hand RK4", "dt=0.0025", "float64"),
    ("`jax.vmap(diffeqsolve(Tsit5, PID))`, rtol 1e-6", "vmap diffeqsolve", "rtol=1e-06", "float64"),
    ("`jax.vmap(diffeqsolve(Tsit5, PID))`, rtol 1e-8", "vmap diffeqsolve", "rtol=1e-08", "float64"),
    ("`jax.vmap(diffeqsolve(Tsit5, PID))`, rtol 1e-10", "vmap diffeqsolve", "rtol=1e-10", "float64"),
    ("scipy `solve_ivp` DOP853 per body, rtol 1e-10", "scipy solve_ivp DOP853", "rtol=1e-10", "float64"),
    ("MuJoCo RK4, dt 0.01", "MuJoCo RK4", "dt=0.01", "float64"),
    ("MuJoCo RK4, dt 0.0025", "MuJoCo RK4", "dt=0.0025", "float64"),
    ("MuJoCo Euler, dt 0.01", "MuJoCo Euler", "dt=0.01", "float64"),
    ('float32 `simulate` "balanced"', "simulate 'balanced'", "preset", "float32"),
    ('float32 `simulate` "exact"', "simulate 'exact'", "-", "float32"),
    ("float32 hand RK4, dt 0.01", "hand RK4", "dt=0.01", "float32"),
    ("float32 `jax.vmap(diffeqsolve(Tsit5, PID))`, rtol 1e-6", "vmap diffeqsolve", "rtol=1e-06", "float32"),
]


def readme_section(meta, rows, targets) -> str:
    """The key rows and the targets, as the accuracy guide shows them (between README_MARKERS)."""
    load = f"load {meta['loadavg_start'][0]:.1f} -> {meta['loadavg_end'][0]:.1f}"
    lines = [
        f"Measured by `{meta['command']}` ({meta['devices'][0]}, {meta['cpu_count']} CPUs, {load}, "
        f"jax {meta['jax']}); median of {meta['repeats']} rounds (under 50 ms: each round the median of "
        f"calls over ~0.2 s), compile excluded. Every row and column: "
        "`benchmarks/results/work_precision.md`.",
        "",
        "| method | run s | compile s | max rel ω err | median rel ω err | max angle err rad |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    any_scaled = False
    for label, family, setting, dtype in README_ROWS:
        match = [
            r
            for r in rows
            if r["family"].startswith(family) and r["dtype"] == dtype and setting in (None, r["setting"])
        ]
        if not match:
            continue
        r = match[0]
        scaled = "" if r["time_scale"] == 1 else " ¹"
        any_scaled = any_scaled or bool(scaled)
        # None or ~0: the program was compiled by an earlier row (a new rtol is a traced value).
        compile_s = "(shared)" if r["compile_s"] is None or r["compile_s"] < 0.1 else f"{r['compile_s']:.1f}"
        angle = "-" if r["max_angle"] is None else f"{r['max_angle']:.1e}"
        lines.append(
            f"| {label} | {r['run_s']:.3g}{scaled} | {compile_s} | {r['max_rel_omega']:.1e} | "
            f"{r['median_rel_omega']:.1e} | {angle} |"
        )
    if any_scaled:
        lines += ["", "¹ run on a subset of the bodies (the most sensitive included), time scaled to N."]
    lines += ["", "Performance targets, as the script evaluates them (float64, this run):", ""]
    for t in targets:
        flag = {True: "**met**", False: "**not met**", None: "n/a"}[t["met"]]
        lines.append(f"- {flag} — {t['target']}: {t['text']}")
    return "\n".join(lines)


def update_readme(meta, rows, targets, path=README):
    with open(path) as fh:
        text = fh.read()
    start, end = README_MARKERS
    if start not in text or end not in text:
        print(f"{path} has no {start} ... {end} markers: table not updated", file=sys.stderr)
        return
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    with open(path, "w") as fh:
        fh.write(head + start + "\n" + readme_section(meta, rows, targets) + "\n" + end + tail)
    print(f"updated the table in {path}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=B.positive_int, default=10_000, help="number of bodies")
    p.add_argument("--quick", action="store_true", help="fewer sweep points (development)")
    p.add_argument("--repeats", type=B.positive_int, default=3, help="timed calls per method after the first")
    p.add_argument(
        "--only",
        type=B.names_from((*B.METHOD_KEYS, "scipy", "mujoco")),
        default=None,
        help=f"comma-separated subset of {','.join(B.METHOD_KEYS)},scipy,mujoco",
    )
    p.add_argument("--taylor-sensitive", type=int, default=200, help="bodies nearest the separatrix redone")
    p.add_argument("--taylor-random", type=int, default=200, help="random other bodies redone")
    p.add_argument("--scipy-ref-bodies", type=int, default=20, help="DOP853 1e-13 cross-check bodies")
    p.add_argument("--scipy-bodies", type=int, default=20, help="bodies for the scipy per-body peers")
    p.add_argument("--out-prefix", default=DEFAULT_PREFIX, help="writes PREFIX.json, PREFIX.md, PREFIX.png")
    p.add_argument("--no-plot", action="store_true")
    p.add_argument(
        "--cpu-devices",
        type=int,
        default=1,
        help="JAX devices the CPU is split into (rigidjax.use_cpu_cores) for every method of the run; "
        "0: one per core",
    )
    p.add_argument(
        "--no-readme",
        action="store_true",
        help="do not rewrite the key-rows table of docs/guides/accuracy.md (a full run with the default "
        "prefix does)",
    )
    p.add_argument(
        "--replot", action="store_true", help="only redo PREFIX.md and PREFIX.png from PREFIX.json"
    )
    a = p.parse_args(argv)
    if a.replot:
        with open(a.out_prefix + ".json") as fh:
            saved = json.load(fh)
        saved["targets"] = B.evaluate_targets(saved["rows"])  # the current reading of the targets
        with open(a.out_prefix + ".json", "w") as fh:
            json.dump(saved, fh, indent=1)
        write_reports(saved["meta"], saved["rows"], saved["targets"], a.out_prefix, a.no_plot)
        if a.out_prefix == DEFAULT_PREFIX and not a.no_readme:
            update_readme(saved["meta"], saved["rows"], saved["targets"])
        return

    import rigidjax as rj

    cpu_devices = rj.use_cpu_cores(a.cpu_devices or None)
    t_start = time.perf_counter()
    meta = B.run_meta(
        "benchmarks/work_precision.py",
        argv,
        n=a.n,
        quick=a.quick,
        repeats=a.repeats,
        T=B.T_END,
        backend=jax.default_backend(),
        cpu_devices=cpu_devices,
    )
    print(f"N={a.n} on {meta['devices']}, {os.cpu_count()} CPUs, load {meta['loadavg_start']}", flush=True)
    scene = B.reference_scene(a.n)

    omega_ref, q_ref, checked, ref_info = B.refined_reference(scene, a.taylor_sensitive, a.taylor_random)
    omega_cf, q_cf, _ = B.closed_form_reference(scene)
    print(
        f"reference: closed form vs extended-precision Taylor on {ref_info['checked_bodies']} bodies "
        f"({ref_info['checked_most_sensitive']} nearest the separatrix, min |s| {ref_info['min_abs_s']:.1e}; "
        f"{ref_info['taylor_s']:.0f} s): max rel omega "
        f"{ref_info['closed_form_vs_taylor_max_rel_omega']:.1e}, "
        f"median {ref_info['closed_form_vs_taylor_median_rel_omega']:.1e}, max angle "
        f"{ref_info['closed_form_vs_taylor_max_angle']:.1e} rad",
        flush=True,
    )
    if a.scipy_ref_bodies:
        ref_info["scipy_DOP853_1e-13"] = sc = check_reference(
            scene, checked, omega_ref, q_ref, omega_cf, q_cf, min(a.scipy_ref_bodies, checked.size)
        )
        print(
            f"reference: scipy DOP853 rtol=atol=1e-13 on {sc['n_bodies']} of them ({sc['run_s']:.0f} s): "
            f"vs Taylor max rel omega {sc['dop853_vs_taylor_max_rel_omega']:.1e} (median "
            f"{sc['dop853_vs_taylor_median_rel_omega']:.1e}); vs closed form max "
            f"{sc['dop853_vs_closed_form_max_rel_omega']:.1e}",
            flush=True,
        )
    meta["reference"] = ref_info

    only = a.only
    keys = None if only is None else [k for k in only if k not in ("scipy", "mujoco")]
    methods = B.standard_methods(scene, "quick" if a.quick else "full", include=keys)
    if (only is None or "scipy" in only) and a.scipy_bodies:
        # A quarter of them the bodies nearest the separatrix, so that the max is comparable.
        k = max(1, a.scipy_bodies // 4)
        index = B.sensitive_subset(scene, min(a.scipy_bodies, a.n), n_sensitive=k, seed=3)
        methods += scipy_methods(scene, index, a.quick, f"incl. the {k} nearest the separatrix")
    if only is None or "mujoco" in only:
        mj, meta["mujoco"] = mujoco_methods(scene, a.quick)
        methods += mj
    else:
        meta["mujoco"] = "not selected (--only)"
    print(f"mujoco: {meta['mujoco']}", flush=True)

    def progress(what, done, total):
        print(f"  [{done:3d}/{total}] {time.perf_counter() - t_start:6.0f} s  {what}", flush=True)

    rows = B.run_methods(
        methods,
        scene,
        (omega_ref, q_ref),
        repeats=a.repeats,
        progress=progress,
        checked=checked,
        first_calls={"exact": ref_info["closed_form_first_call_s"]},
    )
    targets = B.evaluate_targets(rows)
    meta["loadavg_end"] = os.getloadavg()
    meta["total_s"] = time.perf_counter() - t_start
    table = B.format_table(rows)
    target_text = B.format_targets(targets)
    print("\n" + table + "\n\nTargets (float64):\n" + target_text, flush=True)

    os.makedirs(os.path.dirname(os.path.abspath(a.out_prefix)), exist_ok=True)
    with open(a.out_prefix + ".json", "w") as fh:
        json.dump(dict(meta=meta, rows=rows, targets=targets), fh, indent=1)
    write_reports(meta, rows, targets, a.out_prefix, a.no_plot)
    if a.out_prefix == DEFAULT_PREFIX and not a.no_readme and a.only is None and not a.quick:
        update_readme(meta, rows, targets)
    written = ".json/.md" if a.no_plot else ".json/.md/.png"
    print(f"total {meta['total_s']:.0f} s; wrote {a.out_prefix}{written}", flush=True)


if __name__ == "__main__":
    main()
