"""Malformed input, tried as a hostile new user would: every failure is one line with its exit code.

The battery runs the command line in process (``symsbl._cli.main``) on broken files and options and
matches each error message exactly; model files and ``--base`` strings carrying code must never run
it; random corruption of a CSV file and random mutations of a model file must end in a result or a
one-line :class:`symsbl.SymsblError`, never a traceback, and never change an input file.
"""

import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import exactly
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import symsbl
from symsbl._cli import EXIT_CODES, main

CANARY = "symsbl_canary_{}"


@pytest.fixture(scope="module")
def files(tmp_path_factory, duffing_short):
    d = tmp_path_factory.mktemp("malformed")
    train = duffing_short
    symsbl.write_trajectory(train, d / "train.csv")
    symsbl.write_trajectory(train, d / "train.npz")
    code = main(
        [
            "identify",
            str(d / "train.csv"),
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--library",
            "poly",
            "--json",
            str(d / "model.json"),
            "--quiet",
        ]
    )
    assert code == 0
    return d


def _digest(directory: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(directory.iterdir()) if p.is_file()}


def run(argv, capsys):
    code = main(
        [*argv, "--quiet"] if argv and argv[0] in ("identify", "validate", "simulate", "discrepancy", "demo") else argv
    )
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _dead_input(d: Path) -> Path:
    data = np.loadtxt(d / "train.csv", delimiter=",", skiprows=1)
    data[:, 3] = 0.0
    np.savetxt(d / "dead.csv", data, delimiter=",", header="t,x1,x2,F", comments="", fmt="%.17g")
    return d / "dead.csv"


#: (name, files to make, argv with {d} for the folder, exit code, the one line on stderr)
CLI_CASES = [
    (
        "unknown derivative",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--derivative", "spline"],
        2,
        "symsbl identify: error: argument --derivative: invalid choice: 'spline' (choose from 'weak', 'central', "
        "'point', 'savgol')",
    ),
    (
        "derivative in capitals",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--derivative", "WEAK"],
        2,
        "symsbl identify: error: argument --derivative: invalid choice: 'WEAK' (choose from 'weak', 'central', "
        "'point', 'savgol')",
    ),
    (
        "degree 0",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--inputs", "F", "--degree", "0"],
        2,
        "symsbl identify: error: --degree: expected an integer >= 1, received 0",
    ),
    (
        "degree 100",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--inputs", "F", "--degree", "100"],
        2,
        "symsbl identify: error: degree: expected a library of at most 5000 candidate terms, received 4598126 terms "
        "(degree 100 in 4 variables; their Gram matrix alone would take 1.58e+05 GiB); lower the degree or use fewer "
        "variables",
    ),
    (
        "degree not a number",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--degree", "abc"],
        2,
        "symsbl identify: error: argument --degree: invalid int value: 'abc'",
    ),
    (
        "json over the data",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--json", "{d}/train.csv"],
        2,
        "symsbl identify: error: --json: expected an output file other than the inputs, received '{d}/train.csv', "
        "which is the input '{d}/train.csv'; choose another file name; inputs are never modified",
    ),
    (
        "json over a symbolic link to the data",
        "link",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--json", "{d}/link.csv"],
        2,
        "symsbl identify: error: --json: expected an output file other than the inputs, received '{d}/link.csv', "
        "which is the input '{d}/train.csv'; choose another file name; inputs are never modified",
    ),
    (
        "json over a hard link to the data",
        "hardlink",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--json", "{d}/hard.csv"],
        2,
        "symsbl identify: error: --json: expected an output file other than the inputs, received '{d}/hard.csv', "
        "which is the input '{d}/train.csv'; choose another file name; inputs are never modified",
    ),
    (
        "json into a directory",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--json", "{d}"],
        2,
        "symsbl identify: error: --json: expected a file path, received '{d}', which is a directory",
    ),
    (
        "json in a missing directory",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--json", "{d}/no/such/m.json"],
        2,
        "symsbl identify: error: --json: expected a file in an existing directory, received '{d}/no/such/m.json'; "
        "create '{d}/no/such' first",
    ),
    (
        "validate json over the model",
        None,
        ["validate", "{d}/model.json", "{d}/train.csv", "--json", "{d}/model.json"],
        2,
        "symsbl validate: error: --json: expected an output file other than the inputs, received '{d}/model.json', "
        "which is the input '{d}/model.json'; choose another file name; inputs are never modified",
    ),
    (
        "simulate (alias) json over the data",
        None,
        ["simulate", "{d}/model.json", "{d}/train.npz", "--json", "{d}/train.npz"],
        2,
        "symsbl simulate: error: --json: expected an output file other than the inputs, received '{d}/train.npz', "
        "which is the input '{d}/train.npz'; choose another file name; inputs are never modified",
    ),
    (
        "discrepancy json over the data",
        None,
        [
            "discrepancy",
            "{d}/train.csv",
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--base",
            "x1: x2; x2: F, x1, x2",
            "--json",
            "{d}/train.csv",
        ],
        2,
        "symsbl discrepancy: error: --json: expected an output file other than the inputs, received '{d}/train.csv', "
        "which is the input '{d}/train.csv'; choose another file name; inputs are never modified",
    ),
    (
        "empty json path",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--json", ""],
        2,
        "symsbl identify: error: --json: expected a file path, received ''; name the file to write",
    ),
    (
        "discrepancy json and plot on one file",
        None,
        [
            "discrepancy",
            "{d}/train.csv",
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--base",
            "x1: x2; x2: F, x1, x2",
            "--json",
            "{d}/r.png",
            "--plot",
            "{d}/r.png",
        ],
        2,
        "symsbl discrepancy: error: --plot: expected a file other than --json's, received '{d}/r.png', which --json "
        "writes too; give each output its own file",
    ),
    (
        "json through a link into a missing directory",
        "dangling",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--json", "{d}/dangling.json"],
        2,
        "symsbl identify: error: --json: expected a file in an existing directory, received '{d}/dangling.json' (a "
        "symbolic link to '{d}/nowhere/m.json'); create '{d}/nowhere' first",
    ),
    (
        "json into a socket",
        "socket",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--json", "{d}/sock"],
        2,
        "symsbl identify: error: --json: expected a file, a FIFO or a character device, received '{d}/sock', which is "
        "a socket; choose a file name",
    ),
    (
        "overlap beyond the record",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--inputs", "F", "--overlap", "100000"],
        2,
        "symsbl identify: error: --overlap: expected at most 2048 for a record of 4097 samples (a window spans "
        "at least 2 x overlap sample intervals), received 100000; use 2 (half overlap) or 3",
    ),
    (
        "overlap whose rows cannot be whitened",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--inputs", "F", "--overlap", "8"],
        2,
        "symsbl identify: error: --overlap: expected an overlap whose rows a filter of at most 4096 taps whitens, "
        "received 8 (with windows every 4 samples the noise the rows share is singular to rounding); use 2 (half "
        "overlap) or 3",
    ),
    (
        "a model term that divides by zero",
        "div0",
        ["validate", "{d}/div0.json", "{d}/train.csv"],
        2,
        "symsbl validate: error: model JSON.equations[1].terms[0].term: expected a term that is finite where its "
        "variables are, received 'x1/0', which divides by zero; correct or remove the term",
    ),
    (
        "a coefficient of 400 digits",
        "numbers",
        ["validate", "{d}/coef400.json", "{d}/train.csv"],
        2,
        "symsbl validate: error: model JSON.equations[1].terms[0].coef: expected a number within a float's range "
        "(magnitude below 1.8e+308), received an integer of 400 digits; correct the number; a model file holds the "
        "floats symsbl wrote",
    ),
    (
        "a log evidence of 400 digits",
        "numbers",
        ["validate", "{d}/evidence400.json", "{d}/train.csv"],
        2,
        "symsbl validate: error: model JSON.equations[1].log_evidence: expected a number within a float's range "
        "(magnitude below 1.8e+308), received an integer of 400 digits; correct the number; a model file holds the "
        "floats symsbl wrote",
    ),
    (
        "a coefficient of 5001 digits",
        "numbers",
        ["validate", "{d}/coef5001.json", "{d}/train.csv"],
        2,
        "symsbl validate: error: model JSON.equations[1].terms[0].coef: expected a number within a float's range "
        "(magnitude below 1.8e+308), received an integer of 5001 digits; correct the number; a model file holds the "
        "floats symsbl wrote",
    ),
    (
        "a base term that divides by zero",
        None,
        ["discrepancy", "{d}/train.csv", "--states", "x1,x2", "--inputs", "F", "--base", "x1: x2; x2: F, x1/(1-1)"],
        2,
        "symsbl discrepancy: error: --base (state 'x2'): expected a term that is finite where its variables are, "
        "received 'x1/(1-1)', which divides by zero; correct or remove the term",
    ),
    (
        "a band of a billion draws",
        None,
        ["validate", "{d}/model.json", "{d}/train.csv", "--band", "1000000000"],
        2,
        "symsbl validate: error: --band: expected at most 10000 Monte Carlo draws for 4097 samples of 2 channels "
        "(2 GiB held at once), received 1000000000; 100 draws give the 3-sigma band to about 7 %, 1000 to about 2 %",
    ),
    (
        "held-out record that is DATA",
        "link",
        [
            "discrepancy",
            "{d}/train.csv",
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--base",
            "x1: x2; x2: F, x1, x2",
            "--held-out",
            "{d}/link.csv",
        ],
        2,
        "symsbl discrepancy: error: --held-out: expected a record other than DATA (errors on the data a model was "
        "fitted to say nothing of how it predicts), received '{d}/link.csv', which is DATA; leave --held-out out to "
        "hold out the last 30 % of DATA",
    ),
    (
        "empty held-out path",
        None,
        [
            "discrepancy",
            "{d}/train.csv",
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--base",
            "x1: x2; x2: F, x1, x2",
            "--held-out",
            "",
        ],
        2,
        "symsbl discrepancy: error: --held-out: expected a record other than DATA (errors on the data a model was "
        "fitted to say nothing of how it predicts), received ''; leave --held-out out to hold out the last 30 % of "
        "DATA",
    ),
    (
        "a directory as DATA",
        "folder",
        ["identify", "{d}/folder.csv", "--states", "x1,x2"],
        2,
        "symsbl identify: error: {d}/folder.csv: expected an existing data file, received a directory",
    ),
    (
        "a socket as DATA",
        "socket data",
        ["identify", "{d}/sock.csv", "--states", "x1,x2"],
        2,
        "symsbl identify: error: {d}/sock.csv: expected an existing data file, received a device or socket, not a file",
    ),
    (
        "plot with an unknown extension",
        None,
        ["validate", "{d}/model.json", "{d}/train.csv", "--plot", "{d}/x.xyz"],
        2,
        "symsbl validate: error: --plot: expected a file ending in one of ['.png', '.pdf', '.svg', '.jpg', '.jpeg', "
        "'.eps', '.ps', '.tif', '.tiff', '.webp'], received '{d}/x.xyz'",
    ),
    (
        "demo with a negative seed",
        None,
        ["demo", "--seed", "-1"],
        2,
        "symsbl demo: error: --seed: expected an integer >= 0, received -1",
    ),
    (
        "demo plots into a file",
        None,
        ["demo", "--plots", "{d}/train.csv"],
        2,
        "symsbl demo: error: --plots: expected a directory (created if missing), received '{d}/train.csv', which is a "
        "file",
    ),
    (
        "negative sample rate",
        None,
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--fs", "-3"],
        2,
        "symsbl identify: error: fs: expected a positive sample rate in Hz, received -3.0",
    ),
    (
        "missing data file",
        None,
        ["identify", "{d}/nope.csv", "--states", "x1,x2"],
        2,
        "symsbl identify: error: {d}/nope.csv: expected an existing data file, received no such file",
    ),
    (
        "binary bytes in a CSV",
        "garbage",
        ["identify", "{d}/garbage.csv", "--states", "x1,x2"],
        2,
        "symsbl identify: error: {d}/garbage.csv: expected a text CSV file, received binary content (NUL bytes); "
        "export the record as CSV text, .npz or .mat",
    ),
    (
        "garbage in an npz",
        "garbage",
        ["identify", "{d}/garbage.npz", "--states", "x1,x2"],
        2,
        "symsbl identify: error: {d}/garbage.npz: expected a readable .npz file (a zip archive written by "
        "numpy.savez), received a file that is not a zip archive",
    ),
    (
        "garbage in a mat",
        "garbage",
        ["identify", "{d}/garbage.mat", "--states", "x1,x2"],
        2,
        "symsbl identify: error: {d}/garbage.mat: expected a readable MATLAB .mat file (v4-v7.2), received an "
        "unreadable file (MatReadError: Mat file appears to be truncated); save with -v7 or export CSV",
    ),
    (
        "library file that raises",
        "libraries",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--library", "{d}/raises.py"],
        2,
        "symsbl identify: error: --library '{d}/raises.py': expected a Python file that runs, received "
        "RuntimeError: boom",
    ),
    (
        "library file with a syntax error",
        "libraries",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--library", "{d}/syntax.py"],
        2,
        "symsbl identify: error: --library '{d}/syntax.py': expected a Python file that runs, received SyntaxError: "
        "invalid syntax (syntax.py, line 1)",
    ),
    (
        "library file that calls sys.exit",
        "libraries",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--library", "{d}/exits.py"],
        2,
        "symsbl identify: error: --library '{d}/exits.py': expected a file that defines `library`, received a file "
        "that called sys.exit(0)",
    ),
    (
        "library file that raises a BaseException of its own",
        "libraries",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--library", "{d}/stops.py"],
        2,
        "symsbl identify: error: --library '{d}/stops.py': expected a Python file that runs, received Stop: halt",
    ),
    (
        "library file that raises KeyboardInterrupt, as Ctrl-C does",
        "libraries",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--library", "{d}/interrupted.py"],
        130,
        "symsbl identify: error: interrupted",
    ),
    (
        "library function that calls sys.exit",
        "libraries",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--inputs", "F", "--library", "{d}/exits_later.py"],
        2,
        "symsbl identify: error: --library '{d}/exits_later.py': expected library(states, inputs) returning a "
        "Library, received a file that called sys.exit(3)",
    ),
    (
        "library file of 1140 terms",
        "libraries",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--inputs", "F", "--library", "{d}/wide.py"],
        2,
        "symsbl identify: error: --library '{d}/wide.py': expected at most 1000 terms in all (the most a model file "
        "holds: every term is ranked and compiled before any fit), received 1140; use fewer terms, or --library poly "
        "or paper with --degree for a larger polynomial library",
    ),
    (
        "library file of 13109 expression nodes",
        "libraries",
        ["identify", "{d}/train.csv", "--states", "x1,x2", "--inputs", "F", "--library", "{d}/deep.py"],
        2,
        "symsbl identify: error: --library '{d}/deep.py': expected at most 12000 expression nodes in all (the most a "
        "model file holds: every term is ranked and compiled before any fit), received 13109; use fewer or smaller "
        "terms",
    ),
    (
        "effects file of 1001 effects",
        "effects",
        ["discrepancy", "{d}/train.csv", "--states", "x1,x2", "--base", "x1: x2; x2: x1", "--effects", "{d}/many.txt"],
        2,
        "symsbl discrepancy: error: --effects {d}/many.txt: expected at most 1000 effects in all (the most a model "
        "file holds: every effect is scored as a candidate term), received 1001; use fewer or smaller effects",
    ),
    (
        "effects file of 18399 expression nodes",
        "effects",
        ["discrepancy", "{d}/train.csv", "--states", "x1,x2", "--base", "x1: x2; x2: x1", "--effects", "{d}/heavy.txt"],
        2,
        "symsbl discrepancy: error: --effects {d}/heavy.txt: expected at most 12000 expression nodes in all (the most "
        "a model file holds: every effect is scored as a candidate term), received 18399; use fewer or smaller "
        "effects",
    ),
    (
        "dead-sensor input",
        "dead",
        ["identify", "{d}/dead.csv", "--states", "x1,x2", "--inputs", "F"],
        2,
        "symsbl identify: error: input 'F': expected a column that varies, received a constant 0; remove it from the "
        "inputs (a dead sensor?); a free decay needs no input column",
    ),
    (
        "discrepancy with a dead-sensor input",
        "dead",
        ["discrepancy", "{d}/dead.csv", "--states", "x1,x2", "--inputs", "F", "--base", "x1: x2; x2: F, x1, x2"],
        2,
        "symsbl discrepancy: error: input 'F': expected a column that varies, received a constant 0; remove it from "
        "the inputs (a dead sensor?); a free decay needs no input column",
    ),
    (
        "unknown error measure",
        None,
        ["discrepancy", "{d}/train.csv", "--states", "x1,x2", "--base", "x1: x2; x2: x1", "--error", "rms"],
        2,
        "symsbl discrepancy: error: argument --error: invalid choice: 'rms' (choose from 'simulation', 'equation')",
    ),
    (
        "no state in the data",
        None,
        ["identify", "{d}/train.csv", "--states", "y1,y2", "--inputs", "F"],
        2,
        "symsbl identify: error: --states: expected at least one column of DATA, received none of y1,y2",
    ),
    (
        "discrepancy: a velocity left out without its pair",
        None,
        ["discrepancy", "{d}/train.csv", "--states", "x1,v1", "--inputs", "F", "--base", "x1: v1; v1: F, x1, v1"],
        2,
        "symsbl discrepancy: error: --states v1: expected a column of DATA, received no such column; if v1 is an "
        "unmeasured velocity, declare its pair: --kinematics <position>:v1",
    ),
    (
        "missing required option",
        None,
        ["identify", "{d}/train.csv"],
        2,
        "symsbl identify: error: the following arguments are required: --states",
    ),
    ("no command", None, [], 2, "symsbl: error: the following arguments are required: command"),
]


def _make(d: Path, kind: str | None) -> None:
    if kind == "link" and not (d / "link.csv").exists():
        (d / "link.csv").symlink_to(d / "train.csv")
    elif kind == "hardlink" and not (d / "hard.csv").exists():
        os.link(d / "train.csv", d / "hard.csv")
    elif kind == "garbage":
        for ext in (".csv", ".npz", ".mat"):
            (d / f"garbage{ext}").write_bytes(b"garbage\x00\x01\x02\xff")
    elif kind == "libraries":
        _write(d / "raises.py", "raise RuntimeError('boom')\n")
        _write(d / "syntax.py", "def f(:\n")
        _write(d / "exits.py", "import sys\nsys.exit(0)\n")
        _write(d / "stops.py", "class Stop(BaseException):\n    pass\n\n\nraise Stop('halt')\n")
        _write(d / "interrupted.py", "raise KeyboardInterrupt\n")
        _write(d / "exits_later.py", "import sys\n\n\ndef library(states, inputs):\n    sys.exit(3)\n")
        polynomial = "import symsbl\n\nlibrary = symsbl.polynomial(symsbl.symbols('x1 x2 F'), {})\n"
        _write(d / "wide.py", polynomial.format(17))  # 1140 terms
        _write(d / "deep.py", polynomial.format(16))  # 969 terms, 13109 nodes
    elif kind == "effects":
        _write(d / "many.txt", "".join(f"e{k}: tanh(x/{k + 1}.0)\n" for k in range(1001)))
        terms = ("+".join(f"sin({j + 1}*x+{k}*v)*v**{j % 4}" for j in range(25)) for k in range(100))
        _write(d / "heavy.txt", "".join(f"e{k}: {t}\n" for k, t in enumerate(terms)))  # 184 nodes each
    elif kind == "dead":
        _dead_input(d)
    elif kind == "dangling" and not (d / "dangling.json").is_symlink():
        (d / "dangling.json").symlink_to(d / "nowhere" / "m.json")
    elif kind in ("socket", "socket data"):
        import socket

        where = d / ("sock" if kind == "socket" else "sock.csv")
        if not where.exists():
            with socket.socket(socket.AF_UNIX) as server:  # the socket file stays once it is closed
                server.bind(str(where))
    elif kind == "folder":
        (d / "folder.csv").mkdir(exist_ok=True)
    elif kind == "numbers":  # integers written out in full, as a hand edit or another tool might
        doc = json.loads((d / "model.json").read_text())
        for name, path, digits in (
            ("coef400", ("equations", 1, "terms", 0, "coef"), 400),
            ("evidence400", ("equations", 1, "log_evidence"), 400),
            ("coef5001", ("equations", 1, "terms", 0, "coef"), 5001),
        ):
            edited = json.loads(json.dumps(doc))
            _set(edited, path, "DIGITS")
            (d / f"{name}.json").write_text(json.dumps(edited).replace('"DIGITS"', "1" + "0" * (digits - 1)))
    elif kind == "div0":
        doc = json.loads((d / "model.json").read_text())
        doc["equations"][1]["terms"][0]["term"] = "x1/0"
        del doc["equations"][1]["rhs"]
        (d / "div0.json").write_text(json.dumps(doc))


@pytest.mark.parametrize("name, kind, argv, code, line", CLI_CASES, ids=[c[0] for c in CLI_CASES])
def test_every_cli_failure_is_one_line_with_its_exit_code(files, capsys, name, kind, argv, code, line):
    _make(files, kind)
    before = _digest(files)
    got, _, err = run([a.format(d=files) for a in argv], capsys)
    assert got == code and code in EXIT_CODES
    assert err == line.format(d=files) + "\n", err
    assert _digest(files) == before  # no input changed, no output left behind


PAYLOAD = "__import__('os').system('touch {canary}')"


def _model_doc(files) -> dict:
    return json.loads((files / "model.json").read_text())


def _string_fields(doc, path=()):
    """Every (path, value) of a string in the model document."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _string_fields(v, path + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _string_fields(v, path + (i,))
    elif isinstance(doc, str):
        yield path, doc


def _set(doc, path, value):
    for key in path[:-1]:
        doc = doc[key]
    doc[path[-1]] = value


def test_code_planted_in_any_string_field_of_a_model_file_never_runs(files, tmp_path, capsys):
    doc = _model_doc(files)
    fields = list(_string_fields(doc))
    assert len(fields) > 10
    for k, (path, value) in enumerate(fields):
        canary = tmp_path / CANARY.format(k)
        planted = json.loads(json.dumps(doc))
        _set(planted, path, value + " + " + PAYLOAD.format(canary=canary))
        model_file = tmp_path / f"planted{k}.json"
        model_file.write_text(json.dumps(planted))
        code, _, err = run(["validate", str(model_file), str(files / "train.csv")], capsys)
        assert not canary.exists(), path
        assert err.count("\n") <= 1, err
        # fields symsbl only displays (alternatives, metadata, the model path) may hold any text; the others are
        # refused
        if path[0] not in ("metadata", "path") and "alternatives" not in path:
            assert code == 2 and err.startswith("symsbl validate: error: model JSON"), (path, err)


def test_code_planted_in_the_base_model_never_runs(files, tmp_path, capsys):
    canary = tmp_path / CANARY.format("base")
    base = f"x1: x2; x2: F, x1, {PAYLOAD.format(canary=canary)}"
    code, _, err = run(
        ["discrepancy", str(files / "train.csv"), "--states", "x1,x2", "--inputs", "F", "--base", base], capsys
    )
    assert code == 2 and not canary.exists()
    assert err == (
        "symsbl discrepancy: error: --base (state 'x2'): expected a term such as x1**2*Abs(x2), received "
        f'{PAYLOAD.format(canary=canary)!r}: the character "\'" at position 11 is not part of the '
        "grammar; use numbers, the variable names, + - * / ** and the listed functions\n"
    )


MODEL_CASES = [
    (
        "a string coefficient",
        lambda d: _set(d, ("equations", 1, "terms", 0, "coef"), "1.0"),
        "model JSON.equations[1].terms[0].coef: expected a finite number, received '1.0'",
    ),
    (
        "a NaN coefficient",
        lambda d: _set(d, ("equations", 1, "terms", 0, "coef"), float("nan")),
        "model JSON.equations[1].terms[0].coef: expected a finite number, received nan",
    ),
    (
        "a covariance of the wrong shape",
        lambda d: _set(d, ("equations", 1, "covariance"), [[1.0]]),
        "model JSON.equations[1].covariance: expected a finite 4 x 4 array (one row per term), received shape (1, 1)",
    ),
    (
        "version 99",
        lambda d: _set(d, ("version",), 99),
        "model JSON.version: expected one of [1, 2], received 99; the file was written by a newer symsbl; upgrade to "
        "read it",
    ),
    (
        "an unknown fit",
        lambda d: _set(d, ("fit",), "magic"),
        "model JSON.fit: expected one of ['equation-error', 'output-error'], received 'magic'",
    ),
    (
        "a state equation twice",
        lambda d: _set(d, ("equations", 1, "lhs"), "x1"),
        "model JSON.equations[1].lhs: expected one equation per state ['x1', 'x2'], received 'x1'",
    ),
    (
        "deep nesting",
        lambda d: _set(d, ("equations", 1, "terms", 0, "term"), "(" * 300 + "x1" + ")" * 300),
        "model JSON.equations[1].terms[0].term: expected at most 50 levels of nesting, received deeper text; simplify "
        "the expression",
    ),
    (
        "attribute access",
        lambda d: _set(d, ("equations", 1, "terms", 0, "term"), "x1.__class__"),
        "model JSON.equations[1].terms[0].term: expected a term such as x1**2*Abs(x2), received 'x1.__class__': the "
        "character '.' at position 2 is not part of the grammar; use numbers, the variable names, + - * / ** and the "
        "listed functions",
    ),
    (
        "a negative std",
        lambda d: _set(d, ("equations", 1, "terms", 0, "std"), -1.0),
        "model JSON.equations[1].terms[0].std: expected a finite number >= 0 or null, received -1.0",
    ),
    (
        "not an object",
        lambda d: d.clear() or d.update({"format": "symsbl-model", "version": 2, "states": "x1"}),
        "model JSON.states: expected a list of names, received 'x1'",
    ),
    (
        "an integer no float holds",
        lambda d: _set(d, ("equations", 0, "log_evidence"), -(10**400)),
        "model JSON.equations[0].log_evidence: expected a number within a float's range (magnitude below 1.8e+308), "
        "received an integer of 401 digits; correct the number; a model file holds the floats symsbl wrote",
    ),
    (
        "20000 terms (a 1 MB file)",
        lambda d: _set(d, ("equations", 1, "terms"), [{"term": "x1", "coef": 1.0}] * 20000),
        "model JSON.equations: expected at most 1000 terms in all (the most a model of this release is re-simulated "
        "with), received 20001; a model file holds the terms an identification kept; check where this one came from",
    ),
    (
        "100 terms of 184 nodes each",
        lambda d: _heavy(d, 100),
        "model JSON.equations: expected at most 12000 expression nodes in all (the most a model of this release is "
        "re-simulated with), received 18400; a model file holds the terms an identification kept; check where this "
        "one came from",
    ),
]


def _heavy(doc, n: int):
    """``n`` terms of 184 expression nodes each in the second equation (a 54 kB file took 684 s to validate)."""
    eq = doc["equations"][1]
    eq["terms"] = [
        {"term": "+".join(f"sin({j + 1}*x1+{k}*x2)*x2**{j % 4}" for j in range(25)), "coef": 1e-12} for k in range(n)
    ]
    del eq["rhs"], eq["covariance"]
    doc.pop("covariance", None)


@pytest.mark.parametrize("name, change, message", MODEL_CASES, ids=[c[0] for c in MODEL_CASES])
def test_malformed_model_files_are_named(files, name, change, message):
    doc = _model_doc(files)
    change(doc)
    with pytest.raises(symsbl.DataError, match=exactly(message)):
        symsbl.IdentifiedModel.from_json(doc)


def test_an_edited_rhs_is_reported_not_ignored(files):
    doc = _model_doc(files)
    eq = next(e for e in doc["equations"] if e["lhs"] == "x2")
    eq["rhs"] = eq["rhs"].replace("F", "2*F", 1)
    with pytest.raises(
        symsbl.DataError,
        match=r"^model JSON\.equations\[1\]\.rhs: expected the sum of the equation's "
        r"terms, received .*; edit 'terms' \(the source of truth\) and delete "
        r"or "
        r"regenerate 'rhs'$",
    ):
        symsbl.IdentifiedModel.from_json(doc)
    del eq["rhs"]  # rhs is a redundant copy: without it the model reads from its terms
    assert symsbl.IdentifiedModel.from_json(doc).equation("x2").names == _model_names(files)


def _model_names(files):
    return symsbl.IdentifiedModel.load(files / "model.json").equation("x2").names


def _mutate(doc, rng: random.Random, canary: Path):
    """One random change to a model document: a field deleted, retyped, or replaced by a payload."""
    paths = []

    def walk(node, path):
        paths.append(path)
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, path + (k,))
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, path + (i,))

    walk(doc, ())
    path = rng.choice(paths[1:])
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    choice = rng.randrange(7)
    replacement = [None, "", PAYLOAD.format(canary=canary), 1e308, -1, [1, "x", None], {"term": "x1"}][choice]
    if rng.random() < 0.2 and isinstance(parent, dict):
        del parent[path[-1]]
    else:
        parent[path[-1]] = replacement


def test_200_random_model_mutations_never_run_code_or_crash(files, tmp_path):
    doc = _model_doc(files)
    record = symsbl.read_trajectory(files / "train.csv", states=["x1", "x2"], inputs=["F"]).slice(0, 400)
    rng = random.Random(12)
    outcomes = {"loaded": 0, "refused": 0}
    for k in range(200):
        canary = tmp_path / CANARY.format(f"mutation{k}")
        mutated = json.loads(json.dumps(doc))
        for _ in range(rng.randint(1, 3)):
            _mutate(mutated, rng, canary)
        try:
            model = symsbl.IdentifiedModel.from_json(json.dumps(mutated))
            symsbl.validate_model(model, record)
            outcomes["loaded"] += 1
        except symsbl.SymsblError as err:
            assert "\n" not in str(err)
            outcomes["refused"] += 1
        assert not canary.exists()
    assert outcomes["refused"] > 100 and outcomes["loaded"] > 5, outcomes


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_random_csv_corruption_never_gives_a_traceback_or_changes_the_file(files, tmp_path, data):
    original = (files / "train.csv").read_bytes()[:6000]
    edits = data.draw(
        st.lists(
            st.tuples(
                st.integers(0, len(original) - 1),
                st.sampled_from(["flip", "drop", "insert", "cut"]),
                st.binary(min_size=1, max_size=4),
            ),
            min_size=1,
            max_size=6,
        )
    )
    corrupted = bytearray(original)
    for pos, kind, payload in edits:
        pos = min(pos, max(len(corrupted) - 1, 0))
        if kind == "flip" and corrupted:
            corrupted[pos] ^= payload[0] or 1
        elif kind == "drop":
            del corrupted[pos : pos + len(payload)]
        elif kind == "insert":
            corrupted[pos:pos] = payload
        else:
            del corrupted[pos:]
    path = tmp_path / "corrupt.csv"
    path.write_bytes(bytes(corrupted))
    start = time.perf_counter()
    try:
        symsbl.read_trajectory(path, states=["x1", "x2"], inputs=["F"])
    except symsbl.DataError as err:
        assert "\n" not in str(err)
    assert time.perf_counter() - start < 5.0
    assert path.read_bytes() == bytes(corrupted)


def test_lab_csv_dialects_are_read(tmp_path):
    t = np.arange(64) / 1000.0
    x = np.column_stack([np.sin(20 * t), np.cos(20 * t)])
    lines = ["# exported by a logger", "t;x1;x2", "s;m;m/s"]
    for k, row in enumerate(np.column_stack([t, x])):
        if k == 10:
            lines.append("# a comment between rows")
        lines.append(";".join(repr(float(v)).replace(".", ",") for v in row))
    path = tmp_path / "lab.csv"
    path.write_bytes(b"\xef\xbb\xbf" + "\r\n".join(lines).encode())
    record = symsbl.read_trajectory(path, states=["x1", "x2"])
    np.testing.assert_array_equal(record.states, x)
    np.testing.assert_array_equal(record.t, t)
    tabbed = tmp_path / "tab.csv"
    tabbed.write_text(
        "t\tx1\tx2\n" + "\n".join("\t".join(repr(float(v)) for v in row) for row in np.column_stack([t, x]))
    )
    np.testing.assert_array_equal(symsbl.read_trajectory(tabbed, states=["x1", "x2"]).states, x)


def test_a_rounded_time_column_is_replaced_by_fs(tmp_path):
    fs = 32768.0
    t = np.round(np.arange(500) / fs, 4)  # timestamps to 0.1 ms
    x = np.column_stack([np.sin(200 * np.arange(500) / fs), np.cos(200 * np.arange(500) / fs)])
    path = tmp_path / "rounded.csv"
    np.savetxt(path, np.column_stack([t, x]), delimiter=",", header="t,x1,x2", comments="", fmt="%.17g")
    with pytest.raises(
        symsbl.DataError,
        match=r"time: expected strictly increasing values, received t = 0\.0 at "
        r"row 1 after t = 0\.0; sort the rows or pass --fs/fs",
    ):
        symsbl.read_trajectory(path, states=["x1", "x2"])
    record = symsbl.read_trajectory(path, states=["x1", "x2"], fs=fs)
    np.testing.assert_allclose(record.t, np.arange(500) / fs, atol=1e-15)
    with pytest.raises(
        symsbl.DataError,
        match=r"time column 't': expected times within one step of a uniform 1000 Hz "
        r"grid \(--fs\), received a deviation of",
    ):
        symsbl.read_trajectory(path, states=["x1", "x2"], fs=1000.0)


def test_python_api_refuses_what_it_cannot_do():
    rng = np.random.default_rng(0)
    with pytest.raises(
        symsbl.DataError,
        match=exactly(
            "rows: expected more regression rows than candidate terms (10), received 3 rows from X; use longer "
            "records, fewer candidate terms (a lower degree) or a derivative strategy with more rows"
        ),
    ):
        symsbl.RVM().fit(rng.standard_normal((3, 10)), rng.standard_normal(3))
    x1, x2 = symsbl.symbols("x1 x2")
    t = symsbl.time_grid(0.5, 1000)
    record = symsbl.Trajectory(t, np.column_stack([np.sin(9 * t), 9 * np.cos(9 * t)]), None, ("x1", "x2"))
    with pytest.raises(
        symsbl.ParameterError, match=exactly("equivalence_nats: expected a finite number >= 0.0, received -5")
    ):
        symsbl.identify(record, symsbl.polynomial([x1, x2], 1), equivalence_nats=-5)
    huge = symsbl.Trajectory(t, np.column_stack([np.sin(9 * t), 9 * np.cos(9 * t)]) * 1e300, None, ("x1", "x2"))
    with pytest.raises(symsbl.DataError, match=r"^column 'x1': expected magnitudes below 1e\+100, received "):
        symsbl.identify(huge, symsbl.polynomial([x1, x2], 1))


def test_a_term_undefined_on_some_samples_is_named_with_the_values_there(tmp_path, capsys):
    """A level that noise takes below zero under a square root: the term and the sample's values, in Python and
    on the command line (exit 2, the file unchanged)."""
    x, u = symsbl.symbols("x u")
    t = symsbl.time_grid(20.0, 400)
    level = 0.6 + 0.5 * np.sin(0.7 * t)
    level[1234] = -0.0125
    flow = 1.0 + 0.3 * np.cos(1.3 * t)
    record = symsbl.Trajectory(t, level[:, None], flow[:, None], ("x",), ("u",))
    library = symsbl.polynomial([x], 1) + symsbl.elementwise([x], ["sqrt"]) + symsbl.inputs([u])
    line = (
        "term 'sqrt(x)': expected a term defined on every sample, received nan where x = -0.0125, u = "
        f"{flow[1234]:.6g}; leave the term out of the library, or clean the record where it is undefined"
    )
    with pytest.raises(symsbl.DataError, match=exactly(line)):
        symsbl.identify(record, library)
    path = tmp_path / "level.csv"
    np.savetxt(path, np.column_stack([t, level, flow]), delimiter=",", header="t,x,u", comments="")
    (tmp_path / "lib.py").write_text(
        "import symsbl\nx, u = symsbl.symbols('x u')\n"
        "library = symsbl.polynomial([x], 1) + symsbl.elementwise([x], ['sqrt']) + symsbl.inputs([u])\n"
    )
    before = hashlib.md5(path.read_bytes()).hexdigest()
    args = ["identify", str(path), "--states", "x", "--inputs", "u", "--library", str(tmp_path / "lib.py")]
    assert main([*args, "--quiet"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"symsbl identify: error: {line}"]
    assert hashlib.md5(path.read_bytes()).hexdigest() == before


@pytest.mark.slow
def test_ctrl_c_is_one_line_and_exit_130(tmp_path):
    # as from an interactive shell: SIGINT at its default, whatever the test process inherited (a program started
    # with SIGINT ignored keeps ignoring it, as it should)
    proc = _command(["demo", "--quick"], cwd=tmp_path)
    # interrupt once the demo is running (its header is printed after the imports, which on a loaded machine
    # can take several seconds; Ctrl-C during the imports is Python's own KeyboardInterrupt)
    assert proc.stdout.readline().startswith("symsbl demo:")
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert err == "symsbl demo: error: interrupted\n"


@pytest.mark.parametrize(
    "swallow", ["returns normally", "raises a symsbl error", "raises another error", "keeps running"]
)
def test_ctrl_c_that_a_library_swallows_still_ends_the_command_as_interrupted(swallow, monkeypatch, capsys):
    """A SIGINT consumed on the way (CasADi's callbacks and overload resolution, a DM conversion) still gives one
    line and exit 130, within a second when the command would go on running."""
    import warnings

    import symsbl._cli as cli

    def command(args):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)  # the handler runs here
        except KeyboardInterrupt:
            warnings.warn("a fallback after the swallowed interrupt", UserWarning, stacklevel=1)
            if swallow == "raises a symsbl error":
                raise symsbl.SimulationError("simulation: expected a finite solution, received a failure") from None
            if swallow == "raises another error":
                raise SystemError("error return with an exception set") from None
            if swallow == "keeps running":
                time.sleep(30.0)
        return 0

    monkeypatch.setattr(cli, "_cmd_demo", command)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        start = time.monotonic()
        assert main(["demo"]) == 130
        assert time.monotonic() - start < 10.0
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)
    assert capsys.readouterr().err == "symsbl demo: error: interrupted\n"


def _lab_record(tmp_path):
    t = np.arange(64) / 1000.0
    return t, np.column_stack([np.sin(20 * t), np.cos(20 * t)])


@pytest.mark.parametrize("codec", ["utf-16", "utf-16-le", "utf-16-be"])
def test_a_utf16_spreadsheet_export_is_read(tmp_path, codec):
    t, x = _lab_record(tmp_path)
    text = "t\tx1\tx2\r\n" + "".join(f"{a!r}\t{b!r}\t{c!r}\r\n" for a, b, c in np.column_stack([t, x]).tolist())
    path = tmp_path / "unicode.csv"
    path.write_bytes(text.encode(codec))  # "utf-16" writes a byte-order mark, the others none
    record = symsbl.read_trajectory(path, states=["x1", "x2"])
    np.testing.assert_array_equal(record.states, x)


def test_an_unused_empty_or_text_column_does_not_refuse_the_file(tmp_path):
    t, x = _lab_record(tmp_path)
    rows = [f"{a!r},{b!r},{c!r}" for a, b, c in np.column_stack([t, x]).tolist()]
    cases = {
        "every line": ["t,x1,x2,"] + [r + "," for r in rows],
        "data lines": ["t,x1,x2"] + [r + "," for r in rows],
        "a notes column": ["t,x1,note,x2"] + [r.replace(",", ",ok,", 2).replace(",ok,", ",", 1) for r in rows],
    }
    for name, lines in cases.items():
        path = tmp_path / f"{name}.csv"
        path.write_text("\n".join(lines) + "\n")
        np.testing.assert_array_equal(symsbl.read_trajectory(path, states=["x1", "x2"]).states, x, err_msg=name)
    with pytest.raises(
        symsbl.DataError,
        match=exactly(
            f"{tmp_path / 'a notes column.csv'}: column 'note' at line 2: expected a number, received 'ok'; repair "
            "or remove the row"
        ),
    ):
        symsbl.read_trajectory(tmp_path / "a notes column.csv", states=["x1", "note"])


def test_a_fifo_is_read_as_data(files, tmp_path, capsys):
    import threading

    fifo = tmp_path / "stream.csv"
    os.mkfifo(fifo)
    content = (files / "train.csv").read_bytes()

    def feed():
        with open(fifo, "wb") as fh:
            fh.write(content)

    thread = threading.Thread(target=feed, daemon=True)
    thread.start()
    code, out, err = run(
        [
            "identify",
            str(fifo),
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--no-refine",
            "--library",
            "poly",
            "--degree",
            "1",
        ],
        capsys,
    )
    thread.join(10)
    assert (code, err) == (0, "") and out.startswith("identified from 4097 samples")


def _diverging_model(files: Path) -> Path:
    doc = json.loads((files / "model.json").read_text())
    eq = doc["equations"][1]
    eq["terms"] = [{"term": "x1**3", "coef": 1e16}]
    eq["covariance"] = [[0.0]]
    del eq["rhs"]
    doc.pop("covariance", None)
    path = files.parent / f"{files.name}-diverging.json"
    path.write_text(json.dumps(doc))
    return path


def _raising(exc):
    def command(*args, **kwargs):
        raise exc

    return command


#: (failure, what the command does, exit code, the last line on standard error)
EXIT_PATHS = [
    ("no model found", lambda args: 1, 1, None),
    (
        "bad input",
        _raising(symsbl.DataError("DATA: expected a record, received none")),
        2,
        "symsbl demo: error: DATA: expected a record, received none",
    ),
    (
        "missing extra",
        _raising(symsbl.MissingExtraError("matplotlib: expected it installed, received none")),
        2,
        "symsbl demo: error: matplotlib: expected it installed, received none",
    ),
    ("out of memory", _raising(MemoryError()), 2, "symsbl demo: error: out of memory: use --quick"),
    (
        "a bug",
        _raising(ZeroDivisionError("division by zero")),
        3,
        "symsbl demo: error: internal error (ZeroDivisionError: division by zero); {advice}",
    ),
    ("Ctrl-C", _raising(KeyboardInterrupt()), 130, "symsbl demo: error: interrupted"),
]


@pytest.mark.parametrize("traceback", [None, "1"], ids=["plain", "SYMSBL_TRACEBACK=1"])
@pytest.mark.parametrize("name, command, code, line", EXIT_PATHS, ids=[p[0] for p in EXIT_PATHS])
def test_the_exit_code_table_holds_on_every_failure_path(monkeypatch, capsys, traceback, name, command, code, line):
    import symsbl._cli as cli

    if traceback is None:
        monkeypatch.delenv("SYMSBL_TRACEBACK", raising=False)
    else:
        monkeypatch.setenv("SYMSBL_TRACEBACK", traceback)
    monkeypatch.setattr(cli, "_cmd_demo", command)
    got, _, err = run(["demo"], capsys)
    assert got == code and code in EXIT_CODES
    lines = err.splitlines()
    if line is None:
        assert err == ""
        return
    advice = "please report it" if traceback else "rerun with SYMSBL_TRACEBACK=1 and report it"
    assert lines[-1] == line.format(advice=advice)
    if code == 3 and traceback:  # the traceback, then the one line
        assert lines[0] == "Traceback (most recent call last):" and "ZeroDivisionError" in lines[-2]
    else:
        assert len(lines) == 1


@pytest.mark.parametrize("traceback", [None, "1"], ids=["plain", "SYMSBL_TRACEBACK=1"])
def test_real_failures_keep_their_exit_codes_with_and_without_tracebacks(files, monkeypatch, capsys, traceback):
    if traceback is None:
        monkeypatch.delenv("SYMSBL_TRACEBACK", raising=False)
    else:
        monkeypatch.setenv("SYMSBL_TRACEBACK", traceback)
    diverging = _diverging_model(files)
    code, out, err = run(["validate", str(diverging), str(files / "train.csv")], capsys)
    assert (code, err) == (1, "") and out.startswith("the identified model diverged in simulation at t = ")
    code, _, err = run(["validate", str(files / "model.json"), str(files / "train.csv"), "--band", "-2"], capsys)
    assert code == 2 and err.count("\n") == 1
    import symsbl._validate.validate as validation

    monkeypatch.setattr(validation, "validate_model", _raising(ZeroDivisionError("division by zero")))
    code, _, err = run(["validate", str(files / "model.json"), str(files / "train.csv")], capsys)
    assert code == 3 and err.endswith(
        "internal error (ZeroDivisionError: division by zero); "
        + ("please report it\n" if traceback else "rerun with SYMSBL_TRACEBACK=1 and report it\n")
    )


def test_a_model_that_diverges_at_the_first_step_exits_1(files, capsys):
    doc = json.loads((files / "model.json").read_text())
    doc["equations"][1]["terms"] = [{"term": "x1**3", "coef": 1e300}]
    doc["equations"][1]["covariance"] = [[0.0]]
    del doc["equations"][1]["rhs"]
    doc.pop("covariance", None)
    path = files.parent / f"{files.name}-first-step.json"
    path.write_text(json.dumps(doc))
    code, out, err = run(["validate", str(path), str(files / "train.csv")], capsys)
    assert (code, err) == (1, "")
    assert (
        out == "the identified model diverged in simulation at t = 0.00012207 s (of 0.5 s); it is unstable on "
        "this input.\n"
    )


#: The environment of a command run in a subprocess: this checkout's symsbl, wherever it runs.
HERE = {**os.environ, "PYTHONPATH": str(Path(symsbl.__file__).parents[1])}


def _command(argv, **kw):
    return subprocess.Popen(
        [sys.executable, "-u", "-m", "symsbl", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=HERE,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        **kw,
    )


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.2, 0.6])
def test_ctrl_c_while_the_command_starts_is_one_line_and_exit_130(tmp_path, delay):
    proc = _command(["demo", "--quick"], cwd=tmp_path)
    time.sleep(delay)  # the imports take a second or more: numpy, scipy, sympy, CasADi
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert (proc.returncode, err) == (130, "symsbl demo: error: interrupted\n")


def test_ctrl_c_right_after_the_imports_is_one_line_and_exit_130(tmp_path):
    script = (
        "import sys; sys.argv = ['symsbl', 'demo']; import os, signal, time, symsbl; "
        "os.kill(os.getpid(), signal.SIGINT); time.sleep(30)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=60,
        env=HERE,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    assert (proc.returncode, proc.stderr) == (130, "symsbl demo: error: interrupted\n")
    library = subprocess.run(
        [
            sys.executable,
            "-c",
            "import signal, symsbl; assert signal.getsignal(signal.SIGINT) is signal.default_int_handler",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        env=HERE,
        # Python installs its handler only where SIGINT is not ignored (a job started in the background)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    assert library.returncode == 0, library.stderr  # a program importing symsbl keeps Python's handler


def test_a_reader_that_leaves_early_does_not_stop_the_command(files, tmp_path):
    out = tmp_path / "model.json"
    proc = _command(
        [
            "identify",
            str(files / "train.csv"),
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--no-refine",
            "--library",
            "poly",
            "--degree",
            "1",
            "--json",
            str(out),
        ]
    )
    proc.stdout.close()  # as `| head -0` does
    err = proc.stderr.read()
    proc.stderr.close()
    proc.wait(60)
    assert (proc.returncode, err) == (0, "") and json.loads(out.read_text())["format"] == "symsbl-model"
