"""Reference sets of true states (``pocoloco data histories``): the history motions end exactly on
the frame's body, the frames spread over the subjects, and the set is a dataset that verifies,
resumes and refuses bad input. The cloth subject's simulation is exercised by the CLI run quoted
in docs/guides/evaluation.md; here the tight subject keeps the test fast (no simulation)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import run_cli


def _motion(n: int, seed: int, yaw_rate: float = 0.0):
    rng = np.random.default_rng(seed)
    rot = np.cumsum(rng.normal(0, 0.01, (n, 24, 3)), 0).astype(np.float32)
    rot[:, 0] = 0.0
    rot[:, 0, 2] = yaw_rate * np.arange(n)
    trans = np.cumsum(np.tile([[0.02, 0.01, 0.0]], (n, 1)), 0).astype(np.float32)
    return rot, trans


@pytest.mark.parametrize("shared", [0, 7])
def test_join_ends_exactly_on_the_own_motion_and_is_smooth(shared):
    from pocoloco.synth.histories import join_motions

    p_rot, p_trans = _motion(30, 1, yaw_rate=0.05)
    o_rot, o_trans = _motion(40, 2, yaw_rate=-0.03)
    end = 35
    rot, trans = join_motions(p_rot, p_trans, o_rot, o_trans, end - shared, end, blend=10)
    assert rot.shape == (30 + 10 + shared + 1, 24, 3) and trans.shape == (len(rot), 3)
    np.testing.assert_array_equal(rot[-1], o_rot[end])
    np.testing.assert_array_equal(trans[-1], o_trans[end])
    np.testing.assert_array_equal(rot[-(shared + 1):], o_rot[end - shared : end + 1])
    # no jump: frame-to-frame steps through the blend stay near the motions' own
    own_step = np.abs(np.diff(o_trans, axis=0)).max()
    assert np.abs(np.diff(trans, axis=0)).max() < 3 * own_step + 1e-3
    from scipy.spatial.transform import Rotation

    root = Rotation.from_rotvec(rot[:, 0])
    steps = (root[1:] * root[:-1].inv()).magnitude()
    assert steps.max() < 0.2  # radians per frame: the heading is turned, not snapped


def test_join_rejects_a_window_outside_the_motion():
    from pocoloco.synth.histories import join_motions

    p_rot, p_trans = _motion(10, 1)
    o_rot, o_trans = _motion(20, 2)
    with pytest.raises(ValueError, match="join"):
        join_motions(p_rot, p_trans, o_rot, o_trans, 15, 25, blend=4)


def test_poses_spread_over_the_subjects(tiny_dataset):
    from pocoloco.synth.histories import HistoriesSpec, select_poses

    spec = HistoriesSpec(poses=4, histories=2, shared_seconds=(0.0,), seed=3)
    poses = select_poses(tiny_dataset, spec)
    assert len(poses) == 4 and len(set(poses)) == 4
    assert sorted({p.subject for p in poses}) == ["skirt", "tight"]
    assert poses == select_poses(tiny_dataset, spec)  # seeded
    with pytest.raises(ValueError, match="no test frame has 10 s"):
        select_poses(tiny_dataset, HistoriesSpec(poses=2, shared_seconds=(10.0,)))
    with pytest.raises(ValueError, match="no subject nobody"):
        select_poses(tiny_dataset, HistoriesSpec(poses=2, subjects=("nobody",)))


def test_histories_cli_makes_a_verified_resumable_reference_set(tiny_dataset, tmp_path):
    from pocoloco.data.format import read_frame
    from pocoloco.synth.histories import reference_sets

    out = tmp_path / "refs"
    args = ["data", "histories", str(tiny_dataset), "--out", str(out), "--poses", "2", "--histories", "3",
            "--shared-seconds", "0", "0.2", "--subjects", "tight"]  # fmt: skip
    r = run_cli(*args)
    assert r.returncode == 0, r.stderr
    assert "reference set: 2 test poses" in r.stdout
    card = json.loads((out / "card.json").read_text())
    assert card["status"] == "complete" and card["histories"]["histories"] == 3
    sets = reference_sets(out)
    assert len(sets) == 4 and {s["shared_seconds"] for s in sets} == {0.0, 0.2}
    for s in sets:
        own = read_frame(s["own"])
        meta = json.loads((s["own"].parent.parent / "sequence.json").read_text())
        assert [r["k"] for r in meta["references"]] == [0, 1, 2, 3] and meta["references"][-1]["own_scan"]
        for path in s["refs"]:
            ref = read_frame(path)
            np.testing.assert_allclose(ref.body_vertices, own.body_vertices, atol=1e-4)  # exactly the frame's body
            assert ref.points.shape == own.points.shape and ref.normals.shape == own.normals.shape
    r = run_cli("data", "verify", str(out))
    assert r.returncode == 0 and "OK" in r.stdout
    # a lost reference is made again by the same command; the rest is kept
    victim = sets[0]["refs"][1]
    seq_dir = victim.parent.parent
    before = sets[0]["refs"][0].read_bytes()
    (seq_dir / "sequence.json").unlink()
    victim.unlink()
    for k in (0, 2):
        (seq_dir / "frames" / f"{k:06d}.json").write_text(json.dumps({"k": k, "prefix_kind": "x"}))
    r = run_cli(*args)
    assert r.returncode == 0, r.stderr
    assert victim.exists() and sets[0]["refs"][0].read_bytes() == before
    # resumed again in-process: what exists counts as done from the first report (12 = 2 poses x 3 x 2
    # windows; the lost one's history is all that runs), so the time left is this run's estimate
    from pocoloco.synth.histories import HistoriesSpec, make_histories

    (seq_dir / "sequence.json").unlink()
    victim.unlink()
    for k in (0, 2):
        (seq_dir / "frames" / f"{k:06d}.json").write_text(json.dumps({"k": k, "prefix_kind": "x"}))
    reports = []
    make_histories(tiny_dataset, out, HistoriesSpec(poses=2, histories=3, shared_seconds=(0.0, 0.2), subjects=("tight",)),
                   progress=lambda done, total: reports.append((done, total)))  # fmt: skip
    assert reports == [(10, 12), (12, 12)] and victim.exists(), reports
    # another request into the same folder, and bad input: one line each
    for bad, msg in ((["--histories", "4"], "holds another reference set"), (["--histories", "1"], "--histories"),
                     (["--shared-seconds", "-1"], "--shared-seconds")):  # fmt: skip
        r = run_cli(*args, *bad)
        assert r.returncode != 0 and msg in r.stderr and "Traceback" not in r.stderr
    not_synth = tmp_path / "copy"
    shutil.copytree(out, not_synth)
    r = run_cli("data", "histories", str(not_synth), "--out", str(tmp_path / "again"))
    assert r.returncode != 0 and "is itself a reference set" in r.stderr


def test_bench_distribution_ranks_the_truth_first_and_reports_every_row(tiny_dataset, tiny_run, tmp_path):
    from pocoloco.synth.histories import HistoriesSpec, make_histories

    refs = tmp_path / "refs"
    make_histories(tiny_dataset, refs, HistoriesSpec(poses=2, histories=4, shared_seconds=(0.0,), subjects=("tight",)))
    out = tmp_path / "judge"
    r = run_cli("bench", "distribution", "--refs", str(refs), "--ckpt-pocoloco", str(tiny_run), "--samples", "3",
                "--points", "256", "--probes", "64", "--out", str(out))  # fmt: skip
    assert r.returncode == 0, r.stderr
    report = json.loads((out / "distribution.json").read_text())
    rows = report["rows"]
    assert set(rows) == {"pocoloco", "truth_loo", "refs_medoid", "posed_body"}
    w = report["windows"][0]
    assert w == "0"
    es = {n: rows[n][w]["energy_score"]["mean"] for n in rows}
    # a 2-step model is far from the truth; the truth itself is the floor
    assert es["truth_loo"] < es["pocoloco"] and es["truth_loo"] <= es["refs_medoid"] + 1e-9
    assert rows["truth_loo"][w]["es_minus_truth"]["mean"] == pytest.approx(0.0, abs=1e-9)
    # by Chamfer too: a perfect sampler's (two distinct true states) is below the 2-step model's
    assert rows["truth_loo"][w]["chamfer_to_refs"]["mean"] < rows["pocoloco"][w]["chamfer_to_refs"]["mean"]
    st = rows["pocoloco"][w]
    assert st["energy_score"]["lo"] <= st["energy_score"]["mean"] <= st["energy_score"]["hi"]
    for key in ("spread_refs", "spread_samples", "to_refs", "energy_distance", "chamfer_to_refs", "cov", "mmd",
                "nna_refs", "nna_samples"):  # fmt: skip
        assert key in st
    assert rows["posed_body"][w]["nna_samples"]["mean"] is None  # one cloud: no sample neighbour (NaN -> null)
    # per garment kind (here only the tight body): the spread of the true states and every row's ES
    kind = report["by_garment"]["tight"][w]
    assert kind["poses"] == 2
    assert kind["spread_refs"] == pytest.approx(rows["posed_body"][w]["spread_refs"]["mean"])
    assert kind["energy_score"]["pocoloco"] == pytest.approx(es["pocoloco"])
    assert "## Per garment kind" in (out / "distribution.md").read_text()
    assert len(report["per_pose"]) == 2 and "ES" in (out / "distribution.md").read_text()
    r = run_cli("bench", "distribution", "--refs", str(tiny_dataset), "--ckpt-pocoloco", str(tiny_run),
                "--out", str(tmp_path / "no"))  # fmt: skip
    assert r.returncode != 0 and "not a reference set" in r.stderr and not (tmp_path / "no").exists()


@pytest.mark.slow  # ~1 min: tiny cloth, two references per window and two direct simulations
def test_a_garments_windows_continue_one_prefix_as_a_direct_simulation_would(tiny_dataset, tmp_path):
    """Both windows of a history continue one simulated prefix (turned to each join); the reference
    is as near the direct simulation of the joined motion from rest as that simulation is to itself
    turned by a heading (the cloth is chaotic: rounding alone moves a hem by millimetres)."""
    from scipy.spatial.transform import Rotation

    from pocoloco.data.format import DatasetLayout, read_frame, read_motion, read_sequence_meta
    from pocoloco.synth.cloth_sim import simulate_garment
    from pocoloco.synth.histories import (
        HistoriesSpec,
        RefPose,
        _prefix,
        join_motions,
        make_histories,
        own_motion,
        reference_sets,
        synth_source,
    )
    from pocoloco.synth.pipeline import cloth_settings, subject_assets

    spec = HistoriesSpec(poses=1, histories=2, shared_seconds=(0.0, 0.2), prefix_seconds=0.4, subjects=("skirt",))
    out = tmp_path / "refs"
    make_histories(tiny_dataset, out, spec)
    sets = reference_sets(out)
    metas = [json.loads((s["own"].parent.parent / "sequence.json").read_text())["references"] for s in sets]
    assert [r["prefix_seed"] for r in metas[0][:2]] == [r["prefix_seed"] for r in metas[1][:2]]  # one prefix each
    s = next(s for s in sets if s["shared_seconds"] == 0.2)
    _, config = synth_source(tiny_dataset)
    pose = RefPose(**s["source"])
    subject = next(x for x in config.subjects if x.name == pose.subject)
    body, garment = subject_assets(subject, config)
    src = DatasetLayout(tiny_dataset)
    record = read_sequence_meta(src.sequence_meta_path(subject.name, "test", pose.sequence))
    own = own_motion(config, body, "test", {**record, "name": pose.sequence},
                     read_motion(src.motion_path(subject.name, "test", pose.sequence)))  # fmt: skip
    t = own.num_frames - config.frames_per_sequence + pose.frame
    _, _, prefix = _prefix(config, body, spec, 0, 0, 0)
    rot, trans = join_motions(prefix.joint_rotvecs, prefix.root_translation, own.joint_rotvecs, own.root_translation,
                              t - int(round(0.2 * config.fps)), t, config.blend_frames)  # fmt: skip
    settings = cloth_settings(config, subject.garment)
    direct = simulate_garment(body, garment, body.pose(rot, trans), settings).vertices[-1]
    turn = Rotation.from_euler("z", 0.5)
    rot_t = rot.copy()
    rot_t[:, 0] = (turn * Rotation.from_rotvec(rot[:, 0])).as_rotvec()
    turned = simulate_garment(body, garment, body.pose(rot_t, turn.apply(trans).astype(np.float32)), settings)
    control = np.linalg.norm(turn.inv().apply(turned.vertices[-1]) - direct, axis=1).mean()
    shared = np.linalg.norm(read_frame(s["refs"][0]).garment_vertices - direct, axis=1).mean()
    assert control < 0.02 and shared < 3 * control + 0.002, (shared, control)


def test_bench_distribution_gives_a_motion_aware_model_the_shared_motion(tiny_dataset, tmp_path):
    """A --motion-window model draws twice per pose: with the frame's own window where every true
    state shares it (the window's shared seconds cover the model's), at rest where they do not."""
    from pocoloco.cli import main as cli_main
    from pocoloco.synth.histories import HistoriesSpec, make_histories

    refs = tmp_path / "refs"
    make_histories(tiny_dataset, refs, HistoriesSpec(poses=1, histories=2, shared_seconds=(0.0, 0.2),
                                                     prefix_seconds=0.4, subjects=("tight",)))  # fmt: skip
    run = tmp_path / "run"
    assert cli_main(["train", "--data", str(tiny_dataset), "--preset", "latent_tiny", "--motion-window", "0.2", "--steps",
                     "2", "--out", str(run), "--no-progress", "--sample-every", "0"]) in (0, None)  # fmt: skip
    r = run_cli("bench", "distribution", "--refs", str(refs), "--ckpt-pocoloco", str(run), "--samples", "2",
                "--points", "128", "--probes", "32", "--out", str(tmp_path / "judge"))  # fmt: skip
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "judge" / "distribution.json").read_text())
    assert report["settings"]["motion_windows"] == {"pocoloco": 0.2}
    assert set(report["windows"]) == {"0", "0.2"}
    a, b = (report["per_pose"][k]["rows"]["pocoloco"]["spread_samples"] for k in (0, 1))
    assert a != b  # two draws: at rest, and with the shared motion
    r = run_cli("bench", "distribution", "--refs", str(refs), "--ckpt-pocoloco", str(run), "--samples", "2",
                "--points", "128", "--probes", "32", "--history", "rest", "--out", str(tmp_path / "rest"))  # fmt: skip
    assert r.returncode == 0, r.stderr
    rest = json.loads((tmp_path / "rest" / "distribution.json").read_text())
    assert rest["settings"]["history"] == "rest"
    c, d = (rest["per_pose"][k]["rows"]["pocoloco"]["spread_samples"] for k in (0, 1))
    assert c == d == a  # no window anywhere: the clouds drawn at rest, for both windows
