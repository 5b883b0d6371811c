"""The run directory: where a run keeps its description, config, checkpoints, logs and shells.

Layout::

    RUN/run.json              data set path, downscale, device (written by shells-train)
    RUN/config.json           the full Config used (shells.config)
    RUN/checkpoint.pt         stage-1 checkpoint (atomic): step, field, optimiser, config, aabb
    RUN/train_log.jsonl       stage 1: one JSON record per log step
    RUN/train_curve.jsonl     stage 1: the running test curve (`RunDir.curve`)
    RUN/train_summary.json    stage 1 finished: steps, seconds, last record, test PSNR
    RUN/shells/               outer.ply, inner.ply, stats.json, slice.png (shells-extract)
    RUN/shells/lod/           outer.ply, inner.ply, stats.json: coarse shells that contain the
                              fine ones (shells-lod); `load_shells(..., which="lod")`
    RUN/finetune.pt           stage-2 checkpoint (shells-finetune), same content as stage 1's
    RUN/finetune_log.jsonl    stage 2 log
    RUN/finetune_summary.json stage 2 finished
    RUN/render-MODE/          images and metrics.json (shells-render)
    RUN/cage/                 cage.npz, cage.vtu, cage.json: the tetrahedral cage (shells-cage);
                              RUN/cage/lod/ the same for the LOD shells (--shells lod)
    RUN/animate-MOTION/       frames, video.mp4, motion.npz, metrics.json (shells-animate)
    RUN/.lock                 held by the command writing the run (`shells.files.lock`): pid,
                              host, command

Versions and identity: run.json holds ``format`` (`FORMAT_VERSION`, the layout of the run
directory and its files) and ``run_id`` (random, made by shells-train); checkpoints hold both
too, and shells/stats.json holds the run id and the stage-1 step the shells were extracted
from. A run of another format, a checkpoint whose tensors do not fit its architecture, a
checkpoint of another run, or shells of another run (or of an older stage-1 checkpoint) are
refused with a one-line InputError saying what to re-run. Runs written before the version
existed have no ``format``: they are version 1, today's layout, and are read as before (and
without the identity checks, as they carry no ids).

This is the only module that knows these names. It sits above fields/, levelset/ and render/
(it builds their objects from the files) and below the training stages, the pipeline and the
CLI, which reach the run only through it.
"""

from __future__ import annotations

import hashlib
import json
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from shells.config import Config
from shells.errors import InputError
from shells.files import atomic_write, read_json, write_json
from shells.fields.network import ShellField

STAGES = ("stage1", "stage2")
SHELL_KINDS = ("fine", "lod")  # RUN/shells and RUN/shells/lod
FORMAT_VERSION = 1  # the run directory's layout; a missing "format" key means 1


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

    @property
    def lod(self) -> Path:
        return self.shells / "lod"

    def shell_files(self, which: str = "fine") -> tuple[Path, Path]:
        """(outer.ply, inner.ply) of the fine shells or of their LOD (RUN/shells/lod)."""
        if which not in SHELL_KINDS:
            raise InputError(f"--shells {which}: expected one of {SHELL_KINDS}")
        base = self.shells if which == "fine" else self.lod
        return base / "outer.ply", base / "inner.ply"

    def checkpoint(self, stage: str = "stage1") -> Path:
        return self.root / {"stage1": "checkpoint.pt", "stage2": "finetune.pt"}[stage]

    def log(self, stage: str = "stage1") -> Path:
        return self.root / {"stage1": "train_log.jsonl", "stage2": "finetune_log.jsonl"}[stage]

    @property
    def curve(self) -> Path:
        """Stage 1's running test curve (JSON lines: step, wall_s, psnr)."""
        return self.root / "train_curve.jsonl"

    def summary(self, stage: str = "stage1") -> Path:
        return self.root / {"stage1": "train_summary.json",
                            "stage2": "finetune_summary.json"}[stage]

    def render_dir(self, mode: str) -> Path:
        return self.root / f"render-{mode}"

    @property
    def cage(self) -> Path:
        return self.root / "cage"

    @property
    def baked(self) -> Path:
        """RUN/baked: the baked layer meshes (shells-bake)."""
        return self.root / "baked"

    def cage_dir(self, which: str = "fine") -> Path:
        """RUN/cage: the cage of the fine shells; RUN/cage/lod: that of the LOD shells."""
        self.shell_files(which)  # checks the name
        return self.cage if which == "fine" else self.cage / "lod"

    def animate_dir(self, motion: str) -> Path:
        return self.root / f"animate-{motion}"

    @property
    def lock(self) -> Path:
        return self.root / ".lock"


# ---------------------------------------------------------------------------------------------
# run.json and config.json
# ---------------------------------------------------------------------------------------------

def write_run(run: RunDir, data: str | Path, downscale: int, device: str, cfg: Config) -> None:
    """Create RUN with its description (run.json: format version, a new run id) and the config
    it is trained with."""
    run.root.mkdir(parents=True, exist_ok=True)
    write_json(run.run_json, {"format": FORMAT_VERSION, "run_id": uuid.uuid4().hex,
                              "data": str(Path(data).resolve()), "downscale": int(downscale),
                              "device": str(device)})
    write_json(run.config, cfg.to_dict())


def _check_format(version: Any, path: Path) -> None:
    if version != FORMAT_VERSION:
        import shells

        raise InputError(f"{path}: written in run format {version!r}, but shells "
                         f"{shells.__version__} "
                         f"reads format {FORMAT_VERSION}; re-train the run with this version "
                         "(shells-train --out NEW_RUN) or use the shells version that wrote it")


def read_run(run: RunDir) -> dict[str, Any]:
    """run.json as a dict with at least 'data', 'downscale' and 'format' (1 when absent: runs
    written before the version existed); one-line errors."""
    meta = read_json(run.run_json, "run description (run.json); run shells-train first")
    if not isinstance(meta, dict) or "data" not in meta:
        raise InputError(f"{run.run_json}: missing key 'data'; re-run shells-train")
    meta.setdefault("format", 1)
    _check_format(meta["format"], run.run_json)
    meta.setdefault("downscale", 1)
    return meta


def require_bounded(run: RunDir, command: str, why: str) -> None:
    """A one-line error when RUN is an unbounded scene (field.unbounded in its config) and
    ``command`` works on bounded objects only (``why`` says what it needs)."""
    if not run.config.is_file():
        return
    cfg = read_json(run.config)
    if isinstance(cfg, dict) and (cfg.get("field") or {}).get("unbounded", False):
        raise InputError(f"{run.root}: an unbounded scene (trained with --scene unbounded); "
                         f"{command} {why}, so it takes bounded runs only")


def run_id(run: RunDir) -> str | None:
    """The run's id from run.json (None for runs written before ids existed, or none yet)."""
    return read_run(run).get("run_id") if run.run_json.is_file() else None


# ---------------------------------------------------------------------------------------------
# Checkpoints and fields
# ---------------------------------------------------------------------------------------------

def save_checkpoint(path: Path, field: ShellField, opt: torch.optim.Optimizer, step: int,
                    cfg: Config, extra: dict[str, Any] | None = None,
                    wall_s: float | None = None) -> None:
    """Field, optimiser, step, config and a stage's extra state (its occupancy grid) in one
    file, written atomically, with the format version and the id of the run it is in (RUN =
    the file's folder); ``wall_s``: the stage's wall time so far, over all its sittings."""
    state = {"format": FORMAT_VERSION, "run_id": run_id(RunDir(Path(path).parent)),
             "step": step, "field": field.state_dict(), "optimizer": opt.state_dict(),
             "config": cfg.to_dict(), "aabb": field.aabb.detach().cpu()}
    if wall_s is not None:
        state["wall_s"] = wall_s
    if extra is not None:
        state["extra"] = extra
    def write(p: Path) -> None:
        try:
            torch.save(state, p)
        except RuntimeError as exc:  # torch's writer reports a full disk this way
            if "write" not in str(exc) and "unexpected pos" not in str(exc):
                raise
            why = (str(exc).splitlines() or [""])[0][:100]
            raise InputError(f"{path}: writing the checkpoint failed ({why}); is the disk full? "
                             "Free space and continue with --resume (the previous checkpoint "
                             "is intact)") from None

    atomic_write(path, write)


def checkpoint_config(ckpt: dict[str, Any], source: str) -> Config:
    """The config a checkpoint stores; one line saying to re-train when this version cannot
    read it (a key it does not know: another shells version)."""
    try:
        return Config.from_dict(ckpt["config"], source)
    except InputError as exc:
        raise InputError(f"{exc}; the checkpoint is of another shells version or architecture: "
                         "re-train the run (shells-train)") from None


def load_field_state(field: ShellField, state: dict[str, Any], source: str) -> None:
    """``field.load_state_dict(state)``; tensors of another architecture (other names or
    shapes) are a one-line InputError instead of torch's report."""
    try:
        field.load_state_dict(state)
    except RuntimeError as exc:
        why = " ".join(str(exc).split("\n", 2)[1:2]).strip().rstrip(".")[:160]
        raise InputError(f"{source}: the field's tensors do not fit the architecture of its "
                         f"config ({why}); the checkpoint is of another architecture or version:"
                         " re-train the run (shells-train)") from None


def read_checkpoint(run: RunDir, stage: str = "stage1") -> dict[str, Any]:
    """The checkpoint dict of a stage, on the CPU; one-line errors naming the command to run."""
    path = run.checkpoint(stage)
    if not path.is_file():
        fix = ("run shells-train first (or pass the right RUN)" if stage == "stage1" else
               f"run shells-finetune {run.root} first (or render --stage stage1)")
        raise InputError(f"{path}: no {stage} checkpoint; {fix}")
    meta = read_run(run) if run.run_json.is_file() else {}
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # corrupt or foreign file
        raise InputError(f"{path}: unreadable checkpoint ({type(exc).__name__}); retrain")
    if not isinstance(ckpt, dict) or not {"step", "field", "config", "aabb"} <= set(ckpt):
        raise InputError(f"{path}: not a shells checkpoint (no step / field / config); retrain")
    _check_format(ckpt.get("format", 1), path)
    if ckpt.get("run_id") and meta.get("run_id") and ckpt["run_id"] != meta["run_id"]:
        raise InputError(f"{path}: the checkpoint belongs to another run (id {ckpt['run_id'][:8]}"
                         f", this run is {meta['run_id'][:8]}); copy whole run folders, or "
                         "re-train this one")
    return ckpt


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
    cfg = checkpoint_config(ckpt, source)
    field = ShellField(cfg.field, ckpt["aabb"]).to(device)
    load_field_state(field, ckpt["field"], source)
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

def shell_meshes(run: RunDir, which: str = "fine"
                 ) -> tuple[tuple[Any, Any], tuple[Any, Any] | None]:
    """The (V, F) arrays of RUN/shells (``which`` 'fine') or RUN/shells/lod ('lod',
    shells-lod): (outer, inner), inner None when there is no inner.ply. Shells of another run or
    an older checkpoint, and LOD shells made from other fine shells, are refused."""
    from shells.levelset.mesh import load_ply

    outer_path, inner_path = run.shell_files(which)
    if not run.outer.is_file():
        raise InputError(f"{run.outer}: no outer shell; run shells-extract {run.root} first")
    check_shells(run)
    if which == "lod":
        check_lod(run)
    return load_ply(outer_path), (load_ply(inner_path) if inner_path.is_file() else None)


def load_shells(run: RunDir, variant: str | None = None, which: str = "fine") -> Any:
    """A `shells.render.raycast.ShellScene` from RUN/shells (``which`` 'fine') or RUN/shells/lod
    ('lod', shells-lod) (Mitsuba ``variant``); a missing or empty inner.ply means no interior
    termination. LOD shells made from other fine shells than RUN/shells are refused."""
    from shells.render.raycast import ShellScene  # Mitsuba: only for the commands that cast

    outer, inner = shell_meshes(run, which)
    if len(outer[1]) == 0:
        raise InputError(f"{run.shell_files(which)[0]}: the outer shell is empty; re-run "
                         "shells-extract")
    return ShellScene(outer, inner, variant)


def check_lod(run: RunDir) -> None:
    """RUN/shells/lod must exist and be made from the current RUN/shells (its stats.json keeps
    their digest)."""
    stats = run.lod / "stats.json"
    if not (run.lod / "outer.ply").is_file() or not stats.is_file():
        raise InputError(f"{run.lod}: no LOD shells; run shells-lod {run.root} first")
    made_from = read_json(stats, "LOD statistics").get("shells_sha1")
    if made_from is not None and made_from != shells_digest(run):
        raise InputError(f"{run.lod}: made from other shells than {run.shells}; run shells-lod "
                         f"{run.root} again")


def shells_source(run: RunDir, step: int) -> dict[str, Any]:
    """What shells/stats.json records of where its shells come from (`check_shells`)."""
    return {"run_id": run_id(run), "stage1_step": int(step)}


def check_shells(run: RunDir) -> None:
    """Refuse shells extracted in another run or from an older stage-1 checkpoint (their
    stats.json says where they come from; shells without that record are accepted)."""
    stats_path = run.shells / "stats.json"
    if not stats_path.is_file():
        return
    src = read_json(stats_path, "shell statistics").get("source") or {}
    fix = f"re-extract them with shells-extract {run.root}"
    mine = run_id(run)
    if src.get("run_id") and mine and src["run_id"] != mine:
        raise InputError(f"{run.shells}: the shells were extracted in another run (id "
                         f"{src['run_id'][:8]}, this run is {mine[:8]}); {fix}")
    if src.get("stage1_step") is not None and run.checkpoint("stage1").is_file():
        step = _step(run)
        if step is not None and step != src["stage1_step"]:
            raise InputError(f"{run.shells}: the shells were extracted from step "
                             f"{src['stage1_step']} of {run.checkpoint('stage1').name}, which "
                             f"is now at step {step}; {fix}")


def shells_digest(run: RunDir, which: str = "fine") -> str:
    """A content hash of the shells' outer.ply and inner.ply (RUN/shells, or RUN/shells/lod for
    ``which`` 'lod'): what a cage or a LOD was built from."""
    h = hashlib.sha1()
    for p in run.shell_files(which):
        h.update(p.read_bytes() if p.is_file() else b"")
    return h.hexdigest()


def load_cage(run: RunDir, which: str = "fine"
              ) -> tuple[Any, dict[str, Any], tuple[Any, Any], tuple[Any, Any]]:
    """The cage of RUN/cage (shells-cage; RUN/cage/lod for the LOD shells) with the shells it
    embeds: (Cage, embedding, outer (V, F), inner (V, F)). A cage built from other shells than
    the current ones is refused."""
    from shells.levelset.cage import read_cage

    outer, inner = shell_meshes(run, which)
    if inner is None:
        inner = (outer[0][:0], outer[1][:0])
    folder = run.cage_dir(which)
    fix = f"run shells-cage {run.root}{' --shells lod' if which == 'lod' else ''} again"
    cage, emb = read_cage(folder / "cage.npz")
    meta = folder / "cage.json"
    built_from = read_json(meta, "cage statistics").get("shells_sha1") if meta.is_file() else None
    if built_from is not None and built_from != shells_digest(run, which):
        raise InputError(f"{folder}: the cage was built from other shells than the current "
                         f"{which} shells; {fix}")
    if len(emb["outer_tet"]) != len(outer[0]) or len(emb["inner_tet"]) != len(inner[0]):
        raise InputError(f"{folder / 'cage.npz'}: its shell embedding does not match the "
                         f"{which} shells; {fix}")
    return cage, emb, outer, inner


def _step(run: RunDir) -> int | None:
    """The step of the stage-1 checkpoint (memory-mapped: the tensors are not read)."""
    try:
        return int(torch.load(run.checkpoint("stage1"), map_location="cpu", mmap=True,
                              weights_only=False)["step"])
    except Exception:  # noqa: BLE001 - unreadable: read_checkpoint reports it where it matters
        return None


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
