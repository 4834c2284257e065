"""Inverse sensor models: geometric ray casting ISMs for lidar and radar (paper sec. V).

* :func:`ray_ilm` — ray casting inverse lidar model (paper sec. V-A);
* :func:`ray_irm` — ray casting inverse radar model with 2-degree cones (paper sec. V-B),
  fed by the last N sweeps per radar (:class:`evgrid.data.RadarBuffer`);
* :class:`EvidenceParams` — how much free evidence one map update of either carries: per
  metre of travel (the default) or the paper's constant per look.

All return float32 mass grids ``(n, n, 3)`` = [m_f, m_o, m_u] on a
:class:`~evgrid.geometry.GridSpec`; the ``*_with_stats`` variants also count dropped points.
"""

from evgrid.ism._common import IsmResult
from evgrid.ism.evidence import EvidenceParams, free_mass_per_distance
from evgrid.ism.lidar import RayIlmParams, ray_ilm, ray_ilm_with_stats
from evgrid.ism.radar import RayIrmParams, ray_irm, ray_irm_with_stats, ray_irm_xy

__all__ = [
    "IsmResult",
    "EvidenceParams",
    "free_mass_per_distance",
    "RayIlmParams",
    "ray_ilm",
    "ray_ilm_with_stats",
    "RayIrmParams",
    "ray_irm",
    "ray_irm_with_stats",
    "ray_irm_xy",
]
