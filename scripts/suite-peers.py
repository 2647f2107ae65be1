#!/usr/bin/env python3
"""Adapters: other programs' form factors on the exported suite, in the scorer's formats.

Run through scripts/suite-peers.sh, which makes the virtual environment (pyViewFactor 1.1.0,
raystrack 2.0.0, pyradiance 1.3.1, whose wheel carries the Radiance programs). Each adapter
reads suite.json and the cases' OBJ files and writes what `radiosity suite score` reads:

- pyviewfactor: one folder per case, OUT/CASE/{F.mtx, patches.csv, provenance.json}: the
  face-to-face matrix of pyvf.compute_viewfactor_matrix (SA-30 kernel, its own obstruction
  tests), patches = OBJ faces (`face` column), `seconds` the timed call. Score with
  `--matrix OUT`.
- raystrack: OUT.csv (case,from,to,value,stderr,seconds): one raystrack Surface per suite
  surface, cosine-weighted rays from a 4 x 4 grid of cells per surface, RAYS_PER_CELL rays
  per cell and replicate, 4 replicates; its standard error where it reports one.
- radiance: OUT.csv (case,from,to,value,,seconds): rfluxmtx with the from-surface as the
  sender (uniform basis `h=u`), the to-surface as the receiver, every other surface black
  (`plastic 0 0 0`), `-ab 1 -c RAYS`.

Times are wall-clock seconds of the computation per case on this machine, after one untimed
warm-up call for the programs that compile code on first use (Numba).
"""
import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np


def read_obj(path):
    """(vertices, faces): faces as (surface name, [vertex indices]) in `f` order."""
    verts, faces, current = [], [], None
    with open(path) as f:
        for line in f:
            w = line.split()
            if not w or w[0].startswith("#"):
                continue
            if w[0] == "v":
                verts.append([float(x) for x in w[1:4]])
            elif w[0] in ("o", "g"):
                current = w[1]
            elif w[0] == "f":
                faces.append((current, [int(x.split("/")[0]) - 1 for x in w[1:]]))
    return np.array(verts), faces


def area(p):
    n = np.zeros(3)
    for k in range(len(p)):
        n += np.cross(p[k], p[(k + 1) % len(p)])
    return np.linalg.norm(n) / 2


def cases(suite_dir, only):
    with open(os.path.join(suite_dir, "suite.json")) as f:
        table = json.load(f)
    for c in table["cases"]:
        if only and c["case"] not in only:
            continue
        verts, faces = read_obj(os.path.join(suite_dir, c["geometry"]))
        yield table["suite"], c, verts, faces


def run_pyviewfactor(suite_dir, out, only):
    import pyvista as pv
    import pyviewfactor as pvf

    def mesh_of(verts, faces):
        cells = np.hstack([[len(ix)] + ix for _, ix in faces])
        return pv.PolyData(verts, cells)

    first = True
    for _, c, verts, faces in cases(suite_dir, only):
        mesh = mesh_of(verts, faces)
        if first:  # Numba compiles on first use
            pvf.compute_viewfactor_matrix(mesh)
            first = False
        t = time.perf_counter()
        M = np.asarray(pvf.compute_viewfactor_matrix(mesh))
        dt = time.perf_counter() - t
        F = M.T  # pyViewFactor returns M[i, j] = F(j -> i)
        d = os.path.join(out, c["case"])
        os.makedirs(d, exist_ok=True)
        nz = [(i, j, float(F[i, j])) for i in range(len(faces)) for j in range(len(faces)) if F[i, j] != 0]
        with open(os.path.join(d, "F.mtx"), "w") as f:
            f.write("%%MatrixMarket matrix coordinate real general\n% pyViewFactor 1.1.0\n")
            f.write(f"{len(faces)} {len(faces)} {len(nz)}\n")
            for i, j, x in nz:
                f.write(f"{i + 1} {j + 1} {x!r}\n")
        with open(os.path.join(d, "patches.csv"), "w") as f:
            f.write("id,area,face\n")
            for k, (_, ix) in enumerate(faces):
                f.write(f"{k},{float(area(verts[ix]))!r},{k}\n")
        with open(os.path.join(d, "provenance.json"), "w") as f:
            json.dump({"writer": "pyViewFactor 1.1.0", "seconds": dt}, f)
        print(f"{c['case']:<28} {dt:8.3f}s", flush=True)


def triangles(verts, faces, name):
    tris = []
    for s, ix in faces:
        if s == name:
            for k in range(1, len(ix) - 1):
                tris.append([verts[ix[0]], verts[ix[k]], verts[ix[k + 1]]])
    pts = np.array(tris).reshape(-1, 3)
    return pts, np.arange(len(pts)).reshape(-1, 3)


def run_raystrack(suite_dir, out, only, rays_per_cell):
    import raystrack as rt

    rows = []
    warmed = False
    for _, c, verts, faces in cases(suite_dir, only):
        names = [s["name"] for s in c["surfaces"]]
        surfaces = [rt.Surface(n, rt.Mesh(*triangles(verts, faces, n))) for n in names]
        scene = rt.Scene(surfaces)
        # raystrack's emitter grid has max(4, ceil(sqrt(area * density))) cells per side:
        # the density (an integer >= 1) is set so that the largest surface has about 4 x 4;
        # a case that would need more than 64 x 64 even at density 1 is skipped.
        big = max(s["area"] for s in c["surfaces"])
        density = max(1, round(16.0 / big))
        if big * density > 64 * 64:
            print(f"{c['case']:<28} skipped: {math.ceil(math.sqrt(big * density))}^2 emitter cells", flush=True)
            continue
        opts = rt.SolveOptions(
            sampling=rt.Sampling(density=density, rays_per_cell=rays_per_cell, seed=1),
            accuracy=rt.Accuracy(min_replicates=4, max_replicates=4))
        query = rt.Query.matrix(receiver_sides=("front",))
        if not warmed:
            with rt.Solver(scene, device="cpu") as solver:
                solver.solve(query, opts)
            warmed = True
        t = time.perf_counter()
        with rt.Solver(scene, device="cpu") as solver:
            res = solver.solve(query, opts)
        dt = time.perf_counter() - t
        dense = res.dense(unknown=0.0)
        se = None
        for attr in ("dense_stderr", "stderr_dense"):
            if hasattr(res, attr):
                se = getattr(res, attr)(unknown=0.0)
        value, err = None, None
        row = list(res.sender_ids).index(c["from"])
        for k, ch in enumerate(res.channels):
            if ch.kind == "surface" and ch.side == "front" and ch.surface_id == c["to"]:
                value = float(dense[row, k])
                err = float(se[row, k]) if se is not None else None
        rows.append((c["case"], c["from"], c["to"], value, err, dt))
        print(f"{c['case']:<28} {value!r:>24} {dt:8.3f}s", flush=True)
    write_csv(out, rows)


def rad_polygons(verts, faces, name, modifier, reverse=False):
    out = []
    for k, (s, ix) in enumerate(faces):
        if s != name:
            continue
        p = verts[ix][::-1] if reverse else verts[ix]
        coords = " ".join(repr(float(x)) for x in p.reshape(-1))
        out.append(f"{modifier} polygon {name}.{k}\n0\n0\n{3 * len(p)} {coords}\n")
    return "".join(out)


def up_axis(verts, faces, name):
    """The coordinate axis least aligned with the first polygon of surface `name` (rfluxmtx
    needs an up vector off the surface normal, even for its one-bin basis)."""
    for s, ix in faces:
        if s == name:
            p = verts[ix]
            n = np.cross(p[1] - p[0], p[2] - p[0])
            return "XYZ"[int(np.argmin(np.abs(n) / np.linalg.norm(n)))]


def run_radiance(suite_dir, out, only, rays):
    rows = []
    for _, c, verts, faces in cases(suite_dir, only):
        with tempfile.TemporaryDirectory() as d:
            # rfluxmtx sends from a sender surface's back side: the from-surface reversed.
            snd = f"#@rfluxmtx h=u u={up_axis(verts, faces, c['from'])}\nvoid glow snd 0 0 4 1 1 1 0\n"
            snd += rad_polygons(verts, faces, c["from"], "snd", reverse=True)
            rcv = f"#@rfluxmtx h=u u={up_axis(verts, faces, c['to'])}\nvoid glow rcv 0 0 4 1 1 1 0\n"
            rcv += rad_polygons(verts, faces, c["to"], "rcv")
            scene = "void plastic black 0 0 5 0 0 0 0 0\n"
            for s in c["surfaces"]:
                if s["name"] not in (c["from"], c["to"]):
                    scene += rad_polygons(verts, faces, s["name"], "black")
            for n, text in (("snd.rad", snd), ("rcv.rad", rcv), ("scene.rad", scene)):
                with open(os.path.join(d, n), "w") as f:
                    f.write(text)
            args = ["rfluxmtx", "-h", "-ab", "1", "-c", str(rays), "snd.rad", "rcv.rad", "scene.rad"]
            t = time.perf_counter()
            r = subprocess.run(args, cwd=d, capture_output=True, text=True)
            dt = time.perf_counter() - t
            if r.returncode != 0:
                raise RuntimeError(f"{c['case']}: {' '.join(args)}: {r.stderr.strip()}")
            value = float(r.stdout.split()[0])
        rows.append((c["case"], c["from"], c["to"], value, None, dt))
        print(f"{c['case']:<28} {value!r:>24} {dt:8.3f}s", flush=True)
    write_csv(out, rows)


def write_csv(path, rows):
    with open(path, "w") as f:
        f.write("case,from,to,value,stderr,seconds\n")
        for case, a, b, v, e, t in rows:
            if v is None:
                continue
            f.write(f"{case},{a},{b},{v!r},{'' if e is None else repr(e)},{t!r}\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tool", choices=["pyviewfactor", "raystrack", "radiance"])
    ap.add_argument("--suite", default="suite", help="exported suite folder (suite.json)")
    ap.add_argument("-o", "--output", required=True,
                    help="folder (pyviewfactor) or CSV file (raystrack, radiance)")
    ap.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    ap.add_argument("--rays", type=int, default=100000, help="radiance: rfluxmtx -c")
    ap.add_argument("--rays-per-cell", type=int, default=16,
                    help="raystrack: rays per emitter cell and replicate")
    a = ap.parse_args()
    only = set(x for x in a.cases.split(",") if x)
    if a.tool == "pyviewfactor":
        run_pyviewfactor(a.suite, a.output, only)
    elif a.tool == "raystrack":
        run_raystrack(a.suite, a.output, only, a.rays_per_cell)
    else:
        run_radiance(a.suite, a.output, only, a.rays)


if __name__ == "__main__":
    sys.exit(main())
