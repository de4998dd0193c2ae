"""cellctl.errors_format: pydantic errors as one actionable line."""

from __future__ import annotations

import pytest
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from cellctl.errors_format import MAX_INPUT_CHARS, format_validation_errors


class Inner(BaseModel):
    model_config = ConfigDict(extra="forbid")
    port: int = Field(ge=1, le=65535)


class Outer(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    http: Inner


def _error(data: object) -> ValidationError:
    with pytest.raises(ValidationError) as err:
        Outer.model_validate(data)
    return err.value


def test_paths_messages_unknown_and_missing_keys() -> None:
    exc = _error({"http": {"port": 0, "colour": "red"}})
    text = format_validation_errors(exc)
    parts = text.split("; ")
    assert "name: Field required" in parts
    assert "http.port: Input should be greater than or equal to 1 (got 0)" in parts
    assert "http.colour: unknown key" in parts
    assert len(parts) == 3


def test_prefix_and_without_input() -> None:
    exc = _error({"name": "c", "http": {"port": "x"}})
    assert format_validation_errors(exc, prefix="cameras.cam0.settings") == (
        "cameras.cam0.settings.http.port: Input should be a valid integer, unable to parse string as an "
        "integer (got 'x')")
    assert format_validation_errors(exc.errors(), with_input=False) == (
        "http.port: Input should be a valid integer, unable to parse string as an integer")


def test_top_level_and_long_inputs_are_shortened() -> None:
    exc = _error(["not", "a", "mapping"] * 30)
    text = format_validation_errors(exc)
    assert text.startswith("(top level): Input should be a valid dictionary")
    got = text.split("(got ", 1)[1]
    assert got.endswith("...)") and len(got) == MAX_INPUT_CHARS + 1
