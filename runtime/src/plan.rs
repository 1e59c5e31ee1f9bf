//! The plan file: what the compiler emits and the runtime maps into memory.
//!
//! A plan is a [safetensors] file. Its tensors are the stored weights (f32, each stored
//! once); its metadata holds three keys:
//!
//! * `readi.format_version`: [`FORMAT_VERSION`], checked first;
//! * `readi.manifest`: the [`Manifest`] as JSON: inputs, outputs, the schedule of steps,
//!   every value's shape, the buffer plan, the stored tensors and the model's parameter
//!   table, and the variant tables;
//! * `readi.checksum`: CRC-32 of the manifest text followed by every tensor's bytes in
//!   manifest order, so a flipped bit anywhere is caught at load.
//!
//! Any safetensors tool can list a plan's tensors. Loading maps the file and borrows the
//! weight bytes in place: nothing proportional to the weights is copied, at load or later.
//! Plans are untrusted input: [`Plan::load`] checks the container, the version, the
//! checksum and every index in the manifest, and reports a [`PlanError`] naming what is
//! wrong; shapes are checked again when a batch size is bound.
//!
//! # Variants
//!
//! A plan holds one base model and any number of *variants*, each a [`VariantTable`]
//! naming the stored tensors it reads instead of the base's. Variant 0 is the base (key
//! [`BASE_VARIANT`]); variant `i + 1` is `manifest.variants[i]`. At construction the plan
//! builds, per variant, a dense map from the tensor index a step names to the tensor it
//! reads ([`VariantTensors`]), so resolving a tensor under a variant is one array lookup
//! and selecting a variant copies nothing.
//!
//! [safetensors]: https://huggingface.co/docs/safetensors

use std::collections::{HashMap, HashSet};
use std::fmt;
use std::ops::Range;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};

use crate::kernels::{Act, BinaryOp};

/// Version of the plan format this runtime reads and writes.
pub const FORMAT_VERSION: u32 = 1;
const KEY_VERSION: &str = "readi.format_version";
const KEY_MANIFEST: &str = "readi.manifest";
const KEY_CHECKSUM: &str = "readi.checksum";

/// The key of variant 0, the base model; no variant table may use it.
pub const BASE_VARIANT: &str = "base";

/// Most entries the variant maps may take together (variants x mapped tensors): 256 MiB.
/// A real plan needs a few thousand; the bound keeps a small crafted manifest from asking
/// for an enormous allocation.
const MAX_MAP_ENTRIES: usize = 1 << 26;

/// A dimension `coef * s1 * s2 ...` over the plan's symbols (the batch size `N`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SymDim {
    pub coef: i64,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub syms: Vec<String>,
}

impl SymDim {
    pub fn known(n: i64) -> SymDim {
        SymDim { coef: n, syms: Vec::new() }
    }
    /// The size under the given symbol values, or `None` if a symbol is unbound or the
    /// result overflows or is negative.
    pub fn eval(&self, bindings: &HashMap<String, usize>) -> Option<usize> {
        let mut v = usize::try_from(self.coef).ok()?;
        for s in &self.syms {
            v = v.checked_mul(*bindings.get(s)?)?;
        }
        Some(v)
    }
}

impl fmt::Display for SymDim {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.syms.is_empty() {
            return write!(f, "{}", self.coef);
        }
        if self.coef != 1 {
            write!(f, "{}*", self.coef)?;
        }
        f.write_str(&self.syms.join("*"))
    }
}

/// Shows a symbolic shape: `[N, 3, 224, 224]`.
pub fn show_shape(shape: &[SymDim]) -> String {
    let parts: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    format!("[{}]", parts.join(", "))
}

/// Everything about a plan except the tensor bytes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    /// The model's name and the parameter values it was compiled with.
    pub model: String,
    pub model_params: Vec<(String, String)>,
    /// Symbolic dimensions, bound from the input shapes at run time.
    pub symbols: Vec<String>,
    pub inputs: Vec<InputSpec>,
    pub outputs: Vec<OutputSpec>,
    /// Every value the schedule reads or writes.
    pub values: Vec<ValueSpec>,
    /// The schedule, in execution order.
    pub steps: Vec<Step>,
    /// Number of activation buffers; a value stored in slot `s` shares buffer `s` with
    /// the values whose lifetimes do not overlap it.
    pub slots: usize,
    /// The stored tensors, in checksum order.
    pub tensors: Vec<TensorSpec>,
    /// The model's parameters as the spec declares them (PyTorch names) and where each
    /// went (a folded BatchNorm lives on in its conv's epilogue).
    pub params: Vec<ParamSpec>,
    /// Per-variant tensor tables; empty in format version 1 plans without variants.
    #[serde(default)]
    pub variants: Vec<VariantTable>,
    /// The spec's conditions (axes, selectors, missing-modality policies, meld rule), for
    /// choosing a variant from the inputs; `None` for specs without a variants section.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub conditions: Option<crate::conditions::Conditions>,
}

impl Manifest {
    /// Every symbol bound to `batch` (a plan's symbols are batch sizes, `N`).
    pub fn batch_bindings(&self, batch: usize) -> HashMap<String, usize> {
        self.symbols.iter().map(|s| (s.clone(), batch)).collect()
    }

    /// Each input's name and shape at batch size `batch`.
    pub fn input_shapes(&self, batch: usize) -> Vec<(&str, Vec<usize>)> {
        let b = self.batch_bindings(batch);
        self.inputs
            .iter()
            .map(|i| (i.name.as_str(), i.shape.iter().map(|d| d.eval(&b).unwrap_or(1)).collect()))
            .collect()
    }
}

/// A graph input.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InputSpec {
    pub name: String,
    pub shape: Vec<SymDim>,
    pub modality: Option<String>,
    pub optional: bool,
    pub value: usize,
}

/// A graph output.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OutputSpec {
    pub name: String,
    pub value: usize,
}

/// A value (tensor) of the schedule.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ValueSpec {
    pub shape: Vec<SymDim>,
    pub storage: Storage,
}

/// Where a value lives.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Storage {
    /// The caller's buffer for input `i`.
    Input(usize),
    /// Activation buffer `s`.
    Slot(usize),
    /// Stored tensor `t` (a `parameter` used as a value).
    Tensor(usize),
}

/// A stored tensor: its name in the container and its shape.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TensorSpec {
    pub name: String,
    pub shape: Vec<usize>,
}

impl TensorSpec {
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }
}

/// A parameter of the model as declared in the spec.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ParamSpec {
    /// PyTorch `state_dict` name.
    pub name: String,
    pub shape: Vec<usize>,
    /// A trainable parameter (`true`) or a buffer such as a running statistic.
    pub trainable: bool,
    /// How it is stored: `tensor <name>`, `folded into <tensor>`, `unused`.
    pub stored_as: String,
    /// Added by an adaptation rule (a LoRA matrix, an adapter weight): zero in the base
    /// model, owned by the variants.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub added: bool,
}

/// One variant: the stored tensors it reads instead of the base's, and its budget.
///
/// A run under the variant reads tensor `with` wherever a step names tensor `base`; every
/// other tensor is the base's. Replacements are ordinary entries of
/// [`Manifest::tensors`] (stored once however many variants share them) and have their
/// base tensor's shape.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct VariantTable {
    /// The variant's key, `fog=0.03` or `missing=lidar`.
    pub key: String,
    pub replaces: Vec<Replacement>,
    /// Elements of existing parameters the variant owns (the paper's "exist budget").
    pub tuned_elements: u64,
    /// Elements of parameters the variant adds: LoRA matrices, adapters ("add budget").
    pub added_elements: u64,
    /// Owned parameters the variant's files did not provide; they keep the base value.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub fallback: Vec<String>,
}

/// A base tensor a variant replaces, and with which.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Replacement {
    pub base: usize,
    pub with: usize,
    /// Derived from parameters the adaptation rules add (LoRA, adapters), rather than
    /// from tuned existing parameters.
    pub added: bool,
}

/// One step of the schedule: a kernel applied to values.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Step {
    /// The node path in the spec, for messages and profiles.
    pub path: String,
    pub kernel: Kernel,
    pub inputs: Vec<usize>,
    pub output: usize,
}

/// A per-channel epilogue read from stored tensors.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EpilogueSpec {
    pub scale: Option<usize>,
    pub shift: Option<usize>,
    pub relu: bool,
    /// Set when `scale` and `shift` are a folded BatchNorm: what re-estimating its
    /// statistics needs ([`crate::calibrate`]). Absent in plans compiled before it was
    /// recorded; never read by a normal run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bn: Option<BnInfo>,
}

/// The BatchNorm a conv or channel-affine epilogue was folded from, so that its running
/// statistics can be re-estimated (AdaBN) from a plan that holds only the folded affine.
///
/// The tensors are the base model's (a variant's own affine is in its `scale`/`shift`
/// replacements); no kernel reads them and no variant may replace them. Each has the
/// epilogue's channel count. Cost: two (three with a conv bias) vectors of `C` floats
/// per BatchNorm, 37.5 KiB for ResNet-18.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BnInfo {
    /// The BatchNorm's path, its PyTorch module name (`layer1.0.bn1`): its statistics are
    /// `<name>.running_mean` and `<name>.running_var`.
    pub name: String,
    pub eps: f64,
    /// Stored tensor of its `weight` (gamma).
    pub weight: usize,
    /// Stored tensor of its `bias` (beta).
    pub bias: usize,
    /// Stored tensor of the conv bias folded into `shift` (conv epilogues only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub conv_bias: Option<usize>,
}

impl BnInfo {
    /// The stored tensors it names.
    pub fn tensors(&self) -> impl Iterator<Item = usize> {
        [self.weight, self.bias].into_iter().chain(self.conv_bias)
    }
}

/// Serialisable names for the kernel enums.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum BinaryKind {
    Add,
    Sub,
    Mul,
    Div,
}

impl From<BinaryKind> for BinaryOp {
    fn from(k: BinaryKind) -> BinaryOp {
        match k {
            BinaryKind::Add => BinaryOp::Add,
            BinaryKind::Sub => BinaryOp::Sub,
            BinaryKind::Mul => BinaryOp::Mul,
            BinaryKind::Div => BinaryOp::Div,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ActKind {
    Relu,
    Gelu,
    GeluTanh,
    Sigmoid,
}

impl From<ActKind> for Act {
    fn from(k: ActKind) -> Act {
        match k {
            ActKind::Relu => Act::Relu,
            ActKind::Gelu => Act::Gelu,
            ActKind::GeluTanh => Act::GeluTanh,
            ActKind::Sigmoid => Act::Sigmoid,
        }
    }
}

/// What a step computes. Sizes that depend on the batch come from the values' shapes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Kernel {
    /// 2-D convolution with a fused per-channel epilogue. `weight` is the packed weight
    /// for `algo` (see `kernels::conv`).
    Conv2d {
        cout: usize,
        kernel: [usize; 2],
        stride: [usize; 2],
        padding: [usize; 2],
        dilation: [usize; 2],
        groups: usize,
        algo: String,
        weight: usize,
        epilogue: EpilogueSpec,
    },
    /// `y = x W^T` over the last axis with a fused epilogue (bias = shift).
    Linear {
        out_features: usize,
        weight: usize,
        epilogue: EpilogueSpec,
    },
    MatMul,
    Binary {
        op: BinaryKind,
    },
    Scalar {
        op: BinaryKind,
        value: f32,
        scalar_first: bool,
    },
    Activation {
        act: ActKind,
    },
    /// Per-channel affine over axis 1 (an unfused BatchNorm, folded to scale and shift).
    ChannelAffine {
        epilogue: EpilogueSpec,
    },
    LayerNorm {
        weight: Option<usize>,
        bias: Option<usize>,
        eps: f32,
    },
    Softmax {
        axis: usize,
    },
    Concat {
        axis: usize,
    },
    /// Same elements, new shape.
    Reshape,
    Permute {
        perm: Vec<usize>,
    },
    Pool {
        max: bool,
        kernel: [usize; 2],
        stride: [usize; 2],
        padding: [usize; 2],
        ceil_mode: bool,
        count_include_pad: bool,
    },
    GlobalAvgPool,
    Upsample {
        bilinear: bool,
        align_corners: bool,
        scale: Option<[f64; 2]>,
    },
    Mean {
        axes: Vec<usize>,
    },
}

impl Kernel {
    /// Short name for listings.
    pub fn name(&self) -> &'static str {
        match self {
            Kernel::Conv2d { .. } => "conv2d",
            Kernel::Linear { .. } => "linear",
            Kernel::MatMul => "matmul",
            Kernel::Binary { .. } => "binary",
            Kernel::Scalar { .. } => "scalar",
            Kernel::Activation { .. } => "activation",
            Kernel::ChannelAffine { .. } => "channel_affine",
            Kernel::LayerNorm { .. } => "layernorm",
            Kernel::Softmax { .. } => "softmax",
            Kernel::Concat { .. } => "concat",
            Kernel::Reshape => "reshape",
            Kernel::Permute { .. } => "permute",
            Kernel::Pool { .. } => "pool",
            Kernel::GlobalAvgPool => "global_avgpool",
            Kernel::Upsample { .. } => "upsample",
            Kernel::Mean { .. } => "mean",
        }
    }

    /// The kernel's per-channel epilogue, if it has one.
    pub fn epilogue(&self) -> Option<&EpilogueSpec> {
        match self {
            Kernel::Conv2d { epilogue, .. } | Kernel::Linear { epilogue, .. } | Kernel::ChannelAffine { epilogue } => {
                Some(epilogue)
            }
            _ => None,
        }
    }

    /// The stored tensors the kernel reads (not those of an epilogue's [`BnInfo`], which
    /// only calibration reads).
    pub fn tensors(&self) -> Vec<usize> {
        let ep = |e: &EpilogueSpec| e.scale.into_iter().chain(e.shift).collect::<Vec<_>>();
        match self {
            Kernel::Conv2d { weight, epilogue, .. } | Kernel::Linear { weight, epilogue, .. } => {
                let mut v = vec![*weight];
                v.extend(ep(epilogue));
                v
            }
            Kernel::ChannelAffine { epilogue } => ep(epilogue),
            Kernel::LayerNorm { weight, bias, .. } => weight.iter().chain(bias).copied().collect(),
            _ => Vec::new(),
        }
    }
}

/// Why a plan could not be loaded or written.
#[derive(Debug)]
pub enum PlanError {
    Io {
        path: String,
        error: std::io::Error,
    },
    /// The file is not a readable safetensors container (truncated, corrupted header).
    Container {
        path: String,
        detail: String,
    },
    /// A safetensors file that is not a readi plan.
    NotAPlan {
        path: String,
        missing: &'static str,
    },
    Version {
        path: String,
        found: String,
    },
    Manifest {
        path: String,
        detail: String,
    },
    Checksum {
        path: String,
        stored: String,
        computed: u32,
    },
    Tensor {
        path: String,
        name: String,
        detail: String,
    },
}

impl fmt::Display for PlanError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PlanError::Io { path, error } => write!(f, "{path}: {error}"),
            PlanError::Container { path, detail } => {
                write!(f, "{path}: not a valid plan file ({detail}); the file may be truncated or corrupted")
            }
            PlanError::NotAPlan { path, missing } => {
                write!(f, "{path}: a safetensors file but not a readi plan (no `{missing}` in its metadata)")
            }
            PlanError::Version { path, found } => write!(
                f,
                "{path}: plan format version {found}, but this readi reads version {FORMAT_VERSION}; recompile the plan"
            ),
            PlanError::Manifest { path, detail } => write!(f, "{path}: invalid plan manifest: {detail}"),
            PlanError::Checksum { path, stored, computed } => {
                write!(f, "{path}: checksum mismatch (stored {stored}, computed {computed:08x}): the file is corrupted")
            }
            PlanError::Tensor { path, name, detail } => write!(f, "{path}: tensor `{name}`: {detail}"),
        }
    }
}

impl std::error::Error for PlanError {}

/// Where the tensor bytes are.
enum Weights {
    /// Straight from the compiler.
    Owned(Vec<Vec<f32>>),
    /// Borrowed from a memory-mapped file: byte range of each tensor.
    Mapped { map: memmap2::Mmap, ranges: Vec<Range<usize>> },
}

/// A compiled model: the manifest and its tensors.
///
/// The variant maps are built from the manifest at construction ([`Plan::new`],
/// [`Plan::load`]); edit a manifest before building a plan from it, not after.
pub struct Plan {
    pub manifest: Manifest,
    weights: Weights,
    variants: VariantMaps,
}

/// Per variant, which stored tensor a step's tensor index resolves to; built once at
/// construction so runs resolve with one array lookup and switching is a key lookup.
#[derive(Default)]
struct VariantMaps {
    /// Key of each variant: [`BASE_VARIANT`], then the tables' keys in manifest order.
    keys: Box<[Box<str>]>,
    /// Variant indices sorted by [`key_order`], for lookups by binary search (no hashing,
    /// no allocation).
    by_key: Box<[u32]>,
    /// `span` entries per variant: entry `t` of row `v` is the tensor variant `v` reads
    /// where a step names tensor `t`. Row 0 (the base) is the identity.
    maps: Box<[u32]>,
    /// One past the highest tensor index a step or a value names (0 in a plan without
    /// variants). Tensors from `span` on are never named by a step, so never replaced;
    /// they resolve to themselves without an entry.
    span: usize,
}

impl VariantMaps {
    /// Builds the maps of a validated manifest.
    fn build(m: &Manifest) -> VariantMaps {
        // Without variants every lookup falls through to the identity: no map at all.
        let span =
            if m.variants.is_empty() { 0 } else { read_tensors(m).iter().rposition(|&r| r).map_or(0, |t| t + 1) };
        let count = m.variants.len() + 1;
        let mut maps: Vec<u32> = Vec::with_capacity(count * span);
        for _ in 0..count {
            // Validation bounds the tensor count by u32::MAX.
            maps.extend((0..span).map(|t| t as u32));
        }
        for (i, v) in m.variants.iter().enumerate() {
            let row = &mut maps[(i + 1) * span..(i + 2) * span];
            for r in &v.replaces {
                // Validation: `base` is read by a step, so below `span`.
                row[r.base] = r.with as u32;
            }
        }
        let keys: Box<[Box<str>]> =
            std::iter::once(BASE_VARIANT).chain(m.variants.iter().map(|v| v.key.as_str())).map(Box::from).collect();
        let mut by_key: Vec<u32> = (0..count as u32).collect();
        by_key.sort_by(|&a, &b| key_order(&keys[a as usize], &keys[b as usize]));
        VariantMaps { keys, by_key: by_key.into(), maps: maps.into(), span }
    }
}

/// The order of the key lookup table: by length, then by bytes, so that most comparisons
/// of a lookup are decided by the lengths.
fn key_order(a: &str, b: &str) -> std::cmp::Ordering {
    a.len().cmp(&b.len()).then_with(|| a.cmp(b))
}

/// The stored tensors as one variant sees them: where a step names tensor `t`, the
/// variant reads [`resolve(t)`](VariantTensors::resolve). Cheap to copy.
#[derive(Clone, Copy)]
pub struct VariantTensors<'a> {
    plan: &'a Plan,
    map: &'a [u32],
    index: usize,
}

impl<'a> VariantTensors<'a> {
    /// The variant's index (0 is the base).
    pub fn index(&self) -> usize {
        self.index
    }

    /// The variant's key.
    pub fn key(&self) -> &'a str {
        &self.plan.variants.keys[self.index]
    }

    /// The stored tensor read where a step names tensor `t`.
    #[inline]
    pub fn resolve(&self, t: usize) -> usize {
        self.map.get(t).map_or(t, |&w| w as usize)
    }

    /// The data read where a step names tensor `t`.
    #[inline]
    pub fn get(&self, t: usize) -> &'a [f32] {
        self.plan.tensor(self.resolve(t))
    }
}

impl fmt::Debug for VariantTensors<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("VariantTensors").field("index", &self.index).field("key", &self.key()).finish()
    }
}

impl fmt::Debug for Plan {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let kind = match self.weights {
            Weights::Owned(_) => "owned",
            Weights::Mapped { .. } => "mapped",
        };
        f.debug_struct("Plan").field("model", &self.manifest.model).field("weights", &kind).finish()
    }
}

impl Plan {
    /// A plan from the compiler: the manifest and one f32 vector per manifest tensor.
    pub fn new(manifest: Manifest, tensors: Vec<Vec<f32>>) -> Result<Plan, PlanError> {
        Plan::build(manifest, Weights::Owned(tensors), "<compiled plan>")
    }

    /// Validates and builds the variant maps.
    fn build(manifest: Manifest, weights: Weights, path: &str) -> Result<Plan, PlanError> {
        let mut plan = Plan { manifest, weights, variants: VariantMaps::default() };
        plan.validate(path)?;
        plan.variants = VariantMaps::build(&plan.manifest);
        Ok(plan)
    }

    /// Number of variants including the base; their indices are `0..variant_count()`.
    pub fn variant_count(&self) -> usize {
        self.variants.keys.len()
    }

    /// The index of the variant with key `key` ([`BASE_VARIANT`] is 0). Allocates nothing.
    pub fn variant_index(&self, key: &str) -> Option<usize> {
        let keys = &self.variants.keys;
        let at = self.variants.by_key.binary_search_by(|&i| key_order(&keys[i as usize], key)).ok()?;
        Some(self.variants.by_key[at] as usize)
    }

    /// The key of variant `i`.
    ///
    /// # Panics
    /// If `i >= self.variant_count()`.
    pub fn variant_key(&self, i: usize) -> &str {
        &self.variants.keys[i]
    }

    /// The keys of all variants, the base first.
    pub fn variant_keys(&self) -> impl ExactSizeIterator<Item = &str> {
        self.variants.keys.iter().map(|k| &**k)
    }

    /// The tensors as variant `i` sees them, or `None` if the plan has no variant `i`.
    pub fn variant_tensors(&self, i: usize) -> Option<VariantTensors<'_>> {
        if i >= self.variant_count() {
            return None;
        }
        let span = self.variants.span;
        let map = self.variants.maps.get(i * span..(i + 1) * span)?;
        Some(VariantTensors { plan: self, map, index: i })
    }

    /// The base model's tensors (variant 0).
    pub fn base_tensors(&self) -> VariantTensors<'_> {
        let span = self.variants.span;
        VariantTensors { plan: self, map: &self.variants.maps[..span], index: 0 }
    }

    /// The data of stored tensor `i`.
    pub fn tensor(&self, i: usize) -> &[f32] {
        match &self.weights {
            Weights::Owned(t) => &t[i],
            // Alignment and length were checked at load.
            Weights::Mapped { map, ranges } => bytemuck::cast_slice(&map[ranges[i].clone()]),
        }
    }

    /// Whether the weights are borrowed from a mapped file.
    pub fn is_mapped(&self) -> bool {
        matches!(self.weights, Weights::Mapped { .. })
    }

    /// Total bytes of the stored tensors.
    pub fn tensor_bytes(&self) -> usize {
        self.manifest.tensors.iter().map(|t| t.numel() * 4).sum()
    }

    fn checksum(manifest_json: &str, tensors: impl Iterator<Item = impl AsRef<[u8]>>) -> u32 {
        let mut h = crc32fast::Hasher::new();
        h.update(manifest_json.as_bytes());
        for t in tensors {
            h.update(t.as_ref());
        }
        h.finalize()
    }

    /// The plan as file bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>, PlanError> {
        let err = |detail: String| PlanError::Manifest { path: "<plan>".into(), detail };
        let json = serde_json::to_string(&self.manifest).map_err(|e| err(e.to_string()))?;
        let data: Vec<&[u8]> = (0..self.manifest.tensors.len()).map(|i| bytemuck::cast_slice(self.tensor(i))).collect();
        let checksum = Plan::checksum(&json, data.iter());
        let mut views = Vec::with_capacity(data.len());
        for (spec, bytes) in self.manifest.tensors.iter().zip(&data) {
            let view = TensorView::new(Dtype::F32, spec.shape.clone(), bytes).map_err(|e| PlanError::Tensor {
                path: "<plan>".into(),
                name: spec.name.clone(),
                detail: e.to_string(),
            })?;
            views.push((spec.name.clone(), view));
        }
        let metadata = HashMap::from([
            (KEY_VERSION.to_string(), FORMAT_VERSION.to_string()),
            (KEY_MANIFEST.to_string(), json),
            (KEY_CHECKSUM.to_string(), format!("{checksum:08x}")),
        ]);
        safetensors::serialize(views, Some(metadata)).map_err(|e| err(e.to_string()))
    }

    /// Writes the plan to a file.
    pub fn write(&self, path: &Path) -> Result<(), PlanError> {
        let bytes = self.to_bytes()?;
        std::fs::write(path, bytes).map_err(|error| PlanError::Io { path: path.display().to_string(), error })
    }

    /// Maps a plan file and checks it. The weights stay in the mapping.
    pub fn load(path: &Path) -> Result<Plan, PlanError> {
        let name = path.display().to_string();
        let file = std::fs::File::open(path).map_err(|error| PlanError::Io { path: name.clone(), error })?;
        let map = map_file(&file).map_err(|error| PlanError::Io { path: name.clone(), error })?;
        Plan::from_map(map, &name)
    }

    fn from_map(map: memmap2::Mmap, path: &str) -> Result<Plan, PlanError> {
        let container =
            |e: safetensors::SafeTensorError| PlanError::Container { path: path.into(), detail: e.to_string() };
        let st = SafeTensors::deserialize(&map).map_err(container)?;
        let (header_len, meta) = SafeTensors::read_metadata(&map).map_err(container)?;
        let md = meta.metadata().clone().unwrap_or_default();
        let get = |key: &'static str| md.get(key).ok_or(PlanError::NotAPlan { path: path.into(), missing: key });
        let version = get(KEY_VERSION)?;
        if version.trim() != FORMAT_VERSION.to_string() {
            return Err(PlanError::Version { path: path.into(), found: version.clone() });
        }
        let json = get(KEY_MANIFEST)?;
        let stored = get(KEY_CHECKSUM)?;
        let manifest: Manifest =
            serde_json::from_str(json).map_err(|e| PlanError::Manifest { path: path.into(), detail: e.to_string() })?;
        if manifest.format_version != FORMAT_VERSION {
            return Err(PlanError::Version { path: path.into(), found: manifest.format_version.to_string() });
        }
        let data_start = 8 + header_len;
        let base = map.as_ptr() as usize;
        let mut ranges = Vec::with_capacity(manifest.tensors.len());
        for spec in &manifest.tensors {
            let terr = |detail: String| PlanError::Tensor { path: path.into(), name: spec.name.clone(), detail };
            let view = st.tensor(&spec.name).map_err(|e| terr(e.to_string()))?;
            if view.dtype() != Dtype::F32 {
                return Err(terr(format!("stored as {:?}, expected F32", view.dtype())));
            }
            if view.shape() != spec.shape.as_slice() {
                return Err(terr(format!(
                    "stored shape {:?} differs from the manifest's {:?}",
                    view.shape(),
                    spec.shape
                )));
            }
            let start = view.data().as_ptr() as usize - base;
            if start < data_start || !(base + start).is_multiple_of(4) {
                return Err(terr("is not 4-byte aligned in the file".into()));
            }
            ranges.push(start..start + view.data().len());
        }
        let computed = Plan::checksum(json, ranges.iter().map(|r| &map[r.clone()]));
        if u32::from_str_radix(stored.trim(), 16).ok() != Some(computed) {
            return Err(PlanError::Checksum { path: path.into(), stored: stored.clone(), computed });
        }
        drop(st);
        Plan::build(manifest, Weights::Mapped { map, ranges }, path)
    }

    /// Checks that every index in the manifest is in range, that the schedule is
    /// well-formed (each value written once, before it is read), and that the variant
    /// tables are usable (see [`Plan::validate_variants`]).
    fn validate(&self, path: &str) -> Result<(), PlanError> {
        let m = &self.manifest;
        let bad = |detail: String| Err(PlanError::Manifest { path: path.into(), detail });
        if let Weights::Owned(t) = &self.weights {
            if t.len() != m.tensors.len() {
                return bad(format!("{} tensors for {} manifest entries", t.len(), m.tensors.len()));
            }
            for (spec, data) in m.tensors.iter().zip(t) {
                if data.len() != spec.numel() {
                    return bad(format!(
                        "tensor `{}` has {} elements, its shape {:?} needs {}",
                        spec.name,
                        data.len(),
                        spec.shape,
                        spec.numel()
                    ));
                }
            }
        }
        let nv = m.values.len();
        let mut written = vec![false; nv];
        for (i, inp) in m.inputs.iter().enumerate() {
            if inp.value >= nv || m.values[inp.value].storage != Storage::Input(i) {
                return bad(format!("input `{}` refers to an invalid value", inp.name));
            }
            for d in &inp.shape {
                if d.coef < 0 || d.syms.iter().any(|s| !m.symbols.contains(s)) {
                    return bad(format!("input `{}` has an invalid dimension {d}", inp.name));
                }
            }
            written[inp.value] = true;
        }
        for (i, v) in m.values.iter().enumerate() {
            match v.storage {
                Storage::Input(k) if k >= m.inputs.len() => return bad(format!("value {i} reads input {k}")),
                Storage::Slot(s) if s >= m.slots => return bad(format!("value {i} uses slot {s} of {}", m.slots)),
                Storage::Tensor(t) if t >= m.tensors.len() => return bad(format!("value {i} reads tensor {t}")),
                Storage::Tensor(_) => written[i] = true,
                _ => {}
            }
            for d in &v.shape {
                if d.coef < 0 || d.syms.iter().any(|s| !m.symbols.contains(s)) {
                    return bad(format!("value {i} has an invalid dimension {d}"));
                }
            }
        }
        for (k, step) in m.steps.iter().enumerate() {
            let at = format!("step {k} (`{}`)", step.path);
            if step.output >= nv || !matches!(m.values[step.output].storage, Storage::Slot(_)) {
                return bad(format!("{at} writes an invalid value"));
            }
            if written[step.output] {
                return bad(format!("{at} writes value {} a second time", step.output));
            }
            for &i in &step.inputs {
                if i >= nv || !written[i] {
                    return bad(format!("{at} reads value {i} before it is written"));
                }
            }
            for t in step.kernel.tensors() {
                if t >= m.tensors.len() {
                    return bad(format!("{at} reads tensor {t} of {}", m.tensors.len()));
                }
            }
            written[step.output] = true;
        }
        for o in &m.outputs {
            if o.value >= nv || !written[o.value] {
                return bad(format!("output `{}` is never computed", o.name));
            }
        }
        Plan::validate_batchnorms(m).map_err(|detail| PlanError::Manifest { path: path.into(), detail })?;
        Plan::validate_variants(m).map_err(|detail| PlanError::Manifest { path: path.into(), detail })
    }

    /// Checks the [`BnInfo`] of every epilogue: only on conv and channel-affine steps with
    /// a scale and a shift (a conv bias on conv steps only); names non-empty and unique;
    /// `eps` finite and not negative; every tensor in range with the scale's shape `[C]`.
    fn validate_batchnorms(m: &Manifest) -> Result<(), String> {
        let mut names: HashSet<&str> = HashSet::new();
        for (k, step) in m.steps.iter().enumerate() {
            let Some(ep) = step.kernel.epilogue() else { continue };
            let Some(bn) = &ep.bn else { continue };
            let at = format!("step {k} (`{}`), BatchNorm `{}`", step.path, bn.name);
            let conv = matches!(step.kernel, Kernel::Conv2d { .. });
            if !conv && !matches!(step.kernel, Kernel::ChannelAffine { .. }) {
                return Err(format!("{at}: only conv2d and channel_affine steps fold a BatchNorm"));
            }
            if bn.conv_bias.is_some() && !conv {
                return Err(format!("{at}: a conv bias on a step without a conv"));
            }
            if bn.name.trim().is_empty() || !names.insert(&bn.name) {
                return Err(format!("{at}: the name is empty or used by another step"));
            }
            if !(bn.eps.is_finite() && bn.eps >= 0.0) {
                return Err(format!("{at}: eps {} is not a finite non-negative number", bn.eps));
            }
            let (Some(scale), Some(_)) = (ep.scale, ep.shift) else {
                return Err(format!("{at}: a folded BatchNorm needs the epilogue's scale and shift"));
            };
            let shape = &m.tensors[scale].shape;
            if shape.len() != 1 {
                return Err(format!("{at}: the scale has shape {shape:?}, not [C]"));
            }
            for t in bn.tensors() {
                match m.tensors.get(t) {
                    None => return Err(format!("{at}: reads tensor {t} of {}", m.tensors.len())),
                    Some(spec) if &spec.shape != shape => {
                        return Err(format!(
                            "{at}: tensor {t} (`{}`) has shape {:?}, the scale {shape:?}",
                            spec.name, spec.shape
                        ));
                    }
                    Some(_) => {}
                }
            }
        }
        Ok(())
    }

    /// Checks the variant tables of a manifest whose schedule is valid: keys non-empty,
    /// unique and not [`BASE_VARIANT`]; every replacement names tensors in range, replaces
    /// a tensor that a step or a value reads, at most once per variant, with a tensor of
    /// exactly its shape (so bind-time checks of the base cover every variant); and the
    /// maps fit [`MAX_MAP_ENTRIES`].
    fn validate_variants(m: &Manifest) -> Result<(), String> {
        let n = m.tensors.len();
        if m.variants.is_empty() {
            return Ok(());
        }
        if u32::try_from(n).is_err() {
            return Err(format!("{n} tensors; variant plans hold at most {}", u32::MAX));
        }
        let read = read_tensors(m);
        let span = read.iter().rposition(|&r| r).map_or(0, |t| t + 1);
        if (m.variants.len() + 1).saturating_mul(span) > MAX_MAP_ENTRIES {
            return Err(format!(
                "{} variants over {span} tensors exceed the limit of {MAX_MAP_ENTRIES} variant map entries",
                m.variants.len()
            ));
        }
        let name = |t: usize| &m.tensors[t].name;
        let mut keys: HashSet<&str> = HashSet::with_capacity(m.variants.len());
        let mut replaced = vec![usize::MAX; n];
        for (i, v) in m.variants.iter().enumerate() {
            if v.key.trim().is_empty() {
                return Err(format!("variant {i} has an empty key"));
            }
            let at = format!("variant `{}`", v.key);
            if v.key == BASE_VARIANT {
                return Err(format!("{at}: the key `{BASE_VARIANT}` is reserved for the base model"));
            }
            if !keys.insert(&v.key) {
                return Err(format!("{at}: the key is used by two variants"));
            }
            for r in &v.replaces {
                if r.base >= n || r.with >= n {
                    return Err(format!("{at} replaces tensor {} with tensor {}, of {n} tensors", r.base, r.with));
                }
                if !read[r.base] {
                    return Err(format!("{at} replaces tensor {} (`{}`), which no step reads", r.base, name(r.base)));
                }
                let (base, with) = (&m.tensors[r.base].shape, &m.tensors[r.with].shape);
                if base != with {
                    return Err(format!(
                        "{at} replaces tensor {} (`{}`, shape {base:?}) with tensor {} (`{}`, shape {with:?}); \
                         a replacement must have its base tensor's shape",
                        r.base,
                        name(r.base),
                        r.with,
                        name(r.with)
                    ));
                }
                if std::mem::replace(&mut replaced[r.base], i) == i {
                    return Err(format!("{at} replaces tensor {} (`{}`) twice", r.base, name(r.base)));
                }
            }
        }
        Ok(())
    }
}

/// Which stored tensors the schedule names: read by a step's kernel or stored as a value.
/// Indices out of range are skipped (validation reports them).
fn read_tensors(m: &Manifest) -> Vec<bool> {
    let mut read = vec![false; m.tensors.len()];
    let named = m.steps.iter().flat_map(|s| s.kernel.tensors());
    let values = m.values.iter().filter_map(|v| match v.storage {
        Storage::Tensor(t) => Some(t),
        _ => None,
    });
    for t in named.chain(values) {
        if let Some(r) = read.get_mut(t) {
            *r = true;
        }
    }
    read
}

/// Maps a file read-only.
#[allow(unsafe_code)]
fn map_file(file: &std::fs::File) -> std::io::Result<memmap2::Mmap> {
    // SAFETY: the mapping is read-only and private to this process. Another process
    // truncating or rewriting the file while it is mapped is outside what readi can
    // prevent (as for any mmap-based loader); plans are written once and not modified.
    unsafe { memmap2::Mmap::map(file) }
}
