"""Benchmarks: `python -m benchmarks NAME`. Each prints absolute times and ratios measured in
one process (medians of repeated runs) and states the machine; with `--json DIR` it also writes
a record (`benchmarks._record`) that `python -m benchmarks render-results` turns into
benchmarks/RESULTS.md (`benchmarks.results_page`). The committed records are in
benchmarks/results/cpu and benchmarks/results/gpu."""
