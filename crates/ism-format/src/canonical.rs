//! The canonical spelling of numbers and JSON text (spec §7.7), used by every encoding that writes
//! text: the JSON encoding and the `json` members of the binary encoding.
//!
//! serde_json's own float formatting is not used: it has changed between releases (`1e16` became
//! `1e+16`), and the spec fixes one spelling so that files are byte-for-byte reproducible.

use std::io;

/// The canonical JSON spelling of a finite `f64` (spec §7.7): the shortest decimal digits that read
/// back to the same value, laid out by the position of the decimal point.
///
/// ```
/// use ism_format::canonical::format_f64;
/// assert_eq!(format_f64(1.0), "1.0");
/// assert_eq!(format_f64(0.00001), "0.00001");
/// assert_eq!(format_f64(1e-6), "1e-6");
/// assert_eq!(format_f64(1e16), "1e16");
/// assert_eq!(format_f64(-0.0), "-0.0");
/// ```
///
/// # Panics
/// On NaN or infinity, which JSON cannot hold (writers refuse them before formatting).
pub fn format_f64(x: f64) -> String {
    assert!(x.is_finite(), "JSON numbers are finite");
    let sign = if x.is_sign_negative() { "-" } else { "" };
    if x == 0.0 {
        return format!("{sign}0.0");
    }
    // Rust's `{:e}` prints the shortest digits that round-trip (the nearest such when several).
    let sci = format!("{:e}", x.abs());
    let (mantissa, exponent) = sci.split_once('e').expect("{:e} has an exponent");
    let digits: String = mantissa.chars().filter(|c| *c != '.').collect();
    let exponent: i32 = exponent.parse().expect("decimal exponent");
    let len = digits.len() as i32;
    // The value is 0.d₁d₂…d_len × 10^point.
    let point = exponent + 1;
    let body = if 0 < point && point <= 16 {
        if len <= point {
            format!("{digits}{}.0", "0".repeat((point - len) as usize))
        } else {
            format!(
                "{}.{}",
                &digits[..point as usize],
                &digits[point as usize..]
            )
        }
    } else if -5 < point && point <= 0 {
        format!("0.{}{digits}", "0".repeat((-point) as usize))
    } else if len == 1 {
        format!("{digits}e{exponent}")
    } else {
        format!("{}.{}e{exponent}", &digits[..1], &digits[1..])
    };
    format!("{sign}{body}")
}

/// A serde_json formatter that writes floats canonically and delegates layout to `F`
/// (compact or pretty).
pub(crate) struct Canonical<F>(pub F);

impl<F: serde_json::ser::Formatter> serde_json::ser::Formatter for Canonical<F> {
    fn write_f64<W: ?Sized + io::Write>(&mut self, writer: &mut W, value: f64) -> io::Result<()> {
        writer.write_all(format_f64(value).as_bytes())
    }
    fn write_f32<W: ?Sized + io::Write>(&mut self, writer: &mut W, value: f32) -> io::Result<()> {
        self.write_f64(writer, f64::from(value))
    }
    fn begin_array<W: ?Sized + io::Write>(&mut self, w: &mut W) -> io::Result<()> {
        self.0.begin_array(w)
    }
    fn end_array<W: ?Sized + io::Write>(&mut self, w: &mut W) -> io::Result<()> {
        self.0.end_array(w)
    }
    fn begin_array_value<W: ?Sized + io::Write>(
        &mut self,
        w: &mut W,
        first: bool,
    ) -> io::Result<()> {
        self.0.begin_array_value(w, first)
    }
    fn end_array_value<W: ?Sized + io::Write>(&mut self, w: &mut W) -> io::Result<()> {
        self.0.end_array_value(w)
    }
    fn begin_object<W: ?Sized + io::Write>(&mut self, w: &mut W) -> io::Result<()> {
        self.0.begin_object(w)
    }
    fn end_object<W: ?Sized + io::Write>(&mut self, w: &mut W) -> io::Result<()> {
        self.0.end_object(w)
    }
    fn begin_object_key<W: ?Sized + io::Write>(
        &mut self,
        w: &mut W,
        first: bool,
    ) -> io::Result<()> {
        self.0.begin_object_key(w, first)
    }
    fn end_object_key<W: ?Sized + io::Write>(&mut self, w: &mut W) -> io::Result<()> {
        self.0.end_object_key(w)
    }
    fn begin_object_value<W: ?Sized + io::Write>(&mut self, w: &mut W) -> io::Result<()> {
        self.0.begin_object_value(w)
    }
    fn end_object_value<W: ?Sized + io::Write>(&mut self, w: &mut W) -> io::Result<()> {
        self.0.end_object_value(w)
    }
}

/// Serializes `value` as canonical JSON text: compact, or pretty (two-space indent) when `pretty`.
///
/// # Errors
/// Whatever `value`'s serialization reports (non-finite numbers must be refused before).
pub(crate) fn to_json_vec<T: serde::Serialize + ?Sized>(
    value: &T,
    pretty: bool,
) -> serde_json::Result<Vec<u8>> {
    let mut out = Vec::new();
    to_json_writer(value, pretty, &mut out)?;
    Ok(out)
}

/// [`to_json_vec`] into a writer.
///
/// # Errors
/// As [`to_json_vec`], plus the writer's.
pub(crate) fn to_json_writer<T: serde::Serialize + ?Sized, W: io::Write>(
    value: &T,
    pretty: bool,
    out: W,
) -> serde_json::Result<()> {
    if pretty {
        let formatter = Canonical(serde_json::ser::PrettyFormatter::with_indent(b"  "));
        value.serialize(&mut serde_json::Serializer::with_formatter(out, formatter))
    } else {
        let formatter = Canonical(serde_json::ser::CompactFormatter);
        value.serialize(&mut serde_json::Serializer::with_formatter(out, formatter))
    }
}

/// The canonical compact JSON text of a value: how the binary encoding stores `json` members.
pub fn json_text(value: &serde_json::Value) -> String {
    String::from_utf8(to_json_vec(value, false).expect("JSON values serialize"))
        .expect("serde_json writes UTF-8")
}

#[cfg(test)]
mod tests {
    use super::format_f64;

    /// Expected spellings worked out by hand from spec §7.7, not from any formatter.
    #[test]
    fn spellings_follow_the_spec_table() {
        let cases: &[(f64, &str)] = &[
            (0.0, "0.0"),
            (-0.0, "-0.0"),
            (1.0, "1.0"),
            (-2.5, "-2.5"),
            (100.0, "100.0"),
            (0.1, "0.1"),
            (0.1 + 0.2, "0.30000000000000004"),
            (0.0001, "0.0001"),
            (0.00001, "0.00001"),
            (0.000012345, "0.000012345"),
            (0.000001, "1e-6"),
            (1.2345e-7, "1.2345e-7"),
            (1e15, "1000000000000000.0"),
            (1234567890123456.0, "1234567890123456.0"),
            (1e16, "1e16"),
            (1.5e16, "1.5e16"),
            (123456789012345680.0, "1.2345678901234568e17"),
            (1e21, "1e21"),
            (5e-324, "5e-324"),
            (f64::MAX, "1.7976931348623157e308"),
            (f64::MIN_POSITIVE, "2.2250738585072014e-308"),
            (12345678.9, "12345678.9"),
        ];
        for &(x, text) in cases {
            assert_eq!(format_f64(x), text, "{x:?}");
            assert_eq!(
                text.parse::<f64>().unwrap().to_bits(),
                x.to_bits(),
                "{text}"
            );
        }
    }
}
