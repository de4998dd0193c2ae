"""OPC UA for Machine Vision (OPC 40100-1): ``Objects/VisionSystem`` beside the ``Cell`` object of
the PLC's OPC UA server (docs/plc-opcua.md). The NodeSet is package data (``cellctl/plc/nodesets``)."""

from cellctl.plc.opcua_mv.system import VisionSystem, add_vision_system

__all__ = ["VisionSystem", "add_vision_system"]
