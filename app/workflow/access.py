"""Who may write: bearer tokens mapped to operator names.

Rules:

* On a loopback address (127.0.0.1, ::1, localhost) writes need no token:
  only local users can reach the server.
* On any other address every write (POST/PUT) needs
  ``Authorization: Bearer <token>``, and the server refuses to start when no
  token is configured.
* Tokens come from ``STARID_TOKENS`` (``"token1=alice,token2=bob"``) and/or
  a file named by ``STARID_TOKENS_FILE`` (lines ``token operator``; blank
  lines and ``#`` comments ignored).  The token's operator is the one written
  into audit records, whatever name a request body gives; so a name holding a
  control or bidirectional control character (:mod:`app.workflow.text`) is
  refused here as it is in a request body, and the server does not start.
"""

from __future__ import annotations

import hmac
import ipaddress
from dataclasses import dataclass, field
from pathlib import Path

from app.workflow.text import operator_name_problem


class TokenConfigError(ValueError):
    """The token configuration cannot be read or is malformed."""


def is_loopback_host(host: str) -> bool:
    """True for ``localhost`` and loopback IP addresses (127.0.0.0/8, ::1)."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip().strip("[]")).is_loopback
    except ValueError:
        return False


def _check_pair(token: str, operator: str, where: str) -> None:
    if not token or not operator:
        raise TokenConfigError(f"{where}: expected a token and an operator name")
    if any(ch.isspace() for ch in token):
        raise TokenConfigError(f"{where}: a token cannot contain blanks")
    problem = operator_name_problem(operator)
    if problem:
        raise TokenConfigError(f"{where}: the operator name {problem}")


def parse_token_list(text: str) -> dict[str, str]:
    """``"token1=alice,token2=bob"`` -> {token: operator}."""
    tokens: dict[str, str] = {}
    for k, item in enumerate(part.strip() for part in text.split(",")):
        if not item:
            continue
        token, sep, operator = item.partition("=")
        if not sep:
            raise TokenConfigError(f"STARID_TOKENS item {k + 1}: expected token=operator")
        _check_pair(token.strip(), operator.strip(), f"STARID_TOKENS item {k + 1}")
        tokens[token.strip()] = operator.strip()
    return tokens


def parse_token_file(text: str, name: str = "token file") -> dict[str, str]:
    """Lines ``token operator name`` (the rest of the line is the name) -> {token: operator}."""
    tokens: dict[str, str] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(None, 1)
        if len(parts) != 2:
            raise TokenConfigError(f"{name} line {number}: expected 'token operator'")
        _check_pair(parts[0], parts[1].strip(), f"{name} line {number}")
        tokens[parts[0]] = parts[1].strip()
    return tokens


def load_tokens(token_list: str = "", token_file: str | None = None) -> dict[str, str]:
    """Tokens from the environment's list and the file (the file wins on a clash)."""
    tokens = parse_token_list(token_list or "")
    if token_file:
        try:
            text = Path(token_file).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise TokenConfigError(f"cannot read STARID_TOKENS_FILE {token_file}: {exc}") from None
        tokens.update(parse_token_file(text, "STARID_TOKENS_FILE"))
    return tokens


@dataclass(frozen=True)
class AccessPolicy:
    """Whether writes need a token, and which tokens exist."""

    tokens: dict[str, str] = field(default_factory=dict)
    require_token: bool = False

    @classmethod
    def for_host(cls, host: str, tokens: dict[str, str]) -> "AccessPolicy":
        """Tokens required off loopback; raises TokenConfigError if none are configured there."""
        loopback = is_loopback_host(host)
        if not loopback and not tokens:
            raise TokenConfigError(
                f"refusing to listen on {host}, a non-loopback address, without bearer tokens: "
                "set STARID_TOKENS='token=operator,...' or STARID_TOKENS_FILE (lines 'token operator'), "
                "or bind to 127.0.0.1")
        return cls(tokens=dict(tokens), require_token=not loopback)

    def operator_of(self, token: str) -> str | None:
        """The operator of ``token``, compared in constant time; None if unknown."""
        found = None
        for known, operator in self.tokens.items():
            if hmac.compare_digest(known.encode(), token.encode()):
                found = operator
        return found
