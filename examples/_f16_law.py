"""The F-16 example's nonlinear mode: one law whose equivalent stiffness and damping follow the level.

Equivalent (statistical) linearization: under a Gaussian motion of standard deviation ``sd``, a force
law ``f(q)`` acts on average as the stiffness ``E[f'(q)]``: ``q|q|`` as ``2 sqrt(2/pi) sd``, ``q^3``
as ``3 sd^2``; a law of the velocity ``p`` likewise as a damping. Under a random-phase multisine the
modes' motion is close to Gaussian, so one law in the distorted mode gives every force level its own
linear response, with ``sd`` from that response itself (a fixed point). All levels' frequency
responses are fitted at once by variable projection: the output coefficients are linear given the
poles and the law's coefficients, which are fitted by nonlinear least squares. The law itself is
chosen by leave-one-level-out: each candidate is fitted on all levels but one and scored by free-run
simulation on the one left out, what a model meets at a level it was not trained on.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import _f16
import casadi as ca
import numpy as np
from scipy.optimize import least_squares

from symsbl import DivergenceError, IdentifiedModel

#: Candidate laws of the distorted mode: name -> (its variable, q or p; its Gaussian equivalent gain of sd).
LAWS = {
    "q|q|": ("q", lambda sd: 2 * np.sqrt(2 / np.pi) * sd),
    "q^3": ("q", lambda sd: 3 * sd**2),
    "p|p|": ("p", lambda sd: 2 * np.sqrt(2 / np.pi) * sd),
    "p^3": ("p", lambda sd: 3 * sd**2),
}
#: The structures compared: a stiffness law, a damping law, both, or none (the linear model).
STRUCTURES = ((), ("q|q|",), ("q^3",), ("p|p|",), ("p^3",), ("q|q|", "p|p|"), ("q|q|", "p^3"), ("q^3", "p|p|"))
#: How far each pole may move from the start: the levels' fits stay with the start's modes.
POLE_RANGE = 0.05


def law_expression(name: str, x):
    """The CasADi expression of the law ``name`` in ``x`` (the mode's q or p)."""
    return {"q|q|": x * ca.fabs(x), "q^3": x**3, "p|p|": x * ca.fabs(x), "p^3": x**3}[name]


def law_values(name: str, x: np.ndarray) -> np.ndarray:
    """The law ``name`` at the values ``x``, as :func:`law_expression` computes it."""
    return x * np.abs(x) if name.endswith("|") else x**3


@dataclass(frozen=True)
class Spectra:
    """The records on the excited lines: frequencies, responses (record, output, line), forces
    (record, line), the outputs' RMS (record, output), each averaged over periods 2-9."""

    f: np.ndarray
    H: np.ndarray
    F: np.ndarray
    rms: np.ndarray

    def subset(self, keep) -> Spectra:
        keep = list(keep)
        return Spectra(self.f, self.H[keep], self.F[keep], self.rms[keep])


def spectra(records: list[_f16.Record]) -> Spectra:
    """The :class:`Spectra` of ``records``."""
    F, H = zip(*(_f16.response(rec) for rec in records))
    rms = np.array([_f16.rms(rec) for rec in records])
    return Spectra(_f16.line_frequencies(records[0].fs), np.array(H), np.array(F), rms)


def motion_sd(k: float, c: float, force: np.ndarray, s: np.ndarray) -> tuple[float, float]:
    """Standard deviations of ``q`` and ``p`` of the mode ``q'' + c q' + k q = F`` in periodic steady state
    (Parseval over one period's excited lines, ``force`` in FFT units of one period)."""
    q = force / (s**2 + c * s + k)
    return tuple(float(np.sqrt(2 * np.sum(np.abs(x) ** 2)) / _f16.PERIOD) for x in (q, s * q))


def equivalent(k0: float, c0: float, laws, coefs, force: np.ndarray, s: np.ndarray) -> tuple[float, float]:
    """The mode's equivalent stiffness and damping under ``force``: a fixed point of its own motion's spread."""
    k, c = k0, c0
    for _ in range(100):
        sd = dict(zip("qp", motion_sd(k, c, force, s)))
        gains = {v: 0.0 for v in "qp"}
        for name, coef in zip(laws, coefs):
            variable, gain = LAWS[name]
            gains[variable] += coef * gain(sd[variable])
        k_new, c_new = k0 + gains["q"], c0 + gains["p"]
        if abs(k_new - k) <= 1e-10 * k0 and abs(c_new - c) <= 1e-10 * k0:
            break
        k, c = 0.5 * (k + k_new), 0.5 * (c + c_new)  # damped: the spread falls as the stiffness moves
    return k_new, c_new


@dataclass(frozen=True)
class JointFit:
    """One model of every level: poles (rad/s), damping ratios, the distorted mode, its laws and their
    coefficients, and the output coefficients (output, column) in :func:`_design`'s layout."""

    w: np.ndarray
    zeta: np.ndarray
    mode: int
    laws: tuple
    coefs: np.ndarray
    C: np.ndarray


def _design(fit_w, fit_zeta, mode, k, c, s):
    """Columns of the responses: the other modes' ``1/den`` and ``s/den``, the direct term and the
    distorted mode's ``s^2 / (s^2 + c s + k)`` (an accelerometer's reading ``phi p'`` of it)."""
    others = [i for i in range(fit_w.size) if i != mode]
    den = s[None] ** 2 + 2 * (fit_zeta * fit_w)[others, None] * s[None] + (fit_w**2)[others, None]
    return np.vstack([1 / den, s[None] / den, np.ones_like(s)[None], (s**2 / (s**2 + c * s + k))[None]]).T


def _solve(x, spec: Spectra, mode: int, laws):
    """Output coefficients by weighted least squares given the poles and laws ``x``, and the residuals.

    Each record's residual is weighted by its force over its outputs' RMS: the score's error in %."""
    n = (x.size - len(laws)) // 2
    w, zeta, coefs = x[:n], x[n : 2 * n], x[2 * n :]
    s = 2j * np.pi * spec.f
    designs = []
    for force in spec.F:
        k, c = equivalent(w[mode] ** 2, 2 * zeta[mode] * w[mode], laws, coefs, force, s)
        designs.append(_design(w, zeta, mode, k, c, s))
    C, residuals = [], []
    for j in range(spec.H.shape[1]):
        weight = np.abs(spec.F) / spec.rms[:, j, None]
        B = np.vstack([d * wt[:, None] for d, wt in zip(designs, weight)])
        Y = np.concatenate(spec.H[:, j] * weight)
        Br, Yr = np.vstack([B.real, B.imag]), np.concatenate([Y.real, Y.imag])
        coef, *_ = np.linalg.lstsq(Br, Yr, rcond=None)
        C.append(coef)
        residuals.append((Br @ coef - Yr) / _f16.PERIOD)
    return np.array(C), np.concatenate(residuals)


def fit_joint(spec: Spectra, w0, zeta0, mode: int, laws, start: JointFit | None = None) -> JointFit:
    """Fit the poles, the laws' coefficients and the outputs to every record of ``spec`` at once, the
    poles within :data:`POLE_RANGE` of ``w0``, from ``start`` (a fit of the same laws) when given."""
    n = w0.size
    x0 = np.concatenate([w0, zeta0, np.zeros(len(laws))] if start is None else [start.w, start.zeta, start.coefs])
    bound = np.full(len(laws), np.inf)
    lower = np.concatenate([w0 * (1 - POLE_RANGE), np.full(n, 1e-3), -bound])
    upper = np.concatenate([w0 * (1 + POLE_RANGE), np.full(n, 3.0), bound])
    # the laws' natural units: a thousandth of the mode's stiffness, or of its rate w, at the strongest record
    s = 2j * np.pi * spec.f
    strongest = spec.F[np.argmax(np.abs(spec.F).sum(1))]
    sd = dict(zip("qp", motion_sd(w0[mode] ** 2, 2 * zeta0[mode] * w0[mode], strongest, s)))
    natural = {"q": 1e-3 * w0[mode] ** 2, "p": 1e-3 * w0[mode]}
    units = [natural[LAWS[name][0]] / LAWS[name][1](sd[LAWS[name][0]]) for name in laws]
    x_scale = np.concatenate([w0 * 1e-3, np.full(n, 1e-3), units])
    sol = least_squares(lambda x: _solve(x, spec, mode, laws)[1], x0, bounds=(lower, upper), x_scale=x_scale)
    C, _ = _solve(sol.x, spec, mode, laws)
    return JointFit(sol.x[:n], sol.x[n : 2 * n], mode, tuple(laws), sol.x[2 * n :], C)


def polish(fit: JointFit, records: list[_f16.Record], spec: Spectra) -> JointFit:
    """The distorted mode's frequency, damping and laws refined by free-run simulation, the rest held.

    Equivalent linearization is an approximation (a law's distortion falls on the excited lines too):
    the fit is moved to what the time domain says, each record's first two periods simulated from rest
    and its second period's error weighted by its outputs' RMS, as the score weighs it."""
    t, period = fit.mode, _f16.PERIOD
    short = [_f16.Record(r.force[: 2 * period], r.acc[:, : 2 * period], r.fs) for r in records]

    def moved(x):
        w, zeta = fit.w.copy(), fit.zeta.copy()
        w[t], zeta[t] = fit.w[t] * (1 + 1e-3 * x[0]), fit.zeta[t] * (1 + 0.1 * x[1])
        return dataclasses.replace(fit, w=w, zeta=zeta, coefs=fit.coefs * (1 + 0.1 * x[2:]))

    def residuals(x):
        model, out = model_of(moved(x)), []
        for rec, rms in zip(short, spec.rms):
            try:
                error = (_f16.simulate(model, rec) - rec.acc)[:, period:] / rms[:, None]
            except DivergenceError:
                error = np.full((rms.size, period), 10.0)  # a run away: far worse than any fit
            out.append(error.ravel() / np.sqrt(error.size))
        return np.concatenate(out)

    sol = least_squares(residuals, np.zeros(2 + len(fit.laws)), diff_step=1e-2, max_nfev=40)
    return moved(sol.x)


def model_of(fit: JointFit) -> IdentifiedModel:
    """The fit as a model: the distorted mode ``p' = F - k q - c p - sum_l coef_l law_l`` and outputs
    reading it as an accelerometer does, ``phi p'``, beside the other modes' ``c_q q + c_p p`` and ``d F``."""
    n, t = fit.w.size, fit.mode
    others = [i for i in range(n) if i != t]
    k0, c0 = fit.w[t] ** 2, 2 * fit.zeta[t] * fit.w[t]
    phi = fit.C[:, -1]
    C = np.zeros((fit.C.shape[0], 2 * n + 1))
    C[:, others] = fit.C[:, : n - 1]
    C[:, [n + i for i in others]] = fit.C[:, n - 1 : 2 * n - 2]
    C[:, t], C[:, n + t], C[:, -1] = -phi * k0, -phi * c0, fit.C[:, -2] + phi

    def extra(q, p, force):
        variables = {"q": q[t], "p": p[t]}
        laws = [law_expression(name, variables[LAWS[name][0]]) for name in fit.laws]
        terms = {f"p{t + 1}": tuple(zip(laws, -fit.coefs))}
        for j, name in enumerate(_f16.ACCELERATIONS):
            terms[name] = tuple(zip(laws, -phi[j] * fit.coefs))
        return terms

    model = _f16.modal_model(fit.w, fit.zeta, C, extra)
    law = {"mode": t, "laws": list(fit.laws), "coefs": [float(c) for c in fit.coefs]}
    return dataclasses.replace(model, metadata={**model.metadata, "law": law})


def leave_one_level_out(records: list[_f16.Record], spec: Spectra, w0, zeta0, mode: int, structures=STRUCTURES):
    """Per structure, its fit on every record and each record's free-run error (% of each output's RMS,
    rows: records; infinite where the model diverges) when the structure is fitted on the others only,
    started from its fit on every record (so the record left out shaped the start: an optimistic score)."""
    table = {}
    for laws in structures:
        whole = fit_joint(spec, w0, zeta0, mode, laws)
        errors = []
        for k, record in enumerate(records):
            others = spec.subset(i for i in range(len(records)) if i != k)
            model = model_of(fit_joint(others, w0, zeta0, mode, laws, start=whole))
            try:
                errors.append(100 * _f16.score(model, record) / spec.rms[k])
            except DivergenceError:  # a law that runs away at a level it was not fitted to
                errors.append(np.full(spec.rms.shape[1], np.inf))
        table[laws] = (whole, np.array(errors))
    return table


def structure_name(laws) -> str:
    return " + ".join(laws) or "linear"


def mode_terms(model: IdentifiedModel):
    """The distorted mode's stiffness, damping, laws and their coefficients, as ``model`` holds them."""
    law = model.metadata["law"]
    mode = law["mode"] + 1
    terms = {str(t.expr): t.coef for t in model.equation(f"p{mode}").terms}
    return mode, -terms[f"q{mode}"], -terms[f"p{mode}"], law["laws"], np.array(law["coefs"], float)


def equivalent_mode(model: IdentifiedModel, record: _f16.Record, scale: float = 1.0) -> tuple[float, float, float]:
    """The distorted mode's equivalent natural frequency (Hz) and damping ratio under ``record``'s force times
    ``scale``, and the standard deviation of its q there."""
    _, k0, c0, laws, coefs = mode_terms(model)
    s = 2j * np.pi * _f16.line_frequencies(record.fs)
    force = scale * _f16.force_lines(record)
    k, c = equivalent(k0, c0, laws, coefs, force, s)
    return float(np.sqrt(k) / (2 * np.pi)), float(c / (2 * np.sqrt(k))), motion_sd(k, c, force, s)[0]


def describe(model: IdentifiedModel) -> str:
    """The distorted mode's law as the model holds it: frequency, damping and each law's coefficient."""
    mode, k, c, laws, coefs = mode_terms(model)
    head = f"p{mode}' = F - {k:.6g} q - {c:.4g} p"
    terms = "".join(f" {'-' if coef > 0 else '+'} {abs(coef):.4g} {n}" for n, coef in zip(laws, coefs))
    return f"{head}{terms}   (f0 {np.sqrt(k) / (2 * np.pi):.4f} Hz, damping ratio {c / (2 * np.sqrt(k)):.4f})"


def identify_and_save(folder: Path, levels, paths) -> None:
    """Fit the modes to the weakest level, choose the distorted mode's law by leave-one-level-out, fit it
    and the linear model on every level at once, and save both."""
    start = time.process_time()
    records = [_f16.read_record(folder / f"F16Data_FullMSine_Level{n}.mat") for n in levels]
    w, zeta, _ = _f16.fit_modes(*_f16.frf([min(records, key=lambda r: r.force.std())]))
    mode = _f16.distorted_mode(w, records)
    spec = spectra(records)
    print(
        f"modes fitted ({time.process_time() - start:.0f} s of CPU); the distorted mode: "
        f"{w[mode] / (2 * np.pi):.3f} Hz; each structure's free-run error on the level left out (%):"
    )
    table = leave_one_level_out(records, spec, w, zeta, mode)
    for laws, (_, errors) in table.items():
        cells = "  ".join(f"L{n} " + "/".join(f"{e:.1f}" for e in row) for n, row in zip(levels, errors))
        print(f"  {structure_name(laws):12s} mean {errors.mean():6.1f}   {cells}")
    chosen = min(table, key=lambda laws: table[laws][1].mean())
    print(f"chosen: {structure_name(chosen)} ({time.process_time() - start:.0f} s of CPU)")
    choice = {  # a divergent run as null: model files hold finite numbers
        structure_name(laws): [[round(float(e), 2) if np.isfinite(e) else None for e in row] for row in errors]
        for laws, (_, errors) in table.items()
    }
    for kind, laws in (("nonlinear", chosen), ("linear", ())):
        model = model_of(polish(table[laws][0], records, spec))
        law = {**model.metadata["law"], "levels": list(levels), "leave_one_level_out": choice}
        dataclasses.replace(model, metadata={**model.metadata, "law": law}).save(paths[kind])
    print(f"both models: {time.process_time() - start:.0f} s of CPU")
