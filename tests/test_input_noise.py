"""The covariance a measured input's noise adds to an output-error estimate (:mod:`symsbl._refine.inputnoise`),
against closed forms: the refits' spread of a mean, and a covariance added to a model's posterior."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import symsbl
from symsbl._refine.inputnoise import input_noise_covariance, widened


@pytest.fixture(scope="module")
def model():
    """An equation-error model of a linear oscillator (``x' = v`` fixed, ``v'`` of three terms)."""
    t = np.arange(2001) / 200.0
    F = np.sin(3.1 * t) + 0.5 * np.sin(7.3 * t)
    x, v, f = symsbl.symbols("x v F")
    rng = np.random.default_rng(1)
    xs = np.sin(t) + 1e-3 * rng.standard_normal(t.size)
    vs = np.cos(t) + 1e-3 * rng.standard_normal(t.size)
    record = symsbl.Trajectory(t, np.column_stack([xs, vs]), F[:, None], ("x", "v"), ("F",))
    library = symsbl.polynomial([x, v], 1) + symsbl.inputs([f])
    return symsbl.identify(record, library, kinematics={"x": "v"}, refine=False), record


def _with_coef(model, value):
    """``model`` with the first free coefficient of its last equation set to ``value``."""
    eq = model.equations[-1]
    terms = (dataclasses.replace(eq.terms[0], coef=float(value)),) + eq.terms[1:]
    return dataclasses.replace(model, equations=model.equations[:-1] + (dataclasses.replace(eq, terms=terms),))


def test_the_refits_spread_is_the_variance_of_what_they_estimate(model):
    """A refit that returns the mean of the noisy input as a coefficient: its variance over the draws is
    sigma^2 / n (2000 draws: within 8 %), every other coefficient's spread zero."""
    fitted, record = model
    sigma = 0.3
    offset = record.column("F").mean()

    def refit(records):
        return _with_coef(fitted, records[0].column("F").mean() - offset)

    cov = input_noise_covariance(fitted, [record], [{"F": sigma}], refit, draws=2000, seed=3)
    first = len(fitted.equations[0].terms)  # the kinematic equation's coefficient comes first
    expected = sigma**2 / record.n_samples
    assert cov[first, first] == pytest.approx(expected, rel=0.08)
    others = [k for k in range(cov.shape[0]) if k != first]
    assert np.all(cov[np.ix_(others, others)] == 0.0)


def test_the_same_seed_draws_the_same_noise(model):
    fitted, record = model

    def refit(records):
        return _with_coef(fitted, records[0].column("F")[7])

    a = input_noise_covariance(fitted, [record], [{"F": 0.1}], refit, draws=5, seed=2)
    b = input_noise_covariance(fitted, [record], [{"F": 0.1}], refit, draws=5, seed=2)
    assert np.array_equal(a, b) and a.max() > 0


def test_a_widened_model_carries_the_sum_in_every_place(model):
    """The joint covariance is the sum, each equation's block is its slice, each free term's std the root of its
    diagonal, and the fixed kinematic equation is untouched."""
    fitted, _ = model
    n = fitted.covariance().shape[0]
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n))
    extra = a @ a.T * 1e-4
    extra[0, :] = extra[:, 0] = 0.0  # the fixed coefficient has no spread
    out = widened(fitted, extra)
    total = fitted.covariance() + extra
    np.testing.assert_allclose(out.covariance(), total)
    eq = out.equations[-1]
    k = n - len(eq.terms)
    np.testing.assert_allclose(eq.covariance, total[k:, k:])
    np.testing.assert_allclose(eq.stds, np.sqrt(np.diag(total)[k:]))
    assert out.equations[0] == fitted.equations[0]
    assert [t.coef for t in eq.terms] == [t.coef for t in fitted.equations[-1].terms]


def test_the_disagreement_of_two_fits_is_their_difference_over_their_covariances(model):
    """Two fits of one structure whose first coefficient differs by d, each with covariance C: the statistic is
    d^2 (C^-1)_11 / 2, against the chi-square quantile at 99 % of as many degrees of freedom as terms."""
    from scipy.stats import chi2

    from symsbl._refine.inputnoise import disagreement

    fitted, _ = model
    eq = fitted.equations[-1]
    d = 3.0 * eq.stds[0]
    stat, level = disagreement(fitted, _with_coef(fitted, eq.terms[0].coef + d))
    assert stat == pytest.approx(d**2 * np.linalg.inv(eq.covariance)[0, 0] / 2, rel=1e-9)
    assert level == pytest.approx(chi2.ppf(0.99, len(eq.terms)))
    assert disagreement(fitted, fitted)[0] == 0.0


def test_a_draw_that_runs_away_is_left_out_and_too_many_give_none(model):
    """Refits that raise SimulationError on every other draw: the covariance of the rest (the refit's value of
    the noisy input's mean, as above); on every draw: None, so that identify keeps the equation error's model."""
    fitted, record = model
    calls = []

    def flaky(every):
        def refit(records):
            calls.append(1)
            if len(calls) % every == 0:
                raise symsbl.SimulationError("ran away")
            return _with_coef(fitted, records[0].column("F").mean())

        return refit

    cov = input_noise_covariance(fitted, [record], [{"F": 0.3}], flaky(2), draws=400, seed=1)
    first = len(fitted.equations[0].terms)
    assert cov[first, first] == pytest.approx(0.3**2 / record.n_samples, rel=0.2)
    assert input_noise_covariance(fitted, [record], [{"F": 0.3}], flaky(1), draws=4) is None
