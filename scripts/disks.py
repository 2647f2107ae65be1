#!/usr/bin/env python3
"""Writes scenes/disks-ngon.obj and scenes/disks-polar.obj: two coaxial regular 128-gons
of circumradius 1, one unit apart (the emitter at y = 0 facing up, the receiver at y = 1
facing down), each written once as a single 128-corner face and once as a polar grid
(a fan of 128 triangles around the centre and 3 rings of 128 quads) over the very same
rim vertices. Deterministic: the files in the repository are its output."""
import math
import pathlib

N, RINGS = 128, 4
ROOT = pathlib.Path(__file__).resolve().parent.parent / "scenes"


def rim(y, r):
    # Counter-clockwise seen from +y for the emitter; the receiver reverses it.
    return [(r * math.cos(2 * math.pi * k / N), y, -r * math.sin(2 * math.pi * k / N)) for k in range(N)]


def fmt(v):
    return "v %.17g %.17g %.17g" % v


def write(name, polar):
    out = [f"# {name}: see scripts/disks.py", "mtllib disks.mtl"]
    verts = []
    faces = []
    for y, mat, up in ((0.0, "lamp", True), (1.0, "grey", False)):
        faces.append(f"usemtl {mat}")
        base = len(verts) + 1
        if not polar:
            verts += rim(y, 1.0)
            idx = [base + k for k in range(N)]
            faces.append("f " + " ".join(map(str, idx if up else idx[::-1])))
            continue
        centre = base
        verts.append((0.0, y, 0.0))
        ring0 = len(verts) + 1
        for j in range(1, RINGS + 1):
            verts += rim(y, j / RINGS)
        at = lambda j, k: ring0 + (j - 1) * N + k % N
        for k in range(N):
            tri = [centre, at(1, k), at(1, k + 1)]
            faces.append("f " + " ".join(map(str, tri if up else tri[::-1])))
        for j in range(1, RINGS):
            for k in range(N):
                q = [at(j, k), at(j + 1, k), at(j + 1, k + 1), at(j, k + 1)]
                faces.append("f " + " ".join(map(str, q if up else q[::-1])))
    (ROOT / name).write_text("\n".join(out + [fmt(v) for v in verts] + faces) + "\n")


write("disks-ngon.obj", polar=False)
write("disks-polar.obj", polar=True)
(ROOT / "disks.mtl").write_text("newmtl lamp\nKd 0 0 0\nKe 1 1 1\nnewmtl grey\nKd 0.5 0.5 0.5\n")
