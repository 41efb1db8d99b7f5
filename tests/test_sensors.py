"""Sensors that are not states: accelerometers, force cells, and several records of one system.

References: records simulated independently of symsbl (scipy's DOP853 with its reversal events for friction,
a hand-written RK4 for the chain; :mod:`reference_oscillator`), closed-form integrals, and the true coefficients.
"""

import json
import warnings

import numpy as np
import pytest
import reference_oscillator as ro
from helpers import chain, exactly

import symsbl
from symsbl import AccelerationOutput, AlgebraicOutput, DataError, ParameterError, StateOutput
from symsbl._derivatives.kinematics import band_edges, integrate, kinematic_triples

NOISE = 0.01


def _library(*extra):
    x, v, F = symsbl.symbols("x v F")
    lib = symsbl.polynomial([x, v], 3) + symsbl.inputs([F])
    for e in extra:
        lib = lib + e([x, v])
    return lib


def _errors(eq, truth: dict) -> dict:
    return {n: eq.coef(n) / c - 1 for n, c in truth.items()}


def _quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", symsbl.RefineWarning)
        return fn(*args, **kwargs)


# -- the pieces --------------------------------------------------------------------------------------
def test_integrating_a_biased_accelerometer_gives_the_closed_form_motion():
    t = np.arange(20000) / 2000.0
    w1, w2 = 2 * np.pi * 3.0, 2 * np.pi * 11.0
    x = 0.02 * np.sin(w1 * t + 0.3) + 0.005 * np.cos(w2 * t)
    a = -0.02 * w1**2 * np.sin(w1 * t + 0.3) - 0.005 * w2**2 * np.cos(w2 * t) + 0.4  # a bias of 0.4
    low, high = band_edges(t, a, integrations=2)
    assert low == pytest.approx(3.0, abs=0.15) and high == pytest.approx(11.0, abs=0.15)  # leakage: a bin
    v_hat, x_hat = integrate(t, a, low / 3.0, times=2)
    inside = slice(4000, -4000)
    v = 0.02 * w1 * np.cos(w1 * t + 0.3) - 0.005 * w2 * np.sin(w2 * t)
    assert np.max(np.abs(v_hat - v)[inside]) < 2e-3 * np.max(np.abs(v))
    assert np.max(np.abs(x_hat - x)[inside]) < 1e-2 * np.max(np.abs(x))


def test_kinematics_name_an_acceleration_column_as_a_third_member():
    assert kinematic_triples("x1:v1:a1, x2:v2", ["x1", "v1", "x2", "v2"]) == (("x1", "v1", "a1"), ("x2", "v2", None))
    assert kinematic_triples({"x": ("v", "acc")}, ["x", "v"]) == (("x", "v", "acc"),)
    with pytest.raises(
        DataError,
        match=exactly(
            "--kinematics: expected position:velocity pairs such as x1:x2,x3:x4, "
            "each with an acceleration column as a third name if one is measured "
            "(x1:x2:a1), received 'x:v:a:j'"
        ),
    ):
        kinematic_triples("x:v:a:j", ["x", "v"])
    with pytest.raises(
        DataError,
        match=exactly(
            "kinematics: expected an acceleration column named unlike the states "
            "and the other accelerations, received x:v:v"
        ),
    ):
        kinematic_triples("x:v:v", ["x", "v"])


def test_a_system_with_outputs_simulates_them_as_columns():
    x, v, F = symsbl.symbols("x v F")
    k = symsbl.symbols("k")[0]
    system = symsbl.OdeSystem((x, v), (F,), (v, F - 2.0 * v - k * x), (k,), (400.0,), "osc")
    system = system.with_outputs(a=system.rhs[1], Fc=k * x + 2.0 * v)
    record = symsbl.simulate(system, symsbl.time_grid(2.0, 500), inputs=symsbl.Sine(3.0, 4.0), method="rk4", substeps=8)
    assert record.state_names == ("x", "v", "a", "Fc")
    X, U = record.states[:, :2], record.inputs[:, 0]
    assert np.allclose(record.column("a"), U - 2.0 * X[:, 1] - 400.0 * X[:, 0], rtol=0, atol=1e-12)
    assert np.allclose(record.column("Fc"), 400.0 * X[:, 0] + 2.0 * X[:, 1], rtol=0, atol=1e-12)
    assert np.allclose(system.with_parameters(k=100.0).evaluate_outputs(X, U)[:, 1], 100.0 * X[:, 0] + 2 * X[:, 1])


def test_outputs_that_clash_with_the_symbols_are_refused():
    x, v, F = symsbl.symbols("x v F")
    system = symsbl.OdeSystem((x, v), (F,), (v, F - x))
    with pytest.raises(
        symsbl.SimulationError,
        match=exactly("outputs: expected names unlike the states', inputs', parameters' and each other's, received v"),
    ):
        system.with_outputs(v=x)


def test_an_algebraic_output_that_is_not_a_column_is_refused():
    record, _ = ro.accelerometer_record(ro.HARDENING, 0, seconds=1.0, keep=("x", "v"))
    with pytest.raises(DataError, match=exactly("outputs Fc: expected columns of the data, received no such column")):
        symsbl.identify(record, _library(), states=["x", "v"], outputs=["Fc"])
    with pytest.raises(
        ParameterError,
        match=exactly("outputs: expected columns named unlike the states and the accelerations, received ['x']"),
    ):
        symsbl.identify(record, _library(), states=["x", "v"], outputs=["x"])


def test_rows_high_passed_alike_keep_every_linear_identity_across_slabs():
    """``H (D xi) = (H D) xi`` for any ``xi`` whatever the slabs (one filter state carried across them); a constant
    column is removed from the first row (the filter starts in its steady state); a line well above the cut-off
    passes and one well below is stopped, as Butterworth's ``1 / sqrt(1 + (fc / f)^8)``; no filter at 0 or at the
    rows' Nyquist."""
    from symsbl._regression.band import high_passed

    rate, cutoff = 100.0, 2.0
    t = np.arange(4000) / rate
    rng = np.random.default_rng(0)
    D = np.column_stack([rng.standard_normal(t.size), np.ones(t.size), np.sin(2 * np.pi * 20 * t), np.sin(0.4 * t)])
    xi = rng.standard_normal((4, 2))
    slabs = [(D[a : a + n], D[a : a + n] @ xi) for a, n in ((0, 700), (700, 1), (701, 2299), (3000, 1000))]
    out = list(high_passed(iter(slabs), cutoff, rate))
    Df, Yf = np.vstack([d for d, _ in out]), np.vstack([y for _, y in out])
    assert np.max(np.abs(Yf - Df @ xi)) < 1e-12 * np.max(np.abs(Yf))
    whole = next(high_passed(iter([(D, D @ xi)]), cutoff, rate))[0]
    assert np.max(np.abs(whole - Df)) < 1e-12
    assert not Df[:, 1].any()
    tail = slice(2000, None)  # after the start's transient
    for column, f in ((2, 20.0), (3, 0.4 / (2 * np.pi))):
        gain = np.std(Df[tail, column]) / np.std(D[tail, column])
        assert gain == pytest.approx(1 / np.sqrt(1 + (cutoff / f) ** 8), rel=0.02, abs=1e-4), f
    for off in (0.0, 0.4 * rate):
        assert next(high_passed(iter([(D, D @ xi)]), off, rate))[0] is D


def test_the_rows_band_is_where_a_state_was_integrated_and_other_records_reuse_it():
    """``identify`` high-passes the rows only where it integrated a position or a velocity (with both measured, a
    constant force stays identifiable); the statistics carry their band to the records that reuse their targets
    (the equation error's folds), which would find another edge on a shorter record."""
    from symsbl._regression.band import lower_edge

    record, _ = ro.accelerometer_record(ro.HARDENING, 0, seconds=2.0, keep=("x", "v", "a"))
    edge = lower_edge(record.t, [record.column("a")])
    assert 2.0 <= edge < 30.0  # within the multisine's band
    problem = symsbl.regression_stats(record, _library(), states=["x", "v"], derivatives={"v": "a"}, band=edge)
    again = symsbl.regression_stats(record.slice(0, 500), _library(), **problem.targets)
    assert problem.band == again.band == edge
    assert symsbl.regression_stats(record, _library(), states=["x", "v"], derivatives={"v": "a"}).band == 0.0


# -- accelerometers ----------------------------------------------------------------------------------
def test_an_accelerometer_alone_identifies_a_hardening_oscillator():
    """m 0.7, c 1.1, k 3e3, k3 4e7 (the cubic force 1.4x the linear one at the peak), a 2-30 Hz multisine, 1 kHz,
    4 s, 1 % noise on the acceleration: the exact terms, each within 0.5 %, and the held-out acceleration at the
    noise floor; the positions and velocities it never saw within 0.5 % of the truth."""
    measured, _ = ro.accelerometer_record(ro.HARDENING, 1)
    model = _quiet(symsbl.identify, measured, _library(), states=["x", "v"], kinematics="x:v:a")
    assert model.outputs == (AccelerationOutput("a", "v"),)
    assert model.fit.value == "output-error"
    eq = model.equation("v")
    truth = {n: c for n, c in ro.HARDENING.truth().items()}
    assert sorted(eq.names) == sorted(truth)
    assert max(abs(e) for e in _errors(eq, truth).values()) < 5e-3, _errors(eq, truth)
    test, clean = ro.accelerometer_record(ro.HARDENING, 2, rms=3.0)
    assert symsbl.validate_model(model, test).nrmse["a"] < 1.1 * NOISE
    check = symsbl.validate_model(model, clean)
    assert max(check.nrmse.values()) < 5e-3, check.nrmse


def test_the_model_file_keeps_the_outputs_and_validates_the_same(tmp_path):
    measured, _ = ro.accelerometer_record(ro.HARDENING, 1, seconds=2.0)
    model = _quiet(symsbl.identify, measured, _library(), states=["x", "v"], kinematics="x:v:a")
    path = tmp_path / "model.json"
    model.save(path)
    doc = json.loads(path.read_text())
    assert doc["outputs"] == [{"name": "a", "kind": "acceleration", "of": "v"}] and doc["measured"] == []
    again = symsbl.IdentifiedModel.load(path)
    assert str(again) == str(model) and again.outputs == model.outputs and again.latent_names == ()
    test, _ = ro.accelerometer_record(ro.HARDENING, 2, seconds=2.0, rms=3.0)
    assert symsbl.validate_model(again, test).nrmse == symsbl.validate_model(model, test).nrmse
    again.save(tmp_path / "again.json")
    assert (tmp_path / "again.json").read_text() == path.read_text()


def test_a_velocity_the_records_lack_is_said_to_come_from_where_it_was_made():
    """A position with an accelerometer: the velocity is integrated from the acceleration (and the model says so);
    a position alone: it is a smoothing derivative of the position."""
    for keep, how in ((("x", "a"), "v by integration"), (("x",), "v by smoothing derivative")):
        measured, _ = ro.accelerometer_record(ro.HARDENING, 1, seconds=2.0, keep=keep)
        kinematics = "x:v:a" if "a" in keep else "x:v"
        model = _quiet(symsbl.identify, measured, _library(), states=["x", "v"], kinematics=kinematics, refine=False)
        assert model.metadata["unmeasured_estimate"] == how


def test_a_model_file_with_an_output_of_an_unknown_kind_is_refused(tmp_path):
    measured, _ = ro.accelerometer_record(ro.HARDENING, 1, seconds=2.0)
    model = _quiet(symsbl.identify, measured, _library(), states=["x", "v"], kinematics="x:v:a", refine=False)
    doc = model.to_json()
    doc["outputs"] = [{"name": "a", "kind": "strain", "of": "v"}]
    with pytest.raises(
        DataError,
        match=r"^model JSON.outputs\[0\]: expected an object \{name, kind\} with kind one "
        r"of \['state', 'acceleration', 'algebraic'\]",
    ):
        symsbl.IdentifiedModel.from_json(doc)
    doc["outputs"] = [{"name": "a", "kind": "acceleration", "of": "x"}]
    with pytest.raises(DataError, match=r"^model JSON.outputs: 'a': expected the acceleration of the velocity"):
        symsbl.IdentifiedModel.from_json(doc)


@pytest.mark.slow
def test_an_accelerometer_alone_identifies_coulomb_friction():
    """m 1, c 0.8, k 400, k3 2e5, Coulomb 0.6 N under a 4 N rms multisine (stick-slip), the acceleration alone: the
    exact terms within 1 %; the held-out acceleration within 1.5x the noise (the samples at a reversal jump)."""
    measured, _ = ro.accelerometer_record(ro.COULOMB, 1)
    library = _library(lambda s: symsbl.elementwise([s[1]], ["sign"]))
    model = _quiet(symsbl.identify, measured, library, states=["x", "v"], kinematics="x:v:a")
    eq = model.equation("v")
    truth = ro.COULOMB.truth()
    assert sorted(eq.names) == sorted(truth)
    assert max(abs(e) for e in _errors(eq, truth).values()) < 0.01, _errors(eq, truth)
    test, clean = ro.accelerometer_record(ro.COULOMB, 2, rms=3.0)
    assert symsbl.validate_model(model, test).nrmse["a"] < 1.5 * NOISE
    assert max(symsbl.validate_model(model, clean).nrmse[n] for n in ("x", "v")) < 2e-3


@pytest.mark.slow
def test_the_discrepancy_workflow_names_friction_hidden_from_an_accelerometer(tmp_path, capsys):
    """The acceleration alone, a base model without the Coulomb friction: the workflow names it, its force within
    1 % of the truth, every coefficient within 1 %, the held-out acceleration within 1.25x the noise (the samples
    at a reversal jump); from the command line the same."""
    train, _ = ro.accelerometer_record(ro.COULOMB, 1)
    held, _ = ro.accelerometer_record(ro.COULOMB, 2, rms=3.0)
    base = "x: v; v: F, x, v, x**3"
    report = symsbl.discrepancy(train, base, heldout=held, kinematics="x:v:a", rule=symsbl.DecisionRule(n_bootstrap=0))
    assert [a.effect for a in report.added] == ["coulomb_friction"], report.verdict
    assert report.added[0].physical == pytest.approx(ro.COULOMB.fc, rel=0.01)
    eq, truth = report.final.equation("v"), ro.COULOMB.truth()
    assert sorted(eq.names) == sorted(truth), str(report.final)
    assert max(abs(e) for e in _errors(eq, truth).values()) < 0.01, _errors(eq, truth)
    assert report.final.output_names == ("a",) and report.steps[-1].decision == "nothing missing"
    assert report.steps[-1].error_heldout < 1.25 * NOISE < 10 * NOISE < report.steps[0].error_heldout
    for name, record in (("train", train), ("held", held)):
        symsbl.write_trajectory(record, tmp_path / f"{name}.csv")
    code, out, err = _cli(
        [
            "discrepancy",
            str(tmp_path / "train.csv"),
            "--held-out",
            str(tmp_path / "held.csv"),
            "--states",
            "x,v",
            "--inputs",
            "F",
            "--kinematics",
            "x:v:a",
            "--base",
            base,
            "--json",
            str(tmp_path / "report.json"),
        ],
        capsys,
    )
    assert code == 0, err
    doc = json.loads((tmp_path / "report.json").read_text())
    assert [a["effect"] for a in doc["added"]] == ["coulomb_friction"] and "a: measures v'" in out


@pytest.mark.slow
def test_the_discrepancy_workflow_finds_two_effects_hidden_from_an_accelerometer():
    """Friction and the cubic spring both missing from the base: each is named in turn, the final model exact."""
    train, _ = ro.accelerometer_record(ro.COULOMB, 1)
    held, _ = ro.accelerometer_record(ro.COULOMB, 2, rms=3.0)
    report = symsbl.discrepancy(
        train, "x: v; v: F, x, v", heldout=held, kinematics="x:v:a", rule=symsbl.DecisionRule(n_bootstrap=0)
    )
    assert sorted(a.effect for a in report.added) == ["coulomb_friction", "cubic_stiffness"], report.verdict
    eq, truth = report.final.equation("v"), ro.COULOMB.truth()
    assert sorted(eq.names) == sorted(truth), str(report.final)
    assert max(abs(e) for e in _errors(eq, truth).values()) < 0.01, _errors(eq, truth)
    assert report.steps[-1].decision == "nothing missing"


@pytest.mark.slow
def test_two_accelerometers_identify_a_chain_with_a_cubic_spring():
    """Two masses in a chain, a cubic spring from the ground to the first, accelerometers on both: the exact terms of
    both velocity equations (35 candidates each) within 1 %, held-out accelerations at the noise floor."""
    chain = ro.Chain()
    measured, _ = chain.record(1)
    x1, v1, x2, v2, F = symsbl.symbols("x1 v1 x2 v2 F")
    library = symsbl.polynomial([x1, v1, x2, v2], 3) + symsbl.inputs([F])
    model = _quiet(symsbl.identify, measured, library, states=["x1", "v1", "x2", "v2"], kinematics="x1:v1:a1,x2:v2:a2")
    for state, truth in chain.truth().items():
        eq = model.equation(state)
        assert sorted(eq.names) == sorted(truth), (state, eq.names)
        assert max(abs(e) for e in _errors(eq, truth).values()) < 0.01, _errors(eq, truth)
    test, _ = chain.record(2, rms=4.0)
    assert max(symsbl.validate_model(model, test).nrmse.values()) < 1.1 * NOISE


@pytest.mark.slow
def test_a_chain_of_three_masses_from_its_accelerometers_finds_every_weak_dashpot():
    """Three masses in a chain, each dashpot 0.5 % of its spring's critical damping, cubic springs to the ground and
    between the last two masses, recorded by three accelerometers at 0.5 % noise (1-30 Hz, 4 s, simulated by
    CVODES). Positions integrated from accelerations carry errors of 3-9 % below the accelerations' band, which hid
    every dashpot from the equation error and the refinement then ran away (the equation error's model stood, 11
    terms missing); with the rows high-passed at the band's lower edge: exact."""
    from symsbl import Multisine, simulate, symbols, time_grid

    n = 3
    system, x, v = chain([1.06, 1.25, 1.30], [3107.0, 3534.0, 3989.0], zeta=0.005, kg=2.63e6, kc=5.25e6)
    (F,) = symbols("F")
    signal = Multisine(rms=20.0, f_min=1.0, f_max=30.0, seed=3, period=4.0)
    clean = simulate(system, time_grid(4.0, 1024), inputs=signal, method="cvodes")
    a = np.asarray(system.evaluate_rhs(clean.states, clean.inputs))[:, n:]
    a = a + 0.005 * a.std(axis=0) * np.random.default_rng(0).standard_normal(a.shape)
    names = [f"a{i + 1}" for i in range(n)]
    record = symsbl.Trajectory(clean.t, a, clean.inputs, tuple(names), ("F",))
    library = symsbl.polynomial(x + v, 3) + symsbl.inputs([F])
    triples = ",".join(f"x{i + 1}:v{i + 1}:a{i + 1}" for i in range(n))
    model = symsbl.identify(record, library, states=[str(s) for s in x + v], kinematics=triples)
    truth = symsbl.compare_to_truth(model, system)
    assert model.fit is symsbl.FitMethod.OUTPUT_ERROR
    assert truth.exact_support, (truth.missing, truth.spurious)
    assert truth.max_error() < 0.05, truth.relative_error


# -- force cells -------------------------------------------------------------------------------------
def _force_cell_record(seed: int, rms: float = 4.0):
    """The hardening oscillator's position and the force its spring and damper put on the ground, 1 % noise each."""
    plant = ro.HARDENING
    _, clean = ro.accelerometer_record(plant, seed, rms=rms)
    x, v = clean.column("x"), clean.column("v")
    force = plant.k * x + plant.c * v + plant.k3 * x**3
    rng = np.random.default_rng(seed + 100)
    columns = np.column_stack([x, force])
    noisy = columns + NOISE * columns.std(axis=0) * rng.standard_normal(columns.shape)
    return symsbl.Trajectory(clean.t, noisy, clean.inputs, ("x", "Fc"), ("F",))


def test_a_force_cell_is_an_algebraic_output_identified_with_the_motion():
    """Position and ground force measured, velocity not: both equations exact, the force cell's within 1 %."""
    plant = ro.HARDENING
    model = _quiet(
        symsbl.identify, _force_cell_record(1), _library(), states=["x", "v"], kinematics="x:v", outputs=["Fc"]
    )
    assert model.outputs == (StateOutput("x"), AlgebraicOutput("Fc"))
    cell = model.equation("Fc")
    assert cell.algebraic and str(cell).startswith("Fc = ")
    truth = {"x": plant.k, "v": plant.c, "x**3": plant.k3}
    assert sorted(cell.names) == sorted(truth)
    for t in cell.terms:  # within 1 %, or within 3 standard deviations for the damping (3 % of the force)
        assert abs(t.coef - truth[t.name]) < max(0.01 * abs(truth[t.name]), 3 * t.std), (t.name, t.coef, t.std)
    eq = model.equation("v")
    assert sorted(eq.names) == sorted(plant.truth())
    assert max(abs(e) for e in _errors(eq, plant.truth()).values()) < 0.01
    check = symsbl.validate_model(model, _force_cell_record(2, rms=3.0))
    assert max(check.nrmse.values()) < 1.1 * NOISE, check.nrmse
    assert "Fc &= " in model.to_latex() and model.to_sympy()[-1].lhs.func.__name__ == "Fc"


# -- several records -------------------------------------------------------------------------------
@pytest.mark.slow
def test_three_levels_together_show_the_cubic_the_lowest_alone_does_not():
    """Accelerations at three force levels (0.1, 1 and 4 N rms): at the lowest the cubic force is 0.1 % of the
    linear one and is not found; the three records together give the exact model within 1 %, each record with its
    own noise level."""
    plant = ro.HARDENING
    records = [ro.accelerometer_record(plant, seed, rms=rms)[0] for seed, rms in ((1, 0.1), (2, 1.0), (3, 4.0))]
    low = _quiet(symsbl.identify, records[0], _library(), states=["x", "v"], kinematics="x:v:a")
    assert "x**3" not in low.equation("v").names
    model = _quiet(symsbl.identify, records, _library(), states=["x", "v"], kinematics="x:v:a")
    eq = model.equation("v")
    assert sorted(eq.names) == sorted(plant.truth())
    assert max(abs(e) for e in _errors(eq, plant.truth()).values()) < 0.01, _errors(eq, plant.truth())
    by_record = model.metadata["refine"]["noise"]["a"]["innovation_std_by_record"]
    spreads = [r.column("a").std() for r in records]
    assert np.allclose(np.array(by_record) / (NOISE * np.array(spreads)), 1.0, atol=0.1)


@pytest.mark.slow
def test_accelerometer_coefficients_are_calibrated_over_twenty_seeds():
    """z-scores ``(estimate - truth) / std`` of every coefficient over 20 independent records spread as a standard
    normal (between 0.7 and 1.4)."""
    plant = ro.HARDENING
    truth = plant.truth()
    z = []
    for seed in range(20):
        measured, _ = ro.accelerometer_record(plant, 100 + seed, seconds=2.0)
        model = _quiet(symsbl.identify, measured, _library(), states=["x", "v"], kinematics="x:v:a")
        eq = model.equation("v")
        assert sorted(eq.names) == sorted(truth)
        z += [(t.coef - truth[t.name]) / t.std for t in eq.terms]
    spread = float(np.std(z))
    assert 0.7 < spread < 1.4, spread


# -- the command line ------------------------------------------------------------------------------
def _cli(argv, capsys):
    from symsbl._cli import main

    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.slow
def test_the_command_line_identifies_from_several_accelerometer_files_and_validates_each(tmp_path, capsys):
    files = []
    for seed, rms in ((1, 1.0), (2, 4.0)):
        record, _ = ro.accelerometer_record(ro.HARDENING, seed, rms=rms, seconds=2.0)
        files.append(str(tmp_path / f"level{seed}.csv"))
        symsbl.write_trajectory(record, files[-1])
    code, out, err = _cli(
        [
            "identify",
            *files,
            "--states",
            "x,v",
            "--inputs",
            "F",
            "--kinematics",
            "x:v:a",
            "--library",
            "poly",
            "--json",
            str(tmp_path / "model.json"),
            "--quiet",
        ],
        capsys,
    )
    assert code == 0, err
    assert "identified from 2 records (4002 samples)" in out and "a: measures v' (acceleration)" in out
    model = symsbl.IdentifiedModel.load(tmp_path / "model.json")
    assert sorted(model.equation("v").names) == sorted(ro.HARDENING.truth())
    held, _ = ro.accelerometer_record(ro.HARDENING, 3, rms=2.0, seconds=2.0)
    symsbl.write_trajectory(held, tmp_path / "held.csv")
    code, out, err = _cli(
        [
            "validate",
            str(tmp_path / "model.json"),
            str(tmp_path / "held.csv"),
            files[0],
            "--json",
            str(tmp_path / "v.json"),
            "--quiet",
        ],
        capsys,
    )
    assert code == 0, err
    doc = json.loads((tmp_path / "v.json").read_text())
    assert doc["status"] == "ok" and [r["data"] for r in doc["records"]] == [str(tmp_path / "held.csv"), files[0]]
    assert all(r["nrmse"]["a"] < 1.1 * NOISE for r in doc["records"])


def test_the_command_line_refuses_files_of_other_columns(tmp_path, capsys):
    a, _ = ro.accelerometer_record(ro.HARDENING, 1, seconds=0.5)
    b, _ = ro.accelerometer_record(ro.HARDENING, 2, seconds=0.5, keep=("x", "a"))
    symsbl.write_trajectory(a, tmp_path / "a.csv")
    symsbl.write_trajectory(b, tmp_path / "b.csv")
    before = (tmp_path / "b.csv").read_bytes()
    code, out, err = _cli(
        [
            "identify",
            str(tmp_path / "a.csv"),
            str(tmp_path / "b.csv"),
            "--states",
            "x,v",
            "--inputs",
            "F",
            "--kinematics",
            "x:v:a",
            "--quiet",
        ],
        capsys,
    )
    assert code == 2 and out == ""
    assert err == (
        f"symsbl identify: error: DATA {str(tmp_path / 'b.csv')!r}: expected the columns of "
        f"{str(tmp_path / 'a.csv')!r} ['a', 'F'], received ['x', 'a', 'F']; give files of one test "
        "campaign, each with the same columns\n"
    )
    assert (tmp_path / "b.csv").read_bytes() == before
