"""Rendering: PNG encoder/decoder, the rasteriser (pixel checks), wireframe pictures, SVG."""

import struct
import xml.etree.ElementTree as ET
import zlib

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from agents.files.render import (
    LABEL_COLORS,
    TRAJECTORY_COLOR,
    TRUTH_COLOR,
    Canvas,
    decode_png,
    draw_wireframe,
    encode_png,
    likelihood_colors,
    map_png,
    wireframe_svg,
)
from mapping import Label, Wireframe

WHITE = (255, 255, 255)
RED = (255, 0, 0)


def chunks(png):
    pos, out = 8, []
    while pos < len(png):
        (n,) = struct.unpack(">I", png[pos : pos + 4])
        tag, body = png[pos + 4 : pos + 8], png[pos + 8 : pos + 8 + n]
        (crc,) = struct.unpack(">I", png[pos + 8 + n : pos + 12 + n])
        out.append((tag, body, crc))
        pos += 12 + n
    return out


# ---------------------------------------------------------------------- PNG
def test_png_structure_by_hand():
    img = np.zeros((2, 3, 3), dtype=np.uint8)
    img[0, 0] = (255, 0, 0)
    img[1, 2] = (1, 2, 3)
    png = encode_png(img)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    cs = chunks(png)
    assert [c[0] for c in cs] == [b"IHDR", b"IDAT", b"IEND"]
    for tag, body, crc in cs:
        assert zlib.crc32(tag + body) & 0xFFFFFFFF == crc
    w, h, depth, ctype, comp, filt, interlace = struct.unpack(">IIBBBBB", cs[0][1])
    assert (w, h, depth, ctype, comp, filt, interlace) == (3, 2, 8, 2, 0, 0, 0)
    raw = zlib.decompress(cs[1][1])
    # one filter byte (0 = none) per row, then the row's RGB triples
    assert raw == bytes([0, 255, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 2, 3])


@settings(max_examples=30, deadline=None)
@given(arrays(np.uint8, st.tuples(st.integers(1, 12), st.integers(1, 12), st.just(3))))
def test_png_round_trip(img):
    assert np.array_equal(decode_png(encode_png(img)), img)


def test_decode_png_handles_all_filters():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, size=(5, 4, 3), dtype=np.uint8)
    h, w = img.shape[:2]
    bpp, stride = 3, 3 * w
    rows = img.reshape(h, stride).astype(np.int32)
    raw = bytearray()
    for y in range(h):
        f = y % 5
        cur, prev = rows[y], rows[y - 1] if y else np.zeros(stride, np.int32)
        enc = []
        for x in range(stride):
            a = cur[x - bpp] if x >= bpp else 0
            b = prev[x]
            c = prev[x - bpp] if x >= bpp else 0
            if f == 0:
                pred = 0
            elif f == 1:
                pred = a
            elif f == 2:
                pred = b
            elif f == 3:
                pred = (a + b) // 2
            else:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            enc.append((int(cur[x]) - int(pred)) & 0xFF)
        raw += bytes([f, *enc])

    def chunk(tag, data):
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))

    png = (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(bytes(raw)))
        + chunk(b"IEND", b"")
    )
    assert np.array_equal(decode_png(png), img)


def test_decode_png_rejects_bad_input():
    png = bytearray(encode_png(np.zeros((2, 2, 3), np.uint8)))
    with pytest.raises(ValueError, match="signature"):
        decode_png(b"GIF89a" + bytes(png[6:]))
    png[-20] ^= 0xFF  # inside IDAT
    with pytest.raises(ValueError, match="CRC"):
        decode_png(bytes(png))
    with pytest.raises(ValueError):
        encode_png(np.zeros((2, 2), np.uint8))


# ---------------------------------------------------------------------- canvas
def test_canvas_geometry_and_y_axis_up():
    c = Canvas((0, 0, 10, 5), px_per_m=10, margin_px=5)
    assert (c.width, c.height) == (110, 60)
    assert c.pixel_of((0.01, 4.99)) == (5, 5)  # world top-left -> image top-left
    assert c.pixel_of((9.99, 0.01)) == (54, 104)  # world bottom-right -> image bottom-right
    c2 = Canvas((0, 0, 30, 10), max_px=320, margin_px=10)
    assert c2.scale == pytest.approx(10.0) and c2.width == 320
    with pytest.raises(ValueError):
        Canvas((0, 0, float("nan"), 1))
    with pytest.raises(ValueError):
        Canvas((0, 0, 1, 1), px_per_m=-1)


def test_line_pixels():
    c = Canvas((0, 0, 10, 10), px_per_m=10, margin_px=0)
    c.line((1, 5), (9, 5), RED, width=3)
    img = c.image
    row, col = c.pixel_of((5, 5))
    # the row through the line is fully red between the ends, white well away from it
    assert tuple(img[row, col]) == RED or tuple(img[row - 1, col]) == RED
    band = img[row - 1 : row + 1, 15:85]
    assert np.all(band[..., 0] == 255) and np.all(band[..., 1] <= 128)
    assert tuple(img[row - 6, col]) == WHITE and tuple(img[row + 6, col]) == WHITE
    assert tuple(img[row, 5]) == WHITE and tuple(img[row, 95]) == WHITE  # beyond the ends
    # a vertical line is drawn in the right column (x) and rows flipped (y up)
    c.line((2, 1), (2, 3), (0, 0, 255), width=1)
    r_top, col2 = c.pixel_of((2, 2.9))
    r_bot, _ = c.pixel_of((2, 1.1))
    assert r_top < r_bot
    assert img[r_top, col2 - 1 : col2 + 1, 2].min() >= 128 or img[r_top, col2, 2] == 255


def test_markers_have_their_shapes():
    c = Canvas((0, 0, 10, 10), px_per_m=10, margin_px=0)
    c.point((2.05, 5.05), RED, radius=5, shape="circle")
    c.point((5.05, 5.05), RED, radius=5, shape="square")
    c.point((8.05, 5.05), RED, radius=5, shape="triangle")
    img = c.image
    r, cc = c.pixel_of((2.05, 5.05))
    assert tuple(img[r, cc]) == RED
    assert tuple(img[r - 4, cc - 4]) == WHITE  # corner of the box is outside the circle
    r, cs = c.pixel_of((5.05, 5.05))
    assert tuple(img[r - 4, cs - 4]) == RED and tuple(img[r + 4, cs + 4]) == RED
    assert tuple(img[r - 7, cs]) == WHITE
    r, ct = c.pixel_of((8.05, 5.05))
    assert tuple(img[r, ct]) == RED
    assert tuple(img[r - 3, ct]) == RED  # towards the apex (up)
    assert tuple(img[r - 3, ct - 3]) == WHITE  # beside the apex
    assert tuple(img[r + 2, ct - 3]) == RED  # the base is wide
    with pytest.raises(ValueError, match="shape"):
        c.point((1, 1), RED, shape="star")


def test_polygon_fill_with_hole():
    c = Canvas((0, 0, 10, 10), px_per_m=10, margin_px=0, background=(0, 0, 0))
    poly = shapely.Polygon([(1, 1), (9, 1), (9, 9), (1, 9)], [[(4, 4), (6, 4), (6, 6), (4, 6)]])
    c.polygon_fill(poly, WHITE)
    img = c.image
    assert tuple(img[c.pixel_of((2, 2))]) == WHITE
    assert tuple(img[c.pixel_of((5, 5))]) == (0, 0, 0)  # the hole
    assert tuple(img[c.pixel_of((0.5, 0.5))]) == (0, 0, 0)  # outside
    assert (img[..., 0] == 255).sum() == 64 * 100 - 4 * 100  # exactly the area in pixels
    c.polygon_fill(shapely.MultiPolygon([shapely.box(0, 0, 1, 1)]), RED)
    assert tuple(img[c.pixel_of((0.5, 0.5))]) == RED


def test_save_png(tmp_path):
    c = Canvas((0, 0, 1, 1), px_per_m=8, margin_px=1)
    c.point((0.5, 0.5), RED, 2)
    p = tmp_path / "sub" / "a.png"
    c.save_png(p)
    img = decode_png(p.read_bytes())
    assert img.shape == (10, 10, 3)
    assert tuple(img[5, 5]) == RED


# ---------------------------------------------------------------------- wireframes
def labelled_wireframe():
    pts = [(0, 0), (4, 0), (4, 3), (0, 3)]
    return Wireframe.build(pts, [(0, 1), (1, 2), (2, 3)], labels=[0, 1, 2, 0], likelihood=[1.0, 0.5, 0.0])


def test_likelihood_colors():
    c = likelihood_colors([0.0, 1.0, 2.0, -1.0])
    assert tuple(c[0]) == (255, 160, 40) and tuple(c[1]) == (20, 70, 200)
    assert tuple(c[2]) == tuple(c[1]) and tuple(c[3]) == tuple(c[0])


def test_draw_wireframe_pixels():
    wf = labelled_wireframe()
    c = Canvas((0, 0, 4, 3), px_per_m=20, margin_px=10)
    draw_wireframe(c, wf, edge_color=None, width=3, point_radius=4)
    img = c.image
    # the certain edge (0 -> 1) is blue at its midpoint, the unlikely one (2 -> 3) orange
    assert tuple(img[c.pixel_of((2.0, 0.0))]) == (20, 70, 200)
    assert tuple(img[c.pixel_of((2.0, 3.0))]) == (255, 160, 40)
    # corners coloured by label
    assert tuple(img[c.pixel_of((0.0, 0.0))]) == LABEL_COLORS[Label.NOMINAL]
    assert tuple(img[c.pixel_of((4.0, 0.0))]) == LABEL_COLORS[Label.OCCLUSION]
    assert tuple(img[c.pixel_of((4.0, 3.0))]) == LABEL_COLORS[Label.FRONTIER]
    # no edge from 3 back to 0
    assert tuple(img[c.pixel_of((0.0, 1.5))]) == WHITE


def test_draw_wireframe_arrows_and_hidden_labels():
    wf = Wireframe.build([(0, 0), (10, 0)], [(0, 1)])
    c = Canvas((0, -1, 10, 1), px_per_m=10, margin_px=0)
    draw_wireframe(c, wf, edge_color=(0, 0, 0), arrows=True, width=1, label_colors={})
    img = c.image
    # arrowhead at the midpoint points right: its barbs are left of the midpoint
    r, col = c.pixel_of((5.0, 0.0))
    barbs_left = (img[r - 6 : r - 1, col - 8 : col - 1] < 128).any()
    barbs_right = (img[r - 6 : r - 1, col + 3 : col + 10] < 128).any()
    assert barbs_left and not barbs_right
    assert tuple(img[c.pixel_of((0.05, 0.0))]) != LABEL_COLORS[Label.NOMINAL]


def test_map_png_shows_truth_trajectory_and_map():
    truth = Wireframe.from_polylines([[(0, 0), (10, 0), (10, 10), (0, 10)]])
    wf = Wireframe.build([(0, 0), (10, 0)], [(0, 1)], likelihood=[1.0])
    traj = np.array([[2.0, 5.025], [8.0, 5.025]])  # through pixel centres
    img = decode_png(map_png(wf, truth=truth, trajectory=traj, px_per_m=20))
    # map the same way the function does
    c = Canvas((0, 0, 10, 10), px_per_m=20, margin_px=20)
    assert img.shape == (c.height, c.width, 3)
    assert tuple(img[c.pixel_of((0.0, 5.0))]) == TRUTH_COLOR  # a truth wall not in the map
    r, col = c.pixel_of((5.0, 0.0))  # the map edge on top (anti-aliased across two rows)
    px = img[r - 1 : r + 1, col].astype(int)
    assert np.all(px[:, 2] - px[:, 0] > 100)
    assert tuple(img[c.pixel_of((5.0, 5.025))]) == TRAJECTORY_COLOR
    assert tuple(img[c.pixel_of((8.0, 2.0))]) == WHITE


def test_wireframe_svg():
    wf = labelled_wireframe()
    truth = Wireframe.from_polylines([[(0, 0), (4, 0), (4, 3), (0, 3)]])
    svg = wireframe_svg(wf, truth=truth, trajectory=[(1, 1), (2, 2)], title="a <test>")
    root = ET.fromstring(svg)
    ns = "{http://www.w3.org/2000/svg}"
    edges = [e for e in root.iter(f"{ns}line") if e.get("class") == "edge"]
    assert len(edges) == wf.n_edges
    assert ([(int(e.get("data-from")), int(e.get("data-to"))) for e in edges]
            == [tuple(e) for e in wf.edges.tolist()])
    assert all(e.get("marker-end") == "url(#arrow)" for e in edges)
    truth_g = next(g for g in root.iter(f"{ns}g") if g.get("class") == "truth")
    assert len(list(truth_g)) == truth.n_edges
    assert len([e for e in root.iter(f"{ns}circle") if e.get("class") == "nominal"]) == 2
    assert len([e for e in root.iter(f"{ns}polygon") if e.get("class") == "occlusion"]) == 1
    assert len([e for e in root.iter(f"{ns}rect") if e.get("class") == "frontier"]) == 1
    # y up: vertex 3 (y = 3) is drawn above vertex 0 (y = 0)
    circles = {int(e.get("data-index")): e for e in root.iter(f"{ns}circle")}
    assert float(circles[3].get("cy")) < float(circles[0].get("cy"))
    assert float(circles[3].get("cx")) == pytest.approx(float(circles[0].get("cx")))
    assert root.find(f"{ns}title").text == "a <test>"
    assert root.find(f"{ns}polyline").get("class") == "trajectory"


def test_render_builtin_world():
    """(How fast: `wiremap bench speed --pieces`, render_museum_ms.)"""
    from agents.sim.world import load_world

    w = load_world("museum")
    png = map_png(w.truth, truth=w.truth, max_px=1000)
    img = decode_png(png)
    assert img.shape[1] == 1000 or img.shape[0] == 1000
