"""Renderer cost at 128 x 128: hard, soft and perturbed (M = 1, 8, 32), forward and
forward + backward, for a 1k- and a 20k-face icosphere; and one pose-optimization step.

Peak memory is XLA's own account of the compiled call (arguments, outputs and temporaries
that are live at once). Forward + backward is the gradient of a weighted sum of the RGB image with respect to the
mesh's translation (the backward pass goes through every fragment). Everything is jitted and
timed in this one process (float32, JAX's default); ratios are against the hard forward pass
on the same mesh. The pose step is one batched Adam step of the render-pose experiment
(perturbed-gaussian, default configuration: 128 x 128, cube, 8 problems), which includes the
hard render of the updated pose that `keep_best` compares with the target; one problem is also
timed without it.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp

from benchmarks._timing import fmt, machine, median_time
from rsmooth import render
from rsmooth.experiments import render_pose

SIZE = 128
# (subdivisions, tile_size, faces_per_tile): denser meshes need smaller tiles (see rasterize).
MESHES = ((3, 8, 64), (5, 4, 128))
# (mode, samples, clip_near): near-plane clipping is opt-in (Renderer(clip_near=True)); its
# row prices it on a mesh that does not cross the near plane (the worst case: all cost, no use).
VARIANTS = (("hard", 1, False), ("hard", 1, True), ("soft", 1, False), ("perturbed", 1, False), ("perturbed", 8, False),
            ("perturbed", 32, False))
MAX_REPEATS = 10


def _peak_mb(fn, *args) -> float:
    """XLA's memory for the compiled call, in MB: arguments, outputs and the temporary buffer
    (the buffer assignment's live set at its largest), independent of the allocator. (On CPU
    `peak_memory_in_bytes` leaves the temporaries out: 0.3 MB for every renderer here.)"""
    stats = fn.lower(*args).compile().memory_analysis()
    total = stats.argument_size_in_bytes + stats.output_size_in_bytes + stats.temp_size_in_bytes - stats.alias_size_in_bytes
    return total / 1e6


def _functions(mesh, camera, renderer):
    weights = jax.random.uniform(jax.random.key(2), (SIZE, SIZE, 3))

    def image(key, translation):
        return renderer(key, render.transform_mesh(mesh, jnp.eye(3), translation), camera).rgb

    forward = jax.jit(image)
    backward = jax.jit(jax.grad(lambda key, t: jnp.sum(image(key, t) * weights), argnums=1))
    return forward, backward


def _pose_step_time(repeats: int, problems: int = 8, at_cap: bool = False, **changes) -> tuple[float, render_pose.Config]:
    """Median time of one batched Adam step of render pose; `at_cap`: a step whose noise schedule
    holds max_samples samples per pixel at the noise scale where growth reaches them (the late
    steps with sample growth: each growth comes with a noise decrease)."""
    config = dataclasses.replace(render_pose.Config(), problems=problems, **changes)
    mesh = render_pose.load(config.mesh)
    cam = render_pose.camera(config)
    r_true, r_init, offset = render_pose.problems(config, jax.random.key(0), 20.0)
    target = jax.vmap(lambda r: render.Renderer(mode="hard")(None, render.transform_mesh(mesh, r), cam).rgb)(r_true)
    cap = max(config.max_samples, config.num_samples)
    growths = math.ceil(math.log(cap / config.num_samples) / math.log(config.sample_growth)) if config.sample_growth > 1 else 0

    def capped(schedule):
        return eqx.tree_at(lambda s: (s.sigma, s.num_samples), schedule,
                           (jnp.full_like(schedule.sigma, config.decay_factor ** -growths), jnp.full_like(schedule.num_samples, cap)))

    fit = render_pose.make_fit(config, "perturbed-gaussian", mesh)  # vmapped over problems, as render.fit_poses does
    state = jax.jit(jax.vmap(fit.init))(offset)
    step = jax.jit(jax.vmap(lambda s, k, t, r: fit.step(s, k, mesh, cam, t, r)))
    if at_cap:
        state = eqx.tree_at(lambda s: s.schedule, state, capped(state.schedule))
    keys = jax.random.split(jax.random.key(1), config.problems)
    return median_time(step, state, keys, target, r_init, repeats=repeats), config


def main(repeats: int = 5) -> dict:
    """Prints the tables; returns ``{"image_size", "meshes", "pose"}``, times in seconds: per mesh
    its faces, tile settings, a row per renderer (label, mode, num_samples, clip_near, forward,
    forward_backward, peak_mb_forward, peak_mb_forward_backward) and the back-face-culled runs
    (hard_forward, random_pixels, a row per pixel chunk); per pose-step variant its label, the
    seconds per Adam step and the number of problems."""
    repeats = min(repeats, MAX_REPEATS)
    print(f"machine: {machine()}")
    print(f"image {SIZE} x {SIZE}, sigma = 1 px, gamma = 0.01, faces_per_pixel = 8; median of {repeats} jitted calls "
          f"(capped at {MAX_REPEATS}: a call takes up to a second)\n")
    camera = render.look_at(jnp.array([0.0, 0.0, 3.0]), image_size=(SIZE, SIZE), fov=45.0, near=1.0, far=5.0)
    key = jax.random.key(0)
    t0 = jnp.zeros(3)
    rows = []
    meshes, pose = [], []
    for subdivisions, tile_size, faces_per_tile in MESHES:
        mesh = render.position_colors(render.icosphere(subdivisions))
        fragments = render.rasterize(mesh, camera, margin=3.0, sigma=1.0, gamma=0.01, tile_size=tile_size, faces_per_tile=faces_per_tile)
        overflow, near_culled = int(fragments.tile_overflow), int(fragments.near_culled)
        print(f"icosphere({subdivisions}): {mesh.num_faces} faces, tiles {tile_size} px, faces_per_tile {faces_per_tile} "
              f"({overflow} tiles had more candidate faces than that; the farthest, back faces here, were dropped; "
              f"{near_culled} faces crossing the near plane culled without clipping)")
        header = (f"{'renderer':>16} | {'forward':>11} | {'fwd+bwd':>11} | {'fwd / hard fwd':>14} | {'fwd+bwd / hard fwd':>18} "
                  f"| {'peak MB fwd':>11} | {'peak MB fwd+bwd':>15}")
        print(header)
        print("-" * len(header))
        hard_forward = None
        first = len(rows)
        for mode, samples, clip_near in VARIANTS:
            renderer = render.Renderer(
                mode=mode, sigma=1.0, gamma=0.01, num_samples=samples, faces_per_pixel=8,
                faces_per_tile=faces_per_tile, tile_size=tile_size, clip_near=clip_near,
            )
            forward, backward = _functions(mesh, camera, renderer)
            t_forward = median_time(forward, key, t0, repeats=repeats)
            t_backward = median_time(backward, key, t0, repeats=repeats)
            m_forward, m_backward = _peak_mb(forward, key, t0), _peak_mb(backward, key, t0)
            hard_forward = hard_forward or t_forward
            name = mode if mode != "perturbed" else f"perturbed M={samples}"
            name += ", clip near" if clip_near else ""
            print(f"{name:>16} | {fmt(t_forward):>11} | {fmt(t_backward):>11} | {t_forward / hard_forward:>14.2f} | {t_backward / hard_forward:>18.2f} "
                  f"| {m_forward:>11.1f} | {m_backward:>15.1f}")
            rows.append({"label": name, "faces": mesh.num_faces, "mode": mode, "num_samples": samples, "clip_near": clip_near,
                         "forward": t_forward, "forward_backward": t_backward,
                         "peak_mb_forward": m_forward, "peak_mb_forward_backward": m_backward})
        ratio = next(r["forward_backward"] for r in rows if r["faces"] == mesh.num_faces and r["num_samples"] == 8) / hard_forward
        print(f"perturbed (M=8) forward+backward / hard forward: {ratio:.2f}")
        # The sphere is closed: culling its back faces leaves the hard image as it is, and the
        # perturbed renderer's samples are then random only near the silhouette (the back faces'
        # depth noise made every pixel of the sphere random), which the pixel chunks draw alone.
        common = dict(sigma=1.0, gamma=0.01, faces_per_pixel=8, faces_per_tile=faces_per_tile, tile_size=tile_size, cull_backfaces=True)
        hard_culled = median_time(_functions(mesh, camera, render.Renderer(mode="hard", **common))[0], key, t0, repeats=repeats)
        uncertainty = render.Renderer(mode="perturbed", **common).uncertainty(mesh, camera)
        random = float(jnp.mean(uncertainty > render.NEGLIGIBLE))
        line = []
        renderers = rows[first:]
        for chunk in (1.0, 0.125):
            renderer = render.Renderer(mode="perturbed", num_samples=8, pixel_chunk=chunk, **common)
            forward, backward = _functions(mesh, camera, renderer)
            t_forward, t_backward = median_time(forward, key, t0, repeats=repeats), median_time(backward, key, t0, repeats=repeats)
            line.append(f"pixel_chunk {chunk:g}: forward {fmt(t_forward)}, fwd+bwd {fmt(t_backward)}, "
                        f"{t_backward / hard_culled:.2f}x the hard forward")
            rows.append({"label": f"perturbed M=8, back faces culled, pixel_chunk {chunk:g}", "faces": mesh.num_faces,
                         "mode": "perturbed", "num_samples": 8, "cull_backfaces": True,
                         "pixel_chunk": chunk, "forward": t_forward, "forward_backward": t_backward, "hard_forward": hard_culled})
        print(f"back faces culled: hard forward {fmt(hard_culled)}; {random:.1%} of the pixels random; perturbed M=8 "
              + "; ".join(line) + "\n")
        meshes.append({"faces": mesh.num_faces, "subdivisions": subdivisions, "tile_size": tile_size, "faces_per_tile": faces_per_tile,
                       "tile_overflow": overflow, "renderers": renderers,
                       "culled": {"hard_forward": hard_culled, "random_pixels": random, "rows": rows[first + len(renderers):]}})
    # the defaults (4 faces per pixel, keep_best on, 16 samples at the first steps) and one change at a time
    default = render_pose.Config()
    variants = ({}, {"faces_per_pixel": 8}, {"keep_best": False}, {"num_samples": 8})
    for changes in variants:
        t_one, config = _pose_step_time(repeats, problems=1, **changes)
        change = ", ".join(f"{name} = {value}" for name, value in changes.items()) or "the defaults"
        print(f"pose optimization, one problem (render-pose: cube, back faces culled, perturbed-gaussian "
              f"M = {config.num_samples}, {config.faces_per_pixel} faces per pixel, keep_best {config.keep_best}; "
              f"{change}): {fmt(t_one)} per Adam step (goal: under 50 ms per iteration)")
        rows.append({"pose_step": t_one, "problems": 1, "faces_per_pixel": config.faces_per_pixel,
                     "keep_best": config.keep_best, "num_samples": config.num_samples})
        pose.append({"label": f"one problem, {change}", "seconds": t_one, "problems": 1})
        if not changes:
            t_first = t_one
    # with sample growth (on by default), the steps after the noise has decreased average up to
    # max_samples / num_samples renders (render_pose.Config.sample_growth), at two antithetic
    # poses; the perturbed renders draw only the pixels their noise may change, in chunks of
    # pixel_chunk of the image (the rest: one hard render per pose); and with whole renders
    # (pixel_chunk 1), first steps and at the cap
    t_whole, _ = _pose_step_time(repeats, problems=1, pixel_chunk=1.0)
    print(f"pose optimization, one problem, the defaults with whole perturbed renders (pixel_chunk 1): {fmt(t_whole)} per Adam "
          f"step, {t_whole / t_first:.2f}x the defaults'")
    rows.append({"pose_step": t_whole, "problems": 1, "pixel_chunk": 1.0})
    pose.append({"label": "one problem, whole perturbed renders (pixel_chunk 1)", "seconds": t_whole, "problems": 1})
    for pixel_chunk in (default.pixel_chunk, 1.0):
        t_cap, config = _pose_step_time(repeats, problems=1, at_cap=True, pixel_chunk=pixel_chunk)
        print(f"pose optimization, one problem, the defaults at the sample cap (sample growth {config.sample_growth} up to "
              f"{config.max_samples} samples per pixel, {config.max_samples // config.num_samples} renders per step, "
              f"pixel_chunk {pixel_chunk:g}): {fmt(t_cap)} per Adam step, {t_cap / t_first:.2f}x the first steps' of the defaults")
        rows.append({"pose_step_at_cap": t_cap, "problems": 1, "max_samples": config.max_samples, "pixel_chunk": pixel_chunk})
        pose.append({"label": f"one problem at the sample cap ({config.max_samples} samples per pixel, pixel_chunk {pixel_chunk:g})",
                     "seconds": t_cap, "problems": 1})
    t_step, config = _pose_step_time(repeats)
    print(f"pose optimization (render-pose defaults: cube, {SIZE} x {SIZE}, perturbed-gaussian M = {default.num_samples}, "
          f"{config.problems} problems vmapped): {fmt(t_step)} per Adam step, {fmt(t_step / config.problems)} per problem")
    rows.append({"pose_step": t_step, "problems": config.problems, "num_samples": default.num_samples})
    pose.append({"label": f"the defaults, {config.problems} problems vmapped", "seconds": t_step, "problems": config.problems})
    return {"image_size": SIZE, "meshes": meshes, "pose": pose}


if __name__ == "__main__":
    main()
