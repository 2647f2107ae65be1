#!/usr/bin/env python3
"""Converged radiosity reference of the Cornell box (scenes/cornell.obj) with Mitsuba 3.

Radiosity here is the project's: B = E + rho * H in exitance units, H the irradiance,
Lambertian one-sided faces. A Lambertian surface's outgoing radiance is L = B / pi, so B is
measured as pi times radiance; for the light the emitted part comes in with it. Mitsuba's
path tracer (`scalar_rgb`, one thread, max_depth 100, no Russian roulette) does the light
transport.

- Face averages: for every OBJ face, in file order (0-based, as `f` lines appear), the
  area average of B: for each of its triangles an orthographic camera looking straight
  down at it from 0.1 mm, one sample per pixel, the samples that land on the triangle
  (found from their hit positions, an `aov`) averaged; the triangles' averages weighted by
  area.
- Probe points: B = pi L from a `radiancemeter` 0.01 mm above the point looking straight
  down at it, at points beside the blocks' bases, across the tall block's shadow on the
  back wall, and on open surfaces (`cornell_probes`).

Each value is the mean of `--runs` independent runs (new seeds), with the standard error
std / sqrt(runs). Sample counts come from a pilot so that every value reaches its target
relative standard error (`--face-target`, `--point-target`), scaled down to `--budget`.

`--check` runs the convention checks instead: furnaces (scenes/cube.obj with E 1,
rho 0.5 and 0.9: B = E / (1 - rho)) through the same face-average and point code, the
direct irradiance from the light (max_depth 2) at points against the exact point-to-polygon
factor (Lambert's contour formula), the face route against the point route on a 1 mm
square, and Mitsuba's irradiancemeter on the floor against the face route.

`--refine-faces MULT --seed S` measures the face averages of the table at `--out` again,
independently (seed S, which the table must not have used), with MULT times the table's
first run's samples per face and run, and combines the two by sample count (a mean of
both estimates weighted by their samples; its standard error from both); the probe
points are kept as they are.

    python3 scripts/reference/mitsuba_cornell.py --budget 1900   # -> docs/reference/cornell-mitsuba.csv
    python3 scripts/reference/mitsuba_cornell.py --refine-faces 6 --seed 2 --threads 2
    python3 scripts/reference/mitsuba_cornell.py --check
"""
import argparse
import csv
import math
import os
import re
import struct
import sys
import tempfile
import time

import numpy as np
import drjit as dr
import mitsuba as mi

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
LIFT = 1e-2  # radiancemeter height above the surface point (scene units)
# Camera rays start this far above the face: at 0.01 mm, float32 camera transforms put some
# rays of tilted faces past the plane (they miss it); at 0.1 mm every pixel hits.
LIFT_CAM = 1e-1


# ----------------------------------------------------------------------------- scene


def load_obj(path):
    """OBJ `v`, `f`, `o`, `usemtl`, `mtllib` and the MTL's `newmtl`, `Kd`, `Ke`.

    Returns (faces, materials): every `f` line is one face, a dict with its id (0-based
    in file order), object, material, polygon corners and fan triangles (corner 0, k, k+1).
    """
    verts, faces, mats = [], [], {}
    obj, mtl = "", None
    d = os.path.dirname(path)
    for line in open(path):
        t = line.split()
        if not t or t[0].startswith("#"):
            continue
        if t[0] == "v":
            verts.append(np.array([float(x) for x in t[1:4]]))
        elif t[0] == "o":
            obj = t[1]
        elif t[0] == "usemtl":
            mtl = t[1]
        elif t[0] == "mtllib":
            mats.update(load_mtl(os.path.join(d, t[1])))
        elif t[0] == "f":
            idx = []
            for s in t[1:]:
                i = int(s.split("/")[0])
                idx.append(i - 1 if i > 0 else len(verts) + i)
            poly = np.array([verts[i] for i in idx])
            tris = [np.array([poly[0], poly[k], poly[k + 1]]) for k in range(1, len(poly) - 1)]
            faces.append({"id": len(faces), "object": obj, "material": mtl, "poly": poly,
                          "tris": tris})
    for f in faces:
        areas, normals = [], []
        for tri in f["tris"]:
            c = np.cross(tri[1] - tri[0], tri[2] - tri[0])
            areas.append(0.5 * np.linalg.norm(c))
            normals.append(c / np.linalg.norm(c))
        f["areas"], f["normals"] = np.array(areas), normals
        f["area"] = float(sum(areas))
        n = sum(a * nn for a, nn in zip(areas, normals))
        f["normal"] = n / np.linalg.norm(n)
        f["rho"] = np.array(mats[f["material"]]["Kd"])
        f["E"] = np.array(mats[f["material"]].get("Ke", [0.0, 0.0, 0.0]))
    return faces, mats


def load_mtl(path):
    mats, cur = {}, None
    for line in open(path):
        t = line.split()
        if not t or t[0].startswith("#"):
            continue
        if t[0] == "newmtl":
            cur = t[1]
            mats[cur] = {}
        elif t[0] in ("Kd", "Ke"):
            mats[cur][t[0]] = [float(x) for x in t[1:4]]
    return mats


def write_ply(path, tris):
    with open(path, "wb") as f:
        f.write((f"ply\nformat binary_little_endian 1.0\nelement vertex {3 * len(tris)}\n"
                 "property float x\nproperty float y\nproperty float z\n"
                 f"element face {len(tris)}\nproperty list uchar int vertex_indices\n"
                 "end_header\n").encode())
        for tri in tris:
            for v in tri:
                f.write(struct.pack("<3f", *v))
        for k in range(len(tris)):
            f.write(struct.pack("<B3i", 3, 3 * k, 3 * k + 1, 3 * k + 2))


FILM = {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"},
        "pixel_format": "rgb", "component_format": "float32"}


def path_integrator(max_depth=100):
    """Path tracing, Russian roulette off (rr_depth beyond max_depth)."""
    return {"type": "path", "max_depth": max_depth, "rr_depth": max_depth + 1,
            "hide_emitters": False}


def face_camera(tri, n, h):
    """An orthographic camera looking straight down at triangle tri (normal n) from LIFT_CAM
    above it, its film a grid of h x h pixels covering the triangle's bounding rectangle
    in its plane (rays start LIFT_CAM above the plane and end soon after it)."""
    e = [tri[1] - tri[0], tri[2] - tri[1], tri[0] - tri[2]]
    e1 = max(e, key=np.linalg.norm)
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    a, b = (tri - tri[0]) @ e2, (tri - tri[0]) @ e1
    W = max(1, int(math.ceil((a.max() - a.min()) / h)))
    H = max(1, int(math.ceil((b.max() - b.min()) / h)))
    c = tri[0] + e2 * (a.max() + a.min()) / 2 + e1 * (b.max() + b.min()) / 2
    near = 1e-3 * LIFT_CAM
    T = mi.ScalarTransform4f
    return {"type": "orthographic", "near_clip": near, "far_clip": near + 2 * LIFT_CAM,
            "to_world": T().look_at(origin=(c + (LIFT_CAM + near) * n).tolist(),
                                    target=c.tolist(), up=e1.tolist())
                        @ T().scale([W * h / 2, W * h / 2, 1.0]),
            "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
                     "pixel_format": "rgb", "component_format": "float32"},
            "sampler": {"type": "independent", "sample_count": 1}}, W * H


def build(faces, meters, tmp, cameras=(), max_depth=100, irradiancemeter=None):
    """Mitsuba scene: one PLY mesh per OBJ face (diffuse, rho = Kd; area emitter with
    radiance Ke / pi on its front side); radiancemeters at (origin, direction) LIFT above
    each point looking down at it (sensors 0..len(meters)-1), then the cameras. The
    integrator is `aov` (hit position) around the path tracer."""
    sc = {"type": "scene",
          "integrator": {"type": "aov", "aovs": "pp:position",
                         "path": path_integrator(max_depth)}}
    for f in faces:
        fn = os.path.join(tmp, f"face{f['id']}.ply")
        write_ply(fn, f["tris"])
        d = {"type": "ply", "filename": fn, "face_normals": True,
             "bsdf": {"type": "diffuse",
                      "reflectance": {"type": "rgb", "value": f["rho"].tolist()}}}
        if f["E"].any():
            d["emitter"] = {"type": "area",
                            "radiance": {"type": "rgb", "value": (f["E"] / math.pi).tolist()}}
        if f["id"] == irradiancemeter:
            d["sensor"] = {"type": "irradiancemeter", "sampler": {"type": "independent"},
                           "film": FILM}
        sc[f"face{f['id']}"] = d
    for k, (o, n) in enumerate(meters):
        sc[f"s{k:06d}"] = {"type": "radiancemeter",
                           "origin": (o + LIFT * n).tolist(), "direction": (-n).tolist(),
                           "sampler": {"type": "independent"}, "film": FILM}
    for k, cam in enumerate(cameras):
        sc[f"s{len(meters) + k:06d}"] = cam
    return mi.load_dict(sc)


def measure(scene, k, spp, seed):
    """B = pi * L seen by radiancemeter k."""
    img = mi.render(scene, sensor=k, spp=int(spp), seed=int(seed))
    return math.pi * np.array(img, dtype=np.float64)[0, 0, :3]


def face_mean(scene, k, tri, n, seed):
    """Mean of B over triangle tri from camera k: one sample per pixel (uniform in the
    pixel), the mean over the samples whose hit lies on the triangle (uniform on it).
    Returns (sum of B over those samples, their number)."""
    img = np.array(mi.render(scene, sensor=k, spp=1, seed=int(seed)), dtype=np.float64)
    B = math.pi * img[..., :3].reshape(-1, 3)
    p = img[..., 3:6].reshape(-1, 3)
    d = p - tri[0]
    v0, v1 = tri[1] - tri[0], tri[2] - tri[0]
    d00, d01, d11 = v0 @ v0, v0 @ v1, v1 @ v1
    d20, d21 = d @ v0, d @ v1
    den = d00 * d11 - d01 * d01
    b1 = (d11 * d20 - d01 * d21) / den
    b2 = (d00 * d21 - d01 * d20) / den
    hit = np.abs(p).sum(1) > 0  # a ray that hits nothing has position 0
    inside = hit & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1) & (np.abs(d @ n) < 1e-2 * LIFT_CAM)
    return B[inside].sum(0), int(inside.sum())


class FacePlan:
    """Cameras for every triangle of every face, with a pixel size per face such that a
    run renders about samples[f] one-sample pixels for face f over its triangles' bounding
    rectangles (about half of them land on the face), in passes of at most pmax."""

    def __init__(self, faces, samples, pmax, first):
        self.cams, self.items, self.passes = [], [], []
        for f, nf in zip(faces, samples):
            rect = 0.0
            for tri, n in zip(f["tris"], f["normals"]):
                _, wh = face_camera(tri, n, 1.0)
                rect += wh
            passes = max(1, int(math.ceil(nf * rect / f["area"] / pmax)))
            h = math.sqrt(rect * passes / nf) if nf > 0 else 1.0
            for t, (tri, n) in enumerate(zip(f["tris"], f["normals"])):
                cam, _ = face_camera(tri, n, h)
                self.items.append((f["id"], t, first + len(self.cams), tri, n, h))
                self.cams.append(cam)
            self.passes.append(passes)

    def run(self, scene, faces, seed):
        """Area averages of B, one independent estimate per face: the area-weighted mean
        of its triangles' sample means (a ratio estimator: the number of samples that land
        on a triangle varies, its bias is of the order of 1 / samples)."""
        acc = np.zeros((len(faces), 3))
        count = np.zeros(len(faces), dtype=np.int64)
        for fid, t, k, tri, n, h in self.items:
            S, m = np.zeros(3), 0
            for q in range(self.passes[fid]):
                s_, m_ = face_mean(scene, k, tri, n, seed + 1000 * k + q)
                S, m = S + s_, m + m_
            acc[fid] += faces[fid]["areas"][t] / faces[fid]["area"] * S / max(m, 1)
            count[fid] += m
        return acc, count


def on_face(faces, fid, p):
    """The triangle of face fid whose plane holds p best (p projected onto it), normal."""
    f = faces[fid]
    best = None
    for tri, n in zip(f["tris"], f["normals"]):
        q = p - np.dot(p - tri[0], n) * n
        # barycentric inside test
        v0, v1, v2 = tri[1] - tri[0], tri[2] - tri[0], q - tri[0]
        d00, d01, d11 = v0 @ v0, v0 @ v1, v1 @ v1
        d20, d21 = v2 @ v0, v2 @ v1
        den = d00 * d11 - d01 * d01
        b1 = (d11 * d20 - d01 * d21) / den
        b2 = (d00 * d21 - d01 * d20) / den
        inside = min(b1, b2, 1 - b1 - b2)
        if best is None or inside > best[0]:
            best = (inside, q, n)
    assert best[0] >= -1e-9, (fid, p)
    return best[1], best[2]


def face_id(faces, obj, n_hint=None):
    c = [f for f in faces if f["object"] == obj]
    if n_hint is None:
        assert len(c) == 1
        return c[0]["id"]
    return max(c, key=lambda f: f["normal"] @ np.array(n_hint))["id"]


def segment_blocked(faces, a, b, skip):
    """True if the open segment a-b crosses a triangle of a face other than skip."""
    d = b - a
    for f in faces:
        if f["id"] in skip:
            continue
        for tri in f["tris"]:
            e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
            pv = np.cross(d, e2)
            det = e1 @ pv
            if abs(det) < 1e-12:
                continue
            tv = a - tri[0]
            u = (tv @ pv) / det
            if u < 0 or u > 1:
                continue
            qv = np.cross(tv, e1)
            v = (d @ qv) / det
            if v < 0 or u + v > 1:
                continue
            t = (e2 @ qv) / det
            if 1e-9 < t < 1 - 1e-9:
                return True
    return False


def light_visibility(faces, p, light, m=12):
    """Fraction of an m x m grid of points on the light visible from p."""
    vis = tot = 0
    for tri in light["tris"]:
        for i in range(m):
            for j in range(m):
                u, v = (i + 0.5) / m, (j + 0.5) / m
                su = math.sqrt(u)
                q = tri[0] + (1 - su) * (tri[1] - tri[0]) + v * su * (tri[2] - tri[0])
                tot += 1
                vis += not segment_blocked(faces, p, q, {light["id"]})
    return vis / tot


def cornell_probes(faces):
    """[(name, face id, point, normal, note)] in the scene's millimetres."""
    out = []
    floor = face_id(faces, "floor")
    for blk in ("short_block", "tall_block"):
        # base corners: bottom face vertices of the block (y = 0), in order around it
        pts = {tuple(v) for f in faces if f["object"] == blk for v in f["poly"] if v[1] == 0}
        base = np.array(sorted(pts))
        cen = base.mean(0)
        ang = np.arctan2(base[:, 2] - cen[2], base[:, 0] - cen[0])
        base = base[np.argsort(ang)]
        nb = len(base)
        outn = []
        for e in range(nb):
            a, b = base[e], base[(e + 1) % nb]
            t = (b - a) / np.linalg.norm(b - a)
            n = np.array([t[2], 0.0, -t[0]])
            if n @ ((a + b) / 2 - cen) < 0:
                n = -n
            outn.append(n)
            mid = (a + b) / 2
            for dist in (5, 8, 10, 12, 15):
                p = mid + dist * n
                out.append((f"{blk}-edge{e}-{dist}mm", floor, p, np.array([0.0, 1, 0]),
                            f"floor {dist} mm out from the middle of {blk} base edge {e} "
                            f"({a[0]:g},{a[2]:g})-({b[0]:g},{b[2]:g})"))
        for c in range(nb):
            n1, n2 = outn[c - 1], outn[c]  # edges meeting at corner c
            for dist in (5, 10):
                p = base[c] + dist * (n1 + n2) / (1 + n1 @ n2)
                out.append((f"{blk}-corner{c}-{dist}mm", floor, p, np.array([0.0, 1, 0]),
                            f"floor {dist} mm from both base edges at corner "
                            f"({base[c][0]:g},{base[c][2]:g}) of {blk}, outside"))
    # the tall block's shadow on the back wall: a vertical line behind the block
    back = face_id(faces, "back_wall")
    z = faces[back]["poly"][0][2]
    light = faces[face_id(faces, "light")]
    x = SHADOW_X
    for y in SHADOW_Y:
        p = np.array([x, y, z])
        v = light_visibility(faces, p, light, 16)
        out.append((f"back-shadow-y{y:g}", back, p, np.array([0.0, 0, -1]),
                    f"back wall across the tall block's shadow, light visible {v:.3f}"))
    controls = [
        ("floor-open-front", "floor", [450, 0, 60]),
        ("floor-open-left", "floor", [60, 0, 400]),
        ("floor-centre-front", "floor", [278, 0, 30]),
        ("ceiling-front", "ceiling", [278, 548.8, 100]),
        ("ceiling-back-left", "ceiling", [80, 548.8, 480]),
        ("back-wall-high", "back_wall", [150, 450, 559.2]),
        ("back-wall-centre", "back_wall", [278, 300, 559.2]),
        ("red-wall-centre", "red_wall", [554, 274, 280]),
        ("green-wall-centre", "green_wall", [0, 274, 280]),
        ("light-centre", "light", [278, 548.7, 279.5]),
        ("short-block-top", "short_block", [186, 165, 168.5]),
        ("tall-block-top", "tall_block", [368.5, 330, 351.5]),
    ]
    for name, obj, p in controls:
        p = np.array(p, dtype=float)
        if obj == "ceiling":
            fid = next(f["id"] for f in faces if f["object"] == "ceiling"
                       and inside_poly_xz(f["poly"], p))
        else:
            fid = face_id(faces, obj, [0, 1, 0] if obj.endswith("block") else None)
        q, n = on_face(faces, fid, p)
        out.append((name, fid, q, n, f"control on {obj}"))
    return out


SHADOW_X = 420.0
SHADOW_Y = (40, 80, 100, 120, 140, 160, 180, 200, 215, 240, 280)


def inside_poly_xz(poly, p):
    c = 0
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        if (a[2] > p[2]) != (b[2] > p[2]):
            x = a[0] + (p[2] - a[2]) / (b[2] - a[2]) * (b[0] - a[0])
            if x > p[0]:
                c ^= 1
    return bool(c)


def point_to_polygon_factor(p, n, poly):
    """Exact differential-area-to-polygon configuration factor (Lambert's contour
    formula), the polygon fully visible and in front of p."""
    s = 0.0
    k = len(poly)
    for i in range(k):
        a, b = poly[i] - p, poly[(i + 1) % k] - p
        g = math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))
        c = np.cross(a, b)
        s += g * (c @ n) / np.linalg.norm(c)
    return abs(s) / (2 * math.pi)


# ----------------------------------------------------------------------------- running


def run(faces, probes, args, tmp, log):
    """Pilot, then args.runs independent runs. Returns per-face and per-probe means and
    standard errors (over the runs) and run statistics."""
    meters = [(p, n) for _, _, p, n, _ in probes]
    se = lambda a: a.std(0, ddof=1) / math.sqrt(a.shape[0])
    rel = lambda m, s: (s / np.maximum(np.abs(m), 1e-300)).max(-1)

    # pilot: 4 runs of pilot_samples per face, 4 x pilot_spp per probe
    t0 = time.time()
    pilot = FacePlan(faces, [args.pilot_samples] * len(faces), args.pmax, len(meters))
    scene = build(faces, meters, tmp, pilot.cams)
    path = mi.load_dict(path_integrator())
    fr = np.array([pilot.run(scene, faces, 100_000_000 + 1_000_000 * r)[0] for r in range(4)])
    frel = rel(fr.mean(0), se(fr))  # relative se of the 4-run mean: half the sd of a run
    face_samples = []
    for f, r0 in zip(faces, frel):
        need = args.pilot_samples * (r0 * 2 / args.face_target) ** 2 / args.runs * args.margin
        face_samples.append(int(min(max(need, args.min_samples), args.max_samples)))
        log(f"pilot face {f['id']:2d} {f['object']:12s} B~{np.round(fr.mean(0)[f['id']], 4)} "
            f"rel sd of a run {2 * r0:.2e} -> {face_samples[-1]} samples x {args.runs} runs")
    point_spp = []
    for j, pr in enumerate(probes):
        vals = np.array([math.pi * np.array(mi.render(scene, sensor=j, integrator=path,
                                                      spp=args.pilot_spp,
                                                      seed=8_000_000 + 16 * j + r))[0, 0, :3]
                         for r in range(4)])
        r0 = rel(vals.mean(0), vals.std(0, ddof=1))  # per render of pilot_spp
        need = args.pilot_spp * (r0 / args.point_target) ** 2 / args.runs * args.margin
        point_spp.append(int(min(max(need, args.min_spp), args.max_point_spp)))
    pilot_time = time.time() - t0
    pilot_total = 4 * (args.pilot_samples * len(faces) + args.pilot_spp * len(probes))
    total = args.runs * (sum(face_samples) + sum(point_spp))
    eta = total * pilot_time / pilot_total
    log(f"pilot {pilot_time:.0f} s; probes {min(point_spp)}..{max(point_spp)} spp per run; "
        f"planned {total:.3g} samples, about {eta:.0f} s")
    if args.budget and eta > args.budget:
        k = args.budget / eta
        face_samples = [max(args.min_samples, int(x * k)) for x in face_samples]
        point_spp = [max(args.min_spp, int(x * k)) for x in point_spp]
        total = args.runs * (sum(face_samples) + sum(point_spp))
        log(f"over the budget of {args.budget:.0f} s: every count scaled by {k:.3f}, "
            f"{total:.3g} samples")

    plan = FacePlan(faces, face_samples, args.pmax, len(meters))
    scene = build(faces, meters, tmp, plan.cams)
    fres = np.zeros((args.runs, len(faces), 3))
    pres = np.zeros((args.runs, len(probes), 3))
    counts = np.zeros((args.runs, len(faces)), dtype=np.int64)
    t1 = time.time()
    for r in range(args.runs):
        seed = 1_000_000_000 * (args.seed % 4) + 10_000_000 * (r + 1)
        fres[r], counts[r] = plan.run(scene, faces, seed)
        for j in range(len(probes)):
            img = mi.render(scene, sensor=j, integrator=path, spp=point_spp[j],
                            seed=seed + 9_000_000 + j)
            pres[r, j] = math.pi * np.array(img, dtype=np.float64)[0, 0, :3]
        log(f"run {r + 1}/{args.runs} done, {time.time() - t1:.0f} s")
    run_time = time.time() - t1
    return (fres.mean(0), se(fres), pres.mean(0), se(pres),
            {"pilot_s": pilot_time, "runs_s": run_time, "face_samples": counts.mean(0),
             "point_spp": point_spp, "samples": total, "passes": plan.passes})


def refine_faces(faces, args, tmp, log):
    """`--refine-faces`: the table's face rows measured again with a new seed and combined
    with what they hold by sample count. Seeds follow `run` (base 1e9 * (seed % 4)), the
    cameras numbered from 0 (no radiancemeters in the scene)."""
    with open(args.out, newline="") as fh:
        rows = list(csv.DictReader(fh))
        fields = list(rows[0].keys())
    old = {int(r["id"]): r for r in rows if r["kind"] == "face"}
    if sorted(old) != [f["id"] for f in faces]:
        sys.exit(f"{args.out}: its face rows do not match the faces of {args.scene}")
    # Each face's note lists its runs, "N samples x R runs[, seed S]" (a table made by
    # `run` names no seed: it is --seed's default, 1).
    parts, seeds = {}, {}
    for i, r in old.items():
        runs = re.findall(r"(\d+) samples x (\d+) runs(?:, seed (\d+))?", r["note"])
        if not runs:
            sys.exit(f"{args.out}: face {i}: no sample count in its note")
        parts[i] = [(int(n), int(k)) for n, k, _ in runs]
        seeds[i] = [int(sd) if sd else 1 for _, _, sd in runs]
        if args.seed % 4 in [x % 4 for x in seeds[i]]:
            sys.exit(f"{args.out}: face {i} already holds runs of seeds {seeds[i]} (taken "
                     f"modulo 4); choose another --seed")
    samples = [int(parts[f["id"]][0][0] * args.refine_faces) for f in faces]
    plan = FacePlan(faces, samples, args.pmax, 0)
    scene = build(faces, [], tmp, plan.cams)
    res = np.zeros((args.runs, len(faces), 3))
    counts = np.zeros((args.runs, len(faces)), dtype=np.int64)
    t = time.time()
    for r in range(args.runs):
        res[r], counts[r] = plan.run(scene, faces, 1_000_000_000 * (args.seed % 4)
                                     + 10_000_000 * (r + 1))
        log(f"run {r + 1}/{args.runs} done, {time.time() - t:.0f} s")
    m1 = res.mean(0)
    s1 = res.std(0, ddof=1) / math.sqrt(args.runs)
    g = lambda v: f"{v + 0.0:.6g}"
    for f in faces:
        i, r = f["id"], old[f["id"]]
        m0 = np.array([float(r[k]) for k in ("B_r", "B_g", "B_b")])
        s0 = np.array([float(r[k]) for k in ("se_r", "se_g", "se_b")])
        n0 = sum(n * k for n, k in parts[i])
        n1 = counts[:, i].sum()
        w = n1 / (n0 + n1)
        m = (1 - w) * m0 + w * m1[i]
        s = np.sqrt(((1 - w) * s0) ** 2 + (w * s1[i]) ** 2)
        z = (m1[i] - m0) / np.sqrt(s0 ** 2 + s1[i] ** 2)
        log(f"face {i:2d} {f['object']:12s} new/old - 1 = "
            + " ".join(f"{100 * (a / b - 1):+.3f}%" for a, b in zip(m1[i], m0))
            + f" ({' '.join(f'{x:+.1f}' for x in z)} combined se)")
        for k, v in zip(("B_r", "B_g", "B_b", "se_r", "se_g", "se_b"), [*m, *s]):
            r[k] = g(v)
        head = r["note"].split("; ")[:2]
        runs = [f"{n} samples x {k} runs, seed {sd}" for (n, k), sd in zip(parts[i], seeds[i])]
        runs.append(f"{n1 / args.runs:.0f} samples x {args.runs} runs, seed {args.seed}")
        r["note"] = "; ".join(head + runs) + "; combined by sample count)"
    tmpout = args.out + ".tmp"
    with open(tmpout, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)
    os.replace(tmpout, args.out)
    log(f"wrote {args.out}: faces refined in {time.time() - t:.0f} s")


def checks(args, tmp, log):
    """Furnace through the same code, direct light against the exact factor, and the
    face route (orthographic camera) against the point route (radiancemeter)."""
    path = mi.load_dict(path_integrator())
    for rho in (0.5, 0.9):
        for scale in (1.0, 500.0):
            cube, _ = load_obj(os.path.join(ROOT, "scenes", "cube.obj"))
            for f in cube:
                f["rho"] = np.array([rho] * 3)
                f["tris"] = [scale * t for t in f["tris"]]
                f["area"] *= scale ** 2
                f["areas"] = f["areas"] * scale ** 2
            plan = FacePlan(cube, [100_000] * len(cube), args.pmax, 1)
            q = np.array([0.3, 0.4, 0.0]) * scale
            scene = build(cube, [(q, np.array([0.0, 0, 1]))], os.path.join(tmp, "cube"),
                          plan.cams)
            fr = np.array([plan.run(scene, cube, 1000 * r)[0][:, 0] for r in range(4)])
            m, s = fr.mean(0), fr.std(0, ddof=1) / 2
            pv = np.array([math.pi * np.array(mi.render(scene, sensor=0, integrator=path,
                                                        spp=100_000, seed=77 + r))[0, 0, 0]
                           for r in range(4)])
            exact = 1 / (1 - rho)
            log(f"furnace cube side {scale:g}, rho {rho}, E 1 (exact B = {exact:g}): face "
                f"averages {' '.join(f'{a:.5f}' for a in m)} (se {s.max():.1e}); mean "
                f"{m.mean():.5f} +- {math.sqrt((s ** 2).sum()) / 6:.5f}; point {q.round(1)}: "
                f"{pv.mean():.5f} +- {pv.std(ddof=1) / 2:.5f}")

    faces, _ = load_obj(args.scene)
    light = faces[face_id(faces, "light")]
    pts = [np.array(p, dtype=float) for p in ([278, 0, 279.6], [450, 0, 60], [80, 0, 500],
                                               [150, 450, 559.2])]
    meters, ok = [], []
    for p in pts:
        fid = face_id(faces, "floor") if p[1] == 0 else face_id(faces, "back_wall")
        q, n = on_face(faces, fid, p)
        meters.append((q, n))
        ok.append((q, n, fid, light_visibility(faces, q, light, 16)))
    scene = build(faces, meters, tmp)
    direct = mi.load_dict(path_integrator(2))
    for k, (q, n, fid, vis) in enumerate(ok):
        F = point_to_polygon_factor(q, n, light["poly"])
        exact = faces[fid]["rho"] * light["E"] * F
        v = np.array([math.pi * np.array(mi.render(scene, sensor=k, integrator=direct,
                                                   spp=200_000, seed=31 * r + k))[0, 0, :3]
                      for r in range(4)])
        m, s = v.mean(0), v.std(0, ddof=1) / 2
        log(f"direct only (max_depth 2) at {q.round(2)}, light visible {vis:.3f}: Mitsuba "
            f"{' '.join(f'{x:.6g}' for x in m)} (rel se {(s / m).max():.1e}); rho E F "
            f"{' '.join(f'{x:.6g}' for x in exact)} (F = {F:.7f}); ratio "
            f"{' '.join(f'{x:.5f}' for x in m / exact)}")

    # face route vs point route: a 1 mm square of open floor around (450, 0, 60)
    c = np.array([450.0, 0, 60])
    sq = [np.array([c + [-0.5, 0, -0.5], c + [-0.5, 0, 0.5], c + [0.5, 0, 0.5]]),
          np.array([c + [-0.5, 0, -0.5], c + [0.5, 0, 0.5], c + [0.5, 0, -0.5]])]
    patch = {"id": 0, "tris": sq, "normals": [np.array([0.0, 1, 0])] * 2, "area": 1.0,
             "areas": np.array([0.5, 0.5])}
    plan = FacePlan([patch], [40_000], args.pmax, 1)
    scene = build(faces, [(c, np.array([0.0, 1, 0]))], tmp, plan.cams)
    fr = np.array([plan.run(scene, [patch], 5000 * r)[0][0] for r in range(8)])
    pv = np.array([math.pi * np.array(mi.render(scene, sensor=0, integrator=path,
                                                spp=40_000, seed=99 + r))[0, 0, :3]
                   for r in range(8)])
    log(f"1 mm floor square at {c}: camera route {fr.mean(0).round(6)} +- "
        f"{(fr.std(0, ddof=1) / math.sqrt(8)).round(6)}; radiancemeter at its centre "
        f"{pv.mean(0).round(6)} +- {(pv.std(0, ddof=1) / math.sqrt(8)).round(6)}")


def check_irradiancemeter(args, tmp, log, fid=0, spp=4_000_000, runs=4):
    """Mitsuba's own irradiancemeter on face fid: B = E + rho * H over the face, against the
    camera route. It samples the incident directions by the cosine without light sampling,
    so it needs about 100 times the samples of the camera route on the Cornell floor."""
    faces, _ = load_obj(args.scene)
    path = mi.load_dict(path_integrator())
    scene = build(faces, [], tmp, irradiancemeter=fid)
    k = next(i for i, x in enumerate(scene.sensors()) if "IrradianceMeter" in str(x))
    f = faces[fid]
    v = np.array([f["E"] + f["rho"] * np.array(mi.render(scene, sensor=k, integrator=path,
                                                         spp=spp, seed=4242 + r),
                                                dtype=np.float64)[0, 0, :3]
                  for r in range(runs)])
    plan = FacePlan([f | {"id": 0}], [spp // 40], args.pmax, 0)
    scene = build(faces, [], tmp, plan.cams)
    c = np.array([plan.run(scene, [f | {"id": 0}], 300_000 * (r + 1))[0][0]
                  for r in range(runs)])
    log(f"face {fid} ({f['object']}): irradiancemeter, {runs} x {spp} samples: B = "
        f"{v.mean(0).round(6)} +- {(v.std(0, ddof=1) / math.sqrt(runs)).round(6)}; camera "
        f"route, {runs} x {spp // 40}: {c.mean(0).round(6)} +- "
        f"{(c.std(0, ddof=1) / math.sqrt(runs)).round(6)}")


def main():
    ap = argparse.ArgumentParser(description="Mitsuba 3 radiosity reference of an OBJ scene")
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes", "cornell.obj"))
    ap.add_argument("-o", "--out", default=os.path.join(ROOT, "docs", "reference",
                                                        "cornell-mitsuba.csv"))
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--pmax", type=int, default=1_000_000, help="pixels per render at most")
    ap.add_argument("--face-target", type=float, default=3.5e-4,
                    help="relative standard error aimed at for face averages")
    ap.add_argument("--point-target", type=float, default=3.5e-3,
                    help="relative standard error aimed at for probe points")
    ap.add_argument("--pilot-samples", type=int, default=20000,
                    help="samples per face in each of the 4 pilot runs")
    ap.add_argument("--pilot-spp", type=int, default=2000,
                    help="samples per probe in each of the 4 pilot renders")
    ap.add_argument("--margin", type=float, default=1.0)
    ap.add_argument("--min-spp", type=int, default=1000)
    ap.add_argument("--min-samples", type=int, default=20000)
    ap.add_argument("--max-samples", type=int, default=20_000_000,
                    help="samples per face per run at most")
    ap.add_argument("--max-point-spp", type=int, default=2000000)
    ap.add_argument("--budget", type=float, default=0,
                    help="seconds for the runs after the pilot; counts are scaled down to fit")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--check", action="store_true", help="run the convention checks only")
    ap.add_argument("--refine-faces", type=float, default=0, metavar="MULT",
                    help="measure the face averages of the table at --out again with MULT "
                         "times its samples and this --seed, and combine them with it")
    args = ap.parse_args()

    mi.set_variant("scalar_rgb")
    dr.set_thread_count(args.threads)
    log = lambda s: print(time.strftime("%H:%M:%S"), s, flush=True)
    log(f"Mitsuba {mi.__version__}, variant {mi.variant()}, threads {dr.thread_count()}")
    tmp = tempfile.mkdtemp(prefix="mitsuba-ref-")
    os.makedirs(os.path.join(tmp, "cube"), exist_ok=True)
    if args.check:
        checks(args, tmp, log)
        check_irradiancemeter(args, tmp, log)
        return

    faces, _ = load_obj(args.scene)
    if args.refine_faces > 0:
        refine_faces(faces, args, tmp, log)
        return
    probes = cornell_probes(faces)
    log(f"{len(faces)} faces, {len(probes)} probe points")
    t = time.time()
    fm, fs, pm, ps, st = run(faces, probes, args, tmp, log)
    wall = time.time() - t
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["kind", "id", "object", "x", "y", "z", "nx", "ny", "nz",
                    "B_r", "B_g", "B_b", "se_r", "se_g", "se_b", "note"])
        g = lambda v: f"{v + 0.0:.6g}"  # no "-0"
        for f, m, s in zip(faces, fm, fs):
            c = sum(a * t.mean(0) for a, t in zip(f["areas"], f["tris"])) / f["area"]
            w.writerow(["face", f["id"], f["object"], *map(g, c), *map(g, f["normal"]),
                        *map(g, m), *map(g, s),
                        f"area average (x y z = area centroid; area {f['area']:.6g}; "
                        f"{st['face_samples'][f['id']]:.0f} samples x {args.runs} runs)"])
        for (name, fid, p, n, note), m, s, spp in zip(probes, pm, ps, st["point_spp"]):
            w.writerow(["point", name, faces[fid]["object"], *map(g, p), *map(g, n),
                        *map(g, m), *map(g, s), f"{note}; face {fid}; {spp} spp x {args.runs} runs"])
    rf = fs / np.maximum(fm, 1e-30)
    rp = ps / np.maximum(pm, 1e-30)
    log(f"wrote {args.out}: wall {wall:.0f} s (pilot {st['pilot_s']:.0f} s), "
        f"{st['samples']:.3g} samples")
    log(f"face relative se {rf.min():.2e}..{rf.max():.2e}; point {rp.min():.2e}..{rp.max():.2e}")


if __name__ == "__main__":
    main()
