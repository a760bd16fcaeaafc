"""What every layer of the render client shades with: the sun, colours, fog, sky.

One :class:`Frame` is built per rendered frame and handed to every layer's
``draw``; :data:`GLSL_COMMON` is the shader code they share.

Lighting (thesis §3.1.7 shades its clipmap with "simple phong lighting"): a
directional sun plus a constant ambient term, Lambert diffuse
(colour = albedo x (AMBIENT + SUN x max(n . l, 0)), the split of
sortie/demo.py's hillshade: 0.35 + 0.65 x shade), and a Blinn-Phong specular
highlight on water only (Blinn, "Models of light reflection for computer
synthesized pictures", SIGGRAPH 1977).

The sun is one of two. Fixed (``sortie render`` without ``--time``, and a
``Renderer`` given no ``sun_time``): an azimuth and elevation in the sky of the
local origin (from the north-west, 45 degrees up, by default), fixed in the
local sky as the origin moves. Or the sun of an instant (``Renderer.sun_time``:
a live exercise's or a replay's start_time + world time, ``sortie render
--time``): terrain/sun.py's apparent sun (NOAA/Meeus, refraction included, as
``sortie terrain texture`` lights by default) in the sky of the camera's
position, turned into ECEF (:func:`sun_direction_ecef`) and recomputed once
SUN_UPDATE_S of that time has passed (:class:`EphemerisSun`). With the sun at
or below the camera's horizon there is no direct light (``Frame.sun_light``
0: no diffuse term, no specular glint, no sun disc): the terrain is lit by the
ambient term alone, as terrain/texture.py's light map has no directional term
then, never black and never from below (max(n . l, 0) alone would light a
slope facing a sun under the horizon).

Colour by height and slope (virtual-terrain-generation: "points located
above a limit and parts of steep mountains are colored like rocks, the rest
like grass"): sortie/demo.py's hypsometric tint (green, brown, snow) on
absolute heights MSL, blended to rock on slopes between ROCK_SLOPE_DEG. A
fragment whose interpolated height is <= the water level (``Frame.water_level_m``)
is water (the seeds' rule: water at sea level; a DEM has no water mask). The
water level is 0 m MSL over a DEM, a lossless store or a procedural world, and
half the step over a lossy terrain store (:func:`water_level_m`): such a store
decodes a sea at 0 m anywhere within s/2 of it, so it cannot tell the sea from
ground at s/2 (docs/STORE.md), and ``sortie terrain texture`` draws posts within
s/2 of sea level as water (terrain/texture.py) for the same reason.

Fog: squared exponential, f = exp(-(density x distance)^2) (OpenGL 2.1
specification, §3.10 "Fog", GL_EXP2), colour = mix(fog colour, lit colour,
f), distance the horizontal distance from the camera (the eye-to-point vector
less its part along the camera's local vertical): the fog hides where the
terrain ends round the camera, and the ground straight below a camera high up
stays clear (with the Euclidean distance, a camera 10,000 km up saw only fog).
The density makes the mesh's nearest far edge invisible to 8 bits (f = 1/255
there: density = sqrt(ln 255) / distance). GL_EXP2 rather than GL_EXP: hiding an edge at
distance D with exp(-k d) already costs 25 % of the contrast at D / 4 and
63 % at D / 2.3; exp(-(k d)^2) keeps 92 % at D / 4 and fades over the last
half. The fog colour is the sky's horizon colour, so fogged terrain meets
the sky seamlessly.

Sky: an empirical gradient, not a physical model: horizon colour at and below
the local horizontal, blending to the zenith colour as sin(elevation)^SKY_EXPONENT,
plus a sun disc and glow (a cosine power). In test mode (``flat_sky_rgb``) the
sky is one exact colour and fog is off, so a sky pixel is recognisable bit
for bit (the holes check).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np

from client.render.camera import Camera, LocalOrigin
from sortie.errors import InvalidArgument

DEFAULT_SUN_AZIMUTH_DEG = 315.0  # sortie/demo.py's hillshade: light from the north-west
DEFAULT_SUN_ELEVATION_DEG = 45.0
AMBIENT = 0.35
SUN = 0.65
FOG_EDGE_TRANSMITTANCE = 1.0 / 255.0  # what is left of the far edge's colour: below 8 bits
SKY_ZENITH_RGB = (70, 120, 200)
SKY_HORIZON_RGB = (190, 205, 220)  # also the fog colour
SKY_EXPONENT = 0.5
SUN_RGB = (255, 245, 225)
# Hypsometric tint (sortie/demo.py's palette) at these heights MSL, linear between.
TINT_LOW_RGB, TINT_MID_RGB, TINT_HIGH_RGB = (70, 120, 60), (170, 150, 100), (245, 245, 245)
TINT_MID_M, TINT_HIGH_M = 1500.0, 3000.0
ROCK_RGB = (125, 118, 110)
ROCK_SLOPE_DEG = (30.0, 45.0)  # slope where rock starts, and where it is all rock
WATER_RGB = (35, 75, 125)
WATER_SHININESS = 64.0
WATER_SPECULAR = 0.6
# The sun of an instant is recomputed once this much of its time has passed: the sun moves
# 360 degrees a day, 0.0042 degree (15 arcseconds) a second, under a pixel of any view here.
SUN_UPDATE_S = 1.0
UNIX_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)


def rgb(c) -> tuple[float, float, float]:
    """0-255 integer colour -> 0-1 floats."""
    return tuple(v / 255.0 for v in c)


def sun_direction_local(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3,) unit vector towards the sun in local ENU (azimuth clockwise from north)."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


def sun_direction_ecef(when, lat_deg: float, lon_deg: float, *, refraction: bool = True) -> np.ndarray:
    """(3,) float64 unit vector, ECEF, toward the sun's centre at UTC instant ``when`` (a
    timezone-aware datetime or a numpy datetime64, as terrain.sun.julian_day takes) seen from
    (lat_deg, lon_deg): terrain.sun.sun_position's azimuth and elevation there (apparent, with
    refraction, unless ``refraction`` is False) as an ENU vector turned into ECEF. Parallax is
    8.8 arcseconds (the solar parallax): the direction holds from anywhere near that point, and
    its elevation in another point's sky is that point's geometric one (plus the refraction
    where it was computed, 0.57 degree at most, at the horizon)."""
    from terrain.geodesy import enu_basis
    from terrain.sun import sun_direction_enu, sun_position

    s = sun_position(when, lat_deg, lon_deg, refraction=refraction)
    e, n, u = sun_direction_enu(s.azimuth_deg, s.elevation_deg)
    east, north, up = enu_basis(lat_deg, lon_deg)
    return e * east + n * north + u * up


def sun_in_sky_deg(sun_ecef, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """(azimuth degrees clockwise from north in [0, 360), elevation degrees) of the ECEF
    direction ``sun_ecef`` (3,) in the sky of (lat_deg, lon_deg)."""
    from terrain.geodesy import enu_basis

    v = np.asarray(sun_ecef, np.float64)
    e, n, u = (float(b @ v) for b in enu_basis(lat_deg, lon_deg))
    return math.degrees(math.atan2(e, n)) % 360.0, math.degrees(math.atan2(u, math.hypot(e, n)))


def instant_s(field: str, when) -> float:
    """Seconds (float64) since 1970-01-01T00:00:00 UTC of one instant, a timezone-aware datetime
    or a numpy datetime64 taken as UTC (what terrain.sun.julian_day takes); InvalidArgument
    naming ``field`` for anything else. (Seconds, not a Julian day: a day number of 2.46e6 holds
    a second only to 40 microseconds, so one second later could compare as less than one.)"""
    if isinstance(when, datetime):
        if when.tzinfo is None or when.utcoffset() is None:
            raise InvalidArgument(field, "must be timezone-aware (a time without a zone is ambiguous)",
                                  value=when.isoformat())
        return (when - UNIX_EPOCH).total_seconds()
    stamp = np.asarray(when) if isinstance(when, np.datetime64) else None
    if stamp is None or np.isnat(stamp):
        raise InvalidArgument(field, "must be a timezone-aware datetime or a numpy datetime64 instant", value=when)
    return float((stamp - np.datetime64(0, "us")).astype("timedelta64[us]").astype(np.int64)) / 1e6


class EphemerisSun:
    """The sun of an instant for a camera that moves: :func:`sun_direction_ecef` at the camera's
    position, computed again only once the instant asked for is SUN_UPDATE_S or more from the one
    it was computed for (either way: a replay seeks back), so a frame costs a comparison. The
    direction is ECEF, the same from anywhere (:func:`sun_direction_ecef`): a camera that moved
    meanwhile sees it in its own sky."""

    def __init__(self, refraction: bool = True):
        self.refraction = bool(refraction)
        self.computed = 0  # how many times the ephemeris was evaluated
        self._t = None
        self._ecef = None

    def direction_ecef(self, when, lat_deg: float, lon_deg: float) -> np.ndarray:
        """(3,) float64 unit ECEF vector toward the sun at ``when`` (to within SUN_UPDATE_S)."""
        t = instant_s("sun_time", when)
        if self._t is None or abs(t - self._t) >= SUN_UPDATE_S:
            self._ecef = sun_direction_ecef(when, lat_deg, lon_deg, refraction=self.refraction)
            self._t = t
            self.computed += 1
        return self._ecef


def water_level_m(terrain) -> float:
    """The height MSL at or below which the terrain is drawn as water: the quantisation bound of
    its sources (terrain.texture_cli.water_tolerance_m, the tolerance of ``sortie terrain
    texture``'s water test: half the step of a lossy store, local or behind a terrain service;
    0 for a DEM, a lossless store, a procedural world). 0 without a terrain, or one that does
    not describe its sources."""
    if terrain is None or not callable(getattr(terrain, "describe", None)):
        return 0.0
    from terrain.texture_cli import water_tolerance_m

    return float(water_tolerance_m(terrain))


def fog_density_per_m(edge_distance_m: float) -> float:
    """GL_EXP2 fog density (1/m) whose transmittance is FOG_EDGE_TRANSMITTANCE at edge_distance_m."""
    return math.sqrt(-math.log(FOG_EDGE_TRANSMITTANCE)) / edge_distance_m


@dataclass(frozen=True)
class Frame:
    """Everything a layer needs to draw one frame.

    view: (4, 4) float64, local ENU -> view; projection: (4, 4) float64 reversed-Z;
    camera_local: (3,) float64, the camera's local offset; up_local: (3,) the camera's
    local vertical in the local frame; sun_local: (3,) unit vector to the sun; fog_density
    1/m (0: no fog); fog_rgb and the sky colours 0-1 floats; flat_sky: test mode;
    water_level_m: terrain at or below this height MSL is water (:func:`water_level_m`);
    sun_light: the weight of the sun's direct light, 1 with the sun above the camera's horizon,
    0 at or below it (ambient only).
    """

    camera: Camera
    origin: LocalOrigin
    width: int
    height: int
    view: np.ndarray
    projection: np.ndarray
    camera_local: np.ndarray
    up_local: np.ndarray
    sun_local: np.ndarray
    fog_density: float
    fog_rgb: tuple
    flat_sky_rgb: tuple | None
    water_level_m: float = 0.0
    sun_light: float = 1.0

    def write_common(self, program) -> None:
        """Set the uniforms of GLSL_COMMON (those the program uses) and its matrices."""
        values = {
            "u_view": self.view.T.astype("f4").tobytes(),
            "u_projection": self.projection.T.astype("f4").tobytes(),
            "u_camera": self.camera_local.astype("f4").tobytes(),
            "u_sun": self.sun_local.astype("f4").tobytes(),
            "u_sun_light": np.float32(self.sun_light).tobytes(),
            "u_fog_density": np.float32(self.fog_density).tobytes(),
            "u_fog_rgb": np.array(self.fog_rgb, "f4").tobytes(),
            "u_vertical": np.asarray(self.up_local, "f4").tobytes(),
            "u_water_level": np.float32(self.water_level_m).tobytes(),
        }
        for name, data in values.items():
            member = program.get(name, None)  # one lookup (``name in program`` walks every member)
            if member is not None:
                member.write(data)


GLSL_COMMON = f"""
uniform mat4 u_view;
uniform mat4 u_projection;
uniform vec3 u_camera;       // camera offset, local ENU metres
uniform vec3 u_sun;          // unit vector to the sun, local ENU
uniform float u_sun_light;   // the sun's direct light: 1 above the horizon, 0 at or below (ambient only)
uniform float u_fog_density; // 1/m; 0 turns fog off
uniform vec3 u_fog_rgb;
uniform vec3 u_vertical;     // the camera's local vertical, local ENU (fog is by horizontal distance)

const float AMBIENT = {AMBIENT};
const float SUN = {SUN};

vec3 lambert(vec3 albedo, vec3 n) {{
    return albedo * (AMBIENT + SUN * u_sun_light * max(dot(n, u_sun), 0.0));
}}

vec3 fogged(vec3 colour, vec3 world) {{
    vec3 d = world - u_camera;
    float kd = u_fog_density * length(d - dot(d, u_vertical) * u_vertical);
    float f = exp(-kd * kd);
    return mix(u_fog_rgb, colour, f);
}}
"""
