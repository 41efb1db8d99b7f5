"""The discrepancy workflow: find what a physics model is missing, name it, add it, show the gain.

Split by responsibility:

- :mod:`.catalogue`: the named physical effects (and users' own);
- :mod:`.inputs`: the starting model (``--base``) and user effects (``--effects``) read as data, position
  records;
- :mod:`.design`: one library of base and candidate terms, per-record statistics, fits, held-out errors;
- :mod:`.locate`: where in the phase plane and in time the model disagrees;
- :mod:`.decide`: equation-error evidence scores, the calibrated threshold and the :class:`DecisionRule`;
- :mod:`.candidates`: what the output-error search tries: effects on every pair and between coupled
  pairs, library terms beyond the catalogue;
- :mod:`.scoring`: output-error evidence of candidates (a screen, then refits) and its null calibration;
- :mod:`.confirm`: cross-validated confirmation and the experiment that separates two effects;
- :mod:`.search`: one output-error iteration: score, decide, confirm;
- :mod:`.results`: the frozen results and the :class:`Decision` enum;
- :mod:`.figures`: the before/after, residual-map and evidence figure;
- :mod:`.workflow`: :func:`discrepancy`, the iteration.
"""

from .catalogue import CATALOGUE, Effect, Variant, catalogue
from .decide import DecisionRule
from .inputs import parse_base, position_record
from .results import Decision, Disagreement, DiscrepancyReport, DiscrepancyStep, EffectScore
from .workflow import discrepancy

__all__ = [
    "CATALOGUE",
    "Effect",
    "Variant",
    "catalogue",
    "DecisionRule",
    "parse_base",
    "position_record",
    "Decision",
    "Disagreement",
    "DiscrepancyReport",
    "DiscrepancyStep",
    "EffectScore",
    "discrepancy",
]
