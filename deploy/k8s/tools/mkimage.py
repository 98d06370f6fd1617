#!/usr/bin/env python3
"""Write a one-layer container image of a folder as a ``docker save`` archive, with no engine.

    mkimage.py ROOTFS NAME:TAG OUT.tar [--entrypoint JSON] [--cmd JSON]

deploy/k8s/build-binaries.sh makes the pod sandbox ("pause") image with it: kubeadm would
pull registry.k8s.io/pause, and no registry is reachable here. ``ctr images import`` (and
``docker load``) read the archive. Files are owned by root with mtime 0, so the same
folder always gives the same image id.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import tarfile


def _as_root(info: tarfile.TarInfo) -> tarfile.TarInfo:
    info.uid = info.gid = 0
    info.uname = info.gname = "root"
    info.mtime = 0
    return info


def layer_of(rootfs: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for root, dirs, files in os.walk(rootfs):
            dirs.sort()
            for name in dirs + sorted(files):
                path = os.path.join(root, name)
                tar.add(path, arcname=os.path.relpath(path, rootfs), recursive=False, filter=_as_root)
    return buf.getvalue()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rootfs")
    ap.add_argument("ref", help="NAME:TAG")
    ap.add_argument("out")
    ap.add_argument("--entrypoint", help="JSON list")
    ap.add_argument("--cmd", help="JSON list")
    args = ap.parse_args()

    layer = layer_of(args.rootfs)
    diff_id = "sha256:" + hashlib.sha256(layer).hexdigest()
    config: dict[str, object] = {"Env": ["PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"]}
    if args.entrypoint:
        config["Entrypoint"] = json.loads(args.entrypoint)
    if args.cmd:
        config["Cmd"] = json.loads(args.cmd)
    image = {
        "architecture": "amd64",
        "os": "linux",
        "created": "1970-01-01T00:00:00Z",
        "config": config,
        "rootfs": {"type": "layers", "diff_ids": [diff_id]},
        "history": [{"created_by": "deploy/k8s/tools/mkimage.py"}],
    }
    image_bytes = json.dumps(image, sort_keys=True).encode()
    image_name = hashlib.sha256(image_bytes).hexdigest() + ".json"
    layer_name = diff_id.removeprefix("sha256:") + "/layer.tar"
    manifest = json.dumps([{"Config": image_name, "RepoTags": [args.ref], "Layers": [layer_name]}]).encode()
    with tarfile.open(args.out, "w") as tar:
        for name, data in ((image_name, image_bytes), (layer_name, layer), ("manifest.json", manifest)):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    print(f"{args.out}: {args.ref} {diff_id[:19]} ({len(layer)} bytes)")


if __name__ == "__main__":
    main()
