"""The size budget: every size a user can set is bounded by the memory it implies.

A window of 1200 m, a grid of 8192 cells or a GIF window of 1e7 m is a valid number, but the
arrays it implies would take GBs to PiBs; numpy would say so (``Unable to allocate 2.73 PiB``)
only after a scene was mapped, naming no option. :func:`check_budget` computes, from a run's
config alone and before any scene starts, the memory each setting implies (:func:`costs`, from
the arrays the code allocates for it) and refuses, in one line naming the config key, its
command-line option and the cost, any that exceeds the budget, and then their sum.

The budget (:func:`memory_budget`): ``EVGRID_MEMORY_BUDGET_GB`` when set, else a quarter of
the memory this process may use (the machine's, or its container's limit when lower). See
docs/hostile-input.md#sizes.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from evgrid.io import size_text
from evgrid.serial import ConfigError

__all__ = [
    "BUDGET_ENV",
    "BudgetError",
    "Cost",
    "check_budget",
    "costs",
    "machine_memory",
    "memory_budget",
]

#: The environment variable that sets the budget in GB (a number, e.g. ``12`` or ``0.5``).
BUDGET_ENV = "EVGRID_MEMORY_BUDGET_GB"
#: The share of the memory the budget takes by default.
DEFAULT_SHARE = 0.25

# Bytes a cell of each array costs, from the arrays the code allocates (float32 masses: 12 B,
# a coverage bool: 1 B, a float32 layer: 4 B).
#: A map of the mapper per local-grid cell: its ISM's local grid (12), the warper's padded copy
#: (12) and warped grid (12), the map's tiles under the local grid (13) and the update's masks
#: and temporaries, rounded up (measured in docs/hostile-input.md#sizes).
MAP_CELL_BYTES = 64
#: A map tile per cell: masses (12), coverage (1), the dynamic score when kept (4).
TILE_CELL_BYTES = 13
DYNAMIC_CELL_BYTES = 4
#: An MCAP window per cell and map (export/mcap.py ``_write_maps``): the cells read (masses 12,
#: coverage 1), P(occ) (4), classes and masks (3), the ROS-order copy (1) and the serialised
#: message with its copy (2) for the occupancy grid ...
MCAP_OCCUPANCY_BYTES = 23
#: ... and per GridMap layer: the layer's column-major copy (4), its serialised bytes and their
#: copy (8), the rounded score's temporaries (4); the dynamic layer also reads the score (4).
MCAP_LAYER_BYTES = 16
#: A picture pixel (render.sample_map, map_picture): the masses and coverage sampled (13), the
#: RGB picture (3) and its temporaries (4).
PICTURE_PIXEL_BYTES = 20
RGB_BYTES = 3


class BudgetError(ConfigError):
    """A setting whose memory exceeds the budget; the message names the option and the cost."""


@dataclass(frozen=True)
class Cost:
    """The memory ``bytes`` that the setting ``key`` (config key; ``option``: its command-line
    option, if any) implies; ``what`` says what it pays for."""

    key: str
    bytes: float
    what: str
    option: str | None = None

    def name(self) -> str:
        return f"{self.key} ({self.option})" if self.option else self.key


def machine_memory() -> int:
    """Bytes of memory this process may use: the machine's, or its cgroup's limit when lower."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for limit_file in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(limit_file) as f:
                text = f.read(64).strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < total:
            total = int(text)
        break
    return total


def memory_budget(environ: Mapping[str, str] = os.environ) -> int:
    """The budget in bytes: ``EVGRID_MEMORY_BUDGET_GB`` (GB, 1e9 bytes) when set, else a
    quarter of :func:`machine_memory`."""
    text = environ.get(BUDGET_ENV)
    if text is None or not text.strip():
        return int(machine_memory() * DEFAULT_SHARE)
    try:
        gb = float(text)
    except ValueError:
        gb = math.nan
    if not (gb > 0 and math.isfinite(gb)):
        raise ConfigError(f"{BUDGET_ENV}={text!r}: must be a positive number of GB")
    return int(gb * 1e9)


def option_names(options: Mapping[str, tuple[str, ...]] | None) -> dict[str, str]:
    """Config key -> ``--option`` from the command line's option table (``evgrid.cli.options.
    MAP_OPTIONS``, passed by the command line; a library call names the config keys alone)."""
    out: dict[str, str] = {}
    for name, keys in (options or {}).items():
        for k in keys:
            if "=" not in k:
                out.setdefault(k, f"--{name}")
    return out


def costs(
    mapper: Any,
    outputs: Any = None,
    options: Mapping[str, tuple[str, ...]] | None = None,
) -> list[Cost]:
    """The memory each size setting of a run implies, for one scene: ``mapper`` a
    ``MapperConfig`` (or a ``RunConfig``, whose outputs are then used), ``outputs`` an
    ``OutputConfig`` (None: no outputs)."""
    if outputs is None and hasattr(mapper, "outputs"):
        mapper, outputs = mapper.mapper, mapper.outputs
    opt = option_names(options)
    grid = mapper.grid
    res = grid.resolution
    n_maps = len(mapper.maps)
    dynamic = bool(getattr(mapper.dynamic, "enabled", False))
    out: list[Cost] = []

    def add(key: str, nbytes: float, what: str) -> None:
        out.append(Cost(key, float(nbytes), what, opt.get(key)))

    cells = float(grid.n_cells) ** 2
    add(
        "mapper.grid.n_cells",
        cells * MAP_CELL_BYTES * n_maps,
        f"{n_maps} map(s) on a local grid of {grid.n_cells} x {grid.n_cells} cells",
    )
    t = int(mapper.tile_cells)
    per_side = math.ceil(grid.n_cells / t) + 1  # the tiles a local grid can touch
    tile_bytes = TILE_CELL_BYTES + (DYNAMIC_CELL_BYTES if dynamic else 0)
    add(
        "mapper.tile_cells",
        n_maps * per_side**2 * float(t) ** 2 * tile_bytes,
        f"{per_side**2} tiles of {t} x {t} cells under the local grid, for each of {n_maps} map(s)",
    )
    if outputs is not None:
        _output_costs(outputs, res, n_maps, add)
    return out


def _output_costs(
    outputs: Any, res: float, n_maps: int, add: Callable[[str, float, str], None]
) -> None:
    """The memory of the outputs' windows: the MCAP window, the GIF frames kept, the rerun
    picture (each passed to ``add``)."""
    exports = tuple(outputs.exports)
    mcap = outputs.mcap
    if "mcap" in exports and mcap.window_m > 0:
        n = float(math.ceil(mcap.window_m / res))
        layers = [k for k in mcap.layers if k != "occupancy"]
        per_cell = (MCAP_OCCUPANCY_BYTES if "occupancy" in mcap.layers else 13) + (
            MCAP_LAYER_BYTES * len(layers) + (DYNAMIC_CELL_BYTES if "dynamic" in layers else 0)
        )
        n_window = len(mcap.maps) if mcap.maps else 1
        if n_window > 1:
            per_cell += 13  # the previous map's cells, alive while the next ones are read
        add(
            "outputs.mcap.window_m",
            n * n * per_cell,
            f"an MCAP window of {mcap.window_m:g} m ({n:.0f} x {n:.0f} cells) at each write",
        )
    if getattr(outputs, "figures", False):
        side = float(math.ceil(round(outputs.gif_window_m / res) / outputs.gif_step))
        px = side * side
        kept = outputs.gif_max_frames + 1
        add(
            "outputs.gif_window_m",
            kept * n_maps * px * RGB_BYTES + px * PICTURE_PIXEL_BYTES,
            f"a GIF of up to {kept - 1} frames of {n_maps} picture(s) of {side:.0f} x {side:.0f} "
            f"pixels ({outputs.gif_window_m:g} m at one pixel per {outputs.gif_step} cells)",
        )
    rerun = outputs.rerun
    if "rerun" in exports or getattr(outputs, "viewer", False):
        side = float(math.ceil(round(rerun.window_m / res) / rerun.step))
        add(
            "outputs.rerun.window_m",
            side * side * (PICTURE_PIXEL_BYTES + RGB_BYTES),
            f"a rerun picture of {rerun.window_m:g} m ({side:.0f} x {side:.0f} pixels) per map",
        )


def check_budget(
    mapper: Any,
    outputs: Any = None,
    workers: int = 1,
    budget: int | None = None,
    options: Mapping[str, tuple[str, ...]] | None = None,
) -> list[Cost]:
    """Refuse, with a :class:`BudgetError` naming the option and what it would cost, a run whose
    settings imply more memory than ``budget`` bytes (None: :func:`memory_budget`); first each
    setting alone (the most expensive named), then their sum over ``workers`` scenes mapped at
    once. Returns the costs."""
    budget = memory_budget() if budget is None else int(budget)
    found = costs(mapper, outputs, options)
    where = (
        f"the memory budget of {size_text(budget)} (set {BUDGET_ENV}, in GB, to change it; "
        "docs/hostile-input.md#sizes)"
    )
    over = [c for c in found if c.bytes > budget]
    if over:
        c = max(over, key=lambda c: c.bytes)
        raise BudgetError(
            f"{c.name()}: {c.what} would take {size_text(c.bytes)}, more than {where}"
        )
    total = sum(c.bytes for c in found) * max(1, int(workers))
    if total > budget:
        top = sorted(found, key=lambda c: -c.bytes)[:3]
        each = ", ".join(f"{c.name()} {size_text(c.bytes)}" for c in top)
        scenes = f" x {workers} scenes at once" if workers > 1 else ""
        raise BudgetError(
            f"this run would take {size_text(total)} ({each}{scenes}), more than {where}"
        )
    return found
