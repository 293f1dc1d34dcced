"""The ``rigidjax`` command: its parser (one subcommand per module of this package) and ``main``."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

import rigidjax as rj

from . import bench, fit, simulate
from .common import INTERRUPTED, UsageError, positive_int, run_command


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``rigidjax``: subcommands ``fit``, ``bench`` and ``simulate``."""
    parser = argparse.ArgumentParser(
        prog="rigidjax", description="Rotational dynamics of rigid bodies in JAX: command-line tools."
    )
    parser.add_argument("--version", action="version", version=f"rigidjax {rj.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    fit.add_parser(sub)
    bench.add_parser(sub)
    simulate.add_parser(sub)
    for command in sub.choices.values():
        command.add_argument(
            "--cpu-devices",
            type=positive_int,
            default=None,
            metavar="N",
            help="JAX devices the CPU is split into, one per core, so that batches of several "
            "chunks run on N cores at once (default: every core this process may use; 1 is better "
            "when other jobs keep the cores busy)",
        )
    return parser


def use_cores(requested: int | None) -> None:
    """The command's CPU devices (:func:`rigidjax.use_cpu_cores`). Without a request, every core
    where JAX has not started yet (a command run from Python after other JAX work keeps what is
    there); a request that cannot be met is a usage error."""
    try:
        rj.use_cpu_cores(requested)
    except ValueError as error:
        raise UsageError(f"--cpu-devices {requested}: {error}") from None
    except RuntimeError as error:
        if requested is not None:
            raise UsageError(f"--cpu-devices {requested}: {error}") from None


def _with_cores(func):
    def run(args):
        use_cores(args.cpu_devices)
        return func(args)

    return run


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``rigidjax`` command; returns the exit status (130 after Ctrl-C, which
    ends the process at once when ``argv`` is None, i.e. when this is the command itself)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a usage error (already printed)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    if args.command is None:
        parser.print_help()
        return 0
    rj.use_compilation_cache()
    code = run_command(_with_cores(args.func), args)
    if code == INTERRUPTED and argv is None:
        # Ctrl-C in the command itself: a compiled JAX computation may still be running in JAX's
        # threads, and interpreter shutdown under it waits for it to finish or crashes. Everything
        # this process writes is already complete or removed, so it ends here.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code
