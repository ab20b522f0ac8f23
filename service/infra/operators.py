"""Named admin tokens: who may administer calibrations, under which name (recorded in the audit).

``CKS_ADMIN_TOKENS_FILE`` holds ``name:token`` lines (``#`` comments); ``CKS_ADMIN_TOKEN`` is the
operator ``admin``. A line ``feedback name:token`` may only send feedback; ``predict name:token`` is
a predict token: once the file has one, predict needs a predict (or admin) token, each holder one
caller for admission's cap. Every token has at least 16 characters and no spaces.
"""

from __future__ import annotations

import hmac
import re
from pathlib import Path

TOKEN_SETTING = "CKS_ADMIN_TOKEN"
TOKENS_FILE_SETTING = "CKS_ADMIN_TOKENS_FILE"
SINGLE_TOKEN_NAME = "admin"
FEEDBACK_SCOPE = "feedback"
PREDICT_SCOPE = "predict"
SCOPES = (FEEDBACK_SCOPE, PREDICT_SCOPE)
MIN_TOKEN_CHARS = 16
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,63}$")


class OperatorsError(ValueError):
    """The admin token configuration is unusable; the message says what to fix."""


def load_operators(single_token: str | None, tokens_file: Path | None) -> dict[str, str]:
    """Token -> operator name, from ``CKS_ADMIN_TOKEN`` and the tokens file (empty: admin off)."""
    operators: dict[str, str] = {}
    if single_token:
        _check_token(single_token, f"{TOKEN_SETTING}: the token")
        operators[single_token] = SINGLE_TOKEN_NAME
    if tokens_file is not None:
        for where, name, token in _entries(tokens_file, scope=None):
            if token in operators:
                raise OperatorsError(f"{where}: this token is already given to {operators[token]!r}")
            if name in operators.values():
                raise OperatorsError(f"{where}: the name {name!r} is used twice; give each operator one name")
            operators[token] = name
    return operators


def load_feedback_senders(single_token: str | None, tokens_file: Path | None) -> dict[str, str]:
    """Token -> name of those who may send feedback: the admins and the ``feedback`` lines."""
    return _scoped(single_token, tokens_file, FEEDBACK_SCOPE)


def load_predict_callers(single_token: str | None, tokens_file: Path | None) -> dict[str, str]:
    """Token -> name of those who may predict where predict tokens are on (the ``predict`` lines and
    the admins); empty where the file has no ``predict`` line: predict needs no token then."""
    if tokens_file is None or not _entries(tokens_file, scope=PREDICT_SCOPE):
        return {}
    return _scoped(single_token, tokens_file, PREDICT_SCOPE)


def _scoped(single_token: str | None, tokens_file: Path | None, scope: str) -> dict[str, str]:
    """The admins' tokens and those of ``scope``'s lines."""
    senders = load_operators(single_token, tokens_file)
    for where, name, token in _entries(tokens_file, scope) if tokens_file is not None else ():
        if token in senders:
            raise OperatorsError(f"{where}: this token is already given to {senders[token]!r}")
        senders[token] = name
    return senders


def operator_named(operators: dict[str, str], presented: str) -> str | None:
    """The operator whose token ``presented`` is, or None. Compares with every token in constant
    time each, so timing tells nothing about which matched."""
    found = None
    for token, name in operators.items():
        if hmac.compare_digest(presented.encode(), token.encode()):
            found = name
    return found


def _entries(path: Path, scope: str | None) -> list[tuple[str, str, str]]:
    """(where, name, token) of the lines of ``scope`` (None: the admin lines, which name no scope)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise OperatorsError(f"{TOKENS_FILE_SETTING}: cannot read {path}: {error}") from error
    entries, named = [], 0
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{TOKENS_FILE_SETTING} {path}, line {number}"
        line_scope = next((s for s in SCOPES if line.startswith(s + " ")), None)
        line = line.removeprefix(f"{line_scope} ") if line_scope else line
        name, sep, token = line.partition(":")
        name, token = name.strip(), token.strip()
        if not sep or not _NAME.match(name):
            raise OperatorsError(
                f"{where}: write 'name:token' with a name of letters, digits and . _ @ - (at most 64)"
            )
        _check_token(token, f"{where}: the token of {name!r}")
        named += 1
        if line_scope == scope:
            entries.append((where, name, token))
    if not named:
        raise OperatorsError(f"{TOKENS_FILE_SETTING} {path} names no operator; add 'name:token' lines")
    return entries


def _check_token(token: str, what: str) -> None:
    if len(token) < MIN_TOKEN_CHARS or any(ch.isspace() for ch in token):
        raise OperatorsError(
            f"{what} must be at least {MIN_TOKEN_CHARS} characters without spaces "
            "(make one with: openssl rand -hex 16)"
        )
