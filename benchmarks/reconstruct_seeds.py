"""Render reconstruct's scores over seeds: the default command's targets (cube, torus, Solo-12
upper leg) for several `--seed` values at once, per method and Laplacian weight.

`python -m benchmarks.reconstruct_seeds [--seeds 0 1 ...] [--runs METHOD:WEIGHT ...]
[--steps N] [--samples M] [--baseline B] [--json FILE]`. Every (seed, target) pair is one
problem of one vmapped batch, with the keys `rsmooth render reconstruct --seed S` draws for it,
so a row reproduces that command's scores for its method: exactly on a CPU (seed 0 checked, in
a batch of 8 seeds), up to rounding on a GPU, whose scatter-adds sum in no fixed order (the
optimization is chaotic at the thin upper leg: there soft rendering, which draws nothing,
scatters by 0.03 over seeds through that rounding alone). A quality
sweep, not a timing: a GPU takes ~16 s per run of 8 seeds, two CPU cores ~1 min per seed and
run. Prints a row per seed and the mean (with its standard error) per target and run. Float32,
as the command runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._timing import machine
from rsmooth import render
from rsmooth.experiments import render_reconstruct as rr


def main(seeds=(0, 1, 2, 3), runs=("perturbed-gaussian:30", "soft:30"), steps: int | None = None, json_path: str | None = None,
         **changes) -> list[dict]:
    """`changes`: other fields of render_reconstruct.Config (num_samples, baseline, ...)."""
    print(f"machine: {machine()}")
    base = dataclasses.replace(rr.Config(), **changes, **({} if steps is None else {"steps": steps}))
    names = [rr._name(t) for t in base.targets]
    count = len(names)
    targets = rr.stack_meshes([rr.load_target(t) for t in base.targets])
    template = render.icosphere(base.subdivisions, base.template_radius)
    cams = rr.cameras(base)
    # as rr.run renders the targets and scores the reconstructions (hard renders draw nothing:
    # any key)
    images, silhouettes = rr.target_images_and_silhouettes(base, jax.random.key(0), targets, template, cams)
    target_alpha = jnp.concatenate([images.alpha] * len(seeds))
    target_rgb = jnp.concatenate([images.rgb] * len(seeds))
    print(f"targets {names}, seeds {list(seeds)}, {base.steps} steps, {base.views} views, {base.num_samples} samples per pixel, "
          f"baseline {base.baseline!r}\n")
    rows = []
    for run in runs:
        method, weight = run.split(":")
        config = dataclasses.replace(base, laplacian_weight=float(weight))
        _, init, step = rr.make_solver(config, method, template, cams)
        state = init(jnp.zeros((len(seeds) * count,) + template.vertices.shape, template.vertices.dtype))
        # rr.run: k_metrics, k_run = split(key(seed)); the method's run key folds in its index
        splits = [jax.random.split(jax.random.key(s)) for s in seeds]
        run_keys = [jax.random.fold_in(k_run, rr.METHODS.index(method)) for _, k_run in splits]
        start = time.perf_counter()
        for t in range(config.steps):
            keys = jnp.concatenate([jax.random.split(jax.random.fold_in(k, t), count) for k in run_keys])
            state, loss, _ = step(state, keys, target_alpha, target_rgb)
        jax.block_until_ready(loss)
        seconds = time.perf_counter() - start
        first = len(rows)
        for i, seed in enumerate(seeds):
            offsets = state[0][i * count:(i + 1) * count]
            scores = rr._scores(config, splits[i][0], names, targets, template, images.alpha, offsets, silhouettes(offsets))
            row = {"method": method, "laplacian_weight": float(weight), "num_samples": config.num_samples, "baseline": config.baseline,
                   "seed": seed, **scores}
            rows.append(row)
            print(json.dumps({"run": run, "seed": seed, **{n: round(scores[n]["iou_3d"], 4) for n in names}}))
        means = []
        for n in names:
            iou = np.array([r[n]["iou_3d"] for r in rows[first:]])
            error = iou.std(ddof=1) / np.sqrt(len(iou)) if len(iou) > 1 else float("nan")
            means.append(f"{n} {iou.mean():.3f} ± {error:.3f}")
        print(f"== {run}: 3D IoU " + ", ".join(means) + f" ({seconds:.0f} s, compilation included)\n")
        if json_path:
            with open(json_path, "w") as f:
                json.dump(rows, f, indent=1)
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--runs", nargs="+", default=["perturbed-gaussian:30", "soft:30"], help="METHOD:LAPLACIAN_WEIGHT")
    parser.add_argument("--steps", type=int, help="Adam steps (default: the command's)")
    parser.add_argument("--json", dest="json_path", help="write the rows there, after each run")
    parser.add_argument("--samples", type=int, help="samples per pixel of the perturbed renderer (default: the command's)")
    parser.add_argument("--baseline", choices=("hard", "leave-one-out"), help="the perturbed estimator's baseline (default: the command's)")
    args = parser.parse_args()
    from rsmooth import _xla

    _xla.apply_cpu_defaults(render=True)  # the settings `rsmooth render` runs with, before JAX starts
    changes = {name: value for name, value in (("num_samples", args.samples), ("baseline", args.baseline)) if value is not None}
    main(tuple(args.seeds), tuple(args.runs), args.steps, args.json_path, **changes)
