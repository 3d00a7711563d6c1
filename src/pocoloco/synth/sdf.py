"""Signed distance to a closed triangle mesh (open3d ray casting), for garment building and the
penetration checks of the cloth simulation."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def signed_distance_fn(vertices: np.ndarray, faces: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A function points (N, 3) -> signed distance (N,) to the closed triangle
    mesh (V, 3)/(F, 3), negative inside (open3d RaycastingScene: closest point
    plus a ray-parity inside test). Build once, query many times."""
    import open3d as o3d  # lazy: heavy import

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
    )

    def query(points: np.ndarray) -> np.ndarray:
        q = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        return scene.compute_signed_distance(q).numpy()

    return query


def signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed distance (N,) of points (N, 3) to a closed triangle mesh, negative inside."""
    return signed_distance_fn(vertices, faces)(points)
