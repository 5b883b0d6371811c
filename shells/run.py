"""The run directory: where a run keeps its description, config, checkpoints, logs and shells.

Layout::

    RUN/run.json              data set path, downscale, device (written by shells-train)
    RUN/config.json           the full Config used (shells.config)
    RUN/checkpoint.pt         stage-1 checkpoint (atomic): step, field, optimiser, config, aabb
    RUN/train_log.jsonl       stage 1: one JSON record per log step
    RUN/train_summary.json    stage 1 finished: steps, seconds, last record, test PSNR
    RUN/shells/               outer.ply, inner.ply, stats.json, slice.png (shells-extract)
    RUN/finetune.pt           stage-2 checkpoint (shells-finetune), same content as stage 1's
    RUN/finetune_log.jsonl    stage 2 log
    RUN/finetune_summary.json stage 2 finished
    RUN/render-MODE/          images and metrics.json (shells-render)

This is the only module that knows these names. It sits above fields/, levelset/ and render/
(it builds their objects from the files) and below the training stages, the pipeline and the
CLI, which reach the run only through it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from shells.config import Config
from shells.errors import InputError, atomic_write, read_json, write_json
from shells.fields.network import ShellField

STAGES = ("stage1", "stage2")


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
    def shells(self) -> Path:
        return self.root / "shells"

    @property
    def outer(self) -> Path:
        return self.shells / "outer.ply"

    @property
    def inner(self) -> Path:
        return self.shells / "inner.ply"

    def checkpoint(self, stage: str = "stage1") -> Path:
        return self.root / {"stage1": "checkpoint.pt", "stage2": "finetune.pt"}[stage]

    def log(self, stage: str = "stage1") -> Path:
        return self.root / {"stage1": "train_log.jsonl", "stage2": "finetune_log.jsonl"}[stage]

    def summary(self, stage: str = "stage1") -> Path:
        return self.root / {"stage1": "train_summary.json",
                            "stage2": "finetune_summary.json"}[stage]

    def render_dir(self, mode: str) -> Path:
        return self.root / f"render-{mode}"


# ---------------------------------------------------------------------------------------------
# run.json and config.json
# ---------------------------------------------------------------------------------------------

def write_run(run: RunDir, data: str | Path, downscale: int, device: str, cfg: Config) -> None:
    """Create RUN with its description (run.json) and the config it is trained with."""
    run.root.mkdir(parents=True, exist_ok=True)
    write_json(run.run_json, {"data": str(Path(data).resolve()), "downscale": int(downscale),
                              "device": str(device)})
    write_json(run.config, cfg.to_dict())


def read_run(run: RunDir) -> dict[str, Any]:
    """run.json as a dict with at least 'data' and 'downscale'; one-line errors."""
    meta = read_json(run.run_json, "run description (run.json); run shells-train first")
    if not isinstance(meta, dict) or "data" not in meta:
        raise InputError(f"{run.run_json}: missing key 'data'; re-run shells-train")
    meta.setdefault("downscale", 1)
    return meta


# ---------------------------------------------------------------------------------------------
# Checkpoints and fields
# ---------------------------------------------------------------------------------------------

def save_checkpoint(path: Path, field: ShellField, opt: torch.optim.Optimizer, step: int,
                    cfg: Config, extra: dict[str, Any] | None = None) -> None:
    """Field, optimiser, step, config and a stage's extra state (its occupancy grid) in one
    file, written atomically."""
    state = {"step": step, "field": field.state_dict(), "optimizer": opt.state_dict(),
             "config": cfg.to_dict(), "aabb": field.aabb.detach().cpu()}
    if extra is not None:
        state["extra"] = extra
    atomic_write(path, lambda p: torch.save(state, p))


def read_checkpoint(run: RunDir, stage: str = "stage1") -> dict[str, Any]:
    """The checkpoint dict of a stage, on the CPU; one-line errors naming the command to run."""
    path = run.checkpoint(stage)
    if not path.is_file():
        fix = ("run shells-train first (or pass the right RUN)" if stage == "stage1" else
               f"run shells-finetune {run.root} first (or render --stage stage1)")
        raise InputError(f"{path}: no {stage} checkpoint; {fix}")
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # corrupt or foreign file
        raise InputError(f"{path}: unreadable checkpoint ({type(exc).__name__}); retrain")


def resolve_stage(run: RunDir, stage: str) -> str:
    """'stage1', 'stage2' or 'latest' -> the stage whose checkpoint is used (stage 2 when the
    run has one)."""
    if stage == "latest":
        return "stage2" if run.checkpoint("stage2").is_file() else "stage1"
    if stage not in STAGES:
        raise InputError(f"stage '{stage}': expected latest, stage1 or stage2")
    return stage


def field_from_checkpoint(ckpt: dict[str, Any], source: str,
                          device: str | torch.device = "cpu") -> tuple[ShellField, Config]:
    """The field (eval mode) and config stored in a checkpoint dict."""
    cfg = Config.from_dict(ckpt["config"], source)
    field = ShellField(cfg.field, ckpt["aabb"]).to(device)
    field.load_state_dict(ckpt["field"])
    field.eval()
    return field, cfg


def load_field(run_dir: str | Path, device: str | torch.device = "cpu",
               stage: str = "latest") -> tuple[ShellField, Config]:
    """The trained field of a run: stage 'stage1', 'stage2' or 'latest' (stage 2 if present)."""
    run = RunDir(run_dir)
    stage = resolve_stage(run, stage)
    return field_from_checkpoint(read_checkpoint(run, stage), str(run.checkpoint(stage)), device)


# ---------------------------------------------------------------------------------------------
# Shells
# ---------------------------------------------------------------------------------------------

def load_shells(run: RunDir, variant: str | None = None) -> Any:
    """A `shells.render.raycast.ShellScene` from RUN/shells (Mitsuba ``variant``); a missing or
    empty inner.ply means no interior termination."""
    from shells.levelset.mesh import load_ply
    from shells.render.raycast import ShellScene  # Mitsuba: only for the commands that cast

    if not run.outer.is_file():
        raise InputError(f"{run.outer}: no outer shell; run shells-extract {run.root} first")
    outer = load_ply(run.outer)
    if len(outer[1]) == 0:
        raise InputError(f"{run.outer}: the outer shell is empty; re-run shells-extract")
    inner = load_ply(run.inner) if run.inner.is_file() else None
    return ShellScene(outer, inner, variant)


# ---------------------------------------------------------------------------------------------
# JSON-lines logs
# ---------------------------------------------------------------------------------------------

def append_log(path: Path, record: dict[str, Any]) -> None:
    """Add one JSON record as a line."""
    with open(path, "a") as fh:
        fh.write(json.dumps(record) + "\n")


def truncate_log(path: Path, step: int) -> None:
    """Drop log records past ``step`` (a resumed run redoes them)."""
    if not path.is_file():
        return
    keep = [ln for ln in path.read_text().splitlines()
            if ln.strip() and json.loads(ln).get("step", 0) <= step]
    atomic_write(path, lambda p: p.write_text("".join(k + "\n" for k in keep)))


def read_log(path: Path) -> list[dict[str, Any]]:
    """All records of a JSON-lines log ([] when there is none)."""
    if not path.is_file():
        return []
    return [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]
