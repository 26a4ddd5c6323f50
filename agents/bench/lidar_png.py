"""The picture of a real-log run: the map over the real scan endpoints at the true poses.

Drawn with :class:`agents.files.render.Canvas` (no matplotlib): endpoints as light grey pixels, the
true path in grey, the estimated path in green, the map's walls coloured by likelihood (orange =
unlikely, blue = certain) with their corners; a legend box (top left) and a scale bar (bottom
left) lettered in a small built-in 3x5 pixel font.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from agents.files.render import POINTS_COLOR, Canvas, draw_wireframe
from mapping.wireframe import Wireframe

Color = tuple[int, int, int]

ENDPOINT_COLOR: Color = POINTS_COLOR
TRUE_PATH_COLOR: Color = (90, 90, 90)
ESTIMATE_COLOR: Color = (0, 160, 60)
WALL_COLOR: Color = (20, 70, 200)
TEXT_COLOR: Color = (0, 0, 0)

__all__ = ["lidar_png", "text_width"]

# 3x5 glyphs, one string of 15 bits per character (rows top to bottom, "1" = ink).
_GLYPHS = {
    "0": "111101101101111", "1": "010110010010111", "2": "111001111100111", "3": "111001111001111",
    "4": "101101111001001", "5": "111100111001111", "6": "111100111101111", "7": "111001010010010",
    "8": "111101111101111", "9": "111101111001111",
    "a": "010101111101101", "b": "110101110101110", "c": "011100100100011", "d": "110101101101110",
    "e": "111100110100111", "f": "111100110100100", "g": "011100101101011", "h": "101101111101101",
    "i": "111010010010111", "j": "001001001101010", "k": "101101110101101", "l": "100100100100111",
    "m": "101111111101101", "n": "110101101101101", "o": "010101101101010", "p": "110101110100100",
    "q": "010101101110011", "r": "110101110101101", "s": "011100010001110", "t": "111010010010010",
    "u": "101101101101111", "v": "101101101101010", "w": "101101111111101", "x": "101101010101101",
    "y": "101101010010010", "z": "111001010100111",
    " ": "000000000000000", ".": "000000000000010", "-": "000000111000000", ":": "000010000010000",
    "(": "010100100100010", ")": "010001001001010", "%": "101001010100101", "/": "001001010100100",
    ",": "000000000010100", "=": "000111000111000", "+": "000010111010000",
}
_SCALE = 2  # pixels per font pixel
_ADVANCE = 4 * _SCALE  # 3 columns + 1 blank


def text_width(text: str) -> int:
    """Width in pixels of ``text`` in the built-in font."""
    return len(text) * _ADVANCE - _SCALE if text else 0


def _text(canvas: Canvas, row: int, col: int, text: str, color: Color = TEXT_COLOR) -> None:
    """Letter ``text`` with its top-left corner at pixel ``(row, col)`` (lower case; unknown
    characters are blank)."""
    img = canvas.image
    for k, ch in enumerate(text.lower()):
        bits = _GLYPHS.get(ch, _GLYPHS[" "])
        for i, b in enumerate(bits):
            if b != "1":
                continue
            r = row + (i // 3) * _SCALE
            c = col + k * _ADVANCE + (i % 3) * _SCALE
            if 0 <= r and r + _SCALE <= img.shape[0] and 0 <= c and c + _SCALE <= img.shape[1]:
                img[r : r + _SCALE, c : c + _SCALE] = color


def _box(canvas: Canvas, r0: int, c0: int, r1: int, c1: int, fill: Color, edge: Color) -> None:
    img = canvas.image
    r0, c0 = max(r0, 0), max(c0, 0)
    r1, c1 = min(r1, img.shape[0]), min(c1, img.shape[1])
    if r1 <= r0 or c1 <= c0:
        return
    img[r0:r1, c0:c1] = fill
    img[r0, c0:c1] = edge
    img[r1 - 1, c0:c1] = edge
    img[r0:r1, c0] = edge
    img[r0:r1, c1 - 1] = edge


def _nice_length(metres: float) -> float:
    """The largest of 1, 2, 5 times a power of ten not above ``metres``."""
    if not metres > 0:
        return 1.0
    p = 10.0 ** math.floor(math.log10(metres))
    return max(m * p for m in (1.0, 2.0, 5.0) if m * p <= metres)


def lidar_png(
    wf: Wireframe,
    endpoints: ArrayLike,
    true_path: ArrayLike,
    estimate: ArrayLike | None = None,
    *,
    title: str = "",
    max_px: int = 1400,
) -> bytes:
    """The map over the real scan endpoints at the true poses, as PNG bytes.

    Parameters
    ----------
    wf : Wireframe
        The map (best particle).
    endpoints : (m, 2) array
        Real scan endpoints placed at the true poses (world frame).
    true_path, estimate : (k, 2) arrays
        The true and the estimated sensor positions.
    title : str
        A line above the legend (e.g. the log's name and its scores).
    max_px : int
        The image's larger side.
    """
    ep = np.asarray(endpoints, dtype=np.float64).reshape(-1, 2)
    truth = np.asarray(true_path, dtype=np.float64).reshape(-1, 2)
    est = None if estimate is None else np.asarray(estimate, dtype=np.float64).reshape(-1, 2)
    pts = [a for a in (ep, truth, est, np.asarray(wf.points).reshape(-1, 2)) if a is not None and len(a)]
    allp = np.concatenate(pts) if pts else np.zeros((1, 2))
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    canvas = Canvas((lo[0], lo[1], hi[0], hi[1]), max_px=max_px, margin_px=60)
    canvas.dots(ep, ENDPOINT_COLOR)
    if len(truth) >= 2:
        canvas.polyline(truth, TRUE_PATH_COLOR, 1.5)
    if est is not None and len(est) >= 2:
        canvas.polyline(est, ESTIMATE_COLOR, 1.5)
    draw_wireframe(canvas, wf, edge_color=None, width=2.0, point_radius=2.5)

    # Legend, top left.
    items: list[tuple[Color, str]] = [
        (WALL_COLOR, "map walls (blue certain, orange unlikely)"),
        (ENDPOINT_COLOR, "real scan endpoints at the true poses"),
        (TRUE_PATH_COLOR, "true path"),
        *([(ESTIMATE_COLOR, "estimated path")] if est is not None and len(est) >= 2 else []),
    ]
    lines = ([title] if title else []) + [t for _, t in items]
    line_h = 7 * _SCALE
    width = max(text_width(t) for t in lines) + 40
    height = line_h * len(lines) + 12
    _box(canvas, 6, 6, 6 + height, 6 + width, (255, 255, 255), (0, 0, 0))
    row = 12
    if title:
        _text(canvas, row, 14, title)
        row += line_h
    for color, label in items:
        canvas.image[row + 3 : row + 7, 14:34] = color
        _text(canvas, row, 40, label)
        row += line_h

    # Scale bar, bottom left: a round length near a fifth of the view.
    bar_m = _nice_length((canvas.width - 2 * canvas.margin) / canvas.scale / 5.0)
    bar_px = max(1, round(bar_m * canvas.scale))
    r = canvas.height - 24
    c0 = 16
    canvas.image[r : r + 4, c0 : c0 + bar_px] = TEXT_COLOR
    canvas.image[r - 6 : r + 4, c0 : c0 + 2] = TEXT_COLOR
    canvas.image[r - 6 : r + 4, c0 + bar_px - 2 : c0 + bar_px] = TEXT_COLOR
    _text(canvas, r + 7, c0, f"{bar_m:g} m")
    return canvas.to_png()

