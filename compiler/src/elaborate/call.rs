//! Calls: builtin ops and functions, block instantiation, and the binding of call
//! arguments to parameters (positional, keyword, defaults).
//!
//! Separate because a call is where the elaborator leaves expression arithmetic: it checks
//! arguments against a signature, builds a node through `builtins`, or runs a block body
//! in a new scope and frame.

use std::collections::HashMap;
use std::rc::Rc;

use readi_grammar::ast::{self, BlockDef};
use readi_grammar::diag::{Code, Diagnostic, Span, suggest};

use super::builtins;
use super::eval::as_f64;
use super::{Call, Elab, Frame, Hint, MAX_BLOCK_DEPTH, Value};
use crate::ir::*;
use crate::ops::pytorch::Spelling;
use crate::ops::{Args, Def};

impl<'a> Elab<'a> {
    pub(super) fn call(
        &mut self,
        callee: &'a ast::Ident,
        args: Vec<(Option<ast::Ident>, Value, Span)>,
        span: Span,
        hint: Option<Hint>,
        frame: &mut Frame<'a>,
    ) -> Value {
        let name = callee.name.as_str();
        // `min(a, b)` and `max(a, b)` of numbers are functions; with a tensor, reductions.
        let op = crate::ops::builtin(name).filter(|_| {
            builtins::function(name).is_none() || args.iter().any(|(_, v, _)| matches!(v, Value::Tensor { .. }))
        });
        if let Some(sig) = op.map(|b| &b.sig).or_else(|| builtins::function(name)) {
            let Some(values) = self.bind_args(
                name,
                sig.params.iter().map(|p| (p.name, !matches!(p.default, Def::Required))).collect(),
                args,
                span,
            ) else {
                return Value::Poison;
            };
            let values: Vec<Option<(Value, Span)>> = values
                .into_iter()
                .zip(sig.params)
                .map(|(v, p)| v.or_else(|| default_value(p.default).map(|d| (d, span))))
                .collect();
            if values.iter().flatten().any(|(v, _)| v.is_poison() || contains_poison(v)) {
                return Value::Poison;
            }
            let Some(op) = op else { return self.call_function(name, &values, span) };
            let args = Args { sig, values, call_span: span, graph: &self.graph };
            return match op.make {
                crate::ops::Make::One(build) => match build(&args) {
                    Ok((op, inputs)) => self.add_node_in(op, inputs, hint, span, frame.scope),
                    Err(d) => self.error(d),
                },
                crate::ops::Make::Many(many) => match many(&args) {
                    Ok(pieces) => self.add_nodes_as_list(pieces, hint, span, frame.scope),
                    Err(d) => self.error(d),
                },
            };
        }
        if let Some(&def) = self.blocks.get(name) {
            return self.call_block(def, args, span, hint, frame);
        }
        let mut d = Diagnostic::error(Code::UnknownName, format!("unknown op or block `{name}`"))
            .with_primary(callee.span, "not an op, block or function");
        // A PyTorch (spconv, mmcv) name gets its own answer, never a nearby one (`relu6` is not `relu`).
        match crate::ops::pytorch::lookup(name) {
            Some((lib, Spelling::Readi(s))) if s.contains(' ') => {
                return self.error(d.with_note(format!("{lib}'s `{name}` is {s}")));
            }
            Some((lib, Spelling::Readi(s))) => {
                return self.error(d.with_note(format!("{lib}'s `{name}` is written `{s}` in readi")));
            }
            Some((lib, Spelling::Unsupported)) => {
                return self.error(d.with_note(format!("{lib}'s `{name}` is not supported (yet)")));
            }
            None => {}
        }
        let mut candidates: Vec<&str> = builtins::names().collect();
        candidates.extend(self.blocks.keys().copied());
        if let Some(s) = suggest(name, candidates) {
            d = d.with_note(format!("did you mean `{s}`?"));
        }
        self.error(d)
    }

    /// The nodes of a list-valued builtin (`chunk`, `split`): named `0`, `1`, ... in a
    /// list scope when the call is named, like a list literal's elements.
    fn add_nodes_as_list(
        &mut self,
        pieces: Vec<(Op, Vec<ValueRef>)>,
        hint: Option<Hint>,
        span: Span,
        scope: ScopeId,
    ) -> Value {
        let list_scope = hint.map(|h| self.new_scope(&h, ScopeKind::List, span));
        let mut out = Vec::with_capacity(pieces.len());
        for (k, (op, inputs)) in pieces.into_iter().enumerate() {
            let h = list_scope.map(|s| Hint { scope: s, name: k.to_string() });
            let v = self.add_node_in(op, inputs, h, span, scope);
            if let Some(s) = list_scope {
                self.tables[s.0 as usize].names.insert(k.to_string(), (v.clone(), span));
            }
            out.push(v);
        }
        Value::List(Rc::new(out))
    }

    /// Matches call arguments to parameters `(name, optional)`: positional first, then by
    /// keyword. Returns one slot per parameter, or `None` after reporting errors.
    fn bind_args(
        &mut self,
        callee: &str,
        params: Vec<(&str, bool)>,
        args: Vec<(Option<ast::Ident>, Value, Span)>,
        span: Span,
    ) -> Option<Vec<Option<(Value, Span)>>> {
        let mut slots: Vec<Option<(Value, Span)>> = vec![None; params.len()];
        let mut ok = true;
        // Parameters a misspelt keyword was probably meant for: not reported missing too.
        let mut suggested: Vec<&str> = Vec::new();
        let mut positional = 0;
        let mut seen_keyword = false;
        for (name, v, vspan) in args {
            match name {
                None => {
                    if seen_keyword {
                        self.error(
                            Diagnostic::error(Code::BadArgument, "a positional argument follows a keyword argument")
                                .with_primary(vspan, "move this before the keyword arguments"),
                        );
                        ok = false;
                        continue;
                    }
                    if positional >= params.len() {
                        self.error(
                            Diagnostic::error(
                                Code::BadArgument,
                                format!(
                                    "`{callee}` takes at most {} argument{}",
                                    params.len(),
                                    if params.len() == 1 { "" } else { "s" }
                                ),
                            )
                            .with_primary(vspan, "extra argument")
                            .with_note(format!(
                                "parameters: {}",
                                params.iter().map(|p| p.0).collect::<Vec<_>>().join(", ")
                            )),
                        );
                        ok = false;
                        continue;
                    }
                    slots[positional] = Some((v, vspan));
                    positional += 1;
                }
                Some(id) => {
                    seen_keyword = true;
                    match params.iter().position(|p| p.0 == id.name) {
                        Some(i) if slots[i].is_some() => {
                            self.error(
                                Diagnostic::error(Code::BadArgument, format!("argument `{}` is given twice", id.name))
                                    .with_primary(id.span, "given again here"),
                            );
                            ok = false;
                        }
                        Some(i) => slots[i] = Some((v, vspan)),
                        None => {
                            let mut d = Diagnostic::error(
                                Code::BadArgument,
                                format!("`{callee}` has no parameter `{}`", id.name),
                            )
                            .with_primary(id.span, "unknown parameter");
                            match suggest(&id.name, params.iter().map(|p| p.0)) {
                                Some(s) => {
                                    suggested.push(s);
                                    d = d.with_note(format!("did you mean `{s}`?"));
                                }
                                None => {
                                    d = d.with_note(format!(
                                        "parameters: {}",
                                        params.iter().map(|p| p.0).collect::<Vec<_>>().join(", ")
                                    ))
                                }
                            }
                            self.error(d);
                            ok = false;
                        }
                    }
                }
            }
        }
        let missing: Vec<&str> = params
            .iter()
            .zip(&slots)
            .filter(|((n, opt), s)| !opt && s.is_none() && !suggested.contains(n))
            .map(|((n, _), _)| *n)
            .collect();
        if !missing.is_empty() {
            let list = missing.iter().map(|m| format!("`{m}`")).collect::<Vec<_>>().join(", ");
            self.error(
                Diagnostic::error(Code::BadArgument, format!("`{callee}` is missing argument {list}"))
                    .with_primary(span, format!("needs {list}")),
            );
            ok = false;
        }
        ok.then_some(slots)
    }

    fn call_function(&mut self, name: &str, values: &[Option<(Value, Span)>], span: Span) -> Value {
        let arg = |i: usize| values.get(i).and_then(|v| v.clone()).unwrap_or((Value::Poison, span));
        match name {
            "dim" | "rank" => {
                let (x, xs) = arg(0);
                let Value::Tensor { value, .. } = x else {
                    return self.error(
                        Diagnostic::error(Code::TypeMismatch, format!("`{name}` needs a tensor, found {}", x.kind()))
                            .with_primary(xs, "not a tensor"),
                    );
                };
                let Some(t) = self.graph.value_type(value).cloned() else { return Value::Poison };
                if name == "rank" {
                    return Value::Int(t.rank() as i64);
                }
                let (a, aspan) = arg(1);
                let Value::Int(a) = a else {
                    return self.error(
                        Diagnostic::error(Code::TypeMismatch, format!("an axis must be an int, found {}", a.kind()))
                            .with_primary(aspan, "not an int"),
                    );
                };
                let r = t.rank() as i64;
                let ax = if a < 0 { a + r } else { a };
                match usize::try_from(ax).ok().and_then(|i| t.shape.get(i)) {
                    Some(d) => d.as_known().map(Value::Int).unwrap_or_else(|| Value::Dim(d.clone())),
                    None => self.error(
                        Diagnostic::error(Code::BadValue, format!("axis {a} is out of range for {t}"))
                            .with_primary(aspan, "out of range"),
                    ),
                }
            }
            "len" => match arg(0) {
                (Value::List(l), _) => Value::Int(l.len() as i64),
                (v, s) => self.error(
                    Diagnostic::error(Code::TypeMismatch, format!("`len` needs a list, found {}", v.kind()))
                        .with_primary(s, "not a list"),
                ),
            },
            _ => {
                let (a, _) = arg(0);
                let (b, bs) = arg(1);
                let pick_b = match (&a, &b) {
                    (Value::Int(x), Value::Int(y)) => (name == "min") == (y < x),
                    (Value::Int(_) | Value::Float(_), Value::Int(_) | Value::Float(_)) => {
                        (name == "min") == (as_f64(&b) < as_f64(&a))
                    }
                    _ => {
                        return self.error(
                            Diagnostic::error(Code::TypeMismatch, format!("`{name}` needs numbers"))
                                .with_primary(bs.to(span), "not numbers"),
                        );
                    }
                };
                if pick_b { b } else { a }
            }
        }
    }

    fn call_block(
        &mut self,
        def: &'a BlockDef,
        args: Vec<(Option<ast::Ident>, Value, Span)>,
        span: Span,
        hint: Option<Hint>,
        frame: &mut Frame<'a>,
    ) -> Value {
        let name = def.name.name.as_str();
        self.used_blocks.insert(name.to_string());
        if self.stack.iter().any(|c| c.block == name) {
            let mut cycle: Vec<&str> = self.stack.iter().map(|c| c.block.as_str()).collect();
            let start = cycle.iter().position(|b| *b == name).unwrap_or(0);
            cycle = cycle.split_off(start);
            cycle.push(name);
            return self.error(
                Diagnostic::error(Code::RecursiveBlock, format!("block `{name}` is recursive"))
                    .with_primary(span, "this call never ends")
                    .with_secondary(def.name.span, "block defined here")
                    .with_note(format!("call cycle: {}", cycle.join(" -> "))),
            );
        }
        if self.stack.len() >= MAX_BLOCK_DEPTH {
            self.abort(span, format!("block instances are nested more than {MAX_BLOCK_DEPTH} deep"));
            return Value::Poison;
        }
        let params: Vec<(&str, bool)> =
            def.params.iter().map(|p| (p.name.name.as_str(), p.default.is_some())).collect();
        let Some(slots) = self.bind_args(name, params, args, span) else { return Value::Poison };
        let hint = match hint {
            Some(h) => h,
            None => Hint { scope: frame.scope, name: self.anon_name(frame.scope, name) },
        };
        let scope = self.new_scope(&hint, ScopeKind::Block(name.to_string()), span);
        let path = self.graph.scope(scope).path.clone();
        let mut inner = Frame { vars: HashMap::new(), scope, block: Some(def), ret: None };
        self.stack.push(Call { block: name.to_string(), span, path });
        for (p, slot) in def.params.iter().zip(slots) {
            let v = match slot {
                Some((v, _)) => v,
                None => match &p.default {
                    Some(d) => self.eval(d, &mut inner, None),
                    None => Value::Poison,
                },
            };
            let v = self.check_param_type(p, v);
            inner.vars.insert(p.name.name.clone(), v);
        }
        self.exec_body(&def.body.stmts, &mut inner);
        self.stack.pop();
        match inner.ret {
            Some(Value::Tensor { value, .. }) => Value::Tensor { value, scope: Some(scope) },
            Some(v) => v,
            None => Value::Scope(scope),
        }
    }
}

fn default_value(d: Def) -> Option<Value> {
    match d {
        Def::Required | Def::Absent => None,
        Def::Int(i) => Some(Value::Int(i)),
        Def::Float(f) => Some(Value::Float(f)),
        Def::Bool(b) => Some(Value::Bool(b)),
        Def::Str(s) => Some(Value::Str(Rc::from(s))),
    }
}

fn contains_poison(v: &Value) -> bool {
    match v {
        Value::Poison => true,
        Value::List(l) => l.iter().any(contains_poison),
        _ => false,
    }
}
