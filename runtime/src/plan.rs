//! The plan file: what the compiler emits and the runtime maps into memory.
//!
//! A plan is a [safetensors] file. Its tensors are the stored weights (f32, each stored
//! once); its metadata holds three keys:
//!
//! * `readi.format_version`: [`FORMAT_VERSION`], checked first;
//! * `readi.manifest`: the [`Manifest`] as JSON: inputs, outputs, the schedule of steps,
//!   every value's shape, the buffer plan, the stored tensors and the model's parameter
//!   table, and per-variant tables (empty in this version);
//! * `readi.checksum`: CRC-32 of the manifest text followed by every tensor's bytes in
//!   manifest order, so a flipped bit anywhere is caught at load.
//!
//! Any safetensors tool can list a plan's tensors. Loading maps the file and borrows the
//! weight bytes in place: nothing proportional to the weights is copied, at load or later.
//! Plans are untrusted input: [`Plan::load`] checks the container, the version, the
//! checksum and every index in the manifest, and reports a [`PlanError`] naming what is
//! wrong; shapes are checked again when a batch size is bound.
//!
//! [safetensors]: https://huggingface.co/docs/safetensors

use std::collections::HashMap;
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
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct EpilogueSpec {
    pub scale: Option<usize>,
    pub shift: Option<usize>,
    pub relu: bool,
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

    /// The stored tensors the kernel reads.
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
pub struct Plan {
    pub manifest: Manifest,
    weights: Weights,
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
        let plan = Plan { manifest, weights: Weights::Owned(tensors) };
        plan.validate("<compiled plan>")?;
        Ok(plan)
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
        let plan = Plan { manifest, weights: Weights::Mapped { map, ranges } };
        plan.validate(path)?;
        Ok(plan)
    }

    /// Checks that every index in the manifest is in range and that the schedule is
    /// well-formed: each value written once, before it is read.
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
        for v in &m.variants {
            for r in &v.replaces {
                if r.base >= m.tensors.len() || r.with >= m.tensors.len() {
                    return bad(format!(
                        "variant `{}` replaces tensor {} with {} of {}",
                        v.key,
                        r.base,
                        r.with,
                        m.tensors.len()
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Maps a file read-only.
#[allow(unsafe_code)]
fn map_file(file: &std::fs::File) -> std::io::Result<memmap2::Mmap> {
    // SAFETY: the mapping is read-only and private to this process. Another process
    // truncating or rewriting the file while it is mapped is outside what readi can
    // prevent (as for any mmap-based loader); plans are written once and not modified.
    unsafe { memmap2::Mmap::map(file) }
}
