"""The paper's claims at scale: Table I and the convergence table over many simulated val scenes.

Maps ``--scenes`` simulated validation scenes of ``--duration`` seconds (default 50 of 20 s,
seeds from ``--first-seed`` on, default 1000: 1004, 1009, ...) with the shipped Ev-Net through
:func:`evgrid.engine.fan_out` (``--engine local|ray``, ``--workers``), and reports Table I
(against ``ray_ilm``), IoU against the simulator's truth and the convergence table, each with
its 95 % bootstrap interval over scenes, and the paired bootstrap intervals (resampling
scenes) of the differences that carry the paper's claims:

* ``fused`` minus ``ray_irm``, free IoU against the truth after 1, 2, 5 and 10 s (the deep
  prior speeds up convergence, Sec. IV);
* ``fused`` minus each deep map (``deep_acc``, ``deep_replace``, ``deep_disc``) on Table I's
  classes (the fused map is at least as good as the deep maps, Table I).

The seeds are checked to be disjoint from the shipped checkpoints' training scenes (the first
40 train-split and first 8 val-split seeds from 0), from the ``m_u_min`` sweep's (4, 9, 14,
19) and from those that chose the radar-support radius (val seeds 504, ..., 549). Each scene's
metrics are written to ``OUT/scenes/<scene>.json`` as it finishes, and the
tables are rewritten after every scene, so a run that is cut short still reports the scenes it
finished; run again with the same ``--out`` and the finished scenes are kept, not redone.

Run: ``PYTHONPATH=src python benchmarks/claims_at_scale.py --out out/claims --workers 2``.
Prints and writes ``OUT/claims.md`` and ``OUT/claims.json``; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from evgrid.classes import CLASSES  # noqa: E402
from evgrid.config import OutputConfig, RunConfig, resolve_config  # noqa: E402
from evgrid.engine import ENGINES, fan_out  # noqa: E402
from evgrid.evaluate import bootstrap_interval, markdown_table  # noqa: E402
from evgrid.io import atomic_write_text, write_json  # noqa: E402
from evgrid.runs import convergence_table, map_scene, summarize  # noqa: E402
from evgrid.sources import SimSource  # noqa: E402

DEEP_MAPS = ("deep_acc", "deep_replace", "deep_disc")
# The scenes the shipped checkpoints and the choices of m_u_min and of the radar-support radius
# saw (docs/decisions.md, docs/training.md).
SWEEP_SEEDS = (4, 9, 14, 19)
SUPPORT_SEEDS = SimSource.split("val", 10, first_seed=500).seeds  # 504, 509, ..., 549


def used_seeds() -> set[int]:
    """Seeds of the shipped checkpoints' training and validation scenes (sim-v2's are the first
    of sim-v1's), of the m_u_min sweep and of the radar-support radius's choice."""
    train = SimSource.split("train", 40, first_seed=0).seeds
    val = SimSource.split("val", 8, first_seed=0).seeds
    return set(train) | set(val) | set(SWEEP_SEEDS) | set(SUPPORT_SEEDS)


def map_one(args: tuple) -> dict[str, Any]:
    """One scene's metrics (module level: it runs in a worker process or a Ray task)."""
    source, name, config, outputs = args
    return map_scene(source.load(name), None, config, outputs, name=name).metrics


def paired(per_scene: list[dict], a: str, b: str, get) -> dict[str, float]:
    """Mean of ``get(scene, a) - get(scene, b)`` with its bootstrap interval over scenes."""
    diffs = []
    for m in per_scene:
        x, y = get(m, a), get(m, b)
        if x is None or y is None or math.isnan(x) or math.isnan(y):
            continue
        diffs.append(x - y)
    return bootstrap_interval(diffs)


def differences(per_scene: list[dict]) -> dict[str, Any]:
    """The paired differences that carry the paper's claims (see the module docstring)."""

    def conv_free(i: int):
        return lambda m, n: m["convergence_truth"]["maps"][n]["free"][i]

    t_s = per_scene[0]["convergence_truth"]["t_s"]
    out: dict[str, Any] = {
        "fused_minus_ray_irm_free_vs_truth_after": {
            f"{t:g}": paired(per_scene, "fused", "ray_irm", conv_free(i)) for i, t in enumerate(t_s)
        },
        "fused_minus_deep_vs_ray_ilm": {},
        "fused_minus_deep_vs_truth": {},
    }
    for deep in DEEP_MAPS:
        out["fused_minus_deep_vs_ray_ilm"][deep] = {
            c: paired(per_scene, "fused", deep, lambda m, n, c=c: m["vs_ray_ilm"][n][c])
            for c in CLASSES
        }
        out["fused_minus_deep_vs_truth"][deep] = {
            c: paired(per_scene, "fused", deep, lambda m, n, c=c: m["vs_truth"][n].get(c))
            for c in ("free", "occupied")
        }
    return out


def _pts(ci: dict[str, float]) -> str:
    """A difference in percentage points with its interval, and whether it excludes zero."""
    if ci["n"] == 0:
        return "n/a"
    sign = ""
    if ci["n"] >= 2:
        sign = " >0" if ci["lo"] > 0 else (" <0" if ci["hi"] < 0 else " ~0")
    return (
        f"{100 * ci['mean']:+.1f} ({100 * ci['lo']:+.1f} to {100 * ci['hi']:+.1f}){sign}"
        if ci["n"] >= 2
        else f"{100 * ci['mean']:+.1f}"
    )


def differences_table(d: dict[str, Any]) -> str:
    t = d["fused_minus_ray_irm_free_vs_truth_after"]
    lines = [
        "**fused minus ray_irm, free IoU against the truth** (percentage points; paired 95% "
        "bootstrap interval over scenes; >0 / <0: the interval excludes zero, ~0: it does not)",
        "",
        "| after | " + " | ".join(f"{k} s" for k in t) + " |",
        "|" + "---|" * (1 + len(t)),
        "| fused - ray_irm | " + " | ".join(_pts(ci) for ci in t.values()) + " |",
        "",
        "**fused minus each deep map, Table I classes** (percentage points, paired 95% bootstrap "
        "interval over scenes; against ray_ilm, and against the truth for free and occupied)",
        "",
        "| difference | free | occupied | unknown | free vs truth | occupied vs truth |",
        "|---|---|---|---|---|---|",
    ]
    for deep, ci in d["fused_minus_deep_vs_ray_ilm"].items():
        truth = d["fused_minus_deep_vs_truth"][deep]
        cells = [_pts(ci[c]) for c in CLASSES] + [_pts(truth[c]) for c in ("free", "occupied")]
        lines.append(f"| fused - {deep} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def report(per_scene: list[dict], total: int, wall_s: float, header: str) -> tuple[str, dict]:
    summary = summarize(per_scene)
    diffs = differences(per_scene)
    n = len(per_scene)
    text = [
        header,
        f"{n} of {total} scene(s) mapped" + ("" if n == total else " (a partial run)"),
        f"; {wall_s:.0f} s of wall time in this invocation.\n\n",
        markdown_table(
            {k: v for k, v in summary["maps"].items() if k != "ray_ilm"},
            title=f"Table I: {n} scene(s), against ray_ilm; 95% bootstrap interval over scenes",
            intervals=summary.get("maps_interval"),
        ),
        "\n",
        markdown_table(
            summary["vs_truth"],
            title="against the true occupancy (simulator)",
            paper=False,
            intervals=summary.get("vs_truth_interval"),
        ),
        "\n",
        convergence_table(summary["convergence_truth"]),
        "\n",
        differences_table(diffs),
    ]
    return "".join(text), {"summary": summary, "differences": diffs}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/claims"))
    ap.add_argument("--scenes", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--engine", choices=ENGINES, default="local")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a run config field, e.g. mapper.checkpoint=out/train/best.safetensors or "
        "mapper.evidence.mode=per_look (repeatable)",
    )
    a = ap.parse_args(argv)

    source = SimSource.split("val", a.scenes, first_seed=a.first_seed, duration_s=a.duration)
    clash = sorted(set(source.seeds) & used_seeds())
    if clash:
        sys.exit(f"claims_at_scale: seeds {clash} were used for training or the m_u_min sweep")
    overrides = [tuple(item.split("=", 1)) for item in a.set]
    if any(len(o) != 2 for o in overrides):
        sys.exit(f"claims_at_scale: --set takes KEY=VALUE, got {a.set}")
    config = resolve_config(RunConfig, overrides=overrides).mapper
    outputs = replace(OutputConfig(), figures=False, save_maps=False, exports=())
    scenes_dir = a.out / "scenes"
    scenes_dir.mkdir(parents=True, exist_ok=True)
    names = source.names()
    done: dict[str, dict] = {}
    for name in names:
        p = scenes_dir / f"{name}.json"
        if p.exists():
            done[name] = json.loads(p.read_text())
    header = (
        f"`benchmarks/claims_at_scale.py --scenes {a.scenes} --first-seed {a.first_seed} "
        f"--duration {a.duration:g} --workers {a.workers} --engine {a.engine}`: val seeds "
        f"{source.seeds[0]}, {source.seeds[1]}, ..., {source.seeds[-1]}, "
        + (
            f"MapperConfig with {', '.join(a.set)}. "
            if a.set
            else "the shipped checkpoint, the default MapperConfig. "
        )
    )
    todo = [(n, (source, n, config, outputs)) for n in names if n not in done]
    print(f"{len(done)} scene(s) already mapped, {len(todo)} to map", flush=True)
    t0 = time.perf_counter()
    failed = []
    for outcome in fan_out(map_one, todo, engine=a.engine, workers=a.workers):
        if not outcome.ok:
            failed.append(outcome.key)
            print(f"{outcome.key}: {outcome.error}", file=sys.stderr, flush=True)
            continue
        done[outcome.key] = outcome.result
        write_json(scenes_dir / f"{outcome.key}.json", outcome.result)
        per_scene = [done[n] for n in names if n in done]
        text, result = report(per_scene, len(names), time.perf_counter() - t0, header)
        atomic_write_text(a.out / "claims.md", text)
        write_json(a.out / "claims.json", result)
        print(
            f"{outcome.key} done ({len(done)}/{len(names)}, {time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    if done:
        per_scene = [done[n] for n in names if n in done]
        text, result = report(per_scene, len(names), time.perf_counter() - t0, header)
        atomic_write_text(a.out / "claims.md", text)
        write_json(a.out / "claims.json", result)
        print(text)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
