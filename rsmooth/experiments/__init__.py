"""The experiments: one module each, registered here (see :mod:`rsmooth.experiments._protocol`).

:func:`registry` imports the modules when it is called, not when this package is imported:
an experiment module imports JAX, the simulator and the renderer.
"""

from __future__ import annotations

import importlib

from rsmooth.experiments._protocol import Experiment

# In the order of the command line's help: the smoothing core, simulation, rendering, control.
MODULES = (
    "estimators",
    "perturbed_argmax",
    "null_gradients",
    "solo12_sim",
    "sim_scene",
    "landscape_stiffness",
    "landscape_chaos",
    "landscape_continuity",
    "render_pose",
    "render_reconstruct",
    "control_cube_lift",
    "control_solo_lift",
    "control_pusher",
    "control_panda_push",
    "control_policy",
    "control_policy_pusher",
)


def registry() -> dict[tuple[str, ...], Experiment]:
    """Every experiment, keyed by its command (e.g. ``("control", "cube-lift")``), in the order
    of :data:`MODULES`.

    Raises:
      ValueError: two modules register the same command or output folder.
    """
    experiments: dict[tuple[str, ...], Experiment] = {}
    names: set[str] = set()
    for module in MODULES:
        experiment = importlib.import_module(f"{__name__}.{module}").EXPERIMENT
        if experiment.command in experiments or experiment.name in names:
            raise ValueError(f"rsmooth.experiments.{module}: command {experiment.title!r} or folder {experiment.name!r} taken")
        experiments[experiment.command] = experiment
        names.add(experiment.name)
    return experiments
