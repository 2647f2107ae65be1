#!/usr/bin/env python3
"""Point radiosity of the generated rooms (`room-spheres-N`, `radiosity scenes`) with Mitsuba 3.

Radiosity is the project's, B = E + rho * H (exitance units, one-sided Lambertian faces),
measured as pi times the radiance seen by a `radiancemeter` 0.1 mm above the point, looking
straight down its normal. Mitsuba's path tracer (`scalar_rgb`, max_depth 100, no Russian
roulette) does the light transport; each value is the mean of `--runs` independent runs
(new seeds), with the standard error std / sqrt(runs). Values are luminance (0.2126 R +
0.7152 G + 0.0722 B).

The geometry is read from a bake's `mesh.ply` (the surfaces themselves; any bake of the
scene will do: its triangles cover the input faces exactly), and the materials of the
generated family are assigned by position: the light (the 1 x 1 quad 1 cm below the
ceiling, Ke 10, Kd 0.78), the pale blue wall at x = 0 (Kd 0.6 0.65 0.7), the other walls,
floor and ceiling (Kd 0.7), and the spheres (Kd 0.5): see src/scene/generated.rs.

Points are given as `x,y,z,nx,ny,nz` (a file of one per line, or arguments); a point on an
edge between two walls is ill-posed (the meter's ray grazes the other wall): use interior
points.

    python3 scripts/reference/mitsuba_room_points.py BAKE/mesh.ply POINTS.txt --spp 8192 --runs 8 > REF.csv
    python3 scripts/reference/mitsuba_room_points.py --score REF.csv BAKE1/mesh.ply BAKE2/mesh.ply

`--score` reads each bake's vertex radiosity (luminance) at the reference points (vertices
matched by position to 1e-4 and normal) and prints the relative errors: mean absolute,
90th percentile, largest, mean signed, and how many points are over 3% and 10%.
"""
import argparse
import os
import sys
import tempfile

import numpy as np

# Mitsuba is imported only to render (`main`), so that `--score` needs numpy alone.
mi = None

LIFT = 1e-4  # meter height above the surface (scene units, metres)
VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                   ("nz", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1"), ("R", "<f4"),
                   ("G", "<f4"), ("B", "<f4"), ("q", "<f4")])
MATERIALS = {"white": [0.7, 0.7, 0.7], "blue": [0.6, 0.65, 0.7], "grey": [0.5, 0.5, 0.5],
             "light": [0.78, 0.78, 0.78]}


def read_ply(path):
    """Vertices and triangles of a `mesh.ply` written by `radiosity bake`."""
    data = open(path, "rb").read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode()
    count = lambda what: int(next(l for l in head.split("\n") if l.startswith(what)).split()[2])
    nv, nf = count("element vertex"), count("element face")
    v = np.frombuffer(data, VERTEX, count=nv, offset=end)
    faces = np.frombuffer(data, np.dtype([("n", "u1"), ("i", "<i4", (3,))]), count=nf,
                          offset=end + nv * VERTEX.itemsize)
    if not (faces["n"] == 3).all():
        sys.exit(f"{path}: expected triangles only")
    p = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    return p[faces["i"]]


def material(c, n, eps=1e-5):
    x, y, z = c
    if abs(y - 2.99) < eps and 2 - eps <= x <= 3 + eps and 1.5 - eps <= z <= 2.5 + eps and n[1] < -0.9:
        return "light"
    if abs(x) < eps and n[0] > 0.9:
        return "blue"
    if min(abs(y), abs(y - 3), abs(z), abs(z - 4), abs(x - 5)) < eps:
        return "white"
    return "grey"


def scene(tri):
    centre = tri.mean(1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    groups = {}
    for k in range(len(tri)):
        groups.setdefault(material(centre[k], normal[k]), []).append(k)
    tmp = tempfile.mkdtemp()
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": 100, "rr_depth": 1000}}
    for name, ks in groups.items():
        path = os.path.join(tmp, name + ".obj")
        with open(path, "w") as o:
            for t in tri[ks]:
                for p in t:
                    o.write("v %.9f %.9f %.9f\n" % tuple(p))
            for j in range(len(ks)):
                o.write("f %d %d %d\n" % (3 * j + 1, 3 * j + 2, 3 * j + 3))
        shape = {"type": "obj", "filename": path, "face_normals": True,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": MATERIALS[name]}}}
        if name == "light":
            shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": [10 / np.pi] * 3}}
        d[name] = shape
    return mi.load_dict(d)


def score(ref_path, plys):
    ref = [list(map(float, l.split(","))) for l in open(ref_path).read().split()[1:]]
    key = lambda x, y, z, nx, ny, nz: (round(x, 4), round(y, 4), round(z, 4), round(nx), round(ny), round(nz))
    for path in plys:
        data = open(path, "rb").read()
        end = data.index(b"end_header\n") + len(b"end_header\n")
        head = data[:end].decode()
        nv = int(next(l for l in head.split("\n") if l.startswith("element vertex")).split()[2])
        v = np.frombuffer(data, VERTEX, count=nv, offset=end)
        lum = 0.2126 * v["R"] + 0.7152 * v["G"] + 0.0722 * v["B"]
        table = {key(*map(float, q)): b for *q, b in zip(v["x"], v["y"], v["z"], v["nx"], v["ny"], v["nz"], lum)}
        e = np.array([table[key(*r[:6])] / r[6] - 1 if key(*r[:6]) in table and r[6] > 0 else np.nan
                      for r in ref])
        a = np.abs(e)
        print("%s: %d of %d points; mean |e| %.2f%%, p90 %.1f%%, max %.1f%%, mean %+.2f%%, over 3%%: %d, "
              "over 10%%: %d" % (path, np.isfinite(e).sum(), len(ref), 100 * np.nanmean(a),
                                 100 * np.nanpercentile(a, 90), 100 * np.nanmax(a), 100 * np.nanmean(e),
                                 (a > 0.03).sum(), (a > 0.1).sum()))


def main():
    if len(sys.argv) > 2 and sys.argv[1] == "--score":
        score(sys.argv[2], sys.argv[3:])
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("ply")
    ap.add_argument("points", nargs="+")
    ap.add_argument("--spp", type=int, default=8192)
    ap.add_argument("--runs", type=int, default=8)
    a = ap.parse_args()
    global mi
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    s = scene(read_ply(a.ply))
    words = open(a.points[0]).read().split() if a.points[0].endswith(".txt") else a.points
    print("x,y,z,nx,ny,nz,B,se")
    for w in words:
        x, y, z, nx, ny, nz = map(float, w.split(","))
        vals = []
        for r in range(a.runs):
            sensor = mi.load_dict({
                "type": "radiancemeter", "origin": [x + LIFT * nx, y + LIFT * ny, z + LIFT * nz],
                "direction": [-nx, -ny, -nz],
                "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"},
                         "pixel_format": "rgb"},
                "sampler": {"type": "independent", "sample_count": a.spp}})
            rgb = np.array(mi.render(s, sensor=sensor, spp=a.spp, seed=r + 1)).reshape(-1)[:3]
            vals.append(np.pi * (0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]))
        vals = np.array(vals)
        print("%s,%.6f,%.6f" % (w, vals.mean(), vals.std(ddof=1) / np.sqrt(a.runs)), flush=True)


if __name__ == "__main__":
    main()
