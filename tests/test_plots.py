"""Figures: they render, and what they draw is the model's posterior."""

import dataclasses
import sys

import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")

from matplotlib.collections import PolyCollection  # noqa: E402

import symsbl  # noqa: E402
from symsbl import plots  # noqa: E402
from symsbl.errors import DataError  # noqa: E402

FS = 4096.0


@pytest.fixture(scope="module")
def duffing_case():
    system = symsbl.systems.duffing()
    train = symsbl.simulate(system, symsbl.time_grid(1.0, FS), inputs=symsbl.Sine(100.0, 10.0)).with_noise(0.004, seed=0)
    model = symsbl.identify(train, symsbl.paper(system.states, system.inputs, degree=3))
    heldout_input = symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1)
    heldout = symsbl.simulate(system, symsbl.time_grid(0.5, FS), inputs=heldout_input).with_noise(0.004, seed=2)
    validation = symsbl.validate_model(model, heldout, n_band=6)
    return train, model, validation


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
    np.testing.assert_array_equal(ax_b.lines[0].get_ydata(), validation.measured.column("x1")[(validation.measured.t >= 0.1) & (validation.measured.t <= 0.2)])
    fig.savefig(tmp_path / "figure2_x1.png", dpi=60)


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
    with pytest.raises(DataError, match=r"state must be one of the model's states \['x1', 'x2'\]; received 'x3'"):
        plots.figure2(model, validation, state="x3")
    with pytest.raises(DataError, match=r"window must be \(t_start, t_stop\)"):
        plots.figure2(model, validation, window=(0.3, 0.1))
    with pytest.raises(DataError, match="validation must be a Validation"):
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
        assert texts == [symsbl.model.format_uncertain(t.coef, t.std) for t in eq.terms]
    fig.savefig(tmp_path / "uncertainty.png", dpi=60)


def test_missing_matplotlib_says_how_to_install(duffing_case, monkeypatch):
    _, model, _ = duffing_case
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    with pytest.raises(ImportError, match=r"pip install symsbl\[plot\]"):
        plots.coefficient_uncertainty(model)
