"""The map update rules of the paper's Table I, declared once; a set of maps updated in one pass.

:data:`RULES` is the one table of the rules: each row names a map, the inputs its per-cell
kernel reads, the kernel's code in :mod:`evgrid.kernels` and the parameters it uses. The
paper's six maps (:data:`MAP_NAMES`), and a navigation map computed when asked for:

==============  ==========================================================================
``ray_ilm``     map = map (+)_D ray ILM (the reference)
``deep_acc``    map = map (+)_D deep IRM
``deep_replace`` m = limit_unknown(deep IRM, m_u_min); cell := m where m_u(m) < m_u(map)
``deep_disc``   m = limit_unknown(deep IRM, m_u_min); map = map (+)_Y (gamma (x) m)
``ray_irm``     map = map (+)_D ray IRM
``fused``       the deep_disc step, then map = map (+)_D ray IRM
``nav``         the ray_ilm map (+)_D the fused map, the fused map's free mass ignored within
                a margin of the lidar's returns and of fused obstacles, its occupied mass
                where the lidar's evidence is free-dominant (:mod:`evgrid.nav`)
==============  ==========================================================================

:class:`MapSet` updates any of them in one pass per time step (:meth:`MapSet.update`, the
only route by which a map is updated); the ``update_*`` functions apply one rule to dense
views (the same kernel, for users and tests). ISM cells that are vacuous leave a map cell
unchanged under the six rules, so kernels skip them. ISM cells that are not masses (NaN or
inf, a negative mass, a sum off 1 by more than ``evgrid.kernels.MASS_ATOL``) leave it
unchanged too: each rule returns how many it rejected (docs/hostile-input.md). The paper's
equations behind each rule: docs/equations.md#the-six-maps-of-table-i.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from evgrid.geometry import MAX_POSE_M, SE2, GridSpec
from evgrid.grid import EvidentialMap, MapWindow, Warper, warp_window, window_affine
from evgrid.kernels import (
    BLOCK,
    DYNAMIC_RULES,
    RULE_DEEP_DISC,
    RULE_DEEP_REPLACE,
    RULE_DEMPSTER,
    RULE_FUSED,
    RULE_NAV,
    DopplerDiscs,
    MapTiles,
    PassSources,
    RuleTable,
    TilePiece,
    WindowAffine,
    band_columns,
    informative_blocks,
    rows,
    update_rows,
    warp_update,
    window_spans,
)
from evgrid.nav import NavParams, nav_dense, refresh
from evgrid.store import TileStore, tile_distance_m
from evgrid.validation import check_number

__all__ = [
    "MAP_NAMES",
    "NAV_MAP",
    "ISM_NAMES",
    "FusionParams",
    "DynamicParams",
    "UpdateRule",
    "RULES",
    "update_ray_ilm",
    "update_deep_acc",
    "update_deep_replace",
    "update_deep_disc",
    "update_ray_irm",
    "update_fused",
    "update_nav",
    "MapSet",
]

#: The six maps of the paper's Table I, in its order (the default map set).
MAP_NAMES: tuple[str, ...] = (
    "ray_ilm",
    "deep_acc",
    "deep_replace",
    "deep_disc",
    "ray_irm",
    "fused",
)
#: The navigation map: computed when asked for, not one of Table I's.
NAV_MAP = "nav"
#: The three inverse sensor models that feed them.
ISM_NAMES: tuple[str, ...] = ("ray_ilm", "ray_irm", "deep_irm")

# Default lower limit on the deep ISM's unknown mass; the paper gives no value
# (docs/decisions.md#default-lower-limit-on-unknown-mass).
# Chosen by `evgrid sweep-m-u-min` on simulated validation scenes (seeds 4, 9, 14, 19) with the
# sim-v1 Ev-Net: the highest limit whose deep_disc mIoU is within 0.01 of the best; at >= 0.5
# a cell known only to the deep IRM can never be classified free or occupied, below 0.3 the
# prior is less clearly apart from verified space for no gain.
M_U_MIN_DEFAULT = 0.3
ALPHA_DEFAULT = 10.0  # paper, section IV-D, eq. (28)

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class FusionParams:
    """Parameters of the deep-ISM rules: ``m_u_min`` (unitless, in [0, 1)) and ``alpha`` (the
    gain of tanh, >= 0)."""

    m_u_min: float = M_U_MIN_DEFAULT
    alpha: float = ALPHA_DEFAULT

    def __post_init__(self) -> None:
        check_number(self, "m_u_min", min=0.0, max=1.0, max_open=True)
        check_number(self, "alpha", min=0.0)


# Defaults of the dynamic score (docs/equations.md#the-dynamic-score): chosen with
# benchmarks/dynamic.py on simulated scenes (docs/speed.md#the-dynamic-score).
DYNAMIC_DECAY_DEFAULT = 0.3
DYNAMIC_THRESHOLD_DEFAULT = 0.2
GATE_THRESHOLD_DEFAULT = 0.03
# The Doppler cue (docs/equations.md#the-doppler-cue): the ego-motion compensation of a static
# target leaves errors of a few tenths of a m/s (odometry speed and yaw rate, the radar's 0.1 m/s
# Doppler resolution) and clutter shows slow false speeds; the disc behind a detection covers a
# part of its object. Chosen with benchmarks/dynamic.py on simulated scenes (tuning seeds, checked
# on held-out ones).
DOPPLER_MPS_DEFAULT = 2.0
DOPPLER_MASS_DEFAULT = 0.5
DOPPLER_RADIUS_DEFAULT = 1.0


@dataclass(frozen=True, slots=True)
class DynamicParams:
    """The dynamic score of the maps fused with Dempster's rule (docs/equations.md).

    At each update a map cell's score becomes ``decay * score + K_arr + K_left``, the conflict
    of its Dempster step split by direction (Moras et al. 2011); a cell whose score exceeds
    ``threshold`` is called dynamic. ``enabled=False`` keeps no score (the maps are the same
    either way unless gated). ``decay`` in (0, 1], ``threshold`` > 0.

    A cell the ISM of its Dempster step sees free now keeps no score (whatever moved there is
    gone).

    The Doppler cue: cells of a disc of radius ``doppler_radius_m`` (m) that touches from behind
    (seen from its radar) a detection of the newest sweep of each radar whose ego-motion
    compensated Doppler speed exceeds ``doppler_mps`` (m/s) add ``doppler_mass`` (>= 0; 0: no
    cue) times the ISM's not-free share to the score once per update.

    The gate: a scored cell whose score exceeds ``gate_threshold`` (> 0) moves its occupied mass
    to unknown before a Dempster step whose ISM does not say occupied; ``gate_maps`` gates the
    paper's maps (off by default: Table I stays the paper's), ``gate_nav`` the navigation map's
    inputs.
    """

    enabled: bool = True
    decay: float = DYNAMIC_DECAY_DEFAULT
    threshold: float = DYNAMIC_THRESHOLD_DEFAULT
    doppler_mps: float = DOPPLER_MPS_DEFAULT
    doppler_mass: float = DOPPLER_MASS_DEFAULT
    doppler_radius_m: float = DOPPLER_RADIUS_DEFAULT
    gate_maps: bool = False
    gate_nav: bool = True
    gate_threshold: float = GATE_THRESHOLD_DEFAULT

    def __post_init__(self) -> None:
        for name in ("enabled", "gate_maps", "gate_nav"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(
                    f"DynamicParams.{name} must be true or false, got {getattr(self, name)!r}"
                )
        check_number(self, "decay", min=0.0, max=1.0, min_open=True)
        check_number(self, "threshold", min=0.0, min_open=True)
        check_number(self, "gate_threshold", min=0.0, min_open=True)
        check_number(self, "doppler_mps", min=0.0)
        check_number(self, "doppler_mass", min=0.0)
        check_number(self, "doppler_radius_m", min=0.0, max=10.0)


# --- the table of rules --------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class UpdateRule:
    """One map's update rule: a row of :data:`RULES`.

    ``inputs`` are what its kernel reads per cell, in argument order: local ISM grids, or for a
    rule ``from_maps`` other maps of the same step (already updated). ``isms`` are the ISMs a
    map set must compute for it; ``kernel`` its code in :mod:`evgrid.kernels`; ``params`` the
    :class:`FusionParams` fields it uses; ``equation`` what it computes (paper's numbers).
    """

    name: str
    inputs: tuple[str, ...]
    kernel: int
    params: tuple[str, ...]
    equation: str
    from_maps: bool = False
    isms: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.from_maps:
            object.__setattr__(self, "isms", self.inputs)

    def update(self, cell: np.ndarray, *args, spans: np.ndarray | None = None) -> int:
        """``update(cell, *inputs[, params[, spans]])``: apply the rule in place on dense views.

        Rules from maps read a neighbourhood, not cells: :func:`update_nav` applies nav.

        ``cell`` and each input are ``(h, w, 3)`` float32 views with contiguous rows; ``spans``
        (``(h, 2)`` int64) limits row i to columns ``spans[i, 0]:spans[i, 1]``. Returns the
        number of invalid input cells rejected (their map cells are left untouched).
        """
        if self.from_maps:
            raise TypeError(
                f"{self.name} is computed from whole maps and a neighbourhood of cells, not per "
                f"cell: use evgrid.fusion.update_nav"
            )
        n = len(self.inputs)
        if not n <= len(args) <= n + 2:
            raise TypeError(
                f"{self.name}: update(cell, {', '.join(self.inputs)}[, params[, spans]]) "
                f"got {len(args)} argument(s) after cell"
            )
        inputs, rest = args[:n], args[n:]
        params = rest[0] if rest and rest[0] is not None else FusionParams()
        if len(rest) > 1:
            spans = rest[1]
        if not isinstance(params, FusionParams):
            raise TypeError(f"{self.name}: params must be a FusionParams, got {params!r}")
        _check_views(cell, *inputs)
        fm, mrs, h, w = rows(cell)
        fa, ars, _, _ = rows(inputs[0])
        fb, brs, _, _ = rows(inputs[-1])
        return int(
            update_rows(
                self.kernel,
                fm,
                mrs,
                fa,
                ars,
                fb,
                brs,
                h,
                w,
                _row_spans(spans, h, w),
                float(params.m_u_min),
                float(params.alpha),
            )
        )


#: Every map's update rule, declared once (paper Table I, then the navigation map); the one-pass
#: update of :class:`MapSet` and the ``update_*`` functions dispatch the kernels from it.
RULES: dict[str, UpdateRule] = {
    r.name: r
    for r in (
        UpdateRule("ray_ilm", ("ray_ilm",), RULE_DEMPSTER, (), "map (+)_D ray ILM, eq. (5)"),
        UpdateRule("deep_acc", ("deep_irm",), RULE_DEMPSTER, (), "map (+)_D deep IRM, eq. (5)"),
        UpdateRule(
            "deep_replace",
            ("deep_irm",),
            RULE_DEEP_REPLACE,
            ("m_u_min",),
            "m = deep IRM (box+) m_u_min, eq. (15); cell := m where m_u(m) < m_u(cell)",
        ),
        UpdateRule(
            "deep_disc",
            ("deep_irm",),
            RULE_DEEP_DISC,
            ("m_u_min", "alpha"),
            "map (+)_Y (gamma (x) (deep IRM (box+) m_u_min)), eqs. (15), (29), (35)",
        ),
        UpdateRule("ray_irm", ("ray_irm",), RULE_DEMPSTER, (), "map (+)_D ray IRM, eq. (5)"),
        UpdateRule(
            "fused",
            ("deep_irm", "ray_irm"),
            RULE_FUSED,
            ("m_u_min", "alpha"),
            "the deep_disc step, then map (+)_D ray IRM, eq. (5)",
        ),
        UpdateRule(
            NAV_MAP,
            ("ray_ilm", "fused"),
            RULE_NAV,
            (),
            "ray_ilm map (+)_D fused map kept off the lidar's returns, eq. (5)",
            from_maps=True,
            isms=("ray_ilm", "deep_irm", "ray_irm"),
        ),
    )
}


def _check_views(cell: np.ndarray, *isms: np.ndarray) -> None:
    for a in (cell, *isms):
        if not isinstance(a, np.ndarray):
            raise ValueError(f"map and ISM views must be numpy arrays, got {type(a).__name__}")
        if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.float32:
            raise ValueError(
                f"map and ISM views must be float32 (h, w, 3), got {a.dtype} {a.shape}"
            )
        if a.shape != cell.shape:
            raise ValueError(f"ISM view shape {a.shape} differs from the map view's {cell.shape}")
    if not cell.flags.writeable:
        raise ValueError("the map view must be writeable (updates are in place)")


def _row_spans(spans: np.ndarray | None, h: int, w: int) -> np.ndarray:
    """Columns to update per row, ``(h, 2)`` int64 ``[lo, hi)``; None means whole rows."""
    if spans is None:
        out = np.empty((h, 2), dtype=np.int64)
        out[:, 0] = 0
        out[:, 1] = w
        return out
    if not isinstance(spans, np.ndarray) or spans.shape != (h, 2) or spans.dtype != np.int64:
        got = (
            f"{spans.dtype} {spans.shape}"
            if isinstance(spans, np.ndarray)
            else type(spans).__name__
        )
        raise ValueError(f"spans must be an int64 array of shape {(h, 2)}, got {got}")
    return spans  # kernels clamp each [lo, hi) to [0, w]


# The rules on dense views: thin calls of the table's rows (the same kernel as MapSet.update's
# pass), kept for users who fuse their own grids, and as the per-rule reference of the tests.


def update_ray_ilm(
    cell: np.ndarray,
    ilm: np.ndarray,
    params: FusionParams | None = None,
    spans: np.ndarray | None = None,
) -> int:
    """``map = map (+)_D ray ILM`` (paper eq. (5)), in place on ``(h, w, 3)`` float32 views."""
    return RULES["ray_ilm"].update(cell, ilm, params, spans=spans)


def update_deep_acc(
    cell: np.ndarray,
    deep: np.ndarray,
    params: FusionParams | None = None,
    spans: np.ndarray | None = None,
) -> int:
    """``map = map (+)_D deep IRM`` (paper: deep IRM (acc.)), in place."""
    return RULES["deep_acc"].update(cell, deep, params, spans=spans)


def update_deep_replace(
    cell: np.ndarray,
    deep: np.ndarray,
    params: FusionParams | None = None,
    spans: np.ndarray | None = None,
) -> int:
    """Take ``limit_unknown(deep IRM, m_u_min)`` where it is less unknown (deep IRM (replace))."""
    return RULES["deep_replace"].update(cell, deep, params, spans=spans)


def update_deep_disc(
    cell: np.ndarray,
    deep: np.ndarray,
    params: FusionParams | None = None,
    spans: np.ndarray | None = None,
) -> int:
    """``map (+)_Y (gamma (x) limit_unknown(deep IRM))`` (eqs. (29), (35); deep IRM (disc.))."""
    return RULES["deep_disc"].update(cell, deep, params, spans=spans)


def update_ray_irm(
    cell: np.ndarray,
    irm: np.ndarray,
    params: FusionParams | None = None,
    spans: np.ndarray | None = None,
) -> int:
    """``map = map (+)_D ray IRM`` (paper eq. (5)), in place."""
    return RULES["ray_irm"].update(cell, irm, params, spans=spans)


def update_fused(
    cell: np.ndarray,
    deep: np.ndarray,
    irm: np.ndarray,
    params: FusionParams | None = None,
    spans: np.ndarray | None = None,
) -> int:
    """The deep_disc step with the deep IRM, then ``map (+)_D ray IRM`` (fused IRM), in place.

    An invalid cell of one ISM skips that ISM's step on the cell; the count is over both ISMs.
    """
    return RULES["fused"].update(cell, deep, irm, params, spans=spans)


def update_nav(
    cell: np.ndarray,
    lidar_map: np.ndarray,
    fused_map: np.ndarray,
    *,
    margin_cells: int = 0,
    occupied_min: float = 1.0,
) -> int:
    """``cell := nav(lidar_map, fused_map)`` on dense ``(h, w, 3)`` float32 maps
    (:mod:`evgrid.nav`, docs/equations.md#the-navigation-map); cells beyond the edges are vacuous.

    Dempster's rule (eq. (5)) of the lidar map's cell with the fused map's, whose free mass
    counts as unknown within ``margin_cells`` of a cell with lidar occupied mass or fused
    occupied mass above ``occupied_min`` (the defaults look at each cell alone), and whose
    occupied mass counts as unknown where the lidar's free mass exceeds its occupied mass.
    Returns 0 (maps hold no invalid cells to reject).
    """
    _check_views(cell, lidar_map, fused_map)
    cell[...] = nav_dense(lidar_map, fused_map, margin_cells, occupied_min)
    return 0


# --- a set of maps, updated in one pass ----------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class _Row:
    """One map in a pass: its name, rule, tiles and parameters."""

    name: str
    rule: UpdateRule
    map: EvidentialMap
    params: FusionParams
    shown: bool  # False: kept only as an input of a rule from maps (not in MapSet.maps)
    plain: bool = False  # never gated: the ungated lidar map beside nav's gated copies


def _check_pose(pose: SE2) -> None:
    if not isinstance(pose, SE2):
        raise TypeError(f"pose must be an evgrid.geometry.SE2, got {type(pose).__name__}")
    x, y, yaw = pose.x, pose.y, pose.yaw
    if not all(math.isfinite(v) for v in (x, y, yaw)) or max(abs(x), abs(y)) > MAX_POSE_M:
        raise ValueError(
            f"pose {pose!r} is not a valid ego pose in the map frame: poses must be finite and "
            f"within {MAX_POSE_M:g} m of the frame's origin (check the odometry's units and frame)"
        )


def _check_map_set_args(grid, params, names, dynamic, nav) -> None:
    """MapSet's arguments, each of its type, and the map names known and distinct."""
    if grid is not None and not isinstance(grid, GridSpec):
        raise TypeError(f"MapSet: grid must be a GridSpec, got {type(grid).__name__}")
    if params is not None and not isinstance(params, FusionParams):
        raise TypeError(
            f"MapSet: params must be a FusionParams (e.g. FusionParams(m_u_min=0.3)), "
            f"got {type(params).__name__} {params!r}"
        )
    if isinstance(names, str) or not all(isinstance(n, str) for n in names):
        raise TypeError(f"MapSet: names must be a tuple of map names, got {names!r}")
    unknown = [n for n in names if n not in RULES]
    if unknown or not names:
        raise ValueError(f"unknown map name(s) {unknown}; choose from {tuple(RULES)}")
    if len(set(names)) != len(names):
        raise ValueError(f"map names repeat: {tuple(names)}")
    if dynamic is not None and not isinstance(dynamic, DynamicParams):
        raise TypeError(
            f"MapSet: dynamic must be a DynamicParams, got {type(dynamic).__name__} {dynamic!r}"
        )
    if nav is not None and not isinstance(nav, NavParams):
        raise TypeError(f"MapSet: nav must be a NavParams, got {type(nav).__name__} {nav!r}")


def _pass_layout(
    names: tuple[str, ...], dynamic: DynamicParams
) -> tuple[list[tuple[str, bool, bool]], bool]:
    """The rows of a set's pass in order, each (map name, shown, plain), and whether nav reads
    gated copies of its inputs.

    Maps read by a rule from maps come first in the pass, and are kept when not shown; with
    the gate on for nav but not for the shown maps, nav reads gated copies of its inputs
    (hidden rows of the same pass: docs/equations.md#the-gate), and beside them the lidar map
    ungated (plain): the gate may take a cell the lidar map calls occupied to unknown in nav,
    never to free.
    """
    gated_copies = dynamic.enabled and dynamic.gate_nav and not dynamic.gate_maps
    needed = [m for n in names if RULES[n].from_maps for m in RULES[n].inputs]
    order = [n for n in names if not RULES[n].from_maps]
    hidden = [m for m in dict.fromkeys(needed) if m not in order or gated_copies]
    derived = [n for n in names if RULES[n].from_maps]
    lidar = RULES["nav"].inputs[0]  # nav = L (+)_D F'
    plain = [lidar] if gated_copies and derived and lidar not in order else []
    layout = [
        *((n, True, False) for n in order),
        *((n, False, False) for n in hidden),
        *((n, False, True) for n in plain),
        *((n, True, False) for n in derived),
    ]
    return layout, gated_copies


class MapSet:
    """Several maps over one scene, in the map frame, updated in one pass per time step.

    :meth:`update` loads each ISM grid once (checked, into the padded copy of its
    :class:`~evgrid.grid.Warper`) and then visits each covered map cell once: it samples every
    ISM there as a warp would (bilinearly) and applies every map's rule, row by row of the
    map's rule table (kernel code, inputs, ``m_u_min``, ``alpha``). Other map sets attached
    with :meth:`attach` (the ``m_u_min`` sweep's) are extra rows of the same pass.

    ``names`` are any of :data:`RULES` (default: the six of Table I). ``nav`` (with ``nav``
    :class:`~evgrid.nav.NavParams`) is computed from the ``ray_ilm`` and ``fused`` maps when
    it is read from :attr:`maps`, over the cells the updates since the last read changed: where
    those two are not asked for, the set keeps them for it without showing them in :attr:`maps`.

    Invalid ISM cells never reach a map: ``n_rejected[ism]`` counts the cells of the local ISM
    grids that were not masses and were taken as vacuous (no information);
    ``n_rejected_cells[map]`` the cells a map's rule rejected (0 when every ISM went through
    the loading check, as it does in :meth:`update`).

    With ``dynamic`` enabled (:class:`DynamicParams`; default off), the maps with a Dempster
    step on an ISM (:attr:`dynamic_maps`) keep a dynamic score per cell beside their masses,
    updated in the same pass (:meth:`~evgrid.grid.EvidentialMap.read_dynamic` reads it), plus
    the Doppler cue of the ``moving`` detections given to :meth:`update`. With its gate on
    (``gate_maps``) those maps shed the occupied mass of cells scored dynamic; with
    ``gate_nav`` (and not ``gate_maps``) ``nav`` reads gated copies of ``ray_ilm`` and
    ``fused``, hidden rows of the same pass (twice their memory), so the shown maps stay the
    paper's (docs/equations.md#the-gate).
    """

    def __init__(
        self,
        grid: GridSpec | None = None,
        params: FusionParams | None = None,
        names: tuple[str, ...] = MAP_NAMES,
        tile_cells: int = 256,
        dynamic: DynamicParams | None = None,
        nav: NavParams | None = None,
    ):
        _check_map_set_args(grid, params, names, dynamic, nav)
        self.grid = grid or GridSpec()
        self.params = params or FusionParams()
        self.dynamic = dynamic or DynamicParams(enabled=False)
        self.nav = nav or NavParams()
        self.names = tuple(names)
        layout, gated_copies = _pass_layout(self.names, self.dynamic)
        self._rows = [self._row(n, shown, plain, tile_cells) for n, shown, plain in layout]
        self.tile_cells = self._rows[0].map.tile_cells
        every = {r.name: r.map for r in self._rows if r.shown}
        self._derived = self._derived_inputs(every, gated_copies)
        self._stale: tuple[int, int, int, int] | None = None  # cells changed since the last read
        self.maps: Mapping[str, EvidentialMap] = _Maps(self, {n: every[n] for n in self.names})
        self.required_isms: tuple[str, ...] = tuple(
            i for i in ISM_NAMES if any(i in RULES[n].isms for n in self.names)
        )
        # one loader per ISM: its checked, padded copy of the local grid is what the pass samples
        self._warpers = {i: Warper(self.grid, i) for i in self.required_isms}
        self._attached: list[MapSet] = []
        self._host: MapSet | None = None
        self._bufs = np.empty((len(self.required_isms), 3 * self.tile_cells), dtype=np.float32)
        side = int(np.ceil(self.grid.n_cells * np.sqrt(2.0))) + 4
        self._spans = np.zeros((side, 2), dtype=np.int64)
        self._plan()
        self.n_updates = 0
        self.n_rejected_cells: dict[str, int] = {m: 0 for m in self.names}
        #: Milliseconds of the last update: ``warp`` checking and padding the ISMs, ``fuse``
        #: the pass that samples them and applies the rules.
        self.last_ms: dict[str, float] = {}

    def _row(self, name: str, shown: bool, plain: bool, tile_cells: int) -> _Row:
        """The pass's row of map ``name``: its rule, a new map of this set's grid and its
        parameters (a plain row keeps no dynamic score)."""
        p = self.params
        meta = {"rule": name, "m_u_min": p.m_u_min, "alpha": p.alpha}
        dynamic = self._scores(name) and not plain
        m = EvidentialMap(self.grid, tile_cells, meta, dynamic=dynamic)
        return _Row(name, RULES[name], m, p, shown, plain)

    def _derived_inputs(
        self, every: dict[str, EvidentialMap], gated_copies: bool
    ) -> list[tuple[EvidentialMap, ...]]:
        """The maps computed from others when read (nav), each with its input maps (the hidden
        gated copies where nav reads them) and, beside gated copies, the ungated lidar map."""
        inputs = {**every, **{r.name: r.map for r in self._rows if not (r.shown or r.plain)}}
        derived = any(r.rule.from_maps for r in self._rows)
        lidar = RULES["nav"].inputs[0]
        ungated = (
            ({**every, **{r.name: r.map for r in self._rows if r.plain}}[lidar],)
            if gated_copies and derived
            else (None,)
        )
        return [
            (every[r.name], *(inputs[m] for m in r.rule.inputs), *ungated)
            for r in self._rows
            if r.rule.from_maps
        ]

    def _scores(self, name: str) -> bool:
        """Whether map ``name`` keeps a dynamic score: its rule has a Dempster step on an ISM."""
        return self.dynamic.enabled and RULES[name].kernel in DYNAMIC_RULES

    @property
    def dynamic_maps(self) -> tuple[str, ...]:
        """The maps of this set that keep a dynamic score (empty with the score off)."""
        return tuple(r.name for r in self._rows if r.shown and r.map.dynamic)

    @property
    def reach(self) -> int:
        """Cells beyond an update's window that it can change: the navigation map's margin
        (nav reads a neighbourhood) when this set or one attached to it has nav, else 0."""
        return max(
            (s.nav.margin_cells(s.grid.resolution) for s in (self, *self._attached) if s._derived),
            default=0,
        )

    @property
    def doppler_mps_min(self) -> float | None:
        """The lowest ``doppler_mps`` of this set and those attached to it among those with the
        Doppler cue (m/s), or None if none has it: the detections an update needs."""
        return min((mps for mps, _ in self._discs), default=None)

    def _gate(self, row: _Row) -> float:
        """The gate's threshold of a row (docs/equations.md#the-gate); 0: not gated."""
        d = self.dynamic
        on = d.gate_maps if row.shown else d.gate_nav and not row.plain  # hidden: nav's inputs
        return d.gate_threshold if (on and row.map.dynamic) else 0.0

    def _plan(self) -> None:
        """The pass's table: per row (kernel code, first input, last input, Doppler disc set) and
        (m_u_min, alpha, decay, gate, Doppler mass), decay 0 for a map without a dynamic score,
        gate 0 for one not gated, disc set -1 for one without the Doppler cue; the disc sets are
        :attr:`_discs`' (speed, radius) (docs/equations.md#the-doppler-cue)."""
        slot = {i: s for s, i in enumerate(self.required_isms)}
        codes, params, rows_, owners = [], [], [], []
        discs: dict[tuple[float, float], int] = {}
        for s in (self, *self._attached):
            updated = [r for r in s._rows if not r.rule.from_maps]  # nav is computed when read
            d = s.dynamic
            for r in updated:
                cue = r.map.dynamic and d.doppler_mass > 0.0
                q = discs.setdefault((d.doppler_mps, d.doppler_radius_m), len(discs)) if cue else -1
                codes.append((r.rule.kernel, slot[r.rule.inputs[0]], slot[r.rule.inputs[-1]], q))
                decay = d.decay if r.map.dynamic else 0.0
                params.append((r.params.m_u_min, r.params.alpha, decay, s._gate(r), d.doppler_mass))
            rows_ += updated
            owners += [s] * len(updated)
        self._discs = tuple(discs)
        self._codes = np.array(codes, dtype=np.int64).reshape(-1, 4)
        self._params = np.array(params, dtype=np.float64).reshape(-1, 5)
        self._pass_rows: list[_Row] = rows_
        self._pass_owners: list[MapSet] = owners

    def attach(self, other: MapSet) -> None:
        """Update ``other``'s maps in this set's pass from now on: extra rows of the same table.

        ``other`` (same grid and tiling, its ISMs among this set's) keeps its own parameters,
        maps and counters; its :meth:`update` must not be called while attached.
        """
        if not isinstance(other, MapSet):
            raise TypeError(f"can only attach a MapSet, got {type(other).__name__}")
        if other is self or other._host is not None or other._attached:
            raise ValueError("a map set can be attached once, to one other set, and not to itself")
        missing = set(other.required_isms) - set(self.required_isms)
        if missing:
            raise ValueError(
                f"the attached map set needs ISMs {sorted(missing)} that this set does not compute"
            )
        if other.grid != self.grid or other.tile_cells != self.tile_cells:
            raise ValueError(
                f"the attached map set's grid {other.grid} / tiles {other.tile_cells} differ "
                f"from this set's {self.grid} / {self.tile_cells}"
            )
        other._host = self
        self._attached.append(other)
        self._plan()

    @property
    def n_rejected(self) -> dict[str, int]:
        """Per ISM, the cells of its local grids that were not masses and were taken as vacuous."""
        if self._host is not None:
            return {i: self._host._warpers[i].n_rejected for i in self.required_isms}
        return {i: w.n_rejected for i, w in self._warpers.items()}

    def __getitem__(self, name: str) -> EvidentialMap:
        return self.maps[name]

    def update(
        self, pose: SE2, isms: Mapping[str, np.ndarray], moving: np.ndarray | None = None
    ) -> dict[str, int]:
        """Fuse one time step: local ISM grids ``(n, n, 3)`` keyed by ISM name, taken at ego
        ``pose`` (m, rad) in the map frame; every map of this set and of the sets attached to it.

        ``moving``: ``(k, 5)`` map-frame position (m), compensated Doppler speed (m/s) and the
        radar's map-frame position (m) of radar detections
        (:func:`evgrid.doppler.moving_detections`), the Doppler cue of the dynamic score: those
        faster than each set's ``dynamic.doppler_mps`` count, each with a disc behind it (added
        in the pass, after the gate; discs outside the local grid are ignored).

        Cells of an ISM grid that are not masses are taken as vacuous and counted in
        :attr:`n_rejected`. Returns, per map of this set, the cells its rule rejected.
        """
        if self._host is not None:
            raise ValueError("this map set is attached to another: update that one")
        _check_pose(pose)
        if moving is not None:
            moving = np.asarray(moving, dtype=np.float64)
            if moving.ndim != 2 or moving.shape[1] != 5:
                raise ValueError(
                    f"moving must be (k, 5) (x, y, speed, radar x, radar y), got shape "
                    f"{moving.shape}"
                )
            if not np.isfinite(moving).all():
                bad = int((~np.isfinite(moving)).any(axis=1).sum())
                raise ValueError(f"moving has {bad} row(s) with NaN or inf")
        missing = [i for i in self.required_isms if i not in isms]
        if missing:
            raise ValueError(f"missing ISM grid(s) {missing}; these maps need {self.required_isms}")
        t0 = time.perf_counter()
        for name, warper in self._warpers.items():
            warper.load(isms[name])
        t1 = time.perf_counter()
        box = warp_window(self.grid, pose)
        rejected = self._pass(pose, box, self._disc_runs(pose, box, moving))
        self.last_ms = {"warp": (t1 - t0) * 1e3, "fuse": (time.perf_counter() - t1) * 1e3}
        for s in (self, *self._attached):
            s.n_updates += 1
            if s._derived:
                s._stale = _union(s._stale, box)
        out: dict[str, int] = {n: 0 for n in self.names if RULES[n].from_maps}
        for row, owner, r in zip(self._pass_rows, self._pass_owners, rejected):
            if row.shown:
                owner.n_rejected_cells[row.name] += int(r)
                if owner is self:
                    out[row.name] = int(r)
        return out

    def clear_occupied(self, r0: int, c0: int, mask: np.ndarray, names: tuple[str, ...]) -> int:
        """Move the occupied mass of the map cells ``(r0 + i, c0 + j)`` where ``mask[i, j]`` to
        free (``m_f += m_o, m_o = 0``) in the maps ``names`` of this set and of the sets attached
        to it; tiles a map does not have stay absent. Returns the cells changed, over all maps.
        Only for maps no other map is computed from (nav reads ``ray_ilm`` and ``fused``)."""
        derived_inputs = {m for r in self._rows if r.rule.from_maps for m in r.rule.inputs}
        if set(names) & derived_inputs:
            raise ValueError(f"clear_occupied cannot change {sorted(set(names) & derived_inputs)}")
        h, w = mask.shape
        n = 0
        for s in (self, *self._attached):
            for row in s._rows:
                if row.name not in names or not row.shown:
                    continue
                m = row.map
                for key, tr, tc, wr, wc in m.pieces(r0, c0, h, w):
                    where = mask[wr, wc]
                    if key not in m.tiles or not where.any():
                        continue
                    cells = m.tile(key)[0][tr, tc]
                    hit = where & (cells[..., 1] > 0)
                    cells[..., 0][hit] += cells[..., 1][hit]
                    cells[..., 1][hit] = 0.0
                    n += int(np.count_nonzero(hit))
        return n

    def attach_store(self, store: TileStore, prefix: str = "") -> None:
        """Page every map of this set (hidden rows and sets attached included) to ``store``, each
        in a group of its own: the map's name (the ungated lidar map beside nav's gated inputs
        ``NAME.plain``, attached sets ``setI.NAME``); a hidden row that is a gated copy of a map
        of the set is kept in that map's tile files (copy "gated": docs/store.md), other hidden
        rows in ``NAME.gated``."""
        groups = {}
        for row in self._rows:
            if row.shown or row.plain:
                groups[row.name] = f"{prefix}{row.name}{'' if row.shown else '.plain'}"
                row.map.attach_store(store.group(groups[row.name]))
        for row in self._rows:
            if not (row.shown or row.plain):
                if row.name in groups:
                    row.map.attach_store(store.group(groups[row.name]), copy="gated")
                else:
                    row.map.attach_store(store.group(f"{prefix}{row.name}.gated"))
        for i, s in enumerate(self._attached):
            s.attach_store(store, f"{prefix}set{i}.")

    def page_out(self, x: float, y: float, radius_m: float) -> int:
        """Move the tiles of every map (and of the sets attached) farther than ``radius_m`` metres
        from map point ``(x, y)`` to the store (:meth:`attach_store`); returns how many moved.

        The maps computed from others (nav) are brought up to date first, so that what they
        still have to read is near the vehicle; the maps are unchanged either way."""
        ts, res = self.tile_cells, self.grid.resolution
        sets = (self, *self._attached)
        far = any(
            tile_distance_m(k, ts, res, x, y) > radius_m
            for s in sets
            for r in s._rows
            for k in r.map._tiles
        )
        if not far:
            return 0
        n = 0
        for s in sets:
            s._settle()
            n += sum(r.map.page_out(x, y, radius_m) for r in s._rows)
        return n

    def _settle(self) -> None:
        """Compute the maps derived from others (nav) over the cells changed since the last read."""
        if self._stale is None:
            return
        t0 = time.perf_counter()
        r = self.nav.margin_cells(self.grid.resolution)
        avoid = self.nav.avoid_moving and self.dynamic.enabled
        moving_min = self.dynamic.threshold if avoid else math.inf
        for nav, lidar, fused, plain in self._derived:
            refresh(nav, lidar, fused, self._stale, r, self.nav.occupied_min, moving_min, plain)
        self._stale = None
        self.last_ms["nav"] = self.last_ms.get("nav", 0.0) + (time.perf_counter() - t0) * 1e3

    def _pass(
        self, pose: SE2, box: tuple[int, int, int, int], discs: tuple[np.ndarray, np.ndarray]
    ) -> np.ndarray:
        """The one pass over the window ``box`` at ``pose``: the ISMs of the last load, every
        row's rule, and the Doppler cue on the window rows' runs ``discs`` (:meth:`_disc_runs`)."""
        grid, n = self.grid, self.grid.n_cells
        r0, c0, h, w = box
        affine = WindowAffine(*window_affine(grid, pose, r0, c0))
        spans = self._spans[:h]
        window_spans(*affine, n, h, w, spans)
        nb = (h + BLOCK - 1) // BLOCK
        jl, jh = np.empty(nb, np.int64), np.empty(nb, np.int64)
        band_columns(spans, h, w, jl, jh)
        warpers = tuple(self._warpers.values())
        informative = np.zeros((len(warpers), nb, (w + BLOCK - 1) // BLOCK + 1), dtype=np.bool_)
        for s, warper in enumerate(warpers):
            informative_blocks(warper.coarse, n, *affine, h, jl, jh, informative[s])
        maps = [r.map for r in self._pass_rows]
        rejected = np.zeros(len(maps), dtype=np.int64)
        sources = PassSources(tuple(wp.source for wp in warpers), 3 * (n + 3), n, informative, jl)
        table, discs = RuleTable(self._codes, self._params), DopplerDiscs(*discs)
        no_layer = np.zeros(0, dtype=np.float32)  # the dynamic layer of a map that keeps none
        for key, tr, tc, wr, wc in maps[0].pieces(r0, c0, h, w):
            cut = spans[wr]
            rows_on = np.flatnonzero(
                np.minimum(cut[:, 1], wc.stop) > np.maximum(cut[:, 0], wc.start)
            )
            if len(rows_on) == 0:
                continue
            a, b = int(rows_on[0]), int(rows_on[-1]) + 1  # the piece's rows with covered cells
            tiles = [m.tile(key) for m in maps]
            piece = TilePiece(
                spans, wr.start + a, wr.start + b, wc.start, wc.stop, tr.start + a, tc.start
            )
            layers = MapTiles(
                tuple(t.reshape(-1) for t, _ in tiles),
                tuple(c.reshape(-1) for _, c in tiles),
                tuple(m.dynamic_tiles[key].reshape(-1) if m.dynamic else no_layer for m in maps),
                self.tile_cells,
            )
            warp_update(sources, affine, piece, layers, table, discs, self._bufs, rejected)
        return rejected

    def _disc_runs(
        self, pose: SE2, box: tuple[int, int, int, int], moving: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The cells of the Doppler cue's discs in window ``box``, per disc set of :attr:`_discs`:
        ``ptr`` ``(sets, h + 1)`` into ``runs`` ``(n, 2)``, the runs of window row i of set q
        being ``runs[ptr[q, i]:ptr[q, i + 1]]`` (:func:`evgrid.doppler.disc_runs`)."""
        h = box[2]
        if moving is None or not len(moving) or not self._discs:
            return np.zeros((len(self._discs), h + 1), np.int64), np.zeros((0, 2), np.int64)
        from evgrid.doppler import disc_centres, disc_runs

        ptrs, runs, n = [], [], 0
        for mps, radius in self._discs:
            centres = disc_centres(moving[moving[:, 2] > mps], radius)
            ptr, r = disc_runs(self.grid, pose, box, centres, radius)
            ptrs.append(ptr + n)
            runs.append(r)
            n += len(r)
        return np.stack(ptrs), np.concatenate(runs)

    def windows(self, pose: SE2) -> dict[str, MapWindow]:
        """The ISM grids of the last :meth:`update` warped whole into map windows at ``pose``.

        For observers that want whole windows; no map is updated from them. Each window is a
        view of its warper's buffers that the next call overwrites.
        """
        host = self._host or self
        return {i: host._warpers[i].warp_loaded(pose) for i in self.required_isms}


def _union(a: tuple[int, int, int, int] | None, b: tuple[int, int, int, int]):
    """The smallest box (r0, c0, h, w) holding boxes ``a`` (None: none) and ``b``."""
    if a is None:
        return b
    r0, c0 = min(a[0], b[0]), min(a[1], b[1])
    return r0, c0, max(a[0] + a[2], b[0] + b[2]) - r0, max(a[1] + a[3], b[1] + b[3]) - c0


class _Maps(Mapping):
    """A map set's maps by name; reading one first brings the maps computed from others (nav)
    up to date, so every reader sees them as of the last update."""

    def __init__(self, owner: MapSet, maps: dict[str, EvidentialMap]):
        self._owner, self._maps = owner, maps

    def __getitem__(self, name: str) -> EvidentialMap:
        m = self._maps[name]
        self._owner._settle()
        return m

    def __iter__(self) -> Iterator[str]:
        return iter(self._maps)

    def __len__(self) -> int:
        return len(self._maps)

    def __repr__(self) -> str:
        return f"maps({', '.join(self._maps)})"
