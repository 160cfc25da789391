"""Iso-Simplicial Models (ISM) in Python: read, write, validate, sample, query, export and fit.

A binding over the Rust ISM libraries (``ism-format``, ``ism-validate``, ``ism-sample``,
``ism-export``, ``ism-fit``): every operation is the library call the ``ism`` command-line tool
makes, so results are the CLI's, number for number.

    >>> import ism
    >>> m = ism.read("spec/examples/sphere.ismb")
    >>> m.vertices.shape, m.simplices.dtype
    ((343, 3), dtype('uint32'))
    >>> m.validate().verdict
    'valid'
    >>> pts = m.sample_surface(1000, seed=7)
    >>> pts.dtype.names
    ('x', 'y', 'z', 'nx', 'ny', 'nz', 'f', 'simplex')

(The examples run from the repository root; ``python/tests/test_examples.py`` runs them.) See
``python/README.md`` (docs page) for a conversion script and a walk-through.
"""

from __future__ import annotations

import os
from typing import Any, Mapping, Optional, Union

from . import errors
from ._ism import FORMAT_VERSION, Model, Stage, __version__
from ._ism import fit as _fit
from ._ism import fit_hermite as _fit_hermite
from ._ism import fit_mesh as _fit_mesh
from ._ism import presets
from ._ism import read_bytes as _read_bytes
from ._ism import read_path as _read_path
from ._ism import validate_bytes as _validate_bytes
from ._ism import validate_path as _validate_path
from ._results import Surface, ValidationReport
from .errors import (
    EvaluationError,
    ExportError,
    FileError,
    FitError,
    FormatError,
    InternalError,
    InversionError,
    ISMError,
    SampleError,
    StructureError,
)

__all__ = [
    "FORMAT_VERSION",
    "Model",
    "Stage",
    "Surface",
    "ValidationReport",
    "__version__",
    "read",
    "loads",
    "write",
    "validate",
    "fit",
    "fit_mesh",
    "fit_hermite",
    "presets",
    "errors",
    "ISMError",
    "FileError",
    "FormatError",
    "StructureError",
    "EvaluationError",
    "SampleError",
    "ExportError",
    "InversionError",
    "FitError",
    "InternalError",
]

Source = Union[str, "os.PathLike[str]", bytes, bytearray, memoryview, Any]


def read(source: Source, *, check: bool = True, limits: Optional[Mapping[str, int]] = None) -> Model:
    """Reads a model from a path, ``bytes`` or a binary file object.

    The encoding (JSON, MessagePack or binary) is detected from the content, as the CLI does.
    With ``check`` (default) the structural rules are enforced; ``check=False`` reads a model that
    decodes but breaks them (to pass it to :meth:`Model.validate`).

    ``limits`` bounds what the reader accepts from an untrusted file, as the CLI's ``--max-*``
    flags do: a dict with any of ``max_payload_bytes``, ``max_vertices``, ``max_simplices``,
    ``max_stages`` and ``max_records`` (face records plus vertex maps over all stages). A file past
    a limit raises :class:`FormatError` with rule ``ISM-007`` and the member's JSON pointer; the
    defaults refuse nothing a readable file can hold.

    Raises :class:`FileError`, :class:`FormatError` (rule id, byte offset or JSON pointer) or
    :class:`StructureError` (every structural error in ``diagnostics``).

    >>> import ism
    >>> m = ism.read("spec/examples/circle-curved.ism.json")
    >>> with open("spec/examples/circle-curved.ismb", "rb") as f:
    ...     ism.read(f) == m
    True
    >>> try:
    ...     ism.read("spec/examples/circle-curved.ismb", limits={"max_simplices": 31})
    ... except ism.FormatError as e:
    ...     print(e.rule, e.pointer)
    ISM-007 /simplices
    """
    if isinstance(source, (bytes, bytearray, memoryview)):
        return _read_bytes(bytes(source), check, limits)
    if isinstance(source, (str, os.PathLike)):
        return _read_path(os.fspath(source), check, limits)
    if hasattr(source, "read"):
        data = source.read()
        if not isinstance(data, (bytes, bytearray)):
            raise TypeError("ism.read: the file object must be opened in binary mode ('rb')")
        return _read_bytes(bytes(data), check, limits)
    raise TypeError(f"ism.read: expected a path, bytes or a binary file object, got {type(source).__name__}")


def loads(
    data: Union[bytes, bytearray, memoryview], *, check: bool = True, limits: Optional[Mapping[str, int]] = None
) -> Model:
    """Reads a model from bytes (any encoding); see :func:`read`."""
    return _read_bytes(bytes(data), check, limits)


def write(model: Model, dest: Any, encoding: Union[str, None] = None, **options: Any) -> None:
    """Writes ``model`` to a path or binary file object; see :meth:`Model.write`."""
    model.write(dest, encoding, **options)


def validate(source: Union[Source, Model], **options: Any) -> ValidationReport:
    """Validates a model, a path, ``bytes`` or a binary file object as ``ism validate --json``
    does (for files, the report's ``file`` member names path, encoding and size).

    Options: ``max_issues``, ``threads``, ``max_pieces``, ``quality``, ``theorems``,
    ``progress(phase, done, total)`` (Ctrl-C or an exception from it stops the run), and for
    files ``limits`` (as in :func:`read`; a file past one is unreadable: :class:`FormatError`).
    A file that cannot be read raises :class:`FileError` or :class:`FormatError`; structural
    errors are findings of the report, not exceptions.
    """
    if isinstance(source, Model):
        return source.validate(**options)
    if isinstance(source, (bytes, bytearray, memoryview)):
        return _validate_bytes(bytes(source), **options)
    if isinstance(source, (str, os.PathLike)):
        return _validate_path(os.fspath(source), **options)
    if hasattr(source, "read"):
        return _validate_bytes(bytes(source.read()), **options)
    raise TypeError(f"ism.validate: expected a model, path, bytes or file object, got {type(source).__name__}")


def fit(expr: Union[str, None] = None, domain: Any = None, **options: Any) -> "tuple[Model, dict]":
    """Fits an ISM to the zero set of ``expr`` over ``domain`` (or ``preset=``), as ``ism fit``.

    Returns ``(model, report)``; the report has the members of ``ism fit --json``
    (``maxDistance``, ``toleranceMet``, ``components``, ``euler``, ...) and the same verdict:
    ``outcome`` is ``"passed"`` or the first failure (``"structural errors"``, ``"tolerance not
    met"``, ``"topology not certified"``, ``"topology differs"``); ``topologyMatches`` is ``None``
    when there is no reference topology (an expression), so nothing is claimed unchecked.

    >>> import ism
    >>> m, r = ism.fit("x^2 + y^2 - 0.25", (-1, 1, -1, 1), resolution=6)
    >>> r["toleranceMet"], r["components"], r["euler"], r["outcome"], r["topologyMatches"]
    (True, 1, 0, 'passed', None)
    """
    return _fit(expr, None if domain is None else [float(x) for x in domain], **options)


def fit_mesh(vertices: Any, faces: Any, **options: Any) -> "tuple[Model, dict]":
    """Fits an ISM to a closed, oriented triangle mesh, as ``ism fit --mesh``; returns
    ``(model, report)``."""
    return _fit_mesh(vertices, faces, **options)


def fit_hermite(data: Any, model: Union[Model, None] = None, *, progress: Any = None) -> "tuple[Model, dict]":
    """Fits positions and normals on sign-changing edges (spec/hermite.md; ``data`` a dict or JSON
    text), as ``ism fit --hermite``; returns ``(model, report)``. ``progress(phase, done, total)``
    is called per sweep over the free faces; Ctrl-C or an exception from it stops the fit."""
    return _fit_hermite(data, model, progress=progress)


def _register_meshio() -> None:
    try:
        from . import _meshio
    except ImportError:  # pragma: no cover - meshio is optional
        return
    _meshio.register()


_register_meshio()
