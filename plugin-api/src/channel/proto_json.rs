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
//! The non-finite values are caught by [`Floats`], a serializer that hands everything else
//! on unchanged; the finite ones reach serde_json's writer through [`CFormatter`].

use std::io;

use serde::ser::{
    Serialize, SerializeMap, SerializeSeq, SerializeStruct, SerializeStructVariant, SerializeTuple,
    SerializeTupleStruct, SerializeTupleVariant, Serializer,
};

/// `msg` as JSON, its doubles and floats as AimRT's protobuf writes them.
pub(crate) fn to_vec<T: Serialize + ?Sized>(msg: &T) -> serde_json::Result<Vec<u8>> {
    let mut out = Vec::with_capacity(128);
    let mut ser = serde_json::Serializer::with_formatter(&mut out, CFormatter);
    msg.serialize(Floats(&mut ser))?;
    Ok(out)
}

/// C's `%.<p>g` of `v` (finite): `p` significant digits, trailing zeros dropped, in
/// exponent form (`e-09`, `e+20`: a sign and two digits at least) when the exponent is
/// below -4 or not below `p`. Rust's `{:.ne}` and `{:.n}` round the exact value
/// correctly, as glibc's printf does (a float is widened to a double exactly, as printf's
/// arguments are).
fn c_g(v: f64, p: usize) -> String {
    let sci = format!("{v:.*e}", p - 1);
    let (mantissa, exp) = sci.split_once('e').unwrap_or((&sci, "0"));
    let x: i32 = exp.parse().unwrap_or(0);
    if x < -4 || x >= p as i32 {
        let sign = if x < 0 { '-' } else { '+' };
        format!("{}e{sign}{:02}", trim_zeros(mantissa), x.unsigned_abs())
    } else {
        let decimals = usize::try_from(p as i32 - 1 - x).unwrap_or(0);
        trim_zeros(&format!("{v:.decimals$}")).to_owned()
    }
}

/// `1.500` → `1.5`, `2.000` → `2`, `100` → `100`.
fn trim_zeros(s: &str) -> &str {
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.')
    } else {
        s
    }
}

/// protobuf's `SimpleDtoa` (finite `v`).
fn dtoa(v: f64) -> String {
    let short = c_g(v, 15);
    if short.parse::<f64>() == Ok(v) {
        return short;
    }
    c_g(v, 17)
}

/// protobuf's `SimpleFtoa` (finite `v`).
fn ftoa(v: f32) -> String {
    let short = c_g(f64::from(v), 6);
    if short.parse::<f32>() == Ok(v) {
        return short;
    }
    c_g(f64::from(v), 9)
}

/// serde_json's compact layout, with finite doubles and floats as [`dtoa`] / [`ftoa`].
struct CFormatter;

impl serde_json::ser::Formatter for CFormatter {
    fn write_f64<W: ?Sized + io::Write>(&mut self, writer: &mut W, value: f64) -> io::Result<()> {
        writer.write_all(dtoa(value).as_bytes())
    }

    fn write_f32<W: ?Sized + io::Write>(&mut self, writer: &mut W, value: f32) -> io::Result<()> {
        writer.write_all(ftoa(value).as_bytes())
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
        self.0.serialize(Floats(serializer))
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
        ] {
            assert_eq!(dtoa(v), c, "{v:?}");
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
            (3.0e38, "3e+38"),
        ] {
            assert_eq!(ftoa(v), c, "{v:?}");
            assert_eq!(c.parse::<f32>(), Ok(v), "{c} reads back");
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
