"""`evgrid bench` of several commits, run in turns, so that all see the same machine load.

Run: ``python benchmarks/bench_commits.py 7d0adc3 HEAD [--passes 3] [--out DIR]``. Each commit
is checked out once into a git worktree (``DIR/worktrees``) and benchmarked with this
environment's Python (``PYTHONPATH=<worktree>/src python -m evgrid.cli bench``); the passes go
round the commits in turns. The table gives, per commit, the median over the passes of the
whole map update (``step_total``, ms), fused map alone and all six maps, each pass's figure
beside it. The machine this runs on is shared and its speed varies 1.3-2.4x between days:
comparing a commit with the one whose figures a goal was set on, in the same run, gives the
factor by which the machine is slower today. Extra arguments after ``--`` go to every bench.
Each bench JSON is kept in ``DIR``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from harness import machine_line

_MAPS = {"fused map": "fused_only", "six maps": "six_maps"}


def _worktree(repo: Path, rev: str, root: Path) -> tuple[str, Path]:
    sha = subprocess.run(
        ["git", "-C", str(repo), "rev-parse", "--short", rev],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    path = root / sha
    if not path.exists():
        subprocess.run(
            ["git", "-C", str(repo), "worktree", "add", "--detach", "-q", str(path), sha],
            check=True,
        )
    return sha, path


def _bench(tree: Path, out: Path, extra: list[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree / "src"))
    cmd = [sys.executable, "-m", "evgrid.cli", "bench", "--out", str(out), *extra]
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(
            f"bench of {tree} failed: "
            f"{done.stderr.strip().splitlines()[-1] if done.stderr.strip() else done.returncode}"
        )
    return json.loads(out.read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("revs", nargs="+", help="git revisions (e.g. 7d0adc3 HEAD)")
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("out/bench_commits"))
    args, extra = ap.parse_known_args()
    extra = [a for a in extra if a != "--"]
    repo = Path(__file__).resolve().parents[1]
    args.out.mkdir(parents=True, exist_ok=True)
    trees = [_worktree(repo, rev, (args.out / "worktrees").resolve()) for rev in args.revs]
    totals: dict[str, dict[str, list[float]]] = {sha: {m: [] for m in _MAPS} for sha, _ in trees}
    for k in range(args.passes):
        for sha, tree in trees:
            res = _bench(tree, (args.out / f"{sha}_{k}.json").resolve(), extra)
            for label, key in _MAPS.items():
                totals[sha][label].append(
                    float(res["per_frame"][key]["components_ms"]["step_total"])
                )
            print(
                f"pass {k + 1}/{args.passes} {sha}: "
                + ", ".join(f"{label} {totals[sha][label][-1]:.1f} ms" for label in _MAPS),
                flush=True,
            )
    print(f"\n{machine_line()}")
    print("| commit | " + " | ".join(f"{m}, ms (passes)" for m in _MAPS) + " |")
    print("|---|" + "---|" * len(_MAPS))
    for sha, _ in trees:
        cells = [
            f"{np.median(v):.1f} ({' / '.join(f'{x:.1f}' for x in v)})"
            for v in totals[sha].values()
        ]
        print(f"| {sha} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
