#!/usr/bin/env python3
"""Checks that SciPy reads the same matrices from a factors folder's npz files as from
Matrix Market files of the same run, bit for bit.

    scripts/check-npz.py NPZ_DIR MTX_DIR

NPZ_DIR holds F.npz and stderr.npz (`radiosity factors ... --format npz`), MTX_DIR F.mtx
and stderr.mtx (`--format mtx`, same scene, settings and seed). F.npz is read with
`scipy.sparse.load_npz` and F.mtx with `scipy.io.mmread`; both become CSR, and the
shapes, row pointers, columns and the bits of every float64 value must agree. The standard
errors are float32 in stderr.npz; stderr.mtx holds each float32 in its shortest decimal
form, so its values rounded to float32 must give the same bits. Prints one line per
matrix and exits 1 on the first difference (2 when SciPy is missing).
"""

import sys

try:
    import numpy as np
    import scipy
    import scipy.io
    import scipy.sparse
except ImportError as e:  # the caller says why it skips
    print(f"check-npz: needs numpy and scipy ({e})", file=sys.stderr)
    sys.exit(2)


def csr(m):
    m = scipy.sparse.csr_matrix(m)
    m.sort_indices()
    return m


def compare(name, a, b, dtype):
    """a from load_npz, b from mmread; their values compared as `dtype` bits."""
    problems = []
    if a.shape != b.shape:
        problems.append(f"shape {a.shape} vs {b.shape}")
    elif a.nnz != b.nnz:
        problems.append(f"{a.nnz} vs {b.nnz} stored entries")
    else:
        if not np.array_equal(a.indptr, b.indptr):
            problems.append("row pointers differ")
        if not np.array_equal(a.indices, b.indices):
            problems.append("columns differ")
        if a.data.dtype != dtype:
            problems.append(f"npz values are {a.data.dtype}, expected {dtype}")
        else:
            bits = np.uint64 if dtype == np.float64 else np.uint32
            x = a.data.view(bits)
            y = b.data.astype(dtype).view(bits)
            diff = np.flatnonzero(x != y)
            if diff.size:
                k = diff[0]
                problems.append(f"{diff.size} values differ, first entry {k}: "
                                f"{a.data[k]!r} vs {b.data[k]!r}")
    if problems:
        print(f"{name}: DIFFERENT: " + "; ".join(problems))
        return False
    print(f"{name}: same {a.shape[0]} x {a.shape[1]} matrix, {a.nnz} entries, "
          f"{a.data.dtype} values bit for bit (scipy {scipy.__version__})")
    return True


def main():
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    npz, mtx = sys.argv[1], sys.argv[2]
    ok = True
    for stem, dtype in (("F", np.float64), ("stderr", np.float32)):
        a = scipy.sparse.load_npz(f"{npz}/{stem}.npz")
        if a.format != "csr":
            print(f"{stem}.npz: load_npz gave {a.format}, expected csr")
            ok = False
            continue
        b = csr(scipy.io.mmread(f"{mtx}/{stem}.mtx"))
        ok = compare(f"{stem}.npz vs {stem}.mtx", csr(a), b, dtype) and ok
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
