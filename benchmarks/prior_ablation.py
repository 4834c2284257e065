"""Each change to Ev-Net measured on the same paired scenes (issue 38: targets, inputs, loss, net).

Trains one Ev-Net per variant (``evgrid train`` with the variant's ``--set`` overrides, the same
scenes, seed and epochs for all), maps the same simulated evaluation scenes with each through
``benchmarks/claims_at_scale.py`` (``mapper.evidence.mode=per_look``, the paper's evidence, so
that ``ray_irm`` is the paper's while the car stands), and prints per variant the free IoU
against the truth after 1 s of every deep map, ``ray_irm`` and ``fused``, ``fused - ray_irm``
after 1 and 2 s and fused's occupied IoU, then each variant minus the one before it (the
contribution of that change), paired over scenes with a 95 % bootstrap interval. The variant
``shipped`` maps with the shipped checkpoint and trains nothing.

Evaluation seeds default to the val split from 2000 (claims_at_scale's goal scenes start at 1000;
seeds from 3000 up are reserved for checks the issue's authors run: never evaluate choices on
them). Variants run ``--jobs`` at a time; each trains with its own cache.

    PYTHONPATH=src python benchmarks/prior_ablation.py --out out/ablation --jobs 2 \\
        --variant shipped \\
        --variant "paper:train.target.kind=single_frame;train.loss=paper" \\
        --variant "targets:train.loss=paper" \\
        --variant "inputs:train.image.n_sweeps=20;train.image.horizon_s=2;\\
mapper.image.n_sweeps=20;mapper.image.horizon_s=2"

A ``mapper.*`` setting of a variant maps its evaluation scenes (the radar image's sweeps and
horizon come from the mapping config, and must match the training's ``train.image.*``).

Prints and writes ``OUT/ablation.md`` and ``OUT/ablation.json``; asserts nothing. Run again
with the same ``--out``: finished trainings and mapped scenes are kept.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from evgrid.evaluate import bootstrap_interval

HERE = Path(__file__).resolve().parent
MAPS = ("deep_acc", "deep_replace", "deep_disc", "ray_irm", "fused")


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``NAME`` or ``NAME:KEY=VALUE;KEY=VALUE`` -> (name, overrides)."""
    name, _, sets = text.partition(":")
    overrides = [s.strip() for s in sets.split(";") if s.strip()]
    bad = [s for s in overrides if "=" not in s]
    if not name or bad:
        sys.exit(f"prior_ablation: --variant takes NAME[:KEY=VALUE;...], got {text!r}")
    return name, overrides


def run_logged(cmd: list[str], log: Path) -> None:
    with open(log, "a") as f:
        f.write("$ " + " ".join(cmd) + "\n")
        f.flush()
        rc = subprocess.call(cmd, stdout=f, stderr=subprocess.STDOUT)
    if rc:
        raise RuntimeError(f"{cmd[1:3]} exited {rc}; see {log}")


def one_variant(name: str, overrides: list[str], a: argparse.Namespace) -> dict:
    """Train (unless ``shipped``) and map the evaluation scenes; returns timings."""
    out = a.out / name
    out.mkdir(parents=True, exist_ok=True)
    log = out / "log.txt"
    timing: dict[str, float] = {}
    # mapper.* settings map the evaluation scenes (an input that the mapping config decides,
    # such as mapper.image.n_sweeps, must match the training's train.image.*); the rest train
    mapper_sets = ["mapper.evidence.mode=per_look"]
    mapper_sets += [s for s in overrides if s.startswith("mapper.")]
    overrides = [s for s in overrides if not s.startswith("mapper.")]
    if name != "shipped":
        ckpt = out / "train" / "best.safetensors"
        if not ckpt.exists():
            t0 = time.perf_counter()
            cmd = [sys.executable, "-m", "evgrid.cli", "train", "--out", str(out / "train")]
            cmd += ["--scenes", str(a.scenes), "--val-scenes", str(a.val_scenes)]
            cmd += ["--epochs", str(a.epochs), "--duration", f"{a.duration:g}", "--seed", "0"]
            cmd += ["--workers", str(a.loader_workers), "--cache-workers", str(a.cache_workers)]
            cmd += ["--batch-size", str(a.batch_size)]
            for s in overrides:
                cmd += ["--set", s]
            run_logged(cmd, log)
            timing["train_s"] = time.perf_counter() - t0
        mapper_sets.append(f"mapper.checkpoint={ckpt}")
    t0 = time.perf_counter()
    cmd = [sys.executable, str(HERE / "claims_at_scale.py"), "--out", str(out / "claims")]
    cmd += ["--scenes", str(a.eval_scenes), "--first-seed", str(a.eval_first_seed)]
    cmd += ["--duration", f"{a.eval_duration:g}", "--workers", str(a.eval_workers)]
    for s in mapper_sets:
        cmd += ["--set", s]
    run_logged(cmd, log)
    timing["map_s"] = time.perf_counter() - t0
    return timing


def per_scene(out: Path) -> dict[str, dict]:
    return {
        p.stem: json.loads(p.read_text()) for p in sorted((out / "claims/scenes").glob("*.json"))
    }


def free_at(m: dict, name: str, i: int) -> float:
    return m["convergence_truth"]["maps"][name]["free"][i]


def occ_at(m: dict, name: str, i: int) -> float:
    return m["convergence_truth"]["maps"][name]["occupied"][i]


def pts(ci: dict) -> str:
    if not ci.get("n"):
        return "n/a"
    return f"{100 * ci['mean']:+.1f} ({100 * ci['lo']:+.1f} to {100 * ci['hi']:+.1f})"


def summarize(names: list[str], a: argparse.Namespace) -> tuple[str, dict]:
    scenes = {n: per_scene(a.out / n) for n in names}
    common = sorted(set.intersection(*(set(s) for s in scenes.values()))) if scenes else []
    result: dict = {"scenes": len(common), "variants": {}}
    head = "| variant | " + " | ".join(f"`{m}` free 1 s" for m in MAPS)
    head += " | fused - ray_irm 1 s | fused - ray_irm 2 s | `fused` occ. 1 s | deep occ. 1 s"
    head += " | vs the one before: fused free 1 s | deep_acc free 1 s |"
    lines = [head, "|" + "---|" * (len(MAPS) + 7)]
    prev = None
    for n in names:
        ms = [scenes[n][s] for s in common]
        row: dict = {m: bootstrap_interval([free_at(x, m, 0) for x in ms]) for m in MAPS}
        row["fused_minus_ray_irm_1s"] = bootstrap_interval(
            [free_at(x, "fused", 0) - free_at(x, "ray_irm", 0) for x in ms]
        )
        row["fused_minus_ray_irm_2s"] = bootstrap_interval(
            [free_at(x, "fused", 1) - free_at(x, "ray_irm", 1) for x in ms]
        )
        row["fused_occupied_1s"] = bootstrap_interval([occ_at(x, "fused", 0) for x in ms])
        for m in MAPS[:3]:
            row[f"{m}_occupied_1s"] = bootstrap_interval([occ_at(x, m, 0) for x in ms])
        if prev is not None:
            ps = [scenes[prev][s] for s in common]
            row["step_fused_1s"] = bootstrap_interval(
                [free_at(x, "fused", 0) - free_at(y, "fused", 0) for x, y in zip(ms, ps)]
            )
            row["step_deep_acc_1s"] = bootstrap_interval(
                [free_at(x, "deep_acc", 0) - free_at(y, "deep_acc", 0) for x, y in zip(ms, ps)]
            )
        result["variants"][n] = row
        cells = [f"{100 * row[m]['mean']:.1f}" for m in MAPS]
        cells += [pts(row["fused_minus_ray_irm_1s"]), pts(row["fused_minus_ray_irm_2s"])]
        cells += [f"{100 * row['fused_occupied_1s']['mean']:.1f}"]
        cells += ["/".join(f"{100 * row[f'{m}_occupied_1s']['mean']:.1f}" for m in MAPS[:3])]
        cells += [pts(row.get("step_fused_1s", {})), pts(row.get("step_deep_acc_1s", {}))]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
        prev = n
    return "\n".join(lines) + "\n", result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/ablation"))
    ap.add_argument("--variant", action="append", required=True, help="NAME[:KEY=VALUE;...]")
    ap.add_argument("--scenes", type=int, default=12, help="training scenes")
    ap.add_argument("--val-scenes", type=int, default=3)
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--duration", type=float, default=20.0, help="seconds a training scene")
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--loader-workers", type=int, default=1)
    ap.add_argument("--cache-workers", type=int, default=1)
    ap.add_argument("--eval-scenes", type=int, default=12)
    ap.add_argument("--eval-first-seed", type=int, default=2000)
    ap.add_argument("--eval-duration", type=float, default=20.0)
    ap.add_argument("--eval-workers", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=1, help="variants at once")
    ap.add_argument(
        "--report-only", action="store_true", help="train and map nothing: report what is there"
    )
    a = ap.parse_args(argv)
    if a.eval_first_seed + 5 * a.eval_scenes > 3000:
        sys.exit(
            "prior_ablation: evaluation seeds from 3000 up are reserved; lower --eval-first-seed"
        )
    variants = [parse_variant(v) for v in a.variant]
    a.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    timings: dict[str, dict] = {}
    with ThreadPoolExecutor(max_workers=a.jobs) as pool:
        futures = (
            {} if a.report_only else {n: pool.submit(one_variant, n, o, a) for n, o in variants}
        )
        for n, f in futures.items():
            try:
                timings[n] = f.result()
                print(f"{n}: {timings[n]}", flush=True)
            except RuntimeError as e:
                print(f"{n}: failed: {e}", flush=True)
    have = [n for n, _ in variants if per_scene(a.out / n)]
    names = have if a.report_only else [n for n, _ in variants if n in timings]
    text, result = summarize(names, a)
    result["timings_s"] = timings
    result["variants_sets"] = dict(variants)
    header = (
        f"{result['scenes']} paired scenes (val seeds from {a.eval_first_seed}, "
        f"{a.eval_duration:g} s, evidence per look); training: {a.scenes} scenes of "
        f"{a.duration:g} s, {a.epochs} epochs; {time.perf_counter() - t0:.0f} s in all. "
        "Free/occupied IoU against the truth in %, differences in points (95 % paired "
        "bootstrap interval).\n\n"
    )
    print(header + text)
    (a.out / "ablation.md").write_text(header + text)
    (a.out / "ablation.json").write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
