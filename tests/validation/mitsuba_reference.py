#!/usr/bin/env python3
"""Independent Mitsuba 3 reference for translux's radiosity.

Why this exists
---------------
translux computes radiance on the surfaces of translucent scenes with its own
radiosity / subsurface machinery.  This script renders the *same* quantity with
a general-purpose, widely used path tracer (Mitsuba 3's ``path`` / ``volpath``
integrators) so that tests and benchmarks can compare against something that
shares no code and no approximations with translux.  Nothing in this file is
derived from translux code; it only reads the scene description below.

Usage
-----
    python3 tests/validation/mitsuba_reference.py IN.json OUT.json
    python3 tests/validation/mitsuba_reference.py --self-test

Exit codes: 0 success, 1 self-test failure, 2 bad input / usage,
3 Mitsuba (or the LLVM library its CPU backend needs) is not available.

Input (IN.json)
---------------
    {
      "objects": [
        {"name": "floor",
         "positions": [[x, y, z], ...],     # metres
         "indices":   [[i, j, k], ...],     # triangles, counter-clockwise seen from
                                            # the front: normal = (b-a) x (c-a)
         "material":
             {"type": "diffuse", "albedo": [r, g, b]}
                 # Lambertian.  One-sided, as Mitsuba's `diffuse` is: black seen
                 # from behind.  Optional "two_sided": true wraps it in `twosided`.
           | {"type": "emitter", "radiance": [r, g, b]}
                 # one-sided Lambertian emitter (W m^-2 sr^-1) on the front side,
                 # black (albedo 0) otherwise.
           | {"type": "volume", "sigma_a": [r, g, b], "sigma_s": [r, g, b],
              "g": 0.0, "eta": 1.3}
                 # closed mesh (outward normals) holding a homogeneous medium
                 # (coefficients per metre) inside a smooth dielectric boundary of
                 # relative IOR eta (eta == 1: index-matched `null` boundary).
        }, ...
      ],
      "lights": [
        {"type": "point", "position": [x, y, z], "intensity": [r, g, b]},          # W/sr
        {"type": "spot", "position": [...], "direction": [...], "intensity": [...],
         "inner_deg": a, "outer_deg": b},
             # Mitsuba `spot`: full intensity inside inner_deg (beam_width), falling
             # off *linearly in angle* to zero at outer_deg (cutoff_angle).
        {"type": "directional", "direction": [dx, dy, dz], "irradiance": [r, g, b]}
             # direction = where the light travels; irradiance on a surface facing it
      ],
      "queries": {"points": [[x, y, z], ...], "normals": [[nx, ny, nz], ...]},
      "measure": "normal", # "normal": radiance leaving along the normal; "exitance":
                           # its cosine-weighted mean over the hemisphere (exitance / pi,
                           # what a Lambertian radiosity patch carries)
      "spp": 256,          # samples per query point (>= 2, for the standard error)
      "max_depth": 64,     # Mitsuba max_depth (-1 = unbounded)
      "seed": 0,
      "threads": 0         # 0 = Dr.Jit default, else the size of its thread pool
    }
Optional keys: "rr_depth" (Mitsuba's Russian-roulette start depth, default 5),
"eps" (the query ray offset in metres; default 1e-4 x the scene's bounding-box
diagonal) and "integrator" ("path", "volpath" or "volpathmis"; by default "path"
without volumes, "volpathmis" when a volume's extinction differs between channels,
"volpath" otherwise).

Output (OUT.json)
-----------------
    {"radiance":  [[r, g, b], ...],  # mean outgoing radiance at each query point
                                     # toward its normal (W m^-2 sr^-1)
     "std_error": [[r, g, b], ...],  # standard error of that mean, per channel,
                                     # from the per-sample variance
     "spp": 256, "seconds": 1.23,    # seconds = scene build + rendering (no import,
                                     # no JSON I/O); JIT compilation is included
     "variant": "llvm_ad_rgb", "integrator": "path" | "volpath" | "volpathmis",
     "mitsuba_version": "3.9.1",
     # diagnostics:
     "build_seconds": ..., "render_seconds": ..., "threads": ..., "eps": ...,
     "scale": 1.0,                   # factor the scene was scaled by (volumes; see
                                     # _medium_scale)
     "nonfinite_samples": 0,         # samples that came back NaN/inf (counted as 0)
     "suspect_queries": [i, ...]}    # queries whose ray did not hit a front face at
                                     # the query point (see check_queries)

How a query is measured: a ray starts at p + eps*n and travels along -n, so it
hits the surface at p from the front; the radiance Mitsuba returns along it is
the surface's outgoing radiance toward +n (emission included).  For Lambertian
surfaces that is the view-independent radiance; for a volume's dielectric
boundary it is the radiance leaving along the normal.

Known limitation of the reference: with a dielectric (eta != 1) boundary, light
from point, spot and directional lights can only reach the medium through a
refraction, which a path tracer cannot connect to a delta light (a caustic).
Such volumes render (nearly) black under delta lights; use eta = 1 or area
emitters for them.  The script warns on stderr when that combination occurs.
"""

import json
import math
import os
import sys
import time

VARIANT = "llvm_ad_rgb"
LIBLLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
INSTALL_HINT = ("mitsuba_reference: Mitsuba 3 with its LLVM backend is required: "
                "run `pip install mitsuba` and `apt-get install libllvm19`")

# Rays per integrator call.  Bounded so that memory stays modest on large queries.
MAX_WAVEFRONT = 1 << 20

mi = None
dr = None


class InputError(Exception):
    """The scene description is malformed."""


def load_mitsuba(threads=0):
    """Import Mitsuba and select the CPU variant, or exit with code 3."""
    global mi, dr
    if os.path.exists(LIBLLVM):
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", LIBLLVM)
    try:
        import drjit
        import mitsuba
        mitsuba.set_variant(VARIANT)
    except Exception as exc:  # ImportError, or the variant cannot find libLLVM
        print(f"{INSTALL_HINT} ({type(exc).__name__}: {exc})".replace("\n", " "),
              file=sys.stderr)
        sys.exit(3)
    mi, dr = mitsuba, drjit
    if threads and threads > 0:
        dr.set_thread_count(int(threads))


# ----------------------------------------------------------------------------
# Scene construction
# ----------------------------------------------------------------------------

def _vec3(value, what):
    try:
        v = [float(c) for c in value]
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected three numbers, got {value!r}")
    if len(v) != 3 or not all(math.isfinite(c) for c in v):
        raise InputError(f"{what}: expected three finite numbers, got {value!r}")
    return v


def _rgb(value):
    return {"type": "rgb", "value": value}


def _mesh(name, positions, indices, props):
    """A flat-shaded triangle mesh filled through mi.traverse."""
    mesh = mi.Mesh(name, len(positions), len(indices), props=props,
                   has_vertex_normals=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float([c for p in positions for c in p])
    params["faces"] = mi.UInt32([c for t in indices for c in t])
    params.update()
    return mesh


def _object(index, obj):
    name = str(obj.get("name", f"object{index}"))
    what = f"objects[{index}] ({name})"
    positions = [_vec3(p, f"{what}.positions") for p in obj.get("positions", [])]
    indices = []
    for t in obj.get("indices", []):
        if len(t) != 3 or not all(0 <= int(i) < len(positions) for i in t):
            raise InputError(f"{what}.indices: bad triangle {t!r}")
        indices.append([int(i) for i in t])
    if not positions or not indices:
        raise InputError(f"{what}: needs positions and indices")

    mat = obj.get("material") or {}
    kind = mat.get("type")
    props = mi.Properties()
    if kind == "diffuse":
        albedo = _vec3(mat.get("albedo"), f"{what}.material.albedo")
        if not all(0.0 <= a <= 1.0 for a in albedo):
            raise InputError(f"{what}.material.albedo must lie in [0, 1]")
        bsdf = {"type": "diffuse", "reflectance": _rgb(albedo)}
        if mat.get("two_sided", False):
            bsdf = {"type": "twosided", "material": bsdf}
        props["bsdf"] = mi.load_dict(bsdf)
    elif kind == "emitter":
        radiance = _vec3(mat.get("radiance"), f"{what}.material.radiance")
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": _rgb([0.0] * 3)})
        props["emitter"] = mi.load_dict({"type": "area", "radiance": _rgb(radiance)})
    elif kind == "volume":
        sa = _vec3(mat.get("sigma_a"), f"{what}.material.sigma_a")
        ss = _vec3(mat.get("sigma_s"), f"{what}.material.sigma_s")
        if min(sa + ss) < 0.0:
            raise InputError(f"{what}.material: negative coefficient")
        g = float(mat.get("g", 0.0))
        eta = float(mat.get("eta", 1.0))
        st = [a + s for a, s in zip(sa, ss)]
        albedo = [s / t if t > 0.0 else 0.0 for s, t in zip(ss, st)]
        # Reflectance-typed RGB textures must lie in [0, 1]: store sigma_t
        # normalised, with its maximum in the medium's `scale`.
        scale = max(st) if max(st) > 0.0 else 1.0
        phase = {"type": "hg", "g": g} if g != 0.0 else {"type": "isotropic"}
        props["interior"] = mi.load_dict({
            "type": "homogeneous",
            "sigma_t": _rgb([t / scale for t in st]),
            "scale": scale,
            "albedo": _rgb(albedo),
            "phase": phase,
        })
        if eta == 1.0:
            props["bsdf"] = mi.load_dict({"type": "null"})
        else:
            props["bsdf"] = mi.load_dict({"type": "dielectric",
                                          "int_ior": eta, "ext_ior": 1.0})
    else:
        raise InputError(f"{what}.material.type must be diffuse, emitter or volume, "
                         f"got {kind!r}")
    return name, _mesh(name, positions, indices, props), positions, kind


def _light(index, light):
    what = f"lights[{index}]"
    kind = light.get("type")
    if kind == "point":
        return {"type": "point",
                "position": _vec3(light.get("position"), f"{what}.position"),
                "intensity": _rgb(_vec3(light.get("intensity"), f"{what}.intensity"))}
    if kind == "directional":
        d = _vec3(light.get("direction"), f"{what}.direction")
        if math.hypot(*d) == 0.0:
            raise InputError(f"{what}.direction is zero")
        return {"type": "directional", "direction": d,
                "irradiance": _rgb(_vec3(light.get("irradiance"), f"{what}.irradiance"))}
    if kind == "spot":
        p = _vec3(light.get("position"), f"{what}.position")
        d = _vec3(light.get("direction"), f"{what}.direction")
        norm = math.hypot(*d)
        if norm == 0.0:
            raise InputError(f"{what}.direction is zero")
        d = [c / norm for c in d]
        outer = float(light.get("outer_deg", 20.0))
        inner = float(light.get("inner_deg", outer * 0.75))
        if not 0.0 <= inner <= outer:
            raise InputError(f"{what}: need 0 <= inner_deg <= outer_deg")
        up = [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0]
        to_world = mi.ScalarTransform4f().look_at(
            origin=p, target=[p[i] + d[i] for i in range(3)], up=up)
        return {"type": "spot", "to_world": to_world,
                "intensity": _rgb(_vec3(light.get("intensity"), f"{what}.intensity")),
                "cutoff_angle": outer, "beam_width": inner}
    raise InputError(f"{what}.type must be point, spot or directional, got {kind!r}")


def _chromatic(obj):
    """Whether object `obj` is a volume whose extinction differs between channels."""
    mat = obj.get("material") or {}
    if mat.get("type") != "volume":
        return False
    st = [a + b for a, b in zip(mat.get("sigma_a", [0] * 3), mat.get("sigma_s", [0] * 3))]
    return max(st) - min(st) > 1e-6 * max(max(st), 1e-30)


def build_scene(desc):
    """Return (scene, integrator name, all vertex positions)."""
    scene_dict = {"type": "scene"}
    kinds, verts = set(), []
    for i, obj in enumerate(desc.get("objects", [])):
        name, mesh, positions, kind = _object(i, obj)
        key = f"obj{i}_{''.join(c if c.isalnum() else '_' for c in name)}"
        scene_dict[key] = mesh
        kinds.add(kind)
        verts.extend(positions)
    delta_lights = 0
    for i, light in enumerate(desc.get("lights", [])):
        scene_dict[f"light{i}"] = _light(i, light)
        delta_lights += 1
    if not verts:
        raise InputError("the scene has no objects")

    # volpath samples free flights in one colour channel and weights the others by the
    # ratio of their transmittances, which its documentation says is no good strategy for
    # an extinction that varies with the channel: over a few hundred scattering events
    # those weights are heavy-tailed, and a finite sample of them comes out low (on a
    # 16 mm cube, sigma_t 0.81 / 0.62 / 0.54 per mm, the far face's red 16% below three
    # grey runs at 65,536 paths, beyond its reported standard error). volpathmis combines
    # the channels by spectral MIS and agrees with the grey runs; it is used whenever a
    # medium's sigma_t differs between channels ("integrator" in IN.json overrides).
    integrator = "path"
    if "volume" in kinds:
        integrator = "volpathmis" if any(_chromatic(o) for o in desc["objects"]) else "volpath"
    integrator = str(desc.get("integrator", integrator))
    if integrator not in ("path", "volpath", "volpathmis"):
        raise InputError(f"integrator must be path, volpath or volpathmis, got {integrator!r}")
    scene_dict["integrator"] = {
        "type": integrator,
        "max_depth": int(desc.get("max_depth", 64)),
        "rr_depth": int(desc.get("rr_depth", 5)),
        "hide_emitters": False,
    }
    if delta_lights and any(
            (o.get("material") or {}).get("type") == "volume"
            and float(o["material"].get("eta", 1.0)) != 1.0
            for o in desc.get("objects", [])):
        print("mitsuba_reference: warning: volumes with a dielectric boundary "
              "(eta != 1) receive no light from point/spot/directional lights in a "
              "path tracer (caustic paths); their radiance will be underestimated",
              file=sys.stderr)
    return mi.load_dict(scene_dict), integrator, verts


# ----------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------

def _seed_for(seed, pass_index):
    """A 32-bit seed per (user seed, pass), so passes draw independent streams."""
    x = (int(seed) * 0x9E3779B1 + pass_index * 0x85EBCA77 + 0x27D4EB2F) & 0xFFFFFFFF
    x ^= x >> 15
    x = (x * 0x2C1B3C6D) & 0xFFFFFFFF
    x ^= x >> 12
    return x


def check_queries(scene, origins, dirs, eps):
    """Indices of queries whose ray does not hit a front face at distance ~eps."""
    n = len(origins)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float([o[i] for o in origins]) for i in range(3)]),
                   mi.Vector3f(*[mi.Float([d[i] for d in dirs]) for i in range(3)]))
    si = scene.ray_intersect(ray)
    ok = si.is_valid() & (dr.abs(si.t - eps) <= 0.5 * eps) & (dr.dot(si.n, ray.d) < 0.0)
    ok = list(ok)
    return [i for i in range(n) if not ok[i]]


# The largest coordinate of a scene with volumes after `_scaled`.
MEDIUM_EXTENT = 1000.0


def _medium_scale(desc):
    """The factor a scene with volumes is scaled by before Mitsuba sees it (1 without).

    Mitsuba offsets every ray it spawns at a surface by about (1 + max|p|) x 8.9e-5
    scene units (float32), so a ray entering a null or dielectric boundary skips that
    layer of the medium behind it. In a scene in metres that is ~0.1 mm whatever its
    size: on a half-space of mean free path 1.2 mm lit at normal incidence, single
    scattering came out 8% low and the total 2.3% high at albedo 0.988 (the source
    function grows with depth there) against Chandrasekhar's H function; at a free path
    of 0.12 mm, 57% low. Scaled so that its largest coordinate is 1000, the layer is
    ~9e-5 of the scene's half-size, the floor float32 allows (0.7 um on a 16 mm cube;
    still 1.4% of a 1.25 mm free path on a 400 mm slab). Radiance is unchanged by a
    uniform scaling when coefficients are divided by the factor and point and spot
    intensities multiplied by its square, which `_scaled` does.
    """
    if not any((o.get("material") or {}).get("type") == "volume"
               for o in desc.get("objects", [])):
        return 1.0
    extent = max((abs(c) for o in desc.get("objects", []) for p in o.get("positions", [])
                  for c in p), default=0.0)
    return MEDIUM_EXTENT / extent if extent > 0.0 and math.isfinite(extent) else 1.0


def _scaled(desc, k):
    """`desc` with lengths multiplied by k (see `_medium_scale`)."""
    if k == 1.0:
        return desc
    out = dict(desc)
    objects = []
    for o in desc.get("objects", []):
        o = dict(o)
        o["positions"] = [[k * float(c) for c in p] for p in o.get("positions", [])]
        mat = dict(o.get("material") or {})
        if mat.get("type") == "volume":
            for key in ("sigma_a", "sigma_s"):
                if key in mat:
                    mat[key] = [float(c) / k for c in mat[key]]
        o["material"] = mat
        objects.append(o)
    out["objects"] = objects
    lights = []
    for light in desc.get("lights", []):
        light = dict(light)
        if light.get("type") in ("point", "spot"):
            if "position" in light:
                light["position"] = [k * float(c) for c in light["position"]]
            if "intensity" in light:
                light["intensity"] = [k * k * float(c) for c in light["intensity"]]
        lights.append(light)
    out["lights"] = lights
    q = dict(desc.get("queries") or {})
    q["points"] = [[k * float(c) for c in p] for p in q.get("points", [])]
    out["queries"] = q
    if "eps" in desc:
        out["eps"] = k * float(desc["eps"])
    return out


def render(desc):
    """Render the queries of a scene description; return the output dict."""
    try:
        scale = _medium_scale(desc)
        desc = _scaled(desc, scale)
    except (TypeError, ValueError, AttributeError):
        # Malformed input: left as it is, for the checks below to name the field.
        scale = 1.0
    spp = int(desc.get("spp", 256))
    if spp < 2:
        raise InputError("spp must be at least 2 (the standard error needs two samples)")
    seed = int(desc.get("seed", 0))
    measure = desc.get("measure", "normal")
    if measure not in ("normal", "exitance"):
        raise InputError(f"measure must be normal or exitance, got {measure!r}")
    q = desc.get("queries") or {}
    points = [_vec3(p, "queries.points") for p in q.get("points", [])]
    normals = [_vec3(n, "queries.normals") for n in q.get("normals", [])]
    if len(points) != len(normals):
        raise InputError("queries.points and queries.normals differ in length")
    normals = [[c / (math.hypot(*n) or 1.0) for c in n] for n in normals]

    t0 = time.perf_counter()
    scene, integrator_name, verts = build_scene(desc)
    allp = verts + points
    lo = [min(p[i] for p in allp) for i in range(3)]
    hi = [max(p[i] for p in allp) for i in range(3)]
    diag = math.dist(lo, hi)
    eps = float(desc.get("eps", 1e-4 * diag))
    t1 = time.perf_counter()

    n_pts = len(points)
    sums = [[0.0] * 3 for _ in range(n_pts)]
    sqs = [[0.0] * 3 for _ in range(n_pts)]
    nonfinite = 0
    suspect = []
    if n_pts:
        origins = [[p[i] + eps * n[i] for i in range(3)] for p, n in zip(points, normals)]
        dirs = [[-c for c in n] for n in normals]
        suspect = check_queries(scene, origins, dirs, eps)
        ox, oy, oz = (mi.Float([o[i] for o in origins]) for i in range(3))
        dx, dy, dz = (mi.Float([d[i] for d in dirs]) for i in range(3))
        px, py, pz = (mi.Float([p[i] for p in points]) for i in range(3))

        integrator = scene.integrator()
        sampler = mi.load_dict({"type": "independent"})
        spp_pass = min(spp, MAX_WAVEFRONT)
        pts_per_chunk = max(1, MAX_WAVEFRONT // spp_pass)
        pass_index = 0
        for p0 in range(0, n_pts, pts_per_chunk):
            p1 = min(n_pts, p0 + pts_per_chunk)
            for s0 in range(0, spp, spp_pass):
                ns = min(spp, s0 + spp_pass) - s0
                count = (p1 - p0) * ns
                # Opaque offsets, so that every chunk reuses the same compiled kernel.
                idx = (dr.opaque(mi.UInt32, p0)
                       + dr.arange(mi.UInt32, count) // dr.opaque(mi.UInt32, ns))
                ray = mi.RayDifferential3f(
                    mi.Point3f(dr.gather(mi.Float, ox, idx), dr.gather(mi.Float, oy, idx),
                               dr.gather(mi.Float, oz, idx)),
                    mi.Vector3f(dr.gather(mi.Float, dx, idx), dr.gather(mi.Float, dy, idx),
                                dr.gather(mi.Float, dz, idx)))
                sampler.seed(dr.opaque(mi.UInt32, _seed_for(seed, pass_index)), count)
                pass_index += 1
                if measure == "exitance":
                    # A cosine-weighted direction w around the normal per sample; the
                    # ray comes back along -w to the point: the mean is exitance / pi.
                    n = -ray.d
                    w = mi.Frame3f(n).to_world(
                        mi.warp.square_to_cosine_hemisphere(sampler.next_2d()))
                    p = mi.Point3f(dr.gather(mi.Float, px, idx), dr.gather(mi.Float, py, idx),
                                   dr.gather(mi.Float, pz, idx))
                    ray = mi.RayDifferential3f(p + eps * w, -w)
                value, _, _ = integrator.sample(scene, sampler, ray)
                chans = []
                bad = mi.UInt32(0)
                for c in (value.x, value.y, value.z):
                    finite = dr.isfinite(c)
                    bad += dr.select(finite, 0, 1)
                    c = mi.Float64(dr.select(finite, c, 0.0))
                    chans.append((dr.block_sum(c, ns), dr.block_sum(c * c, ns)))
                bad_total = dr.sum(bad)
                dr.eval(chans, bad_total)
                nonfinite += int(bad_total[0])
                for ch, (s, s2) in enumerate(chans):
                    for k, (a, b) in enumerate(zip(list(s), list(s2))):
                        sums[p0 + k][ch] += a
                        sqs[p0 + k][ch] += b
    t2 = time.perf_counter()

    radiance, std_error = [], []
    for s, s2 in zip(sums, sqs):
        mean = [v / spp for v in s]
        var = [max(0.0, (b - spp * m * m) / (spp - 1)) for b, m in zip(s2, mean)]
        radiance.append(mean)
        std_error.append([math.sqrt(v / spp) for v in var])
    if suspect:
        print(f"mitsuba_reference: warning: {len(suspect)} query ray(s) do not hit a "
              f"front face at their point (first: {suspect[:5]}); check the normals "
              f"and eps", file=sys.stderr)
    if nonfinite:
        print(f"mitsuba_reference: warning: {nonfinite} non-finite samples counted as 0",
              file=sys.stderr)
    return {
        "radiance": radiance,
        "std_error": std_error,
        "spp": spp,
        "seconds": t2 - t0,
        "variant": VARIANT,
        "integrator": integrator_name,
        "mitsuba_version": mi.__version__,
        "build_seconds": t1 - t0,
        "render_seconds": t2 - t1,
        "threads": dr.thread_count(),
        "eps": eps / scale,
        "scale": scale,
        "nonfinite_samples": nonfinite,
        "suspect_queries": suspect,
    }


# ----------------------------------------------------------------------------
# Self-test: closed-form checks
# ----------------------------------------------------------------------------

def _gauss_legendre(n):
    """Nodes and weights of the n-point Gauss-Legendre rule on [0, 1]."""
    nodes, weights = [], []
    for i in range(1, n + 1):
        x = math.cos(math.pi * (i - 0.25) / (n + 0.5))
        for _ in range(100):
            p0, p1 = 1.0, x
            for k in range(2, n + 1):
                p0, p1 = p1, ((2 * k - 1) * x * p1 - (k - 1) * p0) / k
            dp = n * (x * p1 - p0) / (x * x - 1.0)
            dx = p1 / dp
            x -= dx
            if abs(dx) < 1e-15:
                break
        nodes.append(0.5 * (x + 1.0))
        weights.append(1.0 / ((1.0 - x * x) * dp * dp))
    return nodes, weights


def _chandrasekhar_h(w, mu, n=64):
    """Chandrasekhar's H function of isotropic scattering at single-scattering albedo w,
    from 1/H(mu) = sqrt(1 - w) + (w/2) int_0^1 mu' H(mu') / (mu + mu') dmu', iterated
    (H(1) = 1.8501 at w = 0.9, Chandrasekhar's table 1.8505). The iteration slows down
    toward the conservative case, so w is limited to 0.999."""
    if not 0.0 <= w <= 0.999:
        raise ValueError(f"_chandrasekhar_h: w must lie in [0, 0.999], got {w}")
    x, a = _gauss_legendre(n)
    h = [1.0] * n
    root = math.sqrt(1.0 - w)

    def at(m, h):
        return 1.0 / (root + 0.5 * w * sum(ai * xi * hi / (m + xi)
                                           for xi, ai, hi in zip(x, a, h)))
    for _ in range(500):
        new = [at(m, h) for m in x]
        done = max(abs(p - q) for p, q in zip(new, h)) < 1e-12
        h = new
        if done:
            break
    return at(mu, h)


def _square(half, z=0.0):
    """Upward-facing square [-half, half]^2 at height z."""
    return ([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]],
            [[0, 1, 2], [0, 2, 3]])


def _box(lo, hi, inward):
    """Axis-aligned box as 12 triangles, normals pointing inward or outward."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
         [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]]
    # Quads wound counter-clockwise seen from outside.
    quads = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4],
             [2, 3, 7, 6], [1, 2, 6, 5], [3, 0, 4, 7]]
    tris = []
    for a, b, c, d in quads:
        tris += [[a, b, c], [a, c, d]]
    if inward:
        tris = [[a, c, b] for a, b, c in tris]
    return v, tris


def _room_queries(half, n):
    """Cell-centred n x n grid on each wall of the cube [-half, half]^3, inward normals."""
    pts, nrm = [], []
    ticks = [-half + (i + 0.5) * 2 * half / n for i in range(n)]
    for axis in range(3):
        for sign in (-1.0, 1.0):
            for u in ticks:
                for w in ticks:
                    p = [0.0, 0.0, 0.0]
                    p[axis] = sign * half
                    p[(axis + 1) % 3] = u
                    p[(axis + 2) % 3] = w
                    nn = [0.0, 0.0, 0.0]
                    nn[axis] = -sign
                    pts.append(p)
                    nrm.append(nn)
    return pts, nrm


def self_test():
    checks = []  # (name, passed)

    def report(name, got, want, tol, se=None):
        rel = abs(got - want) / abs(want) if want != 0 else abs(got)
        ok = rel <= tol
        extra = f"  (std err {se:.3g})" if se is not None else ""
        print(f"  {'ok  ' if ok else 'FAIL'} {name}: got {got:.6g}, expected {want:.6g}, "
              f"rel err {rel:.2e} (tol {tol:g}){extra}")
        checks.append(ok)

    def run(title, desc):
        t = time.perf_counter()
        out = render(desc)
        wall = time.perf_counter() - t
        n = len(desc["queries"]["points"])
        print(f"[{title}] {n} points x {desc['spp']} spp, {out['integrator']}: "
              f"render {out['render_seconds']:.2f} s, total {wall:.2f} s")
        if out["suspect_queries"] or out["nonfinite_samples"]:
            print(f"  FAIL suspect queries {out['suspect_queries'][:5]}, "
                  f"non-finite samples {out['nonfinite_samples']}")
            checks.append(False)
        return out

    start = time.perf_counter()
    floor_v, floor_t = _square(50.0)
    rho = [0.6, 0.4, 0.2]
    floor = {"name": "floor", "positions": floor_v, "indices": floor_t,
             "material": {"type": "diffuse", "albedo": rho}}

    # 1. Point light at height h: L = rho I cos(theta) / (pi r^2), measured as the radiance
    # along the normal and (1b) as exitance / pi over the hemisphere (Lambertian: equal).
    h, intensity = 2.0, [10.0, 20.0, 5.0]
    ds = [0.0, 0.5, 1.0, 2.0, 4.0]
    for title, extra in (("1 point light over a diffuse square", {"spp": 64, "seed": 1}),
                         ("1b point light over a diffuse square, measured as exitance",
                          {"measure": "exitance", "spp": 256, "seed": 11})):
        out = run(title, {
            "objects": [floor],
            "lights": [{"type": "point", "position": [0, 0, h], "intensity": intensity}],
            "queries": {"points": [[d, 0, 0] for d in ds], "normals": [[0, 0, 1]] * len(ds)},
            "max_depth": 4, **extra})
        for d, L, se in zip(ds, out["radiance"], out["std_error"]):
            r2 = h * h + d * d
            cos = h / math.sqrt(r2)
            for c in range(3):
                report(f"d={d:g} ch{c}", L[c], rho[c] * intensity[c] * cos / (math.pi * r2),
                       0.01, se[c])

    # 2. Directional light: L = rho E cos(theta) / pi.
    irr = [3.0, 2.0, 1.0]
    for theta in (0.0, 60.0):
        t = math.radians(theta)
        out = run(f"2 directional light at {theta:g} deg onto the square", {
            "objects": [floor],
            "lights": [{"type": "directional", "direction": [math.sin(t), 0, -math.cos(t)],
                        "irradiance": irr}],
            "queries": {"points": [[0, 0, 0], [3, -2, 0]], "normals": [[0, 0, 1]] * 2},
            "spp": 64, "max_depth": 4, "seed": 2})
        for i, (L, se) in enumerate(zip(out["radiance"], out["std_error"])):
            for c in range(3):
                report(f"point {i} ch{c}", L[c], rho[c] * irr[c] * math.cos(t) / math.pi,
                       0.01, se[c])

    # 3. Closed cube room, albedo 0.5, point light at its centre:
    #    mean radiance = rho (Phi/A) / (1 - rho) / pi,  Phi = 4 pi I.
    #    (The 12 x 12 midpoint grid over-estimates the area mean of the direct
    #    term by about 0.1 % of the answer; the tolerance is 2 %.)
    half, rho_room, i_room = 1.0, 0.5, 10.0
    room_v, room_t = _box([-half] * 3, [half] * 3, inward=True)
    pts, nrm = _room_queries(half, 12)
    out = run("3 closed cube room, point light at the centre", {
        "objects": [{"name": "room", "positions": room_v, "indices": room_t,
                     "material": {"type": "diffuse", "albedo": [rho_room] * 3}}],
        "lights": [{"type": "point", "position": [0, 0, 0], "intensity": [i_room] * 3}],
        "queries": {"points": pts, "normals": nrm},
        "spp": 256, "max_depth": -1, "seed": 3})
    area = 6 * (2 * half) ** 2
    want = rho_room * (4 * math.pi * i_room / area) / (1 - rho_room) / math.pi
    n = len(pts)
    for c in range(3):
        mean = sum(L[c] for L in out["radiance"]) / n
        se = math.sqrt(sum(s[c] ** 2 for s in out["std_error"])) / n
        report(f"wall-grid mean ch{c}", mean, want, 0.02, se)

    # 4. Spot light straight down: full intensity inside the beam, zero beyond the cutoff.
    out = run("4 spot light over the square", {
        "objects": [floor],
        "lights": [{"type": "spot", "position": [0, 0, h], "direction": [0, 0, -1],
                    "intensity": intensity, "inner_deg": 20.0, "outer_deg": 30.0}],
        "queries": {"points": [[0, 0, 0], [0.5, 0, 0], [2, 0, 0]],
                    "normals": [[0, 0, 1]] * 3},
        "spp": 16, "max_depth": 4, "seed": 4})
    for d, L in zip([0.0, 0.5], out["radiance"]):  # 0 and 14 degrees off axis
        r2 = h * h + d * d
        cos = h / math.sqrt(r2)
        report(f"inside beam d={d:g} ch0", L[0],
               rho[0] * intensity[0] * cos / (math.pi * r2), 0.01)
    outside = out["radiance"][2][0]  # 45 degrees off axis
    print(f"  {'ok  ' if outside == 0.0 else 'FAIL'} outside cutoff d=2 ch0: got {outside:g}, "
          f"expected 0")
    checks.append(outside == 0.0)

    # 5. Area emitter: its front returns its radiance; nothing else lights the scene.
    em_v, em_t = _square(0.5, z=1.0)
    le = [4.0, 2.0, 1.0]
    out = run("5 area emitter seen head-on", {
        "objects": [{"name": "lamp", "positions": em_v, "indices": em_t,
                     "material": {"type": "emitter", "radiance": le}}],
        "lights": [],
        "queries": {"points": [[0.1, 0.2, 1.0]], "normals": [[0, 0, 1]]},
        "spp": 16, "max_depth": 4, "seed": 5})
    for c in range(3):
        report(f"emitter front ch{c}", out["radiance"][0][c], le[c], 1e-4)

    # 6. Absorbing slab (eta = 1) between a directional light and the floor:
    #    L = rho E exp(-sigma_a * thickness) / pi.
    sig_a, thick = [0.5, 1.0, 2.0], 0.5
    slab_v, slab_t = _box([-20, -20, 1.0], [20, 20, 1.0 + thick], inward=False)
    grid = [[x * 0.5, y * 0.5, 0.0] for x in range(-2, 3) for y in range(-2, 3)]
    out = run("6 absorbing slab over the square, directional light", {
        "objects": [floor, {"name": "slab", "positions": slab_v, "indices": slab_t,
                            "material": {"type": "volume", "sigma_a": sig_a,
                                         "sigma_s": [0, 0, 0], "g": 0.0, "eta": 1.0}}],
        "lights": [{"type": "directional", "direction": [0, 0, -1], "irradiance": irr}],
        "queries": {"points": grid, "normals": [[0, 0, 1]] * len(grid)},
        "spp": 2048, "max_depth": 8, "seed": 6})
    n = len(grid)
    for c in range(3):
        mean = sum(L[c] for L in out["radiance"]) / n
        se = math.sqrt(sum(s[c] ** 2 for s in out["std_error"])) / n
        report(f"under slab ch{c}", mean,
               rho[c] * irr[c] * math.exp(-sig_a[c] * thick) / math.pi, 0.02, se)

    # 7. A scattering half-space (a 40 mm block, 16 free paths deep, in metres) lit at
    #    normal incidence, one albedo per channel, against Chandrasekhar: the plane
    #    albedo A = 1 - H(1) sqrt(1 - w) as exitance, and single scattering alone
    #    (max_depth 2) along the normal, L = w E / (8 pi). A ray-epsilon layer skipped
    #    behind the boundary (see _medium_scale) makes the second 8% low.
    sig_t, albedo, half = 800.0, [0.1, 0.5, 0.95], 0.02
    block_v, block_t = _box([-half] * 3, [half] * 3, inward=False)
    block = {"name": "block", "positions": block_v, "indices": block_t,
             "material": {"type": "volume", "sigma_a": [sig_t * (1 - w) for w in albedo],
                          "sigma_s": [sig_t * w for w in albedo], "g": 0.0, "eta": 1.0}}
    face = [[half, 0.002 * i, -0.003 * i] for i in range(-2, 3)]
    lit = {"objects": [block],
           "lights": [{"type": "directional", "direction": [-1, 0, 0], "irradiance": [1.0] * 3}],
           "queries": {"points": face, "normals": [[1, 0, 0]] * len(face)}}
    out = run("7 scattering half-space, exitance", {
        **lit, "measure": "exitance", "spp": 16384, "max_depth": 4096, "rr_depth": 256,
        "seed": 7})
    n = len(face)
    for c, w in enumerate(albedo):
        mean = sum(L[c] for L in out["radiance"]) / n
        se = math.sqrt(sum(e[c] ** 2 for e in out["std_error"])) / n
        report(f"plane albedo / pi, w={w:g}", mean,
               (1.0 - _chandrasekhar_h(w, 1.0) * math.sqrt(1.0 - w)) / math.pi, 0.01, se)
    out = run("7b single scattering along the normal", {
        **lit, "spp": 16384, "max_depth": 2, "seed": 8})
    for c, w in enumerate(albedo):
        mean = sum(L[c] for L in out["radiance"]) / n
        se = math.sqrt(sum(e[c] ** 2 for e in out["std_error"])) / n
        report(f"single scattering, w={w:g}", mean, w / (8.0 * math.pi), 0.015, se)

    total = time.perf_counter() - start
    failed = checks.count(False)
    print(f"self-test: {len(checks) - failed}/{len(checks)} checks passed in {total:.2f} s "
          f"(Mitsuba {mi.__version__}, {VARIANT}, {dr.thread_count()} threads)")
    return failed == 0


# ----------------------------------------------------------------------------

def main(argv):
    if len(argv) == 2 and argv[1] == "--self-test":
        load_mitsuba()
        return 0 if self_test() else 1
    if len(argv) != 3:
        print(__doc__.split("Input (IN.json)")[0].strip(), file=sys.stderr)
        return 2
    try:
        with open(argv[1]) as f:
            desc = json.load(f)
    except (OSError, ValueError) as exc:
        print(f"mitsuba_reference: cannot read {argv[1]}: {exc}", file=sys.stderr)
        return 2
    load_mitsuba(int(desc.get("threads", 0) or 0))
    try:
        out = render(desc)
    except InputError as exc:
        print(f"mitsuba_reference: bad input: {exc}", file=sys.stderr)
        return 2
    with open(argv[2], "w") as f:
        json.dump(out, f)
        f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
