"""How much `uw-train --viewer` slows training:

    python benchmarks/speed/viewer_slowdown.py [--steps 1000] [--repeats 2] [--browser]


Trains `uw3dgs` on the built-in synthetic scene (CPU) once per setting and prints one JSON line each: steps/s of the
training loop (RUN/train_time.json), frames rendered for the viewer and their seconds. Settings: 'off' (no viewer),
'noclient' (--viewer, nobody looking), 'simulated' (a client with a 1000 x 700 canvas looking through the first
training view: frames rendered at --max-resolution and JPEG-encoded in the loop, no browser), and with --browser
'browser' (headless Chromium connected on this machine: it also competes for the CPU). docs/viewer.md has the numbers.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import threading
from pathlib import Path
from types import SimpleNamespace

from uw3dgs.engine.trainer import Trainer
from uw3dgs.registry import METHODS
from uw3dgs.viewer.camera import camera_to_viser


def simulate_client(viewer, camera) -> None:
    """Make `viewer` see one client looking through `camera` with a 1000 x 700 canvas; its frames are encoded and
    queued as a real client's are."""
    wxyz, position, fov, _ = camera_to_viser(camera)
    scene = SimpleNamespace(set_background_image=viewer.server.scene.set_background_image)
    client = SimpleNamespace(client_id=0, scene=scene, camera=SimpleNamespace(
        wxyz=wxyz, position=position, fov=fov, aspect=1000 / 700, image_width=1000, image_height=700))
    viewer.server.get_clients = lambda: {0: client}


def open_browser(url: str, holder: dict) -> None:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1000,700",
                "--enable-unsafe-swiftshader", "--use-angle=swiftshader"):
        options.add_argument(arg)
    holder["driver"] = driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
    driver.get(url)


def process_tree_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process `pid` and its descendants (Linux /proc; 0 where unreadable)."""
    import os

    total, pending = 0.0, [pid]
    while pending:
        current = pending.pop()
        try:
            fields = Path(f"/proc/{current}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            for task in Path(f"/proc/{current}/task").iterdir():
                pending += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError, IndexError):
            continue
    return total


def measure(setting: str, steps: int, output_dir: Path, port: int) -> dict:
    config = dataclasses.replace(METHODS["uw3dgs"].config, max_num_iterations=steps, output_dir=output_dir,
                                 timestamp=setting, progress=False, device="cpu", steps_per_eval_image=10**9,
                                 steps_per_eval_all_images=10**9, steps_per_save=10**9, viewer=setting != "off",
                                 viewer_port=port)
    held: dict = {}
    original = Trainer._start_viewer

    def start(trainer: Trainer, console) -> object:
        viewer = held["viewer"] = original(trainer, console)
        if setting == "simulated":
            simulate_client(viewer, trainer.datamanager.scene.cameras[trainer.datamanager.train_indices[0]])
        elif setting == "browser":
            threading.Thread(target=open_browser, args=(viewer.url, held), daemon=True).start()
        return viewer

    Trainer._start_viewer = start
    try:
        trainer = Trainer(config)
        trainer.setup()
        trainer.train()
    finally:
        Trainer._start_viewer = original
        if "driver" in held:
            held["browser_cpu_seconds"] = process_tree_cpu_seconds(held["driver"].service.process.pid)
            held["driver"].quit()
    seconds = json.loads((trainer.run_dir / "train_time.json").read_text())["train_seconds"]
    viewer = held.get("viewer")
    return {"setting": setting, "steps": steps, "train_seconds": round(seconds, 2),
            "steps_per_s": round(steps / seconds, 2), "frames": getattr(viewer, "frames", 0),
            "render_seconds": round(getattr(viewer, "render_seconds", 0.0), 2),
            **({"browser_cpu_seconds": round(held["browser_cpu_seconds"], 1)} if "browser_cpu_seconds" in held else {})}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--port", type=int, default=7311)
    parser.add_argument("--browser", action="store_true", help="also with headless Chromium connected")
    args = parser.parse_args()
    settings = ["off", "noclient", "simulated"] + (["browser"] if args.browser else [])
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            for setting in settings:
                result = measure(setting, args.steps, Path(tmp) / str(repeat), args.port)
                print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
