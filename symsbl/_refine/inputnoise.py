"""The output-error estimate where a measured input carries noise: its covariance widened by refits.

Noise on a measured input drives the simulation like a random force the record does not hold. Output error's
estimate stays close to the truth (its bias is the noise's share of the input's power in the system's band,
small for a force cell's white noise), but its posterior counts measurement noise alone and is too narrow:
on a hardening oscillator with 2 % white noise on the measured force (10 seeds, the true structure) the
coefficients' z-scores had a spread of 7.4 and reached 22, while every coefficient was within 0.82 % of the
truth. The equation error, calibrated there (spread 1.07), was up to 7.7 % off. Refitting the same structure
on the record with white noise of the input's own level drawn again (:data:`DRAWS` times) shows the spread that
noise gives the estimate; added to the posterior covariance it brought the spread to 1.08 (max 3.0) with the
same point estimate (0.96, max 2.2, through :func:`symsbl.identify`, whose draws are seeded otherwise).
Shifting the estimate by the draws' mean change (a one-step simulation-extrapolation) moved it by no more than
its spread and was not kept: the error is a variance, not a bias.

That holds for the right structure. Where the structure lacks a term the record hides from output error (Coulomb
friction of 3 % of the force under 1 % noise on it: 4 of 8 seeds), output error absorbs it into the other
coefficients, 11-20 % off and up to 105 of its widened deviations. The equation error is consistent and output
error efficient for the right structure, so their difference tells (Hausman's test, :func:`disagreement`): on
those 8 seeds its statistic was 3.8-12.5 for the four exact structures (the 99 % level: 15.1) and 42-102 for the
four that lacked the friction (13.3).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
from scipy.stats import chi2

from .._base.errors import SimulationError
from .._data.trajectory import Trajectory
from .._model import IdentifiedModel

__all__ = ["input_noise_covariance", "widened", "disagreement", "DRAWS", "AGREEMENT"]

#: Refits with the input's noise drawn again. Four left the spread's estimate so rough that the z-scores' spread
#: stayed at 1.8 on the case above; ten brought it to 1.08.
DRAWS = 10
#: The level at which the equation error's and output error's fits of one structure are said to disagree.
AGREEMENT = 0.99


def input_noise_covariance(
    model: IdentifiedModel,
    records: Sequence[Trajectory],
    levels: Sequence[dict],
    refit: Callable[[list], IdentifiedModel],
    draws: int = DRAWS,
    seed: int = 0,
) -> np.ndarray | None:
    """The covariance, in :meth:`IdentifiedModel.parameters` order, of ``refit`` (the same structure fitted
    again) over ``draws`` copies of ``records`` whose inputs carry white noise of ``levels`` (per record,
    ``{input: standard deviation}``) added again; a draw whose refit runs away is left out, and with fewer than
    half left, None."""
    rng = np.random.default_rng(seed)
    samples = []
    for _ in range(draws):
        noisier = [_with_noise(r, lv, rng) for r, lv in zip(records, levels)]
        try:
            samples.append(refit(noisier).parameters()[1])
        except (SimulationError, np.linalg.LinAlgError):  # a draw whose simulation runs away is left out
            continue
    if 2 * len(samples) < draws:
        return None
    return np.atleast_2d(np.cov(np.array(samples), rowvar=False))


def _with_noise(record: Trajectory, levels: dict, rng: np.random.Generator) -> Trajectory:
    """``record`` with white noise of ``levels[name]`` added to each input it names."""
    scale = np.array([levels.get(n, 0.0) for n in record.input_names])
    inputs = record.inputs + scale * rng.standard_normal(record.inputs.shape)
    return Trajectory(record.t, record.states, inputs, record.state_names, record.input_names)


def widened(model: IdentifiedModel, extra: np.ndarray) -> IdentifiedModel:
    """``model`` with ``extra`` (in :meth:`IdentifiedModel.parameters` order) added to its covariance: the joint
    one, each equation's block and each free term's standard deviation."""
    joint = model.covariance() + extra
    equations, k = [], 0
    for eq in model.equations:
        n = len(eq.terms)
        block = joint[k : k + n, k : k + n]
        if not eq.fixed:
            terms = tuple(
                t if t.fixed else dataclasses.replace(t, std=float(np.sqrt(block[j, j])))
                for j, t in enumerate(eq.terms)
            )
            eq = dataclasses.replace(eq, terms=terms, covariance=np.array(block))
        equations.append(eq)
        k += n
    return dataclasses.replace(model, equations=tuple(equations), joint_covariance=joint)


def disagreement(consistent: IdentifiedModel, efficient: IdentifiedModel) -> tuple[float, float]:
    """Hausman's statistic of two fits of one structure: the difference of their coefficients on every fitted
    equation's shared terms, squared over the sum of their covariances (conservative: the efficient fit's is
    not subtracted), and its chi-square quantile at :data:`AGREEMENT` (degrees of freedom: the terms compared).
    Each equation counts alone: with several, their coefficients' correlation is left out and the statistic is
    chi-square only roughly."""
    stat, dof = 0.0, 0
    for eq in efficient.equations:
        if eq.fixed:
            continue
        other = consistent.equation(eq.lhs)
        shared = [n for n in eq.names if n in other.names]
        mine = [eq.names.index(n) for n in shared]
        theirs = [other.names.index(n) for n in shared]
        d = np.array([eq.terms[i].coef - other.terms[j].coef for i, j in zip(mine, theirs)])
        V = np.asarray(eq.covariance)[np.ix_(mine, mine)] + np.asarray(other.covariance)[np.ix_(theirs, theirs)]
        stat += float(d @ np.linalg.pinv(V) @ d)
        dof += len(shared)
    return stat, float(chi2.ppf(AGREEMENT, max(dof, 1)))
