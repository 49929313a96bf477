"""Contact kinematics and position correction: where the contacts are, and the distance term
of the velocity the contact solve takes.

- Detection of spheres (a point is a sphere of radius 0) against half-spaces:
  :func:`sphere_halfspace_contacts` gives signed distances, contact points and contact
  frames (:func:`contact_frame`).
- Position correction: :func:`corrected_free_velocity` adds the signed distance to the normal
  free velocity (speculative contact within a skin, Baumgarte below it), giving the ``g`` of
  the contact NCP (:mod:`rsmooth.sim._ncp`).

Conventions of the contact stages (this module, :mod:`rsmooth.sim._ncp` and
:mod:`rsmooth.sim._laws`):

- A contact frame is a rotation matrix ``R = [t1 t2 n]`` (columns in world coordinates):
  two tangents then the normal, with ``t1 x t2 = n``. A world vector ``v`` has
  contact coordinates ``R.T @ v = (v.t1, v.t2, v.n)``.
- Per-contact impulses and velocities are ordered ``[tangent1, tangent2, normal]``
  (the order Pinocchio's ``CoulombFrictionCone`` uses), flattened to ``3 n`` for ``n``
  contacts.
- The normal points out of the obstacle into the free space, so a positive normal
  velocity separates and a positive normal impulse pushes the body away.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from rsmooth import _checks
from rsmooth._unrolled import sum_last

Array = jax.Array

__all__ = [
    "ContactPoints",
    "contact_frame",
    "corrected_free_velocity",
    "sphere_halfspace_contacts",
]


# --------------------------------------------------------------------------------------
# Host-side checks (before tracing) and traced checks (rsmooth._checks.error_if).
# --------------------------------------------------------------------------------------


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_finite(name: str, x: Array) -> Array:
    """Raises ValueError on the host for concrete values, or an equinox error if traced."""
    if _is_concrete(x):
        if not np.all(np.isfinite(np.asarray(x))):
            raise ValueError(f"{name} contains NaN or infinite values.")
        return x
    return _checks.error_if(x, ~jnp.all(jnp.isfinite(x)), f"{name} contains NaN or infinite values.")


def _check_nonnegative(name: str, x: Array) -> Array:
    if _is_concrete(x):
        if np.any(np.asarray(x) < 0):
            raise ValueError(f"{name} must be non-negative, got {np.asarray(x)}.")
        return x
    return _checks.error_if(x, jnp.any(x < 0), f"{name} must be non-negative.")


def _safe_norm(x: Array) -> Array:
    """Euclidean norm over the last axis whose derivative at 0 is 0 instead of NaN."""
    squared = sum_last(x * x)  # unrolled: see rsmooth._unrolled
    nonzero = squared > 0
    return jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, squared, 1.0)), 0.0)


# --------------------------------------------------------------------------------------
# Detection: spheres against half-spaces.
# --------------------------------------------------------------------------------------


def contact_frame(normal: ArrayLike) -> Array:
    """Right-handed orthonormal frame ``[t1 t2 n]`` whose third column is ``normal``.

    Branch-free construction of Duff et al.: the tangents are smooth in ``normal`` except
    across the plane ``n_z = 0`` where the sign switch happens. For ``n = e_z`` the frame is
    the identity, so a floor contact has world-aligned tangents.

    Args:
        normal: unit vectors, shape ``(..., 3)``.

    Returns:
        Rotation matrices of shape ``(..., 3, 3)`` with columns ``(t1, t2, n)`` in world
        coordinates, ``det = +1``.

    References:
        T. Duff, J. Burgess, P. Christensen, C. Hery, A. Kensler, M. Liani, R. Villemin,
        "Building an orthonormal basis, revisited", JCGT 6(1), 2017 (Listing 3).
    """
    normal = jnp.asarray(normal)
    nx, ny, nz = normal[..., 0], normal[..., 1], normal[..., 2]
    sign = jnp.where(nz >= 0, 1.0, -1.0)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    tangent1 = jnp.stack([1.0 + sign * nx * nx * a, sign * b, -sign * nx], axis=-1)
    tangent2 = jnp.stack([b, sign + ny * ny * a, -ny], axis=-1)
    return jnp.stack([tangent1, tangent2, normal], axis=-1)


class ContactPoints(eqx.Module):
    """Candidate contacts between every sphere and every half-space.

    Attributes:
        distance: signed distance, shape ``(S, P)``; negative means penetration.
        point: contact point on the sphere, the sphere point deepest towards the plane,
            ``center - radius * n``, shape ``(S, P, 3)``. It moves with the sphere, so the
            contact velocity is the sphere body's velocity at this point; the matching
            point on the plane is ``point - distance * n``.
        frame: contact frames ``[t1 t2 n]`` (see :func:`contact_frame`), ``(S, P, 3, 3)``.
    """

    distance: Array
    point: Array
    frame: Array


def sphere_halfspace_contacts(
    centers: ArrayLike, radii: ArrayLike, normals: ArrayLike, offsets: ArrayLike
) -> ContactPoints:
    """Signed distances, points and frames of ``S`` spheres against ``P`` half-spaces.

    The half-space ``{p : n . p >= offset}`` is the free space; the plane is its boundary.
    The signed distance of a sphere is ``n . c - offset - r``.

    Args:
        centers: sphere centers, shape ``(S, 3)``.
        radii: sphere radii, shape ``(S,)``, ``>= 0`` (``0`` is a point).
        normals: unit normals of the half-spaces pointing into the free space, ``(P, 3)``.
        offsets: plane offsets, shape ``(P,)``.

    Returns:
        A :class:`ContactPoints` with arrays of leading shape ``(S, P)``. Every pair is
        returned (branch-free); select active contacts with ``distance``.

    Example:
        >>> import jax.numpy as jnp
        >>> c = sphere_halfspace_contacts(jnp.array([[0.0, 0.0, 0.1]]), jnp.array([0.02]),
        ...                               jnp.array([[0.0, 0.0, 1.0]]), jnp.array([0.0]))
        >>> round(float(c.distance[0, 0]), 6)
        0.08
    """
    centers, radii = jnp.asarray(centers), jnp.asarray(radii)
    normals, offsets = jnp.asarray(normals), jnp.asarray(offsets)
    if centers.ndim != 2 or centers.shape[1] != 3:
        raise ValueError(f"centers must have shape (S, 3), got {centers.shape}.")
    if radii.shape != centers.shape[:1]:
        raise ValueError(f"radii must have shape ({centers.shape[0]},), got {radii.shape}.")
    if normals.ndim != 2 or normals.shape[1] != 3:
        raise ValueError(f"normals must have shape (P, 3), got {normals.shape}.")
    if offsets.shape != normals.shape[:1]:
        raise ValueError(f"offsets must have shape ({normals.shape[0]},), got {offsets.shape}.")
    radii = _check_nonnegative("radii", radii)
    if _is_concrete(normals):
        lengths = np.linalg.norm(np.asarray(normals), axis=-1)
        if not np.allclose(lengths, 1.0, atol=1e-6):
            raise ValueError(f"normals must be unit vectors, got lengths {lengths}.")

    distance = centers @ normals.T - offsets[None, :] - radii[:, None]
    point = centers[:, None, :] - radii[:, None, None] * normals[None, :, :]
    frame = jnp.broadcast_to(contact_frame(normals)[None], distance.shape + (3, 3))
    return ContactPoints(distance=distance, point=point, frame=frame)


# --------------------------------------------------------------------------------------
# Position correction: the signed distance in the normal free velocity.
# --------------------------------------------------------------------------------------


# The contact skin of corrected_free_velocity (m): resting distances are rounding-sized, 1e-12
# to 1e-8 m; a gap of a micrometre is nothing to the motion.
CONTACT_SKIN = 1e-6


def corrected_free_velocity(
    free_velocity: ArrayLike,
    distance: ArrayLike,
    time_step: ArrayLike,
    *,
    baumgarte=0.2,
    skin=CONTACT_SKIN,
    max_correction_speed=float("inf"),
) -> Array:
    """Adds the position term to the normal free velocity, ``g_N + phi / h``-style.

    The NCP constrains the normal velocity ``c_N >= 0``. Replacing ``c_N`` by ``c_N + r(phi)
    / h`` with ``r(phi) = beta phi`` for ``phi <= s`` and ``r(phi) = phi - (1 - beta) s``
    beyond (``s`` the contact skin) makes a contact detected at a distance act only if the
    gap would close within the step, to within the skin (speculative contact: no force at a
    distance beyond it), and pushes a penetration out at the Baumgarte rate ``beta / h``
    (``beta = 1`` removes it in one step, which injects energy; smaller values spread it),
    at most at ``max_correction_speed``: ``beta phi / h`` grows without bound as ``h``
    shrinks or the penetration deepens (a body or a joint limit starting well inside),
    and the speed it gives is kinetic energy the correction injects.

    Why a skin: resting contacts sit at distances of rounding size on both sides of zero (a
    box on four corners tilted by 1e-9 rad). With the rate ``1 / h`` above zero and
    ``beta / h`` below, their targets are not those of one rigid motion: the sticking
    equations have no solution and the solver stalls at its iteration cap. Within the skin
    the correction is linear, so they do; ``r`` is continuous and its derivative at
    ``phi = 0`` is ``beta / h`` from both sides.

    Args:
        free_velocity: contact-frame free velocities, flat ``(3 n,)`` ordered
            ``[t1, t2, n]`` per contact.
        distance: signed distances, shape ``(n,)``.
        time_step: the step ``h > 0``.
        baumgarte: ``beta`` in ``[0, 1]``.
        skin: ``s >= 0`` (m, or rad for a joint limit); far below any gap that matters to
            the motion (a contact stops approaching at ``(1 - beta) s``, then closes the rest
            at the Baumgarte rate), far above the rounding of resting distances.
        max_correction_speed: the largest speed (m/s, or rad/s for a joint limit) at which a
            penetration is pushed out, ``> 0``; ``inf``: no bound.

    Returns:
        The corrected free velocity ``g``, shape ``(3 n,)``, to pass to :func:`solve_ncp`.

    References:
        J. Baumgarte, "Stabilization of constraints and integrals of motion in dynamical
        systems", Computer Methods in Applied Mechanics and Engineering 1(1), 1972.
    """
    free_velocity, distance = jnp.asarray(free_velocity), jnp.asarray(distance)
    if free_velocity.shape != (3 * distance.shape[0],) or distance.ndim != 1:
        raise ValueError(
            f"free_velocity must have shape (3 n,) and distance (n,), got "
            f"{free_velocity.shape} and {distance.shape}."
        )
    correction = jnp.where(distance > skin, distance - (1.0 - baumgarte) * skin, baumgarte * distance) / time_step
    if max_correction_speed != float("inf"):  # (static: no operation without a bound)
        correction = jnp.maximum(correction, -max_correction_speed)
    return free_velocity.reshape(-1, 3).at[:, 2].add(correction).reshape(-1)
