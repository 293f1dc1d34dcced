"""The benchmark harness (``benchmarks/_harness.py``) and the work-precision script's reports.

The scripts run as ``python benchmarks/<name>.py``, with ``benchmarks/`` on ``sys.path``; the tests
put it there too.
"""

import ast
import sys
import warnings
from pathlib import Path

import pytest

import rigidjax as rj

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import _harness as H  # noqa: E402
import work_precision as wp  # noqa: E402


def _rj_attributes(path):
    """Every ``rj.<name>`` and ``rj.<namespace>.<name>`` a script uses, as dotted strings."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "rj":
            out.add(node.attr)
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Attribute)
            and isinstance(node.value.value, ast.Name)
            and node.value.value.id == "rj"
        ):
            out.add(f"{node.value.attr}.{node.attr}")
    return out


def test_harness_imports_rigidjax_through_public_names_only():
    tree = ast.parse((BENCHMARKS / "_harness.py").read_text(encoding="utf-8"))
    imported = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported += [a.name for a in node.names]
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0, "a relative import"
            imported += [f"{node.module}.{a.name}" for a in node.names]
    ours = [name for name in imported if name.split(".")[0] == "rigidjax"]
    assert ours == ["rigidjax"]  # `import rigidjax as rj`, nothing else
    assert all(not name.startswith("_") for name in _rj_attributes(BENCHMARKS / "_harness.py"))


@pytest.mark.parametrize(
    "script", sorted(p.name for p in BENCHMARKS.glob("*.py") if p.name != "extremes_table.py"), ids=str
)
def test_benchmarks_use_current_public_names(script):
    """No private ``rj._x`` and no top-level name that has moved (those warn)."""
    for name in sorted(_rj_attributes(BENCHMARKS / script)):
        assert not any(part.startswith("_") for part in name.split(".")), name
        with warnings.catch_warnings():
            warnings.simplefilter("error", DeprecationWarning)
            obj = rj
            for part in name.split("."):
                obj = getattr(obj, part)


def test_time_at_error_interpolates_on_the_pareto_front():
    # A fourth-order method: time ~ error^(-1/4). A dominated point (slower and less accurate) is ignored.
    errs = [1e-4, 1e-6, 1e-8]
    rows = [{"max_rel_omega": e, "run_s": e**-0.25} for e in errs] + [{"max_rel_omega": 1e-5, "run_s": 1e3}]
    t, extrapolated = H.time_at_error(rows, 1e-7)
    assert t == pytest.approx(1e-7**-0.25) and not extrapolated
    assert H.time_at_error(rows, 1e-2) == (rows[0]["run_s"], False)  # no extrapolation to cheaper
    assert H.time_at_error(rows, 1e-10) == (None, False)
    t, extrapolated = H.time_at_error(rows, 1e-10, extrapolate=True)
    assert t == pytest.approx(1e-10**-0.25) and extrapolated


def test_run_methods_refuses_a_row_computed_in_another_dtype():
    """A method declared float32 whose output comes back float64 (diffrax promotes a float32 state
    under float64 times) stops the run instead of landing in the float32 rows."""
    scene = H.reference_scene(4)
    omega, q = scene[1], scene[2]  # float64 numpy arrays

    promoted = H.Method("peer", "rtol=1e-6", lambda: (omega, q), "g", dtype="float32", kind="peer")
    with pytest.raises(RuntimeError, match="computed in float64, declared float32"):
        H.run_methods([promoted], scene, (omega, q), repeats=0)
    honest = H.Method("peer", "rtol=1e-6", lambda: (omega, q), "g", dtype="float64", kind="peer")
    (row,) = H.run_methods([honest], scene, (omega, q), repeats=0)
    assert row["max_rel_omega"] == 0.0 and row["dtype"] == "float64"


@pytest.mark.slow
def test_small_run_closed_form_and_hand_rk4():
    """Closed form and hand RK4 on 8 bodies against the extended-precision reference: the rows,
    the table and the targets, and the physics in them."""
    scene = H.reference_scene(8)
    omega_ref, q_ref, checked, info = H.refined_reference(scene, 8, 0)
    assert info["checked_bodies"] == 8  # every body's reference redone in extended precision
    # The float64 closed form agrees with the 80-bit Taylor integration to near roundoff.
    assert info["closed_form_vs_taylor_max_rel_omega"] < 1e-11
    assert info["closed_form_vs_taylor_max_angle"] < 1e-11
    methods = H.standard_methods(scene, "quick", include=["exact", "rk4"])
    calls = []
    rows = H.run_methods(
        methods,
        scene,
        (omega_ref, q_ref),
        repeats=1,
        progress=lambda what, done, total: calls.append((done, total)),
        checked=checked,
        first_calls={"exact": info["closed_form_first_call_s"]},
    )
    # 5 methods (closed form with and without q, RK4 at 3 steps) x (first call + 1 repeat)
    assert calls[-1] == (10, 10)
    by_key = {(r["family"], r["setting"]): r for r in rows}
    exact = by_key[("simulate 'exact' (closed form)", "-")]
    assert exact["errors_on"] == "8 checked bodies" and exact["max_rel_omega"] < 1e-11
    rk4 = [by_key[("hand RK4 (7,N)", f"dt={dt}")] for dt in ("0.02", "0.01", "0.005")]
    # Fourth order: halving the step divides the error by ~16 (omega and orientation).
    for coarse, fine in zip(rk4, rk4[1:], strict=False):
        assert 8 < coarse["max_rel_omega"] / fine["max_rel_omega"] < 32
        assert 8 < coarse["max_angle"] / fine["max_angle"] < 32
        assert 8 < coarse["max_energy"] / fine["max_energy"] < 32
    assert rk4[0]["new_compile"] and not rk4[1]["new_compile"]  # one program for every step
    assert all(r["run_s"] > 0 and len(r["run_s_all"]) == 1 for r in rows)
    # The table carries the numbers of the rows.
    table = H.format_table(rows)
    line = next(x for x in table.splitlines() if x.startswith("| hand RK4 (7,N) | dt=0.01 |"))
    assert float(line.split("|")[6]) == pytest.approx(rk4[1]["max_rel_omega"], rel=0.06)
    # The closed-form target is evaluated (met or not) against the fastest integrator reaching 1e-9 in
    # omega and orientation, or where none does the most accurate one.
    targets = H.evaluate_targets(rows)
    target = next(t for t in targets if t["target"].startswith("exact"))
    error = {id(r): max(r["max_rel_omega"], r["max_angle"]) for r in rk4}
    reaching = [r for r in rk4 if error[id(r)] <= 1e-9]
    basis = min(reaching, key=lambda r: r["run_s"]) if reaching else min(rk4, key=lambda r: error[id(r)])
    assert target["value"] == pytest.approx(basis["run_s"] / exact["run_s"])
    assert target["target"] in H.format_targets(targets)


def test_work_precision_readme_section_lists_the_key_rows_and_targets(tmp_path):
    """benchmarks/work_precision.py rewrites the README table between its markers from the results."""

    def row(family, setting, dtype, run_s, err, compile_s=None, scale=1.0):
        return dict(
            family=family,
            setting=setting,
            dtype=dtype,
            run_s=run_s,
            compile_s=compile_s,
            time_scale=scale,
            max_rel_omega=err,
            median_rel_omega=err / 10,
            max_angle=None,
        )

    rows = [
        row("simulate 'balanced'", "preset", "float64", 0.5, 4e-9, compile_s=3.0),
        row("simulate 'balanced'", "preset", "float32", 0.2, 1.7),
        row("scipy solve_ivp DOP853 per body", "rtol=1e-10", "float64", 120.0, 1.6e-8, scale=500.0),
    ]
    targets = [{"target": "balanced >= 10x vmapped diffrax at <= 1e-06", "met": False, "text": "3.1x"}]
    meta = dict(
        command="python benchmarks/work_precision.py",
        devices=["cpu:0"],
        cpu_count=2,
        jax="0",
        repeats=3,
        loadavg_start=[1.0],
        loadavg_end=[1.0],
    )
    text = wp.readme_section(meta, rows, targets)
    assert '| `simulate` "balanced" | 0.5 | 3.0 | 4.0e-09 | 4.0e-10 | - |' in text
    assert '| float32 `simulate` "balanced" | 0.2 | (shared) | 1.7e+00 |' in text
    assert "| 120 ¹ |" in text and "¹ run on a subset" in text
    assert "- **not met** — balanced >= 10x vmapped diffrax at <= 1e-06: 3.1x" in text
    readme = tmp_path / "README.md"
    start, end = wp.README_MARKERS
    readme.write_text(f"head\n{start}\nold\n{end}\ntail\n")
    wp.update_readme(meta, rows, targets, path=readme)
    new = readme.read_text()
    assert new.startswith(f"head\n{start}\n") and new.endswith(f"{end}\ntail\n") and "old" not in new


def test_a_round_of_a_quick_method_is_the_median_of_calls_over_a_fifth_of_a_second(monkeypatch):
    """The call times are given (no clock): a 10 ms call is repeated until 0.2 s (20 calls), a
    1 ms call stops at 51 calls, a 60 ms call is timed once."""
    for seconds, expected_calls in ((0.01, 20), (0.001, 51), (0.06, 1)):
        calls = []
        monkeypatch.setattr(H, "_call", lambda fn, s=seconds, log=calls: (log.append(1), s))
        assert H._round_time(lambda: None) == seconds
        assert len(calls) == expected_calls


def test_peer_program_samples_the_motion_at_every_time():
    """The user-written peer sampled at given times (``peer_program(ts)``, ``sample_cost.py``'s) returns
    the motion at every sample time, bodies first: against scipy's DOP853 at rtol 1e-12 on three
    bodies of the scene, its errors are those of its tolerance; and ``sample_cost.py``'s error
    measure is the largest over bodies and samples."""
    import numpy as np
    import sample_cost
    from scipy.integrate import solve_ivp

    inertia, omega0, q0 = H.reference_scene(3)
    ts = np.linspace(0.0, 2.0, 5)
    ys = np.asarray(H.peer_program(ts)(inertia, np.concatenate([omega0, q0], -1), 1e-8, 1e-8))
    assert ys.shape == (3, 5, 7)
    omega, q = ys[..., :3], ys[..., 3:]

    reference = np.stack([
        solve_ivp(wp._euler_rhs(inertia[b]), (0.0, 2.0), np.concatenate([omega0[b], q0[b]]),
                  method="DOP853", t_eval=ts, rtol=1e-12, atol=1e-12).y.T
        for b in range(3)
    ])  # fmt: skip
    rel, angle = sample_cost.errors((omega, q), (reference[..., :3], reference[..., 3:]))
    assert 1e-12 < rel < 1e-6 and angle < 1e-6
    # One sample of one body moved by 1e-3: the measure finds it.
    moved = omega.copy()
    moved[1, 3] *= 1.001
    assert sample_cost.errors((moved, q), (reference[..., :3], reference[..., 3:]))[0] == pytest.approx(
        1e-3, rel=1e-2
    )


@pytest.mark.parametrize(
    "script, argv, message",
    [
        ("work_precision", ["--only", "bogus"], "argument --only: unknown bogus; choose from fast,"),
        ("work_precision", ["--only", ","], "argument --only: no name given"),
        ("work_precision", ["--n", "0"], "argument --n: must be a positive integer, got 0"),
        ("work_precision", ["--repeats", "0"], "argument --repeats: must be a positive integer, got 0"),
        ("gradient_cost", ["--accuracies", "bogus"], "argument --accuracies: unknown bogus"),
        ("gradient_cost", ["--n", "0"], "argument --n: must be a positive integer, got 0"),
        ("preset_drift", ["--periods", "0"], "argument --periods: must be a positive number, got 0"),
    ],
)
def test_bad_options_are_one_line_usage_errors(script, argv, message, capsys):
    """They ended in tracebacks from deep in a run ("the batch of bodies is empty", "ts must be
    strictly increasing"), --only refused scipy and mujoco although its help offered them, and
    --repeats 0 reported the compiling first call as the median run time."""
    import importlib

    with pytest.raises(SystemExit) as exit_info:
        importlib.import_module(script).main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and message in err and "Traceback" not in err
