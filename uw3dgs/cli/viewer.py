"""`uw-viewer RUN/config.yml`: look at a trained run in the browser (viser), with the output switch (UWI, URI,
depth, attenuation, backscatter) and the water control; docs/viewer.md."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import tyro
from rich.console import Console

from uw3dgs.cli.errors import report_user_errors
from uw3dgs.utils.console import info, route_warnings


@dataclass(frozen=True)
class ViewerArgs:
    load_config: tyro.conf.Positional[Path]
    """The run's config.yml (outputs/<scene>/<method>/<timestamp>/config.yml)."""
    port: int = 7007
    """Port of the web server (http://HOST:PORT)."""
    host: str = "127.0.0.1"
    """Address to listen on; 127.0.0.1 (default) is this machine only (reach it from elsewhere with ssh -L), 0.0.0.0
    every network interface."""
    max_resolution: int = 512
    """Long side in pixels of a rendered frame (at most the browser's canvas); smaller is faster."""
    step: int | None = None
    """Show the checkpoint of this step instead of the latest."""
    camera_images: bool = True
    """Show the dataset images in the camera frustums (False: the poses only)."""
    device: str = "auto"
    """Where the model renders: cpu, cuda, or auto (CUDA when PyTorch sees it)."""


def start_viewer(args: ViewerArgs):
    """Load the run and start the server (returns the `Viewer`; the caller serves or stops it)."""
    from uw3dgs.engine.evaluator import load_trained
    from uw3dgs.engine.trainer import resolve_device
    from uw3dgs.viewer.server import Viewer, check_port, require_viser, views_from_datamanager

    if args.max_resolution < 16:
        raise ValueError(f"--max-resolution must be at least 16, got {args.max_resolution}")
    require_viser()
    check_port(args.host, args.port)  # before loading the run, which may take long
    device = resolve_device(args.device)
    config, datamanager, model, checkpoint = load_trained(args.load_config, device, step=args.step)
    if model.rays_per_batch() is not None:
        raise ValueError(f"{args.load_config}: the viewer shows Gaussian models; render a ray-marched radiance field "
                         f"({config.method_name}) with uw-render")
    model.eval()
    title = f"{config.experiment_name or datamanager.scene_name} / {config.method_name}"
    viewer = Viewer(model, views_from_datamanager(datamanager, images=args.camera_images), host=args.host,
                    port=args.port, max_resolution=args.max_resolution, title=title)
    info(f"{title}: {checkpoint.name}, {model.num_gaussians:,} Gaussians")
    return viewer


def entrypoint(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    route_warnings()
    args = tyro.cli(ViewerArgs, args=argv, prog="uw-viewer", description=__doc__)
    from uw3dgs.engine.signals import sigterm_as_interrupt

    viewer = report_user_errors(lambda: start_viewer(args))
    try:
        # after loading the run (pycolmap installs its own SIGTERM handler), before the address is announced
        with sigterm_as_interrupt():
            Console().print(f"viewer at {viewer.url} (Ctrl-C to stop)", soft_wrap=True, highlight=False)
            viewer.serve_forever()
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the usual ways to stop a server
        Console().print("Stopped.")
    finally:
        viewer.stop()


if __name__ == "__main__":
    entrypoint()
