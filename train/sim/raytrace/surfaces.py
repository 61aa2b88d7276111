"""Device data of a room and the device functions every ray-tracing kernel shares: random sampling, following a
ray through glass to the first opaque surface, a surface's material at a hit, and the reflectance model.

Frames: everything is in the world frame (z up, metres). Normals called *outward* follow the faces' winding
(counter-clockwise seen from outside); *facing* normals are flipped towards the ray's origin.

Glass (a material with opacity ``o < 1``)
    A ray meeting glass goes on through it: the light behind is multiplied by ``(1 - o) (1 - F)`` and by the
    glass colour normalised to its brightest channel (the tint); the glass adds the reflection ``F`` of the
    ambient light (Schlick's Fresnel term, refractive index 1.5) and a haze, ``o`` times its colour lit by the
    ambient light. After ``glass_layers`` glass surfaces the next one counts as opaque.

Emitters (emission ``e > 0``) shine with radiance ``e`` times their colour (texture or image included) and reflect
nothing; they cast no shadow and occlude no ambient light (the outdoor view behind a window stands in the sun's
way, a lamp's shade around its bulb).

Reflectance: Lambert diffuse (``(1 - metallic) albedo / pi``) plus a GGX microfacet specular lobe (Smith-Schlick
masking, Schlick Fresnel with ``F0 = lerp(0.04, albedo, metallic)``, ``alpha = roughness^2``, roughness at least
:data:`MIN_ROUGHNESS`).
"""

from __future__ import annotations

from fruxel.kernels.wp.runtime import warp

from .textures import sample_albedo, sample_normal

wp = warp()
wp.set_module_options({"enable_backward": False})

PI = wp.constant(3.14159265358979)
MIN_ROUGHNESS = wp.constant(0.06)
RAY_EPS = wp.constant(1.0e-4)
"""Metres a ray starts off a surface (or goes on past glass), against self-intersection in float32 rooms."""
FAR = wp.constant(1.0e4)
"""Metres: a ray that meets nothing by then has left the scene."""
EMITTER_ANGLE = wp.constant(0.05)
"""Radians of the footprint that light gathered from an emitter reads its image with (a blurred view of it)."""


@wp.struct
class MaterialData:
    """One row of the material table (:data:`.scene_arrays.MATERIAL_FIELDS`)."""

    color: wp.vec3
    roughness: float
    metallic: float
    opacity: float
    emission: float
    mode: int
    albedo_layer: int
    normal_layer: int
    scale: wp.vec2
    offset: wp.vec2
    origin: wp.vec3
    axis_u: wp.vec3
    axis_v: wp.vec3
    axis_n: wp.vec3


@wp.struct
class LightData:
    """One light (:data:`.scene_arrays.LIGHT_FIELDS`)."""

    kind: int
    radiance: wp.vec3
    position: wp.vec3
    direction: wp.vec3
    cos_inner: float
    cos_outer: float
    radius: float
    shadows: int


@wp.struct
class SceneData:
    """A room on the device: the BVH of all its triangles, their materials, the lights and the texture layers.

    Besides the BVH of every triangle (``mesh``: camera rays, which see glass and lamp shades), the triangles split
    in two: ``opaque``, those that stop light (an opaque material that does not shine), and ``clear``, the rest
    (glass, emitters), whose faces ``clear_face`` maps to ``mesh``'s; ``clear_faces`` is 0 where a room has none
    (``clear`` is then no mesh). Shadow and ambient rays ask the first whether anything stops them, with one
    any-hit query, and walk only the few faces of the second."""

    mesh: wp.uint64
    opaque: wp.uint64
    clear: wp.uint64
    clear_face: wp.array(dtype=wp.int32)
    clear_faces: int
    face_material: wp.array(dtype=wp.int32)
    corner_normals: wp.array(dtype=wp.vec3)
    materials: wp.array(dtype=MaterialData)
    lights: wp.array(dtype=LightData)
    albedo_texels: wp.array(dtype=wp.vec4ub)
    normal_texels: wp.array(dtype=wp.vec4ub)
    srgb: wp.array(dtype=wp.float32)
    layer_size: int
    levels: int
    glass_layers: int
    sky: wp.vec3
    portals: wp.array(dtype=wp.int32)
    portal_cdf: wp.array(dtype=wp.float32)
    portal_area: float
    portal_radiance: wp.array(dtype=wp.vec3)


@wp.struct
class Hit:
    """What a ray found: ``kind`` 0 nothing opaque (it left the scene), 1 an opaque surface; ``glass``: the glass
    surfaces it passed."""

    kind: int
    face: int
    u: float
    v: float
    t: float
    pos: wp.vec3
    outward: wp.vec3
    material: int
    through: wp.vec3
    front: wp.vec3
    glass: int


@wp.struct
class Surface:
    """A surface point's material: linear albedo, facing shading and geometric normals, roughness, metalness,
    emitted radiance (``emitter`` 1: it only emits)."""

    albedo: wp.vec3
    normal: wp.vec3
    geometric: wp.vec3
    roughness: float
    metallic: float
    emitted: wp.vec3
    emitter: int


# ---------------------------------------------------------------------------------------------------- sampling
@wp.func
def fract(x: float) -> float:
    return x - wp.floor(x)


@wp.func
def orthonormal_basis(n: wp.vec3) -> wp.mat33:
    """Columns ``(t, b, n)``, a right-handed frame around unit ``n`` (Duff et al. 2017)."""
    s = wp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (s + n[2])
    b = n[0] * n[1] * a
    t = wp.vec3(1.0 + s * n[0] * n[0] * a, s * b, -s * n[0])
    bb = wp.vec3(b, s + n[1] * n[1] * a, -n[1])
    return wp.matrix_from_cols(t, bb, n)


@wp.func
def cosine_direction(n: wp.vec3, r1: float, r2: float) -> wp.vec3:
    """A direction about unit ``n`` with density ``cos / pi`` from two uniform numbers."""
    phi = 2.0 * PI * r1
    s = wp.sqrt(r2)
    local = wp.vec3(s * wp.cos(phi), s * wp.sin(phi), wp.sqrt(wp.max(0.0, 1.0 - r2)))
    return orthonormal_basis(n) * local


@wp.func
def sphere_direction(r1: float, r2: float) -> wp.vec3:
    """A uniform unit vector from two uniform numbers."""
    z = 1.0 - 2.0 * r2
    s = wp.sqrt(wp.max(0.0, 1.0 - z * z))
    phi = 2.0 * PI * r1
    return wp.vec3(s * wp.cos(phi), s * wp.sin(phi), z)


@wp.func
def cone_direction(axis: wp.vec3, cos_max: float, r1: float, r2: float) -> wp.vec3:
    """A uniform direction within the cone of half-angle ``acos(cos_max)`` about unit ``axis``."""
    c = 1.0 - r2 * (1.0 - cos_max)
    s = wp.sqrt(wp.max(0.0, 1.0 - c * c))
    phi = 2.0 * PI * r1
    return orthonormal_basis(axis) * wp.vec3(s * wp.cos(phi), s * wp.sin(phi), c)


R2_1 = wp.constant(0.7548776662466927)
R2_2 = wp.constant(0.5698402909980532)
"""The R2 sequence's two steps (Roberts 2018), the ``alpha`` of :func:`stratified` for a pair of numbers that
spread evenly over the unit square (pixel positions, light points, ray directions)."""


@wp.func
def stratified(rotation: float, k: int, alpha: float) -> float:
    """Sample ``k`` of a pixel's additive recurrence (``alpha`` irrational), rotated by a per-pixel random
    offset (Cranley-Patterson): the samples of a pixel spread evenly, and differ between pixels."""
    return fract(rotation + float(k) * alpha)


# ---------------------------------------------------------------------------------------------------- reflectance
@wp.func
def schlick(f0: float, cos_theta: float) -> float:
    c = wp.clamp(1.0 - cos_theta, 0.0, 1.0)
    c2 = c * c
    return f0 + (1.0 - f0) * c2 * c2 * c


@wp.func
def specular_f0(albedo: wp.vec3, metallic: float) -> wp.vec3:
    return (1.0 - metallic) * wp.vec3(0.04, 0.04, 0.04) + metallic * albedo


@wp.func
def ggx_specular(n: wp.vec3, v: wp.vec3, wi: wp.vec3, alpha: float, f0: wp.vec3) -> wp.vec3:
    """The GGX specular BRDF (per steradian) for unit normal ``n``, view ``v`` and light ``wi`` directions."""
    n_l = wp.dot(n, wi)
    n_v = wp.max(wp.dot(n, v), 1.0e-4)
    if n_l <= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    h = wp.normalize(v + wi)
    n_h = wp.max(wp.dot(n, h), 0.0)
    v_h = wp.max(wp.dot(v, h), 0.0)
    a2 = alpha * alpha
    d = n_h * n_h * (a2 - 1.0) + 1.0
    distribution = a2 / (PI * d * d)
    k = 0.5 * alpha
    masking = n_v / (n_v * (1.0 - k) + k) * n_l / (n_l * (1.0 - k) + k)
    c = wp.clamp(1.0 - v_h, 0.0, 1.0)
    c5 = c * c * c * c * c
    fresnel = f0 + (wp.vec3(1.0, 1.0, 1.0) - f0) * c5
    return fresnel * (distribution * masking / (4.0 * n_v * n_l))


@wp.func
def ambient_specular(f0: wp.vec3, n_v: float, roughness: float) -> wp.vec3:
    """Share of a uniform surrounding radiance that the specular lobe reflects (Schlick's Fresnel averaged over
    the lobe, the usual roughness-aware fit)."""
    c = wp.clamp(1.0 - n_v, 0.0, 1.0)
    c5 = c * c * c * c * c
    top = wp.max(1.0 - roughness, f0[0])
    grazing = wp.vec3(wp.max(top, f0[0]), wp.max(top, f0[1]), wp.max(top, f0[2]))
    return (f0 + (grazing - f0) * c5) * (1.0 - 0.5 * roughness)


# ---------------------------------------------------------------------------------------------------- rays
@wp.func
def glass_tint(color: wp.vec3) -> wp.vec3:
    m = wp.max(wp.max(color[0], color[1]), wp.max(color[2], 1.0e-3))
    return color / m


@wp.func
def trace(scene: SceneData, origin: wp.vec3, d: wp.vec3, ambient: wp.vec3) -> Hit:
    """Follow the unit ray ``origin + t d`` through glass to its first opaque surface (module docstring).

    ``ambient``: the radiance of the room's ambient light (what glass reflects). ``Hit.front`` gathers what the
    glass adds and, on a miss, the sky; ``Hit.through`` what it lets through; ``Hit.t`` is the distance from
    ``origin``.
    """
    h = Hit()
    h.kind = 0
    h.face = -1
    h.material = -1
    h.through = wp.vec3(1.0, 1.0, 1.0)
    h.front = wp.vec3(0.0, 0.0, 0.0)
    h.t = FAR
    h.glass = 0
    t0 = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    for layer in range(scene.glass_layers + 1):
        q = wp.mesh_query_ray(scene.mesh, origin + t0 * d, d, FAR - t0)
        if not q.result:
            h.front = h.front + wp.cw_mul(h.through, scene.sky)
            return h
        m = scene.face_material[q.face]
        mat = scene.materials[m]
        if mat.opacity < 1.0 and layer < scene.glass_layers:
            f = schlick(0.04, wp.abs(wp.dot(q.normal, d)))
            seen = mat.opacity * mat.color + (1.0 - mat.opacity) * f * wp.vec3(1.0, 1.0, 1.0)
            h.front = h.front + wp.cw_mul(h.through, wp.cw_mul(seen, ambient))
            h.through = wp.cw_mul(h.through, glass_tint(mat.color)) * ((1.0 - mat.opacity) * (1.0 - f))
            h.glass = h.glass + 1
            t0 = t0 + q.t + RAY_EPS
            continue
        h.kind = 1
        h.face = q.face
        h.u = q.u
        h.v = q.v
        h.t = t0 + q.t
        h.pos = origin + h.t * d
        h.outward = q.normal
        h.material = m
        return h
    return h


@wp.func
def transmittance(scene: SceneData, origin: wp.vec3, d: wp.vec3, distance: float) -> wp.vec3:
    """What reaches ``origin`` from ``distance`` along unit ``d``: 0 behind an opaque surface, the tint of the glass
    in between otherwise (0 past more than ``glass_layers`` panes); emitters let light through."""
    if wp.mesh_query_ray_anyhit(scene.opaque, origin, d, distance):
        return wp.vec3(0.0, 0.0, 0.0)
    through = wp.vec3(1.0, 1.0, 1.0)
    if scene.clear_faces == 0:
        return through
    t0 = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    panes = int(0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    for _ in range(scene.glass_layers + 4):  # the panes allowed and a lamp's shade, front and back
        if t0 >= distance:
            return through
        q = wp.mesh_query_ray(scene.clear, origin + t0 * d, d, distance - t0)
        if not q.result:
            return through
        mat = scene.materials[scene.face_material[scene.clear_face[q.face]]]
        if mat.emission <= 0.0:
            if panes >= scene.glass_layers:
                return wp.vec3(0.0, 0.0, 0.0)
            f = schlick(0.04, wp.abs(wp.dot(q.normal, d)))
            through = wp.cw_mul(through, glass_tint(mat.color)) * ((1.0 - mat.opacity) * (1.0 - f))
            panes = panes + 1
        t0 = t0 + q.t + RAY_EPS
    return through


@wp.func
def open_distance(scene: SceneData, origin: wp.vec3, d: wp.vec3, distance: float) -> float:
    """How far unit ray ``origin + t d`` goes before an opaque surface that does not shine, at most ``distance``
    (glass and emitters do not stop it: ambient light comes through windows and past lamp shades)."""
    q = wp.mesh_query_ray(scene.opaque, origin, d, distance)
    if q.result:
        return q.t
    return distance


# ---------------------------------------------------------------------------------------------------- surfaces
@wp.func
def box_uv(p: wp.vec3, outward: wp.vec3, scale: wp.vec2, offset: wp.vec2) -> wp.vec2:
    """Texture coordinates (tiles) of world point ``p`` on a face with this outward normal (box projection of
    :mod:`.scene_arrays`)."""
    ax = wp.abs(outward[0])
    ay = wp.abs(outward[1])
    az = wp.abs(outward[2])
    u = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    v = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    if ax >= ay and ax >= az:
        u = wp.sign(outward[0]) * p[1]
        v = p[2]
    elif ay >= az:
        u = -wp.sign(outward[1]) * p[0]
        v = p[2]
    else:
        u = wp.sign(outward[2]) * p[0]
        v = p[1]
    return wp.vec2(u * scale[0] + offset[0], v * scale[1] + offset[1])


@wp.func
def box_tangent(outward: wp.vec3) -> wp.vec3:
    """World direction of increasing u of :func:`box_uv`."""
    ax = wp.abs(outward[0])
    ay = wp.abs(outward[1])
    az = wp.abs(outward[2])
    if ax >= ay and ax >= az:
        return wp.vec3(0.0, wp.sign(outward[0]), 0.0)
    if ay >= az:
        return wp.vec3(-wp.sign(outward[1]), 0.0, 0.0)
    return wp.vec3(wp.sign(outward[2]), 0.0, 0.0)


@wp.func
def smooth_normal(scene: SceneData, face: int, u: float, v: float) -> wp.vec3:
    """Outward shading normal interpolated from the face's corner normals (barycentrics ``u, v, 1 - u - v``)."""
    n = (u * scene.corner_normals[3 * face] + v * scene.corner_normals[3 * face + 1]
         + (1.0 - u - v) * scene.corner_normals[3 * face + 2])
    return wp.normalize(n)


@wp.func
def surface_at(scene: SceneData, hit: Hit, d: wp.vec3, pixel_angle: float) -> Surface:
    """The material of an opaque hit seen along unit ``d``; ``pixel_angle`` (radians) sizes the pixel's footprint
    there, which picks the texture's mip level."""
    mat = scene.materials[hit.material]
    s = Surface()
    s.roughness = wp.max(mat.roughness, MIN_ROUGHNESS)
    s.metallic = mat.metallic
    s.emitter = 0
    s.emitted = wp.vec3(0.0, 0.0, 0.0)
    facing = wp.where(wp.dot(hit.outward, d) > 0.0, -1.0, 1.0)
    s.geometric = facing * hit.outward
    n = smooth_normal(scene, hit.face, hit.u, hit.v)
    cos_view = wp.max(wp.abs(wp.dot(hit.outward, d)), 0.02)
    footprint = hit.t * pixel_angle / wp.sqrt(cos_view)
    albedo = mat.color
    size = float(scene.layer_size)
    if mat.mode == 1:
        uv = box_uv(hit.pos, hit.outward, mat.scale, mat.offset)
        lod = wp.log2(wp.max(footprint * wp.max(mat.scale[0], mat.scale[1]) * size, 1.0e-6))
        albedo = wp.cw_mul(albedo, sample_albedo(scene.albedo_texels, scene.srgb, mat.albedo_layer,
                                                 scene.layer_size, scene.levels, uv, lod, 1))
        tn = sample_normal(scene.normal_texels, scene.srgb, mat.normal_layer, scene.layer_size, scene.levels, uv, lod)
        t = box_tangent(hit.outward)
        t = wp.normalize(t - wp.dot(t, n) * n)
        b = wp.cross(n, t)
        n = wp.normalize(tn[0] * t + tn[1] * b + tn[2] * n)
    elif mat.mode == 2:
        rel = hit.pos - mat.origin
        su = wp.dot(rel, mat.axis_u) * mat.scale[0]
        if wp.dot(d, mat.axis_n) > 0.0:
            su = 1.0 - su
        uv = wp.vec2(su, wp.dot(rel, mat.axis_v) * mat.scale[1])
        lod = wp.log2(wp.max(footprint * wp.max(mat.scale[0], mat.scale[1]) * size, 1.0e-6))
        albedo = wp.cw_mul(albedo, sample_albedo(scene.albedo_texels, scene.srgb, mat.albedo_layer,
                                                 scene.layer_size, scene.levels, uv, lod, 0))
    n = facing * n
    if wp.dot(n, -d) < 0.02:
        # A normal bent away from the viewer (normal map, smoothing at a silhouette) would show the back.
        n = wp.normalize(n + (0.02 - wp.dot(n, -d)) * (-d))
    s.normal = n
    if mat.emission > 0.0:
        s.emitter = 1
        s.emitted = mat.emission * albedo
    s.albedo = wp.min(albedo, wp.vec3(0.95, 0.95, 0.95))
    return s


@wp.func
def seen_light(scene: SceneData, hit: Hit, d: wp.vec3) -> wp.vec3:
    """The radiance a ray brings from what shines by itself: the emitter it ended on (its image blurred), or the
    sky, with what the glass on the way adds; 0 when it ended on a surface that does not shine."""
    if hit.kind == 0:
        return hit.front
    s = surface_at(scene, hit, d, EMITTER_ANGLE)
    if s.emitter == 0:
        return wp.vec3(0.0, 0.0, 0.0)
    return hit.front + wp.cw_mul(hit.through, s.emitted)
