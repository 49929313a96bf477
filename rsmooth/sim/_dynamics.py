"""Rigid-body kinematics and dynamics of kinematic trees (no contact), in pure JAX.

Each function takes a :class:`~rsmooth.sim.Model` and plain arrays, and follows Pinocchio's
conventions (see ``_spatial.py``): a free-flyer configuration is ``[x, y, z, qx, qy, qz, qw]``
and its velocity ``[linear, angular]`` in the body frame; joint placements are those of
Pinocchio's ``data.oMi``.

Design: the dynamics are written in the world frame (as Pinocchio's own implementation), so
that after the forward kinematics every quantity is one vectorized operation over all bodies
or all degrees of freedom, with the tree structure entering only through static 0/1 masks
(which bodies a dof moves, which bodies a subtree holds). The only sequential part is the
forward kinematics, one step per tree *depth* (4 for Solo-12, whose legs are processed
together). This keeps the traced graph a few hundred operations long whatever the number of
joints, so compiling, ``vmap`` over samples and ``jacfwd`` stay cheap. No Python control flow
depends on traced values.

References:
    R. Featherstone, "Rigid Body Dynamics Algorithms", Springer, 2008.
    J. Carpentier, N. Mansard, "Analytical Derivatives of Rigid Body Dynamics Algorithms",
    RSS, 2018 (world-frame formulation of RNEA and CRBA).
"""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from rsmooth import _linalg as linalg
from rsmooth.sim import _spatial as spatial
from rsmooth.sim._model import FREE_FLYER, JOINT_NV, PRISMATIC, REVOLUTE, SPHERICAL, Model

Reference = Literal["local_world_aligned", "local", "world"]
_REFERENCES = ("local_world_aligned", "local", "world")


# --------------------------------------------------------------------------------------
# Static structure of the tree (numpy, computed once per tree at trace time)
# --------------------------------------------------------------------------------------


class _Tree(NamedTuple):
    """Index arrays and masks derived from a model's static fields."""

    levels: tuple[np.ndarray, ...]  # joints at depth 0 (the universe), 1, 2, ...
    level_parents: tuple[np.ndarray, ...]  # position of each one's parent in the level above
    level_order: np.ndarray  # permutation from the concatenated levels to joint order
    revolute: np.ndarray  # joint indices by type
    prismatic: np.ndarray
    free_flyer: np.ndarray
    spherical: np.ndarray
    assemble: np.ndarray  # permutation: [universe, revolute, prismatic, free flyers, spherical] -> joints
    dof_owner: np.ndarray  # (nv,) joint moved by each dof
    dof_is_revolute: np.ndarray  # (nv, 1) bool
    dof_is_prismatic: np.ndarray  # (nv, 1) bool
    twist_basis: np.ndarray  # (nv, 6) unit twists of free-flyer and spherical dofs, zeros elsewhere
    rotation_q: np.ndarray  # configuration offset of every joint's unit quaternion (free flyer, spherical)
    rotation_v: np.ndarray  # velocity offset of its angular velocity
    support: np.ndarray  # (njoints, nv) bool: dof moves body i (its joint is i or an ancestor)
    subtree: np.ndarray  # (njoints, njoints) float: subtree[j, i] = 1 if body i is j or below j
    dof_ancestor: np.ndarray  # (nv, nv) bool: owner(a) is owner(b) or an ancestor of it
    dof_same_joint: np.ndarray  # (nv, nv) bool
    vector_q: np.ndarray  # configuration coordinates of revolute/prismatic joints
    vector_v: np.ndarray  # their velocity coordinates


@functools.lru_cache(maxsize=64)
def _tree_structure(
    joint_types: tuple[str, ...], parents: tuple[int, ...], idx_q: tuple[int, ...], idx_v: tuple[int, ...]
) -> _Tree:
    njoints = len(joint_types)
    depth = [0] * njoints
    for joint in range(1, njoints):
        depth[joint] = depth[parents[joint]] + 1
    levels = tuple(
        np.array([j for j in range(njoints) if depth[j] == d], dtype=np.int32) for d in range(max(depth) + 1)
    )
    level_parents = [np.zeros(1, dtype=np.int32)]
    for above, level in zip(levels[:-1], levels[1:]):
        position = {int(joint): i for i, joint in enumerate(above)}
        level_parents.append(np.array([position[parents[j]] for j in level], dtype=np.int32))
    by_type = {
        kind: np.array([j for j in range(1, njoints) if joint_types[j] == kind], dtype=np.int32)
        for kind in (REVOLUTE, PRISMATIC, FREE_FLYER, SPHERICAL)
    }
    order = np.concatenate(
        [[0], by_type[REVOLUTE], by_type[PRISMATIC], by_type[FREE_FLYER], by_type[SPHERICAL]]
    ).astype(np.int32)
    nv = sum(JOINT_NV[kind] for kind in joint_types)
    dof_owner = np.zeros(nv, dtype=np.int32)
    twist_basis = np.zeros((nv, 6))
    rotation_q, rotation_v = [], []
    for joint in range(1, njoints):
        dofs = slice(idx_v[joint], idx_v[joint] + JOINT_NV[joint_types[joint]])
        dof_owner[dofs] = joint
        if joint_types[joint] == FREE_FLYER:
            twist_basis[dofs] = np.eye(6)
            rotation_q.append(idx_q[joint] + 3)
            rotation_v.append(idx_v[joint] + 3)
        elif joint_types[joint] == SPHERICAL:
            twist_basis[dofs] = np.eye(6)[3:]  # angular velocity in the joint frame
            rotation_q.append(idx_q[joint])
            rotation_v.append(idx_v[joint])
    ancestor_or_self = np.zeros((njoints, njoints), dtype=bool)  # [a, b]: a is b or above b
    for joint in range(1, njoints):
        ancestor = joint
        while ancestor != 0:
            ancestor_or_self[ancestor, joint] = True
            ancestor = parents[ancestor]
    vector_joints = [j for j in range(1, njoints) if joint_types[j] in (REVOLUTE, PRISMATIC)]
    return _Tree(
        levels=levels,
        level_parents=tuple(level_parents),
        level_order=np.argsort(np.concatenate(levels)).astype(np.int32),
        revolute=by_type[REVOLUTE],
        prismatic=by_type[PRISMATIC],
        free_flyer=by_type[FREE_FLYER],
        spherical=by_type[SPHERICAL],
        assemble=np.argsort(order).astype(np.int32),
        dof_owner=dof_owner,
        dof_is_revolute=np.array([joint_types[j] == REVOLUTE for j in dof_owner])[:, None],
        dof_is_prismatic=np.array([joint_types[j] == PRISMATIC for j in dof_owner])[:, None],
        twist_basis=twist_basis,
        rotation_q=np.asarray(rotation_q, dtype=np.int64),
        rotation_v=np.asarray(rotation_v, dtype=np.int64),
        support=ancestor_or_self[dof_owner, :].T,
        subtree=ancestor_or_self.astype(np.float64),
        dof_ancestor=ancestor_or_self[np.ix_(dof_owner, dof_owner)],
        dof_same_joint=dof_owner[:, None] == dof_owner[None, :],
        vector_q=np.array([idx_q[j] for j in vector_joints], dtype=np.int32),
        vector_v=np.array([idx_v[j] for j in vector_joints], dtype=np.int32),
    )


def _dof_blocks(model: Model) -> tuple | None:
    """The diagonal blocks of the mass matrix: ``((size, starts), ...)`` per block size, the
    blocks being the dofs of each tree hanging from the world (a free object, a robot), or
    ``None`` for a single tree. ``M`` couples no two trees (CRBA: ``M_ij`` is zero unless one
    dof's body is an ancestor of the other's), and a tree's dofs are a contiguous range."""
    tree = _tree(model)
    roots = [joint for joint in range(1, len(model.parents)) if model.parents[joint] == 0]
    if len(roots) < 2:
        return None
    by_size: dict[int, list[int]] = {}
    for root in roots:
        dofs = np.flatnonzero(tree.subtree[root, tree.dof_owner])  # the dofs of the root's subtree
        if not np.array_equal(dofs, np.arange(dofs[0], dofs[0] + dofs.size)):
            return None  # a tree's dofs not contiguous: no blocks (the dense factorization)
        by_size.setdefault(int(dofs.size), []).append(int(dofs[0]))
    return tuple((size, np.asarray(sorted(starts), np.int64)) for size, starts in sorted(by_size.items()))


def _blocks_of(matrix: jax.Array, size: int, starts: np.ndarray) -> jax.Array:
    """The diagonal blocks ``(k, size, size)`` of ``matrix`` at ``starts``, by static slices:
    XLA's gathers and scatters with index arrays run element by element on a CPU (a tower of
    16 boxes' free motion took five times as long through them). A slice per tree: the
    program grows by a few small operations per tree."""
    return jnp.stack([matrix[start : start + size, start : start + size] for start in starts.tolist()])


def _in_dof_order(blocks, pieces: list[jax.Array]) -> jax.Array:
    """The rows of each block's ``pieces`` (``(k, size, ...)``, in :func:`_dof_blocks`' order)
    put back in dof order."""
    rows = [(start, piece[i]) for (size, starts), piece in zip(blocks, pieces) for i, start in enumerate(starts.tolist())]
    return jnp.concatenate([row for _, row in sorted(rows, key=lambda item: item[0])])


def mass_cholesky(model: Model, mass: jax.Array) -> jax.Array:
    """The lower Cholesky factor of ``mass`` (``M`` plus a diagonal), block by block where the
    model has several trees (:func:`_dof_blocks`): a scene of many free objects factors their
    ``6 x 6`` blocks, not one ``6 N x 6 N`` matrix (the same factor, to rounding)."""
    blocks = _dof_blocks(model)
    if blocks is None:
        return linalg.cholesky(mass)
    nv = mass.shape[-1]
    pieces = []
    for size, starts in blocks:
        factors = linalg.cholesky(_blocks_of(mass, size, starts))
        # each block's rows of the dense factor: zeros, the block, zeros
        pieces.append(jnp.stack([
            jnp.pad(factors[i], ((0, 0), (start, nv - start - size))) for i, start in enumerate(starts.tolist())
        ]))
    return _in_dof_order(blocks, pieces)


def mass_solve_triangular(model: Model, factor: jax.Array, b: jax.Array, *, trans: bool = False) -> jax.Array:
    """``L^-1 b`` (``L^-T b`` with ``trans``) for the factor of :func:`mass_cholesky` and ``b``
    ``(nv,)`` or ``(nv, k)``, block by block where it has blocks."""
    blocks = _dof_blocks(model)
    if blocks is None:
        return linalg.solve_triangular(factor, b, trans=trans)
    matrix = b if b.ndim == 2 else b[:, None]
    pieces = []
    for size, starts in blocks:
        rhs = jnp.stack([matrix[start : start + size] for start in starts.tolist()])
        factors = _blocks_of(factor, size, starts)
        if matrix.shape[1] <= size:
            pieces.append(linalg.solve_triangular(factors, rhs, trans=trans))
            continue
        # More columns than the block's size (a contact Jacobian's): each block's inverse (a
        # solve with `size` columns), then a batched product. On a CPU rsmooth._linalg hands
        # LAPACK a batch of solves with many columns in small chunks, one after another (L^-1 Jᵀ
        # of a tower of 16 boxes under vmap 64: 616 us per env against 142 by inverses, alone).
        inverse = linalg.solve_triangular(factors, jnp.broadcast_to(jnp.eye(size, dtype=factors.dtype), factors.shape))
        pieces.append((jnp.swapaxes(inverse, -1, -2) if trans else inverse) @ rhs)
    solved = _in_dof_order(blocks, pieces)
    return solved if b.ndim == 2 else solved[:, 0]


def mass_cho_solve(model: Model, factor: jax.Array, b: jax.Array) -> jax.Array:
    """``(L Lᵀ)^-1 b`` for the factor of :func:`mass_cholesky`."""
    return mass_solve_triangular(model, factor, mass_solve_triangular(model, factor, b), trans=True)


def _mask_sum(mask: np.ndarray, values: jax.Array) -> jax.Array:
    """``mask @ values`` for a static 0/1 ``mask`` and values ``(n, 6)``, computed as
    ``(values.T @ mask.T).T``: under ``vmap``/``jacfwd`` the batched operand is then the
    GEMM's row-major left factor, so XLA on CPU need not move the contracted axis to the
    front of the whole batch (a strided copy that took most of the batched step Jacobian)."""
    return (values.T @ jnp.asarray(mask.T, values.dtype)).T


def _tree(model: Model) -> _Tree:
    return _tree_structure(model.joint_types, model.parents, model.idx_q, model.idx_v)


def _support_columns(model: Model, kinematics, joints) -> jax.Array:
    """World-frame motion subspace columns of the dofs that move body ``joints`` (an int, or an
    integer array of any shape ``B``, static or traced), ``B + (nv, 6)``: zero for the other
    dofs. ``kinematics``: anything with the ``motion_subspace`` ``(nv, 6)`` at the configuration."""
    support = _tree(model).support
    moves = support[joints] if isinstance(joints, (int, np.integer, np.ndarray)) else jnp.asarray(support)[joints]
    moves = moves[..., None]  # B + (nv, 1)
    subspace = kinematics.motion_subspace
    return jnp.where(moves, subspace.reshape((1,) * (moves.ndim - 2) + subspace.shape), 0.0)


def _point_velocity_columns(model: Model, kinematics, joints, points: jax.Array) -> jax.Array:
    """``(..., nv, 3)``: row ``k`` is the world velocity of the material point of body
    ``joints`` at world position ``points`` ``(..., 3)`` per unit velocity of dof ``k``;
    ``joints`` (as :func:`_support_columns`) broadcasts against the leading axes of ``points``
    (all contacts of a step in one batched expression: see ``RigidBodySystem.contacts``)."""
    columns = _support_columns(model, kinematics, joints)
    return columns[..., :3] - jnp.cross(points[..., None, :], columns[..., 3:])


def _take(values: jax.Array, indices: np.ndarray) -> jax.Array:
    """``values[indices]`` for static indices, as a slice when they are a contiguous range."""
    if len(indices) and np.array_equal(indices, np.arange(indices[0], indices[0] + len(indices))):
        return values[int(indices[0]) : int(indices[0]) + len(indices)]
    return values[indices]


# --------------------------------------------------------------------------------------
# Boundary checks (host side, on static shapes)
# --------------------------------------------------------------------------------------


def _check_vector(name: str, value: ArrayLike, size: int) -> jax.Array:
    value = jnp.asarray(value)
    if value.shape != (size,):
        raise ValueError(f"{name} must have shape ({size},), got {value.shape}")
    return value


def _gravity(model: Model, gravity: ArrayLike | None) -> jax.Array:
    if gravity is None:
        return model.gravity
    return _check_vector("gravity", gravity, 3)


# --------------------------------------------------------------------------------------
# Kinematics shared by all algorithms
# --------------------------------------------------------------------------------------

_compose = jax.vmap(spatial.compose)
_transform_motions = jax.vmap(spatial.transform_motion)
_transform_inertias = jax.vmap(spatial.transform_inertia)
_inertia_apply = jax.vmap(spatial.inertia_apply)
_motion_cross_motion = jax.vmap(spatial.motion_cross_motion)
_motion_cross_force = jax.vmap(spatial.motion_cross_force)


def _local_placements(model: Model, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Placements ``parent_M_joint(q)`` of all joints, shapes ``(njoints, 3, 3)``, ``(njoints, 3)``.

    Each is the fixed joint placement times the joint motion ``X_J(q)``; the joint motions are
    computed per joint type, each type in one vectorized operation.
    """
    tree = _tree(model)
    dtype = model.joint_placement_translation.dtype
    axes = model.joint_axes
    revolute_angles = q[np.asarray(model.idx_q)[tree.revolute]]
    prismatic_offsets = q[np.asarray(model.idx_q)[tree.prismatic]]
    free_flyer_q = q[np.asarray(model.idx_q)[tree.free_flyer][:, None] + np.arange(7)]
    spherical_q = q[np.asarray(model.idx_q)[tree.spherical][:, None] + np.arange(4)]
    identity = jnp.eye(3, dtype=dtype)
    rotations = [
        identity[None],
        jax.vmap(spatial.rotation_about_axis)(axes[tree.revolute], revolute_angles),
        jnp.broadcast_to(identity, (len(tree.prismatic), 3, 3)),
        jax.vmap(spatial.quaternion_to_rotation)(free_flyer_q[:, 3:]),
        jax.vmap(spatial.quaternion_to_rotation)(spherical_q),
    ]
    translations = [
        jnp.zeros((1 + len(tree.revolute), 3), dtype=dtype),
        axes[tree.prismatic] * prismatic_offsets[:, None],
        free_flyer_q[:, :3],
        jnp.zeros((len(tree.spherical), 3), dtype=dtype),
    ]
    joint_rotation = jnp.concatenate(rotations)[tree.assemble]
    joint_translation = jnp.concatenate(translations)[tree.assemble]
    return _compose(
        model.joint_placement_rotation, model.joint_placement_translation, joint_rotation, joint_translation
    )


def _world_placements(model: Model, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Placements ``oMi`` of all joints, one composition step per tree depth.

    Levels are concatenated and permuted back to joint order once at the end (an indexed
    update per level would be a scatter, whose JVP is much costlier than a gather).
    """
    rotation, translation = _local_placements(model, q)
    tree = _tree(model)
    # The universe (depth 0) and the joints hanging from it (depth 1): world = local.
    rotations = [_take(rotation, level) for level in tree.levels[:2]]
    translations = [_take(translation, level) for level in tree.levels[:2]]
    for level, parents in zip(tree.levels[2:], tree.level_parents[2:]):
        rotation_level, translation_level = _compose(
            _take(rotations[-1], parents),
            _take(translations[-1], parents),
            _take(rotation, level),
            _take(translation, level),
        )
        rotations.append(rotation_level)
        translations.append(translation_level)
    return _take(jnp.concatenate(rotations), tree.level_order), _take(jnp.concatenate(translations), tree.level_order)


class Kinematics(NamedTuple):
    """The world placements of a model's joints at one configuration and the motion subspace of
    every dof (the first stage of a step, :func:`~rsmooth.sim.kinematics`): what the dynamics,
    the contacts and the frame Jacobians are computed from.

    Attributes:
        rotation: ``(njoints, 3, 3)``, each joint frame's orientation in the world (Pinocchio's
            ``data.oMi[i].rotation``).
        translation: ``(njoints, 3)``, its origin in the world.
        motion_subspace: ``(nv, 6)``, the unit twist ``[linear, angular]`` of every dof, in
            world axes about the world origin.
    """

    rotation: jax.Array
    translation: jax.Array
    motion_subspace: jax.Array


def _kinematics(model: Model, q: jax.Array) -> Kinematics:
    tree = _tree(model)
    rotation, translation = _world_placements(model, q)
    # Joint-frame motion subspaces: [0, axis] (revolute), [axis, 0] (prismatic), unit twists
    # (free flyer), angular unit twists (spherical); then expressed in the world frame by the
    # owning joint's placement.
    dof_axes = model.joint_axes[tree.dof_owner]
    local_subspace = jnp.concatenate(
        [jnp.where(tree.dof_is_prismatic, dof_axes, 0.0), jnp.where(tree.dof_is_revolute, dof_axes, 0.0)], axis=1
    ) + tree.twist_basis
    world_subspace = _transform_motions(rotation[tree.dof_owner], translation[tree.dof_owner], local_subspace)
    return Kinematics(rotation, translation, world_subspace)


def _world_inertias(model: Model, kinematics: Kinematics) -> spatial.SpatialInertia:
    """Body inertias about the world origin, in world axes, batched over joints."""
    local = jax.vmap(spatial.spatial_inertia)(model.body_mass, model.body_com, model.body_inertia)
    return _transform_inertias(kinematics.rotation, kinematics.translation, local)


# --------------------------------------------------------------------------------------
# Kinematics: public functions
# --------------------------------------------------------------------------------------

# The public functions are jitted: called eagerly (tests, set-up code such as standing
# torques), each of their few hundred small operations would otherwise be compiled and
# dispatched one by one (seconds to set up Solo-12). Inside a caller's jit they are inlined.


@jax.jit
def forward_kinematics(model: Model, q: ArrayLike) -> tuple[jax.Array, jax.Array]:
    """Placements of all joint frames in the world (Pinocchio's ``data.oMi``).

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.

    Returns:
        ``(rotations, translations)`` of shapes ``(njoints, 3, 3)`` and ``(njoints, 3)``;
        index 0 is the universe (identity).
    """
    q = _check_vector("q", q, model.nq)
    return _world_placements(model, q)


def _frame_placement(
    model: Model, rotation: jax.Array, translation: jax.Array, frame: int
) -> tuple[jax.Array, jax.Array]:
    """``oMf = oMi[parent joint] * iMf`` from the joint placements ``oMi``."""
    joint = model.frame_parents[frame]
    return spatial.compose(
        rotation[joint], translation[joint], model.frame_placement_rotation[frame], model.frame_placement_translation[frame]
    )


@functools.partial(jax.jit, static_argnames=("frame",))
def frame_placement(model: Model, q: ArrayLike, frame: str | int) -> tuple[jax.Array, jax.Array]:
    """Placement of a frame in the world (Pinocchio's ``data.oMf[frame]``).

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.
        frame: frame name (e.g. ``"FL_FOOT"``) or index.

    Returns:
        ``(rotation, translation)`` of shapes ``(3, 3)`` and ``(3,)``.
    """
    q = _check_vector("q", q, model.nq)
    return _frame_placement(model, *_world_placements(model, q), model.frame_id(frame))


@functools.partial(jax.jit, static_argnames=("frame", "reference"))
def frame_jacobian(
    model: Model, q: ArrayLike, frame: str | int, reference: Reference = "local_world_aligned"
) -> jax.Array:
    """Jacobian of a frame's twist with respect to ``v``, as ``pin.getFrameJacobian``.

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.
        frame: frame name or index.
        reference: ``"local_world_aligned"`` (velocity of the frame origin and angular
            velocity, both in world axes: what contact models need), ``"local"`` (the frame's
            twist in the frame's axes; Pinocchio's default) or ``"world"`` (the spatial twist
            in the world frame, i.e. the velocity of the body point at the world origin).

    Returns:
        Array of shape ``(6, nv)``; rows ``[linear, angular]``.
    """
    if reference not in _REFERENCES:
        raise ValueError(f"reference must be one of {_REFERENCES}, got {reference!r}")
    q = _check_vector("q", q, model.nq)
    frame = model.frame_id(frame)
    kinematics = _kinematics(model, q)
    # Only the dofs of the joints between the root and the frame move it.
    moves_frame = _tree(model).support[model.frame_parents[frame]][:, None]
    columns = jnp.where(moves_frame, kinematics.motion_subspace, 0.0)  # (nv, 6), world frame
    if reference != "world":
        frame_rotation, frame_translation = _frame_placement(
            model, kinematics.rotation, kinematics.translation, frame
        )
        # Move the reference point from the world origin to the frame origin: v_p = v_o - p x w.
        linear = columns[:, :3] - jnp.cross(frame_translation, columns[:, 3:])
        columns = jnp.concatenate([linear, columns[:, 3:]], axis=1)
        if reference == "local":
            columns = jax.vmap(spatial.rotate_inverse, (None, 0))(frame_rotation, columns.reshape(-1, 3)).reshape(-1, 6)
    return columns.T


@functools.partial(jax.jit, static_argnames=("frame", "reference"))
def frame_velocity(
    model: Model, q: ArrayLike, v: ArrayLike, frame: str | int, reference: Reference = "local_world_aligned"
) -> jax.Array:
    """Twist of a frame, ``frame_jacobian(model, q, frame, reference) @ v``.

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.
        v: velocity, shape ``(nv,)``.
        frame: frame name or index.
        reference: see :func:`frame_jacobian` (Pinocchio's ``getFrameVelocity`` defaults to
            ``LOCAL``).

    Returns:
        Twist ``[linear, angular]`` of shape ``(6,)``.
    """
    v = _check_vector("v", v, model.nv)
    return frame_jacobian(model, q, frame, reference) @ v


# --------------------------------------------------------------------------------------
# Dynamics
# --------------------------------------------------------------------------------------


def _rnea(
    model: Model,
    kinematics: Kinematics,
    inertias: spatial.SpatialInertia,
    v: jax.Array,
    a: jax.Array | None,
    gravity: jax.Array,
) -> jax.Array:
    """Recursive Newton-Euler algorithm (Featherstone 2008, Table 5.1) in the world frame.

    The recursions of Table 5.1 become sums over the static support/subtree masks:
    ``v_i = sum_{j <= i} S_j qd_j``, ``a_i = a_0 + sum_{j <= i} (S_j qdd_j + v_j x S_j qd_j)``
    (a body-fixed ``S`` expressed in a fixed frame changes as ``dS/dt = v_j x S``),
    ``f_i = I_i a_i + v_i x* I_i v_i``, ``tau_j = S_j^T sum_{i >= j} f_i``. Gravity enters
    as the fictitious world acceleration ``a_0 = -g`` (Featherstone 2008, Sec. 5.3).
    ``a=None`` means zero acceleration. The armature term is left to the caller.
    """
    tree = _tree(model)
    subspace = kinematics.motion_subspace
    dof_twists = subspace * v[:, None]  # S_j qd_j for every dof
    velocities = _mask_sum(tree.support, dof_twists)  # (njoints, 6)
    bias = _motion_cross_motion(velocities[tree.dof_owner], dof_twists)
    if a is not None:
        bias = bias + subspace * a[:, None]
    world_acceleration = jnp.concatenate([-gravity, jnp.zeros_like(gravity)]).astype(subspace.dtype)
    accelerations = _mask_sum(tree.support, bias) + world_acceleration[None, :]
    momenta = _inertia_apply(inertias, velocities)
    forces = _inertia_apply(inertias, accelerations) + _motion_cross_force(velocities, momenta)
    subtree_forces = _mask_sum(tree.subtree, forces)
    return spatial.sum_last(subspace * subtree_forces[tree.dof_owner])


def _crba(model: Model, kinematics: Kinematics, inertias: spatial.SpatialInertia) -> jax.Array:
    """Composite-rigid-body algorithm (Featherstone 2008, Table 6.2) in the world frame.

    Composite inertias are subtree sums ``I^c_j = sum_{i >= j} I_i`` (one masked sum: in the
    world frame the recursion of Table 6.2 needs no change of frame), and
    ``H_ab = S_a^T I^c_{deeper of a, b} S_b`` for ``a``, ``b`` on one branch, else 0.
    """
    tree = _tree(model)
    subtree = jnp.asarray(tree.subtree, dtype=inertias.mass.dtype)
    composite = spatial.SpatialInertia(
        subtree @ inertias.mass,
        subtree @ inertias.first_moment,
        jnp.einsum("ji,ikl->jkl", subtree, inertias.rotational_inertia),
    )
    subspace = kinematics.motion_subspace
    owner_composite = jax.tree_util.tree_map(lambda x: x[tree.dof_owner], composite)
    composite_forces = _inertia_apply(owner_composite, subspace)  # I^c_{owner(b)} S_b
    # [a, b] = S_a^T I^c_{owner(b)} S_b (elementwise: a batched 18x6x18 dot is slower on CPU)
    pairings = spatial.sum_last(subspace[:, None, :] * composite_forces[None, :, :])
    upper = jnp.where(tree.dof_ancestor, pairings, 0.0)
    return upper + upper.T - jnp.where(tree.dof_same_joint, pairings, 0.0)


@jax.jit
def crba(model: Model, q: ArrayLike) -> jax.Array:
    """Joint-space mass matrix ``M(q)`` (full and symmetric, armature included).

    Composite-rigid-body algorithm, Featherstone (2008), Table 6.2; the armature (rotor
    inertia) is added to the diagonal, as Pinocchio does.

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.

    Returns:
        Array of shape ``(nv, nv)``.
    """
    q = _check_vector("q", q, model.nq)
    kinematics = _kinematics(model, q)
    return _crba(model, kinematics, _world_inertias(model, kinematics)) + jnp.diag(model.armature)


@jax.jit
def rnea(
    model: Model, q: ArrayLike, v: ArrayLike, a: ArrayLike, gravity: ArrayLike | None = None
) -> jax.Array:
    """Inverse dynamics ``tau = M(q) a + C(q, v) v + g(q)``, as ``pin.rnea``.

    Recursive Newton-Euler algorithm, Featherstone (2008), Table 5.1; includes the
    armature term ``armature * a`` as Pinocchio does.

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.
        v: velocity, shape ``(nv,)``.
        a: acceleration, shape ``(nv,)``.
        gravity: linear gravity in the world frame, shape ``(3,)``; default ``model.gravity``.

    Returns:
        Generalized forces, shape ``(nv,)``.
    """
    q = _check_vector("q", q, model.nq)
    v = _check_vector("v", v, model.nv)
    a = _check_vector("a", a, model.nv)
    kinematics = _kinematics(model, q)
    tau = _rnea(model, kinematics, _world_inertias(model, kinematics), v, a, _gravity(model, gravity))
    return tau + model.armature * a


@jax.jit
def nonlinear_effects(model: Model, q: ArrayLike, v: ArrayLike, gravity: ArrayLike | None = None) -> jax.Array:
    """Coriolis, centrifugal and gravity terms ``C(q, v) v + g(q)`` (``pin.nonLinearEffects``).

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.
        v: velocity, shape ``(nv,)``.
        gravity: linear gravity in the world frame, shape ``(3,)``; default ``model.gravity``.

    Returns:
        Array of shape ``(nv,)``.
    """
    q = _check_vector("q", q, model.nq)
    v = _check_vector("v", v, model.nv)
    kinematics = _kinematics(model, q)
    return _rnea(model, kinematics, _world_inertias(model, kinematics), v, None, _gravity(model, gravity))


@jax.jit
def gravity_torques(model: Model, q: ArrayLike, gravity: ArrayLike | None = None) -> jax.Array:
    """Generalized gravity forces ``g(q)`` (``pin.computeGeneralizedGravity``).

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.
        gravity: linear gravity in the world frame, shape ``(3,)``; default ``model.gravity``.

    Returns:
        Array of shape ``(nv,)``.
    """
    q = _check_vector("q", q, model.nq)
    kinematics = _kinematics(model, q)
    gravity = _gravity(model, gravity)
    # With v = 0 the RNEA reduces to tau_j = S_j^T sum_{i >= j} I_i a_0: only the subtree
    # masses and first moments matter (the torque of gravity about the world origin).
    inertias = _world_inertias(model, kinematics)
    world_acceleration = jnp.concatenate([-gravity, jnp.zeros_like(gravity)]).astype(inertias.mass.dtype)
    forces = _inertia_apply(inertias, jnp.broadcast_to(world_acceleration, (model.njoints, 6)))
    tree = _tree(model)
    subtree_forces = jnp.asarray(tree.subtree, dtype=forces.dtype) @ forces
    return jnp.sum(kinematics.motion_subspace * subtree_forces[tree.dof_owner], axis=1)


def _solve_positive_definite(matrix: jax.Array, rhs: jax.Array) -> jax.Array:
    """``matrix^-1 rhs`` by Cholesky, differentiated implicitly.

    ``lax.custom_linear_solve`` differentiates ``x = M^-1 b`` as ``dx = M^-1 (db - dM x)``,
    reusing the factorization, instead of differentiating through the Cholesky factorization
    (whose JVP solves a matrix equation per tangent and was ~50x slower here).
    """
    factor = linalg.cho_factor(matrix)
    return jax.lax.custom_linear_solve(
        lambda x: jnp.sum(matrix * x[None, :], axis=1),
        rhs,
        solve=lambda _, b: linalg.cho_solve(factor, b),
        symmetric=True,
    )


@jax.jit
def forward_dynamics(
    model: Model, q: ArrayLike, v: ArrayLike, tau: ArrayLike, gravity: ArrayLike | None = None
) -> jax.Array:
    """Joint accelerations ``a = M(q)^-1 (tau - C(q, v) v - g(q))``, as ``pin.aba``.

    The mass matrix (CRBA) is factorized by Cholesky; CRBA and RNEA share one kinematics pass.

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.
        v: velocity, shape ``(nv,)``.
        tau: generalized forces, shape ``(nv,)``.
        gravity: linear gravity in the world frame, shape ``(3,)``; default ``model.gravity``.

    Returns:
        Accelerations, shape ``(nv,)``.
    """
    q = _check_vector("q", q, model.nq)
    v = _check_vector("v", v, model.nv)
    tau = _check_vector("tau", tau, model.nv)
    kinematics = _kinematics(model, q)
    inertias = _world_inertias(model, kinematics)
    mass_matrix = _crba(model, kinematics, inertias) + jnp.diag(model.armature)
    bias = _rnea(model, kinematics, inertias, v, None, _gravity(model, gravity))
    return _solve_positive_definite(mass_matrix, tau - bias)


# --------------------------------------------------------------------------------------
# Configuration manifold
# --------------------------------------------------------------------------------------


@jax.jit
def integrate(model: Model, q: ArrayLike, v: ArrayLike, dt: ArrayLike = 1.0) -> jax.Array:
    """Configuration reached from ``q`` by the constant velocity ``v`` during ``dt``.

    ``pin.integrate(model, q, v * dt)``: revolute and prismatic joints add ``v dt``; a free
    flyer follows the twist on SE(3), ``M <- M exp6(v dt)`` (linear and angular velocity in
    the body frame), and its quaternion is kept in the hemisphere of the input quaternion and
    normalized to first order, exactly as Pinocchio.

    Args:
        model: the kinematic tree.
        q: configuration, shape ``(nq,)``.
        v: velocity, shape ``(nv,)``.
        dt: duration (scalar).

    Returns:
        Configuration, shape ``(nq,)``.
    """
    q = _check_vector("q", q, model.nq)
    v = _check_vector("v", v, model.nv)
    tree = _tree(model)
    step = v * dt
    result = q.at[tree.vector_q].add(step[tree.vector_v])
    result = _per_joint(model, tree.free_flyer, (7, 6), _integrate_free_flyer, result, q, step)
    return _per_joint(model, tree.spherical, (4, 3), _integrate_spherical, result, q, step)


def _joint_coordinates(model: Model, joints: np.ndarray, width_q: int, width_v: int) -> tuple[np.ndarray, np.ndarray]:
    """Configuration and velocity indices ``(k, width_q)``, ``(k, width_v)`` of ``joints``."""
    return (np.asarray(model.idx_q)[joints][:, None] + np.arange(width_q),
            np.asarray(model.idx_v)[joints][:, None] + np.arange(width_v))


def _per_joint(model: Model, joints: np.ndarray, widths: tuple[int, int], function, result: jax.Array, q: jax.Array,
               v: jax.Array) -> jax.Array:
    """``result`` with the configuration coordinates of ``joints`` (joints of one type, whose
    configuration and velocity have ``widths``) set to ``function(q_j, v_j)``, in one vectorized
    call: the program does not grow with the number of joints, as a loop over them would."""
    if len(joints) == 0:
        return result
    iq, iv = _joint_coordinates(model, joints, *widths)
    return result.at[iq].set(jax.vmap(function)(q[iq], v[iv]))


def _first_order_normalized(quaternion: jax.Array, increment: jax.Array) -> jax.Array:
    """``quaternion * increment`` in ``quaternion``'s hemisphere, normalized to first order."""
    new_quaternion = spatial.quaternion_multiply(quaternion, increment)
    # Pinocchio flips the result into the input's hemisphere: dot(q, q dq) = w(dq) |q|^2.
    new_quaternion = jnp.where(increment[3] < 0.0, -new_quaternion, new_quaternion)
    # pinocchio::quaternion::firstOrderNormalize: q (3 - |q|^2) / 2.
    return new_quaternion * (0.5 * (3.0 - jnp.sum(new_quaternion * new_quaternion)))


def _integrate_free_flyer(q: jax.Array, step: jax.Array) -> jax.Array:
    """One free flyer's ``(7,)`` configuration moved by the twist ``step`` ``(6,)`` on SE(3)."""
    position, quaternion = q[:3], q[3:]
    linear, angular = step[:3], step[3:]
    position = position + spatial.rotate(
        spatial.quaternion_to_rotation(quaternion), spatial.rotate(spatial.left_jacobian_so3(angular), linear)
    )
    return jnp.concatenate([position, _first_order_normalized(quaternion, spatial.quaternion_exp(angular))])


def _integrate_spherical(q: jax.Array, step: jax.Array) -> jax.Array:
    """One spherical joint's quaternion ``(4,)`` turned by the rotation vector ``step``."""
    return _first_order_normalized(q, spatial.quaternion_exp(step))


@jax.jit
def difference(model: Model, q0: ArrayLike, q1: ArrayLike) -> jax.Array:
    """Velocity that goes from ``q0`` to ``q1`` in unit time (``pin.difference``).

    The inverse of :func:`integrate`: ``integrate(model, q0, difference(model, q0, q1))``
    equals ``q1`` (for a free flyer, ``log6(M0^-1 M1)``, rotation angle in ``[0, pi]``).

    Args:
        model: the kinematic tree.
        q0: start configuration, shape ``(nq,)``.
        q1: end configuration, shape ``(nq,)``.

    Returns:
        Velocity, shape ``(nv,)``.
    """
    q0 = _check_vector("q0", q0, model.nq)
    q1 = _check_vector("q1", q1, model.nq)
    tree = _tree(model)
    dtype = jnp.result_type(q0.dtype, q1.dtype)
    result = jnp.zeros(model.nv, dtype=dtype).at[tree.vector_v].set(q1[tree.vector_q] - q0[tree.vector_q])
    for joints, width_q, width_v, function in ((tree.free_flyer, 7, 6, _difference_free_flyer),
                                              (tree.spherical, 4, 3, _difference_spherical)):
        if len(joints):
            iq, iv = _joint_coordinates(model, joints, width_q, width_v)
            result = result.at[iv].set(jax.vmap(function)(q0[iq], q1[iq]))
    return result


def _difference_free_flyer(q0: jax.Array, q1: jax.Array) -> jax.Array:
    """The twist ``(6,)`` from one free flyer's configuration ``q0`` to ``q1``, ``log6(M0^-1 M1)``."""
    relative_quaternion = spatial.quaternion_multiply(spatial.quaternion_conjugate(q0[3:]), q1[3:])
    angular = spatial.quaternion_log(relative_quaternion)
    relative_position = spatial.rotate_inverse(spatial.quaternion_to_rotation(q0[3:]), q1[:3] - q0[:3])
    return jnp.concatenate([spatial.left_jacobian_so3_inverse_apply(angular, relative_position), angular])


def _difference_spherical(q0: jax.Array, q1: jax.Array) -> jax.Array:
    """The rotation vector ``(3,)`` from one spherical joint's quaternion ``q0`` to ``q1``."""
    return spatial.quaternion_log(spatial.quaternion_multiply(spatial.quaternion_conjugate(q0), q1))



# --------------------------------------------------------------------------------------
# Time stepping of free flyers
# --------------------------------------------------------------------------------------


def _free_flyer_transport(model: Model, v: jax.Array) -> jax.Array:
    """``omega x v_lin`` on every free flyer's linear dofs, zeros elsewhere; shape ``(nv,)``.

    A free flyer's velocity is its body twist ``[v_lin, omega]`` (body axes), whose time
    derivative is the spatial acceleration ``a``; the acceleration of the body origin in a
    frame that does not rotate is ``a_lin + omega x v_lin``. A time step that writes the
    end-of-step velocity in the body axes of the step's start (a frame frozen for the step)
    therefore uses ``a = (v+ - v) / h - omega x v_lin``, and turns ``v+`` into the new body axes
    afterwards (:func:`_free_flyer_new_axes`): the frame's rotation is then exact, where the
    explicit ``-h omega x v_lin`` followed by the rotation of the frame scales the velocity
    across the spin axis by ``sqrt(1 + (h omega)^2)`` every step.
    """
    joints = _tree(model).free_flyer
    if len(joints) == 0:
        return jnp.zeros_like(v)
    _, iv = _joint_coordinates(model, joints, 7, 6)
    twists = v[iv]
    return jnp.zeros_like(v).at[iv[:, :3]].set(jnp.cross(twists[:, 3:], twists[:, :3]))


def _lone_free_flyers(model: Model) -> tuple[int, ...]:
    """The free-flyer joints that carry a single body (no joint below them): free objects."""
    below = set(model.parents[1:])
    return tuple(int(j) for j in _tree(model).free_flyer if int(j) not in below)


def _free_body_rotation(model: Model, v: jax.Array, dt: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(v', gyroscopic)``: the torque-free rotation of every free object
    (:func:`_lone_free_flyers`) over ``dt``, and the gyroscopic torques ``omega x I omega`` it
    replaces in the bias forces, both ``(nv,)`` (zeros and ``v`` elsewhere).

    Euler's equation ``I domega/dt + omega x I omega = 0`` (``I`` about the centre of mass,
    body axes) by the implicit midpoint rule, ``I (omega' - omega) + dt m x I m = 0`` with
    ``m = (omega + omega') / 2``, which keeps ``omega . I omega`` exactly (a quadratic
    invariant): an explicit gyroscopic term gains energy in every tumble (4.6 % in 3 s through a
    flip about the intermediate axis at 5 rad/s, ``h = 10 ms``). Solved by Newton's method
    (quadratic convergence from ``omega``: four iterations reach rounding for ``dt |omega|``
    up to about 1), in a ``fori_loop``: every step program holds one iteration, not four
    written out (a smaller program to compile, no slower to run). Bodies with joints below
    keep the explicit term (their coupling to the joints is not a rigid body's).
    """
    joints = np.asarray(_lone_free_flyers(model), dtype=np.int32)
    if len(joints) == 0:
        return v, jnp.zeros_like(v)
    angular = _joint_coordinates(model, joints, 7, 6)[1][:, 3:]
    omega, inertia = v[angular], model.body_inertia[joints]

    def rotate(omega, inertia):
        def newton(_, rotated):
            middle = 0.5 * (omega + rotated)
            momentum = inertia @ middle
            residual = inertia @ (rotated - omega) + dt * jnp.cross(middle, momentum)
            jacobian = inertia + 0.5 * dt * (spatial.skew(middle) @ inertia - spatial.skew(momentum))
            return rotated - linalg.solve(jacobian, residual)

        return jax.lax.fori_loop(0, 4, newton, omega)

    gyroscopic = jnp.cross(omega, jnp.einsum("kij,kj->ki", inertia, omega))
    return v.at[angular].set(jax.vmap(rotate)(omega, inertia)), jnp.zeros_like(v).at[angular].set(gyroscopic)


def _free_flyer_start(model: Model, v: jax.Array, dt: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(v_start, removed_bias)`` of a time step: the velocity the step's forces act from
    (free objects rotated torque-free, :func:`_free_body_rotation`, and every free flyer's
    linear velocity transported, :func:`_free_flyer_transport`) and the bias forces that this
    accounts for, to subtract from RNEA's. The step's acceleration is ``(v+ - v_start) / dt``."""
    rotated, gyroscopic = _free_body_rotation(model, v, dt)
    return rotated + dt * _free_flyer_transport(model, v), gyroscopic


def _free_flyer_new_axes(model: Model, v: jax.Array, dt: jax.Array) -> jax.Array:
    """``v`` with every free flyer's linear velocity turned from its body axes at the start of
    a step to those at its end, ``exp(dt omega)^T v_lin`` (its angular velocity is unchanged by
    a rotation about itself): the same world velocity in the state's convention, body axes."""
    joints = _tree(model).free_flyer
    if len(joints) == 0:
        return v
    _, iv = _joint_coordinates(model, joints, 7, 6)
    twists = v[iv]
    turned = jax.vmap(lambda t: spatial.rotate_inverse(spatial.exp3(dt * t[3:]), t[:3]))(twists)
    return v.at[iv[:, :3]].set(turned)
