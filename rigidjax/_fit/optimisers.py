"""The optimisers of the fit, both one compiled loop over a :class:`_Problem`'s flat parameters:
Levenberg–Marquardt on its residuals (the Jacobian by forward mode), or any optax
``GradientTransformation`` on its mean loss. :func:`_run` adds the covariance at the optimum.

``callback``, when given, is called on the host after every iteration as
``callback(iteration, loss, step_norm)`` (the loss and the step in the optimiser's scaled units)."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import optax

from .problem import _Problem


def _levenberg_marquardt(problem: _Problem, p0, steps: int, tol: float, callback):
    """Levenberg–Marquardt with Marquardt's diagonal scaling; the Jacobian by forward mode (few
    parameters, many residuals).

    Returns ``(p, history, iterations, converged, J)`` with the Jacobian at the final ``p``. The
    Jacobian appears once in the program (at the top of the loop body; the loop runs one extra,
    step-free pass to evaluate it at the final point), which halves the compile time against
    evaluating it again after the loop.
    """
    jacobian = jax.jacfwd(problem.residuals)
    n = problem.count()

    def cond(carry):
        return ~carry["exit"]

    def body(carry):
        p, r, lam, i = carry["p"], carry["r"], carry["lam"], carry["i"]
        J = jacobian(p)
        finished = carry["finished"]
        g = J.T @ r
        A = J.T @ J
        d = jnp.maximum(jnp.diag(A), 1e-12 * jnp.max(jnp.diag(A)) + 1e-300)
        f = jnp.sum(r * r)

        # Try the step, raising the damping until it lowers the loss (at most 12 tries).
        def retry_cond(c):
            _, _, f_new, tries, _ = c
            return ~finished & ((tries == 0) | (~(f_new < f) & (tries < 12)))

        def retry_body(c):
            lam, _, _, tries, _ = c
            lam = jnp.where(tries == 0, lam, lam * 4.0)
            step = jnp.linalg.solve(A + lam * jnp.diag(d), -g)
            r_new = problem.residuals(p + step)
            return lam, step, jnp.sum(r_new * r_new), tries + 1, r_new

        init = (lam, jnp.zeros_like(p), jnp.asarray(jnp.inf, f.dtype), 0, r)
        lam, step, f_new, _, r_new = jax.lax.while_loop(retry_cond, retry_body, init)
        improved = ~finished & jnp.isfinite(f_new) & (f_new < f)
        p_next = jnp.where(improved, p + step, p)
        r_next = jnp.where(improved, r_new, r)
        f_next = jnp.where(improved, f_new, f)
        lam = jnp.where(improved, jnp.maximum(lam / 5.0, 1e-12), lam)
        small_change = (f - f_next) <= tol * f_next
        small_step = jnp.max(jnp.abs(step)) <= tol * (1.0 + jnp.max(jnp.abs(p)))
        tiny_gradient = jnp.max(jnp.abs(g)) <= tol * tol * (f + 1e-300)
        converged = (improved & (small_change | small_step)) | tiny_gradient
        # No damping makes the step lower the loss: a minimum to roundoff if the last accepted step
        # barely changed the loss, a failure otherwise.
        stalled = ~finished & ~improved
        converged = converged | (stalled & (carry["last_decrease"] <= jnp.sqrt(tol)))
        decrease = jnp.where(improved, (f - f_next) / jnp.maximum(f_next, 1e-300), carry["last_decrease"])
        history = jnp.where(finished, carry["history"], carry["history"].at[i].set(f_next / n))
        if callback is not None:  # not in the step-free pass after the last step

            def report():
                jax.debug.callback(callback, i + 1, f_next / n, jnp.linalg.norm(p_next - p), ordered=True)

            jax.lax.cond(finished, lambda: None, report)
        i_next = jnp.where(finished, i, i + 1)
        return {
            "p": p_next,
            "r": r_next,
            "lam": lam,
            "i": i_next,
            "history": history,
            # The pass after the last step only evaluates J at the final point.
            "exit": finished,
            "finished": finished | converged | stalled | (i_next >= steps),
            "converged": carry["converged"] | (~finished & converged),
            "last_decrease": decrease,
            "J": J,
        }

    r0 = problem.residuals(p0)
    false = jnp.asarray(False)
    init = {
        "p": p0,
        "r": r0,
        "lam": jnp.asarray(1.0, p0.dtype),
        "i": jnp.asarray(0),
        "history": jnp.full((steps,), jnp.nan, p0.dtype),
        "exit": false,
        "finished": jnp.asarray(steps <= 0),
        "converged": false,
        "last_decrease": jnp.asarray(jnp.inf, p0.dtype),
        "J": jnp.zeros((r0.shape[0], p0.shape[0]), p0.dtype),
    }
    out = jax.lax.while_loop(cond, body, init)
    return out["p"], out["history"], out["i"], out["converged"], out["J"]


@functools.cache
def _default_optimizer():
    # One object for every call: the optimiser is static in the compiled fit, so a new object
    # would recompile it.
    return optax.lbfgs()


def _optax_fit(problem: _Problem, p0, optimizer, steps: int, tol: float, callback):
    """Minimises the mean loss with an optax optimiser until it stops changing (over the last ten
    iterations) or ``steps`` run out. Returns ``(p, history, iterations, converged)``."""
    optimizer = optax.with_extra_args_support(optimizer)
    state0 = optimizer.init(p0)
    try:  # line-search optimisers (L-BFGS) keep the last value and gradient in their state
        reuses_value = optax.tree_utils.tree_get(state0, "value", None) is not None
    except (KeyError, ValueError):
        reuses_value = False
    if reuses_value:
        value_and_grad = optax.value_and_grad_from_state(problem.loss)
    else:

        def value_and_grad(p, state):
            del state
            return jax.value_and_grad(problem.loss)(p)

    def cond(carry):
        _, _, i, _, done, _ = carry
        return (i < steps) & ~done

    def body(carry):
        p, state, i, history, _, previous = carry
        value, grad = value_and_grad(p, state=state)
        updates, state = optimizer.update(grad, state, p, value=value, grad=grad, value_fn=problem.loss)
        p = optax.apply_updates(p, updates)
        history = history.at[i].set(value)
        if callback is not None:
            step_norm = jnp.sqrt(sum(jnp.sum(u * u) for u in jax.tree_util.tree_leaves(updates)))
            jax.debug.callback(callback, i + 1, value, step_norm, ordered=True)
        # Converged when the loss has stopped changing over the last ten iterations. An integrated
        # model's loss is smooth only to about the solver's rtol (1e-10; step-size decisions jump),
        # so changes below 1e-8 of it are noise there (and statistically irrelevant: parameters move
        # by ~1e-4 of their standard errors).
        loss_tol = tol if problem.torque is None else max(tol, 1e-8)
        previous = previous.at[i % 10].set(value)
        spread = jnp.max(previous) - jnp.min(previous)
        done = (i >= 10) & (spread <= loss_tol * jnp.abs(value))
        return p, state, i + 1, history, done, previous

    history = jnp.full((steps,), jnp.nan, p0.dtype)
    recent = jnp.full((10,), jnp.inf, p0.dtype)
    init = (p0, state0, jnp.asarray(0), history, jnp.asarray(False), recent)
    p, _, i, history, done, _ = jax.lax.while_loop(cond, body, init)
    return p, history, i, done


@eqx.filter_jit
def _run(problem: _Problem, p0, method: str, optimizer, steps: int, tol: float, callback):
    """The compiled fit: the optimum, its history and step count, whether it converged, the
    Gauss–Newton covariance of the parameters, the final loss and the rms residual per component."""
    if method == "levenberg-marquardt":
        p, history, n_steps, done, J = _levenberg_marquardt(problem, p0, steps, tol, callback)
    else:
        p, history, n_steps, done = _optax_fit(problem, p0, optimizer, steps, tol, callback)
        # The integrated (torque) model is differentiable in reverse mode only on this path.
        J = (jax.jacrev if problem.reverse_mode else jax.jacfwd)(problem.residuals)(p)
    r = problem.residuals(p)
    n = problem.count()
    dof = jnp.maximum(n - p.shape[0], 1.0)
    variance = jnp.sum(r * r) / dof
    covariance = variance * jnp.linalg.pinv(J.T @ J, hermitian=True)
    raw = problem.raw_residuals(p)
    counts = jnp.sum(problem.mask, axis=(0, 1)).astype(raw.dtype)
    rms = jnp.sqrt(jnp.sum(raw * raw, axis=(0, 1)) / jnp.maximum(counts, 1.0))
    return p, history, n_steps, done, covariance, problem.loss(p), rms
