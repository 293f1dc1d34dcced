"""Progress reporting of long runs: ``simulate(..., progress=...)`` and ``fit_inertia(..., progress=...)``.

Progress must report and change nothing: the trajectories and fits are compared bit for bit with
the runs without it. The scenes are tiny (six bodies in chunks of two: three chunks, three reports)
so that the file compiles little."""

import re
import threading
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dop853_free_body

import rigidjax as rj

TS = jnp.linspace(0.0, 2.0, 5)
N = 6


def _scene():
    rng = np.random.default_rng(0)
    inertia = rng.uniform(2.0, 3.0, (N, 3))  # moments obey the triangle inequality
    omega = rng.normal(size=(N, 3)) * rng.uniform(0.5, 3.0, (N, 1))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (N, 1))
    return rj.FreeBody(jnp.asarray(inertia)), rj.State(jnp.asarray(omega), orientation=jnp.asarray(q))


def _nan_when_fast(t, s, a):
    """NaN after t = 1 for a body spinning faster than 3 rad/s about its first axis, else zero."""
    return jnp.where((t > 1.0) & (s.omega[0] > 3.0), jnp.nan, 0.0) * jnp.ones(3)


def _faulty_scene():
    """Six bodies whose fourth gets a NaN torque after t = 1 (its chunk stops there)."""
    omega0 = np.tile([1.0, 0.2, 0.3], (N, 1))
    omega0[3, 0] = 5.0
    torque = rj.Torque(_nan_when_fast, needs_orientation=False)
    model = rj.RigidBody(jnp.asarray(np.tile([1.0, 2.0, 3.0], (N, 1))), torque)
    return model, rj.State(jnp.asarray(omega0))


def _assert_same(a, b):
    for name in ("omega", "orientation", "success"):
        np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)))
    assert a.stats.keys() == b.stats.keys()
    for name, value in a.stats.items():
        np.testing.assert_array_equal(np.asarray(value), np.asarray(b.stats[name]), err_msg=name)


def test_progress_callable_counts_and_same_result():
    model, state0 = _scene()
    plain = rj.simulate(model, state0, TS, chunk_size=2)
    calls = []
    traj = rj.simulate(
        model, state0, TS, chunk_size=2, progress=lambda done, total: calls.append((done, total))
    )
    assert calls == [(0, N), (2, N), (4, N), (6, N)]
    _assert_same(plain, traj)


def test_progress_bar_text(capfd):
    model, state0 = _scene()
    rj.simulate(model, state0, TS, chunk_size=2, progress=True)
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("simulate [")]
    assert len(lines) == 4, err
    assert re.fullmatch(r"simulate \[\.{30}\] 0/6 bodies, \d+\.\d s", lines[0])
    assert re.fullmatch(r"simulate \[#{10}\.{20}\] 2/6 bodies, \d+\.\d s", lines[1])
    # From the second block on, an estimate from the blocks after the first (which compiles).
    assert re.fullmatch(r"simulate \[#{20}\.{10}\] 4/6 bodies, \d+\.\d s, ~\d+\.\d s left", lines[2])
    assert re.fullmatch(r"simulate \[#{30}\] 6/6 bodies, \d+\.\d s", lines[3])


def test_progress_with_error_estimate_is_one_report_over_both_solves(capfd):
    """The estimate's second solve continues the same report: totals are twice the bodies, the
    count never goes back nor repeats (the second solve's start was reported again as (6, 12)), and
    the bar ends once."""
    model, state0 = _scene()
    plain = rj.simulate(model, state0, TS, chunk_size=2, error_estimate=True)
    calls = []
    traj = rj.simulate(
        model, state0, TS, chunk_size=2, error_estimate=True, progress=lambda d, t: calls.append((d, t))
    )
    assert calls == [
        (0, 2 * N),
        (2, 2 * N),
        (4, 2 * N),
        (6, 2 * N),
        (8, 2 * N),
        (10, 2 * N),
        (12, 2 * N),
    ]
    _assert_same(plain, traj)
    rj.simulate(model, state0, TS, chunk_size=2, error_estimate=True, progress=True)
    lines = [line for line in capfd.readouterr().err.splitlines() if line.startswith("simulate [")]
    assert len(lines) == 7 and all("/12 body solves (2 per body: result, error estimate)" in x for x in lines)
    assert lines[-1].startswith(f"simulate [{'#' * 30}] 12/12") and not any("12/12" in x for x in lines[:-1])


def test_progress_starts_at_zero_and_ends_at_the_total_in_one_program_too():
    """The closed form and a batch of one chunk run as one program: they reported only the total
    (a progress bar stayed blank until the run had ended); now 0 first, as documented."""
    model, state0 = _scene()
    for options in (dict(accuracy="exact"), dict(chunk_size=N), dict(chunk_size=N, error_estimate=True)):
        calls = []
        rj.simulate(model, state0, TS, progress=lambda d, t, calls=calls: calls.append((d, t)), **options)
        total = 2 * N if options.get("error_estimate") else N
        assert calls == ([(0, total), (N, total), (total, total)] if total > N else [(0, N), (N, N)])


@pytest.mark.parametrize("bad", ["yes", 1, 0.5])
def test_progress_bad_value(bad, without_runtime_typecheck):
    model, state0 = _scene()
    with pytest.raises(TypeError, match=r"progress must be True .*, False, or a callable"):
        rj.simulate(model, state0, TS, progress=bad)


def test_progress_under_jit_is_a_clear_error():
    model, state0 = _scene()

    @jax.jit
    def final(omega):
        return rj.simulate(model, rj.State(omega, state0.orientation), TS, chunk_size=2, progress=True).omega

    with pytest.raises(ValueError, match=r"progress .*jax\.jit.*progress=False"):
        final(state0.omega)


def _record():
    inertia, omega0 = np.array([1.0, 2.0, 2.5]), np.array([0.3, 0.05, 1.0])
    ts = np.linspace(0.0, 4.0 * float(rj.torque_free_period(inertia, omega0)), 60)
    omega, _ = dop853_free_body(inertia, omega0, ts)  # scipy: no program to compile for the data
    return ts, omega + 1e-3 * np.random.default_rng(1).standard_normal(omega.shape)


def test_fit_progress_lines_and_callable(capsys):
    ts, omega = _record()
    plain = rj.fit_inertia(ts, omega, method="levenberg-marquardt")
    printed = rj.fit_inertia(ts, omega, method="levenberg-marquardt", progress=True)
    err = capsys.readouterr().err.splitlines()
    iterations = [line for line in err if line.startswith("fit: iteration")]
    assert len(iterations) == min(plain.num_steps, 10)
    assert re.fullmatch(r"fit: iteration 1, loss \d\.\d{6}e[+-]\d\d, step \d\.\d{3}e[+-]\d\d", iterations[0])
    assert re.fullmatch(rf"fit: {plain.num_steps} iterations, loss \S+, converged", err[-1])
    seen = []
    called = rj.fit_inertia(
        ts, omega, method="levenberg-marquardt", progress=lambda i, loss: seen.append((i, loss))
    )
    assert [i for i, _ in seen] == list(range(1, plain.num_steps + 1))
    assert all(isinstance(loss, float) for _, loss in seen)
    # A fit that reports is a different compiled program (a host call per iteration), and XLA may
    # fuse it differently: the same iterations, equal up to a few units of roundoff.
    for fit in (printed, called):
        np.testing.assert_allclose(np.asarray(fit.inertia), np.asarray(plain.inertia), rtol=1e-13, atol=0)
        np.testing.assert_allclose(np.asarray(fit.history), np.asarray(plain.history), rtol=1e-12, atol=0)
        assert fit.num_steps == plain.num_steps


@pytest.mark.parametrize("fit", [rj.fit_inertia, rj.fit_inertia_to_orientation])
def test_fit_progress_bad_value(fit, without_runtime_typecheck):
    ts = np.linspace(0.0, 1.0, 20)
    data = np.tile([0.3, 0.05, 1.0], (20, 1)) if fit is rj.fit_inertia else np.tile([1.0, 0, 0, 0], (20, 1))
    with pytest.raises(TypeError, match=r"progress must be True .*, False, or a callable"):
        fit(ts, data, progress="verbose")


@pytest.fixture
def threads(monkeypatch):
    """Sets the number of threads ``simulate`` runs its blocks from (``progress.host_threads``)."""
    from rigidjax._integrate import progress

    def use(count):
        monkeypatch.setattr(progress, "host_threads", lambda *args: count)

    return use


def test_threads_give_the_one_program_trajectories(threads):
    """Reference: the same batch as one compiled call. Run from one thread per block (three blocks of
    one chunk each, three threads, whatever the cores), the trajectories and every statistic are the
    same to the bit: each chunk holds the same bodies and takes the same steps. The threads share
    one compiled program (their blocks are of one size): it is traced, and so compiled, once."""
    from rigidjax._integrate.chunked import _integrate_traced

    model, state0 = _scene()
    threads(1)
    one_program = rj.simulate(model, state0, TS, chunk_size=2)
    threads(3)
    jax.clear_caches()  # so that the call below traces its program, whatever ran before in this process
    traces = eqx.debug.get_num_traces(_integrate_traced)
    _assert_same(one_program, rj.simulate(model, state0, TS, chunk_size=2))
    assert eqx.debug.get_num_traces(_integrate_traced) == traces + 1
    threads(2)  # two threads, three blocks: one thread runs two
    _assert_same(one_program, rj.simulate(model, state0, TS, chunk_size=2))


def test_threads_report_each_block_when_it_finishes(threads, monkeypatch):
    """The first block holds the fastest bodies (the most steps); reports in block order left the
    bar at 0 while the other threads finished the rest. Here the first block waits (up to 20 s)
    until some report counts bodies: it must come from the blocks behind it. The trajectories are
    the one-program run's, to the bit."""
    from rigidjax._integrate import progress

    model, state0 = _scene()
    threads(1)
    one_program = rj.simulate(model, state0, TS, chunk_size=2)
    fastest = state0.omega[int(np.argmax(np.linalg.norm(np.asarray(state0.omega), axis=-1)))]
    reported = threading.Event()
    waited = []
    run_in_blocks = progress.run_in_blocks

    def first_block_waits(run, *rest):
        def run_block(model, omega0, q0, chunk_size, sort):
            out = run(model, omega0, q0, chunk_size, sort)
            if bool(jnp.any(jnp.all(omega0 == fastest, axis=-1))):
                waited.append(reported.wait(timeout=20.0))
            return out

        return run_in_blocks(run_block, *rest)

    monkeypatch.setattr(progress, "run_in_blocks", first_block_waits)
    threads(2)
    calls = []

    def report(done, total):
        calls.append(done)
        if done > 0:
            reported.set()

    traj = rj.simulate(model, state0, TS, chunk_size=2, progress=report)
    assert waited == [True]  # a report arrived while the first block was still running
    assert calls == [0, 2, 4, 6]
    _assert_same(one_program, traj)


@pytest.mark.parametrize("count", [1, 2])
def test_progress_with_faults_throw_false(threads, count):
    """Reference: one compiled call without progress. A NaN torque stops its chunk, which is run
    again body by body; with progress, from one thread or two, the result is the same to the bit,
    and the reports arrive in order."""
    model, state0 = _faulty_scene()
    threads(1)
    one_program = rj.simulate(model, state0, TS, chunk_size=2, throw=False)
    threads(count)
    calls = []
    traj = rj.simulate(model, state0, TS, chunk_size=2, throw=False, progress=lambda d, t: calls.append(d))
    assert calls == [0, 2, 4, 6]
    assert np.asarray(traj.success).tolist() == [True, True, True, False, True, True]
    _assert_same(one_program, traj)


def _alone(model, state0, i, **options):
    """Body ``i`` of a six-body scene simulated by itself."""
    one = jax.tree.map(lambda x: x[i] if jnp.ndim(x) and jnp.shape(x)[0] == N else x, model)
    return rj.simulate(
        one,
        rj.State(state0.omega[i], None if state0.orientation is None else state0.orientation[i]),
        TS,
        **options,
    )


@pytest.mark.parametrize("scene", ["free", "gyrostat", "free exact", "heavy top exact"])
def test_blocks_of_three_bodies_keep_their_principal_moments(scene, threads):
    """Reference: each body simulated by itself. A block of three bodies (six bodies, chunks of
    three, one block per report) rebuilt its scene from inertia of shape (3, 3), which the scene read
    as one inertia tensor: every body of the batch came out wrong, marked successful."""
    rng = np.random.default_rng(1)
    inertia = rng.uniform(2.0, 3.0, (N, 3))  # numpy until handed over: no small programs
    omega0 = rng.normal(size=(N, 3))
    q0 = jnp.asarray(np.tile([1.0, 0.0, 0.0, 0.0], (N, 1)))
    options = {"accuracy": "exact"} if scene.endswith("exact") else {}
    if scene.startswith("free"):
        model = rj.FreeBody(jnp.asarray(inertia))
    elif scene == "gyrostat":
        model = rj.Gyrostat(jnp.asarray(inertia), jnp.asarray(rng.normal(size=(N, 3))))
    else:  # Lagrange tops: I1 = I2, centre of mass on the body z axis
        inertia[:, 1] = inertia[:, 0]
        model = rj.HeavyTop(jnp.asarray(inertia), 1.0, jnp.array([0.0, 0.0, 0.1]))
        omega0[:, 2] *= 20.0
    state0 = rj.State(jnp.asarray(omega0), q0)
    threads(1)
    traj = rj.simulate(model, state0, TS, chunk_size=3, progress=lambda done, total: None, **options)
    assert bool(np.all(np.asarray(traj.success)))
    # A body alone takes its own steps: the integrators agree within their tolerance (rtol 1e-8),
    # the closed forms to roundoff. Misread as a tensor, bodies were off by 0.1 to 30 rad/s.
    tolerance = 1e-12 if options else 1e-6
    for i in range(N):
        alone = _alone(model, state0, i, **options)
        np.testing.assert_allclose(np.asarray(traj.omega[i]), np.asarray(alone.omega), atol=tolerance)
        np.testing.assert_allclose(
            np.asarray(traj.orientation[i]), np.asarray(alone.orientation), atol=tolerance
        )


def test_three_bodies_run_again_keep_their_principal_moments(threads):
    """Reference: each healthy body simulated by itself. A chunk of three bodies stopped by its
    faulty body is run again body by body, from a scene of those three bodies' moments, (3, 3),
    which read as one tensor."""
    model, state0 = _faulty_scene()
    threads(1)
    traj = rj.simulate(model, state0, TS, chunk_size=3, throw=False)
    assert np.asarray(traj.success).tolist() == [True, True, True, False, True, True]
    for i in (0, 4, 5):
        alone = _alone(model, state0, i)
        np.testing.assert_allclose(np.asarray(traj.omega[i]), np.asarray(alone.omega), atol=1e-6)


def test_a_slice_of_three_bodies_stays_three_bodies(tmp_path):
    """Cut from a batch of six, three bodies' principal moments have the shape of one tensor; the
    scene keeps counting three bodies, and a file, which would read them back as a tensor, is refused."""
    model, state0 = _scene()
    three = jax.tree.map(lambda x: x[:3], model)
    assert three.inertia.shape == (3, 3) and three.batch_shape() == (3,)
    traj = rj.simulate(three, rj.State(state0.omega[:3], state0.orientation[:3]), TS, accuracy="exact")
    assert traj.batch_shape == (3,)
    with pytest.raises(ValueError, match=r"principal moments of shape \(3, 3\).*inertia\[\.\.\., None, :\]"):
        traj.save(tmp_path / "three.npz")
    assert list(tmp_path.iterdir()) == []


def test_host_threads_only_where_they_can_help(monkeypatch):
    """One thread per core up to one per chunk, on a single CPU device with values to run on;
    one compiled call under jit, for a single sample time and for a trajectory over the size limit."""
    from rigidjax._integrate import progress

    monkeypatch.setattr(progress, "available_cores", lambda: 4)
    model, state0 = _scene()
    w, q = state0.omega, state0.orientation
    assert progress.host_threads(model, w, q, TS, None, 2) == 3  # three chunks
    assert progress.host_threads(model, w, q, TS, None, 1) == 4  # six chunks, four cores
    monkeypatch.setattr(progress, "available_cores", lambda: 64)
    assert progress.host_threads(model, w, q, TS, None, 1) == progress.MAX_HOST_THREADS
    monkeypatch.setattr(progress, "available_cores", lambda: 4)
    assert progress.host_threads(model, w, q, TS, None, 6) == 1  # one chunk
    assert progress.host_threads(model, w, q, TS[:1], None, 2) == 1  # nothing to integrate
    monkeypatch.setattr(progress, "THREADED_MAX_BYTES", N * TS.shape[0] * 7 * 8 - 1)
    assert progress.host_threads(model, w, q, TS, None, 2) == 1
    monkeypatch.setattr(progress, "THREADED_MAX_BYTES", N * TS.shape[0] * 7 * 8)
    seen = []

    @jax.jit
    def traced(w):
        seen.append(progress.host_threads(model, w, q, TS, None, 2))
        return w

    traced(w)
    assert seen == [1]


@pytest.mark.filterwarnings("ignore:Explicitly requested dtype float64")  # the float32 context's
def test_threads_trace_in_the_callers_jax_context(threads):
    """JAX's context managers hold per thread: inside one (here ``jax.enable_x64(False)``) the
    blocks run in the calling thread, whose context a worker thread would not see; outside it, in
    worker threads. Seen through the thread that traces a torque function."""
    traced_in = set()

    def torque(t, state, args):
        traced_in.add(threading.get_ident())
        # Zero for these bodies (none spins faster than 3 rad/s): the faulty scene's torque, so
        # that the float64 run is the program of the faulty scene's blocks above, not another.
        return _nan_when_fast(t, state, args)

    def model():  # a new function each time: a new program, traced again
        return rj.RigidBody(
            jnp.asarray(np.tile([1.0, 2.0, 3.0], (N, 1))),
            rj.Torque(lambda t, s, a: torque(t, s, a), needs_orientation=False),
        )

    state0 = rj.State(jnp.asarray(np.tile([1.0, 0.2, 0.3], (N, 1))))
    threads(3)
    with jax.enable_x64(False):
        traj = rj.simulate(model(), state0, TS, chunk_size=2)
    assert traj.omega.dtype == jnp.float32
    assert traced_in == {threading.get_ident()}
    traced_in.clear()
    rj.simulate(model(), state0, TS, chunk_size=2)
    assert traced_in - {threading.get_ident()}, "no block ran in a worker thread"


def test_the_diffrax_check_switch_is_shared_by_threads():
    """Solves traced at the same time in two threads: the first in switches equinox's error mode
    off, the second out (not the first) switches it back, whatever the order they leave in."""
    import equinox._errors as equinox_errors

    from rigidjax._integrate import driver

    assert equinox_errors.EQX_ON_ERROR == "raise"
    first, second = (driver._without_diffrax_runtime_checks(True) for _ in range(2))
    first.__enter__()
    second.__enter__()
    assert equinox_errors.EQX_ON_ERROR == "off"
    first.__exit__(None, None, None)
    assert equinox_errors.EQX_ON_ERROR == "off"  # the second solve is still being traced
    second.__exit__(None, None, None)
    assert equinox_errors.EQX_ON_ERROR == "raise"


def test_ctrl_c_between_blocks_starts_no_further_block(threads, monkeypatch):
    """Ctrl-C (here a KeyboardInterrupt from the progress callback at the first finished block) while
    two threads run six blocks of one body each: the blocks not yet started do not run (all six ran
    before the interrupt was raised), and the running ones end before it is. Each block is held for
    a second, so that the count does not depend on how soon a loaded host runs the main thread
    (with blocks of a few milliseconds, a fifth one started once on a busy CI machine)."""
    from rigidjax._integrate import progress

    model, state0 = _scene()
    threads(2)
    # Compiled before counting: with progress, as below (blocks of one chunk each).
    rj.simulate(model, state0, TS, chunk_size=1, progress=lambda done, total: None)
    started = []
    block_until_ready = jax.block_until_ready

    def counted(x):
        if threading.current_thread() is threading.main_thread():
            return block_until_ready(x)
        started.append(1)
        out = block_until_ready(x)
        time.sleep(1.0)
        return out

    monkeypatch.setattr(progress.jax, "block_until_ready", counted)

    def interrupt(done, total):
        if done > 0:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        rj.simulate(model, state0, TS, chunk_size=1, progress=interrupt)
    assert 1 <= len(started) <= 4, len(started)
