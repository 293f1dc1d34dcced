"""Fitting an inertia tensor to a record of a body's motion: gyroscope (angular velocity) or motion
capture (orientation) samples, torque-free or under a known torque."""

from .fit import InertiaFit as InertiaFit
from .fit import _prepare_omega as _prepare_omega  # benchmarks/fit_methods.py builds the problem
from .fit import estimate_inertia as estimate_inertia
from .fit import fit_inertia as fit_inertia
from .fit import fit_inertia_to_orientation as fit_inertia_to_orientation
from .fit import omega_from_orientations as omega_from_orientations
