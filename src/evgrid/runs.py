"""Whole-scene runs: map a scene or a source of scenes into a results folder; sweep ``m_u_min``.

A results folder holds ``config.json`` (the :class:`~evgrid.config.RunConfig` that reproduces it),
``summary.json``, ``table.md`` (Table I beside the paper's) and one folder per scene with
``metrics.json``, figures and the GIF, written as each scene finishes (through
:func:`evgrid.engine.fan_out`), its ``config.json`` naming its own source and scene, and a
completion marker written last. The folder's policy (refused unless ``overwrite`` or ``resume``,
locked while the run lasts, no empty folder left by a failed run) is :mod:`evgrid.outdir`'s.
A scene that fails is reported by name while the others finish; ``summary.json`` lists it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.classes import CLASSES
from evgrid.config import MapperConfig, OutputConfig, RunConfig, SweepConfig, config_hash
from evgrid.data.frame import Frame
from evgrid.evaluate import (
    bootstrap_interval,
    compare_maps,
    dynamic_summary,
    iou_intervals,
    markdown_table,
    mean_iou,
)
from evgrid.fusion import FusionParams, MapSet
from evgrid.io import jsonable, write_json
from evgrid.mapper import OccupancyMapper
from evgrid.observers import GifRecorder, SceneScores, TruthTracker
from evgrid.outdir import ResultsExistError, is_complete, mark_complete, results_folder
from evgrid.store import TileStore

#: The tile store's folder in a scene's results folder (docs/store.md).
STORE_FOLDER = "store"

__all__ = [
    "SceneResult",
    "map_scene",
    "map_scenes",
    "summarize",
    "sweep_m_u_min",
    "choose_m_u_min",
    "results_folder",
    "ResultsExistError",
    "RunEvents",
    "RunInterrupted",
    "convergence_at",
    "convergence_table",
    "frame_time_summary",
]


log = logging.getLogger(__name__)


class RunEvents:
    """What a run tells as it goes (the command line shows it); every method may be left out."""

    def start(self, todo: list[str], kept: list[str], dropped: Mapping[str, str]) -> None:
        """``todo`` scenes to map, ``kept`` complete ones resumed, ``dropped`` by the source."""

    def frame(self, scene: str, done: int, total: int | None) -> None:
        """One more frame of ``scene`` mapped (only when scenes run in this process)."""

    def scene(self, metrics: dict[str, Any]) -> None:
        """A scene finished; its results are written."""

    def failed(self, scene: str, error: str) -> None:
        """A scene raised; the others go on."""


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C during a run: ``kept`` names the complete scenes left in ``out``."""

    def __init__(self, out: Path, kept: list[str], total: int) -> None:
        super().__init__(
            f"interrupted: {len(kept)} of {total} scene(s) complete in {out} "
            f"({', '.join(kept) or 'none'}); no file is left half-written; "
            f"continue with --resume --out {out}, or start again with --overwrite"
        )
        self.out, self.kept = out, kept


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
    source: dict[str, Any] | None = None,
    fixed_frame: str | None = None,
    resume: bool = False,
) -> SceneResult:
    """Map a whole scene; with ``out_dir`` write ``config.json`` (naming ``source``, a source as
    :func:`~evgrid.sources.source_to_dict` gives it, and this scene), ``metrics.json``, figures,
    the GIF, the exports of ``outputs.exports`` and (optionally) the maps.

    ``fixed_frame`` names the recording's fixed frame (the frame of its ego poses; default
    :func:`~evgrid.sources.fixed_frame_of` the scene: a recording's rig ``world_frame``, else
    the simulator's ``world``): the exports' map frame when ``config.frame`` is ``world``, the
    map frame's parent otherwise. ``observers`` (e.g. exporters) see every map update after the
    built-in ones. Files are written under temporary names and renamed when complete (the
    exports when closed; on any exception, Ctrl-C included, they are aborted). With ``out_dir``,
    the scene's resumable state is saved every ``outputs.checkpoint_every_s`` seconds of the
    drive, and ``resume`` continues from it (docs/store.md).
    """
    from evgrid.sources import fixed_frame_of

    name = name or getattr(frames, "name", "scene")
    fixed_frame = fixed_frame or fixed_frame_of(None, frames)
    config = _maps_the_rig_can_make(config, frames, name, outputs.exports)
    with (
        results_folder(out_dir, overwrite)
        if out_dir is not None
        else contextlib.nullcontext() as out
    ):
        exporters = _exporters(outputs, out, name, config.frame, fixed_frame)
        try:
            return _map_scene(
                frames, out, config, outputs, deep, name, progress, observers, source, exporters,
                fixed_frame, resume,
            )  # fmt: skip
        except BaseException:
            # Ctrl-C included: an export not closed is incomplete, and its temporary file goes
            # now rather than whenever the exporter is collected
            for exporter in exporters:
                exporter.abort()
            raise


def _maps_the_rig_can_make(
    config: MapperConfig, frames: Any, name: str, exports: tuple[str, ...] = ()
) -> MapperConfig:
    """A recording whose rig names no radar gives no radar maps: the deep IRM never runs on
    detections from no sensor (docs/ros.md). A rig with a lidar and a radar whose run exports
    for robots (nav2, or the MCAP's window) also maps ``nav``, the map to navigate on."""
    from evgrid.fusion import NAV_MAP, RULES

    if getattr(frames, "has_radar", True):
        if NAV_MAP in config.maps or not {"nav2", "mcap"} & set(exports):
            return config
        logging.getLogger(__name__).info(
            "%s: mapping the navigation map %r too, for the %s export",
            name,
            NAV_MAP,
            " and ".join(e for e in exports if e in ("nav2", "mcap")),
        )
        return replace(config, maps=(*config.maps, NAV_MAP))

    keep = tuple(m for m in config.maps if set(RULES[m].isms) <= {"ray_ilm"})
    if not keep:
        raise ValueError(
            f"{name}: the rig names no radar, and every map asked for ({', '.join(config.maps)}) "
            "needs one; ask for --maps ray_ilm"
        )
    left = [m for m in config.maps if m not in keep]
    if left:
        logging.getLogger(__name__).warning(
            "%s: the rig names no radar: mapping %s only (%s need a radar)",
            name,
            ", ".join(keep),
            ", ".join(left),
        )
    return replace(config, maps=keep)


def _map_scene(
    frames, out, config, outputs, deep, name, progress, observers, source, exporters, fixed_frame,
    resume=False,
) -> SceneResult:  # fmt: skip
    from evgrid.checkpoint import checkpoint_path

    truth = TruthTracker(config.grid, config.tile_cells)
    # the tile store in the scene's folder (docs/store.md): what a killed run leaves is there
    saved = _checkpointing(out, outputs, observers, name)
    path = None if out is None else checkpoint_path(out / STORE_FOLDER)
    go_on = resume and saved and path.exists() and _same_run(path, config, outputs, source, name)
    if out is not None and not go_on:
        shutil.rmtree(out / STORE_FOLDER, ignore_errors=True)  # a killed run's: start afresh
    store = None
    if out is not None and config.store.paging:
        store = TileStore(out / STORE_FOLDER)
    state = _resumed(path, store, config, deep, name) if go_on else None
    if state is None:
        mapper = OccupancyMapper(config, deep, store=store)
        state = {"mapper": mapper, "truth": truth, "seconds": 0.0, "frame_ms": []}
    else:
        mapper = state["mapper"]
        for exporter in exporters:  # the checkpoint's exporters replace the fresh ones
            exporter.abort()
        exporters[:] = state["exporters"]
    try:
        return _map_with(
            state, frames, out, config, outputs, name, progress, observers, source, exporters,
            fixed_frame, saved,
        )  # fmt: skip
    finally:
        mapper.close()


def _checkpointing(out: Path | None, outputs: OutputConfig, observers: tuple, name: str) -> bool:
    """Whether a scene saves resumable states: with a results folder, ``checkpoint_every_s``
    and nothing that streams into a file as it goes (the MCAP and rerun exports, the viewer)
    or that the run does not own (observers passed in)."""
    if out is None or not outputs.checkpoint_every_s:
        return False
    streams = [e for e in outputs.exports if e != "nav2"] + (["viewer"] if outputs.viewer else [])
    if streams or observers:
        log.info(
            "%s: no checkpoints (%s); --resume maps it again from its first frame",
            name,
            f"{', '.join(streams)} write as they go" if streams else "observers passed in",
        )
        return False
    return True


def _same_run(path: Path, config, outputs, source, name) -> bool:
    """Whether the checkpoint ``path`` was written for this scene's config (a damaged one or
    one of another version is refused naming it)."""
    from evgrid.checkpoint import read_header

    head, _ = read_header(path)
    if head["config_sha256"] != scene_config_hash(RunConfig(config, outputs, source), name):
        log.warning("%s: its checkpoint is of another config; mapping it from frame 0", name)
        return False
    return True


def _resumed(path, store, config, deep, name) -> dict[str, Any]:
    """The scene's state at its last checkpoint."""
    from evgrid.checkpoint import load_checkpoint
    from evgrid.mapper import deep_irm

    state, _ = load_checkpoint(path, store, lambda: deep or deep_irm(config))
    log.warning("resuming %s at frame %d", name, state["mapper"].n_frames)
    return state


def _map_with(
    state, frames, out, config, outputs, name, progress, observers, source, exporters,
    fixed_frame, saved,
) -> SceneResult:  # fmt: skip
    mapper, truth = state["mapper"], state["truth"]
    if "scores" not in state:  # else resumed: the observers are the checkpoint's
        scores = SceneScores(mapper.maps.maps, truth, track=outputs.convergence)
        gif = None
        if out is not None and outputs.figures:
            gif = GifRecorder(
                config.grid, outputs.gif_window_m, outputs.gif_step, outputs.gif_max_frames
            )
        mapper.observers += [truth, scores, *([gif] if gif else []), *exporters, *observers]
        state.update(scores=scores, gif=gif, exporters=list(exporters), costs=[], next_us=None)
    scores, gif, costs = state["scores"], state["gif"], state["costs"]
    frame_ms: list[float] = state["frame_ms"]  # mapper and observers, without reading the frame
    every_us = outputs.checkpoint_every_s * 1e6 if saved else None
    frames_iter = iter(frames)
    for k in range(mapper.n_frames):  # resumed: the frames mapped before the checkpoint
        if next(frames_iter, None) is None:
            raise ValueError(f"{name}: the source has {k} frames, the checkpoint {mapper.n_frames}")
        if progress is not None:
            progress()
    t0 = time.perf_counter() - state["seconds"]
    for frame in frames_iter:
        t = time.perf_counter()
        mapper.process(frame)
        frame_ms.append((time.perf_counter() - t) * 1e3)
        if progress is not None:
            progress()
        due = state["next_us"]  # of the drive's clock: the same frames in every run
        if every_us is not None and (due is None or frame.timestamp >= due):
            state["next_us"] = frame.timestamp + every_us
            if due is not None:
                state["seconds"] = time.perf_counter() - t0
                costs.append(_save_state(state, out, config, outputs, name, source))
    seconds = time.perf_counter() - t0
    if mapper.n_updates == 0:  # empty maps are no result: the scene fails, saying why
        raise NoFrameMapped(nothing_mapped(name, mapper.n_frames, frames))
    # the drive is over: its tiles to the store, so that what follows (the exports' final
    # maps above all) reads them from there and its memory does not come on top of theirs
    mapper.page_out_all()
    files: dict[str, str] = {}
    for fmt, exporter in zip(outputs.exports, exporters):
        written = exporter.close()
        if written:  # nav2: the files written (none when no update came)
            files[f"export_{fmt}"] = str(written[0] if isinstance(written, list) else written)
    if outputs.viewer:
        exporters[-1].close()
    metrics = _scene_metrics(name, mapper, scores, seconds, frame_ms)
    if costs:  # what the resumable states cost (docs/store.md)
        metrics["checkpoints"] = {
            "n": len(costs),
            **{f"{k}_mean": float(np.mean([c[k] for c in costs])) for k in costs[0]},
        }
    metrics.update(_source_report(frames))
    if out is not None:
        run = RunConfig(config, outputs, source, (name,) if source is not None else None)
        files["config"] = str(write_json(out / "config.json", run.to_dict()))
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
                    mapper.maps.dynamic.threshold,
                )
            )
        if outputs.save_maps:
            from evgrid.grid import MapFrame, save_map

            frame = MapFrame.of(mapper, fixed_frame)  # the file says where its cells lie
            for m_name, m in mapper.maps.maps.items():
                path = out / "maps" / f"{m_name}.npz"
                files[f"map_{m_name}"] = str(save_map(m, path, frame))
        # the scene is complete: its maps are in the files above, and the store goes
        shutil.rmtree(out / STORE_FOLDER, ignore_errors=True)
    return SceneResult(name, jsonable(metrics), files, metrics["frames_per_second"])


class NoFrameMapped(ValueError):
    """A scene of which no frame was mapped (every frame skipped, or none made): its maps would
    be empty, so the scene fails rather than give a table of n/a (docs/hostile-input.md)."""


def nothing_mapped(name: str, n_frames: int, frames: Any) -> str:
    """The one line saying why scene ``name`` mapped nothing: the frames made and the skips its
    source counted, each under its reason."""
    report = _source_report(frames).get("source_report", {})
    skips = {
        k: v
        for part in ("counts", "stats")
        for k, v in (report.get(part) or {}).items()
        if isinstance(v, int) and not isinstance(v, bool) and v > 0
    }
    why = (
        "; skipped: " + ", ".join(f"{k} {v}" for k, v in skips.items())
        if skips
        else "; the source skipped nothing it counts"
    )
    stopped = f"; {report['stopped']}" if report.get("stopped") else ""
    return f"{name}: no frame mapped ({n_frames} frame(s) made){why}{stopped}"


def _save_state(state, out, config, outputs, name, source) -> dict[str, float]:
    """Write the scene's resumable state (:mod:`evgrid.checkpoint`); returns its cost."""
    from evgrid.checkpoint import checkpoint_path, save_checkpoint

    mapper = state["mapper"]
    return save_checkpoint(
        checkpoint_path(out / STORE_FOLDER),
        state,
        mapper.store,
        mapper.deep,
        scene_config_hash(RunConfig(config, outputs, source), name),
    )


def _exporters(
    outputs: OutputConfig, out: Path | None, name: str, map_frame: str, fixed_frame: str
) -> list[Any]:
    """The recorders ``outputs.exports`` asks for, into the scene's folder (nav2 ``nav2/``,
    ``NAME.mcap``, ``NAME.rrd``), then the live viewer; each with its parameters from
    ``outputs`` and the run's frames.

    ``map_frame`` is :attr:`MapperConfig.frame`: with ``world`` the maps are in the recording's
    ``fixed_frame`` itself (the exports' map frame is that frame: no transform, origins in its
    coordinates); with ``first_pose`` they are in the map frame the parameters name, a parent
    of ``fixed_frame``.
    """
    from evgrid.export import make_observer

    if outputs.exports and out is None:
        raise ValueError("exports need a results folder (out_dir)")

    def framed(params: Any) -> Any:
        own = fixed_frame if map_frame == "world" else params.map_frame
        return replace(params, map_frame=own, fixed_frame=fixed_frame)

    params = {"nav2": outputs.nav2, "mcap": outputs.mcap, "rerun": outputs.rerun}
    paths: dict[str, Path] = {}
    if out is not None:
        paths = {"nav2": out / "nav2", "mcap": out / f"{name}.mcap", "rerun": out / f"{name}.rrd"}
        for fmt in ("mcap", "rerun"):  # temporary files of a run killed outright (SIGKILL)
            for tmp in out.glob(f".{paths[fmt].name}.*.part"):
                tmp.unlink(missing_ok=True)
    # the results folder is this run's (evgrid.outdir refused it otherwise), so the exports
    # replace what an earlier run left there
    found: list[Any] = []
    try:
        for fmt in outputs.exports:
            found.append(make_observer(fmt, paths[fmt], framed(params[fmt]), overwrite=True))
        if outputs.viewer:
            # rerun spawns its viewer by name: the one installed beside this interpreter (a
            # virtual environment's bin) is found even when that bin is not on PATH
            bin_dir = str(Path(sys.executable).parent)
            if bin_dir not in os.environ.get("PATH", "").split(os.pathsep):
                os.environ["PATH"] = os.pathsep.join([bin_dir, os.environ.get("PATH", "")])
            found.append(make_observer("rerun", None, framed(outputs.rerun)))
    except BaseException:
        for exporter in found:
            exporter.abort()
        raise
    return found


def _source_report(frames: Any) -> dict[str, Any]:
    """What the data source itself reports about the scene (bags: where a cut recording stopped;
    loaders: gap counts)."""
    found = {k: getattr(frames, k, None) for k in ("stopped", "counts", "stats")}
    report = {k: v for k, v in found.items() if v and not callable(v)}
    return {"source_report": report} if report else {}


#: Seconds of driving after which convergence is reported (paper: faster convergence with the deep
#: prior).
CONVERGENCE_TIMES_S: tuple[float, ...] = (1.0, 2.0, 5.0, 10.0)


def convergence_at(
    keyframes: list[dict[str, Any]], times_s: tuple[float, ...] = CONVERGENCE_TIMES_S
) -> dict[str, Any]:
    """Each map's perception field (free and occupied IoU against the truth, and the area classified
    correctly) at the first keyframe at least ``t`` seconds after the scene's first; ``None``
    past its end."""
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
    from evgrid.sources import fixed_frame_of

    source, name, out_dir, config, outputs, source_dict, on_frame, resume = args
    scene = source.load(name)
    progress = None
    if on_frame is not None:  # only in this process (a callback does not cross processes)
        total = len(scene) if hasattr(scene, "__len__") else None
        count = iter(range(1, 1 << 62))
        progress = lambda: on_frame(name, next(count), total)  # noqa: E731
    res = map_scene(
        scene,
        Path(out_dir) / name,
        config,
        outputs,
        name=name,
        overwrite=True,
        progress=progress,
        source=source_dict,
        fixed_frame=fixed_frame_of(source, scene),
        resume=resume,
    )
    return res.metrics


def scene_config_hash(run: RunConfig, name: str) -> str:
    """The hash a scene's completion marker and checkpoint hold: its mapper, outputs (the
    checkpoints' interval aside), source and name."""
    outputs = replace(run.outputs, checkpoint_every_s=OutputConfig.checkpoint_every_s)
    return config_hash(replace(run, outputs=outputs, scenes=(name,)))


#: Fields a resumed run may change: the scenes (more, or fewer), how often states are saved.
RESUME_MAY_CHANGE = ("scenes", "outputs.checkpoint_every_s")


def _check_same_config(path: Path, run: RunConfig) -> None:
    """``--resume`` continues the run of ``path`` (its config.json): a config that differs in
    any field but :data:`RESUME_MAY_CHANGE` is refused, naming the fields."""
    import json

    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return  # no run to continue: every scene is mapped
    changed = [
        k
        for k in _changed_fields(old, json.loads(json.dumps(jsonable(run.to_dict()))))
        if k not in RESUME_MAY_CHANGE
    ]
    if changed:
        raise ResultsExistError(
            f"{path}: --resume with a changed config ({', '.join(changed)}); resume with that "
            "config (drop the options that changed it), or recompute with --overwrite or "
            "another --out"
        )


def _changed_fields(old: Any, new: Any, prefix: str = "") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        keys = sorted(set(old) | set(new))
        return [
            k
            for key in keys
            for k in _changed_fields(old.get(key), new.get(key), prefix + key + ".")
        ]
    return [] if old == new else [prefix.rstrip(".")]


def summarize(per_scene: list[dict[str, Any]]) -> dict[str, Any]:
    """mIoU over scenes (against ray_ilm and, where known, the truth), speed and skip counts, from
    per-scene metrics."""

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
    scored = [m["dynamic"] for m in per_scene if m.get("dynamic")]
    if scored:  # cells called dynamic against the moving objects of the truth (simulator)
        out["dynamic"] = dynamic_summary(scored)
    left = [m["left_behind_m2"] for m in per_scene if m.get("left_behind_m2")]
    if left:  # the area movers leave behind that a map calls occupied (simulator)
        out["left_behind_m2"] = {
            n: bootstrap_interval(d[n] for d in left if n in d) for n in left[0]
        }
    return jsonable(out)


def _ci_cell(ci: Mapping[str, float] | None, scale: float, fmt: str) -> str:
    """A table cell of a bootstrap interval (``mean``, ``lo``, ``hi``, ``n`` scenes), scaled:
    the mean, with the interval once there are two scenes; n/a without any."""
    if not ci or ci["n"] == 0:
        return "n/a"
    v = format(ci["mean"] * scale, fmt)
    if ci["n"] < 2:
        return v
    return f"{v} ({format(ci['lo'] * scale, fmt)}-{format(ci['hi'] * scale, fmt)})"


def dynamic_table(summary: Mapping[str, Any]) -> str:
    """Markdown: per map, precision, recall and IoU of the cells called dynamic against the moving
    objects, and the area movers left behind that it calls occupied (mean over scenes, 95 %
    bootstrap interval)."""

    dyn = summary.get("dynamic", {})
    left = summary.get("left_behind_m2", {})
    lines = [
        "**moving objects** (simulator; mean over scenes, 95% bootstrap interval): the cells "
        "called dynamic against the moving objects the current ray ILM or IRM observed, in %, "
        "and the area movers left behind that a map calls occupied (m², mean over keyframes)",
        "",
        "| map | precision | recall | IoU | left behind m² |",
        "|---|---|---|---|---|",
    ]
    for name in dict.fromkeys([*dyn, *left]):
        d = dyn.get(name, {})
        row = [_ci_cell(d.get(k), 100, ".1f") if d else "-" for k in ("precision", "recall", "iou")]
        row.append(_ci_cell(left.get(name), 1, ".2f"))
        lines.append(f"| `{name}` | " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def convergence_table(conv: Mapping[str, Any]) -> str:
    """Markdown: per map, free and occupied IoU against the truth and the area classified correctly
    after each time."""
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

    for name, q in conv["maps"].items():
        row = (
            [_ci_cell(c, 100, ".1f") for c in q["free"]]
            + [_ci_cell(c, 100, ".1f") for c in q["occupied"]]
            + [_ci_cell(c, 1, ".0f") for c in q["area_m2"]]
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
    on_scene: Callable[[dict], None] | None = None,
    overwrite: bool = False,
    *,
    engine: str = "local",
    resume: bool = False,
    events: RunEvents | None = None,
) -> dict[str, Any]:
    """Map every scene of a source; write config, per-scene results as each scene finishes,
    summary and table. Returns the summary.

    Scenes run through :func:`evgrid.engine.fan_out` (``engine``, ``workers`` at once). Writes
    ``OUT/config.json`` (re-run with ``evgrid map --config``), ``OUT/<scene>/...`` with its own
    ``config.json`` and a completion marker, ``OUT/summary.json`` (``failed``: the scenes that
    raised, with their errors) and ``OUT/table.md``. With ``resume``, scenes complete for the
    same config are kept, those with a checkpoint continue from it and the rest are redone.
    Ctrl-C raises :class:`RunInterrupted`.
    """
    from evgrid.budget import check_budget
    from evgrid.engine import fan_out
    from evgrid.sources import scenes_of, source_to_dict

    check_budget(config, outputs, workers=workers)  # before any scene or file
    events = events or RunEvents()
    dropped = getattr(source, "dropped", None)
    dropped = dropped() if callable(dropped) else {}
    names = scenes_of(source, names)
    source_dict = source_to_dict(source)
    run = RunConfig(config, outputs, source_dict, tuple(names))
    with results_folder(out_dir, overwrite, resume) as out:
        if resume:
            _check_same_config(out / "config.json", run)
        write_json(out / "config.json", run.to_dict())
        hashes = {n: scene_config_hash(run, n) for n in names}
        done: dict[str, dict[str, Any]] = {}
        if resume:
            done = {n: m for n in names if (m := is_complete(out / n, hashes[n])) is not None}
        failed: dict[str, str] = {}
        todo = [n for n in names if n not in done]
        events.start(todo, list(done), dropped)
        # fan_out runs jobs in this process with one worker or one job: frames can be shown
        in_process = engine == "local" and (workers <= 1 or len(todo) <= 1)
        on_frame = events.frame if in_process else None
        jobs = [
            (n, (source, n, str(out), config, outputs, source_dict, on_frame, resume)) for n in todo
        ]
        try:
            for o in fan_out(_map_one, jobs, engine=engine, workers=workers):
                if o.ok:
                    mark_complete(out / o.key, hashes[o.key])  # last: the scene is whole
                    done[o.key] = o.result
                    (on_scene or events.scene)(o.result)
                else:
                    failed[o.key] = o.error
                    log.error("scene %s failed: %s", o.key, o.error)
                    events.failed(o.key, o.error)
        except KeyboardInterrupt:
            raise RunInterrupted(out, [n for n in names if n in done], len(names)) from None
        return _write_summary(out, [done[n] for n in names if n in done], failed, dropped, outputs)


def _write_summary(
    out: Path,
    per_scene: list[dict[str, Any]],
    failed: dict[str, str],
    dropped: Mapping[str, str],
    outputs: OutputConfig,
) -> dict[str, Any]:
    summary = summarize(per_scene) if per_scene else {"maps": {}, "scenes": []}
    summary["failed"] = failed
    summary["dropped"] = dict(dropped)
    if "ray_ilm" not in summary["maps"] and per_scene:
        summary["no_reference"] = (
            "no IoU can be computed: the maps mapped do not include the reference ray_ilm"
        )
    write_json(out / "summary.json", summary)
    if not per_scene:
        return summary
    n = len(summary["scenes"])
    table = markdown_table(
        {k: v for k, v in summary["maps"].items() if k != "ray_ilm"},
        title=f"{n} scene(s), against ray_ilm",
        intervals=summary.get("maps_interval"),
    )
    if "no_reference" in summary:
        table = f"{summary['no_reference']} (add it with --maps ray_ilm,...)\n"
    if "vs_truth" in summary:
        table += "\n" + markdown_table(
            summary["vs_truth"],
            title="against the true occupancy (simulator)",
            paper=False,
            intervals=summary.get("vs_truth_interval"),
        )
    if "dynamic" in summary or "left_behind_m2" in summary:
        table += "\n" + dynamic_table(summary)
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
    "the highest m_u_min whose deep_disc mIoU (mean of the three classes, against ray_ilm) is "
    "within 0.01 of the best value swept: cells known only to the deep IRM stay as clearly apart "
    "from verified space as accuracy allows; at m_u_min >= 0.5 such cells can never be "
    "classified free or occupied"
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
    *,
    engine: str = "local",
    events: RunEvents | None = None,
) -> dict[str, Any]:
    """mIoU against ray_ilm of deep_replace, deep_disc and fused for each ``m_u_min``; writes
    ``config.json`` (a :class:`~evgrid.config.SweepConfig`: ``evgrid sweep-m-u-min --config``
    re-runs it), ``m_u_min_sweep.json`` (``failed``: scenes that raised) and a plot.

    ISMs are computed and warped once per update and shared by one map set per value.
    """
    from evgrid.engine import fan_out
    from evgrid.render import plot_m_u_min_sweep
    from evgrid.sources import scenes_of, source_to_dict

    events = events or RunEvents()
    names = scenes_of(source, names)
    sweep = SweepConfig(config, source_to_dict(source), tuple(names), tuple(values))
    jobs = [(n, (source, n, list(values), config)) for n in names]
    with results_folder(out_dir, overwrite) as out:
        write_json(out / "config.json", {**sweep_document(sweep)})
        events.start(names, [], {})
        per_scene, failed = [], {}
        for o in fan_out(_sweep_one, jobs, engine=engine, workers=workers):
            if o.ok:
                per_scene.append(o.result)
                events.scene({"scene": o.key})
            else:
                failed[o.key] = o.error
                events.failed(o.key, o.error)
        if not per_scene:
            raise RuntimeError(f"every scene of the sweep failed: {failed}")
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
        result = jsonable(
            {
                "scenes": [s["scene"] for s in per_scene],
                "rows": rows,
                "chosen": chosen,
                "rule": CHOICE_RULE,
                "failed": failed,
            }
        )
        write_json(out / "m_u_min_sweep.json", result)
        plot_m_u_min_sweep(rows, SWEPT_MAPS, out / "m_u_min_sweep.png", chosen)
    return result


def sweep_document(sweep: SweepConfig) -> dict[str, Any]:
    """A sweep's config as its results folder keeps it."""
    from evgrid.config import document

    return document(sweep)


def choose_m_u_min(rows: list[dict], tolerance: float = 0.01) -> float:
    """The m_u_min picked from sweep rows by :data:`CHOICE_RULE`."""
    best = max(r["mean_of_classes"]["deep_disc"] for r in rows)
    return max(r["m_u_min"] for r in rows if r["mean_of_classes"]["deep_disc"] >= best - tolerance)
