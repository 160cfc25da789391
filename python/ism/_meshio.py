"""A meshio plugin, registered when ``ism`` is imported (if meshio is installed):
``meshio.read("x.ismb")`` gives the linear complex with the vertex values as point data ``"f"``.

Reading only: an ISM needs vertex values and stages that a general mesh does not have, so meshio
cannot write one (use ``ism import`` or :class:`ism.Model` for that).
"""

from __future__ import annotations

from typing import Any

import meshio

EXTENSIONS = [".ismb", ".ismc", ".ismz", ".isms", ".ism.json", ".ism.msgpack"]


def read(filename: Any) -> "meshio.Mesh":
    """meshio reader: any ISM encoding, detected from content."""
    import ism

    return ism.read(filename).to_meshio()


def register() -> None:
    """Registers the ``ism`` format with meshio (idempotent)."""
    meshio.register_format("ism", EXTENSIONS, read, {})
