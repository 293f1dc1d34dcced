"""The ``rigidjax simulate`` command, run in-process on small batches of each scene."""

import argparse
import contextlib
import io
import json
import math
import re
import sys

import numpy as np
import pytest
from helpers import cli_in_fresh_cache, removed_after

import rigidjax
from rigidjax._cli import main


def _run(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def _field(text, label):
    """The value printed after ``label:`` in the summary."""
    match = re.search(rf"^\s+{re.escape(label)}:\s+(.*)$", text, re.MULTILINE)
    assert match, f"no {label!r} line in:\n{text}"
    return match.group(1)


def _number(text, label):
    return float(_field(text, label).split()[0].replace(",", ""))


@pytest.fixture(scope="module")
def heavy_top(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("heavy_top")
    npz, png = tmp / "tops.npz", tmp / "tops.png"
    argv = [
        "simulate",
        "-n",
        "64",
        "--duration",
        "0.5",
        "--samples",
        "20",
        "--out",
        str(npz),
        "--plot",
        str(png),
    ]
    code, out, err = _run(argv)
    return code, out, err, npz, png


def test_heavy_top_runs_and_writes_files(heavy_top):
    code, out, err, npz, png = heavy_top
    assert code == 0, err
    assert npz.stat().st_size > 0 and png.stat().st_size > 0
    assert "compiled in" in err and "simulating [" in err and "1/1 blocks" in err
    with np.load(npz) as data:
        assert data["ts"].shape == (20,)
        assert data["omega"].shape == (64, 20, 3) and data["omega"].dtype == np.float32
        assert data["orientation"].shape == (64, 20, 4)
        assert data["euler_angles"].shape == (64, 20, 3)
        for key, shape in [
            ("inertia", (64, 3)),
            ("mass", (64,)),
            ("com", (64, 3)),
            ("omega0", (64, 3)),
            ("euler0", (64, 3)),
            ("orientation0", (64, 4)),
            ("theta_max", (64,)),
            ("theta_max_pred", (64,)),
            ("success", (64,)),
            ("drift_energy", (64,)),
        ]:
            assert data[key].shape == shape, key
        assert str(data["scene"]) == "heavy-top" and int(data["save_every"]) == 1
        # The stored samples are the simulated motion: t = 0 is the initial state.
        np.testing.assert_allclose(data["omega"][:, 0], data["omega0"], rtol=1e-6)
        np.testing.assert_allclose(data["euler_angles"][:, 0, 1], data["euler0"][:, 1], atol=1e-6)
        summary = json.loads(str(data["summary_json"]))
        drift = data["drift_energy"]
        theta_err = np.abs(data["theta_max"] - data["theta_max_pred"])
        estimate = {key: data["error_estimate_" + key] for key in ("omega", "orientation")}
    # The summary prints the numbers that are in the file.
    assert _number(out, "bodies") == 64
    assert _number(out, "samples") == 20
    assert _field(out, "dtype") == "float64"
    assert _field(out, "accuracy").startswith("balanced")
    assert _number(out, "solver steps") == summary["solver_steps"] > 0
    assert _number(out, "body-steps") == summary["body_steps"] == summary["solver_steps"] * 64
    assert _number(out, "wall time") > 0 and _number(out, "compile time") > 0
    assert _number(out, "worst drift energy") == pytest.approx(drift.max(), rel=1e-3)
    assert _number(out, "failed bodies") == 0
    # The error estimate (on by default): the worst body named, with the value the file holds.
    for key, values in estimate.items():
        worst = summary["worst_error_estimate"][key]
        assert values.shape == (64,) and values[worst["body"]] == values.max() == worst["estimate"]
        assert _number(out, f"worst error estimate {key}") == pytest.approx(values.max(), rel=1e-3)
        assert _field(out, f"worst error estimate {key}").endswith(f"(body {worst['body']})")
    upright, fell = re.findall(r"([\d,]+) (?:stayed|fell)", _field(out, "upright / fell"))
    assert int(upright) + int(fell) == 64
    # Physics: energy is conserved and the nutation reaches the closed-form turning point.
    assert drift.max() < 1e-6
    assert _number(out, "worst drift vertical_angular_momentum") < 1e-6
    assert np.median(theta_err) < 1e-2


@pytest.fixture(scope="module")
def earth(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("earth")
    npz, png = tmp / "earth.npz", tmp / "earth.png"
    code, out, err = _run(["simulate", "--scene", "earth", "-n", "4", "--out", str(npz), "--plot", str(png)])
    return code, out, err, npz, png


def test_earth_wobble_period(earth):
    code, out, err, npz, png = earth
    assert code == 0, err
    assert png.exists()
    # The rigid Earth's Euler period from its dynamical ellipticity H = (C - A) / C (IERS
    # Conventions 2010): A / (C - A) sidereal days (the moments 8.0101e37, 8.0365e37 gave 302.58).
    h, omega3 = 3.2737949e-3, 7.292115e-5
    closed = 2 * math.pi / (h / (1 - h) * omega3)
    assert closed / 86400 == pytest.approx(303.62, abs=0.01)
    assert closed * omega3 / (2 * math.pi) == pytest.approx((1 - h) / h, rel=1e-12)  # sidereal days
    printed = _number(out, "wobble period")
    assert printed == pytest.approx(closed, rel=1e-6)
    with np.load(npz) as data:
        assert data["omega"].shape == (4, 200, 3)
        assert "orientation" not in data.files  # Euler's equations only
        np.testing.assert_allclose(data["wobble_period"], closed, rtol=1e-6)
        assert data["ts"][-1] == pytest.approx(3 * closed, rel=1e-6)
        assert np.max(data["wobble_amplitude_drift"]) < 1e-6


@pytest.mark.slow
def test_free_bodies(tmp_path):
    npz, png = tmp_path / "free.npz", tmp_path / "free.png"
    argv = [
        "simulate",
        "--scene",
        "free",
        "-n",
        "30",
        "--duration",
        "3",
        "--samples",
        "60",
        "--out",
        str(npz),
        "--plot",
        str(png),
    ]
    code, out, err = _run(argv)
    assert code == 0, err
    assert png.exists()
    with np.load(npz) as data:
        assert data["orientation"].shape == (30, 60, 4)
        axis, flipped = data["spin_axis"], data["flipped"]
        assert not flipped[axis != 1].any()  # spins about the minor and major axes are stable
        assert flipped[axis == 1].any()  # the tennis-racket flip
        for key in ("energy", "angular_momentum_norm", "space_angular_momentum"):
            assert data["drift_" + key].max() < 1e-6, key
    assert _number(out, "worst drift energy") < 1e-6
    assert "spun near intermediate" in out


@pytest.mark.slow
def test_float32_without_matplotlib(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    npz, png = tmp_path / "f32.npz", tmp_path / "f32.png"
    argv = [
        "simulate",
        "--scene",
        "free",
        "-n",
        "5",
        "--duration",
        "1",
        "--samples",
        "10",
        "--dtype",
        "float32",
        "--save-dtype",
        "float64",
        "--out",
        str(npz),
        "--plot",
        str(png),
        "--seed",
        "3",
    ]
    code, out, err = _run(argv)
    assert code == 0, err
    assert "matplotlib is not installed" in err and not png.exists()
    assert _field(out, "dtype") == "float32"
    with np.load(npz) as data:
        assert data["omega"].shape == (5, 10, 3) and data["omega"].dtype == np.float64
        assert data["drift_energy"].max() < 1e-4
        assert int(data["seed"]) == 3


def test_quiet_prints_nothing(tmp_path):
    # Same shapes as test_float32_without_matplotlib: no new compile.
    argv = [
        "simulate",
        "--scene",
        "free",
        "-n",
        "5",
        "--duration",
        "1",
        "--samples",
        "10",
        "--dtype",
        "float32",
        "--out",
        str(tmp_path / "q.npz"),
        "--no-plot",
        "--quiet",
        "--no-error-estimate",
    ]
    code, out, err = _run(argv)
    assert code == 0 and out == "" and err == ""
    assert (tmp_path / "q.npz").exists() and not (tmp_path / "rigidjax_simulate.png").exists()
    with np.load(tmp_path / "q.npz") as data:
        assert "error_estimate_omega" not in data
        assert json.loads(str(data["summary_json"]))["worst_error_estimate"] == {}


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "-n", "0"], "must be a positive integer, got 0"),
        (["simulate", "--bodies", "ten"], "must be a positive integer, got 'ten'"),
        (["simulate", "--duration", "-1"], "must be a positive finite number"),
        (["simulate", "--samples", "1"], "must be at least 2"),
        (["simulate", "--scene", "moon"], "invalid choice: 'moon'"),
        (["simulate", "--accuracy", "sloppy"], "invalid choice: 'sloppy'"),
        # NumPy's own error, in a traceback, before.
        (["simulate", "--seed", "-1"], "--seed: must be a non-negative integer, got -1"),
    ],
)
def test_bad_arguments(argv, message):
    code, out, err = _run(argv)
    assert code == 2
    assert message in err and "usage: rigidjax simulate" in err


def test_help_and_version():
    code, out, _ = _run([])
    assert code == 0 and "simulate" in out and "usage: rigidjax" in out
    code, out, _ = _run(["--version"])
    assert code == 0 and out.strip() == f"rigidjax {rigidjax.__version__}"
    code, out, _ = _run(["simulate", "--help"])
    assert code == 0 and "--save-every" in out and "--dtype" in out
    code, out, _ = _run(["bench", "--help"])
    assert code == 0 and "--methods" in out and "block_until_ready" in out


def test_heavy_top_orientation_is_rigidjax_quat_from_euler():
    """The tops' initial orientation is rigidjax's own zxz quaternion, in float64."""
    from rigidjax._cli.scenes import SCENE_BUILDERS

    scene = SCENE_BUILDERS["heavy-top"](20, np.random.default_rng(0))
    euler0 = scene.params["euler0"]
    assert scene.orientation0.dtype == np.float64 and scene.orientation0.shape == (20, 4)
    np.testing.assert_allclose(scene.orientation0, np.asarray(rigidjax.quat_from_euler(euler0)), atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(scene.orientation0, axis=-1), 1.0, atol=1e-15)
    back = np.asarray(rigidjax.euler_from_quat(scene.orientation0))
    np.testing.assert_allclose(back[:, 1], euler0[:, 1], atol=1e-12)  # the tilt survives the round trip


# ---------------------------------------------------------------------------------------------
# rigidjax bench


def _bench_table_row(out, accuracy):
    line = next(x for x in out.splitlines() if x.startswith(f"| {accuracy} |"))
    return [cell.strip() for cell in line.strip("|").split("|")]


@pytest.mark.slow
def test_bench_small_run(tmp_path):
    """A preset and the closed form on 3 bodies: the progress line, the JSON, the table, the physics.
    (Three bodies' moments, a (3, 3) array, were once read as one inertia tensor and refused.)"""
    path = tmp_path / "bench.json"
    argv = ["bench", "-n", "3", "--methods", "fast,exact", "--repeats", "1", "--json", str(path)]
    code, out, err = _run(argv)
    assert code == 0, err
    assert "bench [" in err and "4/4 calls" in err  # 2 settings x (first call + 1 repeat)
    data = json.loads(path.read_text())
    assert data["bodies"] == 3 and data["dtype"] == "float64" and data["repeats"] == 1
    rows = {r["accuracy"]: r for r in data["rows"]}
    assert list(rows) == ["fast", "exact"]
    fast, exact = rows["fast"], rows["exact"]
    # The float64 closed form is the reference: its own error is zero and the table says so.
    assert exact["max_rel_omega"] == 0.0 and exact["max_angle"] < 1e-15 and exact["steps"] is None
    assert _bench_table_row(out, "exact")[5:] == ["(reference)"] * 3
    # The "fast" preset (Tsit5, rtol 1e-5) through the flips: small but nonzero error, steps counted.
    assert 0 < fast["max_rel_omega"] < 1e-3 and 0 < fast["max_angle"] < 1e-1
    assert fast["median_rel_omega"] <= fast["max_rel_omega"] and fast["steps"] > 10
    assert fast["solver"] == "Tsit5, rtol 1e-05"
    for r in data["rows"]:
        assert r["run_s"] > 0 and len(r["runs_s"]) == 1 and r["run_s"] == r["runs_s"][0]
        assert r["compile_s"] == pytest.approx(max(r["first_call_s"] - r["run_s"], 0.0))  # noise: >= 0
    # The printed table carries the numbers of the JSON.
    cells = _bench_table_row(out, "fast")
    assert float(cells[5]) == pytest.approx(fast["max_rel_omega"], rel=0.06)
    assert int(cells[4].replace(",", "")) == fast["steps"]
    assert "3 torque-free bodies" in out and "T = 20 s" in out


@pytest.mark.slow
def test_bench_float32_against_the_float64_closed_form(tmp_path):
    """In float32 the closed form is measured against the float64 one (computed apart)."""
    path = tmp_path / "bench32.json"
    argv = ["bench", "-n", "8", "--methods", "exact", "--dtype", "float32", "--repeats", "1"]
    code, out, err = _run(argv + ["--duration", "2", "--json", str(path)])
    assert code == 0, err
    assert "3/3 calls" in err  # the float64 reference, then the first call and one repeat
    (row,) = json.loads(path.read_text())["rows"]
    assert row["dtype"] == "float32"
    assert 1e-9 < row["max_rel_omega"] < 1e-3
    assert "(reference)" not in out


def test_bench_rejects_unknown_method():
    code, out, err = _run(["bench", "--methods", "fast,euler"])
    _assert_one_line_error(code, out, err, "bench", "unknown --methods euler; choose from fast,")
    code, out, err = _run(["bench", "--methods", ","])
    _assert_one_line_error(code, out, err, "bench", "--methods names no method")
    code, out, err = _run(["bench", "-n", "0"])
    assert code == 2 and "must be a positive integer, got 0" in err and "usage: rigidjax bench" in err


def test_cli_uses_public_rigidjax_names_only():
    """The command line imports rigidjax as a user would: ``import rigidjax as rj``, no private module,
    no ``rj._name`` and no top-level name that has moved (those warn). Two exceptions, in
    ``common.py`` only: the atomic file writer of ``Trajectory.save`` (``_integrate/storage.py``) and
    the progress line of ``simulate(progress=True)`` (``_integrate/progress.py``), so that the
    commands write files and progress with the same code rather than a copy of it."""
    import ast
    import warnings
    from pathlib import Path

    package = Path(rigidjax.__file__).parent / "_cli"
    for path in sorted(package.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                if (path.name, node.level) == ("common.py", 2) and node.module in (
                    "_integrate.storage",
                    "_integrate.progress",
                ):
                    continue
                assert node.level in (0, 1), f"{path.name}: import from outside the CLI package"
                assert node.level == 1 or not (node.module or "").startswith("rigidjax"), path.name
            if isinstance(node, ast.Import):
                assert all(a.name.split(".")[0] != "rigidjax" or a.name == "rigidjax" for a in node.names)
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "rj":
                name = node.attr
                assert not name.startswith("_") or name == "__version__", f"{path.name}: rj.{name}"
                with warnings.catch_warnings():
                    warnings.simplefilter("error", DeprecationWarning)
                    getattr(rigidjax, name)


# ---------------------------------------------------------------------------------------------
# Nothing lost on disk: output paths checked before the run, atomic writes, Ctrl-C


def _fail_if_run(*args, **kwargs):
    raise AssertionError("the job started before its output paths were checked")


def _assert_one_line_error(code, out, err, command, message):
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith(f"rigidjax {command}: error: "), err
    assert message in err and "Traceback" not in err


@pytest.mark.parametrize(
    "options, message",
    [
        (["--out", "missing/x.npz"], "--out: cannot write 'missing/x.npz': the directory"),
        (["--out", "x.csv"], "--out 'x.csv': the file name must end in .npz"),
        (["--out", "result"], "--out 'result': the file name must end in .npz"),
        (["--out", "adir.npz"], "--out: 'adir.npz' is a directory"),
        (["--plot", "missing/x.png"], "--plot: cannot write 'missing/x.png': the directory"),
        (["--plot", "x.txt"], "--plot 'x.txt': the file name must end in .png or .pdf or .svg"),
    ],
)
def test_simulate_checks_output_paths_before_the_run(tmp_path, monkeypatch, options, message):
    """``--out missing_dir/x.npz`` once ran the whole job, then died with a raw FileNotFoundError."""
    from rigidjax._cli import simulate as cli_simulate

    monkeypatch.chdir(tmp_path)
    (tmp_path / "adir.npz").mkdir()
    monkeypatch.setattr(cli_simulate, "plan_run", _fail_if_run)
    code, out, err = _run(["simulate", *options])
    _assert_one_line_error(code, out, err, "simulate", message)


def test_simulate_skipped_outputs_are_not_checked(tmp_path, monkeypatch):
    """``--out ''`` and ``--no-plot`` write nothing, so their paths are not checked."""
    from rigidjax._cli import simulate as cli_simulate

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli_simulate, "plan_run", _fail_if_run)
    with pytest.raises(AssertionError, match="the job started"):
        _run(["simulate", "--out", "", "--plot", "missing/x.txt", "--no-plot"])


def test_bench_checks_its_json_path_before_the_run(tmp_path, monkeypatch):
    from rigidjax._cli import bench as cli_bench

    monkeypatch.setattr(cli_bench, "tennis_racket_scene", _fail_if_run)
    code, out, err = _run(["bench", "--json", str(tmp_path / "missing" / "b.json")])
    _assert_one_line_error(code, out, err, "bench", "--json: cannot write")
    code, out, err = _run(["bench", "--json", str(tmp_path / "b.txt")])
    _assert_one_line_error(code, out, err, "bench", "the file name must end in .json")


def test_ctrl_c_exits_130_with_one_line(monkeypatch, tmp_path):
    from rigidjax._cli import simulate as cli_simulate

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli_simulate, "plan_run", interrupted)
    code, out, err = _run(["simulate", "-q"])
    assert code == 130 and out == ""
    assert err == "rigidjax simulate: interrupted (Ctrl-C); no output file is left half-written.\n"


def test_ctrl_c_while_writing_leaves_the_old_file(tmp_path, monkeypatch):
    """An interrupted write of the .npz (the writer of Trajectory.save, here interrupted halfway)
    leaves the previous file intact and no temporary file behind. The same small float32 run as
    test_quiet_prints_nothing (no new compile)."""
    from rigidjax._integrate import storage

    def half_then_interrupt(file, arrays):
        file.write(b"PK\x03\x04 half an archive")
        raise KeyboardInterrupt

    out_path = tmp_path / "q.npz"
    out_path.write_bytes(b"the previous result")
    monkeypatch.setattr(storage, "_write_arrays", half_then_interrupt)
    argv = ["simulate", "--scene", "free", "-n", "5", "--duration", "1", "--samples", "10"]
    argv += ["--dtype", "float32", "--out", str(out_path), "--no-plot", "--quiet"]
    code, out, err = _run(argv)
    assert code == 130 and "interrupted (Ctrl-C)" in err
    assert out_path.read_bytes() == b"the previous result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["q.npz"]


def test_interrupted_text_and_figure_writes_leave_nothing(tmp_path):
    """The JSON and figure writers of the commands: the old file or the complete new one."""
    from rigidjax._cli.common import write_figure, write_text

    class Figure:
        def savefig(self, handle, format, dpi):
            assert format == "png"
            handle.write(b"\x89PNG partial")
            raise KeyboardInterrupt

    target = tmp_path / "result.json"
    write_text(str(target), '{"old": 1}')
    with pytest.raises(KeyboardInterrupt):
        write_figure(str(tmp_path / "plot.png"), Figure())
    assert target.read_text() == '{"old": 1}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.json"]


@pytest.mark.slow
def test_a_real_sigint_exits_130_with_one_line(tmp_path):
    """The real signal, in a child process: Ctrl-C once the run has started (after the
    'compiling' line) gives one line, exit status 130 and no file, complete or partial."""
    import signal
    import subprocess

    out_dir = tmp_path / "out"
    out_dir.mkdir()
    argv = [sys.executable, "-m", "rigidjax._cli", "simulate", "-n", "2000", "--duration", "50"]
    argv += ["--out", str(out_dir / "x.npz"), "--plot", str(out_dir / "x.png")]
    child = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        lines = []
        while not lines or "compiling" not in lines[-1]:
            lines.append(child.stderr.readline())
            assert lines[-1], f"the run ended before it started compiling: {lines}"
        child.send_signal(signal.SIGINT)
        out, err = child.communicate(timeout=600)  # a guard against a hang, not a timing
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == 130, err
    assert err == "rigidjax simulate: interrupted (Ctrl-C); no output file is left half-written.\n"
    assert out == "" and list(out_dir.iterdir()) == []


def test_ctrl_c_in_the_command_itself_ends_the_process_at_once(monkeypatch, tmp_path):
    """As the command (``main()`` with no arguments) Ctrl-C ends the process with ``os._exit(130)``:
    interpreter shutdown under a compiled computation still running in JAX's threads waited for it
    to finish or crashed (a fit interrupted with -q exited with SIGSEGV). Called with arguments, as
    here above, main returns 130 instead."""
    from rigidjax._cli import parser
    from rigidjax._cli import simulate as cli_simulate

    class Exited(Exception):
        pass

    def fake_exit(code):
        raise Exited(code)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli_simulate, "plan_run", interrupted)
    monkeypatch.setattr(parser.os, "_exit", fake_exit)
    monkeypatch.setattr(sys, "argv", ["rigidjax", "simulate", "-q"])
    err = io.StringIO()
    with contextlib.redirect_stderr(err), pytest.raises(Exited) as exited:
        main()
    assert exited.value.args == (130,)
    assert err.getvalue() == "rigidjax simulate: interrupted (Ctrl-C); no output file is left half-written.\n"


@pytest.mark.parametrize("extension", [".png", ".pdf", ".svg"])
def test_figures_are_written_in_the_format_of_their_extension(tmp_path, extension):
    """--plot accepts .png, .pdf and .svg; the atomic writer passes the format on (a temporary file's
    name does not end in it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rigidjax._cli.common import write_figure

    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = tmp_path / f"figure{extension}"
    write_figure(str(path), fig)
    plt.close(fig)
    magic = {".png": b"\x89PNG", ".pdf": b"%PDF", ".svg": b"<?xml"}[extension]
    assert path.read_bytes().startswith(magic)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_save_every_beyond_the_samples_is_an_error(tmp_path, monkeypatch):
    """--save-every 500 with 200 samples stored only t = 0, silently."""
    from rigidjax._cli import simulate as cli_simulate

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli_simulate, "run_block", _fail_if_run)
    code, out, err = _run(["simulate", "-n", "3", "--samples", "200", "--save-every", "500"])
    _assert_one_line_error(
        code,
        out,
        err,
        "simulate",
        "--save-every 500 is not below the number of samples (200); give at most 199",
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_exact_runs_the_main_job_on_symmetric_tops(tmp_path):
    """--accuracy exact: the heavy-top scene made of Lagrange tops, evaluated in closed form; the
    stored motion agrees with rigidjax.simulate(accuracy="precise") integrating the same tops from
    the parameters the file stores."""
    out = tmp_path / "exact.npz"
    argv = ["simulate", "--accuracy", "exact", "-n", "6", "--duration", "1", "--samples", "11"]
    code, stdout, _ = _run(argv + ["--out", str(out), "--no-plot"])
    assert code == 0, stdout
    assert "exact (closed form" in stdout and "symmetric" in stdout and "solver steps" not in stdout
    data = np.load(out)
    assert np.all(data["inertia"][:, 0] == data["inertia"][:, 1]) and np.all(data["success"])
    model = rigidjax.HeavyTop(data["inertia"], data["mass"], data["com"], gravity=data["gravity"])
    state0 = rigidjax.State(data["omega0"], data["orientation0"])
    precise = rigidjax.simulate(model, state0, data["ts"], accuracy="precise")
    np.testing.assert_allclose(
        data["omega"], precise.omega, rtol=0, atol=1e-7 * np.max(np.abs(data["omega"]))
    )


@pytest.mark.parametrize("command", ["simulate", "fit", "bench"])
def test_help_is_plain_text(command):
    """Help a user reads: no '(default: None)' for options without a default, no docstring markup."""
    code, out, _ = _run([command, "--help"])
    assert code == 0 and f"usage: rigidjax {command}" in out
    assert "default: None" not in out
    assert "``" not in out and not re.search(r":[a-z]+:`", out), out


@pytest.mark.slow
def test_compiled_programs_are_kept_between_invocations(tmp_path):
    """With no cache directory chosen, the command keeps its programs in
    $XDG_CACHE_HOME/rigidjax/jax, the integration among them (it holds no host callback, which JAX
    would refuse to store); a second run of the same scene loads it instead of compiling it."""
    run = cli_in_fresh_cache(
        tmp_path, "simulate", "--scene", "free", "-n", "8", "--duration", "1", "--samples", "5",
        "--out", str(tmp_path / "x.npz"), "--no-plot", "-q",
    )  # fmt: skip
    run()
    cache = tmp_path / "xdg" / "rigidjax" / "jax"
    assert any("integrate_traced" in p.name for p in cache.iterdir()), sorted(p.name for p in cache.iterdir())
    _, second = run()
    assert "Persistent compilation cache hit for 'jit__integrate_traced'" in second


def _three_free_bodies(tmp_path, *extra):
    argv = [
        "simulate",
        "--scene",
        "free",
        "-n",
        "3",
        "--duration",
        "1",
        "--samples",
        "10",
        "--no-error-estimate",
    ]
    return _run([*argv, "--out", str(tmp_path / "three.npz"), *extra])


def test_three_bodies_run_in_a_block_of_four_and_are_drawn_as_themselves(tmp_path, monkeypatch):
    """Three bodies' principal moments, a (3, 3) array, read as ONE inertia tensor: ``-n 3`` (or any
    block of three) was refused with a traceback, and ``--animate`` drew the first three bodies as
    boxes of that matrix's eigenvalues. Reference: each body integrated alone by rigidjax.simulate."""
    import jax.numpy as jnp

    import rigidjax.plot
    from rigidjax._plot import data as plot_data

    drawn = {}

    def record(trajectory, path, bodies):
        drawn["moments"] = [np.linalg.eigvalsh(plot_data.inertia(trajectory, i)) for i in bodies]
        with open(path, "wb") as f:
            f.write(b"GIF89a")

    monkeypatch.setattr(rigidjax.plot, "animate", record)
    code, out, err = _three_free_bodies(tmp_path, "--no-plot", "--animate", str(tmp_path / "three.gif"))
    assert code == 0, err
    assert _field(out, "bodies") == "3 (1 block of 4, last padded with 1 copy)"
    with np.load(tmp_path / "three.npz") as data:
        inertia, omega0, q0, ts = data["inertia"], data["omega0"], data["orientation0"], data["ts"]
        assert data["omega"].shape == (3, 10, 3) and bool(np.all(data["success"]))
        stored = data["omega"]
    for i in range(3):
        np.testing.assert_allclose(np.sort(drawn["moments"][i]), np.sort(inertia[i]), rtol=1e-6)
        alone = rigidjax.simulate(
            rigidjax.FreeBody(jnp.asarray(inertia[i])),
            rigidjax.State(jnp.asarray(omega0[i]), jnp.asarray(q0[i])),
            jnp.asarray(ts),
        )
        np.testing.assert_allclose(
            stored[i], np.asarray(alone.omega), rtol=0, atol=1e-5 * np.abs(omega0[i]).max()
        )


def test_results_are_rescued_when_the_output_directory_goes_away_during_the_run(tmp_path, monkeypatch):
    """The output directory existed when the run started and was removed during it: the run ended
    in a raw FileNotFoundError, without its summary, and nothing was saved."""
    from rigidjax._cli import simulate as cli_simulate

    outputs = tmp_path / "outputs"
    outputs.mkdir()
    rescue = removed_after(monkeypatch, cli_simulate, "simulate_blocks", outputs)
    code, out, err = _three_free_bodies(
        tmp_path, "--out", str(outputs / "r.npz"), "--plot", str(outputs / "r.png")
    )
    assert code == 1
    assert "Traceback" not in err
    saved = sorted(rescue.iterdir())
    assert [p.suffix for p in saved] == [".npz", ".png"]
    for option, path in zip(("--out", "--plot"), saved, strict=True):
        assert f"error: {option} '{outputs / ('r' + path.suffix)}': could not write" in err
        assert f"written to '{path}' instead" in err
        assert "wrote:" in out and str(path) in out  # the summary is printed, with where the files are
    with np.load(saved[0]) as data:
        assert data["omega"].shape == (3, 10, 3)


def test_a_file_system_that_refuses_files_is_found_before_the_run(tmp_path, monkeypatch):
    """Permission bits allow the write (as for the superuser on /proc): creating a file is the test."""
    from rigidjax._cli import simulate as cli_simulate
    from rigidjax._integrate import storage

    def refuse(directory, name):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(storage, "_open_temporary", refuse)
    monkeypatch.setattr(cli_simulate, "plan_run", _fail_if_run)
    code, out, err = _run(["simulate", "--out", str(tmp_path / "r.npz")])
    _assert_one_line_error(code, out, err, "simulate", "a file cannot be created in")
    assert "Read-only file system" in err


def test_a_duration_beyond_the_step_limit_is_one_line(tmp_path):
    """``--duration 1e20`` compiled on a span of 1e11 s (the span shrunk by 1e-9) for hours;
    ``--duration 1e-300`` shrunk to zero and stopped with a traceback. The compiling call now covers
    a milliradian of the fastest body's rotation (or the whole span if shorter)."""
    code, out, err = _three_free_bodies(tmp_path, "--duration", "1e20", "--no-plot", "-q")
    assert code == 2 and out == "" and "Traceback" not in err
    assert err.startswith("rigidjax simulate: error: --duration 1e+20: simulate: ts spans")
    assert "accuracy='exact'" in err
    code, out, err = _three_free_bodies(tmp_path, "--duration", "1e-300", "--no-plot", "-q")
    assert code == 0, err
    with np.load(tmp_path / "three.npz") as data:
        np.testing.assert_allclose(data["omega"][:, -1], data["omega0"], rtol=1e-6)  # no time to move


def _simulate_args(**options):
    """The parsed options of ``rigidjax simulate --scene free`` that planning a run reads."""
    import argparse

    defaults = dict(scene="free", bodies=3, duration=1.0, samples=10, seed=0, accuracy="balanced",
                    blocks=None, save_every=None, save_dtype="float32", dtype="float64", out="")  # fmt: skip
    return argparse.Namespace(**{**defaults, **options})


@pytest.mark.parametrize("duration", [1e-300, 1.0, 1e20])
def test_the_compiling_call_is_short_and_its_times_distinct(duration):
    from rigidjax._cli.batch import plan_run
    from rigidjax._cli.simulate import _warm_up_times

    plan = plan_run(_simulate_args(bodies=3, duration=duration, out="rigidjax_simulate.npz"))
    ts = _warm_up_times(plan)
    fastest = np.max(np.linalg.norm(plan.scene.omega0, axis=-1))
    assert ts.shape == (10,) and np.all(np.diff(ts) > 0) and ts[0] == 0.0
    assert ts[-1] == min(duration, 1e-3 / fastest)


def test_earth_in_float32_with_the_closed_form():
    """The Earth's squared angular momentum in SI units (~3e67) overflows float32, so the command
    refused the closed form in float32. The closed form now computes with the moments scaled so that
    the largest is below 1: the run succeeds, and the wobble period fitted to its samples agrees
    with Euler's formula 2 pi / ((C - A)/A w3) to float32's resolution (the integrator's float32 run
    of the same scene: 8e-7)."""
    argv = ["simulate", "--scene", "earth", "--accuracy", "exact", "--dtype", "float32", "--no-plot"]
    code, out, err = _run([*argv, "--out", ""])
    assert code == 0, err
    assert _number(out, "failed bodies") == 0
    largest = float(_field(out, "period rel. error").split()[1].rstrip(","))  # "max 6.8e-07, mean ..."
    assert largest < 1e-5, _field(out, "period rel. error")


def test_failed_closed_form_rows_are_nan_from_the_first_failed_sample(tmp_path):
    """Over 1e20 s the closed form's phase is beyond what float64 resolves: the bodies fail, and
    the stored rows were the values evaluated there (up to 1e56 for a unit quaternion), though the
    message said NaN rows. The first sample (t = 0) is the initial state itself."""
    code, out, err = _three_free_bodies(
        tmp_path, "--duration", "1e20", "--accuracy", "exact", "--no-plot", "-q"
    )
    # The run is float64 already: the advice is the duration only (it named --dtype float64 too).
    assert (
        code == 1 and "closed form failed for 3 bodies" in err and err.endswith("try a shorter --duration.\n")
    )
    with np.load(tmp_path / "three.npz") as data:
        assert not data["success"].any()
        np.testing.assert_allclose(data["omega"][:, 0], data["omega0"], rtol=1e-7)
        for key in ("omega", "orientation", "euler_angles"):
            assert np.isnan(data[key][:, 1:]).all(), key


def test_the_free_scene_says_when_its_samples_are_too_sparse_to_see_flips():
    """With three samples over 5 s the summary said "0 flipped (unstable: flips expected)" with no
    hint that flips fall between samples: the reversal lasts about half a wobble period
    (rigidjax.torque_free_period)."""
    import argparse

    from rigidjax._cli.scenes import SCENE_BUILDERS

    scene = SCENE_BUILDERS["free"](30, np.random.default_rng(0))
    res = {"flipped": np.zeros(30, bool), "success": np.ones(30, bool)}
    args = argparse.Namespace()
    sparse, _ = scene.summarize(res, np.linspace(0.0, 5.0, 3), args)
    dense, _ = scene.summarize(res, np.linspace(0.0, 5.0, 200), args)
    assert "flips can fall between samples" in dict(sparse)["flip detection"]
    assert "flip detection" not in dict(dense)


@pytest.mark.slow
def test_a_float32_run_estimates_its_error_against_a_float64_solve(tmp_path):
    """float32 runs (a process of their own, JAX's 64-bit mode off, as a user starts them) had their
    second solve in float32 at the same tolerance floor (1.2e-6): every body's estimate was that
    floor while the true error reached 2e4 times it near the separatrix. Reference: the float64
    closed form of the float32 inputs."""
    import subprocess

    npz = tmp_path / "f32.npz"
    argv = ["simulate", "--scene", "free", "-n", "20", "--duration", "5", "--samples", "50", "--no-plot"]
    child = subprocess.run(
        [sys.executable, "-m", "rigidjax._cli", *argv, "--dtype", "float32", "--save-dtype", "float64",
         "--out", str(npz)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert child.returncode == 0, child.stderr
    assert _field(child.stdout, "accuracy") == "balanced (Dopri8, rtol 1.2e-06)"
    with np.load(npz) as data:
        inertia, omega0, q0 = (
            data[k].astype(np.float32).astype(np.float64) for k in ("inertia", "omega0", "orientation0")
        )
        omega, q = data["omega"], data["orientation"]
        estimate = {k: data["error_estimate_" + k] for k in ("omega", "orientation")}
    ts = np.linspace(0.0, 5.0, 50)
    exact = rigidjax.simulate(rigidjax.FreeBody(inertia), rigidjax.State(omega0, q0), ts, accuracy="exact")
    scale = np.max(np.linalg.norm(exact.omega, axis=-1), axis=-1)
    true_omega = np.max(np.linalg.norm(omega - exact.omega, axis=-1), axis=-1) / scale
    relative = np.asarray(rigidjax.quat_multiply(rigidjax.quat_conjugate(q), exact.orientation))
    true_angle = np.max(
        2 * np.arctan2(np.linalg.norm(relative[..., 1:], axis=-1), np.abs(relative[..., 0])), axis=-1
    )
    assert np.max(true_omega) > 100 * np.finfo(np.float32).eps  # errors above the floor to estimate
    assert np.all(estimate["omega"] >= true_omega), np.max(true_omega / estimate["omega"])
    assert np.all(estimate["orientation"] >= true_angle), np.max(true_angle / estimate["orientation"])


def test_short_runs_compare_only_the_tops_that_reach_their_turning_point(tmp_path):
    """The heavy top's comparison with the closed form's turning point counted tops that had not
    reached it yet (--duration 0.02: "agrees for 44 of 50", a median error of 0.07 rad); the
    stored samples ended before the last (every 4th sample of 7 stored t = 0 and 4/6 of the span).
    Reference for the turning time: half the symmetric top's nutation period, 2 K(m) / sqrt(beta
    (u3 - u1)), checked here against the sampled theta of an integration."""
    npz = tmp_path / "short.npz"
    argv = ["simulate", "-n", "4", "--samples", "7", "--save-every", "4", "--accuracy", "fast", "--no-plot"]
    code, out, err = _run([*argv, "--duration", "0.01", "--out", str(npz)])
    assert code == 0, err
    assert _field(out, "closed form").startswith("no top reaches its turning point within the run")
    assert _field(out, "max theta error") == "none to compare"
    assert _field(out, "accuracy") == "fast (Tsit5, rtol 1e-05)"
    with np.load(npz) as data:
        np.testing.assert_array_equal(data["ts"], np.linspace(0.0, 0.01, 7)[[0, 4, 6]])
        turning = data["turning_time_pred"]
        model = rigidjax.HeavyTop(data["inertia"], data["mass"], data["com"], gravity=data["gravity"])
        state = rigidjax.State(data["omega0"], data["orientation0"])
    ts = np.linspace(0.0, 1.2 * turning.max(), 4001)
    theta = np.asarray(rigidjax.simulate(model, state, ts, accuracy="precise").euler_angles())[..., 1]
    first_max = ts[np.argmax(np.diff(theta, axis=-1) < 0, axis=-1)]  # the first sample after the top
    # The tops are up to 2 % asymmetric: the symmetric top's time within a few per cent.
    np.testing.assert_allclose(first_max, turning, rtol=0.05)


def test_odd_sizes_and_spans_are_one_line_errors(tmp_path, monkeypatch):
    """A span whose samples round to one time (--duration 1e-320: the compiling call failed with a
    traceback) and sizes beyond the machine's memory (numpy's "Maximum allowed dimension exceeded",
    or an XLA allocation failure of 36 GB after the start) end in one line naming the options."""
    monkeypatch.chdir(tmp_path)
    code, out, err = _run(["simulate", "-n", "4", "--samples", "5", "--duration", "1e-320", "--no-plot"])
    _assert_one_line_error(
        code, out, err, "simulate", "--duration 9.99989e-321: its 5 sample times are not distinct in float64"
    )
    from rigidjax._cli import simulate as cli_simulate

    monkeypatch.setattr(cli_simulate, "run_block", _fail_if_run)
    for argv in (
        ["--samples", str(10**13)],
        ["-n", str(10**20)],
        ["--samples", str(10**9), "-n", "5", "--out", ""],
    ):
        code, out, err = _run(["simulate", *argv, "--no-plot"])
        _assert_one_line_error(code, out, err, "simulate", "GiB), more than this machine's")
    assert list(tmp_path.iterdir()) == []


def test_a_file_removed_after_writing_does_not_stop_the_summary(tmp_path):
    """The summary read each written file's size again: a file removed in between ended the run in
    a FileNotFoundError traceback, without the summary."""
    from rigidjax._cli.common import file_size

    written = tmp_path / "out.npz"
    written.write_bytes(b"x" * 3000)
    assert file_size(str(written)) == "2.9 KiB"
    written.unlink()
    assert file_size(str(written)) == "size unknown: No such file or directory"


def test_a_drift_below_the_dtype_resolution_says_so(tmp_path):
    """The Earth in float32 printed its energy and |L| drift as 0.000e+00, which reads as exact
    conservation; the stored values do not change within float32's resolution."""
    code, out, err = _run(["simulate", "--scene", "earth", "--dtype", "float32", "--no-plot", "--out", ""])
    assert code == 0, err
    for key in ("energy", "angular_momentum_norm"):
        value = _field(out, f"worst drift {key}")
        assert value == "0 (below float32's resolution, 1.2e-07)" or float(value) > 0, value


def test_ctrl_c_keeps_the_bodies_of_the_finished_blocks(tmp_path, monkeypatch):
    """Ctrl-C after two of three blocks discarded what they had computed; now their bodies are kept
    beside --out (rows equal to the uninterrupted run's), and the one-line exit follows. Blocks of 4
    bodies and 10 samples: the program of _three_free_bodies (no compile of its own)."""
    from rigidjax._cli import batch as cli_batch

    argv = ["simulate", "--scene", "free", "-n", "12", "--blocks", "3", "--duration", "1", "--samples", "10"]
    argv += ["--no-plot", "--no-error-estimate"]
    code, out, err = _run([*argv, "--out", str(tmp_path / "whole.npz")])
    assert code == 0, err
    real_run_block, calls = cli_batch.run_block, []

    def stopped_at_the_third_block(*args, **kwargs):
        calls.append(args[2])  # the block number
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_run_block(*args, **kwargs)

    monkeypatch.setattr(cli_batch, "run_block", stopped_at_the_third_block)
    code, out, err = _run([*argv, "--out", str(tmp_path / "cut.npz")])
    assert code == 130 and calls == [0, 1, 2]
    lines = err.strip().splitlines()
    assert (
        "the 8 bodies of the 2 finished blocks (of 3) are in" in lines[-2] and "cut.partial.npz" in lines[-2]
    )
    assert lines[-1] == "rigidjax simulate: interrupted (Ctrl-C); no output file is left half-written."
    assert not (tmp_path / "cut.npz").exists()
    with np.load(tmp_path / "cut.partial.npz") as cut, np.load(tmp_path / "whole.npz") as whole:
        bodies = cut["body"]
        assert bodies.shape == (8,) and int(cut["blocks_done"]) == 2 and int(cut["blocks"]) == 3
        for key in ("omega", "orientation", "success", "inertia", "omega0", "drift_energy"):
            np.testing.assert_array_equal(cut[key], whole[key][bodies], err_msg=key)


def test_the_automatic_save_every_keeps_the_stored_samples_within_the_budget():
    """--save-every's default divided the samples' size by the budget and ignored that the last
    sample is kept too: 32.04 MiB for 10^5 Earths at 50 float64 samples, 38 MiB for 10^5 free
    bodies. Reference: the smallest K found by trying every one, counting the samples kept as the
    writer keeps them."""
    from rigidjax._cli.batch import SAVE_BUDGET_BYTES, _save_every_within_budget

    def kept(samples, every):
        return len(np.union1d(np.arange(0, samples, every), [samples - 1]))

    for samples, n, values, itemsize in [(50, 100_000, 3, 8), (200, 100_000, 10, 4), (1001, 10_000, 10, 4),
                                         (3, 10**7, 10, 8), (101, 10, 3, 4)]:  # fmt: skip
        per_sample = n * values * itemsize
        fits = [
            k for k in range(1, max(1, samples - 1) + 1) if kept(samples, k) * per_sample <= SAVE_BUDGET_BYTES
        ]
        assert _save_every_within_budget(samples, per_sample) == (fits[0] if fits else max(1, samples - 1))


def test_a_run_where_every_body_failed_reports_no_drift_and_writes_strict_json():
    """Every body failed: the summary printed "worst drift energy: 0 (below float32's resolution)"
    for NaN drifts, and summary_json held bare NaN; a seed of 2^70 made the .npz need pickling."""
    from rigidjax._cli.common import finite_or_none, rng_seed
    from rigidjax._cli.simulate import _drift_text

    assert _drift_text(float("nan"), "float32", 1.2e-7) == "n/a (no body finished)"
    assert _drift_text(0.0, "float32", 1.2e-7).startswith("0 (below float32's resolution")
    assert _drift_text(3e-9, "float64", 2.2e-16) == "3.000e-09"
    assert json.loads(
        json.dumps(finite_or_none({"worst_drift": {"energy": np.float64("nan")}}), allow_nan=False)
    ) == {"worst_drift": {"energy": None}}
    assert rng_seed(str(2**64 - 1)) == 2**64 - 1
    with pytest.raises(argparse.ArgumentTypeError, match="below 2\\^64"):
        rng_seed(str(2**70))


@pytest.mark.parametrize(
    "bodies, blocks, planned, why",
    [
        (10, 6, 5, "more would hold only padding"),
        (12, 4, 3, "blocks of 3 hold 4"),
        (10, 5, 5, None),
    ],
)
def test_a_number_of_blocks_other_than_asked_says_why(bodies, blocks, planned, why):
    """``--blocks 6`` for 10 bodies ran 5 blocks of 2 (equal blocks: a sixth would hold only copies)
    and the header did not say that the request was changed."""
    from rigidjax._cli.batch import plan_run
    from rigidjax._cli.simulate import _blocks_note

    args = _simulate_args(bodies=bodies, blocks=blocks)
    plan = plan_run(args)
    assert plan.blocks == planned and plan.blocks * plan.block_size >= bodies
    note = _blocks_note(plan, args)
    if why is None:
        assert note == ""
    else:
        assert note.startswith(f" (not --blocks {blocks}: ") and why in note


def test_one_body_is_one_body():
    code, out, err = _run(
        ["simulate", "--scene", "free", "-n", "1", "--blocks", "3", "--duration", "0.1", "--samples", "5"]
        + ["--out", "", "--no-plot"]
    )
    assert code == 0, err
    assert "1 block of 1 body (not --blocks 3: " in err, err
    assert _field(out, "bodies") == "1 (1 block of 1)"
    # The error estimate's second solve is in the wall time, not in the steps counted.
    assert "over the wall time of both solves" in _field(out, "body-steps/s")
    assert not re.search(r"(?<![/\d,])1 bodies", out + err) and "block(s)" not in out + err


@pytest.mark.parametrize("command", ["simulate", "fit", "bench"])
def test_every_option_with_a_default_shows_it_in_the_help(command):
    """``rigidjax bench --help`` and ``rigidjax fit --help`` did not show the defaults of --repeats,
    --dtype, --seed, --loss, --method or --steps (nor what --loss and --method do)."""
    import argparse

    from rigidjax._cli.parser import build_parser

    subparsers = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    parser = subparsers.choices[command]
    text = parser.format_help()
    for action in parser._actions:
        if action.default in (None, False, argparse.SUPPRESS) or not action.option_strings:
            continue
        help_text = parser._get_formatter()._get_help_string(action) or ""
        assert "(default" in help_text, (action.option_strings, help_text)
        assert help_text.count("(default") - help_text.count("%(default)") == 1, help_text
    assert "(default 300)" not in text and "default: False" not in text


def test_samples_too_sparse_to_show_the_turning_point_are_not_compared():
    """Three samples over 1 s fall anywhere in the tops' nutation (half periods of 0.02-0.3 s): the
    largest sampled tilt is not the largest tilt, and the summary compared it with the closed form
    anyway ("agrees for 4 of 4", a median error of 0.04 rad: the agreement was luck)."""
    argv = ["simulate", "-n", "4", "--samples", "3", "--duration", "1", "--accuracy", "fast", "--no-plot"]
    code, out, err = _run([*argv, "--out", "", "--no-error-estimate"])
    assert code == 0, err
    comparison = _field(out, "closed form")
    assert comparison.startswith("nothing to compare: 4 reach their turning point between samples too far"), (
        out
    )
    assert _field(out, "max theta error") == "none to compare"


@pytest.mark.parametrize(
    "accuracy, dtype, second",
    [
        ("balanced", "float64", "second, finer solve"),
        ("balanced", "float32", "second, finer solve, in float64"),
        ("exact", "float64", "second evaluation, at inputs perturbed by a rounding unit"),
        ("exact", "float32", "second evaluation, in float64"),
    ],
)
def test_the_wall_time_names_the_error_estimates_second_run(accuracy, dtype, second):
    """It said "second, finer solve" also for the closed form, which is evaluated again at perturbed
    inputs (or in float64 for a float32 run: rigidjax._integrate.error_estimate)."""
    from rigidjax._cli.simulate import _second_run

    assert _second_run(_simulate_args(accuracy=accuracy, dtype=dtype)) == second


def test_a_directory_given_as_the_plot_is_answered_with_a_plot_name(tmp_path):
    """``--plot pp.png`` naming a directory suggested 'pp.png/trajectory.npz', which --plot refuses."""
    from rigidjax._cli.common import UsageError, check_output

    folder = tmp_path / "pp.png"
    folder.mkdir()
    with pytest.raises(
        UsageError, match=r"is a directory; give a file path such as '.*pp\.png/trajectory\.png'"
    ):
        check_output(str(folder), "--plot", (".png", ".pdf", ".svg"))
    (tmp_path / "out.npz").mkdir()
    with pytest.raises(UsageError, match=r"give a file path such as '.*out\.npz/trajectory\.npz'"):
        check_output(str(tmp_path / "out.npz"), "--out", (".npz",))
