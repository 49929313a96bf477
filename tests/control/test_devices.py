"""R-DDP's sampled linearization and the policy-gradient estimates with their samples on several
devices give the one-device results.

The test process has one CPU device; the multi-device cases run in one subprocess started
with ``--xla_force_host_platform_device_count=4`` (four XLA CPU devices), as in
tests/test_parallel.py."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import pytest
from control_systems import cube_lift

from rsmooth import control

_FOUR_DEVICES = textwrap.dedent(
    """
    import dataclasses, sys
    import equinox as eqx, jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_rank_promotion", "raise")
    sys.path.insert(0, sys.argv[1])
    from control_systems import cube_lift, pendulum_swing_up
    from rsmooth import control, sim
    assert len(jax.devices()) == 4, jax.devices()

    def same(a, b, tol=1e-12):
        for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            np.testing.assert_allclose(u, v, rtol=tol, atol=tol)

    jacobians = eqx.filter_jit(control.smoothed_dynamics_jacobians)

    # (a) a smooth system: the three estimators with the 3 x 8 (node, sample) pairs on 4
    # devices, or in chunks of 5 pairs on 3 devices (padded), equal one device's
    pendulum = pendulum_swing_up(horizon=3)
    xs = jax.random.normal(jax.random.key(1), (4, 2))
    us = jax.random.normal(jax.random.key(2), (3, 1))
    key = jax.random.key(3)
    for estimator, spread in [
        ("first", dict(devices="all")),
        ("zeroth", dict(devices=tuple(jax.devices()[:3]), sample_chunk=5)),
        ("alpha", dict(devices="all")),
    ]:
        run = lambda **spread: jacobians(
            pendulum, key, xs, us, eps=0.3, num_samples=8, estimator=estimator, noise_effect=True, **spread
        )
        same(run(**spread), run())

    # (a) through the contact solver (while loops, LAPACK): a ball on a floor, pushed along it,
    # first order by the simulator's own Jacobians (and project_state). Each CPU device
    # evaluates its pairs one at a time: equal to one device evaluating each pair alone; a
    # vmapped node's solver loops run until its slowest sample converges, so the default
    # moves within the solver's tolerance. (A cube resting on four coplanar corners would
    # not do: its rank-deficient contact solve turns the rounding of two programs into
    # differences of 1e-7 in its Jacobians, on one device as on several.)
    system = sim.ball()
    ball = control.ShootingProblem(
        system, lambda x, u: jnp.sum(u**2), lambda x: jnp.sum(x**2), system.initial_state(), 3
    )
    xs = jnp.broadcast_to(ball.x0, (4, ball.nx))
    us = jnp.broadcast_to(jnp.array([0.2, 0.0, 0.0]), (3, 3))
    run = lambda **spread: jacobians(ball, key, xs, us, eps=0.5, num_samples=8, state_noise_scale=1e-3, **spread)
    spread, alone, vmapped = run(devices="all"), run(sample_chunk=1), run()
    same(spread, alone)
    assert float(jnp.max(jnp.abs(alone[1]))) > 1e-3  # a non-trivial estimate
    for a, b in zip(vmapped, alone):
        assert float(jnp.max(jnp.abs(a - b))) < 1e-3 * float(jnp.max(jnp.abs(b)))

    # (b) R-DDP on a non-smooth lift (no solver loop): the solve on 4 devices is the
    # one-device solve, iterate for iterate
    lift = cube_lift(horizon=5)
    solver = control.RDDP(
        eps=1.0, num_samples=8, state_noise_scale=0.01, control_noise_scale=10.0, max_iterations=4, throw=False
    )
    spread = dataclasses.replace(solver, devices="all")
    state = spread.init(lift, jnp.zeros((lift.horizon, lift.nu)), key)
    assert "shard_map" in str(jax.make_jaxpr(lambda state: spread.step(lift, state))(state))
    one = control.rddp(lift, key, solver=solver)
    four = control.rddp(lift, key, solver=spread)
    assert one.iterations == four.iterations >= 2
    same(four.us, one.us, 1e-10)
    for name in ("cost", "noise", "expected_improvement"):
        same(four.stats[name], one.stats[name], 1e-10)

    # (c) policy gradients: policy_gradient passes devices and sample_chunk to the estimator;
    # PolicyGradient threads them to every estimate, shared samples included
    problem = pendulum_swing_up(horizon=4)
    policy = control.OpenLoop(horizon=4, nu=1)
    theta = jnp.linspace(-1.0, 1.0, 4)[:, None]
    gradient = jax.jit(
        lambda k, th, **spread: control.policy_gradient(
            problem, policy, k, th, sigma=0.1, num_samples=8, estimator="alpha", **spread
        ),
        static_argnames=("devices", "sample_chunk"),
    )
    same(gradient(key, theta, devices="all", sample_chunk=1), gradient(key, theta))
    for shared in (False, True):
        solver = control.PolicyGradient(
            estimator="alpha", sigma=0.1, num_samples=8, learning_rate=0.1, iterations=2, shared_samples=shared
        )
        one = control.optimize_policy(problem, policy, key, theta, solver=solver)
        four = control.optimize_policy(problem, policy, key, theta, solver=dataclasses.replace(solver, devices="all"))
        same(four.stats["theta"], one.stats["theta"])
        for name in ("cost", "smoothed_cost", "alpha", "variance"):
            same(four.stats[name], one.stats[name], 1e-10)
    print("ok")
    """
)


def _flags(flag: str) -> str:
    """XLA_FLAGS for a subprocess: the suite's own (tests/conftest.py) and ``flag``."""
    return f"{os.environ.get('XLA_FLAGS', '')} {flag}".strip()


def test_four_devices_give_the_one_device_linearization_solve_and_policy_gradients():
    """smoothed_dynamics_jacobians, an R-DDP solve and policy-gradient estimates and steps with
    their samples on 4 devices equal their one-device values to rounding (through the contact
    solver: against one device evaluating each sample alone, as each CPU device does)."""
    env = dict(os.environ, XLA_FLAGS=_flags("--xla_force_host_platform_device_count=4"), JAX_PLATFORMS="cpu")
    here = os.path.dirname(os.path.abspath(__file__))
    result = subprocess.run(
        [sys.executable, "-c", _FOUR_DEVICES, here], env=env, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("ok")


@pytest.mark.parametrize(
    "options, message",
    [
        ({"devices": "gpu"}, "devices must be None, 'all'"),
        ({"devices": []}, "devices must not be empty"),
        ({"devices": [0, 1]}, "devices must hold jax devices"),
        ({"devices": 2}, "devices must be None, 'all'"),
        ({"sample_chunk": 0}, "sample_chunk must be None or an int >= 1"),
        ({"sample_chunk": 2.0}, "sample_chunk must be None or an int >= 1"),
    ],
)
def test_bad_devices_or_chunk_are_refused_by_name(options, message):
    problem = cube_lift(horizon=2)
    xs, us = jnp.zeros((3, 2)), jnp.zeros((2, 1))
    with pytest.raises(ValueError, match=message):
        control.smoothed_dynamics_jacobians(problem, jax.random.key(0), xs, us, eps=0.1, num_samples=2, **options)
    with pytest.raises(ValueError, match=message):
        control.RDDP(**options)
    with pytest.raises(ValueError, match=message):
        control.PolicyGradient(**options)
    policy = control.OpenLoop(horizon=2, nu=1)
    with pytest.raises(ValueError, match=message):
        control.policy_gradient(problem, policy, jax.random.key(0), policy.init(), sigma=0.1, num_samples=2, **options)


def test_devices_are_static_and_hashable():
    """A list of devices is kept as a tuple: the solvers are static arguments of jitted steps."""
    devices = jax.devices()
    for solver in (control.RDDP(devices=list(devices), sample_chunk=2), control.PolicyGradient(devices=list(devices))):
        assert solver.devices == tuple(devices)
        hash(solver)
    assert control.RDDP().devices is None and control.PolicyGradient().sample_chunk is None
