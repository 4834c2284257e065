"""The maps of commit 1f2fccd, bit for bit: every change to the update path must keep them.

Two levels. The fusion level feeds seeded ISM grids (patches of free, occupied and mixed mass,
with vacuous and invalid cells) at poses that cross tiles, turn by quarter turns and by odd
angles, into one :class:`MapSet` of the six maps; each map is hashed over its tiles (keys,
masses and coverage), and the hashes were written by the code of 1f2fccd (``python
tests/test_golden_maps.py`` prints them): a hash that changes means the maps changed.

The mapper level maps a short simulated scene with the geometric ISMs (numba only, so no
inference library's kernels enter) and compares the maps with 1f2fccd's, stored whole
(tests/data/golden_mapper_1f2fccd.npz): the same tiles and coverage, masses within
:data:`MAPPER_ATOL`. Not by hash: numba compiles the ray casts for the host CPU with fast math,
and two AMD EPYC generations (with and without AVX-512 VP2INTERSECT) gave maps of 1f2fccd that
differ in the last bits.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np

from evgrid.geometry import SE2, GridSpec

GOLDEN = Path(__file__).with_name("data") / "golden_maps.json"
GOLDEN_MAPPER = Path(__file__).with_name("data") / "golden_mapper_1f2fccd.npz"
#: Masses of the mapper level may differ by this between CPUs (rounding, not a change of map).
MAPPER_ATOL = 1e-4


def _digest(m) -> str:
    h = hashlib.sha256()
    for key in sorted(m.tiles):
        masses, covered = m.tiles[key], m.covered_tiles[key]
        h.update(np.asarray(key, np.int64).tobytes())
        h.update(np.ascontiguousarray(masses).tobytes())
        h.update(np.ascontiguousarray(covered).tobytes())
    return h.hexdigest()


def _isms(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    out = {}
    for name in ("ray_ilm", "ray_irm", "deep_irm"):
        g = np.zeros((n, n, 3), np.float32)
        g[..., 2] = 1.0
        for _ in range(12):
            r, c = rng.integers(0, n - 40, 2)
            h, w = rng.integers(4, 40, 2)
            f, o = rng.uniform(0, 0.7), rng.uniform(0, 0.3)
            g[r : r + h, c : c + w] = (f, o, 1.0 - f - o)
        mixed = rng.dirichlet((1.0, 1.0, 2.0), size=(n // 4, n // 4)).astype(np.float32)
        g[: n // 4, -n // 4 :] = mixed
        g[5, 7] = (np.nan, 0.0, 1.0)  # invalid: taken as vacuous, counted
        g[9, 11] = (0.5, 0.6, 0.2)
        out[name] = g
    return out


POSES = [
    SE2(0.0, 0.0, 0.0),
    SE2(1.3, -0.4, 0.05),
    SE2(2.6, 0.2, math.pi / 2),
    SE2(7.9, 3.1, math.radians(10.0)),
    SE2(12.2, 9.7, math.radians(45.0)),
    SE2(-6.4, 4.4, math.pi),
    SE2(30.0, -22.0, -2.0),
]


def fusion_digests(update) -> dict[str, str]:
    """The six maps after ``update(maps, pose, isms)`` at :data:`POSES` with seeded ISMs."""
    from evgrid.fusion import MapSet

    grid = GridSpec(n_cells=128, length_m=19.2)
    maps = MapSet(grid)
    rng = np.random.default_rng(20261202)
    for pose in POSES:
        update(maps, pose, _isms(rng, grid.n_cells))
    return {name: _digest(maps[name]) for name in maps.names}


def mapper_maps(dynamic: bool = True) -> dict[str, np.ndarray]:
    """The geometric maps of a 2 s simulated scene (ray ILM and ray IRM, no Ev-Net), in the
    first pose's frame (the frame the reference maps were built in; runs default to the
    recording's fixed frame, MapperConfig.frame) and with the paper's evidence per look
    (``evidence.mode = "per_look"``; the default is evidence per metre), as
    ``{"NAME/TR_TC/masses" | covered: tile}``;
    ``dynamic``: with the dynamic score on (the default) or off."""
    from evgrid.config import MapperConfig
    from evgrid.fusion import DynamicParams
    from evgrid.ism.evidence import EvidenceParams
    from evgrid.mapper import OccupancyMapper
    from evgrid_sim import SimConfig, simulate_scene

    # the paper's evidence per look: the reference maps predate evidence per metre
    config = MapperConfig(
        maps=("ray_ilm", "ray_irm"),
        frame="first_pose",
        dynamic=DynamicParams(enabled=dynamic),
        evidence=EvidenceParams(mode="per_look"),
    )
    mapper = OccupancyMapper(config)
    for frame in simulate_scene(3, SimConfig(duration_s=2.0)):
        mapper.process(frame)
    out = {}
    for name in mapper.maps.names:
        m = mapper.maps[name]
        for (tr, tc), masses in m.tiles.items():
            out[f"{name}/{tr}_{tc}/masses"] = masses
            out[f"{name}/{tr}_{tc}/covered"] = m.covered_tiles[(tr, tc)]
    return out


def _update(maps, pose, isms):
    maps.update(pose, isms)


def test_fusion_maps_are_the_reference_maps():
    assert fusion_digests(_update) == json.loads(GOLDEN.read_text())["fusion"]


def test_mapper_maps_are_the_reference_maps():
    maps = mapper_maps()
    with np.load(GOLDEN_MAPPER) as ref:
        assert sorted(maps) == sorted(ref.files)
        for key, value in maps.items():
            if key.endswith("covered"):
                np.testing.assert_array_equal(value, ref[key], err_msg=key)
            else:
                np.testing.assert_allclose(value, ref[key], rtol=0, atol=MAPPER_ATOL, err_msg=key)


if __name__ == "__main__":
    import sys

    print(json.dumps({"fusion": fusion_digests(_update)}, indent=1))
    if len(sys.argv) > 1:  # python tests/test_golden_maps.py OUT.npz: the mapper level's maps
        np.savez_compressed(sys.argv[1], **mapper_maps())
