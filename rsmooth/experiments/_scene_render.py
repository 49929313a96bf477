"""Animations of simulated scenes, drawn by rsmooth's own renderer.

Every drawn geom of a :class:`rsmooth.sim.MujocoModel` (:func:`drawn_geoms`) that has a surface is triangulated once in its own frame (primitives by trimesh's
constructions, meshes as loaded, or their convex hulls beyond :data:`MAX_MESH_FACES` faces),
placed by its joint's pose at each frame, and the
whole scene is one :class:`rsmooth.render.Mesh` rendered by a hard :class:`rsmooth.render.Renderer`
with a directional light: the face count is the same at every frame, so the renderer compiles
once per scene. Planes are drawn as a grey square under the scene (they are infinite).
"""

from __future__ import annotations

import jax
import numpy as np

from rsmooth import render, viz


# A mesh of more faces is drawn by its convex hull (MuJoCo's, of at most the loader's
# max_hull_vertices): a robot's visual meshes hold tens of thousands of faces, which a CPU
# renders in seconds per frame.
MAX_MESH_FACES = 2000


def geom_triangles(loaded, geom: int, max_faces: int = MAX_MESH_FACES):
    """The triangles of a geom in its own frame, ``(vertices, faces)`` (a mesh of more than
    ``max_faces`` faces: its convex hull's); ``None`` for a plane (drawn as the floor) and for
    height fields and SDFs."""
    import trimesh

    kind, size = loaded.geom_types[geom], np.asarray(loaded.geom_size[geom], dtype=np.float64)
    if kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    elif kind == "ellipsoid":
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        mesh.vertices *= size
    elif kind == "capsule":
        mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[12, 8])
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=16)
    elif kind == "box":
        mesh = trimesh.creation.box(extents=2 * size)
    elif kind == "mesh":
        vertices, faces = np.asarray(loaded.geom_vertices[geom]), np.asarray(loaded.geom_faces[geom])
        if faces.shape[0] <= max_faces:
            return vertices, faces
        mesh = trimesh.Trimesh(np.asarray(loaded.geom_hull[geom]), process=False).convex_hull  # MuJoCo's hull
    else:
        return None
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def drawn_geoms(loaded) -> list[int]:
    """The geoms an animation draws: the visual ones (neither ``contype`` nor ``conaffinity``),
    and the colliding ones of the bodies that have no visual geom (a robot's links are drawn
    by their visual meshes, not twice; a box without one by its collision shape)."""
    visual = {g for g in range(loaded.ngeom) if not loaded.geom_contype[g] and not loaded.geom_conaffinity[g]}
    dressed = {loaded.geom_bodies[g] for g in visual}
    return [g for g in range(loaded.ngeom) if g in visual or loaded.geom_bodies[g] not in dressed]


def bounds(loaded, placements, floor_height: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A box that holds every drawn geom's reach over the run (``placements``: the joints'
    ``(rotations (T, J, 3, 3), translations (T, J, 3))``), and the floor under it."""
    rotations, translations = placements
    points = [np.zeros((1, 3))]
    for geom in drawn_geoms(loaded):
        shape = geom_triangles(loaded, geom)
        if shape is None:
            continue
        reach = float(np.max(np.linalg.norm(shape[0], axis=-1)))
        joint = loaded.geom_joints[geom]
        centres = np.einsum("tab,b->ta", rotations[:, joint], np.asarray(loaded.geom_translation[geom]))
        centres = centres + translations[:, joint]
        points += [centres - reach, centres + reach]
    points = np.concatenate(points)
    low, high = points.min(axis=0), points.max(axis=0)
    low[2] = min(low[2], floor_height)
    margin = 0.05 * max(float(np.max(high - low)), 0.1)
    return low - margin, high + margin


class SceneFrames:
    """Renders a model's geoms at given joint placements (see the module docstring).

    Args:
        loaded: the :class:`rsmooth.sim.MujocoModel`.
        box: ``(low, high)`` corners of the region to show (:func:`bounds`).
        floor_height: the floor's ``z`` (drawn over the box's ``x``-``y`` extent).
        image_size: ``(height, width)`` in pixels.
        colors: one RGB per geom (default: matplotlib's ``tab10`` cycle).
    """

    def __init__(self, loaded, box, floor_height: float = 0.0, image_size=(240, 320), colors=None):
        self.loaded = loaded
        low, high = (np.asarray(corner, dtype=np.float64) for corner in box)
        palette = np.asarray(viz.plt.get_cmap("tab10")(np.arange(loaded.ngeom) % 10))[:, :3] if colors is None else (
            np.asarray(colors, dtype=np.float64))
        self.parts = [(geom, *shape) for geom in drawn_geoms(loaded) if (shape := geom_triangles(loaded, geom)) is not None]
        floor = np.array([[low[0], low[1], floor_height], [high[0], low[1], floor_height],
                          [high[0], high[1], floor_height], [low[0], high[1], floor_height]])
        self.floor = floor
        sizes = [vertices.shape[0] for _, vertices, _ in self.parts]
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        self.faces = np.concatenate([faces + offset for (_, _, faces), offset in zip(self.parts, offsets)]
                                    + [np.array([[0, 1, 2], [0, 2, 3]]) + offsets[-1]])
        self.colors = np.concatenate([np.broadcast_to(palette[geom], (vertices.shape[0], 3)) for geom, vertices, _ in self.parts]
                                     + [np.full((4, 3), 0.8)])
        centre, extent = 0.5 * (low + high), float(np.max(high - low))
        self.camera = render.look_at(centre + extent * np.array([0.8, -1.15, 0.75]), centre, (0.0, 0.0, 1.0), fov=40.0,
                                     near=0.05 * extent, far=10.0 * extent, image_size=tuple(image_size))
        renderer = render.Renderer(mode="hard", background=(1.0, 1.0, 1.0))
        # Drawn in float32 whatever the simulation ran in: under jax_enable_x64 (every
        # simulation experiment) a float64 frame costs tens of times more on a CPU, for images
        # that differ by at most one level of 255.
        camera = jax.tree.map(lambda a: np.asarray(a, np.float32) if np.issubdtype(np.asarray(a).dtype, np.floating) else a,
                              self.camera)
        self._render = jax.jit(lambda vertices, faces, colors: renderer(None, render.Mesh(vertices, faces, colors), camera).rgb)

    def __call__(self, rotations, translations) -> np.ndarray:
        """An RGB image (uint8) of the scene with its joints at ``(rotations (J, 3, 3),
        translations (J, 3))``."""
        placed = []
        for geom, vertices, _ in self.parts:
            joint = self.loaded.geom_joints[geom]
            rotation = rotations[joint] @ np.asarray(self.loaded.geom_rotation[geom])
            translation = rotations[joint] @ np.asarray(self.loaded.geom_translation[geom]) + translations[joint]
            placed.append(vertices @ rotation.T + translation)
        vertices = np.concatenate(placed + [self.floor]).astype(np.float32)
        image = np.asarray(self._render(vertices, self.faces, self.colors.astype(np.float32)))
        return (255 * np.clip(image, 0.0, 1.0)).astype(np.uint8)


def side_by_side(loaded, placements, path, frames: int, duration_s: float, hold: int = 3, image_size=(200, 260)):
    """An animation of several runs of one scene side by side (GIF or MP4 at ``path``).

    Args:
        loaded: the :class:`rsmooth.sim.MujocoModel` whose geoms are drawn.
        placements: per run, the joints' ``(rotations (T, J, 3, 3), translations (T, J, 3))``
            (equal ``T``); one camera frames all of them.
        frames: how many frames, at evenly spaced steps from the first to the last.
        duration_s: how long the animation plays (before the held last frame).
        hold: extra copies of the last frame.
    """
    everything = tuple(np.concatenate([placement[i] for placement in placements]) for i in range(2))
    draw = SceneFrames(loaded, bounds(loaded, everything), image_size=image_size)
    shown = np.linspace(0, placements[0][0].shape[0] - 1, frames).round().astype(int)
    images = [np.concatenate([draw(rotations[k], translations[k]) for rotations, translations in placements], axis=1)
              for k in shown]
    viz.save_animation(images + images[-1:] * hold, path, fps=max(1, round((frames - 1) / duration_s)))
