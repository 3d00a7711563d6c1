"""Coulomb friction in the fabric's bending: the rate-independent half of its hysteresis.

Kawabata's pure-bending test (KES-FB2) measures a woven fabric's bending moment per unit length
against curvature; loading and unloading differ by a band of constant width 2HB whatever the
rate: friction between the yarns (Lahey and Heppler, "Mechanical modeling of fabrics in bending",
J. Appl. Mech. 2004; Miguel et al., "Modeling and estimation of internal friction in cloth", SIGGRAPH
Asia 2013, who model it with Dahl's friction). Data v3 models the fabric's bending loss as viscous
(``edge_kd``), which vanishes at low rates: a small, slow jiggle meets no resistance at all. A dry
friction moment does not vanish: below it, a hinge sticks.

The model per bending hinge (a Dahl / elastic-perfectly-plastic element in parallel with the
elastic bending spring of newton's VBD, whose moment over the hinge is ``k_e L (theta - theta_0)``):

    friction moment  k_f L (theta - theta_p),   |k_f (theta - theta_p)| <= HB
    when exceeded, the element slips:  theta_p <- theta - sign(theta - theta_p) HB / k_f

so the hinge sticks within a stick angle theta_s = HB / k_f of where it last slipped, and past it
carries a constant friction moment HB per unit length. The two springs together are one quadratic,
``(k_e + k_f) L / 2 (theta - theta_eff)^2 + const``, with theta_eff = (k_e theta_0 + k_f theta_p) /
(k_e + k_f): newton's own bending energy with stiffness k_e + k_f and rest angle theta_eff, which
:class:`BendFriction` writes into the model after every substep (a warp kernel, recordable in a
graph).
"""

from __future__ import annotations

import numpy as np
import warp as wp

#: gram-force centimetre per centimetre (KES's unit of the bending moment per unit length) in N
GF_CM_PER_CM = 9.80665e-3


@wp.func
def _dihedral_angle(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3) -> float:
    """newton VBD's bending angle of the hinge (opposite vertices x0, x1; edge x2 -> x3)."""
    e = x3 - x2
    n1 = wp.cross(x2 - x0, x3 - x0)
    n2 = wp.cross(x3 - x1, x2 - x1)
    n1n, n2n, en = wp.length(n1), wp.length(n2), wp.length(e)
    if n1n < 1.0e-6 or n2n < 1.0e-6 or en < 1.0e-6:
        return 1.0e30  # degenerate: no update
    a = n1 / n1n
    b = n2 / n2n
    return wp.atan2(wp.dot(wp.cross(a, b), e / en), wp.dot(a, b))


@wp.kernel
def bend_friction_update(
    pos: wp.array[wp.vec3],
    edges: wp.array2d[wp.int32],
    rest_elastic: wp.array[float],
    stick_angle: float,
    share: float,
    slip_angle: wp.array[float],
    rest_out: wp.array[float],
):
    """Per hinge: slip the friction element's angle theta_p to within ``stick_angle`` of theta, and
    write the combined rest angle (1 - share) theta_0 + share theta_p (share = k_f / (k_e + k_f))."""
    i = wp.tid()
    if edges[i, 0] == -1 or edges[i, 1] == -1:
        return
    theta = _dihedral_angle(pos[edges[i, 0]], pos[edges[i, 1]], pos[edges[i, 2]], pos[edges[i, 3]])
    if theta > 1.0e29:
        return
    d = theta - slip_angle[i]
    if d > wp.pi:  # the same hinge angle across the +-pi cut
        d = d - 2.0 * wp.pi
    if d < -wp.pi:
        d = d + 2.0 * wp.pi
    if d > stick_angle:
        slip_angle[i] = theta - stick_angle
    elif d < -stick_angle:
        slip_angle[i] = theta + stick_angle
    rest_out[i] = (1.0 - share) * rest_elastic[i] + share * slip_angle[i]


def dihedral_angles_reference(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """NumPy reference of the hinge angles (E,) of positions x (V, 3) (NaN for boundary or
    degenerate hinges), as newton's VBD bending computes them."""
    x = np.asarray(x, np.float64)
    out = np.full(len(edges), np.nan)
    ok = (edges[:, 0] >= 0) & (edges[:, 1] >= 0)
    x0, x1, x2, x3 = (x[edges[ok, k]] for k in range(4))
    e = x3 - x2
    n1, n2 = np.cross(x2 - x0, x3 - x0), np.cross(x3 - x1, x2 - x1)
    n1n, n2n, en = (np.linalg.norm(v, axis=1) for v in (n1, n2, e))
    good = (n1n >= 1e-6) & (n2n >= 1e-6) & (en >= 1e-6)
    a, b = n1 / np.maximum(n1n, 1e-30)[:, None], n2 / np.maximum(n2n, 1e-30)[:, None]
    ang = np.arctan2((np.cross(a, b) * (e / np.maximum(en, 1e-30)[:, None])).sum(1), (a * b).sum(1))
    idx = np.flatnonzero(ok)
    out[idx[good]] = ang[good]
    return out


def bend_friction_update_reference(x: np.ndarray, edges: np.ndarray, rest_elastic: np.ndarray,
                                   slip_angle: np.ndarray, stick_angle: float, share: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """NumPy reference of :func:`bend_friction_update`: (new slip angles (E,), combined rest
    angles (E,); entries of boundary / degenerate hinges: slip unchanged, rest NaN)."""
    theta = dihedral_angles_reference(x, edges)
    d = (theta - slip_angle + np.pi) % (2 * np.pi) - np.pi
    slip = np.where(np.isnan(theta), slip_angle, np.where(d > stick_angle, theta - stick_angle,
                    np.where(d < -stick_angle, theta + stick_angle, slip_angle)))  # fmt: skip
    rest = np.where(np.isnan(theta), np.nan, (1 - share) * rest_elastic + share * slip)
    return slip, rest


class BendFriction:
    """Coulomb bending friction (module docstring) on a finalized newton model with cloth bending.

    moment: the friction moment per unit length HB [N m / m = N] (KES: half the hysteresis width
    2HB). stick_angle: theta_s [rad], the angle over which the friction builds up to HB (Dahl's
    stick region); k_f = HB / theta_s. Multiplies each hinge's stiffness by (k_e + k_f) / k_e once;
    :meth:`apply` after each solver step. Hinges with no bending stiffness are left alone.
    """

    def __init__(self, model, moment: float, stick_angle: float, device):  # noqa: ANN001 (newton's types)
        if not moment > 0.0 or not stick_angle > 0.0:
            raise ValueError(f"bend friction: moment and stick_angle must be > 0, got {moment} and {stick_angle}")
        props = model.edge_bending_properties.numpy()
        k_e = props[:, 0].astype(np.float64)
        k_f = moment / stick_angle
        if not (k_e > 0).all():
            raise ValueError("bend friction: every hinge needs a bending stiffness (edge_ke > 0)")
        shares = k_f / (k_e + k_f)
        if np.ptp(shares) > 1e-6 * shares.max():
            raise ValueError("bend friction: one bending stiffness per garment (edge_ke differs between hinges)")
        self.share = float(shares[0])
        self.stick_angle = float(stick_angle)
        props[:, 0] = (k_e + k_f).astype(np.float32)
        model.edge_bending_properties.assign(props)
        self.edges = model.edge_indices
        self.rest_angle = model.edge_rest_angle  # written in place: the solver reads it
        self.rest_elastic = wp.clone(model.edge_rest_angle)
        self.slip_angle = wp.clone(model.edge_rest_angle)  # the friction element starts unloaded
        self.device = device

    def apply(self, pos) -> None:  # noqa: ANN001 (a warp array)
        """Slip the friction elements to the positions ``pos`` (the step's result)."""
        wp.launch(bend_friction_update, dim=self.edges.shape[0],
                  inputs=[pos, self.edges, self.rest_elastic, self.stick_angle, self.share, self.slip_angle,
                          self.rest_angle], device=self.device)  # fmt: skip
