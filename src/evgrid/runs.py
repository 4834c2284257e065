"""Whole-scene runs: map a scene or a source of scenes into a results folder; sweep ``m_u_min``.

A results folder holds ``config.json`` (the :class:`~evgrid.config.RunConfig` that reproduces it),
``summary.json``, ``table.md`` (Table I beside the paper's) and one folder per scene with
``metrics.json``, figures and the GIF. A run refuses to write into a folder that already holds
results unless told to overwrite, and a run that fails leaves no empty folder behind.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.classes import CLASSES
from evgrid.config import MapperConfig, OutputConfig, RunConfig
from evgrid.data.frame import Frame
from evgrid.evaluate import (
    bootstrap_interval,
    compare_maps,
    iou_intervals,
    markdown_table,
    mean_iou,
)
from evgrid.fusion import FusionParams, MapSet
from evgrid.io import jsonable, write_json
from evgrid.mapper import OccupancyMapper
from evgrid.observers import GifRecorder, SceneScores, TruthTracker

__all__ = [
    "SceneResult",
    "map_scene",
    "map_scenes",
    "summarize",
    "sweep_m_u_min",
    "choose_m_u_min",
    "results_folder",
    "ResultsExistError",
    "convergence_at",
    "convergence_table",
    "frame_time_summary",
]


class ResultsExistError(FileExistsError):
    """The results folder already holds another run's results."""


@contextlib.contextmanager
def results_folder(out: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """A results folder for one run: refused if it holds results (unless ``overwrite``); removed again if the run fails empty."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ResultsExistError(f"{out} is a file, not a results folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ResultsExistError(
            f"{out} already holds results; pass --overwrite to replace them or choose another --out"
        )
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        yield out
    except BaseException:
        if created:
            _remove_empty_dirs(out)
        raise


def _remove_empty_dirs(path: Path) -> None:
    for sub in sorted(
        (p for p in path.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True
    ):
        with contextlib.suppress(OSError):
            sub.rmdir()
    with contextlib.suppress(OSError):
        path.rmdir()


@dataclass
class SceneResult:
    """What mapping one scene produced: metrics and the files written."""

    scene: str
    metrics: dict[str, Any]
    files: dict[str, str]
    fps: float


def map_scene(
    frames: Iterable[Frame],
    out_dir: str | os.PathLike | None,
    config: MapperConfig = MapperConfig(),
    outputs: OutputConfig = OutputConfig(),
    deep: Any = None,
    name: str | None = None,
    progress: Any = None,
    observers: tuple = (),
    overwrite: bool = False,
) -> SceneResult:
    """Map a whole scene; with ``out_dir`` write ``config.json``, ``metrics.json``, figures, the GIF,
    the exports of ``outputs.exports`` and (optionally) the maps.

    ``observers`` (e.g. exporters) see every map update after the built-in ones.
    """
    name = name or getattr(frames, "name", "scene")
    with (
        results_folder(out_dir, overwrite)
        if out_dir is not None
        else contextlib.nullcontext() as out
    ):
        exporters = _exporters(outputs, out, name)
        truth = TruthTracker(config.grid, config.tile_cells)
        mapper = OccupancyMapper(config, deep)
        scores = SceneScores(mapper.maps.maps, truth, track=outputs.convergence)
        gif = (
            GifRecorder(config.grid, outputs.gif_window_m, outputs.gif_step, outputs.gif_max_frames)
            if out is not None and outputs.figures
            else None
        )
        mapper.observers += [truth, scores, *([gif] if gif else []), *exporters, *observers]
        t0 = time.perf_counter()
        frame_ms: list[float] = []  # mapper and observers, without reading the frame
        for frame in frames:
            t = time.perf_counter()
            mapper.process(frame)
            frame_ms.append((time.perf_counter() - t) * 1e3)
            if progress is not None:
                progress()
        seconds = time.perf_counter() - t0
        files: dict[str, str] = {}
        for fmt, exporter in zip(outputs.exports, exporters):
            written = exporter.close()
            files[f"export_{fmt}"] = str(written[0] if isinstance(written, list) else written)
        metrics = _scene_metrics(name, mapper, scores, seconds, frame_ms)
        metrics.update(_source_report(frames))
        if out is not None:
            files["config"] = str(
                write_json(out / "config.json", RunConfig(config, outputs).to_dict())
            )
            files["metrics"] = str(write_json(out / "metrics.json", metrics))
            if outputs.figures and scores.keyframes:
                from evgrid.render import write_scene_figures

                files.update(
                    write_scene_figures(
                        mapper.maps.maps,
                        out,
                        name,
                        mapper.trajectory,
                        mapper.last_isms,
                        scores.keyframes,
                        gif.frames if gif else (),
                    )
                )
            if outputs.save_maps:
                from evgrid.grid import save_map

                for m_name, m in mapper.maps.maps.items():
                    files[f"map_{m_name}"] = str(save_map(m, out / "maps" / f"{m_name}.npz"))
    return SceneResult(name, jsonable(metrics), files, metrics["frames_per_second"])


def _exporters(outputs: OutputConfig, out: Path | None, name: str) -> list[Any]:
    """The recorders ``outputs.exports`` asks for (into the scene's folder), and the live viewer."""
    from evgrid.export import make_observer

    if outputs.exports and out is None:
        raise ValueError("exports need a results folder (out_dir)")
    paths = {
        "nav2": lambda: out / "nav2",
        "mcap": lambda: out / f"{name}.mcap",
        "rerun": lambda: out / f"{name}.rrd",
    }
    # MCAP keeps a fixed window around the vehicle per update, so a long drive's file grows with time, not area x time
    kwargs = {"mcap": {"window_m": outputs.export_window_m}}
    found = [make_observer(fmt, paths[fmt](), **kwargs.get(fmt, {})) for fmt in outputs.exports]
    if outputs.viewer:
        found.append(make_observer("rerun", None))
    return found


def _source_report(frames: Any) -> dict[str, Any]:
    """What the data source itself reports about the scene (bags: where a cut recording stopped; loaders: gap counts)."""
    found = {k: getattr(frames, k, None) for k in ("stopped", "counts", "stats")}
    report = {k: v for k, v in found.items() if v and not callable(v)}
    return {"source_report": report} if report else {}


#: Seconds of driving after which convergence is reported (paper: faster convergence with the deep prior).
CONVERGENCE_TIMES_S: tuple[float, ...] = (1.0, 2.0, 5.0, 10.0)


def convergence_at(
    keyframes: list[dict[str, Any]], times_s: tuple[float, ...] = CONVERGENCE_TIMES_S
) -> dict[str, Any]:
    """Each map's perception field (free and occupied IoU against the truth, and the area classified
    correctly) at the first keyframe at least ``t`` seconds after the scene's first; ``None`` past its end."""
    kfs = [k for k in keyframes if "field" in k]
    if not kfs:
        return {}
    t0 = keyframes[0]["timestamp"]
    at = []
    for t in times_s:
        later = [k for k in kfs if (k["timestamp"] - t0) * 1e-6 >= t - 1e-6]
        at.append(later[0]["field"] if later else None)
    names = next(iter(kfs))["field"].keys()
    return {
        "t_s": list(times_s),
        "maps": {
            n: {q: [(f[n][q] if f else None) for f in at] for q in ("free", "occupied", "area_m2")}
            for n in names
        },
    }


def _map_area_km2(maps: MapSet) -> float:
    """Area of the tiles the maps hold (what the memory is proportional to)."""
    m = next(iter(maps.maps.values()))
    return len(m.tiles) * (m.tile_cells * m.grid.resolution) ** 2 * 1e-6


def frame_time_summary(frame_ms: list[float]) -> dict[str, float]:
    """Milliseconds per frame (mapper and observers): mean, median, 95th percentile, and the mean
    of the first and last tenth of the scene, which stay equal when nothing grows with the drive."""
    if not frame_ms:
        return {}
    a = np.asarray(frame_ms)
    tenth = max(1, len(a) // 10)
    return {
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "p95": float(np.percentile(a, 95)),
        "first_tenth_mean": float(a[:tenth].mean()),
        "last_tenth_mean": float(a[-tenth:].mean()),
    }


def _scene_metrics(
    name: str,
    mapper: OccupancyMapper,
    scores: SceneScores,
    seconds: float,
    frame_ms: list[float] = (),
) -> dict[str, Any]:
    n_kf = len(scores.keyframes)
    return {
        "scene": name,
        "frames": mapper.n_frames,
        "keyframes": n_kf,
        "updates": mapper.n_updates,
        "seconds": seconds,
        "frames_per_second": mapper.n_frames / seconds if seconds > 0 else math.nan,
        "keyframes_per_second": n_kf / seconds if seconds > 0 else math.nan,
        **scores.final(),
        "timings_ms": mapper.timing_summary(),
        "frame_ms": frame_time_summary(list(frame_ms)),
        "map_area_km2": _map_area_km2(mapper.maps),
        "counts": mapper.counts(),
        "pose_jumps": mapper.poses.jumps,
        "convergence": [{"iou": {}, **rec} for rec in scores.keyframes],
        "convergence_truth": convergence_at(scores.keyframes),
        "trajectory": mapper.trajectory,
    }


# --- many scenes --------------------------------------------------------------------------------


def _map_one(args: tuple) -> dict[str, Any]:
    source, name, out_dir, config, outputs = args
    scene = source.load(name)
    res = map_scene(scene, Path(out_dir) / name, config, outputs, name=name, overwrite=True)
    return res.metrics


def summarize(per_scene: list[dict[str, Any]]) -> dict[str, Any]:
    """mIoU over scenes (against ray_ilm and, where known, the truth), speed and skip counts, from per-scene metrics."""

    def clean(d: Mapping[str, Mapping[str, Any]]) -> dict:
        return {
            k: {c: (math.nan if v is None else v) for c, v in ious.items()} for k, ious in d.items()
        }

    vs_ilm = mean_iou(clean(m["vs_ray_ilm"]) for m in per_scene if "vs_ray_ilm" in m)
    maps = {"ray_ilm": {c: 1.0 for c in CLASSES}} if vs_ilm else {}
    maps.update(vs_ilm)
    out: dict[str, Any] = {
        "maps": maps,
        "reference": "ray_ilm",
        "scenes": [m["scene"] for m in per_scene],
    }
    out["maps_interval"] = iou_intervals(m["vs_ray_ilm"] for m in per_scene if "vs_ray_ilm" in m)
    conf = [m["confusion_vs_ray_ilm"] for m in per_scene if m.get("confusion_vs_ray_ilm")]
    if conf:
        out["confusion_vs_ray_ilm"] = {
            n: np.sum([c[n] for c in conf if n in c], axis=0).tolist() for n in conf[0]
        }
    truth = [clean(m["vs_truth"]) for m in per_scene if m.get("vs_truth")]
    if truth:
        out["vs_truth"] = mean_iou(truth)
        out["vs_truth_interval"] = iou_intervals(
            m["vs_truth"] for m in per_scene if m.get("vs_truth")
        )
    conv = [m["convergence_truth"] for m in per_scene if m.get("convergence_truth")]
    if conv:
        out["convergence_truth"] = {
            "t_s": conv[0]["t_s"],
            "maps": {
                n: {
                    q: [
                        bootstrap_interval(c["maps"][n][q][i] for c in conv if n in c["maps"])
                        for i in range(len(conv[0]["t_s"]))
                    ]
                    for q in ("free", "occupied", "area_m2")
                }
                for n in conv[0]["maps"]
            },
        }
    frames = sum(m["frames"] for m in per_scene)
    seconds = sum(m["seconds"] for m in per_scene)
    out["frames_per_second"] = frames / seconds if seconds else math.nan
    keys = sorted({k for m in per_scene for k in m.get("timings_ms", {})})
    out["timings_ms"] = {
        k: float(np.median([m["timings_ms"][k] for m in per_scene if k in m["timings_ms"]]))
        for k in keys
    }
    keys = sorted({k for m in per_scene for k in m.get("counts", {})})
    out["counts"] = {k: sum(m.get("counts", {}).get(k, 0) for m in per_scene) for k in keys}
    return jsonable(out)


def convergence_table(conv: Mapping[str, Any]) -> str:
    """Markdown: per map, free and occupied IoU against the truth and the area classified correctly after each time."""
    ts = conv["t_s"]
    head = (
        "| map | "
        + " | ".join(f"free IoU {t:g} s" for t in ts)
        + " | "
        + " | ".join(f"occ. IoU {t:g} s" for t in ts)
        + " | "
        + " | ".join(f"correct m² {t:g} s" for t in ts)
        + " |"
    )
    lines = [
        "**convergence against the true occupancy** (mean over scenes, 95% bootstrap interval; "
        "every true cell seen so far counts, covered by the lidar or not)",
        "",
        head,
        "|" + "---|" * (1 + 3 * len(ts)),
    ]

    def cell(ci: Mapping[str, float], scale: float, fmt: str) -> str:
        if ci["n"] == 0:
            return "n/a"
        v = format(ci["mean"] * scale, fmt)
        return (
            v
            if ci["n"] < 2
            else f"{v} ({format(ci['lo'] * scale, fmt)}-{format(ci['hi'] * scale, fmt)})"
        )

    for name, q in conv["maps"].items():
        row = (
            [cell(c, 100, ".1f") for c in q["free"]]
            + [cell(c, 100, ".1f") for c in q["occupied"]]
            + [cell(c, 1, ".0f") for c in q["area_m2"]]
        )
        lines.append(f"| `{name}` | " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def map_scenes(
    source: Any,
    out_dir: str | os.PathLike,
    config: MapperConfig = MapperConfig(),
    outputs: OutputConfig = OutputConfig(),
    names: list[str] | None = None,
    workers: int = 1,
    on_scene: Any = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Map every scene of a source (``workers`` processes, one scene each); write config, summary and table.

    Writes ``OUT/config.json`` (re-run with ``evgrid map --config``), ``OUT/<scene>/...`` per
    scene, ``OUT/summary.json`` and ``OUT/table.md``. Returns the summary.
    """
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from evgrid.sources import scenes_of, source_to_dict

    names = scenes_of(source, names)
    if not names:
        raise ValueError("no scenes to map")
    with results_folder(out_dir, overwrite) as out:
        run = RunConfig(config, outputs, source_to_dict(source), tuple(names))
        write_json(out / "config.json", run.to_dict())
        jobs = [(source, n, str(out), config, outputs) for n in names]
        per_scene: list[dict[str, Any]] = []
        if workers <= 1 or len(jobs) == 1:
            results: Iterable[dict[str, Any]] = map(_map_one, jobs)
            pool = contextlib.nullcontext()
        else:
            # spawn: a fresh interpreter per worker, safe with torch's and numba's thread pools
            pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"))
            results = pool.map(_map_one, jobs)
        with pool:
            for m in results:
                per_scene.append(m)
                if on_scene:
                    on_scene(m)
        summary = summarize(per_scene)
        write_json(out / "summary.json", summary)
        table = markdown_table(
            {k: v for k, v in summary["maps"].items() if k != "ray_ilm"},
            title=f"{len(names)} scene(s), against ray_ilm; 95% bootstrap interval over scenes",
            intervals=summary.get("maps_interval"),
        )
        if "vs_truth" in summary:
            table += "\n" + markdown_table(
                summary["vs_truth"],
                title="against the true occupancy (simulator)",
                paper=False,
                intervals=summary.get("vs_truth_interval"),
            )
        if "convergence_truth" in summary:
            table += "\n" + convergence_table(summary["convergence_truth"])
            if outputs.figures:
                from evgrid.render import plot_perception_field

                plot_perception_field(summary["convergence_truth"], out / "convergence_truth.png")
        from evgrid.io import atomic_write_text

        atomic_write_text(out / "table.md", table)
    return summary


# --- choosing m_u_min ---------------------------------------------------------------------------

SWEPT_MAPS: tuple[str, ...] = ("deep_replace", "deep_disc", "fused")  # the maps m_u_min changes

CHOICE_RULE = (
    "the highest m_u_min whose deep_disc mIoU (mean of the three classes, against ray_ilm) is within "
    "0.01 of the best value swept: cells known only to the deep IRM stay as clearly apart from verified "
    "space as accuracy allows; at m_u_min >= 0.5 such cells can never be classified free or occupied"
)


def _sweep_one(args: tuple) -> dict[str, Any]:
    source, name, values, config = args
    scene = source.load(name)
    sets = [
        MapSet(
            config.grid,
            FusionParams(m_u_min=v, alpha=config.fusion.alpha),
            SWEPT_MAPS,
            config.tile_cells,
        )
        for v in values
    ]
    # ray_ilm is the reference; fused makes the mapper compute all three ISMs
    mapper = OccupancyMapper(replace(config, maps=("ray_ilm", "fused")), extra=tuple(sets))
    for frame in scene:
        mapper.process(frame)
    ref = mapper.maps.maps["ray_ilm"]
    per_value = [
        {"m_u_min": v, "vs_ray_ilm": compare_maps({"ray_ilm": ref, **s.maps})}
        for v, s in zip(values, sets)
    ]
    return {"scene": name, "values": per_value}


def sweep_m_u_min(
    source: Any,
    values: list[float],
    out_dir: str | os.PathLike,
    config: MapperConfig = MapperConfig(),
    names: list[str] | None = None,
    workers: int = 1,
    overwrite: bool = False,
) -> dict[str, Any]:
    """mIoU against ray_ilm of deep_replace, deep_disc and fused for each ``m_u_min``; writes JSON and a plot.

    ISMs are computed and warped once per update and shared by one map set per value.
    """
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from evgrid.render import plot_m_u_min_sweep
    from evgrid.sources import scenes_of

    names = scenes_of(source, names)
    jobs = [(source, n, list(values), config) for n in names]
    with results_folder(out_dir, overwrite) as out:
        if workers <= 1:
            per_scene = [_sweep_one(j) for j in jobs]
        else:
            with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as ex:
                per_scene = list(ex.map(_sweep_one, jobs))
        rows = []
        for k, v in enumerate(values):
            m = mean_iou(s["values"][k]["vs_ray_ilm"] for s in per_scene)
            rows.append(
                {
                    "m_u_min": v,
                    "miou": m,
                    "mean_of_classes": {
                        n: float(np.nanmean(list(d.values()))) for n, d in m.items()
                    },
                }
            )
        chosen = choose_m_u_min(rows)
        result = jsonable({"scenes": names, "rows": rows, "chosen": chosen, "rule": CHOICE_RULE})
        write_json(out / "m_u_min_sweep.json", result)
        plot_m_u_min_sweep(rows, SWEPT_MAPS, out / "m_u_min_sweep.png", chosen)
    return result


def choose_m_u_min(rows: list[dict], tolerance: float = 0.01) -> float:
    """The m_u_min picked from sweep rows by :data:`CHOICE_RULE`."""
    best = max(r["mean_of_classes"]["deep_disc"] for r in rows)
    return max(r["m_u_min"] for r in rows if r["mean_of_classes"]["deep_disc"] >= best - tolerance)
