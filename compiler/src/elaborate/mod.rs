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
//!
//! The elaborator is split by what it evaluates: `stmt` runs statements and the items of a
//! `seq`, `eval` computes expressions (compile-time values and tensor arithmetic), and
//! `call` binds arguments and instantiates blocks, builtin ops and functions. This module
//! holds the state, the entry point, diagnostics, scopes and naming, and node creation.

mod builtins;
mod call;
mod eval;
mod stmt;
mod subscript;

use std::collections::{HashMap, HashSet};
use std::rc::Rc;

use readi_grammar::ast::{self, BlockDef, LayerName, TypeName};
use readi_grammar::diag::{Code, Diagnostic, Diagnostics, FileId, Span, suggest};

use crate::ir::*;
pub use crate::value::Value;

/// Maximum number of nodes a model may elaborate to.
pub const MAX_NODES: usize = 200_000;
/// Maximum depth of nested block instances.
pub const MAX_BLOCK_DEPTH: usize = 32;
/// Maximum length of one range (`for i in a..b`, `[... for i in a..b]`).
pub const MAX_RANGE: i64 = 100_000;
/// Maximum number of expression evaluations in one elaboration.
pub const MAX_STEPS: u64 = 5_000_000;

/// Default limit on the activation memory of a model at batch size 1 (4 GiB): one value,
/// and the peak of the values alive at once. `readi compile --max-activation-memory`.
pub const DEFAULT_MAX_ACTIVATION_BYTES: u64 = 4 << 30;
/// Most elements one parameter tensor may have (2^32, 16 GiB as f32).
pub const MAX_PARAM_ELEMENTS: u64 = 1 << 32;
/// Most inputs one op may take (its input ports are 16-bit).
pub const MAX_OP_INPUTS: usize = u16::MAX as usize;

/// The bytes of a tensor at batch size 1 (every symbolic dimension 1), or `None` if the
/// count overflows `u64`.
pub fn bytes_at_batch_1(t: &TensorType) -> Option<u64> {
    t.shape.iter().try_fold(t.dtype.size_bytes(), |acc, d| acc.checked_mul(d.coef().max(0) as u64))
}

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
    /// Most bytes one value may take at batch size 1
    /// ([`DEFAULT_MAX_ACTIVATION_BYTES`] when `None`).
    pub max_activation_bytes: Option<u64>,
}

/// Elaborates the model of `file` into a graph. Returns the graph (complete only when the
/// diagnostics hold no errors) and the diagnostics.
pub fn elaborate(file: &ast::SourceFile, file_id: FileId, opts: &ElabOptions) -> (Option<Graph>, Diagnostics) {
    let mut e = Elab::new(file_id);
    e.max_value_bytes = opts.max_activation_bytes.unwrap_or(DEFAULT_MAX_ACTIVATION_BYTES);
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
    /// See [`ElabOptions::max_activation_bytes`].
    max_value_bytes: u64,
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
            max_value_bytes: DEFAULT_MAX_ACTIVATION_BYTES,
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
        // Several `adapt` sections are allowed (scoped ones: `adapt camera { ... }`).
        for (kind, spans) in [("variants", file.variant_sections().map(|v| v.span).collect::<Vec<_>>())] {
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
            if builtins::is_builtin(name) {
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
    // Scopes and naming
    // ---------------------------------------------------------------------------------

    /// The path segment a layer name stands for: a quoted name's `{expr}` parts evaluated
    /// (ints and strings) and the result checked; `None` (reported) when it is no name.
    fn layer_text(&mut self, name: &'a LayerName, frame: &mut Frame<'a>) -> Option<String> {
        let LayerName::Quoted(q) = name else { return Some(name.text()) };
        let mut text = String::new();
        for part in &q.parts {
            match part {
                ast::NamePart::Text(t) => text.push_str(t),
                ast::NamePart::Expr(e) => match self.eval(e, frame, None) {
                    Value::Int(i) => text.push_str(&i.to_string()),
                    Value::Str(s) => text.push_str(&s),
                    Value::Poison => return None,
                    v => {
                        self.error(
                            Diagnostic::error(
                                Code::TypeMismatch,
                                format!("a layer name is made of ints and strings, found {}", v.kind()),
                            )
                            .with_primary(e.span, "not an int or a string"),
                        );
                        return None;
                    }
                },
            }
        }
        if let Some(why) = ast::bad_layer_name(&text) {
            self.error(
                Diagnostic::error(Code::BadValue, format!("`{text}`: {why}"))
                    .with_primary(q.span, "computed name is not a layer name"),
            );
            return None;
        }
        Some(text)
    }

    /// Checks that `name` is free in the current scope and returns the hint for it.
    fn claim_name(&mut self, name: &'a LayerName, frame: &mut Frame<'a>) -> Option<Hint> {
        let text = self.layer_text(name, frame)?;
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

    fn bind_name(&mut self, name: &LayerName, text: String, v: Value, frame: &mut Frame<'a>) {
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
        if inputs.len() > MAX_OP_INPUTS {
            return self.error(
                Diagnostic::error(
                    Code::Limit,
                    format!("`{}` has {} inputs, over the limit of {MAX_OP_INPUTS}", op.kind_name(), inputs.len()),
                )
                .with_primary(span, "too many inputs")
                .with_note("combine the inputs in stages (a concat of concats)"),
            );
        }
        let types: Vec<TensorType> = inputs.iter().filter_map(|v| self.graph.value_type(*v).cloned()).collect();
        let type_refs: Vec<&TensorType> = types.iter().collect();
        let outputs = match op.infer(&type_refs) {
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
        if let Some(d) = self.size_error(&path, &outputs, span) {
            return self.error(d);
        }
        let params = op.param_slots();
        for p in &params {
            let numel = p.shape.iter().try_fold(1u64, |acc, &d| acc.checked_mul(d.max(0) as u64));
            if numel.is_none_or(|n| n > MAX_PARAM_ELEMENTS) {
                let shown = numel.map_or("more than 2^64".to_string(), |n| n.to_string());
                return self.error(
                    Diagnostic::error(
                        Code::Limit,
                        format!(
                            "parameter `{path}.{}` of shape {:?} has {shown} elements, over the limit of \
                             {MAX_PARAM_ELEMENTS}",
                            p.name, p.shape
                        ),
                    )
                    .with_primary(span, "too large a parameter"),
                );
            }
        }
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
        let id = self.graph.add_node(Node::new(op, path, scope, params, outputs, span), &inputs);
        Value::Tensor { value: ValueRef { node: id, port: 0 }, scope: None }
    }
}

impl Elab<'_> {
    /// An error if a value `path` creates is too large at batch size 1: its byte count
    /// overflows, or is over the activation limit.
    fn size_error(&self, path: &str, outputs: &[TensorType], span: Span) -> Option<Diagnostic> {
        let limit = self.max_value_bytes;
        outputs.iter().find_map(|t| {
            let message = match bytes_at_batch_1(t) {
                None => format!("`{}` is {t}: its size in bytes overflows", display_path(path)),
                Some(b) if b > limit => format!(
                    "`{}` is {t}: {} at batch size 1, over the activation limit of {}",
                    display_path(path),
                    crate::print::bytes(b),
                    crate::print::bytes(limit)
                ),
                Some(_) => return None,
            };
            Some(
                Diagnostic::error(Code::Limit, message)
                    .with_primary(span, "too large a tensor")
                    .with_note("`readi compile --max-activation-memory` sets the limit (default 4G)"),
            )
        })
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
