"""Frame file storage (``format.FRAME_STORAGES``): the float32 default keeps its bytes, compact
frames read back within ``COMPACT_MAX_ERROR`` as float32, and a dataset of compact frames works
with every reader (dataset, verify, info, export)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import time
import types
import zipfile

import numpy as np
import pytest
import torch

from pocoloco.data import frame as frame_module
from pocoloco.cli import main
from pocoloco.data import format as fmt
from pocoloco.synth.config import synth_preset
from pocoloco.data.dataset import PointCloudDataset
from pocoloco.data.published import export_frame, read_ply, read_pop_npz
from pocoloco.utils import save_npz_atomic

#: sha256 of fixed_frame() written by write_frame with the zip clock frozen, computed with the code
#: before compact storage existed (numpy 2.4, Python 3.11; a numpy that writes npy headers
#: differently changes it, and so does any change to the float32 files).
FLOAT32_SHA256 = "d538067f467cede5e85b2489d9192a0a071caa4f1653f173fb97f0bdaa53f2f2"


def fixed_frame() -> fmt.Frame:
    n, v = 4, 3
    normals = np.zeros((n, 3), np.float32)
    normals[:, 2] = 1
    return fmt.Frame(points=np.arange(3 * n, dtype=np.float32).reshape(n, 3) / 10, normals=normals,
                     joints=np.arange(72, dtype=np.float32).reshape(24, 3) / 100, frame_index=7,
                     labels=np.array([0, 1, 1, 0], np.uint8), parts=np.array([-1, 0, 3, 23], np.int8),
                     body_vertices=np.arange(3 * v, dtype=np.float32).reshape(v, 3) / 4,
                     vtransf=np.tile(np.eye(3, dtype=np.float32), (v, 1, 1)),
                     garment_vertices=np.ones((2, 3), np.float32))  # fmt: skip


def captured_frame(rng: np.random.Generator, n: int = 2000, v: int = 500, vg: int | None = 300) -> fmt.Frame:
    """A frame shaped like a capture: a ~1.9 m tall body whose root is metres from the origin."""
    root = np.array([4.7, -3.2, 0.95])

    def body(k):  # (k, 3) around the root, z from the feet to above the head
        x = rng.uniform(-1, 1, (k, 3)) * [0.45, 0.3, 0.95]
        return (root + x).astype(np.float32)

    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rot, _ = np.linalg.qr(rng.normal(size=(v, 3, 3)))  # (V, 3, 3) orthonormal: entries in [-1, 1]
    return fmt.Frame(points=body(n), normals=normals.astype(np.float32),
                     joints=body(24), frame_index=12, labels=rng.integers(0, 2, n).astype(np.uint8),
                     parts=rng.integers(-1, 24, n).astype(np.int8), body_vertices=body(v),
                     vtransf=rot.astype(np.float32), garment_vertices=None if vg is None else body(vg))  # fmt: skip


@pytest.fixture
def frozen_zip_clock(monkeypatch):
    """npz members carry the time they were written: freeze it so files can be compared byte for byte."""
    fixed = time.struct_time((2024, 1, 2, 3, 4, 6, 1, 2, 0))
    monkeypatch.setattr(zipfile, "time", types.SimpleNamespace(time=lambda: 0.0, localtime=lambda t: fixed))


def test_float32_storage_writes_the_same_bytes_as_before(tmp_path, frozen_zip_clock):
    default, explicit, direct = tmp_path / "a.npz", tmp_path / "b.npz", tmp_path / "c.npz"
    fmt.write_frame(default, fixed_frame())
    fmt.write_frame(explicit, fixed_frame(), storage="float32")
    save_npz_atomic(direct, **frame_module._validate_frame_arrays("x", fixed_frame().to_arrays()))  # the unchanged path
    assert hashlib.sha256(default.read_bytes()).hexdigest() == FLOAT32_SHA256
    assert default.read_bytes() == explicit.read_bytes() == direct.read_bytes()
    assert fmt.frame_storage(default) == "float32"


@pytest.mark.parametrize("vg", [300, None])
def test_compact_round_trip_within_the_documented_error(tmp_path, vg):
    frame = captured_frame(np.random.default_rng(0), vg=vg)
    fmt.write_frame(tmp_path / "f32.npz", frame)
    fmt.write_frame(tmp_path / "compact.npz", frame, storage="compact")
    assert fmt.frame_storage(tmp_path / "compact.npz") == "compact"
    assert (tmp_path / "compact.npz").stat().st_size < 0.6 * (tmp_path / "f32.npz").stat().st_size
    ref, back = fmt.read_frame(tmp_path / "f32.npz"), fmt.read_frame(tmp_path / "compact.npz")
    assert back.frame_index == ref.frame_index == 12
    for key in fmt.FRAME_KEYS:
        if key == "frame_index":
            continue
        a, b = getattr(ref, key), getattr(back, key)
        assert (a is None) == (b is None), key
        if a is None:
            continue
        assert b.dtype == a.dtype == fmt.FRAME_KEYS[key] and b.shape == a.shape, key
        err = np.abs(a.astype(np.float64) - b).max()
        assert err <= fmt.COMPACT_MAX_ERROR.get(key, 0.0), (key, err)
    # positions use their int16 range: ~1.5e-5 m here, far inside the 1e-4 bound
    assert np.abs(ref.points.astype(np.float64) - back.points).max() < 2e-5
    with np.load(tmp_path / "compact.npz") as z:  # a reader unaware of compact finds no 'points' to misread
        assert "points" not in z.files and z["points_q16"].dtype == np.int16 and z["normals"].dtype == np.float16


def test_compact_reads_subsets_and_absent_optional_keys(tmp_path):
    frame = captured_frame(np.random.default_rng(1))
    p = tmp_path / "f.npz"
    fmt.write_frame(p, frame, storage="compact")
    full = fmt.read_frame(p)
    sub = fmt.read_frame(p, ["points", "labels"])
    assert sub.normals is None and sub.body_vertices is None and sub.joints is None
    np.testing.assert_array_equal(sub.points, full.points)
    np.testing.assert_array_equal(fmt.read_frame(p, "garment_vertices").garment_vertices, full.garment_vertices)
    minimal = fmt.Frame(points=frame.points, normals=frame.normals, joints=frame.joints, frame_index=0)
    fmt.write_frame(p, minimal, storage="compact")
    sub = fmt.read_frame(p, ["points", "labels", "body_vertices"], allow_missing=True)
    assert sub.labels is None and sub.body_vertices is None and sub.points.dtype == np.float32
    with pytest.raises(ValueError, match="missing key 'body_vertices'"):
        fmt.read_frame(p, ["body_vertices"])


def test_compact_keeps_float32_where_it_cannot_meet_the_bound(tmp_path):
    frame = captured_frame(np.random.default_rng(2))
    frame.points[0] += 30.0  # a 30 m extent: int16 steps of 0.46 mm
    frame.vtransf[0, 0, 0] = 1.5  # beyond +-1: float16 would round by up to 2^-11 * 1.5
    p = tmp_path / "f.npz"
    fmt.write_frame(p, frame, storage="compact")
    with np.load(p) as z:
        assert z["points"].dtype == np.float32 and z["vtransf"].dtype == np.float32 and "body_vertices_q16" in z.files
    back = fmt.read_frame(p)
    np.testing.assert_array_equal(back.points, frame.points)
    np.testing.assert_array_equal(back.vtransf, frame.vtransf)


@pytest.mark.parametrize("keep", [0.3, 0.9, 0.999])
def test_truncated_compact_frame_is_a_one_line_error(tmp_path, keep):
    p = tmp_path / "f.npz"
    fmt.write_frame(p, captured_frame(np.random.default_rng(3)), storage="compact")
    p.write_bytes(p.read_bytes()[: int(p.stat().st_size * keep)])
    with pytest.raises(ValueError, match="corrupt or truncated npz") as info:
        fmt.read_frame(p)
    assert str(info.value).startswith(f"{p}: ") and "\n" not in str(info.value)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda a: a.__setitem__("frame_storage", np.asarray("bfloat16")), "unknown frame storage bfloat16"),
        (lambda a: a.pop("points_q16_scale"), "missing key 'points_q16_scale'"),
        (lambda a: a.__setitem__("points_q16", a["points_q16"].astype(np.int32)), "'points_q16' must be int16"),
        (lambda a: a["body_vertices_q16_scale"].__setitem__((1, 0), np.nan), "'body_vertices_q16_scale' must be"),
    ],
)
def test_malformed_compact_frame_is_a_one_line_error(tmp_path, change, message):
    arrays = fmt.encode_compact(frame_module._validate_frame_arrays("x", captured_frame(np.random.default_rng(4)).to_arrays()))
    change(arrays)
    p = tmp_path / "bad.npz"
    np.savez_compressed(p, **arrays)
    with pytest.raises(ValueError, match=message) as info:
        fmt.read_frame(p)
    assert str(info.value).startswith(f"{p}: ") and "\n" not in str(info.value)


def test_write_frame_refuses_an_unknown_storage(tmp_path):
    with pytest.raises(ValueError, match="write_frame: storage must be one of"):
        fmt.write_frame(tmp_path / "f.npz", fixed_frame(), storage="float16")
    assert not (tmp_path / "f.npz").exists()


def test_resume_checks_frame_storage_and_older_cards_still_resume(tmp_path):
    from pocoloco.synth.pipeline import prepare_output

    config = synth_preset("tiny")
    prepare_output(config, tmp_path / "d")
    card = json.loads((tmp_path / "d" / "card.json").read_text())
    assert card["generation_config"]["frame_storage"] == "float32"
    del card["generation_config"]["frame_storage"]  # a run started before the setting existed wrote float32
    (tmp_path / "d" / "card.json").write_text(json.dumps(card))
    prepare_output(config, tmp_path / "d")
    with pytest.raises(ValueError, match=r"differs in: frame_storage\)"):
        prepare_output(dataclasses.replace(config, frame_storage="compact"), tmp_path / "d")
    with pytest.raises(ValueError, match="frame_storage must be one of"):
        prepare_output(dataclasses.replace(config, frame_storage="half"), tmp_path / "e")


# --------------------------------------------------------------------------- a compact dataset
@pytest.fixture(scope="module")
def compact_dataset(tmp_path_factory):
    """The tiny preset's skirt subject generated with compact frames."""
    from pocoloco.synth.pipeline import synthesize

    tiny = synth_preset("tiny")
    config = dataclasses.replace(tiny, subjects=tiny.subjects[:1], frame_storage="compact")
    out = tmp_path_factory.mktemp("compact") / "data"
    synthesize(config, out)
    return out


def test_compact_dataset_is_recorded_loads_and_verifies(compact_dataset, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "500")
    card = fmt.read_card(compact_dataset)
    assert card["generation_config"]["frame_storage"] == "compact"
    layout = fmt.DatasetLayout(compact_dataset)
    paths = [p for split in fmt.SPLITS for _, _, p in layout.iter_frames(split)]
    assert paths and all(fmt.frame_storage(p) == "compact" for p in paths)
    ds = PointCloudDataset(compact_dataset, "train", num_points=100, with_normals=True)
    item = ds[0]
    assert item["points"].dtype == item["normals"].dtype == item["joints"].dtype == torch.float32
    assert main(["data", "verify", str(compact_dataset)]) == 0
    assert f"{len(paths)} frame files OK ({len(paths)} by CRC-32)" in capsys.readouterr().out
    assert main(["data", "info", str(compact_dataset)]) == 0
    assert "frame_storage=compact" in capsys.readouterr().out


def test_compact_frames_export_and_mix_with_float32_ones(compact_dataset, tmp_path):
    data = shutil.copytree(compact_dataset, tmp_path / "data")
    layout = fmt.DatasetLayout(data)
    subject, sequence, path = layout.iter_frames("test")[0]
    export_frame(path, tmp_path / "f.ply", "ply")
    export_frame(path, tmp_path / "f.npz", "npz")
    frame = fmt.read_frame(path)
    np.testing.assert_array_equal(read_ply(tmp_path / "f.ply").points, frame.points)
    np.testing.assert_array_equal(read_pop_npz(tmp_path / "f.npz")["vtransf"], frame.vtransf)
    fmt.write_frame(path, frame)  # one frame rewritten as float32: a mixed dataset
    fmt.refresh_card(data, rehash=[layout.sequence_key(subject, "test", sequence)])
    assert fmt.frame_storage(path) == "float32" and fmt.verify_dataset(data).ok
    test = PointCloudDataset(data, "test", num_points=None)
    assert all(test[i]["points"].dtype == torch.float32 for i in range(len(test)))
