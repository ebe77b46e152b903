//! Colour maps, opacity maps and interpolation, parsed by hand from TOML values so every
//! error names the exact key (`objects[3].opacity.bounds`) and what was expected.

use toml::Value;

use crate::interp::Interpolation;
use crate::mapping::{ColourMap, Lut, OpacityMap, Polynomial, Ramp, RawColour};

/// Largest number of coefficients in a general polynomial map.
pub const MAX_POLYNOMIAL_TERMS: usize = 32;
/// Largest number of LUT domains or ramp points.
pub const MAX_TABLE_ENTRIES: usize = 65_536;

/// An error at a key path, completed with the file name by the caller.
pub(super) type KeyError = (String, String);

fn err<T>(key: &str, msg: impl Into<String>) -> Result<T, KeyError> {
    Err((key.to_string(), msg.into()))
}

/// A table's keys: `type` plus exactly the `allowed` ones.
fn table<'a>(v: &'a Value, key: &str, allowed: &[&str]) -> Result<&'a toml::Table, KeyError> {
    let Some(t) = v.as_table() else {
        return err(key, format!("expected a table such as {{ type = \"lut\", ... }}, got {}", v.type_str()));
    };
    for k in t.keys() {
        if k != "type" && !allowed.contains(&k.as_str()) {
            let expected = if allowed.is_empty() { "no other keys".to_string() } else { allowed.join(", ") };
            return err(&format!("{key}.{k}"), format!("unknown key for this type; expected {expected}"));
        }
    }
    for k in allowed {
        if !t.contains_key(*k) {
            return err(&format!("{key}.{k}"), "missing; this type requires it");
        }
    }
    Ok(t)
}

fn type_of<'a>(v: &'a Value, key: &str, expected: &str) -> Result<&'a str, KeyError> {
    if !v.is_table() {
        return err(key, format!("expected a table such as {{ type = \"lut\", ... }}, got {}", v.type_str()));
    }
    match v.get("type") {
        Some(Value::String(s)) => Ok(s),
        Some(other) => err(&format!("{key}.type"), format!("expected a string ({expected}), got {}", other.type_str())),
        None => err(&format!("{key}.type"), format!("missing; expected one of {expected}")),
    }
}

fn number(v: &Value, key: &str) -> Result<f64, KeyError> {
    let x = match v {
        Value::Float(f) => *f,
        Value::Integer(i) => *i as f64,
        other => return err(key, format!("expected a number, got {}", other.type_str())),
    };
    if !x.is_finite() {
        return err(key, format!("expected a finite number, got {x}"));
    }
    Ok(x)
}

fn numbers(v: &Value, key: &str) -> Result<Vec<f64>, KeyError> {
    let Some(a) = v.as_array() else {
        return err(key, format!("expected an array of numbers, got {}", v.type_str()));
    };
    a.iter().enumerate().map(|(i, x)| number(x, &format!("{key}[{i}]"))).collect()
}

fn tuples<const N: usize>(v: &Value, key: &str) -> Result<Vec<[f64; N]>, KeyError> {
    let Some(a) = v.as_array() else {
        return err(key, format!("expected an array of {N}-number arrays, got {}", v.type_str()));
    };
    a.iter()
        .enumerate()
        .map(|(i, x)| {
            let k = format!("{key}[{i}]");
            let xs = numbers(x, &k)?;
            xs.try_into().or_else(|xs: Vec<f64>| err(&k, format!("expected {N} numbers, got {}", xs.len())))
        })
        .collect()
}

fn bounds(t: &toml::Table, key: &str, entries: usize, entries_key: &str) -> Result<Vec<f64>, KeyError> {
    let key_b = format!("{key}.bounds");
    let b = numbers(&t["bounds"], &key_b)?;
    if b.len() >= MAX_TABLE_ENTRIES {
        return err(&key_b, format!("expected fewer than {MAX_TABLE_ENTRIES} bounds"));
    }
    if let Some(i) = (1..b.len()).find(|&i| b[i] <= b[i - 1]) {
        return err(&key_b, format!("bounds must be strictly increasing, but [{}] = {} follows {}", i, b[i], b[i - 1]));
    }
    if entries != b.len() + 1 {
        return err(
            &format!("{key}.{entries_key}"),
            format!("expected {} entries (one more than the {} bounds), got {entries}", b.len() + 1, b.len()),
        );
    }
    Ok(b)
}

fn coefficients(t: &toml::Table, key: &str, name: &str, ty: &str) -> Result<Polynomial, KeyError> {
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
        Some(n) if c.len() != n => {
            let s = if n == 1 { "" } else { "s" };
            err(&k, format!("a {ty} map takes exactly {n} coefficient{s}, got {}", c.len()))
        }
        None if c.is_empty() || c.len() > MAX_POLYNOMIAL_TERMS => {
            err(&k, format!("expected 1 to {MAX_POLYNOMIAL_TERMS} coefficients (ascending powers), got {}", c.len()))
        }
        _ => Ok(Polynomial(c)),
    }
}

fn ramp_points<const N: usize>(t: &toml::Table, key: &str) -> Result<Vec<(f64, [f64; N])>, KeyError> {
    let k = format!("{key}.points");
    let Some(a) = t["points"].as_array() else {
        return err(&k, format!("expected an array of [value, ...] points, got {}", t["points"].type_str()));
    };
    if a.is_empty() || a.len() > MAX_TABLE_ENTRIES {
        return err(&k, format!("expected 1 to {MAX_TABLE_ENTRIES} points"));
    }
    let mut pts = Vec::with_capacity(a.len());
    for (i, p) in a.iter().enumerate() {
        let ki = format!("{k}[{i}]");
        let xs = numbers(p, &ki)?;
        if xs.len() != N + 1 {
            let shape = if N == 1 { "[value, opacity]" } else { "[value, r, g, b]" };
            return err(&ki, format!("expected {} numbers {shape}, got {}", N + 1, xs.len()));
        }
        if let Some(&(prev, _)) = pts.last() {
            if xs[0] < prev {
                return err(&ki, format!("points must be ordered by value, but {} follows {prev}", xs[0]));
            }
        }
        pts.push((xs[0], std::array::from_fn(|c| xs[c + 1])));
    }
    Ok(pts)
}

const POLY_TYPES: [&str; 5] = ["polynomial", "constant", "linear", "quadratic", "cubic"];
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
                err(key, "a raw colour map needs the dataset to have red, green and blue channels, or grey, or bit")
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
        t if POLY_TYPES.contains(&t) => {
            let tab = table(v, key, &["red", "green", "blue"])?;
            Ok(ColourMap::Polynomial([
                coefficients(tab, key, "red", t)?,
                coefficients(tab, key, "green", t)?,
                coefficients(tab, key, "blue", t)?,
            ]))
        }
        other => {
            err(&format!("{key}.type"), format!("unknown colour map type \"{other}\"; expected one of {COLOUR_TYPES}"))
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
                return err(key, "a raw opacity map needs the dataset to have an alpha channel");
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
        t if POLY_TYPES.contains(&t) => {
            let tab = table(v, key, &["coefficients"])?;
            Ok(OpacityMap::Polynomial(coefficients(tab, key, "coefficients", t)?))
        }
        other => {
            err(&format!("{key}.type"), format!("unknown opacity map type \"{other}\"; expected one of {COLOUR_TYPES}"))
        }
    }
}

/// `"nearest"`, `"trilinear"`, `"cubic"`, or `{ type = "nonlinear", omega = [w0, w1, w2] }`.
pub(super) fn interpolation(v: &Value, key: &str) -> Result<Interpolation, KeyError> {
    const EXPECTED: &str = "\"nearest\", \"trilinear\", \"cubic\" or { type = \"nonlinear\", omega = [w0, w1, w2] }";
    let name = match v {
        Value::String(s) => s.as_str(),
        Value::Table(_) => type_of(v, key, EXPECTED)?,
        other => return err(key, format!("expected {EXPECTED}, got {}", other.type_str())),
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
            let k = format!("{key}.omega");
            let w = numbers(&t["omega"], &k)?;
            let omega: [f64; 3] = w
                .try_into()
                .or_else(|w: Vec<f64>| err(&k, format!("expected 3 numbers [w0, w1, w2], got {}", w.len())))?;
            Ok(Interpolation::Nonlinear { omega })
        }
        "nonlinear" => {
            err(key, "nonlinear interpolation needs its coefficients: { type = \"nonlinear\", omega = [w0, w1, w2] }")
        }
        other => err(key, format!("unknown interpolation \"{other}\"; expected {EXPECTED}")),
    }
}
