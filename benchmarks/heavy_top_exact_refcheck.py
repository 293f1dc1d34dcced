"""Is scipy's DOP853 (rtol 1e-13) the limit of heavy_top_exact.py's "vs DOP853" errors?

The 16 reference tops of ``heavy_top_exact.py -n 10000`` at T = 20 s: the closed form against DOP853
at rtol 1e-13 and at 2.5e-14 (all tops as one system, as in the benchmark), the two references
against each other, and the closed form against DOP853 at 1e-13 solved for single tops (the 4
fastest; no error norm shared between tops).

    python benchmarks/heavy_top_exact_refcheck.py
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from heavy_top_exact import GRAVITY, abs_q, dop853, rel_omega, tops

from rigidjax._closed_form.heavy_top import lagrange_top_motion


def main():
    argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    ).parse_args()
    params, _, _ = tops(10_000)
    pick = np.linspace(0, 9_999, 16).astype(int)
    inertia, mass, com, w0, q0 = (x[pick] for x in params)
    ts = np.linspace(0.0, 20.0, 200)
    args = (
        inertia[:, None],
        mass[:, None],
        com[:, None],
        np.full((16, 1), GRAVITY),
        w0[:, None],
        q0[:, None],
        ts,
    )
    w, q = (np.asarray(x) for x in jax.jit(lagrange_top_motion)(*(jnp.asarray(a) for a in args)))
    refs = {}
    for tol in (1e-13, 2.5e-14):
        start = time.perf_counter()
        wr, qr, nfev = dop853(inertia, mass, com, w0, q0, ts, tol=tol)
        refs[tol] = (wr, qr)
        print(f"DOP853 rtol {tol:g}: {nfev} evaluations, {time.perf_counter() - start:.0f} s; "
              f"exact vs it: omega {rel_omega(w, wr):.1e}, q {abs_q(q, qr):.1e}", flush=True)  # fmt: skip
    (w13, q13), (w14, q14) = refs[1e-13], refs[2.5e-14]
    print(f"DOP853 1e-13 vs 2.5e-14: omega {rel_omega(w13, w14):.1e}, q {abs_q(q13, q14):.1e}")
    errors = []
    for k in np.argsort(w0[:, 2])[-4:]:
        one = slice(k, k + 1)
        wr, qr, _ = dop853(inertia[one], mass[one], com[one], w0[one], q0[one], ts)
        errors.append(f"{rel_omega(w[one], wr):.1e} / {abs_q(q[one], qr):.1e}")
    print("exact vs DOP853 1e-13 on single tops (the 4 fastest), omega / q:", ", ".join(errors))


if __name__ == "__main__":
    main()
