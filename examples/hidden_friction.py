"""A linear model misses a small Coulomb friction; the discrepancy workflow finds, names and adds it.

The paper's oscillator (m = 1, c = 20, k = 1e4) with a friction force of 1 N (``kc``) is driven by
the 100 N, 10 Hz sine for 3 s (training) and by a 10 N, 10 Hz sine for 1.5 s (held out), sampled at
4096 Hz with 0.4 % noise on the states. At 100 N the friction is 1 % of the forcing, so the
refitted linear model re-simulates the training record within the noise; at 10 N it is 10 %.
Starting from ``x1: x2; x2: F, x1, x2``, the workflow fits the model by output error on both
records, scores every effect of the catalogue (and library terms beyond it) by its log-evidence
gain, and adds the winner only if it clears the calibrated threshold and predicts the halves of
the records it was not fitted on better (cross-validation).
"""

import symsbl
from symsbl import discrepancy

FS = 4096.0
KC = 1.0
NOISE = 0.004


def records():
    """The training record (100 N) and the held-out one (10 N), with 0.4 % noise."""
    system = symsbl.systems.coulomb(kc=KC)
    train = symsbl.simulate(system, symsbl.time_grid(3.0, FS), inputs=symsbl.Sine(100.0, 10.0), method="rk4")
    held = symsbl.simulate(system, symsbl.time_grid(1.5, FS), inputs=symsbl.Sine(10.0, 10.0), method="rk4")
    return train.with_noise(NOISE, seed=0), held.with_noise(NOISE, seed=1000)


def main(search_library=True):
    """The study: prints the report, checks it, and returns it (the documentation's gallery draws it).
    ``search_library=False`` scores the catalogue's named effects only, which is quicker."""
    train, held = records()
    report = discrepancy(train, "x1: x2; x2: F, x1, x2", heldout=held, seed=0, search_library=search_library)
    print(report)

    (added,) = report.added
    first = report.steps[0]
    print(
        f"\nadded {added.effect}: coefficient of {added.terms[0]} = {added.coef:.4g} (true {-KC:g}); "
        f"held-out error {100 * first.error_heldout:.3g} % -> {100 * first.error_after:.3g} % "
        f"({first.error_heldout / first.error_after:.1f}x lower; the noise is {100 * NOISE:g} %)"
    )

    assert added.effect == "coulomb_friction", report.verdict
    assert abs(added.coef - (-KC)) < 0.10 * KC, added.coef
    # the noise is NOISE x each state's std, so a model at the noise floor has a held-out NRMSE of NOISE
    assert first.error_after < 1.1 * NOISE < 1.5 * NOISE < first.error_heldout
    assert first.bayes_factor > 20 and first.confirmation > 0
    return report


if __name__ == "__main__":
    main()
