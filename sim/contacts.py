"""Contact bookkeeping for the checks: who touches whom, how deep, and the support polygon.

Signed distances follow MuJoCo: ``dist < 0`` is penetration depth (m).
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, QhullError


class ContactClassifier:
    """Splits the active contacts of one step into robot-self, robot-floor and others.

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

    def classify(self, data: mujoco.MjData) -> dict:
        """Returns self_min_dist (m, +inf if none), self_pairs [(g1, g2)], floor_points
        (k, 3), floor_min_dist, non_foot_on_floor (bool), foot_bodies_on_floor (set)."""
        n = data.ncon
        out = {"self_min_dist": np.inf, "self_pairs": [], "floor_points": np.zeros((0, 3)),
               "floor_min_dist": np.inf, "non_foot_on_floor": False, "foot_bodies_on_floor": set()}
        if n == 0:
            return out
        con = data.contact
        g = np.asarray(con.geom)[:n]
        dist = np.asarray(con.dist)[:n]
        pos = np.asarray(con.pos)[:n]
        r1, r2 = self.is_robot[g[:, 0]], self.is_robot[g[:, 1]]
        selfc = r1 & r2
        if selfc.any():
            out["self_min_dist"] = float(dist[selfc].min())
            out["self_pairs"] = [tuple(p) for p in g[selfc][dist[selfc] < 0]]
        floorc = ((g[:, 0] == self.floor) & r2) | ((g[:, 1] == self.floor) & r1)
        if floorc.any():
            out["floor_points"] = pos[floorc]
            out["floor_min_dist"] = float(dist[floorc].min())
            robot_g = np.where(g[floorc, 0] == self.floor, g[floorc, 1], g[floorc, 0])
            bodies = self.geom_body[robot_g]
            feet = self.is_foot_body[bodies]
            out["non_foot_on_floor"] = bool((~feet).any())
            out["foot_bodies_on_floor"] = set(bodies[feet].tolist())
        return out


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
