"""Data-parallel stages under torchrun (gloo on the CPU, 2 processes): the same parameters as one
process on the same rays, a killed rank, resume with another number of processes.

Each test launches ``python -m torch.distributed.run`` (torchrun) on the console scripts, as a
user would; a launch costs a few seconds (two interpreters importing torch and Mitsuba).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from shells.run import RunDir, read_log
from tests.conftest import tiny_config, write_tiny_blender

BIN = Path(sys.executable).parent


def _script(name: str) -> str:
    path = BIN / name
    found = path if path.is_file() else shutil.which(name)
    assert found, f"console script {name} not installed (pip install -e .)"
    return str(found)


def _env() -> dict[str, str]:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(k, None)
    return env


def launch(nproc: int, command: str, *args: str, wait: bool = True):
    """torchrun --standalone --nproc-per-node nproc COMMAND ARGS (nproc 0: no torchrun)."""
    argv = [_script(command), *map(str, args)]
    if nproc:
        argv = [sys.executable, "-m", "torch.distributed.run", "--standalone",
                f"--nproc-per-node={nproc}", *argv]
    if not wait:
        return subprocess.Popen(argv, env=_env(), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
    return subprocess.run(argv, env=_env(), capture_output=True, text=True, timeout=300)


def _params(run: Path, stage: str = "stage1") -> dict[str, torch.Tensor]:
    return torch.load(RunDir(run).checkpoint(stage), map_location="cpu",
                      weights_only=False)["field"]


def max_relative_difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    """max over tensors of |a - b| / |a| (Frobenius norms)."""
    worst = 0.0
    for k in a:
        x, y = a[k].double(), b[k].double()
        if x.numel():
            worst = max(worst, float((x - y).norm() / x.norm().clamp_min(1e-30)))
    return worst


def _config_file(path: Path, iters: int, shards: int, ft_shards: int | None = None,
                 **train) -> Path:
    cfg = tiny_config(train_iters=iters, train_batch=64).to_dict()
    # the torch lookups: a torchrun rank and one process then sum the same gradients in the
    # same order (one process would add into the compiled path's persistent gradient, in
    # another order, and Adam's eps of 1e-15 turns rounding in near-zero gradients into
    # whole steps)
    cfg["train"].update(shards=shards, log_every=1, hashgrid="torch", **train)
    cfg["finetune"].update(shards=shards if ft_shards is None else ft_shards, iters=4,
                           batch_rays=128, log_every=1, hashgrid="torch")
    path.write_text(json.dumps({k: cfg[k] for k in ("field", "train", "shell", "finetune")}))
    return path


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_tiny_blender(tmp_path_factory.mktemp("ddp") / "data")


def test_two_ranks_give_the_parameters_of_one_process(data, tmp_path):
    """20 steps of 2 ranks x B/2 rays == 20 steps of 1 process x B on the same rays (the two
    shards of every step), stage 1 and then stage 2."""
    cfg = _config_file(tmp_path / "cfg.json", iters=20, shards=2)
    one, two = tmp_path / "one", tmp_path / "two"
    r1 = launch(0, "shells-train", "--data", data, "--out", one, "--config", cfg)
    r2 = launch(2, "shells-train", "--data", data, "--out", two, "--config", cfg)
    assert r1.returncode == 0, r1.stderr[-2000:]
    assert r2.returncode == 0, r2.stderr[-2000:]
    assert max_relative_difference(_params(one), _params(two)) <= 1e-5
    # rank 0 alone wrote the log (one record per step) and printed the result
    assert [r["step"] for r in read_log(RunDir(two).log())] == list(range(1, 21))
    assert r2.stdout.count("test PSNR") == 1
    # stage 2 on the same shells, 4 steps
    for run in (one, two):
        assert launch(0, "shells-extract", run).returncode == 0
    for name in ("outer.ply", "inner.ply"):  # the same meshes (stats.json names its own run)
        shutil.copy(one / "shells" / name, two / "shells" / name)
    f1 = launch(0, "shells-finetune", one, "--device", "cpu")
    f2 = launch(2, "shells-finetune", two, "--device", "cpu")
    assert f1.returncode == 0 and f2.returncode == 0, f2.stderr[-2000:]
    assert max_relative_difference(_params(one, "stage2"), _params(two, "stage2")) <= 1e-5
    # three shards cannot be shared by two processes: one line, exit 2, nothing written
    bad = _config_file(tmp_path / "bad.json", iters=4, shards=3, ft_shards=1, batch_rays=63)
    r3 = launch(2, "shells-train", "--data", data, "--out", tmp_path / "three", "--config", bad)
    assert r3.returncode != 0 and "cannot be shared by 2 processes" in r3.stderr
    assert r3.stderr.count("shells-train: error: stage 1: 3 ray shards per step") == 2
    assert not (tmp_path / "three").exists()


def _rank_pid(parent: int, rank: int) -> int | None:
    """The pid of the torchrun worker with RANK=rank below ``parent``."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            env = (entry / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == parent and f"RANK={rank}".encode() in env:
            return int(entry.name)
    return None


def test_killed_rank_stops_the_run_and_resume_continues_it(data, tmp_path):
    cfg = _config_file(tmp_path / "cfg.json", iters=120, shards=2, checkpoint_every=20)
    full = tmp_path / "full"
    assert launch(2, "shells-train", "--data", data, "--out", full, "--config", cfg).returncode == 0
    want = _params(full)

    killed = tmp_path / "killed"
    proc = launch(2, "shells-train", "--data", data, "--out", killed, "--config", cfg, wait=False)
    log = RunDir(killed).log()
    t0 = time.time()
    while time.time() - t0 < 120:
        records = read_log(log) if log.is_file() else []
        if records and records[-1]["step"] >= 45:
            break
        time.sleep(0.02)
    pid = _rank_pid(proc.pid, 1)
    assert pid is not None, "rank 1 not found"
    os.kill(pid, signal.SIGKILL)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode != 0
    assert "continue with --resume" in err  # rank 0's message: what is intact, what to do
    ck = torch.load(RunDir(killed).checkpoint(), weights_only=False)  # intact, loadable
    assert ck["step"] % 20 == 0 and 40 <= ck["step"] < 120
    assert not [p.name for p in killed.iterdir() if p.name.startswith(".")]  # no temp files

    for nproc, name in ((0, "one"), (2, "two")):  # resume with 1 process, and with 2
        run = tmp_path / f"resumed-{name}"
        shutil.copytree(killed, run)
        r = launch(nproc, "shells-train", "--out", run, "--resume")
        assert r.returncode == 0, r.stderr[-2000:]
        assert max_relative_difference(want, _params(run)) <= 1e-5, name
        steps = [rec["step"] for rec in read_log(RunDir(run).log())]
        assert steps == list(range(1, 121)), name


def test_two_process_render_of_a_path_and_a_split_equals_one_process(tmp_path):
    """Frames i on rank i mod 2: the same PNG files, byte for byte, as a one-process render; the
    metrics agree (timings aside)."""
    from tests.conftest import trained_run

    run = trained_run(tmp_path, tiny_config())
    for extra in (["--path", "orbit", "--frames", "5"], []):  # a camera path, the test split
        outs = []
        for nproc in (0, 2):
            out = tmp_path / f"r{nproc}-{len(extra)}"
            r = launch(nproc, "shells-render", run, *extra, "--out", out)
            assert r.returncode == 0, r.stderr[-2000:]
            outs.append(out)
        one, two = outs
        pngs = sorted(p.name for p in one.glob("*.png"))
        assert pngs and pngs == sorted(p.name for p in two.glob("*.png"))
        for name in pngs:
            assert (one / name).read_bytes() == (two / name).read_bytes(), name
        m1, m2 = (json.loads((o / "metrics.json").read_text()) for o in outs)
        assert (m1["processes"], m2["processes"]) == (1, 2)
        for key in ("psnr", "ssim", "samples_per_pixel", "covered_fraction", "n_views"):
            assert m1[key] == m2[key], key
        if extra:
            assert (two / "video.mp4").is_file()
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folders


def test_independent_shards_merge_into_the_one_process_render(tmp_path, capsys):
    """`shells-render --shard K/N` as plain processes: nothing in OUT until the last shard is
    done, then the same files as one process (heatmaps on one scale, metrics, video)."""
    from shells.cli import render_main
    from tests.conftest import trained_run

    run = trained_run(tmp_path, tiny_config())
    args = [str(run), "--path", "orbit", "--frames", "5"]
    assert render_main([*args, "--out", str(tmp_path / "one")]) == 0
    out = tmp_path / "sharded"
    assert render_main([*args, "--out", str(out), "--shard", "1/2"]) == 0
    assert not out.exists() and "written when all shards are done" in capsys.readouterr().out
    assert render_main([*args, "--out", str(out), "--shard", "0/2"]) == 0
    one = tmp_path / "one"
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in one.iterdir())
    for p in one.glob("*.png"):
        assert (out / p.name).read_bytes() == p.read_bytes(), p.name
    m = json.loads((out / "metrics.json").read_text())
    assert m["processes"] == 2 and m["n_views"] == 5 and (out / "video.mp4").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # stage removed
    assert render_main([*args, "--out", str(out), "--shard", "2/2"]) == 2


def test_the_shards_of_a_step_draw_different_rays_on_the_cpu():
    """Every shard of a step (and so every rank of a data-parallel run) gets its own rays. The
    CPU generator keeps only the low 32 bits of a seed, so shard offsets above 2^32 (as they
    were) gave all shards the same draws; shard 0 stays the stream of runs made before shards
    existed."""
    from shells.train.loop import step_generator

    cpu = torch.device("cpu")
    n_pixels = 100 * 100 * 50

    def draw(step: int, shard: int) -> list[int]:
        gen = step_generator(0, step, cpu, shard)
        return torch.randint(0, n_pixels, (64,), generator=gen).tolist()

    shards = [draw(7, k) for k in range(8)]
    assert len({tuple(s) for s in shards}) == 8
    # no overlap beyond chance between any two shards of a step (64 of 500 000 pixels each)
    assert max(len(set(a) & set(b)) for i, a in enumerate(shards) for b in shards[i + 1:]) <= 1
    # nor with the neighbouring steps' shards
    assert all(draw(t, k) != shards[j] for t in (6, 8) for k in range(8) for j in range(8))
    # shard 0: seed * 1_000_003 + step, the generator of runs made before shards existed
    legacy = torch.Generator().manual_seed(7)
    assert shards[0] == torch.randint(0, n_pixels, (64,), generator=legacy).tolist()
