"""Headless particle renderer: turn particle sets into a PNG so a person can see what the engine does.

Pure numpy + Pillow (no Taichi, no display). Particles are drawn as shaded disks (a sphere impostor lit
from the upper left) with an orthographic camera and a per-pixel painter's algorithm: every pixel shows
the particle whose centre is nearest to the camera, so near particles cover far ones. Farther particles
are also drawn slightly darker (a depth cue) so the 3-D shape reads in a still picture.

Conventions
-----------
World frame is ROS REP-103: x forward, y left, z up, lengths in metres. A view is a camera direction
given by azimuth and elevation, in degrees, of the *camera position* seen from the scene:

    camera direction  c = (cos el · cos az,  cos el · sin az,  sin el)     (unit vector towards the camera)
    screen right      r = (-sin az, cos az, 0)
    screen up         u = c × r

so az = 0 puts the camera on +x looking back along -x, az = 90 on +y, and el = 90 looks straight down.
This is the yaw/pitch convention of RViz's orbit camera. A point p is nearer than q when c·p > c·q.

Named views (``VIEWS``), described by the world axes that point right and up on screen:

    =======  ===========  =================================  ==============  ==========
    name     (az, el)     camera                             screen right    screen up
    =======  ===========  =================================  ==============  ==========
    front    (0, 0)       in front of the robot (+x), looks  +y (robot's     +z
                          back along -x                      left)
    side     (-90, 0)     on the robot's right (-y), looks   +x (forward)    +z
                          along +y
    top      (-90, 90)    above (+z), looks down along -z    +x (forward)    +y (left)
    iso      (45, 30)     front-left and above (RViz-like)   (-x+y)/√2       mostly +z
    =======  ===========  =================================  ==============  ==========

"top" is the usual map view (x right, y up); larger z is nearer. Any ``(azimuth_deg, elevation_deg)``
tuple is accepted as well.

The view is fitted to ``bounds`` (default: the bounding box of all points): the eight corners of the box
are projected, and the result is centred and scaled uniformly (no distortion) to fill the image minus a
margin. Points outside the bounds are still drawn and clipped at the image edge.

Example::

    from fluidlab_core.render import Layer, render
    render([Layer(water_xyz, (0.2, 0.4, 0.9), "water")], "out/frame_000.png", view="iso",
           bounds=((0, 0, 0), (1, 1, 1)), title="t = 0.00 s")
"""
from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw, ImageFont

VIEWS: dict[str, tuple[float, float]] = {
    "front": (0.0, 0.0),  # camera at +x; right = +y, up = +z
    "side": (-90.0, 0.0),  # camera at -y; right = +x, up = +z
    "top": (-90.0, 90.0),  # camera at +z; right = +x, up = +y
    "iso": (45.0, 30.0),  # camera front-left, above
}

MARGIN_FRACTION = 0.06  # empty border around the fitted bounds, fraction of the smaller image side
TITLE_BAND_PX = 18  # extra top margin reserved when a title is drawn
DEPTH_CUE = 0.35  # the farthest particles are this much darker than the nearest
AMBIENT = 0.45  # sphere shading: ambient, diffuse and specular weights
DIFFUSE = 0.55
SPECULAR = 0.2
SHININESS = 30.0
LIGHT_DIR = np.array([-0.4, 0.5, 0.75]) / np.linalg.norm([-0.4, 0.5, 0.75])  # screen (right, up, out)
AUTO_RADIUS_SPACING = 0.6  # automatic radius = this × mean particle spacing of the layer
MIN_RADIUS_PX = 0.75  # every particle covers at least one pixel centre
MAX_AUTO_RADIUS_FRACTION = 0.03  # automatic radius cap, fraction of the smaller image side
BOX_COLOR = (150, 150, 150)  # bounds box edges
CHUNK_CANDIDATES = 4_000_000  # (particle, pixel) pairs rasterised per batch; bounds memory use

Color = tuple[float, float, float]


def _layer_name(label: str) -> str:
    return f"layer {label!r}" if label else "unlabelled layer"


def _check_rgb(value, what: str) -> tuple[float, float, float]:
    try:
        rgb = tuple(float(c) for c in value)
    except TypeError:
        raise ValueError(f"{what} must be an (r, g, b) tuple with values in [0, 1], got {value!r}") from None
    if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
        raise ValueError(f"{what} must be an (r, g, b) tuple with values in [0, 1], got {value!r}")
    return rgb


@dataclass(frozen=True)
class Layer:
    """One set of particles drawn in one colour.

    points: (N, 3) positions in metres (world frame), finite. N may be 0.
    color:  (r, g, b) in [0, 1].
    label:  name shown in the legend; layers with an empty label are left out of it.
    radius: particle radius in metres; None picks one from the layer's mean particle spacing.
    """

    points: np.ndarray
    color: Color
    label: str = ""
    radius: float | None = None

    def __post_init__(self):
        name = _layer_name(self.label)
        points = np.asarray(self.points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"{name}: points must have shape (N, 3), got {points.shape}")
        bad = int(np.count_nonzero(~np.isfinite(points).all(axis=1)))
        if bad:
            raise ValueError(
                f"{name}: {bad} of {len(points)} points are not finite (NaN or inf); "
                "the simulation probably diverged (try a smaller dt), or filter them out before rendering"
            )
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "color", _check_rgb(self.color, f"{name}: color"))
        if self.radius is not None and not (math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"{name}: radius must be a positive number of metres or None, got {self.radius!r}")


@dataclass(frozen=True)
class _Camera:
    """Orthographic camera fitted to an image: world → pixel (x right, y down) and depth (larger = nearer)."""

    right: np.ndarray  # (3,) world direction of screen right
    up: np.ndarray  # (3,) world direction of screen up
    toward: np.ndarray  # (3,) world direction towards the camera
    scale: float  # pixels per metre
    offset: tuple[float, float]  # pixel position of the world origin's projection

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, depth): pixel column, pixel row (both continuous, pixel centres at i + 0.5), depth in m."""
        u = self.offset[0] + self.scale * (points @ self.right)
        v = self.offset[1] - self.scale * (points @ self.up)
        return u, v, points @ self.toward


def view_axes(view: str | tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, up, toward_camera) world unit vectors of a named view or an (azimuth_deg, elevation_deg) tuple."""
    if isinstance(view, str):
        if view not in VIEWS:
            known = ", ".join(sorted(VIEWS))
            raise ValueError(f"unknown view {view!r}; known views: {known}, or an (azimuth_deg, elevation_deg) tuple")
        az_deg, el_deg = VIEWS[view]
    else:
        try:
            az_deg, el_deg = (float(a) for a in view)
        except (TypeError, ValueError):
            known = ", ".join(sorted(VIEWS))
            raise ValueError(
                f"view must be one of {known} or an (azimuth_deg, elevation_deg) tuple, got {view!r}"
            ) from None
        if not (math.isfinite(az_deg) and math.isfinite(el_deg) and -90.0 <= el_deg <= 90.0):
            raise ValueError(f"view elevation must be in [-90, 90] degrees and azimuth finite, got {view!r}")
    az, el = math.radians(az_deg), math.radians(el_deg)
    toward = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    right = np.array([-math.sin(az), math.cos(az), 0.0])
    up = np.cross(toward, right)
    return right, up, toward


def _box_corners(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    idx = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    return np.where(idx == 0, lower, upper)


def _box_edges() -> list[tuple[int, int]]:
    """Pairs of corner indices (into `_box_corners`) that differ in exactly one axis."""
    return [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def _resolve_bounds(bounds, layers: list[Layer]) -> tuple[np.ndarray, np.ndarray]:
    if bounds is not None:
        try:
            lower, upper = (np.asarray(b, dtype=np.float64) for b in bounds)
        except (TypeError, ValueError):
            raise ValueError(f"bounds must be ((x0, y0, z0), (x1, y1, z1)) in metres, got {bounds!r}") from None
        if lower.shape != (3,) or upper.shape != (3,):
            raise ValueError(f"bounds must be ((x0, y0, z0), (x1, y1, z1)) in metres, got {bounds!r}")
        if not (np.isfinite(lower).all() and np.isfinite(upper).all() and (lower < upper).all()):
            raise ValueError(f"bounds need finite lower < upper on every axis, got lower={lower}, upper={upper}")
        return lower, upper
    nonempty = [layer.points for layer in layers if len(layer.points)]
    if not nonempty:
        raise ValueError("no points to fit the view to; pass bounds=((x0, y0, z0), (x1, y1, z1))")
    lower = np.min([p.min(axis=0) for p in nonempty], axis=0)
    upper = np.max([p.max(axis=0) for p in nonempty], axis=0)
    extent = upper - lower
    pad = np.where(extent > 0, 0.0, 0.5 * extent.max() if extent.max() > 0 else 0.05)  # flat or single-point data
    return lower - pad, upper + pad


def _fit_camera(view, lower, upper, size: tuple[int, int], title: bool) -> _Camera:
    right, up, toward = view_axes(view)
    width, height = size
    corners = _box_corners(lower, upper)
    su, sv = corners @ right, corners @ up
    margin = MARGIN_FRACTION * min(width, height)
    top = margin + (TITLE_BAND_PX if title else 0)
    avail_w, avail_h = max(width - 2 * margin, 1.0), max(height - margin - top, 1.0)
    extent_u, extent_v = float(su.max() - su.min()), float(sv.max() - sv.min())
    scale = min(avail_w / extent_u if extent_u > 0 else math.inf, avail_h / extent_v if extent_v > 0 else math.inf)
    mid_u, mid_v = 0.5 * float(su.max() + su.min()), 0.5 * float(sv.max() + sv.min())
    centre = (0.5 * width, top + 0.5 * avail_h)
    return _Camera(right, up, toward, scale, (centre[0] - scale * mid_u, centre[1] + scale * mid_v))


def _radius_px(layer: Layer, camera: _Camera, size: tuple[int, int]) -> float:
    """Particle radius in pixels: the layer's own, or AUTO_RADIUS_SPACING × its mean particle spacing."""
    if layer.radius is not None:
        return max(layer.radius * camera.scale, MIN_RADIUS_PX)
    points = layer.points
    cap = MAX_AUTO_RADIUS_FRACTION * min(size)
    if len(points) < 2:
        return cap / 2
    extent = points.max(axis=0) - points.min(axis=0)
    extent = extent[extent > 1e-6 * max(extent.max(), 1e-12)]  # flat layers: density in 2-D or 1-D
    if extent.size == 0:
        return cap / 2
    spacing = (float(np.prod(extent)) / len(points)) ** (1.0 / extent.size)
    return float(np.clip(AUTO_RADIUS_SPACING * spacing * camera.scale, 1.0, cap))


def _rasterise(u, v, radius, rank, width: int, height: int, best: np.ndarray) -> None:
    """For every pixel a disk covers, keep in `best` the largest depth rank (nearest particle) seen so far.

    A disk centred in pixel (i, j) reaches pixels i ± ceil(r + 0.5); the squared distances from the centre
    to pixel centres are separable (du² + dv²), so they are built per axis and summed by broadcasting.
    """
    reach = int(math.ceil(float(radius.max()) + 0.5))
    offsets = np.arange(-reach, reach + 1, dtype=np.int32)
    span = len(offsets)
    chunk = max(1, CHUNK_CANDIDATES // (span * span))
    for start in range(0, len(u), chunk):
        cu, cv = u[start : start + chunk], v[start : start + chunk]
        px = np.floor(cu).astype(np.int32)[:, None] + offsets  # (M, span) pixel columns
        py = np.floor(cv).astype(np.int32)[:, None] + offsets  # (M, span) pixel rows
        du2 = np.square((px + 0.5 - cu[:, None]).astype(np.float32))
        dv2 = np.square((py + 0.5 - cv[:, None]).astype(np.float32))
        du2[(px < 0) | (px >= width)] = np.inf  # off-image pixels never hit
        dv2[(py < 0) | (py >= height)] = np.inf
        r2 = np.square(radius[start : start + chunk].astype(np.float32))
        hit = dv2[:, :, None] + du2[:, None, :] <= r2[:, None, None]  # (M, span, span)
        i, a, b = np.nonzero(hit)
        if i.size:
            pixel = py[i, a].astype(np.int64) * width + px[i, b]
            np.maximum.at(best, pixel, rank[start : start + chunk][i])


def _shade(best, u, v, depth, radius, colors, camera_depth_range, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel indices covered by particles and their RGB in [0, 1] (sphere shading × depth cue)."""
    pixel = np.flatnonzero(best >= 0)
    owner = best[pixel]
    du = (pixel % width + 0.5 - u[owner]) / radius[owner]  # screen right, in radii
    dv = -(pixel // width + 0.5 - v[owner]) / radius[owner]  # screen up, in radii
    dn = np.sqrt(np.clip(1.0 - du * du - dv * dv, 0.0, 1.0))  # sphere normal towards the viewer
    normal = np.stack([du, dv, dn], axis=1)
    lambert = np.clip(normal @ LIGHT_DIR, 0.0, None)
    half = LIGHT_DIR + np.array([0.0, 0.0, 1.0])
    specular = np.clip(normal @ (half / np.linalg.norm(half)), 0.0, None) ** SHININESS
    near, far = camera_depth_range
    farness = np.clip((far - depth[owner]) / max(far - near, 1e-12), 0.0, 1.0)  # 0 nearest, 1 farthest
    cue = 1.0 - DEPTH_CUE * farness
    rgb = colors[owner] * ((AMBIENT + DIFFUSE * lambert) * cue)[:, None] + (SPECULAR * specular * cue)[:, None]
    return pixel, np.clip(rgb, 0.0, 1.0)


def _font(size_px: int):
    try:
        return ImageFont.load_default(size=size_px)
    except (TypeError, OSError):  # Pillow built without FreeType: fixed bitmap font
        return ImageFont.load_default()


def _draw_box(draw: ImageDraw.ImageDraw, camera: _Camera, lower, upper, front: bool) -> None:
    """Bounds edges: the far half (front=False) goes under the particles, the near half over them."""
    corners = _box_corners(lower, upper)
    u, v, depth = camera.project(corners)
    centre_depth = 0.5 * (depth.max() + depth.min())
    for a, b in _box_edges():
        is_front = 0.5 * (depth[a] + depth[b]) >= centre_depth - 1e-9
        if is_front == front:
            draw.line([(u[a], v[a]), (u[b], v[b])], fill=BOX_COLOR, width=1)


def _draw_axes(draw: ImageDraw.ImageDraw, camera: _Camera, size: tuple[int, int], ink, font) -> None:
    """Small x/y/z triad (red/green/blue) in the bottom-left corner showing the world axes' directions."""
    length = max(10.0, 0.045 * min(size))
    origin = (8 + length, size[1] - 8 - length)
    for axis, (name, color) in enumerate((("x", (220, 40, 40)), ("y", (30, 160, 30)), ("z", (40, 70, 220)))):
        e = np.zeros(3)
        e[axis] = 1.0
        du, dv = float(e @ camera.right), -float(e @ camera.up)
        if du * du + dv * dv < 1e-6:  # axis points at the camera: a dot
            draw.ellipse([origin[0] - 2, origin[1] - 2, origin[0] + 2, origin[1] + 2], fill=color)
            continue
        tip = (origin[0] + length * du, origin[1] + length * dv)
        draw.line([origin, tip], fill=color, width=2)
        draw.text((tip[0] + 2 * du - 3, tip[1] + 2 * dv - 6), name, fill=color, font=font)


def _draw_legend(draw: ImageDraw.ImageDraw, layers: list[Layer], size: tuple[int, int], ink, font) -> None:
    labelled = [layer for layer in layers if layer.label]
    y = 6
    for layer in labelled:
        text_w = draw.textlength(layer.label, font=font)
        x = size[0] - 6 - text_w - 16
        swatch = tuple(int(round(255 * c)) for c in layer.color)
        draw.rectangle([x, y + 2, x + 10, y + 12], fill=swatch, outline=ink)
        draw.text((x + 16, y), layer.label, fill=ink, font=font)
        y += 16


def _write_png_atomic(image: Image.Image, path: str | os.PathLike) -> None:
    """Write to a temporary file in the target folder, then rename it over `path` (readers never see half a PNG)."""
    from fluidlab_core.files import atomic_path

    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG")


def render(
    layers: Layer | Sequence[Layer],
    path: str | os.PathLike | None = None,
    view: str | tuple[float, float] = "iso",
    bounds=None,
    size: tuple[int, int] = (640, 480),
    background: Color = (1.0, 1.0, 1.0),
    title: str | None = None,
    draw_bounds: bool = True,
    draw_axes: bool = True,
) -> np.ndarray:
    """Render particle layers to an (H, W, 3) uint8 RGB image, and write it as PNG when `path` is given.

    layers:      one Layer or a sequence of them; nearer particles cover farther ones whatever the order.
    path:        PNG file to write (atomically; parent folders are created), or None.
    view:        a name in VIEWS ("front", "side", "top", "iso") or an (azimuth_deg, elevation_deg) tuple.
    bounds:      ((x0, y0, z0), (x1, y1, z1)) in metres the view is fitted to; default: the points' box.
    size:        (width, height) in pixels.
    background:  (r, g, b) in [0, 1].
    title:       text drawn at the top left, or None.
    draw_bounds: draw the bounds box edges as thin gray lines.
    draw_axes:   draw a small x/y/z triad (red/green/blue) in the bottom-left corner.
    """
    if isinstance(layers, Layer):
        layers = [layers]
    layers = list(layers)
    for i, layer in enumerate(layers):
        if not isinstance(layer, Layer):
            raise ValueError(f"layers[{i}] must be a Layer, got {type(layer).__name__}")
    try:
        width, height = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"size must be (width, height) in pixels, got {size!r}") from None
    if width <= 0 or height <= 0:
        raise ValueError(f"size must be positive (width, height) in pixels, got {size!r}")
    background = _check_rgb(background, "background")
    lower, upper = _resolve_bounds(bounds, layers)
    camera = _fit_camera(view, lower, upper, (width, height), title=bool(title))

    # project all particles; rank them far (0) to near (N-1)
    points = np.concatenate([layer.points for layer in layers]) if layers else np.zeros((0, 3))
    u, v, depth = camera.project(points)
    radius = np.concatenate(
        [np.full(len(layer.points), _radius_px(layer, camera, (width, height))) for layer in layers] or [[]]
    )
    colors = np.concatenate([np.tile(layer.color, (len(layer.points), 1)) for layer in layers] or [np.zeros((0, 3))])
    order = np.argsort(depth, kind="stable")
    rank = np.empty(len(points), dtype=np.int64)
    rank[order] = np.arange(len(points))

    # z-buffer of depth ranks, one disk size at a time
    best = np.full(width * height, -1, dtype=np.int64)
    for r in np.unique(radius):
        sel = radius == r
        _rasterise(u[sel], v[sel], radius[sel], rank[sel], width, height, best)
    covered = best >= 0
    best[covered] = order[best[covered]]  # rank → particle index

    # shade covered pixels
    box_depth = _box_corners(lower, upper) @ camera.toward
    pixel, rgb = _shade(best, u, v, depth, radius, colors, (box_depth.min(), box_depth.max()), width)
    canvas = np.empty((width * height, 3), dtype=np.uint8)
    canvas[:] = np.round(255 * np.asarray(background)).astype(np.uint8)
    back = Image.fromarray(canvas.reshape(height, width, 3))
    if draw_bounds:  # far box edges under the particles
        _draw_box(ImageDraw.Draw(back), camera, lower, upper, front=False)
    canvas = np.asarray(back).reshape(-1, 3).copy()
    canvas[pixel] = np.round(255 * rgb).astype(np.uint8)
    image = Image.fromarray(canvas.reshape(height, width, 3))

    # overlays
    draw = ImageDraw.Draw(image)
    ink = (0, 0, 0) if sum(background) > 1.5 else (255, 255, 255)
    font = _font(max(10, min(14, height // 32)))
    if draw_bounds:
        _draw_box(draw, camera, lower, upper, front=True)
    if draw_axes:
        _draw_axes(draw, camera, (width, height), ink, font)
    if title:
        draw.text((6, 4), title, fill=ink, font=font)
    _draw_legend(draw, layers, (width, height), ink, font)

    if path is not None:
        _write_png_atomic(image, path)
    return np.asarray(image).copy()


def gas_slice(view, spec, path=None, field: str = "temperature", axis: int = 2, at: float | None = None,
              size: tuple[int, int] = (800, 600), title: str | None = None, vmin=None, vmax=None,
              points=None, tools=None, time: float = 0.0) -> np.ndarray:
    """A slice of a gas field as a picture: the cells of the plane `axis` = `at` (m; default the middle of the gas
    box), coloured by `field` ("temperature" in °C, "smoke", "speed", or a named scalar), solids grey, the tools'
    origins `tools` (T, 3) m marked, optional `points` (P, 3) (e.g. sensors) as dots. World axes label the picture
    (REP-103). `view` is the gas's fluidlab_core.gas.GasView, `spec` its GasSpec, `time` (s) goes into the title.
    The temperature's colour scale is the scene's fixed range (GasSpec.temperature_range) unless vmin/vmax say
    otherwise. Returns the RGB image (H, W, 3) uint8 and writes it as a PNG if `path` is given."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if field == "temperature" and vmin is None and vmax is None:
        vmin, vmax = (t - 273.15 for t in spec.temperature_range())
    shape = view.temperature.shape
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2 (x, y, z), got {axis!r}")
    lo = spec.lower[axis]
    at = lo + 0.5 * shape[axis] * spec.dx if at is None else float(at)
    k = int(np.clip(np.floor((at - lo) / spec.dx), 0, shape[axis] - 1))
    if field == "speed":
        values, unit = np.linalg.norm(view.velocity, axis=-1), "m/s"
    elif field == "temperature":
        values, unit = view.temperature - 273.15, "°C"
    else:
        values, unit = view.field(field), ("kg/m³" if field == "smoke" else "")
    plane = np.take(values, k, axis=axis)
    solid = np.take(view.solid, k, axis=axis)
    other = [d for d in range(3) if d != axis]
    extent = [spec.lower[other[0]], spec.lower[other[0]] + shape[other[0]] * spec.dx,
              spec.lower[other[1]], spec.lower[other[1]] + shape[other[1]] * spec.dx]
    dpi = 100
    fig, ax = plt.subplots(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    shown = np.ma.masked_where(solid, plane)
    cmap = plt.get_cmap("coolwarm" if field == "temperature" else "viridis").copy()
    cmap.set_bad((0.55, 0.55, 0.55))
    im = ax.imshow(shown.T, origin="lower", extent=extent, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    fig.colorbar(im, ax=ax, label=f"{field} ({unit})" if unit else field)
    for p in np.asarray(tools if tools is not None else np.zeros((0, 3)), dtype=np.float64).reshape(-1, 3):
        ax.plot(p[other[0]], p[other[1]], "k^", markersize=8)
    if points is not None:
        pts = np.asarray(points).reshape(-1, 3)
        ax.plot(pts[:, other[0]], pts[:, other[1]], "wo", markersize=3, markeredgecolor="k", markeredgewidth=0.5)
    names = "xyz"
    ax.set_xlabel(f"{names[other[0]]} (m)")
    ax.set_ylabel(f"{names[other[1]]} (m)")
    ax.set_title(title or f"{field}, {names[axis]} = {lo + (k + 0.5) * spec.dx:.3f} m, t = {time:.2f} s")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    buf.seek(0)
    image = Image.open(buf).convert("RGB")
    if path is not None:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        _write_png_atomic(image, path)
    return np.asarray(image)
