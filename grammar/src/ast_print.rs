//! Prints a syntax tree back as canonical readi source.
//!
//! This is what `readi ast` shows: the file as the parser understood it, one statement per
//! line, two-space indentation, and every nested binary operation parenthesised so the
//! precedence the parser chose is visible (`a + (b * c)`). Parsing the output again gives
//! the same tree (spans aside); a property test holds the printer to that.

use std::fmt::Write;

use crate::ast::*;

/// Canonical source text of a parsed file.
pub fn to_source(file: &SourceFile) -> String {
    let mut p = Printer { out: String::new(), indent: 0 };
    for (i, item) in file.items.iter().enumerate() {
        if i > 0 {
            p.out.push('\n');
        }
        p.item(item);
    }
    p.out
}

/// Canonical source text of one expression.
pub fn expr_to_source(e: &Expr) -> String {
    let mut p = Printer { out: String::new(), indent: 0 };
    p.expr(e, false);
    p.out
}

struct Printer {
    out: String,
    indent: usize,
}

impl Printer {
    fn line(&mut self, text: &str) {
        for _ in 0..self.indent {
            self.out.push_str("  ");
        }
        self.out.push_str(text);
        self.out.push('\n');
    }

    fn item(&mut self, item: &Item) {
        match item {
            Item::Use(u) => self.line(&format!("use \"{}\"", u.path)),
            Item::Block(b) => {
                let params = self.params(&b.params);
                self.open(&format!("block {}({params})", b.name.name));
                self.body(&b.body);
            }
            Item::Model(m) => {
                let header = if m.params.is_empty() {
                    format!("model {}", m.name.name)
                } else {
                    format!("model {}({})", m.name.name, self.params(&m.params))
                };
                self.open(&header);
                self.body(&m.body);
            }
            Item::Adapt(a) => {
                let scopes: Vec<String> = a.scopes.iter().map(AdaptScope::text).collect();
                self.open(&if scopes.is_empty() {
                    "adapt".to_string()
                } else {
                    format!("adapt {}", scopes.join(", "))
                });
                for r in &a.rules {
                    let text = adapt_rule(r);
                    self.line(&text);
                }
                self.close();
            }
            Item::Variants(v) => {
                self.open("variants");
                for d in &v.decls {
                    let text = variant_decl(d);
                    self.line(&text);
                }
                self.close();
            }
        }
    }

    fn open(&mut self, header: &str) {
        self.line(&format!("{header} {{"));
        self.indent += 1;
    }

    fn close(&mut self) {
        self.indent -= 1;
        self.line("}");
    }

    fn params(&mut self, params: &[Param]) -> String {
        let parts: Vec<String> = params
            .iter()
            .map(|p| {
                let mut s = p.name.name.clone();
                if let Some((t, _)) = &p.ty {
                    let _ = write!(s, ": {}", t.as_str());
                }
                if let Some(d) = &p.default {
                    let _ = write!(s, " = {}", expr_to_source(d));
                }
                s
            })
            .collect();
        parts.join(", ")
    }

    /// Prints the statements of a body and its closing brace.
    fn body(&mut self, body: &Body) {
        for s in &body.stmts {
            self.stmt(s);
        }
        self.close();
    }

    fn stmt(&mut self, s: &Stmt) {
        match &s.kind {
            StmtKind::Input(i) => {
                let dims: Vec<String> = i.dims.iter().map(expr_to_source).collect();
                let mut text = format!("input {}: {}[{}]", i.name.name, i.dtype.0.as_str(), dims.join(", "));
                if let Some(m) = &i.modality {
                    let _ = write!(text, " @{}", m.name);
                }
                if i.optional {
                    text.push_str(" optional");
                }
                self.line(&text);
            }
            StmtKind::Output { name, value } => match value {
                Some(v) => self.line(&format!("output {} = {}", name.name, self.render(v))),
                None => self.line(&format!("output {}", name.name)),
            },
            StmtKind::Let { name, value } => {
                self.line_with_expr(&format!("let {} = ", name.name), value);
            }
            StmtKind::If { branches, otherwise } => {
                for (i, (cond, body)) in branches.iter().enumerate() {
                    let kw = if i == 0 { "if" } else { "} else if" };
                    if i > 0 {
                        self.indent -= 1;
                        self.line(&format!("{kw} {} {{", expr_to_source(cond)));
                        self.indent += 1;
                    } else {
                        self.open(&format!("{kw} {}", expr_to_source(cond)));
                    }
                    for s in &body.stmts {
                        self.stmt(s);
                    }
                }
                if let Some(body) = otherwise {
                    self.indent -= 1;
                    self.line("} else {");
                    self.indent += 1;
                    for s in &body.stmts {
                        self.stmt(s);
                    }
                }
                self.close();
            }
            StmtKind::Return(v) => self.line_with_expr("return ", v),
            StmtKind::Scope { name, body } => {
                self.open(&name.source());
                self.body(body);
            }
            StmtKind::Named { name, value } => {
                self.line_with_expr(&format!("{} = ", name.source()), value);
            }
        }
    }

    /// A line `prefix <expr>`, where a `seq` expression spreads over several lines.
    fn line_with_expr(&mut self, prefix: &str, value: &Expr) {
        if let ExprKind::Seq { input, items } = &value.kind {
            self.open(&format!("{prefix}seq({})", expr_to_source(input)));
            self.seq_items(items);
            self.close();
        } else {
            let text = format!("{prefix}{}", self.render(value));
            self.line(&text);
        }
    }

    fn seq_items(&mut self, items: &[SeqItem]) {
        for item in items {
            match item {
                SeqItem::Call { name, callee, args, .. } => {
                    let mut text = String::new();
                    if let Some(n) = name {
                        let _ = write!(text, "{} = ", n.source());
                    }
                    text.push_str(&callee.name);
                    if !args.is_empty() {
                        let _ = write!(text, "({})", args_to_source(args));
                    }
                    self.line(&text);
                }
                SeqItem::For { var, start, end, items, .. } => {
                    self.open(&format!("for {} in {}..{}", var.name, expr_to_source(start), expr_to_source(end)));
                    self.seq_items(items);
                    self.close();
                }
                SeqItem::If { branches, otherwise, .. } => {
                    for (i, (cond, items)) in branches.iter().enumerate() {
                        if i > 0 {
                            self.indent -= 1;
                            self.line(&format!("}} else if {} {{", expr_to_source(cond)));
                            self.indent += 1;
                        } else {
                            self.open(&format!("if {}", expr_to_source(cond)));
                        }
                        self.seq_items(items);
                    }
                    if let Some(items) = otherwise {
                        self.indent -= 1;
                        self.line("} else {");
                        self.indent += 1;
                        self.seq_items(items);
                    }
                    self.close();
                }
            }
        }
    }

    fn render(&self, e: &Expr) -> String {
        let mut p = Printer { out: String::new(), indent: self.indent };
        p.expr(e, false);
        p.out
    }

    /// Writes an expression; `nested` parenthesises binary operations.
    fn expr(&mut self, e: &Expr, nested: bool) {
        match &e.kind {
            ExprKind::Int(v) => {
                let _ = write!(self.out, "{v}");
            }
            ExprKind::Float(v) => self.out.push_str(&float_to_source(*v)),
            ExprKind::Bool(b) => {
                let _ = write!(self.out, "{b}");
            }
            ExprKind::Str(s) => {
                let _ = write!(self.out, "\"{s}\"");
            }
            ExprKind::Var(i) => self.out.push_str(&i.name),
            ExprKind::Unary(op, x) => {
                self.out.push_str(match op {
                    UnaryOp::Neg => "-",
                    UnaryOp::Not => "not ",
                });
                self.expr(x, true);
            }
            ExprKind::Binary(op, a, b) => {
                if nested {
                    self.out.push('(');
                }
                self.expr(a, true);
                let _ = write!(self.out, " {} ", op.as_str());
                self.expr(b, true);
                if nested {
                    self.out.push(')');
                }
            }
            ExprKind::Call { callee, args } => {
                let _ = write!(self.out, "{}({})", callee.name, args_to_source(args));
            }
            ExprKind::Member(base, name) => {
                self.expr(base, true);
                let _ = write!(self.out, ".{}", name.source());
            }
            ExprKind::Index(base, idx) => {
                self.expr(base, true);
                self.out.push('[');
                self.expr(idx, false);
                self.out.push(']');
            }
            ExprKind::Subscript(base, subs) => {
                self.expr(base, true);
                let parts: Vec<String> = subs
                    .iter()
                    .map(|s| match s {
                        Subscript::Index(e) => expr_to_source(e),
                        Subscript::Ellipsis(_) => "...".to_string(),
                        Subscript::Range { start, stop, step, .. } => {
                            let part = |e: &Option<Expr>| e.as_ref().map(expr_to_source).unwrap_or_default();
                            match step {
                                Some(st) => format!("{}:{}:{}", part(start), part(stop), expr_to_source(st)),
                                None => format!("{}:{}", part(start), part(stop)),
                            }
                        }
                    })
                    .collect();
                let comma = if subs.len() == 1 && matches!(subs[0], Subscript::Index(_)) { "," } else { "" };
                let _ = write!(self.out, "[{}{comma}]", parts.join(", "));
            }
            ExprKind::List(items) => {
                let parts: Vec<String> = items.iter().map(expr_to_source).collect();
                let _ = write!(self.out, "[{}]", parts.join(", "));
            }
            ExprKind::Comprehension { elem, var, start, end } => {
                let _ = write!(
                    self.out,
                    "[{} for {} in {}..{}]",
                    expr_to_source(elem),
                    var.name,
                    expr_to_source(start),
                    expr_to_source(end)
                );
            }
            ExprKind::IfElse { cond, then, otherwise } => {
                if nested {
                    self.out.push('(');
                }
                let _ = write!(
                    self.out,
                    "if {} then {} else {}",
                    expr_to_source(cond),
                    expr_to_source(then),
                    expr_to_source(otherwise)
                );
                if nested {
                    self.out.push(')');
                }
            }
            ExprKind::Seq { input, items } => {
                // Inline form, used when a `seq` is nested inside a larger expression.
                let _ = write!(self.out, "seq({}) {{ ", expr_to_source(input));
                let mut sub = Printer { out: String::new(), indent: 0 };
                sub.seq_items(items);
                let inline: Vec<&str> = sub.out.lines().map(str::trim).collect();
                self.out.push_str(&inline.join(" "));
                self.out.push_str(" }");
            }
        }
    }
}

fn args_to_source(args: &[Arg]) -> String {
    let parts: Vec<String> = args
        .iter()
        .map(|a| match &a.name {
            Some(n) => format!("{}={}", n.name, expr_to_source(&a.value)),
            None => expr_to_source(&a.value),
        })
        .collect();
    parts.join(", ")
}

/// A float literal that reads back as a float (`1.0`, not `1`).
fn float_to_source(v: f64) -> String {
    let s = format!("{v:?}");
    if s.contains('.') || s.contains('e') || s.contains("inf") || s.contains("NaN") { s } else { format!("{s}.0") }
}

fn pattern_list(ps: &[Pattern]) -> String {
    ps.iter().map(|p| p.text.as_str()).collect::<Vec<_>>().join("|")
}

fn selector(sel: &Selector) -> String {
    let parts: Vec<String> = sel
        .items
        .iter()
        .map(|item| match item {
            SelItem::KindsIn { kinds, scopes, .. } => {
                let k: Vec<&str> = kinds.iter().map(|k| k.name.as_str()).collect();
                format!("{} in {}", k.join("|"), pattern_list(scopes))
            }
            SelItem::Pattern(p) => p.text.clone(),
        })
        .collect();
    parts.join(", ")
}

fn options(opts: &[RuleOption]) -> String {
    let mut s = String::new();
    for o in opts {
        s.push(' ');
        s.push_str(&o.name.name);
        match &o.value {
            None => {}
            Some(OptionValue::Number(n)) => {
                let _ = write!(s, "={}", n.text);
            }
            Some(OptionValue::Str(v, _)) => {
                let _ = write!(s, "=\"{v}\"");
            }
            Some(OptionValue::Word(w)) => {
                let _ = write!(s, "={}", w.name);
            }
        }
    }
    s
}

/// One adaptation rule as source.
pub fn adapt_rule(r: &AdaptRule) -> String {
    match &r.kind {
        AdaptKind::Tune { selector: sel } => format!("tune {}", selector(sel)),
        AdaptKind::Lora { options: o, selector: sel } => {
            format!("lora{} on {}", options(o), selector(sel))
        }
        AdaptKind::Adapter { options: o, scopes, before } => {
            format!("adapter{} in {} before {}", options(o), pattern_list(scopes), before.text)
        }
        AdaptKind::Prune { options: o, selector: None } => format!("prune{}", options(o)),
        AdaptKind::Prune { options: o, selector: Some(sel) } => format!("prune{} in {}", options(o), selector(sel)),
    }
}

/// One variants declaration as source.
pub fn variant_decl(d: &VariantDecl) -> String {
    match d {
        VariantDecl::Axis { name, modality, levels, clear, .. } => {
            let l: Vec<&str> = levels.iter().map(|n| n.text.as_str()).collect();
            let mut s = format!("axis {} on {}: {}", name.name, modality.name, l.join(", "));
            if let Some(c) = clear {
                let _ = write!(s, " clear {}", c.text);
            }
            s
        }
        VariantDecl::Missing { modality, policy, .. } => {
            format!("missing {}: {}", modality.name, policy.name)
        }
        VariantDecl::Select { axis, source, mapping, .. } => {
            let src = match source {
                SelectSource::Meta { key, .. } => format!("meta(\"{key}\")"),
                SelectSource::Stat { stat, input } => format!("{}({})", stat.name, input.name),
            };
            let map = match mapping {
                SelectMap::Nearest => "nearest".to_string(),
                SelectMap::Thresholds(arms) => {
                    let a: Vec<String> = arms
                        .iter()
                        .map(|arm| {
                            let lvl = match &arm.level {
                                LevelRef::Clear(_) => "clear".to_string(),
                                LevelRef::Level(n) => n.text.clone(),
                            };
                            match &arm.bound {
                                None => format!("else -> {lvl}"),
                                Some((incl, n)) => {
                                    format!("{} {} -> {lvl}", if *incl { "<=" } else { "<" }, n.text)
                                }
                            }
                        })
                        .collect();
                    format!("{{ {} }}", a.join(", "))
                }
            };
            format!("select {} by {src} {map}", axis.name)
        }
        VariantDecl::Meld { weights, .. } => {
            let w: Vec<String> = weights.iter().map(|(m, n)| format!("{} = {}", m.name, n.text)).collect();
            format!("meld {}", w.join(", "))
        }
    }
}
