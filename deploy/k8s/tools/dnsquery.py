#!/usr/bin/env python3
"""Ask a DNS server for a name's A record; exit 0 when it answers with the expected address.

    dnsquery.py SERVER NAME [EXPECTED_IP]

deploy/k8s/cluster-up.sh uses it to wait until CoreDNS answers cluster names (no dig or
nslookup on these machines). Only the standard library; one UDP datagram to SERVER.
"""

from __future__ import annotations

import random
import socket
import struct
import sys


def query(server: str, name: str, timeout_s: float = 2.0) -> list[str]:
    """The IPv4 addresses of ``name``'s A records, as ``server`` answers them."""
    ident = random.randrange(1 << 16)
    header = struct.pack("!HHHHHH", ident, 0x0100, 1, 0, 0, 0)  # recursion desired, one question
    question = b"".join(bytes([len(p)]) + p.encode() for p in name.rstrip(".").split(".")) + b"\0"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(timeout_s)
        sock.sendto(header + question + struct.pack("!HH", 1, 1), (server, 53))
        reply = sock.recv(4096)
    rid, flags, _qd, ancount, _ns, _ar = struct.unpack("!HHHHHH", reply[:12])
    if rid != ident or flags & 0x000F:
        return []  # not ours, or an error code (NXDOMAIN, SERVFAIL, ...)
    pos = 12 + len(question) + 4
    addresses = []
    for _ in range(ancount):
        if reply[pos] & 0xC0 == 0xC0:  # a compressed name: a two-byte pointer
            pos += 2
        else:
            while reply[pos]:
                pos += reply[pos] + 1
            pos += 1
        rtype, _cls, _ttl, length = struct.unpack("!HHIH", reply[pos : pos + 10])
        pos += 10
        if rtype == 1 and length == 4:
            addresses.append(socket.inet_ntoa(reply[pos : pos + 4]))
        pos += length
    return addresses


def main() -> int:
    server, name, *expected = sys.argv[1:]
    try:
        found = query(server, name)
    except OSError as e:
        print(f"{server}: {e}", file=sys.stderr)
        return 1
    print(" ".join(found) or "no answer")
    return 0 if found and (not expected or expected[0] in found) else 1


if __name__ == "__main__":
    sys.exit(main())
