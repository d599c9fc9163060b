"""Ray casting and shading of a SimScene (simulator/scene.py): ray/primitive intersection on component arrays,
per-view casting in bounded bands, and the linear approximate SSS shading model described in scene.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightstage.errors import LightstageError
from lightstage.simulator.scene import (
    KIND_NONE,
    KIND_OBJECT,
    KIND_STAND,
    Cylinder,
    Ellipsoid,
    SimScene,
    SolidTexture,
    core_albedo,
    dark_patches,
    object_albedo,
    stand_albedo,
)

# Pixels per ray-casting band (keeps memory bounded at any resolution).
BAND_PIXELS = 1 << 20


# ---- ray / primitive intersection (component arrays, vectorised over rays) -------------------------
def ellipsoid_interval(e: Ellipsoid, o: tuple, d: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_enter, t_exit, hit) of rays o + t d (tuples of x, y, z arrays) with an ellipsoid."""
    ox, oy, oz = ((o[i] - e.centre[i]) / e.radii[i] for i in range(3))
    dx, dy, dz = (d[i] / e.radii[i] for i in range(3))
    a = dx * dx + dy * dy + dz * dz
    b = ox * dx + oy * dy + oz * dz
    c = ox * ox + oy * oy + oz * oz - 1.0
    disc = b * b - a * c
    hit = disc > 0
    s = np.sqrt(np.maximum(disc, 0))
    return (-b - s) / a, (-b + s) / a, hit


def ellipsoid_normal(e: Ellipsoid, p: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit outward normal at points p on the ellipsoid."""
    n = [(p[i] - e.centre[i]) / (e.radii[i] ** 2) for i in range(3)]
    inv = 1.0 / np.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)
    return n[0] * inv, n[1] * inv, n[2] * inv


def cylinder_interval(
    c: Cylinder, o: tuple, d: tuple
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t_enter, t_exit, hit, entered_through_cap) of rays with a vertical capped cylinder."""
    ox, oy = o[0] - c.centre_xy[0], o[1] - c.centre_xy[1]
    dx, dy, dz = d
    a = dx * dx + dy * dy
    b = ox * dx + oy * dy
    cc = ox * ox + oy * oy - c.radius**2
    disc = b * b - a * cc
    safe_a = np.where(a > 1e-12, a, 1.0)
    s = np.sqrt(np.maximum(disc, 0))
    vertical = a <= 1e-12
    t0 = np.where(vertical, np.where(cc < 0, -np.inf, np.inf), (-b - s) / safe_a)
    t1 = np.where(vertical, np.where(cc < 0, np.inf, -np.inf), (-b + s) / safe_a)
    t0 = np.where(~vertical & (disc <= 0), np.inf, t0)
    t1 = np.where(~vertical & (disc <= 0), -np.inf, t1)
    safe_dz = np.where(np.abs(dz) > 1e-12, dz, 1e-12)
    za, zb = (c.z_min - o[2]) / safe_dz, (c.z_max - o[2]) / safe_dz
    tz0, tz1 = np.minimum(za, zb), np.maximum(za, zb)
    enter = np.maximum(t0, tz0)
    exit_ = np.minimum(t1, tz1)
    return enter, exit_, enter < exit_, tz0 > t0


def union_length(intervals: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Length of the union of ray intervals restricted to t > 0, and the farthest exit distance (0 if none)."""
    starts = np.stack([np.where(h, np.maximum(a, 0), 0) for a, b, h in intervals])
    ends = np.stack([np.where(h, np.maximum(b, 0), 0) for a, b, h in intervals])
    ends = np.maximum(ends, starts)
    order = np.argsort(starts, axis=0)
    starts = np.take_along_axis(starts, order, axis=0)
    ends = np.take_along_axis(ends, order, axis=0)
    total = np.zeros(starts.shape[1], starts.dtype)
    reach = np.zeros(starts.shape[1], starts.dtype)
    for k in range(starts.shape[0]):
        s = np.maximum(starts[k], reach)
        total += np.maximum(ends[k] - s, 0)
        reach = np.maximum(reach, ends[k])
    return total, reach


# ---- per-view ray casting ----------------------------------------------------------------------------
@dataclass
class ViewHits:
    """Everything light-independent about one view: which pixels see the object/stand and their surface data."""

    width: int
    height: int
    index: np.ndarray  # (N,) flat pixel indices of hits (row-major)
    kind: np.ndarray  # (N,) KIND_OBJECT / KIND_STAND
    pos: np.ndarray  # (N, 3) float64 surface points
    normal: np.ndarray  # (N, 3) float32
    view: np.ndarray  # (N, 3) float32 unit direction from the point to the camera
    albedo: np.ndarray  # (N, 3) float32 effective albedo (object: surface mixed with the visible core)

    def mask(self) -> np.ndarray:
        """(H, W) bool foreground (object + stand)."""
        m = np.zeros(self.width * self.height, bool)
        m[self.index] = True
        return m.reshape(self.height, self.width)


def first_hit(scene: SimScene, o: tuple, d: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, kind, primitive) of the first surface along rays; t = inf and kind = KIND_NONE on a miss.
    primitive: index into scene.body for object hits, -1 for the stand cap, -2 for the stand side."""
    n = o[0].shape[0]
    t = np.full(n, np.inf)
    kind = np.zeros(n, np.int8)
    prim = np.zeros(n, np.int16)
    for k, e in enumerate(scene.body):
        a, _b, h = ellipsoid_interval(e, o, d)
        better = h & (a > 0) & (a < t)
        t = np.where(better, a, t)
        kind[better] = KIND_OBJECT
        prim[better] = k
    a, _b, h, cap = cylinder_interval(scene.stand, o, d)
    better = h & (a > 0) & (a < t)
    t = np.where(better, a, t)
    kind[better] = KIND_STAND
    prim[better] = np.where(cap[better], -1, -2)
    return t, kind, prim


def _pixel_rays(
    u: np.ndarray, v: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World rays (origins, unit directions) through pixel coordinates; same maths as
    `lightstage.cameras.pixel_rays` with explicit products (no BLAS on (N, 3) arrays)."""
    Ki = np.linalg.inv(np.asarray(K, np.float64))
    x = Ki[0, 0] * u + Ki[0, 1] * v + Ki[0, 2]
    y = Ki[1, 0] * u + Ki[1, 1] * v + Ki[1, 2]
    z = Ki[2, 0] * u + Ki[2, 1] * v + Ki[2, 2]
    R = np.asarray(R, np.float64)
    d = np.stack([R[0, i] * x + R[1, i] * y + R[2, i] * z for i in range(3)], axis=-1)
    d /= np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
    centre = -R.T @ np.asarray(t, np.float64)
    return np.broadcast_to(centre, d.shape).copy(), d


def _scene_roi(
    scene: SimScene, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int
) -> tuple[int, int, int, int]:
    """Pixel box (col0, col1, row0, row1) that contains the projection of the object and stand bounding boxes
    (the whole image if any corner is behind the camera); rays outside it cannot hit anything."""
    lo, hi = scene.bounding_box()
    st = scene.stand
    slo = [st.centre_xy[0] - st.radius, st.centre_xy[1] - st.radius, st.z_min]
    shi = [st.centre_xy[0] + st.radius, st.centre_xy[1] + st.radius, st.z_max]
    corners = []
    for a, b in ((lo, hi), (slo, shi)):
        for k in range(8):
            corners.append([(b if k >> i & 1 else a)[i] for i in range(3)])
    pc = np.asarray(corners) @ np.asarray(R).T + np.asarray(t)
    if (pc[:, 2] <= 1e-6).any():
        return 0, width, 0, height
    uv = pc @ np.asarray(K).T
    uv = uv[:, :2] / uv[:, 2:]
    c0 = int(np.clip(np.floor(uv[:, 0].min()) - 2, 0, width))
    c1 = int(np.clip(np.ceil(uv[:, 0].max()) + 2, 0, width))
    r0 = int(np.clip(np.floor(uv[:, 1].min()) - 2, 0, height))
    r1 = int(np.clip(np.ceil(uv[:, 1].max()) + 2, 0, height))
    return c0, c1, r0, r1


def cast_view(
    scene: SimScene, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int
) -> ViewHits:
    """Ray-cast every pixel centre of a view once (in row bands) and gather surface data of the hits."""
    tex = SolidTexture(scene.texture_seed)
    mat = scene.material
    c0, c1, row0, row1 = _scene_roi(scene, K, R, t, width, height)
    rows_per_band = max(1, BAND_PIXELS // max(c1 - c0, 1))
    parts: dict[str, list[np.ndarray]] = {
        k: [] for k in ("index", "kind", "pos", "normal", "view", "prim", "depth")
    }
    for r0 in range(row0, row1, rows_per_band):
        r1 = min(row1, r0 + rows_per_band)
        jj, ii = np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij")
        origins, dirs = _pixel_rays(ii.ravel() + 0.5, jj.ravel() + 0.5, K, R, t)
        o = (origins[:, 0], origins[:, 1], origins[:, 2])
        d = (dirs[:, 0], dirs[:, 1], dirs[:, 2])
        th, kind, prim = first_hit(scene, o, d)
        sel = np.nonzero(kind != KIND_NONE)[0]
        if sel.size == 0:
            continue
        pos = origins[sel] + th[sel, None] * dirs[sel]
        parts["index"].append((jj.ravel()[sel] * width + ii.ravel()[sel]).astype(np.int64))
        parts["kind"].append(kind[sel])
        parts["pos"].append(pos)
        parts["view"].append(-dirs[sel])
        parts["prim"].append(prim[sel])
        # depth below the surface at which the camera ray meets the core (inf where it misses)
        os_ = (origins[sel, 0], origins[sel, 1], origins[sel, 2])
        ds_ = (dirs[sel, 0], dirs[sel, 1], dirs[sel, 2])
        ca, _cb, ch = ellipsoid_interval(scene.core, os_, ds_)
        parts["depth"].append(np.where(ch & (kind[sel] == KIND_OBJECT), ca - th[sel], np.inf))
    if not parts["index"]:
        z3 = np.zeros((0, 3), np.float32)
        return ViewHits(
            width, height, np.zeros(0, np.int64), np.zeros(0, np.int8), z3.astype(float), z3, z3, z3
        )
    index = np.concatenate(parts["index"])
    kind = np.concatenate(parts["kind"])
    pos = np.concatenate(parts["pos"])
    view = np.concatenate(parts["view"]).astype(np.float32)
    prim = np.concatenate(parts["prim"])
    depth = np.concatenate(parts["depth"])
    normal = np.zeros_like(pos)
    p3 = (pos[:, 0], pos[:, 1], pos[:, 2])
    for k, e in enumerate(scene.body):
        s = prim == k
        if s.any():
            n = ellipsoid_normal(e, tuple(c[s] for c in p3))
            normal[s] = np.stack(n, axis=-1)
    side = (kind == KIND_STAND) & (prim == -2)
    radial = pos[side, :2] - np.asarray(scene.stand.centre_xy)
    normal[side, :2] = radial / np.linalg.norm(radial, axis=-1, keepdims=True)
    normal[(kind == KIND_STAND) & (prim == -1), 2] = 1.0
    albedo = np.zeros((len(index), 3), np.float32)
    obj = kind == KIND_OBJECT
    if obj.any():
        base = np.asarray(mat.base_rgb, np.float32)
        surf = object_albedo(tex, pos[obj], base) if mat.texture else np.tile(base, (int(obj.sum()), 1))
        core_pts = (
            pos[obj] - view[obj].astype(float) * np.where(np.isfinite(depth[obj]), depth[obj], 0)[:, None]
        )
        core = core_albedo(tex, core_pts, np.asarray(mat.core_rgb, np.float32))
        vis = mat.core_opacity * np.exp(
            -mat.sigma_view * np.where(np.isfinite(depth[obj]), depth[obj], np.inf)
        )
        vis = vis.astype(np.float32)[:, None]
        albedo[obj] = (1.0 - vis) * surf + vis * core
        if mat.dark_fraction > 0:
            dark = dark_patches(tex, pos[obj], mat.dark_fraction)[:, None]
            albedo[obj] *= 1.0 - (1.0 - np.float32(mat.dark_albedo)) * dark
    st = kind == KIND_STAND
    if st.any():
        stand_base = np.asarray(mat.stand_rgb, np.float32)
        albedo[st] = (
            stand_albedo(tex, pos[st], stand_base) if mat.texture else np.tile(stand_base, (int(st.sum()), 1))
        )
    return ViewHits(width, height, index, kind, pos, normal.astype(np.float32), view, albedo)


def scatter_rows(dst: np.ndarray, index: np.ndarray, rows: np.ndarray) -> None:
    """`dst[index] = rows` for a C-contiguous (N, C) `dst`, each row copied as one opaque item of C values:
    numpy's row-wise fancy assignment is ~3x slower with 3 float32 per row. The bytes are copied unchanged."""
    item = np.dtype((np.void, dst.shape[1] * dst.itemsize))
    src = np.ascontiguousarray(rows, dst.dtype)
    dst.view(item).reshape(-1)[index] = src.view(item).reshape(-1)


# ---- shading -----------------------------------------------------------------------------------------
class _Prepared:
    """Light-independent per-view arrays for fast shading: float32 components, per-primitive offsets."""

    def __init__(self, scene: SimScene, hits: ViewHits, sel: np.ndarray):
        f = np.float32
        self.sel = sel
        self.p = tuple(np.ascontiguousarray(hits.pos[sel, i], f) for i in range(3))
        self.n = tuple(np.ascontiguousarray(hits.normal[sel, i], f) for i in range(3))
        self.v = tuple(np.ascontiguousarray(hits.view[sel, i], f) for i in range(3))
        self.albedo = hits.albedo[sel]
        self.ell = [_EllipsoidOrigin(e, self.p) for e in scene.body]
        self.core = _EllipsoidOrigin(scene.core, self.p)
        # light entering here splits: the part diffusing through to the far side (thickness along -n)
        # leaves there, so only the rest re-emerges on this side (1 - T(back thickness))
        inward = tuple(-c for c in self.n)
        back, _ = _positive_union_length([e.interval(inward) for e in self.ell])
        sig = np.asarray(scene.material.sigma_tr, f)
        self.same_side = (1.0 - np.exp(-back[:, None] * sig[None, :])).astype(f)
        st = scene.stand
        self.sx = self.p[0] - f(st.centre_xy[0])
        self.sy = self.p[1] - f(st.centre_xy[1])
        self.scc = self.sx * self.sx + self.sy * self.sy - f(st.radius**2)
        self.sz = (f(st.z_min) - self.p[2], f(st.z_max) - self.p[2])


class _EllipsoidOrigin:
    """An ellipsoid with the ray origins (surface points) already in its unit-sphere frame."""

    def __init__(self, e: Ellipsoid, p: tuple):
        f = np.float32
        self.inv_r = tuple(f(1.0 / r) for r in e.radii)
        self.q = tuple((p[i] - f(e.centre[i])) * self.inv_r[i] for i in range(3))
        self.c = self.q[0] * self.q[0] + self.q[1] * self.q[1] + self.q[2] * self.q[2] - f(1.0)

    def interval(self, d: tuple) -> tuple[np.ndarray, np.ndarray]:
        """(t_enter, t_exit) along unit directions d; t_enter = t_exit = 0 where the ray misses."""
        dx, dy, dz = (d[i] * self.inv_r[i] for i in range(3))
        a = dx * dx + dy * dy + dz * dz
        b = self.q[0] * dx + self.q[1] * dy + self.q[2] * dz
        disc = b * b - a * self.c
        miss = disc <= 0
        np.maximum(disc, 0, out=disc)
        s = np.sqrt(disc, out=disc)
        inv_a = np.divide(1.0, a, out=a)
        nb = np.negative(b, out=b)  # -b once, then (-b - s) / a and (-b + s) / a, in place
        t0 = nb - s
        t0 *= inv_a
        t1 = np.add(nb, s, out=nb)
        t1 *= inv_a
        t0[miss] = 0
        t1[miss] = 0
        return t0, t1


def _positive_union_length(intervals: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Length of the union of intervals within t > 0 (inclusion-exclusion), and the farthest exit."""
    clipped = [(np.maximum(a, 0), np.maximum(b, 0)) for a, b in intervals]
    total = np.zeros_like(clipped[0][0])
    k = len(clipped)
    for mask in range(1, 1 << k):
        members = [clipped[i] for i in range(k) if mask >> i & 1]
        lo = members[0][0]
        hi = members[0][1]
        for a, b in members[1:]:
            lo = np.maximum(lo, a)
            hi = np.minimum(hi, b)
        part = np.maximum(hi - lo, 0)
        if len(members) % 2:
            total += part
        else:
            total -= part
    far = clipped[0][1]
    for _a, b in clipped[1:]:
        far = np.maximum(far, b)
    return np.maximum(total, 0), far


def _prepared(scene: SimScene, hits: ViewHits) -> tuple[_Prepared, _Prepared]:
    cache = getattr(hits, "_prep", None)
    if cache is None or cache[0] is not scene:
        obj = np.nonzero(hits.kind == KIND_OBJECT)[0]
        st = np.nonzero(hits.kind == KIND_STAND)[0]
        cache = (scene, _Prepared(scene, hits, obj), _Prepared(scene, hits, st))
        hits._prep = cache
    return cache[1], cache[2]


def shade(
    scene: SimScene, hits: ViewHits, light_pos: np.ndarray, intensity: np.ndarray | float
) -> np.ndarray:
    """(N, 3) float32 radiance of the hit points under one point light (linear in `intensity`, RGB or scalar)."""
    mat = scene.material
    f = np.float32
    inten = np.broadcast_to(np.asarray(intensity, f), (3,))
    lp = np.asarray(light_pos, np.float64)
    obj, st = _prepared(scene, hits)
    out = np.zeros((len(hits.index), 3), f)
    for prep, is_obj in ((obj, True), (st, False)):
        if prep.sel.size == 0:
            continue
        L = [f(lp[i]) - prep.p[i] for i in range(3)]
        r2 = L[0] * L[0] + L[1] * L[1] + L[2] * L[2]
        inv_r = 1.0 / np.sqrt(r2)
        d = tuple(c * inv_r for c in L)
        E = inv_r * inv_r  # irradiance per unit intensity at normal incidence (inverse square)
        n, v = prep.n, prep.v
        ndl = n[0] * d[0] + n[1] * d[1] + n[2] * d[2]
        h = [d[i] + v[i] for i in range(3)]
        hn = 1.0 / np.maximum(np.sqrt(h[0] * h[0] + h[1] * h[1] + h[2] * h[2]), f(1e-12))
        ndh = np.maximum((n[0] * h[0] + n[1] * h[1] + n[2] * h[2]) * hn, 0)
        intervals = [e.interval(d) for e in prep.ell]
        thick, far = _positive_union_length(intervals)
        ca, cb = prep.core.interval(d)
        if is_obj:
            vis = _stand_free(scene.stand, prep, d)
            # the light enters the wax at the farthest exit along the ray: weight by its cosine there
            entry = tuple(prep.p[i] + far * d[i] for i in range(3))
            ne = _union_normal(scene, entry)
            ne_dot = np.maximum(ne[0] * d[0] + ne[1] * d[1] + ne[2] * d[2], 0)
            core_pass = _core_shadow(ca, cb, mat.core_opacity)
            sig = np.asarray(mat.sigma_tr, f)
            trans = np.exp(-thick[:, None] * sig[None, :])
            lit_side = thick < f(1e-4)
            np.multiply(trans, prep.same_side, out=trans, where=lit_side[:, None])
            trans *= (ne_dot * core_pass * f(mat.kt / np.pi))[:, None]
            wrap = np.maximum(ndl + f(mat.wrap), 0) * f(mat.kd / (np.pi * (1.0 + mat.wrap) ** 2))
            spec = f(mat.ks * (mat.shininess + 8.0) / (8.0 * np.pi)) * ndh ** f(mat.shininess)
            spec *= np.maximum(ndl, 0)
            trans += wrap[:, None]
            rad = trans * prep.albedo
            rad += spec[:, None]
            rad *= (E * vis)[:, None]
        else:
            shadow = np.exp(-f(mat.sigma_shadow) * thick) * _core_shadow(ca, cb, 1.0)
            ndl_s = np.maximum(ndl, 0)
            spec = f(mat.stand_ks * (40.0 + 8.0) / (8.0 * np.pi)) * ndh**40 * ndl_s
            rad = prep.albedo * (ndl_s * f(1.0 / np.pi))[:, None]
            rad += spec[:, None]
            rad *= (E * shadow)[:, None]
        rad *= inten[None, :]  # every hit is object or stand: each row of `out` is set once, here
        scatter_rows(out, prep.sel, rad)
    return out


def _stand_free(stand: Cylinder, prep: _Prepared, d: tuple) -> np.ndarray:
    """1 where the ray from the surface point towards the light misses the opaque stand, else 0."""
    f = np.float32
    dx, dy, dz = d
    a = np.maximum(dx * dx + dy * dy, f(1e-12))
    b = prep.sx * dx + prep.sy * dy
    disc = b * b - a * prep.scc
    s = np.sqrt(np.maximum(disc, 0))
    t0, t1 = (-b - s) / a, (-b + s) / a
    safe = np.where(np.abs(dz) > 1e-9, dz, f(1e-9))
    za, zb = prep.sz[0] / safe, prep.sz[1] / safe
    enter = np.maximum(t0, np.minimum(za, zb))
    exit_ = np.minimum(t1, np.maximum(za, zb))
    blocked = (disc > 0) & (enter < exit_) & (exit_ > 1e-5)
    return (~blocked).astype(f)


def _core_shadow(a: np.ndarray, b: np.ndarray, opacity: float) -> np.ndarray:
    """Fraction of diffused light passing the opaque core along a light ray: soft (diffusion blurs its shadow),
    darkest where the ray's chord through the core is long (a = b where the ray misses)."""
    chord = np.maximum(b, 0) - np.maximum(a, 0)
    return 1.0 - np.float32(opacity) * (1.0 - np.exp(chord * np.float32(-1.0 / 0.012)))


def _union_normal(scene: SimScene, p: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Outward normal at points on the union surface: that of the ellipsoid whose boundary is nearest (the
    first on ties). The nearest is found first and its normal computed once per point, with that ellipsoid's
    centre and squared radii gathered per point (the same float32 operations as ellipsoid_normal)."""
    best = None
    which = np.zeros(p[0].shape, np.intp)
    for k, e in enumerate(scene.body):
        q = [(p[i] - e.centre[i]) / e.radii[i] for i in range(3)]
        err = np.abs(np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2) - 1.0)
        if best is None:
            best = err
            continue
        better = err < best
        np.copyto(best, err, where=better)
        which[better] = k
    centre = np.array([e.centre for e in scene.body], p[0].dtype).T  # (3, K): one row per axis
    r2 = np.array([[r**2 for r in e.radii] for e in scene.body], p[0].dtype).T
    n = [(p[i] - centre[i].take(which)) / r2[i].take(which) for i in range(3)]
    inv = 1.0 / np.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)
    return n[0] * inv, n[1] * inv, n[2] * inv


def render_hits(
    scene: SimScene, hits: ViewHits, light_positions: np.ndarray, intensities: np.ndarray | float = 1.0
) -> np.ndarray:
    """(H, W, 3) float32 clean radiance (background 0) for a sum of point lights."""
    light_positions = np.atleast_2d(np.asarray(light_positions, np.float64))
    inten = np.asarray(intensities, np.float32)
    if inten.ndim == 0:
        inten = np.full(len(light_positions), inten)
    if len(inten) != len(light_positions):
        raise LightstageError(f"{len(light_positions)} lights but {len(inten)} intensities")
    acc = np.zeros((len(hits.index), 3), np.float32)
    for p, i in zip(light_positions, inten, strict=True):
        acc += shade(scene, hits, p, i)
    img = np.zeros((hits.height * hits.width, 3), np.float32)
    img[hits.index] = acc
    return img.reshape(hits.height, hits.width, 3)
