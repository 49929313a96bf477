"""Impossible physics is rejected where it enters: URDF inertials, models, system factories.

Host-side checks only: nothing here is compiled.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim

# A body with an arm (revolute) and a massless tool frame fixed to the arm (legal in URDF).
URDF = """<robot name="arm">
  <link name="body"><inertial><mass value="{mass}"/>
    <inertia ixx="{ixx}" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="arm"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="tool"><inertial><mass value="0"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial></link>
  <joint name="elbow" type="revolute"><parent link="body"/><child link="arm"/><axis xyz="0 1 0"/>
    <limit effort="1" lower="-1" upper="1" velocity="1"/></joint>
  <joint name="tool_mount" type="fixed"><parent link="arm"/><child link="tool"/></joint>
</robot>
"""


def _write(tmp_path, mass="1", ixx="1"):
    path = tmp_path / "arm.urdf"
    path.write_text(URDF.format(mass=mass, ixx=ixx))
    return path


@pytest.mark.parametrize(
    "mass, ixx, message",
    [
        ("-0.5", "1", r"link 'body' has mass -0.5"),
        ("nan", "1", r"link 'body' has mass nan"),
        ("inf", "1", r"link 'body' has mass inf"),
        ("1", "nan", r"link 'body' has inertia ixx = nan"),
        ("heavy", "1", r"mass of link 'body' is 'heavy'"),
    ],
)
def test_urdf_with_impossible_mass_or_inertia_is_rejected_naming_the_link(tmp_path, mass, ixx, message):
    # Checked on the XML before Pinocchio builds the model (it would accept them).
    with pytest.raises(ValueError, match=message):
        sim.load_urdf(_write(tmp_path, mass, ixx))


def test_urdf_inertia_must_be_that_of_a_rigid_body(tmp_path):
    pytest.importorskip("pinocchio")
    model = sim.load_urdf(_write(tmp_path))  # the massless tool frame is legal
    assert model.nq == 8 and float(model.body_mass[2]) == 1.0
    with pytest.raises(ValueError, match=r"link 'body'.*principal moments \(-1, 1, 1\) are not all >= 0"):
        sim.load_urdf(_write(tmp_path, ixx="-1"))
    with pytest.raises(ValueError, match=r"link 'body'.*triangle inequality"):
        sim.load_urdf(_write(tmp_path, ixx="3"))
    # Published URDFs with such inertias can still be loaded, on request.
    assert sim.load_urdf(_write(tmp_path, ixx="3"), check_inertia=False).nq == 8


def test_models_reject_negative_or_non_finite_values():
    body = sim.free_body(2.0, [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r"joint 'root_joint' has mass -1.0"):
        dataclasses.replace(body, body_mass=jnp.array([0.0, -1.0]))
    with pytest.raises(ValueError, match="body_com must be finite"):
        dataclasses.replace(body, body_com=body.body_com.at[1, 2].set(jnp.nan))
    with pytest.raises(ValueError, match="armature must be finite and >= 0"):
        dataclasses.replace(body, armature=-jnp.ones(6))
    with pytest.raises(ValueError, match="mass must be a positive, finite number, got nan"):
        sim.free_body(math.nan, [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="inertia must be finite"):
        sim.free_body(1.0, [1.0, math.nan, 1.0])


NAN, INF = math.nan, math.inf


@pytest.mark.parametrize(
    "factory, name, value",
    [
        (sim.cube, "time_step", 0.0),
        (sim.cube, "time_step", -0.01),
        (sim.cube, "time_step", NAN),
        (sim.cube, "time_step", INF),
        (sim.cube, "side", 0.0),
        (sim.cube, "mass", -1.0),
        (sim.cube, "mass", NAN),
        (sim.cube, "friction", -0.5),
        (sim.cube, "friction", NAN),
        (sim.ball_wall, "time_step", 0.0),
        (sim.ball_wall, "radius", 0.0),
        (sim.ball_wall, "mass", 0.0),
        (sim.ball_wall, "wall_distance", NAN),
        (sim.ball_wall, "friction", INF),
        (sim.pusher, "time_step", 0.0),
        (sim.pusher, "box_side", 0.0),
        (sim.pusher, "box_side", -0.2),
        (sim.pusher, "box_mass", 0.0),
        (sim.pusher, "finger_radius", -0.01),
        (sim.pusher, "finger_mass", NAN),
        (sim.pusher, "floor_friction", -0.1),
        (sim.pusher, "finger_friction", NAN),
        (sim.pusher, "force_limit", 0.0),
        (sim.pusher, "force_limit", NAN),
        # solo12 checks its numbers before it loads the URDF: no Pinocchio needed
        (sim.solo12, "time_step", 0.0),
        (sim.solo12, "time_step", NAN),
        (sim.solo12, "friction", -0.7),
        (sim.solo12, "torque_limit", 0.0),
        (sim.solo12, "armature", NAN),
        (sim.solo12, "joint_damping", NAN),
    ],
)
def test_system_factories_reject_impossible_parameters_by_name(factory, name, value):
    with pytest.raises(ValueError, match=rf"^{name} must be"):
        factory(**{name: value})


def test_system_factories_accept_the_limits_of_their_ranges():
    assert float(sim.pusher(finger_radius=0.0, force_limit=INF).geometry.geom_pairs[0].shape2.radius) == 0.0  # a point finger, unlimited
    assert float(sim.cube(friction=0.0).geometry.friction[0]) == 0.0
    assert np.isfinite(float(sim.ball_wall(wall_distance=-1.0).geometry.plane_offsets[1]))


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("time_step", 0.0, "time_step must be positive"),
        ("time_step", -0.01, "time_step must be positive"),
        ("time_step", float("nan"), "time_step must be positive"),
        ("friction", [-0.1], "friction must be non-negative"),
        ("sphere_radii", [-0.01] + [0.0] * 7, "sphere_radii must be non-negative"),
        ("input_limit", [0.0] * 6, "input_limit must be positive"),
    ],
)
def test_a_system_built_directly_rejects_impossible_physics(field, value, match):
    cube = sim.cube()
    with pytest.raises(ValueError, match=match):
        if field == "time_step":
            cube.with_options(time_step=value)
        else:
            group = "actuation" if field == "input_limit" else "geometry"
            dataclasses.replace(cube, **{group: dataclasses.replace(getattr(cube, group), **{field: jnp.asarray(value)})})


def test_options_are_checked_by_name():
    cube = sim.cube()
    assert cube.options.time_step == cube.time_step and cube.solver is cube.options.solver
    assert isinstance(sim.Options(time_step=0.01).time_step, jax.Array)  # traced, not a constant
    changed = cube.with_options(time_step=0.005, derivative="autodiff")
    assert float(changed.time_step) == 0.005 and changed.derivative == "autodiff" and cube.derivative == "implicit"
    for changes, match in (
        ({"baumgarte": 1.5}, "baumgarte must be in"),
        ({"derivative": "finite"}, "derivative must be 'implicit' or 'autodiff'"),
        ({"contact": "soft"}, "contact must be 'hard'"),
        ({"max_motion_per_step": 0.0}, "max_motion_per_step must be positive"),
        ({"time_step": [0.01, 0.02]}, "time_step must be a scalar"),
    ):
        with pytest.raises(ValueError, match=match):
            cube.with_options(**changes)
    with pytest.raises(TypeError, match="with_options takes the fields of Options"):
        cube.with_options(timestep=0.01)
    with pytest.raises(ValueError, match="options must be an Options"):
        dataclasses.replace(cube, options=0.01)
