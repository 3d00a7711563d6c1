"""Stateless point-cloud ops (pure torch, no nn.Modules), each with a slow ``*_reference``.

knn.py:      ``knn`` (chunked, differentiable distances), ``knn_numpy`` (scipy cKDTree),
             ``ball_query`` (PointNet++ convention).
chamfer.py:  ``chamfer_distance`` (both directions, squared and unsquared reductions).
sampling.py: ``farthest_point_sampling``, ``sample_surface`` (uniform by area).
"""

from .chamfer import Chamfer, chamfer_distance, chamfer_distance_reference, safe_sqrt
from .knn import KNN, ball_query, ball_query_reference, knn, knn_numpy, knn_reference
from .sampling import (
    SurfaceSample,
    farthest_point_sampling,
    farthest_point_sampling_reference,
    sample_surface,
)

__all__ = [
    "KNN",
    "Chamfer",
    "SurfaceSample",
    "ball_query",
    "ball_query_reference",
    "chamfer_distance",
    "chamfer_distance_reference",
    "farthest_point_sampling",
    "farthest_point_sampling_reference",
    "knn",
    "knn_numpy",
    "knn_reference",
    "safe_sqrt",
    "sample_surface",
]
