"""Real records: the noise model, the residual tests and the validated model choice, against known truths and
the real data sets' published models.

Part 1, simulated references with known truth (``tests/reference_oscillator.py``: scipy DOP853 on an analytic
input, independent of symsbl's simulator): a hardening oscillator ``m x'' + c x' + k x + k3 x^3 = F`` (m 0.7, c 1.1,
k 3e3, k3 4e7; 1 kHz, 4 s, a 2-30 Hz multisine of 4 N rms; x and v measured with 1 % noise) under white
measurement noise, AR(2) measurement noise of 20 dB spectral range, a band-limited random force of 0.5 % of the
input's rms that the record does not hold (process noise, 0.5 % and 2 %), and 1 % and 3 % white noise on the
measured force; and a cubic oscillator with Coulomb friction (m 1, c 0.8, k 400, k3 2e5, Fc 0.6; 1200 Hz, 12 s,
a 1-15 Hz multisine of 20 N rms) with 0.7 % noise on x and v and 1 % on the force;
``symsbl.identify`` with its defaults and a 22-term library (polynomials of degree 3 in x, v with absolute values,
sin and sign of each, F). Per case over the seeds: exact support, the spread (standard deviation) of the true
terms' z-scores ``(estimate - truth) / posterior std`` (calibrated: about 1; over the seeds whose support holds
each term), the largest |z|, how often the residual tests doubted the output error's likelihood, which estimate
was reported, and the mean time.

Part 2, EMPS (``../shared/data/EMPS``, real, closed loop): ``identify`` from the position with a friction library
``{1, v, sign(v), v|v|, v^3, tau}``, and ``discrepancy`` from mass + viscous + offset with its defaults, against
the published inverse model (Janot, Gautier, Brunot 2019), and the inverse model's relative force residual on the
test record (DATA_EMPS_PULSES; the published model's is 5.6 %, per the data README).

Run: ``python bench/bench_real.py [--seeds N]`` (default 20).
"""

import sys
import time
import warnings
from pathlib import Path

import _report  # bench/ is on sys.path when run as a script
import numpy as np

import symsbl

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from reference_oscillator import COULOMB, HARDENING, library, record  # noqa: E402

EMPS_DIR = ROOT.parent / "shared" / "data" / "EMPS"
PUBLISHED = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "OF": -3.1648}

#: case -> the plant and the keyword arguments of :func:`reference_oscillator.record`
CASES = {
    "white": (HARDENING, {}),
    "AR(2) measurement noise, 20 dB": (HARDENING, {"coloured": True}),
    "process noise 0.5 %": (HARDENING, {"process": 0.005}),
    "process noise 2 %": (HARDENING, {"process": 0.02}),
    "1 % noise on F": (HARDENING, {"force_noise": 0.01}),
    "3 % noise on F": (HARDENING, {"force_noise": 0.03}),
    "Coulomb 3 %, 0.7 % on x, v, 1 % on F, 12 s": (
        COULOMB,
        {"seconds": 12.0, "fs": 1200.0, "rms": 20.0, "band": (1.0, 15.0), "noise": 0.007, "force_noise": 0.01},
    ),
}


def simulated(seeds: int) -> None:
    rows = []
    for name, (plant, kwargs) in CASES.items():
        truth = plant.truth()
        exact, zs, doubted, seconds, used = 0, [], 0, [], {}
        for seed in range(seeds):
            train = record(plant, 1000 + seed, **kwargs)
            start = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", symsbl.RefineWarning)
                model = symsbl.identify(train, library())
            seconds.append(time.perf_counter() - start)
            eq = model.equation("v")
            exact += sorted(eq.names) == sorted(truth)
            zs += [(eq.coef(n) - c) / eq.stds[eq.names.index(n)] for n, c in truth.items() if n in eq.names]
            doubted += bool(model.metadata.get("refine", {}).get("doubts"))
            estimate = model.metadata.get("estimator", {}).get("used", model.fit.value)
            used[estimate] = used.get(estimate, 0) + 1
        z = np.asarray(zs)
        rows.append(
            [
                name,
                f"{exact}/{seeds}",
                f"{np.std(z):.2f}",
                f"{np.max(np.abs(z)):.1f}",
                f"{doubted}/{seeds}",
                ", ".join(f"{k} {n}" for k, n in sorted(used.items())),
                f"{np.mean(seconds):.1f}",
            ]
        )
        print(f"  {name}: exact {exact}/{seeds}, z spread {np.std(z):.2f}", flush=True)
    _report.table(
        "Simulated references (hardening oscillator, known truth)",
        ["case", "exact support", "z spread", "max |z|", "doubted", "estimate reported", "s per fit"],
        rows,
    )


def _emps(name):
    from scipy.io import loadmat

    m = loadmat(EMPS_DIR / name)
    tau = float(m["gtau"].ravel()[0]) * m["vir"].ravel()
    return symsbl.position_record(m["t"].ravel(), m["qm"].ravel(), tau, cutoff=100.0)


def _parameters(model) -> dict:
    c = {t.name: t.coef for t in model.equation("v").terms}
    M = 1.0 / c["tau"]
    return {
        "M": M,
        "Fv": -c.get("v", 0.0) * M,
        "Fc": -c.get("sign(v)", 0.0) * M,
        "OF": -c.get("1", 0.0) * M,
        "terms": len(c),
    }


def _force_residual(p: dict, test) -> float:
    """The inverse model's relative force residual on ``test`` (tau against M a + Fv v + Fc sign(v) + OF)."""
    v = test.column("v")
    a = np.gradient(v, test.t)
    tau = test.column("tau")
    pred = p["M"] * a + p["Fv"] * v + p["Fc"] * np.sign(v) + p["OF"]
    keep = slice(50, -50)
    return float(np.linalg.norm((tau - pred)[keep]) / np.linalg.norm(tau[keep]))


def emps() -> None:
    import casadi as ca

    if not (EMPS_DIR / "DATA_EMPS.mat").exists():
        print(f"EMPS: not run, the data are not at {EMPS_DIR}")
        return
    train, test = _emps("DATA_EMPS.mat"), _emps("DATA_EMPS_PULSES.mat")
    q, v, tau = symsbl.symbols("q v tau")
    friction = symsbl.custom([ca.SX(1), v, ca.sign(v), v * ca.fabs(v), v**3, tau], [q, v, tau])
    rows = [
        ["published (IDIM-LS)"]
        + [f"{PUBLISHED[k]:.4g}" for k in PUBLISHED]
        + ["4", "", f"{100 * _force_residual(dict(PUBLISHED), test):.2f}", ""]
    ]
    runs = {
        "identify, friction library": lambda: symsbl.identify(train, friction, kinematics={"q": "v"}),
        "discrepancy from M, Fv, OF": lambda: symsbl.discrepancy(train, "q: v; v: tau, v, 1", heldout=test).final,
    }
    for name, run in runs.items():
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", symsbl.RefineWarning)
            model = run()
        seconds = time.perf_counter() - start
        p = _parameters(model)
        worst = max(abs(p[k] / PUBLISHED[k] - 1) for k in ("M", "Fv", "Fc"))
        rows.append(
            [name]
            + [f"{p[k]:.4g}" for k in PUBLISHED]
            + [str(p["terms"]), f"{100 * worst:.2f}", f"{100 * _force_residual(p, test):.2f}", f"{seconds:.0f}"]
        )
    _report.table(
        "EMPS (real, closed loop): the inverse model against the published one",
        ["model", "M", "Fv", "Fc", "OF", "terms", "worst of M, Fv, Fc off (%)", "test force residual (%)", "s"],
        rows,
    )


if __name__ == "__main__":
    seeds = int(sys.argv[sys.argv.index("--seeds") + 1]) if "--seeds" in sys.argv else 20
    with _report.one_blas_thread():
        simulated(seeds)
        emps()
    _report.write_page("real", __doc__)
