//! Mutations shared by the targets: byte-level (flips, cuts, splices, random bytes) and
//! structure-aware (replace, delete, retype or rename a node of a JSON or TOML tree, with values
//! chosen to hit limits: huge and negative numbers, NaN-like text, long strings, deep nesting).

use super::Rng;
use serde_json::{json, Map, Value};

/// Tokens that mean something to the parsers; spliced into text and used as keys.
pub const TOKENS: &[&str] = &[
    "{",
    "}",
    "[",
    "]",
    "\"",
    ":",
    ",",
    "=",
    "\n",
    "[[",
    "]]",
    ".",
    "-1",
    "0",
    "1e309",
    "18446744073709551616",
    "-9223372036854775809",
    "nan",
    "inf",
    "true",
    "null",
    "\\u0000",
    "\\ud800",
    "```",
    "```json",
    "\u{1F600}",
    "\u{0}",
    "é",
    "#",
    "'''",
    "\"\"\"",
];

/// Numbers at the edges of every integer and float type the readers use.
pub fn edge_number(r: &mut Rng) -> Value {
    match r.below(12) {
        0 => json!(-1),
        1 => json!(u64::MAX),
        2 => json!(i64::MIN),
        3 => json!(1e300),
        4 => json!(-0.5),
        5 => json!(u32::MAX as u64 + 1),
        6 => json!(1u64 << 40),
        7 => json!(0),
        8 => json!(usize::MAX / 4 + 1),
        9 => json!(f64::MIN_POSITIVE),
        _ => json!(r.below(64)),
    }
}

pub fn random_string(r: &mut Rng) -> String {
    match r.below(8) {
        0 => String::new(),
        1 => "x".repeat(1 + r.index(100_000)),
        2 => r.pick(TOKENS).repeat(1 + r.index(2000)),
        _ => (0..r.index(12)).map(|_| *r.pick(TOKENS)).collect(),
    }
}

/// A random JSON value of at most `depth` levels.
pub fn random_json(r: &mut Rng, depth: usize, keys: &[&str]) -> Value {
    let leaf = depth == 0 || r.chance(0.4);
    match if leaf { r.below(4) } else { 4 + r.below(2) } {
        0 => Value::Null,
        1 => Value::Bool(r.chance(0.5)),
        2 => edge_number(r),
        3 => Value::String(if r.chance(0.5) && !keys.is_empty() { r.pick(keys).to_string() } else { random_string(r) }),
        4 => Value::Array((0..r.below(5)).map(|_| random_json(r, depth - 1, keys)).collect()),
        _ => {
            let mut m = Map::new();
            for _ in 0..r.below(5) {
                let k = if keys.is_empty() { random_string(r) } else { r.pick(keys).to_string() };
                m.insert(k, random_json(r, depth - 1, keys));
            }
            Value::Object(m)
        }
    }
}

/// Change one node of a JSON tree.
pub fn mutate_json(r: &mut Rng, v: &mut Value, keys: &[&str]) {
    match v {
        Value::Object(m) if !m.is_empty() && r.chance(0.8) => {
            let names: Vec<String> = m.keys().cloned().collect();
            let key = r.pick(&names).clone();
            match r.below(6) {
                0 => {
                    m.remove(&key);
                }
                1 => *m.get_mut(&key).unwrap() = random_json(r, 3, keys),
                2 => {
                    let val = m.remove(&key).unwrap();
                    let new = if keys.is_empty() { random_string(r) } else { r.pick(keys).to_string() };
                    m.insert(new, val);
                }
                _ => mutate_json(r, m.get_mut(&key).unwrap(), keys),
            }
        }
        Value::Array(a) if !a.is_empty() && r.chance(0.8) => {
            let i = r.index(a.len());
            match r.below(5) {
                0 => {
                    a.remove(i);
                }
                1 => {
                    // Long arrays of leaves; containers only a few times (repeated edits of
                    // nested containers would grow the input exponentially).
                    let x = a[i].clone();
                    let n = if x.is_array() || x.is_object() { 1 + r.index(3) } else { 1 + r.index(100) };
                    a.extend(std::iter::repeat_n(x, n));
                }
                2 => a.push(random_json(r, 2, keys)),
                _ => mutate_json(r, &mut a[i], keys),
            }
        }
        Value::Number(_) => *v = edge_number(r),
        Value::String(_) if r.chance(0.5) => *v = Value::String(random_string(r)),
        _ => *v = random_json(r, 3, keys),
    }
}

/// Deep nesting (arrays or objects) around a value: recursion limits.
pub fn nest_json(r: &mut Rng, inner: Value) -> Value {
    let max = if r.chance(0.2) { 1500 } else { 40 };
    let depth = 1 + r.index(max);
    let mut v = inner;
    for _ in 0..depth {
        v = if r.chance(0.5) { json!([v]) } else { json!({ "neg": v }) };
    }
    v
}

fn random_toml(r: &mut Rng, depth: usize, keys: &[&str]) -> toml::Value {
    let leaf = depth == 0 || r.chance(0.5);
    match if leaf { r.below(5) } else { 5 + r.below(2) } {
        0 => toml::Value::Boolean(r.chance(0.5)),
        1 => toml::Value::Integer(*r.pick(&[-1, 0, 1, i64::MAX, i64::MIN, 1 << 40, u32::MAX as i64 + 1, 3, 64])),
        2 => toml::Value::Float(*r.pick(&[f64::NAN, f64::INFINITY, -0.0, 1e300, -1.5, 0.125])),
        3 => toml::Value::String(if r.chance(0.5) && !keys.is_empty() { r.pick(keys).to_string() } else { random_string(r) }),
        4 => toml::Value::String(r.pick(keys).to_string()),
        5 => toml::Value::Array((0..r.below(5)).map(|_| random_toml(r, depth - 1, keys)).collect()),
        _ => {
            let mut t = toml::Table::new();
            for _ in 0..r.below(4) {
                t.insert(r.pick(keys).to_string(), random_toml(r, depth - 1, keys));
            }
            toml::Value::Table(t)
        }
    }
}

/// Change one node of a TOML tree.
pub fn mutate_toml(r: &mut Rng, v: &mut toml::Value, keys: &[&str]) {
    match v {
        toml::Value::Table(t) if !t.is_empty() && r.chance(0.85) => {
            let names: Vec<String> = t.keys().cloned().collect();
            let key = r.pick(&names).clone();
            match r.below(6) {
                0 => {
                    t.remove(&key);
                }
                1 => *t.get_mut(&key).unwrap() = random_toml(r, 2, keys),
                2 => {
                    let val = t.remove(&key).unwrap();
                    t.insert(r.pick(keys).to_string(), val);
                }
                _ => mutate_toml(r, t.get_mut(&key).unwrap(), keys),
            }
        }
        toml::Value::Array(a) if !a.is_empty() && r.chance(0.8) => {
            let i = r.index(a.len());
            match r.below(5) {
                0 => {
                    a.remove(i);
                }
                1 => {
                    let x = a[i].clone();
                    a.extend(std::iter::repeat_n(x, 1 + r.index(100)));
                }
                _ => mutate_toml(r, &mut a[i], keys),
            }
        }
        toml::Value::Integer(_) | toml::Value::Float(_) => *v = random_toml(r, 0, keys),
        _ => *v = random_toml(r, 2, keys),
    }
}

/// Byte-level damage: bit flips, truncation, splices of tokens, overwrites, random bytes.
pub fn mutate_bytes(r: &mut Rng, b: &mut Vec<u8>) -> &'static str {
    if b.is_empty() {
        b.extend((0..r.index(64)).map(|_| r.next() as u8));
        return "random bytes";
    }
    match r.below(8) {
        0 => {
            for _ in 0..1 + r.index(8) {
                let i = r.index(b.len());
                b[i] ^= 1 << r.below(8);
            }
            "bit flips"
        }
        1 => {
            b.truncate(r.index(b.len()));
            "truncated"
        }
        2 => {
            let i = r.index(b.len() + 1);
            let t = r.pick(TOKENS).as_bytes().to_vec();
            b.splice(i..i, t);
            "token spliced in"
        }
        3 => {
            let i = r.index(b.len());
            let n = (1 + r.index(16)).min(b.len() - i);
            for x in &mut b[i..i + n] {
                *x = r.next() as u8;
            }
            "bytes overwritten"
        }
        4 => {
            let (i, j) = (r.index(b.len()), r.index(b.len()));
            let (a, z) = (i.min(j), i.max(j));
            let chunk = b[a..z].to_vec();
            let at = r.index(b.len() + 1);
            b.splice(at..at, chunk);
            "chunk duplicated"
        }
        5 => {
            let i = r.index(b.len());
            let n = r.index(b.len() - i + 1);
            b.drain(i..i + n);
            "chunk deleted"
        }
        6 => {
            *b = (0..r.index(512)).map(|_| r.next() as u8).collect();
            "random bytes"
        }
        _ => {
            let i = r.index(b.len());
            b[i] = *r.pick(&[0u8, 0xff, b'\n', b'"', b'{', b'[', 0x80, 0xc0]);
            "special byte"
        }
    }
}

/// Overwrite a little-endian integer field at `at` with an extreme value.
pub fn poke_le(r: &mut Rng, b: &mut [u8], at: usize, width: usize) {
    if at + width > b.len() {
        return;
    }
    let v: u64 = *r.pick(&[0, 1, u32::MAX as u64, u64::MAX, 1 << 31, 1 << 40, u64::MAX / 4 + 1, 1000, 0x1_0000_0001]);
    b[at..at + width].copy_from_slice(&v.to_le_bytes()[..width]);
}
