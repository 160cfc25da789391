"""The exceptions of the ``ism`` package.

Every error the package raises for bad input or a failed operation is an :class:`ISMError`. Errors
that come from a rule of the specification carry that rule and its place::

    >>> import ism
    >>> try:
    ...     ism.loads(b'{"version": "1.0"}')
    ... except ism.FormatError as e:
    ...     print(e.rule, repr(e.pointer), e.offset)
    ISM-006 '' 0

Attributes (``None`` when the error has none):

- ``rule``: the rule id of ``spec/validation.md``, e.g. ``"ISM-010"``;
- ``pointer``: a JSON pointer (RFC 6901) into the JSON encoding, e.g. ``"/stages/0/faces/3"``;
- ``offset``: a byte offset in the file;
- ``location``: the whole location as a dict (pointer, offset, stage, simplex, face, vertex);
- ``diagnostics``: every finding, as dicts ``{"rule", "severity", "location", "message"}``
  (a :class:`StructureError` lists all structural errors found).
"""

from __future__ import annotations

from typing import Any, Optional, Sequence


class ISMError(Exception):
    """Base class of the package's errors."""

    def __init__(
        self,
        message: str,
        *,
        rule: Optional[str] = None,
        pointer: Optional[str] = None,
        offset: Optional[int] = None,
        location: Optional[dict] = None,
        diagnostics: Sequence[dict] = (),
    ) -> None:
        super().__init__(message)
        self.message = message
        self.rule = rule
        self.pointer = pointer
        self.offset = offset
        self.location = location if location is not None else {}
        self.diagnostics = list(diagnostics)


class FileError(ISMError, OSError):
    """The operating system refused to read or write a file."""


class FormatError(ISMError, ValueError):
    """The bytes break a container or encoding rule (spec §7; rules ISM-0xx)."""


class StructureError(ISMError, ValueError):
    """The decoded model breaks structural rules (spec §2–5); ``diagnostics`` lists them all."""


class EvaluationError(ISMError, ValueError):
    """The model cannot be evaluated (degenerate simplices, malformed stage records)."""


class SampleError(ISMError):
    """Sampling or querying failed (empty shape, uncertified stage, numerical failure)."""


class ExportError(ISMError):
    """Extraction or export failed."""


class InversionError(ExportError):
    """A stage inversion did not converge on the shape: a numerical failure (``validate()`` tells
    whether the model itself is valid)."""


class FitError(ISMError):
    """A fit, smoothing or Hermite fit could not be carried out."""


class InternalError(ISMError):
    """A bug in the library (a Rust panic caught at the boundary); please report it."""


def _make(kind: str, message: str, diagnostics: Sequence[dict] = ()) -> ISMError:
    """Builds an error of class ``kind`` from the library's diagnostics (called by ``ism._ism``)."""
    cls = globals()[kind]
    first: Any = diagnostics[0] if diagnostics else None
    location = dict(first["location"]) if first else {}
    return cls(
        message,
        rule=first["rule"] if first else None,
        pointer=location.get("pointer"),
        offset=location.get("offset"),
        location=location,
        diagnostics=diagnostics,
    )
