"""Fitting an inertia tensor to a record of a body's motion: gyroscope (angular velocity) or motion
capture (orientation) samples, torque-free or under a known torque.

The path of the data: ``data`` checks the record, ``estimate`` finds a starting point from Euler's
equations (linear in the inertia), ``prepare`` cuts the record into windows and builds the residual
problem of ``problem``, ``optimisers`` minimises it, and ``fit`` turns the optimum into an
:class:`InertiaFit` (``result``) with standard errors.
"""

from .data import omega_from_orientations as omega_from_orientations
from .estimate import estimate_inertia as estimate_inertia
from .fit import fit_inertia as fit_inertia
from .fit import fit_inertia_to_orientation as fit_inertia_to_orientation
from .result import InertiaFit as InertiaFit
