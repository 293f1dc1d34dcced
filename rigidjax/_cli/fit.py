"""``rigidjax fit data.csv``: fit a body's inertia to a recorded wobble from the command line.

The CSV has a header row naming its columns: ``t, wx, wy, wz`` (time in s, body-frame angular
velocity in rad/s, as a gyroscope records it). Other columns are ignored; empty cells or ``nan``
are missing samples. The fitted inertia is printed with its standard errors, and written to
``<stem>_fit.json`` with a figure of observed and fitted omega, ``<stem>_fit.png``.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
import time
import warnings

import jax
import numpy as np

import rigidjax as rj

from .common import (
    DocstringHelpFormatter,
    StatusLine,
    UsageError,
    check_output,
    finite_or_none,
    plain,
    positive_int,
    write_figure,
    write_or_rescue,
    write_text,
)

OMEGA_COLUMNS = ("t", "wx", "wy", "wz")
QUATERNION_COLUMNS = ("t", "qw", "qx", "qy", "qz")


class DataError(ValueError):
    """A malformed input file; the message says what is wrong and how to fix it."""


def read_record(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Reads ``t, wx, wy, wz`` from a CSV with a header row; returns ``(ts, omega)``.

    Standard CSV: quoted cells and a byte-order mark (as spreadsheets write them) are read; blank
    lines, ``#`` comment lines and text after a ``#`` are skipped; an empty cell or ``nan`` is a
    missing sample."""
    if os.path.isdir(path):
        raise DataError(f"{path}: a directory, not a CSV file.")
    if not os.path.isfile(path):
        raise DataError(f"{path}: no such file.")
    try:
        with open(path, encoding="utf-8-sig", newline="") as handle:
            rows = list(csv.reader(handle))
    except UnicodeDecodeError as error:
        raise DataError(
            f"{path}: not a text file in UTF-8 (byte {error.start} cannot be read); save the record "
            "as a UTF-8 (or ASCII) CSV with columns t, wx, wy, wz."
        ) from None
    except csv.Error as error:  # a cell beyond the csv module's size limit, a NUL byte
        raise DataError(f"{path}: not a readable CSV file ({error}).") from None
    header = _header_line(rows)
    if header is None:
        raise DataError(
            f"{path}: "
            + ("the file is empty" if not rows else "no header row, only blank or comment lines")
            + "; a record needs a header row naming t, wx, wy, wz and then one row per sample."
        )
    names = [name.strip().lower() for name in rows[header]]
    if not all(c in names for c in OMEGA_COLUMNS):  # a comment after the names: "t,wx,wy,wz  # rad/s"
        names = [name.strip().lower() for name in _without_comment(rows[header])]
    if all(c in names for c in QUATERNION_COLUMNS) and not all(c in names for c in OMEGA_COLUMNS):
        raise DataError(
            f"{path}: orientation records (t, qw, qx, qy, qz) cannot be fitted from the command line "
            "yet; fit body-frame angular velocity (columns t, wx, wy, wz)."
        )
    missing = [c for c in OMEGA_COLUMNS if c not in names]
    if missing:
        raise DataError(_missing_columns(path, missing, names, rows[:header]))
    repeated = [c for c in OMEGA_COLUMNS if names.count(c) > 1]
    if repeated:
        raise DataError(f"{path}: the header names column(s) {', '.join(repeated)} more than once.")
    index = [names.index(c) for c in OMEGA_COLUMNS]
    data = []
    for line, cells in enumerate(rows[header + 1 :], start=header + 2):
        cells = _without_comment(cells)
        if not any(c.strip() for c in cells):
            continue  # a blank or comment line
        row = len(data) + 1
        # Fewer cells than the columns read, or more non-empty ones than the header names (a stray
        # comma shifts every later value of the row into the wrong column).
        if len(cells) <= max(index) or any(c.strip() for c in cells[len(names) :]):
            raise DataError(
                f"{path}: data row {row} (line {line}) has {len(cells)} cell(s); the header names "
                f"{len(names)} columns."
            )
        data.append(
            [_number(path, row, column, cells[i]) for column, i in zip(OMEGA_COLUMNS, index, strict=True)]
        )
    if not data:
        raise DataError(f"{path}: no data rows after the header.")
    data = np.asarray(data, dtype=float)
    _check_columns(path, data)
    ts, omega = data[:, 0], data[:, 1:4]
    if not np.all(np.isfinite(ts)):
        row = int(np.argmin(np.isfinite(ts)))
        raise DataError(
            f"{path}: the time in data row {row + 1} is missing or not a finite number ({ts[row]})."
        )
    if ts.shape[0] > 1 and not np.all(np.diff(ts) > 0):
        row = int(np.argmin(np.diff(ts) > 0))
        raise DataError(
            f"{path}: time must increase strictly; data row {row + 2} (t = {ts[row + 1]}) does not come "
            f"after row {row + 1} (t = {ts[row]}). Sort the rows and drop duplicates."
        )
    infinite = np.isinf(omega)
    if infinite.any():
        row, column = (int(i[0]) for i in np.nonzero(infinite))
        raise DataError(
            f"{path}: data row {row + 1} has an infinite {OMEGA_COLUMNS[column + 1]} "
            f"({omega[row, column]}); leave the cell empty (or write nan) for a missing sample."
        )
    _check_values_per_column(path, omega)
    return ts, omega


def _header_line(rows: list[list[str]]) -> int | None:
    """The index of the header row: the first line that is neither blank nor a ``#`` comment."""
    for k, cells in enumerate(rows):
        if any(c.strip() for c in _without_comment(cells)):
            return k
    return None


def _missing_columns(path: str, missing: list[str], names: list[str], before: list[list[str]]) -> str:
    """The message for a header without some of t, wx, wy, wz: the columns, and where the header is
    there but unread (separated by semicolons, tabs or spaces; commented out), that cause."""
    text = ",".join(names)
    for separator, called in ((";", "semicolons (;)"), ("\t", "tabs"), ("|", "bars (|)"), (None, "spaces")):
        parts = [part.strip().strip('"') for part in (text.split(separator) if separator else text.split())]
        if len(names) == 1 and all(c in parts for c in OMEGA_COLUMNS):
            return (
                f"{path}: the columns are separated by {called}, not commas (header {text!r}); "
                "save the record as comma-separated values, with '.' as the decimal point."
            )
    for cells in before:
        commented = [c.strip().lstrip("#").strip().lower() for c in cells]
        if all(c in commented for c in OMEGA_COLUMNS):
            return (
                f"{path}: the header row is commented out ({','.join(cells).strip()!r}); remove the '#' "
                "before the column names (numpy.savetxt writes it unless given comments='')."
            )
    return (
        f"{path}: missing column(s) {', '.join(missing)}; the header must name t, wx, wy, wz "
        f"(found: {', '.join(names) or 'nothing'})."
    )


def _check_columns(path: str, data: np.ndarray) -> None:
    """A column of t, wx, wy, wz with no value at all (every cell empty or nan) is named."""
    empty = [name for name, column in zip(OMEGA_COLUMNS, data.T, strict=True) if np.isnan(column).all()]
    if empty:
        needs = ["every sample needs its time"] if "t" in empty else []
        needs += ["the fit needs samples of each of wx, wy, wz"] if empty != ["t"] else []
        raise DataError(
            f"{path}: column{'s' if len(empty) > 1 else ''} {', '.join(empty)} "
            f"{'has' if len(empty) == 1 else 'have'} no values (all {data.shape[0]} data rows are empty "
            f"or nan there); {' and '.join(needs)}."
        )


def _check_values_per_column(path: str, omega: np.ndarray) -> None:
    """At least 10 values in each of wx, wy, wz (a row may miss some, as ``fit_inertia`` takes
    them); otherwise the columns with too few are named, the fewest first."""
    rows = omega.shape[0]
    observed = np.isfinite(omega).sum(axis=0)
    if np.all(observed >= 10):
        return
    short = [
        f"{OMEGA_COLUMNS[k + 1]} has {observed[k]} ({rows - observed[k]} of {rows} empty or nan)"
        for k in sorted(range(3), key=lambda k: observed[k])
        if observed[k] < 10
    ]
    raise DataError(
        f"{path}: too few samples: {', '.join(short)}. A fit needs at least 10 values of each of wx, wy, "
        "wz (a row may miss some), and several wobble cycles to be well determined."
    )


def _without_comment(cells: list[str]) -> list[str]:
    """The cells before a ``#`` (the rest of the line is a comment)."""
    for k, cell in enumerate(cells):
        if "#" in cell:
            return [*cells[:k], cell.split("#")[0]]
    return cells


def _number(path: str, row: int, column: str, text: str) -> float:
    """One cell as a float: empty or ``nan`` is a missing sample (NaN); text that is not a number
    is a :class:`DataError` naming the row and the column."""
    text = text.strip()
    if not text or text.lower() == "nan":
        return float("nan")
    try:
        if "_" in text:  # Python's float reads 1_000 as 1000; a CSV cell with one is not a number
            raise ValueError
        return float(text)
    except ValueError:
        raise DataError(
            f"{path}: data row {row}, column {column}: {text!r} is not a number; leave the cell empty "
            "(or write nan) for a missing sample."
        ) from None


class _Progress:
    """The fit's iterations on one status line: rewritten in place on a terminal; in a log, a line
    a second at most, and the last iteration's when the fit ends."""

    def __init__(self, steps: int, stream, enabled: bool):
        self.steps, self.line = steps, StatusLine(stream, enabled)
        self.start = self.shown = time.perf_counter()
        self.pending = None
        # A fit from the estimated start that ends badly runs again from the moments (2, 3, 4) in
        # each of the six orders, each counting its iterations from 1.
        self.last_iteration, self.other_starts = 0, 0

    def __call__(self, iteration, loss) -> None:
        if not self.line.enabled:
            return
        iteration = int(iteration)
        if iteration < self.last_iteration:
            self.close()  # the previous start's last iteration stays on screen
            self.other_starts += 1
            self.line.show(
                f"  fitting again from the moments (2, 3, 4) in each order: start {self.other_starts} of 6",
                last=True,
            )
        self.last_iteration = iteration
        now = time.perf_counter()
        text = (
            f"  iteration {iteration:4d} (at most {self.steps}), loss {float(loss):.3e}, "
            f"{now - self.start:5.1f} s"
        )
        if self.line.tty or now - self.shown >= 1.0:
            self.line.show(text)
            self.shown, self.pending = now, None
        else:
            self.pending = text

    def close(self) -> None:
        if self.pending is not None:
            self.line.show(self.pending, last=True)
            self.pending = None
        self.line.end()


def _format(value: float, error: float) -> str:
    return f"{value:.6g} ± {error:.2g}"


def _plot(path: str, ts, omega, fit) -> str | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fine = np.linspace(ts[0], ts[-1], max(2000, 4 * ts.shape[0]))
    predicted = np.asarray(fit.predict_omega(fine))
    at_samples = np.asarray(fit.predict_omega(ts))
    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    for k, name in enumerate(("x", "y", "z")):
        axes[k].plot(ts, omega[:, k], ".", ms=2.5, color="0.4", label="observed")
        axes[k].plot(fine, predicted[:, k], "-", lw=1.0, color="C3", label="fitted")
        axes[k].set_ylabel(f"ω_{name} (rad/s)")
    axes[0].legend(loc="upper right", fontsize=8)
    for start in np.asarray(fit.segment_starts)[1:]:
        for ax in axes:
            ax.axvline(start, color="0.85", lw=0.6, zorder=0)
    axes[3].plot(ts, omega - at_samples, ".", ms=2)
    axes[3].set_ylabel("residual (rad/s)")
    axes[3].set_xlabel("t (s)")
    fig.suptitle("rigidjax fit: observed and fitted body-frame angular velocity")
    fig.tight_layout()
    try:
        return write_or_rescue("fit", "--out", path, lambda where: write_figure(where, fig))
    finally:
        plt.close(fig)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "fit",
        help="fit the inertia of a torque-free body to a CSV record of body-frame omega",
        description=plain(__doc__),
        formatter_class=DocstringHelpFormatter,
    )
    p.add_argument("data", help="CSV file with a header row and columns t, wx, wy, wz")
    p.add_argument(
        "--segments",
        default="1",
        help="multiple shooting: number of windows, or 'auto' (about one wobble period each)",
    )
    p.add_argument("--full-tensor", action="store_true", help="fit a full tensor (sensor axes not principal)")
    p.add_argument(
        "--loss",
        default="squared",
        choices=("squared", "huber", "soft_l1", "cauchy"),
        help="loss of the residuals; the robust ones (huber, soft_l1, cauchy) limit the pull of outliers",
    )
    p.add_argument(
        "--method",
        default="optax",
        choices=("optax", "levenberg-marquardt"),
        help="optimiser: optax (L-BFGS with a strong-Wolfe line search) or levenberg-marquardt "
        "(Gauss-Newton with damping: fewer iterations, faster once compiled)",
    )
    p.add_argument(
        "--steps",
        type=positive_int,
        default=None,
        help="iteration limit (default: 2000 for optax, 200 for levenberg-marquardt)",
    )
    p.add_argument(
        "--inertia-init",
        nargs=3,
        type=float,
        metavar=("I1", "I2", "I3"),
        default=None,
        help="starting principal moments, any scale (only their ratios matter); default: estimated "
        "from the record, which needs enough neighbouring samples of each column",
    )
    p.add_argument("--trace", type=float, default=None, help="known trace of the inertia (kg m^2)")
    p.add_argument(
        "--known-moment",
        nargs=2,
        metavar=("AXIS", "VALUE"),
        default=None,
        help="known diagonal entry: sensor axis (x, y, z or 0, 1, 2) and its value (kg m^2)",
    )
    p.add_argument(
        "--out",
        default=None,
        help="output stem: writes STEM.json and STEM.png, checked before the fit (a trailing .json or "
        ".png is dropped; default: the data file's stem + '_fit')",
    )
    p.add_argument("--no-plot", action="store_true", help="do not write the PNG")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    p.set_defaults(func=run)


def in_command_words(text: str) -> str:
    """An :attr:`InertiaFit.warnings` text or a ``fit_inertia`` error with its advice in this
    command's options rather than ``fit_inertia``'s keyword arguments."""
    return (
        text.replace("(segments='auto')", "(--segments auto)")
        .replace("a robust loss", "a robust --loss")
        .replace("inertia_init", "--inertia-init")
    )


def _options(args) -> tuple[int | str, tuple[int, float] | None]:
    """``--segments`` and ``--known-moment`` as fit_inertia takes them, with ``--trace`` checked; a
    :class:`UsageError` naming the option otherwise."""
    segments: int | str = args.segments
    if segments != "auto":
        try:
            segments = int(segments)
        except ValueError:
            raise UsageError(f"--segments must be a positive integer or 'auto', got {segments!r}.") from None
        if segments < 1:
            raise UsageError(f"--segments must be a positive integer or 'auto', got {segments}.")
    if args.trace is not None and not (math.isfinite(args.trace) and args.trace > 0):
        raise UsageError(f"--trace must be a positive finite number (kg m^2), got {args.trace}.")
    known_moment = None
    if args.known_moment is not None:
        axis_text, value_text = args.known_moment
        axis = {"x": 0, "y": 1, "z": 2, "0": 0, "1": 1, "2": 2}.get(axis_text.strip().lower())
        try:
            value = float(value_text)
        except ValueError:
            value = None
        if axis is None or value is None:
            raise UsageError(
                f"--known-moment needs an axis (x, y, z) and a number, got {axis_text!r} {value_text!r}."
            )
        if not (math.isfinite(value) and value > 0):
            raise UsageError(
                f"--known-moment: the moment must be a positive finite number (kg m^2), got {value}."
            )
        known_moment = (axis, value)
    if args.trace is not None and known_moment is not None:
        raise UsageError("give at most one scale: --trace or --known-moment, not both.")
    if args.inertia_init is not None and not all(math.isfinite(v) and v > 0 for v in args.inertia_init):
        raise UsageError(f"--inertia-init needs three positive finite moments, got {args.inertia_init}.")
    return segments, known_moment


def _inertia_init(args):
    """``--inertia-init`` as ``fit_inertia`` takes it: the moments, or their diagonal tensor with
    ``--full-tensor``."""
    if args.inertia_init is None:
        return None
    moments = np.asarray(args.inertia_init, float)
    return np.diag(moments) if args.full_tensor else moments


def _outputs(args) -> tuple[str, str | None]:
    """The JSON and figure paths (None with ``--no-plot``), checked before the fit."""
    stem = args.out or os.path.splitext(args.data)[0] + "_fit"
    if os.path.isdir(stem) or not os.path.basename(stem):
        raise UsageError(
            f"--out {stem!r} is a directory; --out is a file stem (STEM.json and STEM.png are written), "
            f"such as {os.path.join(stem, 'fit')!r}."
        )
    if os.path.splitext(stem)[1].lower() in (".json", ".png"):
        stem = os.path.splitext(stem)[0]
    json_path = check_output(stem + ".json", "--out", (".json",))
    png_path = None if args.no_plot else check_output(stem + ".png", "--out", (".png",))
    return json_path, png_path


def run(args) -> int:
    """The ``fit`` command: read the record, fit, print, write the JSON and the figure."""
    jax.config.update("jax_enable_x64", True)

    segments, known_moment = _options(args)
    json_path, png_path = _outputs(args)
    try:
        ts, omega = read_record(args.data)
    except DataError as error:
        print(f"rigidjax fit: error: {error}", file=sys.stderr)
        return 2
    stream = sys.stderr
    if not args.quiet:
        stream.write(
            f"rigidjax fit: {args.data}: {ts.shape[0]} samples over {ts[-1] - ts[0]:.6g} s, "
            f"{int(np.sum(~np.isfinite(omega)))} missing values\n"
        )
        stream.write("  compiling the fit (first iterations include the compile) ...\n")
    steps = args.steps or (200 if args.method == "levenberg-marquardt" else 2000)
    progress = _Progress(steps, stream, not args.quiet)
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            # The command says so itself, below, against the plain rms.
            warnings.filterwarnings("ignore", message="the fit's residuals are", category=RuntimeWarning)
            fit = rj.fit_inertia(
                ts,
                omega,
                segments=segments,
                full_tensor=args.full_tensor,
                loss=args.loss,
                method=args.method,
                steps=args.steps,
                inertia_trace=args.trace,
                known_moment=known_moment,
                inertia_init=_inertia_init(args),
                callback=None if args.quiet else progress,
            )
    except ValueError as error:
        progress.close()
        print(f"rigidjax fit: error: {in_command_words(str(error))}", file=sys.stderr)
        return 2
    progress.close()
    seconds = time.perf_counter() - t0

    inertia = np.asarray(fit.inertia)
    err = np.asarray(fit.inertia_stderr)
    unit = "(trace 1: torque-free motion fixes only ratios)" if fit.normalised else "kg m^2"
    lines = [f"fitted inertia {unit}:"]
    if inertia.ndim == 1:
        for k, name in enumerate("xyz"):
            lines.append(f"  I_{name} = {_format(inertia[k], err[k])}")
    else:
        for i in range(3):
            row = "  ".join(f"{_format(inertia[i, j], err[i, j]):>22}" for j in range(3))
            lines.append(f"  [{row}]")
        lines.append("principal moments: " + ", ".join(f"{m:.6g}" for m in np.asarray(fit.principal_moments)))
    w0 = np.asarray(fit.omega0).reshape(-1, 3)
    w0_err = np.asarray(fit.omega0_stderr).reshape(-1, 3)
    lines.append(
        "omega0 (rad/s): "
        + ", ".join(_format(w0[0, k], w0_err[0, k]) for k in range(3))
        + (f"  (first of {w0.shape[0]} windows)" if w0.shape[0] > 1 else "")
    )
    rms = np.asarray(fit.residual_rms)
    noise = np.asarray(fit.noise_estimate)
    robust = "" if args.loss == "squared" else ", robust: 1.4826 median |residual|"
    lines.append(f"residual rms (rad/s{robust}): " + ", ".join(f"{r:.3g}" for r in rms))
    lines.append("noise estimate (rad/s, from the record alone): " + ", ".join(f"{r:.3g}" for r in noise))
    lines.append(
        f"{'converged' if bool(fit.converged) else 'NOT converged'} after {fit.num_steps} iterations "
        f"({fit.method}, {seconds:.1f} s including compile)"
    )
    print("\n".join(lines))
    cautions = [in_command_words(warning) for warning in fit.warnings]
    for warning in cautions:
        print(f"warning: {warning}", file=sys.stderr)

    result = {
        "data": args.data,
        "inertia": inertia.tolist(),
        "inertia_stderr": err.tolist(),
        "normalised_to_trace_1": fit.normalised,
        "principal_moments": np.asarray(fit.principal_moments).tolist(),
        "principal_axes_columns": np.asarray(fit.principal_axes).tolist(),
        "omega0": w0.tolist(),
        "omega0_stderr": w0_err.tolist(),
        "segment_starts": np.asarray(fit.segment_starts).tolist(),
        "loss": float(fit.loss),
        "residual_rms": rms.tolist(),
        "noise_estimate": noise.tolist(),
        "warnings": cautions,
        "converged": bool(fit.converged),
        "iterations": fit.num_steps,
        "method": fit.method,
        "loss_function": args.loss,
        "seconds": seconds,
    }
    text = json.dumps(finite_or_none(result), indent=2, allow_nan=False)
    json_written = write_or_rescue("fit", "--out", json_path, lambda path: write_text(path, text))
    written = [json_written] if json_written else []
    misplaced = json_written != json_path
    if png_path is not None:
        try:
            png_written = _plot(png_path, ts, omega, fit)
            written += [png_written] if png_written else []
            misplaced |= png_written != png_path
        except ImportError:
            print("(matplotlib is not installed: no figure; pip install 'rigidjax[plot]')", file=sys.stderr)
    if written:
        print("wrote " + ", ".join(written))
    if json_written is None:
        print(text)  # the results, where nothing else holds them
    return 0 if bool(fit.converged) and not misplaced else 1
