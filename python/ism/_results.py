"""Result objects: the validation report and an extracted surface."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

import numpy as np


class ValidationReport:
    """The report of ``ism validate --json`` (``spec/schema/report.schema.json``).

    ``verdict`` is ``"valid"``, ``"invalid"`` or ``"undetermined"``; ``diagnostics`` lists the
    messages (``code`` = rule id, ``severity``, ``location``, ``message``); ``certificates`` gives
    per stage how many elements each certificate proved; :meth:`to_dict` is the whole report.
    """

    def __init__(self, report: Dict[str, Any]) -> None:
        self._report = report

    @classmethod
    def from_json(cls, text: str) -> "ValidationReport":
        return cls(json.loads(text))

    @property
    def verdict(self) -> str:
        return self._report["verdict"]

    @property
    def valid(self) -> bool:
        return self.verdict == "valid"

    def __bool__(self) -> bool:
        return self.valid

    @property
    def diagnostics(self) -> List[Dict[str, Any]]:
        return self._report["issues"]["messages"]

    @property
    def rules(self) -> List[str]:
        """Rule ids of the listed messages, in report order."""
        return [m["code"] for m in self.diagnostics]

    @property
    def counts(self) -> Dict[str, int]:
        """Messages per rule id (all are counted, even those not listed)."""
        return self._report["issues"]["counts"]

    @property
    def stages(self) -> List[Dict[str, Any]]:
        return self._report["stages"]

    @property
    def certificates(self) -> List[Dict[str, int]]:
        """Per stage: certificate name -> number of elements it certified."""
        return [s.get("certificates", {}) for s in self.stages]

    def to_dict(self) -> Dict[str, Any]:
        """The report as plain Python data (a deep copy)."""
        return json.loads(json.dumps(self._report))

    def __repr__(self) -> str:
        i = self._report["issues"]
        return (
            f"<ism.ValidationReport {self.verdict}: {i['numErrors']} error(s), "
            f"{i['numWarnings']} warning(s), {i['numInfos']} info(s)>"
        )


@dataclass
class Surface:
    """An extracted shape: a triangle mesh (3D) or polyline segments (2D), welded.

    ``positions`` and ``normals`` are (Nv, n) float64 (normals = ∇F/|∇F|, outward); ``cells`` is
    (Nc, 3) triangles or (Nc, 2) segments (uint32); ``cell_simplex`` the source top simplex of each
    cell; ``report`` the extraction's summary (topology, inversion residual, ...).
    """

    dimension: int
    positions: np.ndarray
    normals: np.ndarray
    cells: np.ndarray
    cell_simplex: np.ndarray
    vertex_simplex: np.ndarray
    gradient_norm: np.ndarray
    report: Dict[str, Any] = field(default_factory=dict)

    @property
    def faces(self) -> np.ndarray:
        """The triangles (3D models)."""
        if self.dimension != 3:
            raise AttributeError("a 2D model's shape is made of segments; use .segments or .cells")
        return self.cells

    @property
    def segments(self) -> np.ndarray:
        """The segments (2D models)."""
        if self.dimension != 2:
            raise AttributeError("a 3D model's shape is made of triangles; use .faces or .cells")
        return self.cells

    def polylines(self) -> List[np.ndarray]:
        """2D: the segments chained head to tail into polylines (arrays of vertex ids; a closed
        curve repeats its first id at the end)."""
        nxt: Dict[int, int] = {int(a): int(b) for a, b in self.segments}
        targets = set(nxt.values())
        seen: set = set()
        out: List[np.ndarray] = []
        # Open chains first (from vertices nothing points to), then the closed curves.
        for s in [s for s in nxt if s not in targets] + list(nxt):
            if s in seen:
                continue
            chain = [s]
            seen.add(s)
            v: Optional[int] = nxt.get(s)
            while v is not None and v not in seen:
                chain.append(v)
                seen.add(v)
                v = nxt.get(v)
            if v == s:
                chain.append(s)
            out.append(np.array(chain, dtype=np.uint32))
        return out
