"""The command line: identify, simulate, demo, and the errors a user can trigger."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from symsbl import Multisine, Sine, simulate, systems, time_grid, write_trajectory
from symsbl._cli import main


@pytest.fixture(scope="module")
def files(tmp_path_factory, duffing_system, duffing_train):
    d = tmp_path_factory.mktemp("cli")
    system = duffing_system
    train = duffing_train
    held = simulate(system, time_grid(0.5, 32768), inputs=Multisine(rms=60, f_min=2, f_max=30, seed=1))
    write_trajectory(train, d / "train.csv")
    write_trajectory(held, d / "held.npz")
    return d


def run(argv, capsys):
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.slow
def test_identify_then_simulate(files, capsys):
    before = (files / "train.csv").read_bytes()
    code, out, err = run(
        [
            "identify",
            str(files / "train.csv"),
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--json",
            str(files / "model.json"),
        ],
        capsys,
    )
    assert code == 0, err
    assert "x2' = " in out and "x1^3" in out
    assert (files / "train.csv").read_bytes() == before  # input never modified
    doc = json.loads((files / "model.json").read_text())
    assert doc["states"] == ["x1", "x2"] and doc["inputs"] == ["F"]
    x2 = next(e for e in doc["equations"] if e["lhs"] == "x2")
    assert sorted(t["term"] for t in x2["terms"]) == ["F", "x1", "x1**3", "x2"]
    cubic = next(t for t in x2["terms"] if t["term"] == "x1**3")
    assert cubic["coef"] == pytest.approx(-1e9, rel=0.01) and cubic["std"] > 0
    assert {"noise_std", "log_evidence", "rhs"} <= set(x2)

    code, out, err = run(
        ["simulate", str(files / "model.json"), str(files / "held.npz"), "--json", str(files / "errors.json")], capsys
    )
    assert code == 0, err
    errors = json.loads((files / "errors.json").read_text())
    assert errors["status"] == "ok" and max(errors["nrmse"].values()) < 0.005


@pytest.mark.slow
def test_simulate_with_a_predictive_band_and_a_figure(files, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    code, _, err = run(
        [
            "identify",
            str(files / "train.csv"),
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--library",
            "poly",
            "--json",
            str(tmp_path / "model.json"),
        ],
        capsys,
    )
    assert code == 0, err
    system = systems.duffing()
    held = simulate(system, time_grid(0.5, 32768), inputs=Multisine(rms=60, f_min=2, f_max=30, seed=4))
    write_trajectory(held.with_noise(0.004, seed=9), tmp_path / "held.npz")
    png, out_json = tmp_path / "figure2.png", tmp_path / "errors.json"
    code, out, err = run(
        [
            "simulate",
            str(tmp_path / "model.json"),
            str(tmp_path / "held.npz"),
            "--band",
            "10",
            "--json",
            str(out_json),
            "--plot",
            str(png),
        ],
        capsys,
    )
    assert code == 0, err
    assert "% of samples inside the 3-sigma predictive band" in out and f"figure written to {png}" in out
    doc = json.loads(out_json.read_text())
    assert set(doc["coverage"]) == {"x1", "x2"} and min(doc["coverage"].values()) > 0.96
    added = 0.004 * held.states.std(axis=0)
    assert [doc["noise_std"][n] / a for n, a in zip(("x1", "x2"), added)] == pytest.approx([1, 1], rel=0.05)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    code, _, err = run(["simulate", str(tmp_path / "model.json"), str(tmp_path / "held.npz"), "--band", "-1"], capsys)
    assert code == 2
    assert "--band: expected a number of Monte Carlo draws >= 0 (0: no band), received -1" in err


def test_poly_library_and_derivative_option(files, capsys):
    code, out, err = run(
        [
            "identify",
            str(files / "train.csv"),
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--library",
            "poly",
            "--degree",
            "3",
            "--derivative",
            "central",
        ],
        capsys,
    )
    assert code == 0, err
    assert "x1^3" in out


def test_library_file(files, capsys, tmp_path):
    lib = tmp_path / "lib.py"
    lib.write_text(
        "import symsbl\n"
        "x1, x2, F = symsbl.symbols('x1 x2 F')\n"
        "library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])\n"
    )
    code, out, err = run(
        ["identify", str(files / "train.csv"), "--states", "x1,x2", "--inputs", "F", "--library", str(lib)], capsys
    )
    assert code == 0, err
    assert "x1^3" in out


def test_a_state_the_data_lack_is_named_before_it_is_identified_as_latent(files, capsys):
    """Without --kinematics, ``q`` (a typo, or a velocity whose pair was left out) reads as latent: a note says so
    before any work, and an option the latent path refuses still fails in one line."""
    code, out, err = run(
        ["identify", str(files / "train.csv"), "--states", "x1,q", "--inputs", "F", "--no-refine"], capsys
    )
    assert code == 2
    note, error = err.strip().splitlines()
    assert note == (
        "symsbl identify: note: q is not a column of DATA: it is identified as a latent state, with a law of its own "
        "(if it is a velocity, declare its pair: --kinematics <position>:q)"
    )
    assert error.startswith("symsbl identify: error: ") and "when a state is latent" in error


@pytest.mark.parametrize(
    "make, argv, message",
    [
        (None, ["--states", "q,r"], r"--states: expected at least one column of DATA, received none of q,r$"),
        (
            None,
            ["--states", "x1,x2", "--library", "LIBFILE"],
            r"nolib\.py': expected a file defining `library`, a symsbl Library .*, received no `library`$",
        ),
        (
            None,
            ["--states", "x1,x2", "--library", "spline"],
            r"--library: expected 'paper', 'poly' or an existing Python file \(\.py\) defining the library, received "
            r"'spline'$",
        ),
        ("nan", ["--states", "x1,x2", "--inputs", "F"], r"x2.*(NaN|non-finite|not finite)"),
        ("jitter", ["--states", "x1,x2", "--inputs", "F"], r"(uniform|monoton)"),
        (
            "flat",
            ["--states", "x1,x2", "--inputs", "F"],
            r"state 'x2': expected a column that varies, received a "
            r"constant 3; remove it from the states",
        ),
        (
            "short",
            ["--states", "x1,x2", "--inputs", "F"],
            r"rows: expected more regression rows than candidate terms "
            r"\(34\), received \d+ rows from 1 record\(s\) with "
            r"WeakForm",
        ),
        (
            None,
            ["--states", "x1,x2,z", "--inputs", "F", "--kinematics", "x1:x2"],
            r"data: expected an input exciting at least 8 frequencies \(the skeleton and the hidden law need a "
            r"broadband input\), received 1 excited frequencies; use a multisine",
        ),
        (
            None,
            ["--states", "x1,x2,z", "--inputs", "F", "--kinematics", "x1:x2", "--no-refine"],
            r"refine: expected True or a RefineOptions when a state is latent .*, received False; drop refine=False "
            r"\(--no-refine\)$",
        ),
        (
            None,
            ["--states", "x1,x2,z", "--inputs", "F", "--kinematics", "x1:x2", "--derivative", "central"],
            r"derivative: expected 'weak' when a state is latent .*, received 'central'; drop derivative",
        ),
        (
            None,
            ["--states", "q,x2", "--inputs", "F", "--kinematics", "q:x2"],
            r"--states q: expected a column of DATA \(the position of each --kinematics pair is measured; its velocity "
            r"and latent states may be absent\), received no such column$",
        ),
    ],
)
def test_errors_are_clear(files, capsys, tmp_path, make, argv, message):
    src = files / "train.csv"
    if make:
        t = np.arange(400) / 1000.0
        x = np.column_stack([np.sin(20 * t), np.cos(20 * t)])
        f = np.sin(7 * t)
        if make == "nan":
            x[17, 1] = np.nan
        elif make == "jitter":
            t = t.copy()
            t[100] += 0.0004
        elif make == "flat":
            x[:, 1] = 3.0
        elif make == "short":
            t, x, f = t[:40], x[:40], f[:40]
        src = tmp_path / "bad.csv"
        header = "t,x1,x2,F"
        np.savetxt(src, np.column_stack([t, x, f]), delimiter=",", header=header, comments="")
    argv = [a if a != "LIBFILE" else str(tmp_path / "nolib.py") for a in argv]
    (tmp_path / "nolib.py").write_text("x = 1\n")
    code, out, err = run(["identify", str(src), *argv], capsys)
    assert code == 2
    assert err.startswith("symsbl identify: error: ")
    import re

    assert re.search(message, err), err


def test_missing_file(capsys):
    code, _, err = run(["simulate", "nope.json", "nope.csv"], capsys)
    assert code == 2 and err == (
        "symsbl simulate: error: model file 'nope.json': expected an existing JSON file, received no such file\n"
    )


def test_module_entry_point_help():
    out = subprocess.run([sys.executable, "-m", "symsbl", "--help"], capture_output=True, text=True, check=True)
    assert "identify" in out.stdout and "demo" in out.stdout


@pytest.mark.slow
def test_demo_quick(capsys, tmp_path):
    code, out, err = run(["demo", "--quick", "--plots", str(tmp_path)], capsys)
    assert code == 0, err
    table = out[out.index("system ") :]
    assert table.count("exact") == 5 and "WRONG" not in table
    for row in table.splitlines()[1:6]:  # equation error -> output error, per column
        (ee, oe), (ee_all, oe_all), (ee_held, oe_held) = [
            tuple(map(float, cell.split(" -> "))) for cell in re.findall(r"[\d.]+ -> [\d.]+", row)
        ]
        assert oe < 0.05 and oe < ee and oe_all < ee_all, row  # percent
        assert oe_held < 0.41 and oe_held <= ee_held, row  # the noise floor is 0.4 %
    written = sorted(p.name for p in tmp_path.glob("*.png"))
    assert written == ["bouc_wen_n_2.png", "coulomb_friction.png", "duffing.png", "linear.png", "quadratic_damping.png"]
    assert all((tmp_path / name).stat().st_size > 10_000 for name in written)


def test_residual_test_findings_are_listed_apart():
    """Each failed residual test's findings in one line, separated: correlated innovations, an input the
    residual depends on, an input fed back from past residuals."""
    from types import SimpleNamespace

    from symsbl._cli import _diagnosis

    test = {
        "channel": "v",
        "white": False,
        "independent": False,
        "open_loop": False,
        "whiteness_p": 0.0,
        "input_ratio": {"tau": 3.0, "u": 0.5},
        "feedback_ratio": {"tau": 2.0},
    }
    model = SimpleNamespace(metadata={"refine": {"noise": {}, "residual": [test]}}, path=())
    assert _diagnosis(model) == [
        "residual test of v: innovations correlated (Ljung-Box p = 0); depends on tau; feedback to tau"
    ]


def test_identify_without_a_degree_on_a_record_too_short_for_degree_4(tmp_path, capsys):
    """46 regression rows: degree 3's 34 candidates fit, degree 4's 50 do not, and the command keeps degree 3."""
    record = simulate(systems.duffing(), time_grid(0.15, 1229), inputs=Sine(100.0, 10.0)).with_noise(0.004, seed=0)
    write_trajectory(record, tmp_path / "short.csv")
    code, out, err = run(["identify", str(tmp_path / "short.csv"), "--states", "x1,x2", "--inputs", "F"], capsys)
    assert code == 0, err
    assert "with 34 candidate terms, coefficients by" in out
    assert "library: the richer one (50 candidates) was not tried: rows: expected more regression rows" in out
    assert "x1^3" in out


@pytest.mark.slow
def test_identify_takes_the_degree_a_law_needs_unless_one_is_given(tmp_path, capsys):
    """A Bouc-Wen hysteresis of exponent 3 needs terms of degree 4: without --degree the command tries the degree
    above 3 and says which equation took it; with --degree 3 the library is that one alone."""
    record = simulate(systems.bouc_wen(), time_grid(3.0, 4096), inputs=Sine(100.0, 10.0)).with_noise(0.005, seed=0)
    write_trajectory(record, tmp_path / "bw.csv")
    argv = ["identify", str(tmp_path / "bw.csv"), "--states", "x1,x2,x3", "--inputs", "F"]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    assert "with 76 candidate terms (142 for x3; the refinement's 142), coefficients by output error" in out
    assert "library: the richer one (142 candidates against 76) holds a law in fewer terms" in out
    assert "x3 17 terms -> 3" in out
    law = r"x3' = 679\d\.\d\(\S+\) x2 \+ 1\.50\d*\(\S+\) x2 x3\^2 \|x3\| - 1\.50\d*\(\S+\) x3\^3 \|x2\|$"
    assert re.search(law, out, re.M), out
    code, out, err = run([*argv, "--no-refine", "--degree", "3"], capsys)
    assert code == 0, err
    assert "with 76 candidate terms" in out and "richer" not in out
