"""Doubts: how often each is raised where it is false and where it is true.

False alarms, on open-loop records whose law the library lacks (model error, the case that once read as
feedback and as input noise): the electronic-Duffing stand-in of ``tests/electronic_duffing.py`` (a saturating
hardening, 610 Hz) under a periodic multisine to 0.35 fs (3 periods of 2048 samples, the first dropped; 0.5 %
noise on x and v, 0.05 % on F) and under a band-limited random force to 0.3 fs (8192 samples, not periodic;
0.5 % on x and v, none on F), identified with a cubic polynomial library in x and v plus F (it holds neither the
saturation nor x|x|). Power, on records where the doubt is true (``tests/reference_oscillator.py``, a hardening
oscillator at 1 kHz, 4 s, a 2-30 Hz multisine, the 22-term library of the real-records benchmark): a digital PD
loop on the previous sample's measurements with a hidden disturbance of 5 % (closed loop; also with the position
alone recorded, the velocity estimated from it), a random force of 2 % of
the input's rms that the record does not hold (process noise: the whiteness doubt), and 2 % white noise on the
measured force (a noisy input). Per case over the seeds: how often ``identify`` (its defaults) raised each
doubt (``metadata["refine"]``: ``closed_loop``, ``input_noise``, and a whiteness doubt among ``doubts``), and
which estimate it reported.

Run: ``python bench/bench_doubts.py [--seeds N]`` (default 10).
"""

import sys
import time
import warnings
from pathlib import Path

import _report  # bench/ is on sys.path when run as a script

import symsbl

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from electronic_duffing import Oscillator, extrapolating, saturating, training  # noqa: E402
from reference_oscillator import HARDENING, closed_loop, library, record  # noqa: E402

x, v, F = symsbl.symbols("x v F")
CUBIC = symsbl.polynomial([x, v], 3) + symsbl.inputs([F])
STAND_IN = Oscillator(saturating)

#: case -> (what is true, a record of a seed, the library, the refinement's options[, identify's keywords])
CASES = {
    "open loop, law outside the library, periodic multisine": (
        "nothing",
        lambda seed: training(STAND_IN, seed, length=2048, periods=3, band=0.35, input_noise=0.0005),
        CUBIC,
        None,
    ),
    "open loop, law outside the library, random force": (
        "nothing",
        lambda seed: extrapolating(STAND_IN, seed, n=8192, growth=(1.0, 1.0)),
        CUBIC,
        None,
    ),
    "digital PD loop, 5 % hidden disturbance": (
        "closed loop",
        lambda seed: closed_loop(HARDENING, 1000 + seed),
        library(),
        symsbl.RefineOptions(interpolation="hold"),
    ),
    "digital PD loop, position only": (
        "closed loop",
        lambda seed: position_only(closed_loop(HARDENING, 1000 + seed)),
        library(),
        symsbl.RefineOptions(interpolation="hold"),
        {"states": ["x", "v"], "kinematics": {"x": "v"}},
    ),
    "random force of 2 % hidden (process noise)": (
        "disturbance",
        lambda seed: record(HARDENING, 1000 + seed, process=0.02),
        library(),
        None,
    ),
    "2 % noise on the measured force": (
        "noisy input",
        lambda seed: record(HARDENING, 1000 + seed, force_noise=0.02),
        library(),
        None,
    ),
}


def position_only(record: symsbl.Trajectory) -> symsbl.Trajectory:
    """``record`` without its velocity column (the velocity is then estimated from the position)."""
    return symsbl.Trajectory(record.t, record.states[:, :1], record.inputs, ("x",), record.input_names)


def main() -> None:
    seeds = int(sys.argv[sys.argv.index("--seeds") + 1]) if "--seeds" in sys.argv else 10
    rows = []
    for name, (truth, make, terms, options, *keywords) in CASES.items():
        loop = noisy = white = 0
        used: dict = {}
        seconds = []
        for seed in range(seeds):
            data = make(seed)
            start = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", symsbl.RefineWarning)
                model = symsbl.identify(data, terms, refine_options=options, **(keywords[0] if keywords else {}))
            seconds.append(time.perf_counter() - start)
            info = model.metadata.get("refine", {})
            loop += bool(info.get("closed_loop"))
            noisy += bool(info.get("input_noise"))
            white += any("white" in d for d in info.get("doubts", []))
            estimate = model.metadata.get("estimator", {}).get("used", model.fit.value)
            used[estimate] = used.get(estimate, 0) + 1
        reported = ", ".join(f"{k} {n}" for k, n in sorted(used.items()))
        mean = sum(seconds) / len(seconds)
        rows.append([name, truth, f"{loop}/{seeds}", f"{noisy}/{seeds}", f"{white}/{seeds}", reported, f"{mean:.1f}"])
        print(f"{name}: done", flush=True)
    header = ["record", "true", "closed loop", "noisy input", "not white", "reported", "s per fit"]
    _report.table("Doubts raised", header, rows)
    _report.write_page("doubts", __doc__)


if __name__ == "__main__":
    main()
