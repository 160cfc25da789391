//! `ism.Model` and `ism.Stage`: an immutable model and its stages, with numpy arrays.
//!
//! The model's coordinate, simplex and value arrays are views of the Rust model's own buffers
//! (no copy); each view keeps the `Model` object alive as its numpy base, and is read-only because
//! the model is immutable. The stage tables (face ids, points, weights) are laid out flat with
//! offsets; `ism_format::Model` stores one record per face, so those are built (copied) on first
//! access and cached.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, OnceLock};

use ism_format::{
    io, Direction, Encoding, FaceRecord, IndexedModel, JsonValue, StageKind, VertexMap,
};
use numpy::ndarray::{ArrayView1, ArrayView2};
use numpy::{
    PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict, PyList, PyTuple};

use crate::errors::format_error;

/// An Iso-Simplicial Model: a simplicial complex with a value per vertex, a level and a sequence
/// of stages; its shape is the level set `F = level` of the deformed function. Immutable; its
/// arrays are read-only numpy views that keep the model's memory alive.
///
/// >>> import ism, numpy as np
/// >>> bend = ism.Stage("bezier", 2, faces=[([0, 2], [0.6, 0.4])])
/// >>> square = ism.Model(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float),
/// ...                    [[0, 1, 2], [0, 2, 3]], [-1.0, 1, 1, 1], 0.0, [bend],
/// ...                    metadata={"name": "square"})
/// >>> square.simplices.dtype, square.stages[0].points
/// (dtype('uint32'), array([0.6, 0.4]))
/// >>> ism.loads(square.to_bytes("msgpack")) == square
/// True
/// >>> square.validate().verdict
/// 'valid'
#[pyclass(frozen, module = "ism", name = "Model")]
pub struct Model {
    pub(crate) inner: Shared,
    encoding: Option<Encoding>,
    stages: OnceLock<Py<PyTuple>>,
    /// The checked index (topology, dense stage tables): the reader's own for checked reads, built
    /// on first use (from a copy of the model) otherwise.
    index: OnceLock<Result<IndexedModel, ism_format::Error>>,
    /// The evaluator and surface table, built on first use by sampling and queries and kept.
    pub(crate) sampler: Mutex<Option<ism_sample::Sampler>>,
    /// The complex as a Kuhn grid and its edge splits, for a model a fit returned: the structured
    /// encoding writes it (`complexForm` 1, spec §7.4.3) instead of the coordinates and ids.
    refinement: Option<Arc<ism_format::refine::KuhnRefinement>>,
}

/// The model as the binding holds it: shared with worker threads without a copy. A checked read
/// keeps the reader's [`IndexedModel`] (which owns the model); other models are plain.
#[derive(Clone)]
pub(crate) enum Shared {
    Plain(Arc<ism_format::Model>),
    Indexed(IndexedModel),
}

impl std::ops::Deref for Shared {
    type Target = ism_format::Model;
    fn deref(&self) -> &ism_format::Model {
        match self {
            Shared::Plain(m) => m,
            Shared::Indexed(i) => i.model(),
        }
    }
}

impl Model {
    pub(crate) fn new(model: ism_format::Model, encoding: Option<Encoding>) -> Model {
        Model::from_shared(Shared::Plain(Arc::new(model)), encoding)
    }

    fn from_shared(inner: Shared, encoding: Option<Encoding>) -> Model {
        Model {
            inner,
            encoding,
            stages: OnceLock::new(),
            index: OnceLock::new(),
            sampler: Mutex::new(None),
            refinement: None,
        }
    }

    /// This model with the refinement its complex came from (see [`Model::refinement`]'s field).
    pub(crate) fn with_refinement(
        mut self,
        refinement: Option<ism_format::refine::KuhnRefinement>,
    ) -> Model {
        self.refinement = refinement.map(Arc::new);
        self
    }

    /// The index, built on first use when the model was not read checked.
    fn indexed(&self, py: Python<'_>) -> PyResult<&IndexedModel> {
        if let Shared::Indexed(i) = &self.inner {
            return Ok(i);
        }
        let model = &*self.inner;
        self.index
            .get_or_init(|| py.allow_threads(|| IndexedModel::new(model.clone())))
            .as_ref()
            .map_err(|e| format_error(py, e))
    }
}

/// A read-only numpy view of `view`'s data, kept alive by `owner` (the `Model` or `Stage`).
fn view_of<'py, T: numpy::Element, D: numpy::ndarray::Dimension>(
    owner: &Bound<'py, PyAny>,
    view: numpy::ndarray::ArrayView<'_, T, D>,
) -> PyResult<Bound<'py, numpy::PyArray<T, D>>> {
    // SAFETY: the data belongs to the frozen pyclass `owner`, whose Rust contents never change
    // and are freed only after every numpy array that has `owner` as its base is gone (numpy
    // holds a reference to the base). The array is made read-only below, so numpy never writes
    // through it either.
    let array = unsafe { numpy::PyArray::borrow_from_array(&view, owner.clone()) };
    let kwargs = PyDict::new(owner.py());
    kwargs.set_item("write", false)?;
    array.call_method("setflags", (), Some(&kwargs))?;
    Ok(array)
}

fn kind_from_str(text: &str) -> PyResult<StageKind> {
    match text {
        "bezier" => Ok(StageKind::Bezier),
        "rational" => Ok(StageKind::Rational),
        "monotonic" => Ok(StageKind::Monotonic),
        _ => Err(PyValueError::new_err(format!(
            "stage kind {text:?}: expected 'bezier', 'rational' or 'monotonic'"
        ))),
    }
}

fn direction_from_str(text: &str) -> PyResult<Direction> {
    match text {
        "implicit" => Ok(Direction::Implicit),
        "parametric" => Ok(Direction::Parametric),
        _ => Err(PyValueError::new_err(format!(
            "stage direction {text:?}: expected 'implicit' or 'parametric'"
        ))),
    }
}

pub(crate) fn encoding_from_str(text: &str) -> PyResult<Encoding> {
    match text {
        "json" => Ok(Encoding::Json),
        "msgpack" | "messagepack" => Ok(Encoding::MessagePack),
        "binary" => Ok(Encoding::Binary),
        "compact" => Ok(Encoding::Compact),
        "compressed" => Ok(Encoding::Compressed),
        "structured" => Ok(Encoding::Structured),
        _ => Err(PyValueError::new_err(format!(
            "encoding {text:?}: expected 'json', 'msgpack', 'binary', 'compact', 'compressed' or 'structured'"
        ))),
    }
}

fn float_array<'py>(
    obj: &Bound<'py, PyAny>,
    name: &str,
    ndim: usize,
) -> PyResult<Bound<'py, PyAny>> {
    crate::convert(obj.py())?
        .getattr("float_array")?
        .call1((obj, name, ndim))
}

fn index_array<'py>(
    obj: &Bound<'py, PyAny>,
    name: &str,
    ndim: usize,
) -> PyResult<Bound<'py, PyAny>> {
    crate::convert(obj.py())?
        .getattr("index_array")?
        .call1((obj, name, ndim))
}

fn f64_vec(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<f64>> {
    let a = float_array(obj, name, 1)?;
    let a: PyReadonlyArray1<f64> = a.extract()?;
    Ok(a.as_slice()?.to_vec())
}

fn u32_vec(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<u32>> {
    let a = index_array(obj, name, 1)?;
    let a: PyReadonlyArray1<u32> = a.extract()?;
    Ok(a.as_slice()?.to_vec())
}

/// Flattens any array-like of numbers (points are given per multi-index or flat).
fn f64_flat(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<f64>> {
    let np = obj.py().import("numpy")?;
    let flat = np.getattr("ravel")?.call1((obj,))?;
    f64_vec(&flat, name)
}

fn json_value(obj: Option<&Bound<'_, PyAny>>, name: &str) -> PyResult<JsonValue> {
    match obj {
        None => Ok(JsonValue::default()),
        Some(o) if o.is_none() => Ok(JsonValue::default()),
        Some(o) => Ok(JsonValue(crate::py_to_value(o, name)?)),
    }
}

/// Splits `flat` by `offsets` (n + 1 increasing entries from 0 to `flat.len()`).
fn split<T: Clone>(flat: &[T], offsets: &[u32], name: &str) -> PyResult<Vec<Vec<T>>> {
    let bad = || {
        PyValueError::new_err(format!(
            "{name}: offsets must start at 0, never decrease and end at the data's length {}",
            flat.len()
        ))
    };
    if offsets.first() != Some(&0) || *offsets.last().unwrap_or(&0) as usize != flat.len() {
        return Err(bad());
    }
    offsets
        .windows(2)
        .map(|w| {
            if w[1] < w[0] {
                Err(bad())
            } else {
                Ok(flat[w[0] as usize..w[1] as usize].to_vec())
            }
        })
        .collect()
}

/// One stage of a model: kind, degree, direction and its tables.
///
/// Tables, flat with offsets (entry `i` of a table is `data[offsets[i]:offsets[i+1]]`):
/// `face_vertices` by `face_offsets` (each face's sorted global vertex ids), `points` by
/// `point_offsets` (barycentric coordinates w.r.t. the face, `k + 1` per owned multi-index, in
/// canonical order), `weights` by `weight_offsets` (rational stages), and for monotonic stages
/// `coefficients` by `coefficient_offsets` with `map_vertices` (one Bernstein polynomial per
/// vertex).
#[pyclass(frozen, module = "ism", name = "Stage")]
pub struct Stage {
    pub(crate) inner: ism_format::Stage,
    tables: OnceLock<Tables>,
}

/// The flat tables of a stage (built once).
struct Tables {
    face_offsets: Vec<u32>,
    face_vertices: Vec<u32>,
    point_offsets: Vec<u32>,
    points: Vec<f64>,
    weight_offsets: Vec<u32>,
    weights: Vec<f64>,
    map_vertices: Vec<u32>,
    coefficient_offsets: Vec<u32>,
    coefficients: Vec<f64>,
}

impl Stage {
    pub(crate) fn new(inner: ism_format::Stage) -> Stage {
        Stage {
            inner,
            tables: OnceLock::new(),
        }
    }

    fn flat(&self) -> &Tables {
        self.tables.get_or_init(|| {
            // One pass over the records with every table allocated once (the flat layout is a copy
            // of the per-record model; this is most of what reading a table costs).
            let f = &self.inner.faces;
            let m = &self.inner.vertex_maps;
            let mut t = Tables {
                face_offsets: Vec::with_capacity(f.len() + 1),
                face_vertices: Vec::with_capacity(f.iter().map(|r| r.face.len()).sum()),
                point_offsets: Vec::with_capacity(f.len() + 1),
                points: Vec::with_capacity(f.iter().map(|r| r.points.len()).sum()),
                weight_offsets: Vec::with_capacity(f.len() + 1),
                weights: Vec::with_capacity(f.iter().map(|r| r.weights.len()).sum()),
                map_vertices: Vec::with_capacity(m.len()),
                coefficient_offsets: Vec::with_capacity(m.len() + 1),
                coefficients: Vec::with_capacity(m.iter().map(|v| v.coefficients.len()).sum()),
            };
            // u32 offsets: a readable file holds at most 8 GiB of payload (io::Limits), i.e. fewer
            // than 2^30 numbers; saturating is unreachable short of a 32 GiB table in memory.
            let offset = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
            t.face_offsets.push(0);
            t.point_offsets.push(0);
            t.weight_offsets.push(0);
            for r in f {
                t.face_vertices.extend_from_slice(r.face);
                t.points.extend_from_slice(r.points);
                t.weights.extend_from_slice(r.weights);
                t.face_offsets.push(offset(t.face_vertices.len()));
                t.point_offsets.push(offset(t.points.len()));
                t.weight_offsets.push(offset(t.weights.len()));
            }
            t.coefficient_offsets.push(0);
            for v in m {
                t.map_vertices.push(v.vertex);
                t.coefficients.extend_from_slice(&v.coefficients);
                t.coefficient_offsets.push(offset(t.coefficients.len()));
            }
            t
        })
    }
}

fn table_u32<'py>(
    slf: &Bound<'py, Stage>,
    pick: fn(&Tables) -> &Vec<u32>,
) -> PyResult<Bound<'py, PyArray1<u32>>> {
    let data = pick(slf.get().flat());
    view_of(slf.as_any(), ArrayView1::from(data.as_slice()))
}

fn table_f64<'py>(
    slf: &Bound<'py, Stage>,
    pick: fn(&Tables) -> &Vec<f64>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let data = pick(slf.get().flat());
    view_of(slf.as_any(), ArrayView1::from(data.as_slice()))
}

#[pymethods]
impl Stage {
    /// A stage from per-face records.
    ///
    /// ``faces``: iterable of ``(face_ids, points)`` or ``(face_ids, points, weights)``, points
    /// given flat or as rows of ``k + 1`` barycentric coordinates; ``vertex_maps``: iterable of
    /// ``(vertex, coefficients)`` for monotonic stages.
    #[new]
    #[pyo3(signature = (kind, degree, direction = "implicit", *, faces = None, vertex_maps = None, name = None, extras = None))]
    fn py_new(
        kind: &str,
        degree: u32,
        direction: &str,
        faces: Option<&Bound<'_, PyAny>>,
        vertex_maps: Option<&Bound<'_, PyAny>>,
        name: Option<String>,
        extras: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Stage> {
        let mut stage = ism_format::Stage::identity(kind_from_str(kind)?, degree);
        stage.direction = direction_from_str(direction)?;
        stage.name = name;
        stage.extras = json_value(extras, "extras")?;
        if let Some(faces) = faces {
            for (i, item) in faces.try_iter()?.enumerate() {
                let item = item?;
                let parts: Vec<Bound<'_, PyAny>> = item.try_iter()?.collect::<PyResult<_>>()?;
                if parts.len() != 2 && parts.len() != 3 {
                    return Err(PyValueError::new_err(format!(
                        "faces[{i}]: expected (face_ids, points) or (face_ids, points, weights)"
                    )));
                }
                stage.faces.push_record(&FaceRecord {
                    face: u32_vec(&parts[0], &format!("faces[{i}] ids"))?,
                    points: f64_flat(&parts[1], &format!("faces[{i}] points"))?,
                    weights: match parts.get(2) {
                        Some(w) if !w.is_none() => f64_flat(w, &format!("faces[{i}] weights"))?,
                        _ => Vec::new(),
                    },
                });
            }
        }
        if let Some(maps) = vertex_maps {
            for (i, item) in maps.try_iter()?.enumerate() {
                let (vertex, coefficients): (u32, Bound<'_, PyAny>) = item?.extract()?;
                stage.vertex_maps.push(VertexMap {
                    vertex,
                    coefficients: f64_flat(&coefficients, &format!("vertex_maps[{i}]"))?,
                });
            }
        }
        Ok(Stage::new(stage))
    }

    /// A stage from the flat tables (as the properties of the same names give them):
    /// ``Stage.from_tables(**stage.tables())`` rebuilds ``stage``.
    #[staticmethod]
    #[pyo3(signature = (kind, degree, direction = "implicit", *, face_offsets = None, face_vertices = None, point_offsets = None, points = None, weight_offsets = None, weights = None, map_vertices = None, coefficient_offsets = None, coefficients = None, name = None, extras = None))]
    #[allow(clippy::too_many_arguments)]
    fn from_tables(
        kind: &str,
        degree: u32,
        direction: &str,
        face_offsets: Option<&Bound<'_, PyAny>>,
        face_vertices: Option<&Bound<'_, PyAny>>,
        point_offsets: Option<&Bound<'_, PyAny>>,
        points: Option<&Bound<'_, PyAny>>,
        weight_offsets: Option<&Bound<'_, PyAny>>,
        weights: Option<&Bound<'_, PyAny>>,
        map_vertices: Option<&Bound<'_, PyAny>>,
        coefficient_offsets: Option<&Bound<'_, PyAny>>,
        coefficients: Option<&Bound<'_, PyAny>>,
        name: Option<String>,
        extras: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Stage> {
        let mut stage = ism_format::Stage::identity(kind_from_str(kind)?, degree);
        stage.direction = direction_from_str(direction)?;
        stage.name = name;
        stage.extras = json_value(extras, "extras")?;
        let u32s = |o: Option<&Bound<'_, PyAny>>, n: &str| -> PyResult<Vec<u32>> {
            o.map(|o| u32_vec(o, n))
                .transpose()
                .map(Option::unwrap_or_default)
        };
        let f64s = |o: Option<&Bound<'_, PyAny>>, n: &str| -> PyResult<Vec<f64>> {
            o.map(|o| f64_vec(o, n))
                .transpose()
                .map(Option::unwrap_or_default)
        };
        let face_offsets = u32s(face_offsets, "face_offsets")?;
        if face_offsets.len() > 1 {
            let faces = split(
                &u32s(face_vertices, "face_vertices")?,
                &face_offsets,
                "face_offsets",
            )?;
            let n = faces.len();
            let pts = split(
                &f64s(points, "points")?,
                &u32s(point_offsets, "point_offsets")?,
                "point_offsets",
            )?;
            let wo = u32s(weight_offsets, "weight_offsets")?;
            let ws = if wo.is_empty() {
                vec![Vec::new(); n]
            } else {
                split(&f64s(weights, "weights")?, &wo, "weight_offsets")?
            };
            if pts.len() != n || ws.len() != n {
                return Err(PyValueError::new_err(
                    "face_offsets, point_offsets and weight_offsets must have the same length",
                ));
            }
            for ((face, points), weights) in faces.into_iter().zip(pts).zip(ws) {
                stage.faces.push_record(&FaceRecord {
                    face,
                    points,
                    weights,
                });
            }
        }
        let co = u32s(coefficient_offsets, "coefficient_offsets")?;
        if co.len() > 1 {
            let vs = u32s(map_vertices, "map_vertices")?;
            let cs = split(
                &f64s(coefficients, "coefficients")?,
                &co,
                "coefficient_offsets",
            )?;
            if vs.len() != cs.len() {
                return Err(PyValueError::new_err(
                    "map_vertices needs one entry per coefficient_offsets interval",
                ));
            }
            for (vertex, coefficients) in vs.into_iter().zip(cs) {
                stage.vertex_maps.push(VertexMap {
                    vertex,
                    coefficients,
                });
            }
        }
        Ok(Stage::new(stage))
    }

    /// ``"bezier"``, ``"rational"`` or ``"monotonic"``.
    #[getter]
    fn kind(&self) -> &'static str {
        self.inner.kind.as_str()
    }

    /// Polynomial degree ``d``.
    #[getter]
    fn degree(&self) -> u32 {
        self.inner.degree
    }

    /// ``"implicit"`` (the stored map is the stage) or ``"parametric"`` (its inverse).
    #[getter]
    fn direction(&self) -> &'static str {
        match self.inner.direction {
            Direction::Implicit => "implicit",
            Direction::Parametric => "parametric",
        }
    }

    /// The optional label.
    #[getter]
    fn name(&self) -> Option<String> {
        self.inner.name.clone()
    }

    /// Application data (any JSON value as a Python object; ``None`` for none).
    #[getter]
    fn extras<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        crate::value_to_py(py, &self.inner.extras.0)
    }

    /// Number of face records.
    #[getter]
    fn num_faces(&self) -> usize {
        self.inner.faces.len()
    }

    /// ``len(face_offsets) == num_faces + 1`` offsets into ``face_vertices`` (uint32).
    #[getter]
    fn face_offsets<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<u32>>> {
        table_u32(slf, |t| &t.face_offsets)
    }

    /// Every face's sorted global vertex ids, concatenated (uint32).
    #[getter]
    fn face_vertices<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<u32>>> {
        table_u32(slf, |t| &t.face_vertices)
    }

    /// Offsets into ``points`` per face (uint32).
    #[getter]
    fn point_offsets<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<u32>>> {
        table_u32(slf, |t| &t.point_offsets)
    }

    /// Control points, concatenated (float64).
    #[getter]
    fn points<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        table_f64(slf, |t| &t.points)
    }

    /// Offsets into ``weights`` per face (uint32).
    #[getter]
    fn weight_offsets<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<u32>>> {
        table_u32(slf, |t| &t.weight_offsets)
    }

    /// Rational weights, concatenated (float64).
    #[getter]
    fn weights<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        table_f64(slf, |t| &t.weights)
    }

    /// Monotonic stages: the vertex of each map (uint32).
    #[getter]
    fn map_vertices<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<u32>>> {
        table_u32(slf, |t| &t.map_vertices)
    }

    /// Offsets into ``coefficients`` per map (uint32).
    #[getter]
    fn coefficient_offsets<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<u32>>> {
        table_u32(slf, |t| &t.coefficient_offsets)
    }

    /// Bernstein coefficients of the monotonic maps, concatenated (float64).
    #[getter]
    fn coefficients<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        table_f64(slf, |t| &t.coefficients)
    }

    /// Keyword arguments of :meth:`from_tables` that rebuild this stage.
    fn tables<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyDict>> {
        let py = slf.py();
        let d = PyDict::new(py);
        let me = slf.get();
        d.set_item("kind", me.kind())?;
        d.set_item("degree", me.degree())?;
        d.set_item("direction", me.direction())?;
        for name in [
            "face_offsets",
            "face_vertices",
            "point_offsets",
            "points",
            "weight_offsets",
            "weights",
            "map_vertices",
            "coefficient_offsets",
            "coefficients",
        ] {
            d.set_item(name, slf.getattr(name)?)?;
        }
        d.set_item("name", me.name())?;
        d.set_item("extras", me.extras(py)?)?;
        Ok(d)
    }

    /// Face records as ``(face_ids, points, weights)`` tuples, points as rows of ``k + 1``
    /// barycentric coordinates (copies).
    #[getter]
    fn faces<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let list = PyList::empty(py);
        for r in &self.inner.faces {
            let k1 = r.face.len().max(1);
            let pts = PyArray1::from_slice(py, r.points);
            let pts = if r.points.len() % k1 == 0 {
                pts.reshape([r.points.len() / k1, k1])?.into_any()
            } else {
                pts.into_any()
            };
            list.append((
                PyArray1::from_slice(py, r.face),
                pts,
                PyArray1::from_slice(py, r.weights),
            ))?;
        }
        Ok(list)
    }

    /// Monotonic maps as ``(vertex, coefficients)`` tuples (copies).
    #[getter]
    fn vertex_maps<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let list = PyList::empty(py);
        for m in &self.inner.vertex_maps {
            list.append((m.vertex, PyArray1::from_slice(py, &m.coefficients)))?;
        }
        Ok(list)
    }

    fn __eq__(&self, other: &Bound<'_, PyAny>) -> bool {
        other
            .downcast::<Stage>()
            .map(|o| o.get().inner == self.inner)
            .unwrap_or(false)
    }

    fn __repr__(&self) -> String {
        format!(
            "<ism.Stage {} degree {} {}: {} faces, {} vertex maps>",
            self.inner.kind.as_str(),
            self.inner.degree,
            self.direction(),
            self.inner.faces.len(),
            self.inner.vertex_maps.len()
        )
    }
}

/// What `__reduce__` returns: the reader and its arguments.
type Reduced<'py> = (Bound<'py, PyAny>, (Bound<'py, PyBytes>, bool));

/// The reader's resource limits from the `limits` keyword: `None` or a dict whose keys are
/// among [`LIMIT_NAMES`] (the names of `io::Limits`' fields and of the CLI's `--max-*` flags),
/// each a whole number; what is not given keeps its default.
pub(crate) fn limits_from(obj: Option<&Bound<'_, PyAny>>) -> PyResult<io::Limits> {
    let mut limits = io::Limits::default();
    let Some(obj) = obj.filter(|o| !o.is_none()) else {
        return Ok(limits);
    };
    let dict = obj.downcast::<PyDict>().map_err(|_| {
        PyTypeError::new_err(format!(
            "limits: expected a dict with keys among {}",
            LIMIT_NAMES.join(", ")
        ))
    })?;
    for (k, v) in dict.iter() {
        let key: String = k.extract()?;
        let value: u64 = v.extract().map_err(|_| {
            PyValueError::new_err(format!(
                "limits[{key:?}]: expected a whole number from 0 to {}",
                u64::MAX
            ))
        })?;
        let field = match key.as_str() {
            "max_payload_bytes" => &mut limits.max_payload_bytes,
            "max_vertices" => &mut limits.max_vertices,
            "max_simplices" => &mut limits.max_simplices,
            "max_stages" => &mut limits.max_stages,
            "max_records" => &mut limits.max_records,
            _ => {
                return Err(PyValueError::new_err(format!(
                    "limits: unknown key {key:?} (expected one of {})",
                    LIMIT_NAMES.join(", ")
                )))
            }
        };
        *field = value;
    }
    Ok(limits)
}

/// The keys `limits` accepts, in the order of `io::Limits`' fields.
const LIMIT_NAMES: [&str; 5] = [
    "max_payload_bytes",
    "max_vertices",
    "max_simplices",
    "max_stages",
    "max_records",
];

/// Reads a model from a file (any encoding, detected from content), within `limits`.
#[pyfunction]
#[pyo3(signature = (path, check = true, limits = None))]
pub fn read_path(
    py: Python<'_>,
    path: std::path::PathBuf,
    check: bool,
    limits: Option<&Bound<'_, PyAny>>,
) -> PyResult<Model> {
    let options = io::ReadOptions {
        check_structure: check,
        limits: limits_from(limits)?,
        ..io::ReadOptions::default()
    };
    if check {
        // The checked read keeps the topology its structural check builds.
        return match py.allow_threads(|| io::read_path_indexed_with(&path, &options)) {
            Ok(doc) => Ok(Model::from_shared(
                Shared::Indexed(doc.model),
                Some(doc.encoding),
            )),
            Err(e) => Err(format_error(py, &e)),
        };
    }
    match py.allow_threads(|| io::read_path_with(&path, &options)) {
        Ok(doc) => Ok(Model::new(doc.model, Some(doc.encoding))),
        Err(e) => Err(format_error(py, &e)),
    }
}

/// Reads a model from bytes (any encoding, detected from content), within `limits`.
#[pyfunction]
#[pyo3(signature = (data, check = true, limits = None))]
pub fn read_bytes(
    py: Python<'_>,
    data: &[u8],
    check: bool,
    limits: Option<&Bound<'_, PyAny>>,
) -> PyResult<Model> {
    let options = io::ReadOptions {
        check_structure: check,
        limits: limits_from(limits)?,
        ..io::ReadOptions::default()
    };
    if check {
        return match py.allow_threads(|| io::from_slice_indexed(data, &options)) {
            Ok(doc) => Ok(Model::from_shared(
                Shared::Indexed(doc.model),
                Some(doc.encoding),
            )),
            Err(e) => Err(format_error(py, &e)),
        };
    }
    match py.allow_threads(|| io::from_slice_with(data, &options)) {
        Ok(doc) => Ok(Model::new(doc.model, Some(doc.encoding))),
        Err(e) => Err(format_error(py, &e)),
    }
}

fn metadata_from(obj: Option<&Bound<'_, PyAny>>) -> PyResult<ism_format::Metadata> {
    let mut m = ism_format::Metadata::default();
    let Some(obj) = obj.filter(|o| !o.is_none()) else {
        return Ok(m);
    };
    let dict = obj
        .downcast::<PyDict>()
        .map_err(|_| PyTypeError::new_err("metadata: expected a dict"))?;
    for (k, v) in dict.iter() {
        let key: String = k.extract()?;
        let value: Option<String> = v.extract()?;
        match key.as_str() {
            "name" => m.name = value,
            "generator" => m.generator = value,
            "units" => m.units = value,
            "description" => m.description = value,
            _ => {
                return Err(PyValueError::new_err(format!(
                    "metadata: unknown member {key:?} (name, generator, units, description; put anything else in extras)"
                )))
            }
        }
    }
    Ok(m)
}

#[pymethods]
impl Model {
    /// A model from numpy arrays: ``vertices`` (Nv, n) with n = 2 or 3, ``simplices`` (Ns, n + 1)
    /// vertex ids (positively oriented), ``values`` (Nv,) nonzero, ``level``, ``stages`` (a
    /// sequence of :class:`Stage`), ``metadata`` (dict of name, generator, units, description),
    /// ``extras`` and ``extensions`` (JSON-like Python objects). With ``check`` (default) the
    /// structural rules of the specification are enforced (``ism.StructureError``).
    #[new]
    #[pyo3(signature = (vertices, simplices, values, level = 0.0, stages = None, *, metadata = None, extras = None, extensions_used = None, extensions_required = None, extensions = None, check = true))]
    #[allow(clippy::too_many_arguments)]
    fn py_new(
        py: Python<'_>,
        vertices: &Bound<'_, PyAny>,
        simplices: &Bound<'_, PyAny>,
        values: &Bound<'_, PyAny>,
        level: f64,
        stages: Option<&Bound<'_, PyAny>>,
        metadata: Option<&Bound<'_, PyAny>>,
        extras: Option<&Bound<'_, PyAny>>,
        extensions_used: Option<Vec<String>>,
        extensions_required: Option<Vec<String>>,
        extensions: Option<&Bound<'_, PyDict>>,
        check: bool,
    ) -> PyResult<Model> {
        let v = float_array(vertices, "vertices", 2)?;
        let v: PyReadonlyArray2<f64> = v.extract()?;
        let n = v.shape()[1];
        if n != 2 && n != 3 {
            return Err(PyValueError::new_err(format!(
                "vertices: expected shape (Nv, 2) or (Nv, 3), got {:?}",
                v.shape()
            )));
        }
        let s = index_array(simplices, "simplices", 2)?;
        let s: PyReadonlyArray2<u32> = s.extract()?;
        if s.shape()[1] != n + 1 && s.shape()[0] != 0 {
            return Err(PyValueError::new_err(format!(
                "simplices: expected shape (Ns, {}), got {:?}",
                n + 1,
                s.shape()
            )));
        }
        let mut model = ism_format::Model::new(n as u8);
        model.vertices = v.as_slice()?.to_vec();
        model.simplices = s.as_slice()?.to_vec();
        model.values = f64_vec(values, "values")?;
        model.level = level;
        model.metadata = metadata_from(metadata)?;
        model.extras = json_value(extras, "extras")?;
        model.extensions_used = extensions_used.unwrap_or_default();
        model.extensions_required = extensions_required.unwrap_or_default();
        if let Some(ext) = extensions {
            let mut map = BTreeMap::new();
            for (k, v) in ext.iter() {
                let key: String = k.extract()?;
                let value = JsonValue(crate::py_to_value(&v, &format!("extensions[{key:?}]"))?);
                map.insert(key, value);
            }
            model.extensions = map;
        }
        if let Some(stages) = stages {
            for item in stages.try_iter()? {
                let item = item?;
                let stage = item
                    .downcast::<Stage>()
                    .map_err(|_| PyTypeError::new_err("stages: expected ism.Stage objects"))?;
                model.stages.push(stage.get().inner.clone());
            }
        }
        if check {
            let errors: Vec<_> = py
                .allow_threads(|| {
                    ism_format::structure::check(
                        &model,
                        ism_format::structure::DEFAULT_MAX_DIAGNOSTICS,
                    )
                })
                .into_iter()
                .filter(|d| d.severity == ism_format::Severity::Error)
                .collect();
            if !errors.is_empty() {
                let err = ism_format::Error::Structure(errors);
                return Err(format_error(py, &err));
            }
        }
        Ok(Model::new(model, None))
    }

    /// Format version of the model (``"1.0"``).
    #[getter]
    fn version(&self) -> String {
        self.inner.version.clone()
    }

    /// Space dimension n (2 or 3).
    #[getter]
    fn dimension(&self) -> u8 {
        self.inner.dimension
    }

    /// Number of vertices.
    #[getter]
    fn num_vertices(&self) -> usize {
        self.inner.num_vertices()
    }

    /// Number of top simplices.
    #[getter]
    fn num_simplices(&self) -> usize {
        self.inner.num_simplices()
    }

    /// The encoding the model was read from (``"json"``, ``"msgpack"``, ``"binary"``,
    /// ``"compact"``, ``"compressed"``, ``"structured"``), or ``None``
    /// for a model built in memory.
    #[getter]
    fn encoding(&self) -> Option<&'static str> {
        self.encoding.map(|e| e.name())
    }

    /// Vertex coordinates, (Nv, n) float64, a read-only view of the model's own buffer.
    #[getter]
    fn vertices<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let m = &slf.get().inner;
        let view = ArrayView2::from_shape(
            (m.num_vertices(), m.dim()),
            &m.vertices[..m.num_vertices() * m.dim()],
        )
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
        view_of(slf.as_any(), view)
    }

    /// Top simplices, (Ns, n + 1) uint32 vertex ids, a read-only view.
    #[getter]
    fn simplices<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray2<u32>>> {
        let m = &slf.get().inner;
        let k = m.dim() + 1;
        let ns = m.simplices.len() / k;
        let view = ArrayView2::from_shape((ns, k), &m.simplices[..ns * k])
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        view_of(slf.as_any(), view)
    }

    /// The vertex function, (Nv,) float64, a read-only view.
    #[getter]
    fn values<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        view_of(
            slf.as_any(),
            ArrayView1::from(slf.get().inner.values.as_slice()),
        )
    }

    /// The dimension-``k`` faces of the complex (1 <= k < n), (N_k, k + 1) uint32 sorted vertex
    /// ids in increasing lexicographic order: the face numbering of :meth:`stage_tables`. A
    /// read-only view of the checked index (zero-copy; built on first use for models not read with
    /// ``check=True``). ``k = 0`` gives the vertex ids, ``k = n`` the simplices.
    fn faces<'py>(slf: &Bound<'py, Self>, k: usize) -> PyResult<Bound<'py, PyAny>> {
        let py = slf.py();
        let me = slf.get();
        let n = me.inner.dim();
        if k == 0 {
            let ids: Vec<u32> = (0..me.inner.num_vertices() as u32).collect();
            return Ok(PyArray1::from_vec(py, ids)
                .reshape([me.inner.num_vertices(), 1])?
                .into_any());
        }
        if k == n {
            return Ok(Model::simplices(slf)?.into_any());
        }
        if k > n {
            return Err(PyValueError::new_err(format!(
                "k: expected 0..={n}, got {k}"
            )));
        }
        let table = me.indexed(py)?.topology().face_vertices(k);
        let view = ArrayView2::from_shape((table.len() / (k + 1), k + 1), table)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok(view_of(slf.as_any(), view)?.into_any())
    }

    /// Facet neighbours, (Ns, n + 1) uint32: entry ``[s, i]`` is the simplex across the facet of
    /// ``s`` opposite its local vertex ``i``, ``2**32 - 1`` on the boundary (a read-only view of
    /// the index).
    #[getter]
    fn neighbours<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyArray2<u32>>> {
        let me = slf.get();
        let table = me.indexed(slf.py())?.topology().neighbours();
        let m = me.inner.dim() + 1;
        let view = ArrayView2::from_shape((table.len() / m, m), table)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        view_of(slf.as_any(), view)
    }

    /// The dense tables of stage ``i`` from the checked index (zero-copy read-only views), keyed by
    /// face dimension ``k`` (0..=n) over the faces of :meth:`faces` ``(k)``:
    /// ``points[k]`` (N_k, (k + 1)·C(d − 1, k)) owned control points (the identity's where the
    /// file has no record), ``weights[k]`` (N_k, C(d − 1, k)) for rational stages,
    /// ``records[k]`` (N_k,) the record index in :attr:`Stage.faces` or ``2**32 - 1``; monotonic
    /// stages: ``coefficients`` (Nv, d + 1) and ``vertex_records`` (Nv,).
    fn stage_tables<'py>(slf: &Bound<'py, Self>, i: usize) -> PyResult<Bound<'py, PyDict>> {
        let py = slf.py();
        let me = slf.get();
        let index = me.indexed(py)?;
        if i >= index.stages.len() {
            return Err(PyValueError::new_err(format!(
                "stage {i}: the model has {} stage(s)",
                index.stages.len()
            )));
        }
        let table = index.stage(i);
        let owner = slf.as_any();
        let n = me.inner.dim();
        let rows2 = |data: &[f64], rows: usize| -> PyResult<Bound<'py, PyAny>> {
            let cols = data.len().checked_div(rows).unwrap_or(0);
            let view = ArrayView2::from_shape((rows, cols), data)
                .map_err(|e| PyValueError::new_err(e.to_string()))?;
            Ok(view_of(owner, view)?.into_any())
        };
        let out = PyDict::new(py);
        out.set_item("kind", table.kind().as_str())?;
        out.set_item("degree", table.degree())?;
        if table.kind() == StageKind::Monotonic {
            out.set_item(
                "coefficients",
                rows2(table.coefficients(), me.inner.num_vertices())?,
            )?;
            out.set_item(
                "vertex_records",
                view_of(owner, ArrayView1::from(table.vertex_records()))?,
            )?;
            return Ok(out);
        }
        let (points, weights, records) = (PyList::empty(py), PyList::empty(py), PyList::empty(py));
        for k in 0..=n {
            let rows = index.topology().face_slots(k);
            points.append(rows2(table.points(k), rows)?)?;
            weights.append(rows2(
                table.weights(k),
                if table.weights(k).is_empty() { 0 } else { rows },
            )?)?;
            records.append(view_of(owner, ArrayView1::from(table.records(k)))?)?;
        }
        out.set_item("points", points)?;
        out.set_item("weights", weights)?;
        out.set_item("records", records)?;
        Ok(out)
    }

    /// The level c of the shape F = c.
    #[getter]
    fn level(&self) -> f64 {
        self.inner.level
    }

    /// The stages, applied in order (a tuple of :class:`Stage`).
    #[getter]
    fn stages<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        if let Some(t) = self.stages.get() {
            return Ok(t.bind(py).clone());
        }
        let items = self
            .inner
            .stages
            .iter()
            .map(|s| Py::new(py, Stage::new(s.clone())))
            .collect::<PyResult<Vec<_>>>()?;
        let tuple = PyTuple::new(py, items)?;
        let _ = self.stages.set(tuple.clone().unbind());
        Ok(self
            .stages
            .get()
            .map(|t| t.bind(py).clone())
            .unwrap_or(tuple))
    }

    /// Descriptive metadata as a dict (members that are set: name, generator, units, description).
    #[getter]
    fn metadata<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        let m = &self.inner.metadata;
        for (k, v) in [
            ("name", &m.name),
            ("generator", &m.generator),
            ("units", &m.units),
            ("description", &m.description),
        ] {
            if let Some(v) = v {
                d.set_item(k, v)?;
            }
        }
        Ok(d)
    }

    /// Application data (any JSON value as a Python object; ``None`` for none).
    #[getter]
    fn extras<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        crate::value_to_py(py, &self.inner.extras.0)
    }

    /// Names of the extensions the model uses.
    #[getter]
    fn extensions_used(&self) -> Vec<String> {
        self.inner.extensions_used.clone()
    }

    /// Names of the extensions a reader must understand.
    #[getter]
    fn extensions_required(&self) -> Vec<String> {
        self.inner.extensions_required.clone()
    }

    /// Extension payloads by name (Python objects).
    #[getter]
    fn extensions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (k, v) in &self.inner.extensions {
            d.set_item(k, crate::value_to_py(py, &v.0)?)?;
        }
        Ok(d)
    }

    /// The file's bytes in ``encoding`` (``"json"``, ``"msgpack"``, ``"binary"``, ``"compact"``:
    /// the binary encoding with variable-length integers, ``"compressed"``: the compact payload
    /// compressed by xz, the smallest, or ``"structured"``: the compact encoding with face records
    /// given by the complex and control points on a lattice, the smallest uncompressed; a model
    /// :func:`fit` returned writes its complex there as the Kuhn grid and edge splits it came from,
    /// as ``ism fit -o X.isms`` does); ``pretty`` indents JSON; ``container`` wraps JSON in the
    /// checksummed container.
    #[pyo3(signature = (encoding = "binary", *, pretty = false, container = false))]
    fn to_bytes<'py>(
        &self,
        py: Python<'py>,
        encoding: &str,
        pretty: bool,
        container: bool,
    ) -> PyResult<Bound<'py, PyBytes>> {
        let encoding = encoding_from_str(encoding)?;
        let options = io::WriteOptions {
            pretty,
            json_in_container: container,
        };
        let model = &self.inner;
        let refinement = self.refinement.as_deref();
        match py.allow_threads(|| match (encoding, refinement) {
            (Encoding::Structured, Some(r)) => io::to_vec_refined(model, r).map(|(b, _)| b),
            _ => io::to_vec(model, encoding, options),
        }) {
            Ok(bytes) => Ok(PyBytes::new(py, &bytes)),
            Err(e) => Err(format_error(py, &e)),
        }
    }

    /// Writes the model to ``path`` atomically (a failure leaves no partial file). The encoding
    /// defaults to the extension's (``.ism.json``/``.json``, ``.ism.msgpack``/``.msgpack``,
    /// ``.ismb``, ``.ismc``, ``.ismz``; binary otherwise).
    #[pyo3(signature = (path, encoding = None, *, pretty = false, container = false))]
    fn write_path(
        &self,
        py: Python<'_>,
        path: std::path::PathBuf,
        encoding: Option<&str>,
        pretty: bool,
        container: bool,
    ) -> PyResult<()> {
        let encoding = encoding.map(encoding_from_str).transpose()?;
        let options = io::WriteOptions {
            pretty,
            json_in_container: container,
        };
        let model = &self.inner;
        let structured =
            encoding.or_else(|| Encoding::from_path(&path)) == Some(Encoding::Structured);
        let refinement = self.refinement.as_deref().filter(|_| structured);
        py.allow_threads(|| match refinement {
            Some(r) => io::write_path_refined(model, &path, r).map(|_| ()),
            None => io::write_path(model, &path, encoding, options),
        })
        .map_err(|e| format_error(py, &e))
    }

    /// Writes the model to a path (see :meth:`write_path`) or a binary file object (``encoding``
    /// defaults to binary there).
    #[pyo3(signature = (dest, encoding = None, *, pretty = false, container = false))]
    fn write(
        &self,
        dest: &Bound<'_, PyAny>,
        encoding: Option<&str>,
        pretty: bool,
        container: bool,
    ) -> PyResult<()> {
        let py = dest.py();
        if dest.hasattr("write")? {
            let bytes = self.to_bytes(py, encoding.unwrap_or("binary"), pretty, container)?;
            dest.call_method1("write", (bytes,))?;
            return Ok(());
        }
        let path: std::path::PathBuf = dest.extract()?;
        self.write_path(py, path, encoding, pretty, container)
    }

    fn __eq__(&self, other: &Bound<'_, PyAny>) -> bool {
        other
            .downcast::<Model>()
            .map(|o| *o.get().inner == *self.inner)
            .unwrap_or(false)
    }

    fn __repr__(&self) -> String {
        let m = &self.inner;
        format!(
            "<ism.Model {}D{}: {} vertices, {} simplices, {} stage(s), level {}>",
            m.dimension,
            m.metadata
                .name
                .as_deref()
                .map(|n| format!(" {n:?}"))
                .unwrap_or_default(),
            m.num_vertices(),
            m.num_simplices(),
            m.stages.len(),
            m.level
        )
    }

    /// Pickling goes through the binary encoding (bit-exact).
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<Reduced<'py>> {
        let py = slf.py();
        let f = py.import("ism._ism")?.getattr("read_bytes")?;
        let bytes = slf.get().to_bytes(py, "binary", false, false)?;
        Ok((f, (bytes, false)))
    }
}
