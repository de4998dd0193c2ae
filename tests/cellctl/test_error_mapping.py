"""The API maps the project's own error types (by type, not by module) to a 4xx; anything else is a 500.

Routes raising each kind on the real error handlers (``install_error_handlers``): a library root's
subclass is the caller's 4xx with its message; a bare ``ValueError`` or ``KeyError`` (numpy's, the
stdlib's, raised inside our own code) is a bug: 500 naming the request id.
"""

from __future__ import annotations

import importlib
import pkgutil

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from calibration.handeye import HandEyeError
from calibration.measure import MappingError
from cellctl.api.errors import OWN_ERRORS, install_error_handlers
from vision.errors import SettingsError


def _client() -> TestClient:
    app = FastAPI()
    install_error_handlers(app)
    raised: dict[str, Exception] = {
        "bare-value": ValueError("operands could not be broadcast together"),
        "bare-key": KeyError("fx"),
        "calibration": MappingError("the working plane's height is needed"),
        "handeye": HandEyeError("the stations rotate about one axis only"),
        "vision": SettingsError("min_score must lie in (0, 1], got 2"),
    }

    @app.get("/raise/{kind}")
    def _raise(kind: str) -> None:
        raise raised[kind]

    return TestClient(app, raise_server_exceptions=False)


@pytest.mark.parametrize("kind", ["bare-value", "bare-key"])
def test_an_error_that_is_not_ours_is_a_500_with_the_request_id(kind: str) -> None:
    r = _client().get(f"/raise/{kind}", headers={"X-Request-Id": "rid-4711"})
    assert r.status_code == 500
    assert r.json()["error"]["code"] == "internal_error"
    assert "rid-4711" in r.json()["error"]["message"] and r.headers["X-Request-Id"] == "rid-4711"


@pytest.mark.parametrize(("kind", "words"), [("calibration", "working plane"), ("handeye", "one axis"),
                                             ("vision", "min_score")])
def test_a_library_root_error_is_the_callers_422(kind: str, words: str) -> None:
    r = _client().get(f"/raise/{kind}")
    assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_input"
    assert words in r.json()["error"]["message"]


def test_every_typed_value_or_lookup_error_of_ours_is_mapped() -> None:
    """A new ValueError/LookupError subclass in our packages outside OWN_ERRORS would answer 500."""
    for top in ("cellctl", "drivers", "calibration", "vision"):
        pkg = importlib.import_module(top)
        for m in pkgutil.walk_packages(pkg.__path__, top + "."):
            if not m.name.endswith("__main__"):
                importlib.import_module(m.name)

    def subclasses(c: type[Exception]) -> list[type[Exception]]:
        found: list[type[Exception]] = []
        for sub in c.__subclasses__():
            found += [sub, *subclasses(sub)]
        return found

    ours = {c for base in (ValueError, LookupError) for c in subclasses(base)
            if c.__module__.split(".")[0] in ("cellctl", "drivers", "calibration", "vision")}
    assert len(ours) > 30
    unmapped = sorted(f"{c.__module__}.{c.__qualname__}" for c in ours if not issubclass(c, OWN_ERRORS))
    assert not unmapped, f"add these to cellctl.api.errors.OWN_ERRORS (or derive them from a root): {unmapped}"
