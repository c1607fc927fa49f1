"""Exact capsule geometry shared by the surface and marker modules (private)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def closest_on_segment(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Closest points on segments a–b (broadcast, (..., 3)) to points p (..., 3)."""
    ba = b - a
    l2 = np.sum(ba * ba, axis=-1)
    t = np.sum((p - a) * ba, axis=-1) / np.where(l2 > 0, l2, 1.0)
    return np.asarray(a + np.clip(t, 0.0, 1.0)[..., None] * ba)


def _dot(x: FloatArray, y: FloatArray) -> FloatArray:
    return np.asarray(np.sum(x * y, axis=-1)) if x.ndim == y.ndim else np.asarray(x @ y)


def ray_capsule(
    o: FloatArray, d: FloatArray, a: FloatArray, b: FloatArray, r: float, t_min: float
) -> FloatArray:
    """Smallest ray parameter t > t_min where rays o + t d (N,3; o may be (3,)) meet the
    surface of one capsule a–b of radius r; +inf on a miss. ``d`` need not be unit length.

    The candidates are both roots of the infinite cylinder (kept where the hit projects inside
    the segment) and of each end sphere (kept where it projects beyond that end); for a convex
    capsule these are exactly its boundary points, so origins inside the capsule get the exit.
    """
    ba = b - a
    l2 = float(ba @ ba)
    oa = o - a
    dd = _dot(d, d)
    bd = d @ ba
    bo = oa @ ba
    do = _dot(d, oa)
    oo = _dot(oa, oa)
    best = np.full(d.shape[0], np.inf)

    def take(t: FloatArray, ok: npt.NDArray[np.bool_]) -> None:
        np.copyto(best, t, where=ok & (t > t_min) & (t < best))

    # Cylinder (scaled by l2 to avoid divisions): A t² + 2 B t + C = 0.
    a_cyl = l2 * dd - bd * bd
    b_cyl = l2 * do - bo * bd
    c_cyl = l2 * oo - bo * bo - r * r * l2
    disc = b_cyl * b_cyl - a_cyl * c_cyl
    # Rays (near) parallel to the axis have no cylinder roots; the caps catch them.
    ok = (disc >= 0) & (a_cyl > 1e-12 * l2 * dd)
    if l2 > 0 and np.any(ok):
        sq = np.sqrt(np.where(ok, disc, 0.0))
        inv = 1.0 / np.where(ok, a_cyl, 1.0)
        for t in ((-b_cyl - sq) * inv, (-b_cyl + sq) * inv):
            y = bo + t * bd
            take(t, ok & (y > 0) & (y < l2))
    # End spheres: dd t² + 2 (d·(o-c)) t + |o-c|² - r² = 0.
    for do_c, oo_c, is_a in ((do, oo, True), (do - bd, oo - 2 * bo + l2, False)):
        disc = do_c * do_c - dd * (oo_c - r * r)
        ok = disc >= 0
        if not np.any(ok):
            continue
        sq = np.sqrt(np.where(ok, disc, 0.0))
        for t in ((-do_c - sq) / dd, (-do_c + sq) / dd):
            y = bo + t * bd
            take(t, ok & ((y <= 0) if is_a else (y >= l2)))
    return best


def surface_normals(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    n = p - closest_on_segment(p, a, b)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.asarray(n / np.where(norm > 0, norm, 1.0))
