"""The ego vehicle's own lidar returns: moved to :mod:`evgrid.preprocess` (what is removed from
a frame before any ISM); these names stay importable from here."""

from __future__ import annotations

from evgrid.preprocess import (
    NUSCENES_BODY,
    SELF_RETURN_MODES,
    BodyBox,
    SelfReturnFilter,
    SelfReturnParams,
    parse_body_box,
)

__all__ = [
    "BodyBox",
    "NUSCENES_BODY",
    "SELF_RETURN_MODES",
    "SelfReturnParams",
    "SelfReturnFilter",
    "parse_body_box",
]
