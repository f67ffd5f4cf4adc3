"""Support polygons on the ground plane: level footprints, shrinking, convex hulls, half-planes.

All coordinates are world xy in metres (Z up, ground z = 0). A convex polygon is kept as
half-planes ``A c ≤ b`` with unit rows a_i (outward normals), so the signed distance of a
point c to edge i is b_i − a_i·c (positive inside) and

    margin(c) = min_i (b_i − a_i·c)

is the distance to the nearest edge for a point inside (> 0) and a lower bound on the
depth of a point outside (< 0); it is 0 exactly on the boundary.

Used by the streaming retargeter's balance term (:mod:`retarget.streaming`) and by tests
that check a trajectory's centre of mass against its support polygon.
"""

from __future__ import annotations

import numpy as np


def convex_hull(points: np.ndarray) -> np.ndarray:
    """(n, 2) points → (m, 2) hull vertices, counter-clockwise, no collinear points
    (Andrew's monotone chain). Fewer than 3 distinct non-collinear points give what is left
    (a segment or a point)."""
    p = np.unique(np.asarray(points, dtype=np.float64).reshape(-1, 2), axis=0)  # sorted by x, then y
    if len(p) < 3:
        return p

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for q in p:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 1e-15:
            lower.pop()
        lower.append(q)
    upper: list = []
    for q in p[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 1e-15:
            upper.pop()
        upper.append(q)
    return np.array(lower[:-1] + upper[:-1])


def halfplanes(hull: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Counter-clockwise hull (m ≥ 3, 2) → A (m, 2) unit outward normals, b (m,): inside ⇔ A c ≤ b.

    Edge v_i → v_{i+1} with direction e has outward normal (e_y, −e_x)/|e| (the interior of a
    counter-clockwise polygon lies to the left of each edge)."""
    v = np.asarray(hull, dtype=np.float64)
    if len(v) < 3:
        raise ValueError(f"halfplanes: a polygon needs 3 vertices, got {len(v)}")
    e = np.roll(v, -1, axis=0) - v
    n = np.stack([e[:, 1], -e[:, 0]], axis=1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n, np.sum(n * v, axis=1)


def margin(c: np.ndarray, A: np.ndarray, b: np.ndarray) -> float:
    """Signed distance (m) of the point c (2,) to the polygon A c ≤ b: > 0 inside (see the module docstring)."""
    return float(np.min(b - A @ np.asarray(c, dtype=np.float64)))


def closest_point(c: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """The point (2,) of the convex polygon ``hull`` (m, 2), counter-clockwise, nearest to c (2,)."""
    c = np.asarray(c, dtype=np.float64)
    v = np.asarray(hull, dtype=np.float64)
    if len(v) >= 3:
        A, b = halfplanes(v)
        if np.all(A @ c <= b):
            return c.copy()
    if len(v) == 1:
        return v[0].copy()
    w = np.roll(v, -1, axis=0) if len(v) >= 3 else v[1:]
    v = v if len(v) >= 3 else v[:1]
    e = w - v
    t = np.clip(np.sum((c - v) * e, axis=1) / np.maximum(np.sum(e * e, axis=1), 1e-18), 0.0, 1.0)
    q = v + t[:, None] * e
    return q[np.argmin(np.sum((q - c) ** 2, axis=1))]


def rectangle_frame(local_corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A sole's four corners (4, 3) in its body frame, in order around the rectangle →
    their coordinates (4, 2) along the sole's two edge directions u1 = unit(c0 − c1) and
    u2 = unit(c1 − c2), measured from the sole centre, and the half lengths (2,)."""
    c = np.asarray(local_corners, dtype=np.float64)
    centre = c.mean(axis=0)
    u1 = (c[0] - c[1]) / np.linalg.norm(c[0] - c[1])
    u2 = (c[1] - c[2]) / np.linalg.norm(c[1] - c[2])
    ab = np.stack([(c - centre) @ u1, (c - centre) @ u2], axis=1)
    return ab, np.abs(ab).max(axis=0)


def level_footprint(world_corners: np.ndarray, local_corners: np.ndarray, shrink: float = 0.0) -> np.ndarray:
    """Where a sole's corners (4, 2) land on the ground if the foot is put down flat.

    The footprint keeps the sole's centre (mean of ``world_corners`` (4, 3) or (4, 2)) and its
    heading (the ground projection of the c0 → c1 edge, or of c1 → c2 if the first stands
    nearly vertical), and has the true size of the
    sole from ``local_corners`` (4, 3), each half length reduced by ``shrink`` (m, not below 0):

        corner_i = centre + a_i ê1 + b_i ê2,   ê2 = ê1 turned by the sole's handedness

    with (a_i, b_i) the corner's coordinates along the sole's own edges (:func:`rectangle_frame`)."""
    w = np.asarray(world_corners, dtype=np.float64)[:, :2]
    ab, half = rectangle_frame(local_corners)
    ab = np.sign(ab) * np.maximum(np.abs(ab) - shrink, 0.0)
    centre = w.mean(axis=0)
    d1, d2 = w[0] - w[1], w[1] - w[2]
    if np.linalg.norm(d1) >= 0.2 * np.linalg.norm(d2) * half[0] / half[1]:
        e1 = d1 / np.linalg.norm(d1)
        e2 = np.array([-e1[1], e1[0]])
        if e2 @ d2 < 0:  # keep the sole's handedness: ê2 on the side c1 − c2 projects to
            e2 = -e2
    else:  # the c0 → c1 edge stands (nearly) vertical: take the heading from c1 → c2
        e2 = d2 / np.linalg.norm(d2)
        e1 = np.array([e2[1], -e2[0]])
        if e1 @ d1 < 0:
            e1 = -e1
    return centre + ab[:, :1] * e1 + ab[:, 1:] * e2


#: The share of a footprint's half length that shrinking by a margin always leaves.
MIN_KEPT = 0.2


def shrink_footprint(footprint: np.ndarray, shrink: float) -> np.ndarray:
    """A rectangular footprint (4, 2), corners in order around it, with each half length
    reduced by ``shrink`` (m) about its centre, but never below :data:`MIN_KEPT` of itself: a
    sole narrower than twice the margin (a 6 cm wide G1 foot against a 3 cm margin) keeps an
    area instead of collapsing to a line (a polygon the CoM constraints cannot be built on)."""
    f = np.asarray(footprint, dtype=np.float64)
    centre = f.mean(axis=0)
    e1 = (f[0] - f[1]) / np.linalg.norm(f[0] - f[1])
    e2 = (f[1] - f[2]) / np.linalg.norm(f[1] - f[2])
    a, b = (f - centre) @ e1, (f - centre) @ e2
    a = np.sign(a) * np.maximum(np.abs(a) - shrink, MIN_KEPT * np.abs(a))
    b = np.sign(b) * np.maximum(np.abs(b) - shrink, MIN_KEPT * np.abs(b))
    return centre + a[:, None] * e1 + b[:, None] * e2


def centre_line(footprint: np.ndarray, shrink: float = 0.0) -> np.ndarray:
    """The two ends (2, 2) of a rectangular footprint's (4, 2) long centre line, each end
    ``shrink`` (m) in from the footprint's short edge."""
    f = np.asarray(footprint, dtype=np.float64)
    centre = f.mean(axis=0)
    e = f[0] - f[1] if np.linalg.norm(f[0] - f[1]) >= np.linalg.norm(f[1] - f[2]) else f[1] - f[2]
    half = max(0.5 * np.linalg.norm(e) - shrink, MIN_KEPT * 0.5 * np.linalg.norm(e))
    e = e / np.linalg.norm(e)
    return np.stack([centre + half * e, centre - half * e])


def double_support_points(footprints: list[np.ndarray], shrink: float, inset: float) -> np.ndarray:
    """Points (4, 2) whose hull is the CoM's region while both feet carry weight: each foot's
    centre line (``shrink`` in from its toe and heel), moved ``inset`` (m) towards the other
    foot's centre line. A CoM over one foot's centre line or beyond would unload the other foot,
    which a compliant (servo-driven) robot does not survive standing on both."""
    lines = [centre_line(f, shrink) for f in footprints]
    out = []
    for i, line in enumerate(lines):
        other = lines[1 - i].mean(axis=0)
        d = other - line.mean(axis=0)
        dist = float(np.linalg.norm(d))
        out.append(line + (min(inset, 0.5 * dist) / max(dist, 1e-12)) * d)
    return np.concatenate(out)


def stance_points(footprint: np.ndarray, other: np.ndarray, shrink: float) -> np.ndarray:
    """Points (4, 2) whose hull is the CoM's region while one foot stands alone: the half of its
    ``footprint`` (4, 2), shrunk by ``shrink`` (m), on the side of the ``other`` (lifted) foot's
    footprint, down to the long centre line. A servo leg carrying the robot alone sags outwards;
    a CoM on the inner half leans against that."""
    small = shrink_footprint(footprint, shrink)
    line = centre_line(footprint, shrink)
    towards = np.asarray(other, dtype=np.float64).mean(axis=0) - small.mean(axis=0)
    side = (small - small.mean(axis=0)) @ towards
    inner = small[np.argsort(side)[-2:]]
    return np.concatenate([line, inner])


def support_polygon(footprints: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Convex hull of the feet's footprints (each (4, 2)) → (hull (m, 2), A (m, 2), b (m,))."""
    hull = convex_hull(np.concatenate(footprints, axis=0))
    A, b = halfplanes(hull)
    return hull, A, b


def com_margins(
    com_xy: np.ndarray, soles: np.ndarray, local_corners: list[np.ndarray], on: np.ndarray, shrink: float = 0.0
) -> np.ndarray:
    """Per frame, the margin (m) of the CoM over the support polygon of the feet in contact.

    com_xy (T, 2); soles (T, 4·F, 3) world sole corners, four per foot in foot order;
    local_corners: F arrays (4, 3) (the feet's corners in their body frames); on (T, F) bool.
    The polygon is the hull of the level footprints (shrunk by ``shrink``) of the feet that
    are ``on``; NaN where no foot is."""
    T, F = on.shape
    out = np.full(T, np.nan)
    for t in range(T):
        prints = [level_footprint(soles[t, 4 * f : 4 * f + 4], local_corners[f], shrink) for f in range(F) if on[t, f]]
        if prints:
            _, A, b = support_polygon(prints)
            out[t] = margin(com_xy[t], A, b)
    return out
