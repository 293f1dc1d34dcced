"""Test configuration: float64 and strict dtype promotion for every test.

Float32 tests opt in explicitly by building float32 inputs; with strict promotion an accidental
float32/float64 mix is an error rather than a silent upcast.
"""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
