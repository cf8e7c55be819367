#!/usr/bin/env python3
"""Compares two .safetensors files tensor by tensor (a device harness, not part of CI).

Usage: compare-safetensors.py A B
For two mixture files it also counts the kept slots (`atoms`) whose codebook rows have the same
content in both: all of them when the files hold the same embeddings with the codebook's rows
stored in another order.
Prints, per tensor: equal, or the count of differing elements and the largest absolute
difference (f16 and f32 read as float64). Exit status 0 either way.
"""
import sys

import numpy as np
from safetensors.numpy import load_file

a, b = load_file(sys.argv[1]), load_file(sys.argv[2])
for name in sorted(set(a) | set(b)):
    if name not in a or name not in b:
        print(f"{name}: only in {'A' if name in a else 'B'}")
        continue
    x, y = a[name], b[name]
    if x.shape != y.shape or x.dtype != y.dtype:
        print(f"{name}: shape/dtype {x.shape} {x.dtype} vs {y.shape} {y.dtype}")
        continue
    diff = x != y
    n = int(diff.sum())
    if n == 0:
        print(f"{name}: equal {x.shape} {x.dtype}")
    else:
        d = np.abs(x.astype(np.float64) - y.astype(np.float64))
        print(f"{name}: {n} of {x.size} differ, max |diff| {d.max():.3g} {x.shape} {x.dtype}")

# Mixture files: does each kept slot point at the same codebook row content in both (the same
# embeddings, whatever order the codebook rows are stored in)?
if all(k in a and k in b for k in ("codebook", "atoms")):
    ids = {}
    content = lambda book: np.array([ids.setdefault(r.tobytes(), len(ids)) for r in book] + [-1])
    ca, cb = content(a["codebook"]), content(b["codebook"])
    unused = np.iinfo(a["atoms"].dtype).max
    slot = lambda atoms, c: c[np.where(atoms == unused, len(c) - 1, atoms).astype(np.int64)]
    same = int((slot(a["atoms"], ca) == slot(b["atoms"], cb)).sum())
    print(f"atoms by codebook row content: {same} of {a['atoms'].size} slots agree")
