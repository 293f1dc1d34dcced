"""rigidjax's structure-preserving solvers, written as diffrax solvers that run at a fixed step."""

from .rkmk import RKMK
from .splitting import HeavyTopSplitting, LiePoissonSplitting

STRUCTURE_PRESERVING = (HeavyTopSplitting, LiePoissonSplitting, RKMK)
"""The solvers that :func:`rigidjax.simulate` runs at the fixed step ``dt0``."""

__all__ = ["STRUCTURE_PRESERVING", "RKMK", "HeavyTopSplitting", "LiePoissonSplitting"]
