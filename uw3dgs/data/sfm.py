"""Structure from motion with pycolmap for a folder of images: SIFT features (CPU), matching, incremental mapping.

    run_sfm(image_dir, work_dir, camera=None, matcher="exhaustive") -> work_dir/sparse/0

`camera` fixes the intrinsics when they are known (a calibration): one `FixedCamera` for every image, or one
per subfolder (`{"left": ..., "right": ...}` for a stereo rig). Fixed intrinsics are never refined by
bundle adjustment. Without it, COLMAP estimates one camera for all images (or one per image).

The largest reconstruction is kept. Too few registered images raise `SfmError` with what to try.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pycolmap
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

from uw3dgs.utils.console import CONSOLE, info, warn
from uw3dgs.utils.images import image_size

Matcher = Literal["exhaustive", "sequential"]
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
EXTRACTION_CHUNK = 16
"""Images per feature-extraction call: small enough for a live progress bar, large enough to keep threads busy."""
MATCH_BLOCK_PAIRS = 256
"""Image pairs per matching call, for the same reason."""


class SfmError(RuntimeError):
    """Structure from motion could not pose enough images; the message says how many and what to try."""


def _num_params(model: str) -> int | None:
    """Number of parameters of a COLMAP camera model, None for an unknown name."""
    try:
        return len(pycolmap.Camera.create_from_model_name(1, model, 1.0, 1, 1).params)
    except Exception:  # pycolmap raises a bare error for unknown model names
        return None


@dataclass(frozen=True)
class FixedCamera:
    """Known intrinsics of the camera that took a set of images, in COLMAP's model and parameter order
    (e.g. OPENCV: fx, fy, cx, cy, k1, k2, p1, p2), COLMAP pixel convention (top-left pixel centre at 0.5, 0.5)."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        expected = _num_params(self.model)
        if expected is None:
            raise ValueError(f"unknown COLMAP camera model {self.model!r}")
        if len(self.params) != expected:
            raise ValueError(f"camera model {self.model} takes {expected} parameters, got {len(self.params)}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")

    def to_pycolmap(self, camera_id: int = 1) -> pycolmap.Camera:
        camera = pycolmap.Camera(model=self.model, width=self.width, height=self.height,
                                 params=list(self.params), camera_id=camera_id)
        camera.has_prior_focal_length = True
        return camera

    def rescaled(self, width: int, height: int) -> FixedCamera:
        """The same camera for images resized to width x height (same aspect ratio): focal lengths and
        principal point scale, distortion (in normalised coordinates) does not."""
        sx, sy = width / self.width, height / self.height
        if abs(sx - sy) > 1e-3 * max(sx, sy):
            raise ValueError(f"cannot rescale a {self.width}x{self.height} calibration to {width}x{height}: "
                             "the aspect ratio differs (cropped images?)")
        camera = self.to_pycolmap()
        camera.rescale(width, height)
        return FixedCamera(self.model, width, height, tuple(float(p) for p in camera.params))


def list_images(image_dir: Path) -> list[str]:
    """Image files under `image_dir` (recursively, hidden files and folders skipped), as sorted relative
    POSIX paths: the names COLMAP gives them."""
    names = []
    for path in Path(image_dir).rglob("*"):
        rel = path.relative_to(image_dir)
        if any(part.startswith(".") for part in rel.parts):
            continue
        if path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS:
            names.append(rel.as_posix())
    return sorted(names)


@contextlib.contextmanager
def quiet_colmap(verbose: bool = False) -> Iterator[None]:
    """Silence COLMAP's (glog) INFO and WARNING lines for the duration; errors still show."""
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = previous if verbose else max(previous, 2)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def _progress(enabled: bool) -> Progress:
    return Progress(SpinnerColumn(), TextColumn("[progress.description]{task.description}"), BarColumn(),
                    MofNCompleteColumn(), TimeElapsedColumn(), console=CONSOLE, disable=not enabled, transient=False)


def _group_by_camera(names: Sequence[str], camera: FixedCamera | Mapping[str, FixedCamera] | None,
                     image_dir: Path) -> list[tuple[FixedCamera | None, list[str]]]:
    """Split the images by the camera that took them, checking fixed intrinsics against the image sizes."""
    if camera is None or isinstance(camera, FixedCamera):
        groups: list[tuple[FixedCamera | None, list[str]]] = [(camera, list(names))]
    else:
        groups = []
        folders = {name.split("/")[0] if "/" in name else "" for name in names}
        unknown = sorted(folders - set(camera))
        if unknown:
            raise ValueError(f"{image_dir}: images in {', '.join(repr(f + '/') for f in unknown)} but fixed "
                             f"intrinsics only for {', '.join(repr(f + '/') for f in camera)}")
        for folder, cam in camera.items():
            group = [n for n in names if n.startswith(folder + "/")]
            if group:
                groups.append((cam, group))
    for cam, group in groups:
        if cam is None:
            continue
        for name in group:
            size = image_size(image_dir / name)
            if size != (cam.width, cam.height):
                raise ValueError(f"{image_dir / name}: {size[0]}x{size[1]} pixels but its calibration is for "
                                 f"{cam.width}x{cam.height}; use the calibration of these images (or rescale it)")
    return groups


def _extract(database: Path, image_dir: Path, groups: list[tuple[FixedCamera | None, list[str]]],
             camera_model: str, single_camera: bool, num_threads: int, max_image_size: int, bar: Progress) -> None:
    task = bar.add_task("extracting features", total=sum(len(g) for _, g in groups))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.max_image_size = max_image_size
    extraction.sift.max_num_features = 8192
    for cam, group in groups:
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        mode = pycolmap.CameraMode.SINGLE
        if cam is not None:
            with pycolmap.Database.open(str(database)) as db:
                reader.existing_camera_id = db.write_camera(cam.to_pycolmap())
        elif not single_camera:
            mode = pycolmap.CameraMode.PER_IMAGE
        for start in range(0, len(group), EXTRACTION_CHUNK):
            chunk = group[start : start + EXTRACTION_CHUNK]
            pycolmap.extract_features(database, image_dir, image_names=chunk, camera_mode=mode,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu)
            if mode == pycolmap.CameraMode.SINGLE and reader.existing_camera_id < 0:
                with pycolmap.Database.open(str(database)) as db:  # later chunks share the first chunk's camera
                    reader.existing_camera_id = db.read_image_with_name(chunk[0]).camera_id
            bar.advance(task, len(chunk))
    with pycolmap.Database.open(str(database)) as db:
        read = {image.name for image in db.read_all_images()}
    missing = [n for _, g in groups for n in g if n not in read]
    if missing:
        raise SfmError(f"COLMAP could not read {len(missing)} image(s), e.g. {image_dir / missing[0]}; "
                       "re-export them (8-bit PNG or JPEG) or remove them from the folder")


def sequential_pairs(names: Sequence[str], overlap: int,
                     key: Callable[[str], str] | None = None) -> list[tuple[str, str]]:
    """COLMAP's sequential pairing (each step with the next `overlap` steps and, as its quadratic overlap, the
    steps 2, 4, 8, ... 2^(overlap-1) ahead), over steps of images that share `key(name)`: with a key that drops
    the camera folder, both images of a stereo pair are one step, matched together and with their neighbours."""
    key = key or (lambda name: name)
    steps: dict[str, list[str]] = {}
    for name in sorted(names):
        steps.setdefault(key(name), []).append(name)
    order = [steps[k] for k in sorted(steps)]
    distances = sorted(set(range(1, overlap + 1)) | {2**i for i in range(overlap)})
    pairs = [(a, b) for group in order for i, a in enumerate(group) for b in group[i + 1 :]]
    for i, group in enumerate(order):
        for d in distances:
            if i + d < len(order):
                pairs += [(a, b) for a in group for b in order[i + d]]
    return pairs


def _match(database: Path, work_dir: Path, names: Sequence[str], matcher: Matcher, overlap: int,
           sequence_key: Callable[[str], str] | None, num_threads: int, bar: Progress) -> None:
    """Match the image pairs (every pair, or `sequential_pairs`) as explicit pair lists of MATCH_BLOCK_PAIRS pairs
    each, so the bar counts pairs (exhaustive matching is one call otherwise, silent for minutes)."""
    if matcher == "exhaustive":
        pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    else:  # stereo partners count as one step
        pairs = list(sequential_pairs(names, overlap, sequence_key))
    task = bar.add_task(f"matching ({matcher}, pairs)", total=len(pairs))
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = num_threads
    pair_file = work_dir / "pairs.txt"
    for start in range(0, len(pairs), MATCH_BLOCK_PAIRS):
        block = pairs[start:start + MATCH_BLOCK_PAIRS]
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in block))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pair_file)
        pycolmap.match_image_pairs(database, matching_options=options, pairing_options=pairing,
                                   device=pycolmap.Device.cpu)
        bar.advance(task, len(block))


def _mapping_options(fixed_intrinsics: bool, seed: int, num_threads: int) -> pycolmap.IncrementalPipelineOptions:
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.mapper.random_seed = seed
    options.triangulation.random_seed = seed
    options.num_threads = num_threads
    options.min_model_size = 2  # report small models too: the caller decides (and says) what is too few
    if fixed_intrinsics:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        options.mapper.abs_pose_refine_focal_length = False
        options.mapper.abs_pose_refine_extra_params = False
    return options


def _map(database: Path, image_dir: Path, out: Path, options: pycolmap.IncrementalPipelineOptions,
         num_images: int, bar: Progress, label: str) -> dict[int, pycolmap.Reconstruction]:
    task = bar.add_task(label, total=num_images)
    registered = [0]

    def next_image() -> None:
        registered[0] += 1
        bar.update(task, completed=min(registered[0], num_images))

    def initial_pair() -> None:
        registered[0] = 2
        bar.update(task, completed=min(2, num_images))

    reconstructions = pycolmap.incremental_mapping(database, image_dir, out, options=options,
                                                   initial_image_pair_callback=initial_pair,
                                                   next_image_callback=next_image)
    best = max((r.num_reg_images() for r in reconstructions.values()), default=0)
    bar.update(task, completed=best)
    bar.stop_task(task)
    return reconstructions


def too_few_message(registered: int, total: int, needed: int, image_dir: Path, matcher: Matcher) -> str:
    other = "sequential" if matcher == "exhaustive" else "exhaustive"
    return (
        f"structure from motion registered only {registered} of {total} images in {image_dir} "
        f"(need at least {needed}). The images probably overlap too little, are too blurry or too murky for "
        f"feature matching. Try: more overlap between neighbouring shots (60-80%), more frames (a smaller "
        f"--every-n for video), the {other} matcher (sequential suits video frames in capture order, "
        f"exhaustive suits unordered photos), or removing images without texture (open water, sand only)."
    )


def run_sfm(
    image_dir: Path,
    work_dir: Path,
    camera: FixedCamera | Mapping[str, FixedCamera] | None = None,
    matcher: Matcher = "exhaustive",
    progress: bool = True,
    *,
    image_names: Sequence[str] | None = None,
    camera_model: str = "SIMPLE_RADIAL",
    single_camera: bool = True,
    min_registered_fraction: float = 0.5,
    sequential_overlap: int = 10,
    sequence_key: Callable[[str], str] | None = None,
    max_image_size: int = 3200,
    num_threads: int = -1,
    seed: int = 0,
    quality_check: Callable[[pycolmap.Reconstruction], tuple[float, str]] | None = None,
    attempts: int = 3,
    verbose: bool = False,
) -> Path:
    """Pose the images of `image_dir` (searched recursively) and return the sparse model folder
    `work_dir/sparse/0` (the largest reconstruction; `work_dir/database.db` keeps features and matches).

    camera: fixed intrinsics, one for all images or one per top-level subfolder; None = self-calibration
    with `camera_model` (one shared camera, or one per image when `single_camera` is False).
    image_names: the images to use (relative to image_dir); default every image found.
    matcher: "exhaustive" (every pair; unordered photos, up to a few hundred images) or "sequential"
    (each image with its `sequential_overlap` successors by name, and quadratic jumps; video frames).
    sequence_key: for "sequential", images with the same key form one step (e.g. a stereo pair).
    Raises SfmError when fewer than 2 images, or fewer than `min_registered_fraction` of them, register.

    quality_check: an independent test of the model (e.g. a stereo rig's known baseline) returning (badness,
    why); above 1 the mapping is re-run with another seed (incremental SfM can settle in a wrong local
    minimum), up to `attempts` times, keeping the first model that passes, else the least bad one.
    """
    image_dir, work_dir = Path(image_dir), Path(work_dir)
    if matcher not in ("exhaustive", "sequential"):
        raise ValueError(f"matcher must be 'exhaustive' or 'sequential', got {matcher!r}")
    if not image_dir.is_dir():
        raise FileNotFoundError(f"{image_dir}: no such image folder")
    names = list(image_names) if image_names is not None else list_images(image_dir)
    if len(names) < 2:
        raise SfmError(f"{image_dir}: {len(names)} image(s) found ({', '.join(IMAGE_EXTENSIONS)}); "
                       "structure from motion needs at least 2 overlapping images, better 20 or more")
    missing = [n for n in names if not (image_dir / n).is_file()]
    if missing:
        raise FileNotFoundError(f"{image_dir / missing[0]}: no such image ({len(missing)} missing)")
    if camera is None and _num_params(camera_model) is None:
        raise ValueError(f"unknown COLMAP camera model {camera_model!r} (e.g. SIMPLE_RADIAL, RADIAL, OPENCV, PINHOLE)")
    groups = _group_by_camera(names, camera, image_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    database.unlink(missing_ok=True)  # features of another image set must not leak into this run
    mapping_dir = work_dir / "mapping"
    shutil.rmtree(mapping_dir, ignore_errors=True)
    mapping_dir.mkdir()
    sparse_dir = work_dir / "sparse" / "0"
    pycolmap.set_random_seed(seed)
    start = time.perf_counter()
    with quiet_colmap(verbose), _progress(progress) as bar:
        _extract(database, image_dir, groups, camera_model, single_camera, num_threads, max_image_size, bar)
        _match(database, work_dir, names, matcher, sequential_overlap, sequence_key, num_threads, bar)
        needed = max(2, math.ceil(min_registered_fraction * len(names)))
        tried: list[tuple[float, int, pycolmap.Reconstruction, str]] = []
        for attempt in range(max(1, attempts) if quality_check is not None else 1):
            options = _mapping_options(camera is not None, seed + attempt, num_threads)
            shutil.rmtree(mapping_dir, ignore_errors=True)
            mapping_dir.mkdir()
            label = "mapping (registered images)" if not tried else f"mapping again ({tried[-1][3]})"
            reconstructions = _map(database, image_dir, mapping_dir, options, len(names), bar, label)
            best = max(reconstructions.values(), key=lambda r: r.num_reg_images(), default=None)
            if best is None or best.num_reg_images() < needed:
                if tried:
                    continue  # a retry that failed outright: an earlier model is still there
                registered = best.num_reg_images() if best is not None else 0
                raise SfmError(too_few_message(registered, len(names), needed, image_dir, matcher))
            badness, why = quality_check(best) if quality_check is not None else (0.0, "")
            tried.append((badness, attempt, best, why))
            if badness <= 1.0:
                break
    badness, _, best, why = min(tried, key=lambda item: item[:2])
    if badness > 1.0:
        warn(f"structure from motion: {why} after {len(tried)} attempts; keeping the most consistent model")
    shutil.rmtree(sparse_dir, ignore_errors=True)
    sparse_dir.mkdir(parents=True)
    best.write_binary(str(sparse_dir))
    shutil.rmtree(mapping_dir, ignore_errors=True)
    if progress:
        info(f"structure from motion: {best.num_reg_images()} of {len(names)} images registered, "
             f"{best.num_points3D()} points, {time.perf_counter() - start:.1f} s")
    return sparse_dir
