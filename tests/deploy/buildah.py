"""Build and run the repository's Dockerfile with buildah: no Docker engine, no registry.

The FROM images cannot be pulled here, so stand-ins with the same tags are made once with
debootstrap (Debian bookworm, Python 3.11 from Debian instead of /usr/local) and kept in
buildah's storage and ~/.cache; the Dockerfile itself is built unchanged. A container runs
with no engine either: ``buildah run`` under the image's USER, on the host's network.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
import zlib
from pathlib import Path

ENV = {**os.environ, "STORAGE_DRIVER": "vfs", "BUILDAH_ISOLATION": "chroot"}
CA_BUNDLE = "/etc/ssl/certs/ca-certificates.crt"
STAND_INS = {  # tag -> extra Debian packages (the build stage compiles the native extensions)
    "docker.io/library/python:3.11-bookworm": "gcc,libc6-dev,python3-dev,libjpeg62-turbo-dev",
    "docker.io/library/python:3.11-slim-bookworm": "",
}
_PACKAGES_LABEL = '{{index .OCIv1.Config.Labels "stand-in-packages"}}'
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "base-image-stand-ins"


def missing_tools() -> list[str]:
    return [tool for tool in ("buildah", "debootstrap") if shutil.which(tool) is None]


def buildah(*args: str, timeout: float = 600, check: bool = True) -> str:
    result = subprocess.run(["buildah", *args], env=ENV, capture_output=True, text=True, timeout=timeout)
    if check and result.returncode != 0:
        raise RuntimeError(f"buildah {' '.join(args)} failed ({result.returncode}):\n{result.stderr}")
    return result.stdout.strip()


def ensure_stand_in(tag: str, extra: str) -> None:
    """A minimal Debian root with python3 and pip, committed under ``tag`` (made once, and again
    when its packages change)."""
    packages = ",".join(p for p in ("python3,python3-venv,python3-pip,ca-certificates", extra) if p)
    if buildah("images", "-q", tag, check=False):
        made_with = buildah("inspect", "--type", "image", "--format", _PACKAGES_LABEL, tag, check=False)
        if made_with == packages:
            return
        buildah("rmi", "-f", tag, check=False)
    root = CACHE / f"{tag.replace(':', '_').replace('/', '_')}-{zlib.crc32(packages.encode()):08x}"
    if not (root / "usr").is_dir():
        subprocess.run(
            ["debootstrap", "--variant=minbase", f"--include={packages}", "bookworm", str(root)],
            check=True,
            capture_output=True,
            timeout=1200,
        )
    for marker in root.glob("usr/lib/python3*/EXTERNALLY-MANAGED"):
        marker.unlink()
    (root / "usr/local/bin/python").unlink(missing_ok=True)
    (root / "usr/local/bin/python").symlink_to("/usr/bin/python3")
    pip = root / "usr/local/bin/pip"
    pip.write_text('#!/bin/sh\nexec python3 -m pip "$@"\n')
    pip.chmod(0o755)
    container = buildah("from", "scratch")
    mount = buildah("mount", container)
    subprocess.run(["cp", "-a", f"{root}/.", f"{mount}/"], check=True, timeout=600)
    buildah("umount", container)
    buildah("config", "--env", "PATH=/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin", container)
    buildah("config", "--label", f"stand-in-packages={packages}", container)
    buildah("commit", "-q", container, tag)
    buildah("rm", container)


def build(context: Path, tag: str) -> None:
    """``buildah bud`` of the Dockerfile in ``context``; --layers reuses unchanged steps.

    Docker format, as ``docker build`` makes it (OCI images have no HEALTHCHECK). pip inside
    RUN reaches the package index through the host's CA bundle, named by PIP_CERT: buildah's
    --env also leaves PIP_CERT in the image's environment, where it is harmless.
    """
    for stand_in, extra in STAND_INS.items():
        ensure_stand_in(stand_in, extra)
    buildah(
        "bud",
        "--pull=never",
        "--layers",
        "--format",
        "docker",
        "-v",
        f"{CA_BUNDLE}:{CA_BUNDLE}:ro",
        "--env",
        f"PIP_CERT={CA_BUNDLE}",
        "-t",
        tag,
        str(context),
        timeout=1800,
    )


def image_bytes(tag: str) -> int:
    """The image's size: the sum of its (uncompressed) layers."""
    manifest = json.loads(json.loads(buildah("inspect", "--type", "image", tag))["Manifest"])
    return sum(layer["size"] for layer in manifest["layers"])


def image_config(tag: str) -> dict:
    """The image's Docker config (User, Cmd, Volumes, Healthcheck, ...)."""
    return json.loads(buildah("inspect", "--type", "image", tag))["Docker"]["config"]


class Container:
    """One container of an image, serving ``keypoint-service serve`` with a host folder as /data.

    Unlike ``docker run -v``, ``buildah run`` mounts the image's anonymous ``VOLUME /data``
    over a ``-v`` bind mount, so the working container's volume entry is dropped first
    (the image is not changed).
    """

    def __init__(self, tag: str, data_dir: Path, env: dict[str, str], log: Path) -> None:
        self.name = buildah("from", tag)
        buildah("config", "--volume", "/data-", self.name)
        arguments = [f"--env={key}={value}" for key, value in env.items()]
        with open(log, "ab") as out:
            self._buildah = subprocess.Popen(
                [
                    "buildah",
                    "run",
                    *arguments,
                    "-v",
                    f"{data_dir}:/data",
                    self.name,
                    "--",
                    "keypoint-service",
                    "serve",
                ],
                env=ENV,
                stdout=out,
                stderr=subprocess.STDOUT,
            )

    def served_pid(self, timeout: float = 60) -> int:
        """The pid of the service process inside the container (a descendant of buildah run)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for pid in _descendants(self._buildah.pid):
                if b"keypoint-service" in _cmdline(pid) and b"python" in _cmdline(pid):
                    return pid
            time.sleep(0.2)
        raise AssertionError("the container's keypoint-service process did not appear")

    def stop(self) -> None:
        """SIGTERM the service (as an engine's stop would), wait for it, remove the container."""
        try:
            os.kill(self.served_pid(timeout=5), signal.SIGTERM)
            self._buildah.wait(timeout=60)
        except (AssertionError, ProcessLookupError, subprocess.TimeoutExpired):
            self._buildah.kill()
            self._buildah.wait(timeout=30)
        buildah("rm", self.name, check=False)


def process_uid(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("Uid:"):
            return int(line.split()[1])
    raise AssertionError(f"no Uid line for process {pid}")


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def _descendants(root: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    found, stack = [], [root]
    while stack:
        for child in children.get(stack.pop(), []):
            found.append(child)
            stack.append(child)
    return found
