"""Cloth statistics of a synthetic dataset's card: per sequence (from the simulated frames) and
per subject (from its sequences). Pure numpy; the simulation itself is ``synth.cloth_sim``."""

from __future__ import annotations

import numpy as np

__all__ = ["merge_cloth_stats", "summarise_cloth_stats"]


def summarise_cloth_stats(stats: list[dict]) -> dict:
    """One sequence's cloth statistics from its frames' (``simulate_garment`` stats: penetration in m,
    stretch, self-contact / self-intersections): max / mean penetration in mm, the share of vertices
    inside the body, worst stretch, self-intersection counts; frames marked invalid are left out
    unless all are."""
    if not stats:
        return {}
    valid = [s for s in stats if s["valid"]] or stats
    out = {
        "max_mm": 1000.0 * max(s["penetration_max"] for s in valid),
        "mean_mm": 1000.0 * float(np.mean([s["penetration_mean"] for s in valid])),
        "fraction_percent": 100.0 * float(np.mean([s["penetration_fraction"] for s in valid])),
        "stretch_max": max(s["stretch_max"] for s in valid),
    }
    if "self_contact" in valid[0]:
        out["self_contact_frames_percent"] = 100.0 * float(np.mean([s["self_contact"] for s in valid]))
    inter = [s["self_intersections"] for s in valid if s.get("self_intersections") is not None]
    if inter:
        out["self_intersection_pairs_mean"] = float(np.mean(inter))
        out["self_intersection_frames_percent"] = 100.0 * float(np.mean(np.array(inter) > 0))
        out["self_intersection_frames_counted"] = len(inter)
    return out


def merge_cloth_stats(pens: list[dict]) -> dict:
    """A subject's cloth statistics from its sequences' (means of per-sequence means)."""
    out = {
        "max_mm": max(p["max_mm"] for p in pens),
        "mean_mm": float(np.mean([p["mean_mm"] for p in pens])),
        "fraction_percent": float(np.mean([p["fraction_percent"] for p in pens])),
        "stretch_max": max(p["stretch_max"] for p in pens),
    }
    counted = [p for p in pens if p.get("self_intersection_frames_counted")]
    if counted:
        w = np.array([p["self_intersection_frames_counted"] for p in counted], dtype=np.float64)
        pairs = [p["self_intersection_pairs_mean"] for p in counted]
        out["self_intersection_pairs_mean"] = float(np.average(pairs, weights=w))
        out["self_intersection_frames_percent"] = float(
            np.average([p["self_intersection_frames_percent"] for p in counted], weights=w)
        )
    return out
