"""Edits of ``cell.yaml`` that keep the file as its author wrote it (comments, order, quoting).

The file is read with ruamel.yaml's round-trip loader, changed in place, validated as a whole
(:func:`cellctl.config.parse_config`) and replaced atomically, keeping its permission bits. A
config that does not validate is never touched.
"""

from __future__ import annotations

import io
import os
import tempfile
from pathlib import Path
from typing import Any

from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq
from ruamel.yaml.error import YAMLError

from cellctl.auth import hash_token, new_token
from cellctl.config import ConfigError, Role, load_config, parse_config


def _yaml() -> YAML:
    y = YAML()  # round-trip
    y.preserve_quotes = True
    y.indent(mapping=2, sequence=4, offset=2)
    y.width = 4096

    def none_as_null(representer: Any, _: None) -> Any:
        return representer.represent_scalar("tag:yaml.org,2002:null", "null")

    y.representer.add_representer(type(None), none_as_null)
    return y


def _load(path: Path) -> tuple[YAML, Any]:
    load_config(path)  # refuse to touch a config that does not validate (the message names the line)
    y = _yaml()
    try:
        data = y.load(path.read_text())
    except YAMLError as exc:  # load_config accepted it, so this is rare (a YAML 1.2 vs 1.1 difference)
        raise ConfigError(f"{path}: cannot be edited without losing its layout ({str(exc).splitlines()[0]})") from None
    if data is None:
        data = CommentedMap()
    return y, data


def _save(path: Path, y: YAML, data: Any) -> None:
    buf = io.StringIO()
    y.dump(data, buf)
    text = buf.getvalue()
    parse_config(_plain(text), str(path))
    mode = path.stat().st_mode & 0o777
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _plain(text: str) -> Any:
    import yaml

    return yaml.safe_load(text)


def _tokens(data: Any, create: bool) -> CommentedSeq | None:
    auth = data.get("auth")
    if auth is None:
        if not create:
            return None
        auth = data["auth"] = CommentedMap()
    tokens = auth.get("tokens")
    if tokens is None:
        if not create:
            return None
        tokens = auth["tokens"] = CommentedSeq()
    return tokens  # type: ignore[no-any-return]


def list_tokens(path: str | Path) -> list[dict[str, str]]:
    """The configured tokens' names and roles (never their hashes)."""
    cfg = load_config(path)
    return [{"name": t.name, "role": t.role} for t in cfg.auth.tokens]


def add_token(path: str | Path, name: str, role: Role) -> str:
    """Add a token named ``name`` with ``role`` (stored as its SHA-256) and return the token itself."""
    p = Path(path)
    y, data = _load(p)
    tokens = _tokens(data, create=True)
    if tokens is None:  # for mypy: create=True always gives a list
        raise ConfigError(f"{p}: auth.tokens cannot be created")
    if any(isinstance(t, dict) and t.get("name") == name for t in tokens):
        raise ConfigError(f"{p}: a token named {name!r} exists already; choose another name "
                          f"(or remove it first: cellctl token remove --config {p} --name {name})")
    token = new_token()
    tokens.fa.set_block_style()  # `tokens: []` becomes a block list; a comment on its line stays
    tokens.append(CommentedMap(name=name, role=role, sha256=hash_token(token)))
    _save(p, y, data)
    return token


def remove_token(path: str | Path, name: str) -> dict[str, str]:
    """Remove the token named ``name``; returns its name and role. Unknown names are refused."""
    p = Path(path)
    y, data = _load(p)
    tokens = _tokens(data, create=False)
    if tokens is None:
        tokens = CommentedSeq()
    for i, t in enumerate(tokens):
        if isinstance(t, dict) and t.get("name") == name:
            removed = {"name": str(t.get("name")), "role": str(t.get("role"))}
            del tokens[i]
            if not tokens:
                tokens.fa.set_flow_style()  # back to `tokens: []`
            _save(p, y, data)
            return removed
    names = [str(t.get("name")) for t in tokens if isinstance(t, dict)]
    raise ConfigError(f"{p}: no token named {name!r}; configured: {', '.join(names) or 'none'} "
                      f"(see them with: cellctl token list --config {p})")
