"""What decides a run, as typed configs that dump to JSON and load back; one serialiser for all.

A run writes its config as ``config.json`` beside its results (and each scene folder its own,
naming its source and scene); ``evgrid map --config OUT/config.json`` reads it back and maps the
same scenes the same way (KISS-ICP's rule: a results folder reproduces its run). A config is
resolved in one place, :func:`resolve_config`: the file (or the defaults), then overrides
``KEY=VALUE`` with dotted keys such as ``mapper.fusion.m_u_min=0.4``; the command line's options
are such overrides (:data:`MAP_OPTIONS`). :func:`to_dict` and :func:`from_dict` serialise every
parameter dataclass of evgrid: unknown keys and bad values are errors naming the field.
See docs/config.md.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evgrid.data.radar_filter import RadarFilter
from evgrid.export.mcap import McapParams
from evgrid.export.nav2 import Nav2Params
from evgrid.export.rerun import RerunParams
from evgrid.fusion import MAP_NAMES, RULES, DynamicParams, FusionParams
from evgrid.geometry import GridSpec
from evgrid.ism.deep import RadarImageParams
from evgrid.ism.lidar import RayIlmParams
from evgrid.ism.radar import RayIrmParams
from evgrid.ism.runtime import RUNTIMES
from evgrid.ism.self_returns import SelfReturnParams
from evgrid.nav import NavParams
from evgrid.serial import ConfigError, from_dict, to_dict
from evgrid.store import StoreParams
from evgrid.validation import check_choice, check_int, check_number

__all__ = [
    "PoseLimits",
    "MapperConfig",
    "OutputConfig",
    "RunConfig",
    "SweepConfig",
    "ConfigError",
    "to_dict",
    "from_dict",
    "config_hash",
    "document",
    "load_config",
    "load_run_config",
    "resolve_config",
    "parse_overrides",
    "options_to_overrides",
    "MAP_OPTIONS",
    "SWEEP_OPTIONS",
    "config_from_args",
    "available_cores",
]

_FORMAT_VERSION = 1

#: Largest local grid and map tile a config may ask for: a float32 mass grid takes 12 bytes a
#: cell, several buffers of it per map, and a typo (100000 cells) would otherwise try to
#: allocate hundreds of GiB before anything is said.
MAX_GRID_CELLS = 8192
MAX_TILE_CELLS = 4096
_BYTES_PER_CELL = 12  # [m_f, m_o, m_u] in float32

#: The frames maps can be built in (:attr:`MapperConfig.frame`): the recording's fixed frame
#: itself, or the first ego pose's frame (the paper's figures).
MAP_FRAMES: tuple[str, ...] = ("world", "first_pose")


def config_hash(obj: Any) -> str:
    """SHA-256 of a config's plain JSON (sorted keys): what a completion marker records."""
    import hashlib

    text = json.dumps(to_dict(obj), sort_keys=True, allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def available_cores() -> int:
    """CPU cores this process may run on (its affinity, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


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
    """Everything that decides the maps of a run (the core of
    :class:`~evgrid.mapper.OccupancyMapper`)."""

    grid: GridSpec = field(default_factory=GridSpec)
    fusion: FusionParams = field(default_factory=FusionParams)
    dynamic: DynamicParams = field(default_factory=DynamicParams)  # moving objects' score
    # the navigation map's clearance around the lidar's returns (docs/equations.md)
    nav: NavParams = field(default_factory=NavParams)
    maps: tuple[str, ...] = MAP_NAMES
    lidar: RayIlmParams = field(default_factory=RayIlmParams)  # ray ILM
    # The ego vehicle's own lidar returns, removed before the ray ILM (docs/rigs.md#self-returns).
    self_returns: SelfReturnParams = field(default_factory=SelfReturnParams)
    # Radar detections kept by their validity fields, before any radar ISM; the same as in training.
    radar_filter: RadarFilter = field(default_factory=RadarFilter)
    radar: RayIrmParams = field(default_factory=RayIrmParams)  # ray IRM (n_sweeps: the paper's N)
    image: RadarImageParams = field(default_factory=RadarImageParams)  # the deep IRM's input
    # Ev-Net weights; None = the shipped checkpoint. In a file, relative to the file's folder.
    checkpoint: str | None = None
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
    # The map frame: "world", the recording's fixed frame (nuScenes global, a rig's
    # world_frame, the simulator's world), axis-aligned with it, so map files and exports need
    # no transform; or "first_pose", the first ego pose's frame, as in the paper's figures.
    frame: str = "world"
    # Tiles farther than store.resident_m from the vehicle live on disk (docs/store.md); the
    # maps are the same bit for bit whatever the radius.
    store: StoreParams = field(default_factory=StoreParams)

    def __post_init__(self) -> None:
        check_choice(self, "runtime", choices=RUNTIMES)
        check_choice(self, "frame", choices=MAP_FRAMES)
        unknown = [m for m in self.maps if m not in RULES]  # Table I's six, and nav
        if unknown or not self.maps:
            raise ValueError(
                f"MapperConfig.maps: unknown map name(s) {unknown}; choose from {tuple(RULES)}"
            )
        check_number(self, "update_rate_hz", min=0.0, min_open=True)
        check_int(self, "threads", min=1)
        cores = available_cores()
        if self.threads > cores:
            # a thousand threads on two cores print nothing for minutes and stall the machine
            raise ValueError(
                f"MapperConfig.threads: {self.threads} threads on a machine with {cores} "
                f"core(s); use at most {cores}"
            )
        _check_cells("MapperConfig.grid.n_cells", self.grid.n_cells, MAX_GRID_CELLS, "local grid")
        check_int(self, "tile_cells", min=8)
        _check_cells("MapperConfig.tile_cells", self.tile_cells, MAX_TILE_CELLS, "map tile")

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (see :func:`from_dict`)."""
        return to_dict(self)


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
    viewer: bool = False  # a live rerun viewer
    # Each export's parameters (docs/ros.md). Their map_frame and fixed_frame are the run's:
    # the recording's fixed frame, and the map frame of MapperConfig.frame.
    nav2: Nav2Params = field(default_factory=Nav2Params)
    mcap: McapParams = field(default_factory=McapParams)
    rerun: RerunParams = field(default_factory=RerunParams)

    def __post_init__(self) -> None:
        from evgrid.export import FORMATS

        bad = [e for e in self.exports if e not in FORMATS]
        if bad:
            raise ValueError(
                f"OutputConfig.exports: unknown format(s) {bad}; choose from {FORMATS}"
            )
        for key, cls in (("nav2", Nav2Params), ("mcap", McapParams), ("rerun", RerunParams)):
            if not isinstance(getattr(self, key), cls):
                raise ValueError(
                    f"OutputConfig.{key} must be {cls.__name__}, got {getattr(self, key)!r}"
                )
        check_number(self, "gif_window_m", min=0.0, min_open=True)
        check_int(self, "gif_step", min=1)
        check_int(self, "gif_max_frames", min=2)


def _check_cells(label: str, n: int, limit: int, what: str) -> None:
    if n > limit:
        gib = n * n * _BYTES_PER_CELL / 2**30
        size = f"{gib / 1024:.1f} TiB" if gib >= 1024 else f"{gib:.1f} GiB"
        raise ValueError(
            f"{label}: {n} cells a side would take {size} per {what} of masses; at most {limit}"
        )


@dataclass(frozen=True)
class RunConfig:
    """A mapping run: the mapper, the outputs, where the scenes come from and which ones.

    ``source`` is a scene source as :func:`evgrid.sources.source_to_dict` writes it; ``scenes``
    None means every scene of the source. A scene folder's config names its one scene.
    """

    mapper: MapperConfig = field(default_factory=MapperConfig)
    outputs: OutputConfig = field(default_factory=OutputConfig)
    source: dict[str, Any] | None = None
    scenes: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if self.source is not None:
            from evgrid.sources import source_from_dict

            source_from_dict(self.source)  # a bad source is an error when loading, not mapping

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form, tagged with the file format and the evgrid version that wrote it."""
        return document(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "config") -> RunConfig:
        """Inverse of :meth:`to_dict`; raises :class:`ConfigError` naming the bad field."""
        return _from_document(cls, d, where)


@dataclass(frozen=True)
class SweepConfig:
    """``evgrid sweep-m-u-min``: the mapper, the scenes and the ``m_u_min`` values swept."""

    mapper: MapperConfig = field(default_factory=MapperConfig)
    source: dict[str, Any] | None = None
    scenes: tuple[str, ...] | None = None
    values: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)

    def __post_init__(self) -> None:
        if not self.values or any(not 0.0 <= v <= 1.0 for v in self.values):
            raise ValueError(f"SweepConfig.values must be masses in [0, 1], got {self.values}")


#: The ``format`` tag of each kind of config file (evgrid.train_run adds ``evgrid-train``).
FORMATS: dict[type, str] = {RunConfig: "evgrid-run", SweepConfig: "evgrid-sweep"}


def document(obj: Any) -> dict[str, Any]:
    """A config as the JSON a results folder keeps: format tag, version, evgrid version, fields."""
    import evgrid

    tag = {"format": FORMATS[type(obj)], "version": _FORMAT_VERSION, "evgrid": evgrid.__version__}
    return {**tag, **to_dict(obj)}


def _from_document(cls: type, d: Any, where: str, required: Sequence[str] = ()) -> Any:
    if not isinstance(d, Mapping):
        raise ConfigError(f"{where}: expected a JSON object, got {type(d).__name__}")
    d = dict(d)
    tag = d.pop("format", FORMATS[cls])
    if tag != FORMATS[cls]:
        raise ConfigError(f"{where}: a config of format {tag!r}, not {FORMATS[cls]!r}")
    version = d.pop("version", _FORMAT_VERSION)
    if version != _FORMAT_VERSION:
        raise ConfigError(
            f"{where}: config version {version!r}; this evgrid reads {_FORMAT_VERSION}"
        )
    d.pop("evgrid", None)
    _refuse_replaced(d, where)
    return from_dict(cls, d, where, required)


#: Fields that earlier versions wrote and that are gone: (section, field) -> what replaced them.
REPLACED_FIELDS: dict[tuple[str, str], str] = {
    ("outputs", "export_window_m"): (
        "outputs.mcap.window_m (default 40 m; --mcap-window); the MCAP export's other "
        "parameters are under outputs.mcap"
    ),
}


def _refuse_replaced(d: dict, where: str) -> None:
    """A config that still has a field of :data:`REPLACED_FIELDS` is an error naming it: read
    silently, it would change what the run writes."""
    for (section, name), instead in REPLACED_FIELDS.items():
        node = d.get(section)
        if isinstance(node, Mapping) and name in node:
            raise ConfigError(
                f"{where}: {section}.{name} is no longer a field; set {instead} instead"
            )


#: Keys whose string values are paths: in a config file they are relative to the file's folder.
PATH_KEYS = frozenset({"checkpoint", "dataroot", "folder", "paths", "rig", "init"})


def _absolute(d: Any, base: Path) -> Any:
    if isinstance(d, dict):
        return {
            k: (_absolute_path(v, base) if k in PATH_KEYS else _absolute(v, base))
            for k, v in d.items()
        }
    return d


def _absolute_path(v: Any, base: Path) -> Any:
    if isinstance(v, str):
        return str(base / v) if not os.path.isabs(v) else v
    if isinstance(v, list):
        return [_absolute_path(x, base) for x in v]
    return v


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ConfigError(f"{path}: not a readable JSON config ({e})") from None


#: The kinds of config file that other modules own, imported when a file names them.
_KIND_OWNERS = {
    "evgrid-train": "evgrid.train_run",
    "evgrid-simulate": "evgrid.sim_writer",
    "evgrid-bench": "evgrid.bench",
}


def load_config(path: str | os.PathLike, cls: type | None = RunConfig) -> Any:
    """Read a config file of kind ``cls`` (None: the kind its ``format`` names); every section
    must be there, paths are taken relative to the file's folder; raises :class:`ConfigError`
    naming the file and the problem."""
    if cls is None:
        d = _read_json(Path(path))
        tag = d.get("format", FORMATS[RunConfig]) if isinstance(d, dict) else None
        if tag in _KIND_OWNERS:
            importlib.import_module(_KIND_OWNERS[tag])  # registers its kind in FORMATS
        kinds = {t: c for c, t in FORMATS.items()}
        if tag not in kinds:
            raise ConfigError(f"{path}: not an evgrid config (format {tag!r}; known {list(kinds)})")
        cls = kinds[tag]
    return resolve_config(cls, path)


def load_run_config(path: str | os.PathLike) -> RunConfig:
    """Read a run's ``config.json`` (see :func:`load_config`)."""
    return load_config(path, RunConfig)


def resolve_config(
    cls: type,
    path: str | os.PathLike | None = None,
    overrides: Iterable[tuple[str, Any]] = (),
    base: Any = None,
) -> Any:
    """The one way a config is made: the file at ``path`` (else ``base``, else the defaults),
    then each override ``(dotted key, value)`` in order; a string value is parsed by the field's
    type (``"0.4"``, ``"true"``, ``"a,b"``, ``"none"``, JSON). Errors name the file and field."""
    if path is not None:
        path = Path(path)
        where = str(path)
        d = _read_json(path)
        if not isinstance(d, dict):
            raise ConfigError(f"{where}: expected a JSON object, got {type(d).__name__}")
        d = _absolute(d, path.resolve().parent)
        required = [f.name for f in dataclasses.fields(cls) if f.init]
    else:
        where = "config"
        d = document(base if base is not None else cls())
        required = []
    for key, value in overrides:
        _override(cls, d, key, value, where)
    return _from_document(cls, d, where, required)


def _override(cls: type, d: dict, key: str, value: Any, where: str) -> None:
    parts = key.split(".")
    tp: Any = cls
    node = d
    for i, part in enumerate(parts):
        here = ".".join(parts[: i + 1])
        if dataclasses.is_dataclass(tp):
            hints = typing.get_type_hints(tp)
            if part not in hints:
                known = [f.name for f in dataclasses.fields(tp) if f.init]
                raise ConfigError(
                    f"{where}: no field {here!r}; {'.'.join(parts[:i]) or 'the config'} has {known}"
                )
            tp = hints[part]
        else:  # inside a free-form section (the scene source): JSON values
            tp = Any
        if i == len(parts) - 1:
            if isinstance(value, str):
                value = _parse(tp, value, f"{where}: {key}")
            if part in PATH_KEYS and isinstance(value, str):
                value = os.path.abspath(value)  # given on the command line: from here
            node[part] = value
            return
        if node.get(part) is None:
            if not _optional_dataclass(tp) and tp is not Any:
                raise ConfigError(f"{where}: {here} is not a section")
            node[part] = to_dict(_optional_dataclass(tp)()) if _optional_dataclass(tp) else {}
        node = node[part]
        if not isinstance(node, dict):
            raise ConfigError(f"{where}: {here} is a value, not a section")
        tp = _optional_dataclass(tp) or tp


def _optional_dataclass(tp: Any) -> Any:
    for a in (tp, *typing.get_args(tp)):
        if dataclasses.is_dataclass(a):
            return a
    return None


_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


def _parse(tp: Any, text: str, where: str) -> Any:
    """A command-line string as a value of type ``tp`` (plain JSON, as a config file holds)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    s = text.strip()
    try:
        if origin in (typing.Union, types.UnionType):
            if s.lower() in ("none", "null") and type(None) in args:
                return None
            inner = [a for a in args if a is not type(None)]
            return _parse(inner[0], text, where) if len(inner) == 1 else json.loads(s)
        if tp is bool:
            if s.lower() not in _TRUE + _FALSE:
                raise ValueError(f"expected true or false, got {text!r}")
            return s.lower() in _TRUE
        if tp in (int, float):
            return tp(s)
        if tp is str:
            return text
        if s.startswith(("[", "{")):
            return json.loads(s)
        if origin is tuple:
            parts = [p.strip() for p in s.split(",") if p.strip()]
            kinds = [args[0]] * len(parts) if len(args) == 2 and args[1] is Ellipsis else args
            return [_parse(k, p, where) for k, p in zip(kinds, parts)]
        if dataclasses.is_dataclass(tp):  # "a,b,c": its fields in order (a box: x0,y0,...)
            fs = [f for f in dataclasses.fields(tp) if f.init]
            parts = s.split(",")
            hints = typing.get_type_hints(tp)
            if len(parts) != len(fs):
                raise ValueError(f"expected {len(fs)} values {[f.name for f in fs]}, got {text!r}")
            return {f.name: _parse(hints[f.name], p, where) for f, p in zip(fs, parts)}
    except ConfigError:
        raise
    except (ValueError, json.JSONDecodeError) as e:
        raise ConfigError(f"{where}: {e}") from None
    try:
        return json.loads(s)
    except json.JSONDecodeError:
        return text


def parse_overrides(items: Iterable[str]) -> list[tuple[str, str]]:
    """``["mapper.fusion.m_u_min=0.4", ...]`` (``--set``) as ``(key, text)`` pairs."""
    out = []
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. mapper.fusion.m_u_min=0.4")
        out.append((key.strip(), value))
    return out


#: The command line's short options for a mapping run, each an override of config fields
#: (``--set KEY=VALUE`` sets any field). ``KEY=VALUE`` entries are implied, applied first.
MAP_OPTIONS: dict[str, tuple[str, ...]] = {
    "checkpoint": ("mapper.checkpoint",),
    "m-u-min": ("mapper.fusion.m_u_min",),
    "dynamic": ("mapper.dynamic.enabled",),
    "dynamic-gate": ("mapper.dynamic.gate_maps",),
    "update-rate": ("mapper.update_rate_hz",),
    "maps": ("mapper.maps",),
    "lidar-min-range": ("mapper.lidar.min_range_m",),
    "max-speed": ("mapper.poses.max_speed_mps",),
    "self-returns": ("mapper.self_returns.mode",),
    "body-box": (
        "mapper.self_returns.mode=box",
        "mapper.self_returns.body",
        "mapper.self_returns.prior",
    ),
    "radar-filter": ("mapper.radar_filter.mode",),
    "threads": ("mapper.threads",),
    "save-maps": ("outputs.save_maps",),
    "figures": ("outputs.figures",),
    "export": ("outputs.exports",),
    "mcap-window": ("outputs.mcap.window_m",),
    "mcap-rate": ("outputs.mcap.rate_hz",),
    "mcap-maps": ("outputs.mcap.maps",),
    "mcap-layers": ("outputs.mcap.layers",),
    "map-frame": ("mapper.frame",),
    "viewer": ("outputs.viewer",),
}


def _field_type(cls: type, key: str) -> Any:
    tp: Any = cls
    for part in key.split("."):
        dc = _optional_dataclass(tp)
        if dc is None:
            return Any
        tp = typing.get_type_hints(dc).get(part, Any)
    return tp


def options_to_overrides(
    args: Sequence[str],
    aliases: Mapping[str, tuple[str, ...]],
    cls: type,
    plain: type | None = None,
) -> tuple[list[tuple[str, str]], dict[str, Any]]:
    """Parse ``--name VALUE``, ``--name=VALUE``, ``--flag [on|off]`` and ``--no-flag`` options.

    An option of ``aliases`` becomes overrides of ``cls``'s fields; an option named after a
    field of the dataclass ``plain`` (``--sim-dir`` for ``sim_dir``) is returned by field name,
    parsed by its type (a tuple field repeats). Returns ``(overrides, plain values)``.
    """
    plain_types = typing.get_type_hints(plain) if plain else {}
    implied: list[tuple[str, str]] = []
    given: list[tuple[str, str]] = []
    values: dict[str, Any] = {}
    i = 0
    while i < len(args):
        arg = args[i]
        if not arg.startswith("--"):
            raise ConfigError(f"unexpected argument {arg!r}")
        name, eq, text = arg[2:].partition("=")
        negated = name.startswith("no-") and name[3:] in {**aliases, **_dashed(plain_types)}
        name = name[3:] if negated else name
        if name in aliases:
            keys = [k for k in aliases[name] if "=" not in k]
            tp = _field_type(cls, keys[0])
        elif name in _dashed(plain_types):
            tp = plain_types[_dashed(plain_types)[name]]
        else:
            known = sorted([*aliases, *_dashed(plain_types)])
            raise ConfigError(f"no such option --{name}; options: --{', --'.join(known)}")
        if tp is bool and not eq:
            # --flag, --no-flag, or --flag on|off (a value with a space, as for other options)
            value = args[i + 1].strip().lower() if i + 1 < len(args) and not negated else ""
            if value in _TRUE + _FALSE:
                i += 1
                text = value
            else:
                text = "false" if negated else "true"
        elif not eq:
            i += 1
            if i >= len(args):
                raise ConfigError(f"--{name} needs a value")
            text = args[i]
        i += 1
        if name in aliases:
            for k in aliases[name]:
                if "=" in k:
                    implied.append(tuple(k.split("=", 1)))  # type: ignore[arg-type]
                else:
                    given.append((k, text))
            continue
        field_name = _dashed(plain_types)[name]
        where = f"--{name}"
        if typing.get_origin(tp) is tuple:  # repeatable
            values[field_name] = (*values.get(field_name, ()), text)
        else:
            values[field_name] = _parse(tp, text, where)
    return implied + given, values


def _dashed(hints: Mapping[str, Any]) -> dict[str, str]:
    return {n.replace("_", "-"): n for n in hints}


def options_help(aliases: Mapping[str, tuple[str, ...]], plain: type | None = None) -> str:
    """The options of :func:`options_to_overrides`, one a line, for a command's help."""
    lines = [f"--{n}: {', '.join(keys)}" for n, keys in aliases.items()]
    if plain is not None:
        defaults = {f.name: f.default for f in dataclasses.fields(plain)}
        for n, f in _dashed(typing.get_type_hints(plain)).items():
            lines.append(f"--{n} (default {defaults[f]!r})")
    return "\b\n" + "\n".join(lines)  # \b: click keeps the lines as they are


#: The options of ``evgrid sweep-m-u-min``: the mapper's, and the values swept.
SWEEP_OPTIONS: dict[str, tuple[str, ...]] = {
    **{k: v for k, v in MAP_OPTIONS.items() if v[0].startswith("mapper.")},
    "values": ("values",),
}


def config_from_args(
    cls: type,
    args: Sequence[str],
    path: str | os.PathLike | None = None,
    sets: Iterable[str] = (),
    preset: Iterable[tuple[str, Any]] = (),
    data_defaults: Mapping[str, Any] | None = None,
    resume: str | os.PathLike | None = None,
) -> Any:
    """A run's config (:class:`RunConfig` or :class:`SweepConfig`) from command-line words: the
    file at ``path`` (else, when resuming the results folder ``resume``, its config.json; else
    the defaults), the command's ``preset``, the scene source of the data options
    (:class:`evgrid.sources.DataOptions`, over ``data_defaults``; given or without a file, they
    replace the file's scenes), the short options of :data:`MAP_OPTIONS` (or
    :data:`SWEEP_OPTIONS`), then ``--set`` overrides, in that order."""
    from evgrid.sources import DataOptions, source_to_dict

    if path is None and resume and (Path(resume) / "config.json").is_file():
        path = Path(resume) / "config.json"  # the run being continued

    aliases = SWEEP_OPTIONS if cls is SweepConfig else MAP_OPTIONS
    overrides, data = options_to_overrides(args, aliases, cls, DataOptions)
    scene = data.pop("scene", None)
    source: list[tuple[str, Any]] = []
    if data or path is None:
        src = DataOptions(**{**(data_defaults or {}), **data}).source()
        source = [("source", source_to_dict(src)), ("scenes", None)]
    if scene:
        source.append(("scenes", list(scene)))
    return resolve_config(cls, path, [*preset, *source, *overrides, *parse_overrides(sets)])


#: Each command's config options, for its help: (short options table, plain options class).
COMMAND_OPTIONS: dict[str, tuple[str | None, str]] = {
    "map": ("evgrid.config:MAP_OPTIONS", "evgrid.sources:DataOptions"),
    "train": ("evgrid.train_run:TRAIN_OPTIONS", "evgrid.train_run:TrainData"),
    "simulate": (None, "evgrid.sim_writer:SimulateOptions"),
    "sweep-m-u-min": ("evgrid.config:SWEEP_OPTIONS", "evgrid.sources:DataOptions"),
}


def command_options_help(command: str) -> str:
    """The end of a command's help: the options it takes from the config (evaluate, demo and
    ``config show`` take those of map)."""
    import importlib

    def load(spec: str | None) -> Any:
        if spec is None:
            return {}
        module, _, name = spec.partition(":")
        return getattr(importlib.import_module(module), name)

    aliases, plain = map(load, COMMAND_OPTIONS.get(command, COMMAND_OPTIONS["map"]))
    return f"Config options (--set KEY=VALUE sets any field):\n\n{options_help(aliases, plain)}"
