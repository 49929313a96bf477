"""Box towers: rsmooth's whole step (collision, contact solve, integration) against MuJoCo C's
``mj_step``, for towers of N boxes.

A tower of N cubes (side 10 cm, 1 kg, friction 0.5) resting on a floor, written in MJCF and
loaded by both (``sim.scene`` for rsmooth), time step 0.01 s. MuJoCo: its default solver and
soft contacts, ``mj_step`` on one ``MjData`` reset to the resting tower before each call (C,
one thread), per step. rsmooth: hard contact, float64, with a contact budget of
``max_contacts = 8 N`` (the resting tower touches at 4 N corners among ``4 N + 2 N (N - 1)``
candidates; every pair of boxes is a candidate pair, as MuJoCo's filters keep them) and a broad
phase of ``max_pairs = N`` (the N box pairs and the N box-floor pairs of smallest
bounding-sphere gap are collided: N - 1 box pairs and one floor pair touch), timed as
``jit(vmap(step))`` over a batch of ``BATCH`` copies of the resting tower, per env; also the
compile time of that program (lower and compile). Medians of ``repeats`` calls after warm-up.
Where rsmooth's step goes: its stages (:mod:`rsmooth.sim`'s ``collision``: the candidates'
distances, frames and witness points, ``free_motion``, ``solve_contacts``: the contact
Jacobian's rows of the selected contacts, the NCP, its velocity, impulses and diagnostics, as
the step reads them; only derivatives read the candidates' full Jacobian and the Delassus
matrix, which a step forms only where the solve's start does not solve the problem) timed
the same way, each a program of its own (their sum exceeds the step, whose program shares the
kinematics between them).

Every timed step starts its contact solve cold, the same for all three: rsmooth from zero
impulses (where its sticking guess runs), MuJoCo with ``qacc_warmstart`` zeroed before each
``mj_step`` (``mj_setState`` with ``mjSTATE_FULLPHYSICS`` leaves the previous call's solution
there), MJX from ``put_data`` after ``mj_forward`` (a zero ``qacc_warmstart``).

Ratios: ours per env / ``mj_step`` (the issue's goal: <= 2 in a batch of 64), and the growth
of each with N, the log-log slope of time per step from the smallest to the largest N (the
goal: ours no steeper than MuJoCo's). Sanity: after ``SETTLE`` steps both towers stand, each
box's height within a millimetre of ``(i + 1/2) 10 cm`` (MuJoCo's soft contacts sink by a
fraction of that). MJX (``mujoco-mjx``, whose version must match MuJoCo's: the ``bench`` extra)
on the same MJCF: ``jit(vmap(mjx.step))`` over the same batch, per env, its compile time, and
its height error after ``SETTLE`` steps of one env; without MJX its entries are null and the
record says why. MJX is the JAX program MuJoCo's developers write for the same physics: what a
JAX step on this CPU costs, beside the C one.
"""

from __future__ import annotations

import math
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks._timing import fmt, machine, median_time  # noqa: E402
from rsmooth import sim  # noqa: E402

BATCH = 64
HALF = 0.05
DT = 0.01
SETTLE = 50
SIZES = (2, 4, 8, 16)
QUICK_SIZES = (2, 4, 8)


def tower(n: int) -> str:
    """The MJCF of a tower of ``n`` cubes resting on a floor, each on the one below."""
    bodies = "".join(
        f'<body name="box{i}" pos="0 0 {HALF * (2 * i + 1):.3f}"><freejoint/>'
        f'<geom type="box" size="{HALF} {HALF} {HALF}" mass="1" friction="0.5"/></body>'
        for i in range(n)
    )
    return (
        f'<mujoco><option timestep="{DT}"/><worldbody><geom name="floor" type="plane" size="2 2 0.1" friction="0.5"/>'
        f"{bodies}</worldbody></mujoco>"
    )


def _heights_error(heights: np.ndarray) -> float:
    return float(np.max(np.abs(heights - HALF * (2 * np.arange(len(heights)) + 1))))


def _solved(solution):
    """What a step reads of :func:`rsmooth.sim.solve_contacts`: the velocity, impulses and diagnostics."""
    return solution.velocity, solution.impulse, solution.joint_impulse, solution.ncp


def _collided(contacts):
    """What a step without derivatives reads of :func:`rsmooth.sim.collision` (the candidates'
    full Jacobian left out: the solve builds the selected contacts' rows)."""
    return contacts.distance, contacts.frames, contacts.points, contacts.friction, contacts.joint_rows


def _stage_times(system, xs, us, repeats: int) -> dict:
    """Seconds per env of each stage of the batched step (see the module docstring)."""
    qs, vs = system.split(xs)
    collision = jax.jit(jax.vmap(lambda q: sim.collision(system, q)))
    collided = jax.jit(jax.vmap(lambda q: _collided(sim.collision(system, q))))
    free_motion = jax.jit(jax.vmap(lambda q, v, u: sim.free_motion(system, q, v, u)))
    # the step's outputs of the solve (the Delassus matrix, which only derivatives read, left out)
    solve = jax.jit(jax.vmap(lambda motion, contacts: _solved(sim.solve_contacts(system, motion, contacts))))
    contacts, motion = collision(qs), free_motion(qs, vs, us)
    return {
        "collision": median_time(collided, qs, repeats=repeats) / BATCH,
        "free_motion": median_time(free_motion, qs, vs, us, repeats=repeats) / BATCH,
        "solve_contacts": median_time(solve, motion, contacts, repeats=repeats) / BATCH,
        "jacobian_rows": int(contacts.jacobian.shape[1]),
        "solved_rows": 3 * min(system.options.max_contacts or system.num_contacts, system.num_contacts),
    }


def measure_mjx(xml: str, n: int, repeats: int) -> dict:
    """MJX's batched step on the tower (see the module docstring); raises where MJX is missing."""
    import mujoco
    from mujoco import mjx

    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    mx, dx = mjx.put_model(model), mjx.put_data(model, data)
    batch = jax.tree.map(lambda leaf: jnp.broadcast_to(leaf, (BATCH,) + leaf.shape), dx)
    step_batch = jax.jit(jax.vmap(mjx.step, in_axes=(None, 0)))
    start = time.perf_counter()
    compiled = step_batch.lower(mx, batch).compile()
    compile_s = time.perf_counter() - start
    per_env = median_time(compiled, mx, batch, repeats=repeats) / BATCH
    step = jax.jit(mjx.step)
    for _ in range(SETTLE):
        dx = step(mx, dx)
    return {"mjx_step_batch": per_env, "mjx_compile_s": compile_s,
            "mjx_height_error": _heights_error(np.asarray(dx.qpos).reshape(n, 7)[:, 2])}


def measure(n: int, repeats: int, with_mjx: bool = True) -> dict:
    import mujoco

    xml = tower(n)
    system = sim.scene(xml, max_contacts=8 * n, max_pairs=n)
    x0 = system.initial_state()
    xs = jnp.tile(x0, (BATCH, 1))
    us = jnp.zeros((BATCH, system.nu))
    step_batch = jax.jit(jax.vmap(lambda x, u: system.step(x, u)))
    start = time.perf_counter()
    compiled = step_batch.lower(xs, us).compile()
    compile_s = time.perf_counter() - start
    ours = median_time(compiled, xs, us, repeats=repeats) / BATCH
    stages = _stage_times(system, xs, us, repeats)
    rollout = jax.jit(lambda x: system.rollout(x, jnp.zeros((SETTLE, system.nu))))
    states, infos = rollout(x0)
    counts = sim.check_steps(infos, what=f"the tower of {n} boxes")
    ours_error = _heights_error(np.asarray(states[-1, : 7 * n]).reshape(n, 7)[:, 2])

    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    state0 = np.empty(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(model, data, state0, mujoco.mjtState.mjSTATE_FULLPHYSICS)

    def one_step():
        mujoco.mj_setState(model, data, state0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        data.qacc_warmstart[:] = 0.0  # cold, as rsmooth's step (module docstring)
        mujoco.mj_step(model, data)

    reference = median_time(one_step, repeats=max(repeats, 200))
    mujoco.mj_setState(model, data, state0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    for _ in range(SETTLE):
        mujoco.mj_step(model, data)
    mujoco_error = _heights_error(np.asarray(data.qpos).reshape(n, 7)[:, 2])
    reference_mjx, mjx_error = {}, None
    if with_mjx:
        try:
            reference_mjx = measure_mjx(xml, n, repeats)
        except ImportError as error:  # MJX missing, or not matching MuJoCo: null entries, rsmooth's measured
            mjx_error = f"MJX unavailable: {error!r}"[:300]
    return {
        "candidates": system.num_contacts,
        "pairs": len(system.geometry.geom_pairs),
        "max_contacts": system.options.max_contacts,
        "max_pairs": system.options.max_pairs,
        "ours_step_batch": ours,
        "ours_compile_s": compile_s,
        "ours_stages": stages,
        "mj_step": reference,
        "ratio": ours / reference,
        "ours_height_error": ours_error,
        "mujoco_height_error": mujoco_error,
        "ours_unconverged_steps": counts["unconverged_steps"],
        "ours_dropped_contact_steps": counts["dropped_contact_steps"],
        "ours_skipped_pair_steps": counts["skipped_pair_steps"],
        "mjx_step_batch": reference_mjx.get("mjx_step_batch"),
        "mjx_compile_s": reference_mjx.get("mjx_compile_s"),
        "mjx_height_error": reference_mjx.get("mjx_height_error"),
        "mjx_ratio": reference_mjx["mjx_step_batch"] / reference if reference_mjx else None,
        "mjx_error": mjx_error,
    }


def _slope(sizes, times) -> float:
    return math.log(times[-1] / times[0]) / math.log(sizes[-1] / sizes[0])


def main(repeats: int = 30, quick: bool = False) -> dict:
    sizes = QUICK_SIZES if quick else SIZES
    repeats = min(repeats, 5) if quick else max(3, repeats // 3)
    print(f"machine: {machine()}")
    print(
        f"towers of N cubes ({2 * HALF} m, 1 kg, mu 0.5) on a floor, dt = {DT} s; ours: float64, "
        f"jit(vmap(step)) over {BATCH}, per env, max_contacts = 8 N, max_pairs = N; MuJoCo: mj_step, one thread; "
        f"every step cold (zero impulses / qacc_warmstart); median of {repeats} calls\n"
    )
    cases = {}
    header = (f"{'N':>3} {'pairs':>6} {'cand.':>6} {'ours/env':>10} {'mj_step':>10} {'ratio':>8} {'compile':>9} "
              f"{'MJX/env':>10} {'MJX ratio':>9} {'height err ours / mj / MJX':>28}")
    print(header)
    mjx_error = None
    for n in sizes:
        case = measure(n, repeats, with_mjx=mjx_error is None)
        error = case.pop("mjx_error")
        mjx_error = mjx_error or error
        cases[str(n)] = case
        mjx = case["mjx_step_batch"] is not None
        print(
            f"{n:>3} {case['pairs']:>6} {case['candidates']:>6} {fmt(case['ours_step_batch']):>10} {fmt(case['mj_step']):>10} "
            f"{case['ratio']:>8.1f} {case['ours_compile_s']:>8.1f}s "
            f"{fmt(case['mjx_step_batch']) if mjx else '-':>10} {case['mjx_ratio'] if mjx else float('nan'):>9.1f} "
            f"{case['ours_height_error'] * 1e3:>10.3f} / {case['mujoco_height_error'] * 1e3:.3f} / "
            f"{case['mjx_height_error'] * 1e3 if mjx else float('nan'):.3f} mm",
            flush=True,
        )
    print(f"\nours by stage, per env (each stage its own program): {'collision':>10} {'free motion':>12} {'contact solve':>14}"
          f"  (candidate rows / solved rows)")
    for n in sizes:
        stage = cases[str(n)]["ours_stages"]
        print(f"{n:>3}{'':>49} {fmt(stage['collision']):>10} {fmt(stage['free_motion']):>12} {fmt(stage['solve_contacts']):>14}"
              f"  ({stage['jacobian_rows']} / {stage['solved_rows']})")
    ours = [cases[str(n)]["ours_step_batch"] for n in sizes]
    reference = [cases[str(n)]["mj_step"] for n in sizes]
    growth = {"ours": _slope(sizes, ours), "mj_step": _slope(sizes, reference)}
    if mjx_error is None:
        growth["mjx"] = _slope(sizes, [cases[str(n)]["mjx_step_batch"] for n in sizes])
    print(
        f"\ngrowth with N (log-log slope, N = {sizes[0]} to {sizes[-1]}): ours {growth['ours']:.2f}, "
        f"mj_step {growth['mj_step']:.2f}" + (f", MJX {growth['mjx']:.2f}" if "mjx" in growth else "") + " (goal: ours <= mj_step's)"
    )
    print("goal: ours per env / mj_step <= 2 in a batch of 64 (ratio column)")
    if mjx_error:
        print(f"note: {mjx_error}")
    return {"batch": BATCH, "cold_start": True, "sizes": list(sizes), "cases": cases, "growth": growth, "notes": [mjx_error] if mjx_error else []}
