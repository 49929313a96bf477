"""rsmooth.render.PoseFit and fit_poses: pose noise, sample growth, random-pixel chunks,
keep-best and iterate averaging, batches and restarts, on a small cube."""

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import noise, render, schedules

MESH = render.position_colors(render.cube(1.2))


def _camera(size):
    return render.look_at(jnp.array([0.0, 0.0, 4.0]), image_size=(size, size), fov=40.0, near=2.0, far=6.0)


def _renderer(size, mode="perturbed", **changes):
    options = dict(
        sigma=3.0 * size / 128.0, gamma=0.02, faces_per_pixel=4, faces_per_tile=32, cull_backfaces=True,
        num_samples=8, coverage_noise=noise.Gaussian(),
    )
    if mode == "soft":
        options.update(dilation=6.0)
    return render.Renderer(mode=mode, **{**options, **changes})


def _schedule(**changes):
    return schedules.Adaptive(**{**dict(factor=2.0, momentum=0.9, floor=0.05, patience=10), **changes})


def _problems(key, count, error_deg):
    """Target rotations and initial rotations `error_deg` from them, about random axes."""
    k_true, k_axis = jax.random.split(key)
    r_true = jax.vmap(lambda k: render.quaternion_to_matrix(jax.random.normal(k, (4,))))(jax.random.split(k_true, count))
    axis = jax.random.normal(k_axis, (count, 3))
    axis = axis / jnp.linalg.norm(axis, axis=1, keepdims=True)
    return r_true, jax.vmap(render.pose_rotation)(np.deg2rad(error_deg) * axis, r_true)


@functools.lru_cache
def _hard_images(size):
    """A jitted function from rotations (N, 3, 3) to the mesh's hard images (N, H, W, 3)."""
    hard, camera = _renderer(size, "hard"), _camera(size)
    return jax.jit(jax.vmap(lambda r: hard(None, render.transform_mesh(MESH, r), camera).rgb))


def _targets(size, rotations):
    return _hard_images(size)(jnp.asarray(rotations))


def _with_samples(state, num_samples, scale=None):
    """`state` (one problem or a batch) whose schedule holds `num_samples` samples per pixel."""
    sched = state.schedule
    sched = eqx.tree_at(lambda s: s.num_samples, sched, jnp.full_like(sched.num_samples, num_samples))
    if scale is not None:
        sched = eqx.tree_at(lambda s: s.sigma, sched, jnp.full_like(sched.sigma, scale))
    return eqx.tree_at(lambda s: s.schedule, state, sched)


def test_pose_rotation_composes_the_offset_with_the_initial_rotation():
    r0 = render.axis_angle_to_matrix(jnp.array([0.3, -0.2, 0.5]))
    omega = jnp.array([0.0, 0.4, 0.1])
    np.testing.assert_allclose(render.pose_rotation(omega, r0), render.axis_angle_to_matrix(omega) @ r0, rtol=1e-12)
    np.testing.assert_allclose(render.pose_rotation(jnp.zeros(3), r0), r0, rtol=1e-12)


def test_bad_fits_are_rejected():
    renderer = _renderer(16)
    for change, name in (
        ({"steps": 0}, "steps"), ({"pose_noise": -1.0}, "pose_noise"), ({"pose_noise_until": 0.0}, "pose_noise_until"),
        ({"pose_noise_until": 1.5}, "pose_noise_until"), ({"average_decay": 1.0}, "average_decay"),
        ({"learning_rate": float("nan")}, "learning_rate"),
    ):
        with pytest.raises(ValueError, match=name):
            render.PoseFit(renderer, **change)
    with pytest.raises(TypeError, match="renderer"):
        render.PoseFit("perturbed")
    with pytest.raises(ValueError, match="restarts"):
        render.fit_poses(render.PoseFit(renderer), jax.random.key(0), MESH, _camera(16), jnp.zeros((1, 16, 16, 3)),
                         jnp.eye(3)[None], jnp.zeros((1, 3)), restarts=-1)


def test_keep_best_holds_the_closest_iterate_among_the_iterates_and_their_average():
    # keep_best picks the iterate whose hard render is closest to the target; with average_decay,
    # among the iterates and their exponential average (started at the initial pose), which does
    # not change the iterates. From 4 deg with steps of up to 11 deg, Adam overshoots and the
    # average is sometimes nearer.
    size = 24
    camera = _camera(size)
    plain = render.PoseFit(_renderer(size), steps=60, learning_rate=0.2, schedule=_schedule(), pose_noise=np.deg2rad(25.0))
    averaged = dataclasses.replace(plain, average_decay=0.7)
    r_true, r_init = _problems(jax.random.key(5), 2, 4.0)
    targets = _targets(size, r_true)

    def run(fit):
        step = jax.jit(jax.vmap(lambda s, k, t, r: fit.step(s, k, MESH, camera, t, r)))
        state, iterates = jax.vmap(fit.init)(jnp.zeros((2, 3))), []
        for t in range(6):
            state = step(state, jax.random.split(jax.random.key(t), 2), targets, r_init)[0]
            iterates.append(np.asarray(state.params["axis_angle"]))
        return state, np.stack(iterates)

    def hard_losses(omegas):
        rotations = jax.vmap(render.pose_rotation)(jnp.asarray(omegas), r_init)
        return np.mean((np.asarray(_targets(size, rotations)) - np.asarray(targets)) ** 2, axis=(1, 2, 3))

    plain_state, plain_iterates = run(plain)
    losses = np.stack([hard_losses(o) for o in plain_iterates])
    best = np.argmin(losses, axis=0)
    assert not np.all(best == 5)  # the selection is exercised: not merely the last iterate
    np.testing.assert_allclose(plain_state.best_loss, losses[best, [0, 1]], rtol=1e-5)
    np.testing.assert_allclose(plain_state.best_params["axis_angle"], plain_iterates[best, [0, 1]], rtol=1e-6)
    np.testing.assert_array_equal(plain.reported(plain_state)["axis_angle"], plain_state.best_params["axis_angle"])

    state, iterates = run(averaged)
    # the same iterates, up to rounding: the two steps are different programs, fused differently
    np.testing.assert_allclose(iterates, plain_iterates, rtol=1e-10, atol=1e-12)
    averages, average = [], np.zeros_like(iterates[0])
    for omega in iterates:
        average = 0.7 * average + 0.3 * omega
        averages.append(average)
    np.testing.assert_allclose(state.average["axis_angle"], average, rtol=1e-6, atol=1e-9)
    candidates = np.stack([c for pair in zip(iterates, averages) for c in pair])  # in step order
    losses = np.stack([hard_losses(c) for c in candidates])
    best = np.argmin(losses, axis=0)
    assert np.any(best % 2 == 1)  # an average was the closest for some problem
    np.testing.assert_allclose(state.best_loss, losses[best, [0, 1]], rtol=1e-5)
    np.testing.assert_allclose(state.best_params["axis_angle"], candidates[best, [0, 1]], rtol=1e-5, atol=1e-8)
    assert np.all(np.asarray(state.best_loss) <= np.asarray(plain_state.best_loss))


def test_pose_noise_fades_out_at_pose_noise_until():
    # The soft renderer draws nothing: the pose noise is the step's only randomness, so two keys
    # give different steps until the noise has faded out (at pose_noise_until x steps) and the
    # same step from there on.
    size = 16
    camera = _camera(size)
    fit = render.PoseFit(
        _renderer(size, "soft"), steps=60, schedule=_schedule(), pose_noise=np.deg2rad(40.0), pose_noise_until=0.5,
        keep_best=False,
    )
    fade_steps = 30
    r_true, r_init = _problems(jax.random.key(2), 1, 30.0)
    target = _targets(size, r_true)[0]
    step = jax.jit(lambda s, k: fit.step(s, k, MESH, camera, target, r_init[0])[0].params["axis_angle"])

    def omegas(t):
        state = eqx.tree_at(lambda s: s.step, fit.init(jnp.zeros(3)), jnp.asarray(t, jnp.int32))
        return [np.asarray(step(state, jax.random.key(k))) for k in (0, 1)]

    first = omegas(0)
    assert np.all(np.abs(first[0]) > 0) and not np.allclose(first[0], first[1])
    almost = omegas(fade_steps - 1)  # the last smoothed step: 1 / fade_steps of the noise
    assert not np.array_equal(almost[0], almost[1])
    for t in (fade_steps, fit.steps):
        faded = omegas(t)
        np.testing.assert_array_equal(faded[0], faded[1])


def test_sample_growth_averages_renders_at_antithetic_pose_pairs():
    # A step whose schedule holds 4 M samples per pixel averages four renders of M, two at each
    # pose of an antithetic pair (+eps z, -eps z), with the keys PoseFit.estimate documents: its
    # loss and gradients are the mean of the one-render losses and gradients.
    size = 16
    camera = _camera(size)
    fit = render.PoseFit(
        _renderer(size, num_samples=4), steps=60, schedule=_schedule(sample_growth=2, max_num_samples=16),
        pose_noise=np.deg2rad(25.0),
    )
    assert fit.grows
    r_true, r_init = _problems(jax.random.key(3), 1, 30.0)
    target, r0 = _targets(size, r_true)[0], r_init[0]
    state = fit.init(jnp.zeros(3))
    assert int(state.schedule.num_samples) == 4
    key = jax.random.key(7)
    estimate = jax.jit(lambda s: fit.estimate(key, s, MESH, camera, target, r0))
    loss, (grad, scale_grad) = estimate(_with_samples(state, 16))

    pose_key, image_key = jax.random.split(key)
    eps = fit.pose_noise  # at scale 1, step 0
    z = jax.random.normal(jax.random.fold_in(pose_key, 0), (3,))
    one = jax.jit(jax.value_and_grad(lambda p, s, k: fit.render_loss(p, s, k, MESH, camera, target, r0), argnums=(0, 1)))
    outs = []
    for i in range(4):
        sign = 1.0 if i // 2 == 0 else -1.0
        params = {**state.params, "axis_angle": state.params["axis_angle"] + sign * eps * z}
        outs.append(one(params, jnp.asarray(1.0), jax.random.fold_in(image_key, i)))
    mean = jax.tree.map(lambda *xs: sum(xs) / 4, *outs)
    assert not np.allclose(outs[0][1][1], outs[1][1][1])  # the renders' noise differs
    np.testing.assert_allclose(loss, mean[0], rtol=1e-10)
    np.testing.assert_allclose(grad["axis_angle"], mean[1][0]["axis_angle"], rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(scale_grad, mean[1][1], rtol=1e-8, atol=1e-14)


def test_perturbed_renders_of_the_random_pixels_alone_give_the_whole_renders_estimate():
    # Where the noise cannot change a pixel (Renderer.uncertainty ~ 0), every sample gives it the
    # hard pixel's value and derivative: with pixel_chunk < 1 the perturbed renders draw only the
    # random pixels, in chunks, and one hard render per pose draws the others. The estimate is
    # then the one of whole renders with the same keys, pose noise included, with one render (4
    # samples) and with four at two antithetic poses (16), in chunks of 141 pixels: two, the
    # second overlapping the first (most of the 256 pixels are random at sigma 6 px).
    size = 16
    camera = _camera(size)
    whole = render.PoseFit(
        _renderer(size, num_samples=4, sigma=6.0 * size / 128.0), steps=60,
        schedule=_schedule(sample_growth=2, max_num_samples=16), pose_noise=np.deg2rad(25.0),
    )
    chunked = dataclasses.replace(whole, renderer=dataclasses.replace(whole.renderer, pixel_chunk=0.55))
    r_true, r_init = _problems(jax.random.key(3), 1, 30.0)
    target, r0 = _targets(size, r_true)[0], r_init[0]
    random = whole.renderer.uncertainty(render.transform_mesh(MESH, r0), camera) > render.NEGLIGIBLE
    assert 0.55 < float(jnp.mean(random)) < 0.9  # the premise: two chunks of 0.55, overlapping
    state = whole.init(jnp.zeros(3))
    key = jax.random.key(7)

    def estimates(fit):
        estimate = jax.jit(lambda s: fit.estimate(key, s, MESH, camera, target, r0))
        return [estimate(_with_samples(state, samples)) for samples in (4, 16)]

    expected = estimates(whole)
    assert not np.allclose(expected[0][1][1], expected[1][1][1])  # the renders differ
    for a, b in zip(expected, estimates(chunked)):
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_allclose(y, x, rtol=1e-9, atol=1e-15)


def test_antithetic_pose_noise_keeps_the_mean_gradient_and_lowers_its_variance():
    # Two poses per step, delta + eps z and delta - eps z: the first-order terms of the pose noise
    # cancel in their mean. The same problem 32 times near its solution, with 32 samples per
    # pixel so that the pose noise dominates the gradient's variance; random-pixel chunks.
    n, size = 32, 32
    camera = _camera(size)
    base = render.PoseFit(
        _renderer(size, num_samples=32, pixel_chunk=0.125), steps=60, schedule=_schedule(sample_growth=2, max_num_samples=64),
        pose_noise=np.deg2rad(25.0),
    )
    # a pose whose gradient's variance near the solution is mostly the pose noise's
    k_true = jax.random.split(jax.random.key(0), 3)[0]
    r_true = render.quaternion_to_matrix(jax.random.normal(jax.random.split(k_true, 32)[0], (4,), jnp.float32).astype(float))
    r0 = render.axis_angle_to_matrix(jnp.array([0.01, -0.01, 0.005])) @ r_true
    target = _targets(size, r_true[None])[0]
    keys = jax.random.split(jax.random.key(5), n)

    def gradients(antithetic):
        fit = dataclasses.replace(base, antithetic_pose=antithetic)
        state = _with_samples(fit.init(jnp.zeros(3)), 64, scale=0.25)
        estimate = jax.jit(jax.vmap(lambda k: fit.estimate(k, state, MESH, camera, target, r0)[1][0]["axis_angle"]))
        return np.asarray(estimate(keys))

    independent, antithetic = gradients(False), gradients(True)
    assert np.all(antithetic.std(axis=0) < 0.7 * independent.std(axis=0))
    stderr = np.sqrt((independent.var(axis=0) + antithetic.var(axis=0)) / n)
    assert np.all(np.abs(antithetic.mean(axis=0) - independent.mean(axis=0)) < 4 * stderr)


@pytest.mark.slow
def test_fit_poses_runs_batches_independently_and_restarts_far_problems():
    # 3 problems, 2 at a time: every problem gets its result, and a problem's result does not
    # depend on the others run with it (its own keys); the short last batch is padded (one
    # compiled step, reused by later calls with an equal fit, mesh and camera).
    size = 24
    camera = _camera(size)
    fit = render.PoseFit(_renderer(size), steps=3, schedule=_schedule(), pose_noise=np.deg2rad(25.0), keep_best=False)
    r_true, r_init = _problems(jax.random.key(4), 3, 60.0)
    targets = _targets(size, r_true)
    zeros = jnp.zeros((3, 3))
    render._pose._COMPILED.clear()
    seen = []

    def run(count, **options):
        return render.fit_poses(fit, jax.random.key(3), MESH, camera, targets[:count], r_init[:count], zeros[:count],
                                batch_size=2, **options)

    once = run(3, on_step=lambda run, problems, t, rotation, translation: seen.append((run, tuple(problems), t)))
    assert once.batch_size == 2 and once.rotation.shape == (3, 3, 3) and once.trajectory.shape == (4, 3, 3, 3)
    assert seen == [(0, (0, 1), t) for t in range(3)] + [(0, (2,), t) for t in range(3)]
    assert len(once.step_seconds) == 2 and all(s > 0 for s in once.step_seconds)
    np.testing.assert_array_equal(once.runs, 1)
    np.testing.assert_allclose(once.trajectory[-1], once.rotation)  # keep_best off: the last iterate
    alone = run(2)
    np.testing.assert_allclose(alone.rotation, once.rotation[:2], rtol=1e-12)
    assert len(render._pose._COMPILED) == 1
    assert next(iter(render._pose._COMPILED.values()))[1]._cache_size() == 1
    # the losses are the hard image's mean squared error to the target, of the reported pose and
    # of the initial one
    reported = _targets(size, jnp.asarray(once.rotation))
    np.testing.assert_allclose(once.loss, np.mean((reported - targets) ** 2, axis=(1, 2, 3)), rtol=1e-6)
    initial = _targets(size, r_init)
    np.testing.assert_allclose(once.initial_loss, np.mean((initial - targets) ** 2, axis=(1, 2, 3)), rtol=1e-6)

    # no problem is far enough from its target: the first run is the result
    kept = run(3, restarts=2, restart_loss=1e9)
    np.testing.assert_array_equal(kept.runs, 1)
    np.testing.assert_array_equal(kept.rotation, once.rotation)
    # every problem is (any loss is above a tiny fraction of the initial one): two more runs
    # each, with fresh noise, and each reports its closest run
    rerun = run(3, restarts=2, restart_loss=1e-12)
    np.testing.assert_array_equal(rerun.runs, 3)
    np.testing.assert_array_equal(rerun.first_rotation, once.rotation)
    assert np.all(rerun.loss <= once.loss) and np.any(rerun.loss < once.loss), (once.loss, rerun.loss)
    changed = rerun.loss < once.loss
    assert not np.allclose(rerun.rotation[changed], once.rotation[changed])
    np.testing.assert_allclose(rerun.trajectory[-1], rerun.rotation)  # the trajectory of the reported run
