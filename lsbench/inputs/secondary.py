"""The rays a renderer traces besides the camera's: shadow, ambient occlusion, one diffuse bounce,
and incoherent rays (issue 14). Each generator is deterministic for its seed and returns plain
arrays (origins, directions, per-ray tmax); lsbench/inputs/rays.py makes the RaySet and says which
query it asks (shadow and ao: any hit; diffuse and incoherent: the closest hit).

Secondary rays start where Embree's primary rays hit (lsbench/oracle/embree.py), so every
structure traces the very same rays; a primary ray that misses spawns none. The hit point is
taken on the triangle's plane in float64 (o + t d with t from the plane, not Embree's float32 t)
and then moved off the surface with the integer-ulp offset of Wächter & Binder, "A Fast and
Robust Method for Avoiding Self-Intersection" (Ray Tracing Gems, ch. 6): each coordinate steps a
number of float32 ulps proportional to the geometric normal's component, so the offset scales with
the coordinates' own rounding error wherever the point lies; near zero, where ulps vanish, a fixed
small step is taken instead. The normal is the geometric one, turned towards the side the primary
ray came from: every secondary ray leaves on that side. The origin then moves as far again along
the secondary ray's own direction (`leave_surface`): a hit on a concave edge lies on two faces
(the Cornell box's wall meets its ceiling: a 24x24 image has a row of such hits), and the normal
step of one face leaves the point on the other one, where the ray would start with a hit at t = 0.
(Checked at 96x96 on cornell, spheres and atrium: no shadow, AO or diffuse ray has an Embree hit
closer than 1e-5 x the scene diagonal, and none hits its own triangle.)

Directions on a hemisphere are cosine-weighted (Malley's method: uniform on the unit disk,
projected up; pdf cos(theta) / pi, Pharr, Jakob & Humphreys, PBR 4th ed. 13.6) in an orthonormal
basis built from the normal (Duff et al., "Building an Orthonormal Basis, Revisited", JCGT 2017).
"""
from __future__ import annotations

import numpy as np

# Wächter & Binder's constants (RTG ch. 6): ulps per unit of normal, and below ORIGIN a fixed
# step of FLOAT_SCALE per unit of normal.
OFFSET_INT_SCALE = 256.0
OFFSET_ORIGIN = 1.0 / 32.0
OFFSET_FLOAT_SCALE = 1.0 / 65536.0


class SecondaryError(ValueError):
    """Parameters a generator cannot use (rays.py turns it into a RayError)."""


def offset_origin(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Float32 points `p` (N, 3) moved off their surface along unit normals `n` (N, 3), towards
    the side n points to (Wächter & Binder, RTG ch. 6): each coordinate steps trunc(256 n_i)
    ulps in the direction of n_i; a coordinate within 1/32 of zero moves by n_i / 65536 instead."""
    p = np.ascontiguousarray(p, np.float32)
    n32 = np.asarray(n, np.float32)
    steps = (OFFSET_INT_SCALE * n32).astype(np.int32)  # truncation toward zero, as int() in C
    # Adding k to the bits of a float moves it k ulps away from zero (for k >= 0): a negative
    # coordinate moves along -n_i in magnitude, hence the sign flip.
    bits = p.view(np.int32) + np.where(p < 0, -steps, steps)
    stepped = bits.view(np.float32)
    near_zero = np.abs(p) < OFFSET_ORIGIN
    return np.where(near_zero, p + np.float32(OFFSET_FLOAT_SCALE) * n32, stepped).astype(np.float32)


def leave_surface(p: np.ndarray, n: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The float32 origin of a ray in direction `d` from surface points `p` with unit normals `n`
    (on d's side): offset along the normal (Wächter & Binder), then moved along d itself by as far
    as that offset went (in real space: an ulp step along d would skew it by the axes' ulp sizes
    and could cross back behind the surface). Every coordinate d moves along moves at least one
    ulp that way, or a small component would round back onto a face the point lies on."""
    p = np.asarray(p, np.float32)
    d = np.asarray(d, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    lifted = offset_origin(p, n)
    step = np.linalg.norm(lifted.astype(np.float64) - p, axis=1, keepdims=True)
    moved = (lifted + step * d).astype(np.float32)
    stuck = (moved == lifted) & (d != 0)
    towards = np.where(d > 0, np.float32(np.inf), np.float32(-np.inf))
    return np.where(stuck, np.nextafter(lifted, towards), moved).astype(np.float32)


def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (N, 3) that with unit `n` make a right-handed orthonormal basis, without a
    branch on the normal's direction (Duff et al., JCGT 6(1), 2017, Listing 3)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    s = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, s


def cosine_directions(n: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One cosine-weighted direction (float64, unit) on the hemisphere of each unit normal in `n`:
    Malley's method (a uniform point on the unit disk, lifted onto the hemisphere)."""
    u1, u2 = rng.random(len(n)), rng.random(len(n))
    r, phi = np.sqrt(u1), 2.0 * np.pi * u2
    t, s = orthonormal_basis(n)
    z = np.sqrt(np.maximum(0.0, 1.0 - u1))
    d = (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * s + z[:, None] * n
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def unit_directions(d: np.ndarray) -> np.ndarray:
    """Float32 unit vectors from float64 ones (normalized again after rounding)."""
    d32 = d.astype(np.float32)
    return (d32 / np.linalg.norm(d32.astype(np.float64), axis=1, keepdims=True)).astype(np.float32)


class SurfacePoints:
    """Where the primary rays hit (Embree's answer), in float64: triangle id, point on the
    triangle's plane and geometric normal facing the incoming ray, and the offset float32 origins
    of the secondary rays that leave them."""

    def __init__(self, scene, primary) -> None:
        from lsbench.oracle.embree import embree_closest  # lazy: embree imports inputs.rays

        prim, _t = embree_closest(scene, primary)
        hit = np.flatnonzero(prim >= 0)
        self.primary_ray = hit  # which primary ray each point comes from
        self.prim = prim[hit].astype(np.int64)
        tris = scene.triangles[self.prim].astype(np.float64)
        o = primary.origins[hit].astype(np.float64)
        d = primary.directions[hit].astype(np.float64)
        normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)  # a zero-area triangle is never hit
        facing = np.einsum("ij,ij->i", normal, d) > 0
        normal[facing] *= -1.0  # towards the side the ray came from
        # the hit on the triangle's plane (float64), not o + t d with Embree's float32 t
        t_plane = np.einsum("ij,ij->i", tris[:, 0] - o, normal) / np.einsum("ij,ij->i", d, normal)
        self.point = o + t_plane[:, None] * d
        self.normal = normal

    def origins(self, directions: np.ndarray, per_point: int = 1) -> np.ndarray:
        """Float32 origins of rays leaving each point in `directions` ((count * per_point, 3),
        per_point consecutive rays a point)."""
        point = np.repeat(self.point.astype(np.float32), per_point, axis=0)
        return leave_surface(point, np.repeat(self.normal, per_point, axis=0), directions)

    @property
    def count(self) -> int:
        return int(len(self.prim))


def default_light(scene) -> np.ndarray:
    """A point light derived from the scene bounds: above the centre, at 90 % of the height along
    the scene camera's up axis (the built-ins' up is +y), so it lies inside an interior (the
    Cornell box's ceiling is the top of its bounds) and above an open scene's objects."""
    from lsbench.inputs.scenes import default_camera

    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    up_axis = int(np.argmax(np.abs(default_camera(scene).up)))
    light = 0.5 * (lo + hi)
    light[up_axis] = lo[up_axis] + 0.9 * (hi[up_axis] - lo[up_axis])
    return light


def light_samples(scene, light, light_size: float, samples: int, rng: np.random.Generator) -> np.ndarray:
    """(samples, 3) float64 points on the light: the point light itself, or uniform points on a
    square quad light of edge light_size centred there, spanning the two axes other than up."""
    from lsbench.inputs.scenes import default_camera

    centre = default_light(scene) if light is None else np.asarray(light, np.float64)
    if light_size == 0.0:
        if samples != 1:
            raise SecondaryError(f"samples = {samples} needs light_size > 0: a point light has one sample")
        return centre[None, :]
    up_axis = int(np.argmax(np.abs(default_camera(scene).up)))
    pts = np.repeat(centre[None, :], samples, axis=0)
    for axis, u in zip([a for a in range(3) if a != up_axis], (rng.random(samples), rng.random(samples))):
        pts[:, axis] += (u - 0.5) * light_size
    return pts


def shadow_arrays(scene, primary, *, light=None, light_size: float = 0.0, samples: int = 1,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shadow rays: from each primary hit to each of `samples` points on the light (one point
    light, or a square quad light of edge `light_size`; rays.py documents the parameters), with
    tmax = the distance to that point, for an any-hit query. A hit that faces away from a light
    point spawns no ray to it (N.L <= 0: the surface shades itself; a renderer traces nothing).
    The same light points serve every hit (one draw per seed), ray order: hit by hit, sample by
    sample."""
    rng = np.random.default_rng(seed)
    lights = light_samples(scene, light, float(light_size), int(samples), rng)
    sp = SurfacePoints(scene, primary)
    target = np.tile(lights, (sp.count, 1))
    normal = np.repeat(sp.normal, len(lights), axis=0)
    point = np.repeat(sp.point, len(lights), axis=0)
    keep = np.einsum("ij,ij->i", target - point, normal) > 0
    point, normal, target = point[keep], normal[keep], target[keep]
    origin = leave_surface(point.astype(np.float32), normal, target - point).astype(np.float64)
    directions = unit_directions(target - origin)
    # tmax from the float32 origin and direction the kernels read: o + tmax d is the light point
    tmax = np.linalg.norm(target - origin, axis=1).astype(np.float32)
    return origin.astype(np.float32), directions, tmax


def ao_arrays(scene, primary, *, samples: int = 4, distance: float = 0.1,
              seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ambient-occlusion rays: `samples` cosine-weighted directions per primary hit, tmax =
    `distance` x the scene's bounding-box diagonal, for an any-hit query. Ray order: hit by hit."""
    rng = np.random.default_rng(seed)
    sp = SurfacePoints(scene, primary)
    directions = unit_directions(cosine_directions(np.repeat(sp.normal, samples, axis=0), rng))
    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    tmax = np.full(len(directions), distance * float(np.linalg.norm(hi - lo)), np.float32)
    return sp.origins(directions, samples), directions, tmax


def diffuse_arrays(scene, primary, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray, None]:
    """One diffuse bounce: a cosine-weighted direction per primary hit, for the closest hit."""
    rng = np.random.default_rng(seed)
    sp = SurfacePoints(scene, primary)
    directions = unit_directions(cosine_directions(sp.normal, rng))
    return sp.origins(directions), directions, None


def incoherent_arrays(scene, *, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, None]:
    """`count` rays with origins uniform in the scene's bounding box and directions uniform on
    the sphere (z uniform in [-1, 1], azimuth uniform: Archimedes), for the closest hit."""
    rng = np.random.default_rng(seed)
    lo, hi = (b.astype(np.float64) for b in scene.bounds)
    origins = lo + rng.random((count, 3)) * (hi - lo)
    z = rng.uniform(-1.0, 1.0, count)
    phi = rng.uniform(0.0, 2.0 * np.pi, count)
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    return origins.astype(np.float32), unit_directions(d), None
