"""The one override parser: a command's short options (its table: overrides of config fields),
option group (a dataclass's fields, :mod:`evgrid.cli.groups`) and ``--set KEY=VALUE``."""

from __future__ import annotations

import os
import typing
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from evgrid.cli.groups import DataOptions, TrainData

from evgrid.config import ConfigError, SweepConfig, resolve_config  # isort: skip
from evgrid.config import FALSE_WORDS, TRUE_WORDS, field_type, parse_value  # isort: skip
from evgrid.sources import source_to_dict

#: The short options of a mapping run, each an override of config fields (``--set KEY=VALUE``
#: sets any field). ``KEY=VALUE`` entries are implied, applied first.
MAP_OPTIONS: dict[str, tuple[str, ...]] = {
    "checkpoint": ("mapper.checkpoint",), "m-u-min": ("mapper.fusion.m_u_min",),
    "dynamic": ("mapper.dynamic.enabled",), "dynamic-gate": ("mapper.dynamic.gate_maps",),
    "update-rate": ("mapper.update_rate_hz",), "maps": ("mapper.maps",),
    "lidar-min-range": ("mapper.lidar.min_range_m",),
    "max-speed": ("mapper.poses.max_speed_mps",),
    "self-returns": ("mapper.self_returns.mode",), "body-box": (
        "mapper.self_returns.mode=box", "mapper.self_returns.body", "mapper.self_returns.prior",
    ),
    "radar-filter": ("mapper.radar_filter.mode",), "threads": ("mapper.threads",),
    "save-maps": ("outputs.save_maps",), "figures": ("outputs.figures",),
    "export": ("outputs.exports",), "mcap-window": ("outputs.mcap.window_m",),
    "mcap-rate": ("outputs.mcap.rate_hz",), "mcap-maps": ("outputs.mcap.maps",),
    "mcap-layers": ("outputs.mcap.layers",), "map-frame": ("mapper.frame",),
    "viewer": ("outputs.viewer",), "checkpoint-every": ("outputs.checkpoint_every_s",),
}  # fmt: skip

#: The options of ``evgrid sweep-m-u-min``: the mapper's, and the values swept.
SWEEP_OPTIONS = {k: v for k, v in MAP_OPTIONS.items() if v[0].startswith("mapper.")}
SWEEP_OPTIONS["values"] = ("values",)

#: ``evgrid train``'s short options, each an override of the training run's config.
TRAIN_OPTIONS: dict[str, tuple[str, ...]] = {
    "epochs": ("train.epochs",), "batch-size": ("train.batch_size",), "lr": ("train.lr",),
    "workers": ("train.workers",), "frame-stride": ("train.frame_stride",),
    "width": ("train.model.width",), "depth": ("train.model.depth",),
    "self-returns": ("train.self_returns.mode",), "body-box": (
        "train.self_returns.mode=box", "train.self_returns.body", "train.self_returns.prior",
    ),
    "radar-filter": ("train.radar_filter.mode",), "init": ("train.init",),
    "precision": ("train.precision",), "engine": ("train.engine",),
    "cache-workers": ("train.cache_workers",), "target": ("train.target.kind",),
    "target-rule": ("train.target.rule",),
}  # fmt: skip

#: Each command's options beyond its own: (short options, option group); evaluate, demo and
#: ``config show`` take those of map.
COMMAND_OPTIONS: dict[str, tuple[Mapping[str, tuple[str, ...]], type]] = {
    "map": (MAP_OPTIONS, DataOptions),
    "train": (TRAIN_OPTIONS, TrainData),
    "simulate": ({}, None),
    "bench": ({}, None),
    "sweep-m-u-min": (SWEEP_OPTIONS, DataOptions),
}


def parse_overrides(items: Iterable[str]) -> list[tuple[str, str]]:
    """``["mapper.fusion.m_u_min=0.4", ...]`` (``--set``) as ``(key, text)`` pairs."""
    out = []
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. mapper.fusion.m_u_min=0.4")
        out.append((key.strip(), value))
    return out


def _dashed(cls: type | None) -> dict[str, tuple[str, Any]]:
    """An option group's options: ``--sim-dir`` -> (``sim_dir``, its type)."""
    hints = typing.get_type_hints(cls) if cls else {}
    return {n.replace("_", "-"): (n, tp) for n, tp in hints.items()}


def _option_type(name: str, aliases: Mapping, group: Mapping, cls: type) -> Any:
    """The type of --``name``: its field's in ``cls`` (an alias) or in the plain group."""
    if name in aliases:
        return field_type(cls, next(k for k in aliases[name] if "=" not in k))
    if name in group:
        return group[name][1]
    raise ConfigError(
        f"no such option --{name}; options: --{', --'.join(sorted([*aliases, *group]))}"
    )


def options_to_overrides(
    args: Sequence[str],
    aliases: Mapping[str, tuple[str, ...]],
    cls: type,
    plain: type | None = None,
) -> tuple[list[tuple[str, str]], dict[str, Any]]:
    """Parse ``--name VALUE``, ``--name=VALUE``, ``--flag [on|off]`` and ``--no-flag`` options.

    An option of ``aliases`` becomes overrides of ``cls``'s fields; an option named after a
    field of the option group ``plain`` (``--sim-dir`` for ``sim_dir``) is returned by field
    name, parsed by its type (a tuple field repeats). Returns ``(overrides, plain values)``.
    """
    group = _dashed(plain)
    implied: list[tuple[str, str]] = []
    given: list[tuple[str, str]] = []
    values: dict[str, Any] = {}
    i = 0
    while i < len(args):
        arg = args[i]
        if not arg.startswith("--"):
            raise ConfigError(f"unexpected argument {arg!r}")
        name, eq, text = arg[2:].partition("=")
        negated = name.startswith("no-") and name[3:] in {**aliases, **group}
        name = name[3:] if negated else name
        tp = _option_type(name, aliases, group, cls)
        if tp is bool and not eq:
            # --flag, --no-flag, or --flag on|off (a value with a space, as for other options)
            value = args[i + 1].strip().lower() if i + 1 < len(args) and not negated else ""
            if value in TRUE_WORDS + FALSE_WORDS:
                i, text = i + 1, value
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
                key, implies, fixed = k.partition("=")
                (implied if implies else given).append((key, fixed if implies else text))
        elif typing.get_origin(tp) is tuple:  # repeatable
            values[group[name][0]] = (*values.get(group[name][0], ()), text)
        else:
            values[group[name][0]] = parse_value(tp, text, f"--{name}")
    return implied + given, values


def command_options_help(command: str) -> list[tuple[str, list[tuple[str, str]]]]:
    """The help's sections of the options a command takes from its config: (title, rows of
    ``--name METAVAR`` and what the field it sets means), written from the fields' own docs."""
    from evgrid.config import RunConfig
    from evgrid.fielddoc import field_help, metavar, shown

    aliases, plain = COMMAND_OPTIONS.get(command, COMMAND_OPTIONS["map"])
    if plain is None:  # the simulator's (evgrid_sim imports slowly: only for their help)
        from evgrid_lab import options

        plain = options.SimulateOptions if command == "simulate" else options.BenchOptions
    cls = SweepConfig if command == "sweep-m-u-min" else RunConfig
    if command == "train":
        from evgrid.train_run import TrainRunConfig as cls
    rows, data = [], []
    for name, keys in aliases.items():
        key = next(k for k in keys if "=" not in k)
        tp, doc, default = field_help(cls, key)
        also = "".join(f"; sets {k}" for k in keys if "=" in k)
        rows.append((f"--{name} {metavar(tp)}", f"{doc} [{key}{also}; default {shown(default)}]"))
    for name, (f, _) in _dashed(plain).items():
        tp, doc, default = field_help(plain, f)
        data.append((f"--{name} {metavar(tp)}", f"{doc} [default {shown(default)}]"))
    what = {"simulate": "Simulation options", "bench": "Bench options"}.get(command)
    title = what or f"Data options (the scenes it {'trains on' if command == 'train' else 'maps'})"
    config = [("Config options (--set KEY=VALUE sets any field)", rows)] if rows else []
    return [*config, (title, data)]


def _file(path: Any, resume: Any) -> Any:
    """The config file to start from: ``path``, else the results folder being continued's."""
    if path is None and resume and (Path(resume) / "config.json").is_file():
        return Path(resume) / "config.json"
    return path


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
    the defaults), the command's ``preset``, the scene source of the data options (over
    ``data_defaults``; given or without a file, they replace the file's scenes), the short
    options of :data:`MAP_OPTIONS` (or :data:`SWEEP_OPTIONS`), then ``--set``, in that order."""
    path = _file(path, resume)
    aliases = SWEEP_OPTIONS if cls is SweepConfig else MAP_OPTIONS
    overrides, data = options_to_overrides(args, aliases, cls, DataOptions)
    scene = data.pop("scene", None)
    source: list[tuple[str, Any]] = []
    if data or path is None:
        src = DataOptions(**{**(data_defaults or {}), **data}).source()
        source = [("source", source_to_dict(src)), ("scenes", None)]
    if scene:
        source.append(("scenes", list(scene)))
    items = [*preset, *source, *overrides, *parse_overrides(sets)]
    return resolve_config(cls, path, items, options=aliases)


def train_config_from_args(
    args: Sequence[str],
    path: str | os.PathLike | None = None,
    sets: Iterable[str] = (),
    resume: str | os.PathLike | None = None,
) -> Any:
    """``evgrid train``'s config from command-line words: the file (else, resuming the run
    folder ``resume``, its config.json; else the defaults), the data options of
    :class:`TrainData` (given or without a file), the short options of :data:`TRAIN_OPTIONS`,
    then ``--set``."""
    from evgrid.train_run import TrainRunConfig, resolve_train_config

    path = _file(path, resume)
    overrides, data = options_to_overrides(args, TRAIN_OPTIONS, TrainRunConfig, TrainData)
    source = TrainData(**data).overrides() if data or path is None else []
    return resolve_train_config(path, [*source, *overrides, *parse_overrides(sets)])
