"""Trajectories on disk: ``Trajectory.save`` / ``Trajectory.load`` round trips are exact (dtypes,
bits, model class and settings, stats), checked against the in-memory original and against the raw
file as ``numpy.load`` sees it; models that cannot be stored and paths that cannot be written are
refused before anything is written; an interrupted write leaves the target as it was; the repr."""

import os
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rigidjax as rj
from rigidjax._integrate import storage

TS = (0.0, 0.5, 1.0)
Q_IDENTITY = (1.0, 0.0, 0.0, 0.0)
TENSOR = ((2.0, 0.1, 0.0), (0.1, 3.0, 0.2), (0.0, 0.2, 4.0))


def _omega(batch, dtype):
    base = np.array([0.3, 1.0, 0.2])
    steps = np.arange(int(np.prod(batch, dtype=int)) * 3).reshape(batch + (3,))
    return jnp.asarray(base + 0.05 * steps, dtype)


def _orientation(batch, dtype):
    q = np.array([1.0, 0.2, -0.1, 0.3]) / np.linalg.norm([1.0, 0.2, -0.1, 0.3])
    return jnp.asarray(np.broadcast_to(q, batch + (4,)), dtype)


def _simulate(model, batch, dtype, with_orientation, accuracy="fast"):
    q = _orientation(batch, dtype) if with_orientation else None
    return rj.simulate(model, rj.State(_omega(batch, dtype), q), jnp.asarray(TS, dtype), accuracy=accuracy)


# The scenes of the round trips: small, so that each compiles once and quickly.
CASES = {
    "free-moments-batch(2,3)-orientation-f64": lambda: _simulate(
        rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0])), (2, 3), jnp.float64, True
    ),
    "free-moments-batch(2,3)-omega-only-f32": lambda: _simulate(
        rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0], jnp.float32)), (2, 3), jnp.float32, False
    ),
    "free-tensor-omega-only-f64": lambda: _simulate(rj.FreeBody(jnp.asarray(TENSOR)), (), jnp.float64, False),
    "free-tensor-orientation-f32": lambda: _simulate(
        rj.FreeBody(jnp.asarray(TENSOR, jnp.float32)), (), jnp.float32, True
    ),
    "heavy-top-space-torque-damping": lambda: _simulate(
        rj.HeavyTop(
            jnp.asarray([[1.0, 1.0, 0.5], [1.2, 1.2, 0.4]]),
            jnp.asarray([1.0, 2.0]),
            jnp.asarray([0.0, 0.0, 0.1]),
            gravity=jnp.asarray(9.81),
            torque=(
                rj.ConstantTorque(jnp.asarray([0.0, 0.01, 0.02]), frame="space"),
                rj.ViscousDamping(jnp.asarray([[0.01], [0.02]])),
            ),
        ),
        (2,),
        jnp.float64,
        True,
    ),
    "rigid-body-gravity-torque": lambda: _simulate(
        rj.RigidBody(
            jnp.asarray([1.0, 1.0, 0.5]), rj.GravityTorque(jnp.asarray(0.5), jnp.asarray([0.0, 0.0, 0.2]))
        ),
        (),
        jnp.float64,
        True,
    ),
    "exact-batch(2,)-orientation-f64": lambda: _simulate(
        rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0])), (2,), jnp.float64, True, accuracy="exact"
    ),
    "exact-omega-only-f32": lambda: _simulate(
        rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0], jnp.float32)), (), jnp.float32, False, accuracy="exact"
    ),
}

_computed = {}


# The fast tier keeps one case per stored layout (moments and tensor, omega only and with
# orientation, float32, torques, the closed form); these two repeat layouts covered there.
_REPEATED_LAYOUTS = {"free-moments-batch(2,3)-omega-only-f32", "exact-omega-only-f32"}


@pytest.fixture(
    params=[
        pytest.param(name, marks=pytest.mark.slow) if name in _REPEATED_LAYOUTS else name for name in CASES
    ]
)
def case(request):
    """(name, trajectory): each scene is simulated once per test session."""
    if request.param not in _computed:
        _computed[request.param] = CASES[request.param]()
    return request.param, _computed[request.param]


def _bits(x):
    return np.asarray(x).tobytes()


def assert_identical(loaded, original):
    """Same classes, static settings and stats keys (the pytree structure), and every leaf of the
    same type, dtype, shape, weak type and bits."""
    leaves_a, tree_a = jax.tree_util.tree_flatten(loaded)
    leaves_b, tree_b = jax.tree_util.tree_flatten(original)
    assert tree_a == tree_b
    assert list(loaded.stats) == list(original.stats)
    for a, b in zip(leaves_a, leaves_b, strict=True):
        assert type(a) is type(b)
        if isinstance(b, jax.Array):
            assert (a.dtype, a.shape, a.weak_type) == (b.dtype, b.shape, b.weak_type)
            assert _bits(a) == _bits(b)
        else:
            assert a == b


def assert_same_invariants(loaded, original):
    inv_a, inv_b = loaded.invariants(), original.invariants()
    assert list(inv_a) == list(inv_b)
    for key in inv_b:
        assert inv_a[key].dtype == inv_b[key].dtype
        assert _bits(inv_a[key]) == _bits(inv_b[key])


def test_round_trip_is_exact(case, tmp_path):
    name, traj = case
    path = tmp_path / "traj.npz"
    traj.save(path)
    assert os.listdir(tmp_path) == ["traj.npz"]  # one file, no temporary left behind
    loaded = rj.Trajectory.load(path)
    assert_identical(loaded, traj)
    if traj.batch_shape[-1:] != (3,):  # see test_invariants_of_a_batch_ending_in_3
        assert_same_invariants(loaded, traj)
    assert repr(loaded) == repr(traj)


def test_raw_file_holds_the_arrays(case, tmp_path):
    """The independent check: what numpy.load reads from the file, without pickling."""
    name, traj = case
    path = tmp_path / "traj.npz"
    traj.save(path)
    with np.load(path, allow_pickle=False) as raw:
        for key in ("ts", "omega", "success"):
            assert raw[key].dtype == getattr(traj, key).dtype
            assert _bits(raw[key]) == _bits(getattr(traj, key))
        if traj.orientation is None:
            assert "orientation" not in raw.files
            assert "orientation" in raw["meta/none"]
        else:
            assert _bits(raw["orientation"]) == _bits(traj.orientation)
        assert raw["model/class"] == type(traj.model).__name__
        assert _bits(raw["model/inertia"]) == _bits(traj.model.inertia)
        assert raw["model/inertia"].dtype == traj.model.inertia.dtype
        assert _bits(raw["stats/num_steps"]) == _bits(traj.stats["num_steps"])
        assert int(raw["stats/chunk_size"]) == traj.stats["chunk_size"]
        assert list(raw["meta/stats"]) == list(traj.stats)
        assert raw["meta/format"] == "rigidjax.Trajectory"
        assert raw["meta/format_version"] == storage.FORMAT_VERSION == 1
        assert raw["meta/rigidjax_version"] == rj.__version__
        assert raw["meta/dtype"] == str(traj.omega.dtype)


def test_torques_and_settings_in_the_file(tmp_path):
    name = "heavy-top-space-torque-damping"
    traj = _computed.get(name) or CASES[name]()
    traj.save(tmp_path / "top.npz")
    with np.load(tmp_path / "top.npz", allow_pickle=False) as raw:
        assert raw["model/class"] == "HeavyTop"
        for field in ("mass", "com", "gravity"):
            assert _bits(raw[f"model/{field}"]) == _bits(getattr(traj.model, field))
        assert raw["model/torques/length"] == 2
        assert raw["model/torques/0/class"] == "ConstantTorque"
        assert raw["model/torques/0/frame"] == "space"
        assert _bits(raw["model/torques/0/torque"]) == _bits(traj.model.torques[0].torque)
        assert raw["model/torques/1/class"] == "ViscousDamping"
        assert raw["model/torques/1/coefficient"].shape == (2, 1)
    loaded = rj.Trajectory.load(tmp_path / "top.npz")
    assert loaded.model.torques[0].frame == "space"
    assert loaded.model.torques[0].needs_orientation


def test_loaded_model_simulates_the_same(tmp_path):
    """The model that comes back is the scene itself: simulating it again gives the same bits."""
    name = "heavy-top-space-torque-damping"
    traj = _computed.get(name) or CASES[name]()
    traj.save(tmp_path / "top.npz")
    loaded = rj.Trajectory.load(tmp_path / "top.npz")
    state = rj.State(_omega((2,), jnp.float64), _orientation((2,), jnp.float64))
    again = rj.simulate(loaded.model, state, loaded.ts, accuracy="fast")
    assert _bits(again.omega) == _bits(traj.omega)
    assert _bits(again.orientation) == _bits(traj.orientation)


def test_invariants_of_a_batch_ending_in_3(tmp_path):
    """Principal moments (3,) with a (2, 3) batch of states: the trajectory keeps the model as given,
    so nothing reads a moment vector broadcast to (2, 3, 3) as a tensor."""
    name = "free-moments-batch(2,3)-orientation-f64"
    traj = _computed.get(name) or CASES[name]()
    traj.save(tmp_path / "traj.npz")
    assert_same_invariants(rj.Trajectory.load(tmp_path / "traj.npz"), traj)


def _hand_made(model, dtype=jnp.float64, orientation=True, stats=None):
    """A small trajectory built without simulating (no compile)."""
    ts = jnp.asarray(TS, dtype)
    omega = jnp.broadcast_to(jnp.asarray([0.1, 0.2, 0.3], dtype), (2, 3, 3))
    q = jnp.broadcast_to(jnp.asarray(Q_IDENTITY, dtype), (2, 3, 4)) if orientation else None
    stats = {"num_steps": jnp.zeros((), jnp.int32), "chunk_size": 0} if stats is None else stats
    return rj.Trajectory(ts, omega, q, model, jnp.ones((2,), bool), stats)


def test_failed_rows_and_stats_kinds(tmp_path):
    """NaN rows of a failed body, success=False, a None stat, a float stat, a weakly typed array."""
    model = rj.FreeBody(jnp.asarray([[1.0, 2.0, 3.0], [2.0, 2.0, 3.0]]))
    traj = _hand_made(
        model,
        stats={
            "num_steps": jnp.full((1,), 6),  # weakly typed int64, as simulate returns it
            "chunk_size": 2,
            "quaternion_norm_error": None,
            "wall_time": 0.25,
            "converged": True,
        },
    )
    failed = (traj.omega.at[1].set(jnp.nan), jnp.asarray([True, False]))
    traj = eqx.tree_at(lambda t: (t.omega, t.success), traj, failed)
    assert traj.stats["num_steps"].weak_type
    traj.save(tmp_path / "t.npz")
    loaded = rj.Trajectory.load(tmp_path / "t.npz")
    assert_identical(loaded, traj)
    assert loaded.stats["quaternion_norm_error"] is None
    assert type(loaded.stats["wall_time"]) is float and type(loaded.stats["converged"]) is bool
    assert "1/2 bodies succeeded" in repr(loaded)


def test_stats_that_are_not_numbers_are_skipped_with_a_warning(tmp_path):
    stats = {"num_steps": jnp.zeros(()), "solver": object()}
    traj = _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0])), stats=stats)
    with pytest.warns(UserWarning, match=r"stats\['solver'\]"):
        traj.save(tmp_path / "t.npz")
    assert list(rj.Trajectory.load(tmp_path / "t.npz").stats) == ["num_steps"]


# --- refusals -------------------------------------------------------------------------------------


def _fn_torque(t, state, args):
    return -0.1 * state.omega


@pytest.mark.parametrize(
    "torque",
    [
        rj.Torque(_fn_torque, needs_orientation=False),
        _fn_torque,
        (rj.ViscousDamping(0.1), rj.Torque(_fn_torque)),
    ],
    ids=["Torque(fn)", "bare-callable", "in-a-tuple"],
)
def test_user_torque_is_refused(torque, tmp_path):
    traj = _hand_made(rj.RigidBody(jnp.asarray([1.0, 2.0, 3.0]), torque))
    with pytest.raises(ValueError, match=r"Torque\(fn\).*numpy\.savez"):
        traj.save(tmp_path / "t.npz")
    assert os.listdir(tmp_path) == []


def test_custom_torque_class_is_refused(tmp_path):
    class Spring(rj.AbstractTorque):
        k: jax.Array
        needs_orientation: ClassVar[bool] = False

        def __call__(self, t, state, args):
            return -self.k * state.omega

    traj = _hand_made(rj.RigidBody(jnp.asarray([1.0, 2.0, 3.0]), Spring(jnp.asarray(1.0))))
    with pytest.raises(ValueError, match="Spring.*cannot rebuild"):
        traj.save(tmp_path / "t.npz")
    assert os.listdir(tmp_path) == []


def test_unwritable_paths_are_refused_before_writing(tmp_path):
    traj = _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0])))
    missing = tmp_path / "no-such-dir" / "t.npz"
    with pytest.raises(FileNotFoundError, match="no-such-dir.*does not exist"):
        traj.save(missing)
    with pytest.raises(IsADirectoryError, match=f"{tmp_path.name}.*is a directory"):
        traj.save(tmp_path)
    assert os.listdir(tmp_path) == []


def test_not_a_trajectory(tmp_path):
    other = tmp_path / "other.npz"
    np.savez(other, omega=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="other.npz.*not a rigidjax trajectory.*omega"):
        rj.Trajectory.load(other)
    npy = tmp_path / "array.npy"
    np.save(npy, np.zeros(3))
    with pytest.raises(ValueError, match="array.npy.*single NumPy array"):
        rj.Trajectory.load(npy)
    text = tmp_path / "notes.npz"
    text.write_text("not an archive")
    with pytest.raises(ValueError, match="notes.npz.*not a rigidjax trajectory"):
        rj.Trajectory.load(text)
    with pytest.raises(FileNotFoundError, match="absent.npz"):
        rj.Trajectory.load(tmp_path / "absent.npz")


def _rewrite(path, **changes):
    with np.load(path, allow_pickle=False) as raw:
        arrays = {key: raw[key] for key in raw.files}
    for key, value in changes.items():
        key = key.replace("__", "/")
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def test_unknown_format_version(tmp_path):
    path = tmp_path / "t.npz"
    _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0]))).save(path)
    _rewrite(path, meta__format_version=np.asarray(2))
    with pytest.raises(ValueError, match="t.npz.*format version 2.*reads version 1.*upgrade rigidjax"):
        rj.Trajectory.load(path)


def test_damaged_files(tmp_path):
    path = tmp_path / "t.npz"
    traj = _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0])))
    traj.save(path)
    _rewrite(path, omega=None)
    with pytest.raises(ValueError, match="t.npz.*'omega' is missing"):
        rj.Trajectory.load(path)
    traj.save(path)
    _rewrite(path, model__extra=np.zeros(3))
    with pytest.raises(ValueError, match="does not know.*model/extra"):
        rj.Trajectory.load(path)
    traj.save(path)
    _rewrite(path, model__class=np.asarray("Spaceship"))
    with pytest.raises(ValueError, match="'Spaceship'.*cannot rebuild"):
        rj.Trajectory.load(path)
    traj.save(path)
    _rewrite(path, model__inertia=np.zeros(4))
    with pytest.raises(ValueError, match="FreeBody cannot be rebuilt"):
        rj.Trajectory.load(path)


def test_files_whose_arrays_do_not_fit_together(tmp_path, without_runtime_typecheck):
    """An edited or pieced-together file loaded, then failed in the first computation with a
    broadcasting error (omega of 5 samples beside 6 times, a model of 3 bodies beside 2), or gave
    wrong values (orientations of norm 6); the save of an empty or non-path path was a raw error."""
    path = tmp_path / "t.npz"
    traj = _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0])))
    T = traj.ts.shape[0]
    damaged = [
        ("omega", np.asarray(traj.omega)[..., :-1, :], rf"omega should have shape \(\.\.\., {T}, 3\)"),
        ("orientation", 6.0 * np.asarray(traj.orientation), "not unit quaternions"),
        ("success", np.ones(7, bool), "success should be booleans of shape"),
        ("ts", np.asarray(traj.ts)[::-1], "strictly increasing"),
        ("model__inertia", np.ones((7, 3)), "model's bodies do not broadcast"),
        # A string where a number goes was a raw JAX TypeError without the file's name; a float32
        # ts beside a float64 omega, or a NaN omega marked successful, loaded silently.
        ("model__inertia", np.array("1.0"), "'model/inertia' should hold numbers, got dtype <U3"),
        ("ts", np.asarray(traj.ts, np.float32), r"share omega's dtype \(float64\): ts is float32"),
        ("omega", np.full(traj.omega.shape, np.nan), "a body marked successful has non-finite omega"),
    ]
    for key, value, message in damaged:
        traj.save(path)
        _rewrite(path, **{key: value})
        with pytest.raises(ValueError, match="t.npz.*" + message):
            rj.Trajectory.load(path)
    # A trajectory built by hand that load would refuse is refused before it is written.
    off_unit = rj.Trajectory(
        traj.ts, traj.omega, 6.0 * traj.orientation, traj.model, traj.success, traj.stats
    )
    with pytest.raises(ValueError, match="^Trajectory.save: its orientations are not unit.*loaded back"):
        off_unit.save(tmp_path / "hand.npz")
    assert not (tmp_path / "hand.npz").exists()
    for bad, error in (("", ValueError), (3, TypeError), (None, TypeError)):
        with pytest.raises(error, match=r"^Trajectory.save: path (is empty|must be a file path)"):
            traj.save(bad)
        with pytest.raises(error, match=r"^Trajectory.load: path (is empty|must be a file path)"):
            rj.Trajectory.load(bad)


def test_a_model_that_simulate_refuses_is_refused_by_load_and_save(tmp_path):
    """A file whose scene was edited to a negative moment, moments that no mass distribution has
    (I3 > I1 + I2) or a negative mass loaded, and its invariants were computed with them."""
    path = tmp_path / "t.npz"
    top = rj.HeavyTop(inertia=jnp.asarray([1.0, 1.0, 0.5]), mass=1.0, com=jnp.asarray([0.0, 0.0, 0.1]))
    traj = _hand_made(top)
    for key, value, message in [
        ("model__inertia", np.array([1.0, 1.0, -0.5]), "non-positive principal moment"),
        ("model__inertia", np.array([1.0, 1.0, 5.0]), "triangle inequality"),
        ("model__mass", np.array(-1.0), "'mass' must be positive"),
        ("model__com", np.array([0.0, np.nan, 0.1]), "'com' contains NaN"),
    ]:
        traj.save(path)
        _rewrite(path, **{key: value})
        with pytest.raises(ValueError, match=f"^Trajectory.load: .*t.npz.*its model: .*{message}"):
            rj.Trajectory.load(path)
    unphysical = rj.Trajectory(
        traj.ts,
        traj.omega,
        traj.orientation,
        rj.FreeBody(jnp.asarray([1.0, 1.0, 5.0])),
        traj.success,
        traj.stats,
    )
    with pytest.raises(ValueError, match="^Trajectory.save: its model: .*triangle.*loaded back"):
        unphysical.save(tmp_path / "hand.npz")
    assert not (tmp_path / "hand.npz").exists()


def test_float64_file_in_32_bit_mode(tmp_path):
    traj64 = _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0])))
    traj64.save(tmp_path / "t64.npz")
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match="t64.npz.*jax_enable_x64"):
            rj.Trajectory.load(tmp_path / "t64.npz")
        traj32 = _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0], jnp.float32)), jnp.float32)
        traj32.save(tmp_path / "t32.npz")
        assert_identical(rj.Trajectory.load(tmp_path / "t32.npz"), traj32)


# --- atomic writes --------------------------------------------------------------------------------


@pytest.mark.parametrize("error", [OSError("disk full"), KeyboardInterrupt()], ids=["OSError", "interrupt"])
@pytest.mark.parametrize("existing", [False, True], ids=["new", "overwrite"])
def test_interrupted_write_leaves_the_target_alone(error, existing, tmp_path, monkeypatch):
    path = tmp_path / "t.npz"
    if existing:
        path.write_bytes(b"an earlier result")

    def fail_midway(file, arrays):
        file.write(b"PK\x03\x04 half an archive")
        raise error

    monkeypatch.setattr(storage, "_write_arrays", fail_midway)
    with pytest.raises(type(error)):
        _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0]))).save(path)
    if existing:
        assert os.listdir(tmp_path) == ["t.npz"]
        assert path.read_bytes() == b"an earlier result"
    else:
        assert os.listdir(tmp_path) == []


def test_overwrite_replaces_and_keeps_permissions(tmp_path):
    path = tmp_path / "t.npz"
    path.write_bytes(b"an earlier result")
    os.chmod(path, 0o640)
    traj = _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0])))
    traj.save(str(path))
    assert os.stat(path).st_mode & 0o777 == 0o640
    assert_identical(rj.Trajectory.load(str(path)), traj)
    assert os.listdir(tmp_path) == ["t.npz"]


# --- repr -----------------------------------------------------------------------------------------


def test_repr_is_a_summary():
    traj = _hand_made(
        rj.HeavyTop(
            jnp.asarray([1.0, 1.0, 0.5]),
            jnp.asarray(1.0),
            jnp.asarray([0.0, 0.0, 0.1]),
            torque=rj.ConstantTorque(jnp.asarray([0.0, 0.0, 0.1]), frame="space"),
        )
    )
    text = repr(traj)
    assert text == (
        "Trajectory(HeavyTop[ConstantTorque], batch_shape=(2,), 3 samples, t=0 to 1 s, float64, "
        "with orientation, 2/2 bodies succeeded)"
    )
    assert str(traj) == text
    omega_only = _hand_made(
        rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0], jnp.float32)), jnp.float32, orientation=False
    )
    assert "Trajectory(FreeBody, " in repr(omega_only)
    assert "float32, omega only" in repr(omega_only)


def test_repr_while_tracing():
    seen = []

    @jax.jit
    def f(ts):
        traj = _hand_made(rj.FreeBody(jnp.asarray([1.0, 2.0, 3.0])))
        seen.append(repr(eqx.tree_at(lambda t: t.ts, traj, ts)))
        return ts

    f(jnp.asarray(TS))
    assert seen[0].startswith("Trajectory(FreeBody, batch_shape=(2,), 3 samples, float64")


def test_a_trajectory_of_abstract_values_or_shapes_has_a_repr():
    """``jax.eval_shape`` of a simulation gave a Trajectory whose repr raised IndexError (NumPy's
    array of a ShapeDtypeStruct), and ``tree_map`` over a Trajectory failed on its one Python-int leaf
    (``stats["chunk_size"]``): every leaf is an array now, and every Trajectory prints."""

    def sim(omega0):
        model = rj.FreeBody(jnp.asarray([1.0, 2.0, 2.5]))
        return rj.simulate(model, rj.State(omega0), jnp.linspace(0.0, 1.0, 5), accuracy="exact")

    omega0 = jnp.asarray([[0.3, 0.1, 1.0], [0.2, 0.5, 0.1]])
    abstract = jax.eval_shape(sim, omega0)
    assert repr(abstract) == "Trajectory(FreeBody, batch_shape=(2,), 5 samples, float64, omega only)"
    traj = sim(omega0)
    shapes = jax.tree_util.tree_map(lambda x: x.shape, traj)
    assert shapes.omega == (2, 5, 3) and shapes.stats["chunk_size"] == ()
    assert repr(shapes).startswith("Trajectory(")
    assert int(traj.stats["chunk_size"]) == 2
