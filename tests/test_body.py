import numpy as np
import pytest

from pocoloco.body import JOINT_NAMES, JOINT_PARENTS, NUM_JOINTS, AnnyBody, joint_index
from pocoloco.body.anny_body import _rotvec_to_matrix
from pocoloco.body.skeleton import MIRROR_PAIRS


@pytest.fixture(scope="module")
def body():
    return AnnyBody({"gender": 0.3, "height": 0.6})


def test_skeleton_topology():
    assert NUM_JOINTS == 24 == len(JOINT_PARENTS)
    assert JOINT_PARENTS[0] == -1
    assert all(0 <= p < i for i, p in enumerate(JOINT_PARENTS) if i > 0)
    assert len(MIRROR_PAIRS) == 9
    with pytest.raises(ValueError, match="unknown joint"):
        joint_index("tail")


def test_template_is_a_plausible_human(body):
    v, j = body.template, body.template_joints
    assert v.shape == (body.num_vertices, 3) and body.faces.max() < len(v)
    height = v[:, 2].max() - v[:, 2].min()
    assert 1.4 < height < 2.1, height  # metres, Z up
    assert np.allclose(j[0], 0, atol=1e-6)  # bind-pose pelvis at the origin
    assert np.abs(body.zero_pose.joints[0] - j).max() < 0.06  # zero pose ~ bind pose  # pelvis near the origin
    assert j[joint_index("head"), 2] > j[joint_index("neck"), 2] > j[0, 2] > j[joint_index("left_knee"), 2]
    assert j[joint_index("left_hip"), 0] > 0 > j[joint_index("right_hip"), 0]  # +X is the body's left
    assert j[joint_index("left_foot"), 1] < j[joint_index("left_ankle"), 1]  # toes point to -Y
    # every skeleton joint has vertices assigned to its body part (except tiny collar bones)
    counts = np.bincount(body.vertex_joint, minlength=NUM_JOINTS)
    assert (counts > 0).sum() >= 22


def _rotz(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)


def test_global_rotation_and_translation_are_rigid(body):
    """Turning the pelvis by theta about Z and translating must move every vertex
    and joint rigidly, and every skinning transform must equal that rotation."""
    theta, trans = 0.7, np.array([0.3, -0.2, 0.1], np.float32)
    rot = np.zeros((1, NUM_JOINTS, 3), np.float32)
    rot[0, 0, 2] = theta
    posed = body.pose(rot, trans[None])
    r = _rotz(theta)
    zero = body.zero_pose
    root = zero.joints[0, 0]
    expect_v = (zero.vertices[0] - root) @ r.T + root + trans
    expect_j = (zero.joints[0] - root) @ r.T + root + trans
    assert np.abs(posed.vertices[0] - expect_v).max() < 2e-4
    assert np.abs(posed.joints[0] - expect_j).max() < 2e-4
    assert np.abs(posed.vtransf[0] - r @ zero.vtransf[0]).max() < 1e-4


def test_vtransf_matches_finite_difference_of_skinning(body):
    """vtransf maps rest-pose offsets to posed offsets: for two nearby vertices
    skinned to the same bones, posed difference ~= vtransf @ rest difference."""
    rot = np.zeros((1, NUM_JOINTS, 3), np.float32)
    rot[0, joint_index("left_hip")] = [-0.9, 0.2, 0.1]
    rot[0, joint_index("left_knee")] = [1.1, 0.0, 0.0]
    rot[0, joint_index("spine2")] = [0.2, 0.1, 0.3]
    posed = body.pose(rot)
    faces = body.faces
    # edges (a, b) whose endpoints have the same skinning weights -> exactly linear
    w = body.model.vertex_bone_weights.numpy()
    idx = body.model.vertex_bone_indices.numpy()
    a, b = faces[:, 0], faces[:, 1]
    same = (np.abs(w[a] - w[b]).max(1) < 1e-6) & (idx[a] == idx[b]).all(1)
    a, b = a[same][:500], b[same][:500]
    assert len(a) > 50
    lhs = posed.vertices[0, a] - posed.vertices[0, b]
    rhs = np.einsum("nij,nj->ni", posed.vtransf[0, a], body.template[a] - body.template[b])
    assert np.abs(lhs - rhs).max() < 1e-4


def test_hip_flexion_moves_the_leg_forward(body):
    rot = np.zeros((1, NUM_JOINTS, 3), np.float32)
    rot[0, joint_index("left_hip"), 0] = -0.8
    j = body.pose(rot).joints[0]
    knee, hip = joint_index("left_knee"), joint_index("left_hip")
    assert j[knee, 1] < body.template_joints[knee, 1] - 0.15  # forward is -Y
    zero = body.zero_pose.joints[0]
    bone = np.linalg.norm(j[knee] - j[hip])
    assert abs(bone - np.linalg.norm(zero[knee] - zero[hip])) < 1e-4


def test_batched_pose_equals_single_poses(body):
    rng = np.random.default_rng(0)
    rot = rng.normal(scale=0.2, size=(5, NUM_JOINTS, 3)).astype(np.float32)
    batched = body.pose(rot, chunk=2)
    single = body.pose(rot[3])
    assert np.allclose(batched.vertices[3], single.vertices[0], atol=1e-5)
    assert batched.vtransf.shape == (5, body.num_vertices, 3, 3)


def test_rotvec_to_matrix_matches_scipy():
    import torch
    from scipy.spatial.transform import Rotation

    rv = np.random.default_rng(1).normal(size=(20, 3))
    rv[0] = 0
    ours = _rotvec_to_matrix(torch.tensor(rv)).numpy()
    assert np.allclose(ours, Rotation.from_rotvec(rv).as_matrix(), atol=1e-9)


def test_bad_input_is_rejected(body):
    with pytest.raises(ValueError, match=r"shape \(T, 24, 3\)"):
        body.pose(np.zeros((2, 23, 3)))
    bad = np.zeros((1, NUM_JOINTS, 3))
    bad[0, 3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        body.pose(bad)
    with pytest.raises(ValueError, match="frames"):
        body.pose(np.zeros((2, NUM_JOINTS, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="unknown phenotype"):
        AnnyBody({"shoe_size": 0.5})
    with pytest.raises(ValueError, match="outside"):
        AnnyBody({"age": 1.5})
    assert JOINT_NAMES[0] == "pelvis"


def test_skeleton_rig_rebuilds_anny_exactly(body):
    """Skinning from the 24 joint transforms alone (what a --bodies pack stores) against anny's
    own forward pass over all 104 bones: the same vertices and vtransf."""
    rot = np.random.default_rng(3).normal(0, 0.5, (4, NUM_JOINTS, 3)).astype(np.float32)
    rig = body.skeleton_rig()
    verts, vtransf = rig.pose(body.joint_transforms(rot))
    ref = body.pose(rot)
    assert verts.shape == ref.vertices.shape and vtransf.shape == ref.vtransf.shape
    assert np.abs(verts - (ref.vertices - ref.joints[:, :1])).max() < 1e-5
    assert np.abs(vtransf - ref.vtransf).max() < 1e-5
    slow_v, slow_t = rig.pose_reference(body.joint_transforms(rot))  # bone by bone, float64
    assert np.abs(verts - slow_v).max() < 2e-6 and np.abs(vtransf - slow_t).max() < 2e-6
    assert np.abs(rig.rest_vertices - rig.rest_vertices[0] + body.template[0] - body.template).max() < 1e-6
    with pytest.raises(ValueError, match="joint_transforms must have shape"):
        rig.pose(np.zeros((1, 23, 3, 4)))
