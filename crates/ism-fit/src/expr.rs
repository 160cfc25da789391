//! Implicit functions `g: Rⁿ → R`: the [`ImplicitFunction`] trait and user expressions.
//!
//! An [`Expression`] is parsed by `exmex` (variables `x`, `y`, `z`), evaluated in `f64`, its
//! gradient comes from `exmex`'s exact symbolic partial derivatives, and both the value and the
//! gradient are also compiled over [`Interval`] for the Plantinga–Vegter test.
//!
//! Syntax caveat inherited from `exmex`: unary operators bind tighter than binary ones, so
//! `-x^2` means `(-x)^2`. Write `0-x^2` or `-(x^2)`.

use exmex::prelude::*;
use exmex::{BinOp, FlatEx, MakeOperators, NumberMatcher, Operator};

use crate::interval::Interval;
use crate::FitError;

/// Names of the coordinates, in order.
pub const VARIABLES: [&str; 3] = ["x", "y", "z"];

/// Interval enclosures of a function and its gradient over a box.
#[derive(Clone, Debug, PartialEq)]
pub struct Enclosure {
    /// Encloses `g` over the box.
    pub value: Interval,
    /// Encloses each partial derivative over the box.
    pub gradient: Vec<Interval>,
}

/// A function whose zero set is the shape to fit.
pub trait ImplicitFunction: Sync {
    /// Number of variables `n` (2 or 3).
    fn dim(&self) -> usize;
    /// `g(p)`.
    fn value(&self, p: &[f64]) -> f64;
    /// Writes `∇g(p)` into `gradient` and returns `g(p)`.
    fn gradient(&self, p: &[f64], gradient: &mut [f64]) -> f64;
    /// Enclosures of `g` and `∇g` over the box `[lo, hi]`, or `None` when the function has no
    /// interval extension.
    fn enclose(&self, lo: &[f64], hi: &[f64]) -> Option<Enclosure>;

    /// `|g(p)| / |∇g(p)|`: the first-order estimate of the distance from `p` to the zero set
    /// (infinite where the gradient vanishes).
    fn distance_estimate(&self, p: &[f64]) -> f64 {
        let mut grad = [0.0; 3];
        let n = self.dim();
        let v = self.gradient(p, &mut grad[..n]);
        let norm = grad[..n].iter().map(|g| g * g).sum::<f64>().sqrt();
        if norm > 0.0 {
            v.abs() / norm
        } else if v == 0.0 {
            0.0
        } else {
            f64::INFINITY
        }
    }
}

/// `exmex` operators over [`Interval`], with the priorities of `exmex`'s float operators so a text
/// parses to the same tree in both number types.
#[derive(Clone, Debug)]
pub struct IntervalOps;

impl MakeOperators<Interval> for IntervalOps {
    fn make<'a>() -> Vec<Operator<'a, Interval>> {
        use std::f64::consts::{E, PI, TAU};
        // Constants that are not exact doubles are widened like literals.
        let around = Interval::around;
        vec![
            Operator::make_bin(
                "^",
                BinOp {
                    apply: |a: Interval, b| a.pow(b),
                    prio: 4,
                    is_commutative: false,
                },
            ),
            Operator::make_bin(
                "*",
                BinOp {
                    apply: |a: Interval, b| a * b,
                    prio: 2,
                    is_commutative: true,
                },
            ),
            Operator::make_bin(
                "/",
                BinOp {
                    apply: |a: Interval, b| a / b,
                    prio: 3,
                    is_commutative: false,
                },
            ),
            Operator::make_bin_unary(
                "+",
                BinOp {
                    apply: |a: Interval, b| a + b,
                    prio: 0,
                    is_commutative: true,
                },
                |a| a,
            ),
            Operator::make_bin_unary(
                "-",
                BinOp {
                    apply: |a: Interval, b| a - b,
                    prio: 1,
                    is_commutative: false,
                },
                |a: Interval| -a,
            ),
            Operator::make_unary("abs", |a: Interval| a.abs()),
            Operator::make_unary("signum", |a: Interval| a.signum()),
            Operator::make_unary("sin", |a: Interval| a.sin()),
            Operator::make_unary("cos", |a: Interval| a.cos()),
            Operator::make_unary("tan", |a: Interval| a.tan()),
            Operator::make_unary("exp", |a: Interval| a.exp()),
            Operator::make_unary("sqrt", |a: Interval| a.sqrt()),
            Operator::make_unary("ln", |a: Interval| a.ln()),
            Operator::make_unary("log", |a: Interval| a.ln()),
            Operator::make_constant("PI", around(PI)),
            Operator::make_constant("π", around(PI)),
            Operator::make_constant("E", around(E)),
            Operator::make_constant("e", around(E)),
            Operator::make_constant("TAU", around(TAU)),
            Operator::make_constant("τ", around(TAU)),
        ]
    }
}

type IntervalEx = FlatEx<Interval, IntervalOps, NumberMatcher>;

/// One compiled expression and, for each of its variables (in `exmex`'s order), the coordinate it
/// reads.
#[derive(Clone, Debug)]
struct Compiled<E> {
    ex: E,
    slots: Vec<usize>,
}

fn slots_of(names: &[String], dim: usize, text: &str) -> Result<Vec<usize>, FitError> {
    names
        .iter()
        .map(|name| {
            VARIABLES[..dim]
                .iter()
                .position(|v| v == name)
                .ok_or_else(|| FitError::Expression {
                    text: text.to_string(),
                    message: format!(
                        "unknown variable `{name}`; a {dim}-D expression may use {}",
                        VARIABLES[..dim].join(", ")
                    ),
                })
        })
        .collect()
}

/// A user expression `g(x, y[, z])` with its exact gradient and interval extensions.
#[derive(Clone, Debug)]
pub struct Expression {
    text: String,
    dim: usize,
    value: Compiled<FlatEx<f64>>,
    /// `None` where the expression does not depend on that coordinate (derivative 0).
    partials: Vec<Option<Compiled<FlatEx<f64>>>>,
    interval_value: Option<Compiled<IntervalEx>>,
    interval_partials: Option<Vec<Option<Compiled<IntervalEx>>>>,
    /// Second partials `[i][j]` over intervals, for the mean-value form of the gradient.
    interval_hessian: Option<Vec<Vec<Option<Compiled<IntervalEx>>>>>,
}

impl Expression {
    /// Parses `text` as a function of the first `dim` of `x, y, z`.
    ///
    /// # Errors
    /// [`FitError::Expression`] when the text does not parse, uses another variable, or has no
    /// symbolic derivative.
    pub fn parse(text: &str, dim: usize) -> Result<Expression, FitError> {
        if !(1..=3).contains(&dim) {
            return Err(FitError::Options(format!(
                "dimension {dim} is not 1, 2 or 3"
            )));
        }
        let err = |message: String| FitError::Expression {
            text: text.to_string(),
            message,
        };
        let ex = exmex::parse::<f64>(text).map_err(|e| err(e.to_string()))?;
        let slots = slots_of(ex.var_names(), dim, text)?;
        let mut partials = vec![None; dim];
        for (var_index, &coord) in slots.iter().enumerate() {
            let d = ex
                .clone()
                .partial(var_index)
                .map_err(|e| err(format!("no derivative: {e}")))?;
            let d_slots = slots_of(d.var_names(), dim, text)?;
            partials[coord] = Some(Compiled {
                ex: d,
                slots: d_slots,
            });
        }
        // The interval versions re-parse the same texts; a function without an interval extension
        // (e.g. `atan`) still fits, only without the Plantinga–Vegter test.
        let to_interval = |f: &FlatEx<f64>| -> Option<Compiled<IntervalEx>> {
            let t = f.unparse();
            let t: &str = t;
            let ex = IntervalEx::parse(t).ok()?;
            let slots = slots_of(ex.var_names(), dim, text).ok()?;
            Some(Compiled { ex, slots })
        };
        let interval_value = to_interval(&ex);
        let interval_partials: Option<Vec<Option<Compiled<IntervalEx>>>> = partials
            .iter()
            .map(|p| match p {
                None => Some(None),
                Some(c) => to_interval(&c.ex).map(Some),
            })
            .collect();
        let interval_hessian: Option<Vec<Vec<Option<Compiled<IntervalEx>>>>> = partials
            .iter()
            .map(|p| -> Option<Vec<Option<Compiled<IntervalEx>>>> {
                let mut row = vec![None; dim];
                if let Some(c) = p {
                    for (var_index, &coord) in c.slots.iter().enumerate() {
                        let d2 = c.ex.clone().partial(var_index).ok()?;
                        row[coord] = Some(to_interval(&d2)?);
                    }
                }
                Some(row)
            })
            .collect();
        let (interval_value, interval_partials) = match (interval_value, interval_partials) {
            (Some(v), Some(p)) => (Some(v), Some(p)),
            _ => (None, None),
        };
        Ok(Expression {
            text: text.to_string(),
            dim,
            value: Compiled { ex, slots },
            partials,
            interval_value,
            interval_partials,
            interval_hessian,
        })
    }

    /// The source text.
    pub fn text(&self) -> &str {
        &self.text
    }

    /// Whether interval enclosures are available (every function used has an interval version).
    pub fn has_interval_extension(&self) -> bool {
        self.interval_value.is_some()
    }
}

fn eval_f64(c: &Compiled<FlatEx<f64>>, p: &[f64]) -> f64 {
    let mut args = [0.0; 3];
    for (a, &s) in args.iter_mut().zip(&c.slots) {
        *a = p[s];
    }
    // exmex only fails on a wrong argument count, which `slots` rules out; NaN is the honest
    // answer if it ever did.
    c.ex.eval(&args[..c.slots.len()]).unwrap_or(f64::NAN)
}

fn eval_interval(c: &Compiled<IntervalEx>, b: &[Interval]) -> Interval {
    let mut args = [Interval::default(); 3];
    for (a, &s) in args.iter_mut().zip(&c.slots) {
        *a = b[s];
    }
    c.ex.eval(&args[..c.slots.len()])
        .unwrap_or(Interval::ENTIRE)
}

impl ImplicitFunction for Expression {
    fn dim(&self) -> usize {
        self.dim
    }

    fn value(&self, p: &[f64]) -> f64 {
        eval_f64(&self.value, p)
    }

    fn gradient(&self, p: &[f64], gradient: &mut [f64]) -> f64 {
        for (g, d) in gradient.iter_mut().zip(&self.partials) {
            *g = d.as_ref().map_or(0.0, |d| eval_f64(d, p));
        }
        self.value(p)
    }

    /// Natural interval extensions intersected with mean-value forms around the box centre
    /// (`g(c) + □∇g·(box − c)`, and `∇g(c) + □H·(box − c)` for the gradient): the natural extension
    /// of an expanded polynomial loses all cancellation between its terms, while the mean-value
    /// form overestimates only to second order in the box size. Both enclose, so their
    /// intersection does.
    fn enclose(&self, lo: &[f64], hi: &[f64]) -> Option<Enclosure> {
        let value = self.interval_value.as_ref()?;
        let partials = self.interval_partials.as_ref()?;
        let boxes: Vec<Interval> = lo
            .iter()
            .zip(hi)
            .map(|(&a, &b)| Interval::new(a, b))
            .collect();
        let centre: Vec<Interval> = lo
            .iter()
            .zip(hi)
            .map(|(&a, &b)| Interval::point(0.5 * (a + b)))
            .collect();
        let offsets: Vec<Interval> = boxes.iter().zip(&centre).map(|(b, c)| *b - *c).collect();
        let partial_over = |d: &Option<Compiled<IntervalEx>>, over: &[Interval]| {
            d.as_ref()
                .map_or(Interval::point(0.0), |d| eval_interval(d, over))
        };
        let natural: Vec<Interval> = partials.iter().map(|d| partial_over(d, &boxes)).collect();
        let mut v = eval_interval(value, &centre);
        for (g, o) in natural.iter().zip(&offsets) {
            v = v + *g * *o;
        }
        let value = eval_interval(value, &boxes).intersect(v);
        let gradient = match &self.interval_hessian {
            Some(h) => natural
                .iter()
                .zip(partials.iter().zip(h))
                .map(|(nat, (d, row))| {
                    let mut g = partial_over(d, &centre);
                    for (hd, o) in row.iter().zip(&offsets) {
                        g = g + partial_over(hd, &boxes) * *o;
                    }
                    nat.intersect(g)
                })
                .collect(),
            None => natural,
        };
        Some(Enclosure { value, gradient })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn parses_evaluates_and_differentiates() {
        let e = Expression::parse("x^2 + y^2 - 0.28^2", 2).unwrap();
        let mut g = [0.0; 2];
        let v = e.gradient(&[0.5, -0.25], &mut g);
        assert!((v - (0.25 + 0.0625 - 0.0784)).abs() < 1e-15);
        assert_eq!(g, [1.0, -0.5]);
        // A variable that does not occur has derivative 0.
        let e = Expression::parse("sin(x) - 0.5", 2).unwrap();
        let _ = e.gradient(&[0.3, 9.0], &mut g);
        assert!((g[0] - 0.3f64.cos()).abs() < 1e-15 && g[1] == 0.0);
    }

    #[test]
    fn rejects_unknown_variables_and_syntax() {
        assert!(matches!(
            Expression::parse("x + w", 2),
            Err(FitError::Expression { .. })
        ));
        assert!(matches!(
            Expression::parse("x + z", 2),
            Err(FitError::Expression { .. })
        ));
        assert!(matches!(
            Expression::parse("x + (y", 2),
            Err(FitError::Expression { .. })
        ));
    }

    #[test]
    fn unary_minus_binds_tighter_than_power() {
        // Documented exmex behaviour; the presets are written with it in mind.
        let e = Expression::parse("-x^2", 1).unwrap();
        assert_eq!(e.value(&[2.0]), 4.0);
        let e = Expression::parse("0-x^2", 1).unwrap();
        assert_eq!(e.value(&[2.0]), -4.0);
    }

    fn torus() -> Expression {
        Expression::parse(
            "(x^2 + y^2 + z^2 + 0.36 - 0.0625)^2 - 1.44*(x^2 + y^2) + sin(x*z)",
            3,
        )
        .unwrap()
    }

    proptest! {
        // Cross-check 1: the symbolic gradient against central differences.
        #[test]
        fn gradient_matches_finite_differences(x in -1.0f64..1.0, y in -1.0f64..1.0, z in -1.0f64..1.0) {
            let e = torus();
            let p = [x, y, z];
            let mut g = [0.0; 3];
            e.gradient(&p, &mut g);
            for k in 0..3 {
                let h = 1e-6;
                let mut a = p; a[k] += h;
                let mut b = p; b[k] -= h;
                let fd = (e.value(&a) - e.value(&b)) / (2.0 * h);
                prop_assert!((fd - g[k]).abs() < 1e-6 * (1.0 + g[k].abs()), "k={} fd={} g={}", k, fd, g[k]);
            }
        }

        // Cross-check 2: interval enclosures contain the point values and derivatives.
        #[test]
        fn enclosures_contain_point_values(x in -1.0f64..0.8, y in -1.0f64..0.8, z in -1.0f64..0.8,
                                           s in 0.0f64..=1.0, t in 0.0f64..=1.0, u in 0.0f64..=1.0) {
            let e = torus();
            let lo = [x, y, z];
            let hi = [x + 0.2, y + 0.2, z + 0.2];
            let p = [x + 0.2 * s, y + 0.2 * t, z + 0.2 * u];
            let enc = e.enclose(&lo, &hi).unwrap();
            prop_assert!(enc.value.contains(e.value(&p)));
            let mut g = [0.0; 3];
            e.gradient(&p, &mut g);
            for (bound, gk) in enc.gradient.iter().zip(g) {
                prop_assert!(bound.contains(gk));
            }
        }
    }
}
