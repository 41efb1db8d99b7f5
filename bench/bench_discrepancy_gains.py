"""Discrepancy workflow: how the evidence gains are distributed over seeds, next to the threshold.

On the oscillator and records of ``bench_discrepancy.py`` (two records, output-error evidence), each
seed runs the workflow once and keeps the first step's refitted gains. For a hidden effect of
``--size``: the quantiles of the true effect's gain, the share of seeds whose gain clears 4, 5 and
8 nats, and what the step chose. For ``none`` (nothing missing, the linear oscillator): the
quantiles of the best gain of any candidate and of the bootstrap's null gains, the distribution a
false-alarm threshold has to sit above.

Run: ``python bench/bench_discrepancy_gains.py [--effects none,velocity_squared,...] [--size S]
[--noise N] [--seeds N] [--first-seed S]``.
"""

import argparse
import time
from collections import Counter

import _report  # bench/ is on sys.path when run as a script
import numpy as np
from bench_discrepancy import BASE, EFFECTS, FA, V, X, clean_records, oscillator

import symsbl

CUTS = (4.0, 5.0, 8.0)


def step_gains(effect, size, noise, seed):
    """The first step of one seed: ``(gain of effect or None, best gain, best label, null gains, added)``."""
    force = (lambda x, v: 0 * v) if effect == "none" else EFFECTS[effect](size)
    train, held = clean_records(oscillator(force), seed=seed)
    report = symsbl.discrepancy(
        train.with_noise(noise, seed=seed), BASE, heldout=held.with_noise(noise, seed=seed + 500), seed=seed
    )
    step = report.steps[0]
    best = max(step.scores, key=lambda s: s.evidence_gain)
    own = [s.evidence_gain for s in step.scores if s.effect == effect]
    return (
        max(own) if own else None,
        best.evidence_gain,
        best.label,
        list(step.null_gains),
        tuple(a.effect for a in report.added),
    )


def quantiles(values) -> str:
    q = np.percentile(values, [10, 50, 90, 99])
    return (
        f"min {np.min(values):.2f}, q10 {q[0]:.2f}, median {q[1]:.2f}, q90 {q[2]:.2f}, q99 {q[3]:.2f}, "
        f"max {np.max(values):.2f}"
    )


def report(effect, rows):
    own = [r[0] if r[0] is not None else 0.0 for r in rows]
    best = [r[1] for r in rows]
    null = [g for r in rows for g in r[3]]
    print(f"\n{effect}: {len(rows)} seeds")
    if effect == "none":
        print(f"- best gain of any candidate: {quantiles(best)}")
        print(f"- bootstrap null gains: {quantiles(null)}")
    else:
        print(f"- the effect's gain: {quantiles(own)}")
        print("- seeds whose gain clears " + ", ".join(f"{c:g} nats: {np.mean(np.array(own) >= c):.2f}" for c in CUTS))
    chosen = Counter(" + ".join(r[4]) or "nothing" for r in rows)
    print("- added: " + ", ".join(f"{k} {n}" for k, n in chosen.most_common()))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--effects", default="none,velocity_squared,cubic_stiffness")
    p.add_argument("--size", type=float, default=0.005, help="effect size (share of the force)")
    p.add_argument("--noise", type=float, default=0.01)
    p.add_argument("--seeds", type=int, default=30)
    p.add_argument("--first-seed", type=int, default=0)
    args = p.parse_args()
    print(
        f"peak displacement {X:.4g} m, peak velocity {V:.4g} m/s, force amplitude {FA:.4g} N; "
        f"size {100 * args.size:g} % of the force, noise {100 * args.noise:g} %, two records"
    )
    for effect in args.effects.split(","):
        if effect != "none" and effect not in EFFECTS:
            p.error(f"--effects: expected 'none' or one of {', '.join(EFFECTS)}, got {effect!r}")
        t0 = time.perf_counter()
        rows = [
            step_gains(effect, args.size, args.noise, seed)
            for seed in range(args.first_seed, args.first_seed + args.seeds)
        ]
        report(effect, rows)
        print(f"- {time.perf_counter() - t0:.0f} s")
    _report.write_page("discrepancy-gains", __doc__)


if __name__ == "__main__":
    main()
