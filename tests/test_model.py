"""IdentifiedModel forms (print, sympy, LaTeX, CasADi, JSON) and re-simulation checks."""

import dataclasses
import json
import math

import casadi as ca
import numpy as np
import pytest
import sympy as sp
from helpers import exactly

import symsbl
from symsbl import (
    DataError,
    Equation,
    IdentifiedModel,
    Multisine,
    TermEstimate,
    Trajectory,
    simulate,
    symbols,
    time_grid,
    validate_model,
)
from symsbl._base.format import format_uncertain


@pytest.fixture(scope="module")
def duffing(duffing_system, duffing_train, duffing_model):
    return duffing_system, duffing_train, duffing_model


@pytest.mark.parametrize(
    "value, std, signed, text",
    [
        (1.0003, 0.0012, False, "1.000(0.001)"),
        (-1.0002e4, 3.1, True, "- 1.0002e4(3)"),
        (-20.03, 0.1, True, "- 20.0(0.1)"),
        (-1.0001e9, 2e6, True, "- 1.000e9(2e6)"),
        (9.99996e8, 3e5, False, "1.000e9(3e5)"),
        (2.5e-5, 1e-6, True, "+ 2.5e-5(1e-6)"),
    ],
)
def test_format_uncertain(value, std, signed, text):
    assert format_uncertain(value, std, signed=signed) == text


def test_print_shows_terms_with_uncertainties(duffing):
    _, _, model = duffing
    text = str(model)
    assert text.splitlines()[0].startswith("x1' = 1.000")
    line = text.splitlines()[1]
    assert line.startswith("x2' = ") and " F " in line and "x1^3" in line and "(" in line


def _latent_model(u_terms, z_terms):
    """A model with two latent states ``u`` and ``z`` (input Y, measured output F = u + z)."""
    u, z, Y = symbols("u z Y")

    def eq(lhs, terms, **kw):
        estimates = tuple(TermEstimate(e, c, 0.0, fixed=f) for e, c, f in terms)
        return Equation(lhs, estimates, np.zeros((len(terms),) * 2), 0.0, 0.0, **kw)

    equations = (
        eq("u", u_terms(u, Y)),
        eq("z", z_terms(z, Y)),
        eq("F", [(u, 1.0, False), (z, 2.0, False)], algebraic=True),
    )
    return IdentifiedModel((u, z), (Y,), equations, measured=(), outputs=(symsbl.AlgebraicOutput("F"),))


def test_a_sum_term_prints_in_parentheses_and_each_latent_scale_is_named():
    model = _latent_model(
        lambda u, Y: [(Y - u, 120.0, False)], lambda z, Y: [(Y, 1.0, True), (z * ca.fabs(z) * ca.fabs(Y), -50.0, False)]
    )
    lines = str(model).splitlines()
    assert lines[0] == "u' = 120 (Y - u)"  # 120 (Y - u), not 120 Y - u
    assert lines[3] == "u: latent (not measured); its scale is fixed by the form of the term Y - u of u'"
    assert lines[4] == "z: latent (not measured); scaled so that the term Y of z' has the coefficient 1"
    # each term homogeneous in z (|s z| = s |z|), no coefficient fixed: z and 3 z fit alike
    free = _latent_model(lambda u, Y: [(ca.tanh(u / 0.1), 1.0, False)], lambda z, Y: [(Y * ca.fabs(z), -5.0, False)])
    assert free.convention("z") == "its scale is not fixed by a term of the model"
    assert free.convention("u") == "its scale is fixed by the form of the term tanh(10.0 u) of u'"
    # a fixed term of degree 1 in z' takes no factor when z is scaled: it fixes nothing (nor Max(0, z) in F)
    linear = _latent_model(
        lambda u, Y: [(Y - u, 1.0, False)], lambda z, Y: [(z * ca.fabs(Y), -1.0, True), (Y, 3.0, False)]
    )
    assert linear.convention("z") == "its scale is not fixed by a term of the model"
    one_sided = _latent_model(lambda u, Y: [(Y - u, 1.0, False)], lambda z, Y: [(ca.fmax(z, 0) * Y, 2.0, False)])
    assert one_sided.convention("z") == "its scale is not fixed by a term of the model"


def test_sympy_and_latex_forms(duffing):
    _, _, model = duffing
    eqs = model.to_sympy()
    t = sp.Symbol("t", real=True)
    assert eqs[1].lhs == sp.Derivative(sp.Function("x2")(t), t)
    rhs = eqs[1].rhs
    x1 = sp.Symbol("x1", real=True)
    assert float(rhs.coeff(x1**3)) == pytest.approx(-1e9, rel=0.01)
    latex = model.to_latex()
    assert latex.startswith(r"\begin{aligned}") and r"\dot{x_{2}}" in latex and "x_{1}^{3}" in latex
    assert model._repr_latex_() == "$" + latex + "$"


def test_casadi_system_reproduces_the_identified_equations(duffing):
    _, data, model = duffing
    system = model.to_system()
    rhs = system.evaluate_rhs(data.states[:50], data.inputs[:50])
    for k, eq in enumerate(model.equations):
        expected = sum(
            t.coef
            * np.array(
                [
                    float(ca.Function("f", list(model.states) + list(model.inputs), [t.expr])(*row))
                    for row in np.hstack([data.states[:50], data.inputs[:50]])
                ]
            )
            for t in eq.terms
        )
        np.testing.assert_allclose(rhs[:, k], expected, rtol=1e-12, atol=1e-9)


def test_json_round_trip(duffing, tmp_path):
    _, _, model = duffing
    path = tmp_path / "model.json"
    model.save(path)
    doc = json.loads(path.read_text())
    assert doc["states"] == ["x1", "x2"] and doc["inputs"] == ["F"]
    eq = doc["equations"][1]
    assert eq["lhs"] == "x2"
    assert {"term", "coef", "std", "alpha"} <= set(eq["terms"][0])
    # rhs parses with sympy in the state and input names and equals the terms
    local = {n: sp.Symbol(n, real=True) for n in ("x1", "x2", "F")}
    rhs = sp.sympify(eq["rhs"], locals=local)
    assert float(rhs.coeff(local["x1"] ** 3)) == pytest.approx(model.equation("x2").coef("x1**3"))
    back = IdentifiedModel.load(path)
    assert str(back) == str(model)
    np.testing.assert_array_equal(back.equation("x2").coefs, model.equation("x2").coefs)
    np.testing.assert_array_equal(back.equations[1].covariance, model.equations[1].covariance)


def test_a_term_whose_standard_deviation_is_unknown_saves_as_null_and_loads(duffing, tmp_path):
    # a term the regression could not bound (std NaN, as a start's extended model may hold) is written as
    # null, which the reader takes back as unknown: the file was once refused on reading
    _, _, model = duffing
    eq = model.equations[1]
    terms = (dataclasses.replace(eq.terms[0], std=math.nan),) + eq.terms[1:]
    unknown = dataclasses.replace(model, equations=(model.equations[0], dataclasses.replace(eq, terms=terms)))
    unknown.save(tmp_path / "unknown.json")
    assert json.loads((tmp_path / "unknown.json").read_text())["equations"][1]["terms"][0]["std"] is None
    back = IdentifiedModel.load(tmp_path / "unknown.json")
    assert math.isnan(back.equations[1].terms[0].std)
    assert back.equations[1].terms[1].std == eq.terms[1].std


def test_a_covariance_symmetric_to_rounding_loads_and_an_asymmetric_one_does_not(duffing, tmp_path):
    # a refinement's covariance can hold entries near 1e-21 beside 1e-4 whose mirror differs in the
    # sixth digit (seen on a 24-state modal model): rounding, not a different matrix
    _, _, model = duffing
    doc = model.to_json()
    cov = np.array(doc["equations"][1]["covariance"])
    n = cov.shape[0]
    tiny = cov.copy()
    tiny[0, n - 1], tiny[n - 1, 0] = 4.0e-21, 4.00002e-21
    doc["equations"][1]["covariance"] = tiny.tolist()
    (tmp_path / "tiny.json").write_text(json.dumps(doc))
    assert IdentifiedModel.load(tmp_path / "tiny.json").equations[1].covariance[0, n - 1] == 4.0e-21
    skewed = cov.copy()
    skewed[0, n - 1] = cov[0, n - 1] + 1e-3 * np.abs(cov).max()
    doc["equations"][1]["covariance"] = skewed.tolist()
    (tmp_path / "skewed.json").write_text(json.dumps(doc))
    with pytest.raises(symsbl.DataError, match="symmetric"):
        IdentifiedModel.load(tmp_path / "skewed.json")


def test_load_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(DataError, match=r"bad\.json': expected valid JSON, received invalid JSON \(Expecting property"):
        IdentifiedModel.load(bad)
    with pytest.raises(DataError, match=r"missing\.json': expected an existing JSON file, received no such file$"):
        IdentifiedModel.load(tmp_path / "missing.json")
    with pytest.raises(
        DataError, match=exactly("model JSON: expected a field 'equations', received fields ['states']")
    ):
        IdentifiedModel.from_json({"states": ["x"]})
    doc = {"states": ["x"], "inputs": [], "equations": [{"lhs": "x", "terms": [{"term": "y**2", "coef": 1.0}]}]}
    with pytest.raises(
        DataError,
        match=exactly(
            "model JSON.equations[0].terms[0].term: expected a variable among ['x'] or a constant (pi, E) in 'y**2', "
            "received 'y' at position 0"
        ),
    ):
        IdentifiedModel.from_json(doc)


def test_a_term_defined_for_positive_values_only_loads_with_its_rhs():
    # a tank level's sqrt(h): NaN at negative probes on both sides is agreement, not a mismatch
    def doc(rhs):
        return {
            "states": ["h"],
            "inputs": ["q"],
            "equations": [
                {"lhs": "h", "rhs": rhs, "terms": [{"term": "q", "coef": 2.0}, {"term": "sqrt(h)", "coef": -0.5}]}
            ],
        }

    model = IdentifiedModel.from_json(doc("-0.5*sqrt(h) + 2.0*q"))
    assert model.equation("h").coef("sqrt(h)") == -0.5
    with pytest.raises(DataError, match=r"equations\[0\]\.rhs: expected the sum of the equation's terms"):
        IdentifiedModel.from_json(doc("-0.6*sqrt(h) + 2.0*q"))


def test_heldout_validation_and_band(duffing):
    system, _, model = duffing
    heldout = simulate(system, time_grid(0.5, 32768), inputs=Multisine(rms=60, f_min=2, f_max=30, seed=3))
    result = validate_model(model, heldout, n_band=8, seed=0)
    assert result.status == "ok"
    assert max(result.nrmse.values()) < 0.005
    assert result.fit["x1"] == pytest.approx(100 * (1 - result.nrmse["x1"]))
    lower, upper = result.band
    assert lower.shape == heldout.states.shape and np.all(upper >= lower)
    # the band is about the simulated response
    inside = np.mean((result.simulated.states >= lower) & (result.simulated.states <= upper))
    assert inside > 0.95


def test_divergence_is_reported_not_raised():
    # x' = x^2 from x(0) = 1 blows up at t = 1
    (x,) = symbols("x")
    eq = Equation("x", (TermEstimate(expr=x**2, coef=1.0, std=0.01),), np.array([[1e-4]]), 1e-6, 0.0)
    model = IdentifiedModel(states=(x,), inputs=(), equations=(eq,))
    t = np.linspace(0.0, 2.0, 2001)
    data = Trajectory(t=t, states=(1.0 / (1.5 - np.minimum(t, 1.4)))[:, None] * 1.5, state_names=("x",))
    first = validate_model(model, data, method="rk4", substeps=4, initial_state="first")
    assert first.status == "diverged"
    assert first.diverged_at == pytest.approx(1.0, abs=0.01)
    assert first.nrmse["x"] == np.inf
    assert "diverged in simulation at t = " in first.message
    # from the initial state fitted to the record's start, it blows up at 1 / x0
    result = validate_model(model, data, method="rk4", substeps=4)
    assert result.status == "diverged"
    assert result.diverged_at == pytest.approx(1.0 / result.simulated.states[0, 0], abs=0.01)


def test_validation_errors(duffing):
    _, data, model = duffing
    other = Trajectory(t=data.t, states=data.states, inputs=data.inputs, state_names=("y1", "y2"), input_names=("F",))
    with pytest.raises(
        DataError,
        match=exactly(
            "data: expected the model's channels ['x1', 'x2'], received columns ['y1', 'y2'] (missing ['x1', 'x2'])"
        ),
    ):
        validate_model(model, other)
    no_input = Trajectory(t=data.t, states=data.states, state_names=("x1", "x2"))
    with pytest.raises(
        DataError, match=exactly("data: expected the model's inputs ['F'], received inputs [] (missing ['F'])")
    ):
        validate_model(model, no_input)


@pytest.mark.parametrize("seed", [0, 1])
def test_predictive_band_covers_new_measurements_as_a_3_sigma_band_should(duffing, seed):
    """A new noisy record falls inside the predictive band (model spread widened by the estimated
    measurement noise) for close to 99.7 % of its samples (97.2-99.8 % measured over six records;
    the posterior slightly under-covers); the coefficients-only band, which ignores the noise,
    covers far fewer. The noise estimate matches the noise added."""
    system, _, model = duffing
    clean = simulate(system, time_grid(0.5, 32768), inputs=Multisine(rms=60, f_min=2, f_max=30, seed=5 + seed))
    noisy = clean.with_noise(0.004, seed=100 + seed)
    result = validate_model(model, noisy, n_band=20, seed=seed)
    added = 0.004 * clean.states.std(axis=0)
    for k, name in enumerate(clean.state_names):
        assert result.noise_std[name] == pytest.approx(added[k], rel=0.05)
        assert 0.96 <= result.coverage[name] <= 1.0, result.coverage
    lower, upper = result.band
    inside_model_band = np.mean((noisy.states >= lower) & (noisy.states <= upper))
    assert inside_model_band < 0.9
    wide_lower, wide_upper = result.predictive_band
    assert np.all(wide_upper - wide_lower > upper - lower)
    assert "% of samples inside the 3-sigma predictive band" in result.message


def test_no_band_means_no_predictive_band_or_coverage(duffing):
    system, _, model = duffing
    heldout = simulate(system, time_grid(0.2, 32768), inputs=Multisine(rms=60, f_min=2, f_max=30, seed=3))
    result = validate_model(model, heldout)
    assert result.band is None and result.predictive_band is None and result.coverage is None
    assert "band" not in result.message


def test_draws_that_diverge_are_left_out_of_the_band_and_said_so():
    """x' = c x^2 from x(0) = 1 blows up at t = 1/c: with c = 0.3 +- 0.5 the mean model runs 2 s,
    the draws with c > 0.5 do not; they are counted, left out, and reported."""
    (x,) = symbols("x")
    eq = Equation("x", (TermEstimate(expr=x**2, coef=0.3, std=0.5),), np.array([[0.25]]), 1e-6, 0.0)
    model = IdentifiedModel(states=(x,), inputs=(), equations=(eq,))
    t = np.linspace(0.0, 2.0, 2001)
    data = Trajectory(t=t, states=(1.0 / (1.0 - 0.3 * t))[:, None], state_names=("x",))
    result = validate_model(model, data, method="rk4", n_band=20, seed=0)
    c = np.random.default_rng(0).multivariate_normal([0.3], [[0.25]], size=20, method="eigh")[:, 0]
    expected = int(np.sum(c < 0.5))  # blow-up after t = 2 s
    assert result.status == "ok" and result.band_draws == expected < 20
    assert f"the band uses {expected} of 20 posterior draws; the others diverged in simulation" in result.message


@pytest.mark.parametrize("n_band", [-1, 2.5, True])
def test_a_bad_number_of_band_draws_is_named(duffing, n_band):
    system, data, model = duffing
    with pytest.raises(
        DataError,
        match=rf"n_band: expected a number of Monte Carlo draws >= 0 \(0: no band\), "
        rf"received {n_band!r}",
    ):
        validate_model(model, data.slice(0, 1000), n_band=n_band)


def test_the_batched_band_equals_one_simulation_per_draw(duffing, duffing_heldout):
    """All Monte Carlo draws in one compiled call give the band of one simulation per draw."""
    from symsbl._validate.validate import _band, _band_loop, _draws

    _, _, model = duffing
    system = model.to_system()
    kw = dict(
        inputs=symsbl.Sampled(duffing_heldout.t, duffing_heldout.inputs),
        x0=duffing_heldout.states[0],
        method="rk4",
        substeps=1,
        on_divergence="truncate",
    )
    (lower, upper), n = _band(model, system, duffing_heldout, kw, 12, seed=3)
    draws = _draws(model, 12, seed=3)
    runs = np.stack(_band_loop(system, duffing_heldout, kw, draws), axis=1)
    mu, sd = runs.mean(axis=1), runs.std(axis=1, ddof=1)
    assert n == 12
    scale = np.max(np.abs(mu), axis=0)
    np.testing.assert_allclose(lower / scale, (mu - 3 * sd) / scale, rtol=0, atol=1e-12)
    np.testing.assert_allclose(upper / scale, (mu + 3 * sd) / scale, rtol=0, atol=1e-12)
