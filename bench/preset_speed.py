"""Shared by the A/B speed benches (run as ``python bench/NAME.py``, so ``bench/`` is on the
import path): stage 1 of the preset ``--preset auto`` picks, for a few steps, in a scratch run."""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import shells.training as training  # noqa: E402


def preset_rays_per_s(data: str, downscale: int, iters: int, caller: str) -> float:
    """Stage-1 rays/s of ``iters`` steps of the auto preset for ``data`` on the CPU (no test
    render; the scratch run is removed). The caller sets up what it compares around the call."""
    cpu = torch.device("cpu")
    cfg, _ = training.preset_config("auto", data, downscale, cpu)
    cfg.update({"train": {"iters": iters}}, caller)
    run = Path(tempfile.mkdtemp(prefix="preset_speed_"))
    try:
        s = training.train(data, run / "run", cfg, cpu, downscale=downscale, progress=False,
                           evaluate_test=False)
    finally:
        shutil.rmtree(run, ignore_errors=True)
    return s["rays_per_s"]
