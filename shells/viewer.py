"""A web viewer of a trained run (`shells-view RUN`), with viser.

The browser shows the outer and inner shells as meshes (hidden by default; a checkbox shows
them), the training cameras as frustums, and, as the background image, the band render of the
browser's current camera (Dr.Jit, `shells.render.frame.render_image`). While the camera moves
the render is made at a lower resolution; once it rests for ``settle_s`` it is made again at
full resolution. A checkbox swaps the colours for the samples-per-pixel heatmap.

viser's camera is in OpenCV axes (x right, y down, z forward, as `shells.data.cameras`); its ``fov``
is the vertical field of view in radians and ``aspect`` width / height of the canvas.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shells.errors import InputError
from shells.run import RunDir, load_field, load_shells, read_run


def camera_c2w(wxyz: Any, position: Any) -> torch.Tensor:  # -> [4, 4] OpenCV camera-to-world
    w, x, y, z = (float(v) for v in wxyz)
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rot, np.asarray(position, np.float64)
    return torch.from_numpy(c2w).float()


def wxyz_of(c2w: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix [3, 3]."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(c2w).as_quat()
    return np.array([w, x, y, z])


class Viewer:
    """Loads RUN once; `frame` renders one camera; `serve` runs the viser server."""

    def __init__(self, run_dir: str | Path, stage: str = "latest", max_side: int = 320,
                 moving_side: int = 120) -> None:
        from shells.data.datasets import load_dataset
        from shells.device import mitsuba_variant
        from shells.fields.drjit_field import DrJitField

        run = RunDir(run_dir)
        meta = read_run(run)
        field, self.cfg = load_field(run.root, stage=stage)
        self.variant = mitsuba_variant(self.cfg.render.variant)
        self.scene = load_shells(run, self.variant)
        self.dj = DrJitField(field)
        self.data = load_dataset(meta["data"], "train", downscale=int(meta["downscale"]),
                                 background=tuple(self.cfg.data.background))
        self.run, self.max_side, self.moving_side = run, max_side, moving_side
        self.lock = threading.Lock()  # one render at a time (Dr.Jit state is shared)

    def frame(self, c2w: torch.Tensor, fov: float, aspect: float, side: int,
              heat: bool = False) -> np.ndarray:
        """The band render [H, W, 3] uint8 of an OpenCV camera with vertical ``fov``; the
        longer image side is ``side`` pixels."""
        from shells.data.cameras import pinhole_cameras
        from shells.render.frame import render_image
        from shells.render.views import heatmap, to_png

        if aspect >= 1:
            width, height = side, max(1, round(side / aspect))
        else:
            width, height = max(1, round(side * aspect)), side
        fy = 0.5 * height / np.tan(0.5 * fov)
        cams = pinhole_cameras(c2w[None], fx=fy, width=width, height=height)
        o, d = cams.pixel_rays(0, self.cfg.render.spp)
        with self.lock:
            img, spp = render_image(self.dj, o, d, height, width, self.cfg.render, "band",
                                    self.scene, self.data.aabb, tuple(self.cfg.data.background))
        return heatmap(spp, float(spp.max())) if heat else to_png(img)

    def serve(self, host: str = "0.0.0.0", port: int = 8080, settle_s: float = 0.3,
              dump: Path | None = None) -> None:
        """Run the server until interrupted; ``dump``: write each full-resolution background
        (frame.png, camera.json) there, for tests."""
        import viser

        from shells.levelset.mesh import load_ply

        server = viser.ViserServer(host=host, port=port)
        server.gui.configure_theme(control_layout="collapsible", show_logo=False)
        outer = load_ply(self.run.outer)
        shells = [server.scene.add_mesh_simple("/shells/outer", outer[0], outer[1],
                                               color=(230, 120, 60), opacity=0.3, visible=False)]
        if self.run.inner.is_file():
            inner = load_ply(self.run.inner)
            if len(inner[1]):
                shells.append(server.scene.add_mesh_simple(
                    "/shells/inner", inner[0], inner[1], color=(60, 120, 230), opacity=0.5,
                    visible=False))
        cams = self.data.cameras
        fov0 = float(2 * np.arctan(0.5 * cams.height / float(cams.fy[0])))
        for i in range(len(cams)):
            c2w = cams.c2w[i].double().numpy()
            server.scene.add_camera_frustum(f"/cameras/{i:03d}", fov=fov0,
                                            aspect=cams.width / cams.height, scale=0.1,
                                            wxyz=wxyz_of(c2w[:3, :3]), position=c2w[:3, 3])
        show_shells = server.gui.add_checkbox("Show shells", False)
        heat = server.gui.add_checkbox("Samples per pixel", False)
        side = server.gui.add_slider("Resolution", 32, 1024, 16, self.max_side)

        @show_shells.on_update
        def _(_: Any) -> None:
            for s in shells:
                s.visible = show_shells.value

        c0 = cams.c2w[0].double().numpy()
        alive: dict[int, bool] = {}  # render loops stop when their browser tab goes

        @server.on_client_disconnect
        def _(client: Any) -> None:
            alive.pop(client.client_id, None)

        @server.on_client_connect
        def _(client: Any) -> None:
            client.camera.fov = fov0
            client.camera.wxyz = wxyz_of(c0[:3, :3])
            client.camera.position = c0[:3, 3]
            state = {"stamp": None, "full": False, "heat": None, "side": None, "t": 0.0}
            alive[client.client_id] = True

            def loop() -> None:
                while alive.get(client.client_id):
                    cam = client.camera
                    stamp = (tuple(np.round(cam.wxyz, 6)), tuple(np.round(cam.position, 6)),
                             round(cam.fov, 6), round(cam.aspect, 6))
                    moved = stamp != state["stamp"] or heat.value != state["heat"] \
                        or side.value != state["side"]
                    if moved:
                        state.update(stamp=stamp, full=False, t=time.time(), heat=heat.value,
                                     side=side.value)
                        img = self.frame(camera_c2w(cam.wxyz, cam.position), cam.fov,
                                         cam.aspect, self.moving_side, heat.value)
                        client.scene.set_background_image(img, format="png")
                    elif not state["full"] and time.time() - state["t"] > settle_s:
                        c2w = camera_c2w(cam.wxyz, cam.position)
                        img = self.frame(c2w, cam.fov, cam.aspect, int(side.value), heat.value)
                        client.scene.set_background_image(img, format="png")
                        state["full"] = True
                        if dump is not None:
                            _dump(dump, img, c2w, cam.fov, cam.aspect)
                    time.sleep(0.03)

            threading.Thread(target=loop, daemon=True).start()

        url = f"http://{'localhost' if host in ('0.0.0.0', '') else host}:{server.get_port()}"
        print(f"shells-view: {self.run.root} at {url} (Ctrl-C to stop)", flush=True)
        server.sleep_forever()


def _dump(folder: Path, img: np.ndarray, c2w: torch.Tensor, fov: float, aspect: float) -> None:
    import json

    from shells.files import atomic_write, write_image

    folder.mkdir(parents=True, exist_ok=True)
    atomic_write(folder / "frame.png", lambda p: write_image(p, img, extension=".png"))
    atomic_write(folder / "camera.json", lambda p: p.write_text(json.dumps(
        {"c2w": c2w.tolist(), "fov": fov, "aspect": aspect})))


def view(run_dir: str | Path, host: str = "0.0.0.0", port: int = 8080, stage: str = "latest",
         max_side: int = 320, dump: str | Path | None = None) -> None:
    run = RunDir(run_dir)
    if not run.outer.is_file():
        raise InputError(f"{run.outer}: no shells; run shells-extract {run.root} first")
    Viewer(run_dir, stage, max_side).serve(host, port, dump=Path(dump) if dump else None)
