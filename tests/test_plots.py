"""Figures: they render, and what they draw is the model's posterior."""

import dataclasses
import sys

import numpy as np
import pytest
from helpers import exactly

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")

from matplotlib.collections import PolyCollection  # noqa: E402

import symsbl  # noqa: E402
from symsbl import DataError, plots  # noqa: E402
from symsbl._base.format import format_uncertain  # noqa: E402
from symsbl._figures import AFTER  # noqa: E402

FS = 4096.0


@pytest.fixture(scope="module")
def duffing_case(duffing_train, duffing_model, duffing_heldout):
    validation = symsbl.validate_model(duffing_model, duffing_heldout, n_band=6)
    return duffing_train, duffing_model, validation


def test_figure2_panels_and_bars(duffing_case, tmp_path):
    train, model, validation = duffing_case
    assert validation.band is not None
    fig = plots.figure2(model, validation, data=train)
    ax_a, ax_b, ax_c, ax_var = fig.axes
    eq = model.equation("x2")
    assert [t.name for t in eq.terms] == ["F", "x1", "x2", "x1**3"]
    # (a) the phase portrait is the training record
    x, y = ax_a.lines[0].get_data()
    np.testing.assert_array_equal(x, train.column("x1"))
    np.testing.assert_array_equal(y, train.column("x2"))
    # (b) measured, simulated and the band
    assert [line.get_label() for line in ax_b.lines] == ["measured", "identified model"]
    assert sum(isinstance(c, PolyCollection) for c in ax_b.collections) == 1
    # (c) one bar per kept term at |coef|, labelled with the term; variances on the twin axis
    assert len(ax_c.patches) == len(eq.terms)
    np.testing.assert_allclose([p.get_height() for p in ax_c.patches], np.abs(eq.coefs))
    labels = [t.get_text() for t in ax_c.get_xticklabels()]
    assert labels == [plots.term_label(n) for n in eq.names] == ["F", "x1", "x2", "x1^3"]
    assert ax_c.get_yscale() == "log" and ax_var.get_yscale() == "log"
    prior, posterior = ax_var.lines
    np.testing.assert_allclose(prior.get_ydata(), [1.0 / t.alpha for t in eq.terms])
    np.testing.assert_allclose(posterior.get_ydata(), eq.stds**2)
    path = tmp_path / "figure2.png"
    fig.savefig(path, dpi=60)
    assert path.stat().st_size > 10_000


def test_figure2_state_and_window(duffing_case, tmp_path):
    _, model, validation = duffing_case
    fig = plots.figure2(model, validation, state="x1", window=(0.1, 0.2))
    ax_b, ax_c = fig.axes[1], fig.axes[2]
    assert len(ax_c.patches) == len(model.equation("x1").terms) == 1
    assert [t.get_text() for t in ax_c.get_xticklabels()] == ["x2"]
    assert ax_b.get_xlim() == (0.1, 0.2)
    t = ax_b.lines[0].get_xdata()
    assert t.min() >= 0.1 and t.max() <= 0.2
    np.testing.assert_array_equal(
        ax_b.lines[0].get_ydata(),
        validation.measured.column("x1")[(validation.measured.t >= 0.1) & (validation.measured.t <= 0.2)],
    )
    fig.savefig(tmp_path / "figure2_x1.png", dpi=60)


def test_figure2_draws_the_predictive_band_with_the_noise(duffing_case):
    _, model, validation = duffing_case
    fig = plots.figure2(model, validation, window=(0.0, 0.5))
    (band,) = [c for c in fig.axes[1].collections if isinstance(c, PolyCollection)]
    assert band.get_label() == r"3$\sigma$ predictive band"
    lower, upper = validation.predictive_band
    k = model.state_names.index("x2")
    drawn = band.get_paths()[0].vertices[:, 1]
    assert drawn.max() == pytest.approx(upper[:, k].max()) and drawn.min() == pytest.approx(lower[:, k].min())
    coefficients_only = dataclasses.replace(validation, noise_std=None)
    fig = plots.figure2(model, coefficients_only)
    (band,) = [c for c in fig.axes[1].collections if isinstance(c, PolyCollection)]
    assert band.get_label() == r"3$\sigma$ band (coefficients)"


def test_figure2_shows_the_equation_with_the_nonlinearity():
    """Bouc-Wen: x2' has more terms, x3' the nonlinear ones; the paper's Figure 2e shows x3'."""
    x1, x2, x3, F = symsbl.symbols("x1 x2 x3 F")

    def equation(lhs, exprs):
        terms = tuple(symsbl.TermEstimate(expr=e, coef=1.0, std=0.1) for e in exprs)
        return symsbl.Equation(lhs, terms, np.eye(len(terms)) * 0.01, 1e-6, 0.0)

    model = symsbl.IdentifiedModel(
        states=(x1, x2, x3),
        inputs=(F,),
        equations=(equation("x1", [x2]), equation("x2", [F, x1, x2, x3]), equation("x3", [x2, x2 * x3**2, x2 * x3])),
    )
    assert plots._equation_for(model, None).lhs == "x3"
    linear = dataclasses.replace(model, equations=model.equations[:2] + (equation("x3", [x2]),))
    assert plots._equation_for(linear, None).lhs == "x2"


def test_figure2_without_band_and_diverged(duffing_case):
    _, model, validation = duffing_case
    no_band = dataclasses.replace(validation, band=None)
    fig = plots.figure2(model, no_band)
    assert not any(isinstance(c, PolyCollection) for c in fig.axes[1].collections)
    cut = validation.simulated.slice(0, 100)
    diverged = dataclasses.replace(no_band, simulated=cut, status="diverged", diverged_at=float(cut.t[-1]))
    fig = plots.figure2(model, diverged)
    assert "diverged at" in fig.axes[1].get_title()


def test_figure2_errors(duffing_case):
    _, model, validation = duffing_case
    with pytest.raises(
        DataError, match=exactly("state: expected one of the model's states ['x1', 'x2'], received 'x3'")
    ):
        plots.figure2(model, validation, state="x3")
    with pytest.raises(
        DataError,
        match=exactly("window: expected (t_start, t_stop) with t_start < t_stop in seconds, received (0.3, 0.1)"),
    ):
        plots.figure2(model, validation, window=(0.3, 0.1))
    with pytest.raises(
        DataError, match=exactly("validation: expected a Validation from symsbl.validate_model, received Trajectory")
    ):
        plots.figure2(model, validation.measured)


def test_forcing_window_is_one_cycle_of_the_slowest_component():
    system = symsbl.systems.linear()
    t = symsbl.time_grid(1.0, FS)
    sine = symsbl.simulate(system, t, inputs=symsbl.Sine(100.0, 10.0))
    t0, t1 = plots.forcing_window(sine)
    assert t1 == pytest.approx(1.0) and t1 - t0 == pytest.approx(0.1, rel=1e-3)
    multi = symsbl.simulate(system, t, inputs=symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1))
    t0, t1 = plots.forcing_window(multi, cycles=2)
    assert t1 - t0 == pytest.approx(1.0, rel=1e-3)


def test_coefficient_uncertainty(duffing_case, tmp_path):
    _, model, _ = duffing_case
    fig = plots.coefficient_uncertainty(model)
    assert len(fig.axes) == len(model.equations)
    for ax, eq in zip(fig.axes, model.equations):
        assert ax.get_title(loc="left") == f"{eq.lhs}'"
        # terms listed top to bottom in equation order
        ticks = sorted(zip(ax.get_yticks(), (t.get_text() for t in ax.get_yticklabels())), reverse=True)
        assert [label for _, label in ticks] == [plots.term_label(n) for n in eq.names]
        (container,) = ax.containers
        segments = container.lines[2][0].get_segments()
        assert len(segments) == len(eq.terms)
        half = np.array([(seg[1, 0] - seg[0, 0]) / 2 for seg in segments])
        np.testing.assert_allclose(half, 3 * eq.stds / np.abs(eq.coefs), rtol=1e-12)
        texts = [a.get_text() for a in ax.texts]
        assert texts == [format_uncertain(t.coef, t.std) for t in eq.terms]
    fig.savefig(tmp_path / "uncertainty.png", dpi=60)


def test_missing_matplotlib_says_how_to_install(duffing_case, monkeypatch):
    _, model, _ = duffing_case
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    with pytest.raises(
        ImportError,
        match=exactly(
            "figures: expected matplotlib to be installed, received ImportError; "
            "pip install matplotlib (or pip install '.[plot]' from a clone of "
            "symsbl, pip install 'symsbl[plot]' from an index)"
        ),
    ):
        plots.coefficient_uncertainty(model)


def test_cli_plot_without_matplotlib_is_one_line_not_a_traceback(duffing_case, tmp_path, capsys, monkeypatch):
    from symsbl._cli import main

    _, model, validation = duffing_case
    model.save(tmp_path / "model.json")
    symsbl.write_trajectory(validation.measured, tmp_path / "held.npz")
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    code = main(
        ["simulate", str(tmp_path / "model.json"), str(tmp_path / "held.npz"), "--plot", str(tmp_path / "f.png")]
    )
    assert code == 2
    assert capsys.readouterr().err.strip() == (
        "symsbl simulate: error: figures: expected matplotlib to be installed, received ImportError; pip install "
        "matplotlib (or pip install '.[plot]' from a clone of symsbl, pip install 'symsbl[plot]' from an index)"
    )
    assert not (tmp_path / "f.png").exists()


@pytest.fixture(scope="module")
def friction_case():
    """Hidden Coulomb friction under the 100 N, 10 Hz sine; held out at 10 N, as in test_discrepancy."""
    system = symsbl.systems.coulomb(kc=1.0)
    train = symsbl.simulate(system, symsbl.time_grid(3.0, 16384.0), inputs=symsbl.Sine(100.0, 10.0), method="rk4")
    held = symsbl.simulate(system, symsbl.time_grid(1.5, 16384.0), inputs=symsbl.Sine(10.0, 10.0), method="rk4")
    train, held = train.with_noise(0.004, seed=5), held.with_noise(0.004, seed=1005)
    report = symsbl.discrepancy(train, "x1: x2; x2: F, x1, x2", heldout=held, rule=symsbl.DecisionRule(n_bootstrap=0))
    return report, held


@pytest.mark.slow
def test_discrepancy_figure_panels(friction_case, tmp_path):
    report, held = friction_case
    assert [a.effect for a in report.added] == ["coulomb_friction"]
    fig = plots.discrepancy_figure(report, held)
    assert len(fig.axes) == 4  # (a), (b), (c) and the colour bar of (b)
    ax_a, ax_b, ax_c, _ = fig.axes
    # (a) measured, before and after; the re-simulated error falls
    assert [line.get_label().split(" ")[0] for line in ax_a.lines] == ["measured", "before", "after"]
    before = symsbl.validate_model(report.initial, held, method="rk4")
    after = symsbl.validate_model(report.final, held, method="rk4")
    assert f"{100 * before.nrmse['x2']:.3g} %" in ax_a.lines[1].get_label()
    assert after.nrmse["x2"] < before.nrmse["x2"] / 3
    # (b) the residual map of the first step over displacement x velocity
    x_edges, v_edges, grid = report.steps[0].disagreement.residual_map
    (mesh,) = ax_b.collections
    assert mesh.get_array().size == grid.size
    assert (ax_b.get_xlabel(), ax_b.get_ylabel()) == ("x1", "x2")
    # (c) one bar per scored candidate at its gain, the threshold line, the added effect highlighted
    step = report.steps[0]
    scored = [c for c in step.scores if np.isfinite(c.evidence_gain)]
    assert len(ax_c.patches) == len(scored)
    np.testing.assert_allclose([p.get_width() for p in ax_c.patches], [c.evidence_gain for c in scored])
    ticks = sorted(zip(ax_c.get_yticks(), (t.get_text() for t in ax_c.get_yticklabels())), reverse=True)
    assert [label for _, label in ticks] == [c.label for c in scored]  # best on top
    (threshold,) = [line for line in ax_c.lines if line.get_label().startswith("threshold")]
    assert threshold.get_xdata()[0] == step.threshold
    colours = {c.label: p.get_facecolor() for c, p in zip(scored, ax_c.patches)}
    highlighted = [label for label, rgba in colours.items() if rgba == matplotlib.colors.to_rgba(AFTER)]
    assert highlighted == ["coulomb_friction"]
    path = tmp_path / "discrepancy.png"
    fig.savefig(path, dpi=60)
    assert path.stat().st_size > 10_000


@pytest.mark.slow
def test_discrepancy_figure_equation_error_and_without_records(friction_case):
    report, held = friction_case
    equation = dataclasses.replace(report, error_measure="equation")
    ax_a = plots.discrepancy_figure(equation, held).axes[0]
    assert "residual" in ax_a.get_title() and "equation error" in ax_a.get_title()
    assert [line.get_label().split(" ")[0] for line in ax_a.lines[:2]] == ["before", "after"]
    ax_a = plots.discrepancy_figure(report).axes[0]
    assert not ax_a.lines and "pass heldout=" in ax_a.texts[0].get_text()


@pytest.mark.slow
def test_discrepancy_figure_errors(friction_case):
    report, held = friction_case
    with pytest.raises(
        DataError,
        match=exactly(
            "report: expected a DiscrepancyReport from symsbl.discrepancy with at "
            "least one iteration, received IdentifiedModel"
        ),
    ):
        plots.discrepancy_figure(report.final, held)
    with pytest.raises(
        DataError, match=exactly("heldout: expected a Trajectory (the held-out record), received ndarray")
    ):
        plots.discrepancy_figure(report, held.states)


def test_model_path_figure_draws_one_row_per_equation_and_rings_each_choice_once(duffing_case):
    """Two equations each with its own path (the equation error's, per equation): a row of panels for each,
    titled by its left-hand side, each path's points where they belong, the chosen structure ringed once per
    path and labelled once in the figure; the residual tests span the rows."""
    _, model, _ = duffing_case
    E = symsbl.PathEntry
    path = symsbl.ModelPath(
        (
            E((("v1", ("x1",)),), 1, -90.0, -95.0, 0.30, 0.02, "path"),
            E((("v1", ("x1", "F")),), 2, -50.0, -60.0, 0.05, 0.0, "equation error", chosen=True),
            E((("v2", ("x2",)),), 1, -80.0, -85.0, 0.20, 0.0, "path", chosen=True),
            E((("v2", ("x2", "F")),), 2, -79.0, -89.0, 0.21, 0.01, "equation error"),
            E((("v2", ("x2", "F", "x1")),), 3, -78.0, -93.0, 0.22, 0.01, "path"),
        ),
        "rule",
    )
    fig = plots.model_path_figure(dataclasses.replace(model, path=path))
    cv1, ev1, cv2, ev2, res = fig.axes
    assert [ax.get_title() for ax in (cv1, ev1, cv2, ev2)] == [
        "model path of v1'",
        "evidence of v1'",
        "model path of v2'",
        "evidence of v2'",
    ]
    points = cv2.lines[0].get_data() if cv2.lines else None
    np.testing.assert_allclose(points[0], [1, 2, 3])
    np.testing.assert_allclose(points[1], [20.0, 21.0, 22.0])
    for ax, size in ((cv1, 2), (cv2, 1), (ev1, 2), (ev2, 1)):  # the ring: once, at the chosen size
        assert [line.get_data()[0][0] for line in ax.lines if line.get_markersize() == 10] == [size]
    labels = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
    assert labels == ["chosen"]
    assert res.get_title() == "residual tests"
