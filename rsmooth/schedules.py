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
* :class:`Reheating` is that sign rule in both directions: it also *raises* sigma when the
  optimization is stuck, i.e. when the loss has not improved for `stall_patience` updates
  while the averaged :math:`\partial L_\sigma / \partial\sigma` is not positive.

Why the sign of :math:`\partial L_\sigma / \partial\sigma` separates "converged" from
"stuck": near a minimum of a convex loss, Jensen's inequality gives
:math:`L_\sigma(x) = \mathbb{E}\,L(x + \sigma z) \geq L(x)`, growing with sigma, so the
signal is positive and the rule refines (smaller sigma). On a plateau (the null gradients of
a contact not yet made, an object outside every sampled pixel) the signal is about zero; on
a slope the optimizer cannot follow at this noise level (lower loss lies further than the
samples reach) it is negative. Neither resolves by itself, and a decrease-only schedule
makes both worse: a larger sigma lets the samples reach the lower loss.

Every schedule's state also tracks the best loss seen (``best``) and the number of updates
since it last improved (``stalled``); only :class:`Reheating` needs the ``loss``.

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

__all__ = ["ScheduleState", "Schedule", "Constant", "Geometric", "Adaptive", "Reheating"]


class ScheduleState(eqx.Module):
    """A schedule's state.

    Attributes:
        sigma: the noise level.
        num_samples: the sample count (int32).
        step: updates since the start or the last change of sigma by an adaptive rule.
        ema: the moving average of the signal (adaptive rules).
        best: the lowest loss passed to `update` (``inf`` when none was).
        stalled: updates since ``best`` last improved (or since the last change of sigma).
    """

    sigma: Array
    num_samples: Array
    step: Array
    ema: Array
    best: Array
    stalled: Array


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
            best=jnp.asarray(jnp.inf, sigma.dtype),
            stalled=jnp.zeros((), jnp.int32),
        )

    def update(self, state: ScheduleState, signal: ArrayLike | None = None, loss: ArrayLike | None = None) -> ScheduleState:
        """The state after one optimizer step.

        Args:
            state: the current state.
            signal: d loss / d sigma at the current iterate (adaptive rules).
            loss: the loss at the current iterate (:class:`Reheating`; the others only record
                it in ``best`` and ``stalled``).
        """
        raise NotImplementedError


def _progress(state: ScheduleState, loss, tolerance: float = 0.0) -> tuple[Array, Array]:
    """``(best, stalled)`` after seeing ``loss``: an improvement is a loss below ``best`` by
    more than ``tolerance`` times ``|best|``."""
    if loss is None:
        return state.best, state.stalled + 1
    loss = jnp.asarray(loss, state.best.dtype)
    if loss.ndim != 0:
        raise ValueError(f"loss must be a scalar, got shape {loss.shape}")
    margin = tolerance * jnp.where(jnp.isfinite(state.best), jnp.abs(state.best), 0.0)
    improved = jnp.isfinite(loss) & (loss < state.best - margin)
    return jnp.where(improved, loss, state.best), jnp.where(improved, 0, state.stalled + 1)


class Constant(Schedule):
    """sigma stays what `init` set."""

    def update(self, state, signal=None, loss=None):
        best, stalled = _progress(state, loss)
        return ScheduleState(state.sigma, state.num_samples, state.step + 1, state.ema, best, stalled)


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

    def update(self, state, signal=None, loss=None):
        step = state.step + 1
        decayed = jnp.maximum(state.sigma * self.decay, self.floor)
        sigma = jnp.where(step % self.every == 0, decayed, state.sigma)
        best, stalled = _progress(state, loss)
        return ScheduleState(sigma, state.num_samples, step, state.ema, best, stalled)


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

    def _average(self, state, signal) -> Array:
        if signal is None:
            raise ValueError(f"{type(self).__name__}.update needs signal = d loss / d sigma")
        signal = _checks.check_finite(jnp.asarray(signal, state.ema.dtype), "signal (d loss / d sigma) must be finite")
        if signal.ndim != 0:
            raise ValueError(f"signal must be a scalar, got shape {signal.shape}")
        return self.momentum * state.ema + (1.0 - self.momentum) * signal

    def update(self, state, signal=None, loss=None):
        ema = self._average(state, signal)
        step = state.step + 1
        best, stalled = _progress(state, loss, self._stall_tolerance())
        reduce = (ema > 0) & (step >= self.patience) & (state.sigma > self.floor)
        grow = self._grow(state, reduce, ema, stalled)
        sigma = jnp.where(reduce, jnp.maximum(state.sigma / self.factor, self.floor), state.sigma)
        sigma = jnp.where(grow, self._grown_sigma(state.sigma), sigma)
        grown = jnp.minimum(state.num_samples * self.sample_growth, self.max_num_samples)
        num_samples = jnp.where(reduce, grown, state.num_samples)
        changed = reduce | grow
        # A new sigma is a new smoothed problem: the average, the patience and the stall count
        # restart (the best loss is kept: progress is judged on one scale throughout).
        return ScheduleState(
            sigma=sigma,
            num_samples=num_samples.astype(state.num_samples.dtype),
            step=jnp.where(changed, 0, step),
            ema=jnp.where(changed, 0.0, ema),
            best=best,
            stalled=jnp.where(changed, 0, stalled),
        )

    # The sign rule only decreases sigma; Reheating overrides these three.
    def _stall_tolerance(self) -> float:
        return 0.0

    def _grow(self, state, reduce, ema, stalled) -> Array:
        return jnp.zeros((), bool)

    def _grown_sigma(self, sigma) -> Array:
        return sigma


class Reheating(Adaptive):
    """The adaptive sign rule in both directions: sigma shrinks when the averaged
    d loss / d sigma is positive (as :class:`Adaptive`) and grows when the optimization is
    stuck: no improvement of the loss for ``stall_patience`` updates while the average is not
    positive (the module docstring says why the sign tells the two apart).

    `update(state, signal, loss)` takes ``signal`` = d loss / d sigma and ``loss``, the loss at
    the current iterate (the value the optimizer is judged by: a true cost, or the smoothed
    estimate when that is all there is).

    Args:
        factor, momentum, floor, sample_growth, max_num_samples, patience: as :class:`Adaptive`.
        growth: sigma is multiplied by this (> 1) when stuck, up to ``ceiling``.
        ceiling: the largest sigma (> 0; ``inf``: none).
        stall_patience: updates without improvement that make a stall (>= 1).
        stall_tolerance: an improvement is a decrease of the best loss by more than this
            share of it (>= 0): Monte-Carlo losses fluctuate.

    Example:
        >>> from rsmooth.schedules import Reheating
        >>> schedule = Reheating(growth=2.0, momentum=0.0, stall_patience=2)
        >>> state = schedule.init(0.125)
        >>> for _ in range(3):  # a plateau: the loss does not move, d loss / d sigma = 0
        ...     state = schedule.update(state, 0.0, loss=1.0)
        >>> float(state.sigma)
        0.25
    """

    growth: float = 2.0
    ceiling: float = float("inf")
    stall_patience: int = 10
    stall_tolerance: float = 1e-3

    def __check_init__(self):  # equinox runs Adaptive's too
        if not self.growth > 1.0:
            raise ValueError(f"growth must be > 1, got {self.growth}")
        if not self.ceiling > 0:
            raise ValueError(f"ceiling must be > 0, got {self.ceiling}")
        _checks.check_num_samples(self.stall_patience, "stall_patience")
        if not self.stall_tolerance >= 0:
            raise ValueError(f"stall_tolerance must be >= 0, got {self.stall_tolerance}")

    def update(self, state, signal=None, loss=None):
        if loss is None:
            raise ValueError("Reheating.update needs loss, the loss at the current iterate")
        return super().update(state, signal, loss)

    def _stall_tolerance(self) -> float:
        return self.stall_tolerance

    def _grow(self, state, reduce, ema, stalled) -> Array:
        return ~reduce & (ema <= 0) & (stalled >= self.stall_patience) & (state.sigma < self.ceiling)

    def _grown_sigma(self, sigma) -> Array:
        return jnp.minimum(sigma * self.growth, self.ceiling)
