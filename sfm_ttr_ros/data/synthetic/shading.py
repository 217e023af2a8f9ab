"""Shading of the hit pixels: sky gradient, surface normals and texture coordinates, Lambert
with a sun direction and an ambient term, trilinear texture lookups, lane markings,
distance haze."""

from __future__ import annotations

import numpy as np

from sfm_ttr_ros.data.synthetic.geometry import _FACE_CURVED, CYLINDER
from sfm_ttr_ros.data.synthetic.materials import _sample, _shuffle


def _shade(scene, intr, T, OID, FACE, hitm, Dx, Dy, Dz, C):
    p = scene.params
    H, W = T.shape
    f32 = np.float32
    dnorm = np.sqrt(Dx * Dx + Dy * Dy + Dz * Dz)
    # sky: vertical gradient on the ray elevation (at infinity: rotation-consistent)
    elev = np.clip(-Dy / dnorm * 4.0, 0, 1)[..., None]
    img = (1 - elev) * np.array(p.sky_horizon, f32) + elev * np.array(p.sky_top, f32)
    img = img.astype(f32)

    idx = np.flatnonzero(hitm)
    if idx.size == 0:
        return img
    t = T.ravel()[idx]
    dx, dy, dz = Dx.ravel()[idx], Dy.ravel()[idx], Dz.ravel()[idx]
    Cf = np.asarray(C, f32)
    px, py, pz = Cf[0] + t * dx, Cf[1] + t * dy, Cf[2] + t * dz
    oid = OID.ravel()[idx]
    face = FACE.ravel()[idx]
    # normals
    nx = np.zeros_like(t)
    ny = np.zeros_like(t)
    nz = np.zeros_like(t)
    sgn = np.where(face % 2 == 0, f32(-1), f32(1))  # even: ray went +axis, normal -axis
    ax = face // 2
    nx[ax == 0] = sgn[ax == 0]
    ny[ax == 1] = sgn[ax == 1]
    nz[ax == 2] = sgn[ax == 2]
    # texture coordinates: metres on the surface, world-anchored; a moving object carries its
    # texture (its anchor, the distance it moved, is taken off)
    tx, ty, tz = px, py, pz
    if scene.anchor is not None:
        a = scene.anchor[oid]
        tx, ty, tz = px - a[:, 0], py - a[:, 1], pz - a[:, 2]
    u = np.where(ax == 0, tz, tx)
    v = np.where(ax == 1, tz, ty)
    curved = face == _FACE_CURVED
    if curved.any():
        o = oid[curved]
        cen = scene.centre[o].astype(f32)
        rad = scene.radius[o].astype(f32)
        qx, qz = px[curved] - cen[:, 0], pz[curved] - cen[:, 2]
        is_cyl = scene.kind[o] == CYLINDER
        qy = np.where(is_cyl, 0, py[curved] - cen[:, 1])
        n = np.sqrt(qx * qx + qy * qy + qz * qz) + 1e-9
        nx[curved], ny[curved], nz[curved] = qx / n, qy / n, qz / n
        u[curved] = np.arctan2(qx, qz) * rad
        v[curved] = np.where(is_cyl, ty[curved], np.arcsin(np.clip(qy / n, -1, 1)) * rad)
    # Lambert + ambient
    sun = np.asarray(p.sun_direction, f32)
    lam = np.maximum(nx * sun[0] + ny * sun[1] + nz * sun[2], 0)
    shade = p.ambient + (1 - p.ambient) * p.sun_strength * lam
    # texture lookups with trilinear mip-mapping
    mat = scene.material[oid]
    u = u + scene.offset[oid, 0]
    v = v + scene.offset[oid, 1]
    dlen = np.sqrt(dx * dx + dy * dy + dz * dz)
    rng_dist = t * dlen  # distance along the ray
    cosi = np.abs(nx * dx + ny * dy + nz * dz) / dlen
    # pixel footprint (metres): isotropic filtering between the minor and major axes of the
    # footprint ellipse, biased towards the sharp side
    foot_m = rng_dist / intr.fx / np.sqrt(np.sqrt(np.maximum(cosi, 0.02))) * np.float32(0.75)
    albedo = np.empty((idx.size, 3), f32)
    for m in np.flatnonzero(np.bincount(mat, minlength=len(scene.materials))):
        sel = np.flatnonzero(mat == m)
        mt = scene.materials[m]
        us, vs = u[sel], v[sel]
        if mt.shuffle is not None:
            us, vs = _shuffle(mt, us, vs, oid[sel])
        albedo[sel] = _sample(mt, us, vs, foot_m[sel])
    albedo *= scene.tint[oid]
    # lane markings on the road (anti-aliased over the pixel footprint)
    road = np.flatnonzero(oid == 0)
    if road.size:
        x, z, fm = px[road], pz[road], foot_m[road] + 1e-4
        hw = p.street_width / 2

        def band(d, half):
            return np.clip((half - np.abs(d)) / fm + 0.5, 0, 1)

        dash = np.clip((np.minimum(np.mod(z, 9.0), 9.0 - np.mod(z, 9.0)) - 1.5) / fm + 0.5, 0, 1)
        cover = np.maximum(band(x, 0.06) * dash, band(np.abs(x) - (hw - 2.4), 0.06))[:, None]
        paint = np.clip(0.5 + 0.9 * albedo[road], 0, 1)  # worn paint keeps the asphalt's texture
        albedo[road] = albedo[road] * (1 - cover) + paint * cover
    col = albedo * shade[:, None]
    haze = np.exp(-rng_dist / p.haze_distance)[:, None]
    col = col * haze + np.asarray(p.haze_color, f32) * (1 - haze)
    img.reshape(-1, 3)[idx] = col
    return img
