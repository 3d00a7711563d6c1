"""Adapter over the ``anny`` parametric body (Apache-2.0, assets in the wheel).

A subject is built once from phenotype parameters; ``AnnyBody.pose`` then poses
it for a batch of frames and returns everything the data pipeline and the
models need: posed vertices, the 24 skeleton joints, per-vertex skinning
transforms (POP's ``vtransf``), all in metres, Z up, body facing -Y.

Rotations are given per skeleton joint as axis-angle vectors in anny's
``local-ref`` parameterisation: a rotation of a bone expressed in axes that, in
the rest pose, are (almost) the world axes. So a hip flexion (leg forward, to
-Y) is a rotation about -X, a knee flexion about +X, turning the whole body is
a rotation of the pelvis about +Z.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass

import numpy as np
import torch

from .rig import SkeletonRig
from .skeleton import ANNY_BONE_OF_JOINT, JOINT_NAMES, NUM_JOINTS

#: Phenotype parameters anny accepts, each in [0, 1] (0.5 = average).
PHENOTYPE_KEYS: tuple[str, ...] = ("gender", "age", "muscle", "weight", "height", "proportions")


def default_cache_dir() -> str:
    """Where anny's parsed assets are cached (``$ANNY_CACHE_DIR`` wins)."""
    return os.environ.get("ANNY_CACHE_DIR") or os.path.join(
        os.path.expanduser("~"), ".cache", "pocoloco", "anny"
    )


@functools.lru_cache(maxsize=1)
def load_anny_model():
    """The anny model in float32 on CPU, loaded once per process.

    The first call in a fresh cache parses the MakeHuman assets (~2.5 min on a
    2-core CPU); later calls load a compact cached file (~1 s).
    """
    os.environ.setdefault("ANNY_CACHE_DIR", default_cache_dir())
    os.makedirs(os.environ["ANNY_CACHE_DIR"], exist_ok=True)
    quiet_warp()
    import anny  # deferred: importing anny initialises warp

    return anny.Anny().to(dtype=torch.float32)


def quiet_warp() -> None:
    """Silence warp's start-up banner, its per-kernel load messages (anny and newton both use warp)
    and, on machines without a GPU, the CUDA-driver warning its native code prints to stderr when
    it initialises (warp then runs on the CPU, which is all pocoloco asks of it): warp is
    initialised here with the process's stderr captured, and anything else it printed is passed
    on. ``POCOLOCO_VERBOSE_WARP=1`` keeps everything."""
    if os.environ.get("POCOLOCO_VERBOSE_WARP"):
        return
    try:
        import warp
    except ImportError:
        return
    import logging
    import sys
    import tempfile

    warp.config.log_level = logging.WARNING
    warp.config.quiet = True
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as captured:
        os.dup2(captured.fileno(), 2)
        try:
            warp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            captured.seek(0)
            rest = [ln for ln in captured.read().decode(errors="replace").splitlines()
                    if ln.strip() and "CUDA driver" not in ln]  # fmt: skip
    if rest:
        print("\n".join(rest), file=sys.stderr)


def _rotvec_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula. (..., 3) axis-angle -> (..., 3, 3) rotation matrix."""
    angle = rotvec.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    axis = rotvec / angle
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*rotvec.shape[:-1], 3, 3)
    s = torch.sin(angle)[..., None]
    c = torch.cos(angle)[..., None]
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(k)
    return eye + s * k + (1 - c) * (k @ k)


@dataclass
class PosedBody:
    """A batch of T posed bodies (numpy float32, metres, Z up).

    vertices: (T, V, 3) posed surface vertices.
    joints:   (T, J, 3) the 24 skeleton joints (``skeleton.JOINT_NAMES``).
    vtransf:  (T, V, 3, 3) linear part of each vertex's skinning transform
              sum_k w_vk A_k (POP's ``vtransf``), mapping rest-pose offsets to
              posed offsets.
    """

    vertices: np.ndarray
    joints: np.ndarray
    vtransf: np.ndarray


class AnnyBody:
    """One subject: an anny body with fixed phenotype.

    Attributes (numpy):
        faces:       (F, 3) int64 triangle vertex indices.
        uv:          (Vt, 2) float32 texture coordinates.
        uv_faces:    (F, 3) int64 indices into ``uv`` per face corner.
        template:    (V, 3) float32 bind-pose (A-pose) vertices of this subject:
                     the pose in which skinning is exact, ``vtransf`` maps
                     offsets in this pose to posed offsets.
        template_joints: (J, 3) float32 skeleton joints in the bind pose.
        zero_pose:   PosedBody of the all-zero rotation pose (T=1). It differs
                     slightly from the bind pose (anny's ``local-ref`` zero
                     tilts the upper spine and shoulders by ~0.1 rad).
        vertex_joint: (V,) int64 the skeleton joint that moves each vertex most
                     (its body part), used for labels and colliders.
    """

    def __init__(self, phenotype: dict[str, float] | None = None):
        phenotype = dict(phenotype or {})
        unknown = set(phenotype) - set(PHENOTYPE_KEYS)
        if unknown:
            raise ValueError(f"unknown phenotype keys {sorted(unknown)}; expected {PHENOTYPE_KEYS}")
        for k, v in phenotype.items():
            if not (0.0 <= float(v) <= 1.0):
                raise ValueError(f"phenotype {k}={v} is outside [0, 1]")
        self.phenotype = {k: float(phenotype.get(k, 0.5)) for k in PHENOTYPE_KEYS}
        self.model = load_anny_model()
        labels = list(self.model.bone_labels)
        self.num_bones = len(labels)
        self.bone_of_joint = torch.tensor([labels.index(ANNY_BONE_OF_JOINT[n]) for n in JOINT_NAMES])

        self.faces = self.model.faces.cpu().numpy().astype(np.int64)
        self.uv = self.model.texture_coordinates.cpu().numpy().astype(np.float32)
        self.uv_faces = self.model.face_texture_coordinate_indices.cpu().numpy().astype(np.int64)

        zero = self.run_anny(torch.zeros(1, NUM_JOINTS, 3))
        # anny's posed output has the pelvis at the origin; shift the bind pose to match
        origin = zero["rest_bone_poses"][0, self.bone_of_joint[0], :3, 3]
        self.template = (zero["rest_vertices"][0] - origin).numpy().astype(np.float32)
        self.template_joints = (zero["rest_bone_poses"][0, self.bone_of_joint, :3, 3] - origin).numpy().astype(np.float32)
        self.zero_pose = self._forward(torch.zeros(1, NUM_JOINTS, 3), torch.zeros(1, 3))
        self.vertex_joint = self._vertex_joint(labels)

    @property
    def num_vertices(self) -> int:
        return self.template.shape[0]

    def _bone_joint(self) -> np.ndarray:
        """(B,) int64: the skeleton joint of each anny bone's nearest skeleton ancestor (itself for
        a skeleton bone; fingers -> hand, toes -> foot, ...)."""
        parents = self.model.bone_parents
        parents = parents.tolist() if torch.is_tensor(parents) else list(parents)
        joint_of_bone = {int(b): j for j, b in enumerate(self.bone_of_joint.tolist())}
        bone_to_joint = np.zeros(self.num_bones, dtype=np.int64)
        for b in range(self.num_bones):
            a = b
            while a not in joint_of_bone and parents[a] >= 0:
                a = parents[a]
            bone_to_joint[b] = joint_of_bone.get(a, 0)
        return bone_to_joint

    def _vertex_joint(self, labels: list[str]) -> np.ndarray:
        """Map each vertex to the skeleton joint of its heaviest-weighted bone's
        nearest skeleton ancestor (:meth:`_bone_joint`)."""
        w = self.model.vertex_bone_weights.cpu().numpy()
        idx = self.model.vertex_bone_indices.cpu().numpy()
        heaviest = idx[np.arange(len(idx)), w.argmax(1)]
        return self._bone_joint()[heaviest]

    def run_anny(self, joint_rotvecs: torch.Tensor) -> dict[str, torch.Tensor]:
        """joint_rotvecs (T, J, 3) -> anny's raw output (bones not in the skeleton keep zero rotation)."""
        t = joint_rotvecs.shape[0]
        pose = torch.eye(4).expand(t, self.num_bones, 4, 4).clone()
        pose[:, self.bone_of_joint, :3, :3] = _rotvec_to_matrix(joint_rotvecs)
        pheno = {k: torch.full((t,), v) for k, v in self.phenotype.items()}
        with torch.no_grad():
            return self.model(pose_parameters=pose, phenotype_kwargs=pheno)

    def _forward(self, joint_rotvecs: torch.Tensor, root_translation: torch.Tensor) -> PosedBody:
        """joint_rotvecs (T, J, 3), root_translation (T, 3) -> PosedBody."""
        out = self.run_anny(joint_rotvecs)
        bone_poses = out["bone_poses"]  # (T, B, 4, 4)
        skin = bone_poses @ torch.linalg.inv(out["rest_bone_poses"])  # A_k, (T, B, 4, 4)
        w = self.model.vertex_bone_weights  # (V, 9)
        idx = self.model.vertex_bone_indices  # (V, 9)
        vtransf = (w[None, :, :, None, None] * skin[:, idx, :3, :3]).sum(2)  # (T, V, 3, 3)
        shift = root_translation[:, None, :]  # anny puts the posed pelvis at the origin
        return PosedBody(
            vertices=(out["vertices"] + shift).numpy().astype(np.float32),
            joints=(bone_poses[:, self.bone_of_joint, :3, 3] + shift).numpy().astype(np.float32),
            vtransf=vtransf.numpy().astype(np.float32),
        )

    def joint_transforms(self, joint_rotvecs: np.ndarray | torch.Tensor, chunk: int = 64) -> np.ndarray:
        """(T, 24, 3) rotations -> (T, 24, 3, 4) float64 skinning transforms ``A_j = bone_pose @
        inv(rest_bone_pose)`` of the 24 skeleton bones (anny's posed frame: pelvis at the origin);
        with :meth:`skeleton_rig` they give the posed body (:class:`~pocoloco.body.rig.SkeletonRig`)."""
        rot = torch.as_tensor(np.asarray(joint_rotvecs, dtype=np.float32))
        if rot.ndim != 3 or rot.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"joint_rotvecs must have shape (T, {NUM_JOINTS}, 3), got {tuple(rot.shape)}")
        out = []
        for i in range(0, rot.shape[0], chunk):
            r = self.run_anny(rot[i : i + chunk])
            bones = self.bone_of_joint
            skin = r["bone_poses"][:, bones].double() @ torch.linalg.inv(r["rest_bone_poses"][:, bones].double())
            out.append(skin[..., :3, :].numpy())
        return np.concatenate(out)

    def skeleton_rig(self) -> SkeletonRig:
        """This subject's :class:`~pocoloco.body.rig.SkeletonRig`: anny's rest vertices, weights and
        bones, each bone's skeleton ancestor and its constant offset ``C_b = inv(A_j(b)) A_b``
        (taken at the zero pose; the same at every pose)."""
        bone_joint = self._bone_joint()
        r = self.run_anny(torch.zeros(1, NUM_JOINTS, 3))
        skin = r["bone_poses"][0].double() @ torch.linalg.inv(r["rest_bone_poses"][0].double())  # (B, 4, 4)
        offsets = torch.linalg.inv(skin[torch.as_tensor(self.bone_of_joint)[bone_joint]]) @ skin
        return SkeletonRig(
            rest_vertices=r["rest_vertices"][0].numpy().astype(np.float32),
            weights=self.model.vertex_bone_weights.cpu().numpy().astype(np.float32),
            bones=self.model.vertex_bone_indices.cpu().numpy().astype(np.int64),
            bone_joint=bone_joint,
            bone_offsets=offsets[:, :3, :].numpy(),
        )

    def pose_joints(self, joint_rotvecs: np.ndarray | torch.Tensor, chunk: int = 64) -> np.ndarray:
        """Only the (T, 24, 3) skeleton joints for (T, 24, 3) rotations, zero root
        translation: ``pose(...).joints`` without the per-vertex skinning
        transforms (~6x faster). Inputs are validated by the caller."""
        rot = torch.as_tensor(np.asarray(joint_rotvecs, dtype=np.float32))
        out = []
        for i in range(0, rot.shape[0], chunk):
            bone_poses = self.run_anny(rot[i : i + chunk])["bone_poses"]  # (t, B, 4, 4)
            out.append(bone_poses[:, self.bone_of_joint, :3, 3].numpy().astype(np.float32))
        return np.concatenate(out)

    def pose(
        self,
        joint_rotvecs: np.ndarray | torch.Tensor,
        root_translation: np.ndarray | torch.Tensor | None = None,
        chunk: int = 32,
    ) -> PosedBody:
        """Pose the subject for T frames.

        Args:
            joint_rotvecs: (T, 24, 3) or (24, 3) axis-angle per skeleton joint
                (anny ``local-ref`` axes, see module docstring). Joint 0 is the
                global orientation.
            root_translation: (T, 3) or (3,) metres added to everything; None = 0
                (the bind-pose pelvis is at the origin).
            chunk: frames posed per anny call (bounds memory).
        Returns:
            PosedBody with a leading T axis (kept even for a single pose).
        """
        rot = torch.as_tensor(np.asarray(joint_rotvecs, dtype=np.float32))
        if rot.ndim == 2:
            rot = rot[None]
        if rot.ndim != 3 or rot.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"joint_rotvecs must have shape (T, {NUM_JOINTS}, 3), got {tuple(rot.shape)}")
        if not torch.isfinite(rot).all():
            raise ValueError("joint_rotvecs contains NaN or inf")
        if root_translation is None:
            trans = torch.zeros(rot.shape[0], 3)
        else:
            trans = torch.as_tensor(np.asarray(root_translation, dtype=np.float32)).reshape(-1, 3)
            if trans.shape[0] != rot.shape[0]:
                raise ValueError(
                    f"root_translation has {trans.shape[0]} frames but joint_rotvecs has {rot.shape[0]}"
                )
        parts = [self._forward(rot[i : i + chunk], trans[i : i + chunk]) for i in range(0, rot.shape[0], chunk)]
        return PosedBody(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("vertices", "joints", "vtransf")))


# ------------------------------------------------------------------------------ fitting to a cloud
#: skeleton joints whose body parts (``AnnyBody.vertex_joint``) make up the head and the hands: neck
#: and head (with the neck the replaced head joins the torso below the chin), left/right wrist
#: (palm), left/right hand (fingers)
HEAD_HAND_JOINTS: tuple[int, ...] = (12, 15, 20, 21, 22, 23)


@dataclass
class BodyFit:
    """What :func:`fit_body_to_cloud` returns (numpy, metres).

    joint_rotvecs: (24, 3) axis-angle (anny ``local-ref``); root_translation: (3,);
    phenotype: the fitted phenotype (each in [0, 1]); vertices: (V, 3) the fitted posed body;
    faces: (F, 3) int64; joints: (24, 3) its skeleton joints; part_vertices: (V,) bool, the
    head and hand vertices (``HEAD_HAND_JOINTS``).
    joint_error_cm: mean distance of the fitted joints to the target joints;
    part_error_cm_initial / part_error_cm: PocoLoco Chamfer (S2M + M2S, cm) between the body's
    head/hand vertices and the cloud points nearest to them, after the joint stage (pose from
    the joints only) and after the surface stage; losses: the loss per step of both stages.
    """

    joint_rotvecs: np.ndarray
    root_translation: np.ndarray
    phenotype: dict[str, float]
    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    part_vertices: np.ndarray
    joint_error_cm: float
    part_error_cm_initial: float
    part_error_cm: float
    losses: list[float]


def _pose_matrices(body: AnnyBody, rot: torch.Tensor) -> torch.Tensor:
    """(T, J, 3) rotvecs -> (T, B, 4, 4) anny pose parameters (other bones identity), differentiable."""
    pose = torch.eye(4, dtype=rot.dtype).expand(rot.shape[0], body.num_bones, 4, 4).clone()
    pose[:, body.bone_of_joint, :3, :3] = _rotvec_to_matrix(rot)
    return pose


def _part_chamfer(body_pts: torch.Tensor, cloud_pts: torch.Tensor) -> torch.Tensor:
    """Unsquared Chamfer (metres): mean over body points of the distance to the nearest cloud
    point + the same from the cloud side. (P, 3), (Q, 3) -> scalar."""
    d = torch.cdist(body_pts, cloud_pts)  # (P, Q)
    return d.min(1).values.mean() + d.min(0).values.mean()


def fit_body_to_cloud(
    points: np.ndarray,
    joints: np.ndarray,
    *,
    joint_steps: int = 150,
    surface_steps: int = 150,
    lr: float = 0.02,
    fit_shape: bool = True,
    parts: tuple[int, ...] = HEAD_HAND_JOINTS,
    margin: float = 0.06,
    max_part_points: int = 2000,
    seed: int = 0,
    progress=None,
) -> BodyFit:
    """Fit the anny body to a clothed point cloud posed by ``joints`` (PocoLoco appendix A.2,
    which fits SMPL to a generated cloud to take its head and hands).

    Parameters theta (24 joint rotations, axis-angle), a root translation t and, with
    ``fit_shape``, the phenotype beta (6 values in [0, 1], as sigmoid of free logits).

    1. Joint stage (``joint_steps`` Adam steps from the zero pose at the target root):
       ``L_J = mean_j |J_j(theta, beta) + t - J*_j|^2 + 1e-4 |theta|^2`` (inverse kinematics
       to the target joints J* (24, 3); the small prior picks the least-rotated solution).
    2. Surface stage (``surface_steps`` steps): ``L = 10 L_J + CD(B_parts, X_parts)``, the
       unsquared Chamfer between the body's head/hand vertices B_parts (those of ``parts``,
       subsampled to ``max_part_points``) and the cloud points X_parts whose nearest body
       vertex is one of them and lies within ``margin`` m (re-selected every 25 steps). Loose
       clothing elsewhere does not pull the body: only the head and hands, where the clothed
       cloud is skin, and the joints constrain it.

    points: (N, 3) metres; joints: (24, 3) metres, the pose the cloud was generated for.
    progress: optional callable(done, total) after each step. Returns :class:`BodyFit`.
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float32)
    target = np.asarray(joints, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"points must have shape (N, 3) with N >= 1, got {pts.shape}")
    if target.shape != (NUM_JOINTS, 3):
        raise ValueError(f"joints must have shape ({NUM_JOINTS}, 3), got {target.shape}")
    if not (np.isfinite(pts).all() and np.isfinite(target).all()):
        raise ValueError("points or joints contain NaN or inf")
    if joint_steps < 0 or surface_steps < 0:
        raise ValueError("joint_steps and surface_steps must be >= 0")
    body = AnnyBody()
    part_vertices = np.isin(body.vertex_joint, list(parts))
    part_idx = np.flatnonzero(part_vertices)
    gen = np.random.default_rng(seed)
    if len(part_idx) > max_part_points:
        part_sub = torch.as_tensor(np.sort(gen.choice(part_idx, max_part_points, replace=False)))
    else:
        part_sub = torch.as_tensor(part_idx)
    torch.manual_seed(seed)
    rot = (1e-3 * torch.randn(1, NUM_JOINTS, 3)).requires_grad_(True)
    trans = torch.as_tensor(target[0]).clone()[None].requires_grad_(True)
    logits = torch.zeros(len(PHENOTYPE_KEYS), requires_grad=fit_shape)
    jt = torch.as_tensor(target)[None]
    cloud = torch.as_tensor(pts)

    def forward():
        beta = torch.sigmoid(logits)
        out = body.model(pose_parameters=_pose_matrices(body, rot),
                         phenotype_kwargs={k: beta[i : i + 1] for i, k in enumerate(PHENOTYPE_KEYS)})  # fmt: skip
        verts = out["vertices"][0] + trans[0]
        jts = out["bone_poses"][:, body.bone_of_joint, :3, 3] + trans
        return verts, jts

    def joint_loss(jts):
        return (jts - jt).square().sum(-1).mean() + 1e-4 * rot.square().sum(-1).mean()

    def part_cloud(verts: np.ndarray) -> np.ndarray:
        d, i = cKDTree(verts).query(pts)
        return pts[part_vertices[i] & (d < margin)]

    params = [rot, trans] + ([logits] if fit_shape else [])
    losses: list[float] = []
    total = joint_steps + surface_steps
    opt = torch.optim.Adam(params, lr=lr)
    for step in range(joint_steps):
        opt.zero_grad()
        _, jts = forward()
        loss = joint_loss(jts)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        if progress is not None:
            progress(step + 1, total)

    with torch.no_grad():
        verts, _ = forward()
    sel = part_cloud(verts.numpy())
    initial = float(_part_chamfer(verts[part_sub], torch.as_tensor(sel))) * 100 if len(sel) else float("nan")
    opt = torch.optim.Adam(params, lr=lr / 2)
    target_pts = torch.as_tensor(sel)
    for step in range(surface_steps):
        if step and step % 25 == 0:
            target_pts = torch.as_tensor(part_cloud(verts.detach().numpy()))
        opt.zero_grad()
        verts, jts = forward()
        loss = 10.0 * joint_loss(jts)
        if len(target_pts):
            loss = loss + _part_chamfer(verts[part_sub], target_pts)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        if progress is not None:
            progress(joint_steps + step + 1, total)

    with torch.no_grad():
        verts, jts = forward()
    verts_np = verts.numpy().astype(np.float32)
    sel = part_cloud(verts_np)
    final = float(_part_chamfer(verts[part_sub], torch.as_tensor(sel))) * 100 if len(sel) else float("nan")
    beta = torch.sigmoid(logits).detach().numpy()
    return BodyFit(
        joint_rotvecs=rot.detach().numpy()[0].astype(np.float32),
        root_translation=trans.detach().numpy()[0].astype(np.float32),
        phenotype={k: float(beta[i]) for i, k in enumerate(PHENOTYPE_KEYS)},
        vertices=verts_np,
        faces=body.faces,
        joints=jts.numpy()[0].astype(np.float32),
        part_vertices=part_vertices,
        joint_error_cm=float(np.linalg.norm(jts.numpy()[0] - target, axis=1).mean() * 100),
        part_error_cm_initial=initial,
        part_error_cm=final,
        losses=losses,
    )
