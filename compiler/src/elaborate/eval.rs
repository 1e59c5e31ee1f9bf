//! Expression evaluation: names, literals, unary and binary operators (on ints, floats,
//! bools, strings, symbolic dimensions, lists and tensors), member access, indexing,
//! lists, comprehensions, ranges, `if ... then ... else` and `seq`.
//!
//! Separate because this is the arithmetic of compile-time values, with its own rules
//! (Python-style `//` and `%`, exact `/` on ints, overflow checks); tensor operands only
//! hand off to node creation.

use std::rc::Rc;

use readi_grammar::ast::{BinaryOp, Expr, ExprKind, UnaryOp};
use readi_grammar::diag::{Code, Diagnostic, Span, suggest};
use readi_plan::ops::BinaryOp as TensorOp;

use super::{Elab, Frame, Hint, MAX_RANGE, Value, builtins, display_path, restore};
use crate::ir::*;

impl<'a> Elab<'a> {
    pub(super) fn lookup_var(&mut self, name: &str, span: Span, frame: &Frame<'a>) -> Value {
        if let Some(v) = frame.vars.get(name) {
            return v.clone();
        }
        // Element types name themselves, for `buffer([2401], dtype=i64)`.
        if matches!(name, "f32" | "i64" | "bool") {
            return Value::Str(Rc::from(name));
        }
        if self.symbols_allowed {
            if let Some(s) = suggest(name, frame.vars.keys().map(String::as_str)) {
                self.diags.push(
                    Diagnostic::warning(Code::LikelyTypo, format!("`{name}` is taken as a symbolic dimension"))
                        .with_primary(span, "not defined, so symbolic")
                        .with_note(format!("did you mean `{s}`?")),
                );
            }
            return Value::Dim(Dim::symbol(name));
        }
        let mut d = Diagnostic::error(Code::UnknownName, format!("unknown name `{name}`"))
            .with_primary(span, "not defined here");
        if builtins::is_builtin(name) || self.blocks.contains_key(name) {
            d = d.with_note(format!("`{name}` is an op or block; call it: `{name}(...)`"));
        } else if let Some(s) = suggest(name, frame.vars.keys().map(String::as_str)) {
            d = d.with_note(format!("did you mean `{s}`?"));
        }
        self.error(d)
    }

    pub(super) fn eval(&mut self, e: &'a Expr, frame: &mut Frame<'a>, hint: Option<Hint>) -> Value {
        if !self.step(e.span) {
            return Value::Poison;
        }
        match &e.kind {
            ExprKind::Int(i) => Value::Int(*i),
            ExprKind::Float(f) => Value::Float(*f),
            ExprKind::Bool(b) => Value::Bool(*b),
            ExprKind::Str(s) => Value::Str(Rc::from(s.as_str())),
            ExprKind::Var(id) => self.lookup_var(&id.name, id.span, frame),
            ExprKind::Unary(op, x) => {
                let v = self.eval(x, frame, None);
                self.unary(*op, v, e.span, hint, frame.scope)
            }
            ExprKind::Binary(op, a, b) => {
                let (va, vb) = if matches!(op, BinaryOp::And | BinaryOp::Or) {
                    // Short-circuit, so `i > 0 and xs[i - 1] ...` is safe.
                    let va = self.eval(a, frame, None);
                    match (op, &va) {
                        (BinaryOp::And, Value::Bool(false)) => return Value::Bool(false),
                        (BinaryOp::Or, Value::Bool(true)) => return Value::Bool(true),
                        _ => {}
                    }
                    (va, self.eval(b, frame, None))
                } else {
                    (self.eval(a, frame, None), self.eval(b, frame, None))
                };
                self.binary(*op, va, vb, e.span, (a.span, b.span), hint, frame)
            }
            ExprKind::Call { callee, args } => {
                let mut vals = Vec::with_capacity(args.len());
                for a in args {
                    vals.push((a.name.clone(), self.eval(&a.value, frame, None), a.value.span));
                }
                self.call(callee, vals, e.span, hint, frame)
            }
            ExprKind::Member(base, name) => {
                let b = self.eval(base, frame, None);
                let Some(text) = self.layer_text(name, frame) else { return Value::Poison };
                self.member(b, &text, name.span(), base.span)
            }
            ExprKind::Index(base, idx) => {
                let b = self.eval(base, frame, None);
                let i = self.eval(idx, frame, None);
                self.index(b, i, idx.span, base.span, hint, frame.scope)
            }
            ExprKind::Subscript(base, subs) => self.subscript(base, subs, e.span, hint, frame),
            ExprKind::List(items) => {
                let list_scope = hint.map(|h| self.new_scope(&h, ScopeKind::List, e.span));
                let mut out = Vec::with_capacity(items.len());
                for (i, item) in items.iter().enumerate() {
                    let h = list_scope.map(|s| Hint { scope: s, name: i.to_string() });
                    let v = self.eval(item, frame, h);
                    if let Some(s) = list_scope {
                        self.tables[s.0 as usize].names.insert(i.to_string(), (v.clone(), item.span));
                    }
                    out.push(v);
                }
                Value::List(Rc::new(out))
            }
            ExprKind::Comprehension { elem, var, start, end } => {
                let Some((a, b)) = self.range(start, end, frame) else { return Value::Poison };
                let list_scope = hint.map(|h| self.new_scope(&h, ScopeKind::List, e.span));
                let saved = frame.vars.get(&var.name).cloned();
                let mut out = Vec::new();
                for (k, i) in (a..b).enumerate() {
                    if self.aborted {
                        break;
                    }
                    frame.vars.insert(var.name.clone(), Value::Int(i));
                    let h = list_scope.map(|s| Hint { scope: s, name: k.to_string() });
                    let v = self.eval(elem, frame, h);
                    if let Some(s) = list_scope {
                        self.tables[s.0 as usize].names.insert(k.to_string(), (v.clone(), elem.span));
                    }
                    out.push(v);
                }
                restore(&mut frame.vars, &var.name, saved);
                Value::List(Rc::new(out))
            }
            ExprKind::IfElse { cond, then, otherwise } => match self.eval(cond, frame, None) {
                Value::Bool(true) => self.eval(then, frame, hint),
                Value::Bool(false) => self.eval(otherwise, frame, hint),
                Value::Poison => Value::Poison,
                v => self.error(
                    Diagnostic::error(Code::TypeMismatch, format!("`if` needs a bool, found {}", v.kind()))
                        .with_primary(cond.span, "not a bool"),
                ),
            },
            ExprKind::Seq { input, items } => {
                let input = self.eval(input, frame, None);
                let scope = match &hint {
                    Some(h) => self.new_scope(h, ScopeKind::Seq, e.span),
                    None => frame.scope,
                };
                let mut counter = 0usize;
                let out = self.seq_items(items, input, scope, &mut counter, frame);
                match (out, hint.is_some()) {
                    (Value::Tensor { value, .. }, true) => Value::Tensor { value, scope: Some(scope) },
                    (v, _) => v,
                }
            }
        }
    }

    /// Evaluates `a..b` to a bounded integer range.
    pub(super) fn range(&mut self, start: &'a Expr, end: &'a Expr, frame: &mut Frame<'a>) -> Option<(i64, i64)> {
        let a = self.eval(start, frame, None);
        let b = self.eval(end, frame, None);
        match (a, b) {
            (Value::Int(a), Value::Int(b)) => {
                if b.saturating_sub(a) > MAX_RANGE {
                    self.error(
                        Diagnostic::error(Code::Limit, format!("range {a}..{b} is longer than {MAX_RANGE}"))
                            .with_primary(start.span.to(end.span), "too long"),
                    );
                    return None;
                }
                Some((a, b))
            }
            (Value::Poison, _) | (_, Value::Poison) => None,
            (a, b) => {
                let bad = if matches!(a, Value::Int(_)) { (end.span, b) } else { (start.span, a) };
                self.error(
                    Diagnostic::error(Code::TypeMismatch, format!("range bounds must be ints, found {}", bad.1.kind()))
                        .with_primary(bad.0, "not an int"),
                );
                None
            }
        }
    }

    fn unary(&mut self, op: UnaryOp, v: Value, span: Span, hint: Option<Hint>, scope: ScopeId) -> Value {
        match (op, v) {
            (_, Value::Poison) => Value::Poison,
            (UnaryOp::Neg, Value::Int(i)) => match i.checked_neg() {
                Some(n) => Value::Int(n),
                None => self.overflow(span),
            },
            (UnaryOp::Neg, Value::Float(f)) => Value::Float(-f),
            (UnaryOp::Not, Value::Bool(b)) => Value::Bool(!b),
            (UnaryOp::Neg, Value::Tensor { value, .. }) => {
                let op = Op::Pure(Pure::Scalar(Scalar { op: TensorOp::Mul, value: -1.0, scalar_first: false }));
                self.add_node_in(op, vec![value], hint, span, scope)
            }
            (op, v) => self.error(
                Diagnostic::error(
                    Code::TypeMismatch,
                    format!("`{}` does not apply to {}", if op == UnaryOp::Neg { "-" } else { "not" }, v.kind()),
                )
                .with_primary(span, "invalid operand"),
            ),
        }
    }

    fn overflow(&mut self, span: Span) -> Value {
        self.error(
            Diagnostic::error(Code::BadValue, "integer overflow").with_primary(span, "result does not fit in 64 bits"),
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn binary(
        &mut self,
        op: BinaryOp,
        a: Value,
        b: Value,
        span: Span,
        spans: (Span, Span),
        hint: Option<Hint>,
        frame: &Frame<'a>,
    ) -> Value {
        use BinaryOp::*;
        let mismatch = |this: &mut Self, a: &Value, b: &Value| {
            this.error(
                Diagnostic::error(
                    Code::TypeMismatch,
                    format!("`{}` does not apply to {} and {}", op.as_str(), a.kind(), b.kind()),
                )
                .with_primary(span, "invalid operands"),
            )
        };
        match (&a, &b) {
            (Value::Poison, _) | (_, Value::Poison) => Value::Poison,
            (Value::Tensor { value: x, .. }, Value::Tensor { value: y, .. }) => {
                let Some(kind) = tensor_kind(op) else { return mismatch(self, &a, &b) };
                self.add_node_in(Op::Pure(Pure::Binary(kind)), vec![*x, *y], hint, span, frame.scope)
            }
            (Value::Tensor { value: x, .. }, s @ (Value::Int(_) | Value::Float(_)))
            | (s @ (Value::Int(_) | Value::Float(_)), Value::Tensor { value: x, .. }) => {
                let Some(kind) = tensor_kind(op) else { return mismatch(self, &a, &b) };
                let value = match s {
                    Value::Int(i) => *i as f64,
                    Value::Float(f) => *f,
                    _ => 0.0,
                };
                let scalar_first = matches!(a, Value::Int(_) | Value::Float(_));
                let op = Op::Pure(Pure::Scalar(Scalar { op: kind, value, scalar_first }));
                self.add_node_in(op, vec![*x], hint, span, frame.scope)
            }
            (Value::Int(x), Value::Int(y)) => self.int_binary(op, *x, *y, span, spans.1),
            (Value::Int(_) | Value::Float(_), Value::Int(_) | Value::Float(_)) => {
                let x = as_f64(&a);
                let y = as_f64(&b);
                if let Some(c) = compare(op, x, y) {
                    return Value::Bool(c);
                }
                let v = match op {
                    Add => x + y,
                    Sub => x - y,
                    Mul => x * y,
                    Div => x / y,
                    FloorDiv => (x / y).floor(),
                    Mod => x - y * (x / y).floor(),
                    Pow => x.powf(y),
                    _ => return mismatch(self, &a, &b),
                };
                if v.is_finite() {
                    Value::Float(v)
                } else {
                    self.error(
                        Diagnostic::error(Code::BadValue, format!("`{}` gives {v}", op.as_str()))
                            .with_primary(span, "not a finite number"),
                    )
                }
            }
            (Value::Bool(x), Value::Bool(y)) => match op {
                And => Value::Bool(*x && *y),
                Or => Value::Bool(*x || *y),
                Eq => Value::Bool(x == y),
                Ne => Value::Bool(x != y),
                _ => mismatch(self, &a, &b),
            },
            (Value::Str(x), Value::Str(y)) => match op {
                Eq => Value::Bool(x == y),
                Ne => Value::Bool(x != y),
                Add => Value::Str(Rc::from(format!("{x}{y}").as_str())),
                _ => mismatch(self, &a, &b),
            },
            (Value::Dim(_) | Value::Int(_), Value::Dim(_) | Value::Int(_)) => {
                let x = as_dim(&a);
                let y = as_dim(&b);
                let r = match op {
                    Mul => x.checked_mul(&y),
                    Div | FloorDiv => x.checked_div(&y),
                    Eq => return Value::Bool(x == y),
                    Ne => return Value::Bool(x != y),
                    _ => {
                        return self.error(
                            Diagnostic::error(
                                Code::TypeMismatch,
                                format!("`{}` cannot combine a symbolic dimension ({x}, {y})", op.as_str()),
                            )
                            .with_primary(span, "only `*` and exact `/` apply to symbolic dimensions"),
                        );
                    }
                };
                match r {
                    Some(d) => d.as_known().map(Value::Int).unwrap_or(Value::Dim(d)),
                    None => self.error(
                        Diagnostic::error(Code::BadValue, format!("{x} {} {y} is not a whole dimension", op.as_str()))
                            .with_primary(span, "not exact"),
                    ),
                }
            }
            (Value::List(x), Value::List(y)) if op == Add => {
                let mut v = (**x).clone();
                v.extend(y.iter().cloned());
                Value::List(Rc::new(v))
            }
            _ => mismatch(self, &a, &b),
        }
    }

    fn int_binary(&mut self, op: BinaryOp, x: i64, y: i64, span: Span, rhs_span: Span) -> Value {
        use BinaryOp::*;
        if let Some(c) = compare(op, x, y) {
            return Value::Bool(c);
        }
        let div_zero = |this: &mut Self| {
            this.error(Diagnostic::error(Code::BadValue, "division by zero").with_primary(rhs_span, "this is zero"))
        };
        let r = match op {
            Add => x.checked_add(y),
            Sub => x.checked_sub(y),
            Mul => x.checked_mul(y),
            Div => {
                if y == 0 {
                    return div_zero(self);
                }
                if x % y != 0 {
                    return self.error(
                        Diagnostic::error(Code::BadValue, format!("{x} / {y} is not a whole number"))
                            .with_primary(span, "inexact division")
                            .with_note("`/` on ints must divide exactly; use `//` to round down or a float operand"),
                    );
                }
                x.checked_div(y)
            }
            FloorDiv => {
                if y == 0 {
                    return div_zero(self);
                }
                // Python semantics: round towards negative infinity.
                x.checked_div(y).map(|q| if x % y != 0 && ((x < 0) != (y < 0)) { q - 1 } else { q })
            }
            Mod => {
                if y == 0 {
                    return div_zero(self);
                }
                // Python semantics: the result has the sign of the divisor.
                x.checked_rem(y).map(|r| if r != 0 && ((r < 0) != (y < 0)) { r + y } else { r })
            }
            Pow => {
                if y < 0 {
                    let v = (x as f64).powf(y as f64);
                    if v.is_finite() {
                        return Value::Float(v);
                    }
                    // `0 ** -1`: infinite, which no plan can hold.
                    return self.error(
                        Diagnostic::error(Code::BadValue, format!("`{x} ** {y}` gives {v}"))
                            .with_primary(span, "not a finite number"),
                    );
                }
                u32::try_from(y).ok().and_then(|e| x.checked_pow(e))
            }
            _ => {
                return self.error(
                    Diagnostic::error(Code::TypeMismatch, format!("`{}` needs bools, found ints", op.as_str()))
                        .with_primary(span, "invalid operands"),
                );
            }
        };
        match r {
            Some(v) => Value::Int(v),
            None => self.overflow(span),
        }
    }

    fn member(&mut self, base: Value, name: &str, span: Span, base_span: Span) -> Value {
        let scope = match &base {
            Value::Poison => return Value::Poison,
            Value::Tensor { scope: Some(s), .. } | Value::Scope(s) => *s,
            Value::List(items) => {
                if let Ok(i) = name.parse::<usize>()
                    && let Some(v) = items.get(i)
                {
                    return v.clone();
                }
                return self.error(
                    Diagnostic::error(Code::UnknownName, format!("this list has no element `{name}`"))
                        .with_primary(span, format!("the list has {} elements", items.len())),
                );
            }
            other => {
                return self.error(
                    Diagnostic::error(Code::TypeMismatch, format!("{} has no layer `{name}`", other.kind()))
                        .with_primary(span, "no such member")
                        .with_secondary(base_span, "this has no named layers"),
                );
            }
        };
        if let Some((v, _)) = self.tables[scope.0 as usize].names.get(name) {
            return v.clone();
        }
        let path = self.graph.scope(scope).path.clone();
        let mut names: Vec<&str> = self.tables[scope.0 as usize].names.keys().map(String::as_str).collect();
        names.sort_unstable();
        let mut d = Diagnostic::error(Code::UnknownName, format!("`{}` has no layer `{name}`", display_path(&path)))
            .with_primary(span, "no such layer");
        if let Some(s) = suggest(name, names.iter().copied()) {
            d = d.with_note(format!("did you mean `{s}`?"));
        } else if !names.is_empty() {
            d = d.with_note(format!("its layers are: {}", names.join(", ")));
        }
        self.error(d)
    }

    fn index(
        &mut self,
        base: Value,
        idx: Value,
        idx_span: Span,
        base_span: Span,
        hint: Option<Hint>,
        scope: ScopeId,
    ) -> Value {
        match (&base, &idx) {
            (Value::Poison, _) | (_, Value::Poison) => Value::Poison,
            (Value::List(items), Value::Int(i)) => {
                let n = items.len() as i64;
                let j = if *i < 0 { i + n } else { *i };
                match usize::try_from(j).ok().and_then(|j| items.get(j)) {
                    Some(v) => v.clone(),
                    None => self.error(
                        Diagnostic::error(Code::BadValue, format!("index {i} is out of range for a list of {n}"))
                            .with_primary(idx_span, "out of range"),
                    ),
                }
            }
            (Value::Tensor { scope: Some(_), .. } | Value::Scope(_), Value::Int(i)) => {
                self.member(base.clone(), &i.to_string(), idx_span, base_span)
            }
            (Value::Tensor { .. }, Value::Int(i)) => {
                self.index_tensor(base.clone(), *i, idx_span, base_span, hint, scope)
            }
            (_, Value::Int(_)) => self.error(
                Diagnostic::error(Code::TypeMismatch, format!("cannot index {}", base.kind()))
                    .with_primary(base_span, "not a list, sequence or tensor"),
            ),
            _ => self.error(
                Diagnostic::error(Code::TypeMismatch, format!("an index must be an int, found {}", idx.kind()))
                    .with_primary(idx_span, "not an int"),
            ),
        }
    }
}

/// The result of a comparison operator; `None` for the other operators.
fn compare<T: PartialOrd>(op: BinaryOp, x: T, y: T) -> Option<bool> {
    Some(match op {
        BinaryOp::Eq => x == y,
        BinaryOp::Ne => x != y,
        BinaryOp::Lt => x < y,
        BinaryOp::Le => x <= y,
        BinaryOp::Gt => x > y,
        BinaryOp::Ge => x >= y,
        _ => return None,
    })
}

fn tensor_kind(op: BinaryOp) -> Option<TensorOp> {
    match op {
        BinaryOp::Add => Some(TensorOp::Add),
        BinaryOp::Sub => Some(TensorOp::Sub),
        BinaryOp::Mul => Some(TensorOp::Mul),
        BinaryOp::Div => Some(TensorOp::Div),
        BinaryOp::Pow => Some(TensorOp::Pow),
        BinaryOp::Eq => Some(TensorOp::Eq),
        BinaryOp::Ne => Some(TensorOp::Ne),
        BinaryOp::Lt => Some(TensorOp::Lt),
        BinaryOp::Le => Some(TensorOp::Le),
        BinaryOp::Gt => Some(TensorOp::Gt),
        BinaryOp::Ge => Some(TensorOp::Ge),
        BinaryOp::FloorDiv => Some(TensorOp::FloorDiv),
        BinaryOp::Mod => Some(TensorOp::Remainder),
        _ => None,
    }
}

pub(super) fn as_f64(v: &Value) -> f64 {
    match v {
        Value::Int(i) => *i as f64,
        Value::Float(f) => *f,
        _ => f64::NAN,
    }
}

fn as_dim(v: &Value) -> Dim {
    match v {
        Value::Int(i) => Dim::known(*i),
        Value::Dim(d) => d.clone(),
        _ => Dim::known(0),
    }
}
