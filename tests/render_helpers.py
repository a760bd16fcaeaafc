"""Helpers shared by the render tests (tests/test_render.py, tests/test_clipmap.py)."""

import numpy as np

from client.render.camera import Camera
from terrain.geodesy import WGS84_A_M, WGS84_B_M


def hits_height(camera: Camera, rays: np.ndarray, h_m: float) -> np.ndarray:
    """(..., 3) ECEF points where unit rays from the camera first meet the surface of
    ellipsoid height h_m (modelled as the ellipsoid of semi-axes a + h, b + h: within
    h e^2 / 2 < 2 m of it here); NaN where they miss it."""
    scale = np.array([1.0 / (WGS84_A_M + h_m), 1.0 / (WGS84_A_M + h_m), 1.0 / (WGS84_B_M + h_m)])
    o, d = camera.position_ecef * scale, rays * scale
    a, b, c = np.sum(d * d, -1), 2.0 * np.sum(o * d, -1), np.dot(o, o) - 1.0
    disc = b * b - 4.0 * a * c
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / (2.0 * a)
    t = np.where((disc >= 0) & (t > 0), t, np.nan)
    return camera.position_ecef + t[..., None] * rays
