"""The ``trackcal`` command: validate, diagnose, report, history, record (docs/understand.md).

Colour and progress bars only when the stream is a terminal. User errors exit with status 2 and a
one-line message naming the file, line and column (from the C++ readers).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time
from typing import Callable, List, Optional

import numpy as np


class Terminal:
    """ANSI colour and a progress bar on a TTY, plain text otherwise."""

    def __init__(self, out=None, err=None):
        self.out = out or sys.stdout
        self.err = err or sys.stderr
        self.colour = self.out.isatty() and os.environ.get("NO_COLOR") is None
        self.progress_enabled = self.err.isatty()
        self._t0 = None

    def c(self, text: str, code: str) -> str:
        return f"\033[{code}m{text}\033[0m" if self.colour else text

    def progress(self, label: str) -> Callable[[float, float], None]:
        """A callback (done, total) drawing a bar on stderr, only after work has run for 1 s."""
        start = time.monotonic()

        def update(done, total):
            if not self.progress_enabled or time.monotonic() - start < 1.0:
                return
            frac = min(1.0, done / total) if total else 1.0
            bar = "#" * int(30 * frac)
            self.err.write(f"\r{label} [{bar:<30}] {100 * frac:5.1f}%")
            if frac >= 1.0:
                self.err.write("\n")
            self.err.flush()
        return update


def _load(args):
    from trackcal import Calibration
    from trackcal.captures import load_poses
    capture = load_poses(args.capture)
    cal = Calibration.load(args.calibration) if args.calibration else None
    return capture, cal


def _fmt_rows(rows: List[dict], cols: List[str]) -> str:
    if not rows:
        return "  (none)"
    widths = {c: max(len(c), *(len(_cell(r.get(c))) for r in rows)) for c in cols}
    lines = ["  " + "  ".join(c.rjust(widths[c]) for c in cols)]
    for r in rows:
        lines.append("  " + "  ".join(_cell(r.get(c)).rjust(widths[c]) for c in cols))
    return "\n".join(lines)


def _cell(v) -> str:
    if isinstance(v, (float, np.floating)):
        return f"{v:.3f}"
    return "" if v is None else str(v)


def _validation(args, term, covariates: bool):
    from trackcal.validation import cross_validate, validate
    capture, cal = _load(args)
    v = validate(capture, cal, analyse_covariates=covariates,
                 covariate_options={"n_permutations": args.permutations, "seed": args.seed} if covariates else None,
                 progress=term.progress("covariates") if covariates else None)
    if getattr(args, "cross_validate", 0):
        v.tables.append(cross_validate(capture, folds=args.cross_validate))
    return capture, cal, v


def candidate_source():
    """The fit engine's ranking of missing physical effects, if installed: a module
    ``trackcal.candidates`` with ``rank(validation) -> list of dict rows``; None otherwise."""
    import importlib
    try:
        mod = importlib.import_module("trackcal.candidates")
    except ModuleNotFoundError as e:
        if e.name != "trackcal.candidates":
            raise
        return None
    return mod.rank


def _record_history(args, v) -> None:
    if not getattr(args, "workdir", None) or getattr(args, "command", "") != "validate":
        return
    from trackcal.history import record_fit, scores_from_validation
    if not args.calibration:
        raise ValueError("--workdir records a fit: give its calibration with -c")
    data = v.capture.path
    record_fit(args.workdir, model=args.calibration, data=[(data, "validation_capture")],
               scores=scores_from_validation(v), label=args.label or pathlib.Path(args.calibration).name)


def cmd_validate(args, term) -> int:
    _, _, v = _validation(args, term, covariates=False)
    _record_history(args, v)
    for t in v.tables:
        print(term.c(t.format(), "1") if t.set_name == "valid" else t.format())
    print(f"stations outside the calibrated volume: {int(v.extrapolated.sum())} of {len(v.extrapolated)}")
    if args.json:
        print(json.dumps({t.set_name: t.to_dict() for t in v.tables}, indent=2))
    return 0


def cmd_diagnose(args, term, candidates=None) -> int:
    capture, cal, v = _validation(args, term, covariates=True)
    for t in v.tables:
        print(t.format())
    n_out = int(v.extrapolated.sum())
    msg = f"stations outside the calibrated volume: {n_out} of {len(v.extrapolated)}"
    print(term.c(msg, "33") if n_out else msg)
    cols = ["label", "count", "before_position_mm", "before_orientation_deg"]
    if v.after is not None:
        cols += ["after_position_mm", "after_orientation_deg"]
    print("\n" + term.c("By distance from the transmitter", "1"))
    print(_fmt_rows(v.by_distance, cols))
    print("\n" + term.c("By region (octants around the volume centre)", "1"))
    print(_fmt_rows(v.by_region, cols))
    print("\n" + term.c(f"Worst {len(v.worst)} stations", "1"))
    print(_fmt_rows(v.worst, ["station", "set", "sensor", "x", "y", "z", "distance", "position_mm",
                              "orientation_deg", "extrapolated"]))
    print("\n" + term.c("Residual structure (cross-validated R², permutation test)", "1"))
    sig = [e for e in v.covariate_effects if e.significant]
    if not sig:
        print("  no covariate explains the residuals beyond noise")
    for e in sig[:args.top]:
        print("  " + term.c(f"{e.covariate:<24}", "31") + f" {e.target:<20} R²={e.r2:.3f}  p={e.p_value:.3g}")
    if candidates is not None:
        print("\n" + term.c("Candidate effects", "1"))
        rows = candidates(v)
        print(_fmt_rows(rows, list(rows[0].keys()) if rows else []))
    return 0


def cmd_report(args, term) -> int:
    from trackcal.history import load_history
    from trackcal.report import write_report
    capture, cal, v = _validation(args, term, covariates=not args.no_covariates)
    hist = load_history(args.workdir) if args.workdir else None
    path = write_report(v, args.output, inputs=[args.capture, args.calibration], history_entries=hist,
                        candidates=candidate_source(), progress=term.progress("figures"))
    print(f"wrote {path}")
    return 0


def cmd_history(args, term) -> int:
    from trackcal.history import history_table, load_history
    entries = load_history(args.workdir)
    if not entries:
        print(f"{args.workdir}: no fits recorded (history.jsonl)")
        return 0
    print(history_table(entries))
    if args.plot:
        from trackcal import figures
        figures.save_png(figures.history_plot(entries), args.plot)
        print(f"wrote {args.plot}")
    return 0


def cmd_record(args, term) -> int:
    from trackcal.record import record_streams
    devices = {}
    for spec in args.device:
        if "=" not in spec:
            raise ValueError(f"--device {spec!r}: expected LABEL=Tracker0@tcp://host:port")
        label, name = spec.split("=", 1)
        devices[label] = name
    out = record_streams(devices, args.output, args.duration, progress=term.progress("recording"))
    for label, p in out.items():
        print(f"{label}: wrote {p}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="trackcal", description="Validate, diagnose and report tracker calibrations.")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp, covariates=True):
        sp.add_argument("capture", help="capture folder or poses.csv")
        sp.add_argument("-c", "--calibration", help="calibration file (docs/calibration-file.md)")
        sp.add_argument("--cross-validate", type=int, default=0, metavar="K",
                        help="also K-fold cross-validate a least-squares degree-3 polynomial")
        if covariates:
            sp.add_argument("--permutations", type=int, default=199, help="permutations per covariate test")
            sp.add_argument("--seed", type=int, default=0)

    sp = sub.add_parser("validate", help="Table 1 before/after for the calibration and validation sets")
    common(sp, covariates=False)
    sp.add_argument("--json", action="store_true", help="also print the tables as JSON")
    sp.add_argument("--workdir", help="record this calibration's scores in WORKDIR/history.jsonl")
    sp.add_argument("--label", help="what changed in this fit (history label; default: file name)")
    sp = sub.add_parser("diagnose", help="compare and see where it fails: breakdowns, worst stations, covariates")
    common(sp)
    sp.add_argument("--top", type=int, default=15, help="significant covariates to list")
    sp = sub.add_parser("report", help="write a self-contained HTML report and PNG figures")
    common(sp)
    sp.add_argument("-o", "--output", required=True, help="output folder")
    sp.add_argument("--workdir", help="work folder whose history.jsonl to plot")
    sp.add_argument("--no-covariates", action="store_true")
    sp = sub.add_parser("history", help="error after each recorded fit of a work folder")
    sp.add_argument("workdir")
    sp.add_argument("--plot", help="write the history plot to this PNG")
    sp = sub.add_parser("record", help="record live raw and corrected streams from a VRPN server")
    sp.add_argument("--device", action="append", required=True,
                    help="LABEL=Tracker0@tcp://host:port (repeat: e.g. raw=... corrected=...)")
    sp.add_argument("--duration", type=float, required=True, help="seconds")
    sp.add_argument("-o", "--output", required=True, help="output folder")
    return p


COMMANDS = {"validate": cmd_validate, "diagnose": cmd_diagnose, "report": cmd_report,
            "history": cmd_history, "record": cmd_record}


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    term = Terminal()
    try:
        if args.command == "diagnose":
            return cmd_diagnose(args, term, candidates=candidate_source())
        return COMMANDS[args.command](args, term)
    except (ValueError, KeyError, RuntimeError, FileNotFoundError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        print(term.c("error: ", "31") + str(msg), file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into head & co.
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
