//! Diagnostics: source spans, errors and warnings, and their rendering.
//!
//! Every stage of readi reports problems as [`Diagnostic`]s that point into source files
//! by [`Span`]. Rendering goes through `codespan-reporting`, which prints
//! `file:line:col`, the source line and a caret underline:
//!
//! ```text
//! error[E0101]: expected `,` or `)`
//!   ┌─ models/resnet18.readi:12:27
//!   │
//! 12 │   conv1 = conv2d(x, planes kernel=3)
//!   │                            ^ expected `,` or `)`
//! ```

use codespan_reporting::diagnostic as cs;
use codespan_reporting::files::SimpleFiles;
use codespan_reporting::term;

/// Index of a file in a [`SourceMap`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FileId(pub u32);

/// A byte range of one source file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Span {
    pub file: FileId,
    pub start: u32,
    pub end: u32,
}

impl Span {
    pub fn new(file: FileId, start: usize, end: usize) -> Span {
        Span { file, start: start as u32, end: end as u32 }
    }
    /// The smallest span covering both.
    pub fn to(self, other: Span) -> Span {
        Span { file: self.file, start: self.start.min(other.start), end: self.end.max(other.end) }
    }
    /// An empty span at the start of this one.
    pub fn head(self) -> Span {
        Span { end: self.start, ..self }
    }
    pub fn range(self) -> std::ops::Range<usize> {
        self.start as usize..self.end as usize
    }
}

/// How bad a diagnostic is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Severity {
    Error,
    Warning,
}

/// A place in the source with a short message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Label {
    pub span: Span,
    pub message: String,
    /// The primary label is underlined with `^`; secondary ones with `-`.
    pub primary: bool,
}

/// An error or warning with its code, message, labelled places and notes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Diagnostic {
    pub severity: Severity,
    pub code: Code,
    pub message: String,
    pub labels: Vec<Label>,
    pub notes: Vec<String>,
}

impl Diagnostic {
    pub fn error(code: Code, message: impl Into<String>) -> Diagnostic {
        Diagnostic { severity: Severity::Error, code, message: message.into(), labels: Vec::new(), notes: Vec::new() }
    }
    pub fn warning(code: Code, message: impl Into<String>) -> Diagnostic {
        Diagnostic { severity: Severity::Warning, ..Diagnostic::error(code, message) }
    }
    /// Adds the primary label.
    pub fn with_primary(mut self, span: Span, message: impl Into<String>) -> Diagnostic {
        self.labels.push(Label { span, message: message.into(), primary: true });
        self
    }
    /// Adds a secondary label.
    pub fn with_secondary(mut self, span: Span, message: impl Into<String>) -> Diagnostic {
        self.labels.push(Label { span, message: message.into(), primary: false });
        self
    }
    pub fn with_note(mut self, note: impl Into<String>) -> Diagnostic {
        self.notes.push(note.into());
        self
    }
    pub fn is_error(&self) -> bool {
        self.severity == Severity::Error
    }
    /// The span of the primary label, if any.
    pub fn primary_span(&self) -> Option<Span> {
        self.labels.iter().find(|l| l.primary).map(|l| l.span)
    }
}

/// Diagnostic codes. The first digit groups them: 1 syntax, 2 names and structure,
/// 3 arguments and values, 4 shapes, 5 adaptation rules, 6 variants, 7 weights, 9 limits
/// and bugs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Code {
    /// The parser expected something else here.
    Syntax,
    /// A bracket was opened and never closed.
    Unclosed,
    /// A literal that cannot be represented (integer too large).
    BadLiteral,
    /// A file a `use` names cannot be read.
    UseFile,
    /// A name that is not bound where it is used.
    UnknownName,
    /// Two things with the same name in one place.
    DuplicateName,
    /// A block that calls itself, directly or through others.
    RecursiveBlock,
    /// A statement that does not belong where it is (an `input` inside a block, ...).
    Misplaced,
    /// The file has no model, or several.
    ModelCount,
    /// A value computed but never used by any output.
    Unused,
    /// A name that is accepted but is probably a typo (a symbolic dimension close to a
    /// model parameter).
    LikelyTypo,
    /// Wrong number or names of arguments.
    BadArgument,
    /// A value of the wrong type.
    TypeMismatch,
    /// A value out of its allowed range (negative stride, zero heads, ...).
    BadValue,
    /// A layer with parameters that has no name, so its weights could not be bound.
    AnonymousParams,
    /// Shapes that do not fit together.
    ShapeMismatch,
    /// A selector of an adaptation rule that selects nothing or the wrong kind of layer.
    BadSelector,
    /// Two adaptation rules that claim one parameter in conflicting ways.
    RuleConflict,
    /// An adaptation rule option that is unknown or has a bad value.
    BadOption,
    /// A problem in the variants section.
    BadVariant,
    /// A weights file that does not fit the model (missing, extra, misshapen tensors).
    Weights,
    /// A variant's parameter files do not fit the adaptation rules (a tensor the rules do
    /// not make per-variant, an undeclared key, a PEFT config that disagrees with a rule).
    VariantWeights,
    /// A resource limit (nesting, node count, loop length) was exceeded.
    Limit,
    /// A bug in readi: an invariant of the IR does not hold.
    Internal,
}

impl Code {
    /// The stable code printed in brackets, `E0101`.
    pub fn as_str(self) -> &'static str {
        match self {
            Code::Syntax => "E0101",
            Code::Unclosed => "E0102",
            Code::BadLiteral => "E0103",
            Code::UseFile => "E0104",
            Code::UnknownName => "E0201",
            Code::DuplicateName => "E0202",
            Code::RecursiveBlock => "E0203",
            Code::Misplaced => "E0204",
            Code::ModelCount => "E0205",
            Code::Unused => "W0206",
            Code::LikelyTypo => "W0207",
            Code::BadArgument => "E0301",
            Code::TypeMismatch => "E0302",
            Code::BadValue => "E0303",
            Code::AnonymousParams => "E0304",
            Code::ShapeMismatch => "E0401",
            Code::BadSelector => "E0501",
            Code::RuleConflict => "E0502",
            Code::BadOption => "E0503",
            Code::BadVariant => "E0601",
            Code::Weights => "E0701",
            Code::VariantWeights => "E0702",
            Code::Limit => "E0901",
            Code::Internal => "E0999",
        }
    }
}

/// A list of diagnostics collected by one stage.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Diagnostics(pub Vec<Diagnostic>);

impl Diagnostics {
    pub fn push(&mut self, d: Diagnostic) {
        self.0.push(d);
    }
    pub fn has_errors(&self) -> bool {
        self.0.iter().any(Diagnostic::is_error)
    }
    pub fn error_count(&self) -> usize {
        self.0.iter().filter(|d| d.is_error()).count()
    }
    pub fn warning_count(&self) -> usize {
        self.0.len() - self.error_count()
    }
    pub fn extend(&mut self, other: Diagnostics) {
        self.0.extend(other.0);
    }
    pub fn iter(&self) -> std::slice::Iter<'_, Diagnostic> {
        self.0.iter()
    }
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
    /// Sorts by file and position, errors before warnings at the same place.
    pub fn sort(&mut self) {
        self.0.sort_by_key(|d| (d.primary_span().map(|s| (s.file, s.start)), d.severity));
    }
}

/// The source files of one run, for rendering diagnostics and computing line:col.
#[derive(Default)]
pub struct SourceMap {
    files: SimpleFiles<String, String>,
    count: u32,
}

impl SourceMap {
    pub fn new() -> SourceMap {
        SourceMap::default()
    }

    /// Registers a file and returns its id.
    pub fn add(&mut self, name: impl Into<String>, text: impl Into<String>) -> FileId {
        let id = self.files.add(name.into(), text.into());
        self.count += 1;
        FileId(id as u32)
    }

    /// The text of a file.
    pub fn text(&self, file: FileId) -> &str {
        self.files.get(file.0 as usize).map(|f| f.source().as_str()).unwrap_or("")
    }

    /// The name of a file as registered.
    pub fn name(&self, file: FileId) -> &str {
        self.files.get(file.0 as usize).map(|f| f.name().as_str()).unwrap_or("<unknown>")
    }

    /// One-based line and column of the start of a span.
    pub fn line_col(&self, span: Span) -> (usize, usize) {
        use codespan_reporting::files::Files;
        let id = span.file.0 as usize;
        let start = span.start as usize;
        match self.files.location(id, start) {
            Ok(loc) => (loc.line_number, loc.column_number),
            Err(_) => (0, 0),
        }
    }

    /// `file:line:col` of the start of a span.
    pub fn locate(&self, span: Span) -> String {
        let (l, c) = self.line_col(span);
        format!("{}:{}:{}", self.name(span.file), l, c)
    }

    /// Renders one diagnostic, with ANSI colours when `color` is set.
    pub fn render(&self, diag: &Diagnostic, color: bool) -> String {
        let config = term::Config::default();
        let cs_diag = self.to_codespan(diag);
        if color {
            let mut buf = term::termcolor::Buffer::ansi();
            match term::emit_to_write_style(&mut buf, &config, &self.files, &cs_diag) {
                Ok(()) => String::from_utf8_lossy(buf.as_slice()).into_owned(),
                Err(_) => self.render_fallback(diag),
            }
        } else {
            let mut out = String::new();
            match term::emit_to_string(&mut out, &config, &self.files, &cs_diag) {
                Ok(()) => out,
                Err(_) => self.render_fallback(diag),
            }
        }
    }

    /// Renders every diagnostic, then a one-line summary when there are errors.
    pub fn render_all(&self, diags: &Diagnostics, color: bool) -> String {
        let mut out = String::new();
        for d in diags.iter() {
            out.push_str(&self.render(d, color));
        }
        out
    }

    fn to_codespan(&self, diag: &Diagnostic) -> cs::Diagnostic<usize> {
        let base = match diag.severity {
            Severity::Error => cs::Diagnostic::error(),
            Severity::Warning => cs::Diagnostic::warning(),
        };
        let text_len = |f: FileId| self.text(f).len();
        let labels = diag
            .labels
            .iter()
            .map(|l| {
                // Clamp to the file and to char boundaries: a label must never make the
                // renderer fail.
                let len = text_len(l.span.file);
                let text = self.text(l.span.file);
                let mut s = (l.span.start as usize).min(len);
                let mut e = (l.span.end as usize).clamp(s, len);
                while s > 0 && !text.is_char_boundary(s) {
                    s -= 1;
                }
                while e < len && !text.is_char_boundary(e) {
                    e += 1;
                }
                let style = if l.primary { cs::LabelStyle::Primary } else { cs::LabelStyle::Secondary };
                cs::Label::new(style, l.span.file.0 as usize, s..e).with_message(l.message.clone())
            })
            .collect();
        base.with_code(diag.code.as_str())
            .with_message(diag.message.clone())
            .with_labels(labels)
            .with_notes(diag.notes.clone())
    }

    fn render_fallback(&self, diag: &Diagnostic) -> String {
        let place = diag.primary_span().map(|s| self.locate(s)).unwrap_or_default();
        format!("{}[{}]: {} at {}\n", "error", diag.code.as_str(), diag.message, place)
    }
}

/// Levenshtein distance, for "did you mean" suggestions.
pub fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    let mut cur = vec![0; b.len() + 1];
    for (i, ca) in a.chars().enumerate() {
        cur[0] = i + 1;
        for (j, &cb) in b.iter().enumerate() {
            let cost = usize::from(ca != cb);
            cur[j + 1] = (prev[j] + cost).min(prev[j + 1] + 1).min(cur[j] + 1);
        }
        std::mem::swap(&mut prev, &mut cur);
    }
    prev[b.len()]
}

/// The candidate closest to `name`, if it is close enough to be a likely typo.
pub fn suggest<'a>(name: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    let len = name.chars().count();
    if len < 3 {
        // One- and two-letter names are close to everything.
        return None;
    }
    let limit = (len / 3).clamp(1, 3);
    candidates
        .into_iter()
        .filter(|c| *c != name)
        .map(|c| (edit_distance(name, c), c))
        .filter(|(d, _)| *d <= limit)
        .min_by_key(|(d, c)| (*d, *c))
        .map(|(_, c)| c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edit_distance_matches_hand_computed_values() {
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        assert_eq!(edit_distance("", "abc"), 3);
        assert_eq!(edit_distance("padding", "padding"), 0);
        assert_eq!(edit_distance("paddng", "padding"), 1);
    }

    #[test]
    fn suggest_picks_close_names_only() {
        let names = ["padding", "stride", "dilation"];
        assert_eq!(suggest("paddin", names), Some("padding"));
        assert_eq!(suggest("strid", names), Some("stride"));
        assert_eq!(suggest("kernel", names), None);
    }

    #[test]
    fn rendering_shows_file_line_col_and_caret() {
        let mut sm = SourceMap::new();
        let f = sm.add("a.readi", "model m {\n  x = y\n}\n");
        let d =
            Diagnostic::error(Code::UnknownName, "unknown name `y`").with_primary(Span::new(f, 16, 17), "not defined");
        let out = sm.render(&d, false);
        assert!(out.contains("a.readi:2:7"), "{out}");
        assert!(out.contains("x = y"), "{out}");
        assert!(out.contains('^'), "{out}");
        assert!(out.contains("E0201"), "{out}");
    }

    #[test]
    fn out_of_range_labels_do_not_break_rendering() {
        let mut sm = SourceMap::new();
        let f = sm.add("a.readi", "é");
        let d = Diagnostic::error(Code::Syntax, "x").with_primary(Span::new(f, 1, 99), "here");
        let out = sm.render(&d, false);
        assert!(out.contains("a.readi:1:1"), "{out}");
    }
}
