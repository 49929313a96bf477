"""Optimal control: shooting problems, DDP / Box-DDP, and randomized DDP (R-DDP).

* :class:`ShootingProblem`: dynamics (any pytree with ``step(x, u)``, ``nx``, ``nu``),
  running and terminal costs, horizon, initial state, optional box limits on the controls.
* :func:`ddp` (configured by :class:`DDP`): DDP / iLQR, Box-DDP with control limits.
* :func:`rddp` (configured by :class:`RDDP`): randomized DDP, whose backward pass uses
  Monte-Carlo derivatives of the smoothed dynamics, with an adaptive noise schedule.

Both return a :class:`Solution`: a :class:`Trajectory` (states, controls, feedback gains),
a :class:`~rsmooth.RESULTS` item (also exported here as ``control.RESULTS``), statistics
(cost, noise, step-size histories, timings) and the final :class:`DDPState`.

Policy optimization (Suh, Simchowitz, Zhang, Tedrake, ICML 2022):

* policies ``u = pi(theta, x, t)``: :class:`OpenLoop` (``u_t = theta_t``),
  :class:`LinearFeedback` (``u = K x + k``, time-invariant or per node), or any callable;
* :func:`rollout` (closed loop, one `lax.scan`) and :func:`policy_cost` (``V(theta)``, the
  total cost of the rollout of a :class:`ShootingProblem`);
* :func:`policy_gradient`: the gradient of the smoothed ``E_w V(theta + sigma w)`` by the
  first-, zeroth- or alpha-order estimator of :mod:`rsmooth.estimators`;
* :func:`optimize_policy` (configured by :class:`PolicyGradient`): Adam on those estimates,
  sigma owned by a :mod:`rsmooth.schedules` schedule; returns a :class:`PolicySolution` with
  the parameter, cost, sigma, alpha and gradient-variance histories and a
  :class:`~rsmooth.RESULTS` item.
"""

from rsmooth._results import RESULTS
from rsmooth.control._ddp import DDP, DDPState, Solution, Trajectory, box_qp, ddp
from rsmooth.control._policy import (
    LinearFeedback,
    OpenLoop,
    PolicyGradient,
    PolicySolution,
    optimize_policy,
    policy_cost,
    policy_gradient,
    rollout,
)
from rsmooth.control._problem import ShootingProblem
from rsmooth.control._rddp import RDDP, rddp, smoothed_dynamics_jacobians

__all__ = [
    "DDP",
    "DDPState",
    "LinearFeedback",
    "OpenLoop",
    "PolicyGradient",
    "PolicySolution",
    "RDDP",
    "RESULTS",
    "ShootingProblem",
    "Solution",
    "Trajectory",
    "box_qp",
    "ddp",
    "optimize_policy",
    "policy_cost",
    "policy_gradient",
    "rddp",
    "rollout",
    "smoothed_dynamics_jacobians",
]
