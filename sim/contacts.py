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

    def classify_many(self, n_ticks: int, counts: np.ndarray, geoms, dists, points) -> ContactLog:
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

    Attributes (K,): ``self_min`` (m, +inf when none), ``floor_min`` (m), ``foot_floor_min``
    (m, the feet's contacts only), ``non_foot`` (a robot part other than a foot touches the
    floor); ``self_pairs`` the distinct penetrating geom pairs."""

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
        self._floor_body = (
            cls.geom_body[np.where(is_floor[floorc, 0], gf[:, 1], gf[:, 0])] if len(gf) else np.zeros(0, int)
        )
        self._floor_pos = pos[floorc]
        self._floor_mask = floorc
        self._floor_foot = cls.is_foot_body[self._floor_body]
        self.non_foot = np.zeros(n_ticks, bool)
        np.logical_or.at(self.non_foot, self._floor_tick, ~self._floor_foot)
        self.foot_floor_min = np.full(n_ticks, np.inf)
        np.minimum.at(self.foot_floor_min, self._floor_tick[self._floor_foot], dist[floorc][self._floor_foot])
        self._n = n_ticks
        self._starts = np.searchsorted(self._floor_tick, np.arange(n_ticks + 1))

    def non_foot_bodies(self, k: int) -> list[int]:
        """Ids of the robot bodies other than feet that touch the floor at tick k."""
        sl = slice(self._starts[k], self._starts[k + 1])
        return sorted({int(b) for b, foot in zip(self._floor_body[sl], self._floor_foot[sl]) if not foot})

    def centre_of_pressure(self, normal_force: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The measured ZMP: centre of pressure (K, 2) m of the robot-floor contacts and their
        total normal force (K,) N, from ``normal_force`` (N,) of every recorded contact, in the
        order given to :meth:`ContactClassifier.classify_many`.

        On a level floor the contact points lie in one plane, so the point about which the
        contact forces have no horizontal moment is p = sum(f_i p_i) / sum(f_i) over the
        normal forces f_i at the points p_i. NaN where the robot does not press on the floor."""
        f = np.asarray(normal_force, np.float64)[self._floor_mask]
        total = np.zeros(self._n)
        np.add.at(total, self._floor_tick, f)
        moment = np.zeros((self._n, 2))
        np.add.at(moment, self._floor_tick, f[:, None] * self._floor_pos)
        with np.errstate(invalid="ignore", divide="ignore"):
            cop = np.where((total > 1e-9)[:, None], moment / total[:, None], np.nan)
        return cop, total

    def foot_on_floor(self, feet) -> np.ndarray:
        """(K, len(feet)) bool: that foot touches the floor at that tick. Each foot is a
        body id or a collection of them (a foot made of an ankle and a toe link)."""
        out = np.zeros((self._n, len(feet)), bool)
        for i, bodies in enumerate(feet):
            sel = np.isin(self._floor_body, np.atleast_1d(np.asarray(bodies, dtype=int)))
            out[self._floor_tick[sel], i] = True
        return out

    def floor_points(self, k: int) -> np.ndarray:
        """(c, 2) xy of the robot-floor contact points at tick k."""
        return self._floor_pos[self._starts[k] : self._starts[k + 1]]

    def support_margins(self, com_xy: np.ndarray) -> np.ndarray:
        """(K',) margin (m) of the centre of mass ``com_xy`` (K', 2), K' <= K, to the
        support polygon of each tick's floor contacts; NaN with no floor contact."""
        return SupportMargin().many_flat(com_xy, self._floor_pos, self._starts[: len(com_xy) + 1])


def min_distance(
    model: mujoco.MjModel, data: mujoco.MjData, geoms_a: np.ndarray, geoms_b: np.ndarray, distmax: float = 0.05
) -> float:
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
    """:func:`support_margin` for many ticks at once, the polygon built once per run.

    Feet resting flat give the same contact points tick after tick, so the hull is
    rebuilt only when a tick's points (rounded to ``resolution`` m) differ from the
    previous tick's; the margins of a run of ticks sharing one polygon are evaluated
    together, vectorised.
    """

    def __init__(self, resolution: float = 0.001):
        self.resolution = resolution

    def many(self, points_xy: np.ndarray, contacts_xy: list[np.ndarray]) -> np.ndarray:
        """Margins (K,) of points (K, 2) to the polygons of ``contacts_xy`` (K arrays
        (c_k, 2)); NaN where a tick has no contact."""
        counts = np.array([len(c) for c in contacts_xy], dtype=np.int64)
        flat = (
            np.concatenate([np.asarray(c, np.float64).reshape(-1, 2) for c in contacts_xy])
            if len(contacts_xy)
            else np.zeros((0, 2))
        )
        return self.many_flat(points_xy, flat, np.concatenate([[0], np.cumsum(counts)]))

    def many_flat(self, points_xy: np.ndarray, contact_xy: np.ndarray, starts: np.ndarray) -> np.ndarray:
        """As :meth:`many`, with the contacts of all ticks concatenated: tick k's
        points are ``contact_xy[starts[k]:starts[k + 1]]`` (``starts`` (K+1,))."""
        points_xy = np.asarray(points_xy, np.float64)
        K = len(points_xy)
        out = np.full(K, np.nan)
        if K == 0:
            return out
        runs = np.flatnonzero(~self._same_as_previous(contact_xy, starts[: K + 1]))
        bounds = np.append(runs, K)
        for s, e in zip(bounds[:-1], bounds[1:]):
            c = contact_xy[starts[s] : starts[s + 1]]
            if len(c):
                out[s:e] = _margins_to(points_xy[s:e], c)
        return out

    def _same_as_previous(self, xy: np.ndarray, starts: np.ndarray) -> np.ndarray:
        """(K,) bool: tick k has exactly tick k-1's points (same count, same order,
        equal after rounding to ``resolution``); False at k = 0.

        Ticks are stored back to back, so when counts match, tick k's i-th point sits
        exactly ``count`` rows after tick k-1's i-th point."""
        counts = np.diff(starts)
        K = len(counts)
        same = np.zeros(K, bool)
        same[1:] = counts[1:] == counts[:-1]
        if not len(xy):
            return same
        r = np.round(np.asarray(xy, np.float64) / self.resolution).astype(np.int64)
        tick = np.repeat(np.arange(K), counts)
        i = np.flatnonzero(same[tick])
        differs = np.any(r[i] != r[i - counts[tick[i]]], axis=1)
        same[np.unique(tick[i[differs]])] = False
        return same

    def __call__(self, point_xy: np.ndarray, contact_xy: np.ndarray) -> float:
        """Margin (m) of one point (2,) to the polygon of ``contact_xy`` (c, 2)."""
        return support_margin(point_xy, contact_xy)


def _margins_to(points: np.ndarray, contact_xy: np.ndarray) -> np.ndarray:
    """Margins (m,) of points (m, 2) to the convex hull of ``contact_xy`` (c >= 1, 2):
    the hull's inequalities n . x + b <= 0 give the inside distance -max(n . p + b);
    outside (or for a degenerate hull, a segment or a point, as in
    :func:`support_margin`) it is minus the distance to the hull's boundary."""
    pts = np.asarray(contact_xy, dtype=np.float64)
    hull = None
    if len(pts) >= 3:
        try:
            hull = ConvexHull(pts)
        except QhullError:
            hull = None
    if hull is None:
        return -_dist_to_polyline_many(points, _degenerate_support(pts))
    sd = points @ hull.equations[:, :2].T + hull.equations[:, 2]  # (m, edges)
    inside = np.all(sd <= 0, axis=1)
    out = np.empty(len(points))
    out[inside] = -sd[inside].max(axis=1)
    if not inside.all():
        verts = pts[hull.vertices]
        out[~inside] = -_dist_to_polyline_many(points[~inside], np.vstack([verts, verts[:1]]))
    return out


def _degenerate_support(contact_xy: np.ndarray) -> np.ndarray:
    """The support of points without a 2-D hull, as a polyline (2, 2): the segment
    spanning them (collinear points), or a point repeated."""
    pts = np.unique(np.round(contact_xy, 5), axis=0)
    if len(pts) == 1:
        return np.vstack([pts, pts])
    d = pts - pts[0]
    axis = d[np.argmax(np.linalg.norm(d, axis=1))]
    proj = d @ axis / (axis @ axis)
    return np.vstack([pts[np.argmin(proj)], pts[np.argmax(proj)]])


def support_margin(point_xy: np.ndarray, contact_xy: np.ndarray) -> float:
    """Signed distance (m) from ``point_xy`` (2,) to the convex hull of ``contact_xy``
    (k, 2): positive inside (distance to the nearest edge), negative outside.

    Fewer than three distinct points, or collinear ones, make a degenerate polygon
    (a segment or a point): the margin is then minus the distance to it. No points
    at all gives NaN (no support: airborne).
    """
    if len(contact_xy) == 0:
        return float("nan")
    return float(_margins_to(np.asarray(point_xy, np.float64).reshape(1, 2), contact_xy)[0])


def _dist_to_polyline_many(p: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """Distances (m,) from points (m, 2) to the polyline ``verts`` (v, 2): for each
    segment a -> b the closest point is a + clip((p - a).(b - a) / |b - a|^2, 0, 1) (b - a)."""
    a, ab = verts[:-1], verts[1:] - verts[:-1]  # (s, 2)
    ap = p[:, None, :] - a[None]  # (m, s, 2)
    t = np.clip(np.einsum("msj,sj->ms", ap, ab) / np.maximum(np.einsum("sj,sj->s", ab, ab), 1e-18), 0.0, 1.0)
    return np.linalg.norm(ap - t[..., None] * ab[None], axis=2).min(axis=1)
