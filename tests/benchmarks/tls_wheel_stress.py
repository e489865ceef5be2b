"""Two Zenoh sessions of the eclipse-zenoh Python package in one process, one listening on TLS and
one connected to it, each publishing 24 KiB messages to the other as fast as the link takes them
(the Python side of crates/bone_sim/tests/tls_link.rs; docs/decisions/0017-patched-tls-link.md).
The package carries Zenoh's unpatched TLS link: a crash or lost messages here would be its race.

    python tests/benchmarks/tls_wheel_stress.py [--seconds 6] [--runs 4]

Needs openssl for the certificates. Each run is a child process; prints what each sent and got.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time


def _certificates(d: str) -> None:
    def ossl(*a: str) -> None:
        subprocess.run(["openssl", *a], cwd=d, check=True, capture_output=True)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    ossl("req", "-x509", *ec, "-keyout", "ca-key.pem", "-out", "ca.pem", "-subj", "/CN=test CA")
    ossl("req", *ec, "-keyout", "key.pem", "-out", "c.csr", "-subj", "/CN=localhost")
    with open(os.path.join(d, "c.ext"), "w") as f:
        f.write("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    ossl("x509", "-req", "-in", "c.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial",
         "-out", "cert.pem", "-extfile", "c.ext")  # fmt: skip


def _one_run(d: str, seconds: float) -> None:
    import zenoh

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    def conf(listen: bool) -> zenoh.Config:
        tls = {"root_ca_certificate": f"{d}/ca.pem"}
        c: dict = {"mode": "peer", "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}
        if listen:
            tls |= {"listen_certificate": f"{d}/cert.pem", "listen_private_key": f"{d}/key.pem"}
            c["listen"] = {"endpoints": [f"tls/127.0.0.1:{port}"]}
        else:
            c["connect"] = {"endpoints": [f"tls/localhost:{port}"]}
        c["transport"] = {"link": {"tls": tls}}
        return zenoh.Config.from_json5(json.dumps(c))

    a, b = zenoh.open(conf(True)), zenoh.open(conf(False))
    got, sent, lock = {"a": 0, "b": 0}, {"a": 0, "b": 0}, threading.Lock()

    def counter(k: str):
        def on_sample(_sample) -> None:
            with lock:
                got[k] += 1

        return on_sample

    subs = [a.declare_subscriber("t/to-a", counter("a")), b.declare_subscriber("t/to-b", counter("b"))]
    to_b = a.declare_publisher("t/to-b", congestion_control=zenoh.CongestionControl.BLOCK)
    to_a = b.declare_publisher("t/to-a", congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + 20.0
    while (not to_b.matching_status.matching or not to_a.matching_status.matching) and time.monotonic() < deadline:
        time.sleep(0.01)
    stop, payload = threading.Event(), bytes(24 * 1024)

    def flood(pub, k: str) -> None:
        while not stop.is_set():
            pub.put(payload)
            sent[k] += 1

    threads = [threading.Thread(target=flood, args=(to_b, "b")), threading.Thread(target=flood, args=(to_a, "a"))]
    for t in threads:
        t.start()
    time.sleep(seconds)
    stop.set()
    for t in threads:
        t.join()
    deadline = time.monotonic() + 20.0
    while (got["a"] < sent["a"] or got["b"] < sent["b"]) and time.monotonic() < deadline:
        time.sleep(0.01)
    print(json.dumps({"sent": sent, "got": got, "all_arrived": got == sent}), flush=True)
    del subs
    os._exit(0 if got == sent else 1)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=6.0)
    p.add_argument("--runs", type=int, default=4)
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        _one_run(args.child, args.seconds)
        return
    with tempfile.TemporaryDirectory() as d:
        _certificates(d)
        for run in range(args.runs):
            done = subprocess.run(
                [sys.executable, __file__, "--child", d, "--seconds", str(args.seconds)],
                capture_output=True, text=True, timeout=args.seconds + 120,
            )  # fmt: skip
            tail = done.stderr.strip()[-300:]
            print(f"run {run + 1}: exit {done.returncode} {done.stdout.strip()} {tail}", flush=True)


if __name__ == "__main__":
    main()
