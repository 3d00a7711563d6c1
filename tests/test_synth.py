"""End-to-end tests of the synthetic capture pipeline and its CLI (tiny preset)."""

import dataclasses
import hashlib
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from pocoloco.synth.config import SYNTH_PRESETS, synth_preset
from pocoloco.data.format import DatasetLayout, read_card, read_frame
from pocoloco.synth.pipeline import list_jobs, prepare_output


def test_tiny_dataset_card_and_frames(tiny_dataset):
    card = read_card(tiny_dataset)
    config = synth_preset("tiny")
    assert card["status"] == "complete"
    assert set(card["subjects"]) == {s.name for s in config.subjects}
    layout = DatasetLayout(tiny_dataset)
    for split in ("train", "test"):
        frames = layout.iter_frames(split)
        expected = sum(card["counts"][s][split]["frames"] for s in card["subjects"])
        assert len(frames) == expected > 0
    assert card["loose_share"]["skirt"] > 0.10  # the skirt is seen by the cameras
    assert card["loose_share"]["tight"] == 0.0
    skirt = card["subjects"]["skirt"]
    assert skirt["penetration"] is not None and skirt["penetration"]["mean_mm"] < 5.0
    norm = card["normalisation"]
    assert len(norm["mean"]) == 3 and 0.05 < norm["std"] < 1.0
    f = read_frame(layout.iter_frames("train", subjects=["skirt"])[0][2])
    assert f.points.shape == (config.num_points, 3) and f.normals.shape == (config.num_points, 3)
    assert np.allclose(np.linalg.norm(f.normals, axis=1), 1.0, atol=1e-4)
    assert f.joints.shape == (24, 3) and f.garment_vertices is not None
    # points lie on the outer surface, near the body or the garment
    from scipy.spatial import cKDTree

    surf = np.concatenate([f.body_vertices, f.garment_vertices])
    d, _ = cKDTree(surf).query(f.points)
    assert np.median(d) < 0.01


def test_train_and_test_motions_differ(tiny_dataset):
    layout = DatasetLayout(tiny_dataset)
    a = np.load(layout.sequence_dir("skirt", "train", "train_0000") / "motion.npz")["joint_rotvecs"]
    b = np.load(layout.sequence_dir("skirt", "test", "test_0000") / "motion.npz")["joint_rotvecs"]
    assert not np.allclose(a, b)


def test_cli_info_and_preview(tiny_dataset, tmp_path):
    r = run_cli("data", "info", str(tiny_dataset))
    assert r.returncode == 0, r.stderr
    assert "skirt" in r.stdout and "loose %" in r.stdout and "normalisation" in r.stdout
    png = tmp_path / "p.png"
    r = run_cli("data", "preview", str(tiny_dataset), "--out", str(png), "--num", "2")
    assert r.returncode == 0, r.stderr
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB")).astype(float)
    assert img.std() > 10  # not blank
    one = tmp_path / "one.png"  # one subject, front views only: half as wide, half as tall
    r = run_cli("data", "preview", str(tiny_dataset), "--out", str(one), "--num", "2", "--subject", "tight", "--front-only")
    assert r.returncode == 0, r.stderr
    small = np.asarray(Image.open(one).convert("RGB"))
    assert small.shape[0] < img.shape[0] and small.shape[1] < img.shape[1]
    r = run_cli("data", "preview", str(tiny_dataset), "--subject", "nobody")
    assert r.returncode == 2 and "no subject 'nobody'" in r.stderr and "skirt, tight" in r.stderr, r.stderr


def test_cli_export_ply(tiny_dataset, tmp_path):
    r = run_cli("data", "export", str(tiny_dataset), "--out", str(tmp_path / "ply"), "--limit", "2")
    assert r.returncode == 0, r.stderr
    from pocoloco.data.published import read_ply

    plys = sorted((tmp_path / "ply").glob("*.ply"))
    assert len(plys) == 2
    cloud = read_ply(plys[0], require_normals=True)
    assert cloud.points.shape[1] == 3 and cloud.normals is not None


def test_cli_bad_input_gives_one_line_errors(tmp_path):
    r = run_cli("data", "synth", "--preset", "huge", "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "unknown preset 'huge'" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = run_cli("data", "info", str(tmp_path))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "file.txt").write_text("x")
    r = run_cli("data", "synth", "--preset", "tiny", "--out", str(tmp_path / "junk"))
    assert r.returncode == 2 and "not a pocoloco dataset" in r.stderr
    assert "Traceback" not in r.stderr


def test_existing_output_of_another_configuration_is_refused(tmp_path):
    config = synth_preset("tiny")
    prepare_output(config, tmp_path / "d")
    prepare_output(config, tmp_path / "d")  # same configuration: fine (resume)
    other = dataclasses.replace(config, seed=7, num_points=3000)
    with pytest.raises(ValueError, match="different configuration.*num_points, seed"):
        prepare_output(other, tmp_path / "d")
    # a split may grow (job i of a split is the same whatever the count), not shrink
    prepare_output(dataclasses.replace(config, train_sequences=3, heldout_sequences=2), tmp_path / "d")
    (tmp_path / "d" / "card.json").write_text((tmp_path / "d" / "card.json").read_text().replace(
        '"train_sequences": 1', '"train_sequences": 3'))  # fmt: skip
    with pytest.raises(ValueError, match="holds 3 train sequences per subject; a dataset can grow but not shrink"):
        prepare_output(config, tmp_path / "d")


def _descendants(pid: int) -> set[int]:
    """PIDs of all live descendants of ``pid`` (Linux /proc)."""
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = {int(c) for c in (task / "children").read_text().split()}
            except OSError:
                continue
            todo += list(kids - out)
            out |= kids
    return out


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.slow
def test_killed_run_resumes_without_rewriting_frames(tmp_path):
    """SIGKILL a 2-worker generation after its first frames, resume, and check
    that no orphan worker survives, the frames written before the kill are
    untouched and the dataset completes."""
    out = tmp_path / "d"
    cmd = [sys.executable, "-m", "pocoloco.cli", "data", "synth", "--preset", "tiny", "--out", str(out),
           "--frames", "6", "--test-sequences", "1", "--workers", "2"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    layout = DatasetLayout(out)
    deadline = time.time() + 900  # generous: the first frames wait for warp / anny set-up on a loaded CI machine
    first = []
    workers: set[int] = set()
    while time.time() < deadline and proc.poll() is None:
        workers |= _descendants(proc.pid)
        first = sorted(out.glob("subjects/*/*/*/frames/*.npz"))
        if len(first) >= 2:
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert len(first) >= 2, "generation produced no frame before the deadline"
    assert workers, "no worker process was seen"
    time.sleep(3)  # workers notice the main process is gone within 0.5 s
    orphans = [p for p in workers if _alive(p)]
    assert not orphans, f"processes of the killed run still alive: {orphans}"
    before = {p: _digest(p) for p in sorted(out.glob("subjects/*/*/*/frames/*.npz"))}
    assert read_card(out)["status"] == "incomplete"
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    card = read_card(out)
    assert card["status"] == "complete"
    for p, digest in before.items():
        assert _digest(p) == digest, f"{p} was rewritten"
    total = sum(c[split]["frames"] for c in card["counts"].values() for split in ("train", "test"))
    rejected = sum(c[split]["rejected_frames"] for c in card["counts"].values() for split in ("train", "test"))
    assert total + rejected == len(list_jobs(dataclasses.replace(SYNTH_PRESETS["tiny"], test_sequences=1))) * 6
    assert len(layout.iter_frames("train")) + len(layout.iter_frames("test")) == total
    json.dumps(card)


def test_v1_settings_and_garment_parameters_round_trip(tmp_path):
    """SYNTH_V1 restores the first pipeline; a subject's garment parameters reach its
    garment and the dataset card (with the kind's defaults filled in)."""
    from pocoloco.synth.config import SYNTH_V1, SubjectSpec, SynthConfig
    from pocoloco.synth.garments import garment_parameters
    from pocoloco.synth.pipeline import subject_assets

    v1 = dataclasses.replace(synth_preset("tiny"), **SYNTH_V1)
    assert v1.garment_tessellation == "grid" and not v1.cloth_self_contact and not v1.capture_cull_hidden_faces
    assert SynthConfig.from_dict(json.loads(json.dumps(v1.to_dict()))) == v1
    maxi = SubjectSpec("m", "maxi_skirt", {"gender": 1.0}, {"hem": 0.6})
    config = dataclasses.replace(synth_preset("tiny"), subjects=(maxi, synth_preset("tiny").subjects[1]))
    assert SynthConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    _, garment = subject_assets(maxi, config)
    assert garment.kind == "maxi_skirt" and garment.params["hem"] == 0.6
    prepare_output(config, tmp_path / "d")
    card = read_card(tmp_path / "d")
    assert card["subjects"]["m"]["garment_params"] == {**garment_parameters("maxi_skirt"), "hem": 0.6}
    assert card["subjects"]["tight"]["garment_params"] is None


def test_heldout_split_draws_test_style_motions_from_its_own_seeds(tiny_dataset, tmp_path):
    """``data heldout`` adds a heldout split to an existing dataset (its card written before the
    setting existed): its own sequences, counted in the card with its own pose coverage, loadable as
    a dataset split, motions unlike the train and test ones, and train / test files untouched."""
    import shutil

    from pocoloco.data.dataset import PointCloudDataset

    tight = next(s for s in synth_preset("tiny").subjects if s.garment == "tight")
    config = dataclasses.replace(synth_preset("tiny"), subjects=(tight,), heldout_sequences=1)
    assert [j.split for j in list_jobs(config)] == ["train", "test", "heldout"]
    out = tmp_path / "d"
    shutil.copytree(tiny_dataset, out)
    card = json.loads((out / "card.json").read_text())
    for key in ("heldout_sequences", "motion_kinds", "frame_storage"):  # as a card from before them
        card["generation_config"].pop(key)
    (out / "card.json").write_text(json.dumps(card))
    before = {p: _digest(p) for p in sorted(out.rglob("*.npz"))}
    r = run_cli("data", "heldout", str(out), "--sequences", "1")
    assert r.returncode == 0, r.stderr
    assert all(_digest(p) == d for p, d in before.items())
    card = read_card(out)
    assert card["generation_config"]["heldout_sequences"] == 1
    assert {s: c["heldout"]["frames"] for s, c in card["counts"].items()} == {"skirt": 4, "tight": 4}
    assert set(card["pose_coverage_heldout"]) == {"skirt", "tight"}
    layout = DatasetLayout(out)
    motion = {split: np.load(layout.sequence_dir("tight", split, f"{split}_0000") / "motion.npz")["joint_rotvecs"]
              for split in ("train", "test", "heldout")}  # fmt: skip
    assert not np.allclose(motion["heldout"], motion["test"]) and not np.allclose(motion["heldout"], motion["train"])
    assert len(PointCloudDataset(out, "heldout", num_points=64)) == 8
    info = run_cli("data", "info", str(out))
    assert "heldout poses" in info.stdout and "heldout_sequences=1" in info.stdout
    assert run_cli("data", "verify", str(out)).returncode == 0
    for args, message in ((["--sequences", "0"], "--sequences must be >= 1"), ([], "no card.json")):
        bad = run_cli("data", "heldout", str(out if args else tmp_path / "none"), *args)
        assert bad.returncode == 2 and message in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
    assert run_cli("data", "synth", "--preset", "tiny", "--out", str(tmp_path / "e"),
                   "--heldout-sequences", "-1").returncode == 2  # fmt: skip


def test_medium_preset_covers_garments_bodies_and_motions():
    from pocoloco.synth.config import ALL_MOTION_KINDS, CLASSIC_MOTION_KINDS
    from pocoloco.synth.garments import GARMENT_KINDS
    from pocoloco.synth.motion import CLASSIC_KINDS, MOTION_KINDS

    assert CLASSIC_MOTION_KINDS == CLASSIC_KINDS and ALL_MOTION_KINDS == MOTION_KINDS
    assert synth_preset("small").motion_kinds == CLASSIC_KINDS
    medium = synth_preset("medium")
    assert medium.motion_kinds == MOTION_KINDS and medium.heldout_sequences > 0
    assert len(medium.subjects) >= 8 and len({s.name for s in medium.subjects}) == len(medium.subjects)
    assert medium.train_sequences * medium.frames_per_sequence >= 800
    assert medium.test_sequences * medium.frames_per_sequence >= 200
    bodies: dict[str, set] = {}
    for s in medium.subjects:
        bodies.setdefault(s.garment, set()).add(tuple(sorted(s.phenotype.items())))
    assert set(bodies) == set(GARMENT_KINDS) | {"tight"}
    assert all(len(b) >= 2 for b in bodies.values()), bodies  # every kind on two bodies at least
    # a card written before these settings existed reads as the values its run used
    from pocoloco.synth.config import FIELDS_ADDED_LATER, config_of_card

    old = {k: v for k, v in synth_preset("small").to_dict().items() if k not in FIELDS_ADDED_LATER}
    assert config_of_card(old) == dataclasses.replace(synth_preset("small"), **FIELDS_ADDED_LATER)
    with pytest.raises(ValueError, match="generation_config"):
        config_of_card({"no_such_setting": 1})


def test_frames_do_not_depend_on_the_callers_torch_threads(tmp_path):
    """Bodies are posed under one torch thread (utils.seeding.torch_threads), so a generating
    process's own thread count cannot change a frame's bytes (it did: float reductions split by
    thread count); the caller's setting is restored."""
    import torch

    from pocoloco.synth.pipeline import run_sequence, write_subject

    tight = next(s for s in synth_preset("tiny").subjects if s.garment == "tight")
    config = dataclasses.replace(synth_preset("tiny"), subjects=(tight,))
    job = list_jobs(config)[0]
    before = torch.get_num_threads()
    digests = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            out = tmp_path / f"t{threads}"
            prepare_output(config, out)
            write_subject(config, out, tight)
            run_sequence(config, out, job)
            assert torch.get_num_threads() == threads
            digests.append(sorted(_digest(p) for p in out.rglob("*.npz")))
    finally:
        torch.set_num_threads(before)
    assert digests[0] == digests[1]
