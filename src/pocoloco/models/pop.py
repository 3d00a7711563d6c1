"""POP: the Power of Points (Ma et al. 2021, "The Power of Points for Modeling Humans in
Clothing", ICCV), re-implemented from the paper and its supplementary material.

Pipeline (paper Fig. 2, Sec. 3.1-3.2, SupMat A.1):

1. Pose encoder: a UV position map I (B, 3, Ri, Ri) of the posed *mean-shape* body
   (Ri = 128) -> UNet (7 stride-2 4x4 convs + BatchNorm + LeakyReLU(0.2); 7 mirrored
   [ReLU, ConvTranspose2d, BatchNorm] ups with skips; no BatchNorm on the last) ->
   pose features P (B, Cp=64, Ri, Ri).
2. Geometric feature tensor G (n_outfits, Cg=64, Ri, Ri), init N(0, 0.01^2),
   auto-decoded (one per outfit, shared by all its frames), smoothed by three
   bias-free 5x5 convolutions.
3. Query points: the valid pixels of an Rq x Rq UV map (Rq = 256) of the subject's
   posed body: UV u_i, position p_i, local frame T_i (barycentric blend of the
   per-vertex skinning transforms, LoopReg-style).
4. Shape decoder f_w([u_i, z_i^P, z_i^G]) with z = bilinear lookup at u_i: 8-layer MLP
   (width 256, input skip into layer 4 as DeepSDF, Softplus(beta=20) + BatchNorm on
   all but the last layer), branching after layer 5 into a displacement head and a
   normal head.
5. Eq. (2): x_i = T_i (s r_i) + p_i with s = 0.02 (the scaling of the public
   code); n_i = normalize(T_i n~_i).

Decoder implementations (same weights, same outputs at the valid query pixels):

* ``"linear_valid"`` (default, fast): features are sampled only at the P valid query
  UVs (``grid_sample``, border padding = the bilinear up-sampling's edge clamp) and
  the MLP is ``nn.Linear`` + ``BatchNorm1d`` over the B*P valid points.
* ``"conv1d_all_pixels"`` (reference, the structure of the public code): the feature
  tensors are bilinearly up-sampled to Rq x Rq and the MLP runs as 1x1 ``Conv1d`` over
  all Rq^2 pixels, valid or not; the valid pixels are picked at the end. Its
  BatchNorm statistics are taken over the valid pixels only (so the two paths agree
  in training mode too; the public code also averages over the empty pixels).

The decoder itself and its fast CPU paths: :mod:`pocoloco.models.pop_decoder`. Losses
(paper Eq. 3-6), training batches and unseen-outfit fitting (Eq. 7) are the method's, in
:mod:`pocoloco.methods.pop`.

Shapes: B batch, V body vertices, P valid query points, N scan points, C channels,
Ri input map resolution, Rq query map resolution.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import ClassVar, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pocoloco.body.surface import (
    BodySurface,
    barycentric_interpolate,
    blend_transforms,
    pixel_uv,
    uv_to_grid,
)
from pocoloco.body.skeleton import NUM_JOINTS
from pocoloco.data.motion_window import motion_feature_dim, window_samples
from pocoloco.models.conditioning import MotionEncoder
from pocoloco.models.pop_decoder import ShapeDecoder
from pocoloco.utils.config import Config

__all__ = ["DECODER_IMPLS", "LEGACY_LOSS_WEIGHTS", "LEGACY_TRAINING_FIELDS", "POP", "POPBatch", "POPConfig", "POPLossWeights", "POPOutput",
           "POPQuery", "POP_PRESETS", "pop_preset"]

DECODER_IMPLS = ("linear_valid", "conv1d_all_pixels")


# ---------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------


#: POPConfig fields of checkpoints written before the network and training configs were split
#: (loss weight names -> POPLossWeights fields; the rest are SkinnedTrainConfig's)
LEGACY_LOSS_WEIGHTS = {"w_s2m": "s2m", "w_m2s": "m2s", "w_normal": "normal", "w_displacement": "displacement",
                       "w_feature": "feature"}  # fmt: skip
LEGACY_TRAINING_FIELDS = frozenset({*LEGACY_LOSS_WEIGHTS, "num_scan_points", "normal_start", "lr", "lr_features",
                                    "batch_size"})  # fmt: skip


@dataclass(frozen=True)
class POPConfig(Config):
    """POP hyper-parameters (paper SupMat A.1-A.2).

    unet_channels: output channels of the stride-2 down convolutions (their number is
        the UNet depth; ``input_resolution`` must be divisible by 2**depth).
    decoder_layers / skip_layer / branch_layer: 1-based MLP layer indices; layer
        ``skip_layer`` takes [hidden, input]; layers >= ``branch_layer`` are duplicated
        into the displacement and normal heads; the last layer has no BN/activation.
    displacement_scale: s in x = T (s r) + p (0.02 in the public code).
    pose_input: "mean_shape" = the UNet sees the posed mean-shape body (paper Sec. 3.2,
        body-shape agnostic), "subject" = the subject's own posed body.
    motion_window: seconds of past motion whose code joins the pose features (issue 41's ablation:
        motion information without a generative model; 0: the pose alone, the paper's POP), at
        ``motion_hz`` samples per second.
    The network only: the loss weights are :class:`POPLossWeights`, the learning rates, batch and
    scan points the training run's (``pocoloco.methods.skinned.SkinnedTrainConfig``).
    """

    input_resolution: int = 128
    query_resolution: int = 256
    unet_channels: tuple[int, ...] = (32, 64, 128, 256, 256, 256, 256)
    pose_channels: int = 64
    geom_channels: int = 64
    geom_smooth_layers: int = 3
    geom_kernel: int = 5
    geom_init_std: float = 0.01
    decoder_width: int = 256
    decoder_layers: int = 8
    skip_layer: int = 4
    branch_layer: int = 6
    softplus_beta: float = 20.0
    displacement_scale: float = 0.02
    decoder_impl: Literal["linear_valid", "conv1d_all_pixels"] = "linear_valid"
    transform_mode: Literal["blend", "polar"] = "blend"
    pose_input: Literal["mean_shape", "subject"] = "mean_shape"
    motion_window: float = 0.0
    motion_hz: float = 8.0
    legacy_fields: ClassVar[frozenset[str]] = LEGACY_TRAINING_FIELDS

    @property
    def motion_feature_dim(self) -> int:
        """F of the motion features the model takes (0: none; 116 for 2 s at 8 Hz)."""
        if not self.motion_window:
            return 0
        return motion_feature_dim(window_samples(self.motion_window, self.motion_hz))

    def __post_init__(self):
        def pos_int(name):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"POPConfig.{name} must be a positive integer, got {v!r}")

        for name in ("input_resolution", "query_resolution", "pose_channels", "geom_channels", "geom_kernel",
                     "decoder_width", "decoder_layers"):  # fmt: skip
            pos_int(name)
        if not self.unet_channels or any(int(c) < 1 for c in self.unet_channels):
            raise ValueError(f"POPConfig.unet_channels must be positive integers, got {self.unet_channels!r}")
        object.__setattr__(self, "unet_channels", tuple(int(c) for c in self.unet_channels))
        if self.input_resolution % (2 ** len(self.unet_channels)):
            raise ValueError(f"POPConfig.input_resolution={self.input_resolution} must be divisible by "
                             f"2**{len(self.unet_channels)} (one halving per UNet level)")  # fmt: skip
        if not (self.motion_window >= 0 and self.motion_hz > 0):
            raise ValueError(f"POPConfig.motion_window must be >= 0 and motion_hz > 0, got {self.motion_window}, "
                             f"{self.motion_hz}")  # fmt: skip
        if self.geom_kernel % 2 == 0:
            raise ValueError(f"POPConfig.geom_kernel must be odd, got {self.geom_kernel}")
        if not 2 <= self.skip_layer < self.branch_layer <= self.decoder_layers:
            raise ValueError("POPConfig needs 2 <= skip_layer < branch_layer <= decoder_layers, got "
                             f"{self.skip_layer}, {self.branch_layer}, {self.decoder_layers}")  # fmt: skip
        if self.decoder_impl not in DECODER_IMPLS:
            raise ValueError(f"POPConfig.decoder_impl must be one of {DECODER_IMPLS}, got {self.decoder_impl!r}")
        if self.transform_mode not in ("blend", "polar"):
            raise ValueError(f"POPConfig.transform_mode must be 'blend' or 'polar', got {self.transform_mode!r}")
        if self.pose_input not in ("mean_shape", "subject"):
            raise ValueError(f"POPConfig.pose_input must be 'mean_shape' or 'subject', got {self.pose_input!r}")
        if not self.geom_init_std >= 0:
            raise ValueError(f"POPConfig.geom_init_std must be >= 0, got {self.geom_init_std!r}")
        if not self.displacement_scale > 0:
            raise ValueError(f"POPConfig.displacement_scale must be > 0, got {self.displacement_scale!r}")


@dataclass(frozen=True)
class POPLossWeights(Config):
    """The weights of POP's loss (paper Eq. 3; the values of its public training configuration):
    scan-to-model and model-to-scan Chamfer 1e4 each, normal 0.1 (from the run's ``normal_start``;
    the paper switches it on at epoch 250 of 400), displacement 2e3, feature 1."""

    s2m: float = 1e4
    m2s: float = 1e4
    normal: float = 0.1
    displacement: float = 2e3
    feature: float = 1.0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
                raise ValueError(f"POPLossWeights.{f.name} must be a finite number >= 0, got {v!r}")



POP_PRESETS: dict[str, POPConfig] = {
    # paper size: 128^2 UNet input, 256^2 query map, ~11.3M network parameters
    "paper": POPConfig(),
    # CPU presets: smaller maps and widths, same structure
    "small": POPConfig(input_resolution=64, query_resolution=128, unet_channels=(16, 32, 64, 128, 128, 128),
                       pose_channels=32, geom_channels=32, decoder_width=128),  # fmt: skip
    "tiny": POPConfig(input_resolution=32, query_resolution=32, unet_channels=(8, 16, 32, 32, 32),
                      pose_channels=8, geom_channels=8, geom_kernel=3, decoder_width=32),  # fmt: skip
}


def pop_preset(name: str, **overrides) -> POPConfig:
    """A named preset (``POP_PRESETS``), optionally with fields replaced."""
    if name not in POP_PRESETS:
        raise ValueError(f"unknown POP preset {name!r}; choose from {sorted(POP_PRESETS)}")
    return replace(POP_PRESETS[name], **overrides)


# ---------------------------------------------------------------------------
# data containers
# ---------------------------------------------------------------------------


@dataclass
class POPBatch:
    """One training/inference batch (torch), all pelvis-centred (root joint at 0).

    pose_vertices: (B, V, 3) body fed to the pose encoder (posed mean shape, or the
                   subject's body when ``pose_input="subject"``).
    body_vertices: (B, V, 3) the subject's posed body (query points p_i).
    vtransf:       (B, V, 3, 3) per-vertex skinning transforms relative to the bind pose.
    outfit:        (B,) int64 outfit id (row of the geometric feature tensor).
    scan_points:   (B, N, 3) ground-truth points, or None (inference).
    scan_normals:  (B, N, 3) their unit normals, or None.
    motion:        (B, J, F) motion-window features (a ``motion_window`` model), or None (at rest).
    """

    pose_vertices: torch.Tensor
    body_vertices: torch.Tensor
    vtransf: torch.Tensor
    outfit: torch.Tensor
    scan_points: torch.Tensor | None = None
    scan_normals: torch.Tensor | None = None
    motion: torch.Tensor | None = None

    def to(self, device) -> POPBatch:
        return POPBatch(*(None if t is None else t.to(device) for t in
                          (self.pose_vertices, self.body_vertices, self.vtransf, self.outfit,
                           self.scan_points, self.scan_normals, self.motion)))  # fmt: skip


@dataclass
class POPQuery:
    """P query points on the body surface: face_idx (P,) int64, barycentric (P, 3), uv (P, 2)."""

    face_idx: torch.Tensor
    barycentric: torch.Tensor
    uv: torch.Tensor

    def __len__(self) -> int:
        return int(self.face_idx.shape[0])

    def subset(self, idx) -> POPQuery:
        """The points ``idx`` (K,) of this query."""
        i = torch.as_tensor(idx, dtype=torch.long, device=self.face_idx.device)
        return POPQuery(self.face_idx[i], self.barycentric[i], self.uv[i])


@dataclass
class POPOutput:
    """Decoder outputs at the P valid query pixels (row-major pixel order).

    points:       (B, P, 3) x_i = T_i (s r_i) + p_i (Eq. 2).
    normals:      (B, P, 3) unit normals normalize(T_i n~_i).
    displacement: (B, P, 3) local displacement s r_i (metres, before T_i).
    base:         (B, P, 3) p_i on the posed body.
    geom:         (B, Cg, Ri, Ri) the raw (unsmoothed) geometric features used (for L_rg).
    """

    points: torch.Tensor
    normals: torch.Tensor
    displacement: torch.Tensor
    base: torch.Tensor
    geom: torch.Tensor


# ---------------------------------------------------------------------------
# network
# ---------------------------------------------------------------------------


class PoseUNet(nn.Module):
    """UNet pose encoder (SupMat A.1): (B, 3, R, R) -> (B, C_out, R, R).

    Down: [Conv2d 4x4 stride 2, BatchNorm, LeakyReLU(0.2)] per level (the innermost,
    1x1 at the paper size, has no BatchNorm so that batch 1 trains). Up: [ReLU,
    ConvTranspose2d 4x4 stride 2, BatchNorm] mirrored, each concatenated with the
    matching down output; the last up has no BatchNorm.
    """

    def __init__(self, in_channels: int, out_channels: int, channels: Sequence[int]):
        super().__init__()
        ch = list(channels)
        n = len(ch)
        self.down = nn.ModuleList()
        prev = in_channels
        for i, c in enumerate(ch):
            layers = [nn.Conv2d(prev, c, 4, 2, 1)]
            if i < n - 1:
                layers.append(nn.BatchNorm2d(c))
            layers.append(nn.LeakyReLU(0.2))
            self.down.append(nn.Sequential(*layers))
            prev = c
        self.up = nn.ModuleList()
        for j in range(n):
            src = n - 1 - j  # down level whose output feeds this up (with its skip)
            cin = ch[src] if j == 0 else 2 * ch[src]
            cout = out_channels if src == 0 else ch[src - 1]
            layers = [nn.ReLU(), nn.ConvTranspose2d(cin, cout, 4, 2, 1)]
            if src > 0:
                layers.append(nn.BatchNorm2d(cout))
            self.up.append(nn.Sequential(*layers))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for d in self.down:
            x = d(x)
            skips.append(x)
        x = self.up[0](skips[-1])
        for j in range(1, len(self.up)):
            x = self.up[j](torch.cat([x, skips[-1 - j]], dim=1))
        return x


class POP(nn.Module):
    """The POP model for one body mesh topology (e.g. anny) and ``num_outfits`` outfits.

    surface: ``BodySurface`` of the mesh (faces, UVs, which faces carry query points);
    its rasters at ``input_resolution`` and ``query_resolution`` are stored as buffers.
    num_vertices: V of the meshes passed in (checked).
    """

    def __init__(self, config: POPConfig, surface: BodySurface, num_outfits: int, num_vertices: int | None = None):
        super().__init__()
        if isinstance(num_outfits, bool) or not isinstance(num_outfits, int) or num_outfits < 1:
            raise ValueError(f"num_outfits must be a positive integer, got {num_outfits!r}")
        self.config = config
        self.faces_np = surface.faces
        self.num_vertices = int(num_vertices if num_vertices is not None else surface.faces.max() + 1)
        if self.num_vertices <= int(surface.faces.max()):
            raise ValueError(f"num_vertices={self.num_vertices} but faces index vertex {int(surface.faces.max())}")
        c = config
        self.surface = surface  # kept to build query rasters at other resolutions (``query_points``)
        self.register_buffer("faces", torch.from_numpy(surface.faces.astype(np.int64)), persistent=False)
        # the UV layout, saved with the weights so a checkpoint rebuilds the model alone (``from_state``)
        self.register_buffer("surface_uv", torch.from_numpy(np.asarray(surface.uv, np.float32)))
        self.register_buffer("surface_uv_faces", torch.from_numpy(np.asarray(surface.uv_faces, np.int64)))
        self.register_buffer("surface_faces", torch.from_numpy(surface.faces.astype(np.int64)))
        self.register_buffer("surface_face_mask", torch.from_numpy(np.asarray(surface.face_mask, bool)))
        rin = surface.raster(c.input_resolution)
        rq = surface.raster(c.query_resolution)
        if rin.num_valid == 0 or rq.num_valid == 0:
            raise ValueError("the UV layout covers no pixel at the configured resolutions")
        pin = rin.points()
        self.register_buffer("in_face", torch.from_numpy(pin.face_idx), persistent=False)
        self.register_buffer("in_bary", torch.from_numpy(pin.barycentric), persistent=False)
        self.register_buffer("in_flat", torch.from_numpy(np.flatnonzero(rin.mask)), persistent=False)
        pq = rq.points()
        self.register_buffer("q_face", torch.from_numpy(pq.face_idx), persistent=False)
        self.register_buffer("q_bary", torch.from_numpy(pq.barycentric), persistent=False)
        self.register_buffer("q_flat", torch.from_numpy(np.flatnonzero(rq.mask)), persistent=False)
        self.register_buffer("q_uv", torch.from_numpy(rq.uv()), persistent=False)  # (P, 2)
        all_pix = np.stack(np.meshgrid(np.arange(c.query_resolution), np.arange(c.query_resolution), indexing="ij"), -1)
        self.register_buffer("all_uv", torch.from_numpy(pixel_uv(all_pix.reshape(-1, 2), c.query_resolution)),
                             persistent=False)  # fmt: skip  (Rq*Rq, 2) row-major

        self.unet = PoseUNet(3, c.pose_channels, c.unet_channels)
        # the last seconds of motion -> a (B, Cp) code added to every pose-feature pixel; zero-initialised
        # so a model given it starts as the pose-only POP it is fine-tuned from
        self.motion_in = (MotionEncoder(c.motion_feature_dim, NUM_JOINTS, c.pose_channels) if c.motion_window
                          else None)  # fmt: skip
        self.geom = nn.Parameter(torch.randn(num_outfits, c.geom_channels, c.input_resolution, c.input_resolution)
                                 * c.geom_init_std)  # fmt: skip
        pad = c.geom_kernel // 2
        self.geom_smooth = nn.Sequential(
            *[nn.Conv2d(c.geom_channels, c.geom_channels, c.geom_kernel, padding=pad, bias=False)
              for _ in range(c.geom_smooth_layers)]  # fmt: skip
        )
        self.decoder = ShapeDecoder(2 + c.pose_channels + c.geom_channels, c.decoder_width, c.decoder_layers,
                                    c.skip_layer, c.branch_layer, c.softplus_beta)  # fmt: skip

    # -- bookkeeping -------------------------------------------------------
    @classmethod
    def from_state(cls, config: POPConfig | dict, state: dict[str, torch.Tensor], num_vertices: int) -> POP:
        """Rebuild a model from ``config`` (or its ``to_dict()``) and a ``state_dict()``: the UV
        layout and the number of outfits are read from the state."""
        cfg = config if isinstance(config, POPConfig) else POPConfig.from_dict(config)
        for k in ("surface_uv", "surface_uv_faces", "surface_faces", "surface_face_mask", "geom"):
            if k not in state:
                raise ValueError(f"POP state is missing {k!r}")
        surface = BodySurface(state["surface_faces"].numpy(), state["surface_uv"].numpy(),
                              state["surface_uv_faces"].numpy(), state["surface_face_mask"].numpy().astype(bool))  # fmt: skip
        model = cls(cfg, surface, int(state["geom"].shape[0]), int(num_vertices))
        model.load_state_dict(state)
        return model

    def query_points(self, resolution: int | None = None) -> POPQuery:
        """The valid pixels of the R x R UV query map (default R = ``config.query_resolution``)
        as a :class:`POPQuery` (P points). POP's decoder takes any UV, so a map finer than the
        training one gives more points on the same surface (paper Sec. 3.1)."""
        R = self.config.query_resolution if resolution is None else int(resolution)
        if R == self.config.query_resolution:
            return POPQuery(self.q_face, self.q_bary, self.q_uv)
        r = self.surface.raster(R)
        pts = r.points()
        dev = self.q_face.device
        return POPQuery(torch.from_numpy(pts.face_idx).to(dev), torch.from_numpy(pts.barycentric).to(dev),
                        torch.from_numpy(r.uv()).to(dev))  # fmt: skip

    @property
    def num_outfits(self) -> int:
        return int(self.geom.shape[0])

    @property
    def num_query_points(self) -> int:
        return int(self.q_face.shape[0])

    def network_parameters(self) -> list[nn.Parameter]:
        """All parameters except the geometric feature tensor."""
        return [p for n, p in self.named_parameters() if n != "geom"]

    def num_network_parameters(self) -> int:
        return sum(p.numel() for p in self.network_parameters())

    @torch.no_grad()
    def add_outfit(self, features: torch.Tensor) -> int:
        """Append a fitted (1, Cg, Ri, Ri) feature tensor as a new outfit; returns its id.
        (Replaces the ``geom`` Parameter: rebuild any optimiser afterwards.)"""
        want = (1, *self.geom.shape[1:])
        if tuple(features.shape) != want:
            raise ValueError(f"features must have shape {want}, got {tuple(features.shape)}")
        self.geom = nn.Parameter(torch.cat([self.geom.data, features.to(self.geom)], 0))
        return self.num_outfits - 1

    def _check_body(self, name: str, t: torch.Tensor, tail: tuple[int, ...], B: int | None = None) -> None:
        if t.ndim != 2 + len(tail) or t.shape[1] != self.num_vertices or tuple(t.shape[2:]) != tail:
            raise ValueError(f"{name} must have shape (B, V={self.num_vertices}, {', '.join(map(str, tail))}), "
                             f"got {tuple(t.shape)}")  # fmt: skip
        if B is not None and t.shape[0] != B:
            raise ValueError(f"{name} has batch {t.shape[0]}, expected {B}")

    # -- pieces ------------------------------------------------------------
    def input_posmap(self, pose_vertices: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) posed (mean-shape) bodies -> (B, 3, Ri, Ri) UV position maps (0 off the body)."""
        self._check_body("pose_vertices", pose_vertices, (3,))
        B, R = pose_vertices.shape[0], self.config.input_resolution
        p = barycentric_interpolate(pose_vertices, self.faces, self.in_face, self.in_bary)  # (B, Pi, 3)
        flat = pose_vertices.new_zeros(B, R * R, 3).index_copy(1, self.in_flat, p)
        return flat.reshape(B, R, R, 3).permute(0, 3, 1, 2)

    def feature_maps(self, posmap: torch.Tensor, geom: torch.Tensor, motion: torch.Tensor | None = None) -> torch.Tensor:
        """(B, 3, Ri, Ri) posmap, (B, Cg, Ri, Ri) raw geometric features [, (B, J, F) motion-window
        features] -> (B, Cp+Cg, Ri, Ri)."""
        pose = self.unet(posmap)
        if self.motion_in is not None:
            want = (posmap.shape[0], NUM_JOINTS, self.config.motion_feature_dim)
            if motion is None:  # a body at rest
                motion = pose.new_zeros(want)
            if tuple(motion.shape) != want or not torch.isfinite(motion).all():
                raise ValueError(f"motion must be finite features of shape {want}, got {tuple(motion.shape)}")
            pose = pose + self.motion_in(motion.to(pose.dtype)).mean(1)[:, :, None, None]
        elif motion is not None:
            raise ValueError("this POP takes no motion window (trained without --motion-window)")
        return torch.cat([pose, self.geom_smooth(geom)], dim=1)

    def decode(self, feats: torch.Tensor, query_uv: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C, Ri, Ri) feature maps -> raw (B, P, 3) displacement, (B, P, 3) normal at
        the valid query pixels, with the configured ``decoder_impl``; or at ``query_uv``
        (P, 2) (any UV points; ``linear_valid`` only)."""
        B = feats.shape[0]
        if query_uv is not None and self.config.decoder_impl != "linear_valid":
            raise ValueError("query points other than the training query map need decoder_impl='linear_valid'")
        q_uv = self.q_uv if query_uv is None else query_uv
        P = q_uv.shape[0]
        if self.config.decoder_impl == "linear_valid":
            grid = uv_to_grid(q_uv).to(feats.dtype)[None, None].expand(B, 1, P, 2)
            z = F.grid_sample(feats, grid, mode="bilinear", padding_mode="border", align_corners=False)  # (B, C, 1, P)
            z = z[:, :, 0].transpose(1, 2)  # (B, P, C)
            uv = q_uv.to(feats.dtype)[None].expand(B, P, 2)
            x = torch.cat([uv, z], dim=-1).reshape(B * P, -1)  # (B*P, 2+C)
            r, n = self.decoder(x)
            return r.reshape(B, P, 3), n.reshape(B, P, 3)
        # reference: up-sample to Rq x Rq, 1x1 convs over all pixels, pick the valid ones
        Rq = self.config.query_resolution
        up = F.interpolate(feats, size=(Rq, Rq), mode="bilinear", align_corners=False)  # (B, C, Rq, Rq)
        uv = self.all_uv.to(feats.dtype).t()[None].expand(B, 2, Rq * Rq)
        x = torch.cat([uv, up.reshape(B, -1, Rq * Rq)], dim=1)  # (B, 2+C, Rq*Rq)
        r, n = self.decoder.forward_conv1d(x, self.q_flat)
        return r.index_select(2, self.q_flat).transpose(1, 2), n.index_select(2, self.q_flat).transpose(1, 2)

    def interpolate_pixels(self, values: torch.Tensor, query_uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, P, C) values at the valid training query pixels -> (B, Q, C) at ``query_uv`` (Q, 2)
        by bilinear interpolation over the valid pixels only (normalised: invalid neighbours
        weigh 0), and the (Q,) summed weight of the valid neighbours (0: none; a pixel centre: 1,
        its own value exactly)."""
        B, P, C = values.shape
        Rq = self.config.query_resolution
        grid = uv_to_grid(query_uv).to(values.dtype)[None, None]  # (1, 1, Q, 2)
        maps = values.new_zeros(B, C + 1, Rq * Rq)
        maps[:, :C].index_copy_(2, self.q_flat, values.transpose(1, 2))
        maps[:, C, self.q_flat] = 1.0
        out = F.grid_sample(maps.reshape(B, C + 1, Rq, Rq), grid.expand(B, 1, -1, 2), mode="bilinear",
                            padding_mode="zeros", align_corners=False)[:, :, 0]  # (B, C+1, Q)  # fmt: skip
        weight = out[:, C]
        return (out[:, :C] / weight.clamp_min(1e-12)[:, None]).transpose(1, 2), weight[0]

    def decode_interpolated(self, feats: torch.Tensor, query_uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw (B, Q, 3) displacement and normal at ``query_uv`` (Q, 2), interpolated from the
        decoder's outputs at the training query pixels (:meth:`interpolate_pixels`); query points
        with no valid pixel among their four neighbours (a UV island's rim) are decoded directly.

        The decoder has only seen the training pixels' UVs: decoded at a finer map's UVs its
        points lie ~13 % farther from the scan (BENCHMARKS, "POP at more points than its UV map");
        interpolated they are as close as at the training pixels."""
        r, n = self.decode(feats, None)
        vals, weight = self.interpolate_pixels(torch.cat([r, n], dim=-1), query_uv)
        r_q, n_q = vals[..., :3], vals[..., 3:]
        rim = weight < 1e-3
        if bool(rim.any()):
            r_d, n_d = self.decode(feats, query_uv[rim])
            r_q, n_q = r_q.clone(), n_q.clone()
            r_q[:, rim], n_q[:, rim] = r_d, n_d
        return r_q, n_q

    def forward(self, batch: POPBatch, geom: torch.Tensor | None = None, query: POPQuery | None = None,
                interpolate: bool = False) -> POPOutput:  # fmt: skip
        """Clothed points for a batch (Eq. 2). ``geom`` (B or 1, Cg, Ri, Ri) overrides the
        outfit rows (used when fitting an unseen outfit). ``query``: decode at these P surface
        points instead of the training query map (e.g. ``query_points(R)`` or a subset); with
        ``interpolate``, their displacements and normals are interpolated from the training
        pixels' (:meth:`decode_interpolated`; for points off the training map)."""
        pv, bv, vt = batch.pose_vertices, batch.body_vertices, batch.vtransf
        self._check_body("pose_vertices", pv, (3,))
        B = pv.shape[0]
        self._check_body("body_vertices", bv, (3,), B)
        self._check_body("vtransf", vt, (3, 3), B)
        if geom is None:
            outfit = torch.as_tensor(batch.outfit)
            if outfit.shape != (B,) or outfit.is_floating_point():
                raise ValueError(f"outfit must be an integer tensor of shape ({B},), got {tuple(outfit.shape)}")
            if B and (int(outfit.min()) < 0 or int(outfit.max()) >= self.num_outfits):
                raise ValueError(f"outfit ids must be in [0, {self.num_outfits}), got {outfit.tolist()}")
            geom = self.geom[outfit.to(self.geom.device)]
        else:
            want = tuple(self.geom.shape[1:])
            if geom.ndim != 4 or tuple(geom.shape[1:]) != want or geom.shape[0] not in (1, B):
                raise ValueError(f"geom must have shape (1 or B, {', '.join(map(str, want))}), got {tuple(geom.shape)}")
            geom = geom.expand(B, *want)
        feats = self.feature_maps(self.input_posmap(pv), geom, batch.motion)
        q_face, q_bary = (self.q_face, self.q_bary) if query is None else (query.face_idx, query.barycentric)
        if query is not None and interpolate:
            r_raw, n_raw = self.decode_interpolated(feats, query.uv)
        else:
            r_raw, n_raw = self.decode(feats, None if query is None else query.uv)
        base = barycentric_interpolate(bv, self.faces, q_face, q_bary)  # (B, P, 3)
        T = blend_transforms(vt, self.faces, q_face, q_bary, self.config.transform_mode)  # (B, P, 3, 3)
        r = r_raw * self.config.displacement_scale
        x = torch.einsum("bpij,bpj->bpi", T, r) + base
        n = F.normalize(torch.einsum("bpij,bpj->bpi", T, n_raw), dim=-1, eps=1e-12)
        return POPOutput(points=x, normals=n, displacement=r, base=base, geom=geom)
