"""rigidjax.plot: what each figure draws (the points on the energy ellipsoid, in the invariable
plane, the Euler angles, the drifts), the frames of the animations, the errors that name their
argument, and ``rigidjax simulate --animate``. Small scenes in closed form, so that little compiles."""

import contextlib
import importlib
import io
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

import rigidjax as rj

pytest.importorskip("matplotlib")
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from PIL import Image  # noqa: E402

import rigidjax.plot as rplot  # noqa: E402

INERTIA = np.array([1.0, 2.0, 3.0])
OMEGA0 = np.array([[0.3, 2.0, 0.2], [2.0, 0.1, 0.5]])  # near the intermediate axis; near the minor


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


@pytest.fixture(scope="module")
def free():
    """Two torque-free bodies, 40 samples over 5 s, in closed form."""
    q0 = rj.quat_from_euler(jnp.array([0.3, 0.7, -0.2]))
    return rj.simulate(
        rj.FreeBody(jnp.asarray(INERTIA)),
        rj.State(jnp.asarray(OMEGA0), q0),
        jnp.linspace(0, 5, 40),
        accuracy="exact",
    )


@pytest.fixture(scope="module")
def top():
    """One Lagrange top (I1 = I2, centre of mass on the body z axis), 30 samples, in closed form."""
    model = rj.HeavyTop(jnp.array([1.0, 1.0, 0.5]), 1.0, jnp.array([0.0, 0.0, 0.1]))
    q0 = rj.quat_from_euler(jnp.array([0.0, 0.5, 0.0]))
    return rj.simulate(
        model, rj.State(jnp.array([0.0, 0.0, 20.0]), q0), jnp.linspace(0, 2, 30), accuracy="exact"
    )


def _line(ax, label):
    [line] = [line for line in ax.get_lines() if line.get_label() == label]
    return line


def _body(trajectory, i):
    return np.asarray(trajectory.omega)[i], np.asarray(trajectory.orientation)[i]


# ---------------------------------------------------------------------------------------------
# Importing


def test_import_rigidjax_does_not_import_matplotlib():
    code = "import sys, rigidjax; assert 'matplotlib' not in sys.modules, 'matplotlib was imported'"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_without_matplotlib_the_import_error_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    monkeypatch.delitem(sys.modules, "rigidjax.plot")
    with pytest.raises(ImportError, match=r"pip install 'rigidjax\[plot\]'"):
        importlib.import_module("rigidjax.plot")


def test_public_names():
    assert sorted(rplot.__all__) == ["animate", "cones", "euler_angles", "invariant_drift", "poinsot"]
    for name in rplot.__all__:
        assert getattr(rplot, name).__doc__.strip()


# ---------------------------------------------------------------------------------------------
# The figures' content


@pytest.mark.parametrize("body", [0, 1, -1])
def test_poinsot_polhode_is_on_the_energy_ellipsoid_and_the_momentum_sphere(free, body):
    fig = rplot.poinsot(free, body=body)
    polhode_ax, herpolhode_ax = fig.axes
    assert polhode_ax.name == "3d" and herpolhode_ax.name == "rectilinear"
    assert polhode_ax.get_xlabel() == "omega_1 (rad/s)" and polhode_ax.get_zlabel() == "omega_3 (rad/s)"
    assert "energy ellipsoid" in polhode_ax.get_title() and "invariable plane" in herpolhode_ax.get_title()
    omega, _ = _body(free, body)
    points = np.stack(_line(polhode_ax, "polhode").get_data_3d(), -1)
    np.testing.assert_array_equal(points, omega)  # the body-frame omega of every sample
    two_energy = points @ (INERTIA * points).T
    two_energy = np.diag(two_energy)
    assert np.max(np.abs(two_energy / (OMEGA0[body] @ (INERTIA * OMEGA0[body])) - 1)) < 1e-8
    momentum = np.linalg.norm(INERTIA * points, axis=-1)
    assert np.max(np.abs(momentum / np.linalg.norm(INERTIA * OMEGA0[body]) - 1)) < 1e-8


def test_poinsot_herpolhode_is_in_the_invariable_plane(free):
    fig = rplot.poinsot(free, body=1)
    herpolhode_ax = fig.axes[1]
    assert herpolhode_ax.get_xlabel() == "omega along e1 (rad/s)"
    omega, q = _body(free, 1)
    omega_space = np.asarray(rj.quat_rotate(q, omega))
    L = np.asarray(rj.space_angular_momentum(INERTIA, omega, q))
    two_energy = OMEGA0[1] @ (INERTIA * OMEGA0[1])
    # The tip of the space-frame omega stays in one plane: L . omega_space = 2E, L fixed.
    np.testing.assert_allclose(L, np.broadcast_to(L[0], L.shape), rtol=0, atol=1e-10 * np.linalg.norm(L[0]))
    np.testing.assert_allclose(omega_space @ L[0], two_energy, rtol=1e-8)
    # The plotted points are that plane's coordinates: their distance from where L pierces the
    # plane and the plane's height 2E / |L| make up |omega|.
    xy = np.stack(_line(herpolhode_ax, "herpolhode").get_data(), -1)
    height = two_energy / np.linalg.norm(L[0])
    np.testing.assert_allclose(np.sum(xy**2, -1) + height**2, np.sum(omega**2, -1), rtol=1e-10)
    assert f"{height:.4g}" in herpolhode_ax.get_title()


def test_cones_are_the_unit_omega_in_the_body_and_in_space(free):
    fig = rplot.cones(free, body=0)
    body_ax, space_ax = fig.axes
    assert body_ax.name == space_ax.name == "3d"
    assert (body_ax.get_xlabel(), space_ax.get_xlabel()) == ("e1", "X1")
    assert "Body cone" in body_ax.get_title() and "Space cone" in space_ax.get_title()
    omega, q = _body(free, 0)
    unit = omega / np.linalg.norm(omega, axis=-1, keepdims=True)
    body_path = np.stack(_line(body_ax, "omega / |omega|").get_data_3d(), -1)
    space_path = np.stack(_line(space_ax, "omega / |omega|").get_data_3d(), -1)
    np.testing.assert_allclose(body_path, unit, atol=1e-14)
    np.testing.assert_allclose(space_path, np.asarray(rj.quat_rotate(q, unit)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(space_path, axis=-1), 1.0, atol=1e-12)
    L = np.asarray(rj.space_angular_momentum(INERTIA, omega[0], q[0]))
    np.testing.assert_allclose(
        np.stack(_line(space_ax, "L / |L|").get_data_3d(), -1)[1], L / np.linalg.norm(L)
    )


@pytest.mark.parametrize("sequence", ["zxz", "xyz"])
def test_euler_angles_are_the_unwrapped_angles_of_the_orientations(top, sequence):
    fig = rplot.euler_angles(top, sequence=sequence)
    assert len(fig.axes) == 3
    assert [ax.get_ylabel() for ax in fig.axes] == ["phi (rad)", "theta (rad)", "psi (rad)"]
    assert fig.axes[-1].get_xlabel() == "t (s)" and sequence in fig.axes[0].get_title()
    # The top's samples are dense: unwrapping by the nearest branch is right there.
    expected = np.unwrap(np.asarray(rj.euler_from_quat(top.orientation, sequence)), axis=0)
    for k, ax in enumerate(fig.axes):
        [line] = ax.get_lines()
        np.testing.assert_array_equal(line.get_xdata(), np.asarray(top.ts))
        np.testing.assert_allclose(line.get_ydata(), expected[:, k], atol=1e-12)
    if sequence == "zxz":  # the same as the trajectory's own (unwrapped) angles
        np.testing.assert_allclose(expected, np.asarray(top.euler_angles("zxz")), atol=1e-10)
        assert np.ptp(expected[:, 0]) > 2 * np.pi or np.all(np.abs(np.diff(expected[:, 0])) < np.pi)


def test_euler_angles_follow_a_spin_of_more_than_pi_per_sample():
    """A torque-free symmetric top with L along space Z (Goldstein 5.6: phi' = C w3 / (A cos theta),
    psi' = w3 (A - C) / A), sampled at 5.4 and 5 rad of phi and psi per sample: drawn as the
    straight lines they are (numpy.unwrap ran them backwards)."""
    a, c, omega3, theta = 1.0, 0.5, 200.0, 0.4
    phi_rate, psi_rate = c * omega3 / (a * np.cos(theta)), omega3 * (a - c) / a
    state = rj.State(
        jnp.array([0.0, phi_rate * np.sin(theta), omega3]), rj.quat_from_euler(jnp.array([0.0, theta, 0.0]))
    )
    ts = jnp.linspace(0.0, 2.0, 41)
    traj = rj.simulate(rj.FreeBody(jnp.array([a, a, c])), state, ts, accuracy="exact")
    fig = rplot.euler_angles(traj)
    for ax, rate in zip(fig.axes[::2], (phi_rate, psi_rate), strict=True):
        [line] = ax.get_lines()
        np.testing.assert_allclose(line.get_ydata(), rate * np.asarray(ts), rtol=0, atol=1e-9)


def test_a_single_sample_and_a_vmap_of_simulate(free, tmp_path):
    """A trajectory of one sample had Euler angles of shape (0, 3) (and its figure raised matplotlib's
    "x and y must have same first dimension"); a trajectory from a user's jax.vmap of simulate holds
    its times per body, ts (B, T), and its Euler angles raised a broadcasting TypeError, its figures
    an IndexError. Reference: the angles of the orientations (euler_from_quat) and the batch's own
    trajectory, in closed form."""
    import jax

    start = rj.State(free.omega[0, 0], free.orientation[0, 0])
    single = rj.simulate(rj.FreeBody(jnp.asarray(INERTIA)), start, jnp.zeros(1), accuracy="exact")
    np.testing.assert_allclose(single.euler_angles(), rj.euler_from_quat(free.orientation[0, :1]), atol=1e-15)
    [line] = rplot.euler_angles(single).axes[0].get_lines()
    assert line.get_xdata().shape == (1,)

    def one(omega0, q0, ts):
        return rj.simulate(rj.FreeBody(jnp.asarray(INERTIA)), rj.State(omega0, q0), ts, accuracy="exact")

    shared = jax.vmap(one, in_axes=(0, 0, None))(free.omega[:, 0], free.orientation[:, 0], free.ts)
    assert shared.ts.shape == (2, 40)
    np.testing.assert_allclose(shared.euler_angles(), free.euler_angles(), rtol=0, atol=1e-12)
    [line] = rplot.euler_angles(shared, body=1).axes[2].get_lines()
    np.testing.assert_allclose(line.get_ydata(), np.asarray(free.euler_angles())[1, :, 2], atol=1e-12)
    rplot.invariant_drift(shared)
    rplot.animate(shared, tmp_path / "shared.gif", frames=2)
    # Times of their own: a body's figure draws its times; a figure of several bodies says why not.
    stretched = jax.vmap(one)(free.omega[:, 0], free.orientation[:, 0], jnp.stack([free.ts, 2 * free.ts]))
    [line] = rplot.euler_angles(stretched, body=1).axes[0].get_lines()
    np.testing.assert_array_equal(line.get_xdata(), 2 * np.asarray(free.ts))
    with pytest.raises(ValueError, match="bodies have different sample times"):
        rplot.invariant_drift(stretched)


def test_invariant_drift_draws_the_scenes_conserved_quantities(free, top):
    fig = rplot.invariant_drift(free)
    [ax] = fig.axes
    assert ax.get_yscale() == "log" and ax.get_xlabel() == "t (s)" and ax.get_ylabel() == "relative drift"
    labels = {line.get_label() for line in ax.get_lines()}
    assert labels == {f"{q}, body {i}" for q in ("energy", "|L|", "space-frame L") for i in (0, 1)}
    floor = np.finfo(np.float64).eps / 100
    invariants = free.invariants()
    for i in (0, 1):
        line = _line(ax, f"energy, body {i}")
        assert np.max(line.get_ydata()) == pytest.approx(
            max(float(invariants["energy"][i]), floor), rel=1e-12
        )
    # A heavy top: its total energy (with the potential) and the vertical L_z, not |L|.
    [ax] = rplot.invariant_drift(top).axes
    assert {line.get_label() for line in ax.get_lines()} == {"energy", "L_z"}
    assert np.max(_line(ax, "L_z").get_ydata()) == pytest.approx(
        max(float(top.invariants()["vertical_angular_momentum"]), floor), rel=1e-12
    )
    # A selection, into axes of one's own.
    fig, own = plt.subplots()
    assert rplot.invariant_drift(free, bodies=[1], ax=own) is fig
    assert {line.get_label() for line in own.get_lines()} == {
        "energy, body 1",
        "|L|, body 1",
        "space-frame L, body 1",
    }


def test_invariant_drift_of_a_large_batch_is_the_worst_body(free):
    """More than 8 bodies: one line per quantity, the largest drift over the bodies at each sample."""
    omega = jnp.concatenate([free.omega] * 5)  # 10 bodies
    many = rj.Trajectory(
        free.ts,
        omega,
        jnp.concatenate([free.orientation] * 5),
        free.model,
        jnp.ones(10, bool),
        {"quaternion_norm_error": jnp.zeros(10)},
    )
    [ax] = rplot.invariant_drift(many).axes
    assert [line.get_label() for line in ax.get_lines()] == [
        f"{q} (worst of 10 bodies)" for q in ("energy", "|L|", "space-frame L")
    ]
    worst = np.max(np.asarray(many.invariants()["energy"]))
    floor = np.finfo(np.float64).eps / 100
    assert np.max(_line(ax, "energy (worst of 10 bodies)").get_ydata()) == pytest.approx(max(worst, floor))


def _with_failed_body(free, copies=1, failed_from=20):
    """``free`` repeated ``copies`` times, the last body failed from sample ``failed_from`` on (NaN
    rows and success False, as ``simulate(..., throw=False)`` leaves a body that failed)."""
    omega = np.concatenate([np.asarray(free.omega)] * copies)
    orientation = np.concatenate([np.asarray(free.orientation)] * copies)
    omega[-1, failed_from:] = np.nan
    orientation[-1, failed_from:] = np.nan
    success = np.ones(len(omega), bool)
    success[-1] = False
    return rj.Trajectory(
        free.ts, jnp.asarray(omega), jnp.asarray(orientation), free.model, jnp.asarray(success), {}
    )


def test_failed_bodies_are_named_not_hidden(free, tmp_path):
    """A failed body's NaN rows: the worst-case drift of a large batch drew the healthy bodies only
    under a label that counted every body, poinsot called a body failed from its first sample one
    that "does not rotate", and animate failed inside matplotlib on the NaN samples."""
    many = _with_failed_body(free, copies=5)  # 10 bodies, the last failed
    [ax] = rplot.invariant_drift(many).axes
    assert [line.get_label() for line in ax.get_lines()] == [
        f"{q} (worst of 9 bodies; 1 failed, not drawn)" for q in ("energy", "|L|", "space-frame L")
    ]
    [ax] = rplot.invariant_drift(_with_failed_body(free)).axes
    assert "energy, body 1 (failed: drawn until it did)" in [line.get_label() for line in ax.get_lines()]
    with pytest.raises(ValueError, match="poinsot: body 1 failed from its first sample"):
        rplot.poinsot(_with_failed_body(free, failed_from=0), body=1)
    path = rplot.animate(_with_failed_body(free), tmp_path / "failed.gif", bodies=(0, 1), frames=8)
    with Image.open(path) as gif:
        assert gif.n_frames == 8
    blank = rplot.animate(_with_failed_body(free, failed_from=0), tmp_path / "blank.gif", bodies=1, frames=3)
    with Image.open(blank) as gif:
        assert gif.n_frames == 3


def test_poinsot_axes_hold_the_whole_energy_ellipsoid():
    """The limits came from the polhode alone, so a polhode about the major axis (the ellipsoid's
    shortest) left the ellipsoid sticking out of the box. Reference: the ellipsoid
    omega . I omega = 2E has semi-axes sqrt(2E / I_k)."""
    inertia, omega0 = np.array([3.0, 2.5, 1.0]), np.array([5.0, 0.1, 0.1])  # near the major axis
    traj = rj.simulate(
        rj.FreeBody(jnp.asarray(inertia)),
        rj.State(jnp.asarray(omega0), jnp.array([1.0, 0.0, 0.0, 0.0])),
        jnp.linspace(0, 2, 20),
        accuracy="exact",
    )
    ax = rplot.poinsot(traj).axes[0]
    semi_axes = np.sqrt(omega0 @ (inertia * omega0) / inertia)
    for (low, high), semi_axis in zip([ax.get_xlim(), ax.get_ylim(), ax.get_zlim()], semi_axes, strict=True):
        assert low <= -semi_axis and high >= semi_axis


# ---------------------------------------------------------------------------------------------
# Errors name the argument


@pytest.mark.parametrize("function", [rplot.poinsot, rplot.cones, rplot.euler_angles])
@pytest.mark.parametrize("body", [2, -3, 1.0, True, "0"])
def test_a_bad_body_is_a_value_error_naming_it(free, function, body):
    with pytest.raises(ValueError, match=r"^body"):
        function(free, body=body)


def test_bad_bodies_and_missing_orientations(free, top):
    with pytest.raises(ValueError, match=r"bodies=5 is out of range: the trajectory holds 2 bodies"):
        rplot.invariant_drift(free, bodies=[0, 5])
    with pytest.raises(ValueError, match=r"bodies=1 is out of range: the trajectory holds 1 body"):
        rplot.animate(top, "never.gif", bodies=(1,))
    omega_only = rj.Trajectory(free.ts, free.omega, None, free.model, free.success, {})
    for function in (rplot.poinsot, rplot.cones, rplot.euler_angles):
        with pytest.raises(ValueError, match="needs the trajectory's orientations"):
            function(omega_only)
    with pytest.raises(ValueError, match="torque-free"):
        rplot.poinsot(top)
    # A body at rest has no invariable plane: the figure's title read "2E/|L| = nan".
    at_rest = rj.Trajectory(
        free.ts, jnp.zeros_like(free.omega), free.orientation, free.model, free.success, {}
    )
    with pytest.raises(ValueError, match="body 1 does not rotate.*no invariable plane"):
        rplot.poinsot(at_rest, body=1)
    with pytest.raises(ValueError, match=r"^sequence must be one of"):  # it named seq, not its own argument
        rplot.euler_angles(top, sequence="abc")


@pytest.mark.parametrize("function", ["poinsot", "cones", "euler_angles", "invariant_drift", "animate"])
def test_a_trajectory_argument_that_is_not_a_trajectory_is_named(free, function, tmp_path):
    """A trajectory's omega array or a dict in its place failed with an AttributeError on the first
    field read."""
    extra = (str(tmp_path / "a.gif"),) if function == "animate" else ()
    for wrong, kind in [(free.omega, "ArrayImpl"), ({"omega": free.omega}, "dict")]:
        with pytest.raises(
            TypeError, match=rf"^{function}: trajectory must be a rigidjax.Trajectory.*got {kind}"
        ):
            getattr(rplot, function)(wrong, *extra)


def test_a_figure_argument_that_is_not_a_figure_is_named(free, top):
    # An Axes or an array where a Figure goes failed inside matplotlib with an AttributeError.
    _, ax = plt.subplots()
    for function in (rplot.poinsot, rplot.cones, rplot.euler_angles):
        with pytest.raises(TypeError, match=r"^fig must be a matplotlib Figure.*got Axes.*pass its \.figure"):
            function(free, fig=ax)
        with pytest.raises(TypeError, match=r"^fig must be a matplotlib Figure.*got ndarray"):
            function(free, fig=np.zeros(3))
    with pytest.raises(TypeError, match=r"^ax must be a matplotlib Axes.*got Figure"):
        rplot.invariant_drift(top, ax=ax.figure)
    assert rplot.poinsot(free, fig=ax.figure) is ax.figure


# ---------------------------------------------------------------------------------------------
# Animations


def test_animate_writes_a_gif_with_one_frame_per_picked_sample(free, top, tmp_path):
    path = tmp_path / "free.gif"
    assert rplot.animate(free, path, bodies=(0, 1), frames=12) == str(path)
    with Image.open(path) as gif:
        assert gif.format == "GIF" and gif.n_frames == 12
        width, height = gif.size
    assert width > 1.5 * height  # two panels side by side
    # Fewer samples than frames: every sample once. A heavy top is drawn too.
    few = rplot.animate(top, tmp_path / "top.gif", frames=100, fps=10)
    with Image.open(few) as gif:
        assert gif.n_frames == 30
    assert sorted(p.name for p in tmp_path.iterdir()) == ["free.gif", "top.gif"]  # no temporary files


def test_animate_checks_its_arguments_before_drawing(free, tmp_path, monkeypatch):
    with pytest.raises(ValueError, match=r"path .*\.avi.*\.gif or \.mp4"):
        rplot.animate(free, tmp_path / "a.avi")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        rplot.animate(free, tmp_path / "missing" / "a.gif")
    with pytest.raises(ValueError, match="frames must be a positive integer"):
        rplot.animate(free, tmp_path / "a.gif", frames=0)
    with pytest.raises(ValueError, match="bodies: give 1 to 6"):
        rplot.animate(free, tmp_path / "a.gif", bodies=[0] * 7)
    # dpi reached Pillow unchecked (an IndexError after every frame was drawn); fps=True was one
    # frame per second; a path of None failed in os.fspath without naming the argument.
    for dpi in (0, -5, "x", float("nan")):
        with pytest.raises(ValueError, match="dpi must be a positive number"):
            rplot.animate(free, tmp_path / "a.gif", dpi=dpi)
    with pytest.raises(ValueError, match="fps must be a positive number, got True"):
        rplot.animate(free, tmp_path / "a.gif", fps=True)
    with pytest.raises(TypeError, match="path must be a file path .*got NoneType"):
        rplot.animate(free, None)
    monkeypatch.setattr(
        importlib.import_module("rigidjax._plot.animation"), "ffmpeg_available", lambda: False
    )
    with pytest.raises(RuntimeError, match=r"needs ffmpeg.*\.gif"):
        rplot.animate(free, tmp_path / "a.mp4")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# rigidjax simulate --animate, and the command's figure


def _run(argv):
    from rigidjax._cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def test_simulate_animate_writes_the_first_bodies(tmp_path):
    gif = tmp_path / "spin.gif"
    argv = ["simulate", "--scene", "free", "-n", "2", "--duration", "1", "--samples", "10"]
    code, out, err = _run(argv + ["--out", "", "--no-plot", "--animate", str(gif)])
    assert code == 0, err
    assert "wrote:" in out and str(gif) in out
    with Image.open(gif) as image:
        assert image.n_frames == 10  # one per stored sample
        width, height = image.size
    assert width > 1.5 * height  # both bodies (of at most 3)


@pytest.mark.parametrize(
    "options, message",
    [
        (["--animate", "x.avi"], "--animate 'x.avi': the file name must end in .gif or .mp4"),
        (["--animate", "missing/x.gif"], "--animate: cannot write 'missing/x.gif': the directory"),
        (["--scene", "earth", "--animate", "x.gif"], "--animate needs orientations"),
    ],
)
def test_simulate_animate_path_is_checked_before_the_run(tmp_path, monkeypatch, options, message):
    from rigidjax._cli import simulate as cli_simulate

    def fail(*args, **kwargs):
        raise AssertionError("the job started before --animate was checked")

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli_simulate, "plan_run", fail)
    code, out, err = _run(["simulate", *options])
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith("rigidjax simulate: error: ") and message in err
    assert list(tmp_path.iterdir()) == []


def test_simulate_figure_names_scenes_of_one_body_and_fills_or_explains_its_panels():
    from rigidjax._cli.scenes import SCENE_BUILDERS

    rng = np.random.default_rng
    assert SCENE_BUILDERS["heavy-top"](1, rng(0)).description.startswith("1 heavy top (")
    assert SCENE_BUILDERS["free"](1, rng(0)).description.startswith("1 torque-free asymmetric body ")
    assert SCENE_BUILDERS["earth"](1, rng(0)).description.startswith("1 rigid Earth (")
    assert SCENE_BUILDERS["heavy-top"](2, rng(0)).description.startswith("2 heavy tops (")
    # Many bodies: the stable panel shows one minor-axis and one major-axis spin, named as such.
    scene = SCENE_BUILDERS["free"](1000, rng(0))
    axis = scene.params["spin_axis"][scene.plot_indices]
    assert {0, 1, 2} <= set(axis.tolist())
    # Two bodies spun near the intermediate axis: the other panel says there is none, not blank.
    seed = next(s for s in range(100) if np.all(SCENE_BUILDERS["free"](2, rng(s)).params["spin_axis"] == 1))
    scene = SCENE_BUILDERS["free"](2, rng(seed))
    ts = np.linspace(0, 1, 5)
    traces = {"omega": np.ones((len(scene.plot_indices), 5, 3))}
    fig, axes = plt.subplots(1, 3)
    scene.plot(axes, ts, traces, {})
    assert [line.get_label().split(",")[0] for line in axes[0].get_lines()] == ["intermediate axis 2"] * 2
    assert not axes[1].get_lines() and "no body of this run" in axes[1].texts[0].get_text()
