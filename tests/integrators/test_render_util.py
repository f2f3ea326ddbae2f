"""Independent helpers for the renderer tests (no tests here).

`BruteForce` intersects every ray with every triangle (Möller–Trumbore) in float64 numpy; it shares
no code with `jaxrt.accel.bvh` and serves as the reference for the renderer's geometric checks.
"""

from __future__ import annotations

import numpy as np


def brute_intersect(vertices, faces, o, d, tmin=0.0, tmax=np.inf):
    """Closest hit of rays (N,3) against triangles: (t, prim, u, v) numpy arrays; prim -1 on miss."""
    v = np.asarray(vertices, np.float64)[np.asarray(faces)]  # (F, 3, 3)
    o = np.asarray(o, np.float64)
    d = np.asarray(d, np.float64)
    n = o.shape[0]
    tmax = np.broadcast_to(np.asarray(tmax, np.float64), (n,))
    best_t = np.full(n, np.inf)
    best_p = np.full(n, -1, np.int64)
    best_u = np.zeros(n)
    best_v = np.zeros(n)
    e1 = v[:, 1] - v[:, 0]
    e2 = v[:, 2] - v[:, 0]
    for s in range(0, n, 4096):
        oo, dd = o[s : s + 4096, None, :], d[s : s + 4096, None, :]
        pv = np.cross(dd, e2[None])
        det = np.sum(e1[None] * pv, -1)
        ok = np.abs(det) > 1e-300
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = oo - v[None, :, 0]
        u = np.sum(tv * pv, -1) * inv
        qv = np.cross(tv, e1[None])
        w = np.sum(dd * qv, -1) * inv
        t = np.sum(e2[None] * qv, -1) * inv
        hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > tmin) & (t < tmax[s : s + 4096, None])
        t = np.where(hit, t, np.inf)
        j = np.argmin(t, axis=1)
        rows = np.arange(len(j))
        tt = t[rows, j]
        found = np.isfinite(tt)
        best_t[s : s + 4096] = np.where(found, tt, np.inf)
        best_p[s : s + 4096] = np.where(found, j, -1)
        best_u[s : s + 4096] = np.where(found, u[rows, j], 0)
        best_v[s : s + 4096] = np.where(found, w[rows, j], 0)
    return best_t, best_p, best_u, best_v


# --------------------------------------------------------------------------- the "lab" test scene
# One scene structure serves every closed-form check (views differ only by camera, which does not
# recompile). Geometry is described here independently of jaxrt so the references use exact shapes.

BG = np.array([0.2, 0.3, 0.4])
LIGHT_POS = np.array([0.5, 4.0, 0.5])
LIGHT_I = np.array([10.0, 12.0, 14.0])
FLOOR_RHO = np.array([0.5, 0.4, 0.3])
BOX_RHO = np.array([0.7, 0.7, 0.7])
BOX_LO = np.array([-0.5, 1.4, -0.5])
BOX_HI = np.array([0.5, 1.6, 0.5])
SPHERE_C, SPHERE_R = np.array([-3.0, 0.5, 1.0]), 0.5
MIRROR_Z, MIRROR_X, MIRROR_Y = -4.0, (-2.0, 2.0), (0.0, 2.0)
SLAB_C, SLAB_SIZE, SLAB_N = np.array([30.0, 5.0, 0.0]), np.array([2.0, 2.0, 0.2]), 1.5
RES = (40, 30)  # width, height shared by all lab views

VIEWS = {
    # looks down at the floor around the box and its shadow
    "top": dict(position=[-0.3, 6.0, 2.5], look_at=[-0.3, 0.0, -0.3], vfov=30.0),
    # looks at the mirror, which shows the floor, the box and the sky behind the camera
    "mirror": dict(position=[0.3, 1.2, 3.0], look_at=[0.0, 0.9, -4.0], vfov=25.0),
    # looks through the glass slab at normal incidence
    "glass": dict(position=[30.0, 5.0, 3.0], look_at=[30.0, 5.0, 0.0], vfov=2.0),
    # everything at once, for gradients
    "wide": dict(position=[1.0, 3.0, 6.0], look_at=[-0.8, 0.6, -1.0], vfov=50.0),
}


def lab_dict(view="top", width=RES[0], height=RES[1]):
    cam = dict(VIEWS[view])
    cam.update(width=width, height=height)
    size = (BOX_HI - BOX_LO).tolist()
    return {
        "camera": cam,
        "lights": [{"position": LIGHT_POS.tolist(), "intensity": LIGHT_I.tolist()}],
        "materials": {
            "floor": {"model": "lambert", "rho_d": FLOOR_RHO.tolist()},
            "box": {"model": "lambert", "rho_d": BOX_RHO.tolist()},
            "plastic": {"model": "phong", "rho_d": [0.3, 0.1, 0.1], "rho_s": 0.4, "s": 30.0},
            "mirror": {"model": "lambert", "rho_d": 0.0, "delta": 1.0},
            "black": {"model": "lambert", "rho_d": 0.0},
            "glass": {"model": "glass", "n_t": SLAB_N},
        },
        "objects": [
            {"name": "floor", "primitive": "plane", "size": [20.0, 20.0], "material": "floor"},
            {"name": "box", "primitive": "box", "size": size, "translate": ((BOX_LO + BOX_HI) / 2).tolist(),
             "material": "box"},
            {"name": "ball", "primitive": "sphere", "radius": SPHERE_R, "subdivisions": 3,
             "translate": SPHERE_C.tolist(), "material": "plastic"},
            # vertical, facing +z, bottom edge touching the floor
            {"name": "mirror", "primitive": "plane", "size": [4.0, 2.0], "rotate": [90.0, 0.0, 0.0],
             "translate": [0.0, 1.0, MIRROR_Z], "material": "mirror"},
            {"name": "slab", "primitive": "box", "size": SLAB_SIZE.tolist(), "translate": SLAB_C.tolist(),
             "material": "glass"},
            # absorbs the slab's reflections, behind the glass view's camera
            {"name": "panel", "primitive": "plane", "size": [8.0, 8.0], "rotate": [-90.0, 0.0, 0.0],
             "translate": [30.0, 5.0, 5.0], "material": "black"},
        ],
        "render": {"max_depth": 3, "background": BG.tolist()},
    }


def pinhole_rays(position, look_at, vfov, width, height, up=(0.0, 1.0, 0.0)):
    """Pixel-centre rays in float64 from the textbook look-at construction: (H*W, 3) o and unit d."""
    position, look_at, up = (np.asarray(x, np.float64) for x in (position, look_at, up))
    f = look_at - position
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    th = np.tan(np.radians(vfov) / 2)
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = (2 * j / width - 1) * th * width / height
    y = (1 - 2 * i / height) * th
    d = x[..., None] * r + y[..., None] * u + f
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.broadcast_to(position, d.shape).reshape(-1, 3), d.reshape(-1, 3)


def view_rays(view, width=RES[0], height=RES[1]):
    v = VIEWS[view]
    return pinhole_rays(v["position"], v["look_at"], v["vfov"], width, height)


def ray_aabb(o, d, lo, hi):
    """Entry distance of rays into an axis-aligned box (inf if missed; 0-clamped)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (lo - o) * inv
        t1 = (hi - o) * inv
    tn = np.nanmax(np.minimum(t0, t1), axis=-1)
    tf = np.nanmin(np.maximum(t0, t1), axis=-1)
    hit = (tf >= np.maximum(tn, 0.0))
    return np.where(hit, np.maximum(tn, 0.0), np.inf)


def ray_plane_y0(o, d):
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[:, 1] / d[:, 1]
    return np.where(t > 0, t, np.inf)


def lambert_radiance(p, n, rho, light_pos=LIGHT_POS, light_i=LIGHT_I):
    """ρ/π · I · cosθ / d² at points p (N,3) with normals n (N,3)."""
    w = light_pos - p
    d2 = np.sum(w * w, -1)
    cos = np.maximum(np.sum(w * n, -1) / np.sqrt(d2), 0.0)
    return rho / np.pi * light_i * (cos / d2)[:, None]


def shadowed_by_box(p, margin):
    """(certainly shadowed, certainly lit) by the box for points p, using a box grown/shrunk by margin."""
    w = LIGHT_POS - p
    dist = np.linalg.norm(w, axis=-1)
    d = w / dist[:, None]
    big = ray_aabb(p, d, BOX_LO - margin, BOX_HI + margin) < dist
    small = ray_aabb(p, d, BOX_LO + margin, BOX_HI - margin) < dist
    return small, ~big
