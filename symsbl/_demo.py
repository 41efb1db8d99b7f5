"""The paper's five systems end to end: simulate, identify, print, re-simulate on held-out data.

Settings follow Fuentes et al. (2019), Sec. 3: m = 1, c = 20, k = 1e4; a 10 Hz, 100 N sine;
32768 Hz; Gaussian noise of 0.4 % of each state's standard deviation; the Eq. 21 dictionary up
to degree 6 with |x| augmentation. Bouc-Wen uses the paper's Figure 2e exponent, n = 2, with the
restoring force x3 measured, as in the paper. Each identified model is re-simulated on a
held-out record driven by a broadband random-phase multisine it has never seen.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from . import systems
from ._base.checks import choice
from ._data.trajectory import Trajectory
from ._identify import identify
from ._model import IdentifiedModel
from ._refine import refine_or_keep
from ._simulation.ode import OdeSystem
from ._simulation.signals import Multisine, Sine
from ._simulation.simulate import simulate, time_grid
from ._symbolic.terms import paper
from ._validate.truth import TruthComparison, compare_to_truth
from ._validate.validate import Validation, validate_model

__all__ = ["CASES", "DemoResult", "run_case", "run_demo", "write_figures"]

FS = 32768.0
NOISE = 0.004

#: name -> (constructor, keyword arguments)
CASES: dict[str, tuple[Callable[..., OdeSystem], dict[str, Any]]] = {
    "linear": (systems.linear, {}),
    "quadratic damping": (systems.quadratic_damping, {}),
    "Duffing": (systems.duffing, {}),
    "Coulomb friction": (systems.coulomb, {}),
    "Bouc-Wen (n = 2)": (systems.bouc_wen, {"n": 2}),
}


@dataclass(frozen=True)
class DemoResult:
    """One system of the demo: the truth, the identified model and how they compare (``start`` and
    ``start_heldout``: the same for the equation-error model the refinement started from)."""

    name: str
    system: OdeSystem
    model: IdentifiedModel
    truth: TruthComparison
    heldout: Validation
    seconds: float
    train: Trajectory | None = None
    start: TruthComparison | None = None  # the equation-error stage against the truth (when refined)
    start_heldout: Validation | None = None


def run_case(
    name: str, *, seed: int = 0, duration: float = 3.0, degree: int = 6, forcing=None, refine: bool = True
) -> DemoResult:
    """Simulate, identify and validate one of :data:`CASES`.

    Parameters
    ----------
    name : str
        A key of :data:`CASES`.
    seed : int
        Seed of the measurement noise (held-out record: ``seed + 1000``).
    duration : float
        Training record length in seconds, starting from rest.
    degree : int
        Polynomial degree of the Eq. 21 dictionary.
    forcing : Signal, optional
        Training input; default the paper's ``Sine(100, 10)``.
    refine : bool
        Refine by output error (as :func:`symsbl.identify` does by default); the equation-error
        model it starts from is compared with the truth too.
    """
    build, kwargs = CASES[name]
    system = build(**kwargs)
    start = time.perf_counter()
    clean = simulate(system, time_grid(duration, FS), inputs=forcing or Sine(100.0, 10.0))
    library = paper(system.states, system.inputs, degree=degree)
    train = clean.with_noise(NOISE, seed=seed)
    model = identify(train, library, refine=False)
    first = model
    if refine:
        model = refine_or_keep(model, train, library=library)
    seconds = time.perf_counter() - start
    heldout_input = Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=seed + 1)
    heldout = simulate(system, time_grid(1.0, FS), inputs=heldout_input).with_noise(NOISE, seed=seed + 1000)
    before = (compare_to_truth(first, system, clean), validate_model(first, heldout)) if refine else (None, None)
    return DemoResult(
        name,
        system,
        model,
        compare_to_truth(model, system, clean),
        validate_model(model, heldout),
        seconds,
        train,
        *before,
    )


def _format_truth(system) -> list[str]:
    return [f"{eq.lhs}' = {eq.rhs}" for eq in system.to_sympy()]


def run_demo(*, seed: int = 0, quick: bool = False, out=print, cases=None, refine: bool = True) -> list[DemoResult]:
    """Run the cases of :data:`CASES`, print the equations and a results table (``symsbl demo``).

    Parameters
    ----------
    seed : int
        Noise seed.
    quick : bool
        Shorter records and degree 3 (a fast check rather than the paper's settings).
    out : callable
        Where lines go (default ``print``).
    cases : sequence of str, optional
        Names among :data:`CASES` (default: all five).
    refine : bool
        Refine by output error (the default of :func:`symsbl.identify`).

    Examples
    --------
    >>> import symsbl
    >>> (result,) = symsbl.run_demo(quick=True, cases=["Duffing"], out=lambda line: None)
    >>> result.truth.exact_support, result.heldout.status
    (True, 'ok')
    """
    duration, degree = (1.5, 3) if quick else (3.0, 6)
    out(
        f"symsbl demo: the five systems of Fuentes et al. (2019); {duration:g} s at {FS:g} Hz from rest, "
        f"100 N sine at 10 Hz, {100 * NOISE:g} % noise, Eq. 21 dictionary to degree {degree}; "
        "held-out: 1 s random-phase multisine 2-30 Hz, 60 N rms.\n"
    )
    results = []
    for name in CASES if cases is None else cases:
        choice("cases", name, CASES)
        r = run_case(name, seed=seed, duration=duration, degree=degree, refine=refine)
        results.append(r)
        out(f"== {name}  ({r.model.metadata['n_candidates']} candidate terms, {r.model.metadata['n_rows']} rows)")
        out("true:")
        for line in _format_truth(r.system):
            out("  " + line.replace("Derivative(", "").replace(", t)", ""))
        out("identified (posterior mean and standard deviation):")
        for line in str(r.model).splitlines():
            out("  " + line)
        out("")
    _table(results, out)
    return results


def _worst(check: Validation) -> str:
    return f"{100 * max(check.nrmse.values()):.3f}" if check.status == "ok" else "diverged"


def _table(results: list[DemoResult], out) -> None:
    """One row per system; with refinement, the equation-error stage before each output-error figure."""
    refined = any(r.start is not None for r in results)
    out(
        f"{'system':20s} {'support':>8s} {'max coef err (%)':>20s} {'all terms err (%)':>20s} "
        f"{'held-out NRMSE (%)':>20s} {'time':>7s}"
    )
    for r in results:
        cells = [(r.truth.max_error(min_share=0.05), r.truth.max_error(), _worst(r.heldout))]
        if r.start is not None and r.start_heldout is not None:  # set together
            cells.insert(0, (r.start.max_error(min_share=0.05), r.start.max_error(), _worst(r.start_heldout)))
        columns = zip(*[(f"{100 * a:.3f}", f"{100 * b:.3f}", h) for a, b, h in cells])
        big, small, held = (" -> ".join(c) for c in columns)
        out(
            f"{r.name:20s} {'exact' if r.truth.exact_support else 'WRONG':>8s} {big:>20s} {small:>20s} {held:>20s} "
            f"{r.seconds:6.1f}s"
        )
    out(
        ("\nequation error -> output error. " if refined else "\n")
        + "max coef err: terms carrying >= 5 % of their equation's variance; all terms err: every term (e.g. "
        "Coulomb friction, about 0.01 % of the variance). Held-out NRMSE: worst state, against the noisy "
        f"held-out record (noise floor {100 * NOISE:g} %). Time: identification."
    )


def write_figures(results: list[DemoResult], directory, *, n_band: int = 30, seed: int = 0) -> list:
    """Write the paper's Figure 2 for each demo result as ``<directory>/<system>.png``.

    The phase portrait is the (noisy) training record, as in the paper; the held-out record is
    re-simulated with a predictive band from ``n_band`` draws of the coefficient posterior and
    the record's measurement noise. Needs the ``plot`` extra (matplotlib).

    Returns
    -------
    list of pathlib.Path
        The files written.
    """
    from pathlib import Path

    from .plots import figure2

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for r in results:
        check = validate_model(r.model, r.heldout.measured, n_band=n_band, seed=seed)
        fig = figure2(r.model, check, data=r.train)
        slug = "_".join("".join(c if c.isalnum() else " " for c in r.name.lower()).split())
        path = directory / f"{slug}.png"
        fig.savefig(path, dpi=100)
        written.append(path)
    return written
