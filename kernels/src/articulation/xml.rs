//! Reading robot files: attributes as numbers and vectors, errors that name the element and
//! its line, and refusing what a format's subset does not cover.

use adflex_runtime::Vec3;
use roxmltree::Node;

use super::model::ArticulationError;

/// A file being read: its name (for errors) and its document.
pub(crate) struct Source<'a> {
    pub file: Option<String>,
    pub doc: &'a roxmltree::Document<'a>,
    /// Where the document's lines come from, when it was spliced from several files.
    pub lines: Option<&'a Lines>,
}

impl Source<'_> {
    /// An error at `node`: `<tag name="...">` on its line (of the file it came from).
    pub fn error(&self, node: Node, message: impl Into<String>) -> ArticulationError {
        let at = node.range().start;
        let (file, row) = match self.lines {
            Some(lines) => lines.origin(self.doc.input_text(), at),
            None => (self.file.clone(), self.doc.text_pos_at(at).row),
        };
        let tag = node.tag_name().name();
        let element = match node.attribute("name") {
            Some(n) => format!("<{tag} name=\"{n}\">"),
            None => format!("<{tag}>"),
        };
        ArticulationError {
            element,
            file,
            line: Some(row),
            message: message.into(),
        }
    }

    /// The attribute `name` of `node`, required.
    pub fn required<'n>(
        &self,
        node: Node<'n, 'n>,
        name: &str,
    ) -> Result<&'n str, ArticulationError> {
        node.attribute(name)
            .ok_or_else(|| self.error(node, format!("needs the attribute `{name}`")))
    }

    /// `n` finite numbers separated by white space in attribute `name`, if present.
    pub fn numbers(
        &self,
        node: Node,
        name: &str,
        n: usize,
    ) -> Result<Option<Vec<f64>>, ArticulationError> {
        let Some(text) = node.attribute(name) else {
            return Ok(None);
        };
        let values: Vec<&str> = text.split_whitespace().collect();
        if values.len() != n {
            return Err(self.error(
                node,
                format!(
                    "attribute `{name}=\"{text}\"` needs {n} number{}, has {}",
                    if n == 1 { "" } else { "s" },
                    values.len()
                ),
            ));
        }
        values
            .iter()
            .map(|v| match v.parse::<f64>() {
                Ok(x) if x.is_finite() => Ok(x),
                _ => Err(self.error(
                    node,
                    format!("attribute `{name}=\"{text}\"`: `{v}` is not a finite number"),
                )),
            })
            .collect::<Result<Vec<_>, _>>()
            .map(Some)
    }

    /// A number in attribute `name`, if present.
    pub fn number(&self, node: Node, name: &str) -> Result<Option<f64>, ArticulationError> {
        Ok(self.numbers(node, name, 1)?.map(|v| v[0]))
    }

    /// A 3-vector in attribute `name`, if present.
    pub fn vec3(&self, node: Node, name: &str) -> Result<Option<Vec3<f64>>, ArticulationError> {
        Ok(self
            .numbers(node, name, 3)?
            .map(|v| Vec3::new(v[0], v[1], v[2])))
    }

    /// Refuses attributes of `node` outside `known`.
    pub fn only_attributes(&self, node: Node, known: &[&str]) -> Result<(), ArticulationError> {
        for a in node.attributes() {
            if !known.contains(&a.name()) {
                return Err(self.error(
                    node,
                    format!(
                        "attribute `{}` is not supported (supported: {})",
                        a.name(),
                        known.join(", ")
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// The element children of `node`, refusing any tag outside `known` (a tag in `skipped` is
/// passed over: it carries nothing the physics uses, e.g. a URDF `<visual>`).
pub(crate) fn children<'a, 'input>(
    src: &Source,
    node: Node<'a, 'input>,
    known: &[&str],
    skipped: &[&str],
) -> Result<Vec<Node<'a, 'input>>, ArticulationError> {
    let mut out = Vec::new();
    for c in node.children().filter(|c| c.is_element()) {
        let tag = c.tag_name().name();
        if skipped.contains(&tag) {
            continue;
        }
        if !known.contains(&tag) {
            return Err(src.error(
                c,
                format!(
                    "element <{tag}> in <{}> is not supported (supported: {})",
                    node.tag_name().name(),
                    known
                        .iter()
                        .map(|k| format!("<{k}>"))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            ));
        }
        out.push(c);
    }
    Ok(out)
}

/// Parses `text`, an XML error becoming an [`ArticulationError`] with its line.
pub(crate) fn parse<'a>(
    text: &'a str,
    file: Option<&str>,
) -> Result<roxmltree::Document<'a>, ArticulationError> {
    roxmltree::Document::parse(text).map_err(|e| ArticulationError {
        element: "XML".into(),
        file: file.map(str::to_string),
        line: Some(e.pos().row),
        message: e.to_string(),
    })
}

/// Reads a file, an I/O error naming it.
pub(crate) fn read(path: &std::path::Path) -> Result<String, ArticulationError> {
    std::fs::read_to_string(path).map_err(|e| ArticulationError {
        element: "file".into(),
        file: Some(path.display().to_string()),
        line: None,
        message: e.to_string(),
    })
}

/// Where each part of a text spliced from several files comes from: pieces in order, each
/// its first byte in the splice, its file and the line it starts on there.
#[derive(Debug, Default)]
pub(crate) struct Lines(Vec<(usize, Option<String>, u32)>);

impl Lines {
    /// The file and line of byte `at` of the splice `text`.
    fn origin(&self, text: &str, at: usize) -> (Option<String>, u32) {
        match self.0.iter().rev().find(|p| p.0 <= at) {
            Some((first, file, line)) => {
                let below = text[*first..at].matches('\n').count() as u32;
                (file.clone(), line + below)
            }
            None => (None, 1),
        }
    }
}

/// How deep `<include>`s may nest (a file including itself would otherwise never end).
const INCLUDE_DEPTH: usize = 16;

/// `text` with every `<include file="...">` replaced by the children of the included file's
/// root (MJCF's `<mujocoinclude>`), recursively; file names are relative to `dir`. Returns
/// the splice and where its lines come from, so that errors name the right file and line.
pub(crate) fn splice_includes(
    text: &str,
    file: Option<&str>,
    dir: &std::path::Path,
) -> Result<(String, Lines), ArticulationError> {
    let mut out = String::new();
    let mut lines = Lines::default();
    let doc = parse(text, file)?;
    splice(
        &doc,
        text,
        file,
        0..text.len(),
        dir,
        0,
        &mut out,
        &mut lines,
    )?;
    Ok((out, lines))
}

/// Copies `text[range]` of `doc` into `out`, splicing its `<include>`s.
#[allow(clippy::too_many_arguments)]
fn splice(
    doc: &roxmltree::Document,
    text: &str,
    file: Option<&str>,
    range: std::ops::Range<usize>,
    dir: &std::path::Path,
    depth: usize,
    out: &mut String,
    lines: &mut Lines,
) -> Result<(), ArticulationError> {
    let src = Source {
        file: file.map(str::to_string),
        doc,
        lines: None,
    };
    let copy = |from: usize, to: usize, out: &mut String, lines: &mut Lines| {
        if from < to {
            let line = doc.text_pos_at(from).row;
            lines.0.push((out.len(), file.map(str::to_string), line));
            out.push_str(&text[from..to]);
        }
    };
    let mut at = range.start;
    let includes = doc.descendants().filter(|n| {
        n.has_tag_name("include") && n.range().start >= range.start && n.range().end <= range.end
    });
    for inc in includes {
        src.only_attributes(inc, &["file"])?;
        children(&src, inc, &[], &[])?;
        let name = src.required(inc, "file")?;
        if depth >= INCLUDE_DEPTH {
            return Err(src.error(
                inc,
                format!(
                    "includes nest deeper than {INCLUDE_DEPTH} files (a file includes itself?)"
                ),
            ));
        }
        // Relative to the main file's directory, or else to the including file's (as MuJoCo).
        let mut path = dir.join(name);
        if let (false, Some(parent)) = (path.exists(), file.map(std::path::Path::new)) {
            let beside = parent.parent().unwrap_or(dir).join(name);
            if beside.exists() {
                path = beside;
            }
        }
        let inner = std::fs::read_to_string(&path)
            .map_err(|e| src.error(inc, format!("cannot read \"{}\": {e}", path.display())))?;
        let inner_file = path.display().to_string();
        let inner_doc = parse(&inner, Some(&inner_file))?;
        let root = inner_doc.root_element();
        let inner_src = Source {
            file: Some(inner_file.clone()),
            doc: &inner_doc,
            lines: None,
        };
        if !matches!(root.tag_name().name(), "mujocoinclude" | "mujoco") {
            return Err(inner_src.error(
                root,
                "the root element of an included file must be <mujocoinclude>",
            ));
        }
        inner_src.only_attributes(root, &["model"])?;
        copy(at, inc.range().start, out, lines);
        if let (Some(first), Some(last)) = (root.first_child(), root.last_child()) {
            let inner_range = first.range().start..last.range().end;
            splice(
                &inner_doc,
                &inner,
                Some(&inner_file),
                inner_range,
                dir,
                depth + 1,
                out,
                lines,
            )?;
        }
        at = inc.range().end;
    }
    copy(at, range.end, out, lines);
    Ok(())
}
