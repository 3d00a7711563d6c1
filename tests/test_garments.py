"""Garment templates: mesh sanity, no initial penetration, pins follow the body."""

import numpy as np
import pytest

from pocoloco.body.anny_body import AnnyBody, PosedBody
from pocoloco.data.cloth_sim import mesh_edges, signed_distance
from pocoloco.data.garments import GARMENT_KINDS, make_garment, pin_positions


@pytest.fixture(scope="module")
def body():
    return AnnyBody()


@pytest.fixture(scope="module")
def garments(body):
    return {k: make_garment(k, body, resolution=0.5) for k in GARMENT_KINDS}


@pytest.mark.parametrize("kind", GARMENT_KINDS)
def test_garment_mesh_is_an_open_manifold_tube(garments, kind):
    g = garments[kind]
    rows, cols = g.grid_shape
    assert g.kind == kind
    assert g.rest_vertices.shape == (rows * cols, 3) and g.rest_vertices.dtype == np.float32
    assert g.faces.shape == (2 * (rows - 1) * cols, 3) and g.faces.dtype == np.int64
    assert g.attach_vertex.shape == (rows * cols,) and g.attach_offset.shape == (rows * cols, 3)
    # every edge is shared by at most 2 triangles; exactly 2 rings are boundary
    e = np.sort(np.concatenate([g.faces[:, [0, 1]], g.faces[:, [1, 2]], g.faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert counts.max() == 2
    assert (counts == 1).sum() == 2 * cols
    # no degenerate triangles, plausible edge lengths (cm scale)
    v = g.rest_vertices
    f = g.faces
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert area.min() > 1e-6
    edges = mesh_edges(g.faces)
    length = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    assert 0.003 < length.min() and length.max() < 0.15


@pytest.mark.parametrize("kind", GARMENT_KINDS)
def test_garment_starts_outside_the_body(body, garments, kind):
    sd = signed_distance(garments[kind].rest_vertices, body.template, body.faces)
    assert sd.min() > 0.002  # every vertex outside the skin, with a few mm clearance


def test_resolution_scales_vertex_count(body):
    full = make_garment("skirt", body)
    assert 2000 <= full.rest_vertices.shape[0] <= 3000
    assert make_garment("skirt", body, resolution=0.5).rest_vertices.shape[0] < full.rest_vertices.shape[0] / 3


def test_skirt_and_shirt_extents(body, garments):
    j = body.template_joints
    skirt, shirt = garments["skirt"].rest_vertices, garments["long_shirt"].rest_vertices
    assert skirt[:, 2].min() < j[4, 2] < skirt[:, 2].max() < j[9, 2]  # waist above, hem below the knee
    assert shirt[:, 2].max() > j[9, 2] and j[4, 2] < shirt[:, 2].min() < j[1, 2]  # shoulders to mid-thigh


def test_pins_follow_the_body(body, garments):
    g = garments["skirt"]
    assert g.pinned.sum() == g.grid_shape[1]  # the waistband ring
    assert (g.attach_vertex[~g.pinned] == -1).all()
    rot = np.zeros((2, 24, 3), np.float32)
    rot[1, 0, 2] = 0.7  # turn
    rot[1, 1, 0] = -0.6  # left hip flexion
    posed = body.pose(rot, np.array([[0, 0, 0], [0.1, 0.0, 0.05]], np.float32))
    pins = pin_positions(g, posed)
    # the template body with identity transforms: pins sit exactly at the rest vertices
    eye = np.tile(np.eye(3, dtype=np.float32), (1, len(body.template), 1, 1))
    rest = PosedBody(body.template[None], body.template_joints[None], eye)
    np.testing.assert_allclose(pin_positions(g, rest)[0], g.rest_vertices[g.pinned], atol=1e-6)
    # posed: slow reference, one vertex at a time
    idx = np.flatnonzero(g.pinned)
    for k in range(0, len(idx), 7):
        a = g.attach_vertex[idx[k]]
        ref = posed.vertices[1, a] + posed.vtransf[1, a] @ g.attach_offset[idx[k]]
        np.testing.assert_allclose(pins[1, k], ref, atol=1e-5)
    # the waistband stays close to the posed body surface
    sd = signed_distance(pins[1], posed.vertices[1], body.faces)
    assert np.abs(sd).max() < 0.03


def test_bad_kinds_are_rejected(body):
    with pytest.raises(ValueError, match="tight"):
        make_garment("tight", body)
    with pytest.raises(ValueError, match="unknown garment"):
        make_garment("poncho", body)
    with pytest.raises(ValueError, match="resolution"):
        make_garment("skirt", body, resolution=0.0)
    with pytest.raises(ValueError, match="parameters"):
        make_garment("skirt", body, sleeves=True)
