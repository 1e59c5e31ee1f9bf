//! `check_variants`: checks the `variants` section against the graph.
//!
//! Changes: nothing in the graph; produces a [`VariantSpec`] side table (axes with their
//! levels, missing-modality policies, selectors, meld weights) and the list of variant
//! keys the section implies (`fog=0.03`, `missing=lidar`).
//!
//! Checks, each an error at the declaration:
//! * axes: unique names, a modality some input has, distinct levels, the clear level not
//!   among them;
//! * `missing m: zero_fill | variant`: `m` is a modality whose inputs are all `optional`;
//! * `select axis by stat(input) {...}`: a known axis and statistic, an input of the
//!   axis's modality, strictly increasing thresholds ending in `else`, levels of the axis;
//! * `meld a = l1, b = l2`: two or more modalities (each with axes) or axes, not mixed,
//!   lambdas in [0, 1] summing to 1.

use std::collections::HashMap;

use readi_grammar::ast::{LevelRef, Number, SelectMap, SelectSource, VariantDecl, VariantSection};
use readi_grammar::diag::{Code, Diagnostic, Diagnostics, Span, suggest};

use crate::ir::{Graph, Op};

/// Missing-modality policies.
pub const POLICIES: &[&str] = &["zero_fill", "variant"];

/// The checked variants section is the plan's [`Conditions`](readi_plan::conditions::Conditions):
/// what the compiler checks is what the plan carries and the runtime selects by.
pub use readi_plan::conditions::{
    ArmSpec as Arm, AxisSpec as Axis, Conditions as VariantSpec, KeySource, MeldBy, MeldSpec as Meld, MissingPolicy,
    SelectorSpec as KeySelector, Statistic,
};
/// A level as it appears in a key: `0.03`, `4`.
pub use readi_plan::key::fmt_level;

struct InputInfo {
    name: String,
    modality: Option<String>,
    optional: bool,
    span: Span,
}

pub fn run(graph: &Graph, section: &VariantSection, diags: &mut Diagnostics) -> VariantSpec {
    let inputs: Vec<InputInfo> = graph
        .input_nodes()
        .into_iter()
        .filter_map(|n| match &graph.node(n).op {
            Op::Input(a) => Some(InputInfo {
                name: a.name.clone(),
                modality: a.modality.clone(),
                optional: a.optional,
                span: graph.node(n).span,
            }),
            _ => None,
        })
        .collect();
    let modalities: Vec<&str> = inputs.iter().filter_map(|i| i.modality.as_deref()).collect();
    let mut spec = VariantSpec { axes: vec![], missing: vec![], selectors: vec![], meld: None };
    let mut axis_spans: HashMap<String, Span> = HashMap::new();

    let unknown_modality = |m: &readi_grammar::ast::Ident| {
        let mut d = Diagnostic::error(Code::BadVariant, format!("no input has modality `{}`", m.name))
            .with_primary(m.span, "unknown modality");
        d = match suggest(&m.name, modalities.iter().copied()) {
            Some(s) => d.with_note(format!("did you mean `{s}`?")),
            None if modalities.is_empty() => d.with_note("tag inputs with a modality: `input x: f32[...] @camera`"),
            None => d.with_note(format!("input modalities: {}", dedup(&modalities).join(", "))),
        };
        d
    };

    // Axes first: the other declarations refer to them.
    for decl in &section.decls {
        let VariantDecl::Axis { name, modality, levels, clear, span } = decl else { continue };
        if let Some(prev) = axis_spans.get(&name.name) {
            diags.push(
                Diagnostic::error(Code::DuplicateName, format!("axis `{}` is declared twice", name.name))
                    .with_primary(name.span, "second declaration")
                    .with_secondary(*prev, "first declaration here"),
            );
            continue;
        }
        axis_spans.insert(name.name.clone(), name.span);
        if !modalities.contains(&modality.name.as_str()) {
            diags.push(unknown_modality(modality));
        }
        let mut seen: Vec<&Number> = Vec::new();
        for l in levels {
            if let Some(prev) = seen.iter().find(|p| p.value == l.value) {
                diags.push(
                    Diagnostic::error(
                        Code::BadVariant,
                        format!("level {} of axis `{}` is listed twice", l.text, name.name),
                    )
                    .with_primary(l.span, "repeated level")
                    .with_secondary(prev.span, "first listed here"),
                );
            }
            seen.push(l);
        }
        if let Some(c) = clear
            && let Some(l) = levels.iter().find(|l| l.value == c.value)
        {
            diags.push(
                Diagnostic::error(Code::BadVariant, format!("the clear level {} is also a variant level", c.text))
                    .with_primary(l.span, "listed as a level")
                    .with_secondary(c.span, "declared clear here")
                    .with_note("the clear condition is served by the base model and needs no variant"),
            );
        }
        let _ = span;
        spec.axes.push(Axis {
            name: name.name.clone(),
            modality: modality.name.clone(),
            levels: levels.iter().map(|l| l.value).collect(),
            clear: clear.as_ref().map(|c| c.value),
        });
    }

    let mut missing_spans: HashMap<String, Span> = HashMap::new();
    let mut select_spans: HashMap<String, Span> = HashMap::new();
    let mut meld_span: Option<Span> = None;
    for decl in &section.decls {
        match decl {
            VariantDecl::Axis { .. } => {}
            VariantDecl::Missing { modality, policy, span } => {
                if let Some(prev) = missing_spans.insert(modality.name.clone(), *span) {
                    diags.push(
                        Diagnostic::error(
                            Code::DuplicateName,
                            format!("`missing {}` is declared twice", modality.name),
                        )
                        .with_primary(*span, "second declaration")
                        .with_secondary(prev, "first declaration here"),
                    );
                    continue;
                }
                if !modalities.contains(&modality.name.as_str()) {
                    diags.push(unknown_modality(modality));
                    continue;
                }
                for i in inputs.iter().filter(|i| i.modality.as_deref() == Some(modality.name.as_str())) {
                    if !i.optional {
                        diags.push(
                            Diagnostic::error(
                                Code::BadVariant,
                                format!(
                                    "input `{}` ({}) is not `optional`, so it cannot be missing",
                                    i.name, modality.name
                                ),
                            )
                            .with_primary(modality.span, "missing-modality rule")
                            .with_secondary(i.span, "add `optional` to this input"),
                        );
                    }
                }
                let p = match policy.name.as_str() {
                    "zero_fill" => MissingPolicy::ZeroFill,
                    "variant" => MissingPolicy::Variant,
                    other => {
                        let mut d =
                            Diagnostic::error(Code::BadVariant, format!("unknown missing-modality policy `{other}`"))
                                .with_primary(policy.span, "expected `zero_fill` or `variant`");
                        if let Some(s) = suggest(other, POLICIES.iter().copied()) {
                            d = d.with_note(format!("did you mean `{s}`?"));
                        }
                        diags.push(d);
                        continue;
                    }
                };
                spec.missing.push((modality.name.clone(), p));
            }
            VariantDecl::Select { axis, source, mapping, span } => {
                let Some(ax) = spec.axes.iter().find(|a| a.name == axis.name).cloned() else {
                    let names: Vec<&str> = spec.axes.iter().map(|a| a.name.as_str()).collect();
                    let mut d = Diagnostic::error(Code::UnknownName, format!("unknown axis `{}`", axis.name))
                        .with_primary(axis.span, "not declared with `axis`");
                    if let Some(s) = suggest(&axis.name, names.iter().copied()) {
                        d = d.with_note(format!("did you mean `{s}`?"));
                    }
                    diags.push(d);
                    continue;
                };
                if let Some(prev) = select_spans.insert(axis.name.clone(), *span) {
                    diags.push(
                        Diagnostic::error(Code::DuplicateName, format!("axis `{}` has two selectors", axis.name))
                            .with_primary(*span, "second selector")
                            .with_secondary(prev, "first selector here"),
                    );
                    continue;
                }
                let src = match source {
                    SelectSource::Meta { key, span } => {
                        if key.is_empty() {
                            diags.push(
                                Diagnostic::error(Code::BadVariant, "metadata key is empty")
                                    .with_primary(*span, "empty key"),
                            );
                            continue;
                        }
                        KeySource::Meta(key.clone())
                    }
                    SelectSource::Stat { stat, input } => {
                        let Some(statistic) = Statistic::from_name(&stat.name) else {
                            let mut d =
                                Diagnostic::error(Code::BadVariant, format!("unknown statistic `{}`", stat.name))
                                    .with_primary(stat.span, "not a statistic");
                            let names = Statistic::ALL.map(Statistic::name);
                            d = match suggest(&stat.name, names) {
                                Some(s) => d.with_note(format!("did you mean `{s}`?")),
                                None => d.with_note(format!("statistics: {}", names.join(", "))),
                            };
                            diags.push(d);
                            continue;
                        };
                        let Some(inp) = inputs.iter().find(|i| i.name == input.name) else {
                            let mut d = Diagnostic::error(Code::UnknownName, format!("unknown input `{}`", input.name))
                                .with_primary(input.span, "not an input of the model");
                            if let Some(s) = suggest(&input.name, inputs.iter().map(|i| i.name.as_str())) {
                                d = d.with_note(format!("did you mean `{s}`?"));
                            }
                            diags.push(d);
                            continue;
                        };
                        if inp.modality.as_deref() != Some(ax.modality.as_str()) {
                            diags.push(
                                Diagnostic::error(
                                    Code::BadVariant,
                                    format!(
                                        "axis `{}` is a {} condition but `{}` is {}",
                                        ax.name,
                                        ax.modality,
                                        inp.name,
                                        inp.modality
                                            .as_deref()
                                            .map(|m| format!("a {m} input"))
                                            .unwrap_or("untagged".into())
                                    ),
                                )
                                .with_primary(input.span, "input of another modality")
                                .with_secondary(inp.span, "input declared here"),
                            );
                            continue;
                        }
                        KeySource::Stat { stat: statistic, input: input.name.clone() }
                    }
                };
                let arms = match mapping {
                    SelectMap::Nearest => Vec::new(),
                    SelectMap::Thresholds(arms) => {
                        let Some(a) = check_thresholds(&ax, arms, *span, diags) else { continue };
                        a
                    }
                };
                spec.selectors.push(KeySelector { axis: ax.name.clone(), source: src, arms });
            }
            VariantDecl::Meld { weights, span } => {
                if let Some(prev) = meld_span.replace(*span) {
                    diags.push(
                        Diagnostic::error(Code::DuplicateName, "the section has two `meld` rules")
                            .with_primary(*span, "second rule")
                            .with_secondary(prev, "first rule here"),
                    );
                    continue;
                }
                if let Some(m) = check_meld(&spec, weights, *span, &modalities, diags) {
                    spec.meld = Some(m);
                }
            }
        }
    }
    spec
}

/// Checks `meld a = l1, b = l2`: the names are all axes or all modalities with axes, each
/// once, with lambdas in [0, 1] that sum to 1.
fn check_meld(
    spec: &VariantSpec,
    weights: &[(readi_grammar::ast::Ident, Number)],
    span: Span,
    modalities: &[&str],
    diags: &mut Diagnostics,
) -> Option<Meld> {
    let mut ok = true;
    let mut kinds = Vec::new();
    let mut out: Vec<(String, f64)> = Vec::new();
    for (m, l) in weights {
        let by = if spec.axes.iter().any(|a| a.name == m.name) {
            Some(MeldBy::Axis)
        } else if spec.axes.iter().any(|a| a.modality == m.name) {
            Some(MeldBy::Modality)
        } else {
            None
        };
        match by {
            _ if out.iter().any(|(n, _)| *n == m.name) => {
                diags.push(
                    Diagnostic::error(Code::DuplicateName, format!("`{}` appears twice in the meld rule", m.name))
                        .with_primary(m.span, "again here"),
                );
                ok = false;
            }
            Some(b) => kinds.push((b, m.span)),
            None => {
                let what = if modalities.contains(&m.name.as_str()) {
                    format!("no axis is declared on `{}`, so it has no variants to meld", m.name)
                } else {
                    format!("`{}` is neither an axis nor a modality with axes", m.name)
                };
                let mut d = Diagnostic::error(Code::BadVariant, what).with_primary(m.span, "nothing to meld");
                let mut names: Vec<&str> = spec.axes.iter().map(|a| a.name.as_str()).collect();
                names.extend(spec.axes.iter().map(|a| a.modality.as_str()));
                if let Some(s) = suggest(&m.name, names) {
                    d = d.with_note(format!("did you mean `{s}`?"));
                }
                diags.push(d);
                ok = false;
            }
        }
        if !(0.0..=1.0).contains(&l.value) {
            diags.push(
                Diagnostic::error(Code::BadVariant, format!("lambda {} is outside [0, 1]", l.text))
                    .with_primary(l.span, "out of range"),
            );
            ok = false;
        }
        out.push((m.name.clone(), l.value));
    }
    if let Some(&(first, _)) = kinds.first()
        && let Some(&(_, other)) = kinds.iter().find(|(k, _)| *k != first)
    {
        diags.push(
            Diagnostic::error(Code::BadVariant, "a meld rule names either modalities or axes, not both")
                .with_primary(other, "of the other kind")
                .with_secondary(kinds[0].1, "first name here"),
        );
        ok = false;
    }
    let sum: f64 = out.iter().map(|(_, l)| l).sum();
    if out.len() < 2 {
        diags.push(
            Diagnostic::error(Code::BadVariant, "a meld rule needs two modalities or axes")
                .with_primary(span, "only one")
                .with_note("for example `meld camera = 0.8, lidar = 0.2`"),
        );
        ok = false;
    } else if ok && (sum - 1.0).abs() > 1e-9 {
        diags.push(
            Diagnostic::error(Code::BadVariant, format!("meld lambdas sum to {sum}, not 1"))
                .with_primary(span, "lambdas must sum to 1"),
        );
        ok = false;
    }
    ok.then(|| Meld { by: kinds.first().map(|k| k.0).unwrap_or(MeldBy::Modality), weights: out })
}

fn check_thresholds(
    ax: &Axis,
    arms: &[readi_grammar::ast::ThresholdArm],
    span: Span,
    diags: &mut Diagnostics,
) -> Option<Vec<Arm>> {
    let mut out = Vec::new();
    let mut ok = true;
    let mut last: Option<f64> = None;
    if arms.is_empty() {
        diags.push(
            Diagnostic::error(Code::BadVariant, "the threshold map is empty")
                .with_primary(span, "add arms such as `< 0.2 -> 0.25, else -> clear`, or write `nearest`"),
        );
        return None;
    }
    for (i, arm) in arms.iter().enumerate() {
        match &arm.bound {
            None if i + 1 != arms.len() => {
                diags.push(
                    Diagnostic::error(Code::BadVariant, "`else` must be the last arm")
                        .with_primary(arm.span, "arms after this are never reached"),
                );
                ok = false;
            }
            None => {}
            Some((_, n)) => {
                if let Some(prev) = last
                    && n.value <= prev
                {
                    diags.push(
                        Diagnostic::error(
                            Code::BadVariant,
                            format!("threshold {} is not above the previous {prev}", n.text),
                        )
                        .with_primary(n.span, "thresholds must increase"),
                    );
                    ok = false;
                }
                last = Some(n.value);
            }
        }
        let level = match &arm.level {
            LevelRef::Clear(_) => None,
            LevelRef::Level(n) => {
                if !ax.levels.contains(&n.value) && ax.clear != Some(n.value) {
                    let shown: Vec<String> = ax.levels.iter().map(|l| fmt_level(*l)).collect();
                    diags.push(
                        Diagnostic::error(Code::BadVariant, format!("{} is not a level of axis `{}`", n.text, ax.name))
                            .with_primary(n.span, "unknown level")
                            .with_note(format!("levels: {} (or `clear`)", shown.join(", "))),
                    );
                    ok = false;
                }
                if ax.clear == Some(n.value) { None } else { Some(n.value) }
            }
        };
        out.push(Arm { below: arm.bound.as_ref().map(|(incl, n)| (n.value, *incl)), level });
    }
    if arms.last().is_some_and(|a| a.bound.is_some()) {
        diags.push(
            Diagnostic::error(Code::BadVariant, "the thresholds do not cover large values")
                .with_primary(span, "add a last arm `else -> level`"),
        );
        ok = false;
    }
    ok.then_some(out)
}

fn dedup<'a>(v: &[&'a str]) -> Vec<&'a str> {
    let mut out: Vec<&str> = Vec::new();
    for x in v {
        if !out.contains(x) {
            out.push(x);
        }
    }
    out
}
