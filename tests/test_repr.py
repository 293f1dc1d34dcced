"""Reprs of the scenes, the torques and InertiaFit: class names, shapes and (for small arrays) values,
never array dumps; short for a batch of 10^4 bodies; shapes only for traced values inside jit."""

import jax
import jax.numpy as jnp
import numpy as np

import rigidjax as rj
from rigidjax._repr import summarize


def _no_dump(text):
    assert "Array(" not in text and "array(" not in text and "..." not in text, text


def test_heavy_top_shows_small_arrays_with_values():
    top = rj.HeavyTop(np.array([1.0, 1.0, 0.5]), 1.0, np.array([0.0, 0.0, 0.3]))
    assert repr(top) == "HeavyTop(inertia=f64[3] (1, 1, 0.5), mass=1.0, com=f64[3] (0, 0, 0.3), gravity=9.81)"


def test_every_model_and_torque_is_named_with_its_fields():
    cases = [
        (rj.FreeBody(np.array([1.0, 2.0, 3.0])), "FreeBody(inertia=f64[3] (1, 2, 3))"),
        (
            rj.Gyrostat(np.array([1.0, 2.0, 3.0]), np.array([0.0, 5.0, 0.0])),
            "Gyrostat(inertia=f64[3] (1, 2, 3), rotor_momentum=f64[3] (0, 5, 0))",
        ),
        (
            rj.RigidBody(np.eye(3), torque=rj.ViscousDamping(0.1)),
            "RigidBody(inertia=f64[3,3] ((1, 0, 0), (0, 1, 0), (0, 0, 1)), "
            "torque=ViscousDamping(coefficient=0.1))",
        ),
    ]
    for model, expected in cases:
        assert repr(model) == expected

    def spin_up(t, state, args):
        return state.omega

    torques = (
        rj.ConstantTorque(np.array([0.0, 0.0, 1.0]), frame="space"),
        rj.Torque(spin_up, needs_orientation=False),
        rj.GravityTorque(2.0, np.array([0.0, 0.0, 0.1])),
    )
    text = repr(rj.RigidBody(np.array([1.0, 2.0, 3.0]), torque=torques))
    assert text.startswith("RigidBody(inertia=f64[3] (1, 2, 3), torque=(ConstantTorque(")
    for part in (
        "ConstantTorque(torque=f64[3] (0, 0, 1), frame='space')",
        "Torque(fn=test_every_model_and_torque_is_named_with_its_fields.<locals>.spin_up, params=None, "
        "needs_orientation=False)",
        "GravityTorque(mass=2.0, com=f64[3] (0, 0, 0.1), gravity=9.81)",
    ):
        assert part in text, text
    _no_dump(text)


def test_a_batch_of_ten_thousand_bodies_is_one_short_line():
    n = 10_000
    rng = np.random.default_rng(0)
    inertia = rng.uniform(1.0, 2.0, (n, 3))
    for model in (
        rj.FreeBody(inertia),
        rj.HeavyTop(
            inertia, np.ones(n), np.array([0.0, 0.0, 0.1]), torque=rj.ConstantTorque(np.ones((n, 3)))
        ),
        rj.Gyrostat(inertia.astype(np.float32), np.zeros((n, 3), np.float32)),
    ):
        text = repr(model)
        assert len(text) < 200 and "\n" not in text, text
        assert text.startswith(type(model).__name__ + "(")
        assert "[10000,3]" in text and "batch_shape=(10000,)" in text
        _no_dump(text)
    assert "f32[10000,3]" in repr(rj.Gyrostat(inertia.astype(np.float32), np.zeros((n, 3), np.float32)))


def test_a_trajectory_of_jax_vmap_is_one_line():
    """jax.vmap of simulate stacks a time axis per body: the repr formatted ts[0], now an array, and
    raised."""
    traj = jax.vmap(
        lambda w: rj.simulate(rj.FreeBody(jnp.array([1.0, 2.0, 3.0])), rj.State(w), jnp.linspace(0, 1, 11))
    )(jnp.array([[0.3, 1.0, 0.2], [1.0, 0.1, 0.1]]))
    assert traj.ts.shape == (2, 11)
    assert repr(traj) == (
        "Trajectory(FreeBody, batch_shape=(2,), 11 samples, t=0 to 1 s, float64, omega only, "
        "2/2 bodies succeeded)"
    )


def test_reprs_of_traced_models_show_shapes_only():
    seen = []

    @jax.jit
    def f(inertia, com):
        model = rj.HeavyTop(inertia, 1.0, com, torque=rj.ViscousDamping(jnp.sum(inertia)))
        seen.append(repr(model))
        seen.append(repr(rj.FreeBody(inertia)))
        return inertia

    f(jnp.ones((4, 3)), jnp.array([0.0, 0.0, 0.1]))
    assert seen[0].startswith("HeavyTop(inertia=f64[4,3], mass=")
    assert "com=f64[3]," in seen[0] and "ViscousDamping(coefficient=f64[])" in seen[0]
    assert seen[1] == "FreeBody(inertia=f64[4,3], batch_shape=(4,))"
    for text in seen:
        assert "Traced" not in text and "Tracer" not in text, text
        _no_dump(text)


def test_summarize():
    assert summarize(np.float32(2.5)) == "2.5"
    assert summarize(np.array(3.0)) == "3.0"
    assert summarize(np.array([True, False])) == "bool[2] (True, False)"
    assert summarize(np.zeros((2, 5), np.int32)) == "i32[2,5]"
    assert summarize(jax.ShapeDtypeStruct((7, 3), jnp.float32)) == "f32[7,3]"
    assert summarize({"k": np.ones(2)}) == "{'k': f64[2] (1, 1)}"
    assert summarize((np.ones(1),)) == "(f64[1] (1),)"


def _fit(inertia, stderr, orientation0=None, torque=None):
    """An InertiaFit built directly (no optimisation): the repr only reads its fields."""
    moments = np.linalg.eigvalsh(inertia) if inertia.ndim == 2 else np.sort(inertia)
    return rj.InertiaFit(
        inertia=jnp.asarray(inertia),
        omega0=jnp.array([0.3, 3.0, 0.2]),
        loss=jnp.array(1.0e-6),
        history=jnp.linspace(1.0, 1e-6, 500),
        converged=jnp.array(True),
        num_steps=37,
        inertia_stderr=jnp.asarray(stderr),
        omega0_stderr=jnp.full(3, 1e-4),
        principal_moments=jnp.asarray(moments),
        principal_axes=jnp.eye(3),
        residual_rms=jnp.full(3, 1e-3),
        noise_estimate=jnp.full(3, 1.1e-3),
        orientation0=None if orientation0 is None else jnp.asarray(orientation0),
        orientation0_stderr=None if orientation0 is None else jnp.full(3, 1e-3),
        segment_starts=jnp.array([0.0]),
        initial_inertia=jnp.asarray(inertia),
        covariance=jnp.eye(5),
        normalised=True,
        method="levenberg-marquardt",
        torque=torque,
    )


def test_inertia_fit_repr_is_a_few_lines():
    text = repr(_fit(np.array([0.2, 0.3, 0.5]), np.array([1.2e-5, 2e-5, 1e-5])))
    assert text.splitlines()[0] == "InertiaFit("
    assert len(text.splitlines()) <= 8
    for part in (
        "inertia=f64[3] (0.2, 0.3, 0.5) (normalised to trace 1)",
        "inertia_stderr=f64[3] (1.2e-05, 2e-05, 1e-05)",
        "converged=True, num_steps=37, method='levenberg-marquardt'",
        "loss=1e-06",
        "fitted to angular velocity",
    ):
        assert part in text, text
    assert "history" not in text and "covariance" not in text  # the long arrays are left out
    _no_dump(text)
    tensor = repr(
        _fit(
            np.diag([0.2, 0.3, 0.5]), np.full((3, 3), 1e-5), np.array([1.0, 0, 0, 0]), rj.ViscousDamping(0.1)
        )
    )
    assert "inertia=f64[3,3] ((0.2, 0, 0), (0, 0.3, 0), (0, 0, 0.5))" in tensor
    assert "principal_moments=f64[3] (0.2, 0.3, 0.5)" in tensor
    assert "fitted to orientation" in tensor and "torque=ViscousDamping(coefficient=0.1)" in tensor


def test_inertia_fit_repr_under_jit():
    seen = []

    @jax.jit
    def f(fit):
        seen.append(repr(fit))
        return fit.loss

    f(_fit(np.array([0.2, 0.3, 0.5]), np.full(3, 1e-5)))
    assert "inertia=f64[3] (normalised to trace 1)" in seen[0] and "converged=bool[]" in seen[0]
    _no_dump(seen[0])


def test_stability_results_print_their_values():
    """``print(rj.spin_stability(...))`` showed only ``f64[3]`` for each field, though the guide's
    example prints it to show the growth rate. Values against the closed forms: growth rate
    omega sqrt((I2 - I1)(I3 - I2) / (I1 I3)) about the intermediate axis, and the sleeping top's
    critical spin 2 sqrt(I1 m g l) / I3."""
    racket = rj.spin_stability(np.array([1.0, 2.0, 2.5]), 4.0)
    growth = 4.0 * np.sqrt(1.0 * 0.5 / 2.5)
    assert f"growth_rate=f64[3] (0, {growth:.6g}, 0)" in repr(racket)
    assert "stable=bool[3] (True, False, True)" in repr(racket)
    top = rj.sleeping_top(np.array([1e-4, 1e-4, 5e-5]), 0.1, np.array([0.0, 0.0, 0.03]), 200.0)
    critical = 2 * np.sqrt(1e-4 * 0.1 * 9.81 * 0.03) / 5e-5
    assert f"critical_spin={critical:.6g}," in repr(top) and "stable=True" in repr(top)
    assert repr(rj.spin_stability(np.ones((5, 3)) * np.array([1.0, 2.0, 2.5]), 4.0)).startswith(
        "SpinStability(growth_rate=f64[5,3], frequency=f64[5,3]"
    )
