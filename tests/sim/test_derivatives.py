"""The closed-form configuration derivative of a step's equations (rsmooth.sim._derivatives)
against forward-mode autodiff of the same equations."""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.sim import _derivatives, _simulator


@functools.lru_cache(maxsize=None)
def _solo():
    return sim.solo12()


def _solo_state(seed: int, spread: float):
    """Solo-12 near (spread small) or far from its standing posture (unit quaternion), with
    torques."""
    solo = _solo()
    x = solo.initial_state()
    keys = jax.random.split(jax.random.key(seed), 3)
    q_noise = spread * jax.random.normal(keys[0], (19,))
    v_noise = 10 * spread * jax.random.normal(keys[1], (18,))
    x = x + jnp.concatenate([q_noise, v_noise])
    x = x.at[3:7].set(x[3:7] / jnp.linalg.norm(x[3:7]))
    return solo, x, sim.solo12_standing_torques(solo, x) + 0.5 * jax.random.normal(keys[2], (12,))


def _pusher_state(seed: int, spread: float):
    """The pusher without its finger-box contact (prismatic finger joints, a free box on 8
    corners): a system the closed form supports."""
    full = sim.pusher()
    pusher = dataclasses.replace(full, geometry=dataclasses.replace(full.geometry, geom_pairs=()))
    x = full.initial_state()
    x = x + spread * jax.random.normal(jax.random.key(seed), x.shape)
    x = x.at[3:7].set(x[3:7] / jnp.linalg.norm(x[3:7])).at[2].set(0.099)  # corners 1 mm into the floor
    return pusher, x, jnp.array([3.0, -1.0])


@eqx.filter_jit
def _both(system, x, u):
    """(closed form, forward mode) of d(momentum, contact velocity) / d(q, v) at the step's
    solution (four matrices each)."""
    q, v = system.split(x)
    update = system._velocity_update(q, v, u, None)
    residuals = _simulator._step_residuals(update)
    geometry = (update.kinematics, update.inertias, update.distance, update.jacobian)
    reference_q = jax.jacfwd(lambda q_: residuals(system, q_, v, u)[:2])(q)
    reference_v = jax.jacfwd(lambda v_: residuals(system, q, v_, u, geometry)[:2])(v)
    by_q, by_v = _derivatives.configuration_jacobian(system, update, residuals, q, v, u)
    return [*by_q, *by_v], [*reference_q, *reference_v], update.impulse


@pytest.mark.parametrize(
    "case, seed, spread",
    [(_solo_state, 0, 1e-3), (_solo_state, 1, 0.3), (_pusher_state, 2, 1e-2)],
)
def test_closed_form_configuration_derivative_equals_forward_mode(case, seed, spread):
    system, x, u = case(seed, spread)
    assert _derivatives.supported(system)
    ours, reference, impulse = _both(system, x, u)
    assert float(jnp.max(jnp.abs(impulse))) > 0  # some contact carries an impulse
    for index, (a, b) in enumerate(zip(ours, reference)):
        scale = float(jnp.max(jnp.abs(b)))
        assert scale > 0 or index == 3  # the contact velocity does not depend on v
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(scale, 1.0))


def test_unsupported_systems_use_forward_mode():
    assert not _derivatives.supported(sim.pusher())  # finger-box contact
    assert not _derivatives.supported(sim.cube())  # wrench input


# step_and_jacobians itself (through this closed form on Solo-12) against the autodiff reference:
# tests/sim/test_simulator.py::test_implicit_step_derivative_equals_the_autodiff_reference.
