"""Discrepancy workflow: detection limits of hidden effects and false alarms on nothing-missing records.

The system is a lightly damped oscillator unlike the paper's (m = 2, c = 6, k = 3e4, zeta = 0.012)
forced by a 2-60 Hz multisine of 20 N RMS for 4 s at 2 kHz; the second record is another multisine
at a quarter of the force, 2 s (both simulated by RK4 with 16 steps per sample). The base model is
``x: v; v: F, x, v``. Each effect's size is its force at the measured peak displacement (or
velocity) as a share of the excitation amplitude (20 sqrt(2) N): Coulomb ``s F`` sign(v), drag
``v|v|``, the paper's ``v^2``, cubic damping ``v^3``, a cubic spring, a quadratic spring ``x|x|``
and a clearance of gap 0.5 x_max.

**Detection.** For each effect, noise level, one or two records (one: the workflow splits it 70/30)
and evidence (``equation-error``, the workflow before output error, and ``output-error``), the sizes
are tried from the smallest up; a size counts when the effect is named alone in every seed. The
first such size is the detection limit (">" the largest tried when none is).

**Cases.** Each effect at one size (``--size``, 1 % by default), and two pairs together (Coulomb
friction with a cubic spring, drag with a quadratic spring): the verdict, the coefficient errors
(also in posterior standard deviations), the gap error of a clearance and the final model's
held-out NRMSE against the noise-free record.

**Beyond.** The 2-DOF chain with a cubic spring on either mass (every mass searched), and a quadratic spring x^2
and an x^2 v damping on the oscillator (terms outside the catalogue), at ``--size``: verdict, coefficient error and the
final model's held-out NRMSE against the noise-free record.

**False alarms.** Nothing-missing records, counted over seeds: the linear oscillator with white
noise, a Duffing oscillator whose base already holds its cubic term, band-limited (coloured)
measurement noise (white noise through a 4th-order Butterworth low-pass at 100 Hz, scaled to the
level), and a record at 400 Hz (20 samples per period of the resonance).

**Information.** What the records can tell at all: for each effect and size, every rival (linear, or linear plus
another catalogue effect, a clearance with its gap free) fitted by Gauss-Newton to the noise-free records (RK4, two
substeps per sample, the input linear between samples); delta^2 / 2 = min sum((y_true - y_rival)^2 / sigma^2) / 2 is
the mean log Bayes factor of the truth over the rival, so Phi((delta^2/2 - 3) / delta) bounds the chance that one
seed names the effect with a 3-nat margin.

Run: ``python bench/bench_discrepancy.py [--part detection|cases|beyond|false-alarms|information] [--size S] [--seeds N]
[--noise 0.01,...] [--records 1,2] [--evidence output-error,equation-error] [--effects coulomb,...] [--null-seeds N]
[--first-seed S] [--null-cases coloured,...] [--sizes 0.005,...]``.
"""

import argparse
import time

import _report  # bench/ is on sys.path when run as a script
import casadi as ca
import numpy as np
from scipy.signal import butter, sosfiltfilt

import symsbl

M, C, K, FRMS, FS = 2.0, 6.0, 3e4, 20.0, 2000.0
FA = FRMS * np.sqrt(2)
BASE = "x: v; v: F, x, v"
SIZES = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.05)


def oscillator(force, k3=0.0):
    x, v, F = ca.SX.sym("x"), ca.SX.sym("v"), ca.SX.sym("F")
    return symsbl.OdeSystem((x, v), (F,), (v, (F - C * v - K * x - k3 * x**3 - force(x, v)) / M), (), (), "light")


#: the records' integrator: RK4 with 16 steps per sample, because a friction force's jump costs RK4 its order (one
#: step per sample left 0.1 % of the response's std as error at 5 % of the force, about 60 nats of spurious
#: evidence against 1 % noise on these records; 16 steps leave 3e-5; CVODES stalls in the stick phases)
TRUTH = {"method": "rk4", "substeps": 16}


def clean_records(system, fs=FS, seed=0):
    grid = symsbl.time_grid(4.0, fs), symsbl.time_grid(2.0, fs)
    train = symsbl.simulate(
        system, grid[0], inputs=symsbl.Multisine(rms=FRMS, f_min=2.0, f_max=60.0, seed=1 + seed), **TRUTH
    )
    held = symsbl.simulate(
        system, grid[1], inputs=symsbl.Multisine(rms=FRMS / 4, f_min=2.0, f_max=60.0, seed=100 + seed), **TRUTH
    )
    return train, held


_peaks = clean_records(oscillator(lambda x, v: 0 * v))[0]
X, V = float(np.max(np.abs(_peaks.column("x")))), float(np.max(np.abs(_peaks.column("v"))))

#: effect -> the coefficient a of its catalogue term phi(x, v) for a share s of the excitation amplitude
SCALE = {
    "coulomb_friction": lambda s: s * FA,
    "quadratic_damping": lambda s: s * FA / V**2,
    "velocity_squared": lambda s: s * FA / V**2,
    "cubic_damping": lambda s: s * FA / V**3,
    "cubic_stiffness": lambda s: s * FA / X**3,
    "quadratic_stiffness": lambda s: s * FA / X**2,
    "clearance": lambda s: s * FA / (0.5 * X),
}
#: effect -> force(x, v) of share s of the excitation amplitude
EFFECTS = {
    "coulomb_friction": lambda s: lambda x, v: s * FA * ca.sign(v),
    "quadratic_damping": lambda s: lambda x, v: s * FA / V**2 * v * ca.fabs(v),
    "velocity_squared": lambda s: lambda x, v: s * FA / V**2 * v**2,
    "cubic_damping": lambda s: lambda x, v: s * FA / V**3 * v**3,
    "cubic_stiffness": lambda s: lambda x, v: s * FA / X**3 * x**3,
    "quadratic_stiffness": lambda s: lambda x, v: s * FA / X**2 * x * ca.fabs(x),
    "clearance": lambda s: lambda x, v: s * FA / (0.5 * X) * ca.fmax(ca.fabs(x) - 0.5 * X, 0) * ca.sign(x),
}


def run(train, held, n_records, evidence, seed):
    kwargs = dict(heldout=held) if n_records == 2 else {}
    return symsbl.discrepancy(train, BASE, evidence=evidence, seed=seed, **kwargs)


def named(effect, size, noise, n_records, evidence, seed, misses) -> bool:
    train, held = clean_records(oscillator(EFFECTS[effect](size)), seed=seed)
    report = run(train.with_noise(noise, seed=seed), held.with_noise(noise, seed=seed + 500), n_records, evidence, seed)
    ok = [a.effect for a in report.added] == [effect]
    if not ok:
        misses.append(
            f"{effect} {100 * size:g} %, noise {100 * noise:g} %, {n_records} record(s), {evidence}, "
            f"seed {seed}: {report.verdict}"
        )
    return ok


def detection(args):
    misses = []
    print("| effect | noise | records | " + " | ".join(args.evidence) + " |")
    print("|---|---|---|" + "---|" * len(args.evidence))
    for effect in args.effects:
        for noise in args.noise:
            for n_records in args.records:
                cells = []
                for evidence in args.evidence:
                    t0, limit = time.perf_counter(), None
                    for size in SIZES:
                        if all(
                            named(effect, size, noise, n_records, evidence, seed, misses) for seed in range(args.seeds)
                        ):
                            limit = size
                            break
                    found = f"{100 * limit:g} %" if limit else f"> {100 * SIZES[-1]:g} %"
                    cells.append(f"{found} ({time.perf_counter() - t0:.0f} s)")
                print(f"| {effect} | {100 * noise:g} % | {n_records} | " + " | ".join(cells) + " |", flush=True)
    print("\nThe first miss at each size below the limit:")
    for m in misses:
        print(f"- {m}")


def cases(args):
    """Each effect (and two pairs together: Coulomb + cubic, drag + x|x|) at ``--size``: the coefficients found
    and the final model's held-out NRMSE against the noise-free truth, with one and two records."""
    combos = [[e] for e in args.effects] + [
        ["coulomb_friction", "cubic_stiffness"],
        ["quadratic_damping", "quadratic_stiffness"],
    ]
    print(f"size {100 * args.size:g} % of the force, noise {', '.join(f'{100 * n:g} %' for n in args.noise)}")
    print("| hidden | noise | records | verdict | coefficient error | gap error | held-out NRMSE vs truth | time |")
    print("|---|---|---|---|---|---|---|---|")
    for combo in combos:
        forces = [EFFECTS[e](args.size) for e in combo]
        system = oscillator(lambda x, v, forces=forces: sum(f(x, v) for f in forces))
        for noise in args.noise:
            for n_records in args.records:
                for seed in range(args.seeds):
                    train, held = clean_records(system, seed=seed)
                    t0 = time.perf_counter()
                    report = run(
                        train.with_noise(noise, seed=seed),
                        held.with_noise(noise, seed=seed + 500),
                        n_records,
                        "output-error",
                        seed,
                    )
                    dt = time.perf_counter() - t0
                    errs, gap = [], "-"
                    for a in report.added:
                        if a.effect in SCALE:
                            true = -SCALE[a.effect](args.size) / M
                            errs.append(
                                f"{a.effect} {100 * (a.coef / true - 1):+.2f} % "
                                f"({(a.coef - true) / a.std * np.sign(true):+.1f} std)"
                            )
                        if a.effect == "clearance":
                            gap = f"{100 * (a.shape / (0.5 * X) - 1):+.2f} %"
                    truth = symsbl.validate_model(report.final, held, method="rk4")
                    print(
                        f"| {' + '.join(combo)} | {100 * noise:g} % | {n_records} | {report.verdict} | "
                        f"{'; '.join(errs) or '-'} | {gap} | {100 * max(truth.nrmse.values()):.3f} % | {dt:.0f} s |",
                        flush=True,
                    )


def coloured(traj, noise, seed):
    """``traj`` with band-limited noise of ``noise`` x each state's std."""
    rng = np.random.default_rng(seed)
    sos = butter(4, 100.0, fs=1.0 / float(traj.t[1] - traj.t[0]), output="sos")
    cols = []
    for j in range(traj.states.shape[1]):
        e = sosfiltfilt(sos, rng.standard_normal(traj.n_samples))
        cols.append(traj.states[:, j] + noise * traj.states[:, j].std() * e / e.std())
    return symsbl.Trajectory(traj.t, np.column_stack(cols), traj.inputs, traj.state_names, traj.input_names)


NULL = {
    "linear, white noise": (lambda: clean_records(oscillator(lambda x, v: 0 * v)), BASE, "white"),
    "Duffing with its cubic term": (
        lambda: clean_records(oscillator(lambda x, v: 0 * v, k3=0.3 * FA / X**3)),
        BASE + ", x**3",
        "white",
    ),
    "coloured noise (100 Hz band)": (lambda: clean_records(oscillator(lambda x, v: 0 * v)), BASE, "coloured"),
    "400 Hz sampling": (lambda: clean_records(oscillator(lambda x, v: 0 * v), fs=400.0), BASE, "white"),
}


def false_alarms(args):
    print(f"seeds {args.first_seed}-{args.first_seed + args.null_seeds - 1}")
    print("| nothing-missing case | noise | false alarms | time per run |")
    print("|---|---|---|---|")
    for case, (make, base, kind) in NULL.items():
        if args.null_cases and not any(word in case for word in args.null_cases):
            continue
        train0, held0 = make()
        for noise in args.noise:
            alarms, t0 = [], time.perf_counter()
            for seed in range(args.first_seed, args.first_seed + args.null_seeds):
                if kind == "white":
                    train, held = train0.with_noise(noise, seed=seed), held0.with_noise(noise, seed=seed + 500)
                else:
                    train, held = coloured(train0, noise, seed), coloured(held0, noise, seed + 500)
                report = symsbl.discrepancy(train, base, heldout=held, seed=seed)
                if report.added or report.steps[0].decision != "nothing missing":
                    alarms.append(f"seed {seed}: {report.verdict}")
            per = (time.perf_counter() - t0) / args.null_seeds
            print(f"| {case} | {100 * noise:g} % | {len(alarms)}/{args.null_seeds} | {per:.1f} s |", flush=True)
            for a in alarms:
                print(f"  - {a}", flush=True)


def chain(extra_on, share):
    """Two masses, the force on the first; a cubic spring to ground on mass ``extra_on`` (1 or 2) whose force at that
    mass's peak displacement (of the linear chain) is ``share`` of the force amplitude. Returns the system, the true
    coefficient in that mass's velocity equation and the spring's k3."""
    x1, v1, x2, v2, F = (ca.SX.sym(n) for n in ("x1", "v1", "x2", "v2", "F"))
    m1, m2 = 1.5, 0.8

    def system(k3):
        f1 = k3 * x1**3 if extra_on == 1 else 0
        f2 = k3 * x2**3 if extra_on == 2 else 0
        rhs = (
            v1,
            (F - 3 * v1 - 2e4 * x1 - 2 * (v1 - v2) - 1.2e4 * (x1 - x2) - f1) / m1,
            v2,
            (-2 * (v2 - v1) - 1.2e4 * (x2 - x1) - f2) / m2,
        )
        return symsbl.OdeSystem((x1, v1, x2, v2), (F,), rhs, (), (), "chain")

    peak = float(np.max(np.abs(clean_records(system(0.0))[0].column(f"x{extra_on}"))))
    k3 = share * FA / peak**3
    return system(k3), -k3 / (m1 if extra_on == 1 else m2), k3


CHAIN_BASE = "x1: v1; v1: F, x1, v1, x2, v2; x2: v2; v2: x1, v1, x2, v2"


def beyond(args):
    """The 2-DOF chain with a cubic spring on either mass (searched on every mass, ``kinematics`` declared), and two
    terms outside the catalogue on the light oscillator: a quadratic spring x^2 and an amplitude-dependent damping
    x^2 v. Two records, effect at ``--size`` of the force."""
    print(f"size {100 * args.size:g} % of the force")
    print("| case | noise | seed | verdict | coefficient error | held-out NRMSE vs truth | time |")
    print("|---|---|---|---|---|---|---|")
    cases_ = {}
    for mass in (1, 2):
        system, true, _ = chain(mass, args.size)
        cases_[f"chain, cubic spring on mass {mass}"] = (
            system,
            CHAIN_BASE,
            {"kinematics": {"x1": "v1", "x2": "v2"}},
            "cubic_stiffness",
            f"x{mass}, v{mass}",
            true,
        )
    kq, kv = args.size * FA / X**2, args.size * FA / (X**2 * V)
    cases_["quadratic spring x^2"] = (oscillator(lambda x, v: kq * x**2), BASE, {}, "x**2", None, -kq / M)
    cases_["x^2 v damping"] = (oscillator(lambda x, v: kv * x**2 * v), BASE, {}, "v*x**2", None, -kv / M)
    for case, (system, base, kwargs, want, where, true) in cases_.items():
        for noise in args.noise:
            for seed in range(args.seeds):
                train, held = clean_records(system, seed=seed)
                t0 = time.perf_counter()
                report = symsbl.discrepancy(
                    train.with_noise(noise, seed=seed),
                    base,
                    heldout=held.with_noise(noise, seed=seed + 500),
                    seed=seed,
                    **kwargs,
                )
                dt = time.perf_counter() - t0
                err = "-"
                hit = [a for a in report.added if want in (a.effect, *a.terms) and (where is None or a.where == where)]
                if len(report.added) == 1 and hit:
                    a = hit[0]
                    err = f"{100 * (a.coef / true - 1):+.2f} % ({(a.coef - true) / a.std * np.sign(true):+.1f} std)"
                truth = symsbl.validate_model(report.final, held, method="rk4")
                print(
                    f"| {case} | {100 * noise:g} % | {seed} | {report.verdict} | {err} | "
                    f"{100 * max(truth.nrmse.values()):.3f} % | {dt:.0f} s |",
                    flush=True,
                )


#: effect -> its basis phi(x, v, gap) in the information bound (sign smoothed as tanh(v / (1e-4 V)))
BASIS = {
    "none": lambda x, v, g: 0 * x,
    "coulomb_friction": lambda x, v, g: ca.tanh(v / (1e-4 * V)),
    "quadratic_damping": lambda x, v, g: v * ca.fabs(v),
    "velocity_squared": lambda x, v, g: v**2,
    "cubic_damping": lambda x, v, g: v**3,
    "cubic_stiffness": lambda x, v, g: x**3,
    "quadratic_stiffness": lambda x, v, g: x * ca.fabs(x),
    "clearance": lambda x, v, g: ca.fmax(ca.fabs(x) - g, 0) * ca.tanh(x / (1e-4 * X)),
}


def _simulator(basis, records):
    """Under the inputs of ``records``, both records' noise-free (x, v) from x(0) = v(0) = 0 under
    x'' = p0 F + p1 x + p2 v + p3 phi(x, v, p4), by RK4 with two substeps per sample and the input linear between
    samples; with its Jacobian in p."""
    x, p, u0, u1 = ca.SX.sym("x", 2), ca.SX.sym("p", 5), ca.SX.sym("u0"), ca.SX.sym("u1")
    h = 1.0 / FS / 2

    def f(z, u):
        return ca.vertcat(z[1], p[0] * u + p[1] * z[0] + p[2] * z[1] + p[3] * basis(z[0], z[1], p[4]))

    z = x
    for k in range(2):
        ua, um, ub = (u0 + (u1 - u0) * (k + c) / 2 for c in (0.0, 0.5, 1.0))
        k1 = f(z, ua)
        k2 = f(z + h / 2 * k1, um)
        k3 = f(z + h / 2 * k2, um)
        k4 = f(z + h * k3, ub)
        z = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    step = ca.Function("step", [x, p, u0, u1], [z])
    P = ca.MX.sym("P", 5)
    outs = []
    for r in records:
        u = r.inputs[:, 0]
        traj = step.mapaccum(len(u) - 1)(ca.DM.zeros(2), ca.repmat(P, 1, len(u) - 1), u[None, :-1], u[None, 1:])
        outs.append(ca.horzcat(ca.DM.zeros(2), traj))
    Y = ca.vec(ca.vertcat(*[o.T for o in outs]))  # columns: x of every record, then v of every record
    return ca.Function("sim", [P], [Y, ca.jacobian(Y, P)])


def _fit(sim, p0, free, weights):
    """Gauss-Newton with Levenberg damping on the coefficients ``free``: (best p, weighted squared residual)."""
    target = weights["y"]
    p, lam = np.array(p0, dtype=float), 1e-3
    y, J = (np.asarray(a) for a in sim(p))
    r = (y[:, 0] - target) * weights["w"]
    cost = r @ r
    for _ in range(60):
        A = J[:, free] * weights["w"][:, None]
        H, g = A.T @ A, A.T @ r
        D = np.diag(np.diag(H) + 1e-9 * np.trace(H) / len(free))  # a gap whose force is still zero has no curvature
        step = np.linalg.solve(H + lam * D, g)
        trial = p.copy()
        trial[free] -= step
        y2, J2 = (np.asarray(a) for a in sim(trial))
        r2 = (y2[:, 0] - target) * weights["w"]
        c2 = r2 @ r2
        if np.isfinite(c2) and c2 < cost:
            done = cost - c2 < 1e-10 * max(cost, 1e-300) + 1e-12
            p, r, J, cost, lam = trial, r2, J2, c2, max(lam / 10, 1e-12)
            if done:
                break
        else:
            lam *= 10
            if lam > 1e10:
                break
    return p, cost


def information(args):
    """How far each hidden effect is, in noise units, from the best model with another effect (or none).

    Under the truth, the log Bayes factor of the true model over a rival has mean about delta^2 / 2 and standard
    deviation delta, where delta^2 = min over the rival's coefficients of sum((y_true - y_rival)^2 / sigma^2) on the
    noise-free records (its own Occam factor aside): an upper bound on what any evidence-based test can tell from
    these records. ``P(> m nats)`` is the chance that one seed clears a margin of m nats, Phi((delta^2/2 - m)/delta).
    """
    from scipy.stats import norm

    rivals = ["none", *EFFECTS]
    # the inputs are the same multisines whatever the system: one compiled simulator per model serves every case
    base = clean_records(oscillator(lambda x, v: 0 * v))
    sims = {r: _simulator(BASIS[r], base) for r in rivals}
    lengths = [r.n_samples for r in base] * 2  # y: x of every record, then v of every record
    print(
        "delta^2 / 2 (nats) of each rival against the truth, two records (4 s + 2 s at a quarter of the force); "
        "P(> 3 nats) for the closest effect"
    )
    print("| hidden | size | noise | " + " | ".join(rivals) + " | closest effect | P(> 3 nats) |")
    print("|---|---|---|" + "---|" * len(rivals) + "---|---|")
    for effect in args.effects:
        for size in args.sizes:
            truth = np.array([1 / M, -K / M, -C / M, -SCALE[effect](size) / M, 0.5 * X])
            y = np.asarray(sims[effect](truth)[0])[:, 0]
            # at unit relative noise (sigma = each channel's std); delta^2 scales as 1 / noise^2
            parts = np.split(y, np.cumsum(lengths)[:-1])
            sig = np.concatenate([np.full(n, np.std(part)) for n, part in zip(lengths, parts)])
            weights, unit = {"y": y, "w": 1.0 / sig}, {}
            for rival in rivals:
                if rival == effect:
                    continue
                sim = sims[rival]
                start, _ = _fit(sim, np.where(np.arange(5) == 3, 0.0, truth), [0, 1, 2], weights)  # linear first
                free = [0, 1, 2] if rival == "none" else [0, 1, 2, 3] + ([4] if rival == "clearance" else [])
                unit[rival] = 0.5 * _fit(sim, start, free, weights)[1]
            closest = min((r for r in unit if r != "none"), key=unit.get)
            for noise in args.noise:
                half = {r: v / noise**2 for r, v in unit.items()}
                d2 = 2 * half[closest]
                p3 = float(norm.cdf((d2 / 2 - 3) / np.sqrt(max(d2, 1e-300))))
                cells = " | ".join("-" if r == effect else f"{half[r]:.3g}" for r in rivals)
                print(
                    f"| {effect} | {100 * size:g} % | {100 * noise:g} % | {cells} | {closest} | {p3:.2f} |", flush=True
                )


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--part", choices=["detection", "cases", "beyond", "false-alarms", "information", "all"], default="all"
    )
    p.add_argument("--size", type=float, default=0.01, help="effect size of --part cases (share of the force)")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--null-seeds", type=int, default=200)
    p.add_argument("--first-seed", type=int, default=0, help="first seed of --part false-alarms (to extend a run)")
    p.add_argument("--null-cases", default="", help="comma-separated words: only the false-alarm cases naming one")
    p.add_argument("--noise", default="0.004,0.01,0.02")
    p.add_argument("--records", default="1,2")
    p.add_argument("--evidence", default="equation-error,output-error")
    p.add_argument("--effects", default=",".join(EFFECTS))
    p.add_argument("--sizes", default="0.0025,0.005,0.01,0.02", help="effect sizes of --part information")
    args = p.parse_args()
    args.noise = [float(s) for s in args.noise.split(",")]
    args.records = [int(s) for s in args.records.split(",")]
    args.evidence = args.evidence.split(",")
    args.effects = args.effects.split(",")
    args.sizes = [float(v) for v in args.sizes.split(",")]
    args.null_cases = [w for w in args.null_cases.split(",") if w]
    print(f"peak displacement {X:.4g} m, peak velocity {V:.4g} m/s, force amplitude {FA:.4g} N")
    if args.part in ("detection", "all"):
        detection(args)
    if args.part in ("cases", "all"):
        cases(args)
    if args.part in ("beyond", "all"):
        beyond(args)
    if args.part in ("false-alarms", "all"):
        false_alarms(args)
    if args.part in ("information", "all"):
        information(args)
    size = f"-{100 * args.size:g}pct" if args.part in ("cases", "beyond") else ""
    _report.write_page(f"discrepancy-{args.part}{size}", __doc__)


if __name__ == "__main__":
    main()
