"""The README's first run, followed line by line: its commands run in bash, with curl, against a
real ``keypoint-service serve`` started as the README starts it (its admin token), and every
output it shows is what the service says; the prediction, the refused activation at upload, the
forced activation and the sets that follow are as the README tells.

The second terminal is a stock one: Debian's default PATH, no venv, in a git repository holding
what a clone holds for these commands (the bundled model, the .gitignore), which they must leave
as it was: their outputs go to /tmp.

Only the installation is left out (this checkout is the installed package) and the addresses:
the server listens on a free port instead of 8000, and the commands' /tmp is one of the test's.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

from service.infra.settings import PACKAGE_ROOT
from tests.live.server import LiveServer
from tests.readme import bash_blocks, commands_and_outputs, section, shows

FIRST_RUN = "First run: a prediction, an upload, an activation"
README_URL = "http://127.0.0.1:8000"
README_OUTPUTS = "/tmp/"
STOCK_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"  # Debian's default
SIZES = re.compile(
    r"(\d+) of the duck's 8 ellipses shrink \(`(\w+)` from ([\d.]+) x ([\d.]+) to\s+([\d.]+) x ([\d.]+) px"
    r" semi-axes\) and (\d+) grow"
)


def git(folder: Path, *arguments: str) -> str:
    return subprocess.run(
        ["git", "-c", "user.name=test", "-c", "user.email=test@localhost", *arguments],
        cwd=folder,
        check=True,
        capture_output=True,
        text=True,
    ).stdout


def a_clone(folder: Path) -> Path:
    """A git repository with what the commands read of a clone, committed: the bundled model and
    the .gitignore (so that what a clone ignores is ignored here too)."""
    folder.mkdir()
    (folder / "models").symlink_to(PACKAGE_ROOT / "models")
    shutil.copy(PACKAGE_ROOT / ".gitignore", folder / ".gitignore")
    git(folder, "init", "-q")
    git(folder, "add", ".")
    git(folder, "commit", "-q", "-m", "a clone")
    return folder


def bash(command: str, server: LiveServer, folder: Path, outputs: Path) -> str:
    """``command`` as a reader would type it in a stock terminal, in ``folder``, asking ``server``."""
    assert shutil.which("curl", path=STOCK_PATH), "curl is not installed: apt-get install curl (.ci/run does)"
    done = subprocess.run(
        [
            "/bin/bash",
            "-euo",
            "pipefail",
            "-c",
            command.replace(README_URL, server.url).replace(README_OUTPUTS, f"{outputs}/"),
        ],
        cwd=folder,
        env={"PATH": STOCK_PATH, "HOME": os.environ.get("HOME", "/root"), "LANG": "C.UTF-8"},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, f"{command}\n{done.stderr}"
    return done.stdout


def semi_axes(answer: dict) -> dict[str, list[float]]:
    return {k["name"]: k["set"]["semi_axes"] for k in answer["instances"][0]["keypoints"]}


def test_the_first_run_reaches_an_activated_upload(tmp_path: Path) -> None:
    blocks = [commands_and_outputs(b) for b in bash_blocks(section(FIRST_RUN))]
    install, predict, picture, upload, activate = blocks
    commands = [command.split(" #")[0].strip() for command, _ in install]  # without their comments
    assert commands[1] == "pip install -e ." and commands[2].endswith(" keypoint-service serve")
    token = re.fullmatch(r"CKS_ADMIN_TOKEN=(\S+) keypoint-service serve", commands[2]).group(1)
    folder, outputs = a_clone(tmp_path / "clone"), tmp_path / "tmp"
    outputs.mkdir()

    def run(command: str) -> str:
        return bash(command, server, folder, outputs)

    with LiveServer(tmp_path / "data", admin_token=token) as server:
        answer = json.loads(run(predict[0][0]))
        keypoints = answer["instances"][0]["keypoints"]
        assert answer["calibration"]["version"] == 1 and len(keypoints) == 8
        assert {k["set"]["type"] for k in keypoints} == {"ellipse"}
        said_n = re.search(r"`n` = ([\d,]+) scores", section(FIRST_RUN)).group(1)
        assert {k["guarantee"]["n"] for k in keypoints} == {int(said_n.replace(",", ""))}
        run(picture[0][0])
        assert (outputs / "sets.png").read_bytes().startswith(b"\x89PNG")

        export = upload[0][0]
        assert export == f"export TOKEN={token}"
        said = [run(f"{export}\n{command}") for command, _ in upload]
        for _ in range(600):  # "repeat the last command until succeeded"
            if '"state":"succeeded"' in said[-1] or '"state":"failed"' in said[-1]:
                break
            time.sleep(0.1)
            said[-1] = run(f"{export}\n{upload[-1][0]}")
        for (command, shown), output in zip(upload, said, strict=True):
            assert shows(output, shown), f"{command}\nshowed {shown}\nsaid   {output}"
        problems = json.loads(said[-1])["result"]["activation_problems"]
        assert len(problems) == len({p.split("'")[1] for p in problems}) == 48, "one line per keypoint"

        for command, shown in activate:
            output = run(f"{export}\n{command}")
            assert shows(output, shown), f"{command}\nshowed {shown}\nsaid   {output}"

        after = json.loads(run(predict[0][0]))
        guarantees = [k["guarantee"] for k in after["instances"][0]["keypoints"]]
        assert after["calibration"]["version"] == 2
        assert {(g["n"], g["t"]) for g in guarantees} == {(11, 1)}, "the README: 11 duck scores, t = 1"

    assert git(folder, "status", "--porcelain", "--untracked-files=all") == "", "the walk-through left files"
    before, now = semi_axes(answer), semi_axes(after)
    area = {name: math.prod(now[name]) / math.prod(before[name]) for name in before}
    said_sizes = SIZES.search(" ".join(section(FIRST_RUN).split()))
    assert said_sizes, "the README says how the duck's sets change"
    shrink, name, *sizes, grow = said_sizes.groups()
    measured = [f"{x:.2f}" for x in before[name] + now[name]]
    assert measured == sizes, f"{name}: {before[name]} -> {now[name]}, the README says {sizes}"
    shrunk = sum(ratio < 1 for ratio in area.values())
    assert (shrunk, len(area) - shrunk) == (int(shrink), int(grow)), area
