"""``rigidjax fit data.csv``: a synthetic record in, the inertia with uncertainties, JSON and PNG out;
clear errors for malformed files."""

import json

import numpy as np
import pytest
from helpers import cli_in_fresh_cache, removed_after

import rigidjax as rj
from rigidjax._cli import main
from rigidjax._cli.fit import in_command_words


def run_fit(argv):
    return main(["fit", *argv])


def write_csv(path, ts, omega, header="t,wx,wy,wz"):
    rows = [header] + [
        ",".join([f"{t:.17g}"] + ["" if np.isnan(w) else f"{w:.17g}" for w in row])
        for t, row in zip(ts, omega, strict=True)
    ]
    path.write_text("\n".join(rows) + "\n")


@pytest.mark.slow
def test_fit_command_recovers_inertia(tmp_path, capsys):
    inertia = np.array([1.0, 2.0, 2.5])
    omega0 = np.array([0.3, 0.05, 1.0])
    ts = np.linspace(0.0, 40.0, 240)
    rng = np.random.default_rng(0)
    w = np.asarray(rj.torque_free_omega(inertia, omega0, ts))
    obs = w + 0.01 * np.std(w, axis=0) * rng.standard_normal(w.shape)
    obs[5, 1] = np.nan
    data = tmp_path / "gyro.csv"
    write_csv(data, ts, obs)
    status = run_fit([str(data), "--quiet"])
    out = capsys.readouterr().out
    assert status == 0, out
    assert "I_x = " in out and "±" in out and "converged" in out
    result = json.loads((tmp_path / "gyro_fit.json").read_text())
    fitted, err = np.array(result["inertia"]), np.array(result["inertia_stderr"])
    assert result["normalised_to_trace_1"] is True
    assert np.all(np.abs(fitted - inertia / inertia.sum()) < 4 * err)
    png = (tmp_path / "gyro_fit.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    # A known moment gives absolute values.
    status = run_fit(
        [str(data), "--quiet", "--no-plot", "--known-moment", "z", "2.5", "--out", str(tmp_path / "abs")]
    )
    result = json.loads((tmp_path / "abs.json").read_text())
    assert status == 0 and result["normalised_to_trace_1"] is False
    assert np.all(
        np.abs(np.array(result["inertia"])[:2] - inertia[:2]) < 4 * np.array(result["inertia_stderr"])[:2]
    )


@pytest.mark.slow
def test_a_result_whose_directory_went_away_is_printed_and_rescued(tmp_path, capsys, monkeypatch):
    """The output directory was removed during the fit: the write ended in a raw traceback. The fit
    of test_fit_command_recovers_inertia's second call (same record and options: no new compile)."""
    import tempfile

    inertia, omega0, ts = np.array([1.0, 2.0, 2.5]), np.array([0.3, 0.05, 1.0]), np.linspace(0.0, 40.0, 240)
    w = np.asarray(rj.torque_free_omega(inertia, omega0, ts))
    obs = w + 0.01 * np.std(w, axis=0) * np.random.default_rng(0).standard_normal(w.shape)
    obs[5, 1] = np.nan
    data, outputs = tmp_path / "gyro.csv", tmp_path / "outputs"
    write_csv(data, ts, obs)
    outputs.mkdir()
    rescue = removed_after(monkeypatch, rj, "fit_inertia", outputs)
    options = ["--quiet", "--no-plot", "--known-moment", "z", "2.5", "--out", str(outputs / "abs")]
    assert run_fit([str(data), *options]) == 1
    captured = capsys.readouterr()
    (saved,) = rescue.iterdir()
    assert f"--out '{outputs / 'abs.json'}': could not write" in captured.err
    assert f"written to '{saved}' instead" in captured.err and "Traceback" not in captured.err
    result = json.loads(saved.read_text())
    assert result["normalised_to_trace_1"] is False and "I_x = " in captured.out
    # With the temporary directory gone too, the results are printed (JSON on stdout).
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "missing"))
    outputs.mkdir()
    assert run_fit([str(data), *options]) == 1
    captured = capsys.readouterr()
    assert "nor" in captured.err
    printed = json.loads(captured.out[captured.out.index("{") :])
    assert printed["inertia"] == result["inertia"]


def test_a_directory_as_the_output_stem_is_named(tmp_path, capsys, no_fit):
    """``--out .`` said "--out '..json': the file name must end in .json"."""
    data = tmp_path / "gyro.csv"
    write_csv(data, np.arange(12.0), np.ones((12, 3)))
    for out in (str(tmp_path), str(tmp_path) + "/"):
        assert run_fit([str(data), "-q", "--out", out]) == 2
        _one_line_error(capsys.readouterr(), "is a directory; --out is a file stem")


@pytest.mark.parametrize(
    "text, message",
    [
        ("time,wx,wy,wz\n0,1,2,3\n", "missing column(s) t"),
        ("t,wx,wy\n0,1,2\n", "missing column(s) wz"),
        (
            "t,wx,wy,wz\n" + "".join(f"{t},1,2,3\n" for t in [0, 1, 3, 2, 4, 5, 6, 7, 8, 9, 10]),
            "increase strictly",
        ),
        ("t,wx,wy,wz\n" + "".join(f"{t},1,2,3\n" for t in range(5)), "too few samples"),
        ("t,wx,wy,wz\n", "no data rows"),
        ("t,qw,qx,qy,qz\n0,1,0,0,0\n", "orientation records"),
        # A stray comma shifted the row's later values into the wrong columns, silently; a cell
        # 1_000 was read as 1000; a repeated column name used its first column.
        ("t,wx,wy,wz\n" + "".join(f"{t},1,2,3\n" for t in range(5)) + "5,,1,2,3\n", "has 5 cell(s)"),
        ("t,wx,wy,wz\n" + "".join(f"{t},1_000,2,3\n" for t in range(12)), "'1_000' is not a number"),
        ("t,wx,wy,wz,wx\n" + "".join(f"{t},1,2,3,4\n" for t in range(12)), "column(s) wx more than once"),
    ],
)
def test_malformed_files_are_named(tmp_path, capsys, text, message):
    data = tmp_path / "bad.csv"
    data.write_text(text)
    assert run_fit([str(data), "--quiet"]) == 2
    assert message in capsys.readouterr().err


def test_missing_file(tmp_path, capsys):
    assert run_fit([str(tmp_path / "nope.csv")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert run_fit([str(tmp_path)]) == 2
    assert "a directory, not a CSV file" in capsys.readouterr().err


@pytest.mark.parametrize(
    "content, message",
    [
        (b"t,wx,wy,wz\n0,1,2,3\n1,\xe9,2,3\n", "not a text file in UTF-8 (byte 21"),
        (b"t,wx,wy,wz\n0," + b"1" * 140_000 + b",2,3\n", "not a readable CSV file (field larger"),
    ],
)
def test_unreadable_files_are_one_line(tmp_path, capsys, content, message):
    """A file that is not UTF-8 text, or a cell beyond the csv module's limit, ended in a traceback
    (UnicodeDecodeError, _csv.Error) with exit 1."""
    data = tmp_path / "bad.csv"
    data.write_bytes(content)
    assert run_fit([str(data), "--quiet"]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    "options, message",
    [
        (["--segments", "many"], "--segments must be a positive integer or 'auto', got 'many'"),
        (["--known-moment", "w", "2.5"], "--known-moment needs an axis (x, y, z) and a number"),
    ],
)
def test_bad_options_are_named_on_stderr(tmp_path, capsys, options, message):
    data = tmp_path / "gyro.csv"
    write_csv(data, np.arange(12.0), np.ones((12, 3)))
    assert run_fit([str(data), "--quiet", *options]) == 2
    captured = capsys.readouterr()
    assert message in captured.err and captured.out == ""


@pytest.fixture
def no_fit(monkeypatch):
    """The fit replaced by a failure: a bad option must be reported before any fitting."""

    def fail(*args, **kwargs):
        raise AssertionError("the fit ran instead of rejecting the command line")

    monkeypatch.setattr(rj, "fit_inertia", fail)


def _one_line_error(captured, message):
    assert captured.out == ""
    assert captured.err.count("\n") == 1 and captured.err.startswith("rigidjax fit: error: "), captured.err
    assert message in captured.err and "Traceback" not in captured.err


@pytest.mark.parametrize(
    "options, message",
    [
        (["--trace", "-1"], "--trace must be a positive finite number (kg m^2), got -1.0"),
        (["--trace", "0"], "--trace must be a positive finite number"),
        (["--trace", "nan"], "--trace must be a positive finite number (kg m^2), got nan"),
        (["--trace", "inf"], "--trace must be a positive finite number (kg m^2), got inf"),
        (["--known-moment", "z", "-1"], "--known-moment: the moment must be a positive finite number"),
        (["--known-moment", "z", "nan"], "--known-moment: the moment must be a positive finite number"),
        (["--known-moment", "x", "0"], "--known-moment: the moment must be a positive finite number"),
        (["--known-moment", "5", "1.0"], "--known-moment needs an axis (x, y, z) and a number, got '5'"),
        (["--known-moment", "y", "big"], "--known-moment needs an axis (x, y, z) and a number"),
        (["--trace", "2", "--known-moment", "z", "1"], "at most one scale"),
        (["--segments", "0"], "--segments must be a positive integer or 'auto', got 0"),
        (["--segments", "many"], "--segments must be a positive integer or 'auto', got 'many'"),
    ],
)
def test_bad_scale_options_are_one_line_errors(tmp_path, capsys, no_fit, options, message):
    """--trace -1 and --known-moment z -1 once fitted a negative inertia and exited 0."""
    data = tmp_path / "gyro.csv"
    write_csv(data, np.arange(12.0), np.ones((12, 3)))
    assert run_fit([str(data), "-q", *options]) == 2
    _one_line_error(capsys.readouterr(), message)
    assert not (tmp_path / "gyro_fit.json").exists()


def test_short_quiet_flag_is_accepted(tmp_path, capsys):
    """``-q`` is ``--quiet``, as for ``rigidjax simulate`` (it was an unrecognised argument)."""
    data = tmp_path / "empty.csv"
    data.write_text("t,wx,wy,wz\n")
    assert run_fit([str(data), "-q"]) == 2
    _one_line_error(capsys.readouterr(), "no data rows")


def test_steps_must_be_positive(tmp_path, capsys, no_fit):
    data = tmp_path / "gyro.csv"
    write_csv(data, np.arange(12.0), np.ones((12, 3)))
    assert run_fit([str(data), "-q", "--steps", "0"]) == 2
    assert "argument --steps: must be a positive integer, got 0" in capsys.readouterr().err


def test_infinite_value_is_reported_with_its_row(tmp_path, capsys, no_fit):
    omega = np.ones((12, 3))
    omega[6, 2] = np.inf
    data = tmp_path / "gyro.csv"
    write_csv(data, np.arange(12.0), omega)
    assert run_fit([str(data), "-q"]) == 2
    _one_line_error(capsys.readouterr(), "data row 7 has an infinite wz (inf)")


@pytest.mark.parametrize(
    "out, message",
    [
        ("missing/result", "--out: cannot write"),
        ("missing/result.json", "the directory"),
    ],
)
def test_output_paths_are_checked_before_the_fit(tmp_path, capsys, no_fit, out, message):
    data = tmp_path / "gyro.csv"
    write_csv(data, np.arange(12.0), np.ones((12, 3)))
    assert run_fit([str(data), "-q", "--out", str(tmp_path / out)]) == 2
    captured = capsys.readouterr()
    _one_line_error(captured, message)
    assert "does not exist; create it first" in captured.err


def test_unwritable_directory_is_reported(tmp_path, capsys, no_fit, monkeypatch):
    """(The test runs as any user: the permission answer is replaced, not the file system's.)"""
    import os

    from rigidjax._integrate import storage

    data = tmp_path / "gyro.csv"
    write_csv(data, np.arange(12.0), np.ones((12, 3)))
    monkeypatch.setattr(storage.os, "access", lambda path, mode: False)
    assert run_fit([str(data), "-q"]) == 2
    _one_line_error(capsys.readouterr(), f"the directory {os.fspath(tmp_path)!r} is not writable")


def test_ctrl_c_during_the_fit_exits_130_with_one_line(tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(rj, "fit_inertia", interrupted)
    data = tmp_path / "gyro.csv"
    write_csv(data, np.arange(12.0), np.ones((12, 3)))
    (tmp_path / "gyro_fit.json").write_text("previous result")
    assert run_fit([str(data), "-q"]) == 130
    captured = capsys.readouterr()
    assert captured.err.strip() == "rigidjax fit: interrupted (Ctrl-C); no output file is left half-written."
    assert (tmp_path / "gyro_fit.json").read_text() == "previous result"


def test_text_that_is_not_a_number_is_reported_not_read_as_missing(tmp_path, capsys, no_fit):
    """Empty cells and ``nan`` are missing samples; ``abc`` was read as one too, silently."""
    rows = ["t,wx,wy,wz", "# a comment line", *(f"{t},1,2,3" for t in range(12))]
    rows[5] = "3,,2,nan"  # missing samples: fine
    rows[8] = "6,1,abc,3"
    data = tmp_path / "gyro.csv"
    data.write_text("\n".join(rows) + "\n")
    assert run_fit([str(data), "-q"]) == 2
    _one_line_error(capsys.readouterr(), "data row 7, column wy: 'abc' is not a number")


@pytest.mark.parametrize(
    "out, expected",
    [
        (None, ("gyro_fit.json", "gyro_fit.png")),
        ("res", ("res.json", "res.png")),
        ("res.json", ("res.json", "res.png")),  # a trailing extension is dropped, not doubled
        ("res.png", ("res.json", "res.png")),
    ],
)
def test_output_stem(tmp_path, out, expected):
    import argparse

    from rigidjax._cli.fit import _outputs

    data = str(tmp_path / "gyro.csv")
    args = argparse.Namespace(data=data, out=None if out is None else str(tmp_path / out), no_plot=False)
    assert _outputs(args) == tuple(str(tmp_path / name) for name in expected)
    args.no_plot = True
    assert _outputs(args) == (str(tmp_path / expected[0]), None)


def test_ragged_rows_are_one_line(tmp_path, capsys, no_fit):
    """A row with too few cells is named (its data row and file line) in one line."""
    rows = ["t,wx,wy,wz", *(f"{t},1,2,3" for t in range(12))]
    rows[4] = "3,1"
    data = tmp_path / "gyro.csv"
    data.write_text("\n".join(rows) + "\n")
    assert run_fit([str(data), "-q"]) == 2
    _one_line_error(capsys.readouterr(), "data row 4 (line 5) has 2 cell(s); the header names 4 columns")


def test_spreadsheet_csv_with_quotes_bom_and_crlf_is_read(tmp_path):
    """What spreadsheets and pandas write: a byte-order mark, quoted names and numbers, CRLF line
    ends, extra columns in any order; plus a trailing comment and an empty (missing) cell."""
    from rigidjax._cli.fit import read_record

    lines = [
        '"time_s","wz","t","wx","wy"',
        '"a",3,0,1,2',
        '"b","3.5","0.5","1e-3",""  # note',
        '"c",4,1.0,-1,2',
    ]
    data = tmp_path / "export.csv"
    data.write_bytes(("\ufeff" + "\r\n".join(lines) + "\r\n").encode("utf-8"))
    (tmp_path / "header_only.csv").write_text('"time_s","wz","t","wx","wy"\n')
    with pytest.raises(ValueError, match="no data rows"):
        read_record(str(tmp_path / "header_only.csv"))
    with pytest.raises(ValueError, match=r"too few samples: wy has 2 \(1 of 3 empty or nan\), wx has 3"):
        read_record(str(data))
    lines += [f'"r{k}",{k},{2 + k},1,2' for k in range(10)]
    data.write_bytes(("\ufeff" + "\r\n".join(lines) + "\r\n").encode("utf-8"))
    ts, omega = read_record(str(data))
    np.testing.assert_array_equal(ts, [0.0, 0.5, 1.0, *range(2, 12)])
    expected = np.array([[1, 2, 3], [1e-3, np.nan, 3.5], [-1, 2, 4], *([1, 2, k] for k in range(10))], float)
    np.testing.assert_array_equal(omega, expected)


@pytest.mark.slow
def test_sparse_records_are_fitted(tmp_path, capsys):
    """60 % of the values missing at random, few rows complete: the command refused the record (it
    counted complete rows, where fit_inertia counts values), and then found no start estimate. A
    record whose three gyro axes were observed in turn (no two at once) has none: it is refused
    with the option that gives a start, and fitted from one. Reference: the moments that made the
    records."""
    rng = np.random.default_rng(7)
    inertia, omega0 = np.array([1.0, 2.0, 2.5]), np.array([0.3, 0.1, 2.0])
    ts = np.linspace(0.0, 8.0, 100)
    exact = np.asarray(rj.torque_free_omega(inertia, omega0, ts)) + 1e-3 * rng.standard_normal((100, 3))
    at_random = np.where(rng.random((100, 3)) < 0.6, np.nan, exact)
    in_turn = exact.copy()
    in_turn[34:, 0] = in_turn[:33, 1] = in_turn[67:, 1] = in_turn[:66, 2] = np.nan
    for observed in (at_random, in_turn):
        assert np.isfinite(observed).all(axis=1).sum() < 10 and np.all(
            np.isfinite(observed).sum(axis=0) >= 10
        )
    argv = ["--quiet", "--no-plot", "--method", "levenberg-marquardt", "--out"]

    def fitted(name, *options):
        data = tmp_path / f"{name}.csv"
        write_csv(data, ts, at_random if name == "at_random" else in_turn)
        assert run_fit([str(data), *argv, str(tmp_path / name), *options]) == 0, capsys.readouterr().err
        fit = json.loads((tmp_path / f"{name}.json").read_text())
        # Within four standard errors (the noise makes the fits up to 1.8 of them off here).
        error = np.abs(np.array(fit["inertia"]) - inertia / inertia.sum())
        assert np.all(error < 4 * np.array(fit["inertia_stderr"])), (error, fit["inertia_stderr"])

    fitted("at_random")
    write_csv(tmp_path / "in_turn.csv", ts, in_turn)
    assert run_fit([str(tmp_path / "in_turn.csv"), *argv, str(tmp_path / "x")]) == 2
    assert "Give --inertia-init" in capsys.readouterr().err
    fitted("in_turn", "--inertia-init", "1", "1.5", "2")
    assert (
        run_fit([str(tmp_path / "in_turn.csv"), *argv, str(tmp_path / "x"), "--inertia-init", "1", "0", "2"])
        == 2
    )
    assert "--inertia-init needs three positive finite moments" in capsys.readouterr().err


def test_the_progress_line_says_when_the_fit_starts_again():
    """A fit from the estimated start that ends badly runs again from six other starts, each
    counting from iteration 1: the status line fell back to iteration 1 without a word, and a log
    ended on the last start's count, not the chosen one's."""
    import io

    from rigidjax._cli.fit import _Progress

    stream = io.StringIO()
    progress = _Progress(200, stream, enabled=True)
    for iterations in (range(1, 31), range(1, 9), range(1, 5)):
        for iteration in iterations:
            progress(iteration, 1.0 / iteration)
    progress.close()
    lines = stream.getvalue().splitlines()
    notices = [k for k, line in enumerate(lines) if "fitting again from the moments (2, 3, 4)" in line]
    assert [lines[k].split()[-3] for k in notices] == ["1", "2"] and "of 6" in lines[notices[0]]
    # Each start's last iteration is in the log, before the notice of the next.
    assert "iteration   30 (at most 200)" in lines[notices[0] - 1]
    assert "iteration    8 (at most 200)" in lines[notices[1] - 1]
    assert "iteration    4 (at most 200)" in lines[-1]


def test_fit_program_is_kept_between_invocations(tmp_path):
    """With no cache directory chosen, ``rigidjax fit`` keeps its compiled fit in
    $XDG_CACHE_HOME/rigidjax/jax (the program holds no host callback, which JAX would refuse to
    store); a second run on the same record loads it instead of compiling it, and prints the same fit."""
    ts = np.linspace(0.0, 20.0, 60)
    w = np.asarray(rj.torque_free_omega(np.array([1.0, 2.0, 2.7]), np.array([0.3, 1.0, 0.2]), ts))
    data = tmp_path / "gyro.csv"
    write_csv(data, ts, w + 1e-3 * np.random.default_rng(0).standard_normal(w.shape))
    run = cli_in_fresh_cache(tmp_path, "fit", str(data), "--no-plot", "-q")

    first_out, first_log = run()
    assert "Persistent compilation cache hit for 'jit__run'" not in first_log
    second_out, second_log = run()
    assert "Persistent compilation cache hit for 'jit__run'" in second_log
    strip_time = [line for line in first_out.splitlines() if "including compile" not in line]
    assert strip_time == [line for line in second_out.splitlines() if "including compile" not in line]


def test_a_fit_the_record_does_not_support_is_flagged():
    """The command printed a steady spin's arbitrary moments (infinite standard errors) and a record
    in milliseconds fitted as a near-sphere with tiny errors, both as "converged", without a word;
    its JSON wrote Infinity, which JSON does not have."""
    from rigidjax._cli.common import finite_or_none
    from rigidjax._fit.result import _fit_warnings

    noise = np.array([1e-3, 1e-3, 1e-3])
    moments = np.array([0.2, 0.35, 0.45])
    assert _fit_warnings(np.array([1e-3, 1e-3, 1e-3]), 1.2 * noise, noise, moments) == []
    [undetermined] = _fit_warnings(np.array([np.inf, 1e-3, np.inf]), noise, noise, moments)
    assert "does not determine every moment" in undetermined
    # A flat body (I_z = I_x + I_y) is named as such, not as a record without a wobble.
    [flat] = _fit_warnings(np.array([1e-3, 1e-3, np.inf]), noise, noise, np.array([1.0, 2.0, 3.0]) / 6)
    assert "flat body" in flat and "wobble" not in flat
    [misfit] = _fit_warnings(np.array([1e-7, 1e-7, 1e-7]), np.array([1.0, 1.0, 3.1]) * noise, noise, moments)
    assert "3.1 times the record's noise estimate" in misfit and "time unit" in misfit
    # The command prints the advice in its own options.
    assert "segments='auto'" in misfit and "robust loss" in misfit
    assert "(--segments auto) or with a robust --loss" in in_command_words(misfit)
    text = json.dumps(finite_or_none({"stderr": [0.1, float("inf")], "loss": float("nan")}), allow_nan=False)
    assert json.loads(text) == {"stderr": [0.1, None], "loss": None}


def _rows(make, n=12):
    return "".join(make(t) for t in range(n))


@pytest.mark.parametrize(
    "text, message",
    [
        # A column with no value at all was reported as "too few samples: 0 complete rows".
        ("t,wx,wy,wz\n" + _rows(lambda t: f"{t},1,nan,3\n"), "column wy has no values (all 12 data rows"),
        ("t,wx,wy,wz\n" + _rows(lambda t: f"{t},1,,3\n"), "column wy has no values"),
        ("t,wx,wy,wz\n" + _rows(lambda t: f"{t},,,\n"), "columns wx, wy, wz have no values"),
        ("t,wx,wy,wz\n" + _rows(lambda t: ",1,2,3\n"), "column t has no values (all 12 data rows are empty"),
        # Too few values in some columns: those columns, the fewest first.
        (
            "t,wx,wy,wz\n" + _rows(lambda t: f"{t},1,{'' if t > 2 else 2},{'' if 5 <= t <= 9 else 3}\n"),
            "too few samples: wy has 3 (9 of 12 empty or nan), wz has 7 (5 of 12 empty or nan). A fit "
            "needs at least 10 values of each of wx, wy, wz (a row may miss some)",
        ),
        # An empty file, or one of comments only, was "missing column(s) t, wx, wy, wz".
        ("", "the file is empty; a record needs a header row naming t, wx, wy, wz"),
        ("\n# no samples yet\n", "no header row, only blank or comment lines"),
        # Columns separated by something else than commas were "missing column(s) t, wx, wy, wz".
        ("t;wx;wy;wz\n" + _rows(lambda t: f"{t};1,5;2;3\n"), "the columns are separated by semicolons (;)"),
        ("t\twx\twy\twz\n" + _rows(lambda t: f"{t}\t1\t2\t3\n"), "the columns are separated by tabs"),
        ("t wx wy wz\n" + _rows(lambda t: f"{t} 1 2 3\n"), "the columns are separated by spaces"),
        # numpy.savetxt(..., header="t,wx,wy,wz") comments the header out.
        (
            "# t,wx,wy,wz\n" + _rows(lambda t: f"{t},1,2,3\n"),
            "the header row is commented out ('# t,wx,wy,wz')",
        ),
    ],
    ids=[
        "wy-nan",
        "wy-empty",
        "wx-wy-wz-empty",
        "t-empty",
        "few-values",
        "empty-file",
        "comments-only",
        "semicolons",
        "tabs",
        "spaces",
        "commented-header",
    ],
)
def test_unusable_columns_are_named(tmp_path, capsys, no_fit, text, message):
    data = tmp_path / "gyro.csv"
    data.write_text(text)
    assert run_fit([str(data), "-q"]) == 2
    _one_line_error(capsys.readouterr(), f"{data}: {message}")


def test_comment_lines_before_the_header_and_after_its_names_are_skipped(tmp_path):
    """Comment and blank lines are skipped, as the docstring says: also above the header (the
    comment was read as the header: "missing column(s) t, wx, wy, wz") and after the column names
    (read as part of the name wz). The file's line numbers count the lines above the header."""
    from rigidjax._cli.fit import read_record

    data = tmp_path / "gyro.csv"
    data.write_text("# gyro, 100 Hz\n\nt,wx,wy,wz  # rad/s\n" + _rows(lambda t: f"{t},1,2,3\n"))
    ts, omega = read_record(str(data))
    np.testing.assert_array_equal(ts, np.arange(12.0))
    np.testing.assert_array_equal(omega, np.tile([1.0, 2.0, 3.0], (12, 1)))
    data.write_text("# gyro\nt,wx,wy,wz\n0,1,2,3\n1,1\n")
    with pytest.raises(ValueError, match=r"data row 2 \(line 4\) has 2 cell\(s\)"):
        read_record(str(data))
