"""The outcome codes shared by rsmooth's iterative solvers.

The contact solver (:func:`rsmooth.sim.solve_ncp`, through ``NCPInfo.result``), DDP and
R-DDP (:func:`rsmooth.control.ddp`, :func:`rsmooth.control.rddp`, through
``Solution.result``) and policy optimization (:func:`rsmooth.control.optimize_policy`,
through ``PolicySolution.result``) report how a solve ended with one item of
:class:`RESULTS`, in the manner of Optimistix: a JAX value (it passes through `jit` and
`vmap`, batched where the solves are), compared with ``==``, whose message is
``RESULTS[result]`` for a concrete, unbatched item.

Example:
    >>> import jax.numpy as jnp
    >>> from rsmooth import RESULTS
    >>> result = RESULTS.where(jnp.array(False), RESULTS.successful, RESULTS.nonfinite)
    >>> bool(result == RESULTS.nonfinite)
    True
    >>> RESULTS[RESULTS.successful]
    ''
"""

from __future__ import annotations

import equinox as eqx

__all__ = ["RESULTS"]


class RESULTS(eqx.Enumeration):
    """How a solve ended; each item carries its message (empty for ``successful``).

    ``successful``: the solver met its stopping test. ``max_iterations_reached``: it stopped at
    its iteration cap first (the returned value is its best or last iterate, not a
    solution). ``regularization_exceeded``: the regularization that makes a step's linear
    system positive definite reached its cap (DDP's backward pass). ``nonfinite``: a value the
    solver computed is NaN or infinite. ``invalid_input``: an input is outside the solver's
    domain (reported where the solver's traced input checks are left out, as in a rollout).
    """

    successful = ""
    max_iterations_reached = (
        "the solver reached its iteration cap (max_iterations) before meeting its stopping "
        "test; the result is its last or best iterate, not a solution: raise max_iterations "
        "or loosen the tolerance"
    )
    regularization_exceeded = (
        "the regularization reached its cap (reg_max) without making the step's linear system "
        "positive definite; raise reg_max, or check the curvature of the costs"
    )
    nonfinite = (
        "a value the solver computed is not finite (NaN or inf): check the inputs, and the "
        "dynamics and costs at the states the solve reached"
    )
    invalid_input = (
        "an input of the solve is outside its domain (NaN or inf, or a negative friction "
        "coefficient): the result is meaningless"
    )
