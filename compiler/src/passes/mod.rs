//! The pipeline, in one place: every pass from source text to plan, run by one driver.
//!
//! | pass               | changes                                                        | assumes                  |
//! |--------------------|----------------------------------------------------------------|--------------------------|
//! | `parse`            | source text to AST                                             | —                        |
//! | `elaborate`        | AST to a fully typed graph                                     | no syntax errors         |
//! | `dead_code`        | removes nodes no output depends on                             | a verified graph         |
//! | `resolve_adapt`    | binds adaptation rules to layers (side table)                  | dead code removed        |
//! | `inject_adapt`     | adds LoRA branches and adapters (zero in the base)             | rules resolved           |
//! | `check_variants`   | checks the variants section (side table)                       | a verified graph         |
//! | `bind_weights`     | the base weights into the tensor table                         | the front end ran        |
//! | `bind_variants`    | each variant's tensors into the table                          | base weights bound       |
//! | `meld`             | melded variants from their parts                               | variants bound           |
//! | `prune`            | zeroes small values of the shared weights (`prune` rules)     | melds built              |
//! | `fold_constants`   | pure nodes of stored tensors no variant changes computed now  | tensor values final      |
//! | `drop_inactive`    | removes LoRA branches and adapters no variant uses             | variants bound           |
//! | `choose_strategy`  | per LoRA layer merge or branch, per variant-owned conv its algorithm (side table) | inactive ones dropped |
//! | `commute_adapters` | moves adapters (and LoRA branches) behind their BatchNorm      | inactive ones dropped    |
//! | `merge_lora`       | merges LoRA into the layer's weight, per variant               | `--lora merge`           |
//! | `fuse_lora`        | a LoRA branch into its conv's or linear's kernel               | LoRA left as branches    |
//! | `fold_batchnorm`   | BatchNorm into the conv before it, or a channel affine         | adaptations placed       |
//! | `fuse_adapters`    | an adapter into the conv producing its input (an epilogue)     | BatchNorms folded        |
//! | `fuse_epilogues`   | biases into epilogue shifts, ReLUs into their producer, a residual add into its conv | BatchNorms folded |
//! | `choose_conv_algo` | an algorithm per conv                                          | epilogues fused          |
//! | `pack_weights`     | conv weights packed for their algorithm, linear transposed     | algorithms chosen        |
//! | `lower`            | one kernel step per node: the schedule and the variant tables  | weights packed           |
//! | `plan_buffers`     | activation buffers shared by values whose lifetimes do not overlap | lowered              |
//!
//! Each pass is a file here, opening with what it changes, what it assumes and when it
//! does nothing. Passes do not mutate the module: a rewriting pass returns [`Patch`]es,
//! named by the rule that made them, which [`apply`] applies; the driver asks the pass
//! again until it finds nothing (a fixed point). The one exception is `inject_adapt`,
//! which creates nodes (a patch only rewires and removes them): it adds them through the
//! graph's API and records them in the adaptation plan. A pass that computes a side table (the
//! adaptation plan, the tensor table, the lowered plan) returns it and the driver stores
//! it. After every pass the driver runs the verifier ([`crate::verify`]); a failure is a
//! compiler bug, reported as an internal error at the node it concerns and naming the
//! pass. The CLI can stop after any pass (`readi ir --stop-after fold_batchnorm`).

pub mod bind_variants;
pub mod bind_weights;
pub mod check_variants;
pub mod choose_conv_algo;
pub mod choose_strategy;
pub mod commute_adapters;
pub mod dead_code;
pub mod drop_inactive;
pub mod fold_batchnorm;
pub mod fold_constants;
pub mod fuse_adapters;
pub mod fuse_epilogues;
pub mod fuse_lora;
pub mod inject_adapt;
pub mod lower;
pub mod meld;
pub mod merge_lora;
pub mod pack_weights;
pub mod plan_buffers;
pub mod prune;
pub mod resolve_adapt;

use std::collections::HashSet;

use readi_grammar::ast::SourceFile;
use readi_grammar::diag::{Code, Diagnostic, Diagnostics, FileId, Span};

use crate::elaborate::{ElabOptions, elaborate};
use crate::ir::{NodeId, Op, ParamSlot, ValueRef};
use crate::module::{Lowered, Module};
use crate::verify::{VerifyError, verify};
use crate::weights::tensors::Tensor;
use crate::weights::{VariantSource, WeightSet};
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
    BindWeights,
    BindVariants,
    Meld,
    Prune,
    FoldConstants,
    DropInactive,
    ChooseStrategy,
    CommuteAdapters,
    MergeLora,
    FuseLora,
    FoldBatchnorm,
    FuseAdapters,
    FuseEpilogues,
    ChooseConvAlgo,
    PackWeights,
    Lower,
    PlanBuffers,
}

/// The passes in order, with their names and one-line descriptions.
pub const PIPELINE: &[(Pass, &str, &str)] = &[
    (Pass::Parse, "parse", "source text to syntax tree"),
    (Pass::Elaborate, "elaborate", "evaluate blocks, loops and attributes into a typed graph"),
    (Pass::DeadCode, "dead_code", "remove layers that no output depends on"),
    (Pass::ResolveAdapt, "resolve_adapt", "bind adaptation rules to layers; check conflicts"),
    (Pass::InjectAdapt, "inject_adapt", "add LoRA branches and adapters to the graph (zero in the base model)"),
    (Pass::CheckVariants, "check_variants", "check axes, selectors, missing-modality and meld rules"),
    (Pass::BindWeights, "bind_weights", "bind the base weights (safetensors, PyTorch names) to the parameter slots"),
    (Pass::BindVariants, "bind_variants", "bind each variant's tensors, checked against the adaptation rules"),
    (Pass::Meld, "meld", "build melded variants: layers one part tunes taken whole, shared ones interpolated"),
    (Pass::Prune, "prune", "zero the shared conv and linear weights' values below a `prune` rule's threshold"),
    (
        Pass::FoldConstants,
        "fold_constants",
        "compute at compile time what depends only on stored tensors no variant changes",
    ),
    (Pass::DropInactive, "drop_inactive", "remove LoRA branches and adapters that are zero in every variant"),
    (Pass::ChooseStrategy, "choose_strategy", "per LoRA layer merge or branch, per variant-owned conv its algorithm"),
    (Pass::CommuteAdapters, "commute_adapters", "move adapters and LoRA branches behind their BatchNorm"),
    (Pass::MergeLora, "merge_lora", "merge LoRA into the adapted layer's weight, per variant (--lora merge)"),
    (Pass::FuseLora, "fuse_lora", "compute each LoRA branch in its conv's or linear's kernel (--lora branch)"),
    (Pass::FoldBatchnorm, "fold_batchnorm", "fold BatchNorm into the conv before it, or make it a channel affine"),
    (Pass::FuseAdapters, "fuse_adapters", "compute each adapter in the kernel of the conv producing its input"),
    (
        Pass::FuseEpilogues,
        "fuse_epilogues",
        "biases into epilogue shifts; ReLUs into the conv, linear or affine before",
    ),
    (
        Pass::ChooseConvAlgo,
        "choose_conv_algo",
        "choose each conv's algorithm (im2col, Winograd, depthwise, 1x1 GEMM, weight panels)",
    ),
    (Pass::PackWeights, "pack_weights", "pack conv weights for their algorithm; store linear weights transposed"),
    (Pass::Lower, "lower", "one kernel step per node: the schedule, stored tensors and variant tables"),
    (Pass::PlanBuffers, "plan_buffers", "share activation buffers between values whose lifetimes do not overlap"),
];

/// The first pass of the back end (it needs weights).
pub const FIRST_BACKEND_PASS: Pass = Pass::BindWeights;

impl Pass {
    pub fn name(self) -> &'static str {
        PIPELINE.iter().find(|p| p.0 == self).map(|p| p.1).unwrap_or("?")
    }
    pub fn from_name(name: &str) -> Option<Pass> {
        PIPELINE.iter().find(|p| p.1 == name).map(|p| p.0)
    }
    /// Whether the pass belongs to the back end (needs weights).
    pub fn is_backend(self) -> bool {
        self >= FIRST_BACKEND_PASS
    }
}

/// A graph rewrite proposed by a pass, applied by [`apply`]. The label names the rule
/// that produced it, for messages and listings. Its parts apply in field order.
#[derive(Clone, Debug, Default)]
pub struct Patch {
    pub rule: &'static str,
    /// Tensors added to the table or replacing one of the same name.
    pub tensors: Vec<(String, Tensor)>,
    /// Nodes whose op and parameter slots are replaced (id, inputs and path are kept).
    pub rewrite: Vec<(NodeId, Op, Vec<ParamSlot>)>,
    /// Nodes whose inputs are disconnected (after `rewrite`): a node that became a
    /// constant reads nothing.
    pub detach: Vec<NodeId>,
    /// Uses of the first value are redirected to the second.
    pub replace_uses: Vec<(ValueRef, ValueRef)>,
    /// Input port of a node set to a value.
    pub set_inputs: Vec<(NodeId, u16, ValueRef)>,
    /// Paths of nodes merged into a node, for listings (`conv1 (+bn1)`).
    pub fuse: Vec<(NodeId, String)>,
    /// Nodes to delete (after everything else). The adaptation plan forgets them.
    pub remove: Vec<NodeId>,
}

impl Patch {
    /// A patch of the rule `rule`.
    pub fn new(rule: &'static str) -> Patch {
        Patch { rule, ..Patch::default() }
    }

    /// Every node the patch changes or whose uses it changes.
    fn touched(&self) -> HashSet<NodeId> {
        let mut t: HashSet<NodeId> = HashSet::new();
        t.extend(self.rewrite.iter().map(|r| r.0));
        t.extend(self.detach.iter().copied());
        t.extend(self.replace_uses.iter().flat_map(|(a, b)| [a.node, b.node]));
        t.extend(self.set_inputs.iter().flat_map(|(n, _, v)| [*n, v.node]));
        t.extend(self.fuse.iter().map(|f| f.0));
        t.extend(self.remove.iter().copied());
        t
    }
}

/// The slots `op` derives, bound to their tensors: a slot named in `bind` reads the tensor
/// given there; a slot of the same name in `old` keeps the tensor and kind it had; any
/// other reads `<path>.<name>`. How a rewrite gives a node its new slots.
pub(crate) fn rebind(op: &Op, old: &[ParamSlot], bind: &[(&str, String)]) -> Vec<ParamSlot> {
    op.param_slots()
        .into_iter()
        .map(|slot| {
            let prev = old.iter().find(|o| o.name == slot.name);
            let kind = prev.map_or(slot.kind, |o| o.kind);
            let tensor = match bind.iter().find(|(n, _)| *n == slot.name) {
                Some((_, t)) => Some(t.clone()),
                None => prev.and_then(|o| o.tensor.clone()),
            };
            ParamSlot { kind, tensor, ..slot }
        })
        .collect()
}

/// Applies a patch to a module.
pub fn apply(module: &mut Module, patch: Patch) {
    if let Some(table) = module.tensors.as_mut() {
        for (name, t) in patch.tensors {
            table.insert(name, t);
        }
    }
    let g = &mut module.graph;
    for (id, op, params) in patch.rewrite {
        let node = g.node_mut(id);
        node.op = op;
        node.params = params;
    }
    for &id in &patch.detach {
        g.detach_inputs(id);
    }
    for (old, new) in &patch.replace_uses {
        g.replace_uses(*old, *new);
    }
    for &(node, port, value) in &patch.set_inputs {
        g.set_input(node, port, value);
    }
    for (id, path) in patch.fuse {
        g.node_mut(id).fused.push(path);
    }
    for &n in &patch.remove {
        g.remove_node(n);
    }
    if let Some(plan) = module.adapt.as_mut()
        && !patch.remove.is_empty()
    {
        plan.forget(&patch.remove);
    }
}

/// Applies the patches of one round; a patch touching a node an earlier one of the round
/// touched is left for the next round (the pass finds it again if it still applies).
/// Counts the rules applied into `log`.
fn apply_round(module: &mut Module, patches: Vec<Patch>, pass: Pass, log: &mut Vec<Applied>) {
    let mut touched: HashSet<NodeId> = HashSet::new();
    for p in patches {
        let t = p.touched();
        if t.iter().any(|n| touched.contains(n)) {
            continue;
        }
        touched.extend(t);
        match log.iter_mut().find(|a| a.pass == pass && a.rule == p.rule) {
            Some(a) => a.count += 1,
            None => log.push(Applied { pass, rule: p.rule, count: 1 }),
        }
        apply(module, p);
    }
}

/// How often a pass applied one of its rules.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Applied {
    pub pass: Pass,
    pub rule: &'static str,
    pub count: usize,
}

/// What a back-end run reports besides the module: its warnings and the rules each pass
/// applied, in order.
#[derive(Debug, Default)]
pub struct BackendRun {
    pub warnings: Diagnostics,
    pub applied: Vec<Applied>,
}

/// Options of a pipeline run.
#[derive(Clone, Debug, Default)]
pub struct Options {
    pub elab: ElabOptions,
    /// Stop after this pass (the whole front end when `None`).
    pub stop_after: Option<Pass>,
}

impl Options {
    /// The whole pipeline with model parameters set from `name=value` text, as the
    /// command line's `--set` gives them.
    pub fn with_overrides<K: AsRef<str>, V: AsRef<str>>(pairs: &[(K, V)]) -> Options {
        let overrides =
            pairs.iter().map(|(k, v)| (k.as_ref().to_string(), crate::elaborate::Literal::parse(v.as_ref()))).collect();
        Options { elab: ElabOptions { overrides, ..ElabOptions::default() }, stop_after: None }
    }
}

/// The activations a model needs at batch size 1, over `limit`: the values alive at once
/// when the nodes run in order, each freed after its last reader (values nothing reads,
/// the outputs, live to the end). Elaboration refuses a single value over the limit; this
/// is their sum at the peak, an error at the largest of them with the next ones labelled.
fn activation_peak_error(g: &crate::ir::Graph, limit: u64) -> Option<Diagnostic> {
    use crate::elaborate::bytes_at_batch_1;
    let order = g.topo_order()?;
    let size = |n: NodeId| -> u64 {
        g.node(n).outputs.iter().map(|t| bytes_at_batch_1(t).unwrap_or(u64::MAX)).fold(0u64, u64::saturating_add)
    };
    let position: std::collections::HashMap<NodeId, usize> = order.iter().enumerate().map(|(i, &n)| (n, i)).collect();
    // The step after which each node's values are freed (`None`: never).
    let last_use = |n: NodeId| g.users(n).iter().filter_map(|u| position.get(u).copied()).max();
    let mut frees: Vec<Vec<NodeId>> = vec![Vec::new(); order.len()];
    for &n in &order {
        if let Some(i) = last_use(n) {
            frees[i].push(n);
        }
    }
    let (mut live, mut peak, mut at) = (0u64, 0u64, 0usize);
    for (i, &n) in order.iter().enumerate() {
        live = live.saturating_add(size(n));
        if live > peak {
            (peak, at) = (live, i);
        }
        for &f in &frees[i] {
            live = live.saturating_sub(size(f));
        }
    }
    if peak <= limit {
        return None;
    }
    // The values alive at the peak, largest first.
    let mut alive: Vec<(u64, NodeId)> = order[..=at]
        .iter()
        .filter(|&&n| last_use(n).is_none_or(|i| i >= at))
        .map(|&n| (size(n), n))
        .filter(|&(b, _)| b > 0)
        .collect();
    alive.sort_by_key(|a| std::cmp::Reverse(a.0));
    let show = |n: NodeId| if g.node(n).path.is_empty() { "<model>".to_string() } else { g.node(n).path.clone() };
    let (b0, n0) = *alive.first()?;
    let mut d = Diagnostic::error(
        Code::Limit,
        format!(
            "the activations at batch size 1 peak at {} ({} values alive together at `{}`), over the activation \
             limit of {}",
            crate::print::bytes(peak),
            alive.len(),
            show(order[at]),
            crate::print::bytes(limit)
        ),
    )
    .with_primary(g.node(n0).span, format!("the largest: `{}`, {}", show(n0), crate::print::bytes(b0)));
    for &(b, n) in alive.iter().skip(1).take(3) {
        d = d.with_secondary(g.node(n).span, format!("`{}`, {}", show(n), crate::print::bytes(b)));
    }
    Some(d.with_note("`readi compile --max-activation-memory` sets the limit (default 4G)"))
}

/// The outcome of a front-end run: the module as far as it got, and every diagnostic.
#[derive(Debug)]
pub struct Outcome {
    pub ast: SourceFile,
    pub module: Option<Module>,
    pub diagnostics: Diagnostics,
    /// The last pass that ran to completion.
    pub reached: Option<Pass>,
}

/// Runs the front end (`parse` to `check_variants`, or up to `opts.stop_after`) on one
/// source file.
pub fn run(file: FileId, src: &str, opts: &Options) -> Outcome {
    run_with_uses(file, src, opts, &mut readi_grammar::imports::no_files)
}

/// As [`run`], for a source read from a file: `load` reads the files its `use`
/// declarations name ([`readi_grammar::imports`]).
pub fn run_with_uses(file: FileId, src: &str, opts: &Options, load: &mut readi_grammar::imports::Load<'_>) -> Outcome {
    let parsed = readi_grammar::imports::parse_with_uses(file, src, load);
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
    let mut module = Module::new(graph);
    let errors = diags.has_errors();
    if !errors {
        check(&module, Pass::Elaborate, &mut diags);
    }
    if errors || diags.has_errors() {
        // A graph with errors is kept for printing but goes no further.
        out.module = Some(module);
        out.diagnostics = diags;
        return out;
    }
    out.reached = Some(Pass::Elaborate);

    for &(pass, _, _) in PIPELINE.iter().filter(|p| p.0 > Pass::Elaborate && !p.0.is_backend()) {
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
                        Some(p) => apply(&mut module, p),
                        None => break,
                    }
                }
                let limit = opts.elab.max_activation_bytes.unwrap_or(crate::elaborate::DEFAULT_MAX_ACTIVATION_BYTES);
                if let Some(d) = activation_peak_error(&module.graph, limit) {
                    diags.push(d);
                }
            }
            Pass::ResolveAdapt => {
                let sections: Vec<_> = out.ast.adapt_sections().collect();
                if !sections.is_empty() {
                    module.adapt = Some(resolve_adapt::run(&module.graph, &sections, &out.ast, &mut diags));
                }
            }
            Pass::InjectAdapt => {
                if let Some(plan) = module.adapt.as_mut()
                    && let Err(e) = inject_adapt::run(&mut module.graph, plan)
                {
                    let span = module.graph.scopes[0].span;
                    diags.push(
                        Diagnostic::error(Code::Internal, format!("internal compiler error in `inject_adapt`: {e}"))
                            .with_primary(span, "please report this with the input file"),
                    );
                }
                // Elaboration bounds the spec's own parameters; an adapter on a wide layer
                // adds `C * C/r` elements, which must fit the same limit.
                let g = &module.graph;
                let max = crate::elaborate::MAX_PARAM_ELEMENTS;
                if let Some((name, id, slot)) = g.param_table().into_iter().find(|(_, _, s)| s.numel() > max) {
                    diags.push(
                        Diagnostic::error(
                            Code::Limit,
                            format!(
                                "parameter `{name}` of shape {:?} has {} elements, over the limit of {max}",
                                slot.shape,
                                slot.numel()
                            ),
                        )
                        .with_primary(g.node(id).span, "an adaptation rule adds this layer")
                        .with_note("a larger squeeze ratio makes an adapter smaller"),
                    );
                }
            }
            Pass::CheckVariants => {
                if let Some(section) = out.ast.variant_sections().next() {
                    module.variants = Some(check_variants::run(&module.graph, section, &mut diags));
                }
            }
            _ => {}
        }
        check(&module, pass, &mut diags);
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

/// How LoRA runs in the plan.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LoraMode {
    /// Folded into the adapted layer's weight per variant: no extra work at run time, but
    /// each variant stores the whole weight of every LoRA layer.
    #[default]
    Merge,
    /// Kept as a side branch `scale * B(A(x))`: each variant stores only `A` and `B`.
    Branch,
    /// Chosen per layer by `choose_strategy` (merge unless a memory budget needs branches).
    Auto,
}

impl LoraMode {
    pub fn name(self) -> &'static str {
        match self {
            LoraMode::Merge => "merge",
            LoraMode::Branch => "branch",
            LoraMode::Auto => "auto",
        }
    }
}

/// Options of the back end.
#[derive(Clone, Debug, Default)]
pub struct CompileOptions {
    /// Tensors in the weights file that the model does not use are warnings, not errors.
    pub allow_unused: bool,
    /// How LoRA branches run.
    pub lora: LoraMode,
    /// An owned parameter a variant does not give is an error, not a warning.
    pub strict: bool,
    /// Melded variants to build from the given ones, `fog=0.06+gamma=0.5`.
    pub melds: Vec<String>,
    /// Most bytes a variant may store, percent of the base plan's (`--memory-budget`):
    /// `choose_strategy` branches LoRA layers and picks compact algorithms to fit.
    pub memory_budget: Option<f64>,
    /// Time the chosen kernels for `--explain` even when no choice needs it.
    pub explain: bool,
    /// Milliseconds of re-merge work a variant switch may take (`--switch-budget`): the
    /// layers `choose_strategy` merges on switch, their measured merge-and-pack time
    /// summed. `None`: [`choose_strategy::DEFAULT_SWITCH_BUDGET_MS`].
    pub switch_budget: Option<f64>,
    /// How `choose_strategy` learns kernel latencies (tests give fixed ones).
    pub timing: choose_strategy::Timing,
    /// Keep adapters as separate steps (`fuse_adapters` does nothing): for comparisons.
    pub unfused_adapters: bool,
    /// `--variant-f16`: `choose_strategy` may store the variants' values of the weights
    /// no choice changes (a tuned head's, a tuned conv's with one algorithm) at half
    /// precision, the largest first, where the memory budget needs it (all of them
    /// without a budget). Lossy: `readi compile` reports how far the outputs move.
    pub variant_f16: bool,
}

/// What the back end compiles a module with.
#[derive(Clone, Copy, Debug)]
pub struct BackendInputs<'a> {
    /// The base model's weights, and the file they came from (for messages).
    pub base: &'a WeightSet,
    pub base_name: &'a str,
    /// Each variant's parameters.
    pub variants: &'a [VariantSource],
    pub opts: &'a CompileOptions,
}

/// What a back-end pass computed.
pub enum Output {
    /// Graph rewrites, applied by the driver.
    Patches(Vec<Patch>),
    /// The tensor table, stored as the module's.
    Tensors(Box<crate::weights::tensors::TensorTable>),
    /// The lowered plan, stored as the module's.
    Lowered(Box<Lowered>),
    /// The per-layer strategy, stored as the module's.
    Strategy(Box<choose_strategy::Strategy>),
}

/// A back-end pass: reads the module, returns what it computed and any warnings, or the
/// errors that stop compilation.
type BackendPass = fn(&Module, &BackendInputs<'_>, &mut Diagnostics) -> Result<Output, Diagnostics>;

fn backend_pass(pass: Pass) -> Option<BackendPass> {
    Some(match pass {
        Pass::BindWeights => bind_weights::run,
        Pass::BindVariants => bind_variants::run,
        Pass::Meld => meld::run,
        Pass::Prune => prune::run,
        Pass::FoldConstants => fold_constants::run,
        Pass::DropInactive => drop_inactive::run,
        Pass::ChooseStrategy => choose_strategy::run,
        Pass::CommuteAdapters => commute_adapters::run,
        Pass::MergeLora => merge_lora::run,
        Pass::FuseLora => fuse_lora::run,
        Pass::FoldBatchnorm => fold_batchnorm::run,
        Pass::FuseAdapters => fuse_adapters::run,
        Pass::FuseEpilogues => fuse_epilogues::run,
        Pass::ChooseConvAlgo => choose_conv_algo::run,
        Pass::PackWeights => pack_weights::run,
        Pass::Lower => lower::run,
        Pass::PlanBuffers => plan_buffers::run,
        _ => return None,
    })
}

/// Most rounds a rewriting pass may take to reach its fixed point before the driver calls
/// it a compiler bug (each round applies every non-overlapping patch found).
const MAX_ROUNDS: usize = 1000;

/// Runs the back end on a module the front end checked, from `bind_weights` to
/// `plan_buffers` or up to `stop_after`, verifying after every pass. Returns the
/// warnings and the rules applied; on errors the module is left as the failing pass
/// found it.
pub fn run_backend(
    module: &mut Module,
    inputs: &BackendInputs<'_>,
    stop_after: Option<Pass>,
) -> Result<BackendRun, Diagnostics> {
    let mut warnings = Diagnostics::default();
    let mut applied = Vec::new();
    for &(pass, name, _) in PIPELINE.iter().filter(|p| p.0.is_backend()) {
        if stop_after.is_some_and(|s| s < pass) {
            break;
        }
        let Some(f) = backend_pass(pass) else { continue };
        let mut rounds = 0;
        loop {
            let output = f(module, inputs, &mut warnings).map_err(|d| locate(d, module, name))?;
            match output {
                Output::Tensors(t) => module.tensors = Some(*t),
                Output::Lowered(l) => module.lowered = Some(*l),
                Output::Strategy(st) => module.strategy = Some(*st),
                Output::Patches(p) if p.is_empty() => break,
                Output::Patches(p) => {
                    check_derived(module, &p, name)?;
                    apply_round(module, p, pass, &mut applied);
                    rounds += 1;
                    if rounds < MAX_ROUNDS {
                        continue;
                    }
                    let span = module.graph.scopes[0].span;
                    let d = Diagnostic::error(
                        Code::Internal,
                        format!("internal compiler error: pass `{name}` did not reach a fixed point"),
                    )
                    .with_primary(span, "please report this with the input file");
                    return Err(Diagnostics(vec![d]));
                }
            }
            break;
        }
        let mut diags = Diagnostics::default();
        check(module, pass, &mut diags);
        if diags.has_errors() {
            return Err(diags);
        }
    }
    Ok(BackendRun { warnings, applied })
}

/// Every tensor a round of patches derives (folded, merged, moved) must be finite, in the
/// base and in every variant: a NaN or infinity there would silently make the model
/// output constants. The error names the tensor, its sources and the cause, and points
/// at the layer the tensor belongs to.
fn check_derived(module: &Module, patches: &[Patch], pass: &str) -> Result<(), Diagnostics> {
    let Some(table) = module.tensors.as_ref() else { return Ok(()) };
    let mut diags = Diagnostics::default();
    for p in patches {
        for (name, t) in &p.tensors {
            if let Err(m) = table.check_finite(name, t) {
                let g = &module.graph;
                // The layer of its first source (`bn1.weight`: `bn1`), else the rewritten node.
                let owner = t.sources.first().and_then(|s| s.rsplit_once('.')).map(|(l, _)| l);
                let layer = g
                    .node_ids()
                    .find(|&n| Some(g.node(n).path.as_str()) == owner)
                    .or_else(|| p.rewrite.first().map(|r| r.0));
                let span = layer.map_or(g.scopes[0].span, |n| g.node(n).span);
                diags.push(
                    Diagnostic::error(Code::Weights, m)
                        .with_primary(span, format!("in `{pass}` (rule `{}`)", p.rule))
                        .with_note("the weights are finite, but the tensor computed from them is not"),
                );
            }
        }
    }
    if diags.has_errors() { Err(diags) } else { Ok(()) }
}

/// An internal compiler error: a bug, never the user's. Passes report them without a
/// place; the driver points them at the model and names the pass ([`locate`]).
pub(crate) fn internal(message: impl std::fmt::Display) -> Diagnostics {
    Diagnostics(vec![Diagnostic::error(Code::Internal, format!("internal compiler error: {message}"))])
}

/// Internal errors a pass reported without a place point at the model and name the pass:
/// no error reaches the user at `0:0`.
fn locate(diags: Diagnostics, module: &Module, pass: &str) -> Diagnostics {
    let span = module.graph.scopes[0].span;
    Diagnostics(
        diags
            .0
            .into_iter()
            .map(|d| {
                if d.code != Code::Internal || d.primary_span().is_some() {
                    return d;
                }
                let message = format!("{} (in pass `{pass}`)", d.message);
                let mut located =
                    Diagnostic::error(Code::Internal, message).with_primary(span, "while compiling this model");
                for n in d.notes {
                    located = located.with_note(n);
                }
                located.with_note("please report this with the input file")
            })
            .collect(),
    )
}

/// Runs the verifier; its failures are compiler bugs, reported as such, each at the node
/// it concerns (the model's declaration for the graph as a whole).
fn check(module: &Module, after: Pass, diags: &mut Diagnostics) {
    let Err(problems) = verify(module) else { return };
    let model_span = module.graph.scopes[0].span;
    let span_of = |e: &VerifyError| {
        e.node.filter(|&n| module.graph.contains(n)).map(|n| module.graph.node(n).span).unwrap_or(model_span)
    };
    let first: Span = problems.first().map(span_of).unwrap_or(model_span);
    let mut d = Diagnostic::error(
        Code::Internal,
        format!("internal compiler error: the module is invalid after pass `{}`", after.name()),
    )
    .with_primary(first, problems.first().map(|p| p.message.clone()).unwrap_or_default());
    for p in problems.iter().skip(1).take(9) {
        d = d.with_secondary(span_of(p), p.message.clone());
    }
    d = d.with_note("please report this with the input file");
    diags.push(d);
}
