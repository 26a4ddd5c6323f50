"""Pictures of maps and worlds without matplotlib: a small anti-aliased numpy rasteriser, a PNG
encoder/decoder (zlib + struct) and an SVG writer.

World coordinates are metres with the y axis pointing **up**; the image's rows run downwards,
so rasterising flips y. A :class:`Canvas` maps a world rectangle onto an RGB image at a fixed
scale (``px_per_m``), keeping the aspect ratio.

Drawing conventions of the paper's figures (Fig. 2-4): walls are lines, a nominal corner is a
red circle, an occlusion vertex a triangle, a frontier vertex a square. In :func:`map_png` the
truth is light grey underneath, map edges are coloured by likelihood (orange = unlikely, blue =
certain) and the trajectory is green.
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mapping.wireframe import Label, Wireframe

__all__ = [
    "LABEL_COLORS",
    "LABEL_SHAPES",
    "Canvas",
    "decode_png",
    "draw_wireframe",
    "encode_png",
    "likelihood_colors",
    "map_figure",
    "map_png",
    "wireframe_svg",
]

Color = tuple[int, int, int]

#: Vertex colours per label.
LABEL_COLORS: dict[Label, Color] = {
    Label.NOMINAL: (220, 30, 30),
    Label.OCCLUSION: (150, 40, 200),
    Label.FRONTIER: (240, 140, 0),
}
#: Vertex marker shapes per label (paper Fig. 2/4).
LABEL_SHAPES: dict[Label, str] = {Label.NOMINAL: "circle", Label.OCCLUSION: "triangle",
                                  Label.FRONTIER: "square"}

TRUTH_COLOR: Color = (200, 200, 200)
#: The truth in :func:`map_figure`: wider than the map's walls and darker than
#: :data:`OUTSIDE_COLOR`, so it shows on both sides of a mapped wall.
FIGURE_TRUTH_COLOR: Color = (165, 175, 190)
#: Outside the world's free space (as ``wiremap world show`` shades it, lighter).
OUTSIDE_COLOR: Color = (222, 222, 222)
#: One colour per robot (robot ``k`` of a map's ``robots``), shared with the Rerun recording.
ROBOT_COLORS: tuple[Color, ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (188, 189, 34),
    (23, 190, 207),
    (127, 127, 127),
)
TRAJECTORY_COLOR: Color = (0, 160, 60)
#: Points under a map (a real log's scan endpoints).
POINTS_COLOR: Color = (150, 150, 150)
_LOW: Color = (255, 160, 40)  # likelihood 0
_HIGH: Color = (20, 70, 200)  # likelihood 1


def likelihood_colors(lik: ArrayLike) -> NDArray[np.uint8]:
    """``(m, 3)`` RGB colours for likelihoods in [0, 1]: orange (0) to blue (1), linearly."""
    t = np.clip(np.asarray(lik, dtype=np.float64).reshape(-1, 1), 0.0, 1.0)
    c = (1.0 - t) * np.array(_LOW, dtype=np.float64) + t * np.array(_HIGH, dtype=np.float64)
    return np.asarray(np.round(c), dtype=np.uint8)


# ---------------------------------------------------------------------- PNG
def _chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def encode_png(rgb: NDArray[np.uint8], level: int = 6) -> bytes:
    """Encode an ``(h, w, 3)`` uint8 image as an 8-bit RGB PNG (filter type 0 on every row)."""
    img = np.ascontiguousarray(rgb, dtype=np.uint8)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"expected an (h, w, 3) image, got {img.shape}")
    h, w = img.shape[:2]
    raw = np.empty((h, 1 + 3 * w), dtype=np.uint8)
    raw[:, 0] = 0
    raw[:, 1:] = img.reshape(h, 3 * w)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", zlib.compress(raw.tobytes(), level))
        + _chunk(b"IEND", b"")
    )


def decode_png(data: bytes) -> NDArray[np.uint8]:
    """Decode an 8-bit RGB, non-interlaced PNG (what :func:`encode_png` writes; all five row
    filters are supported) to ``(h, w, 3)`` uint8. Checks every chunk's CRC.

    Raises
    ------
    ValueError
        Not a PNG, a bad CRC, or a PNG kind this reader does not handle.
    """
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG (bad signature)")
    pos, idat, header = 8, [], None
    while pos < len(data):
        if pos + 8 > len(data):
            raise ValueError("truncated PNG chunk header")
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        tag = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        if zlib.crc32(tag + body) & 0xFFFFFFFF != crc:
            raise ValueError(f"bad CRC in PNG chunk {tag.decode(errors='replace')}")
        if tag == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            idat.append(body)
        elif tag == b"IEND":
            break
        pos += 12 + length
    if header is None:
        raise ValueError("PNG has no IHDR")
    w, h, depth, ctype, _, _, interlace = header
    if depth != 8 or ctype != 2 or interlace != 0:
        raise ValueError("only 8-bit RGB non-interlaced PNGs are supported")
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), dtype=np.uint8).reshape(h, 1 + 3 * w)
    out = np.zeros((h, 3 * w), dtype=np.int32)
    bpp = 3
    for y in range(h):
        f, line = int(raw[y, 0]), raw[y, 1:].astype(np.int32)
        prev = out[y - 1] if y else np.zeros(3 * w, dtype=np.int32)
        if f == 0:
            cur = line
        elif f == 2:
            cur = (line + prev) & 0xFF
        elif f in (1, 3, 4):
            cur = np.zeros(3 * w, dtype=np.int32)
            for x in range(3 * w):
                a = int(cur[x - bpp]) if x >= bpp else 0
                b = int(prev[x])
                c = int(prev[x - bpp]) if x >= bpp else 0
                if f == 1:
                    pred = a
                elif f == 3:
                    pred = (a + b) // 2
                else:
                    p = a + b - c
                    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                    pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                cur[x] = (int(line[x]) + pred) & 0xFF
        else:
            raise ValueError(f"bad PNG filter type {f} on row {y}")
        out[y] = cur
    return out.reshape(h, w, 3).astype(np.uint8)


# ---------------------------------------------------------------------- canvas
class Canvas:
    """An RGB image over a world rectangle.

    Parameters
    ----------
    bounds : (xmin, ymin, xmax, ymax)
        World rectangle to show (metres); a degenerate one is widened to 1 m.
    px_per_m : float, optional
        Scale. By default the larger side of ``bounds`` fills ``max_px - 2 * margin_px``.
    max_px : int
        Upper limit of the image's larger side when ``px_per_m`` is not given.
    margin_px : int
        Blank border around ``bounds``.
    background : RGB

    Notes
    -----
    Shapes are anti-aliased: each pixel's coverage is estimated from the signed distance of its
    centre to the shape (one pixel wide ramp) and the colour is blended by it. Widths and radii
    are in pixels.
    """

    def __init__(
        self,
        bounds: Sequence[float],
        *,
        px_per_m: float | None = None,
        max_px: int = 1600,
        margin_px: int = 20,
        background: Color = (255, 255, 255),
    ) -> None:
        xmin, ymin, xmax, ymax = (float(v) for v in bounds)
        if not all(math.isfinite(v) for v in (xmin, ymin, xmax, ymax)) or xmax < xmin or ymax < ymin:
            raise ValueError(f"bad bounds {tuple(bounds)}")
        if xmax - xmin < 1e-9:
            xmin, xmax = xmin - 0.5, xmax + 0.5
        if ymax - ymin < 1e-9:
            ymin, ymax = ymin - 0.5, ymax + 0.5
        if margin_px < 0:
            raise ValueError("margin_px must be >= 0")
        if px_per_m is None:
            if max_px <= 2 * margin_px:
                raise ValueError("max_px must exceed twice the margin")
            px_per_m = (max_px - 2 * margin_px) / max(xmax - xmin, ymax - ymin)
        if not (px_per_m > 0 and math.isfinite(px_per_m)):
            raise ValueError("px_per_m must be positive")
        self.bounds = (xmin, ymin, xmax, ymax)
        self.scale = float(px_per_m)
        self.margin = int(margin_px)
        self.width = math.ceil((xmax - xmin) * self.scale) + 2 * self.margin
        self.height = math.ceil((ymax - ymin) * self.scale) + 2 * self.margin
        if self.width * self.height > 64_000_000:
            raise ValueError(f"image of {self.width} x {self.height} px is too large")
        self.image = np.empty((self.height, self.width, 3), dtype=np.uint8)
        self.image[:] = np.asarray(background, dtype=np.uint8)

    # -------------------------------------------------------------- coordinates
    def to_px(self, xy: ArrayLike) -> NDArray[np.float64]:
        """World ``(k, 2)`` to continuous pixel coordinates ``(col, row)``; pixel ``(c, r)``
        covers ``[c, c+1) x [r, r+1)``, so its centre is at ``(c + 0.5, r + 0.5)``."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        xmin, _, _, ymax = self.bounds
        out = np.empty_like(p)
        out[:, 0] = self.margin + (p[:, 0] - xmin) * self.scale
        out[:, 1] = self.margin + (ymax - p[:, 1]) * self.scale
        return out

    def pixel_of(self, xy: ArrayLike) -> tuple[int, int]:
        """``(row, col)`` of the pixel containing world point ``xy``."""
        c = self.to_px(xy)[0]
        return math.floor(c[1]), math.floor(c[0])

    # -------------------------------------------------------------- blending
    def _blend(self, r0: int, c0: int, alpha: NDArray[np.float64], color: Color) -> None:
        if alpha.size == 0:
            return
        region = self.image[r0 : r0 + alpha.shape[0], c0 : c0 + alpha.shape[1]]
        a = alpha[..., None]
        col = np.asarray(color, dtype=np.float64)
        region[:] = np.round(region * (1.0 - a) + col * a).astype(np.uint8)

    def _window(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> tuple[int, int, int, int] | None:
        c0 = max(math.floor(lo[0]), 0)
        r0 = max(math.floor(lo[1]), 0)
        c1 = min(math.ceil(hi[0]) + 1, self.width)
        r1 = min(math.ceil(hi[1]) + 1, self.height)
        if c1 <= c0 or r1 <= r0:
            return None
        return r0, r1, c0, c1

    # -------------------------------------------------------------- shapes
    def line(self, a: ArrayLike, b: ArrayLike, color: Color, width: float = 1.0) -> None:
        """A segment from world ``a`` to ``b``, ``width`` pixels wide with round caps."""
        self.lines(np.array([[a, b]], dtype=np.float64), color, width)

    def lines(self, segs: ArrayLike, color: Color, width: float = 1.0) -> None:
        """Segments ``(k, 2, 2)`` (world), all in one colour."""
        s = np.asarray(segs, dtype=np.float64).reshape(-1, 2, 2)
        if len(s) == 0:
            return
        px = self.to_px(s.reshape(-1, 2)).reshape(-1, 2, 2)
        half = max(float(width), 0.5) / 2.0
        for a, b in px:
            self._capsule(a, b, half, color)

    def polyline(self, xy: ArrayLike, color: Color, width: float = 1.0) -> None:
        """Consecutive points ``(k, 2)`` joined by segments."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if len(p) >= 2:
            self.lines(np.stack([p[:-1], p[1:]], axis=1), color, width)
        elif len(p) == 1:
            self.point(p[0], color, width / 2)

    def _capsule(self, a: NDArray[np.float64], b: NDArray[np.float64], half: float, color: Color) -> None:
        pad = half + 1.0
        win = self._window(np.minimum(a, b) - pad, np.maximum(a, b) + pad)
        if win is None:
            return
        r0, r1, c0, c1 = win
        cy, cx = np.mgrid[r0:r1, c0:c1]
        px, py = cx + 0.5, cy + 0.5
        d = b - a
        l2 = float(d @ d)
        if l2 > 0:
            t = np.clip(((px - a[0]) * d[0] + (py - a[1]) * d[1]) / l2, 0.0, 1.0)
        else:
            t = np.zeros_like(px)
        dist = np.hypot(px - (a[0] + t * d[0]), py - (a[1] + t * d[1]))
        self._blend(r0, c0, np.clip(half + 0.5 - dist, 0.0, 1.0), color)

    def point(self, xy: ArrayLike, color: Color, radius: float = 3.0, shape: str = "circle") -> None:
        """One marker at world ``xy``: ``circle``, ``square`` or ``triangle`` (pointing up),
        ``radius`` pixels from centre to edge (square: half side; triangle: circumradius)."""
        self.points(np.asarray(xy, dtype=np.float64).reshape(1, 2), color, radius, shape)

    def dots(self, xy: ArrayLike, color: Color) -> None:
        """One pixel at each world point ``(k, 2)`` (many points: scan endpoints); points outside
        the image are skipped."""
        if len(np.asarray(xy).reshape(-1, 2)) == 0:
            return
        p = np.floor(self.to_px(xy)).astype(np.int64)
        ok = (p[:, 0] >= 0) & (p[:, 1] >= 0) & (p[:, 0] < self.width) & (p[:, 1] < self.height)
        self.image[p[ok, 1], p[ok, 0]] = np.asarray(color, dtype=np.uint8)

    def points(self, xy: ArrayLike, color: Color, radius: float = 3.0, shape: str = "circle") -> None:
        """Markers at world points ``(k, 2)``."""
        if shape not in ("circle", "square", "triangle"):
            raise ValueError(f"unknown marker shape {shape!r} (circle, square or triangle)")
        p = self.to_px(xy)
        r = max(float(radius), 0.5)
        for cxy in p:
            win = self._window(cxy - r - 1.0, cxy + r + 1.0)
            if win is None:
                continue
            r0, r1, c0, c1 = win
            gy, gx = np.mgrid[r0:r1, c0:c1]
            dx, dy = gx + 0.5 - cxy[0], gy + 0.5 - cxy[1]
            if shape == "circle":
                sd = np.hypot(dx, dy) - r
            elif shape == "square":
                sd = np.maximum(np.abs(dx), np.abs(dy)) - r
            else:
                # equilateral triangle, apex up (image rows grow downwards): three half-planes
                inr = r / 2.0
                n = np.array([[0.0, 1.0], [math.sqrt(3) / 2, -0.5], [-math.sqrt(3) / 2, -0.5]])
                sd = np.max(np.stack([dx * nx + dy * ny for nx, ny in n]), axis=0) - inr
            self._blend(r0, c0, np.clip(0.5 - sd, 0.0, 1.0), color)

    def polygon_fill(self, geom: Any, color: Color) -> None:
        """Fill a shapely (Multi)Polygon (or anything with polygons in ``.geoms``), holes left
        out. Pixel centres are tested with the even-odd rule on all rings (no anti-aliasing)."""
        rings = list(_rings(geom))
        if not rings:
            return
        segs = []
        for r in rings:
            p = self.to_px(r)
            segs.append(np.stack([p[:-1], p[1:]], axis=1) if len(p) > 1 else np.zeros((0, 2, 2)))
        s = np.concatenate(segs)
        if len(s) == 0:
            return
        y0s, y1s = s[:, 0, 1], s[:, 1, 1]
        x0s, x1s = s[:, 0, 0], s[:, 1, 0]
        lo = max(math.floor(min(y0s.min(), y1s.min())), 0)
        hi = min(math.ceil(max(y0s.max(), y1s.max())) + 1, self.height)
        col = np.asarray(color, dtype=np.uint8)
        xs_pix = np.arange(self.width) + 0.5
        for row in range(lo, hi):
            yc = row + 0.5
            crosses = (y0s <= yc) != (y1s <= yc)
            if not crosses.any():
                continue
            ya, yb, xa, xb = y0s[crosses], y1s[crosses], x0s[crosses], x1s[crosses]
            xi = np.sort(xa + (yc - ya) * (xb - xa) / (yb - ya))
            # even-odd: a pixel centre is inside when an odd number of crossings lie left of it
            inside = (np.searchsorted(xi, xs_pix) % 2) == 1
            self.image[row, inside] = col

    # -------------------------------------------------------------- output
    def to_png(self) -> bytes:
        return encode_png(self.image)

    def save_png(self, path: str | os.PathLike[str]) -> None:
        """Write the PNG atomically (:func:`agents.files.io.write_atomic`)."""
        from agents.files.io import write_atomic

        write_atomic(path, self.to_png())


def _rings(geom: Any) -> Iterable[NDArray[np.float64]]:
    if geom is None or getattr(geom, "is_empty", True):
        return
    if hasattr(geom, "geoms"):
        for g in geom.geoms:
            yield from _rings(g)
    elif hasattr(geom, "exterior"):
        yield np.asarray(geom.exterior.coords, dtype=np.float64)[:, :2]
        for h in geom.interiors:
            yield np.asarray(h.coords, dtype=np.float64)[:, :2]


# ---------------------------------------------------------------------- wireframes
def draw_wireframe(
    canvas: Canvas,
    wf: Wireframe,
    *,
    edge_color: Color | None = None,
    label_colors: Mapping[Label, Color | None] | None = None,
    arrows: bool = False,
    width: float = 2.0,
    point_radius: float = 3.0,
) -> None:
    """Draw a wireframe: edges, then its vertices.

    Parameters
    ----------
    edge_color : RGB or None
        One colour for all edges; None colours each by its likelihood
        (:func:`likelihood_colors`).
    label_colors : mapping Label -> RGB or None
        Vertex colour per label (default :data:`LABEL_COLORS`); None for a label (or an empty
        mapping) leaves those vertices out. Shapes follow :data:`LABEL_SHAPES`.
    arrows : bool
        Draw an arrowhead at each edge's midpoint showing its direction.
    """
    segs = wf.segments()
    if edge_color is not None:
        canvas.lines(segs, edge_color, width)
    else:
        cols = likelihood_colors(wf.likelihood)
        for seg, c in zip(segs, cols):
            canvas.lines(seg[None], (int(c[0]), int(c[1]), int(c[2])), width)
    if arrows and len(segs):
        size = max(4.0, 3.0 * width) / canvas.scale  # metres
        for k, (a, b) in enumerate(segs):
            d = b - a
            n = float(np.hypot(*d))
            if n < 1e-12:
                continue
            u = d / n
            s = min(size, 0.4 * n)
            tip = (a + b) / 2 + u * s / 2
            left = tip - u * s + np.array([-u[1], u[0]]) * s / 2
            right = tip - u * s - np.array([-u[1], u[0]]) * s / 2
            c = (edge_color if edge_color is not None
                 else tuple(int(v) for v in likelihood_colors(wf.likelihood[k])[0]))
            canvas.lines(np.array([[left, tip], [right, tip]]), c, width)
    colors: Mapping[Label, Color | None] = LABEL_COLORS if label_colors is None else label_colors
    for lab in Label:
        col = colors.get(lab)
        if col is None:
            continue
        sel = wf.labels == int(lab)
        if sel.any():
            canvas.points(wf.points[sel], col, point_radius, LABEL_SHAPES[lab])


def _auto_bounds(*items: Any) -> tuple[float, float, float, float]:
    pts = []
    for it in items:
        if it is None:
            continue
        if isinstance(it, Wireframe):
            if it.n_vertices:
                pts.append(np.asarray(it.points))
        else:
            a = np.asarray(it, dtype=np.float64).reshape(-1, 2)
            if len(a):
                pts.append(a)
    if not pts:
        return (0.0, 0.0, 1.0, 1.0)
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def map_png(
    wf: Wireframe,
    truth: Wireframe | None = None,
    trajectory: ArrayLike | None = None,
    *,
    px_per_m: float | None = None,
    max_px: int = 1200,
    arrows: bool = False,
) -> bytes:
    """The standard "map over truth" picture as PNG bytes.

    The truth (if given) in light grey underneath, the trajectory ``(k, 2)`` (if given) in green,
    then the map: edges coloured by likelihood, corners by label (nominal red circle, occlusion
    triangle, frontier square). The view covers all three.
    """
    traj = None if trajectory is None else np.asarray(trajectory, dtype=np.float64).reshape(-1, 2)
    canvas = Canvas(_auto_bounds(wf, truth, traj), px_per_m=px_per_m, max_px=max_px)
    w = max(1.5, min(3.0, canvas.scale * 0.08))
    if truth is not None:
        draw_wireframe(canvas, truth, edge_color=TRUTH_COLOR, label_colors={}, width=w + 2.0)
    if traj is not None:
        canvas.polyline(traj, TRAJECTORY_COLOR, 1.5)
    draw_wireframe(canvas, wf, edge_color=None, arrows=arrows, width=w, point_radius=w + 1.5)
    return canvas.to_png()


# ---------------------------------------------------------------------- SVG
def _hex(c: Sequence[int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*(int(v) for v in c[:3]))


def wireframe_svg(
    wf: Wireframe,
    *,
    truth: Wireframe | None = None,
    trajectory: ArrayLike | None = None,
    px_per_m: float | None = None,
    max_px: int = 1000,
    margin_px: float = 20.0,
    arrows: bool = True,
    title: str | None = None,
    trajectories: Sequence[tuple[ArrayLike, Color]] = (),
) -> str:
    """An SVG picture of a wireframe (optionally over a grey truth, with a green trajectory and
    more trajectories, each ``(points, colour)``: a fleet's routes).

    World y points up: SVG y is ``ymax - y``, scaled. Each map edge is a ``<line>`` of class
    ``edge`` with ``data-from``/``data-to``/``data-likelihood``; each vertex a ``circle``,
    ``polygon`` (triangle) or ``rect`` of class ``nominal``/``occlusion``/``frontier``. With
    ``arrows`` every map edge ends in an arrowhead marker showing its direction.
    """
    given = [(trajectory, TRAJECTORY_COLOR)] if trajectory is not None else []
    lines = [(np.asarray(t, dtype=np.float64).reshape(-1, 2), c) for t, c in [*given, *trajectories]]
    xmin, ymin, xmax, ymax = _auto_bounds(wf, truth, *(t for t, _ in lines))
    span = max(xmax - xmin, ymax - ymin, 1e-9)
    s = float(px_per_m) if px_per_m is not None else (max_px - 2 * margin_px) / span
    m = float(margin_px)
    width = (xmax - xmin) * s + 2 * m
    height = (ymax - ymin) * s + 2 * m

    def tx(p: NDArray[np.float64]) -> tuple[float, float]:
        return (m + (float(p[0]) - xmin) * s, m + (ymax - float(p[1])) * s)

    sw = max(1.0, min(3.0, 0.08 * s))
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.1f}" height="{height:.1f}" '
        f'viewBox="0 0 {width:.3f} {height:.3f}">',
    ]
    if title:
        out.append(f"<title>{_xml_escape(title)}</title>")
    if arrows:
        out.append(
            '<defs><marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="5" '
            'markerHeight="5" orient="auto-start-reverse"><path d="M 0 0 L 10 5 L 0 10 z" '
            'fill="context-stroke"/></marker></defs>'
        )
    out.append(f'<rect x="0" y="0" width="{width:.3f}" height="{height:.3f}" fill="#ffffff"/>')
    if truth is not None:
        out.append(f'<g class="truth" stroke="{_hex(TRUTH_COLOR)}" stroke-width="{sw + 2:.2f}" '
                   'stroke-linecap="round">')
        for a, b in truth.segments():
            (x1, y1), (x2, y2) = tx(a), tx(b)
            out.append(f'<line x1="{x1:.3f}" y1="{y1:.3f}" x2="{x2:.3f}" y2="{y2:.3f}"/>')
        out.append("</g>")
    for line, color in lines:
        if len(line) >= 2:
            pts = " ".join(f"{x:.3f},{y:.3f}" for x, y in (tx(p) for p in line))
            out.append(f'<polyline class="trajectory" points="{pts}" fill="none" '
                       f'stroke="{_hex(color)}" stroke-width="1.5"/>')
    marker = ' marker-end="url(#arrow)"' if arrows else ""
    out.append(f'<g class="map" stroke-width="{sw:.2f}" stroke-linecap="round">')
    cols = likelihood_colors(wf.likelihood)
    for (i, j), lk, c in zip(wf.edges.tolist(), wf.likelihood.tolist(), cols):
        (x1, y1), (x2, y2) = tx(wf.points[i]), tx(wf.points[j])
        out.append(
            f'<line class="edge" data-from="{i}" data-to="{j}" data-likelihood="{lk:.4g}" x1="{x1:.3f}" '
            f'y1="{y1:.3f}" x2="{x2:.3f}" y2="{y2:.3f}" stroke="{_hex(c)}"{marker}/>'
        )
    out.append("</g>")
    r = sw + 1.5
    out.append('<g class="corners">')
    for k, (p, lab) in enumerate(zip(wf.points, wf.labels.tolist())):
        x, y = tx(p)
        label = Label(lab)
        fill = _hex(LABEL_COLORS[label])
        cls = f'class="{label.text}" data-index="{k}"'
        if label is Label.NOMINAL:
            out.append(f'<circle {cls} cx="{x:.3f}" cy="{y:.3f}" r="{r:.2f}" fill="{fill}"/>')
        elif label is Label.FRONTIER:
            out.append(f'<rect {cls} x="{x - r:.3f}" y="{y - r:.3f}" width="{2 * r:.2f}" '
                       f'height="{2 * r:.2f}" fill="{fill}"/>')
        else:
            tri = [(x, y - r), (x + r * 0.866, y + r / 2), (x - r * 0.866, y + r / 2)]
            pts = " ".join(f"{a:.3f},{b:.3f}" for a, b in tri)
            out.append(f'<polygon {cls} points="{pts}" fill="{fill}"/>')
    out.append("</g>")
    out.append("</svg>")
    return "\n".join(out) + "\n"


def _xml_escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


# ---------------------------------------------------------------------- figures
def _nice_length(span_m: float) -> float:
    """A round length (1, 2 or 5 times a power of ten) of about a fifth of ``span_m``."""
    target = max(span_m / 5.0, 1e-6)
    p = 10.0 ** math.floor(math.log10(target))
    for f in (5.0, 2.0, 1.0):
        if f * p <= target:
            return f * p
    return p


def _fmt_m(v: float) -> str:
    return f"{v:g} m" if v >= 1 else f"{v * 100:g} cm"


def _font(size: int) -> Any:
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


def map_figure(
    wf: Wireframe,
    truth: Wireframe | None = None,
    *,
    title: str = "map",
    trajectories: Mapping[str, ArrayLike] | None = None,
    free: Any = None,
    max_px: int = 1000,
    points: ArrayLike | None = None,
    points_label: str = "scan endpoints",
) -> bytes:
    """The picture every command writes (``wiremap map``, ``run``, ``watch --save``,
    ``export --format png``), as PNG bytes: a self-explanatory figure.

    From the top: the ``title``; the map (outside the world's ``free`` space shaded, the
    ``truth`` underneath as wide blue-grey lines, each robot's trajectory in its colour, then
    the map's walls coloured by likelihood and its corners by label); below it the legend (the
    corner symbols, the wall colours, the truth, the shading, one line per trajectory), a scale
    bar and a north arrow (north is +y, up). ``points`` (``(k, 2)``, such as a real log's scan
    endpoints) are drawn as grey pixels under everything, in the legend as ``points_label``; the
    picture's extent takes in all but their outer 0.5 % on each axis (stray long returns).
    """
    tracks = {str(k): np.asarray(v, dtype=np.float64).reshape(-1, 2) for k, v in (trajectories or {}).items()}
    tracks = {k: v for k, v in tracks.items() if len(v)}
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2) if points is not None else np.zeros((0, 2))
    items: list[Any] = [wf, truth, *tracks.values()]
    if len(pts):
        items.append(np.percentile(pts, [0.5, 99.5], axis=0))
    if free is not None and not getattr(free, "is_empty", True):
        xmin, ymin, xmax, ymax = free.bounds
        items.append(np.array([[xmin, ymin], [xmax, ymax]]))
    bounds = _auto_bounds(*items)
    span = max(bounds[2] - bounds[0], bounds[3] - bounds[1], 1e-9)
    # leave room for the legend: the map is at most max_px wide and tall
    canvas = Canvas(bounds, max_px=max_px, margin_px=24)
    if free is not None and not getattr(free, "is_empty", True):
        canvas.image[:] = np.asarray(OUTSIDE_COLOR, dtype=np.uint8)
        canvas.polygon_fill(free, (255, 255, 255))
    w = max(1.5, min(3.0, canvas.scale * 0.08))
    if len(pts):
        canvas.dots(pts, POINTS_COLOR)
    if truth is not None:
        draw_wireframe(canvas, truth, edge_color=FIGURE_TRUTH_COLOR, label_colors={}, width=w + 5.0)
    colours: dict[str, Color] = {}
    for k, (name, xy) in enumerate(sorted(tracks.items())):
        colours[name] = ROBOT_COLORS[k % len(ROBOT_COLORS)] if len(tracks) > 1 else TRAJECTORY_COLOR
        canvas.polyline(xy, colours[name], 1.5)
    draw_wireframe(canvas, wf, edge_color=None, width=w, point_radius=w + 1.5)

    # ---- legend rows (pixels; y grows downwards here)
    width = max(canvas.width, 560)
    row_h, title_h = 22, 34
    legend_rows = 3 + (1 if tracks else 0)
    height = title_h + canvas.height + row_h * legend_rows + 12
    img = np.full((height, width, 3), 255, dtype=np.uint8)
    x0 = (width - canvas.width) // 2
    img[title_h : title_h + canvas.height, x0 : x0 + canvas.width] = canvas.image
    texts: list[tuple[int, int, str, int]] = [(12, 8, title, 18)]
    panel = Canvas((0.0, 0.0, float(width), float(height)), px_per_m=1.0, margin_px=0)
    panel.image = img

    def at(x: float, row_y: float) -> tuple[float, float]:  # panel pixel -> panel "world" (y up)
        return (x, height - row_y)

    top = title_h + canvas.height + 6
    r = w + 1.5
    y = top + row_h / 2
    x = 16.0
    for lab, name in ((Label.NOMINAL, "nominal corner"), (Label.OCCLUSION, "occlusion corner"),
                      (Label.FRONTIER, "frontier corner")):
        panel.point(at(x, y), LABEL_COLORS[lab], r, LABEL_SHAPES[lab])
        texts.append((int(x + 10), int(y - 7), name, 13))
        x += 150
    y += row_h
    x = 16.0
    for t in np.linspace(0.0, 1.0, 8):
        c = likelihood_colors([t])[0]
        panel.line(at(x + 5 * t * 7, y), at(x + 5 * t * 7 + 5, y), (int(c[0]), int(c[1]), int(c[2])), w)
    texts.append((int(x + 46), int(y - 7), "wall, likelihood low to high", 13))
    x += 250
    if truth is not None or not len(pts):
        panel.line(at(x, y), at(x + 30, y), FIGURE_TRUTH_COLOR, w + 5.0)
        texts.append((int(x + 38), int(y - 7), "truth", 13))
        x += 90
    if len(pts):
        grey = np.asarray(POINTS_COLOR, dtype=np.uint8)
        for k in range(5):
            panel.image[int(y) - 4 + 2 * k, int(x) : int(x) + 24 : 3] = grey
        texts.append((int(x + 30), int(y - 7), points_label, 13))
        x += 40 + 7 * len(points_label)
    if free is not None:
        panel.image[int(y - 7) : int(y + 7), int(x) : int(x + 24)] = np.asarray(OUTSIDE_COLOR, dtype=np.uint8)
        texts.append((int(x + 30), int(y - 7), "outside the world", 13))
    if tracks:
        y += row_h
        x = 16.0
        for name, col in colours.items():
            panel.line(at(x, y), at(x + 24, y), col, 2.0)
            label = f"{name}: path" if len(tracks) > 1 else f"{name}"
            texts.append((int(x + 30), int(y - 7), label, 13))
            x += 40 + 8 * len(label)
            if x > width - 80:
                break
    # scale bar and north arrow
    y += row_h
    length = _nice_length(span)
    px = length * canvas.scale
    x = 16.0
    panel.line(at(x, y), at(x + px, y), (0, 0, 0), 2.0)
    for tick in (x, x + px):
        panel.line(at(tick, y - 5), at(tick, y + 5), (0, 0, 0), 1.5)
    texts.append((int(x + px + 8), int(y - 7), _fmt_m(length), 13))
    nx = width - 40.0
    panel.line(at(nx, y + 6), at(nx, y - 12), (0, 0, 0), 2.0)
    panel.line(at(nx - 5, y - 6), at(nx, y - 12), (0, 0, 0), 2.0)
    panel.line(at(nx + 5, y - 6), at(nx, y - 12), (0, 0, 0), 2.0)
    texts.append((int(nx + 9), int(y - 9), "N", 14))

    from PIL import Image, ImageDraw

    pil = Image.fromarray(panel.image)
    draw = ImageDraw.Draw(pil)
    for tx, ty, text, size in texts:
        draw.text((tx, ty), text, fill=(0, 0, 0), font=_font(size))
    return encode_png(np.asarray(pil, dtype=np.uint8))
