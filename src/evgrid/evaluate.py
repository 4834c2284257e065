"""Evaluation (DESIGN 6): cell classes, per-class IoU against a reference map, mIoU over scenes.

A cell's class is the state with the largest mass; a tie goes to unknown. Maps are compared
with the ``ray_ilm`` map of the same scene over the cells that any local grid of the scene
covered (the reference map's coverage).
"""

from __future__ import annotations

import math
from typing import Iterable, Mapping

import numpy as np

from evgrid.classes import CLASSES, FREE, OCCUPIED, UNKNOWN
from evgrid.grid import EvidentialMap

__all__ = [
    "CLASSES",
    "FREE",
    "OCCUPIED",
    "UNKNOWN",
    "PAPER_TABLE_I",
    "classify",
    "iou_per_class",
    "compare_maps",
    "mean_iou",
    "markdown_table",
]


#: The paper's Table I (nuScenes val, mIoU in %), for comparison of orderings, not digits.
PAPER_TABLE_I: dict[str, dict[str, float]] = {
    "deep_acc": {"free": 61.78, "occupied": 2.07, "unknown": 11.05},
    "deep_replace": {"free": 69.63, "occupied": 3.43, "unknown": 45.96},
    "deep_disc": {"free": 71.64, "occupied": 4.75, "unknown": 46.23},
    "ray_irm": {"free": 76.68, "occupied": 6.02, "unknown": 63.55},
    "fused": {"free": 76.88, "occupied": 5.44, "unknown": 45.69},
}


def classify(m: np.ndarray) -> np.ndarray:
    """Class of each cell of masses ``(..., 3)``: FREE, OCCUPIED or UNKNOWN (uint8); ties go to UNKNOWN."""
    a = np.asarray(m)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"masses must have a last axis of length 3, got shape {a.shape}")
    f, o, u = a[..., 0], a[..., 1], a[..., 2]
    out = np.full(a.shape[:-1], UNKNOWN, dtype=np.uint8)
    out[(f > o) & (f > u)] = FREE
    out[(o > f) & (o > u)] = OCCUPIED
    return out


def iou_per_class(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """IoU of each class between two class rasters over ``mask``; NaN where a class is in neither."""
    pred = np.asarray(pred)
    ref = np.asarray(ref)
    if pred.shape != ref.shape:
        raise ValueError(f"class rasters differ in shape: {pred.shape} vs {ref.shape}")
    if mask is None:
        mask = np.ones(pred.shape, bool)
    elif mask.shape != pred.shape:
        raise ValueError(f"mask shape {mask.shape} differs from the rasters' {pred.shape}")
    p, r = pred[mask], ref[mask]
    out = {}
    for k, name in enumerate(CLASSES):
        inter = np.count_nonzero((p == k) & (r == k))
        union = np.count_nonzero((p == k) | (r == k))
        out[name] = inter / union if union else math.nan
    return out


def _common_window(maps: Iterable[EvidentialMap]) -> tuple[int, int, int, int]:
    boxes = [m.bounds() for m in maps if m.tiles]
    if not boxes:
        return (0, 0, 0, 0)
    r0 = min(b[0] for b in boxes)
    c0 = min(b[1] for b in boxes)
    r1 = max(b[0] + b[2] for b in boxes)
    c1 = max(b[1] + b[3] for b in boxes)
    return r0, c0, r1 - r0, c1 - c0


def compare_maps(maps: Mapping[str, EvidentialMap], reference: str = "ray_ilm") -> dict[str, dict[str, float]]:
    """Per-class IoU of every map against ``maps[reference]`` over the reference's covered cells."""
    if reference not in maps:
        raise KeyError(f"reference map {reference!r} not among {sorted(maps)}")
    r0, c0, h, w = _common_window(maps.values())
    ref_m, covered = maps[reference].read(r0, c0, h, w)
    ref_cls = classify(ref_m)
    out = {}
    for name, m in maps.items():
        if name == reference:
            continue
        masses, _ = m.read(r0, c0, h, w)
        out[name] = iou_per_class(classify(masses), ref_cls, covered)
    return out


def mean_iou(per_scene: Iterable[Mapping[str, Mapping[str, float]]]) -> dict[str, dict[str, float]]:
    """Mean over scenes of per-map, per-class IoU (scenes where a class is undefined are skipped)."""
    acc: dict[str, dict[str, list[float]]] = {}
    for scene in per_scene:
        for name, ious in scene.items():
            for cls, v in ious.items():
                acc.setdefault(name, {}).setdefault(cls, [])
                if not math.isnan(v):
                    acc[name][cls].append(v)
    return {
        name: {cls: (float(np.mean(v)) if v else math.nan) for cls, v in d.items()} for name, d in acc.items()
    }


def markdown_table(results: Mapping[str, Mapping[str, float]], title: str = "ours", paper: bool = True) -> str:
    """A Markdown table of per-class mIoU in %, with the paper's Table I beside it."""
    head = "| map | free | occupied | unknown |"
    if paper:
        head += " paper free | paper occupied | paper unknown |"
    sep = "|" + "---|" * (head.count("|") - 1)
    lines = [f"**{title}** (mIoU in %)", "", head, sep]
    for name, ious in results.items():
        row = f"| `{name}` | " + " | ".join(_pct(ious.get(c, math.nan)) for c in CLASSES) + " |"
        if paper:
            p = PAPER_TABLE_I.get(name)
            row += " " + " | ".join(f"{p[c]:.2f}" if p else "-" for c in CLASSES) + " |"
        lines.append(row)
    return "\n".join(lines) + "\n"


def _pct(v: float) -> str:
    return "n/a" if math.isnan(v) else f"{100 * v:.2f}"
