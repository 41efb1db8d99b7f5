"""The discrepancy workflow: find what a physics model is missing, name it, add it, show the gain.

Starting from a user's model (per state, a list of terms whose coefficients are fitted), each
iteration

1. fits the current model on weak-form rows of the training record (every term kept: the
   structure is the user's, the coefficients are the data's) and re-simulates it on the
   training and held-out records;
2. locates the disagreement: the equation residual of the velocity equation and the
   simulation error, where in time and in the phase plane (displacement, velocity) they
   concentrate (:class:`Disagreement`);
3. scores every effect of the catalogue (:mod:`symsbl.catalogue`) by the exact change of the
   RVM log evidence when its term(s) join the velocity equation (a refit, other terms free),
   and by the held-out error of the refitted model;
4. adds the winner only when its evidence gain clears a threshold calibrated against "nothing
   missing", beats the runner-up by ``margin_nats`` and lowers the held-out error by at least
   ``min_improvement``; otherwise it reports "nothing missing" or "ambiguous between A and B".

Calibration. The weak form on non-overlapping windows gives rows with independent noise, so under
"nothing missing" the gain of one candidate is ``1/2 (z^2 - 1 - ln z^2)`` with ``z^2 ~ chi^2_1``.
Errors in the regressors (noise on the measured states), finite-difference effects and the
fitted-coefficient bias break that ideal, so the threshold is also measured by a parametric
bootstrap: the current model is simulated on the training input, noise of the level measured in
the data (:func:`noise_levels`) is added to every channel, and the whole scoring is rerun; the
threshold is ``max(floor_nats, bootstrap_factor * max null gain)``. When the residual rows are
correlated (a real record's unmodelled dynamics), the statistics are scaled by the effective
sample fraction ``N_eff / N`` before scoring (:class:`Disagreement`).

Measured (oscillator m = 1, c = 20, k = 1e4; 3 s of a 100 N, 10 Hz sine at 16384 Hz; 0.4 % noise;
7 effects, 15 candidates): under "nothing missing" the largest gain over the catalogue stayed below
6 nats in 600 runs (white noise on the states, noise on every channel, a Duffing model that already
has its cubic term; 200 seeds each; the bootstrap raised the threshold to 24.5 nats at most) and
nothing was added. Hidden effects that move the training re-simulation by less than 2x the noise
gain 230-440 nats, 20-90 nats ahead of the runner-up. Ten times smaller ones (cubic stiffness,
Coulomb friction, quadratic damping; 3 seeds each) ended as "nothing missing", "ambiguous" or the
right name, never a wrong one.

The held-out error is the simulation NRMSE averaged over the states (``error="simulation"``)
or, for closed-loop or drifting plants, the NRMSE of the velocity equation on the held-out
weak-form rows (``error="equation"``, a one-step force error).
"""

from __future__ import annotations

from typing import Sequence

import casadi as ca
import numpy as np

from .._checks import choice, integer
from .._derivatives import get_differentiator
from .._errors import DataError, LibraryError, expected
from .._symbolic import casadi_to_sympy
from .._trajectory import Trajectory, noise_levels
from .catalogue import CATALOGUE, Effect
from .decide import DecisionRule, decide
from .design import ERROR_MEASURES, Design, heldout_error
from .inputs import check_record, parse_base, split_record
from .results import Decision, DiscrepancyReport

__all__ = ["discrepancy", "Workflow"]


def _pair(base, state_names, displacement, velocity):
    """The (displacement, velocity) pair: ``x: v`` in the base names them unless given."""
    for name, label in ((displacement, "displacement"), (velocity, "velocity")):
        if name is not None and name not in state_names:
                raise DataError(expected(label, f"one of the states {list(state_names)}", name))
    if velocity is None:
        for x, terms in base.items():
            names = [str(t) for t in terms]
            if len(names) == 1 and names[0] in state_names and names[0] != x and (displacement in (None, x)):
                return x, names[0]
        shown = {k: [str(t) for t in casadi_to_sympy(list(v))] for k, v in base.items()}
        raise DataError(expected("velocity", "a base equation 'x: v' naming the velocity v, another state",
                                 f"the base {shown}", "pass velocity= (and displacement=) explicitly", raw=True))
    return displacement, velocity


def discrepancy(
    data: Trajectory,
    base,
    *,
    heldout: Trajectory | None = None,
    effects: Sequence[Effect] = CATALOGUE,
    displacement: str | None = None,
    velocity: str | None = None,
    derivative="weak",
    error: str = "simulation",
    rule: DecisionRule = DecisionRule(),
    max_iterations: int = 4,
    seed: int = 0,
) -> DiscrepancyReport:
    """Find, name and add what the model ``base`` is missing; show the held-out gain.

    Parameters
    ----------
    data : Trajectory
        Training record (states and inputs).
    base : str or dict
        The starting model: ``"x1: x2; x2: F, x1, x2"`` (see :func:`parse_base`) or a dict
        state -> sequence of casadi.SX terms. Its coefficients are fitted.
    heldout : Trajectory, optional
        Held-out record, ideally at another forcing level; without it the last 30 % of ``data``
        is held out.
    effects : sequence of Effect
        The catalogue (default :data:`symsbl.CATALOGUE`; see
        :func:`symsbl.catalogue` to add or remove entries).
    displacement, velocity : str, optional
        State names of the pair the effects act on; by default read from a base equation
        ``x: v``.
    derivative : str or strategy
        Regression rows (default the weak form on non-overlapping windows; its window is fixed
        from the training record and reused for every record).
    error : {"simulation", "equation"}
        Held-out error: mean NRMSE of the re-simulated states, or NRMSE of the velocity equation
        on the held-out rows (for closed-loop or drifting plants that cannot be run open-loop).
    rule : DecisionRule
        When an effect is added: evidence floor, bootstrap calibration, margin over the
        runner-up, held-out improvement.
    max_iterations : int
    seed : int
        Seed of the bootstrap noise.

    Returns
    -------
    DiscrepancyReport

    Raises
    ------
    DataError, LibraryError
        Malformed records or base model, naming the argument, what was expected and received.

    Examples
    --------
    A linear model misses 1 N of Coulomb friction; trained at 100 N it hides, held out at 10 N it shows:

    >>> import symsbl
    >>> truth = symsbl.systems.coulomb(kc=1.0)
    >>> grid = symsbl.time_grid(2.0, 8192)
    >>> train = symsbl.simulate(truth, grid, inputs=symsbl.Sine(100.0, 10.0)).with_noise(0.004, seed=0)
    >>> held = symsbl.simulate(truth, grid[:8193], inputs=symsbl.Sine(10.0, 10.0)).with_noise(0.004, seed=1)
    >>> report = symsbl.discrepancy(train, "x1: x2; x2: F, x1, x2", heldout=held,
    ...                             rule=symsbl.DecisionRule(n_bootstrap=0))
    >>> report.verdict
    'added coulomb_friction; then nothing missing'
    >>> (added,) = report.added
    >>> added.terms, round(added.coef, 1)
    (('sign(x2)',), -1.0)
    >>> step = report.steps[0]
    >>> step.error_heldout > 10 * step.error_after    # held-out error before and after
    True
    """
    check_record(data, "data", None)
    names = (tuple(data.state_names), tuple(data.input_names))
    choice("error", error, ERROR_MEASURES, error=DataError)
    if not isinstance(rule, DecisionRule):
        raise DataError(expected("rule", "a DecisionRule", type(rule).__name__, raw=True))
    max_iterations = integer("max_iterations", max_iterations, low=1, error=DataError)
    if heldout is None:
        data, heldout = split_record(data)
    check_record(heldout, "heldout", names)
    if isinstance(base, str):
        base = parse_base(base, data.state_names, data.input_names)
    if not isinstance(base, dict) or set(base) != set(data.state_names):
        got = sorted(base) if isinstance(base, dict) else type(base).__name__
        raise LibraryError(expected("base", f"terms for exactly the states {list(data.state_names)}", got))
    run = Workflow(data, heldout, base, effects, displacement, velocity, derivative, error)
    initial = model = run.design.model(run.structure, data)
    steps, names_added, note = [], [], _ending(None)
    for it in range(1, max_iterations + 1):
        step = decide(run, it, model, rule, seed=seed + it)
        steps.append(step)
        if step.added is None:
            note = _ending(step)
            break
        names_added.append(step.added.effect)
        model = step.model_after
    verdict = f"added {', '.join(names_added)}; then {note}" if names_added else note
    return DiscrepancyReport(initial, model, tuple(steps), verdict, error, run.noise)


def _ending(step) -> str:
    """How a run ends, in words: the decision of its last step (or the iteration limit)."""
    if step is None:
        return "stopped after the last iteration"
    if step.decision is Decision.NOTHING_MISSING:
        return str(step.decision)
    ranked = [c for c in step.scores if c.admissible and np.isfinite(c.evidence_gain)]
    if step.decision is Decision.AMBIGUOUS:
        return f"ambiguous between {ranked[0].effect} and {ranked[1].effect}"
    return step.verdict


class Workflow:
    """The state of one discrepancy run: the records, the design and the current structure."""

    def __init__(self, data, heldout, base, effects, displacement, velocity, derivative, error):
        self.data, self.heldout, self.error, self.effects = data, heldout, error, tuple(effects)
        self.x, self.v = _pair(base, data.state_names, displacement, velocity)
        states = tuple(ca.SX.sym(n) for n in data.state_names)
        inputs = tuple(ca.SX.sym(n) for n in data.input_names)
        sym = dict(zip(data.state_names, states))
        x_amp = float(np.max(np.abs(data.column(self.x)))) if self.x else 1.0
        x_sym = sym[self.x] if self.x else ca.SX.sym("_unused")
        variants = [w for e in self.effects
                    for w in e.variants(x_sym, sym[self.v], x_amp, float(np.max(np.abs(data.column(self.v)))))]
        variants = [w for w in variants if self.x or not any(ca.depends_on(e, x_sym) for e in w.exprs)]
        n_terms = len(variants) + sum(map(len, base.values()))
        diff = get_differentiator(derivative).resolve(data.t, data.states, n_terms=n_terms)
        self.design = Design(base, variants, states, inputs, diff)
        self.structure = {s: [self.design.column(e) for e in terms] for s, terms in base.items()}
        for s, cols in self.structure.items():
            if None in cols or len(set(cols)) < len(cols):
                raise LibraryError(expected(f"base: state {s!r}", "distinct terms (up to a constant factor)",
                                            [str(e) for e in casadi_to_sympy(list(base[s]))], "list each term once"))
        candidates = [(w, [self.design.column(e) for e in w.exprs]) for w in variants]
        self.candidates = [(w, cols) for w, cols in candidates if None not in cols]
        lib = self.design.library
        self.input_terms = [i for i, c in enumerate(self.structure[self.v]) if lib.terms[c].name in data.input_names]
        self.noise = noise_levels(data)

    def err(self, model, traj) -> float:
        """The held-out error measure of ``model`` on ``traj``."""
        return heldout_error(model, traj, self.error, self.design, self.v)

    def with_terms(self, *scores) -> dict:
        """The current structure with the terms of ``scores`` added to the velocity equation."""
        trial = dict(self.structure)
        trial[self.v] = self.structure[self.v] + [self.design.library.index(n) for c in scores for n in c.terms]
        return trial
