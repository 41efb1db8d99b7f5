"""The F-16 example's pieces against closed forms: the modal fit, the law's equivalent linearization, the records.

The example itself (identification and scores on the benchmark's data) runs in ``test_examples.py``;
these checks need no data.
"""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import _f16  # noqa: E402
import _f16_law  # noqa: E402

#: A three-mode structure: natural frequencies (Hz), damping ratios, residues r_ji = phi_j phi_drive.
FREQS = np.array([4.1, 7.3, 11.6])
ZETA = np.array([0.012, 0.006, 0.02])
RESIDUES = np.array([[0.8, 0.5, 0.3], [0.6, -0.9, 0.4], [0.2, 1.3, -0.5]])


def accelerance(f):
    """Acceleration per unit force of the structure: ``sum_i r_ji s^2 / (s^2 + 2 zeta w s + w^2)``."""
    s = 2j * np.pi * np.asarray(f)
    w = 2 * np.pi * FREQS
    den = s[None] ** 2 + 2 * (ZETA * w)[:, None] * s[None] + (w**2)[:, None]
    return RESIDUES @ (s[None] ** 2 / den)


def modal_coefficients():
    """The output coefficients (c_q, c_p, d) of that structure: ``a = sum r (F - k q - c p)``."""
    w = 2 * np.pi * FREQS
    return np.hstack([-RESIDUES * w**2, -RESIDUES * 2 * ZETA * w, RESIDUES.sum(1, keepdims=True)])


def test_the_modal_fit_recovers_a_known_structure():
    f = np.arange(2.0, 15.0, 400 / 8192)
    w, zeta, C = _f16.fit_modes(f, accelerance(f), n_modes=3)
    assert np.allclose(w / (2 * np.pi), FREQS, rtol=1e-6)
    assert np.allclose(zeta, ZETA, rtol=1e-4)
    assert np.allclose(C, modal_coefficients(), rtol=1e-4, atol=1e-6)


def test_a_record_reads_the_same_from_the_benchmarks_csv_layout(tmp_path):
    n = 2 * _f16.PERIOD  # a record holds the period its score leaves out, and one more
    rng = np.random.default_rng(0)
    force, acc = rng.normal(size=n), rng.normal(size=(3, n))
    rows = ["Force,Voltage,Acceleration1,Acceleration2,Acceleration3,Fs"]
    rows += [f"{force[k]:.17g},0.5,{acc[0, k]:.17g},{acc[1, k]:.17g},{acc[2, k]:.17g},400" for k in range(n)]
    path = tmp_path / "level.csv"
    path.write_text("\n".join(rows) + "\n")
    record = _f16.read_record(path)
    assert np.array_equal(record.force, force) and np.array_equal(record.acc, acc) and record.fs == 400.0
    # spaces after the commas, the rate in the first row only, the voltage left blank
    rows = ["Force, Voltage, Acceleration1, Acceleration2, Acceleration3, Fs"]
    rows += [
        f"{force[k]:.17g}, , {acc[0, k]:.17g}, {acc[1, k]:.17g}, {acc[2, k]:.17g}, {'400' if k == 0 else ''}"
        for k in range(n)
    ]
    path.write_text("\n".join(rows) + "\n")
    record = _f16.read_record(path)
    assert np.array_equal(record.force, force) and np.array_equal(record.acc, acc) and record.fs == 400.0
    path.write_text("\n".join(rows[:17]) + "\n")
    with pytest.raises(ValueError, match="two periods or more"):  # 16 rows: nothing to score
        _f16.read_record(path)
    bad = rows[:6] + [rows[6].replace(f"{acc[1, 5]:.17g}", "n/a")] + rows[7:]  # data row 5 is line 7
    path.write_text("\n".join(bad) + "\n")
    with pytest.raises(ValueError, match=r"^line 7, column Acceleration2: expected a number, received 'n/a'$"):
        _f16.read_record(path)
    path.write_text("\n".join(bad[:3] + [""] + bad[3:]) + "\n")  # a blank line above it: the file's own line count
    with pytest.raises(ValueError, match=r"^line 8, column Acceleration2"):
        _f16.read_record(path)


@pytest.mark.slow
def test_the_free_run_of_the_modal_model_meets_the_steady_state_of_its_frequency_response():
    # reference: the periodic steady state, accelerance times the force's spectrum line by line
    record = steady_record()
    rms = np.sqrt(np.mean(record.acc**2, axis=1))
    model = _f16.modal_model(2 * np.pi * FREQS, ZETA, modal_coefficients())
    # what is left is the start's transient, decayed to exp(-zeta w T) ~ 0.3 % after one period
    assert np.all(_f16.score(model, record) < 0.01 * rms)
    stiffer = _f16.modal_model(2 * np.pi * FREQS * 1.01, ZETA, modal_coefficients())
    assert np.all(_f16.score(stiffer, record) > 0.05 * rms)


def steady_record(periods: int = 3) -> "_f16.Record":
    """The structure's periodic steady state under a 2-15 Hz multisine of 10 N RMS, from its accelerance."""
    rng = np.random.default_rng(1)
    spectrum = np.zeros(_f16.PERIOD // 2 + 1, complex)
    spectrum[np.arange(41, 308)] = np.exp(2j * np.pi * rng.random(267))  # 2-15 Hz on the period's grid
    f = np.fft.rfftfreq(_f16.PERIOD, 1 / 400.0)
    period = np.fft.irfft(spectrum, _f16.PERIOD)
    scale = 10.0 / period.std()
    response = np.zeros((3, f.size), complex)
    response[:, 1:] = accelerance(f[1:]) * spectrum[1:] * scale
    steady = np.fft.irfft(response, _f16.PERIOD, axis=-1)
    return _f16.Record(np.tile(period * scale, periods), np.tile(steady, periods), 400.0)


def test_floors_split_a_record_into_what_repeats_in_band_and_the_rest():
    """Closed forms: a 30 Hz line of known amplitude (outside the band, on the period's grid) and white noise
    of known level added to a periodic record are read back as the floors."""
    steady = steady_record(periods=9)
    t = np.arange(steady.force.size) / steady.fs
    rms = np.sqrt(np.mean(steady.acc[:, _f16.PERIOD :] ** 2, axis=1))
    f30 = 614 * steady.fs / _f16.PERIOD  # 30 Hz, on the period's grid
    line = 0.2 * rms[:, None] * np.sqrt(2) * np.sin(2 * np.pi * f30 * t)  # 20 % of each output's RMS
    burst = np.zeros_like(line)
    burst[:, : _f16.PERIOD] = 5 * line[:, : _f16.PERIOD]  # in the first period, which the floors leave out
    clean = _f16.Record(steady.force, steady.acc + line + burst, steady.fs)
    varying, outside = _f16.floors(clean)
    total = np.sqrt(rms**2 + (0.2 * rms) ** 2)  # the line is orthogonal to the band's response
    assert varying == pytest.approx(np.zeros(3), abs=1e-9)
    assert outside == pytest.approx(100 * 0.2 * rms / total, rel=1e-6)
    noise = 0.05 * rms[:, None] * np.random.default_rng(4).standard_normal(steady.acc.shape)
    varying, outside = _f16.floors(_f16.Record(steady.force, steady.acc + noise, steady.fs))
    # 8 x 8192 samples: the estimate of the noise's RMS is within 1 % of it (its own spread is 0.3 %)
    level = 100 * 0.05 * rms / np.sqrt(rms**2 + (0.05 * rms) ** 2)
    assert varying == pytest.approx(level, rel=0.01)
    # the mean of 8 periods keeps 1/sqrt(8) of the white noise, spread evenly over the lines
    share = 1 - np.count_nonzero(_f16.excited(steady.fs)) / (_f16.PERIOD // 2)
    assert outside == pytest.approx(level * np.sqrt(share / 8), rel=0.03)
    with pytest.raises(ValueError, match="three or more"):
        _f16.floors(steady_record(periods=2))


@pytest.mark.slow
def test_validate_prints_each_accelerations_error_and_refuses_a_bad_record(tmp_path, capsys):
    import f16

    record = steady_record()
    rows = ["Force,Voltage,Acceleration1,Acceleration2,Acceleration3,Fs"]
    rows += [
        f"{record.force[k]:.17g},0,{record.acc[0, k]:.17g},{record.acc[1, k]:.17g},{record.acc[2, k]:.17g},400"
        for k in range(record.force.size)
    ]
    good = tmp_path / "level.csv"
    good.write_text("\n".join(rows) + "\n")
    model = _f16.modal_model(2 * np.pi * FREQS, ZETA, modal_coefficients())
    assert f16.validate(model, [str(good)]) == 0
    lines = capsys.readouterr().out.splitlines()
    percents = [float(line.split("(")[1].split(" %")[0]) for line in lines if line.strip().startswith("Acceleration")]
    assert len(percents) == 3 and max(percents) < 1.0  # the generating structure: its start's transient only
    bad = tmp_path / "bad.csv"
    bad.write_text("Force,Fs\n1,400\n")
    assert f16.validate(model, [str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--validate" in err[0] and "Acceleration1-3" in err[0]


def test_the_equivalent_gains_are_the_mean_slopes_of_the_laws_under_a_gaussian_motion():
    # reference: E[f'(x)] by brute force over a million Gaussian samples
    sd = 0.37
    x = np.random.default_rng(2).normal(0.0, sd, 1_000_000)
    slopes = {"q|q|": 2 * np.abs(x), "q^3": 3 * x**2, "p|p|": 2 * np.abs(x), "p^3": 3 * x**2}
    for name, (_, gain) in _f16_law.LAWS.items():
        assert gain(sd) == pytest.approx(slopes[name].mean(), rel=3e-3), name


def test_the_motions_spread_is_that_of_its_steady_state():
    # reference: the standard deviation of the periodic steady state itself, by inverse FFT
    record = steady_record(periods=1)
    force = np.fft.rfft(record.force)
    s = 2j * np.pi * np.fft.rfftfreq(_f16.PERIOD, 1 / 400.0)
    k, c = (2 * np.pi * 7.3) ** 2, 0.4
    q = np.zeros_like(force)
    q[1:] = force[1:] / (s[1:] ** 2 + c * s[1:] + k)
    sd_q, sd_p = _f16_law.motion_sd(k, c, force[1:], s[1:])
    assert sd_q == pytest.approx(np.fft.irfft(q, _f16.PERIOD).std(), rel=1e-9)
    assert sd_p == pytest.approx(np.fft.irfft(s * q, _f16.PERIOD).std(), rel=1e-9)


def law_structure(laws=("q|q|", "p|p|"), coefs=(-300.0, 0.05)):
    """The three-mode structure with a law in its 7.3 Hz mode, as a joint fit holds it."""
    w, mode = 2 * np.pi * FREQS, 1
    others = [0, 2]
    C = np.hstack(
        [
            -RESIDUES[:, others] * w[others] ** 2,
            -RESIDUES[:, others] * 2 * ZETA[others] * w[others],
            RESIDUES[:, others].sum(1, keepdims=True),
            RESIDUES[:, [mode]],
        ]
    )
    return _f16_law.JointFit(w, ZETA.copy(), mode, tuple(laws), np.array(coefs), C)


def law_spectra(fit, forces_rms=(5.0, 20.0, 60.0)):
    """What the equivalent linearization of ``fit`` predicts at several force levels, as :class:`Spectra`."""
    f = np.fft.rfftfreq(_f16.PERIOD, 1 / 400.0)[41:308]
    s = 2j * np.pi * f
    phases = np.exp(2j * np.pi * np.random.default_rng(3).random(f.size))
    H, F = [], []
    for level in forces_rms:
        force = phases * level * _f16.PERIOD / np.sqrt(2 * f.size)
        w, zeta, t = fit.w, fit.zeta, fit.mode
        k, c = _f16_law.equivalent(w[t] ** 2, 2 * zeta[t] * w[t], fit.laws, fit.coefs, force, s)
        H.append((_f16_law._design(w, zeta, t, k, c, s) @ fit.C.T).T)
        F.append(force)
    rms = np.array([np.sqrt(2 * np.sum(np.abs(h * x) ** 2, axis=1)) / _f16.PERIOD for h, x in zip(H, F)])
    return _f16_law.Spectra(f, np.array(H), np.array(F), rms)


def test_the_joint_fit_recovers_a_law_from_the_levels_it_shapes():
    truth = law_structure()
    spec = law_spectra(truth)
    start_w = truth.w * np.array([1.01, 0.995, 0.99])
    fit = _f16_law.fit_joint(spec, start_w, truth.zeta * 1.2, truth.mode, truth.laws)
    assert np.allclose(fit.w, truth.w, rtol=1e-7) and np.allclose(fit.zeta, truth.zeta, rtol=1e-5)
    assert np.allclose(fit.coefs, truth.coefs, rtol=1e-5)
    assert np.allclose(fit.C, truth.C, rtol=1e-5, atol=1e-8)
    # one linear model cannot serve the three levels: it leaves a misfit where the law leaves none
    linear = _f16_law.fit_joint(spec, start_w, truth.zeta * 1.2, truth.mode, ())
    misfit = [
        np.linalg.norm(_f16_law._solve(np.r_[x.w, x.zeta, x.coefs], spec, x.mode, x.laws)[1]) for x in (fit, linear)
    ]
    assert misfit[1] > 0.05 and misfit[0] < 1e-6 * misfit[1], misfit


def test_a_law_free_fit_is_the_modal_structure_and_a_law_is_named_back():
    linear = _f16_law.model_of(law_structure(laws=(), coefs=()))
    reference = _f16.modal_model(2 * np.pi * FREQS, ZETA, modal_coefficients())
    for eq, ref in zip(linear.equations, reference.equations):
        assert eq.lhs == ref.lhs and np.allclose(eq.coefs, ref.coefs, rtol=1e-12), eq.lhs
    text = _f16_law.describe(_f16_law.model_of(law_structure()))
    assert text.startswith("p2' = F - 2103.8 q - 0.5504 p + 300 q|q| - 0.05 p|p|") and "7.3000 Hz" in text, text


@pytest.mark.slow
def test_the_simulated_law_meets_its_equivalent_linearization():
    # reference: the nonlinear model's own free run at 20 N RMS, its response on the excited lines in
    # periods 2-3; the equivalent linear response (what the joint fit is fitted to) is an approximation
    # (the law's distortion falls on the excited lines too): within a fifth of it, and four times nearer
    # than the linear mode's (measured: 16 % and 74 %)
    truth = law_structure()
    spec = law_spectra(truth, forces_rms=(20.0,))
    spectrum = np.zeros(_f16.PERIOD // 2 + 1, complex)
    spectrum[41:308] = spec.F[0]
    force = np.tile(np.fft.irfft(spectrum, _f16.PERIOD), 3)
    run = _f16.simulate(_f16_law.model_of(truth), _f16.Record(force, np.zeros((3, force.size)), 400.0))
    response = np.fft.rfft(run[:, _f16.PERIOD :].reshape(3, 2, _f16.PERIOD), axis=-1).mean(1)[:, 41:308]
    predicted = spec.H[0] * spec.F[0]
    linear = law_spectra(replace(truth, coefs=np.zeros(2)), forces_rms=(20.0,))
    error = np.linalg.norm(response - predicted) / np.linalg.norm(predicted)
    linear_error = np.linalg.norm(response - linear.H[0] * linear.F[0]) / np.linalg.norm(predicted)
    assert error < 0.2 and error < 0.25 * linear_error, (error, linear_error)
