"""Experiment: recover a mesh's pose from one RGB image with differentiable renderers.

The task of Le Lidec, Laptev, Schmid, Carpentier, "Differentiable rendering with perturbed
optimizers", NeurIPS 2021 (pose estimation experiment): a target image is rendered (hard z-buffer) at a random
rotation; the optimization starts from that rotation composed with a rotation of a fixed
angle (`init_errors_deg`) about a random axis, and minimizes the mean squared RGB error between
the rendered and the target images with Adam (optax), for each renderer:

* ``perturbed-gaussian``, ``perturbed-cauchy``: the perturbed renderer (Gaussian or Cauchy
  noise on signed distances, Gumbel noise on depths), with the paper's adaptive noise
  decrease (:class:`rsmooth.schedules.Adaptive`): an exponential average of
  d loss / d (noise scale) is kept, and when it is positive, sigma and gamma shrink by
  `decay_factor`;
* ``soft``: SoftRas-like sigmoid coverage and softmax aggregation, same schedule (its
  derivative with respect to the scale is exact);
* ``hard``: the z-buffer; only shading and colour interpolation give it a gradient.

Independent problems are batched with `jax.vmap` (at most `batch_size` at a time, which bounds
the memory, in chunks of equal size), spread over the devices when there are several
(:mod:`rsmooth.parallel`). The mesh's vertices are coloured by their
position, so that symmetric shapes (cube, sphere) have a unique pose. The rotation is
parametrized as R = exp([delta]) R_init with delta in R^3 starting at 0; the translation, when
optimized, starts off by `init_translation` in a random direction.

The smoothed renderers also smooth the loss over rotations (`pose_noise_deg`): each step takes
its gradient at a randomly rotated pose (delta + eps z, z ~ N(0, I_3)), eps shrinking with the
renderer's noise scale and linearly to 0 at the last step (or at `pose_noise_until` x steps),
so the run ends on the unsmoothed loss (as R-DDP does). Image-space smoothing alone leaves a
rotated cube in the basin of a pose with the same silhouette; smoothing over poses lets it out
(rates measured: `Config.pose_noise_deg`).
The default command with 100 steps on the cube (32 problems per angle, seed 7, Gaussian and
soft): Gaussian solves 100 / 90.6 / 43.8 % from 20 / 50 / 80 deg (without pose smoothing: 97 /
50 / 22), soft 100 / 87.5 / 43.8. With 200 steps (the default since: the pose noise and the
learning rate decay twice as slowly), each angle run alone (`--init-error A --problems 32
--seed 7`): Gaussian 96.9 / 90.6 / 65.6 % (100 steps: 93.8 / 81.3 / 43.8), soft 68.8 % at 80
deg; the paper's cube: 93 / 84 / 67 (perturbed), 84 / 75 / 55 (SoftRas). The default command
(100 problems per angle, 200 steps, seed 0, each angle run alone with ``--init-error A``, about
an hour per angle on one CPU core): % solved at 20 / 50 / 80 deg, perturbed Gaussian 96 / 85 /
59, perturbed Cauchy 99 / 90 / 59, soft 99 / 82 / 66, hard 73 / 50 / 41 (mean final errors at
80 deg 30.4, 29.1, 28.2, 30.0 deg; the failures mostly end near 90 deg, the cube turned a
quarter about an axis: a pose whose silhouette matches). At 20 and 50 deg the perturbed
renderers beat both of the paper's rows, at 80 deg they beat SoftRas's 55 but not the paper's
perturbed 67 (binomial standard error about 5 points at 100 problems); which problems are
solved varies between methods (at 80 deg 38 were solved by all three smoothed ones, 80 by at
least one). These rates were measured with 8 samples per pixel; with 16 (the default since) the
perturbed Gaussian renderer solves 97 / 91 / 73 % and beats the paper's rows and our soft
renderer at 50 and 80 deg; perturbed Cauchy 100 / 89 / 57 % (no gain at 80 deg; benchmarks/RESULTS.md). So a
failed run is largely the noise's luck, and `restarts` reruns, with fresh
noise, the problems whose best hard render stays far from the target (a test on the image, not
on the ground truth): with two restarts at 80 deg (100 problems, seed 0, one H200 GPU, two
minutes for both methods) Gaussian solves 75 % (its first runs 57) and soft 80 % (67), at 1.76
and 1.60 runs per problem. On the unseen panda
link4 mesh (8 problems, seed 31, 100 steps) pose smoothing does not help: Gaussian 87.5 / 50 %
from 20 / 50 deg (without: 100 / 50; the 20-deg miss ends at 11 deg, the others at 0.3-3.5
deg instead of under 1), soft 87.5 / 25; neither a noise-free end (the pose noise at 0 from
75 % of the steps: 100 / 37.5 %, median 2.5 deg at 20; from 50 %: 87.5 / 50 %, median 2.0)
nor Adam's b2 = 0.99 (87.5 / 50 %, median 1.2) brings the solved ones under 1 deg.
More samples at the noise floor do (`sample_growth`, the paper's "samples may double"): the
same mesh from 20 deg, 16 problems, seed 31, 200 steps, one CPU core each (benchmarks/RESULTS.md):
16 samples per pixel throughout solve 87.5 % with a median final error of 0.79 deg; doubling
them at each noise decrease up to 64 solves 93.75 % (one problem more, within noise) with a
median of 0.27 deg, soft rendering's precision (0.27, session 24), for 2.6x the time; 32
throughout: 87.5 %, median 0.32 deg, 1.5x the time. From 50 deg: 81.25 % (median 0.47 deg)
with 16 throughout, 87.5 % (0.36 deg) with growth; soft 69 % (0.43 deg). On by default since
session 31 (growth 2 up to 64 samples; benchmarks/RESULTS.md): on four unseen panda meshes (16 to
32 problems each, 20 and 50 deg) it solves 142 of 160 problems against soft's 130, nearly as
near the truth (median error of the solved 0.15-0.83 deg, soft's 0.15-0.33; with 16 samples
throughout the perturbed renderer had trailed soft by 10 points on panda link2); on the cube
(50 problems of the default command's, seed 0) 96 / 86 / 77 % from 20 / 50 / 80 deg (80: the
first 30) against 96 / 80 / 70 with 16 throughout, losing none. Near the solution most of the
gradient's variance on the cube is the pose noise's, not the image's (`antithetic_pose`), and
the image noise lives at the few pixels near a silhouette edge: since session 32 a step's
renders come at two opposite poses (+eps z, -eps z), and since session 33 its perturbed renders
draw only the pixels their noise may change (`pixel_chunk`; the others, whose every sample is
the hard pixel, from one hard render per pose: the same estimate). The cube from 20 / 50 / 80
deg, 50 problems each: 96 / 86 / 72 % (one render per step: 96 / 80 / 68); with session 33's
chunks, on all 100 of the default problems, 98 / 87 / 77 % from 20 / 50 / 80 deg (the paper: 93 /
84 / 67 perturbed, 84 / 75 / 55 SoftRas), at 0.09-0.10 s per problem-step against 0.16 (session 32) and
0.27 (session 31's four whole renders). A run costs about the time of one whole render
per step (`--sample-growth 1` turns growth off; benchmarks/RESULTS.md, sessions 32-33).

Each problem reports the iterate whose hard-rendered image is closest to the target
(`keep_best`, one hard render per step, ~3 % of a perturbed step on the cube), not the last one: at the
noise floor Adam keeps moving. Measured on an unseen mesh (example-robot-data's panda link4
collision mesh, 8 problems, seed 31, perturbed Gaussian): solved 100 / 50 % from 20 / 50 deg
either way, mean error 4.1 -> 1.4 deg and 27.0 -> 17.5 deg (`last_*` keys: the last iterate).
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from rsmooth import noise, parallel, render, schedules, viz
from rsmooth._xla import matmul
from rsmooth.estimators import check_baseline

METRICS_DOC = """metrics.json keys: for each method (perturbed-gaussian, perturbed-cauchy, soft, hard),
a dict keyed by the initial rotation error in degrees (as a string) holding solved_pct (percent of
problems whose final rotation error is below success_deg), mean_error_deg and std_error_deg (final
rotation error over problems), median_error_deg, final_errors_deg (per problem; "final" is the
iterate whose hard-rendered image was closest to the target when keep_best, the last one
otherwise; with restarts, of the run whose image was closest), last_solved_pct and
last_mean_error_deg (the last iterate's), first_run_solved_pct (solved by the first run alone,
before restarts), runs_per_problem (mean runs per problem, 1 without restarts: the compute
spent), final_losses and initial_losses (per problem, the mean squared RGB error of the hard
image of the reported and of the initial pose to the target), final_sigma (mean
final noise scale factor), final_num_samples (mean final samples per pixel of the perturbed
renderers, in all the renders of a step: num_samples unless sample_growth), mean_translation_error (distance of the final translation to the true
one, 0 unless optimize_translation), seconds_per_step (wall time of one batched Adam step of
batch_size problems, first steps excluded; null when there is none) and seconds_per_problem_step
(the same per problem); also methods, init_errors_deg, success_deg, problems, batch_size (the
problems per chunk actually run: at most the config's, so that chunks are of equal size), steps, image_size, mesh, num_faces, faces_per_pixel, num_samples (of the perturbed renderers), sample_growth, max_samples, pixel_chunk and antithetic_pose,
cull_backfaces (whether faces seen from behind were dropped: by default when the mesh is closed) and
interior_edges (whether coverage was smoothed across every triangle edge, as in the paper),
keep_best, pose_noise_deg (the initial rotation noise of the pose smoothing, 0 when off) and
pose_noise_until (the fraction of the steps at which that noise has faded to 0), restarts,
restart_loss, average_decay and baseline (see Config)."""

METHODS = ("perturbed-gaussian", "perturbed-cauchy", "soft", "hard")


@dataclasses.dataclass(frozen=True)
class Config:
    mesh: str = "cube"  # cube, icosphere, torus, or a mesh file path
    image_size: int = 128
    init_errors_deg: tuple[float, ...] = (20.0, 50.0, 80.0)
    problems: int = 100  # per initial error (the paper's count); --problems for fewer
    batch_size: int = 25  # problems optimized at once (vmapped); the rest wait their turn
    # Adam steps per problem: 200, not 100, for the 80-deg problems (see the module docstring:
    # the cube at 80 deg, perturbed Gaussian, 65.6 % solved against 43.8 with 100 steps)
    steps: int = 200
    methods: tuple[str, ...] = METHODS
    learning_rate: float = 0.05
    # coverage noise scale in pixels at image_size 128 (scaled with the size). A wider Gaussian
    # does not close its gap to soft at 80 deg (the logistic's std is 1.8x its scale): the
    # default 100 problems at 80 deg (seed 0, perturbed Gaussian) solve 59 / 56 / 63 % with
    # sigma 3 / 4.5 / 6, within the binomial noise (about 5 points); soft: 66
    sigma: float = 3.0
    gamma: float = 0.02  # depth temperature (normalized inverse depth)
    # More samples do close it: 59 / 73 / 83 % at 80 deg with 8 / 16 / 32 samples on the same
    # problems, at 1x / 1.7x / 2.5x the step time on the CPU; 16 also solve 97 / 91 % from 20 /
    # 50 deg against 96 / 85 with 8 (benchmarks/RESULTS.md, session 24), hence the default
    num_samples: int = 16
    # the "samples may double": at each noise decrease the number of renders averaged
    # per step is multiplied by this (1: off), each of num_samples samples per pixel, up to
    # max_samples samples per pixel in all. On by default since session 31: it removes most of
    # the Monte-Carlo noise of the gradient at the noise floor, which left problems unsolved on
    # meshes the tests have not seen (see the module docstring). The price: after the first noise
    # decreases (within ~50 of the 200 steps) a step averages up to max_samples / num_samples
    # renders (of the random pixels alone, pixel_chunk): about the time of one whole render per
    # step over a run of the default command (~3x with whole renders)
    sample_growth: int = 2
    max_samples: int = 64
    # the perturbed renders draw only the pixels that their noise may change (those whose
    # Renderer.uncertainty, an upper bound on the probability that a sample differs from the hard
    # pixel, exceeds 1e-12), in chunks of this fraction of the image's pixels, as many as they
    # fill; the others, whose value and derivative are the hard pixel's in every sample, come
    # from one hard render per pose. The same estimate as whole renders (to rounding, a test), at
    # less cost: 42 / 20 / 10 % of the cube's pixels are random at noise scale 1 / 0.5 / 0.25
    # (sigma 3 / 1.5 / 0.75 px). 1: whole perturbed renders. One problem's step, cube (both cores,
    # benchmarks/RESULTS.md, session 33): first steps 23.4 ms, at the sample cap 35.6, against
    # 32.4 / 93.1 ms with whole renders
    pixel_chunk: float = 0.125
    # a step's pose noise (pose_noise_deg) in antithetic pairs, +eps z and -eps z, rather than
    # independent draws: the first-order terms of the pose noise, most of the gradient's
    # variance near the solution on the cube, cancel in their mean (the cube 0.2 deg from the
    # truth at the noise floor, 48 draws: gradient std on the worst axis 2.7e-3 with two
    # antithetic renders, 9.8e-3 with two independent ones, 7.4e-3 with four, 14.4e-3 with one)
    antithetic_pose: bool = True
    # candidates per pixel: since the candidate-selection fix of session 9, 4 suffice for the
    # torus (8 problems, seed 11, seamless: the same % solved at 20/50 deg as with 8, a step
    # 1.3-1.6x faster) as for the culled cube (session 8: the same solve rates, a step 2x faster)
    faces_per_pixel: int = 4
    faces_per_tile: int = 64  # raise for dense meshes (see rsmooth.render.rasterize)
    # drop faces seen from behind (rsmooth.render.Renderer); None: when the mesh is closed and
    # outward-oriented (rsmooth.render.is_closed_outward), where the hard image is the same
    cull_backfaces: bool | None = None
    # smooth coverage across every triangle edge, as the paper's perturbed renderer and SoftRas
    # do (seams along shared edges), rather than the silhouette only (rsmooth.render.Renderer).
    # Off: on a torus of small faces (8 problems per angle, seed 11, % solved at 20/50 deg)
    # the seams cost Gaussian 100/87.5 -> 50/87.5 and soft 100/100 -> 75/75; on the cube
    # (16 problems, seed 5, before the candidate-selection fix of session 9) they helped:
    # Gaussian 93.75/68.75/18.75 without, 100/75/37.5 % with at 20/50/80 deg
    interior_edges: bool = False
    decay_factor: float = 2.0
    momentum: float = 0.9
    noise_floor: float = 0.05  # smallest noise scale factor
    patience: int = 10  # least number of steps between two noise decreases
    final_learning_rate: float = 0.1  # fraction of learning_rate reached at the end (cosine decay)
    optimize_translation: bool = False
    init_translation: float = 0.2
    camera_distance: float = 4.0
    fov: float = 40.0
    success_deg: float = 10.0
    # report each problem's iterate whose hard-rendered image is closest to the target (mean
    # squared RGB error, one hard render per step), not the last one: the target image is the
    # optimizer's own data, and at the noise floor Adam may walk away from a solved pose
    keep_best: bool = True
    # randomized smoothing of the loss over rotations as well as in the image: each step takes
    # the gradient at delta + eps z, z ~ N(0, I_3), eps = pose_noise_deg (in radians) times the
    # noise schedule's scale factor (it shrinks with sigma and gamma): a one-sample first-order
    # estimate of the gradient of the pose-smoothed loss; eps also fades linearly to 0 at the last
    # step. Not for the hard renderer (no schedule: it stays the unsmoothed baseline). 0 turns it
    # off. Cube, perturbed Gaussian, 100 steps, 32 problems per angle (in batches of 25 and 7,
    # before chunks were balanced: float32 rounding moves a few %), seed 7 (each angle alone),
    # % solved at 20 / 50 / 80 deg: 96.9 / 65.6 / 21.9 with 0, 93.8 / 81.3 / 43.8 with 25
    # (without the fade: 90.6 / 87.5 / 46.9; 40 without the fade: 50 deg 78.1, 80 deg 50.0;
    # 10: 50 deg 75.0); the paper: 93 / 84 / 67 (perturbed), 84 / 75 / 55 (SoftRas)
    pose_noise_deg: float = 25.0
    # the fraction of the steps at whose end the pose noise has faded to 0 (1: the last step);
    # the steps after it descend the image-smoothed loss alone. The cube at 80 deg (32 problems,
    # seed 7, 100 steps, Gaussian): 43.75 % solved with 0.75 as with 1; the panda: see above
    pose_noise_until: float = 1.0
    # problems whose reported pose renders (hard) further from the target than restart_loss times
    # the initial pose's image (mean squared RGB error: no ground truth used) are run again from
    # their initial pose with fresh noise, up to `restarts` more runs each; each problem reports
    # the run whose image is closest to the target. Cube, 80 deg, Gaussian, 32 problems (seed 7):
    # the solved problems' ratio was at most 0.014, the failed ones' at least 0.245. 0: the
    # paper's protocol, one run per problem. The default 100 problems at 80 deg (seed 0, on one
    # H200 GPU, benchmarks/RESULTS.md) with restarts=2: Gaussian 57 -> 75 % solved (1.76 runs
    # per problem), soft 67 -> 80 % (1.60)
    restarts: int = 0
    restart_loss: float = 0.05
    # with keep_best, also consider an exponential average of the iterates, decay `average_decay`
    # per step (Polyak-Ruppert averaging; 0: off), one more hard render per step: at the noise
    # floor the perturbed gradient's Monte-Carlo noise makes Adam walk around the solution, and
    # the walk's average is nearer it. The reported hard loss can only go down (the candidates
    # are a superset). Panda link4, 16 problems, seed 31, perturbed Gaussian (benchmarks/RESULTS.md,
    # session 27): median final error 0.69 -> 0.48 deg from 20 deg with 0.97 (0.49 with 0.9),
    # 0.58 -> 0.54 from 50, solved rates unchanged; soft (exact gradient) about unchanged (median
    # 0.23 / 0.25, one problem 1.05 -> 0.52 deg). Off by default: the measured runs are without it
    average_decay: float = 0.0
    # the perturbed estimator's baseline (rsmooth.render.Renderer): True, the hard pixel (Le
    # Lidec et al.'s); "leave-one-out", the mean of the pixel's other samples (lower variance at
    # the edge pixels, where the hard pixel is 0 or 1 and the smoothed one in between)
    baseline: bool | str = True
    gif_every: int = 2

    @classmethod
    def quick(cls) -> "Config":
        # one render per step: the quick profile stays a two-minute look; whole renders: the random
        # pixels' chunks compile for longer than a short run at 48 x 48 wins back (perturbed
        # Gaussian alone, one core: 26.6 s against 32.9 with chunks)
        return cls(image_size=48, problems=4, steps=60, num_samples=8, faces_per_tile=32, sample_growth=1, pixel_chunk=1.0)


def load(name: str) -> render.Mesh:
    """A named primitive or a mesh file, normalized into the unit ball, coloured by position."""
    primitives = {
        "cube": lambda: render.cube(1.2),
        "icosphere": lambda: render.icosphere(2),
        "torus": lambda: render.torus(0.7, 0.3, 24, 12),
    }
    if name in primitives:
        mesh = primitives[name]()
    else:
        mesh = render.load_mesh(name, normalize=True)
    return render.position_colors(mesh)


def make_renderer(config: Config, method: str, mesh: render.Mesh | None = None) -> render.Renderer:
    """The renderer of `method`; `mesh` decides `cull_backfaces` when the config leaves it None."""
    sigma = config.sigma * config.image_size / 128.0
    cull = config.cull_backfaces
    if cull is None:
        cull = mesh is not None and render.is_closed_outward(mesh)
    common = dict(
        sigma=sigma, gamma=config.gamma, faces_per_pixel=config.faces_per_pixel,
        faces_per_tile=config.faces_per_tile, cull_backfaces=cull, interior_edges=config.interior_edges,
    )
    if method == "hard":
        return render.Renderer(mode="hard", **common)
    if method == "soft":
        return render.Renderer(mode="soft", dilation=6.0, **common)
    laws = {"perturbed-gaussian": noise.Gaussian(), "perturbed-cauchy": noise.Cauchy()}
    if method not in laws:
        raise ValueError(f"unknown method {method!r}; choose from {METHODS}")
    dilation = 3.0 if method == "perturbed-gaussian" else 6.0
    return render.Renderer(
        mode="perturbed", num_samples=config.num_samples, coverage_noise=laws[method], dilation=dilation,
        baseline=config.baseline, **common
    )


def camera(config: Config) -> render.Camera:
    d = config.camera_distance
    return render.look_at(
        jnp.array([0.0, 0.0, d]), image_size=(config.image_size, config.image_size), fov=config.fov,
        near=max(d - 2.0, 0.1), far=d + 2.0,
    )


def problems(config: Config, key, init_error_deg: float):
    """Target rotations, initial rotations at exactly `init_error_deg` from them, initial
    translation offsets."""
    k_true, k_axis, k_trans = jax.random.split(key, 3)
    n = config.problems
    # Drawn in float32 whatever the precision, then cast: a seed poses the same problems in
    # float32 (the CLI) and float64 runs. (Not render.random_rotation(k, float32): its matrix
    # would be orthonormal only to float32 accuracy in a float64 run.)
    dtype = jnp.zeros(()).dtype

    def normal(k, shape):
        return jax.random.normal(k, shape, jnp.float32).astype(dtype)

    r_true = jax.vmap(lambda k: render.quaternion_to_matrix(normal(k, (4,))))(jax.random.split(k_true, n))
    axis = normal(k_axis, (n, 3))
    axis = axis / jnp.linalg.norm(axis, axis=1, keepdims=True)
    r_init = matmul(render.axis_angle_to_matrix(np.deg2rad(init_error_deg) * axis), r_true)
    offset = normal(k_trans, (n, 3))
    offset = config.init_translation * offset / jnp.linalg.norm(offset, axis=1, keepdims=True)
    if not config.optimize_translation:
        offset = jnp.zeros_like(offset)
    return r_true, r_init, offset


def make_solver(config: Config, method: str, mesh: render.Mesh, cam: render.Camera):
    """init(offset) -> state; step(state, key, target, r_init) -> (state, loss, rotation).

    The state is (params, optimizer state, noise schedule state, best, step, average) with
    best = (params, hard-image loss) of the iterate closest to the target so far (with
    ``keep_best=False`` it stays at the initial params, loss inf) and average the exponential
    average of the iterates (``average_decay``; the initial params when 0)."""
    renderer = make_renderer(config, method, mesh)
    hard = make_renderer(config, "hard", mesh)
    optimizer = optax.adam(optax.cosine_decay_schedule(config.learning_rate, config.steps, alpha=config.final_learning_rate))
    adaptive = method != "hard"
    grows = config.sample_growth > 1 and method.startswith("perturbed")  # soft and hard draw no samples
    schedule = (
        schedules.Adaptive(
            factor=config.decay_factor, momentum=config.momentum, floor=config.noise_floor, patience=config.patience,
            sample_growth=config.sample_growth if grows else 1, max_num_samples=max(config.max_samples, config.num_samples),
        )
        if adaptive else schedules.Constant()
    )

    pose_smoothing = config.pose_noise_deg > 0.0 and adaptive  # the hard renderer stays unsmoothed
    fade_steps = max(1, round(config.pose_noise_until * config.steps))  # the pose noise is 0 from this step

    def pose(params, r_init):
        return _rotation(params["delta"], r_init), params["translation"]

    def noisy_pose(params, scale, key, t, sign=1.0):
        """params with the step's pose noise (the gradient with respect to them is the one at
        the noisy pose); the identity without pose smoothing."""
        if pose_smoothing:
            # linear decay to exactly 0 at step fade_steps (not 1 - t / fade_steps: XLA turns the
            # division into a product by a rounded reciprocal, and the end would be -5e-8, not 0)
            fade = jnp.maximum(fade_steps - t, 0).astype(params["delta"].dtype) / fade_steps
            eps = np.deg2rad(config.pose_noise_deg) * jax.lax.stop_gradient(scale) * fade
            params = {**params, "delta": params["delta"] + sign * eps * jax.random.normal(key, (3,), params["delta"].dtype)}
        return params

    def posed_mesh(params, r_init):
        rotation, translation = pose(params, r_init)
        return render.transform_mesh(mesh, rotation, translation)

    def image_loss(params, scale, key, target, r_init, pixels=None, weight=None):
        """The mean squared RGB error of a render, over the whole image; with `pixels`, the
        squared errors of those pixels only, times their (P,) `weight`, over the image's size; with a
        (H, W) `weight` (and no pixels), of the whole image weighted per pixel."""
        image = renderer(key, posed_mesh(params, r_init), cam, sigma=scale * renderer.sigma, gamma=scale * renderer.gamma, pixels=pixels)
        if pixels is not None:
            return jnp.sum(weight[:, None] * (image.rgb - target.reshape(-1, 3)[pixels]) ** 2) / target.size
        if weight is not None:
            return jnp.sum(weight[..., None] * (image.rgb - target) ** 2) / target.size
        return jnp.mean((image.rgb - target) ** 2)

    def loss_fn(params, scale, key, target, r_init, t, pose_key=None, sign=1.0):
        """The loss of one render, at a pose drawn with `key` (or `pose_key`, times `sign`)."""
        if pose_smoothing:
            key, k_pose = jax.random.split(key)
            params = noisy_pose(params, scale, k_pose if pose_key is None else pose_key, t, sign)
        return image_loss(params, scale, key, target, r_init)

    def hard_loss(params, target, r_init, weight=None):
        """image_loss of the hard render; with an (H, W) `weight`, each pixel's squared error
        times its weight."""
        image = hard(None, posed_mesh(params, r_init), cam)
        if weight is not None:
            return jnp.sum(weight[..., None] * (image.rgb - target) ** 2) / target.size
        return jnp.mean((image.rgb - target) ** 2)

    def init(offset):
        params = {"delta": jnp.zeros(3), "translation": offset}
        best = (params, jnp.asarray(jnp.inf, offset.dtype))
        # (params, optimizer state, schedule state, best, step, average of the iterates)
        return params, optimizer.init(params), schedule.init(1.0, config.num_samples), best, jnp.zeros((), jnp.int32), params

    value_and_grads = jax.value_and_grad(loss_fn, argnums=(0, 1))
    image_value_and_grads = jax.value_and_grad(image_loss, argnums=(0, 1))
    height, width = cam.image_size
    num_pixels = height * width
    chunked = method.startswith("perturbed") and config.pixel_chunk < 1.0
    chunk = min(num_pixels, max(1, round(config.pixel_chunk * num_pixels)))

    hard_value_and_grad = jax.value_and_grad(hard_loss)

    def estimate(params, sched, key, target, r_init, t):
        """The loss and its gradients (params, noise scale) from one render of num_samples
        samples per pixel, or with sample_growth the mean over sched.num_samples // num_samples
        renders with independent image noise (keys: `key`, then `key` folded with 1, 2, ...),
        and with antithetic_pose each odd render at the previous one's pose noise, negated; with
        pixel_chunk < 1, see chunked_estimate."""
        if chunked:
            return chunked_estimate(params, sched, key, target, r_init, t)
        first = value_and_grads(params, sched.sigma, key, target, r_init, t)
        if not grows:  # one render: no loop in the program
            return first
        passes = _renders_per_step(config, sched.num_samples)

        def another(i, total):
            if config.antithetic_pose:  # an odd render: the previous one's pose noise, negated
                pair = i - i % 2
                pair_key = jax.lax.cond(pair == 0, lambda: key, lambda: jax.random.fold_in(key, pair))
                pose_key, sign = jax.random.split(pair_key)[1], jnp.where(i % 2 == 1, -1.0, 1.0)
            else:
                pose_key, sign = None, 1.0
            out = value_and_grads(params, sched.sigma, jax.random.fold_in(key, i), target, r_init, t, pose_key, sign)
            return jax.tree.map(jnp.add, total, out)

        total = jax.lax.fori_loop(1, passes, another, first)
        return jax.tree.map(lambda a: a / passes.astype(a.dtype), total)

    def chunked_estimate(params, sched, key, target, r_init, t):
        """estimate() whose perturbed renders draw only the random pixels of their pose (those
        whose samples may differ from the hard pixel: Renderer.uncertainty > render.NEGLIGIBLE), in
        chunks of `chunk` pixels, as many as they fill; the other pixels, whose value and
        derivative are the hard pixel's in every sample, come from one hard render of the pose.
        Without pose noise this is estimate() with the same keys per pixel (a test). The poses
        of a step: with pose noise and antithetic_pose, two (+eps z, -eps z) once it averages
        two renders or more, each with half the renders; with independent pose noise one per
        render; without pose noise one."""
        scale = sched.sigma
        passes = _renders_per_step(config, sched.num_samples)
        image_key, pose_key = jax.random.split(key) if pose_smoothing else (key, None)  # the keys of loss_fn
        if pose_smoothing and config.antithetic_pose:
            poses = jnp.minimum(passes, 2)
        else:
            poses = passes if pose_smoothing else jnp.ones_like(passes)
        # per pose: passes is a power of sample_growth, so exact for growth 2 (3: 1 and 4 per pose
        # for 3 and 9 renders)
        renders = passes // poses
        share = 1.0 / renders.astype(target.dtype)

        def one_pose(g, total):
            if pose_key is None:
                noisy = params
            elif config.antithetic_pose:
                noisy = noisy_pose(params, scale, pose_key, t, jnp.where(g == 1, -1.0, 1.0))
            else:
                noisy = noisy_pose(params, scale, jax.lax.cond(g == 0, lambda: pose_key, lambda: jax.random.fold_in(pose_key, g)), t)
            k = jax.lax.cond(g == 0, lambda: image_key, lambda: jax.random.fold_in(image_key, 0x7FFFFFFF - g + 1))
            uncertainty = renderer.uncertainty(
                jax.lax.stop_gradient(posed_mesh(noisy, r_init)), cam, sigma=scale * renderer.sigma, gamma=scale * renderer.gamma
            ).reshape(-1)
            order, chunks = render.random_pixel_chunks(uncertainty, chunk)
            random = uncertainty > render.NEGLIGIBLE  # the chunks' pixels count where random, the hard render's elsewhere
            loss, grad = hard_value_and_grad(noisy, target, r_init, (~random).astype(target.dtype).reshape(height, width))
            total = jax.tree.map(jnp.add, total, (loss, (grad, jnp.zeros_like(scale))))

            def one_render(j, total):
                pixels, fresh = render.chunk_rows(order, j // renders, chunk)
                i = j % renders
                weight = jnp.where(fresh & random[pixels], share, 0.0)
                render_key = jax.lax.cond(i == 0, lambda: k, lambda: jax.random.fold_in(k, i))
                out = image_value_and_grads(noisy, scale, render_key, target, r_init, pixels, weight)
                return jax.tree.map(jnp.add, total, out)

            return jax.lax.fori_loop(0, chunks * renders, one_render, total)

        zero = jax.tree.map(jnp.zeros_like, (jnp.zeros((), target.dtype), (params, scale)))
        total = jax.lax.fori_loop(0, poses, one_pose, zero)
        return jax.tree.map(lambda a: a / poses.astype(a.dtype), total)

    def step(state, key, target, r_init):
        params, opt_state, sched, best, t, average = state
        loss, (grad, scale_grad) = estimate(params, sched, key, target, r_init, t)
        if not config.optimize_translation:
            grad = {"delta": grad["delta"], "translation": jnp.zeros_like(grad["translation"])}
        updates, opt_state = optimizer.update(grad, opt_state, params)
        params = optax.apply_updates(params, updates)
        sched = schedule.update(sched, scale_grad) if adaptive else schedule.update(sched)
        candidates = [params]
        if config.average_decay > 0:
            decay = config.average_decay
            average = jax.tree.map(lambda a, p: decay * a + (1.0 - decay) * p, average, params)
            candidates.append(average)
        if config.keep_best:
            for candidate in candidates:
                current = hard_loss(candidate, target, r_init)
                better = current < best[1]
                kept = jax.tree.map(lambda new, old: jnp.where(better, new, old), candidate, best[0])
                best = (kept, jnp.minimum(current, best[1]))
        return (params, opt_state, sched, best, t + 1, average), loss, pose(params, r_init)[0]

    # independent problems: one share per device when there are several (rsmooth.parallel)
    return renderer, jax.vmap(init), jax.jit(parallel.vmap_samples(step))


# Config fields that do not enter the compiled step (which problems are posed, how many at once,
# how they are reported): runs that differ only in these reuse one compiled step.
_PROBLEM_FIELDS = dict(
    init_errors_deg=(), problems=1, batch_size=1, methods=(), success_deg=0.0, init_translation=0.0, gif_every=1,
    restarts=0, restart_loss=1.0,
)
_SOLVERS: dict = {}  # the last few solvers built by run(), by (step config, method, mesh)


def _solver(config: Config, method: str, mesh: render.Mesh, cam: render.Camera):
    """make_solver's (init, step), reused from an earlier run() with the same step config and mesh
    (a step compiles in ~10-20 s; sweeps and tests call run() again and again)."""
    digest = hashlib.sha1()
    for array in (mesh.vertices, mesh.faces, mesh.albedo()):
        digest.update(np.ascontiguousarray(array).tobytes())
    key = (dataclasses.replace(config, **_PROBLEM_FIELDS), method, digest.hexdigest())
    if key not in _SOLVERS:
        while len(_SOLVERS) >= 8:
            _SOLVERS.pop(next(iter(_SOLVERS)))
        _SOLVERS[key] = make_solver(config, method, mesh, cam)[1:]
    return _SOLVERS[key]


def _renders_per_step(config: Config, num_samples):
    """How many renders of config.num_samples samples per pixel a step averages when its noise
    schedule holds `num_samples` (sample growth; 1 without)."""
    return jnp.maximum(num_samples // config.num_samples, 1)


def _rotation(delta, r_init):
    """The pose's rotation: exp([delta]) r_init."""
    return matmul(render.axis_angle_to_matrix(delta), r_init)


def _degrees(r1, r2):
    return np.rad2deg(np.asarray(render.rotation_angle(r1, r2)))


def run(config: Config, out: Path, key, progress: bool = True) -> dict:
    """Runs every method from every initial error; writes metrics.json, PNGs and a GIF."""
    out = Path(out)
    for name in ("problems", "batch_size", "steps", "sample_growth", "max_samples"):
        value = getattr(config, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be an int >= 1, got {value!r}")
    if not (np.isfinite(config.pixel_chunk) and 0.0 < config.pixel_chunk <= 1.0):
        raise ValueError(f"pixel_chunk must be in (0, 1] (a fraction of the image's pixels), got {config.pixel_chunk!r}")
    if isinstance(config.restarts, bool) or not isinstance(config.restarts, int) or config.restarts < 0:
        raise ValueError(f"restarts must be an int >= 0, got {config.restarts!r}")
    if not (np.isfinite(config.restart_loss) and config.restart_loss > 0.0):
        raise ValueError(f"restart_loss must be a finite number > 0 (a fraction of the initial image loss), got {config.restart_loss!r}")
    if not (np.isfinite(config.average_decay) and 0.0 <= config.average_decay < 1.0):
        raise ValueError(f"average_decay must be in [0, 1) (0: no averaging), got {config.average_decay!r}")
    if any(m.startswith("perturbed") for m in config.methods):
        check_baseline(config.baseline, config.num_samples)
    for method in config.methods:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose from {METHODS}")
    if not (np.isfinite(config.pose_noise_deg) and config.pose_noise_deg >= 0.0):
        raise ValueError(f"pose_noise_deg must be a finite number >= 0 (degrees), got {config.pose_noise_deg!r}")
    if not (np.isfinite(config.pose_noise_until) and 0.0 < config.pose_noise_until <= 1.0):
        raise ValueError(f"pose_noise_until must be in (0, 1] (a fraction of the steps), got {config.pose_noise_until!r}")
    if not config.init_errors_deg:
        raise ValueError("init_errors_deg must hold at least one initial rotation error (degrees)")
    for err in config.init_errors_deg:
        if isinstance(err, bool) or not isinstance(err, (int, float, np.integer, np.floating)) or not 0.0 <= err <= 180.0:
            raise ValueError(f"init_errors_deg must hold angles in [0, 180] degrees, got {err!r}")
    mesh = load(config.mesh)
    cam = camera(config)
    target_renderer = make_renderer(config, "hard", mesh)
    render_hard = jax.jit(jax.vmap(lambda r, t: target_renderer(None, render.transform_mesh(mesh, r, t), cam).rgb))

    k_problems, k_run = jax.random.split(key)
    setups = {}
    for i, err in enumerate(config.init_errors_deg):
        r_true, r_init, offset = problems(config, jax.random.fold_in(k_problems, i), err)
        targets = render_hard(r_true, jnp.zeros_like(offset))
        setups[err] = (r_true, r_init, offset, targets)

    results: dict = {}
    curves: dict = {}
    finals: dict = {}
    gif_frames = []
    gif_method = config.methods[0]
    gif_error = config.init_errors_deg[len(config.init_errors_deg) // 2]
    # as few chunks as batch_size allows, of equal sizes (32 problems: 2 x 16, not 25 + 7 padded
    # to 25, which would compute 18 padding problems); restarts reuse that size
    batch = -(-config.problems // -(-config.problems // config.batch_size))
    total = len(config.methods) * len(config.init_errors_deg) * -(-config.problems // batch) * config.steps
    hard_losses = jax.jit(lambda r, t, target: jnp.mean((render_hard(r, t) - target) ** 2, axis=(1, 2, 3)))

    def optimize(init, step, setup, indices, step_keys, record, bar):
        """Runs the problems `indices` (into the setup's arrays) in chunks of `batch`;
        step_keys(c_index, chunk, padding, t) gives a chunk's keys at step t. Returns, per problem
        in the order of `indices`: the rotation error at every step (steps + 1, n), the reported
        rotation and translation, the final noise scale factor and samples per pixel (n, 2);
        and the timed step durations."""
        r_true, r_init, offset, targets = setup
        errors, rotations, translations, ends, elapsed = [], [], [], [], []
        for c_index, lo in enumerate(range(0, len(indices), batch)):
            chunk = indices[lo:lo + batch]
            size = len(chunk)
            # a short chunk is padded to the batch size by repeating its last problem (the copies
            # are dropped), so that every chunk runs one compiled step
            padding = np.minimum(np.arange(batch), size - 1)  # indices into the chunk
            padded = chunk[padding]
            state = init(offset[padded])
            chunk_targets, chunk_r_init = targets[padded], r_init[padded]
            chunk_errors = [_degrees(r_init[chunk], r_true[chunk])]
            for t in range(config.steps):
                keys = step_keys(c_index, chunk, padding, t)
                start = time.perf_counter()
                state, loss, rotation = step(state, keys, chunk_targets, chunk_r_init)
                jax.block_until_ready(rotation)
                # timed: full batches after their first step (which may compile)
                if t > 0 and size == batch:
                    elapsed.append(time.perf_counter() - start)
                rotation = rotation[:size]
                chunk_errors.append(_degrees(rotation, r_true[chunk]))
                if record and c_index == 0 and t % config.gif_every == 0:
                    target0 = np.asarray(targets[chunk[0]])
                    current = np.asarray(render_hard(rotation[:1], state[0]["translation"][:1])[0])
                    gif_frames.append(np.concatenate([target0, current], axis=1))
                bar.update()
            errors.append(np.stack(chunk_errors))
            if config.keep_best:
                best_params = state[3][0]
                rotation = jax.vmap(_rotation)(best_params["delta"][:size], r_init[chunk])
                translations.append(best_params["translation"][:size])
            else:
                translations.append(state[0]["translation"][:size])
            rotations.append(rotation)
            # the final noise scale factor, and samples per pixel: the renders the last step averaged
            renders = np.asarray(_renders_per_step(config, state[2].num_samples[:size]))
            ends.append(np.stack([np.asarray(state[2].sigma)[:size], renders * config.num_samples], axis=-1))
        return (
            np.concatenate(errors, axis=1), jnp.concatenate(rotations), jnp.concatenate(translations),
            np.concatenate(ends), elapsed,
        )

    with tqdm(total=total, desc="render-pose", disable=not progress) as bar:
        for m_index, method in enumerate(config.methods):
            init, step = _solver(config, method, mesh, cam)
            results[method] = {}
            for e_index, err in enumerate(config.init_errors_deg):
                setup = setups[err]
                r_true, r_init, offset, targets = setup
                run_key = jax.random.fold_in(jax.random.fold_in(k_run, m_index), e_index)

                def first_keys(c_index, chunk, padding, t):
                    chunk_key = jax.random.fold_in(run_key, c_index)
                    return jax.random.split(jax.random.fold_in(chunk_key, t), len(chunk))[padding]

                record = method == gif_method and err == gif_error
                everything = np.arange(config.problems)
                curve, rotation, translation, schedule_end, elapsed = optimize(init, step, setup, everything, first_keys, record, bar)
                loss = np.array(hard_losses(rotation, translation, targets))  # updated by restarts
                initial_loss = np.asarray(hard_losses(r_init, offset, targets))
                first = _degrees(rotation, r_true)
                runs = np.ones(config.problems, int)
                for round_index in range(1, config.restarts + 1):
                    again = everything[loss > config.restart_loss * initial_loss]
                    if again.size == 0:
                        break
                    # fresh noise per problem (not per chunk): a problem's rerun does not depend
                    # on which others are rerun with it
                    round_key = jax.random.fold_in(jax.random.fold_in(run_key, 2**31), round_index)

                    def restart_keys(c_index, chunk, padding, t, round_key=round_key):
                        keys = jax.vmap(lambda i: jax.random.fold_in(round_key, i))(jnp.asarray(chunk[padding]))
                        return jax.vmap(lambda k: jax.random.fold_in(k, t))(keys)

                    bar.total += -(-again.size // batch) * config.steps
                    bar.refresh()
                    redo = optimize(init, step, setup, again, restart_keys, False, bar)
                    runs[again] += 1
                    redo_loss = np.asarray(hard_losses(redo[1], redo[2], targets[again]))
                    better = again[redo_loss < loss[again]]
                    take = redo_loss < loss[again]
                    curve[:, better] = redo[0][:, take]
                    rotation = rotation.at[better].set(redo[1][take])
                    translation = translation.at[better].set(redo[2][take])
                    schedule_end[better] = redo[3][take]
                    loss[better] = redo_loss[take]
                    elapsed += redo[4]
                curves[(method, err)] = curve
                last = curve[-1]
                final = _degrees(rotation, r_true)
                finals[(method, err)] = (rotation, translation)
                results[method][f"{err:g}"] = {
                    "solved_pct": float(100.0 * np.mean(final < config.success_deg)),
                    "mean_error_deg": float(np.mean(final)),
                    "std_error_deg": float(np.std(final)),
                    "median_error_deg": float(np.median(final)),
                    "final_errors_deg": final.tolist(),
                    "last_solved_pct": float(100.0 * np.mean(last < config.success_deg)),
                    "last_mean_error_deg": float(np.mean(last)),
                    "first_run_solved_pct": float(100.0 * np.mean(first < config.success_deg)),
                    "runs_per_problem": float(np.mean(runs)),
                    "final_losses": loss.tolist(),
                    "initial_losses": initial_loss.tolist(),
                    "final_sigma": float(np.mean(schedule_end[:, 0])),
                    "final_num_samples": float(np.mean(schedule_end[:, 1])),
                    "mean_translation_error": float(np.mean(np.linalg.norm(np.asarray(translation), axis=-1))),
                    "seconds_per_step": float(np.median(elapsed)) if elapsed else None,
                    "seconds_per_problem_step": float(np.median(elapsed)) / batch if elapsed else None,
                }

    _figures(config, out, setups, curves, finals, render_hard)
    if gif_frames:
        viz.save_animation(gif_frames, out / "optimization.gif", fps=10)
    metrics = {
        **results,
        "methods": list(config.methods),
        "init_errors_deg": list(config.init_errors_deg),
        "success_deg": config.success_deg,
        "problems": config.problems,
        "batch_size": batch,
        "steps": config.steps,
        "image_size": config.image_size,
        "mesh": config.mesh,
        "num_faces": int(mesh.faces.shape[0]),
        "faces_per_pixel": config.faces_per_pixel,
        "num_samples": config.num_samples,
        "sample_growth": config.sample_growth,
        "max_samples": config.max_samples,
        "pixel_chunk": config.pixel_chunk,
        "antithetic_pose": config.antithetic_pose,
        "cull_backfaces": target_renderer.cull_backfaces,
        "interior_edges": config.interior_edges,
        "keep_best": config.keep_best,
        "pose_noise_deg": config.pose_noise_deg,
        "pose_noise_until": config.pose_noise_until,
        "restarts": config.restarts,
        "restart_loss": config.restart_loss,
        "average_decay": config.average_decay,
        "baseline": config.baseline,
        "gif": f"optimization.gif: {gif_method}, initial error {gif_error:g} deg, problem 0 (target | current)",
    }
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def _figures(config, out, setups, curves, finals, render_hard):
    methods, errs = config.methods, config.init_errors_deg
    fig, axes = viz.plt.subplots(1, len(errs), figsize=(4.5 * len(errs), 3.6), squeeze=False)
    for ax, err in zip(axes[0], errs):
        for method in methods:
            c = curves[(method, err)]
            ax.plot(np.median(c, axis=1), label=method)
        ax.axhline(config.success_deg, color="k", ls=":", lw=1)
        ax.set_title(f"initial error {err:g} deg")
        ax.set_xlabel("Adam step")
        ax.set_ylabel("median rotation error (deg)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    viz.save_figure(fig, out / "errors.png")

    shown = min(config.problems, 3)
    for err in errs:
        r_true, r_init, offset, targets = setups[err]
        initial = np.asarray(render_hard(r_init[:shown], offset[:shown]))
        columns = [("target", np.asarray(targets[:shown])), ("initial", initial)]
        for method in methods:
            rotation, translation = finals[(method, err)]
            final = np.asarray(render_hard(rotation[:shown], translation[:shown]))
            errors = _degrees(rotation[:shown], r_true[:shown])  # of the reported (kept) iterate
            columns.append((method, final, errors))
        fig, axes = viz.plt.subplots(shown, len(columns), figsize=(2.0 * len(columns), 2.1 * shown), squeeze=False)
        for j, column in enumerate(columns):
            for i in range(shown):
                ax = axes[i][j]
                ax.imshow(np.clip(column[1][i], 0.0, 1.0))
                ax.set_xticks([])
                ax.set_yticks([])
                title = column[0] if len(column) == 2 else f"{column[0]}\n{column[2][i]:.1f} deg"
                ax.set_title(title, fontsize=7)
        fig.suptitle(f"initial error {err:g} deg: targets and final renders")
        fig.tight_layout()
        viz.save_figure(fig, out / f"renders_{err:g}deg.png")
