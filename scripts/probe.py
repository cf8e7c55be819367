#!/usr/bin/env python3
"""Hostile-client probe of `slag-shards serve` and `slag-edge serve` on loopback (127.0.0.1, and
127.0.0.2 as a second client).

Run through scripts/probe.sh, which builds or takes the binaries and makes the fixture. Every case
is bounded in time and count; prints `case | expected | observed | pass/fail` and RSS figures, and
exits 1 when a case fails. Standard library only.
"""
import argparse
import json
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

HOST = "127.0.0.1"
# A second loopback address: a well-behaved client beside the flooding one on HOST (Linux routes
# all of 127.0.0.0/8 to lo). The servers give each address its own share of the slots.
OTHER = "127.0.0.2"
TOKEN = "probe-token"
ROWS = []
FIVEXX = [0]


SHORT = [False]


def row(case, expected, observed, ok, goal=False):
    """One table row; a memory goal (`goal`) is reported but not failed in the short (CI) form,
    whose small scene and loaded machine make RSS a figure, not a verdict."""
    verdict = "pass" if ok else ("info" if goal and SHORT[0] else "FAIL")
    ROWS.append((case, expected, observed, verdict))
    print(f"  {case}: {observed} -> {verdict}", flush=True)


def rss_mb(pid):
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def settled_rss(pid, bound_s=30.0, min_s=12.0):
    """RSS once it has settled: sampled every second for at least `min_s` seconds (an allocator
    that hands freed pages back after a decay time, 10 s for jemalloc's, has then done so), then
    until it moved by under 1 % over the last 3 s, at most `bound_s` seconds."""
    samples, t0 = [rss_mb(pid)], time.time()
    while time.time() - t0 < bound_s:
        time.sleep(1)
        samples.append(rss_mb(pid))
        last = samples[-4:]
        if (time.time() - t0 >= min_s and len(last) == 4
                and max(last) - min(last) < 0.01 * last[-1]):
            break
    return samples[-1]


def fds(pid):
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return -1


class Peak:
    """Samples a process's RSS every 20 ms in a thread; `.peak` is the largest seen."""

    def __init__(self, pid):
        self.pid, self.peak, self.stop = pid, rss_mb(pid), False
        self.t = threading.Thread(target=self.run, daemon=True)
        self.t.start()

    def run(self):
        while not self.stop:
            r = rss_mb(self.pid)
            if r == r:
                self.peak = max(self.peak, r)
            time.sleep(0.02)

    def done(self):
        self.stop = True
        self.t.join()
        return self.peak


def request(port, method, path, body=None, headers=None, timeout=60.0, raw=None, source=None):
    """One request on a fresh connection: (status, headers dict lower-case, body bytes).
    `source`: the local address to connect from (OTHER is another client to the servers'
    per-address share of the connection slots)."""
    s = socket.create_connection((HOST, port), timeout=timeout,
                                 source_address=(source, 0) if source else None)
    try:
        if raw is None:
            h = {"Host": f"{HOST}:{port}", "Connection": "close"}
            h.update(headers or {})
            data = b"" if body is None else body
            if body is not None:
                h["Content-Length"] = str(len(data))
            raw = (f"{method} {path} HTTP/1.1\r\n"
                   + "".join(f"{k}: {v}\r\n" for k, v in h.items()) + "\r\n").encode() + data
        s.sendall(raw)
        out = bytearray()
        while True:
            try:
                chunk = s.recv(1 << 16)
            except ConnectionResetError:
                break
            if not chunk:
                break
            out += chunk
    finally:
        s.close()
    head, _, rest = bytes(out).partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split(" ")[1]) if lines and len(lines[0].split(" ")) > 1 else 0
    hdrs = {}
    for line in lines[1:]:
        k, _, v = line.partition(":")
        hdrs[k.strip().lower()] = v.strip()
    if hdrs.get("transfer-encoding") == "chunked":
        body_b, buf = bytearray(), rest
        while buf:
            n, _, buf = buf.partition(b"\r\n")
            n = int(n or b"0", 16)
            if n == 0:
                break
            body_b += buf[:n]
            buf = buf[n + 2:]
        rest = bytes(body_b)
    if status >= 500:
        FIVEXX[0] += 1
    return status, hdrs, rest


def auth(extra=None):
    h = {"Authorization": f"Bearer {TOKEN}"}
    h.update(extra or {})
    return h


def json_error(status, hdrs, body):
    try:
        v = json.loads(body)
    except ValueError:
        return False
    return hdrs.get("content-type", "").startswith("application/json") and v.get("status") == status


def wait_up(port, path, proc, secs=120):
    t0 = time.time()
    while time.time() - t0 < secs:
        if proc.poll() is not None:
            return False
        try:
            st, _, _ = request(port, "GET", path, headers=auth(), timeout=5)
            if st == 200:
                return True
        except OSError:
            pass
        time.sleep(0.2)
    return False


def start(cmd, env_extra=None, nofile=None, log=None):
    env = dict(os.environ)
    env.update(env_extra or {})
    env.setdefault("RUST_LOG", "warn")

    def pre():
        os.setsid()
        if nofile:
            resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

    return subprocess.Popen(cmd, env=env, preexec_fn=pre, stdout=log or subprocess.DEVNULL,
                            stderr=log or subprocess.DEVNULL)


def stop(proc):
    if proc and proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def supports(binary, sub, flag):
    out = subprocess.run([binary, sub, "--help"], capture_output=True, text=True).stdout
    return flag in out


def stalled(port, n, line):
    socks = []
    for _ in range(n):
        try:
            s = socket.socket()
            s.setblocking(True)
            s.settimeout(10)
            s.connect((HOST, port))
            s.sendall(line)
            socks.append(s)
        except OSError:
            s.close()
            break
    return socks


def count_closed(socks, bound_s):
    """Sockets the server closed within `bound_s` seconds (EOF or reset on read)."""
    closed, t0 = set(), time.time()
    for s in socks:
        s.setblocking(False)
    while time.time() - t0 < bound_s and len(closed) < len(socks):
        for i, s in enumerate(socks):
            if i in closed:
                continue
            try:
                if s.recv(4096) == b"":
                    closed.add(i)
            except BlockingIOError:
                pass
            except OSError:
                closed.add(i)
        time.sleep(0.2)
    for s in socks:
        s.close()
    return len(closed), time.time() - t0


def slow_readers(port, n, raw):
    socks = []
    for _ in range(n):
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.connect((HOST, port))
        s.sendall(raw)
        socks.append(s)
    return socks


def batch(n, k):
    q = [{"text": f"probe {i}", "top_k": k, "threshold": "none"} for i in range(n)]
    return json.dumps({"queries": q}).encode()


def post_raw(port, body):
    return (f"POST /query HTTP/1.1\r\nHost: {HOST}\r\nAuthorization: Bearer {TOKEN}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n").encode() + body


# ---- Stalled bodies, credentials in URLs, strict inputs (self-contained cases) ----------------

# With the token, so the request gets past authentication and its body is read.
STALLED_BODY = (f"POST /query HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n"
                "Content-Type: application/json\r\nContent-Length: 60000\r\n\r\n"
                '{"queries": ').encode()
SECRET = "probe-password-7c1e"


def stall_bodies(port, n, head):
    """`n` connections that each send `head` (a whole request head and the first bytes of its
    body) and then nothing. Connections the server refuses at once (its per-address share) are
    kept too: they count as closed. Returns the sockets."""
    socks = []
    for _ in range(n):
        s = socket.socket()
        s.settimeout(10)
        try:
            s.connect((HOST, port))
            s.sendall(head)
        except OSError:
            pass
        socks.append(s)
    return socks


def timed_status(port, path, source, headers=None):
    """(status or 'error …', seconds) of one GET from `source`."""
    t0 = time.time()
    try:
        st = request(port, "GET", path, headers=headers, timeout=60, source=source)[0]
    except OSError as e:
        st = f"error {e.__class__.__name__}"
    return st, time.time() - t0


def case_stalled_bodies(ep, sp, n, other):
    """`n` stalled request bodies (a whole head announcing 60,000 bytes, 12 sent) from HOST:
    /health from another address answers in under 1 s, the same address is answered at once too
    (429 while its share is full), and every stalled body is closed within the body timeout
    (3 s in the probe) plus a margin. Then the same against the shard server."""
    socks = stall_bodies(ep, n, STALLED_BODY)
    hs, h_s = timed_status(ep, "/health", other)
    same, same_s = timed_status(ep, "/health", HOST)
    closed, took = count_closed(socks, 20)
    row(f"{n} stalled bodies, edge",
        f"/health from {other} 200 in < 1 s; from {HOST} answered in < 1 s (429 while its share "
        "is full); all closed by the body timeout",
        f"/health {hs} after {h_s:.2f} s; same address {same} after {same_s:.2f} s; "
        f"{closed}/{len(socks)} closed in {took:.0f} s",
        hs == 200 and h_s < 1.0 and same in (200, 429) and same_s < 1.0 and closed == len(socks))
    head = STALLED_BODY.replace(b"POST /query", b"GET /v1/scenes")
    socks = stall_bodies(sp, n // 2, head)
    ss, s_s = timed_status(sp, "/v1/scenes", other, headers=auth())
    closed, took = count_closed(socks, 20)
    row(f"{n // 2} stalled bodies, shard server",
        f"/v1/scenes from {other} 200 in < 1 s; all closed by the body timeout",
        f"/v1/scenes {ss} after {s_s:.2f} s; {closed}/{len(socks)} closed in {took:.0f} s",
        ss == 200 and s_s < 1.0 and closed == len(socks))


def store_holds(root, needles):
    """Files under `root` that hold one of `needles` (bytes search), as relative paths."""
    found = []
    for d, _, files in os.walk(root):
        for f in files:
            p = os.path.join(d, f)
            try:
                data = open(p, "rb").read()
            except OSError:
                continue
            if any(x.encode() in data for x in needles):
                found.append(os.path.relpath(p, root))
    return found


def case_credentials(edge_bin, ep, sp, store, work):
    """A shard-server URL with a password, through POST /fetch and `slag-edge fetch --from`:
    refused (400 / exit != 0) without the password in the answer; neither the password nor the
    bearer token in /stats or any file of the store (fetch.json included)."""
    url = f"http://robot:{SECRET}@{HOST}:{sp}"
    body = json.dumps({"center": [0, 0], "radius": 100000, "server": url}).encode()
    st, _, b = request(ep, "POST", "/fetch", body=body,
                       headers=auth({"Content-Type": "application/json"}), timeout=120)
    stats = request(ep, "GET", "/stats", headers=auth())[2].decode("utf-8", "replace")
    shown = [w for w, x in [("password", SECRET), ("token", TOKEN)] if x in stats]
    stored = store_holds(store, [SECRET, TOKEN])
    row("POST /fetch, server URL with a password",
        "400; password and token in neither the answer, /stats nor the store (fetch.json)",
        f"{st}; answer {'shows' if SECRET.encode() in b else 'hides'} the password; /stats "
        f"shows {shown or 'neither'}; stored in {stored or 'no file'}",
        st == 400 and SECRET.encode() not in b and not shown and not stored)
    d = os.path.join(work, "cred-store")
    r = subprocess.run([edge_bin, "fetch", "--from", url, "--scene", "probe", "--center", "0,0",
                        "--radius", "100000", "--store", d],
                       env={**os.environ, "SLAG_SHARD_TOKEN": TOKEN}, capture_output=True,
                       text=True, timeout=120)
    stored = store_holds(d, [SECRET]) if os.path.isdir(d) else []
    row("slag-edge fetch --from URL with a password",
        "refused; password not printed, not stored",
        f"exit {r.returncode}; output {'shows' if SECRET in r.stdout + r.stderr else 'hides'} "
        f"the password; stored in {stored or 'no file'}",
        r.returncode != 0 and SECRET not in r.stdout + r.stderr and not stored)


def case_strict_inputs(ep, sp):
    """`text` that is not a JSON string, query strings that are not UTF-8, two Authorization
    headers on both servers."""
    for kind, text in [("object", {"a": 1}), ("array", ["red"]), ("true", True), ("number", 5)]:
        body = json.dumps({"queries": [{"text": text}]}).encode()
        st, _, b = request(ep, "POST", "/query", body=body,
                           headers=auth({"Content-Type": "application/json"}))
        row(f"text as a JSON {kind}", "400 naming text", f"{st} {b[:90]!r}",
            st == 400 and b"text" in b)
    for path in ["/query?text=%FF", "/query?text=caf%C3", "/query.ply?text=%FF"]:
        st, _, b = request(ep, "GET", path, headers=auth())
        row(f"GET {path}", "400 naming text (not U+FFFD)", f"{st} {b[:90]!r}",
            st == 400 and b"text" in b)
    two = f"Authorization: Bearer {TOKEN}\r\n" * 2
    for port, name, path in [(ep, "edge", "/stats"), (sp, "shards", "/v1/scenes")]:
        raw = f"GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n{two}\r\n".encode()
        st = request(port, "GET", path, raw=raw)[0]
        row(f"two Authorization headers, {name}", "401", str(st), st == 401)
def store_integrity_cases(a, W, sp, port, short):
    """The store's integrity cases: reload racing fetch (every state seen is a committed one), a
    manifest that lists a tile twice (refused before anything is stored), a FIFO, a symlink to
    /dev/zero and a dangling symlink in place of a shard (check, query and serve answer without
    hanging or reading past the manifest's size; check reports each; one fetch repairs each).
    Servers on `port` and `port + 1`; `sp` is the shard server's port."""
    fetch_env = {**os.environ, "SLAG_SHARD_TOKEN": TOKEN, "RUST_LOG": "warn"}
    check_cmd = [a.edge, "check", "--scene", "probe", "--clip-textual", a.text_model,
                 "--tokenizer", a.tokenizer]

    def fetch(store, radius, url=f"http://{HOST}:{sp}"):
        return subprocess.run([a.edge, "fetch", "--from", url, "--scene", "probe", "--center",
                               "0,0", "--radius", str(radius), "--store", store],
                              env=fetch_env, capture_output=True, text=True, timeout=120)

    # Reload racing fetch: fetch loops (a pruning small disc, then the full one), reload and
    # query loops; every answer, /stats and /health must report one of the committed counts.
    d = f"{W}/integrity-race"
    shutil.rmtree(d, ignore_errors=True)
    shutil.copytree(f"{W}/edge-pristine", d)
    srv = start([a.edge, "serve", "--store", d, "--scene", "probe", "--listen", f"{HOST}:{port}",
                 "--clip-textual", a.text_model, "--tokenizer", a.tokenizer],
                {"SLAG_EDGE_TOKEN": TOKEN})
    assert wait_up(port, "/health", srv), "edge server (race) did not start"
    committed, seen, stop_flag = set(), [], [False]
    _, _, b = request(port, "GET", "/stats", headers=auth())
    committed.add(json.loads(b)["gaussians"])

    def watch(path, field):
        while not stop_flag[0]:
            try:
                st, _, body = request(port, "GET", path, headers=auth(), timeout=30)
                if st == 200:
                    seen.append(json.loads(body)[field])
            except (OSError, ValueError):
                pass

    def reloads():
        while not stop_flag[0]:
            try:
                request(port, "POST", "/reload", body=b"", headers=auth(), timeout=60)
            except OSError:
                pass

    threads = [threading.Thread(target=watch, args=p, daemon=True) for p in
               [("/query?text=red&top_k=1&threshold=none", "searched"),
                ("/stats", "gaussians"), ("/health", "gaussians")]]
    threads.append(threading.Thread(target=reloads, daemon=True))
    for t in threads:
        t.start()
    fetch_errors = 0
    peak = Peak(srv.pid)
    t0 = time.time()
    for _ in range(3 if short else 15):
        for radius, prune in [(1, True), (100000, False)]:
            body = json.dumps({"center": [0, 0], "radius": radius, "prune": prune,
                               "token": TOKEN}).encode()
            st, _, b = request(port, "POST", "/fetch", body=body,
                               headers={**auth(), "Content-Type": "application/json"}, timeout=120)
            if st != 200:
                fetch_errors += 1
                continue
            s = json.loads(b)
            # The committed state: the disc's Gaussians with pruning; without, every tile stored.
            committed.add(s["gaussians"] if prune else max(committed))
    stop_flag[0] = True
    for t in threads:
        t.join(70)
    strays = sorted({n for n in seen if n not in committed})
    row("store: reload racing fetch (pruning small disc, full disc)",
        "every answer, /stats and /health from a committed state",
        f"{len(seen)} answers in {time.time() - t0:.0f} s, states {sorted(set(seen))}, committed "
        f"{sorted(committed)}, {fetch_errors} fetch errors, peak RSS {peak.done():.0f} MB",
        not strays and fetch_errors == 0 and len(seen) > 0)
    stop(srv)

    # A manifest that lists a tile twice: refused, nothing stored.
    _, _, mb = request(sp, "GET", "/v1/scenes/probe/manifest", headers=auth())
    m = json.loads(mb)
    m["tiles"].append(m["tiles"][0])
    doctored = json.dumps(m).encode()
    lsock = socket.socket()
    lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    lsock.bind((HOST, port + 1))
    lsock.listen(8)

    def serve_doctored():
        while True:
            try:
                c, _ = lsock.accept()
            except OSError:
                return
            try:
                c.settimeout(5)
                c.recv(65536)
                c.sendall(b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: "
                          + str(len(doctored)).encode() + b"\r\nConnection: close\r\n\r\n"
                          + doctored)
            except OSError:
                pass
            finally:
                c.close()

    threading.Thread(target=serve_doctored, daemon=True).start()
    d = f"{W}/integrity-dup"
    shutil.rmtree(d, ignore_errors=True)
    r = fetch(d, 100000, url=f"http://{HOST}:{port + 1}")
    shards_written = sum(len(f) for _, _, f in os.walk(f"{d}/shards")) if os.path.isdir(d) else 0
    lsock.close()
    row("store: manifest listing a tile twice", "fetch refused, nothing stored",
        f"fetch exit {r.returncode} ({(r.stderr.strip().splitlines() or [''])[-1][:90]}), "
        f"{shards_written} files stored",
        r.returncode != 0 and "twice" in r.stderr and shards_written == 0)

    # A FIFO, a symlink to /dev/zero, a dangling symlink in place of a shard file.
    shard_dir = None
    for root, _, files in os.walk(f"{W}/edge-pristine/shards"):
        if any(f.endswith(".shard") for f in files):
            shard_dir = root
    name = sorted(f for f in os.listdir(shard_dir) if f.endswith(".shard"))[0]
    rel = os.path.relpath(f"{shard_dir}/{name}", f"{W}/edge-pristine")
    pristine = open(f"{shard_dir}/{name}", "rb").read()
    for kind in ["fifo", "/dev/zero", "dangling symlink"]:
        d = f"{W}/integrity-{kind.strip('/').replace('/', '-').replace(' ', '-')}"
        shutil.rmtree(d, ignore_errors=True)
        shutil.copytree(f"{W}/edge-pristine", d)
        os.remove(f"{d}/{rel}")
        if kind == "fifo":
            os.mkfifo(f"{d}/{rel}")
        elif kind == "/dev/zero":
            os.symlink("/dev/zero", f"{d}/{rel}")
        else:
            os.symlink(f"{d}/nowhere.shard", f"{d}/{rel}")
        obs, ok = [], True
        try:
            c0 = subprocess.run(check_cmd + ["--store", d], capture_output=True, text=True,
                                timeout=60)
            named = "where a regular file belongs" in c0.stdout
            obs.append(f"check exit {c0.returncode}{' naming it' if named else ''}")
            ok &= c0.returncode != 0 and named
        except subprocess.TimeoutExpired:
            obs.append("check HUNG")
            ok = False
        srv = start([a.edge, "serve", "--store", d, "--scene", "probe", "--listen",
                     f"{HOST}:{port}", "--clip-textual", a.text_model, "--tokenizer", a.tokenizer],
                    {"SLAG_EDGE_TOKEN": TOKEN})
        peak = Peak(srv.pid)
        up = wait_up(port, "/health", srv, secs=60)
        qs = request(port, "GET", "/query?text=red&top_k=1", headers=auth(), timeout=30)[0] \
            if up else 0
        rss = peak.done()
        stop(srv)
        obs.append(f"serve /health {'200' if up else 'NO ANSWER'}, query {qs}, peak RSS "
                   f"{rss:.0f} MB")
        ok &= up and qs == 200 and rss < 1024
        r = fetch(d, 100000)
        restored = (os.path.isfile(f"{d}/{rel}") and not os.path.islink(f"{d}/{rel}")
                    and open(f"{d}/{rel}", "rb").read() == pristine)
        c1 = subprocess.run(check_cmd + ["--store", d], capture_output=True, text=True,
                            timeout=60)
        obs.append(f"fetch exit {r.returncode}, file {'restored' if restored else 'NOT restored'}"
                   f", check after exit {c1.returncode}")
        ok &= r.returncode == 0 and restored and c1.returncode == 0
        row(f"store: {kind} in place of a shard file",
            "check/serve answer and name it; RSS bounded; one fetch repairs", "; ".join(obs), ok)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--edge", required=True)
    ap.add_argument("--shards", required=True)
    ap.add_argument("--work", required=True)
    ap.add_argument("--text-model", required=True)
    ap.add_argument("--tokenizer", required=True)
    ap.add_argument("--short", action="store_true")
    ap.add_argument("--skip-store", action="store_true")
    ap.add_argument("--rss-only", action="store_true",
                    help="only the memory cases (huge and worst accepted request), for comparing "
                         "allocators through SLAG_PROBE_PRELOAD (LD_PRELOAD of the edge server)")
    ap.add_argument("--port", type=int, default=18190)
    a = ap.parse_args()
    SHORT[0] = a.short
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    n_stall = 300 if a.short else 2000
    hold = 8 if a.short else 20
    sp, ep = a.port, a.port + 1
    W = a.work
    log = open(os.path.join(W, "servers.log"), "ab")
    new_flags = supports(a.edge, "serve", "--header-timeout")
    timeouts_e = ["--header-timeout", "3", "--write-timeout", "3"] if new_flags else []
    timeouts_s = (["--header-timeout", "3", "--write-timeout", "3"]
                  if supports(a.shards, "serve", "--header-timeout") else [])
    if supports(a.edge, "serve", "--body-timeout"):
        timeouts_e += ["--body-timeout", "3"]
    if supports(a.shards, "serve", "--body-timeout"):
        timeouts_s += ["--body-timeout", "3"]
    print(f"probe: {'short' if a.short else 'full'}; {n_stall} stalled sockets; edge "
          f"{'with' if new_flags else 'without'} timeout flags", flush=True)

    shard_cmd = [a.shards, "serve", "--shard-store", f"{W}/shards", "--listen", f"{HOST}:{sp}"] + timeouts_s
    shards = start(shard_cmd, {"SLAG_SHARD_TOKEN": TOKEN}, nofile=1024, log=log)
    assert wait_up(sp, "/v1/scenes", shards), "shard server did not start"
    r = subprocess.run([a.edge, "fetch", "--from", f"http://{HOST}:{sp}", "--scene", "probe",
                        "--center", "0,0", "--radius", "100000", "--store", f"{W}/edge"],
                       env={**os.environ, "SLAG_SHARD_TOKEN": TOKEN}, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    shutil.copytree(f"{W}/edge", f"{W}/edge-pristine", dirs_exist_ok=True)
    edge_cmd = [a.edge, "serve", "--store", f"{W}/edge", "--scene", "probe", "--listen",
                f"{HOST}:{ep}", "--clip-textual", a.text_model, "--tokenizer", a.tokenizer] + timeouts_e
    edge_env = {"SLAG_EDGE_TOKEN": TOKEN}
    if os.environ.get("SLAG_PROBE_PRELOAD"):
        edge_env["LD_PRELOAD"] = os.environ["SLAG_PROBE_PRELOAD"]
        print(f"probe: edge allocator preloaded: {edge_env['LD_PRELOAD']}", flush=True)
    edge = start(edge_cmd, edge_env, nofile=1024, log=log)
    assert wait_up(ep, "/health", edge), "edge server did not start"

    # The well-behaved client's address: OTHER where the servers share slots per address (a
    # flood from HOST then leaves it its share), else HOST as before.
    other = OTHER if new_flags and supports(a.edge, "serve", "--max-connections-per-ip") else None

    def query(text, k=20, source=None):
        st, _, b = request(ep, "GET", f"/query?text={text}&top_k={k}", headers=auth(),
                           source=source)
        return st, ([m["id"] for m in json.loads(b)["matches"]] if st == 200 else None)

    reference = {t: query(t)[1] for t in ["red", "a chair", "blue"]}
    idle = settled_rss(edge.pid)
    idle_fds = fds(edge.pid)
    print(f"probe: edge idle RSS {idle:.1f} MB, {idle_fds} descriptors", flush=True)

    # 1. Stalled sockets against the edge under a 1,024 descriptor limit.
    socks = [] if a.rss_only else stalled(ep, n_stall, b"GET /health HTTP/1.1\r\nHost: x\r\n")
    t0 = time.time()
    try:
        hs, _, _ = request(ep, "GET", "/health", timeout=60, source=other)
    except OSError as e:
        hs = f"error {e.__class__.__name__}"
    h_s = time.time() - t0
    try:
        qs, ids = query("red", source=other)
    except OSError as e:
        qs, ids = f"error {e.__class__.__name__}", None
    closed, took = count_closed(socks, 30)
    row("stalled sockets, edge (ulimit -n 1024)",
        f"/health and a query 200 (from {other or HOST}) while {n_stall} sockets stall; all "
        "closed by the header timeout",
        f"/health {hs} after {h_s:.1f} s, query {qs}; {closed}/{len(socks)} closed in {took:.0f} s",
        hs == 200 and qs == 200 and ids == reference["red"] and closed == len(socks))

    # 2. The same against the shard server.
    socks = [] if a.rss_only else stalled(sp, n_stall // 2, b"GET /v1/scenes HTTP/1.1\r\nHost: x\r\n")
    try:
        ss, _, _ = request(sp, "GET", "/v1/scenes", headers=auth(), timeout=60, source=other)
    except OSError as e:
        ss = f"error {e.__class__.__name__}"
    closed, took = count_closed(socks, 30)
    row("stalled sockets, shard server (ulimit -n 1024)",
        f"/v1/scenes 200 while {len(socks)} sockets stall; all closed by the header timeout",
        f"/v1/scenes {ss}; {closed}/{len(socks)} closed in {took:.0f} s",
        ss == 200 and closed == len(socks))

    # 3. The 3.6 KB request: 64 queries x top_k 10000, no threshold.
    huge = batch(64, 10000)
    before = rss_mb(edge.pid)
    pk = Peak(edge.pid)
    st, hdrs, body = request(ep, "POST", "/query", body=huge,
                             headers=auth({"Content-Type": "application/json"}), timeout=120)
    peak = pk.done()
    time.sleep(1)
    after = rss_mb(edge.pid)
    msg = ""
    try:
        msg = json.loads(body).get("error", "") if st != 200 else f"{len(body)/1e6:.0f} MB answer"
    except ValueError:
        pass
    row(f"huge request ({len(huge)} B: 64 x top_k 10000)",
        "400 naming max_matches; RSS +<=100 MB",
        f"{st} {msg[-90:]!r}; RSS {before:.0f} -> peak {peak:.0f} -> {after:.0f} MB",
        st == 400 and "max_matches" in msg and peak - before <= 100)

    # 4. The largest requests the cap accepts: 2 x top_k 10000 ranked; 8 threshold queries that
    # every Gaussian passes (threshold -1: the summary and the objects cover all of them, the
    # answer lists the top_k best); the whole scene as a painted .ply.
    worst = batch(2, 10000)
    thr_all = json.dumps({"queries": [{"text": f"probe all {i}", "top_k": 2500, "threshold": -1}
                                      for i in range(8)]}).encode()
    accepted = [
        ("2 x top_k 10000", "POST", "/query", worst),
        ("8 x threshold -1, top_k 2500", "POST", "/query", thr_all),
        ("GET /query.ply threshold -1", "GET", "/query.ply?text=probe&threshold=-1", None),
    ]
    for name, method, path, body_in in accepted:
        before = rss_mb(edge.pid)
        pk = Peak(edge.pid)
        st, _, body = request(ep, method, path, body=body_in,
                              headers=auth({"Content-Type": "application/json"}), timeout=120)
        peak = pk.done()
        time.sleep(1)
        after = rss_mb(edge.pid)
        row(f"worst accepted request ({name})", "200; RSS +<=100 MB",
            f"{st}, {len(body)/1e6:.1f} MB answer; RSS {before:.0f} -> peak {peak:.0f} -> "
            f"{after:.0f} MB", st == 200 and peak - before <= 100)

    if a.rss_only:
        t0 = time.time()
        end = settled_rss(edge.pid, 30)
        print(f"probe: edge RSS idle {idle:.0f} MB, after the requests {end:.0f} MB (settled in "
              f"{time.time() - t0:.0f} s)")
        stop(edge)
        stop(shards)
        for r in ROWS[2:]:
            print("| " + " | ".join(str(x) for x in r) + " |")
        return 0

    # 5. Slow readers on the edge: clients send the worst accepted request and never read.
    n_slow = 4 if a.short else 10
    before = rss_mb(edge.pid)
    pk = Peak(edge.pid)
    socks = slow_readers(ep, n_slow, post_raw(ep, worst))
    time.sleep(hold)
    during = rss_mb(edge.pid)
    open_fds = fds(edge.pid)
    peak = pk.done()
    for s in socks:
        s.close()
    row(f"{n_slow} slow readers, edge", "dropped after the write timeout",
        f"RSS {before:.0f} -> peak {peak:.0f} MB; after {hold} s {open_fds - idle_fds} extra "
        f"descriptors, RSS {during:.0f} MB", open_fds - idle_fds <= 1)

    # 6. Slow readers on the shard server: 60 clients fetch the largest shard, never read.
    m = json.loads(request(sp, "GET", "/v1/scenes/probe/manifest", headers=auth())[2])
    big = max(m["tiles"], key=lambda t: t["bytes"])
    n_sr = 20 if a.short else 60
    s_idle, s_fds = rss_mb(shards.pid), fds(shards.pid)
    pk = Peak(shards.pid)
    raw = (f"GET /v1/scenes/probe/shards/{big['id']} HTTP/1.1\r\nHost: x\r\n"
           f"Authorization: Bearer {TOKEN}\r\n\r\n").encode()
    socks = slow_readers(sp, n_sr, raw)
    time.sleep(hold)
    s_open = fds(shards.pid)
    peak = pk.done()
    for s in socks:
        s.close()
    time.sleep(1)
    s_after = rss_mb(shards.pid)
    row(f"{n_sr} slow readers, shard server ({big['bytes']/1e6:.1f} MB shard)",
        "no copy per connection (RSS +<=3 shards); dropped after the write timeout",
        f"RSS {s_idle:.0f} -> peak {peak:.0f} -> {s_after:.0f} MB; after {hold} s "
        f"{s_open - s_fds} extra descriptors",
        peak - s_idle <= 3 * big["bytes"] / 1e6 and s_open - s_fds <= 1)

    # 7. Error bodies.
    cases = [
        (ep, "edge", 405, dict(method="DELETE", path="/query", headers=auth())),
        (ep, "edge", 413, dict(method="POST", path="/query", body=b"{" + b" " * 70000 + b"}",
                               headers=auth({"Content-Type": "application/json"}))),
        (ep, "edge", 414, dict(method="GET", path="/query?text=" + "a" * 9000, headers=auth())),
        (ep, "edge", 431, dict(method="GET", path="/health", headers={"X-Pad": "p" * 20000})),
        (sp, "shards", 405, dict(method="POST", path="/v1/scenes", body=b"", headers=auth())),
        (sp, "shards", 414, dict(method="GET", path="/v1/" + "a" * 9000, headers=auth())),
        (sp, "shards", 431, dict(method="GET", path="/v1/scenes",
                                 headers=auth({"X-Pad": "p" * 20000}))),
        (sp, "shards", 416, dict(method="GET", path=f"/v1/scenes/probe/shards/{big['id']}",
                                 headers=auth({"Range": f"bytes={big['bytes']}-"}))),
    ]
    for port, name, want, kw in cases:
        st, hdrs, body = request(port, kw.pop("method"), kw.pop("path"), **kw)
        row(f"{want} body, {name}", f"{want} with the JSON error body",
            f"{st} {hdrs.get('content-type', 'no content-type')}, {len(body)} B",
            st == want and json_error(want, hdrs, body))

    # 8. Bearer scheme in another case.
    st_e = request(ep, "GET", "/stats", headers={"Authorization": f"bearer {TOKEN}"})[0]
    st_s = request(sp, "GET", "/v1/scenes", headers={"Authorization": f"BEARER {TOKEN}"})[0]
    row("bearer scheme case", "'bearer' / 'BEARER' accepted (RFC 9110)", f"edge {st_e}, shards {st_s}",
        st_e == 200 and st_s == 200)

    # 8b. Stalled bodies, credentials in URLs, strict inputs (functions above).
    case_stalled_bodies(ep, sp, n_stall, other or HOST)
    case_credentials(a.edge, ep, sp, f"{W}/edge", W)
    case_strict_inputs(ep, sp)

    # 9. Answers unchanged, memory back.
    same = all(query(t)[1] == ids_ for t, ids_ in reference.items())
    t0 = time.time()
    end = settled_rss(edge.pid, 30)
    row("answers after the probe", "equal to those before it", "equal" if same else "DIFFERENT", same)
    row("edge RSS after the probe", f"at most 10 % over idle ({idle:.0f} MB)",
        f"{end:.0f} MB ({100 * (end - idle) / idle:+.1f} %, settled in {time.time() - t0:.0f} s)",
        end - idle <= 0.1 * idle, goal=True)
    stop(edge)

    # 10. Blank tokens refuse to start.
    for name, cmd, var in [
        ("edge", [a.edge, "serve", "--store", f"{W}/edge", "--scene", "probe", "--listen",
                  f"{HOST}:{ep + 10}", "--clip-textual", a.text_model, "--tokenizer", a.tokenizer],
         "SLAG_EDGE_TOKEN"),
        ("shards", [a.shards, "serve", "--shard-store", f"{W}/shards-copy", "--listen", f"{HOST}:{ep + 11}"],
         "SLAG_SHARD_TOKEN"),
    ]:
        os.makedirs(f"{W}/shards-copy", exist_ok=True)
        for blank in ["", "   "]:
            p = subprocess.Popen(cmd, env={**os.environ, var: blank, "RUST_LOG": "warn"},
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            try:
                _, err = p.communicate(timeout=20)
                refused = p.returncode != 0 and "blank" in err
                obs = f"exit {p.returncode}: {err.strip().splitlines()[0][:70] if err.strip() else ''}"
            except subprocess.TimeoutExpired:
                p.kill()
                p.communicate()
                refused, obs = False, "started (open, no token)"
            row(f"blank {var}={blank!r}, {name}", "refused at start-up", obs, refused)

    # 11. Store damage: one `slag-edge fetch` repairs, `check` tells the truth.
    kinds = [] if a.skip_store else ["flip", "truncate", "append", "swap", "directory"]
    shard_dir = None
    for root, _, files in os.walk(f"{W}/edge-pristine/shards"):
        if any(f.endswith(".shard") for f in files):
            shard_dir = os.path.relpath(root, f"{W}/edge-pristine")
    files = sorted(f for f in os.listdir(f"{W}/edge-pristine/{shard_dir}") if f.endswith(".shard"))

    def damage(kind, d):
        f0, f1 = f"{d}/{shard_dir}/{files[0]}", f"{d}/{shard_dir}/{files[1]}"
        if kind == "flip":
            with open(f0, "r+b") as f:
                f.seek(4096)
                b = f.read(16)
                f.seek(4096)
                f.write(bytes(x ^ 0xFF for x in b))
        elif kind == "truncate":
            os.truncate(f0, os.path.getsize(f0) // 2)
        elif kind == "append":
            with open(f0, "ab") as f:
                f.write(b"\0" * 1000)
        elif kind == "swap":
            os.rename(f0, f0 + ".t")
            os.rename(f1, f0)
            os.rename(f0 + ".t", f1)
        elif kind == "directory":
            os.remove(f0)
            os.mkdir(f0)

    check_cmd = [a.edge, "check", "--scene", "probe", "--clip-textual", a.text_model,
                 "--tokenizer", a.tokenizer]
    for kind in kinds:
        d = f"{W}/case-{kind}"
        shutil.rmtree(d, ignore_errors=True)
        shutil.copytree(f"{W}/edge-pristine", d)
        damage(kind, d)
        c0 = subprocess.run(check_cmd + ["--store", d], capture_output=True, text=True)
        fr = subprocess.run([a.edge, "fetch", "--from", f"http://{HOST}:{sp}", "--scene", "probe",
                             "--center", "0,0", "--radius", "100000", "--store", d],
                            env={**os.environ, "SLAG_SHARD_TOKEN": TOKEN}, capture_output=True,
                            text=True)
        c1 = subprocess.run(check_cmd + ["--store", d], capture_output=True, text=True)
        repaired = all(
            os.path.isfile(f"{d}/{shard_dir}/{f}")
            and open(f"{d}/{shard_dir}/{f}", "rb").read()
            == open(f"{W}/edge-pristine/{shard_dir}/{f}", "rb").read() for f in files)
        row(f"store: {kind} a shard file", "check fails before; one fetch repairs; check passes",
            f"check before exit {c0.returncode}, fetch exit {fr.returncode}, "
            f"check after exit {c1.returncode}, files {'restored' if repaired else 'NOT restored'}",
            c0.returncode != 0 and fr.returncode == 0 and c1.returncode == 0 and repaired)
    # 12. Store integrity: one committed generation under fetch and reload, a manifest that is a
    # set, regular files only.
    if not a.skip_store:
        store_integrity_cases(a, W, sp, ep + 20, a.short)
    stop(shards)
    row("5xx answers over the probe", "0", str(FIVEXX[0]), FIVEXX[0] == 0)

    print()
    print("| case | expected | observed | pass/fail |")
    print("|---|---|---|---|")
    for r in ROWS:
        print("| " + " | ".join(str(x).replace("|", "/") for x in r) + " |")
    failed = sum(1 for r in ROWS if r[3] == "FAIL")
    print(f"\nprobe: {len(ROWS) - failed} of {len(ROWS)} cases pass")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
