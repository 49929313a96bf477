"""rsmooth: randomized smoothing for optimizing non-smooth physical processes in JAX.

The smoothing core: noise laws (:mod:`rsmooth.noise`), Monte-Carlo gradient estimators
(:func:`zeroth_order`, :func:`first_order`, :func:`alpha_order`), the :func:`smooth`
transform, noise schedules (:mod:`rsmooth.schedules`), perturbed optimizers
(:mod:`rsmooth.perturbed`) and estimator diagnostics (:mod:`rsmooth.stats`); and
:class:`RESULTS`, the outcome codes of the iterative solvers of :mod:`rsmooth.sim` (the
contact solver) and :mod:`rsmooth.control` (DDP, R-DDP, policy optimization).
"""

from rsmooth import diagnostics, noise, perturbed, schedules, stats
from rsmooth._results import RESULTS
from rsmooth.estimators import Estimate, alpha_order, first_order, zeroth_order
from rsmooth.diagnostics import bias_test, estimator_bias_variance, smoothed_landscape
from rsmooth.smooth import smooth, smooth_elementwise

__version__ = "0.1.0"

__all__ = [
    "Estimate",
    "RESULTS",
    "alpha_order",
    "bias_test",
    "diagnostics",
    "estimator_bias_variance",
    "first_order",
    "noise",
    "perturbed",
    "schedules",
    "smooth",
    "smooth_elementwise",
    "smoothed_landscape",
    "stats",
    "zeroth_order",
]
