"""Command line: ``symsbl identify``, ``symsbl validate`` (alias ``simulate``), ``symsbl discrepancy``,
``symsbl demo``.

A thin front end: parsing, reading files, printing. The work is done by the library. Every
failure is one line on standard error, ``symsbl <command>: error: <what>``, with a documented
exit code (:data:`EXIT_CODES`); outputs are checked before the work starts, never overwrite an
input, and are written through a temporary file renamed into place.
"""

from __future__ import annotations

import argparse
import json
import runpy
import sys
from pathlib import Path

from ._base.errors import DataError, LibraryError, ParameterError, SymsblError, expected
from ._data.residuals import LEVEL
from ._outcome import EXIT_CODES, run_command
from ._outcome import fail as _fail
from ._refine.problem import INTERPOLATIONS

__all__ = ["main", "build_parser", "EXIT_CODES"]

#: Image formats ``--plot`` accepts (those matplotlib's Agg backend writes).
PLOT_FORMATS = (".png", ".pdf", ".svg", ".jpg", ".jpeg", ".eps", ".ps", ".tif", ".tiff", ".webp")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``symsbl <command>: error: <message>`` and exit code 2."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        self.exit(2, f"{self.prog}: error: {message}\n")


def _names(text: str | None) -> list[str]:
    return [n.strip() for n in text.split(",") if n.strip()] if text else []


#: Why a library file holds no more than a model file, as the error says.
_LIBRARY_BOUND = "the most a model file holds: every term is ranked and compiled before any fit"


def _user_code(run, where: str, what: str, exited: str):
    """``run()``, code of a library file; whatever it raises but Ctrl-C is one :class:`LibraryError` naming the
    file (``exited``: what was expected instead of a call of ``sys.exit``)."""
    try:
        return run()
    except KeyboardInterrupt:  # Ctrl-C, or the file's own: the command ends as interrupted, as everywhere
        raise
    except SystemExit as exc:
        what, got = exited, f"a file that called sys.exit({exc.code!r})"
    except BaseException as exc:  # noqa: BLE001 - the user's file may raise anything, a BaseException subclass too
        try:
            line = (str(exc).strip().splitlines() or [""])[0]
        except Exception:  # noqa: BLE001 - an exception whose own __str__ fails
            line = ""
        got = f"{type(exc).__name__}{': ' + line if line else ''}"[:160]
    raise LibraryError(expected(where, what, got, raw=True))


def _run_library_file(path: Path, states, inputs):
    """Run a library file (its Python runs, by design) and return its ``library``, no larger than a model file
    may be (:data:`~symsbl._symbolic.library.MAX_FILE_TERMS` terms,
    :data:`~symsbl._symbolic.library.MAX_FILE_NODES` expression nodes)."""
    from ._symbolic.library import MAX_FILE_NODES, MAX_FILE_TERMS, Library, bound_size, expression_nodes

    where = f"--library {str(path)!r}"
    namespace = _user_code(
        lambda: runpy.run_path(str(path)), where, "a Python file that runs", "a file that defines `library`"
    )
    found = namespace.get("library")
    if callable(found) and not isinstance(found, Library):
        build, call = found, "library(states, inputs) returning a Library"
        found = _user_code(lambda: build(states, inputs), where, call, call)
    if not isinstance(found, Library):
        got = type(found).__name__ if found is not None else "no `library`"
        raise LibraryError(
            expected(
                where,
                "a file defining `library`, a symsbl Library (or a "
                "function library(states, inputs) returning one) named like the data's columns",
                got,
                raw=True,
            )
        )
    fix = "use fewer terms, or --library poly or paper with --degree for a larger polynomial library"
    bound_size(len(found), MAX_FILE_TERMS, "terms", where=where, why=_LIBRARY_BOUND, fix=fix, error=LibraryError)
    bound_size(
        expression_nodes(found.exprs),
        MAX_FILE_NODES,
        "expression nodes",
        where=where,
        why=_LIBRARY_BOUND,
        fix="use fewer or smaller terms",
        error=LibraryError,
    )
    return found


#: The degree of a built-in library when ``--degree`` is not given, and the degree above it tried where an
#: equation's law needs it (see :func:`symsbl._regression.ladder.climb`).
DEGREE = 3
#: The richer degree is tried only while its library holds at most this many candidates: the equation error's
#: cost grows with their square, and a structure of many states already has a large library.
LADDER_TERMS = 500


def _library(spec: str, states, inputs, degree: int | None):
    """The command's library: a file's, or a built-in one of ``degree``; without a degree, the ladder of
    :data:`DEGREE` and the degree above it (when that holds at most :data:`LADDER_TERMS` candidates)."""
    from ._symbolic.terms import paper, polynomial

    if degree is not None and degree < 1:
        raise LibraryError(expected("--degree", "an integer >= 1", degree))
    if spec in ("paper", "poly"):

        def build(n: int):
            return paper(states, inputs, degree=n) if spec == "paper" else polynomial(list(states) + list(inputs), n)

        if degree is not None:
            return build(degree)
        first = build(DEGREE)
        try:
            richer = build(DEGREE + 1)
        except LibraryError:  # beyond the size a library may have
            return first
        return [first, richer] if len(richer) <= LADDER_TERMS else first
    path = Path(spec)
    if path.suffix != ".py" or not path.is_file():
        raise LibraryError(
            expected("--library", "'paper', 'poly' or an existing Python file (.py) defining the library", spec)
        )
    return _run_library_file(path, states, inputs)


def _outputs(args, inputs: list) -> None:
    """Check every output option before the work starts: each can be written, none is an input, no two
    are one file."""
    from ._base.outputs import distinct_outputs, safe_output

    if getattr(args, "json", None) is not None:
        safe_output(args.json, inputs, what="--json")
    plot = getattr(args, "plot", None)
    if plot is not None:
        if Path(plot).suffix.lower() not in PLOT_FORMATS:
            raise LibraryError(expected("--plot", f"a file ending in one of {list(PLOT_FORMATS)}", plot))
        safe_output(plot, inputs, what="--plot")
    distinct_outputs([("--json", getattr(args, "json", None)), ("--plot", plot)])
    plots = getattr(args, "plots", None)
    if plots == "":
        raise DataError(expected("--plots", "a directory path", "''", "name the directory to write", raw=True))
    if plots and Path(plots).exists() and not Path(plots).is_dir():
        raise LibraryError(
            expected("--plots", "a directory (created if missing)", f"{plots!r}, which is a file", raw=True)
        )
    if plot or plots:
        from ._figures import require_matplotlib

        require_matplotlib()


def _write_json(path, doc: dict) -> None:
    from ._base.outputs import write_atomic

    text = json.dumps(doc, indent=2, default=float) + "\n"
    write_atomic(path, lambda fh: fh.write(text), binary=False)


def _save_figure(fig, path) -> None:
    from ._base.outputs import write_atomic

    suffix = Path(path).suffix
    write_atomic(path, lambda fh: fig.savefig(fh, dpi=120, format=suffix[1:]), suffix=suffix)


def _read(args, path, states, inputs, *, optional=()):
    """The record's ``states`` and ``inputs``; states in ``optional`` (unmeasured ones) may be missing. The file
    is read once (a FIFO can be read only once)."""
    from ._data.io import column_names, columns_trajectory, read_columns

    time = None if args.time == "" else args.time
    columns = read_columns(path)
    present = column_names(columns)
    if optional:
        absent = [s for s in states if s not in present and s not in optional]
        if absent:
            raise DataError(
                expected(
                    f"--states {','.join(absent)}",
                    "a column of DATA (the position of each --kinematics pair is "
                    "measured; its velocity and latent states may be absent)",
                    "no such column",
                    raw=True,
                )
            )
        states = [s for s in states if s in present or s not in optional]
        if not states:
            raise DataError(
                expected("--states", "at least one column of DATA", f"none of {','.join(optional)}", raw=True)
            )
    try:
        return columns_trajectory(columns, path, states=states, inputs=inputs, time=time, fs=args.fs)
    except DataError:
        if optional or getattr(args, "kinematics", None) != "":
            raise
        absent = [s for s in states if s not in present]  # a velocity left out, its pair not declared?
        if not absent or len(absent) == len(states):
            raise
        raise DataError(
            expected(
                f"--states {','.join(absent)}",
                "a column of DATA",
                "no such column",
                f"if {absent[0]} is an unmeasured velocity, declare its pair: --kinematics <position>:{absent[0]}",
                raw=True,
            )
        ) from None


def _unmeasured_allowed(states, kinematics) -> tuple:
    """Columns a record may lack once kinematic pairs are declared: the velocities, the positions of pairs that
    have an acceleration column, the acceleration columns, and any other state (latent: its law is identified
    from the measured ones, see :mod:`symsbl._latent`)."""
    from ._derivatives.kinematics import kinematic_triples

    if not kinematics:
        return ()
    triples = kinematic_triples(kinematics, states)
    positions = {x for x, _, a in triples if a is None}
    return tuple(s for s in states if s not in positions) + tuple(a for _, _, a in triples if a is not None)


def _accelerations(states, kinematics) -> list[str]:
    """The acceleration columns the kinematic pairs name."""
    from ._derivatives.kinematics import kinematic_triples

    return [a for _, _, a in kinematic_triples(kinematics, states) if a is not None] if kinematics else []


def _read_all(args, paths, states, inputs, *, optional=()) -> list:
    """Every DATA file's record; the files must hold the same columns."""
    records = [_read(args, path, states, inputs, optional=optional) for path in paths]
    first = records[0]
    for path, r in zip(paths[1:], records[1:]):
        if (r.state_names, r.input_names) != (first.state_names, first.input_names):
            raise DataError(
                expected(
                    f"DATA {path!r}",
                    f"the columns of {paths[0]!r} {list(first.state_names + first.input_names)}",
                    f"{list(r.state_names + r.input_names)}",
                    "give files of one test campaign, each with the same columns",
                    raw=True,
                )
            )
    return records


def _cmd_identify(args) -> int:
    from ._symbolic.symbols import symbols

    states, inputs, outputs = _names(args.states), _names(args.inputs), _names(args.outputs)
    _outputs(args, [*args.data, args.library if str(args.library).endswith(".py") else None])
    accelerations = _accelerations(states, args.kinematics)
    # without pairs, a state no record holds is latent (the upper of two tanks), as in identify
    optional = _unmeasured_allowed(states, args.kinematics) if args.kinematics else tuple(states)
    records = _read_all(args, args.data, states + accelerations + outputs, inputs, optional=optional)
    if not args.kinematics:  # a typo or a velocity whose pair was left out reads as latent: say so first
        for name in (s for s in states if s not in records[0].state_names):
            print(
                f"symsbl identify: note: {name} is not a column of DATA: it is identified as a latent state, with a "
                f"law of its own (if it is a velocity, declare its pair: --kinematics <position>:{name})",
                file=sys.stderr,
            )
    library = _library(args.library, symbols(states), symbols(inputs) if inputs else (), args.degree)
    derivative = _identify_derivative(args)
    model = _identify_model(args, records, library, derivative, states, outputs)
    _print_identified(args, model, records, library)
    return 0 if any(eq.terms for eq in model.equations) else 1


def _identify_derivative(args):
    """Check ``--overlap`` and return the derivative method identify takes: the name, or a weak form."""
    from ._base.checks import integer
    from ._derivatives.weakform import WeakForm

    derivative = args.derivative
    integer("--overlap", args.overlap, low=1)
    if args.overlap != 1:
        if derivative != "weak":
            raise ParameterError(
                expected(
                    "--overlap",
                    "1 unless --derivative is weak",
                    f"--overlap {args.overlap} with --derivative {derivative}",
                    raw=True,
                )
            )
        derivative = WeakForm(overlap=args.overlap)
    return derivative


def _identify_model(args, records, library, derivative, states, outputs):
    """Run :func:`identify` with the command's options, naming the option in its errors."""
    from ._base.rule import SelectionRule
    from ._identify import identify
    from ._refine.options import RefineOptions

    options = RefineOptions(
        noise=args.noise, doubts=args.doubts, **({"interpolation": args.interpolation} if args.interpolation else {})
    )
    try:
        return identify(
            records if len(records) > 1 else records[0],
            library,
            derivative=derivative,
            states=states,
            kinematics=args.kinematics or None,
            refine=False if args.no_refine else options,
            selection=SelectionRule(model_choice=args.selection),
            outputs=outputs,
        )
    except SymsblError as err:  # name the option, not the keyword behind it
        raise type(err)(str(err).replace("WeakForm.overlap:", "--overlap:", 1)) from None


def _print_identified(args, model, records, library) -> None:
    """Print the identified model with its diagnosis, and write ``--json`` and ``--plot``."""
    estimator = model.metadata.get("estimator", {})
    how = (
        "output error on the equation error's structure (the input is noisy: error bars widened by refits)"
        if estimator.get("input_noise")
        else "output error (refined)"
        if model.fit.value == "output-error"
        else "equation error (output error is biased here)"
        if estimator.get("used") == "equation-error"
        else "equation error"
    )
    where = (
        f"{records[0].n_samples} samples at {records[0].fs:.6g} Hz"
        if len(records) == 1
        else f"{len(records)} records ({sum(r.n_samples for r in records)} samples)"
    )
    first = len(library[0] if isinstance(library, list) else library)
    steps = model.metadata.get("library", [])
    # an equation the ladder moved chose among the richer library's candidates, the refinement among them all
    richer = "; ".join(f"{s['candidates']} for {', '.join(s['equations'])}" for s in steps)
    refined = f"; the refinement's {steps[-1]['candidates']}" if steps and model.fit.value == "output-error" else ""
    candidates = f"{first} candidate terms" + (f" ({richer}{refined})" if richer else "")
    print(f"identified from {where} with {candidates}, coefficients by {how}:")
    print(model)
    for line in _diagnosis(model):
        print(line)
    if args.path:
        print("model path:")
        print(model.path)
    if "latent" in model.metadata:
        print(_latent_summary(model.metadata["latent"]))
    if args.json is not None:
        model.save(args.json)
        print(f"model written to {args.json}")
    if args.plot:
        from .plots import model_path_figure

        model_path_figure(model).savefig(args.plot)
        print(f"figure written to {args.plot}")


def _diagnosis(model) -> list[str]:
    """What the refinement says about the record: its noise model, the residual tests that failed, why the
    equation-error estimate is reported."""
    refine = model.metadata.get("refine", {})
    lines = []
    coloured = {k: v["model"] for k, v in refine.get("noise", {}).items() if v["model"] != "white"}
    if coloured:
        lines.append("noise model: " + ", ".join(f"{k} {m}" for k, m in coloured.items()))
    for t in refine.get("residual", []):
        if not (t["white"] and t["independent"] and t["open_loop"]):
            found = [] if t["white"] else [f"innovations correlated (Ljung-Box p = {t['whiteness_p']:.2g})"]
            if not t["white"] and (t.get("noise_p") or 0.0) >= LEVEL:
                found[-1] += " over a white noise between periods (the model's error, not a disturbance)"
            found += [f"depends on {k}" for k, r in t["input_ratio"].items() if r > 1]
            found += [f"feedback to {k}" for k, r in t["feedback_ratio"].items() if r > 1]
            lines.append(f"residual test of {t['channel']}: " + "; ".join(found))
    for reason in model.metadata.get("estimator", {}).get("doubts", []):
        lines.append(f"output error doubted: {reason}")
    if refine.get("short_segments"):
        lines.append(
            f"fitted on segments of at most {refine['short_segments']} samples, each from its own initial "
            "state (the residual is not the measurement noise the likelihood describes)"
        )
    chosen = model.path.chosen if len(model.path) else None
    if chosen is not None and chosen.source != "evidence":
        lines.append(f"structure chosen from the model path ({chosen.source}): {model.path.rule}")
    for step in model.metadata.get("library", []):
        grown = ", ".join(f"{n} {a} terms -> {b}" for n, (a, b, *_) in step["equations"].items())
        lines.append(
            f"library: the richer one ({step['candidates']} candidates against {step['from']}) holds a law in "
            f"fewer terms at a decisively higher evidence: {grown}"
        )
    refused = model.metadata.get("library_refused")
    if refused:
        lines.append(f"library: the richer one ({refused['candidates']} candidates) was not tried: {refused['why']}")
    if refine.get("beyond_library"):
        lines.append(f"library: {refine['beyond_library']}")
    return lines


def _latent_summary(info: dict) -> str:
    """What the latent-state pipeline found: its verdict, and the branches the record does not tell from it."""
    found = _latent_verdict(info)
    rivals = info.get("rivals")  # absent from files written before the rivals were recorded
    if not rivals:
        return found
    within = ", ".join(f"{k} ({d:+.3g} nats)" for k, d in rivals.items())
    return (
        f"{found}\nlatent state {info['latent']}: within the verdict's margin ({info['margin']:.3g} nats) of the "
        f"chosen {info['chosen']}: {within}; the record does not tell them apart"
    )


def _latent_verdict(info: dict) -> str:
    """The verdict and each branch's log evidence, in one line."""
    branches = ", ".join(f"{k} {v['log_evidence']:.6g}" for k, v in info["branches"].items())
    if info.get("start") == "driven":
        law = info["screened_law"]
        how = "started from" if info["verdict"] == "hidden" else "best screened"
        return (
            f"latent state {info['latent']}: {info['verdict']}; log evidence by branch: {branches} ({how} "
            f"{info['latent']}' = {law['drive']} - {law['rate']:.3g} {law['law']}, time constant {law['tau']:.3g} s, "
            f"of {info['n_candidates']} laws screened)"
        )
    record = (
        f"{info['periods']} periods of {info['period_samples']} samples; noise of their average"
        if info["periodic"]
        else "a transient record; noise"
    )
    misfit = info.get("misfit", {})
    host = (
        f" on {info['host']} (each position's linear misfit over its noise: "
        + ", ".join(f"{k} {v:.2g}" for k, v in misfit.items())
        + ")"
        if misfit
        else ""
    )
    return (
        f"latent state {info['latent']}{host}: {info['verdict']}; log evidence by branch: {branches} "
        f"({record} {info['noise_std_of_average']:.3g})"
    )


def _cmd_validate(args) -> int:
    from ._model import IdentifiedModel
    from ._validate.validate import validate_model

    _outputs(args, [args.model, *args.data])
    model = IdentifiedModel.load(args.model)
    channels = [o.name for o in model.observation if o.state is None]
    # a record may hold any of the model's channels: the states it lacks start as unknowns or from the others
    optional = tuple(model.state_names) + tuple(channels)
    records = [
        _read(args, path, list(model.state_names) + channels, model.input_names, optional=optional)
        for path in args.data
    ]
    results = []
    for path, traj in zip(args.data, records):
        try:
            result = validate_model(model, traj, n_band=args.band, interpolation=args.interpolation)
        except SymsblError as err:  # name the option, not the keyword behind it
            raise type(err)(str(err).replace("n_band:", "--band:", 1)) from None
        print(f"{path}:\n" + result.message if len(records) > 1 else result.message)
        results.append(result)
    if args.json is not None:
        docs = [_validation_doc(r) for r in results]
        if len(docs) == 1:
            _write_json(args.json, docs[0])
        else:
            worst = "diverged" if any(r.status != "ok" for r in results) else "ok"
            _write_json(
                args.json, {"status": worst, "records": [dict(data=str(p), **d) for p, d in zip(args.data, docs)]}
            )
    if args.plot is not None:
        from .plots import figure2

        _save_figure(figure2(model, results[0]), args.plot)
        print(f"figure written to {args.plot}" + (f" (for {args.data[0]})" if len(records) > 1 else ""))
    return 0 if all(r.status == "ok" for r in results) else 1


def _validation_doc(result) -> dict:
    """What ``validate --json`` writes of one record's validation."""
    return {
        "status": result.status,
        "diverged_at": result.diverged_at,
        "nrmse": result.nrmse,
        "fit": result.fit,
        **({} if result.coverage is None else {"coverage": result.coverage, "noise_std": result.noise_std}),
        **({} if result.horizon is None else {"horizon": result.horizon, "short_nrmse": result.short_nrmse}),
    }


def _cmd_discrepancy(args) -> int:
    from ._base.outputs import same_file
    from ._discrepancy import catalogue, discrepancy
    from ._discrepancy.inputs import describe_effects, read_effects

    effects = catalogue(read_effects(args.effects) if args.effects else ())
    if args.list_effects:
        print(describe_effects(effects))
        return 0
    for value, name in ((args.data, "DATA"), (args.states, "--states"), (args.base, "--base")):
        if not value:
            raise DataError(expected(name, "a value (or --list-effects alone)", "none", raw=True))
    states, inputs = _names(args.states), _names(args.inputs)
    _outputs(args, [args.data, args.held_out, args.effects])
    if args.held_out is not None and (args.held_out == "" or same_file(args.held_out, args.data)):
        raise DataError(
            expected(
                "--held-out",
                "a record other than DATA (errors on the data a model was fitted to say nothing of how it predicts)",
                repr(args.held_out) + ", which is DATA" * (args.held_out != ""),
                "leave --held-out out to hold out the last 30 % of DATA",
                raw=True,
            )
        )
    # displacement or acceleration only: the pairs' other states estimated
    columns, optional = states + _accelerations(states, args.kinematics), _unmeasured_allowed(states, args.kinematics)
    traj = _read(args, args.data, columns, inputs, optional=optional)
    heldout = _read(args, args.held_out, columns, inputs, optional=optional) if args.held_out else None
    report = discrepancy(
        traj,
        args.base,
        heldout=heldout,
        error=args.error,
        effects=effects,
        kinematics=args.kinematics or None,
        evidence=args.evidence,
        search_library=not args.no_library,
    )
    print(report)
    if args.json is not None:
        _write_json(args.json, report.to_json())
        print(f"report written to {args.json}")
    if args.plot is not None:
        from .plots import discrepancy_figure

        _save_figure(discrepancy_figure(report, heldout), args.plot)
        print(f"figure written to {args.plot}")
    return 0


def _cmd_demo(args) -> int:
    from ._demo import run_demo, write_figures

    if args.seed < 0:
        raise LibraryError(expected("--seed", "an integer >= 0", args.seed))
    _outputs(args, [])
    results = run_demo(seed=args.seed, quick=args.quick, refine=not args.no_refine)
    if args.plots:
        for path in write_figures(results, args.plots, seed=args.seed):
            print(f"figure written to {path}")
    return 0


def _data_options(p, *, states: bool = True, optional: bool = False, several: bool = False) -> None:
    if several:
        p.add_argument(
            "data",
            nargs="+",
            help="one or several records (CSV with a header row, .npz or .mat), "
            "fitted together, each with its own initial state and noise level",
        )
    else:
        p.add_argument("data", nargs="?" if optional else None, help="CSV with a header row, .npz or .mat")
    if states:
        p.add_argument(
            "--states",
            required=not optional,
            help="comma-separated state columns, e.g. x1,x2; identify takes a state DATA lacks for unmeasured (a "
            "member of a --kinematics pair) or latent (a law of its own: the upper of two tanks)",
        )
        p.add_argument("--inputs", default="", help="comma-separated input columns, e.g. F")
    p.add_argument("--time", default="t", help="time column (default: t; '' for none, then --fs is needed)")
    p.add_argument(
        "--fs",
        type=float,
        default=None,
        metavar="HZ",
        help="sample rate: builds the time grid when there is no time column, or replaces a "
        "time column rounded to a coarse resolution",
    )


def _add_identify(sub, common) -> None:
    p = sub.add_parser("identify", parents=[common], help="identify equations of motion from one or several data files")
    _data_options(p, several=True)
    _add_identify_model(p)
    _add_identify_refine(p)
    _add_identify_outputs(p)
    p.set_defaults(func=_cmd_identify)


def _add_identify_model(p) -> None:
    """Add the options that set up the candidate library, the derivatives and the modelled channels."""
    from ._derivatives.registry import DIFFERENTIATORS

    p.add_argument(
        "--library",
        default="paper",
        help="'paper' (Eq. 21), 'poly', or a .py file defining `library` (its Python runs)",
    )
    p.add_argument(
        "--degree",
        type=int,
        default=None,
        help="polynomial degree >= 1 (default: 3, and 4 for an equation whose law needs it, where the degree-4 "
        "library holds at most 500 candidates and the records more regression rows than its candidates)",
    )
    p.add_argument(
        "--derivative", default="weak", choices=list(DIFFERENTIATORS), help="how targets are built (default: weak)"
    )
    p.add_argument(
        "--overlap",
        type=int,
        default=1,
        metavar="Q",
        help="weak form: test functions per window length (default: 1, windows apart; 2: half overlap, "
        "rows whitened for the noise correlation they share)",
    )
    p.add_argument(
        "--kinematics",
        default="",
        metavar="X:V[:A][,...]",
        help="position:velocity pairs with x' = v exactly (fixed, not identified), each with the column of "
        "an accelerometer that measures v' as a third name if there is one; any member may be absent "
        "from DATA (unmeasured), e.g. --kinematics y:v or x1:v1:a1,x2:v2:a2",
    )
    p.add_argument(
        "--outputs",
        default="",
        metavar="NAME[,...]",
        help="columns with an equation of their own over the library (a force cell), identified with the "
        "states, e.g. --outputs Fc",
    )


def _add_identify_refine(p) -> None:
    """Add the options of the output-error refinement and of the structure selection."""
    p.add_argument(
        "--no-refine",
        action="store_true",
        help="stop at the equation-error fit (default: refine every coefficient by output error)",
    )
    p.add_argument(
        "--interpolation",
        default=None,
        choices=list(INTERPOLATIONS),
        help="how the inputs run between samples while refining (default: cubic, periodic when a state "
        "is latent; hold: a digital controller's stepped output)",
    )
    p.add_argument(
        "--noise",
        default="auto",
        type=_noise_option,
        metavar="{auto,white,0..8}",
        help="output-error noise model: auto (default: an autoregressive filter per measured channel, its "
        "order by BIC, white when the residual is), white, or an order",
    )
    p.add_argument(
        "--selection",
        default="validated",
        choices=["validated", "evidence"],
        help="how the structure is chosen from the model path: validated (default: from the simplest, a "
        "richer structure only where it lowers the cross-validated free-run error by more than one "
        "standard error and by a tenth of its gap to the noise floor) or evidence",
    )
    p.add_argument(
        "--doubts",
        default="adapt",
        choices=["adapt", "report"],
        help="when the residual tests doubt output error's likelihood: adapt (default: refit on short "
        "segments; in a closed loop report the equation-error model) or report (warn only)",
    )


def _add_identify_outputs(p) -> None:
    """Add the options that print the model path and write the model and its figure."""
    p.add_argument(
        "--path",
        action="store_true",
        help="print the model path: each candidate structure with its evidence and cross-validated error",
    )
    p.add_argument("--json", help="write the identified model as JSON to this file")
    p.add_argument(
        "--plot",
        metavar="FILE",
        help="write the model path (cross-validated error against the number "
        "of terms) and the residual tests to FILE, e.g. path.png (needs matplotlib)",
    )


def _noise_option(text: str):
    """``--noise``: auto, white or an autoregressive order (the order as a number; :class:`RefineOptions` checks
    the value)."""
    return int(text) if text.strip().isdigit() else text


def _add_validate(sub, common) -> None:
    p = sub.add_parser(
        "validate",
        aliases=["simulate"],
        parents=[common],
        help="re-simulate a saved model on a data file and print its errors",
    )
    p.add_argument("model", help="model JSON written by `symsbl identify --json`")
    _data_options(p, states=False, several=True)
    p.add_argument(
        "--json", help="write the errors as JSON to this file (several DATA: one entry per record under 'records')"
    )
    p.add_argument(
        "--band",
        type=int,
        default=0,
        metavar="N",
        help="Monte Carlo draws for the 3-sigma predictive band; prints the share of samples inside it "
        "(default: 0, no band)",
    )
    p.add_argument(
        "--interpolation",
        default=None,
        choices=list(INTERPOLATIONS),
        help="how the inputs run between samples (default: as the model was refined, else cubic)",
    )
    p.add_argument(
        "--plot",
        metavar="FILE",
        help="write the paper's Figure 2 for this record to FILE, e.g. fig.png (needs matplotlib)",
    )
    p.set_defaults(func=_cmd_validate)


def _add_discrepancy(sub, common) -> None:
    from ._discrepancy.design import ERROR_MEASURES

    p = sub.add_parser(
        "discrepancy", parents=[common], help="find the physical effect a model is missing, add it, show the gain"
    )
    _data_options(p, optional=True)
    p.add_argument("--base", help='starting model per state, e.g. "x1: x2; x2: F, x1, x2" (1: offset)')
    p.add_argument(
        "--kinematics",
        default="",
        metavar="X:V[,...]",
        help="position:velocity pairs to search, e.g. x1:v1,x2:v2 (default: every base equation 'x: v'); "
        "effects between coupled pairs are searched too; a velocity absent from DATA is unmeasured "
        "(output-error evidence fits the positions alone)",
    )
    p.add_argument(
        "--effects",
        metavar="FILE",
        help="user effects, one 'name: expression' line each in x and v "
        "(displacement, velocity of a pair), optionally '; dissipative'",
    )
    p.add_argument("--list-effects", action="store_true", help="print the catalogue (with --effects) and exit")
    p.add_argument(
        "--evidence",
        default=None,
        choices=["output-error", "equation-error"],
        help="how effects are scored (default: output-error; equation-error with --error equation)",
    )
    p.add_argument(
        "--no-library",
        action="store_true",
        help="search the catalogue only (default: library terms outside it are tried too)",
    )
    p.add_argument("--held-out", help="held-out record (default: the last 30 %% of DATA)")
    p.add_argument(
        "--error", default="simulation", choices=list(ERROR_MEASURES), help="held-out error (default: simulation)"
    )
    p.add_argument("--json", help="write the report as JSON to this file")
    p.add_argument(
        "--plot",
        metavar="FILE",
        help="write the before/after, residual-map and evidence figure to FILE, e.g. report.png (needs matplotlib)",
    )
    p.set_defaults(func=_cmd_discrepancy)


def _version() -> str:
    """The installed distribution's version (the one version source: pyproject.toml)."""
    from importlib import metadata

    try:
        return metadata.version("symsbl")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``symsbl`` command."""
    parser = _Parser(
        prog="symsbl",
        description="Sparse Bayesian identification of nonlinear ODEs from sampled data.",
        epilog="exit codes: " + "; ".join(f"{k} {v}" for k, v in EXIT_CODES.items()),
    )
    parser.add_argument("--version", action="version", version=f"symsbl {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    common = _Parser(add_help=False)  # a parent: only its arguments are copied
    common.add_argument(
        "--quiet",
        action="store_true",
        help="no progress lines (they are shown only on a terminal, for steps longer than 0.5 s)",
    )
    _add_identify(sub, common)
    _add_validate(sub, common)
    _add_discrepancy(sub, common)
    p = sub.add_parser("demo", parents=[common], help="the paper's five systems end to end")
    p.add_argument("--seed", type=int, default=0, help="noise seed >= 0 (default: 0)")
    p.add_argument("--quick", action="store_true", help="shorter records (for a fast check)")
    p.add_argument(
        "--no-refine",
        action="store_true",
        help="the equation-error models only (default: refined by output error, both shown)",
    )
    p.add_argument(
        "--plots", metavar="DIR", help="write the paper's Figure 2 for each system as PNG into DIR (needs matplotlib)"
    )
    p.set_defaults(func=_cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``symsbl`` console script; returns the exit code (see :data:`EXIT_CODES`)."""
    from ._base.interrupt import command_started

    command_started()
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2), already printed in one line
        return exc.code if isinstance(exc.code, int) else 2
    except KeyboardInterrupt:
        return _fail("", "interrupted", 130)
    return run_command(args.command, lambda: args.func(args), quiet=args.quiet)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
