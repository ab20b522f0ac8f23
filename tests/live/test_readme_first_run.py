"""The README's first run, followed line by line: its commands run in bash, with curl, against a
real ``keypoint-service serve`` started as the README starts it (its admin token), and every
output it shows is what the service says; the prediction, the refused activation at upload, the
forced activation and the sets that follow are as the README tells.

Only the installation is left out (this checkout is the installed package) and the address:
the server listens on a free port instead of 8000.
"""

from __future__ import annotations

import json
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


def bash(command: str, server: LiveServer, folder: Path) -> str:
    """``command`` as a reader would type it, in ``folder``, asking ``server``."""
    assert shutil.which("curl"), "curl is not installed: apt-get install curl (.ci/run does)"
    done = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", command.replace(README_URL, server.url)],
        cwd=folder,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(PACKAGE_ROOT), str(PACKAGE_ROOT / "client")])},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, f"{command}\n{done.stderr}"
    return done.stdout


def test_the_first_run_reaches_an_activated_upload(tmp_path: Path) -> None:
    blocks = [commands_and_outputs(b) for b in bash_blocks(section(FIRST_RUN))]
    install, predict, picture, upload, activate = blocks
    commands = [command.split(" #")[0].strip() for command, _ in install]  # without their comments
    assert commands[1] == "pip install -e ." and commands[2].endswith(" keypoint-service serve")
    token = re.fullmatch(r"CKS_ADMIN_TOKEN=(\S+) keypoint-service serve", commands[2]).group(1)
    folder = tmp_path / "clone"  # what a reader's working folder holds: the bundled model
    folder.mkdir()
    (folder / "models").symlink_to(PACKAGE_ROOT / "models")

    with LiveServer(tmp_path / "data", admin_token=token) as server:
        answer = json.loads(bash(predict[0][0], server, folder))
        keypoints = answer["instances"][0]["keypoints"]
        assert answer["calibration"]["version"] == 1 and len(keypoints) == 8
        assert {k["set"]["type"] for k in keypoints} == {"ellipse"}
        assert {k["guarantee"]["n"] for k in keypoints} == {413}
        bash(picture[0][0], server, folder)
        assert (folder / "sets.png").read_bytes().startswith(b"\x89PNG")

        export = upload[0][0]
        assert export == f"export TOKEN={token}"
        said = [bash(f"{export}\n{command}", server, folder) for command, _ in upload]
        for _ in range(600):  # "repeat the last command until succeeded"
            if '"state":"succeeded"' in said[-1] or '"state":"failed"' in said[-1]:
                break
            time.sleep(0.1)
            said[-1] = bash(f"{export}\n{upload[-1][0]}", server, folder)
        for (command, shown), output in zip(upload, said, strict=True):
            assert shows(output, shown), f"{command}\nshowed {shown}\nsaid   {output}"

        for command, shown in activate:
            output = bash(f"{export}\n{command}", server, folder)
            assert shows(output, shown), f"{command}\nshowed {shown}\nsaid   {output}"

        answer = json.loads(bash(predict[0][0], server, folder))
        guarantees = [k["guarantee"] for k in answer["instances"][0]["keypoints"]]
        assert answer["calibration"]["version"] == 2
        assert {(g["n"], g["t"]) for g in guarantees} == {(11, 1)}, "the README: 11 duck scores, t = 1"
