"""The experiments' scientific results as one record: `python -m benchmarks experiments --metrics
ROOT --profile quick|default --json DIR` reads ``ROOT/NAME/metrics.json`` for each experiment of
:data:`EXPERIMENTS` (the output folders of `rsmooth experiment ...`) and writes
``DIR/experiments.json`` (a `benchmarks._record` record, area "experiments"), whose results are
``{"profile": ..., "experiments": {NAME: {"metrics": {...}, "date": "YYYY-MM-DD", "profile": ...}
or null}}``: null where the file is missing (the page shows "not measured"). With
``--keep-missing``, an experiment without a metrics.json under ROOT keeps its entry of the
record already in DIR, with that entry's profile, date and machine (e.g. the experiments that
run at their default size on a CPU beside one whose default size needs a GPU, kept at its
quick size). The metrics are copied as the
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


def collect(root: str | os.PathLike, profile: str) -> dict:
    """``{NAME: {"metrics": ..., "date": ..., "profile": profile} or None}`` for every experiment
    of :data:`EXPERIMENTS`."""
    found: dict = {}
    for name in EXPERIMENTS:
        path = pathlib.Path(root) / name / "metrics.json"
        if not path.is_file():
            found[name] = None
            continue
        date = datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.timezone.utc).strftime("%Y-%m-%d")
        found[name] = {"metrics": without_curves(json.loads(path.read_text())), "date": date, "profile": profile}
    return found


def kept_entries(found: dict, previous: dict) -> dict:
    """`found` with each missing experiment's entry taken from the `previous` record, stamped
    with that record's profile and machine where the entry does not name its own."""
    results = previous.get("results") or {}
    old = results.get("experiments") or {}
    kept = dict(found)
    for name, entry in found.items():
        if entry is None and old.get(name):
            kept[name] = {"profile": results.get("profile"), "machine": previous.get("machine"), **old[name]}
    return kept


def main(root: str, directory: str, profile: str, keep_missing: bool = False) -> dict:
    found = collect(root, profile)
    previous_path = pathlib.Path(directory) / "experiments.json"
    if keep_missing and previous_path.is_file():
        found = kept_entries(found, json.loads(previous_path.read_text()))
    for name, entry in found.items():
        status = "not measured (no metrics.json)" if entry is None else (
            "collected" if entry.get("profile") == profile and "machine" not in entry
            else f"kept from the previous record ({entry.get('profile')}, {entry.get('date')})")
        print(f"{name:>20}: {status}")
    rec = _record.record("experiments", {"profile": profile, "experiments": found}, command=_record.command_line(),
                         options={"profile": profile})
    print(f"wrote {_record.write(directory, rec)}")
    return rec
