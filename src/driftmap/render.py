"""Drawing a point cloud without a GPU: pinhole cameras (:class:`ViewCamera`, OpenCV convention: x right, y down,
z forward), fitting a camera to a cloud, and a numpy z-buffer renderer with eye-dome shading. The viewer
(:mod:`driftmap.viewer`) uses it when Open3D's offscreen renderer is not available, and for its overview; and
whether a window can be opened at all (:func:`display_problem`)."""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

BACKGROUND_RGB = (20, 20, 24)
SESSION_PALETTE_RGB: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
)
"""The colour of each session of a merged store (``--color session`` of ``driftmap view`` and ``driftmap export
--mcap``): matplotlib's qualitative ``tab10`` palette as 8-bit RGB; session ``k`` gets entry ``k % 10``."""
SESSION_PALETTE_NAMES = ("blue", "orange", "green", "red", "purple", "brown", "pink", "grey", "olive", "cyan")
"""A word for each entry of :data:`SESSION_PALETTE_RGB` (legends and printed lists)."""


def session_color_rgb(session: int) -> tuple[int, int, int]:
    """The 8-bit RGB colour of ``session`` (:data:`SESSION_PALETTE_RGB`, repeating after 10 sessions)."""
    return SESSION_PALETTE_RGB[int(session) % len(SESSION_PALETTE_RGB)]


def session_color_text(session: int) -> str:
    """``#rrggbb (name)`` of ``session``'s colour, for legends and printed lists."""
    r, g, b = session_color_rgb(session)
    return f"#{r:02x}{g:02x}{b:02x} ({SESSION_PALETTE_NAMES[int(session) % len(SESSION_PALETTE_NAMES)]})"


@dataclass(frozen=True)
class ViewCamera:
    """A pinhole view: ``K`` (3x3, pixels) and ``T_cam_world`` (4x4; camera x right, y down, z forward).

    ``clip_up``/``clip_max_m``: the view leaves out points whose height ``p . clip_up`` exceeds ``clip_max_m``
    (the top view of an indoor map cuts the ceiling away).
    """

    name: str
    K: NDArray[np.float64]
    T_cam_world: NDArray[np.float64]
    width_px: int
    height_px: int
    clip_up: NDArray[np.float64] | None = None
    clip_max_m: float | None = None

    def project(self, points_world: NDArray[np.floating]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixel coordinates (N, 2; pixel (i, j) spans u in [j, j+1)) and depth along the optical axis (N,)."""
        p = np.asarray(points_world, dtype=np.float64) @ self.T_cam_world[:3, :3].T + self.T_cam_world[:3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (p[:, :2] / z[:, None]) * np.diag(self.K)[:2] + self.K[:2, 2]
        return uv, z

    def visible(self, points_world: NDArray[np.floating]) -> NDArray[np.bool_]:
        """Points this view draws at all (the clip; not occlusion or the image bounds)."""
        if self.clip_up is None or self.clip_max_m is None:
            return np.ones(len(points_world), bool)
        return np.asarray(points_world, dtype=np.float64) @ self.clip_up <= self.clip_max_m

    def to_json(self) -> dict:
        return {"name": self.name, "K": self.K.tolist(), "T_cam_world": self.T_cam_world.tolist(),
                "width_px": self.width_px, "height_px": self.height_px,
                "clip_up": None if self.clip_up is None else self.clip_up.tolist(), "clip_max_m": self.clip_max_m}


def look_along(forward: NDArray[np.float64], up_hint: NDArray[np.float64]) -> NDArray[np.float64]:
    """R_world_cam (columns: camera x right, y down, z forward) looking along ``forward``."""
    z = forward / np.linalg.norm(forward)
    x = np.cross(z, up_hint)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def fit_camera(name: str, R_world_cam: NDArray[np.float64], points: NDArray[np.float64], center: NDArray[np.float64],
                fov_deg: float, width_px: int, height_px: int, quantile: float = 99.5, margin: float = 1.06) -> ViewCamera:
    """A camera with rotation ``R_world_cam`` backed off from ``center`` until ``quantile`` % of the points fit."""
    f = 0.5 * width_px / math.tan(math.radians(fov_deg) / 2)
    q = (points - center) @ R_world_cam  # camera-axis coordinates relative to the centre
    need = np.maximum(np.abs(q[:, 0]) * f / (0.5 * width_px), np.abs(q[:, 1]) * f / (0.5 * height_px)) - q[:, 2]
    dist = max(float(np.percentile(need, quantile)) * margin, 1e-3)
    eye = center - dist * R_world_cam[:, 2]
    T = np.eye(4)
    T[:3, :3] = R_world_cam.T
    T[:3, 3] = -R_world_cam.T @ eye
    K = np.array([[f, 0.0, width_px / 2], [0.0, f, height_px / 2], [0.0, 0.0, 1.0]])
    return ViewCamera(name, K, T, width_px, height_px)


def render_software(points_world: NDArray[np.floating], colors: NDArray[np.uint8], camera: ViewCamera, *,
                    point_size_px: int = 2, background: tuple[int, int, int] = BACKGROUND_RGB,
                    shading: bool = True) -> NDArray[np.uint8]:
    """(H, W, 3) image: every point a ``point_size_px`` square, the nearest point wins each pixel; ``shading``
    darkens pixels lying behind their neighbours (eye-dome lighting) so depth edges read as outlines."""
    W, H = camera.width_px, camera.height_px
    keep = camera.visible(points_world)
    uv, z = camera.project(np.asarray(points_world)[keep])
    rgb = np.asarray(colors)[keep]
    ok = np.isfinite(z) & (z > 1e-3) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] > -point_size_px) & (uv[:, 0] < W + point_size_px) & (uv[:, 1] > -point_size_px) & (uv[:, 1] < H + point_size_px)
    u0, v0 = np.floor(uv[ok, 0]).astype(np.int64), np.floor(uv[ok, 1]).astype(np.int64)
    z, rgb = z[ok], rgb[ok]
    s = max(int(point_size_px), 1)
    offsets = np.arange(s) - (s - 1) // 2
    pix, depth, src = [], [], []
    idx = np.arange(len(z))
    for dy in offsets:
        for dx in offsets:
            u, v = u0 + dx, v0 + dy
            inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
            pix.append(v[inside] * W + u[inside])
            depth.append(z[inside])
            src.append(idx[inside])
    pix_a, depth_a, src_a = np.concatenate(pix), np.concatenate(depth), np.concatenate(src)
    image = np.empty((H * W, 3), np.uint8)
    image[:] = background
    zbuf = np.full(H * W, np.inf)
    if len(pix_a):
        # nearest point per pixel: one sort of (pixel, depth) packed in an int64 (positive float32 bits keep their order)
        packed = (pix_a << 32) | depth_a.astype(np.float32).view(np.uint32).astype(np.int64)
        order = np.argsort(packed)
        first = np.ones(len(order), bool)
        first[1:] = pix_a[order][1:] != pix_a[order][:-1]
        win = order[first]
        image[pix_a[win]] = rgb[src_a[win]]
        zbuf[pix_a[win]] = depth_a[win]
    image = image.reshape(H, W, 3)
    if shading and np.isfinite(zbuf).any():
        image = _eye_dome(image, zbuf.reshape(H, W))
    return image


def _eye_dome(image: NDArray[np.uint8], zbuf: NDArray[np.float64], strength: float = 1.2) -> NDArray[np.uint8]:
    """Darken each drawn pixel by how far it lies behind 8 neighbours 1-2 px away (log depth; background
    neighbours count as far, so silhouettes stay bright and depth steps get a dark outline)."""
    drawn = np.isfinite(zbuf)
    ref = np.full(zbuf.shape, np.nan)
    ref[drawn] = np.log(zbuf[drawn])
    pad = np.pad(ref, 2, constant_values=np.nan)
    H, W = zbuf.shape
    response = np.zeros((H, W))
    for dy, dx in ((-2, 0), (2, 0), (0, -2), (0, 2), (-1, -1), (1, 1), (-1, 1), (1, -1)):
        nb = pad[2 + dy : 2 + dy + H, 2 + dx : 2 + dx + W]
        response += np.nan_to_num(np.maximum(ref - nb, 0.0), nan=0.0)
    shade = np.exp(-strength * 40.0 * response / 8.0)
    out = image.astype(np.float64)
    out[drawn] *= np.clip(shade[drawn], 0.35, 1.0)[:, None]
    return (out + 0.5).astype(np.uint8)


def display_available() -> bool:
    """True when a window can be opened: macOS/Windows, or a ``DISPLAY`` / ``WAYLAND_DISPLAY`` that answers
    (:func:`display_problem`)."""
    return display_problem() is None


def display_problem() -> str | None:
    """Why no window can be opened (None: one can): on Linux neither ``DISPLAY`` nor ``WAYLAND_DISPLAY`` is set, or
    the one set does not answer -- an X server's socket (``/tmp/.X11-unix/XN``, or TCP port 6000+N of its host, as
    over ``ssh -X``) refusing a connection within a second, a Wayland socket missing. Open3D given an unreachable
    ``DISPLAY`` falls back to EGL and can hang for ever."""
    if sys.platform in ("darwin", "win32"):
        return None
    wayland, display = os.environ.get("WAYLAND_DISPLAY"), os.environ.get("DISPLAY")
    if wayland:
        path = Path(wayland) if os.path.isabs(wayland) else Path(os.environ.get("XDG_RUNTIME_DIR", "/run/user")) / wayland
        if path.exists():
            return None
        if not display:
            return f"WAYLAND_DISPLAY={wayland} is set but its socket {path} does not exist"
    if not display:
        return "DISPLAY / WAYLAND_DISPLAY are unset"
    return None if _x_display_answers(display) else f"DISPLAY={display} is set but no X server answers there"


def _x_display_answers(display: str) -> bool:
    import re
    import socket

    match = re.fullmatch(r"(?P<host>[^:]*):(?P<n>\d+)(\.\d+)?", display.strip())
    if match is None:
        return False
    host, n = match["host"], int(match["n"])
    if host in ("", "unix"):
        targets = [(socket.AF_UNIX, f"/tmp/.X11-unix/X{n}"), (socket.AF_UNIX, f"\0/tmp/.X11-unix/X{n}")]
    else:
        targets = [(socket.AF_INET6 if ":" in host else socket.AF_INET, (host, 6000 + n))]
    for family, address in targets:
        try:
            with socket.socket(family, socket.SOCK_STREAM) as sock:
                sock.settimeout(1.0)
                sock.connect(address)
                return True
        except OSError:
            continue
    return False
