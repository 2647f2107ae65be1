#!/usr/bin/env python3
"""Side-by-side form factors: radiosity (CLI), raystrack 2.0.0 and pyViewFactor 1.1.0.

Run through scripts/peers.sh, which makes the virtual environment. Cases: two perpendicular
unit squares with a common edge (Howell C-14, F = 0.2000438), two parallel unit squares at
distance 1 (Howell C-11, F = 0.1998249), and the closed unit cube with n x n patches per
face (face-to-face factors aggregated from the patch matrix: adjacent faces C-14, opposite
faces C-11; rows of the patch matrix sum to 1). Prints one table: time and error per tool.
"time s" is the computation alone: radiosity's form-factor stage as the CLI reports it, the
peers' timed API call (after one untimed warm-up call that compiles their Numba code);
"process s" is radiosity's whole process (start, scene, stage, diagnostics, writing the
text matrices) and, for the peers, the same as "time s".
"""
import argparse
import math
import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

PERP, PARA = 0.20004377607540316, 0.19982489569838746  # Howell C-14 and C-11 (radiosity::analytic)
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


def read_mtx(path, n):
    """Dense matrix from a Matrix Market coordinate file (parsed in C by numpy)."""
    with open(path, "rb") as f:
        data = f.read()
    # Skip the comment lines and the size line.
    pos = 0
    while data.startswith(b"%", pos):
        pos = data.index(b"\n", pos) + 1
    pos = data.index(b"\n", pos) + 1
    t = np.fromstring(data[pos:].decode(), sep=" ").reshape(-1, 3)
    F = np.zeros((n, n))
    F[t[:, 0].astype(int) - 1, t[:, 1].astype(int) - 1] = t[:, 2]
    return F


def read_npz(path, n):
    """Dense matrix from SciPy's sparse npz layout (CSR arrays, read with numpy alone)."""
    with np.load(path, allow_pickle=False) as z:
        indptr, indices, data = z["indptr"], z["indices"], z["data"]
    F = np.zeros((n, n))
    rows = np.repeat(np.arange(n), np.diff(indptr))
    F[rows, indices] = data
    return F


def run_radiosity(case, n, estimator):
    """Runs `radiosity factors`; the time is that of its form-factor stage (as it reports),
    comparable with the peers' timed calls; the whole process time is printed too."""
    with tempfile.TemporaryDirectory() as d:
        scene = "cube" if case == "cube" else case
        args = [BIN, "factors", scene, "-o", d, "--max-edge", str(1.0 / n if case == "cube" else 10.0)]
        args += estimator
        t = time.perf_counter()
        out = subprocess.run(args, check=True, capture_output=True, text=True)
        process = time.perf_counter() - t
        m = re.search(r" in ([0-9.]+)s", out.stdout + out.stderr)
        dt = float(m.group(1)) if m else process
        rows = np.genfromtxt(os.path.join(d, "patches.csv"), delimiter=",", names=True, dtype=None,
                             encoding=None)
        npz = os.path.join(d, "F.npz")  # the default layout past 2^20 entries
        F = read_npz(npz, len(rows)) if os.path.exists(npz) else read_mtx(os.path.join(d, "F.mtx"), len(rows))
        normals = np.stack([rows["nx"], rows["ny"], rows["nz"]], axis=1).astype(float)
        return dt, F, normals, rows["area"].astype(float), process


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
    return dt, F, np.array([x[0] for x in na]), np.array([x[1] for x in na]), dt


def run_raystrack(case, n, rays):
    """Cosine tracing with `rays` rays per patch in all: raystrack's emitter grid is
    max(4, ceil(sqrt(area * density))) cells per side (4 x 4 for every patch here, density
    4), each cell shoots `rays_per_cell` rays per replicate, and 4 replicates run."""
    import raystrack as rt
    quads = case_geometry(case, n)
    surfaces = [rt.Surface(f"p{k}", rt.Mesh(q, np.array([[0, 1, 2], [0, 2, 3]])))
                for k, q in enumerate(quads)]
    scene = rt.Scene(surfaces)
    per_cell = rays // (16 * 4)
    assert per_cell * 16 * 4 == rays, rays
    opts = rt.SolveOptions(sampling=rt.Sampling(density=4, rays_per_cell=per_cell, seed=1),
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
    return dt, F, np.array([x[0] for x in na]), np.array([x[1] for x in na]), dt


CASES = {"plates-perpendicular": ("plates-perpendicular", 1), "plates-parallel": ("plates-parallel", 1),
         "cube8": ("cube", 8), "cube16": ("cube", 16), "cube32": ("cube", 32)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated, of: " + ", ".join(CASES))
    ap.add_argument("--tools", default="semi,hemisphere,raystrack,pyviewfactor",
                    help="comma-separated, of: semi, hemisphere, raystrack, pyviewfactor")
    ap.add_argument("--semi-args", default="--tol 1e-8",
                    help="extra arguments of `radiosity factors` for the semi-analytic estimator")
    args = ap.parse_args()
    semi = args.semi_args.split()
    tools = {
        "semi": (f"radiosity semi {' '.join(semi)}", lambda c, n: run_radiosity(c, n, semi)),
        "hemisphere": ("radiosity hemisphere 16x16x4 = 1024 rays/patch",
                       lambda c, n: run_radiosity(c, n, ["--estimator", "hemisphere", "--samples", "16"])),
        "raystrack": ("raystrack 2.0.0 cosine 4x4x16x4 = 1024 rays/patch", lambda c, n: run_raystrack(c, n, 1024)),
        "pyviewfactor": ("pyViewFactor 1.1.0 SA-30", run_pyviewfactor),
    }
    chosen = [(tools[t][0], tools[t][1], t) for t in args.tools.split(",")]
    # Numba compiles on first use: one untimed warm-up call per peer.
    for name, fn, key in chosen:
        if key in ("raystrack", "pyviewfactor"):
            try:
                fn("plates-parallel", 1)
            except Exception as e:
                print(f"warm-up of {name} FAILED: {type(e).__name__}: {e}")
    print(f"{'case':<22} {'tool':<50} {'time s':>9} {'process s':>10} {'|F - exact|':>12} "
          f"{'max|rowsum-1|':>14}  time / first")
    for key in args.cases.split(","):
        case, n = CASES[key]
        label = case if case != "cube" else f"cube {n}x{n}/face"
        base = None
        for name, fn, _ in chosen:
            try:
                dt, F, normals, areas, process = fn(case, n)
                err, rs = errors(case, F, normals, areas)
                del F
                base = base or dt
                print(f"{label:<22} {name:<50} {dt:>9.3f} {process:>10.3f} {err:>12.2e} {rs:>14.2e}"
                      f"  x{dt / base:.2f}", flush=True)
            except Exception as e:  # record exactly what happened
                print(f"{label:<22} {name:<50} FAILED: {type(e).__name__}: {e}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
