"""The annotated frame: a solved frame drawn the way astrometry.net users expect it.

The identified stars circled and named, the constellation stick figures, the detected sources no
star explains (small squares), an RA/Dec grid and a title line (where the image centre points, the
field of view, the roll, the status), drawn with Pillow over the frame as 8-bit grey.

Geometry, the only thing here that can be wrong without looking wrong: a sky direction ``v`` (an
ICRS unit vector, apparent place) lands on frame pixel ``camera.vectors_to_pixels(R v)``, the
solved camera model (distortion included) under the attitude ``R`` (ICRS -> camera,
docs/conventions.md).  The canvas is the grey image enlarged by an integer ``zoom``; the grey image is
the frame averaged over ``scale`` x ``scale`` blocks (1 for the frame itself, more for the stored
previews), so frame pixel ``x`` is canvas pixel ``(x + 0.5) k - 0.5`` with ``k = zoom / scale``
(pixel centres stay pixel centres).  Great-circle arcs (figure segments) and grid lines are
sampled finely and drawn as polylines, so distortion bends them as it bends the sky; directions
farther from the boresight than :data:`FIELD_MARGIN` times the half diagonal are not drawn (a
distorted projection of a far off-axis direction can fold back onto the sensor).

Nothing here reads files or knows the workflow: arrays and the camera in, an RGB array out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from app.camera import Camera
from app.catalogue import radec_to_vectors, vectors_to_radec

#: Widest canvas, pixels: a preview is enlarged back towards its frame's size, by an integer factor.
MAX_CANVAS_WIDTH = 2048
#: Directions drawn: at most this many half diagonals of the field from the boresight.
FIELD_MARGIN = 1.5
#: Grid lines across the field's span in RA or Dec: the step is the first of :data:`GRID_STEPS_DEG`
#: at least span / GRID_LINES (so 3 to 6 lines cross the frame each way).
GRID_LINES = 5
#: Grid steps, degrees: each divides 360, so RA lines meet where they wrap.
GRID_STEPS_DEG = (0.01, 0.02, 0.05, 0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 2.5, 5.0, 10.0, 15.0, 30.0, 45.0, 90.0)
#: Samples along one grid line (it spans the field plus a step on each side).
GRID_SAMPLES = 361
#: Frame pixels a polyline may run outside the frame, as a fraction of its size (Pillow clips the rest).
DRAW_MARGIN = 0.1
#: Most samples of one figure segment, and the angle between samples at most (fraction of the field's
#: diagonal): enough for a distorted arc to look bent as it is.
ARC_SAMPLES = 48
ARC_STEP_FRACTION = 1 / 96

STAR_COLOUR = (255, 214, 64)
PLANET_COLOUR = (255, 140, 220)
UNMATCHED_COLOUR = (255, 96, 64)
FIGURE_COLOUR = (72, 200, 120)
GRID_COLOUR = (110, 160, 255)
TITLE_COLOUR = (255, 255, 255)
#: Opacity of the grid lines and of the figure lines (0-255): the stars under them stay visible.
GRID_ALPHA = 120
FIGURE_ALPHA = 190
#: Opacity of the box behind the title.
TITLE_BOX_ALPHA = 170


@dataclass(frozen=True, eq=False)
class SkyLabel:
    """A direction to circle and name: an identified star or planet (``vector``: apparent ICRS unit)."""

    text: str
    vector: np.ndarray
    planet: bool = False


@dataclass(frozen=True, eq=False)
class Figure:
    """A constellation stick figure: polylines of (K, 3) ICRS unit vectors, each vertex a star."""

    abbreviation: str
    name: str
    polylines: tuple[np.ndarray, ...]


@dataclass(frozen=True, eq=False)
class Annotation:
    """What is drawn over one frame.  ``rotation`` None: nothing was solved, only the sources and the title."""

    camera: Camera
    status: str
    rotation: np.ndarray | None = None
    stars: tuple[SkyLabel, ...] = ()
    #: (N, 2) frame pixels of the detected sources no identified star or planet explains.
    unmatched_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    figures: tuple[Figure, ...] = ()


@dataclass(frozen=True, eq=False)
class GridLine:
    """One line of constant RA or Dec: its value and its visible runs, (K, 2) frame pixels each."""

    kind: Literal["ra", "dec"]
    value_deg: float
    step_deg: float
    runs: tuple[np.ndarray, ...]

    @property
    def label(self) -> str:
        decimals = max(0, -math.floor(math.log10(self.step_deg) + 1e-9)) if self.step_deg < 1 else 0
        if self.kind == "dec":
            return f"Dec {self.value_deg:+.{decimals}f}°"
        return f"RA {self.value_deg % 360.0:.{decimals}f}°"


# ---------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------

def canvas_zoom(image_width: int, scale: int) -> int:
    """The integer enlargement of a grey image averaged over ``scale`` blocks: back to the frame's size
    (``scale``) where the canvas stays within :data:`MAX_CANVAS_WIDTH`, else the most that does (>= 1)."""
    return max(1, min(int(scale), MAX_CANVAS_WIDTH // max(1, int(image_width))))


@dataclass(frozen=True)
class MarkerSizes:
    """Canvas pixels of the text and the marks: they grow with the canvas so that labels read the same."""

    font_px: int
    #: Radius of a star's circle, and half the side of an unmatched source's square.
    radius: int
    square_half: int
    #: Line widths of the circles and squares, and of the figure lines (the grid's is 1).
    mark_width: int
    figure_width: int


def marker_sizes(canvas_width: int) -> MarkerSizes:
    """Sizes for a canvas ``canvas_width`` pixels wide: text 1/80 of it (11 to 28 px), circles a little
    smaller than the text is high."""
    font_px = int(min(28, max(11, round(canvas_width / 80))))
    radius = max(6, round(0.9 * font_px))
    return MarkerSizes(font_px=font_px, radius=radius, square_half=max(3, round(0.35 * radius)),
                       mark_width=max(2, round(radius / 6)), figure_width=max(1, round(radius / 7)))


def field_cone_cos(camera: Camera) -> float:
    """Cosine of the largest angle from the boresight that is drawn (see :data:`FIELD_MARGIN`)."""
    return math.cos(min(math.radians(89.0), FIELD_MARGIN * camera.diagonal_fov_rad / 2))


def project(vectors: np.ndarray, camera: Camera, rotation: np.ndarray,
            cone_cos: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Frame pixels of (N, 3) ICRS ``vectors`` and whether each is drawable (in front, within the cone
    of :func:`field_cone_cos`, which ``cone_cos`` gives when the caller has it)."""
    cam = np.asarray(vectors, dtype=float).reshape(-1, 3) @ np.asarray(rotation, dtype=float).T
    xy, front = camera.vectors_to_pixels(cam)
    cone = field_cone_cos(camera) if cone_cos is None else cone_cos
    with np.errstate(invalid="ignore"):
        ok = front & (cam[:, 2] >= cone) & np.isfinite(xy).all(axis=1)
    return xy, ok


def runs_of(xy: np.ndarray, ok: np.ndarray) -> list[np.ndarray]:
    """The maximal stretches of consecutive ``ok`` points with two points or more."""
    runs, start = [], None
    for i, good in enumerate(list(ok) + [False]):
        if good and start is None:
            start = i
        elif not good and start is not None:
            if i - start >= 2:
                runs.append(xy[start:i])
            start = None
    return runs


def within_margin(xy: np.ndarray, camera: Camera) -> np.ndarray:
    """Points within the frame grown by :data:`DRAW_MARGIN` of its size on each side."""
    dx, dy = DRAW_MARGIN * camera.width, DRAW_MARGIN * camera.height
    with np.errstate(invalid="ignore"):
        return ((xy[:, 0] >= -0.5 - dx) & (xy[:, 0] <= camera.width - 0.5 + dx)
                & (xy[:, 1] >= -0.5 - dy) & (xy[:, 1] <= camera.height - 0.5 + dy))


def arc(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points at fractions ``t`` of the great-circle arc from unit vector ``a`` to ``b`` (slerp)."""
    theta = math.acos(max(-1.0, min(1.0, float(a @ b))))
    if theta < 1e-12:
        return np.repeat(a[None, :], len(t), axis=0)
    s = math.sin(theta)
    return (np.sin((1 - t) * theta)[:, None] * a + np.sin(t * theta)[:, None] * b) / s


def position_angle_deg(centre: np.ndarray, towards: np.ndarray) -> float:
    """Position angle (degrees, north through east, [0, 360)) of ``towards`` seen from ``centre``."""
    ra, dec = vectors_to_radec(centre)
    ra, dec = float(ra[0]), float(dec[0])
    north = np.array([-math.sin(dec) * math.cos(ra), -math.sin(dec) * math.sin(ra), math.cos(dec)])
    east = np.array([-math.sin(ra), math.cos(ra), 0.0])
    d = np.asarray(towards, dtype=float) - np.asarray(centre, dtype=float)
    return math.degrees(math.atan2(float(d @ east), float(d @ north))) % 360.0


def image_centre_pointing(camera: Camera, rotation: np.ndarray) -> tuple[float, float, float]:
    """(RA, Dec, roll) in degrees of the image's centre pixel: where it points, and the position angle of
    the image's up direction (-y) there (docs/conventions.md's roll, at the image centre)."""
    x0, y0 = (camera.width - 1) / 2, (camera.height - 1) / 2
    v = camera.pixels_to_vectors(np.array([[x0, y0], [x0, y0 - 1.0]])) @ np.asarray(rotation, dtype=float)
    ra, dec = vectors_to_radec(v[0])
    return float(np.degrees(ra[0])), float(np.degrees(dec[0])), position_angle_deg(v[0], v[1])


def grid_step(span_deg: float) -> float:
    """The first of :data:`GRID_STEPS_DEG` at least ``span_deg`` / :data:`GRID_LINES`."""
    return next((s for s in GRID_STEPS_DEG if s >= span_deg / GRID_LINES), GRID_STEPS_DEG[-1])


def field_extent(camera: Camera, rotation: np.ndarray) -> tuple[float, float, float, float]:
    """``(ra_centre, ra_half_span, dec_min, dec_max)`` in degrees of the sky the frame shows.

    From the frame's border and an interior grid of pixels (RA measured from the centre's, wrapped to
    +-180); a celestial pole on the sensor takes every RA and that pole's declination.
    """
    w, h = camera.width, camera.height
    edge = np.linspace(0.0, 1.0, 41)
    inner = np.linspace(0.0, 1.0, 7)
    fx = np.concatenate([edge, edge, np.zeros_like(edge), np.ones_like(edge), np.repeat(inner, len(inner))])
    fy = np.concatenate([np.zeros_like(edge), np.ones_like(edge), edge, edge, np.tile(inner, len(inner))])
    xy = np.column_stack([-0.5 + fx * w, -0.5 + fy * h])
    v = camera.pixels_to_vectors(xy) @ np.asarray(rotation, dtype=float)
    ra, dec = (np.degrees(a) for a in vectors_to_radec(v))
    centre_ra = float(np.degrees(vectors_to_radec(camera.pixels_to_vectors(
        np.array([[(w - 1) / 2, (h - 1) / 2]])) @ np.asarray(rotation, dtype=float))[0][0]))
    offset = (ra - centre_ra + 180.0) % 360.0 - 180.0
    half_span = float(np.max(np.abs(offset)))
    dec_min, dec_max = float(dec.min()), float(dec.max())
    for sign in (1.0, -1.0):
        pxy, ok = project(np.array([[0.0, 0.0, sign]]), camera, rotation)
        if ok[0] and camera.on_sensor(pxy)[0]:
            half_span = 180.0
            dec_min, dec_max = (dec_min, 90.0) if sign > 0 else (-90.0, dec_max)
    return centre_ra, half_span, dec_min, dec_max


def grid_lines(camera: Camera, rotation: np.ndarray) -> list[GridLine]:
    """The RA and Dec lines over the frame, in frame pixels (runs within the frame grown by
    :data:`DRAW_MARGIN`); the steps from :func:`grid_step` of the field's extent."""
    centre_ra, half_span, dec_min, dec_max = field_extent(camera, rotation)
    dec_step = grid_step(dec_max - dec_min)
    ra_step = grid_step(2 * half_span)
    if half_span >= 180.0:
        ra_lo, ra_hi = 0.0, 360.0
    else:
        ra_lo, ra_hi = centre_ra - half_span - ra_step, centre_ra + half_span + ra_step
    dec_lo, dec_hi = max(-90.0, dec_min - dec_step), min(90.0, dec_max + dec_step)
    lines: list[GridLine] = []

    def add(kind, value, ra_deg, dec_deg, step):
        v = radec_to_vectors(np.radians(ra_deg), np.radians(dec_deg))
        xy, ok = project(v, camera, rotation)
        runs = tuple(runs_of(xy, ok & within_margin(xy, camera)))
        if runs:
            lines.append(GridLine(kind=kind, value_deg=float(value), step_deg=step, runs=runs))

    ra_samples = np.linspace(ra_lo, ra_hi, GRID_SAMPLES)
    for k in range(math.ceil(dec_min / dec_step), math.floor(dec_max / dec_step) + 1):
        dec = round(k * dec_step, 10)
        if abs(dec) < 90.0:
            add("dec", dec, ra_samples, np.full(GRID_SAMPLES, dec), dec_step)
    dec_samples = np.linspace(dec_lo, dec_hi, GRID_SAMPLES)
    first = math.ceil(ra_lo / ra_step)
    for k in range(first, math.floor(ra_hi / ra_step) + 1):
        ra = round(k * ra_step, 10)
        if half_span >= 180.0 and ra >= 360.0:
            break
        add("ra", ra, np.full(GRID_SAMPLES, ra), dec_samples, ra_step)
    return lines


def figure_runs(figure: Figure, camera: Camera, rotation: np.ndarray, gap_rad: float,
                cone_cos: float | None = None) -> list[np.ndarray]:
    """Each segment of a stick figure as frame-pixel runs along its great-circle arc, stopping
    ``gap_rad`` short of both its stars (so the line never covers them).

    Every point of an arc of length theta lies within theta / 2 of one of its ends, so a segment whose
    ends are both farther than the drawn cone's radius plus theta / 2 from the boresight is skipped
    unsampled; the others are sampled and projected together.
    """
    cone_cos = field_cone_cos(camera) if cone_cos is None else cone_cos
    cone = math.acos(cone_cos)
    boresight = np.asarray(rotation, dtype=float)[2]
    step = max(1e-6, ARC_STEP_FRACTION * camera.diagonal_fov_rad)
    pieces = []
    for line in figure.polylines:
        off_axis = np.arccos(np.clip(line @ boresight, -1.0, 1.0))
        for k in range(len(line) - 1):
            a, b = line[k], line[k + 1]
            theta = math.acos(max(-1.0, min(1.0, float(a @ b))))
            if theta <= 2 * gap_rad or min(off_axis[k], off_axis[k + 1]) > cone + theta / 2:
                continue
            n = int(min(ARC_SAMPLES, max(2, math.ceil((theta - 2 * gap_rad) / step) + 1)))
            pieces.append(arc(a, b, np.linspace(gap_rad / theta, 1 - gap_rad / theta, n)))
    if not pieces:
        return []
    xy, ok = project(np.concatenate(pieces), camera, rotation, cone_cos)
    ok &= within_margin(xy, camera)
    runs, start = [], 0
    for piece in pieces:
        end = start + len(piece)
        runs += runs_of(xy[start:end], ok[start:end])
        start = end
    return runs


# ---------------------------------------------------------------------------
# Drawing
# ---------------------------------------------------------------------------

@dataclass
class _Layout:
    """Boxes already taken on the canvas (circles, squares, labels, the title): labels avoid them."""

    width: int
    height: int
    taken: list[tuple[float, float, float, float]] = field(default_factory=list)

    def inside(self, box) -> bool:
        return box[0] >= 0 and box[1] >= 0 and box[2] <= self.width - 1 and box[3] <= self.height - 1

    def free(self, box) -> bool:
        return self.inside(box) and not any(box[0] < t[2] and t[0] < box[2] and box[1] < t[3] and t[1] < box[3]
                                            for t in self.taken)

    def place(self, candidates, force: bool = True):
        """The first candidate box inside the canvas and clear of the others (taken); with ``force``,
        failing that the first inside the canvas; else None."""
        for box in candidates:
            if self.free(box):
                self.taken.append(box)
                return box
        if force:
            for box in candidates:
                if self.inside(box):
                    self.taken.append(box)
                    return box
        return None


class _Painter:
    """One canvas: sizes scale with its width so that labels read the same on every frame."""

    def __init__(self, grey: np.ndarray, scale: int, camera: Camera):
        from PIL import Image, ImageFont

        height, width = grey.shape
        if (height, width) != (-(-camera.height // scale), -(-camera.width // scale)):
            raise ValueError(f"a {width} x {height} image is not a {camera.width} x {camera.height} frame "
                             f"averaged over {scale} x {scale} blocks")
        self.zoom = canvas_zoom(width, scale)
        self.k = self.zoom / scale
        base = Image.fromarray(np.ascontiguousarray(grey, dtype=np.uint8))
        if self.zoom > 1:
            base = base.resize((width * self.zoom, height * self.zoom), Image.Resampling.BILINEAR)
        self.image = base.convert("RGBA")
        self.sizes = marker_sizes(self.image.width)
        self.font_px, self.radius = self.sizes.font_px, self.sizes.radius
        self.font = ImageFont.load_default(size=self.font_px)
        self.layout = _Layout(self.image.width, self.image.height)

    def canvas(self, xy: np.ndarray) -> np.ndarray:
        """Frame pixels -> the canvas pixels they fall in (rounded here: Pillow would truncate)."""
        return np.round((np.asarray(xy, dtype=float) + 0.5) * self.k - 0.5)

    def layer(self):
        from PIL import Image, ImageDraw

        overlay = Image.new("RGBA", self.image.size, (0, 0, 0, 0))
        return overlay, ImageDraw.Draw(overlay)

    def merge(self, overlay) -> None:
        self.image.alpha_composite(overlay)

    def text_size(self, text: str) -> tuple[float, float]:
        left, top, right, bottom = self.font.getbbox(text)
        return right - left, bottom - top

    def text_box(self, text: str, x: float, y: float) -> tuple[float, float, float, float]:
        w, h = self.text_size(text)
        return (x, y, x + w, y + h)

    def text(self, draw, box, text: str, colour) -> None:
        left, top, _, _ = self.font.getbbox(text)
        draw.text((box[0] - left, box[1] - top), text, font=self.font, fill=colour + (255,),
                  stroke_width=max(1, self.font_px // 8), stroke_fill=(0, 0, 0, 255))

    def on_canvas(self, runs: list[np.ndarray]) -> np.ndarray:
        """The canvas points of frame-pixel ``runs`` that fall on the canvas, (K, 2)."""
        if not runs:
            return np.zeros((0, 2))
        points = self.canvas(np.concatenate(runs))
        W, H = self.image.width, self.image.height
        return points[(points[:, 0] >= 0) & (points[:, 0] <= W - 1) & (points[:, 1] >= 0) & (points[:, 1] <= H - 1)]

    def box_within(self, x: float, y: float, w: float, h: float) -> tuple[float, float, float, float]:
        """A w x h box at top-left (x, y), slid as little as it takes to lie on the canvas."""
        x, y = min(max(x, 0.0), self.image.width - 1 - w), min(max(y, 0.0), self.image.height - 1 - h)
        return (x, y, x + w, y + h)

    def polylines(self, draw, runs, colour, alpha: int, width: int) -> None:
        for run in runs:
            points = [tuple(p) for p in self.canvas(run).tolist()]
            draw.line(points, fill=colour + (alpha,), width=width, joint="curve")


def annotate(grey: np.ndarray, scale: int, annotation: Annotation) -> np.ndarray:
    """The annotated frame as an RGB array: ``grey`` (uint8, the frame averaged over ``scale`` x ``scale``
    blocks) enlarged by :func:`canvas_zoom`, with everything of ``annotation`` drawn over it."""
    camera, R = annotation.camera, annotation.rotation
    painter = _Painter(grey, scale, camera)
    title_lines, title_box = _title_layout(painter, _title(annotation))

    circles = []  # (canvas x, y, label)
    if R is not None:
        R = np.asarray(R, dtype=float)
        vectors = np.array([s.vector for s in annotation.stars], dtype=float).reshape(-1, 3)
        xy, ok = project(vectors, camera, R)
        for star, p, good in zip(annotation.stars, painter.canvas(xy), ok):
            if good and -painter.radius <= p[0] <= painter.image.width + painter.radius \
                    and -painter.radius <= p[1] <= painter.image.height + painter.radius:
                circles.append((float(p[0]), float(p[1]), star))
    r = painter.radius
    for x, y, _ in circles:
        painter.layout.taken.append((x - r, y - r, x + r, y + r))
    half = painter.sizes.square_half
    squares = painter.canvas(np.asarray(annotation.unmatched_xy, dtype=float).reshape(-1, 2))
    for x, y in squares:
        painter.layout.taken.append((x - half, y - half, x + half, y + half))
    painter.layout.taken.append(title_box)
    # (box, text, colour), drawn after every line; the stars' names placed first, the rest where there is room.
    labels = [(_star_label_box(painter, x, y, star.text), star.text, PLANET_COLOUR if star.planet else STAR_COLOUR)
              for x, y, star in circles]

    overlay, draw = painter.layer()
    if R is not None:
        grid = grid_lines(camera, R)
        for line in grid:
            painter.polylines(draw, line.runs, GRID_COLOUR, GRID_ALPHA, 1)
        for line in grid:
            box = _grid_label_box(painter, line)
            if box is not None:
                labels.append((box, line.label, GRID_COLOUR))
        gap = (r + 3) / (painter.k * camera.focal_length_px)
        cone_cos = field_cone_cos(camera)
        for figure in annotation.figures:
            runs = figure_runs(figure, camera, R, gap, cone_cos)
            painter.polylines(draw, runs, FIGURE_COLOUR, FIGURE_ALPHA, painter.sizes.figure_width)
            box = _figure_label_box(painter, figure, runs)
            if box is not None:
                labels.append((box, figure.name, FIGURE_COLOUR))
    painter.merge(overlay)

    overlay, draw = painter.layer()
    width = painter.sizes.mark_width
    for x, y in squares:
        draw.rectangle((x - half, y - half, x + half, y + half), outline=UNMATCHED_COLOUR + (255,), width=width)
    for x, y, star in circles:
        colour = PLANET_COLOUR if star.planet else STAR_COLOUR
        draw.ellipse((x - r, y - r, x + r, y + r), outline=colour + (255,), width=width)
    for box, text, colour in labels:
        painter.text(draw, box, text, colour)
    painter.merge(overlay)
    _draw_title(painter, title_lines, title_box)  # last: over a circle that falls under it
    return np.asarray(painter.image.convert("RGB"))


def _title(annotation: Annotation) -> list[str]:
    """The title's parts: where the image centre points, the field, the roll, the status."""
    camera = annotation.camera
    fx, fy = camera.fov_deg
    parts = []
    if annotation.rotation is not None:
        ra, dec, roll = image_centre_pointing(camera, annotation.rotation)
        parts += [f"centre RA {ra:.4f}° Dec {dec:+.4f}°", f"field {fx:.2f}° x {fy:.2f}°", f"roll {roll:.2f}°"]
    else:
        parts.append(f"field {fx:.2f}° x {fy:.2f}° (declared)")
    parts.append(annotation.status)
    return parts


def _title_layout(painter: _Painter, parts: list[str]) -> tuple[list[str], tuple[float, float, float, float]]:
    """The title's lines (its parts joined by ' · ', wrapped to the canvas) and its box at the top left."""
    limit = painter.image.width - 2 * _title_pad(painter) - 4
    lines = [parts[0]]
    for part in parts[1:]:
        joined = f"{lines[-1]} · {part}"
        if painter.text_size(joined)[0] <= limit:
            lines[-1] = joined
        else:
            lines.append(part)
    pad = _title_pad(painter)
    width = max(painter.text_size(line)[0] for line in lines)
    return lines, (0.0, 0.0, width + 2 * pad, len(lines) * _title_line_height(painter) + 2 * pad)


def _title_pad(painter: _Painter) -> int:
    return max(3, painter.font_px // 3)


def _title_line_height(painter: _Painter) -> int:
    return round(painter.font_px * 1.3)


def _draw_title(painter: _Painter, lines: list[str], box: tuple[float, float, float, float]) -> None:
    """The title's lines on a dark box."""
    pad, height = _title_pad(painter), _title_line_height(painter)
    overlay, draw = painter.layer()
    draw.rectangle(box, fill=(0, 0, 0, TITLE_BOX_ALPHA))
    for i, line in enumerate(lines):
        painter.text(draw, painter.text_box(line, pad, pad + i * height), line, TITLE_COLOUR)
    painter.merge(overlay)


def _star_label_box(painter: _Painter, x: float, y: float, text: str):
    """Beside the circle: right, left, above, below, then the diagonals; clear of every circle."""
    r, gap = painter.radius, max(2, painter.radius // 4)
    w, h = painter.text_size(text)
    d = 0.71 * r + gap
    corners = [(x + r + gap, y - h / 2), (x - r - gap - w, y - h / 2), (x - w / 2, y - r - gap - h),
               (x - w / 2, y + r + gap), (x + d, y - d - h), (x + d, y + d), (x - d - w, y - d - h),
               (x - d - w, y + d)]
    return painter.layout.place([(cx, cy, cx + w, cy + h) for cx, cy in corners])


def _grid_label_box(painter: _Painter, line: GridLine):
    """At one end of the line where it meets the frame's edge (a Dec line's left end, an RA line's
    bottom end first), inside the canvas; a Dec circle wholly inside at its leftmost point, an RA line
    that ends at a pole on the frame only at its edge end; None where there is no room."""
    inside = painter.on_canvas(list(line.runs))
    if len(inside) == 0:
        return None
    w, h = painter.text_size(line.label)
    W, H = painter.image.width, painter.image.height
    key = inside[:, 0] if line.kind == "dec" else -inside[:, 1]
    ends = [inside[int(np.argmin(key))], inside[int(np.argmax(key))]]
    near = max(12.0, 0.03 * W)
    at_edge = [(x, y) for x, y in ends if min(x, y, W - 1 - x, H - 1 - y) <= near]
    ends = at_edge or (ends[:1] if line.kind == "dec" else [])
    gap = 4.0
    # Beside the end, on the canvas side of it, then slid along the edge to fit.
    candidates = [painter.box_within(x + gap if x < painter.image.width / 2 else x - gap - w,
                                     y - gap - h if y > painter.image.height / 2 else y + gap, w, h) for x, y in ends]
    return painter.layout.place(candidates, force=False)


def _figure_label_box(painter: _Painter, figure: Figure, runs: list[np.ndarray]):
    """The constellation's name near the middle of its lines on the canvas, where it is free."""
    inside = painter.on_canvas(runs)
    if len(inside) == 0:
        return None
    w, h = painter.text_size(figure.name)
    # Below-right or above-left of line points, the points nearest the lines' mean first (every n-th of them).
    mean = inside.mean(axis=0)
    order = np.argsort(np.hypot(inside[:, 0] - mean[0], inside[:, 1] - mean[1]))[:: max(1, len(inside) // 24)]
    candidates = [painter.box_within(bx, by, w, h) for x, y in inside[order]
                  for bx, by in ((x + 6, y + 4), (x - 6 - w, y - 4 - h))]
    return painter.layout.place(candidates, force=False)
