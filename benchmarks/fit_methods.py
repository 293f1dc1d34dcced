"""How ``rigidjax.fit_inertia`` should optimise, measured: Levenberg–Marquardt vs optax, and forward
vs reverse mode for the derivatives.

Records (synthetic, from the closed-form torque-free motion; 2 % gyro noise, default_rng(0)):
  short  I = (1, 2, 2.5), omega0 = (0.3, 0.05, 1.0): 4 wobble periods, 240 samples, single shooting.
  long   the same body over 45 periods, 1800 samples, multiple shooting with segments="auto" (45 windows).
  earth  (C - A)/A = 3.3e-3 in SI units, 3 wobble periods (~2.5 years), 240 samples.

Sections
  1 methods     LM vs optax L-BFGS (the default: optax's L-BFGS directions with the fit's own
                strong-Wolfe line search) vs ``optimizer=optax.lbfgs()`` (optax's zoom line search,
                which calls the model itself) vs optax Adam (lr 1e-2) from the same data-driven
                start: iterations, wall time after compile (median of --repeats), compile time,
                final loss, error against the truth in units of the standard error.
  2 derivatives the Jacobian of the residuals (what LM needs) by jacfwd vs jacrev, and the gradient of
                the loss (what optax needs) by forward mode (jvp per parameter) vs reverse mode, for
                1 and 45 windows; and through the integrator: d omega(T) / d inertia through
                ``simulate`` by jax.jacrev (RecursiveCheckpointAdjoint, the default) vs jax.jacfwd
                (diffrax.ForwardMode).

Times: compile excluded (first call reported apart), ``block_until_ready``, median of repeats.
Usage: python benchmarks/fit_methods.py [--repeats 3] [--out benchmarks/results/fit_methods.json]
"""

from __future__ import annotations

import argparse
import json

import jax

jax.config.update("jax_enable_x64", True)

import _harness as B  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import rigidjax as rj  # noqa: E402
from rigidjax._fit.prepare import _prepare_omega  # noqa: E402  (the residual problem the fit builds)


def records():
    rng = np.random.default_rng(0)
    inertia = np.array([1.0, 2.0, 2.5])
    omega0 = np.array([0.3, 0.05, 1.0])
    period = float(rj.torque_free_period(inertia, omega0))
    out = {}
    for name, cycles, samples in (("short", 4, 240), ("long", 45, 1800)):
        ts = np.linspace(0.0, cycles * period, samples)
        w = np.asarray(rj.torque_free_omega(inertia, omega0, ts))
        obs = w + 0.02 * np.std(w, axis=0) * rng.standard_normal(w.shape)
        out[name] = (ts, obs, inertia / inertia.sum(), {"segments": "auto"} if name == "long" else {})
    A = 8.0e37
    earth = np.array([A, A * (1 + 1e-4), A * (1 + 3.3e-3)])
    w0 = np.array([7.292e-6, 0.0, 7.292e-5])
    period = float(rj.torque_free_period(earth, w0))
    ts = np.linspace(0.0, 3 * period, 240)
    w = np.asarray(rj.torque_free_omega(earth, w0, ts))
    obs = w + 0.02 * np.std(w, axis=0) * rng.standard_normal(w.shape)
    out["earth"] = (ts, obs, earth / earth.sum(), {})
    return out


def timed(fn, repeats):
    """(result, median run s, compile s): ``_harness.timed_calls``."""
    result, t = B.timed_calls(fn, repeats)
    return result, t["run_s"], t["compile_s"]


def methods_section(repeats):
    rows = []
    configs = {
        "levenberg-marquardt": {"method": "levenberg-marquardt"},
        "optax L-BFGS": {"method": "optax"},
        "optax.lbfgs() as given": {"optimizer": optax.lbfgs()},
        "optax Adam 1e-2": {"optimizer": optax.adam(1e-2), "steps": 5000},
    }
    for record, (ts, obs, truth, extra) in records().items():
        for label, kwargs in configs.items():

            def run(kwargs=kwargs, ts=ts, obs=obs, extra=extra):
                return rj.fit_inertia(ts, obs, **kwargs, **extra)

            fit, seconds, compile_s = timed(run, repeats)
            z = (np.asarray(fit.inertia) - truth) / np.asarray(fit.inertia_stderr)
            rows.append(
                {
                    "record": record,
                    "method": label,
                    "iterations": fit.num_steps,
                    "converged": bool(fit.converged),
                    "run_s": seconds,
                    "compile_s": compile_s,
                    "loss": float(fit.loss),
                    "max_abs_z": float(np.max(np.abs(z))),
                }
            )
            print(
                f"{record:6s} {label:24s} iters {fit.num_steps:5d} conv {bool(fit.converged)!s:5s} "
                f"run {seconds:7.3f} s compile {compile_s:6.1f} s loss {float(fit.loss):.4e} "
                f"max|z| {np.max(np.abs(z)):.2f}",
                flush=True,
            )
    return rows


def derivatives_section(repeats):
    rows = []
    rec = records()
    for record, segments in (("short", 1), ("long", 45)):
        ts, obs, _, _ = rec[record]
        data = _prepare_omega(ts, obs, segments, False, None, None, "squared", None, None, jnp.float64)
        problem, p = data.problem, jnp.asarray(data.p0)
        jf = jax.jit(jax.jacfwd(problem.residuals))
        jr = jax.jit(jax.jacrev(problem.residuals))
        gr = jax.jit(jax.grad(problem.loss))

        # Forward-mode gradient: one jvp per parameter (what jacfwd of the scalar loss does).
        gf = jax.jit(jax.jacfwd(problem.loss))
        for label, fn in (
            ("jacobian jacfwd", jf),
            ("jacobian jacrev", jr),
            ("gradient forward", gf),
            ("gradient reverse", gr),
        ):
            _, seconds, compile_s = timed(lambda fn=fn, p=p: fn(p), repeats)
            rows.append(
                {
                    "record": record,
                    "parameters": int(p.shape[0]),
                    "residuals": int(problem.observed.size),
                    "what": label,
                    "run_s": seconds,
                    "compile_s": compile_s,
                }
            )
            print(
                f"{record:6s} P={p.shape[0]:4d} R={problem.observed.size:6d} {label:18s} "
                f"run {seconds * 1e3:9.2f} ms compile {compile_s:6.1f} s",
                flush=True,
            )
        # After the timing, whose first call is the compile: both modes give the same derivatives.
        np.testing.assert_allclose(jf(p), jr(p), rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(gf(p), gr(p), rtol=1e-8, atol=1e-12)
    # Through the integrator (a torque-driven fit would need it): d omega(T) / d inertia.
    ts = jnp.linspace(0.0, 20.0, 2)
    w0 = jnp.array([0.3, 0.05, 1.0])

    def final(inertia, adjoint):
        return rj.simulate(
            rj.FreeBody(inertia), rj.State(w0), ts, accuracy="balanced", adjoint=adjoint
        ).omega[-1]

    inertia = jnp.array([1.0, 2.0, 2.5])
    rev = jax.jit(jax.jacrev(lambda i: final(i, None)))
    fwd = jax.jit(jax.jacfwd(lambda i: final(i, diffrax.ForwardMode())))
    for label, fn in (("simulate jacrev (checkpointed)", rev), ("simulate jacfwd (ForwardMode)", fwd)):
        _, seconds, compile_s = timed(lambda fn=fn: fn(inertia), repeats)
        rows.append({"record": "simulate T=20", "what": label, "run_s": seconds, "compile_s": compile_s})
        print(f"simulate T=20 {label:32s} run {seconds * 1e3:9.2f} ms compile {compile_s:6.1f} s", flush=True)
    np.testing.assert_allclose(rev(inertia), fwd(inertia), rtol=1e-6)
    return rows


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="benchmarks/results/fit_methods.json")
    parser.add_argument("--sections", default="methods,derivatives")
    args = parser.parse_args()
    result = {"devices": [str(d) for d in jax.devices()], "repeats": args.repeats}
    if "methods" in args.sections:
        result["methods"] = methods_section(args.repeats)
    if "derivatives" in args.sections:
        result["derivatives"] = derivatives_section(args.repeats)
    with open(args.out, "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
