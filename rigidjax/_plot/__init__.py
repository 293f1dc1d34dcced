"""The implementation of :mod:`rigidjax.plot` (matplotlib figures and animations of trajectories).

Import :mod:`rigidjax.plot`, not these modules: it checks that matplotlib is installed first."""
