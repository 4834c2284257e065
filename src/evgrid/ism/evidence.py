"""Evidence per distance seen, not per update: the geometric ISMs' free mass of one map update
(docs/equations.md#evidence-per-distance-seen).

The paper gives every look of the ray ILM ``m_f = 0.05`` and every look of the ray IRM
``m_f = 0.3``. Dempster's rule (eq. (5)) on ``n`` looks of free evidence ``m`` leaves
``m_u = (1 - m)^n``, so a cell's free mass then depends on how many updates saw it, that is on
the update rate and the speed, not on what the sensor saw. Here the per-look constant is the
evidence of ``reference_m`` metres of new viewpoint, and an update that stands for ``d`` metres
gives

    m_f(d) = 1 - (1 - m_ref)^(d / reference_m),

so that any split of the same stretch of road into updates leaves the same
``m_u = (1 - m_ref)^(L / reference_m)``. ``d`` is the distance the vehicle travelled since the
last update, at least ``standstill_mps`` times the time since it (a standing vehicle's identical
looks add evidence only as fast as a crawl would, so they do not turn into certainty within a
stop) and at most ``max_step_m`` (a gap in the data does not make one look certain).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from evgrid.validation import check_choice, check_mass, check_number

__all__ = ["EVIDENCE_MODES", "EvidenceParams", "free_mass_per_distance"]

#: ``per_metre``: the free mass of an update follows the distance it stands for (the default);
#: ``per_look``: the paper's constant for every update, whatever the speed and rate (Table I).
EVIDENCE_MODES: tuple[str, ...] = ("per_metre", "per_look")


def free_mass_per_distance(m_ref: float, steps: float) -> float:
    """``1 - (1 - m_ref)^steps``: the free mass of ``steps`` reference looks of ``m_ref`` combined
    by Dempster's rule (eq. (5)), for a fractional number of looks too."""
    check_mass("free_mass_per_distance", "m_ref", m_ref)
    check_number("free_mass_per_distance", "steps", steps, min=0.0)
    if steps == 0.0:
        return 0.0
    if m_ref >= 1.0:
        return 1.0
    return -math.expm1(steps * math.log1p(-m_ref))


@dataclass(frozen=True, slots=True)
class EvidenceParams:
    """How much free evidence one map update of the ray ILM and ray IRM carries (lengths in
    metres, speeds in m/s)."""

    mode: str = "per_metre"
    #: The ISMs' ``m_free`` (0.05 ray ILM, 0.3 ray IRM) is the evidence of this much new
    #: viewpoint (m): one update at 10 Hz and 6.5 m/s, the simulated towns' mean speed, so that
    #: city maps keep the paper's evidence
    #: (docs/results.md#evidence-per-metre-highway-and-city).
    reference_m: float = 0.65
    #: A standing vehicle's updates count as this speed's travel (the floor of ``step_m``).
    standstill_mps: float = 1.0
    #: One update stands for at most this much travel (the lidar's reach, 15 m).
    max_step_m: float = 15.0

    def __post_init__(self) -> None:
        check_choice(self, "mode", choices=EVIDENCE_MODES)
        check_number(self, "reference_m", min=0.0, min_open=True)
        check_number(self, "standstill_mps", min=0.0)
        check_number(self, "max_step_m", min=0.0, min_open=True)

    def step_m(self, travelled_m: float, dt_s: float) -> float:
        """The metres of new viewpoint an update stands for: ``travelled_m`` since the last
        update, at least ``standstill_mps * dt_s``, at most ``max_step_m``."""
        check_number(self, "travelled_m", travelled_m, min=0.0)
        check_number(self, "dt_s", dt_s, min=0.0)
        return min(max(travelled_m, self.standstill_mps * dt_s), self.max_step_m)

    def free_mass(self, m_look: float, travelled_m: float, dt_s: float) -> float:
        """The free mass of one update whose per-look (paper) mass is ``m_look``, after
        ``travelled_m`` metres and ``dt_s`` seconds since the last update."""
        if self.mode == "per_look":
            return m_look
        return free_mass_per_distance(m_look, self.step_m(travelled_m, dt_s) / self.reference_m)
