//! From source text to the typed AST, with recovery and readable syntax errors.
//!
//! The grammar (`readi.pest`) has recovery productions (`stmt_error`, `seq_error`,
//! `rule_error`, `decl_error`, `item_error`) that swallow one broken statement or item, so
//! a parse always yields a tree. Each swallowed piece is then parsed again on its own with
//! the matching `*_only` entry rule; that second parse fails at the precise place, and its
//! expected-set is turned into words ("expected `,` or `)`, found `kernel`").
//!
//! There is one `parse_<rule>` function per grammar rule. Resource limits (nesting depth,
//! operator chain length, literal ranges) are enforced here so that no input can make a
//! later stage recurse without bound.
//!
//! The parse functions are grouped as the grammar's sections are: `items` (the file, its
//! items and the statements of a body), `expr` (expressions and `seq`), `sections` (the
//! `adapt` and `variants` sections) and `errors` (recovery and the wording of syntax
//! errors). This module holds the entry point, the parser state and the span helpers.

mod errors;
mod expr;
mod items;
mod sections;

use pest::Parser;
use pest::iterators::Pair;

use crate::ast::*;
use crate::diag::{Code, Diagnostic, Diagnostics, FileId, Span};

#[derive(pest_derive::Parser)]
#[grammar = "readi.pest"]
struct ReadiParser;

/// Maximum bracket nesting depth of a source file.
pub const MAX_NESTING: usize = 32;
/// Maximum weight of one expression: nested sub-expressions plus operators in a chain.
pub const MAX_EXPR_WEIGHT: usize = 96;
/// Maximum size of a source file in bytes.
pub const MAX_SOURCE_BYTES: usize = 4 << 20;

/// The result of parsing one file: a tree (possibly partial) and the syntax errors found.
#[derive(Debug)]
pub struct Parsed {
    pub file: SourceFile,
    pub diagnostics: Diagnostics,
}

/// Parses a whole `.readi` file. The tree is complete when `diagnostics` has no errors;
/// otherwise it holds every item and statement that did parse.
pub fn parse(file: FileId, src: &str) -> Parsed {
    configure_pest();
    let mut p = Builder { file, src, diags: Diagnostics::default(), expr_weight: 0, prev_stmt: None };
    if src.len() > MAX_SOURCE_BYTES {
        p.diags.push(
            Diagnostic::error(
                Code::Limit,
                format!("source file is {} bytes; the limit is {MAX_SOURCE_BYTES}", src.len()),
            )
            .with_primary(Span::new(file, 0, 0), "file too large"),
        );
        return Parsed { file: SourceFile { items: vec![] }, diagnostics: p.diags };
    }
    let unclosed = match scan_brackets(file, src) {
        BracketScan::TooDeep(d) => {
            p.diags.push(d);
            return Parsed { file: SourceFile { items: vec![] }, diagnostics: p.diags };
        }
        BracketScan::Unclosed(d) => Some(d),
        BracketScan::Balanced => None,
    };
    let items = match ReadiParser::parse(Rule::file, src) {
        Ok(mut pairs) => match pairs.next() {
            Some(file_pair) => p.parse_file(file_pair),
            None => vec![],
        },
        Err(e) => {
            p.push_pest_error(e, 0, Rule::file);
            vec![]
        }
    };
    if let Some(d) = unclosed {
        // The parser's own complaint about that is "found end of file"; the bracket is the
        // better place to point at.
        let end = src.len() as u32;
        p.diags.0.retain(|x| x.primary_span().is_none_or(|s| s.start < end));
        p.diags.push(d);
    }
    p.diags.sort();
    Parsed { file: SourceFile { items }, diagnostics: p.diags }
}

fn configure_pest() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // Literal tokens in expected-sets ("`,` or `)`") need the detailed attempt tracking.
        pest::set_error_detail(true);
        // A generous bound on rule calls: a pathological input fails cleanly instead of
        // backtracking for minutes.
        pest::set_call_limit(std::num::NonZeroUsize::new(50_000_000));
    });
}

enum BracketScan {
    Balanced,
    Unclosed(Diagnostic),
    TooDeep(Diagnostic),
}

/// Checks bracket nesting outside comments and strings before pest runs: refuses inputs
/// nested deeper than [`MAX_NESTING`], and finds the opener of an unclosed bracket.
fn scan_brackets(file: FileId, src: &str) -> BracketScan {
    let bytes = src.as_bytes();
    let mut stack: Vec<(u8, usize)> = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'#' => {
                while i < bytes.len() && bytes[i] != b'\n' {
                    i += 1;
                }
            }
            b'"' => {
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' && bytes[i] != b'\n' {
                    i += 1;
                }
            }
            c @ (b'(' | b'[' | b'{') => {
                stack.push((c, i));
                if stack.len() > MAX_NESTING {
                    return BracketScan::TooDeep(
                        Diagnostic::error(Code::Limit, format!("brackets nested more than {MAX_NESTING} levels deep"))
                            .with_primary(Span::new(file, i, i + 1), "too deep")
                            .with_note("split the expression with `let` or the network into blocks"),
                    );
                }
            }
            c @ (b')' | b']' | b'}') => {
                let open = match c {
                    b')' => b'(',
                    b']' => b'[',
                    _ => b'{',
                };
                // A mismatched closer is the parser's to report; only pop a match.
                if stack.last().is_some_and(|(o, _)| *o == open) {
                    stack.pop();
                }
            }
            _ => {}
        }
        i += 1;
    }
    // The innermost unclosed bracket is the likely culprit.
    match stack.last() {
        None => BracketScan::Balanced,
        Some(&(c, at)) => {
            let (open, close) = match c {
                b'(' => ("(", ")"),
                b'[' => ("[", "]"),
                _ => ("{", "}"),
            };
            BracketScan::Unclosed(
                Diagnostic::error(Code::Unclosed, format!("this `{open}` is never closed"))
                    .with_primary(Span::new(file, at, at + 1), format!("unclosed `{open}`"))
                    .with_note(format!("add the matching `{close}`")),
            )
        }
    }
}

struct Builder<'s> {
    file: FileId,
    src: &'s str,
    diags: Diagnostics,
    /// Weight of the expressions being built (see [`MAX_EXPR_WEIGHT`]).
    expr_weight: usize,
    /// Start of the statement parsed just before the one being recovered, if any.
    prev_stmt: Option<usize>,
}

/// Inner pairs of a pair, as a vector (the grammar is small; clarity beats laziness).
fn inner(pair: Pair<'_, Rule>) -> Vec<Pair<'_, Rule>> {
    pair.into_inner().collect()
}

impl<'s> Builder<'s> {
    /// The span of a pair without the whitespace and comments pest skipped at its end
    /// (it keeps what it skipped before an optional part that was then absent).
    fn span(&self, pair: &Pair<'_, Rule>) -> Span {
        let s = pair.as_span();
        Span::new(self.file, s.start(), s.start() + trimmed_len(s.as_str()))
    }

    fn ident(&self, pair: Pair<'_, Rule>) -> Ident {
        Ident { span: self.span(&pair), name: pair.as_str().to_string() }
    }
}

/// The length of `text` without trailing whitespace and a trailing `# comment`.
fn trimmed_len(text: &str) -> usize {
    let mut t = text;
    loop {
        let before = t.len();
        t = t.trim_end();
        let line_start = t.rfind('\n').map(|i| i + 1).unwrap_or(0);
        if let Some(hash) = comment_start(&t[line_start..]) {
            t = &t[..line_start + hash];
        }
        if t.len() == before {
            return t.len();
        }
    }
}

/// Where a `#` comment starts in one line, ignoring `#` inside strings.
fn comment_start(line: &str) -> Option<usize> {
    let mut in_string = false;
    for (i, c) in line.char_indices() {
        match c {
            '"' => in_string = !in_string,
            '#' if !in_string => return Some(i),
            _ => {}
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    // Helpers shared with the tests of the submodules.

    pub(super) fn parse_ok(src: &str) -> SourceFile {
        let p = parse(FileId(0), src);
        assert!(p.diagnostics.is_empty(), "{:#?}", p.diagnostics);
        p.file
    }

    pub(super) fn first_error(src: &str) -> Diagnostic {
        let p = parse(FileId(0), src);
        p.diagnostics.0.into_iter().next().expect("an error")
    }

    pub(super) fn model_stmts(f: &SourceFile) -> &[Stmt] {
        &f.models().next().expect("a model").body.stmts
    }

    #[test]
    fn unclosed_brace_points_at_the_opener() {
        let src = "model m {\n  a = f(x)\n";
        let d = first_error(src);
        assert_eq!(d.code, Code::Unclosed);
        assert_eq!(d.primary_span().map(|s| s.start), Some(8));
    }

    #[test]
    fn deep_nesting_is_refused_without_recursion() {
        let src = format!("model m {{ let a = {}1{} }}", "(".repeat(10_000), ")".repeat(10_000));
        let d = first_error(&src);
        assert_eq!(d.code, Code::Limit);
    }
}
