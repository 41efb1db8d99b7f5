"""The F-16 example's pieces: records, their spectra, the modal fit and model, the score.

See ``f16.py`` for the model and its argument; this module is what that script runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
from _csvrows import column, number, read_rows  # beside this module
from scipy.io import loadmat
from scipy.optimize import least_squares

import symsbl
from symsbl import AlgebraicOutput, Equation, IdentifiedModel, TermEstimate

PERIOD = 8192  # samples per multisine period
BAND = (2.0, 15.0)  # Hz, the excited band
#: Modes fitted to the band: the six visible peaks, and as many more for the close modes
#: and the residual of modes outside it (fewer leave 4 % of the response unexplained).
N_MODES = 12
#: Lightest damping ratio a mode may take: an undamped pole of a fit rings for ever in free run.
MIN_DAMPING = 2e-3
ACCELERATIONS = ("a1", "a2", "a3")


@dataclass(frozen=True)
class Record:
    """One multisine record: the force (N), the three accelerations (m/s^2, rows) and the rate."""

    force: np.ndarray
    acc: np.ndarray
    fs: float


def have_data(folder: Path) -> bool:
    return all((folder / f"F16Data_FullMSine_Level{n}.mat").is_file() for n in (1, 3, 5, 7))


def read_record(path: Path) -> Record:
    """A benchmark record from its .mat file or its CSV layout (Force, Voltage, Acceleration1-3, Fs)."""
    if path.suffix.lower() == ".mat":
        raw = loadmat(path)
        return Record(
            raw["Force"].ravel().astype(float),
            np.atleast_2d(raw["Acceleration"]).astype(float),
            float(np.ravel(raw["Fs"])[0]),
        )
    rows, lines = read_rows(path)
    needed = ["Force", "Acceleration1", "Acceleration2", "Acceleration3"]
    if len(rows) < 2 * PERIOD:  # the score is taken after the first period
        raise ValueError(f"{len(rows)} rows, where a record holds two periods or more ({PERIOD} samples each)")
    missing = [name for name in [*needed, "Fs"] if name not in rows[0]]
    if missing:
        raise ValueError(f"no column {', '.join(missing)}")
    force, *acc = (column(rows, lines, name) for name in needed)
    at = next((k for k, r in enumerate(rows) if r["Fs"]), 0)  # the rate may be given in the first row only
    return Record(force, np.vstack(acc), number(rows[at]["Fs"], lines[at], "Fs"))


def excited(fs: float) -> np.ndarray:
    """The excited lines of a period at the rate ``fs`` (a mask of its rfft)."""
    f = np.fft.rfftfreq(PERIOD, 1 / fs)
    return (f >= BAND[0] - 1e-9) & (f <= BAND[1] + 1e-9)


def _spectrum(x: np.ndarray) -> np.ndarray:
    """The spectrum of one period (FFT units), averaged over periods 2-9 (the last axis holds time)."""
    periods = x.shape[-1] // PERIOD
    return np.fft.rfft(x[..., : periods * PERIOD].reshape(*x.shape[:-1], periods, PERIOD)[..., 1:, :], axis=-1).mean(-2)


def line_frequencies(fs: float) -> np.ndarray:
    """The excited lines' frequencies (Hz) at the rate ``fs``."""
    return np.fft.rfftfreq(PERIOD, 1 / fs)[excited(fs)]


def force_lines(rec: Record) -> np.ndarray:
    """The force's spectrum on the excited lines, periods 2-9 averaged."""
    return _spectrum(rec.force)[excited(rec.fs)]


def response(rec: Record) -> tuple[np.ndarray, np.ndarray]:
    """The force's spectrum on the excited lines and the accelerations' response to it (rows), periods 2-9."""
    force, lines = _spectrum(rec.force), excited(rec.fs)
    return force[lines], (_spectrum(rec.acc) / force)[:, lines]


def frf(records: list[Record]):
    """The mean frequency response acceleration/force on the excited lines, periods 2-9 of each record."""
    return line_frequencies(records[0].fs), np.mean([response(rec)[1] for rec in records], axis=0)


def _design(f, w, zeta):
    s = 2j * np.pi * f
    den = s[None] ** 2 + 2 * zeta[:, None] * w[:, None] * s[None] + w[:, None] ** 2
    return np.vstack([1 / den, s[None] / den, np.ones_like(s)[None]]).T


def _outputs(f, H, w, zeta):
    """Output coefficients (c_q, c_p, d) per acceleration by least squares, and the residuals."""
    B = _design(f, w, zeta)
    Br = np.vstack([B.real, B.imag])
    Y = np.vstack([H.real.T, H.imag.T])
    C, *_ = np.linalg.lstsq(Br, Y, rcond=None)
    return C.T, (Br @ C - Y).T.ravel()


def fit_modes(f, H, n_modes: int = N_MODES):
    """Natural frequencies (rad/s), damping ratios and output coefficients of a modal fit to ``H``.

    Variable projection: the output coefficients are linear given the poles, the poles (started at
    the band's peaks and spread over the rest) are fitted by nonlinear least squares.
    """
    mag = np.abs(H).sum(0)
    peaks = [i for i in range(1, f.size - 1) if mag[i] >= mag[i - 1] and mag[i] >= mag[i + 1]]
    peaks = sorted(sorted(peaks, key=lambda i: -mag[i])[: n_modes // 2])
    spread = np.linspace(BAND[0] + 0.5, BAND[1] - 1.0, n_modes - len(peaks))
    f0 = np.sort(np.concatenate([f[peaks], spread]))
    p0 = np.concatenate([2 * np.pi * f0, np.full(n_modes, 0.02)])
    lower = np.concatenate([np.full(n_modes, 2 * np.pi * 0.5), np.full(n_modes, MIN_DAMPING)])
    upper = np.concatenate([np.full(n_modes, 2 * np.pi * 40.0), np.full(n_modes, 3.0)])
    fit = least_squares(lambda p: _outputs(f, H, p[:n_modes], p[n_modes:])[1], p0, bounds=(lower, upper))
    w, zeta = fit.x[:n_modes], fit.x[n_modes:]
    order = np.argsort(w)
    w, zeta = w[order], zeta[order]
    return w, zeta, _outputs(f, H, w, zeta)[0]


def _term(expr, coef, fixed=False):
    return TermEstimate(expr, float(coef), 0.0, fixed=bool(fixed))


def modal_model(w, zeta, C, extra=None) -> IdentifiedModel:
    """The modal model of natural frequencies ``w``, damping ratios ``zeta`` and output coefficients ``C``,
    with ``extra`` terms: a function of the modes' q, p and the force giving, per equation name, its
    (expression, coefficient) pairs."""
    n = w.size
    q = [ca.SX.sym(f"q{i + 1}") for i in range(n)]
    p = [ca.SX.sym(f"p{i + 1}") for i in range(n)]
    force = ca.SX.sym("F")
    extra = extra(q, p, force) if extra else {}
    equations, states = [], []
    for i in range(n):
        states += [q[i], p[i]]
        equations.append(Equation(f"q{i + 1}", (_term(p[i], 1.0),), np.zeros((1, 1)), 0.0, 0.0, fixed=True))
        terms = [_term(force, 1.0, fixed=True), _term(q[i], -(w[i] ** 2)), _term(p[i], -2 * zeta[i] * w[i])]
        terms += [_term(e, c) for e, c in extra.get(f"p{i + 1}", ())]
        equations.append(Equation(f"p{i + 1}", tuple(terms), np.zeros((len(terms),) * 2), 0.0, 0.0))
    for j, name in enumerate(ACCELERATIONS):
        terms = [_term(q[i], C[j, i]) for i in range(n)] + [_term(p[i], C[j, n + i]) for i in range(n)]
        terms += [_term(force, C[j, -1])] + [_term(e, c) for e, c in extra.get(name, ())]
        equations.append(Equation(name, tuple(terms), np.zeros((len(terms),) * 2), 0.0, 0.0, algebraic=True))
    return IdentifiedModel(
        tuple(states),
        (force,),
        tuple(equations),
        kinematics=tuple((f"q{i + 1}", f"p{i + 1}") for i in range(n)),
        measured=(),
        outputs=tuple(AlgebraicOutput(a) for a in ACCELERATIONS),
        metadata={"example": "f16", "modes_hz": [round(float(x) / (2 * np.pi), 4) for x in w]},
    )


def distorted_mode(w, records: list[Record]) -> int:
    """The mode nearest the line whose response changes most between the weakest and strongest record."""
    weakest, strongest = (min(records, key=lambda r: r.force.std()), max(records, key=lambda r: r.force.std()))
    f, low = frf([weakest])
    high = frf([strongest])[1]
    worst = f[np.argmax(np.abs(high - low).sum(0))]
    return int(np.argmin(np.abs(w - 2 * np.pi * worst)))


def _free_run(model: IdentifiedModel, rec: Record) -> symsbl.Trajectory:
    """The model's states and outputs from rest, driven by the record's measured force."""
    t = np.arange(rec.force.size) / rec.fs
    force = symsbl.Sampled(t, rec.force, kind="cubic")
    return symsbl.simulate(model.to_system(), t, inputs=force, method="rk4", substeps=4)


def simulate(model: IdentifiedModel, rec: Record) -> np.ndarray:
    """Free-run accelerations (rows) from rest, driven by the measured force."""
    run = _free_run(model, rec)
    return np.vstack([run.states[:, run.state_names.index(a)] for a in ACCELERATIONS])


def rms(rec: Record) -> np.ndarray:
    """Each acceleration's RMS over periods 2-9, what the errors are given in % of."""
    return np.sqrt(np.mean(rec.acc[:, PERIOD:] ** 2, axis=1))


def score(model: IdentifiedModel, rec: Record) -> np.ndarray:
    """RMS of the free-run error per acceleration after the first period (periods 2-9 of a benchmark record; m/s^2)."""
    error = (simulate(model, rec) - rec.acc)[:, PERIOD:]
    return np.sqrt(np.mean(error**2, axis=1))


def floors(rec: Record) -> tuple[np.ndarray, np.ndarray]:
    """What a model of the band cannot be expected to reproduce, per acceleration, in % of its RMS.

    Both are taken over the whole periods after the first (periods 2-9 of a benchmark record), and in
    % of each acceleration's RMS there. The first, the part that does not repeat from period to period
    (noise, and a response that is not periodic): no deterministic model driven by a periodic force
    predicts it. It is the RMS of each period's deviation from the mean period, unbiased for the mean's
    own share (``n / (n - 1)`` over ``n`` periods). The second, the mean period's content outside the
    excited band: the harmonics that a nonlinearity throws out of the band (and drift below it), which
    a model of the band's linear dynamics does not produce. It still holds the noise the mean keeps,
    ``1 / sqrt(n)`` of it, over the lines outside the band: about a third of the first at 9 periods.
    """
    periods = rec.force.size // PERIOD - 1
    if periods < 2:
        raise ValueError(f"{periods + 1} periods, where the floors need three or more")
    y = rec.acc[:, PERIOD : (periods + 1) * PERIOD].reshape(rec.acc.shape[0], periods, PERIOD)
    mean = y.mean(axis=1)
    varying = np.sqrt(np.sum((y - mean[:, None]) ** 2, axis=(1, 2)) / ((periods - 1) * PERIOD))
    spectrum = np.fft.rfft(mean, axis=-1)
    spectrum[:, excited(rec.fs)] = 0.0
    outside = np.sqrt(np.mean(np.fft.irfft(spectrum, PERIOD, axis=-1) ** 2, axis=1))
    spread = np.sqrt(np.mean(y**2, axis=(1, 2)))
    return 100 * varying / spread, 100 * outside / spread


def format_scores(errors, rec: Record) -> str:
    return "   ".join(f"{a} {e:.4f} m/s^2 ({100 * e / r:.1f} %)" for a, e, r in zip(ACCELERATIONS, errors, rms(rec)))


def score_table(model: IdentifiedModel, rec: Record) -> str:
    """One line per acceleration: the free-run error RMS after the first period, in m/s^2 and in % of its RMS."""
    return "\n".join(
        f"  Acceleration{j + 1}: {e:.4f} m/s^2 ({100 * e / r:.2f} % of its RMS {r:.4f} m/s^2)"
        for j, (e, r) in enumerate(zip(score(model, rec), rms(rec)))
    )


def floor_lines(rec: Record) -> str:
    """The record's :func:`floors` as two lines (empty for a record of fewer than three periods)."""
    if rec.force.size // PERIOD < 3:
        return ""
    varying, outside = floors(rec)
    cells = ", ".join
    return (
        f"  not repeated from period to period (no model predicts it): "
        f"{cells(f'a{j + 1} {v:.1f} %' for j, v in enumerate(varying))}\n"
        f"  outside {BAND[0]:g}-{BAND[1]:g} Hz (harmonics of the nonlinearity, drift): "
        f"{cells(f'a{j + 1} {v:.1f} %' for j, v in enumerate(outside))}"
    )
