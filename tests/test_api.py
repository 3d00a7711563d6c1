"""The public Python API: ``pocoloco.load``, ``pocoloco.Pose``, ``Method.sample`` (and README's quick start)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import pocoloco
from pocoloco.data.format import StoredMotion, write_motion
from pocoloco.data.poses import demo_pose_path
from pocoloco.methods import SamplerOptions, predict_clouds

README = Path(__file__).resolve().parent.parent / "README.md"


def quick_start_code() -> str:
    """The README's Python quick start: the first ```python block after the "Python" heading."""
    text = README.read_text()
    m = re.search(r"## Python.*?```python\n(.*?)```", text, flags=re.S)
    assert m, "README has no ## Python section with a ```python block"
    return m.group(1)


def test_readme_quick_start_runs(tmp_path, monkeypatch):
    code = quick_start_code()
    assert len(code.strip().splitlines()) <= 10  # "a ten-line quick start"
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(code, "README quick start", "exec"), scope)  # noqa: S102 - the README's own code
    clouds = scope["clouds"]
    assert clouds.points.shape == (3, 2048, 3) and np.isfinite(clouds.points).all()
    assert len(list(tmp_path.glob("*.ply"))) >= 1  # it writes what it says


def test_import_is_light_and_names_are_public():
    out = subprocess.run([sys.executable, "-c", "import sys, pocoloco; print('torch' in sys.modules)"],
                         capture_output=True, text=True, check=True)  # fmt: skip
    assert out.stdout.strip() == "False"
    for name in pocoloco.__all__:
        assert getattr(pocoloco, name) is not None and (name.startswith("__") or getattr(pocoloco, name).__doc__)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        pocoloco.nope  # noqa: B018


def test_load_names_and_errors(tmp_path):
    assert pocoloco.load("default:pop").kind == "pop"
    with pytest.raises(ValueError, match="no shipped model of that name"):
        pocoloco.load("default:nope")
    with pytest.raises(ValueError, match=str(tmp_path)):
        pocoloco.load(tmp_path)


def test_pose_from_every_source(tmp_path):
    demo = pocoloco.Pose.load("demo:skirt_a")
    assert demo.joints.shape == (24, 3) and demo.subject == "skirt_a" and not demo.has_body
    np.save(tmp_path / "j.npy", demo.joints)
    np.testing.assert_array_equal(pocoloco.Pose.load(tmp_path / "j.npy").joints, demo.joints)
    np.testing.assert_array_equal(pocoloco.Pose.from_joints(demo.joints.tolist()).joints, demo.joints)
    with np.load(demo_pose_path("skirt_a")) as z:
        rot, trans = z["joint_rotvecs"], z["root_translation"]
    path = tmp_path / "seq" / "motion.npz"
    path.parent.mkdir()
    write_motion(path, StoredMotion(np.stack([np.zeros_like(rot), rot]), np.stack([trans, trans])))
    moved = pocoloco.Pose.load(path, frame_id=1)
    from pocoloco.body import AnnyBody

    np.testing.assert_allclose(moved.joints, AnnyBody().pose(rot[None], trans[None]).joints[0], atol=1e-6)
    assert np.abs(moved.joints - demo.joints).max() < 0.1  # the demo's pose, on the mean body (not skirt_a's)
    assert moved.joint_rotvecs is not None
    with pytest.raises(ValueError, match="frame 2 out of range"):
        pocoloco.Pose.load(path, frame_id=2)
    with pytest.raises(ValueError, match=r"joints: expected \(24, 3\)|shape"):
        pocoloco.Pose.from_joints(np.zeros((23, 3)))
    with pytest.raises(ValueError, match="not a body"):
        pocoloco.Pose.from_joints(np.zeros((24, 3)))


def test_sample_is_predict_clouds_and_checks_its_arguments():
    model = pocoloco.load("default")
    pose = pocoloco.Pose.load("demo:skirt_a")
    got = model.sample(pose, num_points=256, seeds=[3, 4], steps=3)
    want = predict_clouds(model, model.load_pose("demo:skirt_a"), 256, [3, 4], model.outfit_id("skirt_a"),
                          SamplerOptions(steps=3))  # fmt: skip
    np.testing.assert_array_equal(got.points, want.points)
    np.testing.assert_allclose(model.sample("demo:skirt_a", 256, 3, steps=3).points[0], want.points[0], atol=1e-5)
    with pytest.raises(ValueError, match="outfit=NAME"):  # bare joints: which outfit?
        model.sample(pose.joints, 64, steps=2)
    assert model.sample(pose.joints, 64, outfit="dress_a", steps=2).points.shape == (1, 64, 3)
    with pytest.raises(ValueError, match="unknown sampler"):
        model.sample(pose, 64, sampler="nope")
    with pytest.raises(ValueError, match="num_points must be >= 1"):
        model.sample(pose, 0)


def test_body_methods_pose_the_body_from_a_spec_or_anny_parameters(tmp_path):
    pop = pocoloco.load("default:pop")
    pose = pocoloco.Pose.load("demo:skirt_a")
    from_pose = pop.sample(pose, 256)
    from_spec = pop.sample("demo:skirt_a", 256)
    np.testing.assert_array_equal(from_pose.points, from_spec.points)
    with np.load(demo_pose_path("skirt_a")) as z:
        rot, trans = z["joint_rotvecs"], z["root_translation"]
    path = tmp_path / "seq" / "motion.npz"
    path.parent.mkdir()
    write_motion(path, StoredMotion(rot[None], trans[None]))
    moved = pop.sample(pocoloco.Pose.load(path), 256, outfit="skirt_a")  # posed anew on skirt_a's body
    np.testing.assert_allclose(moved.points, from_spec.points, atol=1e-4)
    with pytest.raises(ValueError, match="deterministic"):
        pop.sample(pose, 64, seeds=[0, 1])
    with pytest.raises(ValueError, match="needs the posed body"):
        pop.sample(pocoloco.Pose.from_joints(pose.joints), 64)
