//! Conservative interval arithmetic: the Plantinga–Vegter test of `ism-fit` and the certified
//! area-element bounds of `ism-sample`.
//!
//! Hand-written on purpose: the maintained crate `inari` only builds with
//! `RUSTFLAGS=-Ctarget-cpu=haswell` (it refuses plain stable x86-64), and a workspace-wide target-cpu
//! flag would change every other crate's build. We need only enclosure, not tightness, so each
//! operation rounds to nearest and then widens outward by more than its worst rounding error. The
//! results are therefore supersets of the true ranges ("conservative"), which is all the
//! Plantinga–Vegter test needs: a wider interval can only make the test refine more, never less.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// Relative outward widening of one correctly rounded operation: round-to-nearest errs by at most
/// half an ulp, i.e. `EPSILON / 2` relative; one full `EPSILON` covers it with margin.
const BASIC_REL: f64 = f64::EPSILON;

/// Relative outward widening of a libm transcendental (`sin`, `exp`, `ln`, …). glibc documents at
/// most a few ulps for these; 8 ulps is a generous bound.
const LIBM_REL: f64 = 8.0 * f64::EPSILON;

/// A closed interval `[lo, hi]`, possibly unbounded (`±∞` endpoints). Never empty.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Interval {
    /// Lower end.
    pub lo: f64,
    /// Upper end.
    pub hi: f64,
}

/// Pushes `x` down by `rel` relative plus the smallest normal, so subnormal and zero results widen
/// too.
fn down(x: f64, rel: f64) -> f64 {
    if x.is_nan() {
        return f64::NEG_INFINITY;
    }
    x - x.abs() * rel - f64::MIN_POSITIVE
}

fn up(x: f64, rel: f64) -> f64 {
    if x.is_nan() {
        return f64::INFINITY;
    }
    x + x.abs() * rel + f64::MIN_POSITIVE
}

impl Interval {
    /// The whole real line (what an undefined operation returns).
    pub const ENTIRE: Interval = Interval {
        lo: f64::NEG_INFINITY,
        hi: f64::INFINITY,
    };

    /// `[lo, hi]`; the ends are swapped if given in the wrong order and NaN gives the whole line.
    pub fn new(lo: f64, hi: f64) -> Interval {
        if lo.is_nan() || hi.is_nan() {
            return Interval::ENTIRE;
        }
        Interval {
            lo: lo.min(hi),
            hi: lo.max(hi),
        }
    }

    /// An enclosure of a real number whose nearest double is `x` (one rounding away).
    pub fn around(x: f64) -> Interval {
        Interval::widened(x, x, BASIC_REL)
    }

    /// The single point `x` (exact).
    pub fn point(x: f64) -> Interval {
        Interval::new(x, x)
    }

    fn widened(lo: f64, hi: f64, rel: f64) -> Interval {
        if lo.is_nan() || hi.is_nan() {
            return Interval::ENTIRE;
        }
        Interval {
            lo: down(lo, rel),
            hi: up(hi, rel),
        }
    }

    /// Whether `x` lies in the interval.
    pub fn contains(&self, x: f64) -> bool {
        self.lo <= x && x <= self.hi
    }

    /// `hi − lo`.
    pub fn width(&self) -> f64 {
        self.hi - self.lo
    }

    /// The intersection of two enclosures of the same quantity (if rounding made them disjoint,
    /// which two true enclosures cannot be, the hull is returned to stay safe).
    pub fn intersect(self, other: Interval) -> Interval {
        let lo = self.lo.max(other.lo);
        let hi = self.hi.min(other.hi);
        if lo <= hi {
            Interval { lo, hi }
        } else {
            self.hull(other)
        }
    }

    /// The hull of two intervals.
    pub fn hull(self, other: Interval) -> Interval {
        Interval {
            lo: self.lo.min(other.lo),
            hi: self.hi.max(other.hi),
        }
    }

    /// Enclosure of `x²` (tighter than `x·x` when the interval straddles 0).
    pub fn sqr(self) -> Interval {
        let a = self.lo * self.lo;
        let b = self.hi * self.hi;
        if self.contains(0.0) {
            Interval::widened(0.0, a.max(b), BASIC_REL).clamp_lo(0.0)
        } else {
            Interval::widened(a.min(b), a.max(b), BASIC_REL).clamp_lo(0.0)
        }
    }

    fn clamp_lo(self, floor: f64) -> Interval {
        Interval {
            lo: self.lo.max(floor),
            hi: self.hi.max(floor),
        }
    }

    /// Enclosure of `xⁿ` for an integer `n` (negative powers via division).
    pub fn powi(self, n: i32) -> Interval {
        if n == 0 {
            return Interval::point(1.0);
        }
        if n < 0 {
            return Interval::point(1.0) / self.powi(-n);
        }
        // Square-and-multiply keeps every step an enclosure.
        let mut result = Interval::point(1.0);
        let mut base = self;
        let mut e = n;
        while e > 0 {
            if e & 1 == 1 {
                result = result * base;
            }
            e >>= 1;
            if e > 0 {
                base = base.sqr();
            }
        }
        if n % 2 == 0 {
            result.clamp_lo(0.0)
        } else {
            result
        }
    }

    /// Enclosure of `a^b` (`b` an exact integer: repeated products; otherwise `exp(b·ln a)`).
    pub fn pow(self, b: Interval) -> Interval {
        if b.lo == b.hi && b.lo.fract() == 0.0 && b.lo.abs() <= 64.0 {
            return self.powi(b.lo as i32);
        }
        if self.lo > 0.0 {
            (b * self.ln()).exp()
        } else {
            Interval::ENTIRE
        }
    }

    /// Enclosure of `eˣ`.
    pub fn exp(self) -> Interval {
        Interval::widened(self.lo.exp(), self.hi.exp(), LIBM_REL).clamp_lo(0.0)
    }

    /// Enclosure of `ln x` (the whole line when `x` may be `≤ 0`).
    pub fn ln(self) -> Interval {
        if self.lo <= 0.0 {
            return Interval::ENTIRE;
        }
        Interval::widened(self.lo.ln(), self.hi.ln(), LIBM_REL)
    }

    /// Enclosure of `√x` (the whole line when `x` may be negative).
    pub fn sqrt(self) -> Interval {
        if self.lo < 0.0 {
            return Interval::ENTIRE;
        }
        Interval::widened(self.lo.sqrt(), self.hi.sqrt(), BASIC_REL).clamp_lo(0.0)
    }

    /// Enclosure of `|x|`.
    pub fn abs(self) -> Interval {
        if self.contains(0.0) {
            Interval {
                lo: 0.0,
                hi: self.lo.abs().max(self.hi.abs()),
            }
        } else {
            Interval::new(self.lo.abs(), self.hi.abs())
        }
    }

    /// Enclosure of `sign(x)`.
    pub fn signum(self) -> Interval {
        if self.lo > 0.0 {
            Interval::point(1.0)
        } else if self.hi < 0.0 {
            Interval::point(-1.0)
        } else {
            Interval::new(-1.0, 1.0)
        }
    }

    fn clamp_to_unit(self) -> Interval {
        Interval {
            lo: self.lo.max(-1.0),
            hi: self.hi.min(1.0),
        }
    }

    /// Enclosure of `sin x`: endpoint values plus ±1 when a crest or trough lies inside.
    pub fn sin(self) -> Interval {
        self.periodic(0.5 * std::f64::consts::PI, f64::sin)
    }

    /// Enclosure of `cos x`.
    pub fn cos(self) -> Interval {
        self.periodic(0.0, f64::cos)
    }

    /// `f` has its maximum at `peak + 2kπ` and minimum at `peak + π + 2kπ`.
    fn periodic(self, peak: f64, f: fn(f64) -> f64) -> Interval {
        use std::f64::consts::{PI, TAU};
        if self.width().is_nan() || self.width() >= TAU || !self.lo.is_finite() {
            return Interval::new(-1.0, 1.0);
        }
        let a = f(self.lo);
        let b = f(self.hi);
        let mut out = Interval::widened(a.min(b), a.max(b), LIBM_REL);
        // Extremum k lies in [lo, hi] iff ceil((lo − x₀)/2π) ≤ floor((hi − x₀)/2π); the quotients
        // are rounded, so widen the test by one step and accept a too-wide (still valid) result.
        let hits = |x0: f64| {
            let k0 = ((self.lo - x0) / TAU).floor();
            let k1 = ((self.hi - x0) / TAU).ceil();
            k1 - k0 >= 1.0
        };
        if hits(peak) {
            out.hi = 1.0;
        }
        if hits(peak + PI) {
            out.lo = -1.0;
        }
        out.clamp_to_unit()
    }

    /// Enclosure of `tan x` (the whole line when a pole may lie inside).
    pub fn tan(self) -> Interval {
        use std::f64::consts::PI;
        let k0 = ((self.lo - 0.5 * PI) / PI).floor();
        let k1 = ((self.hi - 0.5 * PI) / PI).floor();
        if k0 != k1 || !self.width().is_finite() || self.width() >= PI - 1e-9 {
            return Interval::ENTIRE;
        }
        Interval::widened(self.lo.tan(), self.hi.tan(), LIBM_REL)
    }
}

impl Add for Interval {
    type Output = Interval;
    fn add(self, o: Interval) -> Interval {
        Interval::widened(self.lo + o.lo, self.hi + o.hi, BASIC_REL)
    }
}

impl Sub for Interval {
    type Output = Interval;
    fn sub(self, o: Interval) -> Interval {
        Interval::widened(self.lo - o.hi, self.hi - o.lo, BASIC_REL)
    }
}

impl Neg for Interval {
    type Output = Interval;
    fn neg(self) -> Interval {
        Interval {
            lo: -self.hi,
            hi: -self.lo,
        }
    }
}

impl Mul for Interval {
    type Output = Interval;
    fn mul(self, o: Interval) -> Interval {
        let p = [
            self.lo * o.lo,
            self.lo * o.hi,
            self.hi * o.lo,
            self.hi * o.hi,
        ];
        if p.iter().any(|x| x.is_nan()) {
            // 0 · ∞: the true range is unbounded in general.
            return Interval::ENTIRE;
        }
        let lo = p.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = p.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        Interval::widened(lo, hi, BASIC_REL)
    }
}

impl Div for Interval {
    type Output = Interval;
    fn div(self, o: Interval) -> Interval {
        if o.contains(0.0) {
            return Interval::ENTIRE;
        }
        let p = [
            self.lo / o.lo,
            self.lo / o.hi,
            self.hi / o.lo,
            self.hi / o.hi,
        ];
        if p.iter().any(|x| x.is_nan()) {
            return Interval::ENTIRE;
        }
        let lo = p.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = p.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        Interval::widened(lo, hi, BASIC_REL)
    }
}

impl std::str::FromStr for Interval {
    type Err = std::num::ParseFloatError;

    /// A decimal literal: exact when it is an integer below 2⁵³ written without a fraction,
    /// otherwise the parsed double widened by one ulp each way (the decimal value lies within half
    /// an ulp of it).
    fn from_str(text: &str) -> Result<Interval, Self::Err> {
        let v: f64 = text.parse()?;
        let integral = {
            let (int, frac) = text.split_once('.').unwrap_or((text, ""));
            int.bytes().all(|c| c.is_ascii_digit()) && frac.bytes().all(|c| c == b'0')
        };
        if integral && v.abs() < 9.0e15 {
            Ok(Interval::point(v))
        } else {
            Ok(Interval::around(v))
        }
    }
}

impl std::fmt::Display for Interval {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "[{}, {}]", self.lo, self.hi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn iv() -> impl Strategy<Value = Interval> {
        (-10.0f64..10.0, 0.0f64..5.0).prop_map(|(a, w)| Interval::new(a, a + w))
    }

    proptest! {
        // Enclosure: every sampled point's image lies in the computed interval.
        #[test]
        fn operations_enclose_their_point_values(a in iv(), b in iv(), s in 0.0f64..=1.0, t in 0.0f64..=1.0) {
            let x = a.lo + s * (a.hi - a.lo);
            let y = b.lo + t * (b.hi - b.lo);
            prop_assert!((a + b).contains(x + y));
            prop_assert!((a - b).contains(x - y));
            prop_assert!((a * b).contains(x * y));
            if !b.contains(0.0) { prop_assert!((a / b).contains(x / y)); }
            prop_assert!(a.sqr().contains(x * x));
            prop_assert!(a.powi(3).contains(x.powi(3)));
            prop_assert!(a.powi(4).contains(x.powi(4)));
            prop_assert!(a.sin().contains(x.sin()));
            prop_assert!(a.cos().contains(x.cos()));
            prop_assert!(a.exp().contains(x.exp()));
            prop_assert!(a.abs().contains(x.abs()));
            if a.lo > 0.0 {
                prop_assert!(a.ln().contains(x.ln()));
                prop_assert!(a.sqrt().contains(x.sqrt()));
                prop_assert!(a.pow(Interval::point(0.5)).contains(x.powf(0.5)));
            }
        }
    }

    #[test]
    fn crests_inside_are_found() {
        let i = Interval::new(1.0, 2.0); // contains π/2
        assert_eq!(i.sin().hi, 1.0);
        assert!(i.sin().lo <= 1.0f64.sin());
        let j = Interval::new(3.0, 3.5); // contains π: cos has its minimum there
        assert_eq!(j.cos().lo, -1.0);
        assert!(Interval::new(-1.0, 1.0).sqr().lo == 0.0);
        assert_eq!(
            Interval::new(-1.0, 1.0) / Interval::new(-1.0, 2.0),
            Interval::ENTIRE
        );
    }
}
