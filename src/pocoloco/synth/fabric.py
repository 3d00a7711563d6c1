"""Fabrics: what takes energy out of a garment's swing, with each value's physical meaning.

Data v1 / v2 simulated cloth with almost nothing that dissipates energy: membrane
damping 1e-5, no bending damping, no air, cloth-skin friction 0.05. A skirt's hem then
swung at 30-40 cm/s seconds after the body stopped, so each frame's garment depended
on an unbounded past. A real skirt loses its swing to three things, each modelled here:

- **the air** (``synth.aero``): quadratic pressure drag along the cloth's normal and
  skin-friction drag along its plane, relative to still air; under the ``"unsteady"``
  model also the extra pressure drag of small oscillations (low Keulegan-Carpenter number);
- **the fabric's internal friction** in bending (the hysteresis of Kawabata's bending
  test): a viscous damping of the dihedral angle's rate, newton VBD's ``edge_kd``;
- **friction against the body**: the Coulomb coefficient of cloth on skin.

``FABRICS`` holds the settings per fabric; ``GARMENT_FABRIC`` says which fabric each
garment kind is made of; ``DAMPING_MODELS`` names the ways a dataset can be simulated
(``"physical"``, data v3: steady drag; ``"unsteady"``, the v4 cloth: steady and low-KC drag;
``"none"``, v1 / v2's settings, for reproduction).
"""

from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class Fabric:
    """The dissipative parameters of one fabric (SI units).

    drag_normal: pressure-drag coefficient C_n of the sheet moving along its normal
        (dimensionless). A flat plate broadside to the flow has C_d 1.1-1.3 (Hoerner,
        *Fluid-Dynamic Drag*, 1965, ch. 3); a draped, curved garment less: 1.0.
    drag_tangential: skin-friction coefficient C_t of the sheet moving in its own plane,
        both faces together (dimensionless). A smooth flat plate at the Reynolds numbers of a
        swinging hem (1e4-1e5) has C_f 0.005-0.013 per face (Blasius / Prandtl); a woven
        surface is rougher: 0.02 for the two faces.
    bend_damping: viscous damping of the bending angle, newton VBD's ``edge_kd`` (N m s per
        rad^2 per m of edge: the damping force of an edge is ``-edge_kd * L * dtheta/dt``
        along dtheta/dx). Its ratio to the bending stiffness ``edge_ke`` is a relaxation time
        tau; the loss factor at angular frequency w is w tau. Woven fabrics lose a large
        share of their bending energy per cycle (Kawabata's bending hysteresis 2HB is of the
        order of the bending rigidity B times a curvature of 1/cm: a loss factor of order 0.5 at
        the curvatures of a swinging skirt; Miguel et al., SCA 2013, measure and model it as
        internal friction). At a hem's pendulum frequency (~0.7 Hz, w ~ 4.4 rad/s) a loss
        factor of 0.5 is tau ~ 0.1 s.
    membrane_damping: viscous damping of in-plane strain rate, newton VBD's ``tri_kd`` (Pa s m:
        force ``-tri_kd * area * dC/dt`` on the Green strain's metric C). Cloth barely
        stretches; a small value removes membrane jitter without slowing the swing.
    friction: dynamic Coulomb coefficient of cloth sliding on the body. Cotton on skin
        measures 0.25-0.79 across body regions (Temel et al., *Tribology Letters* 2022); the
        low end, since a garment mostly slides over other clothing or hair: 0.3.
    drag_kc_gain: how much more pressure drag a small oscillation meets than a steady stream at
        Keulegan-Carpenter number 1 (``synth.aero``: the factor is gain * KC^(-1/3), at least 1).
        A sharp-edged plate sheds vortices from its edges every half cycle: Graham's low-KC
        theory (*J. Fluid Mech.* 97, 1980) gives the KC^(-1/3) law; flat-plate data put it at the
        order of C_d ~ 8 KC^(-1/3) against a steady ~2, a gain of 4 (the constant as recalled, not
        re-checked: 1.26x it changes the settle benchmark by less than its noise). Used by the
        ``"unsteady"`` damping model only.
    drag_kc_width: the plate width D of the Keulegan-Carpenter number KC = 2 pi A / D [m]: the
        width of the panel that flaps as one; a skirt's hem flaps in lobes ~0.3 m wide
        (four to six around a 1.5-2 m hem; ``benchmarks/experiments/cloth_rest_diagnostics.py``).
    drag_kc_time: the time over which a vertex's excursion and its amplitude are averaged [s]:
        about a period of the motion it measures (the hanging skirt's flapping is 0.75-1.25 Hz).
    """

    name: str
    drag_normal: float
    drag_tangential: float
    bend_damping: float
    membrane_damping: float
    friction: float
    drag_kc_gain: float = 0.0
    drag_kc_width: float = 0.3
    drag_kc_time: float = 1.0


#: the excursion's averaging time of the fabrics here [s]
KC_TIME = 1.0

#: v1 / v2's settings: no air, almost no damping, slippery contact (for reproducing old data)
UNDAMPED = Fabric("undamped", drag_normal=0.0, drag_tangential=0.0, bend_damping=0.0, membrane_damping=1.0e-5,
                  friction=0.05)  # fmt: skip

#: a light woven cotton (lawn, poplin, voile: 100-150 g/m^2, the data's 0.15 kg/m^2)
COTTON = Fabric("cotton", drag_normal=1.0, drag_tangential=0.02, bend_damping=1.0e-4, membrane_damping=1.0e-2,
                friction=0.3, drag_kc_gain=4.0, drag_kc_width=0.3, drag_kc_time=KC_TIME)  # fmt: skip

FABRICS: dict[str, Fabric] = {f.name: f for f in (UNDAMPED, COTTON)}

#: the fabric of each garment kind under the physical damping model
GARMENT_FABRIC: dict[str, str] = {
    "skirt": "cotton",
    "maxi_skirt": "cotton",
    "dress": "cotton",
    "long_shirt": "cotton",
    "sleeved_shirt": "cotton",
    "wide_trousers": "cotton",
}

#: "physical": each garment's fabric, steady drag (data v3); "unsteady": the same and the drag of
#: small oscillations (the v4 cloth); "none": v1 / v2's undamped cloth
DAMPING_MODELS: tuple[str, ...] = ("physical", "none", "unsteady")


def fabric_for(kind: str, damping: str) -> Fabric:
    """The fabric a garment of ``kind`` is simulated with under damping model ``damping``."""
    if damping not in DAMPING_MODELS:
        raise ValueError(f"unknown cloth damping model {damping!r}; expected one of {DAMPING_MODELS}")
    if damping == "none":
        return UNDAMPED
    fabric = FABRICS[GARMENT_FABRIC.get(kind, "cotton")]
    return fabric if damping == "unsteady" else replace(fabric, drag_kc_gain=0.0)
