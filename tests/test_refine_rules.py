"""Two promises of the output-error refinement: every kept term clears the penalty, and a hypersensitive record is
reported as such (and validated in a way that works on it)."""

import dataclasses
import json
import warnings

import casadi as ca
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import symsbl
from symsbl import SelectionRule
from symsbl._cli import main
from symsbl._refine.candidates import prior
from symsbl._refine.engine import Engine, Settings
from symsbl._refine.laplace import reduce_model
from symsbl._refine.result import to_model
from symsbl._refine.selection import _every_term_clears
from symsbl._simulation.ode import OdeSystem

X, V, F = symsbl.symbols("x v F")
#: Look-alikes of a damping force at velocities below 1 m/s.
LOOK_ALIKES = {
    "v": V,
    "sin(v)": ca.sin(V),
    "v**3": V**3,
    "v*Abs(v)": V * ca.fabs(V),
    "tanh(v)": ca.tanh(V),
    "atan(v)": ca.atan(V),
    "sinh(v)": ca.sinh(V),
}


@pytest.fixture(scope="module")
def light():
    """Displacement only, a lightly damped hardening oscillator: 0.9 x'' + 1.5 x' + 6e3 x + 8e7 x^3 = F (1.1 %
    of critical), 1-30 Hz at 1 kHz, 2 s, 1.5 % noise."""
    system = OdeSystem((X, V), (F,), (V, (F - 1.5 * V - 6e3 * X - 8e7 * X**3) / 0.9), name="light")
    record = symsbl.simulate(
        system,
        symsbl.time_grid(2.0, 1000),
        substeps=8,
        inputs=symsbl.Multisine(rms=10.0, f_min=1.0, f_max=30.0, seed=21, period=2.0),
    )
    record = record.with_noise(0.015, seed=3)
    only_x = symsbl.Trajectory(record.t, record.states[:, :1], record.inputs, ("x",), ("F",))
    library = symsbl.paper([X, V], [F], degree=3)
    start = symsbl.identify(only_x, library, refine=False, states=["x", "v"], kinematics="x:v")
    return only_x, library, start


def _split_damping(start, names):
    """``start`` with its damping shared equally by the look-alikes ``names`` (and no runners-up)."""
    eq = start.equation("v")
    keep = tuple(t for t in eq.terms if t.name in ("F", "x", "x**3"))
    c = -1.5 / 0.9 / len(names)
    group = tuple(symsbl.TermEstimate(expr=LOOK_ALIKES[n], coef=c, std=np.nan, alpha=1 / c**2) for n in names)
    n = len(keep) + len(group)
    equation = dataclasses.replace(eq, terms=keep + group, covariance=np.zeros((n, n)), runners_up=())
    return dataclasses.replace(start, equations=(start.equations[0], equation), joint_covariance=None)


def test_a_damping_shared_by_look_alikes_keeps_only_terms_that_clear_the_penalty(light):
    """The case behind issue 38: fitted together, v, sin(v), v^3 and v|v| share the damping with evidences of
    3.6, 3.6, -0.7 and -1.0 nats against a penalty of 7.3; each refitted without the weakest, one v remains, with
    the true damping."""
    record, library, start = light
    engine = Engine(_split_damping(start, ["v", "sin(v)", "v**3", "v*Abs(v)"]), [record], ("x",), Settings(), {})
    fitted = engine.fit(engine.base, engine.param.theta0.copy(), prior(engine))
    cost = SelectionRule().nats_per_term(record.n_samples, len(library))
    before = [-reduce_model(fitted.posterior, fitted.alpha[fitted.active], [n])[0] for n in range(fitted.active.size)]
    assert sum(e < cost for e in before) >= 2  # the starting point the selection could leave as it was
    best = _every_term_clears(engine, fitted, cost)
    v = to_model(engine, best, {}).equation("v")
    assert v.names == ["F", "x", "x**3", "v"]
    assert min(t.evidence for t in v.terms) >= cost and best.penalty == cost
    assert v.coef("v") == pytest.approx(-1.5 / 0.9, rel=0.01)


@pytest.mark.slow
@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(names=st.lists(st.sampled_from(sorted(LOOK_ALIKES)), min_size=2, max_size=4, unique=True))
def test_no_kept_term_falls_short_of_the_penalty_in_a_fuzz_of_look_alike_groups(light, names):
    record, library, start = light
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", symsbl.RefineWarning)  # a strongly correlated residual may be reported
        model = symsbl.refine(_split_damping(start, names), record, library=library)
    cost = model.metadata["refine"]["penalty"]
    assert cost >= SelectionRule().nats_per_term(record.n_samples, len(library))
    kept = [t for t in model.equation("v").terms if not t.fixed]
    assert all(t.evidence >= cost for t in kept), [(t.name, t.evidence) for t in kept]


def _duffing(c=1.2, k3=1e9, seconds=2.0, seed=0):
    """x'' + c x' + 1e4 x + k3 x^3 = 1000 sin(2 pi 10 t) at 2048 Hz: light damping (0.6 %), strong hardening, a
    chaotic-like response (a 1e-3 change of c moves it by 24 % over 2 s)."""
    system = symsbl.systems.duffing(k3=k3, c=c)
    clean = symsbl.simulate(system, symsbl.time_grid(seconds, 2048), inputs=symsbl.Sine(1000.0, 10.0), substeps=16)
    noisy = clean.with_noise(0.004, seed=seed)
    return clean, symsbl.Trajectory(noisy.t, noisy.states[:, :1], noisy.inputs, ("x1",), ("F",))


@pytest.fixture(scope="module")
def chaotic(tmp_path_factory):
    clean, train = _duffing()
    moved, _ = _duffing(c=1.2 * 1.001)
    change = np.sqrt(np.mean((moved.states[:, 0] - clean.states[:, 0]) ** 2)) / np.std(clean.states[:, 0])
    assert change > 0.2  # the record is hypersensitive
    x1, x2, F = symsbl.symbols("x1 x2 F")
    with pytest.warns(
        symsbl.RefineWarning,
        match=r"^output-error refinement: the record is hypersensitive "
        r"\(chaotic-like\): the model amplifies a state error 10000-fold "
        r"within \d+ samples \([\d.]+ s\), so it was fitted on segments of "
        r"\d+ samples",
    ):
        model = symsbl.identify(train, symsbl.paper([x1, x2], [F], degree=3), states=["x1", "x2"], kinematics="x1:x2")
    d = tmp_path_factory.mktemp("chaotic")
    model.save(d / "model.json")
    _, held = _duffing(seed=5)
    symsbl.write_trajectory(held, d / "held.csv")
    return model, held, d


@pytest.mark.slow
def test_a_hypersensitive_record_is_reported_by_identify(chaotic):
    model, _, _ = chaotic
    meta = model.metadata["refine"]
    assert meta["hypersensitive"] and meta["horizon"] < 4097 and meta["segment_length"] < 4097
    assert symsbl.compare_to_truth(model, symsbl.systems.duffing(k3=1e9, c=1.2)).max_error() < 0.01


@pytest.mark.slow
def test_a_hypersensitive_record_is_validated_over_short_horizons(chaotic, capsys):
    model, held, d = chaotic
    result = symsbl.validate_model(model, held)
    assert result.status == "ok" and result.horizon is not None and result.horizon < 2.0
    assert result.short_nrmse["x1"] < 0.01  # the noise level: the model is right where it can be judged
    assert "hypersensitive record (chaotic-like)" in result.message
    code = main(["validate", str(d / "model.json"), str(d / "held.csv"), "--json", str(d / "errors.json"), "--quiet"])
    out = capsys.readouterr().out
    assert code == 0 and out.splitlines()[-1].startswith(
        "hypersensitive record (chaotic-like): the model amplifies a state error 10^4-fold within "
    )
    doc = json.loads((d / "errors.json").read_text())
    assert doc["horizon"] == pytest.approx(result.horizon) and doc["short_nrmse"]["x1"] < 0.01


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="on this chaotic-like record the verdict turns on the estimated velocity's window: a 6-sample half "
    "window added the cubic; 7 and 8, whose estimates are closer to the truth (1.4 % against 1.7 %), say the "
    "record cannot tell, and 3 added quadratic damping too",
)
def test_the_discrepancy_workflow_finds_the_cubic_missing_from_a_hypersensitive_record():
    """A linear model of the chaotic-like record (x1^3 missing, displacement only): the held-out folds diverge
    whatever the model, so each prediction is scored at the record's measured noise, not at its fold fit's; the
    cubic stiffness is added (held-out error 40 % -> 3 %, the rest is the record's hypersensitivity), the final
    model is the truth within 1 %, and the next candidate is not added."""
    _, train = _duffing(seconds=4.0)
    report = symsbl.discrepancy(train, "x1: x2; x2: F, x1, x2", kinematics="x1:x2")
    assert [a.effect for a in report.added] == ["cubic_stiffness"], report.verdict
    eq = report.final.equation("x2")
    truth = {"F": 1.0, "x1": -1e4, "x2": -1.2, "x1**3": -1e9}
    assert sorted(eq.names) == sorted(truth), str(report.final)
    for name, value in truth.items():
        assert eq.coef(name) == pytest.approx(value, rel=0.01), name
    assert report.steps[-1].model_after is None and report.steps[-1].error_heldout < report.steps[0].error_heldout / 10


def test_the_validated_choice_takes_a_richer_structure_only_when_every_fold_says_so():
    """The model-path rule on hand-made fold errors: the simplest structure stays when a richer one gains less than
    a paired standard error; a richer one that gains on every fold, by more than a tenth of the way to the noise
    floor, is taken; a structure with a fold whose simulation ran away (the demo's quadratic damping without its
    x2**2 term: 3e24 on one fold, which tied its paired standard error) is never chosen."""
    rule = SelectionRule()
    noisy = np.array([[0.0102, 0.0098, 0.0101], [0.0101, 0.0099, 0.0100]])  # within noise of each other
    assert rule.choose([3, 4], [10.0, 11.0], noisy, floor=0.0099)[0] == 0
    clear = np.array([[0.0300, 0.0280, 0.0310], [0.0101, 0.0099, 0.0100]])
    assert rule.choose([3, 4], [10.0, 11.0], clear, floor=0.0099)[0] == 1
    ran_away = np.array([[0.0040, 50.0, 0.0040], [0.0041, 0.0041, 0.0041]])
    assert rule.choose([4, 5], [1.0, 2.0], ran_away, floor=0.0040)[0] == 1


def test_each_term_a_richer_structure_adds_must_close_its_tenth_of_the_gap():
    """EMPS's inverse model from its encoder, its path's fold errors as measured (%: 4 terms 3.383, 5 terms 3.150,
    6 terms 2.906; floor 0): the fifth term closes 6.9 % of the gap and is refused; the sixth with it closes 14.1 %
    together, more than one term's tenth but less than two terms' 19 % (1 - 0.9^2), and is refused too. A pair
    that closes 20 % is taken."""
    rule = SelectionRule()
    spread = np.array([-0.002, 0.0, 0.002])
    E = np.array([m + spread * (1 + k) for k, m in enumerate([0.03383, 0.03150, 0.02906])])
    assert rule.choose([4, 5, 6], [0.0, 1.0, 2.0], E)[0] == 0
    E[2] = 0.8 * 0.03383 - 1e-4 + spread * 0.1
    assert rule.choose([4, 5, 6], [0.0, 1.0, 2.0], E)[0] == 2


def test_at_the_noise_floor_a_richer_structure_must_close_a_share_of_the_floors_own_uncertainty():
    """The drag oscillator's path as measured (%: the exact five terms 0.5990, with tan(v) 0.5989, the pair's
    standard error 5.3e-5; floor 0.5985): the sixth term gained twice its standard error and a fifth of the gap
    (which needs a tenth), and was taken. The gap is now at least 5 % of the floor (an estimate a few per cent
    off), of which the term must close a tenth, 0.0030 %: refused. A gain of 0.0040 % is taken."""
    rule = SelectionRule()
    wobble = np.array([-5e-7, 0.0, 5e-7])
    E = np.array([0.005990 + wobble, 0.005989 - wobble * 0.8])  # the gain 1e-6, its standard error 5e-7
    assert rule.choose([5, 6], [0.0, 1.0], E, floor=0.005985)[0] == 0
    E[1] = 0.005950 - wobble * 0.8
    assert rule.choose([5, 6], [0.0, 1.0], E, floor=0.005985)[0] == 1


def test_the_library_is_said_to_lack_the_law_only_when_more_terms_still_buy_a_little():
    """:func:`symsbl._refine.path.beyond_library` on fold errors (relative) of a path, noise floor 0.031: an
    exact model whose folds stay above it (10.4 %, as from three accelerometer records at 3 % noise) and which a
    richer structure does not beat is not named; a chosen structure that richer ones still beat beyond their
    standard error, or the richest whose last term closed less than a tenth of the gap, is."""
    from symsbl._refine.path import beyond_library

    folds = np.array([0.0, 0.001, -0.001, 0.0005, -0.0005])
    exact = np.array([0.77 + folds, 0.104 + folds, 0.1045 + folds])
    assert beyond_library([3, 4, 5], exact, 1, 0.031, 0.1) is None
    lacking = np.array([0.124 + folds, 0.0241 + folds, 0.0218 + folds, 0.0216 + folds * 1.01])
    line = beyond_library([3, 4, 5, 6], lacking, 2, 0.005, 0.1)
    assert line is not None and "2.18 %" in line and "4.4 times the noise floor" in line
    richest = np.array([0.124 + folds, 0.0225 + folds, 0.0218 + folds])  # its last term: 2.25 -> 2.18 %
    assert beyond_library([3, 4, 5], richest, 2, 0.005, 0.1) is not None
    assert beyond_library([3, 4, 5], lacking[:3], 2, 0.005, 0.1) is None  # 2.41 -> 2.18 %: a tenth of the gap
    assert beyond_library([3, 4, 5, 6], lacking, 2, 0.01, 0.1) is None  # within 3 times the floor


def test_the_library_is_said_to_lack_the_law_when_the_residual_follows_the_trajectory():
    """The clearance stand-in's path (3 to 6 terms, the richest chosen at 3.74 %, its last term closing more than a
    tenth of the gap, floor 0.49 %): named when its residual follows the model's simulated trajectory (0.29 of
    the innovations predicted out of sample, as measured), not when it follows nothing (0.01, a disturbance) or
    stays within 3 times the floor; the exact model above the floor is not named whatever it follows."""
    from symsbl._refine.path import beyond_library

    folds = np.array([0.0, 0.001, -0.001, 0.0005, -0.0005])
    clearance = np.array([0.339 + folds, 0.1356 + folds, 0.0414 + folds, 0.0374 + folds])
    assert beyond_library([3, 4, 5, 6], clearance, 3, 0.0049, 0.1) is None  # 4.14 -> 3.74 %: over a tenth
    line = beyond_library([3, 4, 5, 6], clearance, 3, 0.0049, 0.1, follows=0.29)
    assert line is not None and "3.74 %" in line and "29 % of the innovations" in line
    assert beyond_library([3, 4, 5, 6], clearance, 3, 0.0049, 0.1, follows=0.01) is None
    assert beyond_library([3, 4, 5, 6], clearance, 3, 0.02, 0.1, follows=0.29) is None  # within 3 times
    exact = np.array([0.77 + folds, 0.104 + folds, 0.1045 + folds])
    assert beyond_library([3, 4, 5], exact, 1, 0.031, 0.1, follows=0.01) is None


def _duffing_by_multisine(seconds: float = 1.0):
    x1, x2, F = symsbl.symbols("x1 x2 F")
    train = symsbl.simulate(
        symsbl.systems.duffing(),
        symsbl.time_grid(seconds, 4096),
        inputs=symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1),
    ).with_noise(0.01, seed=0)
    return train, symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])


def test_a_backward_step_far_from_the_best_is_screened_and_the_choice_is_the_same(monkeypatch, tmp_path):
    """A Duffing oscillator (x^3 carrying most of the force) by multisine: the backward step that removes x^3
    is screened after a dozen passes, already far beyond the screen's bound on the best error, and ends the path
    marked screened; with every step refitted to its optimum instead (no screen), the chosen model is the same
    to the last digit. The mark survives a model file, whose entry an earlier release reads as a "path" one."""
    from symsbl._model.path import PATH_SOURCES
    from symsbl._refine import path

    train, library = _duffing_by_multisine()
    model = symsbl.identify(train, library)
    entries = list(model.path)
    screened = [e for e in entries if e.screened]
    chosen = model.path.chosen
    assert len(screened) == 1 and screened[0].source == "path" and chosen is not None and chosen.source == "evidence"
    assert "x1**3" not in screened[0].names("x2") and "x1**3" in chosen.names("x2")
    assert screened[0].cv_error > path.SCREEN_STOP * min(e.cv_error for e in entries)
    assert "path, screened" in str(model.path)
    monkeypatch.setattr(path, "SCREEN_PASSES", None)  # every backward step refitted to its optimum
    again = symsbl.identify(train, library)
    assert str(again) == str(model) and again.path.chosen == chosen
    model.save(tmp_path / "m.json")
    assert symsbl.IdentifiedModel.load(tmp_path / "m.json").path == model.path
    written = json.loads((tmp_path / "m.json").read_text())["path"]["entries"]
    assert all(e["source"] in PATH_SOURCES for e in written) and sum(e.get("screened", False) for e in written) == 1


def test_a_windowed_pass_is_the_full_pass_on_its_window():
    """The cross-validation fits each fold's initial state on its lead: a pass over the chunks holding that
    window gives the window's segment the blocks, residual and end sensitivities of the pass over every sample,
    zero blocks to the other segments and NaN residuals outside it, for a window inside a chunk and one across
    a chunk boundary; and the lead's state fitted on it is the one fitted with passes over every sample."""
    from symsbl._refine.solver import Iterate, initial_states

    train, library = _duffing_by_multisine(4.0)
    model = symsbl.identify(train, library)
    engine = Engine(model, [train], ("x1", "x2"), Settings(), {})
    passes = engine.passes
    theta = engine.param.theta0.copy()
    w = 1.0 / (0.01 * np.std(train.states, axis=0)) ** 2  # the record's noise precisions
    assert passes.records.n_total > 3 * passes.chunk
    for a, lead in ((1500, 256), (passes.chunk - 100, 300), (2 * passes.chunk, 512)):
        starts = np.array([0, a, a + lead])
        seg = passes.segments(starts)
        X0 = engine.guess[starts] * 1.01  # a start off the states
        full = passes.sensitivities(theta, X0, seg, w)
        window = passes.sensitivities(theta, X0, seg, w, rows=(a, a + lead))
        for got, want in ((window.H, full.H), (window.g, full.g), (window.rr, full.rr), (window.end_S, full.end_S)):
            assert got[1] == pytest.approx(want[1], rel=1e-12) and np.all(got[[0, 2]] == 0)
        assert np.array_equal(window.residual[a : a + lead], full.residual[a : a + lead])
        assert np.isnan(np.delete(window.residual, np.s_[a : a + lead], axis=0)).all()
        start = Iterate(theta, X0, seg, w)
        fitted, n_full = initial_states(passes, start, sweeps=4, tol=0.0, rtol=0.0)
        lead_only, n_window = initial_states(passes, start, sweeps=4, tol=0.0, rtol=0.0, rows=(a, a + lead))
        assert n_full == n_window == 5 and not np.allclose(fitted.X0[1], X0[1], rtol=1e-3)  # the state moved
        assert lead_only.X0[1] == pytest.approx(fitted.X0[1], rel=1e-9, abs=1e-12)


def test_a_large_structure_tries_the_terms_of_one_variable_of_each_equations_neighbourhood(monkeypatch):
    """A chain of four masses (eight states and a force: nine terms of one variable) offers each equation those
    of the variables it holds, their kinematic partners and the force; the others only as the equation error's
    alternatives, runners-up or look-alikes, which it offered in every equation before."""
    import symsbl._refine.candidates as cand
    from symsbl._refine.rows import design_rows

    x = symsbl.symbols("x1 x2 x3 x4")
    v = symsbl.symbols("v1 v2 v3 v4")
    (F,) = symsbl.symbols("F")
    k = [3e3, 2e3, 4e3, 2.5e3]
    force = [-k[0] * x[0] + k[1] * (x[1] - x[0]) - 0.5 * v[0]]
    force += [-k[i] * (x[i] - x[i - 1]) + k[i + 1] * (x[i + 1] - x[i]) - 0.5 * v[i] for i in (1, 2)]
    force += [-k[3] * (x[3] - x[2]) - 0.5 * v[3] + F]
    system = OdeSystem(tuple(x) + tuple(v), (F,), tuple(v) + tuple(force), name="chain of 4")
    data = symsbl.simulate(
        system, symsbl.time_grid(4.0, 512), inputs=symsbl.Multisine(rms=20.0, f_min=1.0, f_max=30.0, seed=3)
    ).with_noise(0.005, seed=0)
    library = symsbl.polynomial(list(x) + list(v), 1) + symsbl.inputs([F])
    model = symsbl.identify(data, library, refine=False, kinematics="x1:v1,x2:v2,x3:v3,x4:v4")
    alone = {t.name for t in library.terms if t.sympy.is_Symbol}
    assert len(alone) == 9 > cand.ALONE_EVERYWHERE
    args = (model, cand.Rebased(library, model), design_rows(model, [data], data.states))
    offered, _ = cand.candidates(*args)
    monkeypatch.setattr(cand, "ALONE_EVERYWHERE", len(alone))
    everywhere, _ = cand.candidates(*args)
    dropped = 0
    for eq in model.equations:
        if eq.fixed:
            continue
        held = {str(s) for t in eq.terms for s in t.sympy.free_symbols} | {eq.lhs}
        near = {n for n in alone if n == "F" or {f"x{n[1:]}", f"v{n[1:]}"} & held}
        tried = {str(e) for e, _ in offered.get(eq.lhs, [])}
        before = {str(e) for e, _ in everywhere.get(eq.lhs, [])}
        assert near - set(eq.names) <= tried <= before, eq.lhs
        assert before - tried <= alone - near, eq.lhs  # only a far mass's variables are left out
        dropped += len(before - tried)
    assert dropped >= 4


def test_a_fold_whose_free_run_diverges_scores_infinite_and_raises_nothing(light, monkeypatch):
    """Cross-validation of a structure whose free run over the folds diverges (its blocks not finite: seen on a
    chain of three masses recorded by accelerometers, where it raised from the eigen-decomposition of the initial
    states' block and the whole refinement gave up) scores every fold infinite; a finite one scores finite."""
    from symsbl._refine.crossval import cross_validate, folds

    record, _, start = light
    engine = Engine(start, [record], ("x",), Settings(), {})
    fitted = engine.fit(engine.base, engine.param.theta0.copy(), prior(engine))
    cv = folds(engine.passes, engine.length0)
    assert cv is not None and len(cv) >= 2
    finite = cross_validate(engine.passes, fitted, cv).fold_errors
    assert np.all(np.isfinite(finite)), finite
    true_pass = engine.passes.sensitivities

    def diverged(*args, **kwargs):
        blocks = true_pass(*args, **kwargs)
        blocks.H[-1] = np.nan
        return blocks

    monkeypatch.setattr(engine.passes, "sensitivities", diverged)
    assert np.all(cross_validate(engine.passes, fitted, cv).fold_errors == np.inf)
