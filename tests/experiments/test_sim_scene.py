"""The MuJoCo-scene simulation experiment: a ball and a box dropped on a floor from a file, and a
robot's URDF given a free base and a floor."""

import json

import pytest

import rsmooth.sim as sim
from rsmooth.experiments import sim_scene

# A ball and a box 5 cm above a floor, 10 ms steps: both land within 0.1 s.
SCENE = """<mujoco><option timestep="0.01"/><worldbody>
  <geom name="floor" type="plane" size="1 1 0.1"/>
  <body name="ball" pos="0.3 0 0.1"><freejoint/><geom type="sphere" size="0.05"/></body>
  <body name="box" pos="-0.3 0 0.1"><freejoint/><geom type="box" size="0.05 0.04 0.05" euler="0 0 20"/></body>
</worldbody></mujoco>"""


def test_dropped_ball_and_box_land_without_sinking(tmp_path, getkey):
    scene = tmp_path / "drop.xml"
    scene.write_text(SCENE)
    config = sim_scene.Config(file=str(scene), steps=20, frames=2)
    metrics = sim_scene.run(config, tmp_path / "out", getkey(), progress=False)
    # floor-ball (1 contact), floor-box (4), ball-box (1)
    assert metrics["geom_pairs"] == 3 and metrics["candidate_contacts"] == 1 + 4 + 1
    assert metrics["contacts_active_max"] == 5  # the ball's point and the box's four corners
    assert metrics["max_penetration"] < 1e-3 and metrics["initial_penetration"] == 0.0
    # falling 5 cm and landing inelastically loses potential energy, and gains none on the way
    assert metrics["energy_change"] < 0 and metrics["energy_max_gain"] < 1e-6
    assert metrics["unconverged_steps"] == 0 and metrics["diverged_steps"] == 0
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["steps"] == 20
    assert (tmp_path / "out" / "scene.gif").stat().st_size > 1000


def test_options_that_need_a_file_are_refused_without_one(tmp_path):
    for changes, message in (
        ({"floating_base": True}, r"floating_base \(--floating-base\) applies to a --file"),
        ({"package_dir": str(tmp_path)}, r"package_dir \(--package-dir\) applies to a --file"),
        ({"drop_mimic": True}, r"drop_mimic \(--drop-mimic\) applies to a --file"),
        ({"boundinertia": 1e-9}, r"boundinertia \(--boundinertia\) applies to a --file"),
        ({"file": __file__, "package_dir": str(tmp_path / "missing")}, r"package_dir \(--package-dir\) must be an"),
    ):
        with pytest.raises(ValueError, match=message):
            sim_scene.Config(**changes)
    # a pendulum whose link collides with nothing: a simulation without contacts
    pendulum = tmp_path / "pendulum.xml"
    pendulum.write_text(
        '<mujoco><worldbody><body name="arm" pos="0 0 1"><joint type="hinge" axis="0 1 0"/><geom type="capsule" '
        'size="0.05" fromto="0 0 0 0.5 0 0" contype="0" conaffinity="0"/></body></worldbody></mujoco>'
    )
    metrics = sim_scene.run(sim_scene.Config(file=str(pendulum), steps=50, frames=2), tmp_path / "out", None, progress=False)
    assert metrics["candidate_contacts"] == metrics["contacts_active_max"] == metrics["unconverged_steps"] == 0
    # released horizontal, it swings 0.1 s: the time stepping (h = 2 ms, first order) loses a
    # little energy and never gains any; the bound is 1 % of m g L / 2 (4.45 kg, L = 0.5 m)
    assert metrics["energy_max_gain"] <= 1e-9 and 0.0 < -metrics["energy_change"] < 0.01 * 4.45 * 9.81 * 0.25
    assert metrics["joint_limits"] == 0
    # the same pendulum limited to 5 degrees below horizontal (reached in about 0.08 s): it swings onto its limit and
    # stays there (the limit holds it; the file's other side, -10 degrees, never acts)
    pendulum.write_text(pendulum.read_text().replace('axis="0 1 0"', 'axis="0 1 0" limited="true" range="-10 5"'))
    metrics = sim_scene.run(sim_scene.Config(file=str(pendulum), steps=50, frames=2), tmp_path / "out", None, progress=False)
    assert metrics["joint_limits"] == 2 and metrics["limits_active_max"] == 1
    assert metrics["max_limit_violation"] < 1e-9 and metrics["unconverged_steps"] == 0
    assert metrics["energy_max_gain"] <= 1e-9
    assert metrics["joint_friction_dofs"] == metrics["joint_couplings"] == metrics["connections"] == metrics["welds"] == metrics["joint_springs"] == 0


ARM = 'type="capsule" size="0.05" fromto="0 0 0 0.5 0 0" contype="0" conaffinity="0"'
JOINTED = f"""<mujoco><option timestep="0.002"/><worldbody>
<body name="held" pos="0 0 1"><joint name="held" axis="0 1 0" frictionloss="20"/><geom {ARM}/></body>
<body name="leader" pos="0 1 1"><joint name="leader" axis="0 1 0" stiffness="50"/><geom {ARM}/></body>
<body name="follower" pos="0 2 1"><joint name="follower" axis="0 1 0"/><geom {ARM}/></body>
<body name="pinned" pos="0 3 1"><joint name="pinned" axis="0 1 0"/><geom {ARM}/></body>
<body name="welded" pos="0 4 1"><joint name="welded" axis="0 1 0"/><geom {ARM}/></body>
</worldbody><equality><joint joint1="follower" joint2="leader" polycoef="0 0.5 0 0 0"/>
<connect body1="pinned" body2="world" anchor="0.5 0 0"/><weld body1="welded" body2="world"/></equality></mujoco>"""


def test_joint_friction_couplings_connections_and_springs_are_reported(tmp_path):
    """Five horizontal arms of m = 4.45 kg, L = 0.5 m: one held by its dry friction (20 N m
    against gravity's m g L / 2 = 10.9 N m), one sprung and followed at half its angle by the
    third, the fourth held by its tip to the world, the fifth welded to it."""
    jointed = tmp_path / "jointed.xml"
    jointed.write_text(JOINTED)
    metrics = sim_scene.run(sim_scene.Config(file=str(jointed), steps=50, frames=2), tmp_path / "out", None, progress=False)
    assert metrics["joint_friction_dofs"] == 1 and metrics["joint_friction_held_mean"] == 1.0
    gravity_torque = 4.45 * 9.81 * 0.25  # the friction impulse is gravity's, over the step
    assert metrics["joint_friction_impulse_max"] == pytest.approx(gravity_torque / 20.0, rel=1e-3)
    assert metrics["joint_couplings"] == 1 and metrics["max_coupling_error"] < 1e-12
    assert metrics["connections"] == 1 and metrics["max_connection_error"] < 1e-12
    assert metrics["welds"] == 1 and metrics["max_weld_error"] < 1e-12
    assert metrics["joint_springs"] == 1 and metrics["unconverged_steps"] == 0


def test_solo12_urdf_stands_on_the_floor_put_under_it(tmp_path, getkey):
    """Solo-12's URDF from example-robot-data, its package:// meshes found above the file, with
    a free base, a floor and no self-collision: its 17 collision meshes meet the floor only."""
    config = sim_scene.Config(
        file=str(sim.solo12_urdf_path()), floating_base=True, floor=True, self_collision=False, steps=10, frames=2
    )
    metrics = sim_scene.run(config, tmp_path, getkey(), progress=False)
    assert metrics["bodies"] == 18 and metrics["geom_pairs"] == 17 and metrics["candidate_contacts"] == 17 * 4
    # q = 0, the legs straight down: the feet touch the floor from the first step, none sinks
    assert metrics["contacts_active_max"] >= 4
    assert metrics["max_penetration"] < 1e-2
    assert metrics["unconverged_steps"] == 0 and metrics["diverged_steps"] == 0
    assert metrics["energy_max_gain"] < 1e-4


def test_a_start_with_overlapping_shapes_reports_the_penetration(tmp_path, getkey):
    # the ball 4 mm into the floor in the file's own configuration
    scene = tmp_path / "sunk.xml"
    scene.write_text(SCENE.replace('pos="0.3 0 0.1"', 'pos="0.3 0 0.046"'))
    metrics = sim_scene.run(sim_scene.Config(file=str(scene), steps=2, frames=2), tmp_path / "out", getkey(), progress=False)
    assert metrics["initial_penetration"] == pytest.approx(0.004, abs=1e-12)
    assert sim_scene.summary(metrics)["penetration at the start (m)"].startswith("4.00e-03")
