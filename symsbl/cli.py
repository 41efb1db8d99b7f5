"""Command line: ``symsbl identify``, ``symsbl simulate``, ``symsbl discrepancy``, ``symsbl demo``.

A thin front end: parsing, reading files, printing. The work is done by the library.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import runpy
import sys
from pathlib import Path

from .errors import SymsblError
from .progress import progress_enabled

__all__ = ["main"]


def _names(text: str | None) -> list[str]:
    return [n.strip() for n in text.split(",") if n.strip()] if text else []


def _library(spec: str, states, inputs, degree: int):
    from . import library as lib
    from .errors import LibraryError

    if spec == "paper":
        return lib.paper(states, inputs, degree=degree)
    if spec == "poly":
        return lib.polynomial(list(states) + list(inputs), degree)
    path = Path(spec)
    if path.suffix != ".py" or not path.exists():
        raise LibraryError(
            f"--library must be 'paper', 'poly' or an existing Python file (.py) defining the "
            f"library; received {spec!r}."
        )
    namespace = runpy.run_path(str(path))
    found = namespace.get("library")
    if callable(found) and not isinstance(found, lib.Library):
        found = found(states, inputs)
    if not isinstance(found, lib.Library):
        raise LibraryError(
            f"library file {spec!r} must define `library`, a symsbl Library (or a function "
            "library(states, inputs) returning one) whose variables are named like the data's "
            f"columns; it defines {type(found).__name__ if found is not None else 'no `library`'}."
        )
    return found


def _cmd_identify(args) -> int:
    from .data import read_trajectory
    from .identify import identify
    from .symbolic import symbols

    states, inputs = _names(args.states), _names(args.inputs)
    traj = read_trajectory(args.data, states=states, inputs=inputs, time=args.time)
    sx_states = symbols(states)
    sx_inputs = symbols(inputs) if inputs else ()
    library = _library(args.library, sx_states, sx_inputs, args.degree)
    model = identify(traj, library, derivative=args.derivative)
    print(f"identified from {traj.n_samples} samples at {traj.fs:.6g} Hz with {len(library)} candidate terms:")
    print(model)
    if args.json:
        model.save(args.json)
        print(f"model written to {args.json}")
    return 0


def _cmd_simulate(args) -> int:
    from .data import read_trajectory
    from .errors import DataError
    from .model import IdentifiedModel
    from .validate import validate_model

    model = IdentifiedModel.load(args.model)
    traj = read_trajectory(args.data, states=model.state_names, inputs=model.input_names, time=args.time)
    try:
        result = validate_model(model, traj, n_band=args.band)
    except DataError as err:  # name the option, not the keyword behind it
        raise DataError(str(err).replace("n_band:", "--band:", 1)) from None
    print(result.message)
    if args.json:
        doc = {"status": result.status, "diverged_at": result.diverged_at, "nrmse": result.nrmse, "fit": result.fit}
        if result.coverage is not None:
            doc.update(coverage=result.coverage, noise_std=result.noise_std)
        Path(args.json).write_text(json.dumps(doc, indent=2, default=float) + "\n")
    if args.plot:
        from .plots import figure2

        figure2(model, result).savefig(args.plot, dpi=120)
        print(f"figure written to {args.plot}")
    return 0 if result.status == "ok" else 1


def _cmd_discrepancy(args) -> int:
    from .data import read_trajectory
    from .discrepancy import discrepancy

    states, inputs = _names(args.states), _names(args.inputs)
    traj = read_trajectory(args.data, states=states, inputs=inputs, time=args.time)
    heldout = None
    if args.held_out:
        heldout = read_trajectory(args.held_out, states=states, inputs=inputs, time=args.time)
    report = discrepancy(traj, args.base, heldout=heldout, error=args.error)
    print(report)
    if args.json:
        Path(args.json).write_text(json.dumps(report.to_json(), indent=2, default=float) + "\n")
        print(f"report written to {args.json}")
    if args.plot:
        from .plots import discrepancy_figure

        discrepancy_figure(report, heldout).savefig(args.plot, dpi=120)
        print(f"figure written to {args.plot}")
    return 0


def _cmd_demo(args) -> int:
    from .demo import run_demo

    results = run_demo(seed=args.seed, quick=args.quick)
    if args.plots:
        from .demo import write_figures

        for path in write_figures(results, args.plots, seed=args.seed):
            print(f"figure written to {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``symsbl`` command."""
    parser = argparse.ArgumentParser(
        prog="symsbl",
        description="Sparse Bayesian identification of nonlinear ODEs from sampled data.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", action="store_true",
                        help="no progress lines (they are shown only on a terminal, for steps longer than 0.5 s)")

    p = sub.add_parser("identify", parents=[common], help="identify equations of motion from a data file")
    p.add_argument("data", help="CSV with a header row, .npz or .mat")
    p.add_argument("--states", required=True, help="comma-separated state columns, e.g. x1,x2")
    p.add_argument("--inputs", default="", help="comma-separated input columns, e.g. F")
    p.add_argument("--time", default="t", help="time column (default: t)")
    p.add_argument("--library", default="paper", help="'paper' (Eq. 21), 'poly', or a .py file defining `library`")
    p.add_argument("--degree", type=int, default=3, help="polynomial degree (default: 3)")
    p.add_argument("--derivative", default="weak", help="weak (default), central, point or savgol")
    p.add_argument("--json", help="write the identified model as JSON to this file")
    p.set_defaults(func=_cmd_identify)

    p = sub.add_parser("simulate", parents=[common], help="re-simulate a saved model on a data file and print errors")
    p.add_argument("model", help="model JSON written by `symsbl identify --json`")
    p.add_argument("data", help="CSV/.npz/.mat with the model's states and inputs")
    p.add_argument("--time", default="t", help="time column (default: t)")
    p.add_argument("--json", help="write the errors as JSON to this file")
    p.add_argument("--band", type=int, default=0, metavar="N",
                   help="Monte Carlo draws for the 3-sigma predictive band; prints the share of samples inside it "
                        "(default: 0, no band)")
    p.add_argument("--plot", metavar="FILE", help="write the paper's Figure 2 for this record to FILE, e.g. fig.png "
                   "(needs symsbl[plot])")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("discrepancy", parents=[common], help="find the physical effect a model is missing, add it, show the gain")
    p.add_argument("data", help="training record: CSV with a header row, .npz or .mat")
    p.add_argument("--states", required=True, help="comma-separated state columns, e.g. x1,x2")
    p.add_argument("--inputs", default="", help="comma-separated input columns, e.g. F")
    p.add_argument("--base", required=True, help="starting model per state, e.g. \"x1: x2; x2: F, x1, x2\" (1: offset)")
    p.add_argument("--held-out", help="held-out record (default: the last 30 %% of DATA)")
    p.add_argument("--error", default="simulation", help="held-out error: simulation (default) or equation")
    p.add_argument("--time", default="t", help="time column (default: t)")
    p.add_argument("--json", help="write the report as JSON to this file")
    p.add_argument("--plot", metavar="FILE", help="write the before/after, residual-map and evidence figure to FILE, "
                   "e.g. report.png (needs symsbl[plot])")
    p.set_defaults(func=_cmd_discrepancy)

    p = sub.add_parser("demo", parents=[common], help="the paper's five systems end to end")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    p.add_argument("--quick", action="store_true", help="shorter records (for a fast check)")
    p.add_argument("--plots", metavar="DIR", help="write the paper's Figure 2 for each system as PNG into DIR (needs symsbl[plot])")
    p.set_defaults(func=_cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``symsbl`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with progress_enabled(False) if args.quiet else contextlib.nullcontext():
            return args.func(args)
    except (SymsblError, FileNotFoundError) as exc:  # incl. MissingExtraError: --plot without matplotlib
        print(f"symsbl {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
