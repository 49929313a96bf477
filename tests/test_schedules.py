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


def _descend(schedule, key, steps=300):
    """Gradient descent on f(x) = min(1, (x - 3)^2) from x = 0 with zeroth-order smoothed
    gradients: a plateau at loss 1 around the start, the minimum 3 away."""
    import rsmooth

    f = lambda x: jnp.minimum(1.0, (x[0] - 3.0) ** 2)  # noqa: E731

    def step(carry, key):
        x, state = carry
        estimate = rsmooth.zeroth_order(f, key, x, sigma=state.sigma, num_samples=64)
        x = x - 0.1 * estimate.grad
        return (x, schedule.update(state, estimate.sigma_grad, loss=f(x))), state.sigma

    (x, state), sigmas = jax.jit(lambda k: jax.lax.scan(step, (jnp.zeros(1), schedule.init(0.1, 64)), jax.random.split(k, steps)))(key)
    return float(f(x)), sigmas


def test_reheating_leaves_a_plateau_that_stops_the_decrease_only_rule(getkey):
    """From x = 0 no sample at sigma = 0.1 reaches the well (2 < x < 4): every estimate is
    exactly zero, the sign rule keeps sigma and x never moves. Reheating doubles sigma at each
    stall until samples reach the well, descends, then shrinks sigma again as the smoothed
    minimum turns d loss / d sigma positive."""
    key = getkey()
    loss, sigmas = _descend(schedules.Adaptive(momentum=0.5), key)
    assert loss == 1.0 and float(sigmas.max()) == pytest.approx(0.1)
    loss, sigmas = _descend(schedules.Reheating(momentum=0.5, stall_patience=5), key)
    assert loss < 1e-2
    assert float(sigmas.max()) > 0.4 and float(sigmas[-1]) < float(sigmas.max()) / 2


def test_reheating_rules():
    schedule = schedules.Reheating(factor=2.0, growth=4.0, momentum=0.0, stall_patience=2, ceiling=2.0)
    state = schedule.init(1.0)
    state = schedule.update(state, -1.0, loss=5.0)  # first loss: an improvement on inf
    assert float(state.best) == 5.0 and int(state.stalled) == 0 and float(state.sigma) == 1.0
    state = schedule.update(state, -1.0, loss=5.0)
    state = schedule.update(state, -1.0, loss=4.999)  # within the tolerance: no improvement
    assert float(state.sigma) == 2.0 and int(state.stalled) == 0  # grown, capped by the ceiling
    for _ in range(3):
        state = schedule.update(state, -1.0, loss=5.0)
    assert float(state.sigma) == 2.0  # at the ceiling
    state = schedule.update(state, 1.0, loss=5.0)  # a positive signal still shrinks sigma
    assert float(state.sigma) == 1.0
    with pytest.raises(ValueError, match="loss"):
        schedule.update(state, 1.0)
    with pytest.raises(ValueError, match="growth"):
        schedules.Reheating(growth=1.0)
    with pytest.raises(ValueError, match="stall_patience"):
        schedules.Reheating(stall_patience=0)
