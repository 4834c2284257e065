"""Ev-Net's training losses: the paper's (eqs. (36)-(37)), and the paper's plus a correct-evidence
regulariser that keeps learning where evidence is low
(docs/decisions.md#ev-net-targets-and-loss)."""

from __future__ import annotations

import torch
from torch.nn import functional as F

from evgrid.classes import FREE, OCCUPIED, UNKNOWN

__all__ = ["LOSSES", "evidential_loss", "correct_evidence_term", "training_loss"]

#: Losses a training may name (``TrainConfig.loss``): ``paper``, eqs. (36)-(37) alone;
#: ``paper+cor``, the same plus :func:`correct_evidence_term`.
LOSSES: tuple[str, ...] = ("paper", "paper+cor")


def _check(evidence: torch.Tensor, target: torch.Tensor) -> None:
    if evidence.ndim != 4 or evidence.shape[1] != 2:
        raise ValueError(f"evidence must be (B, 2, H, W), got {tuple(evidence.shape)}")
    if target.shape != evidence.shape[:1] + evidence.shape[2:]:
        raise ValueError(
            f"target must be (B, H, W) = {tuple(evidence.shape[:1] + evidence.shape[2:])}, got "
            f"{tuple(target.shape)}"
        )


def _per_class_mean(per_cell: dict[int, torch.Tensor], target, valid, like) -> torch.Tensor:
    """Sum over classes of the mean of that class's per-cell loss over its cells (absent: 0)."""
    ok = torch.ones_like(target, dtype=torch.bool) if valid is None else valid.bool()
    total = like.new_zeros(())
    for cls, loss in per_cell.items():
        sel = (target == cls) & ok
        if sel.any():
            total = total + loss[sel].mean()
    return total


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
    _check(evidence, target)
    alpha = evidence + 1.0
    s = alpha.sum(dim=1)
    p = alpha / s.unsqueeze(1)
    y = F.one_hot(target.clamp(0, 1).long(), 2).permute(0, 3, 1, 2).to(p.dtype)
    l_k = ((y - p) ** 2 + p * (1.0 - p) / (s + 1.0).unsqueeze(1)).sum(dim=1)
    l_u = (1.0 - 2.0 / s) ** 2
    return _per_class_mean({FREE: l_k, OCCUPIED: l_k, UNKNOWN: l_u}, target, valid, evidence)


def correct_evidence_term(
    evidence: torch.Tensor, target: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """Correct-evidence regulariser after Pandey & Yu 2023: ``-nu * log(e_y)`` on free and occupied
    cells, ``e_y`` the evidence of the target's class, ``nu = 2 / S`` the vacuity (held constant,
    a weight); per-class expectations summed, unknown cells add nothing.

    Why: evidence leaves Ev-Net through a softplus, whose slope ``1 - exp(-e)`` vanishes with the
    evidence, so where the net gives a cell's true class no evidence the squared error (whose
    own gradient is bounded) barely moves it; ``d(-log e)/de = -1/e`` cancels that slope, so the
    push on the logit tends to ``nu`` = 1 as ``e -> 0``, and fades as evidence (S) grows.
    ``e_y`` is floored at the smallest normal float so a zero gives a finite loss.
    """
    _check(evidence, target)
    s = evidence.sum(dim=1) + 2.0
    nu = (2.0 / s).detach()
    cls = target.clamp(0, 1).long().unsqueeze(1)
    e_y = evidence.gather(1, cls)[:, 0].clamp_min(torch.finfo(evidence.dtype).tiny)
    l_c = -nu * torch.log(e_y)
    return _per_class_mean({FREE: l_c, OCCUPIED: l_c}, target, valid, evidence)


def training_loss(
    name: str, evidence: torch.Tensor, target: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """The loss of :data:`LOSSES` called ``name``."""
    if name == "paper":
        return evidential_loss(evidence, target, valid)
    if name == "paper+cor":
        return evidential_loss(evidence, target, valid) + correct_evidence_term(
            evidence, target, valid
        )
    raise ValueError(f"loss must be one of {LOSSES}, got {name!r}")
