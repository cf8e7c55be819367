#!/usr/bin/env python3
"""Checks what `slag-encoder partition --qdrant-url` wrote into a live Qdrant server, with the
server's own REST API only (no qdrant-client), against slag's own files.

    python3 scripts/lab/qdrant-live-check.py --rest http://127.0.0.1:6333 --collection snowmiku \
        --embeddings out/snowmiku/embeddings.safetensors --export out/snowmiku-export \
        [--tiles] [--restore-dir DIR] [--int8]

Needs numpy. Reads:
  * the embeddings file (safetensors: gaussian_ids u32[N], means f32[N,3], embeddings f32|f16[N,D]);
  * the `slag-encoder export` folder (manifest.json + shards/{tile}: ids and means per tile).
Checks, for the main collection (and with --tiles every `<collection>-tile-<id>`):
  * collection info: status (green or yellow = still indexing, with optimizer ok; waits up to
    --wait-green s for green), vector size D, Cosine distance, quantisation, points_count;
  * scrolls every point (payload + vector): id set equal to the expected one, payload exactly
    {id, x, y, z, tile} with id == point id, x/y/z narrowed to f32 == the f32 mean (bit-exact;
    how many f64 values are not the widened f32, and by how many ulp, is reported),
    tile == the shard holding the Gaussian; vector == the f32 embedding normalised (Qdrant
    normalises for Cosine), max abs error reported;
  * 5 exact searches (stored vectors as queries) against numpy's exact cosine top-10, compared
    by score (the embeddings have many near-duplicates); the same queries through the HNSW index
    (recall@10 by score reported);
  * --tiles: one snapshot per tile collection listed by the server (name, size, sha256), one
    downloaded (size and sha256 compared) and, with --restore-dir, uploaded into a new collection
    `<collection>-restored` whose points are checked like the tile's.
Prints one line per check and a JSON summary; exits 1 if any check failed.
"""

import argparse
import hashlib
import json
import struct
import subprocess
import sys
import time
import urllib.request

import numpy as np

FAILS = []
RESULTS = {}
WAIT_GREEN = 0.0


def check(name, ok, detail=""):
    print(f"{'PASS' if ok else 'FAIL'} {name}{': ' + detail if detail else ''}", flush=True)
    if not ok:
        FAILS.append(name)
    return ok


def http(rest, method, path, body=None, raw=False):
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(rest + path, data=data, method=method)
    if data is not None:
        req.add_header("Content-Type", "application/json")
    with urllib.request.urlopen(req, timeout=600) as r:
        b = r.read()
    return b if raw else json.loads(b)


def read_safetensors(path):
    with open(path, "rb") as f:
        buf = f.read()
    (hlen,) = struct.unpack("<Q", buf[:8])
    header = json.loads(buf[8 : 8 + hlen])
    base = 8 + hlen
    dt = {"F32": np.float32, "F16": np.float16, "U32": np.uint32}
    out = {}
    for k, v in header.items():
        if k == "__metadata__":
            continue
        a, b = v["data_offsets"]
        out[k] = np.frombuffer(buf[base + a : base + b], dtype=dt[v["dtype"]]).reshape(v["shape"])
    return out, header.get("__metadata__", {})


def read_shard(path):
    """Ids and means of one shard (format v1, see common/src/shards/format.rs)."""
    with open(path, "rb") as f:
        b = f.read()
    assert b[:8] == b"SLAGSHRD", path
    dim, n, hlen = struct.unpack_from("<III", b, 12)
    (tile,) = struct.unpack_from("<Q", b, 24)
    ids = np.frombuffer(b, dtype="<u4", count=n, offset=hlen)
    means = np.frombuffer(b, dtype="<f4", count=3 * n, offset=hlen + 4 * n).reshape(n, 3)
    return tile, dim, ids, means


def scroll_all(rest, coll, page=2000):
    """Every point of `coll` (id -> (payload, vector)), by the REST scroll API."""
    pts, offset, pages = {}, None, 0
    while True:
        body = {"limit": page, "with_payload": True, "with_vector": True}
        if offset is not None:
            body["offset"] = offset
        r = http(rest, "POST", f"/collections/{coll}/points/scroll", body)["result"]
        pages += 1
        for p in r["points"]:
            if p["id"] in pts:
                raise SystemExit(f"scroll of {coll} returned point {p['id']} twice")
            pts[p["id"]] = (p["payload"], p["vector"])
        offset = r.get("next_page_offset")
        if offset is None:
            return pts, pages


def check_collection(rest, coll, rows, ids, means, unit, tile_of, dim, int8, label=None):
    """Checks collection `coll` holds exactly source rows `rows` (info, ids, payloads, vectors)."""
    label = label or coll
    t0 = time.time()
    while True:
        info = http(rest, "GET", f"/collections/{coll}")["result"]
        if info["status"] == "green" or time.time() - t0 >= WAIT_GREEN:
            break
        time.sleep(10)
    params = info["config"]["params"]["vectors"]
    q = info["config"].get("quantization_config")
    # green = idle; yellow = the server is still optimising (building the HNSW index): not an
    # upload fault, reported with the indexed count. red / optimizer error = failure.
    check(
        f"{label} status / optimizer",
        info["status"] in ("green", "yellow") and info["optimizer_status"] == "ok",
        f"{info['status']} after {time.time() - t0:.0f} s wait, optimizer {info['optimizer_status']}, "
        f"indexed_vectors_count {info.get('indexed_vectors_count')}, segments {info['segments_count']}",
    )
    check(
        f"{label} vector params",
        params.get("size") == dim and params.get("distance") == "Cosine",
        f"size {params.get('size')} (want {dim}), distance {params.get('distance')}",
    )
    if int8:
        sq = (q or {}).get("scalar", {})
        ok = sq.get("type") == "int8" and sq.get("quantile") == 0.99 and sq.get("always_ram") is True
    else:
        ok = q is None
    check(f"{label} quantization_config", ok, json.dumps(q))
    check(f"{label} points_count", info["points_count"] == len(rows),
          f"{info['points_count']} (want {len(rows)})")
    t = time.time()
    pts, pages = scroll_all(rest, coll)
    secs = time.time() - t
    want = {int(ids[r]): r for r in rows}
    got = set(pts)
    check(
        f"{label} scrolled ids",
        got == set(want),
        f"{len(got)} points in {pages} pages ({secs:.1f} s); "
        f"missing {len(set(want) - got)}, unexpected {len(got - set(want))}",
    )
    bad_keys = bad_id = bad_xyz = bad_tile = 0
    ulp_off, max_ulp = 0, 0  # f64 payload coordinates not bit-equal to the widened f32 mean
    max_err, norm_dev = 0.0, 0.0
    for pid, (payload, vec) in pts.items():
        r = want.get(pid)
        if r is None:
            continue
        if set(payload) != {"id", "x", "y", "z", "tile"}:
            bad_keys += 1
            continue
        if not (isinstance(payload["id"], int) and payload["id"] == pid == int(ids[r])):
            bad_id += 1
        m = means[r]
        got_xyz = [payload["x"], payload["y"], payload["z"]]
        # slag sends f64::from(f32) exactly; Qdrant 1.18 keeps payloads as JSON text and reads
        # them back with serde_json's default (not float_roundtrip) parser, which can land one
        # f64 ulp away. Narrowed back to f32 the value must be the mean, bit for bit.
        if any(np.float32(g) != m[i] for i, g in enumerate(got_xyz)):
            bad_xyz += 1
        for i, g in enumerate(got_xyz):
            d = abs(struct.unpack("<q", struct.pack("<d", g))[0] - struct.unpack("<q", struct.pack("<d", float(m[i])))[0])
            if d:
                ulp_off += 1
                max_ulp = max(max_ulp, d)
        if payload["tile"] != tile_of[r]:
            bad_tile += 1
        v = np.asarray(vec, dtype=np.float64)
        if v.shape != (dim,):
            max_err = float("inf")
            continue
        max_err = max(max_err, float(np.max(np.abs(v - unit[r]))))
        norm_dev = max(norm_dev, abs(float(np.linalg.norm(v)) - 1.0))
    check(f"{label} payload keys == {{id,x,y,z,tile}}", bad_keys == 0, f"{bad_keys} points differ")
    check(f"{label} payload id == point id == gaussian id", bad_id == 0, f"{bad_id} points differ")
    check(
        f"{label} payload x,y,z == f32 mean (as f32, bit-exact)",
        bad_xyz == 0,
        f"{bad_xyz} points differ; as f64, {ulp_off} of {3 * len(pts)} coordinates are not the widened "
        f"f32 (max {max_ulp} f64 ulp off)",
    )
    check(f"{label} payload tile == shard of the Gaussian", bad_tile == 0, f"{bad_tile} points differ")
    check(
        f"{label} vectors == normalised f32 embedding",
        max_err <= 1e-6,
        f"max |diff| {max_err:.3g} over {len(pts)}x{dim}; max | |v| - 1 | {norm_dev:.3g}",
    )
    RESULTS[label] = {
        "points_count": info["points_count"],
        "scrolled": len(pts),
        "scroll_pages": pages,
        "scroll_s": round(secs, 1),
        "max_abs_vector_diff": max_err,
        "max_norm_dev": norm_dev,
        "status": info["status"],
        "indexed_vectors_count": info.get("indexed_vectors_count"),
        "bad": {"keys": bad_keys, "id": bad_id, "xyz": bad_xyz, "tile": bad_tile},
        "xyz_f64_coords_off": ulp_off,
        "xyz_f64_max_ulp": max_ulp,
    }
    return pts


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rest", default="http://127.0.0.1:6333")
    ap.add_argument("--collection", required=True)
    ap.add_argument("--embeddings", required=True)
    ap.add_argument("--export", required=True)
    ap.add_argument("--tiles", action="store_true")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--restore-dir")
    ap.add_argument("--wait-green", type=float, default=0,
                    help="seconds to wait for each collection's status to turn green (index built)")
    a = ap.parse_args()
    global WAIT_GREEN
    WAIT_GREEN = a.wait_green

    t, meta = read_safetensors(a.embeddings)
    ids = t["gaussian_ids"]
    means = t["means"]
    emb = t["embeddings"].astype(np.float32)
    n, dim = emb.shape
    print(f"embeddings: {n} Gaussians, dim {dim}, stored {t['embeddings'].dtype}")
    # What the upload sends is the f32 row; Qdrant normalises it for Cosine (in f32).
    norms = np.linalg.norm(emb, axis=1, keepdims=True)
    unit = (emb / norms).astype(np.float32).astype(np.float64)
    print(f"embedding norms: min {norms.min():.7f} max {norms.max():.7f}")

    manifest = json.load(open(f"{a.export}/manifest.json"))
    row_of = {int(g): r for r, g in enumerate(ids)}
    tile_of = np.full(n, -1, dtype=np.int64)
    tile_rows = {}
    for te in manifest["tiles"]:
        tid, sdim, sids, smeans = read_shard(f"{a.export}/shards/{te['id']}")
        assert tid == te["id"] and sdim == dim and len(sids) == te["count"]
        rows = [row_of[int(g)] for g in sids]
        tile_of[rows] = tid
        tile_rows[tid] = rows
        assert np.array_equal(smeans, means[rows]), f"shard {tid} means differ from the embeddings file"
    check("every Gaussian in exactly one shard", (tile_of >= 0).all() and sum(map(len, tile_rows.values())) == n,
          f"{len(tile_rows)} tiles, {sum(map(len, tile_rows.values()))} rows")

    all_rows = list(range(n))
    check_collection(a.rest, a.collection, all_rows, ids, means, unit, tile_of, dim, a.int8)

    # Searches by the server against exact cosine in numpy. The stand-in embeddings have many
    # near-duplicates (hundreds of rows within 1e-4 cosine of one another), so ranks are compared
    # by score, not by id: the true cosines of the ids the server returns must be numpy's top-10
    # cosines (exact search), and for HNSW the share of returned ids at or above numpy's 10th
    # best cosine is reported (recall by score), with the largest shortfall.
    qrows = [int(r) for r in np.linspace(0, n - 1, 5)]
    worst, hn_recall, hn_short = 0.0, [], 0.0
    for qrow in qrows:
        sims = unit @ unit[qrow]
        top = np.sort(sims)[::-1][:10]
        hits = http(a.rest, "POST", f"/collections/{a.collection}/points/query",
                    {"query": emb[qrow].tolist(), "limit": 10, "params": {"exact": True}})["result"]["points"]
        true = np.sort([sims[row_of[h["id"]]] for h in hits])[::-1]
        srv = np.sort([h["score"] for h in hits])[::-1]
        worst = max(worst, float(np.max(np.abs(true - top))), float(np.max(np.abs(srv - top))))
        hn = http(a.rest, "POST", f"/collections/{a.collection}/points/query",
                  {"query": emb[qrow].tolist(), "limit": 10})["result"]["points"]
        ht = np.array([sims[row_of[h["id"]]] for h in hn])
        hn_recall.append(float(np.mean(ht >= top[-1] - 1e-6)))
        hn_short = max(hn_short, float(top[-1] - ht.min()))
    check(f"exact search top-10 == numpy cosine top-10 ({len(qrows)} queries, by score)", worst <= 1e-5,
          f"max |server or returned-id cosine - numpy top-10 cosine| {worst:.3g}")
    print(f"INFO HNSW search (default params) recall@10 by score over {len(qrows)} queries: "
          f"{np.mean(hn_recall):.3f} (per query {hn_recall}); largest shortfall below numpy's 10th best {hn_short:.3g}")
    RESULTS["exact_search_max_diff"] = worst
    RESULTS["hnsw_recall_at_10_by_score"] = hn_recall
    RESULTS["hnsw_max_shortfall"] = hn_short

    if a.tiles:
        colls = {c["name"] for c in http(a.rest, "GET", "/collections")["result"]["collections"]}
        names = {tid: f"{a.collection}-tile-{tid}" for tid in tile_rows}
        check("one collection per tile", set(names.values()) <= colls,
              f"{len(set(names.values()) & colls)} of {len(names)} present; {len(colls)} collections on the server")
        snaps = {}
        for tid, name in sorted(names.items()):
            check_collection(a.rest, name, tile_rows[tid], ids, means, unit, tile_of, dim, a.int8)
            s = http(a.rest, "GET", f"/collections/{name}/snapshots")["result"]
            snaps[name] = s
        one = [len(s) == 1 and s[0]["size"] > 0 for s in snaps.values()]
        sizes = [s[0]["size"] for s in snaps.values() if s]
        check("one non-empty snapshot per tile collection", all(one),
              f"{sum(one)} of {len(one)}; sizes {min(sizes)}-{max(sizes)} bytes, total {sum(sizes)}")
        RESULTS["snapshots"] = {k: v for k, v in snaps.items()}
        # Download the largest tile's snapshot, compare size and sha256, restore it.
        big = max(tile_rows, key=lambda t: len(tile_rows[t]))
        name = names[big]
        sd = snaps[name][0]
        blob = http(a.rest, "GET", f"/collections/{name}/snapshots/{sd['name']}", raw=True)
        sha = hashlib.sha256(blob).hexdigest()
        check(f"download {sd['name']}", len(blob) == sd["size"] and (sd.get("checksum") in (None, sha)),
              f"{len(blob)} bytes (listed {sd['size']}), sha256 {sha[:16]}... (listed {str(sd.get('checksum'))[:16]}...)")
        if a.restore_dir:
            path = f"{a.restore_dir}/{sd['name']}"
            with open(path, "wb") as f:
                f.write(blob)
            target = f"{a.collection}-restored"
            if target in colls:
                http(a.rest, "DELETE", f"/collections/{target}")
            t0 = time.time()
            out = subprocess.run(
                ["curl", "-sS", "-X", "POST",
                 f"{a.rest}/collections/{target}/snapshots/upload?priority=snapshot&wait=true&checksum={sha}",
                 "-F", f"snapshot=@{path}"], capture_output=True, text=True, check=True).stdout
            ok = json.loads(out).get("result") is True
            check(f"restore {sd['name']} into {target}", ok, f"{out.strip()[:200]} ({time.time() - t0:.1f} s)")
            if ok:
                check_collection(a.rest, target, tile_rows[big], ids, means, unit, tile_of, dim, a.int8,
                                 label=f"{target} (from tile {big})")
            RESULTS["restored"] = {"tile": int(big), "snapshot": sd["name"], "bytes": len(blob), "sha256": sha}

    print(json.dumps({"failed": FAILS, "results": RESULTS}, indent=1, default=str))
    sys.exit(1 if FAILS else 0)


if __name__ == "__main__":
    main()
