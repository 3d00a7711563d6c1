"""Dataset integrity: the card's frame records, ``check_frames`` (what train and eval run first),
``verify_dataset`` / ``pocoloco data verify`` and ``pocoloco data info``, on copies of the session's
tiny synthetic dataset with one frame truncated, corrupted, missing or extra."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pocoloco.cli import main
from pocoloco.data import format as fmt
from pocoloco.data.dataset import PointCloudDataset
from pocoloco.data.published import write_joints_txt, write_ply


@pytest.fixture(autouse=True)
def wide_console(monkeypatch):
    monkeypatch.setenv("COLUMNS", "500")  # rich wraps long paths at 80 columns otherwise


@pytest.fixture
def data(tiny_dataset, tmp_path):
    """A private copy of the tiny dataset (the tests damage it)."""
    return shutil.copytree(tiny_dataset, tmp_path / "data")


def _test_frame(root, k=1):
    """The k-th test frame file of the dataset."""
    return fmt.DatasetLayout(root).iter_frames("test")[k][2]


def _one_line_error(capsys, argv) -> tuple[str, str]:
    """Run ``pocoloco ARGV``: exit code 2 and exactly one stderr line; returns (that line, stdout)."""
    code = main(argv)
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    return err, captured.out


def _drop_records(root):
    card = json.loads((root / "card.json").read_text())
    del card["frame_files"]
    (root / "card.json").write_text(json.dumps(card))


# --------------------------------------------------------------------------- records and the clean case
def test_card_records_size_and_crc_of_every_frame(tiny_dataset, capsys):
    card = fmt.read_card(tiny_dataset)
    layout = fmt.DatasetLayout(tiny_dataset)
    frames = layout.iter_frames("train") + layout.iter_frames("test")
    assert sum(len(v) for v in card["frame_files"].values()) == len(frames) > 0
    for subject, seq, path in frames:
        split = path.parts[-4]
        rec = card["frame_files"][f"{subject}/{split}/{seq}"][path.name]
        assert rec == [path.stat().st_size, fmt.file_crc32(path)]
    report = fmt.verify_dataset(tiny_dataset)
    assert report.ok and report.frames == report.recorded == len(frames) and report.card_records
    assert main(["data", "verify", str(tiny_dataset)]) == 0
    assert f"{len(frames)} frame files OK ({len(frames)} by CRC-32)" in capsys.readouterr().out
    assert main(["data", "info", str(tiny_dataset)]) == 0
    out = capsys.readouterr().out
    assert f"complete, {len(frames)} frames recorded" in out and "pocoloco data verify" in out


def test_crc32_matches_zlib_on_the_whole_file(tmp_path):
    import zlib

    f = tmp_path / "x.bin"
    f.write_bytes(bytes(range(256)) * 9000)  # more than one 1 MiB block
    assert fmt.file_crc32(f) == f"{zlib.crc32(f.read_bytes()):08x}"


# --------------------------------------------------------------------------- damaged copies
def test_truncated_frame(data, capsys):
    bad = _test_frame(data)
    size = bad.stat().st_size
    bad.write_bytes(bad.read_bytes()[: size // 2])
    with pytest.raises(ValueError, match=rf"{bad}: {size // 2} bytes, card.json records {size} \(truncated\)"):
        fmt.check_frames(data)
    report = fmt.verify_dataset(data)
    assert [(p.kind, p.path) for p in report.problems] == [("size", bad)]
    assert main(["data", "info", str(data)]) == 0  # info describes, it does not fail
    out = capsys.readouterr().out
    assert "DAMAGED: 1 size" in out and "complete" not in out
    err, table = _one_line_error(capsys, ["data", "verify", str(data)])
    assert err.startswith("pocoloco: error: ") and "1 bad frame file (1 size)" in err and bad.name in err
    assert "bad frame files" in table and "size" in table and "truncated" in table


def test_corrupt_frame_of_the_same_size(data, capsys):
    bad = _test_frame(data)
    raw = bytearray(bad.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    bad.write_bytes(bytes(raw))
    fmt.check_frames(data)  # sizes and listings only: the cheap check cannot see it
    report = fmt.verify_dataset(data)
    assert [(p.kind, p.path) for p in report.problems] == [("checksum", bad)]
    err, _ = _one_line_error(capsys, ["data", "verify", str(data)])
    assert "1 checksum" in err and "(corrupt)" in err


def test_missing_frame(data, capsys):
    bad = _test_frame(data)
    bad.unlink()
    with pytest.raises(ValueError, match=rf"{bad}: missing \(card.json records it\)"):
        fmt.check_frames(data)
    assert [(p.kind, p.path) for p in fmt.verify_dataset(data).problems] == [("missing", bad)]
    assert "DAMAGED: 1 missing" in (main(["data", "info", str(data)]), capsys.readouterr().out)[1]
    err, _ = _one_line_error(capsys, ["data", "verify", str(data)])
    assert "1 missing" in err and str(bad) in err


def test_extra_frame(data, capsys):
    src = _test_frame(data)
    extra = src.with_name("000099.npz")
    shutil.copy(src, extra)
    with pytest.raises(ValueError, match=rf"{extra}: not recorded in card.json"):
        fmt.check_frames(data)
    assert [(p.kind, p.path) for p in fmt.verify_dataset(data).problems] == [("extra", extra)]
    err, _ = _one_line_error(capsys, ["data", "verify", str(data)])
    assert "1 extra" in err


def test_only_the_subjects_used_are_checked(data):
    bad = _test_frame(data)
    bad.unlink()
    subject = bad.parts[-5]
    other = next(s for s in fmt.read_card(data)["subjects"] if s != subject)
    fmt.check_frames(data, subjects=[other])
    with pytest.raises(ValueError, match="missing"):
        PointCloudDataset(data, "train", subjects=[subject])  # the test split counts too
    assert len(PointCloudDataset(data, "train", num_points=16, subjects=[other])) > 0


# --------------------------------------------------------------------------- eval and train refuse
def test_eval_refuses_a_missing_frame(data, tmp_path, capsys):
    """It used to score 7 of 8 test frames without a word."""
    bad = _test_frame(data)
    bad.unlink()
    out = tmp_path / "eval"
    err, _ = _one_line_error(capsys, ["eval", "--baselines-only", "--data", str(data), "--frames", "0", "--points", "32",
                                   "--out", str(out)])  # fmt: skip
    assert str(bad) in err and "missing" in err and "pocoloco data verify" in err
    assert not out.exists()


@pytest.mark.parametrize("command", ["export", "preview"])
def test_export_and_preview_refuse_a_damaged_split_writing_nothing(data, tmp_path, capsys, command):
    """They used to skip the missing frame with no word (and export left a partial folder)."""
    bad = _test_frame(data)
    bad.write_bytes(bad.read_bytes()[:200])  # truncated
    out = tmp_path / ("ply" if command == "export" else "preview.png")
    err, _ = _one_line_error(capsys, ["data", command, str(data), "--split", "test", "--out", str(out)])
    assert str(bad) in err and not out.exists()


@pytest.mark.parametrize("model", ["pocoloco", "pop", "closet"])
def test_train_refuses_a_truncated_frame(data, tmp_path, capsys, model):
    bad = _test_frame(data, 0)
    bad.write_bytes(bad.read_bytes()[:1000])
    run = tmp_path / "run"
    err, _ = _one_line_error(capsys, ["train", "--model", model, "--data", str(data), "--out", str(run),
                                   "--preset", "tiny", "--no-progress"])  # fmt: skip
    assert str(bad) in err and "truncated" in err
    assert not run.exists()


# --------------------------------------------------------------------------- datasets without records
def test_a_dataset_without_records_still_works_and_can_record_them(data, capsys):
    recorded = fmt.read_card(data)["frame_files"]
    _drop_records(data)
    report = fmt.check_frames(data)  # unverified, not corrupt
    assert report.ok and not report.card_records and report.recorded == 0
    assert len(PointCloudDataset(data, "test", num_points=16)) > 0
    assert main(["data", "info", str(data)]) == 0
    assert "not recorded" in capsys.readouterr().out
    assert main(["data", "verify", str(data)]) == 0
    assert "--record" in capsys.readouterr().out
    assert "frame_files" not in fmt.read_card(data)  # verify alone writes nothing
    assert main(["data", "verify", str(data), "--record"]) == 0
    assert fmt.read_card(data)["frame_files"] == recorded


def test_a_dataset_without_records_is_checked_against_sequence_json(data, capsys):
    _drop_records(data)
    frames = fmt.DatasetLayout(data).iter_frames("test")
    missing, truncated = frames[0][2], frames[1][2]
    missing.unlink()
    truncated.write_bytes(truncated.read_bytes()[:-10])
    report = fmt.scan_frames(data)
    assert [(p.kind, p.path) for p in report.problems] == [("missing", missing), ("unreadable", truncated)]
    assert "sequence.json lists it" in report.problems[0].detail
    with pytest.raises(ValueError, match="2 bad frame files"):
        fmt.check_frames(data)
    assert [p.kind for p in fmt.verify_dataset(data, record=True).problems] == ["missing", "unreadable"]
    assert "frame_files" not in fmt.read_card(data)  # nothing recorded over damage
    err, _ = _one_line_error(capsys, ["data", "verify", str(data), "--record"])
    assert "1 missing, 1 unreadable" in err


# --------------------------------------------------------------------------- refresh_card
def test_refresh_keeps_records_of_unchanged_sizes_and_rehashes_on_request(data):
    bad = _test_frame(data)
    raw = bytearray(bad.read_bytes())
    raw[len(raw) // 2] ^= 0xFF  # same size, other bytes
    bad.write_bytes(bytes(raw))
    fmt.refresh_card(data)  # a same-size record is kept, not re-read: the damage stays visible
    assert [p.kind for p in fmt.verify_dataset(data).problems] == ["checksum"]
    key = f"{bad.parts[-5]}/test/{bad.parts[-3]}"
    card = fmt.refresh_card(data, rehash=[key])  # a sequence rewritten on purpose (import does this)
    assert card["frame_files"][key][bad.name] == [bad.stat().st_size, fmt.file_crc32(bad)]


# --------------------------------------------------------------------------- pocoloco data import
def _loose_folder(folder, ids=(3, 4, 7, 8), n=50, bad=None):
    """A LOOSE-style folder (one PLY per frame) and its joints file; ``bad``: frame id whose PLY is cut short."""
    rng = np.random.default_rng(len(ids))
    folder.mkdir(parents=True)
    for i in ids:
        nrm = rng.normal(size=(n, 3))
        write_ply(folder / f"scan_{i:04d}.ply", rng.normal(size=(n, 3)) * 0.3, nrm / np.linalg.norm(nrm, axis=1, keepdims=True))
    if bad is not None:
        path = folder / f"scan_{bad:04d}.ply"
        path.write_bytes(path.read_bytes()[:-40])
    joints_txt = folder.parent / f"{folder.name}.txt"
    write_joints_txt(joints_txt, np.array(ids), rng.normal(size=(len(ids), 24, 3)))
    return folder, joints_txt


def _snapshot(root):
    return {q.relative_to(root).as_posix(): (q.read_bytes() if q.is_file() else None) for q in sorted(root.rglob("*"))}


def test_cli_import_failing_midway_leaves_nothing(data, tmp_path, capsys):
    ply_dir, joints_txt = _loose_folder(tmp_path / "raw" / "walk", bad=7)
    args = ["data", "import", str(ply_dir), "--joints", str(joints_txt), "--subject", "scan"]
    before = _snapshot(tmp_path)
    err, _ = _one_line_error(capsys, [*args, "--out", str(tmp_path / "new" / "ds")])
    assert "scan_0007.ply: truncated PLY" in err
    err, _ = _one_line_error(capsys, [*args, "--out", str(data)])  # into a dataset: card and frames untouched
    assert "scan_0007.ply: truncated PLY" in err
    assert _snapshot(tmp_path) == before


def test_cli_import_into_a_dataset_records_the_new_frames(data, tmp_path, capsys):
    ply_dir, joints_txt = _loose_folder(tmp_path / "raw" / "walk")
    before = fmt.read_card(data)["frame_files"]
    assert main(["data", "import", str(ply_dir), "--joints", str(joints_txt), "--subject", "scan", "--split", "test",
                 "--out", str(data)]) == 0  # fmt: skip
    assert "imported 4 frames into" in capsys.readouterr().out
    card = fmt.read_card(data)
    assert card["frame_files"] == {**before, "scan/test/walk": card["frame_files"]["scan/test/walk"]}
    assert len(card["frame_files"]["scan/test/walk"]) == 4 and card["counts"]["scan"]["test"]["frames"] == 4
    assert fmt.verify_dataset(data).ok and not list(data.glob(".import-*"))
