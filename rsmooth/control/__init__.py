"""Optimal control: shooting problems, DDP / Box-DDP, and randomized DDP (R-DDP).

* :class:`ShootingProblem`: dynamics (any pytree with ``step(x, u)``, ``nx``, ``nu``),
  running and terminal costs, horizon, initial state, optional box limits on the controls.
* :func:`ddp` (configured by :class:`DDP`): DDP / iLQR, Box-DDP with control limits.
* :func:`rddp` (configured by :class:`RDDP`): randomized DDP, whose backward pass uses
  Monte-Carlo derivatives of the smoothed dynamics, with an adaptive noise schedule.

Both return a :class:`Solution`: a :class:`Trajectory` (states, controls, feedback gains),
a :class:`RESULTS` item, statistics (cost, noise, step-size histories, timings) and the final
:class:`DDPState`.
"""

from rsmooth.control._ddp import DDP, RESULTS, DDPState, Solution, Trajectory, box_qp, ddp
from rsmooth.control._problem import ShootingProblem
from rsmooth.control._rddp import RDDP, rddp, smoothed_dynamics_jacobians

__all__ = [
    "DDP",
    "DDPState",
    "RDDP",
    "RESULTS",
    "ShootingProblem",
    "Solution",
    "Trajectory",
    "box_qp",
    "ddp",
    "rddp",
    "smoothed_dynamics_jacobians",
]
