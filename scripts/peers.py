#!/usr/bin/env python3
"""Side-by-side form factors: radiosity (CLI), raystrack 2.0.0 and pyViewFactor 1.1.0.

Run through scripts/peers.sh, which makes the virtual environment. Cases: two perpendicular
unit squares with a common edge (Howell C-14, F = 0.2000438), two parallel unit squares at
distance 1 (Howell C-11, F = 0.1998249), and the closed unit cube with n x n patches per
face (face-to-face factors aggregated from the patch matrix: adjacent faces C-14, opposite
faces C-11; rows of the patch matrix sum to 1). Prints one table: time and error per tool.
"""
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

PERP, PARA = 0.2000438, 0.1998249  # radiosity::analytic, Howell C-14 and C-11
BIN = os.environ.get("RADIOSITY", "target/release/radiosity")


def quad_grid(p0, u, v, n):
    """n x n sub-quads of the parallelogram p0 + s u + t v, counter-clockwise about u x v."""
    quads = []
    for b in range(n):
        for a in range(n):
            c = [p0 + u * (a / n) + v * (b / n), p0 + u * ((a + 1) / n) + v * (b / n),
                 p0 + u * ((a + 1) / n) + v * ((b + 1) / n), p0 + u * (a / n) + v * ((b + 1) / n)]
            quads.append(np.array(c, dtype=float))
    return quads


def case_geometry(case, n):
    """Patches (list of 4x3 corner arrays, counter-clockwise seen from the front)."""
    e = np.eye(3)
    o = np.zeros(3)
    if case == "plates-perpendicular":
        return quad_grid(o, e[0], e[1], 1) + quad_grid(o, e[1], e[2], 1)
    if case == "plates-parallel":
        return quad_grid(o, e[0], e[1], 1) + quad_grid(e[2], e[1], e[0], 1)
    # cube, inward normals, same faces as scenes/cube.obj
    faces = [(o, e[0], e[1]), (e[2], e[1], e[0]), (o, e[2], e[0]),
             (e[1], e[0], e[2]), (o, e[1], e[2]), (e[0], e[2], e[1])]
    out = []
    for p0, u, v in faces:
        out += quad_grid(p0, u, v, n)
    return out


def normal_area(q):
    nrm = np.cross(q[1] - q[0], q[2] - q[0]) + np.cross(q[2] - q[0], q[3] - q[0])
    a = np.linalg.norm(nrm)
    return nrm / a, a / 2


def errors(case, F, normals, areas):
    """(error of the headline factor, worst |row sum - 1| or nan)."""
    keys = [tuple(np.round(nm, 6)) for nm in normals]
    groups = sorted(set(keys))
    idx = {g: [k for k, kk in enumerate(keys) if kk == g] for g in groups}
    def face(a, b):
        ia, ib = idx[a], idx[b]
        return float((areas[ia][:, None] * F[np.ix_(ia, ib)]).sum() / areas[ia].sum())
    if case == "plates-perpendicular":
        return abs(face(keys[0], keys[-1]) - PERP), float("nan")
    if case == "plates-parallel":
        return abs(face(keys[0], keys[-1]) - PARA), float("nan")
    worst = 0.0
    for a in groups:
        for b in groups:
            if a == b:
                continue
            exact = PARA if np.dot(a, b) < -0.5 else PERP
            worst = max(worst, abs(face(a, b) - exact))
    return worst, float(np.abs(F.sum(axis=1) - 1).max())


def run_radiosity(case, n, estimator):
    with tempfile.TemporaryDirectory() as d:
        scene = "cube" if case == "cube" else case
        args = [BIN, "factors", scene, "-o", d, "--max-edge", str(1.0 / n if case == "cube" else 10.0)]
        args += estimator
        t = time.perf_counter()
        subprocess.run(args, check=True, capture_output=True)
        dt = time.perf_counter() - t
        rows = np.genfromtxt(os.path.join(d, "patches.csv"), delimiter=",", names=True, dtype=None,
                             encoding=None)
        N = len(rows)
        F = np.zeros((N, N))
        with open(os.path.join(d, "F.mtx")) as f:
            for line in f:
                if line.startswith("%"):
                    continue
                header = line
                break
            for line in f:
                i, j, v = line.split()
                F[int(i) - 1, int(j) - 1] = float(v)
        normals = np.stack([rows["nx"], rows["ny"], rows["nz"]], axis=1).astype(float)
        return dt, F, normals, rows["area"].astype(float)


def run_pyviewfactor(case, n):
    import pyvista as pv
    import pyviewfactor as pvf
    quads = case_geometry(case, n)
    pts = np.concatenate(quads)
    cells = np.hstack([[4, 4 * k, 4 * k + 1, 4 * k + 2, 4 * k + 3] for k in range(len(quads))])
    mesh = pv.PolyData(pts, cells)
    t = time.perf_counter()
    # The cube is convex: no patch can block another, so obstruction tests are skipped.
    M = pvf.compute_viewfactor_matrix(mesh, skip_obstruction=(case == "cube"))
    dt = time.perf_counter() - t
    F = np.asarray(M).T  # pyViewFactor returns F[i, j] = F(j -> i)
    na = [normal_area(q) for q in quads]
    return dt, F, np.array([x[0] for x in na]), np.array([x[1] for x in na])


def run_raystrack(case, n, rays):
    import raystrack as rt
    quads = case_geometry(case, n)
    surfaces = [rt.Surface(f"p{k}", rt.Mesh(q, np.array([[0, 1, 2], [0, 2, 3]])))
                for k, q in enumerate(quads)]
    scene = rt.Scene(surfaces)
    side = int(math.isqrt(rays // 64))
    opts = rt.SolveOptions(sampling=rt.Sampling(density=max(side, 1), rays_per_cell=64, seed=1),
                           accuracy=rt.Accuracy(min_replicates=4, max_replicates=4))
    t = time.perf_counter()
    with rt.Solver(scene, device="cpu") as solver:
        res = solver.solve(rt.Query.matrix(receiver_sides=("front",)), opts)
    dt = time.perf_counter() - t
    dense = res.dense(unknown=0.0)
    ids = {f"p{k}": k for k in range(len(quads))}
    F = np.zeros((len(quads), len(quads)))
    for c, ch in enumerate(res.channels):
        if ch.kind == "surface" and ch.side == "front":
            F[[ids[s] for s in res.sender_ids], ids[ch.surface_id]] = dense[:, c]
    na = [normal_area(q) for q in quads]
    return dt, F, np.array([x[0] for x in na]), np.array([x[1] for x in na])


def main():
    cases = [("plates-perpendicular", 1), ("plates-parallel", 1), ("cube", 8), ("cube", 16),
             ("cube", 32)]
    tools = [
        ("radiosity semi (default)", lambda c, n: run_radiosity(c, n, [])),
        ("radiosity hemisphere 1024 rays/patch",
         lambda c, n: run_radiosity(c, n, ["--estimator", "hemisphere", "--samples", "16"])),
        ("raystrack 2.0.0 cosine, 1024 rays/patch x 4", lambda c, n: run_raystrack(c, n, 1024)),
        ("pyViewFactor 1.1.0 SA-30", run_pyviewfactor),
    ]
    # Numba compiles on first use: one untimed warm-up call per peer.
    for name, fn in tools[2:]:
        try:
            fn("plates-parallel", 1)
        except Exception as e:
            print(f"warm-up of {name} FAILED: {type(e).__name__}: {e}")
    print(f"{'case':<22} {'tool':<44} {'time s':>9} {'|F - exact|':>12} {'max|rowsum-1|':>14}")
    for case, n in cases:
        label = case if case != "cube" else f"cube {n}x{n}/face"
        base = None
        for name, fn in tools:
            if case == "cube" and n > 8 and name.startswith("radiosity semi"):
                print(f"{label:<22} {name:<44} {'skipped (O(N^3) pair culling)':>37}")
                continue
            try:
                dt, F, normals, areas = fn(case, n)
                err, rs = errors(case, F, normals, areas)
                base = base or dt
                print(f"{label:<22} {name:<44} {dt:>9.3f} {err:>12.2e} {rs:>14.2e}   x{dt / base:.2f}",
                      flush=True)
            except Exception as e:  # record exactly what happened
                print(f"{label:<22} {name:<44} FAILED: {type(e).__name__}: {e}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
