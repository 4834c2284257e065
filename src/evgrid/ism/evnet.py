"""Ev-Net: the deep inverse radar model (Bauer et al. 2019) and its checkpoint files.

The published interface (paper sec. V-C; docs/decisions.md#ev-net-architecture): an accumulated radar detection image in
the current ego frame goes in, max-pooled at the input; an encoder-decoder CNN; bilinear
upsampling at the output; two non-negative evidence channels ``[e_f, e_o]`` come out, turned
into masses by :func:`evgrid.mass.from_evidence`. The exact layers of Ev-Net are not public:
this is a small U-Net with that interface (0.44 M parameters, 1.8 MB by default).

Checkpoints are safetensors files (plain tensors, never code) with the model configuration
in their metadata. The training loss lives with the training, in :mod:`evgrid.learn.loss`.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

# Targets: classes of the ray ILM's cells (docs/decisions.md#ev-net-targets-and-loss).

__all__ = ["EvNetConfig", "EvNet", "save_checkpoint", "load_checkpoint", "CheckpointError"]



@dataclass(frozen=True)
class EvNetConfig:
    """Architecture of an Ev-Net: input channels, width of the first stage, input max-pool factor."""

    in_channels: int = 6
    width: int = 12
    pool: int = 4
    depth: int = 4

    def __post_init__(self) -> None:
        for name in ("in_channels", "width", "pool", "depth"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"EvNetConfig.{name} must be a positive integer, got {v!r}")


def _block(c_in: int, c_out: int, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
        nn.Conv2d(c_out, c_out, 3, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class EvNet(nn.Module):
    """Encoder-decoder from a radar detection image ``(B, C, H, W)`` to evidence ``(B, 2, H, W)`` >= 0."""

    def __init__(self, config: EvNetConfig = EvNetConfig()):
        super().__init__()
        self.config = config
        w, d = config.width, config.depth
        widths = [w * 2**k for k in range(d)]
        self.pool_in = nn.MaxPool2d(config.pool) if config.pool > 1 else nn.Identity()
        self.enc = nn.ModuleList()
        c = config.in_channels
        for k, wk in enumerate(widths):
            self.enc.append(_block(c, wk))
            c = wk
        # Dilated bottleneck: radar detections are sparse, free space lies between them and the
        # sensor, metres away; dilation widens the receptive field cheaply.
        self.bottleneck = _block(c, c, dilation=2)
        self.dec = nn.ModuleList()
        for k in range(d - 2, -1, -1):
            self.dec.append(_block(c + widths[k], widths[k]))
            c = widths[k]
        self.head = nn.Conv2d(c, 2, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Evidence ``[e_f, e_o]`` at the input's resolution."""
        size = x.shape[-2:]
        h = self.pool_in(x)
        skips = []
        for k, blk in enumerate(self.enc):
            if k:
                h = F.max_pool2d(h, 2)
            h = blk(h)
            skips.append(h)
        h = self.bottleneck(h)
        for blk, skip in zip(self.dec, reversed(skips[:-1])):
            h = F.interpolate(h, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            h = blk(torch.cat([h, skip], dim=1))
        e = F.softplus(self.head(h))
        if e.shape[-2:] != size:
            # upsample evidence, which stays non-negative under a convex (bilinear) mix
            e = F.interpolate(e, size=size, mode="bilinear", align_corners=False)
        return e


# --- checkpoints ---------------------------------------------------------------------------------

_FORMAT = "evgrid-evnet"
_FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used: unreadable, not an Ev-Net, or of another shape."""


def save_checkpoint(model: EvNet, path: str | os.PathLike, extra: dict[str, Any] | None = None) -> Path:
    """Write the model's weights and config as a safetensors file, atomically; ``extra`` goes in its metadata."""
    from safetensors.torch import save

    from evgrid.io import atomic_write

    meta = {
        "format": _FORMAT,
        "version": str(_FORMAT_VERSION),
        "config": json.dumps(asdict(model.config)),
        "extra": json.dumps(extra or {}),
    }
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    data = save(tensors, metadata=meta)
    return atomic_write(path, lambda f: f.write(data))


@dataclass
class LoadedCheckpoint:
    """A loaded Ev-Net with the metadata saved beside it."""

    model: EvNet
    path: Path
    extra: dict[str, Any] = field(default_factory=dict)


def load_checkpoint(path: str | os.PathLike, config: EvNetConfig | None = None) -> LoadedCheckpoint:
    """Load an Ev-Net from a safetensors file (no code is run); raise CheckpointError naming file and problem."""
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no Ev-Net checkpoint at {path}")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path}: not a readable safetensors checkpoint ({e})") from e
    if meta.get("format") != _FORMAT:
        raise CheckpointError(f"{path}: not an evgrid Ev-Net checkpoint (format {meta.get('format')!r})")
    if meta.get("version") != str(_FORMAT_VERSION):
        raise CheckpointError(f"{path}: checkpoint format version {meta.get('version')!r}, this evgrid reads {_FORMAT_VERSION}")
    try:
        saved = EvNetConfig(**json.loads(meta["config"]))
        extra = json.loads(meta.get("extra", "{}"))
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: broken config in the checkpoint metadata ({e})") from e
    if config is not None and config != saved:
        raise CheckpointError(f"{path}: checkpoint is for {saved}, but {config} was asked for")
    model = EvNet(saved)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise CheckpointError(f"{path}: weights do not match {saved}: missing {missing[:3]}, unexpected {unexpected[:3]}")
    for k, v in tensors.items():
        if v.shape != expected[k].shape:
            raise CheckpointError(f"{path}: weight {k} has shape {tuple(v.shape)}, expected {tuple(expected[k].shape)}")
        if v.is_floating_point() and not torch.isfinite(v).all():
            raise CheckpointError(f"{path}: weight {k} holds NaN or inf")
    model.load_state_dict(tensors)
    model.eval()
    return LoadedCheckpoint(model, path, extra)
