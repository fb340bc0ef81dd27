//! Curricula: TOML files that describe an experiment as an ordered list of training stages.
//!
//! [`load`] reads a file into a validated [`Curriculum`] or fails with a [`CurriculumError`]
//! whose every line is `FILE:LINE:COL: message`. Four layers of checks run in order, and a
//! layer runs only when the one before it passed:
//! 1. TOML syntax;
//! 2. `schema_version` (so a file for another schema fails on that, not on its keys);
//! 3. the typed schema ([`schema`]): unknown keys, missing keys, wrong types, unknown names of
//!    closed vocabularies (scenarios, reward terms, DR parameters, enum values);
//! 4. [`validate`]: joint names, numbers JSON cannot carry, and the relations between stages
//!    (references, expansion compatibility).
//!
//! What a stage means — ranges, mixtures that must sum to 1, relations between its keys, joint
//! symmetry — is Python's to check (`facade.check_stage`, run by `hifar check` and `hifar train`
//! after [`load`]). Positions come from a span tree of the document ([`span`]), which also maps
//! the key paths Python returns back to lines ([`Curriculum::locate`]).

pub mod features;
pub mod schema;
pub mod span;
pub mod validate;

use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

use serde_json::Value;
use toml::de::DeTable;

pub use features::{feature_names, FeatureKind, FeatureNames};
pub use schema::{Advance, Backend, CurriculumFile, StageTable as Stage};
pub use span::{PathSegment, Target};

use crate::names::{Backends, Vocabulary};
use span::{line_col, SpanNode};
use validate::InitSource;

/// One problem in a curriculum file, with its 1-based position when it has one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Problem {
    pub line: Option<(usize, usize)>,
    pub message: String,
}

/// Why a curriculum file was rejected: one or more problems, each printed on its own line as
/// `FILE:LINE:COL: message` (or `FILE: message` when the file could not be read at all).
#[derive(Debug, Clone)]
pub struct CurriculumError {
    pub file: PathBuf,
    pub problems: Vec<Problem>,
}

impl std::error::Error for CurriculumError {}

impl fmt::Display for CurriculumError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, problem) in self.problems.iter().enumerate() {
            if i > 0 {
                f.write_str("\n")?;
            }
            match problem.line {
                Some((line, col)) => write!(f, "{}:{line}:{col}: {}", self.file.display(), problem.message)?,
                None => write!(f, "{}: {}", self.file.display(), problem.message)?,
            }
        }
        Ok(())
    }
}

/// A position in a curriculum file; displays as `FILE:LINE:COL`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Location {
    pub file: PathBuf,
    pub line: usize,
    pub col: usize,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}:{}", self.file.display(), self.line, self.col)
    }
}

/// A bad command-line override (`--seed`, `--backend`, `--num-envs`).
#[derive(Debug, Clone, thiserror::Error)]
#[error("{0}")]
pub struct OverrideError(pub String);

/// A validated curriculum, with the source text and positions kept for later messages.
#[derive(Debug, Clone)]
pub struct Curriculum {
    path: PathBuf,
    text: String,
    spans: SpanNode,
    file: CurriculumFile,
    init: Vec<InitSource>,
}

/// Reads and validates a curriculum file.
pub fn load(path: &Path) -> Result<Curriculum, CurriculumError> {
    let text = std::fs::read_to_string(path).map_err(|err| CurriculumError {
        file: path.to_path_buf(),
        problems: vec![Problem { line: None, message: format!("cannot read the curriculum: {err}") }],
    })?;
    parse(path, text)
}

/// Validates curriculum text; `path` is only used in messages.
pub fn parse(path: &Path, text: String) -> Result<Curriculum, CurriculumError> {
    let fail = |problems: Vec<(Range<usize>, String)>| CurriculumError {
        file: path.to_path_buf(),
        problems: problems.into_iter().map(|(span, message)| Problem { line: Some(line_col(&text, span.start)), message }).collect(),
    };

    // 1. Syntax.
    let document = DeTable::parse(&text).map_err(|err| {
        fail(vec![(err.span().unwrap_or(0..0), format!("TOML syntax error: {}", err.message().trim_end()))])
    })?;
    let spans = SpanNode::from_document(&document);

    // 2. Schema version, before the keys of a schema we may not know.
    check_schema_version(&document).map_err(|(span, message)| fail(vec![(span, message)]))?;
    drop(document);

    // 3. Types and keys.
    let file: CurriculumFile = serde::Deserialize::deserialize(
        toml::de::Deserializer::parse(&text).expect("the text parsed a moment ago"),
    )
    .map_err(|err| {
        let span = err.span().unwrap_or(0..0);
        fail(vec![(span.clone(), explain(&spans, &span, err.message()))])
    })?;

    // 4. Names, numbers JSON can carry, and the relations between stages.
    let document: toml::Table = text.parse().expect("the text parsed a moment ago");
    let (findings, init) = validate::validate(&file, &document);
    if !findings.is_empty() {
        let mut problems: Vec<(Range<usize>, String)> =
            findings.into_iter().map(|f| (spans.find(&f.path, f.target).0, f.message)).collect();
        problems.sort_by_key(|(span, _)| span.start);
        return Err(fail(problems));
    }
    Ok(Curriculum { path: path.to_path_buf(), text, spans, file, init })
}

fn check_schema_version(document: &toml::Spanned<DeTable<'_>>) -> Result<(), (Range<usize>, String)> {
    let expected = format!("this hifar reads schema_version = {}", schema::SCHEMA_VERSION);
    let Some(value) = document.get_ref().get("schema_version") else {
        return Err((0..0, format!("missing schema_version; {expected} (add it as the first line)")));
    };
    match value.get_ref().as_integer().and_then(|i| i.as_str().parse::<i64>().ok()) {
        Some(v) if v == schema::SCHEMA_VERSION => Ok(()),
        Some(v) => Err((value.span(), format!("unsupported schema_version = {v}; {expected}"))),
        None => Err((value.span(), format!("schema_version must be an integer; {expected}"))),
    }
}

/// What the keys of a table are called, and how to introduce the list of valid ones, for the
/// tables whose keys are names from a closed vocabulary.
fn noun_for_table(path: &[PathSegment]) -> Option<(&'static str, &'static str)> {
    match path.last() {
        Some(PathSegment::Key(k)) if path.len() >= 3 => match k.as_str() {
            "scenarios" => Some(("scenario", "expected one of")),
            "rewards" => Some(("reward term", "expected one of")),
            "domain_randomization" => Some(("domain-randomization parameter", "valid keys:")),
            "terrain" => Some(("terrain", "valid keys:")),
            _ => None,
        },
        _ => None,
    }
}

/// serde's Rust type names in the curriculum's words.
fn plain_types(message: &str) -> String {
    message
        .replace("expected f64", "expected a number")
        .replace("expected u64", "expected a non-negative integer")
        .replace("expected u32", "expected a non-negative integer (at most 4294967295)")
        .replace("expected i64", "expected an integer")
        .replace("expected a sequence", "expected an array")
        .replace("expected a map", "expected a table")
}

/// `[stage.ppo]`-style name of the table at `path` (array indices dropped).
fn table_name(path: &[PathSegment]) -> String {
    let keys: Vec<String> = path
        .iter()
        .filter_map(|s| match s {
            PathSegment::Key(k) => Some(k.clone()),
            PathSegment::Index(_) => None,
        })
        .collect();
    if keys.is_empty() {
        "the top level".to_owned()
    } else if keys.len() == 1 && keys[0] == "stage" {
        "[[stage]]".to_owned()
    } else {
        format!("[{}]", keys.join("."))
    }
}

/// Rewrites a deserializer message with the table it concerns and the curriculum's words
/// ("key", "scenario", "reward term") instead of serde's ("field", "variant").
fn explain(spans: &SpanNode, span: &Range<usize>, message: &str) -> String {
    let message = message.trim_end();
    let key_path = spans.path_of_key_span(span);
    if let Some(rest) = message.strip_prefix("unknown field ").or_else(|| message.strip_prefix("unknown variant ")) {
        let (name, valid) = rest.split_once(", ").unwrap_or((rest, ""));
        let valid = valid.strip_prefix("expected one of ").or_else(|| valid.strip_prefix("expected ")).unwrap_or(valid);
        let valid = if valid == "there are no fields" { "none" } else { valid };
        return match key_path {
            Some(path) => {
                let table = &path[..path.len() - 1];
                let mut text = match noun_for_table(table) {
                    Some((noun, intro)) => format!("unknown {noun} {name} in {}; {intro} {valid}", table_name(table)),
                    None => format!("unknown key {name} in {}; valid keys: {valid}", table_name(table)),
                };
                if table.last() == Some(&PathSegment::from("scenarios")) && name.starts_with("`ksi_") {
                    text.push_str(&format!(
                        " (key-state scenarios are named after the model's keyframes: {})",
                        crate::names::names().keyframes.iter().filter(|k| k.starts_with("ksi_")).copied().collect::<Vec<_>>().join(", ")
                    ));
                }
                text
            }
            None => {
                let path = spans.path_of_span(span);
                format!("unknown value {name} for {}; expected one of {valid}", describe_key(&path))
            }
        };
    }
    if let Some(field) = message.strip_prefix("missing field ") {
        let path = spans.path_of_span(span);
        return format!("missing required key {field} in {}", table_name(&path));
    }
    let message = plain_types(message);
    let path = spans.path_of_span(span);
    if path.is_empty() {
        message
    } else {
        format!("{}: {message}", describe_key(&path))
    }
}

/// `stage.ppo.num_envs`-style name of a key path (array indices as `[i]`, except the
/// `[[stage]]` index: the line number tells the stage).
fn describe_key(path: &[PathSegment]) -> String {
    let mut out = String::new();
    for (i, segment) in path.iter().enumerate() {
        if i == 1 && path[0] == PathSegment::from("stage") && matches!(segment, PathSegment::Index(_)) {
            continue;
        }
        match segment {
            PathSegment::Key(k) => {
                if !out.is_empty() {
                    out.push('.');
                }
                out.push_str(k);
            }
            PathSegment::Index(i) => out.push_str(&format!("[{i}]")),
        }
    }
    out
}

impl Curriculum {
    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn name(&self) -> &str {
        &self.file.name
    }

    pub fn seed(&self) -> u64 {
        self.file.seed
    }

    /// "auto", "mjx" or "native".
    pub fn backend(&self) -> &str {
        self.file.backend.as_str()
    }

    pub fn stages(&self) -> &[Stage] {
        &self.file.stage
    }

    /// Index of the stage whose final checkpoint initialises stage `index` (None: fresh).
    pub fn init_source(&self, index: usize) -> Option<usize> {
        match self.init.get(index)? {
            InitSource::Fresh => None,
            InitSource::Stage(i) => Some(*i),
        }
    }

    /// Applies command-line overrides, then re-checks what depends on them.
    pub fn apply_overrides(
        &mut self,
        seed: Option<u64>,
        backend: Option<&str>,
        num_envs: Option<u32>,
    ) -> Result<(), OverrideError> {
        if let Some(name) = backend {
            let parsed = Backend::parse(name).ok_or_else(|| {
                OverrideError(format!("--backend {name:?}: expected one of {}", Backends::names().join(", ")))
            })?;
            self.file.backend = parsed;
        }
        if let Some(n) = num_envs {
            if n == 0 {
                return Err(OverrideError("--num-envs 0: expected a positive number of environments".into()));
            }
            for (i, stage) in self.file.stage.iter().enumerate() {
                if let Some(problem) = validate::minibatch_problem(n, stage.ppo.num_minibatches) {
                    let at = self.locate_path(&stage_path(i, &["ppo", "num_minibatches"]), Target::Value);
                    return Err(OverrideError(format!("--num-envs {n}: stage {:?}: {problem} ({at})", stage.name)));
                }
            }
            for stage in &mut self.file.stage {
                stage.ppo.num_envs = n;
            }
        }
        if let Some(seed) = seed {
            self.file.seed = seed;
        }
        Ok(())
    }

    /// The position of a key path relative to stage `stage`'s table, as Python's
    /// `check_stage` returns it (`["scenarios", "ksi_prone_7"]`, `["controlled_joints", 3]`).
    /// A path that is not in the file (a missing key) points at the table that should hold it.
    pub fn locate(&self, stage: usize, path: &[Value]) -> Location {
        self.locate_at(stage, path, Target::Key)
    }

    /// [`Curriculum::locate`], pointing at the key or at its value.
    pub fn locate_at(&self, stage: usize, path: &[Value], target: Target) -> Location {
        let mut full = vec![PathSegment::from("stage"), PathSegment::Index(stage)];
        full.extend(path.iter().map_while(PathSegment::from_json));
        self.locate_path(&full, target)
    }

    /// The position of an absolute key path (from the top of the file).
    pub fn locate_path(&self, path: &[PathSegment], target: Target) -> Location {
        let (span, _) = self.spans.find(path, target);
        let (line, col) = line_col(&self.text, span.start);
        Location { file: self.path.clone(), line, col }
    }

    /// The whole curriculum as JSON, overrides applied (for the run manifest).
    pub fn resolved_json(&self) -> Value {
        serde_json::to_value(&self.file).expect("a validated curriculum is plain data")
    }
}

fn stage_path(index: usize, keys: &[&str]) -> Vec<PathSegment> {
    let mut path = vec![PathSegment::from("stage"), PathSegment::Index(index)];
    path.extend(keys.iter().map(|k| PathSegment::from(*k)));
    path
}

impl Stage {
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The stage table as JSON: exactly its keys and values (what Python receives).
    pub fn to_json(&self) -> Value {
        serde_json::to_value(self).expect("a validated stage is plain data")
    }

    pub fn advance(&self) -> &Advance {
        &self.advance
    }

    pub fn initial_action_std(&self) -> f64 {
        self.ppo.initial_action_std
    }

    pub fn feature_names(&self) -> FeatureNames {
        feature_names(self)
    }
}

#[cfg(test)]
mod tests;
