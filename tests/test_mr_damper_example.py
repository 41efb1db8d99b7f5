"""The MR damper example's pieces against references: an independent integrator, a known model, the records.

The example's saved model is scored on the shared record in ``test_examples.py`` (its identification, 20 minutes,
runs with ``--identify``); these checks need no data.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import _mr_damper as mr  # noqa: E402

import symsbl  # noqa: E402

FS = 1000.0


def synthetic(seconds: float = 2.0, seed: int = 3) -> mr.Record:
    """A band-limited random displacement (cm) and a voltage switching between 0 and 2.25 V, force zero."""
    rng = np.random.default_rng(seed)
    n = int(seconds * FS)
    f = np.fft.rfftfreq(n, 1 / FS)
    spectrum = np.where((f > 0.5) & (f < 20), rng.normal(size=f.size) + 1j * rng.normal(size=f.size), 0)
    D = np.fft.irfft(spectrum, n)
    D *= 0.2 / D.std()
    V = np.gradient(D, 1 / FS)
    Y = np.where(np.sin(2 * np.pi * 1.3 * np.arange(n) / FS + 0.4) > 0, 2.25, 0.0)
    return mr.Record(D, V, Y, np.zeros(n), FS)


def test_the_published_model_matches_an_independent_integrator():
    rec = synthetic()
    p = mr.SPENCER
    splines = [CubicSpline(rec.t, x) for x in (rec.D, rec.V, rec.Y)]

    def rhs(t, s):  # the model of the data's README, written out again in numpy
        y, z, u = s
        x, xd, v = (f(t) for f in splines)
        c0, c1 = p["c0a"] + p["c0b"] * u, p["c1a"] + p["c1b"] * u
        dy = ((p["alpha_a"] + p["alpha_b"] * u) * z + c0 * xd + p["k0"] * (x - y)) / (c0 + c1)
        r = xd - dy
        dz = -p["gamma"] * abs(r) * z * abs(z) - p["beta"] * r * z**2 + p["A"] * r
        return [dy, dz, -p["eta"] * (u - v)]

    sol = solve_ivp(rhs, (0, rec.t[-1]), [rec.D[0], 0.0, rec.Y[0]], t_eval=rec.t, rtol=1e-9, atol=1e-12)
    y, z, u = sol.y
    c0, c1 = p["c0a"] + p["c0b"] * u, p["c1a"] + p["c1b"] * u
    dy = ((p["alpha_a"] + p["alpha_b"] * u) * z + c0 * rec.V + p["k0"] * (rec.D - y)) / (c0 + c1)
    reference = c1 * dy + p["k1"] * (rec.D - p["x0"])
    # the rates are cubic splines in both: the forces agree to the RK4 step's error
    assert mr.rms(mr.spencer_force(rec) - reference) < 1e-3 * reference.std()


def test_the_start_finds_the_law_and_coefficients_of_a_model_it_can_express():
    rec = synthetic(seconds=3.0)
    truth_force = [-50.0, 10.0, 20.0, -0.05, 5.0, 15.0, -0.1, 6e4, 2e4]  # as mr.force_terms([z1])
    truth = mr.damper_model(mr.RATES[1], [(-1 / mr.YIELDS[3] ** 2, 0.0, 0.0)], truth_force)
    rec = mr.Record(rec.D, rec.V, rec.Y, mr.force(truth, rec), rec.fs)
    model, guesses = mr.start(rec, 1)
    assert model.equation("u").coef("Y - u") == mr.RATES[1]
    assert model.equation("z1").terms[1].coef == pytest.approx(-1 / mr.YIELDS[3] ** 2)
    np.testing.assert_allclose(model.equation("F").coefs, truth_force, rtol=1e-3, atol=1e-3)
    assert set(guesses) == {"u", "z1"}


def test_a_record_reads_with_its_rate_from_fs_or_t_and_a_bad_cell_is_named(tmp_path):
    rec = synthetic(seconds=0.2)
    rows = ["t,D,V,Y,F,fs"] + [
        f"{t},{d},{v},{y},{f},{FS if k == 0 else ''}"
        for k, (t, d, v, y, f) in enumerate(zip(rec.t, *rec.inputs.T, rec.F))
    ]
    path = tmp_path / "damper.csv"
    path.write_text("\n".join(rows) + "\n")
    read = mr.read_record(path)
    assert read.fs == FS and np.array_equal(read.D, rec.D)
    path.write_text("\n".join(r.rsplit(",", 1)[0] for r in rows) + "\n")  # no fs column: the rate from t
    assert mr.read_record(path).fs == pytest.approx(FS)
    rows[5] = rows[5].replace(str(rec.D[4]), "n/a", 1)
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(ValueError, match="line 6, column D: expected a number, received 'n/a'"):
        mr.read_record(path)
    path.write_text("t,D,V,F\n" + "\n".join(f"{k},0,0,0" for k in range(200)))
    with pytest.raises(ValueError, match="no column Y"):
        mr.read_record(path)


@pytest.mark.parametrize("voltage, bounded", [(1.9, True), (2.1, False)])
def test_a_law_saturates_inside_its_bounded_voltages_and_runs_away_past_them(voltage, bounded):
    law = (-1e4, 4e3, 2e3)  # c1 + c2 u < -max(0, c3) while u < (1e4 - 2e3) / 4e3 = 2 V
    model = mr.damper_model(100.0, [law], np.zeros(len(mr.force_terms(mr.hidden_symbols(1)))))
    assert mr.bounded_voltages(model) == pytest.approx((-np.inf, 2.0))
    rec = synthetic(seconds=4.0)
    rec = mr.Record(rec.D, rec.V, np.full(rec.F.size, voltage), rec.F, rec.fs)
    z = symsbl.simulate(
        model.to_system(),
        rec.t,
        inputs=rec.inputs,
        x0=[voltage, 0.0],
        method="rk4",
        substeps=16,
        on_divergence="truncate",
    ).column("z1")
    if bounded:
        saturation = 1 / np.sqrt(8e3 - 4e3 * voltage)  # loading: z' = V (1 - (8e3 - 4e3 u) z^2)
        assert z.size == rec.F.size and np.max(np.abs(z)) <= saturation * (1 + 1e-6)
    else:  # no saturation loading: the state grows without bound
        assert z.size < rec.F.size or np.max(np.abs(z)) > 1e3


def test_the_active_part_ends_where_the_damper_rests():
    rec = synthetic(seconds=3.0)
    still = np.arange(rec.F.size) >= 2000
    rested = mr.Record(np.where(still, rec.D[2000], rec.D), np.where(still, 0.0, rec.V), rec.Y, rec.F, FS)
    assert abs(mr.active_end(rested) - 2000) <= 0.05 * FS  # within half the 0.1 s window
    assert mr.active_end(rec) == rec.F.size
    span = mr.spans(rested)
    assert span["fit"].start == 0 and span["test"].stop == mr.active_end(rested)
