//! `choose_strategy`: decides, per LoRA layer, whether each variant stores the merged
//! weight (**merge**: no run-time cost), only `A` and `B` (**branch**: the branch's two
//! small kernels run, fused into the layer's), or only `A` and `B` with the layer
//! **merged on switch** (no latency: the session keeps one working copy of the layer,
//! into which it writes `pack(W + B A)` at the start of a run whose variant changed; that
//! takes switch time), and per variant-owned conv (a conv whose weight differs per
//! variant once merged: a tuned conv, a merged LoRA layer) the algorithm, whose packed
//! weight each variant stores (Winograd F(4x4) 4x the raw weight, F(2x2) 16/9 of it,
//! im2col 1x), or merge on switch (the variant stores the raw weight; the session packs
//! it into its working copy at a switch).
//! A side table ([`Strategy`], `Module::strategy`) that `commute_adapters`, `merge_lora`
//! and `choose_conv_algo` read; it changes nothing in the graph, so no choice changes a
//! number the plan computes.
//!
//! The cost model: bytes per variant are exact, from the shapes and the packed lengths of
//! every tensor the variant will replace (the per-variant epilogue vectors, heads and
//! adapters included, which no choice changes); a tensor counts for a variant when one of
//! its sources has a value of its own there. Latency is the runtime's own kernels timed on
//! the layer's shapes at batch 1 ([`Timing`]), a few repetitions, median, cached per
//! (algorithm, shape) within the compile, and only when a choice depends on it (a budget
//! the fastest assignment exceeds, or `--explain`). A branch on a conv costs what it adds
//! to the layer's kernel, which computes it (`fuse_lora`; [`branch_ms`]), and stores `A`
//! raw (the runtime packs a Winograd `A` per session). Merge on switch costs no latency
//! (the layer runs as a merged conv at its default algorithm), stores per variant what a
//! branch stores (a tuned conv: its raw weight), and costs its switch time: the
//! runtime's own merge-and-pack (`readi_runtime::kernels::merge::switch_pack`) timed on
//! the layer's shapes like the kernels ([`Timer::switch_ms`]). Its working copy (the
//! packed weight, once per session, whatever the number of variants) is counted on the
//! session's side (`Footprint::working`), not per variant; `--explain` prints it.
//!
//! The choice: start from the fastest assignment (merge, each conv's default algorithm);
//! while the largest variant exceeds the budget (`--memory-budget PCT`, percent of the
//! base plan's bytes), move one layer to its next cheaper option (the fastest option that
//! stores fewer bytes and keeps the layers merged on switch within `--switch-budget MS`,
//! their switch times summed): first the moves that add no latency (merge on switch),
//! the most bytes saved per switch millisecond first, then the others, the most bytes
//! saved per millisecond of latency added first. Then give back latency (the largest
//! gain first) while both budgets hold, since one large move may overshoot.
//!
//! Half precision (`--variant-f16`, opt-in because it is lossy): the variants' values of
//! the weights no choice changes (a tuned linear head's, a tuned conv's that has one
//! algorithm) may be stored as f16, which a session decodes into one f32 working copy per
//! weight at a switch. Under a budget, after the moves that cost nothing (merge on
//! switch), the largest such weights go to f16 until the budget holds, before any move
//! that adds latency; after the give-back, the smallest go back to f32 while the budget
//! still holds. Without a budget every one of them is stored f16.
//!
//! An unreachable budget: when even every layer's smallest option exceeds it, latency
//! would be paid for a budget missed anyway, so the pass keeps the fastest assignment
//! that saves what costs no latency (merge on switch within the switch budget) and warns
//! with the smallest achievable percentage and the latency it would have cost.
//! `--lora merge|branch` forces every LoRA layer (the algorithms, and merge on switch
//! for tuned convs, are still chosen under a budget).
//!
//! Does nothing (records no table) when no adaptation plan has a LoRA layer or a
//! variant-owned conv, or there are no variants. Assumes `drop_inactive` ran (a dropped
//! branch is no choice).

use std::collections::{BTreeMap, HashMap};
use std::fmt::Write as _;
use std::time::Instant;

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use readi_runtime::kernels::{Epilogue, conv, merge};

use super::bind_variants::{not_bound, same_bits};
use super::choose_conv_algo::spatial;
use super::{BackendInputs, LoraMode, Output};
use super::{fuse_lora, pack_weights};
use crate::adapt::Injection;
use crate::ir::{Graph, NodeId, Op};
use crate::module::Module;
use crate::weights::tensors::TensorTable;
pub use readi_plan::ops::{Conv2dShape, ConvAlgo};

/// How the pass learns a kernel's latency: the runtime's kernel timed at compile time, or
/// a fixed function of the shape (tests; deterministic).
#[derive(Clone, Copy, Debug, Default)]
pub enum Timing {
    /// Time `readi_runtime::kernels::conv::conv2d` on the shape: 5 runs after one warm-up,
    /// the median, on one thread.
    #[default]
    Measure,
    /// Milliseconds as this function says; a layer's switch (merge and pack) as long as
    /// one run of its kernel at the algorithm.
    Fixed(fn(&Conv2dShape, ConvAlgo) -> f64),
    /// Kernels as the first function says, a switch as the second (shape, algorithm,
    /// LoRA rank, 0 for a tuned conv).
    FixedSwitch(fn(&Conv2dShape, ConvAlgo) -> f64, fn(&Conv2dShape, ConvAlgo, usize) -> f64),
}

/// `--switch-budget` when not given: at most 1 ms of re-merge work per switch (issue 11's
/// p99 target for a switch) and at most [`DEFAULT_SWITCH_SHARE`] of the base model's conv
/// time.
pub const DEFAULT_SWITCH_BUDGET_MS: f64 = 1.0;

/// The share of a run the default switch budget gives a switch's re-merge work. The first
/// run after a switch does that work, and should stay within 1.02x a steady run: on
/// ResNet-18 (about 17 ms) one layer3 conv's 0.8 ms re-merge made that run 1.09x.
pub const DEFAULT_SWITCH_SHARE: f64 = 0.02;

/// The decisions, and what they cost, per layer and in total.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Strategy {
    /// Every layer with a choice, in graph order.
    pub layers: Vec<LayerChoice>,
    /// The base plan's bytes (the base model's weights as the plan stores them).
    pub base_bytes: u64,
    /// Per variant, the bytes of the tensors no choice changes (epilogues, heads, adapters).
    pub fixed_bytes: Vec<u64>,
    /// The variants' keys, in table order.
    pub keys: Vec<String>,
    /// `--memory-budget`, percent of `base_bytes`.
    pub budget_pct: Option<f64>,
    /// The smallest achievable percentage, when the budget cannot be met.
    pub unmet: Option<f64>,
    /// The base model's conv time (every conv at its algorithm), when timed.
    pub base_ms: Option<f64>,
    /// `--switch-budget`, ms.
    pub switch_budget_ms: f64,
    /// With [`Strategy::unmet`]: the latency the smallest assignment would have added.
    pub unmet_added_ms: Option<f64>,
    /// The weights whose variant values are stored at half precision (`--variant-f16`);
    /// `fixed_bytes` counts them at their stored (half) size.
    pub half: Vec<HalfChoice>,
}

/// A weight whose variant values the plan stores as f16.
#[derive(Clone, Debug, PartialEq)]
pub struct HalfChoice {
    /// The layer's path.
    pub path: String,
    /// The parameter (`fc.weight`): every stored tensor derived from it alone is f16.
    pub param: String,
    /// Per variant, its bytes at f32 (0 where the variant does not own it); stored, half.
    pub bytes: Vec<u64>,
}

/// One layer's decision.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerChoice {
    pub path: String,
    /// For a LoRA layer: merge or branch.
    pub lora: Option<LoraMode>,
    /// For a conv: its algorithm (for a variant-owned conv, the one its variants store).
    pub algo: Option<ConvAlgo>,
    /// The bytes each variant stores for the layer under the decision.
    pub bytes: Vec<u64>,
    /// The predicted latency of the layer (conv and branch), when timed.
    pub predicted_ms: Option<f64>,
    /// The latency added over the base model's layer (its default algorithm, no branch),
    /// when timed.
    pub added_ms: Option<f64>,
    /// The chosen kernels timed again after the choice (`--explain`).
    pub measured_ms: Option<f64>,
    /// Merged on switch (a LoRA layer's `lora` is then `Branch`: its `A` and `B` are
    /// fused into the layer, which the runtime merges into its working copy).
    pub switch: bool,
    /// Merged on switch: the re-merge time per switch, ms, when timed.
    pub switch_ms: Option<f64>,
    /// Merged on switch: the bytes of its working copy (once per session).
    pub working: u64,
}

impl Strategy {
    /// The decision for a LoRA layer (by the adapted layer's path).
    pub fn lora_of(&self, path: &str) -> Option<LoraMode> {
        self.layers.iter().find(|l| l.path == path).and_then(|l| l.lora)
    }
    /// The algorithm chosen for a conv (by path).
    pub fn algo_of(&self, path: &str) -> Option<ConvAlgo> {
        self.layers.iter().find(|l| l.path == path).and_then(|l| l.algo)
    }
    /// Whether the layer at `path` is merged on switch.
    pub fn switch_of(&self, path: &str) -> bool {
        self.layers.iter().any(|l| l.path == path && l.switch)
    }
    /// The re-merge work of a switch, ms: the layers merged on switch, summed.
    pub fn switch_ms(&self) -> f64 {
        self.layers.iter().filter_map(|l| l.switch_ms).fold(0.0, |a, b| a + b)
    }
    /// The working copies of the layers merged on switch, bytes (once per session).
    pub fn working_bytes(&self) -> u64 {
        self.layers.iter().map(|l| l.working).sum()
    }
    /// Per variant, the bytes it stores: the fixed part and every layer's.
    pub fn variant_bytes(&self) -> Vec<u64> {
        (0..self.fixed_bytes.len())
            .map(|v| self.fixed_bytes[v] + self.layers.iter().map(|l| l.bytes[v]).sum::<u64>())
            .collect()
    }
    /// The largest variant's bytes as a percentage of the base's.
    pub fn max_pct(&self) -> f64 {
        pct(self.variant_bytes().into_iter().max().unwrap_or(0), self.base_bytes)
    }
}

fn pct(bytes: u64, base: u64) -> f64 {
    if base == 0 { 0.0 } else { bytes as f64 * 100.0 / base as f64 }
}

/// The LoRA mode of the layer at `path`: the strategy's decision, else the global flag
/// (`auto` without a decision: merge).
pub fn lora_mode(module: &Module, inputs: &BackendInputs<'_>, path: &str) -> LoraMode {
    match module.strategy.as_ref().and_then(|s| s.lora_of(path)) {
        Some(m) => m,
        None if inputs.opts.lora == LoraMode::Branch => LoraMode::Branch,
        None => LoraMode::Merge,
    }
}

pub fn run(module: &Module, inputs: &BackendInputs<'_>, warnings: &mut Diagnostics) -> Result<Output, Diagnostics> {
    if module.strategy.is_some() {
        return Ok(Output::Patches(Vec::new()));
    }
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let opts = inputs.opts;
    let forced = match opts.lora {
        LoraMode::Auto => None,
        m => Some(m),
    };
    let mut timer = Timer::new(opts.timing);
    let budgets = Budgets { memory_pct: opts.memory_budget, switch_ms: opts.switch_budget, half: opts.variant_f16 };
    let s = choose(module, table, forced, budgets, opts.explain, &mut timer);
    let Some(s) = s else { return Ok(Output::Patches(Vec::new())) };
    if let Some(least) = s.unmet {
        warnings.push(
            Diagnostic::warning(
                Code::Limit,
                format!(
                    "the memory budget of {:.2}% per variant cannot be met: the smallest achievable is {least:.2}% of \
                     the base's {} (+{:.3} ms); kept the fastest assignment instead, {:.2}% per variant with no \
                     latency added",
                    s.budget_pct.unwrap_or(0.0),
                    crate::print::bytes(s.base_bytes),
                    s.unmet_added_ms.unwrap_or(0.0),
                    s.max_pct()
                ),
            )
            .with_primary(module.graph.scopes[0].span, "in this model")
            .with_note(
                "the smallest: every LoRA layer branched and every variant-owned conv at im2col; the rest is \
                 BatchNorms and heads. Latency paid for a budget missed anyway would buy nothing: the layers merged \
                 on switch (within --switch-budget) are the savings kept; a budget at or above the smallest gets it",
            ),
        );
    }
    Ok(Output::Strategy(Box::new(s)))
}

/// The budgets the choice is under.
#[derive(Clone, Copy, Debug)]
pub struct Budgets {
    /// `--memory-budget`, percent of the base's bytes per variant.
    pub memory_pct: Option<f64>,
    /// `--switch-budget`, ms of re-merge work per switch; `None`: the default
    /// ([`DEFAULT_SWITCH_BUDGET_MS`], [`DEFAULT_SWITCH_SHARE`]).
    pub switch_ms: Option<f64>,
    /// `--variant-f16`: the weights no choice changes may be stored at half precision.
    pub half: bool,
}

/// Caches kernel timings per (algorithm, shape) within one compile.
pub struct Timer {
    pub timing: Timing,
    pub cache: HashMap<(ConvAlgo, [usize; 16]), f64>,
    /// The fused kernel with a LoRA branch, by algorithm, shape and rank.
    pub lora_cache: HashMap<(ConvAlgo, [usize; 16], usize), f64>,
    /// A layer's merge and pack at a switch, by algorithm, shape and rank.
    pub switch_cache: HashMap<(ConvAlgo, [usize; 16], usize), f64>,
}

/// A shape as a cache key.
fn key(s: &Conv2dShape) -> [usize; 16] {
    [
        s.n, s.cin, s.h, s.w, s.cout, s.kh, s.kw, s.stride_h, s.stride_w, s.pad_h, s.pad_w, s.dil_h, s.dil_w, s.groups,
        s.oh, s.ow,
    ]
}

impl Timer {
    pub fn new(timing: Timing) -> Timer {
        Timer { timing, cache: HashMap::new(), lora_cache: HashMap::new(), switch_cache: HashMap::new() }
    }

    /// The time a switch takes to merge and pack a layer merged on switch, in ms
    /// (cached): `switch_pack` of the raw weight with a LoRA update of `rank` (0: a
    /// tuned conv's raw weight alone) into the working copy packed for `algo`.
    pub fn switch_ms(&mut self, s: &Conv2dShape, algo: ConvAlgo, rank: usize) -> f64 {
        if let Some(&t) = self.switch_cache.get(&(algo, key(s), rank)) {
            return t;
        }
        let t = match self.timing {
            Timing::Fixed(f) => f(s, algo),
            Timing::FixedSwitch(_, f) => f(s, algo, rank),
            Timing::Measure => time_switch(s, algo, rank),
        };
        self.switch_cache.insert((algo, key(s), rank), t);
        t
    }

    /// The kernel's latency on the shape, in ms (cached).
    pub fn ms(&mut self, s: &Conv2dShape, algo: ConvAlgo) -> f64 {
        if let Some(&t) = self.cache.get(&(algo, key(s))) {
            return t;
        }
        let t = self.fresh(s, algo);
        self.cache.insert((algo, key(s)), t);
        t
    }

    /// A new timing, not the cache's.
    pub fn fresh(&self, s: &Conv2dShape, algo: ConvAlgo) -> f64 {
        match self.timing {
            Timing::Fixed(f) | Timing::FixedSwitch(f, _) => f(s, algo),
            Timing::Measure => time_conv(s, algo, 0),
        }
    }

    /// What a LoRA branch of `rank` adds to the conv kernel on `s` when `fuse_lora`
    /// computes it inside the kernel, in ms: the fused kernel's time less the plain
    /// kernel's (never below 0).
    pub fn fused_branch_ms(&mut self, s: &Conv2dShape, algo: ConvAlgo, rank: usize) -> f64 {
        let plain = self.ms(s, algo);
        let fused = match self.lora_cache.get(&(algo, key(s), rank)) {
            Some(&t) => t,
            None => {
                let t = time_conv(s, algo, rank);
                self.lora_cache.insert((algo, key(s), rank), t);
                t
            }
        };
        (fused - plain).max(0.0)
    }
}

/// The runtime's conv kernel on `s` at batch 1, one thread, with a fused LoRA branch of
/// `rank` (0: none): the median of 5 runs after a warm-up, in ms.
fn time_conv(s: &Conv2dShape, algo: ConvAlgo, rank: usize) -> f64 {
    let w: Vec<f32> = (0..s.cout * s.k()).map(|i| ((i % 7) as f32 - 3.0) * 0.01).collect();
    let mut packed = vec![0.0f32; conv::packed_weight_len(s, algo)];
    conv::pack_weight(s, algo, &w, &mut packed);
    let a: Vec<f32> = (0..rank * s.k()).map(|i| ((i % 3) as f32 - 1.0) * 0.01).collect();
    let mut a_packed = vec![0.0f32; if rank > 0 { conv::lora_a_len(s, algo, rank) } else { 0 }];
    if rank > 0 {
        conv::pack_lora_a(s, algo, rank, &a, &mut a_packed);
    }
    let b: Vec<f32> = (0..s.cout * rank).map(|i| ((i % 5) as f32 - 2.0) * 0.01).collect();
    let lora = (rank > 0).then(|| conv::Lora { a: &a_packed, b: &b, rank });
    let x: Vec<f32> = (0..s.n * s.cin * s.h * s.w).map(|i| ((i % 5) as f32 - 2.0) * 0.1).collect();
    let mut out = vec![0.0f32; s.n * s.cout * s.oh * s.ow];
    let mut scratch = vec![0.0f32; conv::lora_scratch_len(s, algo, rank, 1)];
    let shift = vec![0.0f32; s.cout];
    let ep = Epilogue { scale: None, shift: Some(&shift), act: Some(readi_plan::ops::Activation::Relu) };
    let once = |out: &mut [f32], scratch: &mut [f32]| {
        conv::conv2d_lora(s, algo, &packed, lora.as_ref(), &ep, &x, out, scratch, 1)
    };
    once(&mut out, &mut scratch);
    let mut times: Vec<f64> = (0..5)
        .map(|_| {
            let t = Instant::now();
            once(&mut out, &mut scratch);
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[2]
}

/// The runtime's merge and pack of a layer merged on switch (`switch_pack`), on `s` at
/// `algo` with a LoRA update of `rank` (0: none): the median of 5 runs after a warm-up,
/// in ms, on one thread (a switch runs on the running thread).
fn time_switch(s: &Conv2dShape, algo: ConvAlgo, rank: usize) -> f64 {
    let w: Vec<f32> = (0..s.cout * s.k()).map(|i| ((i % 7) as f32 - 3.0) * 0.01).collect();
    let a: Vec<f32> = (0..rank * s.k()).map(|i| ((i % 3) as f32 - 1.0) * 0.01).collect();
    let b: Vec<f32> = (0..s.cout * rank).map(|i| ((i % 5) as f32 - 2.0) * 0.01).collect();
    let lora = (rank > 0).then(|| conv::Lora { a: &a, b: &b, rank });
    let mut tmp = vec![0.0f32; merge::switch_tmp_len(s, algo, rank > 0)];
    let mut out = vec![0.0f32; conv::packed_weight_len(s, algo)];
    merge::switch_pack(s, algo, &w, lora.as_ref(), &mut tmp, &mut out);
    let mut times: Vec<f64> = (0..5)
        .map(|_| {
            let t = Instant::now();
            merge::switch_pack(s, algo, &w, lora.as_ref(), &mut tmp, &mut out);
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[2]
}

/// A conv's shape at batch 1, its default algorithm.
fn conv_shape(g: &Graph, id: NodeId) -> Option<(Conv2dShape, ConvAlgo)> {
    let Op::Conv2d(c) = &g.node(id).op else { return None };
    let (h, w) = spatial(g, id);
    let s = c.conv.shape(1, h, w);
    Some((s, c.algo.unwrap_or_else(|| conv::choose(&s))))
}

/// The shape a linear layer runs at, as the 1x1 conv over its rows that computes the same
/// GEMM (rows = the input's elements at batch 1 over its features). Every axis counts at
/// batch 1, symbols set to 1: a windowed attention's `[N * windows, area, C]` has
/// `windows * area` rows, not `area`.
fn linear_shape(g: &Graph, id: NodeId, fin: usize, fout: usize) -> Conv2dShape {
    let rows = g
        .inputs(id)
        .first()
        .and_then(|v| g.value_type(*v))
        .map(|t| t.shape.iter().map(|d| d.coef().max(1)).product::<i64>().max(1) as usize)
        .map_or(1, |n| (n / fin.max(1)).max(1));
    Conv2dShape { h: rows, oh: rows, ..Conv2dShape::square(1, fin, 1, fout, 1, 1, 0, 1) }
}

/// The kernels a node runs as, for timing: its shape and algorithm.
fn kernel(g: &Graph, id: NodeId) -> Option<(Conv2dShape, ConvAlgo)> {
    match &g.node(id).op {
        Op::Conv2d(_) => conv_shape(g, id),
        Op::Linear(l) => {
            let (fin, fout) = (l.linear.in_features.max(0) as usize, l.linear.out_features.max(0) as usize);
            Some((linear_shape(g, id, fin, fout), ConvAlgo::Gemm1x1))
        }
        _ => None,
    }
}

/// A LoRA branch's cost, in ms: on a conv, what it adds to the layer's kernel at
/// `algo`, which computes it (`fuse_lora`, [`Timer::fused_branch_ms`]); on a linear, its
/// `A` and `B` GEMMs. The one place the branch is priced.
pub fn branch_ms(g: &Graph, layer: NodeId, algo: Option<ConvAlgo>, a: NodeId, b: NodeId, timer: &mut Timer) -> f64 {
    // Fixed costs (tests) price the branch as its two layers at their own algorithms: the
    // multiply-adds the fused kernel adds.
    if let (Timing::Measure, Some((s, default)), Some((sa, _))) = (timer.timing, conv_shape(g, layer), conv_shape(g, a))
    {
        return timer.fused_branch_ms(&s, algo.unwrap_or(default), sa.cout);
    }
    [a, b].into_iter().filter_map(|n| kernel(g, n)).map(|(s, algo)| timer.ms(&s, algo)).sum()
}

/// One option of a layer.
#[derive(Clone, Debug)]
struct Opt {
    lora: Option<LoraMode>,
    algo: Option<ConvAlgo>,
    bytes: Vec<u64>,
    /// Merged on switch (at `algo`, the default).
    switch: bool,
}

impl Opt {
    fn total(&self) -> u64 {
        self.bytes.iter().sum()
    }
    fn max(&self) -> u64 {
        self.bytes.iter().copied().max().unwrap_or(0)
    }
}

/// A layer with a choice.
struct Item {
    path: String,
    node: NodeId,
    /// The LoRA branch's `A` and `B`.
    branch: Option<(NodeId, NodeId)>,
    /// The LoRA rank merged at a switch (0: a tuned conv).
    rank: usize,
    opts: Vec<Opt>,
    /// The index of the fastest option (merge, the default algorithm).
    start: usize,
}

/// Whether tensor `name` has a value of its own (other bits than the base's) in variant `v`
/// (1-based).
fn own(table: &TensorTable, name: &str, v: usize) -> bool {
    table
        .get(name)
        .is_some_and(|t| t.variants.get(v - 1).is_some_and(|d| d.as_ref().is_some_and(|d| !same_bits(d, &t.base))))
}

/// Whether a tensor is zero everywhere under variant `v` (0: the base).
fn zero(table: &TensorTable, name: &str, v: usize) -> bool {
    table.value(name, v).is_none_or(|d| d.iter().all(|x| *x == 0.0))
}

fn param(g: &Graph, id: NodeId, slot: &str) -> Option<String> {
    let node = g.node(id);
    node.params.iter().find(|s| s.name == slot).map(|s| node.param_name(s))
}

fn numel(table: &TensorTable, name: &str) -> u64 {
    table.get(name).map_or(0, |t| t.numel() as u64)
}

/// The decisions for a module, or `None` when nothing has a choice.
pub fn choose(
    module: &Module,
    table: &TensorTable,
    forced: Option<LoraMode>,
    budgets: Budgets,
    explain: bool,
    timer: &mut Timer,
) -> Option<Strategy> {
    let g = &module.graph;
    let nv = table.variant_count();
    if nv == 0 {
        return None;
    }
    let variants = 1..=nv;
    let injections: &[Injection] = module.adapt.as_ref().map_or(&[], |p| &p.injections);
    // LoRA layers, by their adapted layer.
    let lora: HashMap<NodeId, (NodeId, NodeId)> = injections
        .iter()
        .filter_map(|i| match *i {
            Injection::Lora { base, a, b, .. } => Some((base, (a, b))),
            Injection::Adapter { .. } => None,
        })
        .collect();
    // The LoRA layers a session can merge on switch: convs whose branch `fuse_lora`
    // computes in the layer (so the plan holds `A` and `B` beside the layer's weight).
    let fusable: std::collections::HashSet<NodeId> = injections
        .iter()
        .filter_map(|i| match *i {
            Injection::Lora { base, .. } if matches!(g.node(base).op, Op::Conv2d(_)) => {
                fuse_lora::fusable(g, i).map(|_| base)
            }
            _ => None,
        })
        .collect();
    let branch_nodes: std::collections::HashSet<NodeId> =
        injections.iter().filter(|i| matches!(i, Injection::Lora { .. })).flat_map(|i| i.nodes()).collect();
    // The base plan (no variants) has no injections at all: `drop_inactive` drops them.
    let injected: std::collections::HashSet<NodeId> = injections.iter().flat_map(|i| i.nodes()).collect();

    let mut order: Vec<NodeId> = g.topo_order().unwrap_or_else(|| g.node_ids().collect());
    order.retain(|n| g.contains(*n));
    let mut items: Vec<Item> = Vec::new();
    let mut halves: Vec<HalfChoice> = Vec::new();
    let mut fixed = vec![0u64; nv];
    let mut base_bytes = 0u64;
    for &id in &order {
        let node = g.node(id);
        let in_branch = branch_nodes.contains(&id);
        // The base plan's bytes: every kernel's stored tensors, LoRA branches and adapters
        // aside.
        if !injected.contains(&id) {
            base_bytes += base_node_bytes(g, table, id);
        }
        if in_branch {
            continue;
        }
        let weight = param(g, id, "weight");
        let branch = lora.get(&id).copied();
        let owned_w = |v: usize| weight.as_deref().is_some_and(|w| own(table, w, v));
        let conv = conv_shape(g, id);
        let packed_options: Vec<ConvAlgo> = match conv {
            Some((s, default)) => {
                let mut a = vec![default];
                for c in [ConvAlgo::Winograd4, ConvAlgo::Winograd2, ConvAlgo::Im2col] {
                    if c.supports(&s) && !a.contains(&c) && c.packed_len(&s) < default.packed_len(&s) {
                        a.push(c);
                    }
                }
                a
            }
            None => Vec::new(),
        };
        let owned_anywhere = variants.clone().any(owned_w);
        let has_choice = branch.is_some() || (owned_anywhere && packed_options.len() > 1);
        // The tensors of the node no choice changes.
        for v in variants.clone() {
            fixed[v - 1] += fixed_node_bytes(g, table, id, v, has_choice);
        }
        if !has_choice {
            // A weight a variant owns, to store at half precision if allowed.
            let elems = match (&node.op, conv) {
                (Op::Linear(l), _) => pack_weights::linear_weight_len(g, id, l).map(|n| n as u64),
                (Op::Conv2d(_), Some((s, a))) => Some(a.packed_len(&s) as u64),
                _ => None,
            };
            if let (true, Some(n), Some(w)) = (budgets.half && owned_anywhere, elems, weight.as_deref()) {
                let bytes = variants.clone().map(|v| if owned_w(v) { n * 4 } else { 0 }).collect();
                halves.push(HalfChoice { path: node.path.clone(), param: w.to_string(), bytes });
            }
            continue;
        }
        let w_elems = |algo: Option<ConvAlgo>| match (conv, algo) {
            (Some((s, _)), Some(a)) => a.packed_len(&s) as u64,
            _ => node.params.iter().find(|s| s.name == "weight").map_or(0, |s| stored_numel(g, table, id, s)),
        };
        // The branch's `A` and `B` a variant owns, as the plan stores them: raw (packing
        // `A` for the GEMM paths keeps its layout; the runtime packs a Winograd `A`).
        let ab_elems = |v: usize| -> u64 {
            branch.map_or(0, |(a, bb)| {
                [a, bb]
                    .into_iter()
                    .filter_map(|n| param(g, n, "weight"))
                    .filter(|w| own(table, w, v))
                    .map(|w| numel(table, &w))
                    .sum()
            })
        };
        let mut opts = Vec::new();
        let strategies: Vec<Option<LoraMode>> = match (branch, forced) {
            (None, _) => vec![None],
            (Some(_), Some(m)) => vec![Some(m)],
            (Some(_), None) => vec![Some(LoraMode::Merge), Some(LoraMode::Branch)],
        };
        for lm in strategies {
            let algos: Vec<Option<ConvAlgo>> =
                if packed_options.is_empty() { vec![None] } else { packed_options.iter().map(|&a| Some(a)).collect() };
            for algo in algos {
                let bytes: Vec<u64> = variants
                    .clone()
                    .map(|v| {
                        let mut b = 0u64;
                        let merged_delta = branch.is_some_and(|(a, bb)| {
                            let (wa, wb) = (param(g, a, "weight"), param(g, bb, "weight"));
                            lm == Some(LoraMode::Merge)
                                && wa.is_some_and(|n| !zero(table, &n, v))
                                && wb.is_some_and(|n| !zero(table, &n, v))
                        });
                        if owned_w(v) || merged_delta {
                            b += w_elems(algo);
                        }
                        if lm == Some(LoraMode::Branch) {
                            b += ab_elems(v);
                        }
                        b * 4
                    })
                    .collect();
                // The algorithm matters only where the weight is the variants' own.
                let owned = owned_anywhere || lm == Some(LoraMode::Merge);
                if !owned && algo != packed_options.first().copied() {
                    continue;
                }
                opts.push(Opt { lora: lm, algo, bytes, switch: false });
            }
        }
        // Merge on switch, at the default algorithm: a conv whose weight the variants own
        // (stored raw), or a LoRA layer `fuse_lora` fuses (its `A` and `B` stored raw);
        // not with `--lora merge|branch` on a LoRA layer.
        let switchable = match (branch, conv) {
            (_, None) => false,
            (Some(_), Some(_)) => forced.is_none() && fusable.contains(&id),
            (None, Some(_)) => owned_anywhere,
        };
        if switchable {
            let bytes =
                variants.clone().map(|v| (if owned_w(v) { w_elems(None) } else { 0 } + ab_elems(v)) * 4).collect();
            let lm = branch.map(|_| LoraMode::Branch);
            opts.push(Opt { lora: lm, algo: packed_options.first().copied(), bytes, switch: true });
        }
        let rank = branch.and_then(|(a, _)| conv_shape(g, a)).map_or(0, |(sa, _)| sa.cout);
        items.push(Item { path: node.path.clone(), node: id, branch, rank, opts, start: 0 });
    }
    if items.is_empty() && halves.is_empty() {
        return None;
    }

    let budget = budgets.memory_pct.map(|p| (p / 100.0 * base_bytes as f64).floor() as u64);
    let mut c = Costs { g, items: &items, fixed, switch_budget: budgets.switch_ms.unwrap_or(DEFAULT_SWITCH_BUDGET_MS) };
    let mut at: Vec<usize> = items.iter().map(|i| i.start).collect();
    // Largest first; which of them are stored f16.
    halves.sort_by_key(|h| std::cmp::Reverse(h.bytes.iter().copied().max().unwrap_or(0)));
    let mut half = vec![budget.is_none(); halves.len()];
    if budget.is_none() {
        for h in &halves {
            c.halve(h, true);
        }
    }
    let mut timed = explain;
    let (mut unmet, mut unmet_added_ms) = (None, None);
    if let Some(budget) = budget
        && c.total(&at) > budget
    {
        timed = true;
        if budgets.switch_ms.is_none() {
            c.switch_budget = c.switch_budget.min(DEFAULT_SWITCH_SHARE * conv_ms(g, &order, &branch_nodes, timer));
        }
        if !halves.is_empty() {
            // The moves that cost nothing, then precision, before any latency.
            c.shrink(&mut at, budget, true, timer);
            for (k, h) in halves.iter().enumerate() {
                if c.total(&at) <= budget {
                    break;
                }
                c.halve(h, true);
                half[k] = true;
            }
        }
        c.shrink(&mut at, budget, false, timer);
        c.give_back(&mut at, budget, timer);
        // Precision back where the budget allows, the smallest weight first.
        for (k, h) in halves.iter().enumerate().rev() {
            if !half[k] {
                continue;
            }
            c.halve(h, false);
            if c.total(&at) <= budget {
                half[k] = false;
            } else {
                c.halve(h, true);
            }
        }
        if c.total(&at) > budget {
            // Unreachable: the smallest assignment (switch aside: a branch or im2col
            // stores as little), and what it would cost; then keep only the free savings.
            let least: Vec<usize> = items
                .iter()
                .map(|it| {
                    (0..it.opts.len())
                        .filter(|&k| !it.opts[k].switch)
                        .min_by_key(|&k| (it.opts[k].max(), it.opts[k].total(), k))
                        .unwrap_or(0)
                })
                .collect();
            unmet = Some(pct(c.total(&least), base_bytes));
            let added: f64 = (0..items.len()).map(|i| c.ms(i, least[i], timer) - c.ms(i, items[i].start, timer)).sum();
            unmet_added_ms = Some(added.max(0.0));
            at = items.iter().map(|i| i.start).collect();
            c.shrink(&mut at, budget, true, timer);
        }
    }
    let mut layers = Vec::new();
    for (i, it) in items.iter().enumerate() {
        let o = &it.opts[at[i]];
        let (predicted, added, measured) = if timed {
            let p = c.ms(i, at[i], timer);
            // Over the base model's layer: its kernel at the default algorithm, no branch.
            let base = kernel(g, it.node).map_or(0.0, |(s, a)| timer.ms(&s, a));
            let m = explain.then(|| option_ms_fresh(g, it, o, timer));
            (Some(p), Some(p - base), m)
        } else {
            (None, None, None)
        };
        let algo = o.algo.or_else(|| conv_shape(g, it.node).map(|c| c.1));
        let working = match (o.switch, conv_shape(g, it.node), algo) {
            (true, Some((s, _)), Some(a)) => a.packed_len(&s) as u64 * 4,
            _ => 0,
        };
        layers.push(LayerChoice {
            path: it.path.clone(),
            lora: o.lora,
            algo,
            bytes: o.bytes.clone(),
            predicted_ms: predicted,
            added_ms: added,
            measured_ms: measured,
            switch: o.switch,
            switch_ms: o.switch.then(|| c.switch(i, at[i], timer)),
            working,
        });
    }
    let base_ms = timed.then(|| conv_ms(g, &order, &branch_nodes, timer));
    let switch_budget_ms = c.switch_budget;
    Some(Strategy {
        layers,
        base_bytes,
        fixed_bytes: c.fixed.clone(),
        keys: table.variants.iter().map(|v| v.key.to_string()).collect(),
        budget_pct: budgets.memory_pct,
        unmet,
        base_ms,
        switch_budget_ms,
        unmet_added_ms,
        half: halves.into_iter().zip(half).filter_map(|(h, on)| on.then_some(h)).collect(),
    })
}

/// The base model's conv time: every conv of `order` but the LoRA branches' at its
/// algorithm, ms.
fn conv_ms(g: &Graph, order: &[NodeId], branch_nodes: &std::collections::HashSet<NodeId>, timer: &mut Timer) -> f64 {
    order
        .iter()
        .filter(|n| !branch_nodes.contains(n))
        .filter_map(|&n| conv_shape(g, n))
        .map(|(s, a)| timer.ms(&s, a))
        .sum()
}

/// The layers' options and what an assignment (an option index per layer) costs.
struct Costs<'a> {
    g: &'a Graph,
    items: &'a [Item],
    /// Per variant, the bytes no layer choice changes (the weights stored f16 at half).
    fixed: Vec<u64>,
    switch_budget: f64,
}

impl Costs<'_> {
    /// Counts the weight `h` at half precision (`on`) or back at f32.
    fn halve(&mut self, h: &HalfChoice, on: bool) {
        for (f, b) in self.fixed.iter_mut().zip(&h.bytes) {
            *f = if on { *f - b / 2 } else { *f + b / 2 };
        }
    }

    /// The largest variant's bytes.
    fn total(&self, at: &[usize]) -> u64 {
        (0..self.fixed.len())
            .map(|v| self.fixed[v] + self.items.iter().zip(at).map(|(it, &k)| it.opts[k].bytes[v]).sum::<u64>())
            .max()
            .unwrap_or(0)
    }
    /// Option `k` of layer `i`: its latency.
    fn ms(&self, i: usize, k: usize, timer: &mut Timer) -> f64 {
        option_ms(self.g, &self.items[i], &self.items[i].opts[k], timer)
    }
    /// Option `k` of layer `i`: its switch time (0 unless merged on switch).
    fn switch(&self, i: usize, k: usize, timer: &mut Timer) -> f64 {
        let it = &self.items[i];
        match (it.opts[k].switch, conv_shape(self.g, it.node), it.opts[k].algo) {
            (true, Some((s, _)), Some(a)) => timer.switch_ms(&s, a, it.rank),
            _ => 0.0,
        }
    }
    fn switch_total(&self, at: &[usize], timer: &mut Timer) -> f64 {
        (0..at.len()).map(|i| self.switch(i, at[i], timer)).sum()
    }

    /// Moves layers to cheaper options until the largest variant fits `budget` or no
    /// move is left (`free_only`: only moves that add no latency): per layer its next
    /// cheaper option, the fastest that stores fewer bytes within the switch budget;
    /// of those, the free ones first by bytes saved per switch ms, then the others by
    /// bytes saved per ms added.
    fn shrink(&self, at: &mut [usize], budget: u64, free_only: bool, timer: &mut Timer) {
        while self.total(at) > budget {
            let used = self.switch_total(at, timer);
            let mut best: Option<(bool, f64, usize, usize)> = None;
            for (i, &here) in at.iter().enumerate() {
                let cur = &self.items[i].opts[here];
                let (cur_total, cur_ms, cur_sw) = (cur.total(), self.ms(i, here, timer), self.switch(i, here, timer));
                let mut next: Option<(f64, u64, usize)> = None;
                for k in 0..self.items[i].opts.len() {
                    let o = &self.items[i].opts[k];
                    if o.total() >= cur_total || used - cur_sw + self.switch(i, k, timer) > self.switch_budget + 1e-12 {
                        continue;
                    }
                    let ms = self.ms(i, k, timer);
                    if next.is_none_or(|(nms, nb, _)| ms < nms || (ms == nms && o.total() > nb)) {
                        next = Some((ms, o.total(), k));
                    }
                }
                let Some((ms, bytes, k)) = next else { continue };
                let free = ms <= cur_ms;
                if free_only && !free {
                    continue;
                }
                let saved = (cur_total - bytes) as f64;
                let cost = if free { self.switch(i, k, timer) - cur_sw } else { ms - cur_ms };
                let ratio = saved / cost.max(1e-9);
                if best.is_none_or(|(f, r, _, _)| (free, ratio) > (f, r)) {
                    best = Some((free, ratio, i, k));
                }
            }
            let Some((_, _, i, k)) = best else { break };
            at[i] = k;
        }
    }

    /// The greedy moves may overshoot (one large layer saves more than was missing):
    /// gives back latency while both budgets hold, the largest gain first.
    fn give_back(&self, at: &mut [usize], budget: u64, timer: &mut Timer) {
        loop {
            let mut best: Option<(f64, usize, usize)> = None;
            for i in 0..self.items.len() {
                let cur_ms = self.ms(i, at[i], timer);
                for k in 0..self.items[i].opts.len() {
                    let ms = self.ms(i, k, timer);
                    if ms >= cur_ms || best.is_some_and(|(g, _, _)| cur_ms - ms <= g) {
                        continue;
                    }
                    let mut trial = at.to_vec();
                    trial[i] = k;
                    if self.total(&trial) <= budget && self.switch_total(&trial, timer) <= self.switch_budget + 1e-12 {
                        best = Some((cur_ms - ms, i, k));
                    }
                }
            }
            let Some((_, i, k)) = best else { break };
            at[i] = k;
        }
    }
}

/// An option's latency: the layer's kernel at the option's algorithm, and its branch
/// (none when merged on switch: the layer runs its working copy).
fn option_ms(g: &Graph, it: &Item, o: &Opt, timer: &mut Timer) -> f64 {
    let own = match (kernel(g, it.node), o.algo) {
        (Some((s, _)), Some(a)) => timer.ms(&s, a),
        (Some((s, a)), None) => timer.ms(&s, a),
        _ => 0.0,
    };
    let branch = match (it.branch, o.lora, o.switch) {
        (Some((a, b)), Some(LoraMode::Branch), false) => branch_ms(g, it.node, o.algo, a, b, timer),
        _ => 0.0,
    };
    own + branch
}

/// [`option_ms`] timed again, not from the cache.
fn option_ms_fresh(g: &Graph, it: &Item, o: &Opt, timer: &Timer) -> f64 {
    let mut fresh = Timer::new(timer.timing);
    option_ms(g, it, o, &mut fresh)
}

/// The bytes a node stores in the base plan: a conv's weight packed for its default
/// algorithm, a folded BatchNorm's scale and shift (and its record's `weight` and `bias`,
/// which `readi adapt-bn` reads), a linear's weight and bias, any other node's parameters.
fn base_node_bytes(g: &Graph, table: &TensorTable, id: NodeId) -> u64 {
    let node = g.node(id);
    let elems: u64 = match &node.op {
        Op::Conv2d(c) => {
            let w = conv_shape(g, id).map_or(0, |(s, a)| a.packed_len(&s) as u64);
            w + if c.bias { c.conv.out_channels.max(0) as u64 } else { 0 }
        }
        Op::BatchNorm(b) => 4 * b.channels.max(0) as u64,
        _ => node.params.iter().map(|s| stored_numel(g, table, id, s)).sum(),
    };
    elems * 4
}

/// The bytes variant `v` stores for a node's tensors that no choice changes: everything
/// but the weight of a layer with a choice. A BatchNorm's folded scale varies with its
/// `weight` and `running_var`, its shift with any of its four; a conv's or linear's bias is
/// its epilogue's shift; a conv's weight is packed for its default algorithm.
fn fixed_node_bytes(g: &Graph, table: &TensorTable, id: NodeId, v: usize, has_choice: bool) -> u64 {
    let node = g.node(id);
    let p = |s: &str| param(g, id, s).is_some_and(|n| own(table, &n, v));
    let elems: u64 = match &node.op {
        Op::BatchNorm(b) => {
            let c = b.channels.max(0) as u64;
            let scale = p("weight") || p("running_var");
            let shift = scale || p("bias") || p("running_mean");
            c * (scale as u64 + shift as u64)
        }
        Op::Conv2d(c) => {
            let w = if !has_choice && p("weight") {
                conv_shape(g, id).map_or(0, |(s, a)| a.packed_len(&s) as u64)
            } else {
                0
            };
            w + if c.bias && p("bias") { c.conv.out_channels.max(0) as u64 } else { 0 }
        }
        _ => node
            .params
            .iter()
            .filter(|s| !(has_choice && s.name == "weight"))
            .filter(|s| own(table, &node.param_name(s), v))
            .map(|s| stored_numel(g, table, id, s))
            .sum(),
    };
    elems * 4
}

/// The floats the plan stores for parameter `slot` of node `id`: a linear's weight as
/// `pack_weights` packs it (panels are padded), any other as it is.
fn stored_numel(g: &Graph, table: &TensorTable, id: NodeId, slot: &crate::ir::ParamSlot) -> u64 {
    let node = g.node(id);
    match &node.op {
        Op::Linear(l) if slot.name == "weight" => {
            pack_weights::linear_weight_len(g, id, l).map_or_else(|| numel(table, &node.param_name(slot)), |n| n as u64)
        }
        _ => numel(table, &node.param_name(slot)),
    }
}

/// The `--explain` table: one row per layer with a choice (its largest variant's bytes;
/// the latency the option predicts, what it adds over the base model's layer, the
/// chosen kernels timed again, and a layer merged on switch's re-merge time), then the
/// totals, the switch's and the working copies' (once per session, not per variant)
/// among them.
pub fn explain(s: &Strategy) -> String {
    use crate::print::bytes;
    let mut out = String::new();
    let ms = |t: Option<f64>| t.map_or("-".to_string(), |t| format!("{t:.3} ms"));
    let plus = |t: Option<f64>| t.map_or("-".to_string(), |t| format!("+{:.3} ms", t.max(0.0)));
    let width = s.layers.iter().map(|l| l.path.len()).max().unwrap_or(5).max(5);
    let _ = writeln!(
        out,
        "{:<width$}  {:<15}  {:<9}  {:>13}  {:>10}  {:>10}  {:>10}  {:>9}",
        "layer", "strategy", "algorithm", "bytes/variant", "predicted", "added", "measured", "switch"
    );
    for l in &s.layers {
        let b = l.bytes.iter().copied().max().unwrap_or(0);
        let strategy = if l.switch { "merge-on-switch" } else { l.lora.map_or("-", LoraMode::name) };
        let _ = writeln!(
            out,
            "{:<width$}  {:<15}  {:<9}  {:>13}  {:>10}  {:>10}  {:>10}  {:>9}",
            l.path,
            strategy,
            l.algo.map_or("-", ConvAlgo::name),
            bytes(b),
            ms(l.predicted_ms),
            plus(l.added_ms),
            ms(l.measured_ms),
            if l.switch { ms(l.switch_ms) } else { "-".to_string() }
        );
    }
    let totals = s.variant_bytes();
    let max = totals.iter().copied().max().unwrap_or(0);
    let budget = s.budget_pct.map_or("no budget".to_string(), |b| format!("budget {b:.2}%"));
    let fixed = s.fixed_bytes.iter().copied().max().unwrap_or(0);
    let _ = writeln!(
        out,
        "bytes per variant: {} = {:.2}% of the base's {} ({budget}); {} of it no choice changes (BatchNorms, heads, \
         adapters)",
        bytes(max),
        s.max_pct(),
        bytes(s.base_bytes),
        bytes(fixed)
    );
    for h in &s.half {
        let b = h.bytes.iter().copied().max().unwrap_or(0);
        let _ = writeln!(out, "  {} stored f16: {} instead of {} per variant", h.param, bytes(b / 2), bytes(b));
    }
    if s.keys.len() > 1 {
        let each: Vec<String> =
            s.keys.iter().zip(&totals).map(|(k, b)| format!("{k} {:.2}%", pct(*b, s.base_bytes))).collect();
        let _ = writeln!(out, "  per variant: {}", each.join(", "));
    }
    if let Some(least) = s.unmet {
        let _ = writeln!(
            out,
            "the budget cannot be met: the smallest achievable is {least:.2}% (+{:.3} ms); kept the fastest assignment",
            s.unmet_added_ms.unwrap_or(0.0)
        );
    }
    let switched = s.layers.iter().filter(|l| l.switch).count();
    let _ = writeln!(
        out,
        "switch: {:.3} ms of re-merge per variant switch ({switched} layers merged on switch; budget {:.3} ms); their \
         working copies {} once per session, not per variant",
        s.switch_ms(),
        s.switch_budget_ms,
        bytes(s.working_bytes())
    );
    match s.base_ms {
        Some(base) => {
            let added: f64 = s.layers.iter().filter_map(|l| l.added_ms).sum();
            let _ = writeln!(
                out,
                "predicted latency overhead: +{added:.3} ms over the base's conv time of {base:.3} ms = {:.2}%",
                if base > 0.0 { added * 100.0 / base } else { 0.0 }
            );
        }
        None => {
            let _ = writeln!(out, "latency not timed (no choice depended on it)");
        }
    }
    out
}

/// The strategy's layers by path, for lookups by name.
pub fn by_path(s: &Strategy) -> BTreeMap<&str, &LayerChoice> {
    s.layers.iter().map(|l| (l.path.as_str(), l)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A windowed attention's projection over `[N * 6, 49, 16]` runs 6 * 49 rows at batch
    /// 1, a token linear over `[N, 49, 16]` 49, a static `[3, 49, 16]` 3 * 49.
    #[test]
    fn a_linear_runs_over_every_row_at_batch_one() {
        let text = "model m {\n  input x: f32[N, 6, 49, 16]\n  input s: f32[3, 49, 16]\n  \
            let w = reshape(x, [-1, 49, 16])\n  win = linear(w, 8)\n  tok = linear(x[:, 0], 8)\n  \
            fixed = linear(s, 8)\n  output a = win\n  output b = tok\n  output c = fixed\n}\n";
        let mut sources = readi_grammar::diag::SourceMap::new();
        let file = sources.add("m.readi", text);
        let out = crate::passes::run(file, text, &crate::passes::Options::default());
        assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
        let g = &out.module.expect("module").graph;
        for (path, rows) in [("win", 6 * 49), ("tok", 49), ("fixed", 3 * 49)] {
            let id = g.node_ids().find(|&n| g.node(n).path == path).expect(path);
            assert_eq!(linear_shape(g, id, 16, 8).h, rows, "{path}");
        }
    }
}
