"""`python -m benchmarks NAME [--repeats N]`."""

import argparse
import importlib

NAMES = ("core", "render", "sim")


def main():
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("name", choices=NAMES)
    parser.add_argument("--repeats", type=int, default=30, help="timed calls per measurement (median)")
    args = parser.parse_args()
    importlib.import_module(f"benchmarks.{args.name}").main(repeats=args.repeats)


if __name__ == "__main__":
    main()
