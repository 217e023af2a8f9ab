"""Ray casting of the scene's objects: their screen-space rectangles (:func:`_screen_rects`),
ray / box (slab method), cylinder and sphere (quadratic) intersection (:func:`_intersect`),
and many small objects at once as (object, pixel) pairs with a scatter-min
(:func:`_cast_batch`)."""

from __future__ import annotations

import numpy as np

from sfm_ttr_ros.data.synthetic.geometry import _FACE_CURVED, BOX, CYLINDER, SPHERE, _Scene

_NEAR = 0.05
_BOX_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5),
              (2, 6), (3, 7)]  # fmt: skip


def _screen_rects(scene: _Scene, R_wc, C, K, W, H, max_depth):
    """Pixel rectangles ``(oid, v0, v1, u0, u1)`` of the visible objects' AABBs."""
    lo, hi = scene.lo[3:], scene.hi[3:]
    # cheap pre-cull on the distance along the street
    dz = np.maximum(lo[:, 2] - C[2], C[2] - hi[:, 2])
    cand = np.flatnonzero(dz < max_depth)
    lo, hi = lo[cand], hi[cand]
    bits = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], bool)
    corners = np.where(bits[None], hi[:, None, :], lo[:, None, :])  # (n, 8, 3)
    pc = (corners - C) @ R_wc  # camera coordinates
    z = pc[..., 2]
    zmax, zmin = z.max(1), z.min(1)
    vis = (zmax > _NEAR) & (zmin < max_depth)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * pc[..., 0] / z + cx
        v = fy * pc[..., 1] / z + cy
    umin, umax, vmin, vmax = u.min(1), u.max(1), v.min(1), v.max(1)
    for k in np.flatnonzero(vis & (zmin <= _NEAR)):  # clip these boxes against the near plane
        pts = pc[k]
        keep = [pts[z[k] > _NEAR]]
        for a, bb in _BOX_EDGES:
            za, zb = z[k, a], z[k, bb]
            if (za - _NEAR) * (zb - _NEAR) < 0:
                s = (_NEAR - za) / (zb - za)
                keep.append((pts[a] + s * (pts[bb] - pts[a]))[None])
        pts = np.concatenate(keep)
        uu, vv = fx * pts[:, 0] / pts[:, 2] + cx, fy * pts[:, 1] / pts[:, 2] + cy
        umin[k], umax[k], vmin[k], vmax[k] = uu.min(), uu.max(), vv.min(), vv.max()
    vis &= (umax >= 0) & (umin < W) & (vmax >= 0) & (vmin < H)
    k = np.flatnonzero(vis)
    u0 = np.clip(np.floor(umin[k]), 0, W).astype(int)
    u1 = np.clip(np.ceil(umax[k]) + 1, 0, W).astype(int)
    v0 = np.clip(np.floor(vmin[k]), 0, H).astype(int)
    v1 = np.clip(np.ceil(vmax[k]) + 1, 0, H).astype(int)
    ok = (u0 < u1) & (v0 < v1)
    oid, near = cand[k][ok] + 3, zmin[k][ok]
    order = np.argsort(near, kind="stable")  # front to back: occluded objects get skipped
    cols = (oid, near, v0[ok], v1[ok], u0[ok], u1[ok])
    return list(zip(*(x[order].tolist() for x in cols), strict=True))


_BATCH_AREA = 3000  # objects covering at most this many pixels are ray cast in one batch


def _intersect(scene: _Scene, kind: int, oid, rays, Cx, Cy, Cz):
    """Ray / object hits for one object (scalar ``oid``) or per-pair arrays ``oid``.

    Returns ``(t, hit, face)``: depth along the ray (``D_cam`` has z = 1), validity, face code.
    """
    dx, dy, dz, ix, iy, iz = rays
    if kind == BOX:
        lo, hi = scene.lo32[oid], scene.hi32[oid]
        a, b = (lo[..., 0] - Cx) * ix, (hi[..., 0] - Cx) * ix
        txn, txf = np.minimum(a, b), np.maximum(a, b)
        a, b = (lo[..., 1] - Cy) * iy, (hi[..., 1] - Cy) * iy
        tyn, tyf = np.minimum(a, b), np.maximum(a, b)
        a, b = (lo[..., 2] - Cz) * iz, (hi[..., 2] - Cz) * iz
        tzn, tzf = np.minimum(a, b), np.maximum(a, b)
        tn = np.maximum(np.maximum(txn, tyn), tzn)
        tf = np.minimum(np.minimum(txf, tyf), tzf)
        hit = (tn <= tf) & (tn > _NEAR)
        ax = np.where((txn >= tyn) & (txn >= tzn), 0, np.where(tyn >= tzn, 1, 2))
        d_ax = np.where(ax == 0, dx, np.where(ax == 1, dy, dz))
        face = (2 * ax + (d_ax < 0)).astype(np.int8)  # a ray going +x enters the -x face
        return tn, hit, face
    c = scene.centre32[oid]
    r2 = scene.radius32[oid] ** 2
    ox, oy, oz = Cx - c[..., 0], Cy - c[..., 1], Cz - c[..., 2]
    if kind == CYLINDER:
        a = dx * dx + dz * dz
        bh = dx * ox + dz * oz
        cc = ox * ox + oz * oz - r2
    else:
        a = dx * dx + dy * dy + dz * dz
        bh = dx * ox + dy * oy + dz * oz
        cc = ox * ox + oy * oy + oz * oz - r2
    disc = bh * bh - a * cc
    with np.errstate(invalid="ignore"):
        t = (-bh - np.sqrt(disc)) / a
    hit = (disc > 0) & (t > _NEAR)
    if kind == CYLINDER:
        y = Cy + t * dy
        hit &= (y >= scene.lo32[oid, 1]) & (y <= scene.hi32[oid, 1])
    return t, hit, np.int8(_FACE_CURVED)


def _cast_batch(scene: _Scene, rects: np.ndarray, rays, C, T, OID, FACE) -> None:
    """Ray cast many small objects at once: (object, pixel) pairs, then a scatter-min."""
    W = T.shape[1]
    Tf, Of, Ff = T.ravel(), OID.ravel(), FACE.ravel()
    oid = rects[:, 0].astype(np.int64)
    v0, v1, u0, u1 = (rects[:, k].astype(np.int64) for k in (2, 3, 4, 5))
    kinds = scene.kind[oid]
    found = []
    for kind in (BOX, CYLINDER, SPHERE):
        sel = np.flatnonzero(kinds == kind)
        if sel.size == 0:
            continue
        w, h = u1[sel] - u0[sel], v1[sel] - v0[sel]
        area = w * h
        rep = np.repeat(np.arange(sel.size), area)
        local = np.arange(rep.size) - np.repeat(np.cumsum(area) - area, area)
        wr = w[rep]
        pix = (v0[sel][rep] + local // wr) * W + u0[sel][rep] + local % wr
        o = oid[sel][rep]
        pr = [r.ravel()[pix] for r in rays]
        t, hit, face = _intersect(scene, kind, o, pr, *C)
        hit &= t < Tf[pix]
        face = (
            face[hit]
            if isinstance(face, np.ndarray) and face.ndim
            else np.full(int(hit.sum()), face, np.int8)
        )
        found.append((pix[hit], t[hit], o[hit], face))
    if not found:
        return
    pix, t, o, face = (np.concatenate(x) for x in zip(*found, strict=True))
    np.minimum.at(Tf, pix, t)
    win = t == Tf[pix]
    Of[pix[win]] = o[win]
    Ff[pix[win]] = face[win]
