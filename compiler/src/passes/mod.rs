//! The front-end pipeline, in one place.
//!
//! | pass             | changes                                      | assumes                  |
//! |------------------|----------------------------------------------|--------------------------|
//! | `parse`          | source text to AST                           | —                        |
//! | `elaborate`      | AST to a fully typed graph                   | no syntax errors         |
//! | `dead_code`      | removes nodes no output depends on           | a verified graph         |
//! | `resolve_adapt`  | binds adaptation rules to layers (side table)| dead code removed        |
//! | `inject_adapt`   | adds LoRA branches and adapters (zero in the base) | rules resolved     |
//! | `check_variants` | checks the variants section (side table)     | a verified graph         |
//!
//! Passes that rewrite the graph return [`Patch`]es; [`apply`] applies them, and the
//! driver repeats a rewriting pass until it returns none (a fixed point). After every pass
//! the driver runs the verifier ([`crate::verify`]); a verifier failure is a compiler bug
//! and is reported as an internal error. The CLI can stop after any pass
//! (`readi ir --stop-after elaborate`).

pub mod check_variants;
pub mod dead_code;
pub mod inject_adapt;
pub mod resolve_adapt;

use readi_grammar::ast::SourceFile;
use readi_grammar::diag::{Code, Diagnostic, Diagnostics, FileId, Span};

use crate::elaborate::{ElabOptions, elaborate};
use crate::ir::{Graph, NodeId, ValueRef};
use crate::verify::verify;
pub use check_variants::VariantSpec;
pub use resolve_adapt::AdaptPlan;

/// A pass of the pipeline.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Pass {
    Parse,
    Elaborate,
    DeadCode,
    ResolveAdapt,
    InjectAdapt,
    CheckVariants,
}

/// The passes in order, with their names and one-line descriptions.
pub const PIPELINE: &[(Pass, &str, &str)] = &[
    (Pass::Parse, "parse", "source text to syntax tree"),
    (Pass::Elaborate, "elaborate", "evaluate blocks, loops and attributes into a typed graph"),
    (Pass::DeadCode, "dead_code", "remove layers that no output depends on"),
    (Pass::ResolveAdapt, "resolve_adapt", "bind adaptation rules to layers; check conflicts"),
    (Pass::InjectAdapt, "inject_adapt", "add LoRA branches and adapters to the graph (zero in the base model)"),
    (Pass::CheckVariants, "check_variants", "check axes, selectors, missing-modality and meld rules"),
];

impl Pass {
    pub fn name(self) -> &'static str {
        PIPELINE.iter().find(|p| p.0 == self).map(|p| p.1).unwrap_or("?")
    }
    pub fn from_name(name: &str) -> Option<Pass> {
        PIPELINE.iter().find(|p| p.1 == name).map(|p| p.0)
    }
}

/// A graph and what the passes have learned about it.
#[derive(Clone, Debug)]
pub struct Module {
    pub graph: Graph,
    /// Set by `resolve_adapt` when the file has an `adapt` section.
    pub adapt: Option<AdaptPlan>,
    /// Set by `check_variants` when the file has a `variants` section.
    pub variants: Option<VariantSpec>,
}

/// A graph rewrite proposed by a pass, applied by [`apply`]. The label names the rule
/// that produced it, for `--explain`-style output and errors.
#[derive(Clone, Debug, Default)]
pub struct Patch {
    pub rule: &'static str,
    /// Uses of the first value are redirected to the second.
    pub replace_uses: Vec<(ValueRef, ValueRef)>,
    /// Nodes to delete (after redirection).
    pub remove: Vec<NodeId>,
}

/// Applies a patch to a graph.
pub fn apply(graph: &mut Graph, patch: &Patch) {
    for (old, new) in &patch.replace_uses {
        graph.replace_uses(*old, *new);
    }
    for &n in &patch.remove {
        graph.remove_node(n);
    }
}

/// Options of a pipeline run.
#[derive(Clone, Debug, Default)]
pub struct Options {
    pub elab: ElabOptions,
    /// Stop after this pass (the whole pipeline when `None`).
    pub stop_after: Option<Pass>,
}

impl Options {
    /// The whole pipeline with model parameters set from `name=value` text, as the
    /// command line's `--set` gives them.
    pub fn with_overrides<K: AsRef<str>, V: AsRef<str>>(pairs: &[(K, V)]) -> Options {
        let overrides =
            pairs.iter().map(|(k, v)| (k.as_ref().to_string(), crate::elaborate::Literal::parse(v.as_ref()))).collect();
        Options { elab: ElabOptions { overrides }, stop_after: None }
    }
}

/// The outcome of a pipeline run: the module as far as it got, and every diagnostic.
#[derive(Debug)]
pub struct Outcome {
    pub ast: SourceFile,
    pub module: Option<Module>,
    pub diagnostics: Diagnostics,
    /// The last pass that ran to completion.
    pub reached: Option<Pass>,
}

/// Runs the front-end pipeline on one source file.
pub fn run(file: FileId, src: &str, opts: &Options) -> Outcome {
    let parsed = readi_grammar::parse(file, src);
    let mut diags = parsed.diagnostics;
    let ast = parsed.file;
    let mut out = Outcome { ast, module: None, diagnostics: Diagnostics::default(), reached: None };
    if diags.has_errors() {
        out.diagnostics = diags;
        return out;
    }
    out.reached = Some(Pass::Parse);
    if opts.stop_after == Some(Pass::Parse) {
        out.diagnostics = diags;
        return out;
    }

    let (graph, d) = elaborate(&out.ast, file, &opts.elab);
    diags.extend(d);
    let Some(graph) = graph else {
        out.diagnostics = diags;
        return out;
    };
    let mut module = Module { graph, adapt: None, variants: None };
    let errors = diags.has_errors();
    if !errors {
        check(&module, Pass::Elaborate, file, &mut diags);
    }
    if errors || diags.has_errors() {
        // A graph with errors is kept for printing but goes no further.
        out.module = Some(module);
        out.diagnostics = diags;
        return out;
    }
    out.reached = Some(Pass::Elaborate);

    for &(pass, _, _) in &PIPELINE[2..] {
        if opts.stop_after.is_some_and(|s| s < pass) {
            break;
        }
        match pass {
            Pass::DeadCode => {
                // Iterate to a fixed point; report only what the first round found.
                let mut round = 0;
                loop {
                    let mut found = Diagnostics::default();
                    let patch = dead_code::run(&module.graph, &mut found);
                    if round == 0 {
                        diags.extend(found);
                    }
                    round += 1;
                    match patch {
                        Some(p) => apply(&mut module.graph, &p),
                        None => break,
                    }
                }
            }
            Pass::ResolveAdapt => {
                if let Some(section) = out.ast.adapt_sections().next() {
                    module.adapt = Some(resolve_adapt::run(&module.graph, section, &out.ast, &mut diags));
                }
            }
            Pass::InjectAdapt => {
                if let Some(plan) = module.adapt.as_mut()
                    && let Err(e) = inject_adapt::run(&mut module.graph, plan)
                {
                    diags.push(
                        Diagnostic::error(Code::Internal, format!("internal compiler error in `inject_adapt`: {e}"))
                            .with_primary(Span::new(file, 0, 0), "please report this with the input file"),
                    );
                }
            }
            Pass::CheckVariants => {
                if let Some(section) = out.ast.variant_sections().next() {
                    module.variants = Some(check_variants::run(&module.graph, section, &mut diags));
                }
            }
            Pass::Parse | Pass::Elaborate => {}
        }
        check(&module, pass, file, &mut diags);
        if diags.has_errors() {
            break;
        }
        out.reached = Some(pass);
    }
    diags.sort();
    out.module = Some(module);
    out.diagnostics = diags;
    out
}

/// Runs the verifier; its failures are compiler bugs, reported as such.
fn check(module: &Module, after: Pass, file: FileId, diags: &mut Diagnostics) {
    if let Err(problems) = verify(module) {
        let mut d = Diagnostic::error(
            Code::Internal,
            format!("internal compiler error: the graph is invalid after pass `{}`", after.name()),
        )
        .with_primary(Span::new(file, 0, 0), "please report this with the input file");
        for p in problems.into_iter().take(10) {
            d = d.with_note(p);
        }
        diags.push(d);
    }
}
