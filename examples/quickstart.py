"""Identify the Duffing oscillator from noisy data, then re-simulate it on an input it has not seen."""

import symsbl

# Candidate terms are CasADi expressions of named symbols; libraries combine with +.
x1, x2, F = symsbl.symbols("x1 x2 F")
library = symsbl.polynomial([x1, x2], degree=3) + symsbl.elementwise([x1, x2], ["sin", "sign"]) + symsbl.inputs([F])

# Training data: x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F, driven by a 100 N, 10 Hz sine, 0.4 % noise.
duffing = symsbl.systems.duffing()
t = symsbl.time_grid(1.0, 16384)
train = symsbl.simulate(duffing, t, inputs=symsbl.Sine(100.0, 10.0)).with_noise(0.004, seed=0)

model = symsbl.identify(train, library)
print(model)

# Held-out check: a random-phase multisine, simulated from the identified equations.
test = symsbl.simulate(duffing, t, inputs=symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1))
check = symsbl.validate_model(model, test.with_noise(0.004, seed=1))
print(check)

assert model.equation("x1").names == ["x2"]
assert sorted(model.equation("x2").names) == ["F", "x1", "x1**3", "x2"]
assert abs(model.equation("x2").coef("x1**3") / -1e9 - 1) < 0.01
assert max(check.nrmse.values()) < 0.01
