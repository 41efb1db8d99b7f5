"""End to end on the paper's Duffing system at 32768 Hz: symsbl against pysindy, same data, same terms.

Both tools identify x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F from the same noisy record (1 s, 100 N at
10 Hz, 0.4 % noise on the states, simulated once by symsbl; data generation is not timed) with the
same 20 candidate terms (polynomials of degree 3 in x1, x2, F with the constant), then re-simulate
what they found with their own simulator.

- symsbl: ``identify`` (weak form, RVM; nothing to tune; by equation error, the output-error
  refinement of newer versions off), ``simulate(model.to_system())``.
- pysindy: ``SINDy`` with ``FiniteDifference`` and ``STLSQ(normalize_columns=True)``, the
  configuration that finds this model's exact support under a rule stated in advance in
  ``bench_race.py``: per equation, the (alpha, threshold) of smallest AICc over ridge alpha in
  {0.05, 1e-3, 1e-6} and 30 thresholds, each a ``SINDy.fit`` as a user would run it. Timed
  twice: the whole sweep (what choosing costs) and one fit at the chosen setting (what it costs
  once the setting is known). Then pysindy's own ``model.simulate`` (its default LSODA at rtol
  1e-12, stopped after a deadline, and LSODA at rtol 1e-8).

Also measured: re-simulating the identified model against the hand-written CasADi model of the
same equations, and the Monte Carlo predictive band of ``validate_model``.

Run: ``python bench/bench_end_to_end.py`` (about 1-2 minutes; BLAS on one thread, as in
``bench_race.py``).
"""

from __future__ import annotations

import inspect
import time
import warnings

import numpy as np
from _report import one_blas_thread, table, timed, write_page  # noqa: E402  (bench/ is on sys.path when run as a script)
from bench_race import ALPHAS, THRESHOLDS, aicc_choice, compressed, term_keys, threshold_grid

from symsbl import Sine, identify, polynomial, simulate, symbols, systems, time_grid, validate_model

FS = 32768
F0, W = 100.0, 2 * np.pi * 10.0
TRUE = [{"x2"}, {"x1", "x2", "x1**3", "F"}]


def symsbl_identify(data, lib):
    """Identification by equation error, as in ``bench_race.py``."""
    kw = {"refine": False} if "refine" in inspect.signature(identify).parameters else {}
    return identify(data, lib, **kw)


def pysindy_model(setting):
    import pysindy as ps

    alpha, threshold = setting
    return ps.SINDy(
        optimizer=ps.STLSQ(threshold=threshold, alpha=alpha, normalize_columns=True),
        feature_library=ps.PolynomialLibrary(degree=3),
        differentiation_method=ps.FiniteDifference(),
    )


def pysindy_fit(data, setting):
    model = pysindy_model(setting)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(data.states, t=data.t, u=data.inputs, feature_names=["x1", "x2", "F"])
    return model


def pysindy_sweep(data):
    """Every (alpha, threshold) fitted as a user would, then the AICc choice per equation."""
    first = pysindy_fit(data, (ALPHAS[0], 0.0))
    theta = np.asarray(first.optimizer.Theta_)
    x_dot = np.asarray(first.differentiation_method(data.states, t=data.t))
    settings = [(a, float(thr)) for a in ALPHAS for thr in threshold_grid(x_dot, THRESHOLDS)]
    models = [pysindy_fit(data, s) for s in settings]
    coefs = np.array([m.coefficients() for m in models])
    picks = aicc_choice(*compressed(theta, x_dot), len(x_dot), coefs)
    return settings, coefs, picks, models[0].get_feature_names()


def supports(coef_rows, keys):
    return [{keys[j] for j in np.flatnonzero(c)} for c in coef_rows]


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


def resimulation_error(states, reference):
    return float(np.max(np.abs(states[:, 0] - reference[:, 0])) / np.max(np.abs(reference[:, 0])))


def pysindy_resimulation(model, data, deadline):
    runs = {}
    for label, kw in (
        ("pysindy default (LSODA, rtol 1e-12)", {}),
        ("LSODA, rtol 1e-8", {"integrator_kws": {"method": "LSODA", "rtol": 1e-8, "atol": 1e-10}}),
    ):
        sim, seconds, reached = pysindy_simulate(model, data.states[0], data.t, deadline, **kw)
        err = resimulation_error(sim, data.states) if sim is not None else np.nan
        runs[label] = (seconds, reached, err)
    return runs


def main():
    t = time_grid(1.0, FS)
    x1, x2, F = symbols("x1 x2 F")
    lib = polynomial([x1, x2, F], 3)
    data = simulate(systems.duffing(), t, inputs=Sine(F0, 10.0)).with_noise(0.004, seed=0)

    symsbl_identify(data, lib)  # warm-up: compile the dictionary
    model, t_sym = timed(lambda: symsbl_identify(data, lib), repeats=3)
    sim, t_sym_sim = timed(lambda: simulate(model.to_system(), t, inputs=Sine(F0, 10.0), x0=data.states[0]), repeats=3)
    sym_support = [{term.name for term in eq.terms} for eq in model.equations]

    (settings, coefs, picks, names), t_sweep = timed(lambda: pysindy_sweep(data), repeats=1)
    keys = term_keys(names, systems.duffing())
    chosen = np.array([coefs[i, e] for e, i in enumerate(picks)])
    py_support = supports(chosen, keys)
    # One fit at the chosen setting (the x2' equation's; x1''s rows come from its own setting).
    fitted, t_one = timed(lambda: pysindy_fit(data, settings[picks[1]]), repeats=3)
    fitted.optimizer.coef_ = chosen  # the per-equation choice, for pysindy's own simulate
    runs = pysindy_resimulation(fitted, data, deadline=120.0)
    done = [v for v in runs.values() if v[1] >= t[-1]]
    t_py_sim = min((v[0] for v in done), default=np.inf)

    table(
        "Identification, Duffing, 1 s at 32768 Hz, same data and 20 candidate terms (best of 3)",
        ["", "symsbl (s)", "pysindy (s)", "pysindy / symsbl"],
        [
            ["one fit (pysindy: at the chosen setting)", f"{t_sym:.3f}", f"{t_one:.3f}", f"{t_one / t_sym:.1f}"],
            [
                f"choosing the setting (pysindy: {len(settings)} fits + AICc)",
                "none needed",
                f"{t_sweep:.2f}",
                f"{(t_sweep + t_one) / t_sym:.0f} (sweep and fit)",
            ],
            [
                "re-simulate 1 s with its own simulator",
                f"{t_sym_sim:.3f}",
                f"{t_py_sim:.2f}",
                f"{t_py_sim / t_sym_sim:.0f}",
            ],
        ],
    )
    table(
        "pysindy re-simulation of its model, deadline 120 s",
        ["integrator", "time (s)", "reached t (s)", "max |x1 error| / max |x1|"],
        [
            [k, f"{v[0]:.2f}" + (" (stopped)" if v[1] < t[-1] else ""), f"{v[1]:.4f}", f"{v[2]:.1e}"]
            for k, v in runs.items()
        ],
    )
    table(
        "Supports found (both should be exact) and re-simulation error",
        ["", "x1' support", "x2' support", "exact", "max |x1 error| / max |x1|"],
        [
            [
                "symsbl",
                ", ".join(sorted(sym_support[0])),
                ", ".join(sorted(sym_support[1])),
                sym_support == TRUE,
                f"{resimulation_error(sim.states, data.states):.1e}",
            ],
            [
                "pysindy (AICc)",
                ", ".join(sorted(py_support[0])),
                ", ".join(sorted(py_support[1])),
                py_support == TRUE,
                f"{min((v[2] for v in done), default=np.nan):.1e}",
            ],
        ],
    )
    print(f"pysindy settings chosen by AICc (alpha, threshold) per equation: {[settings[i] for i in picks]}")

    resimulation_tables(model, data, t)


def resimulation_tables(model, data, t):
    """symsbl's re-simulation against the hand-written model, and the Monte Carlo band."""
    force = Sine(F0, 10.0)
    rows = []
    for method in ("cvodes", "rk4"):
        kw = dict(inputs=force, method=method, jit=True) if method == "rk4" else dict(inputs=force, method=method)
        _, t_true = timed(lambda kw=kw: simulate(systems.duffing(), t, **kw), repeats=5, warmup=True)
        _, t_model = timed(lambda kw=kw: simulate(model.to_system(), t, **kw), repeats=5, warmup=True)
        rows.append([method, f"{1e3 * t_true:.1f}", f"{1e3 * t_model:.1f}", f"{t_model / t_true:.2f}"])
    table(
        "Re-simulating 1 s: identified model against the hand-written model",
        ["method", "hand-written (ms)", "identified (ms)", "identified / hand-written"],
        rows,
    )

    _, t0 = timed(lambda: validate_model(model, data), repeats=3)
    _, cold = timed(lambda: validate_model(model, data, n_band=50), repeats=1)  # compiles the batched RK4
    _, t50 = timed(lambda: validate_model(model, data, n_band=50), repeats=3)
    _, t10 = timed(lambda: validate_model(model, data, n_band=10), repeats=3)
    table(
        "Monte Carlo predictive band (validate_model on 1 s; all draws in one batched RK4 simulation)",
        [
            "n_band=0 (s)",
            "n_band=50, first call (s)",
            "n_band=10 (s)",
            "n_band=50 (s)",
            "per draw, 10 -> 50 draws (ms)",
            "one re-simulation (ms)",
        ],
        [[f"{t0:.3f}", f"{cold:.2f}", f"{t10:.2f}", f"{t50:.2f}", f"{1e3 * (t50 - t10) / 40:.1f}", rows[0][2]]],
    )


if __name__ == "__main__":
    with one_blas_thread():
        main()
    write_page("end-to-end", __doc__)
