"""EMPS, a real positioning axis: start from mass + viscous friction + offset, let the discrepancy
workflow find what is missing, and compare the final parameters with the published ones.

The inverse model is ``M q'' = tau - Fv q' - Fc sign(q') - OF``; in state form, with the velocity
``v`` from the filtered encoder position, ``v' = tau/M - (Fv/M) v - (Fc/M) sign(v) - OF/M``.
The axis runs in closed loop, so an open-loop simulation drifts: the held-out error here is the
equation (one-step force) error on the second record (the same trajectory with external force
pulses).

Data: ../shared/data/EMPS (see its README). Reference: A. Janot, M. Gautier, M. Brunot, "Data Set
and Reference Models of EMPS", Workshop on Nonlinear System Identification Benchmarks, 2019.
"""

import sys

from _emps import PUBLISHED, available, load

from symsbl import discrepancy


def physical(model):
    c = {t.name: t.coef for t in model.equation("v").terms}
    M = 1.0 / c["tau"]
    return {"M": M, "Fv": -c["v"] * M, "Fc": -c.get("sign(v)", 0.0) * M, "OF": -c["1"] * M}


def main():
    available()  # exits, reported as skipped, when the data are missing
    report = discrepancy(
        load("DATA_EMPS.mat"), "q: v; v: tau, v, 1", heldout=load("DATA_EMPS_PULSES.mat"), error="equation"
    )
    print(report)
    found = physical(report.final)
    print(f"\n{'':4s} {'found':>10s} {'published':>10s} {'difference':>11s}")
    for name, ref in PUBLISHED.items():
        print(f"{name:4s} {found[name]:10.4g} {ref:10.4g} {100 * (found[name] / ref - 1):10.2f} %")
    assert report.added[0].effect == "coulomb_friction"
    for name in ("M", "Fv", "Fc"):
        assert abs(found[name] / PUBLISHED[name] - 1) < 0.05, (name, found[name])
    return 0


if __name__ == "__main__":
    sys.exit(main())
