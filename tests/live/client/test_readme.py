"""The client's examples, in its README and in the service's, run as written against a real server
(its URL and token substituted), from the root of the checkout as the paths in them assume."""

from __future__ import annotations

import re

import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.live.server import LiveServer
from tests.service_calls import ADMIN_TOKEN

EXAMPLE = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)


@pytest.mark.parametrize(("readme", "least"), [("client/README.md", 5), ("README.md", 1)])
def test_the_readme_examples_run(
    server: LiveServer, monkeypatch: pytest.MonkeyPatch, readme: str, least: int
) -> None:
    examples = EXAMPLE.findall((PACKAGE_ROOT / readme).read_text(encoding="utf-8"))
    assert len(examples) >= least
    monkeypatch.chdir(PACKAGE_ROOT)
    for example in examples:
        code = example.replace("http://127.0.0.1:8000", server.url).replace(
            '"change-me-to-a-secret"', repr(ADMIN_TOKEN)
        )
        exec(compile(code, readme, "exec"), {"__name__": "readme"})


def test_the_readme_installs_the_numpy_extra_before_its_example() -> None:
    text = (PACKAGE_ROOT / "README.md").read_text(encoding="utf-8")
    assert "contains(" in text and text.index("pip install './client[numpy]'") < text.index("contains(")
