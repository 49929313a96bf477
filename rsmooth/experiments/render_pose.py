"""Experiment: recover a mesh's pose from one RGB image with differentiable renderers.

The pose estimation task of Le Lidec, Laptev, Schmid, Carpentier, "Differentiable rendering with
perturbed optimizers", NeurIPS 2021: a target image is rendered (hard z-buffer) at a random
rotation; the fit starts from that rotation composed with a rotation of a fixed angle
(`init_errors_deg`) about a random axis, and minimizes the mean squared RGB error between the
rendered and the target images (:class:`rsmooth.render.PoseFit`, run in batches with restarts by
:func:`rsmooth.render.fit_poses`), for each renderer:

* ``perturbed-gaussian``, ``perturbed-cauchy``: the perturbed renderer (Gaussian or Cauchy noise
  on signed distances, Gumbel noise on depths), with the paper's adaptive noise decrease
  (:class:`rsmooth.schedules.Adaptive`), pose noise, sample growth and keep-best;
* ``soft``: SoftRas-like sigmoid coverage and softmax aggregation, same schedule and pose noise
  (its derivative with respect to the noise scale is exact);
* ``hard``: the z-buffer, unsmoothed: only shading and colour interpolation give it a gradient.

The mesh's vertices are coloured by their position, so that symmetric shapes (cube, sphere)
have a unique pose. A problem is solved when its reported rotation ends within `success_deg`
of the truth. Success rates and step times: see benchmarks/RESULTS.md.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from rsmooth import noise, render, schedules, viz
from rsmooth.estimators import check_baseline
from rsmooth.experiments import _protocol
from rsmooth.experiments._protocol import option

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
renderers, in all the renders of a step: num_samples unless sample_growth), mean_translation_error
(distance of the final translation to the true one, 0 unless optimize_translation), seconds_per_step
(wall time of one batched Adam step of batch_size problems, first steps excluded; null when there
is none) and seconds_per_problem_step (the same per problem); also methods, init_errors_deg,
success_deg, problems, batch_size (the problems per batch actually run: at most the config's, so
that batches are of equal size), steps, image_size, mesh, num_faces, faces_per_pixel, num_samples
(of the perturbed renderers), sample_growth, max_samples, pixel_chunk and antithetic_pose,
cull_backfaces (whether faces seen from behind were dropped: by default when the mesh is closed),
interior_edges (whether coverage was smoothed across every triangle edge, as in the paper),
keep_best, pose_noise_deg (the initial rotation noise of the pose smoothing, 0 when off),
pose_noise_until (the fraction of the steps at which that noise has faded to 0), restarts,
restart_loss, average_decay and baseline (see Config)."""

METHODS = ("perturbed-gaussian", "perturbed-cauchy", "soft", "hard")
BASELINES = ("hard", "leave-one-out")


@dataclasses.dataclass(frozen=True)
class Config:
    mesh: str = option("cube", "The mesh: cube, icosphere, torus, or a mesh file (OBJ, STL, PLY, DAE).")
    image_size: int = option(128, "Image side, pixels.", min=1)
    init_errors_deg: tuple[float, ...] = option(
        (20.0, 50.0, 80.0), "Initial rotation error, degrees (repeatable).", flag="init-error", min=0.0, max=180.0)
    problems: int = option(100, "Problems per initial error.", min=1)
    batch_size: int = option(25, "Most problems optimized at once (vmapped); the others wait their turn.", min=1)
    steps: int = option(200, "Adam steps per problem.", min=1)
    methods: tuple[str, ...] = option(METHODS, "Renderers compared (repeatable).", flag="method", choices=METHODS)
    learning_rate: float = option(0.05, "Adam's initial learning rate (cosine decay).", above=0.0)
    sigma: float = option(3.0, "Coverage noise scale of the smoothed renderers, pixels at a 128-pixel image "
                          "(scaled with the image size).", above=0.0)
    gamma: float = option(0.02, "Depth temperature of the smoothed renderers, normalized inverse depth.", above=0.0)
    num_samples: int = option(16, "Monte-Carlo samples per pixel of a perturbed render.", flag="samples", min=1)
    sample_growth: int = option(
        2, "Multiply the perturbed renderers' samples per pixel by this at each noise decrease (a step then "
        "averages several renders), up to max_samples; 1: off.", min=1)
    max_samples: int = option(64, "Cap on the samples per pixel of a step with sample_growth.", min=1)
    pixel_chunk: float = option(
        0.125, "Perturbed renders draw their samples only at the pixels their noise may change, in chunks of "
        "this fraction of the image, the others from one hard render (the same estimate); 1: whole renders.",
        above=0.0, max=1.0)
    antithetic_pose: bool = option(
        True, "Draw a step's pose noise in antithetic pairs (+eps z, -eps z), whose first-order terms cancel, "
        "rather than independently.", flag="antithetic-pose/independent-pose")
    faces_per_pixel: int = option(4, "Candidate faces per pixel of the smoothed renderers.", min=1)
    faces_per_tile: int = option(64, "Candidate faces per tile in the culling pass (raise for dense meshes).", min=1)
    cull_backfaces: bool | None = option(
        None, "Drop faces seen from behind; None: when the mesh is closed and outward-oriented.", cli=False)
    interior_edges: bool = option(
        False, "Smooth coverage across every triangle edge, as the paper does (seams along shared edges), "
        "rather than the silhouette only.")
    noise_schedule: str = option(
        "adaptive", "The smoothed renderers' noise schedule: the paper's sign rule, which only decreases the "
        "noise, or reheating, which also raises it when the loss stalls (rsmooth.schedules.Reheating).",
        choices=("adaptive", "reheating"))
    decay_factor: float = option(2.0, "The noise scale is divided by this at each decrease.", above=1.0)
    growth_factor: float = option(2.0, "Reheating: the noise scale is multiplied by this when the loss stalls.",
                                  above=1.0)
    stall_steps: int = option(15, "Reheating: steps without a lower loss that make a stall.", min=1)
    noise_ceiling: float = option(4.0, "Reheating: largest noise scale factor.", above=0.0)
    momentum: float = option(0.9, "Momentum of the schedule's average of d loss / d noise scale.", min=0.0, below=1.0)
    noise_floor: float = option(0.05, "Smallest noise scale factor.", min=0.0)
    patience: int = option(10, "Least number of steps between two noise decreases.", min=1)
    final_learning_rate: float = option(0.1, "Fraction of learning_rate reached at the last step.", above=0.0)
    optimize_translation: bool = option(False, "Fit the translation too (it starts off by init_translation).")
    init_translation: float = option(0.2, "Distance of the initial translation to the true one, scene units.", min=0.0)
    camera_distance: float = option(4.0, "Camera distance to the mesh's centre, scene units.", min=0.0)
    fov: float = option(40.0, "Camera field of view, degrees.", min=0.0, max=180.0)
    success_deg: float = option(10.0, "A problem is solved when its final rotation error is below this, degrees.",
                                min=0.0)
    keep_best: bool = option(
        True, "Report each problem's iterate whose hard render is closest to the target (one hard render per "
        "step) rather than the last iterate.", flag="keep-best/last")
    pose_noise_deg: float = option(
        25.0, "Randomized smoothing of the loss over rotations: std of the rotation noise at the start, degrees, "
        "shrunk with the renderer's noise scale (0: off; never for the hard renderer).", flag="pose-noise", min=0.0)
    pose_noise_until: float = option(
        1.0, "Fraction of the steps at which the pose noise has faded linearly to 0; the later steps descend "
        "the image-smoothed loss alone.", above=0.0, max=1.0)
    restarts: int = option(
        0, "Run a problem again from its initial pose with fresh noise, up to this many times, while its best "
        "hard render stays far from the target (no ground truth used); each reports its closest run.", min=0)
    restart_loss: float = option(
        0.05, "A problem is rerun while its image loss is above this fraction of its initial pose's.", above=0.0)
    average_decay: float = option(
        0.0, "With keep_best, also consider the exponential average of the iterates with this decay per step "
        "(one more hard render per step; 0: off).", flag="average-iterates", min=0.0, max=0.999)
    baseline: str = option(
        "hard", "The perturbed estimator's baseline: the hard pixel (the paper's) or the mean of the pixel's "
        "other samples (lower variance at edges).", choices=BASELINES)
    gif_every: int = option(2, "Steps between two frames of the optimization GIF.", min=1)

    @classmethod
    def quick(cls, **changes) -> "Config":
        """A two-minute look: small images, few problems and steps, one whole render per step."""
        small = cls(image_size=48, problems=4, steps=60, num_samples=8, faces_per_tile=32, sample_growth=1, pixel_chunk=1.0)
        return dataclasses.replace(small, **changes)

    def __post_init__(self):
        _protocol.check_options(self)
        if not self.init_errors_deg:
            raise ValueError("init_errors_deg (--init-error) must hold at least one initial rotation error (degrees)")
        if not self.methods:
            raise ValueError("methods (--method) must name at least one renderer")
        if any(m.startswith("perturbed") for m in self.methods):
            check_baseline(renderer_baseline(self.baseline), self.num_samples)


def renderer_baseline(baseline: str) -> bool | str:
    """The `baseline` option as :class:`rsmooth.render.Renderer` takes it."""
    return True if baseline == "hard" else baseline


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
    # Cauchy's heavy tail needs candidates from further away
    dilation = 3.0 if method == "perturbed-gaussian" else 6.0
    return render.Renderer(
        mode="perturbed", num_samples=config.num_samples, coverage_noise=laws[method], dilation=dilation,
        baseline=renderer_baseline(config.baseline), pixel_chunk=config.pixel_chunk, **common
    )


def make_fit(config: Config, method: str, mesh: render.Mesh) -> render.PoseFit:
    """The pose fit of `method`: the hard renderer stays unsmoothed (constant schedule, no pose
    noise); the smoothed ones follow the adaptive (or reheating) schedule, with sample growth
    when perturbed."""
    smoothed = method != "hard"
    adaptive = dict(
        factor=config.decay_factor, momentum=config.momentum, floor=config.noise_floor, patience=config.patience,
        sample_growth=config.sample_growth if method.startswith("perturbed") else 1,
        max_num_samples=max(config.max_samples, config.num_samples),
    )
    if not smoothed:
        schedule = schedules.Constant()
    elif config.noise_schedule == "reheating":
        schedule = schedules.Reheating(
            **adaptive, growth=config.growth_factor, stall_patience=config.stall_steps, ceiling=config.noise_ceiling
        )
    else:
        schedule = schedules.Adaptive(**adaptive)
    return render.PoseFit(
        make_renderer(config, method, mesh), steps=config.steps, learning_rate=config.learning_rate,
        final_learning_rate=config.final_learning_rate, schedule=schedule,
        pose_noise=float(np.deg2rad(config.pose_noise_deg)) if smoothed else 0.0,
        pose_noise_until=config.pose_noise_until, antithetic_pose=config.antithetic_pose, keep_best=config.keep_best,
        average_decay=config.average_decay, optimize_translation=config.optimize_translation,
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
    r_init = jax.vmap(render.pose_rotation)(np.deg2rad(init_error_deg) * axis, r_true)
    offset = normal(k_trans, (n, 3))
    offset = config.init_translation * offset / jnp.linalg.norm(offset, axis=1, keepdims=True)
    if not config.optimize_translation:
        offset = jnp.zeros_like(offset)
    return r_true, r_init, offset


def _degrees(r1, r2):
    return np.rad2deg(np.asarray(render.rotation_angle(jnp.asarray(r1), jnp.asarray(r2))))


def run(config: Config, out: Path, key, progress: bool = True) -> dict:
    """Runs every method from every initial error; writes metrics.json, PNGs and a GIF."""
    out = Path(out)
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
    batch = config.batch_size
    with tqdm(total=len(config.methods) * len(config.init_errors_deg) * config.problems * config.steps,
              desc="render-pose", disable=not progress) as bar:
        for m_index, method in enumerate(config.methods):
            fit = make_fit(config, method, mesh)
            results[method] = {}
            for e_index, err in enumerate(config.init_errors_deg):
                r_true, r_init, offset, targets = setups[err]
                record = method == gif_method and err == gif_error

                def on_step(run_index, indices, t, rotation, translation, targets=targets, record=record):
                    if run_index > 0 and t == 0:  # a restart's batch: its steps join the bar
                        bar.total += len(indices) * config.steps
                        bar.refresh()
                    if record and run_index == 0 and indices[0] == 0 and t % config.gif_every == 0:
                        current = np.asarray(render_hard(rotation[:1], translation[:1])[0])
                        gif_frames.append(np.concatenate([np.asarray(targets[0]), current], axis=1))
                    bar.update(len(indices))

                result = render.fit_poses(
                    fit, jax.random.fold_in(jax.random.fold_in(k_run, m_index), e_index), mesh, cam, targets, r_init,
                    offset, batch_size=config.batch_size, restarts=config.restarts, restart_loss=config.restart_loss,
                    on_step=on_step,
                )
                batch = result.batch_size
                curve = np.stack([_degrees(rotations, r_true) for rotations in result.trajectory])
                curves[(method, err)] = curve
                last = curve[-1]
                final = _degrees(result.rotation, r_true)
                first = _degrees(result.first_rotation, r_true)
                finals[(method, err)] = (jnp.asarray(result.rotation), jnp.asarray(result.translation))
                elapsed = result.step_seconds
                results[method][f"{err:g}"] = {
                    "solved_pct": float(100.0 * np.mean(final < config.success_deg)),
                    "mean_error_deg": float(np.mean(final)),
                    "std_error_deg": float(np.std(final)),
                    "median_error_deg": float(np.median(final)),
                    "final_errors_deg": final.tolist(),
                    "last_solved_pct": float(100.0 * np.mean(last < config.success_deg)),
                    "last_mean_error_deg": float(np.mean(last)),
                    "first_run_solved_pct": float(100.0 * np.mean(first < config.success_deg)),
                    "runs_per_problem": float(np.mean(result.runs)),
                    "final_losses": result.loss.tolist(),
                    "initial_losses": result.initial_loss.tolist(),
                    "final_sigma": float(np.mean(result.final_scale)),
                    "final_num_samples": float(np.mean(result.final_num_samples)),
                    "mean_translation_error": float(np.mean(np.linalg.norm(result.translation, axis=-1))),
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


def summary(metrics: dict) -> dict:
    """The lines printed after a run: per method, the % solved from each initial error (with
    restarts, also the first run's and the runs per problem)."""
    errors = ", ".join(f"{e:g}" for e in metrics["init_errors_deg"])
    if not metrics["restarts"]:
        return {
            f"{method}: solved % from {errors} deg": ", ".join(
                f"{metrics[method][f'{e:g}']['solved_pct']:.0f}" for e in metrics["init_errors_deg"]
            )
            for method in metrics["methods"]
        }
    return {
        f"{method}: solved % from {errors} deg (first run; runs per problem)": ", ".join(
            "{solved_pct:.0f} ({first_run_solved_pct:.0f}; {runs_per_problem:.2f})".format(**metrics[method][f"{e:g}"])
            for e in metrics["init_errors_deg"]
        )
        for method in metrics["methods"]
    }


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


EXPERIMENT = _protocol.Experiment(
    command=("render", "pose"),
    name="render-pose",
    config=Config,
    run=run,
    summary=summary,
    help="Recover a mesh's rotation from one RGB image with the perturbed renderer (Gaussian or Cauchy "
    "noise, adaptive noise decrease), a SoftRas-like one and the hard z-buffer.",
    metrics_doc=METRICS_DOC,
    x64=False,
)
