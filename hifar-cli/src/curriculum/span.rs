//! Where every key and value of a TOML document sits in the file.
//!
//! The typed structs of [`super::schema`] carry no positions; validation reports problems as
//! key paths (`["stage", 1, "ppo", "num_envs"]`) and this tree turns them into `LINE:COL`.
//! Python's `check_stage` answers with key paths too, so both sides share one mapping.

use std::fmt;
use std::ops::Range;

use serde_json::Value;
use toml::de::{DeTable, DeValue};
use toml::Spanned;

/// One step of a key path: a table key or an array index.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PathSegment {
    Key(String),
    Index(usize),
}

impl From<&str> for PathSegment {
    fn from(key: &str) -> Self {
        PathSegment::Key(key.to_owned())
    }
}

impl From<String> for PathSegment {
    fn from(key: String) -> Self {
        PathSegment::Key(key)
    }
}

impl From<usize> for PathSegment {
    fn from(index: usize) -> Self {
        PathSegment::Index(index)
    }
}

impl PathSegment {
    /// A segment of a JSON key path as Python returns it (strings and non-negative integers).
    pub fn from_json(value: &Value) -> Option<Self> {
        match value {
            Value::String(s) => Some(PathSegment::Key(s.clone())),
            Value::Number(n) => n.as_u64().map(|i| PathSegment::Index(i as usize)),
            _ => None,
        }
    }
}

impl fmt::Display for PathSegment {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PathSegment::Key(k) => f.write_str(k),
            PathSegment::Index(i) => write!(f, "{i}"),
        }
    }
}

/// Which end of a `key = value` pair a location should point at.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Target {
    /// The key (unknown names, duplicate entries, missing keys inside it).
    Key,
    /// The value (out-of-range numbers, bad list elements).
    Value,
}

/// Called on every node of a walk with its key span (None for array elements) and its path.
type Visitor<'a> = dyn FnMut(&SpanNode, Option<&Range<usize>>, &[PathSegment]) + 'a;

#[derive(Debug, Clone)]
enum Children {
    Table(Vec<(String, Range<usize>, SpanNode)>),
    Array(Vec<SpanNode>),
    Scalar,
}

/// A value's span and those of everything inside it.
#[derive(Debug, Clone)]
pub struct SpanNode {
    span: Range<usize>,
    children: Children,
}

impl SpanNode {
    pub fn from_document(root: &Spanned<DeTable<'_>>) -> Self {
        Self::table(root.span(), root.get_ref())
    }

    fn table(span: Range<usize>, table: &DeTable<'_>) -> Self {
        let entries = table
            .iter()
            .map(|(key, value)| (key.get_ref().to_string(), key.span(), Self::value(value)))
            .collect();
        SpanNode { span, children: Children::Table(entries) }
    }

    fn value(value: &Spanned<DeValue<'_>>) -> Self {
        match value.get_ref() {
            DeValue::Table(table) => Self::table(value.span(), table),
            DeValue::Array(array) => SpanNode {
                span: value.span(),
                children: Children::Array(array.iter().map(Self::value).collect()),
            },
            _ => SpanNode { span: value.span(), children: Children::Scalar },
        }
    }

    fn child(&self, segment: &PathSegment) -> Option<(Option<Range<usize>>, &SpanNode)> {
        match (&self.children, segment) {
            (Children::Table(entries), PathSegment::Key(key)) => {
                entries.iter().find(|(k, _, _)| k == key).map(|(_, span, node)| (Some(span.clone()), node))
            }
            (Children::Array(items), PathSegment::Index(i)) => items.get(*i).map(|node| (None, node)),
            _ => None,
        }
    }

    /// The byte span of `path`'s key (or value), or of its deepest existing prefix when the
    /// path leads to something that is not in the file (a missing key: point at its table).
    /// The second element is true when the whole path was found.
    pub fn find(&self, path: &[PathSegment], target: Target) -> (Range<usize>, bool) {
        let mut node = self;
        let mut key_span: Option<Range<usize>> = None;
        for segment in path {
            match node.child(segment) {
                Some((span, child)) => {
                    key_span = span;
                    node = child;
                }
                // Something missing: point at the table that should hold it (its `[header]`,
                // its inline `{ }`, or the dotted key that created it; the root is 1:1).
                None => return (node.span.clone(), false),
            }
        }
        let span = match (target, key_span) {
            (Target::Key, Some(key)) => key,
            _ => node.span.clone(),
        };
        (span, true)
    }

    /// The key path of the key whose span is exactly `span` (the deserializer reports
    /// unknown keys by the key's span).
    pub fn path_of_key_span(&self, span: &Range<usize>) -> Option<Vec<PathSegment>> {
        let mut found = None;
        self.walk(&mut Vec::new(), &mut |_, key_span, path| {
            if key_span == Some(span) {
                found = Some(path.to_vec());
            }
        });
        found
    }

    /// The path of the deepest value whose span is exactly `span` (header tables span only
    /// their `[header]`, so containment would not find what is inside them), else of the
    /// deepest value or key whose span contains its start.
    pub fn path_of_span(&self, span: &Range<usize>) -> Vec<PathSegment> {
        let mut best: Option<Vec<PathSegment>> = None;
        let mut path = Vec::new();
        self.walk(&mut path, &mut |node, key_span, path| {
            if node.span == *span || key_span == Some(span) {
                best = Some(path.to_vec());
            }
        });
        if let Some(found) = best {
            return found;
        }
        let mut best = Vec::new();
        self.walk(&mut path, &mut |node, key_span, path| {
            let hit = node.span.contains(&span.start) || key_span.is_some_and(|k| k.contains(&span.start));
            if hit && path.len() >= best.len() {
                best = path.to_vec();
            }
        });
        best
    }

    /// Calls `visit(node, key span, path)` on every node below this one, parents first.
    fn walk(
        &self,
        path: &mut Vec<PathSegment>,
        visit: &mut Visitor<'_>,
    ) {
        match &self.children {
            Children::Table(entries) => {
                for (key, key_span, node) in entries {
                    path.push(PathSegment::Key(key.clone()));
                    visit(node, Some(key_span), path);
                    node.walk(path, visit);
                    path.pop();
                }
            }
            Children::Array(items) => {
                for (i, node) in items.iter().enumerate() {
                    path.push(PathSegment::Index(i));
                    visit(node, None, path);
                    node.walk(path, visit);
                    path.pop();
                }
            }
            Children::Scalar => {}
        }
    }
}

/// 1-based line and column (in characters) of a byte offset.
pub fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let offset = offset.min(text.len());
    let offset = (0..=offset).rev().find(|&i| text.is_char_boundary(i)).unwrap_or(0);
    let before = &text[..offset];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    let col = text[line_start..offset].chars().count() + 1;
    (line, col)
}

#[cfg(test)]
mod tests {
    use super::*;

    const DOC: &str = "a = 1\n[t]\nx = [10, 20]\n[[s]]\nname = \"é\"\n[s.sub]\nk = 2\n";

    fn tree() -> SpanNode {
        SpanNode::from_document(&DeTable::parse(DOC).unwrap())
    }

    fn at(path: &[PathSegment], target: Target) -> ((usize, usize), bool) {
        let (span, found) = tree().find(path, target);
        (line_col(DOC, span.start), found)
    }

    #[test]
    fn keys_values_and_elements() {
        assert_eq!(at(&["a".into()], Target::Key), ((1, 1), true));
        assert_eq!(at(&["a".into()], Target::Value), ((1, 5), true));
        assert_eq!(at(&["t".into(), "x".into(), 1.into()], Target::Key), ((3, 10), true));
        assert_eq!(at(&["s".into(), 0.into(), "sub".into(), "k".into()], Target::Value), ((7, 5), true));
    }

    #[test]
    fn missing_paths_point_at_the_enclosing_table() {
        assert_eq!(at(&["t".into(), "nope".into()], Target::Key), ((2, 1), false));
        assert_eq!(at(&["s".into(), 0.into(), "missing".into()], Target::Key), ((4, 1), false));
        assert_eq!(at(&["zzz".into()], Target::Key), ((1, 1), false));
    }

    #[test]
    fn columns_count_characters() {
        assert_eq!(line_col("é = 1", "é = ".len()), (1, 5));
        assert_eq!(line_col("a\nb", 2), (2, 1));
    }

    #[test]
    fn reverse_lookup() {
        let t = tree();
        let (span, _) = t.find(&["s".into(), 0.into(), "sub".into(), "k".into()], Target::Key);
        assert_eq!(t.path_of_key_span(&span).unwrap(), vec!["s".into(), 0.into(), "sub".into(), "k".into()]);
        let at = DOC.find("20").unwrap();
        assert_eq!(t.path_of_span(&(at..at + 2)), vec![PathSegment::from("t"), "x".into(), 1.into()]);
        let header = DOC.find("[s.sub]").unwrap();
        assert_eq!(t.path_of_span(&(header..header + 7)), vec![PathSegment::from("s"), 0.into(), "sub".into()]);
        assert_eq!(t.path_of_span(&(at + 1..at + 1)), vec![PathSegment::from("t"), "x".into(), 1.into()]);
    }
}
