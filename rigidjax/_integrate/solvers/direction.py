"""The direction of time of a diffrax solve, for solvers that step by their own maps."""


def time_direction(terms):
    """-1 when ``diffeqsolve`` runs from a later to an earlier time, else 1: it then integrates
    forward in ``-t`` with its terms wrapped (``diffrax.WrapTerm``, ``direction`` -1), so a solver
    that steps by its own maps instead of the term's ``contr`` steps by ``direction * (t1 - t0)``
    and its dense output evaluates at ``direction * (t - t0)``."""
    return getattr(terms, "direction", 1)
