"""Analytic SDF scenes and sphere tracing (pure Warp, float32).

A scene is a list of primitives folded left to right into one signed distance: ``acc = d_0``,
then ``acc = op_i(acc, d_i)`` with op union ``min``, smooth union (polynomial smin of width k),
intersection ``max`` and subtraction ``max(acc, -d_i)``. Primitive i is evaluated in its local
frame ``q = R_i (p - c_i)`` (``R_i`` world-to-local rotation, ``c_i`` centre) with parameters
``params_i``:

    0 sphere    (radius)                     |q| - r
    1 box       (half x, half y, half z, rounding)
    2 torus     (major R, minor r), axis y   |(|q.xz| - R, q.y)| - r
    3 capsule   (half length h, radius r), segment from -h to +h along y
    4 plane     the local y = 0 plane, solid below (q.y < 0)

``ids`` reports the primitive that decides the value at a point, for per-primitive colours: the
last one that was nearer than the accumulator (union, smooth union), farther (intersection) or
whose complement was farther (subtraction).

Sphere tracing (one thread per ray): start at ``near``; if the scene is negative there the ray
starts inside a solid (status INSIDE, t = near). Otherwise step ``t += omega * d(t)`` until
``d < eps`` (HIT: t, point, normal from a tetrahedral central difference of width
``normal_eps``), ``t > far`` (MISS, t = far) or ``max_iters`` evaluations (CAP: not a hit; t is
where it stopped). A hit stops where the distance first drops below eps, which is up to
``eps / |n . d|`` before the true surface along the ray (large only for grazing rays).
Non-finite origins/directions/bounds give status INVALID and NaN t.

Over-relaxation (``omega`` > 1, Keinert et al. 2015): a step of ``omega * d`` may pass the
surface; it is accepted only while the unbounding spheres of consecutive points overlap
(``|d_prev| + |d| >= step``); when they do not, the march returns to the last safe point
``t_prev + d_prev`` and continues with omega = 1. With omega = 1 an exact or conservative SDF
(|grad| <= 1) can never step through a surface. Failure modes, documented: grazing rays that
pass within ``eps`` of a silhouette count as hits; rays nearly tangent to a surface take many
small steps and may end as CAP; a distance bound that overestimates (a non-uniformly scaled or
smooth-blended field with |grad| > 1) can tunnel through features thinner than its error, and a
negative value reached this way is reported as a HIT at that t.
"""

import warp as wp

SPHERE = wp.constant(0)
BOX = wp.constant(1)
TORUS = wp.constant(2)
CAPSULE = wp.constant(3)
PLANE = wp.constant(4)

UNION = wp.constant(0)
SMOOTH_UNION = wp.constant(1)
INTERSECTION = wp.constant(2)
SUBTRACTION = wp.constant(3)

MISS = wp.constant(0)
HIT = wp.constant(1)
CAP = wp.constant(2)
INSIDE = wp.constant(3)
INVALID = wp.constant(4)


@wp.func
def primitive_sdf(kind: int, prm: wp.vec4, q: wp.vec3):
    if kind == SPHERE:
        return wp.length(q) - prm[0]
    if kind == BOX:
        rnd = prm[3]
        d = wp.vec3(wp.abs(q[0]), wp.abs(q[1]), wp.abs(q[2])) - wp.vec3(prm[0], prm[1], prm[2])
        d = d + wp.vec3(rnd, rnd, rnd)
        outside = wp.length(wp.vec3(wp.max(d[0], 0.0), wp.max(d[1], 0.0), wp.max(d[2], 0.0)))
        inside = wp.min(wp.max(d[0], wp.max(d[1], d[2])), 0.0)
        return outside + inside - rnd
    if kind == TORUS:
        ring = wp.sqrt(q[0] * q[0] + q[2] * q[2]) - prm[0]
        return wp.sqrt(ring * ring + q[1] * q[1]) - prm[1]
    if kind == CAPSULE:
        y = q[1] - wp.clamp(q[1], -prm[0], prm[0])
        return wp.sqrt(q[0] * q[0] + y * y + q[2] * q[2]) - prm[1]
    return q[1]  # PLANE


@wp.func
def combine(op: int, acc: float, d: float, k: float):
    if op == UNION:
        return wp.min(acc, d)
    if op == SMOOTH_UNION:
        h = wp.clamp(0.5 + 0.5 * (d - acc) / k, 0.0, 1.0)
        return d + (acc - d) * h - k * h * (1.0 - h)
    if op == INTERSECTION:
        return wp.max(acc, d)
    return wp.max(acc, -d)  # SUBTRACTION


@wp.func
def decides(op: int, acc: float, d: float):
    """Whether primitive value d takes over the point (union/blend: nearer; intersection:
    farther; subtraction: its complement farther)."""
    if op == INTERSECTION:
        return d > acc
    if op == SUBTRACTION:
        return -d > acc
    return d < acc


@wp.struct
class Scene:
    """A scene's m primitives, in folding order."""

    kinds: wp.array(dtype=wp.int32)  # [m] SPHERE .. PLANE
    params: wp.array(dtype=wp.vec4)  # [m] meaning per kind (see above)
    rots: wp.array(dtype=wp.mat33)  # [m] world-to-local
    centers: wp.array(dtype=wp.vec3)  # [m]
    ops: wp.array(dtype=wp.int32)  # [m] UNION .. SUBTRACTION (the first one's is not read)
    ks: wp.array(dtype=float)  # [m] smooth-union widths


@wp.func
def scene_eval(p: wp.vec3, scene: Scene):
    """(distance, deciding primitive) of the folded scene at p."""
    acc = float(0.0)
    pid = int(-1)
    for i in range(scene.kinds.shape[0]):
        q = scene.rots[i] * (p - scene.centers[i])
        d = primitive_sdf(int(scene.kinds[i]), scene.params[i], q)
        if i == 0:
            acc = d
            pid = 0
        else:
            op = int(scene.ops[i])
            if decides(op, acc, d):
                pid = i
            acc = combine(op, acc, d, scene.ks[i])
    return acc, pid


@wp.func
def scene_normal(p: wp.vec3, h: float, scene: Scene):
    """Unit gradient by the tetrahedral central difference (4 evaluations, error O(h^2))."""
    k0 = wp.vec3(1.0, -1.0, -1.0)
    k1 = wp.vec3(-1.0, -1.0, 1.0)
    k2 = wp.vec3(-1.0, 1.0, -1.0)
    k3 = wp.vec3(1.0, 1.0, 1.0)
    d0, i0 = scene_eval(p + h * k0, scene)
    d1, i1 = scene_eval(p + h * k1, scene)
    d2, i2 = scene_eval(p + h * k2, scene)
    d3, i3 = scene_eval(p + h * k3, scene)
    g = d0 * k0 + d1 * k1 + d2 * k2 + d3 * k3
    return wp.normalize(g)


@wp.kernel(enable_backward=False)
def scene_sdf_fwd(
    points: wp.array(dtype=wp.vec3),  # [n]
    scene: Scene,
    sdf: wp.array(dtype=float),  # [n] out
    ids: wp.array(dtype=wp.int32),  # [n] out
):
    tid = wp.tid()
    d, pid = scene_eval(points[tid], scene)
    sdf[tid] = d
    ids[tid] = pid


@wp.func
def finite_vec(v: wp.vec3):
    return wp.isfinite(v[0]) and wp.isfinite(v[1]) and wp.isfinite(v[2])


@wp.kernel(enable_backward=False)
def sphere_trace_fwd(
    origins: wp.array(dtype=wp.vec3),  # [n]
    directions: wp.array(dtype=wp.vec3),  # [n] unit length
    near: wp.array(dtype=float),  # [n]
    far: wp.array(dtype=float),  # [n]
    scene: Scene,
    eps: float,
    omega0: float,
    max_iters: int,
    normal_eps: float,
    t_out: wp.array(dtype=float),  # [n]
    status: wp.array(dtype=wp.int32),  # [n]
    iters: wp.array(dtype=wp.int32),  # [n] scene evaluations along the ray
    points: wp.array(dtype=wp.vec3),  # [n] hit points (o + t d for other statuses)
    normals: wp.array(dtype=wp.vec3),  # [n] unit normals at hits, zero otherwise
    ids: wp.array(dtype=wp.int32),  # [n] primitive hit, -1 otherwise
):
    tid = wp.tid()
    o = origins[tid]
    d = directions[tid]
    t = near[tid]
    t_far = far[tid]
    normals[tid] = wp.vec3(0.0, 0.0, 0.0)
    ids[tid] = -1
    if not (finite_vec(o) and finite_vec(d) and wp.isfinite(t) and wp.isfinite(t_far)):
        t_out[tid] = wp.nan
        status[tid] = INVALID
        iters[tid] = 0
        points[tid] = wp.vec3(wp.nan, wp.nan, wp.nan)
        return
    st = int(CAP)
    omega = omega0
    t_prev = t
    d_prev = float(0.0)
    step = float(0.0)
    n_eval = int(0)
    pid = int(-1)
    while n_eval < max_iters:
        if t > t_far:
            if omega > 1.0 and step > d_prev and t_prev + d_prev <= t_far:
                # a relaxed step jumped past far: only t_prev + d_prev is certified empty
                t = t_prev + d_prev
                omega = 1.0
                step = d_prev
                continue
            st = MISS
            t = t_far
            break
        dist, pid = scene_eval(o + t * d, scene)
        n_eval += 1
        if n_eval == 1 and dist < 0.0:
            st = INSIDE
            break
        if omega > 1.0 and wp.abs(dist) + d_prev < step:
            # relaxed step overshot (spheres do not overlap): back to the safe point, omega = 1
            t = t_prev + d_prev
            omega = 1.0
            step = d_prev
            continue
        if dist < eps:
            st = HIT
            break
        t_prev = t
        d_prev = dist
        step = omega * dist
        t = t + step
    if st == CAP and t >= t_far and omega <= 1.0:  # an unrelaxed last step left [near, far]
        st = MISS
        t = t_far
    t_out[tid] = t
    status[tid] = st
    iters[tid] = n_eval
    p = o + t * d
    points[tid] = p
    if st == HIT:
        normals[tid] = scene_normal(p, normal_eps, scene)
        ids[tid] = pid
