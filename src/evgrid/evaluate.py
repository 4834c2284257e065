"""Evaluation: cell classes, per-class IoU against a reference map or the truth, mIoU over scenes.

A cell's class is the state with the largest mass; a tie goes to unknown. Maps are compared
with the ``ray_ilm`` map of the same scene over the cells that any local grid of the scene
covered (the reference map's coverage).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numba
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
    "bootstrap_interval",
    "iou_intervals",
    "iou_per_class",
    "compare_maps",
    "compare_truth",
    "confusion",
    "iou_from_confusion",
    "observable",
    "mean_iou",
    "markdown_table",
    "dynamic_confusion",
    "detection_scores",
    "dynamic_summary",
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
    """Class of each cell of masses ``(..., 3)``: FREE, OCCUPIED or UNKNOWN (uint8); ties go to
    UNKNOWN."""
    a = np.asarray(m)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"masses must have a last axis of length 3, got shape {a.shape}")
    f, o, u = a[..., 0], a[..., 1], a[..., 2]
    out = np.full(a.shape[:-1], UNKNOWN, dtype=np.uint8)
    out[(f > o) & (f > u)] = FREE
    out[(o > f) & (o > u)] = OCCUPIED
    return out


def iou_per_class(
    pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None
) -> dict[str, float]:
    """IoU of each class between two class rasters over ``mask``; NaN where a class is in
    neither."""
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


@numba.njit(cache=True)
def _k_confusion(ref_cls, mask, m, out):
    """out[ref, pred] += cells under ``mask``, pred being the class of ``m`` (largest mass, ties
    unknown)."""
    h, w = ref_cls.shape
    for i in range(h):
        for j in range(w):
            if not mask[i, j]:
                continue
            f = m[i, j, 0]
            o = m[i, j, 1]
            u = m[i, j, 2]
            k = 2  # UNKNOWN
            if f > o and f > u:
                k = 0  # FREE
            elif o > f and o > u:
                k = 1  # OCCUPIED
            out[ref_cls[i, j], k] += 1


def confusion(ref_cls: np.ndarray, mask: np.ndarray, masses: np.ndarray) -> np.ndarray:
    """3 x 3 counts (int64) of reference class (rows) against the class of ``masses`` (columns) over
    ``mask``."""
    out = np.zeros((3, 3), dtype=np.int64)
    _k_confusion(
        np.ascontiguousarray(ref_cls, dtype=np.uint8),
        np.ascontiguousarray(mask, dtype=np.bool_),
        np.ascontiguousarray(masses, dtype=np.float32),
        out,
    )
    return out


def iou_from_confusion(c: np.ndarray) -> dict[str, float]:
    """Per-class IoU from confusion counts: |ref = k and pred = k| / |ref = k or pred = k|; NaN
    where neither."""
    out = {}
    for k, name in enumerate(CLASSES):
        inter = int(c[k, k])
        union = int(c[k, :].sum() + c[:, k].sum()) - inter
        out[name] = inter / union if union else math.nan
    return out


def _tile(m: EvidentialMap, key: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    t = m.tiles.get(key)
    return None if t is None else (t, m.covered_tiles[key])


def tile_keys(m: EvidentialMap, r0: int, c0: int, h: int, w: int) -> set[tuple[int, int]]:
    """Keys of the tiles of ``m``'s layout that the cell box ``[r0, r0+h) x [c0, c0+w)`` meets."""
    ts = m.tile_cells
    return {
        (ti, tj)
        for ti in range(r0 // ts, (r0 + h - 1) // ts + 1)
        for tj in range(c0 // ts, (c0 + w - 1) // ts + 1)
    }


def tile_confusions_vs_map(
    maps: Mapping[str, EvidentialMap], reference: str, key: tuple[int, int]
) -> np.ndarray:
    """Confusion counts ``(len(maps), 3, 3)`` of every map against ``maps[reference]`` on one tile,
    over its covered cells."""
    out = np.zeros((len(maps), 3, 3), dtype=np.int64)
    ref = _tile(maps[reference], key)
    if ref is None:
        return out
    ref_cls = classify(ref[0])
    for i, m in enumerate(maps.values()):
        t = _tile(m, key)
        if t is None:  # a tile a map never got: vacuous, so unknown
            out[i, :, UNKNOWN] = np.bincount(ref_cls[ref[1]], minlength=3)
        else:
            _k_confusion(ref_cls, ref[1], t[0], out[i])
    return out


def observable(cls: np.ndarray) -> np.ndarray:
    """Free cells and occupied cells with a free 8-neighbour (building interiors are occupied but
    unobservable)."""
    free = cls == FREE
    near = free.copy()
    near[1:] |= free[:-1]
    near[:-1] |= free[1:]
    near[:, 1:] |= near[:, :-1].copy()
    near[:, :-1] |= near[:, 1:].copy()
    return free | near


def tile_confusions_vs_truth(
    maps: Mapping[str, EvidentialMap],
    truth: EvidentialMap,
    reference: str | None,
    key: tuple[int, int],
) -> np.ndarray:
    """Confusion counts ``(len(maps), 3, 3)`` of every map against the true occupancy on one tile.

    Cells count where the truth is known, the reference map covered them (any cell with
    ``reference=None``: what a map fills beyond the lidar's reach counts too), and they are
    observable (:func:`observable`, decided with the neighbouring tiles' cells).
    """
    out = np.zeros((len(maps), 3, 3), dtype=np.int64)
    if key not in truth.tiles:
        return out
    ts = truth.tile_cells
    r0, c0 = key[0] * ts, key[1] * ts
    halo, halo_cov = truth.read(r0 - 1, c0 - 1, ts + 2, ts + 2)
    t_all = classify(halo)
    t_cls = t_all[1:-1, 1:-1]
    mask = halo_cov[1:-1, 1:-1] & observable(t_all)[1:-1, 1:-1]
    if reference is not None:
        ref = _tile(maps[reference], key)
        if ref is None:
            return out
        mask &= ref[1]
    for i, m in enumerate(maps.values()):
        t = _tile(m, key)
        if t is None:
            out[i, :, UNKNOWN] = np.bincount(t_cls[mask], minlength=3)
        else:
            _k_confusion(t_cls, mask, t[0], out[i])
    return out


def compare_maps(
    maps: Mapping[str, EvidentialMap], reference: str = "ray_ilm"
) -> dict[str, dict[str, float]]:
    """Per-class IoU of every map against ``maps[reference]`` over the reference's covered cells.

    Works tile by tile over the reference's tiles: the cost grows with the area mapped, never
    with the bounding box of the drive.
    """
    if reference not in maps:
        raise KeyError(f"reference map {reference!r} not among {sorted(maps)}")
    total = sum(
        (tile_confusions_vs_map(maps, reference, k) for k in list(maps[reference].tiles)),
        np.zeros((len(maps), 3, 3), dtype=np.int64),
    )
    return {name: iou_from_confusion(total[i]) for i, name in enumerate(maps) if name != reference}


def compare_truth(
    maps: Mapping[str, EvidentialMap], truth: EvidentialMap, reference: str = "ray_ilm"
) -> dict[str, dict[str, float]]:
    """Per-class IoU (free, occupied) of every map against the accumulated true occupancy
    (simulation)."""
    reference = reference if reference in maps else next(iter(maps))
    total = sum(
        (tile_confusions_vs_truth(maps, truth, reference, k) for k in list(truth.tiles)),
        np.zeros((len(maps), 3, 3), dtype=np.int64),
    )
    return {
        name: {c: v for c, v in iou_from_confusion(total[i]).items() if c != "unknown"}
        for i, name in enumerate(maps)
    }


def mean_iou(per_scene: Iterable[Mapping[str, Mapping[str, float]]]) -> dict[str, dict[str, float]]:
    """Mean over scenes of per-map, per-class IoU (scenes where a class is undefined are
    skipped)."""
    acc: dict[str, dict[str, list[float]]] = {}
    for scene in per_scene:
        for name, ious in scene.items():
            for cls, v in ious.items():
                acc.setdefault(name, {}).setdefault(cls, [])
                if not math.isnan(v):
                    acc[name][cls].append(v)
    return {
        name: {cls: (float(np.mean(v)) if v else math.nan) for cls, v in d.items()}
        for name, d in acc.items()
    }


def bootstrap_interval(
    values: Iterable[float], level: float = 0.95, n_resamples: int = 4000, seed: int = 0
) -> dict[str, float]:
    """Mean over scenes with a percentile-bootstrap confidence interval (resampling scenes).

    NaNs (a class absent from a scene) are left out; ``n`` says how many scenes remain. With
    fewer than two scenes the interval is the mean itself.
    """
    v = np.array([x for x in values if x is not None and not math.isnan(x)], dtype=np.float64)
    if not len(v):
        return {"mean": math.nan, "lo": math.nan, "hi": math.nan, "n": 0}
    if len(v) < 2:
        return {"mean": float(v[0]), "lo": float(v[0]), "hi": float(v[0]), "n": 1}
    means = v[np.random.default_rng(seed).integers(0, len(v), (n_resamples, len(v)))].mean(axis=1)
    lo, hi = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return {"mean": float(v.mean()), "lo": float(lo), "hi": float(hi), "n": int(len(v))}


def iou_intervals(
    per_scene: Iterable[Mapping[str, Mapping[str, float]]], level: float = 0.95
) -> dict[str, dict[str, dict]]:
    """Per-map, per-class mean IoU over scenes with its bootstrap interval (see
    :func:`bootstrap_interval`)."""
    acc: dict[str, dict[str, list[float]]] = {}
    for scene in per_scene:
        for name, ious in scene.items():
            for cls, v in ious.items():
                acc.setdefault(name, {}).setdefault(cls, []).append(math.nan if v is None else v)
    return {
        name: {cls: bootstrap_interval(v, level) for cls, v in d.items()} for name, d in acc.items()
    }


#: What a table's intervals are; with one scene there is none, and the title says so.
INTERVAL_WORDS = "95% bootstrap interval over scenes"
#: The caption under the paper's columns: they are not this run's data.
PAPER_CAPTION = (
    "paper: the paper's Table I (Ev-Net on nuScenes val, its own data and network), not figures "
    "of this run's data: compare the maps' ordering, not the digits (docs/results.md)."
)


def markdown_table(
    results: Mapping[str, Mapping[str, float]],
    title: str = "ours",
    paper: bool = True,
    intervals: Mapping[str, Mapping[str, Mapping[str, float]]] | None = None,
) -> str:
    """A Markdown table of per-class mIoU in %, with the paper's Table I beside it, captioned.

    With ``intervals`` (from :func:`iou_intervals`) each value carries its 95% interval over
    scenes, and the title says so (:data:`INTERVAL_WORDS`); with fewer than two scenes there is
    none, and the title says "one scene: no interval".
    """
    if intervals is not None:
        one = all(ci.get("n", 0) < 2 for d in intervals.values() for ci in d.values())
        title += "; one scene: no interval" if one else f"; {INTERVAL_WORDS}"
    head = "| map | free | occupied | unknown |"
    if paper:
        head += " paper free | paper occupied | paper unknown |"
    sep = "|" + "---|" * (head.count("|") - 1)
    lines = [f"**{title}** (mIoU in %)", "", head, sep]
    for name, ious in results.items():
        ci = (intervals or {}).get(name, {})
        row = (
            f"| `{name}` | "
            + " | ".join(_pct(ious.get(c)) + _interval(ci.get(c)) for c in CLASSES)
            + " |"
        )
        if paper:
            p = PAPER_TABLE_I.get(name)
            row += " " + " | ".join(f"{p[c]:.2f}" if p else "-" for c in CLASSES) + " |"
        lines.append(row)
    if paper:
        lines += ["", PAPER_CAPTION]
    return "\n".join(lines) + "\n"


def _interval(ci: Mapping[str, float] | None) -> str:
    if not ci or ci.get("n", 0) < 2:
        return ""
    return f" ({_pct(ci['lo'])}-{_pct(ci['hi'])})"


def _pct(v: float | None) -> str:
    return "n/a" if v is None or math.isnan(v) else f"{100 * v:.2f}"


# --- moving objects: the dynamic score against the truth (docs/equations.md#the-dynamic-score) ---


def dynamic_confusion(
    score: np.ndarray, threshold: float, moving: np.ndarray, observed: np.ndarray
) -> tuple[int, int, int]:
    """``(tp, fp, fn)`` of the cells called dynamic (``score > threshold``) against the truth
    mask ``moving`` (cells of moving objects), over the ``observed`` cells only (the cells the
    current lidar or radar ISM says anything about: elsewhere neither is checkable).

    All three arrays have one shape; ``moving`` and ``observed`` are boolean.
    """
    if not (score.shape == moving.shape == observed.shape):
        raise ValueError(
            f"score {score.shape}, truth {moving.shape} and observed {observed.shape} differ"
        )
    called = (score > threshold) & observed
    truth = moving & observed
    tp = int(np.count_nonzero(called & truth))
    return tp, int(np.count_nonzero(called)) - tp, int(np.count_nonzero(truth)) - tp


def detection_scores(tp: int, fp: int, fn: int) -> dict[str, float]:
    """Precision, recall and IoU of a detection from its counts; NaN where undefined (no cell
    called, or no true cell)."""
    return {
        "precision": tp / (tp + fp) if tp + fp else math.nan,
        "recall": tp / (tp + fn) if tp + fn else math.nan,
        "iou": tp / (tp + fp + fn) if tp + fp + fn else math.nan,
    }


def dynamic_summary(
    per_scene: Iterable[Mapping[str, Mapping[str, float]]], level: float = 0.95
) -> dict[str, dict[str, dict]]:
    """``summary["dynamic"]``: per map, ``precision``, ``recall`` and ``iou`` of the dynamic
    cells as the mean over scenes with a bootstrap interval (:func:`bootstrap_interval`), from
    each scene's ``metrics["dynamic"]`` (:meth:`evgrid.observers.SceneScores.final`)."""
    acc: dict[str, dict[str, list[float]]] = {}
    for scene in per_scene:
        for name, d in scene.items():
            for key in ("precision", "recall", "iou"):
                v = d.get(key)
                acc.setdefault(name, {}).setdefault(key, []).append(
                    math.nan if v is None else float(v)
                )
    return {
        name: {key: bootstrap_interval(v, level) for key, v in d.items()} for name, d in acc.items()
    }
