"""Ev-Net's training loss (paper eqs. (36)-(37))."""

from __future__ import annotations

import torch
from torch.nn import functional as F

from evgrid.classes import FREE, OCCUPIED, UNKNOWN

__all__ = ["evidential_loss"]


def evidential_loss(
    evidence: torch.Tensor, target: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """Ev-Net loss (paper eqs. (36)-(37)): per-class expectations of the per-cell losses, summed.

    ``evidence`` ``(B, 2, H, W)`` = ``[e_f, e_o]`` >= 0; ``target`` ``(B, H, W)`` int with
    FREE, OCCUPIED, UNKNOWN. Free and occupied cells: the expected squared error of Sensoy et
    al. 2018, ``sum_k (y_k - p_k)^2 + p_k (1 - p_k) / (S + 1)``, p the Dirichlet mean; unknown
    cells: ``(1 - m_u)^2`` with ``m_u = 2 / S``. A class absent from the batch adds nothing.
    How this reads the paper's eq. (36): docs/decisions.md#ev-net-targets-and-loss.
    """
    if evidence.ndim != 4 or evidence.shape[1] != 2:
        raise ValueError(f"evidence must be (B, 2, H, W), got {tuple(evidence.shape)}")
    if target.shape != evidence.shape[:1] + evidence.shape[2:]:
        raise ValueError(
            f"target must be (B, H, W) = {tuple(evidence.shape[:1] + evidence.shape[2:])}, got "
            f"{tuple(target.shape)}"
        )
    alpha = evidence + 1.0
    s = alpha.sum(dim=1)
    p = alpha / s.unsqueeze(1)
    y = F.one_hot(target.clamp(0, 1).long(), 2).permute(0, 3, 1, 2).to(p.dtype)
    l_k = ((y - p) ** 2 + p * (1.0 - p) / (s + 1.0).unsqueeze(1)).sum(dim=1)
    l_u = (1.0 - 2.0 / s) ** 2
    ok = torch.ones_like(target, dtype=torch.bool) if valid is None else valid.bool()
    total = evidence.new_zeros(())
    for cls, per_cell in ((FREE, l_k), (OCCUPIED, l_k), (UNKNOWN, l_u)):
        sel = (target == cls) & ok
        if sel.any():
            total = total + per_cell[sel].mean()
    return total
