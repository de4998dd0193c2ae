"""The OPC UA for Machine Vision NodeSet (OPC 40100-1), shipped in ``cellctl/plc/nodesets/``, loaded
into an asyncua server, with the one correction the published file needs.

The NodeSet declares ``RecipeIdExternalDataType``, ``RecipeIdInternalDataType`` and
``ConfigurationIdDataType`` as subtypes of the abstract ``BinaryIdBaseDataType`` with an empty
``<Definition/>``: no fields of their own. The specification's text (12.9, 12.10, 12.13) gives them
the base's fields, and OPC UA Part 3 (5.8.3) says a subtype's StructureDefinition lists the base's
fields first. asyncua turns an empty definition into an alias without fields and a client of
another stack finds no DataTypeDefinition to encode them, so before importing we copy the base's
fields (``Id``, optional ``Version``, ``Hash``, ``HashAlgorithm``, ``Description``) into the three
definitions. The file on disk stays as published.
"""

from __future__ import annotations

import re
from importlib import resources

from asyncua import Server

NAMESPACE_MV = "http://opcfoundation.org/UA/MachineVision"
NODESET_FILE = "Opc.Ua.MachineVision.NodeSet2.xml"
BINARY_ID_SUBTYPES = ("RecipeIdExternalDataType", "RecipeIdInternalDataType", "ConfigurationIdDataType")
_BASE_DEFINITION = re.compile(r'<Definition Name="1:BinaryIdBaseDataType">(.*?)</Definition>', re.S)


def nodeset_text() -> str:
    """The published NodeSet2 XML (package data)."""
    return resources.files("cellctl.plc").joinpath("nodesets", NODESET_FILE).read_text(encoding="utf-8")


def corrected_nodeset(text: str) -> str:
    """``text`` with the base's fields declared in the three identifier types (see the module docstring)."""
    base = _BASE_DEFINITION.search(text)
    if base is None:
        raise ValueError(f"{NODESET_FILE}: BinaryIdBaseDataType has no field definition")
    for name in BINARY_ID_SUBTYPES:
        empty = f'<Definition Name="1:{name}" />'
        if text.count(empty) != 1:
            raise ValueError(f"{NODESET_FILE}: expected one empty definition of {name}")
        text = text.replace(empty, f'<Definition Name="1:{name}">{base.group(1)}</Definition>')
    return text


async def import_machine_vision(server: Server) -> int:
    """Import the corrected NodeSet into ``server`` (its types get Python classes in ``asyncua.ua``);
    the namespace index of ``NAMESPACE_MV``."""
    await server.import_xml(xmlstring=corrected_nodeset(nodeset_text()))
    return int(await server.get_namespace_index(NAMESPACE_MV))
