r"""Pose estimation by analysis-by-synthesis: fit a mesh's rotation (and translation) to an image.

A pose is parametrized as :math:`R = \exp([\omega]_\times) R_0` about an initial rotation
:math:`R_0`, with the axis-angle offset :math:`\omega \in \mathbb{R}^3` starting at 0, and a
translation. :class:`PoseFit` descends the mean squared RGB error between the render of the
posed mesh and a target image with Adam, the renderer's noise scale driven by a noise schedule
(:class:`rsmooth.schedules.Adaptive`: the scale shrinks when d loss / d scale turns positive),
as in Le Lidec et al. On top of the renderer's smoothing in the image, it offers:

* pose noise: randomized smoothing of the loss over rotations as well. Each render takes its
  gradient at :math:`\omega + \epsilon z`, :math:`z \sim N(0, I_3)`, with :math:`\epsilon` the
  pose noise times the schedule's scale, fading linearly to 0 by ``pose_noise_until`` of the
  steps, so that the fit ends on the image-smoothed loss. Smoothing in the image alone leaves a
  pose in the basin of another with the same silhouette; smoothing over poses lets it out;
* antithetic pose pairs: the renders of a step come in pairs at :math:`\pm\epsilon z`, whose
  first-order terms cancel in their mean (most of the gradient's variance near a solution);
* sample growth: when the schedule multiplies its sample count at a noise decrease, a step
  averages that many renders of the renderer's ``num_samples`` samples per pixel, with
  independent noise (the Monte-Carlo noise of the gradient falls at the noise floor);
* keep-best: the reported pose is the iterate whose hard render is closest to the target (one
  hard render per step), optionally among an exponential average of the iterates as well
  (Polyak-Ruppert averaging): at the noise floor the noisy gradient makes Adam wander around
  the solution;
* restarts (:func:`fit_poses`): problems whose best hard render stays far from the target are
  run again with fresh noise; each reports its closest run. The test is on the image, not on
  the ground truth.

With a perturbed renderer whose ``pixel_chunk`` is below 1, the renders draw their samples at
the random pixels alone (:meth:`PoseFit.estimate`): the same estimate at a cost about
proportional to those pixels.

References:
    Le Lidec, Laptev, Schmid, Carpentier, "Differentiable rendering with perturbed optimizers",
    NeurIPS 2021 (pose estimation experiment, adaptive noise decrease).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import time
from typing import Callable, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import Array

from rsmooth import _checks, parallel, schedules
from rsmooth._xla import matmul
from rsmooth.render._camera import Camera, axis_angle_to_matrix
from rsmooth.render._mesh import Mesh, transform_mesh
from rsmooth.render._renderer import NEGLIGIBLE, Renderer, chunk_rows, random_pixel_chunks

__all__ = ["PoseFit", "PoseFitState", "PoseFitResult", "fit_poses", "pose_rotation", "image_loss"]


def pose_rotation(axis_angle: Array, initial_rotation: Array) -> Array:
    """The rotation :math:`\\exp([\\omega]_\\times) R_0` of an axis-angle offset about `initial_rotation`.

    Args:
        axis_angle: (3,) rotation vector :math:`\\omega` (radians).
        initial_rotation: (3, 3) rotation matrix :math:`R_0`.

    Returns:
        (3, 3) rotation matrix.

    Example:
        >>> import jax.numpy as jnp
        >>> r = pose_rotation(jnp.array([0.0, 0.0, jnp.pi / 2]), jnp.eye(3))
        >>> [round(float(x), 6) + 0.0 for x in r @ jnp.array([1.0, 0.0, 0.0])]
        [0.0, 1.0, 0.0]
    """
    return matmul(axis_angle_to_matrix(axis_angle), initial_rotation)


def image_loss(image: Array, target: Array) -> Array:
    """The mean squared RGB error of an image to a target (both (H, W, 3)): the pose fit's loss."""
    return jnp.mean((image - target) ** 2)


class PoseFitState(eqx.Module):
    """The state of one pose fit (vmap :meth:`PoseFit.init` for a batch).

    Attributes:
        params: ``{"axis_angle": (3,), "translation": (3,)}``, the current iterate.
        opt_state: Adam's state.
        schedule: the noise schedule's state (``schedule.sigma``: the noise scale factor;
            ``schedule.num_samples``: the samples per pixel of a step, in all its renders).
        best_params: the iterate whose hard render was closest to the target so far (with
            ``keep_best`` off: the initial params).
        best_loss: its hard image loss (inf before the first step or with ``keep_best`` off).
        step: the number of steps taken.
        average: the exponential average of the iterates (``average_decay``; the initial params
            when 0).
    """

    params: dict
    opt_state: tuple
    schedule: schedules.ScheduleState
    best_params: dict
    best_loss: Array
    step: Array
    average: dict


class PoseFit(eqx.Module):
    """Fits a mesh's pose to a target image with a smoothed renderer (a frozen configuration).

    ``state = fit.init(translation)`` then ``state, loss = fit.step(state, key, mesh, camera,
    target, initial_rotation)`` once per step, each for one problem (`jax.vmap` them for a
    batch; :func:`fit_poses` runs batches of problems with restarts). The loss is
    :func:`image_loss` of the render at the pose :func:`pose_rotation`\\ (params["axis_angle"],
    initial_rotation) and params["translation"].

    Attributes:
        renderer: the renderer whose image loss is descended (perturbed, soft or hard); its
            `sigma` and `gamma` are scaled by the schedule's noise scale factor.
        steps: the number of steps of a fit (the learning rate's cosine decay and the pose
            noise's fade are spread over them).
        learning_rate: Adam's initial learning rate.
        final_learning_rate: the fraction of `learning_rate` reached at the last step.
        schedule: the noise schedule (:class:`rsmooth.schedules.Adaptive` or
            :class:`~rsmooth.schedules.Reheating`, fed d loss / d scale and the step's loss;
            its `sample_growth` makes a step average several renders); a
            :class:`rsmooth.schedules.Constant` keeps the scale at 1.
        pose_noise: the standard deviation of the pose noise at scale 1, in radians (0: off).
        pose_noise_until: the fraction of `steps` at which the pose noise has faded to 0.
        antithetic_pose: a step's renders in pairs at opposite pose noises (from two renders on).
        keep_best: track the iterate whose hard render is closest to the target.
        average_decay: with `keep_best`, also consider the exponential average of the iterates,
            with this decay per step (0: off).
        optimize_translation: descend the translation too (otherwise it stays as initialized).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from rsmooth import render
        >>> mesh = render.position_colors(render.cube())
        >>> camera = render.look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(16, 16))
        >>> fit = render.PoseFit(render.Renderer(mode="soft", sigma=1.0, faces_per_pixel=2, faces_per_tile=12), steps=2)
        >>> target = fit.hard_renderer(None, mesh, camera).rgb
        >>> state = fit.init(jnp.zeros(3))
        >>> state, loss = jax.jit(fit.step)(state, jax.random.key(0), mesh, camera, target, jnp.eye(3))
        >>> int(state.step), bool(loss >= 0)
        (1, True)

    References:
        Le Lidec, Laptev, Schmid, Carpentier, "Differentiable rendering with perturbed
        optimizers", NeurIPS 2021.
    """

    renderer: Renderer
    steps: int = eqx.field(static=True, default=200)
    learning_rate: float = eqx.field(static=True, default=0.05, converter=float)
    final_learning_rate: float = eqx.field(static=True, default=0.1, converter=float)
    schedule: schedules.Schedule = schedules.Constant()
    pose_noise: float = eqx.field(static=True, default=0.0, converter=float)
    pose_noise_until: float = eqx.field(static=True, default=1.0, converter=float)
    antithetic_pose: bool = eqx.field(static=True, default=True)
    keep_best: bool = eqx.field(static=True, default=True)
    average_decay: float = eqx.field(static=True, default=0.0, converter=float)
    optimize_translation: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if not isinstance(self.renderer, Renderer):
            raise TypeError(f"renderer must be an rsmooth.render.Renderer, got {type(self.renderer).__name__}")
        if not isinstance(self.schedule, schedules.Schedule):
            raise TypeError(f"schedule must be an rsmooth.schedules.Schedule, got {self.schedule!r}")
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"steps must be an int >= 1, got {self.steps!r}")
        for name in ("learning_rate", "final_learning_rate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not (math.isfinite(self.pose_noise) and self.pose_noise >= 0):
            raise ValueError(f"pose_noise must be a finite number >= 0 (radians), got {self.pose_noise!r}")
        if not (math.isfinite(self.pose_noise_until) and 0.0 < self.pose_noise_until <= 1.0):
            raise ValueError(f"pose_noise_until must be in (0, 1] (a fraction of the steps), got {self.pose_noise_until!r}")
        if not (math.isfinite(self.average_decay) and 0.0 <= self.average_decay < 1.0):
            raise ValueError(f"average_decay must be in [0, 1) (0: no averaging), got {self.average_decay!r}")

    @property
    def hard_renderer(self) -> Renderer:
        """The z-buffer renderer with the fit renderer's options: it scores the iterates."""
        return dataclasses.replace(self.renderer, mode="hard")

    @property
    def grows(self) -> bool:
        """Whether a step may average several renders (the schedule grows the sample count)."""
        growth = getattr(self.schedule, "sample_growth", 1)
        return self.renderer.mode == "perturbed" and growth > 1

    def optimizer(self) -> optax.GradientTransformation:
        """Adam with a cosine decay of the learning rate over `steps`."""
        return optax.adam(optax.cosine_decay_schedule(self.learning_rate, self.steps, alpha=self.final_learning_rate))

    def init(self, translation: Array) -> PoseFitState:
        """The state at the initial pose: axis-angle offset 0 and `translation` (3,)."""
        translation = jnp.asarray(translation)
        params = {"axis_angle": jnp.zeros(3, translation.dtype), "translation": translation}
        return PoseFitState(
            params=params,
            opt_state=self.optimizer().init(params),
            schedule=self.schedule.init(1.0, self.renderer.num_samples),
            best_params=params,
            best_loss=jnp.asarray(jnp.inf, translation.dtype),
            step=jnp.zeros((), jnp.int32),
            average=params,
        )

    def renders_per_step(self, schedule_state: schedules.ScheduleState) -> Array:
        """How many renders of ``renderer.num_samples`` samples per pixel a step averages."""
        return jnp.maximum(schedule_state.num_samples // self.renderer.num_samples, 1)

    def pose_noise_scale(self, scale: Array, step: Array) -> Array:
        """The pose noise's standard deviation (radians) at noise scale `scale` and `step`: it
        shrinks with the scale and fades linearly to exactly 0 at ``pose_noise_until * steps``."""
        fade_steps = max(1, round(self.pose_noise_until * self.steps))
        # max(fade_steps - t, 0) / fade_steps rather than 1 - t / fade_steps: XLA turns the
        # division into a product by a rounded reciprocal, and the end would not be exactly 0.
        fade = jnp.maximum(fade_steps - step, 0).astype(scale.dtype) / fade_steps
        return self.pose_noise * jax.lax.stop_gradient(scale) * fade

    def posed(self, mesh: Mesh, params: dict, initial_rotation: Array) -> Mesh:
        """`mesh` at the pose of `params`."""
        return transform_mesh(mesh, pose_rotation(params["axis_angle"], initial_rotation), params["translation"])

    def hard_loss(self, params: dict, mesh: Mesh, camera: Camera, target: Array, initial_rotation: Array) -> Array:
        """:func:`image_loss` of the hard render at the pose of `params`."""
        return image_loss(self.hard_renderer(None, self.posed(mesh, params, initial_rotation), camera).rgb, target)

    def render_loss(self, params, scale, key, mesh, camera, target, initial_rotation) -> Array:
        """:func:`image_loss` of one render at noise scale factor `scale` (the renderer's sigma
        and gamma times it)."""
        r = self.renderer
        image = r(key, self.posed(mesh, params, initial_rotation), camera, sigma=scale * r.sigma, gamma=scale * r.gamma)
        return image_loss(image.rgb, target)

    def layout(self, schedule_state: schedules.ScheduleState) -> tuple[Array, Array]:
        """``(poses, renders_per_pose)`` of a step: without pose noise one pose; with antithetic
        pose noise two (at :math:`\\pm\\epsilon z`) from two renders on; with independent
        pose noise one per render. Each pose takes ``renders // poses`` renders."""
        renders = self.renders_per_step(schedule_state)
        if self.pose_noise == 0:
            poses = jnp.ones_like(renders)
        elif self.antithetic_pose:
            poses = jnp.minimum(renders, 2)
        else:
            poses = renders
        return poses, renders // poses

    def estimate(self, key: Array, state: PoseFitState, mesh: Mesh, camera: Camera, target: Array, initial_rotation: Array):
        """The step's loss and its gradients with respect to the params and the noise scale.

        The mean over the step's renders (:meth:`layout`): with ``pose_key, image_key =
        split(key)``, pose ``g`` is ``axis_angle + eps z`` with z drawn from ``fold_in(pose_key,
        g // 2)`` and negated for odd ``g`` when `antithetic_pose` (else from
        ``fold_in(pose_key, g)``), and its render ``j`` draws its image noise from
        ``fold_in(image_key, g * renders_per_pose + j)``.

        With a perturbed renderer whose ``pixel_chunk`` is below 1, each pose's renders draw
        their samples at its random pixels alone (those whose
        :meth:`~rsmooth.render.Renderer.uncertainty` exceeds :data:`~rsmooth.render.NEGLIGIBLE`),
        in chunks of that fraction of the image, and one hard render gives the other pixels,
        whose every sample is the hard pixel: the same estimate, with the same keys, as whole
        renders. The loss being a sum over pixels, the chunks are taken at the loss: the
        ranking and the hard render are shared by a pose's renders, where the renderer's own
        chunking would redo them for each render.

        Returns:
            ``(loss, (grad_params, d_loss_d_scale))``.
        """
        pose_key, image_key = jax.random.split(key)
        scale = state.schedule.sigma
        eps = self.pose_noise_scale(scale, state.step)
        renderer = self.renderer
        levels = dict(sigma=scale * renderer.sigma, gamma=scale * renderer.gamma)

        def pose(g):
            params = state.params
            if self.pose_noise > 0:
                draw = g // 2 if self.antithetic_pose else g
                sign = jnp.where((g % 2 == 1) & self.antithetic_pose, -1.0, 1.0).astype(scale.dtype)
                z = jax.random.normal(jax.random.fold_in(pose_key, draw), (3,), scale.dtype)
                params = {**params, "axis_angle": params["axis_angle"] + sign * eps * z}
            return params

        chunked = renderer.mode == "perturbed" and renderer.pixel_chunk < 1.0
        if not chunked:
            value_and_grads = jax.value_and_grad(self.render_loss, argnums=(0, 1))
            if not self.grows:  # one render: no loop in the program
                return value_and_grads(pose(0), scale, jax.random.fold_in(image_key, 0), mesh, camera, target, initial_rotation)
            poses, per_pose = self.layout(state.schedule)
            renders = poses * per_pose

            def add_render(i, total):
                out = value_and_grads(pose(i // per_pose), scale, jax.random.fold_in(image_key, i), mesh, camera, target, initial_rotation)
                return jax.tree.map(jnp.add, total, out)

            zero = jax.tree.map(jnp.zeros_like, (jnp.zeros((), target.dtype), (state.params, scale)))
            total = jax.lax.fori_loop(0, renders, add_render, zero)
            return jax.tree.map(lambda a: a / renders.astype(a.dtype), total)

        # perturbed renders of the random pixels alone, in chunks
        whole = dataclasses.replace(renderer, pixel_chunk=1.0)
        height, width = camera.image_size
        num_pixels = height * width
        chunk = min(num_pixels, max(1, round(renderer.pixel_chunk * num_pixels)))
        flat_target = target.reshape(-1, 3)
        poses, per_pose = self.layout(state.schedule)
        share = 1.0 / per_pose.astype(target.dtype)

        def hard_part(params, weight):
            image = self.hard_renderer(None, self.posed(mesh, params, initial_rotation), camera).rgb
            return jnp.sum(weight[..., None] * (image - target) ** 2) / target.size

        def random_part(params, s, key, pixels, weight):
            posed = self.posed(mesh, params, initial_rotation)
            image = whole(key, posed, camera, sigma=s * renderer.sigma, gamma=s * renderer.gamma, pixels=pixels)
            return jnp.sum(weight[:, None] * (image.rgb - flat_target[pixels]) ** 2) / target.size

        def add_pose(g, total):
            params = pose(g)
            posed = jax.lax.stop_gradient(self.posed(mesh, params, initial_rotation))
            uncertainty = renderer.uncertainty(posed, camera, **levels).reshape(-1)
            order, chunks = random_pixel_chunks(uncertainty, chunk)
            random = uncertainty > NEGLIGIBLE  # the chunks count these pixels, the hard render the others
            loss, grad = jax.value_and_grad(hard_part)(params, (~random).astype(target.dtype).reshape(height, width))
            total = jax.tree.map(jnp.add, total, (loss, (grad, jnp.zeros_like(scale))))

            def add_chunk(j, total):
                pixels, fresh = chunk_rows(order, j // per_pose, chunk)
                weight = jnp.where(fresh & random[pixels], share, 0.0)
                key = jax.random.fold_in(image_key, g * per_pose + j % per_pose)
                out = jax.value_and_grad(random_part, argnums=(0, 1))(params, scale, key, pixels, weight)
                return jax.tree.map(jnp.add, total, out)

            return jax.lax.fori_loop(0, chunks * per_pose, add_chunk, total)

        zero = jax.tree.map(jnp.zeros_like, (jnp.zeros((), target.dtype), (state.params, scale)))
        total = jax.lax.fori_loop(0, poses, add_pose, zero)
        return jax.tree.map(lambda a: a / poses.astype(a.dtype), total)

    def step(
        self, state: PoseFitState, key: Array, mesh: Mesh, camera: Camera, target: Array, initial_rotation: Array
    ) -> tuple[PoseFitState, Array]:
        """One Adam step of one problem.

        Args:
            state: the fit's state.
            key: PRNG key of this step (the renderer's noise and the pose noise).
            mesh: the mesh at the identity pose (coloured so that its pose shows in an image).
            camera: the camera of the target image.
            target: (H, W, 3) the target image.
            initial_rotation: (3, 3) :math:`R_0`, about which the axis-angle offset rotates.

        Returns:
            ``(state, loss)``: the new state and the loss estimate at the old params.
        """
        loss, (grad, scale_grad) = self.estimate(key, state, mesh, camera, target, initial_rotation)
        if not self.optimize_translation:
            grad = {**grad, "translation": jnp.zeros_like(grad["translation"])}
        updates, opt_state = self.optimizer().update(grad, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        sched = self.schedule.update(state.schedule, scale_grad, loss=loss)
        average, best_params, best_loss = state.average, state.best_params, state.best_loss
        candidates = [params]
        if self.average_decay > 0:
            decay = self.average_decay
            average = jax.tree.map(lambda a, p: decay * a + (1.0 - decay) * p, average, params)
            candidates.append(average)
        if self.keep_best:
            for candidate in candidates:
                current = self.hard_loss(candidate, mesh, camera, target, initial_rotation)
                better = current < best_loss
                best_params = jax.tree.map(lambda new, old: jnp.where(better, new, old), candidate, best_params)
                best_loss = jnp.minimum(current, best_loss)
        new = PoseFitState(params, opt_state, sched, best_params, best_loss, state.step + 1, average)
        return new, loss

    def reported(self, state: PoseFitState) -> dict:
        """The params a fit reports: the best iterate with `keep_best`, else the last."""
        return state.best_params if self.keep_best else state.params


@dataclasses.dataclass(frozen=True)
class PoseFitResult:
    """What :func:`fit_poses` returns, per problem (numpy arrays, leading axis: the problems).

    Attributes:
        rotation: (N, 3, 3) the reported rotation (:meth:`PoseFit.reported`, of the run whose
            hard render is closest to the target).
        translation: (N, 3) its translation.
        loss: (N,) :func:`image_loss` of its hard render to the target.
        initial_loss: (N,) the same at the initial pose.
        trajectory: (steps + 1, N, 3, 3) the iterates' rotations of the reported run, from the
            initial one.
        first_rotation: (N, 3, 3) the rotation the first run reported.
        runs: (N,) the runs per problem (1 without restarts).
        final_scale: (N,) the noise scale factor at the end of the reported run.
        final_num_samples: (N,) the samples per pixel of its last step, in all its renders.
        step_seconds: wall times of the full-batch steps after each batch's first step.
        batch_size: the problems per batch actually run.
    """

    rotation: np.ndarray
    translation: np.ndarray
    loss: np.ndarray
    initial_loss: np.ndarray
    trajectory: np.ndarray
    first_rotation: np.ndarray
    runs: np.ndarray
    final_scale: np.ndarray
    final_num_samples: np.ndarray
    step_seconds: list
    batch_size: int


_COMPILED: dict = {}  # the last few batched steps, by (fit, mesh, camera)


def _digest(tree) -> str:
    digest = hashlib.sha1()
    for leaf in jax.tree.leaves(tree):
        digest.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
    return digest.hexdigest()


def _compiled(fit: PoseFit, mesh: Mesh, camera: Camera):
    """(init, step, hard loss), jitted and vmapped over problems (spread over the devices when
    there are several, :mod:`rsmooth.parallel`), reused by later calls with an equal fit, mesh
    and camera: a step compiles in seconds, and sweeps call fit_poses again and again."""
    key = (fit, _digest(mesh), _digest(camera))
    if key not in _COMPILED:
        while len(_COMPILED) >= 8:
            _COMPILED.pop(next(iter(_COMPILED)))

        def step(state, key, target, initial_rotation):
            state, loss = fit.step(state, key, mesh, camera, target, initial_rotation)
            return state, loss, pose_rotation(state.params["axis_angle"], initial_rotation)

        def hard_loss(rotation, translation, target):
            return image_loss(fit.hard_renderer(None, transform_mesh(mesh, rotation, translation), camera).rgb, target)

        # The loop of fit_poses checks each step's loss on the host: the step's program leaves
        # out the traced checks, so that the persistent compilation cache can keep it.
        _COMPILED[key] = (
            jax.jit(jax.vmap(fit.init)),
            jax.jit(_checks.without_traced_checks()(parallel.vmap_samples(step))),
            jax.jit(jax.vmap(hard_loss)),
        )
    return _COMPILED[key]


def fit_poses(
    fit: PoseFit,
    key: Array,
    mesh: Mesh,
    camera: Camera,
    targets: Array,
    initial_rotations: Array,
    initial_translations: Array,
    *,
    batch_size: int = 25,
    restarts: int = 0,
    restart_loss: float = 0.05,
    on_step: Optional[Callable] = None,
) -> PoseFitResult:
    """Fits the poses of N independent problems (same mesh and camera), in batches, with restarts.

    The problems run in as few batches of equal size as `batch_size` allows (a short last
    batch is padded by repeating a problem, so that every batch runs one compiled step).
    Problem ``i`` draws step ``t``'s noise from ``fold_in(fold_in(fold_in(key, run), i), t)``:
    a problem's result does not depend on the others run with it. After the first run, a
    problem whose reported pose renders (hard) further from its target than `restart_loss`
    times its initial pose's image is run again from its initial pose with fresh noise, up to
    `restarts` more runs; it reports the run whose hard render is closest to its target.

    Args:
        fit: the pose fit (its `steps` steps per run).
        key: PRNG key of every run's noise.
        mesh: the mesh at the identity pose.
        camera: the camera of the targets.
        targets: (N, H, W, 3) target images.
        initial_rotations: (N, 3, 3) the initial rotations.
        initial_translations: (N, 3) the initial translations.
        batch_size: the most problems optimized at once (vmapped).
        restarts: the most runs a problem gets after its first (0: one run).
        restart_loss: the fraction of the initial image loss above which a problem is rerun.
        on_step: called after every step as ``on_step(run, problems, t, rotation, translation)``
            with the run (0: the first), the batch's problem indices (N,), the step and the
            batch's iterates (unpadded).

    Returns:
        A :class:`PoseFitResult`.

    Raises:
        FloatingPointError: where a step's loss or pose is not finite (checked on the host
            after every step; the step's program leaves out the traced checks so that JAX's
            persistent compilation cache can keep it).
    """
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"batch_size must be an int >= 1, got {batch_size!r}")
    if isinstance(restarts, bool) or not isinstance(restarts, int) or restarts < 0:
        raise ValueError(f"restarts must be an int >= 0, got {restarts!r}")
    if not (math.isfinite(restart_loss) and restart_loss > 0):
        raise ValueError(f"restart_loss must be a finite number > 0 (a fraction of the initial loss), got {restart_loss!r}")
    count = int(targets.shape[0])
    batch = -(-count // -(-count // batch_size))  # as few batches as batch_size allows, of equal sizes
    init, step, hard_loss = _compiled(fit, mesh, camera)
    step_keys = jax.jit(lambda keys, t: jax.vmap(lambda k: jax.random.fold_in(k, t))(keys))
    elapsed: list = []

    def run_problems(run, indices):
        """One run of the problems `indices`: their trajectories (steps + 1, n, 3, 3), reported
        rotations and translations, final scales and samples per pixel."""
        run_key = jax.random.fold_in(key, run)
        trajectories, rotations, translations, scales, samples = [], [], [], [], []
        for lo in range(0, len(indices), batch):
            chunk = indices[lo:lo + batch]
            size = len(chunk)
            padded = chunk[np.minimum(np.arange(batch), size - 1)]
            keys = jax.vmap(lambda i: jax.random.fold_in(run_key, i))(jnp.asarray(padded))
            state = init(initial_translations[padded])
            chunk_targets, chunk_r0 = targets[padded], initial_rotations[padded]
            trajectory = [np.asarray(initial_rotations[chunk])]
            for t in range(fit.steps):
                start = time.perf_counter()
                state, loss, rotation = step(state, step_keys(keys, t), chunk_targets, chunk_r0)
                _checks.check_outputs_on_host({"loss": loss, "rotation": rotation}, f"fit_poses, step {t}")
                if t > 0 and size == batch:  # full batches after their first step (which may compile)
                    elapsed.append(time.perf_counter() - start)
                trajectory.append(np.asarray(rotation[:size]))
                if on_step is not None:
                    on_step(run, chunk, t, rotation[:size], state.params["translation"][:size])
            reported = fit.reported(state)
            rotations.append(np.asarray(jax.vmap(pose_rotation)(reported["axis_angle"], chunk_r0))[:size])
            translations.append(np.asarray(reported["translation"])[:size])
            trajectories.append(np.stack(trajectory))
            scales.append(np.asarray(state.schedule.sigma)[:size])
            samples.append(np.asarray(fit.renders_per_step(state.schedule))[:size] * fit.renderer.num_samples)
        return (np.concatenate(trajectories, axis=1), np.concatenate(rotations), np.concatenate(translations),
                np.concatenate(scales), np.concatenate(samples))

    everything = np.arange(count)
    trajectory, rotation, translation, scale, samples = run_problems(0, everything)
    loss = np.array(hard_loss(jnp.asarray(rotation), jnp.asarray(translation), targets))
    initial_loss = np.asarray(hard_loss(initial_rotations, initial_translations, targets))
    first = rotation.copy()
    runs = np.ones(count, int)
    for run in range(1, restarts + 1):
        again = everything[loss > restart_loss * initial_loss]
        if again.size == 0:
            break
        redo = run_problems(run, again)
        runs[again] += 1
        redo_loss = np.asarray(hard_loss(jnp.asarray(redo[1]), jnp.asarray(redo[2]), targets[again]))
        take = redo_loss < loss[again]
        better = again[take]
        trajectory[:, better] = redo[0][:, take]
        rotation[better], translation[better] = redo[1][take], redo[2][take]
        scale[better], samples[better] = redo[3][take], redo[4][take]
        loss[better] = redo_loss[take]
    return PoseFitResult(
        rotation=rotation, translation=translation, loss=loss, initial_loss=initial_loss, trajectory=trajectory,
        first_rotation=first, runs=runs, final_scale=scale, final_num_samples=samples, step_seconds=elapsed,
        batch_size=batch,
    )
