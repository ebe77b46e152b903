//! Colour maps, opacity maps and interpolation, parsed by hand from TOML values so every
//! error names the exact key (`objects[3].opacity.bounds`) and what was expected.

use toml::Value;

use super::error::SceneErrorKind as Kind;
use super::limits::{INTERPOLATIONS, MAX_POLYNOMIAL_TERMS, MAX_TABLE_ENTRIES};
use crate::interp::Interpolation;
use crate::mapping::{ColourMap, Lut, OpacityMap, Polynomial, Ramp, RawColour};

/// A refusal at a key path, completed with the file name by the caller (`load::scene`).
#[derive(Debug)]
pub(super) struct KeyError {
    /// TOML path of the offending key.
    pub key: String,
    /// What was wrong.
    pub kind: Kind,
}

impl KeyError {
    pub(super) fn new(key: impl Into<String>, kind: Kind) -> KeyError {
        KeyError { key: key.into(), kind }
    }
}

fn err<T>(key: &str, kind: Kind) -> Result<T, KeyError> {
    Err(KeyError::new(key, kind))
}

/// `what` was expected at `key`, and `v` was found (its TOML type).
fn wrong_type<T>(key: &str, expected: impl Into<String>, v: &Value) -> Result<T, KeyError> {
    err(key, Kind::WrongType { expected: expected.into(), got: v.type_str().to_string() })
}

/// A table's keys: `type` plus exactly the `allowed` ones.
fn table<'a>(v: &'a Value, key: &str, allowed: &'static [&'static str]) -> Result<&'a toml::Table, KeyError> {
    let Some(t) = v.as_table() else {
        return err(key, Kind::NotAMap { got: v.type_str() });
    };
    for k in t.keys() {
        if k != "type" && !allowed.contains(&k.as_str()) {
            return err(&format!("{key}.{k}"), Kind::UnknownMapKey { allowed });
        }
    }
    for k in allowed {
        if !t.contains_key(*k) {
            return err(&format!("{key}.{k}"), Kind::MissingMapKey);
        }
    }
    Ok(t)
}

fn type_of<'a>(v: &'a Value, key: &str, expected: &'static str) -> Result<&'a str, KeyError> {
    if !v.is_table() {
        return err(key, Kind::NotAMap { got: v.type_str() });
    }
    match v.get("type") {
        Some(Value::String(s)) => Ok(s),
        Some(other) => wrong_type(&format!("{key}.type"), format!("a string ({expected})"), other),
        None => err(&format!("{key}.type"), Kind::MissingMapType { expected }),
    }
}

fn number(v: &Value, key: &str) -> Result<f64, KeyError> {
    let x = match v {
        Value::Float(f) => *f,
        Value::Integer(i) => *i as f64,
        other => return wrong_type(key, "a number", other),
    };
    if !x.is_finite() {
        return err(key, Kind::NotFinite { got: x });
    }
    Ok(x)
}

fn numbers(v: &Value, key: &str) -> Result<Vec<f64>, KeyError> {
    let Some(a) = v.as_array() else {
        return wrong_type(key, "an array of numbers", v);
    };
    a.iter().enumerate().map(|(i, x)| number(x, &format!("{key}[{i}]"))).collect()
}

/// Exactly `N` numbers at `key`; `layout` says what they mean, for the message.
fn exactly<const N: usize>(v: &Value, key: &str, layout: Option<&'static str>) -> Result<[f64; N], KeyError> {
    let xs = numbers(v, key)?;
    let got = xs.len();
    xs.try_into().or_else(|_| err(key, Kind::NumberCount { expected: N, layout, got }))
}

fn tuples<const N: usize>(v: &Value, key: &str) -> Result<Vec<[f64; N]>, KeyError> {
    let Some(a) = v.as_array() else {
        return wrong_type(key, format!("an array of {N}-number arrays"), v);
    };
    a.iter().enumerate().map(|(i, x)| exactly::<N>(x, &format!("{key}[{i}]"), None)).collect()
}

fn bounds(t: &toml::Table, key: &str, entries: usize, entries_key: &str) -> Result<Vec<f64>, KeyError> {
    let key_b = format!("{key}.bounds");
    let b = numbers(&t["bounds"], &key_b)?;
    if b.len() >= MAX_TABLE_ENTRIES {
        return err(&key_b, Kind::TooManyBounds { got: b.len() });
    }
    if let Some(i) = (1..b.len()).find(|&i| b[i] <= b[i - 1]) {
        return err(&key_b, Kind::BoundsNotIncreasing { index: i, value: b[i], previous: b[i - 1] });
    }
    if entries != b.len() + 1 {
        return err(&format!("{key}.{entries_key}"), Kind::LutEntries { bounds: b.len(), got: entries });
    }
    Ok(b)
}

fn coefficients(t: &toml::Table, key: &str, name: &str, ty: &'static str) -> Result<Polynomial, KeyError> {
    let k = format!("{key}.{name}");
    let c = numbers(&t[name], &k)?;
    let want = match ty {
        "constant" => Some(1),
        "linear" => Some(2),
        "quadratic" => Some(3),
        "cubic" => Some(4),
        _ => None,
    };
    match want {
        Some(n) if c.len() != n => err(&k, Kind::CoefficientCount { ty, expected: n, got: c.len() }),
        None if c.is_empty() || c.len() > MAX_POLYNOMIAL_TERMS => err(&k, Kind::PolynomialTerms { got: c.len() }),
        _ => Ok(Polynomial(c)),
    }
}

fn ramp_points<const N: usize>(t: &toml::Table, key: &str) -> Result<Vec<(f64, [f64; N])>, KeyError> {
    let k = format!("{key}.points");
    let Some(a) = t["points"].as_array() else {
        return wrong_type(&k, "an array of [value, ...] points", &t["points"]);
    };
    if a.is_empty() || a.len() > MAX_TABLE_ENTRIES {
        return err(&k, Kind::RampPointCount { got: a.len() });
    }
    let mut pts = Vec::with_capacity(a.len());
    for (i, p) in a.iter().enumerate() {
        let ki = format!("{k}[{i}]");
        let xs = numbers(p, &ki)?;
        if xs.len() != N + 1 {
            let layout = if N == 1 { "[value, opacity]" } else { "[value, r, g, b]" };
            return err(&ki, Kind::NumberCount { expected: N + 1, layout: Some(layout), got: xs.len() });
        }
        if let Some(&(previous, _)) = pts.last() {
            if xs[0] < previous {
                return err(&ki, Kind::RampNotOrdered { value: xs[0], previous });
            }
        }
        pts.push((xs[0], std::array::from_fn(|c| xs[c + 1])));
    }
    Ok(pts)
}

const POLY_TYPES: [&str; 5] = ["polynomial", "constant", "linear", "quadratic", "cubic"];

/// The polynomial type named `t`, as a `'static` string for messages.
fn poly_type(t: &str) -> Option<&'static str> {
    POLY_TYPES.into_iter().find(|p| *p == t)
}
const COLOUR_TYPES: &str = "raw, lut, polynomial, constant, linear, quadratic, cubic, ramp";

/// A colour map; `raw` picks its channels from what the dataset `has`.
pub(super) fn colour(v: &Value, key: &str, has: impl Fn(&str) -> bool) -> Result<ColourMap, KeyError> {
    let ty = type_of(v, key, COLOUR_TYPES)?;
    match ty {
        "raw" => {
            table(v, key, &[])?;
            if has("red") && has("green") && has("blue") {
                Ok(ColourMap::Raw(RawColour::Rgb))
            } else if has("grey") {
                Ok(ColourMap::Raw(RawColour::Grey))
            } else if has("bit") {
                Ok(ColourMap::Raw(RawColour::Bit))
            } else {
                err(key, Kind::RawColourChannels)
            }
        }
        "lut" => {
            let t = table(v, key, &["bounds", "colours"])?;
            let colours = tuples::<3>(&t["colours"], &format!("{key}.colours"))?;
            let b = bounds(t, key, colours.len(), "colours")?;
            Ok(ColourMap::Lut(Lut::new(b, colours)))
        }
        "ramp" => {
            let t = table(v, key, &["points"])?;
            Ok(ColourMap::Ramp(Ramp::new(ramp_points::<3>(t, key)?)))
        }
        other => {
            let Some(t) = poly_type(other) else {
                let got = other.to_string();
                return err(
                    &format!("{key}.type"),
                    Kind::UnknownMapType { map: "colour", got, expected: COLOUR_TYPES },
                );
            };
            let tab = table(v, key, &["red", "green", "blue"])?;
            Ok(ColourMap::Polynomial([
                coefficients(tab, key, "red", t)?,
                coefficients(tab, key, "green", t)?,
                coefficients(tab, key, "blue", t)?,
            ]))
        }
    }
}

/// An opacity map; `raw` needs the dataset's alpha channel.
pub(super) fn opacity(v: &Value, key: &str, has: impl Fn(&str) -> bool) -> Result<OpacityMap, KeyError> {
    let ty = type_of(v, key, COLOUR_TYPES)?;
    match ty {
        "raw" => {
            table(v, key, &[])?;
            if !has("alpha") {
                return err(key, Kind::RawOpacityAlpha);
            }
            Ok(OpacityMap::Raw)
        }
        "lut" => {
            let t = table(v, key, &["bounds", "values"])?;
            let values = numbers(&t["values"], &format!("{key}.values"))?;
            let b = bounds(t, key, values.len(), "values")?;
            Ok(OpacityMap::Lut(Lut::new(b, values)))
        }
        "ramp" => {
            let t = table(v, key, &["points"])?;
            Ok(OpacityMap::Ramp(Ramp::new(ramp_points::<1>(t, key)?)))
        }
        other => {
            let Some(t) = poly_type(other) else {
                let got = other.to_string();
                return err(
                    &format!("{key}.type"),
                    Kind::UnknownMapType { map: "opacity", got, expected: COLOUR_TYPES },
                );
            };
            let tab = table(v, key, &["coefficients"])?;
            Ok(OpacityMap::Polynomial(coefficients(tab, key, "coefficients", t)?))
        }
    }
}

/// `"nearest"`, `"trilinear"`, `"cubic"`, or `{ type = "nonlinear", omega = [w0, w1, w2] }`.
pub(super) fn interpolation(v: &Value, key: &str) -> Result<Interpolation, KeyError> {
    let name = match v {
        Value::String(s) => s.as_str(),
        Value::Table(_) => type_of(v, key, INTERPOLATIONS)?,
        other => return wrong_type(key, INTERPOLATIONS, other),
    };
    let simple = |i| {
        if v.is_table() {
            table(v, key, &[])?;
        }
        Ok(i)
    };
    match name {
        "nearest" => simple(Interpolation::Nearest),
        "trilinear" => simple(Interpolation::Trilinear),
        "cubic" => simple(Interpolation::Cubic),
        "nonlinear" if v.is_table() => {
            let t = table(v, key, &["omega"])?;
            let omega = exactly::<3>(&t["omega"], &format!("{key}.omega"), Some("[w0, w1, w2]"))?;
            Ok(Interpolation::Nonlinear { omega })
        }
        "nonlinear" => err(key, Kind::NonlinearNeedsOmega),
        other => err(key, Kind::UnknownInterpolation { got: other.to_string() }),
    }
}
