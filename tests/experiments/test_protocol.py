"""The experiment protocol: option fields, their checks, and the registry."""

import dataclasses
from typing import Optional

import pytest

from rsmooth.experiments import _protocol, registry
from rsmooth.experiments._protocol import option


@dataclasses.dataclass(frozen=True)
class Config:
    steps: int = option(10, "Steps.", min=1)
    rate: float = option(0.5, "A rate.", min=0.0, max=1.0)
    method: str = option("a", "A method.", choices=("a", "b"))
    scales: tuple[float, ...] = option((1.0,), "Scales.", flag="scale", min=0.0)
    on: bool = option(True, "A switch.", flag="on/off")
    limit: Optional[int] = option(None, "A limit.", min=0)
    sigma: float = option(1.0, "A noise scale.", above=0.0)
    fraction: float = option(0.5, "A fraction.", above=0.0, max=1.0)
    decay: float = option(0.9, "A decay.", min=0.0, below=1.0)

    def __post_init__(self):
        _protocol.check_options(self)


@pytest.mark.parametrize("changes, match", [
    ({"steps": 0}, r"steps \(--steps\) must be in \[1, inf\], got 0"),
    ({"rate": float("nan")}, r"rate \(--rate\) must be a finite number"),
    ({"rate": 1.5}, r"rate \(--rate\) must be in \[0.0, 1.0\]"),
    ({"method": "c"}, r"method \(--method\) must be one of a, b, got 'c'"),
    ({"scales": (1.0, -2.0)}, r"scales \(--scale\) must be in \[0.0, inf\], got -2.0"),
    ({"limit": -1}, r"limit \(--limit\)"),
    ({"sigma": 0.0}, r"sigma \(--sigma\) must be in \(0.0, inf\], got 0.0"),
    ({"sigma": float("inf")}, r"sigma \(--sigma\) must be a finite number"),
    ({"fraction": 0.0}, r"fraction \(--fraction\) must be in \(0.0, 1.0\], got 0.0"),
    ({"decay": 1.0}, r"decay \(--decay\) must be in \[0.0, 1.0\), got 1.0"),
])
def test_check_options_names_the_field_and_its_flag(changes, match):
    with pytest.raises(ValueError, match=match):
        Config(**changes)


def test_none_and_in_range_values_pass():
    assert Config(limit=None, rate=1.0, scales=(), steps=1, sigma=1e-9, fraction=1.0, decay=0.0).steps == 1


def test_flags_and_types_of_fields():
    fields = {field.name: field for field in dataclasses.fields(Config)}
    assert _protocol.flag(fields["steps"]) == "--steps" and _protocol.flag(fields["scales"]) == "--scale"
    assert _protocol.flag(fields["on"]) == "--on" and _protocol.switches(fields["on"]) == ("--on", "--off")
    assert _protocol.switches(fields["steps"]) == ("--steps", "--no-steps")
    kinds = {name: _protocol.element_type(_protocol.field_type(Config, field)) for name, field in fields.items()}
    assert kinds["scales"] == ("tuple", float) and kinds["limit"] == ("optional", int) and kinds["rate"] == ("plain", float)


def test_registry_lists_every_experiment_once_in_the_help_order():
    experiments = registry()
    assert list(experiments) == [
        ("experiment", "estimators"), ("experiment", "perturbed-argmax"), ("experiment", "null-gradients"),
        ("sim", "solo12"), ("sim", "scene"), ("experiment", "stiffness"), ("experiment", "chaos"), ("experiment", "continuity"), ("render", "pose"), ("render", "reconstruct"), ("control", "cube-lift"),
        ("control", "solo-lift"), ("control", "pusher"), ("control", "panda-push"), ("control", "policy"),
        ("control", "policy-pusher"),
    ]
    for command, experiment in experiments.items():
        assert experiment.command == command and experiment.title == " ".join(command)
        assert experiment.help and "metrics.json" in experiment.metrics_doc
        # every Config builds at both sizes, and checks its options
        experiment.config()
        experiment.config.quick()
        for field in dataclasses.fields(experiment.config):
            assert field.metadata.get("help"), (command, field.name)  # declared with option()
