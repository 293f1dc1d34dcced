"""``rigidjax.use_compilation_cache``: a second process loads what a first one compiled.

Independent evidence: JAX's own log of each compile (``JAX_LOG_COMPILES``: "Persistent compilation
cache hit"), the files in the directory, and the two processes' results, which must agree to the
bit. The children run without the test session's cache settings, so only the function under test
turns the cache on.
"""

import json
import os
import subprocess
import sys

import pytest

import rigidjax as rj

_CHILD = """
import json, os, sys
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import rigidjax as rj
path = rj.use_compilation_cache(None if sys.argv[1] == "default" else sys.argv[1])
omega0 = np.array([[[0.1, 0.9, 0.3]]] * 4)  # 4 bodies, each at 7 times
omega = rj.torque_free_omega(np.array([1.0, 2.0, 3.0]), omega0, np.linspace(0, 9, 7))
files = sorted(os.listdir(path)) if path else []
print(json.dumps({"path": path, "files": files, "omega": np.asarray(omega).tolist()}))
"""


def _child(argument, **env):
    clean = {
        k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT"))
    }
    clean.update(JAX_LOG_COMPILES="1", **env)
    child = subprocess.run(
        [sys.executable, "-c", _CHILD, argument], env=clean, capture_output=True, text=True, timeout=300
    )
    assert child.returncode == 0, child.stderr[-3000:]
    return json.loads(child.stdout.strip().splitlines()[-1]), child.stderr


def test_a_second_process_loads_every_program(tmp_path):
    cache = tmp_path / "programs"
    first, first_log = _child(str(cache))
    second, second_log = _child(str(cache))
    assert first["path"] == second["path"] == str(cache)
    assert "Persistent compilation cache hit" not in first_log
    # The value checks' program compiles in well under JAX's default threshold of one second: it is
    # kept only because the function asks the cache to keep every program.
    for program in ("_omega_program", "_omega_failures"):
        assert f"Persistent compilation cache hit for 'jit_{program}'" in second_log, second_log[-3000:]
    assert second["files"] == first["files"] and len(first["files"]) >= 2
    assert second["omega"] == first["omega"]


def test_default_directory_and_off_switch(tmp_path):
    chosen, _ = _child("default", XDG_CACHE_HOME=str(tmp_path))
    assert chosen["path"] == str(tmp_path / "rigidjax" / "jax") and chosen["files"]
    off, log = _child("default", XDG_CACHE_HOME=str(tmp_path / "off"), RIGIDJAX_NO_COMPILATION_CACHE="1")
    assert off["path"] is None and not (tmp_path / "off").exists()
    assert "Persistent compilation cache hit" not in log


def test_bad_paths_are_named(tmp_path, without_runtime_typecheck):
    occupied = tmp_path / "a_file"
    occupied.write_text("")
    with pytest.raises(ValueError, match="use_compilation_cache: path .*a_file.* cannot be used"):
        rj.use_compilation_cache(occupied)
    with pytest.raises(TypeError, match="path must be a directory path"):
        rj.use_compilation_cache(3)


_MOVING_CHILD = """
import json, os, sys
import jax, jax.numpy as jnp
import rigidjax as rj
first, second = sys.argv[1:3]
rj.use_compilation_cache(first)
jax.jit(lambda x: x * 2 + 1)(jnp.ones(3)).block_until_ready()
in_first = sorted(os.listdir(first))
moved = rj.use_compilation_cache(second)
jax.jit(lambda x: x * 5 - 3)(jnp.ones(3)).block_until_ready()
print(json.dumps({"moved": moved, "first": in_first, "first_after": sorted(os.listdir(first)),
                  "second": sorted(os.listdir(second))}))
"""


def test_a_second_call_moves_the_cache_to_its_directory(tmp_path):
    """JAX opens its cache at the first compile: a second call returned its new directory while
    every program went on to the first one (the second stayed empty)."""
    first, second = tmp_path / "first", tmp_path / "second"
    clean = {
        k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT"))
    }
    child = subprocess.run(
        [sys.executable, "-c", _MOVING_CHILD, str(first), str(second)],
        env=clean, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert child.returncode == 0, child.stderr[-3000:]
    out = json.loads(child.stdout.strip().splitlines()[-1])
    assert out["moved"] == str(second) and out["first"] and out["second"]
    assert out["first_after"] == out["first"]  # the second program went to the second directory only
