"""Type stubs of the compiled module ``ism._ism`` (the Rust half of the package)."""

from os import PathLike
from typing import Any, Callable, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

from ._results import Surface, ValidationReport

__version__: str
FORMAT_VERSION: str

_Path = Union[str, "PathLike[str]"]
_Progress = Optional[Callable[[int, int], Any]]
# (phase, done, total): validation, extraction, export, smoothing, Hermite fits; total 0 = not counted.
_Steps = Optional[Callable[[str, int, int], Any]]

class Stage:
    """One stage of a model: kind, degree, direction and flat tables (see ``python/README.md``)."""

    def __init__(
        self,
        kind: str,
        degree: int,
        direction: str = "implicit",
        *,
        faces: Optional[Iterable[Tuple[Any, Any] | Tuple[Any, Any, Any]]] = None,
        vertex_maps: Optional[Iterable[Tuple[int, Any]]] = None,
        name: Optional[str] = None,
        extras: Any = None,
    ) -> None: ...
    @staticmethod
    def from_tables(
        kind: str,
        degree: int,
        direction: str = "implicit",
        *,
        face_offsets: Any = None,
        face_vertices: Any = None,
        point_offsets: Any = None,
        points: Any = None,
        weight_offsets: Any = None,
        weights: Any = None,
        map_vertices: Any = None,
        coefficient_offsets: Any = None,
        coefficients: Any = None,
        name: Optional[str] = None,
        extras: Any = None,
    ) -> Stage: ...
    @property
    def kind(self) -> str: ...
    @property
    def degree(self) -> int: ...
    @property
    def direction(self) -> str: ...
    @property
    def name(self) -> Optional[str]: ...
    @property
    def extras(self) -> Any: ...
    @property
    def num_faces(self) -> int: ...
    @property
    def face_offsets(self) -> npt.NDArray[np.uint32]: ...
    @property
    def face_vertices(self) -> npt.NDArray[np.uint32]: ...
    @property
    def point_offsets(self) -> npt.NDArray[np.uint32]: ...
    @property
    def points(self) -> npt.NDArray[np.float64]: ...
    @property
    def weight_offsets(self) -> npt.NDArray[np.uint32]: ...
    @property
    def weights(self) -> npt.NDArray[np.float64]: ...
    @property
    def map_vertices(self) -> npt.NDArray[np.uint32]: ...
    @property
    def coefficient_offsets(self) -> npt.NDArray[np.uint32]: ...
    @property
    def coefficients(self) -> npt.NDArray[np.float64]: ...
    @property
    def faces(self) -> List[Tuple[npt.NDArray[np.uint32], npt.NDArray[np.float64], npt.NDArray[np.float64]]]: ...
    @property
    def vertex_maps(self) -> List[Tuple[int, npt.NDArray[np.float64]]]: ...
    def tables(self) -> Dict[str, Any]: ...

class Model:
    """An Iso-Simplicial Model (immutable); arrays are read-only numpy views tied to the model."""

    def __init__(
        self,
        vertices: npt.ArrayLike,
        simplices: npt.ArrayLike,
        values: npt.ArrayLike,
        level: float = 0.0,
        stages: Optional[Sequence[Stage]] = None,
        *,
        metadata: Optional[Dict[str, str]] = None,
        extras: Any = None,
        extensions_used: Optional[List[str]] = None,
        extensions_required: Optional[List[str]] = None,
        extensions: Optional[Dict[str, Any]] = None,
        check: bool = True,
    ) -> None: ...
    @property
    def version(self) -> str: ...
    @property
    def dimension(self) -> int: ...
    @property
    def num_vertices(self) -> int: ...
    @property
    def num_simplices(self) -> int: ...
    @property
    def encoding(self) -> Optional[str]: ...
    @property
    def vertices(self) -> npt.NDArray[np.float64]: ...
    @property
    def simplices(self) -> npt.NDArray[np.uint32]: ...
    @property
    def values(self) -> npt.NDArray[np.float64]: ...
    def faces(self, k: int) -> npt.NDArray[np.uint32]: ...
    @property
    def neighbours(self) -> npt.NDArray[np.uint32]: ...
    def stage_tables(self, i: int) -> Dict[str, Any]: ...
    @property
    def level(self) -> float: ...
    @property
    def stages(self) -> Tuple[Stage, ...]: ...
    @property
    def metadata(self) -> Dict[str, str]: ...
    @property
    def extras(self) -> Any: ...
    @property
    def extensions_used(self) -> List[str]: ...
    @property
    def extensions_required(self) -> List[str]: ...
    @property
    def extensions(self) -> Dict[str, Any]: ...
    def to_bytes(self, encoding: str = "binary", *, pretty: bool = False, container: bool = False) -> bytes: ...  # json | msgpack | binary | compact | compressed | structured
    def write_path(self, path: _Path, encoding: Optional[str] = None, *, pretty: bool = False, container: bool = False) -> None: ...
    def write(self, dest: Any, encoding: Optional[str] = None, *, pretty: bool = False, container: bool = False) -> None: ...
    def validate(
        self,
        *,
        max_issues: int = 100,
        threads: int = 0,
        max_pieces: int = ...,
        quality: bool = False,
        theorems: bool = True,
        progress: _Steps = None,
    ) -> ValidationReport: ...
    def extract_surface(
        self, tolerance: float = 1e-3, *, max_depth: int = 8, linear: bool = False, coarsen: Optional[bool] = None, threads: int = 0,
        progress: _Steps = None
    ) -> Surface: ...
    def export(
        self,
        path: _Path,
        *,
        tolerance: float = 1e-3,
        max_depth: int = 8,
        linear: bool = False,
        volume: bool = False,
        coarsen: Optional[bool] = None,
        compress: bool = False,
        threads: int = 0,
        progress: _Steps = None,
    ) -> Dict[str, Any]: ...
    def sample_surface(self, n: int, seed: int = 0, *, threads: int = 0, progress: _Progress = None) -> np.ndarray: ...
    def sample_volume(
        self, n: int, seed: int = 0, *, box: Optional[Tuple[Sequence[float], Sequence[float]]] = None, threads: int = 0, progress: _Progress = None
    ) -> np.ndarray: ...
    def sample_near_surface(self, n: int, sigma: float, seed: int = 0, *, threads: int = 0, progress: _Progress = None) -> np.ndarray: ...
    def query(self, points: npt.ArrayLike, *, threads: int = 0, progress: _Progress = None) -> np.ndarray: ...
    def smooth(
        self,
        *,
        iterations: Optional[int] = None,
        alpha: Optional[float] = None,
        rational: bool = False,
        degree: Optional[int] = None,
        threads: int = 0,
        progress: _Steps = None,
    ) -> Tuple[Model, Dict[str, Any]]: ...
    def to_trimesh(self, tolerance: float = 1e-3, **options: Any) -> Any: ...
    def to_pyvista(self, tolerance: float = 1e-3, *, volume: bool = False, **options: Any) -> Any: ...
    def to_meshio(self) -> Any: ...

def read_path(path: _Path, check: bool = True, limits: Optional[Mapping[str, int]] = None) -> Model: ...
def read_bytes(data: bytes, check: bool = True, limits: Optional[Mapping[str, int]] = None) -> Model: ...
def validate_path(path: _Path, **options: Any) -> ValidationReport: ...
def validate_bytes(data: bytes, **options: Any) -> ValidationReport: ...
def fit(
    expr: Optional[str] = None,
    domain: Optional[Sequence[float]] = None,
    *,
    preset: Optional[str] = None,
    resolution: int = 8,
    tolerance: Optional[float] = None,
    max_simplices: int = 200000,
    optimize: bool = True,
    rational: bool = False,
    topology: bool = True,
    lattice: bool = False,
    progress: Optional[Callable[[str, int, float], Any]] = None,
) -> Tuple[Model, Dict[str, Any]]: ...
def fit_mesh(
    vertices: npt.ArrayLike,
    faces: npt.ArrayLike,
    *,
    domain: Optional[Sequence[float]] = None,
    margin: float = 0.05,
    resolution: int = 8,
    tolerance: Optional[float] = None,
    max_simplices: int = 200000,
    optimize: bool = True,
    rational: bool = False,
    topology: bool = True,
    lattice: bool = False,
    name: str = "mesh",
    progress: Optional[Callable[[str, int, float], Any]] = None,
) -> Tuple[Model, Dict[str, Any]]: ...
def fit_hermite(data: Any, model: Optional[Model] = None, *, progress: _Steps = None) -> Tuple[Model, Dict[str, Any]]: ...
def presets() -> List[Dict[str, Any]]: ...
