"""Ev-Net: the deep inverse radar model (Bauer et al. 2019) and its checkpoint files.

The published interface (paper sec. V-C; docs/decisions.md#ev-net-architecture): an accumulated
radar detection image in the current ego frame goes in, max-pooled at the input; an encoder-decoder
CNN; bilinear upsampling at the output; two non-negative evidence channels ``[e_f, e_o]`` come out,
turned into masses by :func:`evgrid.mass.from_evidence`. The exact layers of Ev-Net are not public:
this is a small U-Net with that interface (0.44 M parameters, 1.8 MB by default). With
``EvNetConfig.frame="polar"`` the U-Net runs on the pooled input resampled into a range x azimuth
image centred on the ego origin, and its evidence is resampled back (after arXiv 2112.04282;
docs/decisions.md#ev-net-in-the-polar-frame).

Checkpoints are safetensors files (plain tensors, never code) with the model configuration
in their metadata and, from format version 2, a SHA-256 of the tensors, checked at load. The
header is read and checked (names, dtypes, shapes against the architecture it names, within
bounds) before any tensor is allocated. The training loss lives with the training, in
:mod:`evgrid.learn.loss`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import struct
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from evgrid.validation import check_int

# Targets: classes of the ray ILM's cells (docs/decisions.md#ev-net-targets-and-loss).

__all__ = [
    "FRAMES",
    "EvNetConfig",
    "EvNet",
    "save_checkpoint",
    "load_checkpoint",
    "upgrade_checkpoint",
    "CheckpointError",
]

logger = logging.getLogger(__name__)


#: Where the U-Net runs: on the pooled Cartesian grid, or on a range x azimuth image of it.
FRAMES: tuple[str, ...] = ("cartesian", "polar")


@dataclass(frozen=True)
class EvNetConfig:
    """Architecture of an Ev-Net: input channels, first stage width, input max-pool factor, and
    the frame the U-Net runs in (``polar``: ``range_bins x azimuth_bins``, ranges linear up to
    the grid's half diagonal, azimuth over 360 deg)."""

    in_channels: int = 6
    width: int = 12  #: channels of the first stage (each deeper stage doubles them)
    pool: int = 4
    depth: int = 4  #: stages of the encoder
    frame: str = "cartesian"  #: cartesian|polar
    #: polar only: range bins (64: 0.44 m on the default grid's 28.3 m half diagonal)
    range_bins: int = 64
    #: polar only: azimuth bins over 360 deg (256: 1.4 deg; with 64 range bins as many pixels as
    #: the default pooled grid's 128 x 128)
    azimuth_bins: int = 256

    def __post_init__(self) -> None:
        for name in ("in_channels", "width", "pool", "depth", "range_bins", "azimuth_bins"):
            check_int(self, name, min=1)
        if self.frame not in FRAMES:
            raise ValueError(f"EvNetConfig.frame must be one of {FRAMES}, got {self.frame!r}")

    def to_metadata(self) -> dict[str, Any]:
        """The fields a checkpoint saves: a Cartesian net's are the four it always had (its file
        stays byte for byte what it was, and older evgrid reads it)."""
        d = asdict(self)
        if self.frame == "cartesian":
            for k in _POLAR_FIELDS:
                del d[k]
        return d


_POLAR_FIELDS = ("frame", "range_bins", "azimuth_bins")


class _AzimuthConv(nn.Conv2d):
    """A 3x3 convolution on a range x azimuth image: zero padding in range, circular in azimuth
    (the last column's neighbour is the first). Same weights as :class:`nn.Conv2d`."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        d = self.dilation[1]
        # concatenation rather than F.pad(mode="circular"): pads one dimension only, exports to
        # ONNX as Slice + Concat
        x = torch.cat([x[..., -d:], x, x[..., :d]], dim=-1)
        return F.conv2d(x, self.weight, self.bias, 1, (self.dilation[0], 0), self.dilation)


def _block(c_in: int, c_out: int, dilation: int = 1, polar: bool = False) -> nn.Sequential:
    conv = _AzimuthConv if polar else nn.Conv2d
    return nn.Sequential(
        conv(c_in, c_out, 3, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
        conv(c_out, c_out, 3, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


def polar_sampling(
    h: int, w: int, range_bins: int, azimuth_bins: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``F.grid_sample`` grids between a Cartesian image ``(h, w)`` centred on the ego (row 0
    ahead, column 0 left, as :class:`evgrid.geometry.GridSpec`) and a polar one ``(range_bins,
    azimuth_bins)``: ``to_polar`` ``(1, 2 range_bins, 2 azimuth_bins, 2)`` samples the Cartesian
    image at the centres of each polar bin's 2 x 2 sub-bins (range ``(i + 0.5) / (2 range_bins)``
    of the half diagonal, azimuth ``-180 + (j + 0.5) * 180 / azimuth_bins`` deg from the x axis
    towards y), to be max-pooled by 2; ``to_cartesian``
    ``(1, h, w, 2)`` samples the polar image, padded by one column either side (azimuth wraps),
    at each Cartesian cell's centre. Coordinates as ``align_corners=False``, float32.
    """
    diag = math.sqrt(2.0)  # the half diagonal in units of the half edge (a square grid)
    nr, na = 2 * range_bins, 2 * azimuth_bins
    rho = (torch.arange(nr, dtype=torch.float64) + 0.5) / nr * diag
    phi = -math.pi + (torch.arange(na, dtype=torch.float64) + 0.5) * (2 * math.pi / na)
    x = rho[:, None] * torch.cos(phi)[None, :]  # ego x (ahead), y (left): half edges
    y = rho[:, None] * torch.sin(phi)[None, :]
    to_polar = torch.stack([-y, -x], dim=-1)  # grid_sample's (column, row) coordinates
    gy = (2 * torch.arange(h, dtype=torch.float64) + 1) / h - 1  # row -> -x
    gx = (2 * torch.arange(w, dtype=torch.float64) + 1) / w - 1  # column -> -y
    xs, ys = -gy[:, None].expand(h, w), -gx[None, :].expand(h, w)
    r = torch.sqrt(xs**2 + ys**2)
    a = torch.atan2(ys, xs)  # [-pi, pi]
    u = a / math.pi * azimuth_bins / (azimuth_bins + 2)  # in the padded image
    v = r / diag * 2 - 1
    to_cartesian = torch.stack([u, v], dim=-1)
    return to_polar[None].float(), to_cartesian[None].float()


class EvNet(nn.Module):
    """Encoder-decoder from a radar detection image ``(B, C, H, W)`` to evidence ``(B, 2, H, W)`` >=
    0."""

    def __init__(self, config: EvNetConfig = EvNetConfig()):
        super().__init__()
        self.config = config
        polar = config.frame == "polar"
        w, d = config.width, config.depth
        widths = [w * 2**k for k in range(d)]
        self.pool_in = nn.MaxPool2d(config.pool) if config.pool > 1 else nn.Identity()
        self.enc = nn.ModuleList()
        c = config.in_channels
        for k, wk in enumerate(widths):
            self.enc.append(_block(c, wk, polar=polar))
            c = wk
        # Dilated bottleneck: radar detections are sparse, free space lies between them and the
        # sensor, metres away; dilation widens the receptive field cheaply.
        self.bottleneck = _block(c, c, dilation=2, polar=polar)
        self.dec = nn.ModuleList()
        for k in range(d - 2, -1, -1):
            self.dec.append(_block(c + widths[k], widths[k], polar=polar))
            c = widths[k]
        self.head = nn.Conv2d(c, 2, 1)
        self._grids: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def trunk(self, h: torch.Tensor) -> torch.Tensor:
        """Evidence ``[e_f, e_o]`` at the max-pooled input's resolution: the U-Net between the
        input pooling and the output upsampling (what the deep IRM's fast path runs); in the
        polar frame, with the resampling into and out of it."""
        if self.config.frame == "cartesian":
            return self._unet(h)
        to_polar, to_cart = self._sampling(h)
        b = h.shape[0]
        # Every channel bilinear at 2 x 2 points a polar bin, then the max of the four (the input
        # is a max-pool already): where polar bins are coarser than pooled cells (beyond 20 m by
        # default) one point a bin, nearest or bilinear, skips cells and their detections; this
        # reaches every cell. Zeros beyond the grid: no detection is known there.
        p = F.grid_sample(
            h, to_polar.expand(b, -1, -1, -1), "bilinear", "zeros", align_corners=False
        )
        e = self._unet(F.max_pool2d(p, 2))
        e = torch.cat([e[..., -1:], e, e[..., :1]], dim=-1)  # azimuth wraps
        # bilinear: evidence stays non-negative under a convex mix
        return F.grid_sample(
            e, to_cart.expand(b, -1, -1, -1), "bilinear", "border", align_corners=False
        )

    def _sampling(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`polar_sampling`'s grids for inputs like ``h``, made once per size and device."""
        key = (int(h.shape[-2]), int(h.shape[-1]), h.device, h.dtype)
        if key not in self._grids:
            c = self.config
            grids = polar_sampling(key[0], key[1], c.range_bins, c.azimuth_bins)
            self._grids[key] = tuple(g.to(h.device, h.dtype) for g in grids)
        return self._grids[key]

    def _unet(self, h: torch.Tensor) -> torch.Tensor:
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
        return F.softplus(self.head(h))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Evidence ``[e_f, e_o]`` at the input's resolution."""
        size = x.shape[-2:]
        e = self.trunk(self.pool_in(x))
        if e.shape[-2:] != size:
            # upsample evidence, which stays non-negative under a convex (bilinear) mix
            e = F.interpolate(e, size=size, mode="bilinear", align_corners=False)
        return e


# --- checkpoints ---------------------------------------------------------------------------------

_FORMAT = "evgrid-evnet"
_FORMAT_VERSION = 2
_READABLE_VERSIONS = ("1", "2")
_DIGEST_KEY = "tensors_sha256"

# Bounds on what a checkpoint may ask for, checked before anything is allocated: far above any
# useful Ev-Net (the shipped one has 0.44 M parameters), far below what would exhaust memory.
_CONFIG_MAX = {
    "in_channels": 64,
    "width": 512,
    "pool": 64,
    "depth": 8,
    "range_bins": 1024,
    "azimuth_bins": 4096,
}
_MAX_PARAMS = 64_000_000
#: The largest magnitude a weight (or normalisation statistic) may have. A finite but huge
#: weight that passes the checksum (a file written that way on purpose) would overflow float32
#: activations to inf and then masses to NaN, i.e. a silently wrong map; trained weights stay
#: orders of magnitude below this bound.
MAX_WEIGHT = 1e6
_MAX_HEADER_BYTES = 1 << 24

# safetensors dtype codes of the tensors an EvNet holds
_DTYPE_CODES = {torch.float32: "F32", torch.int64: "I64"}


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used: unreadable, not an Ev-Net, corrupt, or of another
    shape."""


def _parse_header(prefix: bytes, size: int, path: Path) -> tuple[dict[str, Any], int]:
    """The JSON header (tensor entries and ``__metadata__``) of a safetensors file of ``size`` bytes
    starting with ``prefix``, and where its data section starts."""
    if size < 8 or len(prefix) < 8:
        raise CheckpointError(f"{path}: not a safetensors checkpoint ({size} bytes)")
    (n,) = struct.unpack("<Q", prefix[:8])
    if n > min(_MAX_HEADER_BYTES, size - 8) or len(prefix) < 8 + n:
        raise CheckpointError(
            f"{path}: not a safetensors checkpoint, or truncated (header of {n} bytes in a file of "
            f"{size})"
        )
    try:
        header = json.loads(prefix[8 : 8 + n].decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise CheckpointError(
            f"{path}: not a safetensors checkpoint (unreadable header: {e})"
        ) from e
    if not isinstance(header, dict):
        raise CheckpointError(f"{path}: not a safetensors checkpoint (header is not a JSON object)")
    return header, 8 + n


def _read_header(path: Path) -> tuple[dict[str, Any], int, int]:
    """Header, data start and size of a checkpoint file, reading only the header."""
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            prefix = f.read(8)
            if len(prefix) == 8:
                n = struct.unpack("<Q", prefix)[0]
                if n <= min(_MAX_HEADER_BYTES, size - 8):
                    prefix += f.read(n)
    except OSError as e:
        raise CheckpointError(f"{path}: cannot read the checkpoint ({e})") from e
    header, start = _parse_header(prefix, size, path)
    return header, start, size


def _entries(
    header: dict[str, Any], path: Path
) -> dict[str, tuple[str, tuple[int, ...], int, int]]:
    """Tensor entries of a header: name -> (dtype code, shape, begin, end) in the data section."""
    out = {}
    for name, e in header.items():
        if name == "__metadata__":
            continue
        try:
            dtype, shape, (begin, end) = e["dtype"], tuple(e["shape"]), e["data_offsets"]
            if not (
                isinstance(dtype, str)
                and all(isinstance(d, int) and d >= 0 for d in shape)
                and isinstance(begin, int)
                and isinstance(end, int)
            ):
                raise TypeError
        except (KeyError, TypeError, ValueError):
            raise CheckpointError(
                f"{path}: broken entry for tensor {name!r} in the header"
            ) from None
        out[name] = (dtype, shape, begin, end)
    return out


def _digest(entries: dict[str, tuple[str, tuple[int, ...], int, int]], data: bytes) -> str:
    """SHA-256 over every tensor (name, dtype, shape and bytes), in name order."""
    h = hashlib.sha256()
    for name in sorted(entries):
        dtype, shape, begin, end = entries[name]
        h.update(f"{name}|{dtype}|{list(shape)}|{end - begin}\n".encode())
        h.update(data[begin:end])
    return h.hexdigest()


def _metadata_field(meta: dict[str, str], name: str, path: Path) -> str:
    v = meta.get(name)
    if not isinstance(v, str):
        raise CheckpointError(f"{path}: checkpoint metadata field {name!r} is missing or not text")
    return v


def _config_from(meta: dict[str, str], path: Path) -> EvNetConfig:
    """The EvNetConfig named by the metadata, within bounds (nothing allocated yet)."""
    try:
        cfg = json.loads(_metadata_field(meta, "config", path))
    except ValueError as e:
        raise CheckpointError(
            f"{path}: checkpoint metadata field 'config' is not JSON ({e})"
        ) from e
    if not isinstance(cfg, dict):
        raise CheckpointError(
            f"{path}: checkpoint metadata field 'config' must be a JSON object, got {cfg!r:.80}"
        )
    unknown = sorted(set(cfg) - set(_CONFIG_MAX) - {"frame"})
    if unknown:
        raise CheckpointError(
            f"{path}: checkpoint metadata field 'config' has unknown key(s) {unknown}"
        )
    for key, hi in _CONFIG_MAX.items():
        v = cfg.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= hi):
            raise CheckpointError(
                f"{path}: checkpoint metadata field 'config.{key}' must be an integer in [1, "
                f"{hi}], got {v!r:.80}"
            )
    if "frame" in cfg and cfg["frame"] not in FRAMES:
        raise CheckpointError(
            f"{path}: checkpoint metadata field 'config.frame' must be one of {FRAMES}, got "
            f"{cfg['frame']!r:.80}"
        )
    try:
        return EvNetConfig(**cfg)  # a file without 'frame' (before it existed) is Cartesian
    except (TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: checkpoint metadata field 'config' is invalid ({e})") from e


def _expected(config: EvNetConfig, path: Path) -> dict[str, tuple[str, tuple[int, ...]]]:
    """Name -> (dtype code, shape) of every tensor of an EvNet of ``config``, built on the meta
    device (no memory)."""
    with torch.device("meta"):
        sd = EvNet(config).state_dict()
    n = sum(v.numel() for v in sd.values())
    if n > _MAX_PARAMS:
        raise CheckpointError(
            f"{path}: checkpoint metadata field 'config' describes {n:,} parameters, more than the "
            f"{_MAX_PARAMS:,} allowed"
        )
    return {k: (_DTYPE_CODES.get(v.dtype, str(v.dtype)), tuple(v.shape)) for k, v in sd.items()}


def _tensor_bytes(dtype: str, shape: tuple[int, ...]) -> int:
    return {"F32": 4, "I64": 8}[dtype] * math.prod(shape)


def _serialise(model: EvNet, extra: dict[str, Any] | None) -> bytes:
    """A format-2 checkpoint of ``model``: safetensors bytes, config, extra, tensor digest."""
    from safetensors.torch import save

    meta = {
        "format": _FORMAT,
        "version": str(_FORMAT_VERSION),
        "config": json.dumps(model.config.to_metadata()),
        "extra": json.dumps(extra or {}),
    }
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    # the data section does not depend on the metadata: serialise once to hash it, then with the
    # hash
    buf = save(tensors, metadata=meta)
    header, start = _parse_header(buf, len(buf), Path("<memory>"))
    meta[_DIGEST_KEY] = _digest(_entries(header, Path("<memory>")), memoryview(buf)[start:])
    return save(tensors, metadata=meta)


def save_checkpoint(
    model: EvNet, path: str | os.PathLike, extra: dict[str, Any] | None = None
) -> Path:
    """Write the model's weights and config as a safetensors file (format 2), atomically; ``extra``
    goes in its metadata."""
    from evgrid.io import atomic_write

    data = _serialise(model, extra)
    return atomic_write(path, lambda f: f.write(data))


@dataclass
class LoadedCheckpoint:
    """A loaded Ev-Net and the metadata saved beside it; ``version``: the file's format version."""

    model: EvNet
    path: Path
    extra: dict[str, Any] = field(default_factory=dict)
    version: int = _FORMAT_VERSION


def _check_entries(
    entries: dict[str, tuple[str, tuple[int, ...], int, int]],
    expected: dict[str, tuple[str, tuple[int, ...]]],
    n_data: int,
    saved: EvNetConfig,
    path: Path,
) -> int:
    """Every tensor the architecture has, of its dtype and shape, within the file's
    ``n_data`` bytes of data and filling them; returns ``n_data``."""
    missing = sorted(set(expected) - set(entries))
    unexpected = sorted(set(entries) - set(expected))
    if missing or unexpected:
        raise CheckpointError(
            f"{path}: weights do not match {saved}: missing {missing[:3]}, unexpected "
            f"{unexpected[:3]}"
        )
    for k, (dtype, shape, begin, end) in entries.items():
        want_dtype, want_shape = expected[k]
        if shape != want_shape:
            raise CheckpointError(f"{path}: weight {k} has shape {shape}, expected {want_shape}")
        if dtype != want_dtype:
            raise CheckpointError(f"{path}: weight {k} has dtype {dtype}, expected {want_dtype}")
        if not (0 <= begin <= end <= n_data) or end - begin != _tensor_bytes(dtype, shape):
            raise CheckpointError(
                f"{path}: weight {k} has data offsets [{begin}, {end}) that do not fit the file; "
                "it is truncated or corrupt"
            )
    if n_data != sum(_tensor_bytes(d, sh) for d, sh, _, _ in entries.values()):
        raise CheckpointError(
            f"{path}: {n_data} bytes of tensor data where the header describes "
            f"{sum(_tensor_bytes(d, sh) for d, sh, _, _ in entries.values())}"
        )
    return n_data


def _check_weights(tensors: dict[str, torch.Tensor], path: Path) -> None:
    """Finite weights, none beyond :data:`MAX_WEIGHT` in magnitude."""
    for k, v in tensors.items():
        if not v.is_floating_point() or not v.numel():
            continue
        if not torch.isfinite(v).all():
            raise CheckpointError(f"{path}: weight {k} holds NaN or inf")
        if float(v.abs().max()) > MAX_WEIGHT:
            raise CheckpointError(
                f"{path}: weight {k} holds {float(v.abs().max()):.3g}, beyond the bound of "
                f"{MAX_WEIGHT:.0e} on any weight's magnitude"
            )


def _checkpoint_metadata(header: dict, path: Path) -> tuple[dict, str, EvNetConfig, dict]:
    """A checkpoint's metadata checked: (the metadata, its format version, the Ev-Net
    configuration it saved, its ``extra`` object, whose ``grid`` must be a grid)."""
    meta = header.get("__metadata__") or {}
    if not isinstance(meta, dict):
        raise CheckpointError(f"{path}: checkpoint metadata is not a JSON object")
    if meta.get("format") != _FORMAT:
        raise CheckpointError(
            f"{path}: not an evgrid Ev-Net checkpoint (metadata field 'format' is "
            f"{meta.get('format')!r})"
        )
    version = meta.get("version")
    if version not in _READABLE_VERSIONS:
        raise CheckpointError(
            f"{path}: checkpoint format version {version!r} (metadata field 'version'), this "
            f"evgrid reads {', '.join(_READABLE_VERSIONS)}"
        )
    saved = _config_from(meta, path)
    try:
        extra = json.loads(meta.get("extra", "{}"))
    except (TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: checkpoint metadata field 'extra' is not JSON ({e})") from e
    if not isinstance(extra, dict):
        raise CheckpointError(
            f"{path}: checkpoint metadata field 'extra' must be a JSON object, got "
            f"{type(extra).__name__}"
        )
    if "grid" in extra:  # the grid it was trained on, which DeepIrm compares with its own
        from evgrid.geometry import GridSpec

        try:
            GridSpec.from_dict(extra["grid"])
        except (AttributeError, KeyError, TypeError, ValueError) as e:
            raise CheckpointError(
                f"{path}: checkpoint metadata field 'extra.grid' is not a grid ({e})"
            ) from e
    return meta, version, saved, extra


def _check_digest(meta: dict, version: str, entries, data: memoryview, path: Path) -> None:
    """Format 2: the weights ``data`` against the SHA-256 in the metadata; format 1 has none,
    and loads with a warning."""
    if version == "1":
        logger.warning(
            "%s: checkpoint format 1 has no checksum of its weights; upgrade it with "
            "evgrid.ism.evnet.upgrade_checkpoint(src, dst) (evgrid upgrade-checkpoint SRC DST)",
            path,
        )
    else:
        digest = _metadata_field(meta, _DIGEST_KEY, path)
        if _digest(entries, data) != digest:
            raise CheckpointError(
                f"{path}: the weights do not match the checksum in the metadata (field "
                f"{_DIGEST_KEY!r}); the file is corrupt"
            )


def load_checkpoint(path: str | os.PathLike, config: EvNetConfig | None = None) -> LoadedCheckpoint:
    """Load an Ev-Net from a safetensors file (no code is run); raise CheckpointError naming file
    and problem.

    Format 2 files must match their SHA-256; format 1 files (no digest) load with a warning
    recommending :func:`upgrade_checkpoint`.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no Ev-Net checkpoint at {path}")
    header, start, size = _read_header(path)
    meta, version, saved, extra = _checkpoint_metadata(header, path)
    if config is not None and config != saved:
        raise CheckpointError(f"{path}: checkpoint is for {saved}, but {config} was asked for")

    # the header against the architecture, before a byte of tensor data is allocated
    entries = _entries(header, path)
    n_data = _check_entries(entries, _expected(saved, path), size - start, saved, path)
    try:
        buf = path.read_bytes()  # now known to be the size of the architecture's weights
    except OSError as e:
        raise CheckpointError(f"{path}: cannot read the checkpoint ({e})") from e
    data = memoryview(buf)[start:]
    if len(data) != n_data:
        raise CheckpointError(f"{path}: the file changed while it was read")
    _check_digest(meta, version, entries, data, path)
    try:
        tensors = load(buf)
    except (SafetensorError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path}: not a readable safetensors checkpoint ({e})") from e
    _check_weights(tensors, path)
    model = EvNet(saved)
    model.load_state_dict(tensors)
    model.eval()
    return LoadedCheckpoint(model, path, extra, int(version))


def upgrade_checkpoint(src: str | os.PathLike, dst: str | os.PathLike) -> Path:
    """Rewrite a checkpoint in the current format (with its checksum), same weights and metadata;
    ``dst`` may be ``src``."""
    loaded = load_checkpoint(src)
    data = _serialise(loaded.model, loaded.extra)
    from safetensors.torch import load

    from evgrid.io import atomic_write

    # the weights written are the weights read, bit for bit
    before, after = loaded.model.state_dict(), load(data)
    if set(before) != set(after) or not all(torch.equal(before[k], after[k]) for k in before):
        raise CheckpointError(f"{src}: upgrading changed the weights; nothing was written")
    return atomic_write(dst, lambda f: f.write(data))
