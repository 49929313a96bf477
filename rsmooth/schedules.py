r"""Noise schedules: who owns the noise level `sigma` (and the sample count) during optimization.

A schedule is a frozen configuration with two pure functions, in the optax style:
``state = schedule.init(sigma, num_samples)`` and ``state = schedule.update(state, signal)``.
The state holds ``sigma`` (a float array), ``num_samples`` (an int array: read it with
``int(state.num_samples)`` outside `jit`, since a new sample count changes array shapes),
``step`` and ``ema``.

* :class:`Constant` keeps sigma.
* :class:`Geometric` multiplies sigma by `decay` every `every` steps, down to `floor`.
* :class:`Adaptive` is the sign rule of Le Lidec, Laptev, Schmid, Carpentier, "Differentiable
  rendering with perturbed optimizers", NeurIPS 2021 (Sec. 3.3): it keeps an exponential
  moving average of :math:`\partial L / \partial\sigma`; when the average is positive (more
  noise would increase the loss: the smoothing now hurts more than it helps), sigma is divided
  by `factor` (down to `floor`), the average restarts, and the sample count is multiplied by
  `sample_growth` (up to `max_num_samples`).

Example:
    >>> from rsmooth.schedules import Adaptive
    >>> schedule = Adaptive(factor=2.0, momentum=0.0)
    >>> state = schedule.init(1.0, num_samples=8)
    >>> state = schedule.update(state, 0.3)   # d loss / d sigma > 0: reduce the noise
    >>> float(state.sigma), int(state.num_samples)
    (0.5, 8)
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from rsmooth import _checks

__all__ = ["ScheduleState", "Schedule", "Constant", "Geometric", "Adaptive"]


class ScheduleState(eqx.Module):
    sigma: Array
    num_samples: Array
    step: Array
    ema: Array


class Schedule(eqx.Module):
    def init(self, sigma: ArrayLike, num_samples: int = 1) -> ScheduleState:
        """The state at the start: the initial noise level and sample count."""
        sigma = _checks.check_positive_scalar(sigma, "sigma")
        num_samples = _checks.check_num_samples(num_samples)
        return ScheduleState(
            sigma=sigma,
            num_samples=jnp.asarray(num_samples, dtype=jnp.int32),
            step=jnp.zeros((), jnp.int32),
            ema=jnp.zeros((), sigma.dtype),
        )

    def update(self, state: ScheduleState, signal: ArrayLike | None = None) -> ScheduleState:
        raise NotImplementedError


class Constant(Schedule):
    """sigma stays what `init` set."""

    def update(self, state, signal=None):
        return ScheduleState(state.sigma, state.num_samples, state.step + 1, state.ema)


class Geometric(Schedule):
    """sigma <- max(decay * sigma, floor) every `every` updates.

    Args:
        decay: factor in (0, 1].
        floor: the smallest sigma, >= 0.
        every: number of updates between two decays.
    """

    decay: float = 0.95
    floor: float = 0.0
    every: int = 1

    def __check_init__(self):
        if not 0.0 < self.decay <= 1.0:
            raise ValueError(f"decay must be in (0, 1], got {self.decay}")
        if self.floor < 0:
            raise ValueError(f"floor must be >= 0, got {self.floor}")
        _checks.check_num_samples(self.every, "every")

    def update(self, state, signal=None):
        step = state.step + 1
        decayed = jnp.maximum(state.sigma * self.decay, self.floor)
        sigma = jnp.where(step % self.every == 0, decayed, state.sigma)
        return ScheduleState(sigma, state.num_samples, step, state.ema)


class Adaptive(Schedule):
    """The adaptive sign rule of Le Lidec et al. (NeurIPS 2021).

    `update(state, signal)` takes `signal` = d loss / d sigma at the current iterate (the
    smoothed losses of :func:`rsmooth.smooth` and the estimators give it).

    Args:
        factor: sigma is divided by this (> 1) when the averaged signal is positive.
        momentum: EMA coefficient in [0, 1): ema <- momentum * ema + (1 - momentum) * signal.
        floor: the smallest sigma, >= 0.
        sample_growth: the sample count is multiplied by this (>= 1) at each reduction.
        max_num_samples: cap on the sample count.
        patience: least number of updates between two reductions (lets the average settle).
    """

    factor: float = 2.0
    momentum: float = 0.9
    floor: float = 1e-4
    sample_growth: int = 1
    max_num_samples: int = 1024
    patience: int = 1

    def __check_init__(self):
        if not self.factor > 1.0:
            raise ValueError(f"factor must be > 1, got {self.factor}")
        if not 0.0 <= self.momentum < 1.0:
            raise ValueError(f"momentum must be in [0, 1), got {self.momentum}")
        if self.floor < 0:
            raise ValueError(f"floor must be >= 0, got {self.floor}")
        _checks.check_num_samples(self.sample_growth, "sample_growth")
        _checks.check_num_samples(self.max_num_samples, "max_num_samples")
        _checks.check_num_samples(self.patience, "patience")

    def update(self, state, signal=None):
        if signal is None:
            raise ValueError("Adaptive.update needs signal = d loss / d sigma")
        signal = _checks.check_finite(jnp.asarray(signal, state.ema.dtype), "signal (d loss / d sigma) must be finite")
        if signal.ndim != 0:
            raise ValueError(f"signal must be a scalar, got shape {signal.shape}")
        ema = self.momentum * state.ema + (1.0 - self.momentum) * signal
        step = state.step + 1
        reduce = (ema > 0) & (step >= self.patience) & (state.sigma > self.floor)
        sigma = jnp.where(reduce, jnp.maximum(state.sigma / self.factor, self.floor), state.sigma)
        grown = jnp.minimum(state.num_samples * self.sample_growth, self.max_num_samples)
        num_samples = jnp.where(reduce, grown, state.num_samples)
        # After a reduction the average restarts, and so does the patience count.
        return ScheduleState(
            sigma=sigma,
            num_samples=num_samples.astype(state.num_samples.dtype),
            step=jnp.where(reduce, 0, step),
            ema=jnp.where(reduce, 0.0, ema),
        )
