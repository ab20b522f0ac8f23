"""The client's README examples run as written against a real server (its URL and token
substituted), from the root of the checkout as the paths in them assume."""

from __future__ import annotations

import re

import pytest

from service.runtime.settings import PACKAGE_ROOT
from tests.live.client.conftest import CLIENT_ROOT
from tests.live.server import LiveServer
from tests.service_calls import ADMIN_TOKEN

EXAMPLE = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)


def test_the_readme_examples_run(server: LiveServer, monkeypatch: pytest.MonkeyPatch) -> None:
    examples = EXAMPLE.findall((CLIENT_ROOT / "README.md").read_text(encoding="utf-8"))
    assert len(examples) >= 5
    monkeypatch.chdir(PACKAGE_ROOT)
    for example in examples:
        code = example.replace("http://127.0.0.1:8000", server.url).replace(
            '"change-me-to-a-secret"', repr(ADMIN_TOKEN)
        )
        exec(compile(code, "client/README.md", "exec"), {"__name__": "readme"})
