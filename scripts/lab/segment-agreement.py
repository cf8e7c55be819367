#!/usr/bin/env python3
"""How far one segmentation of a scene's Gaussians is from another (numpy only; NOT part of CI).

Usage: segment-agreement.py REFERENCE.safetensors OTHER.safetensors [...]

Each file is a `segments.safetensors` (tensor `segments`, u32 [N]). For each OTHER it prints the
segment counts and two purities over the N Gaussians:
  purity      Σ over OTHER's segments of their largest overlap with one REFERENCE segment, / N
              (1 − purity: the share of Gaussians that OTHER merged into a segment of another);
  coverage    the same with the roles swapped (1 − coverage: the share that OTHER split off).
Used to measure what the segmentation's tiles cost against one tile (the exact order).
"""
import json
import struct
import sys

import numpy as np


def segments(path):
    with open(path, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        header = json.loads(f.read(n))
        t = header["segments"]
        assert t["dtype"] == "U32", t
        a, b = t["data_offsets"]
        f.seek(8 + n + a)
        return np.frombuffer(f.read(b - a), dtype=np.uint32)


def purity(a, b):
    """Σ over a's segments of the largest overlap with one of b's, / N."""
    key = a.astype(np.uint64) * np.uint64(int(b.max()) + 1) + b.astype(np.uint64)
    pairs, counts = np.unique(key, return_counts=True)
    owner = pairs // np.uint64(int(b.max()) + 1)
    order = np.lexsort((-counts, owner))
    first = np.ones(len(order), dtype=bool)
    first[1:] = owner[order][1:] != owner[order][:-1]
    return counts[order][first].sum() / len(a)


ref = segments(sys.argv[1])
print(f"reference {sys.argv[1]}: {len(np.unique(ref))} segments over {len(ref)} Gaussians")
for path in sys.argv[2:]:
    s = segments(path)
    assert len(s) == len(ref), (path, len(s), len(ref))
    print(f"{path}: {len(np.unique(s))} segments, purity {purity(s, ref):.4f}, "
          f"coverage {purity(ref, s):.4f}")
