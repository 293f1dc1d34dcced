"""Figures and animations of trajectories, drawn with matplotlib (an optional dependency: install
it with ``pip install 'rigidjax[plot]'``).

Each figure function takes a :class:`rigidjax.Trajectory` (and, for a batch, the index of a body in
the flattened batch) and returns the matplotlib Figure, so that it can be shown, saved or changed
further; pass ``fig=`` (or ``ax=``) to draw into a figure of your own. ``import rigidjax`` does not
import matplotlib; ``import rigidjax.plot`` does.

- :func:`poinsot`: the polhode on the energy ellipsoid and the herpolhode on the invariable plane;
- :func:`cones`: the body cone and the space cone of ``omega``;
- :func:`euler_angles`: the Euler angles over time;
- :func:`invariant_drift`: the relative drift of the conserved quantities, log scale;
- :func:`animate`: a 3-D animation of bodies turning, to ``.gif`` or ``.mp4``.
"""

try:
    import matplotlib as _matplotlib  # noqa: F401
except ImportError as _error:
    raise ImportError(
        "rigidjax.plot needs matplotlib, which is not installed: pip install 'rigidjax[plot]'"
    ) from _error

from ._plot.animation import animate as animate
from ._plot.figures import cones as cones
from ._plot.figures import euler_angles as euler_angles
from ._plot.figures import invariant_drift as invariant_drift
from ._plot.figures import poinsot as poinsot

__all__ = ["animate", "cones", "euler_angles", "invariant_drift", "poinsot"]
