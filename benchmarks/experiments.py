"""The experiments' scientific results as one record: `python -m benchmarks experiments --metrics
ROOT --profile quick|default --json DIR` reads ``ROOT/NAME/metrics.json`` for each experiment of
:data:`EXPERIMENTS` (the output folders of `rsmooth experiment ...`) and writes
``DIR/experiments.json`` (a `benchmarks._record` record, area "experiments"), whose results are
``{"profile": ..., "experiments": {NAME: {"metrics": {...}, "date": "YYYY-MM-DD"} or null}}``:
null where the file is missing (the page shows "not measured"). The metrics are copied as the
experiment wrote them (the keys of each experiment module's METRICS_DOC), without their curves:
a list of more than :data:`LONGEST_LIST` entries (a landscape sampled on a grid) is left out,
since the page shows numbers, not curves, and the record would grow by megabytes.
"""

from __future__ import annotations

import datetime
import json
import os
import pathlib

from benchmarks import _record

# The output folders of the experiments, in the order of `rsmooth.experiments.MODULES`.
EXPERIMENTS = (
    "estimators",
    "perturbed-argmax",
    "null-gradients",
    "solo12",
    "stiffness",
    "chaos",
    "continuity",
    "render-pose",
    "render-reconstruct",
    "cube-lift",
    "solo-lift",
    "pusher",
    "panda-push",
    "policy",
    "policy-pusher",
)


LONGEST_LIST = 64


def without_curves(value):
    """`value` with every list longer than :data:`LONGEST_LIST` (in any dict or list) left out."""
    if isinstance(value, dict):
        return {key: without_curves(item) for key, item in value.items()
                if not (isinstance(item, list) and len(item) > LONGEST_LIST)}
    if isinstance(value, list):
        return [without_curves(item) for item in value if not (isinstance(item, list) and len(item) > LONGEST_LIST)]
    return value


def collect(root: str | os.PathLike) -> dict:
    """``{NAME: {"metrics": ..., "date": ...} or None}`` for every experiment of :data:`EXPERIMENTS`."""
    found: dict = {}
    for name in EXPERIMENTS:
        path = pathlib.Path(root) / name / "metrics.json"
        if not path.is_file():
            found[name] = None
            continue
        date = datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.timezone.utc).strftime("%Y-%m-%d")
        found[name] = {"metrics": without_curves(json.loads(path.read_text())), "date": date}
    return found


def main(root: str, directory: str, profile: str) -> dict:
    found = collect(root)
    for name, entry in found.items():
        print(f"{name:>20}: {'collected' if entry else 'not measured (no metrics.json)'}")
    rec = _record.record("experiments", {"profile": profile, "experiments": found}, command=_record.command_line(),
                         options={"profile": profile})
    print(f"wrote {_record.write(directory, rec)}")
    return rec
