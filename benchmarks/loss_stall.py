"""Does Ev-Net's loss stop learning where evidence is low? (issue 38, point 3)

On cached training samples (``evgrid train``'s cache folder): for each loss of
``evgrid.learn.loss.LOSSES``, the mean magnitude of the per-cell gradient on the logit of the
target class's evidence (evidence = softplus(logit)) of free and occupied cells, binned by that
evidence, for a net at its initialisation (or a checkpoint); then a short training from the same
initialisation with each loss, and the share of free / occupied cells whose target-class evidence
stays below 0.1.

    python benchmarks/loss_stall.py --cache OUT/cache/KEY [--checkpoint X] [--steps 60]

Measures and prints; nothing here is a test.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from evgrid.classes import FREE, OCCUPIED
from evgrid.geometry import GridSpec
from evgrid.ism.evnet import EvNet, EvNetConfig, load_checkpoint
from evgrid.learn.loss import LOSSES, training_loss
from evgrid.learn.train import RadarDataset

BINS = (0.0, 0.01, 0.1, 1.0, 10.0, np.inf)


def _batch(ds, idx):
    xs, ts = zip(*(ds[i] for i in idx))
    return torch.stack(xs), torch.stack(ts)


def _logit_grads(net, x, t, loss):
    """Per-cell |dL/dz_y| (z_y: the target class's logit) and e_y, of free and occupied cells."""
    net.eval()
    e = net(x).detach().requires_grad_(True)
    (g,) = torch.autograd.grad(training_loss(loss, e, t), e)
    cls = t.clamp(0, 1).unsqueeze(1)
    e_y = e.detach().gather(1, cls)[:, 0]
    g_y = g.gather(1, cls)[:, 0] * (1.0 - torch.exp(-e_y))  # softplus' slope
    out = {}
    for c in (FREE, OCCUPIED):
        sel = t == c
        # the loss is a per-class mean: undo the 1/N to get a cell's own gradient
        out[c] = (e_y[sel].numpy(), (g_y[sel].abs() * sel.sum()).numpy())
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cache", required=True, help="a cache folder of evgrid train (with index)")
    ap.add_argument("--checkpoint", default=None, help="a checkpoint (default: a fresh net)")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    root = Path(args.cache)
    scenes = sorted(json.loads((root / "index.json").read_text())["shards"])
    ds = RadarDataset(root, scenes, GridSpec())
    rng = np.random.default_rng(args.seed)
    probe = _batch(ds, rng.choice(len(ds), args.batch_size, replace=False))
    if args.checkpoint:
        init = load_checkpoint(args.checkpoint).model
    else:
        init = EvNet(EvNetConfig())
    state = {k: v.clone() for k, v in init.state_dict().items()}
    print(f"{len(ds)} samples of {len(scenes)} scenes; net: {args.checkpoint or 'fresh'}")
    print("per-cell |dL/dz_y| of the target class's logit, by the target class's evidence e_y")
    for loss in LOSSES:
        g = _logit_grads(init, *probe, loss)
        for c, name in ((FREE, "free"), (OCCUPIED, "occupied")):
            e_y, gy = g[c]
            cells = []
            for lo, hi in zip(BINS[:-1], BINS[1:]):
                sel = (e_y >= lo) & (e_y < hi)
                m = f"{gy[sel].mean():.2e}" if sel.any() else "-"
                cells.append(f"[{lo:g},{hi:g}): n={int(sel.sum())} {m}")
            print(f"  {loss:10s} {name:8s} " + "; ".join(cells))
    print(f"after {args.steps} AdamW steps (lr 2e-3, batch {args.batch_size}) from the same start:")
    for loss in LOSSES:
        net = EvNet(init.config)
        net.load_state_dict(state)
        opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-4)
        r = np.random.default_rng(args.seed + 1)
        for _ in range(args.steps):
            net.train()
            x, t = _batch(ds, r.choice(len(ds), args.batch_size, replace=False))
            opt.zero_grad()
            training_loss(loss, net(x), t).backward()
            opt.step()
        g = _logit_grads(net, *probe, loss)
        shares = ", ".join(
            f"{name} {np.mean(g[c][0] < 0.1):.3f} (median e_y {np.median(g[c][0]):.3g})"
            for c, name in ((FREE, "free"), (OCCUPIED, "occupied"))
        )
        print(f"  {loss:10s} share of cells with e_y < 0.1: {shares}")


if __name__ == "__main__":
    main()
