//! Named test shapes with their domains and their true topology.

use crate::expr::Expression;
use crate::FitError;

/// A named implicit shape `g = 0`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Preset {
    /// Name used on the command line.
    pub name: &'static str,
    /// What it is and where it comes from.
    pub description: &'static str,
    /// Dimension `n`.
    pub dim: usize,
    /// The expression `g` (syntax of [`Expression`]).
    pub expr: &'static str,
    /// Domain box, `lo, hi` per axis.
    pub domain: &'static [f64],
    /// Number of connected components of the true zero set inside the domain.
    pub components: usize,
    /// Euler characteristic of the true zero set inside the domain.
    pub euler: i64,
}

/// Every preset.
pub const PRESETS: &[Preset] = &[
    Preset {
        name: "circle",
        description: "circle x²+y²−0.28² of Mello & Velho 2010, Fig. 4",
        dim: 2,
        expr: "x^2 + y^2 - 0.28^2",
        domain: &[-0.5, 0.5, -0.5, 0.5],
        components: 1,
        euler: 0,
    },
    Preset {
        name: "taubin",
        description: "Taubin's quartic curve of Mello & Velho 2009, §9.2",
        dim: 2,
        expr: "0.004 + 0.110*x - 0.177*y - 0.174*x^2 + 0.224*x*y - 0.303*y^2 - 0.168*x^3 + 0.327*x^2*y \
               - 0.087*x*y^2 - 0.013*y^3 + 0.235*x^4 - 0.667*x^3*y + 0.745*x^2*y^2 - 0.029*x*y^3 + 0.072*y^4",
        domain: &[-1.6, 1.9, -2.0, 2.8],
        components: 2,
        euler: 0,
    },
    Preset {
        name: "sphere",
        description: "sphere of radius 0.6",
        dim: 3,
        expr: "x^2 + y^2 + z^2 - 0.36",
        domain: &[-1.0, 1.0, -1.0, 1.0, -1.0, 1.0],
        components: 1,
        euler: 2,
    },
    Preset {
        name: "torus",
        description: "torus with radii 0.6 and 0.25 around the z axis",
        dim: 3,
        expr: "(x^2 + y^2 + z^2 + 0.36 - 0.0625)^2 - 1.44*(x^2 + y^2)",
        domain: &[-1.0, 1.0, -1.0, 1.0, -0.5, 0.5],
        components: 1,
        euler: 0,
    },
    Preset {
        name: "genus2",
        description: "genus-2 surface: a tube (h² + z² = 0.01) around the figure eight h = x²(1−x²) − y² = 0",
        dim: 3,
        expr: "(x^2*(1 - x^2) - y^2)^2 + z^2 - 0.01",
        domain: &[-1.2, 1.2, -0.7, 0.7, -0.3, 0.3],
        components: 1,
        euler: -2,
    },
];

impl Preset {
    /// The preset called `name`.
    ///
    /// # Errors
    /// [`FitError::Options`] naming the known presets.
    pub fn find(name: &str) -> Result<&'static Preset, FitError> {
        PRESETS.iter().find(|p| p.name == name).ok_or_else(|| {
            let names: Vec<&str> = PRESETS.iter().map(|p| p.name).collect();
            FitError::Options(format!(
                "unknown preset `{name}`; known: {}",
                names.join(", ")
            ))
        })
    }

    /// The parsed expression.
    ///
    /// # Errors
    /// Never for the shipped presets (a test parses each).
    pub fn expression(&self) -> Result<Expression, FitError> {
        Expression::parse(self.expr, self.dim)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::expr::ImplicitFunction;

    #[test]
    fn every_preset_parses_with_interval_extension() {
        for p in PRESETS {
            let e = p.expression().unwrap();
            assert!(e.has_interval_extension(), "{}", p.name);
            assert_eq!(p.domain.len(), 2 * p.dim);
            // The domain's centre region is not all one sign: something to fit.
            let lo: Vec<f64> = p.domain.chunks(2).map(|c| c[0]).collect();
            let hi: Vec<f64> = p.domain.chunks(2).map(|c| c[1]).collect();
            let enc = e.enclose(&lo, &hi).unwrap();
            assert!(enc.value.contains(0.0), "{}", p.name);
        }
        assert!(Preset::find("nope").is_err());
    }
}
