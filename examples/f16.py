"""The F-16 ground-vibration test: one model of the 2-15 Hz band for every force level, from accelerations.

A full-scale F-16 is shaken under its right wing; three accelerometers record the response (1: at the
shaker, 2: on the wing next to the right payload's mounting interface, 3: on the payload across the
same interface). The interface (a T-shaped element sliding in a rail: clearance and friction) makes the
wing-torsion mode near 7.3 Hz soften and damp more as the force grows (Noel and Schoukens, Workshop on
Nonlinear System Identification Benchmarks, 2017).

The model is modal: each mode of the band is a position-velocity pair driven by the measured force,
``q' = p, p' = F - k q - c p`` (unit participation: the scale of a latent mode is a convention), and
each acceleration is an algebraic output of the modes, ``a = sum_i (c_qi q_i + c_pi p_i) + d F``,
what an accelerometer reads of a linear structure. The mode nearest the line whose response changes
most with the level (the wing torsion) carries a law, ``p' = F - k q - c p - sum_l b_l g_l(q, p)``,
and the accelerations read it as ``phi (F - k q - c p - sum_l b_l g_l)``. Its laws are fitted to the
frequency responses of every level at once by equivalent linearization (under a near-Gaussian motion
of spread sd, ``q|q|`` acts as the stiffness ``2 sqrt(2/pi) sd``): the poles, the laws' coefficients
and the outputs of one model, each level's response that of its equivalent linear model. The law is
chosen among stiffness and damping laws by leave-one-level-out free-run simulation, and the mode's
frequency, damping and laws are then polished by free-run simulation of every level. A linear model
(no law) is fitted the same way for comparison.

Usage::

    python examples/f16.py                      # score the saved models on the estimation levels
    python examples/f16.py --validate FILE.csv  # score the saved model on any benchmark-layout record
    python examples/f16.py --identify           # identify again (about 12 minutes of CPU) and save

Scoring: free-run simulation from the measured force alone, all nine periods, the error RMS over
periods 2-9 per acceleration, in m/s^2 and in % of that acceleration's RMS. Under the scores, the
record's own floors in %: the part that does not repeat from period to period, which no model
predicts, and the content outside the excited band (harmonics of the nonlinearity, drift).

Data: ``shared/data/F16GVT`` next to this repository (the benchmark's .mat files); ``--validate``
reads the benchmark's CSV layout (columns Force, Voltage, Acceleration1, Acceleration2,
Acceleration3, Fs) or its .mat files.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

import symsbl

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _f16  # noqa: E402  (the example's modal model, beside this script)
import _f16_law  # noqa: E402  (its nonlinear mode)

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[1] / "shared" / "data" / "F16GVT"
MODELS = {"nonlinear": HERE / "f16_model.json", "linear": HERE / "f16_linear.json"}
ESTIMATION = [1, 3, 5, 7]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--validate", nargs="+", metavar="FILE", help="score the saved model on these records")
    parser.add_argument("--identify", action="store_true", help="identify the models again and save them")
    args = parser.parse_args(argv)
    if args.identify or not MODELS["nonlinear"].is_file():
        if not _f16.have_data(DATA):
            print(f"skipped: the F-16 benchmark data are not in {DATA}")
            return 77  # reported as skipped by the test that runs the examples
        _f16_law.identify_and_save(DATA, ESTIMATION, MODELS)
    if args.validate:
        return validate(symsbl.IdentifiedModel.load(MODELS["nonlinear"]), args.validate)
    return compare_on_estimation_levels()


def validate(model, names) -> int:
    """Print each record's free-run error per acceleration; one line and exit code 2 for a bad record."""
    for name in names:
        try:
            record = _f16.read_record(Path(name))
        except (OSError, KeyError, ValueError, IndexError) as error:
            print(
                f"f16.py: --validate {name}: expected a benchmark record (.mat, or CSV with columns Force, "
                f"Voltage, Acceleration1-3, Fs), got an error reading it ({error}); check the file",
                file=sys.stderr,
            )
            return 2
        periods = f"{record.force.size / _f16.PERIOD:.3g}"
        print(f"{name}: free-run error after the first of {periods} periods, force {record.force.std():.1f} N RMS")
        print(_f16.score_table(model, record))
        floors = _f16.floor_lines(record)
        if floors:
            print(floors)
    return 0


def compare_on_estimation_levels() -> int:
    """Score both saved models on every level they were fitted to."""
    if not _f16.have_data(DATA):
        print(f"skipped: the F-16 benchmark data are not in {DATA}")
        return 77
    models = {kind: symsbl.IdentifiedModel.load(path) for kind, path in MODELS.items()}
    print("the distorted mode of the nonlinear model: " + _f16_law.describe(models["nonlinear"]))
    errors = {}
    for level in ESTIMATION:
        record = _f16.read_record(DATA / f"F16Data_FullMSine_Level{level}.mat")
        print(f"\nlevel {level} (multisine, {record.force.std():.1f} N RMS), error RMS over periods 2-9:")
        for kind, model in models.items():
            errors[level, kind] = _f16.score(model, record)
            print(f"  {kind:9s} " + _f16.format_scores(errors[level, kind], record))
        print(_f16.floor_lines(record))
    for level in ESTIMATION:  # as measured when the models were saved: the nonlinear one is no worse anywhere
        assert np.all(errors[level, "nonlinear"][1:] <= errors[level, "linear"][1:]), level
    return 0


if __name__ == "__main__":
    sys.exit(main())
