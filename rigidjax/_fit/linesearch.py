"""A strong-Wolfe line search written as a state machine: the caller evaluates the loss and its
slope at ``state.stepsize``, hands them to :func:`wolfe_advance` and gets the next stepsize to try,
until ``accepted`` or ``failed``.

Because the search never calls the model itself, the fit's compiled loop evaluates the model from one
place whatever the search is doing (a line search that calls the model, as optax's do, adds copies of
it to the program: one per branch of its search). The search is Nocedal and Wright's Algorithms 3.5
and 3.6 (bracketing by expansion, then zooming by safeguarded cubic interpolation) with the strong
Wolfe conditions, which keep L-BFGS's curvature pairs positive.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

SUFFICIENT_DECREASE = 1e-4
CURVATURE = 0.9
APPROXIMATE_DECREASE = 1e-6  # Hager and Zhang's epsilon; also optax's zoom line search's default
EXPANSION = 3.0
MAX_TRIES = 20
SMALLEST_BRACKET = 1e-5  # relative width at which the bracket stops shrinking


class WolfeSearch(eqx.Module):
    """Where a line search stands: the loss and slope at the start, the stepsize to evaluate next,
    the last trial of the expansion phase and, once a minimiser is bracketed, the bracket's ends
    (``low``: the lowest loss with sufficient decrease so far)."""

    value0: Float[Array, ""]
    slope0: Float[Array, ""]
    stepsize: Float[Array, ""]
    previous: Float[Array, "3"]  # (stepsize, loss, slope) of the previous expansion trial
    low: Float[Array, "3"]
    high: Float[Array, "3"]
    bracketed: Bool[Array, ""]
    forced: Bool[Array, ""]  # the next trial is taken whatever its loss (the fallback to `low`)
    tries: Int[Array, ""]
    accepted: Bool[Array, ""]
    failed: Bool[Array, ""]


def wolfe_start(value0, slope0, stepsize) -> WolfeSearch:
    """A search from loss ``value0`` with slope ``slope0`` (< 0: a descent direction) that first tries
    ``stepsize``."""
    value0 = jnp.asarray(value0)
    start = jnp.stack([jnp.zeros_like(value0), value0, jnp.asarray(slope0, value0.dtype)])
    false = jnp.asarray(False)
    return WolfeSearch(
        value0=value0,
        slope0=start[2],
        stepsize=jnp.asarray(stepsize, value0.dtype),
        previous=start,
        low=start,
        high=start,
        bracketed=false,
        forced=false,
        tries=jnp.asarray(0),
        accepted=false,
        failed=false,
    )


def _interpolate(low, high):
    """The minimiser of the cubic through both ends' losses and slopes, clipped to the bracket less
    10 % of its width at each end; the midpoint where the cubic has no minimiser or ``high``'s loss
    is not finite."""
    a, fa, da = low[0], low[1], low[2]
    b, fb, db = high[0], high[1], high[2]
    width = b - a
    safe_width = jnp.where(width != 0, width, 1.0)
    d1 = da + db - 3.0 * (fa - fb) / (-safe_width)
    radicand = d1 * d1 - da * db
    d2 = jnp.sign(width) * jnp.sqrt(jnp.where(radicand > 0, radicand, 0.0))
    denominator = db - da + 2.0 * d2
    safe_denominator = jnp.where(denominator != 0, denominator, 1.0)
    cubic = b - width * (db + d2 - d1) / safe_denominator
    midpoint = a + 0.5 * width
    margin = 0.1 * jnp.abs(width)
    kept_inside = jnp.clip(cubic, jnp.minimum(a, b) + margin, jnp.maximum(a, b) - margin)
    usable = (radicand > 0) & (denominator != 0) & jnp.isfinite(cubic) & jnp.isfinite(fb) & jnp.isfinite(db)
    return jnp.where(usable, kept_inside, midpoint)


def wolfe_advance(search: WolfeSearch, value, slope) -> WolfeSearch:
    """The search after its trial at ``search.stepsize`` gave loss ``value`` and slope ``slope``
    (the directional derivative). A loss or slope that is NaN or inf counts as too far."""
    t = search.stepsize
    trial = jnp.stack([t, value, slope])
    finite = jnp.isfinite(value) & jnp.isfinite(slope)
    # Sufficient decrease, or Hager and Zhang's approximate form of it (their eq. 23, with the value
    # within APPROXIMATE_DECREASE of the start's): near a minimum the loss changes by roundoff only
    # and no longer resolves SUFFICIENT_DECREASE * t * slope0, while the slope still shows that the
    # step did not overshoot.
    close = value <= search.value0 + APPROXIMATE_DECREASE * jnp.abs(search.value0)
    armijo = value <= search.value0 + SUFFICIENT_DECREASE * t * search.slope0
    approximate = close & (slope <= (1.0 - 2.0 * SUFFICIENT_DECREASE) * -search.slope0)
    decrease = finite & (armijo | approximate)
    flat = finite & (jnp.abs(slope) <= CURVATURE * jnp.abs(search.slope0))

    # Expansion: the trial either bounds a minimiser with the previous one, meets the conditions,
    # or lies on a still-descending stretch (try further out).
    too_far = ~decrease | ((search.tries > 0) & (value >= search.previous[1]))
    expand_ok = ~too_far & flat
    rising = ~too_far & ~expand_ok & (slope >= 0)
    expand_low = jnp.where(rising, trial, search.previous)
    expand_high = jnp.where(rising, search.previous, trial)

    # Zoom: the trial lies inside the bracket.
    above_low = ~decrease | (value >= search.low[1])
    zoom_ok = ~above_low & flat
    flips = ~above_low & ~zoom_ok & (slope * (search.high[0] - search.low[0]) >= 0)
    zoom_high = jnp.where(above_low, trial, jnp.where(flips, search.low, search.high))
    zoom_low = jnp.where(above_low, search.low, trial)

    bracketed = search.bracketed | too_far | rising
    low = jnp.where(search.bracketed, zoom_low, expand_low)
    high = jnp.where(search.bracketed, zoom_high, expand_high)
    # Any trial that meets the (strong or approximate) Wolfe conditions ends the search, whatever
    # the bracket's state: they refer to the start only.
    accepted = jnp.where(search.forced, finite, decrease & flat)
    previous = jnp.where(search.bracketed, search.previous, trial)
    next_stepsize = jnp.where(bracketed, _interpolate(low, high), EXPANSION * t)

    tries = search.tries + 1
    # Out of tries, or a bracket shrunk to a point: take the lowest trial with sufficient decrease
    # (one more evaluation there, for its gradient), or fail if there is none.
    span = jnp.maximum(jnp.abs(low[0]), jnp.abs(high[0]))
    collapsed = bracketed & (jnp.abs(high[0] - low[0]) <= SMALLEST_BRACKET * span)
    give_up = ~accepted & ~search.forced & ((tries >= MAX_TRIES) | collapsed)
    has_low = low[0] > 0
    forced = give_up & has_low
    failed = (search.forced & ~finite) | (give_up & ~has_low)
    return WolfeSearch(
        value0=search.value0,
        slope0=search.slope0,
        stepsize=jnp.where(forced, low[0], next_stepsize),
        previous=previous,
        low=low,
        high=high,
        bracketed=bracketed,
        forced=forced,
        tries=tries,
        accepted=accepted,
        failed=failed,
    )
