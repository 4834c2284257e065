"""Which radar detections count: moved to :mod:`evgrid.preprocess` (what is removed from a frame
before any ISM); these names stay importable from here."""

from __future__ import annotations

from evgrid.preprocess import RADAR_FILTER_MODES, RadarFilter, check_trained_filter

__all__ = ["RadarFilter", "RADAR_FILTER_MODES", "check_trained_filter"]
