//! The plan format: everything a plan file holds besides the tensor bytes.
//!
//! A plan is a [safetensors] file whose tensors are the stored weights (f32, each stored
//! once) and whose metadata holds the [`Manifest`] as JSON: inputs, outputs, the schedule
//! of [`Step`]s, every value's shape, the buffer plan, the stored tensors, the model's
//! parameter table, the variant tables and the conditions. The runtime's `plan` module
//! reads and writes the container; [`crate::validate`] checks a manifest before anything
//! runs it.
//!
//! Each [`Kernel`] holds its operator's attributes as [`crate::ops`] defines them, so the
//! runtime checks a plan's shapes with the same rules the compiler inferred them with.
//!
//! [safetensors]: https://huggingface.co/docs/safetensors

use std::borrow::Cow;
use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use crate::conditions::Conditions;
use crate::dim::Dim;
use crate::key::{KeyPart, VariantKey};
use crate::ops::{
    Activation, ChannelAffine, Conv2d, Conv3d, ConvAlgo, ConvTranspose2d, DType, GroupNorm, LayerNorm, Linear,
    Operator, Pure,
};

/// Version of the plan format this crate describes. Version 2: kernels hold their
/// operators' attributes (`readi_plan::ops`), dimensions are one type, keys are checked.
/// Version 3: an epilogue's activation is any [`Activation`] (`act`), not a `relu` flag;
/// a runtime that reads only version 2 refuses these plans instead of ignoring `act`.
/// Version 4: new kernels and operators (`ConvTranspose2d`, `GroupNorm`, the reductions as
/// `Reduce` with a kind, adaptive pooling, pixel shuffle, pad, roll, slice, expand); a
/// runtime that reads only version 3 refuses these plans by their version, not by an
/// unknown variant deep in the manifest.
/// Version 5: `Conv3d`, `index_select` with its indices in the step, `where`, casts,
/// comparisons and constant fills; for the same reason. Versions 2 to 4 read unchanged.
/// Version 6: a linear weight may be stored in panels (`Kernel::Linear { panels }`),
/// which a version 5 runtime would read as `[in, out]`; versions 2 to 5 read unchanged.
/// Version 7: a reshape may share its input's buffer ([`Step::is_view`]), which a version
/// 6 runtime refuses as a step reading the buffer it writes; run-time index operators
/// (`argmax` / `argmin`, `topk`, `gather` / `take_along_dim`, `index_select` at a computed
/// index, `one_hot`, `where` with a number; `maximum`, `minimum`, `floor_divide`,
/// `remainder`, `atan2` as binary ops); an output's element type (`OutputSpec::dtype`,
/// f32 when absent); `lss_bev_pool`. Versions 2 to 6 read unchanged.
/// Version 8: the lidar front end (`Voxelize` with its output, `LidarDepthMap`) and the
/// sparse 3-D conv (`SparseOutCoords`, `SparseConv3d`, `SparseToDense`), which a version 7
/// runtime would refuse as unknown variants deep in the manifest. Versions 2 to 7 read
/// unchanged.
/// Version 9: a conv may add a residual input in its epilogue (`Kernel::Conv2d {
/// residual }`, the step's second input), which a version 8 runtime would ignore, computing
/// the conv without the add. Versions 2 to 8 read unchanged.
/// Version 10: a conv may scale its input's channels per image (`Kernel::Conv2d {
/// channel_scale }`, a squeeze-and-excitation's multiply, the step's last input), which a
/// version 9 runtime would ignore. Versions 2 to 9 read unchanged.
pub const FORMAT_VERSION: u32 = 10;

/// The oldest plan format version this crate still reads: version 2 plans differ only in
/// writing an epilogue's activation as `"relu": bool`, which [`EpilogueSpec`] accepts.
pub const OLDEST_FORMAT_VERSION: u32 = 2;

/// The key of variant 0, the base model; no variant table may use it.
pub const BASE_VARIANT: &str = crate::key::BASE_KEY;

/// A name read from a plan (an input, output, step path, tensor, BatchNorm or axis name),
/// as messages and listings print it: characters that do not print (control characters
/// such as the terminal escape `\x1b`, line breaks, Unicode format characters) are written
/// as Rust's `escape_debug` writes them (`\u{1b}`, `\n`), and a backslash is doubled, so
/// a hostile plan cannot drive the terminal and an escaped name reads unambiguously.
/// Ordinary names come back as they are, without a copy.
///
/// Every place that prints a plan-provided name goes through this function.
pub fn escaped(name: &str) -> Cow<'_, str> {
    // Quotes print as themselves; `escape_debug` would add a backslash.
    let plain = |c: char| c == '"' || c == '\'' || (c != '\\' && c.escape_debug().len() == 1);
    if name.chars().all(plain) {
        return Cow::Borrowed(name);
    }
    let mut out = String::with_capacity(name.len() + 8);
    for c in name.chars() {
        if plain(c) {
            out.push(c);
        } else {
            out.extend(c.escape_debug());
        }
    }
    Cow::Owned(out)
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
    pub conditions: Option<Conditions>,
    /// The memory a run takes at the compiled batch size, as the plan writer computed it;
    /// `None` in plans written before it was recorded (they load as before: the field is
    /// optional, so the format version did not change). For listings only: the runtime
    /// computes the footprint of every binding itself and never trusts this one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub footprint: Option<PlanFootprint>,
}

/// [`Manifest::footprint`]: bytes a run takes with every symbol bound to `batch`, on one
/// thread.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PlanFootprint {
    pub batch: u64,
    /// The activation buffers.
    pub activations: u64,
    /// The conv kernels' scratch on one thread.
    pub scratch: u64,
    /// Everything a run takes: buffers, scratch, the session's packed LoRA `A`s and the
    /// working copies of convs merged on switch, zeros for absent optional inputs, the
    /// inputs and the outputs.
    pub total: u64,
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
    pub shape: Vec<Dim>,
    pub modality: Option<String>,
    pub optional: bool,
    pub value: usize,
}

/// A graph output.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OutputSpec {
    pub name: String,
    pub value: usize,
    /// The element type the model gives it: its values are f32 either way, integers for
    /// i64 and 0 or 1 for bool, which `readi run` prints and writes as such. Absent (in
    /// plans before version 7, and for f32): f32.
    #[serde(default = "f32_dtype", skip_serializing_if = "is_f32")]
    pub dtype: DType,
}

impl OutputSpec {
    /// An f32 output.
    pub fn f32(name: impl Into<String>, value: usize) -> OutputSpec {
        OutputSpec { name: name.into(), value, dtype: DType::F32 }
    }
}

fn f32_dtype() -> DType {
    DType::F32
}

fn is_f32(d: &DType) -> bool {
    *d == DType::F32
}

/// A value (tensor) of the schedule.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ValueSpec {
    pub shape: Vec<Dim>,
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

/// A stored tensor: its name in the container, its shape and its element type.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TensorSpec {
    pub name: String,
    pub shape: Vec<usize>,
    /// `F32`, or `F16` for a variant's replacement stored at half precision (`readi
    /// compile --variant-f16`): only a [`Replacement::with`] may be, never a tensor a
    /// step, a value or a BatchNorm record names (validation), so the base model is
    /// always f32 and a session decodes the active variant's f16 tensors into f32 working
    /// copies when the variant changes.
    #[serde(default = "f32_dtype", skip_serializing_if = "is_f32")]
    pub dtype: DType,
}

impl TensorSpec {
    /// An f32 tensor.
    pub fn f32(name: impl Into<String>, shape: Vec<usize>) -> TensorSpec {
        TensorSpec { name: name.into(), shape, dtype: DType::F32 }
    }

    /// Bytes of the stored data: 4 per element, 2 for an f16 tensor (saturating).
    pub fn bytes(&self) -> usize {
        let size = if self.dtype == DType::F16 { 2 } else { 4 };
        self.numel().saturating_mul(size)
    }

    /// Elements of the shape; saturates at `usize::MAX` (which no stored tensor has, so a
    /// manifest declaring such a shape is refused when its data is compared).
    pub fn numel(&self) -> usize {
        self.shape.iter().fold(1usize, |a, &d| a.saturating_mul(d))
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
    /// The variants that own it (AdaBN writes only what a variant owns): `None` when no
    /// variant owns it, and in plans compiled before ownership was recorded (a plan
    /// records it when some parameter has `Some`, [`Manifest::records_ownership`]);
    /// `Some([])` for every variant (an unscoped `adapt` section); otherwise the scope
    /// names of the sections that own it, as written (`camera`, `fog`, `missing`,
    /// `missing=lidar`), read against the plan's conditions by [`ParamSpec::is_owned_by`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub owned_by: Option<Vec<String>>,
}

impl ParamSpec {
    /// Whether the variant `key` owns this parameter, declared in the plan or not (a meld:
    /// whether one of its parts does; the base owns nothing). A scope name covers the
    /// level variants of the axis of that name and of the axes on the modality of that
    /// name; `missing=M` covers the variant missing `M`, `missing` every missing variant.
    pub fn is_owned_by(&self, key: &VariantKey, conditions: Option<&Conditions>) -> bool {
        let Some(scopes) = &self.owned_by else { return false };
        if key.is_base() {
            return false;
        }
        if scopes.is_empty() {
            return true;
        }
        scopes.iter().any(|s| scope_covers(s, key, conditions))
    }
}

/// Whether the scope name `scope` (as [`ParamSpec::owned_by`] records it) covers the
/// variant `key`: one of its parts is a level of the axis `scope` or of an axis on the
/// modality `scope`, or `scope` is `missing=M` and the part is missing `M`, or `scope` is
/// `missing` and the part is missing some modality.
pub fn scope_covers(scope: &str, key: &VariantKey, conditions: Option<&Conditions>) -> bool {
    let axes = conditions.map(|c| c.axes.as_slice()).unwrap_or_default();
    key.parts().iter().any(|part| match (part, scope.split_once('=')) {
        (KeyPart::Missing { .. }, None) => scope == crate::key::MISSING_AXIS,
        (KeyPart::Missing { modality }, Some((axis, m))) => axis == crate::key::MISSING_AXIS && m == modality,
        (KeyPart::Level { axis, .. }, None) => {
            axis == scope || axes.iter().any(|a| &a.name == axis && a.modality == scope)
        }
        (KeyPart::Level { .. }, Some(_)) => false,
    })
}

impl Manifest {
    /// Whether the plan records which variants own each parameter ([`ParamSpec::owned_by`]):
    /// some parameter is owned. Plans compiled before it was recorded, and plans whose
    /// variants own nothing, do not.
    pub fn records_ownership(&self) -> bool {
        self.params.iter().any(|p| p.owned_by.is_some())
    }
}

/// One variant: the stored tensors it reads instead of the base's, and its budget.
///
/// A run under the variant reads tensor `with` wherever a step names tensor `base`; every
/// other tensor is the base's. Replacements are ordinary entries of
/// [`Manifest::tensors`] (stored once however many variants share them) and have their
/// base tensor's shape.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VariantTable {
    /// The variant's key, `fog=0.03` or `missing=lidar`.
    pub key: VariantKey,
    pub replaces: Vec<Replacement>,
    /// Elements of existing parameters the variant owns (the paper's "exist budget").
    pub tuned_elements: u64,
    /// Elements of parameters the variant adds: LoRA matrices, adapters ("add budget").
    pub added_elements: u64,
    /// Owned parameters the variant's files did not provide; they keep the base value.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub fallback: Vec<String>,
    /// The scoped `adapt` sections whose parameters it owns (`camera`, `missing=lidar`);
    /// empty when it owns only the unscoped rules' (and in plans compiled before scopes).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub scopes: Vec<String>,
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

impl Step {
    /// Whether the step is a view: a reshape whose output shares its input's activation
    /// buffer. Its data are already in place, so it runs as nothing (`reshape`,
    /// `flatten`, `squeeze`, `unsqueeze`, `view` cost no copy); `plan_buffers` makes
    /// them, keeping the buffer live until the last reader of any of its views.
    pub fn is_view(&self, values: &[ValueSpec]) -> bool {
        let storage = |v: usize| values.get(v).map(|v| v.storage);
        matches!(self.kernel, Kernel::Pure(crate::ops::Pure::Reshape(_)))
            && self.inputs.len() == 1
            && matches!(storage(self.output), Some(Storage::Slot(_)))
            && storage(self.inputs[0]) == storage(self.output)
    }
}

/// A per-channel epilogue read from stored tensors: `act(acc * scale[c] + shift[c])`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(from = "EpilogueSpecRepr")]
pub struct EpilogueSpec {
    pub scale: Option<usize>,
    pub shift: Option<usize>,
    /// The activation applied last, if any (format version 2 wrote `"relu": bool`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub act: Option<Activation>,
    /// Set when `scale` and `shift` are a folded BatchNorm: what re-estimating its
    /// statistics needs ([`crate::calibrate`]). Absent in plans compiled before it was
    /// recorded; never read by a normal run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bn: Option<BnInfo>,
}

/// [`EpilogueSpec`] as plans of format versions 2 and 3 write it.
#[derive(Deserialize)]
struct EpilogueSpecRepr {
    scale: Option<usize>,
    shift: Option<usize>,
    #[serde(default)]
    act: Option<Activation>,
    /// Version 2's activation flag.
    #[serde(default)]
    relu: bool,
    #[serde(default)]
    bn: Option<BnInfo>,
}

impl From<EpilogueSpecRepr> for EpilogueSpec {
    fn from(r: EpilogueSpecRepr) -> EpilogueSpec {
        let act = r.act.or(r.relu.then_some(Activation::Relu));
        EpilogueSpec { scale: r.scale, shift: r.shift, act, bn: r.bn }
    }
}

/// Most rank a [`LoraSpec`] may have (PEFT's ranks are 4 to 64).
pub const MAX_LORA_RANK: usize = 4096;

/// A LoRA branch `B (A x)` fused into a conv or linear kernel: its accumulator gets the
/// branch before the epilogue (so a folded BatchNorm scales both alike).
///
/// * conv: `a` is `A` (`[rank, cin, kh, kw]`, a conv of the layer's geometry to `rank`
///   channels) packed for the conv's algorithm at `rank` output channels, or, when
///   `a_raw`, as PyTorch has it (`rank · cin · kh · kw` values), which the runtime packs
///   for the algorithm into a session-owned buffer when a run's variant differs from the
///   one packed last (a Winograd `A` is 16/9 or 36/9 of its raw size); `b` is `B`,
///   `[cout, rank]`;
/// * linear: `a` is `[rank, in]`, `b` is `[out, rank]`.
///
/// `b` has the LoRA scale (`alpha / rank`) multiplied in. Only these two tensors vary
/// between the variants of a LoRA layer; the conv's weight is the base model's. Conv
/// branches need one group and an algorithm other than the depthwise loop.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct LoraSpec {
    /// Stored tensor of `A`, packed.
    pub a: usize,
    /// Stored tensor of the scaled `B`.
    pub b: usize,
    pub rank: usize,
    /// A conv's `a` is stored raw and packed by the runtime (absent: packed, the plans
    /// compiled before it; always absent for a linear).
    #[serde(default, skip_serializing_if = "is_false")]
    pub a_raw: bool,
}

fn is_false(b: &bool) -> bool {
    !*b
}

/// A residual bottleneck adapter fused into the conv that produces its input
/// (`fuse_adapters`): on the conv's output after the epilogue's scale and shift,
/// `y + up(act(down y + down_bias)) + up_bias`, then the epilogue's ReLU if any. `down` is
/// `[mid, cout]` (a 1x1 conv's weight `[mid, cout, 1, 1]`), `up` `[cout, mid]`, the biases
/// `[mid]` and `[cout]`; all four are the adapter's own tensors, which a variant replaces
/// through its table as it replaces a LoRA branch's. The kernel computes it per chunk of
/// output pixels while the chunk is in cache.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdapterSpec {
    /// Stored tensor of the down-projection's weight, `[mid, cout]`.
    pub down: usize,
    /// Stored tensor of its bias, `[mid]`.
    pub down_bias: usize,
    /// Stored tensor of the up-projection's weight, `[cout, mid]`.
    pub up: usize,
    /// Stored tensor of its bias, `[cout]`.
    pub up_bias: usize,
    /// The bottleneck's channels, `cout / squeeze`.
    pub mid: usize,
    /// The activation between the projections.
    pub act: Activation,
}

impl AdapterSpec {
    /// The stored tensors it reads.
    pub fn tensors(&self) -> [usize; 4] {
        [self.down, self.down_bias, self.up, self.up_bias]
    }
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

/// What a step computes. Sizes that depend on the batch come from the values' shapes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Kernel {
    /// 2-D convolution with a fused per-channel epilogue. `weight` is the packed weight
    /// for `algo` (see `readi_runtime::kernels::conv`), or raw when `switch`.
    Conv2d {
        conv: Conv2d,
        algo: ConvAlgo,
        weight: usize,
        epilogue: EpilogueSpec,
        /// A LoRA branch computed in the same kernel, added before the epilogue. Absent
        /// in plans without one (and in those written before it existed).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        lora: Option<LoraSpec>,
        /// **Merge on switch**: `weight` is stored raw (PyTorch's `[cout, cin/groups, kh,
        /// kw]`, for the base and each variant that owns it), and the session packs it
        /// for `algo`, with the LoRA update `B A` merged in when `lora` is set (whose `A`
        /// is then raw), into one working copy of its own when a run's variant differs
        /// from the one the copy holds; the kernel runs that copy as a plain conv (no
        /// branch). The stored weights are never modified. Absent: `weight` is packed.
        #[serde(default, skip_serializing_if = "is_false")]
        switch: bool,
        /// A residual adapter on the output, between the epilogue's shift and its ReLU.
        /// Absent in plans without one (and in those written before it existed).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        adapter: Option<AdapterSpec>,
        /// The step's second input, of the output's shape, is added after the epilogue's
        /// scale and shift (and after a fused adapter), before its activation: a residual
        /// connection `act(bn(conv(x)) + r)` in one pass over the output. Absent: one input.
        #[serde(default, skip_serializing_if = "is_false")]
        residual: bool,
        /// The step's last input, `[N, in, 1, 1]`, scales each image's input channels
        /// before the conv, `conv(x · s)`: a squeeze-and-excitation's multiply, computed
        /// as the conv with its weight's input channels scaled per image. Only with an
        /// algorithm that stores the weight as PyTorch's ([`ConvAlgo::packs_as_is`]) and
        /// no LoRA branch. Absent: no scale.
        #[serde(default, skip_serializing_if = "is_false")]
        channel_scale: bool,
    },
    /// Transposed 2-D convolution with a fused per-channel epilogue (bias = shift).
    /// `weight` is PyTorch's `[in, out/groups, kh, kw]`, as it is.
    ConvTranspose2d {
        conv: ConvTranspose2d,
        weight: usize,
        epilogue: EpilogueSpec,
    },
    /// 3-D convolution over NCDHW with a fused per-channel epilogue (bias = shift).
    /// `weight` is PyTorch's `[out, in/groups, kd, kh, kw]`, as it is.
    Conv3d {
        conv: Conv3d,
        weight: usize,
        epilogue: EpilogueSpec,
    },
    /// `y = x W^T` over the last axis with a fused epilogue (bias = shift). The weight is
    /// stored transposed, `[in, out]`, or in panels.
    Linear {
        linear: Linear,
        weight: usize,
        epilogue: EpilogueSpec,
        /// As for [`Kernel::Conv2d`].
        #[serde(default, skip_serializing_if = "Option::is_none")]
        lora: Option<LoraSpec>,
        /// The weight is stored in panels of [`PANEL`](crate::ops::PANEL) output columns,
        /// `[ceil(out / PANEL)][in][PANEL]`, zero past `out` ([`Linear::panel_len`]
        /// values), the layout the runtime's register-blocked product reads. Absent: `[in,
        /// out]`.
        #[serde(default, skip_serializing_if = "is_false")]
        panels: bool,
    },
    /// Per-channel affine over axis 1 (an unfused BatchNorm, folded to scale and shift).
    ChannelAffine {
        affine: ChannelAffine,
        epilogue: EpilogueSpec,
    },
    LayerNorm {
        norm: LayerNorm,
        weight: Option<usize>,
        bias: Option<usize>,
    },
    /// Group normalisation over axis 1; `weight` and `bias` (`[num_channels]`) when affine.
    GroupNorm {
        norm: GroupNorm,
        weight: Option<usize>,
        bias: Option<usize>,
    },
    /// An operator without stored tensors, as the IR holds it.
    Pure(Pure),
}

impl Kernel {
    /// The operator the step computes: its name, attributes and shape rule.
    pub fn op(&self) -> &dyn Operator {
        match self {
            Kernel::Conv2d { conv, .. } => conv,
            Kernel::ConvTranspose2d { conv, .. } => conv,
            Kernel::Conv3d { conv, .. } => conv,
            Kernel::Linear { linear, .. } => linear,
            Kernel::ChannelAffine { affine, .. } => affine,
            Kernel::LayerNorm { norm, .. } => norm,
            Kernel::GroupNorm { norm, .. } => norm,
            Kernel::Pure(p) => p.op(),
        }
    }

    /// Short name for listings.
    pub fn name(&self) -> &'static str {
        match self {
            Kernel::Pure(Pure::Binary(_)) => "binary",
            Kernel::Pure(Pure::Scalar(_)) => "scalar",
            Kernel::Pure(Pure::Activation(_)) => "activation",
            Kernel::Pure(Pure::Pool(_)) => "pool",
            k => k.op().kind_name(),
        }
    }

    /// The multiply-adds of one run of the kernel at these concrete shapes: its
    /// operator's ([`Operator::multiply_adds`]) plus a fused LoRA branch's (`A` at the
    /// layer's geometry to `rank` channels, then `B` back) and a fused adapter's (down to
    /// `mid` channels and up again, per output pixel).
    pub fn multiply_adds(&self, inputs: &[&[usize]], output: &[usize]) -> u64 {
        let op = self.op().multiply_adds(inputs, output);
        let elements = crate::ops::count(output);
        let (per_output, outputs) = match self {
            Kernel::Conv2d { conv, .. } => {
                let [cout, cin_g, kh, kw] = conv.weight_shape().map(|d| d.max(1) as u64);
                (cin_g * kh * kw, cout)
            }
            Kernel::Linear { linear, .. } => (linear.in_features.max(1) as u64, linear.out_features.max(1) as u64),
            _ => return op,
        };
        // Per output position (pixel or row): `rank x per_output` for `A`, `outputs x rank`
        // for `B`; `2 x mid x outputs` for an adapter.
        let positions = elements / outputs;
        let lora = self.lora().map_or(0, |l| l.rank as u64 * (per_output + outputs));
        let adapter = self.adapter().map_or(0, |a| 2 * a.mid as u64 * outputs);
        op.saturating_add(positions.saturating_mul(lora + adapter))
    }

    /// The kernel's fused LoRA branch, if it has one.
    pub fn lora(&self) -> Option<&LoraSpec> {
        match self {
            Kernel::Conv2d { lora, .. } | Kernel::Linear { lora, .. } => lora.as_ref(),
            _ => None,
        }
    }

    /// The conv kernel's fused adapter, if it has one.
    pub fn adapter(&self) -> Option<&AdapterSpec> {
        match self {
            Kernel::Conv2d { adapter, .. } => adapter.as_ref(),
            _ => None,
        }
    }

    /// The kernel's per-channel epilogue, if it has one.
    pub fn epilogue(&self) -> Option<&EpilogueSpec> {
        match self {
            Kernel::Conv2d { epilogue, .. }
            | Kernel::ConvTranspose2d { epilogue, .. }
            | Kernel::Conv3d { epilogue, .. }
            | Kernel::Linear { epilogue, .. }
            | Kernel::ChannelAffine { epilogue, .. } => Some(epilogue),
            _ => None,
        }
    }

    /// The stored tensors the kernel reads (not those of an epilogue's [`BnInfo`], which
    /// only calibration reads).
    pub fn tensors(&self) -> Vec<usize> {
        let ep = |e: &EpilogueSpec| e.scale.into_iter().chain(e.shift).collect::<Vec<_>>();
        match self {
            Kernel::Conv2d { weight, epilogue, lora, .. } | Kernel::Linear { weight, epilogue, lora, .. } => {
                let mut v = vec![*weight];
                v.extend(lora.iter().flat_map(|l| [l.a, l.b]));
                v.extend(ep(epilogue));
                v.extend(self.adapter().iter().flat_map(|a| a.tensors()));
                v
            }
            Kernel::ConvTranspose2d { weight, epilogue, .. } | Kernel::Conv3d { weight, epilogue, .. } => {
                let mut v = vec![*weight];
                v.extend(ep(epilogue));
                v
            }
            Kernel::ChannelAffine { epilogue, .. } => ep(epilogue),
            Kernel::LayerNorm { weight, bias, .. } | Kernel::GroupNorm { weight, bias, .. } => {
                weight.iter().chain(bias).copied().collect()
            }
            Kernel::Pure(_) => Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_that_do_not_print_are_escaped() {
        assert!(matches!(escaped("layer1.0.conv1 (+bn1, relu#0)"), Cow::Borrowed(_)));
        assert_eq!(escaped("it's \"x\""), "it's \"x\"");
        assert_eq!(escaped("a\u{1b}[2Jb"), "a\\u{1b}[2Jb");
        assert_eq!(escaped("two\nlines\r\t"), "two\\nlines\\r\\t");
        assert_eq!(escaped("back\\slash"), "back\\\\slash");
        // A right-to-left override (a format character) and a bell.
        assert_eq!(escaped("x\u{202e}y\u{7}"), "x\\u{202e}y\\u{7}");
        assert_eq!(escaped("Grüße, 画像"), "Grüße, 画像");
    }

    #[test]
    fn epilogues_of_version_2_and_3_read_alike() {
        let v2: EpilogueSpec = serde_json::from_str(r#"{"scale":null,"shift":3,"relu":true}"#).expect("v2");
        assert_eq!(v2, EpilogueSpec { shift: Some(3), act: Some(Activation::Relu), ..EpilogueSpec::default() });
        let none: EpilogueSpec = serde_json::from_str(r#"{"scale":1,"shift":null,"relu":false}"#).expect("v2");
        assert_eq!(none.act, None);
        let act = Some(Activation::Clamp { min: Some(0.0), max: Some(6.0) });
        let v3 = EpilogueSpec { scale: Some(1), shift: Some(2), act, bn: None };
        let json = serde_json::to_string(&v3).expect("write");
        assert!(!json.contains("relu"), "{json}");
        assert_eq!(serde_json::from_str::<EpilogueSpec>(&json).expect("read"), v3);
    }

    // A 3x3 conv 4->6 on 5x5 outputs: 150 outputs x 36 products; per pixel (25) a rank-2
    // LoRA adds 2 x 36 (A) + 6 x 2 (B), an adapter to 3 channels 2 x 3 x 6. By hand.
    #[test]
    fn a_conv_s_multiply_adds_include_its_lora_and_adapter() {
        use crate::ops::{Conv2d, ConvAlgo, Window2};
        let window = Window2 { kernel: [3, 3], stride: [1, 1], padding: [1, 1], dilation: [1, 1] };
        let conv = Conv2d { in_channels: 4, out_channels: 6, window, groups: 1 };
        let plain = Kernel::Conv2d {
            conv,
            algo: ConvAlgo::Im2col,
            weight: 0,
            epilogue: EpilogueSpec::default(),
            lora: None,
            switch: false,
            adapter: None,
            residual: false,
            channel_scale: false,
        };
        let (x, y): (&[usize], &[usize]) = (&[1, 4, 5, 5], &[1, 6, 5, 5]);
        assert_eq!(plain.multiply_adds(&[x], y), 150 * 36);
        let Kernel::Conv2d { conv, algo, weight, epilogue, .. } = plain else { unreachable!() };
        let lora = Some(LoraSpec { a: 1, b: 2, rank: 2, a_raw: false });
        let adapter = Some(AdapterSpec { down: 3, down_bias: 4, up: 5, up_bias: 6, mid: 3, act: Activation::Relu });
        let both = Kernel::Conv2d {
            conv,
            algo,
            weight,
            epilogue,
            lora,
            switch: false,
            adapter,
            residual: false,
            channel_scale: false,
        };
        assert_eq!(both.multiply_adds(&[x], y), 150 * 36 + 25 * (2 * 36 + 6 * 2) + 25 * (2 * 3 * 6));
    }
}
