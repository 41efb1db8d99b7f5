"""Extending the dictionary with your own CasADi terms.

The true system has a smooth friction law that no built-in family contains::

    x1' = x2
    x2' = F - 20 x2 - 1e4 x1 - 5 tanh(x2 / 0.2)

The friction term is written as a CasADi expression and added to a polynomial library with ``+``,
next to other user terms that the data should reject. The same data are then identified without
it, to show what a missing term costs: the nearest built-in shape (``sign(x2)``) plus a few
polynomial corrections, a lower evidence and a larger held-out error.
"""

import warnings

import casadi as ca

import symsbl

EPS = 0.2  # m/s, velocity scale of the friction law
x1, x2, F = symsbl.symbols("x1 x2 F")
truth = symsbl.OdeSystem(
    states=(x1, x2), inputs=(F,), rhs=(x2, F - 20 * x2 - 1e4 * x1 - 5 * ca.tanh(x2 / EPS)), name="tanh friction"
)

t = symsbl.time_grid(1.5, 16384)
train = symsbl.simulate(truth, t, inputs=symsbl.Sine(100.0, 10.0)).with_noise(0.004, seed=0)
test = symsbl.simulate(truth, t, inputs=symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1))
test = test.with_noise(0.004, seed=1)

builtin = symsbl.polynomial([x1, x2], degree=3) + symsbl.elementwise([x1, x2], ["sign"]) + symsbl.inputs([F])
mine = symsbl.custom(
    [
        ca.tanh(x2 / EPS),  # smooth Coulomb friction
        x2 * ca.exp(-((x2 / EPS) ** 2)),  # Stribeck-like bump (not in the truth)
        ca.atan(x1 / 0.005),  # a saturating spring (not in the truth)
    ],
    [x1, x2],
)
library = builtin + mine
print(f"{len(builtin)} built-in + {len(mine)} user terms: {mine.names}\n")

results = {}
for label, lib in [("with the user terms", library), ("built-in terms only", builtin)]:
    # without the smooth friction, no candidate can follow the record: the residual test says so (a warning)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", symsbl.RefineWarning)
        model = symsbl.identify(train, lib)
    check = symsbl.validate_model(model, test)
    evidence = model.equation("x2").log_evidence
    results[label] = (model, check, evidence, [str(w.message) for w in caught])
    print(f"-- {label} ({len(lib)} candidates): log evidence of x2' = {evidence:.1f}")
    print(model)
    print(check)
    for message in results[label][3]:
        print("warning:", message)
    print()

model, check, evidence, warned = results["with the user terms"]
assert not warned, warned
friction = mine.names[0]
eq = model.equation("x2")
assert sorted(eq.names) == sorted(["F", "x1", "x2", friction]), eq.names
assert abs(eq.coef(friction) / -5.0 - 1) < 0.02, eq.coef(friction)
assert max(check.nrmse.values()) < 0.01

_, check_builtin, evidence_builtin, warned_builtin = results["built-in terms only"]
assert any("not white" in w for w in warned_builtin), warned_builtin
assert evidence > evidence_builtin + 10, (evidence, evidence_builtin)
assert max(check.nrmse.values()) < max(check_builtin.nrmse.values())
print(
    f"the user's {friction} term: coefficient {eq.coef(friction):.3f} (true -5), "
    f"evidence gain {evidence - evidence_builtin:.0f} nats over the built-in library"
)
