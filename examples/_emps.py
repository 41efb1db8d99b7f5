"""The EMPS records (../shared/data/EMPS) as symsbl Trajectories, and the published parameters.

Shared by ``emps_identification.py`` and ``emps_discrepancy.py``; not an example of its own.

The axis force is ``tau = gtau * vir``; the velocity ``v`` comes from the encoder position low-pass
filtered at 100 Hz (:func:`symsbl.position_record`). Reference: A. Janot, M. Gautier,
M. Brunot, "Data Set and Reference Models of EMPS", Workshop on Nonlinear System Identification
Benchmarks, 2019.
"""

from pathlib import Path

from scipy.io import loadmat

from symsbl import position_record

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "EMPS"
#: The published inverse model M q'' = tau - Fv q' - Fc sign(q') - OF.
PUBLISHED = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "OF": -3.1648}


#: Exit code of an example that cannot run here (the data are missing): reported as skipped, not passed.
SKIPPED = 77


def available() -> bool:
    """True when the records are there; otherwise says why and exits with :data:`SKIPPED`."""
    if (DATA / "DATA_EMPS.mat").exists() and (DATA / "DATA_EMPS_PULSES.mat").exists():
        return True
    print(f"skipped: the EMPS data are not at {DATA} (expected ../shared/data/EMPS next to the repository)")
    raise SystemExit(SKIPPED)


def load(name):
    """``DATA_EMPS.mat`` or ``DATA_EMPS_PULSES.mat`` as a Trajectory with states q, v and input tau."""
    m = loadmat(DATA / name)
    tau = float(m["gtau"].ravel()[0]) * m["vir"].ravel()
    return position_record(m["t"].ravel(), m["qm"].ravel(), tau, cutoff=100.0)
