"""Faults and hostile input (issue 20): bad photos and transforms, runs of another version,
another architecture or another run, interrupted and failing commands, two writers of a run.

Bad input is made in tmp_path; a command given it must exit with status 2 and one line on
stderr that names the file, and create nothing. Interruptions are real SIGINTs sent to a
command in a subprocess after a seeded random delay; a refused write is a write that raises
OSError(ENOSPC) (the disk cannot be filled in a test).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from PIL import Image

from shells import cli
from shells.data.datasets import MAX_TRANSFORMS_BYTES, load_dataset
from tests.conftest import tiny_config, trained_run, write_tiny_blender


def _in_process(main):
    """A CLI entry point called in this process with arguments that may be paths."""
    return lambda argv: main([str(a) for a in argv])


train_main, extract_main, finetune_main, render_main = map(_in_process, (
    cli.train_main, cli.extract_main, cli.finetune_main, cli.render_main))

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["OMP_NUM_THREADS"] = "1"
    return env


def _cmd(name: str, *args: object) -> list[str]:
    return [str(BIN / name), *map(str, args)]


def _refused(capsys, main, argv, needle: str, absent: Path | None = None) -> str:
    """main(argv) exits 2 with one line naming ``needle``; ``absent`` was not created."""
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    said = [ln for ln in err if ln.startswith("shells-")]  # besides a progress bar's lines
    assert len(said) == 1 and said[0] == err[-1] and ": error: " in said[0], err
    assert needle in said[0], said[0]
    if absent is not None:
        assert not absent.exists(), sorted(p.name for p in absent.iterdir())
    return said[0]


def _tree(root: Path) -> dict[str, str]:
    """Every file under root (hidden ones too) -> sha256."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _hidden(folder: Path) -> list[str]:
    """Temporary / staging / lock entries left in a folder (names starting with '.')."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".")) if folder.exists() else []


# --------------------------------------------------------------------------------------------
# 1. Input: photos and transforms
# --------------------------------------------------------------------------------------------

def _data(tmp_path: Path) -> Path:
    return write_tiny_blender(tmp_path / "data", n_train=3, n_test=1, res=8)


def _edit_transforms(data: Path, fn, split: str = "train") -> Path:
    path = data / f"transforms_{split}.json"
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))
    return path


def _truncate(path: Path) -> None:
    b = path.read_bytes()
    path.write_bytes(b[:len(b) // 2])


def _train_refused(capsys, data: Path, needle: str) -> str:
    out = data.parent / "run"
    return _refused(capsys, train_main, ["--data", data, "--out", out, "--iters", 1], needle, out)


def test_truncated_png_is_refused(tmp_path, capsys):
    data = _data(tmp_path)
    _truncate(data / "train" / "r_1.png")
    msg = _train_refused(capsys, data, "r_1.png")
    assert "truncated or corrupt" in msg


def test_truncated_jpeg_is_refused(tmp_path, capsys):
    data = _data(tmp_path)
    (data / "train" / "r_2.png").unlink()
    iio.imwrite(data / "train" / "r_2.jpg", np.full((8, 8, 3), 128, np.uint8))
    _truncate(data / "train" / "r_2.jpg")
    _train_refused(capsys, data, "r_2.jpg")


def test_corrupt_image_is_refused_in_one_line(tmp_path, capsys):
    data = _data(tmp_path)
    (data / "train" / "r_0.png").write_bytes(b"not an image at all\n" * 20)  # the first image
    _train_refused(capsys, data, "r_0.png")


def test_image_of_another_size_is_refused(tmp_path, capsys):
    data = _data(tmp_path)
    iio.imwrite(data / "train" / "r_1.png", np.zeros((10, 8, 4), np.uint8))
    _train_refused(capsys, data, "r_1.png")


def test_image_size_differs_from_transforms_w_h(tmp_path, capsys):
    data = _data(tmp_path)
    _edit_transforms(data, lambda m: m.update(w=16, h=8))
    msg = _train_refused(capsys, data, "transforms_train.json")
    assert "16x8" in msg and "8x8" in msg


def test_empty_frame_list_is_refused(tmp_path, capsys):
    data = _data(tmp_path)
    _edit_transforms(data, lambda m: m.update(frames=[]))
    msg = _train_refused(capsys, data, "transforms_train.json")
    assert "empty" in msg


def test_duplicate_frames_are_refused(tmp_path, capsys):
    data = _data(tmp_path)
    _edit_transforms(data, lambda m: m["frames"].append(dict(m["frames"][0])))
    msg = _train_refused(capsys, data, "transforms_train.json")
    assert "duplicate" in msg and "r_0" in msg


@pytest.mark.parametrize("intrinsics, needle", [
    ({"camera_angle_x": 0.0}, "camera_angle_x"),
    ({"fl_x": 0.0}, "focal"),
    ({"fl_x": -20.0}, "focal"),
    ({"cx": 400.0}, "principal point"),
    ({"cy": -50.0}, "principal point"),
])
def test_absurd_intrinsics_are_refused(tmp_path, capsys, intrinsics, needle):
    data = _data(tmp_path)
    _edit_transforms(data, lambda m: m.update(intrinsics))
    msg = _train_refused(capsys, data, "transforms_train.json")
    assert needle in msg


def test_huge_transforms_file_is_refused_before_parsing(tmp_path, capsys):
    data = _data(tmp_path)
    path = data / "transforms_train.json"
    os.truncate(path, 300 << 20)  # 300 MiB, sparse: no disk space is used
    assert path.stat().st_size > MAX_TRANSFORMS_BYTES
    t0 = time.perf_counter()
    msg = _train_refused(capsys, data, "transforms_train.json")
    assert "300 MiB" in msg and time.perf_counter() - t0 < 5  # not read, let alone parsed


def _png16(path: Path, a: np.ndarray) -> None:
    """A 16-bit PNG (colour type 2 = RGB, 6 = RGBA, 0 = grey), written by hand: Pillow cannot
    write 16-bit colour."""
    h, w = a.shape[:2]
    c = 1 if a.ndim == 2 else a.shape[2]
    raw = b"".join(b"\x00" + a[y].astype(">u2").tobytes() for y in range(h))

    def chunk(t: bytes, d: bytes) -> bytes:
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))

    ihdr = struct.pack(">IIBBBBB", w, h, 16, {1: 0, 3: 2, 4: 6}[c], 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
                     + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def test_sixteen_bit_colour_png_keeps_its_precision(tmp_path):
    data = _data(tmp_path)
    rgb = np.random.default_rng(0).integers(0, 65536, (8, 8, 3)).astype(np.uint16)
    rgba = np.concatenate([rgb, np.full((8, 8, 1), 65535, np.uint16)], -1)
    _png16(data / "train" / "r_0.png", rgba)
    _png16(data / "train" / "r_1.png", rgb)
    ds = load_dataset(data, background=(0.0, 0.0, 0.0))
    want = torch.from_numpy(rgb.astype(np.float32) / 65535)
    torch.testing.assert_close(ds.images[0], want, rtol=0, atol=1e-6)
    torch.testing.assert_close(ds.images[1], want, rtol=0, atol=1e-6)
    assert ds.images[0].mul(65535).sub(torch.from_numpy(rgb.astype(np.float32))).abs().max() < 0.1
    torch.testing.assert_close(ds.alpha[0], torch.ones(8, 8))


def test_grey_grey_alpha_and_palette_images_load(tmp_path):
    data = _data(tmp_path)
    rng = np.random.default_rng(1)
    grey = rng.integers(0, 256, (8, 8)).astype(np.uint8)
    colours = (rng.integers(0, 256, (8, 8, 3)) // 64 * 64).astype(np.uint8)  # few colours
    Image.fromarray(grey, "L").save(data / "train" / "r_0.png")
    la = np.stack([grey, np.full_like(grey, 255)], -1)
    Image.fromarray(la, "LA").save(data / "train" / "r_1.png")
    pal = Image.fromarray(colours, "RGB").quantize(colors=64, method=Image.Quantize.MEDIANCUT)
    assert pal.mode == "P"
    pal.save(data / "train" / "r_2.png")
    ds = load_dataset(data)
    g = torch.from_numpy(grey.astype(np.float32) / 255)[..., None].expand(8, 8, 3)
    torch.testing.assert_close(ds.images[0], g, rtol=0, atol=1e-6)  # grey broadcast to RGB
    torch.testing.assert_close(ds.images[1], g, rtol=0, atol=1e-6)  # opaque grey + alpha
    want = np.asarray(pal.convert("RGB"), np.float32) / 255
    torch.testing.assert_close(ds.images[2], torch.from_numpy(want), rtol=0, atol=1e-6)
    assert ds.alpha is None  # the first image has no alpha


# --------------------------------------------------------------------------------------------
# 2. Run directories of another version, checkpoints of another architecture or run
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two independent tiny runs (stage 1 + shells): A and B."""
    root = tmp_path_factory.mktemp("faults")
    return trained_run(root / "a", tiny_config()), trained_run(root / "b", tiny_config())


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _edit_json(path: Path, fn) -> None:
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))


def _edit_checkpoint(path: Path, fn) -> None:
    ck = torch.load(path, weights_only=False)
    fn(ck)
    torch.save(ck, path)


def test_run_of_another_format_is_refused(runs, tmp_path, capsys):
    run = _copy(runs[0], tmp_path / "run")
    _edit_json(run / "run.json", lambda m: m.update(format=7))
    before = _tree(run)
    for main, argv in ((render_main, [run, "--out", tmp_path / "out"]), (extract_main, [run]),
                       (finetune_main, [run])):
        msg = _refused(capsys, main, argv, "run.json", tmp_path / "out")
        assert "format 7" in msg and "re-train" in msg
    assert _tree(run) == before


def test_checkpoint_of_another_format_is_refused(runs, tmp_path, capsys):
    run = _copy(runs[0], tmp_path / "run")
    _edit_checkpoint(run / "checkpoint.pt", lambda c: c.update(format=2))
    msg = _refused(capsys, render_main, [run, "--out", tmp_path / "out"], "checkpoint.pt",
                   tmp_path / "out")
    assert "re-train" in msg


def test_checkpoint_of_another_architecture_is_refused(runs, tmp_path, capsys):
    run = _copy(runs[0], tmp_path / "run")
    _edit_checkpoint(run / "checkpoint.pt", lambda c: c["config"]["field"].update(geo_hidden=32))
    before = _tree(run)
    for main, argv in ((extract_main, [run]), (render_main, [run, "--out", tmp_path / "out"]),
                       (train_main, ["--out", run, "--resume", "--iters", 8])):
        msg = _refused(capsys, main, argv, "checkpoint.pt", tmp_path / "out")
        assert "architecture" in msg and "re-train" in msg
    assert _tree(run) == before
    # a key this version does not know: a checkpoint of another (newer) version
    _edit_checkpoint(run / "checkpoint.pt", lambda c: c["config"]["field"].update(wings=2))
    msg = _refused(capsys, extract_main, [run], "checkpoint.pt")
    assert "wings" in msg and "re-train" in msg


def test_checkpoint_of_another_run_is_refused(runs, tmp_path, capsys):
    run = _copy(runs[0], tmp_path / "run")
    shutil.copy(runs[1] / "checkpoint.pt", run / "checkpoint.pt")
    msg = _refused(capsys, extract_main, [run], "checkpoint.pt")
    assert "another run" in msg


def test_shells_of_another_run_are_refused(runs, tmp_path, capsys):
    run = _copy(runs[0], tmp_path / "run")
    shutil.rmtree(run / "shells")
    shutil.copytree(runs[1] / "shells", run / "shells")
    before = _tree(run)
    for main, argv in ((render_main, [run, "--out", tmp_path / "out"]), (finetune_main, [run])):
        msg = _refused(capsys, main, argv, "shells", tmp_path / "out")
        assert "another run" in msg and "shells-extract" in msg
    assert _tree(run) == before


def test_shells_of_an_older_checkpoint_are_refused(runs, tmp_path, capsys):
    run = _copy(runs[0], tmp_path / "run")
    _edit_checkpoint(run / "checkpoint.pt", lambda c: c.update(step=c["step"] + 5))
    msg = _refused(capsys, render_main, [run, "--out", tmp_path / "out"], "shells",
                   tmp_path / "out")
    assert "re-extract" in msg


def test_runs_from_before_the_version_are_read(runs, tmp_path, capsys):
    """A run written before format versions and ids existed (no 'format', no 'run_id' in
    run.json and checkpoint, no 'source' in shells/stats.json) is format 1 and still works."""
    run = _copy(runs[0], tmp_path / "run")
    _edit_json(run / "run.json", lambda m: [m.pop("format"), m.pop("run_id")])
    _edit_checkpoint(run / "checkpoint.pt", lambda c: [c.pop("format"), c.pop("run_id")])
    _edit_json(run / "shells" / "stats.json", lambda m: m.pop("source"))
    assert render_main([run, "--out", tmp_path / "out"]) == 0
    assert (tmp_path / "out" / "metrics.json").is_file()


# --------------------------------------------------------------------------------------------
# 3. Refused writes (ENOSPC, unwritable folders) leave everything as it was
# --------------------------------------------------------------------------------------------

def _failing(real, fail_at: int, partial=None):
    """A stand-in for a write function whose ``fail_at``-th call (1-based) writes part of its
    file (``partial(args)``) and raises OSError(ENOSPC), as a full disk does."""
    calls = {"n": 0}

    def fake(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == fail_at:
            if partial is not None:
                partial(*args)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(*args, **kwargs)

    return fake


def _train_config(tmp_path: Path, iters: int, every: int) -> Path:
    cfg = tiny_config(train_iters=iters)
    cfg.train.checkpoint_every, cfg.train.log_every, cfg.train.warmup_iters = every, 1, 2
    path = tmp_path / "train.json"
    path.write_text(json.dumps(cfg.to_dict()))
    return path


def _field_state(run: Path) -> dict[str, torch.Tensor]:
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    return {"step": torch.tensor(ck["step"]), **ck["field"],
            **{f"opt.{k}.{n}": v for k, s in ck["optimizer"]["state"].items()
               for n, v in s.items()}}


def _same_state(a: Path, b: Path) -> None:
    sa, sb = _field_state(a), _field_state(b)
    assert sa.keys() == sb.keys()
    for k in sa:
        torch.testing.assert_close(sa[k], sb[k], rtol=0, atol=0, msg=k)


def _log_steps(run: Path) -> list[int]:
    return [json.loads(ln)["step"] for ln in (run / "train_log.jsonl").open() if ln.strip()]


def test_disk_full_during_training_then_resume(tmp_path, capsys, monkeypatch):
    data = _data(tmp_path)
    cfg = _train_config(tmp_path, 6, 2)
    args = ["--data", data, "--config", cfg, "--preset", "toy", "--device", "cpu"]
    assert train_main([*args, "--out", tmp_path / "ref"]) == 0
    capsys.readouterr()
    real = torch.save
    monkeypatch.setattr(torch, "save", _failing(
        real, 2, lambda obj, p: Path(p).write_bytes(b"PK\x03\x04 half a checkpoint")))
    run = tmp_path / "run"
    msg = _refused(capsys, train_main, [*args, "--out", run], "checkpoint.pt")
    assert "No space left" in msg and "free disk space" in msg
    monkeypatch.setattr(torch, "save", real)
    assert _hidden(run) == []  # no temporary checkpoint, no lock
    assert torch.load(run / "checkpoint.pt", weights_only=False)["step"] == 2  # the last good
    assert train_main(["--out", run, "--resume"]) == 0
    _same_state(run, tmp_path / "ref")
    assert _log_steps(run) == list(range(1, 7))


def test_disk_full_during_extraction_keeps_the_old_shells(runs, tmp_path, capsys, monkeypatch):
    ref = _copy(runs[0], tmp_path / "ref")
    assert extract_main([ref, "--resolution", 24]) == 0
    run = _copy(runs[0], tmp_path / "run")
    before = _tree(run)
    real = Path.write_bytes
    monkeypatch.setattr(Path, "write_bytes", _failing(
        real, 2, lambda self, data: real(self, data[:len(data) // 2])))  # inner.ply
    capsys.readouterr()
    msg = _refused(capsys, extract_main, [run, "--resolution", 24], "shells")
    assert "No space left" in msg
    monkeypatch.setattr(Path, "write_bytes", real)
    assert _tree(run) == before and _hidden(run) == []
    assert extract_main([run, "--resolution", 24]) == 0
    for name in ("outer.ply", "inner.ply", "slice.png"):
        assert (run / "shells" / name).read_bytes() == (ref / "shells" / name).read_bytes()


def _frames(out: Path) -> dict[str, str]:
    return {k: v for k, v in _tree(out).items() if k.endswith(".png")}


def test_disk_full_during_render_keeps_the_old_output(runs, tmp_path, capsys, monkeypatch):
    run = _copy(runs[0], tmp_path / "run")
    ref, out = tmp_path / "ref", tmp_path / "out"
    assert render_main([run, "--out", ref]) == 0
    assert render_main([run, "--out", out, "--width", 12, "--height", 12]) == 0  # an older one
    before = _tree(out)
    real = iio.imwrite
    monkeypatch.setattr(iio, "imwrite", _failing(
        real, 2, lambda p, *a: Path(p).write_bytes(b"\x89PNG half")))
    capsys.readouterr()
    msg = _refused(capsys, render_main, [run, "--out", out], "out")
    assert "No space left" in msg
    monkeypatch.setattr(iio, "imwrite", real)
    assert _tree(out) == before and _hidden(tmp_path) == []
    assert render_main([run, "--out", out]) == 0
    assert _frames(out) == _frames(ref)


def test_unwritable_output_folder_is_one_line(runs, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("a file, not a folder")
    _refused(capsys, render_main, [runs[0], "--out", blocker / "out"], "file")
    assert blocker.read_text() == "a file, not a folder"


# --------------------------------------------------------------------------------------------
# 4. One writer per run: the lock
# --------------------------------------------------------------------------------------------

def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    t0 = time.monotonic()
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout, f"{path} did not appear"
        time.sleep(0.02)


def test_second_finetune_on_a_run_is_refused_at_once(runs, tmp_path):
    run = _copy(runs[0], tmp_path / "run")
    first = subprocess.Popen(_cmd("shells-finetune", run, "--iters", 100000, "--device", "cpu"),
                             env=_env(), stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(run / ".lock", first)
        t0 = time.monotonic()
        second = subprocess.run(_cmd("shells-finetune", run, "--device", "cpu"), env=_env(),
                                capture_output=True, text=True, timeout=60)
        took = time.monotonic() - t0
        err = second.stderr.strip().splitlines()
        assert second.returncode == 2 and len(err) == 1, second.stderr
        assert f"pid {first.pid}" in err[0] and "shells-finetune" in err[0]
        assert took < 15  # at once: refused before any data or field is loaded
        assert first.poll() is None  # the first one goes on
    finally:
        first.send_signal(signal.SIGINT)
        _, first_err = first.communicate(timeout=60)
    assert first.returncode == 130, first_err
    assert not (run / ".lock").exists()


def test_stale_lock_of_a_dead_process_is_taken_over(runs, tmp_path, capsys):
    run = _copy(runs[0], tmp_path / "run")
    dead = subprocess.Popen(["true"])
    dead.wait()
    (run / ".lock").write_text(json.dumps({"pid": dead.pid, "host": os.uname().nodename,
                                           "command": "shells-extract"}))
    assert extract_main([run, "--resolution", 24]) == 0
    assert not (run / ".lock").exists()
    # a live owner (this test process) is respected
    (run / ".lock").write_text(json.dumps({"pid": os.getpid(), "host": os.uname().nodename,
                                           "command": "shells-finetune"}))
    msg = _refused(capsys, extract_main, [run], ".lock")
    assert f"pid {os.getpid()}" in msg


# --------------------------------------------------------------------------------------------
# 5. SIGINT at a random moment
# --------------------------------------------------------------------------------------------

SEEDS = (0, 1, 2)


def _timed(cmd: list[str]) -> float:
    t0 = time.monotonic()
    done = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return time.monotonic() - t0


def _interrupt(cmd: list[str], delay: float) -> subprocess.CompletedProcess:
    """Run cmd, send SIGINT after ``delay`` seconds (unless it ended), wait for it."""
    proc = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        proc.wait(timeout=delay)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    print(f"{Path(cmd[0]).name}: SIGINT after {delay:.2f} s -> status {proc.returncode}")
    assert "Traceback" not in err, err
    if proc.returncode == -signal.SIGINT:
        # the signal came after the command had finished, while the interpreter shut down:
        # the command has reported its result (and the caller compares it)
        assert out.strip(), err
        return subprocess.CompletedProcess(cmd, 0, out, err)
    assert proc.returncode in (0, 130), err
    if proc.returncode == 130:
        assert "interrupted" in err.strip().splitlines()[-1], err
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def _signal_from_another_thread(signum: int = signal.SIGINT) -> None:
    """As a Ctrl-C comes: to the process, taken by whichever thread (torch's, Dr.Jit's)."""
    t = threading.Thread(target=os.kill, args=(os.getpid(), signum))
    t.start()
    t.join()
    time.sleep(0.05)


def test_a_signal_after_the_final_commit_ends_the_command_as_done(tmp_path):
    """A Ctrl-C that comes once a command's outputs are committed must not report the command
    as interrupted (status 130 promises unchanged outputs); elsewhere it interrupts at once."""
    from shells.files import commit_files, final_commit, late_signal

    stage, out = tmp_path / "stage", tmp_path / "out"
    stage.mkdir()
    (stage / "a.txt").write_text("new")
    with final_commit():
        commit_files(stage, out)
        _signal_from_another_thread()  # held back until the block ends, then taken off
    assert late_signal() == signal.SIGINT
    assert (out / "a.txt").read_text() == "new"
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    (stage / "b.txt").write_text("new")
    with pytest.raises(KeyboardInterrupt):  # not a final commit: the signal raises after it
        commit_files(stage, out)
        _signal_from_another_thread()
    assert (out / "b.txt").is_file()
    with final_commit():
        pass
    assert late_signal() is None


def test_a_ctrl_c_inside_a_traced_drjit_loop_ends_in_one_line(capsys):
    """Dr.Jit re-raises an exception of a traced loop body as a RuntimeError whose cause is the
    KeyboardInterrupt: the command still ends as interrupted (130, one line)."""
    import argparse

    import drjit as dr
    from drjit.llvm import UInt32

    def body(i):
        raise KeyboardInterrupt  # as the signal handler raises it, mid-trace

    def fn(args):
        dr.while_loop((UInt32(0, 1),), lambda i: i < 3, body)

    assert cli._run(fn, argparse.ArgumentParser(prog="shells-x"), []) == 130
    assert capsys.readouterr().err.strip().splitlines() == ["shells-x: interrupted"]


def test_a_signal_while_the_lock_is_taken_leaves_no_lock(tmp_path, monkeypatch):
    import shells.files as files_module

    real = os.link

    def link(a, b):
        real(a, b)
        _signal_from_another_thread()  # the lock is there: it must be given up again

    monkeypatch.setattr(files_module.os, "link", link)
    body = []
    with pytest.raises(KeyboardInterrupt):  # raised once it is held, inside its try
        with files_module.lock(tmp_path / ".lock", "test"):
            body.append(1)
    assert body == [] and not (tmp_path / ".lock").exists()


@pytest.fixture(scope="module")
def train_reference(tmp_path_factory):
    root = tmp_path_factory.mktemp("train-ref")
    data = write_tiny_blender(root / "data", n_train=3, n_test=1, res=8)
    cfg = _train_config(root, 40, 5)
    args = ["--data", data, "--config", cfg, "--preset", "toy", "--device", "cpu"]
    seconds = _timed(_cmd("shells-train", *args, "--out", root / "ref"))
    return args, root / "ref", seconds


@pytest.mark.parametrize("seed", SEEDS)
def test_sigint_during_training_then_resume(train_reference, tmp_path, seed):
    args, ref, seconds = train_reference
    rng = np.random.default_rng(seed)
    run = tmp_path / "run"
    done = _interrupt(_cmd("shells-train", *args, "--out", run), rng.uniform(0.4, 1.0) * seconds)
    assert _hidden(run) == []  # no temporary checkpoint, no lock
    if done.returncode == 130:
        if (run / "checkpoint.pt").is_file():
            step = torch.load(run / "checkpoint.pt", weights_only=False)["step"]
            assert step % 5 == 0
            if step < 40:
                assert _timed(_cmd("shells-train", "--out", run, "--resume")) > 0
        else:  # stopped before the first checkpoint: start again
            assert _timed(_cmd("shells-train", *args, "--out", run)) > 0
    _same_state(run, ref)
    assert _log_steps(run) == list(range(1, 41))


@pytest.fixture(scope="module")
def extract_reference(runs, tmp_path_factory):
    ref = _copy(runs[0], tmp_path_factory.mktemp("extract-ref") / "ref")
    seconds = _timed(_cmd("shells-extract", ref, "--resolution", 48))
    return ref, seconds


@pytest.mark.parametrize("seed", SEEDS)
def test_sigint_during_extraction_then_rerun(runs, extract_reference, tmp_path, seed):
    ref, seconds = extract_reference
    rng = np.random.default_rng(100 + seed)
    run = _copy(runs[0], tmp_path / "run")
    before = _tree(run)
    cmd = _cmd("shells-extract", run, "--resolution", 48)
    done = _interrupt(cmd, rng.uniform(0.4, 1.0) * seconds)
    assert _hidden(run) == []
    if done.returncode == 130:
        assert _tree(run) == before  # the old shells, byte for byte
        assert _timed(cmd) > 0
    for name in ("outer.ply", "inner.ply", "slice.png"):
        assert (run / "shells" / name).read_bytes() == (ref / "shells" / name).read_bytes()


@pytest.fixture(scope="module")
def render_reference(runs, tmp_path_factory):
    root = tmp_path_factory.mktemp("render-ref")
    args = ["--split", "train", "--width", 24, "--height", 24]
    seconds = _timed(_cmd("shells-render", runs[0], *args, "--out", root / "ref"))
    return args, root / "ref", seconds


@pytest.mark.parametrize("seed", SEEDS)
def test_sigint_during_render_then_rerun(runs, render_reference, tmp_path, seed):
    args, ref, seconds = render_reference
    rng = np.random.default_rng(200 + seed)
    out = tmp_path / "out"
    assert render_main([runs[0], "--split", "train", "--width", 8, "--height", 8,
                        "--out", out]) == 0  # an older render is there
    before = _tree(out)
    cmd = _cmd("shells-render", runs[0], *args, "--out", out)
    done = _interrupt(cmd, rng.uniform(0.4, 1.0) * seconds)
    assert _hidden(tmp_path) == []  # no staging folder, no lock
    if done.returncode == 130:
        assert _tree(out) == before
        assert _timed(cmd) > 0
    assert _frames(out) == _frames(ref)


# --------------------------------------------------------------------------------------------
# 6. Size: memory budgets split the work, the result stays the same
# --------------------------------------------------------------------------------------------

def test_chunked_level_set_evolution_is_bit_for_bit_the_same():
    from shells.levelset.evolve import evolve

    n, h = 40, 2.0 / 39
    x = np.linspace(-1, 1, n)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    f0 = (np.sqrt(X ** 2 + Y ** 2 + Z ** 2) - 0.5 + 0.05 * np.sin(7 * X)).astype(np.float32)
    v = (0.02 + 0.01 * np.cos(5 * Y)).astype(np.float32)
    whole = evolve(f0, v, (h,) * 3, 10, 0.1, 0.2, 0.01)
    chunked = evolve(f0, v, (h,) * 3, 10, 0.1, 0.2, 0.01, memory_mb=1)  # ~5k voxels a chunk
    assert int((np.abs(f0) < 0.2).sum()) > 5242  # so there are two chunks or more
    assert not np.array_equal(whole, f0)
    np.testing.assert_array_equal(chunked, whole)


def test_tiled_render_is_the_same_image(runs, tmp_path):
    from shells.pipeline import render_run

    cfg = tmp_path / "small.json"
    cfg.write_text(json.dumps({"render": {"memory_mb": 1}}))  # a batch of ~160 rays: tiles
    a = render_run(runs[0], split="train", width=40, height=30, out=tmp_path / "a",
                   progress=False)
    b = render_run(runs[0], split="train", width=40, height=30, out=tmp_path / "b",
                   progress=False, config=cfg)
    assert a["width"] == b["width"] == 40
    assert _frames(tmp_path / "a") == _frames(tmp_path / "b")
