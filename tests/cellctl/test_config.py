"""cell.yaml validation: clear errors with the file, the key path and what is expected."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from cellctl.config import ConfigError, default_config_text, load_config, parse_config
from tests.conftest import REPO


def test_builtin_config_is_the_virtual_cell() -> None:
    cfg = load_config(None)
    assert cfg.cameras["cam0"].kind == "sim"
    assert cfg.robots["robot0"].kind == "sim"
    limits = cfg.robots["robot0"].limits()
    assert limits.x_mm == (100.0, 800.0)
    assert cfg.http.host == "127.0.0.1" and cfg.http.port == 8080


def test_example_file_is_what_config_default_prints() -> None:
    assert (REPO / "deploy" / "examples" / "virtual-cell.yaml").read_text() == default_config_text()


def _base() -> dict:
    return yaml.safe_load(default_config_text())


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda d: d["cameras"]["cam0"].update(kind="nosuch"), "cameras.cam0.kind: unknown camera kind 'nosuch'"),
        (lambda d: d["cameras"]["cam0"]["settings"].update(colour="red"), "cameras.cam0.settings.colour: unknown key"),
        (lambda d: d["http"].update(port=70000), "http.port: Input should be less than or equal to 65535"),
        (lambda d: d["http"].update(port="eighty"), "http.port: Input should be a valid integer"),
        (lambda d: d["robots"]["robot0"]["envelope"].update(x_mm=[800, 100]), "x_mm must be [low, high]"),
        (lambda d: d["robots"]["robot0"].update(max_linear_speed_m_s=-1), "max_linear_speed_m_s"),
        (lambda d: d.update(lights={}), "lights: unknown key"),
        (lambda d: d["robots"]["robot0"].pop("envelope"), "robots.robot0.envelope: Field required"),
        (lambda d: d.update(format_version=99), "newer than this cellctl supports"),
    ],
)
def test_bad_config_names_key_path(mutate, expected: str, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    data = _base()
    mutate(data)
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(path) in str(err.value)
    assert expected in str(err.value)


def test_corrupt_yaml_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text("cameras: [unclosed\n  - : :")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read the config file"):
        load_config(tmp_path / "absent.yaml")


def test_top_level_must_be_mapping() -> None:
    with pytest.raises(ConfigError, match="top level must be a mapping"):
        parse_config([1, 2], "x.yaml")
