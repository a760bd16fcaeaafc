"""Camera math of the render client, pure numpy float64.

Frames (the conventions of ``proto/sortie/v1/simulation.proto``):

- **ECEF**: WGS84 Earth-centred, Earth-fixed, metres, float64.
- **body**: x forward, y right, z down. An orientation is the 3x3 matrix
  ``r_ecef_body`` whose columns are the body axes in ECEF (v_ecef = R v_body),
  the matrix of the ECEF -> body quaternion (w, x, y, z) of the wire
  (``server.dead_reckoning``: Hamilton quaternions, v_e = R(q) v_b).
- **local**: east-north-up axes at a float64 ECEF origin (:class:`LocalOrigin`).
  Geometry goes to the GPU as float32 offsets in this frame; the origin is
  rebased when the camera moves more than ``REBASE_DISTANCE_M`` from it
  (global-terrain-flight-sim §6: float64 world, float32 offsets from a local
  origin "no more than several thousand meters away", shared by all geometry
  so no cracks open between pieces).
- **view**: OpenGL's eye space: x right, y up, looking down -z; metres.
- **pixels**: (col, row) with row 0 at the top of the image; pixel (i, j)
  covers [i, i + 1) x [j, j + 1), so its centre is (i + 0.5, j + 0.5).

Projection: reversed-Z with an infinite far plane (client/render/gl.py says
why): window depth = near_m / d, where d is the view depth (metres along the
optical axis, -z_view). Nothing is clipped far away. The renderer brings the
near plane in from near_m as the camera nears the ground (:func:`near_plane_m`).

Precision of the float32 path (tested): a vertex at distance r from the
origin is stored within r x 2^-24 (1 mm at 24 km), the view matrix's
translation is the camera's offset from the origin (at most
REBASE_DISTANCE_M: 0.12 mm), and the shader's float32 product adds a few
ulps of its largest term: 4 mm at worst over a +-20 km window (measured).
Without rebasing, a camera 1000 km from its origin gets 15 cm.

Argument order is always (lat, lon), degrees; altitudes are metres above mean
sea level (``_msl``), converted to ellipsoid heights with a constant geoid
undulation N (ellipsoid height = MSL + N), the convention of ``server.world``
and of the terrain service's MSL heights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sortie.errors import InvalidArgument
from terrain.geodesy import ecef_to_geodetic, enu_basis, geodetic_to_ecef

REBASE_DISTANCE_M = 4000.0  # the local origin follows the camera once it is farther than this
DEFAULT_FOV_X_DEG = 60.0  # horizontal field of view
DEFAULT_NEAR_M = 1.0
# The renderer brings the near plane in near the ground (near_plane_m): to this fraction of the
# least view depth the ground under the camera can have in the frame, never under NEAR_FLOOR_M.
NEAR_GROUND_FRACTION = 0.5
NEAR_FLOOR_M = 0.01
FOV_X_RANGE_DEG = (1.0, 170.0)
_ORTHONORMAL_TOL = 1e-6


# -- rotations -----------------------------------------------------------------------------------

def quat_to_matrix(quat_wxyz) -> np.ndarray:
    """(..., 4) unit quaternions (w, x, y, z), ECEF -> body -> (..., 3, 3) float64 matrices
    R with v_ecef = R v_body (columns: body x, y, z in ECEF). Normalises first."""
    q = np.asarray(quat_wxyz, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"quat_wxyz must have shape (..., 4), got {q.shape}")
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def ned_to_ecef_matrix(lat_deg: float, lon_deg: float) -> np.ndarray:
    """(3, 3) float64 matrix whose columns are north, east, down at (lat, lon) in ECEF."""
    east, north, up = enu_basis(lat_deg, lon_deg)
    return np.stack([north, east, -up], axis=-1)


def euler_to_matrix(heading_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """(3, 3) float64 body -> NED matrix of z-y-x Euler angles (heading psi, pitch theta,
    roll phi), v_ned = Rz(psi) Ry(theta) Rx(phi) v_body (Stevens & Lewis, *Aircraft Control
    and Simulation*, 3rd ed., eq. 1.3-20, transposed: theirs maps NED to body)."""
    psi, theta, phi = (math.radians(a) for a in (heading_deg, pitch_deg, roll_deg))
    cy, sy, cp, sp, cr, sr = math.cos(psi), math.sin(psi), math.cos(theta), math.sin(theta), math.cos(phi), \
        math.sin(phi)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def heading_pitch_roll_deg(position_ecef, r_ecef_body) -> tuple[float, float, float]:
    """(heading, pitch, roll) degrees of an orientation at an ECEF position (inverse of
    :func:`euler_to_matrix`; heading in [0, 360))."""
    lat, lon, _ = ecef_to_geodetic(np.asarray(position_ecef, dtype=np.float64))
    r = ned_to_ecef_matrix(float(lat), float(lon)).T @ np.asarray(r_ecef_body, dtype=np.float64)
    heading = math.degrees(math.atan2(r[1, 0], r[0, 0])) % 360.0
    pitch = math.degrees(math.asin(max(-1.0, min(1.0, -r[2, 0]))))
    roll = math.degrees(math.atan2(r[2, 1], r[2, 2]))
    return heading, pitch, roll


# -- the local origin ----------------------------------------------------------------------------

class LocalOrigin:
    """A float64 ECEF origin and its ENU basis: what geometry is uploaded relative to.

    ``generation`` counts rebases, so layers know when to re-upload their offsets.
    """

    def __init__(self, origin_ecef, rebase_distance_m: float = REBASE_DISTANCE_M):
        if not (rebase_distance_m > 0):
            raise InvalidArgument("rebase_distance_m", "must be > 0", value=rebase_distance_m)
        self.rebase_distance_m = float(rebase_distance_m)
        self.generation = -1
        self._set(origin_ecef)

    def _set(self, origin_ecef) -> None:
        o = _vector3("origin_ecef", origin_ecef)
        lat, lon, _ = ecef_to_geodetic(o)
        e, n, u = enu_basis(float(lat), float(lon))
        self.ecef = o
        self.basis = np.stack([e, n, u])  # (3, 3) rows east, north, up in ECEF
        self.generation += 1

    def rebase_if_far(self, camera_ecef) -> bool:
        """Move the origin to the camera when it is more than rebase_distance_m away; whether it moved."""
        c = _vector3("camera_ecef", camera_ecef)
        if np.linalg.norm(c - self.ecef) <= self.rebase_distance_m:
            return False
        self._set(c)
        return True

    def to_local(self, points_ecef) -> np.ndarray:
        """(..., 3) ECEF metres -> (..., 3) float64 offsets from the origin, local ENU metres."""
        p = np.asarray(points_ecef, dtype=np.float64)
        return (p - self.ecef) @ self.basis.T

    def vectors_to_local(self, vectors_ecef) -> np.ndarray:
        """(..., 3) ECEF directions -> (..., 3) float64 local ENU components."""
        return np.asarray(vectors_ecef, dtype=np.float64) @ self.basis.T

    def upload(self, points_ecef) -> np.ndarray:
        """(..., 3) ECEF -> (..., 3) float32 local offsets: the GPU boundary."""
        return self.to_local(points_ecef).astype("f4")


def _vector3(name: str, value) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,):
        raise InvalidArgument(name, f"must have shape (3,), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InvalidArgument(name, "must be finite", value=v.tolist())
    return v


# -- the camera ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Camera:
    """A pinhole camera looking along its body x axis.

    position_ecef: (3,) float64, metres, ECEF. r_ecef_body: (3, 3) float64, columns the
    body axes (x forward = the optical axis, y right = image right, z down = image down)
    in ECEF. fov_x_deg: horizontal field of view; the vertical one follows from the
    image's aspect ratio. near_m: the near clipping plane (there is no far plane).
    """

    position_ecef: np.ndarray
    r_ecef_body: np.ndarray
    fov_x_deg: float = DEFAULT_FOV_X_DEG
    near_m: float = DEFAULT_NEAR_M

    def __post_init__(self):
        object.__setattr__(self, "position_ecef", _vector3("position_ecef", self.position_ecef))
        r = np.asarray(self.r_ecef_body, dtype=np.float64)
        if r.shape != (3, 3) or not np.all(np.isfinite(r)):
            raise InvalidArgument("r_ecef_body", f"must be a finite (3, 3) matrix, got shape {r.shape}")
        if np.abs(r.T @ r - np.eye(3)).max() > _ORTHONORMAL_TOL or np.linalg.det(r) < 0:
            raise InvalidArgument("r_ecef_body", "must be a rotation (orthonormal, right-handed)")
        object.__setattr__(self, "r_ecef_body", r)
        lo, hi = FOV_X_RANGE_DEG
        if not (lo <= self.fov_x_deg <= hi):
            raise InvalidArgument("fov_x_deg", f"must be within [{lo:g}, {hi:g}] degrees", value=self.fov_x_deg)
        if not (self.near_m > 0 and math.isfinite(self.near_m)):
            raise InvalidArgument("near_m", "must be > 0", value=self.near_m)

    # -- constructors

    @classmethod
    def from_geodetic(cls, lat_deg: float, lon_deg: float, alt_msl_m: float, heading_deg: float = 0.0,
                      pitch_deg: float = 0.0, roll_deg: float = 0.0, *, geoid_undulation_m: float = 0.0,
                      **kw) -> Camera:
        """At (lat, lon) degrees, alt_msl_m metres above MSL (ellipsoid height = MSL +
        geoid_undulation_m), oriented by heading (true, clockwise from north), pitch (nose
        up positive) and roll (right wing down positive), degrees."""
        for name, v in (("lat_deg", lat_deg), ("lon_deg", lon_deg), ("alt_msl_m", alt_msl_m),
                        ("heading_deg", heading_deg), ("pitch_deg", pitch_deg), ("roll_deg", roll_deg)):
            if not math.isfinite(v):
                raise InvalidArgument(name, "must be finite", value=v)
        if not -90.0 <= lat_deg <= 90.0:
            raise InvalidArgument("lat_deg", "must be within [-90, 90]", value=lat_deg)
        if not -90.0 <= pitch_deg <= 90.0:
            raise InvalidArgument("pitch_deg", "must be within [-90, 90]", value=pitch_deg)
        pos = geodetic_to_ecef(lat_deg, lon_deg, alt_msl_m + geoid_undulation_m)
        r = ned_to_ecef_matrix(lat_deg, lon_deg) @ euler_to_matrix(heading_deg, pitch_deg, roll_deg)
        return cls(pos, r, **kw)

    @classmethod
    def from_ecef_quat(cls, position_ecef, quat_wxyz, **kw) -> Camera:
        """At an ECEF position (3,), oriented by the ECEF -> body quaternion (w, x, y, z)."""
        q = np.asarray(quat_wxyz, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 0.5:
            raise InvalidArgument("quat_wxyz", "must be a finite unit quaternion (w, x, y, z)",
                                  value=q.tolist())
        return cls(position_ecef, quat_to_matrix(q), **kw)

    @classmethod
    def look_at(cls, eye_ecef, target_ecef, **kw) -> Camera:
        """At eye_ecef, looking at target_ecef (both (3,) ECEF), image up along the local vertical
        (no roll). Not straight up or down."""
        eye = _vector3("eye_ecef", eye_ecef)
        forward = _vector3("target_ecef", target_ecef) - eye
        dist = np.linalg.norm(forward)
        if dist == 0:
            raise InvalidArgument("target_ecef", "must differ from eye_ecef")
        forward /= dist
        lat, lon, _ = ecef_to_geodetic(eye)
        up = enu_basis(float(lat), float(lon))[2]
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-9:
            raise InvalidArgument("target_ecef", "must not be straight above or below the eye")
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        return cls(eye, np.stack([forward, right, down], axis=-1), **kw)

    # -- geometry

    def geodetic(self) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, ellipsoid height m) of the camera."""
        lat, lon, h = ecef_to_geodetic(self.position_ecef)
        return float(lat), float(lon), float(h)

    def view_matrix(self, origin: LocalOrigin) -> np.ndarray:
        """(4, 4) float64: local ENU (offsets from ``origin``) -> view space (x right, y up, -z forward)."""
        r_local_body = origin.basis @ self.r_ecef_body
        r_view_local = np.stack([r_local_body[:, 1], -r_local_body[:, 2], -r_local_body[:, 0]])
        m = np.eye(4)
        m[:3, :3] = r_view_local
        m[:3, 3] = -r_view_local @ origin.to_local(self.position_ecef)
        return m

    def focal(self, width: int, height: int) -> tuple[float, float]:
        """(fx, fy): 1 / tan of the half field of view, horizontally and vertically."""
        fx = 1.0 / math.tan(math.radians(0.5 * self.fov_x_deg))
        return fx, fx * width / height

    def projection(self, width: int, height: int) -> np.ndarray:
        """(4, 4) float64 reversed-Z infinite projection: clip = P view; depth = near_m / d."""
        fx, fy = self.focal(width, height)
        return np.array([[fx, 0.0, 0.0, 0.0], [0.0, fy, 0.0, 0.0], [0.0, 0.0, 0.0, self.near_m],
                         [0.0, 0.0, -1.0, 0.0]])

    def to_view(self, points_ecef) -> np.ndarray:
        """(..., 3) ECEF -> (..., 3) float64 view-space coordinates (no float32 anywhere)."""
        p = np.asarray(points_ecef, dtype=np.float64) - self.position_ecef
        r = self.r_ecef_body
        body = p @ r  # components along the body axes
        return np.stack([body[..., 1], -body[..., 2], -body[..., 0]], axis=-1)

    def project(self, points_ecef, width: int, height: int):
        """(..., 3) ECEF -> (pixels (..., 2) float64 (col, row), view depth (...,) metres).

        Depth is the distance along the optical axis (positive in front); pixels of points
        behind the camera are NaN.
        """
        v = self.to_view(points_ecef)
        d = -v[..., 2]
        fx, fy = self.focal(width, height)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(d > 0, fx * v[..., 0] / d, np.nan)
            y = np.where(d > 0, fy * v[..., 1] / d, np.nan)
        return np.stack([(x + 1.0) * 0.5 * width, (1.0 - y) * 0.5 * height], axis=-1), d

    def pixel_rays(self, width: int, height: int) -> np.ndarray:
        """(height, width, 3) float64 unit view rays through the pixel centres, ECEF directions."""
        fx, fy = self.focal(width, height)
        x = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) / fx
        y = (1.0 - (np.arange(height) + 0.5) / height * 2.0) / fy
        gx, gy = np.meshgrid(x, y)
        body = np.stack([np.ones_like(gx), gx, -gy], axis=-1)  # forward, right, down
        rays = body @ self.r_ecef_body.T
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def pixel_footprint_rad(self, width: int) -> float:
        """Angle one pixel subtends at the image centre, radians."""
        return 2.0 * math.tan(math.radians(0.5 * self.fov_x_deg)) / width


def near_plane_m(camera: Camera, width: int, height: int, height_above_ground_m: float) -> float:
    """The near plane for a frame of ``camera`` at height_above_ground_m (metres, above the highest
    surface drawn under it; NaN: unknown): the camera's own near_m, brought in near the ground to
    NEAR_GROUND_FRACTION of the least view depth that ground can have, clamped to NEAR_FLOOR_M.

    Every point of a surface h below the camera is at least h away, and a point seen at angle
    theta off the optical axis has view depth (distance x cos theta); theta is at most the
    frustum's corner angle, cos = 1 / sqrt(1 + 1/fx^2 + 1/fy^2) (fx, fy: :meth:`Camera.focal`).
    So nothing of that ground lies nearer than h cos(corner) along the axis, and the plane at half
    that clips none of it, also where the drawn triangles stand somewhat above the posts' height or
    the ground slopes. Reversed-Z with a float depth buffer resolves depths relative to the
    distance whatever the near plane (client/render/gl.py), so a near plane of 1 cm costs no
    precision; with a fixed 1 m one, a camera 0.5 m above the ground saw through it."""
    near = camera.near_m
    h = float(height_above_ground_m)
    if math.isnan(h):
        return near
    fx, fy = camera.focal(width, height)
    cos_corner = 1.0 / math.sqrt(1.0 + 1.0 / (fx * fx) + 1.0 / (fy * fy))
    return min(near, max(NEAR_FLOOR_M, NEAR_GROUND_FRACTION * cos_corner * h))


def chase_camera(target_ecef, r_ecef_body, back_m: float, up_m: float, **kw) -> Camera:
    """A camera behind (back_m along the target's horizontal heading) and above (up_m along
    the local vertical) the target, looking at it, image up along the vertical.

    target_ecef: (3,) ECEF; r_ecef_body: (3, 3) the target's orientation.
    """
    target = _vector3("target_ecef", target_ecef)
    lat, lon, _ = ecef_to_geodetic(target)
    up = enu_basis(float(lat), float(lon))[2]
    forward = np.asarray(r_ecef_body, dtype=np.float64)[:, 0]
    horizontal = forward - np.dot(forward, up) * up
    if np.linalg.norm(horizontal) < 1e-6:  # pointing straight up or down: use its body z instead
        horizontal = -np.asarray(r_ecef_body, dtype=np.float64)[:, 2]
        horizontal = horizontal - np.dot(horizontal, up) * up
    horizontal /= np.linalg.norm(horizontal)
    return Camera.look_at(target - back_m * horizontal + up_m * up, target, **kw)
