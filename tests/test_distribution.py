"""The distribution judge's score (issue 40): the embedding energy score is proper, the Chamfer
energy score is not (its counterexamples, reproduced), and the statistics against references."""

import numpy as np
import pytest

from pocoloco.evaluation.distribution import (
    canonical_frame,
    chamfer_energy_counterexamples,
    embed_cloud,
    energy_distance,
    energy_score,
    expected_energy_score,
    probe_points,
)


def test_chamfer_energy_score_prefers_a_wrong_forecast_to_the_truth():
    squared, unsquared = chamfer_energy_counterexamples()
    assert squared["perfect"] == 0.0 and squared["wrong"] == pytest.approx(-0.125)
    assert unsquared["perfect"] == 0.0 and unsquared["wrong"] == pytest.approx(1.0 / 75.0 * -1.0, abs=1e-9)
    # the same forecasts under the energy score of an embedding (unsigned distance at probes on a
    # line): the truth wins, as a proper score must
    probes = np.linspace(-1.0, 4.0, 41)
    emb = lambda s: np.abs(probes[:, None] - np.asarray(s)[None]).min(1)  # noqa: E731
    d = lambda a, b: float(np.linalg.norm(emb(a) - emb(b)))  # noqa: E731
    for case in (squared, unsquared):
        assert expected_energy_score([(1.0, case["truth"])], case["truth"], d) == 0.0
        assert expected_energy_score(case["forecast"], case["truth"], d) > 0.01


def _swung_cylinder(swing: np.ndarray, rng, n: int = 1024) -> np.ndarray:
    """A 0.6 m cylinder hanging below the origin whose lower half is swung horizontally by
    ``swing`` (2,) metres at the hem (linearly from mid-height): a toy skirt in one state."""
    z = -rng.random(n) * 0.6
    phi = rng.random(n) * 2 * np.pi
    pts = np.stack([0.15 * np.cos(phi), 0.15 * np.sin(phi), z], 1)
    w = np.clip((-z - 0.3) / 0.3, 0.0, 1.0)[:, None]
    pts[:, :2] += w * swing[None]
    return pts


def test_the_embedding_energy_score_ranks_the_true_distribution_first():
    rng = np.random.default_rng(0)
    probes = probe_points(256, seed=0, box=((-0.45, 0.45), (-0.45, 0.45), (-0.7, 0.05)))

    def draw(scale: float, count: int) -> np.ndarray:  # swings: direction uniform, amplitude U(0, 0.2) m
        a = rng.random(count) * 0.2 * scale
        t = rng.random(count) * 2 * np.pi
        return np.stack([a * np.cos(t), a * np.sin(t)], 1)

    def embed(swings):
        return np.stack([embed_cloud(_swung_cylinder(s, rng), None, probes) for s in swings])

    truths = embed(draw(1.0, 40))
    forecasts = {
        "truth": lambda: embed(draw(1.0, 12)),
        "mean (point mass)": lambda: embed(np.zeros((1, 2))),
        "over-dispersed": lambda: embed(draw(2.0, 12)),
        "under-dispersed": lambda: embed(draw(0.4, 12)),
    }
    scores = {name: float(np.mean([energy_score(make(), y) for y in truths])) for name, make in forecasts.items()}
    best = min(scores, key=scores.get)
    assert best == "truth", scores
    for name, s in scores.items():
        if name != "truth":
            assert s > scores["truth"] * 1.05, scores


def test_energy_statistics_on_known_sets():
    refs = np.array([[0.0, 0.0], [2.0, 0.0]])
    point = np.array([[1.0, 0.0]])
    st = energy_distance(point, refs)
    assert st["to_refs"] == 1.0 and st["spread_samples"] == 0.0 and st["spread_refs"] == 2.0
    assert st["energy_distance"] == 0.0 and st["energy_score"] == 1.0
    same = energy_distance(refs, refs)  # spreads over distinct pairs; to_refs includes the zero self-pairs
    assert same["to_refs"] == 1.0 and same["spread_samples"] == 2.0
    # independent draws of one distribution: the unbiased energy distance is ~0; of two, clearly not
    rng = np.random.default_rng(3)
    a, b, c = rng.normal(size=(400, 5)), rng.normal(size=(400, 5)), rng.normal(size=(400, 5)) + 0.5
    assert abs(energy_distance(a, b)["energy_distance"]) < 0.02
    assert energy_distance(a, c)["energy_distance"] > 0.1
    assert energy_score(point, refs[0]) == 1.0  # a point mass has no spread term
    with pytest.raises(ValueError, match="features"):
        energy_score(np.zeros((2, 3)), np.zeros(4))


def test_embedding_lives_in_the_heading_frame():
    rng = np.random.default_rng(1)
    joints = rng.normal(size=(24, 3)) * 0.1
    joints[1] = [0.1, 0.0, 0.0]  # left hip (+X)
    joints[2] = [-0.1, 0.0, 0.0]
    joints[0] = [0.0, 0.0, 0.0]
    cloud = rng.normal(size=(500, 3)) * [0.2, 0.1, 0.5]
    probes = probe_points(64)
    base = embed_cloud(cloud, joints, probes)
    # the same body and cloud turned about the vertical and moved: the same embedding
    a = 0.7
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    shift = np.array([1.0, -2.0, 0.3])
    moved = embed_cloud(cloud @ rot.T + shift, joints @ rot.T + shift, probes)
    np.testing.assert_allclose(moved, base, atol=1e-9)
    root, r = canonical_frame(joints)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        embed_cloud(np.zeros((0, 3)), None, probes)


def test_pose_statistics_tell_a_sampler_from_a_regressor():
    from pocoloco.evaluation.distribution import pose_statistics, truth_rows

    rng = np.random.default_rng(5)
    probes = probe_points(128, seed=0, box=((-0.45, 0.45), (-0.45, 0.45), (-0.7, 0.05)))

    def states(count, scale=1.0):
        a = 0.1 + rng.random(count) * 0.1 * scale
        t = rng.random(count) * 2 * np.pi
        return [_swung_cylinder(np.array([x * np.cos(y), x * np.sin(y)]), rng, n=512) for x, y in zip(a, t)]

    refs = states(8)
    sampler = pose_statistics(states(8), refs, None, probes)
    regressor = pose_statistics([_swung_cylinder(np.zeros(2), rng, n=512)], refs, None, probes)
    assert sampler["energy_score"] < regressor["energy_score"]
    assert regressor["spread_samples"] == 0.0 and np.isnan(regressor["nna_samples"])
    assert regressor["cov"] == pytest.approx(1 / 8) and sampler["cov"] > 2 / 8
    assert regressor["nna_refs"] >= 0.5  # most true states' nearest other cloud is a true state
    assert 0.0 <= sampler["nna_refs"] <= 1.0 and 0.0 <= sampler["nna_samples"] <= 1.0
    assert sampler["spread_refs"] == regressor["spread_refs"] > 0
    assert sampler["mmd"] < regressor["mmd"]  # every true state has a sample near it
    oracle = truth_rows(refs, None, probes)
    assert oracle["truth_loo"]["energy_score"] < regressor["energy_score"]
    assert 0 <= oracle["refs_medoid"]["medoid"] < 8 and oracle["refs_medoid"]["spread_samples"] == 0.0
    # their Chamfer to the true states, as a model's: the mean over distinct pairs, and the medoid's to the others
    from pocoloco.evaluation.metrics import chamfer_cm

    pairs = [chamfer_cm(a, b) for i, a in enumerate(refs) for j, b in enumerate(refs) if i != j]
    assert oracle["truth_loo"]["chamfer_to_refs"] == pytest.approx(np.mean(pairs))
    m = int(oracle["refs_medoid"]["medoid"])
    assert oracle["refs_medoid"]["chamfer_to_refs"] == pytest.approx(np.mean([chamfer_cm(refs[m], b) for j, b in
                                                                               enumerate(refs) if j != m]))  # fmt: skip
    assert "chamfer_to_refs" not in truth_rows(refs, None, probes, chamfer=False)["truth_loo"]
    # the judge computes the true states' Chamfer matrix and embeddings once per pose and hands them to every
    # row: the same numbers
    from pocoloco.evaluation.distribution import chamfer_matrix, embed_cloud, embed_refs

    d_rr, e_rr = chamfer_matrix(refs, refs), embed_refs(refs, None, probes)
    np.testing.assert_array_equal(e_rr[1], embed_cloud(refs[1], None, probes))
    assert truth_rows(refs, None, probes, d_rr=d_rr) == oracle
    assert truth_rows(refs, None, probes, d_rr=d_rr, e_rr=e_rr) == oracle
    two = states(2)  # two samples: no NaN among the statistics, so the dicts compare exactly
    assert pose_statistics(two, refs, None, probes, d_rr=d_rr) == pose_statistics(two, refs, None, probes)
    assert pose_statistics(two, refs, None, probes, d_rr=d_rr, e_rr=e_rr) == pose_statistics(two, refs, None, probes)
    with pytest.raises(ValueError, match=">= 2 true states"):
        pose_statistics(refs[:1], refs[:1], None, probes)


def test_same_reference_set_tells_two_copies_of_a_set_apart():
    from pocoloco.evaluation.judge import same_reference_set

    def report(spreads: dict, row: str = "pocoloco") -> dict:
        return {"settings": {"probes": 4}, "per_pose": [
            {"subject": s, "sequence": "test_0000", "frame": f, "window": w,
             "rows": {row: {"spread_refs": v, "energy_score": 0.1}}} for (s, f, w), v in spreads.items()]}  # fmt: skip

    one = {("skirt_a", 3, "0"): 0.25, ("skirt_a", 3, "2"): 0.125, ("tight_a", 7, "0"): 0.0625}
    assert same_reference_set(report(one), report(one, row="pop")) is None  # another model, the same true states
    assert same_reference_set(report(one), report({("skirt_a", 3, "0"): 0.25})) is None  # a subset pairs
    why = same_reference_set(report(one), report({**one, ("skirt_a", 3, "2"): 0.126}))
    assert why is not None and "skirt_a test_0000/3 (2 s shared)" in why and "6.250 and 6.300 cm" in why
    assert "no pose" in same_reference_set(report(one), report({("dress_a", 1, "0"): 0.25}))
