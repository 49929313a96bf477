"""Shared test configuration: double precision, strict rank promotion, seeded keys."""

import itertools
import os

# Compile fast rather than run fast: most of the suite's time is XLA compiling small programs,
# and LLVM's optimizations are a large part of that. At level 0 (instead of XLA's default 2) the
# whole suite runs faster on 2 cores (the run-bound control tests slower, the compile-bound ones
# faster); the programs' HLO and so their results are the same, up to rounding. Set here, before
# JAX starts its backend, and inherited by the tests' subprocesses; a level already in XLA_FLAGS
# is kept.
# XLA:CPU's MLIR fusion emitters take about twice as long to compile the large programs (a
# DDP or R-DDP step through the contact solver) as its older loop emitters; the tests compile
# with the older ones. Its concurrency-optimized scheduler makes a batched program more likely
# to wait forever on its own threads (rsmooth._xla): off, as the rsmooth command has it. Same rule: a
# setting already in XLA_FLAGS is kept.
for _flag, _value in (("--xla_backend_optimization_level", "0"), ("--xla_cpu_use_fusion_emitters", "false"),
                      ("--xla_cpu_enable_concurrency_optimized_scheduler", "false")):
    if _flag not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_flag}={_value}".strip()

# On a GPU, JAX takes 75 % of its memory when its backend starts: with `pytest -n 2` the second
# worker then fails at start-up (CUDA_ERROR_OUT_OF_MEMORY; seen on an H200 with 8 workers).
# Allocate on demand instead; a setting already in the environment is kept. (No effect on CPU.)
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


# No persistent compilation cache in the tests, not even the `rsmooth` command's own
# (~/.cache/rsmooth/jax) in their subprocesses: every run starts cold, as CI does, and writes
# nothing outside its temporary folders. A cache shared by the workers does not make the
# suite faster (its programs differ), and jaxlib 0.10's XLA:CPU can crash while serializing
# an executable for it (`put_executable_and_time`, under the full suite).
os.environ.setdefault("RSMOOTH_COMPILATION_CACHE", "0")


def pytest_collection_modifyitems(config, items):
    """Tests marked ``slow`` (30 s to 2 min each, mostly compilation) run first: pytest-xdist
    (``--dist worksteal``, pyproject.toml) starts the first worker on them and lets the other
    take tests from the end of its queue, so a slow one started last cannot keep one worker
    busy while the other has nothing left to do. The order of the others is unchanged."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture
def getkey():
    """Returns a function that gives a fresh, deterministic PRNG key at each call."""
    counter = itertools.count()
    base = jax.random.key(0)

    def _getkey():
        return jax.random.fold_in(base, next(counter))

    return _getkey


@pytest.fixture(autouse=True)
def _double_precision_after_each_test():
    """A test that runs a float32 CLI command in-process (`rsmooth render ...` turns x64
    off) must not change the precision of the tests after it in the same worker."""
    yield
    jax.config.update("jax_enable_x64", True)


_tests_run = itertools.count(1)


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    """A worker compiles thousands of programs, each holding memory maps until dropped from
    JAX's caches: past Linux's bound on them the worker dies compiling (a segmentation fault).
    Half-way there, the caches are dropped (rsmooth._xla.release_compiled_programs). Counting
    the maps reads /proc/self/maps (about 50 ms at 40,000 maps): after every 8th test, which
    adds far fewer maps than the half left."""
    from rsmooth import _xla  # imported after the precision is set above

    yield
    if next(_tests_run) % 8 == 0:
        _xla.release_compiled_programs()


@pytest.fixture
def mujoco_and_rsmooth_trajectories():
    """``run(text, qpos, qvel, steps, ctrl=None, u=None) -> (system, loaded, xs, expected)``:
    MuJoCo's ``qpos`` after each of ``steps`` ``mj_step`` calls from ``(qpos, qvel)`` under the
    constant control ``ctrl`` (``expected``, ``(steps, nq)``), and rsmooth's rollout of
    ``sim.scene(text)`` from the same state under the constant input ``u`` (zero by default);
    for comparisons of scenes without contact with MuJoCo's Euler integrator."""
    import equinox as eqx
    import jax.numpy as jnp
    import mujoco
    import numpy as np

    from rsmooth import sim

    def run(text, qpos, qvel, steps, ctrl=None, u=None):
        m = mujoco.MjModel.from_xml_string(text)
        d = mujoco.MjData(m)
        if qpos is not None:
            d.qpos[:] = qpos
        d.qvel[:] = qvel
        if ctrl is not None:
            d.ctrl[:] = ctrl
        loaded = sim.load_mjcf(text)
        system = sim.scene(loaded)
        start = jnp.asarray(d.qpos)
        x0 = system.state(loaded.qpos_to_q(start), loaded.qvel_to_v(start, jnp.asarray(d.qvel)))
        expected = []
        for _ in range(steps):
            mujoco.mj_step(m, d)
            expected.append(d.qpos.copy())
        inputs = jnp.zeros((steps, system.nu)) if u is None else jnp.tile(jnp.asarray(u, float), (steps, 1))
        xs, _ = eqx.filter_jit(system.rollout)(x0, inputs)
        return system, loaded, xs, np.array(expected)

    return run


@pytest.fixture
def state_jacobian_is_central_differences():
    """``check(system, x, atol=1e-7)``: asserts that the state Jacobian of ``system``'s
    ``step_and_jacobians`` at ``x`` (zero input) equals central differences of its step (``eps
    = 1e-6``) to ``atol``."""
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    def check(system, x, atol=1e-7):
        u = jnp.zeros(system.nu)
        _, fx, _ = eqx.filter_jit(lambda s, x_, u_: s.step_and_jacobians(x_, u_))(system, x, u)
        step = eqx.filter_jit(lambda s, x_, u_: s.step(x_, u_))
        eps = 1e-6
        columns = [(step(system, x + eps * e, u) - step(system, x - eps * e, u)) / (2 * eps) for e in jnp.eye(x.shape[0])]
        np.testing.assert_allclose(np.asarray(fx), np.asarray(jnp.stack(columns, axis=1)), rtol=0, atol=atol)

    return check
