"""Rigid-body simulation: kinematic trees (URDF via Pinocchio), dynamics in pure JAX."""

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
from rsmooth.sim._model import (
    Model as Model,
    from_pinocchio as from_pinocchio,
    load_urdf as load_urdf,
    solo12_standing_configuration as solo12_standing_configuration,
    solo12_urdf_path as solo12_urdf_path,
)
