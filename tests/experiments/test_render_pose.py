"""The render-pose experiment, small: the perturbed renderer recovers a cube's rotation."""

import dataclasses
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rsmooth import render
from rsmooth.experiments import render_pose


@pytest.mark.slow
def test_perturbed_renderer_solves_a_cube_from_20_degrees(tmp_path):
    # The quick profile's defaults (48 px, 60 Adam steps, back faces culled on the closed cube),
    # two problems.
    config = dataclasses.replace(
        render_pose.Config.quick(), problems=2, methods=("perturbed-gaussian",), init_errors_deg=(20.0,), gif_every=5,
    )
    metrics = render_pose.run(config, tmp_path, jax.random.key(0), progress=False)
    result = metrics["perturbed-gaussian"]["20"]
    assert result["solved_pct"] == 100.0, result
    assert result["mean_error_deg"] < 10.0
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["perturbed-gaussian"]["20"]["solved_pct"] == 100.0
    assert saved["cull_backfaces"] is True and saved["faces_per_pixel"] == render_pose.Config.faces_per_pixel
    assert saved["num_samples"] == config.num_samples == 8  # the quick profile's (the default: 16)
    for name in ("errors.png", "renders_20deg.png", "optimization.gif"):
        assert (tmp_path / name).stat().st_size > 0
    assert not list(tmp_path.glob(".*"))


@pytest.mark.slow
def test_problems_run_in_batches(tmp_path):
    # 3 problems, 2 at a time: every problem gets its result, and the first batch's are those of
    # a run of exactly its 2 problems (same targets, same keys).
    # (keep_best off: its hard render would double the step's compilation; the other tests cover it)
    small = dataclasses.replace(
        render_pose.Config.quick(), image_size=24, steps=3, methods=("perturbed-gaussian",), init_errors_deg=(30.0,),
        gif_every=1, keep_best=False,
    )
    render_pose._SOLVERS.clear()
    batched = render_pose.run(dataclasses.replace(small, problems=3, batch_size=2), tmp_path / "a", jax.random.key(3), progress=False)
    result = batched["perturbed-gaussian"]["30"]
    assert len(result["final_errors_deg"]) == 3 and batched["batch_size"] == 2
    assert result["seconds_per_step"] > 0
    alone = render_pose.run(dataclasses.replace(small, problems=2, batch_size=2), tmp_path / "b", jax.random.key(3), progress=False)
    np.testing.assert_allclose(result["final_errors_deg"][:2], alone["perturbed-gaussian"]["30"]["final_errors_deg"], atol=1e-4)
    # the short last batch was padded to 2 (one compiled step), and the second run, which poses
    # other problems with the same step, reused it
    assert len(render_pose._SOLVERS) == 1
    assert next(iter(render_pose._SOLVERS.values()))[1]._cache_size() == 1


@pytest.mark.slow
def test_restarts_rerun_the_problems_whose_render_stays_far_from_the_target(tmp_path):
    small = dataclasses.replace(
        render_pose.Config.quick(), image_size=24, steps=3, methods=("perturbed-gaussian",), init_errors_deg=(60.0,),
        problems=3, batch_size=2, keep_best=False,
    )

    def run(name, **change):
        metrics = render_pose.run(dataclasses.replace(small, **change), tmp_path / name, jax.random.key(4), progress=False)
        return metrics["perturbed-gaussian"]["60"]

    once = run("once")
    assert once["runs_per_problem"] == 1.0 and once["first_run_solved_pct"] == once["solved_pct"]
    # the losses are the hard image's mean squared error to the target, of the reported pose and
    # of the initial one
    config = small
    mesh, cam = render_pose.load(config.mesh), render_pose.camera(config)
    hard = render_pose.make_renderer(config, "hard", mesh)
    r_true, r_init, _ = render_pose.problems(config, jax.random.fold_in(jax.random.split(jax.random.key(4))[0], 0), 60.0)
    for i in range(3):
        target = hard(None, render.transform_mesh(mesh, r_true[i], jnp.zeros(3)), cam).rgb
        start = hard(None, render.transform_mesh(mesh, r_init[i], jnp.zeros(3)), cam).rgb
        np.testing.assert_allclose(once["initial_losses"][i], float(jnp.mean((start - target) ** 2)), rtol=1e-5)
    assert all(0.0 <= final for final in once["final_losses"])

    # no problem is far enough from its target: the first run is the result
    kept = run("kept", restarts=2, restart_loss=1e9)
    assert kept["runs_per_problem"] == 1.0 and kept["final_errors_deg"] == once["final_errors_deg"]
    # every problem is (any loss is above a tiny fraction of the initial one): two more runs
    # each, with fresh noise, and each reports its closest run
    rerun = run("rerun", restarts=2, restart_loss=1e-12)
    assert rerun["runs_per_problem"] == 3.0
    assert rerun["first_run_solved_pct"] == once["solved_pct"]
    first, best = np.array(once["final_losses"]), np.array(rerun["final_losses"])
    assert np.all(best <= first) and np.any(best < first), (first, best)
    changed = best < first
    assert not np.allclose(np.array(rerun["final_errors_deg"])[changed], np.array(once["final_errors_deg"])[changed])


@pytest.mark.parametrize(
    "change",
    [
        {"methods": ("blurry",)}, {"batch_size": 0}, {"problems": 0}, {"pose_noise_deg": -1.0},
        {"pose_noise_deg": float("nan")}, {"pose_noise_until": 0.0}, {"pose_noise_until": 1.5},
        {"restarts": -1}, {"restarts": 1.5}, {"restart_loss": 0.0}, {"restart_loss": float("nan")},
        {"sample_growth": 0}, {"sample_growth": 1.5}, {"max_samples": 0}, {"average_decay": 1.0},
        {"average_decay": -0.1}, {"average_decay": float("nan")}, {"baseline": "mean"}, {"pixel_chunk": 0.0},
        {"pixel_chunk": 1.5},
    ],
)
def test_bad_config_is_rejected(tmp_path, change):
    config = dataclasses.replace(render_pose.Config.quick(), **change)
    with pytest.raises(ValueError, match=next(iter(change)) if "methods" not in change else "blurry"):
        render_pose.run(config, tmp_path, jax.random.key(0), progress=False)


def test_keep_best_holds_the_iterate_whose_hard_render_is_closest_to_the_target():

    config = dataclasses.replace(render_pose.Config.quick(), image_size=24, problems=2, learning_rate=0.2)
    mesh = render_pose.load(config.mesh)
    cam = render_pose.camera(config)
    _, init, step = render_pose.make_solver(config, "perturbed-gaussian", mesh, cam)
    r_true, r_init, offset = render_pose.problems(config, jax.random.key(5), 40.0)
    hard = render_pose.make_renderer(config, "hard", mesh)
    render_hard = jax.jit(jax.vmap(lambda r: hard(None, render.transform_mesh(mesh, r), cam).rgb))
    targets = render_hard(r_true)
    state = init(offset)
    losses, deltas = [], []
    for t in range(6):
        state, _, rotation = step(state, jax.random.split(jax.random.key(t), 2), targets, r_init)
        losses.append(np.mean((np.asarray(render_hard(rotation)) - np.asarray(targets)) ** 2, axis=(1, 2, 3)))
        deltas.append(np.asarray(state[0]["delta"]))
    losses, deltas = np.stack(losses), np.stack(deltas)
    best = np.argmin(losses, axis=0)
    assert not np.all(best == 5)  # the selection is exercised: not merely the last iterate
    np.testing.assert_allclose(state[3][1], losses[best, [0, 1]], rtol=1e-5)
    np.testing.assert_allclose(state[3][0]["delta"], deltas[best, [0, 1]], rtol=1e-6)


def test_keep_best_also_considers_the_average_of_the_iterates():
    # With average_decay, keep_best picks the closest hard render among the iterates and their
    # exponential average (started at the initial pose); the iterates themselves do not change.
    # From 4 deg with steps of up to 11 deg, Adam overshoots and the average is sometimes nearer.
    config = dataclasses.replace(render_pose.Config.quick(), image_size=24, problems=2, learning_rate=0.2)
    averaged = dataclasses.replace(config, average_decay=0.7)
    mesh = render_pose.load(config.mesh)
    cam = render_pose.camera(config)
    r_true, r_init, offset = render_pose.problems(config, jax.random.key(5), 4.0)
    hard = render_pose.make_renderer(config, "hard", mesh)
    render_hard = jax.jit(jax.vmap(lambda r: hard(None, render.transform_mesh(mesh, r), cam).rgb))
    targets = render_hard(r_true)

    def run(cfg):
        _, init, step = render_pose.make_solver(cfg, "perturbed-gaussian", mesh, cam)
        state, deltas = init(offset), []
        for t in range(6):
            state = step(state, jax.random.split(jax.random.key(t), 2), targets, r_init)[0]
            deltas.append(np.asarray(state[0]["delta"]))
        return state, np.stack(deltas)

    plain_state, plain_deltas = run(config)
    state, deltas = run(averaged)
    np.testing.assert_array_equal(deltas, plain_deltas)
    averages, average = [], np.zeros_like(deltas[0])
    for delta in deltas:
        average = 0.7 * average + 0.3 * delta
        averages.append(average)
    np.testing.assert_allclose(state[5]["delta"], average, rtol=1e-6, atol=1e-9)
    candidates = np.stack([c for pair in zip(deltas, averages) for c in pair])  # (12, problems, 3), in step order

    def loss(deltas):
        rotations = jax.vmap(render_pose._rotation)(jnp.asarray(deltas), r_init)
        return np.mean((np.asarray(render_hard(rotations)) - np.asarray(targets)) ** 2, axis=(1, 2, 3))

    losses = np.stack([loss(c) for c in candidates])
    best = np.argmin(losses, axis=0)
    assert np.any(best % 2 == 1)  # an average was the closest for some problem
    np.testing.assert_allclose(state[3][1], losses[best, [0, 1]], rtol=1e-5)
    np.testing.assert_allclose(state[3][0]["delta"], candidates[best, [0, 1]], rtol=1e-5, atol=1e-8)
    assert np.all(np.asarray(state[3][1]) <= np.asarray(plain_state[3][1]))


def test_pose_noise_is_the_only_randomness_of_a_deterministic_renderer():
    # The soft renderer draws nothing: the pose smoothing is the step's only randomness, so two
    # keys give different steps until the noise has faded out (at pose_noise_until x steps)
    # and the same step from there on. The hard renderer stays unsmoothed whatever
    # pose_noise_deg says.
    config = dataclasses.replace(
        render_pose.Config.quick(), image_size=16, problems=1, keep_best=False, pose_noise_deg=40.0, pose_noise_until=0.5
    )
    fade_steps = config.steps // 2
    mesh = render_pose.load(config.mesh)
    cam = render_pose.camera(config)
    r_true, r_init, offset = render_pose.problems(config, jax.random.key(2), 30.0)
    hard = render_pose.make_renderer(config, "hard", mesh)
    target = hard(None, render.transform_mesh(mesh, r_true[0]), cam).rgb[None]

    solvers = {method: render_pose.make_solver(config, method, mesh, cam)[1:] for method in ("soft", "hard")}

    def deltas(method, t):
        init, step = solvers[method]
        state = init(offset)
        state = (*state[:4], jnp.full_like(state[4], t), *state[5:])
        return [np.asarray(step(state, jax.random.key(k)[None], target, r_init)[0][0]["delta"]) for k in (0, 1)]

    first = deltas("soft", 0)
    assert np.all(np.abs(first[0]) > 0) and not np.allclose(first[0], first[1])
    almost = deltas("soft", fade_steps - 1)  # the last smoothed step: a 1 / fade_steps of the noise
    assert not np.array_equal(almost[0], almost[1])
    for t in (fade_steps, config.steps):
        faded = deltas("soft", t)
        np.testing.assert_array_equal(faded[0], faded[1])
    unsmoothed = deltas("hard", 0)
    np.testing.assert_array_equal(unsmoothed[0], unsmoothed[1])


def test_sample_growth_averages_renders_with_independent_noise():
    # With sample_growth, a step whose schedule holds 2 M samples per pixel averages two renders
    # of M: its loss and its d loss / d noise scale (seen through the schedule's average, linear
    # in it) are the means of the one-render steps with the keys it uses, `key` and `key` folded
    # with 1; and a one-render step is the step without sample growth.
    config = dataclasses.replace(
        render_pose.Config.quick(), image_size=16, problems=1, num_samples=4, sample_growth=2, max_samples=16,
        pixel_chunk=1.0, antithetic_pose=False,
    )
    mesh = render_pose.load(config.mesh)
    cam = render_pose.camera(config)
    r_true, r_init, offset = render_pose.problems(config, jax.random.key(3), 30.0)
    hard = render_pose.make_renderer(config, "hard", mesh)
    target = hard(None, render.transform_mesh(mesh, r_true[0]), cam).rgb[None]
    _, init, step = render_pose.make_solver(config, "perturbed-gaussian", mesh, cam)
    state = init(offset)
    assert int(state[2].num_samples[0]) == config.num_samples

    def with_samples(n):  # the state with n samples per pixel in the schedule
        sched = eqx.tree_at(lambda s: s.num_samples, state[2], jnp.full_like(state[2].num_samples, n))
        return (*state[:2], sched, *state[3:])

    key = jax.random.key(7)
    singles = [step(with_samples(4), k[None], target, r_init) for k in (key, jax.random.fold_in(key, 1))]
    double = step(with_samples(8), key[None], target, r_init)
    np.testing.assert_allclose(double[1], (singles[0][1] + singles[1][1]) / 2, rtol=1e-5)
    emas = [np.asarray(out[0][2].ema) for out in singles]
    assert not np.allclose(emas[0], emas[1])  # the two renders' noise differs
    np.testing.assert_allclose(np.asarray(double[0][2].ema), (emas[0] + emas[1]) / 2, rtol=1e-4, atol=1e-9)
    _, init_plain, step_plain = render_pose.make_solver(dataclasses.replace(config, sample_growth=1), "perturbed-gaussian", mesh, cam)
    plain = step_plain(init_plain(offset), key[None], target, r_init)
    np.testing.assert_allclose(plain[1], singles[0][1], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(plain[0][0]["delta"]), np.asarray(singles[0][0][0]["delta"]), rtol=1e-6)


def test_perturbed_renders_of_the_random_pixels_alone_give_the_whole_renders_estimate():
    # Where the noise cannot change a pixel (Renderer.uncertainty ~ 0), every sample gives it the
    # hard pixel's value and derivative: with pixel_chunk < 1 the perturbed renders draw only the
    # random pixels, in chunks, and one hard render draws the others. Without pose noise the
    # step is then the one of whole renders (the same keys per pixel), with one render (4
    # samples) and with four (16), in chunks of 141 pixels: two, the second overlapping the first
    # (177 of the 256 pixels are random).
    base = dataclasses.replace(
        render_pose.Config.quick(), image_size=16, problems=1, num_samples=4, sample_growth=2, max_samples=16,
        pose_noise_deg=0.0, sigma=6.0,
    )
    mesh = render_pose.load(base.mesh)
    cam = render_pose.camera(base)
    r_true, r_init, offset = render_pose.problems(base, jax.random.key(3), 30.0)
    hard = render_pose.make_renderer(base, "hard", mesh)
    target = hard(None, render.transform_mesh(mesh, r_true[0]), cam).rgb[None]
    perturbed = render_pose.make_renderer(base, "perturbed-gaussian", mesh)
    random = perturbed.uncertainty(render.transform_mesh(mesh, render_pose._rotation(jnp.zeros(3), r_init[0])), cam) > render.NEGLIGIBLE
    assert 0.55 < float(jnp.mean(random)) < 0.9  # the premise: two chunks of 0.55, overlapping

    def steps(pixel_chunk):
        config = dataclasses.replace(base, pixel_chunk=pixel_chunk)
        _, init, step = render_pose.make_solver(config, "perturbed-gaussian", mesh, cam)
        state = init(offset)
        outs = []
        for samples in (4, 16):  # one render, four
            sched = eqx.tree_at(lambda s: s.num_samples, state[2], jnp.full_like(state[2].num_samples, samples))
            new, loss, _ = step((*state[:2], sched, *state[3:]), jax.random.key(7)[None], target, r_init)
            outs.append((float(loss[0]), np.asarray(new[2].ema), np.asarray(new[1][0].mu["delta"])))
        return outs

    whole = steps(1.0)
    assert not np.allclose(whole[0][1], whole[1][1])  # the renders differ
    for a, b in zip(whole, steps(0.55)):
        for x, y in zip(a, b):
            np.testing.assert_allclose(y, x, rtol=1e-9, atol=1e-15)


def test_antithetic_pose_noise_keeps_the_mean_gradient_and_lowers_its_variance():
    # Two renders per step at the poses delta + eps z and delta - eps z: the first-order terms of
    # the pose noise cancel in their mean. The same problem 32 times near its solution, with 32
    # samples per pixel so that the pose noise dominates the gradient's variance (measured: std
    # ratios 0.41-0.53; at 128 x 128 and the noise floor 0.19-0.37, benchmarks/RESULTS.md). The
    # default's perturbed renders of the random pixels alone (pixel_chunk; whole renders take
    # the same poses, see test_perturbed_renders_of_the_random_pixels_alone_...).
    n = 32
    base = dataclasses.replace(
        render_pose.Config.quick(), image_size=32, problems=n, num_samples=32, sample_growth=2, max_samples=64, pixel_chunk=0.125,
    )
    mesh = render_pose.load(base.mesh)
    cam = render_pose.camera(base)
    r_true, _, offset = render_pose.problems(base, jax.random.key(0), 20.0)
    r_true = jnp.broadcast_to(r_true[0], r_true.shape)
    r_init = jnp.broadcast_to(render.axis_angle_to_matrix(jnp.array([0.01, -0.01, 0.005])) @ r_true[0], r_true.shape)
    hard = render_pose.make_renderer(base, "hard", mesh)
    target = jax.vmap(lambda r: hard(None, render.transform_mesh(mesh, r), cam).rgb)(r_true)

    def gradients(antithetic):
        config = dataclasses.replace(base, antithetic_pose=antithetic)
        _, init, step = render_pose.make_solver(config, "perturbed-gaussian", mesh, cam)
        state = init(jnp.zeros_like(offset))
        sched = eqx.tree_at(lambda s: (s.sigma, s.num_samples), state[2], (jnp.full_like(state[2].sigma, 0.25), jnp.full_like(state[2].num_samples, 64)))
        new = step((*state[:2], sched, *state[3:]), jax.random.split(jax.random.key(5), n), target, r_init)
        return np.asarray(new[0][1][0].mu["delta"]) / (1.0 - 0.9)  # Adam's first moment after one step: 0.1 g

    independent, antithetic = gradients(False), gradients(True)
    assert np.all(antithetic.std(axis=0) < 0.7 * independent.std(axis=0))
    stderr = np.sqrt((independent.var(axis=0) + antithetic.var(axis=0)) / n)
    assert np.all(np.abs(antithetic.mean(axis=0) - independent.mean(axis=0)) < 4 * stderr)
