"""The synthetic scene's options (every knob of `uw-synth` and the `synthetic` datamanager) and its cache key."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, fields
from typing import Literal

from uw3dgs.datamanagers.synthetic.water_types import WATER_TYPES
from uw3dgs.options import CheckedConfig, OptionError, check_number

GENERATOR_VERSION = 2
"""Bump when the generator's output changes for an unchanged config: it is part of `cache_key`."""

RGB = tuple[float, float, float]
WaterTypeName = Literal["I", "II", "III", "1C", "3C", "5C", "7C", "9C"]
MediumProfile = Literal["homogeneous", "turbid-bottom", "plume", "gradient"]

RAY_SAMPLES = 128
"""Samples along each ray (midpoint rule) for the ray mean of a spatially varying medium."""


@dataclass(frozen=True)
class SyntheticSceneConfig(CheckedConfig):
    """Everything that defines a synthetic scene; the same config always gives the same bytes."""

    seed: int = 0
    """Seed of every random choice (terrain, texture, poses, points)."""
    num_views: int = 32
    """Number of cameras (images)."""
    width: int = 128
    """Image width in pixels."""
    height: int = 96
    """Image height in pixels."""
    fov_deg: float = 60.0
    """Horizontal field of view in degrees (pinhole, square pixels, principal point at the centre)."""
    path: Literal["forward", "lawnmower", "loop"] = "forward"
    """Camera path: a gently swaying forward pass (like SeaThru-NeRF captures), a lawnmower survey, or a loop
    around the scene centre looking inward (a diver circling a coral head: every view has neighbours on both
    sides, so no test view looks past the end of the path)."""
    altitude: float = 3.0
    """Camera height above the mean seabed, in metres."""
    tilt_deg: float = 55.0
    """Angle of the optical axis from straight down (0 = nadir); above ~50 the image top sees open water
    (as in forward-looking dives), which is where the veiling light B_inf shows on its own."""
    path_length: float = 6.0
    """Length of the forward pass, or of each lawnmower line, in metres."""
    pass_altitudes: tuple[float, ...] = ()
    """A survey that passes over the same seabed at several altitudes (metres), e.g. 3 6: the views are split evenly
    among the passes (in this order), each pass the chosen path at its altitude, moved back along its heading by
    (altitude - `altitude`) tan(tilt_deg) so that its optical axes meet the seabed where the reference pass's do: every
    seabed point is then seen at ranges about as different as the altitudes (what pins the medium from the points'
    colours, fields/medium_multiview.py). Empty: one pass at `altitude`."""
    lawnmower_lines: int = 3
    """Number of parallel lines of the lawnmower path (alternating direction)."""
    line_spacing: float = 1.5
    """Distance between lawnmower lines, in metres."""
    loop_radius: float = 3.0
    """Radius of the loop path, in metres."""
    pose_jitter: float = 0.05
    """Standard deviation of random camera position perturbations, in metres (a real diver wobbles)."""
    angle_jitter_deg: float = 2.0
    """Standard deviation of random yaw, tilt and roll perturbations, in degrees."""
    terrain_size: float = 24.0
    """Side of the square seabed centred on the origin, in metres; rays leaving it see open water."""
    open_water: bool = True
    """Whether rays that leave the seabed square see open water (I = B_inf). False continues the seabed beyond the
    square as its mirror image, so every ray pointing below the horizon meets the seabed (ranges then reach further)
    and the seabed inside the square is unchanged; a view with rays above the horizon is refused (lower tilt_deg)."""
    terrain_resolution: float = 0.02
    """Grid spacing of the height field and texture, in metres (finest texture detail is 2-3 cells)."""
    relief: float = 0.25
    """Standard deviation of the large-scale seabed height (dunes, hollows), in metres."""
    num_rocks: int = 8
    """Number of boulders placed in the area the cameras look at."""
    ripple_amplitude: float = 0.025
    """Amplitude of sand ripples, in metres."""
    ripple_wavelength: float = 0.3
    """Wavelength of sand ripples, in metres."""
    num_specks: int = 400
    """Small colourful objects (shells, starfish, sponges) scattered over the viewed area."""
    num_dark_patches: int = 60
    """Near-black patches (sea-urchin clusters, dark sponges, crevices) over the viewed area: where the clean
    radiance is ~0 an underwater pixel shows the backscatter alone, which is what makes beta_B readable."""
    dark_patch_radius: tuple[float, float] = (0.1, 0.3)
    """Range of the dark patches' radii, in metres."""
    dark_patch_albedo: float = 0.03
    """Albedo of the dark patches (all channels)."""
    sun_elevation_deg: float = 60.0
    """Elevation of the directional light above the horizon, in degrees."""
    sun_azimuth_deg: float = 30.0
    """Azimuth of the directional light, counter-clockwise from +x, in degrees."""
    ambient: float = 0.35
    """Share of ambient light in the baked Lambertian shading (the rest comes from the sun)."""
    supersample: int = 2
    """Rays per pixel along each axis (2 = 2x2) averaged for the clean radiance, against aliasing."""
    march_steps: int = 64
    """Ray-marching samples per ray between the top and bottom of the terrain, before bisection."""
    beta_D: RGB = (0.40, 0.20, 0.12)
    """Direct-signal attenuation coefficients (R, G, B) per metre; red attenuates most."""
    beta_B: RGB = (0.30, 0.25, 0.20)
    """Backscatter coefficients (R, G, B) per metre."""
    B_inf: RGB = (0.05, 0.25, 0.35)
    """Veiling light (backscatter at infinite range), RGB in [0, 1]."""
    medium_strength: float = 1.0
    """Multiplier on both beta_D and beta_B (0 = clear water)."""
    water_type: WaterTypeName | None = None
    """A Jerlov water type (oceanic I, II, III; coastal 1C, 3C, 5C, 7C, 9C) whose published coefficients replace
    beta_D, beta_B and B_inf (leave those at their defaults): beta_D = beta_B = K_d (Jerlov 1976, Table XXVII) and
    B_inf = water_light x b / (a + b) (Solonenko & Mobley 2015), read at 600, 525, 475 nm for R, G, B
    (datamanagers/synthetic/water_types.py). None keeps the hand-set medium above."""
    water_light: float = 1.0
    """With water_type: the level E of the light in the water, B_inf = E b / (a + b) (Akkaynak & Treibitz 2018);
    1 = the white light of level 1 that lights the seabed's clean radiance (white-balanced images)."""
    medium_profile: MediumProfile = "homogeneous"
    """How beta_D and beta_B vary in space: both are the reference medium (above, or the water type's) times a
    factor f(x) >= 1. 'homogeneous': f = 1. 'turbid-bottom': f = 1 + gain exp(-max(z, 0) / turbid_height), z the
    height above the mean seabed (turbidity grows towards the seabed). 'plume': f = 1 + gain exp(-|x -
    plume_center|^2 / (2 plume_radius^2)), a Gaussian cloud. 'gradient': a smooth horizontal step (gradient_*).
    A pixel sees the mean of beta along its ray from the
    camera to the seabed (the method's model); B_inf stays one colour."""
    medium_profile_gain: float = 3.0
    """gain of medium_profile: beta at the seabed (turbid-bottom) or the plume's centre is (1 + gain) x reference."""
    turbid_height: float = 1.0
    """turbid-bottom: height above the mean seabed over which the extra turbidity falls by e, in metres."""
    plume_radius: float = 2.0
    """plume: standard deviation of the Gaussian cloud, in metres."""
    plume_center: tuple[float, float, float] = (0.0, 4.0, 1.0)
    """plume: centre (x, y, z) in metres (the default is where the forward path's cameras look)."""
    gradient_azimuth_deg: float = 0.0
    """gradient: the horizontal direction along which the water thickens, counter-clockwise from +x, in degrees."""
    gradient_length: float = 2.0
    """gradient: f = 1 + gain (1 + tanh(s / length)) / 2, s the horizontal distance (metres) past `gradient_center`
    along the direction: a smooth step of about 2 length metres from clear (f = 1) to turbid (1 + gain)."""
    gradient_center: tuple[float, float] = (0.0, 4.0)
    """gradient: the horizontal point (x, y) in metres where f is halfway (the default is where the forward path's
    cameras look)."""
    num_points: int = 4000
    """Number of SfM-like initial points written to points3D.bin (outliers included)."""
    point_noise: float = 0.01
    """Standard deviation of the points' position noise, as a fraction of the median range of all pixels."""
    outlier_fraction: float = 0.05
    """Share of points that are outliers scattered in the camera frusta between the near and far range."""
    marine_snow: int = 0
    """Marine snow: transient particles per view (0 = none, the default). Each is a small bright disc drawn into
    one underwater image only (Images_wb/), like a suspended particle lit by the strobe for one frame: a method
    that trusts every view grows floaters for them. Clean images, ranges, the medium and the SfM points stay
    those of the snow-free scene; the particles are listed in gt/marine_snow.json. Drawn from their own random
    stream: the rest of the scene is the same with or without snow."""
    marine_snow_range: tuple[float, float] = (0.75, 3.0)
    """Range of the particles' distances from the camera, in metres (a strobe lights the water near the camera);
    a particle is always in front of the seabed seen through its pixel (the far end stops there)."""
    marine_snow_radius: tuple[float, float] = (0.015, 0.03)
    """Range of the particles' radii, in metres. The apparent radius is r f / range pixels (f the focal length
    in pixels, 111 at the default 128 px width: 1-9 px across with the default ranges, 2.6 px typically)."""
    marine_snow_brightness: float = 1.0
    """Clean radiance J of a particle (grey, all channels; 1 = white), seen through the water between it and
    the camera like any object: J exp(-beta_D z) + B_inf (1 - exp(-beta_B z)) at its range z."""

    def check_options(self) -> None:
        """Reject settings the generator cannot honour, naming the knob (they usually come from flags)."""
        check_number(self, "seed", ge=0, integer=True)
        for name in ("num_views", "width", "height", "supersample", "lawnmower_lines", "num_points"):
            check_number(self, name, ge=1, integer=True)
        for name in ("num_rocks", "num_specks", "num_dark_patches"):
            check_number(self, name, ge=0, integer=True)
        check_number(self, "march_steps", ge=2, integer=True)
        for name in ("terrain_size", "terrain_resolution", "ripple_wavelength", "altitude", "loop_radius"):
            check_number(self, name, gt=0)
        for name in ("path_length", "line_spacing", "pose_jitter", "angle_jitter_deg", "relief", "ripple_amplitude",
                     "point_noise", "medium_strength"):
            check_number(self, name, ge=0)
        check_number(self, "fov_deg", gt=0, lt=180)
        check_number(self, "tilt_deg", ge=0, le=90)
        check_number(self, "sun_elevation_deg", gt=0, le=90)
        check_number(self, "sun_azimuth_deg")
        for name in ("ambient", "dark_patch_albedo", "outlier_fraction"):
            check_number(self, name, ge=0, le=1)
        for name in ("beta_D", "beta_B"):
            check_number(self, name, ge=0, each=True)
        check_number(self, "B_inf", ge=0, le=1, each=True)
        check_number(self, "dark_patch_radius", gt=0, each=True)
        if self.dark_patch_radius[0] > self.dark_patch_radius[1]:
            raise OptionError("dark_patch_radius", f"must be (smallest, largest), got {self.dark_patch_radius}")
        check_number(self, "marine_snow", ge=0, integer=True)
        for name in ("marine_snow_range", "marine_snow_radius"):
            check_number(self, name, gt=0, each=True)
            low, high = getattr(self, name)
            if low > high:
                raise OptionError(name, f"must be (smallest, largest), got {(low, high)}")
        check_number(self, "marine_snow_brightness", ge=0, le=1)
        check_number(self, "water_light", ge=0, le=1)
        if self.water_type is None and self.water_light != 1.0:
            raise OptionError("water_light", "only applies with water_type (the hand-set B_inf is used as it is)")
        if self.water_type is not None:
            if self.water_type not in WATER_TYPES:
                raise OptionError("water_type", f"must be one of {', '.join(WATER_TYPES)} (or None), "
                                                f"got {self.water_type!r}")
            defaults = {f.name: f.default for f in fields(self)}
            for name in ("beta_D", "beta_B", "B_inf"):
                if tuple(getattr(self, name)) != defaults[name]:
                    raise OptionError(name, f"cannot be set together with water_type (the water type "
                                            f"{self.water_type} sets beta_D, beta_B and B_inf)")
        check_number(self, "pass_altitudes", gt=0, each=True)
        if len(self.pass_altitudes) > self.num_views:
            raise OptionError("pass_altitudes", f"has {len(self.pass_altitudes)} passes for {self.num_views} views: "
                                                "give at most one pass per view")
        check_number(self, "gradient_azimuth_deg")
        check_number(self, "gradient_length", gt=0)
        check_number(self, "gradient_center", each=True)
        if self.medium_profile not in ("homogeneous", "turbid-bottom", "plume", "gradient"):
            raise OptionError("medium_profile", "must be one of homogeneous, turbid-bottom, plume, gradient, "
                                                f"got {self.medium_profile!r}")
        check_number(self, "medium_profile_gain", ge=0)
        for name in ("turbid_height", "plume_radius"):
            check_number(self, name, gt=0)
        check_number(self, "plume_center", each=True)


def config_record(config: SyntheticSceneConfig) -> dict:
    """The config as written to gt/medium.json and hashed by `cache_key`. Knobs of an option that is off change
    nothing and are left out (marine snow, water type, open water, medium profile), so scenes without the option
    keep the keys and bytes they had before it existed."""
    record = asdict(config)
    unused = []
    if config.marine_snow == 0:
        unused += ["marine_snow", "marine_snow_range", "marine_snow_radius", "marine_snow_brightness"]
    if config.water_type is None:
        unused += ["water_type", "water_light"]
    if config.open_water:
        unused.append("open_water")
    if config.medium_profile != "turbid-bottom":
        unused.append("turbid_height")
    if config.medium_profile != "plume":
        unused += ["plume_radius", "plume_center"]
    if config.medium_profile != "gradient":
        unused += ["gradient_azimuth_deg", "gradient_length", "gradient_center"]
    if not config.pass_altitudes:
        unused.append("pass_altitudes")
    if config.medium_profile == "homogeneous":
        unused += ["medium_profile", "medium_profile_gain"]
    for name in unused:
        del record[name]
    return record


def cache_key(config: SyntheticSceneConfig) -> str:
    """A short stable hash of the config and the generator version, to name a cache folder."""
    payload = json.dumps({"version": GENERATOR_VERSION, "config": config_record(config)}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:12]
