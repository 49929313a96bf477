"""Optimal control: per-iteration time of rsmooth's DDP and R-DDP on Solo-12, against Crocoddyl.

The task is the Solo-12 lift-foot problem of ``rsmooth control solo-lift``
(:func:`rsmooth.experiments.control_solo_lift.build_problem`, foot FL, 5 cm, dt = 0.01 s, hard
frictional contact, torques within +-2.7 N m, residual costs), for horizons T = 50 and 100.
Ours: Box-DDP (:func:`rsmooth.control.ddp`) and R-DDP (:func:`rsmooth.control.rddp`, first-order
estimator, the experiment's noise scales, M = 8 and 32 samples per node, every timed iteration
smoothed; and at the largest M the zeroth-order estimator, which needs the sampled steps but not
their Jacobians). R-DDP starts from the standing torques (the experiment's initial guess); DDP starts
from the controls of the first R-DDP solve (M = 8: the foot partly lifted), since from the
standing torques its first iteration sees a zero derivative of the foot height and it stops.
(Random perturbations of the standing torques make the robot collapse within the horizon, and
the contact solver then runs to its iteration cap: not a representative trajectory.) Per
iteration: the median of the wall times of the iterations of one solve, the first (compilation)
excluded; then a breakdown on the first iteration's state (median of ``repeats`` calls of each jitted part): dynamics Jacobians (exact,
or Monte-Carlo smoothed), cost derivatives, one backward pass (with the box QPs), one
forward-pass trial (rollout of the true dynamics), and the whole step.

Crocoddyl (when importable, with a Pinocchio it agrees with): the same URDF with a free-flyer,
``DifferentialActionModelContactFwdDynamics`` with FR, HL and HR in rigid 3-D contact
(``ContactModel3D``, the contact phase given by hand: all nodes), ``IntegratedActionModelEuler``
(dt = 0.01), costs mirroring ours (state and torque regularization, foot translation targets:
the lifted foot's height, the other feet's positions, and the base position), the same initial
controls as R-DDP (standing torques) with the states at x0, ``SolverFDDP`` (and
``SolverBoxFDDP`` with our torque box, for reference); per iteration: the median over the
iterations of ``repeats`` solves. Its dynamics are first checked
against ``pinocchio.aba`` and a rigid-contact KKT solve.

By default the process is pinned to one CPU and Crocoddyl runs one thread: on the shared
2-core machines XLA's two-thread CPU runtime was 10-30x slower and erratic on these programs
(inner ``while`` loops of the contact solver) when other processes were busy; ``--all-cpus``
turns that off. Everything is timed in this one process (float64).

Ratios (goals from the issue): our DDP iteration / Crocoddyl FDDP iteration (<= 3);
R-DDP M = 32 iteration / our DDP iteration (<= 4); and how each grows with T and M.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import os
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks._timing import fmt, machine, median_time, solo12  # noqa: E402
from rsmooth import _xla, control, sim  # noqa: E402
from rsmooth.control import _ddp  # noqa: E402
from rsmooth.experiments import control_solo_lift  # noqa: E402

HORIZONS = (50, 100)
SAMPLES = (8, 32)
ITERATIONS = 8
# --quick: one small problem, no breakdown (compilation dominates: about 45 s for the DDP step
# and 85 s for the R-DDP step on the 2-core machines, plus as much again for the breakdown's parts).
QUICK_HORIZONS = (10,)
QUICK_SAMPLES = (4,)
QUICK_ITERATIONS = 3
FOOT = "FL"
# DDP.node_batch_size and RDDP.sample_node_batch_size, the solvers' defaults. Measured with the
# sticking guess and closed-form step derivatives, one core, T = 50: DDP's node Jacobians 2.2-2.6 ms all nodes
# at once against 4.4-4.6 ms one at a time where every contact sticks, 4.2 against 4.1 ms on this
# benchmark's first DDP state; R-DDP M = 32 236 ms per iteration all at once against 129 ms (M
# samples per node are already a batch). Earlier (jacfwd through the contact solver) batching nodes was no faster: DDP
# 91 ms (1), 85 ms (10), 148 ms (all); R-DDP M = 8 760 ms (1), 790 ms (4), 1.37 s (all).
# On a GPU (an H200) R-DDP M = 32 took 376 ms per iteration one node at a time and
# 56 ms all at once (with all line-search step sizes at once too): RDDP's "auto" picks by backend.
DDP_NODE_BATCH = None
RDDP_NODE_BATCH = "auto"
# Crocoddyl releases and the Pinocchio each was built against (a different one segfaults or
# gave wrong dynamics beside pin 4.1.0).
CROCODDYL_PINOCCHIO = {"3.2.1": "4.0.0"}
ENABLE_CROCODDYL = (
    "run this benchmark from a virtual environment that has rsmooth (pip install -e '.[all]') with "
    "pin==4.0.0 and crocoddyl installed"
)


def _version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def pin_to_one_cpu() -> str:
    """Restricts this process to one CPU before XLA starts (XLA sizes its thread pool from the
    affinity mask); returns a description."""
    from jax._src import xla_bridge

    if xla_bridge._backends:  # too late: the thread pool exists
        return "not pinned (the JAX backend was already initialized)"
    allowed = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {allowed[0]})
    return f"pinned to CPU {allowed[0]} of {len(allowed)} (XLA and Crocoddyl single-threaded)"


# ---------------------------------------------------------------------------------------------
# ours


def _trials(step_sizes: np.ndarray, improvements: np.ndarray, num_step_sizes: int, th_stop: float, batch: int = 1) -> float:
    """Mean number of forward-pass trials (rollouts) per iteration, from the accepted step sizes;
    with `batch` step sizes rolled out at once (DDP.line_search_batch), whole batches."""
    batch = min(batch, num_step_sizes)
    trials = []
    for alpha, improvement in zip(step_sizes, improvements):
        if not np.isfinite(improvement) or improvement < th_stop:
            trials.append(0)  # failed backward pass or convergence test: no line search
        elif alpha > 0:
            trials.append(-(-(int(round(-np.log2(alpha))) + 1) // batch) * batch)
        else:
            trials.append(-(-num_step_sizes // batch) * batch)
    return float(np.mean(trials)) if trials else float("nan")


def _auto(value, accelerator) -> str:
    """A batch-size setting as printed: "auto" with what it means on this backend."""
    if value != "auto":
        return str(value)
    return f"auto ({_xla.resolve_auto(value, cpu=1, accelerator=accelerator)} on {jax.default_backend()})"


def _foot_height(problem, xs) -> float:
    """How far the lifted foot rose over the trajectory (m)."""
    lifted = control_solo_lift.FEET.index(FOOT)
    start, end = (sim.solo12_foot_positions(problem.dynamics, x)[lifted, 2] for x in (xs[0], xs[-1]))
    return float(end - start)


def time_ours(name: str, solver: control.DDP, problem, us_init, key, repeats: int, breakdown: bool) -> dict:
    """One solve (per-iteration wall times) and, optionally, the breakdown of an iteration."""
    start = time.perf_counter()
    if name == "ddp":
        solution = control.ddp(problem, us_init, solver=solver)
    else:
        solution = control.rddp(problem, key, us_init, solver=solver)
    wall = time.perf_counter() - start
    times = np.asarray(solution.stats["time_per_iteration"])
    noise = np.asarray(solution.stats["noise"])[: len(times)]  # noise[i]: that of iteration i + 1
    selected = np.arange(1, len(times))
    if name != "ddp":
        selected = selected[noise[selected] > 0]  # smoothed iterations only
    result = {
        "iterations": solution.iterations,
        "timed": len(selected),
        "per_iteration": float(np.median(times[selected])) if len(selected) else float("nan"),
        "first": float(times[0]) if len(times) else float("nan"),
        "wall": wall,
        "trials": _trials(
            np.asarray(solution.stats["step_size"])[1:],
            np.asarray(solution.stats["expected_improvement"])[1:],
            solver.num_step_sizes,
            solver.th_stop,
            solver._line_search_batch(),
        ),
        "cost": (float(solution.stats["cost"][0]), float(solution.cost)),
        "us": solution.us,
        "foot_height": float(_foot_height(problem, solution.xs)),
    }
    if not breakdown:
        return result

    compiled = dataclasses.replace(solver, throw=True)  # the program the solve compiled
    state = _ddp._jitted_init(compiled, problem, problem.clip(us_init), key)
    jacobians = eqx.filter_jit(lambda s, p, st: s._dynamics_jacobians(p, st))
    costs = eqx.filter_jit(lambda p, xs, us: _ddp._cost_derivatives(p, xs, us))
    backward = eqx.filter_jit(lambda s, p, st, d: s._backward_pass(p, st, d, st.regularization))
    forward = eqx.filter_jit(lambda s, p, tr, k, K: s._forward_pass(p, tr, k, K, 1.0))
    xs, us = state.trajectory.xs, state.trajectory.us
    d = _ddp._Derivatives(*jacobians(compiled, problem, state), *costs(problem, xs, us))
    b = backward(compiled, problem, state, d)
    result["jacobians"] = median_time(jacobians, compiled, problem, state, repeats=repeats, warmup=1)
    result["cost_derivatives"] = median_time(costs, problem, xs, us, repeats=repeats, warmup=1)
    result["backward"] = median_time(backward, compiled, problem, state, d, repeats=repeats, warmup=1)
    result["forward"] = median_time(forward, compiled, problem, state.trajectory, b.feedforward, b.gains, repeats=repeats, warmup=1)
    result["step"] = median_time(_ddp._jitted_step, compiled, problem, state, repeats=repeats, warmup=1)
    first = _ddp._jitted_step(compiled, problem, state)
    result["step_trials"] = _trials(
        np.asarray([first.step_size]), np.asarray([first.expected_improvement]), solver.num_step_sizes, solver.th_stop,
        solver._line_search_batch(),
    )
    return result


# ---------------------------------------------------------------------------------------------
# Crocoddyl


def crocoddyl_status() -> tuple[object | None, str]:
    """``(crocoddyl, description)``, or ``(None, why it is skipped)``."""
    try:
        import crocoddyl
        import pinocchio
    except ImportError as error:
        return None, f"Crocoddyl skipped: cannot import it ({error}). To enable: {ENABLE_CROCODDYL}"
    version = _version("crocoddyl") or _version("libcrocoddyl") or "?"
    pin_version = pinocchio.__version__
    wanted = CROCODDYL_PINOCCHIO.get(version)
    if wanted is not None and pin_version != wanted:
        return None, (
            f"Crocoddyl skipped: crocoddyl {version} needs pin=={wanted} (it segfaults or gives wrong dynamics "
            f"with pin {pin_version}). To enable: {ENABLE_CROCODDYL}"
        )
    return crocoddyl, f"crocoddyl {version}, pinocchio {pin_version}"


def _weighted(crocoddyl, state, residual, weights):
    """A cost ``0.5 sum_i w_i r_i^2`` (Crocoddyl's weighted quadratic activation)."""
    activation = crocoddyl.ActivationModelWeightedQuad(np.asarray(weights, dtype=float))
    return crocoddyl.CostModelResidual(state, activation, residual)


def crocoddyl_problem(crocoddyl, horizon: int, x0, u0, feet0, lifted: int, height: float, dt: float, limit: float):
    """The lift-foot task in Crocoddyl; our costs ``weight * e^2`` are ``0.5 (2 weight) e^2``."""
    import pinocchio as pin

    model = pin.buildModelFromUrdf(str(sim.solo12_urdf_path()), pin.JointModelFreeFlyer())
    state = crocoddyl.StateMultibody(model)
    actuation = crocoddyl.ActuationModelFloatingBase(state)
    nu = actuation.nu
    frames = [model.getFrameId(name) for name in sim.SOLO12_FEET]
    support = [i for i in range(4) if i != lifted]
    x0 = np.asarray(x0, dtype=float)
    u0 = np.asarray(u0, dtype=float)
    feet0 = np.asarray(feet0, dtype=float)

    def contacts():
        model_ = crocoddyl.ContactModelMultiple(state, nu)
        for i in support:
            contact = crocoddyl.ContactModel3D(state, frames[i], feet0[i], pin.LOCAL_WORLD_ALIGNED, nu, np.array([0.0, 50.0]))
            model_.addContact(sim.SOLO12_FEET[i], contact)
        return model_

    # Ours penalizes the quaternion's vector part (about half the rotation angle): weight / 4 on
    # the angle, which Crocoddyl's state difference uses.
    ndx = state.ndx
    posture = np.concatenate([[2 * 10.0] * 3, [2 * 10.0 / 4] * 3, [2 * 0.1] * 12, [2 * 1e-3] * 18])
    running = crocoddyl.CostModelSum(state, nu)
    running.addCost("posture", _weighted(crocoddyl, state, crocoddyl.ResidualModelState(state, x0, nu), posture), 1.0)
    running.addCost("torque", _weighted(crocoddyl, state, crocoddyl.ResidualModelControl(state, u0), [2 * 1e-2] * nu), 1.0)
    terminal = crocoddyl.CostModelSum(state, nu)
    target = feet0[lifted] + np.array([0.0, 0.0, height])
    lift = crocoddyl.ResidualModelFrameTranslation(state, frames[lifted], target, nu)
    terminal.addCost("lifted_foot", _weighted(crocoddyl, state, lift, [0.0, 0.0, 2 * 1e3]), 1.0)
    for i in support:
        foot = crocoddyl.ResidualModelFrameTranslation(state, frames[i], feet0[i], nu)
        terminal.addCost(sim.SOLO12_FEET[i], _weighted(crocoddyl, state, foot, [2 * 1e3] * 3), 1.0)
    base = np.concatenate([[2 * 10.0] * 3, [0.0] * (ndx // 2 - 3), [2 * 1e-3] * (ndx // 2)])
    terminal.addCost("base", _weighted(crocoddyl, state, crocoddyl.ResidualModelState(state, x0, nu), base), 1.0)

    def action(costs, step):
        dynamics = crocoddyl.DifferentialActionModelContactFwdDynamics(state, actuation, contacts(), costs, 0.0, True)
        model_ = crocoddyl.IntegratedActionModelEuler(dynamics, step)
        model_.u_lb = np.full(nu, -limit)
        model_.u_ub = np.full(nu, limit)
        return model_

    runnings = [action(running, dt) for _ in range(horizon)]
    problem = crocoddyl.ShootingProblem(x0, runnings, action(terminal, 0.0))
    return problem, model, frames


def crocoddyl_dynamics_error(crocoddyl, model, frames, lifted: int, key) -> tuple[float, float]:
    """Max relative errors of Crocoddyl's accelerations against ``pinocchio.aba`` (no contact)
    and against a KKT solve of the rigid 3-D contacts built from Pinocchio's terms, at a
    random state and torque."""
    import pinocchio as pin

    rng = np.random.default_rng(int(jax.random.randint(key, (), 0, 2**31 - 1)))
    data = model.createData()
    q = pin.integrate(model, pin.neutral(model), rng.normal(size=model.nv) * 0.3)
    v = rng.normal(size=model.nv)
    u = rng.normal(size=model.nv - 6)
    tau = np.concatenate([np.zeros(6), u])
    state = crocoddyl.StateMultibody(model)
    actuation = crocoddyl.ActuationModelFloatingBase(state)
    costs = crocoddyl.CostModelSum(state, actuation.nu)
    x = np.concatenate([q, v])

    free = crocoddyl.DifferentialActionModelFreeFwdDynamics(state, actuation, costs)
    free_data = free.createData()
    free.calc(free_data, x, u)
    reference = pin.aba(model, data, q, v, tau)
    error_free = float(np.max(np.abs(free_data.xout - reference)) / max(1.0, np.max(np.abs(reference))))

    support = [i for i in range(4) if i != lifted]
    contacts = crocoddyl.ContactModelMultiple(state, actuation.nu)
    for i in support:
        contacts.addContact(str(i), crocoddyl.ContactModel3D(state, frames[i], np.zeros(3), pin.LOCAL_WORLD_ALIGNED, actuation.nu, np.zeros(2)))
    constrained = crocoddyl.DifferentialActionModelContactFwdDynamics(state, actuation, contacts, costs, 0.0, True)
    constrained_data = constrained.createData()
    constrained.calc(constrained_data, x, u)
    pin.computeAllTerms(model, data, q, v)
    pin.forwardKinematics(model, data, q, v, np.zeros(model.nv))
    pin.updateFramePlacements(model, data)
    jacobian = np.concatenate([pin.getFrameJacobian(model, data, frames[i], pin.LOCAL_WORLD_ALIGNED)[:3] for i in support])
    drift = np.concatenate([pin.getFrameClassicalAcceleration(model, data, frames[i], pin.LOCAL_WORLD_ALIGNED).linear for i in support])
    n = jacobian.shape[0]
    kkt = np.block([[data.M, jacobian.T], [jacobian, np.zeros((n, n))]])
    solution = np.linalg.solve(kkt, np.concatenate([tau - data.nle, -drift]))
    reference = solution[: model.nv]
    error_contact = float(np.max(np.abs(constrained_data.xout - reference)) / max(1.0, np.max(np.abs(reference))))
    return error_free, error_contact


def time_crocoddyl(crocoddyl, problem, model, frames, lifted: int, us_init, iterations: int, repeats: int, box: bool, single_thread: bool) -> dict:
    """Per-iteration times (median over ``repeats`` solves) and a breakdown of an iteration."""
    import pinocchio as pin

    if single_thread:
        problem.nthreads = 1
    us = [np.asarray(u, dtype=float) for u in us_init]
    # FDDP's usual start: the states at x0 (the open-loop rollout of the standing torques on three
    # rigid contacts tips the robot over).
    xs = [np.asarray(problem.x0)] * (problem.T + 1)
    Solver = crocoddyl.SolverBoxFDDP if box else crocoddyl.SolverFDDP

    class Clock(crocoddyl.CallbackAbstract):
        def __init__(self):
            crocoddyl.CallbackAbstract.__init__(self)
            self.stamps = []

        def __call__(self, solver):
            self.stamps.append(time.perf_counter())

    per_iteration, counts = [], []
    solver = None
    for _ in range(max(1, repeats)):
        solver = Solver(problem)
        clock = Clock()
        solver.setCallbacks([clock])
        start = time.perf_counter()
        solver.solve(xs, us, iterations, False)
        stamps = np.asarray([start] + clock.stamps)
        per_iteration += list(np.diff(stamps))
        counts.append(len(clock.stamps))
    # The lifted foot's final height above its start: did Crocoddyl do the task?
    data = model.createData()
    q_first, q_last = np.asarray(solver.xs[0])[: model.nq], np.asarray(solver.xs[-1])[: model.nq]
    heights = []
    for q in (q_first, q_last):
        pin.framesForwardKinematics(model, data, q)
        heights.append(float(data.oMf[frames[lifted]].translation[2]))
    # Breakdown, at the solution.
    sol_xs, sol_us = list(solver.xs), list(solver.us)

    def median_wall(fn):
        fn()
        times = []
        for _ in range(max(3, repeats)):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        return statistics.median(times)

    result = {
        "per_iteration": float(np.median(per_iteration)) if per_iteration else float("nan"),
        "iterations": int(statistics.median(counts)),
        "timed": len(per_iteration),
        "cost": float(solver.cost),
        "foot_height": heights[1] - heights[0],
        "calc": median_wall(lambda: problem.calc(sol_xs, sol_us)),
        "calcDiff": median_wall(lambda: problem.calcDiff(sol_xs, sol_us)),
    }
    problem.calcDiff(sol_xs, sol_us)
    solver.calcDiff()
    result["backward"] = median_wall(solver.backwardPass)
    result["forward"] = median_wall(lambda: solver.forwardPass(1.0))
    return result


# ---------------------------------------------------------------------------------------------


def main(
    repeats: int = 5,
    quick: bool = False,
    horizons: tuple[int, ...] | None = None,
    samples: tuple[int, ...] | None = None,
    iterations: int | None = None,
    ddp_node_batch: int | None | str = "default",
    rddp_node_batch: int | None | str = "default",
    line_search_batch: int | str = "auto",
    all_cpus: bool = False,
    breakdown: bool = True,
) -> dict:
    horizons = horizons or (QUICK_HORIZONS if quick else HORIZONS)
    samples = samples or (QUICK_SAMPLES if quick else SAMPLES)
    iterations = iterations or (QUICK_ITERATIONS if quick else ITERATIONS)
    if quick:
        repeats = min(repeats, 3)
        breakdown = False
    ddp_node_batch = DDP_NODE_BATCH if ddp_node_batch == "default" else ddp_node_batch
    rddp_node_batch = RDDP_NODE_BATCH if rddp_node_batch == "default" else rddp_node_batch
    cpus = "all CPUs (not pinned)" if all_cpus else pin_to_one_cpu()
    print(f"machine: {machine()}; {cpus}; load average {', '.join(f'{x:.1f}' for x in os.getloadavg())}")
    parts = f"breakdown: median of {repeats} calls" if breakdown else "no breakdown"
    print(
        f"Solo-12 lift {FOOT} foot 5 cm, dt = 0.01 s, float64; T = {horizons}; R-DDP M = {samples}; "
        f"{iterations} iterations per solve; node batch: DDP {ddp_node_batch}, R-DDP {_auto(rddp_node_batch, None)}; "
        f"line-search batch {_auto(line_search_batch, 'all')}; {parts}"
    )
    croc, croc_note = crocoddyl_status()
    print(croc_note + "\n", flush=True)

    setup = time.perf_counter()
    system = solo12()
    base_config = control_solo_lift.Config(foot=FOOT, horizon=max(horizons))
    results: dict = {"ours": {}, "crocoddyl": {}, "notes": [], "crocoddyl_status": croc_note}
    results["settings"] = {
        "horizons": list(horizons), "samples": list(samples), "iterations": iterations, "foot": FOOT, "cpus": cpus,
        "ddp_node_batch": ddp_node_batch, "rddp_node_batch": _auto(rddp_node_batch, None),
        "line_search_batch": _auto(line_search_batch, "all"), "breakdown": breakdown,
    }
    key = jax.random.key(0)
    lifted = control_solo_lift.FEET.index(FOOT)
    feet0 = np.asarray(sim.solo12_foot_positions(system, system.initial_state()))
    print(f"  (Solo-12 loaded in {time.perf_counter() - setup:.1f} s)", flush=True)

    # ----- Crocoddyl first: it is fast, and a broken build fails before the long part
    if croc is not None:
        for T in horizons:
            _, problem, u0 = control_solo_lift.build_problem(dataclasses.replace(base_config, horizon=T), system=system)
            us_init = np.tile(np.asarray(u0), (T, 1))
            x0 = np.asarray(problem.x0)
            try:
                croc_problem, model, frames = crocoddyl_problem(
                    croc, T, x0, np.asarray(u0), feet0, lifted, base_config.height, float(system.time_step), sim.SOLO12_TORQUE_LIMIT
                )
                if T == horizons[0]:
                    error_free, error_contact = crocoddyl_dynamics_error(croc, model, frames, lifted, key)
                    results["crocoddyl"]["dynamics_error"] = (error_free, error_contact)
                    print(f"Crocoddyl's accelerations vs pinocchio.aba: {error_free:.1e}; vs a rigid-contact KKT solve: {error_contact:.1e} (relative)")
                    if not (error_free < 1e-6 and error_contact < 1e-6):
                        print("Crocoddyl skipped: its dynamics disagree with Pinocchio's (a mismatched build?)")
                        croc = None
                        break
                for box in (False, True):
                    name = "boxfddp" if box else "fddp"
                    results["crocoddyl"][(name, T)] = time_crocoddyl(
                        croc, croc_problem, model, frames, lifted, us_init, max(iterations, 20), repeats, box, not all_cpus
                    )
                print(f"  (Crocoddyl T = {T} timed)", flush=True)
            except Exception as error:  # reported, the rest still runs
                results["notes"].append(f"Crocoddyl failed at T = {T}: {error!r}"[:300])
                croc = None
                break

    # ----- ours
    for T in horizons:
        config = dataclasses.replace(base_config, horizon=T)
        _, problem, u0 = control_solo_lift.build_problem(config, system=system)
        us_init = jnp.tile(u0, (T, 1))
        for M in samples:
            solver = dataclasses.replace(
                dataclasses.replace(config, num_samples=M).solver(),
                max_iterations=iterations,
                max_smoothed_iterations=iterations,
                throw=False,
                node_batch_size=ddp_node_batch,
                sample_node_batch_size=rddp_node_batch,
                line_search_batch=line_search_batch,
            )
            start = time.perf_counter()
            results["ours"][(f"rddp{M}", T)] = time_ours("rddp", solver, problem, us_init, key, repeats, breakdown)
            print(f"  (R-DDP M = {M}, T = {T} timed in {time.perf_counter() - start:.0f} s)", flush=True)
            if M == max(samples):
                # Zeroth order needs the sampled steps only, not their Jacobians: the batching
                # question of the goal at its cheapest (it does not lift the foot: the
                # experiment's estimator is first order; see control_solo_lift).
                start = time.perf_counter()
                zeroth = dataclasses.replace(solver, estimator="zeroth")
                try:
                    results["ours"][(f"rddp{M}zeroth", T)] = time_ours("rddp", zeroth, problem, us_init, key, repeats, breakdown)
                    print(f"  (R-DDP zeroth order M = {M}, T = {T} timed in {time.perf_counter() - start:.0f} s)", flush=True)
                except Exception as error:  # reported, the rest still runs
                    results["notes"].append(f"R-DDP zeroth order M = {M}, T = {T} failed: {str(error).splitlines()[-1]!r}"[:300])
            if M == samples[0]:
                # DDP from where this R-DDP stopped (the foot partly lifted): from the standing
                # torques its first iteration sees a zero derivative and it stops.
                ddp_solver = control.DDP(
                    max_iterations=iterations, throw=False, node_batch_size=ddp_node_batch, line_search_batch=line_search_batch
                )
                start = time.perf_counter()
                ddp_init = results["ours"][(f"rddp{M}", T)]["us"]
                results["ours"][("ddp", T)] = time_ours("ddp", ddp_solver, problem, ddp_init, None, repeats, breakdown)
                print(f"  (DDP T = {T} timed in {time.perf_counter() - start:.0f} s)", flush=True)

    report(results, horizons, samples, breakdown)
    sys.stdout.flush()
    return results


def json_results(results: dict) -> dict:
    """`main`'s results as JSON-ready lists: ``ours`` and ``crocoddyl`` a row per (solver, T)
    (without the control trajectories), ``crocoddyl_status`` (its version, or why it was skipped),
    ``dynamics_error``, ``settings``, ``ratios`` and ``notes``."""

    def rows(source: dict) -> list[dict]:
        return [
            {"solver": name, "T": T, **{k: v for k, v in r.items() if k != "us"}}
            for (name, T), r in sorted(((k, v) for k, v in source.items() if isinstance(k, tuple)), key=lambda kv: (kv[0][1], kv[0][0]))
        ]

    return {
        "ours": rows(results["ours"]),
        "crocoddyl": rows(results["crocoddyl"]),
        "crocoddyl_status": results.get("crocoddyl_status"),
        "dynamics_error": results["crocoddyl"].get("dynamics_error"),
        "settings": results.get("settings", {}),
        "ratios": results.get("ratios", {}),
        "notes": results["notes"],
    }


def report(results: dict, horizons, samples, breakdown: bool) -> None:
    ours, croc = results["ours"], results["crocoddyl"]
    rows = [("ddp", "ours: DDP (Box-DDP)")] + [(f"rddp{M}", f"ours: R-DDP M = {M}") for M in samples]
    rows += [(f"rddp{max(samples)}zeroth", f"ours: R-DDP M = {max(samples)}, zeroth order")]
    if croc:
        rows += [("fddp", "Crocoddyl SolverFDDP"), ("boxfddp", "Crocoddyl SolverBoxFDDP")]
    print("\nper iteration (median; ours: compiled iterations of one solve, Crocoddyl: all iterations of the solves)")
    width = max(len(label) for _, label in rows)
    print(f"{'':<{width}} | " + " | ".join(f"{f'T = {T}':>11} {'(n it)':>8}" for T in horizons))
    for name, label in rows:
        cells = []
        for T in horizons:
            r = ours.get((name, T)) or croc.get((name, T))
            cells.append(f"{fmt(r['per_iteration']):>11} {('(' + str(r['timed']) + ')'):>8}" if r else f"{'n/a':>11} {'':>8}")
        print(f"{label:<{width}} | " + " | ".join(cells))

    def get(source, name, T):
        r = source.get((name, T))
        return r["per_iteration"] if r else float("nan")

    print("\nratios (same run)")
    lines = []
    for T in horizons:
        if croc:
            lines.append((f"our DDP / Crocoddyl FDDP, T = {T}", get(ours, "ddp", T) / get(croc, "fddp", T), "<= 3"))
            lines.append((f"our DDP / Crocoddyl BoxFDDP, T = {T}", get(ours, "ddp", T) / get(croc, "boxfddp", T), ""))
        for M in samples:
            goal = "<= 4" if M == max(samples) else ""
            lines.append((f"R-DDP M = {M} / our DDP, T = {T}", get(ours, f"rddp{M}", T) / get(ours, "ddp", T), goal))
        M = max(samples)
        lines.append((f"R-DDP M = {M}, zeroth order / our DDP, T = {T}", get(ours, f"rddp{M}zeroth", T) / get(ours, "ddp", T), "<= 4"))
    if len(horizons) > 1:
        a, b = horizons[0], horizons[-1]
        for name, label in rows:
            source = croc if name in ("fddp", "boxfddp") else ours
            lines.append((f"{label}: T = {b} / T = {a}", get(source, name, b) / get(source, name, a), f"linear: {b / a:g}"))
    if len(samples) > 1:
        for T in horizons:
            lines.append((f"R-DDP M = {samples[-1]} / M = {samples[0]}, T = {T}", get(ours, f"rddp{samples[-1]}", T) / get(ours, f"rddp{samples[0]}", T), f"linear: {samples[-1] / samples[0]:g}"))
    width = max(len(line[0]) for line in lines)
    for label, value, goal in lines:
        note = f"   (goal {goal})" if goal.startswith("<") else f"   ({goal})" if goal else ""
        print(f"{label:<{width}} | {value:7.2f}{note}")
    results["ratios"] = {label: value for label, value, _ in lines}

    if breakdown:
        print("\nwhere an iteration goes (first iteration's state; median of calls; forward = one line-search trial)")
        labels = [f"{label}, T = {T}" for T in horizons for _, label in rows]
        width = max(len(label) for label in labels)
        print(f"{'':<{width}} | {'dyn. Jacobians':>14} | {'cost derivs':>13} | {'backward':>11} | {'forward x trials':>18} | {'whole step':>11}")
        for T in horizons:
            for name, label in rows:
                label = f"{label}, T = {T}"
                if (name, T) in ours:
                    r = ours[(name, T)]
                    cells = (fmt(r["jacobians"]), fmt(r["cost_derivatives"]), fmt(r["backward"]), f"{fmt(r['forward'])} x {r['step_trials']:g}", fmt(r["step"]))
                elif (name, T) in croc:
                    r = croc[(name, T)]
                    cells = (fmt(r["calcDiff"]), "(in calcDiff)", fmt(r["backward"]), f"{fmt(r['forward'])} x 1", "")
                else:
                    continue
                print(f"{label:<{width}} | {cells[0]:>14} | {cells[1]:>13} | {cells[2]:>11} | {cells[3]:>18} | {cells[4]:>11}")
        if croc:
            calcs = ", ".join(f"{fmt(croc[('fddp', T)]['calc']).strip()} at T = {T}" for T in horizons if ("fddp", T) in croc)
            print(f"(Crocoddyl: dyn. Jacobians = calcDiff of all nodes, dynamics and costs; calc of all nodes: {calcs})")

    print("\nsolves")
    for (name, T), r in sorted(ours.items(), key=lambda item: (item[0][1], item[0][0])):
        print(
            f"  ours {name:>7}, T = {T:>3}: {r['iterations']} iterations ({r['timed']} timed), first (compiles) {r['first']:.1f} s, "
            f"{r['trials']:.1f} line-search trials per iteration, cost {r['cost'][0]:.4g} -> {r['cost'][1]:.4g}, "
            f"lifted foot {100 * r['foot_height']:+.1f} cm"
        )
    for (name, T), r in sorted((k, v) for k, v in croc.items() if isinstance(k, tuple)):
        print(
            f"  Crocoddyl {name:>7}, T = {T:>3}: {r['iterations']} iterations, cost {r['cost']:.4g}, "
            f"lifted foot {100 * r['foot_height']:+.1f} cm"
        )
    for note in results["notes"]:
        print(f"  note: {note}")


if __name__ == "__main__":
    from rsmooth import _xla

    _xla.apply_cpu_defaults()  # the settings `rsmooth` and `python -m benchmarks` run with, before JAX starts
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5, help="calls per breakdown timing and Crocoddyl solves (median)")
    parser.add_argument("--quick", action="store_true", help=f"T = {QUICK_HORIZONS}, M = {QUICK_SAMPLES}, {QUICK_ITERATIONS} iterations, no breakdown")
    parser.add_argument("--horizons", type=int, nargs="+")
    parser.add_argument("--samples", type=int, nargs="+")
    parser.add_argument("--iterations", type=int)
    batch = lambda s: s if s in ("default", "auto") else None if s == "none" else int(s)  # noqa: E731
    parser.add_argument("--ddp-node-batch", type=batch, default="default", help="DDP.node_batch_size for DDP (int or none)")
    parser.add_argument(
        "--rddp-node-batch", type=batch, default="default", help="RDDP.sample_node_batch_size (int, none or auto, the default)"
    )
    parser.add_argument(
        "--line-search-batch", type=lambda s: s if s == "auto" else int(s), default="auto",
        help="DDP.line_search_batch, DDP and R-DDP (int or auto, the default: 1 on the CPU, all step sizes on a GPU)",
    )
    parser.add_argument("--all-cpus", action="store_true", help="do not pin the process to one CPU")
    parser.add_argument("--no-breakdown", action="store_true")
    parser.add_argument("--json", metavar="DIR", help="also write the results to DIR/control.json (benchmarks._record)")
    args = parser.parse_args()
    from benchmarks import _record

    options = dict(
        repeats=args.repeats,
        quick=args.quick,
        horizons=tuple(args.horizons) if args.horizons else None,
        samples=tuple(args.samples) if args.samples else None,
        iterations=args.iterations,
        ddp_node_batch=args.ddp_node_batch,
        rddp_node_batch=args.rddp_node_batch,
        line_search_batch=args.line_search_batch,
        all_cpus=args.all_cpus,
        breakdown=not args.no_breakdown,
    )
    _record.run_and_record("control", main, command=_record.command_line(), options=options, directory=args.json,
                           transform=json_results)
