"""``cellctl token add|list|remove``: edits that keep cell.yaml's comments, clear refusals."""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import dataclass
from pathlib import Path

import yaml

from cellctl.auth import hash_token
from cellctl.cli import main
from cellctl.config import default_config_text, load_config


@dataclass
class Run:
    returncode: int
    stdout: str
    stderr: str


def _run(*args: str) -> Run:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(args))
    return Run(code, out.getvalue(), err.getvalue())


def _comments(text: str) -> list[str]:
    return [line[line.index("#"):] for line in text.splitlines() if "#" in line]


def test_add_list_remove_keep_every_comment(tmp_path: Path) -> None:
    cfg = tmp_path / "cell.yaml"
    original = default_config_text() + "# a closing note of the integrator\n"
    cfg.write_text(original)
    cfg.chmod(0o640)
    added = {}
    for name, role in (("plc", "operator"), ("alice", "engineer")):
        r = _run("token", "add", "--config", str(cfg), "--name", name, "--role", role)
        assert r.returncode == 0, r.stderr
        added[name] = json.loads(r.stdout)["token"]
    text = cfg.read_text()
    assert _comments(text) == _comments(original)
    assert added["plc"] not in text and hash_token(added["plc"]) in text
    assert cfg.stat().st_mode & 0o777 == 0o640
    assert "path: null" in text  # nulls stay spelled as they were
    cfg_model = load_config(cfg)
    assert [(t.name, t.role) for t in cfg_model.auth.tokens] == [("plc", "operator"), ("alice", "engineer")]
    # Everything but the tokens is unchanged.
    before, after = yaml.safe_load(original), yaml.safe_load(text)
    after["auth"]["tokens"] = []
    assert after == before

    r = _run("token", "list", "--config", str(cfg))
    assert r.returncode == 0, r.stderr
    listed = json.loads(r.stdout)["tokens"]
    assert listed == [{"name": "plc", "role": "operator"}, {"name": "alice", "role": "engineer"}]
    assert added["alice"] not in r.stdout and hash_token(added["alice"]) not in r.stdout

    r = _run("token", "remove", "--config", str(cfg), "--name", "plc")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["removed"] == {"name": "plc", "role": "operator"}
    assert [t.name for t in load_config(cfg).auth.tokens] == ["alice"]
    r = _run("token", "remove", "--config", str(cfg), "--name", "alice")
    assert r.returncode == 0, r.stderr
    text = cfg.read_text()
    assert _comments(text) == _comments(original)
    assert yaml.safe_load(text) == yaml.safe_load(original)
    assert "tokens: []" in text


def test_refusals_are_one_line_and_leave_the_file_alone(tmp_path: Path) -> None:
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(default_config_text())
    assert _run("token", "add", "--config", str(cfg), "--name", "plc", "--role", "operator").returncode == 0
    text = cfg.read_text()
    r = _run("token", "add", "--config", str(cfg), "--name", "plc", "--role", "viewer")
    assert r.returncode != 0 and "exists already" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = _run("token", "remove", "--config", str(cfg), "--name", "bob")
    assert r.returncode != 0 and "no token named 'bob'" in r.stderr and "plc" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert cfg.read_text() == text
    bad = tmp_path / "bad.yaml"
    bad.write_text("cell_id: x\ntargets:\n  plate: {type: circle_plate, cols: 7 rows: 7}\n")
    r = _run("token", "add", "--config", str(bad), "--name", "a", "--role", "viewer")
    assert r.returncode != 0 and "line 3" in r.stderr and len(r.stderr.strip().splitlines()) == 1
