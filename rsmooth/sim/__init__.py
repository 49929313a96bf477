"""Differentiable rigid-body simulation with frictional contact, in pure JAX.

Kinematic trees come from URDF files through Pinocchio (:func:`load_urdf`), or from MJCF and
URDF files through MuJoCo's compiler (:func:`load_mjcf`), and are frozen into JAX arrays
(:class:`Model`); dynamics (CRBA, RNEA, Jacobians) are pure JAX functions;
contact is a frictional complementarity problem solved by ADMM and differentiated
implicitly (:func:`solve_ncp`); collision geometry (:class:`Sphere`, :class:`Capsule`,
:class:`Box`, :class:`Cylinder`, :class:`Ellipsoid`, :class:`HalfSpace`, :class:`HeightField`,
:class:`ConvexMesh`) gives contact
manifolds between posed shapes (:func:`collide`, :func:`candidate_pairs`); :class:`RigidBodySystem` steps a system in time
(its contacts: spheres against half-spaces, and any pairs of shapes, :class:`GeomPair`; how it
steps: :class:`Options`, the time step, contact law, solver and derivative mode) and is the
``Dynamics`` (``step(x, u)``, ``nx``, ``nu``) that rsmooth's optimizers consume. As MJX's
``step(model, data)``, :func:`step` advances a :class:`State` (``q``, ``v`` and the impulses
that warm-start the next contact solve, :func:`make_state`), and the stages of a step are
public functions: :func:`kinematics`, :func:`collision`, :func:`free_motion`,
:func:`solve_contacts`, :func:`advance` (composed by :func:`step_stages`). :func:`scene`
builds one from a MuJoCo model (MJCF or URDF), its geoms paired as MuJoCo pairs them;
:func:`panda_push` is a Panda arm beside a box on a table.
"""

from rsmooth.sim._collision import (
    CandidatePairs as CandidatePairs,
    Contacts as Contacts,
    candidate_pairs as candidate_pairs,
    collide as collide,
    manifold_size as manifold_size,
)
from rsmooth.sim._contact import (
    ContactPoints as ContactPoints,
    contact_frame as contact_frame,
    corrected_free_velocity as corrected_free_velocity,
    sphere_halfspace_contacts as sphere_halfspace_contacts,
)
from rsmooth.sim._dynamics import (
    crba as crba,
    difference as difference,
    forward_dynamics as forward_dynamics,
    forward_kinematics as forward_kinematics,
    frame_jacobian as frame_jacobian,
    frame_placement as frame_placement,
    frame_velocity as frame_velocity,
    gravity_torques as gravity_torques,
    integrate as integrate,
    nonlinear_effects as nonlinear_effects,
    rnea as rnea,
)
from rsmooth.sim._geometry import (
    Box as Box,
    Capsule as Capsule,
    ConvexMesh as ConvexMesh,
    Cylinder as Cylinder,
    Ellipsoid as Ellipsoid,
    HalfSpace as HalfSpace,
    HeightField as HeightField,
    NonConvexMeshWarning as NonConvexMeshWarning,
    Sphere as Sphere,
    convex_mesh as convex_mesh,
)
from rsmooth.sim._laws import (
    LogBarrier as LogBarrier,
    SpringDamper as SpringDamper,
    log_barrier_force as log_barrier_force,
    spring_damper_force as spring_damper_force,
)
from rsmooth.sim._model import (
    Model as Model,
    example_robot_data_root as example_robot_data_root,
    free_body as free_body,
    from_pinocchio as from_pinocchio,
    load_model as load_model,
    load_urdf as load_urdf,
    save_model as save_model,
    solo12_standing_configuration as solo12_standing_configuration,
    solo12_urdf_path as solo12_urdf_path,
)
from rsmooth.sim._mujoco import (
    MujocoLoadWarning as MujocoLoadWarning,
    MujocoModel as MujocoModel,
    from_mujoco as from_mujoco,
    load_mjcf as load_mjcf,
)
from rsmooth.sim._ncp import (
    NCPInfo as NCPInfo,
    NCPSolver as NCPSolver,
    ncp_residuals as ncp_residuals,
    project_to_friction_cone as project_to_friction_cone,
    solve_ncp as solve_ncp,
)
from rsmooth.sim._panda import (
    PANDA_HAND_LINKS as PANDA_HAND_LINKS,
    PANDA_LINKS as PANDA_LINKS,
    PANDA_TORQUE_LIMITS as PANDA_TORQUE_LIMITS,
    panda_push as panda_push,
    panda_push_model as panda_push_model,
)
from rsmooth.sim._scene import automatic_contact_budget as automatic_contact_budget
from rsmooth.sim._scene import scene as scene
from rsmooth.sim._simulator import (
    SEPARATED as SEPARATED,
    SLIDING as SLIDING,
    STICKING as STICKING,
    GeomPair as GeomPair,
    Actuation as Actuation,
    Geometry as Geometry,
    JointCoupling as JointCoupling,
    PointConnection as PointConnection,
    Weld as Weld,
    JointFriction as JointFriction,
    JointSprings as JointSprings,
    Tendons as Tendons,
    Fluid as Fluid,
    GravityCompensation as GravityCompensation,
    Servos as Servos,
    ActivationDynamics as ActivationDynamics,
    Joints as Joints,
    Options as Options,
    RigidBodySystem as RigidBodySystem,
    SimulationWarning as SimulationWarning,
    StepInfo as StepInfo,
    check_steps as check_steps,
    energy as energy,
    step as step,
)
from rsmooth.sim._stages import (
    ContactGeometry as ContactGeometry,
    ContactSolution as ContactSolution,
    FreeMotion as FreeMotion,
    Kinematics as Kinematics,
    State as State,
    advance as advance,
    collision as collision,
    free_motion as free_motion,
    kinematics as kinematics,
    make_state as make_state,
    solve_contacts as solve_contacts,
    step_stages as step_stages,
)
from rsmooth.sim._systems import (
    SOLO12_ARMATURE as SOLO12_ARMATURE,
    SOLO12_BASE_HALF_EXTENTS as SOLO12_BASE_HALF_EXTENTS,
    SOLO12_KNEE_RADIUS as SOLO12_KNEE_RADIUS,
    SOLO12_FEET as SOLO12_FEET,
    SOLO12_FOOT_RADIUS as SOLO12_FOOT_RADIUS,
    SOLO12_JOINT_DAMPING as SOLO12_JOINT_DAMPING,
    SOLO12_TORQUE_LIMIT as SOLO12_TORQUE_LIMIT,
    ball as ball,
    ball_wall as ball_wall,
    bodies as bodies,
    box as box,
    pusher as pusher,
    pusher_start_state as pusher_start_state,
    cube as cube,
    solo12 as solo12,
    solo12_foot_positions as solo12_foot_positions,
    solo12_standing_torques as solo12_standing_torques,
)
