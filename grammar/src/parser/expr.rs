//! Expressions: precedence climbing over the infix operators, unary and postfix forms,
//! literals, calls, lists and comprehensions, and `seq(...) { ... }` bodies.
//!
//! Separate because this is where operator precedence is decided and where the
//! expression size limit ([`MAX_EXPR_WEIGHT`]) is enforced.

use pest::iterators::Pair;

use super::{Builder, MAX_EXPR_WEIGHT, Rule, inner};
use crate::ast::*;
use crate::diag::{Code, Diagnostic, Span};

impl<'s> Builder<'s> {
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
    pub(super) fn parse_expr(&mut self, pair: Pair<'_, Rule>) -> Option<Expr> {
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
                    } else if m.as_rule() == Rule::quoted_name {
                        LayerName::Quoted(self.parse_quoted_name(m)?)
                    } else {
                        let s = self.span(&m);
                        LayerName::Index(self.parse_int_literal(&m)? as u64, s)
                    };
                    Expr { kind: ExprKind::Member(Box::new(e), name), span }
                }
                _ => {
                    let parts: Vec<Pair<'_, Rule>> = p.into_inner().collect();
                    if let [one] = parts.as_slice()
                        && one.as_rule() == Rule::expr
                    {
                        let idx = self.parse_expr(one.clone())?;
                        Expr { kind: ExprKind::Index(Box::new(e), Box::new(idx)), span }
                    } else {
                        let mut subs = Vec::new();
                        for q in parts {
                            match q.as_rule() {
                                Rule::expr => subs.push(Subscript::Index(self.parse_expr(q)?)),
                                Rule::ellipsis => subs.push(Subscript::Ellipsis(self.span(&q))),
                                Rule::slice_range => subs.push(self.parse_slice_range(q)?),
                                _ => {}
                            }
                        }
                        Expr { kind: ExprKind::Subscript(Box::new(e), subs), span }
                    }
                }
            };
        }
        Some(e)
    }

    fn parse_slice_range(&mut self, pair: Pair<'_, Rule>) -> Option<Subscript> {
        let span = self.span(&pair);
        let (mut start, mut stop, mut step) = (None, None, None);
        for q in pair.into_inner() {
            let rule = q.as_rule();
            let e = self.parse_expr(q.into_inner().next()?)?;
            match rule {
                Rule::slice_start => start = Some(e),
                Rule::slice_stop => stop = Some(e),
                _ => step = Some(e),
            }
        }
        Some(Subscript::Range { start, stop, step, span })
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

    pub(super) fn parse_int_literal(&mut self, p: &Pair<'_, Rule>) -> Option<i64> {
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
                Rule::seq_if => {
                    if let Some(i) = self.parse_seq_if(p) {
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

    fn parse_seq_if(&mut self, pair: Pair<'_, Rule>) -> Option<SeqItem> {
        let span = self.span(&pair);
        let mut branches = Vec::new();
        let mut otherwise = None;
        let mut cond = None;
        for p in pair.into_inner() {
            match p.as_rule() {
                Rule::expr => cond = Some(self.parse_expr(p)),
                Rule::seq_body => {
                    let items = self.parse_seq_body(p);
                    match cond.take() {
                        Some(c) => branches.push((c?, items)),
                        None => otherwise = Some(items),
                    }
                }
                _ => {}
            }
        }
        Some(SeqItem::If { branches, otherwise, span })
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::parser::tests::{first_error, model_stmts, parse_ok};

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
    fn floor_division_and_remainder_bind_as_multiplication() {
        // `a + b // c % d * e` is `a + (((b // c) % d) * e)`: left to right among `* / // %`.
        let f = parse_ok("model m { let a = i + j // 64 % 8 * 2 }");
        let StmtKind::Let { value, .. } = &model_stmts(&f)[0].kind else { panic!() };
        let ExprKind::Binary(BinaryOp::Add, _, mul) = &value.kind else { panic!("{value:?}") };
        let ExprKind::Binary(BinaryOp::Mul, rem, two) = &mul.kind else { panic!("{mul:?}") };
        assert!(matches!(two.kind, ExprKind::Int(2)));
        let ExprKind::Binary(BinaryOp::Mod, div, eight) = &rem.kind else { panic!("{rem:?}") };
        assert!(matches!(eight.kind, ExprKind::Int(8)));
        assert!(matches!(div.kind, ExprKind::Binary(BinaryOp::FloorDiv, _, _)), "{div:?}");
        assert_eq!(crate::ast_print::expr_to_source(value), "i + (((j // 64) % 8) * 2)");
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
    fn subscripts_parse_and_print_back() {
        let f = parse_ok("model m { let a = x[:, 0:64, ::2, ..., -1:, 1::3] }");
        let StmtKind::Let { value, .. } = &model_stmts(&f)[0].kind else { panic!() };
        let ExprKind::Subscript(_, subs) = &value.kind else { panic!("{value:?}") };
        assert_eq!(subs.len(), 6);
        assert!(matches!(&subs[0], Subscript::Range { start: None, stop: None, step: None, .. }));
        assert!(matches!(&subs[2], Subscript::Range { start: None, stop: None, step: Some(_), .. }));
        assert!(matches!(&subs[3], Subscript::Ellipsis(_)));
        assert!(matches!(&subs[4], Subscript::Range { start: Some(_), stop: None, step: None, .. }));
        assert_eq!(crate::ast_print::expr_to_source(value), "x[:, 0:64, ::2, ..., -1:, 1::3]");
        // One plain index stays a list/sequence index; a trailing comma makes a subscript.
        let f = parse_ok("model m { let a = xs[i]\n let b = x[0,] }");
        assert!(matches!(model_stmts(&f)[0].kind, StmtKind::Let { value: Expr { kind: ExprKind::Index(..), .. }, .. }));
        let StmtKind::Let { value, .. } = &model_stmts(&f)[1].kind else { panic!() };
        assert!(matches!(&value.kind, ExprKind::Subscript(_, s) if s.len() == 1));
        assert_eq!(crate::ast_print::expr_to_source(value), "x[0,]");
    }

    #[test]
    fn negative_literals_fold() {
        let f = parse_ok("model m { let a = -3 }");
        let StmtKind::Let { value, .. } = &model_stmts(&f)[0].kind else { panic!() };
        assert_eq!(value.kind, ExprKind::Int(-3));
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
}
