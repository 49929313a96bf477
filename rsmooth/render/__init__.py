"""Differentiable rendering with perturbed optimizers.

Le Lidec, Laptev, Schmid, Carpentier, "Differentiable rendering with perturbed optimizers",
NeurIPS 2021: the rasterizer's coverage test and the z-buffer's argmax are replaced by their
randomized smoothing, estimated by Monte-Carlo with the zeroth-order (score-function) estimator
of :mod:`rsmooth.smooth`. Hard and SoftRas-like renderers are given for comparison.

Parts: meshes (:class:`Mesh`, primitives, file loading, regularizers), cameras
(:class:`Camera`, :func:`look_at`, rotations), rasterization (signed distances, coverage,
per-pixel culling: :func:`rasterize`), aggregation (hard, soft, perturbed), shading
(:class:`DirectionalLight`), the :class:`Renderer`, pose fitting by analysis-by-synthesis
(:class:`PoseFit`, :func:`fit_poses`), and shape metrics for reconstruction
(:func:`sample_surface`, :func:`chamfer_distance`, :func:`voxelize`, :func:`iou_3d`,
:func:`silhouette_iou`).
"""

from rsmooth.render._aggregate import ProductNoise, change_probability, hard_aggregate, perturbed_aggregate, soft_aggregate
from rsmooth.render._camera import (
    Camera,
    axis_angle_to_matrix,
    look_at,
    quaternion_to_matrix,
    random_rotation,
    rotation_angle,
)
from rsmooth.render._mesh import (
    Mesh,
    box,
    cube,
    cylinder,
    edge_length_loss,
    face_normals,
    icosphere,
    is_closed_outward,
    laplacian_loss,
    load_mesh,
    normal_consistency_loss,
    position_colors,
    torus,
    transform_mesh,
)
from rsmooth.render._metrics import chamfer_distance, iou_3d, sample_surface, silhouette_iou, voxelize
from rsmooth.render._pose import PoseFit, PoseFitResult, PoseFitState, fit_poses, image_loss, pose_rotation
from rsmooth.render._raster import (
    COVERAGE_MODES,
    Fragments,
    barycentric,
    coverage,
    edge_neighbors,
    heaviside,
    project_faces,
    rasterize,
    signed_distance,
)
from rsmooth.render._renderer import MODES, NEGLIGIBLE, Image, Renderer, chunk_rows, random_pixel_chunks
from rsmooth.render._shade import DirectionalLight, shade_faces

__all__ = [
    "COVERAGE_MODES",
    "MODES",
    "NEGLIGIBLE",
    "chunk_rows",
    "random_pixel_chunks",
    "Camera",
    "DirectionalLight",
    "Fragments",
    "Image",
    "Mesh",
    "PoseFit",
    "PoseFitResult",
    "PoseFitState",
    "ProductNoise",
    "Renderer",
    "axis_angle_to_matrix",
    "barycentric",
    "box",
    "chamfer_distance",
    "coverage",
    "cube",
    "cylinder",
    "edge_length_loss",
    "edge_neighbors",
    "face_normals",
    "fit_poses",
    "hard_aggregate",
    "heaviside",
    "icosphere",
    "image_loss",
    "is_closed_outward",
    "iou_3d",
    "laplacian_loss",
    "load_mesh",
    "look_at",
    "normal_consistency_loss",
    "perturbed_aggregate",
    "change_probability",
    "pose_rotation",
    "position_colors",
    "project_faces",
    "quaternion_to_matrix",
    "random_rotation",
    "rasterize",
    "rotation_angle",
    "sample_surface",
    "shade_faces",
    "signed_distance",
    "silhouette_iou",
    "soft_aggregate",
    "torus",
    "transform_mesh",
    "voxelize",
]
