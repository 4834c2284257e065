"""What decides a run, as typed configs that dump to JSON and load back; one serialiser for all.

A run writes its config as ``config.json`` beside its results (and each scene folder its own,
naming its source and scene); ``evgrid map --config OUT/config.json`` reads it back and maps the
same scenes the same way (KISS-ICP's rule: a results folder reproduces its run). A config is
resolved in one place, :func:`resolve_config`: the file (or the defaults), then overrides
``KEY=VALUE`` with dotted keys such as ``mapper.fusion.m_u_min=0.4``; the command line's options
are such overrides (evgrid.cli.options). :func:`to_dict` and :func:`from_dict` serialise every
parameter dataclass of evgrid: unknown keys and bad values are errors naming the field.
See docs/config.md.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
import re
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evgrid.budget import option_names
from evgrid.export.mcap import McapParams
from evgrid.export.nav2 import Nav2Params
from evgrid.export.rerun import RerunParams
from evgrid.fusion import MAP_NAMES, RULES, DynamicParams, FusionParams
from evgrid.geometry import GridSpec
from evgrid.ism.deep import RadarImageParams
from evgrid.ism.evidence import EvidenceParams
from evgrid.ism.lidar import RayIlmParams
from evgrid.ism.prior_guard import PriorGuardParams
from evgrid.ism.radar import RayIrmParams
from evgrid.ism.runtime import RUNTIMES
from evgrid.nav import NavParams
from evgrid.package import SHIPPED_CHECKPOINTS
from evgrid.preprocess import PoseLimits, RadarFilter, SelfReturnParams
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
    "parse_value",
    "field_type",
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
class MapperConfig:
    """Everything that decides the maps of a run (the core of
    :class:`~evgrid.mapper.OccupancyMapper`)."""

    grid: GridSpec = field(default_factory=GridSpec)
    fusion: FusionParams = field(default_factory=FusionParams)
    dynamic: DynamicParams = field(default_factory=DynamicParams)  # moving objects' score
    # the navigation map's clearance around the lidar's returns (docs/equations.md)
    nav: NavParams = field(default_factory=NavParams)
    #: the maps built, comma-separated: any of ray_ilm, deep_acc, deep_replace, deep_disc,
    #: ray_irm, fused (Table I's six) and nav (the navigation map)
    maps: tuple[str, ...] = MAP_NAMES
    lidar: RayIlmParams = field(default_factory=RayIlmParams)  # ray ILM
    # The ego vehicle's own lidar returns, removed before the ray ILM (docs/rigs.md#self-returns).
    self_returns: SelfReturnParams = field(default_factory=SelfReturnParams)
    # Radar detections kept by their validity fields, before any radar ISM; the same as in training.
    radar_filter: RadarFilter = field(default_factory=RadarFilter)
    radar: RayIrmParams = field(default_factory=RayIrmParams)  # ray IRM (n_sweeps: the paper's N)
    #: the free mass of one ray ILM / ray IRM update: per metre of travel, or the paper's
    #: constant per look (mode per_look); docs/equations.md#evidence-per-distance-seen
    evidence: EvidenceParams = field(default_factory=EvidenceParams)
    image: RadarImageParams = field(default_factory=RadarImageParams)  # the deep IRM's input
    #: what the deep IRM's prior may not say: occupied without radar support, occupied on the
    #: vehicle's own path (docs/equations.md#the-deep-irms-guards)
    prior_guard: PriorGuardParams = field(default_factory=PriorGuardParams)
    #: Ev-Net weights: a .safetensors file (in a config file relative to the file's folder) or
    #: the name of a shipped one (shipped, sim-v1, sim-v2; docs/training.md); none: shipped
    checkpoint: str | None = None
    #: map updates per second; keyframes are always updated (they are where maps are scored)
    # The paper's 133,708 training samples over ~700 nuScenes scenes of 20 s are ~10 Hz, not the
    # 2 Hz keyframes. With evidence.mode "per_look" (the paper's constants), m_f = 0.05 per ray
    # ILM update at 2 Hz would leave hardly any cell free; evidence per metre does not depend on
    # the rate.
    update_rate_hz: float = 10.0
    poses: PoseLimits = field(default_factory=PoseLimits)
    threads: int = 1  #: threads of one scene's map updates (at most the machine's cores)
    tile_cells: int = 256
    runtime: str = (
        "auto"  # Ev-Net's inference: auto (ONNX Runtime when installed), onnxruntime, torch
    )
    #: the map frame: world|first_pose (the recording's fixed frame, or the first ego pose's)
    # "world", the recording's fixed frame (nuScenes global, a rig's
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

    figures: bool = True  #: the maps' figures and the GIF of each scene
    convergence: bool = True  # IoU at every keyframe (the paper's convergence claim)
    save_maps: bool = False  #: the final maps as SCENE/maps/NAME.npz (evgrid export reads them)
    gif_window_m: float = 80.0
    gif_step: int = 8
    gif_max_frames: int = 240
    #: exports, comma-separated: nav2 (PGM + YAML of the final maps), mcap (maps and poses per
    #: keyframe), rerun (.rrd); docs/ros.md
    exports: tuple[str, ...] = ()
    viewer: bool = False  #: show the maps live in a rerun viewer (needs evgrid[rerun])
    #: seconds of the drive between two resumable states of a scene, which --resume continues
    #: from (docs/store.md); 0: none
    checkpoint_every_s: float = 60.0
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
        named = ("mcap.maps", "mcap.final_maps", "mcap.navigation", "nav2.maps", "nav2.navigation")
        for key in named:  # the maps named by the exports
            section, name = key.split(".")
            unknown = [m for m in getattr(getattr(self, section), name) or () if m not in RULES]
            if unknown:  # else each scene fails at its first update, after the run started
                raise ValueError(
                    f"OutputConfig.{key}: unknown map name(s) {unknown}; choose from {tuple(RULES)}"
                )
        check_number(self, "gif_window_m", min=0.0, min_open=True)
        check_int(self, "gif_step", min=1)
        check_int(self, "gif_max_frames", min=2)
        check_number(self, "checkpoint_every_s", min=0.0)


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
    #: the m_u_min values swept, comma-separated masses in [0, 1]
    values: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)

    def __post_init__(self) -> None:
        if not self.values or any(not 0.0 <= v <= 1.0 for v in self.values):
            raise ValueError(f"SweepConfig.values must be masses in [0, 1], got {self.values}")


#: The ``format`` tag of each kind of config file (evgrid.train_run adds ``evgrid-train``, the
#: command line those of ``evgrid simulate`` and ``evgrid bench``).
FORMATS: dict[type, str] = {RunConfig: "evgrid-run", SweepConfig: "evgrid-sweep"}


def document(obj: Any) -> dict[str, Any]:
    """A config as the JSON a results folder keeps: format tag, version, evgrid version, fields."""
    from evgrid.package import __version__

    tag = {"format": FORMATS[type(obj)], "version": _FORMAT_VERSION, "evgrid": __version__}
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
        # a shipped checkpoint's name (evgrid.package.SHIPPED_CHECKPOINTS) is not a path
        return v if os.path.isabs(v) or v in SHIPPED_CHECKPOINTS else str(base / v)
    if isinstance(v, list):
        return [_absolute_path(x, base) for x in v]
    return v


def _read_json(path: Path) -> Any:
    from evgrid.io import InputFileError, load_json_bounded  # at most 16 MiB, read bounded

    try:
        return load_json_bounded(path, "config")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except InputFileError as e:
        raise ConfigError(str(e)) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ConfigError(f"{path}: not a readable JSON config ({e})") from None


#: Kinds of config file whose owner registers them in :data:`FORMATS` at its import, and is
#: imported only when a file names it (kind -> module); the command line fills it.
KIND_MODULES: dict[str, str] = {}


def load_config(path: str | os.PathLike, cls: type | None = RunConfig) -> Any:
    """Read a config file of kind ``cls`` (None: the kind its ``format`` names); every section
    must be there, paths are taken relative to the file's folder; raises :class:`ConfigError`
    naming the file and the problem."""
    if cls is None:
        d = _read_json(Path(path))
        tag = d.get("format", FORMATS[RunConfig]) if isinstance(d, dict) else None
        if tag in KIND_MODULES:
            importlib.import_module(KIND_MODULES[tag])  # registers its kind in FORMATS
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
    options: Mapping[str, tuple[str, ...]] | None = None,
) -> Any:
    """The one way a config is made: the file at ``path`` (else ``base``, else the defaults),
    then each override ``(dotted key, value)`` in order; a string value is parsed by the field's
    type (``"0.4"``, ``"true"``, ``"a,b"``, ``"none"``, JSON). Errors name the file and field,
    and the command-line option that sets it from ``options`` (its option table)."""
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
    try:
        return _from_document(cls, d, where, required)
    except ConfigError as e:
        # "config.outputs: OutputConfig.mcap.maps: ..." is the field outputs.mcap.maps
        m = re.match(rf"{re.escape(where)}\.?([\w.]*): [A-Z]\w*\.([\w.]+)", str(e))
        key = m and ".".join(filter(None, m.groups()))
        if key and (opt := option_names(options).get(key)):
            raise ConfigError(f"{opt}: {e}") from None
        raise


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
                value = parse_value(tp, value, f"{where}: {key}")
            if part in PATH_KEYS and isinstance(value, str):
                value = _absolute_path(value, Path.cwd())  # given on the command line: from here
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


#: The words a boolean field reads from text (docs/config.md).
TRUE_WORDS, FALSE_WORDS = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


def parse_value(tp: Any, text: str, where: str) -> Any:
    """Text (an override's value) as a value of a field of type ``tp``, in plain JSON as a
    config file holds it."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    s = text.strip()
    try:
        if origin in (typing.Union, types.UnionType):
            if s.lower() in ("none", "null") and type(None) in args:
                return None
            inner = [a for a in args if a is not type(None)]
            return parse_value(inner[0], text, where) if len(inner) == 1 else json.loads(s)
        if tp is bool:
            if s.lower() not in TRUE_WORDS + FALSE_WORDS:
                raise ValueError(f"expected on|off (or true|false, yes|no, 1|0), got {text!r}")
            return s.lower() in TRUE_WORDS
        if tp in (int, float):
            return tp(s)
        if tp is str:
            return text
        if s.startswith(("[", "{")):
            return json.loads(s)
        if origin is tuple:
            parts = [p.strip() for p in s.split(",") if p.strip()]
            kinds = [args[0]] * len(parts) if len(args) == 2 and args[1] is Ellipsis else args
            return [parse_value(k, p, where) for k, p in zip(kinds, parts)]
        if dataclasses.is_dataclass(tp):  # "a,b,c": its fields in order (a box: x0,y0,...)
            fs = [f for f in dataclasses.fields(tp) if f.init]
            parts = s.split(",")
            hints = typing.get_type_hints(tp)
            if len(parts) != len(fs):
                raise ValueError(f"expected {len(fs)} values {[f.name for f in fs]}, got {text!r}")
            return {f.name: parse_value(hints[f.name], p, where) for f, p in zip(fs, parts)}
    except ConfigError:
        raise
    except (ValueError, json.JSONDecodeError) as e:
        raise ConfigError(f"{where}: {e}") from None
    try:
        return json.loads(s)
    except json.JSONDecodeError:
        return text


def field_type(cls: type, key: str) -> Any:
    """The type of the field at dotted ``key`` of the config class ``cls`` (Any inside a
    free-form section)."""
    tp: Any = cls
    for part in key.split("."):
        dc = _optional_dataclass(tp)
        if dc is None:
            return Any
        tp = typing.get_type_hints(dc).get(part, Any)
    return tp
