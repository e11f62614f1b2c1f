"""The viewer's server: a viser server with the GUI (output switch, water control), the training and test cameras as
frustums, and the decision of when to render which client's view.

Threading: viser calls the GUI and camera callbacks on its own threads; they only mark clients as needing a new
frame. Frames are rendered by whoever calls `Viewer.update()` (the `uw-viewer` loop, or the training loop between
steps), so the model is never read while another thread changes it.
"""

from __future__ import annotations

import contextlib
import errno
import io
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from uw3dgs.cameras import Camera
from uw3dgs.medium.formation import Water
from uw3dgs.render.camera_path import camera_to_world
from uw3dgs.viewer.camera import camera_to_viser, up_direction, viser_to_camera
from uw3dgs.viewer.render import available_outputs, has_medium, learned_b_inf, render_image

THUMBNAIL_PX = 96
"""Long side in pixels of the images shown in the camera frustums."""


class ViewerPortError(RuntimeError):
    """The port asked for cannot be bound (in use, or not allowed)."""


@dataclass
class View:
    """A dataset view to show as a frustum: its camera, its image [H, W, 3] in [0, 1] (or None), its split."""

    camera: Camera
    image: torch.Tensor | None
    split: str


def views_from_datamanager(datamanager: Any, images: bool = True) -> list[View]:
    """The training and test views of a datamanager (`train_indices`, `test_indices`, `scene`)."""
    scene = datamanager.scene
    return [View(scene.cameras[i], scene.images[i] if images else None, split)
            for split, indices in (("train", datamanager.train_indices), ("test", datamanager.test_indices))
            for i in indices]


def require_viser() -> None:
    """Raise a one-line RuntimeError naming the fix when viser is not installed."""
    try:
        import viser  # noqa: F401
    except ImportError:
        raise RuntimeError("the viewer needs the viser package: pip install viser") from None


def check_port(host: str, port: int, option: str = "--port") -> None:
    """Raise `ViewerPortError` (one line: cause and fix) when `port` on `host` cannot be bound. viser itself would
    silently move to the next free port, and the URL the user typed would show something else; port 0 (the OS's
    choice) is refused for the same reason."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ViewerPortError(f"{option} {port} is not a port; give one from 1 to 65535, e.g. {option} 7007")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as sock:
        # as the server binds (asyncio): a port a closed server left in TIME_WAIT is free, a listening one is not
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise ViewerPortError(f"port {port} on {host} is in use (another viewer or program holds it); pass "
                                      f"a free one, e.g. {option} {port + 1}") from None
            raise ViewerPortError(f"cannot listen on {host}:{port} ({exc.strerror or exc}); pass another {option} "
                                  "or --host") from None


def thumbnail(image: torch.Tensor, long_side: int = THUMBNAIL_PX) -> np.ndarray:
    """[h, w, 3] uint8 of `image` [H, W, 3] in [0, 1], subsampled by a whole stride to about `long_side` pixels."""
    stride = max(1, -(-max(image.shape[:2]) // long_side))
    return (image[::stride, ::stride].detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


class Viewer:
    """A viser server showing `model` from every connected client's camera.

    `views`: the dataset cameras drawn as frustums (world units of the model). `max_resolution`: long side in pixels
    of a rendered frame (also at most the client's canvas). `max_share`: with `live` (training), the viewer waits
    after each round of renders until its renders are at most this share of the wall time; `refresh_seconds`: in
    `live` mode, a view whose camera did not move is re-rendered (the model changed) at most this often.
    """

    def __init__(self, model: Any, views: list[View], host: str = "127.0.0.1", port: int = 7007,
                 max_resolution: int = 512, live: bool = False, max_share: float = 0.05,
                 refresh_seconds: float = 2.0, port_option: str = "--port", title: str = "uw3dgs"):
        require_viser()
        check_port(host, port, port_option)
        import viser

        self.model = model
        self.max_resolution = int(max_resolution)
        self.live = live
        self.max_share = max_share
        self.refresh_seconds = refresh_seconds
        self.device = next(iter(model.parameters())).device
        self._lock = threading.Lock()
        self._dirty: set[int] = set()
        self._next_allowed = 0.0
        self._last_round = 0.0
        self._step: int | None = None
        self._rendered_step: int | None = None
        self.render_seconds = 0.0
        """Wall time spent rendering for clients so far (seconds)."""
        self.frames = 0
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: the commands print the URL themselves
            self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        if self.server.get_port() != port:  # taken between the check and the bind
            self.server.stop()
            raise ViewerPortError(f"port {port} on {host} is in use; pass a free one, e.g. {port_option} {port + 1}")
        self.host, self.port = host, port
        self._setup_scene(views)
        self._setup_gui()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(lambda client: self._discard(client.client_id))

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    # -- scene and GUI --

    def _setup_scene(self, views: list[View]) -> None:
        cameras = [v.camera for v in views]
        train = [v.camera for v in views if v.split == "train"] or cameras
        up = up_direction(train)
        self.server.scene.set_up_direction(tuple(float(x) for x in up))
        centers = np.stack([camera_to_viser(c)[1] for c in cameras]) if cameras else np.zeros((1, 3))
        extent = float(np.linalg.norm(centers.max(0) - centers.min(0))) or 1.0
        scale = 0.03 * extent
        self.frustums = []
        for k, view in enumerate(views):
            wxyz, position, fov, aspect = camera_to_viser(view.camera)
            color = (220, 120, 20) if view.split == "train" else (30, 120, 230)
            image = None if view.image is None else thumbnail(view.image)
            self.frustums.append(self.server.scene.add_camera_frustum(
                f"/cameras/{view.split}/{k:05d}", fov=fov, aspect=aspect, scale=scale, thickness=1.5,
                thickness_units="screen", color=color, image=image, wxyz=wxyz, position=position))
        if train:  # start a little behind the first training view (its frustum in sight), looking along it
            _, position, fov, _ = camera_to_viser(train[0])
            forward = camera_to_world(train[0])[:3, 2].numpy()
            initial = self.server.initial_camera
            initial.position = position - forward * 8 * scale
            initial.look_at = position + forward * max(0.5 * extent, 1e-3)
            initial.up = up
            initial.fov = fov

    def _setup_gui(self) -> None:
        gui = self.server.gui
        outputs = available_outputs(self.model)
        self.output = gui.add_dropdown("Output", outputs, initial_value=outputs[0],
                                       hint="UWI: underwater image, URI: water-free image")
        self.water_k = self.b_inf = None
        if has_medium(self.model):
            self.water_k = gui.add_slider("Water k", min=0.0, max=3.0, step=0.05, initial_value=1.0,
                                          hint="beta_D and beta_B times k: 0 = no water, 1 = learned, 3 = murkier")
            self._b_inf_learned = self._learned_rgb255()
            self.b_inf = gui.add_rgb("B_inf", initial_value=self._b_inf_learned,
                                     hint="veiling light (starts at the learned one)")
            reset = gui.add_button("Reset water")

            @reset.on_click
            def _(_event) -> None:
                self.water_k.value = 1.0
                self._b_inf_learned = self._learned_rgb255()
                self.b_inf.value = self._b_inf_learned

        self.show_cameras = gui.add_checkbox("Show cameras", initial_value=True)
        self.status = gui.add_markdown(self._status_text())
        for handle in (self.output, self.water_k, self.b_inf):
            if handle is not None:
                handle.on_update(lambda _event: self.mark_all())

        @self.show_cameras.on_update
        def _(_event) -> None:
            for frustum in self.frustums:
                frustum.visible = self.show_cameras.value

    def _learned_rgb255(self) -> tuple[int, int, int]:
        r, g, b = learned_b_inf(self.model)
        return round(255 * r), round(255 * g), round(255 * b)

    def water(self) -> Water:
        """The water control's current state. B_inf left at the learned value (as the GUI shows it, 8 bits) means the
        learned one itself, at full precision, and while training the learned one as it changes."""
        if self.water_k is None:
            return Water()
        value = tuple(int(x) for x in self.b_inf.value)
        b_inf = None if value == self._b_inf_learned else tuple(x / 255.0 for x in value)
        return Water(k=float(self.water_k.value), b_inf=b_inf)

    def _follow_learned_b_inf(self) -> None:
        """While training: an untouched B_inf control follows the learned B_inf."""
        if self.b_inf is None or tuple(int(x) for x in self.b_inf.value) != self._b_inf_learned:
            return
        learned = self._learned_rgb255()
        if learned != self._b_inf_learned:
            self._b_inf_learned = learned
            self.b_inf.value = learned

    # -- clients --

    def _connect(self, client: Any) -> None:
        client.camera.on_update(lambda camera: self.mark(camera.client.client_id))
        self.mark(client.client_id)

    def mark(self, client_id: int) -> None:
        with self._lock:
            self._dirty.add(client_id)

    def mark_all(self) -> None:
        with self._lock:
            self._dirty.update(self.server.get_clients())

    def _discard(self, client_id: int) -> None:
        with self._lock:
            self._dirty.discard(client_id)

    def render_client(self, client: Any) -> bool:
        """Render and send `client`'s view; False when its camera is not known yet."""
        cam = client.camera
        try:
            wxyz, position, fov, aspect = cam.wxyz, cam.position, cam.fov, cam.aspect
            canvas = max(int(cam.image_width), int(cam.image_height))
        except (AssertionError, AttributeError):  # no camera message from this client yet
            return False
        resolution = min(self.max_resolution, canvas) if canvas > 0 else self.max_resolution
        camera = viser_to_camera(wxyz, position, fov, aspect, resolution, device=self.device)
        image = render_image(self.model, camera, self.output.value, self.water())
        client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
        return True

    def update(self, step: int | None = None) -> bool:
        """Render the views that need it (camera or control changed; in live mode also the model, at most every
        `refresh_seconds`), within the time budget. Cheap when there is nothing to do (no client, or too soon).
        True when something was rendered."""
        if step is not None:
            self._step = step
        now = time.perf_counter()
        if now < self._next_allowed:
            return False
        clients = self.server.get_clients()
        if not clients:
            return False
        with self._lock:
            due = set(self._dirty)
        if self.live and self._step != self._rendered_step and now - self._last_round >= self.refresh_seconds:
            due = set(clients)
        due &= set(clients)
        if not due:
            return False
        if self.live:
            self._follow_learned_b_inf()
        start, rendered = time.perf_counter(), 0
        for client_id in sorted(due):
            with self._lock:
                self._dirty.discard(client_id)
            if self.render_client(clients[client_id]):
                rendered += 1
            else:  # its camera is not known yet: next time
                self.mark(client_id)
        if not rendered:
            return False
        elapsed = time.perf_counter() - start
        self.render_seconds += elapsed
        self.frames += rendered
        self._last_round, self._rendered_step = time.perf_counter(), self._step
        if self.live:  # renders take at most max_share of the wall time
            self._next_allowed = self._last_round + elapsed * (1.0 / self.max_share - 1.0)
        self.status.content = self._status_text()
        return True

    def _status_text(self) -> str:
        n = getattr(self.model, "num_gaussians", None)
        parts = [f"{n:,} Gaussians" if n is not None else "", f"step {self._step}" if self._step is not None else ""]
        return " · ".join(p for p in parts if p)

    def serve_forever(self, poll_seconds: float = 0.02, stop: threading.Event | None = None) -> None:
        """Render on demand until interrupted (Ctrl-C) or `stop` is set."""
        while stop is None or not stop.is_set():
            if not self.update():
                time.sleep(poll_seconds)

    def stop(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # and its "Server stopped"
            self.server.stop()
