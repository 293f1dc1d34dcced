"""Inertia at the ends of the float range: the shape helpers refuse moments that overflow or underflow
their dtype (they returned inf, or 0 for a positive mass and size), and ``check_inertia`` says why
subnormal moments fail.

The references are NumPy: the textbook formulas evaluated in float64 (or with ``log10`` where the
moments themselves overflow float64) and ``np.finfo``, which reads subnormals as they are."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import expect_error

import rigidjax as rj

F32 = np.float32
TINY32, TINY64 = float(np.finfo(np.float32).tiny), float(np.finfo(np.float64).tiny)

# The textbook moments of each shape helper, for a mass m and every length (radius, height, edge) r.
SHAPES = {
    "solid_sphere": lambda m, r: [0.4 * m * r * r] * 3,
    "hollow_sphere": lambda m, r: [2 / 3 * m * r * r] * 3,
    "thin_rod": lambda m, r: [m * r * r / 12] * 2 + [0.0],
    "thin_disc": lambda m, r: [m * r * r / 4] * 2 + [m * r * r / 2],
    "solid_cylinder": lambda m, r: [m * (3 * r * r + r * r) / 12] * 2 + [m * r * r / 2],
    "hollow_cylinder": lambda m, r: [m * (6 * r * r + r * r) / 12] * 2 + [m * r * r],
    "solid_box": lambda m, r: [m * 2 * r * r / 12] * 3,
    "solid_ellipsoid": lambda m, r: [m * 2 * r * r / 5] * 3,
}


def call_shape(name, mass, length):
    """``rigidjax.<name>`` of a body of ``mass`` whose every length (radius, height, edge) is ``length``."""
    mass, length = jnp.asarray(mass), jnp.asarray(length)
    if name in ("solid_box", "solid_ellipsoid"):
        return getattr(rj, name)(mass, jnp.stack([length] * 3))
    if name in ("solid_cylinder", "hollow_cylinder"):
        return getattr(rj, name)(mass, length, length)
    return getattr(rj, name)(mass, length)


def _words(name, dtype, problem):
    hint = ["units"] if dtype == "float64" else ["units", "float64"]
    return [f"{name}: the moments of inertia {problem} {dtype}", *hint]


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_shape_helpers_refuse_moments_that_overflow(name):
    """1e300 kg of radius 1e10 m: each textbook moment is above float64's largest number (by
    log10), and the helpers returned inf."""
    mass, length = 1e300, 1e10
    assert np.log10(mass) + 2 * np.log10(length) + np.log10(0.08) > np.log10(np.finfo(np.float64).max)
    words = _words(name, "float64", "overflow")
    with pytest.raises(ValueError) as info:
        call_shape(name, mass, length)
    for word in words:
        assert word in str(info.value)
    expect_error(lambda: jax.jit(lambda m, r: call_shape(name, m, r))(mass, length), *words)
    # float32: a squared length above its range (1e20^2) though the moments fit (1e-10 kg).
    mass32, length32 = F32(1e-10), F32(1e20)
    assert 1e20**2 > float(np.finfo(F32).max) > max(SHAPES[name](1e-10, 1e20))
    expect_error(lambda: call_shape(name, mass32, length32), *_words(name, "float32", "overflow"))


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_shape_helpers_refuse_moments_that_underflow(name):
    """A positive mass and size whose moments are below the dtype's smallest normal number: the
    helpers returned zero moments (float32 on CPU flushes the subnormal 4e-39 of a 1e-22 kg ball of
    radius 1e-8 m to 0). A radius whose square underflows gives no moment either, also where the
    moment itself is within the range (1e30 kg of radius 1e-25 m: 4e-21 kg m^2)."""
    for mass, length, dtype in [(1e-22, 1e-8, F32), (1e30, 1e-25, F32), (1e-300, 1e-5, np.float64)]:
        expected = np.array(SHAPES[name](mass, length))
        assert expected.max() > 0
        if mass < 1:  # the moments themselves are below the smallest normal number
            assert np.all(expected < np.finfo(dtype).tiny)
        else:  # the moments fit; the squared length does not
            assert np.all(expected[expected > 0] > np.finfo(dtype).tiny) and length**2 < np.finfo(dtype).tiny
        words = _words(name, np.dtype(dtype).name, "underflow")
        args = dtype(mass), dtype(length)
        with pytest.raises(ValueError) as info:
            call_shape(name, *args)
        for word in words:
            assert word in str(info.value)
        expect_error(lambda args=args: jax.jit(lambda m, r: call_shape(name, m, r))(*args), *words)
        batch = [jnp.asarray([1.0, a], dtype) for a in args]
        expect_error(lambda batch=batch: jax.vmap(lambda m, r: call_shape(name, m, r))(*batch), *words)


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_moments_near_the_ends_of_the_range_and_intended_zeros_pass(name):
    """The checks do not narrow the range: moments just inside it are returned, and so are the zeros
    of the formulas (a zero mass, a zero size, a thin rod about its axis, a box with two zero edges)."""
    for mass, length, dtype in [(1e-20, 1e-8, F32), (1e-280, 1e-10, np.float64), (1e290, 1e5, np.float64)]:
        expected = np.array(SHAPES[name](mass, length))
        assert np.all((expected == 0) | (expected > np.finfo(dtype).tiny))
        assert np.all(expected < np.finfo(dtype).max)
        got = call_shape(name, dtype(mass), dtype(length))
        assert got.dtype == dtype
        np.testing.assert_allclose(got, expected, rtol=10 * np.finfo(dtype).eps, atol=0)
    for mass, length in [(0.0, 2.0), (3.0, 0.0), (0.0, 0.0), (0.0, 1e100)]:
        np.testing.assert_array_equal(call_shape(name, mass, length), [0.0, 0.0, 0.0])
        jitted = jax.jit(lambda m, r: call_shape(name, m, r))(mass, length)
        np.testing.assert_array_equal(jitted, [0.0, 0.0, 0.0])


def test_the_bounds_are_the_dtype_s_smallest_and_largest_numbers():
    """A float32 ball of 1e-21 kg and radius 1e-8 m has moments 4e-38, above finfo.tiny = 1.2e-38:
    returned as the float64 formula gives them; a thin rod keeps its zero moment about its axis; a
    box with two zero edges its zero moment about the third."""
    moment = 0.4 * float(F32(1e-21)) * float(F32(1e-8)) ** 2
    assert TINY32 < moment < 4 * TINY32
    np.testing.assert_allclose(rj.solid_sphere(F32(1e-21), F32(1e-8)), [moment] * 3, rtol=1e-6)
    rod = rj.thin_rod(F32(1e30), F32(1e-10))
    np.testing.assert_allclose(rod, [1e30 * 1e-20 / 12] * 2 + [0.0], rtol=1e-6)
    assert rod[2] == 0
    np.testing.assert_allclose(
        rj.solid_box(2.0, jnp.array([1.0, 0.0, 0.0])), [0.0, 2 / 12, 2 / 12], rtol=1e-15
    )
    assert 0 < 1e-300 * 1e-5**2 < TINY64
    expect_error(lambda: rj.solid_box(1e-300, jnp.array([1e-5, 0.0, 0.0])), "underflow float64")


def test_gradients_in_the_range_are_the_textbook_ones():
    """The checks carry no derivative: d(sum of moments)/d(mass, radius) of a solid ball is
    (6 r^2 / 5, 12 m r / 5), eagerly and under jit."""
    grad = jax.grad(lambda m, r: jnp.sum(rj.solid_sphere(m, r)), argnums=(0, 1))
    for g in (grad, jax.jit(grad)):
        np.testing.assert_allclose(g(2.0, 0.5), (6 * 0.5**2 / 5, 12 * 2.0 * 0.5 / 5), rtol=1e-15)


def _programs_compiled(call) -> int:
    """How many XLA programs ``call()`` compiles (JAX's compile events), JAX's disk cache off."""
    seen = []

    def listen(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            seen.append(duration)

    enabled = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        jax.block_until_ready(call())
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
        jax.config.update("jax_enable_compilation_cache", enabled)
    return len(seen)


def test_the_range_checks_stay_in_the_one_program_of_an_eager_call():
    """Called eagerly, a shape helper is still one compiled program with its checks (on shapes no
    other test uses), and ``check_inertia`` too."""
    mass, radius, size = np.full((7, 13), 2.0), np.full((7, 13), 0.5), np.ones((7, 13, 3))
    assert _programs_compiled(lambda: rj.solid_sphere(mass, radius)) == 1
    assert _programs_compiled(lambda: rj.solid_box(mass, size)) == 1
    assert _programs_compiled(lambda: rj.check_inertia(size)) == 1


SUBNORMAL = [
    ("float64", np.array([1e-310] * 3)),
    ("float32", np.array([1e-40] * 3, F32)),
    ("float64", np.array([1e-310, 1.0, 1.0])),
    ("float64", np.diag([1e-310, 2e-310, 2e-310])),
]


@pytest.mark.parametrize(("dtype", "inertia"), SUBNORMAL, ids=["f64", "f32", "one-of-three", "tensor"])
def test_check_inertia_says_why_subnormal_moments_fail(dtype, inertia):
    """Positive moments below the smallest normal number (NumPy reads them as they are; XLA on CPU
    reads them as 0) fail as zero moments: the message said only "non-positive", which they are
    not; it now names the dtype's smallest normal number and the remedy."""
    diagonal = np.diagonal(inertia) if inertia.ndim == 2 else inertia
    tiny = np.finfo(inertia.dtype).tiny
    assert np.all(diagonal > 0) and np.any(diagonal < tiny)
    words = [f"below {tiny:.3g} kg m^2 ({dtype}'s smallest normal number) reads as 0 on CPU", "smaller units"]
    words += [] if dtype == "float64" else ["or use float64"]
    with pytest.raises(ValueError) as info:
        rj.check_inertia(inertia)
    for word in words:
        assert word in str(info.value)
    expect_error(lambda: jax.jit(rj.check_inertia)(inertia), *words)
    assert not rj.is_physical_inertia(inertia)
