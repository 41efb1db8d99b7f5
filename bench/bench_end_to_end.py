"""End to end on the paper's Duffing system at 32768 Hz: symsbl against pysindy.

Both pipelines do the same five things on 1 s of data (m=1, c=20, k=1e4, k3=1e9, 100 N at 10 Hz,
0.4 % noise on the states): simulate the data, differentiate, build the dictionary, fit, and
re-simulate the identified model on the record's input.

- symsbl: ``simulate`` (CVODES), ``identify`` (weak form, Eq. 21 dictionary at degree 3: 34
  terms, RVM; nothing to tune), ``simulate(model.to_system())``.
- pysindy: ``scipy.integrate.solve_ivp`` (DOP853, rtol 1e-8) for the data, ``SINDy`` with
  ``FiniteDifference``, a polynomial library of degree 3 in (x1, x2, F) plus abs/sin/cos/tan/sign
  of each (35 terms) and ``STLSQ(normalize_columns=True)`` at the threshold picked from a sweep
  (picked with knowledge of the true support: the most favourable choice a user could make),
  then pysindy's own ``model.simulate`` (its default LSODA at rtol 1e-12, stopped after a
  deadline, and LSODA at rtol 1e-8; the faster completed run enters the ratio).

Also measured: re-simulating the identified model against the hand-written CasADi model of the
same equations, and the Monte Carlo predictive band of ``validate_model``.

Run: ``PYTHONPATH=. python bench/bench_end_to_end.py``
"""

from __future__ import annotations

import time
import warnings

import numpy as np
from scipy.integrate import solve_ivp

from _report import table, timed  # noqa: E402  (bench/ is on sys.path when run as a script)
from symsbl import identify, paper, symbols, systems, validate_model
from symsbl import Sine
from symsbl import simulate, time_grid

FS = 32768
M, C, K, K3, F0, W = 1.0, 20.0, 1e4, 1e9, 100.0, 2 * np.pi * 10.0
TRUE_X2 = {"x1", "x2", "x1**3", "F"}




def noisy(states, seed=0):
    rng = np.random.default_rng(seed)
    return states + 0.004 * states.std(axis=0) * rng.standard_normal(states.shape)


def symsbl_pipeline(t, lib):
    stages = {}
    t0 = time.perf_counter()
    data = simulate(systems.duffing(), t, inputs=Sine(F0, 10.0)).with_noise(0.004, seed=0)
    stages["simulate"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    model = identify(data, lib)
    stages["differentiate + dictionary + fit"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    sim = simulate(model.to_system(), t, inputs=Sine(F0, 10.0), x0=data.states[0])
    stages["re-simulate"] = time.perf_counter() - t2
    stages["total"] = time.perf_counter() - t0
    err = np.max(np.abs(sim.states[:, 0] - data.states[:, 0])) / np.max(np.abs(data.states[:, 0]))
    return model, data, stages, err


def pysindy_library():
    import pysindy as ps

    funcs = [lambda x: np.abs(x), lambda x: np.sin(x), lambda x: np.cos(x), lambda x: np.tan(x), lambda x: np.sign(x)]
    names = [lambda x: f"|{x}|", lambda x: f"sin({x})", lambda x: f"cos({x})", lambda x: f"tan({x})", lambda x: f"sign({x})"]
    return ps.PolynomialLibrary(degree=3) + ps.CustomLibrary(library_functions=funcs, function_names=names)


def scipy_data(t):
    sol = solve_ivp(lambda s, x: [x[1], (F0 * np.sin(W * s) - C * x[1] - K * x[0] - K3 * x[0] ** 3) / M],
                    (t[0], t[-1]), [0.0, 0.0], method="DOP853", t_eval=t, rtol=1e-8, atol=1e-10)
    return noisy(sol.y.T), F0 * np.sin(W * t)


def pysindy_fit(X, u, t, threshold):
    import pysindy as ps

    model = ps.SINDy(optimizer=ps.STLSQ(threshold=threshold, normalize_columns=True),
                     feature_library=pysindy_library(), differentiation_method=ps.FiniteDifference())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(X, t=t, u=u, feature_names=["x1", "x2", "F"])
    return model


def x2_terms(model):
    names = model.get_feature_names()
    coefs = model.coefficients()[1]
    return {n.replace(" ", "*").replace("^3", "**3") for n, c in zip(names, coefs) if c != 0}


class DeadlineExceeded(Exception):
    pass


def pysindy_simulate(model, x0, t, deadline, **kw):
    """pysindy's simulate with the analytic input as a function of time; stops after ``deadline`` s."""
    stop, reached = time.perf_counter() + deadline, [t[0]]

    def u(s):
        if time.perf_counter() > stop:
            raise DeadlineExceeded
        reached[0] = max(reached[0], float(np.max(s)))
        return F0 * np.sin(W * s)

    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sim = model.simulate(x0, t, u=u, **kw)
    except DeadlineExceeded:
        return None, time.perf_counter() - t0, reached[0]
    return sim, time.perf_counter() - t0, t[-1]


def pysindy_pipeline(t, thresholds, deadline):
    sweep = []
    (X, u), t_data = timed(lambda: scipy_data(t), repeats=1)
    for thr in thresholds:
        model, t_fit = timed(lambda: pysindy_fit(X, u, t, thr), repeats=1)
        sweep.append((thr, t_fit, x2_terms(model), model))
    table("pysindy STLSQ threshold sweep (normalize_columns=True), x2' equation",
          ["threshold", "fit (s)", "terms", "x2' support"],
          [[f"{s[0]:g}", f"{s[1]:.2f}", len(s[2]), ", ".join(sorted(s[2]))] for s in sweep])
    exact = [s for s in sweep if s[2] == TRUE_X2]
    thr, t_fit, terms, model = exact[0] if exact else min(sweep, key=lambda s: len(s[2] ^ TRUE_X2))
    runs = {}
    for label, kw in (("pysindy default (LSODA, rtol 1e-12)", {}),
                      ("LSODA, rtol 1e-8", {"integrator_kws": {"method": "LSODA", "rtol": 1e-8, "atol": 1e-10}})):
        sim, t_sim, reached = pysindy_simulate(model, X[0], t, deadline, **kw)
        err = (np.max(np.abs(sim[:, 0] - X[:, 0])) / np.max(np.abs(X[:, 0]))) if sim is not None else np.nan
        runs[label] = (t_sim, reached, err)
    table(f"pysindy re-simulation of its model (threshold {thr:g}) on 1 s, deadline {deadline:.0f} s",
          ["integrator", "time (s)", "reached t (s)", "max |x1 error| / max |x1|"],
          [[k, f"{v[0]:.2f}" + (" (stopped)" if v[1] < t[-1] else ""), f"{v[1]:.4f}", f"{v[2]:.1e}"] for k, v in runs.items()])
    t_sim = min(v[0] for v in runs.values() if v[1] >= t[-1]) if any(v[1] >= t[-1] for v in runs.values()) else deadline
    err = min((v[2] for v in runs.values() if v[1] >= t[-1]), default=np.nan)
    stages = {"simulate": t_data, "differentiate + dictionary + fit": t_fit, "re-simulate": t_sim,
              "total": t_data + t_fit + t_sim}
    return thr, terms, stages, err


def main():
    t = time_grid(1.0, FS)
    lib = paper(symbols("x1 x2"), symbols("F"), degree=3)
    symsbl_pipeline(t, lib)  # warm-up: compile the dictionary
    runs = [symsbl_pipeline(t, lib) for _ in range(3)]
    model, data, stages, err = min(runs, key=lambda r: r[2]["total"])
    thresholds = [float(v) for v in np.logspace(-1, 5, 13)]
    thr, terms, py_stages, py_err = pysindy_pipeline(t, thresholds, deadline=120.0)
    rows = [[k, f"{stages[k]:.3f}", f"{py_stages[k]:.3f}", f"{py_stages[k] / stages[k]:.1f}"] for k in stages]
    table(f"End to end, Duffing, 1 s at {FS} Hz (symsbl best of 3; pysindy at threshold {thr:g})",
          ["stage", "symsbl (s)", "pysindy (s)", "pysindy / symsbl"], rows)
    sym_support = ", ".join(t.name for t in model.equation("x2").terms)
    table("Supports and re-simulation error", ["", "x1' support", "x2' support", "max |x1 error| / max |x1|"],
          [["symsbl", ", ".join(t.name for t in model.equation("x1").terms), sym_support, f"{err:.1e}"],
           ["pysindy", "", ", ".join(sorted(terms)), f"{py_err:.1e}"]])

    # Re-simulation: identified model against the hand-written CasADi model of the same equations.
    force = Sine(F0, 10.0)
    rows = []
    for method in ("cvodes", "rk4"):
        kw = dict(inputs=force, method=method, jit=True) if method == "rk4" else dict(inputs=force, method=method)
        simulate(systems.duffing(), t, **kw), simulate(model.to_system(), t, **kw)
        _, t_true = timed(lambda: simulate(systems.duffing(), t, **kw), repeats=5)
        _, t_model = timed(lambda: simulate(model.to_system(), t, **kw), repeats=5)
        rows.append([method, f"{1e3 * t_true:.1f}", f"{1e3 * t_model:.1f}", f"{t_model / t_true:.2f}"])
    table("Re-simulating 1 s: identified model against the hand-written model",
          ["method", "hand-written (ms)", "identified (ms)", "identified / hand-written"], rows)

    _, t0 = timed(lambda: validate_model(model, data), repeats=3)
    _, t50 = timed(lambda: validate_model(model, data, n_band=50), repeats=1)
    table("Monte Carlo predictive band (validate_model on 1 s)",
          ["n_band=0 (s)", "n_band=50 (s)", "per draw (ms)", "one re-simulation (ms)"],
          [[f"{t0:.3f}", f"{t50:.2f}", f"{1e3 * (t50 - t0) / 50:.1f}", rows[0][2]]])


if __name__ == "__main__":
    main()
