"""The bound on the Baumgarte correction's speed (Options.max_correction_speed): a cube started
inside its floor and a hinge started beyond its limit are pushed back at exactly the bound where
the full rate would exceed it, and at the full rate otherwise; the step's derivative in the
penetration is then zero, as the bounded correction's."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim

H, BETA, DEPTH = 0.01, 0.2, 0.05
step_jacobians = eqx.filter_jit(lambda system, x, u: system.step_and_jacobians(x, u))
rollout = eqx.filter_jit(lambda system, x0, us: system.rollout(x0, us))


def test_a_sunk_cube_rises_at_the_bound_and_its_derivative_in_depth_vanishes():
    cube = sim.cube(time_step=H, baumgarte=BETA)
    x0 = cube.initial_state().at[2].add(-DEPTH)  # its four lower corners 5 cm into the floor
    full_rate = BETA * DEPTH / H  # 1 m/s
    for bound, speed in ((float("inf"), full_rate), (0.3, 0.3), (2.0, full_rate)):
        system = cube.with_options(max_correction_speed=bound)
        xs, infos = rollout(system, x0, jnp.zeros((3, 6)))
        assert bool(np.all(infos.ncp.converged))
        # the first step's upward velocity; the next ones at the bound while it binds
        np.testing.assert_allclose(xs[1, 9], speed, rtol=1e-9)
        if bound == 0.3:
            np.testing.assert_allclose(xs[1:, 9], 0.3, rtol=1e-9)
            np.testing.assert_allclose(np.diff(xs[:, 2]), 0.3 * H, rtol=1e-9)
        # d v_z+ / d z: -beta / h at the full rate, zero at the bound
        _, fx, _ = step_jacobians(system, x0, jnp.zeros(6))
        np.testing.assert_allclose(fx[9, 2], 0.0 if bound == 0.3 else -BETA / H, atol=1e-7)


ARM = f"""<mujoco><option timestep="{H}" gravity="0 0 0"/><worldbody><body name="arm" pos="0 0 1">
<joint name="hinge" type="hinge" axis="0 1 0" limited="true" range="-30 30"/>
<geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.01" mass="1" contype="0" conaffinity="0"/>
</body></worldbody></mujoco>"""


def test_a_joint_beyond_its_limit_returns_at_the_bound():
    out = 0.5  # rad beyond the upper limit: the full rate is 0.2 * 0.5 / 0.01 = 10 rad/s
    for bound, rate in ((float("inf"), BETA * out / H), (1.0, 1.0)):
        system = sim.scene(ARM, baumgarte=BETA, max_correction_speed=bound)
        x0 = system.state(jnp.array([np.radians(30.0) + out]))
        xs, _ = rollout(system, x0, jnp.zeros((2, 0)))
        np.testing.assert_allclose(xs[1, 1], -rate, rtol=1e-9)


def test_the_bound_is_checked():
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="max_correction_speed must be positive"):
            sim.cube().with_options(max_correction_speed=bad)


CARTS = f"""<mujoco><option timestep="{H}" gravity="0 0 0"/><worldbody>
<body name="a"><joint name="a" type="slide" axis="1 0 0"/><geom size="0.1" mass="1" contype="0" conaffinity="0"/></body>
<body name="b" pos="0 1 0"><joint name="b" type="slide" axis="1 0 0"/><geom size="0.1" mass="1" contype="0" conaffinity="0"/></body>
</worldbody><equality><joint joint1="b" joint2="a"/></equality></mujoco>"""


def test_a_coupling_error_closes_at_the_bound():
    error = 0.5  # m: the full rate closes it at 0.2 * 0.5 / 0.01 = 10 m/s
    for bound, rate in ((float("inf"), BETA * error / H), (1.0, 1.0)):
        system = sim.scene(CARTS, baumgarte=BETA, max_correction_speed=bound)
        xs, _ = rollout(system, system.state(jnp.array([0.0, error])), jnp.zeros((1, 0)))
        np.testing.assert_allclose(xs[1, 3] - xs[1, 2], -rate, rtol=1e-9)
