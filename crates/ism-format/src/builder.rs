//! Builders for models and stages, for programs that make ISMs.

use crate::error::{Error, Result};
use crate::model::{Direction, Model, Stage, StageKind, VertexMap};
use crate::rules::Severity;

/// Builds a [`Model`] vertex by vertex; [`ModelBuilder::build`] runs the structural checks.
#[derive(Clone, Debug)]
pub struct ModelBuilder {
    model: Model,
}

impl ModelBuilder {
    /// Starts a model of dimension `n` (2 or 3).
    pub fn new(dimension: u8) -> ModelBuilder {
        ModelBuilder {
            model: Model::new(dimension),
        }
    }

    /// Sets the name in the metadata.
    pub fn name(mut self, name: impl Into<String>) -> Self {
        self.model.metadata.name = Some(name.into());
        self
    }

    /// Sets the generator in the metadata.
    pub fn generator(mut self, generator: impl Into<String>) -> Self {
        self.model.metadata.generator = Some(generator.into());
        self
    }

    /// Sets the description in the metadata.
    pub fn description(mut self, text: impl Into<String>) -> Self {
        self.model.metadata.description = Some(text.into());
        self
    }

    /// Sets the level `c`.
    pub fn level(mut self, level: f64) -> Self {
        self.model.level = level;
        self
    }

    /// Adds a vertex with its value; returns the builder. Ids are assigned in order from 0.
    pub fn vertex(mut self, position: &[f64], value: f64) -> Self {
        self.model.vertices.extend_from_slice(position);
        self.model.values.push(value);
        self
    }

    /// Adds a top simplex (vertex ids, positively oriented).
    pub fn simplex(mut self, ids: &[u32]) -> Self {
        self.model.simplices.extend_from_slice(ids);
        self
    }

    /// Appends a stage (applied after those already added).
    pub fn stage(mut self, stage: Stage) -> Self {
        self.model.stages.push(stage);
        self
    }

    /// Finishes, returning the model if it is structurally valid.
    ///
    /// # Errors
    /// [`Error::Structure`] listing every structural error.
    pub fn build(self) -> Result<Model> {
        let errors: Vec<_> =
            crate::structure::check(&self.model, crate::structure::DEFAULT_MAX_DIAGNOSTICS)
                .into_iter()
                .filter(|d| d.severity == Severity::Error)
                .collect();
        if errors.is_empty() {
            Ok(self.model)
        } else {
            Err(Error::Structure(errors))
        }
    }

    /// Finishes without checking.
    pub fn build_unchecked(self) -> Model {
        self.model
    }
}

/// Builds a [`Stage`].
#[derive(Clone, Debug)]
pub struct StageBuilder {
    stage: Stage,
}

impl StageBuilder {
    /// A Bézier stage of degree `d` (all points fixed until set).
    pub fn bezier(degree: u32) -> StageBuilder {
        StageBuilder {
            stage: Stage::identity(StageKind::Bezier, degree),
        }
    }

    /// A rational stage of degree `d` (points fixed, weights 1 until set).
    pub fn rational(degree: u32) -> StageBuilder {
        StageBuilder {
            stage: Stage::identity(StageKind::Rational, degree),
        }
    }

    /// A monotonic stage of degree `d` (`g_v(t) = t` until set).
    pub fn monotonic(degree: u32) -> StageBuilder {
        StageBuilder {
            stage: Stage::identity(StageKind::Monotonic, degree),
        }
    }

    /// Stores the stage inverted (parametric direction).
    pub fn parametric(mut self) -> Self {
        self.stage.direction = Direction::Parametric;
        self
    }

    /// Sets the label.
    pub fn name(mut self, name: impl Into<String>) -> Self {
        self.stage.name = Some(name.into());
        self
    }

    /// Records a face's owned control points (flat, canonical order). The face ids are sorted here,
    /// with each point's coordinates permuted to match.
    pub fn face(mut self, face: &[u32], points: &[f64], weights: &[f64]) -> Self {
        let m = face.len();
        let mut order: Vec<usize> = (0..m).collect();
        order.sort_by_key(|&i| face[i]);
        let sorted_face: Vec<u32> = order.iter().map(|&i| face[i]).collect();
        let identity = order.iter().enumerate().all(|(a, &b)| a == b);
        let points = if identity || m == 0 {
            points.to_vec()
        } else {
            // Reorder each point's coordinates; the canonical order of owned indices is defined on
            // the sorted face, so a caller with an unsorted face must already list points in the
            // order of the sorted face's multi-indices.
            points
                .chunks(m)
                .flat_map(|p| order.iter().map(move |&i| p[i]))
                .collect()
        };
        self.stage.faces.push(&sorted_face, &points, weights);
        self
    }

    /// Records a monotonic vertex map.
    pub fn vertex_map(mut self, vertex: u32, coefficients: &[f64]) -> Self {
        self.stage.vertex_maps.push(VertexMap {
            vertex,
            coefficients: coefficients.to_vec(),
        });
        self
    }

    /// Finishes.
    pub fn build(self) -> Stage {
        self.stage
    }
}
