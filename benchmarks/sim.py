"""Simulator: rsmooth's JAX Solo-12 step against MuJoCo (C) and MJX, on CPU.

Solo-12 from the example-robot-data URDF, free-flyer base, four sphere feet of radius
``sim.SOLO12_FOOT_RADIUS`` at the ``*_FOOT`` frames on a floor (contacts feet vs floor only),
12 joint torques, time step 0.01 s, friction 0.7, float64, started at the same standing posture
under the same gravity-compensating torques. Everything is timed in this one process (median of
``repeats`` calls after warm-up; JAX outputs blocked on). Our batched calls are also timed on a
perturbed batch (5 steps under the standing torques plus noise), where feet slide or lift: at the
standing states the sticking guess solves the contact problem at once, on the perturbed ones the
Newton polish (``NCPSolver.polish``) does, and the perturbed step is also timed with the polish
off (ADMM from the sticking guess) for comparison; MuJoCo's step and transition derivative are
timed on its own states after the same protocol (its warm starts included).

Ratios (goals from the issue): our batched step per env / ``mj_step`` (<= 2);
``mjd_transitionFD`` / our full Jacobian w.r.t. (x, u) (>= 5); MJX step / our step.
MJX is the `mujoco-mjx` package (``pip install -e ".[bench]"``); without it its rows print n/a.
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing
import pathlib
import re
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks._timing import fmt, machine, median_time, solo12  # noqa: E402
from rsmooth import sim  # noqa: E402

BATCH = 64
PROBE_BATCH = 8
SANITY_STEPS = 10
DT = 0.01
FRICTION = 0.7


# ---------------------------------------------------------------------------------------------
# MuJoCo model built from the same URDF


def mujoco_solo12():
    """Solo-12 in MuJoCo: the URDF with package:// paths rewritten, a free joint on the base, a
    floor, foot spheres at the foot bodies (the only colliding pairs: feet vs floor), 12 motors,
    the rotor inertia and joint damping of :func:`rsmooth.sim.solo12` on the 12 hinges."""
    import mujoco

    urdf_path = sim.solo12_urdf_path()
    # .../share/example-robot-data/robots/solo_description/robots/solo12.urdf
    share = urdf_path.parents[3]  # .../share/example-robot-data
    text = urdf_path.read_text()
    text = text.replace("package://example-robot-data/", str(share) + "/")
    compiler = '<mujoco><compiler balanceinertia="true" discardvisual="false" fusestatic="false"/></mujoco>'
    text = re.sub(r"(<robot[^>]*>)", r"\1" + compiler, text, count=1)
    spec = mujoco.MjSpec.from_string(text)
    spec.option.timestep = DT
    base = spec.body("base_link")
    base.add_freejoint()
    for geom in spec.geoms:  # mesh collision geometry: no contacts
        geom.contype = 0
        geom.conaffinity = 0
    floor = spec.worldbody.add_geom()
    floor.type = mujoco.mjtGeom.mjGEOM_PLANE
    floor.size = [0.0, 0.0, 0.05]
    floor.contype = 0
    floor.conaffinity = 1
    floor.friction = [FRICTION, 0.005, 0.0001]
    for name in sim.SOLO12_FEET:
        foot = spec.body(name).add_geom()
        foot.type = mujoco.mjtGeom.mjGEOM_SPHERE
        foot.size = [sim.SOLO12_FOOT_RADIUS, 0.0, 0.0]
        foot.contype = 1
        foot.conaffinity = 0
        foot.friction = [FRICTION, 0.005, 0.0001]
    joints = [j.name for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_HINGE]
    for joint in spec.joints:  # the same rotor inertia and joint damping as sim.solo12()
        if joint.type == mujoco.mjtJoint.mjJNT_HINGE:
            joint.armature = sim.SOLO12_ARMATURE
            joint.damping = [sim.SOLO12_JOINT_DAMPING, 0.0, 0.0]  # MuJoCo 4 takes 3 numbers; the first is the linear damping
    for name in joints:
        motor = spec.add_actuator()
        motor.name = name + "_motor"
        motor.trntype = mujoco.mjtTrn.mjTRN_JOINT
        motor.target = name
        motor.gear = [1.0, 0, 0, 0, 0, 0]
        motor.ctrllimited = True
        motor.ctrlrange = [-sim.SOLO12_TORQUE_LIMIT, sim.SOLO12_TORQUE_LIMIT]
    model = spec.compile()
    return model, joints


def to_mujoco_qpos(q: np.ndarray) -> np.ndarray:
    """Our [x, y, z, qx, qy, qz, qw, joints] to MuJoCo's [x, y, z, qw, qx, qy, qz, joints]."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[:3], q[6:7], q[3:6], q[7:]])


def _median_wall(fn, repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


# ---------------------------------------------------------------------------------------------
# probe: does jit(vmap(jacfwd(step))) compile and run within a time limit? (it can hang XLA on CPU)


def _probe_vmap_jacobian(batch: int, queue, repeats: int = 0) -> None:  # runs in a child process
    # On a GPU the parent holds 75 % of its memory (JAX's default): allocate on demand here
    # (before this process's backend starts), or XLA reports an out-of-memory error first.
    import os

    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    try:
        jax.config.update("jax_enable_x64", True)
        system = solo12(friction=FRICTION, time_step=DT)
        x0 = system.initial_state()
        u0 = sim.solo12_standing_torques(system, x0)
        jac = jax.jacfwd(lambda x, u: system.step(x, u), argnums=(0, 1))
        fn = jax.jit(jax.vmap(jac))
        xs, us = jnp.tile(x0, (batch, 1)), jnp.tile(u0, (batch, 1))
        start = time.perf_counter()
        jax.block_until_ready(fn(xs, us))
        first = time.perf_counter() - start
        median = median_time(fn, xs, us, repeats=repeats, warmup=1) if repeats else None
        queue.put(("ok", (first, median)))
    except Exception as error:  # pragma: no cover - reported
        queue.put(("error", repr(error)))


def probe_vmap_jacobian(batch: int, timeout: float, repeats: int = 0) -> tuple[bool, str, float | None]:
    """Whether ``jit(vmap(jacfwd(step)))`` at ``batch`` compiles and runs within ``timeout``
    seconds, in a child process, a note, and with ``repeats`` the median time of a call there.
    The timing runs in the child too: the batched program can stop XLA:CPU (threads waiting on
    each other, see rsmooth._xla) even after a first call returned, and a stopped child is
    killed at the timeout where a stopped benchmark process would wait forever."""
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    process = ctx.Process(target=_probe_vmap_jacobian, args=(batch, queue, repeats), daemon=True)
    process.start()
    process.join(timeout)
    if process.is_alive():
        process.kill()
        process.join()
        return False, f"jit(vmap(jacfwd(step))) at batch {batch} did not finish in {timeout:.0f} s (hang)", None
    if queue.empty():
        return False, f"probe at batch {batch} died (exit code {process.exitcode})", None
    status, value = queue.get()
    if status == "ok":
        first, median = value
        return True, f"jit(vmap(jacfwd(step))) at batch {batch}: compiled and ran in {first:.1f} s", median
    return False, f"probe at batch {batch} failed: {value}", None


# ---------------------------------------------------------------------------------------------


def main(repeats: int = 30, quick: bool = False, probe_timeout: float = 90.0, chunk_sizes: tuple[int, ...] = ()) -> dict:
    if quick:
        repeats = min(repeats, 5)
    print(f"machine: {machine()}")
    print(
        f"Solo-12, 4 sphere feet (r = {sim.SOLO12_FOOT_RADIUS} m) on a floor, dt = {DT} s, mu = {FRICTION}, "
        f"float64 (jax_enable_x64); median of {repeats} calls after warm-up\n"
    )
    results: dict = {}
    notes: list[str] = []

    # ----- ours
    system = solo12(friction=FRICTION, time_step=DT)
    x0 = system.initial_state()
    u0 = sim.solo12_standing_torques(system, x0)
    nq = system.model.nq
    step = jax.jit(lambda x, u: system.step(x, u))
    xs = jnp.tile(x0, (BATCH, 1))
    us = jnp.tile(u0, (BATCH, 1))
    step_batch = jax.jit(jax.vmap(lambda x, u: system.step(x, u)))
    jac = jax.jacfwd(lambda x, u: system.step(x, u), argnums=(0, 1))
    jac1 = jax.jit(jac)

    # sanity: 10 steps standing
    x = x0
    for _ in range(SANITY_STEPS):
        x = step(x, u0)
    ours_drift = float(x[2] - x0[2])
    ours_joint = float(jnp.max(jnp.abs(x[7:nq] - x0[7:nq])))

    # A second batch where the contact solver works: 5 steps under the standing torques plus
    # Gaussian noise of 0.5 N m (feet slide, lift or press harder); at the standing states the
    # sticking guess solves the contact problem without ADMM iterations, at the perturbed ones
    # the Newton polish (and, with the polish off, ADMM: its iterations are counted too).
    noise = 0.5 * jax.random.normal(jax.random.key(0), (BATCH, system.nu))
    us_perturbed = us + noise
    xs_perturbed = xs
    for _ in range(5):
        xs_perturbed = step_batch(xs_perturbed, us_perturbed)
    info_batch = jax.jit(jax.vmap(lambda x, u: system.step_with_info(x, u)[1].ncp.iterations))
    iterations = {name: np.asarray(info_batch(x, u)) for name, x, u in
                  (("standing", xs, us), ("perturbed", xs_perturbed, us_perturbed))}
    unpolished = system.with_options(solver=dataclasses.replace(system.solver, polish=False))
    step_batch_unpolished = jax.jit(jax.vmap(lambda x, u: unpolished.step(x, u)))
    iterations["perturbed, polish off,"] = np.asarray(
        jax.jit(jax.vmap(lambda x, u: unpolished.step_with_info(x, u)[1].ncp.iterations))(xs_perturbed, us_perturbed)
    )

    results["ours_step"] = median_time(step, x0, u0, repeats=repeats)
    results["ours_step_batch"] = median_time(step_batch, xs, us, repeats=repeats) / BATCH
    results["ours_step_batch_perturbed"] = median_time(step_batch, xs_perturbed, us_perturbed, repeats=repeats) / BATCH
    results["ours_step_batch_perturbed_unpolished"] = (
        median_time(step_batch_unpolished, xs_perturbed, us_perturbed, repeats=repeats) / BATCH
    )
    results["ours_jac"] = median_time(jac1, x0, u0, repeats=repeats)
    # the reference derivative: autodiff through CRBA, Cholesky and the Delassus matrix
    reference = system.with_options(derivative="autodiff")
    jac_autodiff = jax.jit(jax.jacfwd(lambda x, u: reference.step(x, u), argnums=(0, 1)))
    results["ours_jac_autodiff"] = median_time(jac_autodiff, x0, u0, repeats=repeats)
    # what DDP and R-DDP call: the next state and both Jacobians from one contact solve
    step_jac = jax.jit(lambda x, u: system.step_and_jacobians(x, u))
    results["ours_step_jac"] = median_time(step_jac, x0, u0, repeats=repeats)
    step_jac_batch = jax.jit(jax.vmap(lambda x, u: system.step_and_jacobians(x, u)))
    # At least 9 calls (a call is ~5 ms): with 3 (--quick) these medians moved by 40 % between runs.
    results["ours_step_jac_batch"] = median_time(step_jac_batch, xs, us, repeats=max(9, repeats // 3)) / BATCH
    results["ours_step_jac_batch_perturbed"] = median_time(
        step_jac_batch, xs_perturbed, us_perturbed, repeats=max(9, repeats // 3)
    ) / BATCH
    # The perturbed batch with other NCPSolver.chunk_size values than the solver's ("auto": 4 on the
    # CPU, the whole batch on a GPU), in this run: the problems the start did not solve go through
    # the polish and ADMM loops this many at a time
    chunk_rows = []
    for chunk in chunk_sizes:
        chunked = system.with_options(solver=dataclasses.replace(system.solver, chunk_size=chunk))
        key_step, key_jac = f"ours_step_batch_perturbed_chunk{chunk}", f"ours_step_jac_batch_perturbed_chunk{chunk}"
        results[key_step] = median_time(
            jax.jit(jax.vmap(lambda x, u: chunked.step(x, u))), xs_perturbed, us_perturbed, repeats=repeats
        ) / BATCH
        results[key_jac] = median_time(
            jax.jit(jax.vmap(lambda x, u: chunked.step_and_jacobians(x, u))), xs_perturbed, us_perturbed,
            repeats=max(9, repeats // 3),
        ) / BATCH
        chunk_rows += [
            (f"ours: jit(vmap(step)), batch {BATCH} perturbed, chunk_size {chunk}, per env", key_step),
            (f"ours: vmap(step_and_jacobians), batch {BATCH} perturbed, chunk_size {chunk}, per env", key_jac),
        ]
    print("  (ours: step, vmapped step and Jacobian timed; probing vmap(jacfwd) in a subprocess)", flush=True)

    ok, message, _ = probe_vmap_jacobian(PROBE_BATCH, probe_timeout)
    notes.append(message)
    jac_label = f"jacfwd(step), vmap {BATCH}, per env"
    median = None
    if ok:
        # timed in the child: see probe_vmap_jacobian
        ok, message64, median = probe_vmap_jacobian(BATCH, probe_timeout, repeats=max(3, repeats // 3))
        notes.append(message64)
    if ok:
        results["ours_jac_batch"] = median / BATCH
    else:
        # sequential lax.map: a lax.map with batch_size > 1 is a vmap inside and hangs the same way
        jac_batch = jax.jit(lambda xs, us: jax.lax.map(lambda a: jac(*a), (xs, us)))
        jac_label = f"jacfwd(step), lax.map over {BATCH} (sequential), per env"
        notes.append(f"batched Jacobian timed with jax.lax.map (no batch_size) instead of vmap")
        results["ours_jac_batch"] = median_time(jac_batch, xs, us, repeats=max(3, repeats // 3)) / BATCH

    # ----- MuJoCo C
    mj_ok = True
    try:
        import mujoco

        model, joints = mujoco_solo12()
        data = mujoco.MjData(model)
        qpos0 = to_mujoco_qpos(np.asarray(x0[:nq]))
        ctrl0 = np.asarray(u0)
        ours_joint_names = [n for n in system.model.joint_names if n in joints] if hasattr(system.model, "joint_names") else joints
        assert list(ours_joint_names) == list(joints), (ours_joint_names, joints)

        def reset():
            mujoco.mj_resetData(model, data)
            data.qpos[:] = qpos0
            data.ctrl[:] = ctrl0
            mujoco.mj_forward(model, data)

        reset()
        for _ in range(SANITY_STEPS):
            mujoco.mj_step(model, data)
        mj_drift = float(data.qpos[2] - qpos0[2])
        mj_joint = float(np.max(np.abs(data.qpos[7:] - qpos0[7:])))
        mj_ncon = int(data.ncon)

        reset()
        state0 = np.empty(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS))
        mujoco.mj_getState(model, data, state0, mujoco.mjtState.mjSTATE_FULLPHYSICS)

        def one_step():
            mujoco.mj_setState(model, data, state0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
            mujoco.mj_step(model, data)

        n_inner = 100
        results["mj_step"] = _median_wall(lambda: [one_step() for _ in range(n_inner)], repeats) / n_inner
        # The perturbed batch's protocol in MuJoCo's own dynamics: 5 steps under the standing
        # torques plus the same noise, then one step from each of those states (their
        # controls and solver warm starts included: mjSTATE_INTEGRATION).
        perturbed_states = []
        for row in np.asarray(noise):
            reset()
            data.ctrl[:] = ctrl0 + row
            for _ in range(5):
                mujoco.mj_step(model, data)
            state = np.empty(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION))
            mujoco.mj_getState(model, data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
            perturbed_states.append(state)

        def perturbed_steps():
            for state in perturbed_states:
                mujoco.mj_setState(model, data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
                mujoco.mj_step(model, data)

        results["mj_step_perturbed"] = _median_wall(perturbed_steps, repeats) / len(perturbed_states)
        nx = 2 * model.nv + model.na
        A = np.zeros((nx, nx))
        B = np.zeros((nx, model.nu))
        reset()
        results["mjd_transitionFD"] = _median_wall(
            lambda: mujoco.mjd_transitionFD(model, data, 1e-6, False, A, B, None, None), repeats
        )

        def perturbed_transitions():
            for state in perturbed_states:
                mujoco.mj_setState(model, data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
                mujoco.mjd_transitionFD(model, data, 1e-6, False, A, B, None, None)

        results["mjd_transitionFD_perturbed"] = _median_wall(perturbed_transitions, repeats) / len(perturbed_states)
        try:
            from mujoco import rollout

            nstep = 100
            datas = [mujoco.MjData(model) for _ in range(2)]
            init = np.tile(state0, (BATCH, 1))
            control = np.tile(ctrl0, (BATCH, nstep, 1))
            with rollout.Rollout(nthread=2) as runner:
                runner.rollout(model, datas, init, control)
                results["mj_rollout"] = _median_wall(
                    lambda: runner.rollout(model, datas, init, control), max(3, repeats // 3), warmup=1
                ) / (BATCH * nstep)
        except Exception as error:
            notes.append(f"mujoco.rollout unavailable: {error!r}")
    except Exception as error:
        mj_ok = False
        notes.append(f"MuJoCo failed: {error!r}")

    # ----- MJX
    mjx_ok = False
    if mj_ok:
        try:
            from mujoco import mjx

            mx = mjx.put_model(model)
            reset()
            dx = mjx.put_data(model, data)
            mjx_step = jax.jit(mjx.step)
            d = dx
            for _ in range(SANITY_STEPS):
                d = mjx_step(mx, d)
            mjx_drift = float(d.qpos[2] - qpos0[2])
            results["mjx_step"] = median_time(mjx_step, mx, dx, repeats=repeats)
            dxs = jax.tree.map(lambda a: jnp.broadcast_to(a, (BATCH,) + jnp.shape(a)), dx)
            mjx_batch = jax.jit(jax.vmap(mjx.step, in_axes=(None, 0)))
            results["mjx_step_batch"] = median_time(mjx_batch, mx, dxs, repeats=repeats) / BATCH
            mjx_ok = True
        except Exception as error:
            notes.append(f"MJX unavailable: {error!r}"[:300])

    # ----- report
    print(f"sanity, {SANITY_STEPS} steps under the same standing torques (base height drift; max joint drift):")
    print(f"  ours:   dz = {ours_drift:+.2e} m; joints {ours_joint:.2e} rad")
    if mj_ok:
        print(f"  MuJoCo: dz = {mj_drift:+.2e} m; joints {mj_joint:.2e} rad; {mj_ncon} contacts")
    if mjx_ok:
        print(f"  MJX:    dz = {mjx_drift:+.2e} m")
    for name, counts in iterations.items():
        print(f"  ADMM iterations in the {name} batch: mean {counts.mean():.1f}, max {counts.max()}")
    print()
    rows = [
        ("ours: jit(step), batch 1", "ours_step"),
        (f"ours: jit(vmap(step)), batch {BATCH}, per env", "ours_step_batch"),
        (f"ours: jit(vmap(step)), batch {BATCH} perturbed, per env", "ours_step_batch_perturbed"),
        (f"ours: jit(vmap(step)), batch {BATCH} perturbed, polish off, per env", "ours_step_batch_perturbed_unpolished"),
        ("ours: jacfwd(step) w.r.t. (x, u), batch 1", "ours_jac"),
        ("ours: jacfwd(step), derivative='autodiff' (reference), batch 1", "ours_jac_autodiff"),
        (f"ours: {jac_label}", "ours_jac_batch"),
        ("ours: step_and_jacobians (next state, d/dx, d/du), batch 1", "ours_step_jac"),
        (f"ours: vmap(step_and_jacobians), batch {BATCH}, per env", "ours_step_jac_batch"),
        (f"ours: vmap(step_and_jacobians), batch {BATCH} perturbed, per env", "ours_step_jac_batch_perturbed"),
        *chunk_rows,
        ("MuJoCo: mj_step", "mj_step"),
        ("MuJoCo: mj_step, perturbed states", "mj_step_perturbed"),
        ("MuJoCo: mjd_transitionFD (forward, eps 1e-6)", "mjd_transitionFD"),
        ("MuJoCo: mjd_transitionFD, perturbed states", "mjd_transitionFD_perturbed"),
        (f"MuJoCo: rollout {BATCH} x 100 steps, 2 threads, per step", "mj_rollout"),
        ("MJX: jit(step), batch 1", "mjx_step"),
        (f"MJX: jit(vmap(step)), batch {BATCH}, per env", "mjx_step_batch"),
    ]
    width = max(len(r[0]) for r in rows)
    for label, key in rows:
        value = fmt(results[key]) if key in results else "     n/a"
        print(f"{label:<{width}} | {value}")
    print()

    def ratio(a, b):
        return results[a] / results[b] if a in results and b in results else float("nan")

    ratios = [
        ("our step per env (vmap 64) / mj_step", ratio("ours_step_batch", "mj_step"), "<= 2"),
        ("  the same, perturbed states", ratio("ours_step_batch_perturbed", "mj_step_perturbed"), "<= 2"),
        ("  the same, polish off", ratio("ours_step_batch_perturbed_unpolished", "mj_step_perturbed"), "<= 2"),
        ("our step (batch 1) / mj_step", ratio("ours_step", "mj_step"), ""),
        ("mjd_transitionFD / our Jacobian (batch 1)", ratio("mjd_transitionFD", "ours_jac"), ">= 5"),
        ("our autodiff-reference Jacobian / our implicit one", ratio("ours_jac_autodiff", "ours_jac"), ""),
        ("mjd_transitionFD / our Jacobian per env (batched)", ratio("mjd_transitionFD", "ours_jac_batch"), ">= 5"),
        ("mjd_transitionFD / our step_and_jacobians (batch 1)", ratio("mjd_transitionFD", "ours_step_jac"), ">= 5"),
        (f"mjd_transitionFD / vmap(step_and_jacobians) per env", ratio("mjd_transitionFD", "ours_step_jac_batch"), ">= 5"),
        ("  the same, perturbed states (both)", ratio("mjd_transitionFD_perturbed", "ours_step_jac_batch_perturbed"), ">= 5"),
        ("MJX step / our step (batch 1)", ratio("mjx_step", "ours_step"), ""),
        (f"MJX step / our step (vmap {BATCH}, per env)", ratio("mjx_step_batch", "ours_step_batch"), ""),
    ]
    width = max(len(r[0]) for r in ratios)
    for label, value, goal in ratios:
        print(f"{label:<{width}} | {value:7.2f}" + (f"   (goal {goal})" if goal else ""))
    results["ratios"] = {label: value for label, value, _ in ratios}
    assert len(results["ratios"]) == len(ratios), "ratio labels must be unique (they key the JSON record)"
    results["batch"] = BATCH
    results["jac_batch_method"] = "vmap" if ok else "lax.map (sequential)"
    results["sanity"] = {"ours_base_drift_m": ours_drift, "ours_joint_drift_rad": ours_joint}
    if mj_ok:
        results["sanity"].update(mujoco_base_drift_m=mj_drift, mujoco_joint_drift_rad=mj_joint, mujoco_contacts=mj_ncon)
    if mjx_ok:
        results["sanity"]["mjx_base_drift_m"] = mjx_drift
    results["admm_iterations"] = {name.strip(" ,"): {"mean": float(c.mean()), "max": int(c.max())} for name, c in iterations.items()}
    results["notes"] = notes
    if notes:
        print("\nnotes:")
        for note in notes:
            print(f"  - {note}")
    sys.stdout.flush()
    return results


if __name__ == "__main__":
    from rsmooth import _xla

    _xla.apply_cpu_defaults()  # the settings `rsmooth` and `python -m benchmarks` run with, before JAX starts
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--quick", action="store_true", help="at most 5 repeats")
    parser.add_argument("--probe-timeout", type=float, default=90.0)
    parser.add_argument("--json", metavar="DIR", help="also write the results to DIR/sim.json (benchmarks._record)")
    parser.add_argument(
        "--chunk-sizes", type=int, nargs="+", default=[],
        help="also time the perturbed batch with these NCPSolver.chunk_size values (default: only the solver's own, "
        "'auto': 4 on the CPU, the whole batch on a GPU)",
    )
    args = parser.parse_args()
    from benchmarks import _record

    options = dict(repeats=args.repeats, quick=args.quick, probe_timeout=args.probe_timeout, chunk_sizes=tuple(args.chunk_sizes))
    _record.run_and_record("sim", main, command=_record.command_line(), options=options, directory=args.json)
