"""`python -m benchmarks NAME [--repeats N] [--quick] [--solo12-model FILE]`."""

import argparse
import importlib
import inspect
import os

NAMES = ("core", "render", "sim", "control")
# A control iteration takes up to seconds: fewer repeats there.
DEFAULT_REPEATS = {"control": 5}


def main():
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("name", choices=NAMES)
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per measurement (median); default 30, control 5")
    parser.add_argument("--quick", action="store_true", help="a reduced size (the benchmarks that have one: sim, control)")
    parser.add_argument(
        "--solo12-model", metavar="FILE",
        help="sim, control: a Solo-12 model file written by rsmooth.sim.save_model, used instead of loading the URDF "
        "through Pinocchio (for machines without it; the SRDF's standing posture is still read from example-robot-data's files)",
    )
    args = parser.parse_args()
    if args.solo12_model:
        from benchmarks._timing import SOLO12_MODEL_VARIABLE

        if not os.path.isfile(args.solo12_model):
            parser.error(f"--solo12-model: no file {args.solo12_model}")
        os.environ[SOLO12_MODEL_VARIABLE] = os.path.abspath(args.solo12_model)
    from rsmooth import _xla

    if args.name == "render":
        _xla.apply_cpu_defaults()  # the settings `rsmooth render` runs with (rsmooth._xla)
    benchmark = importlib.import_module(f"benchmarks.{args.name}").main
    options = {"repeats": args.repeats if args.repeats is not None else DEFAULT_REPEATS.get(args.name, 30)}
    if args.quick:
        if "quick" not in inspect.signature(benchmark).parameters:
            parser.error(f"the {args.name} benchmark has no --quick")
        options["quick"] = True
    benchmark(**options)


if __name__ == "__main__":
    main()
