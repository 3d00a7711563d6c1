"""A membrane that carries no compression: tension field theory for the cloth's in-plane elasticity.

Woven cloth resists stretch but buckles under almost any in-plane compression: its yarns bend out of
plane long before they shorten. A flared garment's hoop is compressed by gravity (the cloth hangs
inward from a hem wider than its waist); newton's VBD membrane (a stable Neo-Hookean triangle)
resists that compression as much as stretch, the compressed hoop buckles into folds that 5 sweeps
never settle, and the hem keeps flapping (``benchmarks/experiments/vbd_energy.py --tube``, the cone;
docs/lab/synthetic-data.md). Tension field theory (Wagner 1929, Reissner 1938; for membranes and
cloth, e.g. the wrinkling models of Roddeman et al. 1987) drops the compressive stress: the membrane's
energy sees only the tensile part of the strain.

Here, before each solver step, each triangle's rest shape is relaxed along its compressed principal
directions: with F = Ds Dm^-1 (the deformation from the garment's original rest shape) and
C = F^T F = V diag(l_1, l_2) V^T, the rest-shape inverse becomes Dm^-1 S with
S = V diag(s_1, s_2) V^T, s_i = 1 / sqrt(l_i) where l_i < 1 and 1 otherwise, so that the membrane
sees (F S)^T (F S) = V diag(max(l_i, 1)) V^T: no strain (and no stress) along a compressed
direction, the original stiffness along a stretched one. The rest area (mass, energy scale) is
unchanged; bending is untouched and now alone decides how the cloth buckles.
"""

from __future__ import annotations

import numpy as np
import warp as wp


@wp.kernel
def relax_compressed_rest_shapes(
    pos: wp.array[wp.vec3],
    tris: wp.array2d[wp.int32],
    poses_original: wp.array[wp.mat22],
    min_metric: float,
    keep: float,
    poses_out: wp.array[wp.mat22],
):
    """Per triangle: Dm^-1 S (module docstring) from the positions ``pos``; a direction compressed
    below sqrt(min_metric) of its length keeps resisting beyond that; ``keep`` scales the strain a
    compressed direction still shows (its stiffness scales as keep^2; 0: none)."""
    i = wp.tid()
    dm_inv = poses_original[i]
    x0 = pos[tris[i, 0]]
    e1 = pos[tris[i, 1]] - x0
    e2 = pos[tris[i, 2]] - x0
    f0 = e1 * dm_inv[0, 0] + e2 * dm_inv[1, 0]  # the columns of F = Ds Dm^-1 (3 x 2)
    f1 = e1 * dm_inv[0, 1] + e2 * dm_inv[1, 1]
    a = wp.dot(f0, f0)
    b = wp.dot(f0, f1)
    c = wp.dot(f1, f1)
    half = 0.5 * (a - c)
    r = wp.sqrt(half * half + b * b)
    l1 = 0.5 * (a + c) + r
    l2 = 0.5 * (a + c) - r
    # unit eigenvector of l1 (l2's is perpendicular)
    v = wp.vec2(1.0, 0.0)
    if r > 1.0e-12:
        if half >= 0.0:
            v = wp.normalize(wp.vec2(l1 - c, b))
        else:
            v = wp.normalize(wp.vec2(b, l1 - a))
    w = wp.vec2(-v[1], v[0])
    s1 = 1.0
    s2 = 1.0
    if l1 < 1.0:
        c1 = wp.sqrt(wp.max(l1, min_metric))
        s1 = (1.0 - keep * (1.0 - c1)) / c1
    if l2 < 1.0:
        c2 = wp.sqrt(wp.max(l2, min_metric))
        s2 = (1.0 - keep * (1.0 - c2)) / c2
    s = wp.mat22(
        s1 * v[0] * v[0] + s2 * w[0] * w[0], s1 * v[0] * v[1] + s2 * w[0] * w[1],
        s1 * v[1] * v[0] + s2 * w[1] * w[0], s1 * v[1] * v[1] + s2 * w[1] * w[1],
    )  # fmt: skip
    poses_out[i] = dm_inv * s


def relaxed_rest_shapes_reference(x: np.ndarray, tris: np.ndarray, poses: np.ndarray,
                                  min_stretch: float = 0.0, compression: float = 0.0) -> np.ndarray:  # fmt: skip
    """NumPy reference of :func:`relax_compressed_rest_shapes`: (T, 2, 2) Dm^-1 S."""
    x = np.asarray(x, np.float64)
    poses = np.asarray(poses, np.float64)
    ds = np.stack([x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]]], axis=2)  # (T, 3, 2)
    f = ds @ poses
    lam, vec = np.linalg.eigh(np.swapaxes(f, 1, 2) @ f)  # (T, 2), (T, 2, 2) columns
    c = np.sqrt(np.maximum(lam, max(min_stretch**2, 1e-30)))
    keep = np.sqrt(compression)
    s = np.where(lam < 1.0, (1.0 - keep * (1.0 - c)) / c, 1.0)
    return poses @ (vec * s[:, None, :]) @ np.swapaxes(vec, 1, 2)


class TensionField:
    """Keeps a finalized newton cloth model's membrane free of compression (module docstring):
    :meth:`apply` before each solver step, with the step's starting positions. ``min_stretch``:
    a direction compressed below this length ratio resists the rest (a triangle must not collapse
    to a line: bending alone cannot hold it). ``compression``: the share of the membrane's stiffness
    a compressed direction keeps (0: none, tension field theory; between 0 and 1 a softened,
    post-buckling response, as in Choi & Ko's buckling model, SIGGRAPH 2002)."""

    def __init__(self, model, device, min_stretch: float = 0.7, compression: float = 0.0):  # noqa: ANN001
        if not 0.0 < min_stretch <= 1.0:
            raise ValueError(f"tension field: min_stretch must be in (0, 1], got {min_stretch}")
        if not 0.0 <= compression <= 1.0:
            raise ValueError(f"tension field: compression must be in [0, 1], got {compression}")
        self.min_metric = float(min_stretch) ** 2
        self.keep = float(np.sqrt(compression))
        self.tris = model.tri_indices
        self.poses = model.tri_poses  # rewritten in place: the solver reads it
        self.original = wp.clone(model.tri_poses)
        self.device = device

    def apply(self, pos) -> None:  # noqa: ANN001 (a warp array)
        wp.launch(relax_compressed_rest_shapes, dim=self.tris.shape[0],
                  inputs=[pos, self.tris, self.original, self.min_metric, self.keep, self.poses], device=self.device)  # fmt: skip
