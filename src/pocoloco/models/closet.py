"""CloSET (Zhang et al. 2023, "CloSET: Modeling Clothed Humans on Continuous Surface
with Explicit Template Decomposition"), re-implemented from the paper (no code exists).

Per subject (one body template, V vertices, faces F):

* Pose encoder F_p (Sec. 3.1, Eq. 1): PointNet++ with 6 SA + 6 FP levels whose input
  points are the T-pose (bind) template vertices V^t and whose input features are the
  posed, pelvis-centred vertices V^u -> per-vertex pose features phi_p (B, V, C_p).
  FPS / ball query / 3-NN of the template are computed once (``TemplateHierarchy``).
* Garment encoder F_g: a smaller PointNet++ over a learnable per-vertex garment code
  phi_gc (one (V, C_gc) tensor per outfit, auto-decoded) -> phi_g (B, V, C_g).
* Surface point p = (face, barycentric b) on the template: phi(p) = sum_j b_j phi(v_j)
  (Eq. 2), p^t = template position, p^u = posed position.
* Explicit template decomposition (Eq. 3): r_g = D_g(phi_g(p), p^t),
  r_p = D_p(phi_g(p) (+) phi_p(p), p^t), r = r_g + r_p; ``decomposition=False`` is the
  ablation with one decoder r = D(phi_g (+) phi_p, p^t).
* Local transformation (Sec. 3.2, as POP): x = T(p) r + p^u with T the barycentric
  blend of the per-vertex skinning transforms ``vtransf``; the normal is predicted in
  the same local frame (by D_p, or D) and mapped to normalize(T n).
* Loss (Sec. 3.3, Eqs. 4-6): l_p Chamfer (squared, both ways) + l_n normal L1 to the
  nearest GT point's normal, on the final points only; + l_rgl (mean |r|^2 +
  l_pd mean |r_p|^2 + l_gc mean |phi_gc|^2).

Widths, radii and loss weights are not in the paper (they are in its unavailable
Supp. Mat.): the ``paper`` preset follows the paper's statements (L = 6, encoders of
POP's size, 50K query points at evaluation) with our choices documented in
``CLOSET_PRESETS``. The loss (its weights default to POP's), batches and
training step are the method's: :mod:`pocoloco.methods.closet`.

Shapes: B frames, V vertices, F faces, P query points, N ground-truth points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pocoloco.body.surface import (
    SurfacePoints,
    barycentric_interpolate,
    blend_transforms,
    largest_component_faces,
    sample_surface_points,
)
from pocoloco.models.pointnet2 import PointNet2Config, PointNet2Encoder
from pocoloco.utils.config import Config

__all__ = ["CLOSET_PRESETS", "CloSET", "CloSETConfig", "CloSETLossWeights", "CloSETOutput", "closet_preset"]


# ---------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class CloSETConfig(Config):
    """Architecture of :class:`CloSET`.

    pose / garment: the two PointNet++ encoders (radii in metres on the template).
    code_dim: channels of the per-vertex garment code phi_gc (init N(0, code_init_std)).
    decoder_width / decoder_depth / decoder_skip: POP-style MLP decoders (Linear ->
    BatchNorm -> Softplus(beta=20); the input is concatenated again before layer
    ``decoder_skip``). disp_scale: the decoder's displacement output is multiplied by
    this (metres; POP's code uses 0.02) so an untrained model starts near the body.
    decomposition: True = D_g + D_p (Eq. 3); False = one decoder (ablation).
    body_only: query points only on the template's largest connected component
    (drops anny's eyeballs and mouth interior).
    """

    pose: PointNet2Config
    garment: PointNet2Config
    code_dim: int = 64
    code_init_std: float = 0.01
    decoder_width: int = 256
    decoder_depth: int = 8
    decoder_skip: int = 4
    decoder_batchnorm: bool = True
    disp_scale: float = 0.02
    decomposition: bool = True
    body_only: bool = True



def _pn2(npoints, radii, nsamples, sa, fp) -> PointNet2Config:
    return PointNet2Config(tuple(npoints), tuple(radii), tuple(nsamples), tuple(map(tuple, sa)), tuple(map(tuple, fp)))


#: Named configurations. ``paper``: L = 6 SA + 6 FP levels (paper Sec. 4), PointNet++
#: SSG-like widths grown by one level, sized so the whole model (~11M parameters with
#: anny's 13,718-vertex template) is comparable to POP's 11.3M as the paper states;
#: radii double per level from 2.5 cm. ``small``: CPU-trainable. ``tiny``: tests.
CLOSET_PRESETS: dict[str, CloSETConfig] = {
    "paper": CloSETConfig(
        pose=_pn2(
            (4096, 1024, 512, 256, 64, 16), (0.025, 0.05, 0.1, 0.2, 0.4, 0.8), (32, 32, 32, 32, 32, 16),
            [(32, 32, 64), (64, 64, 128), (128, 128, 256), (256, 256, 512), (512, 512, 768), (768, 768, 1024)],
            [(128, 128, 64), (256, 128), (256, 256), (512, 256), (768, 512), (768, 768)],
        ),
        garment=_pn2(
            (4096, 1024, 512, 256, 64, 16), (0.025, 0.05, 0.1, 0.2, 0.4, 0.8), (32, 32, 32, 32, 32, 16),
            [(64, 64), (128, 128), (128, 128), (256, 256), (256, 256), (256, 256)],
            [(128, 64), (128, 128), (128, 128), (256, 128), (256, 256), (256, 256)],
        ),
        code_dim=64, decoder_width=256, decoder_depth=8, decoder_skip=4,
    ),  # fmt: skip
    "small": CloSETConfig(
        pose=_pn2(
            (2048, 512, 256, 128, 32, 8), (0.03, 0.06, 0.12, 0.24, 0.48, 0.96), (16, 16, 16, 16, 16, 8),
            [(32, 32), (64, 64), (64, 128), (128, 128), (128, 256), (256, 256)],
            [(64, 32), (64, 64), (128, 64), (128, 128), (256, 128), (256, 256)],
        ),
        garment=_pn2(
            (2048, 512, 256), (0.03, 0.06, 0.12), (16, 16, 16),
            [(32, 32), (64, 64), (128, 128)],
            [(32, 32), (64, 64), (128, 64)],
        ),
        code_dim=32, decoder_width=128, decoder_depth=4, decoder_skip=2,
    ),  # fmt: skip
    "tiny": CloSETConfig(
        pose=_pn2(
            (96, 48, 24, 12, 6, 3), (0.15, 0.25, 0.4, 0.6, 1.0, 2.0), (8, 8, 8, 8, 6, 6),
            [(16,), (16,), (32,), (32,), (32,), (32,)],
            [(16,), (16,), (16,), (32,), (32,), (32,)],
        ),
        garment=_pn2(
            (96, 48), (0.15, 0.25), (8, 8),
            [(8,), (16,)],
            [(8,), (16,)],
        ),
        code_dim=8, decoder_width=32, decoder_depth=3, decoder_skip=1,
    ),  # fmt: skip
}


def closet_preset(name: str, **overrides) -> CloSETConfig:
    """A named preset with field overrides (e.g. ``decomposition=False``); a one-line
    error naming the known presets otherwise."""
    if name not in CLOSET_PRESETS:
        raise ValueError(f"unknown CloSET preset {name!r}; choose one of: {', '.join(CLOSET_PRESETS)}")
    return CLOSET_PRESETS[name].replace(**overrides)


@dataclass(frozen=True)
class CloSETLossWeights:
    """Eq. 4-6 weights. CloSET's values are in its Supp. Mat. (not available); the
    defaults are POP's: Chamfer 1e4 (m^-2), normal 1, displacement L2 2e3; l_gc such
    that l_rgl * l_gc = 1 (POP's feature L2 weight); l_pd = 1 (our choice)."""

    chamfer: float = 1e4
    normal: float = 1.0
    rgl: float = 2e3
    pd: float = 1.0
    gc: float = 5e-4


# ---------------------------------------------------------------------------
# network
# ---------------------------------------------------------------------------


class Decoder(nn.Module):
    """POP-style point decoder: in (..., C_in) -> displacement (..., 3) [, normal (..., 3)].

    ``depth`` x [Linear -> (BatchNorm) -> Softplus(beta=20)], the input concatenated again
    before layer ``skip`` (0 < skip < depth), then linear heads."""

    def __init__(self, in_channels: int, width: int, depth: int, skip: int, batchnorm: bool, normal_head: bool):
        super().__init__()
        if depth < 1 or width < 1:
            raise ValueError(f"decoder depth and width must be >= 1, got {depth}, {width}")
        self.skip = skip if 0 < skip < depth else -1
        self.layers = nn.ModuleList()
        self.norms = nn.ModuleList()
        for i in range(depth):
            c_in = in_channels if i == 0 else width + (in_channels if i == self.skip else 0)
            self.layers.append(nn.Linear(c_in, width))
            self.norms.append(nn.BatchNorm1d(width) if batchnorm else nn.Identity())
        self.act = nn.Softplus(beta=20)
        self.disp = nn.Linear(width, 3)
        self.normal = nn.Linear(width, 3) if normal_head else None

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        shape = x.shape[:-1]
        x0 = x.reshape(-1, x.shape[-1])
        h = x0
        for i, (lin, norm) in enumerate(zip(self.layers, self.norms)):
            if i == self.skip:
                h = torch.cat([h, x0], dim=-1)
            h = self.act(norm(lin(h)))
        disp = self.disp(h).reshape(*shape, 3)
        normal = self.normal(h).reshape(*shape, 3) if self.normal is not None else None
        return disp, normal

    def zero_displacement_(self) -> None:
        """Zero the displacement head (the decoder then predicts r = 0 everywhere)."""
        with torch.no_grad():
            self.disp.weight.zero_()
            self.disp.bias.zero_()


@dataclass
class CloSETOutput:
    """points (B, P, 3) x = T r + p^u; normals (B, P, 3) unit world normals;
    r (B, P, 3) local displacement in metres (= r_g + r_p when decomposed);
    r_g, r_p (B, P, 3) or None (no decomposition); body_points (B, P, 3) p^u;
    codes (B, V, C_gc) the garment codes used (for the l_gc regulariser)."""

    points: torch.Tensor
    normals: torch.Tensor
    r: torch.Tensor
    r_g: torch.Tensor | None
    r_p: torch.Tensor | None
    body_points: torch.Tensor
    codes: torch.Tensor


class CloSET(nn.Module):
    """CloSET for one body template (see module docstring).

    template: (V, 3) bind-pose vertices (``subject.npz`` ``template``); faces (F, 3);
    num_outfits: number of garment codes. The template, faces and query-face mask are
    persistent buffers (saved with the weights); the FPS / ball-query hierarchies are
    rebuilt from the template at construction.
    """

    def __init__(self, template, faces, num_outfits: int = 1, config: CloSETConfig | None = None):
        super().__init__()
        cfg = config or closet_preset("paper")
        self.config = cfg
        template = torch.as_tensor(np.asarray(template, dtype=np.float32) if not torch.is_tensor(template) else template)
        faces_np = np.asarray(faces.cpu() if torch.is_tensor(faces) else faces)
        if template.ndim != 2 or template.shape[1] != 3:
            raise ValueError(f"template must have shape (V, 3), got {tuple(template.shape)}")
        if faces_np.ndim != 2 or faces_np.shape[1] != 3 or not np.issubdtype(faces_np.dtype, np.integer):
            raise ValueError(f"faces must be an integer (F, 3) array, got {faces_np.shape} {faces_np.dtype}")
        V = template.shape[0]
        if faces_np.size == 0 or faces_np.min() < 0 or faces_np.max() >= V:
            raise ValueError(f"faces must be non-empty and index vertices in [0, {V})")
        if isinstance(num_outfits, bool) or not isinstance(num_outfits, (int, np.integer)) or num_outfits < 1:
            raise ValueError(f"num_outfits must be a positive integer, got {num_outfits!r}")
        self.num_vertices = V
        self.num_outfits = int(num_outfits)
        self.register_buffer("template", template.float().clone())
        self.register_buffer("faces", torch.from_numpy(faces_np.astype(np.int64)))
        mask = largest_component_faces(faces_np) if cfg.body_only else np.ones(len(faces_np), bool)
        self.register_buffer("face_mask", torch.from_numpy(mask))

        self.pose_encoder = PointNet2Encoder(cfg.pose, in_channels=3)
        self.garment_codes = nn.Parameter(torch.randn(self.num_outfits, V, cfg.code_dim) * cfg.code_init_std)
        self.garment_encoder = PointNet2Encoder(cfg.garment, in_channels=cfg.code_dim)
        self.pose_hierarchy = self.pose_encoder.build_hierarchy(self.template)
        self.garment_hierarchy = self.garment_encoder.build_hierarchy(self.template, reuse=self.pose_hierarchy)
        cp, cg = self.pose_encoder.out_channels, self.garment_encoder.out_channels
        d = dict(width=cfg.decoder_width, depth=cfg.decoder_depth, skip=cfg.decoder_skip, batchnorm=cfg.decoder_batchnorm)
        if cfg.decomposition:
            self.garment_decoder = Decoder(cg + 3, normal_head=False, **d)  # D_g(phi_g, p^t)
            self.pose_decoder = Decoder(cg + cp + 3, normal_head=True, **d)  # D_p(phi_g (+) phi_p, p^t)
        else:
            self.decoder = Decoder(cg + cp + 3, normal_head=True, **d)  # D(phi_g (+) phi_p, p^t)

    # -- construction helpers ------------------------------------------------

    @classmethod
    def from_state(cls, config: dict | CloSETConfig, state: dict) -> CloSET:
        """Rebuild from ``config.to_dict()`` and a ``state_dict()`` (template, faces and
        the number of outfits are read from the state)."""
        cfg = config if isinstance(config, CloSETConfig) else CloSETConfig.from_dict(config)
        for k in ("template", "faces", "garment_codes"):
            if k not in state:
                raise ValueError(f"CloSET state is missing {k!r}")
        model = cls(state["template"], state["faces"], int(state["garment_codes"].shape[0]), cfg)
        model.load_state_dict(state)
        return model

    def num_parameters(self) -> int:
        """Trainable parameters (including the garment codes)."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)

    def parameter_breakdown(self) -> dict[str, int]:
        n = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
        out = {"pose_encoder": n(self.pose_encoder), "garment_encoder": n(self.garment_encoder),
               "garment_codes": self.garment_codes.numel()}  # fmt: skip
        if self.config.decomposition:
            out |= {"garment_decoder": n(self.garment_decoder), "pose_decoder": n(self.pose_decoder)}
        else:
            out["decoder"] = n(self.decoder)
        out["total"] = self.num_parameters()
        return out

    def sample_query_points(self, num: int, seed: int = 0) -> SurfacePoints:
        """``num`` area-uniform surface points on the template (body faces only when
        ``config.body_only``); reusable for every frame of the subject."""
        if isinstance(num, bool) or not isinstance(num, (int, np.integer)) or num < 1:
            raise ValueError(f"number of query points must be a positive integer, got {num!r}")
        return sample_surface_points(
            self.template.cpu().numpy(), self.faces.cpu().numpy(), int(num), seed,
            face_mask=self.face_mask.cpu().numpy(),
        )  # fmt: skip

    def zero_displacement_heads_(self) -> None:
        """Zero every displacement head: the model then puts each point exactly on the
        posed body surface (x = p^u)."""
        for d in (self.garment_decoder, self.pose_decoder) if self.config.decomposition else (self.decoder,):
            d.zero_displacement_()

    # -- encoders --------------------------------------------------------------

    def encode_pose(self, vertices: torch.Tensor, cached: bool = True) -> torch.Tensor:
        """Eq. (1): posed pelvis-centred vertices (B, V, 3) -> phi_p (B, V, C_p)."""
        B = vertices.shape[0]
        xyz = self.template[None].expand(B, -1, -1)
        return self.pose_encoder(xyz, vertices, self.pose_hierarchy if cached else None)

    def encode_garment(self, outfit: torch.Tensor, cached: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """outfit (B,) -> phi_g (B, V, C_g) and the codes phi_gc (B, V, C_gc); each
        distinct outfit in the batch is encoded once."""
        uniq, inv = torch.unique(outfit, return_inverse=True)
        codes = self.garment_codes[uniq]  # (U, V, C_gc)
        xyz = self.template[None].expand(len(uniq), -1, -1)
        feats = self.garment_encoder(xyz, codes, self.garment_hierarchy if cached else None)
        return feats[inv], codes[inv]

    # -- forward ---------------------------------------------------------------

    def _check_inputs(self, vertices, vtransf, outfit, face_idx, barycentric):
        V = self.num_vertices
        if not torch.is_tensor(vertices) or vertices.ndim != 3 or vertices.shape[-1] != 3:
            shape = tuple(vertices.shape) if hasattr(vertices, "shape") else type(vertices).__name__
            hint = " (a POP UV position map? CloSET takes posed body vertices)" if getattr(vertices, "ndim", 0) == 4 else ""
            raise ValueError(f"vertices must be a (B, V={V}, 3) tensor of posed body vertices, got {shape}{hint}")
        B = vertices.shape[0]
        if vertices.shape[1] != V:
            raise ValueError(f"vertices have {vertices.shape[1]} vertices, the CloSET template has {V}")
        if not torch.is_tensor(vtransf) or vtransf.shape != (B, V, 3, 3):
            shape = tuple(vtransf.shape) if hasattr(vtransf, "shape") else type(vtransf).__name__
            hint = " (POP's 4x4 vtransf: pass vtransf[..., :3, :3])" if shape[-2:] == (4, 4) else ""
            raise ValueError(f"vtransf must have shape ({B}, {V}, 3, 3), got {shape}{hint}")
        outfit = torch.as_tensor(outfit, device=vertices.device)
        if outfit.ndim == 0:
            outfit = outfit.expand(B)
        if outfit.is_floating_point() or outfit.shape != (B,):
            raise ValueError(f"outfit must be an integer id or a ({B},) integer tensor, got {tuple(outfit.shape)} {outfit.dtype}")
        if int(outfit.min()) < 0 or int(outfit.max()) >= self.num_outfits:
            raise ValueError(f"outfit id out of range [0, {self.num_outfits}): got {outfit.tolist()}")
        if face_idx is None or barycentric is None:
            raise ValueError("face_idx and barycentric (query points on the template) are required")
        return outfit.long()

    def forward(
        self, vertices: torch.Tensor, vtransf: torch.Tensor, outfit, face_idx, barycentric, *, cached: bool = True
    ) -> CloSETOutput:
        """vertices (B, V, 3) posed pelvis-centred body; vtransf (B, V, 3, 3); outfit:
        int or (B,) ids; face_idx (P,) or (B, P) and barycentric (P, 3) / (B, P, 3)
        query points on the template. ``cached=False`` recomputes FPS / ball query."""
        outfit = self._check_inputs(vertices, vtransf, outfit, face_idx, barycentric)
        cfg = self.config
        phi_p = self.encode_pose(vertices, cached)  # (B, V, Cp)
        phi_g, codes = self.encode_garment(outfit, cached)  # (B, V, Cg)
        B = vertices.shape[0]
        phi = barycentric_interpolate(torch.cat([phi_g, phi_p], -1), self.faces, face_idx, barycentric)  # Eq. 2
        cg = phi_g.shape[-1]
        p_t = barycentric_interpolate(self.template[None].expand(B, -1, -1), self.faces, face_idx, barycentric)
        p_u = barycentric_interpolate(vertices, self.faces, face_idx, barycentric)  # (B, P, 3)
        if cfg.decomposition:
            r_g, _ = self.garment_decoder(torch.cat([phi[..., :cg], p_t], -1))  # Eq. 3
            r_p, n_local = self.pose_decoder(torch.cat([phi, p_t], -1))
            r_g, r_p = r_g * cfg.disp_scale, r_p * cfg.disp_scale
            r = r_g + r_p
        else:
            r, n_local = self.decoder(torch.cat([phi, p_t], -1))
            r = r * cfg.disp_scale
            r_g = r_p = None
        T = blend_transforms(vtransf, self.faces, face_idx, barycentric)  # (B, P, 3, 3)
        x = (T @ r[..., None])[..., 0] + p_u
        n = F.normalize((T @ n_local[..., None])[..., 0], dim=-1)
        return CloSETOutput(x, n, r, r_g, r_p, p_u, codes)
