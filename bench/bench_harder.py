"""Equation error against output error on cases harder than the paper's: what refinement buys.

Each case trains on one noisy record and re-simulates a held-out record at a different multisine
realisation (half the training length), both with white noise of the stated share of each state's
standard deviation. Equation error (EE) is ``identify(train, library, refine=False)``; output error
(OE) is the default ``identify(train, library)`` (refinement with term selection on the output-error
evidence). Columns: support against the truth, largest relative coefficient error over all true
terms, held-out NRMSE (worst state, against the noisy record, so the noise share is the floor) and
wall time of the call.

Cases (none is the paper's setting):

- hardening Duffing: m = 2, k = 5e3, 5 % damping, cubic force 3x the linear one at the peaks,
  16384 Hz, 2 s, 1-40 Hz multisine, 1 % noise, Eq. 21 dictionary of degree 3;
- Duffing at 400 Hz: m = 0.5, c = 3, k = 2e3, k3 = 2e7, 10 s, multisine to 30 Hz, 1 % noise;
- 2-DOF chain with a cubic spring between the masses, 2048 Hz, 4 s, 1 % noise, polynomial library;
- displacement only: Duffing with only x1 recorded and x1' = x2 declared (``kinematics``), 4096 Hz,
  3 s, 1 % noise;
- displacement only with light damping: m = 3, c = 0.8 (1.5 % of critical), k = 250, quadratic
  drag 5 v|v|, 500 Hz, 20 s, 0.2-5 Hz multisine, 1 % noise (the small viscous term is lost in the
  differentiated velocity; the output-error screen finds it);
- 2-DOF chain recorded by displacement only: m = 1.5 and 0.8, k = 4e3 and 2.5e3, c = 3 and 1.5 (the
  coupling), a cubic coupling spring 1e7, 500 Hz, 12 s, 1 % noise, Eq. 21 dictionary (146 terms);
- Bouc-Wen n = 3 with z measured (the paper's Eq. 20 exponent), 4096 Hz, 3 s, 0.5 % noise, degree 4.

Run: ``PYTHONPATH=. python bench/bench_harder.py``.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
from _report import one_blas_thread, table, timed, write_page  # noqa: E402  (bench/ is on sys.path when run as a script)

from symsbl import (
    Multisine,
    OdeSystem,
    Trajectory,
    compare_to_truth,
    identify,
    inputs,
    paper,
    polynomial,
    simulate,
    symbols,
    systems,
    time_grid,
    validate_model,
)


def _oscillator(m, c, k, k3):
    x1, x2, F = symbols("x1 x2 F")
    return OdeSystem((x1, x2), (F,), (x2, (F - c * x2 - k * x1 - k3 * x1**3) / m), name="duffing")


def _chain():
    y1, v1, y2, v2, F = symbols("y1 v1 y2 v2 F")
    m1, m2, k1, k2, c1, c2, kc = 1.5, 0.8, 4e3, 2.5e3, 4.0, 3.0, 5e7
    rhs = (
        v1,
        (F - k1 * y1 - c1 * v1 - k2 * (y1 - y2) - c2 * (v1 - v2) - kc * (y1 - y2) ** 3) / m1,
        v2,
        (-k2 * (y2 - y1) - c2 * (v2 - v1) - kc * (y2 - y1) ** 3) / m2,
    )
    library = polynomial([y1, y2], 3) + polynomial([v1, v2], 1, include_bias=False) + inputs([F])
    return OdeSystem((y1, v1, y2, v2), (F,), rhs, name="chain"), library


def _light_chain():
    """The chain with a lighter coupling (damping 1.5, cubic 1e7), recorded by displacement only."""
    x1, x2, v1, v2, F = symbols("x1 x2 v1 v2 F")
    m1, m2, k1, k2, c1, c2, kc = 1.5, 0.8, 4e3, 2.5e3, 3.0, 1.5, 1e7
    coupling = k2 * (x2 - x1) + c2 * (v2 - v1) + kc * (x2 - x1) ** 3
    return OdeSystem(
        (x1, x2, v1, v2), (F,), (v1, v2, (F - k1 * x1 - c1 * v1 + coupling) / m1, -coupling / m2), name="light chain"
    )


def cases():
    x1, x2, F = symbols("x1 x2 F")
    duffing_lib = paper([x1, x2], [F], degree=3)
    k = 5e3
    hard = _oscillator(2.0, 2 * 0.05 * np.sqrt(k * 2.0), k, 3 * k / 0.02**2)
    chain, chain_lib = _chain()
    light = _light_chain()
    bw = systems.bouc_wen(A=5000.0, n=3, a=2.0, b=-1.0, m=1.5, c=15.0, k=8e3)
    ms = dict(f_min=1.0)
    drag = OdeSystem((x1, x2), (F,), (x2, (F - 0.8 * x2 - 250 * x1 - 5 * x2 * ca.fabs(x2)) / 3.0), name="drag")
    return [
        ("hardening Duffing, 16 kHz", hard, 16384, 2.0, dict(rms=40.0, f_max=40.0, **ms), 0.01, duffing_lib, {}),
        (
            "Duffing at 400 Hz",
            _oscillator(0.5, 3.0, 2e3, 2e7),
            400,
            10.0,
            dict(rms=10.0, f_max=30.0, **ms),
            0.01,
            duffing_lib,
            {},
        ),
        ("2-DOF chain, cubic spring", chain, 2048, 4.0, dict(rms=30.0, f_max=40.0, **ms), 0.01, chain_lib, {}),
        (
            "displacement only (x1)",
            _oscillator(1.2, 20.0, 6e3, 4e8),
            4096,
            3.0,
            dict(rms=30.0, f_max=40.0, **ms),
            0.01,
            duffing_lib,
            dict(keep=[0], states=["x1", "x2"], kinematics={"x1": "x2"}),
        ),
        (
            "displacement only, light damping + drag",
            drag,
            500,
            20.0,
            dict(rms=5.0, f_min=0.2, f_max=5.0),
            0.01,
            duffing_lib,
            dict(keep=[0], states=["x1", "x2"], kinematics={"x1": "x2"}),
        ),
        (
            "2-DOF chain, displacement only (x1, x2)",
            light,
            500,
            12.0,
            dict(rms=20.0, f_max=40.0, **ms),
            0.01,
            paper(light.states, light.inputs, degree=3),
            dict(keep=[0, 1], states=["x1", "x2", "v1", "v2"], kinematics={"x1": "v1", "x2": "v2"}),
        ),
        (
            "Bouc-Wen n = 3, z measured",
            bw,
            4096,
            3.0,
            dict(rms=40.0, f_max=30.0, **ms),
            0.005,
            paper(bw.states, bw.inputs, degree=4),
            {},
        ),
    ]


def _keep(record, keep):
    if not keep:
        return record
    return Trajectory(
        record.t, record.states[:, keep], record.inputs, tuple(record.state_names[i] for i in keep), record.input_names
    )


def run_case(name, system, fs, seconds, force, noise, library, options):
    options = dict(options)
    keep = options.pop("keep", None)
    train = _keep(
        simulate(system, time_grid(seconds, fs), inputs=Multisine(**force, seed=3, period=seconds)).with_noise(
            noise, seed=0
        ),
        keep,
    )
    held = _keep(
        simulate(system, time_grid(seconds / 2, fs), inputs=Multisine(**force, seed=4, period=seconds / 2)).with_noise(
            noise, seed=1
        ),
        keep,
    )
    rows = []
    for label, refine in (("EE", False), ("OE", True)):
        model, seconds_taken = timed(
            lambda refine=refine: identify(train, library, refine=refine, **options), repeats=1
        )
        truth = compare_to_truth(model, system)
        check = validate_model(model, held)
        held_err = max(check.nrmse.values()) if check.status == "ok" else float("nan")
        missing = [t for terms in truth.missing.values() for t in terms]
        spurious = [t for terms in truth.spurious.values() for t in terms]
        support = (
            "exact"
            if truth.exact_support
            else "; ".join(
                [f"missing {', '.join(missing)}"] * bool(missing) + [f"spurious {', '.join(spurious)}"] * bool(spurious)
            )
        )
        error = f"{100 * truth.max_error():.3g} %" if np.isfinite(truth.max_error()) else "-"
        rows.append(
            [
                name if label == "EE" else "",
                label,
                support,
                error,
                f"{100 * held_err:.3g} %" if np.isfinite(held_err) else check.status,
                f"{seconds_taken:.1f} s",
            ]
        )
    return rows


def main():
    with one_blas_thread():
        rows = [row for case in cases() for row in run_case(*case)]
    table(
        "Equation error (EE) against output error (OE)",
        ["case", "fit", "support", "max coef. error", "held-out NRMSE", "time"],
        rows,
    )
    write_page("harder", __doc__)


if __name__ == "__main__":
    main()
