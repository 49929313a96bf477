"""Compliant contact laws: contact forces from the signed distance and the contact-frame
velocity, with no contact problem to solve.

:class:`SpringDamper` (:func:`spring_damper_force`) is a one-sided penalty spring-damper,
:class:`LogBarrier` (:func:`log_barrier_force`) a log-barrier force acting at a distance; both
add Coulomb friction regularized in the tangential velocity. A law is called as
``law(distance, velocity)`` and returns contact-frame forces ``[f_T1, f_T2, f_N]`` (the
conventions of :mod:`rsmooth.sim._contact`); times the time step, they are the impulses that
replace the NCP's.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from rsmooth import _checks

Array = jax.Array

__all__ = [
    "LogBarrier",
    "SpringDamper",
    "log_barrier_force",
    "spring_damper_force",
]


def _regularized_coulomb(
    normal_force: Array, tangential_velocity: Array, friction: Array, smoothing_velocity
) -> Array:
    """``f_T = -mu f_N v_T / sqrt(||v_T||^2 + v_s^2)``: Coulomb's law, smooth in ``v_T``;
    it reaches ``mu f_N`` (sliding) once ``||v_T|| >> v_s`` and is viscous below."""
    speed = jnp.sqrt(jnp.sum(tangential_velocity**2, axis=-1) + smoothing_velocity**2)
    return -(friction * normal_force / speed)[..., None] * tangential_velocity


def _check_law_parameters(law, positive=(), nonnegative=()) -> None:
    """Named errors for a contact law's concrete parameters out of range (traced ones, e.g. a
    stiffness swept under ``vmap``, are not checked)."""
    for names, test, wanted in ((positive, lambda a: a > 0, "positive"), (nonnegative, lambda a: a >= 0, ">= 0")):
        for name in names:
            value = getattr(law, name)
            if _checks.is_traced(value):
                continue
            array = np.asarray(value, dtype=float)
            if not (np.all(np.isfinite(array)) and np.all(test(array))):
                raise ValueError(f"{type(law).__name__}.{name} must be finite and {wanted}, got {value!r}")


class SpringDamper(eqx.Module):
    """Parameters of the penalty (Kelvin–Voigt) contact model, see
    :func:`spring_damper_force`.

    Attributes:
        stiffness: ``k`` (N/m).
        damping: ``d`` (N s/m).
        friction: Coulomb coefficient ``mu``.
        smoothing_velocity: ``v_s`` (m/s) of the regularized Coulomb law.
    """

    stiffness: ArrayLike
    damping: ArrayLike
    friction: ArrayLike
    smoothing_velocity: ArrayLike = 1e-3

    def __check_init__(self):
        _check_law_parameters(self, positive=("stiffness", "smoothing_velocity"), nonnegative=("damping", "friction"))

    def __call__(self, distance: ArrayLike, velocity: ArrayLike) -> Array:
        return spring_damper_force(distance, velocity, self)


def spring_damper_force(distance: ArrayLike, velocity: ArrayLike, params: SpringDamper) -> Array:
    """Penalty contact force: a one-sided spring-damper and regularized Coulomb friction.

    .. math::
        f_N = \\max(0,\\; k \\max(-\\phi, 0) - d\\, v_N [\\phi < 0]), \\quad
        f_T = -\\mu f_N v_T / \\sqrt{\\|v_T\\|^2 + v_s^2}.

    The clamp keeps the damper from pulling the body back (no sticky contact).

    Args:
        distance: signed distances ``phi``, shape ``(...)``.
        velocity: contact-frame relative velocities ``[t1, t2, n]``, ``(..., 3)``.
        params: a :class:`SpringDamper`.

    Returns:
        Contact-frame forces ``[f_T1, f_T2, f_N]``, shape ``(..., 3)``; multiply by the time
        step for an impulse.

    References:
        Q. Le Lidec, W. Jallet, L. Montaut, I. Laptev, C. Schmid, J. Carpentier, "Contact
        models in robotics: a comparative analysis", IEEE T-RO 2024.
    """
    distance, velocity = jnp.asarray(distance), jnp.asarray(velocity)
    penetration = jnp.maximum(-distance, 0.0)
    in_contact = distance < 0
    normal_force = jnp.maximum(
        params.stiffness * penetration - jnp.where(in_contact, params.damping * velocity[..., 2], 0.0),
        0.0,
    )
    tangential_force = _regularized_coulomb(
        normal_force, velocity[..., :2], params.friction, params.smoothing_velocity
    )
    return jnp.concatenate([tangential_force, normal_force[..., None]], axis=-1)


class LogBarrier(eqx.Module):
    """Parameters of the log-barrier "force at a distance" model, see
    :func:`log_barrier_force`.

    Attributes:
        stiffness: ``kappa`` of the potential ``-kappa log(gap)`` (N m); smaller is stiffer
            contact with a shorter reach.
        min_distance: ``delta > 0`` below which the potential is continued by its
            second-order Taylor expansion (finite, ``C^1`` force through penetration).
        friction: Coulomb coefficient ``mu``.
        smoothing_velocity: ``v_s`` (m/s) of the regularized Coulomb law.
        lookahead: ``h`` (s); the barrier acts on the predicted gap ``phi + h v_N`` (use the
            time step for the quasi-dynamic relaxation of Pang et al.), 0 for the distance.
    """

    stiffness: ArrayLike
    min_distance: ArrayLike = 1e-4
    friction: ArrayLike = 0.0
    smoothing_velocity: ArrayLike = 1e-3
    lookahead: ArrayLike = 0.0

    def __check_init__(self):
        _check_law_parameters(
            self, positive=("stiffness", "min_distance", "smoothing_velocity"), nonnegative=("friction", "lookahead")
        )

    def __call__(self, distance: ArrayLike, velocity: ArrayLike) -> Array:
        return log_barrier_force(distance, velocity, self)


def log_barrier_force(distance: ArrayLike, velocity: ArrayLike, params: LogBarrier) -> Array:
    """Contact force from a log-barrier potential on the gap, smooth in the distance.

    With the gap ``s = phi + h v_N``, the potential ``U(s) = -kappa log s`` gives the
    repulsive normal force ``f_N = -U'(s) = kappa / s``, nonzero at any distance (the
    relaxation that makes contact gradients informative before touching). Below
    ``delta`` the potential is replaced by its quadratic Taylor expansion at ``delta``, so

    .. math::
        f_N = \\kappa / s \\;(s \\ge \\delta), \\qquad
        f_N = (\\kappa / \\delta)(2 - s / \\delta) \\;(s < \\delta),

    which is ``C^1`` in ``s`` and finite through penetration. Friction is the regularized
    Coulomb law on ``f_N``.

    Args:
        distance: signed distances ``phi``, shape ``(...)``.
        velocity: contact-frame relative velocities ``[t1, t2, n]``, ``(..., 3)``.
        params: a :class:`LogBarrier`.

    Returns:
        Contact-frame forces ``[f_T1, f_T2, f_N]``, shape ``(..., 3)``; multiply by the time
        step for an impulse.

    References:
        T. Pang, H. J. T. Suh, L. Yang, R. Tedrake, "Global planning for contact-rich
        manipulation via local smoothing of quasi-dynamic contact models", IEEE T-RO 2023.
        Q. Le Lidec, W. Jallet, L. Montaut, I. Laptev, C. Schmid, J. Carpentier, "Contact
        models in robotics: a comparative analysis", IEEE T-RO 2024.
    """
    distance, velocity = jnp.asarray(distance), jnp.asarray(velocity)
    gap = distance + params.lookahead * velocity[..., 2]
    min_distance = params.min_distance
    far = gap >= min_distance
    barrier = params.stiffness / jnp.where(far, gap, min_distance)
    taylor = (params.stiffness / min_distance) * (2.0 - gap / min_distance)
    normal_force = jnp.where(far, barrier, taylor)
    tangential_force = _regularized_coulomb(
        normal_force, velocity[..., :2], params.friction, params.smoothing_velocity
    )
    return jnp.concatenate([tangential_force, normal_force[..., None]], axis=-1)
