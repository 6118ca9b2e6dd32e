//! Reading robot files: attributes as numbers and vectors, errors that name the element and
//! its line, and refusing what a format's subset does not cover.

use adflex_runtime::Vec3;
use roxmltree::Node;

use super::model::ArticulationError;

/// A file being read: its name (for errors) and its document.
pub(crate) struct Source<'a> {
    pub file: Option<String>,
    pub doc: &'a roxmltree::Document<'a>,
}

impl Source<'_> {
    /// An error at `node`: `<tag name="...">` on its line.
    pub fn error(&self, node: Node, message: impl Into<String>) -> ArticulationError {
        let pos = self.doc.text_pos_at(node.range().start);
        let tag = node.tag_name().name();
        let element = match node.attribute("name") {
            Some(n) => format!("<{tag} name=\"{n}\">"),
            None => format!("<{tag}>"),
        };
        ArticulationError {
            element,
            file: self.file.clone(),
            line: Some(pos.row),
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
