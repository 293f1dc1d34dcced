"""The optimisers of the fit, each one compiled loop over a :class:`_Problem`'s flat parameters:
Levenberg–Marquardt on its residuals (the Jacobian by forward mode), the default L-BFGS on its mean
loss (optax's L-BFGS directions, the line search of :mod:`.linesearch` run by the loop), or any optax
``GradientTransformation`` on its mean loss. :func:`_run` adds the covariance at the optimum.

Compile time, not run time, dominates a fit, and it grows with every place in the program that
evaluates the model: XLA compiles each of them, identical or not (measured: a second, identical call
of a jitted Jacobian still compiled in full). So the closed-form model is differentiated in forward
mode only (the covariance's Jacobian, Levenberg–Marquardt's and the optax gradients), each loop
evaluates it from as few places as it can (Levenberg–Marquardt and the default L-BFGS: one), and
the final residuals come from the Jacobian's pass rather than from further evaluations of the model.

``callback``, when given, is called on the host after every iteration as
``callback(iteration, loss, step_norm)`` (the loss and the step in the optimiser's scaled units)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .linesearch import wolfe_advance, wolfe_start
from .problem import _Problem


def _unset_outputs(problem: _Problem, p0):
    """Zeros in the shapes of the Jacobian, residuals and raw residuals that a fit's loop carries
    (as ``J``, ``r``, ``raw``) until it evaluates them at an accepted point."""
    r0, raw0 = jax.eval_shape(problem.residuals_and_raw, p0)
    return {
        "J": jnp.zeros((r0.shape[0], p0.shape[0]), p0.dtype),
        "r": jnp.zeros(r0.shape, r0.dtype),
        "raw": jnp.zeros(raw0.shape, raw0.dtype),
    }


def _levenberg_marquardt(problem: _Problem, p0, steps: int, tol: float, callback):
    """Levenberg–Marquardt with Marquardt's diagonal scaling; the Jacobian by forward mode (few
    parameters, many residuals).

    Returns ``(p, history, iterations, converged, J, r, raw)`` with the Jacobian, the residuals and
    the raw residuals at the final ``p``. The model appears once in the program: every pass of the
    loop evaluates the Jacobian with the residuals (the primal of the forward-mode pass) at one
    trial point, the first pass at ``p0``. An accepted trial's Jacobian is the next iteration's, and
    a rejected trial only raises the damping, so no pass evaluates the model twice at one point and
    there is no separate, residual-only copy of the model to compile.
    """
    jacobian = _jacobian_with_residuals(problem)
    n = problem.count()
    max_tries = 12  # damping raised fourfold per rejected trial

    def proposal(J, r, lam):
        g = J.T @ r
        A = J.T @ J
        d = jnp.maximum(jnp.diag(A), 1e-12 * jnp.max(jnp.diag(A)) + 1e-300)
        step = jnp.linalg.solve(A + lam * jnp.diag(d), -g)
        return step, g

    def cond(carry):
        return ~carry["exit"]

    def body(carry):
        J_t, (r_t, raw_t) = jacobian(carry["trial"])
        f_t = jnp.sum(r_t * r_t)
        first = carry["first"]
        p, f, lam, i = carry["p"], carry["f"], carry["lam"], carry["i"]
        improved = ~first & jnp.isfinite(f_t) & (f_t < f)
        # An iteration ends when its trial lowers the loss or its last trial fails.
        resolved = ~first & (improved | (carry["tries"] + 1 >= max_tries))
        take = first | improved
        p_next = jnp.where(take, carry["trial"], p)
        f_next = jnp.where(take, f_t, f)
        J = jnp.where(take, J_t, carry["J"])
        r = jnp.where(take, r_t, carry["r"])
        raw = jnp.where(take, raw_t, carry["raw"])

        small_change = (f - f_next) <= tol * f_next
        small_step = jnp.max(jnp.abs(carry["trial"] - p)) <= tol * (1.0 + jnp.max(jnp.abs(p)))
        converged = (improved & (small_change | small_step)) | carry["tiny_gradient"]
        # No damping makes the step lower the loss: a minimum to roundoff if the last accepted step
        # barely changed the loss, a failure otherwise.
        stalled = resolved & ~improved
        converged = resolved & (converged | (stalled & (carry["last_decrease"] <= jnp.sqrt(tol))))
        decrease = jnp.where(improved, (f - f_next) / jnp.maximum(f_next, 1e-300), carry["last_decrease"])
        history = jnp.where(resolved, carry["history"].at[i].set(f_next / n), carry["history"])
        if callback is not None:

            def report():
                jax.debug.callback(callback, i + 1, f_next / n, jnp.linalg.norm(p_next - p), ordered=True)

            jax.lax.cond(resolved, report, lambda: None)
        i_next = jnp.where(resolved, i + 1, i)
        # Accepted steps have a finite loss, so only the start can have none (a known torque's
        # integration that fails there): no step is tried, and the fit reports the loss.
        finished = (first & ((steps <= 0) | ~jnp.isfinite(f_t))) | (
            resolved & (converged | stalled | (i_next >= steps))
        )
        lam_next = jnp.where(
            improved, jnp.maximum(lam / 5.0, 1e-12), jnp.where(first | resolved, lam, lam * 4.0)
        )
        step, g = proposal(J, r, lam_next)
        tiny_gradient = jnp.max(jnp.abs(g)) <= tol * tol * (f_next + 1e-300)
        starts = first | resolved  # a new iteration from p_next: its gradient decides tiny_gradient
        return {
            "trial": p_next + step,
            "first": jnp.asarray(False),
            "exit": finished,
            "p": p_next,
            "f": f_next,
            "lam": lam_next,
            "tries": jnp.where(starts, 0, carry["tries"] + 1),
            "tiny_gradient": jnp.where(starts, tiny_gradient, carry["tiny_gradient"]),
            "i": i_next,
            "history": history,
            "converged": carry["converged"] | converged,
            "last_decrease": decrease,
            "J": J,
            "r": r,
            "raw": raw,
        }

    false = jnp.asarray(False)
    init = {
        "trial": p0,
        "first": jnp.asarray(True),
        "exit": false,
        "p": p0,
        "f": jnp.asarray(jnp.inf, p0.dtype),
        "lam": jnp.asarray(1.0, p0.dtype),
        "tries": jnp.asarray(0),
        "tiny_gradient": false,
        "i": jnp.asarray(0),
        "history": jnp.full((steps,), jnp.nan, p0.dtype),
        "converged": false,
        "last_decrease": jnp.asarray(jnp.inf, p0.dtype),
        **_unset_outputs(problem, p0),
    }
    out = jax.lax.while_loop(cond, body, init)
    return out["p"], out["history"], out["i"], out["converged"], out["J"], out["r"], out["raw"]


def _jacobian_with_residuals(problem: _Problem, reverse: bool = False):
    """``p -> (J, (r, raw))``: the Jacobian of the residuals with the residuals and raw residuals at
    ``p`` from the same pass.

    Forward mode by default, with one tangent per inertia parameter and one per component of the
    per-window parameters shared by all windows: a window's residuals depend only on the inertia and
    on its own parameters, so a tangent that moves every window's ``omega0_x`` at once yields each
    window's column in that window's rows. The cost is that of a few tangents however many windows
    there are (one per parameter would grow with them); the columns are then spread out into the
    full Jacobian. ``reverse``: ``jax.jacrev`` (the integrated model under the optax path).
    """

    def residuals(p):
        r, raw = problem.residuals_and_raw(p)
        return r, (r, raw)

    if reverse:
        return jax.jacrev(residuals, has_aux=True)

    def jacobian(p):
        k = problem.n_inertia_params
        windows = problem.t.shape[0]
        blocks = (p.shape[0] - k) // (3 * windows)  # omega0, and the orientation corrections
        seeds = np.zeros((k + 3 * blocks, p.shape[0]))
        seeds[np.arange(k), np.arange(k)] = 1.0
        for b in range(blocks):
            for c in range(3):
                seeds[k + 3 * b + c, k + 3 * windows * b + 3 * np.arange(windows) + c] = 1.0

        def push(seed):
            return jax.jvp(residuals, (p,), (seed,), has_aux=True)

        r, compressed, aux = jax.vmap(push, out_axes=(None, -1, None))(jnp.asarray(seeds, p.dtype))
        per_window = compressed.reshape(windows, -1, compressed.shape[-1])
        own = jnp.eye(windows, dtype=bool)[:, None, :, None]  # (window of the row, -, window, -)
        columns = [compressed[:, :k]]
        for b in range(blocks):
            block = per_window[:, :, None, k + 3 * b : k + 3 * b + 3]
            columns.append(jnp.where(own, block, 0.0).reshape(r.shape[0], 3 * windows))
        return jnp.concatenate(columns, axis=1), aux

    return jacobian


FORWARD_GRADIENT_SAMPLES = 4096
"""Up to this many samples the optax fits take their gradients through the forward-mode Jacobian
(:func:`_forward_mode_loss`: less to compile, a few tangents more to run); beyond it, in reverse
mode. Measured on a 2-core CPU: the forward gradient saves ~5 s of compile and costs ~0.6 ms per
sample and fit more to run (1800 samples: 0.43 -> 1.4 s), so the two break even near 8000 samples."""


def _stopping_rule(problem: _Problem, steps: int, tol: float) -> tuple[int, float, bool]:
    """The last arguments of :func:`_stops`: the step limit, the relative change of the loss below
    which a fit has converged, and whether the loss is noisy. ``tol``, but at least 1e-8 for an
    integrated (torque) model, whose loss is smooth only to about the solver's rtol (1e-10;
    step-size decisions jump): changes below 1e-8 of it are noise there (and statistically
    irrelevant: parameters move by ~1e-4 of their standard errors)."""
    noisy = problem.torque is not None
    return steps, max(tol, 1e-8) if noisy else tol, noisy


def _forward_gradient(problem: _Problem) -> bool:
    """Whether an optax fit takes its gradient through the forward-mode Jacobian (see
    :data:`FORWARD_GRADIENT_SAMPLES`): not where the problem is differentiated in reverse mode only
    (the integrated model of a known torque, on this path), nor for a long record, where the run
    dominates."""
    return not problem.reverse_mode and problem.t.size <= FORWARD_GRADIENT_SAMPLES


def _stops(i, value, previous, best_before, steps, loss_tol, noisy):
    """(stop here, converged, recent losses, best loss before them) for iteration ``i`` of an optax
    fit whose loss is ``value``: converged when the loss has changed by at most ``loss_tol``
    (relative) over the last ten iterations. A ``noisy`` loss (an integrated model: a known torque)
    has also converged when the best of the last ten is no better, by ``loss_tol``, than the best
    before them: at the floor of the integrator's noise the line search accepts steps that move the
    loss either way by that noise (4e-7 of the loss for a record with noise of 1e-3 rad/s), which
    the first test never sees settle."""
    best_before = jnp.minimum(best_before, previous[i % 10])  # the value leaving the window
    recent = previous.at[i % 10].set(value)
    converged = (i >= 10) & (jnp.max(recent) - jnp.min(recent) <= loss_tol * jnp.abs(value))
    if noisy:
        stagnant = jnp.min(recent) >= best_before - loss_tol * jnp.abs(best_before)
        converged = converged | ((i >= 20) & stagnant)
    return converged | (i >= steps), converged, recent, best_before


def _optax_fit(problem: _Problem, p0, optimizer, steps: int, tol: float, callback):
    """Minimises the mean loss with an optax optimiser until it stops changing (over the last ten
    iterations) or ``steps`` run out. Returns ``(p, history, iterations, converged, J, r, raw)`` with
    the Jacobian, the residuals and the raw residuals at the final ``p``.

    Each pass of the loop starts at a point ``p`` with its loss: it records the loss, decides
    whether to stop, and only if not takes the optimiser's step. The Jacobian at ``p`` comes from one
    place in the loop, whether the pass needs it for the loss and gradient (the start of an L-BFGS
    run, whose later values the line search keeps; every step of an optimiser without a line search)
    or for the covariance at the end, so that the compiled fit holds one copy of the model fewer than
    an evaluation before and another after the loop (a quarter less to compile with L-BFGS)."""
    optimizer = optax.with_extra_args_support(optimizer)
    state0 = optimizer.init(p0)
    try:  # line-search optimisers (L-BFGS) keep the last value and gradient in their state
        reuses_value = optax.tree_utils.tree_get(state0, "value", None) is not None
    except (KeyError, ValueError):
        reuses_value = False
    jacobian = _jacobian_with_residuals(problem, reverse=problem.reverse_mode)
    forward = _forward_gradient(problem)
    loss = _forward_mode_loss(problem, jacobian) if forward else problem.loss
    n = problem.count()
    # Without a line search and with forward-mode gradients, every pass needs the Jacobian.
    jacobian_every_pass = forward and not reuses_value
    stopping = _stopping_rule(problem, steps, tol)

    def cond(carry):
        return ~carry["exit"]

    def body(carry):
        p, state, i = carry["p"], carry["state"], carry["i"]
        if jacobian_every_pass:
            J, (r, raw) = jacobian(p)
            value, grad = jnp.sum(r * r) / n, 2.0 * (J.T @ r) / n
        else:
            if reuses_value:
                stored = (optax.tree_utils.tree_get(state, "value"), optax.tree_utils.tree_get(state, "grad"))
                known = jnp.isfinite(stored[0])
            else:
                stored, known = jax.value_and_grad(loss)(p), jnp.asarray(True)
            # The model is evaluated here only where the loss is not known yet or the fit stops.
            need_jacobian = (
                ~known | _stops(i, stored[0], carry["previous"], carry["best_before"], *stopping)[0]
            )
            J, (r, raw) = jax.lax.cond(
                need_jacobian, jacobian, lambda _: (carry["J"], (carry["r"], carry["raw"])), p
            )
            value = jnp.where(known, stored[0], jnp.sum(r * r) / n)
            grad = jnp.where(known, stored[1], 2.0 * (J.T @ r) / n)
        stop, converged, recent, best_before = _stops(
            i, value, carry["previous"], carry["best_before"], *stopping
        )

        def step(_):
            updates, new_state = optimizer.update(grad, state, p, value=value, grad=grad, value_fn=loss)
            if callback is not None:
                step_norm = jnp.sqrt(sum(jnp.sum(u * u) for u in jax.tree_util.tree_leaves(updates)))
                jax.debug.callback(callback, i + 1, value, step_norm, ordered=True)
            return optax.apply_updates(p, updates), new_state

        p_next, state_next = jax.lax.cond(stop, lambda _: (p, state), step, None)
        # A pass that stops takes no step: its loss is the fit's final loss, not a step's.
        history = carry["history"].at[jnp.minimum(i, steps - 1)].set(value)
        history = jnp.where(stop, carry["history"], history)
        return {
            "p": p_next,
            "state": state_next,
            "i": jnp.where(stop, i, i + 1),
            "history": history,
            "previous": recent,
            "best_before": best_before,
            "exit": stop,
            "converged": converged,
            "J": J,
            "r": r,
            "raw": raw,
        }

    init = {
        "p": p0,
        "state": state0,
        "i": jnp.asarray(0),
        "history": jnp.full((steps,), jnp.nan, p0.dtype),
        "previous": jnp.full((10,), jnp.inf, p0.dtype),
        "best_before": jnp.asarray(jnp.inf, p0.dtype),
        "exit": jnp.asarray(False),
        "converged": jnp.asarray(False),
        **_unset_outputs(problem, p0),
    }
    out = jax.lax.while_loop(cond, body, init)
    return out["p"], out["history"], out["i"], out["converged"], out["J"], out["r"], out["raw"]


def _lbfgs_fit(problem: _Problem, p0, steps: int, tol: float, callback):
    """The default optax fit: L-BFGS directions (optax's ``scale_by_lbfgs``) with a strong-Wolfe
    line search (:mod:`.linesearch`) run by this loop. Returns ``(p, history, iterations, converged,
    J, r, raw)`` as :func:`_optax_fit` does, with the same stopping rule.

    Every pass evaluates the model once, at one trial point, from one place in the program: the start,
    each line-search trial, and (up to :data:`FORWARD_GRADIENT_SAMPLES` samples) the Jacobian for the
    covariance all come from the forward-mode pass that gives the loss and its gradient
    (``2 J^T r / n``). ``optax.lbfgs()``, whose line search calls the loss itself from two branches,
    compiles the model three times in this loop (``benchmarks/fit_methods.py``: 24 s against 14 s
    for the first fit of a 240-sample record). Past that many samples, and with a known torque, the
    gradient comes from reverse mode and the covariance's Jacobian is evaluated once after the loop.
    """
    lbfgs = optax.scale_by_lbfgs()
    forward = _forward_gradient(problem)
    jacobian = _jacobian_with_residuals(problem, reverse=problem.reverse_mode)
    n = problem.count()
    stopping = _stopping_rule(problem, steps, tol)

    def loss_with_residuals(p):
        r, raw = problem.residuals_and_raw(p)
        return jnp.sum(r * r) / n, (r, raw)

    def evaluate(x, carry):
        if forward:
            J, (r, raw) = jacobian(x)
            return jnp.sum(r * r) / n, 2.0 * (J.T @ r) / n, J, r, raw
        (value, (r, raw)), grad = jax.value_and_grad(loss_with_residuals, has_aux=True)(x)
        return value, grad, carry["J"], r, raw

    def steepest_descent(grad):
        """A steepest-descent direction of length <= 1 and its slope."""
        d = -grad * jnp.minimum(1.0, 1.0 / jnp.maximum(jnp.linalg.norm(grad), 1e-300))
        return d, jnp.vdot(grad, d)

    def direction(grad, state, p):
        updates, state = lbfgs.update(grad, state, p)
        d = -updates
        slope = jnp.vdot(grad, d)
        # Not a descent direction (roundoff in the memory): steepest descent instead.
        usable = jnp.isfinite(slope) & (slope < 0)
        steepest, steepest_slope = steepest_descent(grad)
        return jnp.where(usable, d, steepest), jnp.where(usable, slope, steepest_slope), state

    def cond(carry):
        return ~carry["exit"]

    def body(carry):
        first, search, d = carry["first"], carry["search"], carry["d"]
        x = carry["p"] + search.stepsize * d
        x = jnp.where(first, carry["p"], x)
        value, grad, J_x, r_x, raw_x = evaluate(x, carry)
        search = wolfe_advance(search, value, jnp.vdot(grad, d))
        accept = first | search.accepted
        p, i = carry["p"], carry["i"]
        p_new = jnp.where(accept, x, p)
        value_new = jnp.where(accept, value, carry["value"])
        grad_new = jnp.where(accept, grad, carry["grad"])
        J = jnp.where(accept, J_x, carry["J"])
        r = jnp.where(accept, r_x, carry["r"])
        raw = jnp.where(accept, raw_x, carry["raw"])

        stop, converged, recent, best_before = _stops(
            i, value_new, carry["previous"], carry["best_before"], *stopping
        )
        stop = accept & stop
        # A start whose loss is NaN or inf (a known torque's integration that fails there): no step.
        bad_start = first & ~jnp.isfinite(value)
        # No stepsize along the direction lowers the loss. Along an L-BFGS direction: start afresh
        # with steepest descent and an empty memory. Along steepest descent (the search shrinks the
        # step to ~1e-20 of the gradient's unit length first): the gradient is roundoff, a minimum to
        # the working precision (float32's, for instance, above the tolerance asked for).
        failed = ~first & search.failed
        restart = failed & ~carry["steepest"]
        stalled = failed & carry["steepest"]
        converged = jnp.where(stalled, jnp.all(jnp.isfinite(grad_new)), accept & converged)
        if callback is not None:

            def report():
                jax.debug.callback(callback, i, value_new, jnp.linalg.norm(p_new - p), ordered=True)

            jax.lax.cond(accept & ~first, report, lambda: None)

        recorded = carry["history"].at[jnp.minimum(i, steps - 1)].set(value_new)
        history = jnp.where(accept & ~stop, recorded, carry["history"])
        step = accept & ~stop & ~bad_start
        d_new, slope_new, state_new = direction(grad_new, carry["lbfgs"], p_new)
        d_restart, slope_restart = steepest_descent(grad_new)
        d_new = jnp.where(restart, d_restart, d_new)
        slope_new = jnp.where(restart, slope_restart, slope_new)
        state_new = jax.tree.map(lambda a, b: jnp.where(restart, a, b), lbfgs.init(p_new), state_new)
        renew = step | restart
        lbfgs_state = jax.tree.map(lambda a, b: jnp.where(renew, a, b), state_new, carry["lbfgs"])
        search = jax.tree.map(
            lambda a, b: jnp.where(renew, a, b), wolfe_start(value_new, slope_new, 1.0), search
        )
        return {
            "p": p_new,
            "value": value_new,
            "grad": grad_new,
            "d": jnp.where(renew, d_new, d),
            "steepest": restart | (carry["steepest"] & ~accept),
            "search": search,
            "lbfgs": lbfgs_state,
            "first": jnp.asarray(False),
            "i": jnp.where(step, i + 1, i),
            "history": history,
            "previous": jnp.where(accept, recent, carry["previous"]),
            "best_before": jnp.where(accept, best_before, carry["best_before"]),
            "exit": stop | bad_start | stalled,
            "converged": converged,
            "J": J,
            "r": r,
            "raw": raw,
        }

    zero = jnp.zeros((), p0.dtype)
    init = {
        "p": p0,
        "value": jnp.asarray(jnp.inf, p0.dtype),
        "grad": jnp.zeros_like(p0),
        "d": jnp.zeros_like(p0),
        "search": wolfe_start(zero, zero, zero),
        "lbfgs": lbfgs.init(p0),
        "first": jnp.asarray(True),
        "i": jnp.asarray(0),
        "history": jnp.full((steps,), jnp.nan, p0.dtype),
        "previous": jnp.full((10,), jnp.inf, p0.dtype),
        "best_before": jnp.asarray(jnp.inf, p0.dtype),
        "steepest": jnp.asarray(False),
        "exit": jnp.asarray(False),
        "converged": jnp.asarray(False),
        **_unset_outputs(problem, p0),
    }
    out = jax.lax.while_loop(cond, body, init)
    J, r, raw = out["J"], out["r"], out["raw"]
    if not forward:
        J, (r, raw) = jacobian(out["p"])
    return out["p"], out["history"], out["i"], out["converged"], J, r, raw


def _forward_mode_loss(problem: _Problem, jacobian):
    """The mean loss, differentiated through the forward-mode Jacobian of the residuals
    (``grad = 2 J^T r / n``) instead of in reverse mode.

    The compiled program then holds one kind of derivative code, the forward-mode pass of the
    covariance's Jacobian, wherever the line search evaluates the loss; a reverse-mode gradient
    compiles to larger code (measured: ~5 s more compile for the default fit). The price is run time:
    the forward pass carries a few tangents (:func:`_jacobian_with_residuals`) where reverse mode
    costs about two evaluations, about 1 s more on an 1800-sample record, several times less than
    the compile time it saves.
    """
    n = problem.count()

    @jax.custom_vjp
    def loss(p):
        r = problem.residuals(p)
        return jnp.sum(r * r) / n

    def forward(p):
        J, (r, _) = jacobian(p)
        return jnp.sum(r * r) / n, 2.0 * (J.T @ r) / n

    def backward(grad, g):
        return (g * grad,)

    loss.defvjp(forward, backward)
    return loss


def _gauss_newton_covariance(J, variance):
    """``variance (J^T J)^+`` and the projector onto the directions the pseudo-inverse drops: those
    the record does not determine (a steady spin says nothing of the inertia), whose standard
    errors are infinite rather than the pseudo-inverse's zero.

    From the singular value decomposition of ``J``, not the eigenvalues of ``J^T J``, whose roundoff
    (``eps`` of its largest eigenvalue) tilts the dropped directions: in float32 they leaned on
    well-determined parameters by more than 1e-3, and every standard error of a fit to noisy data
    came out infinite. A direction is dropped below ``sqrt(10 p eps)`` of the largest singular
    value (``p`` parameters), the cutoff ``10 p eps`` on the eigenvalues of ``J^T J``.
    """
    _, singular, vt = jnp.linalg.svd(J, full_matrices=False)
    determined = singular > singular[0] * float(np.sqrt(10 * J.shape[1] * np.finfo(J.dtype).eps))
    inverse = jnp.where(determined, 1 / jnp.where(determined, singular, 1.0) ** 2, 0.0)
    covariance = variance * (vt.T * inverse) @ vt
    undetermined = (vt.T * ~determined) @ vt
    return covariance, undetermined


@eqx.filter_jit
def _run(problem: _Problem, p0, method: str, optimizer, steps: int, tol: float, callback):
    """The compiled fit: the optimum, its history and step count, whether it converged, the
    Gauss–Newton covariance of the parameters, the final loss, the rms residual per component (robust,
    1.4826 times the median absolute residual, for a robust loss) and the robust one for every loss."""
    # The loss resolves changes of about its dtype's epsilon only (float32: 1.2e-7): a tolerance
    # below that could be met only by chance.
    tol = max(tol, 10.0 * float(jnp.finfo(p0.dtype).eps))
    if method == "levenberg-marquardt":
        p, history, n_steps, done, J, r, raw = _levenberg_marquardt(problem, p0, steps, tol, callback)
    elif optimizer is None:
        p, history, n_steps, done, J, r, raw = _lbfgs_fit(problem, p0, steps, tol, callback)
    else:
        p, history, n_steps, done, J, r, raw = _optax_fit(problem, p0, optimizer, steps, tol, callback)
    n = problem.count()
    dof = jnp.maximum(n - p.shape[0], 1.0)
    squares = jnp.sum(r * r)
    # A robust loss is chosen for outliers, whose residuals would set the scale of every standard
    # error (27x the spread of the fitted values, for 20 outliers of 3 rad/s among 600 values): its
    # scale is the median absolute residual's (1.4826 MAD, the standard deviation for normal noise).
    mad = jnp.nanmedian(jnp.where(problem.mask.reshape(-1), jnp.abs(r), jnp.nan))
    variance = jnp.where(problem.loss_index == 0, squares / dof, (1.4826 * mad) ** 2 * n / dof)
    covariance, undetermined = _gauss_newton_covariance(J, variance)
    counts = jnp.sum(problem.mask, axis=(0, 1)).astype(raw.dtype)
    rms = jnp.sqrt(jnp.sum(raw * raw, axis=(0, 1)) / jnp.maximum(counts, 1.0))
    # The rms is read against the noise estimate; with a robust loss the outliers it discounts would
    # make that ratio hundreds, so there the rms is estimated the same robust way as the noise.
    robust_rms = 1.4826 * jnp.nanmedian(jnp.where(problem.mask, jnp.abs(raw), jnp.nan), axis=(0, 1))
    robust_rms = jnp.where(counts > 0, robust_rms, 0.0)
    rms = jnp.where(problem.loss_index == 0, rms, robust_rms)
    return p, history, n_steps, done, (covariance, undetermined), squares / n, rms, robust_rms
