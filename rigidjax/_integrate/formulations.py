"""How a chunk of bodies is written as one ODE for the driver: its state layout, vector field,
solver and the way back to angular velocity and orientation.

- :class:`ScaledODE`: any diffrax solver, adaptive or not. The state is one array, rows ``u`` then
  the attitude, bodies on the last (contiguous) axis: ``u = omega / sigma`` (per-body,
  per-component scales that make tolerances dimensionless) and the attitude a quaternion (norm made
  attracting) or Euler angles.
- :class:`LieGroupODE`: :class:`rigidjax.solvers.RKMK` on ``(omega, q)``, bodies first.
- :class:`SplittingODE`: the Lie–Poisson splittings on ``(L, q)`` in each body's principal axes;
  the solver is built per chunk from the scene's parameters.
"""

import math
from typing import Any, ClassVar, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .._dynamics.inertia import principal_axes
from .._dynamics.state import State
from .._kinematics.euler import _euler_from_quat, _euler_rates, _quat_from_euler, is_proper_sequence
from .._kinematics.quaternion import (
    _quat_conjugate,
    _quat_derivative,
    _quat_from_matrix,
    _quat_multiply,
)
from .solvers.rkmk import rigid_body_vector_field
from .solvers.splitting import (
    HeavyTopSplitting,
    LiePoissonSplitting,
    _FreeBodyVectorField,
    _HeavyTopVectorField,
    with_model_parameters,
)


def lock_distance(angles, seq):
    """sin(theta) (proper sequences) or cos(theta) (Tait-Bryan): 0 at gimbal lock.

    Signed on purpose: theta starts inside (0, pi) or (-pi/2, pi/2), so a step that jumps over the
    lock (the event is only checked at step ends) leaves a negative value and is still caught.
    """
    theta = angles[..., 1]
    return jnp.sin(theta) if is_proper_sequence(seq) else jnp.cos(theta)


def _time_first(x):
    """``(T, components, bodies)`` or ``(T, bodies, components)`` -> ``(bodies, T, components)``."""
    return None if x is None else jnp.moveaxis(x, 0, 1)


@eqx.filter_jit
def _scaled_vector_field(shell, leaves, euler_seq, parts, t, y, args):
    """:meth:`ScaledODE.vector_field`'s field. Compiled as a function of its own so that it is traced
    once per solve rather than at every stage of every traced step: a written-out Dopri8 step calls
    it 13 times and diffrax traces its step three times, and tracing the per-body field under
    ``vmap`` each time was most of the integration's tracing time. The program is the same: XLA
    inlines the call."""
    values, scale, inverse_scale, pull_rate = parts

    def body_rhs(body_values, t, w, attitude, pull_rate, args):
        body = shell.replace_body_leaves(leaves, body_values)
        if attitude is None:
            return body.angular_acceleration(t, State(w, None), args), None
        if euler_seq is None:
            q = attitude
            dattitude = _quat_derivative(q, w, pull_rate)
        else:
            q = _quat_from_euler(attitude, euler_seq)
            dattitude = _euler_rates(attitude, w, euler_seq, throw=False)
        return body.angular_acceleration(t, State(w, q), args), dattitude

    # Bodies on the last (contiguous) axis of the state: measured 1.5-2x faster than bodies-first on
    # CPU (benchmarks/batch_strategies.py). The rows are split and joined outside the per-body
    # function: inside it (slices and a concatenation per body) the "balanced" preset ran 2x slower.
    attitude = y[3:] if y.shape[0] > 3 else None
    in_axes = (0, None, 1, None if attitude is None else 1, 0, None)
    domega, dattitude = jax.vmap(body_rhs, in_axes=in_axes, out_axes=1)(
        values, t, y[:3] * scale, attitude, pull_rate, args
    )
    du = (domega * inverse_scale).astype(y.dtype)
    return du if attitude is None else jnp.concatenate([du, dattitude.astype(y.dtype)])


# The solvers' own error constants are well below the Taylor remainder's: at the presets' tolerances
# their steps on moving bodies reach z = 0.6-1.9 times the remainder's step (heavy tops, tennis
# rackets), so the bound is this many times the remainder's, and does not shorten those steps.
REACH_MARGIN = 3.0


class ScaledODE(eqx.Module):
    """Omega scaled per body and component; bodies on the last axis; any diffrax solver.

    The state is one array ``(3 + a, bodies)``: rows 0-2 the scaled angular velocity ``u``, then the
    ``a`` attitude rows (4 for a quaternion, 3 for Euler angles, none without an orientation). One
    array rather than a ``(u, attitude)`` pair: the written-out stages of
    :class:`.solvers.unrolled.UnrolledDopri8` then fuse into one loop per stage (on 10^4
    tennis-racket bodies the pair ran 1.9x slower)."""

    euler_seq: str | None = eqx.field(static=True, default=None)
    lock_tolerance: float = eqx.field(static=True, default=1e-3)

    uses_scale: ClassVar[bool] = True

    def prepare(self, values, leaves):
        """What the other methods take as ``values``: the chunk's per-body model values as given."""
        return values

    def initial_state(self, values, leaves, omega0, q0, sigma):
        u = (omega0 / sigma).T
        if q0 is None:
            return u
        attitude = q0 if self.euler_seq is None else _euler_from_quat(q0, self.euler_seq)
        return jnp.concatenate([u, attitude.T.astype(u.dtype)])

    def vector_field(self, shell, leaves, values, sigma):
        scale = sigma.T
        inverse_scale = 1.0 / scale  # once per chunk: a division per stage was a hot spot
        # The quaternion's norm pull at a constant rate per body, its largest omega scale, rather than
        # at |omega|: no square root per stage (10^4 tennis-racket bodies, "balanced": 12 % less
        # time; the same steps, also for heavy tops).
        pull_rate = jnp.max(sigma, axis=-1)
        parts = (values, scale, inverse_scale, pull_rate)

        def vector_field(t, y, args):
            return _scaled_vector_field(shell, leaves, self.euler_seq, parts, t, y, args)

        return vector_field

    def chunk_solver(self, solver, values, leaves):
        return solver

    def first_step(self, vector_field, y0, sigma, ts, args):
        """A first trial step of 1% of the fastest body's turn (or of sqrt(1/|omega_dot|) for a body
        at rest): diffrax's generic guess overshoots by orders of magnitude at 1e4 rad/s, overflows,
        and the rejected NaN step poisons reverse-mode gradients."""
        speed = jnp.max(jnp.abs(y0[:3].T * sigma))
        accel = jnp.max(jnp.abs(vector_field(ts[0], y0, args)[:3] * sigma.T))
        rate = jax.lax.stop_gradient(jnp.maximum(speed, jnp.sqrt(accel)))
        span = ts[-1] - ts[0]
        first = jnp.where(rate > 0, jnp.minimum(0.01 / jnp.where(rate > 0, rate, 1.0), span), span)
        return jnp.where(first > 0, first, 1.0)  # a single output time

    def step_bound(self, vector_field, y0, sigma, ts, args, rtol, order):
        """The longest step that resolves the linearised motion about ``y0``: ``c / rate``, with
        ``rate`` a bound on the spectral radius of the vector field's Jacobian (the fastest body's)
        and ``c`` the step at which the Taylor remainder of ``exp(z)``, ``|z|^(p+1) / (p+1)!``,
        reaches ``rtol``.

        The controller sees only the state's error, and a body at an equilibrium (a top hanging or
        upright at rest) has none: one step then spanned the whole run, and the derivatives, which
        follow the linearised motion, were those of that single step (1000x off). Moving bodies
        take steps several times shorter than this bound, which then never binds.

        The rate: the Jacobian's blocks ``A = du'/du``, ``B = du'/da``, ``C = da'/du``,
        ``D = da'/da`` (``u`` the scaled omega, ``a`` the attitude) bound it by
        ``max(|A|, |D|) + sqrt(|B| |C|)`` (infinity norms; the block scaling that balances ``B``
        and ``C``), which keeps the units apart: ``sqrt(|B| |C|)`` is a pendulum's
        ``sqrt(m g l / I)``."""
        n_rows = y0.shape[0]
        directions = jnp.broadcast_to(jnp.eye(n_rows, dtype=y0.dtype)[:, :, None], (n_rows,) + y0.shape)

        def column(direction):
            return jax.jvp(lambda y: vector_field(ts[0], y, args), (y0,), (direction,))[1]

        jacobian = jnp.swapaxes(jax.vmap(column)(jax.lax.stop_gradient(directions)), 0, 1)
        # In omega itself, not omega scaled per component: the scales' ratios would enter the norms.
        unscale = jnp.concatenate([sigma.T, jnp.ones((n_rows - 3,) + y0.shape[1:], y0.dtype)])
        jacobian = jnp.abs(jacobian * unscale[:, None, :] / unscale[None, :, :])

        def norm(block):  # (rows, columns, bodies) -> (bodies,): the largest row sum
            return jnp.max(jnp.sum(block, axis=1), axis=0)

        rate = norm(jacobian[:3, :3])
        if n_rows > 3:
            coupling = jnp.sqrt(norm(jacobian[:3, 3:]) * norm(jacobian[3:, :3]))
            rate = jnp.maximum(rate, norm(jacobian[3:, 3:])) + coupling
        rate = jax.lax.stop_gradient(jnp.max(jnp.where(jnp.isfinite(rate), rate, 0.0)))
        factorial = float(math.factorial(order + 1))
        reach = REACH_MARGIN * jnp.minimum(factorial * jnp.asarray(rtol, y0.dtype), 1.0) ** (
            1.0 / (order + 1)
        )
        return jnp.where(rate > 0, reach / jnp.where(rate > 0, rate, 1.0), jnp.inf)

    def event(self):
        if self.euler_seq is None:
            return None
        seq, tolerance = self.euler_seq, self.lock_tolerance

        def margin(t, y, args, **kwargs):
            # In the default float dtype: diffrax compares it with a Python 0.0 (float64 under x64).
            return (jnp.min(lock_distance(y[3:].T, seq)) - tolerance).astype(jnp.result_type(float))

        # A real-valued condition, its crossing found by Newton on the dense output: a boolean one
        # is seen at step ends only, and a smooth motion's long steps ran past the lock (through
        # theta = 0 to 0.11 s later) with the samples in between returned as valid.
        # (Its tolerance on the time is one float32 resolves: Newton converges quadratically, so
        # the located time is far closer than that; at 1e-8 it did not converge in float32.)
        return diffrax.Event(margin, root_finder=optx.Newton(rtol=1e-5, atol=1e-5))

    @staticmethod
    def save_fn(t, y, args):
        """Each sample is kept bodies-first, ``(bodies, rows)``: transposing one sample (a few kB, in
        cache) as it is saved is far cheaper than transposing the whole ``(T, rows, bodies)`` record
        afterwards (measured with 10^4 bodies and 800 samples: the whole-record transpose made
        "fast" 45 % and "balanced" 20 % slower)."""
        return y.T

    def outputs(self, ys, values, leaves, sigma):
        ys = jnp.transpose(ys, (1, 0, 2))  # (T, bodies, rows), saved transposed by save_fn
        omega = ys[..., :3] * sigma[:, None, :]
        if ys.shape[-1] == 3:
            return omega, None
        q = ys[..., 3:]
        if self.euler_seq is not None:
            q = _quat_from_euler(q, self.euler_seq)
        return omega, q


class LieGroupODE(eqx.Module):
    """RKMK on ``(omega, q)``, bodies first; scenes without an orientation carry the identity."""

    uses_scale: ClassVar[bool] = False
    save_fn: ClassVar[None] = None  # the state is bodies-first already

    def prepare(self, values, leaves):
        return values

    def initial_state(self, values, leaves, omega0, q0, sigma):
        if q0 is None:
            q0 = jnp.zeros(omega0.shape[:-1] + (4,), omega0.dtype).at[..., 0].set(1.0)
        return omega0, q0

    def vector_field(self, shell, leaves, values, sigma):
        def accel_one(body_values, t, w, q, args):
            body = shell.replace_body_leaves(leaves, body_values)
            return body.angular_acceleration(t, State(w, q), args)

        def accel(t, w, q, args):
            return jax.vmap(accel_one, in_axes=(0, None, 0, 0, None))(values, t, w, q, args).astype(w.dtype)

        return rigid_body_vector_field(accel)

    def chunk_solver(self, solver, values, leaves):
        return solver

    def event(self):
        return None

    def outputs(self, ys, values, leaves, sigma):
        omega, q = ys
        return _time_first(omega), _time_first(q)


class _Frame(NamedTuple):
    named: dict[str, Any]  # the chunk's per-body parameters by field name
    moments: Any  # (n, 3) principal moments
    axes: Any  # (n, 3, 3) principal -> body components, None for principal moments given
    axes_q: Any  # the same rotation as a quaternion


class SplittingODE(eqx.Module):
    """The Lie–Poisson splittings on ``(L, q)`` in each body's principal axes (a tensor inertia is
    diagonalised once per body). The solver's parameters come from the scene, per chunk."""

    heavy_top: bool = eqx.field(static=True)
    order: int = eqx.field(static=True)

    uses_scale: ClassVar[bool] = False
    save_fn: ClassVar[None] = None  # the state is bodies-first already

    def prepare(self, values, leaves):
        """The chunk's parameters by name and its principal frame, computed once per chunk: a tensor
        inertia ``(n, 3, 3)`` is diagonalised here, and the other methods take this in place of
        ``values``."""
        named = dict(zip([leaf.label for leaf in leaves], values, strict=True))
        inertia = named["inertia"]
        if inertia.ndim == 3:  # (n, 3, 3) tensors: integrate in each body's principal axes
            moments, axes = principal_axes(inertia)  # axes: principal -> body components
            return _Frame(named, moments, axes, _quat_from_matrix(axes))
        return _Frame(named, inertia, None, None)

    def initial_state(self, values, leaves, omega0, q0, sigma):
        _, moments, axes, axes_q = values
        if q0 is None:
            q0 = jnp.zeros(omega0.shape[:-1] + (4,), omega0.dtype).at[..., 0].set(1.0)
        if axes is not None:
            omega0 = jnp.einsum("nji,nj->ni", axes, omega0)
            q0 = _quat_multiply(q0, axes_q)
        return moments * omega0, q0

    def _parameters(self, values, leaves):
        named, moments, axes, _ = values
        if not self.heavy_top:
            return moments, None
        com = named["com"] if axes is None else jnp.einsum("nji,nj->ni", axes, named["com"])
        return moments, (named["mass"], com, named["gravity"])

    def vector_field(self, shell, leaves, values, sigma):
        moments, top = self._parameters(values, leaves)
        if top is None:
            return _FreeBodyVectorField(moments)
        return _HeavyTopVectorField(moments, *top)

    def chunk_solver(self, solver, values, leaves):
        moments, top = self._parameters(values, leaves)
        if top is None:
            return with_model_parameters(LiePoissonSplitting(order=self.order), moments)
        return with_model_parameters(HeavyTopSplitting(order=self.order), moments, *top)

    def event(self):
        return None

    def outputs(self, ys, values, leaves, sigma):
        _, moments, axes, axes_q = values
        L, q = ys  # (T, bodies, 3), (T, bodies, 4)
        omega = L / moments
        if axes is not None:
            omega = jnp.einsum("nij,tnj->tni", axes, omega)
            q = _quat_multiply(q, _quat_conjugate(axes_q))
        return _time_first(omega), _time_first(q)
