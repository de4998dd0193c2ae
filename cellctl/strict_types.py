"""Strict, finite number types for what the network sends (request bodies, recipes, part models).

pydantic's default (lax) mode takes ``true`` for 1.0 and ``"0.4"`` for 0.4: a request that says
``"ry_rad": true`` would tilt the tool by 57 degrees. These types take a JSON number only (a JSON
integer is a fine float), never a bool or a string; floats are finite. Give each field its range
(``Field(ge=..., le=...)`` or ``Annotated[Num, Field(...)]``), so a 400-digit integer is refused as
out of range before any code converts it.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import AllowInfNan, BaseModel, ConfigDict, Strict

Num = Annotated[float, Strict(), AllowInfNan(False)]
"""A finite JSON number (an integer is accepted); not a bool, a string, NaN or Infinity."""
Count = Annotated[int, Strict()]
"""A JSON integer; not a float, a bool or a string. Give it a range."""
Bool = Annotated[bool, Strict()]
"""``true`` or ``false``; not 1, "yes" or "true"."""


class ClosedModel(BaseModel):
    """A section of ``cell.yaml`` (or of a body) that refuses a key it does not know: a misspelt setting is an
    error naming it, never a default silently kept."""

    model_config = ConfigDict(extra="forbid")
