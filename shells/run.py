"""The run directory: where a run keeps its config, checkpoints, logs, shells and renders.

Layout::

    RUN/run.json            data set path, downscale, device, preset (written by shells-train)
    RUN/config.json         the full Config used (shells.config)
    RUN/checkpoint.pt       stage-1 checkpoint (atomic): step, field state, optimiser, RNG
    RUN/train_log.jsonl     one JSON record per log step
    RUN/shells/             outer.ply, inner.ply, stats.json, slice.png (shells-extract)
    RUN/finetune.pt         stage-2 checkpoint (shells-finetune)
    RUN/render-MODE/        images and metrics.json (shells-render)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class RunDir:
    root: Path

    def __init__(self, root: str | Path) -> None:
        object.__setattr__(self, "root", Path(root))

    @property
    def run_json(self) -> Path:
        return self.root / "run.json"

    @property
    def config(self) -> Path:
        return self.root / "config.json"

    @property
    def checkpoint(self) -> Path:
        return self.root / "checkpoint.pt"

    @property
    def finetune_checkpoint(self) -> Path:
        return self.root / "finetune.pt"

    @property
    def train_log(self) -> Path:
        return self.root / "train_log.jsonl"

    @property
    def finetune_log(self) -> Path:
        return self.root / "finetune_log.jsonl"

    @property
    def shells(self) -> Path:
        return self.root / "shells"

    @property
    def outer(self) -> Path:
        return self.shells / "outer.ply"

    @property
    def inner(self) -> Path:
        return self.shells / "inner.ply"

    def render_dir(self, mode: str) -> Path:
        return self.root / f"render-{mode}"
