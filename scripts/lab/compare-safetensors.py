#!/usr/bin/env python3
"""Compares two .safetensors files tensor by tensor (a device harness, not part of CI).

Usage: compare-safetensors.py A B
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
