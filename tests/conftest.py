"""Shared fixtures: tiny data sets written on the fly (no network, no shared data needed)."""

from __future__ import annotations

import json
import math
import signal
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

# The Ctrl-C tests need SIGINT to be deliverable, to this process and to the commands it starts
# (which inherit the disposition). A job started with `&` from a non-interactive shell (nohup,
# CI runners) inherits SIGINT *ignored* (POSIX); restore Python's own handler, as an
# interactive terminal would have it.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

SHARED_DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def write_tiny_blender(root: Path, n_train: int = 4, n_test: int = 2, res: int = 16,
                       seed: int = 0) -> Path:
    """A Blender-format set of cameras on a circle looking at the origin; images are a smooth
    colour ramp with an opaque disc in the middle (content is irrelevant to the users)."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    angle_x = 0.6
    yy, xx = np.mgrid[0:res, 0:res] / (res - 1)
    for split, n in (("train", n_train), ("test", n_test)):
        (root / split).mkdir(exist_ok=True)
        frames = []
        for i in range(n):
            a = 2 * math.pi * (i + 0.5 * (split == "test")) / n + rng.uniform(0, 0.1)
            eye = np.array([3 * math.cos(a), 3 * math.sin(a), 0.8])
            fwd = -eye / np.linalg.norm(eye)
            right = np.cross(fwd, [0, 0, 1.0]); right /= np.linalg.norm(right)
            up = np.cross(right, fwd)
            c2w = np.eye(4); c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -fwd, eye
            disc = ((xx - 0.5) ** 2 + (yy - 0.5) ** 2) < 0.1
            rgba = np.stack([xx, yy, np.full_like(xx, 0.3 + 0.1 * i), disc * 1.0], -1)
            iio.imwrite(root / split / f"r_{i}.png", (rgba * 255).round().astype(np.uint8))
            frames.append({"file_path": f"{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": angle_x, "aabb": [[-1, -1, -1], [1, 1, 1]], "frames": frames}))
    return root


def tiny_config(train_iters: int = 4, train_batch: int = 64):
    """The toy preset shrunk for tests: a 4-level field, short schedules, a 32^3 shell grid."""
    from shells.presets import toy_config

    cfg = toy_config()
    cfg.field.n_levels, cfg.field.log2_hashmap_size, cfg.field.max_resolution = 4, 12, 64
    cfg.train.iters, cfg.train.batch_rays = train_iters, train_batch
    cfg.train.n_samples, cfg.train.n_importance = 16, 8
    cfg.shell.resolution = 32
    cfg.finetune.iters, cfg.finetune.batch_rays = 6, 256
    cfg.finetune.checkpoint_every, cfg.finetune.log_every = 3, 1
    return cfg


def trained_run(root: Path, cfg) -> Path:
    """root/data (the tiny data set) and root/run: stage 1 trained with ``cfg``, shells
    extracted."""
    import torch

    from shells.pipeline import extract_run
    from shells.train.stage1 import train

    data = write_tiny_blender(root / "data")
    run = root / "run"
    train(data, run, cfg, torch.device("cpu"), progress=False, evaluate_test=False)
    extract_run(run)
    return run


@pytest.fixture
def tiny_blender(tmp_path: Path) -> Path:
    return write_tiny_blender(tmp_path / "tiny")
