"""Benchmarks: `python -m benchmarks NAME`. Each prints absolute times and ratios measured in
one process (medians of repeated runs) and states the machine."""
