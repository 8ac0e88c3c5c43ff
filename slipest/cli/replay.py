"""``slipest replay``: run the slip estimator over a logged CSV, one output row per leg cycle.

Run the online slip estimator over a log (columns t, az, theta, optional
slip; '# key=value' metadata such as '# nL=4') and write one row per leg
cycle, to stdout (or -o FILE) as CSV (default) or JSON lines: the fields of
slipest.online.Estimate. Units: t [s], delta_a [g], slip [-], dphi, phiS
[rad], kS [N/m]. A cycle that cannot be estimated has NaN values and its
quality says why. A summary (samples, skipped rows, cycles estimated and
flagged, and with --truth the errors against the log's slip column) goes to
stderr, so stdout stays machine-readable. The log is read in bounded-memory
chunks.

The ``slip`` column is ignored by the estimator unless ``--use-reference``
is given, so a log with the truth in it is still a blind test; ``--truth``
only compares.
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from slipest.cli import estimate_output
from slipest.cli.command import add_command
from slipest.cli.estimator_args import add_estimator_arguments, model_from_args, soil_from_args
from slipest.io.log_csv import LogFormatError, LogReader
from slipest.online import ESTIMATE_FIELDS, SlipEstimator

#: Output columns, in order.
COLUMNS = ESTIMATE_FIELDS


def add_parser(sub) -> None:
    p = add_command(sub, "replay", "estimate slip (and soil) per leg cycle from a logged CSV", __doc__)
    p.add_argument("log", metavar="LOG.csv", help="the log to replay ('-': stdin)")
    p.add_argument("-o", "--output", default="-", help="output file ('-' or omitted: stdout)")
    p.add_argument("--format", choices=("csv", "jsonl"), default="csv", help="output format (default csv)")
    p.add_argument("--legs", type=int, default=None, help="legs of the wheel-leg (default: the log's nL, else 4)")
    add_estimator_arguments(p)
    p.add_argument("--truth", action="store_true",
                   help="summarise the errors against the log's slip column (RMSE, bias, 95%% coverage)")
    p.add_argument("--use-reference", action="store_true",
                   help="let the estimator learn the soil from the log's slip column (default: ignored)")
    p.add_argument("--skip-bad", action="store_true",
                   help="count and skip malformed rows (default: stop with an error naming the line)")
    p.add_argument("--chunk-rows", type=int, default=65536, help=argparse.SUPPRESS)
    p.set_defaults(func=run)


class _Writer:
    def __init__(self, stream, fmt: str):
        self.stream = stream
        self.fmt = fmt
        if fmt == "csv":
            stream.write(estimate_output.header() + "\n")

    def write(self, estimates) -> None:
        if not estimates:
            return
        if self.fmt == "csv":
            self.stream.write("".join(estimate_output.row(e) + "\n" for e in estimates))
        else:
            self.stream.write("".join(estimate_output.json_row(e) + "\n" for e in estimates))


class TruthSummary:
    """Errors of the slip estimates against the reference slip carried on each estimate."""

    def __init__(self, dphi_true: float | None = None):
        self.err = []
        self.std = []
        self.derr = []
        self.dstd = []
        self.no_truth = 0
        self.dphi_true = dphi_true

    def add(self, estimates) -> None:
        for e in estimates:
            if not e.ok:
                continue
            if math.isfinite(e.slip_ref):
                self.err.append(e.slip - e.slip_ref)
                self.std.append(e.slip_std)
            else:
                self.no_truth += 1
            if self.dphi_true is not None and math.isfinite(e.dphi):
                self.derr.append(e.dphi - self.dphi_true)
                self.dstd.append(e.dphi_std)

    @staticmethod
    def _figs(err, std) -> str:
        e = np.asarray(err)
        s = np.asarray(std)
        rmse = float(np.sqrt(np.mean(e**2)))
        cov = float(np.mean(np.abs(e) <= 1.96 * s))
        return f"RMSE {rmse:.4f}, bias {float(np.mean(e)):+.4f}, 95% interval coverage {cov:.3f} ({e.size} cycles)"

    def lines(self) -> list:
        out = []
        if self.err:
            out.append("truth: slip " + self._figs(self.err, self.std))
        else:
            out.append("truth: no cycle had both an estimate and a reference slip")
        if self.no_truth:
            out.append(f"truth: {self.no_truth} estimated cycle(s) had no reference slip")
        if self.derr:
            out.append(f"truth: dphi (log metadata {self.dphi_true:g} rad) " + self._figs(self.derr, self.dstd))
        return out


def _metadata_dphi(meta):
    try:
        phiS, phiD = meta.get_float("phiS"), meta.get_float("phiD")
    except LogFormatError:
        return None  # e.g. "varies"
    return None if phiS is None or phiD is None else phiS - phiD


def run(args: argparse.Namespace) -> int:
    def fail(msg: str) -> int:
        print(f"slipest replay: {msg}", file=sys.stderr)
        return 2

    soil = soil_from_args(args)
    source = sys.stdin.buffer if args.log == "-" else args.log
    try:
        reader = LogReader(source, skip_bad=args.skip_bad)
    except FileNotFoundError:
        return fail(f"{args.log}: no such file")
    except OSError as exc:
        return fail(f"{args.log}: {exc.strerror or exc}")
    except LogFormatError as exc:
        return fail(str(exc))
    out = None
    try:
        legs = args.legs if args.legs is not None else (reader.metadata.n_legs or 4)
        if (args.truth or args.use_reference) and not reader.has_slip:
            return fail(f"{args.log}: --truth and --use-reference need a 'slip' column, the log has none")
        try:
            model = model_from_args(args)
            est = SlipEstimator(n_legs=legs, method=args.method, soil=soil or None, use_reference=args.use_reference,
                                model=model)
        except (ValueError, TypeError) as exc:  # InverseModelError is a ValueError: names the file
            return fail(str(exc))
        truth = TruthSummary(_metadata_dphi(reader.metadata) if args.truth else None) if args.truth else None
        out = sys.stdout if args.output == "-" else open(args.output, "w", encoding="utf-8", newline="\n")
        writer = _Writer(out, args.format)
        pass_ref = args.truth or args.use_reference
        for ch in reader.iter_chunks(args.chunk_rows):
            estimates = est.push_many(ch.t, ch.az, ch.theta, ch.slip if pass_ref else None)
            writer.write(estimates)
            if truth is not None:
                truth.add(estimates)
        out.flush()
    except LogFormatError as exc:
        return fail(str(exc))
    except OSError as exc:
        if isinstance(exc, BrokenPipeError):
            raise
        return fail(f"{exc.filename or args.output}: {exc.strerror or exc}")
    finally:
        reader.close()
        if out is not None and out is not sys.stdout:
            out.close()
    c = est.counters
    lines = [
        f"replay: {c['samples']} samples read from {args.log}"
        + (f", {reader.n_skipped} malformed row(s) skipped" if args.skip_bad else ""),
        f"replay: {c['cycles']} leg cycles: {c['cycles_ok']} estimated, {c['cycles_flagged']} flagged"
        + (" (" + ", ".join(f"{k[len('flagged_'):]} {v}" for k, v in c.items() if k.startswith("flagged_")) + ")"
           if c["cycles_flagged"] else "")
        + f"; method {args.method}, {legs} legs"
        + (f", reference slip used on {c['reference_used']} cycles" if args.use_reference else ""),
    ]
    if args.skip_bad and reader.bad_rows:
        first = reader.bad_rows[0]
        lines.append(f"replay: first malformed row: line {first.line}: {first.reason}")
    if truth is not None:
        lines += truth.lines()
    print("\n".join(lines), file=sys.stderr)
    return 0
