"""`python -m benchmarks NAME [--repeats N] [--quick] [--solo12-model FILE] [--json DIR]`.

NAME is an area (core, render, sim, boxes, throughput, control, startup, scale, schedules, alpha-rules), `all` (each area in its own process, one after
the other), `render-results` (benchmarks/RESULTS.md from the JSON records of
benchmarks/results/) or `experiments` (the experiments' metrics.json files into one record).
With --json DIR, each area also writes DIR/AREA.json (benchmarks._record; alpha-rules: DIR/alpha_rules.json).
"""

import argparse
import importlib
import inspect
import os
import subprocess
import sys
import time

NAMES = ("core", "render", "sim", "boxes", "throughput", "control", "startup", "scale", "schedules", "alpha-rules")
# A control iteration takes up to seconds, a startup run tens of seconds: fewer repeats there;
# scale starts a process per device count and times estimates of up to 256 rollouts; schedules
# runs experiments (success rates, no timing repeats), and so does alpha-rules.
DEFAULT_REPEATS = {"throughput": 10, "control": 5, "startup": 3, "scale": 5, "schedules": 1, "alpha-rules": 1}


def _transform(name: str):
    """The area's results as they go into its JSON record (control's have tuple keys)."""
    if name == "control":
        from benchmarks.control import json_results

        return json_results
    return None


def run_area(parser, args) -> None:
    if args.solo12_model:
        from benchmarks._timing import SOLO12_MODEL_VARIABLE

        if not os.path.isfile(args.solo12_model):
            parser.error(f"--solo12-model: no file {args.solo12_model}")
        os.environ[SOLO12_MODEL_VARIABLE] = os.path.abspath(args.solo12_model)
    from rsmooth import _xla

    _xla.apply_cpu_defaults(render=args.name == "render")  # the settings `rsmooth` runs with (rsmooth._xla)
    module = args.name.replace("-", "_")  # the module, and the record's area
    benchmark = importlib.import_module(f"benchmarks.{module}").main
    options = {"repeats": args.repeats if args.repeats is not None else DEFAULT_REPEATS.get(args.name, 30)}
    if args.quick:
        if "quick" not in inspect.signature(benchmark).parameters:
            parser.error(f"the {args.name} benchmark has no --quick")
        options["quick"] = True
    from benchmarks import _record

    _record.run_and_record(module, benchmark, command=_record.command_line(), options=options, directory=args.json,
                           transform=_transform(args.name))


def run_all(args) -> int:
    """Each area in its own process (their JAX settings differ: float64 for sim and control, the
    renderer's XLA flags), with a time limit each; an area that fails or runs out of time writes
    no record (the page shows it as not measured). Returns the number of areas that failed."""
    failed = []
    for name in NAMES:
        command = [sys.executable, "-m", "benchmarks", name]
        if args.repeats is not None:
            command += ["--repeats", str(args.repeats)]
        if args.quick and name in ("sim", "boxes", "throughput", "control", "startup", "scale", "schedules", "alpha-rules"):
            command.append("--quick")
        if args.solo12_model:
            command += ["--solo12-model", args.solo12_model]
        if args.json:
            command += ["--json", args.json]
        print(f"=== {name}: python {' '.join(command[1:])} (limit {args.timeout:.0f} s)", flush=True)
        start = time.perf_counter()
        try:
            rc = subprocess.run(command, timeout=args.timeout).returncode
        except subprocess.TimeoutExpired:
            rc = "timed out"
        print(f"=== {name}: {'ok' if rc == 0 else rc} after {time.perf_counter() - start:.0f} s\n", flush=True)
        if rc != 0:
            failed.append(name)
    if failed:
        print(f"no record for: {', '.join(failed)}")
    return len(failed)


def main():
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", choices=NAMES + ("all", "render-results", "experiments"))
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per measurement (median); default 30, control 5")
    parser.add_argument("--quick", action="store_true", help="a reduced size (the benchmarks that have one: sim, boxes, throughput, control, startup, scale, schedules, alpha-rules)")
    parser.add_argument(
        "--solo12-model", metavar="FILE",
        help="sim, control: a Solo-12 model file written by rsmooth.sim.save_model, used instead of loading the URDF "
        "through Pinocchio (for machines without it; the SRDF's standing posture is still read from example-robot-data's files)",
    )
    parser.add_argument("--json", metavar="DIR", help="also write the results to DIR/NAME.json (for experiments: DIR/experiments.json)")
    parser.add_argument("--timeout", type=float, default=3600.0, help="all: seconds each area may run (default 3600)")
    parser.add_argument("--metrics", metavar="ROOT", help="experiments: the folder of the experiments' outputs (ROOT/NAME/metrics.json)")
    parser.add_argument("--profile", choices=("quick", "default"),
                        help="experiments: the size the experiments ran at (--quick or the default)")
    parser.add_argument("--keep-missing", action="store_true",
                        help="experiments: keep the existing record's entry of each experiment without a metrics.json "
                        "under ROOT (with its own profile, date and machine)")
    parser.add_argument("--results", metavar="DIR", help="render-results: the records' folder (default benchmarks/results)")
    parser.add_argument("--output", metavar="FILE", help="render-results: the page (default benchmarks/RESULTS.md; - for stdout)")
    args = parser.parse_args()
    if args.name == "all":
        sys.exit(1 if run_all(args) else 0)
    if args.name == "render-results":
        from benchmarks import results_page

        results_page.main(results=args.results, output=args.output)
        return
    if args.name == "experiments":
        if not args.metrics or not args.json or not args.profile:
            parser.error("experiments needs --metrics ROOT, --profile quick|default and --json DIR")
        from benchmarks import experiments

        experiments.main(args.metrics, args.json, args.profile, keep_missing=args.keep_missing)
        return
    run_area(parser, args)


if __name__ == "__main__":
    main()
