"""Test configuration: float64 and strict dtype promotion for every test, and JAX's persistent
compilation cache.

Float32 tests opt in explicitly by building float32 inputs; with strict promotion an accidental
float32/float64 mix is an error rather than a silent upcast.

Compiling is most of the suite's time on a CPU, so every compiled program is kept on disk, in
``.jax_cache/`` at the repository root or in ``$JAX_COMPILATION_CACHE_DIR``: a second run of a file
loads its programs instead of compiling them. The cache is keyed on the program, the jax/jaxlib
versions and the XLA flags, so a changed function simply compiles again; delete the directory to
reclaim the space. The settings are exported to the environment too, so that the notebooks' kernels
and other subprocesses started by the tests share the cache.
"""

import os
import pathlib
import re
import sys

import jax
import jaxtyping
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

_CACHE_SETTINGS = {  # environment variable: (default, type)
    "JAX_COMPILATION_CACHE_DIR": (str(pathlib.Path(__file__).resolve().parent.parent / ".jax_cache"), str),
    # Keep every program, however quick to compile or small: the suite compiles thousands of small
    # ones (eager op-by-op dispatch), and together they are most of a run's compile time.
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": ("0", float),
    "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": ("-1", int),
}
for _name, (_default, _type) in _CACHE_SETTINGS.items():
    os.environ.setdefault(_name, _default)  # an exported setting wins
    jax.config.update(_name.lower(), _type(os.environ[_name]))

# LLVM at -O1 compiles the suite's programs faster than XLA:CPU's default optimisation level; the
# generated code computes the same functions with the same fusions and multiply-add contractions, so
# what the tests check is the code users get.
# RIGIDJAX_TEST_XLA_DEFAULTS=1 runs the suite with XLA's defaults. (XLA's older, non-MLIR fusion
# emitters, --xla_cpu_use_fusion_emitters=false, compile most programs faster still but the closed form
# about 20x slower, and they never contract multiply-adds, which hid an inconsistency that only fused
# multiply-adds expose.) Set here, before JAX creates its CPU backend, and exported, so the notebooks'
# kernels and CLI subprocesses compile the same way.
TEST_XLA_FLAGS = "--xla_backend_optimization_level=1"
_flags = os.environ.get("XLA_FLAGS", "")
if os.environ.get("RIGIDJAX_TEST_XLA_DEFAULTS", "0") != "1" and TEST_XLA_FLAGS not in _flags:
    os.environ["XLA_FLAGS"] = f"{_flags} {TEST_XLA_FLAGS}".strip()


# A worker that holds more than this drops its compiled programs after a test file.
RELEASE_ABOVE_BYTES = 3 * 2**30


def _resident_bytes() -> int | None:
    """This process's resident memory, where the system tells it (Linux); None elsewhere."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drops every compiled program and open figure after a test file once the worker holds more
    than ``RELEASE_ABOVE_BYTES``. A worker runs many files, and keeping every program it ever
    compiled grew one past 8 GiB (two such workers, the notebooks' kernels and a large compile
    exhausted the 24 GiB of a CI machine: XLA aborted). Below the limit the programs stay: files
    that call the same functions with the same shapes (the presets on a free body, the checks, the
    many small programs of eager operations) then neither trace nor load them again. A program a
    later file needs after a release is loaded from the persistent cache instead of compiled."""
    yield
    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")
    resident = _resident_bytes()
    if resident is None or resident > RELEASE_ABOVE_BYTES:
        jax.clear_caches()


@pytest.fixture
def without_runtime_typecheck():
    """The test run checks annotations with jaxtyping first; turn that off to see rigidjax's own checks."""
    old = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", old)


# --- where the suite's time goes ----------------------------------------------------------------
# RIGIDJAX_TEST_COMPILE_REPORT=path appends one JSON line per test to path: its wall time and the
# seconds JAX spent in it tracing, lowering and compiling (XLA), with the number of compiles (a
# program loaded from the persistent cache is not compiled). Compiling is most of a cold run.
_JAX_SECONDS: dict[str, float] = {}
_JAX_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}


def _count_jax_seconds(event: str, duration: float, **_) -> None:
    if event in _JAX_EVENTS:
        key = _JAX_EVENTS[event]
        _JAX_SECONDS[key] = _JAX_SECONDS.get(key, 0.0) + duration
        if key == "compile":
            _JAX_SECONDS["compiles"] = _JAX_SECONDS.get("compiles", 0) + 1


# RIGIDJAX_TEST_PROGRAM_REPORT=path appends one JSON line per program that XLA compiled or loaded
# from the persistent cache: the test, the program's name, the compile seconds, whether it holds host
# callbacks (such a program is never written to the persistent cache, so every process and every run
# compiles it again) and the end of its cache key (the same key twice: the same program twice). It
# wraps two private functions of jax._src.compiler, so it is a diagnostic for this jax version only.
_CURRENT_TEST = {"nodeid": None}


def _report_programs(path: str) -> None:
    import json

    from jax._src import compiler

    write, read = compiler._cache_write, compiler._cache_read

    def record(**fields):
        with open(path, "a") as f:
            f.write(json.dumps({"test": _CURRENT_TEST["nodeid"], "pid": os.getpid(), **fields}) + "\n")

    def cache_write(cache_key, compile_time_secs, module_name, backend, executable, host_callbacks):
        record(event="compiled", program=module_name, seconds=compile_time_secs,
               host_callbacks=len(host_callbacks), key=cache_key[-16:])  # fmt: skip
        return write(cache_key, compile_time_secs, module_name, backend, executable, host_callbacks)

    def cache_read(module_name, cache_key, *args, **kwargs):
        executable, seconds = read(module_name, cache_key, *args, **kwargs)
        if executable is not None:
            record(event="loaded", program=module_name, key=cache_key[-16:])
        return executable, seconds

    compiler._cache_write, compiler._cache_read = cache_write, cache_read


if os.environ.get("RIGIDJAX_TEST_PROGRAM_REPORT"):
    _report_programs(os.environ["RIGIDJAX_TEST_PROGRAM_REPORT"])

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_setup(item):
        _CURRENT_TEST["nodeid"] = item.nodeid  # the setup's fixtures compile for the test too
        yield


if os.environ.get("RIGIDJAX_TEST_COMPILE_REPORT"):
    jax.monitoring.register_event_duration_secs_listener(_count_jax_seconds)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        import json
        import time

        _JAX_SECONDS.clear()
        start = time.perf_counter()
        yield
        record = {"test": item.nodeid, "wall": time.perf_counter() - start}
        record.update({key: _JAX_SECONDS.get(key, 0) for key in ("trace", "lower", "compile", "compiles")})
        with open(os.environ["RIGIDJAX_TEST_COMPILE_REPORT"], "a") as f:
            f.write(json.dumps(record) + "\n")


# --- the published table of extremes -------------------------------------------------------------
# Tests in the files listed in benchmarks/extremes_table.py (gimbal lock, bad input, extreme bodies,
# long horizons) call `extreme(...)` with what they measured. The assertion in the test is the
# check; the record is what `python benchmarks/extremes_table.py` turns into the table of docs/extremes.md (it
# runs those tests with RIGIDJAX_EXTREMES_REPORT set to a JSON path).
_EXTREME_ROWS: list[dict] = []


@pytest.fixture
def extreme(request):
    """Record one row of the extremes table: ``extreme(area, case, behaviour, measured, bound, advice)``.

    ``measured`` and ``bound`` are floats (or None for a pure behaviour row such as "raises");
    the test itself must assert ``measured <= bound``; the row only documents the number.
    """

    def record(area, case, behaviour, measured=None, bound=None, advice=""):
        _EXTREME_ROWS.append(
            {
                "test": request.node.nodeid,
                "area": area,
                "case": case,
                "behaviour": behaviour,
                "measured": None if measured is None else float(measured),
                "bound": None if bound is None else float(bound),
                "advice": advice,
            }
        )

    return record


def pytest_sessionfinish(session, exitstatus):
    import json
    import os

    path = os.environ.get("RIGIDJAX_EXTREMES_REPORT")
    if path and _EXTREME_ROWS:
        with open(path, "w") as f:
            json.dump(_EXTREME_ROWS, f, indent=1)


# Seconds each of the longest units of work took (one cold run on 2 cores): a unit is a test file,
# except that each notebook's run and each page's examples are units of their own (see the scheduler
# below). The workers take
# the units longest first, which keeps one of them from running alone at the end; the rest follow
# in collection order.
_UNIT_SECONDS = {
    "test_heavy_top_exact": 207,
    "test_fit": 175,
    "test_torque_free": 172,
    "test_simulate": 163,
    "test_bad_input": 160,
    "test_long_horizons": 75,
    "test_forward_mode": 59,
    "test_bad_input_sweep": 57,
    "test_gyrostat": 57,
    "docs/guides/fitting.md": 70,
    "06_speed_vs_accuracy.ipynb": 56,
    "docs/guides/plotting.md": 45,
    "test_progress": 53,
    "test_kinematics": 52,
    "test_unrolled_dopri8": 49,
    "test_gimbal_lock": 46,
    "test_faults": 42,
    "test_cpu_cores": 40,
    "test_elliptic": 38,
    "test_cli": 38,
    "05_fit_inertia.ipynb": 37,
    "test_error_estimate": 34,
    "test_lie_group": 33,
    "test_extreme_bodies": 30,
    "test_splitting": 26,
    "04_heavy_top.ipynb": 25,
    "docs/guides/scenes.md": 23,
}


def _own_unit(nodeid: str) -> str | None:
    """The notebook or documentation page a ``test_notebook_runs`` or ``test_examples_run`` item
    executes, or None for any other test."""
    match = re.fullmatch(
        r"[^:]*(?:test_notebooks\.py::test_notebook_runs|test_doc_examples\.py::test_examples_run)"
        r"\[(.+)\]",
        nodeid,
    )
    return match.group(1) if match else None


def pytest_collection_modifyitems(config, items):
    """Under the scheduler below each test file runs on one worker, so module-level compiled
    functions and fixtures are compiled once; the longest units go first."""

    def rank(item):
        return -_UNIT_SECONDS.get(_own_unit(item.nodeid) or item.path.stem, 0)

    items.sort(key=rank)  # stable: the order within each file and among the others is kept


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """Whole test files to each worker (pytest-xdist's ``loadfile``), except that each notebook's
    run and each documentation page's examples are units of their own: they run in their own
    processes and share no compiled program with their file, and the notebooks together take longer
    than any test file, so running them one after another on one worker left the other idle at the
    end. Units are handed out in collection order
    (``--no-loadscope-reorder``)."""
    if config.getvalue("dist") != "loadfile":
        return None  # an explicit other --dist keeps pytest-xdist's own scheduler
    from xdist.scheduler import LoadFileScheduling

    class FilesAndNotebooks(LoadFileScheduling):
        def _split_scope(self, nodeid):
            unit = _own_unit(nodeid)
            return nodeid if unit else super()._split_scope(nodeid)

    return FilesAndNotebooks(config, log)
