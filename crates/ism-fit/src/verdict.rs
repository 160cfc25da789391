//! The verdict on a finished fit, one policy for every front end (`ism fit` and the Python
//! package's `ism.fit` / `ism.fit_mesh` word it; they do not decide it): the written model's
//! structure, its round trip through the encoder, exporter and sampler ([`crate::roundtrip`]), the
//! topology against what the target is known to have, and the order in which failures decide the
//! outcome.

use ism_format::{Diagnostic, Model, Severity};

use crate::fit::Fitted;
use crate::mesh::plan::MeshPlan;
use crate::presets::Preset;
use crate::roundtrip::{RoundTrip, RoundTripError};

/// Structural errors kept in a verdict: enough to show what is wrong, bounded so a broken fit of a
/// large model does not print a diagnostic per simplex.
pub const STRUCTURAL_ERRORS_KEPT: usize = 20;

/// A topology the fit must reproduce, and what it is known from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ExpectedTopology {
    /// What gives it, for messages: "the true shape" (a preset) or "the mesh".
    pub reference: &'static str,
    /// Connected components.
    pub components: usize,
    /// Euler characteristic.
    pub euler: i64,
}

impl ExpectedTopology {
    /// A preset's true zero set in its domain.
    pub fn of_preset(p: &Preset) -> ExpectedTopology {
        ExpectedTopology {
            reference: "the true shape",
            components: p.components,
            euler: p.euler,
        }
    }

    /// A closed mesh's ([`MeshPlan::expected_topology`]).
    pub fn of_mesh(plan: &MeshPlan) -> ExpectedTopology {
        let (components, euler) = plan.expected_topology();
        ExpectedTopology {
            reference: "the mesh",
            components,
            euler,
        }
    }
}

/// How a fit ended, in the order the checks decide it: the first failure is the outcome.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// Every check passed.
    Passed,
    /// The written model breaks a structural rule of the format (a fitter bug).
    StructuralErrors,
    /// The two-sided measure does not meet the tolerance.
    ToleranceNotMet,
    /// Cells still fail the Plantinga–Vegter test at the simplex limit: the topology is not
    /// certified.
    TopologyUncertified,
    /// The fit's topology differs from the target's known one.
    TopologyDiffers,
}

impl Outcome {
    /// The `outcome` member of the JSON report.
    pub fn as_str(self) -> &'static str {
        match self {
            Outcome::Passed => "passed",
            Outcome::StructuralErrors => "structural errors",
            Outcome::ToleranceNotMet => "tolerance not met",
            Outcome::TopologyUncertified => "topology not certified",
            Outcome::TopologyDiffers => "topology differs",
        }
    }
}

/// What is checked of a fit after it is made ([`Verdict::judge`]).
#[derive(Debug)]
pub struct Verdict {
    /// The topology the target is known to have (`None` for an expression: then only the
    /// Plantinga–Vegter certificate speaks for the topology).
    pub expected: Option<ExpectedTopology>,
    /// The fit's components and Euler characteristic equal `expected`'s; `None` when there is
    /// nothing to compare with.
    pub topology_matches: Option<bool>,
    /// The model's structural errors (at most [`STRUCTURAL_ERRORS_KEPT`]).
    pub structural: Vec<Diagnostic>,
    /// The encoding/export/sampling round trip. A failure is reported, not an outcome: the
    /// failures seen are in the exporter's and sampler's inversion (issue 19), which the fitter
    /// must not paper over.
    pub round_trip: Result<RoundTrip, RoundTripError>,
    /// The first failure, or [`Outcome::Passed`].
    pub outcome: Outcome,
}

impl Verdict {
    /// Judges `fitted`, whose written form is `model`, fitted at `tolerance`, against
    /// `expected`. `phase` is told each step's name as it starts (front ends show it as progress).
    pub fn judge(
        fitted: &Fitted,
        model: &Model,
        tolerance: f64,
        expected: Option<ExpectedTopology>,
        mut phase: impl FnMut(&'static str),
    ) -> Verdict {
        let r = &fitted.report;
        phase("checking the model's structure");
        let structural: Vec<Diagnostic> =
            ism_format::structure::check(model, STRUCTURAL_ERRORS_KEPT)
                .into_iter()
                .filter(|d| d.severity == Severity::Error)
                .collect();
        phase("round trip: encoding, export and sampling of the fitted model");
        let round_trip = crate::roundtrip::round_trip(model, r.topology, tolerance);
        let topology_matches =
            expected.map(|e| e.components == r.topology.components && e.euler == r.topology.euler);
        let outcome = if !structural.is_empty() {
            Outcome::StructuralErrors
        } else if !r.tolerance_met {
            Outcome::ToleranceNotMet
        } else if r.pv_unfinished > 0 {
            Outcome::TopologyUncertified
        } else if topology_matches == Some(false) {
            Outcome::TopologyDiffers
        } else {
            Outcome::Passed
        };
        Verdict {
            expected,
            topology_matches,
            structural,
            round_trip,
            outcome,
        }
    }

    /// Adds the verdict's members to a report's JSON ([`crate::FitReport::to_json`]):
    /// `topologyChecked`, `topologyMatches` (`null` when there is nothing to compare with: an
    /// unchecked topology is never reported as matching), `topologyMatchesPreset` (the same value,
    /// its older name), `topologyReference`, `structuralErrors`, `roundTrip` and `outcome`.
    pub fn add_to_json(&self, report: &mut serde_json::Map<String, serde_json::Value>) {
        let mut add = |k: &str, v: serde_json::Value| report.insert(k.to_string(), v);
        add("topologyChecked", self.topology_matches.is_some().into());
        add("topologyMatchesPreset", self.topology_matches.into());
        add("topologyMatches", self.topology_matches.into());
        add(
            "topologyReference",
            self.expected.map(|e| e.reference).into(),
        );
        add("structuralErrors", self.structural.len().into());
        add("roundTrip", crate::roundtrip::to_json(&self.round_trip));
        add("outcome", self.outcome.as_str().into());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{fit, FitOptions};

    fn circle_fit(tolerance: f64) -> (Fitted, Model, f64) {
        let p = Preset::find("circle").unwrap();
        let g = p.expression().unwrap();
        let mut o = FitOptions::new(p.domain);
        o.resolution = 4;
        o.tolerance = tolerance;
        let fitted = fit(&g, &o, &ism_format::Progress::none()).unwrap();
        let model = fitted.to_model("circle");
        (fitted, model, tolerance)
    }

    #[test]
    fn a_good_fit_passes_and_a_wrong_reference_is_named() {
        let (fitted, model, t) = circle_fit(1e-3);
        let p = Preset::find("circle").unwrap();
        let mut phases = Vec::new();
        let v = Verdict::judge(
            &fitted,
            &model,
            t,
            Some(ExpectedTopology::of_preset(p)),
            |s| phases.push(s),
        );
        assert_eq!(v.outcome, Outcome::Passed, "{v:?}");
        assert_eq!(v.topology_matches, Some(true));
        assert!(v.round_trip.is_ok());
        assert_eq!(phases.len(), 2);
        // A circle is one component with χ = 0; claim two circles and the verdict must say so.
        let two = ExpectedTopology {
            reference: "a test",
            components: 2,
            euler: 0,
        };
        let v = Verdict::judge(&fitted, &model, t, Some(two), |_| {});
        assert_eq!(v.outcome, Outcome::TopologyDiffers);
        let mut json = serde_json::Map::new();
        v.add_to_json(&mut json);
        assert_eq!(json["topologyMatches"], false);
        assert_eq!(json["topologyMatchesPreset"], false);
        assert_eq!(json["topologyReference"], "a test");
        assert_eq!(json["outcome"], "topology differs");
    }

    #[test]
    fn nothing_to_compare_with_is_not_a_check() {
        let (fitted, model, t) = circle_fit(1e-2);
        let v = Verdict::judge(&fitted, &model, t, None, |_| {});
        assert_eq!(v.topology_matches, None);
        let mut json = serde_json::Map::new();
        v.add_to_json(&mut json);
        assert_eq!(json["topologyChecked"], false);
        assert!(json["topologyMatchesPreset"].is_null());
        assert!(json["topologyReference"].is_null());
        assert!(json["topologyMatches"].is_null());
    }

    #[test]
    fn a_broken_model_is_a_structural_failure_before_anything_else() {
        let (fitted, mut model, t) = circle_fit(1e-2);
        // A simplex naming a vertex that does not exist (ISM-1xx), whatever the tolerance says.
        model.simplices[0] = u32::MAX;
        let v = Verdict::judge(&fitted, &model, t, None, |_| {});
        assert_eq!(v.outcome, Outcome::StructuralErrors);
        assert!(!v.structural.is_empty());
    }
}
