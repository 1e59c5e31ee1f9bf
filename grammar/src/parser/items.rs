//! File, items and statements: one `parse_<rule>` per rule of the grammar's "File and
//! items" and "Statements" sections, from `file` down to `layer_name`.
//!
//! Separate from expressions because these rules own the structure of a body (and the
//! statement-level recovery), while expressions only ever nest inside them.

use pest::iterators::Pair;

use super::{Builder, Rule, inner};
use crate::ast::*;
use crate::diag::{Code, Diagnostic, Span};

impl<'s> Builder<'s> {
    // ---------------------------------------------------------------------------------
    // Items
    // ---------------------------------------------------------------------------------

    pub(super) fn parse_file(&mut self, pair: Pair<'_, Rule>) -> Vec<Item> {
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
            Rule::use_def => {
                let span = self.span(&p);
                let path =
                    p.into_inner().next()?.into_inner().next().map(|s| s.as_str().to_string()).unwrap_or_default();
                Item::Use(UseDecl { path, span })
            }
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

    pub(super) fn parse_body(&mut self, pair: Pair<'_, Rule>) -> Body {
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

    pub(super) fn parse_layer_name(&mut self, pair: Pair<'_, Rule>) -> Option<LayerName> {
        let p = pair.into_inner().next()?;
        match p.as_rule() {
            Rule::ident => Some(LayerName::Ident(self.ident(p))),
            Rule::quoted_name => self.parse_quoted_name(p).map(LayerName::Quoted),
            _ => {
                let span = self.span(&p);
                let n = self.parse_int_literal(&p)?;
                Some(LayerName::Index(n as u64, span))
            }
        }
    }

    /// `"block1-0"`, `"block{i}-{j}"`. The literal text is checked here; the value of an
    /// `{expr}` part is checked when the elaborator computes it.
    pub(super) fn parse_quoted_name(&mut self, pair: Pair<'_, Rule>) -> Option<QuotedName> {
        let span = self.span(&pair);
        let text = pair.as_str();
        let source = text[1..text.len() - 1].to_string();
        let mut parts = Vec::new();
        let mut ok = true;
        for p in pair.into_inner() {
            match p.as_rule() {
                Rule::name_text => {
                    if let Some(why) = bad_layer_name(p.as_str()) {
                        self.diags.push(
                            Diagnostic::error(Code::BadLiteral, why)
                                .with_primary(self.span(&p), "not allowed in a layer name"),
                        );
                        ok = false;
                    }
                    parts.push(NamePart::Text(p.as_str().to_string()));
                }
                Rule::name_interp => {
                    let e = p.into_inner().next().and_then(|e| self.parse_expr(e));
                    match e {
                        Some(e) => parts.push(NamePart::Expr(e)),
                        None => ok = false,
                    }
                }
                _ => {}
            }
        }
        if parts.is_empty() {
            self.diags.push(
                Diagnostic::error(Code::BadLiteral, "a layer name cannot be empty").with_primary(span, "empty name"),
            );
            return None;
        }
        ok.then_some(QuotedName { parts, source, span })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diag::Code;
    use crate::parser::tests::{first_error, model_stmts, parse_ok};

    #[test]
    fn quoted_layer_names_hold_text_and_interpolations() {
        let f = parse_ok("model m {\n  \"block1-0\" = f(x)\n  \"b{i}-{j + 1}\" { a = g(x) }\n}");
        let stmts = model_stmts(&f);
        let StmtKind::Named { name: LayerName::Quoted(q), .. } = &stmts[0].kind else { panic!("{:?}", stmts[0]) };
        assert_eq!(q.literal().as_deref(), Some("block1-0"));
        assert_eq!(q.span.start, 12);
        let StmtKind::Scope { name: LayerName::Quoted(q), .. } = &stmts[1].kind else { panic!("{:?}", stmts[1]) };
        assert_eq!(q.literal(), None);
        assert_eq!(q.source, "b{i}-{j + 1}");
        let kinds: Vec<bool> = q.parts.iter().map(|p| matches!(p, NamePart::Text(_))).collect();
        assert_eq!(kinds, [true, false, true, false]);
        let NamePart::Expr(e) = &q.parts[3] else { panic!() };
        assert!(matches!(e.kind, ExprKind::Binary(BinaryOp::Add, _, _)), "{e:?}");
    }

    #[test]
    fn quoted_names_are_reached_as_members_and_in_seq_items() {
        let f = parse_ok("model m {\n  y = trunk.block1.\"block1-0\".f\n  z = seq(y) { \"c{k}\" = relu }\n}");
        let stmts = model_stmts(&f);
        let StmtKind::Named { value, .. } = &stmts[0].kind else { panic!() };
        let ExprKind::Member(base, LayerName::Ident(f_)) = &value.kind else { panic!("{value:?}") };
        assert_eq!(f_.name, "f");
        assert!(matches!(&base.kind, ExprKind::Member(_, LayerName::Quoted(q)) if q.source == "block1-0"));
        assert_eq!(crate::ast_print::expr_to_source(value), "trunk.block1.\"block1-0\".f");
        let StmtKind::Named { value, .. } = &stmts[1].kind else { panic!() };
        let ExprKind::Seq { items, .. } = &value.kind else { panic!("{value:?}") };
        assert!(matches!(&items[0], SeqItem::Call { name: Some(LayerName::Quoted(q)), .. } if q.source == "c{k}"));
    }

    #[test]
    fn bad_quoted_names_are_refused_where_they_are() {
        let src = "model m {\n  \"\" = f(x)\n}";
        let d = first_error(src);
        assert_eq!(d.code, Code::BadLiteral);
        assert!(d.message.contains("empty"), "{}", d.message);
        assert_eq!(d.primary_span().map(|s| &src[s.range()]), Some("\"\""));

        let src = "model m {\n  \"a.b{i}\" = f(x)\n}";
        let d = first_error(src);
        assert_eq!(d.code, Code::BadLiteral);
        assert!(d.message.contains("`.`"), "{}", d.message);
        assert_eq!(d.primary_span().map(|s| &src[s.range()]), Some("a.b"));

        let d = first_error("model m {\n  \"a#1\" = f(x)\n}");
        assert!(d.message.contains("`#`"), "{}", d.message);

        // An unclosed interpolation is a syntax error, not a name.
        let d = first_error("model m {\n  \"a{i\" = f(x)\n}");
        assert_eq!(d.code, Code::Syntax);
    }
}
