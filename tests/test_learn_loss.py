import math

import pytest
import torch
from torch.nn import functional as F

from evgrid.classes import FREE, OCCUPIED, UNKNOWN
from evgrid.learn.loss import correct_evidence_term, evidential_loss, training_loss


def test_correct_evidence_term_hand_computed():
    # e = [2, 4]: S = 8, nu = 2/8; free cell: -nu log 2, occupied: -nu log 4, unknown: nothing
    e = torch.tensor([2.0, 4.0]).view(1, 2, 1, 1).expand(1, 2, 1, 3).contiguous()
    t = torch.tensor([[[FREE, OCCUPIED, UNKNOWN]]])
    want = -0.25 * math.log(2.0) - 0.25 * math.log(4.0)
    assert float(correct_evidence_term(e, t)) == pytest.approx(want, rel=1e-6)
    both = training_loss("paper+cor", e, t)
    assert float(both) == pytest.approx(float(evidential_loss(e, t)) + want, rel=1e-6)
    assert float(training_loss("paper", e, t)) == float(evidential_loss(e, t))


def test_correct_evidence_term_per_class_expectations_and_valid():
    # e_f = 1 on three free cells (log 1 = 0), e_o = e on one occupied cell: only it counts, once
    e = torch.zeros(1, 2, 1, 4)
    e[0, 0, 0, :3] = 1.0
    e[0, 1, 0, 3] = math.e
    t = torch.tensor([[[FREE, FREE, FREE, OCCUPIED]]])
    assert float(correct_evidence_term(e, t)) == pytest.approx(-2.0 / (2.0 + math.e), rel=1e-6)
    valid = torch.tensor([[[True, True, True, False]]])
    assert float(correct_evidence_term(e, t, valid)) == pytest.approx(0.0, abs=1e-7)


def test_paper_loss_stalls_at_zero_evidence_the_term_does_not():
    # evidence = softplus(z): at z = -20 the true class has ~2e-9 evidence. The paper's loss
    # pushes z by ~1e-9; the correct-evidence term by ~nu = 1.
    z = torch.full((1, 2, 1, 1), -20.0, requires_grad=True)
    t = torch.tensor([[[FREE]]])
    (g_paper,) = torch.autograd.grad(evidential_loss(F.softplus(z), t), z)
    (g_cor,) = torch.autograd.grad(correct_evidence_term(F.softplus(z), t), z)
    assert abs(float(g_paper[0, 0])) < 1e-8
    assert float(g_cor[0, 0]) == pytest.approx(-1.0, rel=1e-3)  # raises the free evidence


def test_correct_evidence_term_is_finite_at_zero_evidence():
    e = torch.zeros(1, 2, 1, 1, requires_grad=True)
    v = correct_evidence_term(e, torch.tensor([[[OCCUPIED]]]))
    v.backward()
    assert math.isfinite(float(v.detach())) and torch.isfinite(e.grad).all()


def test_unknown_loss_name_is_refused():
    with pytest.raises(ValueError, match="paper"):
        training_loss("mse", torch.zeros(1, 2, 1, 1), torch.zeros(1, 1, 1, dtype=torch.long))


def test_train_config_names_its_loss():
    from evgrid.learn.train import TrainConfig

    assert TrainConfig(loss="paper").loss == "paper"
    with pytest.raises(ValueError, match="loss"):
        TrainConfig(loss="mse")
