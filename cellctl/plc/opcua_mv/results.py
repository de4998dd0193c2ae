"""The Machine Vision results: what each job or production cycle produced, the last ``KEEP`` kept
in memory for ``ResultManagement`` (GetResultById, GetResultListFiltered), and their OPC UA form
(``ResultDataType``, the ``ResultReadyEventType`` event's fields).

``ResultState`` (OPC 40100-1, 12.19): 1 Completed (the processing was carried out: a job's picks,
possibly none; a cycle's outcome, ``placed`` or not, in ``ResultContent``), 3 Aborted (a cycle
ended by a Stop), 4 Failed (the request failed: why in ``ResultContent``'s ``error``).
``ResultContent``: one String, JSON: a job's is the REST pick answer's ``{"picks": [...]}`` (poses
in mm / rad, ``uncertainty`` with ``sigma_mm`` and ``sigma_yaw_deg``); a cycle's is
``{"picks": [<the cycle's pick>], "cycle": {...}}``; a failure's ``{"picks": [], "error": ...}``.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from asyncua import ua

KEEP = 100
STATE_COMPLETED, STATE_ABORTED, STATE_FAILED = 1, 3, 4


def mv_type(name: str) -> Any:
    """A Machine Vision structure's Python class (made by asyncua when the NodeSet is imported)."""
    return getattr(ua, name)


@dataclass(frozen=True)
class Result:
    """One result (ids are the Machine Vision model's strings)."""

    result_id: str
    job_id: str
    recipe_id: int
    configuration_id: str
    state: int
    created: datetime
    content: str
    meas_id: str | None = None
    part_id: str | None = None
    product_id: str | None = None
    external_recipe_id: str | None = None

    def matches(self, state: int, ids: dict[str, str | None]) -> bool:
        """Whether this result passes ``GetResultListFiltered``'s filter (0 / None / "": any)."""
        if state and state != self.state:
            return False
        mine = {"MeasId": self.meas_id, "PartId": self.part_id, "ExternalRecipeId": self.external_recipe_id,
                "InternalRecipeId": str(self.recipe_id), "ExternalConfigurationId": None,
                "InternalConfigurationId": self.configuration_id, "ProductId": self.product_id,
                "JobId": self.job_id}
        return all(not want or mine.get(name) == want for name, want in ids.items())

    def event_fields(self) -> dict[str, Any]:
        """The ``ResultReadyEventType`` fields (every mandatory one, and the optional ones known)."""
        out: dict[str, Any] = {
            "CreationTime": self.created, "ResultId": mv_type("ResultIdDataType")(Id=self.result_id),
            "JobId": mv_type("JobIdDataType")(Id=self.job_id), "IsPartial": False, "IsSimulated": False,
            "ResultState": self.state, "InternalRecipeId": internal_recipe_id(self.recipe_id),
            "InternalConfigurationId": mv_type("ConfigurationIdDataType")(Id=self.configuration_id),
            "ResultContent": [ua.Variant(self.content, ua.VariantType.String)]}
        for name, cls, value in (("MeasId", "MeasIdDataType", self.meas_id), ("PartId", "PartIdDataType", self.part_id),
                                 ("ProductId", "ProductIdDataType", self.product_id),
                                 ("ExternalRecipeId", "RecipeIdExternalDataType", self.external_recipe_id)):
            if value:
                out[name] = mv_type(cls)(Id=value)
        return out

    def structure(self) -> Any:
        """This result as a ``ResultDataType``."""
        f = self.event_fields()
        return mv_type("ResultDataType")(
            ResultId=f["ResultId"], IsPartial=False, IsSimulated=False, ResultState=self.state,
            MeasId=f.get("MeasId"), PartId=f.get("PartId"), ExternalRecipeId=f.get("ExternalRecipeId"),
            InternalRecipeId=f["InternalRecipeId"], ProductId=f.get("ProductId"),
            InternalConfigurationId=f["InternalConfigurationId"], JobId=f["JobId"], CreationTime=self.created,
            ResultContent=f["ResultContent"])


def internal_recipe_id(recipe_id: int, name: str | None = None, version: int | None = None,
                       sha256: bytes | None = None) -> Any:
    """A ``RecipeIdInternalDataType``: ``Id`` the recipe number, optional version, hash and name."""
    cls = mv_type("RecipeIdInternalDataType")
    return cls(Id=str(recipe_id), Version=None if version is None else str(version), Hash=sha256,
               HashAlgorithm=None if sha256 is None else "SHA-256",
               Description=None if name is None else ua.LocalizedText(name))


class ResultStore:
    """The last ``KEEP`` results, newest last (thread-safe)."""

    def __init__(self, keep: int = KEEP) -> None:
        self._results: deque[Result] = deque(maxlen=keep)
        self._lock = threading.Lock()
        self._count = 0

    def next_id(self) -> str:
        with self._lock:
            self._count += 1
            return f"result-{self._count}"

    def add(self, result: Result) -> None:
        with self._lock:
            self._results.append(result)

    def get(self, result_id: str) -> Result | None:
        with self._lock:
            return next((r for r in self._results if r.result_id == result_id), None)

    def newest_first(self) -> list[Result]:
        with self._lock:
            return list(reversed(self._results))

    def filtered(self, state: int, ids: dict[str, str | None], start: int, max_results: int
                 ) -> tuple[list[Result], bool]:
        """Matching results newest first from ``start`` (at most ``max_results``; 0: all); complete?"""
        hits = [r for r in self.newest_first() if r.matches(state, ids)]
        end = len(hits) if max_results == 0 else start + max_results
        return hits[start:end], end >= len(hits)


def id_of(value: Any) -> str | None:
    """The ``Id`` of a Machine Vision identifier structure (None: null or empty)."""
    ident = getattr(value, "Id", None)
    return ident or None


def ids_filter(names: Iterable[str], values: Iterable[Any]) -> dict[str, str | None]:
    return {n: id_of(v) for n, v in zip(names, values, strict=True)}
