"""The torque-free body's principal frame: the moments sorted (by a network of selects, not a sort),
the angular velocity in that frame, and the parameters of the Jacobi-function solution (Landau &
Lifshitz, Mechanics, section 37): which axis the motion circles, the amplitudes, the rate, the
parameter ``m`` and its complement ``p = 1 - m`` computed on its own."""

import jax
import jax.numpy as jnp

from .._numerics import power_of_two_scaled

# The comparators of a sorting network for three elements.
_NETWORK = ((0, 1), (1, 2), (0, 1))


def unit_scaled(inertia):
    """``inertia`` (principal moments, last axis) scaled exactly so that its largest moment lies in
    ``[1/2, 1)``, per body (:func:`power_of_two_scaled`). Euler's equations depend on the moments'
    ratios only, and the closed forms multiply moments together (``I_a I_b I_c``,
    ``I_i (I_i - I_j) omega_i^2``): for a small body in SI units those products underflowed (float32:
    moments of 1e-12 kg m^2 made a tumbling body rotate steadily, its period infinite; float64 below
    about 1e-110). The motion does not change along the scale."""
    return power_of_two_scaled(inertia, axis=-1)


def _sorted_frame(inertia, omega0):
    """Moments ascending, omega permuted alike, the permutation and its parity (+1 even, -1 odd).

    Sorted by a three-comparator network of elementwise selects: ``jnp.argsort`` sorts every row by a
    comparator loop and takes gathers to apply, which on CPU cost more than the elliptic solution.
    Returns ``(swaps, index, moments, omega, parity)``: ``swaps`` are the comparators' outcomes (undone
    by :func:`_unsort`), ``index`` the body axis of each sorted one (three integer arrays). A swap needs a
    strictly larger moment, so equal moments keep their order, as in a stable sort.
    """
    moments = [inertia[..., k] for k in range(3)]
    omega = [omega0[..., k] for k in range(3)]
    index = [jnp.full(inertia.shape[:-1], k, jnp.int32) for k in range(3)]
    swaps = []
    for i, j in _NETWORK:
        swap = moments[i] > moments[j]
        for v in (moments, omega, index):
            v[i], v[j] = jnp.where(swap, v[j], v[i]), jnp.where(swap, v[i], v[j])
        swaps.append(swap)
    parity = jnp.where(swaps[0] ^ swaps[1] ^ swaps[2], -1.0, 1.0).astype(inertia.dtype)
    return swaps, index, moments, omega, parity


def _unsort(x, index):
    """``x`` (sorted frame, last axis) in the body's axis order, ``index`` from :func:`_sorted_frame`.

    A gather by the inverse permutation, declared in bounds (the default out-of-bounds handling adds
    masking to it and to its derivatives). Not selects: XLA fuses the whole elliptic solution into a
    select that forms the output, which made it several times slower on CPU.
    """
    inverse = [sum(jnp.where(i == k, j, 0) for j, i in enumerate(index)) for k in range(3)]
    inverse = jnp.stack(inverse, axis=-1)
    shape = jnp.broadcast_shapes(x.shape[:-1], inverse.shape[:-1]) + (3,)
    return jnp.take_along_axis(
        jnp.broadcast_to(x, shape), jnp.broadcast_to(inverse, shape), axis=-1, mode="promise_in_bounds"
    )


def _cycle(v, shift):
    """``[v[(k + shift) % 3] for k in range(3)]`` for a per-body ``shift`` in ``{0, 1, 2}``, by selects."""
    one, two = shift == 1, shift == 2
    return [jnp.where(one, v[(k + 1) % 3], jnp.where(two, v[(k + 2) % 3], v[k])) for k in range(3)]


def _momentum_defect(moments, x, j):
    """``L^2 - 2 E I_j`` written without cancellation: ``sum_i I_i (I_i - I_j) omega_i^2``."""
    return sum(moments[i] * (moments[i] - moments[j]) * x[i] for i in range(3) if i != j)


def _safe_div(num, den):
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _clip(x, low, high):
    """``clip`` for roundoff only: the value is clipped, the derivative is that of ``x``.

    At a symmetric body ``m`` and ``n`` touch 0 from above under either labelling of the equal axes;
    the formulas continue analytically to ``m < 0``, so the derivative of the unclipped expression is
    the derivative of the motion (``jnp.clip`` would halve it at the boundary).
    """
    return x + jax.lax.stop_gradient(jnp.clip(x, low, high) - x)


def _solution_parameters(moments, omega):
    """Amplitudes, rate, parameter m, 1 - m and ``nu = n / m`` of the elliptic solution, in the sorted frame.

    ``nu = I_c (L^2 - 2 E I_a) / (I_a (2 E I_c - L^2))`` (with ``n`` of :func:`torque_free_motion`) stays
    finite as ``m`` and ``n`` vanish together (symmetric bodies).
    """
    x = [w * w for w in omega]
    D = [_momentum_defect(moments, x, j) for j in range(3)]
    # L^2 >= 2 E I2: omega circles the axis of the largest moment. Decided by comparing D[1]'s two
    # terms, not by its sign: on the separatrix they cancel exactly, and where XLA contracts the sum
    # into a fused multiply-add D[1] becomes +-(the roundoff of one product), whose sign differs
    # between the fusions that each recompute it, so that one body took both sides at once.
    I1, I2, I3 = moments
    around_largest = I3 * (I3 - I2) * x[2] >= I1 * (I2 - I1) * x[0]
    Ia = jnp.where(around_largest, I1, I3)
    Ic = jnp.where(around_largest, I3, I1)
    Ib = I2
    Da = jnp.where(around_largest, D[0], D[2])
    Dc = jnp.where(around_largest, D[2], D[0])
    Db = D[1]
    amp_a = jnp.sqrt(jnp.maximum(_safe_div(-Dc, Ia * (Ic - Ia)), 0.0))
    amp_b = jnp.sqrt(jnp.maximum(_safe_div(-Dc, Ib * (Ic - Ib)), 0.0))
    amp_c = jnp.sqrt(jnp.maximum(_safe_div(Da, Ic * (Ic - Ia)), 0.0))
    rate = jnp.sqrt(jnp.maximum(_safe_div((Ic - Ib) * Da, Ia * Ib * Ic), 0.0))
    m = _clip(_safe_div((Ib - Ia) * -Dc, (Ic - Ib) * Da), 0.0, 1.0)
    p = _clip(_safe_div((Ic - Ia) * Db, (Ic - Ib) * Da), 0.0, 1.0)
    nu = _safe_div(Ic * Da, Ia * -Dc)
    return around_largest, (amp_a, amp_b, amp_c), rate, m, p, nu


PHASE_ROUNDING_LIMIT = 1e-3
"""The largest rounding, in radians, of a closed form's phase: ``eps |phase|``. The closed forms'
results carry an absolute error of about that (float32, moments (1, 2, 3), 1 rad/s in random
directions, against float64: a median 1.5e-7 at t = 10 s, 1e-5 at 10^3 s); beyond it they are
refused. float64 reaches it at a
phase of 4.5e12 rad, float32 at 8.4e3 rad."""


def phase_advice(dtype, start: str) -> str:
    """What to do about a phase beyond :data:`PHASE_ROUNDING_LIMIT`: times nearer ``start`` (and, below
    float64, float64)."""
    nearer = f"times nearer {start} (restart from the state at a later time)"
    return f"Use {nearer}." if jnp.finfo(dtype).bits >= 64 else f"Use float64, or {nearer}."


def largest_phase(*phases):
    """``max |phase|`` over ``phases`` (broadcast together), without derivatives: the size of the
    angles that a closed form evaluates at each sample, whose rounding (``eps |phase|``) bounds the
    accuracy of its result."""
    size = jnp.abs(phases[0])
    for phase in phases[1:]:
        size = jnp.maximum(size, jnp.abs(phase))
    return jax.lax.stop_gradient(size)


def phase_unresolved(phase):
    """Where the rounding of ``phase`` (:func:`largest_phase`) exceeds :data:`PHASE_ROUNDING_LIMIT`.
    NaN counts as unresolved."""
    return ~(phase * jnp.finfo(phase.dtype).eps <= PHASE_ROUNDING_LIMIT)
