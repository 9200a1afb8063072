//! Protobuf messages' JSON as AimRT's protobuf prints doubles and floats, where serde_json
//! alone differs:
//!
//! - a value that is not finite is the string `"NaN"`, `"Infinity"` or `"-Infinity"` (the
//!   proto3 JSON mapping); serde_json writes `null`, which no decoder reads back as that
//!   number, so such a message was lost on its way through JSON;
//! - a finite one is printed as protobuf's C++ `SimpleDtoa` does: `%.15g`, or `%.17g`
//!   where 15 significant digits do not read back as the same double (floats: `%.6g`, or
//!   `%.9g`), so `1` not `1.0`, `1e-09` not `1e-9`, `-0` not `-0.0`.
//!
//! - a `google.protobuf.Timestamp` ends in `Z`, not `+00:00`.
//!
//! The non-finite values are caught by [`Floats`], a serializer that hands everything else
//! on unchanged; the finite ones reach serde_json's writer through [`CFormatter`]; a
//! `Timestamp` is found by its type where [`Fix`] wraps each value.

use std::fmt::Write as _;
use std::io;

use serde::ser::{
    Serialize, SerializeMap, SerializeSeq, SerializeStruct, SerializeStructVariant, SerializeTuple,
    SerializeTupleStruct, SerializeTupleVariant, Serializer,
};

/// `msg` as JSON, its doubles and floats as AimRT's protobuf writes them.
pub(crate) fn to_vec<T: Serialize + ?Sized>(msg: &T) -> serde_json::Result<Vec<u8>> {
    let mut out = Vec::with_capacity(128);
    let mut ser = serde_json::Serializer::with_formatter(&mut out, CFormatter);
    Fix(msg).serialize(&mut ser)?;
    Ok(out)
}

/// A little text on the stack: what a formatted number needs, without an allocation.
struct Text {
    buf: [u8; 48],
    len: usize,
}

impl Text {
    fn new() -> Text {
        Text {
            buf: [0; 48],
            len: 0,
        }
    }

    fn push(&mut self, bytes: &[u8]) {
        // Never more than 48: a sign, 17 digits, a point, up to 22 zeros or an exponent.
        let end = (self.len + bytes.len()).min(self.buf.len());
        self.buf[self.len..end].copy_from_slice(&bytes[..end - self.len]);
        self.len = end;
    }

    fn zeros(&mut self, n: usize) {
        for _ in 0..n {
            self.push(b"0");
        }
    }

    fn as_str(&self) -> &str {
        // Only ASCII is pushed.
        std::str::from_utf8(&self.buf[..self.len]).unwrap_or("")
    }
}

impl std::fmt::Write for Text {
    fn write_str(&mut self, s: &str) -> std::fmt::Result {
        self.push(s.as_bytes());
        Ok(())
    }
}

/// A finite value as its decimal digits (no trailing zeros; `0` for zero) and the
/// exponent of the first: `-1.25e-3` is `-`, `125`, `-3`.
struct Decimal {
    negative: bool,
    digits: [u8; 24],
    len: usize,
    exp: i32,
}

impl Decimal {
    /// From Rust's `{:e}` (the shortest digits that read back, the closest of them) or
    /// `{:.ne}` (n + 1 digits, correctly rounded from the exact value, as glibc's printf
    /// rounds).
    fn of(sci: &Text) -> Decimal {
        let text = sci.as_str();
        let (negative, rest) = match text.strip_prefix('-') {
            Some(rest) => (true, rest),
            None => (false, text),
        };
        let (mantissa, exp) = rest.split_once('e').unwrap_or((rest, "0"));
        let mut d = Decimal {
            negative,
            digits: [0; 24],
            len: 0,
            exp: exp.parse().unwrap_or(0),
        };
        for &c in mantissa.as_bytes().iter().filter(|c| c.is_ascii_digit()) {
            if d.len < d.digits.len() {
                d.digits[d.len] = c;
                d.len += 1;
            }
        }
        while d.len > 1 && d.digits[d.len - 1] == b'0' {
            d.len -= 1;
        }
        d
    }

    fn digits(&self) -> &[u8] {
        &self.digits[..self.len.max(1)]
    }

    /// C's `%.<p>g` of the value, whose digits are its rounding to `p` digits: fixed
    /// notation, or the exponent form (`1.5e-07`, `1e+20`: a sign and two digits at
    /// least) when the exponent is below -4 or not below `p`.
    fn c_g(&self, p: i32) -> Text {
        let mut out = Text::new();
        if self.negative {
            out.push(b"-");
        }
        let digits = self.digits();
        let x = self.exp;
        if x < -4 || x >= p {
            out.push(&digits[..1]);
            if digits.len() > 1 {
                out.push(b".");
                out.push(&digits[1..]);
            }
            let sign = if x < 0 { '-' } else { '+' };
            let _ = write!(out, "e{sign}{:02}", x.unsigned_abs());
        } else if x < 0 {
            out.push(b"0.");
            out.zeros(x.unsigned_abs() as usize - 1);
            out.push(digits);
        } else {
            let whole = x as usize + 1;
            if digits.len() <= whole {
                out.push(digits);
                out.zeros(whole - digits.len());
            } else {
                out.push(&digits[..whole]);
                out.push(b".");
                out.push(&digits[whole..]);
            }
        }
        out
    }
}

/// The text of `value` formatted by `args` (`{:e}`, `{:.16e}`), on the stack.
fn text(args: std::fmt::Arguments<'_>) -> Text {
    let mut out = Text::new();
    let _ = out.write_fmt(args);
    out
}

/// protobuf's `SimpleDtoa` / `SimpleFtoa` of a finite value: `%.<short>g` where it reads
/// back, else `%.<long>g`. For a normal value the shortest digits that read back
/// (`shortest`, `{:e}`) decide: `short` of them or fewer are its rounding to `short`
/// digits (its spacing is finer than `short` digits', so no other `short`-digit string is
/// as close); more, and no `short`-digit string reads back, so `%.<long>g` it is, from the
/// exact rounding (not the shortest digits: on a tie printf rounds half to even, and
/// `{:e}` may not). For a subnormal both exact roundings decide, as printf's do.
fn simple_toa(
    shortest: Text,
    normal: bool,
    short: i32,
    long: i32,
    exact: impl Fn(i32) -> Text,
    reads_back: impl Fn(&str) -> bool,
) -> Text {
    let d = Decimal::of(&shortest);
    if normal && d.len as i32 <= short {
        return d.c_g(short);
    }
    if !normal {
        let rounded = Decimal::of(&exact(short)).c_g(short);
        if reads_back(rounded.as_str()) {
            return rounded;
        }
    }
    Decimal::of(&exact(long)).c_g(long)
}

/// protobuf's `SimpleDtoa` (finite `v`): `%.15g`, or `%.17g`.
fn dtoa(v: f64) -> Text {
    simple_toa(
        text(format_args!("{v:e}")),
        v == 0.0 || v.abs() >= f64::MIN_POSITIVE,
        15,
        17,
        |p| text(format_args!("{v:.*e}", p as usize - 1)),
        |t| t.parse::<f64>() == Ok(v),
    )
}

/// protobuf's `SimpleFtoa` (finite `v`): `%.6g`, or `%.9g`.
fn ftoa(v: f32) -> Text {
    simple_toa(
        text(format_args!("{v:e}")),
        v == 0.0 || v.abs() >= f32::MIN_POSITIVE,
        6,
        9,
        |p| text(format_args!("{v:.*e}", p as usize - 1)),
        |t| t.parse::<f32>() == Ok(v),
    )
}

/// serde_json's compact layout, with finite doubles and floats as [`dtoa`] / [`ftoa`].
struct CFormatter;

impl serde_json::ser::Formatter for CFormatter {
    fn write_f64<W: ?Sized + io::Write>(&mut self, writer: &mut W, value: f64) -> io::Result<()> {
        writer.write_all(dtoa(value).as_str().as_bytes())
    }

    fn write_f32<W: ?Sized + io::Write>(&mut self, writer: &mut W, value: f32) -> io::Result<()> {
        writer.write_all(ftoa(value).as_str().as_bytes())
    }
}

/// A double as JSON text the way AimRT's protobuf writes it (C++ `SimpleDtoa`: `%.15g`,
/// or `%.17g` where 15 digits do not read back), for JSON written by hand that must match
/// AimRT's: `1` not `1.0`, `1e-09`, and a value that is not finite as the proto3 string,
/// quoted. Protobuf messages' `json` format writes every double this way.
///
/// ```
/// use aimrt_plugin_api::channel::json_double;
/// assert_eq!(json_double(2.0), "2");
/// assert_eq!(json_double(0.1 + 0.2), "0.30000000000000004");
/// assert_eq!(json_double(1e-9), "1e-09");
/// assert_eq!(json_double(f64::NAN), "\"NaN\"");
/// ```
pub fn json_double(v: f64) -> String {
    match non_finite(v) {
        Some(name) => format!("\"{name}\""),
        None => dtoa(v).as_str().to_owned(),
    }
}

/// The proto3 JSON name of a value that is not finite.
fn non_finite(v: f64) -> Option<&'static str> {
    if v.is_nan() {
        Some("NaN")
    } else if v == f64::INFINITY {
        Some("Infinity")
    } else if v == f64::NEG_INFINITY {
        Some("-Infinity")
    } else {
        None
    }
}

/// A serializer that writes a non-finite double or float as its proto3 string and hands
/// everything else to `S` unchanged (what it contains wrapped again, at every depth).
struct Floats<S>(S);

/// A value seen through [`Floats`].
struct Fix<'a, T: ?Sized>(&'a T);

impl<T: Serialize + ?Sized> Serialize for Fix<'_, T> {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        #[cfg(feature = "prost")]
        if is_timestamp::<T>() {
            return zulu(self.0, serializer);
        }
        self.0.serialize(Floats(serializer))
    }
}

/// Whether `T` is `google.protobuf.Timestamp` (pbjson-types'), or a reference to one (a
/// list's or a map's elements are serialized by reference). A type's name is the same for
/// the same type within one build, and names the crate that defines it, so no other type
/// matches.
#[cfg(feature = "prost")]
fn is_timestamp<T: ?Sized>() -> bool {
    let mut name = std::any::type_name::<T>();
    while let Some(rest) = name
        .strip_prefix('&')
        .map(|r| r.strip_prefix("mut ").unwrap_or(r))
    {
        name = rest;
    }
    name == std::any::type_name::<pbjson_types::Timestamp>()
}

/// A `Timestamp` as AimRT's protobuf writes it: UTC as `Z` (`2023-11-14T22:13:20.500Z`),
/// where pbjson-types writes `+00:00`. The fraction has 0, 3, 6 or 9 digits in both.
#[cfg(feature = "prost")]
fn zulu<T: Serialize + ?Sized, S: Serializer>(t: &T, serializer: S) -> Result<S::Ok, S::Error> {
    use serde::ser::Error as _;
    match serde_json::to_value(t).map_err(S::Error::custom)? {
        serde_json::Value::String(text) => match text.strip_suffix("+00:00") {
            Some(utc) => serializer.serialize_str(&format!("{utc}Z")),
            None => serializer.serialize_str(&text),
        },
        _ => t.serialize(Floats(serializer)),
    }
}

/// A compound of `S` whose elements are seen through [`Floats`].
struct Parts<C>(C);

macro_rules! forward {
    ($($name:ident($($arg:ident: $ty:ty),*);)*) => {
        $(fn $name(self, $($arg: $ty),*) -> Result<S::Ok, S::Error> {
            self.0.$name($($arg),*)
        })*
    };
}

impl<S: Serializer> Serializer for Floats<S> {
    type Ok = S::Ok;
    type Error = S::Error;
    type SerializeSeq = Parts<S::SerializeSeq>;
    type SerializeTuple = Parts<S::SerializeTuple>;
    type SerializeTupleStruct = Parts<S::SerializeTupleStruct>;
    type SerializeTupleVariant = Parts<S::SerializeTupleVariant>;
    type SerializeMap = Parts<S::SerializeMap>;
    type SerializeStruct = Parts<S::SerializeStruct>;
    type SerializeStructVariant = Parts<S::SerializeStructVariant>;

    fn serialize_f64(self, v: f64) -> Result<S::Ok, S::Error> {
        match non_finite(v) {
            Some(name) => self.0.serialize_str(name),
            None => self.0.serialize_f64(v),
        }
    }

    fn serialize_f32(self, v: f32) -> Result<S::Ok, S::Error> {
        match non_finite(f64::from(v)) {
            Some(name) => self.0.serialize_str(name),
            None => self.0.serialize_f32(v),
        }
    }

    forward! {
        serialize_bool(v: bool);
        serialize_i8(v: i8);
        serialize_i16(v: i16);
        serialize_i32(v: i32);
        serialize_i64(v: i64);
        serialize_i128(v: i128);
        serialize_u8(v: u8);
        serialize_u16(v: u16);
        serialize_u32(v: u32);
        serialize_u64(v: u64);
        serialize_u128(v: u128);
        serialize_char(v: char);
        serialize_str(v: &str);
        serialize_bytes(v: &[u8]);
        serialize_none();
        serialize_unit();
        serialize_unit_struct(name: &'static str);
        serialize_unit_variant(name: &'static str, index: u32, variant: &'static str);
    }

    fn serialize_some<T: Serialize + ?Sized>(self, value: &T) -> Result<S::Ok, S::Error> {
        self.0.serialize_some(&Fix(value))
    }

    fn serialize_newtype_struct<T: Serialize + ?Sized>(
        self,
        name: &'static str,
        value: &T,
    ) -> Result<S::Ok, S::Error> {
        self.0.serialize_newtype_struct(name, &Fix(value))
    }

    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        name: &'static str,
        index: u32,
        variant: &'static str,
        value: &T,
    ) -> Result<S::Ok, S::Error> {
        self.0
            .serialize_newtype_variant(name, index, variant, &Fix(value))
    }

    fn serialize_seq(self, len: Option<usize>) -> Result<Self::SerializeSeq, S::Error> {
        self.0.serialize_seq(len).map(Parts)
    }

    fn serialize_tuple(self, len: usize) -> Result<Self::SerializeTuple, S::Error> {
        self.0.serialize_tuple(len).map(Parts)
    }

    fn serialize_tuple_struct(
        self,
        name: &'static str,
        len: usize,
    ) -> Result<Self::SerializeTupleStruct, S::Error> {
        self.0.serialize_tuple_struct(name, len).map(Parts)
    }

    fn serialize_tuple_variant(
        self,
        name: &'static str,
        index: u32,
        variant: &'static str,
        len: usize,
    ) -> Result<Self::SerializeTupleVariant, S::Error> {
        self.0
            .serialize_tuple_variant(name, index, variant, len)
            .map(Parts)
    }

    fn serialize_map(self, len: Option<usize>) -> Result<Self::SerializeMap, S::Error> {
        self.0.serialize_map(len).map(Parts)
    }

    fn serialize_struct(
        self,
        name: &'static str,
        len: usize,
    ) -> Result<Self::SerializeStruct, S::Error> {
        self.0.serialize_struct(name, len).map(Parts)
    }

    fn serialize_struct_variant(
        self,
        name: &'static str,
        index: u32,
        variant: &'static str,
        len: usize,
    ) -> Result<Self::SerializeStructVariant, S::Error> {
        self.0
            .serialize_struct_variant(name, index, variant, len)
            .map(Parts)
    }

    fn is_human_readable(&self) -> bool {
        self.0.is_human_readable()
    }
}

macro_rules! parts {
    ($($trait:ident, $method:ident;)*) => {
        $(impl<C: $trait> $trait for Parts<C> {
            type Ok = C::Ok;
            type Error = C::Error;
            fn $method<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), C::Error> {
                self.0.$method(&Fix(value))
            }
            fn end(self) -> Result<C::Ok, C::Error> {
                self.0.end()
            }
        })*
    };
}

parts! {
    SerializeSeq, serialize_element;
    SerializeTuple, serialize_element;
    SerializeTupleStruct, serialize_field;
    SerializeTupleVariant, serialize_field;
}

impl<C: SerializeMap> SerializeMap for Parts<C> {
    type Ok = C::Ok;
    type Error = C::Error;
    fn serialize_key<T: Serialize + ?Sized>(&mut self, key: &T) -> Result<(), C::Error> {
        self.0.serialize_key(&Fix(key))
    }
    fn serialize_value<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), C::Error> {
        self.0.serialize_value(&Fix(value))
    }
    fn end(self) -> Result<C::Ok, C::Error> {
        self.0.end()
    }
}

macro_rules! keyed_parts {
    ($($trait:ident),*) => {
        $(impl<C: $trait> $trait for Parts<C> {
            type Ok = C::Ok;
            type Error = C::Error;
            fn serialize_field<T: Serialize + ?Sized>(
                &mut self,
                key: &'static str,
                value: &T,
            ) -> Result<(), C::Error> {
                self.0.serialize_field(key, &Fix(value))
            }
            fn skip_field(&mut self, key: &'static str) -> Result<(), C::Error> {
                self.0.skip_field(key)
            }
            fn end(self) -> Result<C::Ok, C::Error> {
                self.0.end()
            }
        })*
    };
}

keyed_parts!(SerializeStruct, SerializeStructVariant);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn doubles_print_as_protobufs_simple_dtoa() {
        // What C's printf("%.15g") / ("%.17g") gives, as protobuf's C++ prints them.
        for (v, c) in [
            (1.0, "1"),
            (0.0, "0"),
            (-0.0, "-0"),
            (0.5, "0.5"),
            (-2.25, "-2.25"),
            (123456789.0, "123456789"),
            (1e15, "1e+15"),
            (123456789012345.0, "123456789012345"),
            (1e20, "1e+20"),
            (1e-9, "1e-09"),
            (1.5e-7, "1.5e-07"),
            (1e-5, "1e-05"),
            (0.0001, "0.0001"),
            (1e100, "1e+100"),
            (0.1, "0.1"),
            (0.1 + 0.2, "0.30000000000000004"),
            (std::f64::consts::PI, "3.1415926535897931"),
            (f64::MAX, "1.7976931348623157e+308"),
            (f64::MIN_POSITIVE, "2.2250738585072014e-308"),
            // 15 digits read back as the smallest subnormal.
            (5e-324, "4.94065645841247e-324"),
            // A tie at the 17th digit (…23.25): printf rounds half to even.
            (1_690_060_720_831_323.0 + 0.25, "1690060720831323.2"),
        ] {
            assert_eq!(dtoa(v).as_str(), c, "{v:?}");
            assert_eq!(c.parse::<f64>(), Ok(v), "{c} reads back");
        }
    }

    #[test]
    fn floats_print_as_protobufs_simple_ftoa() {
        for (v, c) in [
            (1.0f32, "1"),
            (0.1, "0.1"),
            (1.0 / 3.0, "0.333333343"),
            (1e-9, "1e-09"),
            (16777216.0, "16777216"),
            // The smallest subnormal: 6 digits read back.
            (f32::from_bits(1), "1.4013e-45"),
            (3.0e38, "3e+38"),
        ] {
            assert_eq!(ftoa(v).as_str(), c, "{v:?}");
            assert_eq!(c.parse::<f32>(), Ok(v), "{c} reads back");
        }
    }

    /// C's `%.<p>g` the plain way: exact rounding to `p` digits, always.
    fn reference_g(exact: String, p: i32) -> String {
        let mut t = Text::new();
        t.push(exact.as_bytes());
        Decimal::of(&t).c_g(p).as_str().to_owned()
    }

    /// The fast paths of [`simple_toa`] against the plain `%.15g`-then-`%.17g` (and
    /// `%.6g`-then-`%.9g`) over a million bit patterns: every exponent, subnormals
    /// included, and values with 15, 16 and 17 shortest digits.
    #[test]
    fn the_shortcuts_give_what_printf_gives_for_any_bit_pattern() {
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..500_000 {
            let v = f64::from_bits(next());
            if v.is_finite() {
                let short = reference_g(format!("{v:.14e}"), 15);
                let want = if short.parse::<f64>() == Ok(v) {
                    short
                } else {
                    reference_g(format!("{v:.16e}"), 17)
                };
                assert_eq!(dtoa(v).as_str(), want, "{v:e}");
            }
            let f = f32::from_bits(next() as u32);
            if f.is_finite() {
                let short = reference_g(format!("{f:.5e}"), 6);
                let want = if short.parse::<f32>() == Ok(f) {
                    short
                } else {
                    reference_g(format!("{f:.8e}"), 9)
                };
                assert_eq!(ftoa(f).as_str(), want, "{f:e}");
            }
        }
    }

    #[derive(serde::Serialize)]
    struct Sample {
        x: f64,
        y: f32,
        list: Vec<f64>,
        nested: Option<Box<Sample>>,
        map: std::collections::BTreeMap<String, f64>,
        text: String,
    }

    #[cfg(feature = "prost")]
    #[test]
    fn timestamps_end_in_z_at_every_depth_and_strings_are_left_alone() {
        use std::collections::BTreeMap;
        let t = pbjson_types::Timestamp {
            seconds: 1,
            nanos: 500_000_000,
        };
        let text = "1970-01-01T00:00:01.500+00:00".to_owned();
        let mut by_name = BTreeMap::new();
        by_name.insert("a", t);
        let json = to_vec(&(Some(t), vec![t], by_name, text)).expect("json");
        assert_eq!(
            String::from_utf8(json).expect("utf-8"),
            r#"["1970-01-01T00:00:01.500Z",["1970-01-01T00:00:01.500Z"],{"a":"1970-01-01T00:00:01.500Z"},"1970-01-01T00:00:01.500+00:00"]"#
        );
    }

    #[test]
    fn values_that_are_not_finite_are_protos_strings_at_every_depth() {
        let inner = Sample {
            x: f64::NEG_INFINITY,
            y: f32::NAN,
            list: vec![],
            nested: None,
            map: [("k".to_owned(), f64::INFINITY)].into(),
            text: "NaN".into(),
        };
        let outer = Sample {
            x: f64::NAN,
            y: 1.5,
            list: vec![1.0, f64::INFINITY, -0.5],
            nested: Some(Box::new(inner)),
            map: Default::default(),
            text: String::new(),
        };
        let json = String::from_utf8(to_vec(&outer).expect("json")).expect("utf-8");
        assert_eq!(
            json,
            r#"{"x":"NaN","y":1.5,"list":[1,"Infinity",-0.5],"nested":{"x":"-Infinity","y":"NaN","list":[],"nested":null,"map":{"k":"Infinity"},"text":"NaN"},"map":{},"text":""}"#
        );
    }
}
