"""The licences of cellctl's dependencies, read from the installed distributions' metadata (what pip
shows): the runtime closure of ``cellctl``'s requirements (with its optional extras, without ``test``)."""

from __future__ import annotations

import importlib.metadata as md
import re
from typing import Any

from packaging.requirements import Requirement

PERMISSIVE = re.compile(r"\b(MIT|BSD|Apache|PSF|Python Software Foundation|ISC|Zlib|0BSD|CC0|MIT-CMU|MIT-0|"
                        r"Unlicense|HPND)", re.IGNORECASE)
WEAK_COPYLEFT = re.compile(r"\b(LGPL|Lesser General Public|MPL|Mozilla Public)", re.IGNORECASE)
STRONG_COPYLEFT = re.compile(r"(?<!Lesser )\b(GPL|General Public License)", re.IGNORECASE)


def licence_text(dist: md.Distribution) -> str:
    """``License-Expression``, else ``License`` (first line) and the ``License ::`` classifiers."""
    meta: Any = dist.metadata  # an email.message.Message: .get and .get_all
    if meta.get("License-Expression"):
        return str(meta["License-Expression"])
    classifiers = [c.split("::")[-1].strip() for c in meta.get_all("Classifier") or [] if c.startswith("License ::")]
    first = (meta.get("License") or "").strip().splitlines()
    return "; ".join([*first[:1], *classifiers])


def kind(text: str) -> str:
    """permissive, weak copyleft (LGPL, MPL), strong copyleft (GPL) or unknown; the most restrictive
    term of an AND, the least restrictive of an OR (a dual licence may be taken under either)."""
    options = re.split(r"\bOR\b|\s/\s", text) if " OR " in text else [text]
    found = [_kind_of(o) for o in options]
    order = ["permissive", "weak copyleft", "strong copyleft", "unknown"]
    return min(found, key=order.index)


def _kind_of(text: str) -> str:
    without_lesser = WEAK_COPYLEFT.sub("", text)
    if STRONG_COPYLEFT.search(without_lesser) and "Proprietary" not in text:
        return "strong copyleft"
    if WEAK_COPYLEFT.search(text):
        return "weak copyleft"
    if PERMISSIVE.search(text):
        return "permissive"
    if STRONG_COPYLEFT.search(without_lesser):
        return "strong copyleft"
    return "unknown"


def runtime_closure() -> dict[str, md.Distribution]:
    """Every installed distribution cellctl needs at run time (its extras included, ``test`` not)."""
    found: dict[str, md.Distribution] = {}

    def walk(name: str) -> None:
        key = name.lower().replace("_", "-").replace(".", "-")
        if key in found:
            return
        try:
            dist = md.distribution(name)
        except md.PackageNotFoundError:
            return
        found[key] = dist
        for raw in dist.requires or []:
            req = Requirement(raw)
            if req.marker is not None and not req.marker.evaluate({"extra": ""}):
                continue
            walk(req.name)

    for raw in md.distribution("cellctl").requires or []:
        req = Requirement(raw)
        extra = re.search(r'extra == "([^"]+)"', str(req.marker or ""))
        if extra is not None and extra.group(1) == "test":
            continue
        if req.marker is not None and extra is None and not req.marker.evaluate({"extra": ""}):
            continue
        walk(req.name)
    return found
