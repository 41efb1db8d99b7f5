"""Results of the discrepancy workflow: frozen value objects and their readable report."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from .._base.format import format_uncertain
from .._model import IdentifiedModel

__all__ = [
    "Decision",
    "Disagreement",
    "EffectScore",
    "DiscrepancyStep",
    "DiscrepancyReport",
    "OUTSIDE_CATALOGUE",
]

#: The ``family`` of an :class:`EffectScore` for a library term that no catalogue effect names.
OUTSIDE_CATALOGUE = "not in the catalogue"


class Decision(str, enum.Enum):
    """The outcome of one discrepancy iteration (its value is the text the JSON report carries)."""

    ADDED = "added"
    NOTHING_MISSING = "nothing missing"
    AMBIGUOUS = "ambiguous"
    NO_HELDOUT_GAIN = "no held-out gain"
    UNEXPLAINED = "unexplained"
    REPLACED = "replaced"
    REMOVED = "removed"
    CANNOT_TELL = "badly wrong, the record cannot tell why"

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class Disagreement:
    """Where a model and the data disagree.

    Attributes
    ----------
    residual_nrmse : float
        RMS of the velocity-equation residual over the training weak-form rows / std of the target.
    effective_fraction : float
        ``N_eff / N = 1 / (1 + 2 sum_j rho_j)`` from the residual's autocorrelation (lags summed
        while ``|rho_j| > 0.05``): 1 for independent rows; below 1 when the residual carries
        structure correlated across windows (a real record's unmodelled dynamics), which the
        evidence would otherwise over-count. The evidence of the step uses statistics scaled by it.
    regions : tuple of (str, float, float)
        ``(region, share of rows, share of residual energy)`` for velocity reversals, peak speed,
        large displacement; a region whose energy share exceeds its row share concentrates it.
    jump, jump_z : float
        Mean residual just above ``v = 0`` minus just below (target units) and its z-score: a jump
        is the fingerprint of friction.
    residual_map : tuple of ndarray
        ``(x_edges, v_edges, mean residual (n_x, n_v))`` over the phase plane (NaN in empty bins).
    error_time : tuple of ndarray
        ``(segment mid-times, NRMSE per segment)`` of the held-out simulation (or equation) error.
    summary : str
        The above in words.
    """

    residual_nrmse: float
    effective_fraction: float
    regions: tuple
    jump: float
    jump_z: float
    residual_map: tuple = field(repr=False)
    error_time: tuple = field(repr=False)
    summary: str = ""


@dataclass(frozen=True)
class EffectScore:
    """The score of one catalogue effect in one iteration.

    Attributes
    ----------
    effect, label, description, family : str
        Catalogue name, name with the shape value, physical words, family.
    terms : tuple of str
        The term(s) added to the velocity equation.
    evidence_gain : float
        Log-evidence change (nats) of adding the term(s); for a grid effect, of the best grid
        point minus ``log(grid size)``.
    coef, std : float
        Posterior mean and standard deviation of the (first) term's coefficient after the refit; for an
        effect the output-error workflow added, as the final model holds them.
    physical : float or None
        The coefficient as a force per unit term, ``-coef m``, with ``1/m`` the equation's input gain or,
        for a mass the input does not drive, its reciprocity with one that it does (None when neither is
        known).
    admissible : bool
    reason : str
        Why it is not admissible or not in the model, "" otherwise.
    error_after : float or None
        Held-out error of the refitted model with this effect (None when not evaluated).
    shape : float or None
    where : str
        The pair the effect acts on (``"x, v"``), or ``"between (x1-x2) and (v1-v2)"``; "" for the
        equation-error search, which has one pair.
    """

    effect: str
    label: str
    description: str
    family: str
    terms: tuple
    evidence_gain: float
    coef: float
    std: float
    physical: float | None
    admissible: bool
    reason: str
    error_after: float | None
    shape: float | None = None
    where: str = ""


@dataclass(frozen=True)
class DiscrepancyStep:
    """One iteration: the model, where it disagrees, the scores and the decision.

    Attributes
    ----------
    model : IdentifiedModel
        The current model, fitted on the training record.
    error_train, error_heldout : float
        Its error on the training and held-out records.
    disagreement : Disagreement
    scores : tuple of EffectScore
        Sorted by evidence gain, best first.
    threshold : float
        The evidence gain an effect had to clear (nats).
    null_gains : tuple of float
        Largest gain of any effect on each bootstrap record simulated from the current model.
    decision : Decision
    verdict : str
    added : EffectScore or None
    model_after : IdentifiedModel or None
    error_after : float or None
    evidence : str
        ``"output-error"`` or ``"equation-error"``: what the gains are changes of.
    residual_ratio : float or None
        Output error: the residual standard deviation of the current model over the measured noise level
        (largest over records and states); about 1 when nothing is missing.
    bayes_factor : float or None
        Evidence ratio of the effect added (or leading) over the runner-up, a different effect.
    runner_up : str or None
    confirmation : float or None
        Output error: the cross-validated predictive log-likelihood change (nats) of adding the effect, each
        record predicted by fits on the others.
    separating_experiment : dict or None
        When ambiguous: the input under which the two fitted models differ most (``input``, ``scale``,
        ``frequency_hz``, ``difference_noise_std``, ``difference_on_training_input``, ``duration_s``).
    replaces : str or None
        When replaced: the label of the earlier addition this step's effect takes the place of; when
        removed (``added`` None): the label of the earlier addition taken out.
    """

    iteration: int
    model: IdentifiedModel
    error_train: float
    error_heldout: float
    disagreement: Disagreement
    scores: tuple
    threshold: float
    null_gains: tuple
    decision: Decision
    verdict: str
    added: EffectScore | None = None
    model_after: IdentifiedModel | None = None
    error_after: float | None = None
    evidence: str = "equation-error"
    residual_ratio: float | None = None
    bayes_factor: float | None = None
    runner_up: str | None = None
    confirmation: float | None = None
    separating_experiment: dict | None = None
    replaces: str | None = None


@dataclass(frozen=True)
class DiscrepancyReport:
    """The outcome of :func:`discrepancy`.

    Attributes
    ----------
    initial, final : IdentifiedModel
    steps : tuple of DiscrepancyStep
    verdict : str
    error_measure : str
        ``"simulation"`` or ``"equation"``.
    noise : dict
        Estimated noise level per channel.
    evidence : str
        ``"output-error"`` or ``"equation-error"``.
    notes : tuple of str
        What the workflow decided about the record before the search (a closed loop that sent it to the
        equation-error evidence).
    """

    initial: IdentifiedModel
    final: IdentifiedModel
    steps: tuple
    verdict: str
    error_measure: str
    noise: dict = field(default_factory=dict)
    evidence: str = "equation-error"
    notes: tuple = ()

    @property
    def added(self) -> list[EffectScore]:
        """The effects in the final model, in the order they were added (one replaced later is left out)."""
        return [added for _, added in self._kept()]

    def _kept(self) -> list[tuple[DiscrepancyStep, EffectScore]]:
        """Each step whose effect is in the final model, with that effect."""
        replaced = {s.replaces for s in self.steps if s.replaces is not None}
        return [(s, s.added) for s in self.steps if s.added is not None and s.added.label not in replaced]

    def to_json(self) -> dict:
        """``{"added": [...], "verdict": ..., "final": <identify JSON>, "steps": [...]}``."""
        added = [
            {
                "effect": a.effect,
                "term": ", ".join(a.terms),
                "coef": a.coef,
                "std": a.std,
                "evidence_gain": a.evidence_gain,
                "physical": a.physical,
                "description": a.description,
                "error_before": s.error_heldout,
                "error_after": s.error_after,
                "label": a.label,
                "where": a.where,
                "decision": s.decision.value,
                "bayes_factor": _finite(s.bayes_factor),
                "runner_up": s.runner_up,
                "confirmation": s.confirmation,
                "separating_experiment": s.separating_experiment,
                "replaces": s.replaces,
            }
            for s, a in self._kept()
        ]
        steps = [
            {
                "iteration": s.iteration,
                "decision": s.decision.value,
                "verdict": s.verdict,
                "threshold": s.threshold,
                "null_gains": list(s.null_gains),
                "error_train": s.error_train,
                "error_heldout": s.error_heldout,
                "where": s.disagreement.summary,
                "evidence": s.evidence,
                "residual_ratio": s.residual_ratio,
                "bayes_factor": _finite(s.bayes_factor),
                "runner_up": s.runner_up,
                "confirmation": s.confirmation,
                "separating_experiment": s.separating_experiment,
                "replaces": s.replaces,
                "scores": [_score_json(c) for c in s.scores],
            }
            for s in self.steps
        ]
        return {
            "added": added,
            "verdict": self.verdict,
            "final": self.final.to_json(),
            "error_measure": self.error_measure,
            "evidence": self.evidence,
            "notes": list(self.notes),
            "steps": steps,
        }

    def __str__(self) -> str:
        lines = [f"note: {n}" for n in self.notes] + ["model before:", _indent(str(self.initial))]
        for s in self.steps:
            lines.append(
                f"\niteration {s.iteration}: {self.error_measure} error {100 * s.error_train:.3g} % on "
                f"training, {100 * s.error_heldout:.3g} % held out"
            )
            lines.append("where it disagrees: " + s.disagreement.summary)
            lines += _candidate_lines(s) if s.scores else []  # a removal scores no candidates
            lines.append("decision: " + s.verdict)
        lines += ["\nmodel after:", _indent(str(self.final))]
        if self.steps:
            first, last = self.steps[0], self.steps[-1]
            after = last.error_after if last.error_after is not None else last.error_heldout
            lines.append(
                f"held-out {self.error_measure} error: {100 * first.error_heldout:.3g} % before, "
                f"{100 * after:.3g} % after"
            )
        lines.append("verdict: " + self.verdict)
        return "\n".join(lines)


def _candidate_lines(s: DiscrepancyStep) -> list[str]:
    """The table of one step's candidates."""
    lines = [
        f"candidates ({s.evidence} evidence; threshold {s.threshold:.1f} nats; null gains "
        + ", ".join(f"{g:.1f}" for g in s.null_gains)
        + "):",
        f"  {'effect':34s} {'gain (nats)':>12s} {'coefficient':>22s} {'held-out after':>15s}",
    ]
    for c in s.scores:
        err = "-" if c.error_after is None else f"{100 * c.error_after:.3g} %"
        coef = format_uncertain(c.coef, c.std) if np.isfinite(c.coef) else "-"
        note = "" if c.admissible else f"  ({c.reason})"
        lines.append(f"  {c.label:34s} {c.evidence_gain:12.1f} {coef:>22s} {err:>15s}{note}")
    return lines


def _score_json(c) -> dict:
    """One candidate's score as the JSON report lists it."""
    return {
        "effect": c.label,
        "evidence_gain": _finite(c.evidence_gain),
        "coef": _finite(c.coef),
        "std": _finite(c.std),
        "admissible": c.admissible,
        "error_after": c.error_after,
        "name": c.effect,
        "where": c.where,
        "family": c.family,
        "terms": list(c.terms),
    }


def _finite(x):
    """A JSON number, or None for infinities and NaN (which JSON cannot hold)."""
    return None if x is None or not np.isfinite(x) else float(x)


def _indent(text: str) -> str:
    return "\n".join("  " + line for line in text.splitlines())
