"""The distribution judge (``pocoloco bench distribution``): every model against many true states.

A reference set (``pocoloco data histories``, :mod:`pocoloco.synth.histories`) holds, for each
pose and window of shared motion, K cloth states at exactly that pose plus the frame's own scan.
Each model draws M clouds per pose (a deterministic model one: a point mass, never copies); every
cloud — the model's and the true states' — is cut to the same point count, and scored with
:func:`pocoloco.evaluation.distribution.pose_statistics`: the **energy score** of the probe-distance
embedding (a proper score: lower is better, and the true distribution is best), the energy
distance, the spreads and the Chamfer-based coverage statistics. Oracle rows: ``truth_loo`` (one
true state scored against the others: a perfect sampler), ``refs_medoid`` (the best single guess
an oracle could make) and ``posed_body`` (the body without clothes, as a point mass).

Aggregated over poses per window with 95 % bootstrap intervals; the poses are resampled together
for every row (paired), and each row's energy score is also given as a difference to
``truth_loo``'s with its own interval.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pocoloco.data.format import DatasetLayout, read_card, read_frame
from pocoloco.data.poses import Pose
from pocoloco.engine.shipped import describe_checkpoint, resolve_ckpt_arg
from pocoloco.evaluation.distribution import chamfer_matrix, embed_refs, pose_statistics, probe_points, truth_rows
from pocoloco.methods import SamplerOptions, load_method
from pocoloco.synth.histories import reference_sets
from pocoloco.utils.atomic import jsonable, output_folder, write_json_atomic, write_text_atomic

__all__ = [
    "JUDGE_COLUMNS", "JUDGE_HISTORY_MODES", "ORACLE_ROWS", "bench_distribution", "bootstrap_means",
    "distribution_markdown", "same_reference_set",
]  # fmt: skip

#: oracle / baseline rows, always present
ORACLE_ROWS = {"truth_loo": "truth, leave one out (a perfect sampler)",
               "refs_medoid": "the medoid true state (the best single guess)",
               "posed_body": "posed body, no clothes"}  # fmt: skip
#: columns of distribution.md: key, header, format (embedding statistics in cm)
JUDGE_COLUMNS = (
    ("energy_score", "ES (cm) ↓", "{:.2f}"),
    ("es_minus_truth", "ES - truth (cm)", "{:+.2f}"),
    ("energy_distance", "energy dist. (cm)", "{:.2f}"),
    ("to_refs", "to truth (cm)", "{:.2f}"),
    ("spread_samples", "spread (cm)", "{:.2f}"),
    ("spread_refs", "truth spread (cm)", "{:.2f}"),
    ("chamfer_to_refs", "Chamfer to truth (cm)", "{:.2f}"),
    ("cov", "COV", "{:.2f}"),
    ("mmd", "MMD (cm)", "{:.2f}"),
    ("nna_refs", "1-NNA truth", "{:.2f}"),
    ("nna_samples", "1-NNA samples", "{:.2f}"),
)
#: the motion a --motion-window model is given by the judge: the frame's own where the true states share it, or none
JUDGE_HISTORY_MODES = ("dataset", "rest")
_EMBEDDING_KEYS = ("energy_score", "energy_distance", "to_refs", "spread_samples", "spread_refs")


def _subsample(points: np.ndarray, n: int, seed: int) -> np.ndarray:
    """``n`` points of a cloud (all of them, in a seeded order, when it has fewer: never repeats)."""
    rng = np.random.default_rng(seed)
    idx = rng.permutation(len(points))[:n]
    return np.asarray(points, np.float64)[idx]


def bootstrap_means(values: np.ndarray, indices: np.ndarray) -> tuple[float, float, float]:
    """Mean of ``values`` (P,) over poses (NaN ignored) and its 95 % interval over the bootstrap
    resamples ``indices`` (B, P) (the same resamples for every row: paired)."""
    v = np.asarray(values, np.float64)
    with np.errstate(invalid="ignore"):
        boots = np.nanmean(v[indices], axis=1) if np.isfinite(v).any() else np.full(len(indices), np.nan)
    mean = float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")
    if not np.isfinite(boots).any():
        return mean, float("nan"), float("nan")
    lo, hi = np.nanpercentile(boots, [2.5, 97.5])
    return mean, float(lo), float(hi)


def bench_distribution(
    refs: str | Path,
    ckpts: Mapping[str, str | Path],
    out: str | Path,
    *,
    samples: int = 16,
    points: int = 2048,
    probes: int = 512,
    seed: int = 0,
    bootstrap: int = 1000,
    device: str = "cpu",
    sampler: str = "dpm++sde",
    steps: int | None = None,
    outfits: Mapping[str, str] | None = None,
    history: str = "dataset",
    finish_t: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Score every model of ``ckpts`` (row name -> checkpoint, ``default:...`` names allowed) on the
    reference set ``refs``; write ``distribution.json`` and ``distribution.md`` into ``out``.

    outfits: subject -> the outfit models with outfits draw it in (default: the subject's own name,
    which a model trained on another dataset may not have). progress: ``callable(done_poses,
    total_poses)``. A motion-aware model (``--motion-window W``) is given the frame's own window
    where the reference set's shared seconds cover W (every true state went through that motion),
    and none (the body at rest) where they do not; ``history="rest"`` gives it none anywhere (the
    same network without its window: what the window adds); pose-only models draw once for all windows.
    finish_t: the generative models' own finishing call (``SamplerOptions.finish_t``; None: off).
    JSON: ``rows[NAME][WINDOW]`` (WINDOW = shared seconds as text, "0", "2") -> statistic ->
    ``{"mean", "lo", "hi"}``, embedding statistics in cm per probe; ``per_pose``: every pose's
    statistics, its embedding ones (``_EMBEDDING_KEYS``) as raw Euclidean distances in metres over
    the P probes (x 100 / sqrt(P) gives the rows' cm per probe), Chamfer ones in cm; ``settings``.
    Returns it."""
    if history not in JUDGE_HISTORY_MODES:
        raise ValueError(f"--history must be {' or '.join(JUDGE_HISTORY_MODES)} for the judge (a reference set's "
                         f"true states share their frame's own motion), got {history!r}")  # fmt: skip
    if samples < 2:
        raise ValueError(f"--samples must be >= 2 (a generative model's spread needs two), got {samples}")
    if points < 16 or probes < 8:
        raise ValueError(f"--points must be >= 16 and --probes >= 8, got {points} and {probes}")
    pairs = reference_sets(refs)
    card = read_card(refs)
    hist = card["histories"]
    out = output_folder(out)
    probe = probe_points(probes, seed=seed)
    methods = {}
    for name, ckpt in ckpts.items():
        path = resolve_ckpt_arg(str(ckpt))
        methods[name] = (load_method(path, device=device), path)
        if not methods[name][0].deterministic:  # a bad sampler / steps / finish_t: one line, before any work
            methods[name][0].check_options(SamplerOptions(sampler=sampler, steps=steps, finish_t=finish_t))
    poses: dict[tuple, list[dict]] = {}
    for p in pairs:
        poses.setdefault((p["subject"], p["source"]["sequence"], p["source"]["frame"]), []).append(p)
    per_pose: list[dict[str, Any]] = []
    seconds: dict[str, float] = {name: 0.0 for name in methods}
    for pose_index, (key, windows) in enumerate(poses.items()):
        subject = key[0]
        own_path = windows[0]["own"]
        own = read_frame(own_path)
        joints = own.joints
        spec = f"{Path(refs)}:{subject}/{windows[0]['split']}/{windows[0]['sequence']}/{hist['histories']}"
        pose = Pose.load(spec)
        drawn: dict[tuple[str, str], list[np.ndarray]] = {}  # (model, window) -> its clouds
        if progress:
            progress(pose_index, len(poses))
        source_frame = DatasetLayout(hist["source"]).frame_path(subject, hist["split"], key[1], int(key[2]))
        for name, (method, _) in methods.items():
            seeds = [0] if method.deterministic else [seed * 100_003 + pose_index * 1_000 + i for i in range(samples)]
            kwargs = {} if method.deterministic else {"sampler": sampler, "steps": steps, "finish_t": finish_t}
            outfit = (outfits or {}).get(subject)  # None: the pose's own subject
            for w in windows:
                # a motion-aware model sees the frame's own motion where every true state shares it
                # (the window's shared seconds cover the model's), else the body at rest
                sees = history == "dataset" and bool(method.motion_window) and w["shared_seconds"] >= method.motion_window
                pose.motion = method.motion_of_frame(source_frame) if sees else None
                fixed = not method.motion_window or history == "rest"  # the same clouds for every window
                same = next((c for (n, _), c in drawn.items() if n == name), None) if fixed else None
                t0 = time.perf_counter()
                clouds = same if same is not None else [
                    np.asarray(c, np.float64) for c in method.sample(pose, points, seeds, outfit=outfit, **kwargs).points]
                seconds[name] += time.perf_counter() - t0
                drawn[(name, f"{w['shared_seconds']:g}")] = clouds
        body = [_subsample(own.body_vertices, points, seed)]
        for w in windows:
            members = [*w["refs"], w["own"]]
            truth = [_subsample(read_frame(f, ["points"]).points, points, seed + 7 * i) for i, f in enumerate(members)]
            row: dict[str, Any] = {"subject": subject, "sequence": key[1], "frame": key[2],
                                   "window": f"{w['shared_seconds']:g}", "rows": {}}  # fmt: skip
            here = {n: c for (n, win), c in drawn.items() if win == row["window"]}
            # the true states' Chamfer matrix and embeddings, once for every row of the pose
            d_rr, e_rr = chamfer_matrix(truth, truth), embed_refs(truth, joints, probe)
            for name, clouds in {**here, "posed_body": body}.items():
                row["rows"][name] = pose_statistics(clouds, truth, joints, probe, d_rr=d_rr, e_rr=e_rr)
            oracle = truth_rows(truth, joints, probe, d_rr=d_rr, e_rr=e_rr)
            for stats in oracle.values():  # the true states' spread, as in every other row (not the K - 1's)
                stats["spread_refs"] = row["rows"]["posed_body"]["spread_refs"]
            row["rows"].update(oracle)
            per_pose.append(row)
    if progress:
        progress(len(poses), len(poses))
    report = _aggregate(per_pose, list(methods), bootstrap, seed, probes)
    kinds = {name: (info or {}).get("garment_kind") or "none" for name, info in card["subjects"].items()}
    report["by_garment"] = by_garment(per_pose, kinds, [*methods, *ORACLE_ROWS], probes)
    report["settings"] = {
        "refs": str(refs), "split": hist["split"], "poses": len(poses), "histories": hist["histories"],
        "true_states_per_pose": hist["histories"] + 1, "windows": [f"{s:g}" for s in hist["shared_seconds"]],
        "samples": samples, "points": points, "probes": probes, "seed": seed, "bootstrap": bootstrap,
        "sampler": sampler, "steps": steps, **({"finish_t": finish_t} if finish_t is not None else {}),
        "outfits": dict(outfits or {}),
        "checkpoints": {n: describe_checkpoint(p) for n, (_, p) in methods.items()},
        "motion_windows": {n: m.motion_window for n, (m, _) in methods.items() if m.motion_window}, "history": history,
        "seconds_sampling": seconds,
    }  # fmt: skip
    report["per_pose"] = per_pose
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "distribution.json", jsonable(report, digits=6), indent=None)
    write_text_atomic(out / "distribution.md", distribution_markdown(report))
    return report


def _embedding_cm(probes: int) -> float:
    """cm per probe of a ``per_pose`` embedding statistic (a Euclidean distance in metres over the P
    probes): 100 / sqrt(P), the rows' fixed scale."""
    return 100.0 / float(np.sqrt(probes))


def same_reference_set(a: Mapping[str, Any], b: Mapping[str, Any], rtol: float = 1e-5) -> str | None:
    """Whether two ``bench_distribution`` reports were judged on the same copy of a reference set,
    so that their poses may be paired. A pose's true states are the same for every model, and so is
    their spread (``spread_refs``, any row); a set made again from the same seeds on another kind
    of machine is not bit-identical (chaotic cloth) and shows in it. Returns None when every pose
    both hold agrees within ``rtol``, else a one-line reason naming the first pose that does not
    (or that they share no pose)."""
    def truth_spread(report: Mapping[str, Any]) -> dict[tuple, float]:
        out = {}
        for p in report.get("per_pose", []):
            spreads = [r["spread_refs"] for r in p["rows"].values() if "spread_refs" in r]
            if spreads:
                out[(p["subject"], p["sequence"], p["frame"], p["window"])] = float(spreads[0])
        return out

    sa, sb = truth_spread(a), truth_spread(b)
    common = sorted(set(sa) & set(sb))
    if not common:
        return "the two reports share no pose (judged on different reference sets)"
    for key in common:
        if abs(sa[key] - sb[key]) > rtol * max(abs(sa[key]), abs(sb[key]), 1e-12):
            subject, sequence, frame, window = key
            cm = _embedding_cm(a.get("settings", {}).get("probes", 1))
            return (f"the two reports were judged on different copies of a reference set: {subject} {sequence}/{frame} "
                    f"({window} s shared) has true states {cm * sa[key]:.3f} and {cm * sb[key]:.3f} cm apart; "
                    "judge both models on the same set")  # fmt: skip
    return None


def _aggregate(per_pose: list[dict], models: list[str], bootstrap: int, seed: int, probes: int) -> dict[str, Any]:
    """Means over poses with paired bootstrap intervals. Embedding statistics are reported in cm
    per probe (the Euclidean distance of two embeddings / sqrt(P): a fixed scale, so still proper)."""
    emb_scale = _embedding_cm(probes)
    windows = sorted({r["window"] for r in per_pose}, key=float)
    names = [*models, *ORACLE_ROWS]
    rows: dict[str, dict[str, dict]] = {n: {} for n in names}
    for w in windows:
        mine = [r for r in per_pose if r["window"] == w]
        idx = np.random.default_rng([seed, 11]).integers(0, len(mine), (bootstrap, len(mine)))
        truth_es = np.array([r["rows"]["truth_loo"]["energy_score"] for r in mine])
        for n in names:
            stats = {}
            keys = sorted({k for r in mine for k in r["rows"][n]})
            for k in keys:
                v = np.array([r["rows"][n].get(k, np.nan) for r in mine], np.float64)
                scale = emb_scale if k in _EMBEDDING_KEYS else 1.0
                m, lo, hi = bootstrap_means(v * scale, idx)
                stats[k] = {"mean": m, "lo": lo, "hi": hi}
            es = np.array([r["rows"][n]["energy_score"] for r in mine]) - truth_es
            m, lo, hi = bootstrap_means(es * emb_scale, idx)
            stats["es_minus_truth"] = {"mean": m, "lo": lo, "hi": hi}
            rows[n][w] = stats
    return {"rows": rows, "windows": windows}


def by_garment(per_pose: list[dict], kinds: Mapping[str, str], names: list[str], probes: int) -> dict[str, Any]:
    """Per garment kind (``kinds``: subject -> kind, e.g. "tight"; "none" where the card names none)
    and window: the number of poses, the true states' spread (how uncertain the garment is at the
    pose: its floor for every per-frame score) and each row's energy score, means over the kind's
    poses, in cm per probe.
    ``{kind: {window: {"poses", "spread_refs", "energy_score": {name: mean}}}}``."""
    emb_scale = _embedding_cm(probes)
    out: dict[str, Any] = {}
    for kind in sorted({kinds.get(r["subject"], "none") for r in per_pose}):
        out[kind] = {}
        for w in sorted({r["window"] for r in per_pose}, key=float):
            mine = [r for r in per_pose if r["window"] == w and kinds.get(r["subject"], "none") == kind]
            if not mine:
                continue
            out[kind][w] = {
                "poses": len(mine),
                "spread_refs": float(np.mean([r["rows"]["posed_body"]["spread_refs"] for r in mine]) * emb_scale),
                "energy_score": {n: float(np.mean([r["rows"][n]["energy_score"] for r in mine]) * emb_scale)
                                 for n in names if all(n in r["rows"] for r in mine)},
            }  # fmt: skip
    return out


def distribution_markdown(report: dict[str, Any]) -> str:
    """One table per window: every row's statistics (mean [95 % interval] for the energy score)."""
    s = report["settings"]
    lines = [f"# Distribution judge: {s['poses']} {s['split']} poses x {s['true_states_per_pose']} true states",
             "", f"`{s['refs']}`; {s['samples']} samples per generative model (a deterministic model: one cloud), "
             f"{s['points']} points per cloud, {s['probes']} probes. ES: energy score of the probe-distance "
             "embedding (a proper score, lower is better; the truth itself, `truth_loo`, is the floor); "
             "embedding distances in cm RMS over the probes, Chamfer statistics in cm. "
             "Intervals: 95 % paired bootstrap over poses.", ""]  # fmt: skip
    for w in report["windows"]:
        lines += [f"## Shared motion before the frame: {w} s", "",
                  "| row | " + " | ".join(h for _, h, _ in JUDGE_COLUMNS) + " |",
                  "|---|" + "---|" * len(JUDGE_COLUMNS)]  # fmt: skip
        order = sorted(report["rows"], key=lambda n: report["rows"][n][w]["energy_score"]["mean"])
        for n in order:
            st = report["rows"][n][w]
            cells = []
            for k, _, fmt in JUDGE_COLUMNS:
                v = st.get(k)
                if v is None or not np.isfinite(v["mean"]):
                    cells.append("-")
                elif k in ("energy_score", "es_minus_truth"):
                    cells.append(f"{fmt.format(v['mean'])} [{v['lo']:.2f}, {v['hi']:.2f}]")
                else:
                    cells.append(fmt.format(v["mean"]))
            lines.append(f"| {ORACLE_ROWS.get(n, n)} | " + " | ".join(cells) + " |")
        lines.append("")
    garments = report.get("by_garment")
    if garments:
        windows = report["windows"]
        models = [n for n in report["rows"] if n not in ORACLE_ROWS]
        lines += ["## Per garment kind", "",
                  "How far apart the true states are (truth spread, cm) with each window, and each row's ES "
                  "(cm; means over the kind's poses, no intervals: few poses each).", "",
                  "| garment | poses | " + " | ".join(f"truth spread {w} s" for w in windows) + " | "
                  + " | ".join(f"{n} ES {w} s" for n in ["truth_loo", *models] for w in windows) + " |",
                  "|---|---|" + "---|" * (len(windows) * (2 + len(models)))]  # fmt: skip
        for kind, per_w in garments.items():
            cells = [kind, str(max(v["poses"] for v in per_w.values()))]
            cells += [f"{per_w[w]['spread_refs']:.2f}" if w in per_w else "-" for w in windows]
            for n in ["truth_loo", *models]:
                cells += [f"{per_w[w]['energy_score'][n]:.2f}" if w in per_w and n in per_w[w]["energy_score"]
                          else "-" for w in windows]  # fmt: skip
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)
