//! Reading a scene file: where a field is in the text, the errors that name it, and the
//! [`Checker`] every section's loader reports through (each physics family and force owns its
//! section: its description type and loader live in its own file; `scene_file` lists them).

use std::fmt;

use adflex_runtime::{Real, Vec3};

use crate::validation::{precision, Problem};

/// An error reading a scene file: what is wrong, where (line and column, 1-based, when
/// known) and in which field (a path like `particles[2].mass`, when known).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SceneError {
    /// What is wrong.
    pub message: String,
    /// The field, as a path from the root (`springs[3].ke`).
    pub field: Option<String>,
    /// Line (1-based).
    pub line: Option<usize>,
    /// Column (1-based).
    pub column: Option<usize>,
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("scene file")?;
        if let Some(l) = self.line {
            write!(f, ", line {l}")?;
            if let Some(c) = self.column {
                write!(f, ", column {c}")?;
            }
        }
        if let Some(p) = &self.field {
            write!(f, ", field `{p}`")?;
        }
        write!(f, ": {}", self.message)
    }
}

impl std::error::Error for SceneError {}

pub(crate) fn zero3() -> [f64; 3] {
    [0.0; 3]
}

pub(crate) fn identity_quat() -> [f64; 4] {
    [0.0, 0.0, 0.0, 1.0]
}

// ---- where things are in the text ----------------------------------------------------------
//
// Nothing is indexed up front: serde (through `serde_path_to_error`) gives the field path and
// the parser the line of a deserialization error, and the semantic checks of `build`, which
// know the path of what they reject, find it in the text only when they report an error (one
// linear scan per error).

/// How deep `[` and `{` may nest (serde_json's recursion limit; toml's is lower). Deeper input
/// is rejected as soon as the parser reaches that depth.
pub const MAX_NESTING: usize = 128;

#[derive(Clone, Copy)]
pub(crate) enum Format {
    Json,
    Toml,
}

/// One step of a field path: a key or an index.
#[derive(PartialEq, Eq, Debug)]
enum Seg<'a> {
    Key(&'a str),
    Index(usize),
}

/// `springs[3].ke` as `[Key(springs), Index(3), Key(ke)]`.
fn segments(path: &str) -> Vec<Seg<'_>> {
    let mut out = Vec::new();
    for part in path.split('.') {
        let (key, mut rest) = match part.find('[') {
            Some(k) => (&part[..k], &part[k..]),
            None => (part, ""),
        };
        if !key.is_empty() {
            out.push(Seg::Key(key));
        }
        while let Some(r) = rest.strip_prefix('[') {
            let close = r.find(']').unwrap_or(r.len());
            out.push(Seg::Index(r[..close].parse().unwrap_or(usize::MAX)));
            rest = r.get(close + 1..).unwrap_or("");
        }
    }
    out
}

enum Frame<'a> {
    /// An object and its current key.
    Object(Option<&'a str>),
    /// An array and the current index.
    Array(usize),
}

fn frames_match(stack: &[Frame], key: Option<&str>, target: &[Seg]) -> bool {
    let depth = stack
        .iter()
        .filter(|f| !matches!(f, Frame::Object(None)))
        .count();
    if depth + usize::from(key.is_some()) != target.len() {
        return false;
    }
    let mut t = target.iter();
    for f in stack {
        let ok = match f {
            Frame::Object(Some(k)) => t.next() == Some(&Seg::Key(k)),
            Frame::Object(None) => true,
            Frame::Array(i) => t.next() == Some(&Seg::Index(*i)),
        };
        if !ok {
            return false;
        }
    }
    match key {
        Some(k) => t.next() == Some(&Seg::Key(k)),
        None => true,
    }
}

/// The byte offset in a JSON text of the field `target` (of its key if it has one, else of
/// its value), if it is there. One pass; tolerant of malformed text. Only called on the error
/// path, after serde has accepted the text (so the nesting is at most [`MAX_NESTING`]).
fn json_locate(src: &str, target: &[Seg]) -> Option<usize> {
    let b = src.as_bytes();
    let mut stack: Vec<Frame> = Vec::new();
    let mut expect_key = false;
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        match c {
            b' ' | b'\t' | b'\n' | b'\r' | b':' => i += 1,
            b',' => {
                match stack.last_mut() {
                    Some(Frame::Array(k)) => *k += 1,
                    Some(Frame::Object(_)) => expect_key = true,
                    None => {}
                }
                i += 1;
            }
            b'{' | b'[' => {
                if frames_match(&stack, None, target) {
                    return Some(i);
                }
                if stack.len() > MAX_NESTING {
                    return None;
                }
                stack.push(if c == b'{' {
                    Frame::Object(None)
                } else {
                    Frame::Array(0)
                });
                expect_key = c == b'{';
                i += 1;
            }
            b'}' | b']' => {
                stack.pop();
                expect_key = false;
                i += 1;
            }
            b'"' => {
                let start = i;
                i += 1;
                while i < b.len() && b[i] != b'"' {
                    i += if b[i] == b'\\' { 2 } else { 1 };
                }
                let text = src.get(start + 1..i.min(b.len())).unwrap_or("");
                i += 1;
                if expect_key {
                    expect_key = false;
                    if frames_match(&stack, Some(text), target) {
                        return Some(start);
                    }
                    if let Some(Frame::Object(k)) = stack.last_mut() {
                        *k = Some(text);
                    }
                } else if frames_match(&stack, None, target) {
                    return Some(start);
                }
            }
            _ => {
                if frames_match(&stack, None, target) {
                    return Some(i);
                }
                while i < b.len() && !b",]} \t\r\n".contains(&b[i]) {
                    i += 1;
                }
            }
        }
    }
    None
}

fn toml_header(name: &str) -> Vec<Seg<'_>> {
    name.trim()
        .split('.')
        .map(|k| Seg::Key(k.trim().trim_matches('"')))
        .collect()
}

/// The byte offset in a TOML text of the field `target`: a table header (`[a]`, `[[a]]`
/// counted per name) or a `key = value` line under the current table. Values inside inline
/// tables and arrays are located at their key (their parent is found instead).
fn toml_locate(src: &str, target: &[Seg]) -> Option<usize> {
    let mut counts: std::collections::HashMap<&str, usize> = Default::default();
    let mut prefix: Vec<Seg> = Vec::new();
    let mut offset = 0;
    for line in src.split_inclusive('\n') {
        let t = line.trim();
        let at = offset + line.len() - line.trim_start().len();
        offset += line.len();
        if let Some(name) = t.strip_prefix("[[").and_then(|r| r.split("]]").next()) {
            let n = counts.entry(name.trim()).or_insert(0);
            *n += 1;
            prefix = toml_header(name);
            prefix.push(Seg::Index(*n - 1));
            if prefix == target {
                return Some(at);
            }
        } else if let Some(name) = t.strip_prefix('[').and_then(|r| r.split(']').next()) {
            prefix = toml_header(name);
            if prefix == target {
                return Some(at);
            }
        } else if let Some((key, _)) = t.split_once('=') {
            let key = key.trim().trim_matches('"');
            if !key.is_empty()
                && !key.starts_with('#')
                && target.len() == prefix.len() + 1
                && target[..prefix.len()] == prefix[..]
                && target[prefix.len()] == Seg::Key(key)
            {
                return Some(at);
            }
        }
    }
    None
}

/// Line and column (1-based) of a byte offset.
fn line_col(src: &str, offset: usize) -> (usize, usize) {
    let offset = offset.min(src.len());
    let before = &src.as_bytes()[..offset];
    let line = before.iter().filter(|&&c| c == b'\n').count() + 1;
    let col = offset
        - before
            .iter()
            .rposition(|&c| c == b'\n')
            .map_or(0, |p| p + 1)
        + 1;
    (line, col)
}

/// A semantic error about `path`, located in the text at the field or, if it is not written
/// there (a default), at its nearest parent that is.
fn at(src: &str, format: Format, path: String, message: impl Into<String>) -> SceneError {
    let segs = segments(&path);
    let found = (1..=segs.len()).rev().find_map(|n| match format {
        Format::Json => json_locate(src, &segs[..n]),
        Format::Toml => toml_locate(src, &segs[..n]),
    });
    let (line, column) = match found.map(|o| line_col(src, o)) {
        Some((l, c)) => (Some(l), Some(c)),
        None => (None, None),
    };
    SceneError {
        message: message.into(),
        field: Some(path),
        line,
        column,
    }
}

// ---- checking

/// `[x, y, z]` in `R`.
pub(crate) fn v3<R: Real>(a: [f64; 3]) -> Vec3<R> {
    Vec3::new(R::lit(a[0]), R::lit(a[1]), R::lit(a[2]))
}

/// Reports a section's errors at their field and line.
pub(crate) struct Checker<'a> {
    pub(crate) src: &'a str,
    pub(crate) format: Format,
}

impl Checker<'_> {
    pub(crate) fn err(&self, path: String, message: impl Into<String>) -> SceneError {
        at(self.src, self.format, path, message)
    }

    pub(crate) fn finite(&self, path: impl Fn() -> String, vals: &[f64]) -> Result<(), SceneError> {
        if vals.iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(self.err(path(), "must be finite"))
        }
    }

    pub(crate) fn nonneg(&self, path: impl Fn() -> String, v: f64) -> Result<(), SceneError> {
        if v.is_finite() && v >= 0.0 {
            Ok(())
        } else {
            Err(self.err(path(), format!("must be a finite number >= 0 (got {v})")))
        }
    }

    pub(crate) fn positive(&self, path: impl Fn() -> String, v: f64) -> Result<(), SceneError> {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            Err(self.err(path(), format!("must be a finite number > 0 (got {v})")))
        }
    }

    /// A mass (kg) that is not 0 in the file must not round to 0 in `R` (that would pin the
    /// particle or make the body static).
    pub(crate) fn no_underflow<R: Real>(
        &self,
        path: impl Fn() -> String,
        v: f64,
    ) -> Result<(), SceneError> {
        if v > 0.0 && R::lit(v).to_f64() == 0.0 {
            Err(self.err(
                path(),
                format!(
                    "{v:e} rounds to 0 in {} (which would pin it); give at least {:.1e}, or 0",
                    precision::<R>(),
                    min_positive::<R>()
                ),
            ))
        } else {
            Ok(())
        }
    }

    /// The first problem the builder recorded since it had `from`, as an error at the path
    /// `path(param)` gives.
    pub(crate) fn builder(
        &self,
        problems: &[Problem],
        from: usize,
        path: impl Fn(Option<&str>) -> String,
    ) -> Result<(), SceneError> {
        match problems.get(from) {
            None => Ok(()),
            Some(p) => Err(self.err(path(p.param), p.message.clone())),
        }
    }
}

fn min_positive<R: Real>() -> f64 {
    if precision::<R>() == "f32" {
        f32::from_bits(1) as f64
    } else {
        f64::from_bits(1)
    }
}

/// `item.param`, or `item` for the element as a whole (and for `whole` parameters).
pub(crate) fn sub(item: &str, param: Option<&str>, whole: &[&str]) -> String {
    match param {
        Some(p) if !whole.contains(&p) => format!("{item}.{p}"),
        _ => item.to_string(),
    }
}

/// Strips serde_json's " at line L column C" suffix (the error carries them separately).
fn strip_position(msg: &str) -> String {
    match msg.rfind(" at line ") {
        Some(k) => msg[..k].to_string(),
        None => msg.to_string(),
    }
}

/// The field path of a deserialization error (`None` at the root).
pub(crate) fn field_of(path: &serde_path_to_error::Path) -> Option<String> {
    let p = path.to_string();
    (p != ".").then_some(p)
}

pub(crate) fn json_error(field: Option<String>, e: serde_json::Error) -> SceneError {
    let mut message = strip_position(&e.to_string());
    if message == "recursion limit exceeded" {
        message = format!("nested deeper than {MAX_NESTING} levels of `[` and `{{`");
    }
    let line = e.line();
    SceneError {
        message,
        field,
        line: (line > 0).then_some(line),
        column: (line > 0).then_some(e.column()),
    }
}

pub(crate) fn toml_error(src: &str, field: Option<String>, e: &toml::de::Error) -> SceneError {
    let mut message = e.message().trim().to_string();
    if message.contains("max recursion depth") {
        message = format!("{message} (arrays and inline tables nested too deep)");
    }
    let (line, column) = match e.span() {
        Some(span) => {
            let (l, c) = line_col(src, span.start);
            (Some(l), Some(c))
        }
        None => (None, None),
    };
    SceneError {
        message,
        field,
        line,
        column,
    }
}
