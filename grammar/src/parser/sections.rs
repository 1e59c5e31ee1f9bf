//! The `adapt` section (tune, LoRA and adapter rules, selectors, path patterns) and the
//! `variants` section (axes, missing-modality policies, selection and melding).
//!
//! Separate because these sections have their own small languages that share nothing
//! with the model body but the lexical rules (`number`, `string`, `ident`).

use pest::iterators::Pair;

use super::{Builder, Rule, inner};
use crate::ast::*;
use crate::diag::{Code, Diagnostic};

impl<'s> Builder<'s> {
    // ---------------------------------------------------------------------------------
    // Adaptation section
    // ---------------------------------------------------------------------------------

    pub(super) fn parse_adapt_def(&mut self, pair: Pair<'_, Rule>) -> AdaptSection {
        let span = self.span(&pair);
        let mut rules = Vec::new();
        let mut scopes = Vec::new();
        for part in pair.into_inner() {
            if part.as_rule() == Rule::adapt_scopes {
                scopes = part.into_inner().filter_map(|s| self.parse_adapt_scope(s)).collect();
                continue;
            }
            for p in part.into_inner() {
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
        AdaptSection { scopes, rules, span }
    }

    fn parse_adapt_scope(&mut self, pair: Pair<'_, Rule>) -> Option<AdaptScope> {
        let span = self.span(&pair);
        let mut it = pair.into_inner();
        let name = self.ident(it.next()?);
        let value = it.next().map(|v| self.ident(v));
        Some(AdaptScope { name, value, span })
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
                Rule::rule_option | Rule::prune_option => options.push(self.parse_rule_option(q)?),
                Rule::selector => selector = Some(self.parse_selector(q)),
                Rule::scope_list => scopes = self.parse_scope_list(q),
                Rule::pattern => before = Some(self.parse_pattern(q)),
                _ => {}
            }
        }
        let kind = match rule {
            Rule::tune_rule => AdaptKind::Tune { selector: selector? },
            Rule::lora_rule => AdaptKind::Lora { options, selector: selector? },
            Rule::prune_rule => AdaptKind::Prune { options, selector },
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

    pub(super) fn parse_variants_def(&mut self, pair: Pair<'_, Rule>) -> VariantSection {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::parser::tests::parse_ok;

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
    fn a_prune_rule_ends_where_the_next_rule_begins() {
        let f = parse_ok(
            "model m { }\nadapt {\n  prune below=1e-3\n  tune batchnorm\n  prune below=0.01 in conv2d in layer1\n}\n",
        );
        let a = f.adapt_sections().next().expect("adapt");
        assert_eq!(a.rules.len(), 3);
        let AdaptKind::Prune { options, selector: None } = &a.rules[0].kind else { panic!("{:?}", a.rules[0]) };
        assert_eq!(options[0].name.name, "below");
        assert!(matches!(&options[0].value, Some(OptionValue::Number(n)) if n.value == 1e-3));
        assert!(matches!(&a.rules[1].kind, AdaptKind::Tune { .. }));
        let AdaptKind::Prune { selector: Some(s), .. } = &a.rules[2].kind else { panic!("{:?}", a.rules[2]) };
        assert!(matches!(&s.items[0], SelItem::KindsIn { .. }));
        assert_eq!(crate::ast_print::adapt_rule(&a.rules[2]), "prune below=0.01 in conv2d in layer1");
        assert_eq!(crate::ast_print::adapt_rule(&a.rules[0]), "prune below=1e-3");
    }

    #[test]
    fn scoped_adapt_sections_parse_and_print() {
        let f = parse_ok(
            "model m { }\nadapt { tune head }\nadapt camera { tune batchnorm in camera }\n\
             adapt lidar, missing=lidar { lora rank=4 on lidar.** }\n",
        );
        let scopes: Vec<Vec<String>> =
            f.adapt_sections().map(|a| a.scopes.iter().map(AdaptScope::text).collect()).collect();
        assert_eq!(scopes, vec![vec![], vec!["camera".to_string()], vec!["lidar".into(), "missing=lidar".into()]]);
        let printed = crate::ast_print::to_source(&f);
        assert!(
            printed.contains("adapt camera {\n") && printed.contains("adapt lidar, missing=lidar {\n"),
            "{printed}"
        );
        assert!(printed.contains("adapt {\n  tune head\n}"), "{printed}");
        // The printed file parses to the same tree, spans aside.
        let again = parse_ok(&printed);
        let texts = |f: &SourceFile| -> Vec<String> {
            f.adapt_sections().flat_map(|a| a.scopes.iter().map(AdaptScope::text)).collect()
        };
        assert_eq!(texts(&again), texts(&f));
    }

    #[test]
    fn a_bad_scope_is_a_syntax_error_at_it() {
        let d = crate::parser::tests::first_error("model m { }\nadapt camera, { tune head }\n");
        assert!(d.message.contains("expected a name, found `{`"), "{}", d.message);
        assert_eq!(d.primary_span().map(|s| s.start), Some(26));
        let d = crate::parser::tests::first_error("model m { }\nadapt 3 { tune head }\n");
        assert!(d.message.contains("found `3`"), "{}", d.message);
        let d = crate::parser::tests::first_error("model m { }\nadapt missing=3 { tune head }\n");
        assert!(d.message.contains("expected a name, found `3`"), "{}", d.message);
    }

    #[test]
    fn pattern_split_respects_alternatives() {
        assert_eq!(split_pattern("blocks.*.attn.{q.x,k}"), vec!["blocks", "*", "attn", "{q.x,k}"]);
    }
}
