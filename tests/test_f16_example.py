"""The F-16 example's pieces against closed forms: the modal fit, the interface's motion, the records, the score.

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


def test_the_interface_motion_is_the_modes_displacement_difference():
    # for a modal structure, x_j = sum_i r_ji q_i exactly: x2 - x3 is (r_2 - r_3) q, no velocity part
    g, h = _f16.relative_motion(2 * np.pi * FREQS, ZETA, modal_coefficients())
    assert np.allclose(g, RESIDUES[1] - RESIDUES[2], rtol=1e-9)
    assert np.allclose(h, 0.0, atol=1e-9)


def test_a_record_reads_the_same_from_the_benchmarks_csv_layout(tmp_path):
    rng = np.random.default_rng(0)
    force, acc = rng.normal(size=16), rng.normal(size=(3, 16))
    rows = ["Force,Voltage,Acceleration1,Acceleration2,Acceleration3,Fs"]
    rows += [f"{force[k]:.17g},0.5,{acc[0, k]:.17g},{acc[1, k]:.17g},{acc[2, k]:.17g},400" for k in range(16)]
    path = tmp_path / "level.csv"
    path.write_text("\n".join(rows) + "\n")
    record = _f16.read_record(path)
    assert np.array_equal(record.force, force) and np.array_equal(record.acc, acc) and record.fs == 400.0


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


def test_the_interface_terms_a_model_keeps_are_named_back():
    w = 2 * np.pi * FREQS
    spec = _f16.interface(w, ZETA, modal_coefficients(), scale=1e-4, modes=[1])
    model = _f16.modal_model(w, ZETA, modal_coefficients(), _f16.joint_candidates(spec), free=[1])
    kept = {"r|r|": 2.5, "d^3": -0.75}  # two of the candidates, as a fit might keep them
    equations = []
    for eq in model.equations:
        terms = tuple(
            replace(t, coef=kept.get(_f16.LAWS[k % len(_f16.LAWS)], 0.0)) if k >= 0 else t
            for t, k in zip(eq.terms, _law_index(eq))
        )
        equations.append(replace(eq, terms=tuple(t for t in terms if t.coef != 0.0)))
    model = replace(model, equations=tuple(equations), metadata={"interface": spec})
    text = _f16.joint_law(model)
    assert "p2' += -0.75 (0) d^3  +2.5 (0) r|r|" in text and "a2 += -0.75 (0) d^3" in text, text
    assert "p1'" not in text and "a1" not in text


def _law_index(eq):
    """Per term of ``eq``, its position among the interface's candidates (-1: a term of the linear structure)."""
    linear = sum(1 for t in eq.terms if t.name in {"F"} or t.name[0] in "qp" and t.name[1:].isdigit())
    return [k - linear if k >= linear else -1 for k in range(len(eq.terms))]
