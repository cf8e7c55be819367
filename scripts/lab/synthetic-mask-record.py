#!/usr/bin/env python3
"""Writes a synthetic masks' record (mask-record.safetensors) for a scene's .ply, to time
`slag-encoder segment` at any size without an encode.

Each Gaussian is seen in 6 to 8 of `views` views (8 slots). In each view its mask is the cell
of a grid over the means, shifted per view, so masks are coherent in space the way a real
record's are; a_kj is random in (1, 100) raster pixels. Slots follow the record's order
(a_kj descending, then view ascending).

Usage: synthetic-mask-record.py SCENE/point_cloud.ply OUT.safetensors [views] [cell] [seed]
(`cell`: mask cell side in scene units, default 2.0; numpy only.)
"""
import json
import struct
import sys

import numpy as np

EMPTY = 0xFFFF
SLOTS = 8


def read_means(path):
    with open(path, "rb") as f:
        header = b""
        while not header.endswith(b"end_header\n"):
            header += f.readline()
        lines = header.decode().splitlines()
        n = next(int(l.split()[2]) for l in lines if l.startswith("element vertex"))
        props = [l.split()[2] for l in lines if l.startswith("property float")]
        data = np.fromfile(f, dtype="<f4", count=n * len(props)).reshape(n, len(props))
    return data[:, [props.index("x"), props.index("y"), props.index("z")]]


def main():
    ply, out = sys.argv[1], sys.argv[2]
    views = int(sys.argv[3]) if len(sys.argv) > 3 else 16
    cell = float(sys.argv[4]) if len(sys.argv) > 4 else 2.0
    rng = np.random.default_rng(int(sys.argv[5]) if len(sys.argv) > 5 else 1)
    means = read_means(ply)
    n = len(means)
    # Views each Gaussian is seen in: a random 6 to 8 of them.
    seen = rng.integers(6, SLOTS + 1, n)
    keys = rng.random((n, views))
    order = np.argsort(keys, axis=1)[:, :SLOTS].astype(np.int64)
    shift = rng.random((views, 3)) * cell
    weights = (1.0 + 99.0 * rng.random((n, SLOTS))).astype(np.float32)
    masks = np.zeros((n, SLOTS), dtype=np.uint16)
    for s in range(SLOTS):
        v = order[:, s]
        c = np.floor((means + shift[v]) / cell).astype(np.int64)
        h = (c[:, 0] * 73856093) ^ (c[:, 1] * 19349663) ^ (c[:, 2] * 83492791) ^ (v * 2654435761)
        masks[:, s] = (h % 4096).astype(np.uint16)
    slot_views = order.astype(np.uint16)
    unused = np.arange(SLOTS)[None, :] >= seen[:, None]
    weights[unused] = -1.0
    # a_kj descending, then view ascending; unused slots last.
    idx = np.lexsort((slot_views, -weights), axis=1)
    take = lambda a: np.take_along_axis(a, idx, axis=1)
    slot_views, masks, weights = take(slot_views), take(masks), take(weights)
    unused = weights < 0
    slot_views[unused], masks[unused], weights[unused] = EMPTY, 0, 0.0
    tensors = [("views", "U16", slot_views), ("masks", "U16", masks), ("weights", "F32", weights)]
    header, blobs, at = {}, [], 0
    for name, dtype, a in tensors:
        b = np.ascontiguousarray(a).tobytes()
        header[name] = {"dtype": dtype, "shape": [n, SLOTS], "data_offsets": [at, at + len(b)]}
        blobs.append(b)
        at += len(b)
    header["__metadata__"] = {
        "format": "slag-mask-record",
        "version": "1",
        "scene_gaussians": str(n),
        "slots": str(SLOTS),
        "views": str(views),
    }
    h = json.dumps(header).encode()
    h += b" " * (-len(h) % 8)
    with open(out, "wb") as f:
        f.write(struct.pack("<Q", len(h)))
        f.write(h)
        for b in blobs:
            f.write(b)
    print(json.dumps({"gaussians": n, "views": views, "slots": SLOTS, "cell": cell}))


if __name__ == "__main__":
    main()
