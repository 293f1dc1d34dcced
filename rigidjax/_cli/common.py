"""Pieces the commands share: argument types, output paths checked before a run and written
atomically, messages and progress lines on stderr, file sizes."""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import tempfile
from collections.abc import Callable

import numpy as np

import rigidjax as rj

from .._integrate.progress import StatusLine as StatusLine
from .._integrate.progress import bar as bar
from .._integrate.storage import check_writable, write_atomic, write_file_atomic

# The figure formats every command writes (matplotlib's savefig, chosen by the extension).
FIGURE_EXTENSIONS = (".png", ".pdf", ".svg")


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default in its help, except when there is none to show (``None``, a flag
    that is off) or the help already states it."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or "(default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


class DocstringHelpFormatter(argparse.RawDescriptionHelpFormatter, DefaultsHelpFormatter):
    """:class:`DefaultsHelpFormatter` for a command whose description is its module's docstring,
    kept line for line."""


def plain(docstring: str) -> str:
    """A module docstring as command-line help: ``code`` and :role:`name` markup become plain text."""
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", docstring)
    return text.replace("``", "")


def solver_text(accuracy: str, n_bodies: int, dtype) -> str:
    """The solver and tolerance ``simulate`` runs ``accuracy`` with, for ``n_bodies`` bodies at a
    time in ``dtype`` (the unrolled Dopri8 for large batches, the tolerance floor of float32)."""
    if accuracy == "exact":
        return "closed form"
    solver, rtol = rj.solvers.preset(accuracy, n_bodies, dtype)
    return f"{type(solver).__name__}, rtol {rtol:.2g}"


class UsageError(Exception):
    """A problem with the command line found before any work: one line on stderr, exit status 2."""


def check_output(path: str, option: str, extensions: tuple[str, ...]) -> str:
    """``path`` checked before the run: its extension is one of ``extensions`` and a file can be
    created there (the directory exists and is writable); a :class:`UsageError` naming ``option``
    otherwise."""
    extension = os.path.splitext(path)[1].lower()
    if extension not in extensions:
        choices = " or ".join(extensions)
        raise UsageError(f"{option} {path!r}: the file name must end in {choices}.")
    try:
        return check_writable(path, where=option, example=f"trajectory{extensions[0]}")
    except OSError as error:
        raise UsageError(str(error)) from None


def write_or_rescue(command: str, option: str, path: str, write: Callable[[str], object]) -> str | None:
    """``write(path)``; if that fails (the directory was removed during the run, a full disk, a file
    system that refuses the write), ``write`` to a file in the system's temporary directory instead,
    and say so on stderr naming ``option``: the results of a long run are not lost to the output
    path. Returns the path written, or None when neither write succeeded."""
    try:
        write(path)
        return path
    except OSError as error:
        problem = f"rigidjax {command}: error: {option} {path!r}: could not write ({error.strerror or error})"
    rescue = os.path.join(tempfile.gettempdir(), f"rigidjax-{command}-{os.getpid()}-{os.path.basename(path)}")
    try:
        write(rescue)
    except OSError as error:
        print(f"{problem}; nor {rescue!r} ({error.strerror or error}).", file=sys.stderr, flush=True)
        return None
    print(f"{problem}; written to {rescue!r} instead.", file=sys.stderr, flush=True)
    return rescue


def write_npz(path: str, arrays: dict) -> None:
    """The arrays as an ``.npz`` at ``path``, atomically (the writer of ``Trajectory.save``)."""
    write_atomic(path, arrays)


def write_text(path: str, text: str) -> None:
    """``text`` (UTF-8) at ``path``, atomically: the old file or the complete new one, never a part."""
    write_file_atomic(path, lambda handle: handle.write(text.encode("utf-8")))


def write_figure(path: str, fig) -> None:
    """A matplotlib figure at ``path`` (format from the extension), atomically."""
    extension = os.path.splitext(path)[1].lower().lstrip(".")
    write_file_atomic(path, lambda handle: fig.savefig(handle, format=extension, dpi=110))


INTERRUPTED = 130  # the exit status after Ctrl-C (128 + SIGINT), as shells report it


def interrupted(command: str) -> int:
    """The one line printed when Ctrl-C ends a command; returns the conventional exit status 130."""
    fresh_line = "\n" if hasattr(sys.stderr, "isatty") and sys.stderr.isatty() else ""  # after a progress bar
    print(
        f"{fresh_line}rigidjax {command}: interrupted (Ctrl-C); no output file is left half-written.",
        file=sys.stderr,
        flush=True,
    )
    return INTERRUPTED


def run_command(func: Callable, args) -> int:
    """Runs a command's ``run(args)``: a :class:`UsageError` is one line on stderr (exit status 2),
    Ctrl-C one line (exit status 130); neither shows a traceback."""
    try:
        return func(args)
    except UsageError as error:
        print(f"rigidjax {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return interrupted(args.command)


def _integer_at_least(text: str, minimum: int, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be {what}, got {value}")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    return _integer_at_least(text, 1, "a positive integer")


def rng_seed(text: str) -> int:
    """argparse type: a seed of ``numpy.random.default_rng``, an integer from 0 to 2^64 - 1 (the
    .npz stores it as one number; a larger one would need pickling)."""
    seed = _integer_at_least(text, 0, "a non-negative integer")
    if seed >= 2**64:
        raise argparse.ArgumentTypeError(
            f"must be below 2^64 (stored in the output as one number), got {text}"
        )
    return seed


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


def counted(n: int, one: str, many: str) -> str:
    """``n`` with the noun it counts: ``counted(1, "body", "bodies")`` is ``"1 body"``."""
    return f"{n:,} {one if n == 1 else many}"


def info(args, message: str) -> None:
    """``message`` on stderr unless ``--quiet``."""
    if not args.quiet:
        print(message, file=sys.stderr, flush=True)


def file_size(path: str) -> str:
    """The size of ``path`` in KiB or MiB, for the summaries (which a file removed since it was
    written must not stop)."""
    try:
        size = os.path.getsize(path)
    except OSError as error:
        return f"size unknown: {error.strerror or error}"
    return f"{size / 2**20:.1f} MiB" if size >= 2**20 else f"{size / 2**10:.1f} KiB"


def finite_or_none(value):
    """``value`` with every non-finite float, also inside lists and dicts, as None: JSON has no
    NaN or Infinity (Python writes them, and strict parsers refuse the file)."""
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_or_none(v) for v in value]
    if isinstance(value, float | np.floating) and not math.isfinite(value):
        return None
    return value
