"""The camera view: the ground plane through a pinhole camera on the car, 160x120 RGB like Donkeycar's camera.

How it stays cheap (well under a millisecond per frame on one core):

1. The track is drawn once into a top-down texture (:class:`TrackTexture`, 2 cm per pixel by default):
   grass with some texture, asphalt, white edge lines, a dashed yellow centre line. Smaller copies of it (a
   mip pyramid, each half the size of the last) stand in for the ground far away, where one camera pixel
   covers many texels; sampling the full texture there would alias into flicker.
2. The camera is fixed to the car, so the ground point each pixel sees, in the car's frame, never changes
   (:class:`CameraSpec` → per-pixel ``(forward, left)`` metres, computed once). Each image row gets the
   pyramid level that matches its footprint; rows of one level form a contiguous band.
3. Per frame only the car's pose changes: rotate and translate those ground points into texture pixel
   coordinates (a few vectorised multiply-adds per band) and let ``cv2.remap`` sample bilinearly, writing
   straight into the output image. Rows above the horizon are a pre-rendered sky.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .track import Track

__all__ = ["CameraRenderer", "CameraSpec", "TrackTexture"]

ROAD_RGB = (88, 88, 92)
GRASS_RGB = (70, 118, 48)
WHITE_RGB = (235, 235, 235)
YELLOW_RGB = (230, 190, 30)
SKY_TOP_RGB = (110, 160, 225)
SKY_HORIZON_RGB = (200, 220, 240)


@dataclass(frozen=True, slots=True)
class CameraSpec:
    """A pinhole camera fixed on the car. Distances in metres, angles in degrees.

    Defaults approximate a Donkeycar's wide-angle camera on its mast: 20 cm above the ground, 15 cm ahead
    of the rear axle, tilted 20° down, 100° horizontal field of view, 160x120 pixels.
    """

    width: int = 160
    height: int = 120
    hfov_deg: float = 100.0
    mount_height: float = 0.20
    forward_offset: float = 0.15
    pitch_deg: float = 20.0
    """Downward tilt of the optical axis below horizontal."""

    def __post_init__(self) -> None:
        if not (self.width > 0 and self.height > 0):
            raise ValueError(f"CameraSpec: image size must be positive, got {self.width}x{self.height}")
        if not 10 <= self.hfov_deg <= 150:
            raise ValueError(f"CameraSpec.hfov_deg must be in [10, 150] for a pinhole model, got {self.hfov_deg}")
        if not self.mount_height > 0:
            raise ValueError(f"CameraSpec.mount_height must be positive, got {self.mount_height}")
        if not -30 <= self.pitch_deg < 89:
            raise ValueError(f"CameraSpec.pitch_deg must be in [-30, 89), got {self.pitch_deg}")

    @property
    def focal_px(self) -> float:
        return (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def horizon_row(self) -> float:
        """Image row (fractional, 0 at the top pixel's centre) where the horizon lies."""
        cy = (self.height - 1) / 2
        return cy - self.focal_px * math.tan(math.radians(self.pitch_deg))

    def ground_points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per pixel: ``(forward, left)`` metres from the rear axle where its ray meets the ground, and a
        mask of pixels that see the ground at all (below the horizon). Non-ground pixels hold NaN."""
        f = self.focal_px
        cx, cy = (self.width - 1) / 2, (self.height - 1) / 2
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        xr = (u - cx) / f  # to the right, per unit along the optical axis
        yd = (v - cy) / f  # downward
        p = math.radians(self.pitch_deg)
        ray_fwd = math.cos(p) - yd * math.sin(p)
        ray_up = -math.sin(p) - yd * math.cos(p)
        ground = ray_up < -1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(ground, self.mount_height / -ray_up, np.nan)
        return t * ray_fwd + self.forward_offset, t * -xr, ground


class TrackTexture:
    """The track drawn top-down into an RGB image, with a mip pyramid for distant ground.

    Pixel ``(row, col)`` of level 0 covers world ``x = x0 + (col + 0.5) · resolution``,
    ``y = y1 - (row + 0.5) · resolution`` (north up, like a map).
    """

    def __init__(
        self,
        track: Track,
        *,
        resolution: float = 0.02,
        margin: float = 4.0,
        seed: int = 0,
        line_width: float = 0.05,
        dash: float = 0.3,
        levels: int = 7,
    ) -> None:
        if not 0.002 <= resolution <= 0.2:
            raise ValueError(f"TrackTexture: resolution must be in [0.002, 0.2] m/pixel, got {resolution}")
        self.resolution = float(resolution)
        x0, y0, x1, y1 = track.bounds(margin)
        self.x0, self.y1 = x0, y1
        w = math.ceil((x1 - x0) / resolution)
        h = math.ceil((y1 - y0) / resolution)
        rng = np.random.default_rng(seed)
        img = _draw(track, w, h, x0, y1, self.resolution, rng, line_width, dash)
        # Fade the outermost metre to the mean grass colour: ground beyond the texture (sampled by clamping
        # to the border) then looks like more of the same field rather than smeared edge pixels.
        border = max(2, round(1.0 / resolution))
        fade = np.ones((h, w), np.float32)
        ramp = np.clip(np.arange(max(h, w), dtype=np.float32) / border, 0, 1)
        fade *= np.minimum(ramp[:h], ramp[:h][::-1])[:, None]
        fade *= np.minimum(ramp[:w], ramp[:w][::-1])[None, :]
        img = img * fade[..., None] + np.array(GRASS_RGB, np.float32) * (1 - fade[..., None])
        self.levels: list[np.ndarray] = [np.clip(img + 0.5, 0, 255).astype(np.uint8)]
        for _ in range(1, levels):
            prev = self.levels[-1]
            if min(prev.shape[:2]) < 4:
                break
            self.levels.append(cv2.resize(prev, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA))

    @property
    def image(self) -> np.ndarray:
        """Level 0 (full resolution), RGB uint8."""
        return self.levels[0]


class CameraRenderer:
    """Renders :class:`CameraSpec` views of a :class:`TrackTexture` from car poses.

    ``render(x, y, heading)`` returns a new ``(height, width, 3)`` uint8 RGB array (a fresh array per frame,
    so a published frame is never modified afterwards).
    """

    def __init__(self, texture: TrackTexture, spec: CameraSpec | None = None) -> None:
        self.texture = texture
        self.spec = spec = spec or CameraSpec()
        fwd, left, ground = spec.ground_points()
        rows_ground = np.flatnonzero(ground.any(axis=1))
        self._first_ground = int(rows_ground[0]) if len(rows_ground) else spec.height
        if len(rows_ground) and not ground[self._first_ground :].all():
            raise ValueError("CameraSpec: the ground region is not a band of whole rows")
        self._sky = _sky(spec, self._first_ground)
        # Footprint of each pixel on the ground (metres): how far its neighbours' ground points are.
        bands: list[tuple[int, int, int]] = []
        if len(rows_ground):
            g = slice(self._first_ground, spec.height)
            fw, lf = fwd[g], left[g]
            du = np.hypot(np.gradient(fw, axis=1), np.gradient(lf, axis=1))
            dv = np.hypot(*(np.gradient(a, axis=0) for a in (fw, lf))) if fw.shape[0] > 1 else du
            footprint = np.median(np.maximum(du, dv), axis=1)
            lvl = np.floor(np.log2(np.maximum(footprint / texture.resolution, 1.0)))
            lvl = np.clip(lvl, 0, len(texture.levels) - 1).astype(int)
            r = 0
            while r < len(lvl):
                r1 = r
                while r1 < len(lvl) and lvl[r1] == lvl[r]:
                    r1 += 1
                bands.append((self._first_ground + r, self._first_ground + r1, int(lvl[r])))
                r = r1
        self._bands = []
        for r0, r1, level in bands:
            scale = 1.0 / (texture.resolution * 2**level)
            self._bands.append(
                (
                    r0,
                    r1,
                    texture.levels[level],
                    np.ascontiguousarray(fwd[r0:r1], dtype=np.float32),
                    np.ascontiguousarray(left[r0:r1], dtype=np.float32),
                    scale,
                )
            )
        # Haze: distant rows fade towards the horizon colour (cheap: only those few rows).
        dist = np.where(ground, np.hypot(fwd, left), np.inf)
        row_dist = np.nanmin(np.where(ground, dist, np.inf), axis=1)
        haze = np.clip((row_dist - 6.0) / 30.0, 0.0, 0.7)
        self._haze_rows = [(r, float(haze[r])) for r in range(self._first_ground, spec.height) if haze[r] > 0.01]
        self._haze_rgb = np.array(SKY_HORIZON_RGB, np.float32)

    def render(self, x: float, y: float, heading: float) -> np.ndarray:
        spec = self.spec
        out = np.empty((spec.height, spec.width, 3), np.uint8)
        out[: self._first_ground] = self._sky
        c, s = math.cos(heading), math.sin(heading)
        x0, y1 = self.texture.x0, self.texture.y1
        for r0, r1, tex, fw, lf, scale in self._bands:
            # texture col = (wx - x0) * scale - 0.5 ; row = (y1 - wy) * scale - 0.5 (pixel centres at +0.5)
            a, b = c * scale, s * scale
            mapx = fw * a - lf * b + ((x - x0) * scale - 0.5)
            mapy = fw * -b - lf * a + ((y1 - y) * scale - 0.5)
            cv2.remap(tex, mapx, mapy, cv2.INTER_LINEAR, dst=out[r0:r1], borderMode=cv2.BORDER_REPLICATE)
        for r, h in self._haze_rows:
            row = out[r]
            row[:] = row * (1.0 - h) + self._haze_rgb * h
        return out


def _sky(spec: CameraSpec, rows: int) -> np.ndarray:
    top = np.array(SKY_TOP_RGB, np.float64)
    hor = np.array(SKY_HORIZON_RGB, np.float64)
    horizon = max(spec.horizon_row, 1.0)
    t = np.clip(np.arange(rows, dtype=np.float64) / horizon, 0, 1)[:, None]
    col = top * (1 - t) + hor * t
    return np.repeat(np.clip(col + 0.5, 0, 255).astype(np.uint8)[:, None, :], spec.width, axis=1)


def _draw(
    track: Track,
    w: int,
    h: int,
    x0: float,
    y1: float,
    res: float,
    rng: np.random.Generator,
    line_width: float,
    dash: float,
) -> np.ndarray:
    """Float32 RGB texture: grass, road, white edge lines and a dashed yellow centre line."""
    shift = 4  # cv2 fixed-point sub-pixel bits
    k = 1 << shift

    def to_px(pts: np.ndarray) -> np.ndarray:
        col = (pts[:, 0] - x0) / res - 0.5
        row = (y1 - pts[:, 1]) / res - 0.5
        return np.round(np.stack([col, row], axis=1) * k).astype(np.int32)

    d = _centre_distance(track, w, h, x0, y1, res)

    # grass: two scales of smoothed noise
    coarse = cv2.resize(
        rng.normal(0, 1, (max(2, h // 40), max(2, w // 40))).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
    )
    fine = rng.normal(0, 1, (h, w)).astype(np.float32)
    grass_l = 1.0 + 0.10 * coarse + 0.08 * fine
    img = np.empty((h, w, 3), np.float32)
    img[:] = np.array(GRASS_RGB, np.float32)
    img *= grass_l[..., None]

    px = res

    def cover(inside: np.ndarray) -> np.ndarray:
        """Antialiased coverage from a signed distance (metres, positive inside)."""
        return np.clip(inside / px + 0.5, 0.0, 1.0)[..., None]

    hw = track.half_width
    road_l = 1.0 + 0.05 * rng.normal(0, 1, (h, w)).astype(np.float32)
    road = np.array(ROAD_RGB, np.float32) * road_l[..., None]
    a = cover(hw - d)
    img = img * (1 - a) + road * a
    edge = cover(line_width / 2 - np.abs(d - (hw - line_width * 1.5)))
    img = img * (1 - edge) + np.array(WHITE_RGB, np.float32) * edge

    # dashed centre line: segments of `dash` metres every 2 · dash
    mask = np.zeros((h, w), np.uint8)
    pts = track.points
    n = len(pts)
    on = (track.s % (2 * dash)) < dash
    thick = max(1, round(line_width * 0.8 / res))
    runs = []
    i = 0
    while i < n:
        if on[i]:
            j = i
            while j < n and on[j]:
                j += 1
            runs.append(pts[i : min(j + 1, n)])
            i = j
        else:
            i += 1
    cv2.polylines(mask, [to_px(r) for r in runs if len(r) > 1], False, 255, thick, cv2.LINE_AA, shift)
    y = (mask.astype(np.float32) / 255.0)[..., None]
    img = img * (1 - y) + np.array(YELLOW_RGB, np.float32) * y
    return img


def _centre_distance(track: Track, w: int, h: int, x0: float, y1: float, res: float) -> np.ndarray:
    """Distance (metres) from each texel centre to the centre line, exact near the road.

    A distance transform from rasterised points is only accurate to half a texel (1 cm), enough to shift
    the painted lines visibly in the camera's near field. So: the transform (with labels) finds each
    texel's nearest centre-line vertex, and texels near the road get the exact distance to the segments
    around that vertex.
    """
    pts = track.points
    n = len(pts)
    vc = np.clip(np.round((pts[:, 0] - x0) / res - 0.5).astype(int), 0, w - 1)
    vr = np.clip(np.round((y1 - pts[:, 1]) / res - 0.5).astype(int), 0, h - 1)
    zero = np.full((h, w), 255, np.uint8)
    zero[vr, vc] = 0
    approx, labels = cv2.distanceTransformWithLabels(zero, cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL)
    d = approx.astype(np.float64) * res
    vertex_of_label = np.zeros(int(labels.max()) + 1, np.int64)
    vertex_of_label[labels[vr, vc]] = np.arange(n)
    rows, cols = np.nonzero(d < track.half_width + 0.25)
    px = x0 + (cols + 0.5) * res
    py = y1 - (rows + 0.5) * res
    near = vertex_of_label[labels[rows, cols]]
    best = np.full(len(rows), np.inf)
    nxt = np.roll(pts, -1, axis=0)
    for k in (-2, -1, 0, 1):
        i = (near + k) % n
        ax, ay = pts[i, 0], pts[i, 1]
        bx, by = nxt[i, 0] - ax, nxt[i, 1] - ay
        t = np.clip(((px - ax) * bx + (py - ay) * by) / (bx * bx + by * by), 0.0, 1.0)
        dist = np.hypot(px - ax - t * bx, py - ay - t * by)
        np.minimum(best, dist, out=best)
    d[rows, cols] = best
    return d.astype(np.float32)
