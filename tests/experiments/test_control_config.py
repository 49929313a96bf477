"""What the control experiments' Configs share: validation and the solvers they build."""

import jax
import pytest

from rsmooth import control
from rsmooth.experiments import _control, control_cube_lift, control_pusher, control_solo_lift

EXPERIMENTS = [(control_cube_lift, 13, "force_noise"), (control_solo_lift, 37, "torque_noise"), (control_pusher, 17, "force_noise")]


@pytest.mark.parametrize("module, nx, control_noise", EXPERIMENTS)
def test_solver_takes_the_configs_options_and_noises_the_quaternion_as_the_position(module, nx, control_noise):
    config = module.Config(method="rddp", eps=0.5, num_samples=4, estimator="zeroth", max_iterations=3)
    solver = config.solver()
    assert isinstance(solver, control.RDDP)
    assert (solver.eps, solver.num_samples, solver.estimator, solver.max_iterations) == (0.5, 4, "zeroth", 3)
    assert solver.control_noise_scale == getattr(config, control_noise)
    # The free body's quaternion gets its position's noise (R-DDP projects it back to unit
    # norm): a far smaller one would starve the zeroth- and alpha-order columns.
    noise = solver.state_noise_scale
    assert len(noise) == nx and noise[3:7] == (noise[0],) * 4 and noise[0] >= 1e-3


@pytest.mark.parametrize("module", [module for module, *_ in EXPERIMENTS])
def test_make_solvers_gives_one_solver_per_method(module):
    solvers = _control.make_solvers(module.Config(geometric_decays=(0.5,)))
    assert tuple(solvers) == ("ddp", "rddp", "rddp-geometric-0.5")
    assert type(solvers["ddp"]) is control.DDP
    assert solvers["rddp"].schedule == "adaptive" and solvers["rddp-geometric-0.5"].decay == 0.5
    assert tuple(_control.make_solvers(module.Config(method="ddp"))) == ("ddp",)


@pytest.mark.parametrize("module", [module for module, *_ in EXPERIMENTS])
@pytest.mark.parametrize("changes, match", [
    ({"method": "sgd"}, "method"), ({"horizon": 1}, "horizon"), ({"seeds": 0}, "seeds"), ({"estimator": "second"}, "estimator"),
    ({"estimator": "alpha", "num_samples": 2}, "num_samples"), ({"geometric_decays": (1.5,)}, "geometric_decays"),
])
def test_configs_reject_what_every_control_experiment_rejects(module, changes, match):
    with pytest.raises(ValueError, match=match):
        module.Config(**changes)


@pytest.mark.parametrize("module, changes", [(control_cube_lift, {"height": 0.2}), (control_pusher, {"target_x": 0.05, "target_yaw": -10.0})])
def test_another_target_changes_only_traced_parameters(module, changes):
    """The targets are cost parameters (arrays), not constants of the cost functions: a problem
    for another target has the same static part, so it reuses the compiled solver steps."""
    import equinox as eqx
    import numpy as np

    (_, first, _), (_, second, _) = module.build_problem(module.Config()), module.build_problem(module.Config(**changes))
    arrays_first, static_first = eqx.partition(first, eqx.is_array)
    arrays_second, static_second = eqx.partition(second, eqx.is_array)
    assert static_first == static_second
    assert not all(np.array_equal(a, b) for a, b in zip(*(jax.tree.leaves(p.params) for p in (arrays_first, arrays_second))))


def test_noise_schedule_options_pick_the_reheating_rule():
    """Each experiment's schedule option reaches the solver it builds."""
    from rsmooth import render, schedules
    from rsmooth.experiments import control_policy, control_policy_pusher, render_pose

    assert control_pusher.Config.quick().solver().schedule == "adaptive"
    assert _control.make_solver("rddp-reheating", control_solo_lift.Config.quick().solver()).schedule == "reheating"
    assert isinstance(control_policy.Config(noise_schedule="reheating").solver("alpha").schedule, schedules.Reheating)
    assert isinstance(control_policy.Config().solver("alpha").schedule, schedules.Geometric)
    pusher = control_policy_pusher.Config(noise_schedule="reheating", sigma_ceiling=1.5).solver("alpha").schedule
    assert isinstance(pusher, schedules.Reheating) and pusher.ceiling == 1.5
    assert isinstance(control_policy_pusher.Config().solver("alpha").schedule, schedules.Constant)
    config = render_pose.Config.quick(noise_schedule="reheating", stall_steps=7)
    fit = render_pose.make_fit(config, "soft", render.cube())
    assert isinstance(fit.schedule, schedules.Reheating) and fit.schedule.stall_patience == 7
    assert isinstance(render_pose.make_fit(render_pose.Config.quick(), "hard", render.cube()).schedule, schedules.Constant)
    with pytest.raises(ValueError, match="noise_schedule"):
        control_policy.Config(noise_schedule="sometimes")
