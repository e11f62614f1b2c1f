"""uw-viewer (uw3dgs/viewer/): viser camera -> Camera, the water control, the live viewer in training leaving the
numbers unchanged, its errors, and the page in headless Chromium (skipped without chromium, chromedriver, selenium)."""

from __future__ import annotations

import io
import math
import shutil
import socket
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import as_uw3dgs, run_command, train

from uw3dgs.engine.checkpoint import latest_checkpoint, load_checkpoint
from uw3dgs.engine.evaluator import load_trained
from uw3dgs.engine.trainer import Trainer
from uw3dgs.medium.formation import Water, form_with_water
from uw3dgs.render.camera_path import matrix_to_quaternion
from uw3dgs.viewer.camera import camera_to_viser, viser_to_camera
from uw3dgs.viewer.render import learned_b_inf, render_image, render_outputs

CHROMIUM = next((p for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser", shutil.which("chromium") or "",
                             shutil.which("google-chrome") or "") if p and Path(p).exists()), None)
CHROMEDRIVER = next((p for p in ("/usr/bin/chromedriver", shutil.which("chromedriver") or "")
                     if p and Path(p).exists()), None)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def uw3dgs_run(tiny_uw3dgs_trainer) -> Path:
    """The config.yml of the session's 20-step uw3dgs run (conftest)."""
    return tiny_uw3dgs_trainer.run_dir / "config.yml"


def look_at_wxyz(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """viser's wxyz (R_world_camera, OpenCV axes: x right, y down, z forward) of a camera at `position` looking at
    `target` with `up` up."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return matrix_to_quaternion(torch.tensor(np.stack([right, down, forward], axis=1))).numpy()


# ---- camera conversion --------------------------------------------------------------------------------------------


def test_a_viser_camera_projects_the_point_it_looks_at_to_the_image_centre():
    position, target, up = np.array([1.0, -2.0, 0.5]), np.array([0.3, 1.0, -0.2]), np.array([0.0, 0.0, 1.0])
    fov = math.radians(50.0)
    camera = viser_to_camera(look_at_wxyz(position, target, up), position, fov, aspect=16 / 9, max_resolution=320,
                             dtype=torch.float64)
    assert (camera.width, camera.height) == (320, 180)
    torch.testing.assert_close(camera.center, torch.tensor(position), atol=1e-12, rtol=0)
    uv, inside = camera.project(torch.tensor(target)[None])
    assert bool(inside[0])
    torch.testing.assert_close(uv[0], torch.tensor([160.0, 90.0], dtype=torch.float64), atol=1e-9, rtol=0)
    # handedness and the vertical fov: a point up by tan(fov / 2) x distance lands on the top edge (v = 0), one to the
    # right of the target on the right half
    forward = (target - position) / np.linalg.norm(target - position)
    up_in_view = up - forward * (up @ forward)
    up_in_view /= np.linalg.norm(up_in_view)
    distance = np.linalg.norm(target - position)
    top = target + up_in_view * distance * math.tan(fov / 2)
    right = target + np.cross(forward, up_in_view) * 0.1
    uv, _ = camera.project(torch.tensor(np.stack([top, right])))
    assert abs(float(uv[0, 1])) < 1e-6 and abs(float(uv[0, 0]) - 160.0) < 1e-6
    assert float(uv[1, 0]) > 160.0 and abs(float(uv[1, 1]) - 90.0) < 1e-6
    # a portrait view keeps the long side at max_resolution; camera_to_viser is the inverse
    portrait = viser_to_camera(look_at_wxyz(position, target, up), position, fov, aspect=0.5, max_resolution=320)
    assert (portrait.width, portrait.height) == (160, 320)
    wxyz, back_position, back_fov, aspect = camera_to_viser(camera)
    np.testing.assert_allclose(np.abs(wxyz @ look_at_wxyz(position, target, up)), 1.0, atol=1e-9)
    np.testing.assert_allclose(back_position, position, atol=1e-9)
    assert back_fov == pytest.approx(fov) and aspect == pytest.approx(16 / 9, rel=1e-2)


# ---- the water control ----------------------------------------------------------------------------------------------


def test_the_water_control_at_k_1_is_the_models_uwi_and_at_k_0_the_uri(uw3dgs_run):
    _, datamanager, model, _ = load_trained(uw3dgs_run)
    model.eval()
    camera = datamanager.scene.cameras[datamanager.test_indices[0]]
    with torch.no_grad():
        own = model.get_outputs(camera)
    same = render_outputs(model, camera, Water(k=1.0))
    assert torch.equal(same["rgb"], own["rgb"]) and torch.equal(same["uri"], own["uri"])
    torch.testing.assert_close(render_outputs(model, camera, Water(1.0, learned_b_inf(model)))["rgb"], own["rgb"],
                               atol=1e-6, rtol=0)
    torch.testing.assert_close(same["attenuation"], own["attenuation"])
    assert torch.equal(render_outputs(model, camera, Water(k=0.0))["rgb"], own["uri"])
    murky = render_outputs(model, camera, Water(k=3.0, b_inf=(0.0, 0.5, 0.0)))["rgb"]
    assert (murky - own["rgb"]).abs().max() > 0.05
    for output in ("UWI", "URI", "depth", "attenuation", "backscatter"):
        image = render_image(model, camera, output)
        assert image.dtype == np.uint8 and image.shape == (camera.height, camera.width, 3)
    with pytest.raises(ValueError, match="k must be >= 0"):
        form_with_water(own["uri"], own["alpha"], own["range"], own["beta_d"], own["beta_b"], model.medium.b_inf,
                        model.dataset_scale, Water(k=-1.0))


def test_a_viewer_render_leaves_the_rng_and_the_model_as_they_were(uw3dgs_run):
    _, datamanager, model, _ = load_trained(uw3dgs_run)
    model.train()  # as in training: the PAUP branch and random draws must not run
    state = {k: v.clone() for k, v in model.state_dict().items()}
    rng = torch.get_rng_state()
    render_outputs(model, datamanager.scene.cameras[0], Water(k=2.0))
    assert torch.equal(torch.get_rng_state(), rng)
    assert all(torch.equal(v, state[k]) for k, v in model.state_dict().items())


# ---- uw-train --viewer ----------------------------------------------------------------------------------------------


def fake_client(camera) -> SimpleNamespace:
    """A connected client as viser describes it, looking through `camera`; records the frames sent to it."""
    wxyz, position, fov, aspect = camera_to_viser(camera)
    frames = []
    return SimpleNamespace(client_id=0, frames=frames,
                           camera=SimpleNamespace(wxyz=wxyz, position=position, fov=fov, aspect=aspect,
                                                  image_width=64, image_height=48),
                           scene=SimpleNamespace(set_background_image=lambda image, **_: frames.append(image)))


def test_training_with_the_viewer_rendering_every_step_gives_the_same_numbers(make_config, monkeypatch):
    plain = train(as_uw3dgs(make_config(steps=12, timestamp="plain")))
    client = None
    original = Trainer._start_viewer

    def start(self, console):  # a client rendering after every step, with no time budget
        nonlocal client
        viewer = original(self, console)
        client = fake_client(self.datamanager.scene.cameras[0])
        viewer.server.get_clients = lambda: {0: client}
        viewer.refresh_seconds, viewer.max_share = 0.0, 1.0
        return viewer

    monkeypatch.setattr(Trainer, "_start_viewer", start)
    viewed = train(as_uw3dgs(make_config(steps=12, timestamp="viewed", viewer=True, viewer_port=free_port())))
    assert len(client.frames) == 12 and client.frames[-1].std() > 0
    a = load_checkpoint(latest_checkpoint(plain.run_dir), "cpu")
    b = load_checkpoint(latest_checkpoint(viewed.run_dir), "cpu")
    assert a["model"].keys() == b["model"].keys()
    assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])
    assert torch.equal(a["rng"]["torch"], b["rng"]["torch"])


def test_uw_train_viewer_on_a_port_in_use_names_the_option(make_config):
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        port = sock.getsockname()[1]
        trainer = Trainer(make_config(viewer=True, viewer_port=port))
        with pytest.raises(RuntimeError, match=f"port {port} on 127.0.0.1 is in use.*--viewer-port {port + 1}"):
            trainer.setup()


# ---- uw-viewer: errors ----------------------------------------------------------------------------------------------


def test_uw_viewer_errors_are_one_line(uw3dgs_run, tmp_path, capsys):
    from uw3dgs.cli.viewer import entrypoint

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        port = sock.getsockname()[1]
        code, out, _ = run_command(entrypoint, [str(uw3dgs_run), "--port", str(port)], capsys)
    assert code == 2 and f"port {port} on 127.0.0.1 is in use" in out and f"--port {port + 1}" in out
    bare = tmp_path / "untrained"
    bare.mkdir()
    shutil.copy(uw3dgs_run, bare / "config.yml")
    code, out, _ = run_command(entrypoint, [str(bare / "config.yml"), "--port", str(free_port())], capsys)
    assert code == 2 and "no checkpoint" in out and "train it first" in out


def test_the_gui_water_control_means_the_learned_medium_until_changed(uw3dgs_run):
    from uw3dgs.cli.viewer import ViewerArgs, start_viewer

    viewer = start_viewer(ViewerArgs(load_config=uw3dgs_run, port=free_port(), device="cpu"))
    try:
        assert viewer.water() == Water(k=1.0, b_inf=None)  # the learned B_inf at full precision, not its 8 bits
        assert viewer.output.options == ("UWI", "URI", "depth", "attenuation", "backscatter")
        viewer.water_k.value, viewer.b_inf.value = 0.5, (255, 0, 0)
        assert viewer.water() == Water(k=0.5, b_inf=(1.0, 0.0, 0.0))
        assert not viewer.update()  # no client connected: nothing to render
    finally:
        viewer.stop()


# ---- in a real browser ----------------------------------------------------------------------------------------------


@pytest.fixture
def browser():
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")
    if CHROMIUM is None or CHROMEDRIVER is None:
        pytest.skip("no Chromium or chromedriver (apt-get install chromium chromium-driver)")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=800,600",
                "--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--disable-gpu-sandbox"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)  # no Selenium Manager download
    yield driver
    driver.quit()


def screenshot(driver) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB")).astype(np.float32)


def render_region(image: np.ndarray) -> np.ndarray:
    """The bottom half of the page: the rendered background, away from the GUI panel and notifications."""
    return image[image.shape[0] // 2:]


def wait_for_change(viewer, driver, before: np.ndarray, frames: int, timeout: float = 8.0) -> np.ndarray:
    """A screenshot once a new frame was rendered and the page shows something else than `before`."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if viewer.frames > frames:
            shot = screenshot(driver)
            if np.abs(render_region(shot) - render_region(before)).mean() > 1.0:
                time.sleep(0.3)  # the texture may still be swapping in
                return screenshot(driver)
        time.sleep(0.2)
    raise AssertionError(f"the page did not change within {timeout} s (frames rendered: {viewer.frames})")


def test_the_viewer_page_shows_the_render_and_follows_the_controls(uw3dgs_run, browser):
    from uw3dgs.cli.viewer import ViewerArgs, start_viewer

    viewer = start_viewer(ViewerArgs(load_config=uw3dgs_run, port=free_port(), max_resolution=256, device="cpu"))
    stop = threading.Event()
    loop = threading.Thread(target=viewer.serve_forever, kwargs={"stop": stop}, daemon=True)
    loop.start()
    try:
        browser.get(viewer.url)
        deadline = time.monotonic() + 15
        while viewer.frames == 0 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert viewer.frames > 0, "the browser connected no camera within 15 s"
        time.sleep(1.0)
        uwi = screenshot(browser)
        region = render_region(uwi)
        assert region.std() > 5.0, "the rendered view is blank"
        # viser's empty scene is white; the tiny underwater scene is mostly blue-green water
        assert (region.mean(axis=(0, 1)) < 245).all()
        viewer.output.value = "depth"  # as the dropdown does; the callback marks every client
        depth = wait_for_change(viewer, browser, uwi, viewer.frames)
        viewer.output.value = "UWI"
        back = wait_for_change(viewer, browser, depth, viewer.frames)
        viewer.water_k.value = 0.0  # no water: the URI
        clear = wait_for_change(viewer, browser, back, viewer.frames)
        assert np.abs(render_region(clear) - render_region(back)).mean() > 1.0
        # moving the browser's camera (here from the server: the browser then reports its new camera) renders again
        client = next(iter(viewer.server.get_clients().values()))
        frames = viewer.frames
        client.camera.position = client.camera.position + 0.2 * (client.camera.look_at - client.camera.position)
        deadline = time.monotonic() + 8
        while viewer.frames == frames and time.monotonic() < deadline:
            time.sleep(0.2)
        assert viewer.frames > frames, "moving the camera rendered no new frame"
    finally:
        stop.set()
        loop.join(timeout=5)
        viewer.stop()
