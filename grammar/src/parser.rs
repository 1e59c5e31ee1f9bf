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

use pest::Parser;
use pest::error::{ErrorVariant, InputLocation};
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

    // ---------------------------------------------------------------------------------
    // Items
    // ---------------------------------------------------------------------------------

    fn parse_file(&mut self, pair: Pair<'_, Rule>) -> Vec<Item> {
        let mut items = Vec::new();
        for p in pair.into_inner() {
            match p.as_rule() {
                Rule::item => {
                    if let Some(it) = self.parse_item(p) {
                        items.push(it);
                    }
                }
                Rule::item_error => self.recover(p, Rule::item_only),
                _ => {}
            }
        }
        items
    }

    fn parse_item(&mut self, pair: Pair<'_, Rule>) -> Option<Item> {
        let p = pair.into_inner().next()?;
        Some(match p.as_rule() {
            Rule::block_def => Item::Block(self.parse_block_def(p)?),
            Rule::model_def => Item::Model(self.parse_model_def(p)?),
            Rule::adapt_def => Item::Adapt(self.parse_adapt_def(p)),
            Rule::variants_def => Item::Variants(self.parse_variants_def(p)),
            _ => return None,
        })
    }

    fn parse_block_def(&mut self, pair: Pair<'_, Rule>) -> Option<BlockDef> {
        let span = self.span(&pair);
        let mut it = pair.into_inner();
        let name = self.ident(it.next()?);
        let params = self.parse_param_list(it.next()?);
        let body = self.parse_body(it.next()?);
        Some(BlockDef { name, params, body, span })
    }

    fn parse_model_def(&mut self, pair: Pair<'_, Rule>) -> Option<ModelDef> {
        let span = self.span(&pair);
        let mut name = None;
        let mut params = Vec::new();
        let mut body = None;
        for p in pair.into_inner() {
            match p.as_rule() {
                Rule::ident => name = Some(self.ident(p)),
                Rule::param_list => params = self.parse_param_list(p),
                Rule::body => body = Some(self.parse_body(p)),
                _ => {}
            }
        }
        Some(ModelDef { name: name?, params, body: body?, span })
    }

    fn parse_param_list(&mut self, pair: Pair<'_, Rule>) -> Vec<Param> {
        pair.into_inner().filter_map(|p| self.parse_param(p)).collect()
    }

    fn parse_param(&mut self, pair: Pair<'_, Rule>) -> Option<Param> {
        let span = self.span(&pair);
        let mut it = pair.into_inner();
        let name = self.ident(it.next()?);
        let mut ty = None;
        let mut default = None;
        for p in it {
            match p.as_rule() {
                Rule::type_name => {
                    let t = match p.as_str() {
                        "tensor" => TypeName::Tensor,
                        "int" => TypeName::Int,
                        "float" => TypeName::Float,
                        "bool" => TypeName::Bool,
                        "str" => TypeName::Str,
                        _ => TypeName::List,
                    };
                    ty = Some((t, self.span(&p)));
                }
                Rule::expr => default = self.parse_expr(p),
                _ => {}
            }
        }
        Some(Param { name, ty, default, span })
    }

    // ---------------------------------------------------------------------------------
    // Statements
    // ---------------------------------------------------------------------------------

    fn parse_body(&mut self, pair: Pair<'_, Rule>) -> Body {
        let span = self.span(&pair);
        let mut stmts = Vec::new();
        self.prev_stmt = None;
        for p in pair.into_inner() {
            match p.as_rule() {
                Rule::stmt => {
                    let start = p.as_span().start();
                    if let Some(s) = self.parse_stmt(p) {
                        stmts.push(s);
                    }
                    self.prev_stmt = Some(start);
                }
                Rule::stmt_error => {
                    self.recover(p, Rule::stmt_only);
                    self.prev_stmt = None;
                }
                _ => {}
            }
        }
        self.prev_stmt = None;
        Body { stmts, span }
    }

    fn parse_stmt(&mut self, pair: Pair<'_, Rule>) -> Option<Stmt> {
        let span = self.span(&pair);
        let p = pair.into_inner().next()?;
        let kind = match p.as_rule() {
            Rule::input_stmt => StmtKind::Input(self.parse_input_stmt(p)?),
            Rule::output_stmt => self.parse_output_stmt(p)?,
            Rule::let_stmt => self.parse_let_stmt(p)?,
            Rule::if_stmt => self.parse_if_stmt(p)?,
            Rule::return_stmt => StmtKind::Return(self.parse_expr(p.into_inner().next()?)?),
            Rule::scope_stmt => self.parse_scope_stmt(p)?,
            Rule::named_stmt => self.parse_named_stmt(p)?,
            _ => return None,
        };
        Some(Stmt { kind, span })
    }

    fn parse_input_stmt(&mut self, pair: Pair<'_, Rule>) -> Option<InputDecl> {
        let mut it = pair.into_inner();
        let name = self.ident(it.next()?);
        let (dtype, dims) = self.parse_tensor_type(it.next()?)?;
        let mut modality = None;
        let mut optional = false;
        for p in it {
            match p.as_rule() {
                Rule::modality => modality = p.into_inner().next().map(|i| self.ident(i)),
                Rule::optional_flag => optional = true,
                _ => {}
            }
        }
        Some(InputDecl { name, dtype, dims, modality, optional })
    }

    fn parse_tensor_type(&mut self, pair: Pair<'_, Rule>) -> Option<((DType, Span), Vec<Expr>)> {
        let mut it = pair.into_inner();
        let d = it.next()?;
        let dtype = match d.as_str() {
            "f32" => DType::F32,
            "f16" => DType::F16,
            "bf16" => DType::BF16,
            "i64" => DType::I64,
            "i32" => DType::I32,
            _ => DType::Bool,
        };
        let dspan = self.span(&d);
        let dims = it.filter_map(|e| self.parse_expr(e)).collect();
        Some(((dtype, dspan), dims))
    }

    fn parse_output_stmt(&mut self, pair: Pair<'_, Rule>) -> Option<StmtKind> {
        let mut it = pair.into_inner();
        let name = self.ident(it.next()?);
        let value = match it.next() {
            Some(e) => Some(self.parse_expr(e)?),
            None => None,
        };
        Some(StmtKind::Output { name, value })
    }

    fn parse_let_stmt(&mut self, pair: Pair<'_, Rule>) -> Option<StmtKind> {
        let mut it = pair.into_inner();
        let name = self.ident(it.next()?);
        let value = self.parse_expr(it.next()?)?;
        Some(StmtKind::Let { name, value })
    }

    fn parse_if_stmt(&mut self, pair: Pair<'_, Rule>) -> Option<StmtKind> {
        let parts = inner(pair);
        let mut branches = Vec::new();
        let mut otherwise = None;
        let mut i = 0;
        while i < parts.len() {
            if parts[i].as_rule() == Rule::expr && i + 1 < parts.len() {
                let cond = self.parse_expr(parts[i].clone());
                let body = self.parse_body(parts[i + 1].clone());
                branches.push((cond?, body));
                i += 2;
            } else {
                otherwise = Some(self.parse_body(parts[i].clone()));
                i += 1;
            }
        }
        Some(StmtKind::If { branches, otherwise })
    }

    fn parse_scope_stmt(&mut self, pair: Pair<'_, Rule>) -> Option<StmtKind> {
        let mut it = pair.into_inner();
        let name = self.parse_layer_name(it.next()?)?;
        let body = self.parse_body(it.next()?);
        Some(StmtKind::Scope { name, body })
    }

    fn parse_named_stmt(&mut self, pair: Pair<'_, Rule>) -> Option<StmtKind> {
        let mut it = pair.into_inner();
        let name = self.parse_layer_name(it.next()?)?;
        let value = self.parse_expr(it.next()?)?;
        Some(StmtKind::Named { name, value })
    }

    fn parse_layer_name(&mut self, pair: Pair<'_, Rule>) -> Option<LayerName> {
        let p = pair.into_inner().next()?;
        match p.as_rule() {
            Rule::ident => Some(LayerName::Ident(self.ident(p))),
            _ => {
                let span = self.span(&p);
                let n = self.parse_int_literal(&p)?;
                Some(LayerName::Index(n as u64, span))
            }
        }
    }

    // ---------------------------------------------------------------------------------
    // Expressions
    // ---------------------------------------------------------------------------------

    /// Enters an expression of the given weight; `false` (and an error) past the limit.
    fn enter_expr(&mut self, weight: usize, span: Span) -> bool {
        self.expr_weight += weight;
        if self.expr_weight > MAX_EXPR_WEIGHT {
            self.diags.push(
                Diagnostic::error(Code::Limit, "expression is too deeply nested or too long")
                    .with_primary(span, "too complex")
                    .with_note("split it into smaller pieces with `let`"),
            );
            self.expr_weight -= weight;
            return false;
        }
        true
    }

    /// `unary (op unary)*`, folded by precedence climbing with an explicit stack.
    fn parse_expr(&mut self, pair: Pair<'_, Rule>) -> Option<Expr> {
        let span = self.span(&pair);
        let parts = inner(pair);
        let weight = 1 + parts.len() / 2;
        if !self.enter_expr(weight, span) {
            return None;
        }
        let result = self.fold_infix(parts);
        self.expr_weight -= weight;
        result
    }

    fn fold_infix(&mut self, parts: Vec<Pair<'_, Rule>>) -> Option<Expr> {
        let mut operands: Vec<Expr> = Vec::new();
        let mut ops: Vec<BinaryOp> = Vec::new();
        fn reduce(operands: &mut Vec<Expr>, ops: &mut Vec<BinaryOp>) -> Option<()> {
            let op = ops.pop()?;
            let rhs = operands.pop()?;
            let lhs = operands.pop()?;
            let span = lhs.span.to(rhs.span);
            operands.push(Expr { kind: ExprKind::Binary(op, Box::new(lhs), Box::new(rhs)), span });
            Some(())
        }
        let mut ok = true;
        for p in parts {
            match p.as_rule() {
                Rule::unary => match self.parse_unary(p) {
                    Some(e) => operands.push(e),
                    None => ok = false,
                },
                rule => {
                    let op = binary_op(rule)?;
                    while let Some(&top) = ops.last() {
                        let tighter = top.precedence() > op.precedence()
                            || (top.precedence() == op.precedence() && !op.right_assoc());
                        if !tighter {
                            break;
                        }
                        if ok {
                            reduce(&mut operands, &mut ops)?;
                        } else {
                            ops.pop();
                        }
                    }
                    ops.push(op);
                }
            }
        }
        if !ok {
            return None;
        }
        while !ops.is_empty() {
            reduce(&mut operands, &mut ops)?;
        }
        operands.pop()
    }

    fn parse_unary(&mut self, pair: Pair<'_, Rule>) -> Option<Expr> {
        let span = self.span(&pair);
        let parts = inner(pair);
        let weight = parts.len();
        if !self.enter_expr(weight, span) {
            return None;
        }
        let result = self.parse_unary_parts(parts, span);
        self.expr_weight -= weight;
        result
    }

    fn parse_unary_parts(&mut self, parts: Vec<Pair<'_, Rule>>, span: Span) -> Option<Expr> {
        let mut prefixes = Vec::new();
        let mut operand = None;
        for p in parts {
            match p.as_rule() {
                Rule::neg_op => prefixes.push((UnaryOp::Neg, self.span(&p))),
                Rule::not_op => prefixes.push((UnaryOp::Not, self.span(&p))),
                Rule::postfix_expr => operand = self.parse_postfix_expr(p),
                _ => {}
            }
        }
        let mut e = operand?;
        for (op, op_span) in prefixes.into_iter().rev() {
            // Fold `-64` into a literal so that it prints and evaluates as one number.
            e = match (op, e.kind) {
                (UnaryOp::Neg, ExprKind::Int(v)) => Expr { kind: ExprKind::Int(-v), span },
                (UnaryOp::Neg, ExprKind::Float(v)) => Expr { kind: ExprKind::Float(-v), span },
                (op, kind) => {
                    let inner = Expr { kind, span: e.span };
                    Expr { kind: ExprKind::Unary(op, Box::new(inner)), span: op_span.to(e.span) }
                }
            };
        }
        Some(e)
    }

    fn parse_postfix_expr(&mut self, pair: Pair<'_, Rule>) -> Option<Expr> {
        let mut it = pair.into_inner();
        let mut e = self.parse_primary(it.next()?)?;
        for p in it {
            let pspan = self.span(&p);
            let span = e.span.to(pspan);
            e = match p.as_rule() {
                Rule::member => {
                    let m = p.into_inner().next()?;
                    let name = if m.as_rule() == Rule::ident {
                        LayerName::Ident(self.ident(m))
                    } else {
                        let s = self.span(&m);
                        LayerName::Index(self.parse_int_literal(&m)? as u64, s)
                    };
                    Expr { kind: ExprKind::Member(Box::new(e), name), span }
                }
                _ => {
                    let idx = self.parse_expr(p.into_inner().next()?)?;
                    Expr { kind: ExprKind::Index(Box::new(e), Box::new(idx)), span }
                }
            };
        }
        Some(e)
    }

    fn parse_primary(&mut self, p: Pair<'_, Rule>) -> Option<Expr> {
        let span = self.span(&p);
        let kind = match p.as_rule() {
            Rule::int => ExprKind::Int(self.parse_int_literal(&p)?),
            Rule::float => ExprKind::Float(self.parse_float_literal(&p)?),
            Rule::boolean => ExprKind::Bool(p.as_str() == "true"),
            Rule::string => ExprKind::Str(p.into_inner().next().map(|s| s.as_str().to_string()).unwrap_or_default()),
            Rule::var => ExprKind::Var(self.ident(p.into_inner().next()?)),
            Rule::paren => return self.parse_expr(p.into_inner().next()?),
            Rule::if_expr => return self.parse_if_expr(p),
            Rule::call => return self.parse_call(p),
            Rule::list => {
                let elems: Vec<Expr> = p.into_inner().filter_map(|e| self.parse_expr(e)).collect();
                ExprKind::List(elems)
            }
            Rule::list_comp => return self.parse_list_comp(p),
            Rule::seq_expr => return self.parse_seq_expr(p),
            _ => return None,
        };
        Some(Expr { kind, span })
    }

    fn parse_int_literal(&mut self, p: &Pair<'_, Rule>) -> Option<i64> {
        match p.as_str().parse::<i64>() {
            Ok(v) => Some(v),
            Err(_) => {
                self.diags.push(
                    Diagnostic::error(Code::BadLiteral, "integer literal is too large")
                        .with_primary(self.span(p), format!("larger than {}", i64::MAX)),
                );
                None
            }
        }
    }

    fn parse_float_literal(&mut self, p: &Pair<'_, Rule>) -> Option<f64> {
        match p.as_str().parse::<f64>() {
            Ok(v) if v.is_finite() => Some(v),
            _ => {
                self.diags.push(
                    Diagnostic::error(Code::BadLiteral, "number literal is out of range")
                        .with_primary(self.span(p), "not a finite number"),
                );
                None
            }
        }
    }

    fn parse_if_expr(&mut self, pair: Pair<'_, Rule>) -> Option<Expr> {
        let span = self.span(&pair);
        let mut it = pair.into_inner();
        let cond = self.parse_expr(it.next()?);
        let then = self.parse_expr(it.next()?);
        let otherwise = self.parse_expr(it.next()?);
        Some(Expr {
            kind: ExprKind::IfElse { cond: Box::new(cond?), then: Box::new(then?), otherwise: Box::new(otherwise?) },
            span,
        })
    }

    fn parse_call(&mut self, pair: Pair<'_, Rule>) -> Option<Expr> {
        let span = self.span(&pair);
        let mut it = pair.into_inner();
        let callee = self.ident(it.next()?);
        let args = self.parse_call_args(it.next()?)?;
        Some(Expr { kind: ExprKind::Call { callee, args }, span })
    }

    fn parse_call_args(&mut self, pair: Pair<'_, Rule>) -> Option<Vec<Arg>> {
        let mut args = Vec::new();
        let mut ok = true;
        for a in pair.into_inner() {
            match self.parse_arg(a) {
                Some(arg) => args.push(arg),
                None => ok = false,
            }
        }
        ok.then_some(args)
    }

    fn parse_arg(&mut self, pair: Pair<'_, Rule>) -> Option<Arg> {
        let span = self.span(&pair);
        let parts = inner(pair);
        let (name, value) = match parts.len() {
            2 => (Some(self.ident(parts[0].clone())), parts[1].clone()),
            _ => (None, parts.into_iter().next()?),
        };
        Some(Arg { name, value: self.parse_expr(value)?, span })
    }

    fn parse_list_comp(&mut self, pair: Pair<'_, Rule>) -> Option<Expr> {
        let span = self.span(&pair);
        let mut it = pair.into_inner();
        let elem = self.parse_expr(it.next()?);
        let var = self.ident(it.next()?);
        let (start, end) = self.parse_range(it.next()?)?;
        Some(Expr {
            kind: ExprKind::Comprehension { elem: Box::new(elem?), var, start: Box::new(start), end: Box::new(end) },
            span,
        })
    }

    fn parse_range(&mut self, pair: Pair<'_, Rule>) -> Option<(Expr, Expr)> {
        let mut it = pair.into_inner();
        let a = self.parse_expr(it.next()?);
        let b = self.parse_expr(it.next()?);
        Some((a?, b?))
    }

    fn parse_seq_expr(&mut self, pair: Pair<'_, Rule>) -> Option<Expr> {
        let span = self.span(&pair);
        let mut it = pair.into_inner();
        let input = self.parse_expr(it.next()?);
        let items = self.parse_seq_body(it.next()?);
        Some(Expr { kind: ExprKind::Seq { input: Box::new(input?), items }, span })
    }

    fn parse_seq_body(&mut self, pair: Pair<'_, Rule>) -> Vec<SeqItem> {
        let mut items = Vec::new();
        for p in pair.into_inner() {
            match p.as_rule() {
                Rule::seq_item => {
                    if let Some(i) = self.parse_seq_item(p) {
                        items.push(i);
                    }
                }
                Rule::seq_for => {
                    if let Some(i) = self.parse_seq_for(p) {
                        items.push(i);
                    }
                }
                Rule::seq_error => self.recover(p, Rule::seq_item_only),
                _ => {}
            }
        }
        items
    }

    fn parse_seq_item(&mut self, pair: Pair<'_, Rule>) -> Option<SeqItem> {
        let span = self.span(&pair);
        let mut name = None;
        let mut callee = None;
        let mut args = Vec::new();
        for p in pair.into_inner() {
            match p.as_rule() {
                Rule::layer_name => name = self.parse_layer_name(p),
                Rule::ident => callee = Some(self.ident(p)),
                Rule::call_args => args = self.parse_call_args(p)?,
                _ => {}
            }
        }
        Some(SeqItem::Call { name, callee: callee?, args, span })
    }

    fn parse_seq_for(&mut self, pair: Pair<'_, Rule>) -> Option<SeqItem> {
        let span = self.span(&pair);
        let mut it = pair.into_inner();
        let var = self.ident(it.next()?);
        let (start, end) = self.parse_range(it.next()?)?;
        let items = self.parse_seq_body(it.next()?);
        Some(SeqItem::For { var, start, end, items, span })
    }

    // ---------------------------------------------------------------------------------
    // Adaptation section
    // ---------------------------------------------------------------------------------

    fn parse_adapt_def(&mut self, pair: Pair<'_, Rule>) -> AdaptSection {
        let span = self.span(&pair);
        let mut rules = Vec::new();
        if let Some(body) = pair.into_inner().next() {
            for p in body.into_inner() {
                match p.as_rule() {
                    Rule::adapt_rule => {
                        if let Some(r) = self.parse_adapt_rule(p) {
                            rules.push(r);
                        }
                    }
                    Rule::rule_error => self.recover(p, Rule::rule_only),
                    _ => {}
                }
            }
        }
        AdaptSection { rules, span }
    }

    fn parse_adapt_rule(&mut self, pair: Pair<'_, Rule>) -> Option<AdaptRule> {
        let span = self.span(&pair);
        let p = pair.into_inner().next()?;
        let rule = p.as_rule();
        let mut options = Vec::new();
        let mut selector = None;
        let mut scopes = Vec::new();
        let mut before = None;
        for q in p.into_inner() {
            match q.as_rule() {
                Rule::rule_option => options.push(self.parse_rule_option(q)?),
                Rule::selector => selector = Some(self.parse_selector(q)),
                Rule::scope_list => scopes = self.parse_scope_list(q),
                Rule::pattern => before = Some(self.parse_pattern(q)),
                _ => {}
            }
        }
        let kind = match rule {
            Rule::tune_rule => AdaptKind::Tune { selector: selector? },
            Rule::lora_rule => AdaptKind::Lora { options, selector: selector? },
            _ => AdaptKind::Adapter { options, scopes, before: before? },
        };
        Some(AdaptRule { kind, span })
    }

    fn parse_rule_option(&mut self, pair: Pair<'_, Rule>) -> Option<RuleOption> {
        let span = self.span(&pair);
        let mut it = pair.into_inner();
        let name = self.ident(it.next()?);
        let value = match it.next() {
            None => None,
            Some(v) => Some(match v.as_rule() {
                Rule::number => OptionValue::Number(self.parse_number(v)?),
                Rule::string => OptionValue::Str(
                    v.clone().into_inner().next().map(|s| s.as_str().to_string()).unwrap_or_default(),
                    self.span(&v),
                ),
                _ => OptionValue::Word(self.ident(v)),
            }),
        };
        Some(RuleOption { name, value, span })
    }

    fn parse_selector(&mut self, pair: Pair<'_, Rule>) -> Selector {
        let span = self.span(&pair);
        let items = pair.into_inner().filter_map(|p| self.parse_sel_item(p)).collect();
        Selector { items, span }
    }

    fn parse_sel_item(&mut self, pair: Pair<'_, Rule>) -> Option<SelItem> {
        let span = self.span(&pair);
        let parts = inner(pair);
        match parts.as_slice() {
            [kinds, scopes] => Some(SelItem::KindsIn {
                kinds: kinds.clone().into_inner().map(|k| self.ident(k)).collect(),
                scopes: self.parse_scope_list(scopes.clone()),
                span,
            }),
            [pattern] => Some(SelItem::Pattern(self.parse_pattern(pattern.clone()))),
            _ => None,
        }
    }

    fn parse_scope_list(&mut self, pair: Pair<'_, Rule>) -> Vec<Pattern> {
        pair.into_inner().map(|p| self.parse_pattern(p)).collect()
    }

    fn parse_pattern(&mut self, pair: Pair<'_, Rule>) -> Pattern {
        let span = self.span(&pair);
        let text = pair.as_str().to_string();
        let segments = split_pattern(&text)
            .into_iter()
            .map(|s| if s == "**" { PatternSeg::AnyDepth } else { PatternSeg::Word(s.to_string()) })
            .collect();
        Pattern { segments, text, span }
    }

    // ---------------------------------------------------------------------------------
    // Variants section
    // ---------------------------------------------------------------------------------

    fn parse_variants_def(&mut self, pair: Pair<'_, Rule>) -> VariantSection {
        let span = self.span(&pair);
        let mut decls = Vec::new();
        if let Some(body) = pair.into_inner().next() {
            for p in body.into_inner() {
                match p.as_rule() {
                    Rule::variant_decl => {
                        if let Some(d) = self.parse_variant_decl(p) {
                            decls.push(d);
                        }
                    }
                    Rule::decl_error => self.recover(p, Rule::decl_only),
                    _ => {}
                }
            }
        }
        VariantSection { decls, span }
    }

    fn parse_variant_decl(&mut self, pair: Pair<'_, Rule>) -> Option<VariantDecl> {
        let p = pair.into_inner().next()?;
        let span = self.span(&p);
        match p.as_rule() {
            Rule::axis_decl => {
                let mut it = p.into_inner();
                let name = self.ident(it.next()?);
                let modality = self.ident(it.next()?);
                let mut levels = Vec::new();
                let mut clear = None;
                for q in it {
                    if q.as_rule() == Rule::axis_clear {
                        clear = Some(self.parse_number(q.into_inner().next()?)?);
                    } else {
                        levels.push(self.parse_number(q)?);
                    }
                }
                Some(VariantDecl::Axis { name, modality, levels, clear, span })
            }
            Rule::missing_decl => {
                let mut it = p.into_inner();
                let modality = self.ident(it.next()?);
                let policy = self.ident(it.next()?);
                Some(VariantDecl::Missing { modality, policy, span })
            }
            Rule::select_decl => {
                let mut it = p.into_inner();
                let axis = self.ident(it.next()?);
                let source = self.parse_select_source(it.next()?)?;
                let mapping = match it.next() {
                    Some(m) => self.parse_select_map(m)?,
                    None => SelectMap::Nearest,
                };
                Some(VariantDecl::Select { axis, source, mapping, span })
            }
            Rule::meld_decl => {
                let mut weights = Vec::new();
                for w in p.into_inner() {
                    let mut it = w.into_inner();
                    let m = self.ident(it.next()?);
                    let n = self.parse_number(it.next()?)?;
                    weights.push((m, n));
                }
                Some(VariantDecl::Meld { weights, span })
            }
            _ => None,
        }
    }

    fn parse_select_source(&mut self, pair: Pair<'_, Rule>) -> Option<SelectSource> {
        let p = pair.into_inner().next()?;
        let span = self.span(&p);
        match p.as_rule() {
            Rule::meta_source => {
                let s = p.into_inner().next()?;
                let key = s.into_inner().next().map(|b| b.as_str().to_string()).unwrap_or_default();
                Some(SelectSource::Meta { key, span })
            }
            _ => {
                let mut it = p.into_inner();
                let stat = self.ident(it.next()?);
                let input = self.ident(it.next()?);
                Some(SelectSource::Stat { stat, input })
            }
        }
    }

    fn parse_select_map(&mut self, pair: Pair<'_, Rule>) -> Option<SelectMap> {
        let p = pair.into_inner().next()?;
        if p.as_rule() == Rule::nearest_map {
            return Some(SelectMap::Nearest);
        }
        let mut arms = Vec::new();
        for arm in p.into_inner() {
            let span = self.span(&arm);
            let mut bound = None;
            let mut inclusive = false;
            let mut level = None;
            for q in arm.into_inner() {
                match q.as_rule() {
                    Rule::threshold_cmp => inclusive = q.as_str() == "<=",
                    Rule::number => bound = Some((inclusive, self.parse_number(q)?)),
                    Rule::level_ref => {
                        let l = q.into_inner().next()?;
                        level = Some(match l.as_rule() {
                            Rule::clear_kw => LevelRef::Clear(self.span(&l)),
                            _ => LevelRef::Level(self.parse_number(l)?),
                        });
                    }
                    _ => {}
                }
            }
            arms.push(ThresholdArm { bound, level: level?, span });
        }
        Some(SelectMap::Thresholds(arms))
    }

    fn parse_number(&mut self, pair: Pair<'_, Rule>) -> Option<Number> {
        let span = self.span(&pair);
        let text = pair.as_str().to_string();
        match text.parse::<f64>() {
            Ok(value) if value.is_finite() => Some(Number { value, text, span }),
            _ => {
                self.diags.push(
                    Diagnostic::error(Code::BadLiteral, "number literal is out of range")
                        .with_primary(span, "not a finite number"),
                );
                None
            }
        }
    }

    // ---------------------------------------------------------------------------------
    // Recovery and error messages
    // ---------------------------------------------------------------------------------

    /// Re-parses a swallowed piece with its `*_only` rule and reports where and why it
    /// fails.
    fn recover(&mut self, pair: Pair<'_, Rule>, rule: Rule) {
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

    fn push_pest_error(&mut self, e: pest::error::Error<Rule>, offset: usize, entry: Rule) {
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

fn binary_op(rule: Rule) -> Option<BinaryOp> {
    Some(match rule {
        Rule::or_op => BinaryOp::Or,
        Rule::and_op => BinaryOp::And,
        Rule::eq_op => BinaryOp::Eq,
        Rule::ne_op => BinaryOp::Ne,
        Rule::lt_op => BinaryOp::Lt,
        Rule::le_op => BinaryOp::Le,
        Rule::gt_op => BinaryOp::Gt,
        Rule::ge_op => BinaryOp::Ge,
        Rule::add_op => BinaryOp::Add,
        Rule::sub_op => BinaryOp::Sub,
        Rule::mul_op => BinaryOp::Mul,
        Rule::div_op => BinaryOp::Div,
        Rule::floordiv_op => BinaryOp::FloorDiv,
        Rule::mod_op => BinaryOp::Mod,
        Rule::pow_op => BinaryOp::Pow,
        _ => return None,
    })
}

/// Splits a pattern at the dots that are not inside `{...}`.
fn split_pattern(text: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let mut depth = 0;
    let mut start = 0;
    for (i, c) in text.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => depth -= 1,
            '.' if depth == 0 => {
                out.push(&text[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    out.push(&text[start..]);
    out
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
        Rule::layer_name => "a layer name",
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
        Rule::item | Rule::block_def | Rule::model_def | Rule::adapt_def | Rule::variants_def => {
            "`block`, `model`, `adapt` or `variants`"
        }
        Rule::seq_item | Rule::seq_for | Rule::seq_body => "a sequence item such as `conv2d(64, 3)`",
        Rule::adapt_rule | Rule::tune_rule | Rule::lora_rule | Rule::adapter_rule => {
            "a rule (`tune`, `lora` or `adapter`)"
        }
        Rule::rule_option => "an option such as `rank=4`",
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
            Rule::item_only | Rule::file => "`block`, `model`, `adapt` or `variants`".into(),
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

    fn parse_ok(src: &str) -> SourceFile {
        let p = parse(FileId(0), src);
        assert!(p.diagnostics.is_empty(), "{:#?}", p.diagnostics);
        p.file
    }

    fn first_error(src: &str) -> Diagnostic {
        let p = parse(FileId(0), src);
        p.diagnostics.0.into_iter().next().expect("an error")
    }

    fn model_stmts(f: &SourceFile) -> &[Stmt] {
        &f.models().next().expect("a model").body.stmts
    }

    #[test]
    fn precedence_follows_arithmetic() {
        let f = parse_ok("model m { let a = 1 + 2 * 3 ** 2 ** 1 - 4 }");
        let StmtKind::Let { value, .. } = &model_stmts(&f)[0].kind else { panic!() };
        // ((1 + (2 * (3 ** (2 ** 1)))) - 4)
        let ExprKind::Binary(BinaryOp::Sub, lhs, rhs) = &value.kind else { panic!("{value:?}") };
        assert!(matches!(rhs.kind, ExprKind::Int(4)));
        let ExprKind::Binary(BinaryOp::Add, one, mul) = &lhs.kind else { panic!() };
        assert!(matches!(one.kind, ExprKind::Int(1)));
        let ExprKind::Binary(BinaryOp::Mul, _, pow) = &mul.kind else { panic!() };
        let ExprKind::Binary(BinaryOp::Pow, _, pow2) = &pow.kind else { panic!() };
        assert!(matches!(pow2.kind, ExprKind::Binary(BinaryOp::Pow, _, _)));
    }

    #[test]
    fn dotted_member_paths_are_not_floats() {
        let f = parse_ok("model m { x = layer1.0.conv1 }");
        let StmtKind::Named { value, .. } = &model_stmts(&f)[0].kind else { panic!() };
        let ExprKind::Member(base, LayerName::Ident(c)) = &value.kind else { panic!("{value:?}") };
        assert_eq!(c.name, "conv1");
        assert!(matches!(base.kind, ExprKind::Member(_, LayerName::Index(0, _))));
    }

    #[test]
    fn ranges_are_not_floats() {
        let f = parse_ok("model m { let a = [i for i in 0..3] }");
        let StmtKind::Let { value, .. } = &model_stmts(&f)[0].kind else { panic!() };
        assert!(matches!(value.kind, ExprKind::Comprehension { .. }));
    }

    #[test]
    fn negative_literals_fold() {
        let f = parse_ok("model m { let a = -3 }");
        let StmtKind::Let { value, .. } = &model_stmts(&f)[0].kind else { panic!() };
        assert_eq!(value.kind, ExprKind::Int(-3));
    }

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

    #[test]
    fn long_operator_chains_are_refused() {
        let src = format!("model m {{ let a = 1{} }}", " + 1".repeat(500));
        let d = first_error(&src);
        assert_eq!(d.code, Code::Limit);
    }

    #[test]
    fn huge_integer_literal_is_an_error() {
        let d = first_error("model m { let a = 99999999999999999999999 }");
        assert_eq!(d.code, Code::BadLiteral);
    }

    #[test]
    fn adapt_and_variants_sections_parse() {
        let f = parse_ok(
            "model m { }\n\
             adapt {\n  tune batchnorm, head.*\n  lora rank=4 alpha=8 rslora on linear in Attention|blocks.*\n\
               adapter squeeze=2 act=relu in BasicBlock before bn{1,2}\n}\n\
             variants {\n  axis fog on lidar: 0.01, 0.03 clear 0\n  missing camera: zero_fill\n\
               select fog by meta(\"fog\") nearest\n\
               select gamma by brightness(image) { < 0.2 -> 0.25, <= 0.8 -> clear, else -> 4 }\n\
               meld camera = 0.8, lidar = 0.2\n}\n",
        );
        let a = f.adapt_sections().next().expect("adapt");
        assert_eq!(a.rules.len(), 3);
        let AdaptKind::Lora { options, selector } = &a.rules[1].kind else { panic!() };
        assert_eq!(options.len(), 3);
        assert!(matches!(&selector.items[0], SelItem::KindsIn { scopes, .. } if scopes.len() == 2));
        let AdaptKind::Adapter { before, .. } = &a.rules[2].kind else { panic!() };
        assert_eq!(before.segments, vec![PatternSeg::Word("bn{1,2}".into())]);
        let v = f.variant_sections().next().expect("variants");
        assert_eq!(v.decls.len(), 5);
        let VariantDecl::Axis { levels, clear, .. } = &v.decls[0] else { panic!() };
        assert_eq!(levels.len(), 2);
        assert_eq!(clear.as_ref().map(|c| c.value), Some(0.0));
    }

    #[test]
    fn pattern_split_respects_alternatives() {
        assert_eq!(split_pattern("blocks.*.attn.{q.x,k}"), vec!["blocks", "*", "attn", "{q.x,k}"]);
    }
}
