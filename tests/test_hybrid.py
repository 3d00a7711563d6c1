"""The hybrid method's free-region maps (pocoloco.methods.hybrid.regions) and the region pack its
generator trains on: checked against a per-vertex loop and on the tiny dataset's skirt and tight
subjects."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pocoloco.cli import main
from pocoloco.data.format import LABEL_GARMENT, DatasetLayout, read_frame, read_subject
from pocoloco.data.pack import PackedDataset, write_pack
from pocoloco.data.published import read_ply, write_ply
from pocoloco.methods import load_method, train
from pocoloco.methods.base import SampledClouds, SamplerOptions
from pocoloco.methods.hybrid import FreeRegionMaps, HybridMethod, learn_free_maps, point_regions, render_free_maps
from pocoloco.body.surface import vertex_normals
from pocoloco.methods.hybrid.regions import inside_depth, scan_vertex_votes
from pocoloco.methods.skinned import skinned_preset


def _reference_share(data, subject: str, every: int, margin: float) -> np.ndarray:
    """Slow reference: per frame, per vertex, the nearest point by a full distance scan."""
    layout = DatasetLayout(data)
    paths = [layout.frame_path(subject, "train", q, i) for q in layout.sequences(subject, "train")
             for i in layout.frame_indices(subject, "train", q)][::every]  # fmt: skip
    votes = None
    for p in paths:
        fr = read_frame(p, ("points", "labels", "body_vertices"), allow_missing=True)
        vote = np.zeros(len(fr.body_vertices), bool)
        for v, x in enumerate(fr.body_vertices.astype(np.float64)):
            d = np.linalg.norm(fr.points.astype(np.float64) - x, axis=1)
            j = int(d.argmin())
            vote[v] = fr.labels[j] == LABEL_GARMENT or d[j] > margin
        votes = vote.astype(int) if votes is None else votes + vote
    return votes / len(paths)


def test_free_maps_match_a_per_vertex_loop_and_separate_skirt_from_tight(tiny_dataset, tmp_path):
    maps = learn_free_maps(tiny_dataset, margin=0.03, threshold=0.5, every=4)
    assert maps.outfits == ("skirt", "tight")
    skirt, tight = (maps.outfits.index(n) for n in ("skirt", "tight"))
    np.testing.assert_allclose(maps.vertex_share[skirt], _reference_share(tiny_dataset, "skirt", 4, 0.03), atol=1e-6)
    # the skirt hangs free over hips and legs; nothing of the tight outfit leaves the body (a few
    # uncaptured vertices are far from every point, but a share below MIN_FREE_SHARE is no region)
    assert maps.point_share[skirt] > 0.25 and maps.point_share[tight] == 0, maps.point_share
    assert maps.free(skirt).mean() > 0.05 and not maps.free(tight).any()
    raw = _reference_share(tiny_dataset, "tight", 4, 0.03)
    assert raw.max() > 0  # what was dropped
    # save / load round trip; a damaged file is one line
    back = FreeRegionMaps.load(maps.save(tmp_path / "maps.npz"))
    assert back.outfits == maps.outfits and np.array_equal(back.vertex_share, maps.vertex_share)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a free-region map file"):
        FreeRegionMaps.load(tmp_path / "bad.npz")
    png = render_free_maps(maps, tiny_dataset, tmp_path / "maps.png")
    assert (tmp_path / "maps.png").stat().st_size > 5000 and png.endswith("maps.png")
    with pytest.raises(ValueError, match="margin"):
        learn_free_maps(tiny_dataset, margin=0.0)


def test_point_regions_take_the_region_of_the_nearest_body_vertex():
    body = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    free = np.array([False, True, False])
    pts = np.array([[0.9, 0.1, 0], [0.1, 0.8, 0], [0.2, 0.1, 0.3], [1.5, 0, 0]], np.float32)
    assert point_regions(pts, body, free).tolist() == [True, False, False, True]
    # far: a point farther than that from every vertex is free whatever its nearest one
    assert point_regions(pts, body, free, far=0.3).tolist() == [True, False, True, True]
    far = np.array([np.linalg.norm(body - x, axis=1).min() > 0.25 for x in pts])  # the loop
    assert point_regions(pts, body, free, far=0.25).tolist() == (free[[1, 2, 0, 1]] | far).tolist()


def test_point_shares_counted_with_far_points_add_them_and_leave_attached_outfits_alone(tiny_dataset, tmp_path):
    """recount_point_shares: by the nearest vertex alone it repeats learn_free_maps' shares on the
    same frames; with far it counts the scan points far from the body too (checked by a loop), an
    outfit without a free region stays wholly attached, and the rule travels with the maps."""
    from pocoloco.methods.hybrid.regions import recount_point_shares

    maps = learn_free_maps(tiny_dataset, margin=0.03, threshold=0.5, every=4)
    skirt, tight = (maps.outfits.index(n) for n in ("skirt", "tight"))
    again = recount_point_shares(maps, tiny_dataset, None, every=12)  # learn_free_maps: every 3rd of every 4th
    np.testing.assert_allclose(again.point_share, maps.point_share, atol=1e-6)
    far = recount_point_shares(maps, tiny_dataset, 0.05, every=12)
    layout = DatasetLayout(tiny_dataset)
    paths = [layout.frame_path("skirt", "train", q, i) for q in layout.sequences("skirt", "train")
             for i in layout.frame_indices("skirt", "train", q)][::12]  # fmt: skip
    loop = []
    for path in paths:
        fr = read_frame(path, ("points", "body_vertices"), allow_missing=True)
        d = np.array([np.linalg.norm(fr.body_vertices - x, axis=1) for x in fr.points])
        loop.append(np.mean(maps.free(skirt)[d.argmin(1)] | (d.min(1) > 0.05)))
    assert far.point_share[skirt] == pytest.approx(np.mean(loop), abs=1e-6)
    assert far.point_share[skirt] >= maps.point_share[skirt] and far.point_share[tight] == 0 and far.far == 0.05
    assert FreeRegionMaps.load(far.save(tmp_path / "far.npz")).far == 0.05
    direct = learn_free_maps(tiny_dataset, margin=0.03, threshold=0.5, every=4, far=0.05)
    np.testing.assert_allclose(direct.point_share, far.point_share, atol=1e-6)


def test_inside_depth_matches_a_per_point_loop_and_is_positive_inside_a_closed_body(tiny_dataset):
    """Vertex normals of the posed body point outwards; a point's depth is minus its offset along the
    normal of its nearest vertex (checked against a per-point loop)."""
    _, _, path = _frame(tiny_dataset, "tight")
    fr = read_frame(path, ("body_vertices",))
    faces = read_subject(DatasetLayout(tiny_dataset).subject_path("tight")).faces
    v = fr.body_vertices.astype(np.float64)
    n = vertex_normals(v, faces)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    centre = v.mean(0)
    f = np.asarray(faces, np.int64)
    assert np.linalg.det(np.stack([v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]], axis=1)).sum() > 0  # faces wind outwards
    rng = np.random.default_rng(0)
    pick = rng.choice(len(v), 200, replace=False)
    outside, inside = v[pick] + 0.002 * n[pick], v[pick] - 0.002 * n[pick]
    pts = np.concatenate([outside, inside, centre + rng.normal(0, 0.3, (50, 3))])
    depth = inside_depth(pts, v, n)
    ref = np.array([-(p - v[j]) @ n[j] for p in pts for j in [int(np.argmin(np.linalg.norm(v - p, axis=1)))]])
    np.testing.assert_allclose(depth, ref, atol=1e-6)
    assert np.mean(depth[:200] < 0) > 0.9 and np.mean(depth[200:400] > 0) > 0.9


def test_a_region_pack_holds_only_selected_points_and_keeps_outfit_ids(tiny_dataset, tmp_path):
    maps = learn_free_maps(tiny_dataset, every=4)
    free = maps.free(maps.outfits.index("skirt"))

    def select(subject, path):
        fr = read_frame(path, ("points", "body_vertices"))
        return point_regions(fr.points, fr.body_vertices, free)

    meta = write_pack(tiny_dataset, tmp_path / "free.pack", points=128, subjects=["skirt"], select=select)
    assert meta["subject_names"] == ["skirt", "tight"] and meta["skipped"] == {}
    ds = PackedDataset(tmp_path / "free.pack", "train")
    layout = DatasetLayout(tiny_dataset)
    assert len(ds) == sum(len(layout.frame_indices("skirt", "train", q)) for q in layout.sequences("skirt", "train"))
    for i in (0, len(ds) - 1):
        item = ds[i]
        assert int(item["subject"]) == 0  # the card's id of "skirt", as in the full dataset
        pts = ds.normalisation.denormalise(item["points"].numpy(), item["root"].numpy(), item["angle"].numpy())
        subject, split, seq, index = ds.frame_key(i).split("/")
        fr = read_frame(layout.frame_path(subject, split, seq, int(index)), ("points", "body_vertices"))
        assert point_regions(pts, fr.body_vertices, free).mean() > 0.97  # quantised to 1 mm
    # a selection no frame can fill is one line
    with pytest.raises(ValueError, match="selected points"):
        write_pack(tiny_dataset, tmp_path / "none.pack", points=128, subjects=["tight"],
                   select=lambda s, p: np.zeros(4000, bool))  # fmt: skip


# ------------------------------------------------------------------------------- the method
@pytest.fixture(scope="module")
def hybrid(tiny_dataset, tiny_run, tmp_path_factory):
    """A hybrid assembled from a 2-step tiny POP and the 2-step tiny PocoLoco (through the CLI)."""
    root = tmp_path_factory.mktemp("hybrid")
    cfg = skinned_preset("pop", "tiny", steps=2, ckpt_every=0, sample_every=0, log_every=1)
    train(cfg, tiny_dataset, root / "pop", progress=False)
    out = root / "hybrid"
    assert main(["hybrid", "--attached", str(root / "pop"), "--free", str(tiny_run), "--data", str(tiny_dataset),
                 "--out", str(out), "--every", "4"]) == 0  # fmt: skip
    return out


def _frame(tiny_dataset, subject):
    s, seq, path = next(f for f in DatasetLayout(tiny_dataset).iter_frames("test") if f[0] == subject)
    return s, seq, path


def test_hybrid_splits_points_by_region_and_hypotheses_differ_only_where_free(hybrid, tiny_dataset):
    m = load_method(hybrid)
    assert isinstance(m, HybridMethod) and (hybrid / "maps.png").is_file()
    for subject in ("skirt", "tight"):
        _, _, path = _frame(tiny_dataset, subject)
        fr = read_frame(path, allow_missing=True)
        pose = m.pose_from_frame(path, subject, frame=fr)
        o = m.outfit_id(subject)
        clouds = m.predict(pose, 300, seeds=(0, 1), outfit=o, options=SamplerOptions(steps=2))
        assert clouds.points.shape == (2, 300, 3) and clouds.normals is None
        n_att, n_free = m.split(o, 300)
        assert n_free == round(m.maps.point_share[o] * 300)
        free = m.maps.free(o)
        for pts in clouds.points:
            assert not point_regions(pts[:n_att], fr.body_vertices, free).any()
            assert point_regions(pts[n_att:], fr.body_vertices, free).all()
        np.testing.assert_array_equal(clouds.points[0, :n_att], clouds.points[1, :n_att])  # attached: shared
        if subject == "skirt":
            assert n_free > 60 and not np.array_equal(clouds.points[0, n_att:], clouds.points[1, n_att:])
        else:
            assert n_free == 0


def test_even_keeps_the_hybrids_own_layout(hybrid, tiny_dataset):
    """``--even`` on the hybrid: its own clouds (FPS of its points measured worse), said in its settings."""
    from pocoloco.methods import predict_clouds

    m = load_method(hybrid)
    _, _, path = _frame(tiny_dataset, "skirt")
    pose = m.pose_from_frame(path, "skirt")
    o, options = m.outfit_id("skirt"), SamplerOptions(steps=2, even=True)
    assert m.even_candidates(300) == 300 and "own layout" in m.sample_settings(options, 300)["even"]
    np.testing.assert_array_equal(predict_clouds(m, pose, 300, (0, 1), o, options).points,
                                  m.predict(pose, 300, (0, 1), o, SamplerOptions(steps=2)).points)  # fmt: skip


def test_hybrid_through_the_cli_and_its_one_line_errors(hybrid, tiny_dataset, tiny_run, tmp_path, capsys):
    s, seq, path = _frame(tiny_dataset, "skirt")
    idx = int(read_frame(path, ["frame_index"]).frame_index)
    spec = f"{tiny_dataset}:{s}/test/{seq}/{idx}"
    out = tmp_path / "sample"
    assert main(["sample", "--ckpt", str(hybrid), "--joints", spec, "--num", "2", "--points", "200", "--steps", "2",
                 "--no-render", "--out", str(out)]) == 0  # fmt: skip
    assert len(list(out.glob("*.ply"))) == 2
    ev = tmp_path / "eval"
    assert main(["eval", "--ckpt", str(hybrid), "--data", str(tiny_dataset), "--frames", "2", "--points", "64",
                 "--seeds", "0", "1", "--steps", "2", "--no-baselines", "--out", str(ev)]) == 0  # fmt: skip
    report = json.loads((ev / "eval.json").read_text())
    assert report["settings"]["model_kind"] == "hybrid" and report["settings"]["free_point_share"]["tight"] == 0
    capsys.readouterr()
    for argv, message in (
        (["hybrid", "--attached", str(tiny_run), "--free", str(tiny_run), "--data", str(tiny_dataset),
          "--out", str(tmp_path / "x")], "expected 'pop'"),
        (["hybrid", "--attached", str(hybrid), "--free", str(tiny_run), "--data", str(tiny_dataset),
          "--out", str(tmp_path / "y"), "--margin", "nan"], "--margin"),
        (["train", "--model", "hybrid", "--data", str(tiny_dataset), "--out", str(tmp_path / "z")], "assembled"),
    ):  # fmt: skip
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err


def test_a_generator_share_splits_the_free_region_between_pop_and_the_generator(hybrid, tiny_dataset, tmp_path):
    """generator_share 0.5: half the free region's points are POP's (shared by the hypotheses), half generated."""
    ck = load_method(hybrid)
    half = HybridMethod(ck.model, ck.config.replace(generator_share=0.5), ck.normalisation, ck.path, ck.step, ck.meta)
    _, _, path = _frame(tiny_dataset, "skirt")
    fr = read_frame(path, allow_missing=True)
    pose = half.pose_from_frame(path, "skirt", frame=fr)
    o = half.outfit_id("skirt")
    clouds = half.predict(pose, 300, seeds=(0, 1), outfit=o, options=SamplerOptions(steps=2)).points
    n_att, n_free = half.split(o, 300)
    n_gen = round(0.5 * n_free)
    shared = 300 - n_gen
    np.testing.assert_array_equal(clouds[0, :shared], clouds[1, :shared])
    assert not np.array_equal(clouds[0, shared:], clouds[1, shared:])
    region = point_regions(clouds[0], fr.body_vertices, half.maps.free(o))
    assert not region[:n_att].any() and region[n_att:].all()
    with pytest.raises(ValueError, match="generator share"):
        ck.config.replace(generator_share=1.5)


def test_an_inside_tolerance_draws_again_the_generated_points_inside_the_body(hybrid, tiny_dataset):
    """The generator is replaced by one that draws free-region body vertices moved 1 cm in or out
    along their normals: with inside_tolerance 0.5 cm only the outer ones are kept."""
    loaded = load_method(hybrid)
    ck = HybridMethod(loaded.model, loaded.config.replace(generator_share=1.0), loaded.normalisation, loaded.path,
                      loaded.step, loaded.meta)  # fmt: skip  (the free region wholly generated)
    strict = HybridMethod(ck.model, ck.config.replace(inside_tolerance=0.005), ck.normalisation, ck.path, ck.step,
                          ck.meta)  # fmt: skip
    _, _, path = _frame(tiny_dataset, "skirt")
    fr = read_frame(path, allow_missing=True)
    pose = strict.pose_from_frame(path, "skirt", frame=fr)
    o = strict.outfit_id("skirt")
    free = strict.maps.free(o)
    normals = vertex_normals(fr.body_vertices, strict.attached.model.faces_np)
    ids = np.flatnonzero(free)

    def fake_predict(pose, m, seeds, outfit, options, code=None):
        rng = np.random.default_rng(seeds[0])
        pick = rng.choice(ids, (len(seeds), m))
        side = rng.choice([-0.01, 0.01], (len(seeds), m, 1))
        return SampledClouds((fr.body_vertices[pick] + side * normals[pick]).astype(np.float32), None)

    for method in (ck, strict):
        method.free.predict = fake_predict
    n_att, _ = strict.split(o, 300)
    loose = ck.predict(pose, 300, seeds=(0,), outfit=o).points[0, n_att:]
    kept = strict.predict(pose, 300, seeds=(0,), outfit=o).points[0, n_att:]
    assert (inside_depth(loose, fr.body_vertices, normals) > 0.005).mean() > 0.3
    assert (inside_depth(kept, fr.body_vertices, normals) <= 0.005).all()
    assert point_regions(kept, fr.body_vertices, free).all()
    for bad in (-0.01, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="inside tolerance"):
            ck.config.replace(inside_tolerance=bad)


def test_the_generator_is_asked_for_the_free_region_at_its_share_then_only_for_what_is_missing(hybrid, tiny_dataset):
    """A generator that puts every other point on an attached vertex keeps half its draw: the first
    draw is sized by the free region's share of a scan, a second one (if any) only for the points
    still missing, and the cloud still has exactly its free-region points, all in the region."""
    m = load_method(hybrid)
    _, _, path = _frame(tiny_dataset, "skirt")
    fr = read_frame(path, allow_missing=True)
    pose = m.pose_from_frame(path, "skirt", frame=fr)
    o = m.outfit_id("skirt")
    free = m.maps.free(o)
    ids_free, ids_att = np.flatnonzero(free), np.flatnonzero(~free)
    asked = []

    def fake_predict(pose, n, seeds, outfit, options, code=None):
        asked.append(n)
        rng = np.random.default_rng(seeds[0])
        pick = np.where(np.arange(n) % 2 == 0, rng.choice(ids_free, n), rng.choice(ids_att, n))
        return SampledClouds(np.repeat(fr.body_vertices[pick][None], len(seeds), 0).astype(np.float32), None)

    m.free.predict = fake_predict
    n_free = m.split(o, 400)[1]
    n_gen = round(m.config.generator_share * n_free)
    cloud = m.predict(pose, 400, seeds=(0,), outfit=o).points[0]
    assert cloud.shape == (400, 3) and point_regions(cloud[400 - n_gen :], fr.body_vertices, free).all()
    assert asked[0] == int(np.ceil(1.3 * n_gen / (n_free / 400)))
    assert len(asked) <= 2 and all(a < asked[0] for a in asked[1:])  # the missing points, not n_gen again


def test_the_hybrid_animates_a_dataset_sequence_and_refuses_bare_joints(hybrid, tiny_dataset, tmp_path, capsys):
    """animate: the free region's generator runs the chain, each frame gets POP's points for its body."""
    s, seq, _ = _frame(tiny_dataset, "skirt")
    out = tmp_path / "anim"
    assert main(["animate", "--ckpt", str(hybrid), "--motion", f"{tiny_dataset}:{s}/test/{seq}", "--frames", "0:3",
                 "--points", "200", "--steps", "2", "--t", "100", "--no-render", "--out", str(out)]) == 0  # fmt: skip
    info = json.loads((out / "animation.json").read_text())
    assert len(info["metrics"]["flicker_cm"]) == 2 and len(list(out.glob("frame_*.ply"))) == 3
    m = load_method(hybrid)
    layout = DatasetLayout(tiny_dataset)
    o = m.outfit_id("skirt")
    n_att, _ = m.split(o, 200)
    for k in range(3):
        pts = read_ply(out / f"frame_{k:04d}.ply").points
        path = layout.frame_path(s, "test", seq, layout.frame_indices(s, "test", seq)[k])
        body = read_frame(path, ("body_vertices",)).body_vertices
        region = point_regions(pts, body, m.maps.free(o))
        assert len(pts) == 200 and not region[:n_att].any() and region[n_att:].all()
    joints = tmp_path / "motion.npy"
    np.save(joints, np.stack([read_frame(layout.frame_path(s, "test", seq, i), ["joints"]).joints
                              for i in layout.frame_indices(s, "test", seq)[:2]]))  # fmt: skip
    capsys.readouterr()
    assert main(["animate", "--ckpt", str(hybrid), "--motion", str(joints), "--outfit", "skirt", "--points", "64",
                 "--no-render", "--out", str(tmp_path / "bare")]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "dataset sequences" in err, err
    assert not (tmp_path / "bare").exists()


@pytest.fixture(scope="module")
def hybrid_with_codes(hybrid, tiny_dataset, tmp_path_factory):
    """The tiny hybrid's POP with a 2-step tiny PocoLoco that has outfit codes and body shape."""
    from pocoloco.methods.pocoloco import train_preset

    root = tmp_path_factory.mktemp("hybrid_codes")
    cfg = train_preset("tiny", steps=2, batch_size=2, num_points=128, ckpt_every=0, sample_every=0, log_every=1,
                       outfit_codes=True, body_shape=True)  # fmt: skip
    train(cfg, tiny_dataset, root / "gen", progress=False)
    out = root / "hybrid"
    assert main(["hybrid", "--attached", load_method(hybrid).config.sources["attached"], "--free", str(root / "gen"),
                 "--data", str(tiny_dataset), "--maps", str(hybrid / "maps.npz"), "--out", str(out)]) == 0  # fmt: skip
    return out


def _linked(hybrid, root):
    """A hybrid linking float32 exports of ``hybrid``'s two networks (``pocoloco hybrid --link``)."""
    copy = load_method(hybrid)
    for part, kind in (("attached", "pop"), ("free", "pocoloco")):
        assert main(["export-model", "--ckpt", copy.config.sources[part], "--out", str(root / kind),
                     "--dtype", "float32"]) == 0  # fmt: skip
    assert main(["hybrid", "--attached", str(root / "pop"), "--free", str(root / "pocoloco"), "--data",
                 str(copy.meta["data"]), "--maps", str(hybrid / "maps.npz"), "--link", "--no-progress", "--out",
                 str(root / "linked")]) == 0  # fmt: skip
    return root / "linked"


@pytest.mark.parametrize("generator", ["joints only", "outfit codes", "linked"])
def test_fit_adds_an_outfit_to_both_networks_and_the_maps(generator, hybrid, hybrid_with_codes, tiny_dataset, tmp_path,
                                                          capsys):  # fmt: skip
    """pocoloco fit on the hybrid: POP's features fitted to the scan, the generator's code (when it
    has outfit codes) to the scan's free-region points; the map from the scan's labels (the outfit
    codes case), else the start's (the mean map), with the scan's own free share; the new
    checkpoint samples the outfit. A linked hybrid's fit is saved as a copy of both networks (its
    POP is no longer the linked one's)."""
    ckpt = {"joints only": hybrid, "outfit codes": hybrid_with_codes}.get(generator)
    ckpt = ckpt or _linked(hybrid, tmp_path / "sources")
    labelled = generator == "outfit codes"
    s, seq, path = _frame(tiny_dataset, "skirt")
    fr = read_frame(path)
    idx = int(fr.frame_index)
    scan = tmp_path / "scan.ply"
    pick = np.sort(np.random.default_rng(0).choice(len(fr.points), 400, replace=False))  # a small scan: a fast test
    write_ply(scan, fr.points[pick], normals=fr.normals[pick], labels=fr.labels[pick] if labelled else None)
    out = tmp_path / "fitted"
    spec = f"{tiny_dataset}:{s}/test/{seq}/{idx}"
    assert main(["fit", "--model", "hybrid", "--ckpt", str(ckpt), "--scan", str(scan), "--frame", spec, "--steps", "3",
                 "--name", "new_skirt", "--start", "mean", "--out", str(out)]) == 0, capsys.readouterr().err  # fmt: skip
    old, new = load_method(ckpt), load_method(out)
    assert isinstance(new, HybridMethod) and new.outfit_names() == ["skirt", "tight", "new_skirt"]
    if labelled:
        votes = scan_vertex_votes(fr.points[pick], fr.labels[pick], fr.body_vertices, old.maps.margin)
        np.testing.assert_array_equal(new.maps.vertex_share[2], votes)
        assert new.maps.point_share[2] > 0.2  # the skirt hangs free
    else:
        np.testing.assert_allclose(new.maps.vertex_share[2], old.maps.vertex_share.mean(0), atol=1e-6)  # the mean map
    expect = point_regions(fr.points[pick], fr.body_vertices, new.maps.free(2)).mean()
    assert new.maps.point_share[2] == pytest.approx(expect if expect >= 0.02 else 0.0, abs=1e-6)
    assert new.model.attached.geom.shape[0] == 3  # POP's features grew; the trained ones are unchanged
    assert torch.equal(new.model.attached.geom[:2], old.model.attached.geom)
    if generator == "outfit codes":
        assert new.free.outfit_names() == [*old.free.outfit_names(), "new_skirt"]
        codes = new.model.free.who.outfit_embed.weight
        assert not torch.allclose(codes[-1], old.model.free.who.outfit_embed.weight.mean(0))  # fitted from the mean
    else:
        assert new.free.outfit_names() == []
    assert ("linked" in new.meta, new.meta.get("unlinked_from")) == (
        (False, {"attached": str(tmp_path / "sources" / "pop"), "free": str(tmp_path / "sources" / "pocoloco")})
        if generator == "linked" else (False, None))  # fmt: skip
    assert main(["sample", "--ckpt", str(out), "--outfit", "new_skirt", "--joints", spec, "--num", "2", "--points",
                 "200", "--steps", "2", "--no-render", "--out", str(tmp_path / "s")]) == 0  # fmt: skip


def test_fine_tune_stages_the_free_generator_and_a_rerun_goes_on_where_it_stopped(hybrid, tiny_dataset, tiny_run,
                                                                                   tmp_path, capsys):  # fmt: skip
    """pocoloco hybrid --fine-tune: maps, a free-region pack, a generator fine-tuned from --free in
    the shared loop, then the hybrid assembled with it; a rerun after the generator finished only
    assembles (and a finished folder is refused)."""
    attached = load_method(hybrid).config.sources["attached"]
    out = tmp_path / "tuned"
    argv = ["hybrid", "--attached", attached, "--free", str(tiny_run), "--data", str(tiny_dataset), "--out", str(out),
            "--every", "4", "--fine-tune", "0.02", "--pack-every", "2", "--pack-points", "64", "--no-progress"]  # fmt: skip
    # a kill after the generator finished, before the assembly: the rerun keeps the stages
    import pocoloco.cli.train as cli_train

    real = cli_train.assemble_hybrid
    cli_train.assemble_hybrid = lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt())
    try:
        assert main(argv) != 0 and "rerun the same command" in capsys.readouterr().err
    finally:
        cli_train.assemble_hybrid = real
    assert (out / "maps.npz").is_file() and (out / "free.pack").is_file() and (out / "free_generator" / "model").is_dir()
    stamp = (out / "free_generator" / "model").stat().st_mtime_ns
    pack = PackedDataset(out / "free.pack", "train")
    assert pack.normalisation is not None and len(pack) > 0
    assert main(argv) == 0, capsys.readouterr().err
    assert (out / "free_generator" / "model").stat().st_mtime_ns == stamp  # not trained again
    m = load_method(out)
    assert isinstance(m, HybridMethod) and m.config.sources["free"].endswith("free_generator/model")
    cfg = json.loads((out / "free_generator" / "config.json").read_text())
    assert cfg["init_from"].startswith(str(tiny_run)) and cfg["num_points"] == 64 and cfg["batch_size"] == 32
    capsys.readouterr()
    assert main(argv) == 2 and "already holds a checkpoint" in capsys.readouterr().err


def test_pop_points_are_drawn_by_the_body_area_their_pixels_stand_for(hybrid, tiny_dataset):
    """Each of POP's query pixels stands for its posed face's area / the face's pixel count (checked
    with a loop); area-weighted draws favour pixels that stand for more surface."""
    m = load_method(hybrid)
    _, _, path = _frame(tiny_dataset, "tight")
    fr = read_frame(path, allow_missing=True)
    pose = m.pose_from_frame(path, "tight", frame=fr)
    P = len(m.attached.model.query_points())
    areas = m._pixel_areas(pose, P)
    faces = np.asarray(m.attached.model.faces_np)
    qf = m.attached.model.q_face.cpu().numpy()
    v = fr.body_vertices.astype(np.float64)
    for i in (0, P // 2, P - 1):
        f = faces[qf[i]]
        area = 0.5 * np.linalg.norm(np.cross(v[f[1]] - v[f[0]], v[f[2]] - v[f[0]]))
        assert areas[i] == pytest.approx(area / sum(int(x == qf[i]) for x in qf), rel=1e-9)
    assert areas.sum() > 0
    pts = m.attached.predict(pose, P, seeds=(0,), outfit=m.outfit_id("tight")).points[0]
    uniform = m.config.replace(area_weighted=False)
    plain = HybridMethod(m.model, uniform, m.normalisation, m.path, m.step, m.meta)
    o = m.outfit_id("tight")
    free = np.zeros(len(fr.body_vertices), bool)
    tree_idx = {tuple(p): k for k, p in enumerate(pts)}
    picked_w = [areas[tree_idx[tuple(p)]] for p in m._skinned_points(pose, o, free, P // 3, 0)]
    picked_u = [areas[tree_idx[tuple(p)]] for p in plain._skinned_points(pose, o, free, P // 3, 0)]
    assert np.mean(picked_w) > 1.2 * np.mean(picked_u)


def test_a_linked_hybrid_holds_only_its_maps_and_draws_what_the_copy_draws(hybrid, tiny_dataset, tmp_path, capsys):
    """pocoloco hybrid --link: references to its two checkpoints (checked by digest) and the maps as
    bits; the same clouds as the hybrid holding copies; a source that changed or went is one line."""
    copy = load_method(hybrid)
    sources = tmp_path / "sources"
    for part, kind in (("attached", "pop"), ("free", "pocoloco")):
        assert main(["export-model", "--ckpt", copy.config.sources[part], "--out", str(sources / kind),
                     "--dtype", "float32"]) == 0  # fmt: skip
    argv = ["hybrid", "--attached", str(sources / "pop"), "--free", str(sources / "pocoloco"), "--data",
            str(tiny_dataset), "--maps", str(hybrid / "maps.npz"), "--generator-share", "1", "--link", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "linked")]) == 0
    linked = load_method(tmp_path / "linked")
    assert set(linked.meta["linked"]) == {"attached", "free"} and linked.config.sources["attached"] == str(sources / "pop")
    weights = sum(p.stat().st_size for p in linked.path.glob("*.safetensors"))
    assert weights < 0.1 * sum(p.stat().st_size for p in copy.path.glob("*.safetensors"))
    np.testing.assert_array_equal(linked.maps.vertex_share > 0.5, copy.maps.vertex_share > 0.5)
    _, _, path = _frame(tiny_dataset, "skirt")
    fr = read_frame(path, allow_missing=True)
    for m in (copy, linked):  # the copy at the linked one's settings: only the weights' source differs
        m.config = m.config.replace(generator_share=1.0, inside_tolerance=None)
    a, b = (m.predict(m.pose_from_frame(path, "skirt", frame=fr), 256, seeds=(0, 1), outfit=m.outfit_id("skirt"),
                      options=SamplerOptions(steps=2)).points for m in (copy, linked))  # fmt: skip
    np.testing.assert_allclose(a, b, atol=1e-6)
    # its maps serve a new assembly as they are (--maps CKPT): the same regions and point shares
    assert main([*argv, "--maps", str(tmp_path / "linked"), "--out", str(tmp_path / "again")]) == 0
    again = load_method(tmp_path / "again")
    np.testing.assert_array_equal(again.maps.vertex_share, linked.maps.vertex_share)
    np.testing.assert_array_equal(again.maps.point_share, linked.maps.point_share)
    with pytest.raises(ValueError, match="expected 'hybrid'"):
        FreeRegionMaps.load(sources / "pop")
    capsys.readouterr()
    import shutil

    shutil.rmtree(sources / "pop")  # the same model exported again, in another dtype: other weights
    assert main(["export-model", "--ckpt", copy.config.sources["attached"], "--out", str(sources / "pop")]) == 0
    capsys.readouterr()
    spec = f"{tiny_dataset}:skirt/test/{_frame(tiny_dataset, 'skirt')[1]}/0"
    sample = ["sample", "--ckpt", str(tmp_path / "linked"), "--joints", spec, "--points", "64", "--steps", "2",
              "--no-render", "--out", str(tmp_path / "s")]  # fmt: skip
    assert main(sample) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "has changed since" in err and "pocoloco hybrid" in err, err
    shutil.rmtree(sources / "pop")
    assert main(sample) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot be loaded" in err, err


def test_the_shipped_hybrid_links_the_shipped_pop_and_pocoloco():
    """default:hybrid: maps only (kilobytes), its networks those of default:pop and default."""
    from pocoloco.engine.shipped import default_checkpoint

    m = load_method(default_checkpoint("hybrid"))
    assert isinstance(m, HybridMethod)
    assert {p: r["ckpt"] for p, r in m.meta["linked"].items()} == {"attached": "default:pop", "free": "default"}
    assert (default_checkpoint("hybrid") / "model.safetensors").stat().st_size < 100_000
    o = m.outfit_id("skirt_a")  # sampled from the CLI with the shipped peers (test_peers.py)
    assert 0.2 < m.maps.point_share[o] < 0.8 and m.config.generator_share == 0.5
    assert m.maps.point_share[m.outfit_id("tight_a")] == 0


def test_with_far_the_free_region_takes_points_far_from_the_body_and_pop_keeps_the_rest(hybrid, tiny_dataset):
    """config.far: generated points farther than far from the body are kept whatever their nearest
    vertex, POP's attached points are the ones near an attached vertex, the hypotheses still share them."""
    ck = load_method(hybrid)
    m = HybridMethod(ck.model, ck.config.replace(far=0.05), ck.normalisation, ck.path, ck.step, ck.meta)
    _, _, path = _frame(tiny_dataset, "skirt")
    fr = read_frame(path, allow_missing=True)
    o = m.outfit_id("skirt")
    clouds = m.predict(m.pose_from_frame(path, "skirt", frame=fr), 300, seeds=(0, 1), outfit=o,
                       options=SamplerOptions(steps=2)).points  # fmt: skip
    n_att, _ = m.split(o, 300)
    free = m.maps.free(o)
    for pts in clouds:
        assert not point_regions(pts[:n_att], fr.body_vertices, free, far=0.05).any()
        assert point_regions(pts[n_att:], fr.body_vertices, free, far=0.05).all()
    np.testing.assert_array_equal(clouds[0, :n_att], clouds[1, :n_att])
    with pytest.raises(ValueError, match="far must be a distance"):
        ck.config.replace(far=0.0)


def test_with_trust_generated_points_stay_near_pops_own_points_in_the_free_region(hybrid, tiny_dataset):
    """config.trust: a generated point is kept only within trust of one of POP's points (at its
    training UV pixels) in the free region (checked by brute force on points around them); the
    attached points are untouched."""
    ck = load_method(hybrid)
    m = HybridMethod(ck.model, ck.config.replace(trust=0.05), ck.normalisation, ck.path, ck.step, ck.meta)
    _, _, path = _frame(tiny_dataset, "skirt")
    fr = read_frame(path, allow_missing=True)
    pose, o = m.pose_from_frame(path, "skirt", frame=fr), m.outfit_id("skirt")
    free = m.maps.free(o)
    pop = m.attached.predict(pose, len(m.attached.model.query_points()), seeds=(0,), outfit=o).points[0]
    ref = pop[point_regions(pop, fr.body_vertices, free)]
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(400, 3))
    pts = ref[rng.integers(len(ref), size=400)] + direction / np.linalg.norm(direction, axis=1, keepdims=True) * \
        rng.uniform(0.0, 0.12, size=(400, 1))  # fmt: skip
    d = np.array([np.linalg.norm(ref - x, axis=1).min() for x in pts])
    expected = point_regions(pts, fr.body_vertices, free) & (d <= 0.05)
    assert 0 < expected.sum() < 400
    np.testing.assert_array_equal(m._kept(pose, free, pts, None, m._reference(pose, o, free)), expected)
    assert ck._reference(pose, o, free) is None  # without trust: no reference
    clouds = m.predict(pose, 300, seeds=(0, 1), outfit=o, options=SamplerOptions(steps=2)).points
    plain = ck.predict(pose, 300, seeds=(0, 1), outfit=o, options=SamplerOptions(steps=2)).points
    n_att, _ = m.split(o, 300)
    np.testing.assert_array_equal(clouds[:, :n_att], plain[:, :n_att])
    calls = []  # POP runs once per prediction: both regions and the trust reference share its cloud
    predict = m.attached.predict
    m.attached.predict = lambda *a, **k: calls.append(a[1]) or predict(*a, **k)
    again = m.predict(pose, 300, seeds=(0, 1), outfit=o, options=SamplerOptions(steps=2)).points
    np.testing.assert_array_equal(again, clouds)
    assert calls == [len(m.attached.model.query_points())], calls
    with pytest.raises(ValueError, match="trust must be a distance"):
        ck.config.replace(trust=-1.0)
