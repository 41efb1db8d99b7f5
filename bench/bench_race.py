"""Accuracy race: symsbl against pysindy in its best configurations, same data, same candidate terms.

Every method sees the same noisy training record and the same candidate library: polynomials of
degree 3 in the states and inputs (with the constant) plus only the non-polynomial terms the true
model needs (``sign(x2)`` for Coulomb friction, ``|x2| x3 |x3|`` for Bouc-Wen). symsbl is also
run with its general Eq. 21 library (degree 3, |x| augmented), which needs no knowledge of the
truth to write.

Methods (settings fixed here before the results were seen, except where noted):

- ``symsbl``: ``identify`` with defaults (weak form on non-overlapping windows, RVM, support
  search; the output-error refinement of newer versions off). Nothing to tune.
- ``pysindy FD / SFD / weak + STLSQ, AICc``: pysindy 2's ``FiniteDifference``,
  ``SmoothedFiniteDifference`` (Savitzky-Golay, polyorder 3, window = symsbl's weak window, the
  bandwidth rule of ``symsbl.WeakForm.resolve``, made odd) or ``WeakPDELibrary`` (K = 1000
  random subdomains, half-width = half symsbl's weak window, p = 4), then
  ``STLSQ(normalize_columns=True)`` over a grid of ridge ``alpha`` in {0.05 (pysindy's
  default), 1e-3, 1e-6} and 30 thresholds (log-spaced from 1e-5 of the smallest to the largest
  target norm). Per equation, the (alpha, threshold) with the smallest AICc,
  ``N log(RSS/N) + 2k + 2k(k+1)/(N-k-1)`` on the regression rows (the rule of Kaptanoglu et
  al. 2023). The alpha grid was added after a first run: at pysindy's default alpha = 0.05 on
  normalised columns no threshold gave the exact support of even the linear system (ridge
  keeps collinear pairs such as x1 and x1^3 and drops F and x2 first). Per-equation choice
  is generous: STLSQ takes one threshold, but its equations are independent.
- ``pysindy weak + ensemble, AICc``: ``EnsembleOptimizer`` (bagging, 20 models, median) around
  STLSQ at the AICc choices of ``weak + STLSQ``.
- ``... oracle``: the (alpha, threshold) chosen per equation *knowing the true model*: the exact
  support if any setting gives it, else all true terms with the fewest spurious ones; then the
  smallest coefficient error; over 60 thresholds x 3 alphas. Not available to a user: it bounds
  what thresholding can do.
- ``pysindy weak + symsbl.RVM``: ``pysindy.WrappedOptimizer(symsbl.RVM(), unbias=False)`` on
  the same weak features: the RVM inside a pysindy pipeline, nothing to tune.

Sweeps run STLSQ on the triangular factor of ``[features | targets]``, which gives the same
coefficients and residuals as all the rows (STLSQ depends on the data only through least
squares, ridge and column norms) in a fraction of the time.

Metrics, per case over the seeds: exact support (every equation has exactly the true terms),
median of the largest relative error over the true coefficients (a missing term counts 100 %),
median held-out NRMSE (%, largest over the states; the identified model re-simulated by symsbl
on a held-out 1 s record driven by a 2-30 Hz random-phase multisine, 60 N rms, against the noisy
record, so the noise level is the floor; ``div`` counts models whose simulation diverged),
median time of one identification (derivatives, library and one fit; for pysindy one STLSQ
fit on all rows at the chosen setting: a sweep costs that many times more, symsbl needs none).

    python bench/bench_race.py            # 3 seeds, every case (about 6 minutes)
    python bench/bench_race.py --quick    # 1 seed, paper cases and two harder ones

BLAS runs on one thread (``_report.one_blas_thread``): pysindy alternates between numpy's and
scipy's OpenBLAS, and with their default threads on this 2-core machine its ensembles ran 50x
slower.
"""

from __future__ import annotations

import argparse
import inspect
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import sympy as sp
from _report import one_blas_thread, table, write_page  # noqa: E402  (bench/ is on sys.path when run as a script)

import symsbl
from symsbl import Multisine, OdeSystem, Sine, Trajectory, simulate, systems, time_grid
from symsbl._validate.truth import _true_terms

THRESHOLDS = 30
ORACLE_THRESHOLDS = 60
ALPHAS = (0.05, 1e-3, 1e-6)  # STLSQ's ridge: pysindy's default, and two that keep collinear terms apart
WEAK_K = 1000
ENSEMBLE_MODELS = 20


def chain2(m1=1.0, m2=1.0, c1=20.0, c2=10.0, k1=1e4, k2=5e3, k3=2e8) -> OdeSystem:
    """Two masses in a chain, force on the first, a cubic spring from the second to ground."""
    q1, v1, q2, v2, F = symsbl.symbols("q1 v1 q2 v2 F")
    p = symsbl.symbols("m1 m2 c1 c2 k1 k2 k3")
    m1_, m2_, c1_, c2_, k1_, k2_, k3_ = p
    rhs = (
        v1,
        (F - c1_ * v1 - k1_ * q1 - k2_ * (q1 - q2) - c2_ * (v1 - v2)) / m1_,
        v2,
        (-k2_ * (q2 - q1) - c2_ * (v2 - v1) - k3_ * q2**3) / m2_,
    )
    return OdeSystem((q1, v1, q2, v2), (F,), rhs, p, (m1, m2, c1, c2, k1, k2, k3), "chain2")


@dataclass(frozen=True)
class Case:
    """One identification problem: a system, how it is measured and driven."""

    name: str
    system: Callable[[], OdeSystem]
    fs: float = 32768.0
    noise: float = 0.004
    duration: float = 2.0
    forcing: Callable[[int], object] = field(default=lambda seed: Sine(100.0, 10.0))
    extras: Callable[[tuple], list] = field(default=lambda states: [])
    sim_fs: float = 32768.0  # simulated at this rate, then decimated to fs


def _velocity_sign(states):
    return [ca.sign(states[1])]


def _hysteresis(states):
    return [ca.fabs(states[1]) * states[2] * ca.fabs(states[2])]


PAPER = [
    Case("linear", systems.linear),
    Case("quadratic damping", systems.quadratic_damping),
    Case("Duffing", systems.duffing),
    Case("Coulomb friction", systems.coulomb, extras=_velocity_sign),
    Case("Bouc-Wen (n = 2)", lambda: systems.bouc_wen(n=2), extras=_hysteresis),
]
HARDER = [
    Case("Duffing, 500 Hz, 1 %", systems.duffing, fs=500.0, noise=0.01),
    Case("Duffing, 32768 Hz, 2 %", systems.duffing, noise=0.02),
    Case("Coulomb, 1000 Hz, 1 %", systems.coulomb, fs=1000.0, noise=0.01, extras=_velocity_sign),
    Case("Bouc-Wen, 1000 Hz, 1 %", lambda: systems.bouc_wen(n=2), fs=1000.0, noise=0.01, extras=_hysteresis),
    Case(
        "2-DOF chain, 1000 Hz, 1 %, multisine",
        chain2,
        fs=1000.0,
        noise=0.01,
        duration=4.0,
        forcing=lambda seed: Multisine(rms=60.0, f_min=2.0, f_max=40.0, seed=100 + seed),
    ),
]


def record(case, system, duration, forcing, seed):
    """Noisy record at ``case.fs``: simulated at ``case.sim_fs``, decimated, noise added."""
    step = round(case.sim_fs / case.fs)
    clean = simulate(system, time_grid(duration, case.sim_fs), inputs=forcing)
    coarse = Trajectory(
        clean.t[::step], clean.states[::step], clean.inputs[::step], clean.state_names, clean.input_names
    )
    return coarse.with_noise(case.noise, seed=seed)


def symsbl_identify(data, library):
    """``symsbl.identify`` by equation error (weak form, RVM, support search): the output-error
    refinement a newer ``identify`` runs by default is switched off, so the race compares the
    sparse regressions."""
    kw = {"refine": False} if "refine" in inspect.signature(symsbl.identify).parameters else {}
    return symsbl.identify(data, library, **kw)


# -- candidate terms, in both packages --------------------------------------------------------


def symsbl_library(system, case, general=False):
    variables = list(system.states) + list(system.inputs)
    if general:
        return symsbl.paper(system.states, system.inputs, degree=3)
    lib = symsbl.polynomial(variables, 3)
    extra = case.extras(system.states)
    return lib + symsbl.custom(extra, variables) if extra else lib


def pysindy_library(system, case):
    """Polynomials of degree 3 plus the needed extras. Each extra is a ``CustomLibrary``
    function of *all* the inputs (so pysindy makes exactly one column of it): pysindy 2.1's
    ``GeneralizedLibrary`` with ``inputs_per_library`` fails inside ``WeakPDELibrary``."""
    import pysindy as ps

    poly = ps.PolynomialLibrary(degree=3)
    if case.extras is _velocity_sign:
        assert len(system.states) + len(system.inputs) == 3  # (x1, x2, F)
        return poly + ps.CustomLibrary([lambda a, b, c: np.sign(b)], [lambda a, b, c: f"sign({b})"], include_bias=False)
    if case.extras is _hysteresis:
        assert len(system.states) + len(system.inputs) == 4  # (x1, x2, x3, F)
        return poly + ps.CustomLibrary(
            [lambda a, b, c, d: np.abs(b) * c * np.abs(c)],
            [lambda a, b, c, d: f"Abs({b})*{c}*Abs({c})"],
            include_bias=False,
        )
    return poly


def term_keys(names, system):
    """pysindy feature names as the canonical sympy strings symsbl and the truth use."""
    local = {s.name(): symsbl.casadi_to_sympy(s) for s in list(system.states) + list(system.inputs)}
    local.update({"Abs": sp.Abs, "sign": sp.sign})
    return [str(sp.sympify(n.replace("^", "**").replace(" ", "*"), locals=local)) for n in names]


# -- pysindy: features once, then the optimisers ------------------------------------------------


class _Capture:
    """A stand-in optimizer that keeps the regression pysindy builds (features, targets)."""

    def fit(self, x, y):
        self.x, self.y = np.asarray(x), np.asarray(y)
        self.coef_ = np.zeros((self.y.shape[1], self.x.shape[1]))
        return self


def pysindy_features(data, system, case, how, window):
    import pysindy as ps

    lib = pysindy_library(system, case)
    diff = None
    if how == "FD":
        diff = ps.FiniteDifference()
    elif how == "SFD":
        w = window + 1 - window % 2
        diff = ps.SmoothedFiniteDifference(smoother_kws={"window_length": max(w, 5), "polyorder": 3})
    else:
        np.random.seed(0)  # pysindy draws the subdomain centres from numpy's global generator
        half = 0.5 * window / case.fs
        lib = ps.WeakPDELibrary(function_library=lib, spatiotemporal_grid=data.t, K=WEAK_K, H_xt=[half], p=4)
    capture = _Capture()
    model = ps.SINDy(optimizer=capture, feature_library=lib, differentiation_method=diff)
    model.fit(data.states, t=data.t, u=data.inputs, feature_names=list(data.state_names + data.input_names))
    names = (
        lib.function_library.get_feature_names(list(data.state_names + data.input_names))
        if how == "weak"
        else model.get_feature_names()
    )
    return capture.x, capture.y, term_keys(names, system)


def threshold_grid(y, n):
    scale = np.linalg.norm(y, axis=0)
    return np.logspace(np.log10(scale.min() * 1e-5), np.log10(scale.max()), n)


def compressed(x, y):
    """Rows ``R`` of ``[x | y] = Q R``. Least squares, ridge and column norms, hence STLSQ's
    coefficients and every residual norm, are the same on them as on all the rows."""
    r = np.linalg.qr(np.column_stack([x, y]), mode="r")
    return r[:, : x.shape[1]], r[:, x.shape[1] :]


def sweep(xc, yc, grid):
    """STLSQ(normalize_columns=True) at every (alpha, threshold); returns the settings and the
    coefficients, shape (n_settings, n_equations, n_terms)."""
    import pysindy as ps

    settings, coefs = [], []
    for alpha in ALPHAS:
        for thr in grid:
            opt = ps.STLSQ(threshold=float(thr), alpha=alpha, normalize_columns=True)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                coefs.append(opt.fit(xc, yc).coef_.copy())
            settings.append((alpha, float(thr)))
    return settings, np.array(coefs)


def aicc_choice(xc, yc, n, coefs):
    """Per equation, the setting with the smallest AICc on the ``n`` regression rows."""
    rss = np.array([np.sum((yc - xc @ c.T) ** 2, axis=0) for c in coefs])  # (n_settings, n_eq)
    k = np.count_nonzero(coefs, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        aicc = n * np.log(rss / n) + 2 * k + 2 * k * (k + 1) / np.maximum(n - k - 1, 1)
    aicc[k == 0] = np.inf
    return np.argmin(aicc, axis=0)


def oracle_choice(coefs, keys, truth):
    """Per equation, the setting a user knowing the truth would pick: the exact support if
    some setting gives it, else every true term with the fewest spurious ones, else the
    fewest missing; then the smallest coefficient error."""

    def badness(c, true):
        found = {keys[j]: c[j] for j in np.flatnonzero(c)}
        return (len(set(true) - set(found)), len(set(found) - set(true)), coef_error(found, true))

    return np.array(
        [
            min(range(len(coefs)), key=lambda i, e=e, true=true: badness(coefs[i, e], true))
            for e, true in enumerate(truth)
        ]
    )


def rows(coefs, picks):
    return np.array([coefs[i, e] for e, i in enumerate(picks)])


def ensemble(x, y, settings, picks):
    import pysindy as ps

    out = np.zeros((y.shape[1], x.shape[1]))
    for i in np.unique(picks):
        np.random.seed(1)
        alpha, thr = settings[i]
        opt = ps.EnsembleOptimizer(
            ps.STLSQ(threshold=thr, alpha=alpha, normalize_columns=True), bagging=True, n_models=ENSEMBLE_MODELS
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            coef = opt.fit(x, y).coef_
        out[picks == i] = coef[picks == i]
    return out


def one_fit_seconds(x, y, setting):
    """Wall time of one pysindy STLSQ fit on all the rows at ``setting = (alpha, threshold)``
    (what each point of a sweep costs a user)."""
    import pysindy as ps

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ps.STLSQ(threshold=setting[1], alpha=setting[0], normalize_columns=True).fit(x, y)
    return time.perf_counter() - t0


def wrapped_rvm(x, y):
    import pysindy as ps

    return ps.WrappedOptimizer(symsbl.RVM(), unbias=False).fit(x, y).coef_


# -- scoring ---------------------------------------------------------------------------------


def coef_error(found, true):
    return max((abs(found[t] - c) / abs(c) if t in found else 1.0) for t, c in true.items())


def as_terms(coef_rows, keys):
    return [{keys[j]: float(c[j]) for j in np.flatnonzero(c)} for c in coef_rows]


def symsbl_terms(model):
    return [{t.name: t.coef for t in eq.terms} for eq in model.equations]


def heldout_error(found, system, heldout):
    """Largest NRMSE (%) over the states of the model re-simulated on the held-out record;
    ``inf`` if it diverges."""
    local = {s.name(): symsbl.casadi_to_sympy(s) for s in list(system.states) + list(system.inputs)}
    local.update({"Abs": sp.Abs, "sign": sp.sign})
    rhs = [sum((c * sp.sympify(t, locals=local) for t, c in eq.items()), sp.Integer(0)) for eq in found]
    model = OdeSystem(system.states, system.inputs, tuple(rhs), name="identified")
    try:
        sim = simulate(model, heldout.t, inputs=heldout.inputs, x0=heldout.states[0], on_divergence="truncate")
    except symsbl.SymsblError:
        return np.inf
    if sim.diverged_at is not None or not np.all(np.isfinite(sim.states)):
        return np.inf
    return 100 * float(np.max(symsbl.nrmse(heldout.states, sim.states)))


@dataclass
class Score:
    exact: list = field(default_factory=list)
    error: list = field(default_factory=list)
    heldout: list = field(default_factory=list)
    seconds: list = field(default_factory=list)

    def add(self, found, truth, system, heldout, seconds):
        self.exact.append(all(set(f) == set(t) for f, t in zip(found, truth, strict=True)))
        self.error.append(max(coef_error(f, t) for f, t in zip(found, truth, strict=True)))
        self.heldout.append(heldout_error(found, system, heldout))
        self.seconds.append(seconds)

    def cells(self):
        ho = np.array(self.heldout)
        div = int(np.sum(~np.isfinite(ho)))
        med = np.median(ho) if div < len(ho) else np.inf
        held = ("diverged" if not np.isfinite(med) else f"{med:.2f}") + (f" ({div} div)" if div else "")
        return [
            f"{sum(self.exact)}/{len(self.exact)}",
            f"{100 * np.median(self.error):.2f}",
            held,
            f"{np.median(self.seconds):.2f}",
        ]


# -- one case ---------------------------------------------------------------------------------


def run_seed(case, seed, scores):
    system = case.system()
    data = record(case, system, case.duration, case.forcing(seed), seed)
    heldout = record(case, system, 1.0, Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=seed + 1), seed + 1000)
    truth = [{k: v for k, (v, _) in eq.items()} for eq in _true_terms(system)]
    window = symsbl.WeakForm().resolve(data.t, data.states).window

    for label, general in (("symsbl", False), ("symsbl, Eq. 21 library", True)):
        lib = symsbl_library(system, case, general)
        symsbl_identify(data.slice(0, len(data.t) // 4), lib)  # compile the dictionary first
        t0 = time.perf_counter()
        model = symsbl_identify(data, lib)
        scores[label].add(symsbl_terms(model), truth, system, heldout, time.perf_counter() - t0)

    for how in ("FD", "SFD", "weak"):
        t0 = time.perf_counter()
        x, y, keys = pysindy_features(data, system, case, how, window)
        t_feat = time.perf_counter() - t0
        xc, yc = compressed(x, y)
        settings, coefs = sweep(xc, yc, threshold_grid(y, THRESHOLDS))
        picks = aicc_choice(xc, yc, len(y), coefs)
        t_one = t_feat + one_fit_seconds(x, y, settings[picks[-1]])
        scores[f"pysindy {how} + STLSQ, AICc"].add(as_terms(rows(coefs, picks), keys), truth, system, heldout, t_one)
        _, fine = sweep(xc, yc, threshold_grid(y, ORACLE_THRESHOLDS))
        best = oracle_choice(fine, keys, truth)
        scores[f"pysindy {how} + STLSQ, oracle"].add(as_terms(rows(fine, best), keys), truth, system, heldout, t_one)
        if how == "weak":
            t1 = time.perf_counter()
            coef = ensemble(x, y, settings, picks)
            scores["pysindy weak + ensemble, AICc"].add(
                as_terms(coef, keys), truth, system, heldout, t_feat + time.perf_counter() - t1
            )
            t1 = time.perf_counter()
            coef = wrapped_rvm(x, y)
            scores["pysindy weak + symsbl.RVM"].add(
                as_terms(coef, keys), truth, system, heldout, t_feat + time.perf_counter() - t1
            )


METHODS = [
    "symsbl",
    "symsbl, Eq. 21 library",
    "pysindy weak + symsbl.RVM",
    "pysindy FD + STLSQ, AICc",
    "pysindy SFD + STLSQ, AICc",
    "pysindy weak + STLSQ, AICc",
    "pysindy weak + ensemble, AICc",
    "pysindy FD + STLSQ, oracle",
    "pysindy SFD + STLSQ, oracle",
    "pysindy weak + STLSQ, oracle",
]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one seed; paper cases and two harder ones")
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()
    seeds = range(1 if args.quick else args.seeds)
    cases = PAPER + (HARDER[:1] + HARDER[-1:] if args.quick else HARDER)
    start = time.perf_counter()
    results = {}
    for case in cases:
        scores = {m: Score() for m in METHODS}
        for seed in seeds:
            run_seed(case, seed, scores)
        results[case.name] = scores
        settings = f"{case.fs:g} Hz, {100 * case.noise:g} % noise, {case.duration:g} s"
        table(
            f"{case.name} ({settings}; {len(seeds)} seed(s))",
            ["method", "exact support", "max coef. error (%)", "held-out NRMSE (%)", "time (s)"],
            [[m] + scores[m].cells() for m in METHODS],
        )
    summary(results, cases)
    print(f"\n(total {time.perf_counter() - start:.0f} s)")


def summary(results, cases):
    rows_ = []
    for m in METHODS:
        row = [m]
        for case in cases:
            s = results[case.name][m]
            row.append(f"{sum(s.exact)}/{len(s.exact)}")
        rows_.append(row)
    table("Exact support, every case", ["method"] + [c.name for c in cases], rows_)


if __name__ == "__main__":
    with one_blas_thread():
        main()
    write_page("race", __doc__)
