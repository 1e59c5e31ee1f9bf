//! Statements: `input`, `output`, `let`, `if`, `return`, namespaces (`name { ... }`) and
//! layer assignments (`name = expr`), and the items of a `seq` body with its `for` loops.
//!
//! Separate from expression evaluation because statements are where names are claimed in
//! a scope and where the model's inputs and outputs are declared; a `seq` body runs its
//! items in order like a statement list, so it lives here too.

use readi_grammar::ast::{self, Expr, LayerName, SeqItem, Stmt, StmtKind};
use readi_grammar::diag::{Code, Diagnostic, Span};

use super::{Elab, Frame, Hint, Value, restore};
use crate::ir::*;

impl<'a> Elab<'a> {
    pub(super) fn exec_body(&mut self, stmts: &'a [Stmt], frame: &mut Frame<'a>) {
        for s in stmts {
            if self.aborted {
                return;
            }
            if frame.ret.is_some() {
                self.error(
                    Diagnostic::error(Code::Misplaced, "statement after `return` is never run")
                        .with_primary(s.span, "unreachable"),
                );
                return;
            }
            self.exec(s, frame);
        }
    }

    fn exec(&mut self, s: &'a Stmt, frame: &mut Frame<'a>) {
        match &s.kind {
            StmtKind::Input(decl) => self.exec_input(decl, s.span, frame),
            StmtKind::Output { name, value } => self.exec_output(name, value.as_ref(), s.span, frame),
            StmtKind::Let { name, value } => {
                let v = self.eval(value, frame, None);
                frame.vars.insert(name.name.clone(), v);
            }
            StmtKind::If { branches, otherwise } => {
                for (cond, body) in branches {
                    match self.eval(cond, frame, None) {
                        Value::Bool(true) => return self.exec_body(&body.stmts, frame),
                        Value::Bool(false) => {}
                        Value::Poison => return,
                        v => {
                            self.error(
                                Diagnostic::error(Code::TypeMismatch, format!("`if` needs a bool, found {}", v.kind()))
                                    .with_primary(cond.span, "not a bool"),
                            );
                            return;
                        }
                    }
                }
                if let Some(body) = otherwise {
                    self.exec_body(&body.stmts, frame);
                }
            }
            StmtKind::Return(value) => {
                if frame.block.is_none() {
                    self.error(
                        Diagnostic::error(Code::Misplaced, "`return` belongs in a block; a model uses `output`")
                            .with_primary(s.span, "not in a block"),
                    );
                    return;
                }
                let v = self.eval(value, frame, None);
                frame.ret = Some(v);
            }
            StmtKind::Scope { name, body } => {
                let Some(hint) = self.claim_name(name, frame) else { return };
                let scope = self.new_scope(&hint, ScopeKind::Namespace, s.span);
                let mut inner = Frame { vars: frame.vars.clone(), scope, block: frame.block, ret: None };
                // Inside, the namespace's own name reaches the layers defined so far, so
                // layers named by an index refer to their siblings: `1 = relu(features.0)`;
                // unless the name means something already (an input `camera` read inside
                // the namespace `camera`).
                if let LayerName::Ident(id) = name
                    && !inner.vars.contains_key(&id.name)
                {
                    inner.vars.insert(id.name.clone(), Value::Scope(scope));
                }
                self.exec_body(&body.stmts, &mut inner);
                if inner.ret.is_some() {
                    self.error(
                        Diagnostic::error(Code::Misplaced, "`return` inside a namespace")
                            .with_primary(s.span, "return from the block instead"),
                    );
                }
                self.bind_name(name, hint.name, Value::Scope(scope), frame);
            }
            StmtKind::Named { name, value } => {
                let Some(hint) = self.claim_name(name, frame) else { return };
                let text = hint.name.clone();
                let v = self.eval(value, frame, Some(hint));
                self.bind_name(name, text, v, frame);
            }
        }
    }

    fn exec_input(&mut self, decl: &'a ast::InputDecl, span: Span, frame: &mut Frame<'a>) {
        if frame.block.is_some() {
            self.error(
                Diagnostic::error(Code::Misplaced, "`input` belongs in the model; blocks take tensors as parameters")
                    .with_primary(span, "inside a block"),
            );
            return;
        }
        let name = &decl.name.name;
        if frame.vars.contains_key(name) {
            self.error(
                Diagnostic::error(Code::DuplicateName, format!("`{name}` is already defined"))
                    .with_primary(decl.name.span, "input of the same name"),
            );
            return;
        }
        self.symbols_allowed = true;
        let mut shape = Vec::new();
        let mut ok = true;
        for d in &decl.dims {
            match self.eval(d, frame, None) {
                Value::Int(i) if i >= 1 => shape.push(Dim::known(i)),
                Value::Dim(dim) => shape.push(dim),
                Value::Poison => ok = false,
                Value::Int(i) => {
                    ok = false;
                    self.error(
                        Diagnostic::error(Code::BadValue, format!("input dimensions must be at least 1, got {i}"))
                            .with_primary(d.span, "not a valid size"),
                    );
                }
                v => {
                    ok = false;
                    self.error(
                        Diagnostic::error(
                            Code::TypeMismatch,
                            format!("input dimensions are ints or symbols, found {}", v.kind()),
                        )
                        .with_primary(d.span, "not a size"),
                    );
                }
            }
        }
        self.symbols_allowed = false;
        if !ok {
            frame.vars.insert(name.clone(), Value::Poison);
            return;
        }
        let ty = TensorType::new(decl.dtype.0, shape);
        if let Some(d) = self.size_error(name, std::slice::from_ref(&ty), span) {
            self.error(d);
            frame.vars.insert(name.clone(), Value::Poison);
            return;
        }
        let op = Op::Input(InputAttrs {
            name: name.clone(),
            modality: decl.modality.as_ref().map(|m| m.name.clone()),
            optional: decl.optional,
        });
        let id = self.graph.add_node(Node::new(op, name.clone(), frame.scope, vec![], vec![ty], span), &[]);
        frame.vars.insert(name.clone(), Value::Tensor { value: ValueRef { node: id, port: 0 }, scope: None });
    }

    fn exec_output(&mut self, name: &ast::Ident, value: Option<&'a Expr>, span: Span, frame: &mut Frame<'a>) {
        if frame.block.is_some() {
            self.error(
                Diagnostic::error(Code::Misplaced, "`output` belongs in the model; blocks use `return`")
                    .with_primary(span, "inside a block"),
            );
            return;
        }
        let v = match value {
            Some(e) => self.eval(e, frame, None),
            None => self.lookup_var(&name.name, name.span, frame),
        };
        if let Some(prev) = self.graph.outputs.iter().find(|o| o.name == name.name) {
            let prev = prev.span;
            self.error(
                Diagnostic::error(Code::DuplicateName, format!("output `{}` is declared twice", name.name))
                    .with_primary(name.span, "second declaration")
                    .with_secondary(prev, "first declaration here"),
            );
            return;
        }
        match v {
            Value::Tensor { value, .. } => {
                self.graph.outputs.push(GraphOutput { name: name.name.clone(), value, span });
            }
            Value::Poison => {}
            other => {
                self.error(
                    Diagnostic::error(
                        Code::TypeMismatch,
                        format!("an output must be a tensor, found {}", other.kind()),
                    )
                    .with_primary(value.map(|e| e.span).unwrap_or(name.span), "not a tensor"),
                );
            }
        }
    }

    pub(super) fn seq_items(
        &mut self,
        items: &'a [SeqItem],
        mut cur: Value,
        scope: ScopeId,
        counter: &mut usize,
        frame: &mut Frame<'a>,
    ) -> Value {
        for item in items {
            if self.aborted {
                return Value::Poison;
            }
            match item {
                SeqItem::Call { name, callee, args, span } => {
                    let layer = name.clone().unwrap_or(LayerName::Index(*counter as u64, callee.span));
                    *counter += 1;
                    let text = match name {
                        Some(n) => match self.layer_text(n, frame) {
                            Some(t) => t,
                            None => {
                                cur = Value::Poison;
                                continue;
                            }
                        },
                        None => layer.text(),
                    };
                    if let Some((_, prev)) = self.tables[scope.0 as usize].names.get(&text) {
                        let prev = *prev;
                        self.error(
                            Diagnostic::error(
                                Code::DuplicateName,
                                format!("`{text}` is already defined in this sequence"),
                            )
                            .with_primary(layer.span(), "defined again here")
                            .with_secondary(prev, "first defined here"),
                        );
                        cur = Value::Poison;
                        continue;
                    }
                    let mut vals = Vec::with_capacity(args.len() + 1);
                    vals.push((None, cur, callee.span));
                    for a in args {
                        vals.push((a.name.clone(), self.eval(&a.value, frame, None), a.value.span));
                    }
                    let hint = Hint { scope, name: text.clone() };
                    cur = self.call(callee, vals, *span, Some(hint), frame);
                    self.tables[scope.0 as usize].names.insert(text, (cur.clone(), layer.span()));
                }
                SeqItem::For { var, start, end, items, .. } => {
                    let Some((a, b)) = self.range(start, end, frame) else { return Value::Poison };
                    let saved = frame.vars.get(&var.name).cloned();
                    for i in a..b {
                        frame.vars.insert(var.name.clone(), Value::Int(i));
                        cur = self.seq_items(items, cur, scope, counter, frame);
                        if self.aborted {
                            break;
                        }
                    }
                    restore(&mut frame.vars, &var.name, saved);
                }
                SeqItem::If { branches, otherwise, .. } => {
                    let mut taken = None;
                    for (cond, items) in branches {
                        match self.eval(cond, frame, None) {
                            Value::Bool(true) => {
                                taken = Some(items);
                                break;
                            }
                            Value::Bool(false) => {}
                            Value::Poison => return Value::Poison,
                            v => {
                                return self.error(
                                    Diagnostic::error(
                                        Code::TypeMismatch,
                                        format!("`if` needs a bool, found {}", v.kind()),
                                    )
                                    .with_primary(cond.span, "not a bool"),
                                );
                            }
                        }
                    }
                    if let Some(items) = taken.or(otherwise.as_ref()) {
                        cur = self.seq_items(items, cur, scope, counter, frame);
                    }
                }
            }
        }
        cur
    }
}
