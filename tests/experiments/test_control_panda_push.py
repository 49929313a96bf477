"""The Panda push: the scene holds still under gravity compensation and zero torque, its tool
starts where it is placed; DDP leaves the box (zero gradient), R-DDP pushes it."""

import json

import imageio.v2 as imageio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import sim
from rsmooth.experiments import control_panda_push


def test_the_scene_starts_where_it_says_and_holds_still_at_zero_torque():
    system = sim.panda_push(tool_gap=0.04)
    assert (system.nx, system.nu) == (27, 7) and system.actuation.gravity_compensation
    np.testing.assert_allclose(system.actuation.input_limit, sim.PANDA_TORQUE_LIMITS)
    x0 = system.initial_state()
    # The tool (radius 1.5 cm) 4 cm behind the box's -x face (half side 5 cm), at its mid-height.
    _, tool = sim.frame_placement(system.model, x0[:14], "panda_hand_tcp")
    np.testing.assert_allclose(np.asarray(tool), [0.55 - 0.05 - 0.04 - 0.015, 0.0, 0.05], atol=1e-9)
    # Gravity compensated: nothing moves (the box rests on the table, the arm holds).
    xs, infos = jax.jit(lambda x: system.rollout(x, jnp.zeros((30, 7))))(x0)
    np.testing.assert_allclose(xs[-1], x0, atol=1e-9)
    assert not bool(jnp.any(infos.diverged)) and bool(jnp.all(infos.ncp.converged))
    with pytest.raises(ValueError, match="box_side must be positive"):
        sim.panda_push(box_side=0.0)
    with pytest.raises(ValueError, match="within the arm's reach"):
        sim.panda_push(box_position=(1.5, 0.0))
    # the model an animation draws is the one the system is built from, for the same arguments
    loaded = sim.panda_push_model(box_side=0.2, tool_gap=0.04)
    box = loaded.geom_names.index("box")
    np.testing.assert_allclose(loaded.geom_size[box], [0.1] * 3)
    with pytest.raises(TypeError, match="box_sides"):
        sim.panda_push_model(box_sides=0.2)
    with pytest.raises(ValueError, match="table_friction must be non-negative"):
        sim.panda_push_model(table_friction=-0.1)


@pytest.mark.slow
def test_ddp_leaves_the_box_and_rddp_pushes_it(tmp_path, getkey):
    config = control_panda_push.Config.quick(max_iterations=8, num_samples=8, frames=2, horizon=25)
    metrics = control_panda_push.run(config, tmp_path, getkey(), progress=False)
    assert metrics["methods"] == ["ddp", "rddp"]
    ddp, rddp = metrics["ddp"], metrics["rddp"]
    # DDP: with the tool 3 cm away the box's state does not depend on the torques: the first
    # backward pass sees no descent direction, the arm holds still and so does the box.
    assert ddp["iterations"] == 1 and ddp["max_torque"] == 0.0 and ddp["box_displacement"] < 1e-6
    assert ddp["position_error"] == pytest.approx(config.push, abs=1e-6) and not ddp["success"]
    # R-DDP: the box pushed most of the way, every contact solve of its trajectory converged.
    assert rddp["box_displacement"] > 0.5 * config.push and rddp["final_cost"] < 0.2 * ddp["final_cost"]
    assert rddp["unconverged_steps"] == rddp["diverged_steps"] == ddp["diverged_steps"] == 0
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["target"] == pytest.approx([0.55 + config.push, 0.0])
    assert (tmp_path / "panda_push.png").stat().st_size > 10_000
    frames = imageio.mimread(tmp_path / "panda_push.gif")  # DDP and R-DDP side by side
    assert len(frames) >= config.frames and frames[0].shape[1] > frames[0].shape[0]
    assert np.ptp(frames[0]) > 100  # drawn: the arm, the box and the table on white


def test_the_colliding_links_option_reaches_the_scene():
    system, problem, _ = control_panda_push.build_problem(control_panda_push.Config.quick(colliding_links=sim.PANDA_HAND_LINKS))
    assert len(system.geometry.geom_pairs) == 3 + 2 * 9  # each of the hand's 9 geoms with the box and the table
    assert len(control_panda_push.build_problem(control_panda_push.Config.quick())[0].geometry.geom_pairs) == 3
    with pytest.raises(ValueError, match="colliding_links"):
        control_panda_push.Config(colliding_links=("panda_link0",))
