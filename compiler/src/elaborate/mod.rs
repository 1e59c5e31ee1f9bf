//! Elaboration: evaluates a parsed file into the graph IR.
//!
//! The model body is run as a small program: blocks are called like functions, `seq`
//! chains items, `if` and list comprehensions are decided here, and attribute arithmetic
//! (`c * 2`, `dim / heads`) is computed. Every op call adds a node whose output types are
//! inferred on the spot, so later expressions can ask for shapes (`dim(x, 1)`).
//!
//! Naming: `name = expr` gives the node (or block instance, `seq`, list) that `expr`
//! creates the path segment `name` in the current scope, so paths are PyTorch
//! `state_dict` prefixes (`layer1.0.conv1`). Nodes created without a name get
//! `<op>#<k>`; a node with parameters must be named.
//!
//! Errors do not stop elaboration: a failed expression yields a poison value that
//! silences its dependants, so one run reports every independent mistake. An error inside
//! a block body is reported once, with the instance that triggered it.

mod builtins;
mod value;

use std::collections::{HashMap, HashSet};
use std::rc::Rc;

use readi_grammar::ast::{
    self, BinaryOp, BlockDef, Expr, ExprKind, LayerName, SeqItem, Stmt, StmtKind, TypeName, UnaryOp,
};
use readi_grammar::diag::{Code, Diagnostic, Diagnostics, FileId, Span, suggest};

use crate::infer::{self, infer};
use crate::ir::*;
use builtins::{Args, BuiltinKind, Def};
pub use value::Value;

/// Maximum number of nodes a model may elaborate to.
pub const MAX_NODES: usize = 200_000;
/// Maximum depth of nested block instances.
pub const MAX_BLOCK_DEPTH: usize = 32;
/// Maximum length of one range (`for i in a..b`, `[... for i in a..b]`).
pub const MAX_RANGE: i64 = 100_000;
/// Maximum number of expression evaluations in one elaboration.
pub const MAX_STEPS: u64 = 5_000_000;

/// A value given on the command line for a model parameter (`--set num_classes=10`).
#[derive(Clone, Debug, PartialEq)]
pub enum Literal {
    Int(i64),
    Float(f64),
    Bool(bool),
    Str(String),
}

impl Literal {
    /// Parses `10`, `0.5`, `true` or any other text (a string).
    pub fn parse(text: &str) -> Literal {
        if let Ok(i) = text.parse::<i64>() {
            Literal::Int(i)
        } else if let Ok(f) = text.parse::<f64>()
            && f.is_finite()
        {
            Literal::Float(f)
        } else if text == "true" || text == "false" {
            Literal::Bool(text == "true")
        } else {
            Literal::Str(text.to_string())
        }
    }
}

/// Options of elaboration.
#[derive(Clone, Debug, Default)]
pub struct ElabOptions {
    /// Model parameter values that replace the defaults.
    pub overrides: Vec<(String, Literal)>,
}

/// Elaborates the model of `file` into a graph. Returns the graph (complete only when the
/// diagnostics hold no errors) and the diagnostics.
pub fn elaborate(file: &ast::SourceFile, file_id: FileId, opts: &ElabOptions) -> (Option<Graph>, Diagnostics) {
    let mut e = Elab::new(file_id);
    let graph = e.run(file, opts);
    e.diags.sort();
    (graph, e.diags)
}

/// A name a statement gives to what its expression creates.
#[derive(Clone, Debug)]
struct Hint {
    scope: ScopeId,
    name: String,
}

/// Named things of one scope, for member access and duplicate detection.
#[derive(Default)]
struct ScopeTable {
    names: HashMap<String, (Value, Span)>,
    anon: HashMap<String, u32>,
}

/// The variables of one block body (or the model body) being evaluated.
struct Frame<'a> {
    vars: HashMap<String, Value>,
    scope: ScopeId,
    block: Option<&'a BlockDef>,
    ret: Option<Value>,
}

/// One active block call, for recursion detection and error context.
struct Call {
    block: String,
    span: Span,
    path: String,
}

struct Elab<'a> {
    file: FileId,
    blocks: HashMap<&'a str, &'a BlockDef>,
    used_blocks: HashSet<String>,
    graph: Graph,
    tables: Vec<ScopeTable>,
    diags: Diagnostics,
    reported: HashSet<(Code, Span)>,
    stack: Vec<Call>,
    steps: u64,
    aborted: bool,
    symbols_allowed: bool,
}

impl<'a> Elab<'a> {
    fn new(file: FileId) -> Elab<'a> {
        Elab {
            file,
            blocks: HashMap::new(),
            used_blocks: HashSet::new(),
            graph: Graph::new("", Span::new(file, 0, 0)),
            tables: vec![ScopeTable::default()],
            diags: Diagnostics::default(),
            reported: HashSet::new(),
            stack: Vec::new(),
            steps: 0,
            aborted: false,
            symbols_allowed: false,
        }
    }

    // ---------------------------------------------------------------------------------
    // Diagnostics
    // ---------------------------------------------------------------------------------

    /// Records an error (once per code and place, with the innermost block instance as
    /// context) and returns poison.
    fn error(&mut self, mut d: Diagnostic) -> Value {
        if let Some(span) = d.primary_span()
            && !self.reported.insert((d.code, span))
        {
            return Value::Poison;
        }
        if let Some(call) = self.stack.last() {
            let inside = d.primary_span().is_some_and(|s| s != call.span);
            if inside {
                d = d.with_secondary(
                    call.span,
                    format!("in `{}`, an instance of `{}`", display_path(&call.path), call.block),
                );
            }
        }
        self.diags.push(d);
        Value::Poison
    }

    fn step(&mut self, span: Span) -> bool {
        if self.aborted {
            return false;
        }
        self.steps += 1;
        if self.steps > MAX_STEPS {
            self.abort(span, format!("elaboration took more than {MAX_STEPS} steps"));
            return false;
        }
        true
    }

    fn abort(&mut self, span: Span, message: String) {
        if !self.aborted {
            self.aborted = true;
            self.diags.push(
                Diagnostic::error(Code::Limit, message)
                    .with_primary(span, "while elaborating this")
                    .with_note("the model is too large or never stops growing; check loop ranges and recursion"),
            );
        }
    }

    // ---------------------------------------------------------------------------------
    // File level
    // ---------------------------------------------------------------------------------

    fn run(&mut self, file: &'a ast::SourceFile, opts: &ElabOptions) -> Option<Graph> {
        self.collect_blocks(file);
        let models: Vec<&ast::ModelDef> = file.models().collect();
        let model = match models.as_slice() {
            [] => {
                self.diags.push(
                    Diagnostic::error(Code::ModelCount, "this file has no `model`")
                        .with_primary(Span::new(self.file, 0, 0), "expected `model name { ... }`")
                        .with_note("a .readi file describes one network in a `model` item"),
                );
                return None;
            }
            [m, rest @ ..] => {
                for extra in rest {
                    self.diags.push(
                        Diagnostic::error(Code::ModelCount, "a file holds one `model`")
                            .with_primary(extra.name.span, "second model")
                            .with_secondary(m.name.span, "first model here"),
                    );
                }
                *m
            }
        };
        for (kind, spans) in [
            ("adapt", file.adapt_sections().map(|a| a.span).collect::<Vec<_>>()),
            ("variants", file.variant_sections().map(|v| v.span).collect::<Vec<_>>()),
        ] {
            for extra in spans.iter().skip(1) {
                self.diags.push(
                    Diagnostic::error(Code::DuplicateName, format!("a file holds one `{kind}` section"))
                        .with_primary(extra.head(), "second section")
                        .with_secondary(spans[0].head(), "first section here"),
                );
            }
        }
        self.graph = Graph::new(model.name.name.clone(), model.span);
        let mut frame = Frame { vars: HashMap::new(), scope: ScopeId(0), block: None, ret: None };
        self.bind_model_params(model, opts, &mut frame);
        self.exec_body(&model.body.stmts, &mut frame);
        if self.graph.outputs.is_empty() && !self.aborted && !self.diags.has_errors() {
            self.error(
                Diagnostic::error(Code::ModelCount, format!("model `{}` has no outputs", model.name.name))
                    .with_primary(model.name.span, "no `output` statement")
                    .with_note("add `output name = value` for each result of the network"),
            );
        }
        let mut unused: Vec<&&BlockDef> =
            self.blocks.values().filter(|b| !self.used_blocks.contains(&b.name.name)).collect();
        unused.sort_by_key(|b| b.span);
        for b in unused {
            self.diags.push(
                Diagnostic::warning(Code::Unused, format!("block `{}` is never used", b.name.name))
                    .with_primary(b.name.span, "defined here"),
            );
        }
        if self.aborted {
            return None;
        }
        Some(std::mem::replace(&mut self.graph, Graph::new("", Span::default())))
    }

    fn collect_blocks(&mut self, file: &'a ast::SourceFile) {
        for b in file.blocks() {
            let name = b.name.name.as_str();
            if builtins::builtin(name).is_some() {
                self.diags.push(
                    Diagnostic::error(Code::DuplicateName, format!("block `{name}` has the name of a builtin op"))
                        .with_primary(b.name.span, "rename this block"),
                );
                continue;
            }
            if let Some(prev) = self.blocks.get(name) {
                self.diags.push(
                    Diagnostic::error(Code::DuplicateName, format!("block `{name}` is defined twice"))
                        .with_primary(b.name.span, "second definition")
                        .with_secondary(prev.name.span, "first definition here"),
                );
                continue;
            }
            let mut seen: HashMap<&str, Span> = HashMap::new();
            for p in &b.params {
                if let Some(prev) = seen.insert(&p.name.name, p.name.span) {
                    self.diags.push(
                        Diagnostic::error(
                            Code::DuplicateName,
                            format!("parameter `{}` is declared twice", p.name.name),
                        )
                        .with_primary(p.name.span, "second declaration")
                        .with_secondary(prev, "first declaration here"),
                    );
                }
            }
            self.blocks.insert(name, b);
        }
    }

    fn bind_model_params(&mut self, model: &'a ast::ModelDef, opts: &ElabOptions, frame: &mut Frame<'a>) {
        for (name, _) in &opts.overrides {
            if !model.params.iter().any(|p| &p.name.name == name) {
                let names: Vec<&str> = model.params.iter().map(|p| p.name.name.as_str()).collect();
                let mut d = Diagnostic::error(
                    Code::BadArgument,
                    format!("`--set {name}`: model `{}` has no parameter `{name}`", model.name.name),
                )
                .with_primary(model.name.span, "parameters are declared here");
                if let Some(s) = suggest(name, names.iter().copied()) {
                    d = d.with_note(format!("did you mean `{s}`?"));
                }
                self.error(d);
            }
        }
        let mut out = Vec::new();
        for p in &model.params {
            let value = match opts.overrides.iter().rev().find(|(n, _)| *n == p.name.name) {
                Some((_, lit)) => match lit {
                    Literal::Int(i) => Value::Int(*i),
                    Literal::Float(f) => Value::Float(*f),
                    Literal::Bool(b) => Value::Bool(*b),
                    Literal::Str(s) => Value::Str(Rc::from(s.as_str())),
                },
                None => match &p.default {
                    Some(d) => self.eval(d, frame, None),
                    None => self.error(
                        Diagnostic::error(Code::BadArgument, format!("model parameter `{}` has no value", p.name.name))
                            .with_primary(p.name.span, "no default")
                            .with_note(format!("give it a default, or pass `--set {}=...`", p.name.name)),
                    ),
                },
            };
            let value = self.check_param_type(p, value);
            out.push((p.name.name.clone(), show_value(&value)));
            frame.vars.insert(p.name.name.clone(), value);
        }
        self.graph.model_params = out;
    }

    fn check_param_type(&mut self, p: &ast::Param, value: Value) -> Value {
        let Some((ty, ty_span)) = p.ty else { return value };
        let ok = matches!(
            (ty, &value),
            (_, Value::Poison)
                | (TypeName::Tensor, Value::Tensor { .. })
                | (TypeName::Int, Value::Int(_))
                | (TypeName::Int, Value::Dim(_))
                | (TypeName::Float, Value::Float(_))
                | (TypeName::Bool, Value::Bool(_))
                | (TypeName::Str, Value::Str(_))
                | (TypeName::List, Value::List(_))
        );
        match (ty, &value) {
            _ if ok => value,
            (TypeName::Float, Value::Int(i)) => Value::Float(*i as f64),
            _ => self.error(
                Diagnostic::error(
                    Code::TypeMismatch,
                    format!("parameter `{}` is declared `{}` but got {}", p.name.name, ty.as_str(), value.kind()),
                )
                .with_primary(p.name.span, format!("expects {}", ty.as_str()))
                .with_secondary(ty_span, "declared here"),
            ),
        }
    }

    // ---------------------------------------------------------------------------------
    // Statements
    // ---------------------------------------------------------------------------------

    fn exec_body(&mut self, stmts: &'a [Stmt], frame: &mut Frame<'a>) {
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
                self.exec_body(&body.stmts, &mut inner);
                if inner.ret.is_some() {
                    self.error(
                        Diagnostic::error(Code::Misplaced, "`return` inside a namespace")
                            .with_primary(s.span, "return from the block instead"),
                    );
                }
                self.bind_name(name, Value::Scope(scope), frame);
            }
            StmtKind::Named { name, value } => {
                let Some(hint) = self.claim_name(name, frame) else { return };
                let v = self.eval(value, frame, Some(hint));
                self.bind_name(name, v, frame);
            }
        }
    }

    /// Checks that `name` is free in the current scope and returns the hint for it.
    fn claim_name(&mut self, name: &LayerName, frame: &Frame<'a>) -> Option<Hint> {
        let text = name.text();
        if let Some((_, prev)) = self.tables[frame.scope.0 as usize].names.get(&text) {
            let prev = *prev;
            self.error(
                Diagnostic::error(Code::DuplicateName, format!("`{text}` is already defined in this scope"))
                    .with_primary(name.span(), "defined again here")
                    .with_secondary(prev, "first defined here")
                    .with_note("layer names are state_dict paths and must be unique; use `let` for a local value"),
            );
            return None;
        }
        Some(Hint { scope: frame.scope, name: text })
    }

    fn bind_name(&mut self, name: &LayerName, v: Value, frame: &mut Frame<'a>) {
        let text = name.text();
        self.tables[frame.scope.0 as usize].names.insert(text.clone(), (v.clone(), name.span()));
        if let LayerName::Ident(_) = name {
            frame.vars.insert(text, v);
        }
    }

    fn new_scope(&mut self, hint: &Hint, kind: ScopeKind, span: Span) -> ScopeId {
        let path = join_path(&self.graph.scope(hint.scope).path, &hint.name);
        let id = self.graph.add_scope(ScopeInfo { path, kind, parent: Some(hint.scope), span });
        self.tables.push(ScopeTable::default());
        id
    }

    /// An unused `<what>#<k>` name in a scope, for something the source did not name.
    fn anon_name(&mut self, scope: ScopeId, what: &str) -> String {
        let counter = self.tables[scope.0 as usize].anon.entry(what.to_string()).or_insert(0);
        let name = format!("{what}#{counter}");
        *counter += 1;
        name
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
        let ty = infer::input_type(decl.dtype.0, shape);
        let op = Op::Input(InputAttrs {
            name: name.clone(),
            modality: decl.modality.as_ref().map(|m| m.name.clone()),
            optional: decl.optional,
        });
        let id = self.graph.add_node(
            Node { op, path: name.clone(), scope: frame.scope, params: vec![], outputs: vec![ty], span },
            &[],
        );
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

    // ---------------------------------------------------------------------------------
    // Expressions
    // ---------------------------------------------------------------------------------

    fn lookup_var(&mut self, name: &str, span: Span, frame: &Frame<'a>) -> Value {
        if let Some(v) = frame.vars.get(name) {
            return v.clone();
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
        if builtins::builtin(name).is_some() || self.blocks.contains_key(name) {
            d = d.with_note(format!("`{name}` is an op or block; call it: `{name}(...)`"));
        } else if let Some(s) = suggest(name, frame.vars.keys().map(String::as_str)) {
            d = d.with_note(format!("did you mean `{s}`?"));
        }
        self.error(d)
    }

    fn eval(&mut self, e: &'a Expr, frame: &mut Frame<'a>, hint: Option<Hint>) -> Value {
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
                self.member(b, &name.text(), name.span(), base.span)
            }
            ExprKind::Index(base, idx) => {
                let b = self.eval(base, frame, None);
                let i = self.eval(idx, frame, None);
                self.index(b, i, idx.span, base.span)
            }
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
    fn range(&mut self, start: &'a Expr, end: &'a Expr, frame: &mut Frame<'a>) -> Option<(i64, i64)> {
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

    fn seq_items(
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
                    let text = layer.text();
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
            }
        }
        cur
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
                let op = Op::Scalar { kind: BinaryKind::Mul, value: -1.0, scalar_first: false };
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
                self.add_node_in(Op::Binary(kind), vec![*x, *y], hint, span, frame.scope)
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
                self.add_node_in(Op::Scalar { kind, value, scalar_first }, vec![*x], hint, span, frame.scope)
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
                    return Value::Float((x as f64).powf(y as f64));
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

    fn index(&mut self, base: Value, idx: Value, idx_span: Span, base_span: Span) -> Value {
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
            (_, Value::Int(_)) => self.error(
                Diagnostic::error(Code::TypeMismatch, format!("cannot index {}", base.kind()))
                    .with_primary(base_span, "not a list or sequence"),
            ),
            _ => self.error(
                Diagnostic::error(Code::TypeMismatch, format!("an index must be an int, found {}", idx.kind()))
                    .with_primary(idx_span, "not an int"),
            ),
        }
    }

    // ---------------------------------------------------------------------------------
    // Calls
    // ---------------------------------------------------------------------------------

    fn call(
        &mut self,
        callee: &'a ast::Ident,
        args: Vec<(Option<ast::Ident>, Value, Span)>,
        span: Span,
        hint: Option<Hint>,
        frame: &mut Frame<'a>,
    ) -> Value {
        let name = callee.name.as_str();
        if let Some(sig) = builtins::builtin(name) {
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
            return match sig.kind {
                BuiltinKind::Function => self.call_function(name, &values, span),
                BuiltinKind::Op => {
                    let built = {
                        let a = Args { sig, values, call_span: span, graph: &self.graph };
                        builtins::build_op(&a)
                    };
                    match built {
                        Ok((op, inputs)) => self.add_node_in(op, inputs, hint, span, frame.scope),
                        Err(d) => self.error(d),
                    }
                }
            };
        }
        if let Some(&def) = self.blocks.get(name) {
            return self.call_block(def, args, span, hint, frame);
        }
        let mut candidates: Vec<&str> = builtins::BUILTINS.iter().map(|s| s.name).collect();
        candidates.extend(self.blocks.keys().copied());
        let mut d = Diagnostic::error(Code::UnknownName, format!("unknown op or block `{name}`"))
            .with_primary(callee.span, "not an op, block or function");
        if let Some(s) = suggest(name, candidates) {
            d = d.with_note(format!("did you mean `{s}`?"));
        }
        self.error(d)
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

    // ---------------------------------------------------------------------------------
    // Nodes
    // ---------------------------------------------------------------------------------

    /// Infers the op's output types and adds it as a node named by `hint` (or
    /// anonymously in `scope`).
    fn add_node_in(&mut self, op: Op, inputs: Vec<ValueRef>, hint: Option<Hint>, span: Span, scope: ScopeId) -> Value {
        if self.graph.node_count() >= MAX_NODES {
            self.abort(span, format!("the model has more than {MAX_NODES} nodes"));
            return Value::Poison;
        }
        let (scope, name) = match hint {
            Some(h) => (h.scope, h.name),
            None => {
                let n = self.anon_name(scope, op.kind_name());
                (scope, n)
            }
        };
        let path = join_path(&self.graph.scope(scope).path, &name);
        let types: Vec<TensorType> = inputs.iter().filter_map(|v| self.graph.value_type(*v).cloned()).collect();
        let type_refs: Vec<&TensorType> = types.iter().collect();
        let outputs = match infer(&op, &type_refs) {
            Ok(o) => o,
            Err(e) => {
                let mut d =
                    Diagnostic::error(Code::ShapeMismatch, format!("shape mismatch in `{path}`: {}", e.message))
                        .with_primary(span, e.message.clone());
                if !types.is_empty() {
                    let shown: Vec<String> = types.iter().map(|t| t.to_string()).collect();
                    d = d.with_note(format!("{} inputs: {}", op.kind_name(), shown.join(", ")));
                }
                for n in e.notes {
                    d = d.with_note(n);
                }
                return self.error(d);
            }
        };
        let params = op.param_slots();
        if !params.is_empty() && path.split('.').any(|seg| seg.contains('#')) {
            let slot = params[0].name;
            return self.error(
                Diagnostic::error(
                    Code::AnonymousParams,
                    format!("this {} has parameters but no name, so its weights cannot be bound", op.kind_name()),
                )
                .with_primary(span, format!("would be `{path}.{slot}`"))
                .with_note("name it with a statement, `name = ...`, so its parameters get a state_dict key"),
            );
        }
        let id = self.graph.add_node(Node { op, path, scope, params, outputs, span }, &inputs);
        Value::Tensor { value: ValueRef { node: id, port: 0 }, scope: None }
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

fn tensor_kind(op: BinaryOp) -> Option<BinaryKind> {
    match op {
        BinaryOp::Add => Some(BinaryKind::Add),
        BinaryOp::Sub => Some(BinaryKind::Sub),
        BinaryOp::Mul => Some(BinaryKind::Mul),
        BinaryOp::Div => Some(BinaryKind::Div),
        _ => None,
    }
}

fn as_f64(v: &Value) -> f64 {
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

fn restore(vars: &mut HashMap<String, Value>, name: &str, saved: Option<Value>) {
    match saved {
        Some(v) => {
            vars.insert(name.to_string(), v);
        }
        None => {
            vars.remove(name);
        }
    }
}

fn display_path(path: &str) -> &str {
    if path.is_empty() { "<model>" } else { path }
}

/// A value as text, for the model parameter record.
fn show_value(v: &Value) -> String {
    match v {
        Value::Int(i) => i.to_string(),
        Value::Float(f) => format!("{f:?}"),
        Value::Bool(b) => b.to_string(),
        Value::Str(s) => format!("\"{s}\""),
        Value::Dim(d) => d.to_string(),
        Value::List(l) => format!("[{}]", l.iter().map(show_value).collect::<Vec<_>>().join(", ")),
        other => other.kind().to_string(),
    }
}
