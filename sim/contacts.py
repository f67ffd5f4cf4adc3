"""Contact bookkeeping for the checks: who touches whom, how deep, and the support polygon.

Signed distances follow MuJoCo: ``dist < 0`` is penetration depth (m).
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, QhullError


class ContactClassifier:
    """Splits recorded contacts into robot-self, robot-floor and others.

    ``robot_geoms`` (k,) ids of the robot's geoms; ``foot_bodies`` ids of the bodies
    that may touch the floor without it counting as a fall.
    """

    def __init__(self, model: mujoco.MjModel, robot_geoms: np.ndarray, floor_geom: int, foot_bodies=()):
        self.is_robot = np.zeros(model.ngeom, bool)
        self.is_robot[robot_geoms] = True
        self.floor = int(floor_geom)
        self.geom_body = model.geom_bodyid.copy()
        self.is_foot_body = np.zeros(model.nbody, bool)
        self.is_foot_body[list(foot_bodies)] = True

    def classify_many(self, n_ticks: int, counts: np.ndarray, geoms, dists, points) -> "ContactLog":
        """All ticks at once: ``counts`` (K,) contacts per tick and, for the ticks with
        contacts, lists of their arrays (geom (c, 2), dist (c,), pos (c, 3)), as
        recorded by the checker."""
        if geoms:
            tick = np.repeat(np.arange(len(counts)), counts)
            g = np.concatenate(geoms)
            dist = np.concatenate(dists)
            pos = np.concatenate(points)[:, :2]
        else:
            tick, g, dist, pos = np.zeros(0, int), np.zeros((0, 2), int), np.zeros(0), np.zeros((0, 2))
        return ContactLog(self, n_ticks, tick, g, dist, pos)


class ContactLog:
    """The contacts of a whole run, split into robot-self and robot-floor per tick.

    Attributes (K,): ``self_min`` (m, +inf when none), ``floor_min`` (m),
    ``non_foot`` (a robot part other than a foot touches the floor); ``self_pairs``
    the distinct penetrating geom pairs."""

    def __init__(self, cls: ContactClassifier, n_ticks: int, tick, g, dist, pos):
        robot = cls.is_robot[g] if len(g) else np.zeros((0, 2), bool)
        selfc = robot[:, 0] & robot[:, 1]
        is_floor = g == cls.floor
        floorc = (is_floor[:, 0] & robot[:, 1]) | (is_floor[:, 1] & robot[:, 0])
        self.self_min = np.full(n_ticks, np.inf)
        np.minimum.at(self.self_min, tick[selfc], dist[selfc])
        self.floor_min = np.full(n_ticks, np.inf)
        np.minimum.at(self.floor_min, tick[floorc], dist[floorc])
        pen = selfc & (dist < 0)
        self.self_pairs = sorted({tuple(p) for p in np.sort(g[pen], axis=1).tolist()})
        gf = g[floorc]
        self._floor_tick = tick[floorc]
        self._floor_body = cls.geom_body[np.where(is_floor[floorc, 0], gf[:, 1], gf[:, 0])] if len(gf) else np.zeros(0, int)
        self._floor_pos = pos[floorc]
        self.non_foot = np.zeros(n_ticks, bool)
        np.logical_or.at(self.non_foot, self._floor_tick, ~cls.is_foot_body[self._floor_body])
        self._n = n_ticks
        self._starts = np.searchsorted(self._floor_tick, np.arange(n_ticks + 1))

    def foot_on_floor(self, foot_bodies) -> np.ndarray:
        """(K, len(foot_bodies)) bool: that foot touches the floor at that tick."""
        out = np.zeros((self._n, len(foot_bodies)), bool)
        for i, b in enumerate(foot_bodies):
            sel = self._floor_body == b
            out[self._floor_tick[sel], i] = True
        return out

    def floor_points(self, k: int) -> np.ndarray:
        """(c, 2) xy of the robot-floor contact points at tick k."""
        return self._floor_pos[self._starts[k]:self._starts[k + 1]]


def min_distance(model: mujoco.MjModel, data: mujoco.MjData, geoms_a: np.ndarray, geoms_b: np.ndarray,
                 distmax: float = 0.05) -> float:
    """Smallest signed distance (m) between two geom sets, capped at ``distmax``.

    Pairs whose bounding spheres are farther apart than ``distmax`` are skipped
    before calling ``mj_geomDistance`` (exact for primitives).
    """
    ca, cb = data.geom_xpos[geoms_a], data.geom_xpos[geoms_b]
    ra, rb = model.geom_rbound[geoms_a], model.geom_rbound[geoms_b]
    gap = np.linalg.norm(ca[:, None, :] - cb[None, :, :], axis=-1) - ra[:, None] - rb[None, :]
    best = distmax
    for i, j in np.argwhere(gap < distmax):
        best = min(best, mujoco.mj_geomDistance(model, data, int(geoms_a[i]), int(geoms_b[j]), distmax, None))
    return float(best)


class SupportMargin:
    """:func:`support_margin` with the polygon cached: feet resting flat give the same
    contact points tick after tick, so the hull is rebuilt only when the points
    (rounded to ``resolution`` m) change."""

    def __init__(self, resolution: float = 0.001):
        self.resolution = resolution
        self._key: bytes | None = None
        self._eq: np.ndarray | None = None
        self._verts: np.ndarray | None = None
        self._pts: np.ndarray | None = None

    def many(self, points_xy: np.ndarray, contacts_xy: list[np.ndarray]) -> np.ndarray:
        """Margins (K,) of points (K, 2) to the polygons of ``contacts_xy`` (K arrays
        (c_k, 2)); runs of ticks with the same polygon are evaluated together."""
        out = np.full(len(points_xy), np.nan)
        keys = [np.round(c / self.resolution).astype(np.int64).tobytes() for c in contacts_xy]
        start = 0
        for k in range(1, len(keys) + 1):
            if k < len(keys) and keys[k] == keys[start]:
                continue
            c = contacts_xy[start]
            if len(c):
                self(points_xy[start], c)  # builds and caches the polygon
                if self._eq is not None:
                    p = points_xy[start:k]
                    sd = p @ self._eq[:, :2].T + self._eq[:, 2]  # (m, edges)
                    inside = np.all(sd <= 0, axis=1)
                    out[start:k][inside] = -sd[inside].max(axis=1)
                    ring = np.vstack([self._verts, self._verts[:1]])
                    for i in np.flatnonzero(~inside):
                        out[start + i] = -_dist_to_polyline(p[i], ring)
                else:
                    for i in range(start, k):
                        out[i] = support_margin(points_xy[i], c)
            start = k
        return out

    def __call__(self, point_xy: np.ndarray, contact_xy: np.ndarray) -> float:
        if len(contact_xy) == 0:
            return float("nan")
        key = np.round(np.asarray(contact_xy) / self.resolution).astype(np.int64).tobytes()
        if key != self._key:
            self._key = key
            self._pts = np.asarray(contact_xy, dtype=np.float64)
            try:
                hull = ConvexHull(self._pts) if len(self._pts) >= 3 else None
            except QhullError:
                hull = None
            self._eq = None if hull is None else hull.equations
            self._verts = None if hull is None else self._pts[hull.vertices]
        if self._eq is None:
            return support_margin(point_xy, self._pts)
        p = np.asarray(point_xy, dtype=np.float64)
        sd = self._eq[:, :2] @ p + self._eq[:, 2]
        if np.all(sd <= 0):
            return float(-sd.max())
        return -_dist_to_polyline(p, np.vstack([self._verts, self._verts[:1]]))


def support_margin(point_xy: np.ndarray, contact_xy: np.ndarray) -> float:
    """Signed distance (m) from ``point_xy`` (2,) to the convex hull of ``contact_xy``
    (k, 2): positive inside (distance to the nearest edge), negative outside.

    Fewer than three distinct points, or collinear ones, make a degenerate polygon
    (a segment or a point): the margin is then minus the distance to it. No points
    at all gives NaN (no support: airborne).
    """
    pts = np.unique(np.round(np.asarray(contact_xy, dtype=np.float64), 5), axis=0)
    p = np.asarray(point_xy, dtype=np.float64)
    if len(pts) == 0:
        return float("nan")
    if len(pts) >= 3:
        try:
            hull = ConvexHull(pts)
        except QhullError:
            hull = None
        if hull is not None:
            # equations: n . x + b <= 0 inside, n unit-length
            s = hull.equations[:, :2] @ p + hull.equations[:, 2]
            if np.all(s <= 0):
                return float(-s.max())
            verts = pts[hull.vertices]
            return -_dist_to_polyline(p, np.vstack([verts, verts[:1]]))
    if len(pts) == 1:
        return -float(np.linalg.norm(p - pts[0]))
    # degenerate: distance to the segment spanning the points
    d = pts - pts[0]
    axis = d[np.argmax(np.linalg.norm(d, axis=1))]
    proj = d @ axis / (axis @ axis)
    seg = np.vstack([pts[np.argmin(proj)], pts[np.argmax(proj)]])
    return -_dist_to_polyline(p, seg)


def _dist_to_polyline(p: np.ndarray, verts: np.ndarray) -> float:
    a, b = verts[:-1], verts[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18), 0.0, 1.0)
    closest = a + t[:, None] * ab
    return float(np.min(np.linalg.norm(p - closest, axis=1)))
