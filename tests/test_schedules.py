"""Noise schedules: constant, geometric decay, the adaptive sign rule."""

import jax
import jax.numpy as jnp
import pytest

from rsmooth import schedules


def test_constant_and_geometric():
    state = schedules.Constant().init(0.5, num_samples=4)
    for _ in range(3):
        state = schedules.Constant().update(state)
    assert float(state.sigma) == 0.5 and int(state.step) == 3
    geometric = schedules.Geometric(decay=0.5, floor=0.1, every=2)
    state = geometric.init(1.0)
    sigmas = []
    for _ in range(8):
        state = geometric.update(state)
        sigmas.append(float(state.sigma))
    assert sigmas == [1.0, 0.5, 0.5, 0.25, 0.25, 0.125, 0.125, 0.1]


def test_adaptive_sign_rule():
    schedule = schedules.Adaptive(factor=2.0, momentum=0.5, floor=0.1, sample_growth=2, max_num_samples=8)
    update = jax.jit(schedule.update)
    state = schedule.init(1.0, num_samples=4)
    # d loss / d sigma < 0: more noise would help, keep it.
    for _ in range(5):
        state = update(state, -1.0)
    assert float(state.sigma) == 1.0 and int(state.num_samples) == 4
    # The average turns positive after two positive signals (0.5 * -0.97 + 0.5 * 3 > 0).
    state = update(state, 3.0)
    assert float(state.sigma) == 0.5 and int(state.num_samples) == 8 and float(state.ema) == 0.0
    for _ in range(10):
        state = update(state, 1.0)
    assert float(state.sigma) == pytest.approx(0.1) and int(state.num_samples) == 8


def test_adaptive_patience():
    schedule = schedules.Adaptive(momentum=0.0, patience=3)
    state = schedule.init(1.0)
    for expected in (1.0, 1.0, 0.5, 0.5, 0.5, 0.25):
        state = schedule.update(state, 1.0)
        assert float(state.sigma) == expected


def test_bad_arguments():
    with pytest.raises(ValueError, match="decay"):
        schedules.Geometric(decay=1.5)
    with pytest.raises(ValueError, match="factor"):
        schedules.Adaptive(factor=0.5)
    with pytest.raises(ValueError, match="momentum"):
        schedules.Adaptive(momentum=1.0)
    with pytest.raises(ValueError, match="sigma"):
        schedules.Constant().init(-1.0)
    schedule = schedules.Adaptive()
    with pytest.raises(ValueError, match="signal"):
        schedule.update(schedule.init(1.0), None)
    with pytest.raises(ValueError, match="signal"):
        schedule.update(schedule.init(1.0), jnp.nan)
