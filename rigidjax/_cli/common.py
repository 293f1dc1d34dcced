"""Pieces the commands share: argument types, messages and progress lines on stderr, file sizes."""

from __future__ import annotations

import argparse
import math
import os
import sys


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


def info(args, message: str) -> None:
    """``message`` on stderr unless ``--quiet``."""
    if not args.quiet:
        print(message, file=sys.stderr, flush=True)


def file_size(path: str) -> str:
    """The size of ``path`` in KiB or MiB, for the summaries."""
    size = os.path.getsize(path)
    return f"{size / 2**20:.1f} MiB" if size >= 2**20 else f"{size / 2**10:.1f} KiB"


def bar(done: int, total: int, width: int = 30) -> str:
    """A text progress bar: ``done / total`` of ``width`` characters filled with ``#``."""
    filled = min(width, max(0, round(width * done / max(total, 1))))
    return "#" * filled + "." * (width - filled)


class StatusLine:
    """One progress line on a stream: rewritten in place on a terminal, one line per update otherwise."""

    def __init__(self, stream, enabled: bool):
        self.stream, self.enabled = stream, enabled
        self.tty = enabled and hasattr(stream, "isatty") and stream.isatty()
        self._width = 0

    def show(self, line: str, last: bool = False) -> None:
        if not self.enabled:
            return
        if self.tty:
            self.stream.write("\r" + line.ljust(self._width) + ("\n" if last else ""))
            self._width = 0 if last else len(line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
