"""Each ball press's centre and radius found from the frame and the no-contact frame.

A ball pressed into a GelSight leaves a coloured ring: where the gel tilts, the colour changes,
most at the contact's edge, and the change fades outside it as the gel's spread flattens. The
change's magnitude (sum over channels of ``|frame - background|``) is the finder's signal:

1. Rough centre: every pixel on a strong edge of the change votes along its gradient (towards
   the brighter side, where a ring's inside lies) at the distances a ring may have (a circle
   Hough transform); the most voted point.
2. Precise centres: the presses' colour-change patches, averaged about their current centres,
   make a template of this sensor's press; each press is moved to where it matches the template
   best (normalised correlation, sub-pixel), and the template is made again (three rounds). The
   centres then agree with each other to a fraction of a pixel, and the template's own centre
   fixes where they all are: the centre of the circle fitted to its ring's outer edge. Frames that
   show no press have no part in the template. One or two presses make a template of their own,
   whose centre carries their shading's asymmetry (1-3 px at the frame's corners); three or more
   average it out (within a pixel and a half, tests/test_hard_cases_round3_presses.py).
3. Radius: around the centre, the change's mean over each circle of radius r; past its peak it
   falls towards the level far away. The radius is where it has fallen :data:`RING_EDGE_FRACTION`
   of the way, the outer edge of the bright ring as a person traces it.

A press is left out, with its reason, when its best match with the template is poor (something
else changed the frame: two touches, a slip, a smear), when its ring is not whole inside the frame,
or when the ring saturates the camera; a frame whose change does not stand out of its own noise
shows no press at all. All positions are pixels (x column, y row).

The public entry points check their arguments first (:func:`checked_frames`, :func:`checked_number`):
anything else is a :class:`GelSightRenderError` naming the argument, before any work.
"""

from __future__ import annotations

import dataclasses
import math
import numbers

import cv2
import numpy as np

from sim.gelsight_effects import GelSightRenderError

RING_EDGE_FRACTION = 0.3  # how far (0: at the peak, 1: the far level) the ring's edge has fallen
MIN_MATCH = 0.8  # normalised correlation with the template below which a press is not trusted
SATURATED_FRACTION = 0.10  # share of a ring's pixel values clipped at 0 or 255 that makes it saturated
SEARCH_PX = 6  # how far the template search moves a centre in each round
ROUNDS = 3
MAX_RING_RADII = 2.5  # the widest ring looked for, in ball radii
# Where a press's reach ends, from the frame's median (0) to its peak (1); on the shipped presses a
# pixel's change at that level is about the ring profile's edge (RING_EDGE_FRACTION) plus its halo.
REACH_LEVEL = 0.3
# A ring wider than this many ball radii cannot be a press of that ball (the gel's spread adds a
# fraction of a millimetre at most); one narrower than half of it is a press too shallow (an eighth of
# the radius deep) to calibrate from.
RING_RADIUS_RANGE = (0.5, 1.5)
# How far a press changes the frame, in ball radii, at most: the shipped presses reach 1.1-1.5 (their
# coloured halo lies outside the ring), presses rendered with a 1.9 mm contact 1.06-1.17. Beyond it
# the ball given is too small for the presses (the finder would lock onto pieces of the rings).
MAX_REACH_RADII = 2.0
# The median, over a frame's pixels, of |frame - background| averaged over channels: the shipped
# frames' fringes and drift give 4-9 levels; a frame of another sensor or light is far beyond.
MAX_BACKGROUND_MISMATCH_LEVELS = 30.0
# A frame shows a press when its change's peak (the 99.9th percentile of the smoothed change) stands
# this many spreads (median absolute deviations) above its median: camera noise alone reaches 4.6-5.2
# (a Gaussian's 99.9th percentile is 3.1 sigma, its deviation 0.67 sigma), the shipped presses 14 and
# more, a rendered press an eighth of the ball deep under 60 levels of lighting drift 9.
PRESS_CONTRAST = 8.0
# ... and by at least this many levels summed over the channels (one 8-bit level each): a frame equal
# to its background has no spread, and would otherwise count a single level's rounding as a press.
MIN_PRESS_LEVELS = 3.0
# Frame sides: a press file's smallest (sim.gelsight_check.read_press_file) and the renderer's largest
# (sim.gelsight.GelSightConfig); the finder holds about five times the frames' bytes in float copies.
FRAME_PX_RANGE = (16, 4096)
MIN_BALL_PX = 4.0  # a smaller press is a few pixels of ring: nothing to centre
# The scales and balls a press file may give (mm per pixel as the renderer takes; a ball a GelSight can press).
MM_PER_PX_RANGE = (1e-3, 10.0)
BALL_RADIUS_RANGE_MM = (0.1, 50.0)


@dataclasses.dataclass(frozen=True)
class FoundPresses:
    """Per press: centre (N x 2 px), radius (N px; NaN where not found or nothing pressed), how far its change
    reaches (:func:`change_extent_px`), the template match and why it is not trusted (empty when
    it is)."""

    centers_xy_px: np.ndarray
    radii_px: np.ndarray
    reaches_px: np.ndarray
    match: np.ndarray
    reasons: list[str]

    @property
    def trusted(self) -> np.ndarray:
        return np.array([not reason for reason in self.reasons], bool)

    @property
    def pressed(self) -> np.ndarray:
        """Whether each frame shows a press at all (trusted or not)."""
        return np.array([not reason.startswith("no press") for reason in self.reasons], bool)


def checked_number(name: str, value: object, low: float, high: float) -> float:
    """``value`` as a float when it is a real number (not a bool) in [low, high]; otherwise
    GelSightRenderError naming ``name`` (an int too large for a float included)."""
    number = math.nan
    if isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)):
        try:
            number = float(value)
        except OverflowError:
            number = math.inf
    if not low <= number <= high:
        shown = repr(value) if len(repr(value)) <= 40 else f"{repr(value)[:40]}..."
        raise GelSightRenderError(f"{name} must be a number in [{low:g}, {high:g}], got {shown}")
    return number


def checked_frames(frames: object, background: object) -> tuple[np.ndarray, np.ndarray]:
    """``frames`` (N x H x W x 3 uint8, N >= 0, H and W in FRAME_PX_RANGE) and ``background`` (H x W
    x 3 uint8, the frames' size) when they are that; otherwise GelSightRenderError naming the one
    that is not."""
    low, high = FRAME_PX_RANGE
    if not (
        isinstance(frames, np.ndarray)
        and frames.dtype == np.uint8
        and frames.ndim == 4
        and frames.shape[3] == 3
        and low <= min(frames.shape[1:3])
        and max(frames.shape[1:3]) <= high
    ):
        raise GelSightRenderError(
            f"frames must be an N x H x W x 3 uint8 array, H and W in [{low}, {high}], got "
            f"{getattr(frames, 'shape', type(frames).__name__)} {getattr(frames, 'dtype', '')}"
        )
    if not (
        isinstance(background, np.ndarray) and background.dtype == np.uint8 and background.shape == frames.shape[1:]
    ):
        raise GelSightRenderError(
            f"background must be a {' x '.join(map(str, frames.shape[1:]))} uint8 frame like the frames, got "
            f"{getattr(background, 'shape', type(background).__name__)} {getattr(background, 'dtype', '')}"
        )
    return frames, background


def change_extent_px(magnitude: np.ndarray) -> float:
    """How far a press reaches (px): the radius of the disc as large as the frame's largest region
    where ``magnitude`` (one press's change) rises REACH_LEVEL of the way from the frame's median to
    its peak (99.9th percentile), the ring's inside counted. Found without a centre or a ball radius, so
    that it still holds when the radius a lab gives is wrong: the finder then locks onto a piece of
    the ring, and the rings it finds fit the wrong ball."""
    smooth = cv2.GaussianBlur(magnitude.astype(np.float32), (0, 0), 1.0)
    far = float(np.median(smooth))
    peak = float(np.percentile(smooth, 99.9))
    changed = (smooth > far + REACH_LEVEL * (peak - far)).astype(np.uint8)
    outlines, _ = cv2.findContours(changed, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    area = max((cv2.contourArea(outline) for outline in outlines), default=0.0)
    return math.sqrt(area / math.pi)


def hough_center(magnitude: np.ndarray, radius_range_px: tuple[float, float]) -> tuple[float, float]:
    """The point the change's strongest edges point at from ``radius_range_px`` away (x, y)."""
    smooth = cv2.GaussianBlur(magnitude, (0, 0), 1.5)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
    strength = np.hypot(gx, gy)
    rows, cols = np.nonzero(strength > np.percentile(strength, 80))
    weight = strength[rows, cols]
    ux, uy = gx[rows, cols] / weight, gy[rows, cols] / weight
    h, w = magnitude.shape
    votes = np.zeros(h * w)
    for rho in np.arange(radius_range_px[0], radius_range_px[1], 0.5):
        vx, vy = np.rint(cols + ux * rho).astype(int), np.rint(rows + uy * rho).astype(int)
        inside = (vx >= 0) & (vx < w) & (vy >= 0) & (vy < h)
        votes += np.bincount(vy[inside] * w + vx[inside], weight[inside], h * w)
    votes = cv2.GaussianBlur(votes.reshape(h, w).astype(np.float32), (0, 0), 1.5)
    y, x = np.unravel_index(int(np.argmax(votes)), votes.shape)
    return float(x), float(y)


def _peak_offset(left: float, centre: float, right: float) -> float:
    """Sub-sample offset of a peak from three samples (a parabola through them)."""
    curvature = left - 2.0 * centre + right
    return 0.0 if curvature >= 0 else 0.5 * (left - right) / curvature


def _patch(image: np.ndarray, center_xy_px: np.ndarray, size: int) -> np.ndarray:
    return cv2.getRectSubPix(image, (size, size), (float(center_xy_px[0]), float(center_xy_px[1])))


def align_to_template(change: np.ndarray, template: np.ndarray, center_xy_px: np.ndarray) -> tuple[np.ndarray, float]:
    """The centre near ``center_xy_px`` where ``change`` matches ``template`` best, and the match."""
    size = template.shape[0]
    search = _patch(change, center_xy_px, size + 2 * SEARCH_PX)
    scores = cv2.matchTemplate(search, template, cv2.TM_CCORR_NORMED)
    y, x = np.unravel_index(int(np.argmax(scores)), scores.shape)
    dx = _peak_offset(scores[y, x - 1], scores[y, x], scores[y, x + 1]) if 0 < x < scores.shape[1] - 1 else 0.0
    dy = _peak_offset(scores[y - 1, x], scores[y, x], scores[y + 1, x]) if 0 < y < scores.shape[0] - 1 else 0.0
    return center_xy_px + np.array([x + dx - SEARCH_PX, y + dy - SEARCH_PX]), float(scores[y, x])


def radial_profile(magnitude: np.ndarray, center_xy_px, step_px: float, max_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Radii (bin centres) and the mean of ``magnitude`` over each ring of width ``step_px``
    (NaN where the ring holds no pixel of the frame)."""
    h, w = magnitude.shape
    rows, cols = np.mgrid[0:h, 0:w]
    k = (np.hypot(cols - center_xy_px[0], rows - center_xy_px[1]) / step_px).astype(np.intp).ravel()
    n = int(max_px / step_px)
    inside = k < n
    sums = np.bincount(k[inside], magnitude.ravel()[inside], n)
    counts = np.bincount(k[inside], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (np.arange(n) + 0.5) * step_px, sums / counts


def ring_edge_px(radii_px: np.ndarray, profile: np.ndarray, max_ring_px: float) -> float:
    """Where ``profile`` (a ring's mean change by radius), past its peak within ``max_ring_px``,
    has fallen RING_EDGE_FRACTION of the way to the level beyond twice the peak's radius; NaN if it never does."""
    valid = np.isfinite(profile)
    candidates = np.where(valid & (radii_px > 2.0) & (radii_px < max_ring_px), profile, -np.inf)
    peak = int(np.argmax(candidates))
    far = profile[valid & (radii_px > 2.0 * radii_px[peak])]
    if far.size == 0 or not np.isfinite(candidates[peak]):
        return math.nan
    level = candidates[peak] - RING_EDGE_FRACTION * (candidates[peak] - float(np.median(far)))
    below = np.flatnonzero(~(profile[peak:] >= level))  # NaN counts as fallen: the frame ends there
    if below.size == 0:
        return math.nan
    k = peak + int(below[0])
    if not np.isfinite(profile[k]):
        return float(radii_px[k - 1])
    return float(
        radii_px[k - 1] + (profile[k - 1] - level) / (profile[k - 1] - profile[k]) * (radii_px[k] - radii_px[k - 1])
    )


def template_center_offset(template: np.ndarray) -> np.ndarray:
    """Offset (x, y px) from the template's middle of the centre of the circle fitted to its ring's outer edge."""
    magnitude = cv2.GaussianBlur(np.abs(template).sum(axis=2), (0, 0), 1.0)
    half = (template.shape[0] - 1) / 2.0
    angles = np.linspace(0.0, 2.0 * math.pi, 90, endpoint=False)
    radii = np.arange(0.0, half, 0.1)
    xs = (half + np.cos(angles)[:, None] * radii).astype(np.float32)
    ys = (half + np.sin(angles)[:, None] * radii).astype(np.float32)
    rays = cv2.remap(magnitude, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    edges = []
    for angle, ray in zip(angles, rays):
        # Along one ray the far level is the ray's end.
        peak = int(np.argmax(ray))
        level = ray[peak] - RING_EDGE_FRACTION * (ray[peak] - ray[-1])
        below = np.flatnonzero(ray[peak:] < level)
        if below.size:
            r = radii[peak + below[0]]
            edges.append((half + math.cos(angle) * r, half + math.sin(angle) * r))
    if len(edges) < 3:  # no ring to fit a circle to (a flat template): its middle is all there is
        return np.zeros(2)
    points = np.array(edges)
    # Kasa's circle fit: x^2 + y^2 = 2 a x + 2 b y + c, linear in a, b, c.
    design = np.column_stack([2.0 * points, np.ones(len(points))])
    (a, b, _), *_ = np.linalg.lstsq(design, (points**2).sum(axis=1), rcond=None)
    return np.array([a - half, b - half])


def find_presses(frames: np.ndarray, background: np.ndarray, ball_radius_px: float) -> FoundPresses:
    """Centre and radius of each press of ``frames`` (N x H x W x 3 uint8) against ``background``
    for a ball of ``ball_radius_px``; presses the finder cannot trust carry their reason.

    Contract: ``frames`` and ``background`` as :func:`checked_frames` takes them (no frames: no
    presses), ``ball_radius_px`` a number from MIN_BALL_PX to half the frame's smaller side;
    otherwise GelSightRenderError naming the argument."""
    checked_frames(frames, background)
    ball_px = checked_number("ball_radius_px", ball_radius_px, MIN_BALL_PX, 0.5 * min(background.shape[:2]))
    return _find_presses(frames, background, ball_px)


def shows_a_change(magnitude: np.ndarray) -> bool:
    """Whether ``magnitude`` (a frame's change) stands out of its own noise anywhere
    (PRESS_CONTRAST and MIN_PRESS_LEVELS)."""
    smooth = cv2.GaussianBlur(magnitude.astype(np.float32), (0, 0), 1.0)
    far = float(np.median(smooth))
    spread = float(np.median(np.abs(smooth - far)))
    return float(np.percentile(smooth, 99.9)) - far > max(PRESS_CONTRAST * spread, MIN_PRESS_LEVELS)


def _no_press_reasons(magnitudes: list[np.ndarray], reaches: np.ndarray) -> list[str]:
    """Per frame, why it shows no press ('' when it shows one)."""
    shows = np.array([shows_a_change(m) for m in magnitudes], bool)
    least_reach = 0.25 * float(np.median(reaches[shows])) if shows.any() else math.inf
    return [
        "no press (the frame changes nowhere beyond its own noise)"
        if not show
        else "no press (the frame changes over less than a quarter of the presses' median reach)"
        if reach < least_reach
        else ""
        for show, reach in zip(shows, reaches)
    ]


def _aligned_centers(
    frames: np.ndarray,
    background: np.ndarray,
    changes: list[np.ndarray],
    centers: np.ndarray,
    pressed: np.ndarray,
    ball_radius_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's centre moved to where it matches the template of the pressed frames best, that
    match, and the template's own centre added (``pressed`` has at least one)."""
    size = 2 * round(1.3 * ball_radius_px) + 1
    # Saturated presses would make the mean press unlike every press: it is made without them.
    unclipped = pressed & np.array(
        [_clipped_share(f, background, c, ball_radius_px) <= SATURATED_FRACTION for f, c in zip(frames, centers)]
    )
    use = unclipped if unclipped.any() else pressed
    match = np.zeros(len(frames))
    for _ in range(ROUNDS):
        template = np.mean([_patch(c, x, size) for c, x, u in zip(changes, centers, use) if u], axis=0)
        moved = [align_to_template(change, template, center) for change, center in zip(changes, centers)]
        centers = np.array([center for center, _ in moved])
        match = np.array([score for _, score in moved])
        matching = pressed & (match >= MIN_MATCH)
        use = matching if matching.any() else use
    return centers + template_center_offset(template), match


def _find_presses(frames: np.ndarray, background: np.ndarray, ball_radius_px: float) -> FoundPresses:
    """:func:`find_presses` on checked arguments."""
    n = len(frames)
    changes = [frame.astype(np.float32) - background.astype(np.float32) for frame in frames]
    magnitudes = [np.abs(change).sum(axis=2) for change in changes]
    reaches = np.array([change_extent_px(m) for m in magnitudes], float)
    no_press = _no_press_reasons(magnitudes, reaches)
    pressed = np.array([not reason for reason in no_press], bool)
    radius_range = (0.4 * ball_radius_px, 1.6 * ball_radius_px)
    centers = np.array([hough_center(m, radius_range) for m in magnitudes], float).reshape(n, 2)
    match = np.zeros(n)
    if pressed.any():
        centers, match = _aligned_centers(frames, background, changes, centers, pressed, ball_radius_px)
    # The ring is looked for out to MAX_RING_RADII ball radii, wider than any press of the ball
    # makes, so that a wrong ball radius or scale shows as rings too wide for it.
    radii = np.array(
        [
            ring_edge_px(
                *radial_profile(m, c, 0.25, 2 * MAX_RING_RADII * ball_radius_px), MAX_RING_RADII * ball_radius_px
            )
            if shown
            else math.nan
            for m, c, shown in zip(magnitudes, centers, pressed)
        ],
        float,
    )
    reasons = [
        reason or _distrust(frame, background, center, radius, score)
        for frame, reason, center, radius, score in zip(frames, no_press, centers, radii, match)
    ]
    return FoundPresses(centers, radii, reaches, match, reasons)


def _distrust(frame: np.ndarray, background: np.ndarray, center: np.ndarray, radius: float, match: float) -> str:
    """Why a found press cannot be trusted ('' when it can)."""
    h, w = frame.shape[:2]
    if not math.isfinite(radius):
        return "no ring edge found"
    clipped = _clipped_share(frame, background, center, radius)
    if clipped > SATURATED_FRACTION:
        return f"saturated ({100 * clipped:.0f} % of the ring's values at 0 or 255)"
    if center[0] - radius < 0 or center[1] - radius < 0 or center[0] + radius > w - 1 or center[1] + radius > h - 1:
        return "the ring leaves the frame"
    if match < MIN_MATCH:
        return f"unlike the other presses (template match {match:.2f} < {MIN_MATCH})"
    return ""


def _clipped_share(frame: np.ndarray, background: np.ndarray, center: np.ndarray, radius: float) -> float:
    """The share of the values within ``radius`` of ``center`` clipped at 0 or 255 (and not so at rest)."""
    h, w = frame.shape[:2]
    rows, cols = np.mgrid[0:h, 0:w]
    ring = np.hypot(cols - center[0], rows - center[1]) <= radius
    if not ring.any():  # a ring found wholly outside the frame: none of its values is clipped
        return 0.0
    clipped = ((frame == 0) | (frame == 255)) & ~((background == 0) | (background == 255))
    return float(clipped[ring].mean())


def check_background(frames: np.ndarray, background: np.ndarray) -> None:
    """Refuses a background that is not the frames' sensor at rest, naming the frames it does not
    match; the arguments' contract is :func:`checked_frames`'s."""
    checked_frames(frames, background)
    _check_background(frames, background)


def _check_background(frames: np.ndarray, background: np.ndarray) -> None:
    mismatch = np.array([np.median(np.abs(f.astype(np.float32) - background).mean(axis=2)) for f in frames])
    bad = np.flatnonzero(mismatch > MAX_BACKGROUND_MISMATCH_LEVELS)
    if bad.size > len(frames) // 2:
        raise GelSightRenderError(
            f"the background does not match the frames: presses {bad.tolist()} differ from it by a median "
            f"{np.median(mismatch[bad]):.0f} levels away from any press (at most {MAX_BACKGROUND_MISMATCH_LEVELS:g}): "
            "capture the no-contact frame with the same sensor, lights and exposure"
        )


def find_checked_presses(
    frames: np.ndarray, background: np.ndarray, mm_per_px: float, ball_radius_mm: float
) -> FoundPresses:
    """:func:`find_presses` for a ball of ``ball_radius_mm`` at ``mm_per_px``; GelSightRenderError
    for a ball too small to see or too large for the frame, presses that reach farther than the
    ball can press, and rings that most presses' ball could not make (a wrong radius or scale),
    and a background that is not these frames' sensor at rest (:func:`check_background`).

    Contract: ``frames`` and ``background`` as :func:`checked_frames` takes them (no frames: no
    presses), ``mm_per_px`` in MM_PER_PX_RANGE, ``ball_radius_mm`` in BALL_RADIUS_RANGE_MM;
    otherwise GelSightRenderError naming the argument, before any work."""
    checked_frames(frames, background)
    scale = checked_number("mm_per_px", mm_per_px, *MM_PER_PX_RANGE)
    ball = checked_number("ball_radius_mm", ball_radius_mm, *BALL_RADIUS_RANGE_MM)
    _check_background(frames, background)
    ball_px = ball / scale
    if not MIN_BALL_PX <= ball_px <= 0.5 * min(background.shape[:2]):
        raise GelSightRenderError(
            f"a ball of {ball:g} mm at {scale:g} mm/px is {ball_px:.1f} px: a press of it cannot be seen "
            f"in a {background.shape[1]} x {background.shape[0]} frame ({MIN_BALL_PX:g} px to half the frame's smaller side)"
        )
    found = _find_presses(frames, background, ball_px)
    _check_rings(found, ball_px, scale, ball)
    return found


def _check_rings(found: FoundPresses, ball_px: float, mm_per_px: float, ball_radius_mm: float) -> None:
    """Refuses presses that reach farther than the ball can press, or rings most presses' ball could not make."""
    # Before the rings: with too small a ball the finder fits pieces of them, which that ball explains.
    pressed = found.pressed
    reach_px = float(np.median(found.reaches_px[pressed])) if pressed.any() else 0.0
    if reach_px > MAX_REACH_RADII * ball_px:
        raise GelSightRenderError(
            f"the presses change the frame out to {reach_px * mm_per_px:.2f} mm from their centres (median), "
            f"more than {MAX_REACH_RADII:g} radii of a ball of {ball_radius_mm:g} mm at {mm_per_px:g} mm/px: "
            "the ball radius is too small or the scale too coarse; check --ball-radius-mm and --mm-per-px"
        )
    ratio = found.radii_px / ball_px
    low, high = RING_RADIUS_RANGE
    unexplained = np.flatnonzero(found.trusted & ~((ratio >= low) & (ratio <= high)))
    if unexplained.size > found.trusted.sum() // 2:
        rings_mm = np.nanmedian(found.radii_px[unexplained]) * mm_per_px
        raise GelSightRenderError(
            f"a ball of {ball_radius_mm:g} mm radius at {mm_per_px:g} mm/px cannot explain the rings of presses "
            f"{unexplained.tolist()} ({rings_mm:.2f} mm median radius, {low:g} to {high:g} ball radii expected): "
            "check --ball-radius-mm and --mm-per-px"
        )
