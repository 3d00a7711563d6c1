"""The quality bench (``pocoloco bench quality``): PocoLoco, POP, CloSET and CloSET without
decomposition on the same test frames, with the nearest-frame and posed-body baselines, in one table.

Every model goes through :func:`pocoloco.evaluation.evaluate.evaluate` with the same :class:`EvalSettings`,
so the frames, the GT subsets (fixed seeds per frame) and the metrics are identical across rows;
the baselines are computed once (a baselines-only pass over the same frames). Checkpoints are given
(``--ckpt-pocoloco`` ...); the command's ``--train-steps K`` trains the missing rows first
(:mod:`pocoloco.cli.evaluate`; this layer evaluates, it does not train); a model with neither is
left out.

Output (``--out``): ``quality.json`` (settings, checkpoints, the mean table, per-subject tables,
per-frame rows of every model, with best of K and the energy score per frame), ``quality.md`` (for
all frames and per subject the main table and the garment / rest / F-score table, and the papers'
two claims checked on these numbers) and ``quality.png`` (one test pose per subject, every model
side by side, points coloured by the label of their nearest GT point, rendered by :mod:`pocoloco.viz.render`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from pocoloco.data.format import DatasetLayout, read_card
from pocoloco.engine.checkpoint import (
    check_model_kind,
    read_meta,
    resolve_checkpoint,
)
from pocoloco.engine.shipped import describe_checkpoint, resolve_ckpt_arg
from pocoloco.evaluation.evaluate import (
    FAIR_NOTE,
    GARMENT_COLUMNS,
    TABLE_COLUMNS,
    EvalSettings,
    evaluate,
    markdown_table,
)
from pocoloco.evaluation.metrics import nearest
from pocoloco.utils.atomic import (
    jsonable,
    output_folder,
    write_json_atomic,
    write_text_atomic,
)
from pocoloco.viz.render import render_grid

__all__ = ["BASELINE_ROWS", "COLUMNS", "GARMENT_COLUMNS", "PER_SUBJECT_ROWS", "QUALITY_ROWS", "TARGETS", "UNTRAINED_ROWS", "bench_quality",
           "check_claims", "check_targets", "garment_table_markdown", "quality_markdown", "table_markdown"]

#: model rows: key -> (title, model kind, decomposition)
QUALITY_ROWS: dict[str, tuple[str, str, bool | None]] = {
    "pocoloco": ("PocoLoco", "pocoloco", None),
    "pocoloco_per_subject": ("PocoLoco, a model per subject (paper)", "pocoloco", None),
    "pop": ("POP", "pop", None),
    "closet": ("CloSET", "closet", True),
    "closet_nodecomp": ("CloSET (no decomposition)", "closet", False),
    "hybrid": ("Hybrid (POP attached + PocoLoco free)", "hybrid", None),
}
BASELINE_ROWS = {"nearest_frame": "nearest training frame", "posed_body": "posed body (no clothes)",
                 "gt_resample": "GT resample (noise floor)"}  # fmt: skip
#: rows given as several checkpoints, one per subject (each trained with ``--subjects``)
PER_SUBJECT_ROWS = ("pocoloco_per_subject",)
#: rows ``bench quality --train-steps`` does not train (a hybrid is assembled: ``pocoloco hybrid``)
UNTRAINED_ROWS = (*PER_SUBJECT_ROWS, "hybrid")
#: columns of quality.md: evaluate's (same keys, headers, formats) minus the split diversity, plus
#: time (finer: the peers take fractions of a second) and parameter count; the second table
#: (garment / rest split, F-scores at 1 and 2 cm) has evaluate's ``GARMENT_COLUMNS``
COLUMNS = (
    *(c for c in TABLE_COLUMNS if c[0] not in ("fscore_pct", "diversity_garment_cm", "diversity_body_cm",
                                              "seconds_per_sample")),
    ("seconds_per_sample", "s/sample", "{:.3f}"),
    ("num_parameters", "params", "{:,.0f}"),
)


def _check_kind(key: str, ckpt) -> Path:
    """The checkpoint folder of ``ckpt`` after checking it is the model ``key`` expects (one-line errors)."""
    path = resolve_checkpoint(resolve_ckpt_arg(ckpt))  # "default" = the shipped PocoLoco model
    meta = read_meta(path)
    title, kind, decomposition = QUALITY_ROWS[key]
    check_model_kind(path, meta["model_kind"], kind, f"--ckpt-{key.replace('_', '-')}")
    if decomposition is not None:
        has = bool(meta["config"].get("net", {}).get("decomposition", True))
        if has != decomposition:
            other = "--ckpt-closet" if has else "--ckpt-closet-nodecomp"
            raise ValueError(f"{path}: CloSET checkpoint {'with' if has else 'without'} decomposition given to "
                             f"--ckpt-{key.replace('_', '-')}; pass it to {other}")  # fmt: skip
    return path


def _check_per_subject(key: str, ckpts) -> dict[str, Path]:
    """subject -> checkpoint folder for a per-subject row: each checkpoint must be of the row's model
    and trained on named subjects (``pocoloco train --subjects``); a subject claimed twice is an error."""
    if isinstance(ckpts, (str, Path)):
        ckpts = [ckpts]
    out: dict[str, Path] = {}
    for ckpt in ckpts:
        path = _check_kind(key, ckpt)
        subjects = read_meta(path)["config"].get("subjects")
        if not subjects:
            raise ValueError(f"{path}: trained on every subject of its dataset; --ckpt-{key.replace('_', '-')} takes "
                             "models trained with --subjects (one per subject, as the paper)")  # fmt: skip
        for s in subjects:
            if s in out:
                raise ValueError(f"two models for subject {s!r} ({out[s]}, {path}) in --ckpt-{key.replace('_', '-')}")
            out[s] = path
    return out


def check_quality_inputs(data, ckpts: dict[str, Any], settings: EvalSettings = EvalSettings()) -> dict[str, Any]:
    """Everything :func:`bench_quality` would refuse, before any long work (training the missing rows
    included): the dataset, the split's frames, the row keys and each given checkpoint's kind.
    Returns row key -> checkpoint path (per-subject rows: subject -> path) for the rows given."""
    unknown = sorted(set(ckpts) - set(QUALITY_ROWS))
    if unknown:
        raise ValueError(f"unknown model rows {unknown}; choose from {', '.join(QUALITY_ROWS)}")
    read_card(data)  # not a dataset: that first
    layout = DatasetLayout(data)
    if not layout.iter_frames(settings.split, list(settings.subjects) if settings.subjects else layout.subjects()):
        raise ValueError(f"{data}: no frames in split {settings.split!r}")  # before a word is printed
    paths: dict[str, Any] = {}
    for key in QUALITY_ROWS:
        if ckpts.get(key) is not None:
            paths[key] = _check_per_subject(key, ckpts[key]) if key in PER_SUBJECT_ROWS else _check_kind(key, ckpts[key])
    return paths


def bench_quality(
    data,
    ckpts: dict[str, Any],
    out,
    settings: EvalSettings = EvalSettings(),
    *,
    trained: dict[str, Any] | None = None,
    device: str = "cpu",
    progress=None,
) -> dict[str, Any]:
    """Evaluate every row on the same frames and write quality.json / quality.md / quality.png.

    ckpts: row key (``QUALITY_ROWS``) -> checkpoint path or None (checked by
    :func:`check_quality_inputs`). trained: what the caller trained for this table, recorded in the
    settings (``{"rows": [keys], "train_steps": K, "train_preset": name}``; the ``pocoloco bench
    quality --train-steps`` command trains the missing rows before calling this). progress:
    ``callable(message)``. Returns the quality.json dict.
    """
    paths = check_quality_inputs(data, ckpts, settings)
    if not paths:
        raise ValueError("no model to compare: give --ckpt-pocoloco / --ckpt-pop / --ckpt-closet / "
                         "--ckpt-closet-nodecomp, or --train-steps K with --work DIR")  # fmt: skip
    out = output_folder(out)
    trained = trained or {}

    if progress:
        progress("baselines")
    base, base_examples = evaluate(None, data, settings, device=device, keep_examples=10**9)
    results: dict[str, Any] = {}
    examples: dict[str, list[dict[str, Any]]] = {}
    no_baselines = EvalSettings(**{**settings.__dict__, "baselines": ()})
    for key, path in paths.items():
        if progress:
            progress(f"evaluating {QUALITY_ROWS[key][0]} ({path})")
        t0 = time.perf_counter()
        res, ex = evaluate(path, data, no_baselines, device=device, keep_examples=10**9)
        results[key] = (res, time.perf_counter() - t0)
        examples[key] = ex

    def row_means(key: str, means: dict[str, float], res) -> dict[str, float]:
        return {**means, "num_parameters": float(res.settings["num_parameters"])}

    table: dict[str, dict[str, float]] = {}
    for key, (res, _) in results.items():
        table[key] = row_means(key, res.means["model"], res)
    for b in BASELINE_ROWS:
        if b in base.means:
            table[b] = dict(base.means[b])
    subjects = sorted(base.per_subject)
    per_subject: dict[str, dict[str, dict[str, float]]] = {}
    for s in subjects:
        per_subject[s] = {key: row_means(key, res.per_subject[s]["model"], res) for key, (res, _) in results.items()}
        per_subject[s].update({b: dict(base.per_subject[s][b]) for b in BASELINE_ROWS if b in base.per_subject[s]})

    report = {
        "settings": {**base.settings, "rows": {k: QUALITY_ROWS[k][0] for k in results},
                     "trained_here": list(trained.get("rows", [])), "train_steps": trained.get("train_steps"),
                     "train_preset": trained.get("train_preset") if trained.get("rows") else None},
        "checkpoints": {k: {"path": ({s: describe_checkpoint(q) for s, q in p.items()} if isinstance(p, dict)
                                     else describe_checkpoint(p)), "step": results[k][0].settings["step"],
                            "preset": results[k][0].settings["preset"], "eval_seconds": results[k][1]}
                        for k, p in paths.items()},
        "means": table,
        "per_subject": per_subject,
        "claims": check_claims(per_subject),
        "targets": check_targets(table, per_subject),
        "frames": {k: res.frames for k, (res, _) in results.items()} | {"baselines": base.frames},
    }  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "quality.json", jsonable(report), indent=None)  # per-frame rows: compact
    write_text_atomic(out / "quality.md", quality_markdown(report))
    render_comparison(base_examples, examples, out / "quality.png")
    return report

#: what PocoLoco should reach on this table (``check_targets``): a subject is *loose* when its GT loose
#: share is above ``loose_subject_pct``, *tight* otherwise
TARGETS = {
    "loose_subject_pct": 5.0,  # GT loose share (%) above which a subject counts as wearing a loose garment
    "tight_margin_cm": 0.3,  # tight subjects: PocoLoco's Chamfer at most this much above the posed body's
    "max_far_pct": 1.0,  # no invented garments: every cloud <= this share (%) of points > 10 cm off
    "loose_share_points": 3.0,  # loose subjects: |loose % - GT loose %| <= this (percentage points)
}


def check_targets(means: dict[str, dict[str, float]],
                  per_subject: dict[str, dict[str, dict[str, float]]]) -> list[dict[str, Any]]:  # fmt: skip
    """PocoLoco against the peers and the posed body, per target of ``TARGETS``:

    - Chamfer <= POP's and <= CloSET's overall and on every loose subject;
    - on every tight subject, Chamfer <= the posed body's + ``tight_margin_cm``;
    - on every frame and seed, at most ``max_far_pct`` % of the points > 10 cm from the scan;
    - on every loose subject, the loose share within ``loose_share_points`` of the GT's.

    Returns ``[{"target", "subject", "value", "bound", "holds"}]``; empty without a PocoLoco row.
    """
    if "pocoloco" not in means:
        return []
    out: list[dict[str, Any]] = []

    def add(target: str, subject: str, value: float, bound: float) -> None:
        out.append({"target": target, "subject": subject, "value": float(value), "bound": float(bound),
                    "holds": bool(value <= bound + 1e-9)})  # fmt: skip

    scopes = [("all", means)] + [(s, rows) for s, rows in per_subject.items()]
    for subject, rows in scopes:
        if "pocoloco" not in rows:
            continue
        poco = rows["pocoloco"]
        gt_loose = next((r["loose_gt_pct"] for r in rows.values() if "loose_gt_pct" in r), None)
        loose = subject == "all" or (gt_loose is not None and gt_loose > TARGETS["loose_subject_pct"])
        if loose:
            for peer in ("pop", "closet"):
                if peer in rows:
                    add(f"Chamfer <= {_title(peer)}", subject, poco["chamfer_cm"], rows[peer]["chamfer_cm"])
            if subject != "all" and "loose_pred_pct" in poco:
                add(f"loose share within {TARGETS['loose_share_points']:g} points of GT", subject,
                    abs(poco["loose_pred_pct"] - gt_loose), TARGETS["loose_share_points"])  # fmt: skip
        elif "posed_body" in rows:
            add(f"Chamfer <= posed body + {TARGETS['tight_margin_cm']:g} cm", subject, poco["chamfer_cm"],
                rows["posed_body"]["chamfer_cm"] + TARGETS["tight_margin_cm"])  # fmt: skip
        if "outlier_10cm_pct_max" in poco:
            add(f"every cloud <= {TARGETS['max_far_pct']:g} % of points > 10 cm off", subject,
                poco["outlier_10cm_pct_max"], TARGETS["max_far_pct"])  # fmt: skip
    return out


def _title(key: str) -> str:
    return QUALITY_ROWS[key][0] if key in QUALITY_ROWS else BASELINE_ROWS.get(key, key)


def table_markdown(rows: dict[str, dict[str, float]]) -> str:
    return markdown_table(rows, {key: _title(key) for key in rows}, columns=COLUMNS, first="model")


def garment_table_markdown(rows: dict[str, dict[str, float]]) -> str:
    """The second table: S2M / M2S on the garment and the rest, F-scores at 1 and 2 cm ("" when no row has them)."""
    if not any(k in r for k, _, _ in GARMENT_COLUMNS for r in rows.values()):
        return ""
    return markdown_table(rows, {key: _title(key) for key in rows}, columns=GARMENT_COLUMNS, first="model")


def _tables(rows: dict[str, dict[str, float]]) -> list[str]:
    garment = garment_table_markdown(rows)
    return [table_markdown(rows)] + (["", garment] if garment else [])


def check_claims(per_subject: dict[str, dict[str, dict[str, float]]]) -> list[dict[str, Any]]:
    """The papers' two claims on this data, computed from the per-subject tables:

    1. PocoLoco: POP puts too few points on a loose skirt (its loose share is further below
       the GT's than PocoLoco's), on the subject with the largest GT loose share.
    2. CloSET: the template decomposition lowers the Chamfer on the loose garment (same subject).
    """
    claims: list[dict[str, Any]] = []
    loose = [(r["loose_gt_pct"], s) for s, m in per_subject.items() for r in m.values() if "loose_gt_pct" in r]
    if not loose:
        return claims
    _, s = max(loose)
    rows = per_subject[s]
    gt = next(r["loose_gt_pct"] for r in rows.values() if "loose_gt_pct" in r)
    if "pop" in rows and "pocoloco" in rows:
        pop, poco = rows["pop"].get("loose_pred_pct"), rows["pocoloco"].get("loose_pred_pct")
        if pop is not None and poco is not None:
            holds = pop < gt and abs(poco - gt) < abs(pop - gt)
            claims.append({"claim": f"POP under-covers the loose garment ({s}) compared with PocoLoco",
                           "subject": s, "gt_loose_pct": gt, "pop_loose_pct": pop, "pocoloco_loose_pct": poco,
                           "holds": bool(holds)})  # fmt: skip
    if "closet" in rows and "closet_nodecomp" in rows:
        a, b = rows["closet"]["chamfer_cm"], rows["closet_nodecomp"]["chamfer_cm"]
        claims.append({"claim": f"template decomposition lowers CloSET's Chamfer on the loose garment ({s})",
                       "subject": s, "closet_chamfer_cm": a, "closet_nodecomp_chamfer_cm": b,
                       "holds": bool(a < b)})  # fmt: skip
    return claims


def quality_markdown(report: dict[str, Any]) -> str:
    s = report["settings"]
    lines = ["# pocoloco bench quality", "",
             f"Data `{s['data']}`, split `{s['split']}`: the same {len(report['frames']['baselines'])} frames and GT "
             f"subsets ({s['num_points']} points) for every row. PocoLoco: mean over seeds {s['seeds']} "
             f"({s['sampler']}); POP / CloSET are deterministic (one cloud per frame, diversity 0)."
             + (" Model points evenly spread (`--even`; energy scores are then not comparable with those of random layouts)."
                if s.get("even") else ""), "",
             "Chamfer = S2M + M2S (unsquared, cm); CD 1e-4 m^2 = POP convention (squared, point-to-plane M2S); "
             "normal = L1 of unit normals x10; >5cm / >10cm % = share of generated points farther than that from "
             "every GT point (mean; max = the worst cloud); loose % = share of points whose nearest GT point is garment; "
             "s/sample on this machine; params = all parameters incl. outfit codes.", "", FAIR_NOTE, "",
             "## Checkpoints", ""]  # fmt: skip
    for k, c in report["checkpoints"].items():
        if isinstance(c["path"], dict):
            models = ", ".join(f"{s}: `{p}` (step {c['step'][s]})" for s, p in c["path"].items())
            lines.append(f"- {_title(k)}: {models}, preset `{c['preset']}`")
        else:
            lines.append(f"- {_title(k)}: `{c['path']}` (step {c['step']}, preset `{c['preset']}`)")
    lines += ["", "## All frames", "", *_tables(report["means"])]
    for subject, rows in report["per_subject"].items():
        lines += ["", f"## {subject}", "", *_tables(rows)]
    if report["claims"]:
        lines += ["", "## The papers' claims on these numbers", ""]
        for c in report["claims"]:
            nums = ", ".join(f"{k} {v:.2f}" for k, v in c.items() if isinstance(v, float))
            lines.append(f"- {c['claim']}: **{'holds' if c['holds'] else 'does not hold'}** ({nums})")
    if report.get("targets"):
        met = sum(t["holds"] for t in report["targets"])
        lines += ["", f"## PocoLoco's targets: {met} of {len(report['targets'])} met", "",
                  "| subject | target | PocoLoco | bound | |", "|---|---|---|---|---|"]  # fmt: skip
        for t in report["targets"]:
            lines.append(f"| {t['subject']} | {t['target']} | {t['value']:.2f} | {t['bound']:.2f} | "
                         f"{'met' if t['holds'] else '**not met**'} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def render_comparison(base_examples: list[dict[str, Any]], examples: dict[str, list[dict[str, Any]]],
                      path: Path) -> Path | None:  # fmt: skip
    """One row per subject (its first evaluated frame): GT, every model, nearest frame, posed body;
    points coloured by the label of their nearest GT point."""
    by_key = {ex["key"]: ex for ex in base_examples}
    model_by_key = {k: {ex["key"]: ex for ex in exs} for k, exs in examples.items()}
    seen, panels, ncols = set(), [], 0
    for key, ex in by_key.items():
        subject = key.split("/")[0]
        if subject in seen:
            continue
        seen.add(subject)
        gt, lab = ex["gt"]
        row = [(gt, lab, None, f"GT {key}")]
        for mk, exs in model_by_key.items():
            if key in exs and "model" in exs[key]:
                pts = exs[key]["model"][0]
                row.append((pts, None if lab is None else lab[nearest(pts, gt)[1]], None, _title(mk)))
        for b in ("nearest_frame", "posed_body"):
            if b in ex:
                pts, blab = ex[b]
                row.append((pts, None if lab is None else lab[nearest(pts, gt)[1]], None, _title(b)))
        ncols = max(ncols, len(row))
        panels.append(row)
    if not panels:
        return None
    flat = []
    for row in panels:  # pad rows to a common width
        flat += row + [(row[0][0][:1], None, None, "")] * (ncols - len(row))
    return Path(render_grid(flat, path, views=("front",), ncols=ncols))
