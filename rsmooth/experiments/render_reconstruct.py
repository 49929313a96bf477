"""Experiment: reconstruct a mesh from multi-view silhouettes by deforming an icosphere.

The mesh reconstruction task of Le Lidec, Laptev, Schmid, Carpentier, "Differentiable rendering
with perturbed optimizers", NeurIPS 2021 (after Liu et al., "Soft Rasterizer", ICCV 2019): a
target mesh, normalized into the unit box [-1/2, 1/2]^3, is rendered (hard z-buffer) from
`views` cameras around it, at alternating elevations; an icosphere is deformed, by an offset
on each vertex, to minimize with Adam (optax)

    mean over views of (1 - IoU(alpha, target alpha))
        + laplacian_weight * Laplacian(offsets) + flatten_weight * normal consistency(vertices)

(:func:`rsmooth.render.silhouette_iou`, :func:`rsmooth.render.laplacian_loss`,
:func:`rsmooth.render.normal_consistency_loss`: SoftRas' silhouette loss and its Laplacian and
flatten regularizers; the Laplacian acts on the offsets, so that the regularizers alone leave
the icosphere in place), optionally plus `rgb_weight` times the mean squared error of grey
shaded images, for each renderer:

* ``perturbed-gaussian``: the perturbed renderer (Gaussian noise on signed distances, Gumbel
  noise on depths) with the paper's adaptive noise decrease
  (:class:`rsmooth.schedules.Adaptive`, as in ``render pose``);
* ``soft``: SoftRas-like sigmoid coverage, same schedule;
* ``hard``: the z-buffer. Its silhouette is piecewise constant in the vertices: the data term
  has a zero gradient, and the icosphere stays where it is.

The targets (primitives, meshes shipped by the installed `example-robot-data` package, or
files) are independent problems sharing the template and the cameras: their optimizations are
batched with `jax.vmap` (spread over the devices when there are several, see
:mod:`rsmooth.parallel`), and the views of each with a nested `jax.vmap`. The reconstructions
are scored against the targets by 3D IoU (:func:`rsmooth.render.iou_3d`, voxelized) and the
Chamfer distance of surface samples (:func:`rsmooth.render.chamfer_distance`).

Scores over seeds, and the effect of the Laplacian weight and of the samples per pixel: see
benchmarks/RESULTS.md.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from rsmooth import _checks, noise, parallel, render, schedules, viz
from rsmooth.estimators import check_baseline
from rsmooth.experiments import _protocol
from rsmooth.experiments._protocol import option

METRICS_DOC = """metrics.json keys: for each method (perturbed-gaussian, soft, hard), a dict keyed by
target name holding iou_3d (voxelized IoU of the reconstruction with the target, on a
voxel_resolution^3 grid over both bounding boxes), chamfer (symmetric Chamfer distance: the mean
of the two directed mean squared nearest-neighbour distances between chamfer_points surface
samples of each mesh, in unit-box units squared), silhouette_iou (mean over the views of the IoU
of the hard-rendered silhouette of the reconstruction with the target's), final_loss (the
smoothed silhouette loss at the last step), final_sigma (final noise scale factor),
first_gradient_norm (norm of the silhouette loss' gradient with respect to the offsets at the
first step: exactly 0 for hard) and seconds_per_step (wall time of one Adam step of the batch of
all targets); 'initial', the same scores for the undeformed icosphere; also methods, targets,
views, steps, image_size, subdivisions, num_vertices, num_faces, voxel_resolution,
chamfer_points, num_samples, pixel_chunk and baseline (perturbed), laplacian_weight, flatten_weight, target_faces."""

METHODS = ("perturbed-gaussian", "soft", "hard")
BASELINES = ("hard", "leave-one-out")

# Meshes of the Solo-12 quadruped shipped by example-robot-data, under
# robots/solo_description/meshes/stl/.
ROBOT_MESHES = {
    "solo-upper-leg": "solo12/solo12_upper_leg_left_side.stl",
    "solo-lower-leg": "solo12/solo12_lower_leg_left_side.stl",
    "solo-hip": "solo12/solo12_hip_fe_fl.stl",
    "solo-foot": "with_foot/solo_foot.stl",
    "solo-base": "solo12/solo_12_base.stl",
}
PRIMITIVES = ("cube", "box", "cylinder", "torus")


@dataclasses.dataclass(frozen=True)
class Config:
    targets: tuple[str, ...] = option(
        ("cube", "torus", "solo-upper-leg"), "Target meshes (repeatable): cube, box, cylinder, torus, solo-upper-leg, "
        "solo-lower-leg, solo-hip, solo-foot, solo-base (example-robot-data), or a mesh file.", flag="mesh")
    methods: tuple[str, ...] = option(METHODS, "Renderers compared (repeatable).", flag="method", choices=METHODS)
    views: int = option(8, "Cameras around the target.", min=1)
    image_size: int = option(64, "Image side, pixels.", min=1)
    subdivisions: int = option(2, "Subdivisions of the icosphere template (2: 162 vertices, 320 faces).", min=0)
    template_radius: float = option(0.5, "Radius of the icosphere template, unit-box units.", above=0.0)
    steps: int = option(200, "Adam steps.", min=1)
    learning_rate: float = option(0.02, "Adam's initial learning rate (cosine decay).", above=0.0)
    final_learning_rate: float = option(0.1, "Fraction of learning_rate reached at the last step.", above=0.0)
    laplacian_weight: float = option(
        30.0, "Weight of the Laplacian of the vertex offsets (the icosphere is the rest shape): thin parts gain "
        "from more, sharp corners lose.", min=0.0)
    flatten_weight: float = option(0.01, "Weight of the normal consistency (flattening) regularizer.", min=0.0)
    rgb_weight: float = option(0.0, "Weight of the mean squared error of grey shaded images (0: silhouettes only).",
                               min=0.0)
    # Well below the faces' size: with independent noise on each face, a pixel on an edge shared
    # by two faces is missed by both with probability 1/4, and the smoothed silhouette gets holes.
    sigma: float = option(0.6, "Coverage noise scale, pixels at a 64-pixel image (scaled with the image size).",
                          above=0.0)
    gamma: float = option(0.02, "Depth temperature, normalized inverse depth.", above=0.0)
    num_samples: int = option(32, "Monte-Carlo samples per pixel of the perturbed renderer.", flag="samples", min=1)
    baseline: str = option(
        "hard", "The perturbed estimator's baseline: the hard pixel (the paper's) or the mean of the pixel's "
        "other samples (lower variance at edges).", choices=BASELINES)
    faces_per_pixel: int = option(8, "Candidate faces per pixel.", min=1)
    faces_per_tile: int = option(64, "Candidate faces per tile in the culling pass.", min=1)
    pixel_chunk: float = option(
        0.125, "The perturbed renderer draws its samples only at the pixels its noise may change, in chunks of "
        "this fraction of a view (the same images and gradients); 1: every pixel.", above=0.0, max=1.0)
    decay_factor: float = option(2.0, "The noise scale is divided by this at each decrease.", above=1.0)
    momentum: float = option(0.9, "Momentum of the schedule's average of d loss / d noise scale.", min=0.0, below=1.0)
    noise_floor: float = option(0.1, "Smallest noise scale factor.", min=0.0)
    patience: int = option(20, "Least number of steps between two noise decreases.", min=1)
    camera_distance: float = option(2.8, "Camera distance to the origin, unit-box units.", above=0.0)
    fov: float = option(40.0, "Camera field of view, degrees.", min=0.0, max=180.0)
    elevation_deg: float = option(30.0, "Camera elevation, degrees; views alternate between + and -.",
                                  min=-90.0, max=90.0)
    voxel_resolution: int = option(64, "Voxels per side of the 3D IoU's grid.", min=1)
    chamfer_points: int = option(4096, "Surface samples per mesh of the Chamfer distance.", min=1)
    gif_every: int = option(5, "Steps between two frames of the optimization GIF.", min=1)

    @classmethod
    def quick(cls, **changes) -> "Config":
        """A short look: fewer views, smaller images, fewer steps and samples."""
        small = cls(
            views=4, image_size=40, steps=60, learning_rate=0.03, patience=10, num_samples=8, voxel_resolution=40,
            chamfer_points=2048, gif_every=3,
        )
        return dataclasses.replace(small, **changes)

    def __post_init__(self):
        _protocol.check_options(self)
        if not self.targets:
            raise ValueError("targets (--mesh) must name at least one mesh")
        if not self.methods:
            raise ValueError("methods (--method) must name at least one renderer")
        if "perturbed-gaussian" in self.methods:
            check_baseline(renderer_baseline(self.baseline), self.num_samples)
        names = [_name(t) for t in self.targets]
        if len(set(names)) != len(names):
            raise ValueError(f"targets (--mesh) must have distinct names, got {names}")


def renderer_baseline(baseline: str) -> bool | str:
    """The `baseline` option as :class:`rsmooth.render.Renderer` takes it."""
    return True if baseline == "hard" else baseline


def _robot_mesh_path(name: str) -> Path:
    from rsmooth.sim import example_robot_data_root

    try:
        root = example_robot_data_root()
    except FileNotFoundError as error:
        raise ValueError(f"target {name!r} needs the example-robot-data package: {error}") from None
    path = root / "robots" / "solo_description" / "meshes" / "stl" / ROBOT_MESHES[name]
    if not path.is_file():
        raise ValueError(f"target {name!r}: {path} is missing from the installed example-robot-data")
    return path


def load_target(name: str) -> render.Mesh:
    """A named primitive, a Solo-12 mesh of example-robot-data, or a mesh file, centred and
    scaled so that its bounding box fits [-1/2, 1/2]^3 with its longest side 1."""
    primitives = {
        "cube": lambda: render.cube(1.0),
        "box": lambda: render.box((1.0, 0.6, 0.35)),
        "cylinder": lambda: render.cylinder(0.35, 1.0, 24),
        "torus": lambda: render.torus(0.7, 0.3, 24, 12),
    }
    if name in primitives:
        mesh = primitives[name]()
    elif name in ROBOT_MESHES:
        mesh = render.load_mesh(_robot_mesh_path(name))
    elif Path(name).suffix:
        mesh = render.load_mesh(name)
    else:
        raise ValueError(f"unknown target {name!r}: choose from {PRIMITIVES + tuple(ROBOT_MESHES)} or a mesh file")
    v = np.asarray(mesh.vertices)
    low, high = v.min(axis=0), v.max(axis=0)
    scale = 1.0 / float(np.max(high - low))
    # Colours are dropped: the targets are silhouettes (and grey shading).
    return render.Mesh(render.transform_mesh(mesh, scale * np.eye(3), -scale * (low + high) / 2.0).vertices, mesh.faces)


def cameras(config: Config, views: int | None = None, azimuth_offset_deg: float = 0.0) -> render.Camera:
    """`views` cameras (a batch: a leading axis on the arrays) on a circle around the origin,
    at evenly spaced azimuths and alternating elevations."""
    views = config.views if views is None else views
    eyes = []
    for i in range(views):
        azimuth = np.deg2rad(azimuth_offset_deg + 360.0 * i / views)
        elevation = np.deg2rad(config.elevation_deg * (1 if i % 2 == 0 else -1))
        eyes.append(config.camera_distance * np.array(
            [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
        ))
    d = config.camera_distance
    size = (config.image_size, config.image_size)
    batch = [render.look_at(eye, image_size=size, fov=config.fov, near=max(d - 1.5, 0.1), far=d + 1.5) for eye in eyes]
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *batch)


def make_renderer(config: Config, method: str) -> render.Renderer:
    sigma = config.sigma * config.image_size / 64.0
    common = dict(
        sigma=sigma, gamma=config.gamma, faces_per_pixel=config.faces_per_pixel,
        faces_per_tile=config.faces_per_tile,
    )
    if method == "hard":
        return render.Renderer(mode="hard", **common)
    if method == "soft":
        return render.Renderer(mode="soft", dilation=6.0, **common)
    if method == "perturbed-gaussian":
        return render.Renderer(
            mode="perturbed", num_samples=config.num_samples, coverage_noise=noise.Gaussian(),
            baseline=renderer_baseline(config.baseline), pixel_chunk=config.pixel_chunk, **common,
        )
    raise ValueError(f"unknown method {method!r}; choose from {METHODS}")


def deformed(template: render.Mesh, offsets) -> render.Mesh:
    """The template with its vertices moved by `offsets` (no validation: may be traced, and a
    failed reconstruction may have degenerate faces)."""
    return eqx.tree_at(lambda m: m.vertices, template, template.vertices + offsets)


def render_views(renderer: render.Renderer, key, mesh: render.Mesh, cams: render.Camera, **overrides) -> render.Image:
    """Images (a batch over the cameras) of one mesh."""
    keys = jax.random.split(key, cams.rotation.shape[0])
    return jax.vmap(lambda k, cam: renderer(k, mesh, cam, **overrides))(keys, cams)


def make_solver(config: Config, method: str, template: render.Mesh, cams: render.Camera):
    """init(offsets) -> state; step(state, key, target_alpha, target_rgb) -> (state, silhouette
    loss, data-term gradient norm); vmap them over problems."""
    renderer = make_renderer(config, method)
    faces = np.asarray(template.faces)
    optimizer = optax.adam(optax.cosine_decay_schedule(config.learning_rate, config.steps, alpha=config.final_learning_rate))
    adaptive = method != "hard"
    schedule = (
        schedules.Adaptive(
            factor=config.decay_factor, momentum=config.momentum, floor=config.noise_floor, patience=config.patience
        )
        if adaptive else schedules.Constant()
    )

    def data_loss(offsets, scale, key, target_alpha, target_rgb):
        images = render_views(
            renderer, key, deformed(template, offsets), cams, sigma=scale * renderer.sigma, gamma=scale * renderer.gamma
        )
        loss = jnp.mean(1.0 - render.silhouette_iou(images.alpha, target_alpha))
        if config.rgb_weight > 0:
            loss = loss + config.rgb_weight * jnp.mean((images.rgb - target_rgb) ** 2)
        return loss

    def regularizer(offsets):
        vertices = template.vertices + offsets
        # The Laplacian of the offsets, not of the vertices: the Laplacian of a sphere's vertices
        # points inwards, and Adam, which normalizes the step, would shrink it wherever no
        # silhouette edge holds it (and the hard renderer's sphere everywhere).
        return (
            config.laplacian_weight * render.laplacian_loss(offsets, faces)
            + config.flatten_weight * render.normal_consistency_loss(vertices, faces)
        )

    def init(offsets):
        return offsets, optimizer.init(offsets), schedule.init(1.0)

    def step(state, key, target_alpha, target_rgb):
        offsets, opt_state, sched = state
        loss, (data_grad, scale_grad) = jax.value_and_grad(data_loss, argnums=(0, 1))(
            offsets, sched.sigma, key, target_alpha, target_rgb
        )
        grad = data_grad + jax.grad(regularizer)(offsets)
        updates, opt_state = optimizer.update(grad, opt_state, offsets)
        offsets = optax.apply_updates(offsets, updates)
        sched = schedule.update(sched, scale_grad) if adaptive else schedule.update(sched)
        return (offsets, opt_state, sched), loss, jnp.linalg.norm(data_grad)

    # independent problems: one per device share when there are several (rsmooth.parallel);
    # the loss and the gradient's norm checked on the host rather than by traced checks, so
    # that the persistent compilation cache can keep the program (rsmooth._checks)
    compiled = jax.jit(_checks.without_traced_checks()(parallel.vmap_samples(step)))

    def checked_step(*args):
        state, loss, grad_norm = compiled(*args)
        _checks.check_outputs_on_host({"loss": loss, "gradient norm": grad_norm}, "render reconstruct's step")
        return state, loss, grad_norm

    return renderer, jax.vmap(init), checked_step


def _name(target: str) -> str:
    return target if target in PRIMITIVES or target in ROBOT_MESHES else Path(target).stem


def stack_meshes(meshes: list[render.Mesh]) -> render.Mesh:
    """Meshes of different sizes as one batch (a leading axis on the arrays), padded to the
    largest: extra vertices copy the first one, extra faces are (0, 0, 0). Those have zero area,
    so they are never drawn, sampled or crossed by a voxelization ray; the batch renders with
    one compilation and `jax.vmap`."""
    num_vertices = max(m.vertices.shape[0] for m in meshes)
    num_faces = max(m.faces.shape[0] for m in meshes)
    vertices = [
        np.concatenate([m.vertices, np.repeat(np.asarray(m.vertices[:1]), num_vertices - m.vertices.shape[0], 0)])
        for m in meshes
    ]
    faces = [np.concatenate([m.faces, np.zeros((num_faces - m.faces.shape[0], 3), np.int32)]) for m in meshes]
    # Built around the validation, which rejects the padding faces.
    batch = (jnp.asarray(np.stack(vertices)), jnp.asarray(np.stack(faces)))
    return eqx.tree_at(lambda m: (m.vertices, m.faces), meshes[0], batch)


def _index(batch: render.Mesh, i: int) -> render.Mesh:
    return jax.tree.map(lambda leaf: leaf[i], batch)


def target_images_and_silhouettes(config: Config, key, targets: render.Mesh, template: render.Mesh, cams: render.Camera):
    """The targets' images (hard, every view; a batch of meshes) and a jitted function from a
    batch of offsets to the hard silhouettes of the deformed templates, as `run` scores them."""
    # Targets are rendered once, hard, with room for dense meshes in the culling pass.
    target_renderer = render.Renderer(mode="hard", faces_per_pixel=config.faces_per_pixel, faces_per_tile=256, tile_size=4)
    hard = render.Renderer(mode="hard", faces_per_pixel=config.faces_per_pixel, faces_per_tile=config.faces_per_tile)
    images = jax.jit(jax.vmap(lambda mesh: render_views(target_renderer, key, mesh, cams)))(targets)
    silhouettes = jax.jit(jax.vmap(lambda offsets: render_views(hard, key, deformed(template, offsets), cams).alpha))
    return images, silhouettes


def run(config: Config, out: Path, key, progress: bool = True) -> dict:
    """Reconstructs every target with every method; writes metrics.json, PNGs and a GIF."""
    out = Path(out)
    names = [_name(t) for t in config.targets]
    meshes = [load_target(t) for t in config.targets]
    targets = stack_meshes(meshes)
    template = render.icosphere(config.subdivisions, config.template_radius)
    cams = cameras(config)
    images, silhouettes = target_images_and_silhouettes(config, key, targets, template, cams)
    target_alpha, target_rgb = images.alpha, images.rgb  # (T, V, H, W), (T, V, H, W, 3)

    k_metrics, k_run = jax.random.split(key)
    zeros = jnp.zeros((len(names),) + template.vertices.shape, template.vertices.dtype)
    initial = _scores(config, k_metrics, names, targets, template, target_alpha, zeros, silhouettes(zeros))

    results: dict = {}
    curves: dict = {}
    finals: dict = {}
    history = []  # offsets of every target, every gif_every steps, for the GIF
    gif_method = config.methods[0]
    with tqdm(total=len(config.methods) * config.steps, desc="render-reconstruct", disable=not progress) as bar:
        for m_index, method in enumerate(config.methods):
            _, init, step = make_solver(config, method, template, cams)
            # Laid out over the devices as `step` returns it: its first call compiles the same
            # program as the later ones (not one for single-device inputs, then another).
            state = parallel.shard_leading(init(zeros))
            run_key = jax.random.fold_in(k_run, m_index)
            losses, elapsed = [], []
            for t in range(config.steps):
                keys = jax.random.split(jax.random.fold_in(run_key, t), len(names))
                start = time.perf_counter()
                state, loss, gradient_norm = step(state, keys, target_alpha, target_rgb)
                jax.block_until_ready(loss)
                elapsed.append(time.perf_counter() - start)
                if t == 0:
                    first_gradient = np.asarray(gradient_norm)
                losses.append(np.asarray(loss))
                if method == gif_method and t % config.gif_every == 0:
                    history.append(state[0])
                bar.update()
            offsets = state[0]
            curves[method] = np.stack(losses)  # (steps, T)
            finals[method] = offsets
            # The first step includes compilation.
            seconds = float(np.median(elapsed[1:] if len(elapsed) > 1 else elapsed))
            scores = _scores(config, k_metrics, names, targets, template, target_alpha, offsets, silhouettes(offsets))
            results[method] = {
                name: {
                    **scores[name],
                    "final_loss": float(curves[method][-1, i]),
                    "final_sigma": float(np.asarray(state[2].sigma)[i]),
                    "first_gradient_norm": float(first_gradient[i]),
                    "seconds_per_step": seconds,
                }
                for i, name in enumerate(names)
            }

    shade = _shader(config, template)
    _figures(config, out, names, targets, template, target_alpha, curves, finals, results, initial, silhouettes, shade)
    if history:
        frames = _gif_frames(config, targets, target_alpha, history, silhouettes, shade)
        viz.save_animation(frames, out / "optimization.gif", fps=8)
    metrics = {
        **results,
        "initial": initial,
        "methods": list(config.methods),
        "targets": names,
        "views": config.views,
        "steps": config.steps,
        "image_size": config.image_size,
        "subdivisions": config.subdivisions,
        "num_vertices": int(template.vertices.shape[0]),
        "num_faces": int(template.faces.shape[0]),
        "voxel_resolution": config.voxel_resolution,
        "chamfer_points": config.chamfer_points,
        "num_samples": config.num_samples,
        "pixel_chunk": config.pixel_chunk,
        "baseline": config.baseline,
        "laplacian_weight": config.laplacian_weight,
        "flatten_weight": config.flatten_weight,
        "target_faces": {name: int(mesh.faces.shape[0]) for name, mesh in zip(names, meshes)},
        "gif": f"optimization.gif: {gif_method}; per target: target | reconstruction (grey, between the views) | "
               "silhouette of view 0 (red: target, green: reconstruction, yellow: both)",
    }
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def _scores(config, key, names, targets, template, target_alpha, offsets, alpha) -> dict:
    """3D IoU, Chamfer distance and silhouette IoU of each target's reconstruction."""
    silhouette = np.asarray(jnp.mean(render.silhouette_iou(alpha, target_alpha), axis=-1))
    k_target, k_mesh = jax.random.split(key)
    sample = jax.jit(jax.vmap(lambda mesh: render.sample_surface(k_target, mesh, config.chamfer_points)))
    target_points = sample(targets)
    sample_deformed = jax.vmap(lambda o: render.sample_surface(k_mesh, deformed(template, o), config.chamfer_points))
    points = jax.jit(sample_deformed)(offsets)
    chamfer = np.asarray(jax.jit(jax.vmap(render.chamfer_distance))(target_points, points))
    scores = {}
    for i, name in enumerate(names):
        iou = render.iou_3d(_index(targets, i), deformed(template, offsets[i]), config.voxel_resolution)
        scores[name] = {"iou_3d": float(iou), "chamfer": float(chamfer[i]), "silhouette_iou": float(silhouette[i])}
    return scores


def _shader(config: Config, template: render.Mesh):
    """For pictures: jitted batch renderers of grey shaded images of meshes and of deformed
    templates, from a camera between the training views, at an integer multiple of the training
    size (96 px at least)."""
    size = config.image_size * -(-96 // config.image_size)
    dense = render.Renderer(mode="hard", faces_per_pixel=4, faces_per_tile=256, tile_size=4)  # for the targets
    coarse = render.Renderer(mode="hard", faces_per_pixel=4, faces_per_tile=config.faces_per_tile)
    grown = dataclasses.replace(config, image_size=size)
    between = jax.tree.map(lambda leaf: leaf[0], cameras(grown, views=1, azimuth_offset_deg=35.0))

    def shade(renderer, mesh):
        return jnp.clip(renderer(None, mesh, between).rgb, 0.0, 1.0)

    return (
        jax.jit(jax.vmap(lambda mesh: shade(dense, mesh))),
        jax.jit(jax.vmap(lambda offsets: shade(coarse, deformed(template, offsets)))),
    )


def _gif_frames(config, targets, target_alpha, history, silhouettes, shade):
    shade_meshes, shade_offsets = shade
    target_rgb = np.asarray(shade_meshes(targets))  # (T, S, S, 3)
    factor = target_rgb.shape[1] // config.image_size
    grow = lambda a: np.repeat(np.repeat(np.asarray(a), factor, axis=-2), factor, axis=-1)  # noqa: E731
    target0 = grow(target_alpha[:, 0])
    frames = []
    for offsets in history:
        rgb = np.asarray(shade_offsets(offsets))
        alpha0 = grow(silhouettes(offsets)[:, 0])
        overlay = np.stack([target0, alpha0, np.zeros_like(target0)], axis=-1)
        rows = [np.concatenate([target_rgb[i], rgb[i], overlay[i]], axis=1) for i in range(rgb.shape[0])]
        frames.append(np.concatenate(rows, axis=0))
    return frames


def _figures(config, out, names, targets, template, target_alpha, curves, finals, results, initial, silhouettes, shade):
    methods = config.methods
    fig, axes = viz.plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.4), squeeze=False)
    for i, (ax, name) in enumerate(zip(axes[0], names)):
        for method in methods:
            ax.plot(curves[method][:, i], label=method)
        ax.set_title(name)
        ax.set_xlabel("Adam step")
        ax.set_ylabel("silhouette loss (1 - IoU)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    viz.save_figure(fig, out / "losses.png")

    zeros = jnp.zeros((len(names),) + template.vertices.shape, template.vertices.dtype)
    alphas = {"target": np.asarray(target_alpha), "initial": np.asarray(silhouettes(zeros))}
    alphas.update({method: np.asarray(silhouettes(finals[method])) for method in methods})
    shown = min(config.views, 4)
    for i, name in enumerate(names):
        fig, axes = viz.plt.subplots(shown, len(alphas), figsize=(1.8 * len(alphas), 1.9 * shown), squeeze=False)
        for j, (title, alpha) in enumerate(alphas.items()):
            for v in range(shown):
                ax = axes[v][j]
                ax.imshow(alpha[i, v], cmap="gray", vmin=0.0, vmax=1.0)
                ax.set_xticks([])
                ax.set_yticks([])
                if v == 0:
                    ax.set_title(title, fontsize=8)
        fig.suptitle(f"{name}: silhouettes (hard) of the first {shown} views")
        fig.tight_layout()
        viz.save_figure(fig, out / f"silhouettes_{name}.png")

    shade_meshes, shade_offsets = shade
    pictures = {"target": np.asarray(shade_meshes(targets)), "initial": np.asarray(shade_offsets(zeros))}
    pictures.update({method: np.asarray(shade_offsets(finals[method])) for method in methods})
    fig, axes = viz.plt.subplots(len(names), len(pictures), figsize=(2.2 * len(pictures), 2.4 * len(names)), squeeze=False)
    for i, name in enumerate(names):
        for j, (column, picture) in enumerate(pictures.items()):
            if column == "target":
                title = name
            else:
                score = initial[name] if column == "initial" else results[column][name]
                label = "icosphere" if column == "initial" else column
                title = f"{label}\nIoU {score['iou_3d']:.2f}, CD {score['chamfer']:.4f}"
            ax = axes[i][j]
            ax.imshow(picture[i])
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(title, fontsize=7)
    fig.suptitle("reconstructions seen from between the training views (3D IoU, Chamfer)")
    fig.tight_layout()
    viz.save_figure(fig, out / "reconstructions.png")


def summary(metrics: dict) -> dict:
    """The lines printed after a run: per method, the 3D IoU and Chamfer distance of each target."""
    return {
        f"{method}: 3D IoU / Chamfer ({', '.join(metrics['targets'])})": ", ".join(
            f"{metrics[method][t]['iou_3d']:.2f} / {metrics[method][t]['chamfer']:.4f}" for t in metrics["targets"]
        )
        for method in metrics["methods"]
    }


EXPERIMENT = _protocol.Experiment(
    command=("render", "reconstruct"),
    name="render-reconstruct",
    config=Config,
    run=run,
    summary=summary,
    help="Reconstruct meshes from multi-view silhouettes by deforming an icosphere (Laplacian and "
    "flattening regularizers) with the perturbed renderer, a SoftRas-like one and the hard "
    "z-buffer; 3D IoU and Chamfer distance to the targets.",
    metrics_doc=METRICS_DOC,
    x64=False,
)
