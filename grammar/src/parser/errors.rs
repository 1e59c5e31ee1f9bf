//! Recovery and the wording of syntax errors: re-parsing a swallowed piece with its
//! `*_only` entry rule, turning pest's error (position, expected rules and tokens) into a
//! diagnostic, and the words for what was expected and what was found.
//!
//! Separate because it is the one part of the parser that reads pest's errors rather than
//! its trees, and because its wording is what the error snapshots pin down.

use pest::Parser;
use pest::error::{ErrorVariant, InputLocation};
use pest::iterators::Pair;

use super::{Builder, ReadiParser, Rule, comment_start};
use crate::diag::{Code, Diagnostic, Span};

impl<'s> Builder<'s> {
    /// Re-parses a swallowed piece with its `*_only` rule and reports where and why it
    /// fails.
    pub(super) fn recover(&mut self, pair: Pair<'_, Rule>, rule: Rule) {
        let offset = pair.as_span().start();
        let text = pair.as_str();
        match ReadiParser::parse(rule, text) {
            Err(e) => self.push_pest_error(e, offset, rule),
            Ok(_) => {
                // The piece parses alone but not in place: it is in the wrong section.
                let span = Span::new(self.file, offset, offset + text.trim_end().len());
                self.diags.push(
                    Diagnostic::error(Code::Syntax, format!("{} is not allowed here", what(rule)))
                        .with_primary(span, "unexpected here"),
                );
            }
        }
    }

    pub(super) fn push_pest_error(&mut self, e: pest::error::Error<Rule>, offset: usize, entry: Rule) {
        let loc = match e.location {
            InputLocation::Pos(p) => p,
            InputLocation::Span((s, _)) => s,
        };
        let positives = match &e.variant {
            ErrorVariant::ParsingError { positives, .. } => positives.clone(),
            ErrorVariant::CustomError { message } => {
                let span = Span::new(self.file, offset + loc, offset + loc);
                self.diags.push(
                    Diagnostic::error(Code::Limit, format!("the parser gave up: {message}")).with_primary(span, "here"),
                );
                return;
            }
        };
        // pest locates the error at the furthest *rule* attempt; the detailed attempts also
        // know failed literal tokens (`on`, `->`), which may be further along.
        let (pos, rules, tokens) = match e.parse_attempts() {
            Some(a) if a.max_position >= loc => {
                // The attempts' call stacks are collapsed to coarse parents (`stmt`), which
                // would only add noise; pest's positives are precise but only at `loc`.
                let rules = if a.max_position == loc { positives.clone() } else { Vec::new() };
                let tokens = a.expected_tokens().iter().map(|t| t.to_string()).collect();
                (a.max_position, rules, tokens)
            }
            _ => (loc, positives.clone(), Vec::new()),
        };
        let mut pos = pos;
        let mut expected = describe_expected(&rules, &tokens, pos == 0, entry);
        if expected == NOTHING_EXPECTED && pos != loc {
            // The detailed attempts only know negative lookaheads here; pest's own
            // positives at its location say more.
            pos = loc;
            expected = describe_expected(&positives, &[], pos == 0, entry);
        }
        let abs = offset + pos;
        let found = found_token(self.src, abs);
        let span = Span::new(self.file, abs, abs + found.len_in_source);
        let message = format!("expected {expected}, found {}", found.description);
        let mut d = Diagnostic::error(Code::Syntax, message).with_primary(span, format!("expected {expected}"));
        // A piece that fails at its very start may be the tail of the statement before it.
        let from = if pos == 0 { self.prev_stmt.unwrap_or(offset) } else { offset };
        if let Some(spill) = spilled_line_end(self.src, from, abs) {
            // Newlines do not end statements, so a dangling operator or an unclosed
            // bracket pulls the next line in; point at where that happened.
            d = d
                .with_secondary(Span::new(self.file, spill, spill + 1), "the statement continues past this line")
                .with_note("is an operand, an argument or a closing bracket missing at the end of that line?");
        }
        self.diags.push(d);
    }
}

/// If the piece starting at `start` runs over a line break before `pos`, the offset of
/// the last character before the first such break (skipping blank space and comments).
fn spilled_line_end(src: &str, start: usize, pos: usize) -> Option<usize> {
    let piece = src.get(start..pos)?;
    let nl = piece.find('\n')?;
    if piece[nl..].trim().is_empty() {
        return None;
    }
    let first_line = &piece[..nl];
    let code = &first_line[..comment_start(first_line).unwrap_or(first_line.len())];
    let end = code.trim_end().len();
    (end > 0).then(|| start + end - code[..end].chars().next_back().map_or(1, char::len_utf8))
}

/// What a recovery entry rule parses, in words.
fn what(rule: Rule) -> &'static str {
    match rule {
        Rule::item_only => "this item",
        Rule::stmt_only => "this statement",
        Rule::seq_item_only => "this sequence item",
        Rule::rule_only => "this rule",
        Rule::decl_only => "this declaration",
        _ => "this",
    }
}

struct Found {
    description: String,
    len_in_source: usize,
}

/// The token at `pos`, for "found `kernel`".
fn found_token(src: &str, pos: usize) -> Found {
    let rest = src.get(pos..).unwrap_or("");
    let Some(c) = rest.chars().next() else {
        return Found { description: "end of file".into(), len_in_source: 0 };
    };
    if c == '\n' || c == '\r' {
        return Found { description: "end of line".into(), len_in_source: 0 };
    }
    let len = if c.is_alphanumeric() || c == '_' {
        rest.find(|ch: char| !(ch.is_alphanumeric() || ch == '_' || ch == '.')).unwrap_or(rest.len())
    } else {
        // Two-character operators read better whole.
        let two: String = rest.chars().take(2).collect();
        if ["==", "!=", "<=", ">=", "**", "//", "->", ".."].contains(&two.as_str()) { 2 } else { c.len_utf8() }
    };
    let tok = &rest[..len];
    let tok = tok.trim_end_matches('.');
    let len = tok.len().max(c.len_utf8());
    Found { description: format!("`{}`", &rest[..len]), len_in_source: len }
}

/// Words for a grammar rule that was expected. `None` hides rules that are covered by a
/// broader description.
fn rule_words(rule: Rule) -> Option<&'static str> {
    Some(match rule {
        Rule::ident | Rule::var => "a name",
        Rule::layer_name | Rule::quoted_name => "a layer name",
        Rule::name_text | Rule::name_interp => return None,
        Rule::int => "an integer",
        Rule::float | Rule::number => "a number",
        Rule::string | Rule::string_body => "a string",
        Rule::boolean => "`true` or `false`",
        Rule::expr
        | Rule::unary
        | Rule::postfix_expr
        | Rule::paren
        | Rule::call
        | Rule::list
        | Rule::list_comp
        | Rule::if_expr
        | Rule::seq_expr
        | Rule::neg_op
        | Rule::not_op => "an expression",
        Rule::or_op
        | Rule::and_op
        | Rule::eq_op
        | Rule::ne_op
        | Rule::le_op
        | Rule::ge_op
        | Rule::lt_op
        | Rule::gt_op
        | Rule::add_op
        | Rule::sub_op
        | Rule::pow_op
        | Rule::mul_op
        | Rule::floordiv_op
        | Rule::div_op
        | Rule::mod_op => "an operator",
        Rule::member => "`.`",
        Rule::index => "`[`",
        Rule::call_args => "`(`",
        Rule::arg => "an argument",
        Rule::range => "a range `a..b`",
        Rule::body => "`{`",
        Rule::stmt
        | Rule::input_stmt
        | Rule::output_stmt
        | Rule::let_stmt
        | Rule::if_stmt
        | Rule::return_stmt
        | Rule::scope_stmt
        | Rule::named_stmt => "a statement",
        Rule::tensor_type => "a tensor type such as `f32[N, 3, 224, 224]`",
        Rule::dtype => "an element type (`f32`, `f16`, `bf16`, `i64`, `i32` or `bool`)",
        Rule::modality => "`@` and a modality",
        Rule::optional_flag => "`optional`",
        Rule::type_name => "a type (`tensor`, `int`, `float`, `bool`, `str` or `list`)",
        Rule::param | Rule::param_list => "a parameter",
        Rule::item | Rule::use_def | Rule::block_def | Rule::model_def | Rule::adapt_def | Rule::variants_def => {
            "`use`, `block`, `model`, `adapt` or `variants`"
        }
        Rule::seq_item | Rule::seq_for | Rule::seq_if | Rule::seq_body => "a sequence item such as `conv2d(64, 3)`",
        Rule::adapt_rule | Rule::tune_rule | Rule::lora_rule | Rule::adapter_rule => {
            "a rule (`tune`, `lora` or `adapter`)"
        }
        Rule::rule_option => "an option such as `rank=4`",
        Rule::adapt_scopes | Rule::adapt_scope => "a scope such as `camera` or `missing=lidar`",
        Rule::selector | Rule::sel_item | Rule::op_kinds => "a selector such as `batchnorm` or `head.*`",
        Rule::scope_list | Rule::pattern => "a block name or path pattern",
        Rule::variant_decl | Rule::axis_decl | Rule::missing_decl | Rule::select_decl | Rule::meld_decl => {
            "a declaration (`axis`, `missing`, `select` or `meld`)"
        }
        Rule::select_source | Rule::meta_source | Rule::stat_source => {
            "a source such as `brightness(image)` or `meta(\"fog\")`"
        }
        Rule::select_map | Rule::threshold_map | Rule::nearest_map => "`{` thresholds `}` or `nearest`",
        Rule::threshold_arm | Rule::threshold_cmp | Rule::else_kw => "`< value -> level` or `else -> level`",
        Rule::level_ref | Rule::clear_kw => "a level or `clear`",
        Rule::meld_weight => "`modality = lambda`",
        Rule::EOI => "end of input",
        _ => return None,
    })
}

/// What [`describe_expected`] says when it has nothing better.
const NOTHING_EXPECTED: &str = "something else";

/// Keywords worth naming when they are what the parser expected; other literal tokens
/// that are words (dtype names, exponent letters) are covered by a rule's description.
const STRUCTURAL_WORDS: &[&str] = &["else", "then", "in", "on", "before", "for", "optional", "clear", "nearest", "by"];

/// Literal tokens that continue an operand; hidden when "an operator" is listed.
const OPERATOR_TOKENS: &[&str] =
    &[".", "[", "(", "!=", "%", "*", "**", "+", "-", "/", "//", "<", "<=", "==", ">", ">=", "and", "or"];

/// Literal tokens that start an expression; hidden when "an expression" is listed.
const EXPR_START_TOKENS: &[&str] = &["(", "[", "-", "\"", "{", "*", "**"];

/// Builds "`,`, `)` or an operator" from what the parser tried at the failure position.
fn describe_expected(rules: &[Rule], tokens: &[String], at_start: bool, entry: Rule) -> String {
    if at_start {
        // Nothing of the piece parsed: say what may start here, in the section's terms.
        return match entry {
            Rule::stmt_only => "a statement (a layer name, `let`, `input`, `output`, `if` or `return`) or `}`".into(),
            Rule::seq_item_only => "a sequence item such as `conv2d(64, 3)`, `for` or `}`".into(),
            Rule::rule_only => "a rule (`tune`, `lora` or `adapter`) or `}`".into(),
            Rule::decl_only => "a declaration (`axis`, `missing`, `select` or `meld`) or `}`".into(),
            Rule::item_only | Rule::file => "`use`, `block`, `model`, `adapt` or `variants`".into(),
            _ => NOTHING_EXPECTED.into(),
        };
    }
    let mut words: Vec<String> = Vec::new();
    fn push(words: &mut Vec<String>, w: String) {
        if !words.contains(&w) {
            words.push(w);
        }
    }
    for &r in rules {
        if let Some(w) = rule_words(r) {
            push(&mut words, w.to_string());
        }
    }
    if words.iter().any(|w| w == "an operator") {
        // After an operand, `.`/`[` continuations are operators too.
        words.retain(|w| w != "`.`" && w != "`[`" && w != "`(`");
    }
    let has_op = words.iter().any(|w| w == "an operator");
    let has_expr =
        words.iter().any(|w| w == "an expression" || w == "an argument" || w == "a name" || w == "a layer name");
    let has_rule_words = !words.is_empty();
    let has_pattern = words.iter().any(|w| w.contains("pattern"));
    let has_number = words.iter().any(|w| w.contains("a number") || w.contains("a level"));
    for t in tokens {
        let t = t.as_str();
        let is_word = t.chars().next().is_some_and(|c| c.is_alphanumeric() || c == '_');
        if t.trim().is_empty() || t == "#" || t == ";" || t.contains("..") {
            continue;
        }
        if is_word && (!STRUCTURAL_WORDS.contains(&t) || (has_rule_words && t.len() == 1)) {
            continue;
        }
        if has_expr && EXPR_START_TOKENS.contains(&t) {
            continue;
        }
        if has_op && OPERATOR_TOKENS.contains(&t) {
            continue;
        }
        if has_pattern && ["*", "**", "{", "_"].contains(&t) {
            continue;
        }
        if has_number && t == "-" {
            continue;
        }
        if words.iter().any(|w| w.contains(&format!("`{t}`"))) {
            continue;
        }
        push(&mut words, format!("`{t}`"));
    }
    if words.iter().any(|w| w == "an expression") {
        words.retain(|w| w != "a name");
    }
    // Punctuation first, then words: "`,`, `)` or an operator".
    words.sort_by_key(|w| (!w.starts_with('`'), w == "end of input"));
    match words.len() {
        0 => NOTHING_EXPECTED.into(),
        1 => words.remove(0),
        _ => {
            let last = words.pop().unwrap_or_default();
            format!("{} or {}", words.join(", "), last)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diag::FileId;
    use crate::parser::parse;
    use crate::parser::tests::first_error;

    #[test]
    fn missing_comma_is_located_and_explained() {
        let src = "model m {\n  c = conv2d(x, 64 kernel=3)\n}\n";
        let d = first_error(src);
        assert_eq!(d.code, Code::Syntax);
        let s = d.primary_span().expect("span");
        assert_eq!(&src[s.range()], "kernel");
        assert!(d.message.contains("`,`"), "{}", d.message);
        assert!(d.message.contains("`)`"), "{}", d.message);
        assert!(d.message.contains("found `kernel`"), "{}", d.message);
    }

    #[test]
    fn statement_start_error_names_a_layer_name_or_brace() {
        let d = first_error("model m {\n  = conv2d(x)\n}\n");
        assert!(d.message.contains("a layer name"), "{}", d.message);
        assert!(d.message.contains("`}`"), "{}", d.message);
    }

    #[test]
    fn several_errors_are_reported_in_one_run() {
        let p = parse(FileId(0), "model m {\n  a = f(x,,)\n  b = 3 +\n  c = ok(x)\n}\n");
        assert_eq!(p.diagnostics.error_count(), 2, "{:#?}", p.diagnostics);
        // The good statement after the broken ones survives.
        assert_eq!(p.file.models().next().map(|m| m.body.stmts.len()), Some(1));
    }
}
