"""Extrapolation: the model choice beyond the training range.

Stand-ins of an electronic Duffing oscillator whose law is outside the library, identified on a multisine to 0.3
fs and simulated on a record whose amplitude grows past the training one (what a user does next).

Each stand-in (``tests/electronic_duffing.py``: ``x'' + 2 zeta w x' + w^2 g(x) = F``, w = 2 pi 50 rad/s, zeta 0.04,
610 Hz; ``g`` a saturating hardening or a stiffness that grows by half beyond a clearance; 2 periods of 4096
samples of a random-phase multisine to 0.3 fs after a dropped transient period; 0.5 % noise on x and v, 0.1 % on F)
is identified by ``symsbl.identify`` with the command line's default library (``paper`` of degree 3, 34
candidates, and of degree 4, 50, for an equation whose law needs it) and its defaults, with the velocity
measured and unmeasured. Every structure on the model path is then refitted by output error on the training record
and simulated free on the extrapolating record (a random force to 0.3 fs whose amplitude ramps from 0.3 to 1.6 times
the training rms, 12288 samples, from rest): its NRMSE on x over the whole record and over its last third (beyond
the training range). The chosen structure should be within 1.5x
of the path's best on the extrapolating record, or the output should say that the library lacks the law.

Long record (``--long``): the saturating stand-in over 14 periods (57344 samples) from its position alone, identified
as above and timed (CPU seconds of this process), once as the solver stands and once with a Levenberg-Marquardt
round that only ends at its tolerance or after 60 passes (``CRAWL_NATS`` 0: no crawl stop), the structure chosen
by each beside. The goal: under 2 minutes.

Run: ``python bench/bench_extrapolation.py [--quick] [--long]`` (``--quick``: the saturating stand-in only).
"""

import dataclasses
import sys
import time
import warnings
from pathlib import Path

import _report  # bench/ is on sys.path when run as a script
import numpy as np
import sympy as sp

import symsbl

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from electronic_duffing import Oscillator, extrapolating, piecewise, saturating, training  # noqa: E402

x, v, F = symsbl.symbols("x v F")
CASES = {"saturating hardening": Oscillator(saturating), "stiffness beyond a clearance": Oscillator(piecewise)}


def _structure(model: symsbl.IdentifiedModel, entry: symsbl.PathEntry) -> symsbl.IdentifiedModel:
    """``model`` with the terms of a path entry (terms it does not hold start at zero)."""
    table = {str(s): s for s in (*model.states, *model.inputs)}
    plain = {k: sp.Symbol(k) for k in table}
    build = symsbl.TermEstimate
    held = {(eq.lhs, t.name): t for eq in model.equations for t in eq.terms}
    names = dict(entry.terms)
    equations = []
    for eq in model.equations:
        if eq.lhs in names:
            terms = [
                held.get((eq.lhs, n)) or build(symsbl.sympy_to_casadi(sp.sympify(n, locals=plain), table), 0.0, 0.0)
                for n in names[eq.lhs]
            ]
            eq = dataclasses.replace(eq, terms=tuple(terms))
        equations.append(eq)
    return dataclasses.replace(model, equations=tuple(equations), path=symsbl.ModelPath())


def _scores(model: symsbl.IdentifiedModel, train, test, measured) -> list:
    """``(entry, NRMSE on x, NRMSE on x over the last third)`` of every structure on ``model``'s path, refitted from
    the chosen model's coefficients (``inf``: the refit ran away from there)."""
    third = test.n_samples // 3
    rows = []
    for entry in model.path.entries:
        try:
            refit = symsbl.refine(_structure(model, entry), train, measured=measured, select=False)
        except symsbl.SimulationError:  # from the chosen model's coefficients the structure ran away
            rows.append((entry, np.inf, np.inf))
            continue
        run = symsbl.validate_model(refit, test)
        sim, meas = run.simulated.column("x"), test.column("x")
        last = np.sqrt(np.mean((sim[-third:] - meas[-third:]) ** 2)) / np.std(meas[-third:])
        rows.append((entry, float(run.nrmse["x"]), float(last)))
    return rows


def case(name: str, plant: Oscillator, unmeasured: bool) -> list:
    train, test = training(plant), extrapolating(plant)
    measured = ("x",) if unmeasured else ("x", "v")
    if unmeasured:
        train = symsbl.Trajectory(train.t, train.states[:, :1], train.inputs, ("x",), ("F",))
    library = [symsbl.paper([x, v], [F], degree=d) for d in (3, 4)]  # the command line's ladder
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", symsbl.RefineWarning)
        model = symsbl.identify(train, library, kinematics={"x": "v"}, states=["x", "v"])
    seconds = time.perf_counter() - start
    info = model.metadata.get("refine", {})
    title = f"{name}, velocity {'unmeasured' if unmeasured else 'measured'}"
    print(f"\n{title}: identified in {seconds:.0f} s")
    print(f"doubts: {info.get('doubts') or 'none'}; reported: {model.metadata.get('estimator', {}).get('used')}")
    print(f"library steps taken: {model.metadata.get('library', 'none')}")
    print(f"library: {info.get('beyond_library') or 'no statement'}")
    rows = _scores(model, train, test, measured)
    best = min(r[1] for r in rows)
    table = []
    for entry, whole, last in rows:
        terms = ", ".join(n for _, names in entry.terms for n in names)
        mark = "chosen" if entry.chosen else entry.source
        table.append(
            [entry.n_terms, terms, mark, f"{100 * entry.cv_error:.3g}", f"{100 * whole:.3g}", f"{100 * last:.3g}"]
        )
    _report.table(title, ["terms", "structure", "", "cv error %", "NRMSE x %", "last third %"], table)
    chosen = next(r for r in rows if r[0].chosen)
    print(f"chosen / best on the path, on the extrapolating record: {chosen[1] / best:.2f}")
    return [name, "no" if unmeasured else "yes", f"{seconds:.0f}", chosen[0].n_terms, f"{chosen[1] / best:.2f}"]


def long_record() -> None:
    """Time the identification of a long record from its position alone, with and without the crawl stop."""
    from symsbl._refine import solver  # the alternative measured: no crawl stop

    long = training(CASES["saturating hardening"], periods=15)
    train = symsbl.Trajectory(long.t, long.states[:, :1], long.inputs, ("x",), ("F",))
    library = [symsbl.paper([x, v], [F], degree=d) for d in (3, 4)]
    rows, crawl = [], solver.CRAWL_NATS
    for label, nats in (("crawl stop", crawl), ("no crawl stop", 0.0)):
        solver.CRAWL_NATS = nats
        start = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", symsbl.RefineWarning)
            model = symsbl.identify(train, library, kinematics={"x": "v"}, states=["x", "v"])
        seconds = time.process_time() - start
        terms = ", ".join(t.name for eq in model.equations for t in eq.terms if not eq.fixed)
        rows.append([label, seconds, len(terms.split(", ")), terms])
    solver.CRAWL_NATS = crawl
    title = f"{train.n_samples} samples, velocity unmeasured"
    cells = [[label, f"{seconds:.0f}", n, terms] for label, seconds, n, terms in rows]
    _report.table(title, ["solver", "identify CPU s", "terms", "structure"], cells)
    print(f"no crawl stop / crawl stop: {rows[1][1] / rows[0][1]:.2f} (goal: under 120 s)")


def main() -> None:
    quick = "--quick" in sys.argv
    summary = []
    for name, plant in CASES.items():
        for unmeasured in (False, True):
            summary.append(case(name, plant, unmeasured))
        if quick:
            break
    _report.table("Summary", ["stand-in", "velocity measured", "identify s", "chosen terms", "chosen / best"], summary)
    if "--long" in sys.argv:
        long_record()
    _report.write_page("extrapolation", __doc__)


if __name__ == "__main__":
    main()
