"""What the command line shows while a run goes: progress per frame and per scene, one line per
finished or failed scene, and tables printed full width when the output is not a terminal."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator, Mapping
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

from evgrid.runs import RunEvents

__all__ = ["ConsoleEvents", "bar", "print_text", "console"]

#: Counts of metrics.json that are not data dropped or skipped.
_NOT_DROPS = ("frames", "updates", "lidar_self_returns_removed", "lidar_self_return_voxels")


def console() -> Console:
    """The console of progress and messages (stderr stays free for errors)."""
    return Console(highlight=False)


def print_text(text: str) -> None:
    """Plain text (a Markdown table) as is: never wrapped at the terminal's or 80 columns."""
    sys.stdout.write(text if text.endswith("\n") else text + "\n")
    sys.stdout.flush()


class _Rate(ProgressColumn):
    def render(self, task: Any) -> Text:
        unit = task.fields.get("unit", "frames")
        return Text(f"{task.speed:.1f} {unit}/s" if task.speed else "")


def _progress(con: Console) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        _Rate(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=con,
    )


@contextlib.contextmanager
def bar(description: str, total: int | None, unit: str = "frames") -> Iterator[Any]:
    """A progress bar; yields ``advance(description=None)``."""
    with _progress(console()) as p:
        task = p.add_task(description, total=total, unit=unit)

        def advance(text: str | None = None) -> None:
            p.update(task, advance=1, **({"description": text} if text else {}))

        yield advance


class ConsoleEvents(RunEvents):
    """A run's events as progress bars (scenes, and the frames of the scene being mapped when
    scenes run in this process) and one line per scene."""

    def __enter__(self) -> ConsoleEvents:
        self.progress = _progress(console())
        self.progress.__enter__()
        self.scenes = None
        self.frames: dict[str, Any] = {}
        return self

    def __exit__(self, *exc: Any) -> None:
        self.progress.__exit__(*exc)

    def say(self, text: str) -> None:
        self.progress.console.print(text, markup=False, soft_wrap=True)

    def start(self, todo: list[str], kept: list[str], dropped: Mapping[str, str]) -> None:
        for name, why in dropped.items():
            self.say(f"  {name}: dropped by the source, {why}")
        if kept:
            self.say(f"resuming: {len(kept)} scene(s) complete for this config, kept: {kept}")
        total = len(todo)
        self.scenes = self.progress.add_task(
            f"mapping {total} scene(s)", total=total, unit="scenes"
        )

    def frame(self, scene: str, done: int, total: int | None) -> None:
        if scene not in self.frames:
            self.frames[scene] = self.progress.add_task(f"  {scene}", total=total)
        self.progress.update(self.frames[scene], completed=done)

    def _end(self, scene: str) -> None:
        if scene in self.frames:
            self.progress.remove_task(self.frames.pop(scene))
        if self.scenes is not None:
            self.progress.advance(self.scenes)

    def scene(self, m: dict[str, Any]) -> None:
        self._end(m["scene"])
        if "frames" not in m:
            self.say(f"  {m['scene']}: done")
            return
        counts = m.get("counts", {})
        dropped = {k: v for k, v in counts.items() if v and k not in _NOT_DROPS}
        extra = f"; dropped or skipped: {dropped}" if dropped else ""
        if counts.get("lidar_self_returns_removed"):
            extra += f"; {counts['lidar_self_returns_removed']} lidar self-returns removed"
        fps = m["frames_per_second"] or 0.0
        self.say(f"  {m['scene']}: {m['frames']} frames, {fps:.1f} frames/s{extra}")

    def failed(self, scene: str, error: str) -> None:
        self._end(scene)
        self.say(f"  {scene}: FAILED: {error}")


@contextlib.contextmanager
def training_events() -> Iterator[dict[str, Any]]:
    """``evgrid train``'s callbacks (``on_cache``, ``on_epoch``, ``on_batch`` of
    :func:`evgrid.train_run.run_training`): a bar over batches, one line per scene cached and
    per epoch."""
    con = console()
    with _progress(con) as p:
        task = p.add_task("epoch 0", total=None, unit="batches")

        def epoch(e: int, row: dict) -> None:
            p.console.print(
                f"epoch {e}: loss {row['train_loss']:.4f}, val IoU free {row['val_free']:.3f} "
                f"occupied {row['val_occupied']:.3f} unknown {row['val_unknown']:.3f} "
                f"(ray IRM free {row['ray_irm_free']:.3f}), {row['seconds']:.0f} s"
            )
            p.reset(task)

        yield {
            "on_cache": lambda split, k, n: p.console.print(f"cached {split} scene {k}/{n}"),
            "on_epoch": epoch,
            "on_batch": lambda e, b, n: p.update(
                task, description=f"epoch {e}", completed=b, total=n
            ),
        }


def map_report(summary: dict[str, Any], out: Any) -> str:
    """What a mapping run prints at its end: the table, the speed, where the results are."""
    table = out / "table.md"
    text = table.read_text() if table.is_file() else ""
    fps = summary.get("frames_per_second") or 0.0
    return f"{text}frames per second (all scenes): {fps:.1f}; results in {out}\n"


def sweep_report(res: dict[str, Any], out: Any) -> str:
    """What ``evgrid sweep-m-u-min`` prints: each value's means, the choice and its rule."""
    lines = [
        f"m_u_min {row['m_u_min']:.2f}: "
        + ", ".join(f"{k} {v:.3f}" for k, v in row["mean_of_classes"].items())
        for row in res["rows"]
    ]
    lines.append(f"chosen m_u_min = {res['chosen']}: {res['rule']}; plot: {out}/m_u_min_sweep.png")
    return "\n".join(lines) + "\n"


def failures(failed: Mapping[str, str], out: Any) -> str | None:
    """The one-line error of a run whose scenes failed (None when none did)."""
    if not failed:
        return None
    listed = "; ".join(f"{k}: {v}" for k, v in failed.items())
    return f"{len(failed)} scene(s) failed ({listed}); the others are in {out}"


def _ious(d: Mapping[str, float] | None) -> str:
    return ", ".join(f"{c} {v:.3f}" for c, v in (d or {}).items()) or "not recorded"


def train_report(res: Any, out: Any) -> str:
    """What ``evgrid train`` prints at its end; after fine-tuning, the parent checkpoint's
    validation IoU on the same scenes beside the new one (and the one it recorded on its own)."""
    text = (
        f"best epoch {res.best_epoch}: {res.best}; ray IRM baseline {res.ray_irm_baseline}; "
        f"{res.seconds_per_epoch:.0f} s per epoch; checkpoint {out / 'best.safetensors'}"
    )
    if getattr(res, "parent_val", None) is None:
        return text
    return (
        f"{text}\nvalidation IoU on these scenes: fine-tuned {_ious(res.best)}; the parent "
        f"before fine-tuning {_ious(res.parent_val)} (on its own validation scenes: "
        f"{_ious(res.parent_recorded_val)})"
    )


def error_line(e: BaseException) -> str:
    """A failure as one line: the exception's own message (a KeyError's unquoted), else its
    type."""
    text = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
    text = " ".join(str(text).split())
    if isinstance(e, (ValueError, OSError, KeyError, RuntimeError, ImportError)):
        return text or type(e).__name__
    return f"{type(e).__name__}: {text}" if text else type(e).__name__
