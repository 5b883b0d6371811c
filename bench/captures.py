"""Does the default preset work on any small object capture? The whole pipeline on toy
captures: per run stage-1 time, band and full-ray PSNR, and whether every object is kept.

    python -m bench.captures --out OUT [--scenes white-tube off-centre] [--res 64 128]
                             [--backdrops none white] [--presets auto object] [--distance D]
                             [--views 40] [--table BENCH.md] [--picture PNG]

For each scene x resolution x background x preset (a run already in OUT is only scored
again): the data set (`shells-scene NAME --res R
--views V [--backdrop 1 1 1] [--distance D]`, 8 test views) into OUT/data/..., then the
commands a user runs: `shells-train --preset P`, `shells-extract`, `shells-finetune`,
`shells-render --mode band` (after stage 2) and `shells-render --mode full --stage stage1`.
Each object of the scene is scored on both renders (`scenes.parts.part_scores`: its test
pixels' mean |error|); an object counts as kept when its error is at most KEPT_FACTOR times
the mean error over all objects' pixels. Prints one JSON line per run and, with ``--table``,
writes the Markdown table. A step that fails (e.g. shells-extract refusing a degenerate field)
is recorded with its exit status and message.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from bench.report import emit_json
from scenes import make_scene
from scenes.parts import objects_kept, part_scores
from shells.data.datasets import has_transparency, load_dataset

BIN = Path(sys.executable).parent


def data_set(out: Path, scene: str, res: int, backdrop: str, views: int,
             distance: float | None) -> Path:
    tag = f"{scene}-{res}-{backdrop}" + ("" if distance is None else f"-d{distance:g}")
    data = out / "data" / tag
    if not (data / "transforms_test.json").is_file():
        make_scene(scene, data, res=res, views=views, test_views=8,
                   backdrop=None if backdrop == "none" else (1.0, 1.0, 1.0), distance=distance)
    return data


def step(cmd: list[str], log: Path) -> tuple[int, str]:
    with open(log, "a") as f:
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.PIPE, text=True)
        f.write(r.stderr)
    last = [ln for ln in r.stderr.splitlines() if ln.strip()]
    return r.returncode, (last[-1] if last and r.returncode else "")


def scores(data: Path, render_dir: Path) -> dict[str, dict[str, float]]:
    meta = json.loads((render_dir / "metrics.json").read_text())
    test = load_dataset(data, "test", background=tuple(meta["background"]))
    alpha = test.alpha.numpy() if has_transparency(test.alpha) else None

    def render(i: int):
        rgb = iio.imread(render_dir / f"r_{i:03d}.png")[..., :3].astype(np.float64) / 255.0
        return rgb, np.full(rgb.shape[:2], np.nan)

    return part_scores(data, test.images.numpy(), alpha, render)


def run_one(out: Path, data: Path, preset: str) -> dict:
    run = out / "runs" / f"{data.name}-{preset}"
    row: dict = {"data": data.name, "preset": preset}
    if (run / "full" / "metrics.json").is_file():  # a finished run: scored again
        return score_run(run, data, row)
    if run.exists():
        import shutil
        shutil.rmtree(run)
    run.parent.mkdir(parents=True, exist_ok=True)
    log = run.parent / f"{run.name}.log"
    log.write_text("")
    t0 = time.perf_counter()
    cmds = [("train", ["shells-train", "--data", str(data), "--out", str(run), "--preset", preset]),
            ("extract", ["shells-extract", str(run)]),
            ("finetune", ["shells-finetune", str(run)]),
            ("band", ["shells-render", str(run), "--mode", "band", "--out", str(run / "band")]),
            ("full", ["shells-render", str(run), "--mode", "full", "--stage", "stage1", "--out",
                      str(run / "full")])]
    for name, cmd in cmds:
        rc, msg = step([str(BIN / cmd[0]), *cmd[1:]], log)
        if rc:
            row["failed"] = {"step": name, "status": rc, "message": msg}
            break
    row["seconds"] = time.perf_counter() - t0
    return score_run(run, data, row)


def score_run(run: Path, data: Path, row: dict) -> dict:
    summary = run / "train_summary.json"
    if summary.is_file():
        s = json.loads(summary.read_text())
        row["stage1_s"] = s["seconds"]
        row["health"] = s.get("health")
        row["stage1_test_psnr"] = (s.get("test") or {}).get("psnr")
    cfg = json.loads((run / "config.json").read_text()) if (run / "config.json").is_file() else {}
    row["iters"] = cfg.get("train", {}).get("iters")
    for mode in ("band", "full"):
        m = run / mode / "metrics.json"
        if m.is_file():
            met = json.loads(m.read_text())
            row[mode] = {k: met[k] for k in ("psnr", "ssim", "samples_per_pixel", "ms_per_frame")}
            parts = scores(data, run / mode)
            row[mode]["parts"] = parts
            row[mode]["kept"] = objects_kept(parts)
    return row


def table(rows: list[dict]) -> str:
    head = ("| data (scene-res-background) | preset | steps | stage 1 s | band after stage 2 dB |"
            " spp | full ray dB | band - full | every object kept | worst object / mean |"
            " health |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        b, f = r.get("band"), r.get("full")
        if b is None or f is None:
            fail = r.get("failed", {})
            lines.append(f"| {r['data']} | {r['preset']} | {r.get('iters')} | "
                         f"{r.get('stage1_s', 0):.0f} | failed at {fail.get('step')} "
                         f"(exit {fail.get('status')}) | | | | | | "
                         f"{','.join((r.get('health') or {}).get('kinds', [])) or 'ok'} |")
            continue
        worst = max(b["kept"]["ratios"].values())
        lines.append(f"| {r['data']} | {r['preset']} | {r['iters']} | {r['stage1_s']:.0f} | "
                     f"{b['psnr']:.2f} | {b['samples_per_pixel']:.2f} | {f['psnr']:.2f} | "
                     f"{b['psnr'] - f['psnr']:+.2f} | "
                     f"{'yes' if b['kept']['all'] and f['kept']['all'] else 'NO'} | "
                     f"{worst:.2f} | {','.join(r['health']['kinds']) or 'ok'} |")
    return head + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--scenes", nargs="+", default=["white-tube", "off-centre"])
    p.add_argument("--res", nargs="+", type=int, default=[64])
    p.add_argument("--backdrops", nargs="+", default=["none", "white"],
                   choices=["none", "white"], help="none: transparent; white: baked in")
    p.add_argument("--presets", nargs="+", default=["auto"])
    p.add_argument("--distance", type=float, default=None)
    p.add_argument("--views", type=int, nargs="+", default=[40],
                   help="training views, one per --res or one for all")
    p.add_argument("--table", default=None, help="also write the Markdown table here")
    p.add_argument("--picture", default=None, metavar="PNG",
                   help="also write test views 0-3 of every run: ground truth, full ray "
                        "(stage 1), band after stage 2, from top to bottom; runs side by side")
    a = p.parse_args(argv)
    out = Path(a.out)
    rows = []
    for i, res in enumerate(a.res):
        views = a.views[min(i, len(a.views) - 1)]
        for scene in a.scenes:
            for backdrop in a.backdrops:
                data = data_set(out, scene, res, backdrop, views, a.distance)
                for preset in a.presets:
                    row = run_one(out, data, preset)
                    emit_json(row)
                    rows.append(row)
                    if a.table:
                        Path(a.table).write_text(table(rows))
    if a.picture:
        picture(out, rows, a.picture)
    return 0


def picture(out: Path, rows: list[dict], path: str, views: int = 4) -> None:
    blocks = []
    for r in rows:
        run = out / "runs" / f"{r['data']}-{r['preset']}"
        if "band" not in r or "full" not in r:
            continue
        gt = [iio.imread(out / "data" / r["data"] / "test" / f"r_{k}.png") for k in range(views)]
        gt = [g[..., :3] if g[..., 3].min() == 255 else
              np.round(g[..., :3] * (g[..., 3:] / 255.0) + 255.0 * (1 - g[..., 3:] / 255.0))
              for g in gt]  # composited on white, as the renders
        rows_ = [gt] + [[iio.imread(run / m / f"r_{k:03d}.png")[..., :3] for k in range(views)]
                        for m in ("full", "band")]
        block = np.concatenate([np.concatenate(x, 1) for x in rows_], 0).astype(np.uint8)
        blocks.append(np.pad(block, ((0, 0), (0, 4), (0, 0)), constant_values=255))
    img = np.concatenate(blocks, 1)
    scale = max(1, 256 // img.shape[0] + 1)
    iio.imwrite(path, np.kron(img, np.ones((scale, scale, 1), np.uint8)))


if __name__ == "__main__":
    raise SystemExit(main())
