"""What decides a mapping run, as typed configs that dump to JSON and load back.

A run writes its :class:`RunConfig` as ``config.json`` beside its results; ``evgrid map --config
OUT/config.json`` reads it back and maps the same scenes the same way (KISS-ICP's rule: a results
folder reproduces its run). Every field can be set in that file; the common ones also on the
command line.
"""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from evgrid.data.radar_filter import RadarFilter
from evgrid.fusion import MAP_NAMES, RULES, FusionParams
from evgrid.geometry import GridSpec
from evgrid.ism.deep import RadarImageParams
from evgrid.ism.lidar import RayIlmParams
from evgrid.ism.radar import RayIrmParams
from evgrid.ism.runtime import RUNTIMES
from evgrid.ism.self_returns import SelfReturnParams
from evgrid.validation import check_choice, check_int, check_number

__all__ = [
    "PoseLimits",
    "MapperConfig",
    "OutputConfig",
    "RunConfig",
    "ConfigError",
    "from_dict",
    "load_run_config",
]

_FORMAT = "evgrid-run"
_FORMAT_VERSION = 1


class ConfigError(ValueError):
    """A configuration file or value that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class PoseLimits:
    """What a vehicle can do between two frames; a pose beyond it is an odometry glitch, not motion.

    A frame whose ego pose moved faster than ``max_speed_mps`` or turned faster than
    ``max_yaw_rate_dps`` since the last accepted frame (each plus a small slack for pose noise)
    is skipped and reported; if no plausible pose comes back within ``max_glitch_s`` the run
    stops with an error naming the time. Positions beyond ``max_position_m`` from the global
    origin are errors (no map frame is that large).
    """

    max_speed_mps: float = 100.0
    max_yaw_rate_dps: float = 360.0
    slack_m: float = 1.0
    slack_deg: float = 10.0
    max_glitch_s: float = 2.0
    max_position_m: float = 1e8

    def __post_init__(self) -> None:
        for name in ("max_speed_mps", "max_yaw_rate_dps", "max_glitch_s", "max_position_m"):
            check_number(self, name, min=0.0, min_open=True)
        for name in ("slack_m", "slack_deg"):
            check_number(self, name, min=0.0)


@dataclass(frozen=True)
class MapperConfig:
    """Everything that decides the maps of a run (the core of :class:`~evgrid.mapper.OccupancyMapper`)."""

    grid: GridSpec = field(default_factory=GridSpec)
    fusion: FusionParams = field(default_factory=FusionParams)
    maps: tuple[str, ...] = MAP_NAMES
    lidar: RayIlmParams = field(default_factory=RayIlmParams)  # ray ILM
    # The ego vehicle's own lidar returns, removed before the ray ILM (docs/rigs.md#self-returns).
    self_returns: SelfReturnParams = field(default_factory=SelfReturnParams)
    # Radar detections kept by their validity fields, before any radar ISM; the same as in training.
    radar_filter: RadarFilter = field(default_factory=RadarFilter)
    radar: RayIrmParams = field(default_factory=RayIrmParams)  # ray IRM (n_sweeps: the paper's N)
    image: RadarImageParams = field(default_factory=RadarImageParams)  # the deep IRM's input
    checkpoint: str | None = None  # Ev-Net weights; None = the shipped checkpoint
    # Map updates per second. The paper's 133,708 training samples over ~700 nuScenes scenes of
    # 20 s are ~10 Hz, not the 2 Hz keyframes; at 2 Hz, m_f = 0.05 per ray ILM update would
    # leave hardly any cell free. Keyframes are always updated (they are where maps are scored).
    update_rate_hz: float = 10.0
    poses: PoseLimits = field(default_factory=PoseLimits)
    threads: int = 1
    tile_cells: int = 256
    runtime: str = (
        "auto"  # Ev-Net's inference: auto (ONNX Runtime when installed), onnxruntime, torch
    )

    def __post_init__(self) -> None:
        check_choice(self, "runtime", choices=RUNTIMES)
        unknown = [m for m in self.maps if m not in RULES]  # Table I's six, and nav
        if unknown or not self.maps:
            raise ValueError(
                f"MapperConfig.maps: unknown map name(s) {unknown}; choose from {tuple(RULES)}"
            )
        check_number(self, "update_rate_hz", min=0.0, min_open=True)
        check_int(self, "threads", min=1)
        check_int(self, "tile_cells", min=8)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (see :func:`from_dict`)."""
        return _plain(asdict(self))


@dataclass(frozen=True)
class OutputConfig:
    """What a run writes besides ``metrics.json``; none of it changes the maps.

    The GIF follows the vehicle: each frame shows ``gif_window_m`` metres around it at one
    pixel per ``gif_step`` cells, and a long drive keeps at most ``gif_max_frames`` frames (every
    second keyframe, then every fourth, ...), so its cost does not grow with the drive.
    """

    figures: bool = True
    convergence: bool = True  # IoU at every keyframe (the paper's convergence claim)
    save_maps: bool = False
    gif_window_m: float = 80.0
    gif_step: int = 8
    gif_max_frames: int = 240
    # nav2 (PGM + YAML of the final maps), mcap (maps and poses per keyframe), rerun (.rrd)
    exports: tuple[str, ...] = ()
    export_window_m: float = 100.0  # the MCAP export's square around the vehicle
    viewer: bool = False  # a live rerun viewer

    def __post_init__(self) -> None:
        from evgrid.export import FORMATS

        bad = [e for e in self.exports if e not in FORMATS]
        if bad:
            raise ValueError(
                f"OutputConfig.exports: unknown format(s) {bad}; choose from {FORMATS}"
            )
        check_number(self, "export_window_m", min=0.0, min_open=True)
        check_number(self, "gif_window_m", min=0.0, min_open=True)
        check_int(self, "gif_step", min=1)
        check_int(self, "gif_max_frames", min=2)


@dataclass(frozen=True)
class RunConfig:
    """A whole run: the mapper, the outputs, and (for runs over a scene source) where the scenes came from."""

    mapper: MapperConfig = field(default_factory=MapperConfig)
    outputs: OutputConfig = field(default_factory=OutputConfig)
    source: dict[str, Any] | None = None  # see evgrid.sources.source_to_dict
    scenes: tuple[str, ...] | None = None  # None: every scene of the source

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form, tagged with the file format and the evgrid version that wrote it."""
        import evgrid

        return {
            "format": _FORMAT,
            "version": _FORMAT_VERSION,
            "evgrid": evgrid.__version__,
            **_plain(asdict(self)),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "config") -> RunConfig:
        """Inverse of :meth:`to_dict`; raises :class:`ConfigError` naming the bad field."""
        if not isinstance(d, dict):
            raise ConfigError(f"{where}: expected a JSON object, got {type(d).__name__}")
        d = dict(d)
        if d.pop("format", _FORMAT) != _FORMAT:
            raise ConfigError(f"{where}: not an evgrid run config (format {d.get('format')!r})")
        version = d.pop("version", _FORMAT_VERSION)
        if version != _FORMAT_VERSION:
            raise ConfigError(
                f"{where}: run config version {version!r}; this evgrid reads {_FORMAT_VERSION}"
            )
        d.pop("evgrid", None)
        return from_dict(cls, d, where)


def _plain(x: Any) -> Any:
    """Tuples to lists, recursively (JSON has no tuples)."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


def from_dict(cls: type, d: Any, where: str | None = None) -> Any:
    """Build dataclass ``cls`` from plain JSON, nested dataclasses included; unknown keys are errors."""
    where = where or cls.__name__
    if not isinstance(d, dict):
        raise ConfigError(f"{where}: expected an object, got {d!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(d) - set(names))
    if unknown:
        raise ConfigError(f"{where}: unknown field(s) {unknown}; known: {names}")
    kwargs = {}
    for name in names:
        if name not in d:
            continue
        kwargs[name] = _convert(hints[name], d[name], f"{where}.{name}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: {e}") from None


def _convert(tp: Any, v: Any, where: str) -> Any:
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, v, where)
    if args and type(None) in args:  # X | None
        if v is None:
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _convert(inner, v, where)
    if typing.get_origin(tp) is tuple:
        if not isinstance(v, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {v!r}")
        return tuple(v)
    return v


def load_run_config(path: str | os.PathLike) -> RunConfig:
    """Read a run's ``config.json``; raises :class:`ConfigError` naming the file and the problem."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ConfigError(f"{path}: not a readable JSON config ({e})") from None
    return RunConfig.from_dict(d, str(path))
