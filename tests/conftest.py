"""Test configuration: float64 and strict dtype promotion for every test.

Float32 tests opt in explicitly by building float32 inputs; with strict promotion an accidental
float32/float64 mix is an error rather than a silent upcast.
"""

import jax
import jaxtyping
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def without_runtime_typecheck():
    """The test run checks annotations with jaxtyping first; turn that off to see rigidjax's own checks."""
    old = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", old)
