"""Integrators for rigid bodies, as diffrax solvers, and the settings of ``simulate``'s presets.

- :class:`RKMK`: Runge–Kutta–Munthe-Kaas on ``(omega, q)``, adaptive, unit quaternions by
  construction, any torque.
- :class:`LiePoissonSplitting`: the free body's symplectic splitting (energy error bounded,
  ``|L|`` and space-frame ``L`` kept to roundoff).
- :class:`HeavyTopSplitting`: the heavy top's splitting (vertical ``L`` kept to roundoff).
- :class:`UnrolledDopri8`: :class:`diffrax.Dopri8` with its stages written out, the same values at
  about a third of the cost per step in ``simulate`` (the ``"balanced"`` and ``"precise"`` presets
  on 1024 bodies or more, when not differentiated); with other vector fields, measure.

Each is a diffrax solver: pass it to ``rigidjax.simulate(..., solver=..., dt0=...)`` (the scene's
parameters then come from the model) or to ``diffrax.diffeqsolve`` with the vector fields of this
module (:func:`rigid_body_vector_field`, :func:`free_body_vector_field`,
:func:`heavy_top_vector_field`). The steps behind them are here too (:func:`rkmk_step` with
:func:`dexpinv`, :func:`splitting_step`, :func:`heavy_top_splitting_step`), and so are runs of
``n_steps`` fixed steps without diffrax (:func:`split_free_body`, :func:`split_heavy_top`).
``PRESETS`` maps each ``accuracy`` name of ``simulate`` to its diffrax solver class and relative
tolerance; :func:`preset` gives the solver and tolerance a run of a given batch and dtype uses.
"""

from ._integrate.presets import PRESETS as PRESETS
from ._integrate.presets import preset as preset
from ._integrate.solvers.rkmk import RKMK as RKMK
from ._integrate.solvers.rkmk import dexpinv as dexpinv
from ._integrate.solvers.rkmk import rigid_body_vector_field as rigid_body_vector_field
from ._integrate.solvers.rkmk import rkmk_step as rkmk_step
from ._integrate.solvers.splitting import HeavyTopSplitting as HeavyTopSplitting
from ._integrate.solvers.splitting import LiePoissonSplitting as LiePoissonSplitting
from ._integrate.solvers.splitting import free_body_vector_field as free_body_vector_field
from ._integrate.solvers.splitting import heavy_top_splitting_step as heavy_top_splitting_step
from ._integrate.solvers.splitting import heavy_top_vector_field as heavy_top_vector_field
from ._integrate.solvers.splitting import split_free_body as split_free_body
from ._integrate.solvers.splitting import split_heavy_top as split_heavy_top
from ._integrate.solvers.splitting import splitting_step as splitting_step
from ._integrate.solvers.unrolled import UnrolledDopri8 as UnrolledDopri8

__all__ = [
    "PRESETS",
    "RKMK",
    "HeavyTopSplitting",
    "LiePoissonSplitting",
    "UnrolledDopri8",
    "dexpinv",
    "free_body_vector_field",
    "heavy_top_splitting_step",
    "heavy_top_vector_field",
    "preset",
    "rigid_body_vector_field",
    "rkmk_step",
    "split_free_body",
    "split_heavy_top",
    "splitting_step",
]
