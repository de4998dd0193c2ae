"""A store holding a virtual world's true camera and hand-eye, both active: for tests that need a
calibrated cell without running the capture routines (docs/testing.md, "Calibrated cells")."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from cellctl.cell import Cell
from cellctl.config import parse_config
from cellctl.jobs import JobManager
from cellctl.services import Services
from cellctl.store import Store, open_store
from drivers.sim import world as world_module

ROBOT_NOISE = {"sigma_mm": 0.02, "sigma_deg": 0.005}
"""The robot's repeatability a stored hand-eye states (a UR's, about)."""


def activate_truth(store: Store, truth: dict[str, Any], setup: str, T_target: Any, *,
                   robot_noise: bool = True) -> tuple[int, int]:
    """Save and activate the world's true camera calibration and a hand-eye of the given ``setup``
    (``eye-in-hand``: ``truth["T_tool_cam"]`` and ``T_target`` as ``T_base_target``; ``eye-to-hand``:
    ``truth["T_base_cam"]`` and ``T_target`` as ``T_tool_target``; 4x4, metres) with a negligible
    covariance and 0.05 px of pixel noise. Returns the two records' ids (camera, hand-eye)."""
    if setup == "eye-in-hand":
        he: dict[str, Any] = {"setup": setup, "T_tool_cam": truth["T_tool_cam"],
                              "T_base_target": np.asarray(T_target).tolist()}
    elif setup == "eye-to-hand":
        he = {"setup": setup, "T_base_cam": truth["T_base_cam"], "T_tool_target": np.asarray(T_target).tolist()}
    else:
        raise ValueError(f"setup {setup!r}: eye-in-hand or eye-to-hand")
    he |= {"uncertainty": {"covariance": (np.eye(6) * 1e-10).tolist()}, "pixel_sigma_px": 0.05}
    if robot_noise:
        he["robot_noise"] = dict(ROBOT_NOISE)
    cam = store.save_calibration("camera", "cam0", None, truth["camera"], {}, creator="test", note="truth")
    h = store.save_calibration("handeye", "cam0", "robot0", he, {}, creator="test", note="truth")
    store.activate(cam.id, "test")
    store.activate(h.id, "test")
    return cam.id, h.id


@contextmanager
def calibrated_services(config_data: dict[str, Any], seed: int) -> Iterator[Services]:
    """The service root of the cell config ``config_data`` (a parsed cell.yaml, e.g. the default one's with
    its store path and seeds set) on a fresh built-in world of ``seed`` (the robot at home), with that world's
    true camera and an eye-in-hand hand-eye (``T_base_target`` identity) stored and active; closed after."""
    world_module._WORLDS.pop(("built-in", seed), None)  # a fresh world, not one an earlier test moved
    config = parse_config(config_data)
    svc = Services(config, Cell(config), open_store(config), JobManager())
    try:
        activate_truth(svc.store, world_module.world_for(None, seed).truth(), "eye-in-hand", np.eye(4))
        yield svc
    finally:
        svc.close()
