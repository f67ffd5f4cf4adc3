"""ZMP preview on the cart-table model, as one linear map per frame (Kajita et al. 2003, in least squares).

Contract: :class:`ZmpPreview` ``(kz, frames)`` precomputes, once, the gains that give the next
CoM position (one horizontal axis, or both at once) from the last two emitted CoM positions and
a ZMP reference over the next ``frames`` frames. The discrete model is the streaming
retargeter's: the ZMP of frame k is z_k = (1 − kz) c_k + kz (2 c_{k−1} − c_{k−2}), i.e.
c − (h/g) c̈ with c̈ by backward second differences and kz = (h/g) fps². The plan c_1..c_N
minimises, in least squares,

    Σ_k ‖z_k − z_ref,k‖² + w_acc Σ_k ‖c_k − 2c_{k−1} + c_{k−2}‖² kz² + w_end (‖c_N − z_ref,N‖² + ‖c_N − c_{N−1}‖²)

(the end rows stop the cart-table's unstable mode: the CoM comes to rest over the last
reference point). Only its first frame is used; the next frame plans again from where the robot
really is (receding horizon). Cost per call: one (N + 2)-vector product per axis.
"""

from __future__ import annotations

import numpy as np


class ZmpPreview:
    """Preview gains for ``frames`` frames ahead (see the module docstring); ``kz`` = (h/g) fps²."""

    def __init__(self, kz: float, frames: int, acc_weight: float = 1e-2, end_weight: float = 10.0):
        if frames < 2:
            raise ValueError(f"ZmpPreview: frames must be at least 2, got {frames}")
        n = int(frames)
        self.frames = n
        # unknowns c_1..c_N; the known c_0, c_{-1} and z_ref move to the right-hand side
        rows, rhs_known, rhs_ref = [], [], []

        def row(coeffs: dict, known=(0.0, 0.0), ref=None, scale=1.0):
            a = np.zeros(n)
            for k, v in coeffs.items():
                if k >= 1:
                    a[k - 1] += v
            rows.append(scale * a)
            rhs_known.append(scale * np.asarray(known, dtype=float))
            r = np.zeros(n)
            if ref is not None:
                r[ref] = 1.0
            rhs_ref.append(scale * r)

        for k in range(1, n + 1):
            # z_k − z_ref,k with the known frames (k − 1, k − 2 ≤ 0) moved to the right
            coeffs = {k: 1.0 - kz, k - 1: 2.0 * kz, k - 2: -kz}
            known = [0.0, 0.0]  # coefficients on (c_0, c_{-1}) of the right-hand side
            for j, v in ((k - 1, 2.0 * kz), (k - 2, -kz)):
                if j == 0:
                    known[0] -= v
                elif j == -1:
                    known[1] -= v
            row(coeffs, known, ref=k - 1)
            acc = {k: 1.0, k - 1: -2.0, k - 2: 1.0}
            known = [0.0, 0.0]
            for j, v in ((k - 1, -2.0), (k - 2, 1.0)):
                if j == 0:
                    known[0] -= v
                elif j == -1:
                    known[1] -= v
            row(acc, known, scale=np.sqrt(acc_weight) * kz)
        row({n: 1.0}, ref=n - 1, scale=np.sqrt(end_weight))
        row({n: 1.0, n - 1: -1.0}, scale=np.sqrt(end_weight))
        A = np.array(rows)
        rhs = np.concatenate([np.array(rhs_known), np.array(rhs_ref)], axis=1)  # (rows, 2 + N)
        gains = np.linalg.lstsq(A, rhs, rcond=None)[0]  # (N, 2 + N): the plan as a map of (c_0, c_-1, z_ref)
        self.plan_gains = gains
        self._first = gains[0].copy()

    def next_com(self, c0: np.ndarray, c_prev: np.ndarray, zmp_ref: np.ndarray) -> np.ndarray:
        """The CoM (d,) for the next frame: ``c0`` the last emitted CoM (d,), ``c_prev`` the one
        before (d,), ``zmp_ref`` (frames, d) the reference for the next ``frames`` frames."""
        g = self._first
        return g[0] * np.asarray(c0) + g[1] * np.asarray(c_prev) + g[2:] @ np.asarray(zmp_ref)

    def plan(self, c0: np.ndarray, c_prev: np.ndarray, zmp_ref: np.ndarray) -> np.ndarray:
        """The whole plan c_1..c_N (frames, d) from the same arguments (for tests and plots)."""
        g = self.plan_gains
        c0, c_prev = np.asarray(c0, dtype=float), np.asarray(c_prev, dtype=float)
        return g[:, 0:1] * c0[None] + g[:, 1:2] * c_prev[None] + g[:, 2:] @ np.asarray(zmp_ref)
